//! detect: the Neyman-Pearson detector ("matched_filter" or "threshold", as the
//! scene's `detector.kind` says). The threshold holds the design false-alarm
//! probability over the range gate, with the detector output's correlation
//! between neighbouring cells accounted for; threshold crossings in the noise
//! gates are counted against the same design, cumulatively per sensor.
//!
//! Optional, as the scene asks:
//! * `detector.whiten`: the matched filter runs on prewhitened data with the
//!   prewhitened template ([`crate::detect::whiten`]); the AR noise model is
//!   fitted on the noise gates, accumulated over frames (with the noise
//!   model's forgetting when `noise_gate.forgetting_frames` is set) and refitted
//!   on frames 1, 2, 4, 8, … and then every 64 frames (every N/4 with
//!   forgetting). The whitened output has unit σ; it is stored scaled by
//!   σ_eff = ‖s‖/‖h ∗ s‖ volts (the white-noise σ that would give the same
//!   matched-filter deflection), so amplitudes (output/‖s‖), thresholds,
//!   scores and Pd downstream keep their meaning; `snr_db` and the
//!   Cramér-Rao `range_sigma_m` are then computed with σ_eff (the
//!   white-noise equivalent), not with the coloured noise itself. The report lists `whiten`
//!   only for frames where it ran (a model exists). Overlapping returns are
//!   not resolved jointly while whitening (each is timed alone).
//! * `detector.cfar = "ca" | "os"`: a per-cell threshold from the local noise
//!   level in training cells around each cell ([`crate::detect::cfar`]), at the
//!   per-cell probability the report-level design gives. The report lists
//!   `cfar_ca` / `cfar_os`; `detector.threshold` is then the full-window
//!   factor times the gate's σ (the threshold where the background equals the
//!   gate noise) and Pd uses the Student-t form with 2·training degrees of
//!   freedom (exact in form for CA, an approximation for OS).

use super::{stop_codes, FrameError, GateCount, Stage, Unit, Work};
use crate::frame::FrameFlag;
use crate::detect::cfar::{CfarMethod, CfarPlan};
use crate::detect::colour::{output_gain_from_acf, taps_acf, NoiseColour, OutputColour};
use crate::detect::kernels::{local_maxima, local_maxima_above, upcrossings, upcrossings_above, DetectorPlan};
use crate::detect::empirical::EmpiricalTail;
use crate::detect::extreme::{ln_upcrossing_prob, threshold_for_report, ReportThreshold};
use crate::detect::finite_gate::{crossing_moments, mean_error_inflation, rho_cubed_sum, rho_squared_sum, variance_bias_factor, GateVariance};
use crate::math::special;
use crate::detect::resolve::Resolver;
use crate::math::stats::clopper_pearson;
use crate::detect::whiten::{ArModel, Whitener};
use crate::math::autocov::AutocovarianceAccumulator;
use crate::dsp::pulse::Shape;
use crate::frame::{DetectorSummary, FalseAlarmStats};
use crate::scene::{CfarKind, DetectorKind, PfaScope, Scene, ThresholdMode, TimingMethod};
use std::ops::Range;
use std::sync::Arc;

/// At most this many pulses are resolved per report.
const MAX_RESOLVED: usize = 32;

/// Whitening waits for this many gate samples per AR coefficient.
const WHITEN_SAMPLES_PER_COEFFICIENT: f64 = 10.0;

/// Whitening refits at most this many frames apart (without forgetting).
const WHITEN_REFIT_FRAMES: u64 = 64;

/// The plain (unwhitened) detector for one sampling period and frame length.
#[derive(Debug)]
struct RawDetector {
    /// Sampling period it was built for, s.
    dt_s: f64,
    /// Longest frame it runs on, samples.
    len: usize,
    /// Return-pulse shape at `dt_s` (the resolver and the whitened template use it).
    shape: Shape,
    /// Matched filter (or plain threshold) plan.
    plan: DetectorPlan,
}

/// The whitened matched filter and the frame length it was planned for.
#[derive(Debug)]
struct WhitenedPlan {
    /// Longest frame it runs on, samples.
    len: usize,
    /// Matched filter for the prewhitened template.
    plan: DetectorPlan,
}

/// Prewhitening state: the accumulated gate autocovariance and the filter.
#[derive(Debug)]
struct WhitenState {
    order: usize,
    /// Forgetting factor per frame (1: accumulate forever).
    lambda: f64,
    refit_frames: u64,
    acc: AutocovarianceAccumulator,
    frames: u64,
    whitener: Option<Whitener>,
    plan: Option<WhitenedPlan>,
    /// The whitened stop channel.
    z: Vec<f64>,
}

/// What the pooled noise colour gave at one version of its estimate (derived
/// once per change of the estimate, in place).
#[derive(Debug)]
struct ColourTerms {
    /// [`NoiseColour::version`] these were derived at (None: not yet for this plan).
    version: Option<u64>,
    /// The detector output's variance gain and lag-1 correlation.
    output: OutputColour,
    /// Correlation time of the noise, samples.
    tau: f64,
    /// 1 + 2 Σ_{k≥1} ρ(k)²: how many correlated samples make one degree of
    /// freedom of the gate's variance.
    rho_sq: f64,
    /// Σρρρ (∫S³): the skewness of the gate's variance estimate. Recomputed
    /// (O(lags²)) only when `rho_sq` moved by more than 0.2 %.
    rho_cube: f64,
    /// `rho_sq` at the last `rho_cube`.
    rho_cube_at: f64,
    /// Normalised autocorrelation ρ(0..) (empty: white); shared with every
    /// frame's [`super::NoiseModel::rho`]; rewritten in place when no frame holds it.
    rho: Arc<[f64]>,
    /// Scratch: the estimate's corrected lag sums.
    g: Vec<f64>,
    /// Scratch: the normalised autocorrelation before it is shared.
    rho_v: Vec<f64>,
    /// The detector taps' autocorrelation (computed when the plan is new).
    acf: Vec<f64>,
}

impl ColourTerms {
    fn new() -> ColourTerms {
        ColourTerms {
            version: None,
            output: OutputColour { variance_gain: 1.0, rho1: 0.0 },
            tau: 1.0,
            rho_sq: 1.0,
            rho_cube: 1.0,
            rho_cube_at: 1.0,
            rho: Arc::from(Vec::new()),
            g: Vec::new(),
            rho_v: Vec::new(),
            acf: Vec::new(),
        }
    }

    /// Derives the terms from `colour` for the detector `taps` when its
    /// estimate changed: as `colour.output(taps)`, `colour.correlation_time()`
    /// and `colour.rho()` (empty where white), without allocating once grown.
    fn refresh(&mut self, colour: &NoiseColour, taps: &[f64]) {
        if self.version == Some(colour.version()) {
            return;
        }
        // The taps change only with the plan, which resets `version`.
        if self.version.is_none() || self.acf.len() != taps.len() {
            taps_acf(taps, &mut self.acf);
        }
        self.version = Some(colour.version());
        let coloured = colour.rho_into(&mut self.g, &mut self.rho_v);
        if coloured {
            self.tau = (1.0 + 2.0 * self.rho_v[1..].iter().sum::<f64>()).max(0.05);
            // Σρ̂² is biased up by the estimate's own noise (2 Σρ² Σ1/N_k):
            // removed, and white kept white unless the excess is 4 sd clear
            // of that noise (so a few frames of white noise do not shrink ν).
            let raw = rho_squared_sum(&self.rho_v);
            let (v1, v2) = colour.inverse_count_sum(self.rho_v.len() - 1);
            let noise_sd = 2.0 * (2.0 * v2).sqrt();
            if raw - 1.0 - 2.0 * v1 > 4.0 * noise_sd {
                self.rho_sq = (raw / (1.0 + 2.0 * v1)).max(1.0);
                if (self.rho_sq / self.rho_cube_at - 1.0).abs() > 2e-3 {
                    self.rho_cube = (rho_cubed_sum(&self.rho_v) - 6.0 * v1 * self.rho_sq).max(1.0);
                    self.rho_cube_at = self.rho_sq;
                }
            } else {
                self.rho_sq = 1.0;
                self.rho_cube = 1.0;
                self.rho_cube_at = 1.0;
            }
            self.output = output_gain_from_acf(taps, &self.rho_v, &self.acf);
        } else {
            self.rho_v.clear();
            self.tau = 1.0;
            self.rho_sq = 1.0;
            self.rho_cube = 1.0;
            self.rho_cube_at = 1.0;
            self.output = output_gain_from_acf(taps, &[1.0], &self.acf);
        }
        match Arc::get_mut(&mut self.rho) {
            Some(r) if r.len() == self.rho_v.len() => r.copy_from_slice(&self.rho_v),
            _ => self.rho = Arc::from(self.rho_v.as_slice()),
        }
    }
}

/// What a CFAR plan was built for: it is rebuilt when any of these change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct CfarKey {
    /// Detector template length, taps.
    template_len: usize,
    /// Tap index of the template peak.
    peak_tap: usize,
    /// Per-cell false-alarm probability (its bits: compared exactly).
    p_cell_bits: u64,
}

/// CFAR settings and the plan for the current template.
#[derive(Debug)]
struct CfarState {
    kind: CfarKind,
    guard: usize,
    training: usize,
    rank: usize,
    /// The plan and what it was built for (None where the settings give no plan).
    plan: Option<(CfarKey, CfarPlan)>,
    /// Training-cell input (mean removed), reused.
    e: Vec<f64>,
    /// Per-cell thresholds on the detector output, volts-equivalent.
    thresholds: Vec<f64>,
    /// The colour estimate the plan's factors were solved for (None: never;
    /// Some(None): whitened input).
    colour_version: Option<Option<u64>>,
}

impl CfarState {
    /// Rebuilds the plan when `key` changed (in place, keeping its buffers,
    /// once there is one).
    fn refresh(&mut self, key: CfarKey, p_cell: f64) {
        if self.plan.as_ref().is_none_or(|p| p.0 != key) {
            let p_cell = p_cell.clamp(f64::MIN_POSITIVE, 0.5);
            if let Some((k, plan)) = &mut self.plan {
                match plan.redesign(key.template_len, key.peak_tap, p_cell) {
                    Ok(()) => *k = key,
                    Err(_) => self.plan = None,
                }
                return;
            }
            let method = match self.kind {
                CfarKind::Os => CfarMethod::OrderedStatistic { rank: self.rank },
                _ => CfarMethod::CellAveraging,
            };
            self.plan = CfarPlan::new(method, self.guard, self.training, key.template_len, key.peak_tap, p_cell)
                .ok()
                .map(|p| (key, p));
        }
    }
}

/// Per-cell CFAR thresholds on the detector output: the training cells are
/// `input` less `mean` (written to `e`), and `gain` turns the input's sigma
/// into the output's in volts-equivalent (the whitening scale times the
/// colour's output gain). `out` gets one threshold per output cell.
fn cfar_thresholds(plan: &mut CfarPlan, input: &[f64], mean: f64, gain: f64, e: &mut Vec<f64>, out: &mut Vec<f64>) {
    e.clear();
    e.extend(input.iter().map(|v| v - mean));
    plan.thresholds(e, out);
    for v in out.iter_mut() {
        *v *= gain;
    }
}

/// Range-gate size and output lag-1 correlation, rounded so that a pooled
/// estimate that barely moves reuses a solved threshold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct ThresholdKey {
    /// Cells (peak positions) in the range gate.
    cells: usize,
    /// round(200 · ln(1 − ρ1)): 0.5 % relative steps of 1 − ρ1.
    decorrelation: i32,
}

impl ThresholdKey {
    fn new(cells: usize, rho1: f64) -> ThresholdKey {
        ThresholdKey {
            cells,
            decorrelation: ((1.0 - rho1).max(1e-12).ln() * 200.0).round() as i32,
        }
    }

    /// The lag-1 correlation the key stands for.
    fn rho1(&self) -> f64 {
        1.0 - (self.decorrelation as f64 / 200.0).exp()
    }
}

/// Thresholds that hold the design false-alarm probability, solved once per
/// key (solving costs ~1 ms) and kept for the last [`ThresholdCache::CAPACITY`] keys.
#[derive(Debug)]
struct ThresholdCache {
    /// Design false-alarm probability.
    pfa: f64,
    /// Per report over the range gate, or per sample.
    scope: PfaScope,
    /// Solved thresholds, oldest first.
    solved: Vec<(ThresholdKey, ReportThreshold)>,
}

impl ThresholdCache {
    /// Keys kept.
    const CAPACITY: usize = 16;

    fn new(pfa: f64, scope: PfaScope) -> ThresholdCache {
        ThresholdCache {
            pfa,
            scope,
            solved: Vec::with_capacity(Self::CAPACITY),
        }
    }

    /// The threshold for a range gate of `cells` cells whose detector output
    /// has lag-1 correlation `rho1`. What the threshold depends on is 1 − ρ1
    /// (the up-crossing rate goes as its square root), so that is rounded.
    fn get(&mut self, cells: usize, rho1: f64) -> ReportThreshold {
        let key = ThresholdKey::new(cells, rho1);
        if let Some(t) = self.solved.iter().find(|t| t.0 == key) {
            return t.1;
        }
        let t = match self.scope {
            PfaScope::Report => threshold_for_report(self.pfa, cells.max(1), key.rho1()),
            PfaScope::Sample => {
                // Per sample: every cell at the design probability. Crossings
                // are counted as up-crossings (one per excursion), which a
                // correlated output makes rarer than exceedances: the cells
                // count as p_up/p effective cells each.
                let u = special::q_inv(self.pfa);
                let p_up = ln_upcrossing_prob(u, key.rho1()).exp();
                ReportThreshold {
                    u,
                    p_cell: self.pfa,
                    cells_effective: cells as f64 * (p_up / self.pfa).min(1.0),
                }
            }
        };
        if self.solved.len() >= Self::CAPACITY {
            self.solved.remove(0);
        }
        self.solved.push((key, t));
        t
    }
}

/// The detection threshold on the detector output, volts-equivalent.
#[derive(Debug, Clone, Copy)]
enum Level<'a> {
    /// One level for every cell.
    Fixed(f64),
    /// One level per output cell (CFAR).
    PerCell(&'a [f64]),
}

impl Level<'_> {
    /// Local maxima of `y` above the level inside `range`, strongest first, into `out`.
    fn peaks(self, y: &[f64], range: Range<usize>, out: &mut Vec<usize>) {
        match self {
            Level::Fixed(thr) => local_maxima(y, range, thr, out),
            Level::PerCell(thr) => local_maxima_above(y, range, thr, out),
        }
    }

    /// Up-crossings of the level by `y` inside `range`.
    fn upcrossings(self, y: &[f64], range: Range<usize>) -> u64 {
        match self {
            Level::Fixed(thr) => upcrossings(y, range, thr),
            Level::PerCell(thr) => upcrossings_above(y, range, thr),
        }
    }
}

/// Threshold crossings in the noise gates, where no return can be, counted
/// against the design per-cell probability cumulatively per sensor.
///
/// The gates' samples gave this frame's mean and sigma, so counting them
/// against this frame's threshold would read low (a sample far out inflates
/// the very σ̂ it is compared with). Each frame's gates are therefore counted
/// against the *previous* frame's threshold and mean ([`HeldOut`]): samples
/// independent of the estimate, as the range gate's are. The crossings of a
/// frame share that estimate, so the count is over-dispersed relative to a
/// binomial one (see [`crossing_moments`]); the interval and the excess test
/// use the quasi-binomial count (observed and cells divided by the
/// dispersion). `excess` means the design lies below the 99.8 % interval.
/// With CFAR each gate cell is judged against its own threshold, from
/// training cells that exclude it: the cells above it are counted against
/// the design per-cell probability (see `exceedance_dispersion`).
///
/// Where the events stage runs, it keeps the counter: detect leaves it the
/// frame's count and excursions (`ThresholdTerms::gate_count`,
/// `Buffers::gate_excursions`), and the crossings the events test judges
/// interference events are not counted, as such detections are not
/// reported. Their cells stay in the count's expectation: near frequent
/// events the check reads low (conservative), as the range gate's reported
/// rate does there. It counts from the frame on which the events test has
/// learned its null from the gates (before, an event in the gates is in the
/// frame's σ̂ and its crossings cannot be judged against the noise's).
#[derive(Debug, Default)]
pub(super) struct FalseAlarmCounter {
    /// Noise-gate crossings since the pipeline started (less those judged
    /// interference events, where the events stage counts).
    observed: u64,
    /// Effective noise-gate cells since the pipeline started.
    cells: f64,
    /// Σ expected crossings and Σ their variance (dispersion-weighted).
    expected: f64,
    variance: f64,
    /// Crossing moments solved per (t, κ, ν, shift), up to [`TCache::CAPACITY`].
    moments: std::collections::HashMap<[u64; 4], (f64, f64)>,
}

/// Thresholds in units of σ̂ for a gate variance distribution and a
/// Gaussian level, kept for up to [`TCache::CAPACITY`] pairs (solving a
/// correlated gate's costs ~0.1 ms; the Student-t form is immediate). A
/// cleaned gate's sample count, and so its quantised distribution, moves from
/// frame to frame over a few dozen values: all of them stay solved.
#[derive(Debug, Default)]
struct TCache {
    solved: std::collections::HashMap<[u64; 3], f64>,
}

impl TCache {
    const CAPACITY: usize = 1024;

    fn get(&mut self, gate: GateVariance, u: f64) -> f64 {
        if gate.shift == 0.0 {
            return gate.t_for(u);
        }
        let key = [gate.nu.to_bits(), gate.shift.to_bits(), u.to_bits()];
        if let Some(t) = self.solved.get(&key) {
            return *t;
        }
        let t = gate.t_for(u);
        if self.solved.len() >= Self::CAPACITY {
            self.solved.clear();
        }
        // Grown once, in full: later insertions allocate nothing.
        if self.solved.capacity() < Self::CAPACITY {
            self.solved.reserve(Self::CAPACITY);
        }
        self.solved.insert(key, t);
        t
    }
}

/// A correlated gate's distribution rounded (ν to 0.5 %, the shift to 1e-3)
/// so that a pooled colour estimate that barely moves reuses a solved threshold.
fn quantised(g: GateVariance) -> GateVariance {
    if g.shift == 0.0 || !g.nu.is_finite() {
        return g;
    }
    GateVariance {
        nu: ((g.nu.ln() * 200.0).round() / 200.0).exp(),
        shift: (g.shift * 1000.0).round() / 1000.0,
    }
}

/// Confidence of the interval whose lower end above the design flags `excess`.
const EXCESS_CONFIDENCE: f64 = 0.998;

/// What the previous frame's threshold was, to count this frame's gates against.
#[derive(Debug, Clone, Copy)]
struct HeldOut {
    /// Fixed threshold on the detector output, volts-equivalent.
    level: f64,
    /// Noise mean the output was taken about, V.
    mean_v: f64,
    /// Output change per volt of input mean (volts-equivalent per V).
    dc_out: f64,
    /// Design per-cell probability and effective cells per gate position.
    p_cell: f64,
    per_position: f64,
    /// Student-t threshold, mean-error inflation and degrees of freedom.
    t: f64,
    kappa: f64,
    gate: GateVariance,
    /// Whether the output was whitened, and the sampling period: a change of
    /// either makes the previous threshold meaningless for this frame.
    whitened: bool,
    dt_s: f64,
}

impl FalseAlarmCounter {
    /// Adds one frame: `observed` crossings over `gate_cells` effective cells
    /// at design per-cell probability `p_cell`, with `dispersion` the
    /// variance of the frame's count over its binomial variance; returns the
    /// running statistics.
    pub(super) fn record(&mut self, observed: u64, gate_cells: f64, p_cell: f64, dispersion: f64) -> FalseAlarmStats {
        self.observed += observed;
        self.cells += gate_cells;
        self.expected += gate_cells * p_cell;
        self.variance += gate_cells * p_cell * dispersion.max(1.0);
        let d = if self.expected > 0.0 { (self.variance / self.expected).max(1.0) } else { 1.0 };
        let trials = (self.cells / d).round() as u64;
        let successes = ((self.observed as f64 / d).round() as u64).min(trials);
        let (lo, hi) = clopper_pearson(successes, trials, 0.95);
        // The strict interval's lower end lies below the observed rate: where
        // that rate is at or below the design it cannot flag, and is not solved.
        let below = successes as f64 <= p_cell * trials as f64;
        let lo_strict = if below { 0.0 } else { clopper_pearson(successes, trials, EXCESS_CONFIDENCE).0 };
        FalseAlarmStats {
            expected_per_frame: gate_cells * p_cell,
            observed: self.observed,
            cells: self.cells,
            rate: if self.cells > 0.0 { self.observed as f64 / self.cells } else { 0.0 },
            ci95: [lo, hi],
            excess: trials > 0 && lo_strict > p_cell,
        }
    }

    /// Counts the frame's gates (`count`, less `events` of its crossings
    /// judged interference events) into the report's statistics and flags.
    pub(super) fn count(&mut self, report: &mut crate::frame::Report, count: GateCount, events: u64) {
        debug_assert!(events <= count.observed);
        report.false_alarm = self.record(count.observed.saturating_sub(events), count.gate_cells, count.p_cell, count.dispersion);
        if report.false_alarm.excess {
            report.flags.push(FrameFlag::FalseAlarmExcess);
        }
    }

    /// Variance over binomial variance of the crossings of `cells` cells
    /// sharing one gate estimate (threshold `t` in units of σ̂κ, inflation
    /// `kappa`, the estimate distributed as `gate` says).
    ///
    /// κ moves with the gate's sample count, which a cleaned gate changes
    /// every frame; it is rounded to 1e-4 (a relative change of the
    /// crossing probabilities below 1e-4 · t², far inside the dispersion's
    /// own approximation) so that the moments are solved once per change
    /// that matters rather than every frame.
    fn dispersion(&mut self, cells: f64, t: f64, kappa: f64, gate: GateVariance) -> f64 {
        let kappa = (kappa * 1e4).round() / 1e4;
        let key = [t.to_bits(), kappa.to_bits(), gate.nu.to_bits(), gate.shift.to_bits()];
        let (m1, m2) = match self.moments.get(&key) {
            Some(m) => *m,
            None => {
                let m = crossing_moments(t, kappa, gate);
                if self.moments.len() >= TCache::CAPACITY {
                    self.moments.clear();
                }
                if self.moments.capacity() < TCache::CAPACITY {
                    self.moments.reserve(TCache::CAPACITY);
                }
                self.moments.insert(key, m);
                m
            }
        };
        if m1 > 0.0 { 1.0 + cells * (m2 - m1 * m1).max(0.0) / m1 } else { 1.0 }
    }
}

/// Variance over binomial variance of the count of output cells above a
/// level each exceeds with probability `p`, the output's lag-1 correlation
/// being `rho1`: exceedances clump as the two-state Markov chain of the
/// up-crossing model (leave the run with P(X₁ ≤ u | X₀ > u) = p_up/p, enter
/// it with p_up/(1 − p), u = Q⁻¹(p)), whose indicator's lag-k correlation is
/// λᵏ with λ = 1 − p_up/p − p_up/(1 − p); the count over many cells then has
/// dispersion (1 + λ)/(1 − λ) (1 for white output, about twice the mean run
/// length for a smooth one).
fn exceedance_dispersion(p: f64, rho1: f64) -> f64 {
    if !(p > 0.0 && p < 0.5) {
        return 1.0;
    }
    let up = ln_upcrossing_prob(special::q_inv(p), rho1).exp();
    let lambda = (1.0 - up / p - up / (1.0 - p)).clamp(0.0, 1.0 - 1e-9);
    (1.0 + lambda) / (1.0 - lambda)
}

/// The excursions of `y` above a level (`above(p)`) over the gate runs
/// `runs`, into `out`: each excursion's highest position and what it
/// counts, one up-crossing (an excursion starting at a run's first position
/// counts, as in `upcrossings`) or, with `exceedances`, its cells above.
fn excursions(y: &[f64], runs: &[std::ops::Range<usize>], above: impl Fn(usize) -> bool, exceedances: bool, out: &mut Vec<(usize, u64)>) {
    // Beyond the cap an excursion is left unlisted: unjudged, it counts.
    let push = |out: &mut Vec<(usize, u64)>, e: (usize, u64)| {
        if out.len() < MAX_GATE_EXCURSIONS {
            out.push(e);
        }
    };
    for r in runs {
        let mut open: Option<(usize, u64)> = None;
        for p in r.clone() {
            match (above(p), &mut open) {
                (true, Some((top, n))) => {
                    if y[p] > y[*top] {
                        *top = p;
                    }
                    *n += exceedances as u64;
                }
                (true, None) => open = Some((p, 1)),
                (false, Some(e)) => {
                    push(out, *e);
                    open = None;
                }
                (false, None) => {}
            }
        }
        if let Some(e) = open {
            push(out, e);
        }
    }
}

/// Most noise-gate excursions listed for the events stage per frame (those
/// counted and the context ones together; more are left unjudged and count).
const MAX_GATE_EXCURSIONS: usize = 64;

/// The excursions above the level over the whole gates `gates` whose
/// highest position lies outside the counted runs `counted` (what the
/// cleaning of a contaminated gate left out: pulses, an event's lobes),
/// appended to `out` as counting nothing: the events stage judges them
/// with the counted ones, so that an event found there reaches the
/// excursions of its tail.
fn context_excursions(y: &[f64], gates: &[std::ops::Range<usize>], counted: &[std::ops::Range<usize>], above: impl Fn(usize) -> bool, out: &mut Vec<(usize, u64)>) {
    let from = out.len();
    excursions(y, gates, above, false, out);
    let mut k = from;
    for i in from..out.len() {
        let top = out[i].0;
        if !counted.iter().any(|r| r.contains(&top)) {
            out[k] = (top, 0);
            k += 1;
        }
    }
    out.truncate(k);
}

/// Most gate runs the noise colour is pooled over in one frame (a cleaned
/// gate's runs beyond it are left out of the colour, not of the noise fit).
const MAX_RUNS: usize = 64;

/// Runs the detector on the stop channel.
#[derive(Debug)]
pub struct Detect {
    kind: DetectorKind,
    pfa: f64,
    pulse_cfg: crate::scene::PulseConfig,
    /// Maximum-likelihood timing resolves overlapping returns here.
    resolve: bool,
    resolver: Resolver,
    raw: Option<RawDetector>,
    thresholds: ThresholdCache,
    /// Noise colour pooled over the noise gates: sets the output sigma and correlation.
    colour: Option<NoiseColour>,
    colour_terms: ColourTerms,
    whiten: Option<WhitenState>,
    cfar: Option<CfarState>,
    /// Normalised gate outputs, for the empirical threshold mode.
    tail: Option<EmpiricalTail>,
    false_alarms: FalseAlarmCounter,
    /// The events stage runs after this one: it judges the gates'
    /// crossings and counts them (see `ThresholdTerms::gate_count`).
    events_count: bool,
    /// The previous frame's threshold, for counting this frame's gates.
    held_out: Option<HeldOut>,
    t_cache: TCache,
    /// Detector output positions over the kept gate runs (scratch).
    gate_pos: Vec<std::ops::Range<usize>>,
    /// An 8-bit stop channel's codes widened to i16 (the integer filter's input).
    wide_codes: Vec<i16>,
}

impl Detect {
    /// From the scene's detector and return-pulse sections.
    pub fn new(scene: &Scene) -> Detect {
        Detect {
            kind: scene.detector.kind,
            pfa: scene.detector.pfa,
            pulse_cfg: scene.return_pulse.clone(),
            resolve: scene.timing.method == TimingMethod::Ml && scene.detector.kind == DetectorKind::MatchedFilter,
            resolver: Resolver::default(),
            raw: None,
            thresholds: ThresholdCache::new(scene.detector.pfa, scene.detector.pfa_scope),
            colour: None,
            colour_terms: ColourTerms::new(),
            whiten: scene.detector.whiten.then(|| {
                let n = scene.noise_gate.forgetting_frames;
                WhitenState {
                    order: scene.detector.whiten_order,
                    lambda: if n > 0 { (-1.0 / n as f64).exp() } else { 1.0 },
                    refit_frames: if n > 0 { (n as u64 / 4).clamp(1, WHITEN_REFIT_FRAMES) } else { WHITEN_REFIT_FRAMES },
                    acc: AutocovarianceAccumulator::new(scene.detector.whiten_order),
                    frames: 0,
                    whitener: None,
                    plan: None,
                    z: Vec::new(),
                }
            }),
            cfar: (scene.detector.cfar != CfarKind::Off).then(|| {
                let d = &scene.detector;
                CfarState {
                    kind: d.cfar,
                    guard: d.cfar_guard_cells,
                    training: d.cfar_training_cells,
                    rank: if d.cfar_os_rank == 0 { CfarPlan::default_rank(d.cfar_training_cells) } else { d.cfar_os_rank },
                    plan: None,
                    e: Vec::new(),
                    thresholds: Vec::new(),
                    colour_version: None,
                }
            }),
            tail: (scene.detector.threshold_mode == ThresholdMode::Empirical).then(EmpiricalTail::default),
            false_alarms: FalseAlarmCounter::default(),
            events_count: scene.events.enabled,
            held_out: None,
            t_cache: TCache::default(),
            gate_pos: Vec::new(),
            wide_codes: Vec::new(),
        }
    }

    /// Builds the raw detector (and resets what depends on it) when the
    /// sampling period changes or a longer frame arrives.
    fn plan_raw(&mut self, dt: f64, n: usize) {
        if self.raw.as_ref().is_none_or(|p| p.dt_s != dt || p.len < n) {
            let shape = self.pulse_cfg.shape(dt);
            let plan = match self.kind {
                DetectorKind::MatchedFilter => DetectorPlan::matched_filter(&shape, n),
                DetectorKind::Threshold => DetectorPlan::threshold(n),
            };
            // Lags up to the template length are all the output's sigma depends on.
            self.colour = Some(NoiseColour::new(plan.len()));
            self.colour_terms.version = None;
            self.raw = Some(RawDetector { dt_s: dt, len: n, shape, plan });
            if let Some(ws) = &mut self.whiten {
                ws.plan = None;
            }
        }
    }
}

impl Stage for Detect {
    fn name(&self) -> &'static str {
        self.kind.name()
    }

    fn process(&mut self, mut w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        let dt = w.frame.sample_interval_s;
        let n = w.buffers.stop_v.len();
        self.plan_raw(dt, n);
        let whitened = match &mut self.whiten {
            Some(ws) => {
                let shape = &self.raw.as_ref().expect("built above").shape;
                update_whitener(ws, &w, shape, n)
            }
            None => false,
        };
        if self.whiten.is_some() && !whitened {
            w.report.flags.push(FrameFlag::WhitenWarmingUp);
        }
        // Noise colour (pooled gate autocorrelation): the plain matched
        // filter's output sigma and correlation depend on it. The whitened
        // filter's output is white with unit sigma by construction.
        let colour = self.colour.as_mut().expect("built with the plan");
        // The stop channel's codes as digitised (stop_v is their decode), for
        // the colour's lag sums and the integer filter; 8-bit codes widened once.
        let digitised = stop_codes(&w.frame.channels[w.source.stop].samples, &mut self.wide_codes);
        if w.noise.summary.samples >= 2 {
            let stop_v = &w.buffers.stop_v;
            // The gates' kept runs (all of both gates unless a contaminated
            // gate was cleaned); at most MAX_RUNS of them, on the stack.
            let mut parts: [&[f64]; MAX_RUNS] = [&[]; MAX_RUNS];
            let runs = w.buffers.quiet.len().min(MAX_RUNS);
            for (p, r) in parts.iter_mut().zip(&w.buffers.quiet) {
                *p = &stop_v[r.clone()];
            }
            // A forgetting noise model's mean rests on more samples than this frame's gates.
            let (mean, mean_samples) = (w.noise.summary.mean_v, w.noise.summary.samples as f64);
            let stop = &w.frame.channels[w.source.stop];
            match digitised {
                // Codes as digitised: exact integer lag sums.
                Some(codes) if codes.len() == stop_v.len() => {
                    let mut code_parts: [&[i16]; MAX_RUNS] = [&[]; MAX_RUNS];
                    for (p, r) in code_parts.iter_mut().zip(&w.buffers.quiet) {
                        *p = &codes[r.clone()];
                    }
                    colour.add_frame_codes_about(&code_parts[..runs], &parts[..runs], stop.volts_per_code, stop.offset_v, mean, mean_samples);
                }
                _ => colour.add_frame_about(&parts[..runs], mean, mean_samples),
            }
        }
        let (out_gain, rho1, tau, rho_sq, rho_cube) = match (&self.whiten, whitened) {
            (Some(ws), true) => (1.0, ws.plan.as_ref().expect("whitened").plan.rho1(), 1.0, 1.0, 1.0),
            _ => {
                let c = &mut self.colour_terms;
                c.refresh(colour, self.raw.as_ref().expect("built above").plan.taps());
                w.noise.rho = Arc::clone(&c.rho);
                (c.output.variance_gain.sqrt(), c.output.rho1, c.tau, c.rho_sq, c.rho_cube)
            }
        };
        // Centring correlated samples on their own mean removes σ²τ/n of
        // their variance: the gate's sigma reads low by that much (2 % in
        // sigma for AR(1) φ = 0.9 on a 400-sample gate), which at a 1e-3
        // design would double the false alarms. Unbiased here; the whitened
        // path has its own sigma.
        if !whitened && let Some(f) = variance_bias_factor(w.noise.summary.samples, tau) {
            w.noise.sigma_v *= f.sqrt();
            w.noise.raw_sigma_v *= f.sqrt();
        }
        w.threshold.out_gain = out_gain;
        let cells = w.noise.gates.range.len();
        let t = self.thresholds.get(cells, rho1);
        let white_dof = match (&self.whiten, whitened) {
            (Some(ws), true) => Some(ws.acc.samples() - 1.0 - ws.order as f64),
            _ => None,
        };
        let mut gate_pos = std::mem::take(&mut self.gate_pos);
        let raw = self.raw.as_mut().expect("built above");
        let raw_norm = raw.plan.norm();
        // The plan whose output is thresholded, its input (for CFAR training
        // cells) and the factor from its unit-σ output to volts-equivalent.
        let (plan, input, scale): (&mut DetectorPlan, &[f64], f64) = match (&mut self.whiten, whitened) {
            (Some(ws), true) => {
                let wh = ws.whitener.as_ref().expect("whitened");
                wh.apply(&w.buffers.stop_v, w.noise.summary.mean_v, &mut ws.z);
                let plan = &mut ws.plan.as_mut().expect("whitened").plan;
                let sigma_eff = raw_norm / plan.norm();
                plan.run(&ws.z, 0.0);
                (plan, &ws.z, sigma_eff)
            }
            _ => {
                // A stop channel of i16 or i8 codes (a frame as digitised, not
                // an average) is filtered exactly in integers; stop_v is its decode.
                let stop = &w.frame.channels[w.source.stop];
                let mean = w.noise.summary.mean_v;
                let exact = match digitised {
                    Some(codes) => raw.plan.run_codes(&w.buffers.stop_v, codes, stop.volts_per_code, stop.offset_v, mean),
                    None => false,
                };
                if !exact {
                    raw.plan.run(&w.buffers.stop_v, mean);
                }
                (&mut raw.plan, &w.buffers.stop_v, 1.0)
            }
        };
        let dc_gain = plan.dc_gain();
        gate_pos.clear();
        gate_pos.extend(w.buffers.quiet.iter().map(|r| plan.positions_inside(r)).filter(|p| !p.is_empty()));
        // The whole gates' positions, what the cleaning left out included.
        let full_gates = [plan.positions_inside(&w.noise.gates.pre), plan.positions_inside(&w.noise.gates.beyond)];
        // The resolver may read the plan's output after this (ML timing on
        // the raw filter); otherwise the output is handed over, not copied.
        let may_resolve = self.resolve && !whitened;
        if scale == 1.0 && !may_resolve {
            plan.take_output(&mut w.buffers.detector_output);
        } else if scale == 1.0 {
            // v · 1 is v: a plain copy.
            w.buffers.detector_output.clear();
            w.buffers.detector_output.extend_from_slice(plan.output());
        } else {
            w.buffers.detector_output.clear();
            w.buffers.detector_output.extend(plan.output().iter().map(|v| v * scale));
        }
        if whitened {
            // Unit σ in whitened units is σ_eff volts-equivalent.
            w.noise.sigma_v = scale;
            let last = w.report.stages.len().saturating_sub(1);
            w.report.stages.insert(last, "whiten");
        }
        // The gate's mean and sigma are estimates: Student-t on the inflated
        // sigma keeps the design pfa for any gate size (see detect::finite_gate).
        // Correlated gate samples carry fewer degrees of freedom than samples:
        // ν = (n − 1)/Σρ(k)² (see detect::finite_gate::effective_dof).
        // Its lower tail (what false alarms come from) needs the third
        // cumulant too: detect::finite_gate::GateVariance.
        let samples = w.noise.summary.samples;
        let gate = match white_dof {
            // σ comes from the AR fit over every gate sample accumulated.
            Some(m) => GateVariance::student(if m > 1.0 { m } else { f64::INFINITY }),
            None => quantised(GateVariance::correlated(samples, rho_sq, rho_cube)),
        };
        w.threshold.nu = gate.dof();
        // The gate mean's error is σ²τ/n (τ: correlation time in samples); in
        // units of the output variance σ²g that is n·g/τ effective samples.
        let mean_samples = (samples as f64 * out_gain * out_gain / tau).round().max(1.0) as u64;
        w.threshold.kappa = mean_error_inflation(dc_gain, if samples == 0 { 0 } else { mean_samples });
        w.threshold.t = self.t_cache.get(gate, t.u);
        w.threshold.u = w.threshold.t * w.threshold.kappa;
        if let Some(tail) = &self.tail {
            match tail.quantile(t.p_cell) {
                Some(z) => {
                    w.threshold.u = z;
                    w.threshold.t = z / w.threshold.kappa;
                    w.report.flags.push(FrameFlag::EmpiricalThreshold);
                }
                None => w.report.flags.push(FrameFlag::EmpiricalThresholdWarmingUp),
            }
        }
        let key = CfarKey {
            template_len: plan.len(),
            peak_tap: plan.peak_tap(),
            p_cell_bits: t.p_cell.to_bits(),
        };
        let cfar_on = match &mut self.cfar {
            Some(cs) => {
                cs.refresh(key, t.p_cell);
                match &mut cs.plan {
                    Some((_, cp)) => {
                        // Correlated training cells carry fewer degrees of freedom.
                        let version = (!whitened).then_some(self.colour_terms.version).flatten();
                        if cs.colour_version != Some(version) {
                            cs.colour_version = Some(version);
                            cp.set_colour(if whitened { &[] } else { &self.colour_terms.rho });
                        }
                        // Training cells: the detector's own input, mean removed
                        // (the whitened input is already zero-mean). The
                        // training cells give the input's sigma; the output's
                        // is out_gain times it (1 for white or whitened noise).
                        let mean = if whitened { 0.0 } else { w.noise.summary.mean_v };
                        // The gate mean's error δ is common to every cell: it
                        // shifts the output by dc_gain·δ (variance dc²/m in
                        // output variances, m the mean's effective samples)
                        // and adds δ² to every training cell's power (g²/m in
                        // input variances, g the output's gain on the
                        // noise). The factors assume neither; the ratio of
                        // the two inflations puts the design back.
                        let kappa = if samples == 0 {
                            1.0
                        } else {
                            let m = mean_samples as f64;
                            ((1.0 + dc_gain * dc_gain / m) / (1.0 + out_gain * out_gain / m)).sqrt()
                        };
                        // Raw codes sit on the ADC's grid (the whitened input's grid is smeared).
                        cp.set_grid(if whitened { 0.0 } else { w.source.lsb_v });
                        cfar_thresholds(cp, input, mean, scale * out_gain * kappa, &mut cs.e, &mut cs.thresholds);
                        // Pd and score: Student-t with the full window's cells.
                        let alpha = cp.factor(cp.full_window());
                        w.threshold.t = alpha;
                        w.threshold.u = alpha * kappa;
                        w.threshold.kappa = kappa;
                        w.threshold.nu = cp.dof(cp.full_window());
                        w.report.stages.push(cs.kind.name());
                        true
                    }
                    None => false,
                }
            }
            None => false,
        };
        let thr = w.threshold.u * w.noise.sigma_v * out_gain;
        let level = match (&self.cfar, cfar_on) {
            (Some(cs), true) => Level::PerCell(&cs.thresholds),
            _ => Level::Fixed(thr),
        };
        level.peaks(&w.buffers.detector_output, w.noise.gates.range.clone(), &mut w.buffers.detections);
        w.buffers.components.clear();
        if w.noise.summary.samples < 2 {
            // Without a noise estimate there is no threshold to hold a false-alarm
            // rate: nothing is declared detected (the report says no_noise_estimate).
            w.buffers.detections.clear();
        }
        if may_resolve && !cfar_on && !w.buffers.detections.is_empty() {
            let raw = self.raw.as_mut().expect("built above");
            self.resolver.resolve(
                &w.buffers.stop_v,
                w.noise.summary.mean_v,
                w.noise.sigma_v,
                w.noise.sigma_v * out_gain,
                &raw.shape,
                &mut raw.plan,
                w.noise.gates.range.clone(),
                thr,
                MAX_RESOLVED,
                &mut w.buffers.components,
            );
        }
        // Empirical false alarms: excursions above the same threshold in the
        // noise gates, where no return can be. Each gate position counts as
        // cells_effective / cells effective cells, as in the range gate.
        let y = &w.buffers.detector_output;
        if let Some(tail) = &mut self.tail {
            for p in gate_pos.iter().flat_map(|r| r.clone()) {
                tail.add(y[p] / (w.noise.sigma_v * out_gain));
            }
        }
        let per_position = if cells > 0 { t.cells_effective / cells as f64 } else { 1.0 };
        let gate_positions = gate_pos.iter().map(|r| r.len()).sum::<usize>() as f64;
        let mean_v = w.noise.summary.mean_v;
        let wh_dc = match (&self.whiten, whitened) {
            (Some(ws), true) => ws.whitener.as_ref().expect("whitened").taps().iter().sum::<f64>(),
            _ => 1.0,
        };
        let dc_out = dc_gain * wh_dc * scale;
        w.buffers.gate_excursions.clear();
        if self.events_count {
            // Room for the most that are listed, taken once per unit.
            w.buffers.gate_excursions.reserve(MAX_GATE_EXCURSIONS);
        }
        let (observed, gate_cells, p_cell, dispersion) = match (&self.cfar, cfar_on) {
            // Each cell's CFAR threshold comes from training cells that
            // exclude it (and its guard cells): already independent of the
            // cell, which exceeds it with the design per-cell probability.
            // Exceedances are counted, not up-crossings: a CFAR threshold
            // moves from cell to cell with its training cells, so one
            // excursion of the output crosses it more often than it would
            // a fixed level (1.4x on whitened AR(1) noise, 1.5x with OS),
            // and the fixed level's up-crossing rate is no expectation for
            // that count. Neighbouring exceedances clump: see
            // `exceedance_dispersion`.
            (Some(cs), true) => {
                let thr = &cs.thresholds;
                let observed = gate_pos.iter().flat_map(|r| r.clone()).filter(|&p| y[p] > thr[p]).count() as u64;
                if self.events_count && observed > 0 {
                    excursions(y, &gate_pos, |p| y[p] > thr[p], true, &mut w.buffers.gate_excursions);
                    context_excursions(y, &full_gates, &gate_pos, |p| y[p] > thr[p], &mut w.buffers.gate_excursions);
                }
                (observed, gate_positions, t.p_cell, exceedance_dispersion(t.p_cell, rho1))
            }
            _ => match self.held_out {
                Some(h) if h.whitened == whitened && h.dt_s == dt && samples >= 2 => {
                    // The previous frame's threshold and mean: the output about
                    // that mean is y + dc_out (μ − μ_prev).
                    let level = Level::Fixed(h.level - h.dc_out * (mean_v - h.mean_v));
                    let observed = gate_pos.iter().map(|r| level.upcrossings(y, r.clone())).sum();
                    if self.events_count && observed > 0 {
                        let Level::Fixed(l) = level else { unreachable!("a fixed level") };
                        excursions(y, &gate_pos, |p| y[p] > l, false, &mut w.buffers.gate_excursions);
                        context_excursions(y, &full_gates, &gate_pos, |p| y[p] > l, &mut w.buffers.gate_excursions);
                    }
                    let gate_cells = gate_positions * h.per_position;
                    let d = self.false_alarms.dispersion(gate_cells, h.t, h.kappa, h.gate);
                    (observed, gate_cells, h.p_cell, d)
                }
                _ => (0, 0.0, t.p_cell, 1.0),
            },
        };
        debug_assert!(w.buffers.gate_excursions.iter().map(|e| e.1).sum::<u64>() <= observed);
        if self.events_count {
            w.threshold.gate_count = Some(GateCount { observed, gate_cells, p_cell, dispersion });
        } else {
            w.threshold.gate_count = None;
            self.false_alarms.count(&mut w.report, GateCount { observed, gate_cells, p_cell, dispersion }, 0);
        }
        self.held_out = (samples >= 2 && !cfar_on && thr.is_finite()).then_some(HeldOut {
            level: thr,
            mean_v,
            dc_out,
            p_cell: t.p_cell,
            per_position,
            t: w.threshold.t,
            kappa: w.threshold.kappa,
            gate,
            whitened,
            dt_s: dt,
        });
        w.report.detector = DetectorSummary {
            kind: self.kind.name(),
            pfa_design: self.pfa,
            threshold: thr / raw_norm,
            pfa_cell: t.p_cell,
            cells_effective: t.cells_effective,
        };
        self.gate_pos = gate_pos;
        out.push(w);
        Ok(())
    }
}

/// Adds this frame's noise gates to the whitener's autocovariance and refits
/// when due; true when a whitening filter is ready for this frame.
fn update_whitener(ws: &mut WhitenState, w: &Work, shape: &Shape, n: usize) -> bool {
    let stop_v = &w.buffers.stop_v;
    if w.noise.summary.samples >= 2 {
        ws.acc.forget(ws.lambda);
        for r in &w.buffers.quiet {
            ws.acc.add_segment(&stop_v[r.clone()], w.noise.summary.mean_v);
        }
        ws.frames += 1;
    }
    let enough = ws.acc.samples() >= WHITEN_SAMPLES_PER_COEFFICIENT * (ws.order + 1) as f64;
    let due = ws.whitener.is_none()
        || ws.plan.as_ref().is_none_or(|p| p.len < n)
        || ws.frames.is_power_of_two()
        || ws.frames.is_multiple_of(ws.refit_frames);
    if enough
        && due
        && let Some(model) = ArModel::levinson_durbin(&ws.acc.autocovariance(), ws.order)
    {
        let wh = Whitener::new(&model);
        let (taps, peak_tap) = shape.template();
        let g = wh.whiten_template(&taps);
        ws.plan = Some(WhitenedPlan {
            len: n,
            plan: DetectorPlan::from_template(g, peak_tap, n),
        });
        ws.whitener = Some(wh);
    }
    ws.whitener.is_some() && ws.plan.as_ref().is_some_and(|p| p.len >= n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_per_sample_is_the_gaussian_quantile() {
        let mut c = ThresholdCache::new(1e-3, PfaScope::Sample);
        let t = c.get(500, 0.3);
        assert_eq!(t.u, special::q_inv(1e-3));
        assert_eq!(t.p_cell, 1e-3);
        // Up-crossings of a correlated output: fewer than exceedances.
        let rho1 = ThresholdKey::new(500, 0.3).rho1();
        assert_eq!(t.cells_effective, 500.0 * ln_upcrossing_prob(t.u, rho1).exp() / 1e-3);
        assert!(t.cells_effective < 500.0 * 0.99, "{}", t.cells_effective);
        // White: P(X_k ≤ u < X_k+1) = p (1 − p).
        let t = c.get(500, 0.0);
        assert!((t.cells_effective / (500.0 * (1.0 - 1e-3)) - 1.0).abs() < 1e-9, "{}", t.cells_effective);
    }

    #[test]
    fn threshold_per_report_solves_at_the_rounded_correlation_and_is_kept() {
        let mut c = ThresholdCache::new(1e-3, PfaScope::Report);
        let rho1 = 0.61;
        let key = ThresholdKey::new(1000, rho1);
        // The rounded correlation is within 0.25 % of 1 − ρ1.
        assert!(((1.0 - key.rho1()) / (1.0 - rho1) - 1.0).abs() < 0.0026);
        let t = c.get(1000, rho1);
        assert_eq!(t, threshold_for_report(1e-3, 1000, key.rho1()));
        // A correlation that rounds to the same key reuses the solved threshold.
        assert_eq!(c.get(1000, rho1 + 1e-6), t);
        assert_eq!(c.solved.len(), 1);
        // The per-cell probability holds the report's: 1 − (1 − p)^cells_eff = P.
        let p_report = -(t.cells_effective * (-t.p_cell).ln_1p()).exp_m1();
        assert!((p_report / 1e-3 - 1.0).abs() < 1e-6, "{p_report}");
    }

    #[test]
    fn threshold_cache_keeps_the_latest_keys() {
        let mut c = ThresholdCache::new(1e-2, PfaScope::Sample);
        for cells in 1..=ThresholdCache::CAPACITY + 3 {
            c.get(cells, 0.0);
        }
        assert_eq!(c.solved.len(), ThresholdCache::CAPACITY);
        assert_eq!(c.solved[0].0.cells, 4);
    }

    #[test]
    fn cfar_thresholds_are_the_plans_on_the_mean_removed_input_scaled() {
        let input: Vec<f64> = (0..300).map(|i| 0.2 + ((i * 7919) % 101) as f64 / 101.0 - 0.5).collect();
        let (mean, gain) = (0.2, 1.7);
        for method in [CfarMethod::CellAveraging, CfarMethod::OrderedStatistic { rank: 12 }] {
            let mut plan = CfarPlan::new(method, 2, 8, 5, 2, 1e-3).expect("valid");
            let (mut e, mut got) = (Vec::new(), Vec::new());
            cfar_thresholds(&mut plan, &input, mean, gain, &mut e, &mut got);
            let centred: Vec<f64> = input.iter().map(|v| v - mean).collect();
            let mut want = Vec::new();
            CfarPlan::new(method, 2, 8, 5, 2, 1e-3).expect("valid").thresholds(&centred, &mut want);
            assert_eq!(got.len(), input.len());
            for (g, w) in got.iter().zip(&want) {
                assert_eq!(*g, w * gain);
            }
        }
    }

    #[test]
    fn cfar_ca_threshold_on_unit_power_is_the_full_window_factor() {
        // |e| = 1 everywhere: the training power is 1 in every full window.
        let input: Vec<f64> = (0..100).map(|i| if i % 2 == 0 { 1.5 } else { -0.5 }).collect();
        let mut plan = CfarPlan::new(CfarMethod::CellAveraging, 1, 4, 1, 0, 1e-2).expect("valid");
        let alpha = plan.factor(plan.full_window());
        let (mut e, mut out) = (Vec::new(), Vec::new());
        cfar_thresholds(&mut plan, &input, 0.5, 2.0, &mut e, &mut out);
        for (p, v) in out.iter().enumerate().take(95).skip(5) {
            assert!((v - 2.0 * alpha).abs() < 1e-12, "cell {p}: {v}");
        }
        // The first cell has only right-hand training cells; none at all gives +∞.
        let mut lone = CfarPlan::new(CfarMethod::CellAveraging, 200, 4, 1, 0, 1e-2).expect("valid");
        cfar_thresholds(&mut lone, &input, 0.5, 2.0, &mut e, &mut out);
        assert!(out.iter().all(|v| *v == f64::INFINITY));
    }

    /// Naive reference: each index of `range` above the level whose
    /// predecessor in the range is not (the range opening above counts).
    fn naive_upcrossings(y: &[f64], range: Range<usize>, level: &dyn Fn(usize) -> f64) -> u64 {
        let start = range.start;
        range
            .filter(|&p| y[p] > level(p) && (p == start || !(y[p - 1] > level(p - 1))))
            .count() as u64
    }

    #[test]
    fn noise_gate_crossings_match_a_naive_count() {
        let y: Vec<f64> = (0..400).map(|i| ((i as f64) * 0.37).sin() + 0.3 * ((i as f64) * 1.9).cos()).collect();
        let per_cell: Vec<f64> = (0..400).map(|i| 0.5 + 0.001 * i as f64).collect();
        for range in [1..400, 10..50, 200..201, 300..300] {
            let fixed = Level::Fixed(0.8).upcrossings(&y, range.clone());
            assert_eq!(fixed, naive_upcrossings(&y, range.clone(), &|_| 0.8), "{range:?}");
            let cells = Level::PerCell(&per_cell).upcrossings(&y, range.clone());
            assert_eq!(cells, naive_upcrossings(&y, range.clone(), &|p| per_cell[p]), "{range:?}");
        }
    }

    #[test]
    fn gate_excursions_count_what_the_self_check_counts() {
        let y: Vec<f64> = (0..400).map(|i| ((i as f64) * 0.37).sin() + 0.3 * ((i as f64) * 1.9).cos()).collect();
        let per_cell: Vec<f64> = (0..400).map(|i| 0.5 + 0.001 * i as f64).collect();
        let runs = [1..120, 150..151, 200..399];
        let mut out = Vec::new();
        // One per up-crossing, at each excursion's highest position.
        excursions(&y, &runs, |p| y[p] > 0.8, false, &mut out);
        let crossings: u64 = runs.iter().map(|r| Level::Fixed(0.8).upcrossings(&y, r.clone())).sum();
        assert!(crossings > 10);
        assert_eq!(out.iter().map(|e| e.1).sum::<u64>(), crossings);
        for &(top, n) in &out {
            assert_eq!(n, 1);
            assert!(y[top] > 0.8 && y[top] >= y[top - 1] && y[top] >= y[top + 1], "{top}");
        }
        // CFAR: every cell above its own threshold.
        out.clear();
        excursions(&y, &runs, |p| y[p] > per_cell[p], true, &mut out);
        let cells = runs.iter().flat_map(|r| r.clone()).filter(|&p| y[p] > per_cell[p]).count() as u64;
        assert_eq!(out.iter().map(|e| e.1).sum::<u64>(), cells);
        // Context: the whole gate's excursions outside the counted runs count nothing.
        out.clear();
        excursions(&y, &runs[..1], |p| y[p] > 0.8, false, &mut out);
        let counted = out.len();
        context_excursions(&y, &[0..400], &runs[..1], |p| y[p] > 0.8, &mut out);
        assert!(out.len() > counted);
        assert!(out[counted..].iter().all(|&(top, n)| n == 0 && !(1..120).contains(&top)));
    }

    #[test]
    fn exceedance_dispersion_is_one_for_white_output_and_grows_with_correlation() {
        // White: P(X₀ ≤ u < X₁) = p(1 − p), so λ = 0.
        assert!((exceedance_dispersion(1e-3, 0.0) - 1.0).abs() < 1e-9);
        let (a, b) = (exceedance_dispersion(1e-4, 0.5), exceedance_dispersion(1e-4, 0.99));
        assert!(1.0 < a && a < b, "{a} {b}");
        // Smooth output: 2r − 1 for mean run length r = p/p_up (geometric runs).
        let run = 1e-4 / ln_upcrossing_prob(special::q_inv(1e-4), 0.99).exp();
        assert!((b / (2.0 * run - 1.0) - 1.0).abs() < 1e-3, "{b} vs run {run}");
    }

    #[test]
    fn false_alarm_counter_accumulates_and_bounds_the_rate() {
        let mut c = FalseAlarmCounter::default();
        let s = c.record(0, 0.0, 5e-3, 1.0);
        assert_eq!((s.observed, s.cells, s.rate, s.excess), (0, 0.0, 0.0, false));
        let s = c.record(3, 1000.4, 5e-3, 1.0);
        assert_eq!(s.expected_per_frame, 1000.4 * 5e-3);
        let s = c.record(5, 999.8, 5e-3, 1.0);
        assert_eq!(s.observed, 8);
        assert_eq!(s.cells, 1000.4 + 999.8);
        assert_eq!(s.rate, 8.0 / (1000.4 + 999.8));
        assert_eq!(s.expected_per_frame, 999.8 * 5e-3);
        assert_eq!(s.ci95, {
            let (lo, hi) = clopper_pearson(8, 2000, 0.95);
            [lo, hi]
        });
        // 8 in 2000 (0.4 %) is not above a 0.5 % design: its interval holds it.
        assert!(!s.excess && s.ci95[0] < 5e-3 && s.ci95[1] > 5e-3);
        // 40 in 3000 (1.3 %) is: the lower end of its 99.8 % interval is above 0.5 %.
        let mut d = FalseAlarmCounter::default();
        let s = c.record(32, 1000.0, 5e-3, 1.0);
        assert!(s.excess, "{s:?}");
        // The same counts from frames whose crossings share a noisy
        // threshold (variance 9x binomial) are 4 in 333: not an excess.
        d.record(8, 2000.2, 5e-3, 9.0);
        let s = d.record(32, 1000.0, 5e-3, 9.0);
        assert!(!s.excess, "{s:?}");
        assert_eq!(s.ci95, {
            let (lo, hi) = clopper_pearson(4, 333, 0.95);
            [lo, hi]
        });
    }
}
