//! `[calibration]` (the system delay and the leading-edge walk table) and the
//! calibration file `tofwave calibrate` writes.

use super::check::{check, FieldError, Range};
use super::{Scene, SceneError, TimingMethod};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct CalibrationConfig {
    /// Fixed start-to-stop delay, seconds.
    pub delay_s: f64,
    /// Standard error of `delay_s`, seconds (from `tofwave calibrate`): it
    /// enters every range's uncertainty. 0: the delay is taken as exact.
    #[serde(skip_serializing_if = "is_zero")]
    pub delay_sigma_s: f64,
    /// Leading-edge walk table: return amplitudes, volts, strictly increasing.
    /// Empty: no walk correction.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub walk_amplitude_v: Vec<f64>,
    /// Leading-edge walk table: extra delay at each amplitude, seconds
    /// (subtracted, with `delay_s`, from the time of flight; interpolated
    /// linearly in ln amplitude, held constant beyond the ends).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub walk_delay_s: Vec<f64>,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl CalibrationConfig {
    /// Checks `[calibration]`: the delay and the walk table.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("calibration.delay_s", self.delay_s.into(), Range::closed(-1.0, 1.0), "[-1, 1] s"),
            ("calibration.delay_sigma_s", self.delay_sigma_s.into(), Range::closed(0.0, 1.0), "[0, 1] s"),
        ])?;
        self.validate_walk()
    }

    /// Checks the walk table: equal lengths, finite, amplitudes positive and
    /// strictly increasing, delays within ±1 s. Names the offending field.
    pub fn validate_walk(&self) -> Result<(), FieldError> {
        let (a, d) = (&self.walk_amplitude_v, &self.walk_delay_s);
        if a.len() != d.len() {
            return Err(FieldError::new(
                "calibration.walk_delay_s",
                format!("{} values ({} amplitudes)", d.len(), a.len()),
                "as many values as calibration.walk_amplitude_v",
            ));
        }
        if a.iter().any(|v| !(v.is_finite() && *v > 0.0)) || a.windows(2).any(|w| w[1] <= w[0]) {
            return Err(FieldError::new(
                "calibration.walk_amplitude_v",
                format!("{a:?}"),
                "finite, positive, strictly increasing volts",
            ));
        }
        if d.iter().any(|v| !(v.is_finite() && v.abs() <= 1.0)) {
            return Err(FieldError::new("calibration.walk_delay_s", format!("{d:?}"), "finite, [-1, 1] s"));
        }
        Ok(())
    }
}

/// A calibration file written by `tofwave calibrate` and applied by
/// `tofwave process --calibration`: the measured delay plus how it was measured,
/// so a scene timed differently can be refused rather than silently biased.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// The delay to apply.
    pub calibration: CalibrationConfig,
    /// How it was measured.
    pub measurement: CalibrationMeasurement,
}

/// Provenance and statistics of a calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationMeasurement {
    /// Range of the calibration target, m.
    pub known_range_m: f64,
    /// Returns used.
    pub returns: u64,
    /// Reports without a usable return, or rejected as outliers.
    pub excluded: u64,
    /// Standard deviation of the per-report delay, s.
    pub delay_std_s: f64,
    /// Standard error of the mean delay, s.
    pub delay_sem_s: f64,
    /// Mean amplitude of the returns used, V.
    pub mean_amplitude_v: f64,
    /// Timing method the delay belongs to.
    pub timing_method: TimingMethod,
    /// Timing fraction the delay belongs to.
    pub timing_fraction: f64,
    /// Leading-edge level the walk table belongs to, volts (0 in files
    /// written before walk tables existed).
    #[serde(default)]
    pub leading_edge_v: f64,
    /// Frames averaged per report when measured.
    pub frames_averaged: u32,
    /// Inputs measured.
    pub inputs: Vec<String>,
}

impl CalibrationFile {
    /// Reads a calibration file.
    pub fn load(path: &Path) -> Result<CalibrationFile, SceneError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: origin.clone(),
            cause: source,
        })?;
        let f: CalibrationFile = toml::from_str(&text).map_err(|e| SceneError::Parse {
            origin: origin.clone(),
            message: e.to_string().trim_end().to_string(),
        })?;
        f.calibration.validate().map_err(|error| SceneError::Invalid { origin, error })?;
        Ok(f)
    }

    /// Applies the delay to `scene`, refusing a scene timed differently from the calibration.
    pub fn apply(&self, scene: &mut Scene, origin: &str) -> Result<(), SceneError> {
        let invalid = |error| SceneError::Invalid {
            origin: origin.to_string(),
            error,
        };
        let m = &self.measurement;
        if m.timing_method != scene.timing.method || m.timing_fraction != scene.timing.fraction {
            return Err(invalid(FieldError::new(
                "measurement.timing_method",
                format!("{} at fraction {}", m.timing_method.name(), m.timing_fraction),
                "the scene's timing.method and timing.fraction (re-run `tofwave calibrate` with this scene)",
            )));
        }
        if !self.calibration.walk_amplitude_v.is_empty() && scene.timing.leading_edge_v != m.leading_edge_v {
            return Err(invalid(FieldError::new(
                "measurement.leading_edge_v",
                m.leading_edge_v,
                "the scene's timing.leading_edge_v (a walk table belongs to one comparator level)",
            )));
        }
        scene.calibration = self.calibration.clone();
        Ok(())
    }
}
