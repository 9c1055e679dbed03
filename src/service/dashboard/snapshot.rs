//! Waveform snapshots for the dashboard: the stop channel, the detector
//! output, the gates, the threshold and the detections of one finished unit
//! of work, decimated to at most [`MAX_POINTS`] values per trace.
//!
//! Cost is paid only while someone looks: a sensor's pipeline observer reads
//! one atomic counter per frame and returns at once when no dashboard client
//! is connected; with clients it takes at most `per_second` snapshots per
//! sensor (a clock read per frame, an O(samples) pass and one JSON rendering
//! per snapshot, shared by every client).

use super::super::lock;
use crate::pipeline::{Observer, Work};
use serde::Serialize;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::broadcast;

/// Values per trace at most: `MAX_POINTS / 2` buckets of (min, max), or the
/// samples themselves when there are no more than this many.
pub const MAX_POINTS: usize = 1000;

/// Snapshots buffered for dashboard clients before a slow one skips some.
const SNAPSHOT_BUFFER: usize = 64;

/// One snapshot, rendered once for every client.
#[derive(Debug)]
pub struct Snapshot {
    /// Sensor id.
    pub sensor: String,
    /// The snapshot as JSON (the `waveform` event's data).
    pub json: String,
}

/// Where sensors' observers leave snapshots and dashboard clients pick them up.
pub struct Snapshots {
    /// Dashboard clients connected now; 0 turns every observer into one atomic load.
    watchers: AtomicUsize,
    /// Shortest spacing of two snapshots of one sensor; `None`: never.
    min_interval: Option<Duration>,
    /// Live snapshots to connected clients.
    tx: broadcast::Sender<Arc<Snapshot>>,
    /// Latest snapshot per sensor, for clients that connect later.
    latest: Mutex<HashMap<String, Arc<Snapshot>>>,
    /// Snapshots taken since start (for tests and the bench).
    taken: AtomicU64,
}

/// A connected client: counted in `watchers` until dropped.
pub struct Watch {
    snapshots: Arc<Snapshots>,
    /// Live snapshots.
    pub live: broadcast::Receiver<Arc<Snapshot>>,
}

impl Drop for Watch {
    fn drop(&mut self) {
        self.snapshots.watchers.fetch_sub(1, Ordering::Relaxed);
    }
}

impl Snapshots {
    /// At most `per_second` snapshots per sensor (0: none).
    pub fn new(per_second: f64) -> Arc<Snapshots> {
        let min_interval = (per_second > 0.0 && per_second.is_finite())
            .then(|| Duration::from_secs_f64(1.0 / per_second));
        let (tx, _) = broadcast::channel(SNAPSHOT_BUFFER);
        Arc::new(Snapshots {
            watchers: AtomicUsize::new(0),
            min_interval,
            tx,
            latest: Mutex::new(HashMap::new()),
            taken: AtomicU64::new(0),
        })
    }

    /// Registers a client: its live receiver, plus the latest snapshot of every sensor.
    pub fn watch(self: &Arc<Self>) -> (Watch, Vec<Arc<Snapshot>>) {
        self.watchers.fetch_add(1, Ordering::Relaxed);
        let live = self.tx.subscribe();
        let mut latest: Vec<_> = lock(&self.latest).values().cloned().collect();
        latest.sort_by(|a, b| a.sensor.cmp(&b.sensor));
        (
            Watch {
                snapshots: self.clone(),
                live,
            },
            latest,
        )
    }

    /// Dashboard clients connected now.
    pub fn watchers(&self) -> usize {
        self.watchers.load(Ordering::Relaxed)
    }

    /// Snapshots taken since start, all sensors.
    pub fn taken(&self) -> u64 {
        self.taken.load(Ordering::Relaxed)
    }

    /// The pipeline observer of one sensor.
    pub fn observer(self: &Arc<Self>) -> Observer {
        let snapshots = self.clone();
        let mut next_at: Option<Instant> = None;
        Box::new(move |w: &Work| {
            if snapshots.watchers.load(Ordering::Relaxed) == 0 {
                return;
            }
            let Some(interval) = snapshots.min_interval else {
                return;
            };
            let now = Instant::now();
            if next_at.is_some_and(|t| now < t) {
                return;
            }
            next_at = Some(now + interval);
            snapshots.publish(w);
        })
    }

    fn publish(&self, w: &Work) {
        let snap = Arc::new(Snapshot {
            sensor: w.report.sensor.clone(),
            json: snapshot_json(w, MAX_POINTS),
        });
        self.taken.fetch_add(1, Ordering::Relaxed);
        lock(&self.latest).insert(snap.sensor.clone(), snap.clone());
        // No receivers (the last client just left) is fine.
        let _ = self.tx.send(snap);
    }
}

/// A trace reduced to at most `max_points` values: `bucket` consecutive
/// samples become their minimum (`lo`) and maximum (`hi`), so a peak one
/// sample wide still shows; with `bucket == 1` `hi` is absent (= `lo`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Decimated {
    /// Samples per bucket.
    pub bucket: usize,
    /// Minimum of each bucket (the samples when `bucket == 1`).
    pub lo: Vec<f32>,
    /// Maximum of each bucket; absent when `bucket == 1`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hi: Option<Vec<f32>>,
}

/// Min/max decimation of `x` (times `scale`) to at most `max_points` values.
/// NaN samples are skipped within a bucket (a bucket of NaN only is NaN).
pub fn decimate(x: &[f64], scale: f64, max_points: usize) -> Decimated {
    let max_points = max_points.max(2);
    if x.len() <= max_points {
        return Decimated {
            bucket: 1,
            lo: x.iter().map(|v| (v * scale) as f32).collect(),
            hi: None,
        };
    }
    let buckets = max_points / 2;
    let bucket = x.len().div_ceil(buckets);
    let (mut lo, mut hi) = (Vec::with_capacity(buckets), Vec::with_capacity(buckets));
    for chunk in x.chunks(bucket) {
        let (mut a, mut b) = (f64::INFINITY, f64::NEG_INFINITY);
        for &v in chunk {
            let v = v * scale;
            a = a.min(v);
            b = b.max(v);
        }
        let (a, b) = if a > b { (f64::NAN, f64::NAN) } else { (a, b) };
        lo.push(a as f32);
        hi.push(b as f32);
    }
    Decimated {
        bucket,
        lo,
        hi: Some(hi),
    }
}

#[derive(Serialize)]
struct SnapshotJson<'a> {
    sensor: &'a str,
    seq_first: u64,
    seq_last: u64,
    frames_averaged: u32,
    /// When the snapshot was taken (server clock), ms since the Unix epoch.
    taken_unix_ms: f64,
    /// Time of sample 0 relative to the trigger, s.
    t0_s: f64,
    /// Sampling period, s.
    dt_s: f64,
    /// Samples of the stop channel.
    samples: usize,
    /// Time reference (start pulse or trigger + offset) relative to the trigger, s.
    t_ref_s: f64,
    /// Stop channel, volts.
    stop_v: Decimated,
    /// Detector output in units of its noise sigma (mean removed).
    detector_sigma: Decimated,
    /// Threshold in the same units; absent without a noise estimate.
    threshold_sigma: Option<f64>,
    mean_v: f64,
    sigma_v: f64,
    /// Sample ranges [start, end): the range gate (peak positions) and the noise gates.
    gates: Gates,
    /// Sample ranges the noise model was fitted on.
    quiet: Vec<[usize; 2]>,
    /// Detected peak positions (sample indices).
    detections: &'a [usize],
    returns: Vec<ReturnMark>,
}

#[derive(Serialize)]
struct Gates {
    range: [usize; 2],
    pre: [usize; 2],
    beyond: [usize; 2],
}

#[derive(Serialize)]
struct ReturnMark {
    t_stop_s: f64,
    t_peak_s: f64,
    amplitude_v: f64,
    range_m: f64,
    range_sigma_m: f64,
    snr_db: f64,
}

/// Renders the snapshot of a finished unit of work.
fn snapshot_json(w: &Work, max_points: usize) -> String {
    let sigma_out = w.noise.sigma_v * w.threshold.out_gain;
    let usable = sigma_out > 0.0 && sigma_out.is_finite() && w.noise.summary.samples >= 2;
    let scale = if usable { 1.0 / sigma_out } else { 1.0 };
    let r = |g: &std::ops::Range<usize>| [g.start, g.end];
    let taken_unix_ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1e3);
    let s = SnapshotJson {
        sensor: &w.report.sensor,
        seq_first: w.report.seq_first,
        seq_last: w.report.seq_last,
        frames_averaged: w.report.frames_averaged,
        taken_unix_ms,
        t0_s: w.frame.first_sample_offset_s,
        dt_s: w.frame.sample_interval_s,
        samples: w.buffers.stop_v.len(),
        t_ref_s: w.reference.t_ref_s,
        stop_v: decimate(&w.buffers.stop_v, 1.0, max_points),
        detector_sigma: decimate(&w.buffers.detector_output, scale, max_points),
        threshold_sigma: (usable && w.threshold.u.is_finite()).then_some(w.threshold.u),
        mean_v: w.noise.summary.mean_v,
        sigma_v: w.noise.summary.sigma_v,
        gates: Gates {
            range: r(&w.noise.gates.range),
            pre: r(&w.noise.gates.pre),
            beyond: r(&w.noise.gates.beyond),
        },
        quiet: w.buffers.quiet.iter().map(r).collect(),
        detections: &w.buffers.detections,
        returns: w
            .report
            .returns
            .iter()
            .map(|x| ReturnMark {
                t_stop_s: x.t_stop_s,
                t_peak_s: x.t_peak_s,
                amplitude_v: x.amplitude_v,
                range_m: x.range_m,
                range_sigma_m: x.range_sigma_m,
                snr_db: x.snr_db,
            })
            .collect(),
    };
    serde_json::to_string(&s).expect("snapshots always serialise")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Naive reference: bucket k's min and max by index arithmetic.
    #[test]
    fn decimation_keeps_every_extreme() {
        let x: Vec<f64> = (0..10_007)
            .map(|i| ((i * 7919) % 1013) as f64 - 500.0)
            .collect();
        let d = decimate(&x, 2.0, 1000);
        let hi = d.hi.as_ref().unwrap();
        assert!(d.lo.len() + hi.len() <= 1000, "{} values", d.lo.len() * 2);
        assert_eq!(d.bucket, 10_007usize.div_ceil(500));
        for (k, (lo, hi)) in d.lo.iter().zip(hi).enumerate() {
            let s = &x[k * d.bucket..((k + 1) * d.bucket).min(x.len())];
            let mn = s.iter().cloned().fold(f64::INFINITY, f64::min) * 2.0;
            let mx = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max) * 2.0;
            assert_eq!((*lo, *hi), (mn as f32, mx as f32), "bucket {k}");
        }
        // A one-sample spike survives decimation.
        let mut y = vec![0.0; 5000];
        y[2345] = 9.0;
        let d = decimate(&y, 1.0, 1000);
        assert_eq!(d.hi.unwrap().iter().filter(|&&v| v == 9.0).count(), 1);
    }

    #[test]
    fn short_traces_are_sent_as_they_are() {
        let x = [1.0, 2.0, f64::NAN];
        let d = decimate(&x, 1.0, 1000);
        assert_eq!(d.bucket, 1);
        assert_eq!(d.lo[..2], [1.0, 2.0]);
        assert!(d.lo[2].is_nan() && d.hi.is_none());
    }

    #[test]
    fn observer_costs_nothing_unwatched_and_is_rate_limited() {
        let snaps = Snapshots::new(5.0);
        let mut obs = snaps.observer();
        let mut w = Work {
            frame: crate::frame::Frame::empty(),
            source: crate::pipeline::Source {
                stop: 0,
                start: None,
                seq_last: 0,
                frames_averaged: 1,
                clip_v: None,
                lsb_v: 0.0,
            },
            buffers: Default::default(),
            reference: Default::default(),
            noise: Default::default(),
            threshold: Default::default(),
            report: Default::default(),
        };
        w.report.sensor = "a".into();
        w.buffers.stop_v = vec![0.0; 3000];
        w.buffers.detector_output = vec![0.0; 3000];
        for _ in 0..100 {
            obs(&w);
        }
        assert_eq!(snaps.taken(), 0, "no client: no snapshot");
        let (watch, latest) = snaps.watch();
        assert!(latest.is_empty());
        for _ in 0..100 {
            obs(&w);
        }
        // 100 back-to-back frames fall inside one 200 ms interval.
        assert_eq!(snaps.taken(), 1);
        drop(watch);
        assert_eq!(snaps.watchers(), 0);
        let (_w, latest) = snaps.watch();
        assert_eq!(latest.len(), 1, "a late client gets the latest snapshot");
        let v: serde_json::Value = serde_json::from_str(&latest[0].json).unwrap();
        assert_eq!(v["sensor"], "a");
        assert_eq!(v["stop_v"]["lo"].as_array().unwrap().len(), 500);
    }
}
