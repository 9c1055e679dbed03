//! The soak run at a small size: a real `tofwave serve` child, 8 sensors,
//! bad frames, stalling and reconnecting subscribers, one `kill -9` midway
//! and a restart on the same state and recording directories; every frame is
//! accounted for exactly. Nothing here depends on timing.

use std::time::Duration;
use tofwave::bench::{SoakConfig, SoakReport, run_soak};

/// One soak run shared by the tests of this file: two servers soaking at
/// once on two cores starved each other (a subscriber found no server in
/// 30 s), and one run answers both questions.
fn small_soak() -> &'static SoakReport {
    static REPORT: std::sync::OnceLock<SoakReport> = std::sync::OnceLock::new();
    REPORT.get_or_init(run_small_soak)
}

fn run_small_soak() -> SoakReport {
    let mut cfg = SoakConfig::new(env!("CARGO_BIN_EXE_tofwave").into());
    cfg.frames = 2000;
    cfg.sensors = 8;
    // 250 frames per sensor: 5 bad ones each, all three kinds.
    cfg.bad_every = 50;
    cfg.batch_frames = 16;
    cfg.kill_at = 0.5;
    cfg.read_phase = Duration::from_millis(100);
    cfg.stall_phase = Duration::from_millis(200);
    cfg.rss_warmup = Duration::ZERO;
    cfg.progress = false;
    let r = run_soak(&cfg, "soak test").expect("the soak runs");
    eprintln!("{}", r.markdown());
    r
}

#[test]
fn kill_nine_midway_reconciles_exactly() {
    let r = small_soak();
    // pushed = acked + rejected: one final verdict per frame, re-pushes included.
    assert_eq!(r.pushed, 2000);
    assert_eq!(r.acked + r.rejected, r.pushed);
    assert_eq!((r.no_verdict, r.double_verdicts), (0, 0));
    assert_eq!(r.bad_frames, 40);
    assert_eq!(r.rejected, r.bad_frames, "exactly the bad frames are rejected");
    assert_eq!((r.bad_accepted, r.good_rejected), (0, 0));
    // Frames handed to a stream the kill broke were pushed again, and only those.
    assert_eq!(r.push_attempts, r.pushed + r.unacknowledged_at_kill);
    assert!(
        r.verdicts_before_kill > 0 && r.acked_after_restart + r.rejected_after_restart > 0,
        "the kill fell midway"
    );
    assert_eq!(r.ack_mismatches, 0);
    assert_eq!(r.unexpected_stream_failures, 0);
    // acked = reported: every acked frame's report reached a subscriber, except
    // reports still in the killed server's buffers (published before the ack);
    // after the restart none is lost, and nothing unacked is reported.
    assert_eq!(r.reported + r.report_lost_at_kill, r.acked);
    assert_eq!(r.report_lost_after_restart, 0);
    assert_eq!(r.reported_not_acked, 0);
    assert_eq!((r.foreign_reports, r.reliable_lagged), (0, 0));
    assert!(r.duplicate_reports <= r.unacknowledged_but_reported);
    // The restarted server's own counters agree with the client's acks.
    assert_eq!(r.status_processed_after_restart, r.acked_after_restart);
    assert_eq!(r.status_reports_after_restart, r.status_processed_after_restart);
    assert_eq!(r.status_rejected_after_restart, r.rejected_after_restart);
    assert_eq!(
        r.status_received_after_restart,
        r.acked_after_restart + r.rejected_after_restart
    );
    assert!(r.check_pushed_eq_acked_plus_rejected && r.check_reported_eq_acked);
    // Subscriber side, lag-and-tell counted: every report the restarted server
    // published reached the reliable subscriber or was announced as skipped.
    assert_eq!(
        r.reliable_reports_after_restart + r.reliable_lagged_after_restart,
        r.status_reports_after_restart
    );
    assert!(r.check_reported_eq_acked_with_lag);
    // Recordings: one file per sensor and server life (a sensor done before the
    // kill has none after it); frames recorded twice are re-pushes.
    assert!(r.recording_files >= r.sensors, "{} files", r.recording_files);
    assert!(r.recorded_twice <= r.unacknowledged_at_kill);
    // acked <= recorded (the recorder flushes before it acks): asserted by
    // `acked_frames_are_all_recorded`.
    eprintln!(
        "acked <= recorded: {} acked frames missing from the recordings ({} acked by the killed server)",
        r.acked_not_recorded, r.acked_not_recorded_before_kill
    );
}

/// Every frame acknowledged by either server life, the killed one included,
/// is in the recordings (measured before the flush-before-ack: 35 of them
/// missing, three files without even a header).
#[test]
fn acked_frames_are_all_recorded() {
    let r = small_soak();
    assert_eq!(r.acked_not_recorded, 0, "acked frames missing from the recordings");
    assert!(r.check_acked_le_recorded);
}
