//! Wire contract <-> domain types (development stand-in; the real version
//! comes from the `convert` branch with exactly this API).

use super::proto;
use crate::frame::{Channel, ChannelRole, Frame, Samples};

/// A wire frame that does not make a valid domain frame.
#[derive(Debug, thiserror::Error)]
#[error("{field}: {message}")]
pub struct ConvertError {
    /// Field at fault, e.g. `channels[1].samples`.
    pub field: String,
    /// What was wrong and what was expected.
    pub message: String,
}

fn err(field: impl Into<String>, message: impl Into<String>) -> ConvertError {
    ConvertError {
        field: field.into(),
        message: message.into(),
    }
}

/// Encodes a domain frame for the wire (samples packed little-endian).
pub fn frame_to_proto(frame: &Frame) -> proto::Frame {
    let channels = frame
        .channels
        .iter()
        .map(|c| {
            let (format, bytes): (proto::SampleFormat, Vec<u8>) = match &c.samples {
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
                    proto::SampleFormat::F32,
                    v.iter().flat_map(|&x| (x as f32).to_le_bytes()).collect(),
                ),
            };
            proto::Channel {
                name: c.name.clone(),
                role: match c.role {
                    ChannelRole::Unspecified => proto::ChannelRole::Unspecified,
                    ChannelRole::Start => proto::ChannelRole::Start,
                    ChannelRole::Stop => proto::ChannelRole::Stop,
                    ChannelRole::Other => proto::ChannelRole::Other,
                } as i32,
                format: format as i32,
                samples: bytes.into(),
                volts_per_code: c.volts_per_code,
                offset_v: c.offset_v,
            }
        })
        .collect();
    proto::Frame {
        sensor_id: frame.sensor_id.clone(),
        sequence: frame.sequence,
        trigger_time_s: frame.trigger_time_s,
        sample_interval_s: frame.sample_interval_s,
        first_sample_offset_s: frame.first_sample_offset_s,
        channels,
        laser_off: frame.laser_off,
    }
}

/// Decodes and validates a wire frame.
pub fn frame_from_proto(msg: &proto::Frame) -> Result<Frame, ConvertError> {
    if !(msg.sample_interval_s.is_finite() && msg.sample_interval_s > 0.0) {
        return Err(err(
            "sample_interval_s",
            format!("{} is not a period > 0 s", msg.sample_interval_s),
        ));
    }
    if msg.channels.is_empty() {
        return Err(err("channels", "no channels"));
    }
    let mut channels = Vec::with_capacity(msg.channels.len());
    for (i, c) in msg.channels.iter().enumerate() {
        let b = &c.samples;
        let fmt =
            proto::SampleFormat::try_from(c.format).unwrap_or(proto::SampleFormat::Unspecified);
        let size = match fmt {
            proto::SampleFormat::I8 => 1,
            proto::SampleFormat::I16 => 2,
            proto::SampleFormat::I32 | proto::SampleFormat::F32 => 4,
            proto::SampleFormat::Unspecified => {
                return Err(err(
                    format!("channels[{i}].format"),
                    format!("{} is not a known sample format", c.format),
                ));
            }
        };
        if b.len() % size != 0 {
            return Err(err(
                format!("channels[{i}].samples"),
                format!(
                    "{} bytes is not a multiple of {size} ({})",
                    b.len(),
                    fmt.as_str_name()
                ),
            ));
        }
        let samples = match fmt {
            proto::SampleFormat::I8 => Samples::I8(b.iter().map(|&x| x as i8).collect()),
            proto::SampleFormat::I16 => Samples::I16(
                b.chunks_exact(2)
                    .map(|x| i16::from_le_bytes([x[0], x[1]]))
                    .collect(),
            ),
            proto::SampleFormat::I32 => Samples::I32(
                b.chunks_exact(4)
                    .map(|x| i32::from_le_bytes([x[0], x[1], x[2], x[3]]))
                    .collect(),
            ),
            _ => {
                let v: Vec<f32> = b
                    .chunks_exact(4)
                    .map(|x| f32::from_le_bytes([x[0], x[1], x[2], x[3]]))
                    .collect();
                if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                    return Err(err(
                        format!("channels[{i}].samples[{k}]"),
                        format!("{} is not finite", v[k]),
                    ));
                }
                Samples::F32(v)
            }
        };
        let mut volts_per_code = c.volts_per_code;
        if volts_per_code == 0.0 {
            if samples.is_integer() {
                return Err(err(
                    format!("channels[{i}].volts_per_code"),
                    "0 for integer codes",
                ));
            }
            volts_per_code = 1.0;
        }
        if i > 0 && samples.len() != channels.first().map_or(0, |c: &Channel| c.samples.len()) {
            return Err(err(
                format!("channels[{i}].samples"),
                "length differs from channels[0]",
            ));
        }
        channels.push(Channel {
            name: c.name.clone(),
            role: match proto::ChannelRole::try_from(c.role)
                .unwrap_or(proto::ChannelRole::Unspecified)
            {
                proto::ChannelRole::Unspecified => ChannelRole::Unspecified,
                proto::ChannelRole::Start => ChannelRole::Start,
                proto::ChannelRole::Stop => ChannelRole::Stop,
                proto::ChannelRole::Other => ChannelRole::Other,
            },
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
