//! Coverage of the reported sigma on the physics simulator's lab set-up
//! (six targets of the source's Table 10.20 along one beam, each return on
//! the previous one's tail, band-limited receiver noise, 8-bit codes, a
//! free-running sample clock): for each timing method, averaging depth and
//! target, the fraction of range errors within 1, 2 and 3 reported sigmas.
//! `tofwave bench` prints it; `tests/suite/coverage.rs` judges it.

use crate::frame::Report;
use crate::math::stats::clopper_pearson;
use crate::physics::{Simulator, Truth};
use crate::pipeline::Pipeline;
use crate::scene::{Scene, TimingMethod};

/// Range of the calibration target of the lab set-up, m (its 3.45 m target).
pub const LAB_CALIBRATION_RANGE_M: f64 = 3.45;

/// A detection farther than this from a target's true range is not its
/// return, m (10 ns of flight).
const SAME_TARGET_M: f64 = 1.5;

/// One target's errors at one method and averaging depth.
#[derive(Debug, Clone)]
pub struct CoverageCell {
    /// Timing method.
    pub method: TimingMethod,
    /// Frames averaged per report.
    pub averaging: u32,
    /// Target index in the scene's simulation.
    pub target: usize,
    /// The target's true range, m.
    pub range_m: f64,
    /// Peak SNR of the averaged return (single-shot peak over the measured
    /// single-shot noise sigma, times √N).
    pub snr: f64,
    /// Reports simulated.
    pub reports: usize,
    /// Range error over the reported range_sigma_m, one per detection.
    pub z: Vec<f64>,
}

impl CoverageCell {
    /// Detections within `k` reported sigmas.
    pub fn within(&self, k: f64) -> u64 {
        self.z.iter().filter(|z| z.abs() <= k).count() as u64
    }

    /// Fraction of detections within `k` reported sigmas (NaN without any).
    pub fn fraction_within(&self, k: f64) -> f64 {
        if self.z.is_empty() { f64::NAN } else { self.within(k) as f64 / self.z.len() as f64 }
    }

    /// RMS of the normalised errors (1 for an exact Gaussian sigma; NaN
    /// without any).
    pub fn rms_z(&self) -> f64 {
        if self.z.is_empty() {
            return f64::NAN;
        }
        (self.z.iter().map(|z| z * z).sum::<f64>() / self.z.len() as f64).sqrt()
    }

    /// The acceptance: with at least 100 detections, within 2σ in
    /// [0.90, 0.98] and within 3σ at least 0.97, each judged by the 99 %
    /// Clopper–Pearson interval of the observed fraction (a cell fails only
    /// when the whole interval lies outside the band). `None` below 100
    /// detections (not judged).
    pub fn meets_band(&self) -> Option<bool> {
        let n = self.z.len() as u64;
        if n < 100 {
            return None;
        }
        let ci2 = clopper_pearson(self.within(2.0), n, 0.99);
        let ci3 = clopper_pearson(self.within(3.0), n, 0.99);
        Some(!(ci2.1 < 0.90 || ci2.0 > 0.98 || ci3.1 < 0.97))
    }
}

/// Runs `lab` (a scene with a simulation section, e.g.
/// `replay-data/scenes/lab-table-10-20.toml`) with `method` and `n` frames
/// averaged per report: calibrates on separate frames as `tofwave
/// calibrate` would at the [`LAB_CALIBRATION_RANGE_M`] target, then
/// simulates `reports` reports; one cell per target. `progress` is called
/// once per pipeline frame.
pub fn lab_cells(
    lab: &Scene,
    method: TimingMethod,
    n: u32,
    reports: usize,
    seed: u64,
    progress: &mut dyn FnMut(),
) -> Result<Vec<CoverageCell>, String> {
    let mut scene = lab.clone();
    scene.timing.method = method;
    scene.averaging.frames = n;
    let sim = Simulator::new(&scene).map_err(|e| format!("lab scene does not simulate: {e}"))?;
    let mut run = |scene: &Scene, seed: u64, count: usize| -> Result<(Vec<Report>, Vec<Truth>), String> {
        let mut p = Pipeline::new(scene, "lab");
        let mut out = Vec::new();
        let mut truth = Vec::new();
        for i in 0..count as u64 * n as u64 {
            let (f, t) = sim.frame(seed, i);
            truth.push(t);
            p.push(f, &mut out).map_err(|e| format!("frame {i}: {e}"))?;
            progress();
        }
        Ok((out, truth))
    };
    let (cal_reports, _) = run(&scene, seed ^ 0xca11, reports.clamp(50, 200))?;
    let cal = crate::calibrate::calibrate(&cal_reports, LAB_CALIBRATION_RANGE_M, &scene, false)
        .map_err(|e| format!("calibrating at {LAB_CALIBRATION_RANGE_M} m: {e}"))?;
    scene.calibration = cal.file.calibration;
    let (out, truth) = run(&scene, seed, reports)?;
    let targets = &scene.simulation.as_ref().ok_or("the lab scene has no [simulation] section")?.targets;
    let mut cells: Vec<CoverageCell> = (0..targets.len())
        .map(|k| CoverageCell { method, averaging: n, target: k, range_m: f64::NAN, snr: 0.0, reports, z: Vec::new() })
        .collect();
    let mut amplitude_v = vec![0.0; targets.len()];
    // SNR against the single-shot noise the pipeline measured (the
    // receiver's, through the TIA).
    let sigma_v = out.iter().map(|r| r.noise.sigma_v).sum::<f64>() / out.len().max(1) as f64 * (n as f64).sqrt();
    for rep in &out {
        let group = &truth[rep.seq_first as usize..=rep.seq_last as usize];
        for (k, cell) in cells.iter_mut().enumerate() {
            let Some(t) = group[0].returns.iter().find(|r| r.target == k) else { continue };
            amplitude_v[k] = t.peak_amplitude_v;
            cell.range_m = t.range_m;
            let hit = rep.returns.iter().min_by(|a, b| (a.range_m - t.range_m).abs().total_cmp(&(b.range_m - t.range_m).abs()));
            if let Some(ret) = hit.filter(|h| (h.range_m - t.range_m).abs() < SAME_TARGET_M) {
                cell.z.push((ret.range_m - t.range_m) / ret.range_sigma_m);
            }
        }
    }
    for (cell, a) in cells.iter_mut().zip(amplitude_v) {
        cell.snr = a / sigma_v * (n as f64).sqrt();
    }
    Ok(cells)
}
