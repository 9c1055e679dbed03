//! Report fan-out: one bounded broadcast channel for live reports, plus a
//! bounded per-sensor history for subscribers that resume from a sequence number.
//!
//! A subscriber that falls behind by more than the broadcast capacity loses
//! the oldest reports and is told how many ([`proto::Lagged`]); publishing
//! never waits for subscribers, so a slow one cannot slow ingestion or others.

use super::lock;
use crate::frame::Report;
use crate::pipeline::report_json;
use crate::wire::{proto, report_to_proto};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use tokio::sync::broadcast;

/// A report as published: the domain report and its JSON line.
#[derive(Debug)]
pub struct Published {
    /// The report (re-rendered when a subscriber filters returns by SNR).
    pub report: Report,
    /// `pipeline::report_json(&report)`.
    pub json: String,
    /// When it was published (server clock), ms since the Unix epoch: the
    /// dashboard measures how long a report takes to reach the screen.
    pub published_unix_ms: u64,
    /// The report as it came off the wire, for reports another cluster node
    /// processed (`serve --cluster`): then `report` holds only the sensor,
    /// sequence numbers, time and returns, and subscribers get this message.
    /// `None` for reports of this server's own pipelines.
    pub wire: Option<proto::Report>,
}

impl Published {
    /// The wire event for a subscriber keeping returns with SNR >= `min_snr_db`.
    pub fn event(&self, min_snr_db: Option<f64>) -> proto::ReportEvent {
        // A NaN SNR never passes a threshold.
        let keep = |snr_db: f64, min: f64| snr_db >= min;
        if let Some(w) = &self.wire {
            let mut msg = w.clone();
            if let Some(min) = min_snr_db
                && msg.returns.iter().any(|r| !keep(r.snr_db, min))
            {
                msg.returns.retain(|x| keep(x.snr_db, min));
                msg.json = filter_json_returns(&msg.json, min);
            }
            return proto::ReportEvent { event: Some(proto::report_event::Event::Report(msg)) };
        }
        let msg = match min_snr_db {
            Some(min) if self.report.returns.iter().any(|r| !keep(r.snr_db, min)) => {
                let mut r = self.report.clone();
                r.returns.retain(|x| keep(x.snr_db, min));
                let json = report_json(&r);
                report_to_proto(&r, json)
            }
            _ => report_to_proto(&self.report, self.json.clone()),
        };
        proto::ReportEvent {
            event: Some(proto::report_event::Event::Report(msg)),
        }
    }
}

/// A report's JSON line keeping only returns with `snr_db >= min` (a
/// `null`, non-finite SNR never passes), re-serialised: the same fields and
/// numbers, object keys in sorted order; a line that does not parse is kept.
fn filter_json_returns(json: &str, min: f64) -> String {
    let Ok(mut v) = serde_json::from_str::<serde_json::Value>(json) else {
        return json.to_string();
    };
    if let Some(returns) = v.get_mut("returns").and_then(|r| r.as_array_mut()) {
        returns.retain(|r| r.get("snr_db").and_then(|x| x.as_f64()).is_some_and(|x| x >= min));
    }
    serde_json::to_string(&v).unwrap_or_else(|_| json.to_string())
}

/// Reports [`Hub::publish_all`] renders and then sends together: a
/// subscriber whose buffer holds fewer may be told it lagged though it
/// keeps up.
pub const PUBLISH_GROUP: usize = 32;

/// Fan-out and history.
pub struct Hub {
    inner: Mutex<HubInner>,
}

struct HubInner {
    /// Live reports; `None` once closed (subscribers then drain and end).
    tx: Option<broadcast::Sender<Arc<Published>>>,
    /// Recent reports per sensor, oldest first.
    history: HashMap<String, VecDeque<Arc<Published>>>,
    /// Reports retained per sensor.
    history_cap: usize,
}

impl HubInner {
    /// Retains `p` for its sensor and sends it to the live subscribers.
    fn push(&mut self, p: Arc<Published>) {
        let cap = self.history_cap;
        if cap > 0 {
            let h = self.history.entry(p.report.sensor.clone()).or_default();
            if h.len() == cap {
                h.pop_front();
            }
            h.push_back(p.clone());
        }
        if let Some(tx) = &self.tx {
            // No receivers is fine: reports are still retained.
            let _ = tx.send(p);
        }
    }
}

/// A new subscription: live receiver plus the retained reports to send first.
pub struct Subscription {
    /// Live reports published after the backlog.
    pub live: broadcast::Receiver<Arc<Published>>,
    /// Retained reports matching the resume point, in publication order per sensor.
    pub backlog: Vec<Arc<Published>>,
}

impl Hub {
    /// `buffer`: reports a subscriber may fall behind before it lags;
    /// `history`: reports retained per sensor.
    pub fn new(buffer: usize, history: usize) -> Hub {
        let (tx, _) = broadcast::channel(buffer.max(1));
        Hub {
            inner: Mutex::new(HubInner {
                tx: Some(tx),
                history: HashMap::new(),
                history_cap: history,
            }),
        }
    }

    /// Publishes a report to live subscribers and the history.
    pub fn publish(&self, report: Report) {
        self.publish_all(std::iter::once(report));
    }

    /// Publishes reports in order, [`PUBLISH_GROUP`] at a time: each group
    /// rendered before the first of it is sent, so a subscriber's stream
    /// finds them together and gRPC sends them in one write, not one write
    /// per report as each is rendered. Nothing to publish takes no lock.
    pub fn publish_all(&self, reports: impl IntoIterator<Item = Report>) {
        let mut reports = reports.into_iter().peekable();
        let mut rendered = Vec::new();
        while reports.peek().is_some() {
            rendered.extend(reports.by_ref().take(PUBLISH_GROUP).map(|report| {
                let json = report_json(&report);
                Arc::new(Published {
                    report,
                    json,
                    published_unix_ms: super::session::unix_ms(),
                    wire: None,
                })
            }));
            let mut g = lock(&self.inner);
            for p in rendered.drain(..) {
                g.push(p);
            }
        }
    }

    /// Publishes a report already rendered (a cluster node's report read from NATS).
    pub fn publish_published(&self, p: Arc<Published>) {
        lock(&self.inner).push(p);
    }

    /// Subscribes; with `resume_from`, retained reports whose `seq_first` is at
    /// least that number (of the sensors `wanted` accepts) come first. Taking
    /// the backlog and the live receiver under one lock means no report is
    /// missed or sent twice. `None` once the hub is closed.
    pub fn subscribe(
        &self,
        resume_from: Option<u64>,
        wanted: impl Fn(&str) -> bool,
    ) -> Option<Subscription> {
        let g = lock(&self.inner);
        let live = g.tx.as_ref()?.subscribe();
        let mut backlog = Vec::new();
        if let Some(from) = resume_from {
            let mut sensors: Vec<_> = g.history.keys().filter(|s| wanted(s)).collect();
            sensors.sort();
            for s in sensors {
                backlog.extend(
                    g.history[s]
                        .iter()
                        .filter(|p| p.report.seq_first >= from)
                        .cloned(),
                );
            }
        }
        Some(Subscription { live, backlog })
    }

    /// Stops publishing: subscribers receive what is buffered, then their streams end.
    pub fn close(&self) {
        lock(&self.inner).tx.take();
    }
}
