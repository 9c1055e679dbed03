//! average: ensemble average of frames (N:1), after the start stage.
//!
//! * **Grouping**: `block` (N consecutive frames per report) or `sliding`
//!   (the last N frames, a report every `hop` frames).
//! * **Alignment** (`align = "start"`): each frame is shifted by a windowed-sinc
//!   fractional delay so its start pulse lands where the group's reference
//!   frame had it; the start jitters against the sample clock by up to a
//!   sample, and averaging unaligned returns would smear them. The averaged
//!   frame's time reference is that reference instant (its error averages
//!   down with the per-frame start timing errors).
//! * **Exact integer accumulation**: unshifted integer codes are summed in
//!   integers ([`CodeAccumulator`]) and divided once (correctly rounded), so
//!   the mean of codes is exact for any N; shifted or float samples
//!   accumulate in f64.
//! * **Robust methods** (`trimmed_mean`, `median`) keep the window's frames
//!   and take the per-sample statistic: a sporadic burst in a few frames does
//!   not reach the result.
//! * **Stationarity guard** (`stationarity_block` > 0): every block of that
//!   many frames is compared with the group so far on the range gate (matched
//!   filter peak position and amplitude, with the amplitude's noise measured
//!   on the gates). A return that moved or changed amplitude ends the group
//!   before the block, flagged `nonstationary`; the block starts the next.
//!
//! The averaged frame goes on as F64 volts; the noise stage re-fits the noise
//! model on it (σ/√N is never assumed). The report carries `frames_averaged`
//! and `snr_gain_db` (single-frame gate σ, rms over the group, over the
//! averaged frame's gate σ). A frame whose geometry differs from the group's
//! (length, sampling, offset, start channel) closes the group early, flagged
//! `partial_average`.

use crate::detect::gates::GatePlacer;
use super::{FrameError, Stage, Work};
use crate::frame::FrameFlag;
use crate::detect::noise_model::Moments;
use crate::dsp::accumulate::{CodeAccumulator, mean_from_sums, robust_average};
use crate::dsp::fracdelay::FractionalDelay;
use crate::frame::{Channel, ChannelRole, Samples};
use crate::scene::{AveragingAlign, AveragingConfig, AveragingMethod, AveragingMode, Scene};
use std::collections::VecDeque;
use std::ops::Range;

/// Exact running sum of one channel over frames.
#[derive(Debug)]
struct Acc {
    /// Integer codes of unshifted integer frames, and their scale.
    codes: Option<(CodeAccumulator, f64)>,
    /// Code sums merged in from other accumulators (stationarity blocks).
    merged: Vec<i64>,
    /// Sum of the offsets of the frames whose codes are in `codes`/`merged`, V.
    offset_sum_v: f64,
    /// Sum of the float (or shifted) frames, V.
    volts: Vec<f64>,
    /// Frames added.
    count: u32,
}

impl Acc {
    fn new(len: usize) -> Acc {
        Acc {
            codes: None,
            merged: Vec::new(),
            offset_sum_v: 0.0,
            volts: vec![0.0; len],
            count: 0,
        }
    }

    fn add_channel(&mut self, c: &Channel, scratch: &mut Vec<f64>) {
        let n = self.volts.len();
        let scale_ok = self
            .codes
            .as_ref()
            .is_none_or(|(_, g)| *g == c.volts_per_code);
        if c.samples.is_integer() && scale_ok && c.samples.len() == n {
            let (acc, _) = self
                .codes
                .get_or_insert_with(|| (CodeAccumulator::new(n), c.volts_per_code));
            match &c.samples {
                Samples::I8(v) => acc.add_i8(v),
                Samples::I16(v) => acc.add_i16(v),
                Samples::I32(v) => acc.add_i32(v),
                _ => unreachable!("is_integer checked"),
            }
            self.offset_sum_v += c.offset_v;
        } else {
            c.volts_into(scratch);
            self.add_volts(scratch);
            return;
        }
        self.count += 1;
    }

    fn add_volts(&mut self, v: &[f64]) {
        crate::dsp::accumulate::add_f64(&mut self.volts, v);
        self.count += 1;
    }

    /// Adds everything `other` holds.
    fn merge(&mut self, other: &mut Acc) {
        if let Some((oc, g)) = &mut other.codes {
            if self.codes.is_none() {
                self.codes = Some((CodeAccumulator::new(self.volts.len()), *g));
            }
            if self.merged.is_empty() {
                self.merged = vec![0; self.volts.len()];
            }
            let same_scale = self.codes.as_ref().is_some_and(|(_, sg)| sg == g);
            if same_scale {
                for (m, s) in self.merged.iter_mut().zip(oc.sums()) {
                    *m += s;
                }
                for (m, s) in self.merged.iter_mut().zip(&other.merged) {
                    *m += s;
                }
                self.offset_sum_v += other.offset_sum_v;
            } else {
                // A different scale cannot share the integer sum: add it as volts.
                let mut sums: Vec<i64> = oc.sums().to_vec();
                for (s, m) in sums.iter_mut().zip(&other.merged) {
                    *s += m;
                }
                for (v, s) in self.volts.iter_mut().zip(&sums) {
                    *v += *s as f64 * *g;
                }
                let off = other.offset_sum_v;
                self.volts.iter_mut().for_each(|v| *v += off);
            }
        }
        crate::dsp::accumulate::add_f64(&mut self.volts, &other.volts);
        self.count += other.count;
    }

    /// Mean in volts: exact integer sums divided once, plus the float part.
    fn mean_v(&mut self) -> Vec<f64> {
        let n = self.count.max(1);
        let mut out = vec![0.0; self.volts.len()];
        if let Some((acc, g)) = &mut self.codes {
            let mut sums = acc.sums().to_vec();
            for (s, m) in sums.iter_mut().zip(&self.merged) {
                *s += m;
            }
            // Σ(g·c + o)/N = g·(Σc/N) + Σo/N with Σc/N correctly rounded.
            mean_from_sums(&sums, n as u64, *g, self.offset_sum_v / n as f64, &mut out);
        }
        let inv = 1.0 / n as f64;
        for (o, v) in out.iter_mut().zip(&self.volts) {
            *o += v * inv;
        }
        out
    }
}

/// A group being accumulated (block mean).
#[derive(Debug)]
struct Group {
    /// The first frame's work: becomes the output.
    first: Work,
    stop: Acc,
    start: Option<Acc>,
    /// Σ of single-frame gate variances, V².
    var_sum: f64,
    /// Σ of start timing variances, s².
    t_var_sum: f64,
    /// Σ and count of the frames' own start instants (unaligned averages), s.
    t_sum_s: f64,
    t_count: u32,
}

impl Group {
    fn count(&self) -> u32 {
        self.stop.count
    }
}

/// One frame kept for a robust or sliding average: aligned volts.
#[derive(Debug)]
struct Kept {
    work: Work,
    stop: Vec<f64>,
    start: Option<Vec<f64>>,
    var: f64,
}

/// Ensemble averaging.
#[derive(Debug)]
pub struct Average {
    cfg: AveragingConfig,
    gates: GatePlacer,
    return_pulse: crate::scene::PulseConfig,
    /// Time reference every frame is aligned to, s (set by the group's first frame with a start pulse).
    reference_s: Option<f64>,
    group: Option<Group>,
    block: Option<Group>,
    kept: VecDeque<Kept>,
    /// Frames since the last sliding report.
    since_report: u32,
    /// The next report crosses a change that ended an earlier group.
    nonstationary: bool,
    volts: Vec<f64>,
    shifted: Vec<f64>,
    scratch: Vec<f64>,
}

fn has_start_pulse(w: &Work) -> bool {
    w.source.start.is_some() && !w.report.flags.iter().any(|f| *f == FrameFlag::NoStartPulse)
}

impl Average {
    /// From the scene's `[averaging]` section.
    pub fn new(scene: &Scene) -> Average {
        Average {
            cfg: scene.averaging.clone(),
            gates: GatePlacer::new(scene),
            return_pulse: scene.return_pulse.clone(),
            reference_s: None,
            group: None,
            block: None,
            kept: VecDeque::new(),
            since_report: 0,
            nonstationary: false,
            volts: Vec::new(),
            shifted: Vec::new(),
            scratch: Vec::new(),
        }
    }

    fn stores_frames(&self) -> bool {
        self.cfg.mode == AveragingMode::Sliding || self.cfg.method != AveragingMethod::Mean
    }

    /// Same geometry as the frame `g` (so the two can be averaged sample by sample).
    fn matches(g: &Work, w: &Work) -> bool {
        let (a, b) = (&g.frame, &w.frame);
        a.len() == b.len()
            && a.sample_interval_s == b.sample_interval_s
            && (a.first_sample_offset_s - b.first_sample_offset_s).abs() <= a.sample_interval_s
            && g.source.start.is_some() == w.source.start.is_some()
    }

    /// Shift (samples, positive: later) that moves `w`'s start pulse to the reference.
    fn shift_of(&mut self, w: &Work) -> Option<f64> {
        if self.cfg.align != AveragingAlign::Start || !has_start_pulse(w) {
            return None;
        }
        let r = *self.reference_s.get_or_insert(w.reference.t_ref_s);
        let d = (r - w.reference.t_ref_s) / w.frame.sample_interval_s;
        (d.abs() > 1e-9).then_some(d)
    }

    /// Gate variance of `v` (the frame's stop channel in volts).
    fn gate_variance(&mut self, w: &Work, v: &[f64]) -> f64 {
        let mut m = Moments::default();
        for r in w.quiet_ranges(&mut self.gates).iter() {
            v[r.clone()].iter()
                .filter(|x| x.is_finite())
                .for_each(|&x| m.push(x));
        }
        if m.count() >= 2 {
            m.variance()
        } else {
            f64::NAN
        }
    }

    /// Aligned volts of channel `c` of `w` into `out`.
    fn aligned(c: &Channel, shift: f64, raw: &mut Vec<f64>, out: &mut Vec<f64>) {
        c.volts_into(raw);
        out.clear();
        out.resize(raw.len(), 0.0);
        FractionalDelay::new(shift).apply(raw, out);
    }

    fn add_to_group(&mut self, g: &mut Group, w: &Work) {
        let shift = self.shift_of(w);
        let stop = &w.frame.channels[w.source.stop];
        let mut volts = std::mem::take(&mut self.volts);
        let mut shifted = std::mem::take(&mut self.shifted);
        match shift {
            Some(d) => {
                Self::aligned(stop, d, &mut volts, &mut shifted);
                g.stop.add_volts(&shifted);
                std::mem::swap(&mut volts, &mut shifted);
            }
            None => {
                g.stop.add_channel(stop, &mut self.scratch);
                stop.volts_into(&mut volts);
            }
        }
        g.var_sum += self.gate_variance(w, &volts);
        g.t_var_sum += w.reference.t_ref_sigma_s * w.reference.t_ref_sigma_s;
        if has_start_pulse(w) {
            g.t_sum_s += w.reference.t_ref_s;
            g.t_count += 1;
        }
        if let (Some(acc), Some(s)) = (&mut g.start, w.source.start) {
            let ch = &w.frame.channels[s];
            match shift {
                Some(d) => {
                    Self::aligned(ch, d, &mut volts, &mut shifted);
                    acc.add_volts(&shifted);
                }
                None => acc.add_channel(ch, &mut self.scratch),
            }
        }
        self.volts = volts;
        self.shifted = shifted;
    }

    fn new_group(&mut self, w: Work) -> Group {
        let n = w.frame.len();
        let mut g = Group {
            stop: Acc::new(n),
            start: w.source.start.map(|_| Acc::new(n)),
            var_sum: 0.0,
            t_var_sum: 0.0,
            t_sum_s: 0.0,
            t_count: 0,
            first: w,
        };
        let first = g.first.clone();
        self.add_to_group(&mut g, &first);
        g
    }

    /// Output work from a mean (or robust) stop/start and the group's bookkeeping.
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        mut w: Work,
        stop: Vec<f64>,
        start: Option<Vec<f64>>,
        count: u32,
        var_sum: f64,
        t_var_sum: f64,
        mean_t_s: Option<f64>,
        seq_last: u64,
    ) -> Work {
        let stop_name = w.frame.channels[w.source.stop].name.clone();
        let mut channels = vec![Channel::from_volts(stop_name, ChannelRole::Stop, stop)];
        if let (Some(s), Some(v)) = (w.source.start, start) {
            let name = w.frame.channels[s].name.clone();
            channels.push(Channel::from_volts(name, ChannelRole::Start, v));
        }
        w.frame.channels = channels;
        w.source.stop = 0;
        w.source.start = w.source.start.map(|_| 1);
        w.source.frames_averaged = count;
        w.source.lsb_v /= count as f64;
        w.source.seq_last = seq_last;
        // Aligned: every frame's start sits at the reference. Unaligned: the
        // returns sit, on average, at the frames' mean start instant.
        if let Some(r) = self
            .reference_s
            .filter(|_| has_start_pulse(&w))
            .or(mean_t_s)
        {
            w.reference.t_ref_s = r;
            w.report.t_start_s = r;
            w.reference.t_ref_sigma_s = t_var_sum.sqrt() / count as f64;
        }
        w.report.frames_averaged = count;
        w.report.seq_last = seq_last;
        let out_var = {
            let v = std::mem::take(&mut self.volts);
            let mut vv = v;
            w.frame.channels[0].volts_into(&mut vv);
            let r = self.gate_variance(&w, &vv);
            self.volts = vv;
            r
        };
        let in_var = var_sum / count as f64;
        if in_var > 0.0 && out_var > 0.0 {
            w.report.snr_gain_db = Some(10.0 * (in_var / out_var).log10());
        }
        w
    }

    fn emit_group(&mut self, mut g: Group, out: &mut Vec<Work>, partial: bool) {
        let stop = g.stop.mean_v();
        let start = g.start.as_mut().map(|a| a.mean_v());
        let count = g.count();
        let seq_last = g.first.source.seq_last;
        let mean_t = (g.t_count > 0).then(|| g.t_sum_s / g.t_count as f64);
        let mut w = self.finish(
            g.first,
            stop,
            start,
            count,
            g.var_sum,
            g.t_var_sum,
            mean_t,
            seq_last,
        );
        if partial {
            w.report.flags.push(FrameFlag::PartialAverage);
        }
        if std::mem::take(&mut self.nonstationary) {
            w.report.flags.push(FrameFlag::Nonstationary);
        }
        self.reference_s = None;
        out.push(w);
    }

    /// Block mean with accumulators.
    fn process_block_mean(&mut self, w: Work, out: &mut Vec<Work>) {
        let geometry_ok =
            |g: &Option<Group>| g.as_ref().is_none_or(|g| Self::matches(&g.first, &w));
        if !geometry_ok(&self.group) || !geometry_ok(&self.block) {
            self.close_block(out);
            if let Some(g) = self.group.take() {
                self.emit_group(g, out, true);
            }
        }
        let guard = self.cfg.stationarity_block;
        let laser_off = w.frame.laser_off;
        let seq = w.source.seq_last;
        // Without a guard the block is the group itself.
        let slot = if guard == 0 {
            &mut self.group
        } else {
            &mut self.block
        };
        match slot.take() {
            Some(mut g) => {
                self.add_to_group(&mut g, &w);
                g.first.source.seq_last = seq;
                if laser_off
                    && !g
                        .first
                        .report
                        .flags
                        .iter()
                        .any(|f| matches!(f, FrameFlag::LaserOff | FrameFlag::LaserOffInGroup))
                {
                    g.first.report.flags.push(FrameFlag::LaserOffInGroup);
                }
                let slot = if guard == 0 {
                    &mut self.group
                } else {
                    &mut self.block
                };
                *slot = Some(g);
            }
            None => {
                let g = self.new_group(w);
                let slot = if guard == 0 {
                    &mut self.group
                } else {
                    &mut self.block
                };
                *slot = Some(g);
            }
        }
        if guard > 0 {
            let in_group = self.group.as_ref().map_or(0, |g| g.count());
            let in_block = self.block.as_ref().map_or(0, |b| b.count());
            if in_block >= guard.min(self.cfg.frames - in_group) {
                self.close_block(out);
            }
        }
        if self
            .group
            .as_ref()
            .is_some_and(|g| g.count() >= self.cfg.frames)
        {
            let g = self.group.take().expect("checked");
            self.emit_group(g, out, false);
        }
    }

    /// Tests the finished guard block against the group and merges it, or
    /// ends the group at the change.
    fn close_block(&mut self, out: &mut Vec<Work>) {
        let Some(mut b) = self.block.take() else {
            return;
        };
        match self.group.take() {
            None => self.group = Some(b),
            Some(mut g) => {
                let gm = g.stop.mean_v();
                let bm = b.stop.mean_v();
                if self.changed(&g.first, &gm, &bm, g.count(), b.count()) {
                    self.nonstationary = true;
                    let r = self.reference_s;
                    self.emit_group(g, out, true);
                    // The block's frames were aligned to the same reference.
                    self.reference_s = r;
                    self.group = Some(b);
                } else {
                    g.stop.merge(&mut b.stop);
                    if let (Some(a), Some(o)) = (&mut g.start, &mut b.start) {
                        a.merge(o);
                    }
                    g.var_sum += b.var_sum;
                    g.t_var_sum += b.t_var_sum;
                    g.t_sum_s += b.t_sum_s;
                    g.t_count += b.t_count;
                    g.first.source.seq_last = b.first.source.seq_last;
                    g.first.report.flags.extend(
                        b.first
                            .report
                            .flags
                            .iter()
                            .filter(|f| **f == FrameFlag::LaserOffInGroup)
                            .copied(),
                    );
                    self.group = Some(g);
                }
            }
        }
    }

    /// The return in `newer` differs from the one in `older` (both mean stop
    /// volts of frames shaped like `w`).
    fn changed(
        &mut self,
        w: &Work,
        older: &[f64],
        newer: &[f64],
        n_older: u32,
        n_newer: u32,
    ) -> bool {
        let _ = (n_older, n_newer);
        let dt = w.frame.sample_interval_s;
        let shape = self.return_pulse.shape(dt);
        let (h, peak_idx) = shape.template();
        let e: f64 = h.iter().map(|v| v * v).sum();
        if e.is_nan() || e <= 0.0 {
            return false;
        }
        let gates = w.place_gates(&mut self.gates);
        let quiet = w.quiet_ranges(&mut self.gates);
        let a = PeakFit::new(older, &h, peak_idx, e, &gates.range, &quiet);
        let b = PeakFit::new(newer, &h, peak_idx, e, &gates.range, &quiet);
        let (Some(a), Some(b)) = (a, b) else {
            return false;
        };
        let sig = |p: &PeakFit| p.amplitude > 6.0 * p.sigma;
        if !sig(&a) && !sig(&b) {
            return false;
        }
        // Amplitudes at the stronger peak's position.
        let at = if a.amplitude / a.sigma >= b.amplitude / b.sigma {
            a.position
        } else {
            b.position
        };
        let (aa, ab) = (
            a.amplitude_at(older, &h, peak_idx, e, at),
            b.amplitude_at(newer, &h, peak_idx, e, at),
        );
        let noise = 4.0 * (a.sigma * a.sigma + b.sigma * b.sigma).sqrt();
        let amp_changed = (aa - ab).abs()
            > noise.max(self.cfg.stationarity_max_amplitude_change * aa.abs().max(ab.abs()));
        let moved = sig(&a)
            && sig(&b)
            && (a.position - b.position).abs() * dt > self.cfg.stationarity_max_shift_s;
        amp_changed || moved
    }

    /// Robust or sliding: frames kept, statistic at each report.
    fn process_kept(&mut self, w: Work, out: &mut Vec<Work>) {
        if self
            .kept
            .front()
            .is_some_and(|k| !Self::matches(&k.work, &w))
        {
            if self.cfg.mode == AveragingMode::Block {
                self.emit_kept(out, true);
            }
            self.kept.clear();
            self.reference_s = None;
            self.since_report = 0;
        }
        let shift = self.shift_of(&w).unwrap_or(0.0);
        let mut raw = std::mem::take(&mut self.scratch);
        let mut stop = Vec::new();
        Self::aligned(&w.frame.channels[w.source.stop], shift, &mut raw, &mut stop);
        let start = w.source.start.map(|s| {
            let mut v = Vec::new();
            Self::aligned(&w.frame.channels[s], shift, &mut raw, &mut v);
            v
        });
        self.scratch = raw;
        let var = self.gate_variance(&w, &stop);
        self.kept.push_back(Kept {
            work: w,
            stop,
            start,
            var,
        });
        self.since_report += 1;
        let n = self.cfg.frames as usize;
        let guard = self.cfg.stationarity_block as usize;
        if guard > 0 && self.kept.len() > guard && self.kept.len().is_multiple_of(guard) {
            let split = self.kept.len() - guard;
            let older = mean_of(self.kept.iter().take(split).map(|k| k.stop.as_slice()));
            let newer = mean_of(self.kept.iter().skip(split).map(|k| k.stop.as_slice()));
            let first = self.kept[0].work.clone();
            if self.changed(&first, &older, &newer, split as u32, guard as u32) {
                if self.cfg.mode == AveragingMode::Block {
                    let rest: Vec<Kept> = self.kept.drain(split..).collect();
                    self.nonstationary = true;
                    let r = self.reference_s;
                    self.emit_kept(out, true);
                    self.reference_s = r;
                    self.kept.extend(rest);
                } else {
                    // The window restarts at the change; its next report says so.
                    self.kept.drain(..split);
                    self.nonstationary = true;
                }
            }
        }
        match self.cfg.mode {
            AveragingMode::Block => {
                if self.kept.len() >= n {
                    self.emit_kept(out, false);
                }
            }
            AveragingMode::Sliding => {
                while self.kept.len() > n {
                    self.kept.pop_front();
                }
                if self.kept.len() == n && self.since_report >= self.cfg.hop {
                    self.since_report = 0;
                    self.report_window(out, false);
                }
            }
        }
    }

    /// Reports the kept frames' statistic (the window stays for sliding).
    fn report_window(&mut self, out: &mut Vec<Work>, partial: bool) {
        let Some(front) = self.kept.front() else {
            return;
        };
        let mut first = front.work.clone();
        let seq_last = self.kept.back().map_or(first.source.seq_last, |k| k.work.source.seq_last);
        first.report.seq_first = front.work.report.seq_first;
        first.report.time_s = front.work.report.time_s;
        let count = self.kept.len() as u32;
        let var_sum: f64 = self.kept.iter().map(|k| k.var).sum();
        let t_var_sum: f64 = self
            .kept
            .iter()
            .map(|k| k.work.reference.t_ref_sigma_s * k.work.reference.t_ref_sigma_s)
            .sum();
        let trim = match self.cfg.method {
            AveragingMethod::Mean => 0.0,
            AveragingMethod::TrimmedMean => self.cfg.trim_fraction,
            AveragingMethod::Median => 0.5,
        };
        let stat = |frames: Vec<&[f64]>| {
            let mut o = vec![0.0; frames.first().map_or(0, |f| f.len())];
            let mut scratch = Vec::new();
            robust_average(&frames, trim, &mut o, &mut scratch);
            o
        };
        let stop = stat(self.kept.iter().map(|k| k.stop.as_slice()).collect());
        let start = first.source.start.map(|_| {
            stat(
                self.kept
                    .iter()
                    .filter_map(|k| k.start.as_deref())
                    .collect(),
            )
        });
        if self.kept.iter().any(|k| k.work.frame.laser_off) && !first.frame.laser_off {
            first.report.flags.push(FrameFlag::LaserOffInGroup);
        }
        let starts: Vec<f64> = self
            .kept
            .iter()
            .filter(|k| has_start_pulse(&k.work))
            .map(|k| k.work.reference.t_ref_s)
            .collect();
        let mean_t = (!starts.is_empty()).then(|| starts.iter().sum::<f64>() / starts.len() as f64);
        let mut w = self.finish(
            first, stop, start, count, var_sum, t_var_sum, mean_t, seq_last,
        );
        if partial {
            w.report.flags.push(FrameFlag::PartialAverage);
        }
        if std::mem::take(&mut self.nonstationary) {
            w.report.flags.push(FrameFlag::Nonstationary);
        }
        out.push(w);
    }

    fn emit_kept(&mut self, out: &mut Vec<Work>, partial: bool) {
        if self.kept.is_empty() {
            return;
        }
        self.report_window(out, partial);
        self.kept.clear();
        self.reference_s = None;
    }
}

/// Per-sample mean of equally long frames.
fn mean_of<'a>(frames: impl Iterator<Item = &'a [f64]>) -> Vec<f64> {
    let mut sum: Vec<f64> = Vec::new();
    let mut n = 0usize;
    for f in frames {
        if sum.is_empty() {
            sum = vec![0.0; f.len()];
        }
        crate::dsp::accumulate::add_f64(&mut sum, f);
        n += 1;
    }
    let inv = 1.0 / n.max(1) as f64;
    sum.iter_mut().for_each(|v| *v *= inv);
    sum
}

/// The strongest matched-filter peak in the range gate of a mean frame, and
/// the amplitude's noise measured through the same filter on the quiet gates.
#[derive(Debug, Clone, Copy)]
struct PeakFit {
    /// Peak position, samples (parabolic sub-sample).
    position: f64,
    /// Least-squares pulse amplitude above the gate mean, V.
    amplitude: f64,
    /// Standard deviation of that amplitude from noise, V.
    sigma: f64,
    /// Mean of the quiet gates (the offset the amplitude is measured from), V.
    mean_v: f64,
}

impl PeakFit {
    fn new(
        x: &[f64],
        h: &[f64],
        peak_idx: usize,
        e: f64,
        range: &Range<usize>,
        quiet: &[Range<usize>],
    ) -> Option<PeakFit> {
        let mut m = Moments::default();
        for r in quiet {
            x[r.clone()].iter().for_each(|&v| m.push(v));
        }
        if m.count() < 8 {
            return None;
        }
        let mean = m.mean();
        // Matched filter output at peak position p: Σ_j h[j] (x[p − peak_idx + j] − mean) / e.
        let mf = |p: isize| -> Option<f64> {
            let lo = p - peak_idx as isize;
            if lo < 0 || lo as usize + h.len() > x.len() {
                return None;
            }
            Some(
                h.iter()
                    .zip(&x[lo as usize..])
                    .map(|(a, b)| a * (b - mean))
                    .sum::<f64>()
                    / e,
            )
        };
        let mut noise = Moments::default();
        for r in quiet {
            for p in r.clone().step_by(2) {
                if let Some(v) = mf(p as isize) {
                    noise.push(v);
                }
            }
        }
        let sigma = if noise.count() >= 8 {
            noise.variance().sqrt()
        } else {
            (m.variance() / e).sqrt()
        };
        let (p, a) = range
            .clone()
            .filter_map(|p| mf(p as isize).map(|v| (p, v)))
            .max_by(|a, b| a.1.total_cmp(&b.1))?;
        let (l, r) = (
            mf(p as isize - 1).unwrap_or(a),
            mf(p as isize + 1).unwrap_or(a),
        );
        let den = l - 2.0 * a + r;
        let delta = if den < 0.0 {
            (0.5 * (l - r) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        };
        Some(PeakFit {
            position: p as f64 + delta,
            amplitude: a,
            sigma: sigma.max(f64::MIN_POSITIVE),
            mean_v: mean,
        })
    }

    /// Amplitude at (the nearest sample to) `position` in `x`.
    fn amplitude_at(&self, x: &[f64], h: &[f64], peak_idx: usize, e: f64, position: f64) -> f64 {
        let p = position.round() as isize;
        let lo = p - peak_idx as isize;
        if lo < 0 || lo as usize + h.len() > x.len() {
            return 0.0;
        }
        let mean = self.mean_v;
        h.iter()
            .zip(&x[lo as usize..])
            .map(|(a, b)| a * (b - mean))
            .sum::<f64>()
            / e
    }
}

impl Stage for Average {
    fn name(&self) -> &'static str {
        "average"
    }

    fn process(&mut self, w: Work, out: &mut Vec<Work>) -> Result<(), FrameError> {
        if self.stores_frames() {
            self.process_kept(w, out);
        } else {
            self.process_block_mean(w, out);
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Work>) {
        if self.stores_frames() {
            if self.cfg.mode == AveragingMode::Block {
                self.emit_kept(out, true);
            }
            return;
        }
        self.close_block(out);
        if let Some(g) = self.group.take() {
            self.emit_group(g, out, true);
        }
    }
}
