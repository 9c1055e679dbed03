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
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            if has!("avx512f") && has!("avx512dq") && has!("avx512vl") && has!("avx2") && has!("fma") {
                // SAFETY: the CPU has the features the function is compiled for.
                unsafe { gaussian_halves_on_grid_avx512(self, t0, out) };
                return;
            }
            if has!("avx2") && has!("fma") {
                // SAFETY: as above.
                unsafe { gaussian_halves_on_grid_avx2(self, t0, out) };
                return;
            }
        }
        gaussian_halves_on_grid(self, t0, out);
    }
}

/// (value, slope) at `t` of a Gaussian of 1/sigma `inv`.
#[inline(always)]
fn gaussian_half(inv: f64, t: f64) -> (f64, f64) {
    let z = t * inv;
    let v = exp(-0.5 * z * z);
    (v, -v * z * inv)
}

/// (value, slope) of `p` at t0, t0 + 1, … into `out`, with
/// [`crate::math::exp::exp`] (exactly rounded operations, so scalar
/// and vectorised give the same bits; without hardware FMA, slowly) and the sigmas' reciprocals: within a few ulp of
/// [`Pulse::value_and_slope`] (libm's `exp` and two divisions) near the
/// peak, growing with z² in the tails (z·2e-16 in z, times z² in the value).
#[inline(always)]
fn gaussian_halves_on_grid(p: &Pulse, t0: f64, out: &mut [(f64, f64)]) {
    // Opaque to the optimiser: otherwise it turns the choice between two
    // reciprocals into a division per point (of the chosen sigma), the
    // same bits at many times the cost.
    let (rise, fall) = std::hint::black_box((1.0 / p.sigma_rise, 1.0 / p.sigma_fall));
    let first = out.len() - out.len() % 8;
    let mut eights = out.chunks_exact_mut(8);
    for (c, o) in eights.by_ref().enumerate() {
        for (i, o) in o.iter_mut().enumerate() {
            let t = t0 + (8 * c + i) as f64;
            *o = gaussian_half(if t < 0.0 { rise } else { fall }, t);
        }
    }
    // The last few points as a whole eight (the same bits, vectorised too)
    // rather than one at a time: a fit's window is seldom a multiple of eight.
    // (The point's expression is written out in both loops: shared as a
    // closure, it stopped both vectorising, 25 % slower on reference frames.)
    let rest = eights.into_remainder();
    if !rest.is_empty() {
        let mut eight = [(0.0, 0.0); 8];
        for (i, o) in eight.iter_mut().enumerate() {
            let t = t0 + (first + i) as f64;
            *o = gaussian_half(if t < 0.0 { rise } else { fall }, t);
        }
        rest.copy_from_slice(&eight[..rest.len()]);
    }
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
}

impl TablePulse {
    /// From values every `step` samples, the first at `first` samples from the peak.
    /// Needs at least 4 values.
    pub fn new(values: Vec<f64>, step: f64, first: f64) -> TablePulse {
        let n = values.len();
        let slopes = (0..n)
            .map(|i| {
                let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
                (values[b] - values[a]) / ((b - a).max(1) as f64 * step)
            })
            .collect();
        let inv = 1.0 / step;
        let power_of_two = step.is_normal() && inv.is_normal() && step.to_bits() & ((1u64 << 52) - 1) == 0;
        TablePulse { step, first, values, slopes, inv_step: power_of_two.then_some(inv) }
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
    /// truncation `eval` takes), read off the bits of floor(u) + 2⁵².
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,fma")]
    fn fill_grid_avx512(&self, t0: f64, inv: f64, out: &mut [(f64, f64)]) {
        const L: usize = 8;
        const TWO_52: f64 = 4_503_599_627_370_496.0;
        let (values, slopes, step, first) = (&self.values[..], &self.slopes[..], self.step, self.first);
        let n = values.len();
        let top = (n - 1) as f64;
        let mut chunks = out.chunks_exact_mut(L);
        let mut k0 = 0usize;
        for chunk in &mut chunks {
            let mut ok = [false; L];
            let mut s = [0.0f64; L];
            let (mut p0, mut p1, mut m0, mut m1) = ([0.0f64; L], [0.0f64; L], [0.0f64; L], [0.0f64; L]);
            for l in 0..L {
                let u = (t0 + (k0 + l) as f64 - first) * inv;
                ok[l] = u >= 0.0 && u < top;
                let fl = if ok[l] { u.floor() } else { 0.0 };
                s[l] = u - fl;
                // fl is an integer in [0, n − 2]: its low bits after adding 2⁵².
                let i = ((fl + TWO_52).to_bits() as u32 as usize).min(n - 2);
                p0[l] = values[i];
                p1[l] = values[i + 1];
                m0[l] = slopes[i] * step;
                m1[l] = slopes[i + 1] * step;
            }
            for l in 0..L {
                let s = s[l];
                let (s2, s3) = (s * s, s * s * s);
                let v = (2.0 * s3 - 3.0 * s2 + 1.0) * p0[l] + (s3 - 2.0 * s2 + s) * m0[l] + (-2.0 * s3 + 3.0 * s2) * p1[l] + (s3 - s2) * m1[l];
                let dv = (6.0 * s2 - 6.0 * s) * p0[l] + (3.0 * s2 - 4.0 * s + 1.0) * m0[l] + (-6.0 * s2 + 6.0 * s) * p1[l] + (3.0 * s2 - 2.0 * s) * m1[l];
                chunk[l] = if ok[l] { (v, dv * inv) } else { (0.0, 0.0) };
            }
            k0 += L;
        }
        for (i, o) in chunks.into_remainder().iter_mut().enumerate() {
            *o = self.eval(t0 + (k0 + i) as f64);
        }
    }
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
                        // And the AVX2 copy, where the CPU has it.
                        #[cfg(target_arch = "x86_64")]
                        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                            let mut avx2 = vec![(0.0, 0.0); count];
                            // SAFETY: the CPU has AVX2 and FMA.
                            unsafe { gaussian_halves_on_grid_avx2(p, t0, &mut avx2) };
                            assert!(avx2.iter().zip(&scalar).all(|(a, b)| a.0.to_bits() == b.0.to_bits() && a.1.to_bits() == b.1.to_bits()));
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

    #[test]
    fn a_table_on_the_grid_is_its_spline_bit_for_bit() {
        let values: Vec<f64> = (0..333).map(|i| (-(i as f64 - 100.0).powi(2) / 900.0).exp() * (1.0 + 0.01 * (i as f64 * 0.7).sin())).collect();
        for step in [0.125, 0.25, 0.3] {
            let t = TablePulse::new(values.clone(), step, -12.5);
            for t0 in [-80.37, -13.0, -12.5, -12.51, -3.5, -0.25, 0.0, 2.9, 1e-17, 28.9, 40.0, f64::NAN] {
                for count in [0, 3, 8, 61, 150] {
                    let mut out = vec![(7.0, 7.0); count];
                    t.fill_grid(t0, &mut out);
                    for (i, &(v, dv)) in out.iter().enumerate() {
                        let (ve, dve) = t.eval(t0 + i as f64);
                        assert_eq!((v.to_bits(), dv.to_bits()), (ve.to_bits(), dve.to_bits()), "step {step} t0 {t0} point {i}");
                    }
                }
            }
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
