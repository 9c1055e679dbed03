//! State directory: per-sensor scenes (TOML) and noise models; scenes saved
//! when they change, noise models periodically while frames arrive
//! (`--persist-interval-s`) and at shutdown; reloaded at start, a file that
//! does not parse skipped with a warning.
//!
//! Layout: `default.toml` (scene for new sensors), `scenes/<sensor>.toml`,
//! `noise/<sensor>.pb` (a `tofwave.v1.NoiseModel` message). Sensor ids are
//! percent-encoded into file names. Files are written to a temporary name and
//! renamed, so a crash never leaves half a scene.

use crate::frame::NoiseSummary;
use crate::scene::Scene;
use crate::wire::{noise_from_proto, noise_to_proto, proto};
use prost::Message;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Errors reading or writing the state directory.
#[derive(Debug, thiserror::Error)]
pub enum StateError {
    /// File system error.
    #[error("{path}: {cause}")]
    Io {
        /// File or directory.
        path: String,
        /// Cause.
        cause: std::io::Error,
    },
    /// A saved file does not parse ([`StateDir::load`] skips it with a
    /// warning: the server starts, and that sensor starts on the default scene).
    #[error("{path}: {message}")]
    Corrupt {
        /// File.
        path: String,
        /// Cause.
        message: String,
    },
}

/// A state directory.
#[derive(Debug, Clone)]
pub struct StateDir {
    root: PathBuf,
}

/// One sensor's saved state.
#[derive(Debug)]
pub struct SavedSensor {
    /// Sensor id.
    pub sensor: String,
    /// Its scene, if one was saved.
    pub scene: Option<Scene>,
    /// Its last noise model, if one was saved.
    pub noise: Option<NoiseSummary>,
}

/// Everything reloaded at start.
#[derive(Debug, Default)]
pub struct Loaded {
    /// Scene for new sensors, if saved.
    pub default_scene: Option<Scene>,
    /// Sensors, sorted by id.
    pub sensors: Vec<SavedSensor>,
    /// Files that could not be read or parsed (e.g. truncated by a crash
    /// of an older version, or edited by hand), with why: skipped, so the
    /// server still starts.
    pub skipped: Vec<String>,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StateError + '_ {
    move |source| StateError::Io {
        path: path.display().to_string(),
        cause: source,
    }
}

/// Sensor id as a file stem: `[A-Za-z0-9_-]` and inner dots kept, the rest `%XX`.
pub fn file_stem(sensor: &str) -> String {
    let mut s = String::new();
    for (i, b) in sensor.bytes().enumerate() {
        if b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || (b == b'.' && i > 0) {
            s.push(b as char);
        } else {
            s.push_str(&format!("%{b:02X}"));
        }
    }
    if s.is_empty() { "%".into() } else { s }
}

/// Inverse of [`file_stem`].
pub fn sensor_from_stem(stem: &str) -> Option<String> {
    if stem == "%" {
        return Some(String::new());
    }
    let b = stem.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = stem.get(i + 1..i + 3)?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

impl StateDir {
    /// A state directory at `root` (created on first save).
    pub fn new(root: PathBuf) -> StateDir {
        StateDir { root }
    }

    /// Writes `bytes` to `path` atomically: a temporary file, synced, then
    /// renamed over `path` and the directory synced, so `path` holds either
    /// the old or the new contents after a crash or a power cut.
    fn write(&self, path: &Path, bytes: &[u8]) -> Result<(), StateError> {
        use std::io::Write;
        let dir = path.parent().unwrap_or(&self.root);
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let tmp = path.with_extension("tmp");
        let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        f.write_all(bytes).map_err(io(&tmp))?;
        f.sync_all().map_err(io(&tmp))?;
        drop(f);
        std::fs::rename(&tmp, path).map_err(io(path))?;
        // The rename is durable once the directory is synced (POSIX); where a
        // directory cannot be opened for syncing, the rename stands unsynced.
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
        Ok(())
    }

    /// Saves a sensor's scene, or the default scene when `sensor` is `None`.
    pub fn save_scene(&self, sensor: Option<&str>, scene: &Scene) -> Result<(), StateError> {
        let path = match sensor {
            Some(s) => self
                .root
                .join("scenes")
                .join(format!("{}.toml", file_stem(s))),
            None => self.root.join("default.toml"),
        };
        self.write(&path, scene.to_toml().as_bytes())
    }

    /// Saves a sensor's noise model.
    pub fn save_noise(&self, sensor: &str, noise: &NoiseSummary) -> Result<(), StateError> {
        let path = self
            .root
            .join("noise")
            .join(format!("{}.pb", file_stem(sensor)));
        self.write(&path, &noise_to_proto(noise).encode_to_vec())
    }

    /// Reads everything saved (an absent directory is an empty state). A
    /// file that does not read or parse is skipped and named in
    /// [`Loaded::skipped`]; only a directory that cannot be listed is an error.
    pub fn load(&self) -> Result<Loaded, StateError> {
        let mut loaded = Loaded::default();
        let default = self.root.join("default.toml");
        if default.exists() {
            match read_scene(&default) {
                Ok(s) => loaded.default_scene = Some(s),
                Err(e) => loaded.skipped.push(e.to_string()),
            }
        }
        let mut sensors: BTreeMap<String, SavedSensor> = BTreeMap::new();
        for (sub, ext) in [("scenes", "toml"), ("noise", "pb")] {
            let dir = self.root.join(sub);
            if !dir.is_dir() {
                continue;
            }
            for entry in std::fs::read_dir(&dir).map_err(io(&dir))? {
                let path = entry.map_err(io(&dir))?.path();
                if path.extension().and_then(|e| e.to_str()) != Some(ext) {
                    continue;
                }
                let Some(sensor) = path
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .and_then(sensor_from_stem)
                else {
                    continue;
                };
                let e = sensors
                    .entry(sensor.clone())
                    .or_insert_with(|| SavedSensor {
                        sensor,
                        scene: None,
                        noise: None,
                    });
                if ext == "toml" {
                    match read_scene(&path) {
                        Ok(s) => e.scene = Some(s),
                        Err(err) => loaded.skipped.push(err.to_string()),
                    }
                } else {
                    let msg = std::fs::read(&path).map_err(|err| err.to_string()).and_then(|bytes| {
                        proto::NoiseModel::decode(bytes.as_slice()).map_err(|err| err.to_string())
                    });
                    match msg {
                        Ok(msg) => e.noise = Some(noise_from_proto(&msg)),
                        Err(err) => loaded.skipped.push(format!("{}: {err}", path.display())),
                    }
                }
            }
        }
        loaded.sensors = sensors.into_values().collect();
        Ok(loaded)
    }
}

fn read_scene(path: &Path) -> Result<Scene, StateError> {
    Scene::load(path).map_err(|e| StateError::Corrupt {
        path: path.display().to_string(),
        message: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stems_round_trip() {
        for s in ["lidar-1", "a/b", "../x", ".hidden", "ü", "", "a.b"] {
            let stem = file_stem(s);
            assert!(!stem.contains('/') && !stem.starts_with('.'), "{stem}");
            assert_eq!(sensor_from_stem(&stem).as_deref(), Some(s));
        }
    }

    #[test]
    fn saves_and_reloads() {
        let dir = tempfile::tempdir().unwrap();
        let st = StateDir::new(dir.path().to_path_buf());
        let mut scene = Scene::default_scene();
        scene.name = "saved".into();
        st.save_scene(Some("s/1"), &scene).unwrap();
        st.save_scene(None, &scene).unwrap();
        let noise = NoiseSummary {
            sigma_v: 0.25,
            samples: 99,
            ..Default::default()
        };
        st.save_noise("s/1", &noise).unwrap();
        let l = st.load().unwrap();
        assert_eq!(l.default_scene.as_ref(), Some(&scene));
        assert_eq!(l.sensors.len(), 1);
        assert_eq!(l.sensors[0].sensor, "s/1");
        assert_eq!(l.sensors[0].scene.as_ref(), Some(&scene));
        assert_eq!(l.sensors[0].noise, Some(noise));
    }

    /// Truncated files (a crash mid-write of an older version, a full disk,
    /// a hand edit) are skipped and named; the rest loads.
    #[test]
    fn truncated_files_are_skipped_not_fatal() {
        let dir = tempfile::tempdir().unwrap();
        let st = StateDir::new(dir.path().to_path_buf());
        let scene = Scene::default_scene();
        let noise = NoiseSummary { sigma_v: 0.25, samples: 99, ..Default::default() };
        st.save_scene(Some("good"), &scene).unwrap();
        st.save_noise("good", &noise).unwrap();
        st.save_scene(Some("bad"), &scene).unwrap();
        st.save_noise("bad", &noise).unwrap();
        for (sub, file) in [("scenes", "bad.toml"), ("noise", "bad.pb")] {
            let path = dir.path().join(sub).join(file);
            let bytes = std::fs::read(&path).unwrap();
            std::fs::write(&path, &bytes[..bytes.len() / 3]).unwrap();
        }
        // A temporary file left by a crash between write and rename is ignored.
        std::fs::write(dir.path().join("noise").join("good.tmp"), b"partial").unwrap();
        let l = st.load().unwrap();
        assert_eq!(l.skipped.len(), 2, "{:?}", l.skipped);
        assert!(l.skipped.iter().any(|w| w.contains("bad.toml")) && l.skipped.iter().any(|w| w.contains("bad.pb")), "{:?}", l.skipped);
        let good = l.sensors.iter().find(|s| s.sensor == "good").unwrap();
        assert_eq!((good.scene.as_ref(), good.noise.as_ref()), (Some(&scene), Some(&noise)));
        let bad = l.sensors.iter().find(|s| s.sensor == "bad").unwrap();
        assert_eq!((bad.scene.as_ref(), bad.noise.as_ref()), (None, None));
    }
}
