//! Wire `tofwave.v1.Frame` <-> domain [`Frame`](crate::frame::Frame).
//!
//! Encoding never loses information: integer codes travel as packed
//! little-endian integers of the same width, `f32` samples as binary32 and
//! `f64` samples as binary64 (`SAMPLE_FORMAT_F64`), so a recording of any
//! domain frame decodes to an identical frame. Decoding validates everything a
//! sender can get wrong and names the offending field
//! (`channels[1].samples`, `sample_interval_s`, ...), because the message goes
//! straight back to the sender (the gRPC service answers `INVALID_ARGUMENT`).

use bytes::Bytes;

use super::proto;
use crate::frame::limits::{self, MAX_SAMPLES_PER_FRAME};
use crate::frame::{Channel, ChannelRole, Frame, Samples};

/// A wire message that does not make a valid domain value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConvertError {
    /// A field holds a value the domain type cannot take.
    #[error("{field}: {message}")]
    InvalidField {
        /// Path of the offending field, e.g. `channels[1].samples` or `sample_interval_s`.
        field: String,
        /// What is wrong with it (expected vs found).
        message: String,
    },
}

impl ConvertError {
    fn new(field: impl Into<String>, message: impl Into<String>) -> Self {
        ConvertError::InvalidField {
            field: field.into(),
            message: message.into(),
        }
    }

    /// Path of the offending field, e.g. `channels[1].samples`.
    pub fn field(&self) -> &str {
        match self {
            ConvertError::InvalidField { field, .. } => field,
        }
    }

    /// What is wrong with the field (expected vs found).
    pub fn message(&self) -> &str {
        match self {
            ConvertError::InvalidField { message, .. } => message,
        }
    }
}

fn role_to_proto(role: ChannelRole) -> proto::ChannelRole {
    match role {
        ChannelRole::Unspecified => proto::ChannelRole::Unspecified,
        ChannelRole::Start => proto::ChannelRole::Start,
        ChannelRole::Stop => proto::ChannelRole::Stop,
        ChannelRole::Other => proto::ChannelRole::Other,
    }
}

fn role_from_proto(role: proto::ChannelRole) -> ChannelRole {
    match role {
        proto::ChannelRole::Unspecified => ChannelRole::Unspecified,
        proto::ChannelRole::Start => ChannelRole::Start,
        proto::ChannelRole::Stop => ChannelRole::Stop,
        proto::ChannelRole::Other => ChannelRole::Other,
    }
}

/// Packs samples little-endian; returns the wire format and the bytes.
fn pack(samples: &Samples) -> (proto::SampleFormat, Vec<u8>) {
    match samples {
        Samples::I8(v) => (
            proto::SampleFormat::I8,
            v.iter().map(|&x| x as u8).collect(),
        ),
        Samples::I16(v) => (
            proto::SampleFormat::I16,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        ),
        Samples::I32(v) => (
            proto::SampleFormat::I32,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        ),
        Samples::F32(v) => (
            proto::SampleFormat::F32,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        ),
        Samples::F64(v) => (
            proto::SampleFormat::F64,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        ),
    }
}

/// Converts a domain frame to its wire form, losslessly (see the module docs).
pub fn frame_to_proto(frame: &Frame) -> proto::Frame {
    proto::Frame {
        sensor_id: frame.sensor_id.clone(),
        sequence: frame.sequence,
        trigger_time_s: frame.trigger_time_s,
        sample_interval_s: frame.sample_interval_s,
        first_sample_offset_s: frame.first_sample_offset_s,
        channels: frame
            .channels
            .iter()
            .map(|c| {
                let (format, bytes) = pack(&c.samples);
                proto::Channel {
                    name: c.name.clone(),
                    role: role_to_proto(c.role) as i32,
                    format: format as i32,
                    samples: Bytes::from(bytes),
                    volts_per_code: c.volts_per_code,
                    offset_v: c.offset_v,
                }
            })
            .collect(),
        laser_off: frame.laser_off,
    }
}

/// `bytes` as `N`-byte little-endian chunks, refusing a ragged tail;
/// `field` names the field in the error (formatted only then).
fn chunks<'a, const N: usize>(
    bytes: &'a [u8],
    field: &dyn Fn() -> String,
    kind: &str,
) -> Result<impl Iterator<Item = [u8; N]> + 'a, ConvertError> {
    if !bytes.len().is_multiple_of(N) {
        return Err(ConvertError::new(
            field(),
            format!(
                "expected a multiple of {N} bytes for {kind} samples, found {} bytes",
                bytes.len()
            ),
        ));
    }
    Ok(bytes.chunks_exact(N).map(|c| <[u8; N]>::try_from(c).expect("chunks_exact gives N bytes")))
}

/// The samples of channel `i`, `bytes` in `format`; errors name the
/// channel's `samples` or `format` field (formatted only then).
fn unpack(format: i32, bytes: &[u8], i: usize) -> Result<Samples, ConvertError> {
    let field = || format!("channels[{i}].samples");
    let format_field = || format!("channels[{i}].format");
    let format = proto::SampleFormat::try_from(format).map_err(|_| {
        ConvertError::new(
            format_field(),
            format!(
                "expected a known sample format (I8, I16, I32, F32, F64), found value {format}"
            ),
        )
    })?;
    Ok(match format {
        proto::SampleFormat::Unspecified => {
            return Err(ConvertError::new(
                format_field(),
                "expected a sample format (I8, I16, I32, F32, F64), found SAMPLE_FORMAT_UNSPECIFIED",
            ));
        }
        proto::SampleFormat::I8 => Samples::I8(bytes.iter().map(|&b| b as i8).collect()),
        proto::SampleFormat::I16 => Samples::I16(chunks::<2>(bytes, &field, "i16")?.map(i16::from_le_bytes).collect()),
        proto::SampleFormat::I32 => Samples::I32(chunks::<4>(bytes, &field, "i32")?.map(i32::from_le_bytes).collect()),
        proto::SampleFormat::F32 => {
            let v: Vec<f32> = chunks::<4>(bytes, &field, "f32")?.map(f32::from_le_bytes).collect();
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(ConvertError::new(
                    field(),
                    format!("expected finite samples, found {} at index {i}", v[i]),
                ));
            }
            Samples::F32(v)
        }
        proto::SampleFormat::F64 => {
            let v: Vec<f64> = chunks::<8>(bytes, &field, "f64")?.map(f64::from_le_bytes).collect();
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(ConvertError::new(
                    field(),
                    format!("expected finite samples, found {} at index {i}", v[i]),
                ));
            }
            Samples::F64(v)
        }
    })
}

/// Checks a sensor id as every wire message carries it: at most
/// [`MAX_SENSOR_ID_BYTES`](limits::MAX_SENSOR_ID_BYTES) bytes, printable
/// (no control characters: a NUL, newline or escape in an id would reach
/// thread names, file names, metric labels and logs). The empty id passes
/// here (it means "the default" in control calls); ingest refuses it itself.
/// The error's [`field`](ConvertError::field) is `sensor_id`.
pub fn check_sensor_id(id: &str) -> Result<(), ConvertError> {
    match limits::sensor_id_problem(id) {
        Some(problem) => Err(ConvertError::new("sensor_id", problem)),
        None => Ok(()),
    }
}

/// Converts and validates a wire frame; the error names the offending field.
///
/// Refused: no channels; channels of unequal length; a byte length that is
/// not a multiple of the sample size; an unknown or unspecified sample
/// format or channel role; NaN/Inf float samples; `sample_interval_s` not
/// finite and > 0; non-finite `trigger_time_s`, `first_sample_offset_s` or
/// `offset_v`; `volts_per_code` zero or non-finite for integer codes. A zero
/// `volts_per_code` on float samples is read as 1 (the values are volts).
/// Resource bounds ([`limits`](crate::frame::limits)): a sensor id that
/// [`check_sensor_id`] refuses; `sample_interval_s` outside
/// [`MIN_SAMPLE_INTERVAL_S`](limits::MIN_SAMPLE_INTERVAL_S),
/// [`MAX_SAMPLE_INTERVAL_S`](limits::MAX_SAMPLE_INTERVAL_S); more than
/// [`MAX_SAMPLES_PER_FRAME`] samples per channel (checked on the byte
/// length, before anything is unpacked).
pub fn frame_from_proto(msg: &proto::Frame) -> Result<Frame, ConvertError> {
    check_sensor_id(&msg.sensor_id)?;
    if !(msg.sample_interval_s.is_finite() && msg.sample_interval_s > 0.0) {
        return Err(ConvertError::new(
            "sample_interval_s",
            format!(
                "expected a finite sampling period > 0 s, found {}",
                msg.sample_interval_s
            ),
        ));
    }
    if let Some(problem) = limits::sample_interval_problem(msg.sample_interval_s) {
        return Err(ConvertError::new("sample_interval_s", problem));
    }
    if !msg.trigger_time_s.is_finite() {
        return Err(ConvertError::new(
            "trigger_time_s",
            format!("expected a finite time, found {}", msg.trigger_time_s),
        ));
    }
    if !msg.first_sample_offset_s.is_finite() {
        return Err(ConvertError::new(
            "first_sample_offset_s",
            format!(
                "expected a finite time, found {}",
                msg.first_sample_offset_s
            ),
        ));
    }
    if msg.channels.is_empty() {
        return Err(ConvertError::new(
            "channels",
            "expected at least one channel, found none",
        ));
    }
    let mut channels = Vec::with_capacity(msg.channels.len());
    for (i, c) in msg.channels.iter().enumerate() {
        let width = match proto::SampleFormat::try_from(c.format) {
            Ok(proto::SampleFormat::I16) => 2,
            Ok(proto::SampleFormat::I32 | proto::SampleFormat::F32) => 4,
            Ok(proto::SampleFormat::F64) => 8,
            _ => 1,
        };
        if c.samples.len() / width > MAX_SAMPLES_PER_FRAME {
            return Err(ConvertError::new(
                format!("channels[{i}].samples"),
                format!(
                    "{} samples ({} bytes) is out of range: allowed at most {MAX_SAMPLES_PER_FRAME} samples per channel",
                    c.samples.len() / width,
                    c.samples.len()
                ),
            ));
        }
        let samples = unpack(c.format, &c.samples, i)?;
        let role = proto::ChannelRole::try_from(c.role).map_err(|_| {
            ConvertError::new(
                format!("channels[{i}].role"),
                format!(
                    "expected a known channel role (0..=3), found value {}",
                    c.role
                ),
            )
        })?;
        let mut volts_per_code = c.volts_per_code;
        if samples.is_integer() {
            if !(volts_per_code.is_finite() && volts_per_code != 0.0) {
                return Err(ConvertError::new(
                    format!("channels[{i}].volts_per_code"),
                    format!(
                        "expected a finite non-zero scale for {} codes, found {volts_per_code}",
                        samples.kind()
                    ),
                ));
            }
        } else if volts_per_code == 0.0 {
            volts_per_code = 1.0;
        } else if !volts_per_code.is_finite() {
            return Err(ConvertError::new(
                format!("channels[{i}].volts_per_code"),
                format!("expected a finite scale, found {volts_per_code}"),
            ));
        }
        if !c.offset_v.is_finite() {
            return Err(ConvertError::new(
                format!("channels[{i}].offset_v"),
                format!("expected a finite offset, found {}", c.offset_v),
            ));
        }
        if let Some(first) = channels.first().map(|c: &Channel| c.samples.len())
            && samples.len() != first
        {
            return Err(ConvertError::new(
                format!("channels[{i}].samples"),
                format!(
                    "expected {first} samples (as channels[0]), found {}",
                    samples.len()
                ),
            ));
        }
        channels.push(Channel {
            name: c.name.clone(),
            role: role_from_proto(role),
            samples,
            volts_per_code,
            offset_v: c.offset_v,
        });
    }
    Ok(Frame {
        sensor_id: msg.sensor_id.clone(),
        sequence: msg.sequence,
        trigger_time_s: msg.trigger_time_s,
        sample_interval_s: msg.sample_interval_s,
        first_sample_offset_s: msg.first_sample_offset_s,
        channels,
        laser_off: msg.laser_off,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> Frame {
        Frame {
            sensor_id: "s1".into(),
            sequence: 7,
            trigger_time_s: 1.5e9 + 0.125,
            sample_interval_s: 1e-9,
            first_sample_offset_s: -1.2e-7,
            channels: vec![
                Channel {
                    name: "C1".into(),
                    role: ChannelRole::Start,
                    samples: Samples::I8(vec![-128, 0, 127]),
                    volts_per_code: 0.01,
                    offset_v: -0.5,
                },
                Channel {
                    name: "C2".into(),
                    role: ChannelRole::Stop,
                    samples: Samples::I16(vec![-32768, 1, 32767]),
                    volts_per_code: 1.25e-4,
                    offset_v: 1.0,
                },
                Channel {
                    name: "m".into(),
                    role: ChannelRole::Other,
                    samples: Samples::I32(vec![i32::MIN, 0, i32::MAX]),
                    volts_per_code: 1e-9,
                    offset_v: 0.0,
                },
                Channel {
                    name: "f".into(),
                    role: ChannelRole::Unspecified,
                    samples: Samples::F32(vec![0.1, -2.5, 1e-30]),
                    volts_per_code: 1.0,
                    offset_v: 0.0,
                },
                Channel::from_volts("d", ChannelRole::Other, vec![0.1, 1.0 / 3.0, -1e300]),
            ],
            laser_off: true,
        }
    }

    #[test]
    fn round_trip_is_exact_for_every_sample_type() {
        let f = frame();
        let back = frame_from_proto(&frame_to_proto(&f)).unwrap();
        assert_eq!(back, f);
        // And through the encoded bytes.
        let bytes = prost::Message::encode_to_vec(&frame_to_proto(&f));
        let msg: proto::Frame = prost::Message::decode(bytes.as_slice()).unwrap();
        assert_eq!(frame_from_proto(&msg).unwrap(), f);
    }

    #[test]
    fn integer_codes_travel_packed_le() {
        let msg = frame_to_proto(&frame());
        assert_eq!(
            msg.channels[1].samples.as_ref(),
            &[0x00, 0x80, 1, 0, 0xff, 0x7f]
        );
        assert_eq!(msg.channels[1].format, proto::SampleFormat::I16 as i32);
        assert_eq!(msg.channels[4].format, proto::SampleFormat::F64 as i32);
        assert_eq!(msg.channels[4].samples.len(), 24);
    }

    fn err(msg: &proto::Frame) -> ConvertError {
        frame_from_proto(msg).unwrap_err()
    }

    #[test]
    fn validation_names_the_field() {
        let good = frame_to_proto(&frame());

        let mut m = good.clone();
        m.channels[1].samples = Bytes::from_static(&[1, 2, 3]);
        let e = err(&m);
        assert_eq!(e.field(), "channels[1].samples");
        assert!(e.message().contains("multiple of 2"), "{e}");

        let mut m = good.clone();
        m.channels[2].format = 0;
        assert_eq!(err(&m).field(), "channels[2].format");
        m.channels[2].format = 42;
        let e = err(&m);
        assert_eq!(e.field(), "channels[2].format");
        assert!(e.message().contains("42"), "{e}");

        let mut m = good.clone();
        m.channels[3].samples = Bytes::from(
            [0.0f32, f32::NAN, 1.0]
                .iter()
                .flat_map(|x| x.to_le_bytes())
                .collect::<Vec<u8>>(),
        );
        let e = err(&m);
        assert_eq!(e.field(), "channels[3].samples");
        assert!(e.message().contains("index 1"), "{e}");

        let mut m = good.clone();
        m.channels[4].samples = Bytes::from(f64::INFINITY.to_le_bytes().repeat(3));
        assert_eq!(err(&m).field(), "channels[4].samples");

        for dt in [0.0, -1e-9, f64::NAN, f64::INFINITY] {
            let mut m = good.clone();
            m.sample_interval_s = dt;
            assert_eq!(err(&m).field(), "sample_interval_s");
        }

        let mut m = good.clone();
        m.channels[1].samples = Bytes::from_static(&[0, 0, 1, 0]);
        let e = err(&m);
        assert_eq!(e.field(), "channels[1].samples");
        assert!(e.message().contains("expected 3 samples"), "{e}");

        let mut m = good.clone();
        m.channels.clear();
        assert_eq!(err(&m).field(), "channels");

        for vpc in [0.0, f64::NAN] {
            let mut m = good.clone();
            m.channels[0].volts_per_code = vpc;
            assert_eq!(err(&m).field(), "channels[0].volts_per_code");
        }

        let mut m = good.clone();
        m.channels[0].role = 9;
        assert_eq!(err(&m).field(), "channels[0].role");

        let mut m = good.clone();
        m.channels[0].offset_v = f64::NAN;
        assert_eq!(err(&m).field(), "channels[0].offset_v");

        let mut m = good.clone();
        m.trigger_time_s = f64::NAN;
        assert_eq!(err(&m).field(), "trigger_time_s");
    }

    #[test]
    fn zero_scale_on_float_samples_means_volts() {
        let mut m = frame_to_proto(&frame());
        m.channels[3].volts_per_code = 0.0;
        let f = frame_from_proto(&m).unwrap();
        assert_eq!(f.channels[3].volts_per_code, 1.0);
    }
}
