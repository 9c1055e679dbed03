//! Static waveform plots (`tofwave plot`): a frame's stop trace (and start
//! channel) with the noise gates shaded, the noise mean, each detected return
//! marked and labelled with its range and SNR; below it the detector output
//! with the threshold. PNG or SVG, chosen by the output's extension.
//!
//! The frames run through the very pipeline `process` builds from the scene
//! (an observer copies what the stages computed), so a plot shows what the
//! reports say, not a re-derivation.

use crate::detect::gates::Gates;
use crate::frame::{Frame, Report};
use crate::pipeline::{FrameError, Pipeline, Work};
use crate::scene::Scene;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::ops::{Range, RangeInclusive};
use std::path::Path;
use std::sync::{Arc, Mutex, OnceLock};

/// Largest number of frames one plot stacks (one row each).
pub const MAX_FRAMES: usize = 16;
/// Allowed image width and height, pixels.
pub const SIZE_PX: RangeInclusive<u32> = 200..=8000;

/// Colour of the stop trace (tests look for it in PNGs).
pub const TRACE_RGB: (u8, u8, u8) = (31, 119, 180);
/// Colour of the detected-return markers and labels.
pub const RETURN_RGB: (u8, u8, u8) = (214, 39, 40);
/// Colour of the threshold line.
pub const THRESHOLD_RGB: (u8, u8, u8) = (255, 127, 14);
/// Colour of the start channel.
const START_RGB: (u8, u8, u8) = (127, 127, 127);
/// Colour of the detector output.
const DETECTOR_RGB: (u8, u8, u8) = (44, 160, 44);
/// Fill of the noise gates.
const GATE_RGB: (u8, u8, u8) = (222, 222, 222);
/// Fill of the range gate.
const RANGE_GATE_RGB: (u8, u8, u8) = (236, 246, 236);

/// Why a plot could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The output's extension names no supported format.
    #[error("--out {path}: the extension must be .png or .svg")]
    Format {
        /// The output path as given.
        path: String,
    },
    /// Width or height outside [`SIZE_PX`].
    #[error("--{which} {value}: allowed {}..={} pixels", SIZE_PX.start(), SIZE_PX.end())]
    Size {
        /// `width` or `height`.
        which: &'static str,
        /// The value given.
        value: u32,
    },
    /// No processed frame fell in the requested range.
    #[error("--frame {wanted}: the input has {frames} frames (0..={last}){why}", last = .frames.saturating_sub(1))]
    NoFrame {
        /// The range as the user wrote it.
        wanted: String,
        /// Frames read.
        frames: usize,
        /// Extra explanation (refused frames), or empty.
        why: String,
    },
    /// More frames than [`MAX_FRAMES`] selected.
    #[error("--frame {wanted}: {count} frames selected, at most {MAX_FRAMES} fit one plot")]
    TooMany {
        /// The range as the user wrote it.
        wanted: String,
        /// Frames selected.
        count: usize,
    },
    /// Drawing failed.
    #[error("drawing the plot: {0}")]
    Draw(String),
    /// Writing the file failed (the OS error follows in the chain).
    #[error("cannot write {path}")]
    Write {
        /// The output file.
        path: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
}

/// Output format, from the extension of the output path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlotFormat {
    /// Portable Network Graphics (8-bit RGB).
    Png,
    /// Scalable Vector Graphics (text stays text).
    Svg,
}

impl PlotFormat {
    /// The format `path`'s extension names.
    pub fn from_path(path: &Path) -> Result<PlotFormat, PlotError> {
        match path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
            Some("png") => Ok(PlotFormat::Png),
            Some("svg") => Ok(PlotFormat::Svg),
            _ => Err(PlotError::Format { path: path.display().to_string() }),
        }
    }
}

/// Which frames to plot: positions in input order, 0-based, inclusive.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameSelection {
    /// First position.
    pub first: usize,
    /// Last position.
    pub last: usize,
}

impl std::str::FromStr for FrameSelection {
    type Err = String;
    /// `K` or `A..B` / `A-B` (inclusive).
    fn from_str(s: &str) -> Result<FrameSelection, String> {
        let bad = || format!("{s:?}: expected a frame number K (0-based) or a range A..B (inclusive)");
        let num = |t: &str| t.trim().parse::<usize>().map_err(|_| bad());
        let (a, b) = match s.split_once("..").or_else(|| s.split_once('-')) {
            Some((a, b)) => (num(a)?, num(b.trim_start_matches('='))?),
            None => {
                let k = num(s)?;
                (k, k)
            }
        };
        if b < a {
            return Err(format!("{s:?}: the range ends before it starts"));
        }
        Ok(FrameSelection { first: a, last: b })
    }
}

impl std::fmt::Display for FrameSelection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.first == self.last {
            write!(f, "{}", self.first)
        } else {
            write!(f, "{}..{}", self.first, self.last)
        }
    }
}

/// What one processed frame (or averaged group) looked like to the pipeline.
#[derive(Debug, Clone)]
pub struct FrameView {
    /// Input position of the group's last frame.
    pub position: usize,
    /// Time of sample 0 relative to the trigger, s.
    pub first_sample_offset_s: f64,
    /// Sampling period, s.
    pub sample_interval_s: f64,
    /// Stop channel name.
    pub stop_name: String,
    /// Stop channel, volts (after the baseline, denoise and averaging stages).
    pub stop_v: Vec<f64>,
    /// Start channel name and volts, when the frame has one.
    pub start: Option<(String, Vec<f64>)>,
    /// Detector output by peak position, volts-equivalent (mean removed).
    pub detector_output: Vec<f64>,
    /// Detections: positions in `detector_output` above the threshold
    /// (peaks of the detector output; timing then finds each pulse's instant).
    pub detections: Vec<usize>,
    /// Range and noise gates.
    pub gates: Gates,
    /// The report of this frame.
    pub report: Report,
}

impl FrameView {
    fn from_work(w: &Work, position: usize) -> FrameView {
        let f = &w.frame;
        let start = w.source.start.map(|i| (f.channels[i].name.clone(), f.channels[i].volts()));
        FrameView {
            position,
            first_sample_offset_s: f.first_sample_offset_s,
            sample_interval_s: f.sample_interval_s,
            stop_name: f.channels[w.source.stop].name.clone(),
            stop_v: w.buffers.stop_v.clone(),
            start,
            detector_output: w.buffers.detector_output.clone(),
            detections: w.buffers.detections.clone(),
            gates: w.noise.gates.clone(),
            report: w.report.clone(),
        }
    }

    /// Time of sample `i` relative to the trigger, ns.
    fn t_ns(&self, i: f64) -> f64 {
        (self.first_sample_offset_s + i * self.sample_interval_s) * 1e9
    }
}

/// Frames processed and kept for a plot.
#[derive(Debug, Default)]
pub struct Processed {
    /// The selected frames, in input order.
    pub views: Vec<FrameView>,
    /// Frames read (stops after the last selected one).
    pub frames_read: usize,
    /// Frames the pipeline refused, with why.
    pub refused: Vec<FrameError>,
}

/// Runs `frames` through the scene's pipeline up to the selection's last
/// position and keeps the selected frames' views (an averaged group is kept
/// when any of its frames is selected).
pub fn process<I, E>(scene: &Scene, sensor: &str, frames: I, sel: &FrameSelection) -> Result<Processed, E>
where
    I: IntoIterator<Item = Result<Frame, E>>,
{
    let mut pipeline = Pipeline::new(scene, sensor);
    let position = Arc::new(Mutex::new(0usize));
    let kept: Arc<Mutex<Vec<FrameView>>> = Arc::default();
    let (p, k, s) = (position.clone(), kept.clone(), sel.clone());
    pipeline.set_observer(Box::new(move |w: &Work| {
        let last = *p.lock().expect("not poisoned");
        let first = last + 1 - (w.source.frames_averaged.max(1) as usize).min(last + 1);
        if first <= s.last && last >= s.first {
            k.lock().expect("not poisoned").push(FrameView::from_work(w, last));
        }
    }));
    let mut out = Processed::default();
    let mut reports = Vec::new();
    for (i, frame) in frames.into_iter().enumerate() {
        if i > sel.last {
            break;
        }
        let frame = frame?;
        *position.lock().expect("not poisoned") = i;
        out.frames_read = i + 1;
        if let Err(e) = pipeline.push(frame, &mut reports) {
            out.refused.push(e);
        }
        pipeline.recycle(&mut reports);
    }
    pipeline.flush(&mut reports);
    drop(pipeline);
    out.views = std::mem::take(&mut *kept.lock().expect("not poisoned"));
    Ok(out)
}

/// Checks that something was selected and that it fits one plot.
pub fn check_selection(p: &Processed, sel: &FrameSelection) -> Result<(), PlotError> {
    if p.views.is_empty() {
        let why = if p.refused.is_empty() {
            String::new()
        } else {
            format!("; {} frames were refused, the last: {}", p.refused.len(), p.refused[p.refused.len() - 1])
        };
        return Err(PlotError::NoFrame { wanted: sel.to_string(), frames: p.frames_read, why });
    }
    if p.views.len() > MAX_FRAMES {
        return Err(PlotError::TooMany { wanted: sel.to_string(), count: p.views.len() });
    }
    Ok(())
}

/// Image options.
#[derive(Debug, Clone)]
pub struct PlotOptions {
    /// Width, pixels.
    pub width_px: u32,
    /// Height, pixels.
    pub height_px: u32,
    /// Title shown over the first frame (the input's name).
    pub title: String,
}

/// Registers the embedded font once (PNG labels need a font; SVG text is
/// rendered by the viewer, but plotters measures it with the same font).
pub(crate) fn font_ready() -> Result<(), PlotError> {
    static FONT: OnceLock<bool> = OnceLock::new();
    let ok = *FONT.get_or_init(|| {
        plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../assets/fonts/DejaVuSans-subset.ttf"),
        )
        .is_ok()
    });
    if ok { Ok(()) } else { Err(PlotError::Draw("the embedded font did not load".into())) }
}

fn draw_err<E: std::fmt::Debug>(e: E) -> PlotError {
    PlotError::Draw(format!("{e:?}"))
}

/// Draws `views` (one row each) and writes `path` in `format`.
pub fn render(views: &[FrameView], path: &Path, format: PlotFormat, opts: &PlotOptions) -> Result<(), PlotError> {
    for (which, value) in [("width", opts.width_px), ("height", opts.height_px)] {
        if !SIZE_PX.contains(&value) {
            return Err(PlotError::Size { which, value });
        }
    }
    font_ready()?;
    let size = (opts.width_px, opts.height_px);
    let write_err = |source| PlotError::Write { path: path.display().to_string(), source };
    match format {
        PlotFormat::Svg => {
            let mut svg = String::new();
            {
                let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
                draw(&root, views, opts)?;
                root.present().map_err(draw_err)?;
            }
            std::fs::write(path, svg).map_err(write_err)?;
        }
        PlotFormat::Png => {
            let mut rgb = vec![0u8; size.0 as usize * size.1 as usize * 3];
            {
                let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
                draw(&root, views, opts)?;
                root.present().map_err(draw_err)?;
            }
            let file = std::fs::File::create(path).map_err(write_err)?;
            let mut enc = png::Encoder::new(std::io::BufWriter::new(file), size.0, size.1);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header().map_err(|e| png_err(path, e))?;
            w.write_image_data(&rgb).map_err(|e| png_err(path, e))?;
            w.finish().map_err(|e| png_err(path, e))?;
        }
    }
    Ok(())
}

fn png_err(path: &Path, e: png::EncodingError) -> PlotError {
    match e {
        png::EncodingError::IoError(source) => PlotError::Write { path: path.display().to_string(), source },
        other => PlotError::Draw(other.to_string()),
    }
}

/// The label of a detected return, as the plot prints it.
pub fn return_label(r: &crate::frame::Return) -> String {
    format!("{:.3} m ± {:.3}, {:.1} dB", r.range_m, r.range_sigma_m, r.snr_db)
}

fn rgb(c: (u8, u8, u8)) -> RGBColor {
    RGBColor(c.0, c.1, c.2)
}

/// y-range of `values` with a margin; never empty.
fn y_span<'a>(values: impl Iterator<Item = &'a f64>) -> Range<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &v in values.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return -1.0..1.0;
    }
    let pad = ((hi - lo) * 0.08).max(1e-9);
    (lo - pad)..(hi + pad)
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, views: &[FrameView], opts: &PlotOptions) -> Result<(), PlotError> {
    root.fill(&WHITE).map_err(draw_err)?;
    let rows = root.split_evenly((views.len(), 1));
    for (k, (row, v)) in rows.iter().zip(views).enumerate() {
        let h = row.dim_in_pixel().1;
        let (upper, lower) = row.split_vertically((h as f64 * 0.62) as u32);
        draw_trace(&upper, v, opts, k == 0)?;
        draw_detector(&lower, v)?;
    }
    Ok(())
}

fn draw_trace<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, v: &FrameView, opts: &PlotOptions, first: bool) -> Result<(), PlotError> {
    let n = v.stop_v.len();
    let x = v.t_ns(0.0)..v.t_ns(n.saturating_sub(1).max(1) as f64);
    let mut ys: Vec<f64> = v.stop_v.clone();
    if let Some((_, s)) = &v.start {
        ys.extend(s.iter().copied());
    }
    let y = y_span(ys.iter());
    let r = &v.report;
    let frames = if r.seq_first == r.seq_last {
        format!("frame {}", v.position)
    } else {
        format!("frames {}..{} averaged", v.position + 1 - r.frames_averaged as usize, v.position)
    };
    let caption = format!(
        "{}{frames}: {} returns; noise {:.2} mV ± {:.2} mV{}",
        if first { format!("{}, ", opts.title) } else { String::new() },
        r.returns.len(),
        r.noise.mean_v * 1e3,
        r.noise.sigma_v * 1e3,
        if r.noise.gaussian { "" } else { " (not Gaussian)" }
    );
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 16))
        .margin(8)
        .x_label_area_size(0)
        .y_label_area_size(60)
        .build_cartesian_2d(x.clone(), y.clone())
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .y_desc(format!("{} (V)", v.stop_name))
        .x_labels(10)
        .y_labels(6)
        .light_line_style(RGBColor(240, 240, 240))
        .draw()
        .map_err(draw_err)?;
    // Noise gates (grey) and range gate (pale green), full height.
    let shade = |range: &Range<usize>, colour: (u8, u8, u8)| {
        let a = v.t_ns(range.start as f64);
        let b = v.t_ns(range.end.saturating_sub(1) as f64);
        Rectangle::new([(a, y.start), (b, y.end)], rgb(colour).filled())
    };
    let mut gates = Vec::new();
    if !v.gates.range.is_empty() {
        gates.push(shade(&v.gates.range, RANGE_GATE_RGB));
    }
    for g in [&v.gates.pre, &v.gates.beyond] {
        if !g.is_empty() {
            gates.push(shade(g, GATE_RGB));
        }
    }
    chart
        .draw_series(gates)
        .map_err(draw_err)?
        .label("noise gates (grey), range gate (green)")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], rgb(GATE_RGB).filled()));
    if let Some((name, s)) = &v.start {
        chart
            .draw_series(LineSeries::new(s.iter().enumerate().map(|(i, &y)| (v.t_ns(i as f64), y)), rgb(START_RGB)))
            .map_err(draw_err)?
            .label(format!("start {name}"))
            .legend(|(x, y)| PathElement::new([(x, y), (x + 14, y)], rgb(START_RGB)));
    }
    let mean = r.noise.mean_v;
    chart
        .draw_series(LineSeries::new([(x.start, mean), (x.end, mean)], BLACK.mix(0.5)))
        .map_err(draw_err)?
        .label("noise mean")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 14, y)], BLACK.mix(0.5)));
    chart
        .draw_series(LineSeries::new(
            v.stop_v.iter().enumerate().map(|(i, &y)| (v.t_ns(i as f64), y)),
            rgb(TRACE_RGB).stroke_width(1),
        ))
        .map_err(draw_err)?
        .label(format!("stop {}", v.stop_name))
        .legend(|(x, y)| PathElement::new([(x, y), (x + 14, y)], rgb(TRACE_RGB)));
    // Returns: a marker at the peak sample, a line at the timing instant, and the label.
    let red = rgb(RETURN_RGB);
    let at = |t_s: f64| {
        let i = ((t_s - v.first_sample_offset_s) / v.sample_interval_s).round();
        if i >= 0.0 && (i as usize) < n { v.stop_v[i as usize] } else { mean }
    };
    let markers: Vec<_> = r
        .returns
        .iter()
        .map(|ret| TriangleMarker::new((ret.t_peak_s * 1e9, at(ret.t_peak_s)), 7, red.filled()))
        .collect();
    chart
        .draw_series(markers)
        .map_err(draw_err)?
        .label("returns (range ± σ, SNR)")
        .legend(|(x, y)| TriangleMarker::new((x + 7, y), 5, rgb(RETURN_RGB).filled()));
    for ret in &r.returns {
        let t = ret.t_stop_s * 1e9;
        chart
            .draw_series(LineSeries::new([(t, y.start), (t, y.end)], red.mix(0.6)))
            .map_err(draw_err)?;
    }
    let labels: Vec<_> = r
        .returns
        .iter()
        .enumerate()
        .map(|(k, ret)| {
            // Staggered downwards so neighbours' labels do not overlap.
            let y_at = y.end - (y.end - y.start) * (0.04 + 0.08 * (k % 4) as f64);
            let x_at = ret.t_stop_s.max(ret.t_peak_s) * 1e9 + (x.end - x.start) * 0.012;
            Text::new(return_label(ret), (x_at, y_at), ("sans-serif", 13).into_font().color(&red))
        })
        .collect();
    chart.draw_series(labels).map_err(draw_err)?;
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.3))
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(draw_err)?;
    Ok(())
}

fn draw_detector<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, v: &FrameView) -> Result<(), PlotError> {
    let n = v.stop_v.len();
    let x = v.t_ns(0.0)..v.t_ns(n.saturating_sub(1).max(1) as f64);
    let thr = v.report.detector.threshold;
    let y = y_span(v.detector_output.iter().chain([thr, 0.0].iter()));
    let mut chart = ChartBuilder::on(area)
        .margin(8)
        .margin_top(0)
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d(x.clone(), y.clone())
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc("time from trigger (ns)")
        .y_desc(format!("{} (V)", v.report.detector.kind))
        .x_labels(10)
        .y_labels(4)
        .light_line_style(RGBColor(240, 240, 240))
        .draw()
        .map_err(draw_err)?;
    chart
        .draw_series(LineSeries::new(
            v.detector_output.iter().enumerate().map(|(i, &y)| (v.t_ns(i as f64), y)),
            rgb(DETECTOR_RGB),
        ))
        .map_err(draw_err)?
        .label("detector output (dots: detections)")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 14, y)], rgb(DETECTOR_RGB)));
    // The threshold applies inside the range gate only.
    let g = &v.gates.range;
    if !g.is_empty() && thr.is_finite() {
        let (a, b) = (v.t_ns(g.start as f64), v.t_ns(g.end.saturating_sub(1) as f64));
        chart
            .draw_series(LineSeries::new([(a, thr), (b, thr)], rgb(THRESHOLD_RGB).stroke_width(2)))
            .map_err(draw_err)?
            .label(format!("threshold (pfa {:.0e} per report)", v.report.detector.pfa_design))
            .legend(|(x, y)| PathElement::new([(x, y), (x + 14, y)], rgb(THRESHOLD_RGB).stroke_width(2)));
    }
    let red = rgb(RETURN_RGB);
    let peaks: Vec<_> = v
        .detections
        .iter()
        .filter(|&&i| i < v.detector_output.len())
        .map(|&i| Circle::new((v.t_ns(i as f64), v.detector_output[i]), 4, red.filled()))
        .collect();
    chart.draw_series(peaks).map_err(draw_err)?;
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.3))
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(draw_err)?;
    Ok(())
}
