//! tofwave: streaming waveform processing and detection for direct-detection
//! time-of-flight lidar.
//!
//! Module map (one line each; DESIGN.md has the architecture):
#![warn(missing_docs)]
// `!(x > y)` is written on purpose throughout: it is true for NaN, so a
// comparison that guards a division or a threshold also catches NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

/// Domain types: frames in, reports out. No wire types.
pub mod frame;
/// Wire contract: generated protobuf messages and their lossless, validating conversion to the domain types.
pub mod wire;
/// Scene: TOML description of a sensor set-up, validated at load, and the embedded default.
pub mod scene;
/// Numerics with no domain knowledge: special functions, statistics, dense solver, autocovariance, selection. Depends on std only.
pub mod math;
/// Pure numeric kernels: matched filter, interpolation, crossings, fits. No I/O.
pub mod dsp;
/// Noise model, Q-function and thresholds, detectors, timing, false-alarm statistics.
pub mod detect;
/// Stage trait, stages built from a scene, per-sensor pipeline.
pub mod pipeline;
/// System-delay (and walk-table) calibration from reports of a target at a known range.
pub mod calibrate;
/// Link budget, pulse and detector models, scene simulator.
pub mod physics;
/// Readers and writers of capture formats; replay source.
pub mod capture;
/// gRPC services, fan-out, sessions, shutdown.
pub mod service;
/// Metric names and recording functions; tracing set-up.
pub mod telemetry;
/// Work-precision report, numpy/scipy peer, service throughput and bandwidth yardstick (`tofwave bench`).
pub mod bench;
