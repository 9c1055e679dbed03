//! The error a timing method really makes on a pulse shape, measured by
//! Monte-Carlo against the *measured* signal-to-noise ratio, and used as the
//! method's bias correction and one-sigma uncertainty.
//!
//! Small-signal formulas (a crossing's σ = noise / slope, the Cramér–Rao
//! bound) describe an estimator whose error is small and linear in the noise.
//! Near the detection threshold that stops being true: the constant
//! fraction's level is taken from a noise-inflated peak and walks, a crossing
//! can be a noise crossing, a parabola through a flat matched-filter top
//! wanders. Every one of those effects is a function of the pulse shape, the
//! method and the SNR only (the error in samples is scale-free in the
//! amplitude), so it can be measured once per shape: pulses at log-uniform
//! true SNR from 0.5 to 3000 (those the detector would find), white Gaussian noise, uniform sub-sample phase,
//! through the very code the pipeline runs (detector peak, timing method,
//! phase-bias correction). The errors are binned by the SNR the method
//! *measures* (amplitude / σ: what a frame offers), and each bin keeps
//!
//! - the median error (a bias the pipeline subtracts), and
//! - a one-sigma width that covers: the larger of the 95 % half-width / 1.96
//!   and the 98 % half-width / 3, so that ±2σ holds about 95 % of the errors
//!   and ±3σ at least 98 % even where the errors have heavy tails.
//!
//! The sub-sample phase scatter that a bias table cannot remove (the constant
//! fraction's jumps) is inside the measured width.
//!
//! The same trials measure how much the shape-mismatch gap
//! ([`mismatch_gap`]: the samples' own constant-fraction crossing against
//! the fitted model's fraction point) scatters when the model *is* the
//! pulse: that scatter is noise (and the fit's position grid), already in
//! the method's width, and the pipeline takes it out of the gap's swing on
//! real data before the swing joins the sigma as a model-mismatch term. The table is deterministic
//! (fixed seed) and cached per (method, shape, fraction, detector): building
//! one costs tens of milliseconds.
//!
//! Leading-edge timing is not tabulated: its level is in volts, so its error
//! depends on the amplitude and the noise separately (the walk table's
//! business); it keeps the small-signal σ with the model's slope.

use crate::detect::kernels::DetectorPlan;
use crate::detect::phase::PhaseBias;
use crate::detect::pulse_timing::{mismatch_gap, time_pulse, ShapeFit, TimingInput};
use crate::dsp::pulse::{PulseShape, Shape};
use crate::scene::TimingMethod;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// Trials per table.
const TRIALS: usize = 6000;
/// True SNR range of the trials (peak amplitude / noise σ).
const SNR_MIN: f64 = 0.5;
/// See [`SNR_MIN`].
const SNR_MAX: f64 = 3000.0;
/// A trial counts only when its detector output reaches this many of its
/// own sigmas (unit-energy taps: the noise sigma; below every per-report
/// threshold the scenes use): a pulse too
/// weak to be detected is never timed by the pipeline either.
const DETECTION_FLOOR: f64 = 3.5;
/// Bins per decade of measured SNR.
const BINS_PER_DECADE: f64 = 6.0;
/// A bin needs this many errors to be kept.
const MIN_PER_BIN: usize = 80;
/// Fixed seed: the table, and so every report, is reproducible.
const SEED: u64 = 0x7f4a_7c15_e0d1_2b33;

/// Measured bias and one-sigma width of a timing method, by measured SNR.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorTable {
    /// The method's sub-sample phase bias, removed before the table applies.
    phase: Option<PhaseBias>,
    /// Bin centres, ln(measured SNR), ascending.
    ln_snr: Vec<f64>,
    /// Median error (estimate − truth) at each, samples.
    bias: Vec<f64>,
    /// One-sigma width at each, samples.
    sigma: Vec<f64>,
    /// RMS of the mismatch gap about its mean at each, on the model shape
    /// (noise only), samples.
    gap: Vec<f64>,
}

/// One measured trial: ln(measured SNR), error in samples, mismatch gap in
/// samples (NaN where the crossing failed).
type Trial = (f64, f64, f64);

impl ErrorTable {
    /// The table of `method` on `shape` (with `fraction`; on the matched
    /// filter's output when `matched`), from the cache or measured now.
    /// `None` for leading-edge timing and for shapes the methods cannot time
    /// noise-free (no finite support).
    pub fn get(method: TimingMethod, shape: &Shape, fraction: f64, matched: bool) -> Option<Arc<ErrorTable>> {
        if method == TimingMethod::LeadingEdge {
            return None;
        }
        static CACHE: OnceLock<Mutex<HashMap<String, Option<Arc<ErrorTable>>>>> = OnceLock::new();
        let key = format!("{method:?}|{fraction}|{matched}|{shape:?}");
        let cache = CACHE.get_or_init(|| Mutex::new(HashMap::new()));
        if let Some(t) = cache.lock().unwrap_or_else(|e| e.into_inner()).get(&key) {
            return t.clone();
        }
        let table = ErrorTable::measure(method, shape, fraction, matched).map(Arc::new);
        let mut map = cache.lock().unwrap_or_else(|e| e.into_inner());
        // A long-running server sees few shapes; a bound keeps a pathological client from growing it.
        if map.len() >= 256 {
            map.clear();
        }
        map.insert(key, table.clone());
        table
    }

    /// The tables of `method` and of its fallback, peak parabolic
    /// ([`ErrorTable::get`] each): measured on two threads at once when
    /// neither is cached (each is the same table whichever thread measures
    /// it), which halves a pipeline's start-up on a machine with a spare core.
    pub fn get_with_fallback(method: TimingMethod, shape: &Shape, fraction: f64, matched: bool) -> (Option<Arc<ErrorTable>>, Option<Arc<ErrorTable>>) {
        let fallback = TimingMethod::PeakParabolic;
        if method == fallback || method == TimingMethod::LeadingEdge {
            return (ErrorTable::get(method, shape, fraction, matched), ErrorTable::get(fallback, shape, fraction, matched));
        }
        std::thread::scope(|s| {
            let other = s.spawn(|| ErrorTable::get(fallback, shape, fraction, matched));
            let own = ErrorTable::get(method, shape, fraction, matched);
            let other = other.join().unwrap_or_else(|_| ErrorTable::get(fallback, shape, fraction, matched));
            (own, other)
        })
    }

    /// Measures the table (see the module documentation). Uncached: use
    /// [`ErrorTable::get`].
    pub fn measure(method: TimingMethod, shape: &Shape, fraction: f64, matched: bool) -> Option<ErrorTable> {
        let (lo, hi) = shape.support();
        if !(lo.is_finite() && hi.is_finite()) {
            return None;
        }
        let phase = PhaseBias::measure(method, shape, fraction, matched);
        let margin = (hi - lo).ceil() as usize + 16;
        let n = 3 * margin;
        let base = (margin as f64 - lo).ceil();
        let mut plan = if matched { DetectorPlan::matched_filter(shape, n) } else { DetectorPlan::threshold(n) };
        let norm = if matched { plan.norm() } else { 1.0 };
        let offset = shape.fraction_offset(fraction);
        let reach = (shape.fwhm() * 0.5).ceil().max(3.0) as usize;
        let mut rng = ChaCha8Rng::seed_from_u64(SEED);
        let mut x = vec![0.0; n];
        let mut trials: Vec<Trial> = Vec::with_capacity(TRIALS);
        let (ln_lo, ln_hi) = (SNR_MIN.ln(), SNR_MAX.ln());
        for _ in 0..TRIALS {
            let snr = (ln_lo + (ln_hi - ln_lo) * rng.random::<f64>()).exp();
            let peak_true = base + rng.random::<f64>();
            for (k, v) in x.iter_mut().enumerate() {
                let noise: f64 = rng.sample(StandardNormal);
                *v = snr * shape.value_and_slope(k as f64 - peak_true).0 + noise;
            }
            let y = plan.run(&x, 0.0);
            let near = peak_true.round() as usize;
            let peak = (near.saturating_sub(reach)..(near + reach + 1).min(n))
                .max_by(|&a, &b| y[a].total_cmp(&y[b]))
                .unwrap_or(near);
            if !(y[peak] >= DETECTION_FLOOR) {
                continue;
            }
            let input = TimingInput {
                x: &x,
                mean_v: 0.0,
                sigma_v: 1.0,
                y,
                norm,
                pulse: shape,
                peak,
                fraction,
                leading_edge_v: 0.5,
            };
            let mut t = time_pulse(method, &input);
            if let Some(pb) = phase.as_ref().filter(|pb| pb.is_smooth()) {
                t.index = pb.correct(t.index);
            }
            let measured = t.amplitude_v;
            if measured > 0.0 && t.index.is_finite() {
                // The gap as the pipeline measures it, on a shape that fits.
                let fit = ShapeFit::measure(&x, 0.0, 1.0, shape, t.index - offset);
                let gap = mismatch_gap(&input, &fit).unwrap_or(f64::NAN);
                trials.push((measured.ln(), t.index - (peak_true + offset), gap));
            }
        }
        let mut table = ErrorTable::from_trials(trials)?;
        table.phase = phase;
        Some(table)
    }

    /// Bins `trials` by measured SNR and keeps each full bin's median and width.
    fn from_trials(mut trials: Vec<Trial>) -> Option<ErrorTable> {
        trials.sort_by(|a, b| a.0.total_cmp(&b.0));
        let width = std::f64::consts::LN_10 / BINS_PER_DECADE;
        let mut table = ErrorTable {
            phase: None,
            ln_snr: Vec::new(),
            bias: Vec::new(),
            sigma: Vec::new(),
            gap: Vec::new(),
        };
        let mut start = 0;
        while start < trials.len() {
            let edge = (trials[start].0 / width).floor() * width + width;
            let end = start + trials[start..].partition_point(|t| t.0 < edge);
            let bin = &trials[start..end];
            if bin.len() >= MIN_PER_BIN {
                let mut e: Vec<f64> = bin.iter().map(|t| t.1).collect();
                let centre = bin.iter().map(|t| t.0).sum::<f64>() / bin.len() as f64;
                let bias = quantile(&mut e, 0.5);
                let mut dev: Vec<f64> = e.iter().map(|v| (v - bias).abs()).collect();
                let sigma = (quantile(&mut dev, 0.95) / 1.96).max(quantile(&mut dev, 0.98) / 3.0);
                // The gap's plain RMS about its mean: the pipeline subtracts
                // it from a running mean square, so like is taken from like.
                let gaps: Vec<f64> = bin.iter().map(|t| t.2).filter(|g| g.is_finite()).collect();
                let gap = if gaps.len() >= MIN_PER_BIN / 2 {
                    let m = gaps.iter().sum::<f64>() / gaps.len() as f64;
                    (gaps.iter().map(|g| (g - m) * (g - m)).sum::<f64>() / (gaps.len() - 1) as f64).sqrt()
                } else {
                    0.0
                };
                table.ln_snr.push(centre);
                table.bias.push(bias);
                table.sigma.push(sigma.max(f64::MIN_POSITIVE));
                table.gap.push(gap.max(f64::MIN_POSITIVE));
            }
            start = end;
        }
        (table.ln_snr.len() >= 2).then_some(table)
    }

    /// `index` as the method measured it at measured SNR `snr`, corrected
    /// (phase bias where smooth, then the table's bias), and its one-sigma
    /// width: (index, sigma), samples.
    pub fn correct(&self, index: f64, snr: f64) -> (f64, f64) {
        let index = match self.phase.as_ref().filter(|pb| pb.is_smooth()) {
            Some(pb) => pb.correct(index),
            None => index,
        };
        let (bias, sigma) = self.at(snr);
        (index - bias, sigma)
    }

    /// RMS over a uniform phase of the method's sub-sample phase bias on the
    /// model shape, samples (0 for methods without one). When the model does
    /// not fit the data its phase correction is wrong by about this much.
    pub fn phase_rms(&self) -> f64 {
        self.phase.as_ref().map_or(0.0, PhaseBias::rms)
    }

    /// Bias and one-sigma width, samples, at measured SNR `snr` (amplitude /
    /// noise σ): interpolated linearly in ln SNR (the width in ln width).
    /// Below the lowest bin both are held; above the highest the bias is held
    /// and the width follows a²/SNR² + f² fitted to the top two bins (a
    /// noise part falling as 1/SNR, a floor that does not).
    pub fn at(&self, snr: f64) -> (f64, f64) {
        let l = snr.max(f64::MIN_POSITIVE).ln();
        let n = self.ln_snr.len();
        let bias = if !(l > self.ln_snr[0]) {
            self.bias[0]
        } else if l >= self.ln_snr[n - 1] {
            self.bias[n - 1]
        } else {
            let i = self.ln_snr.partition_point(|&v| v <= l);
            let w = (l - self.ln_snr[i - 1]) / (self.ln_snr[i] - self.ln_snr[i - 1]);
            self.bias[i - 1] + w * (self.bias[i] - self.bias[i - 1])
        };
        (bias, self.width(&self.sigma, l))
    }

    /// RMS of the shape-mismatch gap ([`mismatch_gap`]) that noise alone
    /// gives at measured SNR `snr` when the model is the pulse, samples;
    /// interpolated as the width in [`ErrorTable::at`].
    pub fn gap_noise(&self, snr: f64) -> f64 {
        self.width(&self.gap, snr.max(f64::MIN_POSITIVE).ln())
    }

    /// A width column at ln SNR `l`: held below the lowest bin, linear in
    /// ln width between bins, a²/SNR² + f² from the top two bins above.
    fn width(&self, col: &[f64], l: f64) -> f64 {
        let n = self.ln_snr.len();
        if !(l > self.ln_snr[0]) {
            return col[0];
        }
        if l >= self.ln_snr[n - 1] {
            // σ² = a²/snr² + f²: a noise part falling as 1/SNR and a floor
            // (phase scatter) that does not, solved from the top two bins.
            let (r1, r2) = (self.ln_snr[n - 2].exp(), self.ln_snr[n - 1].exp());
            let (s1, s2) = (col[n - 2], col[n - 1]);
            let a2 = ((s1 * s1 - s2 * s2) / (1.0 / (r1 * r1) - 1.0 / (r2 * r2))).max(0.0);
            let f2 = (s2 * s2 - a2 / (r2 * r2)).max(0.0);
            let snr = l.exp();
            return (a2 / (snr * snr) + f2).sqrt().min(s2);
        }
        let i = self.ln_snr.partition_point(|&v| v <= l);
        let w = (l - self.ln_snr[i - 1]) / (self.ln_snr[i] - self.ln_snr[i - 1]);
        (col[i - 1].ln() + w * (col[i].ln() - col[i - 1].ln())).exp()
    }

    /// (measured SNR, bias, one-sigma width) of every bin, for reports and plots.
    pub fn rows(&self) -> impl Iterator<Item = (f64, f64, f64)> + '_ {
        (0..self.ln_snr.len()).map(|i| (self.ln_snr[i].exp(), self.bias[i], self.sigma[i]))
    }
}

/// The `q` quantile of `v` (nearest rank; reorders `v`).
fn quantile(v: &mut [f64], q: f64) -> f64 {
    let k = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    *v.select_nth_unstable_by(k, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::PulseConfig;

    fn return_shape() -> Shape {
        PulseConfig::default().shape(1e-9)
    }

    #[test]
    fn width_falls_with_snr_and_matches_the_crlb_at_high_snr() {
        let shape = return_shape();
        let t = ErrorTable::measure(TimingMethod::Ml, &shape, 0.5, true).expect("table");
        let rows: Vec<_> = t.rows().collect();
        assert!(rows.len() >= 10, "{rows:?}");
        // Width times SNR is the CRLB constant at high SNR: Σ s'² of the shape.
        let energy: f64 = (-200..400).map(|k| shape.value_and_slope(k as f64 + 0.3).1.powi(2)).sum();
        let (snr, _, sigma) = rows[rows.len() - 1];
        let ratio = sigma * snr * energy.sqrt();
        eprintln!("ml at SNR {snr:.0}: width / CRLB = {ratio:.3}");
        // 80+ errors per bin: the width is known to ~±15 %.
        assert!((0.8..1.25).contains(&ratio), "{ratio}");
        for w in rows.windows(2) {
            assert!(w[1].2 < w[0].2 * 1.1, "width does not fall: {rows:?}");
        }
    }

    #[test]
    fn above_the_table_the_width_keeps_falling_to_its_floor() {
        let shape = return_shape();
        let t = ErrorTable::measure(TimingMethod::PeakParabolic, &shape, 0.5, true).expect("table");
        let (top, _, s_top) = t.rows().last().unwrap();
        let (_, s10) = t.at(top * 10.0);
        assert!(s10 < s_top && s10 > 0.0, "{s_top} -> {s10}");
        let (_, s_low) = t.at(0.1);
        assert_eq!(s_low, t.rows().next().unwrap().2);
    }

    #[test]
    fn cached_tables_are_shared() {
        let shape = return_shape();
        let a = ErrorTable::get(TimingMethod::PeakGaussian, &shape, 0.5, true).unwrap();
        let b = ErrorTable::get(TimingMethod::PeakGaussian, &shape, 0.5, true).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert!(ErrorTable::get(TimingMethod::LeadingEdge, &shape, 0.5, false).is_none());
    }
}
