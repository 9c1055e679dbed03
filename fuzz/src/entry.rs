//! One function per fuzz target: feed untrusted bytes to a parser and check
//! that it returns `Ok` or an error that names its input, never panics.
//!
//! Shared by the libFuzzer targets (`fuzz/fuzz_targets/*.rs`) and the stable
//! regression test `tests/suite/fuzz_corpus.rs`, which replays the committed
//! corpora and every stored crash through these same functions.

use std::io::Cursor;
use std::path::Path;

use prost::Message;
use tofwave::capture::{self, CaptureError, Format, RecordingReader};
use tofwave::frame::{Frame, Samples};
use tofwave::scene::Scene;
use tofwave::wire::{self, proto};

/// A fuzz target: its name and its entry point.
pub type Target = (&'static str, fn(&[u8]));

/// The fuzz targets, by name (= the directory names under `fuzz/corpus/`).
pub const TARGETS: &[Target] = &[
    ("capture_auto", capture_auto),
    ("capture_trc", capture_trc),
    ("capture_isf", capture_isf),
    ("capture_keysight_bin", capture_keysight_bin),
    ("capture_csv", capture_csv),
    ("capture_recording", capture_recording),
    ("scene_toml", scene_toml),
    ("wire_frame", wire_frame),
];

/// The name every capture error must carry.
const INPUT: &str = "fuzz-input";

/// An error must name the input it is about (every `CaptureError` message
/// starts with the path).
fn check_error(path: &Path, e: &CaptureError) {
    let msg = e.to_string();
    let name = path.display().to_string();
    assert!(
        msg.starts_with(&name),
        "capture error does not start with the file name {name:?}: {msg}"
    );
}

/// What every frame a reader returns must satisfy: what the wire conversion
/// (`frame_from_proto`) requires of a frame, so a capture read from a file is
/// as valid as one pushed over gRPC.
fn check_frames(frames: &[Frame]) {
    for f in frames {
        assert!(
            f.sample_interval_s.is_finite() && f.sample_interval_s > 0.0,
            "reader returned sample interval {}",
            f.sample_interval_s
        );
        assert!(
            f.trigger_time_s.is_finite() && f.first_sample_offset_s.is_finite(),
            "reader returned trigger time {} and first-sample offset {}",
            f.trigger_time_s,
            f.first_sample_offset_s
        );
        assert!(
            !f.channels.is_empty(),
            "reader returned a frame without channels"
        );
        for c in &f.channels {
            assert!(
                c.volts_per_code.is_finite() && c.offset_v.is_finite(),
                "reader returned channel {:?} with volts_per_code {} and offset_v {}",
                c.name,
                c.volts_per_code,
                c.offset_v
            );
            assert_eq!(c.samples.len(), f.len(), "channels of unequal length");
            let finite = match &c.samples {
                Samples::F32(v) => v.iter().all(|x| x.is_finite()),
                Samples::F64(v) => v.iter().all(|x| x.is_finite()),
                _ => true,
            };
            assert!(
                finite,
                "reader returned non-finite samples in channel {:?}",
                c.name
            );
        }
    }
}

fn read(path: &Path, data: &[u8], format: Format) {
    match capture::read_bytes(path, data, format) {
        Ok(frames) => check_frames(&frames),
        Err(e) => check_error(path, &e),
    }
}

/// Format detection (content, then extension tie-break) and the auto reader.
pub fn capture_auto(data: &[u8]) {
    let head = &data[..data.len().min(4096)];
    for ext in ["", ".trc", ".bin", ".isf", ".csv", ".twr", ".dat"] {
        let path = format!("{INPUT}{ext}");
        if let Err(e) = capture::detect_format(Path::new(&path), head) {
            check_error(Path::new(&path), &e);
        }
    }
    read(Path::new("fuzz-input.csv"), data, Format::Auto);
}

/// LeCroy `.trc`.
pub fn capture_trc(data: &[u8]) {
    read(Path::new(INPUT), data, Format::LecroyTrc);
}

/// Tektronix `.isf`.
pub fn capture_isf(data: &[u8]) {
    read(Path::new(INPUT), data, Format::TekIsf);
}

/// Keysight/Agilent `.bin`.
pub fn capture_keysight_bin(data: &[u8]) {
    read(Path::new(INPUT), data, Format::KeysightBin);
}

/// The same bytes through all four CSV dialects.
pub fn capture_csv(data: &[u8]) {
    for f in [
        Format::TekCsv,
        Format::RigolCsv,
        Format::KeysightCsv,
        Format::GenericCsv,
    ] {
        read(Path::new(INPUT), data, f);
    }
}

/// tofwave recordings: the in-memory reader (size known) and the streaming
/// reader (size unknown, as for a pipe).
pub fn capture_recording(data: &[u8]) {
    let path = Path::new(INPUT);
    if let Err(e) = capture::read_bytes(path, data, Format::Tofwave) {
        check_error(path, &e);
    }
    match RecordingReader::new(Cursor::new(data), path) {
        Ok(r) => {
            for item in r {
                if let Err(e) = item {
                    check_error(path, &e);
                }
            }
        }
        Err(e) => check_error(path, &e),
    }
}

/// Scene TOML: parse and validate; a scene that loads must print as TOML that
/// loads again to the same scene (`tofwave scene --check` output is reusable).
pub fn scene_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(scene) = Scene::from_toml_str(text, INPUT) {
        let again = scene.to_toml();
        let back = Scene::from_toml_str(&again, "printed scene").unwrap_or_else(|e| {
            panic!("a valid scene prints as TOML that does not load: {e}\n{again}")
        });
        assert_eq!(back.to_toml(), again, "printed scene does not round-trip");
    }
}

/// Wire conversion of an arbitrary (prost-decoded) `tofwave.v1.Frame`; a
/// frame it accepts converts back and forth unchanged.
pub fn wire_frame(data: &[u8]) {
    let Ok(msg) = proto::Frame::decode(data) else {
        return;
    };
    if let Ok(frame) = wire::frame_from_proto(&msg) {
        let again = wire::frame_to_proto(&frame);
        let back = wire::frame_from_proto(&again)
            .unwrap_or_else(|e| panic!("a converted frame does not convert back: {e}"));
        assert_eq!(back, frame, "frame does not round-trip through the wire");
    }
}
