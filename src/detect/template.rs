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
    counts: Vec<u64>,
    shots: u64,
}

impl TemplateLearner {
    /// A grid of `oversample` bins per sample over [lo, hi] samples around the peak.
    pub fn new(oversample: usize, lo: f64, hi: f64) -> TemplateLearner {
        let oversample = oversample.max(1);
        let bins = ((hi - lo) * oversample as f64).ceil() as usize + 1;
        TemplateLearner { oversample, lo, sums: vec![0.0; bins], counts: vec![0; bins], shots: 0 }
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
            if b >= 0.0 {
                self.sums[b as usize] += (v - mean_v) / amplitude_v;
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
        let mean: Vec<f64> = self.sums.iter().zip(&self.counts).map(|(s, &c)| s / c as f64).collect();
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
        let table: Vec<f64> = mean.iter().map(|v| v / h).collect();
        Ok(PulseConfig {
            model: PulseModel::Table,
            rise_time_s: 0.0,
            fwhm_s: 0.0,
            table_step_s: step * dt_s,
            table_first_s: (self.lo - peak_t) * dt_s,
            table,
        })
    }
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
        let learned = Shape::from_config(&cfg, 1e-9);
        // Timing uses the half-rise point of the shape it has, so compare the shapes aligned there.
        let shift = learned.half_rise_offset() - truth.half_rise_offset();
        for &t in &[-3.0, -1.0, 0.0, 0.5, 2.0, 6.0] {
            let (a, b) = (learned.value_and_slope(t + shift).0, truth.value_and_slope(t).0);
            assert!((a - b).abs() < 5e-3, "{t}: {a} vs {b}");
        }
        assert!(shift.abs() < 0.1, "{shift}");
        assert!((learned.fwhm() - Shape::Parametric(truth).fwhm()).abs() < 0.02);
    }

    #[test]
    fn too_few_shots_is_an_error() {
        let l = TemplateLearner::new(8, -8.0, 16.0);
        assert!(matches!(l.finish(1e-9), Err(TemplateError::TooFewShots { .. })));
    }
}
