//! Capture files: oscilloscope exports and tofwave recordings in, frames out.
//!
//! Readers turn a file into [`Frame`](crate::frame::Frame)s, one per trigger (one per segment of a
//! segmented capture). Integer ADC codes stay integer [`Samples`](crate::frame::Samples) with their
//! `volts_per_code`/`offset_v`, so averaging stays exact; CSV values become
//! `Samples::F64` in volts. The format is detected from the content (the
//! extension only breaks ties and picks the parser whose error explains best
//! why a file is not understood). Every error names the file, the byte offset
//! or line, and what was expected versus found; no input makes a reader panic
//! or allocate more than the file's own size.
//!
//! Frames from scope captures get `ReadOptions::sensor_id` and sequence
//! numbers counted across all files of one call. Frames from tofwave
//! recordings keep the sensor id and sequence number they were recorded
//! with (the recording is lossless), but still advance the counter.

mod codes;
mod csv;
mod cursor;
mod isf;
mod keysight_bin;
pub mod measure;
mod recording;
mod trc;

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use crate::frame::{limits, Frame};

pub use csv::write_csv;
pub use isf::write_isf;
pub use keysight_bin::write_keysight_bin;
pub use recording::{
    RECORDING_MAGIC, RECORDING_VERSION, RecordingReader, RecordingWriter, write_recording,
};
pub use trc::write_trc;

/// A capture format, or `Auto` to detect it per file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Format {
    /// Detect from the content (and the extension as a tie-break).
    Auto,
    /// Teledyne LeCroy `.trc` (LECROY_2_3 WAVEDESC), single or sequence mode.
    LecroyTrc,
    /// Keysight/Agilent InfiniiVision `.bin` (`AG01`/`AG03`/`AG10`).
    KeysightBin,
    /// Tektronix internal save format `.isf`.
    TekIsf,
    /// Tektronix CSV (header block then `TIME,CH1,...`; or the older 5-column layout).
    TekCsv,
    /// Rigol CSV (`X,CH1,...,Start,Increment`).
    RigolCsv,
    /// Keysight/Agilent CSV (`x-axis,1,2` / `second,Volt,Volt`).
    KeysightCsv,
    /// Any CSV with a time column and channel columns.
    GenericCsv,
    /// tofwave's own lossless recording (`.twr`).
    Tofwave,
}

impl Format {
    /// The CLI names, in the order of the variants.
    pub const ALL_NAMES: &'static [&'static str] = &[
        "auto",
        "trc",
        "keysight-bin",
        "isf",
        "tek-csv",
        "rigol-csv",
        "keysight-csv",
        "csv",
        "tofwave",
    ];

    /// The CLI name (`--format`).
    pub fn name(self) -> &'static str {
        match self {
            Format::Auto => "auto",
            Format::LecroyTrc => "trc",
            Format::KeysightBin => "keysight-bin",
            Format::TekIsf => "isf",
            Format::TekCsv => "tek-csv",
            Format::RigolCsv => "rigol-csv",
            Format::KeysightCsv => "keysight-csv",
            Format::GenericCsv => "csv",
            Format::Tofwave => "tofwave",
        }
    }

    const ALL: [Format; 9] = [
        Format::Auto,
        Format::LecroyTrc,
        Format::KeysightBin,
        Format::TekIsf,
        Format::TekCsv,
        Format::RigolCsv,
        Format::KeysightCsv,
        Format::GenericCsv,
        Format::Tofwave,
    ];

    fn is_csv(self) -> bool {
        matches!(
            self,
            Format::TekCsv | Format::RigolCsv | Format::KeysightCsv | Format::GenericCsv
        )
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// An unknown `--format` name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown capture format {name:?}; expected one of: {}", Format::ALL_NAMES.join(", "))]
pub struct ParseFormatError {
    /// The name that was given.
    pub name: String,
}

impl std::str::FromStr for Format {
    type Err = ParseFormatError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let lower = s.trim().to_ascii_lowercase();
        Format::ALL
            .into_iter()
            .find(|f| f.name() == lower)
            .ok_or_else(|| ParseFormatError {
                name: s.to_string(),
            })
    }
}

/// Why a capture could not be read or written. Every message names the
/// file, the byte offset or line, and what was expected versus found.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The operating system refused (missing file, permissions, disk full).
    #[error("{}: byte {}: {} failed: {}", .path.display(), .offset, .action, .cause)]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// Where in the file (0 when opening).
        offset: u64,
        /// What was being done ("open", "read", "write", "list directory").
        action: String,
        /// The OS error.
        cause: std::io::Error,
    },
    /// The file ends before a structure its header promised.
    #[error(
        "{}: byte {}: expected {} ({} bytes), found only {} bytes before the end of the file",
        .path.display(), .offset, .expected, .needed, .available
    )]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Where the structure starts.
        offset: u64,
        /// What structure.
        expected: String,
        /// Bytes it needs.
        needed: u64,
        /// Bytes left in the file from `offset`.
        available: u64,
    },
    /// A binary structure holds a value that makes no sense.
    #[error("{}: byte {}: expected {}, found {}", .path.display(), .offset, .expected, .found)]
    Malformed {
        /// The file.
        path: PathBuf,
        /// Where the value sits.
        offset: u64,
        /// What a valid file has there.
        expected: String,
        /// What this file has.
        found: String,
    },
    /// A text capture (CSV, ISF header) is not as its dialect requires.
    #[error("{}: line {}{}: expected {}, found {}", .path.display(), .line, column_text(*.column), .expected, .found)]
    Text {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// 1-based column (cell) number, when one cell is at fault.
        column: Option<usize>,
        /// What a valid file has there.
        expected: String,
        /// What this file has.
        found: String,
    },
    /// The file is empty.
    #[error("{}: byte 0: expected capture data, found an empty file", .path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// Auto-detection recognised neither the content nor the extension.
    #[error(
        "{}: byte 0: expected a capture file (LeCroy .trc, Keysight .bin, Tektronix .isf, \
         Tektronix/Rigol/Keysight/generic CSV, or tofwave .twr), found {}",
        .path.display(), .found
    )]
    Unrecognised {
        /// The file.
        path: PathBuf,
        /// A printable preview of the first bytes.
        found: String,
    },
    /// A directory argument holds no capture file.
    #[error(
        "{}: expected capture files (.trc, .bin, .isf, .csv, .tsv, .txt, .twr) in the directory, found none",
        .path.display()
    )]
    NoCaptures {
        /// The directory.
        path: PathBuf,
    },
    /// A frame outside the resource bounds of [`crate::frame::limits`]
    /// (sampling period, samples per frame).
    #[error("{}: frame {}: {}: {}", .path.display(), .frame, .field, .message)]
    OutOfBounds {
        /// The file.
        path: PathBuf,
        /// Index of the frame (segment) in the file, from 0.
        frame: usize,
        /// The frame field at fault (`sample_interval_s`, `samples`).
        field: &'static str,
        /// Its value and the allowed range.
        message: String,
    },
    /// A writer was given a frame the format cannot hold.
    #[error("{}: cannot write: expected {}, found {}", .path.display(), .expected, .found)]
    InvalidFrame {
        /// The file being written.
        path: PathBuf,
        /// What the format needs.
        expected: String,
        /// What the frame has.
        found: String,
    },
}

fn column_text(column: Option<usize>) -> String {
    column.map_or(String::new(), |c| format!(", column {c}"))
}

/// How to read captures.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadOptions {
    /// `Auto` detects each file's format; anything else forces one parser for all files.
    pub format: Format,
    /// Sensor id given to frames from scope captures (recordings keep theirs).
    pub sensor_id: String,
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions {
            format: Format::Auto,
            sensor_id: "capture".to_string(),
        }
    }
}

/// Extensions of files a directory listing picks up (lower case).
const CAPTURE_EXTENSIONS: &[&str] = &["trc", "bin", "isf", "csv", "tsv", "txt", "twr"];

/// Bytes of a file's head examined by [`detect_format`].
const HEAD_LEN: usize = 4096;

fn io_err(path: &Path, offset: u64, action: &str, source: std::io::Error) -> CaptureError {
    CaptureError::Io {
        path: path.to_path_buf(),
        offset,
        action: action.to_string(),
        cause: source,
    }
}

/// Detects the format from the first bytes (`head`, up to a few kB) and the
/// extension.
///
/// Content wins: a `.csv` holding a LeCroy file is read as LeCroy. When the
/// content is not recognised the extension picks the parser (whose error then
/// says what is wrong); with neither, the error shows the first bytes.
pub fn detect_format(path: &Path, head: &[u8]) -> Result<Format, CaptureError> {
    if head.is_empty() {
        return Err(CaptureError::Empty {
            path: path.to_path_buf(),
        });
    }
    // A recording cut inside its magic is still a (truncated) recording.
    if head.starts_with(RECORDING_MAGIC) || RECORDING_MAGIC.starts_with(head) {
        return Ok(Format::Tofwave);
    }
    if trc::find_wavedesc(head).is_some() {
        return Ok(Format::LecroyTrc);
    }
    if head.len() >= 4
        && &head[..2] == b"AG"
        && head[2].is_ascii_digit()
        && head[3].is_ascii_digit()
    {
        return Ok(Format::KeysightBin);
    }
    if isf::looks_like_isf(head) {
        return Ok(Format::TekIsf);
    }
    if let Some(dialect) = csv::sniff(head) {
        return Ok(dialect);
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    match ext.as_deref() {
        Some("trc") => Ok(Format::LecroyTrc),
        Some("bin") => Ok(Format::KeysightBin),
        Some("isf") => Ok(Format::TekIsf),
        Some("twr") => Ok(Format::Tofwave),
        Some("csv" | "tsv" | "txt") if csv::is_text(head) => Ok(Format::GenericCsv),
        _ => Err(CaptureError::Unrecognised {
            path: path.to_path_buf(),
            found: preview(head),
        }),
    }
}

/// A short printable rendering of bytes for error messages.
pub(crate) fn preview(bytes: &[u8]) -> String {
    let shown: String = bytes
        .iter()
        .take(24)
        .flat_map(|&b| std::ascii::escape_default(b))
        .map(char::from)
        .collect();
    if bytes.len() > 24 {
        format!("\"{shown}...\"")
    } else {
        format!("\"{shown}\"")
    }
}

/// Parses a capture held in memory; `path` only names it in errors.
///
/// `format` may be `Auto`. Frames carry sensor id `""` and sequence numbers
/// counted from 0 within this file; recordings keep their recorded ids.
pub fn read_bytes(path: &Path, data: &[u8], format: Format) -> Result<Vec<Frame>, CaptureError> {
    let format = match format {
        Format::Auto => detect_format(path, &data[..data.len().min(HEAD_LEN)])?,
        f => f,
    };
    if data.is_empty() {
        return Err(CaptureError::Empty {
            path: path.to_path_buf(),
        });
    }
    let mut frames = match format {
        Format::LecroyTrc => trc::read(path, data)?,
        Format::KeysightBin => keysight_bin::read(path, data)?,
        Format::TekIsf => isf::read(path, data)?,
        Format::Tofwave => {
            return RecordingReader::with_limit(data, path, data.len() as u64)?.collect();
        }
        f if f.is_csv() => csv::read(path, data, f)?,
        _ => unreachable!("Auto was resolved above"),
    };
    for (i, f) in frames.iter_mut().enumerate() {
        f.sequence = i as u64;
        check_bounds(path, i, f)?;
    }
    Ok(frames)
}

/// Refuses a frame outside the resource bounds (frame::limits) as the
/// readers deliver it, so that no caller sizes work from it. Recordings are
/// checked by the wire conversion they decode through.
fn check_bounds(path: &Path, frame: usize, f: &Frame) -> Result<(), CaptureError> {
    let out = |field, message| CaptureError::OutOfBounds { path: path.to_path_buf(), frame, field, message };
    if let Some(m) = limits::sample_interval_problem(f.sample_interval_s) {
        return Err(out("sample_interval_s", m));
    }
    if let Some(m) = limits::samples_per_frame_problem(f.len()) {
        return Err(out("samples", m));
    }
    Ok(())
}

/// A file in an input directory that is not read: what it is and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    /// The file.
    pub path: PathBuf,
    /// Why it is not a capture (for the note printed to the user).
    pub why: String,
}

impl std::fmt::Display for Skipped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: skipped, {}", self.path.display(), self.why)
    }
}

/// Expands directories (capture files in name order, hidden files skipped).
///
/// A file named on the command line is always read (and fails loudly when it
/// is not a capture). In a directory, files without a capture extension, and
/// (with `format` auto) text files whose first line is no capture header
/// (a licence, a README, a manifest), are skipped and listed in the second
/// vector so the caller can say so.
fn expand(paths: &[PathBuf], format: Format) -> Result<(Vec<PathBuf>, Vec<Skipped>), CaptureError> {
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    for p in paths {
        let meta = std::fs::metadata(p).map_err(|e| io_err(p, 0, "open", e))?;
        if !meta.is_dir() {
            out.push(p.clone());
            continue;
        }
        let mut files = Vec::new();
        for entry in std::fs::read_dir(p).map_err(|e| io_err(p, 0, "list directory", e))? {
            let entry = entry.map_err(|e| io_err(p, 0, "list directory", e))?;
            let path = entry.path();
            let name = entry.file_name();
            let name = name.to_string_lossy();
            if name.starts_with('.') || !path.is_file() {
                continue;
            }
            let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
            let Some(ext) = ext.filter(|e| CAPTURE_EXTENSIONS.contains(&e.as_str())) else {
                skipped.push(Skipped {
                    path,
                    why: format!("not a capture file extension (reads {})", CAPTURE_EXTENSIONS.join(", ")),
                });
                continue;
            };
            if format == Format::Auto && matches!(ext.as_str(), "csv" | "tsv" | "txt") {
                let mut head = Vec::with_capacity(HEAD_LEN);
                File::open(&path)
                    .and_then(|f| f.take(HEAD_LEN as u64).read_to_end(&mut head))
                    .map_err(|e| io_err(&path, 0, "read", e))?;
                if csv::sniff(&head).is_none() {
                    skipped.push(Skipped {
                        path,
                        why: "text without a capture header (a time column and channel columns, or a scope's header)".into(),
                    });
                    continue;
                }
            }
            files.push(path);
        }
        if files.is_empty() {
            return Err(CaptureError::NoCaptures { path: p.clone() });
        }
        files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
        skipped.sort_by(|a, b| a.path.cmp(&b.path));
        out.extend(files);
    }
    Ok((out, skipped))
}

/// Frames of the file being read.
enum Current {
    /// No file open.
    Idle,
    /// A scope capture, parsed whole (they are small).
    Buffered(std::vec::IntoIter<Frame>),
    /// A recording, streamed frame by frame (they can be large).
    Recording(Box<RecordingReader<BufReader<File>>>),
}

/// Frames from a list of files, read lazily file by file (see [`frames`]).
pub struct FrameSource {
    /// Files still to open, in order.
    files: std::vec::IntoIter<PathBuf>,
    /// Forced format, or `Auto`.
    format: Format,
    /// Sensor id for scope-capture frames.
    sensor_id: String,
    /// Next sequence number across all files.
    next_sequence: u64,
    /// The open file's remaining frames.
    current: Current,
    /// An error was yielded: the source is finished.
    failed: bool,
    /// Files in input directories that are not read.
    skipped: Vec<Skipped>,
}

impl FrameSource {
    /// Files in the input directories that are not captures and are not read
    /// (a licence, a README): the caller notes them.
    pub fn skipped(&self) -> &[Skipped] {
        &self.skipped
    }

    fn open_next(&mut self) -> Option<Result<(), CaptureError>> {
        let path = self.files.next()?;
        Some(self.open(&path))
    }

    fn open(&mut self, path: &Path) -> Result<(), CaptureError> {
        let mut file = File::open(path).map_err(|e| io_err(path, 0, "open", e))?;
        let format = match self.format {
            Format::Auto => {
                let mut head = Vec::with_capacity(HEAD_LEN);
                (&mut file)
                    .take(HEAD_LEN as u64)
                    .read_to_end(&mut head)
                    .map_err(|e| io_err(path, 0, "read", e))?;
                let f = detect_format(path, &head)?;
                file = File::open(path).map_err(|e| io_err(path, 0, "open", e))?;
                f
            }
            f => f,
        };
        if format == Format::Tofwave {
            let len = file
                .metadata()
                .map_err(|e| io_err(path, 0, "read", e))?
                .len();
            if len == 0 {
                return Err(CaptureError::Empty {
                    path: path.to_path_buf(),
                });
            }
            let reader = RecordingReader::with_limit(BufReader::new(file), path, len)?;
            self.current = Current::Recording(Box::new(reader));
        } else {
            let mut data = Vec::new();
            file.read_to_end(&mut data)
                .map_err(|e| io_err(path, 0, "read", e))?;
            let frames = read_bytes(path, &data, format)?;
            self.current = Current::Buffered(frames.into_iter());
        }
        Ok(())
    }
}

impl Iterator for FrameSource {
    type Item = Result<Frame, CaptureError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        loop {
            let item = match &mut self.current {
                Current::Idle => None,
                Current::Buffered(it) => it.next().map(|mut f| {
                    f.sensor_id.clone_from(&self.sensor_id);
                    f.sequence = self.next_sequence;
                    Ok(f)
                }),
                Current::Recording(r) => r.next(),
            };
            match item {
                Some(Ok(f)) => {
                    self.next_sequence += 1;
                    return Some(Ok(f));
                }
                Some(Err(e)) => {
                    self.failed = true;
                    return Some(Err(e));
                }
                None => {
                    self.current = Current::Idle;
                    match self.open_next()? {
                        Ok(()) => continue,
                        Err(e) => {
                            self.failed = true;
                            return Some(Err(e));
                        }
                    }
                }
            }
        }
    }
}

/// Lazily yields frames file by file (for replay of large inputs); same
/// order and numbering as [`read_paths`]. Directories are listed now; files
/// are opened as the iterator reaches them. After an error it yields nothing.
pub fn frames(paths: &[PathBuf], opts: &ReadOptions) -> Result<FrameSource, CaptureError> {
    let (files, skipped) = expand(paths, opts.format)?;
    Ok(FrameSource {
        skipped,
        files: files.into_iter(),
        format: opts.format,
        sensor_id: opts.sensor_id.clone(),
        next_sequence: 0,
        current: Current::Idle,
        failed: false,
    })
}

/// Reads files and directories in order; sequence numbers continue across files.
///
/// A directory contributes every capture file in it (known extensions,
/// hidden files skipped) in name order. A multi-segment file gives one frame
/// per segment.
pub fn read_paths(paths: &[PathBuf], opts: &ReadOptions) -> Result<Vec<Frame>, CaptureError> {
    frames(paths, opts)?.collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_names_round_trip() {
        for (f, n) in Format::ALL.iter().zip(Format::ALL_NAMES) {
            assert_eq!(f.name(), *n);
            assert_eq!(n.parse::<Format>().unwrap(), *f);
        }
        let e = "wfm".parse::<Format>().unwrap_err().to_string();
        assert!(e.contains("\"wfm\"") && e.contains("keysight-csv"), "{e}");
    }

    #[test]
    fn unrecognised_binary_is_refused_with_a_preview() {
        let e = detect_format(Path::new("x.dat"), &[0, 1, 2, 0xff]).unwrap_err();
        assert!(matches!(e, CaptureError::Unrecognised { .. }));
        let msg = e.to_string();
        assert!(
            msg.starts_with("x.dat: byte 0: expected a capture file"),
            "{msg}"
        );
        assert!(msg.contains("\\x00\\x01\\x02\\xff"), "{msg}");
    }
}
