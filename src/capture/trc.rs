//! Teledyne LeCroy `.trc` (LECROY_2_3 template).
//!
//! Layout (offsets relative to the `WAVEDESC` marker, which may follow a SCPI
//! block prefix `#9nnnnnnnnn`): 346-byte WAVEDESC, USERTEXT, TRIGTIME array
//! (16 bytes per segment: trigger time, horizontal offset), RIS array,
//! WAVE_ARRAY_1 (i8 or i16 codes), WAVE_ARRAY_2. Byte order from COMM_ORDER
//! (byte 34: 1 = little-endian, 0 = big-endian).
//!
//! `volts = VERTICAL_GAIN * code - VERTICAL_OFFSET`, so a channel gets
//! `volts_per_code = gain`, `offset_v = -offset`. Sample 0 sits at
//! HORIZ_OFFSET after the trigger (per segment: the TRIGTIME offset).
//! The trigger time is the WAVEDESC TRIGGER_TIME stamp read as UTC seconds
//! since the Unix epoch (the scope writes its local clock) plus the segment's
//! TRIGTIME time; an implausible stamp counts as 0, leaving times relative to
//! the first segment. RIS interleaving is not undone (the array is skipped).

use std::path::Path;

use super::CaptureError;
use super::codes::{Codes, encode};
use super::cursor::{Order, View, c_string, decode_codes};
use crate::frame::{Channel, ChannelRole, Frame, channel_key};

const MARKER: &[u8] = b"WAVEDESC";
/// WAVEDESC length of the LECROY_2_3 template.
const DESC_LEN: usize = 346;

/// Position of the WAVEDESC marker: at 0, or after a `#<n><n digits>` SCPI prefix.
pub(crate) fn find_wavedesc(head: &[u8]) -> Option<usize> {
    if head.starts_with(MARKER) {
        return Some(0);
    }
    if head.first() == Some(&b'#')
        && let Some(n) = head.get(1).and_then(|&b| (b as char).to_digit(10))
        && let Some(digits) = head.get(2..2 + n as usize)
        && digits.iter().all(u8::is_ascii_digit)
        && head[2 + n as usize..].starts_with(MARKER)
    {
        return Some(2 + n as usize);
    }
    // Other transfer prefixes (a longer SCPI header such as "DAT1:WF1 #9..."):
    // the marker within the first 64 bytes.
    head[..head.len().min(64)]
        .windows(MARKER.len())
        .position(|w| w == MARKER)
}

/// The f64 nearest the shortest decimal that reads back as `x`.
///
/// The scope stores decimal settings (1e-9 s, 1.24995e-4 V) as binary32;
/// widening the bits would give 9.9999997e-10 s, a 3e-8 relative error that
/// accumulates along long records. The shortest decimal is the value meant.
fn f32_decimal(x: f32) -> f64 {
    if !x.is_finite() {
        return x as f64;
    }
    x.to_string().parse().unwrap_or(x as f64)
}

/// Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's algorithm).
fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146097 + doe - 719468
}

/// Inverse of [`days_from_civil`]: (year, month, day).
fn civil_from_days(z: i64) -> (i64, i64, i64) {
    let z = z + 719468;
    let era = z.div_euclid(146097);
    let doe = z - era * 146097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    (
        if m <= 2 {
            yoe + era * 400 + 1
        } else {
            yoe + era * 400
        },
        m,
        d,
    )
}

/// The 16-byte TRIGGER_TIME stamp as seconds since the Unix epoch, if plausible.
fn stamp_seconds(v: &View, at: usize, order: Order) -> Result<Option<f64>, CaptureError> {
    let seconds = v.f64(at, order, "TRIGGER_TIME seconds")?;
    let minutes = v.u8(at + 8, "TRIGGER_TIME minutes")? as i64;
    let hours = v.u8(at + 9, "TRIGGER_TIME hours")? as i64;
    let days = v.u8(at + 10, "TRIGGER_TIME day")? as i64;
    let months = v.u8(at + 11, "TRIGGER_TIME month")? as i64;
    let year = v.i16(at + 12, order, "TRIGGER_TIME year")? as i64;
    let plausible = (1..=9999).contains(&year)
        && (1..=12).contains(&months)
        && (1..=31).contains(&days)
        && hours < 24
        && minutes < 60
        && seconds.is_finite()
        && seconds.abs() < 1e12;
    Ok(plausible.then(|| {
        (days_from_civil(year, months, days) * 86400 + hours * 3600 + minutes * 60) as f64 + seconds
    }))
}

/// Reads a whole `.trc` file: one frame, or one per segment in sequence mode.
pub(crate) fn read(path: &Path, data: &[u8]) -> Result<Vec<Frame>, CaptureError> {
    let v = View::new(path, data);
    let Some(base) = find_wavedesc(&data[..data.len().min(64)]) else {
        return Err(v.malformed(
            0,
            "\"WAVEDESC\" (optionally after a \"#9\" SCPI block prefix)",
            super::preview(data),
        ));
    };
    v.slice(base, DESC_LEN, "the 346-byte WAVEDESC block")?;
    let template = c_string(v.slice(base + 16, 16, "TEMPLATE_NAME")?);
    if !template.starts_with("LECROY_2_") {
        return Err(v.malformed(
            base + 16,
            "template \"LECROY_2_3\"",
            format!("{template:?}"),
        ));
    }
    let order = match v.array::<2>(base + 34, "COMM_ORDER")? {
        [1, 0] => Order::Little,
        [0, 0] | [0, 1] => Order::Big,
        other => {
            return Err(v.malformed(
                base + 34,
                "COMM_ORDER 0 (big-endian) or 1 (little-endian)",
                format!("bytes {other:02x?}"),
            ));
        }
    };
    let width = match v.u16(base + 32, order, "COMM_TYPE")? {
        0 => 1,
        1 => 2,
        other => {
            return Err(v.malformed(base + 32, "COMM_TYPE 0 (i8) or 1 (i16)", other.to_string()));
        }
    };
    // Block lengths: non-negative, and each block must lie inside the file.
    let len_at = |off: usize, what: &str| -> Result<usize, CaptureError> {
        let n = v.i32(base + off, order, what)?;
        usize::try_from(n)
            .map_err(|_| v.malformed(base + off, format!("{what} >= 0"), n.to_string()))
    };
    let desc_len = len_at(36, "WAVE_DESCRIPTOR length")?;
    if desc_len < DESC_LEN {
        return Err(v.malformed(
            base + 36,
            "WAVE_DESCRIPTOR length >= 346",
            desc_len.to_string(),
        ));
    }
    let user_len = len_at(40, "USER_TEXT length")?;
    let trig_len = len_at(48, "TRIGTIME_ARRAY length")?;
    let ris_len = len_at(52, "RIS_TIME_ARRAY length")?;
    let wave1_len = len_at(60, "WAVE_ARRAY_1 length")?;
    let trig_at = base + desc_len + user_len;
    let wave1_at = trig_at + trig_len + ris_len;
    v.slice(base + desc_len, user_len, "USERTEXT block")?;
    v.slice(trig_at, trig_len, "TRIGTIME array")?;
    v.slice(trig_at + trig_len, ris_len, "RIS_TIME array")?;
    let wave1 = v.slice(wave1_at, wave1_len, "WAVE_ARRAY_1 (samples)")?;

    let count = len_at(116, "WAVE_ARRAY_COUNT")?;
    if count.checked_mul(width) != Some(wave1_len) {
        return Err(v.malformed(
            base + 60,
            format!("WAVE_ARRAY_1 length = WAVE_ARRAY_COUNT ({count}) x {width} bytes"),
            format!("{wave1_len} bytes"),
        ));
    }
    let subarrays = v.i32(base + 144, order, "SUBARRAY_COUNT")?;
    let segments = if subarrays > 1 { subarrays as usize } else { 1 };
    if count % segments != 0 || count == 0 {
        return Err(v.malformed(
            base + 116,
            format!("a non-zero sample count divisible by SUBARRAY_COUNT ({segments})"),
            format!("{count} samples"),
        ));
    }
    if segments > 1 && trig_len < 16 * segments {
        return Err(v.malformed(
            base + 48,
            format!(
                "a TRIGTIME array of 16 x {segments} segments = {} bytes",
                16 * segments
            ),
            format!("{trig_len} bytes"),
        ));
    }
    let gain = f32_decimal(v.f32(base + 156, order, "VERTICAL_GAIN")?);
    if !(gain.is_finite() && gain != 0.0) {
        return Err(v.malformed(
            base + 156,
            "a finite non-zero VERTICAL_GAIN",
            gain.to_string(),
        ));
    }
    let voffset = f32_decimal(v.f32(base + 160, order, "VERTICAL_OFFSET")?);
    if !voffset.is_finite() {
        return Err(v.malformed(base + 160, "a finite VERTICAL_OFFSET", voffset.to_string()));
    }
    let dt = f32_decimal(v.f32(base + 176, order, "HORIZ_INTERVAL")?);
    if !(dt.is_finite() && dt > 0.0) {
        return Err(v.malformed(base + 176, "HORIZ_INTERVAL > 0 s", dt.to_string()));
    }
    let hoffset = v.f64(base + 180, order, "HORIZ_OFFSET")?;
    if !hoffset.is_finite() {
        return Err(v.malformed(base + 180, "a finite HORIZ_OFFSET", hoffset.to_string()));
    }
    let epoch_s = stamp_seconds(&v, base + 296, order)?.unwrap_or(0.0);
    let source = v.u16(base + 344, order, "WAVE_SOURCE")?;
    let label = c_string(v.slice(base + 96, 16, "TRACE_LABEL")?);
    let name = match source {
        0..=3 => format!("C{}", source + 1),
        _ if !label.is_empty() => label,
        _ => format!("WAVE_SOURCE {source}"),
    };

    let per = count / segments;
    let seg_bytes = per * width;
    let mut frames = Vec::with_capacity(segments);
    for k in 0..segments {
        let (t_trig, t_first) = if segments > 1 {
            let at = trig_at + 16 * k;
            let t = v.f64(at, order, "TRIGTIME trigger_time")?;
            let o = v.f64(at + 8, order, "TRIGTIME trigger_offset")?;
            if !(t.is_finite() && o.is_finite()) {
                return Err(v.malformed(
                    at,
                    "finite TRIGTIME entries",
                    format!("{t}, {o} for segment {k}"),
                ));
            }
            (epoch_s + t, o)
        } else {
            (epoch_s, hoffset)
        };
        let raw = &wave1[k * seg_bytes..(k + 1) * seg_bytes];
        frames.push(Frame {
            sensor_id: String::new(),
            sequence: k as u64,
            trigger_time_s: t_trig,
            sample_interval_s: dt,
            first_sample_offset_s: t_first,
            channels: vec![Channel {
                name: name.clone(),
                role: ChannelRole::Unspecified,
                samples: decode_codes(raw, width, true, order),
                volts_per_code: gain,
                offset_v: -voffset,
            }],
            laser_off: false,
        });
    }
    Ok(frames)
}

/// Little-endian bytes reordered for `order`.
fn ordered<const N: usize>(mut le: [u8; N], order: Order) -> [u8; N] {
    if order == Order::Big {
        le.reverse();
    }
    le
}

fn put(buf: &mut [u8], at: usize, bytes: &[u8]) {
    buf[at..at + bytes.len()].copy_from_slice(bytes);
}

fn put_str(buf: &mut [u8], at: usize, len: usize, s: &str) {
    let b = s.as_bytes();
    let n = b.len().min(len - 1);
    put(buf, at, &b[..n]);
}

/// Writes one channel of `frames` as a LECROY_2_3 little-endian `.trc`
/// (no SCPI prefix). One frame: a single sweep; more: sequence mode with a
/// TRIGTIME entry per frame (trigger time relative to the first frame, and
/// the frame's own first-sample offset). i8 codes stay 8-bit, i16-range
/// codes with one shared scale stay exact; anything else is quantised to i16
/// over the data's range (error <= half a code). Scale, offset and sampling
/// period are stored as binary32, as the format does. The channel name is
/// kept in WAVE_SOURCE when it is C1..C4 (any vendor spelling), else in
/// TRACE_LABEL (16 bytes).
pub fn write_trc(path: &Path, frames: &[Frame], channel: &str) -> Result<(), CaptureError> {
    let out = encode_trc(path, frames, channel, Order::Little)?;
    std::fs::write(path, out).map_err(|e| CaptureError::Io {
        path: path.to_path_buf(),
        offset: 0,
        action: "write".into(),
        cause: e,
    })
}

/// The bytes of a `.trc` in the given byte order (big-endian only for tests
/// of the reader: scopes and tofwave write little-endian).
fn encode_trc(
    path: &Path,
    frames: &[Frame],
    channel: &str,
    order: Order,
) -> Result<Vec<u8>, CaptureError> {
    let invalid = |expected: &str, found: String| CaptureError::InvalidFrame {
        path: path.to_path_buf(),
        expected: expected.to_string(),
        found,
    };
    let Some(first) = frames.first() else {
        return Err(invalid("at least one frame", "none".into()));
    };
    let mut chans = Vec::with_capacity(frames.len());
    for (k, f) in frames.iter().enumerate() {
        let c = f.channel(channel).ok_or_else(|| {
            invalid(
                &format!("a channel named {channel:?}"),
                format!("channels {:?} in frame {k}", f.channel_names()),
            )
        })?;
        if c.samples.len() != first.len() || c.samples.is_empty() {
            return Err(invalid(
                &format!("{} samples in every frame (and > 0)", first.len()),
                format!("{} in frame {k}", c.samples.len()),
            ));
        }
        if f.sample_interval_s != first.sample_interval_s {
            return Err(invalid(
                &format!(
                    "one sample interval ({} s) for all frames",
                    first.sample_interval_s
                ),
                format!("{} s in frame {k}", f.sample_interval_s),
            ));
        }
        if !(f.sample_interval_s.is_finite() && f.sample_interval_s > 0.0) {
            return Err(invalid(
                "a sample interval > 0",
                f.sample_interval_s.to_string(),
            ));
        }
        chans.push(c);
    }
    let enc = encode(path, &chans, true, true)?;
    let (width, payload): (usize, Vec<u8>) = match &enc.codes {
        Codes::I8(v) => (1, v.iter().flatten().map(|&x| x as u8).collect()),
        Codes::I16(v) => (
            2,
            v.iter()
                .flatten()
                .flat_map(|x| ordered(x.to_le_bytes(), order))
                .collect(),
        ),
    };
    let n = frames.len();
    let trig_len = if n > 1 { 16 * n } else { 0 };
    let mut d = vec![0u8; DESC_LEN];
    put(&mut d, 0, MARKER);
    put(&mut d, 16, b"LECROY_2_3");
    put(
        &mut d,
        32,
        &ordered(((width - 1) as u16).to_le_bytes(), order),
    );
    put(
        &mut d,
        34,
        &ordered(u16::from(order == Order::Little).to_le_bytes(), order),
    );
    put(&mut d, 36, &ordered((DESC_LEN as i32).to_le_bytes(), order));
    put(&mut d, 48, &ordered((trig_len as i32).to_le_bytes(), order));
    let too_big = || {
        invalid(
            "at most 2 GiB of samples",
            format!("{} bytes", payload.len()),
        )
    };
    put(
        &mut d,
        60,
        &ordered(
            i32::try_from(payload.len())
                .map_err(|_| too_big())?
                .to_le_bytes(),
            order,
        ),
    );
    put_str(&mut d, 76, 16, "TOFWAVE");
    let key = channel_key(&chans[0].name);
    let source: u16 = match key.as_str() {
        "1" => 0,
        "2" => 1,
        "3" => 2,
        "4" => 3,
        _ => 4,
    };
    if source == 4 {
        put_str(&mut d, 96, 16, &chans[0].name);
    }
    let per = first.len();
    put(
        &mut d,
        116,
        &ordered(((per * n) as i32).to_le_bytes(), order),
    );
    put(&mut d, 120, &ordered((per as i32).to_le_bytes(), order));
    put(&mut d, 128, &ordered((per as i32 - 1).to_le_bytes(), order));
    put(&mut d, 136, &ordered(1i32.to_le_bytes(), order));
    put(&mut d, 144, &ordered((n as i32).to_le_bytes(), order));
    put(&mut d, 148, &ordered(1i32.to_le_bytes(), order));
    put(
        &mut d,
        156,
        &ordered((enc.volts_per_code as f32).to_le_bytes(), order),
    );
    put(
        &mut d,
        160,
        &ordered((-enc.offset_v as f32).to_le_bytes(), order),
    );
    let (lo, hi) = if width == 1 {
        (-128.0f32, 127.0f32)
    } else {
        (-32768.0, 32767.0)
    };
    put(&mut d, 164, &ordered(hi.to_le_bytes(), order));
    put(&mut d, 168, &ordered(lo.to_le_bytes(), order));
    put(
        &mut d,
        172,
        &ordered(((8 * width) as i16).to_le_bytes(), order),
    );
    put(
        &mut d,
        174,
        &ordered((n.min(i16::MAX as usize) as i16).to_le_bytes(), order),
    );
    put(
        &mut d,
        176,
        &ordered((first.sample_interval_s as f32).to_le_bytes(), order),
    );
    put(
        &mut d,
        180,
        &ordered(first.first_sample_offset_s.to_le_bytes(), order),
    );
    put_str(&mut d, 196, 48, "V");
    put_str(&mut d, 244, 48, "S");
    // TRIGGER_TIME: the first frame's trigger time as a UTC date when it is
    // a plausible epoch time; otherwise 1970-01-01 00:00 plus raw seconds.
    let t0 = first.trigger_time_s;
    let (secs, minute, hour, day, month, year) =
        if t0.is_finite() && (0.0..253_402_300_800.0).contains(&t0) {
            let days = (t0 / 86400.0).floor() as i64;
            let (y, m, dd) = civil_from_days(days);
            let mut rem = t0 - (days * 86400) as f64;
            let hour = ((rem / 3600.0).floor() as i64).clamp(0, 23);
            rem -= (hour * 3600) as f64;
            let minute = ((rem / 60.0).floor() as i64).clamp(0, 59);
            rem -= (minute * 60) as f64;
            (rem, minute, hour, dd, m, y)
        } else {
            (if t0.is_finite() { t0 } else { 0.0 }, 0, 0, 1, 1, 1970)
        };
    put(&mut d, 296, &ordered(secs.to_le_bytes(), order));
    put(
        &mut d,
        304,
        &[minute as u8, hour as u8, day as u8, month as u8],
    );
    put(&mut d, 308, &ordered((year as i16).to_le_bytes(), order));
    put(&mut d, 322, &ordered(1i16.to_le_bytes(), order));
    put(&mut d, 328, &ordered(1f32.to_le_bytes(), order));
    put(&mut d, 336, &ordered(1f32.to_le_bytes(), order));
    put(&mut d, 344, &ordered(source.to_le_bytes(), order));
    let mut out = d;
    if n > 1 {
        for f in frames {
            out.extend_from_slice(&ordered((f.trigger_time_s - t0).to_le_bytes(), order));
            out.extend_from_slice(&ordered(f.first_sample_offset_s.to_le_bytes(), order));
        }
    }
    out.extend_from_slice(&payload);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn big_endian_files_read_like_little_endian_ones() {
        use crate::frame::Samples;
        let frames: Vec<Frame> = (0..3)
            .map(|k| Frame {
                sensor_id: String::new(),
                sequence: k,
                trigger_time_s: 1.6e9 + k as f64 * 0.01,
                sample_interval_s: 2e-9,
                first_sample_offset_s: -1e-7 + k as f64 * 1e-11,
                channels: vec![Channel {
                    name: "C3".into(),
                    role: ChannelRole::Unspecified,
                    samples: Samples::I16((0..64).map(|i| i * 300 - 9000 + k as i16).collect()),
                    volts_per_code: 0.001,
                    offset_v: 0.25,
                }],
                laser_off: false,
            })
            .collect();
        let p = Path::new("be.trc");
        let le = encode_trc(p, &frames, "C3", Order::Little).unwrap();
        let be = encode_trc(p, &frames, "C3", Order::Big).unwrap();
        assert_ne!(le, be);
        assert_eq!(&be[34..36], &[0, 0]);
        let a = read(p, &le).unwrap();
        let b = read(p, &be).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.len(), 3);
        assert_eq!(a[2].channels[0].samples, frames[2].channels[0].samples);
        assert_eq!(a[2].channels[0].name, "C3");
        // i8 codes: byte order does not matter but the header still does.
        let mut f8 = frames[0].clone();
        f8.channels[0].samples = Samples::I8(vec![-5, 0, 5, 127]);
        let b = read(p, &encode_trc(p, &[f8.clone()], "C3", Order::Big).unwrap()).unwrap();
        assert_eq!(b[0].channels[0].samples, f8.channels[0].samples);
        assert_eq!(b[0].first_sample_offset_s, f8.first_sample_offset_s);
    }

    #[test]
    fn civil_dates_round_trip() {
        assert_eq!(days_from_civil(1970, 1, 1), 0);
        assert_eq!(days_from_civil(2022, 11, 9), 19305);
        for z in [-1000, 0, 1, 59, 60, 365, 19305, 2_932_896] {
            let (y, m, d) = civil_from_days(z);
            assert_eq!(days_from_civil(y, m, d), z);
        }
    }

    #[test]
    fn binary32_settings_read_as_their_decimal() {
        assert_eq!(f32_decimal(1e-9f32), 1e-9);
        assert_eq!(f32_decimal(1.24995e-4f32), 1.24995e-4);
        assert_eq!(f32_decimal(-1.0), -1.0);
        assert_eq!(f32_decimal(0.1f32) as f32, 0.1f32);
    }

    #[test]
    fn scpi_prefix_is_found() {
        assert_eq!(find_wavedesc(b"#9000001350WAVEDESC"), Some(11));
        assert_eq!(find_wavedesc(b"WAVEDESC"), Some(0));
        assert_eq!(find_wavedesc(b"#9000001350WAVEDES"), None);
        assert_eq!(find_wavedesc(b"C2:WF? ALL,#9000001350WAVEDESC"), Some(22));
        assert_eq!(find_wavedesc(b"#x"), None);
        assert_eq!(find_wavedesc(b"#"), None);
    }
}
