//! e^x in exactly rounded arithmetic, inlined: the same bits wherever it
//! runs, in a loop the compiler may vectorise, and no call into libm.
//!
//! The pulse shapes evaluate a Gaussian for every sample of every fit window
//! (`exp(-z²/2)`): with libm's `exp` a call, its error-handling wrapper and,
//! in the far tails, its underflow path each time, that was about a seventh
//! of a reference frame's time. This is fdlibm's argument reduction
//! (x = k ln 2 + r, |r| ≤ ln 2 / 2, with ln 2 split so that k·ln2_hi is
//! exact) and the Taylor series of e^r to r¹³ (truncation below 5e-18
//! relative, by Estrin's scheme), 2^k put into the exponent field. Every
//! operation is an IEEE multiply, add or fused multiply-add, each exactly
//! rounded, and there is no table: the result is the same bits on every CPU
//! and in scalar or vector code. The fused multiply-adds run in hardware
//! where the caller is compiled for FMA (the vectorised callers are: see
//! `dsp::pulse`); elsewhere they are libm's software `fma`, correct and slow.
//!
//! Accuracy: within 2 ulp of the correctly rounded value (checked below
//! against libm over the whole range; 1 ulp measured). Range: x < −708.39
//! gives +0 (e^x is subnormal below −708.396: flushed to zero, and the few
//! normal results in between too); x > 709 gives +∞ (exact e^x overflows at
//! 709.78); NaN gives NaN.

/// 1 / ln 2.
const INV_LN2: f64 = std::f64::consts::LOG2_E;
/// ln 2, high part: its low 21 mantissa bits are zero, so k·LN2_HI is exact for |k| < 2^21.
const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
/// ln 2 − LN2_HI.
const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
/// 1.5 · 2^52: adding it rounds to an integer (ties to even) and leaves the
/// integer in the low mantissa bits.
const SHIFT: f64 = 6_755_399_441_055_744.0;
/// Below this the answer is +0 (e^x itself is subnormal below −708.396;
/// at −708.39 the reduction still has k = −1022 and r > 0, a normal result).
const LOWEST: f64 = -708.39;
/// Above this 2^k would need k > 1023.
const HIGHEST: f64 = 709.0;

/// e^x (see the module doc for accuracy and range).
#[inline(always)]
pub fn exp(x: f64) -> f64 {
    let xc = x.clamp(LOWEST, HIGHEST);
    let t = xc.mul_add(INV_LN2, SHIFT);
    let k = t - SHIFT;
    let ki = (t.to_bits() as i64).wrapping_sub(SHIFT.to_bits() as i64);
    let r = (-k).mul_add(LN2_LO, (-k).mul_add(LN2_HI, xc));
    let r2 = r * r;
    let r4 = r2 * r2;
    let a = r2.mul_add(r.mul_add(1.0 / 120.0, 1.0 / 24.0), r.mul_add(1.0 / 6.0, 1.0 / 2.0));
    let b = r2.mul_add(r.mul_add(1.0 / 362_880.0, 1.0 / 40_320.0), r.mul_add(1.0 / 5_040.0, 1.0 / 720.0));
    let c = r2.mul_add(r.mul_add(1.0 / 6_227_020_800.0, 1.0 / 479_001_600.0), r.mul_add(1.0 / 39_916_800.0, 1.0 / 3_628_800.0));
    let p = r4.mul_add(r4.mul_add(c, b), a);
    let er = 1.0 + r2.mul_add(p, r);
    let y = er * f64::from_bits(((ki + 1023) as u64) << 52);
    if x < LOWEST {
        0.0
    } else if x > HIGHEST {
        f64::INFINITY
    } else if x.is_nan() {
        x
    } else {
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in units in the last place between two positive normals.
    fn ulps(a: f64, b: f64) -> u64 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs()
    }

    #[test]
    fn within_two_ulp_of_libm_over_the_range() {
        // libm's exp is within 1 ulp (glibc: correctly rounded in practice),
        // so 2 ulp here bounds ours at 3 ulp of the truth at worst.
        let mut worst = 0;
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for i in 0..2_000_000u64 {
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            let u = (state >> 11) as f64 / (1u64 << 53) as f64;
            // Half the points over the whole range, half near 0 where the
            // Gaussians' values live.
            let x = if i % 2 == 0 { LOWEST + u * (HIGHEST - LOWEST) } else { -40.0 + u * 41.0 };
            let d = ulps(exp(x), x.exp());
            worst = worst.max(d);
            assert!(d <= 2, "x = {x:e}: {:e} vs libm {:e}", exp(x), x.exp());
        }
        assert!(worst >= 1, "compared nothing");
    }

    #[test]
    fn edges_and_exact_points() {
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-0.0), 1.0);
        assert_eq!(exp(-708.4), 0.0);
        assert_eq!(exp(-1e300), 0.0);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert_eq!(exp(709.5), f64::INFINITY);
        assert_eq!(exp(f64::INFINITY), f64::INFINITY);
        assert!(exp(f64::NAN).is_nan());
        // The last normal results, and either side of the clamps.
        assert!(ulps(exp(-708.3), (-708.3f64).exp()) <= 2);
        assert!(ulps(exp(-708.39), (-708.39f64).exp()) <= 2);
        assert!(exp(-708.39) >= f64::MIN_POSITIVE);
        assert!(ulps(exp(709.0), 709f64.exp()) <= 2);
        for x in [1.0, -1.0, 0.5 * std::f64::consts::LN_2, -0.5 * std::f64::consts::LN_2, 1e-300, -1e-17, 36.0, -745.0 + 40.0] {
            assert!(ulps(exp(x), x.exp()) <= 2, "{x}");
        }
    }
}
