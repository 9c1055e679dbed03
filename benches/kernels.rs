//! Criterion benches of the DSP kernels at the prototype's frame size
//! (2500 samples at 1 GS/s), in pipeline order: decode, baseline (noise
//! gate), average, matched filter (FIR and FFT), threshold scan,
//! interpolation, ML refinement, the events test's coloured variance. Run: `cargo bench --bench kernels` (add
//! `-- --quick` for a fast pass).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use tofwave::detect::kernels::{local_maxima, upcrossings};
use tofwave::detect::noise_model::NoiseFitter;
use tofwave::dsp::accumulate::{CodeAccumulator, add_codes_i16, add_f64};
use tofwave::dsp::correlate::{CorrelationMethod, Correlator};
use tofwave::dsp::correlate_codes;
use tofwave::dsp::fracdelay::FractionalDelay;
use tofwave::dsp::mlfit::fit_delay;
use tofwave::dsp::pulse::PulseShape;
use tofwave::dsp::{crossing, interp};
use tofwave::frame::{Channel, ChannelRole, Samples};
use tofwave::math::autocov::{lag_product_sums, toeplitz_quadratic_form};
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
        // The same correlation on i16 codes with i16 taps, exact in i32.
        let q: Vec<i16> = taps.iter().chain(std::iter::repeat_n(&0.0, taps_len % 2)).map(|t| (t * 4000.0) as i16).collect();
        let codes: Vec<i16> = x.iter().map(|v| (v * 400.0) as i16).collect();
        let mut out = vec![0i32; FRAME - q.len() + 1];
        c.bench_function(&format!("correlate/{taps_len}taps_{FRAME}/i16 codes"), |b| {
            b.iter(|| {
                correlate_codes::correlate_valid(black_box(&q), black_box(&codes), &mut out);
                black_box(out[0])
            })
        });
    }
}

fn mlfit(c: &mut Criterion) {
    let shape = Scene::default_scene().return_pulse.pulse(1e-9);
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

/// i16 codes of a 2500-sample frame: ~3000 codes of noise.
fn codes(seed: u64) -> Vec<i16> {
    noise(FRAME, seed)
        .iter()
        .map(|v| (v * 3000.0) as i16)
        .collect()
}

fn decode(c: &mut Criterion) {
    let ch = Channel {
        name: "CH2".into(),
        role: ChannelRole::Stop,
        samples: Samples::I16(codes(7)),
        volts_per_code: 2.5 / 8192.0,
        offset_v: -1e-3,
    };
    let mut out = Vec::with_capacity(FRAME);
    c.bench_function("decode/i16_to_volts_2500", |b| {
        b.iter(|| {
            black_box(&ch).volts_into(&mut out);
            black_box(out.len())
        })
    });
}

fn baseline(c: &mut Criterion) {
    // The prototype's gates: ~230 pre-trigger samples and ~1200 beyond the range gate.
    let x = noise(FRAME, 8);
    let mut fitter = NoiseFitter::default();
    c.bench_function("baseline/noise_fit_230+1200", |b| {
        b.iter(|| black_box(fitter.fit(&[black_box(&x[..230]), black_box(&x[1300..])], 1e-3)))
    });
}

fn threshold_scan(c: &mut Criterion) {
    let y = noise(FRAME, 9);
    let mut peaks = Vec::with_capacity(64);
    // Q^-1(1e-6 / 1000) ≈ 5.6 sigma: a noise-only frame (the common case).
    c.bench_function("threshold/local_maxima_2500", |b| {
        b.iter(|| {
            local_maxima(black_box(&y), 0..FRAME, 5.6, &mut peaks);
            black_box(peaks.len())
        })
    });
    c.bench_function("threshold/upcrossings_2500", |b| {
        b.iter(|| black_box(upcrossings(black_box(&y), 0..FRAME, 2.0)))
    });
}

fn interpolation(c: &mut Criterion) {
    // 1000 peak triples, so the loop overhead of criterion does not dominate.
    let t: Vec<(f64, f64, f64)> = noise(3000, 10)
        .chunks_exact(3)
        .map(|v| (0.8 + 0.05 * v[0], 1.0, 0.7 + 0.05 * v[2]))
        .collect();
    c.bench_function("interp/parabolic_x1000", |b| {
        b.iter(|| {
            black_box(&t)
                .iter()
                .map(|&(m, z, p)| interp::parabolic(m, z, p).0)
                .sum::<f64>()
        })
    });
    c.bench_function("interp/gaussian_x1000", |b| {
        b.iter(|| {
            black_box(&t)
                .iter()
                .map(|&(m, z, p)| interp::gaussian(m, z, p).0)
                .sum::<f64>()
        })
    });
    let shape = Scene::default_scene().return_pulse.pulse(1e-9);
    let x: Vec<f64> = (0..FRAME)
        .map(|k| shape.value_and_slope(k as f64 - 1234.4).0)
        .collect();
    c.bench_function("crossing/rising_before_half", |b| {
        b.iter(|| black_box(crossing::rising_before(black_box(&x), 0.5, 1150, 1234)))
    });
}

/// The events test's coloured variance qᵀRq of a projected pulse column:
/// a 211-sample window and 90 lags of noise colour (the default scene's),
/// as the quadratic form and as lag sums then a dot product with ρ.
fn toeplitz(c: &mut Criterion) {
    let q = noise(211, 7);
    let rho: Vec<f64> = (0..90).map(|k| 0.9f64.powi(k)).collect();
    let mut pad = Vec::new();
    c.bench_function("toeplitz/form_211x90", |b| b.iter(|| black_box(toeplitz_quadratic_form(black_box(&q), &rho, &mut pad))));
    let (mut sums, mut centred) = (vec![0.0; 90], Vec::new());
    c.bench_function("toeplitz/lag_sums_211x90", |b| {
        b.iter(|| {
            lag_product_sums(black_box(&q), 0.0, &mut sums, &mut centred);
            black_box(sums[1..].iter().zip(&rho[1..]).fold(sums[0], |v, (s, r)| v + 2.0 * r * s))
        })
    });
}

criterion_group!(
    benches,
    toeplitz,
    decode,
    baseline,
    average,
    correlate,
    threshold_scan,
    interpolation,
    mlfit,
    fracdelay
);
criterion_main!(benches);
