//! Resolving returns closer than a pulse width: successive cancellation.
//! The strongest matched-filter peak is fitted (amplitude and delay, maximum
//! likelihood) and subtracted; the filter runs again on the residual, until no
//! peak is above the threshold. Then every pulse is refitted with the others
//! subtracted (a few sweeps of coordinate descent on the joint fit).
//!
//! A fit whose residual is much larger than the noise means the scene's shape
//! does not match the data; no further pulse is sought under it (such a
//! residual is the mismatch, not a second return) and it is flagged.
//!
//! A measured shape ends where its support ends, but the data's pulse may
//! go on (a receiver's long tail past the end of a learned shape):
//! subtracting the fitted shape then leaves that tail, a step at the
//! shape's end, which the filter reads as a pulse one shape's length behind
//! the real one. A pulse found there, no stronger than what the shape's own
//! level near its end says the tail can hold, is taken as that leftover:
//! subtracted, not reported (see [`cut_leftover`]).

use super::kernels::DetectorPlan;
use crate::math::linalg::solve_in_place;
use crate::dsp::mlfit::{FitOptions, fit_delay_with};
use crate::dsp::pulse::Shape;
use std::ops::Range;

/// One resolved pulse.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Component {
    /// Fractional sample index of the pulse peak.
    pub peak_index: f64,
    /// Amplitude above the noise mean, volts.
    pub amplitude_v: f64,
    /// Integer position where the detector found it.
    pub detected_at: usize,
    /// RMS of the fit residual over the pulse, in noise sigmas (about 1 when the shape fits).
    pub misfit: f64,
}

/// Levenberg-Marquardt steps at most, for a fit that is reported...
const FIT_ITERATIONS: usize = 40;
/// ... and for the refit of a cluster less one pulse that only decides
/// whether that pulse earns its place (its cost, not its parameters, is used).
const TEST_ITERATIONS: usize = 10;

/// A cluster refit has converged when no delay step exceeds this, samples
/// (a tenth of a picosecond at 1 GS/s, far below any timing sigma)...
const CONVERGED_SAMPLES: f64 = 1e-4;
/// ... and no amplitude step this fraction of the amplitude.
const CONVERGED_AMPLITUDE: f64 = 1e-6;

/// A residual RMS above this many noise sigmas marks a shape mismatch.
pub const MISFIT_LIMIT: f64 = 1.5;

/// A pulse whose filter output stands at least this many times what a pulse
/// of one noise σ would give above the filter's own noise (the output's σ,
/// not the samples': coloured noise raises it) is fitted without the coarse
/// scan, as the start stage fits its pulse: from the filter's interpolated
/// peak the fit is inside its basin. Evidence: `tests/suite/dsp.rs` (alone,
/// white noise, 4 σ and 6 σ) and this module's test (5–9 σ alone and beside
/// a second pulse, white and AR(1) noise).
const NO_SCAN_PEAK_SIGMAS: f64 = 6.0;

/// Scratch for [`Resolver::resolve`], kept between frames: once its buffers
/// have grown, resolving allocates nothing.
#[derive(Debug, Default, Clone)]
pub struct Resolver {
    /// x − mean less the pulses (see `residual_from`).
    residual: Vec<f64>,
    /// The span of `residual` written since it last held x − mean
    /// everywhere (empty: nowhere): `residual_from` writes x − mean again
    /// there only, not over the whole frame.
    dirty: Range<usize>,
    /// Block maxima of the filter output over the range gate.
    blocks: crate::math::select::BlockMaxima,
    /// The components before a trial split (restored when the split fails).
    before: Vec<Component>,
    /// The components less the one being tested for its place.
    rest: Vec<Component>,
    /// The joint refit's normal equations and trial step.
    refit: RefitScratch,
    /// Component indices in order of position (clustering).
    order: Vec<usize>,
    /// Cluster label of each component (clustering output).
    cluster_of: Vec<usize>,
    /// The members of the cluster being refitted.
    cluster: Vec<Component>,
    /// The pulses outside it (held fixed).
    others: Vec<Component>,
    /// The residual over a region with one pulse added back.
    added: Vec<f64>,
    /// Tests: every pulse fitted with the coarse scan (`Some(true)`) or
    /// without it (`Some(false)`), however strong.
    #[cfg(test)]
    scan: Option<bool>,
    /// Tests: fits made without the scan.
    #[cfg(test)]
    unscanned: usize,
    /// Tests: pulses taken as another's leftover in the search.
    #[cfg(test)]
    leftovers: usize,
}

/// Buffers of one Levenberg-Marquardt refit (`m` = 2 × components unknowns).
#[derive(Debug, Default, Clone)]
struct RefitScratch {
    /// JᵀJ, row-major m × m.
    jtj: Vec<f64>,
    /// Jᵀr.
    jtr: Vec<f64>,
    /// JᵀJ with the damped diagonal; destroyed by the solver.
    aug: Vec<f64>,
    /// The step (Jᵀr on entry to the solver).
    step: Vec<f64>,
    /// The components after the step.
    trial: Vec<Component>,
    /// The data less the pulses held fixed, over the refit's region.
    base: Vec<f64>,
    /// Pulse values of the current components...
    cur: PulseValues,
    /// ... and of the trial step's.
    next: PulseValues,
}

/// The pulse value and slope of each component over its window (clipped
/// to a region), concatenated.
#[derive(Debug, Default, Clone)]
struct PulseValues {
    /// (value, slope) per component and sample of its window.
    vals: Vec<(f64, f64)>,
    /// Each component's window, clipped to the region.
    wins: Vec<Range<usize>>,
    /// Where each component's values start in `vals`.
    offsets: Vec<usize>,
}

impl PulseValues {
    /// Evaluates the pulses of `comps` over their windows within [a, b).
    fn fill(&mut self, shape: &Shape, comps: &[Component], window: &dyn Fn(f64) -> Range<usize>, a: usize, b: usize) {
        self.vals.clear();
        self.wins.clear();
        self.offsets.clear();
        for c in comps {
            let w = window(c.peak_index);
            let (s, e) = (w.start.max(a), w.end.min(b));
            let w = s..e.max(s);
            self.offsets.push(self.vals.len());
            shape.values_on_grid(w.start as f64 - c.peak_index, w.len(), &mut self.vals);
            self.wins.push(w);
        }
    }

    /// residual = base - Σ amplitude × value over the region starting at
    /// sample `a` (`residual` and `base` are the region's slices); returns
    /// the residual sum of squares.
    fn residual(&self, base: &[f64], comps: &[Component], residual: &mut [f64], a: usize) -> f64 {
        residual.copy_from_slice(base);
        for (i, c) in comps.iter().enumerate() {
            let w = &self.wins[i];
            let vals = &self.vals[self.offsets[i]..self.offsets[i] + w.len()];
            for (r, &(v, _)) in residual[w.start - a..w.end - a].iter_mut().zip(vals) {
                *r -= c.amplitude_v * v;
            }
        }
        residual.iter().map(|v| v * v).sum()
    }
}

impl Resolver {
    /// Finds up to `max` pulses whose detector output exceeds `threshold`
    /// (output units) at peak positions in `range`, into `comps` (cleared first).
    /// `out_sigma`: the noise σ of the filter's output (`sigma_v` times the
    /// output gain in coloured noise), which decides whether a pulse stands
    /// far enough above it to be fitted without the coarse scan.
    ///
    /// `plan` must hold its run on `x` about `mean_v` (the detector's own
    /// output, which the first pass reads); after each subtracted pulse only
    /// the outputs that read its samples are recomputed, where the plan can
    /// (as direct f64 sums: bit for bit a full run of the direct filter, equal
    /// to the FFT's or the integer filter's to rounding; else the filter runs
    /// again; see [`DetectorPlan::rerun_part`]).
    ///
    /// A pulse found where a stronger one's measured shape is cut off, and
    /// no stronger than that cut-off tail can be, is subtracted but not
    /// kept ([`cut_leftover`]); after `max` such the search ends.
    #[allow(clippy::too_many_arguments)]
    pub fn resolve(
        &mut self,
        x: &[f64],
        mean_v: f64,
        sigma_v: f64,
        out_sigma: f64,
        shape: &Shape,
        plan: &mut DetectorPlan,
        range: Range<usize>,
        threshold: f64,
        max: usize,
        comps: &mut Vec<Component>,
    ) {
        let n = x.len();
        let (lo, hi) = shape.support();
        self.residual.clear();
        self.residual.extend(x.iter().map(|v| v - mean_v));
        self.dirty = 0..0;
        comps.clear();
        let window = |peak: f64| {
            let a = (peak + lo).floor().max(0.0) as usize;
            let b = ((peak + hi).ceil().max(0.0) as usize + 1).min(n);
            a..b.max(a)
        };
        debug_assert_eq!(plan.output().len(), n, "the plan ran on x");
        // Samples of the residual changed since the plan's output (None: none).
        let mut changed: Option<Range<usize>> = None;
        let end = range.end.min(plan.output().len());
        let first = range.start.min(end);
        let taps = plan.len();
        // Never below the white-noise gate: a filter that lowers the noise
        // (output gain below one) does not lower the bar.
        let strong_output = NO_SCAN_PEAK_SIGMAS * plan.norm() * out_sigma.max(sigma_v);
        let fwhm = shape.fwhm();
        // Pulses taken as another's leftover (subtracted, not kept); at most
        // `max` of them, so that the loop ends whatever the data.
        let mut leftovers = 0;
        while comps.len() < max && leftovers < max {
            // The range's outputs by blocks, each block's maximum kept: after
            // a pulse is taken out only the blocks near it are read again.
            let y = match changed.take() {
                None => {
                    self.blocks.fill(&plan.output()[first..end]);
                    plan.output()
                }
                Some(c) if plan.rerun_part(&self.residual, 0.0, c.clone()) => {
                    // Outputs within a template's length of a changed sample moved.
                    let (a, b) = (c.start.saturating_sub(taps).max(first), (c.end + taps).min(end));
                    self.blocks.refresh(&plan.output()[first..end], a.saturating_sub(first)..b.saturating_sub(first));
                    plan.output()
                }
                Some(_) => {
                    let y = plan.run(&self.residual, 0.0);
                    self.blocks.fill(&y[first..end]);
                    y
                }
            };
            // The last largest output of the range (as `max_by` over total_cmp).
            let Some(p) = self.blocks.last_max_index(&y[first..end]).map(|i| first + i) else {
                break;
            };
            if !(y[p] > threshold) {
                break;
            }
            let start = if p > 0 && p + 1 < y.len() {
                p as f64 + crate::dsp::interp::parabolic(y[p - 1], y[p], y[p + 1]).0
            } else {
                p as f64
            };
            // A pulse standing NO_SCAN_PEAK_SIGMAS above the filter's noise,
            // started at the filter's interpolated peak, is inside its basin:
            // its fit needs no coarse scan (see `FitOptions::from_matched_peak`).
            let strong = y[p] >= strong_output;
            // Tests: the scan forced on or off, and the fits without it counted.
            #[cfg(test)]
            let strong = {
                let strong = self.scan.map_or(strong, |scan| !scan);
                self.unscanned += usize::from(strong);
                strong
            };
            let mut c = self.fit(shape, start, p, sigma_v, &window, strong);
            if !(c.amplitude_v > 0.0) {
                // Nothing fits here; take the detector's own estimate and move on.
                c.amplitude_v = y[p] / plan.norm();
                c.peak_index = start;
            }
            let leftover = comps.iter().any(|k| cut_leftover(shape, hi, fwhm, k, &c));
            #[cfg(test)]
            {
                self.leftovers += usize::from(leftover);
            }
            self.subtract(shape, &c, &window, -1.0);
            changed = Some(window(c.peak_index));
            if leftover {
                leftovers += 1;
            } else {
                comps.push(c);
            }
        }
        if comps.is_empty() {
            return;
        }
        // Refit every pulse jointly with its overlapping neighbours.
        self.joint_refit(x, mean_v, sigma_v, shape, comps, &window);
        // A pulse the shape cannot explain alone may be two returns closer than
        // a pulse width: try a split and keep it if it explains the data.
        let mut i = 0;
        while i < comps.len() && comps.len() < max {
            if comps[i].misfit > MISFIT_LIMIT {
                self.before.clear();
                self.before.extend_from_slice(comps);
                let old = comps[i];
                let (a, b) = (
                    Component { peak_index: old.peak_index - fwhm / 3.0, amplitude_v: 0.6 * old.amplitude_v, ..old },
                    Component { peak_index: old.peak_index + fwhm / 3.0, amplitude_v: 0.6 * old.amplitude_v, ..old },
                );
                comps[i] = a;
                comps.push(b);
                // A trial: a few steps decide it; a kept split is refitted in full.
                self.joint_refit_steps(x, mean_v, sigma_v, shape, comps, &window, TEST_ITERATIONS);
                let j = comps.len() - 1;
                let worse = comps[i].misfit > 0.8 * old.misfit && comps[j].misfit > 0.8 * old.misfit;
                let weak = [comps[i], comps[j]].iter().any(|c| !(c.amplitude_v * plan.norm() > threshold));
                // A part that another pulse's cut-off tail explains is that
                // leftover again, not a return the split found.
                let leftover = [i, j].into_iter().any(|m| comps.iter().enumerate().any(|(o, k)| o != i && o != j && cut_leftover(shape, hi, fwhm, k, &comps[m])));
                if worse || weak || leftover {
                    std::mem::swap(comps, &mut self.before);
                    self.residual_from(x, mean_v, shape, comps, &window);
                } else {
                    self.joint_refit(x, mean_v, sigma_v, shape, comps, &window);
                }
            }
            i += 1;
        }
        // Each pulse must earn its place: removing it (and refitting the rest)
        // must raise the residual sum of squares by more than the detection
        // threshold squared, the generalised likelihood-ratio form of the same
        // Neyman-Pearson test (for one pulse at a known delay ΔRSS = y²).
        // Otherwise it was the others' leftover or fitted noise.
        // Pulses whose windows do not overlap (directly or through others)
        // do not interact: the test of one pulse refits only its cluster,
        // over the cluster's span widened by a window each side.
        let margin = ((hi - lo).ceil().max(1.0)) as usize;
        while comps.len() > 1 {
            self.residual_from(x, mean_v, shape, comps, &window);
            self.label_clusters(comps, &window);
            let cluster_of = std::mem::take(&mut self.cluster_of);
            let mut weakest: Option<(usize, f64)> = None;
            for j in 0..comps.len() {
                let label = cluster_of[j];
                let members = || (0..comps.len()).filter(|&i| cluster_of[i] == label);
                let (sa, sb) = members().map(|i| window(comps[i].peak_index)).fold((usize::MAX, 0), |(a, b), w| (a.min(w.start), b.max(w.end)));
                let (a, b) = (sa.saturating_sub(margin), (sb + margin).min(n));
                let rss_all: f64 = self.residual[a..b].iter().map(|v| v * v).sum();
                let mut rest = std::mem::take(&mut self.rest);
                rest.clear();
                rest.extend(members().filter(|&i| i != j).map(|i| comps[i]));
                let rss_rest = if rest.is_empty() {
                    // Alone in its cluster: the residual with it added back.
                    let c = comps[j];
                    let w = window(c.peak_index);
                    self.added.clear();
                    self.added.extend_from_slice(&self.residual[a..b]);
                    let (lo, hi) = (w.start.clamp(a, b), w.end.clamp(a, b));
                    shape.add_scaled(c.peak_index - a as f64, lo - a..hi.max(lo) - a, c.amplitude_v, &mut self.added);
                    self.added.iter().map(|v| v * v).sum()
                } else {
                    // The rest of the cluster refitted, the other pulses held.
                    let mut others = std::mem::take(&mut self.others);
                    others.clear();
                    others.extend((0..comps.len()).filter(|&i| cluster_of[i] != label).map(|i| comps[i]));
                    self.refit_cluster(x, mean_v, shape, &mut rest, &others, &window, (a, b), TEST_ITERATIONS);
                    self.others = others;
                    let rss: f64 = self.residual[a..b].iter().map(|v| v * v).sum();
                    // Back to the residual of all pulses over that region.
                    self.residual_span(x, mean_v, shape, &[comps], &window, a, b);
                    rss
                };
                self.rest = rest;
                let gain = rss_rest - rss_all;
                if weakest.is_none_or(|w| gain < w.1) {
                    weakest = Some((j, gain));
                }
            }
            self.cluster_of = cluster_of;
            match weakest {
                Some((j, gain)) if !(gain > threshold * threshold) => {
                    comps.remove(j);
                    self.joint_refit(x, mean_v, sigma_v, shape, comps, &window);
                }
                _ => break,
            }
        }
        comps.retain(|c| c.amplitude_v > 0.0);
    }

    /// residual = x - mean - Σ pulses: x − mean is written again where
    /// anything was written since it last held x − mean everywhere (the
    /// fill in `resolve` or the previous `residual_from`: `dirty`;
    /// elsewhere it is x − mean, the same bits), then the pulses are subtracted.
    fn residual_from(&mut self, x: &[f64], mean_v: f64, shape: &Shape, comps: &[Component], window: &dyn Fn(f64) -> Range<usize>) {
        debug_assert_eq!(self.residual.len(), x.len(), "resolve filled it from x");
        let d = self.dirty.start.min(x.len())..self.dirty.end.min(x.len());
        // Tests: every write was marked (outside `dirty` the residual is x − mean, bit for bit).
        #[cfg(test)]
        for (i, (r, v)) in self.residual.iter().zip(x).enumerate() {
            assert!(d.contains(&i) || r.to_bits() == (v - mean_v).to_bits(), "sample {i} written but not marked");
        }
        self.refill(x, mean_v, d);
        self.dirty = 0..0;
        for c in comps {
            self.subtract(shape, c, window, -1.0);
        }
    }

    /// residual[a..b] = x - mean - Σ pulses (of every group), over that span only.
    #[allow(clippy::too_many_arguments)]
    fn residual_span(&mut self, x: &[f64], mean_v: f64, shape: &Shape, groups: &[&[Component]], window: &dyn Fn(f64) -> Range<usize>, a: usize, b: usize) {
        self.touch(a..b);
        self.refill(x, mean_v, a..b);
        for c in groups.iter().flat_map(|g| g.iter()) {
            let w = window(c.peak_index);
            let (lo, hi) = (w.start.clamp(a, b), w.end.clamp(a, b));
            shape.add_scaled(c.peak_index, lo..hi.max(lo), -c.amplitude_v, &mut self.residual);
        }
    }

    /// Labels each component with its cluster (`cluster_of`): pulses whose
    /// windows overlap, directly or through others, share one. Returns the
    /// number of clusters.
    fn label_clusters(&mut self, comps: &[Component], window: &dyn Fn(f64) -> Range<usize>) -> usize {
        self.order.clear();
        self.order.extend(0..comps.len());
        self.order.sort_by(|&i, &j| comps[i].peak_index.total_cmp(&comps[j].peak_index));
        self.cluster_of.clear();
        self.cluster_of.resize(comps.len(), 0);
        let mut label = 0;
        let mut reach = 0usize;
        for (rank, &i) in self.order.iter().enumerate() {
            let w = window(comps[i].peak_index);
            if rank > 0 && w.start >= reach {
                label += 1;
            }
            reach = if rank == 0 || w.start >= reach { w.end } else { reach.max(w.end) };
            self.cluster_of[i] = label;
        }
        if comps.is_empty() { 0 } else { label + 1 }
    }

    /// Gauss-Newton (Levenberg-Marquardt damped) on the amplitudes and delays
    /// of each cluster of pulses whose windows overlap, a cluster at a time
    /// (pulses apart do not interact: fitting them jointly changes nothing
    /// but the cost, which grew with the square of the returns in a frame);
    /// leaves `residual` consistent with the result and sets each misfit.
    fn joint_refit(
        &mut self,
        x: &[f64],
        mean_v: f64,
        sigma_v: f64,
        shape: &Shape,
        comps: &mut [Component],
        window: &dyn Fn(f64) -> Range<usize>,
    ) {
        self.joint_refit_steps(x, mean_v, sigma_v, shape, comps, window, FIT_ITERATIONS);
    }

    /// [`joint_refit`](Self::joint_refit) with at most `iterations` steps per cluster.
    #[allow(clippy::too_many_arguments)]
    fn joint_refit_steps(
        &mut self,
        x: &[f64],
        mean_v: f64,
        sigma_v: f64,
        shape: &Shape,
        comps: &mut [Component],
        window: &dyn Fn(f64) -> Range<usize>,
        iterations: usize,
    ) {
        let clusters = self.label_clusters(comps, window);
        let (lo, hi) = shape.support();
        let margin = ((hi - lo).ceil().max(1.0)) as usize;
        let n = x.len();
        let mut cluster = std::mem::take(&mut self.cluster);
        let mut others = std::mem::take(&mut self.others);
        for label in 0..clusters {
            cluster.clear();
            cluster.extend((0..comps.len()).filter(|&i| self.cluster_of[i] == label).map(|i| comps[i]));
            others.clear();
            others.extend((0..comps.len()).filter(|&i| self.cluster_of[i] != label).map(|i| comps[i]));
            let (sa, sb) = span(&cluster, window);
            let region = (sa.saturating_sub(margin), (sb + margin).min(n));
            self.refit_cluster(x, mean_v, shape, &mut cluster, &others, window, region, iterations);
            let mut fitted = cluster.iter();
            for i in 0..comps.len() {
                if self.cluster_of[i] == label
                    && let Some(c) = fitted.next()
                {
                    comps[i] = *c;
                }
            }
        }
        self.cluster = cluster;
        self.others = others;
        self.residual_from(x, mean_v, shape, comps, window);
        for i in 0..comps.len() {
            let w = window(comps[i].peak_index);
            let len = w.len().max(1) as f64;
            let ss: f64 = self.residual[w].iter().map(|v| v * v).sum();
            comps[i].misfit = if sigma_v > 0.0 { (ss / len).sqrt() / sigma_v } else { 0.0 };
        }
    }

    /// Levenberg-Marquardt on one cluster's amplitudes and delays with the
    /// `others` held, minimising the residual sum of squares over the fixed
    /// region [a, b) (the cluster's span and a margin: a cost over a span
    /// that moved with the pulses would reward moving them off the data).
    /// Leaves `residual` over the region consistent with the result.
    #[allow(clippy::too_many_arguments)]
    fn refit_cluster(
        &mut self,
        x: &[f64],
        mean_v: f64,
        shape: &Shape,
        comps: &mut [Component],
        others: &[Component],
        window: &dyn Fn(f64) -> Range<usize>,
        (a, b): (usize, usize),
        iterations: usize,
    ) {
        let k = comps.len();
        let m = 2 * k;
        let mut lambda = 1e-3;
        let mut ws = std::mem::take(&mut self.refit);
        let RefitScratch { jtj, jtr, aug, step, trial, base, cur, next } = &mut ws;
        // The data less the held pulses, over the region: computed once.
        // (It marks a..b written: every write below stays in it.)
        self.residual_span(x, mean_v, shape, &[others], window, a, b);
        base.clear();
        base.extend_from_slice(&self.residual[a..b]);
        // The cluster's pulse values and slopes over their windows, kept from
        // the accepted trial for the next step's Jacobian (one evaluation per
        // sample and pulse per step, not two).
        cur.fill(shape, comps, window, a, b);
        let mut cost = cur.residual(base, comps, &mut self.residual[a..b], a);
        for _it in 0..iterations {
            for v in [&mut *jtj, &mut *jtr] {
                v.clear();
            }
            jtj.resize(m * m, 0.0);
            jtr.resize(m, 0.0);
            // J's rows for pulse i are (value, −amplitude·slope) over its
            // window and zero elsewhere, so JᵀJ is banded: each 2 × 2 block
            // (i, j) sums over the overlap of the two windows only, and each
            // entry is summed in sample order, as a sample-by-sample sweep
            // would add it.
            for i in 0..k {
                let wi = cur.wins[i].clone();
                let vi = &cur.vals[cur.offsets[i]..cur.offsets[i] + wi.len()];
                let na_i = -comps[i].amplitude_v;
                let (mut r0, mut r1) = (0.0, 0.0);
                for (&(v, dv), &r) in vi.iter().zip(&self.residual[wi.clone()]) {
                    r0 += v * r;
                    r1 += na_i * dv * r;
                }
                jtr[2 * i] = r0;
                jtr[2 * i + 1] = r1;
                for j in 0..k {
                    let wj = &cur.wins[j];
                    let (s, e) = (wi.start.max(wj.start), wi.end.min(wj.end));
                    if s >= e {
                        continue;
                    }
                    let vj = &cur.vals[cur.offsets[j] + s - wj.start..cur.offsets[j] + e - wj.start];
                    let na_j = -comps[j].amplitude_v;
                    let (mut a00, mut a01, mut a10, mut a11) = (0.0, 0.0, 0.0, 0.0);
                    for (&(v_i, dv_i), &(v_j, dv_j)) in vi[s - wi.start..e - wi.start].iter().zip(vj) {
                        let (g_i, g_j) = (na_i * dv_i, na_j * dv_j);
                        a00 += v_i * v_j;
                        a01 += v_i * g_j;
                        a10 += g_i * v_j;
                        a11 += g_i * g_j;
                    }
                    let (p, q) = (2 * i, 2 * j);
                    jtj[p * m + q] = a00;
                    jtj[p * m + q + 1] = a01;
                    jtj[(p + 1) * m + q] = a10;
                    jtj[(p + 1) * m + q + 1] = a11;
                }
            }
            let mut improved = false;
            for _try in 0..8 {
                aug.clear();
                aug.extend_from_slice(jtj);
                for p in 0..m {
                    aug[p * m + p] *= 1.0 + lambda;
                    aug[p * m + p] += 1e-30;
                }
                step.clear();
                step.extend_from_slice(jtr);
                if !(solve_in_place(aug, step, m, 0.0) && step.iter().all(|v| v.is_finite())) {
                    break;
                }
                // Converged once no delay would move by CONVERGED_SAMPLES and
                // no amplitude by CONVERGED_AMPLITUDE of itself: stop without
                // evaluating the step (a converged cluster, refitted again
                // beside a changed one, costs one system solve, not eight
                // trial residuals).
                let small = comps.iter().enumerate().all(|(i, c)| {
                    step[2 * i + 1].abs() < CONVERGED_SAMPLES && step[2 * i].abs() <= CONVERGED_AMPLITUDE * c.amplitude_v.abs()
                });
                if small {
                    break;
                }
                trial.clear();
                trial.extend(comps.iter().enumerate().map(|(i, c)| Component {
                    amplitude_v: c.amplitude_v + step[2 * i],
                    peak_index: c.peak_index + step[2 * i + 1].clamp(-2.0, 2.0),
                    ..*c
                }));
                next.fill(shape, trial, window, a, b);
                let new_cost = next.residual(base, trial, &mut self.residual[a..b], a);
                if new_cost.is_finite() && new_cost < cost {
                    comps.copy_from_slice(trial);
                    std::mem::swap(cur, next);
                    cost = new_cost;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = true;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        // The residual of the result (a rejected trial's may be there).
        cur.residual(base, comps, &mut self.residual[a..b], a);
        self.refit = ws;
    }

    /// ML fit of one pulse from `start`; `strong`: well enough above the
    /// noise to skip the coarse scan.
    fn fit(&self, shape: &Shape, start: f64, detected_at: usize, sigma_v: f64, window: &dyn Fn(f64) -> Range<usize>, strong: bool) -> Component {
        let w = window(start);
        let opts = if strong { FitOptions::from_matched_peak() } else { FitOptions::default() };
        let fit = fit_delay_with(&self.residual, 0.0, shape, start, w.clone(), 30, &opts);
        let ok = fit.amplitude.is_finite() && fit.delay.is_finite() && (fit.delay - start).abs() <= 3.0;
        Component {
            peak_index: if ok { fit.delay } else { start },
            amplitude_v: if ok { fit.amplitude } else { f64::NAN },
            detected_at,
            misfit: if ok && sigma_v > 0.0 { fit.residual_rms / sigma_v } else { 0.0 },
        }
    }

    /// Adds `sign` times the component's pulse to the residual.
    fn subtract(&mut self, shape: &Shape, c: &Component, window: &dyn Fn(f64) -> Range<usize>, sign: f64) {
        let w = window(c.peak_index);
        self.touch(w.clone());
        shape.add_scaled(c.peak_index, w, sign * c.amplitude_v, &mut self.residual);
    }

    /// residual = x − mean over `r` (the caller marks it, or clears `dirty`).
    fn refill(&mut self, x: &[f64], mean_v: f64, r: Range<usize>) {
        for (v, &xv) in self.residual[r.clone()].iter_mut().zip(&x[r]) {
            *v = xv - mean_v;
        }
    }

    /// `residual` is about to be written over `r`: `dirty` grows to cover it.
    fn touch(&mut self, r: Range<usize>) {
        if r.is_empty() {
            return;
        }
        self.dirty = if self.dirty.is_empty() { r } else { self.dirty.start.min(r.start)..self.dirty.end.max(r.end) };
    }
}

/// Whether `c`, found after `k` was subtracted, is what `k` leaves where a
/// measured shape (a table, support `lo..hi` about the peak, `fwhm` wide)
/// is cut off: `c` lies within half a FWHM inside the trailing end of `k`'s
/// support or up to two FWHM past it, and is no stronger than `k` times the
/// shape's largest level over the FWHM inside that end. A pulse whose tail
/// goes on past the end holds about the end's level there and less beyond,
/// but a learned table is tapered over its last samples (the data's tail
/// then shows from where the taper starts), and a pulse fitted to a step
/// can come out taller than the step: the level a FWHM inside covers both.
/// A real return that weak, that close behind a strong one, cannot be told
/// from the leftover. Only the trailing end: a table starts where its pulse is
/// already significant, and inside the leading end the shape rises to its
/// peak, so the same bound there would take real returns ahead of a strong
/// one. Parametric shapes are not cut (their support runs to where they
/// vanish): never.
fn cut_leftover(shape: &Shape, hi: f64, fwhm: f64, k: &Component, c: &Component) -> bool {
    use crate::dsp::pulse::PulseShape;
    if !matches!(shape, Shape::Table(_)) || !(k.amplitude_v > 0.0) {
        return false;
    }
    let d = c.peak_index - k.peak_index;
    let inner = 0.5 * fwhm;
    if !(d >= hi - inner && d <= hi + 2.0 * fwhm) {
        return false;
    }
    // Evaluated only for a pulse found there (rare): quarter samples.
    let steps = (4.0 * fwhm).ceil().max(1.0) as usize;
    let level = (0..=steps).map(|i| shape.value_and_slope(hi - fwhm * i as f64 / steps as f64).0.abs()).fold(0.0, f64::max);
    c.amplitude_v.abs() <= k.amplitude_v * level
}

/// Sample span covering every component's window.
fn span(comps: &[Component], window: &dyn Fn(f64) -> Range<usize>) -> (usize, usize) {
    comps.iter().map(|c| window(c.peak_index)).fold((usize::MAX, 0), |(a, b), w| (a.min(w.start), b.max(w.end)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dsp::pulse::PulseShape;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// Strong pulses (at least 6 σ above the filter's noise) are fitted
    /// without the coarse scan: alone and beside a second pulse (3 σ to
    /// 30 σ, from 3 to 0.6 pulse widths apart), in white noise and in AR(1)
    /// noise, every component comes out with the very bits the scan gives.
    /// The first pulse is drawn around the gate (5–9 σ in white noise), and
    /// the gate is seen to fire. Weak pulses near the threshold, fitted
    /// without the scan, do not always match: the comparison sees a difference.
    #[test]
    fn strong_pulses_resolve_to_the_same_bits_without_the_scan() {
        const FRAMES: usize = 1500;
        // The embedded scene's return pulse as the reference frames have it:
        // 5.8 ns rise, 19 ns FWHM at 1 GS/s (a 64-tap template).
        let mut pulse = crate::scene::Scene::default_scene().return_pulse;
        (pulse.rise_time_s, pulse.fwhm_s) = (5.8e-9, 19.0e-9);
        let shape = pulse.shape(1e-9);
        let n = 600;
        let fwhm = shape.fwhm();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(39);
        let mut plan = DetectorPlan::matched_filter(&shape, n);
        // Unit-σ noise, white (φ = 0) or AR(1); and the filter's output σ in it.
        let noise = |phi: f64, len: usize, rng: &mut rand_chacha::ChaCha8Rng| {
            let mut e = rng.sample::<f64, _>(StandardNormal);
            (0..len)
                .map(|_| {
                    e = phi * e + (1.0 - phi * phi).sqrt() * rng.sample::<f64, _>(StandardNormal);
                    e
                })
                .collect::<Vec<f64>>()
        };
        let (mut scanned, mut never) = (Resolver { scan: Some(true), ..Resolver::default() }, Resolver { scan: Some(false), ..Resolver::default() });
        let mut gated = Resolver::default();
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let bits = |c: &[Component]| c.iter().map(|c| (c.peak_index.to_bits(), c.amplitude_v.to_bits(), c.misfit.to_bits())).collect::<Vec<_>>();
        // (pulses, gap in FWHM, first and second amplitude ranges in σ of
        // the filter's noise as a white-noise pulse would give it, φ, threshold in output σ)
        let configs = [
            (1usize, 0.0, (5.0, 9.0), (0.0, 0.0), 0.0, 4.5),
            (2, 3.0, (5.0, 9.0), (3.0, 30.0), 0.0, 4.5),
            (2, 1.5, (5.0, 9.0), (3.0, 30.0), 0.0, 4.5),
            (2, 1.0, (5.0, 9.0), (3.0, 30.0), 0.0, 4.5),
            (2, 0.6, (5.0, 9.0), (3.0, 30.0), 0.0, 4.5),
            (1, 0.0, (5.0, 9.0), (0.0, 0.0), 0.9, 4.5),
            (2, 1.0, (5.0, 9.0), (3.0, 30.0), 0.9, 4.5),
            // The control: weak pulses at a low threshold, never scanned, in
            // four times the frames (25 of the 6000 differ with this seed).
            (1, 0.0, (0.3, 0.8), (0.0, 0.0), 0.0, 2.0),
        ];
        for (k, &(pulses, gap_fwhm, r1, r2, phi, threshold)) in configs.iter().enumerate() {
            let control = k + 1 == configs.len();
            let out_sigma = {
                let e = noise(phi, 20_000, &mut rng);
                let y = plan.run(&e, 0.0);
                (y[100..19_900].iter().map(|v| v * v).sum::<f64>() / 19_800.0).sqrt()
            };
            let mut differ = 0usize;
            gated.unscanned = 0;
            for _ in 0..if control { 4 * FRAMES } else { FRAMES } {
                let first = 250.0 + rng.random::<f64>();
                // Amplitudes in units of the filter's noise over the template's norm.
                let amps = [rng.random_range(r1.0..r1.1) * out_sigma.max(1.0), if pulses > 1 { rng.random_range(r2.0..r2.1) * out_sigma.max(1.0) } else { 0.0 }];
                let at = [first, first + gap_fwhm * fwhm];
                let e = noise(phi, n, &mut rng);
                let x: Vec<f64> = (0..n).map(|k| (0..pulses).map(|i| amps[i] * shape.value_and_slope(k as f64 - at[i]).0).sum::<f64>() + e[k]).collect();
                let thr = threshold * out_sigma;
                plan.run(&x, 0.0);
                scanned.resolve(&x, 0.0, 1.0, out_sigma, &shape, &mut plan, 100..500, thr, 8, &mut a);
                plan.run(&x, 0.0);
                let other = if control { &mut never } else { &mut gated };
                other.resolve(&x, 0.0, 1.0, out_sigma, &shape, &mut plan, 100..500, thr, 8, &mut b);
                differ += usize::from(bits(&a) != bits(&b));
            }
            if control {
                assert!(differ > 0, "weak pulses never scanned: no frame differs, so the comparison cannot see one");
            } else {
                // 0 of 1500: a rate below 2e-3 at 95 %.
                assert_eq!(differ, 0, "{pulses} pulse(s), {gap_fwhm} FWHM apart, φ = {phi}: {differ} of {FRAMES} frames differ");
                // The gate fires for about half the first pulses (those above 6 σ).
                assert!(gated.unscanned > FRAMES / 4, "φ = {phi}: {} fits of {FRAMES} frames unscanned", gated.unscanned);
            }
        }
    }

    /// A pulse whose tail goes on past the end of the shape fitted to it (a
    /// table cut where the tail falls to 1 % of the peak and tapered to 0
    /// over its last 3 samples, as learned tables are; the data's tail
    /// exponential on to the frame's end) leaves, once subtracted, a step at
    /// the shape's end that the filter reads far above the threshold: it is
    /// taken as the leftover, and nothing is reported there. A real second
    /// pulse at 5 % in the same place stays, and so does a real pulse at
    /// 40 % twelve samples ahead of the strong one.
    #[test]
    fn a_tail_past_the_shapes_end_is_not_a_second_return() {
        // Gaussian rise (σ 2 samples), exponential fall (τ 8 samples), peak 1 at 0.
        let pulse = |t: f64| if t < 0.0 { (-t * t / 8.0).exp() } else { (-t / 8.0).exp() };
        let end = 8.0 * 100f64.ln();
        let step = 0.125;
        let taper = |t: f64| if t < end - 3.0 { 1.0 } else { 0.5 * (1.0 + (std::f64::consts::PI * (t - end + 3.0) / 3.0).cos()) };
        let values: Vec<f64> = (0..).map(|i| -8.0 + i as f64 * step).take_while(|&t| t <= end).map(|t| pulse(t) * taper(t)).collect();
        let shape = Shape::Table(crate::dsp::pulse::TablePulse::new(values, step, -8.0));
        let (lo, hi) = shape.support();
        assert!(pulse(hi) > 0.009 && pulse(hi) < 0.011, "the table ends at 1 % of the peak: {}", pulse(hi));
        let n = 400;
        let mut plan = DetectorPlan::matched_filter(&shape, n);
        let sigma = 5e-4;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let out_sigma = {
            let e: Vec<f64> = (0..20_000).map(|_| sigma * rng.sample::<f64, _>(StandardNormal)).collect();
            let y = plan.run(&e, 0.0);
            (y[100..19_900].iter().map(|v| v * v).sum::<f64>() / 19_800.0).sqrt()
        };
        let threshold = 5.0 * out_sigma;
        let fwhm = shape.fwhm();
        let mut resolver = Resolver::default();
        let mut comps = Vec::new();
        let (mut leftover_seen, mut taken) = (0, 0);
        for frame in 0..45 {
            let t0 = 100.0 + rng.random::<f64>();
            // 0: the pulse alone; 1: a real pulse at 5 % where the tail is
            // cut; 2: a real pulse at 40 % twelve samples ahead.
            let kind = frame % 3;
            let (other_at, other_amp) = match kind {
                1 => (t0 + hi + 6.0, 0.05),
                2 => (t0 - 12.0, 0.4),
                _ => (0.0, 0.0),
            };
            let x: Vec<f64> = (0..n).map(|k| pulse(k as f64 - t0) + other_amp * pulse(k as f64 - other_at) + sigma * rng.sample::<f64, _>(StandardNormal)).collect();
            plan.run(&x, 0.0);
            resolver.leftovers = 0;
            resolver.resolve(&x, 0.0, sigma, out_sigma, &shape, &mut plan, 50..350, threshold, 8, &mut comps);
            // At this SNR (66 dB) the fit may split a pulse itself in two, a
            // fraction of a sample apart: what matters is what lies elsewhere.
            let near = |at: f64| comps.iter().filter(move |c| (c.peak_index - at).abs() < fwhm);
            assert!(near(t0).count() > 0, "frame {frame}: the pulse itself: {comps:?}");
            let elsewhere: Vec<&Component> = comps.iter().filter(|c| (c.peak_index - t0).abs() >= fwhm).collect();
            if kind > 0 {
                let amp: f64 = near(other_at).map(|c| c.amplitude_v).sum();
                assert!(
                    near(other_at).count() == elsewhere.len() && (amp / other_amp - 1.0).abs() < 0.2,
                    "frame {frame}: the real pulse at {other_amp} is kept, and nothing else away from the strong one: {comps:?}"
                );
                continue;
            }
            assert!(elsewhere.is_empty(), "frame {frame}: the tail past the shape's end is no return: {comps:?}");
            taken += usize::from(resolver.leftovers > 0);
            // The leftover is there to be found: the data less every fitted
            // part of the pulse, filtered, stands above the threshold past
            // the shape's end.
            let mut r: Vec<f64> = x.clone();
            for c in near(t0) {
                let w = (c.peak_index + lo).floor() as usize..(c.peak_index + hi).ceil() as usize + 1;
                shape.add_scaled(c.peak_index, w, -c.amplitude_v, &mut r);
            }
            let y = plan.run(&r, 0.0).to_vec();
            let (a, b) = ((t0 + hi - fwhm) as usize, (t0 + hi + 2.0 * fwhm) as usize);
            let top = y[a..b].iter().copied().fold(f64::MIN, f64::max);
            leftover_seen += usize::from(top > 2.0 * threshold);
        }
        assert_eq!(leftover_seen, 15, "the residual's step past the shape's end crossed twice the threshold in every frame of the pulse alone");
        assert_eq!(taken, 15, "the search took the step as the leftover in every frame of the pulse alone");
    }
}
