//! Detector kernels: matched filter (correlation with the unit-energy return
//! template) or plain threshold, local maxima above a Neyman-Pearson
//! threshold, and threshold upcrossings counted in the noise gates.
//!
//! Named `kernels` (not `detector`) because "detector" is also the
//! photodetector (`physics::detector`) and `pipeline::detect` is the stage:
//! these are the signal-detection kernels the stage runs.

use crate::dsp::correlate::{correlate_valid_part, CorrelationMethod, Correlator};
use crate::dsp::correlate_codes;
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
    /// The taps as 16-bit integers: every tap is `q[j]·scale` (the f64
    /// taps are those products), so that a channel of integer codes can be
    /// filtered exactly in integers ([`run_codes`](Self::run_codes)).
    code_taps: CodeTaps,
    /// The input, x − mean, with the template's reach of zeros either side
    /// (after `run_codes`, only once `rerun_part` wrote it: `padded_pending`).
    padded: Vec<f64>,
    output: Vec<f64>,
    /// The last run was [`run_codes`](Self::run_codes)'s.
    codes_ran: bool,
    /// `run_codes` left `padded` unwritten (the integer filter reads the
    /// codes, and only [`rerun_part`](Self::rerun_part) reads `padded`,
    /// on frames where the resolver takes a pulse out): `rerun_part`
    /// writes it first, from the input it is given.
    padded_pending: bool,
}

/// Longest template [`DetectorPlan::run_codes`] filters in integers where
/// the f64 filter is the FFT's: on 2500 samples (`cargo bench --bench kernels
/// -- correlate`) the integer filter takes 2.40 µs at 64 taps and 10.4 µs at
/// 300 (about 0.035 µs a tap), the FFT 7.4–8.2 µs at either, so up to here
/// the integer filter is the faster (and exact).
const CODES_OVER_FFT_TAPS: usize = 192;

/// A template's taps quantised to i16, for the exact integer filter.
#[derive(Debug, Clone)]
struct CodeTaps {
    /// The taps, largest |q| in [2^14, 2^15), padded with a zero to an even count.
    q: Vec<i16>,
    /// 1/‖q‖: tap j of the unit-energy filter is `q[j]·scale`.
    scale: f64,
    /// Σ|q|: the integer sums are exact while Σ|q|·max|code| ≤ i32::MAX.
    abs_sum: i64,
    /// prefix[j] = Σ_{i<j} q[i] (length q.len() + 1): the taps over a frame edge.
    prefix: Vec<i64>,
    /// The codes, zero-padded as `padded` is.
    codes: Vec<i16>,
    /// The integer sums.
    sums: Vec<i32>,
}

impl CodeTaps {
    /// Quantises unit-energy `taps`: scaled by the power of two that puts
    /// the largest in [2^14, 2^15), rounded. None for taps that are all zero
    /// or not finite.
    fn quantise(taps: &[f64]) -> Option<CodeTaps> {
        let max = taps.iter().fold(0.0f64, |m, t| m.max(t.abs()));
        if !(max > 0.0 && max.is_finite()) {
            return None;
        }
        // 2^e·max in [2^14, 2^15): rounding keeps every |q| ≤ 2^15 - 1 < i16::MAX.
        let e = (f64::from(i16::MAX) / max).log2().floor() as i32;
        let mut step = 2f64.powi(e);
        if max * step >= 32767.5 {
            step *= 0.5;
        }
        let mut q: Vec<i16> = taps.iter().map(|t| (t * step).round() as i16).collect();
        if q.len() % 2 == 1 {
            q.push(0);
        }
        let energy: i64 = q.iter().map(|&v| i64::from(v) * i64::from(v)).sum();
        let mut prefix = Vec::with_capacity(q.len() + 1);
        prefix.push(0i64);
        for &v in &q {
            prefix.push(prefix.last().expect("pushed above") + i64::from(v));
        }
        Some(CodeTaps {
            abs_sum: q.iter().map(|&v| i64::from(v).abs()).sum(),
            scale: 1.0 / (energy as f64).sqrt(),
            q,
            prefix,
            codes: Vec::new(),
            sums: Vec::new(),
        })
    }
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
        // The filter's taps are the template quantised to 16 bits (a relative
        // step of 2^-15 of the largest tap; the output's SNR loss is below
        // 1e-8), renormalised to unit energy: the same filter on integer codes
        // and on f64 samples, every statistic below taken from those taps.
        let code_taps = CodeTaps::quantise(&taps).unwrap_or_else(|| CodeTaps {
            q: Vec::new(),
            scale: 0.0,
            abs_sum: 0,
            prefix: vec![0],
            codes: Vec::new(),
            sums: Vec::new(),
        });
        if !code_taps.q.is_empty() {
            for (t, &v) in taps.iter_mut().zip(&code_taps.q) {
                *t = f64::from(v) * code_taps.scale;
            }
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
            code_taps,
            padded: Vec::with_capacity(max_samples + len),
            output: Vec::with_capacity(max_samples),
            codes_ran: false,
            padded_pending: false,
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
        self.pad(x, mean);
        self.correlator.correlate(&self.padded, &mut self.output);
        self.codes_ran = false;
        &self.output
    }

    /// As [`run`](Self::run) on `x`, where `x[i]` is `codes[i]·g + o` (the
    /// channel's decode): the correlation runs exactly on the integer codes
    /// (`Σ q[j]·code` in i32) and the output is `scale·(g·Σ + (o − mean)·Σq)`.
    /// It differs from what `run` gives by rounding only: the f64 filter's
    /// (the direct sums round at every tap, a few ulp of the terms' scale
    /// |g·Σ| and |(o − mean)·Σq|; the FFT's rounding scales with the
    /// block's norm). False (nothing done; call `run`) where the sums might not
    /// fit an i32 (Σ|q|·max|code| > i32::MAX: with a 64-tap template, codes
    /// beyond about 12 bits; wider templates allow fewer), the f64 filter is
    /// the FFT's and the template longer than [`CODES_OVER_FFT_TAPS`] (there
    /// the FFT is the faster), |g| or |o| exceeds 1e300 (the noise stage's
    /// limit for codes that decode to finite volts) or `mean` is not finite.
    /// The f64 input (x − mean, padded) is not written here: the integer
    /// filter does not read it. [`rerun_part`](Self::rerun_part) writes it
    /// from the x and mean it is given, which must then equal this run's
    /// x − mean bit for bit outside the samples it names as changed (the
    /// resolver's residual, x − mean less the pulses it took out, with mean
    /// 0, does), and recomputes the outputs it is asked for as the direct
    /// f64 filter would (the others keep this run's values).
    pub fn run_codes(&mut self, x: &[f64], codes: &[i16], g: f64, o: f64, mean: f64) -> bool {
        let ct = &mut self.code_taps;
        let faster = match self.correlator.method() {
            CorrelationMethod::Direct => true,
            CorrelationMethod::Fft => ct.q.len() <= CODES_OVER_FFT_TAPS,
        };
        if ct.q.is_empty()
            || !faster
            || codes.len() != x.len()
            || x.is_empty()
            // The noise stage's test for codes that decode to finite volts
            // (beyond it, samples it replaced are not the codes' decode).
            || !(g.abs() <= 1e300 && o.abs() <= 1e300 && mean.is_finite())
        {
            return false;
        }
        let (lo, hi) = crate::math::code_stats::code_min_max(&[codes]).map_or((0, 0), |(lo, hi)| (lo.min(0), hi.max(0)));
        let max_code = i64::from(lo).abs().max(i64::from(hi).abs());
        if ct.abs_sum.saturating_mul(max_code) > correlate_codes::EXACT_LIMIT {
            return false;
        }
        let (n, len, pt) = (x.len(), self.correlator.taps().len(), self.peak_tap);
        // `padded` is written only if `rerun_part` needs it.
        self.padded_pending = true;
        let ql = ct.q.len();
        ct.codes.clear();
        ct.codes.resize(pt, 0);
        ct.codes.extend_from_slice(codes);
        ct.codes.resize(n + ql - 1, 0);
        // Every output is written by the filter: only the length needs setting.
        ct.sums.resize(n, 0);
        correlate_codes::correlate_valid(&ct.q, &ct.codes, &mut ct.sums);
        let (a, b) = (ct.scale * g, ct.scale * (o - mean));
        let total = ct.prefix[ql] as f64;
        self.output.clear();
        self.output.extend(ct.sums.iter().map(|&v| a * f64::from(v) + b * total));
        // Output p reads code p + j - pt for tap j: near the edges only the
        // taps over the frame's codes carry the constant (o - mean).
        let taps_in = |p: usize| {
            let first = pt.saturating_sub(p).min(ql);
            let end = (n + pt - p).min(ql);
            (ct.prefix[end.max(first)] - ct.prefix[first]) as f64
        };
        let edge = pt.min(n);
        for p in (0..edge).chain(n.saturating_sub(len - 1 - pt).max(edge)..n) {
            self.output[p] = a * f64::from(ct.sums[p]) + b * taps_in(p);
        }
        self.codes_ran = true;
        true
    }

    /// As [`run`](Self::run), but only the outputs at `part` (positions in
    /// `x`, clamped to it) are computed, each bit for bit what `run` gives
    /// there; the others are NaN, so that a reader outside `part` cannot go
    /// unnoticed. Where the correlator cannot compute part of its output
    /// (the FFT method) every output is computed, as by `run`.
    pub fn run_part(&mut self, x: &[f64], mean: f64, part: Range<usize>) -> &[f64] {
        self.pad(x, mean);
        let part = part.start.min(x.len())..part.end.min(x.len());
        self.output.clear();
        self.output.resize(x.len(), f64::NAN);
        if !self.correlator.correlate_part(&self.padded, &mut self.output, part) {
            self.correlator.correlate(&self.padded, &mut self.output);
        }
        self.codes_ran = false;
        &self.output
    }

    /// After [`run`](Self::run) (or [`run_codes`](Self::run_codes)) on an
    /// input of `x.len()` samples that has since changed only at `changed`
    /// (sample indices): brings the output up to date by recomputing just
    /// the outputs whose template reads those samples, each bit for bit what
    /// `run(x, mean)` would give there with the direct method (after
    /// `run_codes` the others keep its values, equal to `run`'s to
    /// rounding). False (nothing done; call `run`) after `run` with the FFT
    /// method (an FFT block's outputs depend on the whole block), or where
    /// the last run was on another length.
    pub fn rerun_part(&mut self, x: &[f64], mean: f64, changed: Range<usize>) -> bool {
        let len = self.len();
        if self.padded_pending && self.output.len() == x.len() {
            // Outside `changed` x − mean is the input `run_codes` had (the
            // contract), inside it is what is written below anyway.
            self.pad(x, mean);
        }
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
        if self.correlator.correlate_part(&self.padded, &mut self.output, part.clone()) {
            return true;
        }
        // An FFT plan's output came from the integer filter: its outputs
        // are each their own sum, and those recomputed are the direct sums.
        if self.codes_ran && !part.is_empty() {
            correlate_valid_part(self.correlator.taps(), &self.padded, &mut self.output, part);
        }
        self.codes_ran
    }

    /// Writes the input x − mean into `padded`, with the template's reach
    /// of zeros either side.
    fn pad(&mut self, x: &[f64], mean: f64) {
        let (len, pt) = (self.len(), self.peak_tap);
        self.padded.clear();
        self.padded.resize(pt, 0.0);
        self.padded.extend(x.iter().map(|v| v - mean));
        self.padded.resize(pt + x.len() + (len - 1 - pt), 0.0);
        self.padded_pending = false;
    }

    /// Hands the last output over into `out` without a copy: the two
    /// buffers are swapped and the plan's (what `out` held) is emptied, so
    /// [`rerun_part`](Self::rerun_part) declines until the next run, which
    /// refills it.
    pub fn take_output(&mut self, out: &mut Vec<f64>) {
        std::mem::swap(&mut self.output, out);
        self.output.clear();
    }

    /// The last output of [`run`](Self::run), [`run_codes`](Self::run_codes)
    /// or [`run_part`](Self::run_part), as [`rerun_part`](Self::rerun_part)
    /// brought it up to date; empty after [`take_output`](Self::take_output).
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
    fn the_taps_are_the_template_quantised_to_sixteen_bits_at_unit_energy() {
        for (rise, fall) in [(3.0, 5.0), (0.4, 0.9), (20.0, 40.0)] {
            let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: rise, sigma_fall: fall });
            let plan = DetectorPlan::matched_filter(&pulse, 400);
            let ct = &plan.code_taps;
            let max = ct.q.iter().map(|v| i32::from(*v).abs()).max().unwrap();
            assert!((1 << 14..1 << 15).contains(&max), "largest tap {max}");
            for (t, &q) in plan.taps().iter().zip(&ct.q) {
                assert_eq!(t.to_bits(), (f64::from(q) * ct.scale).to_bits());
            }
            let energy: f64 = plan.taps().iter().map(|t| t * t).sum();
            assert!((energy - 1.0).abs() < 1e-14, "{energy}");
            // Each tap within half a step (2^-15 of the largest) of the exact unit-energy template.
            let (exact, _) = pulse.template();
            let norm = exact.iter().map(|t| t * t).sum::<f64>().sqrt();
            let top = exact.iter().fold(0.0f64, |m, t| m.max(t.abs())) / norm;
            for (t, e) in plan.taps().iter().zip(&exact) {
                assert!((t - e / norm).abs() <= top * 2f64.powi(-14), "{t} against {}", e / norm);
            }
        }
        // One tap (the plain threshold) stays exactly 1.
        assert_eq!(DetectorPlan::threshold(10).taps(), &[1.0]);
    }

    #[test]
    fn the_filter_on_integer_codes_is_the_filter_on_their_volts() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (rise, fall) in [(3.0, 5.0), (2.0, 9.0), (0.5, 0.7)] {
            let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: rise, sigma_fall: fall });
            let mut plan = DetectorPlan::matched_filter(&pulse, 3000);
            let len = plan.len();
            for n in [2500, 333, len + 1, len / 2 + 1, 1] {
                for (g, o, mean) in [(1.0 / 4096.0, 0.0, 0.0013), (3.7e-5, 0.41, 0.4102), (0.01, -2.5, -2.0)] {
                    let codes: Vec<i16> = (0..n).map(|_| rng.random_range(-2048..=2047)).collect();
                    let x: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
                    let want = plan.run(&x, mean).to_vec();
                    assert!(plan.run_codes(&x, &codes, g, o, mean), "{n} samples");
                    let got = plan.output().to_vec();
                    assert_eq!(got.len(), want.len());
                    // The f64 filter rounds at each of its taps: ulps of the terms' scale.
                    let scale = x.iter().map(|v| (v - mean).abs()).fold(0.0, f64::max) * len as f64;
                    for (p, (a, b)) in got.iter().zip(&want).enumerate() {
                        assert!((a - b).abs() <= 1e-14 * scale, "{n} samples, output {p}: {a} against {b}");
                    }
                    // The plan's input is left as `run` leaves it: a partial rerun works on it.
                    if plan.rerun_part(&x, mean, 0..1) {
                        assert!(plan.output().iter().zip(&want).all(|(a, b)| (a - b).abs() <= 1e-14 * scale));
                    }
                }
            }
        }
    }

    #[test]
    fn an_fft_plan_filters_codes_in_integers_up_to_its_tap_limit_and_reruns_parts() {
        use crate::dsp::correlate::CorrelationMethod;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        let (n, g, o, mean) = (2500, 1.0 / 128.0, 0.05, 0.052);
        let codes: Vec<i16> = (0..n).map(|_| rng.random_range(-128..=127)).collect();
        let x: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
        let mut seen = (false, false);
        for (rise, fall) in [(4.0, 9.0), (6.0, 14.0), (12.0, 30.0), (30.0, 60.0)] {
            let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: rise, sigma_fall: fall });
            let mut plan = DetectorPlan::matched_filter(&pulse, n);
            if plan.correlator.method() != CorrelationMethod::Fft {
                continue;
            }
            let len = plan.len();
            let want = plan.run(&x, mean).to_vec();
            let ran = plan.run_codes(&x, &codes, g, o, mean);
            assert_eq!(ran, len <= CODES_OVER_FFT_TAPS, "{len} taps");
            if !ran {
                seen.1 = true;
                // After the FFT's own run a part cannot be recomputed.
                assert!(!plan.rerun_part(&x, mean, 0..1));
                continue;
            }
            // Nor after an FFT run (full or partial) that follows an integer one.
            plan.run(&x, mean);
            assert!(!plan.rerun_part(&x, mean, 0..1), "{len} taps: after run");
            assert!(plan.run_codes(&x, &codes, g, o, mean));
            plan.run_part(&x, mean, 0..10);
            assert!(!plan.rerun_part(&x, mean, 0..1), "{len} taps: after run_part");
            assert!(plan.run_codes(&x, &codes, g, o, mean));
            seen.0 = true;
            let scale = x.iter().map(|v| (v - mean).abs()).fold(0.0, f64::max) * len as f64;
            for (p, (a, b)) in plan.output().iter().zip(&want).enumerate() {
                assert!((a - b).abs() <= 1e-13 * scale, "{len} taps, output {p}: {a} against {b}");
            }
            // Samples changed after the integer run: the outputs that read them
            // are recomputed (direct sums), the FFT's run of the changed
            // samples agrees to rounding, and no other output moves.
            let mut y = x.clone();
            y[1200..1210].iter_mut().for_each(|v| *v += 0.3);
            let before = plan.output().to_vec();
            assert!(plan.rerun_part(&y, mean, 1200..1210), "{len} taps");
            let after = plan.output().to_vec();
            let full = plan.run(&y, mean).to_vec();
            let reads = (1200 + plan.peak_tap + 1 - len)..(1210 + plan.peak_tap);
            for p in 0..n {
                if reads.contains(&p) {
                    assert!((after[p] - full[p]).abs() <= 1e-13 * scale, "{len} taps, output {p}");
                } else {
                    assert_eq!(after[p].to_bits(), before[p].to_bits(), "{len} taps, output {p} moved");
                }
            }
        }
        assert!(seen.0 && seen.1, "the shapes gave an FFT plan on each side of the limit: {seen:?}");
    }

    #[test]
    fn codes_too_wide_for_exact_sums_fall_back_to_the_f64_filter() {
        let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 3.0, sigma_fall: 5.0 });
        let mut plan = DetectorPlan::matched_filter(&pulse, 400);
        let mut codes = vec![0i16; 400];
        let x = vec![0.0; 400];
        assert!(plan.run_codes(&x, &codes, 1e-3, 0.0, 0.0));
        codes[200] = i16::MIN;
        assert!(!plan.run_codes(&x, &codes, 1e-3, 0.0, 0.0), "full-scale 16-bit codes");
        codes[200] = 0;
        assert!(!plan.run_codes(&x, &codes, f64::NAN, 0.0, 0.0), "a scale that is not finite");
        // A scale the noise stage would not decode to finite volts.
        assert!(!plan.run_codes(&x, &codes, 1e305, 0.0, 0.0), "a scale beyond 1e300");
        assert!(!plan.run_codes(&x, &codes, 1e-3, -2e300, 0.0), "an offset beyond 1e300");
        assert!(!plan.run_codes(&x[..399], &codes, 1e-3, 0.0, 0.0), "codes that are not the samples");
    }

    #[test]
    fn a_rerun_on_the_residual_after_the_integer_filter_is_the_rerun_after_the_f64_filter() {
        // The resolver's calls: run_codes(x, mean), then rerun_part on its
        // residual (x − mean less a pulse, mean 0). run_codes leaves the
        // padded input to rerun_part, which writes it from the residual;
        // after `run` it was written from x − mean up front. The outputs
        // brought up to date are the same bits either way, for a direct and
        // an FFT plan, and the others keep each run's values.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(13);
        let (n, g, o, mean) = (2500, 1.0 / 2048.0, 0.01, 0.0123);
        let codes: Vec<i16> = (0..n).map(|_| rng.random_range(-200..=200)).collect();
        let x: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
        let mut residual: Vec<f64> = x.iter().map(|v| v - mean).collect();
        residual[1200..1210].iter_mut().for_each(|v| *v -= 0.3);
        let mut seen = (false, false);
        for (rise, fall) in [(3.0, 5.0), (12.0, 30.0)] {
            let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: rise, sigma_fall: fall });
            let (mut coded, mut plain) = (DetectorPlan::matched_filter(&pulse, n), DetectorPlan::matched_filter(&pulse, n));
            if !coded.run_codes(&x, &codes, g, o, mean) {
                continue;
            }
            let before = coded.output().to_vec();
            assert!(coded.rerun_part(&residual, 0.0, 1200..1210), "{} taps", coded.len());
            plain.run(&x, mean);
            let len = coded.len();
            let reads = (1200 + coded.peak_tap + 1 - len)..(1210 + coded.peak_tap);
            let mut want = plain.output().to_vec();
            if plain.rerun_part(&residual, 0.0, 1200..1210) {
                seen.0 = true;
                want = plain.output().to_vec();
            } else {
                // An FFT plan recomputes no part after its own run: the
                // direct sums over its input with the residual written in.
                seen.1 = true;
                plain.padded[plain.peak_tap + 1200..plain.peak_tap + 1210].copy_from_slice(&residual[1200..1210]);
                correlate_valid_part(plain.correlator.taps(), &plain.padded, &mut want, reads.clone());
            }
            for p in 0..n {
                if reads.contains(&p) {
                    assert_eq!(coded.output()[p].to_bits(), want[p].to_bits(), "{len} taps, output {p}");
                } else {
                    assert_eq!(coded.output()[p].to_bits(), before[p].to_bits(), "{len} taps, output {p} moved");
                }
            }
        }
        assert!(seen.0 && seen.1, "a direct and an FFT plan: {seen:?}");
    }

    #[test]
    fn a_taken_output_is_handed_over_and_leaves_no_stale_rerun() {
        let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 3.0, sigma_fall: 5.0 });
        let mut plan = DetectorPlan::matched_filter(&pulse, 400);
        let codes: Vec<i16> = (0..400).map(|i| ((i * 37) % 23) as i16 - 11).collect();
        let x: Vec<f64> = codes.iter().map(|&c| f64::from(c) * 1e-3).collect();
        assert!(plan.run_codes(&x, &codes, 1e-3, 0.0, 0.0));
        let want = plan.output().to_vec();
        let mut out = vec![7.0; 3];
        plan.take_output(&mut out);
        assert_eq!(out, want, "the output, handed over");
        assert!(plan.output().is_empty());
        assert!(!plan.rerun_part(&x, 0.0, 100..110), "nothing to bring up to date");
        assert!(plan.run_codes(&x, &codes, 1e-3, 0.0, 0.0));
        assert_eq!(plan.output(), &want[..], "the next run refills it");
        assert!(plan.rerun_part(&x, 0.0, 100..110));
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
