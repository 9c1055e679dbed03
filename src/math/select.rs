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

/// [`last_max_index`] of a slice that changes in small ranges between
/// searches (the resolver's filter output: each resolved pulse changes the
/// outputs near it only): the maximum of every block of [`BlockMaxima::BLOCK`]
/// values is kept, a change refreshes the blocks it touches, and a search
/// reads the block maxima and then one block. The same index as
/// [`last_max_index`] on the whole slice (its serial path where that takes one).
#[derive(Debug, Clone, Default)]
pub struct BlockMaxima {
    /// Largest value of each block (NaN where the block holds one).
    maxima: Vec<f64>,
}

impl BlockMaxima {
    /// Values per block.
    pub const BLOCK: usize = 64;

    /// Takes the maxima of all of `x`.
    pub fn fill(&mut self, x: &[f64]) {
        self.maxima.clear();
        self.maxima.extend(x.chunks(Self::BLOCK).map(block_max));
    }

    /// Refreshes the blocks of `x` (the slice given to [`fill`](Self::fill),
    /// changed since only within `changed`) that `changed` touches.
    pub fn refresh(&mut self, x: &[f64], changed: std::ops::Range<usize>) {
        let end = changed.end.min(x.len());
        if changed.start >= end {
            return;
        }
        for b in changed.start / Self::BLOCK..end.div_ceil(Self::BLOCK) {
            let c = &x[b * Self::BLOCK..((b + 1) * Self::BLOCK).min(x.len())];
            self.maxima[b] = block_max(c);
        }
    }

    /// [`last_max_index`] of `x` (the slice the maxima are of).
    pub fn last_max_index(&self, x: &[f64]) -> Option<usize> {
        debug_assert_eq!(self.maxima.len(), x.len().div_ceil(Self::BLOCK));
        let mut m = f64::NEG_INFINITY;
        for &v in &self.maxima {
            if v.is_nan() {
                return last_max_index(x);
            }
            m = if v > m { v } else { m };
        }
        if m == 0.0 || x.is_empty() {
            return last_max_index(x);
        }
        // m ≠ ±0 and no NaN: the last index holding m is in the last block whose maximum it is.
        let b = self.maxima.iter().rposition(|&v| v == m)?;
        let block = &x[b * Self::BLOCK..((b + 1) * Self::BLOCK).min(x.len())];
        block.iter().rposition(|&v| v == m).map(|i| b * Self::BLOCK + i)
    }
}

/// Largest value of `c` by `>` in eight lanes; NaN if `c` holds one.
fn block_max(c: &[f64]) -> f64 {
    match lane_max(c) {
        (_, true) => f64::NAN,
        (m, false) => m,
    }
}

/// (largest value of `x` by `>`, whether `x` holds a NaN), in eight lanes
/// (one serial comparison chain otherwise); −∞ for an empty slice.
#[inline(always)]
fn lane_max(x: &[f64]) -> (f64, bool) {
    let mut acc = [f64::NEG_INFINITY; 8];
    let mut nan = false;
    let chunks = x.chunks_exact(8);
    let rest = chunks.remainder();
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
    (acc.iter().copied().fold(f64::NEG_INFINITY, |a, b| if b > a { b } else { a }), nan)
}

/// Index of the last largest value of `x` under [`f64::total_cmp`], which is
/// what `(0..x.len()).max_by(|&a, &b| x[a].total_cmp(&x[b]))` returns (None
/// for an empty slice): the maximum in eight lanes, then the last index
/// holding it, instead of one serial comparison chain. Ties at zero (where
/// the total order tells −0 from +0) and NaNs take the serial path.
pub fn last_max_index(x: &[f64]) -> Option<usize> {
    let serial = || (0..x.len()).max_by(|&a, &b| x[a].total_cmp(&x[b]));
    let (m, nan) = lane_max(x);
    let rest = &x[x.len() - x.len() % 8..];
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

/// Robust sigma ([`mad_sigma`]) of the lagged differences of integer codes,
/// `codes[i + lag] − codes[i]` for every `i` with both ends inside one run
/// of `runs`, by counting instead of selecting: the differences of codes
/// that span at most [`CodeDiffMad::MAX_SPAN`] take at most 2·span + 1
/// values, so their median and their median absolute deviation are read off
/// one histogram (the deviations' is the histogram folded about the
/// median). The result is `mad_sigma` of those differences as f64, bit for
/// bit (every value on the way is an exact half-integer); a pass over the
/// differences instead of two selections. The histogram is the caller's to
/// keep: [`CodeDiffMad::reserve`] grows it once, and nothing else allocates.
#[derive(Debug, Default, Clone)]
pub struct CodeDiffMad {
    /// Four interleaved counts per difference (bin `4·(d + span) + lane`):
    /// neighbouring differences are often equal, and four lanes keep their
    /// increments off one another's store.
    hist: Vec<u32>,
}

impl CodeDiffMad {
    /// Widest span (largest less smallest code over the runs) counted; wider
    /// codes are the caller's to select (see [`CodeDiffMad::span`]).
    pub const MAX_SPAN: i32 = 1024;

    /// Grows the histogram to its largest now, so that no frame allocates.
    pub fn reserve(&mut self) {
        let most = 4 * (2 * Self::MAX_SPAN as usize + 1);
        self.hist.reserve(most.saturating_sub(self.hist.len()));
    }

    /// Largest less smallest of `codes` over `runs` (0 with none), or None
    /// past [`CodeDiffMad::MAX_SPAN`]. Panics where a run is out of `codes`.
    pub fn span(codes: &[i16], runs: &[std::ops::Range<usize>]) -> Option<i32> {
        let (mut lo, mut hi) = (i16::MAX, i16::MIN);
        for r in runs {
            if let Some((a, b)) = super::code_stats::code_min_max(&[&codes[r.clone()]]) {
                (lo, hi) = (lo.min(a), hi.max(b));
            }
        }
        let span = (i32::from(hi) - i32::from(lo)).max(0);
        (span <= Self::MAX_SPAN).then_some(span)
    }

    /// (count of differences at `lag`, their [`mad_sigma`] in code units);
    /// `span` from [`CodeDiffMad::span`] on the same codes and runs (a
    /// difference outside ±span panics). (0, 0.0) when no run is longer than `lag`.
    pub fn lag(&mut self, codes: &[i16], runs: &[std::ops::Range<usize>], lag: usize, span: i32) -> (usize, f64) {
        let width = 2 * span as usize + 1;
        self.hist.clear();
        self.hist.resize(4 * width, 0);
        let hist = &mut self.hist[..];
        let bin = |a: i16, b: i16| (i32::from(b) - i32::from(a) + span) as usize;
        let mut n = 0;
        for r in runs {
            if r.end <= r.start + lag {
                continue;
            }
            let (a, b) = (&codes[r.start..r.end - lag], &codes[r.start + lag..r.end]);
            n += a.len();
            let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
            for (&x, &y) in ca.remainder().iter().zip(cb.remainder()) {
                hist[4 * bin(x, y)] += 1;
            }
            for (x, y) in ca.zip(cb) {
                for l in 0..4 {
                    hist[4 * bin(x[l], y[l]) + l] += 1;
                }
            }
        }
        if n == 0 {
            return (0, 0.0);
        }
        for k in 0..width {
            let q = &hist[4 * k..4 * k + 4];
            hist[k] = q[0] + q[1] + q[2] + q[3];
        }
        let counts = &hist[..width];
        // The sorted differences' places n/2 − 1 (even n) and n/2, as
        // `median` takes them; differences as d + span.
        let (upper, lower) = (n / 2, if n % 2 == 0 { n / 2 - 1 } else { n / 2 });
        let at = |place: usize| {
            let mut below = 0usize;
            for (k, &c) in counts.iter().enumerate() {
                below += c as usize;
                if below > place {
                    return k as i64;
                }
            }
            unreachable!("place {place} of {n} counted")
        };
        // Twice the median, in code units (an integer): 2d − m2 is twice a deviation.
        let m2 = at(lower) + at(upper) - 2 * i64::from(span);
        // The deviations |2d − m2| in rising order: each k gathers the
        // differences (m2 ± k)/2 (one of them for k = 0).
        let count = |d2: i64| -> usize {
            if d2 % 2 != 0 {
                return 0;
            }
            let k = d2 / 2 + i64::from(span);
            if (0..width as i64).contains(&k) { counts[k as usize] as usize } else { 0 }
        };
        let (mut below, mut dev_lower, mut dev_upper) = (0usize, None, None);
        for k in 0..=(4 * i64::from(span) + m2.abs()) {
            below += if k == 0 { count(m2) } else { count(m2 + k) + count(m2 - k) };
            if dev_lower.is_none() && below > lower {
                dev_lower = Some(k);
            }
            if below > upper {
                dev_upper = Some(k);
                break;
            }
        }
        let half = |k: Option<i64>| 0.5 * k.expect("every deviation counted") as f64;
        let (lo, hi) = (half(dev_lower), half(dev_upper));
        let med = if n % 2 == 1 { hi } else { 0.5 * (lo + hi) };
        (n, 1.482_602_218_505_602 * med)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_maxima_find_what_last_max_index_finds_as_the_values_change() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for n in [0usize, 1, 7, 63, 64, 65, 200, 1000] {
            // Values on a coarse grid (ties), zeros of both signs and, now and then, a NaN.
            let mut x: Vec<f64> = (0..n).map(|_| (rng.random_range(-8..4) as f64) * 0.5).collect();
            let mut blocks = BlockMaxima::default();
            blocks.fill(&x);
            for round in 0..60 {
                assert_eq!(blocks.last_max_index(&x), last_max_index(&x), "n {n} round {round}");
                if n == 0 {
                    break;
                }
                let a = rng.random_range(0..n);
                let b = (a + rng.random_range(1..40)).min(n);
                for v in &mut x[a..b] {
                    *v = match rng.random_range(0..20) {
                        0 => -0.0,
                        1 => 0.0,
                        2 if round % 7 == 3 => f64::NAN,
                        _ => (rng.random_range(-8..6) as f64) * 0.5,
                    };
                }
                blocks.refresh(&x, a..b);
            }
        }
    }
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

    #[test]
    fn code_diff_mad_is_mad_sigma_of_the_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut mad = CodeDiffMad::default();
        mad.reserve();
        let naive = |codes: &[i16], runs: &[std::ops::Range<usize>], lag: usize| {
            let mut d: Vec<f64> = runs
                .iter()
                .flat_map(|r| (r.start..r.end.saturating_sub(lag)).map(move |i| f64::from(codes[i + lag]) - f64::from(codes[i])))
                .collect();
            (d.len(), mad_sigma(&mut d))
        };
        // Narrow noise (many ties, a median on or between levels), wide
        // noise, a lopsided spread and a constant run; odd and even counts,
        // runs shorter than the lag, the widest span counted.
        for case in 0..40 {
            let n = rng.random_range(1..700usize);
            let spread: i32 = [0, 1, 3, 40, 511][case % 5];
            let centre: i16 = rng.random_range(-2000..2000);
            let codes: Vec<i16> = (0..n)
                .map(|_| {
                    let v = if case % 7 == 3 { rng.random_range(0..=spread).pow(2) / spread.max(1) } else { rng.random_range(-spread..=spread) };
                    centre + v as i16
                })
                .collect();
            let cut = rng.random_range(0..=n);
            let runs = [0..cut / 3, cut..n, cut / 3..cut / 3 + 2.min(n - cut / 3)];
            let span = CodeDiffMad::span(&codes, &runs).expect("narrow");
            for lag in [1usize, 2, 5, 16, 700] {
                let (count, got) = mad.lag(&codes, &runs, lag, span);
                let (want_count, want) = naive(&codes, &runs, lag);
                assert_eq!((count, got.to_bits()), (want_count, want.to_bits()), "case {case} n {n} lag {lag}: {got} vs {want}");
            }
        }
        let wide = [-600i16, 0, 500];
        assert_eq!(CodeDiffMad::span(&wide, &[0..3]), None);
        assert_eq!(CodeDiffMad::span(&wide, &[0..1, 2..3]), None);
        assert_eq!(CodeDiffMad::span(&wide, &[1..3]), Some(500));
        assert_eq!(CodeDiffMad::span(&wide, &[]), Some(0));
        // Differences 1024 and −3 at the top of the codes: median 510.5, both deviations 513.5.
        let (count, got) = mad.lag(&[i16::MAX - 1024, i16::MAX, i16::MAX - 3], &[0..3], 1, 1024);
        assert_eq!((count, got), (2, 1.482_602_218_505_602 * 513.5));
    }
}
