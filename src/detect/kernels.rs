//! Detector kernels: matched filter (correlation with the unit-energy return
//! template) or plain threshold, local maxima above a Neyman-Pearson
//! threshold, and threshold upcrossings counted in the noise gates.
//!
//! Named `kernels` (not `detector`) because "detector" is also the
//! photodetector (`physics::detector`) and `pipeline::detect` is the stage:
//! these are the signal-detection kernels the stage runs.

use crate::dsp::correlate::Correlator;
use crate::dsp::pulse::Shape;
use std::ops::Range;

/// Detector output planned for one pulse shape.
#[derive(Debug, Clone)]
pub struct DetectorPlan {
    correlator: Correlator,
    /// Tap index of the template peak: output `p` is the template with its peak on sample `p`.
    peak_tap: usize,
    /// ‖p‖ of the unit-peak template: amplitude = output / norm.
    norm: f64,
    /// Lag-1 correlation of the output for white input noise.
    rho1: f64,
    /// Σ of the unit-energy taps: how a mean error enters the output.
    dc_gain: f64,
    padded: Vec<f64>,
    output: Vec<f64>,
}

impl DetectorPlan {
    /// Matched filter for `pulse`, for frames up to `max_samples` long.
    pub fn matched_filter(pulse: &Shape, max_samples: usize) -> DetectorPlan {
        let (taps, peak_tap) = pulse.template();
        Self::from_taps(taps, peak_tap, max_samples)
    }

    /// Plain threshold on the samples (a one-tap template).
    pub fn threshold(max_samples: usize) -> DetectorPlan {
        Self::from_taps(vec![1.0], 0, max_samples)
    }

    /// Matched filter for an arbitrary template (e.g. a whitened one): `taps`
    /// in correlation order, `peak_tap` the tap at the pulse peak. The taps are
    /// normalised to unit energy; [`norm`](Self::norm) keeps their ‖·‖.
    pub fn from_template(taps: Vec<f64>, peak_tap: usize, max_samples: usize) -> DetectorPlan {
        Self::from_taps(taps, peak_tap, max_samples)
    }

    fn from_taps(mut taps: Vec<f64>, peak_tap: usize, max_samples: usize) -> DetectorPlan {
        let norm = taps.iter().map(|t| t * t).sum::<f64>().sqrt();
        for t in &mut taps {
            *t /= norm;
        }
        let rho1 = taps.windows(2).map(|w| w[0] * w[1]).sum::<f64>();
        let dc_gain = taps.iter().sum::<f64>();
        let len = taps.len();
        DetectorPlan {
            correlator: Correlator::new(&taps, max_samples + len),
            peak_tap,
            norm,
            rho1,
            dc_gain,
            padded: Vec::with_capacity(max_samples + len),
            output: Vec::with_capacity(max_samples),
        }
    }

    /// Template length, samples.
    pub fn len(&self) -> usize {
        self.correlator.taps().len()
    }

    /// True for an empty template (never: kept for clippy's len/is_empty pairing).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// ‖p‖ of the unit-peak template.
    pub fn norm(&self) -> f64 {
        self.norm
    }

    /// Lag-1 correlation of the output in white noise.
    pub fn rho1(&self) -> f64 {
        self.rho1
    }

    /// Sum of the unit-energy taps (the output's gain for a constant offset).
    pub fn dc_gain(&self) -> f64 {
        self.dc_gain
    }

    /// The unit-energy taps.
    pub fn taps(&self) -> &[f64] {
        self.correlator.taps()
    }

    /// Tap index of the template peak.
    pub fn peak_tap(&self) -> usize {
        self.peak_tap
    }

    /// Runs the detector on `x - mean`, zero-padded so that output `p` (for
    /// every sample `p` of `x`) is the template centred with its peak on `p`.
    /// For white noise of sigma s the output has sigma s (unit-energy taps),
    /// less near the frame edges where the template is cut.
    pub fn run(&mut self, x: &[f64], mean: f64) -> &[f64] {
        let len = self.len();
        self.padded.clear();
        self.padded.resize(self.peak_tap, 0.0);
        self.padded.extend(x.iter().map(|v| v - mean));
        self.padded.resize(self.peak_tap + x.len() + (len - 1 - self.peak_tap), 0.0);
        self.correlator.correlate(&self.padded, &mut self.output);
        &self.output
    }

    /// As [`run`](Self::run), but only the outputs at `part` (positions in
    /// `x`, clamped to it) are computed, each bit for bit what `run` gives
    /// there; the others are NaN, so that a reader outside `part` cannot go
    /// unnoticed. Where the correlator cannot compute part of its output
    /// (the FFT method) every output is computed, as by `run`.
    pub fn run_part(&mut self, x: &[f64], mean: f64, part: Range<usize>) -> &[f64] {
        let len = self.len();
        self.padded.clear();
        self.padded.resize(self.peak_tap, 0.0);
        self.padded.extend(x.iter().map(|v| v - mean));
        self.padded.resize(self.peak_tap + x.len() + (len - 1 - self.peak_tap), 0.0);
        let part = part.start.min(x.len())..part.end.min(x.len());
        self.output.clear();
        self.output.resize(x.len(), f64::NAN);
        if !self.correlator.correlate_part(&self.padded, &mut self.output, part) {
            self.correlator.correlate(&self.padded, &mut self.output);
        }
        &self.output
    }

    /// After [`run`](Self::run) on an input of `x.len()` samples that has
    /// since changed only at `changed` (sample indices): brings the output up
    /// to date by recomputing just the outputs whose template reads those
    /// samples, bit for bit what `run(x, mean)` would give. False (nothing
    /// done; call `run`) where the correlator cannot recompute part of its
    /// output (the FFT method) or the last run was on another length.
    pub fn rerun_part(&mut self, x: &[f64], mean: f64, changed: Range<usize>) -> bool {
        let len = self.len();
        if self.padded.len() != x.len() + len - 1 || self.output.len() != x.len() || changed.end > x.len() {
            return false;
        }
        if changed.is_empty() {
            return true;
        }
        let pt = self.peak_tap;
        for (p, v) in self.padded[pt + changed.start..pt + changed.end].iter_mut().zip(&x[changed.clone()]) {
            *p = v - mean;
        }
        // Output p reads padded[p .. p + len], i.e. samples p − peak_tap .. p − peak_tap + len.
        let part = (changed.start + pt + 1).saturating_sub(len)..(changed.end + pt).min(x.len());
        self.correlator.correlate_part(&self.padded, &mut self.output, part)
    }

    /// The last output of [`run`](Self::run).
    pub fn output(&self) -> &[f64] {
        &self.output
    }

    /// Output positions whose template lies wholly inside `gate` (sample indices).
    pub fn positions_inside(&self, gate: &Range<usize>) -> Range<usize> {
        let lo = gate.start + self.peak_tap;
        let hi = (gate.end + self.peak_tap + 1).saturating_sub(self.len());
        lo..hi.max(lo)
    }
}

/// Local maxima of `y` inside `range` with `y > threshold`, strongest first.
/// A plateau counts once (its first sample).
pub fn local_maxima(y: &[f64], range: Range<usize>, threshold: f64, out: &mut Vec<usize>) {
    out.clear();
    let end = range.end.min(y.len());
    let mut p = range.start;
    while p < end {
        // Eight cells at a time, skipped whole where none is above (nearly
        // all of a range gate: one compare per cell, no branch per cell).
        if p + 8 <= end && !y[p..p + 8].iter().fold(false, |any, &v| any | (v > threshold)) {
            p += 8;
            continue;
        }
        let v = y[p];
        if v > threshold {
            let left_ok = p == 0 || y[p - 1] < v;
            let right_ok = p + 1 >= y.len() || y[p + 1] <= v;
            if left_ok && right_ok {
                out.push(p);
            }
        }
        p += 1;
    }
    out.sort_by(|&a, &b| y[b].total_cmp(&y[a]));
}

/// Local maxima of `y` inside `range` above a per-cell threshold
/// (`y[p] > threshold[p]`), strongest first; a plateau counts once.
pub fn local_maxima_above(y: &[f64], range: Range<usize>, threshold: &[f64], out: &mut Vec<usize>) {
    out.clear();
    let end = range.end.min(y.len()).min(threshold.len());
    for p in range.start..end {
        let v = y[p];
        // A NaN output or threshold is never a detection.
        if v.partial_cmp(&threshold[p]) != Some(std::cmp::Ordering::Greater) {
            continue;
        }
        let left_ok = p == 0 || y[p - 1] < v;
        let right_ok = p + 1 >= y.len() || y[p + 1] <= v;
        if left_ok && right_ok {
            out.push(p);
        }
    }
    out.sort_by(|&a, &b| y[b].total_cmp(&y[a]));
}

/// Excursions of `y` above a per-cell threshold that start inside `range`.
pub fn upcrossings_above(y: &[f64], range: Range<usize>, threshold: &[f64]) -> u64 {
    let end = range.end.min(y.len()).min(threshold.len());
    let mut count = 0;
    let mut above = false;
    for p in range.start.min(end)..end {
        let now = y[p] > threshold[p];
        if now && !above {
            count += 1;
        }
        above = now;
    }
    count
}

/// Number of excursions of `y` above `threshold` that start inside `range`
/// (an upcrossing, or the range opening above the threshold).
pub fn upcrossings(y: &[f64], range: Range<usize>, threshold: f64) -> u64 {
    let end = range.end.min(y.len());
    let s = &y[range.start.min(end)..end];
    // The first cell above opens an excursion; after it, each cell above
    // whose predecessor is not (pairwise, no carried state: vectorises).
    let Some(&first) = s.first() else {
        return 0;
    };
    (first > threshold) as u64 + s.windows(2).map(|w| ((w[1] > threshold) & !(w[0] > threshold)) as u64).sum::<u64>()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_is_indexed_by_peak_position_and_scaled_by_norm() {
        let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 2.0, sigma_fall: 5.0 });
        let mut plan = DetectorPlan::matched_filter(&pulse, 200);
        let mut x = vec![0.1; 200];
        for (i, v) in x.iter_mut().enumerate() {
            *v += 0.7 * pulse_value(&pulse, i as f64 - 80.0);
        }
        let y = plan.run(&x, 0.1).to_vec();
        let best = (0..y.len()).max_by(|&a, &b| y[a].total_cmp(&y[b])).unwrap();
        assert_eq!(best, 80);
        assert!((y[80] / plan.norm() - 0.7).abs() < 1e-9);
    }

    fn pulse_value(p: &Shape, t: f64) -> f64 {
        use crate::dsp::pulse::PulseShape;
        p.value_and_slope(t).0
    }

    #[test]
    fn maxima_and_crossings_match_a_cell_by_cell_scan() {
        let naive_maxima = |y: &[f64], range: Range<usize>, thr: f64| {
            let mut out: Vec<usize> = (range.start..range.end.min(y.len()))
                .filter(|&p| y[p] > thr && (p == 0 || y[p - 1] < y[p]) && (p + 1 >= y.len() || y[p + 1] <= y[p]))
                .collect();
            out.sort_by(|&a, &b| y[b].total_cmp(&y[a]));
            out
        };
        let naive_up = |y: &[f64], range: Range<usize>, thr: f64| {
            let s = &y[range.start.min(y.len())..range.end.min(y.len())];
            (0..s.len()).filter(|&i| s[i] > thr && (i == 0 || !(s[i - 1] > thr))).count() as u64
        };
        let mut state = 7u64;
        let y: Vec<f64> = (0..300)
            .map(|i| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let v = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) + (i as f64 * 0.05).sin();
                if i % 37 == 5 { f64::NAN } else if i % 29 == 3 { 0.7 } else { v }
            })
            .collect();
        let mut got = Vec::new();
        for range in [0..300, 1..299, 3..17, 0..8, 5..5, 250..400, 290..300] {
            for thr in [-2.0, 0.0, 0.5, 0.7, 1.2, 9.0] {
                local_maxima(&y, range.clone(), thr, &mut got);
                assert_eq!(got, naive_maxima(&y, range.clone(), thr), "{range:?} {thr}");
                assert_eq!(upcrossings(&y, range.clone(), thr), naive_up(&y, range.clone(), thr), "{range:?} {thr}");
            }
        }
    }

    #[test]
    fn maxima_and_crossings() {
        let y = [0.0, 2.0, 1.0, 3.0, 3.0, 0.0, 5.0];
        let mut m = Vec::new();
        local_maxima(&y, 0..7, 1.5, &mut m);
        assert_eq!(m, vec![6, 3, 1]);
        assert_eq!(upcrossings(&y, 0..7, 1.5), 3);
        assert_eq!(upcrossings(&y, 4..7, 1.5), 2);
    }

    #[test]
    fn a_partial_rerun_equals_a_full_run_bit_for_bit() {
        let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 3.0, sigma_fall: 5.0 });
        let mut plan = DetectorPlan::matched_filter(&pulse, 400);
        let mut x: Vec<f64> = (0..400).map(|i| ((i * 31 % 97) as f64 * 0.13).sin()).collect();
        plan.run(&x, 0.25);
        for (s, e) in [(0, 3), (100, 140), (390, 400), (0, 400)] {
            for (i, v) in x[s..e].iter_mut().enumerate() {
                *v -= 0.3 * (i as f64 * 0.2).cos();
            }
            if !plan.rerun_part(&x, 0.25, s..e) {
                // Only the FFT method (chosen on a CPU without a fast direct loop) cannot.
                assert_eq!(plan.correlator.method(), crate::dsp::correlate::CorrelationMethod::Fft);
                return;
            }
            let part = plan.output().to_vec();
            let full = plan.run(&x, 0.25).to_vec();
            assert!(part.iter().zip(&full).all(|(a, b)| a.to_bits() == b.to_bits()), "change {s}..{e}");
        }
        assert!(!plan.rerun_part(&x[..300], 0.25, 0..3), "another length needs a full run");
    }

    #[test]
    fn a_partial_run_equals_a_full_run_where_computed_and_is_nan_elsewhere() {
        let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 3.0, sigma_fall: 5.0 });
        let mut plan = DetectorPlan::matched_filter(&pulse, 400);
        for n in [400, 333, 37] {
            let x: Vec<f64> = (0..n).map(|i| ((i * 31 % 97) as f64 * 0.13).sin()).collect();
            let full = plan.run(&x, 0.25).to_vec();
            for (s, e) in [(0, 3), (100, 140), (n - 9, n), (n - 3, n + 5), (0, n), (7, 7)] {
                let (s, e) = (s.min(n), e.min(n + 5));
                let part = plan.run_part(&x, 0.25, s..e).to_vec();
                assert_eq!(part.len(), n);
                let fft = plan.correlator.method() == crate::dsp::correlate::CorrelationMethod::Fft;
                for (k, (a, b)) in part.iter().zip(&full).enumerate() {
                    if (s..e).contains(&k) || fft {
                        assert_eq!(a.to_bits(), b.to_bits(), "n {n}, part {s}..{e}, output {k}");
                    } else {
                        assert!(a.is_nan(), "n {n}, part {s}..{e}, output {k}");
                    }
                }
            }
        }
    }

    #[test]
    fn positions_inside_gate() {
        let plan = DetectorPlan::matched_filter(&Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 1.0, sigma_fall: 1.0 }), 100);
        // 9 taps, peak tap 4.
        assert_eq!(plan.len(), 9);
        assert_eq!(plan.positions_inside(&(0..20)), 4..16);
        assert!(plan.positions_inside(&(0..5)).is_empty());
    }
}
