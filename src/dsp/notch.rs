//! Plain linear filters for interference: second-order notch and high-pass
//! sections (RBJ audio-EQ-cookbook biquads), run forward and backward so the
//! result has zero phase (no timing bias) and the squared magnitude response.
//!
//! They are the baseline the template canceller is compared with: the burst's
//! modes sit in the same band as the return, so any filter that removes them
//! also removes part of the return.

use std::f64::consts::PI;

/// One second-order section, `a0` normalised to 1 (transposed direct form II).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Biquad {
    b: [f64; 3],
    a: [f64; 2],
}

impl Biquad {
    /// Notch at `f_hz` with quality factor `q` (centre / −3 dB bandwidth), sampled every `dt_s`.
    pub fn notch(f_hz: f64, q: f64, dt_s: f64) -> Biquad {
        let w = 2.0 * PI * f_hz * dt_s;
        let alpha = w.sin() / (2.0 * q);
        let a0 = 1.0 + alpha;
        Biquad {
            b: [1.0 / a0, -2.0 * w.cos() / a0, 1.0 / a0],
            a: [-2.0 * w.cos() / a0, (1.0 - alpha) / a0],
        }
    }

    /// Second-order high-pass at `f_hz` with quality factor `q` (1/√2: Butterworth).
    pub fn highpass(f_hz: f64, q: f64, dt_s: f64) -> Biquad {
        let w = 2.0 * PI * f_hz * dt_s;
        let alpha = w.sin() / (2.0 * q);
        let c = w.cos();
        let a0 = 1.0 + alpha;
        Biquad {
            b: [(1.0 + c) / 2.0 / a0, -(1.0 + c) / a0, (1.0 + c) / 2.0 / a0],
            a: [-2.0 * c / a0, (1.0 - alpha) / a0],
        }
    }

    /// Gain at DC.
    pub fn dc_gain(&self) -> f64 {
        let den = 1.0 + self.a[0] + self.a[1];
        if den == 0.0 {
            0.0
        } else {
            (self.b[0] + self.b[1] + self.b[2]) / den
        }
    }

    /// Filters `x` in place, starting from the steady state of a constant input
    /// equal to the first sample (so a frame's offset causes no start-up transient).
    fn run(&self, x: &mut [f64]) {
        let Some(&u) = x.first() else { return };
        let g = self.dc_gain();
        let mut z2 = (self.b[2] - self.a[1] * g) * u;
        let mut z1 = (self.b[1] - self.a[0] * g) * u + z2;
        for v in x.iter_mut() {
            let xin = *v;
            let y = self.b[0] * xin + z1;
            z1 = self.b[1] * xin - self.a[0] * y + z2;
            z2 = self.b[2] * xin - self.a[1] * y;
            *v = y;
        }
    }
}

/// A cascade of sections run forward then backward (zero phase).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ZeroPhaseFilter {
    sections: Vec<Biquad>,
}

impl ZeroPhaseFilter {
    /// Notches at each of `freqs_hz`.
    pub fn notches(freqs_hz: &[f64], q: f64, dt_s: f64) -> ZeroPhaseFilter {
        ZeroPhaseFilter {
            sections: freqs_hz
                .iter()
                .map(|&f| Biquad::notch(f, q, dt_s))
                .collect(),
        }
    }

    /// A second-order Butterworth high-pass (fourth order after the backward pass).
    pub fn highpass(f_hz: f64, dt_s: f64) -> ZeroPhaseFilter {
        ZeroPhaseFilter {
            sections: vec![Biquad::highpass(
                f_hz,
                std::f64::consts::FRAC_1_SQRT_2,
                dt_s,
            )],
        }
    }

    /// Filters `x` in place: every section forward, then every section backward.
    pub fn apply(&self, x: &mut [f64]) {
        for s in &self.sections {
            s.run(x);
        }
        x.reverse();
        for s in &self.sections {
            s.run(x);
        }
        x.reverse();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gain_at(f: &ZeroPhaseFilter, f_hz: f64, dt: f64) -> f64 {
        // Steady-state amplitude of a long sine, measured in the middle.
        let n = 200_000;
        let mut x: Vec<f64> = (0..n)
            .map(|i| (2.0 * PI * f_hz * dt * i as f64).sin())
            .collect();
        f.apply(&mut x);
        let mid = &x[n / 4..3 * n / 4];
        (2.0 * mid.iter().map(|v| v * v).sum::<f64>() / mid.len() as f64).sqrt()
    }

    #[test]
    fn notch_removes_its_frequency_and_passes_others() {
        let dt = 1e-9;
        let f = ZeroPhaseFilter::notches(&[3.1e6], 5.0, dt);
        assert!(gain_at(&f, 3.1e6, dt) < 1e-3);
        assert!((gain_at(&f, 50e6, dt) - 1.0).abs() < 1e-3);
        let h = ZeroPhaseFilter::highpass(10e6, dt);
        // Butterworth forward + backward: |H|² = 1/2 at the corner.
        assert!((gain_at(&h, 10e6, dt) - 0.5).abs() < 1e-2);
        assert!(gain_at(&h, 1e6, dt) < 1e-3);
    }
}
