//! The sensor's own return shape, learned from its frames for the events
//! test ([`crate::detect::events`]).
//!
//! The events test's step 1 asks whether a detection's window holds more
//! than returns: the energy the event subspace explains beyond the pulses
//! (and their slopes) of every reaching detection. Where the scene's pulse
//! shape is not the sensor's (the default scene's measured 26 ns pulse on
//! frames whose returns are 9 ns wide), the misfit of every strong return
//! leaks into that energy (7–20 % of the pulse's energy on the default
//! scene's simulated lab targets, against a noise limit of a few hundred σ²
//! for returns of 10⁴–10⁵ σ²): every strong return goes on to step 2, pays
//! its cost, and is reported with `interference` although the frame holds
//! none.
//!
//! [`ReturnShapeLearner`] measures the shape from the first frames that hold
//! strong returns and no event: the samples around the detections are
//! modelled as Σₖ aₖ s(t − pₖ) with s on a grid of `1/GRID` sample over the
//! scene shape's support (linear interpolation between grid points), the
//! detections' peaks pₖ as the detector placed them and their amplitudes aₖ
//! fitted by least squares (first with the scene's shape, then with the
//! learned one). Overlapping returns are unmixed by the joint fit, and the
//! random sub-sample phase of the detections (the digitiser's clock is free
//! running) fills the grid between samples (equivalent-time sampling); a
//! small second-difference penalty carries the grid across bins no sample
//! reached. Frames whose residual stands out of the others' (an event under
//! a return that no detection answered) are left out of the second pass.
//!
//! The learned shape replaces the scene's in the events test only where the
//! scene's, fitted with its slope to the learned one, leaves more than
//! [`SWITCH_MISFIT`] of its energy: a scene whose shape fits its sensor
//! keeps it, bit for bit.

use crate::dsp::pulse::{PulseShape, Shape, TablePulse};
use crate::math::linalg::solve_in_place;

/// Grid points per sample.
const GRID: usize = 4;

/// Strong returns (amplitude ≥ [`STRONG_SIGMAS`] noise sigmas) the learning waits for.
pub const LEARN_RETURNS: usize = 64;

/// A return is strong from this many noise sigmas: below about 10σ a
/// shape's misfit does not lift step 1's energy over its limit.
const STRONG_SIGMAS: f64 = 10.0;

/// Frames kept for the learning (each with its detections).
const MAX_FRAMES: usize = 64;

/// Detections per frame the learning models (more: the frame is skipped).
const MAX_DETECTIONS: usize = 16;

/// Samples per kept frame (the span of its detections' supports).
const MAX_SPAN: usize = 1024;

/// The learned shape is used where the scene's leaves more than this
/// fraction of its energy unexplained (with amplitude and slope fitted).
pub const SWITCH_MISFIT: f64 = 0.01;

/// Frames whose residual energy per sample exceeds this multiple of the
/// median frame's are left out of the second pass.
const TRIM: f64 = 2.0;

/// One kept frame: its samples' span and detections.
#[derive(Debug, Clone, Copy, Default)]
struct Kept {
    /// Offset of the first sample into `ReturnShapeLearner::xs`, samples kept.
    at: usize,
    len: usize,
    /// Frame index of the first kept sample.
    first: usize,
    /// Offset into `ReturnShapeLearner::peaks`, detections.
    peaks_at: usize,
    count: usize,
    /// Whether the second pass uses the frame.
    used: bool,
}

/// What the learning concluded.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedShape {
    /// The sensor's return shape (peak 1), relative to where the detector
    /// places the peak; support as the scene shape's.
    pub shape: Shape,
    /// Fraction of the learned shape's energy the scene's shape leaves
    /// unexplained (amplitude and slope fitted).
    pub misfit: f64,
    /// Frames it was learned from (second pass) and the returns they hold.
    pub frames: usize,
    /// See `frames`.
    pub returns: usize,
    /// Whether the events test uses it (`misfit` > [`SWITCH_MISFIT`]).
    pub adopted: bool,
}

/// Learns the sensor's return shape from frames with strong returns and no
/// event (module docs). All storage is taken at construction: offering a
/// frame and learning allocate nothing beyond the learned table.
#[derive(Debug, Clone)]
pub struct ReturnShapeLearner {
    /// Support of the scene's shape, samples from its peak.
    lo: f64,
    hi: f64,
    /// Grid points.
    bins: usize,
    /// x − μ over each kept frame's span, in noise sigmas.
    xs: Vec<f64>,
    /// Peaks and amplitudes (in noise sigmas) of the kept frames' detections.
    peaks: Vec<(f64, f64)>,
    kept: Vec<Kept>,
    /// Strong returns in the kept frames.
    strong: usize,
    /// Normal equations (bins × bins) and right-hand side; the solution.
    ata: Vec<f64>,
    atb: Vec<f64>,
    /// Small systems: the amplitudes of one frame's detections.
    small: Vec<f64>,
    small_b: Vec<f64>,
    /// (value, slope) of the scene's shape on the grid; per-sample scratch.
    grid: Vec<f64>,
    residuals: Vec<f64>,
    order: Vec<f64>,
    /// Done: the learned shape (`None` inside: the learning failed).
    outcome: Option<Option<LearnedShape>>,
}

impl ReturnShapeLearner {
    /// A learner for returns of (about) `scene_shape`.
    pub fn new(scene_shape: &Shape) -> ReturnShapeLearner {
        let (lo, hi) = scene_shape.support();
        let bins = ((hi - lo) * GRID as f64).ceil() as usize + 1;
        ReturnShapeLearner {
            lo,
            hi,
            bins,
            xs: Vec::with_capacity(MAX_FRAMES * MAX_SPAN),
            peaks: Vec::with_capacity(MAX_FRAMES * MAX_DETECTIONS),
            kept: Vec::with_capacity(MAX_FRAMES),
            strong: 0,
            ata: vec![0.0; bins * bins],
            atb: vec![0.0; bins],
            small: vec![0.0; MAX_DETECTIONS * MAX_DETECTIONS],
            small_b: vec![0.0; MAX_DETECTIONS],
            grid: Vec::with_capacity(bins),
            residuals: Vec::with_capacity(MAX_FRAMES),
            order: Vec::with_capacity(MAX_FRAMES),
            outcome: None,
        }
    }

    /// Whether the learning has concluded (then [`learned`](Self::learned) says what).
    pub fn done(&self) -> bool {
        self.outcome.is_some()
    }

    /// The learned shape, where it differs from the scene's by more than
    /// [`SWITCH_MISFIT`].
    pub fn learned(&self) -> Option<&LearnedShape> {
        self.outcome().filter(|l| l.adopted)
    }

    /// What the learning found, adopted or not (`None`: not done, or failed).
    pub fn outcome(&self) -> Option<&LearnedShape> {
        self.outcome.as_ref().and_then(Option::as_ref)
    }

    /// Offers a frame whose detections at `peaks` (fractional sample
    /// indices into `x`) are all returns (no event found in the frame, no
    /// sample at a rail): kept where one is strong, and the shape learned
    /// once [`LEARN_RETURNS`] strong returns are in. `scene_shape` fits the
    /// amplitudes. Returns true when this frame concluded the learning.
    pub fn offer(&mut self, x: &[f64], mean_v: f64, sigma_v: f64, peaks: &[f64], scene_shape: &Shape) -> bool {
        if self.done() || peaks.is_empty() || peaks.len() > MAX_DETECTIONS || !(sigma_v > 0.0) || x.is_empty() {
            return false;
        }
        let lo_p = peaks.iter().copied().fold(f64::INFINITY, f64::min);
        let hi_p = peaks.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let first = (lo_p + self.lo).ceil().max(0.0) as usize;
        let last = ((hi_p + self.hi).floor().max(0.0) as usize).min(x.len() - 1);
        if last < first || last + 1 - first > MAX_SPAN || self.kept.len() >= MAX_FRAMES {
            return false;
        }
        let at = self.xs.len();
        self.xs.extend(x[first..=last].iter().map(|v| (v - mean_v) / sigma_v));
        let peaks_at = self.peaks.len();
        self.peaks.extend(peaks.iter().map(|&p| (p, 0.0)));
        let k = Kept { at, len: last + 1 - first, first, peaks_at, count: peaks.len(), used: true };
        let fitted = self.fit_amplitudes(&k, |t| scene_shape.value_and_slope(t).0);
        let strong = self.peaks[peaks_at..].iter().filter(|p| p.1 >= STRONG_SIGMAS).count();
        if !fitted || strong == 0 {
            self.xs.truncate(at);
            self.peaks.truncate(peaks_at);
            return false;
        }
        self.kept.push(k);
        self.strong += strong;
        if self.strong >= LEARN_RETURNS || self.kept.len() >= MAX_FRAMES {
            self.learn(scene_shape);
            return true;
        }
        false
    }

    /// Least-squares amplitudes of frame `k`'s detections with shape `s`,
    /// into `peaks`. False where the system is singular.
    fn fit_amplitudes(&mut self, k: &Kept, s: impl Fn(f64) -> f64) -> bool {
        let n = k.count;
        let (lo, hi) = (self.lo, self.hi);
        self.small[..n * n].fill(0.0);
        self.small_b[..n].fill(0.0);
        let xs = &self.xs[k.at..k.at + k.len];
        let peaks = &self.peaks[k.peaks_at..k.peaks_at + n];
        for (i, &(pi, _)) in peaks.iter().enumerate() {
            for (j, &xv) in xs.iter().enumerate() {
                let t = (k.first + j) as f64 - pi;
                if t < lo || t > hi {
                    continue;
                }
                let vi = s(t);
                self.small_b[i] += vi * xv;
                for (l, &(pl, _)) in peaks.iter().enumerate() {
                    let u = (k.first + j) as f64 - pl;
                    if u >= lo && u <= hi {
                        self.small[i * n + l] += vi * s(u);
                    }
                }
            }
        }
        if !solve_in_place(&mut self.small[..n * n], &mut self.small_b[..n], n, 1e-12) {
            return false;
        }
        for (p, &a) in self.peaks[k.peaks_at..k.peaks_at + n].iter_mut().zip(&self.small_b[..n]) {
            p.1 = a;
        }
        self.small_b[..n].iter().all(|a| a.is_finite())
    }

    /// Grid cell and weight of the later grid point for time `t` from a peak
    /// (None: outside the support).
    fn cell(&self, t: f64) -> Option<(usize, f64)> {
        if t < self.lo || t > self.hi {
            return None;
        }
        let u = (t - self.lo) * GRID as f64;
        let i = (u.floor() as usize).min(self.bins - 2);
        Some((i, u - i as f64))
    }

    /// Solves for the grid values on the kept frames marked `used`, into `atb`.
    fn solve_grid(&mut self) -> bool {
        let g = self.bins;
        self.ata.fill(0.0);
        self.atb[..g].fill(0.0);
        let mut row: [(usize, f64); 2 * MAX_DETECTIONS] = [(0, 0.0); 2 * MAX_DETECTIONS];
        for k in self.kept.iter().filter(|k| k.used) {
            let peaks = &self.peaks[k.peaks_at..k.peaks_at + k.count];
            for (j, &xv) in self.xs[k.at..k.at + k.len].iter().enumerate() {
                let mut m = 0;
                for &(p, a) in peaks {
                    if let Some((i, f)) = self.cell((k.first + j) as f64 - p) {
                        row[m] = (i, a * (1.0 - f));
                        row[m + 1] = (i + 1, a * f);
                        m += 2;
                    }
                }
                for &(i, wi) in &row[..m] {
                    self.atb[i] += wi * xv;
                    for &(l, wl) in &row[..m] {
                        self.ata[i * g + l] += wi * wl;
                    }
                }
            }
        }
        // The second-difference penalty (and a small ridge) at a small
        // fraction of the data's weight per grid point.
        let mean_diag = (0..g).map(|i| self.ata[i * g + i]).sum::<f64>() / g as f64;
        if !(mean_diag > 0.0) {
            return false;
        }
        let lambda = 1e-3 * mean_diag;
        for i in 1..g - 1 {
            let idx = [i - 1, i, i + 1];
            let w = [1.0, -2.0, 1.0];
            for (a, &r) in idx.iter().enumerate() {
                for (b, &c) in idx.iter().enumerate() {
                    self.ata[r * g + c] += lambda * w[a] * w[b];
                }
            }
        }
        for i in 0..g {
            self.ata[i * g + i] += 1e-6 * mean_diag;
        }
        solve_in_place(&mut self.ata, &mut self.atb[..g], g, 0.0) && self.atb[..g].iter().all(|v| v.is_finite())
    }

    /// The learned grid's value at `t` from the peak (zero outside the support).
    fn grid_value(grid: &[f64], lo: f64, hi: f64, t: f64) -> f64 {
        if t < lo || t > hi {
            return 0.0;
        }
        let u = (t - lo) * GRID as f64;
        let i = (u.floor() as usize).min(grid.len() - 2);
        let f = u - i as f64;
        grid[i] * (1.0 - f) + grid[i + 1] * f
    }

    /// Two passes (module docs), then the decision.
    fn learn(&mut self, scene_shape: &Shape) {
        self.outcome = Some(None);
        if !self.solve_grid() {
            return;
        }
        // Second pass: amplitudes with the first pass's shape, frames whose
        // residual stands out left out.
        self.grid.clear();
        self.grid.extend_from_slice(&self.atb[..self.bins]);
        let (lo, hi) = (self.lo, self.hi);
        self.residuals.clear();
        for n in 0..self.kept.len() {
            let k = self.kept[n];
            let grid = std::mem::take(&mut self.grid);
            let ok = self.fit_amplitudes(&k, |t| Self::grid_value(&grid, lo, hi, t));
            let peaks = &self.peaks[k.peaks_at..k.peaks_at + k.count];
            let r = self.xs[k.at..k.at + k.len]
                .iter()
                .enumerate()
                .map(|(j, &xv)| {
                    let model: f64 = peaks.iter().map(|&(p, a)| a * Self::grid_value(&grid, lo, hi, (k.first + j) as f64 - p)).sum();
                    (xv - model) * (xv - model)
                })
                .sum::<f64>()
                / k.len as f64;
            self.grid = grid;
            self.kept[n].used = ok;
            self.residuals.push(if ok { r } else { f64::INFINITY });
        }
        self.order.clear();
        self.order.extend_from_slice(&self.residuals);
        self.order.sort_unstable_by(f64::total_cmp);
        let median = self.order[self.order.len() / 2];
        for (k, r) in self.kept.iter_mut().zip(&self.residuals) {
            k.used &= *r <= TRIM * median;
        }
        if !self.solve_grid() {
            return;
        }
        let grid = &self.atb[..self.bins];
        let peak = grid.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if !(peak > 0.0) || grid.iter().any(|v| -v > peak) {
            return;
        }
        let values: Vec<f64> = grid.iter().map(|v| v / peak).collect();
        // The scene's shape, amplitude and slope fitted to the learned one.
        let misfit = slope_fit_misfit(values.iter().enumerate().map(|(i, &v)| (scene_shape.value_and_slope(lo + i as f64 / GRID as f64), v)));
        let frames = self.kept.iter().filter(|k| k.used).count();
        let returns = self.kept.iter().filter(|k| k.used).map(|k| k.count).sum();
        let shape = Shape::Table(TablePulse::new(values, 1.0 / GRID as f64, lo));
        self.outcome = Some(Some(LearnedShape { shape, misfit, frames, returns, adopted: misfit > SWITCH_MISFIT }));
        // The kept frames are not needed any more.
        self.xs = Vec::new();
        self.peaks = Vec::new();
        self.ata = Vec::new();
    }
}

/// Fraction of the energy of v left unexplained by a·p + b·ṗ (least
/// squares over the points given as ((p, ṗ), v)): how far a shape fitted
/// with its amplitude and slope, as step 1 fits it, is from v.
fn slope_fit_misfit(points: impl Iterator<Item = ((f64, f64), f64)>) -> f64 {
    let (mut pp, mut pd, mut dd, mut px, mut dx, mut xx) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for ((p, d), v) in points {
        pp += p * p;
        pd += p * d;
        dd += d * d;
        px += p * v;
        dx += d * v;
        xx += v * v;
    }
    let det = pp * dd - pd * pd;
    let explained = if det > 0.0 { (dd * px * px - 2.0 * pd * px * dx + pp * dx * dx) / det } else { px * px / pp };
    ((xx - explained) / xx).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::gates::test_noise;
    use crate::dsp::pulse::Pulse;

    /// The default scene's return shape (26 ns bigaussian at 1 GS/s).
    fn scene_shape() -> Shape {
        Shape::Parametric(Pulse::bigaussian(8.08e-9, 26.04e-9, 1e-9))
    }

    /// Frames of 600 samples, noise σ = 1, returns of `truth` at 200 + 40k
    /// (+ a fixed sub-sample phase per frame) with amplitudes 20–80σ; every
    /// third frame, when `events`, a slow 25σ oscillation over the returns.
    /// The detector's peaks: the rounded true peaks. Returns what the
    /// learner concluded.
    fn learn(truth: &Shape, events: bool) -> LearnedShape {
        let scene = scene_shape();
        let mut learner = ReturnShapeLearner::new(&scene);
        for f in 0..MAX_FRAMES as u64 {
            let phase = (f as f64 * 0.618_033_988_75).fract();
            let mut x = test_noise(600, 17 + f);
            let peaks: Vec<f64> = (0..4).map(|k| 200.0 + 40.0 * k as f64 + phase).collect();
            let amps = [80.0, 20.0, 45.0, 30.0];
            for (j, v) in x.iter_mut().enumerate() {
                for (&p, &a) in peaks.iter().zip(&amps) {
                    *v += a * truth.value_and_slope(j as f64 - p).0;
                }
                if events && f % 3 == 0 {
                    let t = j as f64 - 150.0 - 7.0 * f as f64;
                    if t > 0.0 {
                        *v += 25.0 * (t / 60.0) * (1.0 - t / 60.0).exp() * (2.0 * std::f64::consts::PI * 0.004 * t).sin();
                    }
                }
            }
            let detected: Vec<f64> = peaks.iter().map(|p| p.round()).collect();
            if learner.offer(&x, 0.0, 1.0, &detected, &scene) {
                break;
            }
        }
        learner.outcome().expect("learned").clone()
    }

    #[test]
    fn a_narrower_sensor_pulse_is_learned_and_adopted() {
        let truth = Shape::Parametric(Pulse::gaussian(9.4e-9, 1e-9));
        for events in [false, true] {
            let l = learn(&truth, events);
            eprintln!("events {events}: misfit {:.4}, fwhm {:.3}, frames {}, returns {}", l.misfit, l.shape.fwhm(), l.frames, l.returns);
            assert!(l.adopted, "misfit {}", l.misfit);
            // FWHM within 5 % (the detector's integer peaks blur it by a
            // one-sample box: +0.5 % on 9.4 samples).
            assert!((l.shape.fwhm() / 9.4 - 1.0).abs() < 0.05, "fwhm {} (events {events})", l.shape.fwhm());
            // The learned shape fits the truth (amplitude and slope fitted
            // as step 1 does) within 1 % of its energy.
            let (lo, hi) = l.shape.support();
            let points = ((lo * 4.0).ceil() as i64..=(hi * 4.0).floor() as i64).map(|k| k as f64 / 4.0);
            let misfit = slope_fit_misfit(points.map(|t| (truth.value_and_slope(t), l.shape.value_and_slope(t).0)));
            eprintln!("learned vs truth: {misfit:.5}");
            assert!(misfit < 0.01, "learned vs truth misfit {misfit} (events {events})");
        }
    }

    #[test]
    fn a_scene_shape_that_fits_is_kept() {
        let l = learn(&scene_shape(), true);
        eprintln!("misfit {:.5}, frames {}, returns {}", l.misfit, l.frames, l.returns);
        assert!(!l.adopted && l.misfit < SWITCH_MISFIT / 2.0, "misfit {}", l.misfit);
    }
}
