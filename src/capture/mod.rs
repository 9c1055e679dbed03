//! Capture readers and writers (development stand-in for the service branch;
//! the real module comes from the `capture` branch with these signatures).

use crate::frame::Frame;
use crate::service::{convert, proto};
use prost::Message;
use std::io::{Read, Write};
use std::path::PathBuf;

const MAGIC: &[u8] = b"TOFWREC1";

/// Errors reading or writing captures.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// I/O failure.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// Content not understood.
    #[error("{path}: {message}")]
    Format {
        /// File.
        path: String,
        /// What was expected.
        message: String,
    },
}

/// Capture formats.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Format {
    /// Detect from content.
    #[default]
    Auto,
    /// tofwave's recording format.
    Tofwave,
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Format::Auto),
            "tofwave" => Ok(Format::Tofwave),
            _ => Err(format!("unknown format {s:?}")),
        }
    }
}

/// How to read captures.
#[derive(Debug, Clone, Default)]
pub struct ReadOptions {
    /// Format (auto-detected by default).
    pub format: Format,
    /// Sensor id given to frames that carry none.
    pub sensor_id: String,
}

/// Frames from a list of capture files.
pub struct FrameSource {
    frames: std::vec::IntoIter<Result<Frame, CaptureError>>,
}

impl Iterator for FrameSource {
    type Item = Result<Frame, CaptureError>;
    fn next(&mut self) -> Option<Self::Item> {
        self.frames.next()
    }
}

/// Opens captures (files or directories) as a frame source.
pub fn frames(paths: &[PathBuf], opts: &ReadOptions) -> Result<FrameSource, CaptureError> {
    Ok(FrameSource {
        frames: read_paths(paths, opts)?
            .into_iter()
            .map(Ok)
            .collect::<Vec<_>>()
            .into_iter(),
    })
}

/// Reads all frames of the captures.
pub fn read_paths(paths: &[PathBuf], opts: &ReadOptions) -> Result<Vec<Frame>, CaptureError> {
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let rd = std::fs::read_dir(p).map_err(|source| CaptureError::Io {
                path: p.display().to_string(),
                source,
            })?;
            let mut v: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).collect();
            v.sort();
            files.extend(v);
        } else {
            files.push(p.clone());
        }
    }
    let mut out = Vec::new();
    for f in files {
        let path = f.display().to_string();
        let mut bytes = Vec::new();
        std::fs::File::open(&f)
            .and_then(|mut h| h.read_to_end(&mut bytes))
            .map_err(|source| CaptureError::Io {
                path: path.clone(),
                source,
            })?;
        let bad = |m: &str| CaptureError::Format {
            path: path.clone(),
            message: m.to_string(),
        };
        let mut rest = bytes
            .strip_prefix(MAGIC)
            .ok_or_else(|| bad("not a tofwave recording"))?;
        while !rest.is_empty() {
            let msg = proto::Frame::decode_length_delimited(&mut rest)
                .map_err(|e| bad(&e.to_string()))?;
            let mut frame = convert::frame_from_proto(&msg).map_err(|e| bad(&e.to_string()))?;
            if frame.sensor_id.is_empty() {
                frame.sensor_id = opts.sensor_id.clone();
            }
            out.push(frame);
        }
    }
    Ok(out)
}

/// Writes frames losslessly in tofwave's recording format.
pub struct RecordingWriter<W: Write> {
    w: W,
}

impl<W: Write> RecordingWriter<W> {
    /// Writes the header.
    pub fn new(mut w: W) -> Result<Self, CaptureError> {
        w.write_all(MAGIC).map_err(|source| CaptureError::Io {
            path: "recording".into(),
            source,
        })?;
        Ok(RecordingWriter { w })
    }

    /// Appends one frame.
    pub fn write_frame(&mut self, frame: &Frame) -> Result<(), CaptureError> {
        let buf = convert::frame_to_proto(frame).encode_length_delimited_to_vec();
        self.w.write_all(&buf).map_err(|source| CaptureError::Io {
            path: "recording".into(),
            source,
        })
    }

    /// Flushes and returns the writer.
    pub fn finish(mut self) -> Result<W, CaptureError> {
        self.w.flush().map_err(|source| CaptureError::Io {
            path: "recording".into(),
            source,
        })?;
        Ok(self.w)
    }
}
