//! Statistics of integer ADC codes in integer arithmetic: a gate's least and
//! greatest code, its grid (the greatest common divisor of the codes'
//! distances from the least) and its power sums about an integer centre.
//!
//! Integer sums are exact, so they need no fixed order: they vectorise
//! freely and give the same numbers on every CPU, and moments formed from
//! them are rounded once at the end instead of once per sample. A gate of
//! codes is read as codes (2 bytes a sample), not as the volts they decode
//! to (8 bytes a sample).

/// Largest distance |c − centre| [`code_power_sums`] accepts: d⁴ ≤ 2⁴⁸, so
/// the 4096 of a block add up in an `i64` without overflow.
pub const MAX_DISTANCE: i32 = 1 << 12;

/// Samples summed in `i64` lanes before the block's sums join the `i128`
/// totals (4096 · 2⁴⁸ = 2⁶⁰ < 2⁶³).
const BLOCK: usize = 4096;

/// Least and greatest code of `parts` together; `None` when they hold none.
pub fn code_min_max(parts: &[&[i16]]) -> Option<(i16, i16)> {
    let mut span = None;
    for p in parts.iter().filter(|p| !p.is_empty()) {
        let (lo, hi) = min_max(p);
        span = Some(match span {
            None => (lo, hi),
            Some((a, b)) => (lo.min(a), hi.max(b)),
        });
    }
    span
}

fn min_max(c: &[i16]) -> (i16, i16) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512bw") {
        // SAFETY: AVX-512BW checked just above.
        return unsafe { min_max_avx512(c) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 checked just above.
        return unsafe { min_max_avx2(c) };
    }
    min_max_body(c)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn min_max_avx512(c: &[i16]) -> (i16, i16) {
    min_max_body(c)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn min_max_avx2(c: &[i16]) -> (i16, i16) {
    min_max_body(c)
}

#[inline(always)]
fn min_max_body(c: &[i16]) -> (i16, i16) {
    c.iter().fold((i16::MAX, i16::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)))
}

/// The greatest code of `codes` and the last index holding it; `None` for
/// no codes. One pass: each of 32 lanes keeps its greatest code and the
/// last block of 32 where it held it (ties go to the later block), and the
/// lanes holding the greatest are resolved at the end.
pub fn last_max(codes: &[i16]) -> Option<(i16, usize)> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512bw") {
        // SAFETY: AVX-512BW checked just above.
        return unsafe { last_max_avx512(codes) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 checked just above.
        return unsafe { last_max_avx2(codes) };
    }
    last_max_body(codes)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx2")]
fn last_max_avx512(codes: &[i16]) -> Option<(i16, usize)> {
    last_max_body(codes)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn last_max_avx2(codes: &[i16]) -> Option<(i16, usize)> {
    last_max_body(codes)
}

#[inline(always)]
fn last_max_body(codes: &[i16]) -> Option<(i16, usize)> {
    const LANES: usize = 32;
    // Block numbers are kept in u16 lanes: past 2¹⁶ blocks, the plain scan.
    if codes.len() / LANES > usize::from(u16::MAX) {
        let top = *codes.iter().max()?;
        return Some((top, codes.iter().rposition(|&c| c == top)?));
    }
    let (mut acc, mut at) = ([i16::MIN; LANES], [0u16; LANES]);
    let chunks = codes.chunks_exact(LANES);
    let rest = chunks.remainder();
    for (b, c) in chunks.enumerate() {
        for l in 0..LANES {
            let later = c[l] >= acc[l];
            at[l] = if later { b as u16 } else { at[l] };
            acc[l] = acc[l].max(c[l]);
        }
    }
    let whole = codes.len() - rest.len();
    let top = rest.iter().copied().chain(acc.iter().copied().take(whole.min(LANES))).max()?;
    if let Some(i) = rest.iter().rposition(|&c| c == top) {
        return Some((top, whole + i));
    }
    (0..LANES.min(whole)).filter(|&l| acc[l] == top).map(|l| usize::from(at[l]) * LANES + l).max().map(|i| (top, i))
}

/// Greatest common divisor of `c − lo` over every code of `parts` (`lo`
/// their least code): the grid the codes lie on, in codes (1 for a
/// digitiser's own codes, 16 for 12-bit codes shifted into 16 bits). 0 when
/// every code is `lo`.
pub fn code_grid(parts: &[&[i16]], lo: i16) -> u32 {
    let lo = i32::from(lo);
    let dist = |c: i16| (i32::from(c) - lo) as u32;
    // The powers of two all distances share are the trailing zeros of their
    // bitwise OR (one pass that vectorises); the odd part is Euclid's over
    // the distances until it reaches 1, which for a digitiser's codes it
    // does within the first few.
    let or = parts.iter().fold(0u32, |acc, p| p.iter().fold(acc, |a, &c| a | dist(c)));
    if or == 0 {
        return 0;
    }
    let two = or.trailing_zeros();
    let mut odd = 0u32;
    'parts: for p in parts {
        for &c in p.iter() {
            let d = dist(c) >> two;
            if d != 0 {
                odd = gcd(odd, d);
                if odd == 1 {
                    break 'parts;
                }
            }
        }
    }
    odd << two
}

fn gcd(mut a: u32, mut b: u32) -> u32 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Each code's level on the grid of `grid` codes from `lo` ((c − lo)/grid,
/// exact; `grid` from [`code_grid`], so every distance divides) into
/// `index`, the codes of `parts` in order (`index.len()` is their count).
pub fn code_levels(parts: &[&[i16]], lo: i16, grid: u32, index: &mut [u32]) {
    let lo = i32::from(lo);
    let mut at = 0;
    for p in parts {
        let out = &mut index[at..at + p.len()];
        if grid.is_power_of_two() {
            let shift = grid.trailing_zeros();
            for (k, &c) in out.iter_mut().zip(p.iter()) {
                *k = ((i32::from(c) - lo) as u32) >> shift;
            }
        } else {
            for (k, &c) in out.iter_mut().zip(p.iter()) {
                *k = (i32::from(c) - lo) as u32 / grid;
            }
        }
        at += p.len();
    }
}

/// Σd, Σd², Σd³ and Σd⁴ of d = c − `centre` over every code of `parts`,
/// exactly. The caller bounds |d| by [`MAX_DISTANCE`] (debug-asserted).
pub fn code_power_sums(parts: &[&[i16]], centre: i16) -> [i128; 4] {
    power_sums::<4>(parts, centre)
}

/// Σd and Σd² of d = c − `centre` over every code of `parts`, exactly
/// (|d| ≤ [`MAX_DISTANCE`], as for [`code_power_sums`]).
pub fn code_square_sums(parts: &[&[i16]], centre: i16) -> [i128; 2] {
    power_sums::<2>(parts, centre)
}

/// Mean and sum of squared deviations of the volts `c·g + o` of the codes
/// of `parts`, from their exact sums about the code midway between the
/// least and the greatest: n·M2 = n·Σd² − (Σd)² exactly in integers, then
/// converted and scaled (a few roundings: the second moment of
/// [`Moments::of_codes`](crate::detect::noise_model::Moments::of_codes)).
/// `None` for no codes, codes out of [`exact_centre`]'s reach, or sums
/// beyond `i128` (the caller sums the volts).
pub fn code_mean_sum_sq_dev(parts: &[&[i16]], g: f64, o: f64) -> Option<(f64, f64)> {
    let (lo, hi) = code_min_max(parts)?;
    let centre = exact_centre(lo, hi, g, o)?;
    let n = parts.iter().map(|p| p.len()).sum::<usize>();
    let [s1, s2] = code_square_sums(parts, centre);
    let c2 = (n as i128).checked_mul(s2)?.checked_sub(s1.checked_mul(s1)?)?;
    let nf = n as f64;
    Some(((f64::from(centre) * g + o) + g * (s1 as f64 / nf), c2 as f64 / nf * (g * g)))
}

/// The centre about which the codes from `lo` to `hi`, decoded as `c·g +
/// o`, are summed exactly: the code midway between them (rounded down, so
/// no code is further than [`MAX_DISTANCE`] from it). `None` where that
/// cannot be done: `hi < lo`, a span over 2·`MAX_DISTANCE` codes, a scale
/// outside [1e-60, 1e60] (its fourth power must stay normal) or an offset
/// that is not finite.
pub fn exact_centre(lo: i16, hi: i16, g: f64, o: f64) -> Option<i16> {
    let within = hi >= lo && i32::from(hi) - i32::from(lo) <= 2 * MAX_DISTANCE && g.abs() >= 1e-60 && g.abs() <= 1e60 && o.is_finite();
    within.then_some(((i32::from(lo) + i32::from(hi)) >> 1) as i16)
}

/// The first `K` power sums (K = 2 or 4).
fn power_sums<const K: usize>(parts: &[&[i16]], centre: i16) -> [i128; K] {
    let mut total = [0i128; K];
    for p in parts {
        for block in p.chunks(BLOCK) {
            let s = block_sums::<K>(block, i64::from(centre));
            for (t, v) in total.iter_mut().zip(s) {
                *t += i128::from(v);
            }
        }
    }
    total
}

fn block_sums<const K: usize>(c: &[i16], centre: i64) -> [i64; K] {
    debug_assert!(c.iter().all(|&v| (i64::from(v) - centre).abs() <= i64::from(MAX_DISTANCE)));
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512dq") && std::arch::is_x86_feature_detected!("avx512bw") {
        // SAFETY: AVX-512F, DQ and BW checked just above.
        return unsafe { block_sums_avx512::<K>(c, centre) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 checked just above.
        return unsafe { block_sums_avx2::<K>(c, centre) };
    }
    block_sums_body::<K>(c, centre)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512bw,avx2")]
fn block_sums_avx512<const K: usize>(c: &[i16], centre: i64) -> [i64; K] {
    block_sums_body::<K>(c, centre)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn block_sums_avx2<const K: usize>(c: &[i16], centre: i64) -> [i64; K] {
    block_sums_body::<K>(c, centre)
}

#[inline(always)]
fn block_sums_body<const K: usize>(c: &[i16], centre: i64) -> [i64; K] {
    // |d| ≤ 2¹²: d² fits an i32 (the cheap multiply), d³ and d⁴ an i64.
    let (mut s1, mut s2, mut s3, mut s4) = (0i64, 0i64, 0i64, 0i64);
    for &v in c {
        let d = (i64::from(v) - centre) as i32;
        let d2 = d * d;
        s1 += i64::from(d);
        s2 += i64::from(d2);
        if K > 2 {
            s3 += i64::from(d2) * i64::from(d);
            s4 += i64::from(d2) * i64::from(d2);
        }
    }
    let all = [s1, s2, s3, s4];
    std::array::from_fn(|k| all[k])
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn codes(n: usize, centre: i32, spread: i32, grid: i32, seed: u64) -> Vec<i16> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| (centre + grid * rng.random_range(-spread..=spread)) as i16).collect()
    }

    #[test]
    fn power_sums_are_the_naive_sums() {
        // Blocks of every size around BLOCK, centres off the data, the
        // widest distances allowed, parts of any length (empty among them).
        for (n, centre, spread, seed) in [(0usize, 0i32, 3i32, 1u64), (1, 5, 0, 2), (7, -300, 40, 3), (4095, 2000, 1000, 4), (4097, 0, 4096, 5), (9000, -20000, 2048, 6)] {
            let c = codes(n, centre, spread, 1, seed);
            let k = (n / 3).min(c.len());
            let parts: [&[i16]; 3] = [&c[..k], &[], &c[k..]];
            let at = centre.clamp(-32768, 32767) as i16;
            let want = c.iter().fold([0i128; 4], |mut s, &v| {
                let d = i128::from(v) - i128::from(at);
                s[0] += d;
                s[1] += d * d;
                s[2] += d * d * d;
                s[3] += d * d * d * d;
                s
            });
            assert_eq!(code_power_sums(&parts, at), want, "{n} codes about {centre}");
            assert_eq!(block_sums_body::<4>(&c[..n.min(BLOCK)], i64::from(at)).map(i128::from), code_power_sums(&[&c[..n.min(BLOCK)]], at), "{n}: the portable body");
            assert_eq!(code_square_sums(&parts, at), [want[0], want[1]], "{n} codes about {centre}: the first two");
            // Each compile of the block's body this CPU can run.
            let block = &c[..n.min(BLOCK)];
            let body = (block_sums_body::<4>(block, i64::from(at)), block_sums_body::<2>(block, i64::from(at)), min_max_body(block), last_max_body(block));
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: AVX2 checked just above.
                let got = unsafe { (block_sums_avx2::<4>(block, i64::from(at)), block_sums_avx2::<2>(block, i64::from(at)), min_max_avx2(block), last_max_avx2(block)) };
                assert_eq!(got, body, "{n}: AVX2");
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx512dq") && std::arch::is_x86_feature_detected!("avx512bw") {
                // SAFETY: AVX-512F, DQ and BW checked just above.
                let got = unsafe { (block_sums_avx512::<4>(block, i64::from(at)), block_sums_avx512::<2>(block, i64::from(at)), min_max_avx512(block), last_max_avx512(block)) };
                assert_eq!(got, body, "{n}: AVX-512");
            }
        }
    }

    #[test]
    fn the_grid_is_the_gcd_of_the_distances() {
        for (grid, spread, seed) in [(1i32, 20i32, 1u64), (16, 30, 2), (3, 50, 3), (12, 9, 4), (7, 1, 5)] {
            let c = codes(500, -101, spread, grid, seed);
            let (lo, hi) = code_min_max(&[&c[..200], &c[200..]]).expect("codes");
            assert_eq!((lo, hi), (*c.iter().min().unwrap(), *c.iter().max().unwrap()));
            let want = c.iter().fold(0u32, |g, &v| gcd(g, (i32::from(v) - i32::from(lo)) as u32));
            assert_eq!(want, grid as u32, "the data's grid");
            assert_eq!(code_grid(&[&c[..200], &c[200..]], lo), want, "grid {grid}");
            let mut index = vec![0u32; c.len()];
            code_levels(&[&c[..200], &c[200..]], lo, want, &mut index);
            for (k, &v) in index.iter().zip(&c) {
                assert_eq!(i64::from(*k) * i64::from(want), i64::from(v) - i64::from(lo));
            }
        }
        assert_eq!(code_grid(&[&[5, 5, 5]], 5), 0, "one code");
        assert_eq!(code_grid(&[&[-32768, 32767]], -32768), 65535, "the widest span");
        assert_eq!(code_min_max(&[&[], &[]]), None);
    }

    #[test]
    fn last_max_is_the_last_index_of_the_greatest_code() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        for len in [0usize, 1, 31, 32, 33, 64, 95, 2500, 2563] {
            for spread in [1i32, 3, 200, 32767] {
                let c = codes(len, 0, spread, 1, rng.random());
                let want = c.iter().max().map(|&top| (top, c.iter().rposition(|&v| v == top).expect("present")));
                assert_eq!(last_max(&c), want, "{len} codes, spread {spread}");
                assert_eq!(last_max_body(&c), want, "{len} codes, spread {spread}: the portable body");
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: AVX2 checked just above.
                    assert_eq!(unsafe { last_max_avx2(&c) }, want, "{len} codes, spread {spread}: AVX2");
                }
            }
        }
        assert_eq!(last_max(&[i16::MIN; 40]), Some((i16::MIN, 39)), "every code the least");
    }
}
