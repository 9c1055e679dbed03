//! detect: the Neyman-Pearson detector ("matched_filter" or "threshold", as the
//! scene's `detector.kind` says). The threshold holds the design false-alarm
//! probability over the range gate, with the detector output's correlation
//! between neighbouring cells accounted for; threshold crossings in the noise
//! gates are counted against the same design, cumulatively per sensor.

use super::{FrameError, Stage, Work};
use crate::detect::colour::NoiseColour;
use crate::detect::detector::{local_maxima, upcrossings, DetectorPlan};
use crate::detect::extreme::{threshold_for_report, ReportThreshold};
use crate::detect::finite_gate::{mean_error_inflation, t_quantile_from_z};
use crate::detect::qfunc;
use crate::detect::stats::clopper_pearson;
use crate::dsp::pulse::Shape;
use crate::frame::{DetectorSummary, FalseAlarmStats};
use crate::detect::empirical::EmpiricalTail;
use crate::detect::resolve::Resolver;
use crate::scene::{DetectorKind, PfaScope, Scene, ThresholdMode, TimingMethod};

/// At most this many pulses are resolved per report.
const MAX_RESOLVED: usize = 32;

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
            resolve: scene.timing.method == TimingMethod::Ml && scene.detector.kind == DetectorKind::MatchedFilter && std::env::var("TW_NORESOLVE").is_err(),
            resolver: Resolver::default(),
            plan: None,
            thresholds: Vec::new(),
            colour: None,
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
                u: qfunc::q_inv(self.pfa),
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
            let shape = Shape::from_config(&self.pulse_cfg, dt);
            let plan = match self.kind {
                DetectorKind::MatchedFilter => DetectorPlan::matched_filter(&shape, n),
                DetectorKind::Threshold => DetectorPlan::threshold(n),
            };
            // Lags up to the template length are all the output's sigma depends on.
            self.colour = Some(NoiseColour::new(plan.len()));
            self.plan = Some((dt, n, shape, plan));
        }
        let colour = self.colour.as_mut().expect("built with the plan");
        if w.noise.samples >= 2 {
            let (pre, beyond) = (&w.stop_v[w.gates.pre.clone()], &w.stop_v[w.gates.beyond.clone()]);
            colour.add_frame([pre, beyond], w.noise.mean_v);
        }
        let out_colour = colour.output(self.plan.as_ref().expect("built above").3.taps());
        let tau = colour.correlation_time();
        // Output sigma per unit of the sample sigma (1 for white noise).
        let out_gain = out_colour.variance_gain.sqrt();
        w.out_gain = out_gain;
        w.noise_rho = colour.rho().unwrap_or_default();
        let cells = w.gates.range.len();
        let t = self.threshold(cells, out_colour.rho1);
        let (_, _, shape, plan) = self.plan.as_mut().expect("built above");
        let (norm, dc_gain) = (plan.norm(), plan.dc_gain());
        let pre_pos = plan.positions_inside(&w.gates.pre);
        let beyond_pos = plan.positions_inside(&w.gates.beyond);
        let y = plan.run(&w.stop_v, w.noise.mean_v);
        w.detector_output.clear();
        w.detector_output.extend_from_slice(y);
        // The gate's mean and sigma are estimates: Student-t on the inflated
        // sigma keeps the design pfa for any gate size (see detect::finite_gate).
        let samples = w.noise.samples;
        w.nu = if samples > 1 { (samples - 1) as f64 } else { f64::INFINITY };
        // The gate mean's error is σ²τ/n (τ: correlation time in samples); in
        // units of the output variance σ²g that is n·g/τ effective samples.
        let mean_samples = (samples as f64 * out_colour.variance_gain / tau).round().max(1.0) as u64;
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
        let thr = w.threshold_u * w.sigma_v * out_gain;
        local_maxima(&w.detector_output, w.gates.range.clone(), thr, &mut w.detections);
        w.components.clear();
        if w.noise.samples < 2 {
            // Without a noise estimate there is no threshold to hold a false-alarm
            // rate: nothing is declared detected (the report says no_noise_estimate).
            w.detections.clear();
        }
        if self.resolve && !w.detections.is_empty() {
            w.components = self.resolver.resolve(
                &w.stop_v,
                w.noise.mean_v,
                w.sigma_v,
                shape,
                plan,
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
        let observed = upcrossings(y, pre_pos.clone(), thr) + upcrossings(y, beyond_pos.clone(), thr);
        let per_position = if cells > 0 { t.cells_effective / cells as f64 } else { 1.0 };
        let gate_cells = (pre_pos.len() + beyond_pos.len()) as f64 * per_position;
        self.observed_total += observed;
        self.cells_total += gate_cells;
        let trials = self.cells_total.round() as u64;
        let (lo, hi) = clopper_pearson(self.observed_total.min(trials), trials, 0.95);
        w.report.detector = DetectorSummary {
            kind: self.kind.name().into(),
            pfa_design: self.pfa,
            threshold: thr / norm,
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
