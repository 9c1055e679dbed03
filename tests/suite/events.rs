//! Interference events against returns, on frames from the independent
//! generator (`tests/common/seedgen.rs`, written from the source's
//! description without the detector): events at random positions in a third
//! of the frames, events on the return, events in every frame with the laser
//! off, and the project's own simulator burst.

use crate::common;

use common::seedgen::{frame_with_seed, EventConfig, GenConfig, GenTruth};
use tofwave::frame::{Frame, Report};
use tofwave::pipeline::Pipeline;
use tofwave::scene::Scene;

/// Reported range of a return at `range_m` with the generator's system delay
/// left in (the default scene is uncalibrated), and how far from it a
/// report still counts as that return, m.
const SAME_RETURN_M: f64 = 2.0;

/// Tally of one run.
#[derive(Debug, Default)]
struct Tally {
    frames: usize,
    found: usize,
    spurious: usize,
    reports_with_returns: usize,
    flagged_events: usize,
}

fn expected_range_m(cfg: &GenConfig, t: &GenTruth) -> Vec<f64> {
    t.returns.iter().map(|e| e.range_m + 0.5 * cfg.speed_of_light_m_per_s * cfg.system_delay_s).collect()
}

fn run(scene: &Scene, cfg: &GenConfig, frames: u64, seed: u64) -> Tally {
    let mut p = Pipeline::new(scene, "events");
    let mut out: Vec<Report> = Vec::new();
    let mut tally = Tally::default();
    for seq in 0..frames {
        let (frame, truth): (Frame, GenTruth) = frame_with_seed(cfg, seed, seq);
        out.clear();
        p.push(frame, &mut out).expect("frame");
        let want = expected_range_m(cfg, &truth);
        for rep in &out {
            tally.frames += 1;
            if !rep.returns.is_empty() {
                tally.reports_with_returns += 1;
            }
            if rep.flags.iter().any(|f| f.name() == "interference_events") {
                tally.flagged_events += 1;
            }
            let mut hit = vec![false; want.len()];
            for r in &rep.returns {
                match want.iter().position(|w| (r.range_m - w).abs() < SAME_RETURN_M) {
                    Some(i) => hit[i] = true,
                    None => tally.spurious += 1,
                }
            }
            tally.found += hit.iter().filter(|h| **h).count();
        }
    }
    tally
}

fn weak_return(events: Option<EventConfig>) -> GenConfig {
    GenConfig { targets: vec![(1.83, 0.35)], full_scale_v: Some(1.0), events, ..GenConfig::default() }
}

#[test]
fn explore() {
    let scene = Scene::default_scene();
    for (name, peak) in [("4 sigma", 0.055), ("350 mV", 0.35)] {
        let ev = EventConfig { probability: 1.0 / 3.0, peak_v: peak, ..EventConfig::default() };
        let t = run(&scene, &weak_return(Some(ev.clone())), 300, 7);
        eprintln!("uniform {name}: {t:?}");
        let mut off = weak_return(Some(EventConfig { probability: 1.0, ..ev }));
        off.laser_off = true;
        let mut s = scene.clone();
        s.detector.pfa = 1e-3;
        let t = run(&s, &off, 300, 8);
        eprintln!("laser off {name}: {t:?}");
    }
    let t = run(&scene, &weak_return(None), 300, 9);
    eprintln!("clean: {t:?}");
    let mut s = scene.clone();
    s.events.enabled = false;
    let ev = EventConfig { probability: 1.0 / 3.0, peak_v: 0.055, ..EventConfig::default() };
    let t = run(&s, &weak_return(Some(ev)), 300, 7);
    eprintln!("uniform 4 sigma, events off: {t:?}");
}

#[test]
fn debug_one() {
    let scene = { let mut s = Scene::default_scene(); s.detector.pfa = 1e-3; s };
    let ev = EventConfig { probability: 1.0, peak_v: 0.055, ..EventConfig::default() };
    let mut off = weak_return(Some(ev));
    off.laser_off = true;
    let mut p = Pipeline::new(&scene, "events");
    let mut out = Vec::new();
    for seq in 0..40 {
        let (frame, truth) = frame_with_seed(&off, 8, seq);
        out.clear();
        p.push(frame, &mut out).unwrap();
        for rep in &out {
            eprintln!("frame {seq} event at {:?} sigma {:.4} returns {:?} flags {:?}", truth.event_at_s, rep.noise.sigma_v, rep.returns.iter().map(|r| (r.t_peak_s * 1e9, r.snr_db)).collect::<Vec<_>>(), rep.flags);
        }
    }
}

#[test]
fn debug_two() {
    let scene = Scene::default_scene();
    let ev = EventConfig { probability: 1.0 / 3.0, peak_v: 0.35, ..EventConfig::default() };
    let cfg = weak_return(Some(ev));
    let mut p = Pipeline::new(&scene, "events");
    let mut out = Vec::new();
    for seq in 0..300 {
        let (frame, truth) = frame_with_seed(&cfg, 7, seq);
        out.clear();
        p.push(frame, &mut out).unwrap();
        for rep in &out {
            eprintln!("frame {seq} event at {:?} ret at {:.1} sigma {:.4} thr {:.4} returns {:?} flags {:?}", truth.event_at_s.map(|t| t * 1e9), truth.returns[0].t_ref_s * 1e9, rep.noise.sigma_v, rep.detector.threshold, rep.returns.iter().map(|r| (r.t_peak_s * 1e9, r.snr_db)).collect::<Vec<_>>(), rep.flags);
        }
    }
}
