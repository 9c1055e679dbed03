//! `Reports.Subscribe`: a filtered view of the fan-out per subscriber.

use super::fanout::Hub;
use super::{Shared, grpc};
use crate::telemetry;
use crate::wire::proto;
use std::collections::HashSet;
use std::sync::Arc;
use std::pin::Pin;
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status};

/// The Reports service.
pub struct ReportsService {
    shared: Arc<Shared>,
}

impl ReportsService {
    pub(crate) fn new(shared: Arc<Shared>) -> Self {
        ReportsService { shared }
    }
}

/// Stream of events for one subscriber: gRPC polls the fan-out's receiver
/// itself, so the reports waiting there when it polls go out in one write.
pub type EventStream = Pin<Box<dyn Stream<Item = Result<proto::ReportEvent, Status>> + Send>>;

#[tonic::async_trait]
impl grpc::reports_server::Reports for ReportsService {
    type SubscribeStream = EventStream;

    async fn subscribe(
        &self,
        request: Request<proto::SubscribeRequest>,
    ) -> Result<Response<Self::SubscribeStream>, Status> {
        let req = request.into_inner();
        if let Some(m) = req.min_snr_db
            && !m.is_finite()
        {
            return Err(Status::invalid_argument(format!(
                "min_snr_db: {m} is not a finite number of dB"
            )));
        }
        tracing::info!(sensors = ?req.sensor_ids, min_snr_db = ?req.min_snr_db,
            resume = ?req.resume_from_sequence, "subscriber joined");
        subscription_stream(&self.shared.hub, &req)
            .map(Response::new)
            .ok_or_else(|| Status::unavailable("server is shutting down"))
    }
}

/// One subscription's events: the retained reports asked for, then the live
/// ones `req` wants, each filtered by SNR; a lag marker where the subscriber
/// fell more than the fan-out's buffer behind. The stream ends (cleanly)
/// when the hub closes at shutdown, after the last reports, and is dropped
/// when the client goes away; `None` when the hub is already closed.
pub(crate) fn subscription_stream(hub: &Hub, req: &proto::SubscribeRequest) -> Option<EventStream> {
    let sensors: HashSet<String> = req.sensor_ids.iter().cloned().collect();
    let wanted = move |s: &str| sensors.is_empty() || sensors.contains(s);
    let sub = hub.subscribe(req.resume_from_sequence, &wanted)?;
    let min_snr_db = req.min_snr_db;
    let joined = Joined::new();
    let live = BroadcastStream::new(sub.live).filter_map(move |event| {
        let _counted = &joined;
        match event {
            Ok(p) => wanted(&p.report.sensor).then(|| p.event(min_snr_db)),
            Err(BroadcastStreamRecvError::Lagged(skipped)) => {
                telemetry::subscriber_lagged(skipped);
                tracing::warn!(skipped, "subscriber lagged");
                Some(proto::ReportEvent {
                    event: Some(proto::report_event::Event::Lagged(proto::Lagged { skipped })),
                })
            }
        }
    });
    let backlog = tokio_stream::iter(sub.backlog).map(move |p| p.event(min_snr_db));
    Some(Box::pin(backlog.chain(live).map(Ok)))
}

/// Counts a subscriber while its stream lives.
struct Joined;

impl Joined {
    fn new() -> Joined {
        telemetry::subscribers_changed(1.0);
        Joined
    }
}

impl Drop for Joined {
    fn drop(&mut self) {
        telemetry::subscribers_changed(-1.0);
        tracing::info!("subscriber left");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{Report, Return};

    fn report(sensor: &str, seq: u64, snrs: &[f64]) -> Report {
        Report {
            sensor: sensor.into(),
            seq_first: seq,
            seq_last: seq,
            frames_averaged: 1,
            returns: snrs
                .iter()
                .map(|&s| Return {
                    snr_db: s,
                    range_m: s,
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    fn req(sensors: &[&str], min: Option<f64>, resume: Option<u64>) -> proto::SubscribeRequest {
        proto::SubscribeRequest {
            sensor_ids: sensors.iter().map(|s| s.to_string()).collect(),
            min_snr_db: min,
            resume_from_sequence: resume,
        }
    }

    async fn collect(mut s: EventStream) -> Vec<proto::report_event::Event> {
        let mut v = Vec::new();
        while let Some(e) = s.next().await {
            v.push(e.unwrap().event.unwrap());
        }
        v
    }

    fn seqs(events: &[proto::report_event::Event]) -> Vec<(String, u64)> {
        events
            .iter()
            .filter_map(|e| match e {
                proto::report_event::Event::Report(r) => Some((r.sensor.clone(), r.seq_first)),
                _ => None,
            })
            .collect()
    }

    #[tokio::test]
    async fn slow_subscriber_gets_lag_marker_then_continues() {
        let hub = Hub::new(4, 0);
        let stream = subscription_stream(&hub, &req(&[], None, None)).unwrap();
        // The broadcast keeps 4 and nothing reads it while 100 are published.
        for i in 0..100 {
            hub.publish(report("a", i, &[]));
            tokio::task::yield_now().await;
        }
        hub.close();
        let events = collect(stream).await;
        let skipped: u64 = events
            .iter()
            .map(|e| match e {
                proto::report_event::Event::Lagged(l) => l.skipped,
                _ => 0,
            })
            .sum();
        let got = seqs(&events);
        assert!(skipped > 0, "no lag marker in {events:?}");
        assert_eq!(
            got.len() as u64 + skipped,
            100,
            "every report is delivered or counted as skipped"
        );
        // Delivered reports keep their order and the last ones arrive after the marker.
        assert!(got.windows(2).all(|w| w[0].1 < w[1].1));
        assert_eq!(got.last().unwrap().1, 99);
    }

    #[tokio::test]
    async fn reports_published_together_arrive_in_order_and_are_retained() {
        let hub = Hub::new(256, 40);
        let live = subscription_stream(&hub, &req(&[], None, None)).unwrap();
        // Three groups' worth (32 at a time), then nothing.
        hub.publish_all((0..70).map(|i| report("a", i, &[])));
        hub.publish_all(std::iter::empty());
        let resumed = subscription_stream(&hub, &req(&[], None, Some(0))).unwrap();
        hub.close();
        let seq = |events: Vec<proto::report_event::Event>| seqs(&events).into_iter().map(|x| x.1).collect::<Vec<u64>>();
        assert_eq!(seq(collect(live).await), (0..70).collect::<Vec<u64>>());
        assert_eq!(seq(collect(resumed).await), (30..70).collect::<Vec<u64>>(), "the history keeps the last 40");
    }

    #[tokio::test]
    async fn filters_by_sensor_and_snr() {
        let hub = Hub::new(64, 0);
        let stream = subscription_stream(&hub, &req(&["b"], Some(10.0), None)).unwrap();
        hub.publish(report("a", 0, &[20.0]));
        hub.publish(report("b", 1, &[5.0, 12.0]));
        hub.close();
        let events = collect(stream).await;
        assert_eq!(events.len(), 1);
        let proto::report_event::Event::Report(r) = &events[0] else {
            panic!("{events:?}")
        };
        assert_eq!(r.sensor, "b");
        assert_eq!(r.returns.len(), 1);
        assert_eq!(r.returns[0].snr_db, 12.0);
        let json: serde_json::Value = serde_json::from_str(&r.json).unwrap();
        assert_eq!(
            json["returns"].as_array().unwrap().len(),
            1,
            "JSON is filtered too"
        );
    }

    #[tokio::test]
    async fn resume_replays_history_without_duplicates() {
        let hub = Hub::new(64, 3);
        for i in 0..5 {
            hub.publish(report("a", i, &[]));
        }
        let stream = subscription_stream(&hub, &req(&[], None, Some(3))).unwrap();
        hub.publish(report("a", 5, &[]));
        hub.close();
        let got: Vec<u64> = seqs(&collect(stream).await)
            .into_iter()
            .map(|x| x.1)
            .collect();
        // History holds 2, 3, 4 (cap 3); resume from 3 gives 3, 4, then live 5.
        assert_eq!(got, vec![3, 4, 5]);
    }
}
