//! Criterion benches of the DSP kernels at the prototype's frame size
//! (2500 samples at 1 GS/s). Run: `cargo bench --bench kernels` (add
//! `-- --quick` for a fast pass).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use tofwave::dsp::average::{CodeAccumulator, add_codes_i16, add_f64};
use tofwave::dsp::correlate::{CorrelationMethod, Correlator};
use tofwave::dsp::fracdelay::FractionalDelay;
use tofwave::dsp::mlfit::fit_delay;
use tofwave::dsp::pulse::{Pulse, PulseShape};
use tofwave::scene::Scene;

const FRAME: usize = 2500;

fn noise(n: usize, seed: u64) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| StandardNormal.sample(&mut rng)).collect()
}

fn correlate(c: &mut Criterion) {
    let x = noise(FRAME, 1);
    for taps_len in [64usize, 300] {
        let taps = noise(taps_len, 2);
        let chosen = Correlator::new(&taps, FRAME).method();
        for method in [CorrelationMethod::Direct, CorrelationMethod::Fft] {
            let mut corr = Correlator::with_method(&taps, FRAME, method);
            let mut out = Vec::with_capacity(FRAME);
            let mark = if method == chosen { " (chosen)" } else { "" };
            c.bench_function(
                &format!("correlate/{taps_len}taps_{FRAME}/{method:?}{mark}"),
                |b| {
                    b.iter(|| {
                        corr.correlate(black_box(&x), &mut out);
                        black_box(out.len())
                    })
                },
            );
        }
    }
}

fn mlfit(c: &mut Criterion) {
    let shape = Pulse::from_config(&Scene::default_scene().return_pulse, 1e-9);
    let delay = 1234.37;
    let n = noise(FRAME, 3);
    let x: Vec<f64> = (0..FRAME)
        .map(|k| shape.value_and_slope(k as f64 - delay).0 + 0.1 * n[k])
        .collect();
    // A ~60-sample window around the return (4σ of the rise before the peak,
    // ~2.5σ of the fall after it), started a sample off.
    c.bench_function("mlfit/default_pulse_window_60", |b| {
        b.iter(|| {
            black_box(fit_delay(
                black_box(&x),
                0.0,
                &shape,
                delay - 1.0,
                1214..1274,
                50,
            ))
        })
    });
}

fn average(c: &mut Criterion) {
    let codes: Vec<i16> = noise(FRAME, 4)
        .iter()
        .map(|v| (v * 3000.0) as i16)
        .collect();
    let mut acc = vec![0i64; FRAME];
    c.bench_function("average/add_codes_i16_2500", |b| {
        b.iter(|| add_codes_i16(black_box(&mut acc), black_box(&codes)))
    });
    let mut blocked = CodeAccumulator::new(FRAME);
    c.bench_function("average/code_accumulator_i16_2500", |b| {
        b.iter(|| blocked.add_i16(black_box(&codes)))
    });
    let xf = noise(FRAME, 5);
    let mut accf = vec![0.0; FRAME];
    c.bench_function("average/add_f64_2500", |b| {
        b.iter(|| add_f64(black_box(&mut accf), black_box(&xf)))
    });
}

fn fracdelay(c: &mut Criterion) {
    let x = noise(FRAME, 6);
    let plan = FractionalDelay::new(0.37);
    let mut out = vec![0.0; FRAME];
    c.bench_function("fracdelay/apply_2500", |b| {
        b.iter(|| plan.apply(black_box(&x), black_box(&mut out)))
    });
    c.bench_function("fracdelay/shift_2500 (plans each call)", |b| {
        b.iter(|| tofwave::dsp::fracdelay::shift(black_box(&x), black_box(0.37), &mut out))
    });
}

criterion_group!(benches, correlate, mlfit, average, fracdelay);
criterion_main!(benches);
