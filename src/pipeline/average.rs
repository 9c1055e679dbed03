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
use super::{FrameError, Stage, Unit, Work};
use crate::frame::FrameFlag;
use crate::detect::noise_model::Moments;
use crate::dsp::accumulate::{CodeAccumulator, mean_from_sums, robust_average_of};
use crate::dsp::fracdelay::FractionalDelay;
use crate::frame::{Channel, ChannelRole, Samples};
use crate::scene::{AveragingAlign, AveragingConfig, AveragingMethod, AveragingMode, Scene};
use std::collections::VecDeque;
use std::ops::Range;

/// Exact running sum of one channel over frames. Reused from group to group
/// ([`Acc::reset`]), so a new group allocates nothing once one has run.
#[derive(Debug)]
struct Acc {
    /// Integer codes of unshifted integer frames, and their scale.
    codes: Option<(CodeAccumulator, f64)>,
    /// A code accumulator of an earlier group, kept for the next.
    spare_codes: Option<CodeAccumulator>,
    /// Code sums merged in from other accumulators (stationarity blocks).
    merged: Vec<i64>,
    /// Sum of the offsets of the frames whose codes are in `codes`/`merged`, V.
    offset_sum_v: f64,
    /// Sum of the float (or shifted) frames, V.
    volts: Vec<f64>,
    /// Frames added.
    count: u32,
    /// Scratch: code sums.
    sums: Vec<i64>,
}

impl Acc {
    fn new(len: usize) -> Acc {
        Acc {
            codes: None,
            spare_codes: None,
            merged: Vec::new(),
            offset_sum_v: 0.0,
            volts: vec![0.0; len],
            count: 0,
            sums: Vec::new(),
        }
    }

    /// Empties the accumulator for frames of `len` samples: as [`Acc::new`],
    /// keeping the storage.
    fn reset(&mut self, len: usize) {
        if let Some((codes, _)) = self.codes.take() {
            self.spare_codes = Some(codes);
        }
        self.merged.clear();
        self.offset_sum_v = 0.0;
        self.volts.clear();
        self.volts.resize(len, 0.0);
        self.count = 0;
    }

    /// An empty code accumulator for this accumulator's length (the spare one when it fits).
    fn fresh_codes(&mut self) -> CodeAccumulator {
        let n = self.volts.len();
        match self.spare_codes.take() {
            Some(mut c) if c.len() == n => {
                c.reset();
                c
            }
            _ => CodeAccumulator::new(n),
        }
    }

    fn add_channel(&mut self, c: &Channel, scratch: &mut Vec<f64>) {
        let n = self.volts.len();
        let scale_ok = self
            .codes
            .as_ref()
            .is_none_or(|(_, g)| *g == c.volts_per_code);
        if c.samples.is_integer() && scale_ok && c.samples.len() == n {
            if self.codes.is_none() {
                self.codes = Some((self.fresh_codes(), c.volts_per_code));
            }
            let (acc, _) = self.codes.as_mut().expect("set above");
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
                self.codes = Some((self.fresh_codes(), *g));
            }
            if self.merged.is_empty() {
                self.merged.resize(self.volts.len(), 0);
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
                let sums = &mut self.sums;
                sums.clear();
                sums.extend_from_slice(oc.sums());
                for (s, m) in sums.iter_mut().zip(&other.merged) {
                    *s += m;
                }
                for (v, s) in self.volts.iter_mut().zip(sums.iter()) {
                    *v += *s as f64 * *g;
                }
                let off = other.offset_sum_v;
                self.volts.iter_mut().for_each(|v| *v += off);
            }
        }
        crate::dsp::accumulate::add_f64(&mut self.volts, &other.volts);
        self.count += other.count;
    }

    /// Mean in volts into `out`: exact integer sums divided once, plus the float part.
    fn mean_v(&mut self, out: &mut Vec<f64>) {
        let n = self.count.max(1);
        out.clear();
        out.resize(self.volts.len(), 0.0);
        if let Some((acc, g)) = &mut self.codes {
            let sums = &mut self.sums;
            sums.clear();
            sums.extend_from_slice(acc.sums());
            for (s, m) in sums.iter_mut().zip(&self.merged) {
                *s += m;
            }
            // Σ(g·c + o)/N = g·(Σc/N) + Σo/N with Σc/N correctly rounded.
            mean_from_sums(sums, n as u64, *g, self.offset_sum_v / n as f64, out);
        }
        let inv = 1.0 / n as f64;
        for (o, v) in out.iter_mut().zip(&self.volts) {
            *o += v * inv;
        }
    }
}

/// A group being accumulated (block mean).
#[derive(Debug)]
struct Group {
    /// The first frame's work: becomes the output.
    first: Unit,
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
    work: Unit,
    stop: Vec<f64>,
    start: Option<Vec<f64>>,
    var: f64,
}

/// Ensemble averaging.
///
/// The stage reuses its storage from group to group: accumulators, the
/// kept frames' volts and the mean frames' channels (lent to the output
/// frame with [`Work::set_volts`], for spare storage of the output unit),
/// and it hands the units it averaged away back to the pipeline
/// ([`Stage::consumed`]), so the steady state allocates nothing.
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
    /// The alignment's fractional delay, replanned per frame.
    delay: FractionalDelay,
    /// Spare storage for a channel in volts (mean channels, kept frames, scratch).
    pool: Vec<Vec<f64>>,
    /// Spare accumulators.
    accs: Vec<Acc>,
    /// Units averaged away, until the pipeline takes them back.
    consumed: Vec<Unit>,
    /// Kept frames set aside while a group before them is emitted.
    rest: VecDeque<Kept>,
    /// Return-pulse template at a sampling period: (dt, taps, peak tap, energy).
    template: Option<(f64, Vec<f64>, usize, f64)>,
}

fn has_start_pulse(w: &Work) -> bool {
    w.source.start.is_some() && !w.report.flags.iter().any(|f| *f == FrameFlag::NoStartPulse)
}

/// Makes `dst`, a unit this stage is done with, a copy of `src` in all but
/// its channels' samples, keeping `dst`'s storage: what a mean unit needs of
/// the frame it stands for ([`Average::finish`] then replaces the stop and
/// start channels' samples and drops the other channels). `src` has not
/// reached the noise stage, so its per-frame buffers are empty.
fn copy_but_samples(dst: &mut Work, src: &Work) {
    let Work {
        frame,
        source,
        buffers: _,
        reference,
        noise,
        threshold,
        report,
    } = src;
    dst.reclaim_volts();
    let f = &mut dst.frame;
    f.sensor_id.clone_from(&frame.sensor_id);
    f.sequence = frame.sequence;
    f.trigger_time_s = frame.trigger_time_s;
    f.sample_interval_s = frame.sample_interval_s;
    f.first_sample_offset_s = frame.first_sample_offset_s;
    f.laser_off = frame.laser_off;
    f.channels.truncate(frame.channels.len());
    for (i, c) in frame.channels.iter().enumerate() {
        match f.channels.get_mut(i) {
            Some(d) => {
                d.name.clone_from(&c.name);
                d.role = c.role;
                d.volts_per_code = c.volts_per_code;
                d.offset_v = c.offset_v;
            }
            None => f.channels.push(Channel {
                name: c.name.clone(),
                role: c.role,
                samples: Samples::F64(Vec::new()),
                volts_per_code: c.volts_per_code,
                offset_v: c.offset_v,
            }),
        }
    }
    dst.source = *source;
    dst.buffers.clear();
    dst.reference = *reference;
    dst.noise.clone_from(noise);
    dst.threshold = *threshold;
    dst.report.clone_from(report);
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
            delay: FractionalDelay::new(0.0),
            pool: Vec::new(),
            accs: Vec::new(),
            consumed: Vec::new(),
            rest: VecDeque::new(),
            template: None,
        }
    }

    fn stores_frames(&self) -> bool {
        self.cfg.mode == AveragingMode::Sliding || self.cfg.method != AveragingMethod::Mean
    }

    /// Empty storage for a channel in volts, from the pool.
    fn take_volts(&mut self) -> Vec<f64> {
        let mut v = self.pool.pop().unwrap_or_default();
        v.clear();
        v
    }

    /// An empty accumulator for frames of `len` samples, from the spares.
    fn take_acc(&mut self, len: usize) -> Acc {
        match self.accs.pop() {
            Some(mut a) => {
                a.reset(len);
                a
            }
            None => Acc::new(len),
        }
    }

    /// Puts a group's storage with the spares; its first unit is consumed.
    fn recycle_group(&mut self, g: Group) {
        self.consumed.push(g.first);
        self.accs.push(g.stop);
        self.accs.extend(g.start);
    }

    /// Puts a kept frame's storage with the spares; its unit is consumed.
    fn recycle_kept(&mut self, k: Kept) {
        self.consumed.push(k.work);
        self.pool.push(k.stop);
        self.pool.extend(k.start);
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

    /// Aligned volts of channel `c` of `w` into `out` (`delay` is replanned for `shift`).
    fn aligned(c: &Channel, shift: f64, delay: &mut FractionalDelay, raw: &mut Vec<f64>, out: &mut Vec<f64>) {
        c.volts_into(raw);
        out.clear();
        out.resize(raw.len(), 0.0);
        delay.set_delay(shift);
        delay.apply(raw, out);
    }

    /// Adds `w` to the group (`None`: the group's own first frame).
    fn add_to_group(&mut self, g: &mut Group, w: Option<&Work>) {
        let Group {
            first,
            stop: stop_acc,
            start: start_acc,
            var_sum,
            t_var_sum,
            t_sum_s,
            t_count,
        } = g;
        let w = w.unwrap_or(first);
        let shift = self.shift_of(w);
        let stop = &w.frame.channels[w.source.stop];
        let mut volts = std::mem::take(&mut self.volts);
        let mut shifted = std::mem::take(&mut self.shifted);
        match shift {
            Some(d) => {
                Self::aligned(stop, d, &mut self.delay, &mut volts, &mut shifted);
                stop_acc.add_volts(&shifted);
                std::mem::swap(&mut volts, &mut shifted);
            }
            None => {
                stop_acc.add_channel(stop, &mut self.scratch);
                stop.volts_into(&mut volts);
            }
        }
        *var_sum += self.gate_variance(w, &volts);
        *t_var_sum += w.reference.t_ref_sigma_s * w.reference.t_ref_sigma_s;
        if has_start_pulse(w) {
            *t_sum_s += w.reference.t_ref_s;
            *t_count += 1;
        }
        if let (Some(acc), Some(s)) = (start_acc, w.source.start) {
            let ch = &w.frame.channels[s];
            match shift {
                Some(d) => {
                    Self::aligned(ch, d, &mut self.delay, &mut volts, &mut shifted);
                    acc.add_volts(&shifted);
                }
                None => acc.add_channel(ch, &mut self.scratch),
            }
        }
        self.volts = volts;
        self.shifted = shifted;
    }

    fn new_group(&mut self, w: Unit) -> Group {
        let n = w.frame.len();
        let stop = self.take_acc(n);
        let start = w.source.start.is_some().then(|| self.take_acc(n));
        let mut g = Group {
            stop,
            start,
            var_sum: 0.0,
            t_var_sum: 0.0,
            t_sum_s: 0.0,
            t_count: 0,
            first: w,
        };
        self.add_to_group(&mut g, None);
        g
    }

    /// Output work from a mean (or robust) stop/start and the group's
    /// bookkeeping. The frame becomes the mean frame: its stop channel, then
    /// its start channel (names kept), holding `stop` and `start` (storage
    /// lent to the frame, see [`Work::set_volts`]).
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        mut w: Unit,
        stop: Vec<f64>,
        start: Option<Vec<f64>>,
        count: u32,
        var_sum: f64,
        t_var_sum: f64,
        mean_t_s: Option<f64>,
        seq_last: u64,
    ) -> Unit {
        // The unit pays for the storage lent to it with spare storage of its
        // own (storage an earlier stage lent to its frame first): the unit's
        // and the pool's counts stay the same, whichever units the groups end
        // in, so neither side grows without bound nor runs short.
        w.reclaim_volts();
        let with_start = w.source.start.is_some() && start.is_some();
        for _ in 0..1 + with_start as usize {
            let spare = w.spare_volts();
            self.pool.push(spare);
        }
        let (s_stop, s_start) = (w.source.stop, w.source.start);
        let channels = &mut w.frame.channels;
        channels.swap(0, s_stop);
        if let (true, Some(s)) = (with_start, s_start) {
            // Channel 0 went to `s_stop` in the swap above.
            channels.swap(1, if s == 0 { s_stop } else { s });
        }
        channels.truncate(1 + with_start as usize);
        channels[0].role = ChannelRole::Stop;
        w.set_volts(0, stop);
        if let (true, Some(v)) = (with_start, start) {
            w.frame.channels[1].role = ChannelRole::Start;
            w.set_volts(1, v);
        }
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
            w.report.t_start_sigma_s = w.reference.t_ref_sigma_s;
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

    fn emit_group(&mut self, mut g: Group, out: &mut Vec<Unit>, partial: bool) {
        let mut stop = self.take_volts();
        g.stop.mean_v(&mut stop);
        let start = match &mut g.start {
            Some(a) => {
                let mut v = self.take_volts();
                a.mean_v(&mut v);
                Some(v)
            }
            None => None,
        };
        let count = g.count();
        let seq_last = g.first.source.seq_last;
        let mean_t = (g.t_count > 0).then(|| g.t_sum_s / g.t_count as f64);
        let Group {
            first,
            stop: stop_acc,
            start: start_acc,
            var_sum,
            t_var_sum,
            ..
        } = g;
        self.accs.push(stop_acc);
        self.accs.extend(start_acc);
        let mut w = self.finish(
            first,
            stop,
            start,
            count,
            var_sum,
            t_var_sum,
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
    fn process_block_mean(&mut self, w: Unit, out: &mut Vec<Unit>) {
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
                self.add_to_group(&mut g, Some(&w));
                self.consumed.push(w);
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
    fn close_block(&mut self, out: &mut Vec<Unit>) {
        let Some(mut b) = self.block.take() else {
            return;
        };
        match self.group.take() {
            None => self.group = Some(b),
            Some(mut g) => {
                let (mut gm, mut bm) = (self.take_volts(), self.take_volts());
                g.stop.mean_v(&mut gm);
                b.stop.mean_v(&mut bm);
                let changed = self.changed(&g.first, &gm, &bm, g.count(), b.count());
                self.pool.push(gm);
                self.pool.push(bm);
                if changed {
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
                    self.recycle_group(b);
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
        if self.template.as_ref().is_none_or(|t| t.0 != dt) {
            let (h, peak_idx) = self.return_pulse.shape(dt).template();
            let e: f64 = h.iter().map(|v| v * v).sum();
            self.template = Some((dt, h, peak_idx, e));
        }
        let (_, h, peak_idx, e) = self.template.as_ref().expect("set above");
        let (h, peak_idx, e) = (h.as_slice(), *peak_idx, *e);
        if e.is_nan() || e <= 0.0 {
            return false;
        }
        let gates = w.place_gates(&mut self.gates);
        let quiet = w.quiet_ranges(&mut self.gates);
        let a = PeakFit::new(older, h, peak_idx, e, &gates.range, &quiet);
        let b = PeakFit::new(newer, h, peak_idx, e, &gates.range, &quiet);
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
            a.amplitude_at(older, h, peak_idx, e, at),
            b.amplitude_at(newer, h, peak_idx, e, at),
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
    fn process_kept(&mut self, w: Unit, out: &mut Vec<Unit>) {
        if self
            .kept
            .front()
            .is_some_and(|k| !Self::matches(&k.work, &w))
        {
            if self.cfg.mode == AveragingMode::Block {
                self.emit_kept(out, true);
            }
            while let Some(k) = self.kept.pop_front() {
                self.recycle_kept(k);
            }
            self.reference_s = None;
            self.since_report = 0;
        }
        let shift = self.shift_of(&w).unwrap_or(0.0);
        let mut raw = std::mem::take(&mut self.scratch);
        let mut stop = self.take_volts();
        Self::aligned(&w.frame.channels[w.source.stop], shift, &mut self.delay, &mut raw, &mut stop);
        let start = match w.source.start {
            Some(s) => {
                let mut v = self.take_volts();
                Self::aligned(&w.frame.channels[s], shift, &mut self.delay, &mut raw, &mut v);
                Some(v)
            }
            None => None,
        };
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
            let (mut older, mut newer) = (self.take_volts(), self.take_volts());
            mean_of(self.kept.iter().take(split).map(|k| k.stop.as_slice()), &mut older);
            mean_of(self.kept.iter().skip(split).map(|k| k.stop.as_slice()), &mut newer);
            // Out of the window while it is compared (`changed` needs the stage).
            let front = self.kept.pop_front().expect("more than guard frames");
            let changed = self.changed(&front.work, &older, &newer, split as u32, guard as u32);
            self.kept.push_front(front);
            self.pool.push(older);
            self.pool.push(newer);
            if changed {
                if self.cfg.mode == AveragingMode::Block {
                    let mut rest = std::mem::take(&mut self.rest);
                    rest.extend(self.kept.drain(split..));
                    self.nonstationary = true;
                    let r = self.reference_s;
                    self.emit_kept(out, true);
                    self.reference_s = r;
                    self.kept.extend(rest.drain(..));
                    self.rest = rest;
                } else {
                    // The window restarts at the change; its next report says so.
                    for _ in 0..split {
                        let k = self.kept.pop_front().expect("split < len");
                        self.recycle_kept(k);
                    }
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
                    let k = self.kept.pop_front().expect("len > n");
                    self.recycle_kept(k);
                }
                if self.kept.len() == n && self.since_report >= self.cfg.hop {
                    self.since_report = 0;
                    self.report_window(out, false);
                }
            }
        }
    }

    /// Reports the kept frames' statistic. In block mode the window is
    /// emptied: the front frame's own unit carries the report. In sliding
    /// mode the window stays, and a consumed unit is made a copy of the
    /// front frame's (a new one only while there is none).
    fn report_window(&mut self, out: &mut Vec<Unit>, partial: bool) {
        let Some(front) = self.kept.front() else {
            return;
        };
        let seq_last = self.kept.back().map_or(front.work.source.seq_last, |k| k.work.source.seq_last);
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
        let mut stop = self.pool.pop().unwrap_or_default();
        let mut scratch = std::mem::take(&mut self.scratch);
        robust_into(self.kept.iter().map(|k| k.stop.as_slice()), trim, &mut stop, &mut scratch);
        let start = front.work.source.start.map(|_| {
            let mut v = self.pool.pop().unwrap_or_default();
            robust_into(self.kept.iter().filter_map(|k| k.start.as_deref()), trim, &mut v, &mut scratch);
            v
        });
        self.scratch = scratch;
        let laser_off_in_group = self.kept.iter().any(|k| k.work.frame.laser_off);
        let starts = self.kept.iter().filter(|k| has_start_pulse(&k.work)).map(|k| k.work.reference.t_ref_s);
        let n_starts = starts.clone().count();
        let mean_t = (n_starts > 0).then(|| starts.sum::<f64>() / n_starts as f64);
        let mut first = if self.cfg.mode == AveragingMode::Block {
            let k = self.kept.pop_front().expect("not empty");
            self.pool.push(k.stop);
            self.pool.extend(k.start);
            k.work
        } else {
            let front = &self.kept.front().expect("not empty").work;
            match self.consumed.pop() {
                Some(mut u) => {
                    copy_but_samples(&mut u, front);
                    u
                }
                None => front.clone(),
            }
        };
        if laser_off_in_group && !first.frame.laser_off {
            first.report.flags.push(FrameFlag::LaserOffInGroup);
        }
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

    fn emit_kept(&mut self, out: &mut Vec<Unit>, partial: bool) {
        if self.kept.is_empty() {
            return;
        }
        self.report_window(out, partial);
        while let Some(k) = self.kept.pop_front() {
            self.recycle_kept(k);
        }
        self.reference_s = None;
    }
}

/// The robust average of equally long frames into `out` (sized by the first
/// frame; see [`robust_average_of`]).
fn robust_into<'a>(frames: impl Iterator<Item = &'a [f64]> + Clone, trim: f64, out: &mut Vec<f64>, scratch: &mut Vec<f64>) {
    out.clear();
    out.resize(frames.clone().next().map_or(0, |f| f.len()), 0.0);
    robust_average_of(frames, trim, out, scratch);
}

/// Per-sample mean of equally long frames into `out`.
fn mean_of<'a>(frames: impl Iterator<Item = &'a [f64]>, out: &mut Vec<f64>) {
    out.clear();
    let mut n = 0usize;
    for f in frames {
        if out.is_empty() {
            out.resize(f.len(), 0.0);
        }
        crate::dsp::accumulate::add_f64(out, f);
        n += 1;
    }
    let inv = 1.0 / n.max(1) as f64;
    out.iter_mut().for_each(|v| *v *= inv);
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

    fn process(&mut self, w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        if self.stores_frames() {
            self.process_kept(w, out);
        } else {
            self.process_block_mean(w, out);
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Unit>) {
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

    fn consumed(&mut self) -> Option<Unit> {
        self.consumed.pop()
    }
}
