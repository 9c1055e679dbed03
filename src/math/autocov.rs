//! Autocovariance: the one lag-product kernel of the crate and the pooled
//! accumulator built on it.
//!
//! Every autocovariance in the crate (the accumulator below, the noise
//! colour of `detect::colour`, the sample autocorrelation of
//! `detect::noise_model`) is a sum of lag products Σ (x_i − c)(x_{i+k} − c)
//! over one contiguous segment; they differ in the centre `c` (a fixed
//! shift, a frame's gate mean, the sample mean, or 0 for data centred
//! already) and in what they do with the sums. [`lag_product_sum`] is that
//! sum, always in index order, so each caller keeps its exact arithmetic.

/// Σ_{i < n−lag} (x_i − centre)(x_{i+lag} − centre), summed in index order;
/// 0 when `lag ≥ x.len()`. Allocation-free.
pub fn lag_product_sum(x: &[f64], lag: usize, centre: f64) -> f64 {
    let n = x.len();
    if lag >= n {
        return 0.0;
    }
    x[..n - lag]
        .iter()
        .zip(&x[lag..])
        .map(|(a, b)| (a - centre) * (b - centre))
        .sum::<f64>()
}

/// [`lag_product_sum`] for every lag `k < out.len()` at once, each bit for
/// bit the same (a sum in index order of the same products): `out[k]` gets
/// the lag-`k` sum (0 for `k ≥ x.len()`). The lags are computed side by side,
/// a block of them per sample (vector lanes, picked at run time where AVX2
/// or AVX-512 is there), instead of one serial sum after another.
/// `centred` is scratch (`x − centre`), kept by the caller.
pub fn lag_product_sums(x: &[f64], centre: f64, out: &mut [f64], centred: &mut Vec<f64>) {
    out.fill(0.0);
    let lags = out.len().min(x.len());
    if lags == 0 {
        return;
    }
    centred.clear();
    centred.extend(x.iter().map(|v| v - centre));
    let out = &mut out[..lags];
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: AVX-512F checked just above.
            return unsafe { lag_sums_avx512(centred, out) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 checked just above.
            return unsafe { lag_sums_avx2(centred, out) };
        }
    }
    lag_sums_body::<16>(centred, out);
}

/// [`lag_product_sums`] for integer codes `c` about a centre `centre` (in
/// codes, not necessarily an integer), in codes²: about the integer `r`
/// nearest the centre the products `d_i·d_{i+k}` (d = c − r) are summed
/// exactly in integers, and the centre's fractional part `f` enters
/// exactly as algebra says, Σ (d_i − f)(d_{i+k} − f) = D_k − f·(A_k + B_k) +
/// (n − k)·f², with A_k, B_k the two ranges' exact sums of d. |f| ≤ 1/2, so
/// nothing cancels that the f64 sum would have kept: the result is within
/// a few ulp of Σd² (the lag-0 sum) of the exact sum, where the f64 kernel
/// rounds every product. False (nothing written) where a code lies more than 2^12 from
/// `r` or the centre is not finite: the caller sums in f64.
/// `d` is scratch, kept by the caller.
pub fn code_lag_product_sums(c: &[i16], centre: f64, out: &mut [f64], d: &mut Vec<i16>) -> bool {
    const MAX_D: i32 = super::code_stats::MAX_DISTANCE;
    if !(centre.abs() < 1e6) {
        return false;
    }
    let r = centre.round();
    let ri = r as i32;
    if let Some((lo, hi)) = super::code_stats::code_min_max(&[c])
        && (i32::from(hi) - ri > MAX_D || ri - i32::from(lo) > MAX_D)
    {
        return false;
    }
    d.clear();
    // |c − r| ≤ 2^12: fits an i16.
    d.extend(c.iter().map(|&v| (i32::from(v) - ri) as i16));
    out.fill(0.0);
    let n = d.len();
    let f = centre - r;
    let total: i64 = d.iter().map(|&v| i64::from(v)).sum();
    // A_k = Σ_{i<n−k} d_i and B_k = Σ_{i≥k} d_i, updated lag by lag.
    let (mut a, mut b) = (total, total);
    for (k, o) in out.iter_mut().enumerate().take(n) {
        if k > 0 {
            a -= i64::from(d[n - k]);
            b -= i64::from(d[k - 1]);
        }
        let dk = dot_i16(&d[..n - k], &d[k..]);
        *o = dk as f64 - f * (a + b) as f64 + (n - k) as f64 * (f * f);
    }
    true
}

/// Σ a_i·b_i exactly for |a_i|, |b_i| ≤ 2^12 (the caller's bound): pairs of
/// products summed in i32 lanes (`vpmaddwd` where the CPU has AVX-512BW or
/// AVX2), widened to i64 after at most 32 vectors (32 pair sums of at most
/// 2^25 per lane stay below 2^31).
fn dot_i16(a: &[i16], b: &[i16]) -> i64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw") {
            // SAFETY: AVX-512F and AVX-512BW checked just above.
            return unsafe { dot_i16_avx512(a, b) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 checked just above.
            return unsafe { dot_i16_avx2(a, b) };
        }
    }
    dot_i16_from(a, b, 0, 0)
}

/// `acc` plus Σ a_i·b_i from `from` on, in i64.
fn dot_i16_from(a: &[i16], b: &[i16], from: usize, acc: i64) -> i64 {
    acc + a[from..].iter().zip(&b[from..]).map(|(&x, &y)| i64::from(x) * i64::from(y)).sum::<i64>()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw")]
fn dot_i16_avx512(a: &[i16], b: &[i16]) -> i64 {
    use std::arch::x86_64::{
        __m512i, _mm512_add_epi32, _mm512_loadu_si512, _mm512_madd_epi16, _mm512_reduce_add_epi64, _mm512_setzero_si512,
        _mm512_add_epi64, _mm512_castsi512_si256, _mm512_cvtepi32_epi64, _mm512_extracti64x4_epi64,
    };
    let n = a.len();
    let mut wide = _mm512_setzero_si512();
    let mut k = 0;
    while k + 32 <= n {
        // Up to 32 vectors of 32 products per lane pair: |sum| ≤ 32·2·2^24 = 2^30.
        let mut acc = _mm512_setzero_si512();
        let end = (k + 32 * 32).min(n - n % 32);
        while k < end {
            // SAFETY: k + 32 <= n for both slices.
            let (x, y) = unsafe { (_mm512_loadu_si512(a.as_ptr().add(k).cast::<__m512i>()), _mm512_loadu_si512(b.as_ptr().add(k).cast::<__m512i>())) };
            acc = _mm512_add_epi32(acc, _mm512_madd_epi16(x, y));
            k += 32;
        }
        wide = _mm512_add_epi64(wide, _mm512_cvtepi32_epi64(_mm512_castsi512_si256(acc)));
        wide = _mm512_add_epi64(wide, _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(acc)));
    }
    dot_i16_from(a, b, k, _mm512_reduce_add_epi64(wide))
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn dot_i16_avx2(a: &[i16], b: &[i16]) -> i64 {
    use std::arch::x86_64::{
        __m256i, _mm256_add_epi32, _mm256_add_epi64, _mm256_castsi256_si128, _mm256_cvtepi32_epi64, _mm256_extracti128_si256,
        _mm256_loadu_si256, _mm256_madd_epi16, _mm256_setzero_si256, _mm256_storeu_si256,
    };
    let n = a.len();
    let mut wide = _mm256_setzero_si256();
    let mut k = 0;
    while k + 16 <= n {
        // Up to 32 vectors of 16 products per lane pair: |sum| ≤ 2^30.
        let mut acc = _mm256_setzero_si256();
        let end = (k + 32 * 16).min(n - n % 16);
        while k < end {
            // SAFETY: k + 16 <= n for both slices.
            let (x, y) = unsafe { (_mm256_loadu_si256(a.as_ptr().add(k).cast::<__m256i>()), _mm256_loadu_si256(b.as_ptr().add(k).cast::<__m256i>())) };
            acc = _mm256_add_epi32(acc, _mm256_madd_epi16(x, y));
            k += 16;
        }
        wide = _mm256_add_epi64(wide, _mm256_cvtepi32_epi64(_mm256_castsi256_si128(acc)));
        wide = _mm256_add_epi64(wide, _mm256_cvtepi32_epi64(_mm256_extracti128_si256::<1>(acc)));
    }
    let mut lanes = [0i64; 4];
    // SAFETY: lanes is 32 bytes.
    unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast::<__m256i>(), wide) };
    dot_i16_from(a, b, k, lanes.iter().sum())
}

/// Σ_{i < n−k} d_i·d_{i+k} for every lag `k < out.len()` (`out.len() <=
/// d.len()`) of data centred already, each bit for bit the serial sum in
/// index order ([`lag_product_sum`] with centre 0), for a short `d` (a
/// template or a pulse's slope: tens to hundreds of samples): lags in blocks
/// of 8, then 4, then alone, where the gate kernel's long blocks would leave
/// most of their work to their scalar tails. Twice as fast as one serial
/// sum per lag at 70-100 samples.
pub fn lag_sums_short(d: &[f64], out: &mut [f64]) {
    let out_len = out.len().min(d.len());
    let out = &mut out[..out_len];
    let k = lag_blocks::<8>(d, out, 0);
    let k = lag_blocks::<4>(d, out, k);
    lag_blocks::<1>(d, out, k);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn lag_sums_avx512(d: &[f64], out: &mut [f64]) {
    // Blocks of 32 lags in four zmm accumulators, written out (the
    // compiler's copy of `lag_blocks::<32>` ran 1.2x slower). Where one to
    // three lags would be left after the blocks (65 lags: a 64-tap
    // template's), the last block carries them as scalar chains beside its
    // vectors: alone, one serial chain of adds cost as much as half a block.
    let len = out.len();
    let mut k = 0;
    while k + 32 <= len {
        // SAFETY: AVX-512F is enabled for this function; k + 32 + E <= len <= d.len().
        unsafe {
            match len - k - 32 {
                1 => return lag_block_avx512::<1>(d, out, k),
                2 => return lag_block_avx512::<2>(d, out, k),
                3 => return lag_block_avx512::<3>(d, out, k),
                _ => lag_block_avx512::<0>(d, out, k),
            }
        }
        k += 32;
    }
    let k = lag_blocks::<4>(d, out, k);
    lag_blocks::<1>(d, out, k);
}

/// One sample of [`lag_block_avx512`]: the lag window at offset `R` within
/// the eight samples' five loaded vectors, times the sample, added (a
/// multiply, then an add) to each accumulator.
#[cfg(target_arch = "x86_64")]
macro_rules! lag_sample_avx512 {
    ($r:literal, $di:expr, $a:ident, $acc:ident) => {{
        use std::arch::x86_64::{_mm512_add_pd, _mm512_alignr_epi64, _mm512_castpd_si512, _mm512_castsi512_pd, _mm512_mul_pd, _mm512_set1_pd};
        let di = _mm512_set1_pd($di);
        for z in 0..4 {
            // Lanes R..8 of vector z, then 0..R of vector z + 1.
            let w = if $r == 0 {
                $a[z]
            } else {
                _mm512_castsi512_pd(_mm512_alignr_epi64::<$r>(_mm512_castpd_si512($a[z + 1]), _mm512_castpd_si512($a[z])))
            };
            $acc[z] = _mm512_add_pd($acc[z], _mm512_mul_pd(di, w));
        }
    }};
}

/// Lags `k0 .. k0 + 32 + E` (`k0 + 32 + E <= out.len() <= d.len()`): as
/// [`lag_blocks`] does them, lane by lane the same chain `acc += d_i·d_{i+k}`
/// in index order (a multiply, then an add), 32 lags in zmm registers and
/// `E` in scalar registers. The lag window of sample i, d[i + k0 ..][..32],
/// is loaded once per eight samples (five loads, not 32 that nearly all
/// split a cache line) and shifted into place in registers (`valignq`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
unsafe fn lag_block_avx512<const E: usize>(d: &[f64], out: &mut [f64], k0: usize) {
    use std::arch::x86_64::{_mm512_add_pd, _mm512_loadu_pd, _mm512_maskz_loadu_pd, _mm512_mul_pd, _mm512_set1_pd, _mm512_setzero_pd, _mm512_storeu_pd};
    let n = d.len();
    let b = 32 + E;
    assert!(k0 + b <= out.len() && out.len() <= n);
    let all = n - (k0 + b - 1);
    let mut acc = [_mm512_set1_pd(-0.0); 4];
    let mut ex = [-0.0f64; E];
    let p = d.as_ptr();
    let mut i = 0;
    // SAFETY (every read): sample i < all reads d[i + k0 + 31 + E] at most,
    // below n; a group of eight (i + 8 <= all) loads d[i + k0 ..][..39]
    // (the fifth vector masked to its first seven lanes), below
    // i + k0 + 39 <= all + k0 + 31 <= n.
    unsafe {
        while i + 8 <= all {
            let q = p.add(i + k0);
            let mut a = [_mm512_setzero_pd(); 5];
            for (m, v) in a.iter_mut().enumerate().take(4) {
                *v = _mm512_loadu_pd(q.add(8 * m));
            }
            a[4] = _mm512_maskz_loadu_pd(0x7f, q.add(32));
            let s = &d[i..i + 8];
            lag_sample_avx512!(0, s[0], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[0] * *q.add(32 + e);
            }
            lag_sample_avx512!(1, s[1], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[1] * *q.add(33 + e);
            }
            lag_sample_avx512!(2, s[2], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[2] * *q.add(34 + e);
            }
            lag_sample_avx512!(3, s[3], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[3] * *q.add(35 + e);
            }
            lag_sample_avx512!(4, s[4], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[4] * *q.add(36 + e);
            }
            lag_sample_avx512!(5, s[5], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[5] * *q.add(37 + e);
            }
            lag_sample_avx512!(6, s[6], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[6] * *q.add(38 + e);
            }
            lag_sample_avx512!(7, s[7], a, acc);
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s[7] * *q.add(39 + e);
            }
            i += 8;
        }
        while i < all {
            let s = *p.add(i);
            let di = _mm512_set1_pd(s);
            let q = p.add(i + k0);
            for (z, a) in acc.iter_mut().enumerate() {
                *a = _mm512_add_pd(*a, _mm512_mul_pd(di, _mm512_loadu_pd(q.add(8 * z))));
            }
            for (e, x) in ex.iter_mut().enumerate() {
                *x += s * *q.add(32 + e);
            }
            i += 1;
        }
    }
    let mut lanes = [0.0f64; 35];
    for (z, a) in acc.iter().enumerate() {
        // SAFETY: lanes has room for 4 · 8 values.
        unsafe { _mm512_storeu_pd(lanes.as_mut_ptr().add(8 * z), *a) };
    }
    lanes[32..32 + E].copy_from_slice(&ex);
    // Where the longer lags have run out of samples the shorter ones finish alone.
    for (lane, v) in lanes[..b].iter().enumerate() {
        let mut a = *v;
        for i in all..n - (k0 + lane) {
            a += d[i] * d[i + k0 + lane];
        }
        out[k0 + lane] = a;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn lag_sums_avx2(d: &[f64], out: &mut [f64]) {
    lag_sums_body::<16>(d, out);
}

/// Lags in blocks of `B`, then of 4, then one at a time (`out.len() <= d.len()`).
#[inline(always)]
fn lag_sums_body<const B: usize>(d: &[f64], out: &mut [f64]) {
    let k = lag_blocks::<B>(d, out, 0);
    let k = lag_blocks::<4>(d, out, k);
    lag_blocks::<1>(d, out, k);
}

/// Lags `k0 .. k0 + B` per block from `k0` on, while whole blocks fit in
/// `out`: every lane is one chain `acc += d_i·d_{i+k}` in index order
/// (a multiply, then an add: no fused multiply-add, as the serial sum);
/// where the longer lags have run out of samples the shorter ones finish
/// alone. Returns where it stopped.
#[inline(always)]
fn lag_blocks<const B: usize>(d: &[f64], out: &mut [f64], mut k0: usize) -> usize {
    let n = d.len();
    while k0 + B <= out.len() {
        // The neutral element of a float sum, as `Iterator::sum` starts from.
        let mut acc = [-0.0f64; B];
        // Samples for which every lane of the block has its partner.
        let all = n - (k0 + B - 1);
        for i in 0..all {
            let di = d[i];
            let w: &[f64; B] = d[i + k0..i + k0 + B].try_into().expect("slice has length B");
            for b in 0..B {
                acc[b] += di * w[b];
            }
        }
        for (b, a) in acc.iter_mut().enumerate() {
            for i in all..n - (k0 + b) {
                *a += d[i] * d[i + k0 + b];
            }
        }
        out[k0..k0 + B].copy_from_slice(&acc);
        k0 += B;
    }
    k0
}

/// Σ (x_i − centre), summed in index order.
pub fn shifted_sum(x: &[f64], centre: f64) -> f64 {
    x.iter().map(|v| v - centre).sum::<f64>()
}

/// Lanes of [`toeplitz_quadratic_form`]: consecutive samples taken side by
/// side, each with its own chain (four AVX-512 vectors, eight AVX2 ones).
const FORM_LANES: usize = 32;

/// qᵀRq for the symmetric Toeplitz matrix R whose first row is `rho`
/// (ρ(0) taken as 1, whatever `rho[0]` holds; lags past `rho` or `q` are
/// zero): Σᵢ qᵢ·(qᵢ + 2tᵢ), tᵢ = Σ_{k ≥ 1} ρ(k)·q_{i+k}. Each tᵢ is one
/// chain of fused multiply-adds over k in order, the samples
/// [`FORM_LANES`] at a time side by side (every lag costs one vector
/// multiply-add per eight samples; the lag sums of [`lag_product_sums`]
/// cost a multiply and an add per lag and sample, and their last lags,
/// short of a block, run one chain each); the terms qᵢ·(qᵢ + 2tᵢ) go to
/// the lane of i mod [`FORM_LANES`], and the lanes are added in order.
/// One body is compiled for AVX-512, for AVX2 with FMA and portably (fused
/// multiply-adds are exact-rounded on each), so every path gives the same
/// bits. `pad` is scratch (q and the zeros after it), kept by the caller.
pub fn toeplitz_quadratic_form(q: &[f64], rho: &[f64], pad: &mut Vec<f64>) -> f64 {
    pad.clear();
    pad.extend_from_slice(q);
    toeplitz_quadratic_form_padding(pad, rho)
}

/// [`toeplitz_quadratic_form`] of q held in `q` itself, which is left
/// padded with the zeros the form reads past it (for a caller that builds
/// q only to take its form: no copy).
pub fn toeplitz_quadratic_form_padding(q: &mut Vec<f64>, rho: &[f64]) -> f64 {
    let n = q.len();
    if n == 0 {
        return 0.0;
    }
    let lags = rho.len().clamp(1, n);
    let blocks = n.div_ceil(FORM_LANES);
    q.resize(blocks * FORM_LANES + lags, 0.0);
    let pad = &q[..];
    // Only ρ(1..) is read: white noise is ρ = [1].
    let rho: &[f64] = if rho.is_empty() { &[1.0] } else { &rho[..lags] };
    let mut lanes = [0.0f64; FORM_LANES];
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: AVX-512F and FMA checked just above.
            unsafe { form_lanes_avx512(pad, n, rho, &mut lanes) };
            return lanes.iter().sum();
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: AVX2 and FMA checked just above.
            unsafe { form_lanes_avx2(pad, n, rho, &mut lanes) };
            return lanes.iter().sum();
        }
    }
    form_lanes(pad, n, rho, &mut lanes);
    lanes.iter().sum()
}

/// The lanes of [`toeplitz_quadratic_form`]: `pad` is the `n` samples of q
/// padded with zeros to whole blocks of [`FORM_LANES`] and `rho.len()`
/// more. A block's lags that reach only the zeros past q (lane 0's last is
/// n − 1 − i0) are left out: their terms add exactly nothing.
#[inline(always)]
fn form_lanes(pad: &[f64], n: usize, rho: &[f64], lanes: &mut [f64; FORM_LANES]) {
    let blocks = n.div_ceil(FORM_LANES);
    assert!(pad.len() >= blocks * FORM_LANES + rho.len() && !rho.is_empty());
    for b in 0..blocks {
        let i0 = b * FORM_LANES;
        let mut t = [0.0f64; FORM_LANES];
        for (k, &r) in rho[..rho.len().min(n - i0)].iter().enumerate().skip(1) {
            let v: &[f64; FORM_LANES] = pad[i0 + k..i0 + k + FORM_LANES].try_into().expect("a block");
            for l in 0..FORM_LANES {
                t[l] = r.mul_add(v[l], t[l]);
            }
        }
        let q: &[f64; FORM_LANES] = pad[i0..i0 + FORM_LANES].try_into().expect("a block");
        for l in 0..FORM_LANES {
            lanes[l] = q[l].mul_add(2.0f64.mul_add(t[l], q[l]), lanes[l]);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn form_lanes_avx512(pad: &[f64], n: usize, rho: &[f64], lanes: &mut [f64; FORM_LANES]) {
    form_lanes(pad, n, rho, lanes);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn form_lanes_avx2(pad: &[f64], n: usize, rho: &[f64], lanes: &mut [f64; FORM_LANES]) {
    form_lanes(pad, n, rho, lanes);
}

/// Autocovariance of noise-gate segments, accumulated over frames with
/// optional exponential forgetting.
///
/// Lag k is estimated from every pair (x_i, x_{i+k}) inside one segment, about
/// the mean of everything accumulated (not each frame's own gate mean, which in
/// strongly coloured noise is itself off by a sizeable fraction of σ and would
/// bias the low-frequency power down), divided by the number of pairs (the
/// unbiased-lag estimator: the biased one's taper 1 − k/n would shrink an
/// AR(1) φ = 0.9 to ~0.89 on a 150-sample gate and leave the pulse band
/// under-whitened). Values enter relative to a fixed shift (the first
/// segment's mean) so a large offset does not cancel digits.
#[derive(Debug, Clone)]
pub struct AutocovarianceAccumulator {
    /// Origin subtracted from every sample (set by the first segment).
    shift: Option<f64>,
    /// Σ x and the sample count, for the overall mean.
    sum_x: f64,
    samples: f64,
    /// Per lag: Σ x_i x_{i+k}, Σ x_i, Σ x_{i+k} over the pairs, and the pair count.
    sum_xy: Vec<f64>,
    sum_a: Vec<f64>,
    sum_b: Vec<f64>,
    pairs: Vec<f64>,
}

impl AutocovarianceAccumulator {
    /// Accumulates lags 0..=`max_lag`.
    pub fn new(max_lag: usize) -> Self {
        let z = vec![0.0; max_lag + 1];
        Self {
            shift: None,
            sum_x: 0.0,
            samples: 0.0,
            sum_xy: z.clone(),
            sum_a: z.clone(),
            sum_b: z.clone(),
            pairs: z,
        }
    }

    /// Multiplies everything accumulated so far by `lambda` (0 < λ ≤ 1).
    pub fn forget(&mut self, lambda: f64) {
        self.sum_x *= lambda;
        self.samples *= lambda;
        for v in [
            &mut self.sum_xy,
            &mut self.sum_a,
            &mut self.sum_b,
            &mut self.pairs,
        ] {
            v.iter_mut().for_each(|s| *s *= lambda);
        }
    }

    /// Adds one gate segment; `mean` (the frame's fitted noise mean) only
    /// sets the shift on the first call. Non-finite samples end the segment
    /// there (pairs never straddle them).
    pub fn add_segment(&mut self, x: &[f64], mean: f64) {
        let shift = *self
            .shift
            .get_or_insert(if mean.is_finite() { mean } else { 0.0 });
        for part in x.split(|v| !v.is_finite()) {
            let n = part.len();
            self.sum_x += shifted_sum(part, shift);
            self.samples += n as f64;
            for k in 0..self.sum_xy.len().min(n) {
                self.sum_xy[k] += lag_product_sum(part, k, shift);
                self.sum_a[k] += shifted_sum(&part[..n - k], shift);
                self.sum_b[k] += shifted_sum(&part[k..], shift);
                self.pairs[k] += (n - k) as f64;
            }
        }
    }

    /// Weighted number of samples accumulated.
    pub fn samples(&self) -> f64 {
        self.samples
    }

    /// Autocovariance c_k about the accumulated mean, for the lags that have
    /// pairs (empty before any sample).
    pub fn autocovariance(&self) -> Vec<f64> {
        if self.samples <= 0.0 {
            return Vec::new();
        }
        let m = self.sum_x / self.samples;
        (0..self.sum_xy.len())
            .take_while(|&k| self.pairs[k] > 0.0)
            .map(|k| {
                (self.sum_xy[k] - m * (self.sum_a[k] + self.sum_b[k]) + m * m * self.pairs[k])
                    / self.pairs[k]
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn code_lag_sums_are_the_exact_sums() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut d = Vec::new();
        for &(n, lags) in &[(1300usize, 65usize), (37, 65), (2000, 17), (1, 3), (0, 4), (1031, 64)] {
            for &(centre, spread) in &[(0.25, 2047), (-700.75, 40), (1234.5, 4000), (3.0, 4095)] {
                let c: Vec<i16> = (0..n).map(|_| (centre as i32 + rng.random_range(-spread..=spread)) as i16).collect();
                let mut got = vec![f64::NAN; lags];
                assert!(code_lag_product_sums(&c, centre, &mut got, &mut d), "{n} codes about {centre}");
                // Exact: 16·Σ(c_i − centre)(c_{i+k} − centre) is an integer (centre in quarters).
                let q = (centre * 4.0) as i128;
                for (k, g) in got.iter().enumerate() {
                    let exact16: i128 = if k < n {
                        (0..n - k).map(|i| (4 * i128::from(c[i]) - q) * (4 * i128::from(c[i + k]) - q)).sum()
                    } else {
                        0
                    };
                    let exact = exact16 as f64 / 16.0;
                    let scale = (0..n.saturating_sub(k)).map(|i| (f64::from(c[i]) - centre).powi(2)).sum::<f64>().max(1.0);
                    assert!((g - exact).abs() <= 4.0 * f64::EPSILON * scale, "{n} codes, lag {k}: {g} against {exact}");
                }
            }
        }
        // Codes farther than 2^12 from the centre, or no finite centre: the caller sums in f64.
        assert!(!code_lag_product_sums(&[0, 5000], 0.0, &mut [0.0; 2], &mut d));
        assert!(!code_lag_product_sums(&[0, 5], f64::NAN, &mut [0.0; 2], &mut d));
    }

    #[test]
    fn the_integer_dot_is_exact_on_every_path() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        for n in [0usize, 1, 15, 16, 31, 33, 1023, 1024, 1025, 3000] {
            let a: Vec<i16> = (0..n).map(|_| rng.random_range(-4096..=4096)).collect();
            let b: Vec<i16> = (0..n).map(|_| if rng.random_bool(0.5) { 4096 } else { -4096 }).collect();
            let want = dot_i16_from(&a, &b, 0, 0);
            assert_eq!(dot_i16(&a, &b), want, "{n}");
            #[cfg(target_arch = "x86_64")]
            {
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: AVX2 checked just above.
                    assert_eq!(unsafe { dot_i16_avx2(&a, &b) }, want, "AVX2, {n}");
                }
                if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw") {
                    // SAFETY: the features checked just above.
                    assert_eq!(unsafe { dot_i16_avx512(&a, &b) }, want, "AVX-512, {n}");
                }
            }
        }
        // At the bound: every product 2^24, 3000 of them (the i32 lanes would overflow unwidened).
        let a = vec![4096i16; 3000];
        assert_eq!(dot_i16(&a, &a), 3000 * (1i64 << 24));
        let m = vec![-4096i16; 3000];
        assert_eq!(dot_i16(&a, &m), -3000 * (1i64 << 24));
    }
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn lag_products_match_a_naive_double_loop() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let x: Vec<f64> = (0..37).map(|_| rng.random_range(-3.0..5.0)).collect();
        for centre in [0.0, 1.25, -7.0] {
            for lag in 0..40 {
                let mut want = 0.0;
                for i in 0..x.len() {
                    if i + lag < x.len() {
                        want += (x[i] - centre) * (x[i + lag] - centre);
                    }
                }
                // Same order, same operations: bit-identical.
                assert_eq!(
                    lag_product_sum(&x, lag, centre),
                    want,
                    "lag {lag} centre {centre}"
                );
            }
        }
        assert_eq!(lag_product_sum(&[], 0, 1.0), 0.0);
        let mut out = [1.0; 3];
        lag_product_sums(&[], 1.0, &mut out, &mut Vec::new());
        assert_eq!(out, [0.0; 3]);
        assert_eq!(shifted_sum(&[1.0, 2.0, 4.0], 1.0), 4.0);
    }

    #[test]
    fn all_lags_at_once_are_bit_identical_to_each_lag_alone() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let mut centred = Vec::new();
        for n in [1usize, 3, 4, 5, 17, 40, 200, 1391] {
            let x: Vec<f64> = (0..n).map(|_| rng.random_range(-3.0..5.0)).collect();
            for lags in [1usize, 4, 5, 33, 34, 35, 36, 65, 66, 67, 251] {
                let centre = rng.random_range(-1.0..1.0);
                let mut out = vec![f64::NAN; lags];
                lag_product_sums(&x, centre, &mut out, &mut centred);
                for (k, v) in out.iter().enumerate() {
                    assert_eq!(v.to_bits(), lag_product_sum(&x, k, centre).to_bits(), "n {n} lag {k} of {lags}");
                }
                // Every lane width, whichever path this CPU takes.
                let used = lags.min(n);
                for body in [lag_sums_body::<16> as fn(&[f64], &mut [f64]), lag_sums_body::<32>, lag_sums_body::<4>] {
                    let mut o = vec![f64::NAN; used];
                    body(&centred, &mut o);
                    assert!(o.iter().zip(&out).all(|(a, b)| a.to_bits() == b.to_bits()), "n {n} lags {lags}");
                }
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    let mut o = vec![f64::NAN; used];
                    // SAFETY: AVX2 checked just above.
                    unsafe { lag_sums_avx2(&centred, &mut o) };
                    assert!(o.iter().zip(&out).all(|(a, b)| a.to_bits() == b.to_bits()), "avx2 n {n} lags {lags}");
                }
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx512f") {
                    let mut o = vec![f64::NAN; used];
                    // SAFETY: AVX-512F checked just above.
                    unsafe { lag_sums_avx512(&centred, &mut o) };
                    assert!(o.iter().zip(&out).all(|(a, b)| a.to_bits() == b.to_bits()), "avx512 n {n} lags {lags}");
                }
            }
        }
    }

    #[test]
    fn the_toeplitz_form_is_the_same_on_every_path_and_the_lag_by_lag_sum() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let mut pad = Vec::new();
        for n in [1usize, 2, 7, 31, 32, 33, 64, 150, 211, 1000] {
            let q: Vec<f64> = (0..n).map(|_| rng.random_range(-3.0..2.0)).collect();
            for lags in [0usize, 1, 2, 9, 65, 90, 300] {
                // A decaying colour with a sign change, and ρ(0) not 1 (it is taken as 1).
                let rho: Vec<f64> = (0..lags).map(|k| if k == 0 { 7.0 } else { 0.93f64.powi(k as i32) * (0.3 * k as f64).cos() }).collect();
                let got = toeplitz_quadratic_form(&q, &rho, &mut pad);
                // Lag by lag, in index order, and its rounding bound.
                let (mut want, mut bound) = (q.iter().map(|v| v * v).sum::<f64>(), q.iter().map(|v| v * v).sum::<f64>());
                for (k, r) in rho.iter().enumerate().skip(1).take(n.saturating_sub(1)) {
                    let s = q.iter().zip(&q[k..]).map(|(a, b)| a * b).sum::<f64>();
                    want += 2.0 * r * s;
                    bound += 2.0 * r.abs() * q.iter().zip(&q[k..]).map(|(a, b)| (a * b).abs()).sum::<f64>();
                }
                // Both sums round each of at most n·lags + n terms once and
                // accumulate at most n + lags of them in a chain.
                let tol = 4.0 * (n + lags) as f64 * f64::EPSILON * bound;
                assert!((got - want).abs() <= tol, "{n} samples, {lags} lags: {got} against {want} (tolerance {tol:e})");
                // Every path gives the same bits.
                let used: &[f64] = if rho.is_empty() { &[1.0] } else { &rho[..lags.min(n)] };
                let blocks = n.div_ceil(FORM_LANES);
                let mut padded = q.clone();
                padded.resize(blocks * FORM_LANES + used.len(), 0.0);
                let mut portable = [0.0; FORM_LANES];
                form_lanes(&padded, n, used, &mut portable);
                assert_eq!(got.to_bits(), portable.iter().sum::<f64>().to_bits(), "portable, {n} samples, {lags} lags");
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                    let mut l = [0.0; FORM_LANES];
                    // SAFETY: AVX2 and FMA checked just above.
                    unsafe { form_lanes_avx2(&padded, n, used, &mut l) };
                    assert_eq!(l.map(f64::to_bits), portable.map(f64::to_bits), "avx2, {n} samples, {lags} lags");
                }
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("fma") {
                    let mut l = [0.0; FORM_LANES];
                    // SAFETY: AVX-512F and FMA checked just above.
                    unsafe { form_lanes_avx512(&padded, n, used, &mut l) };
                    assert_eq!(l.map(f64::to_bits), portable.map(f64::to_bits), "avx512, {n} samples, {lags} lags");
                }
            }
        }
        assert_eq!(toeplitz_quadratic_form(&[], &[1.0, 0.5], &mut pad), 0.0);
    }

    #[test]
    fn short_lag_sums_are_the_serial_sums() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for n in [0usize, 1, 3, 8, 13, 64, 65, 100, 129] {
            let d: Vec<f64> = (0..n).map(|_| rng.random_range(-2.0..3.0)).collect();
            let mut out = vec![f64::NAN; n];
            lag_sums_short(&d, &mut out);
            for (k, v) in out.iter().enumerate() {
                let serial = d[..n - k].iter().zip(&d[k..]).map(|(a, b)| a * b).sum::<f64>();
                assert_eq!(v.to_bits(), serial.to_bits(), "n {n} lag {k}");
            }
        }
    }

    #[test]
    fn accumulator_is_the_per_pair_estimator_about_the_overall_mean() {
        // Two segments; overall mean (1 + 3 + 2 + 5 + 4) / 5 = 3.
        let mut acc = AutocovarianceAccumulator::new(2);
        acc.add_segment(&[1.0, 3.0, 2.0], 2.0);
        acc.add_segment(&[5.0, 4.0], 1e9);
        let c = acc.autocovariance();
        let d = [-2.0, 0.0, -1.0, 2.0, 1.0];
        assert!((c[0] - d.iter().map(|v| v * v).sum::<f64>() / 5.0).abs() < 1e-12);
        assert!((c[1] - (d[0] * d[1] + d[1] * d[2] + d[3] * d[4]) / 3.0).abs() < 1e-12);
        assert!((c[2] - d[0] * d[2]).abs() < 1e-12);
        acc.forget(0.5);
        assert_eq!(acc.samples(), 2.5);
        assert_eq!(acc.autocovariance(), c);
    }
}
