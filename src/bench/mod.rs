//! The work-precision report: range error and detection statistics against
//! run time, per timing method and averaging depth, on simulated frames with
//! ground truth; the numpy/scipy peer side by side; service throughput; and
//! the memory-bandwidth yardsticks for averaging; and the soak run
//! (`tofwave bench --soak`) against a real server process killed midway.
//!
//! Everything here is driven by [`run`] (what `tofwave bench` calls); the
//! pieces are public so that tests can run a tiny grid.

mod cluster;
mod coverage;
mod grid;
mod limits;
mod membw;
mod output;
mod peer;
mod plot;
mod service;
mod soak;
mod threads;

pub use cluster::{ClusterCost, measure_cluster_cost};
pub use coverage::{CoverageCell, LAB_CALIBRATION_RANGE_M, lab_cells};
pub use grid::{
    BenchConfig, CellStats, RocPoint, SnrSetting, Variant, analytic_crlb_range_m, bench_scene,
    offline_throughput, reference_frames, reference_scene, roc, run_grid, snr_scene, variants,
};
pub use limits::{Limits, StageLimit, Yardsticks, fma_chains, fma_rate, measure_limits};
pub use membw::{Bandwidth, measure_bandwidth};
pub use output::{CSV_COLUMNS, ROC_COLUMNS, write_csv, write_roc_csv};
pub use peer::{FULL_STAGES, MINIMAL_STAGES, PeerComparison, PeerOutcome, PeerRow, REPEATS, WARMUP_FRAMES as PEER_WARMUP_FRAMES, run_peer};
pub use service::{DASHBOARD_SENSORS, DashboardCost, LATENCY_LOADS, LatencyPoint, ServiceThroughput, measure_dashboard_cost, measure_service};
pub use threads::{ThreadsCost, measure_threads_cost};
pub use soak::{ChaoticSummary, RssLife, SoakConfig, SoakReport, run_soak};

use std::path::{Path, PathBuf};

/// What can stop the bench.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The base scene cannot be simulated or a variant made it invalid.
    #[error("scene: {0}")]
    Scene(String),
    /// Writing an output file failed.
    #[error("{path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// A plot could not be drawn.
    #[error("plot {path}: {message}")]
    Plot {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// The loopback service run failed.
    #[error("service: {0}")]
    Service(String),
}

impl BenchError {
    fn io(path: &Path, source: std::io::Error) -> BenchError {
        BenchError::Io {
            path: path.to_path_buf(),
            cause: source,
        }
    }
}

/// Which optional sections `run` includes.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// The grid, ROC and repetition counts.
    pub config: BenchConfig,
    /// Run the numpy/scipy peer (creates its venv when missing).
    pub peer: bool,
    /// Run the loopback gRPC throughput test.
    pub service: bool,
    /// Measure read-only, copy and averaging bandwidth, and the physical-limit table
    /// (each stage against its arithmetic or memory bound), which uses it.
    pub bandwidth: bool,
    /// Learn the return and start pulse shapes from simulated shots first
    /// (as `tofwave template` does) instead of timing with the scene's
    /// parametric shapes.
    pub learn_template: bool,
    /// Repository root: where `bench/peer/` is and `target/peer-venv` goes.
    pub repo_root: PathBuf,
    /// The command line, written into the report.
    pub command: String,
}

/// Shots simulated at 35 dB for [`learned_scene`].
pub const LEARN_SHOTS: u64 = 400;

/// `base` with its return and start pulse shapes learned, as `tofwave
/// template` learns them, from [`LEARN_SHOTS`] shots simulated at 35 dB peak
/// SNR (three passes): model-based timing needs the shape the receiver
/// actually produces.
pub fn learned_scene(base: &crate::scene::Scene, cfg: &BenchConfig) -> Result<crate::scene::Scene, BenchError> {
    use crate::pipeline::learn::{learn_shapes, LearnOptions};
    let (sc, _) = snr_scene(base, cfg.amplitude_v, 35.0)?;
    let sim = crate::physics::Simulator::new(&sc).map_err(|e| BenchError::Scene(e.to_string()))?;
    let frames: Vec<crate::frame::Frame> = (0..LEARN_SHOTS).map(|i| sim.frame(cfg.seed ^ 0x5eed, i).0).collect();
    let opts = LearnOptions { passes: 3, ..Default::default() };
    let learned = learn_shapes(&sc, "bench", &frames, &opts, |_| {}, |_| {})
        .map_err(|e| BenchError::Scene(format!("learning the template: {e}")))?;
    let mut out = base.clone();
    out.return_pulse = learned.return_pulse;
    out.start_pulse = learned.start_pulse;
    Ok(out)
}

/// Everything one bench run measured.
#[derive(Debug, Clone)]
pub struct BenchResults {
    /// One row per (variant, averaging depth, SNR).
    pub cells: Vec<CellStats>,
    /// ROC points.
    pub roc: Vec<RocPoint>,
    /// Peer comparison (or why there is none).
    pub peer: Option<PeerOutcome>,
    /// Loopback service throughput.
    pub service: Option<Result<ServiceThroughput, String>>,
    /// Ingest throughput with and without the dashboard open (runs with the service test).
    pub dashboard: Option<Result<DashboardCost, String>>,
    /// Read-only, copy-loop and averaging bandwidth.
    pub bandwidth: Option<Bandwidth>,
    /// Single-core offline pipeline throughput on the reference configuration
    /// (ML timing, N = 1, 2500-sample i16 frames), frames/s.
    pub offline_frames_per_s: f64,
    /// Each stage's time on the reference frames against its physical limit.
    pub limits: Option<Limits>,
    /// Coverage of the reported sigma on the simulated lab scene (or why
    /// there is none); `None` when the configuration asks for no runs.
    pub lab_coverage: Option<Result<Vec<CoverageCell>, String>>,
}

/// The lab scene the coverage section runs, under the repository root.
pub const LAB_SCENE: &str = "replay-data/scenes/lab-table-10-20.toml";

/// Every timing method through the lab scene at each of `cfg.lab_coverage`'s
/// averaging depths.
fn run_lab_coverage(cfg: &BenchConfig, repo_root: &Path, progress: &indicatif::ProgressBar) -> Result<Vec<CoverageCell>, String> {
    let path = repo_root.join(LAB_SCENE);
    let lab = crate::scene::Scene::load(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut cells = Vec::new();
    for (m, &method) in crate::scene::TimingMethod::ALL.iter().enumerate() {
        for (i, &(n, reports)) in cfg.lab_coverage.iter().enumerate() {
            let seed = cfg.seed ^ (0x1ab0 + 10 * m as u64 + i as u64);
            cells.extend(lab_cells(&lab, method, n, reports, seed, &mut || progress.inc(1))?);
        }
    }
    Ok(cells)
}

/// Runs the whole bench on `base` and writes `report.md`, the CSVs and the
/// SVG plots into `out_dir`. `progress` is advanced by one per pipeline
/// frame (its length is set here).
pub fn run(
    base: &crate::scene::Scene,
    opts: &RunOptions,
    out_dir: &Path,
    progress: &indicatif::ProgressBar,
) -> Result<BenchResults, BenchError> {
    std::fs::create_dir_all(out_dir).map_err(|e| BenchError::io(out_dir, e))?;
    let cfg = &opts.config;
    progress.set_length(cfg.total_work());
    let learned;
    let base = if opts.learn_template {
        progress.set_message("learning the template");
        learned = learned_scene(base, cfg)?;
        &learned
    } else {
        base
    };
    progress.set_message("work-precision grid");
    let cells = run_grid(base, cfg, &variants(), progress)?;
    progress.set_message("ROC");
    let roc_points = roc(base, cfg, progress)?;

    progress.set_message("reference throughput");
    let reference = grid::reference_scene();
    let offline_frames_per_s =
        grid::offline_throughput(&reference, cfg.reference_snr_db, cfg.reference_frames)?;

    let limits = opts.bandwidth.then(|| {
        progress.set_message("physical limits");
        let (frames, _) = reference_frames(&reference, cfg.reference_snr_db, 99, cfg.reference_frames.max(2));
        measure_limits(&reference, &frames, (frames.len() / 5).min(400))
    });

    let lab_coverage = (!cfg.lab_coverage.is_empty()).then(|| {
        progress.set_message("coverage on the lab scene");
        run_lab_coverage(cfg, &opts.repo_root, progress)
    });

    let peer = if opts.peer {
        progress.set_message("numpy/scipy peer");
        Some(run_peer(&reference, cfg, &opts.repo_root, out_dir))
    } else {
        None
    };
    let bandwidth = opts.bandwidth.then(|| {
        progress.set_message("memory bandwidth");
        measure_bandwidth(2500, 4096)
    });
    let service_result = if opts.service {
        progress.set_message("loopback service");
        Some(
            measure_service(&reference, cfg.reference_snr_db, cfg.service_frames)
                .map_err(|e| e.to_string()),
        )
    } else {
        None
    };
    let dashboard = if opts.service {
        progress.set_message("dashboard cost");
        Some(
            measure_dashboard_cost(&reference, cfg.reference_snr_db, 2 * cfg.service_frames, 5)
                .map_err(|e| e.to_string()),
        )
    } else {
        None
    };
    progress.finish_and_clear();

    let results = BenchResults {
        dashboard,
        cells,
        roc: roc_points,
        peer,
        service: service_result,
        bandwidth,
        offline_frames_per_s,
        limits,
        lab_coverage,
    };
    output::write_all(&results, opts, out_dir)?;
    plot::write_all(&results, out_dir)?;
    Ok(results)
}
