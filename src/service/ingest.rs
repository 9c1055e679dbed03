//! `Ingest.Push`: frame batches in, one acknowledgement per batch out.
//!
//! Each frame is decoded and checked against its sensor's scene at the edge;
//! a bad frame becomes a [`proto::Rejection`] naming the field and the stream
//! carries on. Good frames go to their sensor's queue (waiting while it is
//! full: backpressure), and the batch is acknowledged once the pipeline has
//! processed them, so the counts in an ack are final. Frames of one sensor
//! keep their order: one stream queues them in order, and the worker processes
//! its queue in order.

use super::grpc;
use super::session::{QueueError, Session, StartError, Verdict};
use super::{Shared, status};
use crate::frame::{ChannelRole, Frame, channel_key, limits};
use crate::scene::Scene;
use crate::telemetry;
use crate::wire::{self, ConvertError, proto};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tokio::sync::{mpsc, oneshot, OwnedSemaphorePermit, Semaphore};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

/// Relative tolerance of the sample-interval check against the scene.
const SAMPLE_INTERVAL_TOLERANCE: f64 = 1e-6;

/// The Ingest service.
pub struct IngestService {
    shared: Arc<Shared>,
    /// The decoding limit, quoted in oversize errors.
    max_message_bytes: usize,
}

impl IngestService {
    pub(crate) fn new(shared: Arc<Shared>, max_message_bytes: usize) -> Self {
        IngestService {
            shared,
            max_message_bytes,
        }
    }
}

/// Why a frame was refused at the edge: metric label and message.
#[derive(Debug)]
pub(crate) struct EdgeRejection {
    /// Metric `reason` label.
    reason: &'static str,
    /// Field at fault (relative to the frame).
    field: String,
    /// What was wrong.
    message: String,
}

impl From<ConvertError> for EdgeRejection {
    fn from(e: ConvertError) -> Self {
        EdgeRejection {
            reason: "invalid_frame",
            field: e.field().to_string(),
            message: e.message().to_string(),
        }
    }
}

/// Checks a decoded frame against the scene its sensor runs: sample interval,
/// samples per frame and the presence of a stop channel.
pub(crate) fn check_against_scene(frame: &Frame, scene: &Scene) -> Result<(), EdgeRejection> {
    let want = scene.digitiser.sample_interval_s;
    if want > 0.0 && ((frame.sample_interval_s - want) / want).abs() > SAMPLE_INTERVAL_TOLERANCE {
        return Err(EdgeRejection {
            reason: "sample_rate",
            field: "sample_interval_s".into(),
            message: format!(
                "{} s does not match the scene's digitiser.sample_interval_s = {want} s",
                frame.sample_interval_s
            ),
        });
    }
    let n = scene.digitiser.samples_per_frame;
    if n > 0 && frame.len() != n {
        return Err(EdgeRejection {
            reason: "samples_per_frame",
            field: "channels[0].samples".into(),
            message: format!(
                "{} samples; the scene's digitiser.samples_per_frame is {n}",
                frame.len()
            ),
        });
    }
    // A stop channel: named as the scene says, marked STOP, or the only channel.
    let stop = channel_key(&scene.channels.stop);
    let has_stop = frame.channels.len() == 1
        || frame
            .channels
            .iter()
            .any(|c| c.role == ChannelRole::Stop || channel_key(&c.name) == stop);
    if !has_stop {
        return Err(EdgeRejection {
            reason: "missing_stop",
            field: "channels".into(),
            message: format!(
                "no stop channel: the scene's channels.stop is {:?} and no channel has role STOP; channels are {:?}",
                scene.channels.stop,
                frame.channel_names()
            ),
        });
    }
    Ok(())
}

/// Frames a stream may have taken in and not yet acknowledged: enough for a
/// sensor's queue and its pipeline's threads to stay fed while the acks of
/// the batches before travel back (a two-thread ring holds up to 136).
/// While a session records it holds its verdicts back for up to 256 frames
/// (`ACKS_PER_FLUSH`), so a single stream then waits for each such group's
/// acks.
const FRAMES_IN_FLIGHT: usize = 256;

/// Most of the window one batch takes: at least four batches overlap, however
/// large (frames in flight may then exceed [`FRAMES_IN_FLIGHT`]).
const FRAMES_PER_BATCH_PERMIT: usize = FRAMES_IN_FLIGHT / 4;

/// Batches a stream may have taken in and not yet acknowledged: each holds
/// at least one permit of the window, so the channel of pending batches
/// never fills.
const ACKS_IN_FLIGHT: usize = FRAMES_IN_FLIGHT;

/// What one stream has acknowledged so far.
#[derive(Default)]
struct StreamTotals {
    batches: u64,
    accepted: u64,
    rejected: u64,
    /// Of the rejected: refused because the server is shutting down.
    unavailable: u64,
}

#[tonic::async_trait]
impl grpc::ingest_server::Ingest for IngestService {
    type PushStream = ReceiverStream<Result<proto::IngestAck, Status>>;

    async fn push(
        &self,
        request: Request<Streaming<proto::FrameBatch>>,
    ) -> Result<Response<Self::PushStream>, Status> {
        let peer = request.remote_addr();
        let mut incoming = request.into_inner();
        let shared = self.shared.clone();
        let limit = self.max_message_bytes;
        let (tx, rx) = mpsc::channel(4);
        self.shared.tasks.spawn(async move {
            let _guard = shared.sessions.ingest_guard();
            if shared.shutdown.is_cancelled() {
                let _ = tx
                    .send(Err(Status::unavailable("server is shutting down")))
                    .await;
                return;
            }
            tracing::info!(?peer, "ingest stream opened");
            // Acks are finished by a second task, so the next batch is decoded
            // and queued while the pipeline works on this one. A batch takes
            // one permit of the window per frame (FRAMES_PER_BATCH_PERMIT at
            // most) before it is read into the queues and gives them back once
            // its ack is out: backpressure holds.
            let (pending_tx, mut pending_rx) = mpsc::channel::<(PendingBatch, OwnedSemaphorePermit)>(ACKS_IN_FLIGHT);
            let window = Arc::new(Semaphore::new(FRAMES_IN_FLIGHT));
            let ack_out = tx.clone();
            let acker = tokio::spawn(async move {
                let mut totals = StreamTotals::default();
                while let Some((batch, permit)) = pending_rx.recv().await {
                    let ack = finish_batch(batch, &mut totals).await;
                    let sent = ack_out.send(Ok(ack)).await;
                    drop(permit);
                    if sent.is_err() {
                        break;
                    }
                }
                totals
            });
            let mut failure = None;
            let mut cut_off = false;
            loop {
                let msg = tokio::select! {
                    biased;
                    _ = shared.shutdown.cancelled() => {
                        cut_off = true;
                        break;
                    }
                    m = incoming.message() => m,
                };
                match msg {
                    Ok(Some(batch)) => {
                        let frames = batch.frames.len().clamp(1, FRAMES_PER_BATCH_PERMIT) as u32;
                        let permit = window.clone().acquire_many_owned(frames).await.expect("the window is never closed");
                        let pending = start_batch(&shared, batch).await;
                        if pending_tx.send((pending, permit)).await.is_err() {
                            break;
                        }
                    }
                    Ok(None) => break,
                    Err(e) => {
                        failure = Some(status::ingest_stream(e, limit));
                        break;
                    }
                }
            }
            // Acks of every batch taken in go out before the stream ends.
            drop(pending_tx);
            // Frames the client already sent that this stream will not read
            // (counted as far as they have arrived, without waiting).
            let mut unread = 0u64;
            if cut_off {
                for _ in 0..256 {
                    match tokio::time::timeout(std::time::Duration::ZERO, incoming.message()).await {
                        Ok(Ok(Some(b))) => unread += b.frames.len() as u64,
                        _ => break,
                    }
                }
            }
            let totals = acker.await.unwrap_or_default();
            if failure.is_none() && (cut_off || totals.unavailable > 0) {
                // Ending with OK would tell the client everything was taken.
                failure = Some(Status::unavailable(format!(
                    "server is shutting down: {} frames not acknowledged ({} refused at shutdown, {unread} sent and not read; \
                     more may still be in flight); {} accepted and {} rejected in {} batches before",
                    totals.unavailable + unread,
                    totals.unavailable,
                    totals.accepted,
                    totals.rejected - totals.unavailable,
                    totals.batches
                )));
            }
            if let Some(status) = failure {
                tracing::warn!(?peer, %status, "ingest stream failed");
                let _ = tx.send(Err(status)).await;
            }
            tracing::info!(
                ?peer,
                batches = totals.batches,
                accepted = totals.accepted,
                rejected = totals.rejected,
                "ingest stream closed"
            );
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

/// A frame in flight: where it came from and the verdict to come.
struct Pending {
    index: usize,
    sensor: String,
    sequence: u64,
    outcome: Outcome,
}

/// What a frame in flight waits for.
enum Outcome {
    /// The local pipeline's verdict.
    Pipeline {
        session: Arc<Session>,
        verdict: oneshot::Receiver<Verdict>,
    },
    /// Cluster mode: JetStream's acknowledgement that the frame is stored.
    Persisted(async_nats::jetstream::context::PublishAckFuture),
}

/// A batch whose frames are queued: the ack so far (edge rejections, gaps)
/// and the pipeline verdicts still to come.
struct PendingBatch {
    ack: proto::IngestAck,
    pending: Vec<Pending>,
}

/// Decodes and checks a batch and queues its good frames (waiting while a
/// sensor's queue is full).
async fn start_batch(shared: &Shared, batch: proto::FrameBatch) -> PendingBatch {
    let mut ack = proto::IngestAck::default();
    let mut pending = Vec::with_capacity(batch.frames.len());
    for (index, msg) in batch.frames.iter().enumerate() {
        // An id the wire refuses (control characters, too long) is echoed and
        // labelled only in its bounded, escaped form.
        let sensor = limits::shown_sensor_id(&msg.sensor_id);
        let sensor_ok = limits::sensor_id_problem(&msg.sensor_id).is_none();
        let sequence = msg.sequence;
        let mut reject = |r: EdgeRejection, session: Option<&Session>| {
            match session {
                Some(s) => {
                    s.metrics.frames_rejected(r.reason, 1);
                    s.stats.frames_rejected.fetch_add(1, Ordering::Relaxed);
                }
                None => telemetry::frames_rejected(if sensor_ok { &sensor } else { "" }, r.reason, 1),
            }
            ack.rejections.push(proto::Rejection {
                sensor_id: sensor.clone(),
                sequence,
                code: "INVALID_ARGUMENT".into(),
                message: format!("frames[{index}].{}: {}", r.field, r.message),
            });
        };
        if sensor.is_empty() {
            reject(
                EdgeRejection {
                    reason: "invalid_frame",
                    field: "sensor_id".into(),
                    message: "empty; every frame names its sensor".into(),
                },
                None,
            );
            continue;
        }
        // Checked before a session exists: the id names its thread, files and metrics.
        if let Err(e) = wire::check_sensor_id(&msg.sensor_id) {
            reject(e.into(), None);
            continue;
        }
        if let Some(cluster) = &shared.cluster {
            // Cluster mode: checked against the scene every node runs, then
            // stored in JetStream; the sensor's owner node processes it.
            telemetry::frame_received(&sensor);
            let checked = wire::frame_from_proto(msg)
                .map_err(EdgeRejection::from)
                .and_then(|f| check_against_scene(&f, &shared.sessions.default_scene()));
            if let Err(r) = checked {
                reject(r, None);
                continue;
            }
            match cluster.publish_frame(&sensor, prost::Message::encode_to_vec(msg).into()).await {
                Ok(ack) => pending.push(Pending { index, sensor, sequence, outcome: Outcome::Persisted(ack) }),
                Err(message) => {
                    reject(EdgeRejection { reason: "cluster", field: "sensor_id".into(), message }, None);
                    if let Some(r) = ack.rejections.last_mut() {
                        r.code = "UNAVAILABLE".into();
                    }
                }
            }
            continue;
        }
        let session = match shared.sessions.get_or_start(&sensor) {
            Ok(s) => {
                s.metrics.frame_received();
                s
            }
            Err(e) => {
                telemetry::frame_received(&sensor);
                let (reason, code) = match e {
                    StartError::Limit(_) => ("sensor_limit", "RESOURCE_EXHAUSTED"),
                    StartError::Build(_) => ("pipeline", "INTERNAL"),
                };
                let message = e.to_string();
                reject(
                    EdgeRejection {
                        reason,
                        field: "sensor_id".into(),
                        message,
                    },
                    None,
                );
                if let Some(r) = ack.rejections.last_mut() {
                    r.code = code.into();
                }
                continue;
            }
        };
        session
            .stats
            .frames_received
            .fetch_add(1, Ordering::Relaxed);
        if let Some((first_missing, count)) = session.observe_sequence(sequence) {
            ack.gaps.push(proto::SequenceGap {
                sensor_id: sensor.clone(),
                first_missing,
                count,
            });
        }
        let frame = match wire::frame_from_proto(msg)
            .map_err(EdgeRejection::from)
            .and_then(|f| check_against_scene(&f, &session.scene()).map(|()| f))
        {
            Ok(f) => f,
            Err(r) => {
                reject(r, Some(&session));
                continue;
            }
        };
        match session.enqueue(frame).await {
            Ok(verdict) => pending.push(Pending {
                index,
                sensor,
                sequence,
                outcome: Outcome::Pipeline { session, verdict },
            }),
            Err(e) => {
                let (reason, code) = match &e {
                    QueueError::Closed => ("shutdown", "UNAVAILABLE"),
                    QueueError::Faulted(_) => ("fault", "FAILED_PRECONDITION"),
                };
                reject(
                    EdgeRejection {
                        reason,
                        field: "sensor_id".into(),
                        message: e.to_string(),
                    },
                    Some(&session),
                );
                if let Some(r) = ack.rejections.last_mut() {
                    r.code = code.into();
                }
            }
        }
    }
    // The end of the batch: each sensor it fed sends its held verdicts (and
    // reports) now, so the batch's ack waits for its own frames only.
    let mut fed: Vec<&Arc<Session>> = Vec::new();
    for p in &pending {
        if let Outcome::Pipeline { session, .. } = &p.outcome
            && !fed.iter().any(|s| Arc::ptr_eq(s, session))
        {
            fed.push(session);
        }
    }
    for s in fed {
        s.end_of_batch().await;
    }
    PendingBatch { ack, pending }
}

/// Waits for the pipeline's verdicts and completes the ack.
async fn finish_batch(batch: PendingBatch, totals: &mut StreamTotals) -> proto::IngestAck {
    let PendingBatch { mut ack, pending } = batch;
    for p in pending {
        let internal = |message: String| proto::Rejection {
            sensor_id: p.sensor.clone(),
            sequence: p.sequence,
            code: "INTERNAL".into(),
            message,
        };
        let (session, verdict) = match p.outcome {
            Outcome::Pipeline { session, verdict } => (session, verdict),
            Outcome::Persisted(stored) => {
                match stored.await {
                    Ok(_) => ack.accepted += 1,
                    Err(e) => {
                        telemetry::frames_rejected(&p.sensor, "cluster", 1);
                        ack.rejections.push(proto::Rejection {
                            sensor_id: p.sensor.clone(),
                            sequence: p.sequence,
                            code: "UNAVAILABLE".into(),
                            message: format!("frames[{}]: not persisted: JetStream did not acknowledge it ({e})", p.index),
                        });
                    }
                }
                continue;
            }
        };
        match verdict.await {
            Ok(Verdict::Processed) => ack.accepted += 1,
            Ok(Verdict::Refused(e)) => ack.rejections.push(proto::Rejection {
                sensor_id: p.sensor.clone(),
                sequence: p.sequence,
                code: "INVALID_ARGUMENT".into(),
                message: format!("frames[{}].{}: {}", p.index, e.field, e.message),
            }),
            Ok(Verdict::Panicked(m)) => ack.rejections.push(internal(format!(
                "frames[{}]: the pipeline failed on this frame ({m}); it was rebuilt",
                p.index
            ))),
            Ok(Verdict::Unrecorded(m)) => ack.rejections.push(proto::Rejection {
                sensor_id: p.sensor.clone(),
                sequence: p.sequence,
                code: "FAILED_PRECONDITION".into(),
                message: format!("frames[{}]: {m}", p.index),
            }),
            // The worker is gone (it cannot answer): not processed.
            Err(_) => {
                session.metrics.frames_rejected("pipeline", 1);
                session
                    .stats
                    .frames_rejected
                    .fetch_add(1, Ordering::Relaxed);
                ack.rejections.push(internal(format!(
                    "frames[{}]: the sensor's pipeline stopped",
                    p.index
                )));
            }
        }
    }
    ack.rejected = ack.rejections.len() as u64;
    totals.unavailable += ack.rejections.iter().filter(|r| r.code == "UNAVAILABLE").count() as u64;
    totals.batches += 1;
    totals.accepted += ack.accepted;
    totals.rejected += ack.rejected;
    ack.batch = totals.batches;
    ack.total_accepted = totals.accepted;
    ack.total_rejected = totals.rejected;
    ack
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{Channel, Samples};

    fn frame(names: &[(&str, ChannelRole)], n: usize, dt: f64) -> Frame {
        Frame {
            sensor_id: "s".into(),
            sequence: 0,
            trigger_time_s: 0.0,
            sample_interval_s: dt,
            first_sample_offset_s: 0.0,
            channels: names
                .iter()
                .map(|(name, role)| Channel {
                    name: name.to_string(),
                    role: *role,
                    samples: Samples::I16(vec![0; n]),
                    volts_per_code: 1e-3,
                    offset_v: 0.0,
                })
                .collect(),
            laser_off: false,
        }
    }

    #[test]
    fn scene_checks_name_the_field() {
        let mut scene = Scene::default_scene();
        scene.digitiser.sample_interval_s = 1e-9;
        scene.digitiser.samples_per_frame = 100;
        let u = ChannelRole::Unspecified;
        let ok = frame(&[("CH1", u), ("C2", u)], 100, 1e-9);
        assert!(
            check_against_scene(&ok, &scene).is_ok(),
            "vendor spelling C2 is CH2"
        );
        // Within the 1e-6 relative tolerance.
        assert!(
            check_against_scene(&frame(&[("CH2", u)], 100, 1e-9 * (1.0 + 5e-7)), &scene).is_ok()
        );
        let r = check_against_scene(&frame(&[("CH2", u)], 100, 1.001e-9), &scene).unwrap_err();
        assert_eq!(
            (r.reason, r.field.as_str()),
            ("sample_rate", "sample_interval_s")
        );
        let r = check_against_scene(&frame(&[("CH2", u)], 99, 1e-9), &scene).unwrap_err();
        assert_eq!(
            (r.reason, r.field.as_str()),
            ("samples_per_frame", "channels[0].samples")
        );
        let r =
            check_against_scene(&frame(&[("CH1", u), ("CH3", u)], 100, 1e-9), &scene).unwrap_err();
        assert_eq!((r.reason, r.field.as_str()), ("missing_stop", "channels"));
        // A STOP role or a single channel is a stop channel whatever its name.
        let roles = frame(&[("CH1", u), ("rx", ChannelRole::Stop)], 100, 1e-9);
        assert!(check_against_scene(&roles, &scene).is_ok());
        assert!(check_against_scene(&frame(&[("rx", u)], 100, 1e-9), &scene).is_ok());
    }
}
