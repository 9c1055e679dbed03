//! The numpy/scipy peer (`bench/peer/peer.py`), run on the same frames in the
//! same invocation: frames go over as raw little-endian i16 codes plus a JSON
//! header (sample interval, volts per code, template taps, noise gate, search
//! window, per-cell false-alarm probability, pulse shape for the ML fit).

use std::path::{Path, PathBuf};
use std::process::Command;

use super::grid::{BenchConfig, REF_PRE_TRIGGER, process_frames, reference_frames};
use crate::dsp::pulse::PulseShape;
use crate::frame::{Report, Samples};
use crate::scene::Scene;

/// The peer ran: its numbers next to tofwave's.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerComparison {
    /// Frames processed by both.
    pub frames: usize,
    /// Peer time per frame (processing loop only), ns.
    pub peer_ns_per_frame: f64,
    /// tofwave `Pipeline::push` time per frame on the same frames, ns.
    pub rust_ns_per_frame: f64,
    /// Frames where tofwave reported a return.
    pub rust_returns: usize,
    /// Frames where the peer found a return.
    pub peer_returns: usize,
    /// Frames where both found the return (within 1.5 FWHM of each other).
    pub matched: usize,
    /// Median |Δt_stop| over matched frames, s.
    pub median_abs_delta_s: f64,
    /// Largest |Δt_stop|, s.
    pub max_abs_delta_s: f64,
    /// Largest |Δt_stop| over tofwave's reported timing sigma (range_sigma_m · 2 / c).
    pub max_delta_over_sigma: f64,
    /// Fraction of matched frames with |Δt_stop| ≤ 3 sigma.
    pub within_3_sigma_fraction: f64,
    /// Python, numpy and scipy versions.
    pub peer_versions: String,
}

impl PeerComparison {
    /// Peer time / tofwave time per frame.
    pub fn speed_ratio(&self) -> f64 {
        self.peer_ns_per_frame / self.rust_ns_per_frame
    }

    /// Both give the same ranges within the estimators' precision: at least
    /// 99 % of the common detections within 3 sigma, and most frames matched.
    pub fn agree(&self) -> bool {
        self.matched * 10 >= self.rust_returns.min(self.peer_returns) * 9
            && self.within_3_sigma_fraction >= 0.99
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

/// Runs the peer on `cfg.reference_frames` frames of `scene` (the reference
/// configuration), creating `target/peer-venv` under `repo_root` when missing.
/// Exchange files go to `target/peer-exchange`.
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
    let script = repo_root.join("bench/peer/peer.py");
    let dir = repo_root.join("target/peer-exchange");
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;

    let (frames, _truth) = reference_frames(
        scene,
        cfg.reference_snr_db,
        4242,
        cfg.reference_frames.max(1),
    );
    let stop_key = crate::frame::channel_key(&scene.channels.stop);
    let mut codes: Vec<u8> = Vec::new();
    let (mut vpc, mut off, mut dt, mut len) = (1.0, 0.0, 0.0, 0usize);
    let mut offsets = Vec::with_capacity(frames.len());
    for f in &frames {
        let ch = f
            .channels
            .iter()
            .find(|c| crate::frame::channel_key(&c.name) == stop_key)
            .ok_or("a frame has no stop channel")?;
        let Samples::I16(s) = &ch.samples else {
            return Err(format!(
                "the peer takes i16 frames; the stop channel holds {}",
                ch.samples.kind()
            ));
        };
        for v in s {
            codes.extend_from_slice(&v.to_le_bytes());
        }
        (vpc, off, dt, len) = (ch.volts_per_code, ch.offset_v, f.sample_interval_s, s.len());
        offsets.push(f.first_sample_offset_s);
    }

    // tofwave on the same frames; its first report also gives the per-cell pfa.
    let (reports, seconds) = process_frames(scene, &frames).map_err(|e| e.to_string())?;
    let pfa_cell = reports
        .first()
        .map(|r| r.detector.pfa_cell)
        .filter(|p| *p > 0.0)
        .ok_or("tofwave produced no report")?;

    let shape = scene.return_pulse.shape(dt);
    let (taps, peak_index) = shape.template();
    let (lo, hi) = shape.support();
    let steps = ((hi - lo) * 16.0).ceil() as usize;
    let shape_t: Vec<f64> = (0..=steps)
        .map(|k| lo + (hi - lo) * k as f64 / steps as f64)
        .collect();
    let shape_v: Vec<f64> = shape_t
        .iter()
        .map(|&t| shape.value_and_slope(t).0)
        .collect();
    let trig = REF_PRE_TRIGGER;
    let guard = (scene.noise_gate.guard_s / dt).ceil() as usize;
    let tof = |m: f64| 2.0 * m / scene.c_medium_m_per_s() / dt;
    let search = [
        trig + tof(scene.range_gate.min_m).floor() as usize,
        (trig + tof(scene.range_gate.max_m).ceil() as usize + hi.ceil() as usize).min(len),
    ];
    let samples_path = dir.join("frames.i16");
    std::fs::write(&samples_path, &codes)
        .map_err(|e| format!("{}: {e}", samples_path.display()))?;
    let header = serde_json::json!({
        "frames": frames.len(),
        "samples": len,
        "samples_file": samples_path,
        "sample_interval_s": dt,
        "volts_per_code": vpc,
        "offset_v": off,
        "first_sample_offset_s": offsets,
        "template": taps,
        "template_peak_index": peak_index,
        "noise_gate": [0, trig.saturating_sub(guard)],
        "search": search,
        "pfa_cell": pfa_cell,
        "shape_t": shape_t,
        "shape_v": shape_v,
        "fraction_offset": shape.fraction_offset(scene.timing.fraction),
    });
    let header_path = dir.join("frames.json");
    std::fs::write(&header_path, header.to_string())
        .map_err(|e| format!("{}: {e}", header_path.display()))?;
    let out_path = dir.join("peer-out.json");
    let _ = std::fs::remove_file(&out_path);
    let o = Command::new(&python)
        .arg(&script)
        .arg(&header_path)
        .arg(&out_path)
        .output()
        .map_err(|e| format!("running {}: {e}", script.display()))?;
    if !o.status.success() {
        return Err(format!(
            "peer.py failed ({}): {}",
            o.status,
            String::from_utf8_lossy(&o.stderr).trim()
        ));
    }
    let text =
        std::fs::read_to_string(&out_path).map_err(|e| format!("{}: {e}", out_path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("peer output: {e}"))?;
    let peer_t: Vec<Option<f64>> = v["t_stop_s"]
        .as_array()
        .ok_or("peer output has no t_stop_s")?
        .iter()
        .map(|x| x.as_f64())
        .collect();
    let peer_ns = v["ns_per_frame"]
        .as_f64()
        .ok_or("peer output has no ns_per_frame")?;
    let versions = v["versions"]
        .as_str()
        .unwrap_or("unknown versions")
        .to_string();
    Ok(compare(
        scene,
        &reports,
        &peer_t,
        peer_ns,
        seconds * 1e9 / frames.len() as f64,
        versions,
    ))
}

fn compare(
    scene: &Scene,
    reports: &[Report],
    peer_t: &[Option<f64>],
    peer_ns: f64,
    rust_ns: f64,
    versions: String,
) -> PeerComparison {
    let window_s = 1.5 * super::grid::pulse_fwhm_s(scene);
    let to_s = 2.0 / scene.c_medium_m_per_s();
    let mut deltas: Vec<f64> = Vec::new();
    let mut ratios: Vec<f64> = Vec::new();
    let mut rust_returns = 0;
    for r in reports {
        if !r.returns.is_empty() {
            rust_returns += 1;
        }
        let Some(Some(tp)) = peer_t.get(r.seq_first as usize) else {
            continue;
        };
        let best = r
            .returns
            .iter()
            .map(|x| (x.t_stop_s - tp, x.range_sigma_m * to_s))
            .filter(|(d, _)| d.abs() <= window_s)
            .min_by(|a, b| a.0.abs().total_cmp(&b.0.abs()));
        if let Some((d, sigma)) = best {
            deltas.push(d.abs());
            ratios.push(if sigma > 0.0 {
                d.abs() / sigma
            } else {
                f64::INFINITY
            });
        }
    }
    let matched = deltas.len();
    let mut sorted = deltas.clone();
    sorted.sort_by(f64::total_cmp);
    PeerComparison {
        frames: peer_t.len(),
        peer_ns_per_frame: peer_ns,
        rust_ns_per_frame: rust_ns,
        rust_returns,
        peer_returns: peer_t.iter().filter(|t| t.is_some()).count(),
        matched,
        median_abs_delta_s: sorted.get(matched / 2).copied().unwrap_or(f64::NAN),
        max_abs_delta_s: sorted.last().copied().unwrap_or(f64::NAN),
        max_delta_over_sigma: ratios.iter().copied().fold(0.0, f64::max),
        within_3_sigma_fraction: if matched > 0 {
            ratios.iter().filter(|r| **r <= 3.0).count() as f64 / matched as f64
        } else {
            0.0
        },
        peer_versions: versions,
    }
}
