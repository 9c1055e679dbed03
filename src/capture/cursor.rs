//! Bounds-checked reads from a file held in memory.
//!
//! Every read checks its range against the data first and fails with the byte
//! offset and the name of the structure, so a truncated or corrupt file gives
//! an error instead of a panic, and no length read from a file is trusted
//! before it has been checked against the file's size.

use std::path::Path;

use super::CaptureError;

/// Byte order of multi-byte values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Order {
    /// Least significant byte first.
    Little,
    /// Most significant byte first.
    Big,
}

/// A file's bytes plus its path, for offset-checked reads at absolute positions.
#[derive(Clone, Copy)]
pub(crate) struct View<'a> {
    /// The whole file.
    pub data: &'a [u8],
    /// Names the file in errors.
    pub path: &'a Path,
}

impl<'a> View<'a> {
    pub fn new(path: &'a Path, data: &'a [u8]) -> Self {
        View { data, path }
    }

    /// `len` bytes at `offset`, or a `Truncated` error naming `what`.
    pub fn slice(&self, offset: usize, len: usize, what: &str) -> Result<&'a [u8], CaptureError> {
        let available = self.data.len().saturating_sub(offset);
        match offset.checked_add(len) {
            Some(end) if end <= self.data.len() => Ok(&self.data[offset..end]),
            _ => Err(CaptureError::Truncated {
                path: self.path.to_path_buf(),
                offset: offset as u64,
                expected: what.to_string(),
                needed: len as u64,
                available: available as u64,
            }),
        }
    }

    pub fn array<const N: usize>(
        &self,
        offset: usize,
        what: &str,
    ) -> Result<[u8; N], CaptureError> {
        let s = self.slice(offset, N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    pub fn u8(&self, offset: usize, what: &str) -> Result<u8, CaptureError> {
        Ok(self.array::<1>(offset, what)?[0])
    }

    pub fn u16(&self, offset: usize, order: Order, what: &str) -> Result<u16, CaptureError> {
        let a = self.array::<2>(offset, what)?;
        Ok(match order {
            Order::Little => u16::from_le_bytes(a),
            Order::Big => u16::from_be_bytes(a),
        })
    }

    pub fn i16(&self, offset: usize, order: Order, what: &str) -> Result<i16, CaptureError> {
        Ok(self.u16(offset, order, what)? as i16)
    }

    pub fn u32(&self, offset: usize, order: Order, what: &str) -> Result<u32, CaptureError> {
        let a = self.array::<4>(offset, what)?;
        Ok(match order {
            Order::Little => u32::from_le_bytes(a),
            Order::Big => u32::from_be_bytes(a),
        })
    }

    pub fn i32(&self, offset: usize, order: Order, what: &str) -> Result<i32, CaptureError> {
        Ok(self.u32(offset, order, what)? as i32)
    }

    pub fn u64(&self, offset: usize, order: Order, what: &str) -> Result<u64, CaptureError> {
        let a = self.array::<8>(offset, what)?;
        Ok(match order {
            Order::Little => u64::from_le_bytes(a),
            Order::Big => u64::from_be_bytes(a),
        })
    }

    pub fn f32(&self, offset: usize, order: Order, what: &str) -> Result<f32, CaptureError> {
        Ok(f32::from_bits(self.u32(offset, order, what)?))
    }

    pub fn f64(&self, offset: usize, order: Order, what: &str) -> Result<f64, CaptureError> {
        Ok(f64::from_bits(self.u64(offset, order, what)?))
    }

    /// A `Malformed` error at `offset`.
    pub fn malformed(
        &self,
        offset: usize,
        expected: impl Into<String>,
        found: impl Into<String>,
    ) -> CaptureError {
        CaptureError::Malformed {
            path: self.path.to_path_buf(),
            offset: offset as u64,
            expected: expected.into(),
            found: found.into(),
        }
    }
}

/// NUL-terminated (or padded) ASCII field as a trimmed string.
pub(crate) fn c_string(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).trim().to_string()
}

/// Decodes packed integer samples of `width` bytes (1, 2 or 4), signed or
/// unsigned, into the narrowest [`Samples`] type that holds them exactly.
pub(crate) fn decode_codes(
    raw: &[u8],
    width: usize,
    signed: bool,
    order: Order,
) -> crate::frame::Samples {
    use crate::frame::Samples;
    match (width, signed) {
        (1, true) => Samples::I8(raw.iter().map(|&b| b as i8).collect()),
        (1, false) => Samples::I16(raw.iter().map(|&b| b as i16).collect()),
        (2, signed) => {
            let it = raw.chunks_exact(2).map(|c| {
                let a = [c[0], c[1]];
                match order {
                    Order::Little => u16::from_le_bytes(a),
                    Order::Big => u16::from_be_bytes(a),
                }
            });
            if signed {
                Samples::I16(it.map(|u| u as i16).collect())
            } else {
                Samples::I32(it.map(|u| u as i32).collect())
            }
        }
        (_, signed) => {
            let it = raw.chunks_exact(4).map(|c| {
                let a = [c[0], c[1], c[2], c[3]];
                match order {
                    Order::Little => u32::from_le_bytes(a),
                    Order::Big => u32::from_be_bytes(a),
                }
            });
            if signed {
                Samples::I32(it.map(|u| u as i32).collect())
            } else {
                // u32 codes above i32::MAX cannot stay integer: keep them exact in f64.
                Samples::F64(it.map(|u| u as f64).collect())
            }
        }
    }
}
