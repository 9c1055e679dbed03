//! Maximum-likelihood fit of amplitude and delay of a known pulse shape in white
//! Gaussian noise (least squares, Gauss-Newton).
//!
//! Model over the window: `x[k] = baseline + amplitude·shape(k − delay) + noise`.
//! In white Gaussian noise the ML estimate is the least-squares one. The
//! amplitude enters linearly, so it is eliminated at every delay (variable
//! projection): `amplitude(d) = Σ s·y / Σ s²` with `s = shape(k − d)`,
//! `y = x − baseline`, leaving a one-dimensional problem in the delay,
//! minimise `C(d) = Σ y² − (Σ s·y)² / Σ s²`.
//!
//! Robustness: a coarse scan of `C` around the start (±2 samples by default, in
//! steps of a fifth of the pulse's width but at least a quarter sample) puts the iteration inside the basin of the right minimum
//! even for a narrow pulse started 1.5 samples off; Gauss-Newton steps (with the
//! amplitude–delay coupling projected out) are then backtracked until the cost
//! drops, so each iteration is a descent step and the fit never walks uphill.
//! A window that cuts the pulse is fine (the model is evaluated only inside it);
//! a window with no signal returns amplitude ≈ 0 with `converged == false`; the
//! result is never NaN for finite input.

use super::pulse::PulseShape;

/// Result of a fit. Model: `x[k] = baseline + amplitude * shape(k - delay)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MlFit {
    /// Fitted amplitude (same units as x).
    pub amplitude: f64,
    /// Fitted delay, samples (position of the shape's t = 0).
    pub delay: f64,
    /// Gauss-Newton iterations used.
    pub iterations: u32,
    /// The step fell below tolerance within the iteration limit.
    pub converged: bool,
    /// Σ_k shape'(k - delay)² over the window: the delay's Fisher information is amplitude² times this over sigma².
    pub slope_energy: f64,
    /// RMS of the residual over the window.
    pub residual_rms: f64,
}

impl MlFit {
    /// Cramér–Rao bound of the delay's standard deviation, samples, for white
    /// noise of standard deviation `sigma` (same units as the amplitude):
    /// `sigma / (|amplitude|·sqrt(slope_energy))`. Infinite when the fit found no
    /// pulse (zero amplitude or slope energy).
    pub fn delay_crb_samples(&self, sigma: f64) -> f64 {
        let info = self.amplitude * self.amplitude * self.slope_energy;
        if info > 0.0 {
            sigma / info.sqrt()
        } else {
            f64::INFINITY
        }
    }
}

/// Tuning of [`fit_delay_with`]; [`FitOptions::default`] is what [`fit_delay`] uses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitOptions {
    /// Half-width of the coarse scan around the start, samples (0: no scan).
    pub search_half_width: f64,
    /// Finest step of the coarse scan, samples. The scan steps by a fifth of
    /// the pulse's width scale when that is coarser, and is skipped when even
    /// that step exceeds `search_half_width` (wide pulses need no scan).
    pub search_step: f64,
    /// Convergence: |delay step| below this, samples.
    pub delay_tol: f64,
    /// Largest single Gauss-Newton step, samples (a trust region).
    pub max_step: f64,
}

impl FitOptions {
    /// For a start at the interpolated peak of a matched filter of the same
    /// shape on the same samples, on a pulse well above its noise: no coarse
    /// scan. The filter has already searched the projected cost's numerator
    /// on the sample grid. On the reference scene's start and return pulses
    /// at 4 σ and 6 σ (peak over noise), none of 10 000 fits per level gives
    /// other bits than the scanned fit (`tests/suite/dsp.rs`); at 2 σ about
    /// one in a thousand does. The start stage, which times only pulses of
    /// 6 σ and more, uses it; so does the resolver for pulses of 6 σ and
    /// more, alone or beside a second pulse down to 0.6 FWHM apart (tested
    /// in `detect::resolve`), and it keeps the scan for weaker ones.
    pub fn from_matched_peak() -> FitOptions {
        FitOptions { search_half_width: 0.0, ..FitOptions::default() }
    }
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            search_half_width: 2.0,
            search_step: 0.25,
            delay_tol: 1e-10,
            max_step: 2.0,
        }
    }
}

/// Fits amplitude and delay over `x[window]`, starting from `delay0` (samples),
/// with the default [`FitOptions`]. A window reaching past `x` is cut to `x`.
pub fn fit_delay<S: PulseShape + ?Sized>(
    x: &[f64],
    baseline: f64,
    shape: &S,
    delay0: f64,
    window: std::ops::Range<usize>,
    max_iter: u32,
) -> MlFit {
    fit_delay_with(
        x,
        baseline,
        shape,
        delay0,
        window,
        max_iter,
        &FitOptions::default(),
    )
}

/// Sums over the window at one delay.
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    /// Σ s²
    ss: f64,
    /// Σ s·y
    sy: f64,
    /// Σ g² with g = shape'(k − d)
    gg: f64,
    /// Σ s·g
    sg: f64,
    /// Σ g·y
    gy: f64,
}

/// [`fit_delay`] with explicit options. `max_iter` bounds the Gauss-Newton
/// iterations (the coarse scan is not counted).
pub fn fit_delay_with<S: PulseShape + ?Sized>(
    x: &[f64],
    baseline: f64,
    shape: &S,
    delay0: f64,
    window: std::ops::Range<usize>,
    max_iter: u32,
    opts: &FitOptions,
) -> MlFit {
    let end = window.end.min(x.len());
    let first = window.start.min(end);
    let xw = &x[first..end];
    let finite = delay0.is_finite() && baseline.is_finite() && xw.iter().all(|v| v.is_finite());
    if xw.is_empty() || !finite {
        return no_fit(delay0);
    }
    // y = x − baseline, computed on the fly so the fit allocates nothing.
    let yw = Centered { x: xw, baseline };
    // The shape on the window at the last delay evaluated: the sums after an
    // accepted step, and the final sums and residual, read the same delay.
    // The thread's own cache (emptied first): 4 kB zeroed once per thread,
    // not once per fit (a fresh one where a fit runs inside another's, or
    // while the thread's storage is torn down).
    thread_local! {
        static GRID: std::cell::RefCell<GridCache> = std::cell::RefCell::new(GridCache::new());
    }
    GRID.try_with(|cell| {
        cell.try_borrow_mut().ok().map(|mut grid| {
            grid.held = None;
            fit_in(first, yw, shape, delay0, max_iter, opts, &mut grid)
        })
    })
    .ok()
    .flatten()
    .unwrap_or_else(|| fit_in(first, yw, shape, delay0, max_iter, opts, &mut GridCache::new()))
}

/// [`fit_delay_with`] on the window's values less the baseline, `yw`
/// (from sample `first`), with the shape's values kept in `grid`.
fn fit_in<S: PulseShape + ?Sized>(
    first: usize,
    yw: Centered,
    shape: &S,
    delay0: f64,
    max_iter: u32,
    opts: &FitOptions,
    grid: &mut GridCache,
) -> MlFit {

    let mut delay = delay0;
    let s0 = yw.sums(first, shape, delay0, grid);
    let mut cost = if s0.ss > 0.0 {
        -(s0.sy * s0.sy) / s0.ss
    } else {
        0.0
    };

    // Coarse scan: keeps the iteration out of a wrong basin when the start is
    // poor relative to the pulse width. The basin of the projected cost is about
    // the pulse's width scale sqrt(Σs²/Σg²) (1.4σ for a Gaussian), so the scan
    // steps by a fifth of it (but no finer than `search_step`) and is skipped
    // when that step exceeds the search range: for a pulse much wider than the
    // start's error the descent iteration alone is safe.
    let width = if s0.gg > 0.0 {
        (s0.ss / s0.gg).sqrt()
    } else {
        0.0
    };
    let scan_step = opts.search_step.max(0.2 * width);
    if opts.search_half_width > 0.0 && opts.search_step > 0.0 && scan_step < opts.search_half_width
    {
        let steps = (opts.search_half_width / scan_step).floor() as i64;
        for i in (-steps..=steps).filter(|&i| i != 0) {
            let d = delay0 + i as f64 * scan_step;
            let c = yw.reduced_cost(first, shape, d, grid);
            if c < cost {
                cost = c;
                delay = d;
            }
        }
    }

    let mut converged = false;
    let mut iterations = 0;
    // The sums at the start are reused when the scan kept it.
    let mut cached = (delay == delay0).then_some(s0);
    for it in 0..max_iter {
        iterations = it + 1;
        let s = cached
            .take()
            .unwrap_or_else(|| yw.sums(first, shape, delay, grid));
        if s.ss <= 0.0 {
            break;
        }
        let a = s.sy / s.ss;
        // Linearised model around (a, d): a·s − a·g·δd + s·δa, with ∂s/∂d = −g.
        // Projecting out the amplitude direction (the residual r = y − a·s is
        // already orthogonal to s) leaves δd = (v·r) / (v·v − (s·v)²/(s·s))
        // with v = −a·g.
        let vr = -a * (s.gy - a * s.sg);
        let vv = a * a * s.gg;
        let sv = -a * s.sg;
        let h = vv - sv * sv / s.ss;
        if !(h > 0.0 && vr.is_finite()) {
            break;
        }
        let mut step = (vr / h).clamp(-opts.max_step, opts.max_step);
        // Backtrack until the cost does not increase: the Gauss-Newton step is
        // a descent direction, so a short enough step succeeds. Steps below a
        // thousandth of the pulse's width scale sqrt(Σs²/Σg²) are taken as they
        // are: there the iteration converges quadratically and the change in
        // cost is at the level of rounding, so it cannot judge the step.
        let small = 1e-3 * (s.ss / s.gg).sqrt();
        while step.abs() > small {
            let c = yw.reduced_cost(first, shape, delay + step, grid);
            if c <= cost {
                cost = c;
                break;
            }
            step *= 0.5;
        }
        delay += step;
        if step.abs() < opts.delay_tol {
            converged = true;
            break;
        }
    }

    let s = yw.sums(first, shape, delay, grid);
    let amplitude = if s.ss > 0.0 { s.sy / s.ss } else { 0.0 };
    // Summed directly: Σy² − 2aΣsy + a²Σs² would cancel catastrophically for a good fit.
    let mut rss = 0.0;
    yw.on_grid(first, shape, delay, grid, |yk, v, _| {
        let r = yk - amplitude * v;
        rss += r * r;
    });
    let has_signal = amplitude != 0.0 && s.gg > 0.0;
    MlFit {
        amplitude,
        delay,
        iterations,
        converged: converged && has_signal,
        slope_energy: s.gg,
        residual_rms: (rss / yw.x.len() as f64).sqrt(),
    }
}

/// The answer when there is nothing to fit: zero amplitude at the start delay.
fn no_fit(delay0: f64) -> MlFit {
    MlFit {
        amplitude: 0.0,
        delay: if delay0.is_finite() { delay0 } else { 0.0 },
        iterations: 0,
        converged: false,
        slope_energy: 0.0,
        residual_rms: 0.0,
    }
}

/// The window's samples minus the baseline, computed on the fly.
#[derive(Clone, Copy)]
struct Centered<'a> {
    x: &'a [f64],
    baseline: f64,
}

/// Shape values evaluated per call of [`PulseShape::fill_grid`].
const GRID_CHUNK: usize = 64;

/// Longest window whose shape values [`GridCache`] keeps.
const GRID_CACHE: usize = 256;

/// The shape's (value, slope) on the window at one delay (its bits), filled
/// chunk by chunk exactly as [`Centered::on_grid`] fills them, so that a
/// second pass at the same delay reads the very values. One fit's: emptied
/// (`held` None) before the next.
struct GridCache {
    /// Delay (bits) the values are for (the window is the fit's, one
    /// length throughout); None: nothing held.
    held: Option<u64>,
    values: [(f64, f64); GRID_CACHE],
}

impl GridCache {
    fn new() -> GridCache {
        GridCache { held: None, values: [(0.0, 0.0); GRID_CACHE] }
    }

    /// The first `n` values, filled by `fill` unless they hold `delay` already.
    #[inline(always)]
    fn at(&mut self, n: usize, delay: f64, fill: impl FnOnce(&mut [(f64, f64)])) -> &[(f64, f64)] {
        let values = &mut self.values[..n];
        if self.held != Some(delay.to_bits()) {
            fill(values);
            self.held = Some(delay.to_bits());
        }
        values
    }
}

impl Centered<'_> {
    /// Calls `f(y_k, value, slope)` for every sample of the window in order,
    /// the shape at `k − delay` evaluated on the grid a chunk at a time
    /// (vectorised, no libm call per sample); a window
    /// of at most [`GRID_CACHE`] samples keeps the values in `cache` and
    /// reuses them at the same delay.
    #[inline(always)]
    fn on_grid<S: PulseShape + ?Sized>(&self, first: usize, shape: &S, delay: f64, cache: &mut GridCache, mut f: impl FnMut(f64, f64, f64)) {
        let n = self.x.len();
        if n <= GRID_CACHE {
            let values = cache.at(n, delay, |values| {
                for (c, g) in values.chunks_mut(GRID_CHUNK).enumerate() {
                    shape.fill_grid((first + c * GRID_CHUNK) as f64 - delay, g);
                }
            });
            for (x, &(v, dv)) in self.x.iter().zip(values) {
                f(x - self.baseline, v, dv);
            }
            return;
        }
        let mut grid = [(0.0, 0.0); GRID_CHUNK];
        for (c, xs) in self.x.chunks(GRID_CHUNK).enumerate() {
            let start = c * GRID_CHUNK;
            let g = &mut grid[..xs.len()];
            shape.fill_grid((first + start) as f64 - delay, g);
            for (x, &(v, dv)) in xs.iter().zip(g.iter()) {
                f(x - self.baseline, v, dv);
            }
        }
    }

    fn sums<S: PulseShape + ?Sized>(&self, first: usize, shape: &S, delay: f64, cache: &mut GridCache) -> Sums {
        let mut s = Sums::default();
        self.on_grid(first, shape, delay, cache, |yk, v, g| {
            s.ss += v * v;
            s.sy += v * yk;
            s.gg += g * g;
            s.sg += v * g;
            s.gy += g * yk;
        });
        s
    }

    fn reduced_cost<S: PulseShape + ?Sized>(&self, first: usize, shape: &S, delay: f64, cache: &mut GridCache) -> f64 {
        let (mut ss, mut sy) = (0.0, 0.0);
        self.on_grid(first, shape, delay, cache, |yk, v, _| {
            ss += v * v;
            sy += v * yk;
        });
        if ss > 0.0 { -(sy * sy) / ss } else { 0.0 }
    }
}
