//! Noise: coloured (chain-filtered) Gaussian or skewed noise with a
//! signal-dependent shot-noise envelope, the structured mains burst, and the
//! short interference events.
//!
//! All random noise enters as a white current at the receiver input, held over
//! each digitiser sample, and passes through the exact discrete equivalent of
//! the channel's linear chain (see `photodetector`). A white current of one-sided
//! density S (A²/Hz) becomes, over a hold of `dt`, samples of variance
//! `S / (2 dt)` (its power up to the Nyquist frequency); for a chain whose
//! bandwidth is well below Nyquist this reproduces the continuous-time output
//! variance `S · ENBW · R²`. The filter starts each frame from a state drawn
//! from its stationary distribution, so the noise is stationary from sample 0.

// Dense small-matrix kernels index several arrays in lockstep; index loops
// read closer to the maths than zipped iterators here.
#![allow(clippy::needless_range_loop)]

use super::photodetector::Discrete;
use rand::Rng;
use rand_distr::StandardNormal;

/// Quadratic skewing of a standard normal: `(z + c (z² − 1)) / sqrt(1 + 2c²)`
/// has mean 0, variance 1 and skewness `(6c + 8c³) / (1 + 2c²)^{3/2}`.
pub fn skew_of_c(c: f64) -> f64 {
    (6.0 * c + 8.0 * c * c * c) / (1.0 + 2.0 * c * c).powf(1.5)
}

/// The `c` giving skewness `g`, by bisection (the skewness is monotone in c
/// and tends to 2√2 as c grows); `None` if |g| is out of reach.
pub fn c_for_skew(g: f64) -> Option<f64> {
    let max = 8.0 / 2f64.powf(1.5);
    if g.is_nan() || g.abs() >= max * 0.999 {
        return None;
    }
    let (mut lo, mut hi) = (0.0f64, 100.0f64);
    let t = g.abs();
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if skew_of_c(mid) < t {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(0.5 * (lo + hi) * g.signum())
}

/// A coloured-noise generator for one channel.
#[derive(Debug, Clone)]
pub struct ColouredNoise {
    /// Discrete chain at the sample interval (unit DC gain, input in A·Ω = V).
    filter: Discrete,
    /// Cholesky factor of the stationary state covariance (unit input variance).
    chol: Vec<f64>,
    /// Std of the stationary part of the innovation, per sample (V-equivalent at the input).
    stationary_std: f64,
    /// Quadratic skew coefficient of the innovations (0: Gaussian).
    skew_c: f64,
    /// 1/sqrt(1 + 2c²): keeps the skewed innovation at unit variance.
    skew_norm: f64,
}

impl ColouredNoise {
    /// A generator whose stationary output at the digitiser input has std
    /// `sigma_v`, through `filter`. With `skew_c ≠ 0` the innovations are
    /// skewed (see [`skew_of_c`]).
    pub fn new(filter: Discrete, sigma_v: f64, skew_c: f64) -> ColouredNoise {
        let var1 = filter.stationary_output_variance();
        let chol = filter.stationary_cholesky();
        let stationary_std = if var1 > 0.0 {
            sigma_v / var1.sqrt()
        } else {
            0.0
        };
        ColouredNoise {
            filter,
            chol,
            stationary_std,
            skew_c,
            skew_norm: 1.0 / (1.0 + 2.0 * skew_c * skew_c).sqrt(),
        }
    }

    /// Output std per unit innovation std (the chain's white-noise gain per sample).
    pub fn gain_per_unit_innovation(&self) -> f64 {
        self.filter.stationary_output_variance().sqrt()
    }

    /// Std of the stationary innovation.
    pub fn stationary_std(&self) -> f64 {
        self.stationary_std
    }

    /// Skewness of the filtered stationary output for innovations of unit
    /// skewness: `Σh³ / (Σh²)^{3/2}` over the impulse response.
    pub fn skew_transfer(filter: &Discrete) -> f64 {
        // Long enough for the fast modes; the slow AC-coupling tail contributes
        // little to either sum (its amplitude is dt/τ per sample).
        let h = filter.impulse_response(1 << 16);
        let s2: f64 = h.iter().map(|x| x * x).sum();
        let s3: f64 = h.iter().map(|x| x * x * x).sum();
        if s2 > 0.0 { s3 / s2.powf(1.5) } else { 0.0 }
    }

    /// Adds noise to `out`: `envelope_var[i]` is the extra (non-stationary,
    /// shot-noise) innovation variance at sample i (V² at the input), indexed
    /// from `envelope_shift` (clamped to the array).
    pub fn add_to<R: Rng>(
        &self,
        rng: &mut R,
        out: &mut [f64],
        envelope_var: Option<&[f64]>,
        envelope_shift: isize,
    ) {
        // Monomorphised per state count: fixed-size arrays keep the state in
        // registers (the per-sample path is the simulator's hot loop).
        match self.filter.n {
            0 => self.run::<0, R>(rng, out, envelope_var, envelope_shift),
            1 => self.run::<1, R>(rng, out, envelope_var, envelope_shift),
            2 => self.run::<2, R>(rng, out, envelope_var, envelope_shift),
            3 => self.run::<3, R>(rng, out, envelope_var, envelope_shift),
            4 => self.run::<4, R>(rng, out, envelope_var, envelope_shift),
            5 => self.run::<5, R>(rng, out, envelope_var, envelope_shift),
            6 => self.run::<6, R>(rng, out, envelope_var, envelope_shift),
            7 => self.run::<7, R>(rng, out, envelope_var, envelope_shift),
            8 => self.run::<8, R>(rng, out, envelope_var, envelope_shift),
            _ => self.run_dyn(rng, out, envelope_var, envelope_shift),
        }
    }

    /// Innovation for sample `k`: unit normal, optionally skewed, scaled by the local std.
    #[inline(always)]
    fn innovation<R: Rng>(&self, rng: &mut R, k: usize, env: Option<&[f64]>, shift: isize) -> f64 {
        let mut z: f64 = rng.sample(StandardNormal);
        if self.skew_c != 0.0 {
            z = (z + self.skew_c * (z * z - 1.0)) * self.skew_norm;
        }
        match env {
            Some(e) => {
                let idx = (k as isize + shift).clamp(0, e.len() as isize - 1) as usize;
                z * (self.stationary_std * self.stationary_std + e[idx]).sqrt()
            }
            None => z * self.stationary_std,
        }
    }

    fn run<const N: usize, R: Rng>(
        &self,
        rng: &mut R,
        out: &mut [f64],
        env: Option<&[f64]>,
        shift: isize,
    ) {
        let mut phi = [[0.0f64; N]; N];
        let mut gamma = [0.0f64; N];
        let mut c = [0.0f64; N];
        for i in 0..N {
            for j in 0..N {
                phi[i][j] = self.filter.phi[i * N + j];
            }
            gamma[i] = self.filter.gamma[i];
            c[i] = self.filter.c[i];
        }
        let d = self.filter.d;
        // Stationary initial state: x = L z σ.
        let mut z = [0.0f64; N];
        for zi in z.iter_mut() {
            *zi = rng.sample::<f64, _>(StandardNormal);
        }
        let mut x = [0.0f64; N];
        for i in 0..N {
            let mut v = 0.0;
            for j in 0..=i {
                v += self.chol[i * N + j] * z[j];
            }
            x[i] = v * self.stationary_std;
        }
        for (k, o) in out.iter_mut().enumerate() {
            let u = self.innovation(rng, k, env, shift);
            let mut y = d * u;
            for i in 0..N {
                y += c[i] * x[i];
            }
            let mut nx = [0.0f64; N];
            for i in 0..N {
                let mut s = gamma[i] * u;
                for j in 0..N {
                    s += phi[i][j] * x[j];
                }
                nx[i] = s;
            }
            x = nx;
            *o += y;
        }
    }

    fn run_dyn<R: Rng>(&self, rng: &mut R, out: &mut [f64], env: Option<&[f64]>, shift: isize) {
        let n = self.filter.n;
        let mut x = vec![0.0f64; n];
        let mut s = vec![0.0f64; n];
        let z: Vec<f64> = (0..n)
            .map(|_| rng.sample::<f64, _>(StandardNormal))
            .collect();
        for i in 0..n {
            let v: f64 = (0..=i).map(|j| self.chol[i * n + j] * z[j]).sum();
            x[i] = v * self.stationary_std;
        }
        for (k, o) in out.iter_mut().enumerate() {
            let u = self.innovation(rng, k, env, shift);
            *o += self.filter.step(&mut x, u, &mut s);
        }
    }
}

/// The mains-rate interference burst: a fixed shape (sum of modes under a
/// Hann envelope) recurring at `rate_hz` with a phase fixed per seed.
#[derive(Debug, Clone)]
pub struct Burst {
    /// Peak amplitude, V.
    amplitude_v: f64,
    /// Recurrence period, s.
    period_s: f64,
    /// Duration, s.
    duration_s: f64,
    /// Mode angular frequencies, rad/s, with fixed phases (a fixed shape).
    modes: Vec<(f64, f64)>,
    /// Normalisation so the burst's peak |value| is `amplitude_v`.
    norm: f64,
    /// Each burst starts up to this much after its nominal mains instant, s.
    wander_s: f64,
}

impl Burst {
    /// Builds the burst shape.
    pub fn new(
        amplitude_v: f64,
        rate_hz: f64,
        duration_s: f64,
        frequencies_hz: &[f64],
        wander_s: f64,
    ) -> Burst {
        let modes: Vec<(f64, f64)> = frequencies_hz
            .iter()
            .enumerate()
            // Fixed, deterministic phases: the shape is the same every time.
            .map(|(k, f)| (2.0 * std::f64::consts::PI * f, 0.7 + 1.9 * k as f64))
            .collect();
        let mut b = Burst {
            amplitude_v,
            period_s: 1.0 / rate_hz,
            duration_s,
            modes,
            norm: 1.0,
            wander_s,
        };
        let n = 20_000;
        let peak = (0..=n)
            .map(|i| b.shape(duration_s * i as f64 / n as f64).abs())
            .fold(0.0, f64::max);
        b.norm = if peak > 0.0 { 1.0 / peak } else { 0.0 };
        b
    }

    /// Unscaled shape at time `t` since the burst began.
    fn shape(&self, t: f64) -> f64 {
        if !(0.0..=self.duration_s).contains(&t) {
            return 0.0;
        }
        let env = (std::f64::consts::PI * t / self.duration_s).sin().powi(2);
        env * self
            .modes
            .iter()
            .map(|(w, ph)| (w * t + ph).sin())
            .sum::<f64>()
    }

    /// Burst value at time `t` since the burst began, V.
    pub fn value_v(&self, t: f64) -> f64 {
        self.amplitude_v * self.norm * self.shape(t)
    }

    /// Start time of burst `k` (absolute seconds) for `seed`: the nominal
    /// mains instant `phase + k/rate` plus a wander uniform in `[0, wander_s)`
    /// drawn from a hash of `(seed, k)` (the mains phase drifts against the
    /// laser clock, so bursts land at random positions relative to the shots).
    pub fn start_of(&self, seed: u64, phase_s: f64, k: i64) -> f64 {
        let u = (splitmix64(seed ^ (k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)) >> 11) as f64
            / (1u64 << 53) as f64;
        phase_s + k as f64 * self.period_s + u * self.wander_s
    }

    /// Start time of the burst overlapping `[t0, t1]` (absolute seconds), if any.
    pub fn overlapping(&self, seed: u64, phase_s: f64, t0: f64, t1: f64) -> Option<f64> {
        let k0 = ((t0 - self.duration_s - self.wander_s - phase_s) / self.period_s).floor() as i64;
        let k1 = ((t1 - phase_s) / self.period_s).ceil() as i64;
        (k0..=k1)
            .map(|k| self.start_of(seed, phase_s, k))
            .find(|&start| start <= t1 && start + self.duration_s >= t0)
    }
}

/// Envelope cut of an interference event, in decay times after its onset
/// (the envelope `u e^{1−u}` is 3.6e-4 of its peak there).
pub const EVENT_CUT_DECAYS: f64 = 12.0;

/// A short interference event of fixed shape: `g(x) Σ_k sin(2π f_k x)` with
/// `g(x) = (x/τ) exp(1 − x/τ)`, `x` the time since the onset, zero before the
/// onset and past `EVENT_CUT_DECAYS · τ`, scaled so that its largest positive
/// excursion is `peak_v`. The envelope starts from zero with zero value (no
/// step) and its spectrum around each mode falls as `1/(1 + (2π Δf τ)²)`, so
/// the event's energy stays near its modes.
#[derive(Debug, Clone)]
pub struct InterferenceEvent {
    /// Mode angular frequencies, rad/s.
    omegas: Vec<f64>,
    /// Envelope time constant τ, s.
    decay_s: f64,
    /// Scale from the unit shape to volts.
    scale: f64,
    /// Time of the largest positive excursion after the onset, s.
    peak_after_onset_s: f64,
    /// Largest positive excursion, V.
    peak_v: f64,
    /// Probability that a frame holds an event.
    probability: f64,
}

impl InterferenceEvent {
    /// The event shape with modes `frequencies_hz`, envelope time constant
    /// `decay_s` and largest positive excursion `peak_v`; each frame holds one
    /// with `probability`.
    pub fn new(peak_v: f64, decay_s: f64, frequencies_hz: &[f64], probability: f64) -> InterferenceEvent {
        let mut e = InterferenceEvent {
            omegas: frequencies_hz.iter().map(|f| 2.0 * std::f64::consts::PI * f).collect(),
            decay_s,
            scale: 1.0,
            peak_after_onset_s: decay_s,
            peak_v,
            probability,
        };
        // The largest positive excursion, on a grid fine against the fastest
        // mode and the envelope, then refined by golden-section search.
        let f_max = frequencies_hz.iter().fold(0.0f64, |m, f| m.max(*f));
        let span = e.duration_s();
        let step = (0.01 / f_max.max(1.0 / decay_s)).min(span / 2000.0);
        let n = (span / step).ceil() as usize;
        let (mut best_x, mut best) = (decay_s, f64::NEG_INFINITY);
        for i in 1..n {
            let x = i as f64 * step;
            let v = e.unit(x);
            if v > best {
                best = v;
                best_x = x;
            }
        }
        let (mut a, mut b) = ((best_x - step).max(0.0), (best_x + step).min(span));
        let r = 0.5 * (5f64.sqrt() - 1.0);
        for _ in 0..80 {
            let (c, d) = (b - r * (b - a), a + r * (b - a));
            if e.unit(c) > e.unit(d) {
                b = d;
            } else {
                a = c;
            }
        }
        let x = 0.5 * (a + b);
        let top = e.unit(x).max(best);
        e.peak_after_onset_s = x;
        e.scale = if top > 0.0 { peak_v / top } else { 0.0 };
        e
    }

    /// Unscaled shape `x` seconds after the onset.
    fn unit(&self, x: f64) -> f64 {
        if !(x > 0.0 && x <= self.duration_s()) {
            return 0.0;
        }
        let u = x / self.decay_s;
        u * (1.0 - u).exp() * self.omegas.iter().map(|w| (w * x).sin()).sum::<f64>()
    }

    /// The event's value `x` seconds after its onset, V.
    pub fn value_v(&self, x: f64) -> f64 {
        self.scale * self.unit(x)
    }

    /// Length from the onset to the cut, s.
    pub fn duration_s(&self) -> f64 {
        EVENT_CUT_DECAYS * self.decay_s
    }

    /// Time from the onset to the largest positive excursion, s.
    pub fn peak_after_onset_s(&self) -> f64 {
        self.peak_after_onset_s
    }

    /// Largest positive excursion, V.
    pub fn peak_v(&self) -> f64 {
        self.peak_v
    }

    /// Draws whether a frame of `span_s` seconds starting at `t_first_s`
    /// holds an event, and if so its onset (uniform over the frame), s.
    pub fn draw<R: Rng>(&self, rng: &mut R, t_first_s: f64, span_s: f64) -> Option<f64> {
        // Both numbers are drawn every frame, so a frame's draw does not
        // depend on the probability's value beyond the comparison.
        let (p, u) = (rng.random::<f64>(), rng.random::<f64>());
        (p < self.probability).then_some(t_first_s + u * span_s)
    }

    /// Adds an event with onset `onset_s` to `out`, whose sample `k` is at
    /// `t_first_s + k dt_s`.
    pub fn add_to(&self, out: &mut [f64], t_first_s: f64, dt_s: f64, onset_s: f64) {
        for (k, v) in out.iter_mut().enumerate() {
            let x = t_first_s + k as f64 * dt_s - onset_s;
            if x > 0.0 && x <= self.duration_s() {
                *v += self.value_v(x);
            }
        }
    }
}

/// SplitMix64 finaliser: a well-mixed 64-bit hash.
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// The default scene's events: modes 1.3, 3.1 and 6.7 MHz, τ = 80 ns, 0.35 V.
    fn prototype() -> InterferenceEvent {
        InterferenceEvent::new(0.35, 80e-9, &[1.3e6, 3.1e6, 6.7e6], 1.0 / 3.0)
    }

    /// The event on a 1 ns grid from its onset to its cut.
    fn samples(e: &InterferenceEvent, dt: f64) -> Vec<f64> {
        let mut v = vec![0.0; (e.duration_s() / dt).ceil() as usize + 2];
        e.add_to(&mut v, 0.0, dt, 0.0);
        v
    }

    #[test]
    fn event_energy_lies_below_10_mhz() {
        use realfft::RealFftPlanner;
        for (modes, decay) in [(vec![1.3e6, 3.1e6, 6.7e6], 80e-9), (vec![3e6, 7e6], 150e-9), (vec![2e6], 50e-9)] {
            let e = InterferenceEvent::new(0.35, decay, &modes, 1.0);
            let dt = 1e-9;
            let x = samples(&e, dt);
            // Zero-padded to a fine frequency grid (1/(65536 ns) = 15 kHz).
            let n = 1 << 16;
            let mut buf = vec![0.0; n];
            buf[..x.len()].copy_from_slice(&x);
            let fft = RealFftPlanner::<f64>::new().plan_fft_forward(n);
            let mut spec = fft.make_output_vec();
            fft.process(&mut buf, &mut spec).unwrap();
            let (mut above, mut total) = (0.0, 0.0);
            for (k, s) in spec.iter().enumerate() {
                let p = s.norm_sqr();
                total += p;
                if k as f64 / (n as f64 * dt) > 10e6 {
                    above += p;
                }
            }
            // The envelope's spectrum around a mode at f falls as
            // 1/(1 + (2π Δf τ)²): for 6.7 MHz and τ = 80 ns about 4 % of that
            // mode's energy lies beyond 10 MHz; the default scene's event has
            // 1.4 % of its energy there.
            let frac = above / total;
            assert!(frac < 0.05, "modes {modes:?} tau {decay}: {frac:.4} of the energy above 10 MHz");
        }
    }

    #[test]
    fn event_peaks_at_the_configured_amplitude_and_decays() {
        let e = prototype();
        // A fine grid (0.05 ns) finds the largest positive excursion.
        let x = samples(&e, 0.05e-9);
        let top = x.iter().fold(f64::NEG_INFINITY, |m, v| m.max(*v));
        assert!((top - 0.35).abs() < 1e-4, "peak {top}");
        assert!((e.value_v(e.peak_after_onset_s()) - 0.35).abs() < 1e-9);
        assert_eq!(e.peak_v(), 0.35);
        // Smooth onset, and zero before it and past the cut.
        assert_eq!(e.value_v(0.0), 0.0);
        assert_eq!(e.value_v(-1e-9), 0.0);
        assert_eq!(e.value_v(e.duration_s() + 1e-9), 0.0);
        assert!(e.value_v(1e-9).abs() < 0.02, "{}", e.value_v(1e-9));
        // Decays: the largest |value| in successive windows of 2 τ after the
        // envelope's peak falls every window, and is below 5 % of the peak from 6 τ.
        let tau = 80e-9;
        let win_max = |a: f64, b: f64| {
            let n = 4000;
            (0..=n).map(|i| e.value_v(a + (b - a) * i as f64 / n as f64).abs()).fold(0.0, f64::max)
        };
        let maxima: Vec<f64> = (0..5).map(|k| win_max((2 + 2 * k) as f64 * tau, (4 + 2 * k) as f64 * tau)).collect();
        assert!(maxima.windows(2).all(|w| w[1] < w[0]), "{maxima:?}");
        assert!(win_max(6.0 * tau, 12.0 * tau) < 0.05 * 0.35, "{maxima:?}");
        // A fraction of the 2.5 us frame: 99 % of its energy within 500 ns of the onset.
        let x = samples(&e, 1e-9);
        let total: f64 = x.iter().map(|v| v * v).sum();
        let early: f64 = x[..500].iter().map(|v| v * v).sum();
        assert!(early > 0.99 * total, "{}", early / total);
    }

    /// Of 3000 frames with probability 1/3, the fraction holding an event is
    /// within the 99.9 % binomial interval: ±3.29 sqrt(p(1−p)/N) = ±0.028
    /// (normal approximation, N p = 1000); the onsets are uniform over the
    /// frame (mean within 3.29 sqrt(1/12/K) of the middle, K the events).
    #[test]
    fn events_fall_in_the_configured_fraction_of_frames_at_uniform_positions() {
        let e = prototype();
        let (frames, p) = (3000usize, 1.0 / 3.0);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (t_first, span) = (-250e-9, 2500e-9);
        let onsets: Vec<f64> = (0..frames).filter_map(|_| e.draw(&mut rng, t_first, span)).collect();
        let frac = onsets.len() as f64 / frames as f64;
        let tol = 3.29 * (p * (1.0 - p) / frames as f64).sqrt();
        assert!((frac - p).abs() < tol, "fraction {frac} vs {p} +- {tol}");
        assert!(onsets.iter().all(|t| (t_first..t_first + span).contains(t)));
        let mean_u = onsets.iter().map(|t| (t - t_first) / span).sum::<f64>() / onsets.len() as f64;
        let tol_u = 3.29 * (1.0 / 12.0 / onsets.len() as f64).sqrt();
        assert!((mean_u - 0.5).abs() < tol_u, "mean position {mean_u} +- {tol_u}");
        // Probability 0 and 1 are exact.
        let never = InterferenceEvent::new(0.35, 80e-9, &[3e6], 0.0);
        let always = InterferenceEvent::new(0.35, 80e-9, &[3e6], 1.0);
        assert!((0..100).all(|_| never.draw(&mut rng, 0.0, 1e-6).is_none()));
        assert!((0..100).all(|_| always.draw(&mut rng, 0.0, 1e-6).is_some()));
    }
}
