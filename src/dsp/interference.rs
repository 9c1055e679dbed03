//! Cancellation of a structured interference burst (the source's APD bias
//! supply: a fixed-shape burst recurring at the mains rate at a random phase
//! to the laser shots).
//!
//! The burst is longer than a frame, so each frame holds a slice of it. Two
//! parts:
//!
//! * [`BurstLearner`] learns the whole waveform from the noise gates of many
//!   frames (or whole laser-off frames). Frames whose gate variance is well
//!   above the typical (median) frame's hold a burst; consecutive such frames
//!   are one *occurrence*, stitched together on the absolute sample clock
//!   (trigger time / sample interval). Occurrences land at random phases of
//!   the burst, so they are aligned by normalised cross-correlation (FFT) on
//!   their overlap, averaged, re-aligned against the average (refinement), and
//!   the average is low-passed to the burst's band to drop the noise that
//!   averaging left in it. The noise's own autocorrelation is measured on the
//!   burst-free gates: it sets the spread of the correlation statistic.
//! * [`BurstCanceller`] finds the burst in one frame by correlating the
//!   frame's gate samples with the template at every lag. The statistic
//!   `z = c / (σ √(g·e))` (c the correlation, e the template energy seen
//!   through the gate mask, g the noise-colour factor) is N(0, 1) without a
//!   burst, so the Neyman-Pearson threshold for a per-frame false-detection
//!   probability P over M lags is Q⁻¹(1 − (1 − P)^(1/M)). The detected lag is
//!   refined to a sub-sample shift (parabola through the correlation peak),
//!   the template slice is shifted by a fractional-delay filter, its amplitude
//!   fitted by least squares on the gates, and it is subtracted from the
//!   whole frame — the range gate included, which the fit never looked at, so
//!   a return there does not bias it.

use crate::math::special::{per_cell_pfa, q_inv};
use crate::dsp::fracdelay::FractionalDelay;
use realfft::num_complex::Complex;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use std::ops::Range;
use std::sync::Arc;

/// Lags of the noise autocorrelation measured during learning.
const ACF_LAGS: usize = 64;
/// A frame's gate variance above this multiple of the median frame's marks a burst.
const BURST_VARIANCE_RATIO: f64 = 2.0;
/// Fewest overlapping samples for two occurrences to be aligned on.
const MIN_OVERLAP: f64 = 400.0;
/// Frames either side of a detected burst frame that join its occurrence
/// (they hold the burst's faint ends).
const EDGE_FRAMES: usize = 3;
/// Half-length of the fractional-delay filter used to shift the template.
const SHIFT_HALF_LEN: usize = 16;

/// FFT cross-correlation at one size.
struct Xcorr {
    n: usize,
    fwd: Arc<dyn RealToComplex<f64>>,
    inv: Arc<dyn ComplexToReal<f64>>,
    buf: Vec<f64>,
    spec: Vec<Complex<f64>>,
    /// Scratch of the forward and inverse plans (kept: `process` would
    /// allocate its own on every call).
    fwd_scratch: Vec<Complex<f64>>,
    /// See `fwd_scratch`.
    inv_scratch: Vec<Complex<f64>>,
}

impl std::fmt::Debug for Xcorr {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Xcorr").field("n", &self.n).finish()
    }
}

impl Xcorr {
    fn new(min_len: usize) -> Xcorr {
        let n = min_len.max(2).next_power_of_two();
        let mut planner = RealFftPlanner::<f64>::new();
        let fwd = planner.plan_fft_forward(n);
        let inv = planner.plan_fft_inverse(n);
        let spec = fwd.make_output_vec();
        let (fwd_scratch, inv_scratch) = (fwd.make_scratch_vec(), inv.make_scratch_vec());
        Xcorr {
            n,
            fwd,
            inv,
            buf: vec![0.0; n],
            spec,
            fwd_scratch,
            inv_scratch,
        }
    }

    /// Spectrum of `x` zero-padded to the FFT size.
    fn spectrum(&mut self, x: &[f64]) -> Vec<Complex<f64>> {
        let mut out = self.fwd.make_output_vec();
        self.spectrum_into(x, &mut out);
        out
    }

    fn spectrum_into(&mut self, x: &[f64], out: &mut [Complex<f64>]) {
        self.buf.fill(0.0);
        let m = x.len().min(self.n);
        self.buf[..m].copy_from_slice(&x[..m]);
        self.fwd
            .process_with_scratch(&mut self.buf, out, &mut self.fwd_scratch)
            .expect("buffers sized by the plan");
    }

    /// `out[q] = Σ_j a[q + j] · b[j]` from the spectra of `a` and `b` (no
    /// wrap-around as long as `a` and `b` fit in the FFT size and `q + len(b) ≤ n`).
    fn correlate(&mut self, a: &[Complex<f64>], b: &[Complex<f64>], out: &mut [f64]) {
        for ((s, x), y) in self.spec.iter_mut().zip(a).zip(b) {
            *s = x * y.conj();
        }
        // The DC and Nyquist bins of a real signal's product are real.
        if let Some(s) = self.spec.first_mut() {
            s.im = 0.0;
        }
        if let Some(s) = self.spec.last_mut() {
            s.im = 0.0;
        }
        self.inv
            .process_with_scratch(&mut self.spec, &mut self.buf, &mut self.inv_scratch)
            .expect("buffers sized by the plan");
        let scale = 1.0 / self.n as f64;
        for (o, v) in out.iter_mut().zip(&self.buf) {
            *o = v * scale;
        }
    }
}

/// A learned burst waveform with what is needed to detect it.
#[derive(Debug, Clone, PartialEq)]
pub struct BurstTemplate {
    /// The burst, one value per sample, V (at the amplitude it was learned at).
    pub values: Vec<f64>,
    /// Offset of the burst-free gates (the receiver's DC), V.
    pub offset_v: f64,
    /// Noise standard deviation of the burst-free gates, V.
    pub sigma_v: f64,
    /// Normalised noise autocorrelation ρ(0..K) (ρ(0) = 1) of the burst-free gates.
    pub noise_acf: Vec<f64>,
    /// Occurrences averaged into the template.
    pub occurrences: usize,
    /// Fraction of the template's span that some occurrence covered.
    pub coverage: f64,
}

/// One frame's gate samples, kept for learning.
#[derive(Debug, Clone)]
struct LearnFrame {
    /// Absolute sample index of each gate's first sample, and its values.
    segments: Vec<(i64, Vec<f64>)>,
    median_v: f64,
    variance: f64,
}

/// Collects noise-gate samples and learns the burst waveform.
#[derive(Debug, Clone)]
pub struct BurstLearner {
    /// Longest burst, samples.
    max_len: usize,
    /// Band of the burst, cycles per sample.
    bandwidth: f64,
    frames: Vec<LearnFrame>,
}

/// A burst occurrence: values and coverage on a local sample axis.
#[derive(Debug, Clone)]
struct Occurrence {
    values: Vec<f64>,
    mask: Vec<f64>,
    /// Where it sits on the canvas once aligned.
    at: usize,
}

impl BurstLearner {
    /// A learner for bursts up to `max_len` samples long whose modes lie below
    /// `bandwidth` cycles per sample (e.g. 12 MHz × 1 ns = 0.012).
    pub fn new(max_len: usize, bandwidth: f64) -> BurstLearner {
        BurstLearner {
            max_len: max_len.max(16),
            bandwidth,
            frames: Vec::new(),
        }
    }

    /// Frames added so far.
    pub fn frames(&self) -> usize {
        self.frames.len()
    }

    /// Adds one frame: `x` in volts, `abs_pos` the absolute sample index of
    /// `x[0]` (trigger time / sample interval, rounded), `gates` the sample
    /// ranges known to hold no return (the whole frame for a laser-off frame).
    pub fn push(&mut self, abs_pos: i64, x: &[f64], gates: &[Range<usize>]) {
        let mut segments = Vec::new();
        let mut all = Vec::new();
        for g in gates {
            let r = g.start.min(x.len())..g.end.min(x.len());
            if r.is_empty() {
                continue;
            }
            let v: Vec<f64> = x[r.clone()]
                .iter()
                .map(|v| if v.is_finite() { *v } else { 0.0 })
                .collect();
            all.extend_from_slice(&v);
            segments.push((abs_pos + r.start as i64, v));
        }
        if all.len() < 8 {
            return;
        }
        let median_v = crate::math::select::median(&mut all.clone()).unwrap_or(0.0);
        let variance = all.iter().map(|v| (v - median_v).powi(2)).sum::<f64>() / all.len() as f64;
        self.frames.push(LearnFrame {
            segments,
            median_v,
            variance,
        });
    }

    /// Learns the template; `None` when no frame held a burst (or too few did
    /// to be aligned).
    pub fn finish(&self) -> Option<BurstTemplate> {
        if self.frames.len() < 3 {
            return None;
        }
        let mut vars: Vec<f64> = self.frames.iter().map(|f| f.variance).collect();
        let typical = crate::math::select::median(&mut vars)?;
        let has_burst: Vec<bool> = self
            .frames
            .iter()
            .map(|f| f.variance > BURST_VARIANCE_RATIO * typical)
            .collect();
        let mut quiet_medians: Vec<f64> = self
            .frames
            .iter()
            .zip(&has_burst)
            .filter(|(_, b)| !**b)
            .map(|(f, _)| f.median_v)
            .collect();
        let offset_v = crate::math::select::median(&mut quiet_medians)?;
        let (sigma_v, noise_acf) = self.noise_acf(&has_burst, offset_v);
        // Stitch consecutive burst frames into occurrences. The burst's
        // envelope fades in and out: the frames just before and after the ones
        // the variance test caught hold its weak ends, so they join too.
        let mut member = has_burst.clone();
        for (i, _) in has_burst.iter().enumerate().filter(|(_, b)| **b) {
            for m in member
                .iter_mut()
                .take((i + EDGE_FRAMES + 1).min(has_burst.len()))
                .skip(i.saturating_sub(EDGE_FRAMES))
            {
                *m = true;
            }
        }
        let mut occs: Vec<Vec<(i64, &[f64])>> = Vec::new();
        let mut last_end: Option<i64> = None;
        for (f, _) in self.frames.iter().zip(&member).filter(|(_, b)| **b) {
            let start = f.segments.first().map_or(0, |s| s.0);
            let joins = last_end.is_some_and(|e| {
                start - e <= self.max_len as i64 / 4 && start >= e - self.max_len as i64
            });
            if !joins {
                occs.push(Vec::new());
            }
            let o = occs.last_mut().expect("pushed above");
            for (p, v) in &f.segments {
                o.push((*p, v.as_slice()));
            }
            last_end = f.segments.last().map(|(p, v)| p + v.len() as i64);
        }
        let mut occs: Vec<Occurrence> = occs
            .into_iter()
            .filter_map(|segs| {
                let origin = segs.iter().map(|s| s.0).min()?;
                let end = segs.iter().map(|s| s.0 + s.1.len() as i64).max()?;
                let len = ((end - origin) as usize).min(2 * self.max_len);
                let mut values = vec![0.0; len];
                let mut mask = vec![0.0; len];
                for (p, v) in segs {
                    for (k, &x) in v.iter().enumerate() {
                        let i = (p - origin) as usize + k;
                        if i < len {
                            values[i] = x - offset_v;
                            mask[i] = 1.0;
                        }
                    }
                }
                Some(Occurrence {
                    values,
                    mask,
                    at: 0,
                })
            })
            .collect();
        if occs.is_empty() {
            return None;
        }
        // Best-covered first: the reference the others align to.
        occs.sort_by(|a, b| {
            b.mask
                .iter()
                .sum::<f64>()
                .total_cmp(&a.mask.iter().sum::<f64>())
        });
        let longest = occs.iter().map(|o| o.values.len()).max().unwrap_or(0);
        let pad = self.max_len + longest.saturating_sub(occs[0].values.len());
        let width = occs[0].values.len() + 2 * pad;
        // Coarse search on block averages: the burst's band is far below the
        // decimated Nyquist frequency, so the coarse lag is right to a block.
        let d = ((0.1 / self.bandwidth.max(1e-6)) as usize).clamp(1, 64);
        let mut xc = Xcorr::new((width + longest).div_ceil(d) + 1);
        let mut canvas = Canvas {
            sum: vec![0.0; width],
            count: vec![0.0; width],
        };
        occs[0].at = pad;
        canvas.add(&occs[0], 1.0);
        let mut used = vec![false; occs.len()];
        used[0] = true;
        // Pass 1 aligns every occurrence to the reference; pass 2 re-aligns
        // each to the average of pass 1 (refinement).
        for pass in 0..2 {
            let reference = CoarseRef::new(&canvas, d, &mut xc);
            let mut next = Canvas {
                sum: vec![0.0; width],
                count: vec![0.0; width],
            };
            for (i, o) in occs.iter_mut().enumerate() {
                if pass == 0 && i == 0 {
                    next.add(o, 1.0);
                    continue;
                }
                if pass == 1 && !used[i] {
                    continue;
                }
                if let Some(at) = reference.align(&mut xc, o) {
                    o.at = at;
                    used[i] = true;
                    next.add(o, 1.0);
                } else if pass == 1 {
                    next.add(o, 1.0);
                }
            }
            canvas = next;
        }
        let first = canvas.count.iter().position(|&c| c > 0.5)?;
        let last = canvas.count.iter().rposition(|&c| c > 0.5)?;
        let span = &canvas.count[first..=last];
        let coverage = span.iter().filter(|&&c| c > 0.5).count() as f64 / span.len() as f64;
        let raw: Vec<f64> = (first..=last)
            .map(|i| {
                if canvas.count[i] > 0.5 {
                    canvas.sum[i] / canvas.count[i]
                } else {
                    0.0
                }
            })
            .collect();
        let values = low_pass(&raw, self.bandwidth);
        Some(BurstTemplate {
            values,
            offset_v,
            sigma_v,
            noise_acf,
            occurrences: used.iter().filter(|u| **u).count(),
            coverage,
        })
    }

    /// σ and normalised autocorrelation of the burst-free gates.
    fn noise_acf(&self, has_burst: &[bool], offset_v: f64) -> (f64, Vec<f64>) {
        let mut r = [0.0; ACF_LAGS + 1];
        let mut n = [0.0; ACF_LAGS + 1];
        // A few hundred frames pin the autocorrelation to well under 1 %.
        for (f, _) in self
            .frames
            .iter()
            .zip(has_burst)
            .filter(|(_, b)| !**b)
            .take(500)
        {
            for (_, v) in &f.segments {
                for k in 0..=ACF_LAGS.min(v.len().saturating_sub(1)) {
                    let s: f64 = v
                        .iter()
                        .zip(&v[k..])
                        .map(|(a, b)| (a - offset_v) * (b - offset_v))
                        .sum();
                    r[k] += s;
                    n[k] += (v.len() - k) as f64;
                }
            }
        }
        if n[0] == 0.0 || r[0] <= 0.0 {
            return (0.0, vec![1.0]);
        }
        let r0 = r[0] / n[0];
        let acf = (0..=ACF_LAGS)
            .map(|k| if n[k] > 0.0 { r[k] / n[k] / r0 } else { 0.0 })
            .collect();
        (r0.sqrt(), acf)
    }
}

/// Running sums of aligned occurrences.
struct Canvas {
    sum: Vec<f64>,
    count: Vec<f64>,
}

impl Canvas {
    fn add(&mut self, o: &Occurrence, sign: f64) {
        for (k, (v, m)) in o.values.iter().zip(&o.mask).enumerate() {
            self.sum[o.at + k] += sign * v;
            self.count[o.at + k] += sign * m;
        }
    }
}

/// Block sums of `x` weighted by `m` (and of `m`), `d` samples per block.
fn decimate(x: &[f64], m: &[f64], d: usize) -> (Vec<f64>, Vec<f64>) {
    let n = x.len().div_ceil(d);
    let (mut xs, mut ms) = (vec![0.0; n], vec![0.0; n]);
    for (i, (v, w)) in x.iter().zip(m).enumerate() {
        xs[i / d] += v * w;
        ms[i / d] += w;
    }
    // Block means where anything was seen; the weight is the fraction seen.
    for (v, w) in xs.iter_mut().zip(ms.iter_mut()) {
        if *w > 0.0 {
            *v /= *w;
        }
        *w /= d as f64;
    }
    (xs, ms)
}

/// The current average, prepared once per pass for aligning occurrences to it.
struct CoarseRef {
    d: usize,
    /// Full-rate average and coverage.
    t: Vec<f64>,
    mt: Vec<f64>,
    /// Spectra of the decimated average (weighted), its square and its coverage.
    st: Vec<Complex<f64>>,
    st2: Vec<Complex<f64>>,
    smt: Vec<Complex<f64>>,
    coarse_len: usize,
}

impl CoarseRef {
    fn new(c: &Canvas, d: usize, xc: &mut Xcorr) -> CoarseRef {
        let t: Vec<f64> = c
            .sum
            .iter()
            .zip(&c.count)
            .map(|(s, n)| if *n > 0.5 { s / n } else { 0.0 })
            .collect();
        let mt: Vec<f64> = c
            .count
            .iter()
            .map(|&n| if n > 0.5 { 1.0 } else { 0.0 })
            .collect();
        let (tc, mtc) = decimate(&t, &mt, d);
        let tw: Vec<f64> = tc.iter().zip(&mtc).map(|(a, b)| a * b).collect();
        let t2w: Vec<f64> = tc.iter().zip(&mtc).map(|(a, b)| a * a * b).collect();
        CoarseRef {
            d,
            st: xc.spectrum(&tw),
            st2: xc.spectrum(&t2w),
            smt: xc.spectrum(&mtc),
            coarse_len: tc.len(),
            t,
            mt,
        }
    }

    /// Normalised correlation of `o` placed at full-rate position `q` (direct).
    fn fine(&self, o: &Occurrence, q: usize) -> Option<f64> {
        if q + o.values.len() > self.t.len() {
            return None;
        }
        let (mut c, mut et, mut ey, mut ov) = (0.0, 0.0, 0.0, 0.0);
        for (k, (y, m)) in o.values.iter().zip(&o.mask).enumerate() {
            let w = m * self.mt[q + k];
            let t = self.t[q + k];
            c += t * y * w;
            et += t * t * w;
            ey += y * y * w;
            ov += w;
        }
        (ov >= MIN_OVERLAP.min(0.5 * o.mask.iter().sum::<f64>()) && et > 0.0 && ey > 0.0)
            .then(|| c / (et * ey).sqrt())
    }

    /// Canvas position with the highest normalised correlation of `o` with the
    /// average over their overlap: coarse FFT search, then ±1 block at full rate.
    fn align(&self, xc: &mut Xcorr, o: &Occurrence) -> Option<usize> {
        let d = self.d;
        let (yc, myc) = decimate(&o.values, &o.mask, d);
        let yw: Vec<f64> = yc.iter().zip(&myc).map(|(a, b)| a * b).collect();
        let y2w: Vec<f64> = yc.iter().zip(&myc).map(|(a, b)| a * a * b).collect();
        let (sy, sy2, sm) = (xc.spectrum(&yw), xc.spectrum(&y2w), xc.spectrum(&myc));
        let q_count = self.coarse_len.checked_sub(yc.len())? + 1;
        let mut c = vec![0.0; q_count];
        let mut et = vec![0.0; q_count];
        let mut ey = vec![0.0; q_count];
        let mut ov = vec![0.0; q_count];
        xc.correlate(&self.st, &sy, &mut c);
        xc.correlate(&self.st2, &sm, &mut et);
        xc.correlate(&self.smt, &sy2, &mut ey);
        xc.correlate(&self.smt, &sm, &mut ov);
        let need = MIN_OVERLAP.min(0.5 * o.mask.iter().sum::<f64>()) / d as f64;
        let coarse = (0..q_count)
            .filter(|&q| ov[q] >= need && et[q] > 0.0 && ey[q] > 0.0)
            .max_by(|&a, &b| {
                (c[a] / (et[a] * ey[a]).sqrt()).total_cmp(&(c[b] / (et[b] * ey[b]).sqrt()))
            })?;
        let lo = (coarse * d).saturating_sub(d);
        (lo..=coarse * d + d)
            .filter_map(|q| self.fine(o, q).map(|r| (q, r)))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(q, _)| q)
    }
}

/// Zero-phase low-pass: spectrum flat to 0.8·`bandwidth` cycles per sample, a
/// raised-cosine roll-off to zero at 1.2·`bandwidth`.
fn low_pass(x: &[f64], bandwidth: f64) -> Vec<f64> {
    if x.is_empty() || !(bandwidth > 0.0 && bandwidth < 0.5) {
        return x.to_vec();
    }
    // Zero padding on both sides keeps the circular wrap away from the ends.
    let pad = ((4.0 / bandwidth) as usize).min(x.len());
    let mut xc = Xcorr::new(x.len() + 2 * pad);
    let n = xc.n;
    let mut padded = vec![0.0; pad + x.len()];
    padded[pad..].copy_from_slice(x);
    let mut spec = xc.spectrum(&padded);
    for (k, s) in spec.iter_mut().enumerate() {
        let f = k as f64 / n as f64;
        let (lo, hi) = (0.8 * bandwidth, 1.2 * bandwidth);
        let w = if f <= lo {
            1.0
        } else if f >= hi {
            0.0
        } else {
            0.5 * (1.0 + (std::f64::consts::PI * (f - lo) / (hi - lo)).cos())
        };
        *s *= w;
    }
    spec[0].im = 0.0;
    if let Some(s) = spec.last_mut() {
        s.im = 0.0;
    }
    let mut out = vec![0.0; n];
    xc.inv
        .process(&mut spec, &mut out)
        .expect("buffers sized by the plan");
    out[pad..pad + x.len()]
        .iter()
        .map(|v| v / n as f64)
        .collect()
}

/// What was found and subtracted in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cancelled {
    /// Template index (with sub-sample part) aligned with the frame's sample 0.
    pub lag: f64,
    /// Fitted amplitude relative to the template.
    pub amplitude: f64,
    /// The detection statistic (N(0, 1) units).
    pub z: f64,
}

/// Per-frame detection and subtraction of a learned burst. Planned once per
/// template and frame length (FFT plans, template spectra, threshold).
pub struct BurstCanceller {
    template: BurstTemplate,
    /// Frame length, samples.
    n: usize,
    /// Template padded with `n` zeros on both sides.
    padded: Vec<f64>,
    spec_t: Vec<Complex<f64>>,
    spec_t2: Vec<Complex<f64>>,
    xc: Xcorr,
    /// Noise-colour factor: variance of the correlation per unit template energy, in σ².
    colour: f64,
    pfa: f64,
    /// Gate mask the energies below were computed for.
    mask_key: Vec<Range<usize>>,
    /// Template energy seen through the mask, per lag.
    energy: Vec<f64>,
    /// Threshold on |z| for the full search.
    threshold: f64,
    mask: Vec<f64>,
    y: Vec<f64>,
    corr: Vec<f64>,
    spec_y: Vec<Complex<f64>>,
    raw: Vec<f64>,
    seg: Vec<f64>,
    /// The template's sub-sample shift, replanned per call of `slice`.
    shift: FractionalDelay,
}

impl std::fmt::Debug for BurstCanceller {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BurstCanceller")
            .field("template_len", &self.template.values.len())
            .field("frame_len", &self.n)
            .field("threshold", &self.threshold)
            .finish()
    }
}

impl BurstCanceller {
    /// Plans cancellation of `template` in frames of `frame_len` samples with
    /// false-detection probability `pfa` per frame.
    pub fn new(template: BurstTemplate, frame_len: usize, pfa: f64) -> BurstCanceller {
        let n = frame_len.max(1);
        let l = template.values.len();
        let mut padded = vec![0.0; l + 2 * n];
        padded[n..n + l].copy_from_slice(&template.values);
        let mut xc = Xcorr::new(padded.len());
        let spec_t = xc.spectrum(&padded);
        let sq: Vec<f64> = padded.iter().map(|v| v * v).collect();
        let spec_t2 = xc.spectrum(&sq);
        // g = Σ_k ρ_noise(k) ρ_template(k) over k = −K..K.
        let e0: f64 = template.values.iter().map(|v| v * v).sum();
        let mut colour = 1.0;
        if e0 > 0.0 {
            for (k, rho) in template.noise_acf.iter().enumerate().skip(1) {
                let rt: f64 = template
                    .values
                    .iter()
                    .zip(&template.values[k.min(l)..])
                    .map(|(a, b)| a * b)
                    .sum::<f64>()
                    / e0;
                colour += 2.0 * rho * rt;
            }
        }
        let spec_y = xc.fwd.make_output_vec();
        BurstCanceller {
            n,
            padded,
            spec_t,
            spec_t2,
            colour: colour.max(1e-3),
            pfa,
            mask_key: Vec::new(),
            energy: Vec::new(),
            threshold: f64::INFINITY,
            mask: vec![0.0; n],
            y: vec![0.0; n],
            corr: vec![0.0; l + n + 1],
            spec_y,
            raw: vec![0.0; n + 2 * SHIFT_HALF_LEN],
            seg: vec![0.0; n + 2 * SHIFT_HALF_LEN],
            shift: FractionalDelay::new(0.0),
            xc,
            template,
        }
    }

    /// Frame length planned for, samples.
    pub fn frame_len(&self) -> usize {
        self.n
    }

    /// The template.
    pub fn template(&self) -> &BurstTemplate {
        &self.template
    }

    /// Noise-colour factor g (variance of the correlation over σ²·energy).
    pub fn colour_factor(&self) -> f64 {
        self.colour
    }

    /// Threshold on |z| of the full search for the current gates.
    pub fn threshold(&self) -> f64 {
        self.threshold
    }

    fn set_mask(&mut self, gates: &[Range<usize>]) {
        if self.mask_key.as_slice() == gates && !self.energy.is_empty() {
            return;
        }
        self.mask_key = gates.to_vec();
        self.mask.fill(0.0);
        for g in gates {
            let r = g.start.min(self.n)..g.end.min(self.n);
            self.mask[r].fill(1.0);
        }
        let sm = self.xc.spectrum(&self.mask);
        self.energy = vec![0.0; self.corr.len()];
        let st2 = std::mem::take(&mut self.spec_t2);
        self.xc.correlate(&st2, &sm, &mut self.energy);
        self.spec_t2 = st2;
        let peak = self.energy.iter().fold(0.0f64, |m, &e| m.max(e));
        let floor = 1e-6 * peak;
        for e in &mut self.energy {
            if *e <= floor {
                *e = 0.0;
            }
        }
        let lags = self.energy.iter().filter(|&&e| e > 0.0).count().max(1);
        self.threshold = q_inv(per_cell_pfa(self.pfa, lags as f64));
    }

    /// Template value at (integer) index `i`, 0 outside.
    fn t_at(&self, i: i64) -> f64 {
        let p = i + self.n as i64;
        if p < 0 || p as usize >= self.padded.len() {
            0.0
        } else {
            self.padded[p as usize]
        }
    }

    /// Correlation and masked energy at template lag `lag` (direct sums).
    fn direct(&self, lag: i64) -> (f64, f64) {
        let mut c = 0.0;
        let mut e = 0.0;
        for i in 0..self.n {
            let t = self.t_at(lag + i as i64);
            c += t * self.y[i];
            e += t * t * self.mask[i];
        }
        (c, e)
    }

    /// Writes the template at indices `lag + i + delta` for i in
    /// −SHIFT_HALF_LEN..n + SHIFT_HALF_LEN into `seg` (fractional-delay filter).
    fn slice(&mut self, lag: i64, delta: f64) {
        let h = SHIFT_HALF_LEN as i64;
        for j in 0..self.raw.len() {
            self.raw[j] = self.t_at(lag - h + j as i64);
        }
        self.shift.set_delay(-delta);
        self.shift.apply(&self.raw, &mut self.seg);
    }

    /// Finds and subtracts the burst in `x` (volts, one frame of the planned
    /// length); `gates` are the samples free of returns, `predicted_lag` a
    /// template lag where the burst is expected (from the previous frame and
    /// the trigger times), tried first. Returns what was subtracted, or `None`
    /// when no burst crossed its threshold.
    pub fn cancel(
        &mut self,
        x: &mut [f64],
        gates: &[Range<usize>],
        predicted_lag: Option<i64>,
    ) -> Option<Cancelled> {
        // A zero (or NaN) sigma means learning saw no noise: nothing to scale by.
        if x.len() != self.n
            || self.template.values.is_empty()
            || self.template.sigma_v.is_nan()
            || self.template.sigma_v <= 0.0
        {
            return None;
        }
        self.set_mask(gates);
        let off = self.template.offset_v;
        for ((y, &v), &m) in self.y.iter_mut().zip(x.iter()).zip(&self.mask) {
            *y = if v.is_finite() { (v - off) * m } else { 0.0 };
        }
        let scale = self.template.sigma_v * self.colour.sqrt();
        let z_of = |c: f64, e: f64| if e > 0.0 { c / (scale * e.sqrt()) } else { 0.0 };
        // The lag is chosen by maximum likelihood for the burst at its learned
        // amplitude (the largest 2c − e, i.e. the smallest residual); the
        // normalised correlation z at that lag is then held against the
        // Neyman-Pearson threshold. Choosing by z alone would favour a lag
        // where a strong part of the template partly matches a weak burst end.
        let mut found: Option<(i64, f64)> = None;
        if let Some(p) = predicted_lag {
            // A narrow window of 5 lags: its own, much lower threshold.
            let t = q_inv(per_cell_pfa(self.pfa, 5.0));
            let best = (p - 2..=p + 2)
                .map(|l| (l, self.direct(l)))
                .filter(|(_, (_, e))| *e > 0.0)
                .max_by(|a, b| (2.0 * a.1.0 - a.1.1).total_cmp(&(2.0 * b.1.0 - b.1.1)));
            if let Some((l, (c, e))) = best {
                let z = z_of(c, e);
                if z >= t {
                    found = Some((l, z));
                }
            }
        }
        if found.is_none() {
            let y = std::mem::take(&mut self.y);
            let mut sy = std::mem::take(&mut self.spec_y);
            self.xc.spectrum_into(&y, &mut sy);
            self.y = y;
            let st = std::mem::take(&mut self.spec_t);
            let mut corr = std::mem::take(&mut self.corr);
            self.xc.correlate(&st, &sy, &mut corr);
            self.spec_t = st;
            self.spec_y = sy;
            let best = (0..corr.len())
                .filter(|&q| self.energy[q] > 0.0)
                .max_by(|&a, &b| {
                    (2.0 * corr[a] - self.energy[a]).total_cmp(&(2.0 * corr[b] - self.energy[b]))
                });
            if let Some(q) = best {
                let z = z_of(corr[q], self.energy[q]);
                if z >= self.threshold {
                    found = Some((q as i64 - self.n as i64, z));
                }
            }
            self.corr = corr;
        }
        let (mut lag, z) = found?;
        // Sub-sample shift: Gauss-Newton on x ≈ a·T(i + lag + δ) with the
        // template's slope, twice (the second pass from the shifted slice).
        let mut delta = 0.0;
        let mut amplitude = 0.0;
        for _ in 0..3 {
            self.slice(lag, delta);
            let seg = &self.seg[SHIFT_HALF_LEN..SHIFT_HALF_LEN + self.n];
            let (mut sxx, mut sxd, mut sdd, mut sy0, mut syd) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for i in 1..self.n - 1 {
                let m = self.mask[i];
                if m == 0.0 {
                    continue;
                }
                let t0 = seg[i];
                let d = 0.5 * (seg[i + 1] - seg[i - 1]);
                sxx += t0 * t0;
                sxd += t0 * d;
                sdd += d * d;
                sy0 += self.y[i] * t0;
                syd += self.y[i] * d;
            }
            let det = sxx * sdd - sxd * sxd;
            if !(det > 0.0 && sxx > 0.0) {
                break;
            }
            let a = (sy0 * sdd - syd * sxd) / det;
            let b = (sxx * syd - sxd * sy0) / det;
            amplitude = a;
            if a.abs() > 0.0 {
                delta += (b / a).clamp(-1.0, 1.0);
            }
            // Keep the fractional part small: move whole samples into the lag.
            let whole = delta.round();
            lag += whole as i64;
            delta -= whole;
        }
        self.slice(lag, delta);
        let seg = &self.seg[SHIFT_HALF_LEN..SHIFT_HALF_LEN + self.n];
        let (mut num, mut den) = (0.0, 0.0);
        for ((y, s), m) in self.y.iter().zip(seg).zip(&self.mask) {
            num += y * s;
            den += s * s * m;
        }
        if den > 0.0 {
            amplitude = num / den;
        }
        for (v, s) in x.iter_mut().zip(seg) {
            *v -= amplitude * s;
        }
        Some(Cancelled {
            lag: lag as f64 + delta,
            amplitude,
            z,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn burst(t: f64) -> f64 {
        let d = 20_000.0;
        if !(0.0..=d).contains(&t) {
            return 0.0;
        }
        let env = (std::f64::consts::PI * t / d).sin().powi(2);
        env * [(0.0013, 0.7), (0.0031, 2.6), (0.0067, 4.5)]
            .iter()
            .map(|(f, ph)| (2.0 * std::f64::consts::PI * f * t + ph).sin())
            .sum::<f64>()
            * 0.15
    }

    #[test]
    fn learns_and_cancels_a_burst_spread_over_frames() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 0.01).unwrap();
        let (n, period) = (1000usize, 1600i64);
        let gates = [0..300usize, 600..1000];
        let mut learner = BurstLearner::new(22_000, 0.012);
        let make = |k: i64, start: f64, rng: &mut ChaCha8Rng| -> Vec<f64> {
            (0..n)
                .map(|i| burst((k * period + i as f64 as i64) as f64 - start) + noise.sample(rng))
                .collect()
        };
        // Bursts start every 100 frames at a random sub-period phase.
        let starts: Vec<f64> = (0..12)
            .map(|b| b as f64 * 100.0 * period as f64 + 37.3 * b as f64 * 11.0)
            .collect();
        let at = |k: i64| {
            starts
                .iter()
                .copied()
                .find(|s| {
                    (k * period) as f64 + n as f64 > *s && ((k * period) as f64) < s + 20_000.0
                })
                .unwrap_or(-1e12)
        };
        for k in 0..1000i64 {
            let x = make(k, at(k), &mut rng);
            learner.push(k * period, &x, &gates);
        }
        let t = learner.finish().expect("bursts were present");
        assert!(t.occurrences >= 8, "{}", t.occurrences);
        assert!((t.sigma_v - 0.01).abs() < 0.001, "{}", t.sigma_v);
        let mut c = BurstCanceller::new(t, n, 1e-3);
        // A frame in the middle of a burst: after cancellation the residual is noise.
        let k = 1106;
        let mut x = make(k, at(k), &mut rng);
        let before: f64 = x.iter().map(|v| v * v).sum::<f64>() / n as f64;
        let got = c.cancel(&mut x, &gates, None).expect("burst detected");
        let after: f64 = x.iter().map(|v| v * v).sum::<f64>() / n as f64;
        assert!(before > 10.0 * 1e-4, "{before}");
        assert!(
            after < 1.3e-4,
            "residual power {after} (noise 1e-4), {got:?}"
        );
        // A burst-free frame is left alone.
        let mut q = make(50, -1e12, &mut rng);
        let orig = q.clone();
        assert!(c.cancel(&mut q, &gates, None).is_none());
        assert_eq!(q, orig);
    }
}
