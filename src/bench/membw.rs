//! The memory-bandwidth yardstick: a plain copy loop against ensemble
//! averaging over the same stream of i16 frames, in the same process.

use std::hint::black_box;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::dsp::accumulate::CodeAccumulator;

/// Copy-loop and averaging throughput over a stream larger than the caches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bandwidth {
    /// Bytes of the stream (i16 frames).
    pub stream_bytes: usize,
    /// Plain copy (`copy_from_slice` frame by frame), bytes read plus bytes
    /// written per second (the STREAM convention).
    pub copy_bytes_per_s: f64,
    /// `CodeAccumulator::add_i16` over the same frames, bytes of codes read per second.
    pub average_bytes_per_s: f64,
}

impl Bandwidth {
    /// average / copy.
    pub fn ratio(&self) -> f64 {
        self.average_bytes_per_s / self.copy_bytes_per_s
    }
}

/// Measures both over `frames` frames of `len` i16 samples (best of five
/// passes each; the stream should exceed the last-level cache: 4096 × 2500
/// samples is 20 MB).
pub fn measure_bandwidth(len: usize, frames: usize) -> Bandwidth {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let stream: Vec<i16> = (0..len * frames)
        .map(|_| rng.random_range(-2000..2000))
        .collect();
    let mut dst = vec![0i16; stream.len()];
    let bytes = std::mem::size_of_val(stream.as_slice());
    let best = |f: &mut dyn FnMut()| {
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t0 = Instant::now();
            f();
            best = best.min(t0.elapsed().as_secs_f64());
        }
        best
    };
    let copy_s = best(&mut || {
        for (d, s) in dst.chunks_exact_mut(len).zip(stream.chunks_exact(len)) {
            d.copy_from_slice(s);
        }
        black_box(&mut dst);
    });
    let mut acc = CodeAccumulator::new(len);
    let avg_s = best(&mut || {
        acc.reset();
        for s in stream.chunks_exact(len) {
            acc.add_i16(black_box(s));
        }
        black_box(acc.sums());
    });
    Bandwidth {
        stream_bytes: bytes,
        copy_bytes_per_s: 2.0 * bytes as f64 / copy_s,
        average_bytes_per_s: bytes as f64 / avg_s,
    }
}
