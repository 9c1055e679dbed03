//! Replays the committed fuzz corpora (`fuzz/corpus/<target>/`) and every
//! stored fuzz finding (`fuzz/artifacts/<target>/`) through the fuzz
//! targets' own entry points (`fuzz/src/entry.rs`, compiled here too), on
//! stable Rust: every input must give `Ok` or an error naming its input,
//! never a panic. See `fuzz/README.md` for the fuzzing itself.
//!
//! `seeds` (ignored) writes the small synthetic seed files the corpora were
//! started from, next to the real captures in `replay-data/` and
//! `tests/data/`: `TOFWAVE_FUZZ_SEEDS=fuzz/corpus-raw cargo test --release
//! --test suite -- --ignored fuzz_corpus::seeds`.

use std::path::{Path, PathBuf};

#[allow(dead_code)]
#[path = "../../fuzz/src/entry.rs"]
mod entry;

use tofwave::capture::{
    Format, write_csv, write_isf, write_keysight_bin, write_recording, write_trc,
};
use tofwave::frame::{Channel, ChannelRole, Frame, Samples};

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

/// Files of `dir` (none when it does not exist), in name order.
fn files(dir: &Path) -> Vec<PathBuf> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut v: Vec<PathBuf> = rd
        .map(|e| e.expect("list directory").path())
        .filter(|p| p.is_file() && p.file_name().is_none_or(|n| n != "README.md"))
        .collect();
    v.sort();
    v
}

fn replay(kind: &str) -> usize {
    let mut n = 0;
    for (name, run) in entry::TARGETS {
        for file in files(&fuzz_dir().join(kind).join(name)) {
            let data = std::fs::read(&file).expect("read corpus file");
            let r = std::panic::catch_unwind(|| run(&data));
            assert!(r.is_ok(), "{name}: {} panicked", file.display());
            n += 1;
        }
    }
    n
}

#[test]
fn committed_corpora_replay_without_panic() {
    let n = replay("corpus");
    // Every target has a committed corpus.
    for (name, _) in entry::TARGETS {
        assert!(
            !files(&fuzz_dir().join("corpus").join(name)).is_empty(),
            "fuzz/corpus/{name} is missing or empty"
        );
    }
    assert!(n > 0);
}

#[test]
fn stored_fuzz_findings_replay_without_panic() {
    replay("artifacts");
}

fn frame(samples: Samples, vpc: f64, two: bool) -> Frame {
    let ch = |name: &str, role| Channel {
        name: name.into(),
        role,
        samples: samples.clone(),
        volts_per_code: vpc,
        offset_v: 0.01,
    };
    let mut channels = vec![ch("CH2", ChannelRole::Stop)];
    if two {
        channels.insert(0, ch("CH1", ChannelRole::Start));
    }
    Frame {
        sensor_id: "seed".into(),
        sequence: 7,
        trigger_time_s: 12.5,
        sample_interval_s: 1e-9,
        first_sample_offset_s: -4e-9,
        channels,
        laser_off: false,
    }
}

/// Writes small seed files of every format under `$TOFWAVE_FUZZ_SEEDS/<target>/`.
#[test]
#[ignore = "writes fuzz seed files; run by hand (see the module doc)"]
fn seeds() {
    let out = PathBuf::from(std::env::var("TOFWAVE_FUZZ_SEEDS").expect("TOFWAVE_FUZZ_SEEDS"));
    let dir = |t: &str| {
        let d = out.join(t);
        std::fs::create_dir_all(&d).expect("create seed dir");
        d
    };
    let codes: Vec<i16> = vec![0, 3, -2, 40, 90, 35, 4, -1];
    let i8s: Vec<i8> = codes.iter().map(|&c| c as i8).collect();
    let volts: Vec<f64> = codes.iter().map(|&c| f64::from(c) * 0.01).collect();
    let f16 = frame(Samples::I16(codes.clone()), 0.01, true);
    let f8 = frame(Samples::I8(i8s), 0.02, false);
    let ff = frame(Samples::F64(volts.clone()), 1.0, true);
    let f32s = frame(
        Samples::F32(volts.iter().map(|&v| v as f32).collect()),
        1.0,
        false,
    );

    write_trc(&dir("capture_trc").join("i16.trc"), std::slice::from_ref(&f16), "CH2").unwrap();
    write_trc(
        &dir("capture_trc").join("i8-seq.trc"),
        &[f8.clone(), f8.clone()],
        "CH2",
    )
    .unwrap();
    write_isf(&dir("capture_isf").join("i16.isf"), &f16, "CH2").unwrap();
    write_isf(&dir("capture_isf").join("i8.isf"), &f8, "CH2").unwrap();
    write_keysight_bin(&dir("capture_keysight_bin").join("f32.bin"), &f32s).unwrap();
    write_keysight_bin(&dir("capture_keysight_bin").join("two.bin"), &ff).unwrap();
    for (f, name) in [
        (Format::TekCsv, "tek.csv"),
        (Format::RigolCsv, "rigol.csv"),
        (Format::KeysightCsv, "keysight.csv"),
        (Format::GenericCsv, "generic.csv"),
    ] {
        write_csv(&dir("capture_csv").join(name), &ff, f).unwrap();
    }
    write_recording(
        &dir("capture_recording").join("mixed.twr"),
        &[f16.clone(), f8.clone(), ff.clone(), f32s.clone()],
    )
    .unwrap();
    // Wire messages: one bare (unprefixed) Frame message per sample type.
    use prost::Message;
    for (f, name) in [(&f16, "i16"), (&f8, "i8"), (&ff, "f64"), (&f32s, "f32")] {
        let bytes = tofwave::wire::frame_to_proto(f).encode_to_vec();
        std::fs::write(dir("wire_frame").join(format!("{name}.pb")), bytes).unwrap();
    }
    // Detection sees every format.
    for t in [
        "capture_trc",
        "capture_isf",
        "capture_keysight_bin",
        "capture_csv",
        "capture_recording",
    ] {
        for p in files(&out.join(t)) {
            std::fs::copy(&p, dir("capture_auto").join(p.file_name().unwrap())).unwrap();
        }
    }
    std::fs::write(
        dir("scene_toml").join("default.toml"),
        tofwave::scene::Scene::default_scene().to_toml(),
    )
    .unwrap();
}
