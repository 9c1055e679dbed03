//! Learning the return pulse shape from the data by equivalent-time alignment:
//! many shots land at random sub-sample phases, so placing each shot's samples
//! at their time relative to its fitted peak fills a grid finer than the
//! sampling period. The learned table removes the bias a mismatched
//! parametric shape would leave in model-based timing.

use crate::scene::{PulseConfig, PulseModel};

/// Why a template could not be learned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TemplateError {
    /// Not enough shots.
    #[error("only {got} usable returns; at least {need} are needed to fill the {bins}-bin grid")]
    TooFewShots {
        /// Shots added.
        got: u64,
        /// Shots needed.
        need: u64,
        /// Grid bins.
        bins: usize,
    },
    /// Bins no shot reached (the phases were not spread).
    #[error("{empty} of {bins} grid bins received no sample: the shots' sub-sample phases do not cover the period")]
    Gaps {
        /// Empty bins.
        empty: usize,
        /// Grid bins.
        bins: usize,
    },
}

/// Accumulates shots on a fine grid around their peaks.
#[derive(Debug, Clone)]
pub struct TemplateLearner {
    oversample: usize,
    /// Grid start relative to the peak, samples.
    lo: f64,
    sums: Vec<f64>,
    /// Σ of squares per bin: the bin's standard error decides where the
    /// learned pulse ends and noise begins.
    squares: Vec<f64>,
    counts: Vec<u64>,
    shots: u64,
}

/// Tails below this fraction of the peak are cut from the learned table.
const TAIL_FRACTION: f64 = 0.01;
/// ...and so are bins whose mean is within this many standard errors of zero.
const TAIL_SE: f64 = 3.0;

impl TemplateLearner {
    /// A grid of `oversample` bins per sample over [lo, hi] samples around the peak.
    pub fn new(oversample: usize, lo: f64, hi: f64) -> TemplateLearner {
        let oversample = oversample.max(1);
        let bins = ((hi - lo) * oversample as f64).ceil() as usize + 1;
        TemplateLearner {
            oversample,
            lo,
            sums: vec![0.0; bins],
            squares: vec![0.0; bins],
            counts: vec![0; bins],
            shots: 0,
        }
    }

    /// Adds one shot: samples `x` with noise mean `mean_v`, fitted peak at
    /// `peak_index` (fractional samples) and amplitude `amplitude_v`.
    pub fn add(&mut self, x: &[f64], mean_v: f64, peak_index: f64, amplitude_v: f64) {
        if !(amplitude_v > 0.0) || !peak_index.is_finite() {
            return;
        }
        let step = 1.0 / self.oversample as f64;
        let bins = self.sums.len();
        let first = (peak_index + self.lo).ceil().max(0.0) as usize;
        for (k, &v) in x.iter().enumerate().skip(first) {
            let t = k as f64 - peak_index;
            let b = ((t - self.lo) / step).round();
            if b >= bins as f64 {
                break;
            }
            // Masked samples (NaN) are skipped.
            if b >= 0.0 && v.is_finite() {
                let u = (v - mean_v) / amplitude_v;
                self.sums[b as usize] += u;
                self.squares[b as usize] += u * u;
                self.counts[b as usize] += 1;
            }
        }
        self.shots += 1;
    }

    /// Shots added so far.
    pub fn shots(&self) -> u64 {
        self.shots
    }

    /// The learned shape as a scene pulse (table model, unit peak, re-centred on its peak).
    pub fn finish(&self, dt_s: f64) -> Result<PulseConfig, TemplateError> {
        let bins = self.sums.len();
        let need = 2 * self.oversample as u64;
        if self.shots < need {
            return Err(TemplateError::TooFewShots { got: self.shots, need, bins });
        }
        let empty = self.counts.iter().filter(|&&c| c == 0).count();
        if empty > 0 {
            return Err(TemplateError::Gaps { empty, bins });
        }
        let raw: Vec<f64> = self.sums.iter().zip(&self.counts).map(|(s, &c)| s / c as f64).collect();
        // Each bin carries its own noise, and a fit follows the table's
        // slope, which differencing bins 1/oversample apart amplifies: the
        // cost of a delay fit then has ripples a bin wide that trap the
        // iteration. The pulse, sampled at 1/dt, has no content near the
        // grid's own Nyquist rate, so a Gaussian of 0.15 sample (a 0.4 %
        // loss at 0.1 cycle per sample, 1.8 % at 0.2) removes the bin noise
        // and keeps the shape.
        let mean = gaussian_smooth(&raw, 0.15 * self.oversample as f64);
        // A light 3-bin average before locating the peak, so one noisy bin does not move it.
        let smooth: Vec<f64> = (0..bins)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(bins - 1));
                (mean[a] + mean[i] + mean[b]) / 3.0
            })
            .collect();
        let p = (1..bins - 1).max_by(|&a, &b| smooth[a].total_cmp(&smooth[b])).unwrap_or(bins / 2);
        let (d, h) = crate::dsp::interp::parabolic(smooth[p - 1], smooth[p], smooth[p + 1]);
        let step = 1.0 / self.oversample as f64;
        let peak_t = self.lo + (p as f64 + d) * step;
        // The grid is wider than the pulse: where the shape is lost in noise
        // (below 1 % of the peak, or within 3 standard errors of zero) the
        // table ends, one sample beyond the last significant bin, so a
        // matched filter or fit does not carry noisy taps.
        let significant = |i: usize| {
            let c = self.counts[i] as f64;
            let var = (self.squares[i] / c - mean[i] * mean[i]).max(0.0);
            let se = (var / c).sqrt();
            smooth[i].abs() > (TAIL_FRACTION * h).max(TAIL_SE * se)
        };
        // Walk out from the peak; the pulse ends where a whole sample period
        // of bins in a row is insignificant.
        let run = self.oversample;
        let (mut first_sig, mut quiet) = (p, 0);
        for i in (0..p).rev() {
            if significant(i) {
                first_sig = i;
                quiet = 0;
            } else {
                quiet += 1;
                if quiet >= run {
                    break;
                }
            }
        }
        let (mut last_sig, mut quiet) = (p, 0);
        for i in p + 1..bins {
            if significant(i) {
                last_sig = i;
                quiet = 0;
            } else {
                quiet += 1;
                if quiet >= run {
                    break;
                }
            }
        }
        let a = first_sig.saturating_sub(self.oversample);
        let b = (last_sig + self.oversample).min(bins - 1);
        let mut table: Vec<f64> = mean[a..=b].iter().map(|v| v / h).collect();
        // A half-Hann taper over one sample at each end: the shape then goes
        // to zero smoothly where the table stops, so a fit that slides it
        // against a fixed window sees no step at the ends.
        let taper = self.oversample.min(table.len() / 4);
        let len = table.len();
        for i in 0..taper {
            let w = 0.5 * (1.0 - (std::f64::consts::PI * (i as f64 + 0.5) / taper as f64).cos());
            table[i] *= w;
            table[len - 1 - i] *= w;
        }
        Ok(PulseConfig {
            model: PulseModel::Table,
            rise_time_s: 0.0,
            fwhm_s: 0.0,
            table_step_s: step * dt_s,
            table_first_s: (self.lo + a as f64 * step - peak_t) * dt_s,
            table,
        })
    }
}

/// `x` convolved with a unit-area Gaussian of `sigma_bins`, edges renormalised.
fn gaussian_smooth(x: &[f64], sigma_bins: f64) -> Vec<f64> {
    if !(sigma_bins > 0.0) {
        return x.to_vec();
    }
    let half = (3.0 * sigma_bins).ceil() as isize;
    let w: Vec<f64> = (-half..=half).map(|k| (-0.5 * (k as f64 / sigma_bins).powi(2)).exp()).collect();
    let n = x.len() as isize;
    (0..n)
        .map(|i| {
            let (mut s, mut ws) = (0.0, 0.0);
            for (j, wk) in (-half..=half).zip(&w) {
                let k = i + j;
                if (0..n).contains(&k) {
                    s += wk * x[k as usize];
                    ws += wk;
                }
            }
            s / ws
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dsp::pulse::{Pulse, PulseShape, Shape};
    use rand::{Rng, SeedableRng};

    #[test]
    fn learns_a_shape_from_shots_at_random_phases() {
        let truth = Pulse { sigma_rise: 1.2, sigma_fall: 3.0 };
        let mut l = TemplateLearner::new(8, -8.0, 16.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..400 {
            let peak = 50.0 + rng.random::<f64>();
            let x: Vec<f64> = (0..120).map(|k| 0.1 + 2.0 * truth.value_and_slope(k as f64 - peak).0).collect();
            l.add(&x, 0.1, peak, 2.0);
        }
        let cfg = l.finish(1e-9).unwrap();
        let learned = cfg.shape(1e-9);
        // Timing uses the half-rise point of the shape it has, so compare the shapes aligned there.
        let shift = learned.half_rise_offset() - truth.half_rise_offset();
        for &t in &[-3.0, -1.0, 0.0, 0.5, 2.0, 6.0] {
            let (a, b) = (learned.value_and_slope(t + shift).0, truth.value_and_slope(t).0);
            assert!((a - b).abs() < 5e-3, "{t}: {a} vs {b}");
        }
        // The half-rise point sits a constant fraction of a sample off the
        // truth's: 0.08 sample from the equivalent-time grid, and 0.065 more
        // from the 0.15-sample smoothing on this fast (1.2-sample rise) pulse.
        // A constant is what calibration removes; what must not be there is
        // more than 0.2 sample of it.
        assert!(shift.abs() < 0.2, "{shift}");
        assert!((learned.fwhm() - Shape::Parametric(truth).fwhm()).abs() < 0.02);
    }

    #[test]
    fn too_few_shots_is_an_error() {
        let l = TemplateLearner::new(8, -8.0, 16.0);
        assert!(matches!(l.finish(1e-9), Err(TemplateError::TooFewShots { .. })));
    }
}
