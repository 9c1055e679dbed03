//! System-delay calibration from reports of a target at a known range (what
//! `tofwave calibrate` writes and `tofwave process --calibration` applies).
//!
//! The fixed start-to-stop delay is the mean of the measured minus the true
//! time of flight over the reports; with a walk table (leading-edge timing),
//! a delay per amplitude node. The result is a [`CalibrationFile`]: the delay
//! plus the timing method, fraction and comparator level it belongs to, so a
//! scene timed differently can be refused when it is applied.

use crate::detect::walk::{fit_walk, WalkError, WalkFit, WalkTable};
use crate::frame::Report;
use crate::math::select::high_median;
use crate::scene::{CalibrationConfig, CalibrationFile, CalibrationMeasurement, Scene};

/// Why no calibration could be measured.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrateError {
    /// No report holds a return.
    #[error("no returns detected in {reports} reports: nothing to calibrate on")]
    NoReturns {
        /// Reports searched.
        reports: usize,
    },
    /// The walk table could not be fitted.
    #[error(transparent)]
    Walk(#[from] WalkError),
}

/// A measured calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// What the calibration file holds; `measurement.inputs` is left empty for
    /// the caller, who knows where the reports came from.
    pub file: CalibrationFile,
    /// The fitted walk table (nodes and returns per node), when one was asked for.
    pub walk: Option<WalkFit>,
}

/// Measures the system delay from `reports` of a target at `known_range_m`.
///
/// `scene` is the scene the reports were produced with, its calibration
/// cleared (so times of flight are raw); its medium gives the true time of
/// flight and its timing section is recorded as what the delay belongs to.
/// The strongest return of each report is taken as the target. Without
/// `walk`, delays beyond 5 robust sigmas (MAD·1.4826) of the median are
/// rejected as false alarms and the delay is the mean of the rest; with
/// `walk` (leading-edge timing), a walk table is fitted by
/// [`fit_walk`] and the spread is that of the residuals after the table.
pub fn calibrate(
    reports: &[Report],
    known_range_m: f64,
    scene: &Scene,
    walk: bool,
) -> Result<Calibration, CalibrateError> {
    let true_tof_s = 2.0 * known_range_m / scene.c_medium_m_per_s();
    let mut delays = Vec::new();
    let mut amplitudes = Vec::new();
    for rep in reports {
        if let Some(ret) = rep.returns.iter().max_by(|x, y| x.amplitude_v.total_cmp(&y.amplitude_v)) {
            delays.push(ret.tof_s - true_tof_s);
            amplitudes.push(ret.amplitude_v);
        }
    }
    if delays.is_empty() {
        return Err(CalibrateError::NoReturns { reports: reports.len() });
    }
    // Outliers (a false alarm taken for the target) are rejected beyond 5 robust sigmas of the median.
    let mut scratch = delays.clone();
    let median = high_median(&mut scratch).expect("delays is not empty");
    let mut dev: Vec<f64> = delays.iter().map(|d| (d - median).abs()).collect();
    let robust = 1.4826 * high_median(&mut dev).expect("delays is not empty");
    let keep: Vec<usize> = (0..delays.len())
        .filter(|&i| robust == 0.0 || (delays[i] - median).abs() <= 5.0 * robust)
        .collect();
    let n = keep.len() as f64;
    let mean = keep.iter().map(|&i| delays[i]).sum::<f64>() / n;
    let var = if keep.len() > 1 {
        keep.iter().map(|&i| (delays[i] - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    let mut mean_amp = keep.iter().map(|&i| amplitudes[i]).sum::<f64>() / n;
    let mut calibration = CalibrationConfig { delay_s: mean, ..Default::default() };
    let (mut used, mut var, mut n) = (keep.len(), var, n);
    let mut walk_fit = None;
    if walk {
        // Walk: group by amplitude (every return; the outlier rejection is per group).
        let pairs: Vec<(f64, f64)> = amplitudes.iter().copied().zip(delays.iter().copied()).collect();
        let fit = fit_walk(&pairs)?;
        let table = WalkTable::new(&fit.amplitude_v, &fit.walk_delay_s).expect("fit_walk gives at least two nodes");
        // Residuals after the table, over the returns the fit kept (within 5 robust sigmas of their node).
        let residuals: Vec<f64> = pairs
            .iter()
            .map(|&(amp, d)| d - fit.delay_s - table.delay_s(amp))
            .collect();
        used = fit.counts.iter().sum();
        n = used as f64;
        let mut abs: Vec<f64> = residuals.iter().map(|v| v.abs()).collect();
        let cut = 5.0 * 1.4826 * high_median(&mut abs).expect("fit_walk kept at least one return");
        let kept: Vec<f64> = residuals.iter().copied().filter(|v| cut == 0.0 || v.abs() <= cut).collect();
        let rm = kept.iter().sum::<f64>() / kept.len() as f64;
        var = kept.iter().map(|v| (v - rm).powi(2)).sum::<f64>() / (kept.len() as f64 - 1.0).max(1.0);
        mean_amp = fit.amplitude_v.iter().zip(&fit.counts).map(|(a, c)| a * *c as f64).sum::<f64>() / n;
        calibration = CalibrationConfig {
            delay_s: fit.delay_s,
            walk_amplitude_v: fit.amplitude_v.clone(),
            walk_delay_s: fit.walk_delay_s.clone(),
            ..Default::default()
        };
        walk_fit = Some(fit);
    }
    // The delay's own uncertainty enters every range measured with it.
    calibration.delay_sigma_s = (var / n).sqrt();
    let file = CalibrationFile {
        calibration,
        measurement: CalibrationMeasurement {
            known_range_m,
            returns: used as u64,
            excluded: (reports.len() - used) as u64,
            delay_std_s: var.sqrt(),
            delay_sem_s: (var / n).sqrt(),
            mean_amplitude_v: mean_amp,
            timing_method: scene.timing.method,
            timing_fraction: scene.timing.fraction,
            leading_edge_v: scene.timing.leading_edge_v,
            frames_averaged: scene.averaging.frames,
            inputs: Vec::new(),
        },
    };
    Ok(Calibration { file, walk: walk_fit })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Return;

    /// A report holding returns of (time of flight s, amplitude V).
    fn report(returns: &[(f64, f64)]) -> Report {
        Report {
            returns: returns
                .iter()
                .map(|&(tof_s, amplitude_v)| Return { tof_s, amplitude_v, ..Default::default() })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn delay_is_the_mean_excess_of_the_strongest_return_without_outliers() {
        let scene = Scene::default_scene();
        let range_m = 10.0;
        let tof_s = 2.0 * range_m / scene.c_medium_m_per_s();
        let mut reports: Vec<Report> = [5.0e-9, 5.2e-9, 4.8e-9, 5.1e-9, 4.9e-9]
            .iter()
            .map(|d| report(&[(tof_s + 30e-9, 0.1), (tof_s + d, 1.0)]))
            .collect();
        // A false alarm stronger than the target, and a report without returns.
        reports.push(report(&[(tof_s + 80e-9, 2.0)]));
        reports.push(report(&[]));
        let c = calibrate(&reports, range_m, &scene, false).unwrap();
        let m = &c.file.measurement;
        assert!((c.file.calibration.delay_s - 5.0e-9).abs() < 1e-15, "{}", c.file.calibration.delay_s);
        assert_eq!((m.returns, m.excluded), (5, 2));
        // Sample variance 0.025 ns² over 5 returns.
        assert!((m.delay_std_s - 0.025f64.sqrt() * 1e-9).abs() < 1e-15);
        assert!((m.delay_sem_s - (0.025f64 / 5.0).sqrt() * 1e-9).abs() < 1e-15);
        assert_eq!(m.mean_amplitude_v, 1.0);
        assert_eq!(m.timing_method, scene.timing.method);
        assert!(c.walk.is_none() && c.file.calibration.walk_amplitude_v.is_empty());
    }

    #[test]
    fn no_returns_is_an_error() {
        let e = calibrate(&[report(&[]), report(&[])], 3.0, &Scene::default_scene(), false).unwrap_err();
        assert_eq!(e.to_string(), "no returns detected in 2 reports: nothing to calibrate on");
    }
}
