//! Cross-correlation of a signal with a fixed template ("valid" part only).
//!
//! Two methods compute the same thing, `out[k] = Σ_j taps[j]·x[k + j]`:
//!
//! * **Direct**: a block of output samples is accumulated at once (an
//!   outer-product form: for each tap, `acc[b] += taps[j]·x[k + j + b]`), so the
//!   inner loop is a fixed-length vector update the compiler turns into SIMD.
//!   On x86-64 an AVX2+FMA (or AVX-512) copy of the same loop is chosen at run
//!   time, so the shipped binary stays portable (no `target-cpu=native`).
//! * **FFT overlap-save** with `realfft`: the template spectrum is computed once;
//!   each block of `n` input samples yields `n - taps.len() + 1` outputs.
//!
//! [`Correlator::new`](crate::dsp::correlate::Correlator::new) picks the
//! cheaper one from a cost model (see
//! [`estimated_cost_ns`](crate::dsp::correlate::estimated_cost_ns)) whose
//! constants were measured on the development machine;
//! [`Correlator::with_method`](crate::dsp::correlate::Correlator::with_method)
//! forces one.

use std::sync::Arc;

use realfft::num_complex::Complex;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};

/// How the correlation is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorrelationMethod {
    /// Direct sum per output sample.
    Direct,
    /// FFT overlap-save.
    Fft,
}

// Cost model, nanoseconds. Measured on the development machine (a shared
// 2-core Xeon VM with AVX-512, release build, best of 7 × 200 runs on a
// 2500-sample input, while other builds ran — so ±15 %):
// * direct: 0.047 ns per multiply-accumulate with the AVX-512 loop, 0.056 with
//   AVX2+FMA, 0.10 with the portable (SSE2) loop, plus ~0.1 ns per output;
//   e.g. 64 taps: 7.5 µs, 160 taps: 17.7 µs (AVX-512). Past ~180 taps the
//   AVX-512 loop slows to 0.08–0.09 ns per MAC (200 taps: 42 µs, 300 taps:
//   51 µs; cause not investigated), which only strengthens the FFT choice
//   there, so the model keeps the short-template figure;
// * one overlap-save block of length n (forward + inverse realfft, spectrum
//   product, copies): ~0.29·n·log2(n) + 0.3·n ns, e.g. n = 256: 0.61 µs,
//   n = 1024: 3.0 µs, n = 4096: 14 µs; 3·2^k and 5·2^k cost 0–11 % more per
//   n·log2(n) (n = 768: 2.1 µs, 1536: 5.3 µs, 2560: 8.4 µs) but lengths with
//   more odd factors much more (n = 2500: 13 µs).
// Measured cross-over on 2500-sample inputs (AVX-512), direct vs FFT with the
// block length the model picks: 48 taps 6.0 vs 7.7 µs (n = 256); 64 taps 7.6 vs
// 8.4 µs (n = 256); 80 taps 9.7 vs 8.1 µs (n = 512); 128 taps 15.1 vs 9.2 µs
// (n = 1024); 300 taps 51 vs 8.7 µs (n = 2560). The model switches between
// 64 and 80 taps for that input length, as measured. (On a CPU with only the
// portable loop it switches near 30 taps.)
//
// The two fused copies (AVX-512 and AVX2+FMA) give the same bits, but the
// direct sum and the FFT do not: were the choice made on each copy's own
// speed, a template near the cross-over would be correlated directly on one
// CPU and by FFT on another, and the same frames would give reports that
// differ in their last bits from machine to machine. Both fused copies are
// therefore costed at the AVX-512 figure (on an AVX2 CPU the direct sum is
// kept up to ~19 % past its own break-even; the portable loop, whose sums
// differ anyway, keeps its own figure).
const DIRECT_NS_PER_MAC_FUSED: f64 = 0.047;
const DIRECT_NS_PER_MAC_PORTABLE: f64 = 0.10;
const DIRECT_NS_PER_OUTPUT: f64 = 0.1;
const FFT_NS_PER_NLOGN: f64 = 0.29;
const FFT_NON_POW2_FACTOR: f64 = 1.08;
const FFT_NS_PER_SAMPLE: f64 = 0.3;
/// Largest FFT block considered (samples); bigger blocks only waste cache.
const MAX_FFT_LEN: usize = 1 << 18;

/// Estimated time, nanoseconds, to correlate an input of `input_len` samples
/// with a template of `taps` taps by `method` (for the FFT method: with the
/// block length the planner would choose for that input length). The
/// constants were measured on the development machine; only their ratio
/// matters for the choice.
pub fn estimated_cost_ns(method: CorrelationMethod, taps: usize, input_len: usize) -> f64 {
    if taps == 0 || input_len < taps {
        return 0.0;
    }
    let outputs = input_len - taps + 1;
    match method {
        CorrelationMethod::Direct => direct_cost_ns(taps, outputs),
        CorrelationMethod::Fft => fft_block_len(taps, input_len).1,
    }
}

fn direct_cost_ns(taps: usize, outputs: usize) -> f64 {
    outputs as f64 * (taps as f64 * direct_ns_per_mac() + DIRECT_NS_PER_OUTPUT)
}

/// Cost of one multiply-accumulate of the direct loop this CPU will run, as
/// the choice of method counts it (one figure for both fused copies, not
/// each one's own: see the cost model's constants).
fn direct_ns_per_mac() -> f64 {
    ns_per_mac(direct_path())
}

fn ns_per_mac(path: DirectPath) -> f64 {
    match path {
        DirectPath::Avx512 | DirectPath::Avx2 => DIRECT_NS_PER_MAC_FUSED,
        DirectPath::Portable => DIRECT_NS_PER_MAC_PORTABLE,
    }
}

/// Which copy of the direct loop runs on this CPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DirectPath {
    Avx512,
    Avx2,
    Portable,
}

fn direct_path() -> DirectPath {
    #[cfg(target_arch = "x86_64")]
    {
        // Every feature the AVX-512 copies enable (a hypervisor may hide
        // some of what AVX-512F implies).
        if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return DirectPath::Avx512;
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            return DirectPath::Avx2;
        }
    }
    DirectPath::Portable
}

/// Cost of one overlap-save block of length `n`.
fn fft_block_cost_ns(n: usize) -> f64 {
    let nf = n as f64;
    let factor = if n.is_power_of_two() {
        1.0
    } else {
        FFT_NON_POW2_FACTOR
    };
    FFT_NS_PER_NLOGN * factor * nf * nf.log2() + FFT_NS_PER_SAMPLE * nf
}

/// Candidate block lengths in `lo..=hi`, ascending: powers of two and three
/// or five times a power of two. Lengths with more odd factors (e.g.
/// 2500 = 2²·5⁴ or 486 = 2·3⁵) measured up to 1.5× slower per n·log2(n), so they
/// are left out rather than modelled.
fn smooth_lengths(lo: usize, hi: usize) -> Vec<usize> {
    let mut v = Vec::new();
    for odd in [1usize, 3, 5] {
        let mut n = 2 * odd;
        while n <= hi {
            if n >= lo {
                v.push(n);
            }
            n *= 2;
        }
    }
    v.sort_unstable();
    v
}

/// The block length minimising the estimated total time for one input of
/// `input_len` samples, and that time. Requires `1 <= taps <= input_len`.
fn fft_block_len(taps: usize, input_len: usize) -> (usize, f64) {
    let outputs = input_len - taps + 1;
    // A block shorter than 2·taps yields fewer outputs than it has taps; one
    // that covers the whole input in one go is the longest worth having.
    let lo = (2 * taps).max(8);
    let whole = smooth_lengths(input_len.max(lo), 2 * input_len.max(lo))
        .first()
        .copied();
    let hi = whole.unwrap_or(MAX_FFT_LEN).min(MAX_FFT_LEN).max(lo);
    let mut best = (0usize, f64::INFINITY);
    for n in smooth_lengths(lo, hi) {
        let per_block = n - taps + 1;
        let blocks = outputs.div_ceil(per_block);
        let cost = blocks as f64 * fft_block_cost_ns(n);
        if cost < best.1 {
            best = (n, cost);
        }
    }
    if best.0 == 0 {
        // Only when lo > MAX_FFT_LEN: a template longer than half the largest block.
        let n = lo.next_power_of_two();
        best = (
            n,
            outputs.div_ceil(n - taps + 1) as f64 * fft_block_cost_ns(n),
        );
    }
    best
}

/// Plan and buffers of the overlap-save method.
#[derive(Clone)]
struct FftPlan {
    /// Block length (samples).
    n: usize,
    r2c: Arc<dyn RealToComplex<f64>>,
    c2r: Arc<dyn ComplexToReal<f64>>,
    /// conj(FFT(template zero-padded to n)) / n: one product per bin gives the
    /// circular cross-correlation, already normalised for the unnormalised inverse.
    template_spectrum: Vec<Complex<f64>>,
    /// Time-domain block (input, then output of the inverse).
    time: Vec<f64>,
    /// Spectrum of the block.
    freq: Vec<Complex<f64>>,
    /// Scratch shared by both transforms.
    scratch: Vec<Complex<f64>>,
}

impl FftPlan {
    fn new(taps: &[f64], n: usize) -> FftPlan {
        let mut planner = RealFftPlanner::<f64>::new();
        let r2c = planner.plan_fft_forward(n);
        let c2r = planner.plan_fft_inverse(n);
        let mut time = vec![0.0; n];
        time[..taps.len()].copy_from_slice(taps);
        let mut freq = r2c.make_output_vec();
        let mut scratch =
            vec![Complex::new(0.0, 0.0); r2c.get_scratch_len().max(c2r.get_scratch_len())];
        let ok = r2c.process_with_scratch(&mut time, &mut freq, &mut scratch);
        debug_assert!(ok.is_ok(), "buffer lengths come from the plan");
        let scale = 1.0 / n as f64;
        let template_spectrum = freq.iter().map(|c| c.conj() * scale).collect();
        FftPlan {
            n,
            r2c,
            c2r,
            template_spectrum,
            time,
            freq,
            scratch,
        }
    }

    /// Overlap-save: block `b` covers `x[b·p .. b·p + n]` (zero-padded past
    /// the end) and its first `p = n - taps + 1` circular-correlation lags
    /// do not wrap, so they are valid outputs.
    fn run(&mut self, taps_len: usize, x: &[f64], out: &mut Vec<f64>) {
        let outputs = x.len() - taps_len + 1;
        let p = self.n - taps_len + 1;
        let last_bin = self.freq.len() - 1;
        let mut start = 0;
        while start < outputs {
            let end = (start + self.n).min(x.len());
            let filled = end - start;
            self.time[..filled].copy_from_slice(&x[start..end]);
            self.time[filled..].fill(0.0);
            let ok =
                self.r2c
                    .process_with_scratch(&mut self.time, &mut self.freq, &mut self.scratch);
            debug_assert!(ok.is_ok(), "buffer lengths come from the plan");
            for (f, h) in self.freq.iter_mut().zip(&self.template_spectrum) {
                *f *= *h;
            }
            // Both spectra are Hermitian, so these are real up to a signed zero;
            // the inverse insists on exact zeros.
            self.freq[0].im = 0.0;
            self.freq[last_bin].im = 0.0;
            let ok =
                self.c2r
                    .process_with_scratch(&mut self.freq, &mut self.time, &mut self.scratch);
            debug_assert!(ok.is_ok(), "buffer lengths come from the plan");
            let take = p.min(outputs - start);
            out.extend_from_slice(&self.time[..take]);
            start += take;
        }
    }
}

/// Correlates signals with one template; built once per scene.
///
/// `correlate` allocates nothing when `out` already has the capacity for the
/// result (`x.len() - taps.len() + 1`); inputs longer than the planned
/// `max_input_len` work too (the FFT method just runs more blocks).
#[derive(Clone)]
pub struct Correlator {
    /// The template, in correlation order (`out[k] = Σ taps[j]·x[k+j]`).
    taps: Vec<f64>,
    /// Which method `correlate` runs.
    method: CorrelationMethod,
    /// Present when `method` is FFT and the template is not empty.
    fft: Option<FftPlan>,
}

impl std::fmt::Debug for Correlator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Correlator")
            .field("taps", &self.taps.len())
            .field("method", &self.method)
            .field("fft_block_len", &self.fft_block_len())
            .finish()
    }
}

impl Correlator {
    /// Plans for `template` and inputs up to `max_input_len` samples, choosing
    /// the method with the lower estimated cost for an input of `max_input_len`.
    pub fn new(template: &[f64], max_input_len: usize) -> Correlator {
        let l = template.len();
        let method = if l == 0 || max_input_len < l {
            CorrelationMethod::Direct
        } else if estimated_cost_ns(CorrelationMethod::Fft, l, max_input_len)
            < estimated_cost_ns(CorrelationMethod::Direct, l, max_input_len)
        {
            CorrelationMethod::Fft
        } else {
            CorrelationMethod::Direct
        };
        Correlator::with_method(template, max_input_len, method)
    }

    /// Plans for `template` with the given method (tests and benches; the FFT
    /// block length is still chosen by the cost model for `max_input_len`).
    pub fn with_method(
        template: &[f64],
        max_input_len: usize,
        method: CorrelationMethod,
    ) -> Correlator {
        let l = template.len();
        let fft = match method {
            CorrelationMethod::Fft if l > 0 => {
                let (n, _) = fft_block_len(l, max_input_len.max(l));
                Some(FftPlan::new(template, n))
            }
            _ => None,
        };
        Correlator {
            taps: template.to_vec(),
            method,
            fft,
        }
    }

    /// The template.
    pub fn taps(&self) -> &[f64] {
        &self.taps
    }

    /// The method chosen.
    pub fn method(&self) -> CorrelationMethod {
        self.method
    }

    /// FFT block length, samples, when the FFT method is used.
    pub fn fft_block_len(&self) -> Option<usize> {
        self.fft.as_ref().map(|p| p.n)
    }

    /// Recomputes `out[part]` of an earlier [`correlate`](Self::correlate)
    /// of an input of `x.len()` samples, from `x` (the input since changed
    /// only where those outputs read it): bit for bit what `correlate(x, out)`
    /// would write there. Only the direct method can (an FFT block's outputs
    /// depend on the whole block): false, and nothing done, for the FFT method
    /// or when `out` does not have the length `correlate(x, out)` gives.
    pub fn correlate_part(&mut self, x: &[f64], out: &mut [f64], part: std::ops::Range<usize>) -> bool {
        let l = self.taps.len();
        if self.fft.is_some() || l == 0 || x.len() < l || out.len() != x.len() - l + 1 || part.end > out.len() {
            return false;
        }
        if !part.is_empty() {
            correlate_valid_part(&self.taps, x, out, part);
        }
        true
    }

    /// `out[k] = Σ_j taps[j] * x[k + j]` for `k` in `0..=x.len() - taps.len()`;
    /// `out` is cleared (and left empty when `x` is shorter than the template).
    pub fn correlate(&mut self, x: &[f64], out: &mut Vec<f64>) {
        let l = self.taps.len();
        if x.len() < l || l == 0 {
            out.clear();
            return;
        }
        let outputs = x.len() - l + 1;
        match &mut self.fft {
            Some(plan) => {
                out.clear();
                plan.run(l, x, out)
            }
            None => {
                // Every output is written below: a buffer of the right
                // length (the last frame's) needs no zero fill first.
                if out.len() != outputs {
                    out.clear();
                    out.resize(outputs, 0.0);
                }
                correlate_valid(&self.taps, x, out);
            }
        }
    }
}

/// Direct valid correlation of part of the output: `out[k]` for `k` in
/// `part` only, each bit for bit what [`correlate_valid`] writes there for
/// the whole of `out` (which sets the block structure: outputs before the
/// last `out.len() % 8` are one fused multiply-add chain each, in tap order,
/// whatever block computes them; the last few are dot products). Lets a
/// caller whose input changed over a few samples recompute only the outputs
/// that read them. Requires what `correlate_valid` does and `part.end <= out.len()`.
pub(crate) fn correlate_valid_part(taps: &[f64], x: &[f64], out: &mut [f64], part: std::ops::Range<usize>) {
    part_on(direct_path(), taps, x, out, part);
}

/// [`correlate_valid_part`] on the given path (which the CPU must have).
fn part_on(path: DirectPath, taps: &[f64], x: &[f64], out: &mut [f64], part: std::ops::Range<usize>) {
    assert!(!taps.is_empty() && out.len() + taps.len() - 1 <= x.len() && part.end <= out.len());
    let chains_end = out.len() - out.len() % 8;
    let chains = part.start.min(chains_end)..part.end.min(chains_end);
    let l = taps.len();
    let xs = &x[chains.start..chains.end + l - 1];
    let os = &mut out[chains.clone()];
    match path {
        // SAFETY: direct_path() saw AVX-512F, AVX2 and FMA on this CPU.
        #[cfg(target_arch = "x86_64")]
        DirectPath::Avx512 => unsafe { chains_avx512(taps, xs, os) },
        // SAFETY: direct_path() saw AVX2 and FMA on this CPU.
        #[cfg(target_arch = "x86_64")]
        DirectPath::Avx2 => unsafe { chains_avx2(taps, xs, os) },
        _ => chains_body::<16, false>(taps, xs, os),
    }
    let fma = path != DirectPath::Portable;
    for k in part.start.max(chains_end)..part.end {
        out[k] = match fma {
            // SAFETY: direct_path() saw FMA on this CPU.
            #[cfg(target_arch = "x86_64")]
            true => unsafe { dot_fma(taps, &x[k..k + l]) },
            _ => dot::<false>(taps, &x[k..k + l]),
        };
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn chains_avx512(taps: &[f64], x: &[f64], out: &mut [f64]) {
    let k = blocks_avx512(taps, x, out);
    let k = blocks::<8, true>(taps, x, out, k);
    blocks::<1, true>(taps, x, out, k);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn chains_avx2(taps: &[f64], x: &[f64], out: &mut [f64]) {
    chains_body::<32, true>(taps, x, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dot_fma(a: &[f64], b: &[f64]) -> f64 {
    dot::<true>(a, b)
}

/// Every output of `out` as one chain in tap order (blocks of `B`, of 8,
/// then single chains): what [`blocks`] computes for each of its lanes.
#[inline(always)]
fn chains_body<const B: usize, const FMA: bool>(taps: &[f64], x: &[f64], out: &mut [f64]) {
    let k = blocks::<B, FMA>(taps, x, out, 0);
    let k = blocks::<8, FMA>(taps, x, out, k);
    blocks::<1, FMA>(taps, x, out, k);
}

/// Direct valid correlation into a slice: `out[k] = Σ_j taps[j]·x[k + j]` for
/// `k < out.len()`. Requires `!taps.is_empty()` and
/// `out.len() + taps.len() - 1 <= x.len()` (checked; violating it panics, so
/// callers in this crate size `out` from `x`).
pub(crate) fn correlate_valid(taps: &[f64], x: &[f64], out: &mut [f64]) {
    assert!(!taps.is_empty() && out.len() + taps.len() - 1 <= x.len());
    match direct_path() {
        // SAFETY: direct_path() saw AVX-512F, AVX2 and FMA on this CPU.
        #[cfg(target_arch = "x86_64")]
        DirectPath::Avx512 => unsafe { direct_avx512(taps, x, out) },
        // SAFETY: direct_path() saw AVX2 and FMA on this CPU.
        #[cfg(target_arch = "x86_64")]
        DirectPath::Avx2 => unsafe { direct_avx2(taps, x, out) },
        _ => direct_body::<16, false>(taps, x, out),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn direct_avx512(taps: &[f64], x: &[f64], out: &mut [f64]) {
    // 64 lanes = 8 zmm accumulators: enough independent FMA chains to cover
    // the FMA latency (32 lanes: equal at 64 taps, up to 1.3× slower at 300).
    let l = taps.len();
    let k = blocks_avx512(taps, x, out);
    let k = blocks::<8, true>(taps, x, out, k);
    for (kk, o) in out.iter_mut().enumerate().skip(k) {
        *o = dot::<true>(taps, &x[kk..kk + l]);
    }
}

/// Whole blocks of 64 outputs from `out[0]` on, as `blocks::<64, true>`
/// computes them (each output one fused multiply-add chain in tap order,
/// from 0), written out; returns where it stopped. The 64-lane window at
/// tap j is x[k + j ..][..64]: loaded for every tap, nearly every one of
/// its eight zmm loads splits a cache line, and the loads, not the FMAs,
/// set the pace. Here the window is loaded once per eight taps (nine
/// loads) and shifted into place in registers (`valignq`): 1.4x faster at
/// 64 taps, the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn blocks_avx512(taps: &[f64], x: &[f64], out: &mut [f64]) -> usize {
    let l = taps.len();
    let mut k = 0;
    while k + 64 <= out.len() {
        // Every read below is inside x[k .. k + l + 63] (see block64_avx512).
        assert!(k + l + 63 <= x.len());
        // SAFETY: AVX-512F and FMA are enabled here; the bounds were checked just above.
        unsafe { block64_avx512(taps, x.as_ptr().add(k), out.as_mut_ptr().add(k)) };
        k += 64;
    }
    k
}

/// One tap of [`block64_avx512`]: the window at offset `R` within the eight
/// taps' nine loaded vectors, times the tap, added to each accumulator.
#[cfg(target_arch = "x86_64")]
macro_rules! tap_avx512 {
    ($r:literal, $h:expr, $a:ident, $acc:ident) => {{
        use std::arch::x86_64::{_mm512_alignr_epi64, _mm512_castpd_si512, _mm512_castsi512_pd, _mm512_fmadd_pd, _mm512_set1_pd};
        let h = _mm512_set1_pd($h);
        for z in 0..8 {
            // Lanes R..8 of vector z, then 0..R of vector z + 1.
            let w = if $r == 0 {
                $a[z]
            } else {
                _mm512_castsi512_pd(_mm512_alignr_epi64::<$r>(_mm512_castpd_si512($a[z + 1]), _mm512_castpd_si512($a[z])))
            };
            $acc[z] = _mm512_fmadd_pd(h, w, $acc[z]);
        }
    }};
}

/// Outputs `out[0..64]` of the valid correlation of `taps` with the samples
/// at `xs` (`xs[0 .. taps.len() + 63]` readable): lane b accumulates
/// `taps[j]·xs[b + j]` by fused multiply-add in tap order from 0.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn block64_avx512(taps: &[f64], xs: *const f64, out: *mut f64) {
    use std::arch::x86_64::{_mm512_fmadd_pd, _mm512_loadu_pd, _mm512_maskz_loadu_pd, _mm512_set1_pd, _mm512_setzero_pd, _mm512_storeu_pd};
    let l = taps.len();
    let mut acc = [_mm512_setzero_pd(); 8];
    let mut j0 = 0;
    // SAFETY (every read): xs[j0 + 8m + i] for m < 8, i < 8 and j0 + 8 <= l
    // is below l + 56; the ninth vector reads only its first seven lanes
    // (masked), below j0 + 71 <= l + 63; the last taps read below l + 63.
    unsafe {
        while j0 + 8 <= l {
            let p = xs.add(j0);
            let mut a = [_mm512_setzero_pd(); 9];
            for (m, v) in a.iter_mut().enumerate().take(8) {
                *v = _mm512_loadu_pd(p.add(8 * m));
            }
            a[8] = _mm512_maskz_loadu_pd(0x7f, p.add(64));
            let t = &taps[j0..j0 + 8];
            tap_avx512!(0, t[0], a, acc);
            tap_avx512!(1, t[1], a, acc);
            tap_avx512!(2, t[2], a, acc);
            tap_avx512!(3, t[3], a, acc);
            tap_avx512!(4, t[4], a, acc);
            tap_avx512!(5, t[5], a, acc);
            tap_avx512!(6, t[6], a, acc);
            tap_avx512!(7, t[7], a, acc);
            j0 += 8;
        }
        for (j, &tap) in taps.iter().enumerate().skip(j0) {
            let h = _mm512_set1_pd(tap);
            for (z, a) in acc.iter_mut().enumerate() {
                *a = _mm512_fmadd_pd(h, _mm512_loadu_pd(xs.add(j + 8 * z)), *a);
            }
        }
        for (z, a) in acc.iter().enumerate() {
            _mm512_storeu_pd(out.add(8 * z), *a);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn direct_avx2(taps: &[f64], x: &[f64], out: &mut [f64]) {
    // 32 lanes = 8 ymm accumulators (16 lanes measured 10 % slower).
    direct_body::<32, true>(taps, x, out);
}

/// Blocks of `B` outputs accumulate in `B` independent lanes (registers),
/// then blocks of 8 take most of the remainder and a dot product the last
/// few; `FMA` uses fused multiply-add, which is only fast where the target
/// has it.
#[inline(always)]
fn direct_body<const B: usize, const FMA: bool>(taps: &[f64], x: &[f64], out: &mut [f64]) {
    let l = taps.len();
    let k = blocks::<B, FMA>(taps, x, out, 0);
    let k = blocks::<8, FMA>(taps, x, out, k);
    for (kk, o) in out.iter_mut().enumerate().skip(k) {
        *o = dot::<FMA>(taps, &x[kk..kk + l]);
    }
}

/// Computes whole blocks of `B` outputs from `out[k]` on; returns where it stopped.
#[inline(always)]
fn blocks<const B: usize, const FMA: bool>(
    taps: &[f64],
    x: &[f64],
    out: &mut [f64],
    mut k: usize,
) -> usize {
    let l = taps.len();
    while k + B <= out.len() {
        let mut acc = [0.0f64; B];
        let xs = &x[k..k + l - 1 + B];
        for (j, &h) in taps.iter().enumerate() {
            let w: &[f64; B] = xs[j..j + B].try_into().expect("slice has length B");
            for b in 0..B {
                acc[b] = if FMA {
                    h.mul_add(w[b], acc[b])
                } else {
                    acc[b] + h * w[b]
                };
            }
        }
        out[k..k + B].copy_from_slice(&acc);
        k += B;
    }
    k
}

/// Dot product with four independent accumulators.
#[inline(always)]
fn dot<const FMA: bool>(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ac, bc) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ar, br) = (ac.remainder(), bc.remainder());
    for (ca, cb) in ac.zip(bc) {
        for i in 0..4 {
            acc[i] = if FMA {
                ca[i].mul_add(cb[i], acc[i])
            } else {
                acc[i] + ca[i] * cb[i]
            };
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (p, q) in ar.iter().zip(br) {
        s = if FMA { p.mul_add(*q, s) } else { s + p * q };
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smooth_lengths_are_smooth_and_sorted() {
        let v = smooth_lengths(10, 100);
        assert_eq!(v, vec![10, 12, 16, 20, 24, 32, 40, 48, 64, 80, 96]);
    }

    #[test]
    fn cost_model_prefers_direct_for_short_and_fft_for_long_templates() {
        assert_eq!(
            Correlator::new(&[1.0; 7], 2500).method(),
            CorrelationMethod::Direct
        );
        assert_eq!(
            Correlator::new(&[1.0; 300], 2500).method(),
            CorrelationMethod::Fft
        );
        assert_eq!(
            Correlator::new(&[1.0; 300], 100).method(),
            CorrelationMethod::Direct
        );
    }

    /// The two fused copies compute the same bits, so they must choose the
    /// same method too, or the same frames report differently on an AVX2
    /// CPU and an AVX-512 one (the golden reports pin the choice made on
    /// either).
    #[test]
    fn both_fused_copies_cost_the_same() {
        assert_eq!(ns_per_mac(DirectPath::Avx512).to_bits(), ns_per_mac(DirectPath::Avx2).to_bits());
        assert!(ns_per_mac(DirectPath::Portable) > ns_per_mac(DirectPath::Avx2));
    }

    /// Every copy of the direct loop (not only the one this CPU dispatches to)
    /// against the naive sum, over lengths hitting the blocked body and tail.
    #[test]
    fn every_direct_path_matches_a_naive_sum() {
        let x: Vec<f64> = (0..300)
            .map(|i| ((i * 37 % 101) as f64 * 0.37).sin())
            .collect();
        for l in [1usize, 3, 8, 33, 70] {
            let taps: Vec<f64> = (0..l).map(|j| (j as f64 * 0.7).cos()).collect();
            for n in [l, l + 5, l + 31, l + 64, 300] {
                let m = n - l + 1;
                let naive: Vec<f64> = (0..m)
                    .map(|k| taps.iter().enumerate().map(|(j, t)| t * x[k + j]).sum())
                    .collect();
                let check = |out: &[f64], path: &str| {
                    for (a, b) in out.iter().zip(&naive) {
                        assert!((a - b).abs() < 1e-12, "{path} L={l} n={n}: {a} vs {b}");
                    }
                };
                let mut out = vec![0.0; m];
                direct_body::<16, false>(&taps, &x[..n], &mut out);
                check(&out, "portable");
                #[cfg(target_arch = "x86_64")]
                {
                    if std::arch::is_x86_feature_detected!("avx2")
                        && std::arch::is_x86_feature_detected!("fma")
                    {
                        // SAFETY: AVX2 and FMA checked just above.
                        unsafe { direct_avx2(&taps, &x[..n], &mut out) };
                        check(&out, "avx2");
                    }
                    if std::arch::is_x86_feature_detected!("avx512f") {
                        // SAFETY: AVX-512F (and so AVX2, FMA) checked just above.
                        unsafe { direct_avx512(&taps, &x[..n], &mut out) };
                        check(&out, "avx512");
                    }
                }
            }
        }
    }

    #[test]
    fn both_methods_match_a_naive_sum() {
        let taps = [0.5, -1.0, 2.0, 0.25];
        let x: Vec<f64> = (0..40).map(|i| ((i * 7 % 11) as f64) - 5.0).collect();
        let naive: Vec<f64> = (0..=x.len() - taps.len())
            .map(|k| taps.iter().enumerate().map(|(j, t)| t * x[k + j]).sum())
            .collect();
        for m in [CorrelationMethod::Direct, CorrelationMethod::Fft] {
            let mut c = Correlator::with_method(&taps, 16, m);
            let mut out = Vec::new();
            c.correlate(&x, &mut out);
            assert_eq!(out.len(), naive.len());
            for (a, b) in out.iter().zip(&naive) {
                assert!((a - b).abs() < 1e-12, "{m:?}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn a_part_recomputed_after_a_local_change_is_bit_identical_to_a_full_run() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for l in [1usize, 5, 8, 33, 64, 70] {
            let taps: Vec<f64> = (0..l).map(|_| rng.random_range(-1.0..1.0)).collect();
            for n in [l, l + 7, l + 64, 333, 2500] {
                let mut x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
                let mut c = Correlator::with_method(&taps, n, CorrelationMethod::Direct);
                let mut out = Vec::new();
                c.correlate(&x, &mut out);
                for _ in 0..20 {
                    // Change a window of the input, then recompute the outputs that read it.
                    let s = rng.random_range(0..n);
                    let e = (s + rng.random_range(1..40)).min(n);
                    for v in &mut x[s..e] {
                        *v += rng.random_range(-0.5..0.5);
                    }
                    let part = s.saturating_sub(l - 1)..e.min(out.len());
                    assert!(c.correlate_part(&x, &mut out, part));
                    let mut full = Vec::new();
                    c.correlate(&x, &mut full);
                    let same = out.iter().zip(&full).all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "L={l} n={n} change {s}..{e}");
                }
            }
        }
        // Every path this CPU has, against its own full run.
        let mut paths: Vec<(DirectPath, fn(&[f64], &[f64], &mut [f64]))> = vec![(DirectPath::Portable, |t, x, o| direct_body::<16, false>(t, x, o))];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                // SAFETY: AVX2 and FMA checked just above.
                paths.push((DirectPath::Avx2, |t, x, o| unsafe { direct_avx2(t, x, o) }));
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                // SAFETY: AVX-512F (and so AVX2, FMA) checked just above.
                paths.push((DirectPath::Avx512, |t, x, o| unsafe { direct_avx512(t, x, o) }));
            }
        }
        for (path, full) in paths {
            for (l, n) in [(1usize, 9usize), (7, 100), (64, 2500), (70, 333)] {
                let taps: Vec<f64> = (0..l).map(|_| rng.random_range(-1.0..1.0)).collect();
                let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
                let mut want = vec![0.0; n - l + 1];
                full(&taps, &x, &mut want);
                let mut got = vec![f64::NAN; want.len()];
                for p in [0..want.len().min(3), 5.min(want.len())..want.len()] {
                    part_on(path, &taps, &x, &mut got, p);
                }
                if want.len() > 3 {
                    part_on(path, &taps, &x, &mut got, 3..5.min(want.len()));
                }
                assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "{path:?} L={l} n={n}");
            }
        }
        let mut fft = Correlator::with_method(&[1.0, 2.0], 16, CorrelationMethod::Fft);
        let mut out = vec![0.0; 15];
        assert!(!fft.correlate_part(&[0.0; 16], &mut out, 0..3), "FFT blocks cannot be recomputed in part");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn written_out_avx512_blocks_are_the_generic_fma_chains() {
        if !(std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("fma")) {
            return;
        }
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
        for (l, n) in [(1usize, 200usize), (5, 90), (8, 71), (13, 500), (64, 2563), (65, 700), (71, 134), (100, 1000)] {
            let taps: Vec<f64> = (0..l).map(|_| rng.random_range(-1.0..1.0)).collect();
            let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let outputs = n - l + 1;
            let mut want = vec![0.0; outputs];
            let k = blocks::<64, true>(&taps, &x, &mut want, 0);
            let mut got = vec![f64::NAN; outputs];
            // SAFETY: AVX-512F and FMA checked above.
            let k2 = unsafe { blocks_avx512(&taps, &x, &mut got) };
            assert_eq!(k, k2);
            assert!(got[..k].iter().zip(&want[..k]).all(|(a, b)| a.to_bits() == b.to_bits()), "L={l} n={n}");
            // And the whole output, against the AVX2 copy (the same chains in 32 lanes).
            let (mut a, mut b) = (vec![0.0; outputs], vec![0.0; outputs]);
            // SAFETY: AVX-512F (so AVX2) and FMA checked above.
            unsafe {
                direct_avx512(&taps, &x, &mut a);
                direct_avx2(&taps, &x, &mut b);
            }
            let chains = outputs - outputs % 8;
            assert!(a[..chains].iter().zip(&b[..chains]).all(|(p, q)| p.to_bits() == q.to_bits()), "L={l} n={n}");
        }
    }
}
