//! Constant-false-alarm-rate (CFAR) thresholds for a background whose level
//! varies along the frame: cell averaging (CA) and ordered statistic (OS).
//!
//! # Statistic
//!
//! The detector output at cell p is y_p = Σ_j g_j e_{s+j} with unit-energy
//! taps g (the matched filter, or one tap for the plain threshold detector)
//! over the samples s..s+L of the mean-removed input e = x − μ̂ (or of the
//! whitened input, which is white by construction). In locally white Gaussian
//! noise of level σ, y_p ~ N(0, σ²). The local level is estimated from
//! *training cells*: up to `training` input samples on each side of the
//! template's span, separated from it by `guard` samples. Training cells are
//! raw input samples, not detector outputs, so they are independent of each
//! other and of y_p (the guard keeps the pulse out of them), and the false-alarm
//! probability below is exact for white Gaussian noise whatever the template;
//! no hand-set factor and no exponential (square-law) approximation is involved.
//!
//! * **CA**: σ̂² = (1/N) Σ e_i² over the N training cells, test y_p > α σ̂.
//!   N σ̂²/σ² is χ²_N and independent of y_p/σ ~ N(0, 1), so y_p/σ̂ is
//!   Student-t with N degrees of freedom and
//!   `Pfa = P(t_N > α) = ½ I_{N/(N+α²)}(N/2, ½)`; α is its root for the design
//!   per-cell probability (bisection on ln Pfa).
//! * **OS**: the scale is the k-th smallest |e_i| of the N training cells,
//!   z_(k), test y_p > α z_(k). |e_i|/σ is half-normal (CDF F(z) = 1 − 2Q(z),
//!   density 2φ(z)), so
//!   `Pfa(α) = ∫₀^∞ Q(α z) · k C(N,k) F(z)^(k−1) (1 − F(z))^(N−k) 2φ(z) dz`,
//!   evaluated by Simpson's rule in log space on z ∈ [0, 12] (the order
//!   statistic's density is below e⁻⁶⁰ beyond) and solved for α by bisection.
//!   For N = k = 1 it reduces to the Cauchy tail ½ − atan(α)/π (tested).
//!
//! On coloured input (a band-limited receiver) neighbouring training cells
//! are correlated: the local variance estimate has fewer degrees of freedom
//! than cells, and cells next to the cell under test share its excursions.
//! [`CfarPlan::set_colour`] solves the factors for the estimate's
//! distribution; the guard must still span the noise's correlation (about
//! 2τ samples), or the training cells mask the cell they are meant to judge.
//! For CA the full window's distribution is exact: σ̂²/σ² = Σ μ_i Z_i²
//! with μ_i the eigenvalues of the two training blocks' correlation matrix
//! over N, and by Craig's form of Q,
//! `Pfa(α) = E Q(α σ̂/σ) = (1/π) ∫₀^{π/2} Π_i (1 + α² μ_i / sin²θ)^(−1/2) dθ`,
//! a smooth positive integrand (Simpson's rule in log space; for μ_i = 1/N
//! it is the Student-t tail). Matching the variance alone (Satterthwaite,
//! ν = N/Σρ²) or three cumulants (a shifted χ²) misplaces the lower tail of
//! so short a window: on 2 × 32 cells of AR(1) φ = 0.9 they hold 0.1–0.4×
//! and 1.2–1.7× the design at 1e-3 to 1e-4. For OS the full window's factor
//! is solved by importance-sampled Monte Carlo with the radius integrated
//! exactly ([`crate::detect::os_coloured`]; seeded, so reproducible, and
//! held to the safe side by two standard errors); partial windows at the
//! frame ends use as many white cells as their degrees of freedom, which is
//! conservative (far so on strongly coloured noise).
//!
//! The factors take the input's mean as known. The pipeline removes the
//! noise gate's mean, whose error δ is common to every cell: it moves the
//! output by (Σg)·δ and every training cell by δ, so the pipeline scales the
//! thresholds by √((1 + (Σg)²/m)/(1 + g_out²/m)) (m: the mean's effective
//! samples in output units; see `pipeline::detect`). On slow coloured noise
//! the output moves far more than the training power, and without the scale
//! CA-CFAR on AR(1) φ = 0.9 held 1.7× its design.
//!
//! Near the frame ends fewer training cells exist; each N has its own factor
//! (and for OS the rank scales as k·N/(2·training)), so the design holds there
//! too (on coloured input, OS holds it conservatively there). Where a cell's training window straddles a step in the noise level the
//! estimate mixes both levels: cells on the quiet side are desensitised and
//! cells on the loud side see more false alarms, as with every CA/OS-CFAR.

use crate::detect::finite_gate::GateVariance;
use crate::detect::os_coloured::OsColoured;
use crate::math::special::{ln_phi, ln_q};
use crate::math::stats::beta_inc_reg;

/// Which local scale estimate a [`CfarPlan`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CfarMethod {
    /// Root mean square of the training cells.
    CellAveraging,
    /// k-th smallest |training cell| (k is 1-based, for the full 2·training window).
    OrderedStatistic {
        /// Rank among the full window's cells.
        rank: usize,
    },
}

/// Errors from planning a CFAR detector.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CfarError {
    /// Training cells must be at least one per side.
    #[error("cfar training cells {0}: at least 1 per side")]
    NoTraining(usize),
    /// The OS rank is outside 1..=2·training.
    #[error("cfar OS rank {rank}: allowed 1..={max}")]
    Rank {
        /// The requested rank.
        rank: usize,
        /// 2·training.
        max: usize,
    },
    /// The per-cell false-alarm probability is outside (0, 0.5].
    #[error("cfar per-cell probability {0}: allowed (0, 0.5]")]
    Probability(f64),
}

/// ln P(t_N > α) for Student's t with `n` degrees of freedom, α ≥ 0.
pub fn ca_ln_pfa(alpha: f64, n: usize) -> f64 {
    ca_ln_pfa_nu(alpha, n as f64)
}

/// ln P(t_ν > α) for a real number of degrees of freedom ν > 0 (correlated
/// training cells carry fewer degrees of freedom than cells).
pub fn ca_ln_pfa_nu(alpha: f64, nu: f64) -> f64 {
    let x = nu / (nu + alpha * alpha);
    (0.5 * beta_inc_reg(0.5 * nu, 0.5, x)).ln()
}

/// ln P(y > α σ̂) for y standard normal and σ̂² = Σ μ_i Z_i² independent of
/// it (Z_i standard normal): Craig's formula, see the module documentation.
/// `mu` are the weights (the training window's correlation eigenvalues over
/// its cell count), α ≥ 0.
pub fn ca_ln_pfa_weights(alpha: f64, mu: &[f64]) -> f64 {
    // Simpson on θ ∈ [0, π/2]; the integrand is 0 at θ = 0 and smooth.
    const INTERVALS: usize = 256;
    let h = std::f64::consts::FRAC_PI_2 / INTERVALS as f64;
    let a2 = alpha * alpha;
    let ln_f = |i: usize| {
        let s = (i as f64 * h).sin();
        let s2 = s * s;
        -0.5 * mu.iter().map(|m| (a2 * m / s2).ln_1p()).sum::<f64>()
    };
    let mut top = f64::NEG_INFINITY;
    let mut terms = [0.0; INTERVALS];
    for (k, t) in terms.iter_mut().enumerate() {
        *t = ln_f(k + 1);
        top = top.max(*t);
    }
    let sum: f64 = terms
        .iter()
        .enumerate()
        .map(|(k, t)| {
            let i = k + 1;
            let w = if i == INTERVALS { 1.0 } else if i % 2 == 1 { 4.0 } else { 2.0 };
            w * (t - top).exp()
        })
        .sum();
    top + (sum * h / 3.0 / std::f64::consts::PI).ln()
}

/// The variance weights μ_i of a CA-CFAR window of `blocks` independent
/// blocks of `len` cells each, correlated as `rho` (ρ(0..), zero beyond):
/// the eigenvalues of one block's correlation matrix over the window's cell
/// count, once per block.
pub fn window_weights(blocks: usize, len: usize, rho: &[f64]) -> Vec<f64> {
    let r = |d: usize| rho.get(d).copied().unwrap_or(0.0);
    let mut m = vec![0.0; len * len];
    for i in 0..len {
        for j in 0..len {
            m[i * len + j] = r(i.abs_diff(j));
        }
    }
    let ev = crate::math::linalg::symmetric_eigenvalues(&m, len);
    let n = (blocks * len) as f64;
    // Rounding can leave a tiny negative eigenvalue of a nearly singular window.
    (0..blocks).flat_map(|_| ev.iter().map(move |v| v.max(0.0) / n)).collect()
}

/// CA-CFAR factor: the α with P(t_N > α) = `p_cell` (`n` training cells).
pub fn ca_factor(p_cell: f64, n: usize) -> f64 {
    ca_factor_nu(p_cell, n as f64)
}

/// CA-CFAR factor for ν degrees of freedom (real, > 0).
pub fn ca_factor_nu(p_cell: f64, nu: f64) -> f64 {
    solve_alpha(p_cell.ln(), |a| ca_ln_pfa_nu(a, nu))
}

/// ln of the order statistic's density terms on the integration grid:
/// ln[k C(N,k) F^(k−1) (1−F)^(N−k) 2φ(z)] at z_i = i·h, z ∈ [0, z_max],
/// into `dens` (cleared first); returns h.
fn os_ln_density(n: usize, k: usize, z_max: f64, dens: &mut Vec<f64>) -> f64 {
    const INTERVALS: usize = 2400;
    let h = z_max / INTERVALS as f64;
    // ln(k C(N, k)) = ln N! − ln (k−1)! − ln (N−k)!
    let ln_fact = |m: usize| (1..=m).map(|i| (i as f64).ln()).sum::<f64>();
    let ln_c = ln_fact(n) - ln_fact(k - 1) - ln_fact(n - k);
    dens.clear();
    dens.extend((0..=INTERVALS).map(|i| {
            let z = i as f64 * h;
            let ln_upper = std::f64::consts::LN_2 + ln_q(z); // ln(1 − F) = ln 2Q(z)
            let ln_f = if k > 1 {
                // F = 1 − 2Q(z); −expm1(ln 2Q) keeps it accurate near 0.
                (k - 1) as f64 * (-ln_upper.exp_m1()).ln()
            } else {
                0.0
            };
            let ln_g = if n > k {
                (n - k) as f64 * ln_upper
            } else {
                0.0
            };
            ln_c + ln_f + ln_g + std::f64::consts::LN_2 + ln_phi(z)
    }));
    h
}

/// ln Pfa of OS-CFAR with factor α, given the grid from [`os_ln_density`].
fn os_ln_pfa_grid(alpha: f64, dens: &[f64], h: f64) -> f64 {
    let last = dens.len() - 1;
    let term = |i: usize| ln_q(alpha * i as f64 * h) + dens[i];
    let top = (0..=last)
        .map(term)
        .filter(|v| v.is_finite())
        .fold(f64::NEG_INFINITY, f64::max);
    if !top.is_finite() {
        return f64::NEG_INFINITY;
    }
    let mut sum = 0.0;
    for i in 0..=last {
        let w = if i == 0 || i == last {
            1.0
        } else if i % 2 == 1 {
            4.0
        } else {
            2.0
        };
        let v = term(i);
        if v.is_finite() {
            sum += w * (v - top).exp();
        }
    }
    top + (sum * h / 3.0).ln()
}

/// P(y > α z_(k)) for OS-CFAR with `n` training cells and rank `k` (1-based),
/// white Gaussian noise. See the module documentation.
pub fn os_pfa(alpha: f64, n: usize, k: usize) -> f64 {
    let k = k.clamp(1, n.max(1));
    let mut dens = Vec::new();
    let h = os_ln_density(n, k, os_z_max(alpha, k), &mut dens);
    os_ln_pfa_grid(alpha, &dens, h).exp()
}

/// Upper integration limit: the order statistic's density is below e⁻⁶⁰
/// beyond z = 12, and Q(αz)·z^(k−1) is negligible beyond αz = 40 + 2√k, so a
/// large α (small N, small pfa) gets a grid fine enough for Q(αz)'s width 1/α.
fn os_z_max(alpha: f64, k: usize) -> f64 {
    if alpha > 0.0 {
        (12.0f64).min((40.0 + 2.0 * (k as f64).sqrt()) / alpha)
    } else {
        12.0
    }
}

/// OS-CFAR factor: the α with `os_pfa(α, n, k)` = `p_cell`.
pub fn os_factor(p_cell: f64, n: usize, k: usize) -> f64 {
    os_factor_with(p_cell, n, k, &mut Vec::new())
}

/// [`os_factor`] with the integration grid in `dens` (scratch, kept by the caller).
fn os_factor_with(p_cell: f64, n: usize, k: usize, dens: &mut Vec<f64>) -> f64 {
    let k = k.clamp(1, n.max(1));
    // The grid depends on α through z_max: solve on a fixed grid, then refine
    // once on the grid for the root found.
    let h = os_ln_density(n, k, 12.0, dens);
    let a0 = solve_alpha(p_cell.ln(), |a| os_ln_pfa_grid(a, dens, h));
    let h = os_ln_density(n, k, os_z_max(a0, k), dens);
    solve_alpha(p_cell.ln(), |a| os_ln_pfa_grid(a, dens, h))
}

/// Root of the decreasing `ln_pfa(α) = ln_p` for α ≥ 0 (ln_pfa(0) = ln ½):
/// bracket by doubling, then bisection to 1e-12 relative.
pub(crate) fn solve_alpha(ln_p: f64, ln_pfa: impl Fn(f64) -> f64) -> f64 {
    if ln_p >= -std::f64::consts::LN_2 {
        return 0.0;
    }
    let mut hi = 1.0;
    while ln_pfa(hi) > ln_p && hi < 1e300 {
        hi *= 2.0;
    }
    let mut lo = 0.0;
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if ln_pfa(mid) > ln_p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * hi {
            break;
        }
    }
    0.5 * (lo + hi)
}

/// Per-cell CFAR thresholds for one detector template; factors are solved
/// once per training-cell count and kept, the per-frame path does not allocate
/// after the first frame of a given length, and [`CfarPlan::redesign`] (a new
/// template or per-cell probability) keeps the buffers.
#[derive(Debug, Clone)]
pub struct CfarPlan {
    method: CfarMethod,
    guard: usize,
    training: usize,
    /// Template taps covered by one output cell.
    span: usize,
    /// Tap index of the template peak: output p covers input p − peak_tap ….
    peak_tap: usize,
    p_cell: f64,
    /// Degrees of freedom per training cell (1 for white input; fewer when
    /// neighbouring input samples are correlated), in 1/64 steps.
    dof_per_cell: f64,
    /// The full window's variance-estimate distribution on coloured input
    /// (None: white).
    colour: Option<GateVariance>,
    /// The full window's variance weights on coloured input (see
    /// [`window_weights`]; empty: white).
    weights: Vec<f64>,
    /// The input's normalised autocorrelation on coloured input (empty: white).
    rho: Vec<f64>,
    /// OS: the full window's drawn windows for the current colour (built on
    /// first use after a colour change, kept across probability changes).
    os_mc: Option<OsColoured>,
    /// Factor by training-cell count N (index N), solved on first use.
    factors: Vec<Option<f64>>,
    prefix: Vec<f64>,
    scratch: Vec<f64>,
    /// The OS factor's integration grid (scratch).
    dens: Vec<f64>,
    /// OS factors solved by quadrature at `p_cell`: (cells, rank, α).
    os_solved: Vec<(usize, usize, f64)>,
    /// Half the input's quantisation step (0: continuous), the least local
    /// scale: see [`CfarPlan::set_grid`].
    half_step: f64,
}

impl CfarPlan {
    /// Plans CFAR for a template of `span` taps with its peak at `peak_tap`
    /// (1 and 0 for the plain threshold detector), `guard` and `training`
    /// cells on each side, at per-cell false-alarm probability `p_cell`.
    pub fn new(
        method: CfarMethod,
        guard: usize,
        training: usize,
        span: usize,
        peak_tap: usize,
        p_cell: f64,
    ) -> Result<CfarPlan, CfarError> {
        if training == 0 {
            return Err(CfarError::NoTraining(training));
        }
        if let CfarMethod::OrderedStatistic { rank } = method
            && !(1..=2 * training).contains(&rank)
        {
            return Err(CfarError::Rank {
                rank,
                max: 2 * training,
            });
        }
        if !(p_cell > 0.0 && p_cell <= 0.5) {
            return Err(CfarError::Probability(p_cell));
        }
        let mut plan = CfarPlan {
            method,
            guard,
            training,
            span: span.max(1),
            peak_tap,
            p_cell,
            dof_per_cell: 1.0,
            colour: None,
            weights: Vec::new(),
            rho: Vec::new(),
            os_mc: None,
            factors: vec![None; 2 * training + 1],
            prefix: Vec::new(),
            scratch: Vec::with_capacity(2 * training),
            dens: Vec::new(),
            os_solved: Vec::new(),
            half_step: 0.0,
        };
        plan.factor(2 * training);
        Ok(plan)
    }

    /// The plan [`CfarPlan::new`] gives for a template of `span` taps with its
    /// peak at `peak_tap`, at per-cell probability `p_cell`, with this plan's
    /// method, guard and training cells: made in place, keeping the buffers
    /// (and the factors when `p_cell` is unchanged).
    pub fn redesign(&mut self, span: usize, peak_tap: usize, p_cell: f64) -> Result<(), CfarError> {
        if !(p_cell > 0.0 && p_cell <= 0.5) {
            return Err(CfarError::Probability(p_cell));
        }
        self.span = span.max(1);
        self.peak_tap = peak_tap;
        if p_cell.to_bits() != self.p_cell.to_bits() {
            self.p_cell = p_cell;
            self.factors.iter_mut().for_each(|f| *f = None);
            self.os_solved.clear();
            self.factor(2 * self.training);
        }
        Ok(())
    }

    /// Sets the input's colour: its normalised autocorrelation ρ(0..)
    /// (empty or `[1]`: white). Correlated training cells estimate the local
    /// variance with fewer degrees of freedom than cells and a lighter lower
    /// tail than χ²: CA solves the full window's factor on the exact
    /// distribution of the two training blocks' mean square (the weights of
    /// [`window_weights`], Craig's formula: see the module documentation)
    /// and, for partial windows, Student-t on their share of the degrees
    /// of freedom ([`GateVariance::blocks`]); OS uses the rounded effective cell count
    /// and its rank for partial windows, and the full window's factor by
    /// importance-sampled Monte Carlo on the window's correlation
    /// ([`os_factor_coloured`]: order statistics of correlated cells have no
    /// closed form). Re-solved only when the window's degrees of freedom move
    /// by more than 1 %.
    pub fn set_colour(&mut self, rho: &[f64]) {
        let white = rho.len() <= 1;
        let g = (!white).then(|| GateVariance::blocks(2, self.training, rho));
        let dof = g.map_or(1.0, |g| (g.dof() / (2 * self.training) as f64).min(1.0));
        let changed = match (self.colour, g) {
            (None, None) => false,
            (Some(a), Some(b)) => (a.dof() / b.dof() - 1.0).abs() > 0.01,
            _ => true,
        };
        if changed {
            self.dof_per_cell = dof;
            self.colour = g;
            self.weights = if white { Vec::new() } else { window_weights(2, self.training, rho) };
            self.rho.clear();
            if !white {
                self.rho.extend_from_slice(rho);
            }
            self.os_mc = None;
            self.factors.iter_mut().for_each(|f| *f = None);
            self.factor(2 * self.training);
        }
    }

    /// Sets the input's quantisation step (0 for continuous input): no local
    /// scale is taken below half a step. The factors are solved for
    /// continuous noise; on a grid, noise that moves less than a step across
    /// a window leaves most cells on the code of the mean, and their |e| is
    /// then where the mean falls between codes, not the noise: the OS scale
    /// goes to about zero and those cells exceed any threshold (on the lab
    /// scene, 8-bit codes with σ 1.4 steps and ρ(1) = 0.91, runs of gate
    /// cells did in 4 of 16 frames; on rounded AR(1) φ = 0.9, 43 of 400 000
    /// cells at every design from 1e-5 to 1e-8). Half a step is the smallest
    /// scale the grid states. Float input (step 0) is unchanged.
    pub fn set_grid(&mut self, step: f64) {
        self.half_step = if step.is_finite() { 0.5 * step.abs() } else { 0.0 };
    }

    /// Degrees of freedom of the variance estimate from `n` training cells.
    pub fn dof(&self, n: usize) -> f64 {
        n as f64 * self.dof_per_cell
    }

    /// The default OS rank for `training` cells per side: ⌈¾ · 2·training⌉.
    pub fn default_rank(training: usize) -> usize {
        (3 * training).div_ceil(2).max(1)
    }

    /// The design per-cell false-alarm probability.
    pub fn p_cell(&self) -> f64 {
        self.p_cell
    }

    /// Training cells in a full window (both sides).
    pub fn full_window(&self) -> usize {
        2 * self.training
    }

    /// Rank used with `n` training cells (OS): k·n/(2·training), rounded, at least 1.
    pub fn rank_for(&self, n: usize) -> usize {
        match self.method {
            CfarMethod::CellAveraging => 0,
            CfarMethod::OrderedStatistic { rank } => {
                ((rank * n + self.training) / (2 * self.training)).clamp(1, n.max(1))
            }
        }
    }

    /// The threshold factor α for `n` training cells (∞ for n = 0).
    pub fn factor(&mut self, n: usize) -> f64 {
        if n == 0 {
            return f64::INFINITY;
        }
        let n = n.min(2 * self.training);
        if let Some(a) = self.factors[n] {
            return a;
        }
        let a = match self.method {
            CfarMethod::CellAveraging => match self.colour {
                None => ca_factor(self.p_cell, n),
                // The full window's distribution; a partial window (frame
                // ends) the Student-t on its share of the degrees of freedom.
                Some(_) if n == 2 * self.training => {
                    let mu = &self.weights;
                    solve_alpha(self.p_cell.ln(), |a| ca_ln_pfa_weights(a, mu))
                }
                Some(_) => ca_factor_nu(self.p_cell, self.dof(n)),
            },
            // The full window on coloured input: importance-sampled Monte
            // Carlo on the window's correlation (see `os_coloured`).
            CfarMethod::OrderedStatistic { .. }
                if self.colour.is_some()
                    && n == 2 * self.training
                    && let Some(mc) = match &self.os_mc {
                        Some(mc) => Some(mc),
                        None => {
                            self.os_mc = OsColoured::new(self.p_cell, 2, self.training, self.rank_for(n), &self.rho);
                            self.os_mc.as_ref()
                        }
                    } =>
            {
                mc.factor(self.p_cell).alpha
            }
            // White cells, or a partial window (frame ends) on coloured
            // input: as many white cells as the window's degrees of freedom,
            // conservative (on 2 × 32 cells of AR(1) φ = 0.9 it gives 48
            // where the full window's factor is 10, at 4e-9). Kept across
            // colour changes and frames: it depends only on the cells and
            // the rank.
            CfarMethod::OrderedStatistic { .. } => {
                let m = (self.dof(n).round() as usize).max(1);
                let k = self.rank_for(m);
                match self.os_solved.iter().find(|e| (e.0, e.1) == (m, k)) {
                    Some(e) => e.2,
                    None => {
                        let a = os_factor_with(self.p_cell, m, k, &mut self.dens);
                        self.os_solved.push((m, k, a));
                        a
                    }
                }
            }
        };
        self.factors[n] = Some(a);
        a
    }

    /// Training windows of output cell `p` on an input of `len` samples.
    fn windows(&self, p: usize, len: usize) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let s0 = p as isize - self.peak_tap as isize;
        let s1 = s0 + self.span as isize - 1;
        let g = self.guard as isize;
        let t = self.training as isize;
        let clip = |a: isize, b: isize| {
            let a = a.clamp(0, len as isize) as usize;
            let b = b.clamp(0, len as isize) as usize;
            a..b.max(a)
        };
        (clip(s0 - g - t, s0 - g), clip(s1 + g + 1, s1 + g + 1 + t))
    }

    /// Thresholds for every output cell of a frame: `out[p] = α_N · max(scale(p), step/2)`
    /// for the detector output indexed like `e` (same length), where `e` is
    /// the mean-removed (or whitened) input. A cell without training cells
    /// gets +∞ (never a detection).
    pub fn thresholds(&mut self, e: &[f64], out: &mut Vec<f64>) {
        let len = e.len();
        out.clear();
        match self.method {
            CfarMethod::CellAveraging => {
                self.prefix.clear();
                self.prefix.push(0.0);
                let mut acc = 0.0;
                for v in e {
                    acc += v * v;
                    self.prefix.push(acc);
                }
                for p in 0..len {
                    let (a, b) = self.windows(p, len);
                    let n = a.len() + b.len();
                    let ss = (self.prefix[a.end] - self.prefix[a.start])
                        + (self.prefix[b.end] - self.prefix[b.start]);
                    let alpha = self.factor(n);
                    out.push(if n == 0 {
                        f64::INFINITY
                    } else {
                        alpha * (ss.max(0.0) / n as f64).sqrt().max(self.half_step)
                    });
                }
            }
            CfarMethod::OrderedStatistic { .. } => {
                for p in 0..len {
                    let (a, b) = self.windows(p, len);
                    let n = a.len() + b.len();
                    if n == 0 {
                        out.push(f64::INFINITY);
                        continue;
                    }
                    let k = self.rank_for(n);
                    let mut s = std::mem::take(&mut self.scratch);
                    s.clear();
                    s.extend(e[a].iter().chain(&e[b]).map(|v| v.abs()));
                    let (_, z, _) = s.select_nth_unstable_by(k - 1, |x, y| x.total_cmp(y));
                    let z = *z;
                    self.scratch = s;
                    out.push(self.factor(n) * z.max(self.half_step));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ca_factor_is_the_student_t_quantile() {
        // t_{0.999, 16} = 3.686155, t_{0.99, 32} = 2.448678 (tables).
        assert!((ca_factor(1e-3, 16) - 3.686_155).abs() < 2e-5);
        assert!((ca_factor(1e-2, 32) - 2.448_678).abs() < 2e-5);
        // t_1 is Cauchy: P(t > a) = 1/2 − atan(a)/π.
        let a = ca_factor(0.01, 1);
        assert!((0.5 - a.atan() / std::f64::consts::PI - 0.01).abs() < 1e-12);
    }

    #[test]
    fn craig_weights_give_student_t_for_white_cells_and_match_monte_carlo_on_ar1() {
        // Equal weights 1/N: the Student-t tail.
        for (n, alpha) in [(16, 3.686_155), (32, 2.448_678), (5, 7.0)] {
            let mu = vec![1.0 / n as f64; n];
            let got = ca_ln_pfa_weights(alpha, &mu);
            let want = ca_ln_pfa(alpha, n);
            assert!((got - want).abs() < 1e-7, "N {n}: {got} vs {want}");
        }
        // Two blocks of 32 cells of AR(1) φ = 0.9: P(y > α σ̂) against a
        // Monte-Carlo mean of Q(α σ̂/σ) over 200 000 windows (the
        // conditional probability is averaged, not counted, so its
        // standard error is ~1 % at α = 4.5).
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let rho: Vec<f64> = (0..200).map(|k| 0.9f64.powi(k)).collect();
        let mu = window_weights(2, 32, &rho);
        assert!((mu.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        let alpha = 4.5;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let trials = 200_000;
        let mut mean = 0.0;
        for _ in 0..trials {
            let mut ss = 0.0;
            for _ in 0..2 {
                let mut x: f64 = StandardNormal.sample(&mut rng);
                for k in 0..32 {
                    if k > 0 {
                        let e: f64 = StandardNormal.sample(&mut rng);
                        x = 0.9 * x + (1.0 - 0.81f64).sqrt() * e;
                    }
                    ss += x * x;
                }
            }
            mean += crate::math::special::q(alpha * (ss / 64.0).sqrt()) / trials as f64;
        }
        let exact = ca_ln_pfa_weights(alpha, &mu).exp();
        assert!((exact / mean - 1.0).abs() < 0.05, "{exact} vs Monte Carlo {mean}");
    }

    #[test]
    fn os_pfa_reduces_to_cauchy_for_one_cell() {
        for alpha in [0.5, 2.0, 30.0] {
            let exact = 0.5 - f64::atan(alpha) / std::f64::consts::PI;
            let got = os_pfa(alpha, 1, 1);
            assert!(
                (got / exact - 1.0).abs() < 1e-6,
                "alpha {alpha}: {got} vs {exact}"
            );
        }
        let a = os_factor(1e-3, 1, 1);
        assert!((0.5 - a.atan() / std::f64::consts::PI - 1e-3).abs() < 1e-9);
    }

    #[test]
    fn os_pfa_is_a_probability_and_decreases() {
        let p0 = os_pfa(0.0, 32, 24);
        assert!((p0 - 0.5).abs() < 1e-9, "{p0}");
        let mut last = 1.0;
        for a in [0.5, 1.0, 2.0, 4.0, 8.0] {
            let p = os_pfa(a, 32, 24);
            assert!(p < last && p > 0.0);
            last = p;
        }
        let a = os_factor(1e-6, 32, 24);
        assert!((os_pfa(a, 32, 24) / 1e-6 - 1.0).abs() < 1e-6);
    }

    #[test]
    fn windows_skip_the_template_span_and_guard() {
        let plan = CfarPlan::new(CfarMethod::CellAveraging, 2, 3, 5, 2, 1e-3).unwrap();
        // Output 20 covers inputs 18..=22; guard 16,17 and 23,24; training 13..16 and 25..28.
        assert_eq!(plan.windows(20, 100), (13..16, 25..28));
        assert_eq!(plan.windows(0, 100).0, 0..0);
        assert_eq!(plan.windows(99, 100).1, 100..100);
    }

    #[test]
    fn a_redesigned_plan_gives_what_a_new_plan_gives() {
        let e: Vec<f64> = (0..400).map(|i| ((i * 7919) % 211) as f64 / 211.0 - 0.5).collect();
        for method in [CfarMethod::CellAveraging, CfarMethod::OrderedStatistic { rank: 6 }] {
            let mut plan = CfarPlan::new(method, 2, 4, 5, 2, 1e-3).unwrap();
            let mut out = Vec::new();
            plan.thresholds(&e, &mut out);
            for (span, peak_tap, p_cell) in [(5, 2, 1e-3), (9, 3, 1e-3), (9, 3, 2e-4), (1, 0, 0.5)] {
                plan.redesign(span, peak_tap, p_cell).unwrap();
                let (mut got, mut want) = (Vec::new(), Vec::new());
                plan.thresholds(&e, &mut got);
                CfarPlan::new(method, 2, 4, span, peak_tap, p_cell).unwrap().thresholds(&e, &mut want);
                assert_eq!(got, want, "{method:?} {span} {peak_tap} {p_cell}");
            }
            assert!(plan.redesign(5, 2, 0.0).is_err());
        }
    }

    #[test]
    fn bad_plans_are_refused() {
        assert!(CfarPlan::new(CfarMethod::CellAveraging, 0, 0, 1, 0, 1e-3).is_err());
        assert!(CfarPlan::new(CfarMethod::OrderedStatistic { rank: 9 }, 0, 4, 1, 0, 1e-3).is_err());
        assert!(CfarPlan::new(CfarMethod::CellAveraging, 0, 4, 1, 0, 0.0).is_err());
    }

    /// Exceedances of the input itself (a one-tap detector) over its OS-CFAR
    /// thresholds on AR(1) φ = 0.9 noise of σ = 1.4 steps rounded to the
    /// grid (the lab scene's 8-bit codes), per cell, with and without the
    /// half-step floor; and on the same noise unrounded.
    fn os_rates_on_quantised_ar1(p_cell: f64) -> (f64, f64, f64) {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let phi: f64 = 0.9;
        let rho: Vec<f64> = (0..40).map(|k| phi.powi(k)).collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(23);
        let len = 400_000;
        let mut x: f64 = StandardNormal.sample(&mut rng);
        let cont: Vec<f64> = (0..len)
            .map(|_| {
                let u: f64 = StandardNormal.sample(&mut rng);
                x = phi * x + (1.0 - phi * phi).sqrt() * u;
                1.4 * x
            })
            .collect();
        let codes: Vec<f64> = cont.iter().map(|v| v.round()).collect();
        let rate = |e: &[f64], step: f64| {
            let mut plan = CfarPlan::new(CfarMethod::OrderedStatistic { rank: 24 }, 40, 16, 1, 0, p_cell).expect("valid");
            plan.set_colour(&rho);
            plan.set_grid(step);
            let mut thr = Vec::new();
            plan.thresholds(e, &mut thr);
            let inner = 56..e.len() - 56;
            inner.clone().filter(|&i| e[i] > thr[i]).count() as f64 / inner.len() as f64
        };
        (rate(&codes, 1.0), rate(&codes, 0.0), rate(&cont, 0.0))
    }

    #[test]
    fn the_half_step_floor_keeps_os_cfar_on_quantised_slow_noise() {
        // 400 000 cells. Without the floor the rounded noise leaves the OS
        // scale at zero in windows whose cells sit on the code of the mean:
        // those cells exceed whatever the design (measured: 43 at every
        // design from 1e-5 to 1e-8). With it, at 1e-6 the design allows 0.4
        // (clumped: a run of slow noise lasts a few cells), and at 1e-3 the
        // design's 400 are held from above (the grid makes small scales
        // coarse: measured 0.28x). Unrounded, the factor holds 1e-3 within
        // a band several standard deviations of the clumped count wide.
        let (floored, bare, _) = os_rates_on_quantised_ar1(1e-6);
        let cells = |r: f64| (r * 4e5).round();
        eprintln!("OS-CFAR, AR(1) 0.9 at 1.4 steps, design 1e-6: {} cells over with the floor, {} without", cells(floored), cells(bare));
        assert!(cells(bare) > 10.0, "without the floor the rounded noise should show the collapse: {}", cells(bare));
        assert!(cells(floored) <= 3.0, "with the floor: {} cells over", cells(floored));
        let p = 1e-3;
        let (floored, _, continuous) = os_rates_on_quantised_ar1(p);
        eprintln!("design {p:e}: with the floor {:.2}x, unrounded {:.2}x", floored / p, continuous / p);
        assert!((0.6 * p..1.4 * p).contains(&continuous), "unrounded: {continuous:e}");
        assert!(floored < 1.4 * p, "with the floor: {floored:e}");
    }
}
