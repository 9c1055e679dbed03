//! Wire `tofwave.v1.Report` and `tofwave.v1.NoiseModel` <-> domain
//! [`Report`](crate::frame::Report) and [`NoiseSummary`](crate::frame::NoiseSummary).
//!
//! Field for field, no rounding: a report on the wire carries the same numbers
//! as its JSON line.

use super::proto;
use crate::frame::{NoiseSummary, Report};

/// Noise model on the wire.
pub fn noise_to_proto(n: &NoiseSummary) -> proto::NoiseModel {
    proto::NoiseModel {
        mean_v: n.mean_v,
        sigma_v: n.sigma_v,
        skewness: n.skewness,
        excess_kurtosis: n.excess_kurtosis,
        gaussian: n.gaussian,
        normality_p_value: n.normality_p_value,
        robust_sigma_v: n.robust_sigma_v,
        samples: n.samples,
        contaminated: n.contaminated,
    }
}

/// Noise model from the wire (state-dir reload).
pub fn noise_from_proto(n: &proto::NoiseModel) -> NoiseSummary {
    NoiseSummary {
        mean_v: n.mean_v,
        sigma_v: n.sigma_v,
        skewness: n.skewness,
        excess_kurtosis: n.excess_kurtosis,
        gaussian: n.gaussian,
        normality_p_value: n.normality_p_value,
        robust_sigma_v: n.robust_sigma_v,
        samples: n.samples,
        contaminated: n.contaminated,
    }
}

/// A report on the wire; `json` is its JSON line (`pipeline::report_json`).
pub fn report_to_proto(r: &Report, json: String) -> proto::Report {
    proto::Report {
        sensor: r.sensor.clone(),
        seq_first: r.seq_first,
        seq_last: r.seq_last,
        frames_averaged: r.frames_averaged,
        time_s: r.time_s,
        stages: r.stages.iter().map(|s| s.to_string()).collect(),
        noise: Some(noise_to_proto(&r.noise)),
        detector: Some(proto::Detector {
            kind: r.detector.kind.to_string(),
            pfa_design: r.detector.pfa_design,
            threshold: r.detector.threshold,
            pfa_cell: r.detector.pfa_cell,
            cells_effective: r.detector.cells_effective,
        }),
        false_alarm: Some(proto::FalseAlarmStats {
            expected_per_frame: r.false_alarm.expected_per_frame,
            observed: r.false_alarm.observed,
            cells: r.false_alarm.cells,
            rate: r.false_alarm.rate,
            ci95_low: r.false_alarm.ci95[0],
            ci95_high: r.false_alarm.ci95[1],
            excess: r.false_alarm.excess,
        }),
        returns: r
            .returns
            .iter()
            .map(|x| proto::Return {
                range_m: x.range_m,
                range_sigma_m: x.range_sigma_m,
                tof_s: x.tof_s,
                amplitude_v: x.amplitude_v,
                snr_db: x.snr_db,
                score: x.score,
                pd: x.pd,
                t_stop_s: x.t_stop_s,
                flags: x.flags.iter().map(|f| f.name().to_string()).collect(),
            })
            .collect(),
        t_start_s: r.t_start_s,
        t_start_sigma_s: r.t_start_sigma_s,
        flags: r.flags.iter().map(|f| f.to_string()).collect(),
        json,
    }
}

/// A report on the wire from its JSON line (`pipeline::report_json`): the
/// inverse of [`report_to_proto`] for what the JSON carries, which is every
/// wire field (`json` is the line itself). A cluster node reads reports that
/// other nodes published to NATS as JSON lines (readable by any NATS client)
/// and serves them to its gRPC subscribers with this. Numbers round-trip
/// exactly (shortest-representation floats); a non-finite number, written
/// `null`, comes back as NaN.
pub fn report_from_json(json: &str) -> Result<proto::Report, String> {
    use serde_json::Value;
    let v: Value = serde_json::from_str(json).map_err(|e| format!("not a JSON report: {e}"))?;
    let obj = |v: &Value, field: &str| -> Result<Value, String> {
        v.get(field).cloned().ok_or_else(|| format!("report JSON: no field {field:?}"))
    };
    let f = |v: &Value, field: &str| -> Result<f64, String> {
        match v.get(field) {
            Some(Value::Null) => Ok(f64::NAN),
            Some(x) => x.as_f64().ok_or_else(|| format!("report JSON: {field} is not a number")),
            None => Err(format!("report JSON: no field {field:?}")),
        }
    };
    let u = |v: &Value, field: &str| -> Result<u64, String> {
        v.get(field).and_then(Value::as_u64).ok_or_else(|| format!("report JSON: {field} is not an unsigned integer"))
    };
    let b = |v: &Value, field: &str| -> Result<bool, String> {
        v.get(field).and_then(Value::as_bool).ok_or_else(|| format!("report JSON: {field} is not a boolean"))
    };
    let s = |v: &Value, field: &str| -> Result<String, String> {
        v.get(field).and_then(Value::as_str).map(str::to_string).ok_or_else(|| format!("report JSON: {field} is not a string"))
    };
    let strings = |v: &Value, field: &str| -> Result<Vec<String>, String> {
        v.get(field)
            .and_then(Value::as_array)
            .ok_or_else(|| format!("report JSON: {field} is not a list"))?
            .iter()
            .map(|x| x.as_str().map(str::to_string).ok_or_else(|| format!("report JSON: {field} holds a non-string")))
            .collect()
    };
    let noise = obj(&v, "noise")?;
    let det = obj(&v, "detector")?;
    let fa = obj(&v, "false_alarm")?;
    let ci = fa.get("ci95").and_then(Value::as_array).ok_or("report JSON: false_alarm.ci95 is not a list")?;
    let ci_at = |i: usize| match ci.get(i) {
        Some(Value::Null) => Ok(f64::NAN),
        Some(x) => x.as_f64().ok_or_else(|| "report JSON: false_alarm.ci95 holds a non-number".to_string()),
        None => Err("report JSON: false_alarm.ci95 has fewer than 2 numbers".to_string()),
    };
    let returns = v
        .get("returns")
        .and_then(Value::as_array)
        .ok_or("report JSON: returns is not a list")?
        .iter()
        .map(|r| {
            Ok(proto::Return {
                range_m: f(r, "range_m")?,
                range_sigma_m: f(r, "range_sigma_m")?,
                tof_s: f(r, "tof_s")?,
                amplitude_v: f(r, "amplitude_v")?,
                snr_db: f(r, "snr_db")?,
                score: f(r, "score")?,
                pd: f(r, "pd")?,
                t_stop_s: f(r, "t_stop_s")?,
                flags: strings(r, "flags")?,
            })
        })
        .collect::<Result<Vec<_>, String>>()?;
    Ok(proto::Report {
        sensor: s(&v, "sensor")?,
        seq_first: u(&v, "seq_first")?,
        seq_last: u(&v, "seq_last")?,
        frames_averaged: u32::try_from(u(&v, "frames_averaged")?).map_err(|_| "report JSON: frames_averaged is too large")?,
        time_s: f(&v, "time_s")?,
        stages: strings(&v, "stages")?,
        noise: Some(proto::NoiseModel {
            mean_v: f(&noise, "mean_v")?,
            sigma_v: f(&noise, "sigma_v")?,
            skewness: f(&noise, "skewness")?,
            excess_kurtosis: f(&noise, "excess_kurtosis")?,
            gaussian: b(&noise, "gaussian")?,
            normality_p_value: f(&noise, "normality_p_value")?,
            robust_sigma_v: f(&noise, "robust_sigma_v")?,
            samples: u(&noise, "samples")?,
            contaminated: b(&noise, "contaminated")?,
        }),
        detector: Some(proto::Detector {
            kind: s(&det, "kind")?,
            pfa_design: f(&det, "pfa_design")?,
            threshold: f(&det, "threshold")?,
            pfa_cell: f(&det, "pfa_cell")?,
            cells_effective: f(&det, "cells_effective")?,
        }),
        false_alarm: Some(proto::FalseAlarmStats {
            expected_per_frame: f(&fa, "expected_per_frame")?,
            observed: u(&fa, "observed")?,
            cells: f(&fa, "cells")?,
            rate: f(&fa, "rate")?,
            ci95_low: ci_at(0)?,
            ci95_high: ci_at(1)?,
            excess: b(&fa, "excess")?,
        }),
        returns,
        t_start_s: f(&v, "t_start_s")?,
        t_start_sigma_s: f(&v, "t_start_sigma_s")?,
        flags: strings(&v, "flags")?,
        json: json.to_string(),
    })
}
