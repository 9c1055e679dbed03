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

use super::{FrameError, Stage, Work};
use crate::detect::cfar::{CfarMethod, CfarPlan};
use crate::detect::colour::NoiseColour;
use crate::detect::kernels::{local_maxima, local_maxima_above, upcrossings, upcrossings_above, DetectorPlan};
use crate::detect::whiten::{ArModel, Whitener};
use crate::math::autocov::AutocovarianceAccumulator;
use crate::detect::extreme::{threshold_for_report, ReportThreshold};
use crate::detect::finite_gate::mean_error_inflation;
use crate::math::stats::t_quantile_from_z;
use crate::math::special;
use crate::math::stats::clopper_pearson;
use crate::dsp::pulse::Shape;
use crate::frame::{DetectorSummary, FalseAlarmStats};
use crate::detect::empirical::EmpiricalTail;
use crate::detect::resolve::Resolver;
use crate::scene::{CfarKind, DetectorKind, PfaScope, Scene, ThresholdMode, TimingMethod};

/// At most this many pulses are resolved per report.
const MAX_RESOLVED: usize = 32;

/// Whitening waits for this many gate samples per AR coefficient.
const WHITEN_SAMPLES_PER_COEFFICIENT: f64 = 10.0;

/// Whitening refits at most this many frames apart (without forgetting).
const WHITEN_REFIT_FRAMES: u64 = 64;

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
    /// Whitened matched filter and the frame length it was planned for.
    plan: Option<(usize, DetectorPlan)>,
    z: Vec<f64>,
}

/// CFAR settings and the plan for the current template.
#[derive(Debug)]
struct CfarState {
    kind: CfarKind,
    guard: usize,
    training: usize,
    rank: usize,
    /// Built for (template length, peak tap, per-cell probability).
    plan: Option<((usize, usize, u64), CfarPlan)>,
    e: Vec<f64>,
    thresholds: Vec<f64>,
}

/// Runs the detector on the stop channel.
#[derive(Debug)]
pub struct Detect {
    kind: DetectorKind,
    pfa: f64,
    scope: PfaScope,
    pulse_cfg: crate::scene::PulseConfig,
    /// Maximum-likelihood timing resolves overlapping returns here.
    resolve: bool,
    resolver: Resolver,
    plan: Option<(f64, usize, Shape, DetectorPlan)>,
    /// Thresholds already solved, by range-gate size and output lag-1 correlation (rounded).
    thresholds: Vec<((usize, i32), ReportThreshold)>,
    /// Noise colour pooled over the noise gates: sets the output sigma and correlation.
    colour: Option<NoiseColour>,
    /// What the colour estimate gave at its version: output colour, τ, ρ.
    colour_cache: Option<(u64, crate::detect::colour::OutputColour, f64, Vec<f64>)>,
    whiten: Option<WhitenState>,
    cfar: Option<CfarState>,
    /// Normalised gate outputs, for the empirical threshold mode.
    tail: Option<EmpiricalTail>,
    /// Noise-gate crossings since the pipeline started.
    observed_total: u64,
    /// Effective noise-gate cells since the pipeline started.
    cells_total: f64,
}

impl Detect {
    /// From the scene's detector and return-pulse sections.
    pub fn new(scene: &Scene) -> Detect {
        Detect {
            kind: scene.detector.kind,
            pfa: scene.detector.pfa,
            scope: scene.detector.pfa_scope,
            pulse_cfg: scene.return_pulse.clone(),
            resolve: scene.timing.method == TimingMethod::Ml && scene.detector.kind == DetectorKind::MatchedFilter,
            resolver: Resolver::default(),
            plan: None,
            thresholds: Vec::new(),
            colour: None,
            colour_cache: None,
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
                }
            }),
            tail: (scene.detector.threshold_mode == ThresholdMode::Empirical).then(EmpiricalTail::default),
            observed_total: 0,
            cells_total: 0.0,
        }
    }

    fn threshold(&mut self, cells: usize, rho1: f64) -> ReportThreshold {
        // Solving costs ~1 ms: the correlation is rounded so that a pooled
        // estimate that barely moves reuses the solved threshold. What the
        // threshold depends on is 1 − ρ1 (the up-crossing rate goes as its
        // square root), so that is rounded, to 0.5 % relative steps.
        let key = (cells, ((1.0 - rho1).max(1e-12).ln() * 200.0).round() as i32);
        let rho1 = 1.0 - (key.1 as f64 / 200.0).exp();
        if let Some(t) = self.thresholds.iter().find(|t| t.0 == key) {
            return t.1;
        }
        let t = match self.scope {
            PfaScope::Report => threshold_for_report(self.pfa, cells.max(1), rho1),
            PfaScope::Sample => ReportThreshold {
                u: special::q_inv(self.pfa),
                p_cell: self.pfa,
                cells_effective: cells as f64,
            },
        };
        if self.thresholds.len() >= 16 {
            self.thresholds.remove(0);
        }
        self.thresholds.push((key, t));
        t
    }
}

impl Stage for Detect {
    fn name(&self) -> &'static str {
        self.kind.name()
    }

    fn process(&mut self, mut w: Work, out: &mut Vec<Work>) -> Result<(), FrameError> {
        let dt = w.frame.sample_interval_s;
        let n = w.stop_v.len();
        if self.plan.as_ref().is_none_or(|p| p.0 != dt || p.1 < n) {
            let shape = self.pulse_cfg.shape(dt);
            let plan = match self.kind {
                DetectorKind::MatchedFilter => DetectorPlan::matched_filter(&shape, n),
                DetectorKind::Threshold => DetectorPlan::threshold(n),
            };
            // Lags up to the template length are all the output's sigma depends on.
            self.colour = Some(NoiseColour::new(plan.len()));
            self.colour_cache = None;
            self.plan = Some((dt, n, shape, plan));
            if let Some(ws) = &mut self.whiten {
                ws.plan = None;
            }
        }
        let whitened = match &mut self.whiten {
            Some(ws) => {
                let shape = &self.plan.as_ref().expect("built above").2;
                update_whitener(ws, &w, shape, n)
            }
            None => false,
        };
        if self.whiten.is_some() && !whitened {
            w.report.flags.push("whiten_warming_up".into());
        }
        // Noise colour (pooled gate autocorrelation): the plain matched
        // filter's output sigma and correlation depend on it. The whitened
        // filter's output is white with unit sigma by construction.
        let colour = self.colour.as_mut().expect("built with the plan");
        if w.noise.samples >= 2 {
            let (pre, beyond) = (&w.stop_v[w.gates.pre.clone()], &w.stop_v[w.gates.beyond.clone()]);
            colour.add_frame(&[pre, beyond], w.noise.mean_v);
        }
        let (out_gain, rho1, tau) = match (&self.whiten, whitened) {
            (Some(ws), true) => (1.0, ws.plan.as_ref().expect("whitened").1.rho1(), 1.0),
            _ => {
                // Derived once per change of the pooled estimate.
                if self.colour_cache.as_ref().is_none_or(|c| c.0 != colour.version()) {
                    let oc = colour.output(self.plan.as_ref().expect("built above").3.taps());
                    let rho = colour.rho().unwrap_or_default();
                    self.colour_cache = Some((colour.version(), oc, colour.correlation_time(), rho));
                }
                let (_, oc, tau, rho) = self.colour_cache.as_ref().expect("set above");
                w.noise_rho.clone_from(rho);
                (oc.variance_gain.sqrt(), oc.rho1, *tau)
            }
        };
        w.out_gain = out_gain;
        let cells = w.gates.range.len();
        let t = self.threshold(cells, rho1);
        let white_dof = match (&self.whiten, whitened) {
            (Some(ws), true) => Some(ws.acc.samples() - 1.0 - ws.order as f64),
            _ => None,
        };
        let (_, _, _, raw_plan) = self.plan.as_mut().expect("built above");
        let raw_norm = raw_plan.norm();
        // The plan whose output is thresholded, its input (for CFAR training
        // cells) and the factor from its unit-σ output to volts-equivalent.
        let (plan, input, scale): (&mut DetectorPlan, &[f64], f64) = match (&mut self.whiten, whitened) {
            (Some(ws), true) => {
                let wh = ws.whitener.as_ref().expect("whitened");
                wh.apply(&w.stop_v, w.noise.mean_v, &mut ws.z);
                let plan = &mut ws.plan.as_mut().expect("whitened").1;
                let sigma_eff = raw_norm / plan.norm();
                plan.run(&ws.z, 0.0);
                (plan, &ws.z, sigma_eff)
            }
            _ => {
                raw_plan.run(&w.stop_v, w.noise.mean_v);
                (raw_plan, &w.stop_v, 1.0)
            }
        };
        let dc_gain = plan.dc_gain();
        let pre_pos = plan.positions_inside(&w.gates.pre);
        let beyond_pos = plan.positions_inside(&w.gates.beyond);
        w.detector_output.clear();
        w.detector_output.extend(plan.output().iter().map(|v| v * scale));
        if whitened {
            // Unit σ in whitened units is σ_eff volts-equivalent.
            w.sigma_v = scale;
            let last = w.report.stages.len().saturating_sub(1);
            w.report.stages.insert(last, "whiten".into());
        }
        // The gate's mean and sigma are estimates: Student-t on the inflated
        // sigma keeps the design pfa for any gate size (see detect::finite_gate).
        let samples = w.noise.samples;
        w.nu = if samples > 1 { (samples - 1) as f64 } else { f64::INFINITY };
        if let Some(m) = white_dof {
            // σ comes from the AR fit over every gate sample accumulated.
            w.nu = if m > 1.0 { m } else { f64::INFINITY };
        }
        // The gate mean's error is σ²τ/n (τ: correlation time in samples); in
        // units of the output variance σ²g that is n·g/τ effective samples.
        let mean_samples = (samples as f64 * out_gain * out_gain / tau).round().max(1.0) as u64;
        w.kappa = mean_error_inflation(dc_gain, if samples == 0 { 0 } else { mean_samples });
        w.threshold_t = t_quantile_from_z(t.u, w.nu);
        w.threshold_u = w.threshold_t * w.kappa;
        if let Some(tail) = &self.tail {
            match tail.quantile(t.p_cell) {
                Some(z) => {
                    w.threshold_u = z;
                    w.threshold_t = z / w.kappa;
                    w.report.flags.push("empirical_threshold".into());
                }
                None => w.report.flags.push("empirical_threshold_warming_up".into()),
            }
        }
        let cfar_on = if let Some(cs) = &mut self.cfar {
            let key = (plan.len(), plan.peak_tap(), t.p_cell.to_bits());
            if cs.plan.as_ref().is_none_or(|p| p.0 != key) {
                let method = match cs.kind {
                    CfarKind::Os => CfarMethod::OrderedStatistic { rank: cs.rank },
                    _ => CfarMethod::CellAveraging,
                };
                let p_cell = t.p_cell.clamp(f64::MIN_POSITIVE, 0.5);
                cs.plan = CfarPlan::new(method, cs.guard, cs.training, key.0, key.1, p_cell).ok().map(|p| (key, p));
            }
            match &mut cs.plan {
                Some((_, cp)) => {
                    // Training cells: the detector's own input, mean removed
                    // (the whitened input is already zero-mean).
                    let mean = if whitened { 0.0 } else { w.noise.mean_v };
                    cs.e.clear();
                    cs.e.extend(input.iter().map(|v| v - mean));
                    cp.thresholds(&cs.e, &mut cs.thresholds);
                    // The training cells give the input's sigma; the output's
                    // is out_gain times it (1 for white or whitened noise).
                    for v in &mut cs.thresholds {
                        *v *= scale * out_gain;
                    }
                    // Pd and score: Student-t with the full window's cells.
                    let alpha = cp.factor(cp.full_window());
                    w.threshold_t = alpha;
                    w.threshold_u = alpha;
                    w.kappa = 1.0;
                    w.nu = cp.full_window() as f64;
                    w.report.stages.push(cs.kind.name().into());
                    true
                }
                None => false,
            }
        } else {
            false
        };
        let thr = w.threshold_u * w.sigma_v * out_gain;
        match (&self.cfar, cfar_on) {
            (Some(cs), true) => {
                local_maxima_above(&w.detector_output, w.gates.range.clone(), &cs.thresholds, &mut w.detections)
            }
            _ => local_maxima(&w.detector_output, w.gates.range.clone(), thr, &mut w.detections),
        }
        w.components.clear();
        if w.noise.samples < 2 {
            // Without a noise estimate there is no threshold to hold a false-alarm
            // rate: nothing is declared detected (the report says no_noise_estimate).
            w.detections.clear();
        }
        if self.resolve && !whitened && !cfar_on && !w.detections.is_empty() {
            let (_, _, shape, raw_plan) = self.plan.as_mut().expect("built above");
            w.components = self.resolver.resolve(
                &w.stop_v,
                w.noise.mean_v,
                w.sigma_v,
                shape,
                raw_plan,
                w.gates.range.clone(),
                thr,
                MAX_RESOLVED,
            );
        }
        // Empirical false alarms: excursions above the same threshold in the
        // noise gates, where no return can be. Each gate position counts as
        // cells_effective / cells effective cells, as in the range gate.
        let y = &w.detector_output;
        if let Some(tail) = &mut self.tail {
            for p in pre_pos.clone().chain(beyond_pos.clone()) {
                tail.add(y[p] / (w.sigma_v * out_gain));
            }
        }
        let observed = match (&self.cfar, cfar_on) {
            (Some(cs), true) => {
                upcrossings_above(y, pre_pos.clone(), &cs.thresholds)
                    + upcrossings_above(y, beyond_pos.clone(), &cs.thresholds)
            }
            _ => upcrossings(y, pre_pos.clone(), thr) + upcrossings(y, beyond_pos.clone(), thr),
        };
        let per_position = if cells > 0 { t.cells_effective / cells as f64 } else { 1.0 };
        let gate_cells = (pre_pos.len() + beyond_pos.len()) as f64 * per_position;
        self.observed_total += observed;
        self.cells_total += gate_cells;
        let trials = self.cells_total.round() as u64;
        let (lo, hi) = clopper_pearson(self.observed_total.min(trials), trials, 0.95);
        w.report.detector = DetectorSummary {
            kind: self.kind.name().into(),
            pfa_design: self.pfa,
            threshold: thr / raw_norm,
            pfa_cell: t.p_cell,
            cells_effective: t.cells_effective,
        };
        w.report.false_alarm = FalseAlarmStats {
            expected_per_frame: gate_cells * t.p_cell,
            observed: self.observed_total,
            cells: self.cells_total,
            rate: if self.cells_total > 0.0 { self.observed_total as f64 / self.cells_total } else { 0.0 },
            ci95: [lo, hi],
            excess: trials > 0 && lo > t.p_cell,
        };
        if w.report.false_alarm.excess {
            w.report.flags.push("false_alarm_excess".into());
        }
        out.push(w);
        Ok(())
    }
}

/// Adds this frame's noise gates to the whitener's autocovariance and refits
/// when due; true when a whitening filter is ready for this frame.
fn update_whitener(ws: &mut WhitenState, w: &Work, shape: &Shape, n: usize) -> bool {
    if w.noise.samples >= 2 {
        ws.acc.forget(ws.lambda);
        ws.acc.add_segment(&w.stop_v[w.gates.pre.clone()], w.noise.mean_v);
        ws.acc.add_segment(&w.stop_v[w.gates.beyond.clone()], w.noise.mean_v);
        ws.frames += 1;
    }
    let enough = ws.acc.samples() >= WHITEN_SAMPLES_PER_COEFFICIENT * (ws.order + 1) as f64;
    let due = ws.whitener.is_none()
        || ws.plan.as_ref().is_none_or(|p| p.0 < n)
        || ws.frames.is_power_of_two()
        || ws.frames.is_multiple_of(ws.refit_frames);
    if enough
        && due
        && let Some(model) = ArModel::levinson_durbin(&ws.acc.autocovariance(), ws.order)
    {
        let wh = Whitener::new(&model);
        let (taps, peak_tap) = shape.template();
        let g = wh.whiten_template(&taps);
        ws.plan = Some((n, DetectorPlan::from_template(g, peak_tap, n)));
        ws.whitener = Some(wh);
    }
    ws.whitener.is_some() && ws.plan.as_ref().is_some_and(|p| p.0 >= n)
}
