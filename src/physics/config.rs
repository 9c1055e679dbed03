//! `[simulation]`: the scene section that drives the simulator.
//!
//! Every effect is modelled only when its section is present, so a scene says
//! exactly which physics it wants: no `[simulation.atmosphere]` means no
//! extinction, no `[simulation.interference]` means no mains burst, and so on.
//! All types are serde with `deny_unknown_fields`; [`SimulationConfig::validate`]
//! checks every value and names the dotted field and its allowed range.

use super::PhysicsError;
use crate::scene::FieldError;
use serde::{Deserialize, Serialize};

/// The whole `[simulation]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulationConfig {
    /// The transmitter; absent (or `off = true`): no shots, noise-only frames.
    #[serde(default)]
    pub laser: Option<LaserConfig>,
    /// Targets in the beam; empty: no returns.
    #[serde(default)]
    pub targets: Vec<TargetConfig>,
    /// Extinction along the path; absent: lossless medium.
    #[serde(default)]
    pub atmosphere: Option<AtmosphereConfig>,
    /// Receiver optics; required when there are targets or background light.
    #[serde(default)]
    pub receiver: Option<ReceiverConfig>,
    /// Solar background light (shot noise only: the AC-coupled receiver removes its DC).
    #[serde(default)]
    pub background: Option<BackgroundConfig>,
    /// Avalanche photodiode; required when there are targets or background light.
    #[serde(default)]
    pub apd: Option<ApdConfig>,
    /// Stop-channel transimpedance amplifier and what follows it before the digitiser.
    #[serde(default)]
    pub tia: Option<TiaConfig>,
    /// Start channel (PIN tap of the outgoing pulse); absent: the frame has no start channel.
    #[serde(default)]
    pub start: Option<StartConfig>,
    /// Structured mains-rate interference burst on the stop channel.
    #[serde(default)]
    pub interference: Option<InterferenceConfig>,
    /// Extra noise options (thermal override, skewness, DC offset).
    #[serde(default)]
    pub noise: Option<NoiseConfig>,
    /// The digitiser (always required: it defines the frame).
    pub digitiser: SimDigitiserConfig,
}

/// Shape of the emitted laser pulse (`[simulation.laser] pulse_shape`; not the
/// receiver-side [`crate::dsp::pulse::PulseShape`] trait).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LaserPulseShape {
    /// Gaussian; `pulse_width_s` is the FWHM; `emission_time_s` is the centre.
    Gaussian,
    /// Rectangular (a current-driven seed laser); `pulse_width_s` is the full
    /// width; `emission_time_s` is the leading edge.
    Rectangular,
}

/// `[simulation.laser]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaserConfig {
    /// Peak optical power leaving the transmitter, W.
    pub peak_power_w: f64,
    /// Pulse shape.
    #[serde(default = "default_shape")]
    pub pulse_shape: LaserPulseShape,
    /// FWHM (gaussian) or full width (rectangular), s.
    pub pulse_width_s: f64,
    /// Pulse repetition frequency, Hz; one frame per shot.
    pub prf_hz: f64,
    /// Wavelength, m (documentation and background filter; responsivity is given at it).
    #[serde(default = "default_wavelength")]
    pub wavelength_m: f64,
    /// Emission instant relative to the trigger, s (gaussian: centre; rectangular: leading edge).
    #[serde(default)]
    pub emission_time_s: f64,
    /// Beam divergence half-angle, rad (spot size for small targets and overlap).
    #[serde(default = "default_divergence")]
    pub beam_divergence_half_angle_rad: f64,
    /// Beam radius at the exit aperture, m.
    #[serde(default = "default_beam_radius")]
    pub beam_radius_m: f64,
    /// Laser switched off (shutter closed): the receiver's own noise only.
    #[serde(default)]
    pub off: bool,
}

fn default_shape() -> LaserPulseShape {
    LaserPulseShape::Gaussian
}
fn default_wavelength() -> f64 {
    1550e-9
}
fn default_divergence() -> f64 {
    // Table 9.2: 0.016 degrees.
    0.016_f64.to_radians()
}
fn default_beam_radius() -> f64 {
    1e-3
}

/// Target reflection model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetKind {
    /// Lambertian surface filling the beam.
    Extended,
    /// Lambertian surface of `area_m2`, smaller than the spot: scaled by A_target / A_spot.
    Small,
}

/// `[[simulation.targets]]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetConfig {
    /// Range from the transceiver, m.
    pub range_m: f64,
    /// Lambertian reflectivity in [0, 1].
    pub reflectivity: f64,
    /// Reflection model.
    #[serde(default = "default_kind")]
    pub kind: TargetKind,
    /// Area for `kind = "small"`, m².
    #[serde(default)]
    pub area_m2: Option<f64>,
    /// Angle between the beam and the surface normal, degrees (cos law).
    #[serde(default)]
    pub incidence_deg: f64,
}

fn default_kind() -> TargetKind {
    TargetKind::Extended
}

/// `[simulation.atmosphere]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AtmosphereConfig {
    /// Extinction coefficient α, per km (Table 9.5: 0.12 /km); T = exp(−α R) one way.
    pub extinction_per_km: f64,
}

/// `[simulation.receiver]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReceiverConfig {
    /// Receiver lens diameter, m.
    pub aperture_diameter_m: f64,
    /// Transmitter and receiver optics efficiency combined, (0, 1].
    pub optics_efficiency: f64,
    /// Receiver field-of-view half-angle, rad.
    #[serde(default = "default_fov")]
    pub fov_half_angle_rad: f64,
    /// Separation of the parallel transmitter and receiver axes, m (biaxial
    /// overlap; 0: coaxial, full overlap at all ranges).
    #[serde(default)]
    pub tx_rx_separation_m: f64,
    /// Optical band-pass filter width Δλ, m (background light only).
    #[serde(default = "default_filter")]
    pub filter_bandwidth_m: f64,
}

fn default_fov() -> f64 {
    // Table 9.2: 2 mm detector behind f = 25.4 mm gives 2.2546 degrees.
    2.2546_f64.to_radians()
}
fn default_filter() -> f64 {
    10e-9
}

/// `[simulation.background]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundConfig {
    /// Solar spectral radiance illuminating the scene, W/(m²·sr·nm) (the
    /// radiance a white Lambertian surface would have; ~0.07 at 1550 nm in full sun).
    pub spectral_radiance_w_per_m2_sr_nm: f64,
    /// Reflectivity of the scenery filling the field of view.
    #[serde(default = "default_bg_reflectivity")]
    pub reflectivity: f64,
}

fn default_bg_reflectivity() -> f64 {
    0.3
}

/// `[simulation.apd]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApdConfig {
    /// Unity-gain responsivity R_o, A/W.
    pub responsivity_a_per_w: f64,
    /// Multiplication gain M ≥ 1.
    pub gain: f64,
    /// Ionisation-coefficient ratio k in [0, 1] (McIntyre excess noise).
    #[serde(default = "default_k")]
    pub ionisation_ratio_k: f64,
    /// Primary (unmultiplied) dark current, A.
    #[serde(default)]
    pub dark_current_a: f64,
}

fn default_k() -> f64 {
    0.45
}

/// Cable/resonance ringing after the TIA.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, tag = "kind", rename_all = "snake_case")]
pub enum RingingConfig {
    /// A damped resonance added in parallel:
    /// H = 1 + amplitude · (ω0/Q) s / (s² + (ω0/Q) s + ω0²).
    Resonance {
        /// Resonance frequency f, Hz.
        frequency_hz: f64,
        /// Quality factor Q.
        q: f64,
        /// Gain of the resonant path relative to the direct path.
        amplitude: f64,
    },
    /// Mismatched cable: echoes of the (noise-free) signal, each the previous
    /// one times `coefficient` and delayed by `round_trip_s`.
    Reflection {
        /// Product of the two end reflection coefficients, (−1, 1).
        coefficient: f64,
        /// Cable round-trip delay, s.
        round_trip_s: f64,
        /// Number of echoes modelled.
        #[serde(default = "default_echoes")]
        echoes: u32,
    },
}

fn default_echoes() -> u32 {
    3
}

/// `[simulation.tia]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TiaConfig {
    /// Transimpedance, Ω (V/A).
    pub gain_ohm: f64,
    /// −3 dB bandwidth of the TIA (a single real pole), Hz.
    pub bandwidth_hz: f64,
    /// Input-referred noise current, A rms over `bandwidth_hz` (white: density
    /// = noise_current_a / sqrt(bandwidth_hz)); Table 9.5: 25 nA.
    #[serde(default)]
    pub noise_current_a: f64,
    /// Output swing limit, V (the TIA output saturates symmetrically at ±swing).
    #[serde(default)]
    pub swing_v: Option<f64>,
    /// AC-coupling time constant, s (a zero at DC and a pole at 1/τ).
    #[serde(default)]
    pub ac_coupling_s: Option<f64>,
    /// Fixed electrical delay of the stop path (amplifier, cables), s.
    #[serde(default)]
    pub delay_s: f64,
    /// Ringing after the TIA.
    #[serde(default)]
    pub ringing: Option<RingingConfig>,
}

/// `[simulation.start]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartConfig {
    /// Fraction of the transmitted peak power tapped to the PIN (after attenuators).
    pub tap_fraction: f64,
    /// PIN responsivity, A/W (Table 10.10: 0.85).
    pub responsivity_a_per_w: f64,
    /// Start TIA transimpedance, Ω (Table 10.10: 2000).
    pub gain_ohm: f64,
    /// Start TIA bandwidth, Hz (Table 10.10: 10 GHz).
    pub bandwidth_hz: f64,
    /// Fixed electrical delay of the start path, s.
    #[serde(default)]
    pub delay_s: f64,
    /// Stationary noise σ at the digitiser input, V.
    #[serde(default)]
    pub noise_sigma_v: f64,
    /// Negative dip after the pulse (the NPL trigger-out version): this fraction
    /// of the pulse, inverted, `dip_delay_s` later.
    #[serde(default)]
    pub dip_fraction: f64,
    /// Delay of the dip, s.
    #[serde(default)]
    pub dip_delay_s: f64,
}

/// `[simulation.interference]`: the fixed-shape burst the source traced to the
/// APD bias supply (modes below 10 MHz, repeating at the mains rate).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InterferenceConfig {
    /// Peak amplitude of the burst, V.
    pub amplitude_v: f64,
    /// Repetition rate, Hz (mains: 50 or 60; rectifier ripple: 100 or 120).
    #[serde(default = "default_mains")]
    pub rate_hz: f64,
    /// Burst duration, s (a Hann envelope).
    pub duration_s: f64,
    /// Mode frequencies, Hz (each below 10 MHz in the source).
    #[serde(default = "default_modes")]
    pub frequencies_hz: Vec<f64>,
    /// Each burst starts up to this long after its nominal mains instant
    /// (uniform), s: the mains phase wanders against the laser clock, so the
    /// bursts hit random frames instead of a pattern locked to the PRF.
    #[serde(default = "default_wander")]
    pub wander_s: f64,
}

fn default_wander() -> f64 {
    2e-3
}

fn default_mains() -> f64 {
    60.0
}
fn default_modes() -> Vec<f64> {
    vec![1.3e6, 3.1e6, 6.7e6]
}

/// `[simulation.noise]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct NoiseConfig {
    /// Stationary thermal (TIA) noise σ at the digitiser input, V: overrides the
    /// value implied by `tia.noise_current_a`.
    #[serde(default)]
    pub thermal_sigma_v: Option<f64>,
    /// Target skewness of the stationary noise (the source measured 0.7647):
    /// the white innovations are given a quadratic (skewed) distortion sized so
    /// that the noise at the digitiser input has this skewness.
    #[serde(default)]
    pub skewness: Option<f64>,
    /// DC offset of the stop channel, V (the source: mean −5.115e-4 V).
    #[serde(default)]
    pub offset_v: f64,
}

/// `[simulation.digitiser]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimDigitiserConfig {
    /// Sampling period, s.
    pub sample_interval_s: f64,
    /// Samples per channel per frame.
    pub samples_per_frame: usize,
    /// Samples before the trigger.
    #[serde(default)]
    pub pre_trigger_samples: usize,
    /// Resolution, bits in [2, 16] (≤ 8: i8 codes, else i16).
    pub bits: u32,
    /// Lowest code's voltage, V.
    pub full_scale_low_v: f64,
    /// Highest code's voltage, V.
    pub full_scale_high_v: f64,
    /// Analogue bandwidth (a single pole), Hz; absent: none.
    #[serde(default)]
    pub bandwidth_hz: Option<f64>,
    /// Aperture (sampling-instant) jitter σ, s, independent per sample.
    #[serde(default)]
    pub aperture_jitter_s: f64,
    /// Trigger jitter σ, s: the whole frame's time base shifts relative to the shot.
    #[serde(default)]
    pub trigger_jitter_s: f64,
    /// The sample clock is not locked to the laser: the trigger falls uniformly
    /// within a sample interval (±0.5 sample), as on an oscilloscope.
    #[serde(default)]
    pub sample_clock_asynchronous: bool,
    /// Internal fine-grid oversampling for the noise-free waveforms.
    #[serde(default = "default_oversample")]
    pub oversample: usize,
    /// Start channel name.
    #[serde(default = "default_start_name")]
    pub start_channel: String,
    /// Stop channel name.
    #[serde(default = "default_stop_name")]
    pub stop_channel: String,
}

fn default_oversample() -> usize {
    16
}
fn default_start_name() -> String {
    "CH1".into()
}
fn default_stop_name() -> String {
    "CH2".into()
}

/// Validation helper: builds the error naming the field.
fn bad(field: impl Into<String>, value: impl ToString, allowed: &'static str) -> PhysicsError {
    PhysicsError::Invalid(FieldError::new(field, value, allowed))
}

/// `lo < x <= hi` and finite.
fn in_open_closed(x: f64, lo: f64, hi: f64) -> bool {
    x.is_finite() && x > lo && x <= hi
}

/// `lo <= x <= hi` and finite.
fn in_closed(x: f64, lo: f64, hi: f64) -> bool {
    x.is_finite() && x >= lo && x <= hi
}

impl SimulationConfig {
    /// Checks every value against its allowed range; errors name the dotted
    /// field (`simulation.targets[1].range_m`) and the allowed range.
    pub fn validate(&self) -> Result<(), PhysicsError> {
        let d = &self.digitiser;
        if !in_open_closed(d.sample_interval_s, 0.0, 1e-3) {
            return Err(bad(
                "simulation.digitiser.sample_interval_s",
                d.sample_interval_s,
                "(0, 1e-3] s",
            ));
        }
        if d.samples_per_frame < 2 || d.samples_per_frame > 10_000_000 {
            return Err(bad(
                "simulation.digitiser.samples_per_frame",
                d.samples_per_frame,
                "[2, 10000000]",
            ));
        }
        if d.pre_trigger_samples >= d.samples_per_frame {
            return Err(bad(
                "simulation.digitiser.pre_trigger_samples",
                d.pre_trigger_samples,
                "[0, samples_per_frame)",
            ));
        }
        if !(2..=16).contains(&d.bits) {
            return Err(bad("simulation.digitiser.bits", d.bits, "[2, 16]"));
        }
        if !(d.full_scale_low_v.is_finite()
            && d.full_scale_high_v.is_finite()
            && d.full_scale_low_v < d.full_scale_high_v)
        {
            return Err(bad(
                "simulation.digitiser.full_scale_high_v",
                format!("{} (low {})", d.full_scale_high_v, d.full_scale_low_v),
                "finite volts with full_scale_low_v < full_scale_high_v",
            ));
        }
        if let Some(b) = d.bandwidth_hz
            && !in_open_closed(b, 0.0, 1e12)
        {
            return Err(bad("simulation.digitiser.bandwidth_hz", b, "(0, 1e12] Hz"));
        }
        if !in_closed(d.aperture_jitter_s, 0.0, d.sample_interval_s) {
            return Err(bad(
                "simulation.digitiser.aperture_jitter_s",
                d.aperture_jitter_s,
                "[0, sample_interval_s] s",
            ));
        }
        if !in_closed(d.trigger_jitter_s, 0.0, 1e-6) {
            return Err(bad(
                "simulation.digitiser.trigger_jitter_s",
                d.trigger_jitter_s,
                "[0, 1e-6] s",
            ));
        }
        if !(1..=256).contains(&d.oversample) {
            return Err(bad(
                "simulation.digitiser.oversample",
                d.oversample,
                "[1, 256]",
            ));
        }
        if d.start_channel.trim().is_empty()
            || crate::frame::channel_key(&d.start_channel)
                == crate::frame::channel_key(&d.stop_channel)
        {
            return Err(bad(
                "simulation.digitiser.start_channel",
                format!("{:?}", d.start_channel),
                "a non-empty channel name other than stop_channel",
            ));
        }
        if d.stop_channel.trim().is_empty() {
            return Err(bad(
                "simulation.digitiser.stop_channel",
                "\"\"",
                "a non-empty channel name",
            ));
        }

        if let Some(l) = &self.laser {
            if !in_open_closed(l.peak_power_w, 0.0, 1e9) {
                return Err(bad(
                    "simulation.laser.peak_power_w",
                    l.peak_power_w,
                    "(0, 1e9] W",
                ));
            }
            if !in_open_closed(l.pulse_width_s, 0.0, 1e-5) {
                return Err(bad(
                    "simulation.laser.pulse_width_s",
                    l.pulse_width_s,
                    "(0, 1e-5] s",
                ));
            }
            if !in_open_closed(l.prf_hz, 0.0, 1e9) {
                return Err(bad("simulation.laser.prf_hz", l.prf_hz, "(0, 1e9] Hz"));
            }
            if !in_open_closed(l.wavelength_m, 1e-7, 2e-5) {
                return Err(bad(
                    "simulation.laser.wavelength_m",
                    l.wavelength_m,
                    "(1e-7, 2e-5] m",
                ));
            }
            if !in_closed(l.emission_time_s, -1e-3, 1e-3) {
                return Err(bad(
                    "simulation.laser.emission_time_s",
                    l.emission_time_s,
                    "[-1e-3, 1e-3] s",
                ));
            }
            if !in_closed(l.beam_divergence_half_angle_rad, 0.0, 0.5) {
                return Err(bad(
                    "simulation.laser.beam_divergence_half_angle_rad",
                    l.beam_divergence_half_angle_rad,
                    "[0, 0.5] rad",
                ));
            }
            if !in_open_closed(l.beam_radius_m, 0.0, 1.0) {
                return Err(bad(
                    "simulation.laser.beam_radius_m",
                    l.beam_radius_m,
                    "(0, 1] m",
                ));
            }
        }
        for (i, t) in self.targets.iter().enumerate() {
            let f = |name: &str| format!("simulation.targets[{i}].{name}");
            if !in_open_closed(t.range_m, 0.0, 1e6) {
                return Err(bad(f("range_m"), t.range_m, "(0, 1e6] m"));
            }
            if !in_closed(t.reflectivity, 0.0, 1.0) {
                return Err(bad(f("reflectivity"), t.reflectivity, "[0, 1]"));
            }
            if !in_closed(t.incidence_deg, 0.0, 89.9) {
                return Err(bad(
                    f("incidence_deg"),
                    t.incidence_deg,
                    "[0, 89.9] degrees",
                ));
            }
            match (t.kind, t.area_m2) {
                (TargetKind::Small, None) => {
                    return Err(bad(
                        f("area_m2"),
                        "missing",
                        "(0, 1e6] m² (required for kind = \"small\")",
                    ));
                }
                (TargetKind::Small, Some(a)) if !in_open_closed(a, 0.0, 1e6) => {
                    return Err(bad(f("area_m2"), a, "(0, 1e6] m²"));
                }
                (TargetKind::Extended, Some(a)) => {
                    return Err(bad(f("area_m2"), a, "absent for kind = \"extended\""));
                }
                _ => {}
            }
        }
        if let Some(a) = &self.atmosphere
            && !in_closed(a.extinction_per_km, 0.0, 1e3)
        {
            return Err(bad(
                "simulation.atmosphere.extinction_per_km",
                a.extinction_per_km,
                "[0, 1000] /km",
            ));
        }
        if let Some(r) = &self.receiver {
            if !in_open_closed(r.aperture_diameter_m, 0.0, 10.0) {
                return Err(bad(
                    "simulation.receiver.aperture_diameter_m",
                    r.aperture_diameter_m,
                    "(0, 10] m",
                ));
            }
            if !in_open_closed(r.optics_efficiency, 0.0, 1.0) {
                return Err(bad(
                    "simulation.receiver.optics_efficiency",
                    r.optics_efficiency,
                    "(0, 1]",
                ));
            }
            if !in_open_closed(r.fov_half_angle_rad, 0.0, 1.5) {
                return Err(bad(
                    "simulation.receiver.fov_half_angle_rad",
                    r.fov_half_angle_rad,
                    "(0, 1.5] rad",
                ));
            }
            if !in_closed(r.tx_rx_separation_m, 0.0, 10.0) {
                return Err(bad(
                    "simulation.receiver.tx_rx_separation_m",
                    r.tx_rx_separation_m,
                    "[0, 10] m",
                ));
            }
            if !in_open_closed(r.filter_bandwidth_m, 0.0, 1e-5) {
                return Err(bad(
                    "simulation.receiver.filter_bandwidth_m",
                    r.filter_bandwidth_m,
                    "(0, 1e-5] m",
                ));
            }
        }
        if let Some(b) = &self.background {
            if !in_closed(b.spectral_radiance_w_per_m2_sr_nm, 0.0, 1e3) {
                return Err(bad(
                    "simulation.background.spectral_radiance_w_per_m2_sr_nm",
                    b.spectral_radiance_w_per_m2_sr_nm,
                    "[0, 1000] W/(m²·sr·nm)",
                ));
            }
            if !in_closed(b.reflectivity, 0.0, 1.0) {
                return Err(bad(
                    "simulation.background.reflectivity",
                    b.reflectivity,
                    "[0, 1]",
                ));
            }
        }
        if let Some(a) = &self.apd {
            if !in_open_closed(a.responsivity_a_per_w, 0.0, 100.0) {
                return Err(bad(
                    "simulation.apd.responsivity_a_per_w",
                    a.responsivity_a_per_w,
                    "(0, 100] A/W",
                ));
            }
            if !in_closed(a.gain, 1.0, 1e4) {
                return Err(bad("simulation.apd.gain", a.gain, "[1, 10000]"));
            }
            if !in_closed(a.ionisation_ratio_k, 0.0, 1.0) {
                return Err(bad(
                    "simulation.apd.ionisation_ratio_k",
                    a.ionisation_ratio_k,
                    "[0, 1]",
                ));
            }
            if !in_closed(a.dark_current_a, 0.0, 1.0) {
                return Err(bad(
                    "simulation.apd.dark_current_a",
                    a.dark_current_a,
                    "[0, 1] A",
                ));
            }
        }
        if let Some(t) = &self.tia {
            if !in_open_closed(t.gain_ohm, 0.0, 1e12) {
                return Err(bad("simulation.tia.gain_ohm", t.gain_ohm, "(0, 1e12] ohm"));
            }
            if !in_open_closed(t.bandwidth_hz, 0.0, 1e12) {
                return Err(bad(
                    "simulation.tia.bandwidth_hz",
                    t.bandwidth_hz,
                    "(0, 1e12] Hz",
                ));
            }
            if !in_closed(t.noise_current_a, 0.0, 1.0) {
                return Err(bad(
                    "simulation.tia.noise_current_a",
                    t.noise_current_a,
                    "[0, 1] A",
                ));
            }
            if let Some(s) = t.swing_v
                && !in_open_closed(s, 0.0, 1e3)
            {
                return Err(bad("simulation.tia.swing_v", s, "(0, 1000] V"));
            }
            if let Some(tau) = t.ac_coupling_s
                && !in_open_closed(tau, 0.0, 10.0)
            {
                return Err(bad("simulation.tia.ac_coupling_s", tau, "(0, 10] s"));
            }
            if !in_closed(t.delay_s, 0.0, 1e-3) {
                return Err(bad("simulation.tia.delay_s", t.delay_s, "[0, 1e-3] s"));
            }
            match &t.ringing {
                Some(RingingConfig::Resonance {
                    frequency_hz,
                    q,
                    amplitude,
                }) => {
                    if !in_open_closed(*frequency_hz, 0.0, 1e12) {
                        return Err(bad(
                            "simulation.tia.ringing.frequency_hz",
                            frequency_hz,
                            "(0, 1e12] Hz",
                        ));
                    }
                    if !in_closed(*q, 0.05, 1e4) {
                        return Err(bad("simulation.tia.ringing.q", q, "[0.05, 10000]"));
                    }
                    if !in_closed(*amplitude, -10.0, 10.0) {
                        return Err(bad(
                            "simulation.tia.ringing.amplitude",
                            amplitude,
                            "[-10, 10]",
                        ));
                    }
                }
                Some(RingingConfig::Reflection {
                    coefficient,
                    round_trip_s,
                    echoes,
                }) => {
                    if !(coefficient.is_finite() && coefficient.abs() < 1.0) {
                        return Err(bad(
                            "simulation.tia.ringing.coefficient",
                            coefficient,
                            "(-1, 1)",
                        ));
                    }
                    if !in_open_closed(*round_trip_s, 0.0, 1e-5) {
                        return Err(bad(
                            "simulation.tia.ringing.round_trip_s",
                            round_trip_s,
                            "(0, 1e-5] s",
                        ));
                    }
                    if *echoes == 0 || *echoes > 100 {
                        return Err(bad("simulation.tia.ringing.echoes", echoes, "[1, 100]"));
                    }
                }
                None => {}
            }
        }
        if let Some(s) = &self.start {
            if !in_open_closed(s.tap_fraction, 0.0, 1.0) {
                return Err(bad(
                    "simulation.start.tap_fraction",
                    s.tap_fraction,
                    "(0, 1]",
                ));
            }
            if !in_open_closed(s.responsivity_a_per_w, 0.0, 100.0) {
                return Err(bad(
                    "simulation.start.responsivity_a_per_w",
                    s.responsivity_a_per_w,
                    "(0, 100] A/W",
                ));
            }
            if !in_open_closed(s.gain_ohm, 0.0, 1e12) {
                return Err(bad(
                    "simulation.start.gain_ohm",
                    s.gain_ohm,
                    "(0, 1e12] ohm",
                ));
            }
            if !in_open_closed(s.bandwidth_hz, 0.0, 1e12) {
                return Err(bad(
                    "simulation.start.bandwidth_hz",
                    s.bandwidth_hz,
                    "(0, 1e12] Hz",
                ));
            }
            if !in_closed(s.delay_s, 0.0, 1e-3) {
                return Err(bad("simulation.start.delay_s", s.delay_s, "[0, 1e-3] s"));
            }
            if !in_closed(s.noise_sigma_v, 0.0, 1e3) {
                return Err(bad(
                    "simulation.start.noise_sigma_v",
                    s.noise_sigma_v,
                    "[0, 1000] V",
                ));
            }
            if !in_closed(s.dip_fraction, 0.0, 1.0) {
                return Err(bad(
                    "simulation.start.dip_fraction",
                    s.dip_fraction,
                    "[0, 1]",
                ));
            }
            if !in_closed(s.dip_delay_s, 0.0, 1e-5) {
                return Err(bad(
                    "simulation.start.dip_delay_s",
                    s.dip_delay_s,
                    "[0, 1e-5] s",
                ));
            }
        }
        if let Some(i) = &self.interference {
            if !in_closed(i.amplitude_v, 0.0, 1e3) {
                return Err(bad(
                    "simulation.interference.amplitude_v",
                    i.amplitude_v,
                    "[0, 1000] V",
                ));
            }
            if !in_open_closed(i.rate_hz, 0.0, 1e6) {
                return Err(bad(
                    "simulation.interference.rate_hz",
                    i.rate_hz,
                    "(0, 1e6] Hz",
                ));
            }
            if !(in_open_closed(i.duration_s, 0.0, 1.0) && i.duration_s * i.rate_hz < 1.0) {
                return Err(bad(
                    "simulation.interference.duration_s",
                    i.duration_s,
                    "(0, 1/rate_hz) s (bursts must not overlap)",
                ));
            }
            if !(in_closed(i.wander_s, 0.0, 1.0) && (i.wander_s + i.duration_s) * i.rate_hz < 1.0) {
                return Err(bad(
                    "simulation.interference.wander_s",
                    i.wander_s,
                    "[0, 1/rate_hz - duration_s) s (bursts must not overlap)",
                ));
            }
            if i.frequencies_hz.is_empty() || i.frequencies_hz.len() > 32 {
                return Err(bad(
                    "simulation.interference.frequencies_hz",
                    format!("{} modes", i.frequencies_hz.len()),
                    "1 to 32 modes",
                ));
            }
            for (k, f) in i.frequencies_hz.iter().enumerate() {
                if !in_open_closed(*f, 0.0, 1e10) {
                    return Err(bad(
                        format!("simulation.interference.frequencies_hz[{k}]"),
                        f,
                        "(0, 1e10] Hz",
                    ));
                }
            }
        }
        if let Some(n) = &self.noise {
            if let Some(s) = n.thermal_sigma_v
                && !in_closed(s, 0.0, 1e3)
            {
                return Err(bad("simulation.noise.thermal_sigma_v", s, "[0, 1000] V"));
            }
            if let Some(g) = n.skewness
                && !in_closed(g, -2.0, 2.0)
            {
                return Err(bad("simulation.noise.skewness", g, "[-2, 2]"));
            }
            if !in_closed(n.offset_v, -1e3, 1e3) {
                return Err(bad(
                    "simulation.noise.offset_v",
                    n.offset_v,
                    "[-1000, 1000] V",
                ));
            }
        }

        // Sections an effect depends on.
        let laser_on = self.laser.as_ref().is_some_and(|l| !l.off);
        let optical = (laser_on && !self.targets.is_empty()) || self.background.is_some();
        if optical {
            if self.receiver.is_none() {
                return Err(PhysicsError::MissingSection {
                    section: "simulation.receiver",
                    needed_by: "targets or background light",
                });
            }
            if self.apd.is_none() {
                return Err(PhysicsError::MissingSection {
                    section: "simulation.apd",
                    needed_by: "targets or background light",
                });
            }
            if self.tia.is_none() {
                return Err(PhysicsError::MissingSection {
                    section: "simulation.tia",
                    needed_by: "targets or background light",
                });
            }
        }
        if !self.targets.is_empty() && self.laser.is_none() {
            return Err(PhysicsError::MissingSection {
                section: "simulation.laser",
                needed_by: "targets",
            });
        }
        if self.start.is_some() && self.laser.is_none() {
            return Err(PhysicsError::MissingSection {
                section: "simulation.laser",
                needed_by: "the start channel",
            });
        }
        if self.apd.is_some() && self.tia.is_none() {
            return Err(PhysicsError::MissingSection {
                section: "simulation.tia",
                needed_by: "the APD",
            });
        }
        Ok(())
    }
}
