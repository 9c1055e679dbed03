//! Robust scale of samples that lie on a quantisation grid.
//!
//! The MAD of coarsely quantised samples is itself quantised: with a step of
//! one noise sigma (an 8-bit scope at a sensitive range) the median absolute
//! deviation is 0, q/2 or q, and 1.4826·MAD misses the sigma by up to 80 %.
//! Here the samples' empirical distribution is read where it is exact — at
//! the cell boundaries v + q/2, where the fraction of samples at or below a
//! level estimates the underlying Φ((b − μ)/σ) without bias — and a straight
//! line is fitted to Φ⁻¹(F) against the boundary (a probit fit), using only
//! the central boundaries (between the 10 % and 90 % points where three lie
//! there) so that a pulse leaking into a few per cent of the samples hardly
//! moves it (as it hardly moves the MAD). The result estimates the standard deviation of the quantised
//! samples, √(σ² + q²/12) (Sheppard), which is what the plain sample
//! standard deviation estimates too, so the two can be compared.

use super::special::{phi, q_inv};

/// Step of the grid `x` lies on (every sample is `min(x) + k·step` for an
/// integer k, to a tolerance of 1e-9 of the samples' magnitude), or `None`
/// when the samples are not on a grid as coarse as `min_step` (continuous
/// values, a grid finer than `min_step`, fewer than two distinct values).
///
/// A floating-point Euclid over the differences from the minimum: linear in
/// `x.len()`, nothing allocated.
pub fn grid_step(x: &[f64], min_step: f64) -> Option<f64> {
    let (lo, hi) = super::select::min_max(x);
    grid_step_within(x, lo, hi, min_step)
}

/// [`grid_step`] where the caller has `(lo, hi)`, the
/// [`min_max`](super::select::min_max) of `x`, at hand.
pub fn grid_step_within(x: &[f64], lo: f64, hi: f64, min_step: f64) -> Option<f64> {
    if !(hi > lo) || !hi.is_finite() || !lo.is_finite() {
        return None;
    }
    let eps = 1e-9 * lo.abs().max(hi.abs()).max(hi - lo);
    // Samples on the grid found so far are multiples of q to within eps:
    // the test does not need the correctly rounded quotient, so it
    // multiplies by 1/q (a division per sample costs several times more).
    // Samples are taken in order, q shrinking at each one off its grid; the
    // runs of samples on it (nearly all) are checked eight at a time.
    let (mut q, mut inv_q) = (0.0, 0.0);
    let mut i = 0;
    while i < x.len() {
        if q > 0.0 {
            i += on_grid_run(&x[i..], lo, eps, q, inv_q);
            if i == x.len() {
                break;
            }
        }
        let d = x[i] - lo;
        i += 1;
        if d <= eps {
            continue;
        }
        if q == 0.0 {
            q = d;
            inv_q = 1.0 / q;
            continue;
        }
        let r = d * inv_q;
        if (r - round(r)).abs() * q <= eps {
            continue;
        }
        q = float_gcd(q, d, eps);
        inv_q = 1.0 / q;
        if !(q >= min_step) {
            return None;
        }
    }
    (q > 0.0 && q >= min_step).then_some(q)
}

/// How many leading samples of `x` pass [`grid_step`]'s test for the grid
/// `q` (a sample at most `eps` above `lo`, or within `eps` of a multiple of
/// `q` above it), checked eight at a time without branches; the first that
/// may not is left to the caller's exact test. The nearest integer is
/// taken by adding and subtracting 1.5·2⁵² (ties to even: the same distance
/// to it as `round`'s) where the quotient is below 2⁵¹, and quotients
/// beyond are left to the caller.
fn on_grid_run(x: &[f64], lo: f64, eps: f64, q: f64, inv_q: f64) -> usize {
    // The same arithmetic in AVX-512 or AVX2 registers where the CPU has them (picked at run time).
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") {
        // SAFETY: AVX-512F checked just above.
        return unsafe { on_grid_run_avx512(x, lo, eps, q, inv_q) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 checked just above.
        return unsafe { on_grid_run_avx2(x, lo, eps, q, inv_q) };
    }
    on_grid_run_body(x, lo, eps, q, inv_q)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn on_grid_run_avx2(x: &[f64], lo: f64, eps: f64, q: f64, inv_q: f64) -> usize {
    on_grid_run_body(x, lo, eps, q, inv_q)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn on_grid_run_avx512(x: &[f64], lo: f64, eps: f64, q: f64, inv_q: f64) -> usize {
    on_grid_run_body(x, lo, eps, q, inv_q)
}

#[inline(always)]
fn on_grid_run_body(x: &[f64], lo: f64, eps: f64, q: f64, inv_q: f64) -> usize {
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    let passes = |v: f64| {
        let d = v - lo;
        let r = d * inv_q;
        let near = (r + MAGIC) - MAGIC;
        // `|` and `&`, not `||` and `&&`: no branch per sample, so the
        // chunk's eight tests vectorise (5x faster with AVX-512).
        (d <= eps) | ((r < 2_251_799_813_685_248.0) & ((r - near).abs() * q <= eps))
    };
    let mut done = 0;
    for chunk in x.chunks_exact(8) {
        let mut all = true;
        for &v in chunk {
            all &= passes(v);
        }
        if !all {
            break;
        }
        done += 8;
    }
    done + x[done..].iter().take_while(|&&v| passes(v)).count()
}

/// `x.round()` (half away from zero), bit for bit, without the library
/// call the portable x86-64 target makes for it (no SSE4.1 rounding
/// instruction): these loops round every sample.
#[inline(always)]
fn round(x: f64) -> f64 {
    let a = x.abs();
    // 2⁵² and beyond (and NaN, ±∞) are integral already.
    if !(a < 4_503_599_627_370_496.0) {
        return x;
    }
    // Truncation by conversion is exact below 2⁵²; adding the double just
    // below ½ first rounds half away from zero (as LLVM lowers `round` where
    // the CPU has a truncating instruction), with no branch to mispredict.
    ((a + 0.499_999_999_999_999_94) as i64 as f64).copysign(x)
}

/// Greatest common divisor of two positive reals, remainders below `eps` counting as 0.
fn float_gcd(a: f64, b: f64, eps: f64) -> f64 {
    let (mut a, mut b) = (a.max(b), a.min(b));
    while b > eps {
        let r = a % b;
        let r = if b - r <= eps { 0.0 } else { r };
        a = b;
        b = r;
    }
    a
}

/// Most grid levels [`quantised_sigma`] will histogram; a wider spread (a
/// fine grid under huge outliers) gives `None`.
pub const MAX_LEVELS: usize = 1 << 16;

/// Most cell boundaries entering the probit fit (spread evenly over the
/// central ones): beyond a few dozen the estimate does not improve, and each
/// costs an inverse normal.
const MAX_BOUNDARIES: usize = 32;

/// Windows of the cumulative fraction F whose cell boundaries enter the
/// fit, narrowest first, each with the boundaries it needs: the first that
/// has them is used. The narrow window ignores the tails, where a leaked
/// pulse shifts F most; three boundaries at least, because a real scope's
/// codes are not all equally wide (differential non-linearity) and two
/// boundaries around one wide code would read its width as the noise's.
const WINDOWS: [(f64, f64, usize); 4] = [(0.1, 0.9, 3), (0.05, 0.95, 3), (0.02, 0.98, 3), (0.005, 0.995, 2)];

/// Each sample's level on the grid from `lo` with 1/step `inv_step`, at most
/// `top`, into `index` (`lo` is the least of `x`, and `x` spans at most
/// [`MAX_LEVELS`] levels, `inv_step` finite; a NaN is level 0): with AVX-512
/// or AVX2 where the CPU has them, by a packed floor
/// ([`level_indices_floor`]), else by a signed conversion; the same levels
/// for every such input.
fn level_indices(x: &[f64], lo: f64, inv_step: f64, top: i64, index: &mut [u32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512dq") {
            // SAFETY: the CPU has AVX-512F and AVX-512DQ (checked above).
            unsafe { level_indices_avx512(x, lo, inv_step, top, index) };
            return;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            unsafe { level_indices_avx2(x, lo, inv_step, top, index) };
            return;
        }
    }
    level_indices_body(x, lo, inv_step, top, index);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
fn level_indices_avx512(x: &[f64], lo: f64, inv_step: f64, top: i64, index: &mut [u32]) {
    level_indices_floor(x, lo, inv_step, top, index);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn level_indices_avx2(x: &[f64], lo: f64, inv_step: f64, top: i64, index: &mut [u32]) {
    level_indices_floor(x, lo, inv_step, top, index);
}

/// [`level_indices_body`]'s levels by a packed floor (for CPUs with a
/// rounding instruction: AVX2's four lanes or AVX-512's eight).
#[cfg(any(target_arch = "x86_64", test))]
#[inline(always)]
fn level_indices_floor(x: &[f64], lo: f64, inv_step: f64, top: i64, index: &mut [u32]) {
    // The quotient q lies in [0, 2¹⁷) (at most MAX_LEVELS levels), where
    // truncation is floor (one rounding instruction here) and the integer
    // floor(q) is the low bits of floor(q) + 2⁵²: packed, no saturating
    // conversion (which the compiler does element by element).
    const TWO_52: f64 = 4_503_599_627_370_496.0;
    let top = top as u32;
    for (k, &v) in index.iter_mut().zip(x) {
        let q = (v - lo) * inv_step + 0.499_999_999_999_999_94;
        *k = ((q.floor() + TWO_52).to_bits() as u32).min(top);
    }
}

#[inline(always)]
fn level_indices_body(x: &[f64], lo: f64, inv_step: f64, top: i64, index: &mut [u32]) {
    // (A signed conversion: the unsigned one's saturation costs branches.)
    for (k, &v) in index.iter_mut().zip(x) {
        // v ≥ lo: the quotient is +0 or more, where `round` is this truncation.
        *k = (((v - lo) * inv_step + 0.499_999_999_999_999_94) as i64).min(top) as u32;
    }
}

/// Counters per level [`cumulative_counts`] uses for samples `n` over
/// `levels` levels: four where the samples crowd onto few levels (neighbours
/// on one level would otherwise wait on one another's store), one where they
/// spread (then neighbours rarely share a level, and four counters would
/// only cost four times the zeroing and the summing).
fn ways(n: usize, levels: usize) -> usize {
    if 16 * levels <= n { 4 } else { 1 }
}

/// Counts the samples at each level (`index`: each sample's level, below
/// `counts.len() / W`; `counts`: zeros, `W` counters per level, `W` 1 or 4)
/// and leaves in `counts[k]` the count on levels 0..=k. With four, four
/// samples at a time go to their level's four counters.
fn cumulative_counts<const W: usize>(index: &[u32], counts: &mut [u32]) {
    if W == 1 {
        for &k in index {
            counts[k as usize] += 1;
        }
        let mut run = 0u32;
        for c in counts.iter_mut() {
            run += *c;
            *c = run;
        }
        return;
    }
    let quads = index.chunks_exact(4);
    for &k in quads.remainder() {
        counts[4 * k as usize] += 1;
    }
    for q in quads {
        counts[4 * q[0] as usize] += 1;
        counts[4 * q[1] as usize + 1] += 1;
        counts[4 * q[2] as usize + 2] += 1;
        counts[4 * q[3] as usize + 3] += 1;
    }
    // Level k's total goes to counts[k], which no level after k reads
    // (they read from 4(k + 1) on).
    let mut run = 0u32;
    for k in 0..counts.len() / 4 {
        run += counts[4 * k] + counts[4 * k + 1] + counts[4 * k + 2] + counts[4 * k + 3];
        counts[k] = run;
    }
}

/// Robust standard deviation of samples on a grid of step `step` (from
/// [`grid_step`]): the probit fit described in the module documentation.
/// `counts` is scratch (one or four counters per level, then each sample's level), kept between calls.
///
/// The boundaries used are those whose cumulative fraction F lies in
/// [0.1, 0.9] when at least three do; else [0.05, 0.95], [0.02, 0.98] (three
/// needed) and [0.005, 0.995] (two). `None` when even that leaves fewer
/// than two (nearly every sample on one or two levels: the spread is below
/// what the grid resolves), or the samples span more than [`MAX_LEVELS`] levels.
pub fn quantised_sigma(x: &[f64], step: f64, counts: &mut Vec<u32>) -> Option<f64> {
    let (lo, hi) = super::select::min_max(x);
    quantised_sigma_within(x, lo, hi, step, counts)
}

/// [`quantised_sigma`] where the caller has `(lo, hi)`, the
/// [`min_max`](super::select::min_max) of `x`, at hand.
pub fn quantised_sigma_within(x: &[f64], lo: f64, hi: f64, step: f64, counts: &mut Vec<u32>) -> Option<f64> {
    if x.len() < 2 || !(step > 0.0) {
        return None;
    }
    let levels = round((hi - lo) / step) + 1.0;
    if !(levels.is_finite() && levels <= MAX_LEVELS as f64) {
        return None;
    }
    // Samples on the grid (as `grid_step` found it) sit next to an integer
    // number of steps from the lowest: the nearest integer is the same
    // whether (v − lo) is divided by the step or multiplied by its inverse.
    let inv_step = 1.0 / step;
    // A step so fine (below ~5.6e-309) that its inverse overflows has no
    // levels to count (every path would read them differently).
    if !inv_step.is_finite() {
        return None;
    }
    let levels = levels as usize;
    probit_sigma(x.len(), levels, step, counts, |index| level_indices(x, lo, inv_step, levels as i64 - 1, index))
}

/// [`quantised_sigma`] of integer codes (the concatenation of `parts`,
/// `lo` and `hi` their least and greatest, `grid` the greatest common
/// divisor of their distances from `lo`, from
/// [`code_grid`](super::code_stats::code_grid)), one level per `grid`
/// codes, `step` volts apart: each code's level is its distance from `lo`
/// over `grid`, exactly (no rounding to find it), and the fit is the one
/// [`quantised_sigma_within`] makes on the codes' volts.
pub fn quantised_sigma_codes(parts: &[&[i16]], lo: i16, hi: i16, grid: u32, step: f64, counts: &mut Vec<u32>) -> Option<f64> {
    let n: usize = parts.iter().map(|p| p.len()).sum();
    if n < 2 || grid == 0 || !(step > 0.0) || hi < lo {
        return None;
    }
    let levels = (i32::from(hi) - i32::from(lo)) as usize / grid as usize + 1;
    if levels > MAX_LEVELS {
        return None;
    }
    probit_sigma(n, levels, step, counts, |index| super::code_stats::code_levels(parts, lo, grid, index))
}

/// The probit fit of [`quantised_sigma`] on `n` samples over `levels`
/// levels `step` apart, `levels_of` writing each sample's level (below
/// `levels`) into the slice it is given. `counts` is scratch (one or four
/// counters per level, then each sample's level), kept between calls.
fn probit_sigma(n: usize, levels: usize, step: f64, counts: &mut Vec<u32>, levels_of: impl FnOnce(&mut [u32])) -> Option<f64> {
    // `counts` holds the counters (one or four per level, see `ways`) and,
    // after them, each sample's level (scratch): the levels are found in
    // one pass the compiler vectorises (no store between samples), then
    // counted. Only the counters need zeros: every sample's level is written.
    let ways = ways(n, levels);
    let need = ways * levels + n;
    if counts.len() < need {
        counts.resize(need, 0);
    }
    counts[..ways * levels].fill(0);
    let (counts, index) = counts[..need].split_at_mut(ways * levels);
    levels_of(index);
    if ways == 4 {
        cumulative_counts::<4>(index, counts);
    } else {
        cumulative_counts::<1>(index, counts);
    }
    let cum = &counts[..levels - 1];
    let total = n as u64;
    let n = n as f64;
    // Boundary k lies between level k and k + 1, at lo + (k + ½)·step; F is
    // the fraction of samples on levels 0..=k. F = cum/n rounded rises with
    // the count, so a window [a, b] of F is a range of counts, found once
    // with the same divisions (no division per level), and the boundaries
    // whose counts lie in it are one run of k (cum rises with k), found by
    // bisection.
    let counts_in = |(a, b): (f64, f64)| {
        let f = |c: u64| c as f64 / n;
        let mut first = ((a * n).floor() as u64).saturating_sub(2).min(total);
        while first < total && !(f(first) >= a) {
            first += 1;
        }
        let mut last = ((b * n).ceil() as u64 + 2).min(total);
        while last > 0 && !(f(last) <= b) {
            last -= 1;
        }
        (first, last, f(first) >= a && f(last) <= b)
    };
    let in_window = |(a, b): (f64, f64)| {
        let (first, last, any) = counts_in((a, b));
        if !any {
            return 0..0;
        }
        let k_lo = cum.partition_point(|&c| (c as u64) < first);
        let k_hi = cum.partition_point(|&c| (c as u64) <= last);
        k_lo..k_hi.max(k_lo)
    };
    let ks = WINDOWS
        .into_iter()
        .map(|(a, b, need)| (in_window((a, b)), need))
        .find(|(ks, need)| ks.len() >= *need)
        .map(|(ks, _)| ks)?;
    // Every stride-th boundary of the run, from its first.
    let stride = ks.len().div_ceil(MAX_BOUNDARIES);
    let (mut sw, mut swx, mut swy, mut swxx, mut swxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for k in ks.step_by(stride) {
        let f = cum[k] as u64 as f64 / n;
        let z = -q_inv(f);
        // Inverse-variance weight of Φ⁻¹(F̂): Var F̂ = F(1 − F)/n, and dz/dF = 1/φ(z).
        let w = phi(z).powi(2) / (f * (1.0 - f));
        // Abscissae in steps from the lowest level: well scaled whatever the offset.
        let xb = k as f64 + 0.5;
        sw += w;
        swx += w * xb;
        swy += w * z;
        swxx += w * xb * xb;
        swxy += w * xb * z;
    }
    let det = sw * swxx - swx * swx;
    let slope = (sw * swxy - swx * swy) / det;
    if !(det > 0.0 && slope > 0.0 && slope.is_finite()) {
        return None;
    }
    // z = (b − μ)/σ with b in steps: σ = step/slope.
    let sigma = step / slope;
    Some((sigma * sigma + step * step / 12.0).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    #[test]
    fn cumulative_counts_are_the_running_histogram() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for n in 0..40 {
            for levels in [1usize, 2, 3, 7, 40] {
                let index: Vec<u32> = (0..n).map(|_| rand::Rng::random_range(&mut rng, 0..levels as u32)).collect();
                let want: Vec<u32> = (0..levels as u32).map(|k| index.iter().filter(|&&i| i <= k).count() as u32).collect();
                let mut four = vec![0u32; 4 * levels];
                cumulative_counts::<4>(&index, &mut four);
                assert_eq!(&four[..levels], &want[..], "{n} samples on {levels} levels, four counters each");
                let mut one = vec![0u32; levels];
                cumulative_counts::<1>(&index, &mut one);
                assert_eq!(one, want, "{n} samples on {levels} levels, one counter each");
            }
        }
    }

    #[test]
    fn level_indices_are_the_same_on_every_path() {
        let mut x = quantised(1003, 37.0, 0.5, -3.25, 11);
        x.push(f64::NAN);
        let (lo, hi) = crate::math::select::min_max(&x[..1003]);
        let step = 0.5;
        let top = (((hi - lo) / step).round()) as i64;
        let mut want = vec![0u32; x.len()];
        level_indices_body(&x, lo, 1.0 / step, top, &mut want);
        let mut got = vec![0u32; x.len()];
        level_indices(&x, lo, 1.0 / step, top, &mut got);
        assert_eq!(got, want);
        // The packed floor's arithmetic (compiled here for the baseline
        // target: the same operations the AVX2 and AVX-512 copies run).
        level_indices_floor(&x, lo, 1.0 / step, top, &mut got);
        assert_eq!(got, want);
        // Off the grid too (the truncation, not only exact levels).
        for v in &mut x[..1003] {
            *v += 0.2499;
        }
        level_indices_body(&x, lo, 1.0 / step, top, &mut want);
        level_indices(&x, lo, 1.0 / step, top, &mut got);
        assert_eq!(got, want);
        level_indices_floor(&x, lo, 1.0 / step, top, &mut got);
        assert_eq!(got, want);
        assert_eq!(want[1003], 0, "NaN");
    }

    fn quantised(n: usize, sigma: f64, step: f64, offset: f64, seed: u64) -> Vec<f64> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let z: f64 = StandardNormal.sample(&mut rng);
                // Codes times a gain plus an offset, as a scope reader forms volts.
                (offset / step + sigma / step * z).round() * step - 0.33
            })
            .collect()
    }

    #[test]
    fn round_is_the_library_round_bit_for_bit() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let edges = [
            0.0, -0.0, 0.5, -0.5, 1.5, 2.5, -2.5, 0.49999999999999994, -0.49999999999999994, 4503599627370495.5,
            4503599627370496.0, -4503599627370497.0, 1e300, f64::MIN_POSITIVE, f64::INFINITY, f64::NEG_INFINITY,
        ];
        let random = (0..100_000).map(|_| rng.random_range(-1e6..1e6) * 10f64.powi(rng.random_range(-12..8)));
        for x in edges.into_iter().chain(random) {
            assert_eq!(round(x).to_bits(), x.round().to_bits(), "{x}");
        }
        assert!(round(f64::NAN).is_nan());
    }

    #[test]
    fn the_grid_run_is_the_same_on_every_copy_and_a_subnormal_step_has_no_levels() {
        let mut x = quantised(1003, 37.0, 0.5, -3.25, 12);
        let (lo, _) = crate::math::select::min_max(&x);
        // Off the grid at a few places (the run stops at the first).
        for at in [1002usize, 517, 9] {
            let want = on_grid_run_body(&x, lo, 1e-9, 0.5, 2.0);
            assert_eq!(on_grid_run(&x, lo, 1e-9, 0.5, 2.0), want, "off at {at}");
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: AVX2 checked just above.
                assert_eq!(unsafe { on_grid_run_avx2(&x, lo, 1e-9, 0.5, 2.0) }, want, "off at {at}: AVX2");
            }
            x[at] += 0.1;
        }
        // Samples on a grid of the least subnormal: 1/step overflows.
        let tiny: Vec<f64> = (0..64).map(|k| f64::from_bits(1) * (k % 7) as f64).collect();
        assert_eq!(quantised_sigma_within(&tiny, 0.0, 6.0 * f64::from_bits(1), f64::from_bits(1), &mut Vec::new()), None);
    }

    /// `grid_step` as first written: one sample at a time, dividing.
    fn grid_step_naive(x: &[f64], min_step: f64) -> Option<f64> {
        let (lo, hi) = x.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        if !(hi > lo) || !hi.is_finite() || !lo.is_finite() {
            return None;
        }
        let eps = 1e-9 * lo.abs().max(hi.abs()).max(hi - lo);
        let mut q = 0.0;
        for &v in x {
            let d = v - lo;
            if d <= eps {
                continue;
            }
            if q == 0.0 {
                q = d;
                continue;
            }
            let r = d / q;
            if (r - r.round()).abs() * q <= eps {
                continue;
            }
            q = float_gcd(q, d, eps);
            if !(q >= min_step) {
                return None;
            }
        }
        (q > 0.0 && q >= min_step).then_some(q)
    }

    #[test]
    fn grid_step_agrees_with_the_sample_by_sample_search() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for trial in 0..400 {
            let step = 10f64.powi(rng.random_range(-6..2)) * rng.random_range(1.0..2.0);
            let mut x = quantised(rng.random_range(2..1500), step * rng.random_range(0.3..40.0), step, rng.random_range(-5.0..5.0), trial);
            // Some with every code even, some with a sample off the grid.
            if trial % 3 == 1 {
                x.iter_mut().for_each(|v| *v = ((*v / step).round() * 0.5).round() * 2.0 * step);
            }
            if trial % 5 == 2 {
                let k = rng.random_range(0..x.len());
                x[k] += step * rng.random_range(0.01..0.99);
            }
            for min_step in [0.0, step * 0.5, step * 1.5] {
                assert_eq!(grid_step(&x, min_step).map(f64::to_bits), grid_step_naive(&x, min_step).map(f64::to_bits), "trial {trial}");
            }
        }
    }

    /// `quantised_sigma` as first written: a division per level.
    fn quantised_sigma_naive(x: &[f64], step: f64) -> Option<f64> {
        let (lo, hi) = x.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        let levels = ((hi - lo) / step).round() + 1.0;
        if !(levels <= MAX_LEVELS as f64) {
            return None;
        }
        let levels = levels as usize;
        let mut counts = vec![0u32; levels];
        for &v in x {
            counts[(((v - lo) / step).round().max(0.0) as usize).min(levels - 1)] += 1;
        }
        let n = x.len() as f64;
        let in_window = |(a, b): (f64, f64)| {
            let mut cum = 0u64;
            counts[..levels - 1].iter().filter(|&&c| {
                cum += c as u64;
                (a..=b).contains(&(cum as f64 / n))
            }).count()
        };
        let ((a, b), m) = WINDOWS.into_iter().map(|(a, b, need)| ((a, b), in_window((a, b)), need)).find(|&(_, m, need)| m >= need).map(|(w, m, _)| (w, m))?;
        let stride = m.div_ceil(MAX_BOUNDARIES);
        let (mut sw, mut swx, mut swy, mut swxx, mut swxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        let (mut cum, mut seen) = (0u64, 0usize);
        for (k, &c) in counts[..levels - 1].iter().enumerate() {
            cum += c as u64;
            let f = cum as f64 / n;
            if !(a..=b).contains(&f) {
                continue;
            }
            seen += 1;
            if (seen - 1) % stride != 0 {
                continue;
            }
            let z = -q_inv(f);
            let w = phi(z).powi(2) / (f * (1.0 - f));
            let xb = k as f64 + 0.5;
            (sw, swx, swy, swxx, swxy) = (sw + w, swx + w * xb, swy + w * z, swxx + w * xb * xb, swxy + w * xb * z);
        }
        let det = sw * swxx - swx * swx;
        let slope = (sw * swxy - swx * swy) / det;
        if !(det > 0.0 && slope > 0.0 && slope.is_finite()) {
            return None;
        }
        let sigma = step / slope;
        Some((sigma * sigma + step * step / 12.0).sqrt())
    }

    #[test]
    fn quantised_sigma_agrees_with_a_division_per_level() {
        use rand::Rng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let mut counts = Vec::new();
        for trial in 0..300 {
            let step = 10f64.powi(rng.random_range(-6..2));
            let x = quantised(rng.random_range(2..1500), step * rng.random_range(0.2..60.0), step, rng.random_range(-5.0..5.0), trial);
            let q = grid_step(&x, 0.0).unwrap_or(step);
            let got = quantised_sigma(&x, q, &mut counts).map(f64::to_bits);
            assert_eq!(got, quantised_sigma_naive(&x, q).map(f64::to_bits), "trial {trial}");
        }
    }

    #[test]
    fn grid_of_scaled_codes_is_found() {
        let x = quantised(500, 0.025, 0.032, 0.011, 1);
        let q = grid_step(&x, 1e-4).unwrap();
        assert!((q - 0.032).abs() < 1e-12, "{q}");
        // A coarser min_step than the grid refuses it.
        assert_eq!(grid_step(&x, 0.05), None);
    }

    #[test]
    fn a_grid_with_missing_levels_is_still_found() {
        // Levels 0, 3q, 5q: the differences' gcd is q.
        let x = [0.1, 0.1 + 3.0 * 0.004, 0.1 + 5.0 * 0.004, 0.1];
        let q = grid_step(&x, 1e-5).unwrap();
        assert!((q - 0.004).abs() < 1e-12, "{q}");
    }

    #[test]
    fn continuous_samples_have_no_grid() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let x: Vec<f64> = (0..200).map(|_| StandardNormal.sample(&mut rng)).collect();
        assert_eq!(grid_step(&x, 1e-3), None);
        assert_eq!(grid_step(&[1.0, 1.0, 1.0], 1e-9), None);
        assert_eq!(grid_step(&[], 1e-9), None);
    }

    /// Against the sample standard deviation (which estimates the same
    /// quantity, √(σ² + q²/12)) over steps from 0.1 to 2 sigma: 2000
    /// samples give each estimate a relative sd of ~2 %, so 8 % is a 4-sigma bound.
    #[test]
    fn estimates_the_quantised_standard_deviation() {
        for (i, &step) in [0.1, 0.5, 1.0, 1.28, 2.0].iter().enumerate() {
            let x = quantised(2000, 1.0, step, 0.37 * step, 10 + i as u64);
            let q = grid_step(&x, step / 4.0).unwrap();
            let r = quantised_sigma(&x, q, &mut Vec::new()).unwrap();
            let truth = (1.0 + step * step / 12.0_f64).sqrt();
            assert!((r / truth - 1.0).abs() < 0.08, "step {step}: {r} vs {truth}");
        }
    }

    #[test]
    fn a_few_large_outliers_hardly_move_it() {
        let mut x = quantised(1000, 1.0, 1.28, 0.2, 5);
        let clean = quantised_sigma(&x, 1.28, &mut Vec::new()).unwrap();
        for v in x.iter_mut().step_by(50) {
            *v += 10.0 * 1.28;
        }
        let dirty = quantised_sigma(&x, 1.28, &mut Vec::new()).unwrap();
        // 2 % of the samples at +10 sigma: the plain sd grows by ~40 %, this
        // by ~5 % (the tails' boundaries feel the shifted fractions; the MAD
        // of continuous samples moves by ~3 %).
        assert!((dirty / clean - 1.0).abs() < 0.1, "{clean} -> {dirty}");
    }

    #[test]
    fn two_levels_are_too_few() {
        let x: Vec<f64> = (0..100).map(|i| if i % 2 == 0 { 0.0 } else { 0.5 }).collect();
        assert_eq!(quantised_sigma(&x, 0.5, &mut Vec::new()), None);
    }
}
