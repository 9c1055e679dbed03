//! False-alarm accounting on band-limited noise (AR(1) φ = 0.9 and the
//! simulator's TIA chain), gates of 400 and 1400 samples: the per-report
//! false-alarm rate holds the design at 1e-2 and 1e-3, and the self-check's
//! `excess` fires in clean runs at its stated rate and almost always when the
//! noise is twice the fitted sigma. Fixed seeds; Clopper–Pearson 99 %
//! intervals from the trial counts.
//!
//! `cargo test --release --test suite -- false_alarm_coloured:: --nocapture`

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use tofwave::frame::{Channel, ChannelRole, Frame};
use tofwave::math::stats::clopper_pearson;
use tofwave::physics::noise_source::ColouredNoise;
use tofwave::physics::simulator::stop_chain;
use tofwave::pipeline::Pipeline;
use tofwave::frame::Report;
use tofwave::scene::{CfarKind, PfaScope, RangeGateConfig, Scene, TimingMethod};

const SIGMA: f64 = 0.0138;
const DT: f64 = 1e-9;
/// Range gate 0..75 m: 500 samples at 1 GS/s.
const MAX_M: f64 = 75.0;

#[derive(Clone, Copy, Debug)]
enum Noise {
    Ar1,
    Tia,
}

struct Source {
    kind: Noise,
    tia: Option<ColouredNoise>,
    tia_sd: f64,
    rng: ChaCha8Rng,
}

impl Source {
    fn new(kind: Noise, seed: u64) -> Source {
        let tia = matches!(kind, Noise::Tia).then(|| {
            let scene = Scene::load(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/replay-data/scenes/lab-table-10-20.toml"))).unwrap();
            let cfg = scene.simulation.unwrap();
            ColouredNoise::new(stop_chain(&cfg).linear().discretise(DT), 1.0, 0.0)
        });
        // The chain's marginal sigma, measured once (200 000 samples: ±1 %).
        let tia_sd = tia.as_ref().map(|t| {
            let mut v = vec![0.0; 200_000];
            t.add_to(&mut ChaCha8Rng::seed_from_u64(u64::MAX), &mut v, None, 0);
            let m = v[1000..].iter().sum::<f64>() / (v.len() - 1000) as f64;
            (v[1000..].iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1000) as f64).sqrt()
        });
        Source { kind, tia, tia_sd: tia_sd.unwrap_or(1.0), rng: ChaCha8Rng::seed_from_u64(seed) }
    }

    fn samples(&mut self, n: usize, sigma: f64) -> Vec<f64> {
        match self.kind {
            Noise::Ar1 => {
                let phi: f64 = 0.9;
                let e = Normal::new(0.0, sigma * (1.0 - phi * phi).sqrt()).unwrap();
                let mut x = Normal::new(0.0, sigma).unwrap().sample(&mut self.rng);
                (0..n)
                    .map(|_| {
                        let v = x;
                        x = phi * x + e.sample(&mut self.rng);
                        v
                    })
                    .collect()
            }
            Noise::Tia => {
                // Run-in so the filter state is stationary, then scale to sigma.
                let tia = self.tia.as_ref().unwrap();
                let mut v = vec![0.0; n + 200];
                tia.add_to(&mut self.rng, &mut v, None, 0);
                let s = self.tia_sd;
                v.drain(..200);
                v.iter_mut().for_each(|x| *x *= sigma / s);
                v
            }
        }
    }
}

/// Samples before the trigger (the pre gate ends 20 ns before it) and after
/// the range gate for `gate` noise-gate samples in all.
fn frame_layout(scene: &Scene, gate: usize) -> (usize, usize) {
    let half = gate / 2;
    let pre = half + (scene.noise_gate.guard_s / DT).round() as usize;
    // Range gate, then the pulse length and the guard, then the beyond gate.
    let range = (2.0 * MAX_M / 299_792_458.0 / DT).ceil() as usize;
    let guard = (scene.noise_gate.guard_s / DT).round() as usize;
    (pre, pre + range + 141 + guard + half)
}

fn frame(v: Vec<f64>, pre: usize, seq: u64) -> Frame {
    Frame {
        sensor_id: "fa".into(),
        sequence: seq,
        trigger_time_s: seq as f64 * 1e-3,
        sample_interval_s: DT,
        first_sample_offset_s: -(pre as f64) * DT,
        channels: vec![Channel::from_volts("CH2", ChannelRole::Stop, v)],
        laser_off: true,
    }
}

/// The scene for `noise`: the default with the range gate above. The noise
/// gates keep `guard_s` clear of every range cell's filter window; band-limited
/// noise needs that guard to cover its correlation (the simulator's TIA: ρ
/// falls below 0.01 after about 40 samples; with the default 20 ns its
/// 400-sample gates share enough of a large excursion with the range gate
/// to hold 0.4x the design at 1e-3 — safe, but not the design).
fn scene_for(noise: Noise, pfa: f64) -> Scene {
    let mut s = scene(pfa);
    if let Noise::Tia = noise {
        s.noise_gate.guard_s = 50e-9;
    }
    s
}

fn scene(pfa: f64) -> Scene {
    let mut s = Scene::default_scene();
    s.detector.pfa = pfa;
    s.timing.method = TimingMethod::PeakParabolic;
    s.range_gate = RangeGateConfig { min_m: 0.0, max_m: MAX_M };
    // What these tests check is the detector's threshold design. The events
    // stage (on in the default scene) can only take reports away: on strongly
    // coloured noise it drops some noise crossings whose shape is
    // band-limited (simulator TIA noise, gate 400, pfa 1e-3: 29 of 50 000
    // reports with it, 35 without, design 50).
    s.events.enabled = false;
    s
}

/// Reports with a return among `frames` noise-only frames, and the last report.
fn false_reports(s: &Scene, noise: Noise, gate: usize, frames: u64, seed: u64) -> (u64, Report) {
    let (pre, len) = frame_layout(s, gate);
    let mut p = Pipeline::new(s, "fa");
    let mut src = Source::new(noise, seed);
    let mut out = Vec::new();
    let mut hits = 0;
    for seq in 0..frames {
        out.clear();
        p.push(frame(src.samples(len, SIGMA), pre, seq), &mut out).unwrap();
        if !out[0].returns.is_empty() {
            hits += 1;
        }
    }
    (hits, out.pop().unwrap())
}

/// The per-report rate's 99 % Clopper–Pearson interval holds the design;
/// returns the last report.
fn check_report_rate(s: &Scene, label: &str, noise: Noise, gate: usize, seed: u64) -> Report {
    let pfa = s.detector.pfa;
    let frames = (50.0 / pfa).round() as u64;
    let (hits, last) = false_reports(s, noise, gate, frames, seed);
    let (lo, hi) = clopper_pearson(hits, frames, 0.99);
    eprintln!(
        "{label} {noise:?}, gate {} samples, pfa {pfa:e}: {hits} of {frames} reports with a return ({:.2}x design; 99 % [{:.2}, {:.2}]x); \
         gate self-check {:.2}x design, excess {}",
        last.noise.samples,
        hits as f64 / frames as f64 / pfa,
        lo / pfa,
        hi / pfa,
        last.false_alarm.rate / last.detector.pfa_cell,
        last.false_alarm.excess
    );
    assert_eq!(last.noise.samples as usize, gate, "the layout gives the gate asked for");
    assert!(lo <= pfa && pfa <= hi, "{label} {noise:?} gate {gate} pfa {pfa}: {hits} of {frames}");
    last
}

#[test]
fn per_report_rate_holds_the_design_on_ar1_noise() {
    for (gate, pfa, seed) in [(400, 1e-2, 1), (400, 1e-3, 2), (1400, 1e-2, 3), (1400, 1e-3, 4)] {
        check_report_rate(&scene(pfa), "matched filter", Noise::Ar1, gate, seed);
    }
}

#[test]
fn per_report_rate_holds_the_design_on_tia_noise() {
    for (gate, pfa, seed) in [(400, 1e-2, 5), (400, 1e-3, 6), (1400, 1e-2, 7), (1400, 1e-3, 8)] {
        check_report_rate(&scene_for(Noise::Tia, pfa), "matched filter", Noise::Tia, gate, seed);
    }
}

fn whitened_cfar(kind: CfarKind) -> Scene {
    let mut s = scene(1e-2);
    s.detector.cfar = kind;
    s.detector.whiten = true;
    s
}

#[test]
fn cfar_on_whitened_coloured_input_holds_the_design() {
    // CFAR on coloured input: whitening makes the training cells white, and
    // the CA/OS factors exact again. The gate self-check counts cells above
    // their CFAR threshold against the design per-cell probability: after
    // 5 000 clean frames it must not call an excess.
    for (kind, seed) in [(CfarKind::Ca, 11), (CfarKind::Os, 12)] {
        let s = whitened_cfar(kind);
        let last = check_report_rate(&s, &format!("{kind:?}-CFAR, whitened"), Noise::Ar1, 1400, seed);
        assert!(!last.false_alarm.excess, "{kind:?}: {:?}", last.false_alarm);
    }
}

#[test]
fn cfar_self_check_is_quiet_on_clean_whitened_input() {
    // Clean runs of 250 frames each: the flag's design rate is 0.1 % per
    // run (the lower end of a 99.8 % interval) and the acceptance at most
    // 1 %. CA: ≤ 2 flagged in 100 runs is what a 1 % rate gives with
    // probability 0.92 (a true rate of 8 % passes with probability < 2 %).
    // OS re-solves its factors by quadrature whenever the whitener is
    // refitted (about 0.4 s a run): ≤ 1 in 30 runs, which a 1 % rate gives
    // with probability 0.96 and a 15 % rate with probability < 5 %.
    let frames = 250;
    for (kind, runs, allowed) in [(CfarKind::Ca, 100, 2), (CfarKind::Os, 30, 1)] {
        let s = whitened_cfar(kind);
        let (pre, len) = frame_layout(&s, 1400);
        let (mut flagged, mut ratio) = (0, 0.0);
        let mut out = Vec::new();
        for run in 0..runs {
            let mut src = Source::new(Noise::Ar1, 3000 + run);
            let mut p = Pipeline::new(&s, "fa");
            for seq in 0..frames {
                out.clear();
                p.push(frame(src.samples(len, SIGMA), pre, seq), &mut out).unwrap();
            }
            let last = &out[0];
            flagged += last.false_alarm.excess as u64;
            ratio += last.false_alarm.rate / last.detector.pfa_cell / runs as f64;
        }
        eprintln!(
            "{kind:?}-CFAR, whitened Ar1, gate 1400: excess in {flagged}/{runs} clean runs of {frames} frames; \
             gate cells above their threshold {ratio:.2}x the design on average"
        );
        assert!(flagged <= allowed, "{kind:?}: {flagged} of {runs} clean runs flagged");
    }
}

#[test]
fn cfar_on_raw_coloured_input_holds_the_design() {
    // Without whitening the training cells are correlated with each other:
    // the CA factor is solved on the training window's exact variance
    // distribution (about 7 degrees of freedom from 64 cells of AR(1)
    // φ = 0.9), the OS factor by importance-sampled Monte Carlo on the
    // window's correlation, and the gate mean's error, which moves the
    // matched filter's output far more than it moves the training cells'
    // power on noise this slow, scales the thresholds. README still
    // recommends `whiten`: it keeps more of the detection power.
    let mut s = scene(1e-2);
    s.detector.cfar_training_cells = 32;
    s.detector.cfar_guard_cells = 40;
    let frames = 5000;
    let mut fails = Vec::new();
    for (kind, seed) in [(CfarKind::Ca, 11), (CfarKind::Os, 13)] {
        s.detector.cfar = kind;
        let (hits, _) = false_reports(&s, Noise::Ar1, 400, frames, seed);
        let (lo, hi) = clopper_pearson(hits, frames, 0.99);
        eprintln!("{kind:?}-CFAR on raw AR(1) input: {hits} of {frames} reports ({:.2}x design; 99 % [{:.2}, {:.2}]x)", hits as f64 / frames as f64 / 1e-2, lo / 1e-2, hi / 1e-2);
        // Both hold the design from both sides. OS on correlated cells has
        // no closed form: its full-window factor is an importance-sampled
        // Monte-Carlo estimate (held two standard errors to the safe side,
        // about 4 % in Pfa here); the white effective-cell approximation
        // it replaced gave 0 of 5000.
        if !(lo <= 1e-2 && 1e-2 <= hi) {
            fails.push(format!("{kind:?}: design outside the 99 % interval: {hits} of {frames}"));
        }
    }
    assert!(fails.is_empty(), "{fails:?}");
}

/// Self-check runs: `runs` clean runs of `frames`/4 frames with each frame's
/// noise model from its own gates, and as many runs with a slowly forgetting
/// model (10 000 frames) whose last `step` frames carry twice the noise: the
/// fitted sigma then lags the noise by about 2x (40 frames after 1 000: the
/// model has moved 4 % of the way). Design pfa 1e-2 per report. Returns the fraction of runs
/// whose last report says `excess`: (per-frame model, forgetting model before
/// the step, forgetting model after it).
fn self_check_runs(noise: Noise, gate: usize, runs: u64, frames: u64, step: u64) -> (u64, u64, u64, f64) {
    let pfa = 1e-2;
    let plain = scene_for(noise, pfa);
    let mut forgetting = scene_for(noise, pfa);
    forgetting.noise_gate.forgetting_frames = 10_000;
    let (pre, len) = frame_layout(&plain, gate);
    let (mut clean, mut before, mut after, mut lag) = (0, 0, 0, 0.0);
    let mut out = Vec::new();
    for run in 0..runs {
        let mut src = Source::new(noise, 1000 + run);
        let mut p = Pipeline::new(&plain, "fa");
        for seq in 0..frames / 4 {
            out.clear();
            p.push(frame(src.samples(len, SIGMA), pre, seq), &mut out).unwrap();
        }
        clean += out[0].false_alarm.excess as u64;
        let mut p = Pipeline::new(&forgetting, "fa");
        for seq in 0..frames + step {
            let sigma = if seq < frames { SIGMA } else { 2.0 * SIGMA };
            out.clear();
            p.push(frame(src.samples(len, sigma), pre, seq), &mut out).unwrap();
            if seq + 1 == frames {
                before += out[0].false_alarm.excess as u64;
            }
        }
        after += out[0].false_alarm.excess as u64;
        lag += 2.0 * SIGMA / out[0].noise.sigma_v / runs as f64;
    }
    (clean, before, after, lag)
}

fn check_self_check(noise: Noise, gate: usize) {
    let (runs, frames, step) = (100, 1000, 40);
    let (clean, before, after, lag) = self_check_runs(noise, gate, runs, frames, step);
    eprintln!(
        "{noise:?}, gate {gate}: excess in {clean}/{runs} clean runs (per-frame model), {before}/{runs} (forgetting model), \
         {after}/{runs} after {step} frames at 2x the noise (noise / fitted sigma {lag:.2} on average)"
    );
    // The flag's design rate is 0.1 % per run (the lower end of a 99.8 %
    // interval); ≤ 2 in 100 would be seen with probability < 2 % if the true
    // rate were 8 %, and a 1 % rate gives ≤ 2 in 100 with probability 0.92.
    assert!(clean <= 2 && before <= 2, "{clean} / {before} of {runs} clean runs flagged");
    assert!(lag > 1.8, "the test's noise really is about twice the fitted sigma: {lag}");
    // ≥ 99 of 100: a true rate of 95 % passes this with probability < 4 %.
    assert!(after >= runs - 1, "{after} of {runs} runs with 2x noise flagged");
}

#[test]
fn self_check_excess_on_ar1_400() {
    check_self_check(Noise::Ar1, 400);
}

#[test]
fn self_check_excess_on_tia_1400() {
    check_self_check(Noise::Tia, 1400);
}

#[test]
fn per_sample_scope_counts_up_crossings_against_their_expectation() {
    // pfa_scope = "sample" on a correlated output: up-crossings are fewer
    // than exceedances; the expectation counts the same thing.
    let mut s = scene(1e-3);
    s.detector.pfa_scope = PfaScope::Sample;
    let (_, last) = false_reports(&s, Noise::Ar1, 1400, 3000, 21);
    let fa = &last.false_alarm;
    eprintln!(
        "per-sample scope, AR(1): {} crossings in {:.0} cells, rate {:.2e} (design {:.0e}), ci95 [{:.2e}, {:.2e}]",
        fa.observed, fa.cells, fa.rate, last.detector.pfa_cell, fa.ci95[0], fa.ci95[1]
    );
    assert!(fa.ci95[0] <= 1e-3 && 1e-3 <= fa.ci95[1], "{fa:?}");
    assert!(!fa.excess);
}
