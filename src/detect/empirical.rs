//! Empirical-quantile thresholds: when the noise is not Gaussian (the source's
//! receiver noise had skewness 0.76), a threshold from a Gaussian fit does not
//! deliver its false-alarm rate. This accumulates the detector's normalised
//! output z = y / σ̂ in the noise gates, frame after frame, and places the
//! threshold at the empirical (1 − p) quantile of z. Where p is too small to
//! be observed, the tail beyond the top 1000 observations is extrapolated as
//! an exponential (peaks over threshold with shape 0: conservative for
//! Gaussian-like tails, honest for heavier ones).

/// Histogram of normalised detector outputs.
#[derive(Debug, Clone)]
pub struct EmpiricalTail {
    counts: Vec<u64>,
    total: u64,
    /// Exceedances kept exactly above the histogram's top bin.
    overflow: Vec<f64>,
}

/// Lowest z the histogram holds; below it values count in bin 0.
const Z_LO: f64 = -20.0;
/// Bin width in z.
const Z_STEP: f64 = 0.005;
/// Histogram bins (z up to +30).
const BINS: usize = 10_000;
/// Observations needed before the empirical threshold is used.
pub const MIN_OBSERVATIONS: u64 = 10_000;
/// Tail observations the exponential extrapolation is fitted on.
const TAIL: u64 = 1_000;

impl Default for EmpiricalTail {
    fn default() -> Self {
        EmpiricalTail { counts: vec![0; BINS], total: 0, overflow: Vec::new() }
    }
}

impl EmpiricalTail {
    /// Adds one normalised output.
    pub fn add(&mut self, z: f64) {
        if !z.is_finite() {
            return;
        }
        let b = ((z - Z_LO) / Z_STEP).floor();
        if b >= BINS as f64 {
            self.overflow.push(z);
        } else {
            self.counts[b.max(0.0) as usize] += 1;
        }
        self.total += 1;
    }

    /// Observations so far.
    pub fn total(&self) -> u64 {
        self.total
    }

    /// Upper edge of the bin where the count from the top reaches `k`, and the
    /// exact count above that edge.
    fn level_with_count_above(&self, k: u64) -> (f64, u64) {
        let mut above = self.overflow.len() as u64;
        for b in (0..BINS).rev() {
            if above + self.counts[b] >= k {
                return (Z_LO + (b + 1) as f64 * Z_STEP, above);
            }
            above += self.counts[b];
        }
        (Z_LO, above)
    }

    /// The z with P(Z > z) = `p`, or `None` before [`MIN_OBSERVATIONS`].
    pub fn quantile(&self, p: f64) -> Option<f64> {
        if self.total < MIN_OBSERVATIONS || !(p > 0.0 && p < 1.0) {
            return None;
        }
        let n = self.total as f64;
        let k = (p * n).ceil() as u64;
        if k >= TAIL {
            return Some(self.level_with_count_above(k).0);
        }
        // Exponential tail above z0, fitted on the top TAIL observations: the
        // mean excess is the scale.
        let (z0, above) = self.level_with_count_above(TAIL);
        let mut sum_excess = 0.0;
        let mut count = 0u64;
        for &z in &self.overflow {
            sum_excess += z - z0;
            count += 1;
        }
        let first = ((z0 - Z_LO) / Z_STEP).round() as usize;
        for b in first..BINS {
            let mid = Z_LO + (b as f64 + 0.5) * Z_STEP;
            sum_excess += self.counts[b] as f64 * (mid - z0);
            count += self.counts[b];
        }
        let _ = above;
        let beta = if count > 0 { sum_excess / count as f64 } else { Z_STEP };
        let p0 = count as f64 / n;
        Some(z0 + beta.max(Z_STEP) * (p0 / p).ln().max(0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Exp, Normal};

    #[test]
    fn observable_quantiles_are_empirical() {
        let mut t = EmpiricalTail::default();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let n = Normal::new(0.0, 1.0).unwrap();
        for _ in 0..1_000_000 {
            t.add(n.sample(&mut rng));
        }
        // Q^-1(1e-3) = 3.0902; 1000 exceedances: sd of the quantile about 0.03.
        let z = t.quantile(1e-3).unwrap();
        assert!((z - 3.0902).abs() < 0.1, "{z}");
    }

    #[test]
    fn exponential_tails_are_extrapolated() {
        let mut t = EmpiricalTail::default();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let e = Exp::new(1.0).unwrap();
        for _ in 0..200_000 {
            t.add(e.sample(&mut rng));
        }
        // P(E > z) = exp(-z): z = ln(1e8) = 18.42; the scale's relative
        // error is 1/sqrt(1000) = 3 %, so the level within 10 %.
        let z = t.quantile(1e-8).unwrap();
        assert!((z / 18.42 - 1.0).abs() < 0.1, "{z}");
        assert!(EmpiricalTail::default().quantile(1e-3).is_none());
    }
}
