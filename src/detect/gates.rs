//! Where in a frame returns are sought (range gate) and where the noise model
//! is fitted and false alarms are counted (noise gates), in sample indices.
//!
//! [`GatePlacer`] is the one place that turns a scene's geometry and a
//! frame's time reference into gates: the noise stage and the stages before
//! it (baseline, denoise, average) each hold one.

use crate::dsp::pulse::Shape;
use crate::frame::Frame;
use crate::math::select::CodeDiffMad;
use crate::scene::{PulseConfig, Scene};
use std::ops::Range;

/// Inputs that place the gates on one frame.
#[derive(Debug, Clone, Copy)]
pub struct GateInputs {
    /// Samples in the frame.
    pub samples: usize,
    /// Sampling period, s.
    pub dt_s: f64,
    /// Time of sample 0 relative to the trigger, s.
    pub first_sample_offset_s: f64,
    /// Time reference (start instant) relative to the trigger, s.
    pub t_ref_s: f64,
    /// Calibrated system delay, s.
    pub delay_s: f64,
    /// Speed of light in the medium, m/s.
    pub c_m_per_s: f64,
    /// Range gate, m.
    pub min_range_m: f64,
    /// Range gate, m.
    pub max_range_m: f64,
    /// Pulse support before its peak, samples (negative).
    pub support_lo: f64,
    /// Pulse support after its peak, samples.
    pub support_hi: f64,
    /// Timing point relative to the peak, samples (negative: on the leading edge).
    pub timing_offset: f64,
    /// Guard between the gates and any possible return, s.
    pub guard_s: f64,
    /// Use samples before the reference.
    pub pre: bool,
    /// Use samples beyond the range gate.
    pub beyond: bool,
    /// The search widens the range gate by this many samples at each end: a
    /// pulse whose shape differs from the scene's may peak off the predicted
    /// place, and a return right at the gate's edge must not be lost.
    pub margin: f64,
}

/// Gate positions on one frame.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Gates {
    /// Peak positions (sample indices) where a return inside the range gate may lie.
    pub range: Range<usize>,
    /// Noise gate before the first possible return.
    pub pre: Range<usize>,
    /// Noise gate after the last possible return.
    pub beyond: Range<usize>,
}

impl Gates {
    /// Places the gates. Ranges are empty where the frame does not reach.
    pub fn place(g: &GateInputs) -> Gates {
        let n = g.samples as f64;
        // Continuous sample index of time t (relative to the trigger).
        let idx = |t_s: f64| (t_s - g.first_sample_offset_s) / g.dt_s;
        let clamp = |x: f64| x.clamp(0.0, n) as usize;
        // Times in seconds divided by dt land a rounding error off integers;
        // snap within 1e-6 sample so gate edges do not depend on it.
        let floor = |x: f64| (x + 1e-6).floor();
        let ceil = |x: f64| (x - 1e-6).ceil();
        let tof = |r_m: f64| 2.0 * r_m / g.c_m_per_s;
        // Peak position p of a pulse whose timing point has time of flight `tof`.
        let peak_at = |tof_s: f64| idx(g.t_ref_s + g.delay_s + tof_s) - g.timing_offset;
        let p_min = peak_at(tof(g.min_range_m)) - g.margin;
        let p_max = peak_at(tof(g.max_range_m)) + g.margin;
        let range = clamp(ceil(p_min))..clamp(floor(p_max) + 1.0);
        let guard = g.guard_s / g.dt_s;
        let pre_end = (idx(g.t_ref_s) - guard).min(p_min + g.support_lo - guard);
        let beyond_start = p_max + g.support_hi + guard;
        let pre = if g.pre { 0..clamp(floor(pre_end)) } else { 0..0 };
        let beyond = if g.beyond { clamp(ceil(beyond_start))..g.samples } else { g.samples..g.samples };
        Gates { range, pre, beyond }
    }

    /// Samples in the noise gates.
    pub fn noise_samples(&self) -> usize {
        self.pre.len() + self.beyond.len()
    }
}

/// Places a frame's range and noise gates from the scene sections that
/// decide them (return pulse, calibration, medium, range and noise gates,
/// timing fraction); the pulse shape is rebuilt only when the sampling
/// period changes.
#[derive(Debug)]
pub struct GatePlacer {
    /// Return pulse (`return_pulse`): its support and FWHM widen the gates.
    pulse_cfg: PulseConfig,
    /// Timing fraction (`timing.fraction`): where on the pulse a range is measured.
    fraction: f64,
    /// Calibrated system delay (`calibration.delay_s`), s.
    delay_s: f64,
    /// Speed of light in the scene's medium, m/s.
    c_m_per_s: f64,
    /// Range gate (`range_gate.min_m`, `range_gate.max_m`), m.
    range_m: (f64, f64),
    /// Noise-gate guard (`noise_gate.guard_s`), s.
    guard_s: f64,
    /// Noise gates used (`noise_gate.pre_trigger`, `noise_gate.beyond_range`).
    pre: bool,
    /// See `pre`.
    beyond: bool,
    /// Return-pulse shape for the current sampling period.
    pulse: Option<(f64, Shape)>,
}

/// The noise gates that are not empty (at most two ranges), without a heap
/// allocation per frame.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct QuietRanges {
    ranges: [Range<usize>; 2],
    len: usize,
}

impl QuietRanges {
    /// The non-empty ranges, in frame order.
    pub fn as_slice(&self) -> &[Range<usize>] {
        &self.ranges[..self.len]
    }

    fn from_ranges(ranges: [Range<usize>; 2]) -> QuietRanges {
        let mut q = QuietRanges::default();
        for r in ranges {
            if !r.is_empty() {
                q.ranges[q.len] = r;
                q.len += 1;
            }
        }
        q
    }
}

impl std::ops::Deref for QuietRanges {
    type Target = [Range<usize>];

    fn deref(&self) -> &[Range<usize>] {
        self.as_slice()
    }
}

impl GatePlacer {
    /// Copies the sections of `scene` that place gates.
    pub fn new(scene: &Scene) -> GatePlacer {
        GatePlacer {
            pulse_cfg: scene.return_pulse.clone(),
            fraction: scene.timing.fraction,
            delay_s: scene.calibration.delay_s,
            c_m_per_s: scene.c_medium_m_per_s(),
            range_m: (scene.range_gate.min_m, scene.range_gate.max_m),
            guard_s: scene.noise_gate.guard_s,
            pre: scene.noise_gate.pre_trigger,
            beyond: scene.noise_gate.beyond_range,
            pulse: None,
        }
    }

    /// Gates of a frame whose stop channel has `samples` samples, timed from
    /// `t_ref_s` (the start stage's time reference, relative to the trigger).
    pub fn place(&mut self, frame: &Frame, samples: usize, t_ref_s: f64) -> Gates {
        let dt = frame.sample_interval_s;
        if self.pulse.as_ref().is_none_or(|p| p.0 != dt) {
            self.pulse = Some((dt, self.pulse_cfg.shape(dt)));
        }
        let pulse = &self.pulse.as_ref().expect("set above").1;
        let (lo, hi) = pulse.support();
        Gates::place(&GateInputs {
            samples,
            dt_s: dt,
            first_sample_offset_s: frame.first_sample_offset_s,
            t_ref_s,
            delay_s: self.delay_s,
            c_m_per_s: self.c_m_per_s,
            min_range_m: self.range_m.0,
            max_range_m: self.range_m.1,
            support_lo: lo,
            support_hi: hi,
            timing_offset: pulse.fraction_offset(self.fraction),
            guard_s: self.guard_s,
            pre: self.pre,
            beyond: self.beyond,
            margin: pulse.fwhm(),
        })
    }

    /// Sample ranges free of returns: the whole frame when the laser is off,
    /// else the non-empty noise gates.
    pub fn quiet_ranges(&mut self, frame: &Frame, samples: usize, t_ref_s: f64) -> QuietRanges {
        if frame.laser_off {
            return QuietRanges::from_ranges([0..frame.len(), 0..0]);
        }
        let g = self.place(frame, samples, t_ref_s);
        QuietRanges::from_ranges([g.pre, g.beyond])
    }
}

/// Probability that a clean gate loses any sample to the per-sample clip.
const CLIP_ANY: f64 = 0.01;

/// Probability that a clean block of a gate is taken for a structured excursion.
const BLOCK_ALPHA: f64 = 1e-3;

/// Lags of the gate's own autocorrelation that set a block's degrees of freedom.
const BLOCK_LAGS: usize = 16;

/// The smallest of some twenty block standard deviations of white noise
/// (about 50 samples each) reads about 0.8 σ: the starting bound is scaled back by this.
const QUIET_BLOCK_BIAS: f64 = 1.25;

/// Most cleaning passes (each pass refits the centre and sigma on what it kept).
const CLEAN_PASSES: usize = 8;

/// Whether the decode `scale·code + offset` (V) of 16-bit codes keeps their
/// order and spacing to well within a code: a decoded volt is at most
/// |offset| + |scale|·2¹⁵, which this keeps below 2⁴⁰ code steps, so its
/// rounding (half an ulp) is below 2⁻¹³ of a step. Differences of such a
/// decode (2⁻¹² of a step off at most, 1 step apart) sort as the codes'
/// differences do, and so do deviations from their median (½ step apart).
pub fn codes_keep_order(scale: f64, offset: f64) -> bool {
    scale != 0.0 && (offset.abs() + scale.abs() * 32768.0) * 2f64.powi(-40) < scale.abs()
}

/// Whether sample `v` lies at an ADC rail: at or beyond `rails` (low,
/// high), the clip levels a quarter step inside (see
/// `pipeline::Source::rails`); never where the rails are unknown.
pub fn at_rail(rails: Option<(f64, f64)>, v: f64) -> bool {
    rails.is_some_and(|(lo, hi)| v <= lo || v >= hi)
}

/// Cleans noise gates that hold pulses or interference events (a contaminated
/// gate): the samples kept are those that look like the noise around them.
///
/// Samples at the digitiser's rails (when known) are clipped, not noise:
/// they are dropped with the pulse support around them before any pass, and
/// no block holding one bounds the starting sigma (a lobe clipped flat for a
/// block's length has no spread at all).
///
/// Each pass, with centre c and sigma s (first the gate's median and robust
/// sigma, then the kept samples' mean and standard deviation):
/// * a sample beyond c ± k·s, k = Q⁻¹([`CLIP_ANY`]/2n) for n gate samples
///   (a clean gate loses a sample in 1 % of frames), is dropped with the
///   pulse support around it (`dilate` samples before and after);
/// * a block of `block` samples whose mean square about c exceeds its
///   upper [`BLOCK_ALPHA`] quantile (scaled χ² with the gate's own
///   correlation, g = 1 + 2Σρ̂²) is dropped with its neighbours: an event's
///   lobes several sigma high but under the clip level go this way.
///
/// The kept samples' standard deviation is divided by the truncated normal's
/// √(1 − 2kφ(k)/(2Φ(k) − 1)) (under 1e-3 at the k used). Their variance is
/// then that of a sample variance of the kept count, so the finite-gate
/// false-alarm design applies to it unchanged with `samples` = the kept count.
#[derive(Debug, Default, Clone)]
pub struct GateCleaner {
    /// Per frame sample: dropped.
    dropped: Vec<bool>,
    /// The kept runs, in frame order.
    kept: Vec<Range<usize>>,
    /// Lagged differences (scratch for the robust colour).
    diffs: Vec<f64>,
    /// 1 + 2Σρ̂² of the last cleaned gate (robust; see `own_colour`).
    colour_gain: f64,
    /// The lagged differences' robust sigma by counting, where the gate's
    /// samples are integer codes (see `own_colour`).
    code_mad: CodeDiffMad,
}

impl GateCleaner {
    /// Grows the scratch for frames of `samples` samples now, so that the
    /// first contaminated frame does not allocate.
    pub fn reserve(&mut self, samples: usize, runs: usize) {
        self.dropped.reserve(samples.saturating_sub(self.dropped.len()));
        self.diffs.reserve(samples.saturating_sub(self.diffs.len()));
        self.kept.reserve(runs.saturating_sub(self.kept.len()));
        self.code_mad.reserve();
    }

    /// Runs of `gates` kept after cleaning `x` (see the type's doc); `centre`
    /// and `sigma` start the passes: a robust centre of the gates, and a
    /// sigma that an event covering most of the gate has not inflated (the
    /// caller's last clean fit, else the gates' robust sigma). `rails`: the
    /// levels at or beyond which a sample is clipped (low, high), if known.
    /// `codes`: the integer codes `x` decodes (x = scale·code + offset, one
    /// code per sample of `x`) and the scale, V per code, where `x` is their
    /// decode and the scale is coarse enough that the decode keeps the
    /// codes' order (see [`codes_keep_order`]); the gate's colour is then
    /// counted on them (the same figure to the decode's rounding, in a
    /// fraction of the time).
    #[allow(clippy::too_many_arguments)]
    pub fn clean(
        &mut self,
        x: &[f64],
        codes: Option<(&[i16], f64)>,
        gates: &[Range<usize>],
        centre: f64,
        sigma: f64,
        dilate: (usize, usize),
        block: usize,
        rails: Option<(f64, f64)>,
    ) -> &[Range<usize>] {
        let n: usize = gates.iter().map(|g| g.len()).sum();
        self.kept.clear();
        self.kept.extend(gates.iter().filter(|g| !g.is_empty()).cloned());
        if n < 2 || !(sigma > 0.0) || !centre.is_finite() {
            return &self.kept;
        }
        let k = crate::math::special::q_inv(0.5 * CLIP_ANY / n as f64);
        let block = block.max(4);
        // Pulses or events may cover most of a gate (a pulse train): its
        // quietest block, about its own mean, bounds the starting sigma.
        let railed = |v: f64| at_rail(rails, v);
        let quiet_block = self.quiet_block_sigma(x, gates, block.max(4), &railed);
        let sigma = if quiet_block > 0.0 { sigma.min(QUIET_BLOCK_BIAS * quiet_block) } else { sigma };
        let g = self.own_colour(x, codes, gates, sigma);
        self.colour_gain = g;
        let (mut c, mut s) = (centre, sigma);
        let mut last_kept = usize::MAX;
        for pass in 0..CLEAN_PASSES {
            self.dropped.clear();
            self.dropped.resize(x.len(), false);
            for r in gates {
                for i in r.clone() {
                    if (x[i] - c).abs() > k * s || railed(x[i]) {
                        let a = i.saturating_sub(dilate.0).max(r.start);
                        let b = (i + dilate.1 + 1).min(r.end);
                        self.dropped[a..b].fill(true);
                    }
                }
                // Blocks: mean square about c against its scaled χ² quantile
                // (from the second pass, once s rests on clipped samples).
                if pass == 0 {
                    continue;
                }
                let dof = block as f64 / g;
                let limit = g * crate::math::stats::chi2_upper(dof, BLOCK_ALPHA) / block as f64;
                let mut start = r.start;
                while start + block <= r.end {
                    let ms = x[start..start + block].iter().map(|v| (v - c) * (v - c)).sum::<f64>() / (block as f64 * s * s);
                    if ms > limit {
                        let a = start.saturating_sub(block).max(r.start);
                        let b = (start + 2 * block).min(r.end);
                        self.dropped[a..b].fill(true);
                    }
                    start += block;
                }
            }
            // Refit on the kept samples.
            let (mut m, mut count) = (0.0, 0usize);
            for r in gates {
                for i in r.clone().filter(|&i| !self.dropped[i]) {
                    m += x[i];
                    count += 1;
                }
            }
            if count < 2 {
                break;
            }
            m /= count as f64;
            let mut ss = 0.0;
            for r in gates {
                ss += r.clone().filter(|&i| !self.dropped[i]).map(|i| (x[i] - m) * (x[i] - m)).sum::<f64>();
            }
            let truncation = 1.0 - 2.0 * k * crate::math::special::phi(k) / (1.0 - 2.0 * crate::math::special::q(k));
            (c, s) = (m, (ss / (count - 1) as f64 / truncation).sqrt());
            self.collect_kept(gates);
            if count == last_kept || !(s > 0.0) {
                break;
            }
            last_kept = count;
        }
        &self.kept
    }

    /// 1 + 2 Σ ρ̂(k)² (lags 1..16, robust) of the last gate cleaned: the
    /// variance of a variance estimate on it is this many times the white one's.
    pub fn colour_gain(&self) -> f64 {
        self.colour_gain.max(1.0)
    }

    /// Smallest of the gates' block standard deviations (each block of
    /// `block` samples about its own mean, none holding a `railed` sample);
    /// 0 with fewer than four blocks.
    fn quiet_block_sigma(&mut self, x: &[f64], gates: &[Range<usize>], block: usize, railed: &dyn Fn(f64) -> bool) -> f64 {
        self.diffs.clear();
        for r in gates {
            let mut start = r.start;
            while start + block <= r.end {
                let b = &x[start..start + block];
                if b.iter().any(|&v| railed(v)) {
                    start += block;
                    continue;
                }
                let m = b.iter().sum::<f64>() / block as f64;
                self.diffs.push((b.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (block - 1) as f64).sqrt());
                start += block;
            }
        }
        if self.diffs.len() < 4 {
            return 0.0;
        }
        self.diffs.iter().copied().fold(f64::INFINITY, f64::min)
    }

    /// 1 + 2 Σ ρ̂(k)² over lags 1..[`BLOCK_LAGS`], each ρ̂(k) robust:
    /// Var(x_i − x_{i+k}) = 2σ²(1 − ρ(k)), with both variances from the MAD
    /// (an event's slow lobes hardly change a difference of nearby samples,
    /// a pulse's few samples do not move a median).
    ///
    /// Where `x` decodes integer `codes` that span at most
    /// [`CodeDiffMad::MAX_SPAN`] over the gates, each MAD is counted on the
    /// codes' differences and scaled to volts: the decode keeps the codes'
    /// order, so the differences selected are the same. The counted figure
    /// is the exact one; the volts' selection differs from it by the
    /// decode's rounding, which grows with |offset|/|scale| (1e-13 relative
    /// on the test's 12-bit codes at an offset of 1.3 V, 5400 codes' worth;
    /// 5e-7 at 1e11 codes' worth). Else the MAD is selected among the volts'
    /// differences.
    fn own_colour(&mut self, x: &[f64], codes: Option<(&[i16], f64)>, gates: &[Range<usize>], sigma: f64) -> f64 {
        let counted = codes.and_then(|(c, scale)| CodeDiffMad::span(c, gates).map(|span| (c, scale.abs(), span)));
        let mut g = 1.0;
        for lag in 1..=BLOCK_LAGS {
            let (count, sd) = match counted {
                Some((c, scale, span)) => {
                    let (count, mad) = self.code_mad.lag(c, gates, lag, span);
                    (count, scale * mad)
                }
                None => {
                    self.diffs.clear();
                    for r in gates {
                        self.diffs.extend((r.start..r.end.saturating_sub(lag)).map(|i| x[i + lag] - x[i]));
                    }
                    (self.diffs.len(), crate::math::select::mad_sigma(&mut self.diffs))
                }
            };
            if count < 8 {
                break;
            }
            let rho = (1.0 - sd * sd / (2.0 * sigma * sigma)).clamp(-1.0, 1.0);
            g += 2.0 * rho * rho;
        }
        g
    }

    fn collect_kept(&mut self, gates: &[Range<usize>]) {
        self.kept.clear();
        for r in gates {
            let mut run: Option<usize> = None;
            for i in r.clone() {
                match (self.dropped[i], run) {
                    (false, None) => run = Some(i),
                    (true, Some(a)) => {
                        self.kept.push(a..i);
                        run = None;
                    }
                    _ => {}
                }
            }
            if let Some(a) = run {
                self.kept.push(a..r.end);
            }
        }
    }
}

/// Deterministic Gaussian noise for unit tests (Box–Muller on an LCG).
#[cfg(test)]
pub(crate) fn test_noise(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    let mut u = || {
        s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    (0..n).map(|_| (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inputs() -> GateInputs {
        GateInputs {
            samples: 2500,
            dt_s: 1e-9,
            first_sample_offset_s: -500e-9,
            t_ref_s: 0.0,
            delay_s: 0.0,
            c_m_per_s: 3e8,
            min_range_m: 0.0,
            max_range_m: 150.0,
            support_lo: -20.0,
            support_hi: 70.0,
            timing_offset: -5.0,
            guard_s: 20e-9,
            pre: true,
            beyond: true,
            margin: 0.0,
        }
    }

    #[test]
    fn gates_follow_the_geometry() {
        let g = Gates::place(&inputs());
        // tof 0 -> timing point at index 500 -> peak at 505; 150 m -> 1 us -> 1505.
        assert_eq!(g.range, 505..1506);
        assert_eq!(g.pre, 0..465);
        assert_eq!(g.beyond, 1595..2500);
    }

    #[test]
    fn quiet_ranges_keep_only_non_empty_gates_in_order() {
        let q = QuietRanges::from_ranges([0..0, 5..9]);
        assert_eq!(q.as_slice(), &[5..9]);
        let q = QuietRanges::from_ranges([1..3, 5..9]);
        assert_eq!(q.as_slice(), &[1..3, 5..9]);
        assert!(QuietRanges::from_ranges([0..0, 4..4]).is_empty());
    }

    use super::test_noise as noise;

    #[test]
    fn a_lobe_clipped_at_a_rail_is_cleaned_out() {
        // A slow event whose negative lobe sits on the bottom rail (-10 sigma)
        // for over a hundred samples: the clipped block has no spread, and
        // without the rails the cleaning would start from its zero sigma and
        // drop every sample (and then keep the whole gate).
        let mut x = noise(1200, 7);
        for (i, v) in x.iter_mut().enumerate().skip(400).take(500) {
            let t = (i - 400) as f64;
            *v += 25.0 * (2.0 * std::f64::consts::PI * 0.003 * t).sin() * (-(t - 250.0).powi(2) / (2.0 * 100.0f64.powi(2))).exp();
            *v = v.max(-10.0);
        }
        assert!(x.iter().filter(|&&v| v <= -10.0).count() > 100);
        let gates = [0..1200];
        let mut c = GateCleaner::default();
        let kept: Vec<_> = c.clean(&x, None, &gates, 0.0, 1.0, (20, 70), 50, Some((-10.0, 40.0))).to_vec();
        let n: usize = kept.iter().map(|r| r.len()).sum();
        let (mut m, mut ss) = (0.0, 0.0);
        for i in kept.iter().flat_map(|r| r.clone()) {
            m += x[i];
        }
        m /= n as f64;
        for i in kept.iter().flat_map(|r| r.clone()) {
            ss += (x[i] - m).powi(2);
        }
        let sigma = (ss / (n - 1) as f64).sqrt();
        assert!(n >= 500 && n < 1000, "{kept:?}");
        // Binomial-free bound: the sample sigma of >= 500 clean samples is
        // within 10 % of 1 with probability far above 0.999.
        assert!((sigma - 1.0).abs() < 0.1, "{sigma}");
        assert!(kept.iter().all(|r| r.end <= 400 || r.start >= 900), "{kept:?}");
    }

    #[test]
    fn gates_clamp_to_short_frames() {
        let mut i = inputs();
        i.samples = 600;
        let g = Gates::place(&i);
        assert_eq!(g.range, 505..600);
        assert!(g.beyond.is_empty());
    }

    #[test]
    fn the_colour_counted_on_codes_is_the_volts_colour() {
        // Coloured noise (a two-tap moving sum) with an event's lobes and a
        // pulse, digitised at 8 and 12 bits on scales with and without an
        // offset: the cleaner given the codes keeps the same runs and its
        // colour gain is the volts' to 1e-12 (the decode's rounding; offsets
        // of at most some 10⁴ codes' worth here).
        // Noise of 10 codes (8 bits) and 30 codes (12 bits); the pulse may clip.
        for (case, (bits, scale, offset)) in [(8u32, 2e-3, 0.0), (8, 3.7e-3, -0.21), (12, 1.5e-4, 0.05), (12, 2.4e-4, 1.3)].into_iter().enumerate() {
            let amp = if bits == 8 { 10.0 } else { 30.0 } * scale / 1.36f64.sqrt();
            let w = noise(1801, 20 + case as u64);
            let top = f64::from(1u32 << (bits - 1));
            let codes: Vec<i16> = (0..1800)
                .map(|i| {
                    let t = i as f64;
                    let event = if (700..1100).contains(&i) { 2.0 * (0.02 * t).sin() * (-(t - 900.0).powi(2) / 2e4).exp() } else { 0.0 };
                    let pulse = 14.0 * (-(t - 300.0).powi(2) / 18.0).exp();
                    let v = amp * (w[i] + 0.6 * w[i + 1] + event + pulse);
                    (v / scale).round().clamp(-top, top - 1.0) as i16
                })
                .collect();
            let x: Vec<f64> = codes.iter().map(|&c| scale * f64::from(c) + offset).collect();
            let gates = [0..1000, 1150..1800];
            assert!(codes_keep_order(scale, offset));
            let sigma = amp * 1.36f64.sqrt();
            let mut by_volts = GateCleaner::default();
            let mut by_codes = GateCleaner::default();
            by_codes.reserve(x.len(), 16);
            let kept_v = by_volts.clean(&x, None, &gates, offset, sigma, (20, 70), 50, None).to_vec();
            let kept_c = by_codes.clean(&x, Some((&codes, scale)), &gates, offset, sigma, (20, 70), 50, None).to_vec();
            assert_eq!(kept_c, kept_v, "case {case}");
            let (gv, gc) = (by_volts.colour_gain(), by_codes.colour_gain());
            // Some lags' ρ̂ count, and not every one sits at ±1 (g = 33).
            assert!(gv > 1.2 && gv < 17.0, "case {case}: g {gv}");
            assert!((gc - gv).abs() <= 1e-12 * gv, "case {case}: {gc} vs {gv}");
        }
        // Too fine a scale for the decode to keep the codes apart, or none.
        assert!(!codes_keep_order(1e-14, 1e3));
        assert!(!codes_keep_order(0.0, 0.0));
        assert!(!codes_keep_order(f64::NAN, 0.0));
        assert!(!codes_keep_order(1e-3, f64::INFINITY));
    }
}
