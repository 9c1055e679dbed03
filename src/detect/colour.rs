//! Noise colour: the autocorrelation of the noise gates, pooled over frames,
//! and what it does to the detector output.
//!
//! A receiver's noise is rarely white: the TIA and the digitiser band-limit it,
//! so neighbouring samples are correlated over several nanoseconds. The
//! matched filter then sums correlated noise and its output sigma is not the
//! sample sigma: for unit-energy taps h and noise autocorrelation ρ(k),
//!
//! ```text
//! Var(y) / σ² = g = Σ_k ρ(k) A_h(k),   A_h(k) = Σ_i h_i h_{i+k}
//! ```
//!
//! (1 for white noise, several for noise band-limited like the pulse). The
//! output's own correlation, which sets how many cells of a range gate are
//! effectively independent, widens in the same way. A threshold set on the
//! white-noise assumption is then too low by √g and the false-alarm rate is
//! orders of magnitude above design. The autocorrelation is pooled over frames
//! (the colour is a property of the receiver, slow to change) so that a single
//! short gate does not make the threshold jitter.

use crate::math::autocov::{code_lag_product_sums, lag_product_sums, lag_sums_short};

/// Pooled autocovariance of noise-gate samples, lags 0..=max_lag.
#[derive(Debug, Clone)]
pub struct NoiseColour {
    /// Σ (x_i − m)(x_{i+k} − m) per lag, over every segment seen.
    sums: Vec<f64>,
    /// Number of products per lag.
    counts: Vec<f64>,
    /// Σ over segments of (products at this lag) / (samples the frame's mean
    /// was taken over): how much of the mean's variance each lag's sum lost
    /// to centring on an estimated mean.
    centring: Vec<f64>,
    /// Frames offered.
    frames: u64,
    /// Frames whose samples were added (halved with the sums).
    added: f64,
    /// Changes whenever the sums do (callers cache what they derive).
    version: u64,
    /// Scratch: one segment's lag sums, and its samples less the mean.
    partial: Vec<f64>,
    centred: Vec<f64>,
    /// Scratch: a segment's codes less the integer nearest the mean.
    codes: Vec<i16>,
}

/// Pooled samples beyond which old sums are halved, so that the estimate
/// follows a receiver whose colour drifts (about 2 000 frames of 2 000 gate
/// samples).
const POOL_CAP: f64 = 4.0e6;
/// Pooled samples beyond which only every 8th frame is added (the estimate
/// has converged; saves the per-frame cost).
const POOL_CONVERGED: f64 = 1.0e6;

impl NoiseColour {
    /// Estimator for lags up to `max_lag` samples.
    pub fn new(max_lag: usize) -> NoiseColour {
        NoiseColour {
            sums: vec![0.0; max_lag + 1],
            counts: vec![0.0; max_lag + 1],
            centring: vec![0.0; max_lag + 1],
            frames: 0,
            added: 0.0,
            version: 0,
            partial: vec![0.0; max_lag + 1],
            centred: Vec::new(),
            codes: Vec::new(),
        }
    }

    /// A number that changes whenever the estimate does.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// Largest lag estimated.
    pub fn max_lag(&self) -> usize {
        self.sums.len() - 1
    }

    /// Adds one frame's noise segments (each contiguous; no products are taken
    /// across segments), centred on `mean`, the frame's own gate mean.
    pub fn add_frame(&mut self, segments: &[&[f64]], mean: f64) {
        let total = segments.iter().map(|s| s.len()).sum::<usize>() as f64;
        self.add_frame_about(segments, mean, total);
    }

    /// As [`add_frame`](NoiseColour::add_frame) for a `mean` estimated from
    /// `mean_samples` samples (a mean pooled over frames rests on more samples
    /// than this frame's gates: centring on it removes less of each product,
    /// σ²τ/mean_samples).
    pub fn add_frame_about(&mut self, segments: &[&[f64]], mean: f64, mean_samples: f64) {
        let mut centred = std::mem::take(&mut self.centred);
        self.pool(segments.iter().map(|seg| seg.len()), mean_samples, |i, out| {
            lag_product_sums(segments[i], mean, out, &mut centred);
        });
        self.centred = centred;
    }

    /// As [`add_frame_about`](NoiseColour::add_frame_about) for segments of
    /// integer codes that decode as `code·g + o` volts: the lag products
    /// are summed exactly in integers ([`code_lag_product_sums`]), within a
    /// few ulp of the lag-0 sum of the exact sums, where the f64 kernel
    /// rounds every product. A segment whose codes lie more than 2^12 from the mean (in
    /// codes) is summed in f64 from `volts` (the same samples in volts).
    pub fn add_frame_codes_about(&mut self, codes: &[&[i16]], volts: &[&[f64]], g: f64, o: f64, mean: f64, mean_samples: f64) {
        let (mut centred, mut d) = (std::mem::take(&mut self.centred), std::mem::take(&mut self.codes));
        let centre = (mean - o) / g;
        let g2 = g * g;
        self.pool(codes.iter().map(|seg| seg.len()), mean_samples, |i, out| {
            if g.is_finite() && g != 0.0 && code_lag_product_sums(codes[i], centre, out, &mut d) {
                out.iter_mut().for_each(|v| *v *= g2);
            } else {
                lag_product_sums(volts[i], mean, out, &mut centred);
            }
        });
        (self.centred, self.codes) = (centred, d);
    }

    /// Adds one frame: `partial_of(i, out)` writes the lag sums of segment
    /// `i` (its length the i-th of `lens`) into `out`, which are pooled.
    fn pool(&mut self, lens: impl Iterator<Item = usize>, mean_samples: f64, mut partial_of: impl FnMut(usize, &mut [f64])) {
        self.frames += 1;
        if self.counts[0] > POOL_CONVERGED && !self.frames.is_multiple_of(8) {
            return;
        }
        if self.counts[0] > POOL_CAP {
            self.sums.iter_mut().for_each(|s| *s *= 0.5);
            self.counts.iter_mut().for_each(|c| *c *= 0.5);
            self.centring.iter_mut().for_each(|c| *c *= 0.5);
            self.added *= 0.5;
        }
        self.added += 1.0;
        self.version += 1;
        let lags = self.sums.len();
        let total = mean_samples.max(1.0);
        let mut partial = std::mem::take(&mut self.partial);
        for (i, n) in lens.enumerate() {
            // Per-frame partial sums first: the pooled sum then adds values
            // of similar size, frame after frame.
            partial_of(i, &mut partial);
            for (k, p) in partial.iter().enumerate().take(lags.min(n)) {
                self.sums[k] += p;
                self.counts[k] += (n - k) as f64;
                self.centring[k] += (n - k) as f64 / total;
            }
        }
        self.partial = partial;
    }

    /// Normalised autocorrelation ρ(0..=K) (ρ(0) = 1; K is `max_lag` or a
    /// quarter of a frame's gate samples, whichever is less), or `None` before
    /// any noise sample has been seen or when the pooled variance is zero.
    pub fn rho(&self) -> Option<Vec<f64>> {
        let mut rho = Vec::new();
        self.rho_into(&mut Vec::new(), &mut rho).then_some(rho)
    }

    /// [`rho`](NoiseColour::rho) written into `out` (cleared first; `g` is
    /// scratch), so a per-frame refresh does not allocate; false where `rho`
    /// gives `None`.
    pub fn rho_into(&self, g: &mut Vec<f64>, out: &mut Vec<f64>) -> bool {
        out.clear();
        if self.counts[0] < 2.0 || !(self.sums[0] > 0.0) {
            return false;
        }
        // Centring each frame on its own gate mean takes the mean's variance,
        // σ²τ/n, off every product's expectation: for white noise on a
        // 200-sample gate that is −1/200 at every lag, which summed over a
        // long template's lags would shrink the output sigma by several per
        // cent. Added back with τ from the corrected estimate (a few
        // fixed-point steps; τ changes little after the first).
        //
        // With v = σ²τ the corrected lag sums are g_k = (S_k + v W_k)/C_k and
        // v = g_0 + 2 Σ g_k is linear in v: v = A / (1 − B). B grows with the
        // lags used per gate sample; lags are therefore limited to a quarter
        // of a frame's gate (B ≈ 1/2), and the correlation is taken as zero
        // beyond (noise correlated over more than a quarter of the gate
        // cannot be told from a wandering mean with such a gate).
        let per_frame = self.counts[0] / self.added.max(1.0);
        let lags = (self.sums.len() - 1).min((per_frame / 4.0).floor() as usize);
        let (mut a, mut b) = (0.0, 0.0);
        for k in 0..=lags {
            if self.counts[k] > 0.0 {
                let c = if k == 0 { 1.0 } else { 2.0 };
                a += c * self.sums[k] / self.counts[k];
                b += c * self.centring[k] / self.counts[k];
            }
        }
        let v = if b < 0.9 { (a / (1.0 - b)).max(0.0) } else { 0.0 };
        g.clear();
        g.resize(lags + 1, 0.0);
        for (k, gk) in g.iter_mut().enumerate() {
            *gk = if self.counts[k] > 0.0 { (self.sums[k] + v * self.centring[k]) / self.counts[k] } else { 0.0 };
        }
        let c0 = g[0];
        if !(c0 > 0.0) {
            return false;
        }
        out.extend(g.iter().map(|gk| (gk / c0).clamp(-1.0, 1.0)));
        true
    }

    /// Σ_{k=1}^{lags} 1/(products pooled at lag k): the sampling variance of
    /// ρ̂(k) is about Σρ²/(products), so a sum of squared estimates is biased
    /// up by 2 Σρ² times this (large on the first frames).
    pub fn inverse_count_sum(&self, lags: usize) -> (f64, f64) {
        let mut s1 = 0.0;
        let mut s2 = 0.0;
        for c in self.counts.iter().take(lags + 1).skip(1) {
            if *c > 0.0 {
                s1 += 1.0 / c;
                s2 += 1.0 / (c * c);
            }
        }
        (s1, s2)
    }

    /// Integrated correlation time in samples, τ = 1 + 2 Σ_{k≥1} ρ(k): the
    /// variance of a mean of n samples is σ² τ / n. At least 1/n-small; 1 for
    /// white noise or before any data.
    pub fn correlation_time(&self) -> f64 {
        match self.rho() {
            Some(r) => (1.0 + 2.0 * r[1..].iter().sum::<f64>()).max(0.05),
            None => 1.0,
        }
    }

    /// The detector output's variance gain and lag-1 correlation for the
    /// unit-energy `taps` (see [`output_gain`]); white-noise values before
    /// any data.
    pub fn output(&self, taps: &[f64]) -> OutputColour {
        match self.rho() {
            Some(r) => output_gain(taps, &r),
            None => output_gain(taps, &[1.0]),
        }
    }
}

/// How noise colour shapes the detector output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputColour {
    /// Var(output) / σ² for unit-energy taps (1 for white noise).
    pub variance_gain: f64,
    /// Lag-1 correlation of the output.
    pub rho1: f64,
}

/// Output autocorrelation of the FIR `taps` driven by noise of normalised
/// autocorrelation `rho` (lags 0.., zero beyond): r(m) = Σ_k ρ(k) A_h(m − k).
/// Returns r(0) and r(1)/r(0). A non-positive r(0) (an autocorrelation
/// estimate that is not positive definite) falls back to white noise.
pub fn output_gain(taps: &[f64], rho: &[f64]) -> OutputColour {
    output_gain_with(taps, rho, &mut Vec::new())
}

/// [`output_gain`] with the taps' autocorrelation written to `acf` (scratch
/// kept by the caller, so a per-frame call does not allocate).
pub fn output_gain_with(taps: &[f64], rho: &[f64], acf: &mut Vec<f64>) -> OutputColour {
    taps_acf(taps, acf);
    output_gain_from_acf(taps, rho, acf)
}

/// The taps' autocorrelation A_h(j), j = 0..taps.len(), into `acf` (cleared
/// first): what [`output_gain_from_acf`] reads, kept by a caller whose taps
/// do not change from frame to frame.
pub fn taps_acf(taps: &[f64], acf: &mut Vec<f64>) {
    // Σ_i taps_i·taps_{i+j}, each lag the serial sum in index order,
    // several lags side by side (see `lag_sums_short`).
    acf.clear();
    acf.resize(taps.len(), 0.0);
    lag_sums_short(taps, acf);
}

/// [`output_gain`] from the taps' autocorrelation `acf` ([`taps_acf`] of `taps`).
pub fn output_gain_from_acf(taps: &[f64], rho: &[f64], acf: &[f64]) -> OutputColour {
    let len = taps.len() as isize;
    let a = |j: isize| -> f64 { acf.get(j.unsigned_abs()).copied().unwrap_or(0.0) };
    let kmax = (rho.len() as isize - 1).min(len);
    // r(0) and r(1) side by side: two chains of adds, each the serial sum
    // over k in order (as `Iterator::sum`, from −0.0), in one loop.
    let (mut r0, mut r1) = (-0.0f64, -0.0f64);
    for k in -kmax..=kmax {
        let rk = rho[k.unsigned_abs()];
        r0 += rk * a(-k);
        r1 += rk * a(1 - k);
    }
    let white = || {
        let e: f64 = taps.iter().map(|t| t * t).sum();
        OutputColour {
            variance_gain: e,
            rho1: if e > 0.0 { a(1) / e } else { 0.0 },
        }
    };
    if !(r0 > 0.0) || !r0.is_finite() {
        return white();
    }
    OutputColour {
        variance_gain: r0,
        rho1: (r1 / r0).clamp(-1.0, 1.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn unit(taps: &[f64]) -> Vec<f64> {
        let e = taps.iter().map(|t| t * t).sum::<f64>().sqrt();
        taps.iter().map(|t| t / e).collect()
    }

    #[test]
    fn output_gain_is_the_serial_sums_bit_for_bit() {
        // r(m) = Σ_k ρ(|k|) A(m − k), k from −kmax to kmax, one serial sum each.
        for (len, lags) in [(1usize, 1usize), (5, 3), (64, 65), (64, 20), (9, 40)] {
            let h = unit(&(0..len).map(|i| 1.0 + ((i * 7) % 5) as f64 * 0.3).collect::<Vec<_>>());
            let rho: Vec<f64> = (0..lags).map(|k| 0.93f64.powi(k as i32) * if k % 3 == 2 { -0.5 } else { 1.0 }).collect();
            let mut acf = Vec::new();
            taps_acf(&h, &mut acf);
            let a = |j: isize| acf.get(j.unsigned_abs()).copied().unwrap_or(0.0);
            let kmax = (rho.len() as isize - 1).min(len as isize);
            let r = |m: isize| (-kmax..=kmax).map(|k| rho[k.unsigned_abs()] * a(m - k)).sum::<f64>();
            let c = output_gain_from_acf(&h, &rho, &acf);
            assert_eq!(c.variance_gain.to_bits(), r(0).to_bits(), "len {len} lags {lags}");
            assert_eq!(c.rho1.to_bits(), (r(1) / r(0)).clamp(-1.0, 1.0).to_bits(), "len {len} lags {lags}");
        }
    }

    #[test]
    fn codes_pool_as_their_volts_do() {
        // AR(1) noise digitised to 12-bit codes, two runs per frame, pooled
        // past convergence: the integer lag sums give the f64 pool's ρ.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        let (g, o) = (1.0 / 4096.0, -0.013);
        let (mut by_volts, mut by_codes) = (NoiseColour::new(64), NoiseColour::new(64));
        let mut y = 0.0f64;
        for frame in 0..900 {
            let codes: Vec<i16> = (0..1400)
                .map(|_| {
                    let e: f64 = StandardNormal.sample(&mut rng);
                    y = 0.6 * y + 9.0 * e;
                    (y + 31.0).round().clamp(-2048.0, 2047.0) as i16
                })
                .collect();
            let volts: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
            let mean = volts.iter().sum::<f64>() / volts.len() as f64 + 1e-4 * (frame % 7) as f64;
            let (va, vb) = (&volts[..180], &volts[400..]);
            let (ca, cb) = (&codes[..180], &codes[400..]);
            by_volts.add_frame_about(&[va, vb], mean, 5000.0);
            by_codes.add_frame_codes_about(&[ca, cb], &[va, vb], g, o, mean, 5000.0);
        }
        let (rv, rc) = (by_volts.rho().unwrap(), by_codes.rho().unwrap());
        assert_eq!(rv.len(), rc.len());
        for (k, (a, b)) in rv.iter().zip(&rc).enumerate() {
            assert!((a - b).abs() < 1e-12, "lag {k}: {a} against {b}");
        }
        assert!((rv[1] - 0.6).abs() < 0.01, "{}", rv[1]);
        // Codes too far from the mean for the integer sums: the f64 sums of the volts.
        let mut far = NoiseColour::new(4);
        let mut plain = NoiseColour::new(4);
        let codes = [30000i16, -30000, 29000, -29500, 30000, -30000];
        let volts: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
        far.add_frame_codes_about(&[&codes], &[&volts], g, o, 0.0, 6.0);
        plain.add_frame_about(&[&volts], 0.0, 6.0);
        assert_eq!(far.rho(), plain.rho());
    }

    #[test]
    fn white_noise_leaves_the_output_sigma_alone() {
        let h = unit(&[0.2, 0.6, 1.0, 0.7, 0.3]);
        let c = output_gain(&h, &[1.0]);
        assert!((c.variance_gain - 1.0).abs() < 1e-15);
        let a1: f64 = h.windows(2).map(|w| w[0] * w[1]).sum();
        assert!((c.rho1 - a1).abs() < 1e-15);
    }

    #[test]
    fn ar1_noise_gain_matches_the_closed_form() {
        // AR(1), ρ(k) = φ^k: a 2-tap box [1,1]/√2 has Var = (1 + ρ(1)), exactly.
        let phi: f64 = 0.8;
        let rho: Vec<f64> = (0..10).map(|k| phi.powi(k)).collect();
        let h = unit(&[1.0, 1.0]);
        let c = output_gain(&h, &rho);
        assert!((c.variance_gain - (1.0 + phi)).abs() < 1e-14, "{c:?}");
        // Lag-1 output covariance: (ρ(0)+2ρ(1)+ρ(2))/2 over (1+ρ(1)).
        let want = (1.0 + 2.0 * phi + phi * phi) / 2.0 / (1.0 + phi);
        assert!((c.rho1 - want).abs() < 1e-14);
    }

    #[test]
    fn pooled_estimate_recovers_an_ar1_process() {
        // 200 frames x 1000 samples of AR(1) with φ = 0.7: ρ̂(k) has standard
        // error about √((1+φ²)/(1−φ²)/n) ≈ 0.005 at n = 2e5; 0.03 is > 5 of them.
        let phi = 0.7;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut est = NoiseColour::new(8);
        let mut x = 0.0;
        for _ in 0..200 {
            let seg: Vec<f64> = (0..1000)
                .map(|_| {
                    let e: f64 = StandardNormal.sample(&mut rng);
                    x = phi * x + e;
                    x
                })
                .collect();
            est.add_frame(&[seg.as_slice()], 0.0);
        }
        let r = est.rho().expect("data");
        for (k, rk) in r.iter().enumerate() {
            assert!((rk - phi.powi(k as i32)).abs() < 0.03, "lag {k}: {rk}");
        }
        let tau_true = (1.0 + phi) / (1.0 - phi);
        // Truncated at lag 8 the true τ is 1 + 2 Σ_{1..8} φ^k.
        let tau_trunc = 1.0 + 2.0 * (1..=8).map(|k| phi.powi(k)).sum::<f64>();
        assert!((est.correlation_time() - tau_trunc).abs() < 0.3, "{} vs {tau_trunc} ({tau_true})", est.correlation_time());
    }

    #[test]
    fn centring_on_each_frame_mean_does_not_bias_white_noise() {
        // 5 000 frames of 200 white samples, each centred on its own mean:
        // uncorrected, every lag would sit at -1/200 = -0.005. Corrected, the
        // sum over 40 lags (what a 40-tap template's gain sees) is within its
        // Monte-Carlo error (~40 x 1/sqrt(1e6) = 0.04 at most, 3 sigma) of 0.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut est = NoiseColour::new(40);
        for _ in 0..5000 {
            let seg: Vec<f64> = (0..200).map(|_| StandardNormal.sample(&mut rng)).collect();
            let mean = seg.iter().sum::<f64>() / 200.0;
            est.add_frame(&[seg.as_slice()], mean);
        }
        let r = est.rho().unwrap();
        let tail: f64 = r[1..].iter().sum();
        assert!(tail.abs() < 0.04, "sum of rho(1..40) = {tail}");
        assert!((est.correlation_time() - 1.0).abs() < 0.08, "{}", est.correlation_time());
    }

    #[test]
    fn a_pooled_mean_is_not_corrected_as_if_it_were_the_frames_own() {
        // AR(1), φ = 0.9 (τ = 19), 400-sample gates centred on a mean pooled
        // over many frames (here the true mean, 0): the correction for
        // centring on the frame's own mean must not apply. 2 000 frames
        // (800 000 samples; the estimate's sd is about 0.5 of τ = 19 here,
        // so ±15 % is over 5 sd), while the per-frame correction would give
        // τ ≈ 1.5 × 19.
        let phi: f64 = 0.9;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut pooled = NoiseColour::new(100);
        let mut own = NoiseColour::new(100);
        let innovation = (1.0 - phi * phi).sqrt();
        let mut x: f64 = StandardNormal.sample(&mut rng);
        for _ in 0..2000 {
            let seg: Vec<f64> = (0..400)
                .map(|_| {
                    let e: f64 = StandardNormal.sample(&mut rng);
                    x = phi * x + innovation * e;
                    x
                })
                .collect();
            pooled.add_frame_about(&[seg.as_slice()], 0.0, 1e9);
            own.add_frame(&[seg.as_slice()], 0.0);
        }
        let truth = (1.0 + phi) / (1.0 - phi);
        let tau = pooled.correlation_time();
        assert!((tau / truth - 1.0).abs() < 0.15, "pooled mean: tau {tau} vs {truth}");
        assert!(own.correlation_time() > 1.3 * truth, "the frame-mean correction on a pooled mean inflates tau");
    }

    #[test]
    fn short_split_gate_with_long_lags_is_still_white() {
        // A 218-sample gate in two pieces (190 + 28) sharing one mean, lags
        // asked up to 100: the estimate uses a quarter of the gate (54 lags)
        // and τ is 1 within its Monte-Carlo error (3 000 frames: ~0.02).
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut est = NoiseColour::new(100);
        for _ in 0..3000 {
            let seg: Vec<f64> = (0..218).map(|_| StandardNormal.sample(&mut rng)).collect();
            let mean = seg.iter().sum::<f64>() / 218.0;
            est.add_frame(&[&seg[..190], &seg[190..]], mean);
        }
        assert_eq!(est.rho().unwrap().len(), 55);
        assert!((est.correlation_time() - 1.0).abs() < 0.06, "{}", est.correlation_time());
    }

    #[test]
    fn no_data_and_zero_variance_are_white() {
        let est = NoiseColour::new(4);
        assert!(est.rho().is_none());
        assert_eq!(est.correlation_time(), 1.0);
        let mut z = NoiseColour::new(4);
        z.add_frame(&[[0.5; 100].as_slice()], 0.5);
        assert!(z.rho().is_none());
        let h = unit(&[1.0, 2.0, 1.0]);
        assert!((z.output(&h).variance_gain - 1.0).abs() < 1e-15);
    }
}
