//! Exact accumulation for ensemble averages, and robust (trimmed-mean, median)
//! averages of a stack of frames.
//!
//! Named for what it does (accumulating frames) rather than `average`, which
//! is the pipeline stage built on it (`pipeline::average`).
//!
//! Integer ADC codes are summed in `i64`, which is exact for any realistic
//! number of frames: |code| ≤ 2^15 for i16, so 2^48 frames (~9 years at 1 MHz)
//! fit, and the mean is then formed once, correctly rounded
//! ([`mean_from_sums`](crate::dsp::accumulate::mean_from_sums)). The result
//! depends on the number of frames only through the 1/N scaling, never through
//! rounding of a running sum.
//!
//! The `add_*` kernels are written as fixed-size chunks so they auto-vectorise;
//! on x86-64 an AVX2 copy is chosen at run time.
//! [`CodeAccumulator`](crate::dsp::accumulate::CodeAccumulator) goes one
//! step further for narrow codes: it sums frames in `i32` lanes (half the
//! memory traffic and twice the SIMD width of `i64`) and flushes into the
//! `i64` totals before an `i32` could overflow.

use crate::math::select::trimmed_mean;

/// Lanes per chunk of the add kernels: one or two vector registers' worth.
const CHUNK: usize = 16;

/// Adds integer codes into i64 sums (exact for any number of frames below 2^47 of i16).
/// Adds `min(acc.len(), x.len())` samples.
pub fn add_codes_i16(acc: &mut [i64], x: &[i16]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { add_widen_avx2_i16(acc, x) };
        return;
    }
    add_widen(acc, x);
}

/// Adds i8 codes into i64 sums. Adds `min(acc.len(), x.len())` samples.
pub fn add_codes_i8(acc: &mut [i64], x: &[i8]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { add_widen_avx2_i8(acc, x) };
        return;
    }
    add_widen(acc, x);
}

/// Adds i32 codes into i64 sums. Adds `min(acc.len(), x.len())` samples.
pub fn add_codes_i32(acc: &mut [i64], x: &[i32]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { add_widen_avx2_i32(acc, x) };
        return;
    }
    add_widen(acc, x);
}

/// Adds f64 values into f64 sums. Adds `min(acc.len(), x.len())` samples.
pub fn add_f64(acc: &mut [f64], x: &[f64]) {
    let n = acc.len().min(x.len());
    let (acc, x) = (&mut acc[..n], &x[..n]);
    let mut ac = acc.chunks_exact_mut(CHUNK);
    let mut xc = x.chunks_exact(CHUNK);
    for (a, v) in (&mut ac).zip(&mut xc) {
        for i in 0..CHUNK {
            a[i] += v[i];
        }
    }
    for (a, v) in ac.into_remainder().iter_mut().zip(xc.remainder()) {
        *a += v;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_widen_avx2_i16(acc: &mut [i64], x: &[i16]) {
    add_widen(acc, x);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_widen_avx2_i8(acc: &mut [i64], x: &[i8]) {
    add_widen(acc, x);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_widen_avx2_i32(acc: &mut [i64], x: &[i32]) {
    add_widen(acc, x);
}

/// `acc[i] += x[i]` widening to the accumulator type, in fixed chunks so the
/// compiler emits packed sign-extensions and adds.
#[inline(always)]
fn add_widen<A, T>(acc: &mut [A], x: &[T])
where
    A: Copy + std::ops::AddAssign + From<T>,
    T: Copy,
{
    let n = acc.len().min(x.len());
    let (acc, x) = (&mut acc[..n], &x[..n]);
    let mut ac = acc.chunks_exact_mut(CHUNK);
    let mut xc = x.chunks_exact(CHUNK);
    for (a, v) in (&mut ac).zip(&mut xc) {
        for i in 0..CHUNK {
            a[i] += A::from(v[i]);
        }
    }
    for (a, &v) in ac.into_remainder().iter_mut().zip(xc.remainder()) {
        *a += A::from(v);
    }
}

/// Frames of i16 codes an i32 lane can take without overflow: 65 536·(−32 768)
/// = −2^31 = i32::MIN and 65 536·32 767 < i32::MAX.
pub const I16_FRAMES_PER_I32_FLUSH: u32 = 1 << 16;
/// Frames of i8 codes an i32 lane can take without overflow: 2^24·(−128) = −2^31.
pub const I8_FRAMES_PER_I32_FLUSH: u32 = 1 << 24;

/// Running exact sums of integer-code frames of one length.
///
/// i8 and i16 frames are added into `i32` partial sums, flushed into the `i64`
/// totals every [`I16_FRAMES_PER_I32_FLUSH`] (or [`I8_FRAMES_PER_I32_FLUSH`])
/// frames, the largest counts for which the partial sum cannot overflow; i32
/// frames go straight to `i64`. Everything is exact. Built once (it owns its
/// buffers); adding frames allocates nothing.
#[derive(Debug, Clone)]
pub struct CodeAccumulator {
    /// Exact totals of flushed frames.
    total: Vec<i64>,
    /// Partial sums since the last flush.
    partial: Vec<i32>,
    /// Budget left in `partial`, in units of 2^-24 of an i32 lane's range
    /// (an i16 frame costs 2^8, an i8 frame 1), so mixed widths stay safe.
    partial_budget: u64,
    /// Frames added since the last `reset`.
    frames: u64,
}

/// An i32 lane's capacity in the budget unit (2^24 i8 frames).
const PARTIAL_BUDGET: u64 = 1 << 24;

impl CodeAccumulator {
    /// An accumulator for frames of `len` samples.
    pub fn new(len: usize) -> CodeAccumulator {
        CodeAccumulator {
            total: vec![0; len],
            partial: vec![0; len],
            partial_budget: PARTIAL_BUDGET,
            frames: 0,
        }
    }

    /// Samples per frame.
    pub fn len(&self) -> usize {
        self.total.len()
    }

    /// True when frames have zero samples.
    pub fn is_empty(&self) -> bool {
        self.total.is_empty()
    }

    /// Frames added since construction or the last [`reset`](Self::reset).
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Forgets all frames.
    pub fn reset(&mut self) {
        self.total.fill(0);
        self.partial.fill(0);
        self.partial_budget = PARTIAL_BUDGET;
        self.frames = 0;
    }

    fn reserve(&mut self, cost: u64) {
        if self.partial_budget < cost {
            self.flush();
        }
        self.partial_budget -= cost;
    }

    fn flush(&mut self) {
        add_codes_i32(&mut self.total, &self.partial);
        self.partial.fill(0);
        self.partial_budget = PARTIAL_BUDGET;
    }

    /// Adds one frame of i16 codes (the first `min(len, x.len())` samples; a
    /// shorter frame adds nothing to the rest).
    pub fn add_i16(&mut self, x: &[i16]) {
        self.reserve(PARTIAL_BUDGET / I16_FRAMES_PER_I32_FLUSH as u64);
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { add_i32_avx2_i16(&mut self.partial, x) };
            self.frames += 1;
            return;
        }
        add_widen(&mut self.partial, x);
        self.frames += 1;
    }

    /// Adds one frame of i8 codes (see [`add_i16`](Self::add_i16)).
    pub fn add_i8(&mut self, x: &[i8]) {
        self.reserve(PARTIAL_BUDGET / I8_FRAMES_PER_I32_FLUSH as u64);
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { add_i32_avx2_i8(&mut self.partial, x) };
            self.frames += 1;
            return;
        }
        add_widen(&mut self.partial, x);
        self.frames += 1;
    }

    /// Adds one frame of i32 codes (straight into the i64 totals).
    pub fn add_i32(&mut self, x: &[i32]) {
        add_codes_i32(&mut self.total, x);
        self.frames += 1;
    }

    /// The exact per-sample sums of all frames added so far.
    pub fn sums(&mut self) -> &[i64] {
        if self.partial_budget < PARTIAL_BUDGET {
            self.flush();
        }
        &self.total
    }

    /// Writes the per-sample mean in volts (see [`mean_from_sums`]); `out`
    /// should have [`len`](Self::len) samples.
    pub fn mean_v(&mut self, volts_per_code: f64, offset_v: f64, out: &mut [f64]) {
        let n = self.frames;
        mean_from_sums(self.sums(), n, volts_per_code, offset_v, out);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_i32_avx2_i8(acc: &mut [i32], x: &[i8]) {
    add_widen(acc, x);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn add_i32_avx2_i16(acc: &mut [i32], x: &[i16]) {
    add_widen(acc, x);
}

/// Writes `offset_v + volts_per_code · (acc[i] / n)` to `out[i]`, where the
/// mean of codes `acc[i] / n` is the exact quotient correctly rounded to f64
/// (not the f64 sum divided by f64 n, which rounds twice once |sum| > 2^53).
/// Processes `min(acc.len(), out.len())` samples.
///
/// Precondition: `n > 0` (the pipeline never averages zero frames). With
/// `n == 0` there is no mean: `out` is filled with NaN so the mistake cannot
/// pass as data (and debug builds panic).
pub fn mean_from_sums(acc: &[i64], n: u64, volts_per_code: f64, offset_v: f64, out: &mut [f64]) {
    debug_assert!(n > 0, "mean of zero frames");
    for (o, &s) in out.iter_mut().zip(acc) {
        *o = if n == 0 {
            f64::NAN
        } else {
            offset_v + volts_per_code * div_round(s, n)
        };
    }
}

/// `s / n` correctly rounded (to nearest, ties to even). `n > 0`.
pub fn div_round(s: i64, n: u64) -> f64 {
    if s == 0 {
        return 0.0;
    }
    if n == 1 {
        return s as f64; // the conversion itself rounds correctly
    }
    let a = s.unsigned_abs() as u128;
    let d = n as u128;
    let bits = |v: u128| 128 - v.leading_zeros() as i32;
    // Scale so the integer quotient has 54 or 55 bits: one or two more than
    // f64's 53-bit significand, the extra bits (and the remainder) deciding
    // the rounding. With a, d < 2^64 the scaled numerator has < 119 bits.
    let k = 54 - (bits(a) - bits(d));
    let (num, den) = if k >= 0 { (a << k, d) } else { (a, d << -k) };
    let q = num / den;
    let sticky = num % den != 0;
    let extra = bits(q) - 53;
    debug_assert!((1..=2).contains(&extra));
    let mut m = q >> extra;
    let dropped = q & ((1u128 << extra) - 1);
    let half = 1u128 << (extra - 1);
    if dropped > half || (dropped == half && (sticky || m & 1 == 1)) {
        m += 1; // may reach 2^53, still exact in f64
    }
    // m·2^(extra − k) with extra − k in [−116, 11]: a normal power of two.
    let e = extra - k;
    let scale = f64::from_bits(((e + 1023) as u64) << 52);
    let v = m as f64 * scale;
    if s < 0 { -v } else { v }
}

/// Robust per-sample average of a stack of frames: `out[i]` is the
/// [`trimmed_mean`] of `frames[f][i]` over all frames (`trim_fraction` 0: the
/// mean, 0.5: the median). Processes as many samples as the shortest frame and
/// `out` have. `scratch` is reused across calls (allocates only until it has
/// `frames.len()` capacity). With no frames there is no average: `out` is
/// filled with NaN.
pub fn robust_average(
    frames: &[&[f64]],
    trim_fraction: f64,
    out: &mut [f64],
    scratch: &mut Vec<f64>,
) {
    robust_average_of(frames.iter().copied(), trim_fraction, out, scratch);
}

/// [`robust_average`] of the frames `frames` yields (the iterator is cloned
/// once per sample), for frames that are not in one slice: nothing is
/// collected, so nothing is allocated once `scratch` has grown.
pub fn robust_average_of<'a>(
    frames: impl Iterator<Item = &'a [f64]> + Clone,
    trim_fraction: f64,
    out: &mut [f64],
    scratch: &mut Vec<f64>,
) {
    let Some(len) = frames.clone().map(|f| f.len()).min() else {
        out.fill(f64::NAN);
        return;
    };
    let len = len.min(out.len());
    for (i, o) in out[..len].iter_mut().enumerate() {
        scratch.clear();
        scratch.extend(frames.clone().map(|f| f[i]));
        *o = trimmed_mean(scratch, trim_fraction).unwrap_or(f64::NAN);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn div_round_matches_exact_rationals() {
        // Exact cases and a hand-checked rounding case.
        assert_eq!(div_round(7, 2), 3.5);
        assert_eq!(div_round(-7, 2), -3.5);
        assert_eq!(div_round(1, 3), 1.0 / 3.0);
        assert_eq!(div_round(i64::MAX, 1), i64::MAX as f64);
        assert_eq!(div_round(i64::MIN, 1), i64::MIN as f64);
        // (2^53 + 1)·2 / 2 = 2^53 + 1 is a tie between 2^53 and 2^53 + 2: even wins.
        assert_eq!(div_round(((1i64 << 53) + 1) * 2, 2), (1u64 << 53) as f64);
        // (2^53 + 3) ties to 2^53 + 4.
        assert_eq!(
            div_round(((1i64 << 53) + 3) * 2, 2),
            ((1u64 << 53) + 4) as f64
        );
        // Just above the tie: rounds up.
        assert_eq!(
            div_round(((1i64 << 53) + 1) * 3 + 1, 3),
            ((1u64 << 53) + 2) as f64
        );
    }

    /// The portable widening loop (the AVX2 copies run the same code).
    #[test]
    fn portable_widening_matches_plain_loop() {
        let x: Vec<i16> = (0..37).map(|i| (i * 1777 - 30_000) as i16).collect();
        let mut a = vec![1i64; 40];
        add_widen(&mut a, &x);
        let mut b = vec![0i32; 37];
        add_widen(&mut b, &x);
        for i in 0..37 {
            assert_eq!(a[i], 1 + x[i] as i64);
            assert_eq!(b[i], x[i] as i32);
        }
        assert_eq!(&a[37..], &[1, 1, 1]);
    }
}
