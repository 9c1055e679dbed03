//! Selection statistics: median, high median, trimmed mean and the MAD
//! sigma, all by linear-time selection (`select_nth_unstable_by`, no sort) in
//! a slice the caller lends (reordered in place, nothing allocated).
//!
//! Order is `f64::total_cmp`: NaN with the sign bit clear sorts above every
//! number, NaN with it set (what x86 arithmetic produces) below; callers that
//! must ignore non-finite samples drop them first.

/// (smallest, largest) of `x`, NaNs ignored ((+∞, −∞) when nothing is
/// left), in eight lanes (a fold through `f64::min` is one serial chain);
/// zeros of either sign count as equal.
pub fn min_max(x: &[f64]) -> (f64, f64) {
    let (mut lo, mut hi) = ([f64::INFINITY; 8], [f64::NEG_INFINITY; 8]);
    let chunks = x.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for l in 0..8 {
            lo[l] = if c[l] < lo[l] { c[l] } else { lo[l] };
            hi[l] = if c[l] > hi[l] { c[l] } else { hi[l] };
        }
    }
    for (l, &v) in rest.iter().enumerate() {
        lo[l] = if v < lo[l] { v } else { lo[l] };
        hi[l] = if v > hi[l] { v } else { hi[l] };
    }
    let lo = lo.iter().copied().fold(f64::INFINITY, |a, b| if b < a { b } else { a });
    let hi = hi.iter().copied().fold(f64::NEG_INFINITY, |a, b| if b > a { b } else { a });
    (lo, hi)
}

/// Index of the last largest value of `x` under [`f64::total_cmp`], which is
/// what `(0..x.len()).max_by(|&a, &b| x[a].total_cmp(&x[b]))` returns (None
/// for an empty slice): the maximum in eight lanes, then the last index
/// holding it, instead of one serial comparison chain. Ties at zero (where
/// the total order tells −0 from +0) and NaNs take the serial path.
pub fn last_max_index(x: &[f64]) -> Option<usize> {
    let serial = || (0..x.len()).max_by(|&a, &b| x[a].total_cmp(&x[b]));
    let mut acc = [f64::NEG_INFINITY; 8];
    let chunks = x.chunks_exact(8);
    let rest = chunks.remainder();
    let mut nan = false;
    for c in chunks {
        for l in 0..8 {
            nan |= c[l].is_nan();
            acc[l] = if c[l] > acc[l] { c[l] } else { acc[l] };
        }
    }
    for (l, &v) in rest.iter().enumerate() {
        nan |= v.is_nan();
        acc[l] = if v > acc[l] { v } else { acc[l] };
    }
    let m = acc.iter().copied().fold(f64::NEG_INFINITY, |a, b| if b > a { b } else { a });
    if nan || m == 0.0 || x.is_empty() {
        return serial();
    }
    // m ≠ ±0 and no NaN: total_cmp's equal maxima are the values == m.
    // Searched from the end eight at a time (one compare per lane and no
    // branch per sample: a start pulse early in a long channel leaves most
    // of it to pass over), then within the eight that hold it.
    let mut end = x.len() - rest.len();
    if let Some(i) = rest.iter().rposition(|&v| v == m) {
        return Some(end + i);
    }
    while end >= 8 {
        // One bit per lane equal to m; the highest is the last such sample.
        let mut hits = 0u32;
        for (l, &v) in x[end - 8..end].iter().enumerate() {
            hits |= ((v == m) as u32) << l;
        }
        if hits != 0 {
            return Some(end - 8 + (31 - hits.leading_zeros()) as usize);
        }
        end -= 8;
    }
    x.iter().rposition(|&v| v == m)
}

/// Median of `values` (reordered in place): the middle value for an odd
/// count, the mean of the two middle values for an even one; `None` when
/// empty. Equal to `trimmed_mean(values, 0.5)`, with one selection instead
/// of two.
pub fn median(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let (lower, hi, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    let hi = *hi;
    if n % 2 == 1 {
        return Some(hi);
    }
    // The lower middle is the largest value below the upper one.
    let lo = lower.iter().copied().max_by(f64::total_cmp).unwrap_or(hi);
    Some(0.5 * (lo + hi))
}

/// High median of `values` (reordered in place): the order statistic at
/// index n/2 (the middle value for an odd count, the upper of the two middle
/// values for an even one: always a sample, never an average); `None` when
/// empty.
pub fn high_median(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    Some(*values.select_nth_unstable_by(n / 2, f64::total_cmp).1)
}

/// Robust sigma: 1.4826 × the median absolute deviation from the [`median`]
/// (consistent with σ for Gaussian samples). Reorders and overwrites `x`
/// with the absolute deviations; 0 for an empty slice.
pub fn mad_sigma(x: &mut [f64]) -> f64 {
    let Some(med) = median(x) else {
        return 0.0;
    };
    for v in x.iter_mut() {
        *v = (*v - med).abs();
    }
    1.482_602_218_505_602 * median(x).unwrap_or(0.0)
}

/// Mean of `values` after dropping the `floor(trim_fraction · n)` smallest and
/// as many largest (reordered in place; at least one value — two for even `n`
/// — is kept, so `trim_fraction >= 0.5` gives the median). `None` when empty.
/// `trim_fraction` is clamped to [0, 0.5]. Linear time (selection, no sort).
pub fn trimmed_mean(values: &mut [f64], trim_fraction: f64) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let t = if trim_fraction.is_nan() {
        0.0
    } else {
        trim_fraction.clamp(0.0, 0.5)
    };
    let g = ((t * n as f64).floor() as usize).min((n - 1) / 2);
    let kept = if g > 0 {
        // Put the g smallest before index g, then the g largest after n − g.
        let (_, _, upper) = values.select_nth_unstable_by(g - 1, f64::total_cmp);
        let m = upper.len() - g; // values kept live in upper[..m]
        upper.select_nth_unstable_by(m, f64::total_cmp);
        &upper[..m]
    } else {
        &values[..]
    };
    Some(kept.iter().sum::<f64>() / kept.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn min_max_is_the_fold_through_min_and_max() {
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        for n in [0usize, 1, 5, 8, 13, 1391] {
            let mut x: Vec<f64> = (0..n).map(|_| rng.random_range(-1e3..1e3)).collect();
            if n > 4 {
                x[3] = f64::NAN;
            }
            let want = x.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
            assert_eq!(min_max(&x), want, "n {n}");
        }
        assert_eq!(min_max(&[f64::NAN]), (f64::INFINITY, f64::NEG_INFINITY));
    }

    #[test]
    fn last_max_index_is_max_by_total_cmp() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let serial = |x: &[f64]| (0..x.len()).max_by(|&a, &b| x[a].total_cmp(&x[b]));
        for n in [0usize, 1, 7, 8, 9, 100, 2500] {
            for case in 0..6 {
                // Quantised values tie often; zeros of both signs, NaNs and -inf test the edges.
                let mut x: Vec<f64> = (0..n).map(|_| (rng.random_range(-20.0..20.0f64)).round() * 0.25).collect();
                match case {
                    1 => x.iter_mut().for_each(|v| *v = -v.abs()),
                    2 => x.iter_mut().for_each(|v| *v = if rng.random_bool(0.5) { 0.0 } else { -0.0 }),
                    3 if n > 3 => x[n / 2] = f64::NAN,
                    4 => x.iter_mut().for_each(|v| *v = f64::NEG_INFINITY),
                    _ => {}
                }
                assert_eq!(last_max_index(&x), serial(&x), "n {n} case {case}");
            }
        }
    }

    #[test]
    fn trimmed_mean_and_median() {
        let mut v = [5.0, 1.0, 100.0, 2.0, 3.0];
        assert_eq!(median(&mut v), Some(3.0));
        let mut v = [4.0, 1.0, 3.0, 2.0];
        assert_eq!(median(&mut v), Some(2.5));
        let mut v = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 1000.0];
        assert_eq!(trimmed_mean(&mut v, 0.1), Some(5.5)); // drops 1 and 1000
        let mut v = [1.0, 2.0, 4.0];
        assert_eq!(trimmed_mean(&mut v, 0.0), Some(7.0 / 3.0));
        assert_eq!(median(&mut []), None);
    }

    #[test]
    fn match_a_full_sort() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for n in 1..60 {
            let v: Vec<f64> = (0..n).map(|_| rng.random_range(-10.0..10.0)).collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            let want = if n % 2 == 1 {
                sorted[n / 2]
            } else {
                0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
            };
            assert_eq!(median(&mut v.clone()), Some(want), "n={n}");
            assert_eq!(
                median(&mut v.clone()),
                trimmed_mean(&mut v.clone(), 0.5),
                "n={n}"
            );
            assert_eq!(high_median(&mut v.clone()), Some(sorted[n / 2]), "n={n}");
            let mut dev: Vec<f64> = v.iter().map(|x| (x - want).abs()).collect();
            dev.sort_by(f64::total_cmp);
            let mad = if n % 2 == 1 {
                dev[n / 2]
            } else {
                0.5 * (dev[n / 2 - 1] + dev[n / 2])
            };
            assert_eq!(
                mad_sigma(&mut v.clone()),
                1.482_602_218_505_602 * mad,
                "n={n}"
            );
        }
        assert_eq!(high_median(&mut [4.0, 1.0, 3.0, 2.0]), Some(3.0));
        assert_eq!(high_median(&mut []), None);
        assert_eq!(mad_sigma(&mut []), 0.0);
    }
}
