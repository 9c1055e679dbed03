//! CSV and Markdown output of a bench run.

use std::fmt::Write as _;
use std::path::Path;

use super::grid::{CellStats, RocPoint};
use super::peer::PeerOutcome;
use super::{BenchError, BenchResults, RunOptions};

/// Columns of `work_precision.csv`, in order.
pub const CSV_COLUMNS: [&str; 24] = [
    "variant",
    "averaging",
    "snr_db",
    "snr_measured_db",
    "reports",
    "frames",
    "detected",
    "pd",
    "false_reports",
    "pfa_report",
    "pfa_gate_cell",
    "rmse_m",
    "bias_m",
    "sd_m",
    "crlb_m",
    "report_sigma_m",
    "rmse_over_crlb",
    "ns_per_frame",
    "frames_per_s",
    "ns_per_report",
    "sd_over_crlb",
    "within_1_sigma",
    "within_2_sigma",
    "within_3_sigma",
];

/// Columns of `roc.csv`, in order.
pub const ROC_COLUMNS: [&str; 6] = [
    "snr_db",
    "pfa_design",
    "reports",
    "pd",
    "pfa_report",
    "pfa_gate_cell",
];

fn num(x: f64) -> String {
    if x.is_finite() {
        format!("{x:.6e}")
    } else {
        "nan".into()
    }
}

/// Writes the grid rows as CSV (header [`CSV_COLUMNS`]).
pub fn write_csv(rows: &[CellStats], path: &Path) -> Result<(), BenchError> {
    let mut s = CSV_COLUMNS.join(",");
    s.push('\n');
    for r in rows {
        let fields = [
            r.variant.clone(),
            r.averaging.to_string(),
            num(r.snr_db),
            num(r.snr_measured_db),
            r.reports.to_string(),
            r.frames.to_string(),
            r.detected.to_string(),
            num(r.pd),
            r.false_reports.to_string(),
            num(r.pfa_report),
            num(r.pfa_gate_cell),
            num(r.rmse_m),
            num(r.bias_m),
            num(r.sd_m),
            num(r.crlb_m),
            num(r.report_sigma_m),
            num(r.rmse_over_crlb),
            num(r.ns_per_frame),
            num(r.frames_per_s),
            num(r.ns_per_report),
            num(r.sd_m / r.crlb_m),
            num(r.within_sigma[0]),
            num(r.within_sigma[1]),
            num(r.within_sigma[2]),
        ];
        s.push_str(&fields.join(","));
        s.push('\n');
    }
    std::fs::write(path, s).map_err(|e| BenchError::io(path, e))
}

/// Writes the ROC points as CSV (header [`ROC_COLUMNS`]).
pub fn write_roc_csv(points: &[RocPoint], path: &Path) -> Result<(), BenchError> {
    let mut s = ROC_COLUMNS.join(",");
    s.push('\n');
    for p in points {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{}",
            num(p.snr_db),
            num(p.pfa_design),
            p.reports,
            num(p.pd),
            num(p.pfa_report),
            num(p.pfa_gate_cell)
        );
    }
    std::fs::write(path, s).map_err(|e| BenchError::io(path, e))
}

fn fmt_m(x: f64) -> String {
    if !x.is_finite() {
        "–".into()
    } else if x.abs() >= 0.1 {
        format!("{x:.3}")
    } else {
        format!("{:.2} mm", x * 1e3)
    }
}

fn verdict(ok: bool) -> &'static str {
    if ok { "**met**" } else { "**not met**" }
}

/// The Markdown report.
pub fn markdown(res: &BenchResults, opts: &RunOptions) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# tofwave work-precision report\n");
    let _ = writeln!(md, "Command: `{}`\n", opts.command);
    let _ = writeln!(md, "Machine: {}\n", machine_line());
    let cfg = &opts.config;
    let _ = writeln!(
        md,
        "Scene: the bench scene (weak-32m set-up, 14-bit digitiser), noise-free peak {} V; \
         SNR is the per-frame peak SNR (noise-free peak over the stop channel's noise σ); \
         averaging N frames raises it by 10·log10(N) dB. Seed {}. Range errors are against the \
         simulator's true time of flight (50 % leading-edge crossing, start to stop); a return \
         within 1.5 FWHM of the truth is the target, any other return is a false alarm. \
         Pulse shapes: {}. \
         CRLB: analytic bound for the scene's pulse template with amplitude unknown and the \
         noise σ the pipeline measured, white-noise assumption, stop pulse only: the simulated \
         receiver noise is coloured and the start pulse's own timing noise \
         adds to every range, so RMSE/CRLB has a floor above 1 that shows at high \
         SNR; the pipeline's own `range_sigma_m` (column `pipeline σ`) includes both. Times are \
         single-core wall time in `Pipeline::push` (frames copied before the clock starts).\n",
        cfg.amplitude_v,
        cfg.seed,
        if opts.learn_template {
            format!(
                "return and start shapes learned from {} shots simulated at 35 dB (`tofwave template`'s \
                 method), not the scene's parametric ones",
                crate::bench::LEARN_SHOTS
            )
        } else {
            "the scene's parametric shapes (`--no-learn`)".to_string()
        }
    );

    let _ = writeln!(md, "## Performance targets\n");
    let _ = writeln!(
        md,
        "Reference frames: the embedded prototype scene with a 64-tap return template (5.8 ns rise, \
         19 ns FWHM), 2500 samples of i16 codes (12-bit, ±0.5 V) at 1 GS/s on two channels, white \
         Gaussian noise, one return per frame at 32.1 m and {} dB peak SNR, random sub-sample phase; matched-filter Neyman–Pearson \
         detection (pfa 1e-6 per report), ML timing, N = 1.\n",
        cfg.reference_snr_db
    );
    let _ = writeln!(md, "| target | measured | verdict |\n|---|---|---|");
    let _ = writeln!(
        md,
        "| offline pipeline, one core (reference frames: {} dB, ML, N = 1) | {:.0} frames/s ({:.1} µs/frame) | – |",
        cfg.reference_snr_db,
        res.offline_frames_per_s,
        1e6 / res.offline_frames_per_s
    );
    match &res.peer {
        Some(PeerOutcome::Ran(p)) => {
            let _ = writeln!(
                md,
                "| ≥ 10× the stage-matched, batched numpy/scipy peer; ranges within 0.1 σ | peer {:.1} µs/frame, tofwave {:.1} µs/frame: **{:.2}×**; \\|Δrange\\|/σ max {:.3} | {} |",
                p.full.peer_ns_per_frame / 1e3,
                p.full.rust_ns_per_frame / 1e3,
                p.speed_ratio(),
                p.full.max_over_sigma,
                verdict(p.speed_ratio() >= 10.0 && p.agree())
            );
        }
        Some(PeerOutcome::Failed(why)) => {
            let _ = writeln!(
                md,
                "| ≥ 10× the stage-matched, batched numpy/scipy peer | peer did not run: {} | not measured |",
                why.replace('|', "/").replace('\n', " ")
            );
        }
        None => {
            let _ = writeln!(
                md,
                "| ≥ 10× the stage-matched, batched numpy/scipy peer | skipped (--no-peer) | not measured |"
            );
        }
    }
    if let Some(b) = &res.bandwidth {
        let _ = writeln!(
            md,
            "| averaging ≥ 50 % of the read-only bandwidth | read-only pass {:.2} GB/s, averaging {:.2} GB/s of i16 codes read: **{:.0} %** (copy loop {:.2} GB/s, read + write) | {} |",
            b.read_bytes_per_s / 1e9,
            b.average_bytes_per_s / 1e9,
            100.0 * b.ratio(),
            b.copy_bytes_per_s / 1e9,
            verdict(b.ratio() >= 0.5)
        );
    }
    match &res.service {
        Some(Ok(s)) => {
            let ratio = s.frames_per_s / res.offline_frames_per_s;
            let _ = writeln!(
                md,
                "| gRPC ingest + processing ≥ 50 % of offline | {:.0} frames/s vs {:.0} offline: **{:.0} %** | {} |",
                s.frames_per_s,
                res.offline_frames_per_s,
                100.0 * ratio,
                verdict(ratio >= 0.5)
            );
        }
        Some(Err(e)) => {
            let _ = writeln!(
                md,
                "| gRPC ingest + processing ≥ 50 % of offline | failed: {} | not measured |",
                e.replace('|', "/")
            );
        }
        None => {}
    }
    match &res.dashboard {
        Some(Ok(d)) => {
            let _ = writeln!(md, "{}", d.check_row());
        }
        Some(Err(e)) => {
            let _ = writeln!(
                md,
                "| ingest with the dashboard open ≥ 95 % of without | failed: {} | not measured |",
                e.replace('|', "/")
            );
        }
        None => {}
    }
    md.push('\n');

    if let Some(l) = &res.limits {
        let _ = writeln!(md, "## Physical limits (reference frames, ML timing)\n");
        md.push_str(&l.markdown());
        md.push('\n');
    }

    if let Some(peer) = &res.peer {
        let _ = writeln!(md, "## numpy/scipy peer\n");
        match peer {
            PeerOutcome::Ran(p) => {
                md.push_str(&p.markdown());
            }
            PeerOutcome::Failed(why) => {
                let _ = writeln!(
                    md,
                    "The peer did not run, so there are no peer numbers: {why}\n"
                );
            }
        }
    }

    if let Some(Ok(s)) = &res.service {
        let _ = writeln!(md, "## Loopback gRPC service\n");
        let _ = writeln!(
            md,
            "{} frames of {} samples (2 channels, i16) pushed as fast as acknowledged, in batches of {} over one \
             stream to a server on 127.0.0.1, reports received by a subscriber. The latency under this flood is the \
             queue's depth (frames wait behind the ones ahead), not the service's own; the curve below measures that.\n\n\
             | ingested | processed | frames/s | latency p50 (flood) | latency p99 (flood) |\n|---|---|---|---|---|\n\
             | {:.3e} samples/s | {:.3e} samples/s | {:.0} | {:.2} ms | {:.2} ms |\n",
            s.frames,
            s.samples_per_frame,
            s.batch_frames,
            s.ingest_samples_per_s,
            s.processed_samples_per_s,
            s.frames_per_s,
            s.latency_p50_s * 1e3,
            s.latency_p99_s * 1e3
        );
        if !s.latency_curve.is_empty() {
            let _ = writeln!(
                md,
                "Latency against offered load: frames sent one per message on a fixed schedule (open loop, \
                 tokio timers: bursts within 1 ms), each timed from its scheduled send to its report reaching the \
                 subscriber; a fresh sensor per load, its first {} frames not timed.\n\n\
                 | load (of the flood's rate) | offered frames/s | frames timed | p50 | p99 | p99.9 |\n|---|---|---|---|---|---|",
                super::service::LATENCY_WARMUP_FRAMES
            );
            for p in &s.latency_curve {
                let _ = writeln!(
                    md,
                    "| {:.0} % | {:.0} | {} | {:.3} ms | {:.3} ms | {:.3} ms |",
                    100.0 * p.load,
                    p.offered_frames_per_s,
                    p.frames,
                    p.p50_s * 1e3,
                    p.p99_s * 1e3,
                    p.p999_s * 1e3
                );
            }
            md.push('\n');
        }
    }

    if let Some(Ok(d)) = &res.dashboard {
        let _ = writeln!(md, "## Dashboard cost\n\n{}", d.markdown());
    }

    let _ = writeln!(md, "## RMSE / CRLB per method (N = 1)\n");
    let variants = unique(res.cells.iter().map(|c| c.variant.clone()));
    let snrs = unique_f(res.cells.iter().map(|c| c.snr_db));
    let _ = write!(md, "| method |");
    for s in &snrs {
        let _ = write!(md, " {s} dB |");
    }
    let _ = write!(md, "\n|---|");
    for _ in &snrs {
        md.push_str("---|");
    }
    md.push('\n');
    for v in &variants {
        let _ = write!(md, "| {v} |");
        for s in &snrs {
            let c = res
                .cells
                .iter()
                .find(|c| &c.variant == v && c.averaging == 1 && c.snr_db == *s);
            match c {
                Some(c) if c.rmse_over_crlb.is_finite() => {
                    let _ = write!(md, " {:.2} |", c.rmse_over_crlb);
                }
                _ => md.push_str(" – |"),
            }
        }
        md.push('\n');
    }

    let _ = writeln!(md, "\n## Coverage of the reported sigma\n");
    let _ = writeln!(
        md,
        "Fraction of detected returns whose range error against the truth lies within 1, 2 and 3 of their own \
         `range_sigma_m` (a Gaussian error would give 0.68 / 0.95 / 0.997; the acceptance band at 2σ is 0.90–0.98), \
         next to RMSE/CRLB and the time per frame.\n"
    );
    let _ = writeln!(
        md,
        "| method | N | SNR dB | detected | within 1σ | within 2σ | within 3σ | RMSE/CRLB | ns/frame |\n|---|---|---|---|---|---|---|---|---|"
    );
    for c in &res.cells {
        let f = |v: f64| if v.is_finite() { format!("{v:.3}") } else { "–".into() };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {:.0} |",
            c.variant,
            c.averaging,
            c.snr_db,
            c.detected,
            f(c.within_sigma[0]),
            f(c.within_sigma[1]),
            f(c.within_sigma[2]),
            f(c.rmse_over_crlb),
            c.ns_per_frame
        );
    }

    match &res.lab_coverage {
        None => {}
        Some(Err(e)) => {
            let _ = writeln!(md, "\n## Coverage on the simulated lab scene\n\nNot measured: {e}");
        }
        Some(Ok(cells)) => {
            let _ = writeln!(md, "\n## Coverage on the simulated lab scene\n");
            let _ = writeln!(
                md,
                "The physics simulator's lab set-up (`{}`: the source's Table 10.20 targets along one beam, each return \
                 on the previous one's tail, band-limited receiver noise, 8-bit codes, a free-running sample clock), \
                 calibrated at {} m on separate frames; one row per method, averaging depth and target. SNR is the \
                 averaged peak over the measured noise. Band: within 2σ in [0.90, 0.98] and within 3σ ≥ 0.97 by the \
                 99 % Clopper–Pearson interval, judged with at least 100 detections (\"–\" below that).\n",
                super::LAB_SCENE,
                super::LAB_CALIBRATION_RANGE_M
            );
            let _ = writeln!(
                md,
                "| method | N | target m | SNR | detected | within 1σ | within 2σ | within 3σ | rms z | band |\n|---|---|---|---|---|---|---|---|---|---|"
            );
            let f = |v: f64| if v.is_finite() { format!("{v:.3}") } else { "–".into() };
            for c in cells {
                let band = match c.meets_band() {
                    None => "–",
                    Some(true) => "met",
                    Some(false) => "**not met**",
                };
                let _ = writeln!(
                    md,
                    "| {} | {} | {:.2} | {:.1} | {}/{} | {} | {} | {} | {} | {band} |",
                    c.method.name(),
                    c.averaging,
                    c.range_m,
                    c.snr,
                    c.z.len(),
                    c.reports,
                    f(c.fraction_within(1.0)),
                    f(c.fraction_within(2.0)),
                    f(c.fraction_within(3.0)),
                    if c.rms_z().is_finite() { format!("{:.2}", c.rms_z()) } else { "–".into() }
                );
            }
        }
    }

    let _ = writeln!(md, "\n## All cells\n");
    let _ = writeln!(
        md,
        "| method | N | SNR dB | Pd | pfa/report | RMSE | bias | CRLB | RMSE/CRLB | pipeline σ | ns/frame | frames/s |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for c in &res.cells {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {:.3} | {:.3} | {} | {} | {} | {} | {} | {:.0} | {:.0} |",
            c.variant,
            c.averaging,
            c.snr_db,
            c.pd,
            c.pfa_report,
            fmt_m(c.rmse_m),
            fmt_m(c.bias_m),
            fmt_m(c.crlb_m),
            if c.rmse_over_crlb.is_finite() {
                format!("{:.2}", c.rmse_over_crlb)
            } else {
                "–".into()
            },
            fmt_m(c.report_sigma_m),
            c.ns_per_frame,
            c.frames_per_s
        );
    }

    let _ = writeln!(md, "\n## ROC (matched filter, N = 1)\n");
    let _ = writeln!(
        md,
        "| SNR dB | design pfa | Pd | pfa/report | gate pfa/cell |\n|---|---|---|---|---|"
    );
    for p in &res.roc {
        let _ = writeln!(
            md,
            "| {} | {:.0e} | {:.3} | {:.3} | {:.2e} |",
            p.snr_db, p.pfa_design, p.pd, p.pfa_report, p.pfa_gate_cell
        );
    }
    let _ = writeln!(
        md,
        "\nFiles: `work_precision.csv`, `roc.csv`, `work_precision.svg` (RMSE against compute time per report), \
         `rmse_over_crlb.svg`, `roc.svg`."
    );
    md
}

fn unique(it: impl Iterator<Item = String>) -> Vec<String> {
    let mut v: Vec<String> = Vec::new();
    for x in it {
        if !v.contains(&x) {
            v.push(x);
        }
    }
    v
}

fn unique_f(it: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = Vec::new();
    for x in it {
        if !v.contains(&x) {
            v.push(x);
        }
    }
    v
}

/// CPU model, cores and date, from `lscpu`/`/proc/cpuinfo` when available.
pub fn machine_line() -> String {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = cpuinfo
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split(':').nth(1))
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let date = std::process::Command::new("date")
        .args(["-u", "+%Y-%m-%d %H:%M UTC"])
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_default();
    format!("{model}, {cores} cores available, {date}")
}

/// Writes `work_precision.csv`, `roc.csv` and `report.md` into `dir`.
pub fn write_all(res: &BenchResults, opts: &RunOptions, dir: &Path) -> Result<(), BenchError> {
    write_csv(&res.cells, &dir.join("work_precision.csv"))?;
    write_roc_csv(&res.roc, &dir.join("roc.csv"))?;
    let p = dir.join("report.md");
    std::fs::write(&p, markdown(res, opts)).map_err(|e| BenchError::io(&p, e))
}
