//! Sub-sample phase bias of the interpolating timing methods, measured on the
//! model shape and removed.
//!
//! A pulse a few samples wide is timed by interpolating between samples (a
//! linear crossing, a parabola through the matched-filter peak). The answer
//! then depends on where the samples fall on the pulse: for a pulse whose
//! true timing point lies a fraction φ of a sample after a sample instant the
//! estimate is off by a deterministic b(φ), up to a tenth of a sample for the
//! fast start pulse. With an asynchronous sample clock φ is uniform from shot
//! to shot and b(φ) shows up as extra scatter; with a locked clock it is a
//! fixed offset that changes when anything moves. Both go away when b is
//! known: it is measured here by running the very estimator on noise-free
//! copies of the scene's pulse shape at 256 phases, tabulated against the
//! *measured* fractional position (what a frame offers), and subtracted.
//! Model-based fitting (maximum likelihood) has no such bias and the leading
//! edge's bias depends on amplitude (the walk table's business): neither gets
//! a table.

use crate::detect::kernels::DetectorPlan;
use crate::detect::pulse_timing::{time_pulse, TimingInput};
use crate::dsp::pulse::{PulseShape, Shape};
use crate::scene::TimingMethod;

/// Neighbouring table entries further apart than this (samples) are a jump, not a slope.
const JUMP: f64 = 0.004;

/// Phases measured per sample period.
const PHASES: usize = 256;

/// b(measured fractional position), samples, for one method and shape.
#[derive(Debug, Clone, PartialEq)]
pub struct PhaseBias {
    /// Measured fractional positions in [0, 1), ascending.
    frac: Vec<f64>,
    /// Bias (estimate − truth) at each, samples.
    bias: Vec<f64>,
}

impl PhaseBias {
    /// Measures the bias of `method` (with `fraction`, on the matched-filter
    /// output when `matched`, else on the samples) for `shape`. `None` for
    /// methods without a phase bias to remove (maximum likelihood, leading
    /// edge), or if the estimator fails on the noise-free shape.
    pub fn measure(method: TimingMethod, shape: &Shape, fraction: f64, matched: bool) -> Option<PhaseBias> {
        if matches!(method, TimingMethod::Ml | TimingMethod::LeadingEdge) {
            return None;
        }
        let (lo, hi) = shape.support();
        if !(lo.is_finite() && hi.is_finite()) {
            return None;
        }
        let margin = (hi - lo).ceil() as usize + 16;
        let n = 3 * margin;
        let base = (margin as f64 - lo).ceil();
        let mut plan = if matched { DetectorPlan::matched_filter(shape, n) } else { DetectorPlan::threshold(n) };
        let norm = if matched { plan.norm() } else { 1.0 };
        let offset = shape.fraction_offset(fraction);
        let mut pts = Vec::with_capacity(PHASES);
        let mut x = vec![0.0; n];
        for j in 0..PHASES {
            let peak_true = base + j as f64 / PHASES as f64;
            for (k, v) in x.iter_mut().enumerate() {
                *v = shape.value_and_slope(k as f64 - peak_true).0;
            }
            let y = plan.run(&x, 0.0).to_vec();
            let near = peak_true.round() as usize;
            let peak = (near.saturating_sub(3)..(near + 4).min(n)).max_by(|&a, &b| y[a].total_cmp(&y[b]))?;
            let t = time_pulse(
                method,
                &TimingInput {
                    x: &x,
                    mean_v: 0.0,
                    sigma_v: 1e-6,
                    y: &y,
                    norm,
                    pulse: shape,
                    peak,
                    fraction,
                    leading_edge_v: 0.5,
                },
            );
            if t.fallback || !t.index.is_finite() {
                return None;
            }
            let b = t.index - (peak_true + offset);
            if b.abs() >= 0.5 {
                // Not a small sub-sample effect: leave the estimator alone.
                return None;
            }
            pts.push((t.index.rem_euclid(1.0), b));
        }
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        Some(PhaseBias {
            frac: pts.iter().map(|p| p.0).collect(),
            bias: pts.iter().map(|p| p.1).collect(),
        })
    }

    /// The bias at measured index `index` (periodic linear interpolation in
    /// its fractional part), samples.
    pub fn bias_at(&self, index: f64) -> f64 {
        let f = index.rem_euclid(1.0);
        let n = self.frac.len();
        let i = self.frac.partition_point(|&v| v <= f);
        // Neighbours with wrap-around: (i-1, i) modulo n, positions unwrapped.
        let (a, fa) = if i == 0 { (n - 1, self.frac[n - 1] - 1.0) } else { (i - 1, self.frac[i - 1]) };
        let (b, fb) = if i == n { (0, self.frac[0] + 1.0) } else { (i, self.frac[i]) };
        let w = if fb > fa { (f - fa) / (fb - fa) } else { 0.0 };
        if (self.bias[b] - self.bias[a]).abs() > JUMP {
            // A discontinuity (the estimator switched samples): the nearer side.
            return if w < 0.5 { self.bias[a] } else { self.bias[b] };
        }
        self.bias[a] + w * (self.bias[b] - self.bias[a])
    }

    /// `index` with the bias removed.
    pub fn correct(&self, index: f64) -> f64 {
        index - self.bias_at(index)
    }

    /// True when the bias is a continuous function of the measured position
    /// (no neighbouring entries a jump apart), so [`correct`](Self::correct)
    /// removes it. An estimator that switches samples at some phase (the
    /// constant fraction's peak-height fit) jumps there, and near the jump
    /// the measured position no longer tells the phase: its bias is better
    /// carried as uncertainty ([`rms`](Self::rms)) than subtracted.
    pub fn is_smooth(&self) -> bool {
        let n = self.bias.len();
        (0..n).all(|i| (self.bias[(i + 1) % n] - self.bias[i]).abs() <= JUMP)
    }

    /// RMS of the bias over a uniform phase, samples (the scatter an
    /// asynchronous clock adds when the bias is not removed).
    pub fn rms(&self) -> f64 {
        (self.bias.iter().map(|b| b * b).sum::<f64>() / self.bias.len() as f64).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dsp::pulse::Pulse;

    #[test]
    fn removes_the_bias_of_a_fast_pulse_at_every_phase() {
        // The start pulse of the prototype: 1.8 ns rise, 5 ns FWHM at 1 ns sampling.
        let cfg = crate::scene::PulseConfig { rise_time_s: 1.8e-9, fwhm_s: 5e-9, ..Default::default() };
        let shape = Shape::Parametric(cfg.pulse(1e-9));
        for (method, matched) in [
            (TimingMethod::ConstantFraction, false),
            (TimingMethod::PeakParabolic, true),
            (TimingMethod::PeakGaussian, true),
        ] {
            let pb = PhaseBias::measure(method, &shape, 0.5, matched).expect("measurable");
            assert!(pb.is_smooth(), "{method:?}");
            let cf = method == TimingMethod::ConstantFraction;
            // Off-grid phases (not the 64 of the table): the corrected estimate is within 2e-3 samples.
            let mut plan = if matched { DetectorPlan::matched_filter(&shape, 200) } else { DetectorPlan::threshold(200) };
            let norm = if matched { plan.norm() } else { 1.0 };
            let (mut worst, mut ss_raw, mut ss) = (0.0f64, 0.0, 0.0);
            for j in 0..37 {
                let peak_true = 80.0 + (j as f64 + 0.31) / 37.0;
                let x: Vec<f64> = (0..200).map(|k| 0.7 * shape.value_and_slope(k as f64 - peak_true).0).collect();
                let y = plan.run(&x, 0.0).to_vec();
                let peak = (75..90).max_by(|&a, &b| y[a].total_cmp(&y[b])).unwrap();
                let t = time_pulse(
                    method,
                    &TimingInput { x: &x, mean_v: 0.0, sigma_v: 1e-6, y: &y, norm, pulse: &shape, peak, fraction: 0.5, leading_edge_v: 0.5 },
                );
                let truth = peak_true + shape.fraction_offset(0.5);
                let e = pb.correct(t.index) - truth;
                worst = worst.max(e.abs());
                ss_raw += (t.index - truth).powi(2);
                ss += e * e;
            }
            let (rms_raw, rms) = ((ss_raw / 37.0).sqrt(), (ss / 37.0).sqrt());
            eprintln!("{method:?}: phase bias rms {rms_raw:.5} -> {rms:.5} samples, worst after {worst:.4}");
            if cf {
                // The crossing and the peak height are read off the model
                // between samples (`pulse_timing::between_samples`): the
                // estimator itself leaves almost nothing to the table (it
                // left a hundredth of a sample, with jumps, when it read
                // them by straight lines and a bare parabola).
                assert!(rms_raw < 1e-3 && pb.rms() < 1e-3, "{method:?}: rms {rms_raw}, table {}", pb.rms());
            } else {
                assert!(rms < 0.25 * rms_raw, "{method:?}: rms {rms_raw} -> {rms}");
            }
            assert!(worst < 2e-3, "{method:?}: corrected error {worst} samples");
            assert!(pb.rms() > 0.0);
        }
    }

    #[test]
    fn model_fits_have_no_table() {
        let shape = Shape::Parametric(Pulse { sigma_rise: 2.0, sigma_fall: 5.0 });
        assert!(PhaseBias::measure(TimingMethod::Ml, &shape, 0.5, true).is_none());
        assert!(PhaseBias::measure(TimingMethod::LeadingEdge, &shape, 0.5, false).is_none());
    }
}
