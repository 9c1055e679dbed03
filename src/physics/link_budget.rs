//! Link budget: received power, receiver current, voltage and noise.
//!
//! The consistent form of the source's Eq. 9.20 (SEED-NOTES): for an extended
//! Lambertian target `P_r = ρ cos θ · T² · η · P · A_rec / (π R²)`, `T = e^{−αR}`;
//! a target smaller than the beam spot is scaled by `A_target / A_spot`; the
//! biaxial overlap `O(R)` multiplies both. The APD current is `i = P_r R_o M`,
//! the TIA output `V = i R_TIA`, and the noise current (standard form of the
//! garbled Eq. 9.14) `i_n = sqrt(2q (I_d + R_o P_total) M² F B + i_tia²)` with
//! McIntyre's excess noise `F = M (1 − (1−k)((M−1)/M)²)`.

use crate::scene::simulation::{SimulationConfig, TargetConfig, TargetKind};
use serde::Serialize;
use std::f64::consts::PI;

/// Elementary charge, C.
pub const Q_E: f64 = 1.602_176_634e-19;

/// McIntyre excess noise factor `F = M (1 − (1−k)((M−1)/M)²)`.
pub fn excess_noise_factor(gain: f64, k: f64) -> f64 {
    let r = (gain - 1.0) / gain;
    gain * (1.0 - (1.0 - k) * r * r)
}

/// One-way transmission `T = exp(−α R)` for α in 1/km.
pub fn transmission(extinction_per_km: f64, range_m: f64) -> f64 {
    (-extinction_per_km * 1e-3 * range_m).exp()
}

/// Area of the intersection of two circles with radii `r1`, `r2` whose
/// centres are `d` apart.
fn circle_intersection_area(r1: f64, r2: f64, d: f64) -> f64 {
    if d >= r1 + r2 {
        return 0.0;
    }
    if d <= (r1 - r2).abs() {
        let r = r1.min(r2);
        return PI * r * r;
    }
    let a1 = ((d * d + r1 * r1 - r2 * r2) / (2.0 * d * r1))
        .clamp(-1.0, 1.0)
        .acos();
    let a2 = ((d * d + r2 * r2 - r1 * r1) / (2.0 * d * r2))
        .clamp(-1.0, 1.0)
        .acos();
    let k = ((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2)).max(0.0);
    r1 * r1 * a1 + r2 * r2 * a2 - 0.5 * k.sqrt()
}

/// Geometric overlap of a biaxial transceiver with parallel axes: the
/// fraction of the beam spot (radius `w0 + R tan θ_t`) inside the receiver's
/// field of view at range R (footprint radius `R tan θ_fov`, the source's
/// chief-ray form), axes `d` apart. With the source's 2.2546° FOV and 7 cm
/// separation the overlap is full from 0.07 / tan 2.2546° = 1.78 m for a
/// point beam (Table 9.2); with the default 1 mm beam it is zero (blind zone)
/// below 1.74 m and full from 1.82 m.
pub fn overlap(
    range_m: f64,
    beam_radius_m: f64,
    divergence_half_angle_rad: f64,
    fov_half_angle_rad: f64,
    separation_m: f64,
) -> f64 {
    if separation_m == 0.0 {
        return 1.0;
    }
    let r_beam = beam_radius_m + range_m * divergence_half_angle_rad.tan();
    let r_fov = range_m * fov_half_angle_rad.tan();
    circle_intersection_area(r_beam, r_fov, separation_m) / (PI * r_beam * r_beam)
}

/// The per-target numbers of the link budget.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LinkBudgetLine {
    /// Target range, m.
    pub range_m: f64,
    /// Two-way atmospheric transmission T².
    pub transmission2: f64,
    /// Geometric overlap in [0, 1].
    pub overlap: f64,
    /// Peak received optical power, W.
    pub received_power_w: f64,
    /// Peak APD output current `P_r R_o M`, A.
    pub signal_current_a: f64,
    /// Peak TIA output `i R_TIA` for an infinitely slow pulse, V (no bandwidth loss).
    pub peak_voltage_v: f64,
    /// Noise current at the peak (signal + background + dark shot noise, TIA), A rms.
    pub noise_current_a: f64,
    /// Noise voltage `i_n R_TIA`, V rms.
    pub noise_rms_v: f64,
    /// `20 log10(i / i_n)`, dB (the source's "SNR current").
    pub snr_db: f64,
}

/// The receiver quantities the budget needs, resolved from a config.
#[derive(Debug, Clone, Copy)]
pub struct Receiver {
    /// Peak transmitted power, W.
    pub peak_power_w: f64,
    /// Receiver aperture area, m².
    pub aperture_area_m2: f64,
    /// Optics efficiency.
    pub optics_efficiency: f64,
    /// Extinction, 1/km.
    pub extinction_per_km: f64,
    /// APD responsivity, A/W.
    pub responsivity_a_per_w: f64,
    /// APD gain.
    pub gain: f64,
    /// Excess noise factor F.
    pub excess_noise: f64,
    /// Primary dark current, A.
    pub dark_current_a: f64,
    /// TIA transimpedance, Ω.
    pub tia_gain_ohm: f64,
    /// Noise bandwidth B used in the budget, Hz (the TIA bandwidth: the source
    /// takes the smaller of APD and TIA bandwidths as the system's).
    pub bandwidth_hz: f64,
    /// TIA input-referred noise current, A rms over `bandwidth_hz`.
    pub tia_noise_current_a: f64,
    /// Background optical power on the detector, W.
    pub background_power_w: f64,
}

impl Receiver {
    /// Resolves the budget inputs; `None` when the optical sections are absent.
    pub fn from_config(cfg: &SimulationConfig) -> Option<Receiver> {
        let laser = cfg.laser.as_ref()?;
        let rx = cfg.receiver.as_ref()?;
        let apd = cfg.apd.as_ref()?;
        let tia = cfg.tia.as_ref()?;
        let area = PI * 0.25 * rx.aperture_diameter_m * rx.aperture_diameter_m;
        Some(Receiver {
            peak_power_w: laser.peak_power_w,
            aperture_area_m2: area,
            optics_efficiency: rx.optics_efficiency,
            extinction_per_km: cfg.atmosphere.as_ref().map_or(0.0, |a| a.extinction_per_km),
            responsivity_a_per_w: apd.responsivity_a_per_w,
            gain: apd.gain,
            excess_noise: excess_noise_factor(apd.gain, apd.ionisation_ratio_k),
            dark_current_a: apd.dark_current_a,
            tia_gain_ohm: tia.gain_ohm,
            bandwidth_hz: tia.bandwidth_hz,
            tia_noise_current_a: tia.noise_current_a,
            background_power_w: background_power_w(cfg),
        })
    }

    /// Noise current (A rms over the budget bandwidth) for a primary optical power `p_w`.
    pub fn noise_current_a(&self, p_w: f64) -> f64 {
        let shot = 2.0
            * Q_E
            * (self.dark_current_a + self.responsivity_a_per_w * (p_w + self.background_power_w))
            * self.gain
            * self.gain
            * self.excess_noise
            * self.bandwidth_hz;
        (shot + self.tia_noise_current_a * self.tia_noise_current_a).sqrt()
    }
}

/// Background optical power on the detector, W:
/// `P_bg = η ρ_bg L_λ A_rec Ω_FOV Δλ` with Ω the FOV solid angle
/// `2π(1 − cos θ)` (the source's form with the optics efficiency in place of
/// a path transmission: the scenery is near, its light passes the same optics).
pub fn background_power_w(cfg: &SimulationConfig) -> f64 {
    let (Some(bg), Some(rx)) = (cfg.background.as_ref(), cfg.receiver.as_ref()) else {
        return 0.0;
    };
    let area = PI * 0.25 * rx.aperture_diameter_m * rx.aperture_diameter_m;
    let omega = 2.0 * PI * (1.0 - rx.fov_half_angle_rad.cos());
    let dl_nm = rx.filter_bandwidth_m * 1e9;
    rx.optics_efficiency
        * bg.reflectivity
        * bg.spectral_radiance_w_per_m2_sr_nm
        * area
        * omega
        * dl_nm
}

/// Peak received optical power from one target, W (with overlap and extinction).
pub fn received_power_w(cfg: &SimulationConfig, target: &TargetConfig) -> f64 {
    let (Some(laser), Some(rx)) = (cfg.laser.as_ref(), cfg.receiver.as_ref()) else {
        return 0.0;
    };
    let r = target.range_m;
    let alpha = cfg.atmosphere.as_ref().map_or(0.0, |a| a.extinction_per_km);
    let t = transmission(alpha, r);
    let area = PI * 0.25 * rx.aperture_diameter_m * rx.aperture_diameter_m;
    let mut p = target.reflectivity
        * target.incidence_deg.to_radians().cos()
        * t
        * t
        * rx.optics_efficiency
        * laser.peak_power_w
        * area
        / (PI * r * r);
    let spot_radius = laser.beam_radius_m + r * laser.beam_divergence_half_angle_rad.tan();
    if target.kind == TargetKind::Small {
        let spot = PI * spot_radius * spot_radius;
        p *= (target.area_m2.unwrap_or(spot) / spot).min(1.0);
    }
    p * overlap(
        r,
        laser.beam_radius_m,
        laser.beam_divergence_half_angle_rad,
        rx.fov_half_angle_rad,
        rx.tx_rx_separation_m,
    )
}

/// The budget line for one target.
pub fn line(cfg: &SimulationConfig, rcv: &Receiver, target: &TargetConfig) -> LinkBudgetLine {
    let alpha = cfg.atmosphere.as_ref().map_or(0.0, |a| a.extinction_per_km);
    let p_r = received_power_w(cfg, target);
    let i = p_r * rcv.responsivity_a_per_w * rcv.gain;
    let i_n = rcv.noise_current_a(p_r);
    let (laser, rx) = (cfg.laser.as_ref(), cfg.receiver.as_ref());
    LinkBudgetLine {
        range_m: target.range_m,
        transmission2: transmission(alpha, target.range_m).powi(2),
        overlap: match (laser, rx) {
            (Some(l), Some(r)) => overlap(
                target.range_m,
                l.beam_radius_m,
                l.beam_divergence_half_angle_rad,
                r.fov_half_angle_rad,
                r.tx_rx_separation_m,
            ),
            _ => 1.0,
        },
        received_power_w: p_r,
        signal_current_a: i,
        peak_voltage_v: i * rcv.tia_gain_ohm,
        noise_current_a: i_n,
        noise_rms_v: i_n * rcv.tia_gain_ohm,
        snr_db: if i_n > 0.0 && i > 0.0 {
            20.0 * (i / i_n).log10()
        } else {
            f64::NEG_INFINITY
        },
    }
}
