//! The `tofwave` command: parse, load configuration, call the library.

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use std::io::Write;
use std::path::PathBuf;
use tofwave::capture::{self, Format, ReadOptions};
use tofwave::frame::Report;
use tofwave::pipeline::report_json;
use tofwave::calibrate::Calibration;
use tofwave::scene::{CalibrationFile, Scene, TimingMethod, DEFAULT_SCENE_TOML};

/// Waveform processing and detection for direct-detection time-of-flight lidar.
///
/// Turns digitised start/stop waveforms (oscilloscope captures or gRPC frames)
/// into ranges with uncertainties and honest false-alarm statistics. Every
/// command runs on the embedded default scene (the source prototype: 1 GS/s,
/// start on CH1, stop on CH2) unless --scene names another.
#[derive(Parser, Debug)]
#[command(name = "tofwave", version, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the gRPC server: digitisers push frames, dashboards subscribe to reports.
    Serve(tofwave::service::cli::ServeArgs),
    /// Stream capture files to a running server (recorded pace, a multiple of it, or as fast as possible).
    Replay(tofwave::service::cli::ReplayArgs),
    /// Print a server's report stream as JSON lines (the same shape as `process`).
    Subscribe(tofwave::service::cli::SubscribeArgs),
    /// Simulate frames with ground truth from a scene's [simulation] section.
    Simulate(SimulateArgs),
    /// Process capture files offline; prints one JSON report per frame (or averaged group).
    Process(ProcessArgs),
    /// Measure the fixed start-to-stop system delay from captures of a target at a known range.
    Calibrate(CalibrateArgs),
    /// Print the embedded default scene (commented TOML), check a scene file, or measure a
    /// starting scene from a capture (--from-capture).
    Scene(SceneArgs),
    /// Learn the return pulse shape (and the start pulse shape, when the captures have a start channel) from captures (equivalent-time alignment of many shots)
    /// and write a scene that uses it.
    Template(TemplateArgs),
    /// Work-precision report on simulated frames with truth: range RMSE, bias, CRLB, Pd and pfa
    /// against run time per timing method, averaging depth and SNR; the numpy/scipy peer side by
    /// side; loopback gRPC throughput; averaging's bandwidth against a read-only pass. Writes report.md,
    /// CSV and SVG.
    Bench(BenchArgs),
    /// Draw a capture's frame(s) as a PNG or SVG: the stop trace (and start channel), noise gates
    /// shaded, noise mean, each detected return marked with its range and SNR, and below it the
    /// detector output with the threshold. The frames run through the same pipeline as `process`.
    Plot(PlotArgs),
    /// Operate a running server over its Control service: list sensors, read status, get or set
    /// a scene, read a noise model, get or set a calibration.
    Ctl(tofwave::service::cli::CtlArgs),
}

#[derive(Args, Debug)]
struct PlotArgs {
    #[command(flatten)]
    common: SceneInput,
    /// Calibration file from `tofwave calibrate`: its delay (seconds) is subtracted from every time of flight.
    #[arg(long, value_name = "FILE")]
    calibration: Option<PathBuf>,
    /// Frame to draw: its 0-based position in input order (segments of a sequence-mode file count
    /// one each), or an inclusive range A..B drawn as stacked rows (at most 16). With --average N
    /// the averaged group holding the frame is drawn.
    #[arg(long, value_name = "K|A..B", default_value = "0")]
    frame: tofwave::plot::FrameSelection,
    /// Output image; the extension chooses the format: .png (8-bit RGB) or .svg.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Image width, pixels (200..=8000).
    #[arg(long, value_name = "PX", default_value_t = 1400)]
    width: u32,
    /// Image height, pixels (200..=8000) [default: 700 for one frame, 420 per row for several].
    #[arg(long, value_name = "PX")]
    height: Option<u32>,
}

#[derive(Args, Debug)]
struct BenchArgs {
    /// Scene with a [simulation] section holding one target (its reflectivity and thermal noise
    /// are set per SNR) for the work-precision grid and ROC; the performance targets always use the
    /// reference frames (64-tap template, white noise). Default: the embedded bench scene (weak-32m
    /// set-up, 14-bit digitiser).
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    /// Directory for report.md, work_precision.csv, roc.csv and the SVG plots (created).
    #[arg(long, default_value = "bench-out", value_name = "DIR")]
    out: PathBuf,
    /// The long run: SNR every 2.5 dB from 0 to 40 dB and about eight times the trials (tens of minutes).
    #[arg(long)]
    long: bool,
    /// Run the numpy/scipy peer (the default; creates target/peer-venv with pip when missing).
    #[arg(long, overrides_with = "no_peer")]
    peer: bool,
    /// Skip the numpy/scipy peer.
    #[arg(long)]
    no_peer: bool,
    /// Skip the loopback gRPC throughput test.
    #[arg(long)]
    no_service: bool,
    /// Instead of the report: only the dashboard's cost to ingest. Four sensors push simulated
    /// frames to a server on 127.0.0.1 (one connection each), in trials alternating without and
    /// with a client reading the dashboard's /events for every sensor; prints the frames/s of each
    /// trial and the ratio (Markdown) and writes dashboard.md to --out (tens of seconds).
    #[arg(long, conflicts_with = "soak")]
    dashboard_only: bool,
    /// With --dashboard-only: frames per trial, all sensors together (frames).
    #[arg(long, value_name = "N", default_value_t = 8000, requires = "dashboard_only")]
    dashboard_frames: usize,
    /// With --dashboard-only: trials per arm (with and without the dashboard).
    #[arg(long, value_name = "N", default_value_t = 5, requires = "dashboard_only")]
    dashboard_trials: usize,
    /// Skip the bandwidth measurement (a read-only pass, a copy loop and averaging over the same
    /// 20 MB stream of i16 frames) and the physical-limit table that uses it.
    #[arg(long)]
    no_bandwidth: bool,
    /// Time with the scene's parametric pulse shapes instead of shapes learned
    /// from 400 simulated shots at 35 dB (what `tofwave template` does).
    #[arg(long)]
    no_learn: bool,
    /// Random seed of the simulated frames (the same seed gives the same frames).
    #[arg(long, value_name = "S")]
    seed: Option<u64>,
    /// Instead of the report: the soak run. Starts `tofwave serve` (this binary) as a child on
    /// 127.0.0.1 with --state-dir and --record in a scratch directory, pushes frames from every
    /// sensor concurrently with bad frames interleaved, runs stalling and reconnecting subscribers,
    /// kills the server with SIGKILL half way and restarts it, samples its RSS every second, and
    /// reconciles every frame (pushed = acked + rejected, acked = reported, acked <= recorded).
    /// Writes soak.json and soak.md to --out; exits 1 when a check fails.
    #[arg(long)]
    soak: bool,
    /// Soak: frames pushed in all, over all sensors (frames).
    #[arg(long, value_name = "N", default_value_t = 10_000_000, requires = "soak")]
    soak_frames: u64,
    /// Soak: sensors pushing concurrently, one stream each (sensors).
    #[arg(long, value_name = "N", default_value_t = 8, requires = "soak")]
    soak_sensors: usize,
    /// Soak: one frame in N is bad (refused with INVALID_ARGUMENT at the edge); 0: none (frames).
    #[arg(long, value_name = "N", default_value_t = 1000, requires = "soak")]
    soak_bad_every: u64,
    /// Soak: the fraction of frames with a verdict at which the server is killed (SIGKILL) and
    /// restarted, in (0, 1); 1 or more: never killed.
    #[arg(long, value_name = "FRACTION", default_value_t = 0.5, requires = "soak")]
    soak_kill_at: f64,
    /// Soak: RSS samples this long after each server start are warm-up, not judged for flatness (seconds).
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0, requires = "soak")]
    soak_warmup_s: f64,
    /// Soak: keep the scratch directory (recordings, state, server log) instead of deleting it.
    #[arg(long, requires = "soak")]
    soak_keep: bool,
    /// Instead of the report: the cluster path's cost. Trials alternate a server on 127.0.0.1
    /// alone (`serve`) and the same server joined to the NATS JetStream at URL
    /// (`serve --cluster URL`, one node), one sensor pushing as fast as acknowledged; prints the
    /// steady-state frames/s of each trial and their ratio (Markdown) and writes cluster.md to --out.
    #[arg(long, value_name = "URL", conflicts_with_all = ["soak", "dashboard_only"])]
    cluster: Option<String>,
    /// With --cluster: frames per trial and arm (frames).
    #[arg(long, value_name = "N", default_value_t = 8000, requires = "cluster")]
    cluster_frames: usize,
    /// With --cluster: trials per arm.
    #[arg(long, value_name = "N", default_value_t = 3, requires = "cluster")]
    cluster_trials: usize,
    /// Instead of the report: one sensor on N threads against one thread, offline (`process
    /// --threads N`) and in a loopback service (`serve --workers-per-sensor N`), on the same
    /// simulated frames of the default scene (or --scene), trials alternating the arms; each
    /// trial also runs N independent one-thread pipelines at once (the machine's own N-thread
    /// yardstick); prints steady-state frames/s and the ratios (Markdown) and writes threads.md
    /// to --out.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(2..=64),
          conflicts_with_all = ["soak", "dashboard_only", "cluster"])]
    threads: Option<u32>,
    /// With --threads: frames per trial and arm (frames).
    #[arg(long, value_name = "N", default_value_t = 6000, requires = "threads")]
    threads_frames: usize,
    /// With --threads: trials per arm.
    #[arg(long, value_name = "N", default_value_t = 3, requires = "threads")]
    threads_trials: usize,
}

#[derive(Args, Debug)]
struct SceneInput {
    /// Capture files or directories (every capture in a directory, in name order).
    /// Multi-segment files give one frame per segment.
    #[arg(long, short, required = true, num_args = 1.., value_name = "PATH")]
    input: Vec<PathBuf>,
    /// Scene file (TOML). Default: the embedded prototype scene (`tofwave scene` prints it).
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    /// Capture format: auto detects it from the content.
    #[arg(long, default_value = "auto", value_name = "FORMAT", value_parser = parse_format)]
    format: Format,
    /// Average this many consecutive frames per report (overrides averaging.frames). 1: no averaging.
    #[arg(long, value_name = "N")]
    average: Option<u32>,
    /// Design false-alarm probability per report over the whole range gate (overrides detector.pfa), in (0, 0.5].
    #[arg(long, value_name = "P")]
    pfa: Option<f64>,
    /// Start (transmitted-pulse) channel name, e.g. CH1 (overrides channels.start; CH1, Ch1, C1 and 1 match).
    #[arg(long, value_name = "NAME")]
    start_channel: Option<String>,
    /// Stop (receiver) channel name, e.g. CH2 (overrides channels.stop).
    #[arg(long, value_name = "NAME")]
    stop_channel: Option<String>,
    /// Timing method (overrides timing.method): constant_fraction, leading_edge, peak_parabolic, peak_gaussian, ml.
    #[arg(long, value_name = "METHOD", value_parser = parse_timing)]
    timing: Option<TimingMethod>,
    /// Sensor id written into the reports.
    #[arg(long, default_value = "capture", value_name = "ID")]
    sensor: String,
}

#[derive(Args, Debug)]
struct ProcessArgs {
    #[command(flatten)]
    common: SceneInput,
    /// Calibration file from `tofwave calibrate`: its delay (seconds) is subtracted from every time of flight.
    #[arg(long, value_name = "FILE")]
    calibration: Option<PathBuf>,
    /// Where the JSON lines go; `-` is standard output.
    #[arg(long, short, default_value = "-", value_name = "FILE")]
    output: PathBuf,
    /// Threads for the one sensor's pipeline (threads). The stages are cut into this many
    /// consecutive segments, one thread each, cut where the stage times measured on one
    /// thread balance best: on frames 201-400, and again on frames 2001-2200, once start-up
    /// has passed (on 2 threads also a ring: three segments, the first and last on one
    /// thread, where one heavy stage in the middle would leave the chain unbalanced);
    /// every stage still sees the frames in order, so the reports are
    /// bit-identical to one thread's. The busiest thread sets the pace, so more threads
    /// than stages (the scene's, plus validate) add nothing. Default: the machine's cores
    /// for 1000 frames or more, else 1.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=64))]
    threads: Option<u32>,
}

#[derive(Args, Debug)]
struct CalibrateArgs {
    #[command(flatten)]
    common: SceneInput,
    /// True range of the calibration target, metres (from the timing point of the start pulse's
    /// optical reference to the target).
    #[arg(long, value_name = "R")]
    known_range_m: f64,
    /// Calibration file to write (TOML); pass it to `process --calibration`.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Also fit the leading-edge amplitude walk table (timing method leading_edge):
    /// give captures of the target at several amplitudes (returns within 10 % of
    /// each other in amplitude form one table node; at least 5 per node).
    #[arg(long)]
    walk: bool,
}

#[derive(Args, Debug)]
struct SimulateArgs {
    /// Scene with a [simulation] section (e.g. replay-data/scenes/weak-32m.toml).
    /// Without one: the embedded default, the source's prototype (Table 10.20's lab
    /// targets and the receiver's interference events; `tofwave scene` prints it).
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    /// Frames to simulate.
    #[arg(long, value_name = "N")]
    frames: u64,
    /// Random seed; the same seed gives the same frames, whatever the thread count.
    #[arg(long, default_value_t = 1, value_name = "S")]
    seed: u64,
    /// Output; the extension chooses the format: `.twr` tofwave's lossless recording
    /// (all channels), `.trc` a LeCroy sequence file (stop channel only), `.csv` one
    /// generic CSV file (a single frame: --frames 1). A path without an extension (or
    /// ending in `/`) is a directory, created if needed, of one generic CSV per frame
    /// (frame-00000000.csv, ...).
    #[arg(long, value_name = "PATH")]
    out: PathBuf,
    /// Ground truth per frame (true times of flight, amplitudes, samples holding signal,
    /// interference events: onset, peak time, peak volts). `.csv`: CSV, one row per
    /// frame, return and event (columns sequence,kind,index,t_s,t_peak_s,peak_v,range_m,
    /// tof_s,flags); any other name: one JSON line per frame. Times are seconds from the
    /// trigger. `range_m` is the target's geometric range (m); `tof_s` is the stop pulse's 50 %
    /// crossing minus the start pulse's (s) with the chain's system delay left in (the two
    /// paths' rise times and electrical delays: what `tofwave calibrate` measures), so
    /// `tof_s` exceeds 2·range_m/c by that delay (about 2.1 ns in the default scene).
    #[arg(long, value_name = "FILE")]
    truth: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct TemplateArgs {
    #[command(flatten)]
    common: SceneInput,
    /// Scene file to write: the input scene with the learned return_pulse (model = "table").
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Grid points per sample period of the learned shape. Bins no shot reached
    /// (a few dozen shots at random phases leave some) are interpolated from their
    /// neighbours, across at most half a sample; a single shot needs --oversample 1 or 2.
    #[arg(long, default_value_t = 8, value_name = "N")]
    oversample: usize,
    /// Only returns with at least this peak SNR (dB: the larger of the fitted amplitude's
    /// and the raw samples' peak over the noise sigma) and no flags other than
    /// shape_mismatch and non_gaussian_noise are used.
    #[arg(long, default_value_t = 20.0, value_name = "DB")]
    min_snr_db: f64,
    /// Learning passes; each times the shots with the shape the previous pass learned.
    #[arg(long, default_value_t = 2, value_name = "N")]
    passes: u32,
}

#[derive(Args, Debug)]
struct SceneArgs {
    /// Print the embedded default scene, commented (the default action).
    #[arg(long)]
    default: bool,
    /// Validate this scene file and print it as resolved (every default filled in).
    #[arg(long, value_name = "FILE", conflicts_with_all = ["default", "from_capture"])]
    check: Option<PathBuf>,
    /// Measure a starting scene from a capture file (or a directory of them) and print it (or
    /// write it to --out) as commented TOML: the sampling period (s) and record length; which
    /// channel is the start and which the stop (one channel: the stop channel, timed from the
    /// trigger); the noise mean and robust sigma (V, from samples away from every pulse); the
    /// start and return pulses' 10-90 % rise time and FWHM (s, median over frames of each
    /// frame's strongest pulse); a range gate (m) around the returns seen and a noise-gate
    /// guard (s) that keeps every pulse's tail out of the noise gates. Each value carries a
    /// comment saying what it was measured from. At most the first 1000 frames are measured.
    #[arg(long, value_name = "FILE", conflicts_with = "default")]
    from_capture: Option<PathBuf>,
    /// With --from-capture: write the scene to this file instead of standard output.
    #[arg(long, value_name = "SCENE.toml", requires = "from_capture")]
    out: Option<PathBuf>,
    /// With --from-capture: the capture format (auto detects it from the content).
    #[arg(long, default_value = "auto", value_name = "FORMAT", value_parser = parse_format, requires = "from_capture")]
    format: Format,
}

fn parse_format(s: &str) -> Result<Format, String> {
    s.parse::<Format>().map_err(|e| e.to_string())
}

fn parse_timing(s: &str) -> Result<TimingMethod, String> {
    TimingMethod::ALL
        .into_iter()
        .find(|m| m.name() == s)
    .ok_or_else(|| {
        format!("unknown timing method {s:?}: one of constant_fraction, leading_edge, peak_parabolic, peak_gaussian, ml")
    })
}

fn main() {
    tofwave::telemetry::init_tracing();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(a) => block_on(tofwave::service::cli::run_serve(a)),
        Command::Replay(a) => block_on(tofwave::service::cli::run_replay(a)),
        Command::Subscribe(a) => block_on(tofwave::service::cli::run_subscribe(a)),
        Command::Simulate(a) => simulate(a),
        Command::Process(a) => process(a),
        Command::Calibrate(a) => calibrate(a),
        Command::Scene(a) => scene(a),
        Command::Template(a) => template(a),
        Command::Bench(a) => bench(a),
        Command::Plot(a) => plot(a),
        Command::Ctl(a) => block_on(tofwave::service::cli::run_ctl(a)),
    };
    match result {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("error: {}", error_text(&e));
            std::process::exit(2);
        }
    }
}

/// An error and its causes on one line, each cause said once: a cause whose
/// text the message already holds (a wrapper that prints its source) is not
/// repeated.
fn error_text(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let msg = cause.to_string();
        if text.contains(&msg) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&msg);
    }
    text
}

fn bench(a: BenchArgs) -> Result<i32> {
    use tofwave::bench::{self, BenchConfig, RunOptions};
    if a.soak {
        return soak(&a);
    }
    if a.dashboard_only {
        return dashboard_cost(&a);
    }
    if let Some(url) = &a.cluster {
        return cluster_cost(&a, url);
    }
    if let Some(n) = a.threads {
        return threads_cost(&a, n as usize);
    }
    let scene = match &a.scene {
        Some(p) => Scene::load(p)?,
        None => bench::bench_scene(),
    };
    let mut config = if a.long { BenchConfig::long_run() } else { BenchConfig::default_run() };
    if let Some(s) = a.seed {
        config.seed = s;
    }
    // bench/peer lives in the repository: the working directory when run with
    // `cargo run` from the checkout, else the checkout this binary was built from.
    let cwd = std::env::current_dir().context("no working directory")?;
    let repo_root = if cwd.join("bench/peer/peer.py").exists() {
        cwd
    } else {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
    };
    let args: Vec<String> = std::env::args().skip(1).collect();
    let opts = RunOptions {
        config,
        peer: !a.no_peer || a.peer,
        service: !a.no_service,
        bandwidth: !a.no_bandwidth,
        learn_template: !a.no_learn,
        repo_root,
        command: format!("tofwave {}", args.join(" ")),
    };
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{msg:28} {bar:40} {pos}/{len} frames {per_sec} eta {eta}")
            .expect("static template"),
    );
    let plain = tofwave::service::cli::plain_progress(&bar, "bench", std::time::Duration::from_secs(10));
    let res = bench::run(&scene, &opts, &a.out, &bar);
    drop(plain);
    let res = res?;
    if let Some(bench::PeerOutcome::Failed(why)) = &res.peer {
        eprintln!("tofwave bench: the numpy/scipy peer did not run: {why}");
    }
    eprintln!(
        "tofwave bench: {} cells, {} ROC points -> {}",
        res.cells.len(),
        res.roc.len(),
        a.out.join("report.md").display()
    );
    Ok(0)
}

fn dashboard_cost(a: &BenchArgs) -> Result<i32> {
    use tofwave::bench::{self, BenchConfig};
    if a.dashboard_frames < tofwave::bench::DASHBOARD_SENSORS || a.dashboard_trials == 0 {
        bail!(
            "--dashboard-frames {} / --dashboard-trials {}: give at least {} frames and 1 trial",
            a.dashboard_frames,
            a.dashboard_trials,
            tofwave::bench::DASHBOARD_SENSORS
        );
    }
    eprintln!("tofwave bench: dashboard cost, {} trials per arm ...", a.dashboard_trials);
    let reference = bench::reference_scene();
    let snr_db = BenchConfig::default_run().reference_snr_db;
    let cost = bench::measure_dashboard_cost(&reference, snr_db, a.dashboard_frames, a.dashboard_trials)?;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let md = format!(
        "# Dashboard cost to ingest\n\nCommand: `tofwave {}`; {} CPUs.\n\n{}\n{}\n",
        args.join(" "),
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        cost.markdown(),
        cost.check_row()
    );
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    std::fs::write(a.out.join("dashboard.md"), &md).with_context(|| format!("writing {}", a.out.join("dashboard.md").display()))?;
    println!("{md}");
    Ok(0)
}

fn cluster_cost(a: &BenchArgs, url: &str) -> Result<i32> {
    use tofwave::bench::{self, BenchConfig};
    if a.cluster_frames < 2 || a.cluster_trials == 0 {
        bail!("--cluster-frames {} / --cluster-trials {}: give at least 2 frames and 1 trial", a.cluster_frames, a.cluster_trials);
    }
    eprintln!("tofwave bench: cluster path against single node, {} trials per arm ...", a.cluster_trials);
    let reference = bench::reference_scene();
    let snr_db = BenchConfig::default_run().reference_snr_db;
    let cost = bench::measure_cluster_cost(&reference, snr_db, a.cluster_frames, a.cluster_trials, url)?;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let md = format!(
        "# Cluster path cost\n\nCommand: `tofwave {}`; {} CPUs.\n\n{}",
        args.join(" "),
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        cost.markdown()
    );
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    std::fs::write(a.out.join("cluster.md"), &md).with_context(|| format!("writing {}", a.out.join("cluster.md").display()))?;
    println!("{md}");
    Ok(0)
}

fn threads_cost(a: &BenchArgs, threads: usize) -> Result<i32> {
    use tofwave::physics::Simulator;
    if a.threads_frames < 2 || a.threads_trials == 0 {
        bail!("--threads-frames {} / --threads-trials {}: give at least 2 frames and 1 trial", a.threads_frames, a.threads_trials);
    }
    let scene = match &a.scene {
        Some(p) => Scene::load(p)?,
        None => Scene::default_scene(),
    };
    eprintln!("tofwave bench: one sensor on {threads} threads against one, {} frames, {} trials per arm ...", a.threads_frames, a.threads_trials);
    let sim = Simulator::new(&scene)?;
    let seed = a.seed.unwrap_or(1);
    let frames: Vec<_> = (0..a.threads_frames as u64).map(|i| sim.frame(seed, i).0).collect();
    let cost = tofwave::bench::measure_threads_cost(&scene, &frames, threads, a.threads_trials, |m| eprintln!("tofwave bench --threads: {m}"))?;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let md = format!(
        "# One sensor on {threads} threads\n\nCommand: `tofwave {}`; {} CPUs; scene \"{}\".\n\n{}",
        args.join(" "),
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        scene.name,
        cost.markdown()
    );
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    std::fs::write(a.out.join("threads.md"), &md).with_context(|| format!("writing {}", a.out.join("threads.md").display()))?;
    println!("{md}");
    Ok(0)
}

fn soak(a: &BenchArgs) -> Result<i32> {
    use tofwave::bench::{run_soak, SoakConfig};
    if !(a.soak_warmup_s.is_finite() && a.soak_warmup_s >= 0.0) {
        bail!("--soak-warmup-s: a number of seconds >= 0");
    }
    if !(a.soak_kill_at.is_finite() && a.soak_kill_at > 0.0) {
        bail!("--soak-kill-at: a fraction > 0");
    }
    let exe = std::env::current_exe().context("cannot find this executable to start the server")?;
    let mut cfg = SoakConfig::new(exe);
    cfg.frames = a.soak_frames;
    cfg.sensors = a.soak_sensors;
    cfg.bad_every = a.soak_bad_every;
    cfg.kill_at = a.soak_kill_at;
    cfg.rss_warmup = std::time::Duration::from_secs_f64(a.soak_warmup_s);
    cfg.keep_files = a.soak_keep;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let report = run_soak(&cfg, &format!("tofwave {}", args.join(" ")))?;
    report.write(&a.out)?;
    println!("{}", report.markdown());
    eprintln!("tofwave bench --soak: -> {}", a.out.join("soak.md").display());
    let ok = report.check_pushed_eq_acked_plus_rejected
        && report.check_reported_eq_acked_with_lag
        && report.check_acked_le_recorded
        && report.check_rss_flat != Some(false);
    Ok(if ok { 0 } else { 1 })
}

fn block_on(f: impl std::future::Future<Output = Result<()>>) -> Result<i32> {
    let rt = tokio::runtime::Runtime::new().context("cannot start the async runtime")?;
    rt.block_on(f)?;
    Ok(0)
}

fn simulate(a: SimulateArgs) -> Result<i32> {
    use tofwave::physics::Simulator;
    let scene = match &a.scene {
        Some(p) => Scene::load(p)?,
        None => Scene::default_scene(),
    };
    let sim = Simulator::new(&scene)?;
    let bar = indicatif::ProgressBar::new(a.frames).with_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta}")
            .expect("static template"),
    );
    // The extension chooses the format; no extension (or a trailing `/`): a directory of CSVs.
    let dir_out = a.out.as_os_str().to_string_lossy().ends_with(['/', std::path::MAIN_SEPARATOR])
        || a.out.extension().is_none();
    let ext = if dir_out {
        "dir".to_string()
    } else {
        a.out.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase()
    };
    match ext.as_str() {
        "twr" | "trc" | "dir" => {}
        "csv" if a.frames == 1 => {}
        "csv" => bail!(
            "--out {}: a CSV file holds one frame and {} were asked for: use --frames 1, a .twr or .trc file, \
             or a directory (a path without an extension) for one CSV per frame",
            a.out.display(),
            a.frames
        ),
        _ => bail!(
            "--out {}: the extension must be .twr, .trc or .csv (or no extension: a directory of CSVs)",
            a.out.display()
        ),
    }
    let truth_csv = a
        .truth
        .as_ref()
        .and_then(|p| p.extension())
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
    // Parent directories of the outputs are created, as is the CSV directory.
    for p in a.truth.iter().chain(std::iter::once(&a.out)) {
        if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        }
    }
    let mut truth_out = match &a.truth {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("cannot create {}", p.display()))?,
        )),
        None => None,
    };
    if let Some(t) = truth_out.as_mut().filter(|_| truth_csv) {
        writeln!(t, "{}", tofwave::physics::simulator::TRUTH_CSV_HEADER)?;
    }
    let mut frames = Vec::new();
    let mut writer = if ext == "twr" {
        let f = std::fs::File::create(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
        Some(capture::RecordingWriter::new(std::io::BufWriter::new(f))?)
    } else {
        None
    };
    if ext == "dir" {
        std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    }
    for i in 0..a.frames {
        let (frame, truth) = sim.frame(a.seed, i);
        if let Some(t) = &mut truth_out {
            if truth_csv {
                write!(t, "{}", truth.csv_rows())?;
            } else {
                writeln!(t, "{}", serde_json::to_string(&truth)?)?;
            }
        }
        match ext.as_str() {
            "twr" => writer.as_mut().expect("opened").write_frame(&frame)?,
            "dir" => capture::write_csv(&a.out.join(format!("frame-{i:08}.csv")), &frame, Format::GenericCsv)?,
            "csv" => capture::write_csv(&a.out, &frame, Format::GenericCsv)?,
            _ => frames.push(frame),
        }
        bar.inc(1);
    }
    if let Some(w) = writer {
        w.finish()?.flush()?;
    }
    if ext == "trc" {
        capture::write_trc(&a.out, &frames, &scene.channels.stop)?;
    }
    if let Some(mut t) = truth_out {
        t.flush()?;
    }
    bar.finish_and_clear();
    eprintln!("tofwave simulate: {} frames -> {}", a.frames, a.out.display());
    Ok(0)
}

/// The scene with command-line overrides applied and validated again.
fn load_scene(c: &SceneInput) -> Result<Scene> {
    let (mut scene, origin) = match &c.scene {
        Some(p) => (Scene::load(p)?, p.display().to_string()),
        None => (Scene::default_scene(), "embedded default".to_string()),
    };
    if let Some(n) = c.average {
        scene.averaging.frames = n;
    }
    if let Some(p) = c.pfa {
        scene.detector.pfa = p;
    }
    if let Some(s) = &c.start_channel {
        scene.channels.start = s.clone();
    }
    if let Some(s) = &c.stop_channel {
        scene.channels.stop = s.clone();
    }
    if let Some(m) = c.timing {
        scene.timing.method = m;
    }
    scene
        .validate(&format!("{origin} with command-line overrides"))
        .context("invalid option")?;
    Ok(scene)
}

/// Notes the files of input directories that are not read.
fn note_skipped(source: &capture::FrameSource) {
    for s in source.skipped() {
        eprintln!("note: {s}");
    }
}

/// A channel named by --stop-channel or --start-channel must be in the
/// capture: the flag is blamed, with the channels the frame has. (Without the
/// flag, a single-channel capture is the stop channel, timed from the trigger.)
fn check_channel_flags(c: &SceneInput, frame: &tofwave::frame::Frame) -> Result<()> {
    for (flag, name) in [("--stop-channel", &c.stop_channel), ("--start-channel", &c.start_channel)] {
        if let Some(name) = name.as_ref().filter(|n| frame.channel(n).is_none()) {
            bail!(
                "{flag} {name}: the capture has no such channel (frame {} of {} has {}); \
                 give one of those, or leave {flag} out to use the scene's channels",
                frame.sequence,
                c.input.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "),
                frame.channel_names().join(", ")
            );
        }
    }
    Ok(())
}

/// Reads every frame of the inputs (skipped directory entries noted, channel
/// flags checked against each frame).
fn read_inputs(c: &SceneInput) -> Result<Vec<tofwave::frame::Frame>> {
    let opts = ReadOptions { format: c.format, sensor_id: c.sensor.clone() };
    let source = capture::frames(&c.input, &opts)?;
    note_skipped(&source);
    let mut frames = Vec::new();
    for f in source {
        let f = f?;
        check_channel_flags(c, &f)?;
        frames.push(f);
    }
    Ok(frames)
}

/// Runs the pipeline over the inputs on `threads` threads (None: the
/// machine's cores for 1000 frames or more, else 1), handing `each` every
/// report in order as its frame finishes; returns the number of refused
/// frames. `progress`: a progress bar (on stderr) for long runs.
fn run(scene: &Scene, c: &SceneInput, threads: Option<u32>, progress: bool, mut each: impl FnMut(&Report)) -> Result<usize> {
    let frames = read_inputs(c)?;
    if frames.is_empty() {
        bail!("no frames in {}", c.input.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "));
    }
    let bar = indicatif::ProgressBar::new(frames.len() as u64).with_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta}")
            .expect("static template"),
    );
    let progress = progress && frames.len() >= 2000;
    if !progress {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let plain = progress
        .then(|| tofwave::service::cli::plain_progress(&bar, "process", std::time::Duration::from_secs(10)));
    let threads = threads.map_or_else(
        || if frames.len() >= 1000 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { 1 },
        |n| n as usize,
    );
    let mut refused = 0;
    tofwave::pipeline::threaded::run(scene, &c.sensor, threads, frames, |o| {
        o.reports.iter().for_each(&mut each);
        if let Err(e) = &o.result {
            refused += 1;
            bar.suspend(|| eprintln!("refused: {e}"));
        } else if let Some(m) = &o.panic {
            refused += 1;
            let rebuilt = if threads > 1 { "the stage was rebuilt" } else { "the pipeline was rebuilt" };
            bar.suspend(|| eprintln!("refused: the pipeline panicked on this frame ({m}); {rebuilt}"));
        }
        bar.inc(1);
    });
    drop(plain);
    bar.finish_and_clear();
    Ok(refused)
}

fn process(a: ProcessArgs) -> Result<i32> {
    let mut scene = load_scene(&a.common)?;
    if let Some(p) = &a.calibration {
        CalibrationFile::load(p)?.apply(&mut scene, &p.display().to_string())?;
    }
    // The output is created when the first report is ready (after the
    // inputs are read, so a bad input leaves no file behind), and each
    // report's line is written as its frame finishes; after a failed create
    // or write no more lines are tried (the frames still run), and the error
    // is the command's.
    let open = || -> Result<Box<dyn Write>> {
        Ok(if a.output.as_os_str() == "-" {
            Box::new(std::io::BufWriter::new(std::io::stdout().lock()))
        } else {
            let f = std::fs::File::create(&a.output).with_context(|| format!("cannot create {}", a.output.display()))?;
            Box::new(std::io::BufWriter::new(f))
        })
    };
    let cannot_write = |e: std::io::Error| anyhow::Error::new(e).context(format!("cannot write the reports to {}", a.output.display()));
    let (mut reports, mut returns) = (0usize, 0usize);
    let (mut out, mut failed): (Option<Box<dyn Write>>, Option<anyhow::Error>) = (None, None);
    // Lines on the terminal the bar would draw on are progress enough.
    let progress = !(a.output.as_os_str() == "-" && std::io::IsTerminal::is_terminal(&std::io::stdout()));
    let refused = run(&scene, &a.common, a.threads, progress, |r| {
        reports += 1;
        returns += r.returns.len();
        if failed.is_some() {
            return;
        }
        let w = match &mut out {
            Some(w) => w,
            None => match open() {
                Ok(w) => out.insert(w),
                Err(e) => return failed = Some(e),
            },
        };
        if let Err(e) = writeln!(w, "{}", report_json(r)) {
            failed = Some(cannot_write(e));
        }
    })?;
    if let Some(e) = failed {
        return Err(e);
    }
    let mut out = match out {
        Some(w) => w,
        None => open()?,
    };
    out.flush().map_err(cannot_write)?;
    eprintln!("tofwave process: {reports} reports, {returns} returns, {refused} frames refused");
    Ok(if refused > 0 { 1 } else { 0 })
}

fn calibrate(a: CalibrateArgs) -> Result<i32> {
    let r = a.known_range_m;
    if !(r.is_finite() && r > 0.0) {
        bail!("--known-range-m {r}: must be a positive, finite range in metres");
    }
    let mut scene = load_scene(&a.common)?;
    if a.walk && scene.timing.method != TimingMethod::LeadingEdge {
        bail!(
            "--walk: the walk table belongs to leading-edge timing; the scene's timing.method is {} (pass --timing leading_edge)",
            scene.timing.method.name()
        );
    }
    scene.calibration = tofwave::scene::CalibrationConfig::default();
    let mut reports = Vec::new();
    let refused = run(&scene, &a.common, None, true, |r| reports.push(r.clone()))?;
    let no_start = reports
        .iter()
        .filter(|r| r.flags.iter().any(|f| f.name() == "no_start_channel"))
        .count();
    if no_start > 0 {
        eprintln!(
            "tofwave calibrate: warning: {no_start} of {} reports have no start channel (the capture lacks {:?}): \
             their time reference is the trigger plus channels.reference_offset_s, so the delay measured \
             includes the trigger's latency and holds only for captures triggered the same way \
             (give --start-channel NAME if the start pulse is on another channel)",
            reports.len(),
            scene.channels.start
        );
    }
    let Calibration { mut file, walk } = tofwave::calibrate::calibrate(&reports, r, &scene, a.walk)?;
    if let Some(fit) = &walk {
        eprintln!("tofwave calibrate: walk table, {} nodes (amplitude V -> extra delay ns):", fit.amplitude_v.len());
        for ((amp, d), c) in fit.amplitude_v.iter().zip(&fit.walk_delay_s).zip(&fit.counts) {
            eprintln!("  {amp:.4} V -> {:+.4} ns ({c} returns)", d * 1e9);
        }
    }
    file.measurement.inputs = a.common.input.iter().map(|p| p.display().to_string()).collect();
    let text = format!(
        "# tofwave calibration: the fixed start-to-stop delay of the system, seconds.\n\
         # Apply with `tofwave process --calibration {}`.\n{}{}",
        a.out.display(),
        if no_start > 0 {
            "# Measured without a start channel: the delay is from the trigger, not from the start pulse.\n"
        } else {
            ""
        },
        tofwave::scene::human_floats(&toml::to_string(&file)?)
    );
    std::fs::write(&a.out, text).with_context(|| format!("cannot write {}", a.out.display()))?;
    let m = &file.measurement;
    eprintln!(
        "tofwave calibrate: delay {} ± {} (standard error; {} returns, std {}, {} excluded) -> {}",
        tofwave::scene::si(file.calibration.delay_s, "s"),
        tofwave::scene::si(m.delay_sem_s, "s"),
        m.returns,
        tofwave::scene::si(m.delay_std_s, "s"),
        m.excluded,
        a.out.display()
    );
    Ok(if refused > 0 { 1 } else { 0 })
}

fn template(a: TemplateArgs) -> Result<i32> {
    use tofwave::pipeline::learn::{learn_shapes, LearnOptions};
    if !(1..=64).contains(&a.oversample) {
        bail!("--oversample {}: allowed 1..=64 grid points per sample", a.oversample);
    }
    let scene = load_scene(&a.common)?;
    let frames = read_inputs(&a.common)?;
    let learn = LearnOptions { oversample: a.oversample, min_snr_db: a.min_snr_db, passes: a.passes };
    let scene = learn_shapes(
        &scene,
        &a.common.sensor,
        &frames,
        &learn,
        |p| {
            if p.start_shots > 0 {
                eprintln!(
                    "tofwave template: pass {}: start pulse from {} shots, FWHM {:.3} ns, {} grid bins interpolated",
                    p.pass,
                    p.start_shots,
                    p.start_fwhm_s * 1e9,
                    p.start_interpolated_bins
                );
            }
            eprintln!(
                "tofwave template: pass {}: {} shots, FWHM {:.3} ns, half-rise {:.3} ns before the peak, \
                 {} of {} grid bins interpolated (no shot, or too few, reached them){}",
                p.pass,
                p.shots,
                p.fwhm_s * 1e9,
                p.half_rise_s * 1e9,
                p.interpolated_bins,
                p.bins,
                if p.widenings > 0 {
                    format!("; the grid was widened {} time(s) to hold the whole pulse", p.widenings)
                } else {
                    String::new()
                }
            );
        },
        |e| eprintln!("refused: {e}"),
    )?;
    scene.validate("learned scene")?;
    let text = format!(
        "# tofwave scene with the return (and start) pulse shapes learned by `tofwave template` from {}\n{}",
        a.common.input.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "),
        scene.to_toml()
    );
    std::fs::write(&a.out, text).with_context(|| format!("cannot write {}", a.out.display()))?;
    eprintln!("tofwave template: wrote {}", a.out.display());
    Ok(0)
}

fn scene(a: SceneArgs) -> Result<i32> {
    if let Some(p) = &a.from_capture {
        return scene_from_capture(p, a.out.as_deref(), a.format);
    }
    match a.check {
        Some(p) => {
            let s = Scene::load(&p)?;
            print!("{}", s.to_toml());
            eprintln!("{}: valid", p.display());
        }
        None => print!("{DEFAULT_SCENE_TOML}"),
    }
    Ok(0)
}

fn scene_from_capture(input: &std::path::Path, out: Option<&std::path::Path>, format: Format) -> Result<i32> {
    let opts = ReadOptions { format, sensor_id: "capture".to_string() };
    let m = capture::measure::measure_paths(&[input.to_path_buf()], &opts)?;
    // Checked here too: what is written must load.
    m.scene()?;
    let text = m.scene_toml();
    match out {
        Some(path) => {
            std::fs::write(path, &text).with_context(|| format!("cannot write {}", path.display()))?;
        }
        None => print!("{text}"),
    }
    let s = &m.stop;
    eprintln!(
        "tofwave scene: {} frames of {}, {:.3} ns sampling; {}",
        m.frames_measured,
        m.origin,
        m.sample_interval_s * 1e9,
        m.channel_notes.join("; ")
    );
    eprintln!(
        "tofwave scene: return pulse on {}: {:.3} V, rise {:.2} ns, FWHM {:.2} ns (median of {}); noise mean {:.2} mV, sigma {:.2} mV (robust)",
        s.name,
        s.amplitude_v,
        s.rise_time_s * 1e9,
        s.fwhm_s * 1e9,
        s.pulses,
        s.noise_mean_v * 1e3,
        s.noise_sigma_v * 1e3
    );
    if let Some(st) = &m.start {
        eprintln!(
            "tofwave scene: start pulse on {}: {:.3} V, rise {:.2} ns, FWHM {:.2} ns",
            st.name,
            st.amplitude_v,
            st.rise_time_s * 1e9,
            st.fwhm_s * 1e9
        );
    }
    eprintln!(
        "tofwave scene: range gate {:.3} to {:.3} m, noise-gate guard {:.2} ns, {}-{} noise samples per frame{}",
        m.range_gate_m.0,
        m.range_gate_m.1,
        m.guard_s * 1e9,
        m.gates.min_samples,
        m.gates.max_samples,
        match out {
            Some(p) => format!(" -> {}", p.display()),
            None => String::new(),
        }
    );
    if s.undershoot_fraction < -0.05 {
        eprintln!(
            "tofwave scene: the return pulse undershoots to {:.0} % of its peak: learn its shape with `tofwave template --scene SCENE --input {}`",
            -100.0 * s.undershoot_fraction,
            input.display()
        );
    }
    Ok(0)
}

fn plot(a: PlotArgs) -> Result<i32> {
    use tofwave::plot::{self, PlotFormat, PlotOptions};
    // Checked before any work: a wrong extension or size fails at once.
    let format = PlotFormat::from_path(&a.out)?;
    let mut scene = load_scene(&a.common)?;
    if let Some(p) = &a.calibration {
        CalibrationFile::load(p)?.apply(&mut scene, &p.display().to_string())?;
    }
    let opts = ReadOptions { format: a.common.format, sensor_id: a.common.sensor.clone() };
    let source = capture::frames(&a.common.input, &opts)?;
    note_skipped(&source);
    let mut checked = false;
    let frames = source.map(|f| {
        let f = f?;
        if !checked {
            check_channel_flags(&a.common, &f)?;
            checked = true;
        }
        Ok::<_, anyhow::Error>(f)
    });
    let processed = plot::process(&scene, &a.common.sensor, frames, &a.frame)?;
    for e in &processed.refused {
        eprintln!("refused: {e}");
    }
    plot::check_selection(&processed, &a.frame)?;
    let rows = processed.views.len() as u32;
    let title = a.common.input.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ");
    let options = PlotOptions {
        width_px: a.width,
        height_px: a.height.unwrap_or(if rows == 1 { 700 } else { 420 * rows }).min(*plot::SIZE_PX.end()),
        title,
    };
    plot::render(&processed.views, &a.out, format, &options)?;
    let returns: usize = processed.views.iter().map(|v| v.report.returns.len()).sum();
    eprintln!(
        "tofwave plot: {} frame(s), {} returns marked -> {} ({}x{} px)",
        rows,
        returns,
        a.out.display(),
        options.width_px,
        options.height_px
    );
    Ok(0)
}
