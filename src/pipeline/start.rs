//! start: the time reference. With a start channel, the start pulse is timed
//! with the scene's method and the start pulse shape; without one (or when the
//! pulse is missing: laser off, a dropped tap) the reference is the trigger
//! plus `channels.reference_offset_s`, and the report says so.

use super::{FrameError, Stage, Unit};
use crate::frame::{FrameFlag, Samples};
use crate::detect::kernels::DetectorPlan;
use crate::math::select::mad_sigma;
use crate::math::sum;
use crate::detect::error_table::ErrorTable;
use crate::dsp::mlfit::FitOptions;
use crate::detect::pulse_timing::{time_pulse_with, mismatch_gap, ShapeFit, TimingInput, MISMATCH_Z};
use crate::dsp::pulse::Shape;
use crate::scene::{Scene, TimingMethod};
use super::timing::{MismatchSwing, ModelFloor, PhaseDensity};
use std::sync::Arc;

/// Times the start pulse.
#[derive(Debug)]
pub struct Start {
    method: TimingMethod,
    fraction: f64,
    leading_edge_v: f64,
    min_amplitude_v: f64,
    reference_offset_s: f64,
    pulse_cfg: crate::scene::PulseConfig,
    /// Plan for the current sampling period (rebuilt when it changes).
    plan: Option<(f64, Shape, DetectorPlan)>,
    /// Measured bias and width of the method on the start shape by SNR.
    errors: Option<Arc<ErrorTable>>,
    /// The same for the peak interpolation a failed crossing falls back to.
    fallback_errors: Option<Arc<ErrorTable>>,
    /// The mismatch gap's swing beyond noise.
    mismatch: MismatchSwing,
    /// The start shape's error on the pulses it fits.
    floor: ModelFloor,
    /// The start pulse's sub-sample phase error, from the density of its
    /// measured phases (the shot is free-running against the sample clock).
    phase: PhaseDensity,
    volts: Vec<f64>,
    scratch: Vec<f64>,
}

impl Start {
    /// From the scene's channel, start-pulse and timing sections.
    pub fn new(scene: &Scene) -> Start {
        Start {
            method: scene.timing.method,
            fraction: scene.timing.fraction,
            leading_edge_v: scene.timing.leading_edge_v,
            min_amplitude_v: scene.channels.start_min_amplitude_v,
            reference_offset_s: scene.channels.reference_offset_s,
            pulse_cfg: scene.start_pulse.clone(),
            plan: None,
            errors: None,
            fallback_errors: None,
            mismatch: MismatchSwing::default(),
            floor: ModelFloor::default(),
            phase: PhaseDensity::default(),
            volts: Vec::new(),
            scratch: Vec::new(),
        }
    }
}

impl Stage for Start {
    fn name(&self) -> &'static str {
        "start"
    }

    fn process(&mut self, mut w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        w.reference.t_ref_s = self.reference_offset_s;
        w.reference.t_ref_sigma_s = 0.0;
        let Some(s) = w.source.start else {
            w.report.flags.push(FrameFlag::NoStartChannel);
            w.report.t_start_s = w.reference.t_ref_s;
            out.push(w);
            return Ok(());
        };
        let dt = w.frame.sample_interval_s;
        let ch = &w.frame.channels[s];
        // Integer codes on a finite scale decode to finite volts (|code| ≤ 2¹⁵):
        // nothing to check.
        let (g, o) = (ch.volts_per_code, ch.offset_v);
        let codes_finite = matches!(ch.samples, Samples::I16(_)) && g.abs() <= 1e300 && o.abs() <= 1e300;
        // The start pulse occupies a small part of the channel: the largest
        // excursion locates the pulse, and the baseline and noise are
        // measured on the samples well away from it (the median and MAD of
        // the whole channel when too few are left).
        let n = ch.samples.len();
        // Where the codes locate the pulse (the same sample as the volts
        // would), the statistics are taken on the codes (exact integer
        // sums, see below) and only the pulse's neighbourhood is decoded;
        // otherwise the whole channel, in volts.
        let coded = match &ch.samples {
            Samples::I16(c) if codes_finite => last_max_code(c, g, o).map(|p| (&c[..], p)),
            _ => None,
        };
        let x = &mut self.volts;
        x.clear();
        // Whether `x` holds the whole channel in volts.
        let mut decoded = coded.is_none();
        if decoded {
            ch.volts_into(x);
            // Keep the reference finite whatever the samples hold.
            if !codes_finite && !sum::all_finite(x) {
                let (sum, n) = x.iter().filter(|v| v.is_finite()).fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
                let finite_mean = if n > 0 { sum / n as f64 } else { 0.0 };
                x.iter_mut().filter(|v| !v.is_finite()).for_each(|v| *v = finite_mean);
            }
        }
        let peak = match coded {
            Some((_, p)) => p,
            None => crate::math::select::last_max_index(x).unwrap_or(0),
        };
        if self.plan.as_ref().is_none_or(|p| p.0 != dt || p.2.len() > n + 1) {
            let pulse = self.pulse_cfg.shape(dt);
            let plan = DetectorPlan::matched_filter(&pulse, n);
            (self.errors, self.fallback_errors) = ErrorTable::get_with_fallback(self.method, &pulse, self.fraction, true);
            self.plan = Some((dt, pulse, plan));
        }
        let (lo, hi) = self.plan.as_ref().expect("built above").1.support();
        let away_lo = (peak as f64 + 2.0 * lo).floor();
        let away_hi = (peak as f64 + 2.0 * hi).ceil();
        // The mean and the sum of squared deviations of the samples away
        // from the pulse: of codes, from exact integer sums (a pass for
        // the extremes, one for the sums); of volts, in two passes in the
        // eight-lane order of `math::sum` (vectorised; no division per sample).
        let a = (away_lo.max(0.0) as usize).min(n);
        let b = ((away_hi + 1.0).max(0.0) as usize).min(n).max(a);
        let count = a + (n - b);
        let (baseline, sigma) = if count >= 8 {
            let (mean, ss) = match coded {
                Some((c, _)) => {
                    let (left, right) = (&c[..a], &c[b..]);
                    // Exact integer sums where the codes are within reach
                    // and their volts keep their order and spacing (else
                    // the volts are not their decode to rounding), else
                    // the volts' eight-lane sums.
                    let exact = crate::detect::gates::codes_keep_order(g, o).then(|| crate::math::code_stats::code_mean_sum_sq_dev(&[left, right], g, o)).flatten();
                    exact.unwrap_or_else(|| {
                        let mean = (sum::code_sum(left, g, o) + sum::code_sum(right, g, o)) / count as f64;
                        (mean, sum::code_sum_sq_dev(left, g, o, mean) + sum::code_sum_sq_dev(right, g, o, mean))
                    })
                }
                None => {
                    let (left, right) = (&x[..a], &x[b..]);
                    let mean = (sum::sum(left) + sum::sum(right)) / count as f64;
                    (mean, sum::sum_sq_dev(left, mean) + sum::sum_sq_dev(right, mean))
                }
            };
            (mean, (ss / (count - 1) as f64).sqrt())
        } else {
            if !decoded {
                ch.volts_into(x);
                decoded = true;
            }
            self.scratch.clear();
            self.scratch.extend_from_slice(x);
            let median = *self.scratch.select_nth_unstable_by(n / 2, |a, b| a.total_cmp(b)).1;
            (median, mad_sigma(&mut self.scratch))
        };
        // A start pulse far larger than its noise is timed on samples whose
        // quantisation error is not dithered away: its edge sweeps through
        // the codes, so each edge sample carries the full uniform error of
        // one step (LSB²/12), whatever the quiet baseline shows.
        let lsb = if ch.samples.is_integer() { ch.volts_per_code.abs() } else { 0.0 };
        let sigma = (sigma * sigma + lsb * lsb / 12.0).sqrt().max(f64::MIN_POSITIVE);
        // Only the neighbourhood of the pulse is filtered and timed: four
        // template lengths either side hold everything every method reads.
        let reach = 4 * self.plan.as_ref().expect("built above").2.len() + 8;
        let a = peak.saturating_sub(reach);
        let b = (peak + reach + 1).min(n);
        // `x` holds the channel from sample `off` on: all of it, or only
        // the neighbourhood where the statistics were taken on the codes.
        let off = if decoded {
            0
        } else {
            ch.volts_of_into(a..b, x);
            a
        };
        let amplitude = x[peak - off] - baseline;
        if !(amplitude >= self.min_amplitude_v.max(6.0 * sigma)) {
            w.report.flags.push(FrameFlag::NoStartPulse);
            w.report.t_start_s = w.reference.t_ref_s;
            out.push(w);
            return Ok(());
        }
        let (_, pulse, plan) = self.plan.as_mut().expect("built above");
        // The detector output peak is searched near the raw peak: the template may not match exactly.
        let norm = plan.norm();
        let xw = &x[a - off..b - off];
        let w_half = (pulse.fwhm() * 0.5).ceil() as usize + 1;
        let lo = (peak - a).saturating_sub(w_half);
        let hi = (peak - a + w_half + 1).min(xw.len());
        // Of the filter output, the peak search reads lo..hi and the peak
        // interpolation one sample either side of the peak it finds: only
        // those outputs are computed (bit for bit; the rest are NaN).
        let y = plan.run_part(xw, baseline, lo.saturating_sub(1)..hi + 1);
        let y_peak = (lo..hi).max_by(|&i, &j| y[i].total_cmp(&y[j])).unwrap_or(peak - a);
        let input = TimingInput {
            x: xw,
            mean_v: baseline,
            sigma_v: sigma,
            y,
            norm,
            pulse,
            peak: y_peak,
            fraction: self.fraction,
            leading_edge_v: self.leading_edge_v,
        };
        // The start is the peak of the pulse's own matched filter, and the
        // pulse stands at least 6 σ above its noise: the ML fit needs no
        // coarse scan around it (see `FitOptions::from_matched_peak`: the
        // same bits as with it there, so the error table, measured with
        // the scan, describes this fit).
        let mut timed = time_pulse_with(self.method, &input, &FitOptions::from_matched_peak());
        timed.index += a as f64;
        timed.peak_index += a as f64;
        let table = if timed.fallback { &self.fallback_errors } else { &self.errors };
        if let Some(table) = table {
            (timed.index, timed.sigma_samples) = table.correct(timed.index, timed.amplitude_v / sigma);
        }
        // A start shape that does not fit the samples (χ² test): where it
        // puts the timing point is uncertain by the gap between its fraction
        // point and the samples' own crossing.
        let fit = ShapeFit::measure(xw, baseline, sigma, pulse, timed.index - a as f64 - pulse.fraction_offset(self.fraction));
        // The shape's error on the pulses it fits (see `ModelFloor`), as
        // learned before this pulse.
        // Where the start is free-running against the sample clock, the
        // density of its measured phases shows the same error directly
        // (see `PhaseDensity`); the two measure one thing, so the larger.
        let floor = self.floor.floor(timed.sigma_samples, timed.amplitude_v / sigma).max(self.phase.floor());
        self.phase.update(timed.index);
        let mismatched = fit.mismatched(MISMATCH_Z, 1.0);
        if mismatched {
            // Its typical value is a constant the calibration absorbs; the
            // swing noise gives on a fitting shape is in the method's width.
            let noise = self.fallback_errors.as_ref().map_or(0.0, |e| e.gap_noise(timed.amplitude_v / sigma));
            let swing = self.mismatch.update(mismatch_gap(&input, &fit), noise, self.floor.fits_mostly());
            timed.sigma_samples = timed.sigma_samples.hypot(floor).hypot(swing);
        } else {
            timed.sigma_samples = timed.sigma_samples.hypot(floor);
        }
        self.floor.update(fit.chi2, fit.dof(), sigma, timed.amplitude_v, mismatched);
        w.reference.t_ref_s = w.frame.sample_time_s(timed.index);
        w.reference.t_ref_sigma_s = timed.sigma_samples * dt;
        if timed.fallback {
            w.report.flags.push(FrameFlag::StartTimingFallback);
        }
        w.report.t_start_s = w.reference.t_ref_s;
        w.report.t_start_sigma_s = w.reference.t_ref_sigma_s;
        out.push(w);
        Ok(())
    }
}

/// `last_max_index` of the volts `code · g + o` (a multiply, then an add, as
/// `Channel::volts_into` decodes them) found on the codes: the last sample
/// holding the largest code, where that code's volts are above every other
/// code's (g > 0 and the next code down decodes strictly lower: the decoding
/// is monotone, so then the samples at the maximum in volts are exactly those
/// at the largest code) and not zero (where the total order tells −0 from
/// +0). None (the caller searches the volts) otherwise.
fn last_max_code(codes: &[i16], g: f64, o: f64) -> Option<usize> {
    if !(g > 0.0) {
        return None;
    }
    let (top, at) = crate::math::code_stats::last_max(codes)?;
    let volts = |c: i16| c as f64 * g + o;
    if top == i16::MIN || !(volts(top - 1) < volts(top)) || volts(top) == 0.0 {
        return None;
    }
    Some(at)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_largest_code_is_the_largest_volts() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for len in [0usize, 1, 7, 8, 15, 16, 17, 31, 33, 250, 2500] {
            for (g, o) in [(1.0 / 4096.0, 0.0), (2.4e-4, -0.3), (1e-3, 1e-3), (-1e-3, 0.0), (1e-20, 1.0), (0.0, 0.0)] {
                for spread in [3u64, 200, 65536] {
                    let codes: Vec<i16> = (0..len).map(|_| ((next() % spread) as i64 - (spread / 2) as i64) as i16).collect();
                    let volts: Vec<f64> = codes.iter().map(|&c| c as f64 * g + o).collect();
                    let want = crate::math::select::last_max_index(&volts);
                    // Where the codes decide it, the same index; else the caller searches the volts.
                    if let Some(got) = last_max_code(&codes, g, o) {
                        assert_eq!(Some(got), want, "len {len} g {g} o {o} spread {spread}");
                    } else {
                        assert!(!(g > 0.0) || (g < 1e-15) || len == 0 || volts.iter().any(|&v| v == 0.0), "len {len} g {g} o {o}");
                    }
                }
            }
        }
    }
}
