//! Detection: noise model, Neyman-Pearson thresholds, detectors, timing and
//! false-alarm statistics. Plain synchronous code.

/// Noise-gate moments and the fitted noise model.
pub mod noise_model;
/// Noise colour (pooled gate autocorrelation) and the detector output's sigma.
pub mod colour;
/// Maxima of correlated Gaussian sequences: per-report thresholds.
pub mod extreme;
/// Range gate and noise gates in sample indices.
pub mod gates;
/// Matched-filter and threshold detector kernels.
pub mod kernels;
/// Timing methods and their uncertainties.
pub mod pulse_timing;
/// Sub-sample phase bias of the interpolating timing methods, measured and removed.
pub mod phase;
/// Measured bias and one-sigma width of each timing method by measured SNR.
pub mod error_table;
/// Learning the pulse shape from aligned shots (equivalent time).
pub mod template;
/// Thresholds and Pd with the noise mean and sigma estimated from a finite gate.
pub mod finite_gate;
/// Resolving overlapping returns by successive cancellation and joint refit.
pub mod resolve;
/// Empirical-quantile thresholds for non-Gaussian noise.
pub mod empirical;
/// Prewhitening for coloured noise: AR model by Levinson-Durbin, whitening FIR.
pub mod whiten;
/// CA- and OS-CFAR thresholds with factors solved from the design pfa.
pub mod cfar;
/// The OS-CFAR factor on correlated training cells (importance-sampled Monte Carlo).
pub mod os_coloured;
/// Leading-edge amplitude walk table: fit and interpolation.
pub mod walk;
/// Returns against interference events: flank fit and matched subspace test.
pub mod events;
/// The sensor's return shape learned from its frames, for the events test.
pub mod return_shape;
