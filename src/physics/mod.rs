//! Physically grounded lidar simulation: link budget, detector chain, noise,
//! digitiser, and the scene simulator that turns a scene's `[simulation]`
//! section into frames with ground truth.
//!
//! The `[simulation]` scene section it reads (serde, validated) lives in
//! [`crate::scene::simulation`], so the scene layer never depends on physics.
//!
//! Layout (one concern per file):
//! - [`link_budget`]: received power, currents, voltages, noise, SNR.
//! - [`photodetector`]: state-space models of the APD/TIA receiver chain, discretised exactly.
//! - [`noise_source`]: coloured/skewed noise with a shot-noise envelope; the mains burst; interference events.
//! - [`digitiser`]: quantisation to codes, clipping, jittered sampling.
//! - [`simulator`]: [`Simulator`], [`Truth`].
//!
//! Plain synchronous Rust: no I/O, no async.

pub mod digitiser;
pub mod link_budget;
pub mod noise_source;
pub mod photodetector;
pub mod simulator;

pub use crate::scene::simulation::{SimulationConfig, SimulationError};
pub use link_budget::LinkBudgetLine;
pub use simulator::{Simulator, TrueEvent, TrueReturn, Truth};
