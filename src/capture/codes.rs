//! Integer codes for the writers of integer formats (`.trc`, `.isf`).
//!
//! Channels that already hold i8/i16-range codes with one shared scale are
//! written code for code (exact round trip). Anything else (floats, mixed
//! scales, wide i32 codes) is quantised to i16 over its own range: the error
//! is at most half a code, i.e. `(max - min) / 130000` volts.

use std::path::Path;

use super::CaptureError;
use crate::frame::{Channel, Samples};

/// Codes of several channels (or segments) sharing one scale.
pub(crate) enum Codes {
    /// One byte per sample.
    I8(Vec<Vec<i8>>),
    /// Two bytes per sample.
    I16(Vec<Vec<i16>>),
}

/// Codes plus `volts = code * volts_per_code + offset_v`.
pub(crate) struct Encoded {
    pub codes: Codes,
    pub volts_per_code: f64,
    pub offset_v: f64,
}

fn invalid(path: &Path, expected: impl Into<String>, found: impl Into<String>) -> CaptureError {
    CaptureError::InvalidFrame {
        path: path.to_path_buf(),
        expected: expected.into(),
        found: found.into(),
    }
}

/// Encodes channels into shared-scale codes. `allow_i8` lets i8 input stay
/// 8-bit. Scales and offsets are rounded to f32 first when `f32_scale`
/// (formats that store them as binary32), so the codes match the stored scale.
pub(crate) fn encode(
    path: &Path,
    chans: &[&Channel],
    allow_i8: bool,
    f32_scale: bool,
) -> Result<Encoded, CaptureError> {
    let Some(first) = chans.first() else {
        return Err(invalid(path, "at least one channel", "none"));
    };
    for c in chans {
        if !(c.volts_per_code.is_finite() && c.offset_v.is_finite()) {
            return Err(invalid(
                path,
                "a finite volts_per_code and offset_v",
                format!(
                    "{} and {} on channel {}",
                    c.volts_per_code, c.offset_v, c.name
                ),
            ));
        }
        if let Some(i) = (0..c.samples.len()).find(|&i| !c.samples.raw(i).is_finite()) {
            return Err(invalid(
                path,
                "finite samples",
                format!("{} at index {i} of channel {}", c.samples.raw(i), c.name),
            ));
        }
    }
    let same_scale = chans.iter().all(|c| {
        c.volts_per_code.to_bits() == first.volts_per_code.to_bits()
            && c.offset_v.to_bits() == first.offset_v.to_bits()
    }) && first.volts_per_code != 0.0;
    if same_scale && allow_i8 && chans.iter().all(|c| matches!(c.samples, Samples::I8(_))) {
        let codes = chans
            .iter()
            .map(|c| match &c.samples {
                Samples::I8(v) => v.clone(),
                _ => unreachable!("checked above"),
            })
            .collect();
        return Ok(Encoded {
            codes: Codes::I8(codes),
            volts_per_code: first.volts_per_code,
            offset_v: first.offset_v,
        });
    }
    let fits_i16 = |c: &&Channel| {
        c.samples.is_integer()
            && (0..c.samples.len()).all(|i| {
                c.samples
                    .code(i)
                    .is_some_and(|x| (i16::MIN as i64..=i16::MAX as i64).contains(&x))
            })
    };
    if same_scale && chans.iter().all(fits_i16) {
        let codes = chans
            .iter()
            .map(|c| {
                (0..c.samples.len())
                    .map(|i| c.samples.code(i).unwrap_or(0) as i16)
                    .collect()
            })
            .collect();
        return Ok(Encoded {
            codes: Codes::I16(codes),
            volts_per_code: first.volts_per_code,
            offset_v: first.offset_v,
        });
    }
    // Quantise the volts of all channels over their common range.
    let volts: Vec<Vec<f64>> = chans.iter().map(|c| c.volts()).collect();
    let (lo, hi) = volts
        .iter()
        .flatten()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        // No samples at all: any scale will do.
        return Ok(Encoded {
            codes: Codes::I16(volts.iter().map(|_| Vec::new()).collect()),
            volts_per_code: 1.0,
            offset_v: 0.0,
        });
    }
    let round = |x: f64| if f32_scale { x as f32 as f64 } else { x };
    let offset_v = round(0.5 * (lo + hi));
    // 65000 codes instead of 65535 leave room for the f32 rounding of the scale.
    let span = hi - lo;
    let volts_per_code = if span > 0.0 {
        round(span / 65000.0)
    } else {
        1.0
    };
    if !(volts_per_code.is_finite() && volts_per_code > 0.0) {
        return Err(invalid(
            path,
            "sample values whose range fits the format's scale",
            format!("range {lo} .. {hi} V"),
        ));
    }
    let codes = volts
        .iter()
        .map(|v| {
            v.iter()
                .map(|&x| {
                    ((x - offset_v) / volts_per_code)
                        .round()
                        .clamp(i16::MIN as f64, i16::MAX as f64) as i16
                })
                .collect()
        })
        .collect();
    Ok(Encoded {
        codes: Codes::I16(codes),
        volts_per_code,
        offset_v,
    })
}
