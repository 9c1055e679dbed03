//! Physically grounded lidar simulation: link budget, detector chain, noise,
//! digitiser, and the scene simulator that turns a scene's `[simulation]`
//! section into frames with ground truth.
//!
//! Layout (one concern per file):
//! - [`config`]: the `[simulation]` scene section (serde, validated).
//! - [`link_budget`]: received power, currents, voltages, noise, SNR.
//! - [`photodetector`]: state-space models of the APD/TIA receiver chain, discretised exactly.
//! - [`noise_source`]: coloured/skewed noise with a shot-noise envelope; the mains burst.
//! - [`digitiser`]: quantisation to codes, clipping, jittered sampling.
//! - [`simulator`]: [`Simulator`], [`Truth`].
//!
//! Plain synchronous Rust: no I/O, no async.

pub mod config;
pub mod digitiser;
pub mod link_budget;
pub mod noise_source;
pub mod photodetector;
pub mod simulator;

pub use config::SimulationConfig;
pub use link_budget::LinkBudgetLine;
pub use simulator::{Simulator, TrueReturn, Truth};

/// Errors of the physics layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PhysicsError {
    /// A value out of its allowed range (the field is dotted, e.g.
    /// `simulation.targets[1].range_m`).
    #[error(transparent)]
    Invalid(#[from] crate::scene::FieldError),
    /// A section an effect depends on is missing.
    #[error("missing [{section}] section: needed by {needed_by}")]
    MissingSection {
        /// Dotted section name.
        section: &'static str,
        /// What needs it.
        needed_by: &'static str,
    },
}
