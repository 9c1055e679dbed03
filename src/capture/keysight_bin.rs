//! Keysight/Agilent InfiniiVision `.bin` (`AG01`, `AG03`, `AG10`).
//!
//! File header `"AG" + 2 version digits`, file size (u32; u64 for AG03) and
//! the waveform count; per waveform a header (usually 140 bytes: points,
//! x increment/origin, label, time tag, segment index) and its buffers, each
//! a data header (type, bytes per point, size) plus data.
//!
//! Waveforms become channels; waveforms with different segment indices
//! (segmented memory) become separate frames, in order of appearance, each
//! with its time tag as trigger time. Per waveform the first analog buffer
//! is used (normal float32, else maximum, else minimum float32; 1-, 2- or
//! 4-byte integer "normal" buffers are kept as codes with unit scale, since
//! the file carries no scale for them); logic/digital waveforms are skipped.

use std::path::Path;

use super::CaptureError;
use super::cursor::{Order, View, c_string};
use crate::frame::{Channel, ChannelRole, Frame, Samples};

const WFM_HEADER_MIN: usize = 140;

/// A waveform read from the file, before grouping into frames.
struct Waveform {
    offset: usize,
    segment: u32,
    dt: f64,
    x_origin: f64,
    time_tag: f64,
    channel: Channel,
}

/// Reads a whole `.bin` file.
pub(crate) fn read(path: &Path, data: &[u8]) -> Result<Vec<Frame>, CaptureError> {
    let v = View::new(path, data);
    let le = Order::Little;
    let magic = v.slice(0, 4, "the \"AGnn\" file header")?;
    if &magic[..2] != b"AG" || !magic[2].is_ascii_digit() || !magic[3].is_ascii_digit() {
        return Err(v.malformed(
            0,
            "\"AG\" + 2 version digits (AG01, AG03, AG10)",
            super::preview(data),
        ));
    }
    let version = (magic[2] - b'0') * 10 + (magic[3] - b'0');
    let wide = version == 3;
    let (file_size, n_waveforms, mut pos) = if wide {
        (
            v.u64(4, le, "file size")?,
            v.u32(12, le, "waveform count")?,
            16,
        )
    } else {
        (
            v.u32(4, le, "file size")? as u64,
            v.u32(8, le, "waveform count")?,
            12,
        )
    };
    if file_size > data.len() as u64 {
        return Err(CaptureError::Truncated {
            path: path.to_path_buf(),
            offset: 0,
            expected: "the file size declared at byte 4".into(),
            needed: file_size,
            available: data.len() as u64,
        });
    }
    if n_waveforms == 0 {
        return Err(v.malformed(if wide { 12 } else { 8 }, "at least one waveform", "0"));
    }
    let mut waves = Vec::new();
    for w in 0..n_waveforms as usize {
        let at = pos;
        let header_size = v.u32(at, le, "waveform header size")? as usize;
        if header_size < WFM_HEADER_MIN {
            return Err(v.malformed(
                at,
                "a waveform header of >= 140 bytes",
                format!("{header_size} bytes"),
            ));
        }
        v.slice(at, header_size, "waveform header")?;
        let wave_type = v.u32(at + 4, le, "waveform type")?;
        let n_buffers = v.u32(at + 8, le, "buffer count")?;
        let n_pts = v.u32(at + 12, le, "point count")? as usize;
        let dt = v.f64(at + 32, le, "x increment")?;
        let x_origin = v.f64(at + 40, le, "x origin")?;
        let label = c_string(v.slice(at + 112, 16, "waveform label")?);
        let time_tag = v.f64(at + 128, le, "time tag")?;
        let segment = v.u32(at + 136, le, "segment index")?;
        pos = at + header_size;
        // (type, bytes per point, data offset, data length) of every buffer.
        let mut buffers = Vec::new();
        for _ in 0..n_buffers {
            let dh = pos;
            let dh_size = v.u32(dh, le, "data header size")? as usize;
            let min = if wide { 16 } else { 12 };
            if dh_size < min {
                return Err(v.malformed(
                    dh,
                    format!("a data header of >= {min} bytes"),
                    format!("{dh_size} bytes"),
                ));
            }
            v.slice(dh, dh_size, "data header")?;
            let btype = v.u16(dh + 4, le, "buffer type")?;
            let bpp = v.u16(dh + 6, le, "bytes per point")? as usize;
            let size = if wide {
                v.u64(dh + 8, le, "buffer size")?
            } else {
                v.u32(dh + 8, le, "buffer size")? as u64
            };
            let size = usize::try_from(size).map_err(|_| {
                v.malformed(dh + 8, "a buffer size that fits memory", size.to_string())
            })?;
            let start = dh + dh_size;
            v.slice(start, size, "waveform data buffer")?;
            buffers.push((btype, bpp, start, size, dh));
            pos = start + size;
        }
        if wave_type == 6 {
            continue; // logic waveform: nothing analog to process
        }
        let pick = [1u16, 2, 3]
            .iter()
            .find_map(|t| buffers.iter().find(|b| b.0 == *t));
        let Some(&(btype, bpp, start, size, dh)) = pick else {
            continue;
        };
        if size % bpp.max(1) != 0 || bpp == 0 {
            return Err(v.malformed(
                dh + 6,
                format!("a buffer size ({size}) that is a multiple of bytes per point"),
                bpp.to_string(),
            ));
        }
        let n = size / bpp;
        if n != n_pts {
            return Err(v.malformed(
                dh + 8,
                format!(
                    "{n_pts} points x {bpp} bytes = {} bytes as the waveform header says",
                    n_pts.saturating_mul(bpp)
                ),
                format!("{size} bytes"),
            ));
        }
        if n == 0 {
            return Err(v.malformed(at + 12, "at least one point", "0"));
        }
        let raw = &data[start..start + size];
        let samples = match (btype, bpp) {
            (_, 4) => Samples::F32(
                raw.chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
            ),
            (1, 1) => Samples::I8(raw.iter().map(|&b| b as i8).collect()),
            (1, 2) => Samples::I16(
                raw.chunks_exact(2)
                    .map(|c| i16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            ),
            _ => {
                return Err(v.malformed(
                    dh + 6,
                    format!("4 bytes per point for buffer type {btype}"),
                    bpp.to_string(),
                ));
            }
        };
        if let Samples::F32(s) = &samples
            && let Some(i) = s.iter().position(|x| !x.is_finite())
        {
            return Err(v.malformed(start + 4 * i, "finite float32 samples", s[i].to_string()));
        }
        if !(dt.is_finite() && dt > 0.0) {
            return Err(v.malformed(at + 32, "x increment > 0 s", dt.to_string()));
        }
        if !(x_origin.is_finite() && time_tag.is_finite()) {
            return Err(v.malformed(
                at + 40,
                "finite x origin and time tag",
                format!("{x_origin}, {time_tag}"),
            ));
        }
        let name = if label.is_empty() {
            format!("CH{}", w + 1)
        } else {
            label
        };
        waves.push(Waveform {
            offset: at,
            segment,
            dt,
            x_origin,
            time_tag,
            channel: Channel {
                name,
                role: ChannelRole::Unspecified,
                samples,
                volts_per_code: 1.0,
                offset_v: 0.0,
            },
        });
    }
    if waves.is_empty() {
        return Err(v.malformed(
            12,
            "at least one analog waveform",
            "only logic/unknown buffers",
        ));
    }
    // Group by segment index, in order of first appearance.
    // (A map from segment to frame: a linear search per waveform is quadratic
    // in the waveform count, which the file controls.)
    let mut frames: Vec<(u32, Frame)> = Vec::new();
    let mut by_segment: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
    for w in waves {
        match by_segment.get(&w.segment).map(|&i| &mut frames[i]) {
            Some((_, f)) => {
                if w.channel.samples.len() != f.len() || w.dt != f.sample_interval_s {
                    return Err(v.malformed(
                        w.offset,
                        format!(
                            "{} points at {} s like the segment's first waveform",
                            f.len(),
                            f.sample_interval_s
                        ),
                        format!("{} points at {} s", w.channel.samples.len(), w.dt),
                    ));
                }
                f.channels.push(w.channel);
            }
            None => {
                by_segment.insert(w.segment, frames.len());
                frames.push((
                    w.segment,
                    Frame {
                        sensor_id: String::new(),
                        sequence: 0,
                        trigger_time_s: w.time_tag,
                        sample_interval_s: w.dt,
                        first_sample_offset_s: w.x_origin,
                        channels: vec![w.channel],
                        laser_off: false,
                    },
                ));
            }
        }
    }
    Ok(frames.into_iter().map(|(_, f)| f).collect())
}

/// Writes `frame` as an AG10 `.bin`: one waveform per channel, float32 volts
/// (exact for f32 samples in volts; otherwise rounded to binary32), the
/// trigger time as time tag, channel names as labels (16 bytes).
pub fn write_keysight_bin(path: &Path, frame: &Frame) -> Result<(), CaptureError> {
    let invalid = |expected: &str, found: String| CaptureError::InvalidFrame {
        path: path.to_path_buf(),
        expected: expected.to_string(),
        found,
    };
    if frame.channels.is_empty() || frame.is_empty() {
        return Err(invalid(
            "at least one channel with samples",
            format!("{} channels", frame.channels.len()),
        ));
    }
    let mut out = Vec::new();
    out.extend_from_slice(b"AG10");
    out.extend_from_slice(&0u32.to_le_bytes()); // file size, patched below
    out.extend_from_slice(&(frame.channels.len() as u32).to_le_bytes());
    let n = frame.len();
    for c in &frame.channels {
        if c.samples.len() != n {
            return Err(invalid(
                &format!("{n} samples in every channel"),
                format!("{} in {}", c.samples.len(), c.name),
            ));
        }
        let volts: Vec<f32> = c.volts().iter().map(|&x| x as f32).collect();
        if let Some(i) = volts.iter().position(|x| !x.is_finite()) {
            return Err(invalid(
                "finite samples within binary32 range",
                format!("{} at index {i} of {}", volts[i], c.name),
            ));
        }
        let mut h = vec![0u8; WFM_HEADER_MIN];
        h[0..4].copy_from_slice(&(WFM_HEADER_MIN as u32).to_le_bytes());
        h[4..8].copy_from_slice(&1u32.to_le_bytes());
        h[8..12].copy_from_slice(&1u32.to_le_bytes());
        h[12..16].copy_from_slice(&(n as u32).to_le_bytes());
        h[16..20].copy_from_slice(&1u32.to_le_bytes());
        h[20..24].copy_from_slice(&((n as f64 * frame.sample_interval_s) as f32).to_le_bytes());
        h[24..32].copy_from_slice(&frame.first_sample_offset_s.to_le_bytes());
        h[32..40].copy_from_slice(&frame.sample_interval_s.to_le_bytes());
        h[40..48].copy_from_slice(&frame.first_sample_offset_s.to_le_bytes());
        h[48..52].copy_from_slice(&2u32.to_le_bytes());
        h[52..56].copy_from_slice(&1u32.to_le_bytes());
        h[88..95].copy_from_slice(b"TOFWAVE");
        let label = c.name.as_bytes();
        let k = label.len().min(15);
        h[112..112 + k].copy_from_slice(&label[..k]);
        h[128..136].copy_from_slice(&frame.trigger_time_s.to_le_bytes());
        out.extend_from_slice(&h);
        out.extend_from_slice(&12u32.to_le_bytes());
        out.extend_from_slice(&1u16.to_le_bytes());
        out.extend_from_slice(&4u16.to_le_bytes());
        let size = u32::try_from(4 * n)
            .map_err(|_| invalid("at most 4 GiB per channel", format!("{n} samples")))?;
        out.extend_from_slice(&size.to_le_bytes());
        out.extend(volts.iter().flat_map(|x| x.to_le_bytes()));
    }
    let total = u32::try_from(out.len())
        .map_err(|_| invalid("a file under 4 GiB", format!("{} bytes", out.len())))?;
    out[4..8].copy_from_slice(&total.to_le_bytes());
    std::fs::write(path, out).map_err(|e| CaptureError::Io {
        path: path.to_path_buf(),
        offset: 0,
        action: "write".into(),
        cause: e,
    })
}
