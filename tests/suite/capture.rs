//! Capture readers and writers: real scope files, round trips through every
//! writer/reader pair, malformed input (errors name file + offset/line +
//! expectation, never a panic), directory order and auto-detection.

use std::path::{Path, PathBuf};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tofwave::capture::{
    CaptureError, Format, ReadOptions, RecordingReader, RecordingWriter, detect_format, frames,
    read_bytes, read_paths, write_csv, write_isf, write_keysight_bin, write_recording, write_trc,
};
use tofwave::frame::{Channel, ChannelRole, Frame, Samples};

use crate::common;
use common::replay_path as replay;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/capture")
        .join(name)
}

fn read_one(path: &Path) -> Vec<Frame> {
    read_paths(&[path.to_path_buf()], &ReadOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

fn read_err(path: &Path) -> String {
    match read_paths(&[path.to_path_buf()], &ReadOptions::default()) {
        Ok(f) => panic!(
            "{} read as {} frames, expected an error",
            path.display(),
            f.len()
        ),
        Err(e) => e.to_string(),
    }
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[s.len() / 2]
}

fn argmax(v: &[f64]) -> usize {
    (0..v.len()).fold(0, |best, i| if v[i] > v[best] { i } else { best })
}

// ---------------------------------------------------------------- real files

#[test]
fn lecroy_4_single_pulse_has_the_documented_shape_and_time_axis() {
    let frames = read_one(&replay("lecroy_4.trc"));
    assert_eq!(frames.len(), 1);
    let f = &frames[0];
    assert_eq!(f.len(), 502);
    assert_eq!(f.sample_interval_s, 1e-9);
    assert_eq!(f.channels.len(), 1);
    assert_eq!(f.channels[0].name, "C2");
    assert!(matches!(f.channels[0].samples, Samples::I16(_)));
    assert_eq!(f.channels[0].volts_per_code, 1.24995e-4);
    assert_eq!(f.channels[0].offset_v, 1.0);
    assert_eq!(f.first_sample_offset_s, -1.2074500661794662e-7);
    let v = f.channels[0].volts();
    let peak = argmax(&v);
    assert_eq!(peak, 125);
    assert!((v[peak] - 2.504).abs() < 1e-3, "peak {}", v[peak]);
    let t_peak = f.sample_time_s(peak as f64);
    assert!((t_peak - 4.25e-9).abs() < 0.01e-9, "t_peak {t_peak:e}");
    let baseline = median(&v[..100]);
    assert!((baseline - 0.008).abs() < 0.001, "baseline {baseline}");
    // 50 % rising crossing by linear interpolation: the trigger sits on the edge.
    let level = baseline + 0.5 * (v[peak] - baseline);
    let k = (1..=peak).find(|&k| v[k] >= level).unwrap();
    let t50 = f.sample_time_s(k as f64 - 1.0 + (level - v[k - 1]) / (v[k] - v[k - 1]));
    assert!((t50 - 0.77e-9).abs() < 0.02e-9, "t50 {t50:e}");
    // TRIGGER_TIME 2022-11-09 09:23:52.11 (scope clock, read as UTC).
    assert!(
        (f.trigger_time_s - 1_667_985_832.112).abs() < 1e-3,
        "{}",
        f.trigger_time_s
    );
}

#[test]
fn lecroy_3_sequence_gives_one_frame_per_segment_with_trigtime() {
    let frames = read_one(&replay("lecroy_3.trc"));
    assert_eq!(frames.len(), 20);
    let t0 = frames[0].trigger_time_s;
    let rel: Vec<f64> = frames.iter().map(|f| f.trigger_time_s - t0).collect();
    // f64 at ~1.7e9 s resolves 2.4e-7 s: tolerance 1e-6 s.
    assert!((rel[1] - 7.4584e-3).abs() < 1e-6, "{}", rel[1]);
    assert!((rel[2] - 1.7308e-2).abs() < 1e-6, "{}", rel[2]);
    assert!(
        rel.windows(2).all(|w| w[1] > w[0]),
        "trigger times increase"
    );
    assert_eq!(frames[0].first_sample_offset_s, -3.645793678514268e-7);
    assert_eq!(frames[1].first_sample_offset_s, -3.643285602155971e-7);
    assert_eq!(frames[2].first_sample_offset_s, -3.644754030937176e-7);
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f.sequence, i as u64);
        assert_eq!(f.sensor_id, "capture");
        assert_eq!(f.len(), 502);
        assert_eq!(f.channels[0].name, "C2");
        // Every segment holds the pulse at the same place (368-369) over an
        // 8 mV baseline; amplitudes vary shot to shot (1.67-2.57 V).
        let v = f.channels[0].volts();
        let k = argmax(&v);
        assert!((368..=369).contains(&k), "segment {i} peak at {k}");
        assert!((1.6..2.6).contains(&v[k]), "segment {i} peak {}", v[k]);
        assert!((median(&v[..100]) - 0.008).abs() < 0.001);
    }
    // Segments differ (not one segment repeated).
    assert_ne!(frames[0].channels[0].samples, frames[1].channels[0].samples);
}

#[test]
fn lecroy_2_long_record_reads_whole() {
    let frames = read_one(&replay("lecroy_2.trc"));
    assert_eq!(frames.len(), 1);
    let f = &frames[0];
    assert_eq!(f.len(), 100_002);
    assert_eq!(f.sample_interval_s, 1e-7);
    let v = f.channels[0].volts();
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    assert!((mean - 0.328).abs() < 0.001, "mean {mean}");
    assert!((f.first_sample_offset_s + 1.0000682e-3).abs() < 1e-9);
}

#[test]
fn agilent_1_bin_reads_float_volts() {
    let frames = read_one(&replay("agilent_1.bin"));
    assert_eq!(frames.len(), 1);
    let f = &frames[0];
    assert_eq!(f.len(), 2000);
    assert_eq!(f.sample_interval_s, 5e-7);
    assert_eq!(f.first_sample_offset_s, -5.000631603125e-4);
    assert_eq!(f.channels[0].name, "1");
    assert!(matches!(f.channels[0].samples, Samples::F32(_)));
    let v = f.channels[0].volts();
    let (lo, hi) = v
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    assert!(lo > -2.2 && lo < -1.9, "min {lo}");
    assert!(hi < 2.2 && hi > 1.8, "max {hi}");
}

// ---------------------------------------------------------------- round trips

fn sample_frame(seq: u64, samples: Vec<Samples>) -> Frame {
    Frame {
        sensor_id: "sim".into(),
        sequence: seq,
        trigger_time_s: 1.7e9 + seq as f64 * 1e-3,
        sample_interval_s: 1e-9,
        first_sample_offset_s: -2.5e-8 + seq as f64 * 1e-10,
        channels: samples
            .into_iter()
            .enumerate()
            .map(|(i, s)| Channel {
                name: format!("CH{}", i + 1),
                role: ChannelRole::Unspecified,
                samples: s,
                volts_per_code: 1.25e-4,
                offset_v: -0.5,
            })
            .collect(),
        laser_off: false,
    }
}

fn i16_ramp(n: usize, k: i32) -> Vec<i16> {
    (0..n as i32)
        .map(|i| ((i * 977 + k * 31) % 65536 - 32768) as i16)
        .collect()
}

fn pulse_volts(n: usize, shift: f64) -> Vec<f64> {
    (0..n)
        .map(|i| {
            0.01 + 2.5 * (-((i as f64 - 40.0 - shift) / 3.0).powi(2)).exp()
                + 1e-3 * (i as f64 * 0.7).sin()
        })
        .collect()
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn trc_round_trip_keeps_codes_exact() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("one.trc");
    let f = sample_frame(0, vec![Samples::I16(i16_ramp(300, 0))]);
    write_trc(&p, std::slice::from_ref(&f), "C1").unwrap();
    let back = read_one(&p);
    assert_eq!(back.len(), 1);
    let b = &back[0];
    assert_eq!(b.channels[0].samples, f.channels[0].samples);
    assert_eq!(b.channels[0].name, "C1");
    assert_eq!(b.channels[0].volts_per_code, 1.25e-4);
    assert_eq!(b.channels[0].offset_v, -0.5);
    assert_eq!(b.sample_interval_s, 1e-9);
    assert_eq!(b.first_sample_offset_s, f.first_sample_offset_s);
    assert!((b.trigger_time_s - f.trigger_time_s).abs() < 1e-6);

    // i8 codes stay 8-bit.
    let f8 = sample_frame(
        0,
        vec![Samples::I8(
            (0..200).map(|i| (i % 256 - 128) as i8).collect(),
        )],
    );
    write_trc(&p, std::slice::from_ref(&f8), "ch1").unwrap();
    assert_eq!(read_one(&p)[0].channels[0].samples, f8.channels[0].samples);

    // Volts are quantised to i16 within half a code; a non-numbered name is kept.
    let mut fv = sample_frame(0, vec![]);
    fv.channels.push(Channel::from_volts(
        "stop",
        ChannelRole::Stop,
        pulse_volts(256, 0.0),
    ));
    write_trc(&p, std::slice::from_ref(&fv), "stop").unwrap();
    let b = &read_one(&p)[0];
    assert_eq!(b.channels[0].name, "stop");
    let want = fv.channels[0].volts();
    let lsb = b.channels[0].volts_per_code;
    assert!(lsb < 2.6 / 60000.0, "scale {lsb}");
    assert!(max_abs_diff(&b.channels[0].volts(), &want) <= 0.5 * lsb * 1.001 + 1e-12);
}

#[test]
fn trc_sequence_round_trip_keeps_trigger_times_and_offsets() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("seq.trc");
    let frames: Vec<Frame> = (0..5)
        .map(|k| sample_frame(k, vec![Samples::I16(i16_ramp(128, k as i32))]))
        .collect();
    write_trc(&p, &frames, "CH1").unwrap();
    let back = read_one(&p);
    assert_eq!(back.len(), 5);
    for (a, b) in frames.iter().zip(&back) {
        assert_eq!(a.channels[0].samples, b.channels[0].samples);
        assert_eq!(a.first_sample_offset_s, b.first_sample_offset_s);
        assert!((a.trigger_time_s - b.trigger_time_s).abs() < 1e-6);
    }
    // Frames of unequal length cannot share a sequence file.
    let mut bad = frames.clone();
    bad[3] = sample_frame(3, vec![Samples::I16(i16_ramp(100, 3))]);
    let e = write_trc(&p, &bad, "CH1").unwrap_err().to_string();
    assert!(
        e.contains("seq.trc: cannot write: expected 128 samples"),
        "{e}"
    );
}

#[test]
fn isf_round_trip_and_hand_edited_header() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("w.isf");
    let f = sample_frame(
        0,
        vec![
            Samples::I16(i16_ramp(500, 1)),
            Samples::I16(i16_ramp(500, 2)),
        ],
    );
    write_isf(&p, &f, "CH2").unwrap();
    let b = &read_one(&p)[0];
    assert_eq!(b.channels.len(), 1);
    assert_eq!(b.channels[0].name, "CH2");
    assert_eq!(b.channels[0].samples, f.channels[1].samples);
    assert_eq!(b.channels[0].volts_per_code, 1.25e-4);
    assert_eq!(b.channels[0].offset_v, -0.5);
    assert_eq!(b.sample_interval_s, 1e-9);
    assert_eq!(b.first_sample_offset_s, f.first_sample_offset_s);

    let f8 = sample_frame(
        0,
        vec![Samples::I8((0..256).map(|i| (i - 128) as i8).collect())],
    );
    write_isf(&p, &f8, "1").unwrap();
    assert_eq!(read_one(&p)[0].channels[0].samples, f8.channels[0].samples);

    let mut fv = sample_frame(0, vec![]);
    fv.channels.push(Channel::from_volts(
        "CH1",
        ChannelRole::Unspecified,
        pulse_volts(300, 0.3),
    ));
    write_isf(&p, &fv, "CH1").unwrap();
    let b = &read_one(&p)[0];
    let lsb = b.channels[0].volts_per_code;
    assert!(max_abs_diff(&b.channels[0].volts(), &fv.channels[0].volts()) <= 0.5 * lsb * 1.001);

    // Hand-written: short keys, little-endian unsigned codes, PT_OFF, keys reordered.
    let codes: [u16; 4] = [32768, 33768, 31768, 65535];
    let mut bytes = b":WFMP:BYT_N 2;BIT_N 16;ENC BIN;BN_F RP;BYT_O LSB;WFI \"Ch3, AC coupling, 1 V/div\";\
NR_P 4;PT_F Y;XUN \"s\";XIN 2.0E-9;PT_O 10;XZE -1.0E-8;YUN \"V\";YZE 5.0E-1;YMU 1.0E-3;YOF 3.2768E+4;:CURV #18"
        .to_vec();
    bytes.extend(codes.iter().flat_map(|c| c.to_le_bytes()));
    bytes.push(b'\n');
    let p = dir.path().join("hand.isf");
    std::fs::write(&p, &bytes).unwrap();
    let b = &read_one(&p)[0];
    assert_eq!(b.channels[0].name, "Ch3");
    assert_eq!(
        b.channels[0].samples,
        Samples::I32(codes.iter().map(|&c| c as i32).collect())
    );
    let v = b.channels[0].volts();
    for (got, want) in v.iter().zip([0.5, 1.5, -0.5, 0.5 + 32.767]) {
        assert!((got - want).abs() < 1e-9, "{got} vs {want}");
    }
    assert!((b.first_sample_offset_s - (-1e-8 - 10.0 * 2e-9)).abs() < 1e-20);
    assert_eq!(b.sample_interval_s, 2e-9);
}

#[test]
fn keysight_bin_round_trip_is_exact_for_f32_volts() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("k.bin");
    let mut f = sample_frame(0, vec![]);
    for (i, shift) in [0.0, 3.5].into_iter().enumerate() {
        let v: Vec<f32> = pulse_volts(400, shift).iter().map(|&x| x as f32).collect();
        f.channels.push(Channel {
            name: format!("{}", i + 1),
            role: ChannelRole::Unspecified,
            samples: Samples::F32(v),
            volts_per_code: 1.0,
            offset_v: 0.0,
        });
    }
    write_keysight_bin(&p, &f).unwrap();
    let b = &read_one(&p)[0];
    assert_eq!(b.channels, f.channels);
    assert_eq!(b.sample_interval_s, f.sample_interval_s);
    assert_eq!(b.first_sample_offset_s, f.first_sample_offset_s);
    assert_eq!(b.trigger_time_s, f.trigger_time_s);

    // Integer codes are written as volts in binary32.
    let fi = sample_frame(0, vec![Samples::I16(i16_ramp(100, 0))]);
    write_keysight_bin(&p, &fi).unwrap();
    let b = &read_one(&p)[0];
    let want = fi.channels[0].volts();
    let got = b.channels[0].volts();
    assert!(
        want.iter()
            .zip(&got)
            .all(|(w, g)| (w - g).abs() <= w.abs() * 1e-7)
    );
}

#[test]
fn keysight_bin_segments_become_frames() {
    // Two waveforms with segment indices 1 and 2 (segmented memory): two frames.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("seg.bin");
    let mut f = sample_frame(0, vec![]);
    f.trigger_time_s = 0.0;
    for name in ["1", "1"] {
        f.channels.push(Channel {
            name: name.into(),
            role: ChannelRole::Unspecified,
            samples: Samples::F32((0..50).map(|i| i as f32 / 8.0).collect()),
            volts_per_code: 1.0,
            offset_v: 0.0,
        });
    }
    write_keysight_bin(&p, &f).unwrap();
    let mut bytes = std::fs::read(&p).unwrap();
    let second = 12 + 140 + 12 + 4 * 50;
    for (at, seg, tag) in [(12usize, 1u32, 0.0f64), (second, 2, 2.5e-3)] {
        bytes[at + 128..at + 136].copy_from_slice(&tag.to_le_bytes());
        bytes[at + 136..at + 140].copy_from_slice(&seg.to_le_bytes());
    }
    let frames = read_bytes(&p, &bytes, Format::Auto).unwrap();
    assert_eq!(frames.len(), 2);
    assert_eq!(frames[0].channels.len(), 1);
    assert_eq!(frames[1].trigger_time_s, 2.5e-3);
    assert_eq!(frames[1].sequence, 1);
    assert_eq!(frames[1].channels[0].samples, f.channels[1].samples);
}

#[test]
fn csv_dialects_round_trip_f64_values_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = sample_frame(0, vec![]);
    f.trigger_time_s = 0.0;
    f.first_sample_offset_s = -1.2074500661794662e-7;
    f.channels.push(Channel::from_volts(
        "CH1",
        ChannelRole::Unspecified,
        pulse_volts(600, 0.0),
    ));
    f.channels.push(Channel::from_volts(
        "CH2",
        ChannelRole::Unspecified,
        pulse_volts(600, 7.25),
    ));
    for (dialect, ext) in [
        (Format::TekCsv, "csv"),
        (Format::RigolCsv, "csv"),
        (Format::KeysightCsv, "csv"),
        (Format::GenericCsv, "txt"),
    ] {
        let p = dir.path().join(format!("{}.{ext}", dialect.name()));
        write_csv(&p, &f, dialect).unwrap();
        let head = std::fs::read(&p).unwrap();
        assert_eq!(
            detect_format(&p, &head).unwrap(),
            dialect,
            "{}",
            p.display()
        );
        let b = &read_one(&p)[0];
        assert_eq!(b.channels, f.channels, "{dialect}");
        assert_eq!(
            b.first_sample_offset_s, f.first_sample_offset_s,
            "{dialect}"
        );
        assert!(
            (b.sample_interval_s / 1e-9 - 1.0).abs() < 1e-12,
            "{dialect} dt {}",
            b.sample_interval_s
        );
        assert_eq!(b.trigger_time_s, 0.0);
    }
    let e = write_csv(&dir.path().join("x.csv"), &f, Format::LecroyTrc)
        .unwrap_err()
        .to_string();
    assert!(e.contains("expected a CSV dialect"), "{e}");
}

#[test]
fn hand_made_csv_variants_read() {
    let frames = read_one(&data("tek_old_layout.csv"));
    let f = &frames[0];
    assert_eq!(f.channels[0].name, "CH1");
    assert_eq!(f.len(), 6);
    assert_eq!(f.channels[0].volts(), vec![0.0, 0.04, 0.08, 1.2, 0.4, 0.0]);
    assert!((f.sample_interval_s - 2e-9).abs() < 1e-20);
    assert_eq!(f.first_sample_offset_s, -4e-9);

    // Semicolons, decimal commas, a unit in brackets, comments.
    let f = &read_one(&data("generic_semicolon.csv"))[0];
    assert_eq!(f.channel_names(), vec!["start", "stop"]);
    assert!((f.sample_interval_s - 1e-9).abs() < 1e-21);
    assert!((f.first_sample_offset_s + 2e-9).abs() < 1e-21);
    assert!(
        (f.channels[1].volts()[2] - 0.0125).abs() < 1e-15,
        "mV scaled to volts"
    );

    // Tab-separated, time in microseconds.
    let f = &read_one(&data("generic_tab_us.tsv"))[0];
    assert!((f.sample_interval_s - 0.5e-6).abs() < 1e-18);
    assert_eq!(f.channel_names(), vec!["CH1"]);

    // A row-number column is not a channel; time in nanoseconds.
    let f = &read_one(&data("generic_index_ns.csv"))[0];
    assert_eq!(f.channel_names(), vec!["CH1"]);
    assert!((f.sample_interval_s - 1e-9).abs() < 1e-21);

    // Rigol with index offset.
    let f = &read_one(&data("rigol.csv"))[0];
    assert_eq!(f.channel_names(), vec!["CH1", "CH2"]);
    assert_eq!(f.sample_interval_s, 2e-9);
    assert!((f.first_sample_offset_s - (-6e-6 + 2.0 * 2e-9)).abs() < 1e-20);
}

#[test]
fn recording_round_trip_is_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("r.twr");
    let mut frames = vec![
        sample_frame(
            10,
            vec![Samples::I16(i16_ramp(64, 0)), Samples::I8(vec![-3; 64])],
        ),
        sample_frame(
            11,
            vec![Samples::I32((0..64).map(|i| i * 100_000).collect())],
        ),
        sample_frame(
            12,
            vec![Samples::F32((0..64).map(|i| i as f32 * 0.1).collect())],
        ),
    ];
    let mut f64_frame = sample_frame(13, vec![]);
    f64_frame.channels.push(Channel::from_volts(
        "avg",
        ChannelRole::Stop,
        (0..64).map(|i| (i as f64).sqrt() / 3.0).collect(),
    ));
    f64_frame.channels.push(Channel::from_volts(
        "ref",
        ChannelRole::Start,
        (0..64).map(|i| -(i as f64) / 7.0).collect(),
    ));
    f64_frame.laser_off = true;
    frames.push(f64_frame);
    write_recording(&p, &frames).unwrap();
    let back = read_one(&p);
    assert_eq!(
        back, frames,
        "recorded ids, roles and every sample type survive"
    );

    // The streaming writer produces the same bytes.
    let mut w = RecordingWriter::new(Vec::new()).unwrap();
    for f in &frames {
        w.write_frame(f).unwrap();
    }
    assert_eq!(w.frames_written(), 4);
    let bytes = w.finish().unwrap();
    assert_eq!(bytes, std::fs::read(&p).unwrap());
    let streamed: Vec<Frame> = RecordingReader::new(bytes.as_slice(), Path::new("mem.twr"))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(streamed, frames);
    assert_eq!(
        detect_format(Path::new("x.dat"), &bytes).unwrap(),
        Format::Tofwave
    );
}

// ---------------------------------------------------------------- directories

#[test]
fn directory_reads_in_name_order_with_consecutive_sequence_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let seq: Vec<Frame> = (0..3)
        .map(|k| sample_frame(k, vec![Samples::I16(i16_ramp(32, k as i32))]))
        .collect();
    write_trc(&d.join("b_seq.trc"), &seq, "CH1").unwrap();
    let mut single = sample_frame(0, vec![]);
    single.channels.push(Channel::from_volts(
        "CH1",
        ChannelRole::Unspecified,
        vec![0.0, 1.0, 0.5],
    ));
    write_csv(&d.join("a_first.csv"), &single, Format::GenericCsv).unwrap();
    write_csv(&d.join(".hidden.csv"), &single, Format::GenericCsv).unwrap();
    std::fs::write(d.join("notes.md"), "not a capture").unwrap();
    let mut rec = sample_frame(77, vec![Samples::I8(vec![1, 2, 3])]);
    rec.sensor_id = "lidar-7".into();
    write_recording(&d.join("c_rec.twr"), std::slice::from_ref(&rec)).unwrap();
    write_isf(&d.join("d_last.ISF"), &single, "CH1").unwrap();

    let opts = ReadOptions {
        format: Format::Auto,
        sensor_id: "bench".into(),
    };
    // A file before the directory: numbering continues across both.
    let extra = d.join("b_seq.trc");
    let all = read_paths(&[extra.clone(), d.to_path_buf()], &opts).unwrap();
    let ids: Vec<(String, u64, usize)> = all
        .iter()
        .map(|f| (f.sensor_id.clone(), f.sequence, f.len()))
        .collect();
    let b = |s: u64| ("bench".to_string(), s, 32);
    assert_eq!(
        ids,
        vec![
            b(0),
            b(1),
            b(2),
            ("bench".into(), 3, 3),
            b(4),
            b(5),
            b(6),
            ("lidar-7".into(), 77, 3), // recordings keep their ids
            ("bench".into(), 8, 3),
        ]
    );
    // The lazy source yields the same frames.
    let lazy: Vec<Frame> = frames(&[extra, d.to_path_buf()], &opts)
        .unwrap()
        .map(Result::unwrap)
        .collect();
    assert_eq!(lazy, all);

    let empty = tempfile::tempdir().unwrap();
    std::fs::write(empty.path().join("readme.md"), "x").unwrap();
    let e = read_err(empty.path());
    assert!(
        e.contains("expected capture files") && e.contains("found none"),
        "{e}"
    );
}

#[test]
fn forced_format_overrides_detection() {
    let opts = ReadOptions {
        format: Format::KeysightBin,
        sensor_id: "x".into(),
    };
    let e = read_paths(&[replay("lecroy_4.trc")], &opts)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("lecroy_4.trc: byte 0: expected \"AG\" + 2 version digits"),
        "{e}"
    );
}

#[test]
fn format_is_detected_from_content_not_extension() {
    let dir = tempfile::tempdir().unwrap();
    let f = sample_frame(0, vec![Samples::I16(i16_ramp(50, 0))]);
    let cases: Vec<(Format, PathBuf)> = vec![
        (Format::LecroyTrc, replay("lecroy_4.trc")),
        (Format::KeysightBin, replay("agilent_1.bin")),
        (Format::TekIsf, dir.path().join("a")),
        (Format::Tofwave, dir.path().join("b")),
        (Format::TekCsv, dir.path().join("c")),
        (Format::RigolCsv, dir.path().join("d")),
        (Format::KeysightCsv, dir.path().join("e")),
        (Format::GenericCsv, dir.path().join("f")),
    ];
    for (fmt, p) in &cases {
        match fmt {
            Format::TekIsf => write_isf(p, &f, "CH1").unwrap(),
            Format::Tofwave => write_recording(p, std::slice::from_ref(&f)).unwrap(),
            Format::LecroyTrc | Format::KeysightBin => {}
            d => write_csv(p, &f, *d).unwrap(),
        }
        let bytes = std::fs::read(p).unwrap();
        // Misleading extensions: the content decides.
        for name in ["capture.dat", "capture.bin", "capture.csv"] {
            let head = &bytes[..bytes.len().min(4096)];
            assert_eq!(
                detect_format(Path::new(name), head).unwrap(),
                *fmt,
                "{name} holding {fmt}"
            );
        }
        let frames = read_bytes(Path::new("capture.dat"), &bytes, Format::Auto).unwrap();
        assert!(!frames.is_empty());
    }
}

// ---------------------------------------------------------------- malformed input

fn write_tmp(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn truncated_binary_files_give_offset_errors_never_panics() {
    let dir = tempfile::tempdir().unwrap();
    let isf = dir.path().join("w.isf");
    write_isf(
        &isf,
        &sample_frame(0, vec![Samples::I16(i16_ramp(200, 0))]),
        "CH1",
    )
    .unwrap();
    let twr = dir.path().join("w.twr");
    let rec_frames: Vec<Frame> = (0..3)
        .map(|k| sample_frame(k, vec![Samples::I16(i16_ramp(40, 0))]))
        .collect();
    write_recording(&twr, &rec_frames).unwrap();
    for path in [
        replay("lecroy_4.trc"),
        replay("lecroy_3.trc"),
        replay("agilent_1.bin"),
        isf,
        twr,
    ] {
        let good = std::fs::read(&path).unwrap();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let is_twr = name.ends_with(".twr");
        // Every cut in the first kB, then every 37th byte.
        let cuts = (0..good.len().min(1024)).chain((1024..good.len()).step_by(37));
        for cut in cuts {
            match read_bytes(&path, &good[..cut], Format::Auto) {
                Err(e) => {
                    let msg = e.to_string();
                    assert!(msg.contains(&name), "{msg}");
                    assert!(
                        msg.contains("byte ") && msg.contains("expected"),
                        "cut {cut}: {msg}"
                    );
                }
                // A recording cut exactly between frames is a valid shorter recording.
                Ok(frames) if is_twr => assert!(frames.len() < rec_frames.len()),
                // The ISF writer ends with a newline that readers may drop.
                Ok(_) if name.ends_with(".isf") && cut == good.len() - 1 => {}
                Ok(frames) => panic!("{name} cut at {cut} read as {} frames", frames.len()),
            }
        }
    }
    // One cut explained precisely: lecroy_4 has WAVE_ARRAY_1 (1004 bytes) at byte 357.
    let good = std::fs::read(replay("lecroy_4.trc")).unwrap();
    let p = write_tmp(dir.path(), "cut.trc", &good[..800]);
    let e = read_err(&p);
    assert!(
        e.contains(
            "cut.trc: byte 357: expected WAVE_ARRAY_1 (samples) (1004 bytes), found only 443 bytes"
        ),
        "{e}"
    );
    let p = write_tmp(
        dir.path(),
        "cut.bin",
        &std::fs::read(replay("agilent_1.bin")).unwrap()[..5000],
    );
    let e = read_err(&p);
    assert!(e.contains("cut.bin: byte 0: expected the file size declared at byte 4 (8164 bytes), found only 5000"), "{e}");
}

#[test]
fn wrong_magic_and_length_mismatches_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read(replay("lecroy_4.trc")).unwrap();

    let mut bad = good.clone();
    bad[11 + 7] = b'X'; // WAVEDESX
    let e = read_err(&write_tmp(dir.path(), "magic.trc", &bad));
    assert!(
        e.contains("magic.trc: byte 0: expected \"WAVEDESC\""),
        "{e}"
    );

    let mut bad = good.clone();
    bad[11 + 116..11 + 120].copy_from_slice(&501i32.to_le_bytes()); // WAVE_ARRAY_COUNT
    let e = read_err(&write_tmp(dir.path(), "count.trc", &bad));
    assert!(
        e.contains("count.trc: byte 71: expected WAVE_ARRAY_1 length = WAVE_ARRAY_COUNT (501) x 2 bytes, found 1004 bytes"),
        "{e}"
    );

    let mut bad = good.clone();
    bad[11 + 60..11 + 64].copy_from_slice(&i32::MAX.to_le_bytes()); // huge WAVE_ARRAY_1 length
    let e = read_err(&write_tmp(dir.path(), "huge.trc", &bad));
    assert!(
        e.contains("huge.trc: byte 357: expected WAVE_ARRAY_1 (samples) (2147483647 bytes)"),
        "{e}"
    );

    let mut bad = good.clone();
    bad[11 + 32] = 7; // COMM_TYPE
    let e = read_err(&write_tmp(dir.path(), "type.trc", &bad));
    assert!(
        e.contains("type.trc: byte 43: expected COMM_TYPE 0 (i8) or 1 (i16), found 7"),
        "{e}"
    );

    let agilent = std::fs::read(replay("agilent_1.bin")).unwrap();
    let mut bad = agilent.clone();
    bad[0] = b'X';
    let e = read_err(&write_tmp(dir.path(), "magic.bin", &bad));
    assert!(
        e.contains("magic.bin: byte 0: expected \"AG\" + 2 version digits"),
        "{e}"
    );
    let mut bad = agilent.clone();
    bad[12 + 12..12 + 16].copy_from_slice(&1999u32.to_le_bytes()); // points
    let e = read_err(&write_tmp(dir.path(), "points.bin", &bad));
    assert!(
        e.contains("points.bin: byte 160: expected 1999 points x 4 bytes = 7996 bytes"),
        "{e}"
    );
    assert!(e.contains("found 8000 bytes"), "{e}");

    let e = read_err(&data("isf_nr_pt_mismatch.isf"));
    assert!(
        e.contains("isf_nr_pt_mismatch.isf: byte ")
            && e.contains("expected a curve of NR_PT (5) x BYT_NR (2) bytes, found 8 bytes"),
        "{e}"
    );

    let mut rec = Vec::new();
    let mut w = RecordingWriter::new(&mut rec).unwrap();
    w.write_frame(&sample_frame(0, vec![Samples::I8(vec![1, 2])]))
        .unwrap();
    drop(w);
    let mut bad = rec.clone();
    bad[12] = 9; // version
    let e = read_err(&write_tmp(dir.path(), "v.twr", &bad));
    assert!(
        e.contains("v.twr: byte 12: expected recording format version 1, found version 9"),
        "{e}"
    );
    let mut bad = rec.clone();
    bad[0] = b'X';
    let e = read_err(&write_tmp(dir.path(), "m.twr", &bad));
    assert!(
        e.contains("m.twr: byte 0: expected the tofwave recording magic"),
        "{e}"
    );
}

/// A stream of unknown size whose length prefix claims almost 1 GiB but
/// holds 3 bytes: truncation is reported from the bytes actually read, with
/// no buffer sized by the claim (found by fuzzing, `fuzz/README.md`).
#[test]
fn streamed_recording_with_a_huge_length_prefix_is_truncated_not_allocated() {
    let mut rec = RecordingWriter::new(Vec::new()).unwrap().finish().unwrap();
    // varint (1 << 30) - 1, then 3 bytes of "message".
    rec.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0x03, 1, 2, 3]);
    let e = RecordingReader::new(rec.as_slice(), Path::new("pipe.twr"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap_err();
    match &e {
        CaptureError::Truncated {
            offset,
            needed,
            available,
            ..
        } => assert_eq!((*offset, *needed, *available), (21, (1 << 30) - 1, 3), "{e}"),
        other => panic!("expected truncation, got {other}"),
    }
    assert!(e.to_string().starts_with("pipe.twr: byte 21: expected frame 0"), "{e}");
}

/// Finite header numbers or readings that overflow once combined (a kV
/// reading of 1e308, ISF `XINCR x PT_OFF`, Rigol `Start + index x
/// Increment`) are refused with the line or byte and the field, never
/// returned as infinite times or volts (found by fuzzing, `fuzz/artifacts/`).
#[test]
fn overflowing_scales_and_offsets_are_refused() {
    let art = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/artifacts");
    let cases: &[(&str, Format, &str)] = &[
        (
            "capture_csv/kv-overflow-to-inf.csv",
            Format::GenericCsv,
            "line 2, column 2: expected a value for CH1 that is finite in volts",
        ),
        (
            "capture_csv/rigol-start-overflow.csv",
            Format::RigolCsv,
            "line 3, column 1: expected a first sample index whose time",
        ),
        (
            "capture_isf/pt-off-overflow.isf",
            Format::TekIsf,
            "expected XZERO - XINCR x PT_OFF finite",
        ),
        (
            "capture_isf/yoff-overflow.isf",
            Format::TekIsf,
            "expected YZERO - YMULT x YOFF finite",
        ),
    ];
    for (name, format, want) in cases {
        let data = std::fs::read(art.join(name)).unwrap();
        let e = read_bytes(Path::new(name), &data, *format).unwrap_err().to_string();
        assert!(e.starts_with(name) && e.contains(want), "{e}");
    }
}

#[test]
fn csv_errors_name_line_and_column() {
    let cases: &[(&str, &str)] = &[
        (
            "non_numeric.csv",
            "non_numeric.csv: line 5, column 3: expected a finite number for CH2, found \"abc\"",
        ),
        (
            "missing_cell.csv",
            "missing_cell.csv: line 4, column 3: expected a value for CH2, found end of row",
        ),
        (
            "no_channel.csv",
            "no_channel.csv: line 1: expected at least one channel column",
        ),
        (
            "header_only.csv",
            "header_only.csv: line 1: expected at least 2 data rows after the header (to know the sample interval), found none",
        ),
        (
            "no_time_column.csv",
            "no_time_column.csv: line 1: expected a header row with a time column",
        ),
        (
            "nonuniform.csv",
            "nonuniform.csv: line 6: expected a time step of",
        ),
        (
            "comments_only.csv",
            "comments_only.csv: line 3: expected a CSV header row, found only blank or comment lines",
        ),
        (
            "tek_short.csv",
            "tek_short.csv: line 2: expected 5 data rows as this Record Length says, found 3 rows",
        ),
        (
            "tek_no_time.csv",
            "tek_no_time.csv: line 4: expected a \"TIME,CH1,...\" column header",
        ),
        (
            "rigol_gap.csv",
            "rigol_gap.csv: line 5, column 1: expected sample index 2, found 3",
        ),
        (
            "bad_unit.csv",
            "bad_unit.csv: line 1, column 1: expected a time unit s, ms, us, ns or ps, found \"time (h)\"",
        ),
    ];
    for (file, want) in cases {
        let e = read_err(&data(file));
        assert!(e.contains(want), "{file}: {e}");
    }
}

#[test]
fn empty_and_unrecognised_files() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["zero.trc", "zero.csv", "zero.twr", "zero.bin", "zero.isf"] {
        let e = read_err(&write_tmp(dir.path(), name, b""));
        assert!(
            e.contains(&format!(
                "{name}: byte 0: expected capture data, found an empty file"
            )),
            "{e}"
        );
    }
    let e = read_err(&write_tmp(dir.path(), "blank.csv", b"\n\r\n  \n"));
    assert!(
        e.contains("blank.csv: line 4: expected a CSV header row"),
        "{e}"
    );
    let e = read_err(&write_tmp(
        dir.path(),
        "mystery.dat",
        &[0x7f, 0x45, 0x4c, 0x46, 0, 1, 2],
    ));
    assert!(
        e.contains("mystery.dat: byte 0: expected a capture file (LeCroy .trc"),
        "{e}"
    );
    assert!(e.contains("found \"\\x7fELF\\x00\\x01\\x02\""), "{e}");
    let e = read_err(&write_tmp(
        dir.path(),
        "prose.dat",
        b"hello world\nthis is not a capture\n",
    ));
    assert!(
        e.contains("prose.dat: byte 0: expected a capture file"),
        "{e}"
    );
    let e = read_err(&dir.path().join("missing.trc"));
    assert!(e.contains("missing.trc: byte 0: open failed"), "{e}");
}

/// Random corruption of every real file (and of written ISF/recording/CSV
/// files) never panics: each read either succeeds or returns an error.
/// Fixed seed; 400 corruptions per file of 1-16 random bytes, plus random
/// truncation, keep the run well under a second in release.
#[test]
fn random_corruption_never_panics() {
    let dir = tempfile::tempdir().unwrap();
    let isf = dir.path().join("w.isf");
    write_isf(
        &isf,
        &sample_frame(0, vec![Samples::I16(i16_ramp(200, 0))]),
        "CH1",
    )
    .unwrap();
    let twr = dir.path().join("w.twr");
    write_recording(
        &twr,
        &[sample_frame(0, vec![Samples::I16(i16_ramp(40, 0))])],
    )
    .unwrap();
    let csv = dir.path().join("w.csv");
    let mut f = sample_frame(0, vec![]);
    f.channels.push(Channel::from_volts(
        "CH1",
        ChannelRole::Unspecified,
        pulse_volts(100, 0.0),
    ));
    write_csv(&csv, &f, Format::TekCsv).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0x7e57_ca97);
    let mut auto_errors = 0usize;
    let mut total = 0usize;
    for path in [
        replay("lecroy_4.trc"),
        replay("lecroy_3.trc"),
        replay("lecroy_2.trc"),
        replay("agilent_1.bin"),
        isf,
        twr,
        csv,
    ] {
        let good = std::fs::read(&path).unwrap();
        for i in 0..400 {
            let mut bad = good.clone();
            // Headers hold most of the structure: aim half the hits at the first 512 bytes.
            let span = if i % 2 == 0 {
                good.len().min(512)
            } else {
                good.len()
            };
            for _ in 0..rng.random_range(1..=16) {
                let at = rng.random_range(0..span);
                bad[at] = rng.random();
            }
            if i % 5 == 0 {
                bad.truncate(rng.random_range(0..=bad.len()));
            }
            total += 1;
            if read_bytes(&path, &bad, Format::Auto).is_err() {
                auto_errors += 1;
            }
            // Every parser, forced onto any bytes, must fail cleanly or succeed.
            for fmt in Format::ALL_NAMES
                .iter()
                .skip(1)
                .map(|n| n.parse::<Format>().unwrap())
            {
                let _ = read_bytes(&path, &bad, fmt);
            }
        }
    }
    // The corruption is real: a good share of files must be refused.
    assert!(
        auto_errors * 10 > total,
        "{auto_errors} errors in {total} corrupted files"
    );
}

#[test]
fn capture_error_variants_are_matchable() {
    let e = read_bytes(Path::new("x.trc"), b"", Format::Auto).unwrap_err();
    assert!(matches!(e, CaptureError::Empty { .. }));
    let e = read_bytes(Path::new("x.trc"), b"WAVEDESC", Format::Auto).unwrap_err();
    assert!(
        matches!(
            e,
            CaptureError::Truncated {
                offset: 0,
                needed: 346,
                available: 8,
                ..
            }
        ),
        "{e:?}"
    );
}
