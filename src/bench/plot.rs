//! SVG plots of a bench run (plotters' SVG backend; text is measured with the
//! font embedded for `tofwave plot`, no system fonts or C libraries).

use std::path::Path;

use plotters::prelude::*;

use super::grid::CellStats;
use super::{BenchError, BenchResults};

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

fn err(path: &Path, e: impl std::fmt::Display) -> BenchError {
    BenchError::Plot {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn unique<T: PartialEq + Clone>(it: impl Iterator<Item = T>) -> Vec<T> {
    let mut v: Vec<T> = Vec::new();
    for x in it {
        if !v.contains(&x) {
            v.push(x);
        }
    }
    v
}

/// Log-axis range covering the positive finite values, padded by a factor 1.5.
fn log_range(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for v in values.filter(|v| v.is_finite() && *v > 0.0) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return 1e-3..1.0;
    }
    if hi <= lo {
        hi = lo * 10.0;
    }
    lo / 1.5..hi * 1.5
}

/// Work-precision panels: RMSE against compute time per report, one line per
/// method through N = 1 … 256, at three SNRs.
fn work_precision(cells: &[CellStats], path: &Path) -> Result<(), BenchError> {
    let snrs = unique(cells.iter().map(|c| c.snr_db));
    let mut picks: Vec<f64> = Vec::new();
    for want in [10.0, 20.0, 30.0] {
        if let Some(s) = snrs
            .iter()
            .copied()
            .min_by(|a, b| (a - want).abs().total_cmp(&(b - want).abs()))
            && !picks.contains(&s)
        {
            picks.push(s);
        }
    }
    let variants = unique(cells.iter().map(|c| c.variant.clone()));
    let root = SVGBackend::new(path, (420 * picks.len().max(1) as u32, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let panels = root.split_evenly((1, picks.len().max(1)));
    let xr = log_range(cells.iter().map(|c| c.ns_per_report));
    let yr = log_range(cells.iter().map(|c| c.rmse_m));
    for (panel, snr) in panels.iter().zip(&picks) {
        let mut chart = ChartBuilder::on(panel)
            .caption(format!("{snr} dB per frame"), ("sans-serif", 16))
            .margin(8)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(xr.clone().log_scale(), yr.clone().log_scale())
            .map_err(|e| err(path, e))?;
        chart
            .configure_mesh()
            .x_desc("compute time per report, ns")
            .y_desc("range RMSE, m")
            .x_labels(5)
            .y_labels(6)
            .draw()
            .map_err(|e| err(path, e))?;
        for (i, v) in variants.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            let pts: Vec<(f64, f64)> = cells
                .iter()
                .filter(|c| {
                    &c.variant == v && c.snr_db == *snr && c.rmse_m.is_finite() && c.rmse_m > 0.0
                })
                .map(|c| (c.ns_per_report, c.rmse_m))
                .collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
                .map_err(|e| err(path, e))?
                .label(v.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                });
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled())))
                .map_err(|e| err(path, e))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(path, e))?;
    }
    root.present().map_err(|e| err(path, e))
}

/// RMSE / CRLB against per-frame SNR, one line per method, N = 1.
fn rmse_over_crlb(cells: &[CellStats], path: &Path) -> Result<(), BenchError> {
    let variants = unique(cells.iter().map(|c| c.variant.clone()));
    let n1: Vec<&CellStats> = cells.iter().filter(|c| c.averaging == 1).collect();
    let root = SVGBackend::new(path, (640, 440)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let (xlo, xhi) = n1
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), c| {
            (a.min(c.snr_db), b.max(c.snr_db))
        });
    let (xlo, xhi) = if xlo.is_finite() && xhi > xlo {
        (xlo, xhi)
    } else {
        (0.0, 40.0)
    };
    let yr = log_range(n1.iter().map(|c| c.rmse_over_crlb).chain([1.0]));
    let mut chart = ChartBuilder::on(&root)
        .caption("range RMSE / CRLB (N = 1)", ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(xlo..xhi, yr.log_scale())
        .map_err(|e| err(path, e))?;
    chart
        .configure_mesh()
        .x_desc("peak SNR per frame, dB")
        .y_desc("RMSE / CRLB")
        .draw()
        .map_err(|e| err(path, e))?;
    for (i, v) in variants.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        let pts: Vec<(f64, f64)> = n1
            .iter()
            .filter(|c| &c.variant == v && c.rmse_over_crlb.is_finite() && c.rmse_over_crlb > 0.0)
            .map(|c| (c.snr_db, c.rmse_over_crlb))
            .collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(|e| err(path, e))?
            .label(v.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
            });
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled())))
            .map_err(|e| err(path, e))?;
    }
    chart
        .draw_series(LineSeries::new(
            vec![(xlo, 1.0), (xhi, 1.0)],
            BLACK.stroke_width(1),
        ))
        .map_err(|e| err(path, e))?
        .label("CRLB")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(path, e))?;
    root.present().map_err(|e| err(path, e))
}

/// ROC: Pd against the empirical false-alarm probability per report, one line per SNR.
/// A point with no false alarm is drawn at half a report (1 / (2 · reports)).
fn roc(res: &BenchResults, path: &Path) -> Result<(), BenchError> {
    let snrs = unique(res.roc.iter().map(|p| p.snr_db));
    let root = SVGBackend::new(path, (640, 440)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let floor = |p: &super::grid::RocPoint| p.pfa_report.max(0.5 / p.reports.max(1) as f64);
    let xr = log_range(res.roc.iter().map(floor).chain([1.0]));
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "ROC: matched filter, N = 1, sweeping detector.pfa",
            ("sans-serif", 16),
        )
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(48)
        .build_cartesian_2d(xr.log_scale(), 0.0..1.0)
        .map_err(|e| err(path, e))?;
    chart
        .configure_mesh()
        .x_desc("empirical false-alarm probability per report")
        .y_desc("probability of detection")
        .draw()
        .map_err(|e| err(path, e))?;
    for (i, s) in snrs.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        let mut pts: Vec<(f64, f64)> = res
            .roc
            .iter()
            .filter(|p| p.snr_db == *s)
            .map(|p| (floor(p), p.pd))
            .collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(|e| err(path, e))?
            .label(format!("{s} dB"))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
            });
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled())))
            .map_err(|e| err(path, e))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(path, e))?;
    root.present().map_err(|e| err(path, e))
}

/// Writes `work_precision.svg`, `rmse_over_crlb.svg` and `roc.svg` into `dir`.
pub fn write_all(res: &BenchResults, dir: &Path) -> Result<(), BenchError> {
    // plotters measures text with a registered font even for SVG.
    crate::plot::font_ready().map_err(|e| err(&dir.join("work_precision.svg"), e))?;
    work_precision(&res.cells, &dir.join("work_precision.svg"))?;
    rmse_over_crlb(&res.cells, &dir.join("rmse_over_crlb.svg"))?;
    roc(res, &dir.join("roc.svg"))
}
