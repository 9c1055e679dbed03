//! The numpy/scipy peer (`bench/peer/peer.py`), run on the same frames in the
//! same invocation, in two rows:
//!
//! * **stage-matched**: tofwave's reference configuration (start and stop
//!   channels, ML timing, events on) against the peer doing the same stages
//!   on the same channels with the same gates ([`FULL_STAGES`]);
//! * **minimal**: tofwave configured down to the least it can do (stop
//!   channel only, events off) against the peer's minimal chain
//!   ([`MINIMAL_STAGES`]).
//!
//! Frames go over as raw little-endian i16 codes (one file per channel) plus
//! a JSON header (sampling, scales, pulse shapes and templates, gates, the
//! per-cell false-alarm probability, the events test's settings). Both sides
//! are timed best of [`REPEATS`] passes over the frames (alternating between
//! the sides), file reading excluded, the first [`WARMUP_FRAMES`] of each
//! pass off the clock on both sides (start-up). Ranges are compared per tofwave return: the peer's return of the
//! same frame nearest in range (within 1.5 FWHM), |Δrange| / tofwave's
//! `range_sigma_m`.

use std::path::{Path, PathBuf};
use std::process::Command;

use super::grid::{BenchConfig, process_frames_steady, reference_frames};
use crate::dsp::pulse::Shape;
use crate::frame::{Frame, Report, Samples};
use crate::scene::Scene;

/// Passes over the frames on each side; the fastest counts.
pub const REPEATS: usize = 3;

/// Frames at the start of each pass that neither side's clock counts (two
/// of the peer's batches): one-off start-up, not per-frame work. tofwave's
/// first frames build its plans, measure the timing methods' error tables
/// (a few milliseconds of simulation) and learn the noise colour and the
/// events test's nulls; the peer builds its state before its clock and
/// spends its first batches warming numpy's and scipy's caches.
pub const WARMUP_FRAMES: usize = 256;

/// What each side computes per frame in the stage-matched row: (stage,
/// tofwave, peer).
pub const FULL_STAGES: &[(&str, &str, &str)] = &[
    ("decode", "i16 codes to volts, start and stop channels", "the same (2-D arrays, whole batches of frames)"),
    (
        "start",
        "peak; mean and σ off the pulse; start-template matched filter around the peak; ML fit (amplitude, delay); \
         error-table correction; shape-mismatch χ² at 17 positions",
        "the same, less the error-table correction (the filter output only within half a FWHM of the peak; \
         Gauss–Newton fit)",
    ),
    (
        "noise",
        "range and noise gates from t_ref; gate mean, σ, skewness, kurtosis; Jarque–Bera; robust σ (probit fit \
         of the quantised gate samples); contamination test",
        "the same (histogram of the codes by one `bincount`)",
    ),
    (
        "detect",
        "gate autocorrelation pooled over frames (64 lags), output gain and correlation; Student-t threshold \
         with the gate's mean-error inflation; matched filter over the whole frame; local maxima in the range \
         gate; noise-gate up-crossings of the previous frame's threshold, cumulative, Clopper–Pearson",
        "the same (autocorrelation and matched filter by FFT; Clopper–Pearson by `scipy.special.betaincinv`)",
    ),
    (
        "resolve",
        "successive cancellation: ML fit of the strongest peak, subtraction, matched filter again on the \
         residual, until no peak is above the threshold; joint refit; misfit",
        "the same, with the filter output updated only where the subtracted pulse reaches",
    ),
    (
        "events",
        "band-subspace energy of the noise-gate windows (learned null); per return, the energy the band \
         explains beyond pulse and slope, and where above the null the matched-subspace z",
        "the same (batched least squares)",
    ),
    (
        "timing",
        "t_stop, Cramér–Rao σ (joint where pulses overlap), range and range σ, SNR, Pd, flags",
        "t_stop, Cramér–Rao σ, range and range σ, SNR, Pd",
    ),
];

/// What each side computes per frame in the minimal row.
pub const MINIMAL_STAGES: &[(&str, &str, &str)] = &[
    ("decode", "stop channel only (the frames carry no start channel)", "stop channel only"),
    ("start", "none (no start channel: t_ref is the trigger)", "none"),
    (
        "noise",
        "gate mean, σ, skewness, kurtosis, Jarque–Bera, robust σ, contamination test",
        "gate mean and σ",
    ),
    (
        "detect",
        "noise colour, Student-t threshold, matched filter over the whole frame, local maxima, false-alarm counter",
        "matched filter over the whole frame (FFT), Gaussian threshold, strongest peak in the range gate",
    ),
    (
        "timing",
        "resolver: ML fit, subtraction, filter on the residual; Cramér–Rao σ, range σ, Pd",
        "parabolic peak, Gauss–Newton ML fit of the delay, t_stop",
    ),
    ("events", "off (`events.enabled = false`)", "none"),
];

/// One row of the comparison: both sides on the same frames.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerRow {
    /// "stage-matched" or "minimal".
    pub name: &'static str,
    /// Peer time per frame (processing loop only, best of [`REPEATS`]), ns.
    pub peer_ns_per_frame: f64,
    /// tofwave `Pipeline::push` time per frame (best of [`REPEATS`]), ns.
    pub rust_ns_per_frame: f64,
    /// Returns tofwave reported.
    pub rust_returns: usize,
    /// Returns the peer reported.
    pub peer_returns: usize,
    /// tofwave returns with a peer return of the same frame within 1.5 FWHM.
    pub matched: usize,
    /// |range_tofwave − range_peer| / tofwave's range σ over matched returns: 99th percentile.
    pub p99_over_sigma: f64,
    /// The same, largest.
    pub max_over_sigma: f64,
    /// Median |Δrange|, m.
    pub median_abs_delta_m: f64,
}

impl PeerRow {
    /// Peer time / tofwave time per frame.
    pub fn speed_ratio(&self) -> f64 {
        self.peer_ns_per_frame / self.rust_ns_per_frame
    }

    /// Fraction of tofwave's returns the peer found too.
    pub fn matched_fraction(&self) -> f64 {
        if self.rust_returns == 0 { 0.0 } else { self.matched as f64 / self.rust_returns as f64 }
    }

    /// The ranges agree within 0.1 σ (every matched return) and at least 99 %
    /// of tofwave's returns are matched.
    pub fn agree(&self) -> bool {
        self.matched_fraction() >= 0.99 && self.max_over_sigma <= 0.1
    }
}

/// The peer ran: both rows.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerComparison {
    /// Frames processed by both, per row.
    pub frames: usize,
    /// Stage-matched row.
    pub full: PeerRow,
    /// Minimal row.
    pub minimal: PeerRow,
    /// Python, numpy and scipy versions.
    pub peer_versions: String,
}

impl PeerComparison {
    /// The stage-matched row's ratio (the acceptance figure).
    pub fn speed_ratio(&self) -> f64 {
        self.full.speed_ratio()
    }

    /// Both rows' ranges agree.
    pub fn agree(&self) -> bool {
        self.full.agree() && self.minimal.agree()
    }

    /// The report's section (markdown, no heading).
    pub fn markdown(&self) -> String {
        use std::fmt::Write;
        let mut md = String::new();
        let _ = writeln!(
            md,
            "The same {} reference frames through tofwave and `bench/peer/peer.py` ({}), in one run. Times per \
             frame are the best of {REPEATS} passes (alternating between the sides), file reading excluded, one core each, over the frames \
             after the first {WARMUP_FRAMES} of each pass (start-up, off the clock on both sides; none when there are fewer than \
             {} frames). Range agreement: for \
             every return tofwave reports, the peer's return of the same frame nearest in range (within 1.5 FWHM), \
             |range_tofwave − range_peer| / tofwave's `range_sigma_m`.\n",
            self.frames,
            self.peer_versions,
            2 * WARMUP_FRAMES
        );
        let _ = writeln!(
            md,
            "| row | tofwave | peer | peer / tofwave | returns (tofwave / peer / matched) | \\|Δrange\\|/σ p99 | max | median \\|Δrange\\| |\n|---|---|---|---|---|---|---|---|"
        );
        for r in [&self.full, &self.minimal] {
            let _ = writeln!(
                md,
                "| {} | {:.1} µs | {:.1} µs | **{:.2}×** | {} / {} / {} ({:.1} %) | {:.4} | {:.4} | {:.2} µm |",
                r.name,
                r.rust_ns_per_frame / 1e3,
                r.peer_ns_per_frame / 1e3,
                r.speed_ratio(),
                r.rust_returns,
                r.peer_returns,
                r.matched,
                100.0 * r.matched_fraction(),
                r.p99_over_sigma,
                r.max_over_sigma,
                r.median_abs_delta_m * 1e6
            );
        }
        let _ = writeln!(
            md,
            "\nRanges {}.\n",
            if self.agree() { "agree within 0.1 σ in both rows" } else { "**do not agree within 0.1 σ in every row**" }
        );
        for (title, stages) in [("Stage-matched row", FULL_STAGES), ("Minimal row", MINIMAL_STAGES)] {
            let _ = writeln!(md, "{title}: what each side computes per frame.\n\n| stage | tofwave | peer |\n|---|---|---|");
            for (stage, rust, peer) in stages {
                let _ = writeln!(md, "| {stage} | {rust} | {peer} |");
            }
            md.push('\n');
        }
        md
    }
}

/// The peer's outcome.
#[derive(Debug, Clone, PartialEq)]
pub enum PeerOutcome {
    /// It ran.
    Ran(PeerComparison),
    /// It could not run (no Python, venv or pip failure, script error): why.
    Failed(String),
}

/// Runs both rows of the peer comparison on `cfg.reference_frames` frames of
/// `scene` (the reference configuration), creating `target/peer-venv` under
/// `repo_root` when missing. Exchange files go to `target/peer-exchange`.
pub fn run_peer(
    scene: &Scene,
    cfg: &BenchConfig,
    repo_root: &Path,
    _out_dir: &Path,
) -> PeerOutcome {
    match try_run(scene, cfg, repo_root) {
        Ok(c) => PeerOutcome::Ran(c),
        Err(e) => PeerOutcome::Failed(e),
    }
}

fn venv_python(repo_root: &Path) -> Result<PathBuf, String> {
    let venv = repo_root.join("target/peer-venv");
    let python = venv.join("bin/python");
    let requirements = repo_root.join("bench/peer/requirements.txt");
    let ok = |p: &Path| {
        Command::new(p)
            .args(["-c", "import numpy, scipy"])
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false)
    };
    if python.exists() && ok(&python) {
        return Ok(python);
    }
    let run = |cmd: &mut Command, what: &str| -> Result<(), String> {
        let o = cmd.output().map_err(|e| format!("{what}: {e}"))?;
        if o.status.success() {
            Ok(())
        } else {
            let err = String::from_utf8_lossy(&o.stderr);
            let tail: String = err
                .lines()
                .rev()
                .take(3)
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect::<Vec<_>>()
                .join(" / ");
            Err(format!("{what} failed ({}): {tail}", o.status))
        }
    };
    run(
        Command::new("python3").args(["-m", "venv"]).arg(&venv),
        "python3 -m venv target/peer-venv",
    )?;
    run(
        Command::new(venv.join("bin/pip"))
            .args(["install", "--quiet", "-r"])
            .arg(&requirements),
        "pip install -r bench/peer/requirements.txt",
    )?;
    if ok(&python) {
        Ok(python)
    } else {
        Err("the peer venv was created but cannot import numpy and scipy".into())
    }
}

fn try_run(scene: &Scene, cfg: &BenchConfig, repo_root: &Path) -> Result<PeerComparison, String> {
    let python = venv_python(repo_root)?;
    let dir = repo_root.join("target/peer-exchange");
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let (frames, _truth) = reference_frames(scene, cfg.reference_snr_db, 4242, cfg.reference_frames.max(1));

    // Stage-matched: the reference configuration as it is.
    let full = run_row(&python, repo_root, &dir, "stage-matched", scene, &frames)?;

    // Minimal: the stop channel alone, events off; the peer's minimal chain.
    let mut minimal_scene = scene.clone();
    minimal_scene.events.enabled = false;
    let stop_only: Vec<Frame> = frames
        .iter()
        .map(|f| {
            let mut f = f.clone();
            let stop = crate::frame::channel_key(&scene.channels.stop);
            f.channels.retain(|c| crate::frame::channel_key(&c.name) == stop);
            f
        })
        .collect();
    let minimal = run_row(&python, repo_root, &dir, "minimal", &minimal_scene, &stop_only)?;
    Ok(PeerComparison {
        frames: frames.len(),
        peer_versions: full.1.clone(),
        full: full.0,
        minimal: minimal.0,
    })
}

/// The i16 codes of channel `key` of every frame, little-endian, frame after frame.
fn channel_codes(frames: &[Frame], key: &str) -> Result<(Vec<u8>, f64, f64), String> {
    let mut codes = Vec::new();
    let (mut vpc, mut off) = (1.0, 0.0);
    for f in frames {
        let ch = f
            .channels
            .iter()
            .find(|c| crate::frame::channel_key(&c.name) == key)
            .ok_or_else(|| format!("a frame has no channel {key}"))?;
        let Samples::I16(s) = &ch.samples else {
            return Err(format!("the peer takes i16 frames; channel {key} holds {}", ch.samples.kind()));
        };
        codes.reserve(2 * s.len());
        for v in s {
            codes.extend_from_slice(&v.to_le_bytes());
        }
        (vpc, off) = (ch.volts_per_code, ch.offset_v);
    }
    Ok((codes, vpc, off))
}

/// A pulse shape as the peer takes it (parametric shapes only).
fn shape_json(shape: &Shape, fraction: f64) -> Result<serde_json::Value, String> {
    let Shape::Parametric(p) = shape else {
        return Err("the peer takes parametric (bigaussian or Gaussian) pulse shapes".into());
    };
    let (taps, peak_tap) = shape.template();
    let (lo, hi) = shape.support();
    Ok(serde_json::json!({
        "sigma_rise": p.sigma_rise,
        "sigma_fall": p.sigma_fall,
        "support": [lo, hi],
        "taps": taps,
        "peak_tap": peak_tap,
        "fraction_offset": shape.fraction_offset(fraction),
        "fwhm": shape.fwhm(),
    }))
}

/// Runs tofwave (best of [`REPEATS`]) and the peer in `mode` on `frames`;
/// the row and the peer's versions.
fn run_row(
    python: &Path,
    repo_root: &Path,
    dir: &Path,
    name: &'static str,
    scene: &Scene,
    frames: &[Frame],
) -> Result<(PeerRow, String), String> {
    let mode = if name == "minimal" { "minimal" } else { "full" };
    // tofwave's first pass gives the per-cell false-alarm probability the peer thresholds at.
    let warmup = if frames.len() >= 2 * WARMUP_FRAMES { WARMUP_FRAMES } else { 0 };
    let (mut reports, mut best) = process_frames_steady(scene, frames, warmup).map_err(|e| e.to_string())?;
    let pfa_cell = reports
        .iter()
        .map(|r| r.detector.pfa_cell)
        .find(|p| *p > 0.0)
        .ok_or("tofwave produced no report with a threshold")?;
    let dt = frames[0].sample_interval_s;
    let len = frames[0].channels[0].samples.len();
    let stop_key = crate::frame::channel_key(&scene.channels.stop);
    let (stop, stop_vpc, stop_off) = channel_codes(frames, &stop_key)?;
    let stop_file = dir.join(format!("{mode}-stop.i16"));
    std::fs::write(&stop_file, &stop).map_err(|e| format!("{}: {e}", stop_file.display()))?;
    let start_file = dir.join(format!("{mode}-start.i16"));
    let (mut start_vpc, mut start_off) = (1.0, 0.0);
    if mode == "full" {
        let (start, v, o) = channel_codes(frames, &crate::frame::channel_key(&scene.channels.start))?;
        (start_vpc, start_off) = (v, o);
        std::fs::write(&start_file, &start).map_err(|e| format!("{}: {e}", start_file.display()))?;
    }
    let offsets: Vec<f64> = frames.iter().map(|f| f.first_sample_offset_s).collect();
    let header = serde_json::json!({
        "mode": mode,
        "repeats": 1,
        "warmup_frames": warmup,
        "frames": frames.len(),
        "samples": len,
        "stop_file": stop_file,
        "start_file": start_file,
        "sample_interval_s": dt,
        "stop_volts_per_code": stop_vpc,
        "stop_offset_v": stop_off,
        "start_volts_per_code": start_vpc,
        "start_offset_v": start_off,
        "first_sample_offset_s": offsets,
        "stop_shape": shape_json(&scene.return_pulse.shape(dt), scene.timing.fraction)?,
        "start_shape": shape_json(&scene.start_pulse.shape(dt), scene.timing.fraction)?,
        "c_m_per_s": scene.c_medium_m_per_s(),
        "delay_s": scene.calibration.delay_s,
        "delay_sigma_s": scene.calibration.delay_sigma_s,
        "range_m": [scene.range_gate.min_m, scene.range_gate.max_m],
        "guard_s": scene.noise_gate.guard_s,
        "start_min_amplitude_v": scene.channels.start_min_amplitude_v,
        "reference_offset_s": scene.channels.reference_offset_s,
        "pfa_cell": pfa_cell,
        "normality_alpha": scene.detector.normality_alpha,
        "events": {
            "max_frequency": scene.events.max_frequency_hz * dt,
            "flank": (scene.events.flank_s / dt).ceil().max(1.0) as usize,
            "fit_alpha": scene.events.fit_alpha,
        },
    });
    let header_path = dir.join(format!("{mode}.json"));
    std::fs::write(&header_path, header.to_string()).map_err(|e| format!("{}: {e}", header_path.display()))?;
    let out_path = dir.join(format!("{mode}-out.json"));
    let script = repo_root.join("bench/peer/peer.py");
    // Passes alternate between the two sides, so that a neighbour's load
    // on this machine falls on both; the fastest pass of each counts.
    let mut peer_ns = f64::INFINITY;
    let mut v = serde_json::Value::Null;
    for pass in 0..REPEATS {
        if pass > 0 {
            let (r, seconds) = process_frames_steady(scene, frames, warmup).map_err(|e| e.to_string())?;
            best = best.min(seconds);
            reports = r;
        }
        let _ = std::fs::remove_file(&out_path);
        // One core, as tofwave's side: no BLAS or OpenMP threads.
        let o = Command::new(python)
            .env("OPENBLAS_NUM_THREADS", "1")
            .env("OMP_NUM_THREADS", "1")
            .env("MKL_NUM_THREADS", "1")
            .arg(&script)
            .arg(&header_path)
            .arg(&out_path)
            .output()
            .map_err(|e| format!("running {}: {e}", script.display()))?;
        if !o.status.success() {
            return Err(format!("peer.py ({mode}) failed ({}): {}", o.status, String::from_utf8_lossy(&o.stderr).trim()));
        }
        let text = std::fs::read_to_string(&out_path).map_err(|e| format!("{}: {e}", out_path.display()))?;
        v = serde_json::from_str(&text).map_err(|e| format!("peer output: {e}"))?;
        peer_ns = peer_ns.min(v["ns_per_frame"].as_f64().ok_or("peer output has no ns_per_frame")?);
    }
    let peer: Vec<Vec<f64>> = v["returns"]
        .as_array()
        .ok_or("peer output has no returns")?
        .iter()
        .map(|rets| rets.as_array().map(|a| a.iter().filter_map(|r| r["range_m"].as_f64()).collect()).unwrap_or_default())
        .collect();
    let versions = v["versions"].as_str().unwrap_or("unknown versions").to_string();
    let window_m = 1.5 * super::grid::pulse_fwhm_s(scene) * 0.5 * scene.c_medium_m_per_s();
    let row = compare(name, &reports, &peer, window_m, peer_ns, best * 1e9 / (frames.len() - warmup) as f64);
    Ok((row, versions))
}

/// Matches every tofwave return with the peer's nearest return of the same
/// frame (within `window_m`) and measures the range differences.
fn compare(
    name: &'static str,
    reports: &[Report],
    peer: &[Vec<f64>],
    window_m: f64,
    peer_ns: f64,
    rust_ns: f64,
) -> PeerRow {
    let mut ratios: Vec<f64> = Vec::new();
    let mut deltas: Vec<f64> = Vec::new();
    let mut rust_returns = 0;
    for r in reports {
        rust_returns += r.returns.len();
        let Some(theirs) = peer.get(r.seq_first as usize) else {
            continue;
        };
        for ret in &r.returns {
            let nearest = theirs
                .iter()
                .map(|m| (ret.range_m - m).abs())
                .filter(|d| *d <= window_m)
                .min_by(f64::total_cmp);
            if let Some(d) = nearest {
                deltas.push(d);
                ratios.push(if ret.range_sigma_m > 0.0 { d / ret.range_sigma_m } else { f64::INFINITY });
            }
        }
    }
    ratios.sort_by(f64::total_cmp);
    deltas.sort_by(f64::total_cmp);
    let pick = |v: &[f64], q: f64| {
        if v.is_empty() { f64::NAN } else { v[((v.len() - 1) as f64 * q).round() as usize] }
    };
    PeerRow {
        name,
        peer_ns_per_frame: peer_ns,
        rust_ns_per_frame: rust_ns,
        rust_returns,
        peer_returns: peer.iter().map(|r| r.len()).sum(),
        matched: ratios.len(),
        p99_over_sigma: pick(&ratios, 0.99),
        max_over_sigma: ratios.last().copied().unwrap_or(f64::NAN),
        median_abs_delta_m: pick(&deltas, 0.5),
    }
}
