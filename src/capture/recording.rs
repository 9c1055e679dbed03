//! tofwave's own recording format (`.twr`): lossless, streamable.
//!
//! Layout: the 12-byte magic [`RECORDING_MAGIC`], a u16 little-endian
//! format version ([`RECORDING_VERSION`]) and a reserved u16 (0), then
//! `tofwave.v1.Frame` messages, each preceded by its length as a protobuf
//! varint (prost's `encode_length_delimited`). The file ends at a message
//! boundary; a cut anywhere else is reported as truncation. Frames are
//! converted with [`wire`](crate::wire), which keeps every sample type exactly
//! (f64 samples travel as `SAMPLE_FORMAT_F64`), so reading a recording gives
//! back identical frames, sensor ids and sequence numbers included.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use prost::Message;

use super::CaptureError;
use crate::frame::Frame;
use crate::wire::{frame_from_proto, frame_to_proto, proto};

/// First bytes of every recording.
pub const RECORDING_MAGIC: &[u8] = b"TOFWAVE-REC\n";
/// Version written after the magic; readers refuse others.
pub const RECORDING_VERSION: u16 = 1;
const HEADER_LEN: u64 = RECORDING_MAGIC.len() as u64 + 4;
/// Largest message accepted when the input's size is unknown (guards
/// against a corrupt length asking for a huge allocation).
const MAX_MESSAGE: u64 = 1 << 30;

/// Writes frames to a recording. Writes the header on creation.
pub struct RecordingWriter<W: Write> {
    /// Destination (buffer it: each frame is one `write_all`).
    w: W,
    /// Scratch for one encoded message, reused across frames.
    buf: Vec<u8>,
    /// Frames written so far.
    frames: u64,
}

impl<W: Write> RecordingWriter<W> {
    /// Writes the header and returns the writer.
    pub fn new(mut w: W) -> std::io::Result<Self> {
        w.write_all(RECORDING_MAGIC)?;
        w.write_all(&RECORDING_VERSION.to_le_bytes())?;
        w.write_all(&0u16.to_le_bytes())?;
        Ok(RecordingWriter {
            w,
            buf: Vec::new(),
            frames: 0,
        })
    }

    /// Appends one frame.
    pub fn write_frame(&mut self, frame: &Frame) -> std::io::Result<()> {
        self.buf.clear();
        frame_to_proto(frame)
            .encode_length_delimited(&mut self.buf)
            .map_err(std::io::Error::other)?;
        self.w.write_all(&self.buf)?;
        self.frames += 1;
        Ok(())
    }

    /// Frames written so far.
    pub fn frames_written(&self) -> u64 {
        self.frames
    }

    /// Flushes what is buffered to the destination (for a file: to the
    /// operating system, so it survives the process being killed).
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.w.flush()
    }

    /// The destination (e.g. to sync a file to its device).
    pub fn get_ref(&self) -> &W {
        &self.w
    }

    /// Flushes and returns the destination.
    pub fn finish(mut self) -> std::io::Result<W> {
        self.w.flush()?;
        Ok(self.w)
    }
}

/// Writes `frames` to a new recording at `path`.
pub fn write_recording(path: &Path, frames: &[Frame]) -> Result<(), CaptureError> {
    let io = |e| CaptureError::Io {
        path: path.to_path_buf(),
        offset: 0,
        action: "write".into(),
        cause: e,
    };
    let file = std::fs::File::create(path).map_err(io)?;
    let mut w = RecordingWriter::new(std::io::BufWriter::new(file)).map_err(io)?;
    for f in frames {
        w.write_frame(f).map_err(io)?;
    }
    w.finish()
        .map_err(io)?
        .into_inner()
        .map_err(|e| io(e.into_error()))?;
    Ok(())
}

/// Reads frames from a recording, one message at a time.
pub struct RecordingReader<R: Read> {
    /// Source, positioned after the last message read.
    r: R,
    /// Names the input in errors.
    path: PathBuf,
    /// Bytes consumed so far (for error offsets).
    offset: u64,
    /// Total input size when known, else `u64::MAX`.
    limit: u64,
    /// Scratch for one message.
    buf: Vec<u8>,
    /// Frames read so far.
    index: u64,
    /// End reached or error yielded.
    done: bool,
}

impl<R: Read> RecordingReader<R> {
    /// Reads and checks the header; `path` names the input in errors.
    pub fn new(r: R, path: &Path) -> Result<Self, CaptureError> {
        Self::with_limit(r, path, u64::MAX)
    }

    /// As [`new`](Self::new), for an input of known size `len` bytes:
    /// message lengths beyond it are refused before any allocation.
    pub fn with_limit(mut r: R, path: &Path, len: u64) -> Result<Self, CaptureError> {
        let mut head = [0u8; HEADER_LEN as usize];
        let got = read_full(&mut r, &mut head).map_err(|e| io(path, 0, e))?;
        if got == 0 {
            return Err(CaptureError::Empty {
                path: path.to_path_buf(),
            });
        }
        let magic_len = RECORDING_MAGIC.len();
        if !head[..got.min(magic_len)].eq(&RECORDING_MAGIC[..got.min(magic_len)]) {
            return Err(CaptureError::Malformed {
                path: path.to_path_buf(),
                offset: 0,
                expected: "the tofwave recording magic \"TOFWAVE-REC\\n\"".into(),
                found: super::preview(&head[..got]),
            });
        }
        if got < head.len() {
            return Err(CaptureError::Truncated {
                path: path.to_path_buf(),
                offset: 0,
                expected: "the recording header".into(),
                needed: HEADER_LEN,
                available: got as u64,
            });
        }
        let version = u16::from_le_bytes([head[magic_len], head[magic_len + 1]]);
        if version != RECORDING_VERSION {
            return Err(CaptureError::Malformed {
                path: path.to_path_buf(),
                offset: magic_len as u64,
                expected: format!("recording format version {RECORDING_VERSION}"),
                found: format!("version {version}"),
            });
        }
        Ok(RecordingReader {
            r,
            path: path.to_path_buf(),
            offset: HEADER_LEN,
            limit: len,
            buf: Vec::new(),
            index: 0,
            done: false,
        })
    }

    /// Reads the next message length; `None` at a clean end of input.
    fn read_len(&mut self) -> Result<Option<u64>, CaptureError> {
        let start = self.offset;
        let mut value = 0u64;
        for i in 0..10 {
            let mut b = [0u8; 1];
            let got = read_full(&mut self.r, &mut b).map_err(|e| io(&self.path, self.offset, e))?;
            if got == 0 {
                if i == 0 {
                    return Ok(None);
                }
                return Err(CaptureError::Truncated {
                    path: self.path.clone(),
                    offset: start,
                    expected: format!("the length prefix of frame {}", self.index),
                    needed: i + 1,
                    available: i,
                });
            }
            self.offset += 1;
            value |= u64::from(b[0] & 0x7f) << (7 * i);
            if b[0] & 0x80 == 0 {
                return Ok(Some(value));
            }
        }
        Err(CaptureError::Malformed {
            path: self.path.clone(),
            offset: start,
            expected: format!(
                "a varint length prefix of frame {} (<= 10 bytes)",
                self.index
            ),
            found: "more than 10 continuation bytes".into(),
        })
    }

    fn read_frame(&mut self) -> Result<Option<Frame>, CaptureError> {
        let Some(len) = self.read_len()? else {
            return Ok(None);
        };
        let at = self.offset;
        let available = self.limit.saturating_sub(at);
        if len > available || len > MAX_MESSAGE {
            return Err(if len > available {
                CaptureError::Truncated {
                    path: self.path.clone(),
                    offset: at,
                    expected: format!("frame {} as its length prefix says", self.index),
                    needed: len,
                    available,
                }
            } else {
                CaptureError::Malformed {
                    path: self.path.clone(),
                    offset: at,
                    expected: format!("a frame message of at most {MAX_MESSAGE} bytes"),
                    found: format!("{len} bytes"),
                }
            });
        }
        // Grow the buffer with the bytes actually read, not with the length
        // the prefix claims: a stream of unknown size (limit u64::MAX) could
        // otherwise ask for a 1 GiB buffer with a few bytes.
        self.buf.clear();
        let got = (&mut self.r)
            .take(len)
            .read_to_end(&mut self.buf)
            .map_err(|e| io(&self.path, at, e))?;
        if (got as u64) < len {
            return Err(CaptureError::Truncated {
                path: self.path.clone(),
                offset: at,
                expected: format!("frame {} as its length prefix says", self.index),
                needed: len,
                available: got as u64,
            });
        }
        self.offset += len;
        let msg =
            proto::Frame::decode(self.buf.as_slice()).map_err(|e| CaptureError::Malformed {
                path: self.path.clone(),
                offset: at,
                expected: format!("a tofwave.v1.Frame message (frame {})", self.index),
                found: e.to_string(),
            })?;
        let frame = frame_from_proto(&msg).map_err(|e| CaptureError::Malformed {
            path: self.path.clone(),
            offset: at,
            expected: format!("a valid frame {}", self.index),
            found: e.to_string(),
        })?;
        self.index += 1;
        Ok(Some(frame))
    }
}

impl<R: Read> Iterator for RecordingReader<R> {
    type Item = Result<Frame, CaptureError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let r = self.read_frame().transpose();
        if !matches!(r, Some(Ok(_))) {
            self.done = true;
        }
        r
    }
}

fn io(path: &Path, offset: u64, source: std::io::Error) -> CaptureError {
    CaptureError::Io {
        path: path.to_path_buf(),
        offset,
        action: "read".into(),
        cause: source,
    }
}

/// Reads until `buf` is full or the input ends; returns the bytes read.
fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}
