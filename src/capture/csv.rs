//! CSV dialects: Tektronix, Rigol, Keysight and generic.
//!
//! Values become `Samples::F64` in volts (`volts_per_code` 1, offset 0). The
//! time axis must be uniform: the sample interval is the mean spacing of the
//! time column, and a step that deviates from it by more than 1 % is refused
//! with the line it ends on (an unevenly sampled file would silently bend
//! every time estimate). Time is relative to the trigger at 0; the trigger
//! time of the frame is 0 (CSV exports carry no usable absolute time).
//!
//! - Tektronix: `key,value` header lines (Record Length, Sample Interval,
//!   Source, ...) then `TIME,CH1,...` and rows; or the older layout with
//!   the header in columns 1-2 and time/value in columns 4-5 of every line
//!   (one channel, named by `Source`). A Record Length must match the rows.
//! - Rigol: `X,CH1,...,Start,Increment,` / `Sequence,Volt,...,<start>,<inc>` /
//!   `index,v1,...`; time = start + index * increment, indices consecutive.
//! - Keysight: `x-axis,1,2` / `second,Volt,Volt` / rows.
//! - Generic: a header row with a time column (time, t, x, s, sec, seconds,
//!   optionally `time_<unit>` or a unit in brackets: s, ms, us, ns, ps) and
//!   channel columns (a `(mV)`/`[uV]` unit scales to volts); comma,
//!   semicolon or tab separated (with `;` or tab a decimal comma is read as
//!   a point); `#` comment lines and blank lines are skipped.

use std::path::Path;

use super::{CaptureError, Format};
use crate::frame::{Channel, ChannelRole, Frame};

/// First-cell keys that mark a Tektronix CSV header block.
const TEK_KEYS: &[&str] = &[
    "record length",
    "sample interval",
    "trigger point",
    "model",
    "firmware version",
    "waveform type",
    "point format",
    "horizontal units",
    "source",
];

/// True when the bytes look like text (no NUL, mostly printable).
pub(crate) fn is_text(head: &[u8]) -> bool {
    if head.contains(&0) {
        return false;
    }
    let odd = head
        .iter()
        .filter(|&&b| b < 0x20 && !matches!(b, b'\n' | b'\r' | b'\t'))
        .count();
    odd * 100 <= head.len()
}

fn split(line: &str, delim: char) -> Vec<&str> {
    line.split(delim)
        .map(|c| c.trim().trim_matches('"').trim())
        .collect()
}

fn text_lines(head: &[u8]) -> Vec<(usize, String)> {
    let text = String::from_utf8_lossy(head);
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    text.split('\n')
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_end_matches('\r').to_string()))
        .collect()
}

fn is_blank(line: &str, delim: char) -> bool {
    split(line, delim).iter().all(|c| c.is_empty())
}

/// Guesses the CSV dialect from the content; `None` if not CSV-like.
pub(crate) fn sniff(head: &[u8]) -> Option<Format> {
    if !is_text(head) {
        return None;
    }
    let lines = text_lines(head);
    let mut content = lines
        .iter()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let (_, first) = content.next()?;
    let cells = split(first, ',');
    let lower: Vec<String> = cells.iter().map(|c| c.to_ascii_lowercase()).collect();
    if lower[0] == "x-axis" {
        return Some(Format::KeysightCsv);
    }
    if lower[0] == "x"
        && lower.iter().any(|c| c == "start")
        && lower.iter().any(|c| c == "increment")
    {
        return Some(Format::RigolCsv);
    }
    if TEK_KEYS.contains(&lower[0].as_str()) {
        return Some(Format::TekCsv);
    }
    let delim = guess_delim(first);
    let cells = split(first, delim);
    let named = cells.iter().filter(|c| !c.is_empty()).count();
    if named >= 2 && cells.iter().any(|c| time_column(c).is_some()) {
        return Some(Format::GenericCsv);
    }
    None
}

fn guess_delim(header: &str) -> char {
    [',', ';', '\t']
        .into_iter()
        .max_by_key(|&d| (header.matches(d).count(), d == ','))
        .unwrap_or(',')
}

/// Name and unit of a header cell: `"Time (ms)"` -> (`"time"`, `Some("ms")`).
fn name_unit(cell: &str) -> (String, Option<String>) {
    let cell = cell.trim();
    if let Some(open) = cell.find(['(', '['])
        && let Some(close) = cell[open..].find([')', ']'])
    {
        let name = cell[..open].trim().to_string();
        let unit = cell[open + 1..open + close].trim().to_string();
        return (name, Some(unit));
    }
    (cell.to_string(), None)
}

fn time_scale(unit: &str) -> Option<f64> {
    match unit.trim() {
        "s" | "S" | "sec" | "secs" | "second" | "seconds" => Some(1.0),
        "ms" => Some(1e-3),
        "us" | "µs" | "μs" => Some(1e-6),
        "ns" => Some(1e-9),
        "ps" => Some(1e-12),
        _ => None,
    }
}

/// If the header cell names a time column, its unit scale (None inside:
/// a time column with an unknown unit).
fn time_column(cell: &str) -> Option<Option<f64>> {
    let (name, unit) = name_unit(cell);
    let lower = name.to_ascii_lowercase();
    const NAMES: &[&str] = &[
        "time", "t", "x", "s", "sec", "secs", "second", "seconds", "x-axis",
    ];
    if NAMES.contains(&lower.as_str()) {
        return Some(match unit {
            None => Some(1.0),
            Some(u) => time_scale(&u),
        });
    }
    for prefix in ["time_", "t_", "time "] {
        if let Some(u) = lower.strip_prefix(prefix)
            && unit.is_none()
            && let Some(s) = time_scale(u)
        {
            return Some(Some(s));
        }
    }
    None
}

fn volts_scale(unit: Option<&str>) -> f64 {
    match unit.map(str::trim) {
        Some("mV") => 1e-3,
        Some("uV" | "µV" | "μV") => 1e-6,
        Some("kV") => 1e3,
        _ => 1.0,
    }
}

/// How the time axis is found in each row.
enum TimeAxis {
    /// A column of times, scaled to seconds.
    Column { col: usize, scale: f64 },
    /// A column of sample indices (Rigol).
    Index {
        col: usize,
        start: f64,
        increment: f64,
    },
}

/// Where to find the data in the rows.
struct Layout {
    delim: char,
    time: TimeAxis,
    /// (column, name, scale to volts)
    chans: Vec<(usize, String, f64)>,
    /// Line of the column header, for "no data" errors.
    header_line: usize,
    /// A Record Length to check the row count against, with its line.
    record_length: Option<(usize, usize)>,
}

struct Ctx<'a> {
    path: &'a Path,
}

impl Ctx<'_> {
    fn err(
        &self,
        line: usize,
        column: Option<usize>,
        expected: impl Into<String>,
        found: impl Into<String>,
    ) -> CaptureError {
        CaptureError::Text {
            path: self.path.to_path_buf(),
            line,
            column,
            expected: expected.into(),
            found: found.into(),
        }
    }

    fn number(
        &self,
        cells: &[&str],
        col: usize,
        line: usize,
        what: &str,
        decimal_comma: bool,
    ) -> Result<f64, CaptureError> {
        let Some(cell) = cells.get(col) else {
            return Err(self.err(
                line,
                Some(col + 1),
                format!("a value for {what}"),
                "end of row",
            ));
        };
        let parsed = if decimal_comma {
            cell.replace(',', ".").parse::<f64>()
        } else {
            cell.parse::<f64>()
        };
        match parsed {
            Ok(x) if x.is_finite() => Ok(x),
            _ => Err(self.err(
                line,
                Some(col + 1),
                format!("a finite number for {what}"),
                format!("{cell:?}"),
            )),
        }
    }

    /// Parses the data rows in `lines` with `layout` into one frame.
    fn rows(&self, lines: &[(usize, String)], layout: &Layout) -> Result<Frame, CaptureError> {
        let decimal_comma = layout.delim != ',';
        let mut times: Vec<f64> = Vec::new();
        let mut row_lines: Vec<usize> = Vec::new();
        let mut values: Vec<Vec<f64>> = vec![Vec::new(); layout.chans.len()];
        for (line, text) in lines {
            if text.trim_start().starts_with('#') {
                continue;
            }
            let cells = split(text, layout.delim);
            if cells.iter().all(|c| c.is_empty()) {
                continue;
            }
            let t = match layout.time {
                TimeAxis::Column { col, scale } => {
                    self.number(&cells, col, *line, "the time", decimal_comma)? * scale
                }
                TimeAxis::Index { col, .. } => {
                    self.number(&cells, col, *line, "the sample index", decimal_comma)?
                }
            };
            for (k, (col, name, scale)) in layout.chans.iter().enumerate() {
                let x = self.number(&cells, *col, *line, name, decimal_comma)? * scale;
                // A finite reading can overflow when scaled to volts (1e308 kV).
                if !x.is_finite() {
                    return Err(self.err(
                        *line,
                        Some(col + 1),
                        format!("a value for {name} that is finite in volts (x {scale})"),
                        format!("{:?}", cells[*col]),
                    ));
                }
                values[k].push(x);
            }
            times.push(t);
            row_lines.push(*line);
        }
        let n = times.len();
        if let Some((expected, line)) = layout.record_length
            && expected != n
        {
            return Err(self.err(
                line,
                None,
                format!("{expected} data rows as this Record Length says"),
                format!("{n} rows"),
            ));
        }
        if n < 2 {
            return Err(self.err(
                row_lines.first().copied().unwrap_or(layout.header_line),
                None,
                "at least 2 data rows after the header (to know the sample interval)",
                if n == 0 {
                    "none".to_string()
                } else {
                    "1 row".to_string()
                },
            ));
        }
        let (first, dt) = match layout.time {
            TimeAxis::Column { .. } => {
                let dt = (times[n - 1] - times[0]) / (n - 1) as f64;
                if !(dt.is_finite() && dt > 0.0) {
                    return Err(self.err(
                        row_lines[n - 1],
                        None,
                        "time values increasing down the rows",
                        format!("{} after {}", times[n - 1], times[0]),
                    ));
                }
                for i in 1..n {
                    let step = times[i] - times[i - 1];
                    if (step - dt).abs() > 0.01 * dt {
                        return Err(self.err(
                            row_lines[i],
                            None,
                            format!("a time step of {dt:e} s (the mean, within 1 %)"),
                            format!("{step:e} s (from {:e} to {:e})", times[i - 1], times[i]),
                        ));
                    }
                }
                (times[0], dt)
            }
            TimeAxis::Index {
                start, increment, ..
            } => {
                for i in 1..n {
                    if times[i] != times[0] + i as f64 {
                        return Err(self.err(
                            row_lines[i],
                            Some(1),
                            format!("sample index {}", times[0] + i as f64),
                            format!("{}", times[i]),
                        ));
                    }
                }
                let first = start + times[0] * increment;
                if !first.is_finite() {
                    return Err(self.err(
                        row_lines[0],
                        Some(1),
                        "a first sample index whose time (Start + index x Increment) is finite",
                        format!("index {} x {increment:e} s + {start:e} s", times[0]),
                    ));
                }
                (first, increment)
            }
        };
        Ok(Frame {
            sensor_id: String::new(),
            sequence: 0,
            trigger_time_s: 0.0,
            sample_interval_s: dt,
            first_sample_offset_s: first,
            channels: layout
                .chans
                .iter()
                .zip(values)
                .map(|((_, name, _), v)| {
                    Channel::from_volts(name.clone(), ChannelRole::Unspecified, v)
                })
                .collect(),
            laser_off: false,
        })
    }
}

/// Index of the first line that is neither blank nor a `#` comment.
fn first_content(lines: &[(usize, String)], delim: char) -> Option<usize> {
    lines
        .iter()
        .position(|(_, l)| !is_blank(l, delim) && !l.trim_start().starts_with('#'))
}

/// Reads a CSV file in the given dialect (`GenericCsv` and friends).
pub(crate) fn read(path: &Path, data: &[u8], dialect: Format) -> Result<Vec<Frame>, CaptureError> {
    let ctx = Ctx { path };
    let lines = text_lines(data);
    let Some(h) = first_content(&lines, ',') else {
        return Err(ctx.err(
            lines.len(),
            None,
            "a CSV header row",
            "only blank or comment lines",
        ));
    };
    let frame = match dialect {
        Format::TekCsv => read_tek(&ctx, &lines, h)?,
        Format::RigolCsv => read_rigol(&ctx, &lines, h)?,
        Format::KeysightCsv => read_keysight(&ctx, &lines, h)?,
        _ => read_generic(&ctx, &lines, h)?,
    };
    Ok(vec![frame])
}

fn channel_columns(
    ctx: &Ctx,
    cells: &[&str],
    skip: &[usize],
    line: usize,
) -> Result<Vec<(usize, String, f64)>, CaptureError> {
    let chans: Vec<(usize, String, f64)> = cells
        .iter()
        .enumerate()
        .filter(|(i, c)| !skip.contains(i) && !c.is_empty() && !is_index_column(c))
        .map(|(i, c)| {
            let (name, unit) = name_unit(c);
            (i, name, volts_scale(unit.as_deref()))
        })
        .collect();
    if chans.is_empty() {
        return Err(ctx.err(
            line,
            None,
            "at least one channel column beside the time column",
            format!("{:?}", cells.join(",")),
        ));
    }
    Ok(chans)
}

/// Row-number columns some exporters add ("index", "sample", "No."): not channels.
fn is_index_column(cell: &str) -> bool {
    matches!(
        cell.to_ascii_lowercase().as_str(),
        "index" | "sample" | "samples" | "n" | "no" | "no." | "#" | "point" | "points"
    )
}

fn read_generic(ctx: &Ctx, lines: &[(usize, String)], h: usize) -> Result<Frame, CaptureError> {
    let (line, header) = &lines[h];
    let delim = guess_delim(header);
    let cells = split(header, delim);
    let Some((col, scale)) = cells
        .iter()
        .enumerate()
        .find_map(|(i, c)| time_column(c).map(|s| (i, s)))
    else {
        return Err(ctx.err(
            *line,
            None,
            "a header row with a time column (time, t, x, s, seconds; optional unit in brackets) and channel columns",
            format!("{:?}", header.chars().take(80).collect::<String>()),
        ));
    };
    let Some(scale) = scale else {
        return Err(ctx.err(
            *line,
            Some(col + 1),
            "a time unit s, ms, us, ns or ps",
            format!("{:?}", cells[col]),
        ));
    };
    let chans = channel_columns(ctx, &cells, &[col], *line)?;
    ctx.rows(
        &lines[h + 1..],
        &Layout {
            delim,
            time: TimeAxis::Column { col, scale },
            chans,
            header_line: *line,
            record_length: None,
        },
    )
}

fn read_keysight(ctx: &Ctx, lines: &[(usize, String)], h: usize) -> Result<Frame, CaptureError> {
    let (line, header) = &lines[h];
    let cells = split(header, ',');
    if !cells[0].eq_ignore_ascii_case("x-axis") {
        return Err(ctx.err(
            *line,
            Some(1),
            "\"x-axis\" (Keysight CSV header)",
            format!("{:?}", cells[0]),
        ));
    }
    let chans = channel_columns(ctx, &cells, &[0], *line)?;
    // The units row ("second,Volt,Volt") is skipped when present.
    let mut from = h + 1;
    if let Some((_, units)) = lines.get(from)
        && split(units, ',')[0].parse::<f64>().is_err()
    {
        from += 1;
    }
    ctx.rows(
        lines.get(from..).unwrap_or(&[]),
        &Layout {
            delim: ',',
            time: TimeAxis::Column { col: 0, scale: 1.0 },
            chans,
            header_line: *line,
            record_length: None,
        },
    )
}

fn read_rigol(ctx: &Ctx, lines: &[(usize, String)], h: usize) -> Result<Frame, CaptureError> {
    let (line, header) = &lines[h];
    let cells = split(header, ',');
    let find = |name: &str| cells.iter().position(|c| c.eq_ignore_ascii_case(name));
    let (Some(s), Some(inc)) = (find("start"), find("increment")) else {
        return Err(ctx.err(
            *line,
            None,
            "a Rigol header \"X,CH1,...,Start,Increment\"",
            format!("{header:?}"),
        ));
    };
    let chans = channel_columns(ctx, &cells[..s.min(inc)], &[0], *line)?;
    let Some((uline, units)) = lines.get(h + 1) else {
        return Err(ctx.err(
            line + 1,
            None,
            "the units row \"Sequence,Volt,...,<start>,<increment>\"",
            "end of file",
        ));
    };
    let ucells = split(units, ',');
    let start = ctx.number(&ucells, s, *uline, "Start", false)?;
    let increment = ctx.number(&ucells, inc, *uline, "Increment", false)?;
    if increment <= 0.0 {
        return Err(ctx.err(
            *uline,
            Some(inc + 1),
            "an Increment > 0 s",
            increment.to_string(),
        ));
    }
    ctx.rows(
        &lines[h + 2..],
        &Layout {
            delim: ',',
            time: TimeAxis::Index {
                col: 0,
                start,
                increment,
            },
            chans,
            header_line: *line,
            record_length: None,
        },
    )
}

fn read_tek(ctx: &Ctx, lines: &[(usize, String)], h: usize) -> Result<Frame, CaptureError> {
    let first = split(&lines[h].1, ',');
    let mut record_length = None;
    let mut source = None;
    // Older layout: header in columns 1-2, time/value in 4-5 on every line.
    if first[0].eq_ignore_ascii_case("record length") && first.len() >= 5 {
        for (line, text) in &lines[h..] {
            let cells = split(text, ',');
            let value = cells.get(1).copied().unwrap_or("");
            if cells[0].eq_ignore_ascii_case("record length") {
                record_length = Some((tek_count(ctx, value, *line)?, *line));
            } else if cells[0].eq_ignore_ascii_case("source") && !value.is_empty() {
                source = Some(value.to_string());
            }
        }
        return ctx.rows(
            &lines[h..],
            &Layout {
                delim: ',',
                time: TimeAxis::Column { col: 3, scale: 1.0 },
                chans: vec![(4, source.unwrap_or_else(|| "CH1".to_string()), 1.0)],
                header_line: lines[h].0,
                record_length,
            },
        );
    }
    let Some(t) = lines
        .iter()
        .position(|(_, l)| split(l, ',')[0].eq_ignore_ascii_case("time"))
    else {
        return Err(ctx.err(
            lines.last().map_or(1, |l| l.0),
            None,
            "a \"TIME,CH1,...\" column header after the Tektronix header block",
            "end of file",
        ));
    };
    for (line, text) in &lines[..t] {
        let cells = split(text, ',');
        if cells[0].eq_ignore_ascii_case("record length") {
            record_length = Some((
                tek_count(ctx, cells.get(1).copied().unwrap_or(""), *line)?,
                *line,
            ));
        }
    }
    let (line, header) = &lines[t];
    let cells = split(header, ',');
    let chans = channel_columns(ctx, &cells, &[0], *line)?;
    ctx.rows(
        &lines[t + 1..],
        &Layout {
            delim: ',',
            time: TimeAxis::Column { col: 0, scale: 1.0 },
            chans,
            header_line: *line,
            record_length,
        },
    )
}

fn tek_count(ctx: &Ctx, value: &str, line: usize) -> Result<usize, CaptureError> {
    value
        .parse::<f64>()
        .ok()
        .filter(|x| x.is_finite() && *x >= 0.0 && x.fract() == 0.0 && *x < 1e12)
        .map(|x| x as usize)
        .ok_or_else(|| {
            ctx.err(
                line,
                Some(2),
                "a whole number for Record Length",
                format!("{value:?}"),
            )
        })
}

/// Writes `frame` as CSV in `dialect` (TekCsv, RigolCsv, KeysightCsv or
/// GenericCsv): values in volts, times relative to the trigger, all numbers
/// in shortest round-trip form (f64 samples survive exactly). Commas in
/// channel names become `_`.
pub fn write_csv(path: &Path, frame: &Frame, dialect: Format) -> Result<(), CaptureError> {
    use std::fmt::Write as _;
    let invalid = |expected: &str, found: String| CaptureError::InvalidFrame {
        path: path.to_path_buf(),
        expected: expected.to_string(),
        found,
    };
    if !dialect.is_csv() {
        return Err(invalid(
            "a CSV dialect (tek-csv, rigol-csv, keysight-csv, csv)",
            dialect.name().to_string(),
        ));
    }
    let n = frame.len();
    if frame.channels.is_empty() || n == 0 {
        return Err(invalid(
            "at least one channel with samples",
            format!("{} channels, {n} samples", frame.channels.len()),
        ));
    }
    if let Some(c) = frame.channels.iter().find(|c| c.samples.len() != n) {
        return Err(invalid(
            &format!("{n} samples in every channel"),
            format!("{} in {}", c.samples.len(), c.name),
        ));
    }
    let volts: Vec<Vec<f64>> = frame.channels.iter().map(|c| c.volts()).collect();
    let names: Vec<String> = frame
        .channels
        .iter()
        .map(|c| c.name.replace([',', ';', '\t', '"'], "_"))
        .collect();
    let dt = frame.sample_interval_s;
    let t0 = frame.first_sample_offset_s;
    let mut out = String::new();
    // `write!` into a String cannot fail.
    match dialect {
        Format::TekCsv => {
            let _ = writeln!(out, "Model,tofwave");
            let _ = writeln!(out, "Waveform Type,ANALOG");
            let _ = writeln!(out, "Point Format,Y");
            let _ = writeln!(out, "Horizontal Units,s");
            let _ = writeln!(out, "Sample Interval,{dt:e}");
            let _ = writeln!(out, "Record Length,{n}");
            let _ = writeln!(out, "Trigger Point,{:e}", -t0 / dt);
            let _ = writeln!(out, "Source,{}", names.join(" "));
            let _ = writeln!(out, "Vertical Units,V");
            let _ = writeln!(out, ",");
            let _ = writeln!(out, "TIME,{}", names.join(","));
        }
        Format::RigolCsv => {
            let _ = writeln!(out, "X,{},Start,Increment,", names.join(","));
            let volts_units = vec!["Volt"; names.len()].join(",");
            let _ = writeln!(out, "Sequence,{volts_units},{t0:e},{dt:e}");
        }
        Format::KeysightCsv => {
            let _ = writeln!(out, "x-axis,{}", names.join(","));
            let _ = writeln!(out, "second,{}", vec!["Volt"; names.len()].join(","));
        }
        _ => {
            let _ = writeln!(
                out,
                "# tofwave frame: sensor {}, sequence {}",
                frame.sensor_id, frame.sequence
            );
            let _ = writeln!(out, "time (s),{}", names.join(","));
        }
    }
    for i in 0..n {
        if dialect == Format::RigolCsv {
            let _ = write!(out, "{i}");
        } else {
            let _ = write!(out, "{:e}", frame.sample_time_s(i as f64));
        }
        for v in &volts {
            let _ = write!(out, ",{:e}", v[i]);
        }
        out.push_str(if dialect == Format::RigolCsv {
            ",\n"
        } else {
            "\n"
        });
    }
    std::fs::write(path, out).map_err(|e| CaptureError::Io {
        path: path.to_path_buf(),
        offset: 0,
        action: "write".into(),
        cause: e,
    })
}
