//! Sums in a fixed order of eight lanes: sample `i` goes to lane `i % 8`,
//! and the lanes are added pairwise at the end. The order is fixed by the
//! code, not by the CPU, so every target gives the same bits; the lanes are
//! independent, so the compiler vectorises them, where a sum in index order
//! is one serial chain of additions (4 cycles each). The rounding error is
//! that of eight interleaved sums (no larger than one serial sum's bound).

/// Lanes of the fixed summation order.
const LANES: usize = 8;

/// Adds the eight lanes pairwise: ((0+1)+(2+3)) + ((4+5)+(6+7)).
#[inline(always)]
fn fold(acc: [f64; LANES]) -> f64 {
    ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
}

/// Whether this CPU runs the AVX-512 copies of the lane loops below (the
/// same operations on the same lanes, so the same bits; picked at run time,
/// the detection cached by the standard library).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn wide() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
}

/// Whether this CPU runs the AVX2 copies (four lanes to a register, the
/// eight lanes in two: the same operations on the same lanes, so the same bits).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// Σ f(x_i) in the lane order (the neutral element −0.0 in every lane).
/// (An AVX-512 copy measured no faster: eight chains of one add each are
/// as quick in four SSE2 registers.)
#[inline(always)]
fn lane_sum<T: Copy>(x: &[T], f: impl Fn(T) -> f64) -> f64 {
    let mut acc = [-0.0f64; LANES];
    let chunks = x.chunks_exact(LANES);
    let rest = chunks.remainder();
    for c in chunks {
        for l in 0..LANES {
            acc[l] += f(c[l]);
        }
    }
    for (l, &v) in rest.iter().enumerate() {
        acc[l] += f(v);
    }
    fold(acc)
}

/// Σ x_i.
pub fn sum(x: &[f64]) -> f64 {
    lane_sum(x, |v| v)
}

/// Σ (x_i − centre).
pub fn shifted_sum(x: &[f64], centre: f64) -> f64 {
    lane_sum(x, |v| v - centre)
}

/// Σ (x_i − mean)².
pub fn sum_sq_dev(x: &[f64], mean: f64) -> f64 {
    lane_sum(x, |v| {
        let d = v - mean;
        d * d
    })
}

/// [`sum`] of the volts `code · g + o` (decoded as `Channel::volts_into`
/// decodes them: a multiply, then an add), bit for bit, without storing
/// them: a channel's statistics need not write the whole channel in volts.
pub fn code_sum(codes: &[i16], g: f64, o: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if wide() {
        // SAFETY: AVX-512F checked just above.
        return unsafe { code_sum_avx512(codes, g, o) };
    }
    lane_sum(codes, |c: i16| c as f64 * g + o)
}

/// [`sum_sq_dev`] of the volts `code · g + o`, bit for bit (see [`code_sum`]).
pub fn code_sum_sq_dev(codes: &[i16], g: f64, o: f64, mean: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if wide() {
        // SAFETY: AVX-512F checked just above.
        return unsafe { code_sum_sq_dev_avx512(codes, g, o, mean) };
    }
    code_sum_sq_dev_body(codes, g, o, mean)
}

#[inline(always)]
fn code_sum_sq_dev_body(codes: &[i16], g: f64, o: f64, mean: f64) -> f64 {
    lane_sum(codes, |c: i16| {
        let d = (c as f64 * g + o) - mean;
        d * d
    })
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn code_sum_avx512(codes: &[i16], g: f64, o: f64) -> f64 {
    lane_sum_codes_avx512(codes, |v| v, |c| c as f64 * g + o, g, o)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn code_sum_sq_dev_avx512(codes: &[i16], g: f64, o: f64, mean: f64) -> f64 {
    use std::arch::x86_64::{_mm512_mul_pd, _mm512_set1_pd, _mm512_sub_pd};
    let m = _mm512_set1_pd(mean);
    lane_sum_codes_avx512(
        codes,
        |v| {
            let d = _mm512_sub_pd(v, m);
            _mm512_mul_pd(d, d)
        },
        |c| {
            let d = (c as f64 * g + o) - mean;
            d * d
        },
        g,
        o,
    )
}

/// [`lane_sum`] of codes with the eight lanes in one AVX-512 register: each
/// code decoded (`c · g + o`, a multiply, then an add), mapped by `fv`
/// (`f` for the remainder, the same operations), then added to its lane.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn lane_sum_codes_avx512(
    x: &[i16],
    fv: impl Fn(std::arch::x86_64::__m512d) -> std::arch::x86_64::__m512d,
    f: impl Fn(i16) -> f64,
    g: f64,
    o: f64,
) -> f64 {
    use std::arch::x86_64::{__m128i, _mm256_cvtepi16_epi32, _mm512_add_pd, _mm512_cvtepi32_pd, _mm512_mul_pd, _mm512_set1_pd, _mm512_storeu_pd, _mm_loadu_si128};
    let (gv, ov) = (_mm512_set1_pd(g), _mm512_set1_pd(o));
    let mut acc = _mm512_set1_pd(-0.0);
    let chunks = x.chunks_exact(LANES);
    let rest = chunks.remainder();
    for c in chunks {
        // SAFETY: `c` holds eight i16, 128 bits.
        let codes = unsafe { _mm_loadu_si128(c.as_ptr().cast::<__m128i>()) };
        let v = _mm512_add_pd(_mm512_mul_pd(_mm512_cvtepi32_pd(_mm256_cvtepi16_epi32(codes)), gv), ov);
        acc = _mm512_add_pd(acc, fv(v));
    }
    let mut lanes = [0.0f64; LANES];
    // SAFETY: `lanes` holds eight f64.
    unsafe { _mm512_storeu_pd(lanes.as_mut_ptr(), acc) };
    for (l, &v) in rest.iter().enumerate() {
        lanes[l] += f(v);
    }
    fold(lanes)
}

/// (Σ s², Σ d·s, Σ d²) of d_i = x_i − mean over the pairs (x_i, s_i) (the
/// shorter slice sets the length): a least-squares amplitude fit's sums,
/// in one pass.
pub fn fit_sums(x: &[f64], s: &[f64], mean: f64) -> (f64, f64, f64) {
    #[cfg(target_arch = "x86_64")]
    if avx2() {
        // SAFETY: AVX2 checked just above.
        return unsafe { fit_sums_avx2(x, s, mean) };
    }
    fit_sums_body(x, s, mean)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn fit_sums_avx2(x: &[f64], s: &[f64], mean: f64) -> (f64, f64, f64) {
    fit_sums_body(x, s, mean)
}

#[inline(always)]
fn fit_sums_body(x: &[f64], s: &[f64], mean: f64) -> (f64, f64, f64) {
    let n = x.len().min(s.len());
    let (x, s) = (&x[..n], &s[..n]);
    let (mut ss, mut xs, mut xx) = ([-0.0f64; LANES], [-0.0f64; LANES], [-0.0f64; LANES]);
    let mut add = |l: usize, v: f64, s: f64| {
        let d = v - mean;
        ss[l] += s * s;
        xs[l] += d * s;
        xx[l] += d * d;
    };
    let (xc, sc) = (x.chunks_exact(LANES), s.chunks_exact(LANES));
    let (xr, sr) = (xc.remainder(), sc.remainder());
    for (a, b) in xc.zip(sc) {
        for l in 0..LANES {
            add(l, a[l], b[l]);
        }
    }
    for (l, (&v, &s)) in xr.iter().zip(sr).enumerate() {
        add(l, v, s);
    }
    (fold(ss), fold(xs), fold(xx))
}

/// (Σ d², Σ d³, Σ d⁴) of d_i = (x_i − shift) − mean, in one pass (in
/// AVX-512 registers where the CPU has them: 1.5x faster than SSE2's; else
/// in AVX2 ones where it has those).
pub fn central_power_sums(x: &[f64], shift: f64, mean: f64) -> (f64, f64, f64) {
    #[cfg(target_arch = "x86_64")]
    if wide() {
        // SAFETY: AVX-512F checked just above.
        return unsafe { central_power_sums_avx512(x, shift, mean) };
    }
    #[cfg(target_arch = "x86_64")]
    if avx2() {
        // SAFETY: AVX2 checked just above.
        return unsafe { central_power_sums_avx2(x, shift, mean) };
    }
    central_power_sums_body(x, shift, mean)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn central_power_sums_avx2(x: &[f64], shift: f64, mean: f64) -> (f64, f64, f64) {
    central_power_sums_body(x, shift, mean)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn central_power_sums_avx512(x: &[f64], shift: f64, mean: f64) -> (f64, f64, f64) {
    central_power_sums_body(x, shift, mean)
}

#[inline(always)]
fn central_power_sums_body(x: &[f64], shift: f64, mean: f64) -> (f64, f64, f64) {
    let (mut a2, mut a3, mut a4) = ([-0.0f64; LANES], [-0.0f64; LANES], [-0.0f64; LANES]);
    let chunks = x.chunks_exact(LANES);
    let rest = chunks.remainder();
    let mut add = |l: usize, v: f64| {
        let d = (v - shift) - mean;
        let d2 = d * d;
        a2[l] += d2;
        a3[l] += d2 * d;
        a4[l] += d2 * d2;
    };
    for c in chunks {
        for (l, &v) in c.iter().enumerate() {
            add(l, v);
        }
    }
    for (l, &v) in rest.iter().enumerate() {
        add(l, v);
    }
    (fold(a2), fold(a3), fold(a4))
}

/// Whether every value is finite (no NaN, no ±∞), checked a block at a
/// time (an early exit per value does not vectorise).
pub fn all_finite(x: &[f64]) -> bool {
    #[cfg(target_arch = "x86_64")]
    if wide() {
        // SAFETY: AVX-512F checked just above.
        return unsafe { all_finite_avx512(x) };
    }
    #[cfg(target_arch = "x86_64")]
    if avx2() {
        // SAFETY: AVX2 checked just above.
        return unsafe { all_finite_avx2(x) };
    }
    all_finite_body(x)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn all_finite_avx2(x: &[f64]) -> bool {
    all_finite_body(x)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn all_finite_avx512(x: &[f64]) -> bool {
    all_finite_body(x)
}

#[inline(always)]
fn all_finite_body(x: &[f64]) -> bool {
    x.chunks(64).all(|c| c.iter().fold(true, |ok, v| ok & v.is_finite()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn code_sums_are_the_sums_of_the_decoded_volts_bit_for_bit() {
        for n in [0usize, 1, 7, 8, 9, 1003] {
            let mut codes: Vec<i16> = (0..n).map(|i| ((i * 7919 % 4099) as i32 - 2049) as i16).collect();
            // The extreme codes among them.
            if n >= 9 {
                (codes[3], codes[8]) = (i16::MIN, i16::MAX);
            }
            for (g, o) in [(3.05e-5, -0.013), (1.0 / 256.0, 0.0), (-2e-3, 1.5)] {
                let volts: Vec<f64> = codes.iter().map(|&c| c as f64 * g + o).collect();
                assert_eq!(code_sum(&codes, g, o).to_bits(), sum(&volts).to_bits(), "n {n}");
                let mean = sum(&volts) / n.max(1) as f64;
                assert_eq!(code_sum_sq_dev(&codes, g, o, mean).to_bits(), sum_sq_dev(&volts, mean).to_bits(), "n {n}");
            }
        }
    }

    #[test]
    fn sums_match_the_serial_sums_to_rounding_and_follow_the_lane_order_exactly() {
        let x: Vec<f64> = (0..1003).map(|i| ((i * 37 % 101) as f64 * 0.37).sin() + 3.0).collect();
        let serial: f64 = x.iter().sum();
        assert!((sum(&x) - serial).abs() <= 1e-12 * serial.abs());
        // The fixed order, written out.
        let mut lanes = [-0.0f64; 8];
        for (i, v) in x.iter().enumerate() {
            lanes[i % 8] += v - 3.0;
        }
        let want = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
        assert_eq!(shifted_sum(&x, 3.0).to_bits(), want.to_bits());
        let mean = sum(&x) / x.len() as f64;
        let (m2, m3, m4) = central_power_sums(&x, 0.0, mean);
        let d = |p: i32| x.iter().map(|v| (v - mean).powi(p)).sum::<f64>();
        assert!((m2 - d(2)).abs() <= 1e-12 * d(2));
        assert!((m3 - d(3)).abs() <= 1e-12 * d(2).powf(1.5));
        assert!((m4 - d(4)).abs() <= 1e-12 * d(4));
        assert!((sum_sq_dev(&x, mean) - m2).abs() <= 1e-12 * m2);
        assert_eq!(sum(&[]), -0.0);
        assert!(all_finite(&x) && all_finite(&[]));
        let mut y = x.clone();
        y[700] = f64::NAN;
        assert!(!all_finite(&y));
        y[700] = f64::NEG_INFINITY;
        assert!(!all_finite(&y));
        assert_eq!(sum(&[2.5]), 2.5);
    }

    #[test]
    fn every_copy_a_cpu_may_run_gives_the_portable_bits() {
        let x: Vec<f64> = (0..1003).map(|i| ((i * 37 % 101) as f64 * 0.37).sin() * 1e3 + 3.0).collect();
        let s: Vec<f64> = (0..1000).map(|i| ((i * 13 % 61) as f64 * 0.21).cos()).collect();
        let mut odd = x.clone();
        (odd[5], odd[700], odd[1002]) = (f64::NAN, f64::INFINITY, f64::NEG_INFINITY);
        for n in [0usize, 1, 7, 8, 9, 15, 16, 17, 1000, 1003] {
            // Finiteness on values with a NaN or an infinity in reach too.
            let odd = &odd[..n];
            assert_eq!(all_finite(odd), all_finite_body(odd), "all_finite, n {n}");
            assert_eq!(all_finite_body(odd), n <= 5, "n {n}");
            #[cfg(target_arch = "x86_64")]
            if avx2() {
                // SAFETY: AVX2 checked just above.
                assert_eq!(unsafe { all_finite_avx2(odd) }, n <= 5, "AVX2, n {n}");
            }
            let (x, mean) = (&x[..n], 2.75);
            let want = (fit_sums_body(x, &s, mean), central_power_sums_body(x, 1.5, mean), all_finite_body(x));
            let bits = |(a, b, c): (f64, f64, f64)| [a.to_bits(), b.to_bits(), c.to_bits()];
            assert_eq!(bits(fit_sums(x, &s, mean)), bits(want.0), "fit_sums, n {n}");
            assert_eq!(bits(central_power_sums(x, 1.5, mean)), bits(want.1), "central_power_sums, n {n}");
            #[cfg(target_arch = "x86_64")]
            if avx2() {
                // SAFETY: AVX2 checked just above.
                let got = unsafe { (fit_sums_avx2(x, &s, mean), central_power_sums_avx2(x, 1.5, mean), all_finite_avx2(x)) };
                assert_eq!((bits(got.0), bits(got.1), got.2), (bits(want.0), bits(want.1), want.2), "AVX2, n {n}");
            }
            #[cfg(target_arch = "x86_64")]
            if wide() {
                // SAFETY: AVX-512F checked just above.
                let got = unsafe { (central_power_sums_avx512(x, 1.5, mean), all_finite_avx512(x)) };
                assert_eq!((bits(got.0), got.1), (bits(want.1), want.2), "AVX-512, n {n}");
            }
        }
    }
}
