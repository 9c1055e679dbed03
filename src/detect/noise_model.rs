//! Noise-gate moments (Welford/Terriberry, shifted), the fitted noise model,
//! an exponentially forgetting tracker for slow drift, and the spectral
//! checks (Welch PSD, autocorrelation) used to decide whether the noise is
//! white.
//!
//! Named `noise_model` (not `noise`) because `pipeline::noise` is the stage
//! that uses it; this module is the model, the stage is the step.

use crate::frame::NoiseSummary;
use crate::math::autocov::lag_product_sum;
use crate::math::code_stats::{code_grid, code_min_max, code_power_sums, exact_centre};
use crate::math::quantised::{grid_step_within, quantised_sigma_codes, quantised_sigma_within};
use crate::math::select::mad_sigma;
use crate::math::sum;

/// Single-pass central moments up to the fourth (Welford/Terriberry), f64.
///
/// The first sample is kept as a shift and every later sample enters as
/// `x − shift`, which is exact (Sterbenz) for a gate whose spread is small
/// against its offset: a 1 kV mean with a 1 µV spread keeps σ to ~1e-12
/// relative instead of losing 9 digits to the offset. (Moments of integer
/// codes, [`Moments::of_codes`], are shifted to the volts of their middle
/// code instead.)
#[derive(Debug, Clone, Copy, Default)]
pub struct Moments {
    n: u64,
    /// Origin of the accumulation (the first sample, or the middle code's
    /// volts): kills the offset's rounding before it can reach the deviations.
    shift: f64,
    /// Mean of `x − shift`.
    mean: f64,
    m2: f64,
    m3: f64,
    m4: f64,
}

impl Moments {
    /// Adds one sample.
    pub fn push(&mut self, x: f64) {
        if self.n == 0 {
            self.shift = x;
        }
        let x = x - self.shift;
        let n1 = self.n as f64;
        self.n += 1;
        let n = self.n as f64;
        let delta = x - self.mean;
        let delta_n = delta / n;
        let delta_n2 = delta_n * delta_n;
        let term1 = delta * delta_n * n1;
        self.mean += delta_n;
        self.m4 += term1 * delta_n2 * (n * n - 3.0 * n + 3.0) + 6.0 * delta_n2 * self.m2
            - 4.0 * delta_n * self.m3;
        self.m3 += term1 * delta_n * (n - 2.0) - 3.0 * delta_n * self.m2;
        self.m2 += term1;
    }

    /// The moments of `x` (all finite), as pushing them one by one gives up
    /// to rounding, in two passes (the mean of `x − x₀`, then the central
    /// power sums about it) in the eight-lane order of [`crate::math::sum`]:
    /// no division per sample and no serial chain, and at least as accurate
    /// (the two-pass form is the textbook reference for Welford's).
    pub fn of(x: &[f64]) -> Moments {
        let Some(&shift) = x.first() else {
            return Moments::default();
        };
        let n = x.len();
        let mean = sum::shifted_sum(x, shift) / n as f64;
        let (m2, m3, m4) = sum::central_power_sums(x, shift, mean);
        Moments { n: n as u64, shift, mean, m2, m3, m4 }
    }

    /// The moments of integer codes `parts` decoded as `c·g + o` volts, from their power sums about
    /// the code midway between `lo` and `hi`, summed exactly in integers:
    /// the central sums are formed exactly (times powers of n) and rounded
    /// once, so each moment is within a few ulp of the exact moment of the
    /// decoded values (the f64 passes of [`Moments::of`] round every
    /// sample's deviation and power). `None` where that does not hold: a
    /// span of more than 2·[`MAX_DISTANCE`](crate::math::code_stats::MAX_DISTANCE) codes, sums beyond `i128`, a
    /// scale `g` outside [1e-60, 1e60] (its fourth power must stay normal)
    /// or an offset that is not finite; the caller decodes and uses
    /// [`Moments::of`].
    pub fn of_codes(parts: &[&[i16]], g: f64, o: f64) -> Option<Moments> {
        let (lo, hi) = code_min_max(parts)?;
        Moments::of_codes_within(parts, lo, hi, g, o)
    }

    /// [`Moments::of_codes`] where the caller has `(lo, hi)`, the
    /// [`code_min_max`] of `parts`, at hand (wrong extremes would let the
    /// integer sums wrap).
    fn of_codes_within(parts: &[&[i16]], lo: i16, hi: i16, g: f64, o: f64) -> Option<Moments> {
        let n: usize = parts.iter().map(|p| p.len()).sum();
        if n == 0 {
            return None;
        }
        let centre = exact_centre(lo, hi, g, o)?;
        let [s1, s2, s3, s4] = code_power_sums(parts, centre);
        let ni = n as i128;
        // n·M2, n²·M3 and n³·M4 about the mean, in codes, exactly.
        let exact = || -> Option<(i128, i128, i128)> {
            let (n2, n3) = (ni.checked_mul(ni)?, ni.checked_mul(ni)?.checked_mul(ni)?);
            let s1_2 = s1.checked_mul(s1)?;
            let c2 = ni.checked_mul(s2)?.checked_sub(s1_2)?;
            let c3 = n2
                .checked_mul(s3)?
                .checked_sub(ni.checked_mul(s1)?.checked_mul(s2)?.checked_mul(3)?)?
                .checked_add(s1_2.checked_mul(s1)?.checked_mul(2)?)?;
            let c4 = n3
                .checked_mul(s4)?
                .checked_sub(n2.checked_mul(s1)?.checked_mul(s3)?.checked_mul(4)?)?
                .checked_add(ni.checked_mul(s1_2)?.checked_mul(s2)?.checked_mul(6)?)?
                .checked_sub(s1_2.checked_mul(s1_2)?.checked_mul(3)?)?;
            Some((c2, c3, c4))
        };
        let (c2, c3, c4) = exact()?;
        let nf = n as f64;
        let g2 = g * g;
        Some(Moments {
            n: n as u64,
            // The centre code's volts, decoded as the channel decodes.
            shift: f64::from(centre) * g + o,
            mean: g * (s1 as f64 / nf),
            m2: c2 as f64 / nf * g2,
            m3: c3 as f64 / (nf * nf) * (g2 * g),
            m4: c4 as f64 / (nf * nf * nf) * (g2 * g2),
        })
    }

    /// Combines the moments of two disjoint sample sets (Chan et al. 1979 for
    /// M2, Pébay 2008 for M3/M4): the result equals pushing all samples of
    /// both into one accumulator, up to rounding.
    pub fn merge(&mut self, other: &Moments) {
        if other.n == 0 {
            return;
        }
        if self.n == 0 {
            *self = *other;
            return;
        }
        let (na, nb) = (self.n as f64, other.n as f64);
        let n = na + nb;
        // other's mean expressed relative to our shift
        let mb = (other.shift - self.shift) + other.mean;
        let delta = mb - self.mean;
        let dn = delta / n;
        let (m2a, m3a, m4a) = (self.m2, self.m3, self.m4);
        let (m2b, m3b, m4b) = (other.m2, other.m3, other.m4);
        self.m4 = m4a
            + m4b
            + delta * dn * dn * dn * na * nb * (na * na - na * nb + nb * nb)
            + 6.0 * dn * dn * (na * na * m2b + nb * nb * m2a)
            + 4.0 * dn * (na * m3b - nb * m3a);
        self.m3 =
            m3a + m3b + delta * dn * dn * na * nb * (na - nb) + 3.0 * dn * (na * m2b - nb * m2a);
        self.m2 = m2a + m2b + delta * dn * na * nb;
        self.mean += nb * dn;
        self.n += other.n;
    }

    /// Samples seen.
    pub fn count(&self) -> u64 {
        self.n
    }
    /// Mean.
    pub fn mean(&self) -> f64 {
        self.shift + self.mean
    }
    /// Sum of squared deviations from the mean (M2).
    pub fn sum_sq_dev(&self) -> f64 {
        self.m2
    }
    /// Unbiased variance (n - 1); 0 for fewer than two samples.
    pub fn variance(&self) -> f64 {
        if self.n < 2 {
            0.0
        } else {
            self.m2 / (self.n as f64 - 1.0)
        }
    }
    /// Sample skewness g1; 0 when the variance is 0.
    pub fn skewness(&self) -> f64 {
        if self.m2 <= 0.0 {
            0.0
        } else {
            (self.n as f64).sqrt() * self.m3 / self.m2.powf(1.5)
        }
    }
    /// Sample excess kurtosis g2; 0 when the variance is 0.
    pub fn excess_kurtosis(&self) -> f64 {
        if self.m2 <= 0.0 {
            0.0
        } else {
            self.n as f64 * self.m4 / (self.m2 * self.m2) - 3.0
        }
    }
}

/// Exponentially forgetting blend of successive frame moments, for a noise
/// model that follows slow drift (temperature, bias supply) without being
/// thrown by one frame.
///
/// Each [`NoiseTracker::update`] first multiplies the weight of everything
/// seen so far by `lambda` (0 < λ ≤ 1; λ = 1 never forgets), then merges the
/// new frame's moments with unit weight per sample. After many frames of m
/// samples the effective memory is m/(1 − λ) samples. Variance uses
/// reliability weights: M2 / (W − W₂/W), unbiased for i.i.d. data.
#[derive(Debug, Clone, Copy)]
pub struct NoiseTracker {
    /// Forgetting factor per update.
    lambda: f64,
    /// Total weight W = Σ wᵢ.
    w: f64,
    /// Σ wᵢ², for the effective sample size and the unbiased variance.
    w2: f64,
    /// Origin of the accumulation (see [`Moments`]).
    shift: f64,
    /// Weighted mean of `x − shift`.
    mean: f64,
    m2: f64,
    m3: f64,
    m4: f64,
}

impl NoiseTracker {
    /// A tracker whose memory decays with a time constant of `frames` frames:
    /// λ = e^(−1/frames), so a frame k updates old contributes weight e^(−k/frames).
    /// After a step in the noise, the old level's share of the weight falls
    /// below 5 % within 3·`frames` updates. `frames` = 0 never forgets.
    pub fn with_time_constant(frames: f64) -> Self {
        if frames > 0.0 && frames.is_finite() {
            Self::with_forgetting((-1.0 / frames).exp())
        } else {
            Self::with_forgetting(1.0)
        }
    }

    /// The forgetting factor λ per update.
    pub fn lambda(&self) -> f64 {
        self.lambda
    }

    /// A tracker with forgetting factor `lambda`, clamped to [0, 1] (NaN → 1):
    /// 0 keeps only the latest frame, 1 accumulates forever.
    pub fn with_forgetting(lambda: f64) -> Self {
        let lambda = if lambda.is_nan() {
            1.0
        } else {
            lambda.clamp(0.0, 1.0)
        };
        Self {
            lambda,
            w: 0.0,
            w2: 0.0,
            shift: 0.0,
            mean: 0.0,
            m2: 0.0,
            m3: 0.0,
            m4: 0.0,
        }
    }

    /// Forgets by λ, then blends in one frame's moments.
    pub fn update(&mut self, frame: &Moments) {
        let l = self.lambda;
        self.w *= l;
        self.w2 *= l * l;
        self.m2 *= l;
        self.m3 *= l;
        self.m4 *= l;
        if frame.n == 0 {
            return;
        }
        if self.w <= 0.0 {
            self.shift = frame.shift;
            self.mean = frame.mean;
            self.m2 = frame.m2;
            self.m3 = frame.m3;
            self.m4 = frame.m4;
            self.w = frame.n as f64;
            self.w2 = frame.n as f64;
            return;
        }
        let (na, nb) = (self.w, frame.n as f64);
        let n = na + nb;
        let mb = (frame.shift - self.shift) + frame.mean;
        let delta = mb - self.mean;
        let dn = delta / n;
        let (m2a, m3a, m4a) = (self.m2, self.m3, self.m4);
        self.m4 = m4a
            + frame.m4
            + delta * dn * dn * dn * na * nb * (na * na - na * nb + nb * nb)
            + 6.0 * dn * dn * (na * na * frame.m2 + nb * nb * m2a)
            + 4.0 * dn * (na * frame.m3 - nb * m3a);
        self.m3 = m3a
            + frame.m3
            + delta * dn * dn * na * nb * (na - nb)
            + 3.0 * dn * (na * frame.m2 - nb * m2a);
        self.m2 = m2a + frame.m2 + delta * dn * na * nb;
        self.mean += nb * dn;
        self.w = n;
        self.w2 += nb;
    }

    /// Weighted mean.
    pub fn mean(&self) -> f64 {
        self.shift + self.mean
    }
    /// Effective number of samples W²/W₂ (0 before the first update).
    pub fn effective_samples(&self) -> f64 {
        if self.w2 > 0.0 {
            self.w * self.w / self.w2
        } else {
            0.0
        }
    }
    /// Unbiased weighted variance M2/(W − W₂/W); 0 while the effective
    /// sample size is ≤ 1.
    pub fn variance(&self) -> f64 {
        let denom = self.w - self.w2 / self.w.max(f64::MIN_POSITIVE);
        if self.w <= 0.0 || denom <= 0.0 {
            0.0
        } else {
            self.m2 / denom
        }
    }
    /// Weighted skewness (population form, W as n); 0 when the variance is 0.
    pub fn skewness(&self) -> f64 {
        if self.m2 <= 0.0 {
            0.0
        } else {
            self.w.sqrt() * self.m3 / self.m2.powf(1.5)
        }
    }
    /// Weighted excess kurtosis (population form); 0 when the variance is 0.
    pub fn excess_kurtosis(&self) -> f64 {
        if self.m2 <= 0.0 {
            0.0
        } else {
            self.w * self.m4 / (self.m2 * self.m2) - 3.0
        }
    }
}

/// Asymptotic standard deviation of (s − σ̂_MAD)/σ times √n for Gaussian
/// data: Var = Var(s) + Var(σ̂_MAD) − 2 Cov = 1/2 + 1.360459 − 2·(1/2), from
/// the influence functions (x² − 1)/2 and sign(|x| − c)/(4 c φ(c)),
/// c = Φ⁻¹(3/4) (their covariance is 2cφ(c)/(4cφ(c)) = 1/2).
pub const SIGMA_MAD_DIFF_SD: f64 = 0.927_609_456_782_300_7;

/// Finite-sample inflation of the variance of s − σ̂_MAD: the asymptotic
/// 0.8604/n is low at small n (the sample median's and the MAD's variance
/// converge slowly); Var ≈ 0.8604 (1 + 10/n)/n brings the Gaussian flag
/// rate to the nominal α at n = 30…1000 (calibrated by Monte Carlo;
/// `tests/suite/numerics.rs` checks it at n = 30, 100 and 1000).
pub const SMALL_SAMPLE_INFLATION: f64 = 10.0;

/// Fewest samples for the normality and contamination verdicts: below it
/// the asymptotic distributions behind both are not trustworthy and the
/// fit reports `gaussian = false`, `contaminated = false`.
pub const MIN_VERDICT_SAMPLES: u64 = 20;

/// Quantisation grids coarser than σ/`GRID_FRACTION` get the quantised
/// robust sigma: below it the MAD's own rounding (up to a quarter step) is
/// under 0.2 % of σ, well inside its sampling spread at any gate size used.
const GRID_FRACTION: f64 = 256.0;

/// Fits the noise model on gate samples; keeps its scratch buffer between
/// frames, so after the first frame of a given size it does not allocate.
#[derive(Debug, Default)]
pub struct NoiseFitter {
    scratch: Vec<f64>,
    /// Per-level counts for the robust sigma of quantised samples.
    levels: Vec<u32>,
    /// Non-finite samples (NaN, ±Inf) skipped by the last fit.
    skipped_nonfinite: u64,
    /// Moments of the last fit's finite samples, for a [`NoiseTracker`].
    moments: Moments,
}

impl NoiseFitter {
    /// Fits on the concatenation of `parts`.
    ///
    /// * Non-finite samples (NaN, ±Inf) are skipped and counted
    ///   ([`NoiseFitter::skipped_nonfinite`]); `samples` counts the finite
    ///   ones used. The caller flags the frame.
    /// * 0 samples: everything 0, `gaussian = false`, p-value 0.
    /// * 1 sample: mean = that sample, σ = 0.
    /// * σ = 0 (all samples equal: a clipped or noise-free gate): skewness
    ///   and kurtosis 0, p-value 0, `gaussian = false`.
    /// * `gaussian` = Jarque-Bera p ≥ `normality_alpha` and at least
    ///   [`MIN_VERDICT_SAMPLES`] samples and σ > 0.
    /// * `contaminated`: the plain σ (sample s) and the robust σ (MAD·1.4826)
    ///   disagree by more than their Gaussian sampling spread allows, at the
    ///   same two-sided level `normality_alpha`:
    ///   `|s/c4(n) − σ̂_MAD·n/(n − 0.8)| > z_{α/2} · 0.9276 · √(1 + 10/n) · σ̂ / √n`,
    ///   with the small-sample consistency factors c4(n) ≈ 1 − 1/(4n) −
    ///   7/(32n²) and n/(n − 0.8) (Croux & Rousseeuw 1992) and σ̂ the robust
    ///   σ. A few large outliers inflate s but hardly move the MAD, so this
    ///   detects pulses or bursts leaking into the gate. If more than half
    ///   the samples are identical (MAD = 0) while s > 0 the gate is flagged
    ///   too. Requires [`MIN_VERDICT_SAMPLES`] samples.
    /// * `robust_sigma_v` of samples on a quantisation grid coarser than
    ///   σ/256 (scope codes) comes from the probit fit of
    ///   [`quantised_sigma`](crate::math::quantised::quantised_sigma) instead of the MAD, which such a grid rounds
    ///   (an 8-bit scope with a step of 1.3 σ flagged every clean gate).
    ///   With the same bound the verdict is conservative there: the fit
    ///   uses the central samples' distribution and follows s more closely
    ///   than the MAD does (flag rate at most α for steps of 0.3 to 2 σ and
    ///   60 to 1400 samples; `tests/suite/numerics.rs`), at some cost in
    ///   power on steps over one σ (2 % of the gate at 8 σ: flagged in
    ///   about 90 % of 300-sample gates with a step of 1.3 σ, at α = 1e-3).
    pub fn fit(&mut self, parts: &[&[f64]], normality_alpha: f64) -> NoiseSummary {
        self.scratch.clear();
        self.skipped_nonfinite = 0;
        for p in parts {
            if sum::all_finite(p) {
                self.scratch.extend_from_slice(p);
            } else {
                let before = self.scratch.len();
                self.scratch.extend(p.iter().copied().filter(|x| x.is_finite()));
                self.skipped_nonfinite += (p.len() - (self.scratch.len() - before)) as u64;
            }
        }
        let m = Moments::of(&self.scratch);
        self.moments = m;
        let robust = if m.count() == 0 { 0.0 } else { self.robust_sigma(m.variance().sqrt()) };
        summary(&m, robust, normality_alpha)
    }

    /// [`NoiseFitter::fit`] on the volts of integer codes `parts` decoded as
    /// `c·g + o` (`g > 0`), read as codes: the moments from exact integer
    /// sums ([`Moments::of_codes`]) and, on a grid coarser than
    /// σ/256 (`GRID_FRACTION`), the quantised robust sigma from the codes'
    /// levels ([`quantised_sigma_codes`]). The same model as `fit` on the
    /// decoded volts to rounding where the decode keeps the codes' order
    /// and spacing (the caller's test: `detect::gates::codes_keep_order`):
    /// the moments are rounded once instead of per sample, and the grid
    /// step is `g` times the codes' grid exactly instead of a
    /// floating-point Euclid's over rounded volts. Where the offset is
    /// large against the step (|o| beyond ~5e8·g) that Euclid's tolerance
    /// (1e-9 of the volts) exceeds half a code and `fit` can settle on a
    /// grid of several codes; `fit_codes` keeps the codes' own grid there.
    /// `None` (nothing fitted) where there are no codes, `Moments::of_codes`
    /// declines or `g` is not positive: call `fit`.
    pub fn fit_codes(&mut self, parts: &[&[i16]], g: f64, o: f64, normality_alpha: f64) -> Option<NoiseSummary> {
        if !(g > 0.0) {
            return None;
        }
        let (lo, hi) = code_min_max(parts)?;
        let m = Moments::of_codes_within(parts, lo, hi, g, o)?;
        self.skipped_nonfinite = 0;
        self.moments = m;
        // The MAD's scratch, grown now however rarely it is needed: a frame
        // that first needs it later does not allocate.
        let n = m.count() as usize;
        if self.scratch.capacity() < n {
            self.scratch.reserve(n - self.scratch.len());
        }
        let sigma = m.variance().sqrt();
        let grid = if sigma > 0.0 { code_grid(parts, lo) } else { 0 };
        let step = g * f64::from(grid);
        let quantised = (grid > 0 && step >= sigma / GRID_FRACTION)
            .then(|| quantised_sigma_codes(parts, lo, hi, grid, step, &mut self.levels))
            .flatten();
        let robust = match quantised {
            Some(r) => r,
            None => {
                // A grid finer than σ/256, or a fit the levels do not
                // support: the MAD of the volts, as `fit` takes it.
                self.scratch.clear();
                self.scratch.extend(parts.iter().flat_map(|p| p.iter()).map(|&c| f64::from(c) * g + o));
                mad_sigma(&mut self.scratch)
            }
        };
        Some(summary(&m, robust, normality_alpha))
    }

    /// Robust sigma of the samples in `scratch` (reorders them): 1.4826·MAD,
    /// or, for samples on a quantisation grid coarser than σ/[`GRID_FRACTION`]
    /// (`sigma` is the plain one), the probit fit of [`quantised_sigma`](crate::math::quantised::quantised_sigma).
    fn robust_sigma(&mut self, sigma: f64) -> f64 {
        // One min/max pass serves both.
        let (lo, hi) = crate::math::select::min_max(&self.scratch);
        if sigma > 0.0
            && let Some(r) = grid_step_within(&self.scratch, lo, hi, sigma / GRID_FRACTION)
                .and_then(|q| quantised_sigma_within(&self.scratch, lo, hi, q, &mut self.levels))
        {
            return r;
        }
        mad_sigma(&mut self.scratch)
    }

    /// Non-finite samples skipped by the last [`NoiseFitter::fit`] (0 after
    /// [`NoiseFitter::fit_codes`]: codes are finite).
    pub fn skipped_nonfinite(&self) -> u64 {
        self.skipped_nonfinite
    }

    /// Moments of the finite samples of the last [`NoiseFitter::fit`] or
    /// [`NoiseFitter::fit_codes`].
    pub fn moments(&self) -> &Moments {
        &self.moments
    }
}

/// The noise model of samples with moments `m` and robust sigma `robust`:
/// σ, skewness, kurtosis, the Jarque–Bera p-value and the normality and
/// contamination verdicts at `normality_alpha` (see [`NoiseFitter::fit`]).
fn summary(m: &Moments, robust: f64, normality_alpha: f64) -> NoiseSummary {
    let n = m.count();
    if n == 0 {
        return NoiseSummary {
            mean_v: 0.0,
            sigma_v: 0.0,
            skewness: 0.0,
            excess_kurtosis: 0.0,
            gaussian: false,
            normality_p_value: 0.0,
            robust_sigma_v: 0.0,
            samples: 0,
            contaminated: false,
        };
    }
    let sigma = m.variance().sqrt();
    let (skew, kurt) = (m.skewness(), m.excess_kurtosis());
    let p = if sigma > 0.0 {
        crate::math::stats::jarque_bera(n, skew, kurt).1
    } else if n >= 2 {
        0.0
    } else {
        1.0
    };
    let enough = n >= MIN_VERDICT_SAMPLES;
    let alpha = if normality_alpha.is_nan() {
        0.0
    } else {
        normality_alpha.clamp(0.0, 1.0)
    };
    let contaminated = enough && sigma > 0.0 && {
        if robust <= 0.0 {
            true
        } else {
            let nf = n as f64;
            let c4 = 1.0 - 1.0 / (4.0 * nf) - 7.0 / (32.0 * nf * nf);
            let diff = sigma / c4 - robust * nf / (nf - 0.8);
            let z = crate::math::special::q_inv(0.5 * alpha);
            let sd = SIGMA_MAD_DIFF_SD * (1.0 + SMALL_SAMPLE_INFLATION / nf).sqrt() * robust
                / nf.sqrt();
            diff.abs() > z * sd
        }
    };
    NoiseSummary {
        mean_v: m.mean(),
        sigma_v: sigma,
        skewness: skew,
        excess_kurtosis: kurt,
        gaussian: enough && sigma > 0.0 && p >= alpha,
        normality_p_value: p,
        robust_sigma_v: robust,
        samples: n,
        contaminated,
    }
}

/// Welch power spectral density estimate, one-sided, V²/Hz.
///
/// Periodic Hann window of `segment` samples, 50 % overlap (step
/// `segment / 2`), each segment's mean removed (as SciPy's default
/// `detrend='constant'`), periodograms averaged. Bin k is at frequency
/// k/(segment·dt_s), k = 0..=segment/2; bins other than DC and Nyquist are
/// doubled so that Σ PSD·Δf equals the variance. Scaling: |X_k|²·dt_s/Σw².
/// Returns an empty vector when `segment < 2`, `x` is shorter than one
/// segment, or `dt_s` is not positive and finite. Allocates (a spectrum is
/// an analysis product, not a per-frame kernel).
pub fn welch_psd(x: &[f64], segment: usize, dt_s: f64) -> Vec<f64> {
    if segment < 2 || x.len() < segment || !(dt_s > 0.0 && dt_s.is_finite()) {
        return Vec::new();
    }
    let n = segment;
    let window: Vec<f64> = (0..n)
        .map(|i| 0.5 * (1.0 - (2.0 * std::f64::consts::PI * i as f64 / n as f64).cos()))
        .collect();
    let w2: f64 = window.iter().map(|w| w * w).sum();
    let mut planner = realfft::RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(n);
    let mut input = fft.make_input_vec();
    let mut spectrum = fft.make_output_vec();
    let mut scratch = fft.make_scratch_vec();
    let mut psd = vec![0.0; n / 2 + 1];
    let step = (n / 2).max(1);
    let mut segments = 0usize;
    let mut start = 0;
    while start + n <= x.len() {
        let seg = &x[start..start + n];
        let mean = seg.iter().sum::<f64>() / n as f64;
        for ((dst, &v), &w) in input.iter_mut().zip(seg).zip(&window) {
            *dst = (v - mean) * w;
        }
        // Lengths come from the plan, so the transform cannot fail.
        if fft
            .process_with_scratch(&mut input, &mut spectrum, &mut scratch)
            .is_ok()
        {
            for (p, c) in psd.iter_mut().zip(&spectrum) {
                *p += c.norm_sqr();
            }
            segments += 1;
        }
        start += step;
    }
    let scale = dt_s / (w2 * segments.max(1) as f64);
    let last = psd.len() - 1;
    for (k, p) in psd.iter_mut().enumerate() {
        let one_sided = if k == 0 || (n.is_multiple_of(2) && k == last) {
            1.0
        } else {
            2.0
        };
        *p *= scale * one_sided;
    }
    psd
}

/// Normalised sample autocorrelation ρ(k) = c(k)/c(0), k = 0..=max_lag
/// (capped at len − 1), with the biased estimator c(k) = Σ (x_i − x̄)(x_{i+k}
/// − x̄)/n (positive semi-definite). ρ(0) = 1; a constant sequence gives
/// ρ(k) = 0 for k > 0; an empty input gives an empty vector.
pub fn autocorrelation(x: &[f64], max_lag: usize) -> Vec<f64> {
    let n = x.len();
    if n == 0 {
        return Vec::new();
    }
    let mut m = Moments::default();
    x.iter().for_each(|&v| m.push(v));
    let mean = m.mean();
    let lags = max_lag.min(n - 1);
    let c0 = lag_product_sum(x, 0, mean);
    let mut out = Vec::with_capacity(lags + 1);
    out.push(1.0);
    for k in 1..=lags {
        if c0 <= 0.0 {
            out.push(0.0);
            continue;
        }
        out.push(lag_product_sum(x, k, mean) / c0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Relative distance in units of the larger's ulp (2⁻⁵² of it).
    fn ulps(a: f64, b: f64) -> f64 {
        if a == b {
            return 0.0;
        }
        (a - b).abs() / (a.abs().max(b.abs()) * f64::EPSILON)
    }

    #[test]
    fn moments_of_codes_are_within_a_few_ulp_of_the_exact_moments() {
        // The reference forms each central sum from the deviations, not
        // the power sums: Σ(n·c − Σc)^k = n^k·M_k exactly in i128, then
        // rounded and scaled (three roundings). Agreement within 8 ulp
        // means both are within a few ulp of the exact moments.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for (n, centre, spread, g, o) in [
            (2000usize, 0i32, 200i32, 1.0 / 4096.0, 0.0),
            (1400, -3, 2, 0.013 * 1.28, -5e-4),
            (300, 1000, 40, 3.1e-5, 1000.0),
            (61, -20000, 4096, 7.7e-3, -0.25),
            (9000, 5, 900, 1e-6, 2.5),
        ] {
            let codes: Vec<i16> = (0..n).map(|_| (centre + rng.random_range(-spread..=spread)) as i16).collect();
            let (a, b) = codes.split_at(n / 3);
            let (lo, hi) = crate::math::code_stats::code_min_max(&[a, b]).expect("codes");
            let m = Moments::of_codes(&[a, b], g, o).expect("within reach");
            let ni = n as i128;
            let s: i128 = codes.iter().map(|&c| i128::from(c)).sum();
            let x = |k: u32| codes.iter().map(|&c| (ni * i128::from(c) - s).pow(k)).sum::<i128>() as f64;
            let nf = n as f64;
            assert_eq!(m.count(), n as u64);
            let mean = o + g * (s as f64 / nf);
            assert!((m.mean() - mean).abs() <= 4.0 * f64::EPSILON * (o.abs() + g * f64::from(i32::from(lo).abs().max(i32::from(hi).abs()))), "{n}: mean {} vs {mean}", m.mean());
            let m2 = x(2) / (nf * nf) * g * g;
            let m3 = x(3) / (nf * nf * nf) * g * g * g;
            let m4 = x(4) / (nf * nf * nf * nf) * (g * g) * (g * g);
            // Exact integers rounded once each side: no cancellation even
            // where M3 is near 0 (symmetric data).
            assert!(ulps(m.m2, m2) <= 8.0, "{n}: M2 {} vs {m2}", m.m2);
            assert!(ulps(m.m3, m3) <= 8.0, "{n}: M3 {} vs {m3}", m.m3);
            assert!(ulps(m.m4, m4) <= 8.0, "{n}: M4 {} vs {m4}", m.m4);
        }
    }

    #[test]
    fn moments_of_codes_decline_what_they_cannot_sum_exactly() {
        let wide: [i16; 3] = [-5000, 0, 5000];
        assert!(Moments::of_codes(&[&wide], 1e-3, 0.0).is_none(), "a span beyond 2·MAX_DISTANCE");
        assert!(Moments::of_codes(&[&[1, 2]], 1e300, 0.0).is_none(), "a scale whose fourth power overflows");
        assert!(Moments::of_codes(&[&[1, 2]], 1e-3, f64::NAN).is_none(), "a NaN offset");
        assert!(Moments::of_codes(&[&[]], 1e-3, 0.0).is_none(), "no codes");
        assert!(NoiseFitter::default().fit_codes(&[&[], &[]], 1e-3, 0.0, 0.01).is_none(), "no codes to fit");
        let mut f = NoiseFitter::default();
        assert!(f.fit_codes(&[&[1, 2, 3]], -1e-3, 0.0, 0.01).is_none(), "a negative scale");
    }
}
