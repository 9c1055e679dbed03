//! Learning the return pulse shape from the data by equivalent-time alignment:
//! many shots land at random sub-sample phases, so placing each shot's samples
//! at their time relative to its fitted peak fills a grid finer than the
//! sampling period. The learned table removes the bias a mismatched
//! parametric shape would leave in model-based timing.

use crate::scene::{PulseConfig, PulseModel};

/// Why a template could not be learned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TemplateError {
    /// Not enough shots.
    #[error("only {got} usable returns; at least {need} are needed to fill the {bins}-bin grid")]
    TooFewShots {
        /// Shots added.
        got: u64,
        /// Shots needed.
        need: u64,
        /// Grid bins.
        bins: usize,
    },
    /// A run of bins no shot reached is too long to interpolate across.
    #[error(
        "{empty} of {bins} grid bins received no sample (or too few to use), and {run} in a row lie between \
         filled ones where interpolation bridges at most {max_run} (half a sample): the shots' sub-sample \
         phases do not cover the period (use more shots, or fewer grid points per sample)"
    )]
    Gaps {
        /// Bins with no sample (or too few to trust, see [`TemplateLearner::interpolated_bins`]).
        empty: usize,
        /// Grid bins.
        bins: usize,
        /// The longest run of such bins between filled ones.
        run: usize,
        /// The longest run interpolation bridges.
        max_run: usize,
    },
}

/// Accumulates shots on a fine grid around their peaks.
#[derive(Debug, Clone)]
pub struct TemplateLearner {
    oversample: usize,
    /// Grid start relative to the peak, samples.
    lo: f64,
    sums: Vec<f64>,
    /// Σ of squares per bin: the bin's standard error decides where the
    /// learned pulse ends and noise begins.
    squares: Vec<f64>,
    counts: Vec<u64>,
    shots: u64,
}

/// A bin holding fewer samples than this fraction of the typical (median)
/// bin is filled by interpolation like an empty one: its mean rests on one
/// or two noisy samples.
const SPARSE_FRACTION: f64 = 0.25;

/// A learned shape still this large (a fraction of its peak) at an end of
/// the grid, and significant all the way there, reaches beyond the grid
/// ([`Learned::cut_after`]).
const CUT_FRACTION: f64 = 0.05;

/// Tails below this fraction of the peak are cut from the learned table.
const TAIL_FRACTION: f64 = 0.01;
/// ...and so are bins whose mean is within this many standard errors of zero.
const TAIL_SE: f64 = 3.0;

impl TemplateLearner {
    /// A grid of `oversample` bins per sample over [lo, hi] samples around the peak.
    pub fn new(oversample: usize, lo: f64, hi: f64) -> TemplateLearner {
        let oversample = oversample.max(1);
        let bins = ((hi - lo) * oversample as f64).ceil() as usize + 1;
        TemplateLearner {
            oversample,
            lo,
            sums: vec![0.0; bins],
            squares: vec![0.0; bins],
            counts: vec![0; bins],
            shots: 0,
        }
    }

    /// Adds one shot: samples `x` with noise mean `mean_v`, fitted peak at
    /// `peak_index` (fractional samples) and amplitude `amplitude_v`.
    pub fn add(&mut self, x: &[f64], mean_v: f64, peak_index: f64, amplitude_v: f64) {
        if !(amplitude_v > 0.0) || !peak_index.is_finite() {
            return;
        }
        let step = 1.0 / self.oversample as f64;
        let bins = self.sums.len();
        let first = (peak_index + self.lo).ceil().max(0.0) as usize;
        for (k, &v) in x.iter().enumerate().skip(first) {
            let t = k as f64 - peak_index;
            let b = ((t - self.lo) / step).round();
            if b >= bins as f64 {
                break;
            }
            // Masked samples (NaN) are skipped.
            if b >= 0.0 && v.is_finite() {
                let u = (v - mean_v) / amplitude_v;
                self.sums[b as usize] += u;
                self.squares[b as usize] += u * u;
                self.counts[b as usize] += 1;
            }
        }
        self.shots += 1;
    }

    /// Shots added so far.
    pub fn shots(&self) -> u64 {
        self.shots
    }

    /// Grid bins in all.
    pub fn bins(&self) -> usize {
        self.sums.len()
    }

    /// Bins between the first and the last filled one that [`finish`](Self::finish)
    /// fills by interpolation: those no shot reached, and those holding fewer
    /// than a quarter of the typical bin's samples. A few dozen shots at
    /// random phases leave some (20 shots on 8 bins per sample miss one bin
    /// in 15).
    pub fn interpolated_bins(&self) -> usize {
        let sparse = self.sparse_mask();
        match filled_span(&sparse) {
            Some((first, last)) => sparse[first..=last].iter().filter(|&&s| s).count(),
            None => 0,
        }
    }

    /// Longest run of bins interpolation bridges: half a sample.
    pub fn max_interpolated_run(&self) -> usize {
        self.oversample / 2
    }

    /// Bins too sparse to use as they are (see [`interpolated_bins`](Self::interpolated_bins)).
    fn sparse_mask(&self) -> Vec<bool> {
        let mut filled: Vec<u64> = self.counts.iter().copied().filter(|&c| c > 0).collect();
        let typical = if filled.is_empty() {
            0
        } else {
            let mid = filled.len() / 2;
            *filled.select_nth_unstable(mid).1
        };
        let floor = SPARSE_FRACTION * typical as f64;
        self.counts.iter().map(|&c| c == 0 || (c as f64) < floor).collect()
    }

    /// The learned shape as a scene pulse (table model, unit peak, re-centred on its peak).
    ///
    /// Bins no shot reached, or too sparse to trust, are interpolated from
    /// their filled neighbours (a cubic through two on each side, linear
    /// where one side has only one); runs longer than half a sample are
    /// refused ([`TemplateError::Gaps`]). Bins beyond the first and last
    /// filled one (the grid reached past every frame's end) are zero.
    pub fn finish(&self, dt_s: f64) -> Result<PulseConfig, TemplateError> {
        self.finish_learned(dt_s).map(|l| l.pulse)
    }

    /// [`finish`](Self::finish), also saying whether the pulse reaches
    /// beyond the grid's end.
    pub fn finish_learned(&self, dt_s: f64) -> Result<Learned, TemplateError> {
        let bins = self.sums.len();
        // What interpolation needs: phases no more than half a sample apart,
        // which two shots can give.
        let max_run = self.max_interpolated_run();
        let need = (self.oversample as u64).div_ceil(max_run as u64 + 1);
        if self.shots < need || bins < 4 {
            return Err(TemplateError::TooFewShots { got: self.shots, need, bins });
        }
        let sparse = self.sparse_mask();
        let Some((first, last)) = filled_span(&sparse) else {
            return Err(TemplateError::TooFewShots { got: self.shots, need, bins });
        };
        let run = longest_run(&sparse[first..=last]);
        if run > max_run {
            let empty = sparse.iter().filter(|&&s| s).count();
            return Err(TemplateError::Gaps { empty, bins, run, max_run });
        }
        // Bins with two samples or more carry their own variance; the others
        // the pooled within-bin variance of those.
        let (mut pooled_ss, mut pooled_dof) = (0.0, 0.0);
        for ((&s, &q), &c) in self.sums.iter().zip(&self.squares).zip(&self.counts) {
            if c >= 2 {
                pooled_ss += (q - s * s / c as f64).max(0.0);
                pooled_dof += (c - 1) as f64;
            }
        }
        let pooled_var = if pooled_dof > 0.0 { pooled_ss / pooled_dof } else { 0.0 };
        let mut raw: Vec<f64> = (0..bins)
            .map(|i| if sparse[i] { f64::NAN } else { self.sums[i] / self.counts[i] as f64 })
            .collect();
        interpolate_gaps(&mut raw, first, last);
        raw[..first].fill(0.0);
        raw[last + 1..].fill(0.0);
        // Each bin carries its own noise, and a fit follows the table's
        // slope, which differencing bins 1/oversample apart amplifies: the
        // cost of a delay fit then has ripples a bin wide that trap the
        // iteration. The pulse, sampled at 1/dt, has no content near the
        // grid's own Nyquist rate, so a Gaussian of 0.15 sample (a 0.4 %
        // loss at 0.1 cycle per sample, 1.8 % at 0.2) removes the bin noise
        // and keeps the shape.
        let mean = gaussian_smooth(&raw, 0.15 * self.oversample as f64);
        // A light 3-bin average before locating the peak, so one noisy bin does not move it.
        let smooth: Vec<f64> = (0..bins)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(bins - 1));
                (mean[a] + mean[i] + mean[b]) / 3.0
            })
            .collect();
        let p = (1..bins - 1).max_by(|&a, &b| smooth[a].total_cmp(&smooth[b])).unwrap_or(bins / 2);
        let (d, h) = crate::dsp::interp::parabolic(smooth[p - 1], smooth[p], smooth[p + 1]);
        let step = 1.0 / self.oversample as f64;
        let peak_t = self.lo + (p as f64 + d) * step;
        // The grid is wider than the pulse: where the shape is lost in noise
        // (below 1 % of the peak, or within 3 standard errors of zero) the
        // table ends, one sample beyond the last significant bin, so a
        // matched filter or fit does not carry noisy taps.
        let significant = |i: usize| {
            if i < first || i > last {
                return false;
            }
            let c = self.counts[i] as f64;
            let se = if sparse[i] {
                (pooled_var / typical_count(&self.counts, &sparse)).sqrt()
            } else if self.counts[i] >= 2 {
                let var = (self.squares[i] / c - mean[i] * mean[i]).max(0.0);
                (var / c).sqrt()
            } else {
                (pooled_var / c).sqrt()
            };
            smooth[i].abs() > (TAIL_FRACTION * h).max(TAIL_SE * se)
        };
        // Walk out from the peak; the pulse ends where a whole sample period
        // of bins in a row is insignificant.
        let run = self.oversample;
        let (mut first_sig, mut quiet) = (p, 0);
        for i in (0..p).rev() {
            if significant(i) {
                first_sig = i;
                quiet = 0;
            } else {
                quiet += 1;
                if quiet >= run {
                    break;
                }
            }
        }

        let (mut last_sig, mut quiet) = (p, 0);
        for i in p + 1..bins {
            if significant(i) {
                last_sig = i;
                quiet = 0;
            } else {
                quiet += 1;
                if quiet >= run {
                    break;
                }
            }
        }
        // The pulse goes on beyond the grid's end when no quiet run came
        // after it and the shape there is still a sizeable part of the peak
        // (an undershoot or ringing; a neighbouring return's imperfectly
        // subtracted tail is smaller).
        let edge = smooth[bins.saturating_sub(run)..].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let cut_after = quiet < run && edge > CUT_FRACTION * h;
        let a = first_sig.saturating_sub(self.oversample);
        let b = (last_sig + self.oversample).min(bins - 1);
        // The vertex of the 3-bin average sits a little below the table's
        // own top when the grid is coarse (a bin or two per sample): the
        // table is scaled by the larger of the two, so its peak is 1.
        let h = mean[a..=b].iter().copied().fold(h, f64::max);
        let mut table: Vec<f64> = mean[a..=b].iter().map(|v| v / h).collect();
        // A half-Hann taper over one sample at each end: the shape then goes
        // to zero smoothly where the table stops, so a fit that slides it
        // against a fixed window sees no step at the ends.
        let taper = self.oversample.min(table.len() / 4);
        let len = table.len();
        for i in 0..taper {
            let w = 0.5 * (1.0 - (std::f64::consts::PI * (i as f64 + 0.5) / taper as f64).cos());
            table[i] *= w;
            table[len - 1 - i] *= w;
        }
        Ok(Learned {
            pulse: PulseConfig {
                model: PulseModel::Table,
                rise_time_s: 0.0,
                fwhm_s: 0.0,
                table_step_s: step * dt_s,
                table_first_s: (self.lo + a as f64 * step - peak_t) * dt_s,
                table,
            },
            cut_after,
        })
    }
}

/// A learned shape, and whether the grid was too short for it.
#[derive(Debug, Clone, PartialEq)]
pub struct Learned {
    /// The shape as a scene pulse (table model).
    pub pulse: PulseConfig,
    /// The shape was significant all the way to the grid's end and still
    /// above 5 % of its peak there: the pulse goes on past the grid (a long
    /// tail, an undershoot or ringing the first guess of the shape did not
    /// reach); learn again on a wider grid. Only the end is checked: a
    /// pulse's onset is short, and what reaches the grid's start is a
    /// neighbouring return.
    pub cut_after: bool,
}

/// First and last bin that is not sparse.
fn filled_span(sparse: &[bool]) -> Option<(usize, usize)> {
    let first = sparse.iter().position(|&s| !s)?;
    let last = sparse.iter().rposition(|&s| !s)?;
    Some((first, last))
}

/// Longest run of `true`.
fn longest_run(mask: &[bool]) -> usize {
    let (mut best, mut run) = (0, 0);
    for &m in mask {
        run = if m { run + 1 } else { 0 };
        best = best.max(run);
    }
    best
}

/// Mean samples per filled (not sparse) bin.
fn typical_count(counts: &[u64], sparse: &[bool]) -> f64 {
    let (sum, n) = counts.iter().zip(sparse).filter(|(_, s)| !**s).fold((0u64, 0u64), |(a, n), (&c, _)| (a + c, n + 1));
    if n == 0 { 1.0 } else { (sum as f64 / n as f64).max(1.0) }
}

/// Fills the NaN entries of `x[first..=last]` (`x[first]` and `x[last]`
/// are finite) from the finite ones around each run: the cubic through the
/// two nearest on each side, or the line through the nearest where a side
/// has only one. Positions are bin indices, so the neighbours need not be
/// evenly spaced.
fn interpolate_gaps(x: &mut [f64], first: usize, last: usize) {
    let mut i = first;
    while i <= last {
        if !x[i].is_nan() {
            i += 1;
            continue;
        }
        let a = i;
        while x[i].is_nan() {
            i += 1;
        }
        let b = i - 1;
        // Nearest filled bins: l1 < a..=b < r1, and the next ones out.
        let l1 = a - 1;
        let r1 = b + 1;
        let l2 = (first..l1).rev().find(|&k| !x[k].is_nan());
        let r2 = (r1 + 1..=last).find(|&k| !x[k].is_nan());
        let points: Vec<usize> = match (l2, r2) {
            (Some(l2), Some(r2)) => vec![l2, l1, r1, r2],
            _ => vec![l1, r1],
        };
        for k in a..=b {
            x[k] = lagrange(&points, x, k as f64);
        }
    }
}

/// The polynomial through `(p, x[p])` for `p` in `points`, at `t`.
fn lagrange(points: &[usize], x: &[f64], t: f64) -> f64 {
    points
        .iter()
        .map(|&pj| {
            let w: f64 = points
                .iter()
                .filter(|&&pm| pm != pj)
                .map(|&pm| (t - pm as f64) / (pj as f64 - pm as f64))
                .product();
            w * x[pj]
        })
        .sum()
}

/// `x` convolved with a unit-area Gaussian of `sigma_bins`, edges renormalised.
fn gaussian_smooth(x: &[f64], sigma_bins: f64) -> Vec<f64> {
    if !(sigma_bins > 0.0) {
        return x.to_vec();
    }
    let half = (3.0 * sigma_bins).ceil() as isize;
    let w: Vec<f64> = (-half..=half).map(|k| (-0.5 * (k as f64 / sigma_bins).powi(2)).exp()).collect();
    let n = x.len() as isize;
    (0..n)
        .map(|i| {
            let (mut s, mut ws) = (0.0, 0.0);
            for (j, wk) in (-half..=half).zip(&w) {
                let k = i + j;
                if (0..n).contains(&k) {
                    s += wk * x[k as usize];
                    ws += wk;
                }
            }
            s / ws
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dsp::pulse::{Pulse, PulseShape, Shape};
    use rand::{Rng, SeedableRng};

    #[test]
    fn learns_a_shape_from_shots_at_random_phases() {
        let truth = Pulse { sigma_rise: 1.2, sigma_fall: 3.0 };
        let mut l = TemplateLearner::new(8, -8.0, 16.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..400 {
            let peak = 50.0 + rng.random::<f64>();
            let x: Vec<f64> = (0..120).map(|k| 0.1 + 2.0 * truth.value_and_slope(k as f64 - peak).0).collect();
            l.add(&x, 0.1, peak, 2.0);
        }
        let cfg = l.finish(1e-9).unwrap();
        let learned = cfg.shape(1e-9);
        // Timing uses the half-rise point of the shape it has, so compare the shapes aligned there.
        let shift = learned.half_rise_offset() - truth.half_rise_offset();
        for &t in &[-3.0, -1.0, 0.0, 0.5, 2.0, 6.0] {
            let (a, b) = (learned.value_and_slope(t + shift).0, truth.value_and_slope(t).0);
            assert!((a - b).abs() < 5e-3, "{t}: {a} vs {b}");
        }
        // The half-rise point sits a constant fraction of a sample off the
        // truth's: 0.08 sample from the equivalent-time grid, and 0.065 more
        // from the 0.15-sample smoothing on this fast (1.2-sample rise) pulse.
        // A constant is what calibration removes; what must not be there is
        // more than 0.2 sample of it.
        assert!(shift.abs() < 0.2, "{shift}");
        assert!((learned.fwhm() - Shape::Parametric(truth).fwhm()).abs() < 0.02);
    }

    /// Shots of `truth` at the given sub-sample phases (fractions of a sample), noise-free.
    fn learner_with_phases(truth: &Pulse, oversample: usize, phases: &[f64]) -> TemplateLearner {
        let mut l = TemplateLearner::new(oversample, -8.0, 16.0);
        for &ph in phases {
            let peak = 50.0 + ph;
            let x: Vec<f64> = (0..120).map(|k| 0.1 + 2.0 * truth.value_and_slope(k as f64 - peak).0).collect();
            l.add(&x, 0.1, peak, 2.0);
        }
        l
    }

    #[test]
    fn interpolation_reproduces_a_cubic_across_uneven_gaps() {
        let f = |t: f64| 0.5 - 0.2 * t + 0.03 * t * t - 0.001 * t * t * t;
        let mut x: Vec<f64> = (0..20).map(|i| f(i as f64)).collect();
        let truth = x.clone();
        for i in [3, 4, 5, 9, 12, 13] {
            x[i] = f64::NAN;
        }
        interpolate_gaps(&mut x, 0, 19);
        for (i, (a, b)) in x.iter().zip(&truth).enumerate() {
            assert!((a - b).abs() < 1e-12, "bin {i}: {a} vs {b}");
        }
    }

    #[test]
    fn interpolation_is_linear_next_to_the_filled_span_ends() {
        // Bin 1 has one filled neighbour on the left: the line through bins 0 and 2.
        let mut x = vec![1.0, f64::NAN, 3.0, 7.0, 8.0];
        interpolate_gaps(&mut x, 0, 4);
        assert_eq!(x[1], 2.0);
    }

    #[test]
    fn twenty_shots_that_miss_a_phase_still_learn_the_shape() {
        // 20 shots whose phases avoid one of the 8 grid phases (as 20 random
        // ones do with probability 0.43): every 8th bin is empty and is interpolated.
        let truth = Pulse { sigma_rise: 1.2, sigma_fall: 3.0 };
        let phases: Vec<f64> = (0..20).map(|i| [0.0, 0.125, 0.25, 0.375, 0.625, 0.75, 0.875][i % 7] + 0.01).collect();
        let l = learner_with_phases(&truth, 8, &phases);
        // Empty bins between the first and last filled one (an empty bin at
        // the grid's edge is outside the pulse and stays zero).
        let first = l.counts.iter().position(|&c| c > 0).unwrap();
        let last = l.counts.iter().rposition(|&c| c > 0).unwrap();
        let empty = l.counts[first..=last].iter().filter(|&&c| c == 0).count();
        assert!(empty > 10, "{empty}");
        assert_eq!(l.interpolated_bins(), empty);
        let learned = l.finish(1e-9).unwrap().shape(1e-9);
        let shift = learned.half_rise_offset() - truth.half_rise_offset();
        for &t in &[-3.0, -1.0, 0.0, 0.5, 2.0, 6.0] {
            let (a, b) = (learned.value_and_slope(t + shift).0, truth.value_and_slope(t).0);
            assert!((a - b).abs() < 5e-3, "{t}: {a} vs {b}");
        }
        assert!(shift.abs() < 0.2, "{shift}");
        // What interpolation adds: against the same shots with the missing
        // phase present, the shapes differ by far less than the smoothing's
        // own effect (about 1 % at the top of this 1.2-sample rise).
        let full: Vec<f64> = (0..24).map(|i| i as f64 / 8.0 % 1.0 + 0.01).collect();
        let reference = learner_with_phases(&truth, 8, &full).finish(1e-9).unwrap().shape(1e-9);
        assert_eq!(learner_with_phases(&truth, 8, &full).interpolated_bins(), 0);
        for i in -40..=80 {
            let t = i as f64 / 10.0;
            let (a, b) = (learned.value_and_slope(t).0, reference.value_and_slope(t).0);
            assert!((a - b).abs() < 1e-3, "{t}: {a} vs {b}");
        }
    }

    #[test]
    fn a_gap_wider_than_half_a_sample_is_refused_and_named() {
        let truth = Pulse { sigma_rise: 1.2, sigma_fall: 3.0 };
        // Two phases a quarter sample apart leave runs of 5 empty bins of 8.
        let l = learner_with_phases(&truth, 8, &[0.0, 0.25, 0.0, 0.25]);
        let e = l.finish(1e-9).unwrap_err();
        assert!(matches!(e, TemplateError::Gaps { run: 5, max_run: 4, .. }), "{e:?}");
        assert!(e.to_string().contains("half a sample"), "{e}");
        // One shot on a grid of one bin per sample has no gap at all.
        let one = learner_with_phases(&truth, 1, &[0.3]);
        assert_eq!(one.interpolated_bins(), 0);
        assert!(one.finish(1e-9).is_ok());
    }

    #[test]
    fn sparse_bins_are_interpolated_like_empty_ones() {
        let truth = Pulse { sigma_rise: 1.2, sigma_fall: 3.0 };
        // 40 shots on 4 phases of 4, and one on the fifth phase... of a grid of 4
        // bins per sample: phase 0.5 holds 1 sample per bin against 13 elsewhere.
        let mut phases: Vec<f64> = (0..39).map(|i| [0.0, 0.25, 0.75][i % 3]).collect();
        phases.push(0.5);
        let l = learner_with_phases(&truth, 4, &phases);
        let sparse_phase = l.counts.iter().filter(|&&c| c == 1).count();
        assert!(sparse_phase > 5);
        assert_eq!(l.interpolated_bins(), sparse_phase);
        assert!(l.finish(1e-9).is_ok());
    }

    #[test]
    fn too_few_shots_is_an_error() {
        let l = TemplateLearner::new(8, -8.0, 16.0);
        assert!(matches!(l.finish(1e-9), Err(TemplateError::TooFewShots { .. })));
    }
}
