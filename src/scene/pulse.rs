//! `[return_pulse]` and `[start_pulse]`: pulse shapes, and their conversion to
//! the dsp shapes at a sampling period.

use super::check::{check, FieldError, Range};
use crate::frame::limits::{MAX_PULSE_FWHM_S, MAX_PULSE_TABLE_SPAN_S, MAX_PULSE_TABLE_VALUES};
use crate::dsp::pulse::{Pulse, Shape, TablePulse};
use serde::{Deserialize, Serialize};

/// Parametric pulse shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PulseModel {
    /// Gaussian rising half, slower Gaussian falling half.
    Bigaussian,
    /// Symmetric Gaussian (rise time is implied by the FWHM).
    Gaussian,
    /// A measured shape: `table` values (unit peak) every `table_step_s`,
    /// the first at `table_first_s` relative to the peak. `tofwave template` learns one.
    Table,
}

/// A pulse shape.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PulseConfig {
    /// Model family.
    pub model: PulseModel,
    /// 10-90 % rise time, seconds (bigaussian only).
    #[serde(default)]
    pub rise_time_s: f64,
    /// Full width at half maximum, seconds (parametric models).
    #[serde(default)]
    pub fwhm_s: f64,
    /// Table model: spacing of the values, seconds.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub table_step_s: f64,
    /// Table model: time of the first value relative to the peak, seconds (negative).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub table_first_s: f64,
    /// Table model: the shape, unit peak.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub table: Vec<f64>,
}

impl Default for PulseConfig {
    /// The source's measured return pulse.
    fn default() -> Self {
        PulseConfig::default_return()
    }
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl PulseConfig {
    /// The shape at sampling period `dt_s` (units of samples): parametric, or
    /// the measured table.
    pub fn shape(&self, dt_s: f64) -> Shape {
        match self.model {
            PulseModel::Table => Shape::Table(TablePulse::new(
                self.table.clone(),
                self.table_step_s / dt_s,
                self.table_first_s / dt_s,
            )),
            _ => Shape::Parametric(self.pulse(dt_s)),
        }
    }

    /// The parametric shape at sampling period `dt_s`; a table model falls
    /// back to a Gaussian of the table's FWHM.
    pub fn pulse(&self, dt_s: f64) -> Pulse {
        match self.model {
            // The table's FWHM is already in samples: a period of 1 keeps it so.
            PulseModel::Table => Pulse::gaussian(self.shape(dt_s).fwhm(), 1.0),
            PulseModel::Gaussian => Pulse::gaussian(self.fwhm_s, dt_s),
            PulseModel::Bigaussian => Pulse::bigaussian(self.rise_time_s, self.fwhm_s, dt_s),
        }
    }
    /// Checks one pulse section; `section` is its name (`return_pulse`, `start_pulse`).
    /// Length of the pulse's support (where its template has taps), seconds:
    /// independent of the sampling period, and computed without building the
    /// shape (no allocation, so the per-frame bound check can call it).
    pub fn support_s(&self) -> f64 {
        match self.model {
            PulseModel::Table => self.table.len().saturating_sub(1) as f64 * self.table_step_s,
            _ => {
                let (lo, hi) = self.pulse(1.0).support();
                hi - lo
            }
        }
    }

    /// Taps of this pulse's template at sampling period `dt_s` (an upper bound;
    /// `inf` or NaN for a period that is not positive).
    pub fn template_taps(&self, dt_s: f64) -> f64 {
        (self.support_s() / dt_s).ceil() + 1.0
    }

    /// Checks the section (`section` names it in errors). Besides the shape's
    /// own consistency, the resource bounds of [`crate::frame::limits`]:
    /// `fwhm_s` at most `MAX_PULSE_FWHM_S`, a table of at most
    /// `MAX_PULSE_TABLE_VALUES` values spanning at most `MAX_PULSE_TABLE_SPAN_S`.
    pub fn validate(&self, section: &str) -> Result<(), FieldError> {
        if self.model == PulseModel::Table {
            check(&[(
                &format!("{section}.table"),
                self.table.len().into(),
                Range::closed(0.0, MAX_PULSE_TABLE_VALUES as f64),
                "at most 262144 values (frame::limits::MAX_PULSE_TABLE_VALUES)",
            )])?;
            let span_s = self.support_s();
            if span_s.is_finite() && span_s > MAX_PULSE_TABLE_SPAN_S {
                return Err(FieldError::new(
                    format!("{section}.table_step_s"),
                    format!("{} s over {} values ({span_s} s)", self.table_step_s, self.table.len()),
                    "a table spanning at most 1e-5 s (frame::limits::MAX_PULSE_TABLE_SPAN_S)",
                ));
            }
        }
        if self.model == PulseModel::Table {
            let peak = self.table.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            if self.table.len() < 4
                || self.table.iter().any(|v| !v.is_finite())
                || (peak - 1.0).abs() > 0.01
                || !(self.table_step_s.is_finite() && self.table_step_s > 0.0)
                || !(self.table_first_s.is_finite() && self.table_first_s < 0.0)
            {
                return Err(FieldError::new(
                    format!("{section}.table"),
                    format!(
                        "{} values, step {} s, first {} s, peak {peak}",
                        self.table.len(),
                        self.table_step_s,
                        self.table_first_s
                    ),
                    "at least 4 finite values with peak 1 (within 1 %), table_step_s > 0, table_first_s < 0",
                ));
            }
            return Ok(());
        }
        if !Range::positive_max(MAX_PULSE_FWHM_S).contains(self.fwhm_s) {
            return Err(FieldError::new(
                format!("{section}.fwhm_s"),
                self.fwhm_s,
                "(0, 1e-6] s (frame::limits::MAX_PULSE_FWHM_S)",
            ));
        }
        if self.model == PulseModel::Bigaussian {
            // The rising half's share of the FWHM is 1.1774/1.6869 of the
            // rise time; it must leave a positive falling half.
            let max_rise = self.fwhm_s * 1.686_922_421_262_926_4 / 1.177_410_022_515_474_6;
            if !Range::open(0.0, max_rise).contains(self.rise_time_s) {
                return Err(FieldError::new(
                    format!("{section}.rise_time_s"),
                    self.rise_time_s,
                    "(0, 1.43 * fwhm_s) s: the rising half must fit inside the FWHM",
                ));
            }
        }
        Ok(())
    }


    pub(super) fn default_return() -> Self {
        PulseConfig {
            model: PulseModel::Bigaussian,
            rise_time_s: 8.08e-9,
            fwhm_s: 26.04e-9,
            table_step_s: 0.0,
            table_first_s: 0.0,
            table: Vec::new(),
        }
    }
    pub(super) fn default_start() -> Self {
        PulseConfig {
            model: PulseModel::Bigaussian,
            rise_time_s: 3.02e-9,
            fwhm_s: 8.0e-9,
            table_step_s: 0.0,
            table_first_s: 0.0,
            table: Vec::new(),
        }
    }
}
