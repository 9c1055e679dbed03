//! Leading-edge walk: a fixed comparator level is crossed earlier by a large
//! pulse than by a small one of the same shape (for a Gaussian rise of width
//! σ_r the crossing sits σ_r·√(2 ln(A/V)) before the peak), so leading-edge
//! timing depends on amplitude by several nanoseconds — the source's
//! 2.8–181 ns walk errors. The table maps the return amplitude to the extra
//! delay and is subtracted with the fixed delay.
//!
//! The table is measured, not modelled: `tofwave calibrate --walk` with
//! captures of a target at a known range at several amplitudes gives pairs
//! (amplitude, measured delay); [`fit_walk`] groups them by amplitude and
//! stores each group's mean delay relative to the overall mean. Between nodes
//! the walk is interpolated linearly in ln A (the walk is a smooth function of
//! ln(A/V)); beyond the ends it is held at the end value.

/// Errors from fitting a walk table.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WalkError {
    /// Fewer than two amplitude groups had enough returns.
    #[error(
        "walk table needs returns at two or more distinct amplitudes (at least {min_per_node} returns each, amplitudes differing by more than {ratio}x); found {groups} usable group(s) among {returns} returns"
    )]
    TooFewGroups {
        /// Usable groups found.
        groups: usize,
        /// Returns offered.
        returns: usize,
        /// Returns needed per group.
        min_per_node: usize,
        /// Amplitude ratio that separates groups.
        ratio: f64,
    },
}

/// Amplitude ratio within which returns share one table node.
pub const GROUP_RATIO: f64 = 1.1;
/// Returns needed for a node.
pub const MIN_PER_NODE: usize = 5;

/// A walk table, ready to interpolate.
#[derive(Debug, Clone, PartialEq)]
pub struct WalkTable {
    /// ln of the node amplitudes, increasing.
    ln_amplitude: Vec<f64>,
    /// Extra delay at each node, s.
    delay_s: Vec<f64>,
}

impl WalkTable {
    /// From the calibration's table; `None` when it is empty. The table is
    /// validated at load (`CalibrationConfig::validate_walk`).
    pub fn new(amplitude_v: &[f64], delay_s: &[f64]) -> Option<WalkTable> {
        if amplitude_v.is_empty() || amplitude_v.len() != delay_s.len() {
            return None;
        }
        Some(WalkTable {
            ln_amplitude: amplitude_v.iter().map(|a| a.ln()).collect(),
            delay_s: delay_s.to_vec(),
        })
    }

    /// Extra delay for a return of `amplitude_v`, s: linear in ln A between
    /// nodes, the end value beyond them (and for a non-positive amplitude).
    pub fn delay_s(&self, amplitude_v: f64) -> f64 {
        let (x, y) = (&self.ln_amplitude, &self.delay_s);
        let last = x.len() - 1;
        if amplitude_v.is_nan() || amplitude_v <= 0.0 {
            return y[0];
        }
        let u = amplitude_v.ln();
        if u <= x[0] {
            return y[0];
        }
        if u >= x[last] {
            return y[last];
        }
        let i = x.partition_point(|&v| v <= u).clamp(1, last);
        let t = (u - x[i - 1]) / (x[i] - x[i - 1]);
        y[i - 1] + t * (y[i] - y[i - 1])
    }
}

/// A fitted walk table with the fixed delay it is relative to.
#[derive(Debug, Clone, PartialEq)]
pub struct WalkFit {
    /// Mean of the node delays, s (the calibration's `delay_s`).
    pub delay_s: f64,
    /// Node amplitudes (geometric mean of each group), V, increasing.
    pub amplitude_v: Vec<f64>,
    /// Node delay minus `delay_s`, s.
    pub walk_delay_s: Vec<f64>,
    /// Returns per node.
    pub counts: Vec<usize>,
    /// Returns left out (groups too small, or beyond 5 robust sigmas of their group's median).
    pub excluded: usize,
}

/// Fits a walk table to (amplitude V, measured delay s) pairs.
///
/// Pairs are sorted by amplitude and grouped greedily: a group takes every
/// return up to [`GROUP_RATIO`] times its smallest amplitude. Groups with
/// fewer than [`MIN_PER_NODE`] returns are dropped; within a group, delays
/// beyond 5 robust sigmas (MAD·1.4826) of its median are rejected (a false
/// alarm taken for the target). Each node is the group's geometric-mean
/// amplitude and mean delay. Non-finite or non-positive amplitudes are
/// excluded.
pub fn fit_walk(pairs: &[(f64, f64)]) -> Result<WalkFit, WalkError> {
    let mut v: Vec<(f64, f64)> = pairs
        .iter()
        .copied()
        .filter(|(a, d)| a.is_finite() && *a > 0.0 && d.is_finite())
        .collect();
    let mut excluded = pairs.len() - v.len();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut nodes: Vec<(f64, f64, usize)> = Vec::new();
    let mut i = 0;
    while i < v.len() {
        let lo = v[i].0;
        let j = i + v[i..].partition_point(|p| p.0 <= lo * GROUP_RATIO);
        let group = &v[i..j];
        i = j;
        if group.len() < MIN_PER_NODE {
            excluded += group.len();
            continue;
        }
        let mut d: Vec<f64> = group.iter().map(|p| p.1).collect();
        d.sort_by(f64::total_cmp);
        let med = d[d.len() / 2];
        let mut dev: Vec<f64> = d.iter().map(|x| (x - med).abs()).collect();
        dev.sort_by(f64::total_cmp);
        let robust = 1.4826 * dev[dev.len() / 2];
        let keep: Vec<&(f64, f64)> = group
            .iter()
            .filter(|p| robust == 0.0 || (p.1 - med).abs() <= 5.0 * robust)
            .collect();
        excluded += group.len() - keep.len();
        let n = keep.len() as f64;
        let ln_a = keep.iter().map(|p| p.0.ln()).sum::<f64>() / n;
        let mean_d = keep.iter().map(|p| p.1).sum::<f64>() / n;
        nodes.push((ln_a.exp(), mean_d, keep.len()));
    }
    if nodes.len() < 2 {
        return Err(WalkError::TooFewGroups {
            groups: nodes.len(),
            returns: pairs.len(),
            min_per_node: MIN_PER_NODE,
            ratio: GROUP_RATIO,
        });
    }
    let delay_s = nodes.iter().map(|n| n.1).sum::<f64>() / nodes.len() as f64;
    Ok(WalkFit {
        delay_s,
        amplitude_v: nodes.iter().map(|n| n.0).collect(),
        walk_delay_s: nodes.iter().map(|n| n.1 - delay_s).collect(),
        counts: nodes.iter().map(|n| n.2).collect(),
        excluded,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_in_ln_amplitude_and_holds_the_ends() {
        let t = WalkTable::new(&[0.1, 1.0], &[2e-9, 0.0]).unwrap();
        assert!((t.delay_s(0.1f64.sqrt()) - 1e-9).abs() < 1e-20);
        assert_eq!(t.delay_s(0.01), 2e-9);
        assert_eq!(t.delay_s(5.0), 0.0);
        assert_eq!(t.delay_s(-1.0), 2e-9);
        assert!(WalkTable::new(&[], &[]).is_none());
    }

    #[test]
    fn fit_groups_by_amplitude() {
        let mut pairs = Vec::new();
        for (a, d) in [(0.05, 10e-9), (0.5, 6e-9), (2.0, 5e-9)] {
            for k in 0..10 {
                pairs.push((a * (1.0 + 0.002 * k as f64), d + 1e-12 * k as f64));
            }
        }
        pairs.push((0.2, 0.0)); // a lone return: no node
        pairs.push((0.05, 1.0)); // an outlier in the first group
        let f = fit_walk(&pairs).unwrap();
        assert_eq!(f.amplitude_v.len(), 3);
        assert_eq!(f.excluded, 2);
        let mean = (10e-9 + 6e-9 + 5e-9) / 3.0 + 4.5e-12;
        assert!((f.delay_s - mean).abs() < 1e-15);
        assert!((f.walk_delay_s[0] + f.delay_s - 10e-9 - 4.5e-12).abs() < 1e-15);
        assert!(fit_walk(&pairs[..10]).is_err());
    }
}
