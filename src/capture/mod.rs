//! capture (temporary interface stand-in; replaced by the readers)
use crate::frame::Frame;
use std::path::PathBuf;
/// Formats.
#[derive(Debug, Clone, Copy)]
pub enum Format { /** auto */ Auto }
impl std::str::FromStr for Format { type Err = String; fn from_str(_: &str) -> Result<Self, String> { Ok(Format::Auto) } }
impl Format { /** names */ pub const ALL_NAMES: &'static [&'static str] = &["auto"]; }
/// Error.
#[derive(Debug, thiserror::Error)] #[error("capture")] pub struct CaptureError;
/// Options.
#[derive(Debug, Clone)] pub struct ReadOptions { /** f */ pub format: Format, /** s */ pub sensor_id: String }
/// Reads.
pub fn read_paths(_: &[PathBuf], _: &ReadOptions) -> Result<Vec<Frame>, CaptureError> { Err(CaptureError) }
