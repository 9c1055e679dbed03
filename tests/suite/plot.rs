//! `tofwave plot`: a shipped capture drawn to PNG and SVG, checked for what
//! the plot promises (the trace across the plot, a marker and a label for
//! every return `process` reports), and its errors.

use crate::common::{replay_path, tofwave};
use tofwave::plot::{RETURN_RGB, THRESHOLD_RGB, TRACE_RGB};

/// The returns `process` reports for `input`'s first frame.
fn first_report_returns(input: &str) -> Vec<serde_json::Value> {
    let (code, reports, err) = tofwave(&["process", "--input", input]);
    assert_eq!(code, 0, "{err}");
    reports[0]["returns"].as_array().expect("returns").clone()
}

fn label(r: &serde_json::Value) -> String {
    format!(
        "{:.3} m ± {:.3}, {:.1} dB",
        r["range_m"].as_f64().unwrap(),
        r["range_sigma_m"].as_f64().unwrap(),
        r["snr_db"].as_f64().unwrap()
    )
}

fn hex((r, g, b): (u8, u8, u8)) -> String {
    format!("#{r:02X}{g:02X}{b:02X}")
}

#[test]
fn plot_svg_marks_and_labels_every_return_at_its_reported_range() {
    let dir = tempfile::tempdir().unwrap();
    let input = replay_path("lecroy_4.trc");
    let input = input.to_str().unwrap();
    let returns = first_report_returns(input);
    assert!(!returns.is_empty(), "lecroy_4.trc holds one strong return");
    let out = dir.path().join("f.svg");
    let (code, _, err) = tofwave(&["plot", "--input", input, "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains(&format!("{} returns marked", returns.len())), "{err}");
    let svg = std::fs::read_to_string(&out).unwrap();
    assert!(svg.starts_with("<svg"), "{}", &svg[..100.min(svg.len())]);
    for r in &returns {
        let l = label(r);
        assert!(svg.contains(&l), "no label {l:?} in the SVG");
    }
    // One filled triangle per return, plus the legend's.
    let red = hex(RETURN_RGB);
    let triangles = svg.lines().filter(|l| l.contains("<polygon") && l.contains(&red)).count();
    assert_eq!(triangles, returns.len() + 1, "return markers");
    // The trace is one polyline in the trace colour with a point per sample (1 frame of 502 samples... at least hundreds).
    let trace = svg
        .lines()
        .find(|l| l.contains("<polyline") && l.contains(&hex(TRACE_RGB)))
        .expect("a trace polyline");
    assert!(trace.matches(',').count() > 400, "trace points: {}", trace.matches(',').count());
    assert!(svg.contains(&hex(THRESHOLD_RGB)), "threshold line");
    assert!(svg.contains("noise gates"), "gate legend");
}

#[test]
fn plot_png_has_the_asked_size_and_the_trace_across_it() {
    let dir = tempfile::tempdir().unwrap();
    let input = replay_path("lecroy_4.trc");
    let out = dir.path().join("f.png");
    let (code, _, err) = tofwave(&[
        "plot",
        "--input",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "900",
        "--height",
        "500",
    ]);
    assert_eq!(code, 0, "{err}");
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&out).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (900, 500));
    assert_eq!(info.color_type, png::ColorType::Rgb);
    let px = |x: usize, y: usize| {
        let i = (y * 900 + x) * 3;
        (buf[i], buf[i + 1], buf[i + 2])
    };
    // Columns holding a pixel of the trace colour: the trace runs across the
    // plot area (the y-label area is 60 px, margins 8 px).
    let columns = (0..900).filter(|&x| (0..500).any(|y| px(x, y) == TRACE_RGB)).count();
    assert!(columns > 700, "trace in {columns} of 900 columns");
    let count = |c: (u8, u8, u8)| (0..500).flat_map(|y| (0..900).map(move |x| (x, y))).filter(|&(x, y)| px(x, y) == c).count();
    assert!(count(RETURN_RGB) > 30, "return marker pixels: {}", count(RETURN_RGB));
    assert!(count(THRESHOLD_RGB) > 300, "threshold pixels: {}", count(THRESHOLD_RGB));
    // Text is drawn (the embedded font): dark pixels at the caption's height.
    let dark = (0..900).filter(|&x| (0..20).any(|y| { let (r, g, b) = px(x, y); r < 90 && g < 90 && b < 90 })).count();
    assert!(dark > 50, "caption pixels: {dark}");
}

#[test]
fn plot_stacks_a_frame_range_and_refuses_what_it_cannot_draw() {
    let dir = tempfile::tempdir().unwrap();
    let three = replay_path("lecroy_3.trc");
    let three = three.to_str().unwrap();
    let out = dir.path().join("r.svg");
    let (code, _, err) = tofwave(&["plot", "--input", three, "--frame", "2..4", "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let svg = std::fs::read_to_string(&out).unwrap();
    for k in 2..=4 {
        assert!(svg.contains(&format!("frame {k}:")), "frame {k} row");
    }
    assert!(!svg.contains("frame 1:") && !svg.contains("frame 5:"));
    let one = replay_path("lecroy_4.trc");
    let one = one.to_str().unwrap();
    let bad = dir.path().join("f.jpg");
    let (code, _, err) = tofwave(&["plot", "--input", one, "--out", bad.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("f.jpg") && err.contains(".png or .svg"), "{err}");
    let png = dir.path().join("f.png");
    let (code, _, err) = tofwave(&["plot", "--input", one, "--frame", "5", "--out", png.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("--frame 5: the input has 1 frames (0..=0)"), "{err}");
    let (code, _, err) = tofwave(&["plot", "--input", one, "--width", "50", "--out", png.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("--width 50: allowed 200..=8000 pixels"), "{err}");
    let (code, _, err) = tofwave(&["plot", "--input", three, "--frame", "0..19", "--out", png.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("20 frames selected, at most 16"), "{err}");
}
