//! One sensor on several threads (`pipeline::threaded`, `process --threads`):
//! the reports must be bit-identical to one thread's, whatever the cut,
//! with averaging groups, refused frames and the final flush.

use crate::common::tofwave_ok;
use std::path::PathBuf;
use tofwave::capture::{self, ReadOptions};
use tofwave::frame::Frame;
use tofwave::pipeline::{report_json, threaded};
use tofwave::scene::Scene;

/// 700 frames of the default (prototype) scene: past the 400 frames the
/// threaded run spends on one thread choosing its cut.
fn simulated(dir: &tempfile::TempDir) -> Vec<Frame> {
    simulated_n(dir, 700)
}

/// `n` frames of the default scene, seed 11.
fn simulated_n(dir: &tempfile::TempDir, n: usize) -> Vec<Frame> {
    let path = dir.path().join("sim.twr");
    tofwave_ok(&["simulate", "--frames", &n.to_string(), "--seed", "11", "--out", path.to_str().unwrap()]);
    let opts = ReadOptions { sensor_id: "t".into(), ..ReadOptions::default() };
    capture::frames(&[PathBuf::from(&path)], &opts).unwrap().map(|f| f.unwrap()).collect()
}

/// Every outcome as text: each report's JSON, or the refusal's message.
fn run(scene: &Scene, frames: &[Frame], threads: usize) -> (Vec<String>, threaded::Cut) {
    let mut lines = Vec::new();
    let cut = threaded::run(scene, "t", threads, frames.to_vec(), |o| {
        lines.extend(o.reports.iter().map(report_json));
        if let Err(e) = &o.result {
            lines.push(format!("refused: {e}"));
        }
        lines.push("--".into());
    });
    (lines, cut)
}

#[test]
fn threaded_reports_are_bit_identical_to_one_thread() {
    let dir = tempfile::tempdir().unwrap();
    let mut frames = simulated(&dir);
    // Two bad frames, one in the single-thread pilot and one after it.
    for k in [50, 600] {
        frames[k].sample_interval_s = -1.0;
    }
    for average in [1u32, 3] {
        let mut scene = Scene::default_scene();
        scene.averaging.frames = average;
        let (one, _) = run(&scene, &frames, 1);
        assert!(one.iter().filter(|l| l.starts_with("refused")).count() == 2, "the bad frames are refused");
        assert!(one.iter().filter(|l| l.starts_with('{')).count() >= 700 / average as usize - 2);
        for threads in [2, 3, 8] {
            let (many, cut) = run(&scene, &frames, threads);
            // One segment per thread, or on two threads the ring: three
            // segments, the first and last on one thread.
            let used = cut.threads.iter().max().map_or(0, |t| t + 1);
            assert_eq!(used, threads.min(cut.segments.iter().map(Vec::len).sum()), "{cut}");
            assert_eq!(cut.threads.len(), cut.segments.len(), "{cut}");
            assert!(cut.segments.len() == used || (threads == 2 && cut.threads == [0, 1, 0]), "{cut}");
            assert_eq!(many.len(), one.len(), "average {average}, {threads} threads ({cut})");
            for (i, (a, b)) in one.iter().zip(&many).enumerate() {
                assert_eq!(a, b, "average {average}, {threads} threads ({cut}): outcome line {i} differs");
            }
        }
    }
}

/// Every outcome of a `Staged` pipeline on two threads, the ring forced on
/// or off; `sync_at`: frames after which `sync` must hand back every
/// outcome so far. `settle_while` is called too: after frame 480 with input
/// coming back after two outcomes (it must return with frames still in
/// flight, none lost), after every frame from 500 to 509 with input back at
/// once, and after frame 620 with none (it must hand back every outcome).
fn staged(scene: &Scene, frames: &[Frame], ring: bool, sync_at: usize) -> (Vec<String>, threaded::Cut) {
    let mut s = threaded::Staged::new(scene, "t", 2);
    s.prefer_ring(Some(ring));
    let (mut lines, mut out) = (Vec::new(), Vec::new());
    let take = |out: &mut Vec<threaded::Outcome>, lines: &mut Vec<String>| {
        for o in out.drain(..) {
            lines.extend(o.reports.iter().map(report_json));
            if let Err(e) = o.result {
                lines.push(format!("refused: {e}"));
            }
            lines.push("--".into());
        }
    };
    for (i, f) in frames.iter().enumerate() {
        s.push(f.clone(), &mut out);
        if i + 1 == sync_at {
            s.sync(&mut out);
            assert_eq!(s.in_flight(), 0, "sync hands back every outcome");
            take(&mut out, &mut lines);
            assert_eq!(lines.iter().filter(|l| *l == "--").count(), sync_at, "one outcome per frame pushed");
        }
        if i + 1 == 480 {
            let asked = std::cell::Cell::new(0);
            s.settle_while(|| { asked.set(asked.get() + 1); asked.get() <= 2 }, &mut out);
            assert!(s.in_flight() > 0, "input came back: the frames still in flight are left there");
        }
        if (500..510).contains(&(i + 1)) {
            s.settle_while(|| false, &mut out);
        }
        if i + 1 == 620 {
            s.settle_while(|| true, &mut out);
            assert_eq!(s.in_flight(), 0, "settle_while with no input hands back every outcome");
            take(&mut out, &mut lines);
            assert_eq!(lines.iter().filter(|l| *l == "--").count(), 620, "one outcome per frame pushed");
        }
        take(&mut out, &mut lines);
    }
    let flushed = s.finish(&mut out);
    take(&mut out, &mut lines);
    lines.extend(flushed.reports.iter().map(report_json));
    lines.push("--".into());
    (lines, s.cut())
}

#[test]
fn the_ring_and_the_chain_give_one_threads_reports() {
    let dir = tempfile::tempdir().unwrap();
    let mut frames = simulated(&dir);
    frames[600].sample_interval_s = -1.0;
    for average in [1u32, 3] {
        let mut scene = Scene::default_scene();
        scene.averaging.frames = average;
        let (one, _) = run(&scene, &frames, 1);
        for ring in [true, false] {
            let (two, cut) = staged(&scene, &frames, ring, 555);
            assert_eq!(cut.threads == [0, 1, 0], ring, "{cut}");
            assert_eq!(two.len(), one.len(), "average {average}, {cut}");
            for (i, (a, b)) in one.iter().zip(&two).enumerate() {
                assert_eq!(a, b, "average {average} ({cut}): outcome line {i} differs");
            }
        }
    }
    // Dropped without finish, frames in flight: the threads end (no hang).
    let mut s = threaded::Staged::new(&Scene::default_scene(), "t", 2);
    s.prefer_ring(Some(true));
    let mut out = Vec::new();
    for f in &frames {
        s.push(f.clone(), &mut out);
    }
    assert_eq!(s.cut().threads, [0, 1, 0]);
    drop(s);
}

/// Past `threaded::REPILOT_AT` frames the stages come back from their
/// threads, unflushed, are timed again on the calling thread and cut anew:
/// the reports stay one thread's, bit for bit, on the ring, the chain and
/// three threads, with an averaging group open across the hand-back
/// (frame 1999 waits in it: of the 1999 frames before it, frame 600 was
/// refused and the other 1998 made 666 groups), a refused frame at it and
/// one in the second pilot, and the
/// cut says which frames chose it.
#[test]
fn the_second_pilot_hands_the_stages_back_and_changes_no_report() {
    assert_eq!((threaded::REPILOT_AT, threaded::SETTLED_FRAMES), (2000, 2200), "the frames below are placed for these");
    let dir = tempfile::tempdir().unwrap();
    let mut frames = simulated_n(&dir, 2600);
    for k in [600, 2000, 2100] {
        frames[k].sample_interval_s = -1.0;
    }
    for average in [1u32, 3] {
        let mut scene = Scene::default_scene();
        scene.averaging.frames = average;
        let (one, _) = run(&scene, &frames, 1);
        assert_eq!(one.iter().filter(|l| l.starts_with("refused")).count(), 3, "the bad frames are refused");
        if average == 3 {
            let open = r#""seq_first":1999,"seq_last":2002,"#;
            assert!(one.iter().any(|l| l.contains(open)), "a group open across the hand-back: frames 1999, 2001 and 2002");
        }
        let mut arms: Vec<(String, Vec<String>, threaded::Cut)> = Vec::new();
        for ring in [true, false] {
            // All outcomes handed back at frame 1990, ten frames before the hand-back.
            let (lines, cut) = staged(&scene, &frames, ring, 1990);
            assert_eq!(cut.threads == [0, 1, 0], ring, "{cut}");
            arms.push((format!("ring {ring}"), lines, cut));
        }
        let (lines, cut) = run(&scene, &frames, 2);
        arms.push(("2 threads run".into(), lines, cut));
        let (lines, cut) = run(&scene, &frames, 3);
        arms.push(("3 threads".into(), lines, cut));
        for (arm, lines, cut) in &arms {
            assert_eq!(cut.pilot, Some((2001, 2200)), "{arm}: the second pilot chose the cut ({cut})");
            assert_eq!(lines.len(), one.len(), "average {average}, {arm} ({cut})");
            for (i, (a, b)) in one.iter().zip(lines).enumerate() {
                assert_eq!(a, b, "average {average}, {arm} ({cut}): outcome line {i} differs");
            }
        }
    }
    // Before the second pilot, the first chose the cut.
    let (_, cut) = run(&Scene::default_scene(), &frames[..1000], 2);
    assert_eq!(cut.pilot, Some((201, 400)), "{cut}");
}

/// A stream that ends around the second pilot: just before the hand-back
/// (2000 frames: the stages still on their threads), on the hand-back's
/// frame (2001: the stages handed back, then the end), just after it (2002),
/// inside the second pilot (2100, the stages on the calling thread being
/// timed) and on the pilot's last frame (2200, cut again and ended at
/// once). Each is flushed as one thread flushes it, bit for bit, on two and
/// three threads, with averaging 3 (where a group is open at the end, the
/// flush closes it; else the flush has no report) and, at the hand-back's
/// frame, 1; frame 2050 is refused.
#[test]
fn a_stream_ending_in_the_second_pilot_is_flushed_as_on_one_thread() {
    assert_eq!((threaded::REPILOT_AT, threaded::SETTLED_FRAMES), (2000, 2200), "the ends below are placed for these");
    let dir = tempfile::tempdir().unwrap();
    let mut frames = simulated_n(&dir, 2200);
    frames[2050].sample_interval_s = -1.0;
    for (average, ends) in [(3u32, &[2000, 2001, 2002, 2100, 2200][..]), (1, &[2001][..])] {
        let mut scene = Scene::default_scene();
        scene.averaging.frames = average;
        for &end in ends {
            let (one, _) = run(&scene, &frames[..end], 1);
            let outcomes = one.iter().filter(|l| *l == "--").count();
            // One outcome per frame, and the flush's.
            assert_eq!(outcomes, end + 1, "average {average}, end {end}");
            assert_eq!(one.iter().filter(|l| l.starts_with("refused")).count(), usize::from(end > 2050), "end {end}");
            // The frames valid before `end` make the groups.
            let valid = end - usize::from(end > 2050);
            let flush_report = one[one.len() - 2].starts_with('{');
            assert_eq!(flush_report, valid % average as usize != 0, "average {average}, end {end}: the flush closes an open group, and only one");
            for threads in [2, 3] {
                let (many, cut) = run(&scene, &frames[..end], threads);
                assert_eq!(many.len(), one.len(), "average {average}, end {end}, {threads} threads ({cut})");
                for (i, (a, b)) in one.iter().zip(&many).enumerate() {
                    assert_eq!(a, b, "average {average}, end {end}, {threads} threads ({cut}): outcome line {i} differs");
                }
            }
        }
    }
}

/// `process --threads 2` past both pilots (2300 frames) prints what one thread does.
#[test]
fn process_threads_flag_gives_the_same_output() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sim.twr");
    tofwave_ok(&["simulate", "--frames", "2300", "--seed", "5", "--out", path.to_str().unwrap()]);
    let p = path.to_str().unwrap();
    let one = tofwave_ok(&["process", "-i", p, "--threads", "1"]);
    let two = tofwave_ok(&["process", "-i", p, "--threads", "2"]);
    assert_eq!(one.lines().count(), 2300);
    assert!(one == two, "process --threads 2 differs from --threads 1");
}

/// `bench --threads 2` runs its arms and writes threads.md: the rates,
/// the ratios, the machine's yardstick (two independent copies at once), the cut, the pilot's and the steady stage times, and the
/// CPU time by thread or why it was not measured (likely, with this few frames).
#[test]
fn bench_threads_writes_its_report() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let printed = tofwave_ok(&["bench", "--threads", "2", "--threads-frames", "900", "--threads-trials", "1", "--out", out]);
    let md = std::fs::read_to_string(dir.path().join("threads.md")).unwrap();
    assert!(printed.contains(md.trim()), "prints what it writes");
    for want in [
        "| offline, 2 threads (`process --threads 2`) |",
        "| service, 2 workers (`serve --workers-per-sensor 2`) |",
        "Offline 2 threads / 1 thread: **",
        "| offline, 2 independent copies of the 1-thread arm at once (the machine's yardstick) |",
        "The machine's yardstick: 2 independent copies of the one-thread pipeline at once",
        ". Cut: validate+",
        "| stage | pilot µs/frame | share | steady µs/frame | share |",
        "| events |",
    ] {
        assert!(md.contains(want), "threads.md lacks {want:?}:\n{md}");
    }
    // Measured where the arms' CPU windows are long enough, else said not to be.
    assert!(md.contains("CPU time by thread: not measured") || md.contains("\n| all | "), "{md}");
}

/// Two threads against one, bit for bit, past both pilots, on frames the
/// pipeline was not designed around: the independent generator's (the
/// prototype's frames with interference events in a third of them) and
/// the real capture `lecroy_3.trc` (its 20 segments 120 times over, on the
/// scene measured from it).
#[test]
fn threads_match_one_thread_on_frames_not_designed_for() {
    use crate::common::seedgen::{generate, EventConfig, GenConfig};
    let cfg = GenConfig { events: Some(EventConfig { probability: 1.0 / 3.0, random_phase: true, ..EventConfig::default() }), ..GenConfig::default() };
    let generated: Vec<Frame> = generate(&cfg, 2400, 46).into_iter().map(|(f, _)| f).collect();
    let segments = capture::read_paths(&[crate::common::replay_path("lecroy_3.trc")], &ReadOptions::default()).unwrap();
    assert_eq!(segments.len(), 20);
    let measured = capture::measure::measure(&segments, "lecroy_3.trc").unwrap().scene().unwrap();
    let repeated: Vec<Frame> = (0..2400)
        .map(|i| {
            let mut f = segments[i % segments.len()].clone();
            f.sequence = i as u64;
            f
        })
        .collect();
    for (name, scene, frames) in [("independent generator", Scene::default_scene(), generated), ("lecroy_3 repeated", measured, repeated)] {
        let (one, _) = run(&scene, &frames, 1);
        let reports = one.iter().filter(|l| l.starts_with('{')).count();
        assert!(reports >= 2300, "{name}: {reports} reports of 2400 frames");
        let (two, cut) = run(&scene, &frames, 2);
        assert_eq!(cut.pilot, Some((2001, 2200)), "{name}: {cut}");
        assert_eq!(two.len(), one.len(), "{name} ({cut})");
        for (i, (a, b)) in one.iter().zip(&two).enumerate() {
            assert_eq!(a, b, "{name} ({cut}): outcome line {i} differs");
        }
    }
}
