//! Per-sensor sessions: one pipeline per sensor on its own worker thread,
//! fed through a bounded queue.
//!
//! The queue is what turns a slow pipeline into backpressure: when it is full,
//! the ingest stream awaits space, stops reading from the connection, and HTTP/2
//! flow control slows the digitiser. Nothing is dropped. Scene changes travel
//! through the same queue, so they take effect between two frames, in order.

use super::{ServiceError, lock};
use super::fanout::Hub;
use super::dashboard::Snapshots;
use super::state::StateDir;
use crate::capture::RecordingWriter;
use crate::frame::{Frame, NoiseSummary, Report};
use crate::pipeline::threaded::{Outcome, Staged};
use crate::pipeline::{FrameError, Pipeline};
use crate::scene::Scene;
use crate::telemetry;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tokio::sync::{mpsc, oneshot, watch};

/// Builds a pipeline on the calling thread (cluster replay, scene checks);
/// a session's worker runs a [`Staged`] one, on `--workers-per-sensor` threads.
pub fn build_pipeline(scene: &Scene, sensor: &str) -> Result<Pipeline, String> {
    Ok(Pipeline::new(scene, sensor))
}

/// Work for a sensor's worker, in arrival order.
enum Job {
    /// Process one frame and say how it went.
    Frame {
        /// The validated frame.
        frame: Frame,
        /// When it entered the queue (for the latency histogram).
        enqueued: Instant,
        /// Receives the pipeline's verdict.
        done: oneshot::Sender<Verdict>,
    },
    /// The end of an ingest batch: the verdicts and reports held so far go out.
    EndOfBatch,
    /// Replace the pipeline (after flushing the old one).
    SetScene {
        /// The validated scene (boxed: every queued job, frames and batch
        /// ends included, is the size of the largest variant).
        scene: Box<Scene>,
        /// Receives the outcome of building the new pipeline.
        done: oneshot::Sender<Result<(), String>>,
    },
}

/// What became of a queued frame.
#[derive(Debug)]
pub enum Verdict {
    /// The pipeline processed it.
    Processed,
    /// The pipeline refused it (bad content the edge could not see).
    Refused(FrameError),
    /// The pipeline panicked on it (a bug); the sensor's pipeline was rebuilt
    /// from its scene, losing its running state (averages, noise history).
    Panicked(String),
    /// Not acknowledged: the sensor's recording failed, so an ack could no
    /// longer mean "recorded". The reason names the file and the error; a
    /// frame processed before the failure was reported but is still refused.
    Unrecorded(String),
}

/// Counters of one sensor (monotonic; read by `GetStatus`).
#[derive(Default)]
pub struct Stats {
    /// Frames decoded from ingest messages.
    pub frames_received: AtomicU64,
    /// Frames processed without error.
    pub frames_processed: AtomicU64,
    /// Frames refused (at the edge or by the pipeline).
    pub frames_rejected: AtomicU64,
    /// Reports published.
    pub reports: AtomicU64,
    /// Returns in those reports.
    pub returns: AtomicU64,
    /// Highest sequence number seen.
    pub last_sequence: AtomicU64,
    /// Missing sequence numbers detected.
    pub sequence_gaps: AtomicU64,
    /// Queue-to-processed time of the latest frame, µs (the dashboard's latency).
    pub last_latency_us: AtomicU64,
    /// When the latest frame was processed, ms since the Unix epoch (0: none yet).
    pub last_processed_unix_ms: AtomicU64,
}

/// One sensor's session.
pub struct Session {
    /// Sensor id.
    pub sensor: String,
    /// Queue into the worker; `None` once the session is closed.
    tx: Mutex<Option<mpsc::Sender<Job>>>,
    /// Scene the edge validates against and `GetScene` shows (the one the worker
    /// runs, or is about to run once queued frames ahead of it are done).
    scene: Mutex<Arc<Scene>>,
    /// Counters.
    pub stats: Stats,
    /// The sensor's metric handles (labelled once, not per frame).
    pub metrics: telemetry::SensorMetrics,
    /// Latest noise model (from the pipeline, or reloaded from the state dir).
    noise: Mutex<Option<NoiseSummary>>,
    /// Last sequence number seen at the edge, for gap detection.
    last_seq: Mutex<Option<u64>>,
    /// The worker thread, joined at close.
    worker: Mutex<Option<std::thread::JoinHandle<()>>>,
    /// Why the sensor's frames are refused (recording failed, worker
    /// stopped); `None` while healthy. Set once, cleared only by a restart.
    fault: Mutex<Option<String>>,
}

/// Why a session could not be started.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The server already runs its maximum number of sensors.
    #[error("the server already serves its limit of {0} sensors")]
    Limit(usize),
    /// The pipeline could not be built from the scene, or the worker not started.
    #[error("{0}")]
    Build(String),
}

/// Why a frame could not be queued.
#[derive(Debug, thiserror::Error)]
pub enum QueueError {
    /// The server is shutting down.
    #[error("server is shutting down")]
    Closed,
    /// The sensor is faulted (its worker stopped): the reason.
    #[error("{0}")]
    Faulted(String),
}

impl Session {
    /// Current scene.
    pub fn scene(&self) -> Arc<Scene> {
        lock(&self.scene).clone()
    }

    /// Latest noise model.
    pub fn noise(&self) -> Option<NoiseSummary> {
        *lock(&self.noise)
    }

    /// Frames waiting in the queue.
    pub fn queue_depth(&self) -> usize {
        lock(&self.tx)
            .as_ref()
            .map_or(0, |tx| tx.max_capacity() - tx.capacity())
    }

    /// Records sequence `seq` arriving; returns `(first_missing, count)` when
    /// numbers were skipped. A sequence at or below the last one (a digitiser
    /// restart) restarts the count without a gap.
    pub fn observe_sequence(&self, seq: u64) -> Option<(u64, u64)> {
        let mut last = lock(&self.last_seq);
        let gap = match *last {
            Some(l) if seq > l.saturating_add(1) => Some((l + 1, seq - l - 1)),
            _ => None,
        };
        *last = Some(seq);
        self.stats.last_sequence.store(seq, Ordering::Relaxed);
        if let Some((_, n)) = gap {
            self.stats.sequence_gaps.fetch_add(n, Ordering::Relaxed);
            self.metrics.sequence_gap(n);
        }
        gap
    }

    /// Why the sensor's frames are refused, if they are.
    pub fn fault(&self) -> Option<String> {
        lock(&self.fault).clone()
    }

    /// Marks the sensor faulted (the first reason stays) and wakes the
    /// health watcher.
    /// Counts one frame refused for `why` (the metric's label).
    fn rejected(&self, why: &'static str) {
        self.stats.frames_rejected.fetch_add(1, Ordering::Relaxed);
        self.metrics.frames_rejected(why, 1);
    }

    fn set_fault(&self, reason: String, signal: &watch::Sender<u64>) {
        {
            let mut f = lock(&self.fault);
            if f.is_some() {
                return;
            }
            tracing::error!(sensor = %self.sensor, reason = %reason, "sensor faulted: its frames are refused");
            *f = Some(reason);
        }
        telemetry::sensor_faulted(&self.sensor);
        signal.send_modify(|g| *g += 1);
    }

    fn sender(&self) -> Result<mpsc::Sender<Job>, QueueError> {
        lock(&self.tx).clone().ok_or(QueueError::Closed)
    }

    /// The error for a queue that refused a job: the fault when the worker
    /// stopped, else shutdown.
    fn closed(&self) -> QueueError {
        match self.fault() {
            Some(reason) => QueueError::Faulted(reason),
            None => QueueError::Closed,
        }
    }

    /// Queues a frame, waiting while the queue is full (backpressure). The
    /// returned receiver yields the pipeline's verdict.
    pub async fn enqueue(&self, frame: Frame) -> Result<oneshot::Receiver<Verdict>, QueueError> {
        let tx = self.sender()?;
        let (done, rx) = oneshot::channel();
        tx.send(Job::Frame {
            frame,
            enqueued: Instant::now(),
            done,
        })
        .await
        .map_err(|_| self.closed())?;
        self.metrics.queue_depth(tx.max_capacity() - tx.capacity());
        Ok(rx)
    }

    /// Marks the end of an ingest batch in the queue: once the frames queued
    /// before it are processed, their verdicts and reports go out (the worker
    /// holds them while frames are queued, to wake the ingest stream and the
    /// subscribers once a batch, not once a frame). Nothing to do on a
    /// closed queue: its frames were refused.
    pub async fn end_of_batch(&self) {
        if let Ok(tx) = self.sender() {
            let _ = tx.send(Job::EndOfBatch).await;
        }
    }

    /// Applies `scene` between two frames; resolves once the new pipeline runs.
    pub async fn set_scene(&self, scene: Scene) -> Result<(), String> {
        let tx = self.sender().map_err(|e| e.to_string())?;
        let (done, rx) = oneshot::channel();
        tx.send(Job::SetScene {
            scene: Box::new(scene.clone()),
            done,
        })
        .await
        .map_err(|_| self.closed().to_string())?;
        rx.await.map_err(|_| self.closed().to_string())??;
        *lock(&self.scene) = Arc::new(scene);
        Ok(())
    }
}

/// All sessions of a server.
pub struct Sessions {
    /// Sessions by sensor id.
    map: Mutex<HashMap<String, Arc<Session>>>,
    /// Scene new sensors start with.
    default_scene: Mutex<Scene>,
    /// Queue length per sensor, frames.
    queue_frames: usize,
    /// Sessions allowed (each holds a thread and a pipeline).
    max_sensors: usize,
    /// Where reports go.
    hub: Arc<Hub>,
    /// Persistence.
    state: Option<StateDir>,
    /// Recording directory.
    record_dir: Option<PathBuf>,
    /// Record sync policy and persistence period.
    durability: Durability,
    /// Threads each sensor's pipeline may run on (its stages cut over them).
    workers_per_sensor: usize,
    /// Open ingest streams (shutdown waits for zero).
    ingest_streams: watch::Sender<usize>,
    /// Bumped whenever a sensor becomes faulted (`service::run` sets health).
    faults: Arc<watch::Sender<u64>>,
    /// Dashboard waveform snapshots (`serve --dashboard`): every pipeline gets
    /// their observer; `None`: no dashboard, no observer.
    snapshots: Option<Arc<Snapshots>>,
}

/// What an acknowledgement promises about the recording, and how often
/// noise models are saved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Durability {
    /// When recording: what is done with the recorded frames before they are
    /// acknowledged.
    pub record_sync: RecordSync,
    /// Noise models are saved to the state directory at most this often
    /// while frames arrive (and at shutdown).
    pub persist_interval: std::time::Duration,
}

impl Default for Durability {
    fn default() -> Self {
        Durability { record_sync: RecordSync::Flush, persist_interval: std::time::Duration::from_secs(10) }
    }
}

/// Before a recorded frame is acknowledged, it is…
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum RecordSync {
    /// …written to the operating system: an acknowledged frame survives the
    /// server being killed (kill -9), not a power cut.
    #[default]
    Flush,
    /// …written and synced to the storage device (fdatasync): it survives a
    /// power cut as well, at the device's sync cost per acknowledged batch.
    Fsync,
}

/// Counts an open ingest stream while alive.
pub struct IngestGuard<'a>(&'a watch::Sender<usize>);

impl Drop for IngestGuard<'_> {
    fn drop(&mut self) {
        self.0.send_modify(|n| *n -= 1);
    }
}

impl Sessions {
    /// Empty registry; reloads scenes and noise models from `state`.
    pub fn new(
        default_scene: Scene,
        queue_frames: usize,
        max_sensors: usize,
        hub: Arc<Hub>,
        state: Option<StateDir>,
        record_dir: Option<PathBuf>,
        durability: Durability,
        snapshots: Option<Arc<Snapshots>>,
        workers_per_sensor: usize,
    ) -> Result<Sessions, ServiceError> {
        if let Some(dir) = &record_dir {
            std::fs::create_dir_all(dir).map_err(|e| ServiceError::Record {
                path: dir.display().to_string(),
                message: e.to_string(),
            })?;
        }
        let mut default_scene = default_scene;
        let mut saved = Vec::new();
        if let Some(st) = &state {
            let loaded = st.load()?;
            for w in &loaded.skipped {
                tracing::warn!(warning = %w, "state directory: file skipped");
            }
            if let Some(s) = loaded.default_scene {
                // A default set at run time (SetScene with no sensor id) is the
                // operator's latest word; it outlives the --scene of the start.
                if s != default_scene {
                    tracing::warn!(scene = %s.name, "using the default scene saved in the state directory, not the configured one");
                }
                default_scene = s;
            }
            saved = loaded.sensors;
        }
        let sessions = Sessions {
            map: Mutex::new(HashMap::new()),
            default_scene: Mutex::new(default_scene),
            queue_frames: queue_frames.max(1),
            max_sensors,
            hub,
            state,
            record_dir,
            durability,
            workers_per_sensor: workers_per_sensor.max(1),
            ingest_streams: watch::Sender::new(0),
            faults: Arc::new(watch::Sender::new(0)),
            snapshots,
        };
        for s in saved {
            // A saved sensor whose scene no longer builds is skipped with a
            // warning: the server starts, and the sensor starts afresh on the
            // default scene when its frames arrive.
            let session = match sessions.start(&s.sensor, s.scene.unwrap_or_else(|| sessions.default_scene()), false) {
                Ok(session) => session,
                Err(e) => {
                    tracing::warn!(sensor = %s.sensor, error = %e, "saved sensor state skipped");
                    continue;
                }
            };
            *lock(&session.noise) = s.noise;
            tracing::info!(sensor = %s.sensor, "reloaded sensor state");
        }
        Ok(sessions)
    }

    /// Scene new sensors start with.
    pub fn default_scene(&self) -> Scene {
        lock(&self.default_scene).clone()
    }

    /// Changes the scene new sensors start with (and persists it).
    pub fn set_default_scene(&self, scene: Scene) -> Result<(), ServiceError> {
        if let Some(st) = &self.state {
            st.save_scene(None, &scene)?;
        }
        *lock(&self.default_scene) = scene;
        Ok(())
    }

    /// Existing session of `sensor`.
    pub fn get(&self, sensor: &str) -> Option<Arc<Session>> {
        lock(&self.map).get(sensor).cloned()
    }

    /// Changes whenever a sensor becomes faulted.
    pub fn fault_signal(&self) -> watch::Receiver<u64> {
        self.faults.subscribe()
    }

    /// Faulted sensors and why, sorted by sensor id.
    pub fn faulted(&self) -> Vec<(String, String)> {
        self.all()
            .into_iter()
            .filter_map(|s| s.fault().map(|f| (s.sensor.clone(), f)))
            .collect()
    }

    /// All sessions, sorted by sensor id.
    pub fn all(&self) -> Vec<Arc<Session>> {
        let mut v: Vec<_> = lock(&self.map).values().cloned().collect();
        v.sort_by(|a, b| a.sensor.cmp(&b.sensor));
        v
    }

    /// Session of `sensor`, started on the default scene if new.
    pub fn get_or_start(&self, sensor: &str) -> Result<Arc<Session>, StartError> {
        if let Some(s) = self.get(sensor) {
            return Ok(s);
        }
        self.start(sensor, self.default_scene(), true)
    }

    /// Persists `scene` for `sensor` (after it was applied).
    pub fn persist_scene(&self, sensor: &str, scene: &Scene) -> Result<(), ServiceError> {
        match &self.state {
            Some(st) => Ok(st.save_scene(Some(sensor), scene)?),
            None => Ok(()),
        }
    }

    /// Starts a session; `limited`: refuse past `max_sensors`.
    fn start(&self, sensor: &str, scene: Scene, limited: bool) -> Result<Arc<Session>, StartError> {
        let mut map = lock(&self.map);
        if let Some(s) = map.get(sensor) {
            return Ok(s.clone());
        }
        // Saved sensors reload even past the limit: the limit guards against
        // clients inventing ids, not against the operator's own state.
        if limited && map.len() >= self.max_sensors {
            return Err(StartError::Limit(self.max_sensors));
        }
        let mut pipeline = Staged::new(&scene, sensor, self.workers_per_sensor);
        if let Some(s) = &self.snapshots {
            pipeline.set_observer(s.observer());
        }
        let recorder = match &self.record_dir {
            Some(dir) => Some(open_recording(dir, sensor).map_err(StartError::Build)?),
            None => None,
        };
        let record_path = recorder.as_ref().map(|(_, p)| p.clone());
        let recorder = recorder.map(|(w, _)| w);
        let (tx, rx) = mpsc::channel(self.queue_frames);
        let session = Arc::new(Session {
            sensor: sensor.to_string(),
            tx: Mutex::new(Some(tx)),
            scene: Mutex::new(Arc::new(scene)),
            stats: Stats::default(),
            metrics: telemetry::SensorMetrics::new(sensor),
            noise: Mutex::new(None),
            last_seq: Mutex::new(None),
            worker: Mutex::new(None),
            fault: Mutex::new(None),
        });
        let worker = Worker {
            session: session.clone(),
            pipeline,
            hub: self.hub.clone(),
            recorder,
            record_path,
            recording_failed: None,
            faults: self.faults.clone(),
            state: self.state.clone(),
            durability: self.durability,
            saved_at: std::time::Instant::now(),
            unacked: Vec::new(),
            held: Vec::new(),
            batches: Batches::default(),
            waiting: std::collections::VecDeque::new(),
            workers: self.workers_per_sensor,
            snapshots: self.snapshots.clone(),
        };
        let watched = session.clone();
        let faults = self.faults.clone();
        let handle = std::thread::Builder::new()
            .name(thread_name(sensor))
            .spawn(move || {
                // Pipeline panics are caught per frame (`Worker::process`); one
                // anywhere else ends the worker. The sensor is then faulted, not
                // silently dead: its frames get a named refusal and health
                // says NOT_SERVING.
                let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| worker.run(rx)));
                if let Err(panic) = run {
                    let reason = format!("the sensor's worker stopped: {}", panic_message(panic.as_ref()));
                    watched.set_fault(reason, &faults);
                }
            })
            .map_err(|e| StartError::Build(format!("cannot start worker thread: {e}")))?;
        *lock(&session.worker) = Some(handle);
        map.insert(sensor.to_string(), session.clone());
        tracing::info!(sensor, "session started");
        Ok(session)
    }

    /// Registers an open ingest stream until the guard drops.
    pub fn ingest_guard(&self) -> IngestGuard<'_> {
        self.ingest_streams.send_modify(|n| *n += 1);
        IngestGuard(&self.ingest_streams)
    }

    /// Resolves when no ingest stream is open.
    pub async fn wait_ingest_idle(&self) {
        let mut rx = self.ingest_streams.subscribe();
        let _ = rx.wait_for(|n| *n == 0).await;
    }

    /// Closes every queue, lets the workers finish what is queued and flush,
    /// and saves noise models.
    pub async fn close_all(&self) -> Result<(), ServiceError> {
        let sessions = self.all();
        for s in &sessions {
            lock(&s.tx).take();
        }
        for s in &sessions {
            let handle = lock(&s.worker).take();
            if let Some(h) = handle {
                let _ = tokio::task::spawn_blocking(move || h.join()).await;
            }
        }
        // Scenes were saved when set; a sensor on the default scene keeps
        // following the default (a new --scene applies to it after a restart).
        if let Some(st) = &self.state {
            for s in &sessions {
                if let Some(n) = s.noise() {
                    st.save_noise(&s.sensor, &n)?;
                }
            }
        }
        Ok(())
    }
}

/// Now, ms since the Unix epoch (0 before it).
pub(crate) fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The worker thread's name: `tofwave-` and the sensor id reduced to ASCII
/// letters, digits, `-`, `_` and `.` (others become `_`), at most 24
/// characters. The OS refuses some names (a NUL byte; long names on some
/// platforms), and a refused name must never stop a session from starting.
fn thread_name(sensor: &str) -> String {
    let id: String = sensor
        .chars()
        .take(24)
        .map(|c| if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') { c } else { '_' })
        .collect();
    format!("tofwave-{id}")
}

/// A panic's message, when it carries one.
fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

type Recorder = RecordingWriter<std::io::BufWriter<std::fs::File>>;

fn open_recording(dir: &std::path::Path, sensor: &str) -> Result<(Recorder, PathBuf), String> {
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis());
    let path = dir.join(format!("{}-{stamp}.twr", super::state::file_stem(sensor)));
    let file = std::fs::File::create(&path)
        .map_err(|e| format!("cannot create recording {}: {e}", path.display()))?;
    let writer = RecordingWriter::new(std::io::BufWriter::new(file))
        .map_err(|e| format!("cannot start recording {}: {e}", path.display()))?;
    Ok((writer, path))
}

/// The blocking side of a session.
struct Worker {
    /// Counters and noise model to update.
    session: Arc<Session>,
    /// The running pipeline (its stages on `workers` threads once it has timed them).
    pipeline: Staged,
    /// Threads the pipeline may use.
    workers: usize,
    /// Frames in the pipeline, oldest first: when each was queued, and where its verdict goes.
    waiting: std::collections::VecDeque<(Instant, oneshot::Sender<Verdict>)>,
    /// Where reports go.
    hub: Arc<Hub>,
    /// Lossless copy of every accepted frame, when recording.
    recorder: Option<Recorder>,
    /// The recording's path (for messages).
    record_path: Option<PathBuf>,
    /// Why the recording failed, once it has: every frame from then on is
    /// refused ([`Verdict::Unrecorded`]).
    recording_failed: Option<String>,
    /// Wakes the health watcher when this sensor becomes faulted.
    faults: Arc<watch::Sender<u64>>,
    /// Where the noise model is saved periodically.
    state: Option<StateDir>,
    /// Record sync policy and persistence period.
    durability: Durability,
    /// When the noise model was last saved.
    saved_at: std::time::Instant,
    /// Verdicts held until [`release`](Worker::release): while frames are
    /// queued they go out in groups (one wake-up of the ingest stream per
    /// group, not per frame); when recording, an acknowledgement also
    /// means the frame is in the recording.
    unacked: Vec<(oneshot::Sender<Verdict>, Verdict)>,
    /// Reports held until [`release`](Worker::release), likewise (one
    /// wake-up of the subscribers per group).
    held: Vec<Report>,
    /// Which ingest batches have all their verdicts.
    batches: Batches,
    /// Dashboard snapshots: rebuilt pipelines get the observer again.
    snapshots: Option<Arc<Snapshots>>,
}

/// The ingest batches in a sensor's queue, by frame counts: frames taken
/// from the queue, frames with a verdict, and where each batch ended (the
/// count of frames taken before its end was).
#[derive(Debug, Default)]
struct Batches {
    taken: u64,
    done: u64,
    ends: std::collections::VecDeque<u64>,
}

impl Batches {
    /// A frame was taken from the queue.
    fn taken(&mut self) {
        self.taken += 1;
    }

    /// A frame's verdict is in (frames get theirs in the order taken).
    fn done(&mut self) {
        self.done += 1;
    }

    /// A batch's end was taken from the queue.
    fn end(&mut self) {
        self.ends.push_back(self.taken);
    }

    /// Whether the oldest batch not yet forgotten has every verdict in.
    fn one_done(&self) -> bool {
        self.ends.front().is_some_and(|&end| end <= self.done)
    }

    /// Forgets the batches whose verdicts are all in (they went out).
    fn forget_done(&mut self) {
        while self.one_done() {
            self.ends.pop_front();
        }
    }
}

/// Recorded frames held for one flush at most: under load the queue never
/// empties, and a flush per this many frames bounds the wait for an ack.
const ACKS_PER_FLUSH: usize = 256;

/// Frames whose reports and verdicts are held at most while more frames are
/// queued: under load each group wakes the subscribers' and the ingest
/// stream's tasks once, not once a frame; when the queue empties they go
/// out at once, so a sensor below capacity waits for nothing.
const HELD_PER_RELEASE: usize = 32;

impl Worker {
    fn run(mut self, mut rx: mpsc::Receiver<Job>) {
        let sensor = self.session.sensor.clone();
        let mut outcomes = Vec::new();
        while let Some(job) = rx.blocking_recv() {
            match job {
                Job::Frame {
                    frame,
                    enqueued,
                    done,
                } => {
                    if let Some(w) = &mut self.recorder
                        && let Err(e) = w.write_frame(&frame)
                    {
                        self.fail_recording(&e);
                    } else if self.recorder.is_some() {
                        self.session.metrics.frame_recorded();
                    }
                    self.batches.taken();
                    if let Some(reason) = &self.recording_failed {
                        self.session.rejected("recording");
                        self.unacked.push((done, Verdict::Unrecorded(reason.clone())));
                        self.batches.done();
                    } else {
                        self.waiting.push_back((enqueued, done));
                        self.pipeline.push(frame, &mut outcomes);
                    }
                    self.settle(&rx, &mut outcomes, &sensor);
                    self.session.metrics.queue_depth(rx.len());
                }
                Job::EndOfBatch => {
                    self.batches.end();
                    self.settle(&rx, &mut outcomes, &sensor);
                }
                Job::SetScene { scene, done } => {
                    // Every frame before the change finished first: whatever
                    // building the new pipeline says, none is left in flight.
                    self.pipeline.sync(&mut outcomes);
                    for o in outcomes.drain(..) {
                        self.complete(o, &sensor);
                    }
                    let result = self.build(&scene).map(|p| {
                        self.finish(&sensor);
                        // Out while the old pipeline's noise model is the one read.
                        self.publish_held();
                        self.pipeline = p;
                        tracing::info!(sensor = %sensor, scene = %scene.name, "scene applied");
                    });
                    self.release();
                    let _ = done.send(result);
                }
            }
        }
        self.finish(&sensor);
        self.release();
        if let Some(w) = self.recorder.take()
            && let Err(e) = w.finish()
        {
            tracing::error!(sensor = %sensor, error = %e, "recording not finished");
        }
        tracing::info!(sensor = %sensor, "session drained");
    }

    /// After a frame or a batch's end: with nothing more queued, the frames
    /// on the pipeline's threads are finished now rather than with later
    /// ones, unless a frame comes meanwhile (then the threads are fed
    /// first; the worker never waits for the queue with frames in flight
    /// and the queue empty). The outcomes are completed, and what is held
    /// goes out when due.
    fn settle(&mut self, rx: &mpsc::Receiver<Job>, outcomes: &mut Vec<Outcome>, sensor: &str) {
        if rx.is_empty() {
            self.pipeline.settle_while(|| rx.is_empty(), outcomes);
        }
        for o in outcomes.drain(..) {
            self.complete(o, sensor);
        }
        self.release_when_due(rx.is_empty());
    }

    /// Ends the pipeline: the outcomes of its frames, then what its flush
    /// completes (it takes no frames after this).
    fn finish(&mut self, sensor: &str) {
        let mut outcomes = Vec::new();
        let flushed = self.pipeline.finish(&mut outcomes);
        for o in outcomes {
            self.complete(o, sensor);
        }
        self.held.extend(flushed.reports);
    }

    /// One frame's outcome: counted, its reports and verdict held for
    /// [`release`](Self::release).
    fn complete(&mut self, outcome: Outcome, sensor: &str) {
        let Some((enqueued, done)) = self.waiting.pop_front() else {
            tracing::error!(sensor = %sensor, "an outcome with no frame waiting for it");
            return;
        };
        let verdict = match (outcome.panic, outcome.result) {
            (Some(m), _) => Verdict::Panicked(m),
            (None, Err(e)) => Verdict::Refused(e),
            (None, Ok(())) => Verdict::Processed,
        };
        match &verdict {
            Verdict::Processed => {
                let st = &self.session.stats;
                st.frames_processed.fetch_add(1, Ordering::Relaxed);
                let latency = enqueued.elapsed();
                st.last_latency_us.store(latency.as_micros() as u64, Ordering::Relaxed);
                st.last_processed_unix_ms.store(unix_ms(), Ordering::Relaxed);
                self.session.metrics.frame_processed(latency);
            }
            Verdict::Refused(e) => {
                self.session.rejected("pipeline");
                tracing::debug!(sensor = %sensor, error = %e, "pipeline refused frame");
            }
            Verdict::Panicked(m) => {
                self.session.rejected("panic");
                tracing::error!(sensor = %sensor, message = %m, "pipeline panicked; rebuilt");
            }
            // Only the recorder refuses this way (before the pipeline).
            Verdict::Unrecorded(_) => {}
        }
        self.held.extend(outcome.reports);
        // Saved before the ack, so an ack after the period means a saved model.
        self.persist_noise(false);
        self.unacked.push((done, verdict));
        self.batches.done();
    }

    /// Releases what is held when an ingest batch's frames all have their
    /// verdicts (not when recording), when the queue is empty and no frame
    /// is in the pipeline (`queue_empty`: the queue's state), or when a
    /// group is full; otherwise publishes the held reports once a group of
    /// them is in.
    fn release_when_due(&mut self, queue_empty: bool) {
        // Recording, each release flushes (and by policy syncs) the file:
        // once per ACKS_PER_FLUSH frames under load, not once per batch.
        let recording = self.recorder.is_some();
        let group = if recording { ACKS_PER_FLUSH } else { HELD_PER_RELEASE };
        let batch_done = !recording && self.batches.one_done();
        if batch_done || (queue_empty && self.waiting.is_empty()) || self.unacked.len() >= group {
            self.release();
        } else if self.held.len() >= HELD_PER_RELEASE {
            self.publish_held();
        }
    }

    /// A pipeline for `scene`, observed by the dashboard when there is one.
    fn build(&self, scene: &Scene) -> Result<Staged, String> {
        let mut p = Staged::new(scene, &self.session.sensor, self.workers);
        if let Some(s) = &self.snapshots {
            p.set_observer(s.observer());
        }
        Ok(p)
    }

    /// Publishes the held reports, then writes the recording through (and
    /// syncs it, by policy) and sends the held verdicts: an acknowledged
    /// frame's reports are out before its ack.
    fn release(&mut self) {
        self.batches.forget_done();
        self.publish_held();
        if self.unacked.is_empty() {
            return;
        }
        if let Some(w) = &mut self.recorder {
            let synced = w.flush().and_then(|()| match self.durability.record_sync {
                RecordSync::Flush => Ok(()),
                RecordSync::Fsync => w.get_ref().get_ref().sync_data(),
            });
            if let Err(e) = synced {
                // The held frames were processed and reported, but they are
                // not (all) in the recording: they are refused, not acked.
                self.fail_recording(&e);
                return;
            }
        }
        for (done, verdict) in self.unacked.drain(..) {
            let _ = done.send(verdict);
        }
    }

    /// The recording failed (a full disk, a file-size limit, an I/O error):
    /// an ack could no longer mean "recorded", so the held frames and every
    /// later one are refused with the reason, the sensor is faulted and
    /// health goes NOT_SERVING. The file keeps what reached it.
    fn fail_recording(&mut self, e: &dyn std::fmt::Display) {
        // The held frames' reports go out: they were processed.
        self.publish_held();
        let path = self
            .record_path
            .as_ref()
            .map_or_else(String::new, |p| format!(" {}", p.display()));
        let reason = format!(
            "recording{path} failed ({e}): frames of this sensor are not acknowledged until the server is restarted"
        );
        self.session.metrics.recording_failed();
        self.recorder = None;
        for (done, verdict) in self.unacked.drain(..) {
            let verdict = match verdict {
                Verdict::Processed => Verdict::Unrecorded(format!("processed and reported, but {reason}")),
                other => other,
            };
            let _ = done.send(verdict);
        }
        self.session.set_fault(reason.clone(), &self.faults);
        self.recording_failed = Some(reason);
    }

    /// Saves the noise model when the persistence period has passed (or
    /// `now`), atomically (see [`StateDir`]).
    fn persist_noise(&mut self, now: bool) {
        let Some(st) = &self.state else { return };
        if !now && self.saved_at.elapsed() < self.durability.persist_interval {
            return;
        }
        self.saved_at = std::time::Instant::now();
        // The latest model (the session's is refreshed as reports go out).
        self.share_noise();
        if let Some(n) = self.session.noise()
            && let Err(e) = st.save_noise(&self.session.sensor, &n)
        {
            tracing::warn!(sensor = %self.session.sensor, error = %e, "noise model not saved");
        }
    }

    /// The pipeline's latest noise model becomes the session's (what status
    /// reads and the state directory saves).
    fn share_noise(&self) {
        if let Some(n) = self.pipeline.noise_model() {
            *lock(&self.session.noise) = Some(n);
        }
    }

    /// Publishes the held reports (and the sensor's noise model with them).
    fn publish_held(&mut self) {
        self.share_noise();
        for r in &self.held {
            let st = &self.session.stats;
            st.reports.fetch_add(1, Ordering::Relaxed);
            st.returns
                .fetch_add(r.returns.len() as u64, Ordering::Relaxed);
            self.session.metrics.report_published(r.returns.len());
            self.session
                .metrics
                .false_alarm(r.false_alarm.rate, r.false_alarm.ci95, r.detector.pfa_cell);
        }
        self.hub.publish_all(self.held.drain(..));
    }
}

#[cfg(test)]
mod tests {
    use super::Batches;

    #[test]
    fn a_batch_is_done_once_its_own_frames_have_their_verdicts() {
        let mut b = Batches::default();
        assert!(!b.one_done(), "no batch yet");
        // Batch A: three frames; batch B: two, queued behind it.
        for _ in 0..3 {
            b.taken();
        }
        b.end();
        for _ in 0..2 {
            b.taken();
        }
        b.end();
        b.done();
        b.done();
        assert!(!b.one_done(), "A has a frame without its verdict");
        b.done();
        assert!(b.one_done(), "A's three frames are done; B's are not needed");
        b.forget_done();
        assert!(!b.one_done(), "A forgotten; B has none of its verdicts");
        b.done();
        assert!(!b.one_done());
        b.done();
        assert!(b.one_done());
        b.forget_done();
        assert!(!b.one_done());
        // Ends with no frame taken since the last (ingest sends none for a
        // batch without frames for the sensor, but they would be harmless):
        // each is done at once.
        b.end();
        b.end();
        assert!(b.one_done());
        b.forget_done();
        assert!(!b.one_done() && b.ends.is_empty());
    }
}
