//! `tofwave bench --soak`: a long run against a real `tofwave serve` child
//! process, with bad frames, misbehaving subscribers and one `kill -9`, that
//! ends in an exact reconciliation of every frame pushed.
//!
//! The run starts the binary itself (`serve --listen 127.0.0.1:0 --state-dir
//! --record`, in a scratch directory), pushes synthetic frames for every
//! sensor on its own Push stream (one bad frame in `bad_every`, of three kinds
//! the edge refuses with `INVALID_ARGUMENT`), and reads reports with:
//! - one *reliable* subscriber to every sensor, which never stops reading;
//! - one *chaotic* subscriber per sensor, which reads, stalls (stops reading
//!   while the server runs on), disconnects and reconnects with
//!   `resume_from_sequence` after the last report it saw.
//!
//! Once `kill_at` of the frames have a verdict, the server is killed with
//! SIGKILL and restarted on the same state and recording directories; frames
//! handed to a stream that had no ack when it broke are counted as
//! *unacknowledged at kill* and pushed again. At the end every
//! (sensor, sequence) is classified from the client's acks, the reports the
//! subscribers saw, the restarted server's `GetStatus` counters and the
//! recordings on disk (every file, read with [`RecordingReader`]).
//!
//! [`RecordingReader`]: crate::capture::RecordingReader

use std::collections::{HashSet, VecDeque};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use serde::Serialize;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;

use super::BenchError;
use crate::capture::RecordingReader;
use crate::frame::{Channel, ChannelRole, Frame, Samples};
use crate::service::client::{self, ClientOptions};
use crate::wire::frame_to_proto;
use crate::wire::proto::{self, report_event::Event};

/// Locks `m`, recovering from poisoning (a panicked task must not hide the tallies).
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// What the soak run does, and how big it is.
#[derive(Debug, Clone)]
pub struct SoakConfig {
    /// The `tofwave` binary to start as the server (`std::env::current_exe()`).
    pub exe: PathBuf,
    /// Frames pushed in all, over all sensors (each gets an equal share).
    pub frames: u64,
    /// Sensors pushing concurrently, one Push stream each.
    pub sensors: usize,
    /// One frame in this many is bad (refused at the edge); 0: none.
    pub bad_every: u64,
    /// Frames per `FrameBatch`.
    pub batch_frames: usize,
    /// Samples per channel (two channels, i16, 1 ns).
    pub samples: usize,
    /// Fraction of the frames with a verdict at which the server is killed (SIGKILL); >= 1: never.
    pub kill_at: f64,
    /// Chaotic subscribers read for this long, then stall ...
    pub read_phase: Duration,
    /// ... stop reading for this long, then disconnect and reconnect (resume).
    pub stall_phase: Duration,
    /// RSS sampling period.
    pub rss_period: Duration,
    /// RSS samples taken this soon after a (re)start are warm-up, not judged.
    pub rss_warmup: Duration,
    /// Scratch directory (state, recordings, server log); default: a new one under the system temp dir.
    pub work_dir: Option<PathBuf>,
    /// Keep the scratch directory (recordings) afterwards.
    pub keep_files: bool,
    /// Progress lines on stderr every few seconds.
    pub progress: bool,
}

impl SoakConfig {
    /// The defaults of `tofwave bench --soak` for `exe`: 10^7 frames over 8
    /// sensors, 1 bad frame in 1000, killed at half way.
    pub fn new(exe: PathBuf) -> SoakConfig {
        SoakConfig {
            exe,
            frames: 10_000_000,
            sensors: 8,
            bad_every: 1000,
            batch_frames: 32,
            samples: 256,
            kill_at: 0.5,
            read_phase: Duration::from_secs(3),
            stall_phase: Duration::from_secs(2),
            rss_period: Duration::from_secs(1),
            rss_warmup: Duration::from_secs(10),
            work_dir: None,
            keep_files: false,
            progress: true,
        }
    }
}

/// Per-frame state bits.
type Bits = u16;
const ACKED: Bits = 1;
const REJECTED: Bits = 2;
const UNACKED_AT_KILL: Bits = 4;
const SEEN_RELIABLE: Bits = 8;
const SEEN_CHAOTIC: Bits = 16;
const RECORDED: Bits = 32;
/// The verdict came from the first server (before the kill).
const VERDICT_BEFORE_KILL: Bits = 64;
/// A subscriber saw its report from the first server (before the kill).
const SEEN_BEFORE_KILL: Bits = 128;

/// Kinds of bad frame, in rotation.
const BAD_KINDS: [&str; 3] = [
    "NaN in f32 samples",
    "sample_interval_s = 0",
    "i16 payload of odd byte length",
];

/// Whether frame `seq` of a sensor is bad, and which kind.
fn bad_kind(seq: u64, bad_every: u64) -> Option<usize> {
    if bad_every == 0 || seq % bad_every != bad_every / 2 {
        return None;
    }
    Some(((seq / bad_every) % BAD_KINDS.len() as u64) as usize)
}

fn sensor_name(k: usize) -> String {
    format!("soak-{k:03}")
}

fn sensor_index(name: &str) -> Option<usize> {
    name.strip_prefix("soak-")?.parse().ok()
}

/// Frames of one sensor: its share of the total.
fn share(total: u64, sensors: usize, k: usize) -> u64 {
    let n = sensors as u64;
    total / n + u64::from((k as u64) < total % n)
}

/// Pre-encoded frames: a few noise realisations and the bad kinds.
struct Templates {
    good: Vec<proto::Frame>,
    bad: Vec<proto::Frame>,
}

impl Templates {
    fn new(samples: usize) -> Templates {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x50a6);
        let noise = Normal::new(0.0, 0.01).expect("valid sigma");
        let vpc = 1.0 / 4096.0;
        let dt = 1e-9;
        let t0 = -40e-9;
        let mut frame = |f32_nan: bool| {
            let mut ch = |at: f64, fwhm: f64, a: f64| -> Vec<f64> {
                (0..samples)
                    .map(|i| {
                        let t = t0 + i as f64 * dt;
                        let s = fwhm / 2.354_820_045;
                        a * (-0.5 * ((t - at) / s).powi(2)).exp() + noise.sample(&mut rng)
                    })
                    .collect()
            };
            let start = ch(0.0, 8e-9, 0.4);
            let stop = ch(2.0 * 10.0 / 299_792_458.0, 26e-9, 0.2);
            let codes = |v: Vec<f64>| {
                Samples::I16(
                    v.iter()
                        .map(|x| (x / vpc).round().clamp(-2048.0, 2047.0) as i16)
                        .collect(),
                )
            };
            let stop_samples = if f32_nan {
                let mut v: Vec<f32> = stop.iter().map(|x| (x / vpc) as f32).collect();
                v[samples / 2] = f32::NAN;
                Samples::F32(v)
            } else {
                codes(stop)
            };
            let chan = |name: &str, s| Channel {
                name: name.into(),
                role: ChannelRole::Unspecified,
                samples: s,
                volts_per_code: vpc,
                offset_v: 0.0,
            };
            frame_to_proto(&Frame {
                sensor_id: String::new(),
                sequence: 0,
                trigger_time_s: 0.0,
                sample_interval_s: dt,
                first_sample_offset_s: t0,
                channels: vec![chan("CH1", codes(start)), chan("CH2", stop_samples)],
                laser_off: false,
            })
        };
        let good: Vec<proto::Frame> = (0..8).map(|_| frame(false)).collect();
        let nan = frame(true);
        let mut zero_dt = good[0].clone();
        zero_dt.sample_interval_s = 0.0;
        let mut odd = good[1].clone();
        let b = &odd.channels[1].samples;
        odd.channels[1].samples = Bytes::copy_from_slice(&b[..b.len() - 1]);
        Templates {
            good,
            bad: vec![nan, zero_dt, odd],
        }
    }

    fn frame(&self, sensor: &str, seq: u64, bad_every: u64) -> proto::Frame {
        let mut f = match bad_kind(seq, bad_every) {
            Some(kind) => self.bad[kind].clone(),
            None => self.good[(seq % self.good.len() as u64) as usize].clone(),
        };
        f.sensor_id = sensor.to_string();
        f.sequence = seq;
        f.trigger_time_s = seq as f64 * 1e-4;
        f
    }
}

/// Where clients should connect: URL and the server's life (0 before the kill).
type Target = Option<(String, u8)>;

/// Everything the tasks share.
struct Shared {
    cfg: SoakConfig,
    templates: Templates,
    /// Per sensor: one byte of state bits per sequence number.
    flags: Vec<Mutex<Vec<Bits>>>,
    /// Frames with a verdict (acked or rejected).
    verdicts: AtomicU64,
    /// Frames handed to Push streams, re-pushes included.
    handed: AtomicU64,
    /// Frames with two verdicts (must stay 0).
    double_verdicts: AtomicU64,
    /// Acks whose counts did not match the batch they answer.
    ack_mismatches: AtomicU64,
    /// Push streams that failed while the server was not being killed.
    unexpected_stream_failures: AtomicU64,
    /// Push stream failures (all causes).
    stream_failures: AtomicU64,
    /// Reports the reliable subscriber got twice (re-pushed frames processed twice).
    duplicate_reports: AtomicU64,
    /// Reports of sensors or sequence numbers this run never pushed.
    foreign_reports: AtomicU64,
    /// Reports the reliable subscriber received, per server life.
    reliable_reports_by_life: [AtomicU64; 2],
    /// Lag markers' skipped counts, reliable subscriber, per server life.
    reliable_lagged_by_life: [AtomicU64; 2],
    chaotic: ChaoticCounters,
    /// Set when the pushers are done: chaotic subscribers stop.
    stop: AtomicBool,
    /// Pid of the running server (0: none), for the RSS sampler.
    server_pid: AtomicU32,
    /// Server life the RSS sampler attributes samples to.
    life: AtomicU32,
    /// A kill is under way: stream failures are expected.
    killing: AtomicBool,
}

#[derive(Default)]
struct ChaoticCounters {
    reports: AtomicU64,
    stalls: AtomicU64,
    reconnects: AtomicU64,
    lagged_skipped: AtomicU64,
    lag_markers: AtomicU64,
    /// Sequence numbers missed across a disconnect (beyond the history).
    missed_across_reconnect: AtomicU64,
}

impl Shared {
    fn mark(&self, k: usize, seq: u64, bit: Bits) -> Option<Bits> {
        let mut f = lock(&self.flags[k]);
        let slot = f.get_mut(seq as usize)?;
        let old = *slot;
        *slot |= bit;
        Some(old)
    }
}

/// RSS statistics of one server life after warm-up.
#[derive(Debug, Clone, Serialize)]
pub struct RssLife {
    /// 0: before the kill, 1: after the restart.
    pub life: u32,
    /// Samples in all.
    pub samples: usize,
    /// Samples after warm-up.
    pub judged: usize,
    /// Minimum after warm-up, KiB.
    pub min_kib: u64,
    /// Median after warm-up, KiB.
    pub median_kib: u64,
    /// Maximum after warm-up, KiB.
    pub max_kib: u64,
    /// Every judged sample lies within ±10 % of the median (None: fewer than 3 judged samples).
    pub flat: Option<bool>,
}

/// The chaotic subscribers' tallies.
#[derive(Debug, Clone, Serialize)]
pub struct ChaoticSummary {
    /// Reports received.
    pub reports: u64,
    /// Stalls (stopped reading for `stall_phase`).
    pub stalls: u64,
    /// Disconnects followed by a reconnect with `resume_from_sequence`.
    pub reconnects: u64,
    /// Lag markers received.
    pub lag_markers: u64,
    /// Reports the server said were skipped (lag markers).
    pub lagged_skipped: u64,
    /// Sequence numbers missed across a disconnect (older than the history).
    pub missed_across_reconnect: u64,
}

/// The outcome of a soak run. Frame counts are distinct (sensor, sequence) pairs.
#[derive(Debug, Clone, Serialize)]
pub struct SoakReport {
    /// The command line.
    pub command: String,
    /// Frames in the run (distinct sensor, sequence).
    pub frames: u64,
    /// Sensors.
    pub sensors: usize,
    /// One bad frame in this many.
    pub bad_every: u64,
    /// Frames per batch.
    pub batch_frames: usize,
    /// Samples per channel (2 channels, i16).
    pub samples_per_channel: usize,
    /// Wall time of the run, from the first start to the final drain, s.
    pub wall_s: f64,
    /// Frames (with a verdict) per second over the run, kill and restart included.
    pub frames_per_s: f64,

    /// Distinct frames pushed (= frames).
    pub pushed: u64,
    /// Frames handed to Push streams, re-pushes included.
    pub push_attempts: u64,
    /// Frames accepted (acked as processed).
    pub acked: u64,
    /// Frames rejected.
    pub rejected: u64,
    /// Bad frames in the run.
    pub bad_frames: u64,
    /// Bad frames that were accepted (must be 0).
    pub bad_accepted: u64,
    /// Good frames that were rejected (must be 0).
    pub good_rejected: u64,
    /// Frames with no verdict at the end (must be 0).
    pub no_verdict: u64,
    /// Frames with two verdicts (must be 0).
    pub double_verdicts: u64,
    /// Frames handed to a stream before the kill that got no ack; all re-pushed after the restart.
    pub unacknowledged_at_kill: u64,
    /// Of those, frames the first server had processed (a report was seen) before dying.
    pub unacknowledged_but_reported: u64,
    /// Verdicts from the first server (before the kill).
    pub verdicts_before_kill: u64,
    /// Acks whose counts did not match their batch (must be 0).
    pub ack_mismatches: u64,
    /// Push stream failures (the kill breaks one per sensor).
    pub stream_failures: u64,
    /// Push stream failures not caused by the kill (must be 0).
    pub unexpected_stream_failures: u64,

    /// Acked frames whose report some subscriber saw.
    pub reported: u64,
    /// Reports seen for frames that were never acked (must be 0).
    pub reported_not_acked: u64,
    /// Acked frames whose report no subscriber saw, acked by the first server:
    /// reports in the dying server's buffers (the server publishes before it acks).
    pub report_lost_at_kill: u64,
    /// Acked frames whose report no subscriber saw, acked after the restart (must be 0).
    pub report_lost_after_restart: u64,
    /// Reports seen twice by the reliable subscriber (re-pushed frames processed by both servers).
    pub duplicate_reports: u64,
    /// Reports or recorded frames of sensors or sequences this run never pushed (must be 0).
    pub foreign_reports: u64,
    /// Reports the reliable subscriber was told it missed (lag markers'
    /// skipped counts; 0 when it kept up).
    pub reliable_lagged: u64,
    /// Reports the reliable subscriber received from the first server.
    pub reliable_reports_before_kill: u64,
    /// ... and from the restarted server.
    pub reliable_reports_after_restart: u64,
    /// Reports the restarted server told the reliable subscriber it skipped.
    pub reliable_lagged_after_restart: u64,
    /// Restarted server's `GetStatus`, summed over sensors: frames processed.
    pub status_processed_after_restart: u64,
    /// ... reports published.
    pub status_reports_after_restart: u64,
    /// ... frames received.
    pub status_received_after_restart: u64,
    /// ... frames rejected.
    pub status_rejected_after_restart: u64,
    /// Client-side acks from the restarted server.
    pub acked_after_restart: u64,
    /// Client-side rejections from the restarted server.
    pub rejected_after_restart: u64,

    /// Recording files found.
    pub recording_files: usize,
    /// Recording files that end inside a message (cut by the kill).
    pub recording_files_truncated: usize,
    /// Distinct frames in the recordings.
    pub recorded: u64,
    /// Frames recorded more than once (re-pushed frames recorded by both servers).
    pub recorded_twice: u64,
    /// Acked frames missing from every recording.
    pub acked_not_recorded: u64,
    /// Of those, acked by the first server (lost with its unflushed recording buffer).
    pub acked_not_recorded_before_kill: u64,

    /// The kill: seconds into the run.
    pub kill_at_s: f64,
    /// From the kill to the restarted server listening, s.
    pub restart_s: f64,
    /// Subscribers.
    pub chaotic: ChaoticSummary,
    /// RSS per server life.
    pub rss: Vec<RssLife>,
    /// RSS samples: (seconds into the run, server life, KiB).
    pub rss_samples: Vec<(f64, u32, u64)>,
    /// Scratch directory (kept only with `keep_files`).
    pub work_dir: String,

    /// pushed = acked + rejected, every bad frame rejected, every good one acked, one verdict each.
    pub check_pushed_eq_acked_plus_rejected: bool,
    /// Every acked frame reported except reports in the dying server's buffers; nothing reported unacked.
    /// Holds only when the reliable subscriber kept up (no lag markers).
    pub check_reported_eq_acked: bool,
    /// acked = reported with the fan-out's lag-and-tell counted: every report
    /// the restarted server published (= its acks) reached the reliable
    /// subscriber or was announced to it as skipped (received + skipped =
    /// published, exactly); every acked frame whose report nobody saw is
    /// covered by those announcements or was in the dying server's buffers;
    /// nothing unacked was reported.
    pub check_reported_eq_acked_with_lag: bool,
    /// Every acked frame is in a recording (needs the recorder to flush before acking).
    pub check_acked_le_recorded: bool,
    /// RSS flat (±10 %) after warm-up in every judged server life.
    pub check_rss_flat: Option<bool>,
}

/// Runs the soak (blocking; starts its own runtime).
pub fn run_soak(cfg: &SoakConfig, command: &str) -> Result<SoakReport, BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(e.to_string());
    if cfg.sensors == 0 || cfg.frames < cfg.sensors as u64 {
        return Err(BenchError::Service(
            "soak: need at least one sensor and one frame per sensor".into(),
        ));
    }
    let work = match &cfg.work_dir {
        Some(d) => d.clone(),
        None => std::env::temp_dir().join(format!(
            "tofwave-soak-{}-{}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_millis())
        )),
    };
    std::fs::create_dir_all(&work).map_err(|e| BenchError::io(&work, e))?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| err(&e))?;
    let result = rt.block_on(soak(cfg, &work, command));
    if !cfg.keep_files {
        let _ = std::fs::remove_dir_all(&work);
    }
    result
}

/// A running server child.
struct Server {
    child: Child,
    url: String,
}

fn start_server(cfg: &SoakConfig, work: &Path) -> Result<Server, BenchError> {
    let log_path = work.join("server.log");
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(|e| BenchError::io(&log_path, e))?;
    let from = log.metadata().map_or(0, |m| m.len()) as usize;
    let child = Command::new(&cfg.exe)
        .arg("serve")
        .args(["--listen", "127.0.0.1:0"])
        .arg("--state-dir")
        .arg(work.join("state"))
        .arg("--record")
        .arg(work.join("record"))
        // The reliable subscriber must never lag; stalled ones do.
        .args(["--subscriber-buffer", "16384", "--history-reports", "4096"])
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .map_err(|e| BenchError::Service(format!("starting {}: {e}", cfg.exe.display())))?;
    let mut server = Server {
        child,
        url: String::new(),
    };
    let deadline = Instant::now() + Duration::from_secs(30);
    const MARK: &str = "tofwave: serving gRPC on ";
    loop {
        let text = std::fs::read(&log_path).unwrap_or_default();
        let text = String::from_utf8_lossy(text.get(from..).unwrap_or_default());
        if let Some(line) = text.lines().find_map(|l| l.strip_prefix(MARK)) {
            server.url = format!("http://{}", line.trim());
            return Ok(server);
        }
        if let Ok(Some(status)) = server.child.try_wait() {
            return Err(BenchError::Service(format!(
                "the server exited at start ({status}): {text}"
            )));
        }
        if Instant::now() > deadline {
            let _ = server.child.kill();
            let _ = server.child.wait();
            return Err(BenchError::Service(format!(
                "the server did not start listening in 30 s: {text}"
            )));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Frames of sensor `k` still to push: re-pushes first, then fresh ones.
struct Cursor {
    next: u64,
    end: u64,
    redo: VecDeque<u64>,
}

impl Cursor {
    fn take(&mut self, n: usize) -> Vec<u64> {
        let mut v = Vec::with_capacity(n);
        while v.len() < n {
            if let Some(s) = self.redo.pop_front() {
                v.push(s);
            } else if self.next < self.end {
                v.push(self.next);
                self.next += 1;
            } else {
                break;
            }
        }
        v
    }

    fn done(&self) -> bool {
        self.redo.is_empty() && self.next >= self.end
    }
}

async fn pusher(shared: Arc<Shared>, k: usize, mut target: watch::Receiver<Target>) {
    let sensor = sensor_name(k);
    let cursor = Arc::new(Mutex::new(Cursor {
        next: 0,
        end: share(shared.cfg.frames, shared.cfg.sensors, k),
        redo: VecDeque::new(),
    }));
    loop {
        let done = lock(&cursor).done();
        if done {
            return;
        }
        let Some((url, life)) = target.wait_for(|t| t.is_some()).await.ok().and_then(|t| t.clone())
        else {
            return;
        };
        let mut clients = match client::connect(&url, &ClientOptions::default()).await {
            Ok(c) => c,
            Err(_) => {
                // The server died under us: wait for the next one.
                let _ = tokio::time::timeout(
                    Duration::from_secs(1),
                    target.wait_for(|t| t.as_ref().is_none_or(|t| t.0 != url)),
                )
                .await;
                continue;
            }
        };
        let inflight: Arc<Mutex<VecDeque<Vec<u64>>>> = Arc::default();
        let (tx, rx) = mpsc::channel::<proto::FrameBatch>(2);
        let generator = {
            let (shared, cursor, inflight, sensor) =
                (shared.clone(), cursor.clone(), inflight.clone(), sensor.clone());
            // Before the kill, hand over at most half of the frames left past
            // the kill point and then wait for the kill: however fast the
            // pushers are, the kill falls with frames still to push to the
            // restarted server.
            let kill_after = (shared.cfg.kill_at * shared.cfg.frames as f64) as u64;
            let hold_at = kill_after + shared.cfg.frames.saturating_sub(kill_after) / 2;
            let hold = life == 0 && shared.cfg.kill_at < 1.0;
            tokio::spawn(async move {
                loop {
                    while hold && shared.handed.load(Ordering::Relaxed) >= hold_at {
                        tokio::time::sleep(Duration::from_millis(2)).await;
                    }
                    let seqs = lock(&cursor).take(shared.cfg.batch_frames);
                    if seqs.is_empty() {
                        return;
                    }
                    let batch = proto::FrameBatch {
                        frames: seqs
                            .iter()
                            .map(|&s| shared.templates.frame(&sensor, s, shared.cfg.bad_every))
                            .collect(),
                    };
                    shared.handed.fetch_add(seqs.len() as u64, Ordering::Relaxed);
                    lock(&inflight).push_back(seqs);
                    if tx.send(batch).await.is_err() {
                        return;
                    }
                }
            })
        };
        let on_ack = |ack: &proto::IngestAck| {
            let Some(seqs) = lock(&inflight).pop_front() else {
                shared.ack_mismatches.fetch_add(1, Ordering::Relaxed);
                return;
            };
            if ack.accepted + ack.rejected != seqs.len() as u64 {
                shared.ack_mismatches.fetch_add(1, Ordering::Relaxed);
            }
            let refused: HashSet<u64> = ack
                .rejections
                .iter()
                .filter(|r| r.sensor_id == sensor)
                .map(|r| r.sequence)
                .collect();
            let mut flags = lock(&shared.flags[k]);
            for s in seqs {
                let bit = if refused.contains(&s) { REJECTED } else { ACKED };
                let era = if life == 0 { VERDICT_BEFORE_KILL } else { 0 };
                let slot = &mut flags[s as usize];
                if *slot & (ACKED | REJECTED) != 0 {
                    shared.double_verdicts.fetch_add(1, Ordering::Relaxed);
                }
                *slot |= bit | era;
            }
            drop(flags);
            shared
                .verdicts
                .fetch_add(ack.accepted + ack.rejected, Ordering::Relaxed);
        };
        let pushed = client::push(&mut clients.ingest, ReceiverStream::new(rx), on_ack).await;
        generator.abort();
        let _ = generator.await;
        if pushed.is_ok() && lock(&inflight).is_empty() {
            continue; // all done (checked at the top)
        }
        shared.stream_failures.fetch_add(1, Ordering::Relaxed);
        let expected = shared.killing.load(Ordering::Relaxed)
            || u32::from(life) != shared.life.load(Ordering::Relaxed);
        if !expected {
            shared
                .unexpected_stream_failures
                .fetch_add(1, Ordering::Relaxed);
            if let Err(e) = &pushed {
                tracing::warn!(sensor, error = %e, "soak: push stream failed");
            }
        }
        // Handed over and never acknowledged: count, and push again.
        let lost: Vec<u64> = lock(&inflight).drain(..).flatten().collect();
        {
            let mut flags = lock(&shared.flags[k]);
            for &s in &lost {
                flags[s as usize] |= UNACKED_AT_KILL;
            }
        }
        {
            let mut c = lock(&cursor);
            for s in lost.into_iter().rev() {
                c.redo.push_front(s);
            }
        }
        let _ = tokio::time::timeout(
            Duration::from_secs(1),
            target.wait_for(|t| t.as_ref().is_none_or(|t| t.0 != url)),
        )
        .await;
    }
}

/// Marks the sequence numbers of a report; returns false for a report this run never pushed.
fn mark_report(shared: &Shared, r: &proto::Report, bit: Bits, life: u8) -> bool {
    let Some(k) = sensor_index(&r.sensor).filter(|&k| k < shared.cfg.sensors) else {
        return false;
    };
    let mut ok = true;
    let bits = bit | if life == 0 { SEEN_BEFORE_KILL } else { 0 };
    for seq in r.seq_first..=r.seq_last {
        match shared.mark(k, seq, bits) {
            Some(old) if old & bit != 0 && bit == SEEN_RELIABLE => {
                shared.duplicate_reports.fetch_add(1, Ordering::Relaxed);
            }
            Some(_) => {}
            None => ok = false,
        }
    }
    ok
}

/// Reads every report of every sensor, reconnecting to each new server; says
/// which server life it is subscribed to through `ready`. Ends when a
/// server ends the stream cleanly (the final drain).
async fn reliable(shared: Arc<Shared>, mut target: watch::Receiver<Target>, ready: watch::Sender<i32>) {
    loop {
        let Some((url, life)) = target.wait_for(|t| t.is_some()).await.ok().and_then(|t| t.clone())
        else {
            return;
        };
        let stream = async {
            let mut c = client::connect(&url, &ClientOptions::default()).await.ok()?;
            client::subscribe(&mut c.reports, proto::SubscribeRequest::default())
                .await
                .ok()
        };
        let Some(mut stream) = stream.await else {
            let _ = tokio::time::timeout(
                Duration::from_millis(200),
                target.wait_for(|t| t.as_ref().is_none_or(|t| t.0 != url)),
            )
            .await;
            continue;
        };
        ready.send_replace(life as i32);
        loop {
            match stream.message().await {
                Ok(Some(ev)) => match ev.event {
                    Some(Event::Report(r)) => {
                        shared.reliable_reports_by_life[usize::from(life.min(1))].fetch_add(1, Ordering::Relaxed);
                        if !mark_report(&shared, &r, SEEN_RELIABLE, life) {
                            shared.foreign_reports.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Some(Event::Lagged(l)) => {
                        shared.reliable_lagged_by_life[usize::from(life.min(1))].fetch_add(l.skipped, Ordering::Relaxed);
                    }
                    None => {}
                },
                // The server drained and closed the stream: the end.
                Ok(None) => return,
                // Killed: wait for the next server.
                Err(_) => break,
            }
        }
        let _ = target.wait_for(|t| t.as_ref().is_none_or(|t| t.0 != url)).await;
    }
}

/// What a chaotic subscriber remembers across reconnects.
struct ChaoticState {
    /// Highest sequence number seen.
    last: Option<u64>,
    /// The next report is the first after a resume.
    first_after_resume: bool,
    /// Life of the server subscribed to.
    life: u8,
}

/// Reads until `until`; false when the stream ended (the server went away).
async fn read_until(
    shared: &Shared,
    stream: &mut tonic::Streaming<proto::ReportEvent>,
    until: Instant,
    st: &mut ChaoticState,
) -> bool {
    let c = &shared.chaotic;
    loop {
        let now = Instant::now();
        if now >= until || shared.stop.load(Ordering::Relaxed) {
            return true;
        }
        let ev = match tokio::time::timeout(until - now, stream.message()).await {
            Err(_) => return true,
            Ok(Ok(Some(ev))) => ev,
            Ok(_) => return false,
        };
        match ev.event {
            Some(Event::Report(r)) => {
                c.reports.fetch_add(1, Ordering::Relaxed);
                if std::mem::take(&mut st.first_after_resume)
                    && let Some(l) = st.last
                    && r.seq_first > l + 1
                {
                    c.missed_across_reconnect
                        .fetch_add(r.seq_first - l - 1, Ordering::Relaxed);
                }
                st.last = Some(st.last.map_or(r.seq_last, |l| l.max(r.seq_last)));
                if !mark_report(shared, &r, SEEN_CHAOTIC, st.life) {
                    shared.foreign_reports.fetch_add(1, Ordering::Relaxed);
                }
            }
            Some(Event::Lagged(l)) => {
                c.lag_markers.fetch_add(1, Ordering::Relaxed);
                c.lagged_skipped.fetch_add(l.skipped, Ordering::Relaxed);
            }
            None => {}
        }
    }
}

/// One sensor's misbehaving subscriber: read, stall, disconnect, resume.
async fn chaotic(shared: Arc<Shared>, k: usize, target: watch::Receiver<Target>) {
    let sensor = sensor_name(k);
    let c = &shared.chaotic;
    let mut st = ChaoticState {
        last: None,
        first_after_resume: false,
        life: 0,
    };
    let read = shared.cfg.read_phase;
    // Stagger the sensors' cycles.
    tokio::time::sleep(read.mul_f64(k as f64 / shared.cfg.sensors as f64)).await;
    while !shared.stop.load(Ordering::Relaxed) {
        let current = target.borrow().clone();
        let Some((url, life)) = current else {
            tokio::time::sleep(Duration::from_millis(50)).await;
            continue;
        };
        let resume = st.last.map(|l| l + 1);
        let stream = async {
            let mut cl = client::connect(&url, &ClientOptions::default()).await.ok()?;
            let req = proto::SubscribeRequest {
                sensor_ids: vec![sensor.clone()],
                min_snr_db: None,
                resume_from_sequence: resume,
            };
            client::subscribe(&mut cl.reports, req).await.ok()
        };
        let Some(mut stream) = stream.await else {
            tokio::time::sleep(Duration::from_millis(100)).await;
            continue;
        };
        st.first_after_resume = resume.is_some();
        st.life = life;
        // Read ...
        if !read_until(&shared, &mut stream, Instant::now() + read, &mut st).await {
            continue; // the server went away
        }
        // ... stall (the server keeps publishing; this subscriber falls behind) ...
        c.stalls.fetch_add(1, Ordering::Relaxed);
        tokio::time::sleep(shared.cfg.stall_phase).await;
        // ... read what piled up (a lag marker) briefly, then disconnect and resume.
        if !read_until(&shared, &mut stream, Instant::now() + read / 4, &mut st).await {
            continue;
        }
        drop(stream);
        c.reconnects.fetch_add(1, Ordering::Relaxed);
    }
}

fn rss_kib(pid: u32) -> Option<u64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn summarize_rss(samples: &[(f64, u32, u64)], starts: &[f64], warmup: f64) -> Vec<RssLife> {
    let mut out = Vec::new();
    for (life, &start) in starts.iter().enumerate() {
        let life = life as u32;
        let all: Vec<&(f64, u32, u64)> = samples.iter().filter(|s| s.1 == life).collect();
        let mut judged: Vec<u64> = all
            .iter()
            .filter(|s| s.0 - start >= warmup)
            .map(|s| s.2)
            .collect();
        judged.sort_unstable();
        let median = judged.get(judged.len() / 2).copied().unwrap_or(0);
        let (min, max) = (
            judged.first().copied().unwrap_or(0),
            judged.last().copied().unwrap_or(0),
        );
        let flat = (judged.len() >= 3).then(|| {
            let m = median as f64;
            (min as f64) >= 0.9 * m && (max as f64) <= 1.1 * m
        });
        out.push(RssLife {
            life,
            samples: all.len(),
            judged: judged.len(),
            min_kib: min,
            median_kib: median,
            max_kib: max,
            flat,
        });
    }
    out
}

fn sigterm(pid: u32) {
    let _ = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status();
}

async fn soak(cfg: &SoakConfig, work: &Path, command: &str) -> Result<SoakReport, BenchError> {
    let t0 = Instant::now();
    let sensors = cfg.sensors;
    let shared = Arc::new(Shared {
        cfg: cfg.clone(),
        templates: Templates::new(cfg.samples.max(16)),
        flags: (0..sensors)
            .map(|k| Mutex::new(vec![0; share(cfg.frames, sensors, k) as usize]))
            .collect(),
        verdicts: AtomicU64::new(0),
        handed: AtomicU64::new(0),
        double_verdicts: AtomicU64::new(0),
        ack_mismatches: AtomicU64::new(0),
        unexpected_stream_failures: AtomicU64::new(0),
        stream_failures: AtomicU64::new(0),
        duplicate_reports: AtomicU64::new(0),
        foreign_reports: AtomicU64::new(0),
        reliable_reports_by_life: Default::default(),
        reliable_lagged_by_life: Default::default(),
        chaotic: ChaoticCounters::default(),
        stop: AtomicBool::new(false),
        server_pid: AtomicU32::new(0),
        life: AtomicU32::new(0),
        killing: AtomicBool::new(false),
    });

    // RSS sampler.
    let rss_samples: Arc<Mutex<Vec<(f64, u32, u64)>>> = Arc::default();
    let sampler = {
        let (shared, samples) = (shared.clone(), rss_samples.clone());
        let period = cfg.rss_period;
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            loop {
                tick.tick().await;
                let pid = shared.server_pid.load(Ordering::Relaxed);
                if pid != 0
                    && let Some(kib) = rss_kib(pid)
                {
                    let life = shared.life.load(Ordering::Relaxed);
                    lock(&samples).push((t0.elapsed().as_secs_f64(), life, kib));
                }
            }
        })
    };

    let (sub_tx, sub_rx) = watch::channel::<Target>(None);
    let (push_tx, push_rx) = watch::channel::<Target>(None);
    let (ready_tx, mut ready_rx) = watch::channel::<i32>(-1);
    let reliable_task = tokio::spawn(reliable(shared.clone(), sub_rx.clone(), ready_tx));
    let chaotic_tasks: Vec<_> = (0..sensors)
        .map(|k| tokio::spawn(chaotic(shared.clone(), k, sub_rx.clone())))
        .collect();

    // Subscribers first, then pushers: no report is published before the
    // reliable subscriber listens.
    let go = |server: &Server, life: u8, ready_rx: &mut watch::Receiver<i32>| {
        sub_tx.send_replace(Some((server.url.clone(), life)));
        let mut ready_rx = ready_rx.clone();
        let push_tx = push_tx.clone();
        let url = server.url.clone();
        async move {
            let ok = tokio::time::timeout(
                Duration::from_secs(30),
                ready_rx.wait_for(|&l| l == i32::from(life)),
            )
            .await;
            push_tx.send_replace(Some((url, life)));
            ok.is_ok()
        }
    };

    let mut server = start_server(cfg, work)?;
    let mut life_starts = vec![t0.elapsed().as_secs_f64()];
    shared.server_pid.store(server.child.id(), Ordering::Relaxed);
    if !go(&server, 0, &mut ready_rx).await {
        let _ = server.child.kill();
        return Err(BenchError::Service("the reliable subscriber could not subscribe".into()));
    }
    let pushers: Vec<_> = (0..sensors)
        .map(|k| tokio::spawn(pusher(shared.clone(), k, push_rx.clone())))
        .collect();

    let progress = |shared: &Shared, last: &mut Instant| {
        if cfg.progress && last.elapsed() >= Duration::from_secs(5) {
            *last = Instant::now();
            let v = shared.verdicts.load(Ordering::Relaxed);
            let rss = rss_kib(shared.server_pid.load(Ordering::Relaxed)).unwrap_or(0);
            eprintln!(
                "soak: {:>7.1} s  {v}/{} frames with a verdict ({:.0} frames/s), server RSS {} MiB",
                t0.elapsed().as_secs_f64(),
                cfg.frames,
                v as f64 / t0.elapsed().as_secs_f64(),
                rss / 1024
            );
        }
    };
    let mut last_progress = Instant::now();

    // Run to the kill point.
    let kill_after = (cfg.kill_at * cfg.frames as f64) as u64;
    let mut kill_at_s = f64::NAN;
    let mut restart_s = f64::NAN;
    if cfg.kill_at < 1.0 {
        while shared.verdicts.load(Ordering::Relaxed) < kill_after.max(1)
            && !pushers.iter().all(|p| p.is_finished())
        {
            tokio::time::sleep(Duration::from_millis(5)).await;
            progress(&shared, &mut last_progress);
        }
        shared.killing.store(true, Ordering::Relaxed);
        push_tx.send_replace(None);
        sub_tx.send_replace(None);
        let _ = server.child.kill(); // SIGKILL
        let _ = server.child.wait();
        let killed = Instant::now();
        kill_at_s = t0.elapsed().as_secs_f64();
        shared.server_pid.store(0, Ordering::Relaxed);
        if cfg.progress {
            eprintln!(
                "soak: {kill_at_s:.1} s  server killed (SIGKILL) with {} frames with a verdict; restarting",
                shared.verdicts.load(Ordering::Relaxed)
            );
        }
        server = start_server(cfg, work)?;
        restart_s = killed.elapsed().as_secs_f64();
        shared.life.store(1, Ordering::Relaxed);
        life_starts.push(t0.elapsed().as_secs_f64());
        shared.server_pid.store(server.child.id(), Ordering::Relaxed);
        shared.killing.store(false, Ordering::Relaxed);
        let ok = go(&server, 1, &mut ready_rx).await;
        if !ok {
            let _ = server.child.kill();
            return Err(BenchError::Service(
                "the reliable subscriber could not resubscribe after the restart".into(),
            ));
        }
    }
    let mut unfinished = pushers;
    while !unfinished.is_empty() {
        tokio::time::sleep(Duration::from_millis(20)).await;
        progress(&shared, &mut last_progress);
        unfinished.retain(|p| !p.is_finished());
    }

    // The restarted server's own counters.
    let mut status = (0u64, 0u64, 0u64, 0u64);
    if let Ok(mut c) = client::connect(&server.url, &ClientOptions::default()).await {
        for k in 0..sensors {
            let req = proto::SensorRequest {
                sensor_id: sensor_name(k),
            };
            if let Ok(s) = c.control.get_status(req).await {
                let s = s.into_inner();
                status.0 += s.frames_received;
                status.1 += s.frames_processed;
                status.2 += s.frames_rejected;
                status.3 += s.reports;
            }
        }
    }

    // Stop the subscribers' games, then drain the server (SIGTERM): queued work
    // is done, recordings finished, subscriber streams end cleanly.
    shared.stop.store(true, Ordering::Relaxed);
    for t in chaotic_tasks {
        let _ = tokio::time::timeout(Duration::from_secs(10), t).await;
    }
    sigterm(server.child.id());
    let exit_deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Ok(Some(_)) = server.child.try_wait() {
            break;
        }
        if Instant::now() > exit_deadline {
            let _ = server.child.kill();
            let _ = server.child.wait();
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    shared.server_pid.store(0, Ordering::Relaxed);
    let _ = tokio::time::timeout(Duration::from_secs(10), reliable_task).await;
    sampler.abort();
    let wall_s = t0.elapsed().as_secs_f64();

    // Recordings.
    let rec_dir = work.join("record");
    let mut files = 0usize;
    let mut truncated = 0usize;
    let mut recorded_twice = 0u64;
    let mut foreign_recorded = 0u64;
    let mut entries: Vec<PathBuf> = std::fs::read_dir(&rec_dir)
        .map_err(|e| BenchError::io(&rec_dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "twr"))
        .collect();
    entries.sort();
    for path in &entries {
        files += 1;
        let file = std::fs::File::open(path).map_err(|e| BenchError::io(path, e))?;
        let len = file.metadata().map_or(u64::MAX, |m| m.len());
        let reader = match RecordingReader::with_limit(std::io::BufReader::new(file), path, len) {
            Ok(r) => r,
            Err(_) => {
                // Killed before the header reached the disk.
                truncated += 1;
                continue;
            }
        };
        for frame in reader {
            match frame {
                Ok(f) => match sensor_index(&f.sensor_id).filter(|&k| k < sensors) {
                    Some(k) => {
                        if shared.mark(k, f.sequence, RECORDED).is_some_and(|o| o & RECORDED != 0) {
                            recorded_twice += 1;
                        }
                    }
                    None => foreign_recorded += 1,
                },
                Err(_) => {
                    truncated += 1;
                    break;
                }
            }
        }
    }

    // Classify every frame.
    let mut n = Tally::default();
    for k in 0..sensors {
        let flags = lock(&shared.flags[k]);
        for (seq, &f) in flags.iter().enumerate() {
            n.add(f, bad_kind(seq as u64, cfg.bad_every).is_some());
        }
    }
    let samples = lock(&rss_samples).clone();
    let rss = summarize_rss(&samples, &life_starts, cfg.rss_warmup.as_secs_f64());
    let judged: Vec<bool> = rss.iter().filter_map(|l| l.flat).collect();
    let check_rss_flat = (!judged.is_empty()).then(|| judged.iter().all(|&b| b));
    let c = &shared.chaotic;
    let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
    let double_verdicts = get(&shared.double_verdicts);
    let report = SoakReport {
        command: command.to_string(),
        frames: cfg.frames,
        sensors,
        bad_every: cfg.bad_every,
        batch_frames: cfg.batch_frames,
        samples_per_channel: cfg.samples.max(16),
        wall_s,
        frames_per_s: (n.acked + n.rejected) as f64 / wall_s,
        pushed: n.frames,
        push_attempts: get(&shared.handed),
        acked: n.acked,
        rejected: n.rejected,
        bad_frames: n.bad,
        bad_accepted: n.bad_accepted,
        good_rejected: n.good_rejected,
        no_verdict: n.no_verdict,
        double_verdicts,
        unacknowledged_at_kill: n.unacked_at_kill,
        unacknowledged_but_reported: n.unacked_but_reported,
        verdicts_before_kill: n.verdict_before_kill,
        ack_mismatches: get(&shared.ack_mismatches),
        stream_failures: get(&shared.stream_failures),
        unexpected_stream_failures: get(&shared.unexpected_stream_failures),
        reported: n.reported,
        reported_not_acked: n.reported_not_acked,
        report_lost_at_kill: n.report_lost_before,
        report_lost_after_restart: n.report_lost_after,
        duplicate_reports: get(&shared.duplicate_reports),
        foreign_reports: get(&shared.foreign_reports) + foreign_recorded,
        reliable_lagged: shared.reliable_lagged_by_life.iter().map(get).sum(),
        reliable_reports_before_kill: get(&shared.reliable_reports_by_life[0]),
        reliable_reports_after_restart: get(&shared.reliable_reports_by_life[1]),
        reliable_lagged_after_restart: get(&shared.reliable_lagged_by_life[1]),
        status_processed_after_restart: status.1,
        status_reports_after_restart: status.3,
        status_received_after_restart: status.0,
        status_rejected_after_restart: status.2,
        acked_after_restart: n.acked_after,
        rejected_after_restart: n.rejected_after,
        recording_files: files,
        recording_files_truncated: truncated,
        recorded: n.recorded,
        recorded_twice,
        acked_not_recorded: n.acked_not_recorded,
        acked_not_recorded_before_kill: n.acked_not_recorded_before,
        kill_at_s,
        restart_s,
        chaotic: ChaoticSummary {
            reports: get(&c.reports),
            stalls: get(&c.stalls),
            reconnects: get(&c.reconnects),
            lag_markers: get(&c.lag_markers),
            lagged_skipped: get(&c.lagged_skipped),
            missed_across_reconnect: get(&c.missed_across_reconnect),
        },
        rss,
        rss_samples: samples,
        work_dir: work.display().to_string(),
        check_pushed_eq_acked_plus_rejected: n.frames == n.acked + n.rejected
            && n.no_verdict == 0
            && double_verdicts == 0
            && n.bad_accepted == 0
            && n.good_rejected == 0,
        check_reported_eq_acked: n.reported + n.report_lost_before == n.acked
            && n.report_lost_after == 0
            && n.reported_not_acked == 0
            && status.1 == n.acked_after
            && status.3 == status.1,
        check_reported_eq_acked_with_lag: n.reported + n.report_lost_before + n.report_lost_after == n.acked
            && n.reported_not_acked == 0
            && status.1 == n.acked_after
            && status.3 == status.1
            && get(&shared.reliable_reports_by_life[1]) + get(&shared.reliable_lagged_by_life[1]) == status.3
            && n.report_lost_after <= get(&shared.reliable_lagged_by_life[1]),
        check_acked_le_recorded: n.acked_not_recorded == 0,
        check_rss_flat,
    };
    Ok(report)
}

/// Per-frame classification totals.
#[derive(Default)]
struct Tally {
    frames: u64,
    bad: u64,
    acked: u64,
    rejected: u64,
    bad_accepted: u64,
    good_rejected: u64,
    no_verdict: u64,
    unacked_at_kill: u64,
    unacked_but_reported: u64,
    verdict_before_kill: u64,
    acked_after: u64,
    rejected_after: u64,
    reported: u64,
    reported_not_acked: u64,
    report_lost_before: u64,
    report_lost_after: u64,
    recorded: u64,
    acked_not_recorded: u64,
    acked_not_recorded_before: u64,
}

impl Tally {
    fn add(&mut self, f: Bits, bad: bool) {
        let has = |b: Bits| f & b != 0;
        let seen = has(SEEN_RELIABLE) || has(SEEN_CHAOTIC);
        let before = has(VERDICT_BEFORE_KILL);
        self.frames += 1;
        self.bad += u64::from(bad);
        self.recorded += u64::from(has(RECORDED));
        self.verdict_before_kill += u64::from(before);
        if has(UNACKED_AT_KILL) {
            self.unacked_at_kill += 1;
            self.unacked_but_reported += u64::from(has(SEEN_BEFORE_KILL));
        }
        match (has(ACKED), has(REJECTED)) {
            (true, _) => {
                self.acked += 1;
                self.bad_accepted += u64::from(bad);
                self.acked_after += u64::from(!before);
                if seen {
                    self.reported += 1;
                } else if before {
                    self.report_lost_before += 1;
                } else {
                    self.report_lost_after += 1;
                }
                if !has(RECORDED) {
                    self.acked_not_recorded += 1;
                    self.acked_not_recorded_before += u64::from(before);
                }
            }
            (false, true) => {
                self.rejected += 1;
                self.good_rejected += u64::from(!bad);
                self.rejected_after += u64::from(!before);
                self.reported_not_acked += u64::from(seen);
            }
            (false, false) => {
                self.no_verdict += 1;
                self.reported_not_acked += u64::from(seen);
            }
        }
    }
}

impl SoakReport {
    /// The markdown summary (what `soak.md` holds).
    pub fn markdown(&self) -> String {
        let yes = |b: bool| if b { "yes" } else { "**NO**" };
        let rss: String = self
            .rss
            .iter()
            .map(|l| {
                format!(
                    "| {} | {} | {} | {:.1} | {:.1} | {:.1} | {} |\n",
                    if l.life == 0 { "before kill" } else { "after restart" },
                    l.samples,
                    l.judged,
                    l.min_kib as f64 / 1024.0,
                    l.median_kib as f64 / 1024.0,
                    l.max_kib as f64 / 1024.0,
                    match l.flat {
                        Some(b) => yes(b).to_string(),
                        None => "too short to judge".into(),
                    }
                )
            })
            .collect();
        format!(
            "# Soak run\n\n\
             `{cmd}`\n\n\
             {frames} frames ({sensors} sensors, 2 ch x {spc} i16 samples at 1 ns, {batch} frames per batch, \
             1 bad frame in {bad_every}) in {wall:.1} s: {rate:.0} frames/s including one SIGKILL and restart \
             (at {kill:.1} s; listening again after {restart:.2} s).\n\n\
             ## Reconciliation\n\n\
             | quantity | frames |\n|---|---:|\n\
             | pushed (distinct sensor, sequence) | {pushed} |\n\
             | push attempts (re-pushes included) | {attempts} |\n\
             | acked | {acked} |\n\
             | rejected (INVALID_ARGUMENT) | {rejected} |\n\
             | bad frames in the run | {badn} |\n\
             | bad frames accepted / good frames rejected | {bad_acc} / {good_rej} |\n\
             | no verdict / two verdicts | {nov} / {dv} |\n\
             | unacknowledged at kill (re-pushed) | {unack} |\n\
             | of which the dying server had already reported | {unack_rep} |\n\
             | verdicts before the kill | {vbk} |\n\
             | acked and reported | {reported} |\n\
             | acked, report lost in the dying server's buffers | {lost_kill} |\n\
             | acked after the restart, report never seen | {lost_after} |\n\
             | reported but never acked | {rna} |\n\
             | reports seen twice (re-pushed frames processed twice) | {dup} |\n\
             | reliable subscriber lagged (reports skipped) | {rlag} |\n\
             | reliable subscriber, restarted server: reports received + announced skipped = published | {rr1} + {rl1} = {rsum} (server: {srep}) |\n\
             | restarted server GetStatus: received / processed / rejected / reports | {sr} / {sp} / {srj} / {srep} |\n\
             | client acks / rejections from the restarted server | {aa} / {ra} |\n\
             | recorded (distinct, {files} files, {trunc} cut short) | {recorded} |\n\
             | recorded twice | {rec2} |\n\
             | **acked but not in any recording** | {anr} |\n\
             | of which acked by the killed server | {anrb} |\n\n\
             | check | holds |\n|---|---|\n\
             | pushed = acked + rejected (one verdict each; bad frames exactly the rejected ones) | {c1} |\n\
             | acked = reported (+ reports lost in the dying server's buffers), no lag | {c2} |\n\
             | acked = reported, lag-and-tell counted (received + announced skipped = published) | {c2l} |\n\
             | acked <= recorded | {c3} |\n\
             | RSS flat (±10 %) after warm-up | {c4} |\n\n\
             ## Subscribers\n\n\
             Chaotic subscribers (one per sensor): {cr} reports, {cs} stalls, {cre} disconnect/resume cycles, \
             {clm} lag markers ({cls} reports skipped), {cmiss} sequence numbers missed across a reconnect.\n\n\
             ## Server RSS\n\n\
             | server life | samples | after warm-up | min MiB | median MiB | max MiB | flat ±10 % |\n\
             |---|---:|---:|---:|---:|---:|---|\n{rss}",
            cmd = self.command,
            frames = self.frames,
            sensors = self.sensors,
            spc = self.samples_per_channel,
            batch = self.batch_frames,
            bad_every = self.bad_every,
            wall = self.wall_s,
            rate = self.frames_per_s,
            kill = self.kill_at_s,
            restart = self.restart_s,
            pushed = self.pushed,
            attempts = self.push_attempts,
            acked = self.acked,
            rejected = self.rejected,
            badn = self.bad_frames,
            bad_acc = self.bad_accepted,
            good_rej = self.good_rejected,
            nov = self.no_verdict,
            dv = self.double_verdicts,
            unack = self.unacknowledged_at_kill,
            unack_rep = self.unacknowledged_but_reported,
            vbk = self.verdicts_before_kill,
            reported = self.reported,
            lost_kill = self.report_lost_at_kill,
            lost_after = self.report_lost_after_restart,
            rna = self.reported_not_acked,
            dup = self.duplicate_reports,
            rlag = self.reliable_lagged,
            rr1 = self.reliable_reports_after_restart,
            rl1 = self.reliable_lagged_after_restart,
            rsum = self.reliable_reports_after_restart + self.reliable_lagged_after_restart,
            sr = self.status_received_after_restart,
            sp = self.status_processed_after_restart,
            srj = self.status_rejected_after_restart,
            srep = self.status_reports_after_restart,
            aa = self.acked_after_restart,
            ra = self.rejected_after_restart,
            files = self.recording_files,
            trunc = self.recording_files_truncated,
            recorded = self.recorded,
            rec2 = self.recorded_twice,
            anr = self.acked_not_recorded,
            anrb = self.acked_not_recorded_before_kill,
            c1 = yes(self.check_pushed_eq_acked_plus_rejected),
            c2 = yes(self.check_reported_eq_acked),
            c2l = yes(self.check_reported_eq_acked_with_lag),
            c3 = yes(self.check_acked_le_recorded),
            c4 = match self.check_rss_flat {
                Some(b) => yes(b).to_string(),
                None => "too short to judge".into(),
            },
            cr = self.chaotic.reports,
            cs = self.chaotic.stalls,
            cre = self.chaotic.reconnects,
            clm = self.chaotic.lag_markers,
            cls = self.chaotic.lagged_skipped,
            cmiss = self.chaotic.missed_across_reconnect,
        )
    }

    /// Writes `soak.json` and `soak.md` into `dir` (created).
    pub fn write(&self, dir: &Path) -> Result<(), BenchError> {
        std::fs::create_dir_all(dir).map_err(|e| BenchError::io(dir, e))?;
        let json = dir.join("soak.json");
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| BenchError::Service(format!("soak.json: {e}")))?;
        std::fs::write(&json, text).map_err(|e| BenchError::io(&json, e))?;
        let md = dir.join("soak.md");
        std::fs::write(&md, self.markdown()).map_err(|e| BenchError::io(&md, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_add_up_and_bad_frames_rotate() {
        assert_eq!((0..8).map(|k| share(1003, 8, k)).sum::<u64>(), 1003);
        let kinds: Vec<usize> = (0..3000).filter_map(|s| bad_kind(s, 1000)).collect();
        assert_eq!(kinds, vec![0, 1, 2]);
        assert_eq!(sensor_index(&sensor_name(7)), Some(7));
    }
}
