//! Parametric pulse shapes in units of samples, peak 1 at t = 0.

use crate::scene::{PulseConfig, PulseModel};

/// sqrt(2 ln 2): half width at half maximum of a unit-sigma Gaussian.
const HWHM_PER_SIGMA: f64 = 1.177_410_022_515_474_6;
/// sqrt(2 ln 10) - sqrt(2 ln(10/9)): 10-90 % rise of a unit-sigma Gaussian edge.
const RISE_PER_SIGMA: f64 = 1.686_922_421_262_926_4;

/// A shape evaluated at continuous time (in samples).
pub trait PulseShape {
    /// Value and derivative (per sample) at `t`.
    fn value_and_slope(&self, t: f64) -> (f64, f64);
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
    /// Builds the shape from a scene pulse at sampling period `dt_s`.
    pub fn from_config(cfg: &PulseConfig, dt_s: f64) -> Pulse {
        match cfg.model {
            PulseModel::Gaussian => {
                let s = cfg.fwhm_s / (2.0 * HWHM_PER_SIGMA) / dt_s;
                Pulse { sigma_rise: s, sigma_fall: s }
            }
            PulseModel::Bigaussian => {
                let sr = cfg.rise_time_s / RISE_PER_SIGMA;
                let sf = (cfg.fwhm_s - HWHM_PER_SIGMA * sr) / HWHM_PER_SIGMA;
                Pulse { sigma_rise: sr / dt_s, sigma_fall: sf / dt_s }
            }
        }
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bigaussian_matches_rise_and_fwhm() {
        let cfg = PulseConfig { model: PulseModel::Bigaussian, rise_time_s: 8.08e-9, fwhm_s: 26.04e-9 };
        let p = Pulse::from_config(&cfg, 1e-9);
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
