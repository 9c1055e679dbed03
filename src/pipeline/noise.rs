//! noise: converts the stop channel to volts, places the range and noise gates
//! from the time reference, and fits the noise model on the noise gates.
//!
//! With `noise_gate.forgetting_frames = N > 0` the mean, sigma, skewness and
//! kurtosis come from an exponentially forgetting blend of the frames' gate
//! moments ([`NoiseTracker`], λ = e^(−1/N)) and `samples` is its effective
//! sample size W²/ΣW² (so the finite-gate threshold correction sees how much
//! data the model rests on); the normality test, the robust sigma and the
//! contamination flag stay per frame (they judge this frame's gate). With
//! N = 0 (the default) every frame is fitted on its own gates alone.

use super::{stop_codes, FrameError, Stage, Unit};
use crate::frame::{FrameFlag, Samples};
use crate::detect::events::{EventTestConfig, GateScreen};
use crate::detect::gates::{codes_keep_order, GateCleaner, GatePlacer};
use crate::detect::noise_model::{NoiseFitter, NoiseTracker};
use crate::frame::NoiseSummary;
use crate::scene::Scene;

/// A cleaning that keeps fewer samples than this (or than the scene's
/// `noise_gate.min_samples`) is not used.
const MIN_KEPT: usize = 32;

/// Most kept runs of a cleaned gate the noise model is fitted on.
const MAX_RUNS: usize = 64;

/// A gate whose sigma exceeds the last frame's by this factor is cleaned as
/// if contaminated.
const SIGMA_JUMP: f64 = 3.0;

/// Fits the stop channel's noise model.
#[derive(Debug)]
pub struct Noise {
    scene: Scene,
    fitter: NoiseFitter,
    /// Places the range and noise gates (shared with the stages before this one).
    gates: GatePlacer,
    /// Present when the scene asks for a forgetting noise model.
    tracker: Option<NoiseTracker>,
    /// Scratch for the frame's median when there is no noise gate.
    sorted: Vec<f64>,
    /// Cleans contaminated gates.
    cleaner: GateCleaner,
    /// Return-pulse support and FWHM (samples) for the current sampling
    /// period: how far around an excursion the cleaner drops samples.
    pulse_extent: Option<(f64, (usize, usize), usize)>,
    /// The last frame's fitted sigma: where a gate is contaminated, the
    /// cleaning starts from it (an event filling most of a gate inflates
    /// even the robust sigma).
    last_sigma: Option<f64>,
    /// Screens the gates for interference events (scenes with `[events]`
    /// only), for the current sampling period.
    screen: Option<(f64, GateScreen)>,
    /// An 8-bit stop channel's codes widened to 16 bits (for the fits and the cleaner).
    wide_codes: Vec<i16>,
}

impl Noise {
    /// From the scene's gates and return-pulse shape.
    pub fn new(scene: &Scene) -> Noise {
        let n = scene.noise_gate.forgetting_frames;
        Noise {
            scene: scene.clone(),
            fitter: NoiseFitter::default(),
            gates: GatePlacer::new(scene),
            tracker: (n > 0).then(|| NoiseTracker::with_time_constant(n as f64)),
            sorted: Vec::new(),
            cleaner: GateCleaner::default(),
            pulse_extent: None,
            last_sigma: None,
            screen: None,
            wide_codes: Vec::new(),
        }
    }
}

/// The events screen for sampling period `dt` in `slot` (built when it
/// changes), where `scene` tests for events.
fn screen_for<'a>(slot: &'a mut Option<(f64, GateScreen)>, scene: &Scene, dt: f64) -> Option<&'a mut GateScreen> {
    let ev = &scene.events;
    if !ev.enabled {
        return None;
    }
    if slot.as_ref().is_none_or(|s| s.0 != dt) {
        let cfg = EventTestConfig {
            max_frequency: ev.max_frequency_hz * dt,
            flank: (ev.flank_s / dt).ceil().max(1.0) as usize,
            fit_alpha: ev.fit_alpha,
        };
        let shape = scene.return_pulse.shape(dt);
        *slot = Some((dt, GateScreen::new(cfg, &shape, ev.fit_alpha)));
    }
    slot.as_mut().map(|s| &mut s.1)
}

/// The stop channel as the noise model is fitted on it: its volts, and
/// its integer codes with their scale and offset where it has them (then
/// the fit reads the codes: [`NoiseFitter::fit_codes`]).
#[derive(Clone, Copy)]
struct Gated<'a> {
    /// The channel in volts (what the fit reads without codes).
    volts: &'a [f64],
    /// The codes whose decode `volts` is, with the volts per code and the
    /// offset: what `fit_codes` reads.
    codes: Option<(&'a [i16], f64, f64)>,
}

/// Fits the noise model to the runs `quiet` of the channel, as slices on
/// the stack (a cleaned gate has a few dozen runs at most; any beyond
/// [`MAX_RUNS`] are left out of the fit): on its codes where it has them
/// and `fit_codes` takes them, else on its volts.
fn fit_runs(fitter: &mut NoiseFitter, x: Gated, quiet: &[std::ops::Range<usize>], normality_alpha: f64) -> NoiseSummary {
    let runs = quiet.len().min(MAX_RUNS);
    if let Some((c, g, o)) = x.codes {
        let mut parts: [&[i16]; MAX_RUNS] = [&[]; MAX_RUNS];
        for (p, r) in parts.iter_mut().zip(quiet) {
            *p = &c[r.clone()];
        }
        if let Some(fit) = fitter.fit_codes(&parts[..runs], g, o, normality_alpha) {
            return fit;
        }
    }
    let mut parts: [&[f64]; MAX_RUNS] = [&[]; MAX_RUNS];
    for (p, r) in parts.iter_mut().zip(quiet) {
        *p = &x.volts[r.clone()];
    }
    fitter.fit(&parts[..runs], normality_alpha)
}

impl Stage for Noise {
    fn name(&self) -> &'static str {
        "noise"
    }

    fn process(&mut self, mut w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        let s = &self.scene;
        let mut stop_v = std::mem::take(&mut w.buffers.stop_v);
        w.frame.channels[w.source.stop].volts_into(&mut stop_v);
        w.noise.gates = w.place_gates(&mut self.gates);
        // Non-finite samples (a float capture's NaN/Inf) are held at the last
        // finite value so nothing downstream sees them; the report says how many.
        // (Small integer codes on a finite scale decode to finite volts: none to count.)
        let ch = &w.frame.channels[w.source.stop];
        let codes = matches!(ch.samples, Samples::I8(_) | Samples::I16(_));
        let finite_scale = ch.volts_per_code.abs() <= 1e300 && ch.offset_v.abs() <= 1e300;
        let bad = if codes && finite_scale { 0 } else { stop_v.iter().filter(|v| !v.is_finite()).count() };
        if bad > 0 {
            let mut last = stop_v.iter().copied().find(|v| v.is_finite()).unwrap_or(0.0);
            for v in stop_v.iter_mut() {
                if v.is_finite() {
                    last = *v;
                } else {
                    *v = last;
                }
            }
            w.report.flags.push(FrameFlag::NonFiniteSamples(bad));
        }
        let g = &w.noise.gates;
        // The codes as digitised (not an average or a float capture), once
        // per frame, where their volts keep their order and spacing (else
        // the volts the detector reads are not the codes' decode to
        // rounding): the fits read them, and the cleaner counts the gate's
        // colour on them.
        let ch = &w.frame.channels[w.source.stop];
        let codes = (finite_scale && codes_keep_order(ch.volts_per_code, ch.offset_v))
            .then(|| stop_codes(&ch.samples, &mut self.wide_codes))
            .flatten();
        let gated = Gated { volts: &stop_v, codes: codes.map(|c| (c, ch.volts_per_code, ch.offset_v)) };
        let raw = [g.pre.clone(), g.beyond.clone()];
        let noise = fit_runs(&mut self.fitter, gated, &raw, s.detector.normality_alpha);
        // Scratch for a contaminated gate, grown on the first frame.
        self.cleaner.reserve(stop_v.len(), MAX_RUNS);
        self.sorted.reserve(stop_v.len().saturating_sub(self.sorted.len()));
        let quiet = &mut w.buffers.quiet;
        quiet.clear();
        quiet.reserve(MAX_RUNS);
        quiet.extend(raw.iter().filter(|r| !r.is_empty()).cloned());
        // A gate holding pulses or events: fit on what looks like noise. An
        // event filling most of the gate inflates the robust sigma too, so a
        // jump of sigma over the last frame's also calls for cleaning (a real
        // rise of the noise survives it: the cleaning then keeps the gates).
        let jumped = self.last_sigma.is_some_and(|last| noise.sigma_v > SIGMA_JUMP * last);
        let noise = if noise.contaminated || jumped {
            let dt = w.frame.sample_interval_s;
            if self.pulse_extent.is_none_or(|p| p.0 != dt) {
                let shape = s.return_pulse.shape(dt);
                let (lo, hi) = shape.support();
                let fwhm = shape.fwhm().ceil();
                self.pulse_extent = Some((dt, ((-lo).ceil() as usize + fwhm as usize, hi.ceil() as usize + fwhm as usize), (2.0 * fwhm) as usize));
            }
            let (_, dilate, block) = self.pulse_extent.expect("set above");
            let sorted = &mut self.sorted;
            sorted.clear();
            sorted.extend(quiet.iter().flat_map(|r| stop_v[r.clone()].iter().copied()).filter(|v| v.is_finite()));
            let median = crate::math::select::high_median(sorted).unwrap_or(noise.mean_v);
            // The robust sigma, or the last frame's where lower (an event
            // covering most of the gate inflates the robust one too).
            let start = match self.last_sigma {
                Some(last) if last > 0.0 => last.min(noise.robust_sigma_v),
                _ => noise.robust_sigma_v,
            };
            let rails = w.source.rails();
            let codes = codes.map(|c| (c, ch.volts_per_code));
            let kept = self.cleaner.clean(&stop_v, codes, quiet, median, start, dilate, block, rails);
            // Too little left to rest a noise model on (coloured noise whose
            // quiet blocks read low can clip nearly everything): the raw gates.
            let kept_samples: usize = kept.iter().map(|r| r.len()).sum();
            if kept_samples >= s.noise_gate.min_samples.max(MIN_KEPT) {
                quiet.clear();
                quiet.extend_from_slice(kept);
            }
            let clean = fit_runs(&mut self.fitter, gated, quiet, s.detector.normality_alpha);
            // A cleaning that moves sigma by less than the raw gate's own
            // sampling spread (z at normality_alpha; widened by the gate's
            // colour) found nothing worth dropping (the flag's false alarms,
            // frequent on strongly coloured noise): the raw fit stands.
            let n = noise.samples.max(2) as f64;
            let spread = crate::math::special::q_inv(0.5 * s.detector.normality_alpha.clamp(1e-12, 0.5)) * noise.sigma_v
                * (self.cleaner.colour_gain() / (2.0 * (n - 1.0))).sqrt();
            if (clean.sigma_v - noise.sigma_v).abs() <= spread {
                quiet.clear();
                quiet.extend(raw.iter().filter(|r| !r.is_empty()).cloned());
                fit_runs(&mut self.fitter, gated, &raw, s.detector.normality_alpha)
            } else {
                // The verdict stays the raw gate's; the model is the cleaned one's.
                NoiseSummary { contaminated: true, robust_sigma_v: noise.robust_sigma_v, ..clean }
            }
        } else {
            noise
        };
        // Gate windows holding an interference event's lobes or tail (slow
        // structure the sample clipping and block test leave in) are left
        // out, where the scene tests for events: the model is then the
        // receiver's noise, and so are the colour, the self-check and the
        // events test's null, which all read these runs.
        w.buffers.gate_band.clear();
        let noise = match screen_for(&mut self.screen, s, w.frame.sample_interval_s) {
            Some(screen) if noise.samples >= 2 => match screen.screen(&stop_v, noise.mean_v, noise.sigma_v, quiet, &mut w.buffers.gate_band) {
                Some(kept) if kept.iter().map(|r| r.len()).sum::<usize>() >= s.noise_gate.min_samples.max(MIN_KEPT) => {
                    quiet.clear();
                    quiet.extend_from_slice(kept);
                    let clean = fit_runs(&mut self.fitter, gated, quiet, s.detector.normality_alpha);
                    NoiseSummary { contaminated: true, robust_sigma_v: noise.robust_sigma_v, ..clean }
                }
                _ => noise,
            },
            _ => noise,
        };
        if (noise.samples as usize) < s.noise_gate.min_samples {
            w.report.flags.push(FrameFlag::NoiseGateSmall);
        }
        let mut noise = noise;
        if let Some(tracker) = &mut self.tracker {
            tracker.update(self.fitter.moments());
            if tracker.effective_samples() >= 1.0 {
                noise.mean_v = tracker.mean();
                noise.sigma_v = tracker.variance().sqrt();
                noise.skewness = tracker.skewness();
                noise.excess_kurtosis = tracker.excess_kurtosis();
                noise.samples = tracker.effective_samples().floor() as u64;
            }
        }
        // A gate with no spread (noise-free or clipped data) still needs a
        // finite threshold: floor sigma at the quantisation noise, or at 1e-12
        // of the signal scale for float data.
        let floor = if w.source.lsb_v > 0.0 {
            w.source.lsb_v / 12f64.sqrt()
        } else {
            1e-12 * noise.mean_v.abs().max(1e-3)
        };
        if noise.samples < 2 {
            // No gate: the frame's median stands in for the baseline.
            let sorted = &mut self.sorted;
            sorted.clear();
            sorted.extend_from_slice(&stop_v);
            noise.mean_v = crate::math::select::high_median(sorted).unwrap_or(0.0);
        }
        if noise.samples >= 2 && noise.sigma_v > 0.0 {
            self.last_sigma = Some(noise.sigma_v);
        }
        w.noise.sigma_v = noise.sigma_v;
        w.noise.raw_sigma_v = noise.sigma_v;
        if !(noise.sigma_v > floor) {
            w.noise.sigma_v = floor;
            w.noise.raw_sigma_v = floor;
            w.report.flags.push(if noise.samples < 2 { FrameFlag::NoNoiseEstimate } else { FrameFlag::ZeroNoise });
        }
        if !noise.gaussian && noise.samples >= 8 {
            w.report.flags.push(FrameFlag::NonGaussianNoise);
        }
        if noise.contaminated {
            w.report.flags.push(FrameFlag::NoiseGateContaminated);
        }
        w.noise.summary = noise;
        w.report.noise = noise;
        w.buffers.stop_v = stop_v;
        out.push(w);
        Ok(())
    }
}
