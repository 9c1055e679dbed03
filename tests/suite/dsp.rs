//! Integration tests of the pure DSP kernels against naive references, exact
//! arithmetic and the Cramér–Rao bound. Fixed seeds throughout; Monte-Carlo
//! tolerances are derived from the trial count at 99 % confidence.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, StandardNormal};

use tofwave::dsp::accumulate::{
    CodeAccumulator, add_codes_i8, add_codes_i16, add_codes_i32, add_f64, div_round,
    mean_from_sums, robust_average,
};
use tofwave::math::select::{median, trimmed_mean};
use tofwave::dsp::correlate::{CorrelationMethod, Correlator};
use tofwave::dsp::fracdelay::{FractionalDelay, shift};
use tofwave::dsp::mlfit::{FitOptions, fit_delay, fit_delay_with};
use tofwave::dsp::pulse::{Pulse, PulseShape};
use tofwave::scene::Scene;

// ---------------------------------------------------------------------------
// Allocation counting: the per-frame paths must not allocate. Counted per
// thread, because the test harness runs tests on several threads.

struct CountingAlloc;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: CountingAlloc = CountingAlloc;

/// Allocations made by `f` on this thread.
fn allocations_in(f: impl FnOnce()) -> u64 {
    let before = ALLOCATIONS.with(|c| c.get());
    f();
    ALLOCATIONS.with(|c| c.get()) - before
}

/// Two-sided 99 % standard-normal quantile.
const Z99: f64 = 2.575_829_303_548_901;
/// One-sided 99 % standard-normal quantile.
const Z99_ONE_SIDED: f64 = 2.326_347_874_040_841;

fn default_return_pulse() -> Pulse {
    // The default scene's return pulse on the prototype's 1 GS/s digitiser.
    Scene::default_scene().return_pulse.pulse(1e-9)
}

fn gaussian_vec(rng: &mut ChaCha8Rng, n: usize) -> Vec<f64> {
    (0..n).map(|_| StandardNormal.sample(rng)).collect()
}

// ---------------------------------------------------------------------------
// correlate

fn naive_correlation(taps: &[f64], x: &[f64]) -> Vec<f64> {
    if taps.is_empty() || x.len() < taps.len() {
        return Vec::new();
    }
    (0..=x.len() - taps.len())
        .map(|k| taps.iter().enumerate().map(|(j, t)| t * x[k + j]).sum())
        .collect()
}

/// Both methods against the naive sum, relative to the output's scale
/// (max |naive output|), for short, medium and long templates and inputs from
/// shorter than the template (empty output) to 4× the planned length.
#[test]
fn correlate_matches_naive_sum_for_both_methods() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x5eed_c0de);
    let planned = 2500;
    for &l in &[1usize, 2, 7, 64, 130, 300] {
        let taps = gaussian_vec(&mut rng, l);
        let mut lens = vec![
            0,
            l - 1,
            l,
            l + 1,
            l + 17,
            2 * l + 3,
            1000,
            2500,
            2501,
            4099,
            10000,
        ];
        lens.retain(|&n| n <= 10000);
        for method in [CorrelationMethod::Direct, CorrelationMethod::Fft] {
            let mut c = Correlator::with_method(&taps, planned, method);
            assert_eq!(c.method(), method);
            assert_eq!(c.taps(), &taps[..]);
            let mut out = vec![f64::NAN; 3]; // stale content must be cleared
            for &n in &lens {
                let x = gaussian_vec(&mut rng, n);
                c.correlate(&x, &mut out);
                let want = naive_correlation(&taps, &x);
                assert_eq!(out.len(), want.len(), "{method:?} L={l} n={n}");
                let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for (k, (a, b)) in out.iter().zip(&want).enumerate() {
                    assert!(
                        (a - b).abs() <= 1e-12 * scale,
                        "{method:?} L={l} n={n} k={k}: {a} vs {b}"
                    );
                }
            }
        }
    }
}

#[test]
fn correlate_empty_template_gives_empty_output() {
    for method in [CorrelationMethod::Direct, CorrelationMethod::Fft] {
        let mut c = Correlator::with_method(&[], 100, method);
        let mut out = vec![1.0];
        c.correlate(&[1.0, 2.0], &mut out);
        assert!(out.is_empty());
    }
}

/// `new` picks the cheaper method by the cost model: direct for a short
/// template, FFT for a long one on a 2500-sample frame, and the choice agrees
/// with the estimates it reports.
#[test]
fn correlate_new_follows_the_cost_model() {
    use tofwave::dsp::correlate::estimated_cost_ns;
    for &l in &[1usize, 7, 64, 130, 300] {
        let c = Correlator::new(&vec![1.0; l], 2500);
        let d = estimated_cost_ns(CorrelationMethod::Direct, l, 2500);
        let f = estimated_cost_ns(CorrelationMethod::Fft, l, 2500);
        let want = if f < d {
            CorrelationMethod::Fft
        } else {
            CorrelationMethod::Direct
        };
        assert_eq!(c.method(), want, "L={l}: direct {d} ns, fft {f} ns");
        assert_eq!(c.fft_block_len().is_some(), want == CorrelationMethod::Fft);
    }
    assert_eq!(
        Correlator::new(&[1.0; 7], 2500).method(),
        CorrelationMethod::Direct
    );
    assert_eq!(
        Correlator::new(&[1.0; 300], 2500).method(),
        CorrelationMethod::Fft
    );
}

#[test]
fn correlate_allocates_nothing_once_out_has_capacity() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let x = gaussian_vec(&mut rng, 2500);
    for (l, method) in [
        (64, CorrelationMethod::Direct),
        (64, CorrelationMethod::Fft),
        (300, CorrelationMethod::Fft),
    ] {
        let taps = gaussian_vec(&mut rng, l);
        let mut c = Correlator::with_method(&taps, 2500, method);
        let mut out = Vec::with_capacity(2500);
        let n = allocations_in(|| {
            for _ in 0..3 {
                c.correlate(&x, &mut out);
            }
        });
        assert_eq!(n, 0, "{method:?} L={l}");
    }
}

// ---------------------------------------------------------------------------
// mlfit

/// Samples `baseline + amplitude·shape(k − delay)`.
fn synth(n: usize, baseline: f64, amplitude: f64, shape: &dyn PulseShape, delay: f64) -> Vec<f64> {
    (0..n)
        .map(|k| baseline + amplitude * shape.value_and_slope(k as f64 - delay).0)
        .collect()
}

/// Noise-free data: exact delay (1e-9 samples) and amplitude for sub-sample
/// delays across a whole sample period, from starts 1.5 samples off either
/// way, for the default bigaussian return and for a narrow (σ = 0.8) pulse.
#[test]
fn mlfit_is_exact_on_noise_free_data() {
    let wide = default_return_pulse();
    assert!(
        (wide.sigma_rise - 4.79).abs() < 0.01 && (wide.sigma_fall - 17.3).abs() < 0.05,
        "{wide:?}"
    );
    let narrow = Pulse {
        sigma_rise: 0.8,
        sigma_fall: 0.8,
    };
    for (shape, before, after) in [(wide, 20usize, 45usize), (narrow, 6, 7)] {
        for i in 0..=20 {
            let delay = 300.0 + i as f64 / 20.0;
            let (baseline, amplitude) = (0.013, 0.71);
            let x = synth(1000, baseline, amplitude, &shape, delay);
            let center = delay.round() as usize;
            for start_off in [-1.5, -0.7, 0.0, 0.9, 1.5] {
                let fit = fit_delay(
                    &x,
                    baseline,
                    &shape,
                    delay + start_off,
                    center - before..center + after,
                    50,
                );
                assert!(
                    fit.converged,
                    "{shape:?} d={delay} start {start_off}: {fit:?}"
                );
                assert!(
                    (fit.delay - delay).abs() < 1e-9,
                    "{shape:?} d={delay} start {start_off}: {fit:?}"
                );
                assert!(
                    (fit.amplitude - amplitude).abs() < 1e-9 * amplitude,
                    "{fit:?}"
                );
                assert!(fit.residual_rms < 1e-12, "{fit:?}");
                let se: f64 = (center - before..center + after)
                    .map(|k| shape.value_and_slope(k as f64 - delay).1.powi(2))
                    .sum();
                assert!((fit.slope_energy - se).abs() < 1e-9 * se, "{fit:?} vs {se}");
            }
        }
    }
}

/// A pulse cut by the frame edge (leading edge before sample 0, or the tail
/// past the end) is still fitted exactly from what the window holds.
#[test]
fn mlfit_handles_pulses_cut_by_the_frame_edge() {
    let shape = default_return_pulse();
    // Tail cut: peak 6.7 samples before the end of a 400-sample frame.
    let x = synth(400, -0.002, 0.4, &shape, 393.3);
    let fit = fit_delay(&x, -0.002, &shape, 392.0, 360..450, 50);
    assert!(fit.converged && (fit.delay - 393.3).abs() < 1e-9, "{fit:?}");
    assert!((fit.amplitude - 0.4).abs() < 1e-9, "{fit:?}");
    // Leading edge cut: peak 2.4 samples into the frame, rise before sample 0.
    let x = synth(400, 0.0, 1.2, &shape, 2.4);
    let fit = fit_delay(&x, 0.0, &shape, 3.9, 0..60, 50);
    assert!(fit.converged && (fit.delay - 2.4).abs() < 1e-9, "{fit:?}");
    assert!((fit.amplitude - 1.2).abs() < 1e-9, "{fit:?}");
}

/// No signal, an empty window or non-finite samples give a defined answer:
/// zero amplitude, `converged == false`, finite numbers.
#[test]
fn mlfit_degenerate_inputs_are_flagged_not_nan() {
    let shape = default_return_pulse();
    let flat = vec![0.25; 200];
    let fit = fit_delay(&flat, 0.25, &shape, 100.0, 70..140, 50);
    assert_eq!(fit.amplitude, 0.0, "{fit:?}");
    assert!(
        !fit.converged && fit.delay.is_finite() && fit.residual_rms == 0.0,
        "{fit:?}"
    );
    assert_eq!(fit.delay_crb_samples(0.01), f64::INFINITY);

    let fit = fit_delay(&flat, 0.25, &shape, 100.0, 150..150, 50);
    assert!(
        !fit.converged && fit.amplitude == 0.0 && fit.delay == 100.0,
        "{fit:?}"
    );
    // A window reaching past the frame is cut to it.
    let fit = fit_delay(&flat, 0.25, &shape, 100.0, 190..500, 50);
    assert!(!fit.converged && fit.amplitude == 0.0, "{fit:?}");

    let mut bad = synth(200, 0.0, 1.0, &shape, 100.0);
    bad[101] = f64::NAN;
    let fit = fit_delay(&bad, 0.0, &shape, 100.0, 70..140, 50);
    assert!(
        !fit.converged && fit.amplitude == 0.0 && fit.delay == 100.0,
        "{fit:?}"
    );
    let fit = fit_delay(
        &synth(200, 0.0, 1.0, &shape, 100.0),
        0.0,
        &shape,
        f64::NAN,
        70..140,
        50,
    );
    assert!(!fit.converged && fit.delay.is_finite(), "{fit:?}");
}

/// Without the coarse scan a narrow pulse started 1.5 samples off is still
/// found (the line search keeps every step downhill); with it, too.
#[test]
fn mlfit_without_scan_still_converges_from_a_poor_start() {
    let shape = Pulse {
        sigma_rise: 0.8,
        sigma_fall: 0.8,
    };
    let x = synth(100, 0.0, 1.0, &shape, 50.3);
    let opts = FitOptions {
        search_half_width: 0.0,
        ..FitOptions::default()
    };
    for start in [48.8, 51.8] {
        let fit = fit_delay_with(&x, 0.0, &shape, start, 44..57, 100, &opts);
        assert!(
            fit.converged && (fit.delay - 50.3).abs() < 1e-9,
            "start {start}: {fit:?}"
        );
    }
}

#[test]
fn mlfit_allocates_nothing() {
    let shape = default_return_pulse();
    let x = synth(2500, 0.0, 1.0, &shape, 1234.56);
    let n = allocations_in(|| {
        let fit = fit_delay(&x, 0.0, &shape, 1233.5, 1214..1274, 50);
        assert!(fit.converged);
    });
    assert_eq!(n, 0);
}

/// Monte-Carlo at peak SNR 20 dB (A/σ = 10) in white Gaussian noise: the
/// delay's standard deviation is within 1.1× of the Cramér–Rao bound
/// σ/(A·sqrt(slope_energy)) and its bias below 0.1 of it.
///
/// Tolerances at 99 % for `TRIALS` trials: the sample standard deviation's
/// relative standard error is 1/sqrt(2(n−1)), so the hypothesis sd ≤ 1.1·CRB is
/// rejected only when sd_hat > 1.1·CRB·(1 + z₀.₉₉·se) (one-sided); sd_hat must
/// also not fall below CRB·(1 − z₀.₉₉₅·se) (an estimator beating the bound
/// means the test is broken). The mean's standard error is sd_hat/sqrt(n), so
/// |bias| ≤ 0.1·CRB + z₀.₉₉₅·sd_hat/sqrt(n).
#[test]
fn mlfit_delay_spread_attains_the_cramer_rao_bound() {
    const TRIALS: usize = 5000;
    let mut rng = ChaCha8Rng::seed_from_u64(20_251_122);
    let (amplitude, sigma) = (1.0, 0.1); // 20·log10(A/σ) = 20 dB
    let noise = Normal::new(0.0, sigma).expect("valid sigma");
    let cases: [(Pulse, f64, usize, usize); 2] = [
        (default_return_pulse(), 1000.37, 20, 45),
        (
            Pulse {
                sigma_rise: 0.8,
                sigma_fall: 0.8,
            },
            1000.37,
            6,
            7,
        ),
    ];
    for (shape, delay, before, after) in cases {
        let clean = synth(2500, 0.0, amplitude, &shape, delay);
        let center = delay.round() as usize;
        let window = center - before..center + after;
        let slope_energy: f64 = window
            .clone()
            .map(|k| shape.value_and_slope(k as f64 - delay).1.powi(2))
            .sum();
        let crb = sigma / (amplitude * slope_energy.sqrt());
        let mut x = clean.clone();
        let (mut sum, mut sum_sq) = (0.0, 0.0);
        let mut errors = Vec::with_capacity(TRIALS);
        for _ in 0..TRIALS {
            for (xi, ci) in x[window.clone()].iter_mut().zip(&clean[window.clone()]) {
                *xi = ci + noise.sample(&mut rng);
            }
            let start = delay + rng.random_range(-1.5..=1.5);
            let fit = fit_delay(&x, 0.0, &shape, start, window.clone(), 50);
            assert!(fit.converged, "{fit:?}");
            let e = fit.delay - delay;
            errors.push(e);
            sum += e;
        }
        let mean = sum / TRIALS as f64;
        for e in &errors {
            sum_sq += (e - mean) * (e - mean);
        }
        let sd = (sum_sq / (TRIALS - 1) as f64).sqrt();
        let se_rel = 1.0 / (2.0 * (TRIALS - 1) as f64).sqrt();
        let ratio = sd / crb;
        eprintln!(
            "{shape:?}: CRB {crb:.5} samples, sd {sd:.5} (ratio {ratio:.4}), bias {mean:.2e} ({:.3} CRB)",
            mean / crb
        );
        assert!(
            ratio <= 1.1 * (1.0 + Z99_ONE_SIDED * se_rel),
            "{shape:?}: sd/CRB = {ratio}"
        );
        assert!(
            ratio >= 1.0 - Z99 * se_rel,
            "{shape:?}: sd/CRB = {ratio} below the bound"
        );
        assert!(
            mean.abs() <= 0.1 * crb + Z99 * sd / (TRIALS as f64).sqrt(),
            "{shape:?}: bias {mean} vs CRB {crb}"
        );
    }
}

// ---------------------------------------------------------------------------
// average

/// A 16-sample frame with extreme and mixed codes, accumulated 10^7 times:
/// the i64 sums are exactly code·10^7 (|sum| reaches 3.3e11, far past f32's
/// and i32's exact range), and the mean is the code back.
#[test]
fn i16_accumulation_of_ten_million_frames_is_exact() {
    const FRAMES: u64 = 10_000_000;
    let frame: [i16; 16] = [
        i16::MAX,
        i16::MIN,
        -1,
        0,
        1,
        12_345,
        -12_345,
        i16::MAX - 1,
        i16::MIN + 1,
        255,
        -256,
        7,
        -7,
        30_000,
        -30_000,
        2,
    ];
    let mut acc = vec![0i64; 16];
    for _ in 0..FRAMES {
        add_codes_i16(&mut acc, &frame);
    }
    let mut blocked = CodeAccumulator::new(16);
    for _ in 0..FRAMES {
        blocked.add_i16(&frame);
    }
    assert_eq!(blocked.frames(), FRAMES);
    for (i, &c) in frame.iter().enumerate() {
        assert_eq!(acc[i], c as i64 * FRAMES as i64, "sample {i}");
    }
    assert_eq!(blocked.sums(), &acc[..]);
    let mut mean = vec![0.0; 16];
    mean_from_sums(&acc, FRAMES, 1.0, 0.0, &mut mean);
    for (m, &c) in mean.iter().zip(&frame) {
        assert_eq!(*m, c as f64);
    }
}

/// Widths other than i16, the f64 path, and shorter inputs (only the overlap
/// is added), against a plain loop; lengths cover the chunked body and tail.
#[test]
fn add_kernels_match_plain_loops() {
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    for n in [0usize, 1, 15, 16, 17, 100, 2500] {
        let x8: Vec<i8> = (0..n).map(|_| rng.random()).collect();
        let x16: Vec<i16> = (0..n).map(|_| rng.random()).collect();
        let x32: Vec<i32> = (0..n).map(|_| rng.random()).collect();
        let xf = gaussian_vec(&mut rng, n);
        let mut a = vec![5i64; n + 3];
        let mut want = a.clone();
        add_codes_i8(&mut a, &x8);
        add_codes_i16(&mut a, &x16);
        add_codes_i32(&mut a, &x32);
        for i in 0..n {
            want[i] += x8[i] as i64 + x16[i] as i64 + x32[i] as i64;
        }
        assert_eq!(a, want);
        let mut af = vec![0.5; n];
        add_f64(&mut af, &xf);
        for i in 0..n {
            assert_eq!(af[i], 0.5 + xf[i]);
        }
        let mut acc = CodeAccumulator::new(n);
        acc.add_i8(&x8);
        acc.add_i16(&x16);
        acc.add_i32(&x32);
        let direct: Vec<i64> = want[..n].iter().map(|v| v - 5).collect();
        assert_eq!(acc.sums(), &direct[..]);
        acc.reset();
        assert!(acc.sums().iter().all(|&v| v == 0) && acc.frames() == 0);
    }
}

/// The i32 partial sums flush before they could overflow, even with mixed
/// widths at the extreme codes: 3·2^16 frames of i16::MIN, plus i8::MIN frames.
#[test]
fn code_accumulator_flushes_before_i32_overflow() {
    let mut acc = CodeAccumulator::new(2);
    let frames = 3 * (1u64 << 16) + 5;
    for _ in 0..frames {
        acc.add_i16(&[i16::MIN, i16::MAX]);
        acc.add_i8(&[i8::MIN, i8::MAX]);
    }
    let want = [
        frames as i64 * (i16::MIN as i64 + i8::MIN as i64),
        frames as i64 * (i16::MAX as i64 + i8::MAX as i64),
    ];
    assert_eq!(acc.sums(), &want);
    assert_eq!(acc.frames(), 2 * frames);
}

/// Checks that `m` is `s/n` correctly rounded: |m − s/n| ≤ ulp(m)/2, in exact
/// integer arithmetic (m = M·2^E, so the test is 2·|M·n − s·2^−E| ≤ n for E < 0).
fn assert_correctly_rounded(m: f64, s: i64, n: u64) {
    let bits = m.to_bits();
    let exp = ((bits >> 52) & 0x7ff) as i32;
    assert!(exp > 0, "normal numbers only");
    let mant = ((bits & ((1u64 << 52) - 1)) | (1u64 << 52)) as i128 * if m < 0.0 { -1 } else { 1 };
    let e = exp - 1075; // m = mant·2^e
    let (lhs, rhs) = if e < 0 {
        // 2·|mant·n − s·2^−e| ≤ n  (ulp = 2^e; ties allowed)
        let diff = mant * n as i128 - ((s as i128) << -e);
        (2 * diff.abs(), n as i128)
    } else {
        let diff = (mant << e) * n as i128 - s as i128;
        (2 * diff.abs(), (n as i128) << e)
    };
    assert!(lhs <= rhs, "{m} is not s/n = {s}/{n} correctly rounded");
}

/// The mean from exact sums is the correctly rounded quotient, including sums
/// far past 2^53 where the f64 sum itself would already be inexact.
#[test]
fn mean_from_sums_is_the_correctly_rounded_mean() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    // A random stack of i16 frames: the mean of codes vs exact arithmetic.
    let (frames, len) = (1001u64, 64);
    let mut acc = vec![0i64; len];
    let mut exact = vec![0i128; len];
    for _ in 0..frames {
        let x: Vec<i16> = (0..len).map(|_| rng.random()).collect();
        add_codes_i16(&mut acc, &x);
        for (e, &v) in exact.iter_mut().zip(&x) {
            *e += v as i128;
        }
    }
    let mut mean = vec![0.0; len];
    mean_from_sums(&acc, frames, 1.0, 0.0, &mut mean);
    for i in 0..len {
        assert_eq!(acc[i] as i128, exact[i]);
        if acc[i] != 0 {
            assert_correctly_rounded(mean[i], acc[i], frames);
        }
    }
    // Huge sums and awkward divisors, both signs.
    for _ in 0..20_000 {
        let s: i64 = rng.random::<i64>() >> rng.random_range(0..40);
        let n: u64 = (rng.random::<u64>() >> rng.random_range(0..64)).max(1);
        if s != 0 {
            assert_correctly_rounded(div_round(s, n), s, n);
        }
    }
    // Scaling to volts: offset + volts_per_code · mean.
    let mut v = [0.0; 2];
    mean_from_sums(&[3, -5], 2, 0.5, 0.1, &mut v);
    assert_eq!(v, [0.1 + 0.5 * 1.5, 0.1 + 0.5 * -2.5]);
}

/// Naive trimmed mean by sorting.
fn trimmed_by_sort(values: &[f64], t: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let g = ((t.clamp(0.0, 0.5) * n as f64).floor() as usize).min((n - 1) / 2);
    let kept = &v[g..n - g];
    kept.iter().sum::<f64>() / kept.len() as f64
}

#[test]
fn robust_average_matches_sorting_and_rejects_outliers() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for frames in [1usize, 2, 3, 4, 9, 10, 33] {
        let stack: Vec<Vec<f64>> = (0..frames).map(|_| gaussian_vec(&mut rng, 50)).collect();
        let refs: Vec<&[f64]> = stack.iter().map(|f| f.as_slice()).collect();
        let mut scratch = Vec::new();
        for t in [0.0, 0.1, 0.25, 0.4, 0.5] {
            let mut out = vec![0.0; 50];
            robust_average(&refs, t, &mut out, &mut scratch);
            for i in 0..50 {
                let col: Vec<f64> = stack.iter().map(|f| f[i]).collect();
                let want = trimmed_by_sort(&col, t);
                assert!(
                    (out[i] - want).abs() <= 1e-14 * (1.0 + want.abs()),
                    "frames {frames} t {t}: {} vs {want}",
                    out[i]
                );
            }
        }
    }
    // Nine copies of a ramp and one frame of spikes: the median ignores the spikes.
    let ramp: Vec<f64> = (0..20).map(|i| i as f64 * 0.01).collect();
    let spikes = vec![1e6; 20];
    let mut refs: Vec<&[f64]> = vec![&ramp; 9];
    refs.push(&spikes);
    let mut out = vec![0.0; 20];
    let mut scratch = Vec::new();
    robust_average(&refs, 0.5, &mut out, &mut scratch);
    assert_eq!(out, ramp);
    robust_average(&refs, 0.1, &mut out, &mut scratch);
    for (o, r) in out.iter().zip(&ramp) {
        assert!((o - r).abs() < 1e-15);
    }
    // Warm scratch: no allocation.
    let n = allocations_in(|| robust_average(&refs, 0.2, &mut out, &mut scratch));
    assert_eq!(n, 0);
    // No frames: no average.
    robust_average(&[], 0.5, &mut out, &mut scratch);
    assert!(out.iter().all(|v| v.is_nan()));
    let mut v = [2.0, f64::NAN, 1.0];
    assert_eq!(median(&mut v), Some(2.0));
    assert_eq!(trimmed_mean(&mut [], 0.1), None);
}

#[test]
fn accumulation_allocates_nothing() {
    let x: Vec<i16> = (0..2500).map(|i| (i * 13) as i16).collect();
    let mut acc = vec![0i64; 2500];
    let mut blocked = CodeAccumulator::new(2500);
    let mut mean = vec![0.0; 2500];
    let n = allocations_in(|| {
        for _ in 0..70_000 {
            blocked.add_i16(&x);
        }
        add_codes_i16(&mut acc, &x);
        blocked.mean_v(1e-3, 0.0, &mut mean);
    });
    assert_eq!(n, 0);
    assert!((mean[1] - 13e-3).abs() < 1e-17);
}

// ---------------------------------------------------------------------------
// fracdelay

/// Sum of sinusoids below 0.4·fs at continuous sample time `t`.
fn tones(t: f64) -> f64 {
    const TONES: [(f64, f64, f64); 4] = [
        (1.0, 0.013, 0.3),
        (0.7, 0.11, 1.1),
        (0.5, 0.27, -0.4),
        (0.8, 0.39, 2.0),
    ];
    TONES
        .iter()
        .map(|(a, nu, ph)| a * (2.0 * std::f64::consts::PI * nu * t + ph).sin())
        .sum()
}
/// Σ|amplitudes| of `tones`.
const TONES_SCALE: f64 = 3.0;

/// Shifting band-limited content (tones up to 0.39·fs) matches the analytic
/// shift to 2.5e-5 of the amplitude (the filter's designed worst-case response
/// error is 2.2e-5 up to 0.4·fs), and shifting back reproduces the input to
/// 5e-5, away from the edges (the first/last 48 samples see the edge extension).
#[test]
fn fracdelay_shift_and_back_reproduces_band_limited_signal() {
    let n = 1200;
    let x: Vec<f64> = (0..n).map(|i| tones(i as f64)).collect();
    let (mut y, mut z) = (vec![0.0; n], vec![0.0; n]);
    for d in [0.1, 0.25, 0.5, 0.77, -0.3, 3.6, -12.45] {
        shift(&x, d, &mut y);
        shift(&y, -d, &mut z);
        let (mut e1, mut e2) = (0.0f64, 0.0f64);
        for i in 48 + 13..n - 48 - 13 {
            e1 = e1.max((y[i] - tones(i as f64 - d)).abs());
            e2 = e2.max((z[i] - x[i]).abs());
        }
        assert!(e1 <= 2.5e-5 * TONES_SCALE, "delay {d}: shift error {e1}");
        assert!(e2 <= 5e-5 * TONES_SCALE, "delay {d}: round-trip error {e2}");
    }
}

/// Largest |shift(pulse, d) − pulse(· − d)| over the frame, relative to the peak.
fn pulse_shift_error(shape: &Pulse, peak: f64, d: f64) -> (f64, Vec<f64>) {
    let n = 600;
    let x = synth(n, 0.0, 1.0, shape, peak);
    let mut y = vec![0.0; n];
    shift(&x, d, &mut y);
    let emax = y
        .iter()
        .enumerate()
        .map(|(i, v)| (v - shape.value_and_slope(i as f64 - peak - d).0).abs())
        .fold(0.0, f64::max);
    (emax, y)
}

/// The default return pulse (1 GS/s) with its peak between samples, shifted
/// by ±0.5 so the peak lands on a sample, loses less than 0.01 dB (measured:
/// 1.7e-5 dB), and any fractional shift matches the analytic pulse to 1e-3 of
/// the peak (measured: 4.4e-4). That is the pulse's own limit, not the
/// filter's: the bigaussian's curvature jumps at the peak (1/σ_rise² vs
/// 1/σ_fall²), which leaves ~3.5e-4 of its spectrum between 0.4 and 0.5·fs,
/// where the filter rolls off. A smooth (Gaussian, σ = 3 samples) pulse is
/// shifted to 5e-6 (measured: 2.4e-6 to 2.9e-6).
#[test]
fn fracdelay_keeps_the_default_pulse_peak() {
    let shape = default_return_pulse();
    let peak = 300.5;
    for d in [0.5, -0.5] {
        let (emax, y) = pulse_shift_error(&shape, peak, d);
        let loss_db = -20.0 * y[(peak + d) as usize].log10();
        eprintln!("bigaussian shift {d}: max error {emax:.3e}, peak loss {loss_db:.3e} dB");
        assert!(loss_db.abs() < 0.01, "shift {d}: peak loss {loss_db} dB");
        assert!(emax < 1e-3, "shift {d}: error {emax}");
    }
    for d in [0.13, 0.61, -0.87, 2.5] {
        let (emax, _) = pulse_shift_error(&shape, peak, d);
        assert!(emax < 1e-3, "shift {d}: error {emax}");
        let smooth = Pulse {
            sigma_rise: 3.0,
            sigma_fall: 3.0,
        };
        let (emax, _) = pulse_shift_error(&smooth, peak, d);
        eprintln!("gaussian shift {d}: max error {emax:.3e}");
        assert!(emax < 5e-6, "smooth pulse, shift {d}: error {emax}");
    }
}

/// Integer delays are exact shifts with the edge value repeated, for any
/// size of delay including beyond the signal.
#[test]
fn fracdelay_integer_delays_are_exact() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let x = gaussian_vec(&mut rng, 300);
    let mut y = vec![0.0; 300];
    for d in [0i64, 1, -1, 5, -17, 64, 299, 300, -400, 10_000] {
        shift(&x, d as f64, &mut y);
        for (i, v) in y.iter().enumerate() {
            let k = (i as i64 - d).clamp(0, 299) as usize;
            assert_eq!(*v, x[k], "delay {d} sample {i}");
        }
    }
}

/// A constant stays constant under any shift (unit DC gain plus the edge
/// repeat), a planned filter equals `shift`, short signals and long `out`
/// slices are handled, and applying a plan allocates nothing.
#[test]
fn fracdelay_invariants() {
    let c = vec![0.731; 100];
    let mut y = vec![0.0; 100];
    for d in [0.3, -0.5, 7.25, -99.9, 150.5] {
        shift(&c, d, &mut y);
        assert!(y.iter().all(|v| (v - 0.731).abs() < 1e-15), "delay {d}");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let x = gaussian_vec(&mut rng, 2500);
    let plan = FractionalDelay::new(-2.37);
    assert_eq!(plan.taps().len(), 32);
    assert_eq!(plan.delay(), -2.37);
    let (mut a, mut b) = (vec![0.0; 2500], vec![0.0; 2500]);
    shift(&x, -2.37, &mut a);
    let n = allocations_in(|| plan.apply(&x, &mut b));
    assert_eq!(n, 0);
    assert_eq!(a, b);
    // Edge outputs are the filter applied to the edge-extended signal.
    let ext = |k: i64| x[k.clamp(0, 2499) as usize];
    for i in [0usize, 1, 5, 20, 2480, 2499] {
        // Tap m multiplies x[i − whole − H + m], whole = floor(−2.37) = −3, H = 16.
        let base = i as i64 + 3 - 16;
        let want: f64 = plan
            .taps()
            .iter()
            .enumerate()
            .map(|(m, t)| t * ext(base + m as i64))
            .sum();
        assert!((b[i] - want).abs() < 1e-12, "sample {i}");
    }
    // Short input and an output longer than the input.
    let short = [1.0, 2.0, 3.0];
    let mut out = [9.0; 5];
    shift(&short, 0.5, &mut out);
    assert_eq!(&out[3..], &[9.0, 9.0]);
    assert!(
        out[..3]
            .iter()
            .all(|v| v.is_finite() && (0.9..=3.1).contains(v)),
        "{out:?}"
    );
    shift(&[], 0.5, &mut out);
}

// ---------------------------------------------------------------------------
// property tests

proptest::proptest! {
    /// Any sum and any count: the mean of codes is s/n correctly rounded.
    #[test]
    fn prop_div_round_is_correctly_rounded(s in proptest::num::i64::ANY, n in 1u64..) {
        if s != 0 {
            assert_correctly_rounded(div_round(s, n), s, n);
        } else {
            proptest::prop_assert_eq!(div_round(s, n), 0.0);
        }
    }

    /// Selection-based trimmed mean equals the sort-based one for any stack.
    #[test]
    fn prop_trimmed_mean_matches_sorting(
        v in proptest::collection::vec(-1e6f64..1e6, 1..60),
        t in 0.0f64..0.6,
    ) {
        let want = trimmed_by_sort(&v, t);
        let got = trimmed_mean(&mut v.clone(), t).expect("non-empty");
        proptest::prop_assert!((got - want).abs() <= 1e-9 * (1.0 + want.abs()), "{} vs {}", got, want);
    }

    /// Correlation is exact for any template and input (both methods agree
    /// with the naive sum to 1e-12 of the output scale).
    #[test]
    fn prop_correlation_matches_naive(
        taps in proptest::collection::vec(-1.0f64..1.0, 1..40),
        x in proptest::collection::vec(-1.0f64..1.0, 0..300),
    ) {
        let want = naive_correlation(&taps, &x);
        let scale = want.iter().fold(1e-300f64, |m, v| m.max(v.abs()));
        for method in [CorrelationMethod::Direct, CorrelationMethod::Fft] {
            let mut c = Correlator::with_method(&taps, 128, method);
            let mut out = Vec::new();
            c.correlate(&x, &mut out);
            proptest::prop_assert_eq!(out.len(), want.len());
            for (a, b) in out.iter().zip(&want) {
                proptest::prop_assert!((a - b).abs() <= 1e-12 * scale.max(1e-3), "{:?}: {} vs {}", method, a, b);
            }
        }
    }
}

/// The ML fit started at the interpolated peak of the pulse's own matched
/// filter, as the start stage starts it, needs no coarse scan on a pulse
/// well above its noise: on the reference scene's start and return pulses,
/// in white noise, the fit without it gives the very bits of the fit with
/// it at 4 σ and 6 σ (peak over noise; the start stage times pulses of
/// 6 σ and more). None in 10 000 trials per level and pulse: a rate below
/// 3e-4 at 95 % confidence (fixed seed). Below 4 σ the scan does matter now
/// and then, which is why the resolver, which fits down to its threshold,
/// keeps it for pulses below 6 σ of its filter's noise (`detect::resolve`).
#[test]
fn ml_from_a_matched_peak_needs_no_scan_well_above_the_noise() {
    const TRIALS: usize = 10_000;
    let scene = tofwave::bench::reference_scene();
    let dt = scene.digitiser.sample_interval_s;
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    for (name, shape) in [("start", scene.start_pulse.shape(dt)), ("return", scene.return_pulse.shape(dt))] {
        let (taps, peak_tap) = shape.template();
        let (lo, hi) = shape.support();
        for snr in [4.0, 6.0] {
            let mut differ = 0usize;
            for _ in 0..TRIALS {
                let truth = 200.0 + rng.random::<f64>();
                let x: Vec<f64> = (0..400).map(|k| snr * shape.value_and_slope(k as f64 - truth).0 + rng.sample::<f64, _>(StandardNormal)).collect();
                // The matched filter near the pulse, its largest output interpolated.
                let y: Vec<f64> = (0..400).map(|p| if !(179..=221).contains(&p) { f64::NEG_INFINITY } else { taps.iter().enumerate().map(|(j, t)| t * x[p + j - peak_tap]).sum() }).collect();
                let best = (180..221).max_by(|&a, &b| y[a].total_cmp(&y[b])).expect("a range");
                let start = best as f64 + tofwave::dsp::interp::parabolic(y[best - 1], y[best], y[best + 1]).0;
                let window = (start + lo).floor() as usize..(start + hi).ceil() as usize + 1;
                let scanned = fit_delay_with(&x, 0.0, &shape, start, window.clone(), 30, &FitOptions::default());
                let plain = fit_delay_with(&x, 0.0, &shape, start, window, 30, &FitOptions::from_matched_peak());
                differ += usize::from(scanned.delay.to_bits() != plain.delay.to_bits() || scanned.amplitude.to_bits() != plain.amplitude.to_bits());
            }
            assert_eq!(differ, 0, "{name} pulse at {snr} σ: {differ} of {TRIALS} fits differ");
        }
    }
}
