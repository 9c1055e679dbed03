//! The physical-limit table: each stage's time per frame against the least
//! time its essential work could take on this core, whichever binds of
//! arithmetic (f64 fused multiply-adds at the rate [`fma_rate`] measures,
//! every operation counted as if in full-width vectors) and memory (the
//! frame's i16 codes read at the bench's read bandwidth).
//!
//! The essential work is counted from the scene and the frames (see
//! [`essential_work`]): what any implementation of the same stage has to
//! compute, not what tofwave's happens to (transcendental functions,
//! scalar code and serial sums make the distance to the bound).

use std::time::Instant;

use crate::frame::{Frame, Report};
use crate::scene::{Scene, TimingMethod};

/// One stage's row.
#[derive(Debug, Clone, PartialEq)]
pub struct StageLimit {
    /// Stage name (as in reports).
    pub stage: &'static str,
    /// Measured time per frame, s.
    pub time_s: f64,
    /// Essential floating-point operations per frame (an FMA is two).
    pub flops: f64,
    /// Essential bytes read from memory per frame (the channel's codes).
    pub bytes: f64,
    /// The least time per frame that work takes here, s.
    pub bound_s: f64,
}

/// The machine's yardsticks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Yardsticks {
    /// f64 fused multiply-adds per second on one core.
    pub fma_per_s: f64,
    /// Bytes of i16 codes read per second (the read-only pass of
    /// [`super::measure_bandwidth`]).
    pub read_bytes_per_s: f64,
}

/// The table for one scene and its frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Limits {
    /// The machine's yardsticks.
    pub yardsticks: Yardsticks,
    /// Frames timed (after the warm-up).
    pub frames: usize,
    /// One row per stage, in pipeline order.
    pub rows: Vec<StageLimit>,
}

/// What the work counts are taken from.
#[derive(Debug, Clone, Copy)]
struct Shape {
    /// Samples per channel.
    n: f64,
    /// Channels read (start and stop, or stop only).
    channels: f64,
    /// Return and start template taps.
    taps: f64,
    start_taps: f64,
    /// Noise-gate samples per frame.
    gate: f64,
    /// Returns per frame.
    returns: f64,
    /// Fraction of frames whose gates enter the pooled colour.
    pooled: f64,
    /// Band-subspace columns of the events test and its window, samples.
    band: f64,
    event_window: f64,
    /// Maximum-likelihood timing (the resolver runs).
    ml: bool,
}

/// Essential (flops, bytes) per frame of stage `stage` (0 for a stage this
/// model does not know). Per stage, with n samples, L template taps, G gate
/// samples and R returns per frame:
///
/// * start: decode, peak and baseline moments over the channel (6n), the
///   start filter over 8L + 17 samples around the peak, a delay fit (ten
///   evaluations of L samples) and the shape test (17 positions of L samples);
///   2n bytes.
/// * noise: decode (2n), four moments (10G), grid check and level
///   histogram for the robust σ (8G); 2n bytes.
/// * detector: the matched filter (2nL), the pooled colour's lag products
///   (2G(L + 1) on the pooled fraction of frames), peaks and up-crossings
///   (4n); with ML timing per return a delay fit and the filter recomputed
///   where the subtracted pulse reaches (4L²).
/// * events: the gate windows projected on the band subspace (2GB) and per
///   return a Gram–Schmidt of the band, pulse and slope columns over the
///   test window (2W(B + 2)²); the basis itself is built once per window length.
/// * timing: per return the shape test (102L) and the bound's colour gain (2L²).
fn essential_work(stage: &str, s: &Shape) -> (f64, f64) {
    let l = s.taps;
    match stage {
        "start" if s.channels > 1.0 => {
            let ls = s.start_taps;
            (6.0 * s.n + 2.0 * (8.0 * ls + 17.0) * ls + 10.0 * 12.0 * ls + 17.0 * 6.0 * ls, 2.0 * s.n)
        }
        "noise" => (2.0 * s.n + 18.0 * s.gate, 2.0 * s.n),
        "matched_filter" | "threshold" => {
            let resolve = if s.ml { s.returns * (4.0 * l * l + 120.0 * l) } else { 0.0 };
            (2.0 * s.n * l + 2.0 * s.gate * (l + 1.0) * s.pooled + 4.0 * s.n + resolve, 0.0)
        }
        "events" => (2.0 * s.gate * s.band + s.returns * 2.0 * s.event_window * (s.band + 2.0).powi(2), 0.0),
        "constant_fraction" | "leading_edge" | "peak_parabolic" | "peak_gaussian" | "ml" => {
            (s.returns * (102.0 * l + 2.0 * l * l), 0.0)
        }
        _ => (0.0, 0.0),
    }
}

/// f64 fused multiply-adds per second on this core: 64 independent chains
/// in the widest vectors the CPU has (picked at run time), best of five.
pub fn fma_rate() -> f64 {
    const ITER: usize = 4_000_000;
    let mut best = 0.0f64;
    for _ in 0..5 {
        let t0 = Instant::now();
        std::hint::black_box(fma_chains(ITER, std::hint::black_box(1.000_000_1)));
        best = best.max((ITER * 64) as f64 / t0.elapsed().as_secs_f64());
    }
    best
}

/// `iter` rounds of 64 independent fused multiply-add chains (x ← x·m +
/// 1e-9) in the widest vectors the CPU has; returns their sum (keep it
/// live). What [`fma_rate`] times.
pub fn fma_chains(iter: usize, m: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: AVX-512F and FMA checked just above.
            return unsafe { fma_chains_avx512(iter, m) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: AVX2 and FMA checked just above.
            return unsafe { fma_chains_avx2(iter, m) };
        }
    }
    fma_chains_body(iter, m)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn fma_chains_avx512(iter: usize, m: f64) -> f64 {
    fma_chains_body(iter, m)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn fma_chains_avx2(iter: usize, m: f64) -> f64 {
    fma_chains_body(iter, m)
}

#[inline(always)]
fn fma_chains_body(iter: usize, m: f64) -> f64 {
    let mut acc = [0.5f64; 64];
    for _ in 0..iter {
        for a in acc.iter_mut() {
            *a = a.mul_add(m, 1e-9);
        }
    }
    acc.iter().sum()
}

/// Measures the table for `scene` on `frames` (the first `warmup` frames
/// not timed), with the machine's yardsticks measured first.
pub fn measure_limits(scene: &Scene, frames: &[Frame], warmup: usize) -> Limits {
    let bw = super::measure_bandwidth(2500, 4096);
    let yardsticks = Yardsticks { fma_per_s: fma_rate(), read_bytes_per_s: bw.read_bytes_per_s };
    // The frames' gate sizes and returns, from one pass of their reports.
    let mut pipeline = crate::pipeline::Pipeline::new(scene, "limits");
    let mut reports: Vec<Report> = Vec::new();
    for f in frames {
        let _ = pipeline.push(f.clone(), &mut reports);
    }
    let count = reports.len().max(1) as f64;
    let gate = reports.iter().map(|r| r.noise.samples as f64).sum::<f64>() / count;
    let returns = reports.iter().map(|r| r.returns.len() as f64).sum::<f64>() / count;
    let f0 = frames.first();
    let dt = f0.map_or(1e-9, |f| f.sample_interval_s);
    let n = f0.map_or(0.0, |f| f.channels.iter().map(|c| c.samples.len()).max().unwrap_or(0) as f64);
    let channels = f0.map_or(1.0, |f| f.channels.len() as f64);
    let taps = scene.return_pulse.shape(dt).template().0.len() as f64;
    let start_taps = scene.start_pulse.shape(dt).template().0.len() as f64;
    // The colour pools every frame's gates up to 1e6 samples, then every 8th frame's.
    let all = frames.len().max(1) as f64;
    let full = (1e6 / gate.max(1.0)).min(all);
    let pooled = (full + (all - full) / 8.0) / all;
    let (lo, hi) = scene.return_pulse.shape(dt).support();
    let event_window = (hi - lo) + 2.0 * scene.events.flank_s / dt;
    let band = 2.0 * (scene.events.max_frequency_hz * dt * 2.0 * event_window).floor() + 1.0;
    let shape = Shape {
        n,
        channels,
        taps,
        start_taps,
        gate,
        returns,
        pooled,
        band,
        event_window,
        ml: scene.timing.method == TimingMethod::Ml,
    };
    let times = crate::pipeline::threaded::stage_times(scene, frames, warmup);
    let rows = times
        .into_iter()
        .map(|(stage, time_s)| {
            let (flops, bytes) = essential_work(stage, &shape);
            let bound_s = (flops / (2.0 * yardsticks.fma_per_s)).max(bytes / yardsticks.read_bytes_per_s);
            StageLimit { stage, time_s, flops, bytes, bound_s }
        })
        .collect();
    Limits { yardsticks, frames: frames.len().saturating_sub(warmup), rows }
}

impl Limits {
    /// The table as Markdown (no heading).
    pub fn markdown(&self) -> String {
        use std::fmt::Write;
        let y = &self.yardsticks;
        let mut md = format!(
            "This core: {:.1} GFLOP/s of f64 fused multiply-adds ({:.2e} FMA/s, 64 independent chains, widest vectors); \
             {:.1} GB/s reading i16 codes (the bench's read-only pass). Stage times: wall time around each stage, \
             {} frames after the warm-up, one thread (`pipeline::threaded::stage_times`). Bound: the stage's essential \
             work at those rates (`bench::limits`), whichever is longer.\n\n\
             | stage | µs/frame | essential kflop | bytes read | bound µs | time / bound |\n|---|---|---|---|---|---|\n",
            2.0 * y.fma_per_s / 1e9,
            y.fma_per_s,
            y.read_bytes_per_s / 1e9,
            self.frames
        );
        let (mut t, mut b) = (0.0, 0.0);
        for r in &self.rows {
            t += r.time_s;
            b += r.bound_s;
            let ratio = if r.bound_s > 0.0 { format!("{:.0}×", r.time_s / r.bound_s) } else { "–".into() };
            let _ = writeln!(
                md,
                "| {} | {:.1} | {:.0} | {:.0} | {:.2} | {} |",
                r.stage,
                r.time_s * 1e6,
                r.flops / 1e3,
                r.bytes,
                r.bound_s * 1e6,
                ratio
            );
        }
        let _ = writeln!(md, "| **frame** | **{:.1}** | | | **{:.2}** | **{:.0}×** |", t * 1e6, b * 1e6, t / b.max(f64::MIN_POSITIVE));
        md
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_stage_of_the_reference_scene_gets_a_row_with_a_finite_bound() {
        let mut scene = super::super::reference_scene();
        scene.timing.method = TimingMethod::Ml;
        let (frames, _) = super::super::reference_frames(&scene, 20.0, 3, 12);
        let shape = Shape { n: 2500.0, channels: 2.0, taps: 64.0, start_taps: 28.0, gate: 1355.0, returns: 1.0, pooled: 1.0, band: 7.0, event_window: 184.0, ml: true };
        // The matched filter's 2nL dominates the detector's count.
        assert!(essential_work("matched_filter", &shape).0 >= 2.0 * 2500.0 * 64.0);
        assert_eq!(essential_work("validate", &shape), (0.0, 0.0));
        let names = crate::pipeline::Pipeline::new(&scene, "t").stage_names();
        let times = crate::pipeline::threaded::stage_times(&scene, &frames, 2);
        assert_eq!(times.iter().map(|t| t.0).collect::<Vec<_>>(), names);
        assert!(times.iter().all(|t| t.1.is_finite() && t.1 >= 0.0));
    }
}
