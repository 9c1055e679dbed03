//! tofwave: streaming waveform processing and detection for direct-detection
//! time-of-flight lidar.
//!
//! Module map, one line each, lowest layer first: a module uses only modules
//! on layers below its own (`tests/suite/layering.rs` checks every `crate::` path).
//! `ARCHITECTURE.md` has the layer diagram, the data path and where each kind
//! of change goes.
#![warn(missing_docs)]
// `!(x > y)` is written on purpose throughout: it is true for NaN, so a
// comparison that guards a division or a threshold also catches NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

/// Domain types: frames in, reports out. No wire types.
pub mod frame;
/// Numerics with no domain knowledge: special functions, an inlined exponential, statistics, dense solver, autocovariance, selection, robust sigma of quantised samples, exact statistics of integer codes. Depends on std only.
pub mod math;
/// Metric names and recording functions; tracing set-up.
pub mod telemetry;
/// Wire contract: generated protobuf messages and their lossless, validating conversion to the domain types.
pub mod wire;
/// Pure numeric kernels: matched filter (f64, and exact in integers on ADC codes), interpolation, crossings, fits, filters. No I/O.
pub mod dsp;
/// Scene: TOML description of a sensor set-up (including the simulator's `[simulation]`), validated at load, and the embedded default.
pub mod scene;
/// Noise model, thresholds, detector kernels, gates, timing errors, false-alarm statistics.
pub mod detect;
/// Link budget, photodetector chain, noise sources, scene simulator.
pub mod physics;
/// Stage trait, stages built from a scene, per-sensor pipeline (and `threaded`: one sensor's stages cut over threads).
pub mod pipeline;
/// System-delay (and walk-table) calibration from reports of a target at a known range.
pub mod calibrate;
/// Readers and writers of capture formats; replay source; a starting scene measured from a capture.
pub mod capture;
/// Static PNG/SVG plots of processed frames: trace, gates, threshold, detector output, returns.
pub mod plot;
/// gRPC services (the only module that knows tonic), fan-out, sessions, shutdown; the browser dashboard (HTTP, server-sent events); cluster mode over NATS JetStream (`serve --cluster`, the only module that knows NATS).
pub mod service;
/// Work-precision report, numpy/scipy peer, service throughput and bandwidth yardstick (`tofwave bench`).
pub mod bench;
