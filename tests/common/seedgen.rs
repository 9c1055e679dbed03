//! An independent frame generator: start/stop frames of the direct-detection
//! ToF prototype (1550 nm pulsed laser, PIN start detector, APD + TIA
//! receiver, 8-bit oscilloscope at 1 GS/s, 2500 samples a frame), built from
//! the prototype's physical description and measured numbers alone.
//!
//! It shares no model with the library: its pulse shapes are not the
//! library's, it places pulses by their *onset*, it quantises as an
//! oscilloscope does, and it can add the receiver's mains-tied interference
//! events (four shape families, placed at random, near the return or inside a
//! gate, with fixed or random phases and peaks). Tests use it to check
//! timing, detection and uncertainty on frames the library was not designed
//! around. Only `tofwave::frame` is used.
//!
//! # Time base and truth
//!
//! Every time in [`GenTruth`] is relative to the frame's trigger, the time
//! base of [`Frame::sample_time_s`]: sample `k` is at
//! `-pretrigger_s + k * dt_s`.
//!
//! * The shot happens at `t_shot_s = (u - 1/2) * dt_s + start_jitter_s * n`
//!   (`u` uniform on [0, 1), `n` standard normal): uniformly random against
//!   the sample clock, plus the shot's jitter.
//! * The start pulse's **onset** (the first instant it leaves zero; every
//!   [`PulseFamily`] is exactly zero before it) is at `t_shot_s`.
//! * A target at `range_m` has `tof_s = 2 * range_m / c`, `c` being
//!   [`GenConfig::speed_of_light_m_per_s`]; its return's onset is at
//!   `t_ref_s = t_shot_s + system_delay_s + tof_s`.
//! * An interference event ([`TrueEvent`]) is exactly zero outside
//!   `[onset_s, end_s]`; `peak_s` is the instant of its largest positive
//!   excursion `peak_v` (which the frame's samples straddle).
//!
//! A timing method that reports some other point of the pulse (a half-maximum
//! crossing, a peak, a matched-filter centre) differs from these onsets by a
//! constant for each pulse shape ([`PulseFamily::half_rise_offset_s`],
//! [`PulseFamily::peak_offset_s`]); a range calibration against a known
//! target absorbs that constant together with `system_delay_s`.
//!
//! # Signal chain, in order
//!
//! 1. Pulses: `amplitude_v * shape(t - onset)`, point-sampled (the published
//!    rise times and widths are of the digitised pulse, so the scope's
//!    bandwidth is already in the shape).
//! 2. Interference event (stop channel only), see [`EventConfig`],
//!    [`EventShape`], [`EventPlacement`].
//! 3. Receiver noise: Gaussian, mean `noise_mean_v`, standard deviation
//!    `noise_sigma_v`, white or one-pole band-limited (σ holds after the
//!    filter). The start channel gets its own, smaller, white noise.
//! 4. Optional receiver (TIA) output limit.
//! 5. Oscilloscope quantisation to `bits` with clipping at the rails.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use tofwave::frame::{Channel, ChannelRole, Frame, Samples};

/// Vacuum speed of light, m/s (exact, SI).
pub const C_VACUUM_M_PER_S: f64 = 299_792_458.0;

/// Phase refractive index of standard dry air at 1550 nm
/// (15 °C, 101.325 kPa; Ciddor 1996 gives n − 1 = 2.73e-4). The laboratory's
/// temperature and pressure are not recorded; at 20 °C n − 1 is 2.69e-4,
/// a range difference of 4 ppm, far below the prototype's resolution.
pub const N_AIR_1550NM: f64 = 1.000_273;

/// Long-range targets of the prototype (true range m, peak volts), from the
/// oscilloscope measurements with half-maximum timing (Table 10.20).
pub const LONG_RANGE_TARGETS: [(f64, f64); 6] = [
    (32.1147, 0.0208),
    (24.8122, 0.496),
    (19.6814, 0.392),
    (15.3986, 0.505),
    (9.5, 0.560),
    (3.45, 1.480),
];

/// Fraction of the peak at the 10 % / 90 % rise-time points.
const RISE_LO: f64 = 0.1;
const RISE_HI: f64 = 0.9;

/// A unit-peak pulse shape that is exactly zero before its onset (t = 0).
///
/// Both families are set by their 10–90 % rise time and full width at half
/// maximum, the two numbers the prototype's measurements quote. Neither is a
/// Gaussian or a sum of Gaussians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PulseFamily {
    /// Sharp onset: a quarter-sine rise that leaves zero with a finite slope
    /// (a corner at the onset), then a critically damped tail that is
    /// asymptotically exponential. With `a = rise_s / 0.649112` and
    /// `x = t - a`:
    ///
    /// * `0 <= t <= a`: `sin(pi t / (2a))` (10 % → 90 % takes
    ///   `(asin 0.9 − asin 0.1)·2/pi · a = 0.649112 a`; half maximum at `a/3`);
    /// * `t > a`: `(1 + x/tau) exp(-x/tau)`, zero slope at the peak (so the
    ///   peak is smooth), half maximum at `x = 1.678347 tau`, whence
    ///   `tau = (fwhm_s − 2a/3) / 1.678347`.
    ///
    /// Needs `fwhm_s > 1.0271 * rise_s`.
    SharpOnset {
        /// 10–90 % rise time, seconds.
        rise_s: f64,
        /// Full width at half maximum, seconds.
        fwhm_s: f64,
    },
    /// Asymmetric raised cosine: compact support, soft (zero-slope) onset,
    /// no tail. With `a = rise_s / 0.590334` and `b = 2 fwhm_s − a`:
    ///
    /// * `0 <= t <= a`: `(1 − cos(pi t / a)) / 2` (10 % → 90 % takes
    ///   `(acos(−0.8) − acos 0.8)/pi · a = 0.590334 a`; half maximum at `a/2`);
    /// * `a < t <= a + b`: `(1 + cos(pi (t − a) / b)) / 2` (half maximum at
    ///   `a + b/2`, so FWHM = `(a + b)/2`);
    /// * after `a + b`: zero.
    ///
    /// Needs `fwhm_s > 0.8470 * rise_s`; symmetric when
    /// `rise_s = 0.590334 fwhm_s`.
    RaisedCosine {
        /// 10–90 % rise time, seconds.
        rise_s: f64,
        /// Full width at half maximum, seconds.
        fwhm_s: f64,
    },
}

/// 10–90 % rise of `sin(pi t / 2)` on [0, 1], in units of its rise duration.
fn quarter_sine_rise_fraction() -> f64 {
    (RISE_HI.asin() - RISE_LO.asin()) * 2.0 / std::f64::consts::PI
}

/// 10–90 % rise of `(1 − cos(pi t))/2` on [0, 1], in units of its rise duration.
fn raised_cosine_rise_fraction() -> f64 {
    ((1.0 - 2.0 * RISE_HI).acos() - (1.0 - 2.0 * RISE_LO).acos()) / std::f64::consts::PI
}

/// The root of `(1 + x) exp(-x) = 1/2` (Newton, from 1.7).
fn damped_tail_half_point() -> f64 {
    let mut x: f64 = 1.7;
    for _ in 0..50 {
        let f = (1.0 + x) * (-x).exp() - 0.5;
        let df = -x * (-x).exp();
        let step = f / df;
        x -= step;
        if step.abs() < 1e-15 {
            break;
        }
    }
    x
}

impl PulseFamily {
    /// The prototype's return (stop) pulse: rise 8.08 ns, FWHM 26.04 ns
    /// (Table 10.13, terminated 50 Ω line), sharp-onset family.
    pub fn prototype_return() -> PulseFamily {
        PulseFamily::SharpOnset {
            rise_s: 8.08e-9,
            fwhm_s: 26.04e-9,
        }
    }

    /// The prototype's start pulse: rise 3.02 ns (Table 10.12), asymmetric
    /// with a long tail. The source gives no start-pulse width; 8 ns is
    /// assumed (a 5 ns optical pulse widened by the detector's tail).
    pub fn prototype_start() -> PulseFamily {
        PulseFamily::SharpOnset {
            rise_s: 3.02e-9,
            fwhm_s: 8.0e-9,
        }
    }

    /// The configured 10–90 % rise time, seconds.
    pub fn rise_s(&self) -> f64 {
        match *self {
            PulseFamily::SharpOnset { rise_s, .. } | PulseFamily::RaisedCosine { rise_s, .. } => {
                rise_s
            }
        }
    }

    /// The configured full width at half maximum, seconds.
    pub fn fwhm_s(&self) -> f64 {
        match *self {
            PulseFamily::SharpOnset { fwhm_s, .. } | PulseFamily::RaisedCosine { fwhm_s, .. } => {
                fwhm_s
            }
        }
    }

    /// Checks that the rise time and width can be met by the family.
    pub fn validate(&self) -> Result<(), String> {
        let (rise, fwhm) = (self.rise_s(), self.fwhm_s());
        if !(rise > 0.0 && rise.is_finite() && fwhm > 0.0 && fwhm.is_finite()) {
            return Err(format!(
                "{self:?}: rise and FWHM must be positive and finite"
            ));
        }
        let (a, b) = self.segments();
        if b.is_nan() || b <= 0.0 {
            let min = match self {
                PulseFamily::SharpOnset { .. } => 2.0 / 3.0 / quarter_sine_rise_fraction(),
                PulseFamily::RaisedCosine { .. } => 0.5 / raised_cosine_rise_fraction(),
            };
            return Err(format!(
                "{self:?}: FWHM must exceed {min:.4} x rise for this family (rise segment {a:e} s)"
            ));
        }
        Ok(())
    }

    /// (rise-segment length `a`, tail parameter): `tau` for
    /// [`SharpOnset`](PulseFamily::SharpOnset), fall length `b` for
    /// [`RaisedCosine`](PulseFamily::RaisedCosine).
    fn segments(&self) -> (f64, f64) {
        match *self {
            PulseFamily::SharpOnset { rise_s, fwhm_s } => {
                let a = rise_s / quarter_sine_rise_fraction();
                (a, (fwhm_s - 2.0 * a / 3.0) / damped_tail_half_point())
            }
            PulseFamily::RaisedCosine { rise_s, fwhm_s } => {
                let a = rise_s / raised_cosine_rise_fraction();
                (a, 2.0 * fwhm_s - a)
            }
        }
    }

    /// The unit-peak shape `t_s` seconds after its onset (0 for `t_s <= 0`).
    pub fn value(&self, t_s: f64) -> f64 {
        self.evaluator().value(t_s)
    }

    /// Time from the onset to the peak (where the shape is 1), seconds.
    pub fn peak_offset_s(&self) -> f64 {
        self.segments().0
    }

    /// Time from the onset to the rising half-maximum crossing, seconds.
    pub fn half_rise_offset_s(&self) -> f64 {
        let a = self.segments().0;
        match self {
            PulseFamily::SharpOnset { .. } => a / 3.0,
            PulseFamily::RaisedCosine { .. } => a / 2.0,
        }
    }

    /// Time after the onset beyond which the shape stays below `1e-12`
    /// (exactly zero for the raised cosine), seconds.
    pub fn support_s(&self) -> f64 {
        let (a, b) = self.segments();
        match self {
            // (1 + x) e^-x < 1e-12 for x > 31.4.
            PulseFamily::SharpOnset { .. } => a + 32.0 * b,
            PulseFamily::RaisedCosine { .. } => a + b,
        }
    }

    /// The shape sampled every `dt_s` from `t0_s` (relative to the onset):
    /// `n` values, for measuring the shape itself.
    pub fn render(&self, t0_s: f64, dt_s: f64, n: usize) -> Vec<f64> {
        let e = self.evaluator();
        (0..n).map(|k| e.value(t0_s + k as f64 * dt_s)).collect()
    }

    fn evaluator(&self) -> Evaluator {
        let (a, p) = self.segments();
        Evaluator {
            sharp: matches!(self, PulseFamily::SharpOnset { .. }),
            a,
            p,
        }
    }
}

/// A pulse shape with its derived segment lengths (computed once per frame).
#[derive(Debug, Clone, Copy)]
struct Evaluator {
    sharp: bool,
    a: f64,
    p: f64,
}

impl Evaluator {
    fn value(&self, t: f64) -> f64 {
        use std::f64::consts::PI;
        if t.is_nan() || t <= 0.0 {
            return 0.0;
        }
        if t <= self.a {
            return if self.sharp {
                (PI * t / (2.0 * self.a)).sin()
            } else {
                0.5 * (1.0 - (PI * t / self.a).cos())
            };
        }
        let x = t - self.a;
        if self.sharp {
            let u = x / self.p;
            (1.0 + u) * (-u).exp()
        } else if x < self.p {
            0.5 * (1.0 + (PI * x / self.p).cos())
        } else {
            0.0
        }
    }
}

/// The shape of an interference event, as a function of the time `x`
/// (seconds) after the event's onset. Every shape is exactly zero for
/// `x <= 0` and past its cut ([`EventConfig::duration_s`]). Below, `f_k` are
/// [`EventConfig::modes_hz`], `τ` is [`EventConfig::decay_s`] and `φ_k` the
/// event's phases ([`EventWave::phases_rad`]; all zero unless
/// [`EventConfig::random_phase`]). Each event is scaled so that its largest
/// positive excursion is the event's peak ([`EventConfig::peak_v`], possibly
/// spread per event), so that, like the prototype's, it can mimic a return of
/// that height.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum EventShape {
    /// A decaying multi-mode burst (the generator's original model):
    /// `g(x) Σ_k sin(2π f_k x + φ_k)` with the envelope
    /// `g(x) = (x/τ) exp(1 − x/τ)` (rises from zero, peaks at `x = τ`, then
    /// decays); cut at `12 τ` (envelope below 2.1e-4). Starts smoothly.
    #[default]
    MultiMode,
    /// A switching transient: a voltage step (the mains-side switching of the
    /// APD bias supply) exciting a resonance of the receiver's supply filter.
    /// The current of a series resonator driven by a step, one term per mode:
    /// `exp(−x/τ) Σ_k sin(2π f_k x + φ_k)`; cut at `12 τ` (e^−12 = 6.1e-6).
    /// With zero phases it leaves zero at the onset with the finite slope
    /// `2π Σ_k f_k` (a corner: the sharp onset) and, unless its modes beat
    /// up again later, its first lobe is the largest (a single mode's lobes
    /// shrink by `exp(−1/(2 f τ))` each half cycle; true for the preset of
    /// [`EventConfig::for_shape`]). With random phases each mode starts at `sin φ_k`: the onset is
    /// an ideal step (a 50 MHz scope would round it over ~7 ns).
    Ringing,
    /// A Gaussian-windowed wave packet:
    /// `w(x) Σ_k cos(2π f_k (x − c) + φ_k)`, `w(x) = exp(−(x − c)² / (2τ²))`,
    /// centred `c = 5τ` after the onset (τ is the window's rms width); cut at
    /// `10 τ` (window 3.7e-6). With one mode and `f τ ≈ 0.3` it is a
    /// single-cycle packet; the carrier phase moves the largest positive
    /// lobe (symmetric about `c` for `φ = 0`, an antisymmetric, bipolar
    /// packet for `φ = ±π/2`).
    WavePacket,
    /// A bipolar doublet, the time derivative of a Gaussian (a switching
    /// spike coupled through a capacitance):
    /// `p · (−(x − c)/τ) exp(−(x − c)² / (2τ²))`, `c = 5τ`, cut at `10 τ`.
    /// Zero net area, two lobes of equal size at `c ∓ τ`, energy spectrum
    /// peaking at `1/(2π τ)` Hz. Ignores `modes_hz`; its one phase `φ_0` sets
    /// the polarity: `p = +1` (positive lobe first) when `cos φ_0 >= 0`, else
    /// `p = −1`.
    Doublet,
}

impl EventShape {
    /// Every shape, in declaration order.
    pub const ALL: [EventShape; 4] = [
        EventShape::MultiMode,
        EventShape::Ringing,
        EventShape::WavePacket,
        EventShape::Doublet,
    ];
}

/// Where an event lands in its frame. Times are relative to the trigger.
/// Each uses the frame's one position draw `u` (uniform on [0, 1)).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum EventPlacement {
    /// The onset is uniform over the frame's sample span:
    /// `t_first + u · samples · dt_s` (the mains-tied events fall at random
    /// against the shots). The event may run past the frame's end.
    #[default]
    Uniform,
    /// The event's largest positive lobe lands at
    /// `t_peak + (2u − 1) · max_offset_s`, uniform within `±max_offset_s` of
    /// the first target's return peak
    /// `t_peak = t_shot_s + system_delay_s + tof_s + return_pulse.peak_offset_s()`,
    /// so that it overlaps the return as in Fig. 10.18(b). Laser-off frames
    /// use the nominal return all the same. Needs at least one target.
    NearReturn {
        /// Largest distance between the event's peak and the return's, seconds.
        max_offset_s: f64,
    },
    /// The event's largest positive lobe lands at `from_s + u (to_s − from_s)`,
    /// e.g. inside a range gate.
    InGate {
        /// Earliest peak time relative to the trigger, seconds.
        from_s: f64,
        /// Latest peak time relative to the trigger, seconds.
        to_s: f64,
    },
}

/// The receiver's interference events (ch. 10.4.1, 10.5): fixed-shape,
/// oscillating events whose dominant modes lie below 10 MHz, tied to the
/// 60 Hz mains that powers the APD bias, so they land at random positions
/// relative to the laser shots, in a minority of frames. Seen beside a weak
/// return (350 mV) an event looked like a second return of similar height,
/// sometimes partly overlapping it.
///
/// The shape is one of [`EventShape`] (default: the decaying multi-mode
/// burst); the position one of [`EventPlacement`] (default: onset uniform
/// over the frame). Each frame independently holds one event with
/// `probability`.
///
/// Per event, with `random_phase` each phase `φ_k` is uniform on [0, 2π)
/// (zero otherwise); with `amplitude_spread = s > 0` the peak is log-normal,
/// `peak_v · exp(σ z − σ²/2)`, `z` standard normal, `σ² = ln(1 + s²)`: mean
/// `peak_v`, relative standard deviation exactly `s`, always positive.
/// The event is then scaled so that its largest positive excursion is that
/// peak (for the multi-mode burst with zero phases, the maximum on a grid of
/// at most 1/200 of the fastest mode's period, as the generator always did:
/// the true maximum exceeds it by less than 1e-3 relative).
#[derive(Debug, Clone, PartialEq)]
pub struct EventConfig {
    /// Fraction of frames holding an event (each frame independently).
    pub probability: f64,
    /// Largest positive excursion of the event, volts (its mean when
    /// `amplitude_spread > 0`).
    pub peak_v: f64,
    /// Frequencies of the event's modes, Hz (the prototype's were below
    /// 10 MHz). Unused by [`EventShape::Doublet`].
    pub modes_hz: Vec<f64>,
    /// Time constant of the shape, seconds: the envelope's peak time
    /// ([`MultiMode`](EventShape::MultiMode)), the ringing's decay
    /// ([`Ringing`](EventShape::Ringing)), the window's rms width
    /// ([`WavePacket`](EventShape::WavePacket),
    /// [`Doublet`](EventShape::Doublet)).
    pub decay_s: f64,
    /// The shape family. Default [`EventShape::MultiMode`].
    pub shape: EventShape,
    /// Where the event lands. Default [`EventPlacement::Uniform`].
    pub placement: EventPlacement,
    /// Draw each event's phases uniformly on [0, 2π); `false` (default): all
    /// phases zero, every event the same shape.
    pub random_phase: bool,
    /// Relative standard deviation of the per-event peak (log-normal, mean
    /// `peak_v`); 0 (default): every event peaks at `peak_v`.
    pub amplitude_spread: f64,
}

impl Default for EventConfig {
    /// Multi-mode burst with modes at 3 and 7 MHz, 150 ns decay (a burst of
    /// ~0.75 µs, under a third of a frame), peak 0.35 V (the height of the
    /// weak return it mimicked, L13895–13950), in 10 % of the frames, onset
    /// uniform, fixed phases and peak. The source quantifies neither the
    /// per-frame rate nor the modes' exact frequencies.
    fn default() -> Self {
        EventConfig {
            probability: 0.1,
            peak_v: 0.35,
            modes_hz: vec![3e6, 7e6],
            decay_s: 150e-9,
            shape: EventShape::MultiMode,
            placement: EventPlacement::Uniform,
            random_phase: false,
            amplitude_spread: 0.0,
        }
    }
}

/// Golden-section ratio, `(sqrt 5 − 1) / 2`.
const GOLDEN: f64 = 0.618_033_988_749_894_9;

impl EventConfig {
    /// A default event of `shape` (0.35 V, 10 % of the frames, uniform onset,
    /// fixed phases and peak), with time constants for which every shape
    /// lasts a fraction of the 2.5 µs frame and keeps over 95 % of its energy
    /// below 10 MHz (with zero phases):
    ///
    /// * [`MultiMode`](EventShape::MultiMode): [`EventConfig::default`]
    ///   (3 and 7 MHz, τ = 150 ns);
    /// * [`Ringing`](EventShape::Ringing): 1.5 and 4 MHz, τ = 300 ns (Q of
    ///   1.4 and 3.8; below 5 % of its start after 0.9 µs);
    /// * [`WavePacket`](EventShape::WavePacket): 3 MHz, τ = 100 ns
    ///   (a single-cycle packet, ~0.6 µs between its 1 % points);
    /// * [`Doublet`](EventShape::Doublet): τ = 50 ns (lobes 100 ns apart,
    ///   energy peaking at 3.2 MHz).
    pub fn for_shape(shape: EventShape) -> EventConfig {
        let (modes_hz, decay_s) = match shape {
            EventShape::MultiMode => (vec![3e6, 7e6], 150e-9),
            EventShape::Ringing => (vec![1.5e6, 4e6], 300e-9),
            EventShape::WavePacket => (vec![3e6], 100e-9),
            EventShape::Doublet => (vec![], 50e-9),
        };
        EventConfig {
            modes_hz,
            decay_s,
            shape,
            ..EventConfig::default()
        }
    }

    /// Length after the onset past which the event is cut (exactly zero),
    /// seconds: `12 decay_s` for the multi-mode burst and the ringing,
    /// `10 decay_s` for the wave packet and the doublet.
    pub fn duration_s(&self) -> f64 {
        match self.shape {
            EventShape::MultiMode | EventShape::Ringing => 12.0 * self.decay_s,
            EventShape::WavePacket | EventShape::Doublet => 10.0 * self.decay_s,
        }
    }

    /// Phases drawn for each event: one per mode, one for the doublet.
    pub fn phase_count(&self) -> usize {
        match self.shape {
            EventShape::Doublet => 1,
            _ => self.modes_hz.len(),
        }
    }

    /// The unscaled shape `x` seconds after the onset with phases `phases`
    /// (missing phases are zero).
    fn raw(&self, x: f64, phases: &[f64]) -> f64 {
        use std::f64::consts::PI;
        if x.is_nan() || x <= 0.0 || x > self.duration_s() {
            return 0.0;
        }
        let ph = |k: usize| phases.get(k).copied().unwrap_or(0.0);
        match self.shape {
            EventShape::MultiMode => {
                let u = x / self.decay_s;
                let g = u * (1.0 - u).exp();
                // With φ = 0 the argument is unchanged (it is positive), so
                // zero-phase bursts are bit-identical to the original model.
                let s: f64 = self
                    .modes_hz
                    .iter()
                    .enumerate()
                    .map(|(k, f)| (2.0 * PI * f * x + ph(k)).sin())
                    .sum();
                g * s
            }
            EventShape::Ringing => {
                let s: f64 = self
                    .modes_hz
                    .iter()
                    .enumerate()
                    .map(|(k, f)| (2.0 * PI * f * x + ph(k)).sin())
                    .sum();
                (-x / self.decay_s).exp() * s
            }
            EventShape::WavePacket => {
                let y = x - 5.0 * self.decay_s;
                let w = (-0.5 * (y / self.decay_s).powi(2)).exp();
                let s: f64 = self
                    .modes_hz
                    .iter()
                    .enumerate()
                    .map(|(k, f)| (2.0 * PI * f * y + ph(k)).cos())
                    .sum();
                w * s
            }
            EventShape::Doublet => {
                let y = (x - 5.0 * self.decay_s) / self.decay_s;
                let p = if ph(0).cos() >= 0.0 { 1.0 } else { -1.0 };
                -p * y * (-0.5 * y * y).exp()
            }
        }
    }

    /// Maximum of the unscaled zero-phase multi-mode burst, on a grid of at
    /// most 1/200 of the fastest mode's period (relative error below 1e-3):
    /// the original model's normalisation, kept so its frames are unchanged.
    fn norm(&self) -> f64 {
        let f_max = self.modes_hz.iter().copied().fold(0.0, f64::max);
        let n = (self.duration_s() * f_max * 200.0).clamp(2000.0, 1e6) as usize;
        let d = self.duration_s() / n as f64;
        (0..=n)
            .map(|k| self.raw(k as f64 * d, &[]))
            .fold(0.0, f64::max)
    }

    /// (time after the onset, value) of the unscaled shape's largest
    /// positive excursion with `phases`: the best point of a grid of at most
    /// 1/200 of the fastest mode's period and of `decay_s` (its first point
    /// just after the onset, so that a step there counts), refined by golden
    /// section between its neighbours (to ~1e-15 s). A step at the onset
    /// gives a time just after it.
    fn peak_search(&self, phases: &[f64]) -> (f64, f64) {
        let dur = self.duration_s();
        let f_max = match self.shape {
            EventShape::Doublet => 0.0,
            _ => self.modes_hz.iter().copied().fold(0.0, f64::max),
        };
        let mut step = self.decay_s / 200.0;
        if f_max > 0.0 {
            step = step.min(1.0 / (200.0 * f_max));
        }
        let n = (dur / step).ceil().clamp(2000.0, 2e6) as usize;
        let d = dur / n as f64;
        let (mut k_best, mut best) = (0usize, f64::NEG_INFINITY);
        for k in 0..=n {
            // The first point is just after the onset, where a step starts.
            let x = if k == 0 { 1e-9 * d } else { k as f64 * d };
            let v = self.raw(x, phases);
            if v > best {
                (k_best, best) = (k, v);
            }
        }
        let mut a = (k_best as f64 - 1.0).max(0.0) * d;
        let mut b = ((k_best + 1) as f64 * d).min(dur);
        let mut c = b - GOLDEN * (b - a);
        let mut e = a + GOLDEN * (b - a);
        let (mut fc, mut fe) = (self.raw(c, phases), self.raw(e, phases));
        for _ in 0..200 {
            if b - a <= 1e-15 {
                break;
            }
            if fc >= fe {
                (b, e, fe) = (e, c, fc);
                c = b - GOLDEN * (b - a);
                fc = self.raw(c, phases);
            } else {
                (a, c, fc) = (c, e, fe);
                e = a + GOLDEN * (b - a);
                fe = self.raw(e, phases);
            }
        }
        let (x, v) = if fc >= fe { (c, fc) } else { (e, fe) };
        if v >= best {
            (x, v)
        } else if k_best == 0 {
            (1e-9 * d, best)
        } else {
            (k_best as f64 * d, best)
        }
    }

    /// The event with phases `phases_rad` (radians; missing ones are zero)
    /// scaled so that its largest positive excursion is `peak_v` volts. For
    /// the zero-phase multi-mode burst the scale is the original model's,
    /// `peak_v` over the grid maximum, and [`EventWave::peak_v`] (the true
    /// maximum) may exceed `peak_v` by less than 1e-3 relative.
    pub fn wave(&self, phases_rad: &[f64], peak_v: f64) -> EventWave {
        let (peak_offset_s, max) = self.peak_search(phases_rad);
        let legacy = self.shape == EventShape::MultiMode && phases_rad.iter().all(|&p| p == 0.0);
        let norm = if legacy { self.norm() } else { max };
        let scale = if norm > 0.0 { peak_v / norm } else { 0.0 };
        EventWave {
            cfg: self.clone(),
            phases_rad: phases_rad.to_vec(),
            scale,
            peak_offset_s,
            peak_v: scale * max,
        }
    }

    /// The zero-phase event `x_s` seconds after its onset, peaking at
    /// `peak_v`, volts. Finds the event's maximum on every call: use
    /// [`render`](Self::render) or [`wave`](Self::wave) for many samples.
    pub fn value(&self, x_s: f64) -> f64 {
        self.peak_v * self.raw(x_s, &[]) / self.zero_phase_norm()
    }

    /// The zero-phase event sampled every `dt_s` from `x0_s` after its
    /// onset: `n` values, volts.
    pub fn render(&self, x0_s: f64, dt_s: f64, n: usize) -> Vec<f64> {
        let scale = self.peak_v / self.zero_phase_norm();
        (0..n)
            .map(|k| scale * self.raw(x0_s + k as f64 * dt_s, &[]))
            .collect()
    }

    /// Time from the onset to the zero-phase event's largest positive
    /// excursion, seconds.
    pub fn peak_offset_s(&self) -> f64 {
        self.peak_search(&[]).0
    }

    fn zero_phase_norm(&self) -> f64 {
        match self.shape {
            EventShape::MultiMode => self.norm(),
            _ => self.peak_search(&[]).1,
        }
    }

    /// Checks the probability, amplitude, spread, modes, decay and placement
    /// (that a [`NearReturn`](EventPlacement::NearReturn) event has a target
    /// is checked by [`GenConfig::validate`]).
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..=1.0).contains(&self.probability) {
            return Err(format!(
                "events.probability {} outside [0, 1]",
                self.probability
            ));
        }
        if !(self.peak_v >= 0.0 && self.peak_v.is_finite()) {
            return Err(format!(
                "events.peak_v {} must be finite and >= 0",
                self.peak_v
            ));
        }
        if !(self.amplitude_spread >= 0.0 && self.amplitude_spread.is_finite()) {
            return Err(format!(
                "events.amplitude_spread {} must be finite and >= 0",
                self.amplitude_spread
            ));
        }
        if self.shape != EventShape::Doublet
            && (self.modes_hz.is_empty()
                || self.modes_hz.iter().any(|f| !(*f > 0.0 && f.is_finite())))
        {
            return Err(format!(
                "events.modes_hz {:?}: at least one positive frequency",
                self.modes_hz
            ));
        }
        if !(self.decay_s > 0.0 && self.decay_s.is_finite()) {
            return Err(format!("events.decay_s {} must be positive", self.decay_s));
        }
        match self.placement {
            EventPlacement::Uniform => {}
            EventPlacement::NearReturn { max_offset_s } => {
                if !(max_offset_s >= 0.0 && max_offset_s.is_finite()) {
                    return Err(format!(
                        "events.placement: max_offset_s {max_offset_s} must be finite and >= 0"
                    ));
                }
            }
            EventPlacement::InGate { from_s, to_s } => {
                if !(from_s.is_finite() && to_s.is_finite() && from_s <= to_s) {
                    return Err(format!(
                        "events.placement: gate [{from_s}, {to_s}] must be finite with from_s <= to_s"
                    ));
                }
            }
        }
        if self.zero_phase_norm() <= 0.0 {
            return Err("events: the event has no positive excursion".into());
        }
        Ok(())
    }
}

/// One event's waveform: an [`EventConfig`] with the event's phases and
/// scale fixed, ready to evaluate many times ([`EventConfig::wave`]).
#[derive(Debug, Clone, PartialEq)]
pub struct EventWave {
    cfg: EventConfig,
    phases_rad: Vec<f64>,
    scale: f64,
    peak_offset_s: f64,
    peak_v: f64,
}

impl EventWave {
    /// The event `x_s` seconds after its onset, volts.
    pub fn value(&self, x_s: f64) -> f64 {
        self.scale * self.cfg.raw(x_s, &self.phases_rad)
    }

    /// The event sampled every `dt_s` from `x0_s` after its onset: `n`
    /// values, volts.
    pub fn render(&self, x0_s: f64, dt_s: f64, n: usize) -> Vec<f64> {
        (0..n).map(|k| self.value(x0_s + k as f64 * dt_s)).collect()
    }

    /// Time from the onset to the largest positive excursion, seconds.
    pub fn peak_offset_s(&self) -> f64 {
        self.peak_offset_s
    }

    /// The largest positive excursion, volts.
    pub fn peak_v(&self) -> f64 {
        self.peak_v
    }

    /// Length after the onset past which the event is zero, seconds.
    pub fn duration_s(&self) -> f64 {
        self.cfg.duration_s()
    }

    /// The event's phases, radians.
    pub fn phases_rad(&self) -> &[f64] {
        &self.phases_rad
    }
}

/// What to generate. [`Default`] is the prototype as described in ch. 9–10.
#[derive(Debug, Clone, PartialEq)]
pub struct GenConfig {
    /// Sampling period, seconds (1 GS/s).
    pub dt_s: f64,
    /// Samples per channel (the scope recorded 2500).
    pub samples: usize,
    /// Name of the start channel (the default scene's).
    pub start_channel: String,
    /// Name of the stop channel (the default scene's).
    pub stop_channel: String,
    /// Sensor id written into each frame.
    pub sensor_id: String,
    /// Time between successive frames' triggers, seconds: sets
    /// `trigger_time_s = index * frame_period_s`.
    pub frame_period_s: f64,
    /// Shape of the start pulse.
    pub start_pulse: PulseFamily,
    /// Peak of the start pulse, volts.
    pub start_amplitude_v: f64,
    /// Shape of every return.
    pub return_pulse: PulseFamily,
    /// Targets: (range m, peak volts of its return at the receiver output).
    /// Returns that overlap add linearly before any limit or clipping.
    pub targets: Vec<(f64, f64)>,
    /// Fixed delay from the start pulse's onset to the onset of a return
    /// from range zero, seconds (the calibration constant).
    pub system_delay_s: f64,
    /// Mean of the receiver noise, volts.
    pub noise_mean_v: f64,
    /// Standard deviation of the receiver noise, volts (after any band limit,
    /// before quantisation).
    pub noise_sigma_v: f64,
    /// `Some(B)`: the noise passes a one-pole low-pass, `y[k] = a y[k-1] +
    /// sqrt(1 − a²) w[k]`, `a = exp(−2 pi B dt_s)` (−3 dB near `B` for
    /// `B << 1/dt_s`), started in its stationary state; `None`: white.
    pub noise_bandwidth_hz: Option<f64>,
    /// Standard deviation of the start channel's white noise, volts.
    pub start_noise_sigma_v: f64,
    /// ADC resolution: 1..=8 gives i8 codes, 9..=16 i16 codes; 0 leaves the
    /// channels unquantised in volts (f64).
    pub bits: u32,
    /// Stop channel ADC span (top rail − bottom rail), volts; `None`: set
    /// per configuration as a scope user would (see [`auto_full_scale_v`]).
    pub full_scale_v: Option<f64>,
    /// Start channel ADC span, volts; `None`: automatic, as for the stop channel.
    pub start_full_scale_v: Option<f64>,
    /// Fraction of the ADC span below 0 V (the user's baseline position):
    /// rails at `−f·span` and `(1 − f)·span`.
    pub baseline_fraction: f64,
    /// Receiver (TIA) output swing: the stop channel's analog signal plus
    /// noise is clamped to `±limit` before the ADC; `None`: no limit.
    pub receiver_limit_v: Option<f64>,
    /// RMS jitter of the shot time against the trigger, seconds. On top, the
    /// shot is uniformly random against the sample clock.
    pub start_jitter_s: f64,
    /// Nominal time of the shot after the first sample, seconds; the frame's
    /// `first_sample_offset_s` is `−pretrigger_s`.
    pub pretrigger_s: f64,
    /// Interference events on the stop channel; `None`: none.
    pub events: Option<EventConfig>,
    /// No start pulse and no returns: noise (and events) only; the scope's
    /// settings stay those of the laser-on configuration.
    pub laser_off: bool,
    /// Speed of light in the medium, m/s: [`C_VACUUM_M_PER_S`] /
    /// [`N_AIR_1550NM`] ≈ 299 710 637 m/s for air at 1550 nm.
    pub speed_of_light_m_per_s: f64,
}

impl Default for GenConfig {
    /// The prototype of ch. 9–10: 1 GS/s, 2500 samples (L13925); start pulse
    /// 0.304 V, rise 3.02 ns (L13787); one target at 1.83 m giving a 1.5 V
    /// return of rise 8.08 ns and FWHM 26.04 ns (L13871); 223.33 ns system
    /// delay (the amplifier's internal delay, L14493); receiver noise mean
    /// −0.5115 mV, variance 1.916e-4 V² (σ = 13.84 mV, Tables 10.14–10.15),
    /// white; 8-bit ADC scaled per channel; 500 kHz PRF (the ch. 10.4 runs).
    ///
    /// Assumed, as the source does not say: start-channel noise 2 mV, shot
    /// jitter 100 ps rms, shot 250 ns after the first sample, baseline a
    /// quarter of the span above the bottom rail, no interference events
    /// (their per-frame rate is not given; see [`EventConfig::default`]).
    fn default() -> Self {
        GenConfig {
            dt_s: 1e-9,
            samples: 2500,
            start_channel: "CH1".into(),
            stop_channel: "CH2".into(),
            sensor_id: "seedgen".into(),
            frame_period_s: 2e-6,
            start_pulse: PulseFamily::prototype_start(),
            start_amplitude_v: 0.304,
            return_pulse: PulseFamily::prototype_return(),
            targets: vec![(1.83, 1.5)],
            system_delay_s: 223.33e-9,
            noise_mean_v: -5.115e-4,
            noise_sigma_v: 1.916e-4_f64.sqrt(),
            noise_bandwidth_hz: None,
            start_noise_sigma_v: 2e-3,
            bits: 8,
            full_scale_v: None,
            start_full_scale_v: None,
            baseline_fraction: 0.25,
            receiver_limit_v: None,
            start_jitter_s: 100e-12,
            pretrigger_s: 250e-9,
            events: None,
            laser_off: false,
            speed_of_light_m_per_s: C_VACUUM_M_PER_S / N_AIR_1550NM,
        }
    }
}

impl GenConfig {
    /// Checks every field; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let pos = |name: &str, v: f64| {
            if v > 0.0 && v.is_finite() {
                Ok(())
            } else {
                Err(format!("{name} = {v}: must be positive"))
            }
        };
        let nonneg = |name: &str, v: f64| {
            if v >= 0.0 && v.is_finite() {
                Ok(())
            } else {
                Err(format!("{name} = {v}: must be >= 0"))
            }
        };
        pos("dt_s", self.dt_s)?;
        if self.samples == 0 {
            return Err("samples: must be at least 1".into());
        }
        pos("speed_of_light_m_per_s", self.speed_of_light_m_per_s)?;
        nonneg("frame_period_s", self.frame_period_s)?;
        nonneg("start_amplitude_v", self.start_amplitude_v)?;
        nonneg("noise_sigma_v", self.noise_sigma_v)?;
        nonneg("start_noise_sigma_v", self.start_noise_sigma_v)?;
        nonneg("start_jitter_s", self.start_jitter_s)?;
        if !self.noise_mean_v.is_finite()
            || !self.system_delay_s.is_finite()
            || !self.pretrigger_s.is_finite()
        {
            return Err("noise_mean_v, system_delay_s and pretrigger_s must be finite".into());
        }
        self.start_pulse
            .validate()
            .map_err(|e| format!("start_pulse: {e}"))?;
        self.return_pulse
            .validate()
            .map_err(|e| format!("return_pulse: {e}"))?;
        for &(r, a) in &self.targets {
            if !(r.is_finite() && a.is_finite()) {
                return Err(format!("targets: ({r}, {a}) must be finite"));
            }
        }
        if let Some(b) = self.noise_bandwidth_hz {
            pos("noise_bandwidth_hz", b)?;
        }
        if self.bits > 16 {
            return Err(format!("bits = {}: at most 16", self.bits));
        }
        if let Some(f) = self.full_scale_v {
            pos("full_scale_v", f)?;
        }
        if let Some(f) = self.start_full_scale_v {
            pos("start_full_scale_v", f)?;
        }
        if let Some(l) = self.receiver_limit_v {
            pos("receiver_limit_v", l)?;
        }
        if !(self.baseline_fraction > 0.0 && self.baseline_fraction < 1.0) {
            return Err(format!(
                "baseline_fraction = {}: must lie in (0, 1)",
                self.baseline_fraction
            ));
        }
        if let Some(e) = &self.events {
            e.validate()?;
            if matches!(e.placement, EventPlacement::NearReturn { .. }) && self.targets.is_empty() {
                return Err("events.placement: NearReturn needs at least one target".into());
            }
        }
        Ok(())
    }

    /// Time of flight of a target at `range_m`: `2 range_m / c`, seconds.
    pub fn tof_s(&self, range_m: f64) -> f64 {
        2.0 * range_m / self.speed_of_light_m_per_s
    }

    /// The stop channel's ADC span, volts (configured or automatic).
    pub fn stop_adc_span_v(&self) -> f64 {
        self.full_scale_v.unwrap_or_else(|| {
            let e = self.return_pulse.evaluator();
            let tofs: Vec<(f64, f64)> = self
                .targets
                .iter()
                .map(|&(r, a)| (self.tof_s(r), a))
                .collect();
            // Largest excursion of the noise-free returns (overlaps add),
            // on a grid of a tenth of a sample over the returns' span.
            let mut peak: f64 = 0.0;
            for &(tof, _) in &tofs {
                let t0 = tof + e.a;
                for k in -400..400 {
                    let t = t0 + k as f64 * self.dt_s / 10.0;
                    let v: f64 = tofs.iter().map(|&(u, a)| a * e.value(t - u)).sum();
                    peak = peak.max(v.abs());
                }
            }
            let peak = self.receiver_limit_v.map_or(peak, |l| peak.min(l));
            auto_full_scale_v(peak, self.noise_sigma_v, self.baseline_fraction)
        })
    }

    /// The start channel's ADC span, volts (configured or automatic).
    pub fn start_adc_span_v(&self) -> f64 {
        self.start_full_scale_v.unwrap_or_else(|| {
            auto_full_scale_v(
                self.start_amplitude_v,
                self.start_noise_sigma_v,
                self.baseline_fraction,
            )
        })
    }
}

/// The ADC span a scope user picks for a positive pulse of `peak_v` over
/// noise of `sigma_v`, with the baseline at `baseline_fraction` of the span:
/// the smallest span, rounded up to the fine V/div steps 1, 1.2, 1.5, 2, 2.5,
/// 3, 4, 5, 6, 8 × 10^n, that keeps `peak + 4σ` within 90 % of the part
/// above the baseline and puts the bottom rail at least 4σ below it (so the
/// noise stays visible and rarely clips). Never below 1 mV.
pub fn auto_full_scale_v(peak_v: f64, sigma_v: f64, baseline_fraction: f64) -> f64 {
    let f = baseline_fraction;
    let need = ((peak_v.max(0.0) + 4.0 * sigma_v) / (0.9 * (1.0 - f)))
        .max(4.0 * sigma_v / f)
        .max(1e-3);
    let decade = 10f64.powf(need.log10().floor());
    let steps = [1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0];
    let m = steps
        .iter()
        .find(|&&s| s * decade >= need * (1.0 - 1e-12))
        .copied()
        .unwrap_or(10.0);
    m * decade
}

/// One return as generated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueEcho {
    /// Target range, metres.
    pub range_m: f64,
    /// `2 range_m / speed_of_light_m_per_s`, seconds.
    pub tof_s: f64,
    /// Peak of the return at the receiver output, volts (before noise,
    /// limit and quantisation).
    pub amplitude_v: f64,
    /// Onset of the return relative to the trigger:
    /// `t_shot_s + system_delay_s + tof_s`, seconds.
    pub t_ref_s: f64,
}

/// What a frame holds, exactly.
#[derive(Debug, Clone, PartialEq)]
pub struct GenTruth {
    /// Instant of the shot relative to the trigger, seconds; the start pulse's
    /// onset (drawn for laser-off frames too, where no pulse is drawn).
    pub t_shot_s: f64,
    /// The returns, in target order; empty when the laser is off. A return
    /// whose onset lies outside the frame is listed all the same.
    pub returns: Vec<TrueEcho>,
    /// Onset of the interference event relative to the trigger, seconds
    /// (the same as `event`'s `onset_s`; kept for existing callers).
    pub event_at_s: Option<f64>,
    /// The interference event, if the frame holds one.
    pub event: Option<TrueEvent>,
    /// The laser was off.
    pub laser_off: bool,
    /// Stop-channel samples clipped at an ADC rail.
    pub clipped_stop: usize,
    /// Start-channel samples clipped at an ADC rail.
    pub clipped_start: usize,
}

/// One interference event as generated. Times relative to the trigger.
#[derive(Debug, Clone, PartialEq)]
pub struct TrueEvent {
    /// Onset: the event is exactly zero up to here, seconds. It may lie
    /// before the first sample (placements by peak) or after the last.
    pub onset_s: f64,
    /// Instant of the event's largest positive excursion, seconds.
    pub peak_s: f64,
    /// End: the event is exactly zero after `onset_s + duration_s`, seconds.
    pub end_s: f64,
    /// The event's largest positive excursion, volts (before noise, limit and
    /// quantisation; between samples in general).
    pub peak_v: f64,
    /// The event's waveform, `x` seconds after `onset_s` (its phases are
    /// [`EventWave::phases_rad`], all zero without `random_phase`).
    pub wave: EventWave,
}

impl TrueEvent {
    /// The event's contribution at `t_s` seconds after the trigger, volts.
    pub fn value_at(&self, t_s: f64) -> f64 {
        self.wave.value(t_s - self.onset_s)
    }
}

/// `frames` frames, indices `0..frames`, each as [`frame_with_seed`] makes it.
pub fn generate(cfg: &GenConfig, frames: usize, seed: u64) -> Vec<(Frame, GenTruth)> {
    (0..frames as u64)
        .map(|i| frame_with_seed(cfg, seed, i))
        .collect()
}

/// Frame `index` of the sequence `seed`: a function of (`cfg`, `seed`,
/// `index`) alone (ChaCha8 seeded with `seed`, stream `index`), so any frame
/// can be made on its own. Panics on an invalid configuration.
pub fn frame_with_seed(cfg: &GenConfig, seed: u64, index: u64) -> (Frame, GenTruth) {
    if let Err(e) = cfg.validate() {
        panic!("invalid GenConfig: {e}");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(index);
    let n = cfg.samples;
    let dt = cfg.dt_s;
    let t_first = -cfg.pretrigger_s;
    let time = |k: usize| t_first + k as f64 * dt;

    // Draw order is fixed: shot phase, jitter, event (2), stop noise (n),
    // start noise (n), then, only in frames holding an event, its amplitude
    // and phases. The last come after every other draw, so that they leave
    // the frames of earlier versions (which did not make them) unchanged.
    let phase: f64 = rng.random();
    let jitter: f64 = rng.sample(StandardNormal);
    let t_shot_s = (phase - 0.5) * dt + cfg.start_jitter_s * jitter;
    // Both event draws are made whether or not events are configured, so
    // switching them on leaves the rest of the frame's noise unchanged.
    let (u_event, u_position): (f64, f64) = (rng.random(), rng.random());
    let event_cfg = cfg.events.as_ref().filter(|ev| u_event < ev.probability);

    let returns: Vec<TrueEcho> = if cfg.laser_off {
        Vec::new()
    } else {
        cfg.targets
            .iter()
            .map(|&(range_m, amplitude_v)| {
                let tof_s = cfg.tof_s(range_m);
                TrueEcho {
                    range_m,
                    tof_s,
                    amplitude_v,
                    t_ref_s: t_shot_s + cfg.system_delay_s + tof_s,
                }
            })
            .collect()
    };

    let stop_noise: Vec<f64> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
    let start_noise: Vec<f64> = (0..n).map(|_| rng.sample(StandardNormal)).collect();

    let event: Option<TrueEvent> = event_cfg.map(|ev| {
        // Both drawn in every event, whichever options are on.
        let z: f64 = rng.sample(StandardNormal);
        let phases: Vec<f64> = (0..ev.phase_count())
            .map(|_| rng.random::<f64>() * std::f64::consts::TAU)
            .collect();
        let phases_rad = if ev.random_phase {
            phases
        } else {
            vec![0.0; ev.phase_count()]
        };
        let peak_v = if ev.amplitude_spread > 0.0 {
            let s2 = ev.amplitude_spread.powi(2).ln_1p();
            ev.peak_v * (s2.sqrt() * z - 0.5 * s2).exp()
        } else {
            ev.peak_v
        };
        let wave = ev.wave(&phases_rad, peak_v);
        let onset_s = match ev.placement {
            EventPlacement::Uniform => t_first + u_position * n as f64 * dt,
            EventPlacement::NearReturn { max_offset_s } => {
                let tof_s = cfg.tof_s(cfg.targets[0].0);
                let t_peak =
                    t_shot_s + cfg.system_delay_s + tof_s + cfg.return_pulse.peak_offset_s();
                t_peak + (2.0 * u_position - 1.0) * max_offset_s - wave.peak_offset_s()
            }
            EventPlacement::InGate { from_s, to_s } => {
                from_s + u_position * (to_s - from_s) - wave.peak_offset_s()
            }
        };
        TrueEvent {
            onset_s,
            peak_s: onset_s + wave.peak_offset_s(),
            end_s: onset_s + wave.duration_s(),
            peak_v: wave.peak_v(),
            wave,
        }
    });

    // Stop channel: returns + event + noise, limit.
    let ret = cfg.return_pulse.evaluator();
    let support = cfg.return_pulse.support_s();
    let mut stop = vec![0.0; n];
    for echo in &returns {
        for (k, v) in stop.iter_mut().enumerate() {
            let x = time(k) - echo.t_ref_s;
            if x > 0.0 && x < support {
                *v += echo.amplitude_v * ret.value(x);
            }
        }
    }
    if let Some(e) = &event {
        for (v, b) in stop
            .iter_mut()
            .zip(e.wave.render(t_first - e.onset_s, dt, n))
        {
            *v += b;
        }
    }
    let a = cfg
        .noise_bandwidth_hz
        .map_or(0.0, |b| (-2.0 * std::f64::consts::PI * b * dt).exp());
    let innovation = (1.0 - a * a).sqrt();
    let mut state = 0.0;
    for (k, (v, &w)) in stop.iter_mut().zip(&stop_noise).enumerate() {
        // Stationary from the first sample: y[0] ~ N(0, 1).
        state = if k == 0 {
            w
        } else {
            a * state + innovation * w
        };
        *v += cfg.noise_mean_v + cfg.noise_sigma_v * state;
        if let Some(l) = cfg.receiver_limit_v {
            *v = v.clamp(-l, l);
        }
    }

    // Start channel: start pulse + white noise.
    let st = cfg.start_pulse.evaluator();
    let st_support = cfg.start_pulse.support_s();
    let mut start = vec![0.0; n];
    for (k, (v, &w)) in start.iter_mut().zip(&start_noise).enumerate() {
        if !cfg.laser_off {
            let x = time(k) - t_shot_s;
            if x > 0.0 && x < st_support {
                *v += cfg.start_amplitude_v * st.value(x);
            }
        }
        *v += cfg.start_noise_sigma_v * w;
    }

    let (start_ch, clipped_start) = digitise(
        &cfg.start_channel,
        start,
        cfg.bits,
        cfg.start_adc_span_v(),
        cfg.baseline_fraction,
    );
    let (stop_ch, clipped_stop) = digitise(
        &cfg.stop_channel,
        stop,
        cfg.bits,
        cfg.stop_adc_span_v(),
        cfg.baseline_fraction,
    );
    let frame = Frame {
        sensor_id: cfg.sensor_id.clone(),
        sequence: index,
        trigger_time_s: index as f64 * cfg.frame_period_s,
        sample_interval_s: dt,
        first_sample_offset_s: t_first,
        channels: vec![start_ch, stop_ch],
        laser_off: cfg.laser_off,
    };
    let truth = GenTruth {
        t_shot_s,
        returns,
        event_at_s: event.as_ref().map(|e| e.onset_s),
        event,
        laser_off: cfg.laser_off,
        clipped_stop,
        clipped_start,
    };
    (frame, truth)
}

/// Quantises `volts` as an oscilloscope: `2^bits` codes over `span_v`, the
/// bottom rail at `−baseline_fraction·span_v`; `volts = code·vpc + offset`
/// with `vpc = span_v / 2^bits`, code `−2^(bits−1)` at the bottom rail.
/// Rounds to the nearest code and clips at the extreme codes: (channel,
/// samples clipped). `bits == 0` returns the volts unquantised.
pub fn digitise(
    name: &str,
    volts: Vec<f64>,
    bits: u32,
    span_v: f64,
    baseline_fraction: f64,
) -> (Channel, usize) {
    if bits == 0 {
        return (
            Channel::from_volts(name, ChannelRole::Unspecified, volts),
            0,
        );
    }
    let levels = (1u64 << bits) as f64;
    let vpc = span_v / levels;
    let lo_code = -(levels / 2.0);
    let hi_code = levels / 2.0 - 1.0;
    let offset_v = -baseline_fraction * span_v - lo_code * vpc;
    let mut clipped = 0;
    let codes: Vec<f64> = volts
        .iter()
        .map(|v| {
            let c = ((v - offset_v) / vpc).round();
            if c < lo_code || c > hi_code {
                clipped += 1;
            }
            c.clamp(lo_code, hi_code)
        })
        .collect();
    let samples = if bits <= 8 {
        Samples::I8(codes.iter().map(|&c| c as i8).collect())
    } else {
        Samples::I16(codes.iter().map(|&c| c as i16).collect())
    };
    let ch = Channel {
        name: name.into(),
        role: ChannelRole::Unspecified,
        samples,
        volts_per_code: vpc,
        offset_v,
    };
    (ch, clipped)
}
