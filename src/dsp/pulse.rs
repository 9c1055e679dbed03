//! Parametric pulse shapes in units of samples, peak 1 at t = 0.
//!
//! Built from plain parameters (seconds and a sampling period); the scene's
//! `PulseConfig` picks the constructor (`PulseConfig::shape`, `PulseConfig::pulse`).

use crate::math::exp::exp;

/// sqrt(2 ln 2): half width at half maximum of a unit-sigma Gaussian.
const HWHM_PER_SIGMA: f64 = 1.177_410_022_515_474_6;
/// sqrt(2 ln 10) - sqrt(2 ln(10/9)): 10-90 % rise of a unit-sigma Gaussian edge.
const RISE_PER_SIGMA: f64 = 1.686_922_421_262_926_4;

/// A shape evaluated at continuous time (in samples).
pub trait PulseShape {
    /// Value and derivative (per sample) at `t`.
    fn value_and_slope(&self, t: f64) -> (f64, f64);

    /// (value, slope) at t0, t0 + 1, … into every entry of `out`: what
    /// [`value_and_slope`](Self::value_and_slope) gives there (a table's
    /// bit for bit; a Gaussian's within a few ulp, see
    /// [`Pulse`]'s grid).
    fn fill_grid(&self, t0: f64, out: &mut [(f64, f64)]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = self.value_and_slope(t0 + i as f64);
        }
    }
}

/// Two Gaussian halves meeting at the peak (t = 0): sigma_rise before, sigma_fall after.
/// Value and first derivative are continuous.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pulse {
    /// Rising-half sigma, samples.
    pub sigma_rise: f64,
    /// Falling-half sigma, samples.
    pub sigma_fall: f64,
}

impl Pulse {
    /// Symmetric Gaussian of full width at half maximum `fwhm_s` at sampling period `dt_s`.
    pub fn gaussian(fwhm_s: f64, dt_s: f64) -> Pulse {
        let s = fwhm_s / (2.0 * HWHM_PER_SIGMA) / dt_s;
        Pulse { sigma_rise: s, sigma_fall: s }
    }

    /// Bigaussian with 10-90 % rise time `rise_time_s` and full width at half
    /// maximum `fwhm_s` at sampling period `dt_s` (the rise must leave a
    /// positive falling half: `rise_time_s < 1.43 * fwhm_s`).
    pub fn bigaussian(rise_time_s: f64, fwhm_s: f64, dt_s: f64) -> Pulse {
        let sr = rise_time_s / RISE_PER_SIGMA;
        let sf = (fwhm_s - HWHM_PER_SIGMA * sr) / HWHM_PER_SIGMA;
        Pulse { sigma_rise: sr / dt_s, sigma_fall: sf / dt_s }
    }

    /// Time of the 50 % leading-edge crossing relative to the peak, samples (negative).
    pub fn half_rise_offset(&self) -> f64 {
        -HWHM_PER_SIGMA * self.sigma_rise
    }

    /// Time where the leading edge reaches `fraction` of the peak, relative to the peak.
    pub fn fraction_offset(&self, fraction: f64) -> f64 {
        -self.sigma_rise * (-2.0 * fraction.ln()).sqrt()
    }

    /// Support [lo, hi] relative to the peak beyond which the value is below exp(-8) (about 3e-4).
    pub fn support(&self) -> (f64, f64) {
        (-4.0 * self.sigma_rise, 4.0 * self.sigma_fall)
    }

    /// The values alone of [`fill_grid`](PulseShape::fill_grid) at t0,
    /// t0 + 1, … into every entry of `out`: the same bits.
    pub fn fill_values(&self, t0: f64, out: &mut [f64]) {
        match vectors() {
            // SAFETY: the CPU has the features the function is compiled for.
            #[cfg(target_arch = "x86_64")]
            Vectors::Avx512 => unsafe { gaussian_values_on_grid_avx512(self, t0, out) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            Vectors::Avx2Fma => unsafe { gaussian_values_on_grid_avx2(self, t0, out) },
            Vectors::Portable => gaussian_values_on_grid(self, t0, out),
        }
    }

    /// Full width at half maximum, samples.
    pub fn fwhm(&self) -> f64 {
        HWHM_PER_SIGMA * (self.sigma_rise + self.sigma_fall)
    }

    /// Samples the shape on the integer grid covering its support. Returns the
    /// taps and the index of the tap nearest the peak (tap `i` is at time `i - peak_index`).
    pub fn template(&self) -> (Vec<f64>, usize) {
        let (lo, hi) = self.support();
        let first = lo.floor() as i64;
        let last = hi.ceil() as i64;
        let taps = (first..=last).map(|k| self.value_and_slope(k as f64).0).collect();
        (taps, (-first) as usize)
    }
}

impl PulseShape for Pulse {
    #[inline]
    fn value_and_slope(&self, t: f64) -> (f64, f64) {
        let s = if t < 0.0 { self.sigma_rise } else { self.sigma_fall };
        let z = t / s;
        let v = (-0.5 * z * z).exp();
        (v, -v * z / s)
    }

    fn fill_grid(&self, t0: f64, out: &mut [(f64, f64)]) {
        match vectors() {
            // SAFETY: the CPU has the features the function is compiled for.
            #[cfg(target_arch = "x86_64")]
            Vectors::Avx512 => unsafe { gaussian_halves_on_grid_avx512(self, t0, out) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            Vectors::Avx2Fma => unsafe { gaussian_halves_on_grid_avx2(self, t0, out) },
            Vectors::Portable => gaussian_halves_on_grid(self, t0, out),
        }
    }
}

/// Which copies of the Gaussian's grid kernels this CPU can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Vectors {
    /// AVX-512 (F, DQ, VL) with AVX2 and FMA.
    #[cfg(target_arch = "x86_64")]
    Avx512,
    /// AVX2 with FMA.
    #[cfg(target_arch = "x86_64")]
    Avx2Fma,
    /// Neither: the portable body.
    Portable,
}

/// The widest [`Vectors`] this CPU has (the standard library caches the
/// features it detects).
#[inline]
fn vectors() -> Vectors {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx512f") && has!("avx512dq") && has!("avx512vl") && has!("avx2") && has!("fma") {
            return Vectors::Avx512;
        }
        if has!("avx2") && has!("fma") {
            return Vectors::Avx2Fma;
        }
    }
    Vectors::Portable
}

/// (value, slope) at `t` of a Gaussian of 1/sigma `inv`.
#[inline(always)]
fn gaussian_half(inv: f64, t: f64) -> (f64, f64) {
    let v = gaussian_value(inv, t);
    (v, -v * (t * inv) * inv)
}

/// The value alone of [`gaussian_half`] (the one expression both use).
#[inline(always)]
fn gaussian_value(inv: f64, t: f64) -> f64 {
    let z = t * inv;
    exp(-0.5 * z * z)
}

/// (value, slope) of `p` at t0, t0 + 1, … into `out`, with
/// [`crate::math::exp::exp`] (exactly rounded operations, so scalar
/// and vectorised give the same bits; without hardware FMA, slowly) and the sigmas' reciprocals: within a few ulp of
/// [`Pulse::value_and_slope`] (libm's `exp` and two divisions) near the
/// peak, growing with z² in the tails (z·2e-16 in z, times z² in the value).
#[inline(always)]
fn gaussian_halves_on_grid(p: &Pulse, t0: f64, out: &mut [(f64, f64)]) {
    gaussian_on_grid(p, t0, out, gaussian_half);
}

/// The values alone of [`gaussian_halves_on_grid`]: the same operations on
/// each point, so the same bits (no slope, no pairs to store).
#[inline(always)]
fn gaussian_values_on_grid(p: &Pulse, t0: f64, out: &mut [f64]) {
    gaussian_on_grid(p, t0, out, gaussian_value);
}

/// `point(1/sigma, t)` at t0, t0 + 1, … into `out`, eight points at a
/// time, the rise's sigma before the peak and the fall's after it.
/// `point` is a function item, inlined: the loops vectorise. (Shared as a
/// closure over the sigmas, the point's expression stopped both loops
/// vectorising, 25 % slower on reference frames.)
#[inline(always)]
fn gaussian_on_grid<T: Copy + Default>(p: &Pulse, t0: f64, out: &mut [T], point: fn(f64, f64) -> T) {
    // Opaque to the optimiser: otherwise it turns the choice between two
    // reciprocals into a division per point (of the chosen sigma), the
    // same bits at many times the cost.
    let (rise, fall) = std::hint::black_box((1.0 / p.sigma_rise, 1.0 / p.sigma_fall));
    let first = out.len() - out.len() % 8;
    let mut eights = out.chunks_exact_mut(8);
    for (c, o) in eights.by_ref().enumerate() {
        for (i, o) in o.iter_mut().enumerate() {
            let t = t0 + (8 * c + i) as f64;
            *o = point(if t < 0.0 { rise } else { fall }, t);
        }
    }
    // The last few points as a whole eight (the same bits, vectorised too)
    // rather than one at a time: a fit's window is seldom a multiple of eight.
    let rest = eights.into_remainder();
    if !rest.is_empty() {
        let mut eight = [T::default(); 8];
        for (i, o) in eight.iter_mut().enumerate() {
            let t = t0 + (first + i) as f64;
            *o = point(if t < 0.0 { rise } else { fall }, t);
        }
        rest.copy_from_slice(&eight[..rest.len()]);
    }
}

/// [`gaussian_values_on_grid`] compiled for AVX-512, the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
fn gaussian_values_on_grid_avx512(p: &Pulse, t0: f64, out: &mut [f64]) {
    gaussian_values_on_grid(p, t0, out);
}

/// [`gaussian_values_on_grid`] compiled for AVX2 with FMA, the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn gaussian_values_on_grid_avx2(p: &Pulse, t0: f64, out: &mut [f64]) {
    gaussian_values_on_grid(p, t0, out);
}

/// [`gaussian_halves_on_grid`] compiled for AVX-512 (the loop vectorises:
/// eight points at a time, the multiply-adds fused in hardware), the same
/// bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
fn gaussian_halves_on_grid_avx512(p: &Pulse, t0: f64, out: &mut [(f64, f64)]) {
    gaussian_halves_on_grid(p, t0, out);
}

/// The same for AVX2 with FMA (four points at a time), the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn gaussian_halves_on_grid_avx2(p: &Pulse, t0: f64, out: &mut [(f64, f64)]) {
    gaussian_halves_on_grid(p, t0, out);
}

/// A measured shape on a fine grid, interpolated with cubic Hermite splines
/// (value and slope continuous), peak 1 at t = 0, in units of samples.
#[derive(Debug, Clone, PartialEq)]
pub struct TablePulse {
    /// Grid spacing, samples.
    step: f64,
    /// Time of `values[0]` relative to the peak, samples.
    first: f64,
    values: Vec<f64>,
    /// d value / d t at the grid points, per sample.
    slopes: Vec<f64>,
    /// 1/step where the step is a power of two (as a table learned at 8 or
    /// measured at 4 points per sample is): multiplying by it is then the
    /// very division, and costs a fraction of one.
    inv_step: Option<f64>,
    /// The table by phase, where a whole sample is a whole number of steps
    /// (see [`Phased`]; derived from `values` and `slopes`).
    phased: Option<Phased>,
    /// The half-maximum crossings before and after the peak, samples from
    /// it (`crossing`'s, kept: the FWHM and the 50 % fraction point are
    /// asked for every frame, and each is a walk along the table); none
    /// for a table of no values.
    half: Option<(f64, f64)>,
}

/// A table regrouped for a grid of whole samples: with `per` steps to a
/// sample, the points t0, t0 + 1, … fall in cells i, i + per, i + 2·per, …,
/// one phase r = i mod per. Phase r's table points (per·q + r at q) are
/// stored in order, their values and their slopes times the step each as
/// its own run, so that eight points read eight neighbours of a run (no
/// gather): a cell's start from its phase's runs, its end (point i + 1)
/// from the next phase's (phase 0 one further on after the last phase).
/// Each run has [`PAD`](Phased::PAD) zeros before and after it: eight
/// points partly off the table read them in the lanes they then set to zero.
#[derive(Clone)]
struct Phased {
    /// Steps per sample, 2^shift.
    shift: u32,
    /// Points per phase (a phase's last ones past the table are zeros, read
    /// only by points off the table).
    points: usize,
    /// Phase r's values (k = 0) and slopes × step (k = 1) at point q:
    /// `data[(2r + k)·stride + PAD + q]`, stride = points + 2·PAD.
    data: Vec<f64>,
}

/// Derived from the table's values: equal where they are.
impl PartialEq for Phased {
    fn eq(&self, _: &Phased) -> bool {
        true
    }
}

/// The layout only (the numbers are the table's).
impl std::fmt::Debug for Phased {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Phased").field("per", &(1usize << self.shift)).field("points", &self.points).finish()
    }
}

impl Phased {
    /// Zeros on either side of a run: eight points, one of them on the
    /// table, read at most eight points beyond it (seven, and the cell's end).
    const PAD: usize = 8;

    /// For `values` and `slopes` (at least two) with `per` (a power of two)
    /// steps to a sample and step `step`.
    fn new(values: &[f64], slopes: &[f64], step: f64, per: usize) -> Phased {
        let points = values.len().div_ceil(per);
        let stride = points + 2 * Self::PAD;
        let mut data = vec![0.0; 2 * per * stride];
        for (j, (&v, &m)) in values.iter().zip(slopes).enumerate() {
            let (r, q) = (j % per, j / per);
            data[2 * r * stride + Self::PAD + q] = v;
            // The very product `eval` takes.
            data[(2 * r + 1) * stride + Self::PAD + q] = m * step;
        }
        Phased { shift: per.trailing_zeros(), points, data }
    }

    /// Run `k` of phase `r`, eight points from `q` (−PAD ≤ q ≤ points + PAD − 8).
    #[inline(always)]
    fn run8(&self, r: usize, k: usize, q: i64) -> &[f64] {
        let stride = self.points + 2 * Self::PAD;
        let at = (2 * r + k) * stride + (Self::PAD as i64 + q) as usize;
        &self.data[at..at + 8]
    }
}

impl TablePulse {
    /// From values every `step` samples, the first at `first` samples from the peak.
    /// Needs at least 4 values.
    pub fn new(values: Vec<f64>, step: f64, first: f64) -> TablePulse {
        let n = values.len();
        let slopes: Vec<f64> = (0..n)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
                (values[b] - values[a]) / ((b - a).max(1) as f64 * step)
            })
            .collect();
        let inv = 1.0 / step;
        let power_of_two = step.is_normal() && inv.is_normal() && step.to_bits() & ((1u64 << 52) - 1) == 0;
        // A whole sample a whole number of steps, and a table no coarser than
        // a sample (at most 64 phases: the finest tables are learned at 8).
        let per = (power_of_two && (1.0..=64.0).contains(&inv) && n >= 2).then_some(inv as usize);
        let phased = per.map(|per| Phased::new(&values, &slopes, step, per));
        let mut table = TablePulse { step, first, values, slopes, inv_step: power_of_two.then_some(inv), phased, half: None };
        if n > 0 {
            table.half = Some((table.walk_to(0.5, true), table.walk_to(0.5, false)));
        }
        table
    }

    /// The values on the grid.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Grid spacing, samples.
    pub fn step(&self) -> f64 {
        self.step
    }

    /// Time of the first value relative to the peak, samples.
    pub fn first(&self) -> f64 {
        self.first
    }

    fn crossing(&self, fraction: f64, rising: bool) -> f64 {
        if let Some((rise, fall)) = self.half.filter(|_| fraction == 0.5) {
            return if rising { rise } else { fall };
        }
        self.walk_to(fraction, rising)
    }

    /// Where the table, walked from its peak before it (`rising`) or after
    /// it, first falls to `fraction`, linearly between its points; its end
    /// where it never does.
    fn walk_to(&self, fraction: f64, rising: bool) -> f64 {
        let peak = ((-self.first / self.step).round() as usize).min(self.values.len() - 1);
        let v = &self.values;
        let mut i = peak;
        loop {
            let next = if rising { i.checked_sub(1) } else { (i + 1 < v.len()).then_some(i + 1) };
            let Some(j) = next else {
                return self.first + i as f64 * self.step;
            };
            if v[j] <= fraction {
                let f = (v[i] - fraction) / (v[i] - v[j]).max(f64::MIN_POSITIVE);
                let t = i as f64 + if rising { -f } else { f };
                return self.first + t * self.step;
            }
            i = j;
        }
    }
}

impl PulseShape for TablePulse {
    #[inline]
    fn value_and_slope(&self, t: f64) -> (f64, f64) {
        self.eval(t)
    }

    fn fill_grid(&self, t0: f64, out: &mut [(f64, f64)]) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            if let Some(inv) = self.inv_step
                && has!("avx512f")
                && has!("avx512dq")
                && has!("avx512vl")
                && has!("avx2")
                && has!("fma")
            {
                // SAFETY: the CPU has every feature the function is compiled for (checked above).
                unsafe { self.fill_grid_avx512(t0, inv, out) };
                return;
            }
            if let Some(inv) = self.inv_step
                && has!("avx2")
            {
                // SAFETY: the CPU has AVX2 (checked just above).
                unsafe { self.fill_grid_avx2(t0, inv, out) };
                return;
            }
        }
        self.fill_grid_scalar(t0, out);
    }
}

impl TablePulse {
    fn fill_grid_scalar(&self, t0: f64, out: &mut [(f64, f64)]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = self.eval(t0 + i as f64);
        }
    }

    /// [`eval`](Self::eval) at t0, t0 + 1, … for a power-of-two step (1/step
    /// `inv`), eight points at a time in vector registers: the same
    /// operations in the same order on each point, so bit for bit the same
    /// values. The cell index is floor(u) (u in [0, n − 1) where used: the
    /// truncation `eval` takes).
    ///
    /// Where the table is kept by phase and the eight points fall in cells
    /// i, i + per, …, i + 7·per (the usual case: a whole sample is `per`
    /// steps, and only rounding of t0 + k could make it otherwise), the
    /// spline's inputs are read as eight neighbours of the phases' runs
    /// instead of gathered from eight places: the same numbers. Returns the
    /// eights read so and the eights gathered (the tests count both; an
    /// eight wholly off the table is neither).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
    fn fill_grid_avx512(&self, t0: f64, inv: f64, out: &mut [(f64, f64)]) -> (usize, usize) {
        by_eights(out, |k0, chunk| self.grid_eight(t0, k0, inv, chunk))
    }

    /// [`fill_grid_avx512`](Self::fill_grid_avx512) for CPUs with AVX2 but
    /// not AVX-512: the same eights, read the same ways, in eight plain
    /// lanes ([`grid_eight_lanes`](Self::grid_eight_lanes)) the compiler
    /// keeps in two registers each; bit for bit [`eval`](Self::eval) too.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn fill_grid_avx2(&self, t0: f64, inv: f64, out: &mut [(f64, f64)]) -> (usize, usize) {
        by_eights(out, |k0, chunk| self.grid_eight_lanes(t0, k0, inv, chunk))
    }

    /// [`grid_eight`](Self::grid_eight)'s operations, lane by lane, in
    /// plain arrays: the same point, the same mask, the same test for eight
    /// cells one phase apart (on the cells as `vcvttpd2qq` gives them: out
    /// of the i64 range and NaN read as i64::MIN), the same reads and the
    /// same arithmetic in the same order, nothing fused.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn grid_eight_lanes(&self, t0: f64, k0: usize, inv: f64, chunk: &mut [(f64, f64); 8]) -> Read {
        let (values, slopes) = (&self.values[..], &self.slopes[..]);
        let n = values.len();
        let top = (n - 1) as f64;
        let mut u = [0.0f64; 8];
        let mut ok = [false; 8];
        for l in 0..8 {
            let t = t0 + (k0 as f64 + l as f64);
            u[l] = (t - self.first) * inv;
            ok[l] = u[l] >= 0.0 && u[l] < top;
        }
        if !ok.iter().any(|&o| o) {
            *chunk = [(0.0, 0.0); 8];
            return Read::Off;
        }
        let (mut fl, mut s) = ([0.0f64; 8], [0.0f64; 8]);
        for l in 0..8 {
            fl[l] = u[l].floor() + 0.0;
            s[l] = u[l] - fl[l];
        }
        // Lane 0's cell as the truncating conversion gives it (i64::MIN out
        // of the i64 range and for NaN).
        let cell0 = if fl[0] >= -9_223_372_036_854_775_808.0 && fl[0] < 9_223_372_036_854_775_808.0 { fl[0] as i64 } else { i64::MIN };
        let mut phased = None;
        if let Some(ph) = self.phased.as_ref() {
            let per = 1usize << ph.shift;
            let (r, q) = ((cell0 & (per as i64 - 1)) as usize, cell0 >> ph.shift);
            let (r1, q1) = if r + 1 == per { (0, q + 1) } else { (r + 1, q) };
            let pad = Phased::PAD as i64;
            if q >= -pad && q1 + 8 <= ph.points as i64 + pad {
                // Inside the phases' runs cell0 is small, so lane l's cell
                // is cell0 + l·per exactly when its floor is that number in
                // f64 (a NaN or a floor out of range equals none).
                let base = cell0 as f64;
                let mut apart = true;
                for (l, &f) in fl.iter().enumerate() {
                    apart &= f == base + ((l as i64) << ph.shift) as f64;
                }
                if apart {
                    phased = Some((ph, (r, q), (r1, q1)));
                }
            }
        }
        let eight = |run: &[f64]| -> [f64; 8] { run.try_into().expect("eight") };
        let (p0, p1, m0, m1, read) = match phased {
            Some((ph, (r, q), (r1, q1))) => (eight(ph.run8(r, 0, q)), eight(ph.run8(r1, 0, q1)), eight(ph.run8(r, 1, q)), eight(ph.run8(r1, 1, q1)), Read::Phased),
            None => {
                // Lanes off the table read cell 0 (their values are not used).
                let at: [usize; 8] = std::array::from_fn(|l| if ok[l] { fl[l] as usize } else { 0 });
                (
                    at.map(|c| values[c]),
                    at.map(|c| values[c + 1]),
                    at.map(|c| slopes[c] * self.step),
                    at.map(|c| slopes[c + 1] * self.step),
                    Read::Gathered,
                )
            }
        };
        for l in 0..8 {
            let s = s[l];
            let s2 = s * s;
            let s3 = s2 * s;
            let a = 2.0 * s3 - 3.0 * s2 + 1.0;
            let b = s3 - 2.0 * s2 + s;
            let c = -2.0 * s3 + 3.0 * s2;
            let d = s3 - s2;
            let v = a * p0[l] + b * m0[l] + c * p1[l] + d * m1[l];
            let da = 6.0 * s2 - 6.0 * s;
            let db = 3.0 * s2 - 4.0 * s + 1.0;
            let dc = -6.0 * s2 + 6.0 * s;
            let dd = 3.0 * s2 - 2.0 * s;
            let dv = da * p0[l] + db * m0[l] + dc * p1[l] + dd * m1[l];
            chunk[l] = if ok[l] { (v, dv * inv) } else { (0.0, 0.0) };
        }
        read
    }

    /// Points t0 + k0 … t0 + k0 + 7 for [`fill_grid_avx512`](Self::fill_grid_avx512)
    /// (called there for each eight), [`eval`](Self::eval)'s operations in
    /// its order on eight lanes; says how the spline's inputs were read.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
    #[inline]
    fn grid_eight(&self, t0: f64, k0: usize, inv: f64, chunk: &mut [(f64, f64); 8]) -> Read {
        use std::arch::x86_64::{
            _CMP_GE_OQ, _CMP_LT_OQ, _MM_FROUND_NO_EXC, _MM_FROUND_TO_NEG_INF, _mm_cvtsi128_si64, _mm512_add_epi64,
            _mm512_add_pd, _mm512_castsi512_si128, _mm512_cmp_pd_mask, _mm512_cmpeq_epi64_mask, _mm512_cvttpd_epi64,
            _mm512_i64gather_pd, _mm512_loadu_pd, _mm512_maskz_mov_epi64, _mm512_maskz_mov_pd, _mm512_mul_pd,
            _mm512_roundscale_pd, _mm512_set_epi64, _mm512_set_pd, _mm512_set1_epi64, _mm512_set1_pd, _mm512_setzero_pd,
            _mm512_sllv_epi64, _mm512_storeu_pd, _mm512_sub_pd,
        };
        let (values, slopes) = (&self.values[..], &self.slopes[..]);
        let n = values.len();
        let set = _mm512_set1_pd;
        let lane = _mm512_set_pd(7.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0, 0.0);
        // t0 + (k0 + l): k0 + l is exact in f64 (k0 < 2⁵²), and so is k0 + l as a sum.
        let t = _mm512_add_pd(set(t0), _mm512_add_pd(set(k0 as f64), lane));
        let u = _mm512_mul_pd(_mm512_sub_pd(t, set(self.first)), set(inv));
        // 0 ≤ u < n − 1 (false for NaN): the points on the table.
        let ok = _mm512_cmp_pd_mask::<_CMP_GE_OQ>(u, _mm512_setzero_pd()) & _mm512_cmp_pd_mask::<_CMP_LT_OQ>(u, set((n - 1) as f64));
        if ok == 0 {
            *chunk = [(0.0, 0.0); 8];
            return Read::Off;
        }
        // floor(u) + 0: eval's `u as usize` back in f64 is +0 where u is −0.
        let fl = _mm512_add_pd(_mm512_roundscale_pd::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(u), _mm512_setzero_pd());
        let s = _mm512_sub_pd(u, fl);
        // Every lane's cell, off the table too (there outside [0, n − 2];
        // beyond the i64 range and NaN: i64::MIN).
        let cell = _mm512_cvttpd_epi64(fl);
        let cell0 = _mm_cvtsi128_si64(_mm512_castsi512_si128(cell));
        // Eight cells one phase apart, their starts and ends within the
        // phases' runs and zeros: the inputs are eight neighbours there.
        let phased = self.phased.as_ref().and_then(|ph| {
            let steps = _mm512_sllv_epi64(_mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0), _mm512_set1_epi64(i64::from(ph.shift)));
            let want = _mm512_add_epi64(_mm512_set1_epi64(cell0), steps);
            let per = 1usize << ph.shift;
            // Floor division and remainder, for negative cells too.
            let (r, q) = ((cell0 & (per as i64 - 1)) as usize, cell0 >> ph.shift);
            // The cell's end, point per·q + r + 1.
            let (r1, q1) = if r + 1 == per { (0, q + 1) } else { (r + 1, q) };
            let pad = Phased::PAD as i64;
            let inside = q >= -pad && q1 + 8 <= ph.points as i64 + pad;
            (inside && _mm512_cmpeq_epi64_mask(cell, want) == 0xff).then_some((ph, (r, q), (r1, q1)))
        });
        let (p0, p1, m0, m1, read) = match phased {
            Some((ph, (r, q), (r1, q1))) => {
                let load = |r: usize, k: usize, q: i64| {
                    let run = ph.run8(r, k, q);
                    // SAFETY: `run` holds eight f64 (`Phased::run8`'s slice).
                    unsafe { _mm512_loadu_pd(run.as_ptr()) }
                };
                (load(r, 0, q), load(r1, 0, q1), load(r, 1, q), load(r1, 1, q1), Read::Phased)
            }
            None => {
                // Lanes off the table read cell 0 (their values are not used).
                let cell = _mm512_maskz_mov_epi64(ok, cell);
                let next = _mm512_add_epi64(cell, _mm512_set1_epi64(1));
                // SAFETY: every lane's cell is in [0, n − 2], so it and the
                // next are inside `values` and `slopes`.
                unsafe {
                    (
                        _mm512_i64gather_pd::<8>(cell, values.as_ptr()),
                        _mm512_i64gather_pd::<8>(next, values.as_ptr()),
                        _mm512_mul_pd(_mm512_i64gather_pd::<8>(cell, slopes.as_ptr()), set(self.step)),
                        _mm512_mul_pd(_mm512_i64gather_pd::<8>(next, slopes.as_ptr()), set(self.step)),
                        Read::Gathered,
                    )
                }
            }
        };
        let (mul, add, sub) = (_mm512_mul_pd, _mm512_add_pd, _mm512_sub_pd);
        let s2 = mul(s, s);
        let s3 = mul(s2, s);
        // v = (2s³ − 3s² + 1)·p0 + (s³ − 2s² + s)·m0 + (−2s³ + 3s²)·p1 + (s³ − s²)·m1, left to right.
        let a = add(sub(mul(set(2.0), s3), mul(set(3.0), s2)), set(1.0));
        let b = add(sub(s3, mul(set(2.0), s2)), s);
        let c = add(mul(set(-2.0), s3), mul(set(3.0), s2));
        let d = sub(s3, s2);
        let v = add(add(add(mul(a, p0), mul(b, m0)), mul(c, p1)), mul(d, m1));
        // dv = (6s² − 6s)·p0 + (3s² − 4s + 1)·m0 + (−6s² + 6s)·p1 + (3s² − 2s)·m1.
        let da = sub(mul(set(6.0), s2), mul(set(6.0), s));
        let db = add(sub(mul(set(3.0), s2), mul(set(4.0), s)), set(1.0));
        let dc = add(mul(set(-6.0), s2), mul(set(6.0), s));
        let dd = sub(mul(set(3.0), s2), mul(set(2.0), s));
        let dv = add(add(add(mul(da, p0), mul(db, m0)), mul(dc, p1)), mul(dd, m1));
        let (mut vs, mut slopes_out) = ([0.0; 8], [0.0; 8]);
        // SAFETY: each array holds eight f64.
        unsafe {
            _mm512_storeu_pd(vs.as_mut_ptr(), _mm512_maskz_mov_pd(ok, v));
            _mm512_storeu_pd(slopes_out.as_mut_ptr(), _mm512_maskz_mov_pd(ok, mul(dv, set(inv))));
        }
        for (o, (&v, &dv)) in chunk.iter_mut().zip(vs.iter().zip(&slopes_out)) {
            *o = (v, dv);
        }
        read
    }
}

/// `out` eight points at a time by `eight` (called with the first point's
/// index and the eight to fill; the last few points as a whole eight, the
/// same bits per point: a fit's window is seldom a multiple of eight);
/// returns the eights read by phase and those gathered.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn by_eights(out: &mut [(f64, f64)], mut eight: impl FnMut(usize, &mut [(f64, f64); 8]) -> Read) -> (usize, usize) {
    let mut count = (0, 0);
    let mut tally = |read: Read| match read {
        Read::Phased => count.0 += 1,
        Read::Gathered => count.1 += 1,
        Read::Off => {}
    };
    let mut chunks = out.chunks_exact_mut(8);
    let mut k0 = 0usize;
    for chunk in &mut chunks {
        tally(eight(k0, chunk.try_into().expect("eight points")));
        k0 += 8;
    }
    let rest = chunks.into_remainder();
    if !rest.is_empty() {
        let mut last = [(0.0, 0.0); 8];
        tally(eight(k0, &mut last));
        rest.copy_from_slice(&last[..rest.len()]);
    }
    count
}

/// How [`TablePulse::grid_eight`] read the spline's inputs for its eight points.
#[cfg(target_arch = "x86_64")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Read {
    /// As neighbours in the table's runs by phase.
    Phased,
    /// Gathered cell by cell.
    Gathered,
    /// Not at all: every point off the table.
    Off,
}

impl TablePulse {
    /// The spline's value and slope at `t` (inlined into the grid loop).
    #[inline(always)]
    fn eval(&self, t: f64) -> (f64, f64) {
        let u = match self.inv_step {
            Some(inv) => (t - self.first) * inv,
            None => (t - self.first) / self.step,
        };
        let n = self.values.len();
        if !(u >= 0.0) || u >= (n - 1) as f64 {
            return (0.0, 0.0);
        }
        let i = u as usize;
        let s = u - i as f64;
        let (p0, p1) = (self.values[i], self.values[i + 1]);
        let (m0, m1) = (self.slopes[i] * self.step, self.slopes[i + 1] * self.step);
        let (s2, s3) = (s * s, s * s * s);
        let v = (2.0 * s3 - 3.0 * s2 + 1.0) * p0 + (s3 - 2.0 * s2 + s) * m0 + (-2.0 * s3 + 3.0 * s2) * p1 + (s3 - s2) * m1;
        let dv = (6.0 * s2 - 6.0 * s) * p0 + (3.0 * s2 - 4.0 * s + 1.0) * m0 + (-6.0 * s2 + 6.0 * s) * p1 + (3.0 * s2 - 2.0 * s) * m1;
        let slope = match self.inv_step {
            Some(inv) => dv * inv,
            None => dv / self.step,
        };
        (v, slope)
    }
}

/// Any pulse shape a scene can describe: parametric or measured.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// Bigaussian or Gaussian.
    Parametric(Pulse),
    /// Measured.
    Table(TablePulse),
}

impl Shape {
    /// Time where the leading edge reaches `fraction` of the peak, relative to the peak, samples.
    pub fn fraction_offset(&self, fraction: f64) -> f64 {
        match self {
            Shape::Parametric(p) => p.fraction_offset(fraction),
            Shape::Table(t) => t.crossing(fraction, true),
        }
    }

    /// Time of the 50 % leading-edge crossing relative to the peak, samples.
    pub fn half_rise_offset(&self) -> f64 {
        self.fraction_offset(0.5)
    }

    /// Support [lo, hi] relative to the peak, samples.
    pub fn support(&self) -> (f64, f64) {
        match self {
            Shape::Parametric(p) => p.support(),
            Shape::Table(t) => (t.first, t.first + (t.values.len() - 1) as f64 * t.step),
        }
    }

    /// Full width at half maximum, samples.
    pub fn fwhm(&self) -> f64 {
        match self {
            Shape::Parametric(p) => p.fwhm(),
            Shape::Table(t) => t.crossing(0.5, false) - t.crossing(0.5, true),
        }
    }

    /// Appends (value, slope) at t0, t0 + 1, ..., t0 + count - 1 samples
    /// from the peak to `out` ([`PulseShape::fill_grid`]).
    pub fn values_on_grid(&self, t0: f64, count: usize, out: &mut Vec<(f64, f64)>) {
        let start = out.len();
        out.resize(start + count, (0.0, 0.0));
        self.fill_grid(t0, &mut out[start..]);
    }

    /// Calls `f(i, value, slope)` at t0 + i for i in 0..count, the points
    /// computed [`fill_grid`](PulseShape::fill_grid)'s way (vectorised)
    /// in blocks of 64 on the stack: no allocation. (A block's points are
    /// at (t0 + 64m) + j: within an ulp of t0 + i.)
    #[inline]
    pub fn for_each_on_grid(&self, t0: f64, count: usize, mut f: impl FnMut(usize, f64, f64)) {
        const BLOCK: usize = 64;
        let mut buf = [(0.0, 0.0); BLOCK];
        let mut i = 0;
        while i < count {
            let n = (count - i).min(BLOCK);
            self.fill_grid(t0 + i as f64, &mut buf[..n]);
            for (j, &(v, s)) in buf[..n].iter().enumerate() {
                f(i + j, v, s);
            }
            i += n;
        }
    }

    /// dst[k] += gain · value(k − peak_index) for every k in `range` that
    /// is inside `dst` (none where the range is empty or lies past its end).
    pub fn add_scaled(&self, peak_index: f64, range: std::ops::Range<usize>, gain: f64, dst: &mut [f64]) {
        let end = range.end.min(dst.len());
        let start = range.start.min(end);
        let dst = &mut dst[start..end];
        self.for_each_on_grid(start as f64 - peak_index, dst.len(), |i, v, _| dst[i] += gain * v);
    }

    /// Samples the shape on the integer grid covering its support; returns the
    /// taps and the index of the tap at the peak (tap `i` is at time `i - peak_index`).
    pub fn template(&self) -> (Vec<f64>, usize) {
        let (lo, hi) = self.support();
        let first = lo.ceil() as i64;
        let last = hi.floor() as i64;
        let taps = (first..=last).map(|k| self.value_and_slope(k as f64).0).collect();
        (taps, (-first).max(0) as usize)
    }
}

impl PulseShape for Shape {
    #[inline]
    fn value_and_slope(&self, t: f64) -> (f64, f64) {
        match self {
            Shape::Parametric(p) => p.value_and_slope(t),
            Shape::Table(tp) => tp.value_and_slope(t),
        }
    }

    fn fill_grid(&self, t0: f64, out: &mut [(f64, f64)]) {
        match self {
            Shape::Parametric(p) => p.fill_grid(t0, out),
            Shape::Table(tp) => tp.fill_grid(t0, out),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_on_grid_match_direct_evaluation() {
        for shape in [
            Shape::Parametric(Pulse { sigma_rise: 4.79, sigma_fall: 17.3 }),
            Shape::Parametric(Pulse::gaussian(26e-9, 1e-9)),
            Shape::Parametric(Pulse { sigma_rise: 0.7, sigma_fall: 1.3 }),
        ] {
            for t0 in [-80.37, -3.5, -0.25, 0.0, 2.9, -1e4] {
                // Lengths around the vector width (eight) and its remainders.
                for count in [0, 1, 7, 8, 9, 150] {
                    let mut out = Vec::new();
                    shape.values_on_grid(t0, count, &mut out);
                    assert_eq!(out.len(), count);
                    // The dispatched (vectorised) grid is the scalar one, bit for bit.
                    let mut scalar = vec![(0.0, 0.0); count];
                    if let Shape::Parametric(p) = &shape {
                        gaussian_halves_on_grid(p, t0, &mut scalar);
                        // The values alone, portable and dispatched, are the pairs' values.
                        let same = |values: &[f64]| values.iter().zip(&scalar).all(|(v, s)| v.to_bits() == s.0.to_bits());
                        let mut values = vec![f64::NAN; count];
                        gaussian_values_on_grid(p, t0, &mut values);
                        assert!(same(&values), "portable values: {shape:?} t0 {t0} count {count}");
                        values.fill(f64::NAN);
                        p.fill_values(t0, &mut values);
                        assert!(same(&values), "dispatched values: {shape:?} t0 {t0} count {count}");
                        // And the AVX2 copies, pairs and values, where the CPU has them.
                        #[cfg(target_arch = "x86_64")]
                        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                            let mut avx2 = vec![(0.0, 0.0); count];
                            // SAFETY: the CPU has AVX2 and FMA.
                            unsafe { gaussian_halves_on_grid_avx2(p, t0, &mut avx2) };
                            assert!(avx2.iter().zip(&scalar).all(|(a, b)| a.0.to_bits() == b.0.to_bits() && a.1.to_bits() == b.1.to_bits()), "AVX2 pairs: {shape:?} t0 {t0} count {count}");
                            values.fill(f64::NAN);
                            // SAFETY: as above.
                            unsafe { gaussian_values_on_grid_avx2(p, t0, &mut values) };
                            assert!(same(&values), "AVX2 values: {shape:?} t0 {t0} count {count}");
                        }
                    }
                    for (i, &(v, dv)) in out.iter().enumerate() {
                        let t = t0 + i as f64;
                        assert_eq!((v.to_bits(), dv.to_bits()), (scalar[i].0.to_bits(), scalar[i].1.to_bits()), "{shape:?} t {t}");
                        // And value_and_slope (libm): the reciprocal's
                        // rounding moves z by an ulp, the value by z² ulp.
                        let (ve, dve) = shape.value_and_slope(t);
                        let s = if t < 0.0 { shape_sigma(&shape).0 } else { shape_sigma(&shape).1 };
                        let z2 = (t / s).powi(2);
                        let tol = 5e-16 + 3e-16 * z2;
                        assert!((v - ve).abs() <= tol * ve.abs() + 1e-300, "{shape:?} t {t}: {v:e} vs {ve:e}");
                        assert!((dv - dve).abs() <= tol * dve.abs() + 1e-300, "{shape:?} t {t}: {dv:e} vs {dve:e}");
                    }
                }
            }
        }
    }

    fn shape_sigma(shape: &Shape) -> (f64, f64) {
        match shape {
            Shape::Parametric(p) => (p.sigma_rise, p.sigma_fall),
            Shape::Table(_) => unreachable!(),
        }
    }

    #[test]
    fn add_scaled_adds_inside_the_buffer_only() {
        let shape = Shape::Parametric(Pulse { sigma_rise: 2.0, sigma_fall: 5.0 });
        let mut x = vec![0.0; 50];
        // Past the end, empty, reversed-empty: nothing, and no panic.
        shape.add_scaled(60.0, 55..70, 1.0, &mut x);
        shape.add_scaled(10.0, 20..20, 1.0, &mut x);
        shape.add_scaled(10.0, 60..60, 1.0, &mut x);
        assert!(x.iter().all(|&v| v == 0.0));
        // Straddling the end: the part inside, at the right places.
        shape.add_scaled(48.0, 40..58, 2.0, &mut x);
        for (k, &v) in x.iter().enumerate() {
            let want = if k >= 40 { 2.0 * shape.value_and_slope(k as f64 - 48.0).0 } else { 0.0 };
            assert!((v - want).abs() <= 1e-15, "{k}: {v} vs {want}");
        }
    }

    /// `fill_grid` of `t` from `t0` is `eval` at t0, t0 + 1, … bit for bit
    /// (and so is the AVX-512 path called directly, where the CPU has it);
    /// returns that path's (eights read by phase, eights gathered).
    fn check_grid(t: &TablePulse, t0: f64, count: usize) -> (usize, usize) {
        let same = |out: &[(f64, f64)], path: &str| {
            for (i, &(v, dv)) in out.iter().enumerate() {
                let (ve, dve) = t.eval(t0 + i as f64);
                assert_eq!(
                    (v.to_bits(), dv.to_bits()),
                    (ve.to_bits(), dve.to_bits()),
                    "{path}: n {} step {} first {} t0 {t0:e} point {i}",
                    t.values.len(),
                    t.step,
                    t.first
                );
            }
        };
        let mut out = vec![(7.0, 7.0); count];
        t.fill_grid(t0, &mut out);
        same(&out, "fill_grid");
        #[cfg(target_arch = "x86_64")]
        if let Some(inv) = t.inv_step
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512dq")
            && std::arch::is_x86_feature_detected!("avx512vl")
            && std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
        {
            let mut out = vec![(7.0, 7.0); count];
            // SAFETY: the CPU has the features (checked just above).
            let reads = unsafe { t.fill_grid_avx512(t0, inv, &mut out) };
            same(&out, "fill_grid_avx512");
            // The AVX2 copy where the CPU has both: the same reads too.
            let mut out = vec![(7.0, 7.0); count];
            // SAFETY: AVX-512 implies AVX2.
            let lanes = unsafe { t.fill_grid_avx2(t0, inv, &mut out) };
            same(&out, "fill_grid_avx2");
            assert_eq!(lanes, reads, "the AVX2 copy reads as the AVX-512 one does");
            return reads;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(inv) = t.inv_step
            && std::arch::is_x86_feature_detected!("avx2")
        {
            let mut out = vec![(7.0, 7.0); count];
            // SAFETY: the CPU has AVX2 (checked just above).
            let reads = unsafe { t.fill_grid_avx2(t0, inv, &mut out) };
            same(&out, "fill_grid_avx2");
            return reads;
        }
        (0, 0)
    }

    #[test]
    fn a_table_on_the_grid_is_its_spline_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x7ab1e);
        // Steps of 1/128 … 4 samples: by phase from 1/64 to 1, gathered
        // beyond, and 0.3 (no power of two: the scalar spline).
        let steps = [0.0078125, 0.015625, 0.03125, 0.0625, 0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 0.3];
        let (mut by_phase, mut gathered_on_phased, mut phased_tables) = (0, 0, 0);
        for table in 0..440 {
            let step = steps[table % steps.len()];
            let n = if table % 7 == 0 { rng.random_range(4..8usize) } else { rng.random_range(4..=400usize) };
            let kind = rng.random_range(0..3);
            let values: Vec<f64> = (0..n)
                .map(|i| match kind {
                    0 => rng.random_range(-1.0..1.0),
                    // Zero tails, negative zeros in the leading one.
                    1 if i < n / 4 => -0.0,
                    1 if i > 3 * n / 4 => 0.0,
                    1 => (i as f64 * 0.37).sin(),
                    _ => (-(i as f64 - n as f64 / 2.0).powi(2) / n as f64).exp() + 1e-3 * rng.random_range(-1.0..1.0),
                })
                .collect();
            // Whole, fractional, non-dyadic near 1000 and near 2⁴⁰ (where
            // t0 + k rounds), and far out.
            let first = match rng.random_range(0..5) {
                0 => -(rng.random_range(0..50) as f64),
                1 => rng.random_range(-50.0..0.0),
                2 => 1000.0 + rng.random_range(-3.0..3.0f64).round() * 0.1,
                3 => (1u64 << 40) as f64 + rng.random_range(0..8) as f64 * 0.0625,
                _ => rng.random_range(-1e6..1e6),
            };
            let t = TablePulse::new(values, step, first);
            let span = (n - 1) as f64 * step;
            let mut starts = vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, -1e300, 0.0, first, first - 8.0, first + span, first + span - 8.0];
            for _ in 0..40 {
                let base = match rng.random_range(0..4) {
                    0 => first - 110.0 + (span + 120.0) * rng.random::<f64>(),
                    1 => first - rng.random_range(0..110) as f64,
                    2 => first + span - rng.random_range(0..110) as f64 + rng.random_range(-4.0..4.0f64).round() * step,
                    // On a cell boundary.
                    _ => first + rng.random_range(0..n) as f64 * step - rng.random_range(0..100) as f64,
                };
                // An ulp or two either side.
                let nudge = rng.random_range(-2..=2i64);
                starts.push((0..nudge.abs()).fold(base, |x, _| if nudge > 0 { x.next_up() } else { x.next_down() }));
            }
            for &t0 in &starts {
                let (phase, gather) = check_grid(&t, t0, rng.random_range(0..=100));
                if t.phased.is_some() {
                    by_phase += phase;
                    gathered_on_phased += gather;
                } else {
                    assert_eq!(phase, 0, "step {step}: no table by phase, none read by phase");
                }
            }
            phased_tables += usize::from(t.phased.is_some());
        }
        // t0 + k rounding across a cell boundary at 1000 (one step a sample):
        // the cells are not one phase apart, and the inputs are gathered.
        let t = TablePulse::new((0..64).map(|i| (i as f64 * 0.2).cos()).collect(), 1.0, 1000.0);
        let (_, gather) = check_grid(&t, 1000f64.next_down(), 48);
        // The sign of zero where u is −0 (t just below a subnormal `first`).
        check_grid(&TablePulse::new(vec![-0.0, -0.0, 0.0, 0.0, 0.0], 2.0, 5e-324), 0.0, 3);
        check_grid(&TablePulse::new(vec![-0.0, -0.0, 0.0, 0.0, 0.0], 0.5, 5e-324), 0.0, 9);
        // Where the CPU has AVX2 or AVX-512, both ways were taken (none elsewhere).
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            assert!(phased_tables > 100 && by_phase > 10_000, "{phased_tables} tables by phase, {by_phase} eights read so");
            assert!(gathered_on_phased > 0 && gather > 0, "the gather where the cells are not one phase apart: {gathered_on_phased}, {gather}");
        }
    }

    #[test]
    fn a_power_of_two_step_multiplies_to_the_division_bit_for_bit() {
        let values: Vec<f64> = (0..40).map(|i| (-(i as f64 - 12.0).powi(2) / 30.0).exp()).collect();
        for step in [0.25, 0.125, 2.0, 0.3] {
            let t = TablePulse::new(values.clone(), step, -3.0);
            // The spline as written with divisions.
            let divided = |x: f64| {
                let u = (x - t.first) / t.step;
                if !(u >= 0.0) || u >= (t.values.len() - 1) as f64 {
                    return (0.0, 0.0);
                }
                let i = u as usize;
                let s = u - i as f64;
                let (p0, p1) = (t.values[i], t.values[i + 1]);
                let (m0, m1) = (t.slopes[i] * t.step, t.slopes[i + 1] * t.step);
                let (s2, s3) = (s * s, s * s * s);
                let v = (2.0 * s3 - 3.0 * s2 + 1.0) * p0 + (s3 - 2.0 * s2 + s) * m0 + (-2.0 * s3 + 3.0 * s2) * p1 + (s3 - s2) * m1;
                let dv = (6.0 * s2 - 6.0 * s) * p0 + (3.0 * s2 - 4.0 * s + 1.0) * m0 + (-6.0 * s2 + 6.0 * s) * p1 + (3.0 * s2 - 2.0 * s) * m1;
                (v, dv / t.step)
            };
            let mut grid = vec![(0.0, 0.0); 50];
            t.fill_grid(-4.37, &mut grid);
            for (i, g) in grid.iter().enumerate() {
                let x = -4.37 + i as f64;
                let (a, b) = (t.value_and_slope(x), divided(x));
                assert_eq!((a.0.to_bits(), a.1.to_bits()), (b.0.to_bits(), b.1.to_bits()), "step {step} t {x}");
                assert_eq!(*g, a);
            }
        }
    }

    #[test]
    fn table_reproduces_the_shape_it_samples() {
        let p = Pulse { sigma_rise: 4.79, sigma_fall: 17.3 };
        let step = 0.125;
        let first = -30.0;
        let values: Vec<f64> = (0..800).map(|i| p.value_and_slope(first + i as f64 * step).0).collect();
        let t = Shape::Table(TablePulse::new(values, step, first));
        let shape = Shape::Parametric(p);
        for &x in &[-12.3, -5.64, -0.2, 0.0, 3.3, 20.7] {
            let (a, da) = t.value_and_slope(x);
            let (b, db) = shape.value_and_slope(x);
            assert!((a - b).abs() < 2e-4, "{x}: {a} vs {b}");
            assert!((da - db).abs() < 2e-3, "{x}: {da} vs {db}");
        }
        assert!((t.half_rise_offset() - shape.half_rise_offset()).abs() < 1e-3);
        assert!((t.fwhm() - shape.fwhm()).abs() < 1e-2);
    }


    #[test]
    fn bigaussian_matches_rise_and_fwhm() {
        let p = Pulse::bigaussian(8.08e-9, 26.04e-9, 1e-9);
        assert!((p.fwhm() - 26.04).abs() < 1e-9);
        let t10 = p.fraction_offset(0.1);
        let t90 = p.fraction_offset(0.9);
        assert!(((t90 - t10) - 8.08).abs() < 1e-9, "{}", t90 - t10);
        assert!((p.value_and_slope(p.half_rise_offset()).0 - 0.5).abs() < 1e-12);
    }

    #[test]
    fn slope_is_the_derivative() {
        let p = Pulse { sigma_rise: 2.0, sigma_fall: 7.0 };
        for &t in &[-5.0, -1.3, 0.4, 3.0, 11.0] {
            let h = 1e-6;
            let num = (p.value_and_slope(t + h).0 - p.value_and_slope(t - h).0) / (2.0 * h);
            assert!((num - p.value_and_slope(t).1).abs() < 1e-8);
        }
    }
}
