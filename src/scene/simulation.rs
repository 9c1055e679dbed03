//! `[simulation]`: the scene section that drives the simulator (`physics`).
//!
//! Every effect is modelled only when its section is present, so a scene says
//! exactly which physics it wants: no `[simulation.atmosphere]` means no
//! extinction, no `[simulation.interference]` means no mains burst, no
//! `[simulation.interference_events]` means no interference events, and so on.
//! All types are serde with `deny_unknown_fields`; [`SimulationConfig::validate`]
//! checks every value and names the dotted field and its allowed range.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// Errors of the `[simulation]` section and of building a simulator from it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimulationError {
    /// A value out of its allowed range (the field is dotted, e.g.
    /// `simulation.targets[1].range_m`).
    #[error(transparent)]
    Invalid(#[from] FieldError),
    /// A section an effect depends on is missing.
    #[error("missing [{section}] section: needed by {needed_by}")]
    MissingSection {
        /// Dotted section name.
        section: &'static str,
        /// What needs it.
        needed_by: &'static str,
    },
}

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
    /// Short interference events on the stop channel (a fraction of a frame
    /// long, at a random position, in some frames).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interference_events: Option<InterferenceEventsConfig>,
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

impl LaserConfig {
    /// Checks `[simulation.laser]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.laser.peak_power_w", self.peak_power_w.into(), Range::positive_max(1e9), "(0, 1e9] W"),
            ("simulation.laser.pulse_width_s", self.pulse_width_s.into(), Range::positive_max(1e-5), "(0, 1e-5] s"),
            ("simulation.laser.prf_hz", self.prf_hz.into(), Range::positive_max(1e9), "(0, 1e9] Hz"),
            ("simulation.laser.wavelength_m", self.wavelength_m.into(), Range::open_closed(1e-7, 2e-5), "(1e-7, 2e-5] m"),
            ("simulation.laser.emission_time_s", self.emission_time_s.into(), Range::closed(-1e-3, 1e-3), "[-1e-3, 1e-3] s"),
            (
                "simulation.laser.beam_divergence_half_angle_rad",
                self.beam_divergence_half_angle_rad.into(),
                Range::closed(0.0, 0.5),
                "[0, 0.5] rad",
            ),
            ("simulation.laser.beam_radius_m", self.beam_radius_m.into(), Range::positive_max(1.0), "(0, 1] m"),
        ])
    }
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

impl TargetConfig {
    /// Checks target `index` of `[[simulation.targets]]`.
    pub fn validate(&self, index: usize) -> Result<(), FieldError> {
        let f = |name: &str| format!("simulation.targets[{index}].{name}");
        check(&[
            (&f("range_m"), self.range_m.into(), Range::positive_max(1e6), "(0, 1e6] m"),
            (&f("reflectivity"), self.reflectivity.into(), Range::closed(0.0, 1.0), "[0, 1]"),
            (&f("incidence_deg"), self.incidence_deg.into(), Range::closed(0.0, 89.9), "[0, 89.9] degrees"),
        ])?;
        match (self.kind, self.area_m2) {
            (TargetKind::Small, None) => Err(FieldError::new(
                f("area_m2"),
                "missing",
                "(0, 1e6] m² (required for kind = \"small\")",
            )),
            (TargetKind::Small, Some(a)) => check(&[(&f("area_m2"), a.into(), Range::positive_max(1e6), "(0, 1e6] m²")]),
            (TargetKind::Extended, Some(a)) => Err(FieldError::new(f("area_m2"), a, "absent for kind = \"extended\"")),
            _ => Ok(()),
        }
    }
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

impl AtmosphereConfig {
    /// Checks `[simulation.atmosphere]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[(
            "simulation.atmosphere.extinction_per_km",
            self.extinction_per_km.into(),
            Range::closed(0.0, 1e3),
            "[0, 1000] /km",
        )])
    }
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

impl ReceiverConfig {
    /// Checks `[simulation.receiver]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.receiver.aperture_diameter_m", self.aperture_diameter_m.into(), Range::positive_max(10.0), "(0, 10] m"),
            ("simulation.receiver.optics_efficiency", self.optics_efficiency.into(), Range::positive_max(1.0), "(0, 1]"),
            ("simulation.receiver.fov_half_angle_rad", self.fov_half_angle_rad.into(), Range::positive_max(1.5), "(0, 1.5] rad"),
            ("simulation.receiver.tx_rx_separation_m", self.tx_rx_separation_m.into(), Range::closed(0.0, 10.0), "[0, 10] m"),
            ("simulation.receiver.filter_bandwidth_m", self.filter_bandwidth_m.into(), Range::positive_max(1e-5), "(0, 1e-5] m"),
        ])
    }
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

impl BackgroundConfig {
    /// Checks `[simulation.background]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            (
                "simulation.background.spectral_radiance_w_per_m2_sr_nm",
                self.spectral_radiance_w_per_m2_sr_nm.into(),
                Range::closed(0.0, 1e3),
                "[0, 1000] W/(m²·sr·nm)",
            ),
            ("simulation.background.reflectivity", self.reflectivity.into(), Range::closed(0.0, 1.0), "[0, 1]"),
        ])
    }
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

impl ApdConfig {
    /// Checks `[simulation.apd]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.apd.responsivity_a_per_w", self.responsivity_a_per_w.into(), Range::positive_max(100.0), "(0, 100] A/W"),
            ("simulation.apd.gain", self.gain.into(), Range::closed(1.0, 1e4), "[1, 10000]"),
            ("simulation.apd.ionisation_ratio_k", self.ionisation_ratio_k.into(), Range::closed(0.0, 1.0), "[0, 1]"),
            ("simulation.apd.dark_current_a", self.dark_current_a.into(), Range::closed(0.0, 1.0), "[0, 1] A"),
        ])
    }
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

impl TiaConfig {
    /// Checks `[simulation.tia]` and its ringing.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.tia.gain_ohm", self.gain_ohm.into(), Range::positive_max(1e12), "(0, 1e12] ohm"),
            ("simulation.tia.bandwidth_hz", self.bandwidth_hz.into(), Range::positive_max(1e12), "(0, 1e12] Hz"),
            ("simulation.tia.noise_current_a", self.noise_current_a.into(), Range::closed(0.0, 1.0), "[0, 1] A"),
        ])?;
        if let Some(s) = self.swing_v {
            check(&[("simulation.tia.swing_v", s.into(), Range::positive_max(1e3), "(0, 1000] V")])?;
        }
        if let Some(tau) = self.ac_coupling_s {
            check(&[("simulation.tia.ac_coupling_s", tau.into(), Range::positive_max(10.0), "(0, 10] s")])?;
        }
        check(&[("simulation.tia.delay_s", self.delay_s.into(), Range::closed(0.0, 1e-3), "[0, 1e-3] s")])?;
        match &self.ringing {
            Some(RingingConfig::Resonance {
                frequency_hz,
                q,
                amplitude,
            }) => check(&[
                ("simulation.tia.ringing.frequency_hz", (*frequency_hz).into(), Range::positive_max(1e12), "(0, 1e12] Hz"),
                ("simulation.tia.ringing.q", (*q).into(), Range::closed(0.05, 1e4), "[0.05, 10000]"),
                ("simulation.tia.ringing.amplitude", (*amplitude).into(), Range::closed(-10.0, 10.0), "[-10, 10]"),
            ]),
            Some(RingingConfig::Reflection {
                coefficient,
                round_trip_s,
                echoes,
            }) => check(&[
                ("simulation.tia.ringing.coefficient", (*coefficient).into(), Range::open(-1.0, 1.0), "(-1, 1)"),
                ("simulation.tia.ringing.round_trip_s", (*round_trip_s).into(), Range::positive_max(1e-5), "(0, 1e-5] s"),
                ("simulation.tia.ringing.echoes", (*echoes).into(), Range::closed(1.0, 100.0), "[1, 100]"),
            ]),
            None => Ok(()),
        }
    }
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

impl StartConfig {
    /// Checks `[simulation.start]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.start.tap_fraction", self.tap_fraction.into(), Range::positive_max(1.0), "(0, 1]"),
            ("simulation.start.responsivity_a_per_w", self.responsivity_a_per_w.into(), Range::positive_max(100.0), "(0, 100] A/W"),
            ("simulation.start.gain_ohm", self.gain_ohm.into(), Range::positive_max(1e12), "(0, 1e12] ohm"),
            ("simulation.start.bandwidth_hz", self.bandwidth_hz.into(), Range::positive_max(1e12), "(0, 1e12] Hz"),
            ("simulation.start.delay_s", self.delay_s.into(), Range::closed(0.0, 1e-3), "[0, 1e-3] s"),
            ("simulation.start.noise_sigma_v", self.noise_sigma_v.into(), Range::closed(0.0, 1e3), "[0, 1000] V"),
            ("simulation.start.dip_fraction", self.dip_fraction.into(), Range::closed(0.0, 1.0), "[0, 1]"),
            ("simulation.start.dip_delay_s", self.dip_delay_s.into(), Range::closed(0.0, 1e-5), "[0, 1e-5] s"),
        ])
    }
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

impl InterferenceConfig {
    /// Checks `[simulation.interference]`: bursts must not overlap.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.interference.amplitude_v", self.amplitude_v.into(), Range::closed(0.0, 1e3), "[0, 1000] V"),
            ("simulation.interference.rate_hz", self.rate_hz.into(), Range::positive_max(1e6), "(0, 1e6] Hz"),
        ])?;
        if !(Range::positive_max(1.0).contains(self.duration_s) && self.duration_s * self.rate_hz < 1.0) {
            return Err(FieldError::new(
                "simulation.interference.duration_s",
                self.duration_s,
                "(0, 1/rate_hz) s (bursts must not overlap)",
            ));
        }
        if !(Range::closed(0.0, 1.0).contains(self.wander_s) && (self.wander_s + self.duration_s) * self.rate_hz < 1.0) {
            return Err(FieldError::new(
                "simulation.interference.wander_s",
                self.wander_s,
                "[0, 1/rate_hz - duration_s) s (bursts must not overlap)",
            ));
        }
        check_modes("simulation.interference.frequencies_hz", &self.frequencies_hz, 32, "1 to 32 modes")
    }
}

/// `[simulation.interference_events]`: the receiver's interference events as
/// the source describes them (ch. 10.4.1, 10.5): a spurious signal at random
/// instants, a fraction of a frame long, with dominant modes below 10 MHz,
/// sometimes beside the return and sometimes an extra dominant peak. Each
/// event has one fixed shape, `g(x) Σ_k sin(2π f_k x)` with the envelope
/// `g(x) = (x/τ) exp(1 − x/τ)` (rises smoothly from its onset, peaks at
/// `x = τ`, then decays; cut at 12 τ), scaled so that its largest positive
/// excursion is `peak_v`. Each frame independently holds one event with
/// probability `probability_per_frame`; its onset is uniform over the frame
/// (tied to the mains, not to the shots), and it may run past the frame's end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InterferenceEventsConfig {
    /// Largest positive excursion of an event, V.
    pub peak_v: f64,
    /// Envelope time constant τ, s: the envelope peaks τ after the onset and
    /// decays as exp(−x/τ); the event is cut 12 τ after its onset.
    pub decay_s: f64,
    /// Mode frequencies, Hz (the source's were below 10 MHz).
    pub frequencies_hz: Vec<f64>,
    /// Probability that a frame holds an event (each frame independently).
    pub probability_per_frame: f64,
}

impl InterferenceEventsConfig {
    /// Checks `[simulation.interference_events]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.interference_events.peak_v", self.peak_v.into(), Range::closed(0.0, 1e3), "[0, 1000] V"),
            ("simulation.interference_events.decay_s", self.decay_s.into(), Range::closed(1e-10, 1e-3), "[1e-10, 1e-3] s"),
            (
                "simulation.interference_events.probability_per_frame",
                self.probability_per_frame.into(),
                Range::closed(0.0, 1.0),
                "[0, 1]",
            ),
        ])?;
        check_modes("simulation.interference_events.frequencies_hz", &self.frequencies_hz, 16, "1 to 16 modes")
    }
}

/// Checks a list of mode frequencies: 1 to `max_modes` of them (`allowed`
/// says so), each in (0, 1e10] Hz.
fn check_modes(field: &str, frequencies_hz: &[f64], max_modes: usize, allowed: &'static str) -> Result<(), FieldError> {
    if frequencies_hz.is_empty() || frequencies_hz.len() > max_modes {
        return Err(FieldError::new(field, format!("{} modes", frequencies_hz.len()), allowed));
    }
    for (k, f) in frequencies_hz.iter().enumerate() {
        check(&[(&format!("{field}[{k}]"), (*f).into(), Range::positive_max(1e10), "(0, 1e10] Hz")])?;
    }
    Ok(())
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

impl NoiseConfig {
    /// Checks `[simulation.noise]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        if let Some(s) = self.thermal_sigma_v {
            check(&[("simulation.noise.thermal_sigma_v", s.into(), Range::closed(0.0, 1e3), "[0, 1000] V")])?;
        }
        if let Some(g) = self.skewness {
            check(&[("simulation.noise.skewness", g.into(), Range::closed(-2.0, 2.0), "[-2, 2]")])?;
        }
        check(&[("simulation.noise.offset_v", self.offset_v.into(), Range::closed(-1e3, 1e3), "[-1000, 1000] V")])
    }
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

impl SimDigitiserConfig {
    /// Checks `[simulation.digitiser]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("simulation.digitiser.sample_interval_s", self.sample_interval_s.into(), Range::positive_max(1e-3), "(0, 1e-3] s"),
            ("simulation.digitiser.samples_per_frame", self.samples_per_frame.into(), Range::closed(2.0, 1e7), "[2, 10000000]"),
            (
                "simulation.digitiser.pre_trigger_samples",
                self.pre_trigger_samples.into(),
                Range::closed_open(0.0, self.samples_per_frame as f64),
                "[0, samples_per_frame)",
            ),
            ("simulation.digitiser.bits", self.bits.into(), Range::closed(2.0, 16.0), "[2, 16]"),
        ])?;
        if !(self.full_scale_low_v.is_finite()
            && self.full_scale_high_v.is_finite()
            && self.full_scale_low_v < self.full_scale_high_v)
        {
            return Err(FieldError::new(
                "simulation.digitiser.full_scale_high_v",
                format!("{} (low {})", self.full_scale_high_v, self.full_scale_low_v),
                "finite volts with full_scale_low_v < full_scale_high_v",
            ));
        }
        if let Some(b) = self.bandwidth_hz {
            check(&[("simulation.digitiser.bandwidth_hz", b.into(), Range::positive_max(1e12), "(0, 1e12] Hz")])?;
        }
        check(&[
            (
                "simulation.digitiser.aperture_jitter_s",
                self.aperture_jitter_s.into(),
                Range::closed(0.0, self.sample_interval_s),
                "[0, sample_interval_s] s",
            ),
            ("simulation.digitiser.trigger_jitter_s", self.trigger_jitter_s.into(), Range::closed(0.0, 1e-6), "[0, 1e-6] s"),
            ("simulation.digitiser.oversample", self.oversample.into(), Range::closed(1.0, 256.0), "[1, 256]"),
        ])?;
        if self.start_channel.trim().is_empty()
            || crate::frame::channel_key(&self.start_channel) == crate::frame::channel_key(&self.stop_channel)
        {
            return Err(FieldError::new(
                "simulation.digitiser.start_channel",
                format!("{:?}", self.start_channel),
                "a non-empty channel name other than stop_channel",
            ));
        }
        if self.stop_channel.trim().is_empty() {
            return Err(FieldError::new("simulation.digitiser.stop_channel", "\"\"", "a non-empty channel name"));
        }
        Ok(())
    }
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

impl SimulationConfig {
    /// Checks every value against its allowed range; errors name the dotted
    /// field (`simulation.targets[1].range_m`) and the allowed range.
    pub fn validate(&self) -> Result<(), SimulationError> {
        self.digitiser.validate()?;
        if let Some(l) = &self.laser {
            l.validate()?;
        }
        for (i, t) in self.targets.iter().enumerate() {
            t.validate(i)?;
        }
        if let Some(a) = &self.atmosphere {
            a.validate()?;
        }
        if let Some(r) = &self.receiver {
            r.validate()?;
        }
        if let Some(b) = &self.background {
            b.validate()?;
        }
        if let Some(a) = &self.apd {
            a.validate()?;
        }
        if let Some(t) = &self.tia {
            t.validate()?;
        }
        if let Some(s) = &self.start {
            s.validate()?;
        }
        if let Some(i) = &self.interference {
            i.validate()?;
        }
        if let Some(e) = &self.interference_events {
            e.validate()?;
        }
        if let Some(n) = &self.noise {
            n.validate()?;
        }

        // Sections an effect depends on.
        let laser_on = self.laser.as_ref().is_some_and(|l| !l.off);
        let optical = (laser_on && !self.targets.is_empty()) || self.background.is_some();
        if optical {
            if self.receiver.is_none() {
                return Err(SimulationError::MissingSection {
                    section: "simulation.receiver",
                    needed_by: "targets or background light",
                });
            }
            if self.apd.is_none() {
                return Err(SimulationError::MissingSection {
                    section: "simulation.apd",
                    needed_by: "targets or background light",
                });
            }
            if self.tia.is_none() {
                return Err(SimulationError::MissingSection {
                    section: "simulation.tia",
                    needed_by: "targets or background light",
                });
            }
        }
        if !self.targets.is_empty() && self.laser.is_none() {
            return Err(SimulationError::MissingSection {
                section: "simulation.laser",
                needed_by: "targets",
            });
        }
        if self.start.is_some() && self.laser.is_none() {
            return Err(SimulationError::MissingSection {
                section: "simulation.laser",
                needed_by: "the start channel",
            });
        }
        if self.apd.is_some() && self.tia.is_none() {
            return Err(SimulationError::MissingSection {
                section: "simulation.tia",
                needed_by: "the APD",
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn events(text: &str) -> Result<InterferenceEventsConfig, String> {
        let c: InterferenceEventsConfig = toml::from_str(text).map_err(|e| e.to_string())?;
        c.validate().map_err(|e| e.to_string())?;
        Ok(c)
    }

    const GOOD: &str = "peak_v = 0.35\ndecay_s = 80e-9\nfrequencies_hz = [1.3e6, 3.1e6]\nprobability_per_frame = 0.3\n";

    #[test]
    fn interference_events_section_is_checked_by_name() {
        let c = events(GOOD).unwrap();
        assert_eq!(c.frequencies_hz.len(), 2);
        let e = events(&format!("{GOOD}peak = 1.0\n")).unwrap_err();
        assert!(e.contains("unknown field") && e.contains("peak"), "{e}");
        for (from, to, field, allowed) in [
            ("peak_v = 0.35", "peak_v = -0.1", "simulation.interference_events.peak_v", "[0, 1000] V"),
            ("decay_s = 80e-9", "decay_s = 0.0", "simulation.interference_events.decay_s", "[1e-10, 1e-3] s"),
            (
                "probability_per_frame = 0.3",
                "probability_per_frame = 1.5",
                "simulation.interference_events.probability_per_frame",
                "[0, 1]",
            ),
            ("[1.3e6, 3.1e6]", "[]", "simulation.interference_events.frequencies_hz", "1 to 16 modes"),
            ("[1.3e6, 3.1e6]", "[1.3e6, -3.1e6]", "simulation.interference_events.frequencies_hz[1]", "(0, 1e10] Hz"),
        ] {
            let e = events(&GOOD.replace(from, to)).unwrap_err();
            assert!(e.contains(field) && e.contains(allowed), "{to}: {e}");
        }
        let e = events("peak_v = 0.35\ndecay_s = 80e-9\nfrequencies_hz = [1e6]\n").unwrap_err();
        assert!(e.contains("probability_per_frame"), "{e}");
    }
}
