//! Timing of one pulse: the instant its leading edge crosses a fraction of its
//! peak, by the method the scene chooses, with its one-sigma uncertainty.
//!
//! Named `pulse_timing` (not `timing`) because `pipeline::timing` is the
//! stage; this module times one pulse, the stage times every return.

use crate::dsp::crossing;
use crate::dsp::interp;
use crate::dsp::mlfit;
use crate::dsp::pulse::{PulseShape, Shape};
use crate::scene::TimingMethod;

/// What the timing methods need about one pulse.
#[derive(Debug, Clone, Copy)]
pub struct TimingInput<'a> {
    /// Samples, volts.
    pub x: &'a [f64],
    /// Noise mean, volts.
    pub mean_v: f64,
    /// Noise sigma, volts.
    pub sigma_v: f64,
    /// Detector output indexed by peak position (matched filter or raw).
    pub y: &'a [f64],
    /// ‖template‖: amplitude = y / norm.
    pub norm: f64,
    /// Pulse shape (samples).
    pub pulse: &'a Shape,
    /// Sample index of the detector's local maximum.
    pub peak: usize,
    /// Constant fraction (also the timing point of the model-based methods).
    pub fraction: f64,
    /// Leading-edge level above the mean, volts.
    pub leading_edge_v: f64,
}

/// A timed pulse.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timed {
    /// Fractional sample index of the timing point.
    pub index: f64,
    /// Fractional sample index of the pulse peak.
    pub peak_index: f64,
    /// Amplitude above the noise mean, volts.
    pub amplitude_v: f64,
    /// One-sigma timing uncertainty of this method, samples.
    pub sigma_samples: f64,
    /// Cramer-Rao bound for the delay with the pulse shape, samples.
    pub crlb_samples: f64,
    /// The method could not time the pulse and the matched-filter peak was used.
    pub fallback: bool,
}

/// Times the pulse around `input.peak` with `method`.
pub fn time_pulse(method: TimingMethod, input: &TimingInput) -> Timed {
    time_pulse_with(method, input, &mlfit::FitOptions::default())
}

/// [`time_pulse`] with the ML fit's options `fit` (the other methods do
/// not read them).
pub fn time_pulse_with(method: TimingMethod, input: &TimingInput, fit: &mlfit::FitOptions) -> Timed {
    let peak_fit = peak_interp(input, false);
    match method {
        TimingMethod::PeakParabolic => peak_fit,
        TimingMethod::PeakGaussian => peak_interp(input, true),
        TimingMethod::Ml => ml(input, peak_fit.peak_index, fit),
        TimingMethod::ConstantFraction => constant_fraction(input).unwrap_or(Timed { fallback: true, ..peak_fit }),
        TimingMethod::LeadingEdge => leading_edge(input).unwrap_or(Timed { fallback: true, ..peak_fit }),
    }
}

/// How well the shape fits a timed pulse: the least-squares amplitude at
/// the timed peak position and the residual over the shape's support.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShapeFit {
    /// Σ residual² / σ² over the support.
    pub chi2: f64,
    /// Samples in the sum.
    pub samples: usize,
    /// Fitted peak position, fractional sample index.
    pub peak_index: f64,
    /// The least χ² lies at the edge of the searched positions: the fit found
    /// no minimum there, and its position says nothing about the pulse.
    pub at_edge: bool,
}

impl ShapeFit {
    /// Fits `pulse` to `x − mean_v` by least squares in amplitude and peak
    /// position (searched within ±2 samples of `near`, in quarter samples,
    /// then between them) and measures the residual in units of `sigma_v`.
    pub fn measure(x: &[f64], mean_v: f64, sigma_v: f64, pulse: &Shape, near: f64) -> ShapeFit {
        // The thread's own tables: 12 kB zeroed once per thread, not once
        // per fit (fresh ones where a fit runs inside another's, or while
        // the thread's storage is torn down). Every slot a fit reads is
        // written first, so what a previous fit left there is never read.
        thread_local! {
            static TABLES: std::cell::RefCell<ShapeTables> = const { std::cell::RefCell::new(ShapeTables::ZERO) };
        }
        TABLES
            .try_with(|cell| cell.try_borrow_mut().ok().map(|mut t| ShapeFit::measure_in(x, mean_v, sigma_v, pulse, near, &mut t)))
            .ok()
            .flatten()
            .unwrap_or_else(|| {
                let mut fresh = ShapeTables::ZERO;
                ShapeFit::measure_in(x, mean_v, sigma_v, pulse, near, &mut fresh)
            })
    }

    /// [`ShapeFit::measure`] with the pulse's values kept in `tables`.
    fn measure_in(x: &[f64], mean_v: f64, sigma_v: f64, pulse: &Shape, near: f64, tables: &mut ShapeTables) -> ShapeFit {
        // The 17 positions share the pulse's values: sample k at position
        // near + j/4 sits at offset (4k − j)/4 − near, so each value is
        // evaluated once (about 4 per sample instead of 17) and looked up by
        // 4k − j.
        let (lo, hi) = pulse.support();
        let k_min = (near - 2.0 + lo).ceil().max(0.0) as i64;
        let k_max = (near + 2.0 + hi).floor() as i64;
        let m_min = 4 * k_min - 8;
        let len = (4 * (k_max - k_min) + 17).max(0) as usize;
        let ShapeTables { values: table, grid: scratch } = tables;
        let fit = |j: i64, values: Option<&Phases>| ShapeFit::at(x, mean_v, sigma_v, pulse, near + 0.25 * j as f64, j, m_min, values);
        let values = (len <= SHAPE_TABLE).then(|| {
            // Slot i = 4q + r holds the pulse at (i + m_min)/4 − near, kept
            // as four grids of whole samples (phase r, index q), each filled
            // at once: a position reads one of them, contiguously.
            let mut lens = [0; 4];
            for r in 0..4usize.min(len) {
                lens[r] = (len - r).div_ceil(4);
                let t0 = (r as i64 + m_min) as f64 * 0.25 - near;
                match pulse {
                    // The values alone (the same bits as fill_grid's).
                    Shape::Parametric(p) => p.fill_values(t0, &mut table[r][..lens[r]]),
                    Shape::Table(tp) => {
                        let g = &mut scratch[..lens[r]];
                        tp.fill_grid(t0, g);
                        for (t, &(v, _)) in table[r].iter_mut().zip(g.iter()) {
                            *t = v;
                        }
                    }
                }
            }
            Phases { grids: table, lens }
        });
        let mut chi2 = [f64::NAN; 17];
        let mut best: Option<(i64, ShapeFit)> = None;
        for j in -8..=8 {
            let f = fit(j, values.as_ref());
            chi2[(j + 8) as usize] = f.chi2;
            if best.as_ref().is_none_or(|b| f.chi2 < b.1.chi2) {
                best = Some((j, f));
            }
        }
        let (j, mut fit) = best.expect("17 positions");
        fit.at_edge = j.abs() == 8;
        // Between grid positions: the parabola through the least χ² and its
        // neighbours (χ² is quadratic in a small shift of the peak). A
        // quarter-sample grid alone leaves (SNR·‖ṡ‖·δ)² of χ² at a shift δ ≤
        // 1/8 sample: at high SNR far more than the noise, read as a misfit.
        if !fit.at_edge {
            let i = (j + 8) as usize;
            let (l, c, r) = (chi2[i - 1], chi2[i], chi2[i + 1]);
            let curvature = l - 2.0 * c + r;
            if curvature > 0.0 {
                let d = (0.5 * (l - r) / curvature).clamp(-0.5, 0.5);
                fit.chi2 = (c - 0.25 * (l - r) * d).max(0.0);
                fit.peak_index = near + 0.25 * (j as f64 + d);
            }
        }
        fit
    }

    /// The fit with the peak at `peak_index` = near + j/4 (amplitude by
    /// least squares); `values`, when given, holds the pulse's values by
    /// 4k − j − `m_min` (slot 4q + r in phase r at q: the samples read one
    /// phase, contiguously, summed in `math::sum`'s lane order), else the
    /// pulse is evaluated at each sample.
    #[allow(clippy::too_many_arguments)]
    fn at(x: &[f64], mean_v: f64, sigma_v: f64, pulse: &Shape, peak_index: f64, j: i64, m_min: i64, values: Option<&Phases>) -> ShapeFit {
        let (lo, hi) = pulse.support();
        let n = x.len();
        let first = (peak_index + lo).ceil().max(0.0) as usize;
        let last = ((peak_index + hi).floor().max(0.0) as usize).min(n.saturating_sub(1));
        if first > last || !(sigma_v > 0.0) {
            return ShapeFit { chi2: 0.0, samples: 0, peak_index, at_edge: false };
        }
        let base = 4 * first as i64 - j - m_min;
        let count = last + 1 - first;
        let phase = values.and_then(|t| {
            let (r, q) = ((base.rem_euclid(4)) as usize, base.div_euclid(4));
            (base >= 0 && q as usize + count <= t.lens[r]).then(|| &t.grids[r][q as usize..q as usize + count])
        });
        let (ss, xs, xx) = match phase {
            Some(s) => crate::math::sum::fit_sums(&x[first..=last], s, mean_v),
            None => {
                let (mut ss, mut xs, mut xx) = (0.0, 0.0, 0.0);
                for (k, &v) in x.iter().enumerate().take(last + 1).skip(first) {
                    let s = pulse.value_and_slope(k as f64 - peak_index).0;
                    let v = v - mean_v;
                    ss += s * s;
                    xs += v * s;
                    xx += v * v;
                }
                (ss, xs, xx)
            }
        };
        let chi2 = if ss > 0.0 { (xx - xs * xs / ss).max(0.0) } else { xx } / (sigma_v * sigma_v);
        ShapeFit { chi2, samples: last + 1 - first, peak_index, at_edge: false }
    }

    /// Residual degrees of freedom (amplitude and position fitted).
    pub fn dof(&self) -> f64 {
        self.samples.saturating_sub(2) as f64
    }

    /// True when the residual exceeds noise by more than `z` of its own
    /// standard deviations (Gaussian approximation of χ², with the spread
    /// widened by `correlation_gain` = 1 + 2Σρ(k)² for coloured noise).
    pub fn mismatched(&self, z: f64, correlation_gain: f64) -> bool {
        let dof = self.dof();
        dof >= 4.0 && self.chi2 > dof + z * (2.0 * dof * correlation_gain.max(1.0)).sqrt()
    }
}

/// Where a shape that does not fit the data is uncertain about the timing
/// point: the constant-fraction crossing read off the samples minus the
/// fitted model's own fraction point, samples (`None` when the crossing
/// fails, or when the fit's least χ² lies at the edge of its search, where
/// its position is where the search stopped, not where the model fits).
/// For a fitting shape the two agree within the noise (whose
/// scatter of the gap [`ErrorTable::gap_noise`](crate::detect::error_table::ErrorTable::gap_noise)
/// measures); the gap a mismatched one leaves changes with amplitude and
/// sub-sample phase, and no noise-only sigma holds it.
pub fn mismatch_gap(input: &TimingInput, fit: &ShapeFit) -> Option<f64> {
    if fit.at_edge {
        return None;
    }
    constant_fraction(input).map(|cf| cf.index - (fit.peak_index + input.pulse.fraction_offset(input.fraction)))
}

/// Pulse values [`ShapeFit::measure`] keeps in the thread's tables (4 per
/// sample of the support plus margins); longer supports are evaluated directly.
const SHAPE_TABLE: usize = 1024;

/// [`ShapeFit::measure`]'s tables: the pulse's values in four phases and,
/// for a measured shape, its (value, slope) scratch.
struct ShapeTables {
    values: [[f64; SHAPE_TABLE / 4 + 1]; 4],
    grid: [(f64, f64); SHAPE_TABLE / 4 + 1],
}

impl ShapeTables {
    const ZERO: ShapeTables = ShapeTables { values: [[0.0; SHAPE_TABLE / 4 + 1]; 4], grid: [(0.0, 0.0); SHAPE_TABLE / 4 + 1] };
}

/// The pulse's values at quarter-sample offsets for [`ShapeFit::measure`]:
/// four grids of whole samples (phase r at q is slot 4q + r).
struct Phases<'a> {
    grids: &'a [[f64; SHAPE_TABLE / 4 + 1]; 4],
    /// Filled length of each grid.
    lens: [usize; 4],
}

/// Standard deviations of χ² beyond its mean at which a fit is called a
/// shape mismatch (one-sided Gaussian tail 1.3e-3 per pulse).
pub const MISMATCH_Z: f64 = 3.0;

/// Cramer-Rao bound of the delay, samples: sigma / (A sqrt(Σ s'(k - peak)²)).
pub fn crlb_samples(pulse: &Shape, n: usize, peak_index: f64, amplitude_v: f64, sigma_v: f64) -> f64 {
    let (lo, hi) = pulse.support();
    let first = (peak_index + lo).floor().max(0.0) as usize;
    let last = ((peak_index + hi).ceil().max(0.0) as usize).min(n.saturating_sub(1));
    let mut energy = 0.0;
    pulse.for_each_on_grid(first as f64 - peak_index, (last + 1).saturating_sub(first), |_, _, s| energy += s * s);
    let a = amplitude_v.abs();
    if energy > 0.0 && a > 0.0 {
        sigma_v / (a * energy.sqrt())
    } else {
        f64::INFINITY
    }
}

/// Scratch for [`joint_crlb_samples`], kept by the caller.
#[derive(Debug, Default, Clone)]
pub struct JointScratch {
    order: Vec<usize>,
    fisher: Vec<f64>,
    work: Vec<f64>,
    rhs: Vec<f64>,
}

/// Cramér–Rao bounds (samples) on the delays of pulses fitted jointly:
/// `pulses` are (peak index, amplitude V); every amplitude and delay is a
/// parameter, and pulses whose supports overlap share a Fisher matrix
/// F = JᵀJ/σ² (J: ∂model/∂A_i = s(t − τ_i), ∂model/∂τ_i = −A_i s'(t − τ_i)),
/// whose inverse's delay diagonal is the bound. An isolated pulse gets its
/// own 2×2 bound (the delay's, with its amplitude estimated too); two pulses
/// closer than a pulse width get much larger bounds than either alone,
/// which is what a joint fit can really do. `out[i]` is pulse i's bound
/// (infinite where the matrix is singular).
pub fn joint_crlb_samples(pulse: &Shape, n: usize, pulses: &[(f64, f64)], sigma_v: f64, scratch: &mut JointScratch, out: &mut Vec<f64>) {
    out.clear();
    out.resize(pulses.len(), f64::INFINITY);
    let (lo, hi) = pulse.support();
    let last_sample = n.saturating_sub(1);
    let span = |p: f64| {
        let first = (p + lo).floor().max(0.0) as usize;
        let last = ((p + hi).ceil().max(0.0) as usize).min(last_sample);
        (first, last)
    };
    let order = &mut scratch.order;
    order.clear();
    order.extend(0..pulses.len());
    order.sort_by(|&a, &b| pulses[a].0.total_cmp(&pulses[b].0));
    // Clusters of pulses whose supports overlap, in peak order.
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        let mut reach = span(pulses[order[start]].0).1;
        while end < order.len() && span(pulses[order[end]].0).0 <= reach {
            reach = reach.max(span(pulses[order[end]].0).1);
            end += 1;
        }
        let cluster = &order[start..end];
        let m = 2 * cluster.len();
        let f = &mut scratch.fisher;
        f.clear();
        f.resize(m * m, 0.0);
        for (a, &i) in cluster.iter().enumerate() {
            for (b, &j) in cluster.iter().enumerate().skip(a) {
                let (si, sj) = (span(pulses[i].0), span(pulses[j].0));
                let (first, last) = (si.0.max(sj.0), si.1.min(sj.1));
                if first > last {
                    continue;
                }
                let (mut vv, mut vd, mut dv, mut dd) = (0.0, 0.0, 0.0, 0.0);
                // Both pulses on the grid (vectorised), a block at a time.
                const BLOCK: usize = 64;
                let (mut gi, mut gj) = ([(0.0, 0.0); BLOCK], [(0.0, 0.0); BLOCK]);
                let mut t = first;
                while t <= last {
                    let len = (last + 1 - t).min(BLOCK);
                    pulse.fill_grid(t as f64 - pulses[i].0, &mut gi[..len]);
                    if i == j {
                        gj[..len].copy_from_slice(&gi[..len]);
                    } else {
                        pulse.fill_grid(t as f64 - pulses[j].0, &mut gj[..len]);
                    }
                    for (&(vi, di), &(vj, dj)) in gi[..len].iter().zip(&gj[..len]) {
                        let (di, dj) = (-pulses[i].1 * di, -pulses[j].1 * dj);
                        vv += vi * vj;
                        vd += vi * dj;
                        dv += di * vj;
                        dd += di * dj;
                    }
                    t += len;
                }
                for (p, q, v) in [(2 * a, 2 * b, vv), (2 * a, 2 * b + 1, vd), (2 * a + 1, 2 * b, dv), (2 * a + 1, 2 * b + 1, dd)] {
                    f[p * m + q] = v;
                    f[q * m + p] = v;
                }
            }
        }
        for (a, &i) in cluster.iter().enumerate() {
            scratch.work.clear();
            scratch.work.extend_from_slice(f);
            scratch.rhs.clear();
            scratch.rhs.resize(m, 0.0);
            scratch.rhs[2 * a + 1] = 1.0;
            if crate::math::linalg::solve_in_place(&mut scratch.work, &mut scratch.rhs, m, 0.0) {
                let var = scratch.rhs[2 * a + 1];
                if var.is_finite() && var > 0.0 {
                    out[i] = sigma_v * var.sqrt();
                }
            }
        }
        start = end;
    }
}

fn finish(input: &TimingInput, peak_index: f64, amplitude_v: f64, index: f64, sigma_samples: Option<f64>) -> Timed {
    let crlb = crlb_samples(input.pulse, input.x.len(), peak_index, amplitude_v, input.sigma_v);
    Timed {
        index,
        peak_index,
        amplitude_v,
        sigma_samples: sigma_samples.unwrap_or(crlb),
        crlb_samples: crlb,
        fallback: false,
    }
}

fn peak_interp(input: &TimingInput, gaussian: bool) -> Timed {
    let y = input.y;
    let p = input.peak;
    let (d, h) = if p == 0 || p + 1 >= y.len() {
        (0.0, y[p])
    } else if gaussian {
        interp::gaussian(y[p - 1], y[p], y[p + 1])
    } else {
        interp::parabolic(y[p - 1], y[p], y[p + 1])
    };
    let peak_index = p as f64 + d;
    let amplitude = h / input.norm;
    finish(input, peak_index, amplitude, peak_index + input.pulse.fraction_offset(input.fraction), None)
}

fn ml(input: &TimingInput, start: f64, opts: &mlfit::FitOptions) -> Timed {
    let (lo, hi) = input.pulse.support();
    let n = input.x.len();
    let first = (start + lo).floor().max(0.0) as usize;
    let last = ((start + hi).ceil().max(0.0) as usize + 1).min(n);
    if last <= first + 2 {
        return peak_interp(input, false);
    }
    let fit = mlfit::fit_delay_with(input.x, input.mean_v, input.pulse, start, first..last, 30, opts);
    if !fit.amplitude.is_finite() || !fit.delay.is_finite() || fit.amplitude <= 0.0 || (fit.delay - start).abs() > 3.0 {
        return Timed { fallback: true, ..peak_interp(input, false) };
    }
    finish(input, fit.delay, fit.amplitude, fit.delay + input.pulse.fraction_offset(input.fraction), None)
}

/// The raw-sample peak near the detector's peak. Its height is a
/// least-squares parabola over the samples near the top (those above 90 % of
/// the largest), so the noise of a single sample does not bias the
/// constant-fraction level upwards at low SNR.
struct RawTop {
    /// The largest sample near the detector's peak.
    k: usize,
    /// First and last sample of the parabola (both `k`: the height is `x[k]`).
    a: usize,
    b: usize,
    /// The parabola's vertex, samples from `a` (none: the height is `x[k]`).
    vertex: Option<f64>,
    /// The height, volts.
    height_v: f64,
}

impl RawTop {
    /// The height the same samples give a unit pulse of the model peaking at
    /// `peak_index` (below 1 where the samples straddle the peak; `None`
    /// where the model does not describe the top: its peak, placed by the
    /// crossing, more than a sample from the samples' own top).
    fn model_height(&self, input: &TimingInput, peak_index: f64) -> Option<f64> {
        let top = self.vertex.map_or(self.k as f64, |v| self.a as f64 + v);
        if !((peak_index - top).abs() <= 1.0) {
            return None;
        }
        let unit = |k: usize| input.pulse.value_and_slope(k as f64 - peak_index).0;
        let h = match self.vertex {
            Some(_) => {
                let mut v = [0.0; 17];
                let len = self.b - self.a + 1;
                for (i, vi) in v.iter_mut().enumerate().take(len) {
                    *vi = unit(self.a + i);
                }
                quadratic_peak(&v[..len], (self.k - self.a) as f64).map_or(unit(self.k), |q| q.0)
            }
            None => unit(self.k),
        };
        (h > 0.5 && h < 1.5).then_some(h)
    }
}

fn raw_top(input: &TimingInput) -> RawTop {
    let x = input.x;
    let w = (input.pulse.fwhm() * 0.5).ceil().max(2.0) as usize;
    let lo = input.peak.saturating_sub(w);
    let hi = (input.peak + w + 1).min(x.len());
    let k = (lo..hi).max_by(|&a, &b| x[a].total_cmp(&x[b])).unwrap_or(input.peak);
    let top = input.mean_v + 0.9 * (x[k] - input.mean_v);
    let mut a = k;
    while a > 0 && k - a < 8 && x[a - 1] > top {
        a -= 1;
    }
    let mut b = k;
    while b + 1 < x.len() && b - k < 8 && x[b + 1] > top {
        b += 1;
    }
    let half = (k - a).max(b - k).max(1);
    let (a, b) = (k.saturating_sub(half), (k + half).min(x.len() - 1));
    match (b - a >= 2).then(|| quadratic_peak(&x[a..=b], (k - a) as f64)).flatten() {
        Some((height_v, vertex)) => RawTop { k, a, b, vertex: Some(vertex), height_v },
        None => RawTop { k, a: k, b: k, vertex: None, height_v: x[k] },
    }
}

/// Vertex height and position (from the first sample) of the least-squares
/// parabola through `y` (abscissae 0..n), if it opens downwards with its
/// vertex within one sample of `near`.
fn quadratic_peak(y: &[f64], near: f64) -> Option<(f64, f64)> {
    let n = y.len() as f64;
    let c = (n - 1.0) / 2.0;
    let (mut s2, mut s4, mut sy, mut sxy, mut sx2y) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (i, &v) in y.iter().enumerate() {
        let t = i as f64 - c;
        s2 += t * t;
        s4 += t * t * t * t;
        sy += v;
        sxy += t * v;
        sx2y += t * t * v;
    }
    // Centred abscissae: odd sums vanish, so the normal equations decouple.
    let a2 = (n * sx2y - s2 * sy) / (n * s4 - s2 * s2);
    let a1 = sxy / s2;
    let a0 = (sy - a2 * s2) / n;
    if !(a2 < 0.0) {
        return None;
    }
    let t = -a1 / (2.0 * a2);
    ((t + c - near).abs() <= 1.0).then_some((a0 + a1 * t + a2 * t * t, t + c))
}

/// Variance gain of coloured noise on a crossing method's error (1 for
/// white noise, and for the other methods).
///
/// A crossing method's small-signal error is (n_c − q·δA)/slope: the noise
/// n_c at the crossing (the two samples around it, weighted as the straight
/// line weighs them) less the error δA of the peak height (a least-squares
/// parabola over the samples near the top, whose weights are linear in the
/// samples) times q, the level's fraction of the peak. Its width is
/// measured on white noise; on a band-limited receiver's noise the crossing
/// and the top, a few samples apart, share their slow excursions: the level
/// moves with the crossing's noise, and the error shrinks (the lab set-up's
/// 19.5 MHz receiver: about two thirds of the white-noise width). The gain
/// is the ratio of cᵀRc + q²wᵀRw − 2q·cᵀRw to the same with R = I (`rho`
/// the normalised autocorrelation from lag 0, zero beyond its last lag).
pub fn crossing_colour_gain(method: TimingMethod, input: &TimingInput, timed: &Timed, rho: &[f64]) -> f64 {
    let top = raw_top(input);
    let a = top.height_v - input.mean_v;
    let q = match method {
        TimingMethod::ConstantFraction => input.fraction,
        TimingMethod::LeadingEdge => input.leading_edge_v / a,
        _ => return 1.0,
    };
    if rho.len() < 2 || !(a > 0.0) || !timed.index.is_finite() || timed.fallback {
        return 1.0;
    }
    let r = |lag: f64| {
        let lag = lag.abs();
        let i = lag.floor() as usize;
        let u = lag - i as f64;
        let at = |k: usize| rho.get(k).copied().unwrap_or(0.0);
        (1.0 - u) * at(i) + u * at(i + 1)
    };
    // The peak height's weights on samples a..=b (one sample where no parabola was fitted).
    let mut w = [0.0; 17];
    let len = top.b - top.a + 1;
    match top.vertex {
        Some(v) => {
            let n = len as f64;
            let c = (n - 1.0) / 2.0;
            let (s2, s4) = (0..len).fold((0.0, 0.0), |(s2, s4), i| {
                let t = i as f64 - c;
                (s2 + t * t, s4 + t * t * t * t)
            });
            let t = v - c;
            for (i, wi) in w.iter_mut().enumerate().take(len) {
                let ti = i as f64 - c;
                *wi = 1.0 / n + ti * t / s2 + (t * t - s2 / n) * (n * ti * ti - s2) / (n * s4 - s2 * s2);
            }
        }
        None => w[0] = 1.0,
    }
    let w = &w[..len];
    let j = timed.index.floor();
    let u = timed.index - j;
    let c = [(j, 1.0 - u), (j + 1.0, u)];
    let at = |i: usize| (top.a + i) as f64;
    let crc = c[0].1 * c[0].1 + c[1].1 * c[1].1 + 2.0 * c[0].1 * c[1].1 * r(1.0);
    let wrw: f64 = (0..len).map(|i| (0..len).map(|k| w[i] * w[k] * r(at(i) - at(k))).sum::<f64>()).sum();
    let crw: f64 = (0..len).map(|i| c.iter().map(|&(t, ci)| ci * w[i] * r(at(i) - t)).sum::<f64>()).sum();
    let white = c[0].1 * c[0].1 + c[1].1 * c[1].1 + q * q * w.iter().map(|v| v * v).sum::<f64>();
    let coloured = crc + q * q * wrw - 2.0 * q * crw;
    if white > 0.0 && coloured > 0.0 { coloured / white } else { 1.0 }
}

fn search_start(input: &TimingInput, k: usize) -> usize {
    let back = (-input.pulse.support().0 * 2.0).ceil() as usize + 2;
    k.saturating_sub(back)
}

fn constant_fraction(input: &TimingInput) -> Option<Timed> {
    let top = raw_top(input);
    let k = top.k;
    let crossing = |a: f64| {
        let t = crossing::rising_before(input.x, input.mean_v + input.fraction * a, search_start(input, k), k)?;
        Some(between_samples(input.pulse, input.fraction, t))
    };
    let raw = top.height_v - input.mean_v;
    if !(raw > 0.0) {
        return None;
    }
    // The crossing places the pulse; where it falls between samples decides
    // how far the top's samples are below its peak: the level follows the
    // peak the model then implies (twice: the second place is the settled one).
    let (mut a, mut t) = (raw, crossing(raw)?);
    for _ in 0..2 {
        let Some(h) = top.model_height(input, t - input.pulse.fraction_offset(input.fraction)) else { break };
        a = raw / h;
        t = crossing(a)?;
    }
    // Small-signal σ: the noise at the crossing, plus the peak's scaled by
    // the fraction, over the model's slope there (a slope read from two noisy
    // samples would swing with the noise it is meant to scale).
    let slope = a * model_slope(input.pulse, input.fraction);
    let sigma = input.sigma_v * (1.0 + input.fraction * input.fraction).sqrt() / slope.max(f64::MIN_POSITIVE);
    Some(finish(input, k as f64, a, t, Some(sigma)))
}

/// Where the pulse crosses `fraction` of its peak, given `t`, the crossing
/// read by straight-line interpolation between the two samples around it.
///
/// A leading edge is curved between samples, so the straight line misplaces
/// the crossing by an amount that depends on where the samples fall on the
/// edge (the sub-sample phase): a bias that averages over phases to a
/// constant the calibration absorbs, but that scatters report to report
/// once noise is averaged down, and that a calibration at one phase
/// distribution does not remove at another. The model shape says what the
/// straight line makes of a pulse crossing at t*: t* is moved until it makes
/// `t` of it (a few fixed-point steps: the error changes slowly with t*). A
/// shape that does not fit leaves the crossing where it was read (the
/// mismatch is then in the sigma, see [`mismatch_gap`]).
fn between_samples(pulse: &Shape, fraction: f64, t: f64) -> f64 {
    let j = t.floor();
    let offset = pulse.fraction_offset(fraction);
    // The straight line's crossing for a unit pulse whose edge crosses
    // `fraction` at `crossing`.
    let straight = |crossing: f64| {
        let peak = crossing - offset;
        let (a, b) = (pulse.value_and_slope(j - peak).0, pulse.value_and_slope(j + 1.0 - peak).0);
        (b > a).then(|| j + (fraction - a) / (b - a))
    };
    let mut crossing = t;
    for _ in 0..4 {
        let Some(s) = straight(crossing) else { return t };
        let step = t - s;
        crossing += step;
        if step.abs() < 1e-9 {
            break;
        }
    }
    if (crossing - t).abs() < 1.0 && crossing.is_finite() { crossing } else { t }
}

/// Slope of the unit-peak shape where its leading edge crosses `fraction`, per sample.
fn model_slope(pulse: &Shape, fraction: f64) -> f64 {
    pulse.value_and_slope(pulse.fraction_offset(fraction.clamp(1e-3, 0.999))).1.abs()
}

/// Above this fraction of the fitted peak a fixed level crosses where the
/// pulse is flat: the crossing is noise, and the method falls back.
const LEADING_EDGE_MAX_FRACTION: f64 = 0.9;

fn leading_edge(input: &TimingInput) -> Option<Timed> {
    let top = raw_top(input);
    let k = top.k;
    let raw = top.height_v - input.mean_v;
    if !(raw > 0.0 && input.leading_edge_v / raw < LEADING_EDGE_MAX_FRACTION) {
        return None;
    }
    let level = input.mean_v + input.leading_edge_v;
    let crossed = crossing::first_rising(input.x, level, search_start(input, k), k + 1)?;
    // A fixed level crosses a larger pulse earlier (walk): the model moves
    // the crossing to the timing fraction's point of a pulse of the fitted
    // amplitude, so every method reports the same point of the pulse. A
    // calibrated walk table then removes what the model leaves. The
    // amplitude is the top's height less what the samples' phase on the
    // peak takes off it (the model's, at the peak the crossing implies):
    // the walk correction turns an amplitude error into a timing error.
    let at = |a: f64| {
        let r = input.leading_edge_v / a;
        between_samples(input.pulse, r, crossed) + input.pulse.fraction_offset(input.fraction) - input.pulse.fraction_offset(r)
    };
    let (mut a, mut t) = (raw, at(raw));
    for _ in 0..2 {
        let Some(h) = top.model_height(input, t - input.pulse.fraction_offset(input.fraction)) else { break };
        a = raw / h;
        t = at(a);
    }
    let r = input.leading_edge_v / a;
    // Small-signal σ: the noise at the crossing, plus the fitted amplitude's
    // (through the walk correction, scaled by the level's fraction), over
    // the model's slope at the crossing.
    let slope = a * model_slope(input.pulse, r);
    let sigma = input.sigma_v * (1.0 + r * r).sqrt() / slope.max(f64::MIN_POSITIVE);
    Some(finish(input, k as f64, a, t, Some(sigma)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn joint_bound_grows_as_pulses_overlap() {
        let shape = Shape::Parametric(crate::dsp::pulse::Pulse::bigaussian(3.9e-9, 9.4e-9, 1e-9));
        let mut scratch = JointScratch::default();
        let mut out = Vec::new();
        let single = crlb_samples(&shape, 400, 100.0, 1.0, 0.01);
        joint_crlb_samples(&shape, 400, &[(100.0, 1.0)], 0.01, &mut scratch, &mut out);
        assert!(out[0] >= single * (1.0 - 1e-9) && out[0] < 1.2 * single, "{} vs {single}", out[0]);
        // Far apart: each as if alone.
        joint_crlb_samples(&shape, 400, &[(100.0, 1.0), (250.0, 1.0)], 0.01, &mut scratch, &mut out);
        assert!((out[1] / out[0] - 1.0).abs() < 1e-9);
        // 8 samples apart (less than the FWHM): both much worse.
        joint_crlb_samples(&shape, 400, &[(108.0, 0.6), (100.0, 1.0)], 0.01, &mut scratch, &mut out);
        assert!(out[1] > 1.2 * single && out[0] > 1.2 * single / 0.6, "{out:?} vs {single}");
    }
    use crate::detect::kernels::DetectorPlan;

    fn synth(pulse: &Shape, peak: f64, amp: f64, n: usize) -> Vec<f64> {
        (0..n).map(|k| 0.01 + amp * pulse.value_and_slope(k as f64 - peak).0).collect()
    }

    #[test]
    fn noise_free_pulse_is_timed_at_its_fraction_crossing() {
        let pulse = Shape::Parametric(crate::dsp::pulse::Pulse { sigma_rise: 4.79, sigma_fall: 17.3 });
        let mut plan = DetectorPlan::matched_filter(&pulse, 600);
        // Every sub-sample phase a crossing can fall at.
        for phase in [0.0, 0.13, 0.37, 0.5, 0.81] {
            let peak = 300.0 + phase;
            let x = synth(&pulse, peak, 0.8, 600);
            let y = plan.run(&x, 0.01).to_vec();
            let p = (0..y.len()).max_by(|&a, &b| y[a].total_cmp(&y[b])).unwrap();
            let truth = peak + pulse.fraction_offset(0.5);
            for (m, tol) in [
                (TimingMethod::Ml, 1e-6),
                (TimingMethod::PeakParabolic, 0.05),
                (TimingMethod::PeakGaussian, 0.05),
                // Crossings read off the model between samples, and the level
                // from the model's peak: exact on a pulse of the model's shape
                // (a straight line and a bare parabola were off by up to a
                // hundredth of a sample, depending on the phase).
                (TimingMethod::ConstantFraction, 1e-4),
                (TimingMethod::LeadingEdge, 1e-4),
            ] {
                let input = TimingInput {
                    x: &x,
                    mean_v: 0.01,
                    sigma_v: 0.01,
                    y: &y,
                    norm: plan.norm(),
                    pulse: &pulse,
                    peak: p,
                    fraction: 0.5,
                    leading_edge_v: 0.3,
                };
                let t = time_pulse(m, &input);
                assert!((t.index - truth).abs() < tol, "{m:?} at phase {phase}: {} vs {truth}", t.index);
                assert!(!t.fallback);
            }
        }
    }
}
