//! The memory-bandwidth yardsticks: a read-only pass and a plain copy loop
//! against ensemble averaging over the same stream of i16 frames, in the
//! same process.

use std::hint::black_box;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::dsp::accumulate::CodeAccumulator;

/// Read-only, copy-loop and averaging throughput over one stream of i16
/// frames (see [`measure_bandwidth`] on its size and the caches).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bandwidth {
    /// Bytes of the stream (i16 frames).
    pub stream_bytes: usize,
    /// A read-only pass (each frame's codes summed in wrapping integer
    /// lanes: the least work that reads every byte), bytes read per second.
    /// Averaging reads the same bytes and writes nothing per sample, so this
    /// is its yardstick.
    pub read_bytes_per_s: f64,
    /// Plain copy (`copy_from_slice` frame by frame), bytes read plus bytes
    /// written per second (the STREAM convention).
    pub copy_bytes_per_s: f64,
    /// `CodeAccumulator::add_i16` over the same frames, bytes of codes read per second.
    pub average_bytes_per_s: f64,
}

impl Bandwidth {
    /// Averaging over the read-only pass (both count the bytes read).
    pub fn ratio(&self) -> f64 {
        self.average_bytes_per_s / self.read_bytes_per_s
    }
}

/// The wrapping sum of a frame's codes: the read-only pass's work, in
/// vectors as wide as averaging's (AVX2 where the CPU has it).
fn read_frame(s: &[i16]) -> i32 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 checked just above.
        return unsafe { read_frame_avx2(s) };
    }
    read_frame_body(s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn read_frame_avx2(s: &[i16]) -> i32 {
    read_frame_body(s)
}

#[inline(always)]
fn read_frame_body(s: &[i16]) -> i32 {
    s.iter().fold(0i32, |a, &c| a.wrapping_add(i32::from(c)))
}

/// Measures all three over `frames` frames of `len` i16 samples (best of
/// six passes each). The loops take turns, the order rotating each round,
/// so that a slow spell of the machine slows each alike and no loop always
/// runs on what the one before left in the caches. 4096 × 2500 samples is
/// 20 MB: beyond a desktop's last-level cache, within some servers'
/// (then all three read largely from that cache).
pub fn measure_bandwidth(len: usize, frames: usize) -> Bandwidth {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let stream: Vec<i16> = (0..len * frames)
        .map(|_| rng.random_range(-2000..2000))
        .collect();
    let mut dst = vec![0i16; stream.len()];
    let bytes = std::mem::size_of_val(stream.as_slice());
    let mut acc = CodeAccumulator::new(len);
    // Best seconds of the read-only pass, the copy and averaging.
    let mut best = [f64::INFINITY; 3];
    for round in 0..6 {
        for turn in 0..3 {
            let which = (round + turn) % 3;
            let t0 = Instant::now();
            match which {
                0 => {
                    let mut sum = 0i32;
                    for s in stream.chunks_exact(len) {
                        sum = sum.wrapping_add(read_frame(black_box(s)));
                    }
                    black_box(sum);
                }
                1 => {
                    for (d, s) in dst.chunks_exact_mut(len).zip(stream.chunks_exact(len)) {
                        d.copy_from_slice(s);
                    }
                    black_box(&mut dst);
                }
                _ => {
                    acc.reset();
                    for s in stream.chunks_exact(len) {
                        acc.add_i16(black_box(s));
                    }
                    black_box(acc.sums());
                }
            }
            best[which] = best[which].min(t0.elapsed().as_secs_f64());
        }
    }
    let [read_s, copy_s, avg_s] = best;
    Bandwidth {
        stream_bytes: bytes,
        read_bytes_per_s: bytes as f64 / read_s,
        copy_bytes_per_s: 2.0 * bytes as f64 / copy_s,
        average_bytes_per_s: bytes as f64 / avg_s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_read_pass_reads_every_code_and_the_ratio_is_over_it() {
        let codes: Vec<i16> = (0..2503).map(|i| ((i * 7919) % 65536 - 32768) as i16).collect();
        // The exact sum, wrapped once at the end.
        let want = codes.iter().map(|&c| i64::from(c)).sum::<i64>() as i32;
        assert_eq!(read_frame(&codes), want);
        assert_eq!(read_frame_body(&codes), want);
        let b = measure_bandwidth(256, 64);
        assert_eq!(b.stream_bytes, 256 * 64 * 2);
        for (name, rate) in [("read", b.read_bytes_per_s), ("copy", b.copy_bytes_per_s), ("average", b.average_bytes_per_s)] {
            assert!(rate.is_finite() && rate > 0.0, "{name}: {rate}");
        }
        assert_eq!(b.ratio(), b.average_bytes_per_s / b.read_bytes_per_s);
    }
}
