//! Interference cancellation (issue 6): the learned-template canceller against
//! no cancellation and against plain notch / high-pass filters, on simulated
//! seed-like frames (replay-data/scenes/burst-1m83.toml) with ground truth.

use std::sync::{Arc, Mutex};
use tofwave::detect::noise_model::Moments;
use tofwave::math::stats::clopper_pearson;
use tofwave::frame::Report;
use tofwave::physics::{Simulator, Truth};
use tofwave::pipeline::Pipeline;
use tofwave::scene::{DenoiseConfig, DenoiseMethod, Scene};

use crate::common;
use common::load_scene as scene;

/// What the observer keeps of one unit of work: sequence, stop volts, range gate, noise gates.
type Seen = (
    u64,
    Vec<f64>,
    std::ops::Range<usize>,
    Vec<std::ops::Range<usize>>,
);

/// A matched filter with a fixed threshold set on burst-free frames (the
/// source's set-up: one noise model from a long laser-off record), applied to
/// the stop waveform each pipeline hands to its detector. Bursts are not
/// absorbed into a per-frame sigma here, so every burst peak that the
/// cancellation leaves behind shows up as a spurious return.
#[derive(Debug, Clone)]
struct FixedDetector {
    h: Vec<f64>,
    peak: usize,
    energy: f64,
    mean_v: f64,
    threshold_v: f64,
}

impl FixedDetector {
    fn output(&self, x: &[f64], p: usize) -> Option<f64> {
        let lo = p.checked_sub(self.peak)?;
        (lo + self.h.len() <= x.len()).then(|| {
            self.h
                .iter()
                .zip(&x[lo..])
                .map(|(a, b)| a * (b - self.mean_v))
                .sum::<f64>()
                / self.energy
        })
    }
}

/// Per frame: spurious fixed-threshold crossings (local maxima away from the
/// true return) and the filter output at the true return.
#[derive(Debug, Default, Clone)]
struct Fixed {
    spurious: Vec<u32>,
    at_return: Vec<f64>,
}

/// Runs `frames` frames through `scene`'s pipeline; reports in frame order and,
/// if `det` is given, what the fixed detector sees in the detector's input.
fn run_fixed(
    scene: &Scene,
    sim: &Simulator,
    seed: u64,
    frames: u64,
    det: Option<&FixedDetector>,
) -> (Vec<Report>, Vec<Truth>, Fixed, Moments) {
    let mut p = Pipeline::new(scene, "denoise-test");
    let seen: Arc<Mutex<Vec<Seen>>> = Arc::default();
    let sink = seen.clone();
    p.set_observer(Box::new(move |w| {
        let g = &w.noise.gates;
        sink.lock().unwrap().push((
            w.report.seq_first,
            w.buffers.stop_v.clone(),
            g.range.clone(),
            vec![g.pre.clone(), g.beyond.clone()],
        ));
    }));
    let mut out = Vec::new();
    let mut truths = Vec::new();
    let mut fixed = Fixed::default();
    let mut gate = Moments::default();
    let consume = |truths: &Vec<Truth>, fixed: &mut Fixed, gate: &mut Moments| {
        for (seq, x, range, quiet) in seen.lock().unwrap().drain(..) {
            let t = &truths[seq as usize];
            for r in &quiet {
                x[r.clone()].iter().for_each(|&v| gate.push(v));
            }
            let Some(d) = det else { continue };
            let dt = sim.config().digitiser.sample_interval_s;
            let p_true = t
                .returns
                .first()
                .map_or(-1e9, |r| (r.t_peak_s + 250.0 * dt) / dt);
            let y: Vec<f64> = range
                .clone()
                .map(|p| d.output(&x, p).unwrap_or(0.0))
                .collect();
            let mut n = 0;
            for i in 1..y.len().saturating_sub(1) {
                let p = range.start + i;
                if y[i] > d.threshold_v
                    && y[i] >= y[i - 1]
                    && y[i] > y[i + 1]
                    && (p as f64 - p_true).abs() > 15.0
                {
                    n += 1;
                }
            }
            fixed.spurious.push(n);
            let pt = p_true.round() as usize;
            fixed.at_return.push(
                (pt - 2..=pt + 2)
                    .filter_map(|p| d.output(&x, p))
                    .fold(f64::MIN, f64::max),
            );
        }
    };
    for k in 0..frames {
        let (f, t) = sim.frame(seed, k);
        truths.push(t);
        p.push(f, &mut out).unwrap();
        consume(&truths, &mut fixed, &mut gate);
    }
    p.flush(&mut out);
    consume(&truths, &mut fixed, &mut gate);
    assert_eq!(out.len() as u64, frames);
    (out, truths, fixed, gate)
}

/// Signal-to-noise ratio of the fixed filter's output at the true return over
/// the selected frames: mean over standard deviation.
fn snr_of(v: &[f64], sel: &[bool]) -> f64 {
    let mut m = Moments::default();
    v.iter()
        .zip(sel)
        .filter(|(_, s)| **s)
        .for_each(|(x, _)| m.push(*x));
    m.mean() / m.variance().sqrt()
}

#[test]
fn burst_cancellation_removes_spurious_returns_without_weakening_the_return() {
    let with_bursts = scene("burst-1m83");
    let mut clean = with_bursts.clone();
    clean.simulation.as_mut().unwrap().interference = None;
    let sim = Simulator::new(&with_bursts).unwrap();
    // The burst is drawn from its own random stream: the clean scene gives the
    // same frames without it, the reference for the return's SNR.
    let sim_clean = Simulator::new(&clean).unwrap();
    // 3000 frames: ~1000 hold part of a burst, enough for >= 100 spurious
    // returns without cancellation (the 100x claim needs that many).
    let frames = 3000;
    let seed = 11;
    let (reference, _, _, gate) = run_fixed(&clean, &sim_clean, seed, frames, None);
    let dt = sim.config().digitiser.sample_interval_s;
    let (h, peak) = with_bursts.return_pulse.shape(dt).template();
    let energy: f64 = h.iter().map(|v| v * v).sum();
    let mut det = FixedDetector {
        h,
        peak,
        energy,
        mean_v: gate.mean(),
        threshold_v: f64::INFINITY,
    };
    // The filter output's sigma on burst-free gates (coloured noise included),
    // then the Gaussian threshold for pfa 1e-6 per frame over the range gate.
    let mut out_m = Moments::default();
    {
        let mut p = Pipeline::new(&clean, "calib");
        let mut out = Vec::new();
        let xs: Arc<Mutex<Vec<f64>>> = Arc::default();
        let sink = xs.clone();
        let d2 = det.clone();
        p.set_observer(Box::new(move |w| {
            for r in [w.noise.gates.pre.clone(), w.noise.gates.beyond.clone()] {
                for q in r.step_by(4) {
                    if let Some(v) = d2.output(&w.buffers.stop_v, q) {
                        sink.lock().unwrap().push(v);
                    }
                }
            }
        }));
        for k in 0..300 {
            p.push(sim_clean.frame(seed + 1, k).0, &mut out).unwrap();
        }
        xs.lock().unwrap().iter().for_each(|&v| out_m.push(v));
    }
    let cells = 1100.0;
    det.threshold_v = out_m.mean()
        + out_m.variance().sqrt()
            * tofwave::math::special::q_inv(tofwave::math::special::per_cell_pfa(1e-6, cells));
    let (_, _, fx_clean, _) = run_fixed(&clean, &sim_clean, seed, frames, Some(&det));
    let (plain, truths, fx_plain, _) = run_fixed(&with_bursts, &sim, seed, frames, Some(&det));
    let with = |m: DenoiseMethod| {
        let mut s = with_bursts.clone();
        s.denoise = Some(DenoiseConfig {
            method: m,
            max_burst_s: 55e-6,
            notch_frequencies_hz: vec![1.3e6, 3.1e6, 6.7e6],
            ..DenoiseConfig::default()
        });
        s
    };
    let (cancelled, _, fx_cancel, _) = run_fixed(
        &with(DenoiseMethod::Template),
        &sim,
        seed,
        frames,
        Some(&det),
    );
    let (_, _, fx_notch, _) =
        run_fixed(&with(DenoiseMethod::Notch), &sim, seed, frames, Some(&det));
    let (_, _, fx_hp, _) = run_fixed(
        &with(DenoiseMethod::Highpass),
        &sim,
        seed,
        frames,
        Some(&det),
    );
    let burst: Vec<bool> = truths.iter().map(|t| t.interference).collect();
    let n_burst = burst.iter().filter(|b| **b).count();
    let spur = |f: &Fixed, sel: bool| -> u32 {
        f.spurious
            .iter()
            .zip(&burst)
            .filter(|(_, b)| **b == sel)
            .map(|(s, _)| s)
            .sum()
    };
    println!(
        "frames {frames}, with a burst {n_burst}; fixed threshold {:.1} mV (filter sigma {:.2} mV)",
        det.threshold_v * 1e3,
        out_m.variance().sqrt() * 1e3
    );
    let snr_clean = snr_of(&fx_clean.at_return, &burst);
    let mean_clean = fx_clean
        .at_return
        .iter()
        .zip(&burst)
        .filter(|(_, b)| **b)
        .map(|(v, _)| v)
        .sum::<f64>()
        / n_burst as f64;
    println!(
        "{:<22} {:>18} {:>18} {:>16} {:>14}",
        "method", "spurious (burst)", "spurious (quiet)", "return amp loss", "SNR loss"
    );
    let mut rows = Vec::new();
    for (name, f) in [
        ("clean (no burst)", &fx_clean),
        ("none", &fx_plain),
        ("template", &fx_cancel),
        ("notch", &fx_notch),
        ("highpass 10 MHz", &fx_hp),
    ] {
        let mean = f
            .at_return
            .iter()
            .zip(&burst)
            .filter(|(_, b)| **b)
            .map(|(v, _)| v)
            .sum::<f64>()
            / n_burst as f64;
        let amp_loss_db = 20.0 * (mean_clean / mean).log10();
        let snr_loss_db = 20.0 * (snr_clean / snr_of(&f.at_return, &burst)).log10();
        println!(
            "{name:<22} {:>18} {:>18} {:>13.2} dB {:>11.2} dB",
            spur(f, true),
            spur(f, false),
            amp_loss_db,
            snr_loss_db
        );
        rows.push((name, spur(f, true), amp_loss_db, snr_loss_db));
    }
    let (plain_spur, cancel_spur) = (rows[1].1, rows[2].1);
    assert!(
        plain_spur >= 100,
        "too few burst-caused spurious returns to show 100x: {plain_spur}"
    );
    assert!(
        100 * cancel_spur <= plain_spur,
        "cancellation: {cancel_spur} spurious vs {plain_spur} without"
    );
    // SNR loss: the same frames with and without the burst (paired), ~1000
    // burst frames; the estimate's own spread is < 0.05 dB (paired noise).
    assert!(
        rows[2].3 <= 0.5,
        "template cancellation costs {:.2} dB of SNR",
        rows[2].3
    );
    assert!(
        rows[2].2.abs() <= 0.5,
        "template cancellation changes the return amplitude by {:.2} dB",
        rows[2].2
    );
    // The plain filters weaken the return more than the canceller.
    assert!(rows[3].2 > rows[2].2 && rows[4].2 > rows[2].2, "{rows:?}");

    // The pipeline's own reports: the return's reported SNR in burst frames.
    let snr = |reps: &[Report]| -> Vec<Option<f64>> {
        reps.iter()
            .zip(&truths)
            .map(|(r, t)| {
                let tof = t.returns[0].tof_s;
                r.returns
                    .iter()
                    .find(|x| (x.tof_s - tof).abs() < 3e-9)
                    .map(|x| x.snr_db)
            })
            .collect()
    };
    let (sr, sc, sp) = (snr(&reference), snr(&cancelled), snr(&plain));
    let paired = |a: &[Option<f64>], b: &[Option<f64>]| {
        let v: Vec<(f64, f64)> = a
            .iter()
            .zip(b)
            .zip(&burst)
            .filter_map(|((x, y), s)| if *s { x.zip(*y) } else { None })
            .collect();
        let n = v.len() as f64;
        (
            v.iter().map(|p| p.0).sum::<f64>() / n,
            v.iter().map(|p| p.1).sum::<f64>() / n,
            v.len(),
        )
    };
    let found = |v: &[Option<f64>]| {
        v.iter()
            .zip(&burst)
            .filter(|(x, s)| **s && x.is_some())
            .count()
    };
    let (a, b, n) = paired(&sr, &sc);
    println!(
        "pipeline reports, burst frames: return found clean {} / cancelled {} / none {} of {n_burst}",
        found(&sr),
        found(&sc),
        found(&sp)
    );
    println!(
        "pipeline reports, burst frames: return snr_db clean {a:.2}, cancelled {b:.2} ({n} frames): loss {:.2} dB",
        a - b
    );
    let (a2, b2, n2) = paired(&sr, &sp);
    println!(
        "pipeline reports, burst frames: return snr_db clean {a2:.2}, no cancellation {b2:.2} ({n2} frames): loss {:.2} dB",
        a2 - b2
    );
    let flagged = cancelled
        .iter()
        .zip(&burst)
        .filter(|(r, _)| r.flags.iter().any(|f| f == "interference_cancelled"))
        .count();
    let flagged_quiet = cancelled
        .iter()
        .zip(&burst)
        .filter(|(r, b)| !**b && r.flags.iter().any(|f| f == "interference_cancelled"))
        .count();
    println!("frames flagged interference_cancelled: {flagged} ({flagged_quiet} without a burst)");
    // False cancellations: the canceller is designed to find a burst that is
    // not there with probability `denoise.pfa` per frame. Over the burst-free
    // frames the observed count must be consistent with that rate: the 99 %
    // Clopper-Pearson interval of the count may not lie above the design
    // (1e-3 over ~2000 frames: ~2 expected, fails from 7 on).
    let design = DenoiseConfig::default().pfa;
    let quiet = frames - n_burst as u64;
    let (lo, hi) = clopper_pearson(flagged_quiet as u64, quiet, 0.99);
    println!(
        "false cancellations: {flagged_quiet} of {quiet} burst-free frames, 99 % CP [{lo:.2e}, {hi:.2e}], design {design:.0e}"
    );
    assert!(
        lo <= design,
        "{flagged_quiet} false cancellations in {quiet} burst-free frames exceed the design pfa {design}"
    );
    assert!(a - b <= 0.5, "reported SNR loss {:.2} dB", a - b);
    assert!(found(&sc) + 5 >= found(&sr), "cancellation loses returns");
    assert!(
        cancelled
            .iter()
            .all(|r| r.stages.iter().any(|s| *s == "denoise"))
    );
}
