//! Exact correlation of i16 ADC codes with i16 taps in i32 arithmetic.
//!
//! A digitiser's codes are integers, and a template quantised to 16-bit taps
//! makes the matched filter's sum an integer too: `Σ_j q[j]·c[k + j]`. Where
//! it fits in an i32 (the caller checks `Σ|q|·max|c| ≤ i32::MAX`) the sum is
//! exact, so every path below gives the same bits, and one SIMD instruction
//! (`vpmaddwd`) does 32 (AVX-512) or 16 (AVX2) multiply-adds where the f64
//! filter's fused multiply-add does 8 or 4.
//!
//! Layout: output `k + 2i` (even lanes) reads the codes from `k + j` on as
//! i16 pairs, so tap pair `(q[j], q[j + 1])` multiplies `(c[k + 2i + j],
//! c[k + 2i + j + 1])` and `vpmaddwd` adds the two products; output
//! `k + 2i + 1` (odd lanes) reads from `k + j + 1`. The two accumulators are
//! interleaved on the way out.

/// Largest `Σ|q|·max|c|` for which [`correlate_valid`] is exact.
pub const EXACT_LIMIT: i64 = i32::MAX as i64;

/// `out[k] = Σ_j q[j]·c[k + j]` for `k < out.len()`, exactly, in i32.
///
/// Requires `q.len()` even and non-zero (pad an odd template with a zero
/// tap), `out.len() + q.len() - 1 <= c.len()` (checked: violating either
/// panics), and `Σ|q|·max|c| <= EXACT_LIMIT` over the codes read (not
/// checked here; beyond it the sums wrap, the same on every path).
pub fn correlate_valid(q: &[i16], c: &[i16], out: &mut [i32]) {
    assert!(!q.is_empty() && q.len().is_multiple_of(2), "taps: a non-zero even count");
    assert!(out.len() + q.len() - 1 <= c.len(), "codes: out.len() + taps - 1 of them");
    let done = match path() {
        // SAFETY: path() saw AVX-512F, AVX-512BW and AVX2 on this CPU.
        #[cfg(target_arch = "x86_64")]
        Path::Avx512 => unsafe { blocks_avx512(q, c, out) },
        // SAFETY: path() saw AVX2 on this CPU.
        #[cfg(target_arch = "x86_64")]
        Path::Avx2 => unsafe { blocks_avx2(q, c, out) },
        _ => 0,
    };
    portable(q, c, out, done);
}

/// Which copy of the loop runs on this CPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Path {
    Avx512,
    Avx2,
    Portable,
}

fn path() -> Path {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx2")
        {
            return Path::Avx512;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            return Path::Avx2;
        }
    }
    Path::Portable
}

/// Outputs from `from` on, eight at a time where whole, then one by one
/// (wrapping i32 arithmetic: the same sums as the SIMD paths).
fn portable(q: &[i16], c: &[i16], out: &mut [i32], from: usize) {
    let l = q.len();
    let mut k = from;
    while k + 8 <= out.len() {
        let mut acc = [0i32; 8];
        let xs = &c[k..k + l + 7];
        for (j, &h) in q.iter().enumerate() {
            let w: &[i16; 8] = xs[j..j + 8].try_into().expect("slice has length 8");
            for b in 0..8 {
                acc[b] = acc[b].wrapping_add(i32::from(h) * i32::from(w[b]));
            }
        }
        out[k..k + 8].copy_from_slice(&acc);
        k += 8;
    }
    for (kk, o) in out.iter_mut().enumerate().skip(k) {
        *o = q.iter().zip(&c[kk..kk + l]).fold(0i32, |s, (&h, &x)| s.wrapping_add(i32::from(h) * i32::from(x)));
    }
}

/// The tap pair `(q[j], q[j + 1])` as one i32 lane (low half first), as
/// `vpmaddwd` pairs its i16 operands.
#[inline(always)]
fn pair(q: &[i16], j: usize) -> i32 {
    (u32::from(q[j] as u16) | (u32::from(q[j + 1] as u16) << 16)) as i32
}

/// Whole blocks of 128 outputs, then of 32, from `out[0]` on; returns where
/// it stopped.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn blocks_avx512(q: &[i16], c: &[i16], out: &mut [i32]) -> usize {
    let l = q.len();
    let mut k = 0;
    while k + 128 <= out.len() {
        // The block reads c[k .. k + 128 + l - 1) (see block_avx512).
        assert!(k + 128 + l - 1 <= c.len());
        // SAFETY: the features are enabled here; the bounds were checked just above.
        unsafe { block_avx512::<4>(q, c.as_ptr().add(k), out.as_mut_ptr().add(k)) };
        k += 128;
    }
    while k + 32 <= out.len() {
        assert!(k + 32 + l - 1 <= c.len());
        // SAFETY: as above.
        unsafe { block_avx512::<1>(q, c.as_ptr().add(k), out.as_mut_ptr().add(k)) };
        k += 32;
    }
    k
}

/// Outputs `out[0 .. 32·S]`: `S` sub-blocks of 32, each an even and an odd
/// accumulator of 16 lanes (2·S independent chains). Reads `cs[0 .. 32·S + l - 1)`.
/// (Loading the codes once per eight pairs and shifting them into place in
/// registers, as the f64 filter does, measured 8 % slower here.)
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
unsafe fn block_avx512<const S: usize>(q: &[i16], cs: *const i16, out: *mut i32) {
    use std::arch::x86_64::{
        __m512i, _mm512_add_epi32, _mm512_loadu_si512, _mm512_madd_epi16, _mm512_permutex2var_epi32, _mm512_set1_epi32,
        _mm512_setr_epi32, _mm512_setzero_si512, _mm512_storeu_si512,
    };
    let mut even = [_mm512_setzero_si512(); S];
    let mut odd = [_mm512_setzero_si512(); S];
    // SAFETY (every read): sub-block b's loads start at 32b + j and 32b + j + 1
    // for j <= l - 2 and read 32 codes: below 32(S - 1) + l + 31 = 32S + l - 1.
    unsafe {
        for j in (0..q.len()).step_by(2) {
            let w = _mm512_set1_epi32(pair(q, j));
            for (b, (e, o)) in even.iter_mut().zip(odd.iter_mut()).enumerate() {
                let p = cs.add(32 * b + j);
                *e = _mm512_add_epi32(*e, _mm512_madd_epi16(_mm512_loadu_si512(p.cast::<__m512i>()), w));
                *o = _mm512_add_epi32(*o, _mm512_madd_epi16(_mm512_loadu_si512(p.add(1).cast::<__m512i>()), w));
            }
        }
        let lo = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
        let hi = _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
        for (b, (e, o)) in even.iter().zip(&odd).enumerate() {
            let dst = out.add(32 * b);
            _mm512_storeu_si512(dst.cast::<__m512i>(), _mm512_permutex2var_epi32(*e, lo, *o));
            _mm512_storeu_si512(dst.add(16).cast::<__m512i>(), _mm512_permutex2var_epi32(*e, hi, *o));
        }
    }
}

/// Whole blocks of 64 outputs, then of 16, from `out[0]` on; returns where
/// it stopped.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn blocks_avx2(q: &[i16], c: &[i16], out: &mut [i32]) -> usize {
    let l = q.len();
    let mut k = 0;
    while k + 64 <= out.len() {
        assert!(k + 64 + l - 1 <= c.len());
        // SAFETY: AVX2 is enabled here; the bounds were checked just above.
        unsafe { block_avx2::<4>(q, c.as_ptr().add(k), out.as_mut_ptr().add(k)) };
        k += 64;
    }
    while k + 16 <= out.len() {
        assert!(k + 16 + l - 1 <= c.len());
        // SAFETY: as above.
        unsafe { block_avx2::<1>(q, c.as_ptr().add(k), out.as_mut_ptr().add(k)) };
        k += 16;
    }
    k
}

/// Outputs `out[0 .. 16·S]`, as [`block_avx512`] with 8-lane accumulators.
/// Reads `cs[0 .. 16·S + l - 1)`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn block_avx2<const S: usize>(q: &[i16], cs: *const i16, out: *mut i32) {
    use std::arch::x86_64::{
        __m256i, _mm256_add_epi32, _mm256_loadu_si256, _mm256_madd_epi16, _mm256_permute2x128_si256, _mm256_set1_epi32,
        _mm256_setzero_si256, _mm256_storeu_si256, _mm256_unpackhi_epi32, _mm256_unpacklo_epi32,
    };
    let mut even = [_mm256_setzero_si256(); S];
    let mut odd = [_mm256_setzero_si256(); S];
    // SAFETY (every read): loads of 16 codes from 16b + j and 16b + j + 1,
    // j <= l - 2: below 16(S - 1) + l + 15 = 16S + l - 1.
    unsafe {
        for j in (0..q.len()).step_by(2) {
            let w = _mm256_set1_epi32(pair(q, j));
            for b in 0..S {
                let p = cs.add(16 * b + j);
                even[b] = _mm256_add_epi32(even[b], _mm256_madd_epi16(_mm256_loadu_si256(p.cast::<__m256i>()), w));
                odd[b] = _mm256_add_epi32(odd[b], _mm256_madd_epi16(_mm256_loadu_si256(p.add(1).cast::<__m256i>()), w));
            }
        }
        for b in 0..S {
            // unpacklo: e0 o0 e1 o1 | e4 o4 e5 o5; unpackhi: e2 o2 e3 o3 | e6 o6 e7 o7.
            let l = _mm256_unpacklo_epi32(even[b], odd[b]);
            let h = _mm256_unpackhi_epi32(even[b], odd[b]);
            let o = out.add(16 * b);
            _mm256_storeu_si256(o.cast::<__m256i>(), _mm256_permute2x128_si256::<0x20>(l, h));
            _mm256_storeu_si256(o.add(8).cast::<__m256i>(), _mm256_permute2x128_si256::<0x31>(l, h));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn naive(q: &[i16], c: &[i16], n: usize) -> Vec<i32> {
        (0..n).map(|k| q.iter().zip(&c[k..]).map(|(&h, &x)| i32::from(h) * i32::from(x)).sum()).collect()
    }

    /// Taps up to 12000 and 12-bit codes at full scale: 64 taps stay below
    /// the exactness limit (2^31) whatever their signs.
    fn case(rng: &mut rand_chacha::ChaCha8Rng, taps: usize, len: usize) -> (Vec<i16>, Vec<i16>) {
        let q: Vec<i16> = (0..taps).map(|_| rng.random_range(-12000..=12000)).collect();
        let c: Vec<i16> = (0..len).map(|_| rng.random_range(-2048..=2047)).collect();
        (q, c)
    }

    #[test]
    fn every_path_is_the_exact_sum() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for &(taps, outs) in &[(2, 1), (2, 40), (64, 2437), (64, 130), (10, 16), (64, 31), (4, 200), (66, 129)] {
            let (q, c) = case(&mut rng, taps, outs + taps - 1);
            let want = naive(&q, &c, outs);
            let mut got = vec![0; outs];
            correlate_valid(&q, &c, &mut got);
            assert_eq!(got, want, "dispatched path, {taps} taps, {outs} outputs");
            let mut got = vec![-1; outs];
            portable(&q, &c, &mut got, 0);
            assert_eq!(got, want, "portable path, {taps} taps, {outs} outputs");
            #[cfg(target_arch = "x86_64")]
            {
                if std::arch::is_x86_feature_detected!("avx2") {
                    let mut got = vec![-1; outs];
                    // SAFETY: AVX2 checked just above.
                    let k = unsafe { blocks_avx2(&q, &c, &mut got) };
                    portable(&q, &c, &mut got, k);
                    assert_eq!(got, want, "AVX2 path, {taps} taps, {outs} outputs");
                }
                if path() == Path::Avx512 {
                    let mut got = vec![-1; outs];
                    // SAFETY: path() saw the features.
                    let k = unsafe { blocks_avx512(&q, &c, &mut got) };
                    portable(&q, &c, &mut got, k);
                    assert_eq!(got, want, "AVX-512 path, {taps} taps, {outs} outputs");
                }
            }
        }
    }

    #[test]
    fn extreme_codes_and_taps_within_the_limit_are_exact() {
        // One tap pair at ±2^15 with codes at ±2^15: |sum| up to 2^31 - 2^16 + ...
        let q = [i16::MIN, i16::MAX];
        let c = [i16::MIN, i16::MIN, i16::MAX, 0, i16::MIN];
        let want = naive(&q, &c, 4);
        let mut got = vec![0; 4];
        correlate_valid(&q, &c, &mut got);
        assert_eq!(got, want);
    }

    #[test]
    fn sums_past_the_limit_wrap_alike_on_every_path() {
        // Every product at +2^30: 64 taps sum to 2^36, far past i32.
        let q = vec![i16::MIN; 64];
        let c = vec![i16::MIN; 64 + 200 - 1];
        let want: Vec<i32> = (0..200)
            .map(|k| q.iter().zip(&c[k..]).fold(0i32, |s, (&h, &x)| s.wrapping_add(i32::from(h) * i32::from(x))))
            .collect();
        let mut got = vec![0; 200];
        correlate_valid(&q, &c, &mut got);
        assert_eq!(got, want, "dispatched path ({:?})", path());
        let mut got = vec![-1; 200];
        portable(&q, &c, &mut got, 0);
        assert_eq!(got, want, "portable path");
    }

    #[test]
    #[should_panic(expected = "even count")]
    fn an_odd_tap_count_is_refused() {
        correlate_valid(&[1, 2, 3], &[0; 10], &mut [0; 4]);
    }
}
