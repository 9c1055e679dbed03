//! Pure numeric kernels: no tokio, no tonic, no I/O. Plan once, run allocation-free.

/// Parametric pulse shapes (value and slope), template sampling.
pub mod pulse;
/// Cross-correlation with a fixed template: direct FIR or FFT overlap-save, chosen by cost.
pub mod correlate;
/// Exact i32 correlation of i16 ADC codes with i16 taps (runtime-dispatched SIMD).
pub mod correlate_codes;
/// Sub-sample peak interpolation (parabolic, Gaussian).
pub mod interp;
/// Threshold crossings with sub-sample interpolation (constant fraction, leading edge).
pub mod crossing;
/// Maximum-likelihood fit of amplitude and delay of a pulse shape (Gauss-Newton).
pub mod mlfit;
/// Exact accumulation of integer codes and f64 samples for ensemble averages.
pub mod accumulate;
/// Fractional-delay (sub-sample shift) filter.
pub mod fracdelay;
/// Robust per-frame baseline offset and its drift tracking across frames.
pub mod offset;
/// Learning, detection and subtraction of a structured interference burst.
pub mod interference;
/// Zero-phase notch and high-pass filters (the plain alternative to cancellation).
pub mod notch;
