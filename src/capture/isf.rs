//! Tektronix internal save format (`.isf`).
//!
//! An ASCII header of `;`-separated `KEY value` pairs (`:WFMPRE:BYT_NR 2;...`,
//! long or short key forms, any order), then `:CURVE #<n><len>` and `len`
//! bytes of codes. `volts = YZERO + YMULT * (code - YOFF)` and
//! `t_i = XZERO + XINCR * (i - PT_OFF)`. The channel name is the first
//! comma-separated part of WFID (`"Ch1, DC coupling, ..."` -> `Ch1`).
//! Envelope (`PT_FMT ENV`) and ASCII-encoded curves are refused with an error.

use std::collections::HashMap;
use std::path::Path;

use super::CaptureError;
use super::codes::{Codes, encode};
use super::cursor::{Order, View, decode_codes};
use crate::frame::{Channel, ChannelRole, Frame};

/// Canonical header keys and the shortest abbreviation Tektronix accepts.
const KEYS: &[(&str, usize)] = &[
    ("BYT_NR", 5),
    ("BIT_NR", 5),
    ("ENCDG", 3),
    ("BN_FMT", 4),
    ("BYT_OR", 5),
    ("WFID", 3),
    ("NR_PT", 4),
    ("PT_FMT", 4),
    ("XUNIT", 3),
    ("XINCR", 3),
    ("XZERO", 3),
    ("PT_OFF", 4),
    ("YUNIT", 3),
    ("YMULT", 3),
    ("YOFF", 3),
    ("YZERO", 3),
    ("CURVE", 4),
];

fn canonical(key: &str) -> Option<&'static str> {
    let key = key.to_ascii_uppercase();
    KEYS.iter()
        .find(|(k, min)| key.len() >= *min && k.starts_with(key.as_str()))
        .map(|(k, _)| *k)
}

/// True when `head` looks like an ISF header.
pub(crate) fn looks_like_isf(head: &[u8]) -> bool {
    let end = head.iter().position(|&b| b == b'#').unwrap_or(head.len());
    let text = String::from_utf8_lossy(&head[..end]).to_ascii_uppercase();
    text.starts_with(":WFMP")
        || text.starts_with("WFMP")
        || text.starts_with("BYT_N")
        || text.starts_with(":BYT_N")
}

/// Index of the first `#` outside double quotes.
fn find_hash(data: &[u8]) -> Option<usize> {
    let mut quoted = false;
    for (i, &b) in data.iter().enumerate() {
        match b {
            b'"' => quoted = !quoted,
            b'#' if !quoted => return Some(i),
            _ => {}
        }
    }
    None
}

/// Header values by canonical key, with the byte offset of each pair.
fn parse_header(header: &[u8]) -> HashMap<&'static str, (String, usize)> {
    let mut out = HashMap::new();
    let mut start = 0;
    let mut quoted = false;
    for i in 0..=header.len() {
        let end = i == header.len();
        if !end && header[i] == b'"' {
            quoted = !quoted;
        }
        if end || (header[i] == b';' && !quoted) {
            let token = String::from_utf8_lossy(&header[start..i]);
            let token = token.trim();
            let (path, value) = token.split_once(char::is_whitespace).unwrap_or((token, ""));
            let key = path.rsplit(':').next().unwrap_or("");
            if let Some(k) = canonical(key) {
                out.insert(k, (value.trim().to_string(), start));
            }
            start = i + 1;
        }
    }
    out
}

/// Reads a whole `.isf` file (one frame, one channel).
pub(crate) fn read(path: &Path, data: &[u8]) -> Result<Vec<Frame>, CaptureError> {
    let v = View::new(path, data);
    let Some(hash) = find_hash(data) else {
        return Err(v.malformed(
            data.len(),
            "a header ending in \":CURVE #<n><length>\"",
            "no '#' before the end of the file",
        ));
    };
    let header = parse_header(&data[..hash]);
    if header.is_empty() {
        return Err(v.malformed(
            0,
            "an ISF header (\":WFMPRE:BYT_NR ...;\")",
            super::preview(data),
        ));
    }
    let text = |k: &str| {
        header
            .get(k)
            .map(|(s, o)| (s.trim_matches('"').trim().to_ascii_uppercase(), *o))
    };
    let number = |k: &str, default: Option<f64>| -> Result<f64, CaptureError> {
        match header.get(k) {
            Some((s, o)) => s
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| v.malformed(*o, format!("a number for {k}"), format!("{s:?}"))),
            None => default
                .ok_or_else(|| v.malformed(hash, format!("a {k} entry in the header"), "none")),
        }
    };
    if let Some((enc, o)) = text("ENCDG")
        && !enc.starts_with("BIN")
    {
        return Err(v.malformed(o, "ENCDG BIN (binary curve)", enc));
    }
    if let Some((fmt, o)) = text("PT_FMT")
        && fmt != "Y"
    {
        return Err(v.malformed(o, "PT_FMT Y (envelope curves are not supported)", fmt));
    }
    let width = number("BYT_NR", None)?;
    if width != 1.0 && width != 2.0 {
        let o = header.get("BYT_NR").map_or(0, |x| x.1);
        return Err(v.malformed(o, "BYT_NR 1 or 2", width.to_string()));
    }
    let width = width as usize;
    let signed = match text("BN_FMT") {
        None => true,
        Some((f, _)) if f == "RI" => true,
        Some((f, _)) if f == "RP" => false,
        Some((f, o)) => return Err(v.malformed(o, "BN_FMT RI or RP", f)),
    };
    let order = match text("BYT_OR") {
        None => Order::Big,
        Some((f, _)) if f == "MSB" => Order::Big,
        Some((f, _)) if f == "LSB" => Order::Little,
        Some((f, o)) => return Err(v.malformed(o, "BYT_OR MSB or LSB", f)),
    };
    let ymult = number("YMULT", None)?;
    if ymult == 0.0 {
        return Err(v.malformed(header["YMULT"].1, "a non-zero YMULT", "0"));
    }
    let yoff = number("YOFF", Some(0.0))?;
    let yzero = number("YZERO", Some(0.0))?;
    let xincr = number("XINCR", None)?;
    if xincr <= 0.0 {
        return Err(v.malformed(header["XINCR"].1, "XINCR > 0 s", xincr.to_string()));
    }
    let xzero = number("XZERO", Some(0.0))?;
    let pt_off = number("PT_OFF", Some(0.0))?;

    // SCPI definite-length block: '#', digit count n, n digits of length.
    let n_digits = v.u8(hash + 1, "the digit count after '#'")?;
    let n_digits = (n_digits as char).to_digit(10).ok_or_else(|| {
        v.malformed(
            hash + 1,
            "a digit 0-9 after '#'",
            super::preview(&[n_digits]),
        )
    })? as usize;
    let (start, len) = if n_digits == 0 {
        // Indefinite block: to the end, without a final newline.
        let start = hash + 2;
        let mut end = data.len();
        if data.last() == Some(&b'\n') {
            end -= 1;
        }
        (start, end.saturating_sub(start))
    } else {
        let digits = v.slice(hash + 2, n_digits, "the curve length digits")?;
        let len = std::str::from_utf8(digits)
            .ok()
            .filter(|s| s.bytes().all(|b| b.is_ascii_digit()))
            .and_then(|s| s.parse::<usize>().ok())
            .ok_or_else(|| {
                v.malformed(
                    hash + 2,
                    format!("{n_digits} ASCII digits of curve length"),
                    super::preview(digits),
                )
            })?;
        (hash + 2 + n_digits, len)
    };
    if let Some((s, o)) = header.get("NR_PT") {
        let nr_pt: usize = s
            .parse()
            .map_err(|_| v.malformed(*o, "an integer NR_PT", format!("{s:?}")))?;
        if nr_pt.checked_mul(width) != Some(len) {
            return Err(v.malformed(
                hash,
                format!("a curve of NR_PT ({nr_pt}) x BYT_NR ({width}) bytes"),
                format!("{len} bytes"),
            ));
        }
    }
    if len % width != 0 || len == 0 {
        return Err(v.malformed(
            hash,
            format!("a non-empty curve of whole {width}-byte samples"),
            format!("{len} bytes"),
        ));
    }
    let raw = v.slice(start, len, "the curve data")?;
    let name = header
        .get("WFID")
        .map(|(s, _)| {
            s.trim_matches('"')
                .split(',')
                .next()
                .unwrap_or("")
                .trim()
                .to_string()
        })
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unnamed".to_string());
    // Finite header numbers can still combine to infinity (XINCR 1e300 x PT_OFF 1e300).
    let first_sample_offset_s = xzero - xincr * pt_off;
    if !first_sample_offset_s.is_finite() {
        let o = header.get("PT_OFF").map_or(hash, |x| x.1);
        return Err(v.malformed(
            o,
            "XZERO - XINCR x PT_OFF finite (the time of sample 0)",
            format!("{xzero:e} - {xincr:e} x {pt_off:e}"),
        ));
    }
    let offset_v = yzero - ymult * yoff;
    if !offset_v.is_finite() {
        let o = header.get("YOFF").map_or(hash, |x| x.1);
        return Err(v.malformed(
            o,
            "YZERO - YMULT x YOFF finite (the volts of code 0)",
            format!("{yzero:e} - {ymult:e} x {yoff:e}"),
        ));
    }
    Ok(vec![Frame {
        sensor_id: String::new(),
        sequence: 0,
        trigger_time_s: 0.0,
        sample_interval_s: xincr,
        first_sample_offset_s,
        channels: vec![Channel {
            name,
            role: ChannelRole::Unspecified,
            samples: decode_codes(raw, width, signed, order),
            volts_per_code: ymult,
            offset_v,
        }],
        laser_off: false,
    }])
}

/// Writes one channel of `frame` as an `.isf` (big-endian, signed codes).
/// i8 codes stay 8-bit and i16-range codes stay exact; anything else is
/// quantised to i16 over its range (error <= half a code). Scale and times
/// are written with full f64 precision. The channel name goes into WFID
/// (commas and quotes replaced, since they delimit WFID).
pub fn write_isf(path: &Path, frame: &Frame, channel: &str) -> Result<(), CaptureError> {
    let c = frame
        .channel(channel)
        .ok_or_else(|| CaptureError::InvalidFrame {
            path: path.to_path_buf(),
            expected: format!("a channel named {channel:?}"),
            found: format!("channels {:?}", frame.channel_names()),
        })?;
    if c.samples.is_empty()
        || !(frame.sample_interval_s.is_finite() && frame.sample_interval_s > 0.0)
    {
        return Err(CaptureError::InvalidFrame {
            path: path.to_path_buf(),
            expected: "samples and a sample interval > 0".into(),
            found: format!(
                "{} samples at {} s",
                c.samples.len(),
                frame.sample_interval_s
            ),
        });
    }
    let enc = encode(path, &[c], true, false)?;
    let (width, curve): (usize, Vec<u8>) = match &enc.codes {
        Codes::I8(v) => (1, v[0].iter().map(|&x| x as u8).collect()),
        Codes::I16(v) => (2, v[0].iter().flat_map(|x| x.to_be_bytes()).collect()),
    };
    let name = c.name.replace([',', '"', ';', '#'], "_");
    let len = curve.len().to_string();
    let header = format!(
        ":WFMPRE:BYT_NR {width};BIT_NR {bits};ENCDG BIN;BN_FMT RI;BYT_OR MSB;\
         WFID \"{name}, DC coupling, written by tofwave\";NR_PT {n};PT_FMT Y;XUNIT \"s\";\
         XINCR {dt:e};XZERO {x0:e};PT_OFF 0;YUNIT \"V\";YMULT {ym:e};YOFF 0.0E+0;YZERO {yz:e};\
         :CURVE #{digits}{len}",
        bits = 8 * width,
        n = curve.len() / width,
        dt = frame.sample_interval_s,
        x0 = frame.first_sample_offset_s,
        ym = enc.volts_per_code,
        yz = enc.offset_v,
        digits = len.len(),
    );
    let mut out = header.into_bytes();
    out.extend_from_slice(&curve);
    out.push(b'\n');
    std::fs::write(path, out).map_err(|e| CaptureError::Io {
        path: path.to_path_buf(),
        offset: 0,
        action: "write".into(),
        cause: e,
    })
}
