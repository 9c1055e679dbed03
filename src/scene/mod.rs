//! Scene: the declarative description of one sensor set-up (TOML).
//!
//! Parsed with `deny_unknown_fields` and validated at load, so a bad scene
//! fails before any frame is processed, with an error naming the field and the
//! allowed range. The pipeline is built from a validated scene (`pipeline::build`).
//!
//! Each section type sits in the file of its group, with its `validate()`
//! next to it, written as rows for [`check::check`] (field, value, allowed
//! range, the range as the error states it):
//! - `digitiser`: `[digitiser]`, `[channels]`;
//! - `pulse`: `[return_pulse]`, `[start_pulse]`, and their dsp shapes;
//! - `gates`: `[range_gate]`, `[noise_gate]`;
//! - `detector`, `timing`, `averaging`, `baseline`: the section of that name;
//! - `denoise`: `[denoise]` and `[events]` (structured interference);
//! - `calibration`: `[calibration]` and the calibration file;
//! - [`simulation`]: `[simulation]`, which drives `physics` (its many
//!   section types keep their module path: `scene::simulation::X`);
//! - here: [`Scene`], `[medium]`, loading and the order of the checks.
//!
//! Every type is re-exported here: its path is `scene::X` whatever file holds it.

mod averaging;
mod baseline;
mod calibration;
pub mod check;
mod denoise;
mod detector;
mod digitiser;
mod gates;
mod pulse;
pub mod simulation;
mod timing;

pub use averaging::{AveragingAlign, AveragingConfig, AveragingMethod, AveragingMode};
pub use baseline::{BaselineConfig, BaselineEstimator};
pub use calibration::{CalibrationConfig, CalibrationFile, CalibrationMeasurement};
pub use check::FieldError;
pub use denoise::{DenoiseConfig, DenoiseMethod, EventsConfig};
pub use detector::{CfarKind, DetectorConfig, DetectorKind, PfaScope, ThresholdMode};
pub use digitiser::{ChannelsConfig, DigitiserConfig};
pub use gates::{NoiseGateConfig, RangeGateConfig};
pub use pulse::{PulseConfig, PulseModel};
pub use timing::{TimingConfig, TimingMethod};

use check::{check, Range};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The embedded default scene (the source's prototype), commented: the
/// processing sections ([`DEFAULT_PROCESSING_TOML`]) followed by the
/// `[simulation]` section that `tofwave simulate` uses without `--scene`
/// (Table 10.20's lab targets and the receiver's interference events).
pub const DEFAULT_SCENE_TOML: &str =
    concat!(include_str!("../default_scene.toml"), include_str!("../default_simulation.toml"));

/// The default scene's processing sections alone (no `[simulation]`): the
/// starting text of scenes of real sensors (`tofwave scene --from-capture`).
pub const DEFAULT_PROCESSING_TOML: &str = include_str!("../default_scene.toml");

/// Speed of light in vacuum, m/s.
pub const C_VACUUM_M_PER_S: f64 = 299_792_458.0;

/// Errors from loading or validating a scene.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("cannot read scene {path}: {cause}")]
    Io {
        /// File path.
        path: String,
        /// Cause.
        cause: std::io::Error,
    },
    /// TOML syntax error, unknown key or wrong type.
    #[error("scene {origin}: {message}")]
    Parse {
        /// File path or "embedded default".
        origin: String,
        /// The TOML parser's message (names the key and line).
        message: String,
    },
    /// A value out of its allowed range.
    #[error("scene {origin}: {error}")]
    Invalid {
        /// File path or "embedded default".
        origin: String,
        /// The field, its value and the allowed range.
        error: FieldError,
    },
    /// The `[simulation]` section is invalid (the message names the dotted field).
    #[error("scene {origin}: {cause}")]
    Simulation {
        /// File path or "embedded default".
        origin: String,
        /// The physics layer's error, naming the field and the allowed range.
        cause: simulation::SimulationError,
    },
}

/// One sensor set-up.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Free text shown in logs.
    #[serde(default = "default_name")]
    pub name: String,
    /// What the digitiser delivers.
    #[serde(default)]
    pub digitiser: DigitiserConfig,
    /// Which channel is which.
    #[serde(default)]
    pub channels: ChannelsConfig,
    /// Shape of a return on the stop channel.
    #[serde(default = "PulseConfig::default_return")]
    pub return_pulse: PulseConfig,
    /// Shape of the start pulse.
    #[serde(default = "PulseConfig::default_start")]
    pub start_pulse: PulseConfig,
    /// Where returns are sought.
    #[serde(default)]
    pub range_gate: RangeGateConfig,
    /// Where the noise model is fitted.
    #[serde(default)]
    pub noise_gate: NoiseGateConfig,
    /// Detector and false-alarm target.
    #[serde(default)]
    pub detector: DetectorConfig,
    /// How instants are measured.
    #[serde(default)]
    pub timing: TimingConfig,
    /// Ensemble averaging.
    #[serde(default)]
    pub averaging: AveragingConfig,
    /// Baseline (offset) removal; absent: no baseline stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baseline: Option<BaselineConfig>,
    /// Structured-interference cancellation; absent: no denoise stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub denoise: Option<DenoiseConfig>,
    /// Returns told from interference events.
    #[serde(default)]
    pub events: EventsConfig,
    /// System delay.
    #[serde(default)]
    pub calibration: CalibrationConfig,
    /// Propagation medium.
    #[serde(default)]
    pub medium: MediumConfig,
    /// What `tofwave simulate` synthesises for this scene (laser, targets,
    /// receiver, noise, digitiser); absent in scenes of real sensors.
    #[serde(default)]
    pub simulation: Option<simulation::SimulationConfig>,
}

fn default_name() -> String {
    "unnamed".into()
}


/// Medium.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MediumConfig {
    /// Group refractive index.
    pub refractive_index: f64,
}

impl Default for MediumConfig {
    fn default() -> Self {
        MediumConfig {
            refractive_index: 1.000268,
        }
    }
}

impl Scene {
    /// The embedded default scene (the source's prototype).
    pub fn default_scene() -> Scene {
        Scene::from_toml_str(DEFAULT_SCENE_TOML, "embedded default")
            .expect("the embedded default scene is valid (tested)")
    }

    /// Reads and validates a scene file.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.display().to_string(),
            cause: source,
        })?;
        Scene::from_toml_str(&text, &path.display().to_string())
    }

    /// Parses and validates TOML text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Scene, SceneError> {
        let scene: Scene = toml::from_str(text).map_err(|e| SceneError::Parse {
            origin: origin.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        scene.validate(origin)?;
        Ok(scene)
    }

    /// The scene as TOML (uncommented; see [`DEFAULT_SCENE_TOML`] for the commented default).
    pub fn to_toml(&self) -> String {
        human_floats(&toml::to_string(self).expect("a scene always serialises"))
    }

    /// Speed of light in the medium, m/s.
    pub fn c_medium_m_per_s(&self) -> f64 {
        C_VACUUM_M_PER_S / self.medium.refractive_index
    }

    /// Checks every value against its allowed range.
    pub fn validate(&self, origin: &str) -> Result<(), SceneError> {
        self.validate_sections().map_err(|error| SceneError::Invalid {
            origin: origin.to_string(),
            error,
        })?;
        if let Some(sim) = &self.simulation {
            sim.validate().map_err(|source| SceneError::Simulation {
                origin: origin.to_string(),
                cause: source,
            })?;
        }
        Ok(())
    }

    /// Each section in turn (the order fixes which error a scene with several gets).
    fn validate_sections(&self) -> Result<(), FieldError> {
        self.digitiser.validate()?;
        self.channels.validate()?;
        self.return_pulse.validate("return_pulse")?;
        self.start_pulse.validate("start_pulse")?;
        self.range_gate.validate()?;
        self.noise_gate.validate()?;
        self.detector.validate()?;
        self.timing.validate()?;
        self.averaging.validate()?;
        if let Some(b) = &self.baseline {
            b.validate()?;
        }
        if let Some(d) = &self.denoise {
            d.validate(self.digitiser.sample_interval_s)?;
        }
        self.events.validate()?;
        self.calibration.validate()?;
        self.medium.validate()?;
        // A scene that states its sampling period is checked against the
        // resource bounds now; otherwise each frame is, at its own period.
        let dt = self.digitiser.sample_interval_s;
        if dt > 0.0 && let Some(e) = self.work_at(dt, self.digitiser.samples_per_frame) {
            return Err(FieldError {
                field: e.field.to_string(),
                value: format!("{} at digitiser.sample_interval_s = {dt} s: {}", e.value, e.describe()),
                allowed: e.allowed,
            });
        }
        Ok(())
    }

    /// The first resource bound ([`crate::frame::limits`]) that frames at
    /// sampling period `dt_s` with `samples` samples per channel would exceed
    /// in a pipeline built from this scene (`samples` 0: not known), or `None`.
    /// Arithmetic only: no shape is built and nothing is allocated, so the
    /// pipeline calls it for every frame before any buffer is sized.
    pub fn work_at(&self, dt_s: f64, samples: usize) -> Option<WorkExcess> {
        use crate::frame::limits::{MAX_AVERAGING_WINDOW_BYTES, MAX_TEMPLATE_TAPS, MAX_WINDOW_SAMPLES};
        let taps = MAX_TEMPLATE_TAPS as f64;
        let window = MAX_WINDOW_SAMPLES as f64;
        let pulse = |p: &PulseConfig, field: &'static str| {
            let n = p.template_taps(dt_s);
            (!(n <= taps)).then(|| WorkExcess {
                field,
                value: format!("support {:.4e} s", p.support_s()),
                what: "template taps",
                needed: n,
                limit: MAX_TEMPLATE_TAPS,
                allowed: "a template of at most 8192 taps at the sampling period (frame::limits::MAX_TEMPLATE_TAPS)",
            })
        };
        pulse(&self.return_pulse, "return_pulse")
            .or_else(|| pulse(&self.start_pulse, "start_pulse"))
            .or_else(|| {
                let n = ((self.return_pulse.support_s() + 2.0 * self.events.flank_s) / dt_s).ceil() + 1.0;
                (self.events.enabled && !(n <= window)).then(|| WorkExcess {
                    field: "events.flank_s",
                    value: format!("{} s", self.events.flank_s),
                    what: "event-test window samples",
                    needed: n,
                    limit: MAX_WINDOW_SAMPLES,
                    allowed: "an event window (pulse support + 2 flanks) of at most 1048576 samples (frame::limits::MAX_WINDOW_SAMPLES)",
                })
            })
            .or_else(|| {
                let d = self.denoise.as_ref()?;
                let n = (d.max_burst_s / dt_s).ceil();
                (!(n <= window)).then(|| WorkExcess {
                    field: "denoise.max_burst_s",
                    value: format!("{} s", d.max_burst_s),
                    what: "burst template samples",
                    needed: n,
                    limit: MAX_WINDOW_SAMPLES,
                    allowed: "a burst template of at most 1048576 samples (frame::limits::MAX_WINDOW_SAMPLES)",
                })
            })
            .or_else(|| {
                let a = &self.averaging;
                let stored = a.frames > 1 && (a.mode == AveragingMode::Sliding || a.method != AveragingMethod::Mean);
                let bytes = a.frames as f64 * samples as f64 * 8.0;
                (stored && bytes > MAX_AVERAGING_WINDOW_BYTES as f64).then(|| WorkExcess {
                    field: "averaging.frames",
                    value: format!("{} frames of {samples} samples", a.frames),
                    what: "bytes held by the averaging window",
                    needed: bytes,
                    limit: MAX_AVERAGING_WINDOW_BYTES,
                    allowed: "a stored averaging window of at most 1 GiB (frame::limits::MAX_AVERAGING_WINDOW_BYTES)",
                })
            })
    }
}

/// A resource bound a scene would exceed at some sampling period ([`Scene::work_at`]).
#[derive(Debug, Clone, PartialEq)]
pub struct WorkExcess {
    /// The scene field (or section) whose duration or count makes the work.
    pub field: &'static str,
    /// Its value, as the message shows it.
    pub value: String,
    /// What is counted (template taps, window samples, bytes).
    pub what: &'static str,
    /// How many the sampling period makes of it.
    pub needed: f64,
    /// The bound.
    pub limit: usize,
    /// The bound as a sentence, for [`FieldError::allowed`].
    pub allowed: &'static str,
}

impl WorkExcess {
    /// `"<needed> <what> (at most <limit>)"`.
    pub fn describe(&self) -> String {
        format!("{:.4e} {} (at most {})", self.needed, self.what, self.limit)
    }
}

impl MediumConfig {
    /// Checks `[medium]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[("medium.refractive_index", self.refractive_index.into(), Range::closed(1.0, 4.0), "[1, 4]")])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_scene_parses_and_round_trips() {
        let s = Scene::default_scene();
        assert_eq!(s.channels.stop, "CH2");
        assert_eq!(s.detector.pfa, 1e-6);
        let again = Scene::from_toml_str(&s.to_toml(), "round trip").unwrap();
        assert_eq!(s, again);
    }

    #[test]
    fn unknown_key_is_refused_by_name() {
        let text = DEFAULT_SCENE_TOML.replace("[detector]", "[detector]\npfaa = 1e-3");
        let e = Scene::from_toml_str(&text, "x.toml").unwrap_err().to_string();
        assert!(e.contains("pfaa"), "{e}");
        assert!(e.contains("x.toml"), "{e}");
    }

    #[test]
    fn out_of_range_names_field_and_range() {
        let text = DEFAULT_SCENE_TOML.replace("pfa = 1e-6", "pfa = 0.7");
        let e = Scene::from_toml_str(&text, "x.toml").unwrap_err().to_string();
        assert!(e.contains("detector.pfa") && e.contains("(0, 0.5]"), "{e}");
    }

    #[test]
    fn minimal_scene_takes_defaults() {
        let s = Scene::from_toml_str("name = \"m\"\n", "m").unwrap();
        assert_eq!(s.detector.kind, DetectorKind::MatchedFilter);
        assert_eq!(s.return_pulse.fwhm_s, 26.04e-9);
    }
}

/// TOML text with its small and large floats written for people: the
/// serialiser's `0.000000001986994021755361` becomes `1.986994021755361e-9`
/// (the same f64, shortest round-trip digits) followed by a comment in SI
/// units for keys that name one (`# 1.987 ns`). Only `key = value` lines with
/// a float (or an array of floats) change; what the text parses to does not.
pub fn human_floats(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + text.len() / 8);
    for line in text.lines() {
        out.push_str(&human_line(line));
        out.push('\n');
    }
    out
}

fn human_line(line: &str) -> String {
    let Some((key, value)) = line.split_once(" = ") else {
        return line.to_string();
    };
    let v = value.trim();
    let float = |t: &str| {
        let t = t.trim();
        (t.contains('.') || t.contains('e') || t.contains('E'))
            .then(|| t.parse::<f64>().ok())
            .flatten()
            .filter(|x| x.is_finite())
    };
    let exp = |x: f64| {
        if x != 0.0 && (x.abs() < 1e-3 || x.abs() >= 1e7) { format!("{x:e}") } else { format!("{x:?}") }
    };
    let unit = key.trim().rsplit('_').next().and_then(|u| match u {
        "s" => Some("s"),
        "m" => Some("m"),
        "v" => Some("V"),
        "a" => Some("A"),
        "hz" => Some("Hz"),
        _ => None,
    });
    if let Some(x) = float(v) {
        let mut s = format!("{key} = {}", exp(x));
        if let Some(u) = unit.filter(|_| x != 0.0 && (x.abs() < 1e-3 || x.abs() >= 1e7)) {
            s.push_str(&format!("  # {}", si(x, u)));
        }
        return s;
    }
    if let Some(inner) = v.strip_prefix('[').and_then(|r| r.strip_suffix(']')) {
        let items: Vec<&str> = inner.split(',').map(str::trim).filter(|t| !t.is_empty()).collect();
        if !items.is_empty() && items.iter().all(|t| float(t).is_some()) {
            let parts: Vec<String> = items.iter().map(|t| exp(float(t).expect("checked"))).collect();
            return format!("{key} = [{}]", parts.join(", "));
        }
    }
    line.to_string()
}

/// `x` with an SI prefix and four significant digits: `1.987e-9, "s"` -> `1.987 ns`.
pub fn si(x: f64, unit: &str) -> String {
    const PREFIXES: [(f64, &str); 9] = [
        (1e9, "G"),
        (1e6, "M"),
        (1e3, "k"),
        (1.0, ""),
        (1e-3, "m"),
        (1e-6, "µ"),
        (1e-9, "n"),
        (1e-12, "p"),
        (1e-15, "f"),
    ];
    if x == 0.0 || !x.is_finite() {
        return format!("{x} {unit}");
    }
    let (scale, prefix) = PREFIXES.iter().copied().find(|(s, _)| x.abs() >= *s * 0.99995).unwrap_or((1e-15, "f"));
    let y = x / scale;
    let decimals = if y.abs() >= 100.0 { 1 } else if y.abs() >= 10.0 { 2 } else { 3 };
    format!("{y:.decimals$} {prefix}{unit}")
}

#[cfg(test)]
mod human_tests {
    use super::*;

    #[test]
    fn human_floats_keep_the_values_and_say_them_in_si_units() {
        let text = "[calibration]\ndelay_s = 0.000000001986994021755361\nfraction = 0.5\nname = \"a = 0.000001\"\nwalk_delay_s = [0.000000001, 0.0000000025]\n";
        let out = human_floats(text);
        assert!(out.contains("delay_s = 1.986994021755361e-9  # 1.987 ns"), "{out}");
        assert!(out.contains("fraction = 0.5\n"), "{out}");
        assert!(out.contains("name = \"a = 0.000001\""), "{out}");
        assert!(out.contains("walk_delay_s = [1e-9, 2.5e-9]"), "{out}");
        let a: toml::Table = text.parse().unwrap();
        let b: toml::Table = out.parse().unwrap();
        assert_eq!(a, b);
        assert_eq!(si(-1.9242250272808604e-8, "s"), "-19.24 ns");
        assert_eq!(si(1.55e-6, "m"), "1.550 µm");
        let scene = Scene::default_scene();
        assert_eq!(Scene::from_toml_str(&scene.to_toml(), "round trip").unwrap().to_toml(), scene.to_toml());
    }
}
