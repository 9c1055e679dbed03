//! Honest uncertainty: for every timing method and SNR from the detection
//! threshold up, the fraction of range errors within ±2σ and ±3σ of the
//! reported `range_sigma_m`, single-shot, on frames with known truth.
//!
//! Acceptance per cell with at least 100 detections: within 2σ in
//! [0.90, 0.98] and within 3σ at least 0.97, each judged with the 99 %
//! Clopper–Pearson interval of the observed fraction (a cell fails only when
//! the whole interval lies outside the band). The whole band is asserted on
//! frames whose pulse shape the scene models (the project's synthesiser) and
//! on the independent generator's (a pulse family the scene does not model),
//! and on the physics simulator's lab set-up (six targets along one beam,
//! each on the previous one's tail, band-limited receiver noise, 8-bit
//! codes, a free-running sample clock), single-shot and averaged.

use crate::common;

use common::{rng, Synth};
use tofwave::frame::Report;
use tofwave::math::stats::clopper_pearson;
use tofwave::pipeline::Pipeline;
use tofwave::scene::{Scene, TimingMethod};

const METHODS: [TimingMethod; 5] = [
    TimingMethod::ConstantFraction,
    TimingMethod::LeadingEdge,
    TimingMethod::PeakParabolic,
    TimingMethod::PeakGaussian,
    TimingMethod::Ml,
];

/// One SNR cell's errors, in units of the reported sigma.
struct Cell {
    snr: f64,
    z: Vec<f64>,
    frames: usize,
}

impl Cell {
    fn within(&self, k: f64) -> u64 {
        self.z.iter().filter(|z| z.abs() <= k).count() as u64
    }
}

/// Runs `frames` frames of one return of peak `amplitude_v` at `tof_s` through
/// `scene` with `method`; the error of the return nearest the truth, over its sigma.
fn cell(scene: &Scene, method: TimingMethod, amplitude_v: f64, frames: usize, seed: u64) -> Cell {
    averaged_cell(scene, method, amplitude_v, frames, 1, seed)
}

/// As [`cell`], with `n` frames averaged per report (`frames` reports).
fn averaged_cell(scene: &Scene, method: TimingMethod, amplitude_v: f64, frames: usize, n: u32, seed: u64) -> Cell {
    let mut scene = scene.clone();
    scene.timing.method = method;
    scene.averaging.frames = n;
    let mut synth = Synth::prototype();
    synth.quantise_8bit = None;
    let tof_s = 213.4e-9;
    synth.returns = vec![(tof_s, amplitude_v)];
    let mut p = Pipeline::new(&scene, "coverage");
    let mut r = rng(seed);
    let mut out: Vec<Report> = Vec::new();
    let mut z = Vec::new();
    for seq in 0..frames as u64 * n as u64 {
        // The start pulse anywhere within a sample: every sub-sample phase
        // (one per report: the averaged frames share the shot's phase).
        synth.start_time_s = ((seq / n as u64) as f64 * 0.618_034).fract() * synth.dt_s;
        p.push(synth.frame(&scene, seq, &mut r), &mut out).expect("frame");
    }
    for rep in &out {
        let hit = rep.returns.iter().min_by(|a, b| (a.tof_s - tof_s).abs().total_cmp(&(b.tof_s - tof_s).abs()));
        // A detection more than 30 ns from the truth is a false alarm, not a timing error.
        if let Some(ret) = hit.filter(|h| (h.tof_s - tof_s).abs() < 30e-9) {
            let sigma_t = 2.0 * ret.range_sigma_m / scene.c_medium_m_per_s();
            z.push((ret.tof_s - tof_s) / sigma_t);
        }
    }
    Cell {
        snr: amplitude_v / synth.noise_sigma_v * (n as f64).sqrt(),
        z,
        frames,
    }
}

/// Checks every cell; returns the failures.
fn judge(label: &str, method: TimingMethod, cells: &[Cell]) -> Vec<String> {
    let mut failures = Vec::new();
    for c in cells {
        let n = c.z.len() as u64;
        let (w2, w3) = (c.within(2.0), c.within(3.0));
        let rms = (c.z.iter().map(|z| z * z).sum::<f64>() / n.max(1) as f64).sqrt();
        eprintln!(
            "{label} {:>17} SNR {:6.1}: {n:4}/{} detected, within 1σ {:.3} 2σ {:.3} 3σ {:.3}, rms z {rms:.2}",
            method.name(),
            c.snr,
            c.frames,
            c.within(1.0) as f64 / n.max(1) as f64,
            w2 as f64 / n.max(1) as f64,
            w3 as f64 / n.max(1) as f64,
        );
        if n < 100 {
            continue;
        }
        let ci2 = clopper_pearson(w2, n, 0.99);
        let ci3 = clopper_pearson(w3, n, 0.99);
        if ci2.1 < 0.90 || ci2.0 > 0.98 || ci3.1 < 0.97 {
            failures.push(format!(
                "{label} {} SNR {:.1}: within 2σ {w2}/{n} (99 % CI {:.3?}), within 3σ {w3}/{n} (CI {:.3?})",
                method.name(),
                c.snr,
                ci2,
                ci3
            ));
        }
    }
    failures
}

#[test]
fn reported_sigma_covers_the_error_of_every_method_at_every_snr() {
    let scene = Scene::default_scene();
    let mut failures = Vec::new();
    for (m, &method) in METHODS.iter().enumerate() {
        let cells: Vec<Cell> = [0.02, 0.04, 0.08, 0.16, 0.4, 1.0]
            .iter()
            .enumerate()
            .map(|(i, &a)| cell(&scene, method, a, 300, 1000 + 10 * m as u64 + i as u64))
            .collect();
        failures.extend(judge("default scene", method, &cells));
    }
    assert!(failures.is_empty(), "{} cells fail:\n{}", failures.len(), failures.join("\n"));
}

/// Frames from the independent generator (`common::seedgen`: a sharp-onset
/// pulse family the scene does not model, 8-bit scope quantisation with the
/// vertical scale set per amplitude, shot jitter against the sample clock),
/// processed with the default scene after a calibration at 5 m.
fn seedgen_cell(method: TimingMethod, amplitude_v: f64, frames: usize, seed: u64) -> Cell {
    seedgen_averaged_cell(method, amplitude_v, frames, 1, seed)
}

/// As [`seedgen_cell`], `n` frames averaged per report (`frames` reports;
/// the calibration averaged alike, as a user would calibrate the scene in use).
fn seedgen_averaged_cell(method: TimingMethod, amplitude_v: f64, frames: usize, n: u32, seed: u64) -> Cell {
    use common::seedgen::{generate, GenConfig};
    let mut scene = Scene::default_scene();
    scene.timing.method = method;
    scene.averaging.frames = n;
    // Calibrate as a user would: a target at a known range, a strong return.
    let mut cfg = GenConfig::default();
    cfg.speed_of_light_m_per_s = scene.c_medium_m_per_s();
    cfg.targets = vec![(5.0, 0.5)];
    let mut p = Pipeline::new(&scene, "calibration");
    let mut reports = Vec::new();
    let calibration_reports = if n == 1 { 200 } else { (1600 / n as usize).max(30) };
    for (frame, _) in generate(&cfg, calibration_reports * n as usize, seed ^ 0xca11) {
        p.push(frame, &mut reports).expect("frame");
    }
    let cal = tofwave::calibrate::calibrate(&reports, 5.0, &scene, false).expect("calibrates");
    scene.calibration = cal.file.calibration;
    let range_m = 32.0;
    cfg.targets = vec![(range_m, amplitude_v)];
    let mut p = Pipeline::new(&scene, "coverage");
    let mut out: Vec<Report> = Vec::new();
    for (frame, _) in generate(&cfg, frames * n as usize, seed) {
        p.push(frame, &mut out).expect("frame");
    }
    let mut z = Vec::new();
    for rep in &out {
        let hit = rep.returns.iter().min_by(|a, b| (a.range_m - range_m).abs().total_cmp(&(b.range_m - range_m).abs()));
        // A detection more than 4.5 m (30 ns) from the truth is a false alarm, not a timing error.
        if let Some(ret) = hit.filter(|h| (h.range_m - range_m).abs() < 4.5) {
            z.push((ret.range_m - range_m) / ret.range_sigma_m);
        }
    }
    Cell {
        snr: amplitude_v / cfg.noise_sigma_v * (n as f64).sqrt(),
        z,
        frames,
    }
}

#[test]
fn reported_sigma_covers_the_error_on_independently_generated_frames() {
    let mut failures = Vec::new();
    for (m, &method) in METHODS.iter().enumerate() {
        let cells: Vec<Cell> = [0.0208, 0.04, 0.08, 0.16, 0.4, 1.0]
            .iter()
            .enumerate()
            .map(|(i, &a)| seedgen_cell(method, a, 300, 2000 + 10 * m as u64 + i as u64))
            .collect();
        // On a shape the model does not describe, the sigma holds the
        // mismatch gap's swing beyond what noise gives the gap on the model
        // shape (measured per sensor): it neither misses the mismatch nor
        // counts the noise twice, so the band holds from both sides.
        failures.extend(judge("independent generator", method, &cells));
    }
    assert!(failures.is_empty(), "{} cells fail:\n{}", failures.len(), failures.join("\n"));
}

#[test]
fn reported_sigma_covers_the_error_of_averaged_reports() {
    let scene = Scene::default_scene();
    let mut failures = Vec::new();
    for (m, &method) in METHODS.iter().enumerate() {
        // N = 16: averaged SNR 1.4 to 14; N = 256: 4.6 (105 reports: 27 000
        // frames per method; 2.3 gave 0.955-0.982 within 2σ as well).
        let mut cells: Vec<Cell> = [0.005, 0.01, 0.02, 0.05]
            .iter()
            .enumerate()
            .map(|(i, &a)| averaged_cell(&scene, method, a, 150, 16, 3000 + 10 * m as u64 + i as u64))
            .collect();
        failures.extend(judge("N = 16", method, &cells));
        cells = [0.004]
            .iter()
            .enumerate()
            .map(|(i, &a)| averaged_cell(&scene, method, a, 105, 256, 4000 + 10 * m as u64 + i as u64))
            .collect();
        failures.extend(judge("N = 256", method, &cells));
    }
    assert!(failures.is_empty(), "{} cells fail:\n{}", failures.len(), failures.join("\n"));
}

/// Averaged reports of the independent generator's frames: 16 frames
/// (averaged SNR 1.4 to 14) and 256 (SNR 4.6), every method. The shots
/// jitter against the sample clock, so the averaged pulse is the sharp-onset
/// pulse smoothed by the alignment's sub-sample shifts: a shape further
/// from the scene's than any single shot.
#[test]
fn reported_sigma_covers_the_error_of_averaged_independent_frames() {
    let mut failures = Vec::new();
    for (m, &method) in METHODS.iter().enumerate() {
        let mut cells: Vec<Cell> = [0.005, 0.01, 0.02, 0.05]
            .iter()
            .enumerate()
            .map(|(i, &a)| seedgen_averaged_cell(method, a, 150, 16, 6000 + 10 * m as u64 + i as u64))
            .collect();
        failures.extend(judge("independent N = 16", method, &cells));
        cells = vec![seedgen_averaged_cell(method, 0.004, 105, 256, 7000 + 10 * m as u64)];
        failures.extend(judge("independent N = 256", method, &cells));
    }
    assert!(failures.is_empty(), "{} cells fail:\n{}", failures.len(), failures.join("\n"));
}

/// The lab scene's cells through the bench's own code (what `tofwave bench`
/// prints in its "Coverage on the simulated lab scene" section).
fn lab_cells(method: TimingMethod, n: u32, reports: u64, seed: u64) -> Vec<Cell> {
    let lab = common::load_scene("lab-table-10-20");
    let cells = tofwave::bench::lab_cells(&lab, method, n, reports as usize, seed, &mut || {}).expect("lab coverage runs");
    cells.into_iter().map(|c| Cell { snr: c.snr, z: c.z, frames: c.reports }).collect()
}

/// The lab scene, every method, single shot (300 reports), 16 frames averaged
/// (150) and 256 (105): each target is a cell (the 20.8 mV one at 32 m is
/// found only averaged, and below 100 detections at N = 16 it is printed,
/// not judged). Each return lies on the previous target's 60 ns tail, which
/// every method times with its neighbours' fitted pulses taken off; on a
/// band-limited receiver a crossing's error is smaller than on white noise
/// (the crossing and the peak share the noise's slow excursions); averaged
/// deep, what is left is the table shapes' own error against the pulses
/// (`ModelFloor`). Before these, the N = 256 cells held 0-40 % within 2σ.
#[test]
fn reported_sigma_covers_the_error_on_the_simulated_lab_scene() {
    let mut failures = Vec::new();
    for (m, &method) in METHODS.iter().enumerate() {
        for (i, (n, reports)) in [(1u32, 300u64), (16, 150), (256, 105)].into_iter().enumerate() {
            let cells = lab_cells(method, n, reports, 5000 + 10 * m as u64 + i as u64);
            failures.extend(judge(&format!("lab N = {n}"), method, &cells));
        }
    }
    assert!(failures.is_empty(), "{} cells fail:\n{}", failures.len(), failures.join("\n"));
}
