//! The scene simulator: frames and ground truth.
//!
//! Everything deterministic is computed once in [`Simulator::new`]: the
//! noise-free start and stop waveforms on a fine internal grid (the exact
//! discrete chain, started from the periodic steady state of the shot train,
//! so AC-coupling baselines and returns of earlier shots beyond the
//! unambiguous range are in place), the truth template, the coloured-noise
//! filters and the shot-noise envelope. [`Simulator::frame`] then only samples
//! (with trigger and aperture jitter), adds noise, the interference burst and
//! the interference events, and quantises, from an RNG derived from
//! `(seed, index)` alone (the events from their own stream, so a scene with
//! events gives the same noise as the scene without them).
//!
//! ## Ground truth
//!
//! Times in [`Truth`] are relative to the frame's trigger, like
//! `Frame::sample_time_s`. `t_start_s` is the 50 % leading-edge crossing of the
//! noise-free start pulse of this frame's shot (0 when the scene has no start
//! channel: the trigger is then the time reference). For each return,
//! `t_stop_s` is the 50 % leading-edge crossing of that target's own noise-free
//! stop pulse (50 % of its peak above the baseline just before it) and
//! `tof_s = t_stop_s − t_start_s` (for a return of another shot, e.g. a target
//! beyond the unambiguous range, from that shot's start crossing
//! `t_start_s + shot_offset / PRF`), nothing subtracted: the chain's system delay
//! (different rise times and electrical delays of the two paths) stays in, and
//! is what `calibrate` learns. `range_m` is the geometric range.
//!
//! Each interference event ([`TrueEvent`]) is given by its onset `start_s`
//! (nominal sample time, like the samples it is added to: sample `k` of the
//! frame is at `first_sample_offset_s + k·dt` whatever the trigger jitter, as
//! the events are tied to the mains, not to the shot), the instant of its
//! largest positive excursion `t_peak_s` and that excursion `peak_v`.

use crate::scene::simulation::SimulationError;
use crate::scene::simulation::{LaserPulseShape, RingingConfig, SimulationConfig};
use super::photodetector::{Chain, StateSpace, coast, periodic_state, run_chain};
use super::digitiser::{FineWave, Quantiser};
use super::link_budget::{self, LinkBudgetLine, Q_E};
use super::noise_source::{Burst, ColouredNoise, InterferenceEvent, c_for_skew};
use crate::frame::{Channel, ChannelRole, Frame};
use crate::scene::{FieldError, Scene};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;
use std::f64::consts::PI;

/// One true return in a frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrueReturn {
    /// Index of the target in `simulation.targets`.
    pub target: usize,
    /// Geometric range of the target, m.
    pub range_m: f64,
    /// `t_stop_s` minus the start crossing of this return's own shot
    /// (`t_start_s + shot_offset / PRF`), s: the true, unwrapped time of flight
    /// including the system delay (see the module docs).
    pub tof_s: f64,
    /// Which shot this return belongs to: 0 this frame's, −1 the previous one
    /// (a target beyond the unambiguous range), +1 the next one.
    pub shot_offset: i64,
    /// Peak of the noise-free stop pulse above its baseline, V.
    pub peak_amplitude_v: f64,
    /// 50 % leading-edge crossing of the noise-free stop pulse, s from the trigger.
    pub t_stop_s: f64,
    /// Peak instant of the noise-free stop pulse, s from the trigger.
    pub t_peak_s: f64,
    /// First sample where the pulse exceeds 1 % of its peak (clamped to the frame).
    pub first_sample: usize,
    /// Last sample where the pulse exceeds 1 % of its peak (clamped to the frame).
    pub last_sample: usize,
    /// The pulse extends beyond the frame's first or last sample.
    pub truncated: bool,
    /// The TIA swing or the digitiser's full scale clips the pulse.
    pub saturated: bool,
}

/// One interference event in a frame (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrueEvent {
    /// Onset, s from the trigger (nominal sample time).
    pub start_s: f64,
    /// Instant of the largest positive excursion, s from the trigger.
    pub t_peak_s: f64,
    /// Largest positive excursion, V.
    pub peak_v: f64,
    /// The event's largest positive excursion falls within the frame's samples.
    pub peak_in_frame: bool,
}

/// Ground truth of one frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Truth {
    /// The frame's sequence number (its index).
    pub sequence: u64,
    /// Returns whose signal falls in the frame, in time order.
    pub returns: Vec<TrueReturn>,
    /// 50 % crossing of the noise-free start pulse of this frame's shot, s from the trigger.
    pub t_start_s: f64,
    /// The frame's time base offset from the nominal (trigger jitter), s.
    pub trigger_offset_s: f64,
    /// The interference burst is present in this frame.
    pub interference: bool,
    /// Interference events in this frame (`[simulation.interference_events]`).
    pub events: Vec<TrueEvent>,
    /// The laser is off (noise-only frame).
    pub laser_off: bool,
}

/// Header of the truth as CSV ([`Truth::csv_rows`]): one row per frame
/// (`kind` = `frame`: `t_s` the start crossing, `flags` `interference` when
/// the burst is present and `laser_off`), one per return (`return`: `index`
/// the target, `t_s` the 50 % crossing, `t_peak_s`, `peak_v`, `range_m`,
/// `tof_s`, `flags` `truncated`/`saturated`/`shot_offset=K`) and one per
/// interference event (`event`: `index` its number in the frame, `t_s` its
/// onset, `t_peak_s`, `peak_v`, `flags` `peak_outside_frame`). Times in
/// seconds from the trigger; empty cells where a column does not apply.
pub const TRUTH_CSV_HEADER: &str = "sequence,kind,index,t_s,t_peak_s,peak_v,range_m,tof_s,flags";

impl Truth {
    /// The frame's rows of the truth as CSV (see [`TRUTH_CSV_HEADER`]), each ending in a newline.
    pub fn csv_rows(&self) -> String {
        use std::fmt::Write;
        let mut out = String::new();
        let seq = self.sequence;
        let mut flags: Vec<&str> = Vec::new();
        if self.interference {
            flags.push("interference");
        }
        if self.laser_off {
            flags.push("laser_off");
        }
        let _ = writeln!(out, "{seq},frame,,{:e},,,,,{}", self.t_start_s, flags.join(" "));
        for r in &self.returns {
            let mut f = Vec::new();
            if r.truncated {
                f.push("truncated".to_string());
            }
            if r.saturated {
                f.push("saturated".to_string());
            }
            if r.shot_offset != 0 {
                f.push(format!("shot_offset={}", r.shot_offset));
            }
            let _ = writeln!(
                out,
                "{seq},return,{},{:e},{:e},{:e},{},{:e},{}",
                r.target,
                r.t_stop_s,
                r.t_peak_s,
                r.peak_amplitude_v,
                r.range_m,
                r.tof_s,
                f.join(" ")
            );
        }
        for (k, e) in self.events.iter().enumerate() {
            let _ = writeln!(
                out,
                "{seq},event,{k},{:e},{:e},{:e},,,{}",
                e.start_s,
                e.t_peak_s,
                e.peak_v,
                if e.peak_in_frame { "" } else { "peak_outside_frame" }
            );
        }
        out
    }
}

/// Truth of a return before the frame's jitter is applied.
#[derive(Debug, Clone)]
struct ReturnTemplate {
    ret: TrueReturn,
    t_first_s: f64,
    t_last_s: f64,
}

/// A pulse class: recurs every period at `t_s + k T`.
#[derive(Debug, Clone, Copy)]
struct Event {
    /// Reference instant of shot 0 (centre for gaussian, leading edge for rectangular), s.
    t_s: f64,
    /// Peak input (optical power, W).
    amp: f64,
}

/// The pulse shape of the laser.
#[derive(Debug, Clone, Copy)]
struct Pulse {
    shape: LaserPulseShape,
    width_s: f64,
}

impl Pulse {
    /// Extent before and after the reference instant, s.
    fn extent(&self) -> (f64, f64) {
        match self.shape {
            LaserPulseShape::Gaussian => {
                let sigma = self.width_s / (8.0 * 2f64.ln()).sqrt();
                (7.0 * sigma, 7.0 * sigma)
            }
            LaserPulseShape::Rectangular => (0.0, self.width_s),
        }
    }

    /// Average of the unit-peak pulse over `[t, t + h]` relative to its reference.
    fn cell_average(&self, t: f64, h: f64) -> f64 {
        match self.shape {
            LaserPulseShape::Gaussian => {
                let sigma = self.width_s / (8.0 * 2f64.ln()).sqrt();
                let k = 1.0 / (sigma * 2f64.sqrt());
                let e = crate::math::special::erf((t + h) * k) - crate::math::special::erf(t * k);
                e * sigma * (PI / 2.0).sqrt() / h
            }
            LaserPulseShape::Rectangular => {
                let lo = t.max(0.0);
                let hi = (t + h).min(self.width_s);
                ((hi - lo) / h).max(0.0)
            }
        }
    }
}

/// Linear post-processing of a rendered waveform (commutes with the chain).
#[derive(Debug, Clone, Copy)]
enum Post {
    None,
    /// `v(t) + Σ_j c^j v(t − j T)`.
    Echoes {
        coefficient: f64,
        round_trip_s: f64,
        echoes: u32,
    },
    /// `v(t) − d v(t − τ)`.
    Dip {
        fraction: f64,
        delay_s: f64,
    },
}

/// The stop channel's chain from a config: TIA pole (gain R_o·M·R_TIA, input
/// optical power in W, swing limit), then AC coupling, resonance ringing and the
/// digitiser's bandwidth. Without a TIA: unit gain into the digitiser.
pub fn stop_chain(cfg: &SimulationConfig) -> Chain {
    let mut stage2 = StateSpace::identity();
    let (stage1, gain, swing) = match &cfg.tia {
        Some(t) => {
            if let Some(tau) = t.ac_coupling_s {
                stage2 = stage2.then(&StateSpace::ac_coupling(tau));
            }
            if let Some(RingingConfig::Resonance {
                frequency_hz,
                q,
                amplitude,
            }) = &t.ringing
            {
                stage2 = stage2.then(&StateSpace::resonance(*frequency_hz, *q, *amplitude));
            }
            let g = cfg
                .apd
                .as_ref()
                .map_or(1.0, |a| a.responsivity_a_per_w * a.gain)
                * t.gain_ohm;
            (StateSpace::low_pass(t.bandwidth_hz), g, t.swing_v)
        }
        None => (StateSpace::identity(), 1.0, None),
    };
    if let Some(b) = cfg.digitiser.bandwidth_hz {
        stage2 = stage2.then(&StateSpace::low_pass(b));
    }
    Chain {
        stage1,
        stage2,
        gain,
        swing_v: swing,
    }
}

/// The start channel's chain: PIN TIA pole (gain tap·R·R_TIA, input the
/// transmitted optical power in W), then the digitiser's bandwidth.
pub fn start_chain(cfg: &SimulationConfig) -> Option<Chain> {
    let s = cfg.start.as_ref()?;
    let mut stage2 = StateSpace::identity();
    if let Some(b) = cfg.digitiser.bandwidth_hz {
        stage2 = stage2.then(&StateSpace::low_pass(b));
    }
    Some(Chain {
        stage1: StateSpace::low_pass(s.bandwidth_hz),
        stage2,
        gain: s.tap_fraction * s.responsivity_a_per_w * s.gain_ohm,
        swing_v: None,
    })
}

/// Fast time scale of a channel's response (everything but the AC-coupling
/// tail): the sum of its pole time constants, resonance decay and echo spread,
/// s. Used to size search windows around a pulse.
fn fast_time_s(cfg: &SimulationConfig, start: bool) -> f64 {
    let mut t = 0.0;
    if let Some(b) = cfg.digitiser.bandwidth_hz {
        t += 1.0 / (2.0 * PI * b);
    }
    if start {
        if let Some(s) = &cfg.start {
            t += 1.0 / (2.0 * PI * s.bandwidth_hz) + s.dip_delay_s;
        }
    } else if let Some(tia) = &cfg.tia {
        t += 1.0 / (2.0 * PI * tia.bandwidth_hz);
        match tia.ringing {
            Some(RingingConfig::Resonance {
                frequency_hz, q, ..
            }) => t += q / (PI * frequency_hz),
            Some(RingingConfig::Reflection {
                round_trip_s,
                echoes,
                ..
            }) => t += round_trip_s * echoes as f64,
            None => {}
        }
    }
    t
}

/// Renders the periodic steady-state noise-free output of `chain` for the
/// pulse classes `events` on the fine grid `[t_lo, t_hi]` with step `h`.
/// Also returns the largest |amplifier output| before its clamp per fine
/// step (to flag saturation).
fn render(
    chain: &Chain,
    pulse: Pulse,
    events: &[Event],
    period_s: Option<f64>,
    grid: Grid,
    post: Post,
) -> (FineWave, Vec<f64>) {
    let Grid { t_lo, t_hi, h } = grid;
    let d1 = chain.stage1.discretise(h);
    let d2 = chain.stage2.discretise(h);
    let (ext_a, ext_b) = pulse.extent();
    // The amplifier output must have decayed far below its swing before a
    // quiet gap is coasted through linearly.
    let settle = 40.0 * chain.stage1.a.first().map_or(0.0, |a| 1.0 / a.abs());
    let mut x1 = vec![0.0; d1.n];
    let mut x2 = vec![0.0; d2.n];
    // Active intervals of all instances of the events between `from` and `to`.
    let instances = |from: f64, to: f64| -> Vec<(f64, f64, f64, f64)> {
        let mut out = Vec::new();
        for e in events {
            match period_s {
                Some(t) => {
                    let k0 = ((from - e.t_s - ext_b - settle) / t).floor() as i64;
                    let k1 = ((to - e.t_s + ext_a) / t).ceil() as i64;
                    for k in k0..=k1 {
                        let c = e.t_s + k as f64 * t;
                        let (a, b) = (c - ext_a, c + ext_b + settle);
                        if b > from && a < to {
                            out.push((a, b, c, e.amp));
                        }
                    }
                }
                None => {
                    let (a, b) = (e.t_s - ext_a, e.t_s + ext_b + settle);
                    if b > from && a < to {
                        out.push((a, b, e.t_s, e.amp));
                    }
                }
            }
        }
        out.sort_by(|p, q| p.0.total_cmp(&q.0));
        out
    };
    // A quiet cut at or before t_lo.
    let mut t_cut = t_lo;
    // Bounded: with pulses back to back there may be no quiet instant; then the
    // window starts from rest at the last cut tried.
    for _ in 0..10_000 {
        let moved = instances(t_cut - h, t_cut + h)
            .iter()
            .filter(|i| i.0 < t_cut && i.1 > t_cut)
            .map(|i| i.0)
            .fold(t_cut, f64::min);
        if moved >= t_cut {
            break;
        }
        t_cut = moved - h;
    }
    let input_at = |inst: &[(f64, f64, f64, f64)], t: f64| -> f64 {
        inst.iter()
            .filter(|i| t + h > i.0 && t < i.1)
            .map(|i| i.3 * pulse.cell_average(t - i.2, h))
            .sum()
    };
    if let Some(period) = period_s
        && !events.is_empty()
    {
        // One period before the cut, from rest: merged active intervals
        // simulated finely, quiet gaps coasted exactly.
        let inst = instances(t_cut - period, t_cut);
        let mut t = t_cut - period;
        let mut i = 0;
        while i < inst.len() {
            let start = inst[i].0.max(t);
            let mut end = inst[i].1;
            let mut j = i + 1;
            while j < inst.len() && inst[j].0 <= end {
                end = end.max(inst[j].1);
                j += 1;
            }
            let end = end.min(t_cut);
            if start > t {
                coast(chain, &mut x1, &mut x2, start - t);
            }
            let steps = ((end - start) / h).ceil().max(0.0) as usize;
            let group = &inst[i..j];
            let input: Vec<f64> = (0..steps)
                .map(|k| input_at(group, start + k as f64 * h))
                .collect();
            run_chain(chain, &d1, &d2, &mut x1, &mut x2, &input);
            t = start + steps as f64 * h;
            i = j;
        }
        if t_cut > t {
            coast(chain, &mut x1, &mut x2, t_cut - t);
        } else if t > t_cut {
            // Overshoot of the last fine step past the cut (< h, in a quiet
            // gap): negligible, the state is coasted back by ignoring it.
        }
        let joint: Vec<f64> = x1.iter().chain(x2.iter()).copied().collect();
        let ss = periodic_state(chain, period, &joint);
        x1.copy_from_slice(&ss[..d1.n]);
        x2.copy_from_slice(&ss[d1.n..]);
    }
    // The window, finely, from the cut.
    let steps = ((t_hi - t_cut) / h).ceil() as usize + 2;
    let inst = instances(t_cut, t_cut + steps as f64 * h);
    let input: Vec<f64> = (0..steps)
        .map(|k| input_at(&inst, t_cut + k as f64 * h))
        .collect();
    // Amplifier output before the clamp (for saturation flags).
    let mut amp = Vec::with_capacity(steps);
    {
        let mut xa = x1.clone();
        let mut s = vec![0.0; d1.n];
        for &u in &input {
            amp.push(d1.step(&mut xa, u, &mut s) * chain.gain);
        }
    }
    let v = run_chain(chain, &d1, &d2, &mut x1, &mut x2, &input);
    let raw = FineWave {
        t0_s: t_cut,
        h_s: h,
        v,
    };
    let wave = match post {
        Post::None => raw,
        Post::Echoes {
            coefficient,
            round_trip_s,
            echoes,
        } => {
            let v = (0..raw.v.len())
                .map(|k| {
                    let t = raw.t0_s + k as f64 * h;
                    let mut s = raw.v[k];
                    let mut c = 1.0;
                    for j in 1..=echoes {
                        c *= coefficient;
                        s += c * raw.at(t - j as f64 * round_trip_s);
                    }
                    s
                })
                .collect();
            FineWave { v, ..raw }
        }
        Post::Dip { fraction, delay_s } => {
            let v = (0..raw.v.len())
                .map(|k| raw.v[k] - fraction * raw.at(raw.t0_s + k as f64 * h - delay_s))
                .collect();
            FineWave { v, ..raw }
        }
    };
    (wave, amp)
}

/// The fine grid to render on: `[t_lo, t_hi]` with step `h`, seconds.
#[derive(Debug, Clone, Copy)]
struct Grid {
    t_lo: f64,
    t_hi: f64,
    h: f64,
}

/// A pulse found in a rendered waveform near a reference instant.
#[derive(Debug, Clone, Copy)]
struct Found {
    peak_v: f64,
    t_half_s: f64,
    t_peak_s: f64,
    t_first_s: f64,
    t_last_s: f64,
    max_amp_out: f64,
}

/// Finds the pulse in `w` between `t_a` and `t_b`: peak above the baseline at
/// `t_a`, 50 % leading-edge crossing, and the 1 % span (searched to `t_tail`).
fn find_pulse(w: &FineWave, amp: &[f64], t_a: f64, t_b: f64, t_tail: f64) -> Option<Found> {
    let idx = |t: f64| {
        (((t - w.t0_s) / w.h_s).round().max(0.0) as usize).min(w.v.len().saturating_sub(1))
    };
    let (ia, ib, it) = (idx(t_a), idx(t_b), idx(t_tail));
    if ib <= ia {
        return None;
    }
    let base = w.v[ia];
    let (mut ip, mut peak) = (ia, 0.0);
    for i in ia..=ib {
        if w.v[i] - base > peak {
            peak = w.v[i] - base;
            ip = i;
        }
    }
    if peak <= 0.0 {
        return None;
    }
    let half = base + 0.5 * peak;
    let mut i = ip;
    while i > ia && w.v[i - 1] >= half {
        i -= 1;
    }
    let t_half = if i > ia {
        let (v0, v1) = (w.v[i - 1], w.v[i]);
        w.t0_s + (i as f64 - 1.0 + (half - v0) / (v1 - v0)) * w.h_s
    } else {
        w.t0_s + i as f64 * w.h_s
    };
    let thr = 0.01 * peak;
    let first = (ia..=ip)
        .find(|&k| (w.v[k] - base).abs() > thr)
        .unwrap_or(ip);
    let last = (ip..=it.max(ip))
        .rev()
        .find(|&k| (w.v[k] - base).abs() > thr)
        .unwrap_or(ip);
    let max_amp_out = amp[ia.min(amp.len() - 1)..=ib.min(amp.len() - 1)]
        .iter()
        .fold(0.0f64, |m, x| m.max(x.abs()));
    Some(Found {
        peak_v: peak,
        t_half_s: t_half,
        t_peak_s: w.t0_s + ip as f64 * w.h_s,
        t_first_s: w.t0_s + first as f64 * w.h_s,
        t_last_s: w.t0_s + last as f64 * w.h_s,
        max_amp_out,
    })
}

/// The frame's time base and the laser's emission, which every part of the
/// simulator is built on.
#[derive(Debug, Clone, Copy)]
struct TimeBase {
    /// Sample interval, s.
    dt: f64,
    /// Samples per frame.
    n: usize,
    /// Time of the first sample relative to the trigger, s.
    t_first: f64,
    /// Time of the last sample relative to the trigger, s.
    t_last: f64,
    /// Step of the fine grid waveforms are rendered on, s.
    h: f64,
    /// Start of the fine grid: covers every instant a jittered sample can take, s.
    t_lo: f64,
    /// End of the fine grid, s.
    t_hi: f64,
    /// Laser period (1/PRF), s; `None` without a laser.
    period: Option<f64>,
    /// Trigger period (1/PRF, or the frame length without a laser), s.
    frame_period_s: f64,
    /// Laser off or absent.
    laser_off: bool,
    /// The emitted pulse.
    pulse: Pulse,
    /// Emission instant relative to the trigger, s.
    emit: f64,
}

impl TimeBase {
    fn new(cfg: &SimulationConfig) -> TimeBase {
        let d = &cfg.digitiser;
        let dt = d.sample_interval_s;
        let n = d.samples_per_frame;
        let t_first = -(d.pre_trigger_samples as f64) * dt;
        let t_last = t_first + (n - 1) as f64 * dt;
        let h = dt / d.oversample as f64;
        // The fine grid covers every instant a jittered sample can take.
        let jitter_span = 8.0 * (d.trigger_jitter_s + d.aperture_jitter_s) + dt;
        let (t_lo, t_hi) = (
            t_first - jitter_span - 2.0 * dt,
            t_last + jitter_span + 2.0 * dt,
        );
        let laser = cfg.laser.as_ref();
        let laser_off = laser.is_none_or(|l| l.off);
        let period = laser.map(|l| 1.0 / l.prf_hz);
        let frame_period_s = period.unwrap_or(n as f64 * dt);
        let pulse = Pulse {
            shape: laser.map_or(LaserPulseShape::Gaussian, |l| l.pulse_shape),
            width_s: laser.map_or(1e-9, |l| l.pulse_width_s),
        };
        let emit = laser.map_or(0.0, |l| l.emission_time_s);
        TimeBase {
            dt,
            n,
            t_first,
            t_last,
            h,
            t_lo,
            t_hi,
            period,
            frame_period_s,
            laser_off,
            pulse,
            emit,
        }
    }

    /// The fine grid.
    fn grid(&self) -> Grid {
        Grid {
            t_lo: self.t_lo,
            t_hi: self.t_hi,
            h: self.h,
        }
    }
}

/// The stop channel: receiver chain, reflections after it, one event per
/// target, and the noise-free waveform they render to.
struct StopChannel {
    chain: Chain,
    post: Post,
    /// One per target (none with the laser off); optical peak power in W.
    events: Vec<Event>,
    wave: FineWave,
}

impl StopChannel {
    fn new(cfg: &SimulationConfig, tb: &TimeBase, c_m: f64) -> StopChannel {
        let chain = stop_chain(cfg);
        let stop_delay = cfg.tia.as_ref().map_or(0.0, |t| t.delay_s);
        let post = match cfg.tia.as_ref().and_then(|t| t.ringing.clone()) {
            Some(RingingConfig::Reflection {
                coefficient,
                round_trip_s,
                echoes,
            }) => Post::Echoes {
                coefficient,
                round_trip_s,
                echoes,
            },
            _ => Post::None,
        };
        let powers: Vec<f64> = cfg
            .targets
            .iter()
            .map(|t| link_budget::received_power_w(cfg, t))
            .collect();
        let events: Vec<Event> = if tb.laser_off {
            vec![]
        } else {
            cfg.targets
                .iter()
                .zip(&powers)
                .map(|(t, &p)| Event {
                    t_s: tb.emit + 2.0 * t.range_m / c_m + stop_delay,
                    amp: p,
                })
                .collect()
        };
        let (wave, _) = render(&chain, tb.pulse, &events, tb.period, tb.grid(), post);
        StopChannel {
            chain,
            post,
            events,
            wave,
        }
    }
}

/// The start channel, when the scene has one: its chain, the laser's event
/// on it, and the noise-free waveform.
struct StartChannel {
    chain: Option<Chain>,
    /// The dip after the start pulse, if any.
    post: Post,
    /// The laser shot (none with the laser off or without a start channel).
    events: Vec<Event>,
    wave: Option<FineWave>,
}

impl StartChannel {
    fn new(cfg: &SimulationConfig, tb: &TimeBase) -> StartChannel {
        let chain = start_chain(cfg);
        let post = match &cfg.start {
            Some(s) if s.dip_fraction > 0.0 => Post::Dip {
                fraction: s.dip_fraction,
                delay_s: s.dip_delay_s,
            },
            _ => Post::None,
        };
        let (wave, events) = match (&chain, &cfg.start) {
            (Some(sc), Some(s)) => {
                let ev: Vec<Event> = if tb.laser_off {
                    vec![]
                } else {
                    vec![Event {
                        t_s: tb.emit + s.delay_s,
                        amp: cfg.laser.as_ref().map_or(0.0, |l| l.peak_power_w),
                    }]
                };
                (Some(render(sc, tb.pulse, &ev, tb.period, tb.grid(), post).0), ev)
            }
            _ => (None, vec![]),
        };
        StartChannel {
            chain,
            post,
            events,
            wave,
        }
    }
}

/// Unjittered 50 % crossing of the start pulse, s (0 without one).
fn start_truth(cfg: &SimulationConfig, tb: &TimeBase, start: &StartChannel) -> f64 {
    let (ext_a, ext_b) = tb.pulse.extent();
    match (&start.chain, start.events.first()) {
        (Some(sc), Some(ev)) => {
            let lo = ev.t_s - ext_a - tb.h;
            let hi = ev.t_s + ext_b + 10.0 * fast_time_s(cfg, true);
            let (w, amp) = render(
                sc,
                tb.pulse,
                &[*ev],
                tb.period,
                Grid {
                    t_lo: lo.min(tb.t_lo),
                    t_hi: hi.max(tb.t_hi),
                    h: tb.h,
                },
                start.post,
            );
            find_pulse(&w, &amp, lo, hi, hi).map_or(0.0, |f| f.t_half_s)
        }
        _ => 0.0,
    }
}

/// Unjittered truth of every return in the frame (every shot of every
/// target whose pulse reaches the frame), in order of stop time.
fn return_truth(
    cfg: &SimulationConfig,
    tb: &TimeBase,
    stop: &StopChannel,
    quant: Quantiser,
    offset_v: f64,
    t_start_s: f64,
) -> Vec<ReturnTemplate> {
    let (ext_a, ext_b) = tb.pulse.extent();
    let (t_lo, t_hi, h, period) = (tb.t_lo, tb.t_hi, tb.h, tb.period);
    let fast = fast_time_s(cfg, false);
    let mut returns = Vec::new();
    for (j, ev) in stop.events.iter().enumerate() {
        let (w, amp) = render(&stop.chain, tb.pulse, &[*ev], period, Grid { t_lo, t_hi, h }, stop.post);
        let shots: Vec<i64> = match period {
            Some(p) => {
                let k0 = ((t_lo - ev.t_s - ext_b - 10.0 * fast) / p).floor() as i64;
                let k1 = ((t_hi - ev.t_s + ext_a) / p).ceil() as i64;
                (k0..=k1).collect()
            }
            None => vec![0],
        };
        for k in shots {
            let c = ev.t_s + k as f64 * period.unwrap_or(0.0);
            let (a, b) = (c - ext_a - h, c + ext_b + 10.0 * fast);
            if b < tb.t_first || a > tb.t_last {
                continue;
            }
            let Some(f) = find_pulse(&w, &amp, a.max(t_lo), b.min(t_hi), (b + 20.0 * fast).min(t_hi)) else {
                continue;
            };
            let saturated = stop.chain.swing_v.is_some_and(|s| f.max_amp_out >= s)
                || quant.clips(stop.wave.at(f.t_peak_s) + offset_v);
            returns.push(ReturnTemplate {
                ret: TrueReturn {
                    target: j,
                    range_m: cfg.targets[j].range_m,
                    tof_s: f.t_half_s - (t_start_s + k as f64 * period.unwrap_or(0.0)),
                    shot_offset: k,
                    peak_amplitude_v: f.peak_v,
                    t_stop_s: f.t_half_s,
                    t_peak_s: f.t_peak_s,
                    first_sample: 0,
                    last_sample: 0,
                    truncated: false,
                    saturated,
                },
                t_first_s: f.t_first_s,
                t_last_s: f.t_last_s,
            });
        }
    }
    returns.sort_by(|a, b| a.ret.t_stop_s.total_cmp(&b.ret.t_stop_s));
    returns
}

/// The noise generators of both channels.
struct NoiseGenerators {
    /// Stop channel: thermal, dark-current and background shot noise through the chain.
    stop: Option<ColouredNoise>,
    /// Signal shot-noise innovation variance per sample (V² at the TIA output), if any signal.
    stop_envelope: Option<Vec<f64>>,
    /// Start channel.
    start: Option<ColouredNoise>,
}

impl NoiseGenerators {
    fn new(
        cfg: &SimulationConfig,
        tb: &TimeBase,
        stop: &StopChannel,
        start: &StartChannel,
    ) -> Result<NoiseGenerators, SimulationError> {
        let dt = tb.dt;
        let lin = stop.chain.linear();
        let nf = lin.discretise(dt);
        let unit_gain = nf.stationary_output_variance().sqrt();
        let tia_r = cfg.tia.as_ref().map_or(1.0, |t| t.gain_ohm);
        let (m2f, r_o, i_d) = match &cfg.apd {
            Some(a) => (
                a.gain * a.gain * link_budget::excess_noise_factor(a.gain, a.ionisation_ratio_k),
                a.responsivity_a_per_w,
                a.dark_current_a,
            ),
            None => (0.0, 0.0, 0.0),
        };
        // Innovation variance per sample for a one-sided current density S: S/(2 dt) · R².
        let per_sample = |s_a2_per_hz: f64| s_a2_per_hz / (2.0 * dt) * tia_r * tia_r;
        let p_bg = link_budget::background_power_w(cfg);
        let var_db = per_sample(2.0 * Q_E * (i_d + r_o * p_bg) * m2f);
        let var_th = match cfg.noise.as_ref().and_then(|n| n.thermal_sigma_v) {
            Some(s) => {
                if unit_gain > 0.0 {
                    (s / unit_gain).powi(2)
                } else {
                    0.0
                }
            }
            None => cfg.tia.as_ref().map_or(0.0, |t| {
                per_sample(t.noise_current_a * t.noise_current_a / t.bandwidth_hz)
            }),
        };
        let sigma_stationary = ((var_th + var_db).max(0.0)).sqrt() * unit_gain;
        // Shot-noise envelope from the optical power at the detector.
        let stop_envelope = if !tb.laser_off && !stop.events.is_empty() && m2f > 0.0 {
            let p_wave = render_optical(tb.pulse, &stop.events, tb.period, tb.t_first, dt, tb.n);
            Some(
                p_wave
                    .iter()
                    .map(|&p| per_sample(2.0 * Q_E * r_o * p * m2f))
                    .collect::<Vec<f64>>(),
            )
        } else {
            None
        };
        let skew_c = match cfg.noise.as_ref().and_then(|n| n.skewness) {
            Some(g) if g != 0.0 => {
                let kappa = ColouredNoise::skew_transfer(&nf);
                let needed = if kappa > 0.0 {
                    g / kappa
                } else {
                    f64::INFINITY
                };
                c_for_skew(needed).ok_or(SimulationError::Invalid(FieldError::new(
                    "simulation.noise.skewness",
                    format!("{g} (needs innovation skewness {needed:.3} through this chain)"),
                    "a skewness the chain can deliver: |skewness| < 2.83 x the chain's skew transfer",
                )))?
            }
            _ => 0.0,
        };
        let stop_noise = (sigma_stationary > 0.0 || stop_envelope.is_some())
            .then(|| ColouredNoise::new(nf.clone(), sigma_stationary, skew_c));
        let start_noise = match (&start.chain, &cfg.start) {
            (Some(sc), Some(s)) if s.noise_sigma_v > 0.0 => Some(ColouredNoise::new(
                sc.linear().discretise(dt),
                s.noise_sigma_v,
                0.0,
            )),
            _ => None,
        };
        Ok(NoiseGenerators {
            stop: stop_noise,
            stop_envelope,
            start: start_noise,
        })
    }
}

/// The interference burst, if the scene has one.
fn burst(cfg: &SimulationConfig) -> Option<Burst> {
    cfg.interference.as_ref().map(|i| {
        Burst::new(
            i.amplitude_v,
            i.rate_hz,
            i.duration_s,
            &i.frequencies_hz,
            i.wander_s,
        )
    })
}

/// The simulator built from a scene; see the module docs.
#[derive(Debug, Clone)]
pub struct Simulator {
    /// The configuration it was built from.
    cfg: SimulationConfig,
    /// Frame sensor id (the scene name).
    sensor_id: String,
    /// Sample interval, s.
    dt_s: f64,
    /// Samples per frame.
    n_samples: usize,
    /// Time of sample 0 relative to the trigger, s.
    t_first_s: f64,
    /// Trigger period (1/PRF, or the frame length without a laser), s.
    frame_period_s: f64,
    /// Laser off or absent.
    laser_off: bool,
    /// Codes.
    quant: Quantiser,
    /// Noise-free stop waveform (fine grid).
    stop_wave: FineWave,
    /// Noise-free stop samples when there is no jitter (fast path).
    stop_fixed: Option<Vec<f64>>,
    /// Noise-free start waveform (fine grid), if the scene has a start channel.
    start_wave: Option<FineWave>,
    /// Noise-free start samples when there is no jitter.
    start_fixed: Option<Vec<f64>>,
    /// Stop-channel noise generator.
    stop_noise: Option<ColouredNoise>,
    /// Shot-noise innovation variance per sample (V² at the TIA output), if any signal.
    stop_envelope: Option<Vec<f64>>,
    /// Start-channel noise generator.
    start_noise: Option<ColouredNoise>,
    /// Interference burst.
    burst: Option<Burst>,
    /// Interference events.
    events: Option<InterferenceEvent>,
    /// DC offset of the stop channel, V.
    offset_v: f64,
    /// Unjittered truth of the returns.
    returns: Vec<ReturnTemplate>,
    /// Unjittered start crossing, s.
    t_start_s: f64,
}

/// Stream reserved for per-seed (not per-frame) randomness.
const SEED_STREAM: u64 = u64::MAX;
/// Mixed into the seed of the interference events' generator (one stream per frame).
const EVENT_SEED_SALT: u64 = 0x6576_656E_7473_2121;

impl Simulator {
    /// Builds the simulator; fails if the scene has no `[simulation]` section
    /// or the section is invalid.
    ///
    /// Each part is built by its own function: the time base, the stop chain
    /// and waveform, the start chain and waveform, the truth of the start
    /// crossing and of every return, the noise generators, the interference
    /// burst, and the noise-free samples of a jitter-free digitiser.
    pub fn new(scene: &Scene) -> Result<Simulator, SimulationError> {
        let cfg = scene
            .simulation
            .clone()
            .ok_or(SimulationError::MissingSection {
                section: "simulation",
                needed_by: "the simulator (add a [simulation] section to the scene)",
            })?;
        cfg.validate()?;
        let tb = TimeBase::new(&cfg);
        let d = &cfg.digitiser;
        let quant = Quantiser::new(d.bits, d.full_scale_low_v, d.full_scale_high_v);
        let offset_v = cfg.noise.as_ref().map_or(0.0, |n| n.offset_v);
        let stop = StopChannel::new(&cfg, &tb, scene.c_medium_m_per_s());
        let start = StartChannel::new(&cfg, &tb);
        let t_start_s = start_truth(&cfg, &tb, &start);
        let returns = return_truth(&cfg, &tb, &stop, quant, offset_v, t_start_s);
        let noise = NoiseGenerators::new(&cfg, &tb, &stop, &start)?;
        let burst = burst(&cfg);
        let events = cfg
            .interference_events
            .as_ref()
            .map(|e| InterferenceEvent::new(e.peak_v, e.decay_s, &e.frequencies_hz, e.probability_per_frame));
        let no_jitter =
            d.trigger_jitter_s == 0.0 && d.aperture_jitter_s == 0.0 && !d.sample_clock_asynchronous;
        let sample_all = |w: &FineWave| {
            let mut v = vec![0.0; tb.n];
            w.sample_into(tb.t_first, tb.dt, &mut v);
            v
        };
        let stop_fixed = no_jitter.then(|| sample_all(&stop.wave));
        let start_fixed = match (&start.wave, no_jitter) {
            (Some(w), true) => Some(sample_all(w)),
            _ => None,
        };
        Ok(Simulator {
            sensor_id: scene.name.clone(),
            dt_s: tb.dt,
            n_samples: tb.n,
            t_first_s: tb.t_first,
            frame_period_s: tb.frame_period_s,
            laser_off: tb.laser_off,
            quant,
            stop_wave: stop.wave,
            stop_fixed,
            start_wave: start.wave,
            start_fixed,
            stop_noise: noise.stop,
            stop_envelope: noise.stop_envelope,
            start_noise: noise.start,
            burst,
            events,
            offset_v,
            returns,
            t_start_s,
            cfg,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &SimulationConfig {
        &self.cfg
    }

    /// The digitiser's code mapping.
    pub fn quantiser(&self) -> Quantiser {
        self.quant
    }

    /// The noise-free stop waveform at the nominal sample instants (no jitter, no offset), V.
    pub fn noise_free_stop_v(&self) -> Vec<f64> {
        let mut v = vec![0.0; self.n_samples];
        self.stop_wave
            .sample_into(self.t_first_s, self.dt_s, &mut v);
        v
    }

    /// The noise-free start channel at the sample instants, V (none without a start channel).
    pub fn noise_free_start_v(&self) -> Option<Vec<f64>> {
        let wave = self.start_wave.as_ref()?;
        let mut v = vec![0.0; self.n_samples];
        wave.sample_into(self.t_first_s, self.dt_s, &mut v);
        Some(v)
    }

    /// Stationary noise σ of the stop channel at the digitiser input (before quantisation), V.
    pub fn stop_noise_sigma_v(&self) -> f64 {
        self.stop_noise
            .as_ref()
            .map_or(0.0, |n| n.stationary_std() * n.gain_per_unit_innovation())
    }

    /// Per-target link budget (with the TIA bandwidth as the noise bandwidth).
    pub fn link_budget(&self) -> Vec<LinkBudgetLine> {
        match link_budget::Receiver::from_config(&self.cfg) {
            Some(r) => self
                .cfg
                .targets
                .iter()
                .map(|t| link_budget::line(&self.cfg, &r, t))
                .collect(),
            None => vec![],
        }
    }

    /// Frame `index` for `seed`: deterministic, independent of call order and
    /// thread count (a ChaCha8 stream per `(seed, index)`).
    pub fn frame(&self, seed: u64, index: u64) -> (Frame, Truth) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(index);
        let d = &self.cfg.digitiser;
        let dt = self.dt_s;
        let n = self.n_samples;
        // Time-base offset of this frame relative to the shot.
        let mut delta = 0.0;
        if d.trigger_jitter_s > 0.0 {
            delta += d.trigger_jitter_s * rng.sample::<f64, _>(StandardNormal);
        }
        if d.sample_clock_asynchronous {
            delta += (rng.random::<f64>() - 0.5) * dt;
        }
        let t0 = self.t_first_s + delta;
        let sample = |rng: &mut ChaCha8Rng, w: &FineWave, fixed: &Option<Vec<f64>>| -> Vec<f64> {
            if let Some(f) = fixed {
                return f.clone();
            }
            let mut v = vec![0.0; n];
            if d.aperture_jitter_s > 0.0 {
                for (k, o) in v.iter_mut().enumerate() {
                    let e: f64 = rng.sample(StandardNormal);
                    *o = w.at(t0 + k as f64 * dt + e * d.aperture_jitter_s);
                }
            } else {
                w.sample_into(t0, dt, &mut v);
            }
            v
        };
        let mut stop = sample(&mut rng, &self.stop_wave, &self.stop_fixed);
        if self.offset_v != 0.0 {
            for v in stop.iter_mut() {
                *v += self.offset_v;
            }
        }
        if let Some(noise) = &self.stop_noise {
            let shift = (delta / dt).round() as isize;
            noise.add_to(&mut rng, &mut stop, self.stop_envelope.as_deref(), shift);
        }
        let trigger_time_s = index as f64 * self.frame_period_s;
        let mut interference = false;
        if let Some(b) = &self.burst {
            let mut prng = ChaCha8Rng::seed_from_u64(seed);
            prng.set_stream(SEED_STREAM);
            let period = 1.0 / self.cfg.interference.as_ref().map_or(60.0, |i| i.rate_hz);
            let phase = prng.random::<f64>() * period;
            let (a0, a1) = (
                trigger_time_s + t0,
                trigger_time_s + t0 + (n - 1) as f64 * dt,
            );
            if let Some(start) = b.overlapping(seed, phase, a0, a1) {
                interference = true;
                for (k, v) in stop.iter_mut().enumerate() {
                    *v += b.value_v(a0 + k as f64 * dt - start);
                }
            }
        }
        let mut events = Vec::new();
        if let Some(ev) = &self.events {
            // Its own stream: the frame's other draws are those of the scene without events.
            let mut erng = ChaCha8Rng::seed_from_u64(seed ^ EVENT_SEED_SALT);
            erng.set_stream(index);
            if let Some(onset) = ev.draw(&mut erng, self.t_first_s, n as f64 * dt) {
                ev.add_to(&mut stop, self.t_first_s, dt, onset);
                let t_peak_s = onset + ev.peak_after_onset_s();
                events.push(TrueEvent {
                    start_s: onset,
                    t_peak_s,
                    peak_v: ev.peak_v(),
                    peak_in_frame: t_peak_s <= self.t_first_s + (n - 1) as f64 * dt,
                });
            }
        }
        let mut channels = Vec::with_capacity(2);
        if let Some(w) = &self.start_wave {
            let mut start = sample(&mut rng, w, &self.start_fixed);
            if let Some(noise) = &self.start_noise {
                noise.add_to(&mut rng, &mut start, None, 0);
            }
            channels.push(self.channel(&d.start_channel, ChannelRole::Start, &start));
        }
        channels.push(self.channel(&d.stop_channel, ChannelRole::Stop, &stop));
        let frame = Frame {
            sensor_id: self.sensor_id.clone(),
            sequence: index,
            trigger_time_s,
            sample_interval_s: dt,
            first_sample_offset_s: self.t_first_s,
            channels,
            laser_off: self.laser_off,
        };
        let t_last = self.t_first_s + (n - 1) as f64 * dt;
        let to_index = |t: f64| ((t - self.t_first_s) / dt).clamp(0.0, (n - 1) as f64);
        let returns = self
            .returns
            .iter()
            .filter_map(|r| {
                let (tf, tl) = (r.t_first_s - delta, r.t_last_s - delta);
                if tl < self.t_first_s || tf > t_last {
                    return None;
                }
                let mut ret = r.ret.clone();
                ret.t_stop_s -= delta;
                ret.t_peak_s -= delta;
                ret.first_sample = to_index(tf).ceil() as usize;
                ret.last_sample = to_index(tl).floor() as usize;
                ret.truncated = tf < self.t_first_s || tl > t_last;
                Some(ret)
            })
            .collect();
        let truth = Truth {
            sequence: index,
            returns,
            t_start_s: if self.start_wave.is_some() && !self.laser_off {
                self.t_start_s - delta
            } else {
                0.0
            },
            trigger_offset_s: delta,
            interference,
            events,
            laser_off: self.laser_off,
        };
        (frame, truth)
    }

    fn channel(&self, name: &str, role: ChannelRole, volts: &[f64]) -> Channel {
        Channel {
            name: name.to_string(),
            role,
            samples: self.quant.quantise(volts),
            volts_per_code: self.quant.volts_per_code,
            offset_v: self.quant.offset_v,
        }
    }
}

/// Optical power at the detector at each sample's hold interval (mean over
/// `[t_k, t_k + dt]`), W; the TIA clamp does not limit shot noise.
fn render_optical(
    pulse: Pulse,
    events: &[Event],
    period_s: Option<f64>,
    t_first: f64,
    dt: f64,
    n: usize,
) -> Vec<f64> {
    let (ext_a, ext_b) = pulse.extent();
    let t_last = t_first + n as f64 * dt;
    let mut p = vec![0.0; n];
    for e in events {
        let ks: Vec<i64> = match period_s {
            Some(t) => (((t_first - e.t_s - ext_b) / t).floor() as i64
                ..=((t_last - e.t_s + ext_a) / t).ceil() as i64)
                .collect(),
            None => vec![0],
        };
        for k in ks {
            let c = e.t_s + k as f64 * period_s.unwrap_or(0.0);
            let i0 = (((c - ext_a - t_first) / dt).floor().max(0.0)) as usize;
            let i1 = ((((c + ext_b - t_first) / dt).ceil()).max(0.0) as usize).min(n);
            for (i, pi) in p.iter_mut().enumerate().take(i1).skip(i0) {
                *pi += e.amp * pulse.cell_average(t_first + i as f64 * dt - c, dt);
            }
        }
    }
    p
}

/// Peak of the noise-free stop-channel response, V, to one laser pulse (the
/// configured shape and width) of optical peak power `optical_peak_w` at the
/// detector, through the configured chain from rest (a bench measurement
/// such as the source's TIA gain characterisation, Table 10.7).
pub fn peak_response_v(cfg: &SimulationConfig, optical_peak_w: f64) -> f64 {
    let Some(l) = cfg.laser.as_ref() else {
        return 0.0;
    };
    let pulse = Pulse {
        shape: l.pulse_shape,
        width_s: l.pulse_width_s,
    };
    let chain = stop_chain(cfg);
    let h = cfg.digitiser.sample_interval_s / cfg.digitiser.oversample as f64;
    let (a, b) = pulse.extent();
    let t_hi = b + 30.0 * fast_time_s(cfg, false);
    let (w, _) = render(
        &chain,
        pulse,
        &[Event {
            t_s: 0.0,
            amp: optical_peak_w,
        }],
        None,
        Grid {
            t_lo: -a - h,
            t_hi,
            h,
        },
        Post::None,
    );
    w.v.iter().fold(0.0f64, |m, x| m.max(*x))
}
