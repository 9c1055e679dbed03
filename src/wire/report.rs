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
