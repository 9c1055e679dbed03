//! Synthetic start/stop frames with known truth, for tests: bigaussian pulses
//! (the scene's shapes), white Gaussian noise, optional 8-bit quantisation.
#![allow(dead_code)]

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use tofwave::dsp::pulse::{Pulse, PulseShape};
use tofwave::frame::{Channel, ChannelRole, Frame, Samples};
use tofwave::scene::Scene;

/// Independent frame generator built from the prototype's description alone.
pub mod seedgen;

/// What to synthesise.
#[derive(Debug, Clone)]
pub struct Synth {
    pub samples: usize,
    pub dt_s: f64,
    pub pre_trigger_samples: usize,
    /// Start pulse peak amplitude (0: no start channel pulse), V.
    pub start_amplitude_v: f64,
    /// Start pulse half-max crossing relative to the trigger, s.
    pub start_time_s: f64,
    /// Returns: (time of the half-max crossing relative to the start crossing, s; peak amplitude, V).
    pub returns: Vec<(f64, f64)>,
    pub noise_sigma_v: f64,
    pub noise_mean_v: f64,
    /// Quantise to 8 bits over this full scale (low, high), V.
    pub quantise_8bit: Option<(f64, f64)>,
    pub with_start_channel: bool,
}

impl Synth {
    pub fn prototype() -> Synth {
        Synth {
            samples: 2500,
            dt_s: 1e-9,
            pre_trigger_samples: 500,
            start_amplitude_v: 0.3,
            start_time_s: 0.0,
            returns: vec![],
            noise_sigma_v: 0.0138,
            noise_mean_v: 0.0,
            quantise_8bit: Some((-1.0, 3.0)),
            with_start_channel: true,
        }
    }

    /// Frame `seq` with the scene's pulse shapes; sub-sample phases come from the times given.
    pub fn frame(&self, scene: &Scene, seq: u64, rng: &mut ChaCha8Rng) -> Frame {
        let stop_p = scene.return_pulse.pulse(self.dt_s);
        let start_p = scene.start_pulse.pulse(self.dt_s);
        let t0 = -(self.pre_trigger_samples as f64) * self.dt_s;
        let idx = |t: f64| (t - t0) / self.dt_s;
        let normal = Normal::new(0.0, self.noise_sigma_v.max(0.0)).unwrap();
        let make = |pulses: &[(f64, f64, &Pulse)], rng: &mut ChaCha8Rng| -> Vec<f64> {
            (0..self.samples)
                .map(|k| {
                    let mut v = self.noise_mean_v
                        + if self.noise_sigma_v > 0.0 {
                            normal.sample(rng)
                        } else {
                            0.0
                        };
                    for &(peak, amp, p) in pulses {
                        v += amp * p.value_and_slope(k as f64 - peak).0;
                    }
                    v
                })
                .collect()
        };
        // Pulses are placed by their half-max crossing; the peak follows the shape.
        let start_peak = idx(self.start_time_s) - start_p.half_rise_offset();
        let start = make(&[(start_peak, self.start_amplitude_v, &start_p)], rng);
        let rets: Vec<(f64, f64, &Pulse)> = self
            .returns
            .iter()
            .map(|&(tof, a)| {
                (
                    idx(self.start_time_s + tof) - stop_p.half_rise_offset(),
                    a,
                    &stop_p,
                )
            })
            .collect();
        let stop = make(&rets, rng);
        let chan = |name: &str, role, v: Vec<f64>| match self.quantise_8bit {
            Some((lo, hi)) => {
                let lsb = (hi - lo) / 256.0;
                let codes = v
                    .iter()
                    .map(|x| (((x - lo) / lsb).floor().clamp(0.0, 255.0) as i16 - 128) as i8)
                    .collect();
                Channel {
                    name: name.into(),
                    role,
                    samples: Samples::I8(codes),
                    volts_per_code: lsb,
                    offset_v: lo + 128.0 * lsb + 0.5 * lsb,
                }
            }
            None => Channel::from_volts(name, role, v),
        };
        let mut channels = vec![chan("CH2", ChannelRole::Unspecified, stop)];
        if self.with_start_channel {
            channels.insert(0, chan("CH1", ChannelRole::Unspecified, start));
        }
        Frame {
            sensor_id: "synth".into(),
            sequence: seq,
            trigger_time_s: seq as f64 * 1e-3,
            sample_interval_s: self.dt_s,
            first_sample_offset_s: t0,
            channels,
            laser_off: false,
        }
    }
}

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// A file under the repository's `replay-data/`.
pub fn replay_path(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("replay-data")
        .join(name)
}

/// The shipped scene `replay-data/scenes/{name}.toml`, loaded and validated.
pub fn load_scene(name: &str) -> Scene {
    let path = replay_path(&format!("scenes/{name}.toml"));
    Scene::load(&path).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// Runs the `tofwave` binary: exit code, stdout parsed as JSON lines, stderr.
pub fn tofwave(args: &[&str]) -> (i32, Vec<serde_json::Value>, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_tofwave"))
        .args(args)
        .output()
        .expect("runs");
    let stdout = String::from_utf8(out.stdout).unwrap();
    let reports = stdout
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON line"))
        .collect();
    (
        out.status.code().unwrap_or(-1),
        reports,
        String::from_utf8(out.stderr).unwrap(),
    )
}

/// Runs the `tofwave` binary, which must succeed: its stdout.
pub fn tofwave_ok(args: &[&str]) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_tofwave"))
        .args(args)
        .output()
        .expect("runs");
    assert!(
        out.status.success(),
        "tofwave {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8")
}

/// A laser-off frame of one stop channel (`v`, volts at 1 GS/s) whose first
/// `pre` samples lie before the trigger.
pub fn noise_frame(sensor: &str, v: Vec<f64>, pre: usize, seq: u64) -> Frame {
    Frame {
        sensor_id: sensor.into(),
        sequence: seq,
        trigger_time_s: seq as f64 * 1e-3,
        sample_interval_s: 1e-9,
        first_sample_offset_s: -(pre as f64) * 1e-9,
        channels: vec![Channel::from_volts("CH2", ChannelRole::Stop, v)],
        laser_off: true,
    }
}
