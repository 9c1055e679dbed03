//! Resource bounds: the largest work any input may ask for.
//!
//! Every edge that takes a size from outside (the capture readers, the wire
//! conversion, scene validation) checks it against these constants, and the
//! pipeline checks what a frame's sampling period makes of the scene's
//! durations (pulse templates, event windows, burst templates, averaging
//! windows) before it sizes a buffer. An input outside a bound is refused with
//! an error naming the field, its value and the allowed range; nothing in
//! the process allocates, loops or panics in proportion to an unchecked number.
//! The README's "Resource bounds" section lists the same numbers.

/// Shortest sampling period accepted, seconds (1 THz; the fastest real-time
/// digitisers sample at about 4 ps).
pub const MIN_SAMPLE_INTERVAL_S: f64 = 1e-12;

/// Longest sampling period accepted, seconds.
pub const MAX_SAMPLE_INTERVAL_S: f64 = 1.0;

/// Most samples per channel in one frame (4 Mi; 32 MiB per channel as f64,
/// the pipeline's working precision).
pub const MAX_SAMPLES_PER_FRAME: usize = 1 << 22;

/// Most taps of a pulse template (matched filter, start-pulse fit, timing
/// fits): its support in seconds over the sampling period, plus one. The
/// noise-colour terms cost taps² per noise-model change, so this bounds the
/// per-frame work (8192 taps: about 6.7e7 multiply-adds).
pub const MAX_TEMPLATE_TAPS: usize = 8192;

/// Most samples of a window sized by a duration of the scene at the frame's
/// sampling period: an event-test window (pulse support plus two flanks) or a
/// burst template of the `[denoise]` stage.
pub const MAX_WINDOW_SAMPLES: usize = 1 << 20;

/// Most bytes a stored averaging window may hold (`averaging.frames` frames of
/// f64 samples, kept by a sliding window or a robust method): 1 GiB.
pub const MAX_AVERAGING_WINDOW_BYTES: usize = 1 << 30;

/// Longest pulse FWHM a scene may state, seconds (`return_pulse.fwhm_s`,
/// `start_pulse.fwhm_s`). With [`MAX_TEMPLATE_TAPS`] this still allows
/// sampling periods down to about 0.4 ns for the longest pulse.
pub const MAX_PULSE_FWHM_S: f64 = 1e-6;

/// Longest support of a tabulated pulse shape (`table_step_s` times the
/// number of steps), seconds.
pub const MAX_PULSE_TABLE_SPAN_S: f64 = 1e-5;

/// Most values of a tabulated pulse shape.
pub const MAX_PULSE_TABLE_VALUES: usize = 1 << 18;

/// Longest sensor id, bytes (UTF-8). Sensor ids name threads, files, metric
/// labels and log fields, so they are also printable: no control characters.
/// 64 bytes keep every file named after a sensor (each byte escaped to at
/// most 3 characters, plus a suffix) inside the usual 255-byte name limit.
pub const MAX_SENSOR_ID_BYTES: usize = 64;

/// Why a sensor id is refused, or `None` when it is acceptable: at most
/// [`MAX_SENSOR_ID_BYTES`] bytes and no control characters (NUL, newline,
/// escape, ...). The empty id is acceptable here; callers that need a
/// sensor say so themselves.
pub fn sensor_id_problem(id: &str) -> Option<String> {
    if id.len() > MAX_SENSOR_ID_BYTES {
        return Some(format!(
            "{} bytes; allowed at most {MAX_SENSOR_ID_BYTES} bytes of printable UTF-8",
            id.len()
        ));
    }
    if let Some((i, c)) = id.char_indices().find(|(_, c)| c.is_control()) {
        return Some(format!(
            "control character {:?} at byte {i} in \"{}\"; allowed printable UTF-8 only",
            c,
            id.escape_debug()
        ));
    }
    None
}

/// `id` as it may be echoed in a message or used as a metric label: the id
/// itself when [`sensor_id_problem`] accepts it, else its first 32
/// characters escaped, with the byte count (an invalid id can be as long as
/// the message that carried it).
pub fn shown_sensor_id(id: &str) -> String {
    if sensor_id_problem(id).is_none() {
        return id.to_string();
    }
    let head: String = id.chars().take(32).collect();
    format!("{}... ({} bytes)", head.escape_debug(), id.len())
}

/// Why a sampling period is refused, or `None` when it lies in
/// [[`MIN_SAMPLE_INTERVAL_S`], [`MAX_SAMPLE_INTERVAL_S`]].
pub fn sample_interval_problem(dt_s: f64) -> Option<String> {
    if (MIN_SAMPLE_INTERVAL_S..=MAX_SAMPLE_INTERVAL_S).contains(&dt_s) {
        None
    } else {
        Some(format!(
            "{dt_s:e} s is out of range: allowed [{MIN_SAMPLE_INTERVAL_S:e}, {MAX_SAMPLE_INTERVAL_S}] s"
        ))
    }
}

/// Why a frame length is refused, or `None` when it is at most
/// [`MAX_SAMPLES_PER_FRAME`].
pub fn samples_per_frame_problem(n: usize) -> Option<String> {
    (n > MAX_SAMPLES_PER_FRAME).then(|| {
        format!("{n} samples per channel is out of range: allowed at most {MAX_SAMPLES_PER_FRAME}")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sensor_ids() {
        assert!(sensor_id_problem("lidar-7 front/左").is_none());
        assert!(sensor_id_problem("").is_none());
        assert!(sensor_id_problem("a\0b").unwrap().contains("'\\0'"));
        assert!(sensor_id_problem("a\nb").is_some());
        assert!(sensor_id_problem(&"x".repeat(MAX_SENSOR_ID_BYTES)).is_none());
        assert!(sensor_id_problem(&"x".repeat(MAX_SENSOR_ID_BYTES + 1)).is_some());
        assert_eq!(shown_sensor_id("ok"), "ok");
        let long = format!("a\0{}", "y".repeat(10_000));
        let shown = shown_sensor_id(&long);
        assert!(shown.starts_with("a\\0y") && shown.ends_with("(10002 bytes)") && shown.len() < 64, "{shown}");
    }

    #[test]
    fn intervals() {
        for dt in [1e-12, 1e-9, 1.0] {
            assert!(sample_interval_problem(dt).is_none(), "{dt}");
        }
        for dt in [0.0, -1e-9, 9.9e-13, 1e-19, 1e-30, 1.5, f64::NAN, f64::INFINITY] {
            assert!(sample_interval_problem(dt).is_some(), "{dt}");
        }
    }
}
