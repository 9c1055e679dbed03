//! Digitiser: quantisation to integer codes over the full scale, clipping,
//! and sampling of a fine-grid waveform with trigger and aperture jitter.
//!
//! Codes are two's-complement: `bits` resolution maps the lowest code
//! `−2^(bits−1)` to `full_scale_low_v` and the highest `2^(bits−1) − 1` to
//! `full_scale_high_v`, so `volts = code · volts_per_code + offset_v` exactly
//! as `frame::Channel` defines it. Values beyond either end clip to the end
//! code (the analogue front end saturates).

use crate::frame::Samples;

/// Maps volts to codes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quantiser {
    /// Resolution, bits.
    pub bits: u32,
    /// Volts per code step.
    pub volts_per_code: f64,
    /// Volts at code 0.
    pub offset_v: f64,
    /// 1 / volts_per_code (the hot loop multiplies).
    codes_per_volt: f64,
    /// Lowest code.
    pub code_min: i32,
    /// Highest code.
    pub code_max: i32,
}

impl Quantiser {
    /// A quantiser for `bits` over `[low_v, high_v]`.
    pub fn new(bits: u32, low_v: f64, high_v: f64) -> Quantiser {
        let levels = (1u64 << bits) as f64;
        let code_min = -(1i32 << (bits - 1));
        let code_max = (1i32 << (bits - 1)) - 1;
        let vpc = (high_v - low_v) / (levels - 1.0);
        Quantiser {
            bits,
            volts_per_code: vpc,
            offset_v: low_v - code_min as f64 * vpc,
            codes_per_volt: 1.0 / vpc,
            code_min,
            code_max,
        }
    }

    /// The code for `v` (rounded to nearest, clipped to the range; NaN → lowest code).
    #[inline]
    pub fn code(&self, v: f64) -> i32 {
        let x = (v - self.offset_v) * self.codes_per_volt;
        if x.is_nan() {
            return self.code_min;
        }
        // Round half up without a libm call (`f64::round` is not inlined on the
        // portable x86-64 baseline): clamp, shift by +0.5, floor via truncation.
        let c = x.clamp(self.code_min as f64 - 1.0, self.code_max as f64 + 1.0) + 0.5;
        let mut i = c as i32;
        if (i as f64) > c {
            i -= 1;
        }
        i.clamp(self.code_min, self.code_max)
    }

    /// Volts of a code.
    pub fn volts(&self, code: i32) -> f64 {
        code as f64 * self.volts_per_code + self.offset_v
    }

    /// True if `v` is at or beyond either end of the range.
    pub fn clips(&self, v: f64) -> bool {
        let c = self.code(v);
        c == self.code_min || c == self.code_max
    }

    /// Quantises a waveform to codes (`I8` for ≤ 8 bits, else `I16`).
    pub fn quantise(&self, v: &[f64]) -> Samples {
        if self.bits <= 8 {
            Samples::I8(v.iter().map(|&x| self.code(x) as i8).collect())
        } else {
            Samples::I16(v.iter().map(|&x| self.code(x) as i16).collect())
        }
    }
}

/// A noise-free waveform on a uniform fine grid, sampled by linear interpolation.
#[derive(Debug, Clone, Default)]
pub struct FineWave {
    /// Time of the first fine sample relative to the trigger, s.
    pub t0_s: f64,
    /// Fine step, s.
    pub h_s: f64,
    /// Values, V.
    pub v: Vec<f64>,
}

impl FineWave {
    /// Value at time `t_s` by linear interpolation; outside the grid, the
    /// edge value (grids are built to cover every instant that is sampled).
    #[inline]
    pub fn at(&self, t_s: f64) -> f64 {
        let x = (t_s - self.t0_s) / self.h_s;
        let n = self.v.len();
        if n == 0 {
            return 0.0;
        }
        if x <= 0.0 {
            return self.v[0];
        }
        let i = x.floor() as usize;
        if i + 1 >= n {
            return self.v[n - 1];
        }
        let f = x - i as f64;
        self.v[i] + f * (self.v[i + 1] - self.v[i])
    }

    /// Slope at time `t_s`, V/s (finite difference of the bracketing fine samples).
    #[inline]
    pub fn slope(&self, t_s: f64) -> f64 {
        let x = (t_s - self.t0_s) / self.h_s;
        let n = self.v.len();
        if n < 2 || x <= 0.0 {
            return 0.0;
        }
        let i = x.floor() as usize;
        if i + 1 >= n {
            return 0.0;
        }
        (self.v[i + 1] - self.v[i]) / self.h_s
    }

    /// Samples at `t0 + k dt` into `out` (aperture jitter handled by the caller).
    /// When `dt` is a whole number of fine steps (the simulator's grids are)
    /// every sample shares one interpolation fraction, so no per-sample
    /// division or floor is needed.
    pub fn sample_into(&self, t0_s: f64, dt_s: f64, out: &mut [f64]) {
        let ratio = dt_s / self.h_s;
        let stride = ratio.round();
        let x0 = (t0_s - self.t0_s) / self.h_s;
        let n = self.v.len();
        let last_x = x0 + stride * out.len().saturating_sub(1) as f64;
        if (ratio - stride).abs() > 1e-9 * ratio || x0 < 0.0 || last_x + 1.0 >= n as f64 || n < 2 {
            for (k, o) in out.iter_mut().enumerate() {
                *o = self.at(t0_s + k as f64 * dt_s);
            }
            return;
        }
        let i0 = x0.floor() as usize;
        let f = x0 - i0 as f64;
        let stride = stride as usize;
        for (k, o) in out.iter_mut().enumerate() {
            let i = i0 + k * stride;
            *o = self.v[i] + f * (self.v[i + 1] - self.v[i]);
        }
    }
}
