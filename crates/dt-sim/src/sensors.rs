//! The dyno's sensors (SPEC §2 rates; figures in the parameter table, from
//! the datasheet-class values in physics-notes).
//!
//! | sensor | reads | chain |
//! | --- | --- | --- |
//! | accelerometers `a1` (rod end), `a2` (body end), 1 kHz | specific force along the axis, `ẍ − g` | first-order anti-alias at `acc_bw_hz` → gain error, cubic nonlinearity, offset + drift with sensor temperature → white noise → 3.9 mg quantisation → ±8 g clip |
//! | potentiometer, 100 Hz | extension `y` | first-order RC at `pos_bw_hz` → mid-stroke offset (per run), bow nonlinearity → noise → 16-bit quantisation → range clip |
//! | loadcell, 50 Hz | mount force `F − m ẍ_body` | 2nd-order Butterworth at `force_bw_hz` → zero error (per run) → noise → quantisation |
//! | shock thermocouple, 1 Hz | `contact · T_outer + (1 − contact) · T_room` | first-order lag `tc_shock_tau_s` → K-type offset → noise → 0.25 °C quantisation |
//! | ambient thermocouple, 1 Hz | `T_room` | lag `tc_air_tau_s` → offset → noise → quantisation |
//!
//! Rig errors (accelerometer offsets and gains, thermocouple offsets) are
//! drawn once per campaign seed: the same dyno measures every run. Per-run
//! errors (potentiometer offset, loadcell zero) come from the run's stream.
//! The sensor temperature of `a2` is the mean of outer tube and room, that
//! of `a1` the room plus 20 % of the oil's excess.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::params::PlantParams;
use crate::plant::Truth;

/// First-order low pass `τ ẏ = x − y`, discretised exactly for an input
/// that is linear across each step (first-order hold, "ramp invariant"):
///
/// `y_k = y_{k−1} + α (x_k − y_{k−1}) − β (x_k − x_{k−1})`,
/// `φ = e^{−h/τ}`, `α = 1 − φ`, `β = (τ/h) α − φ` (≈ `α / 2`).
///
/// The input of a step is the truth at its end; holding that value across
/// the step (`β = 0`, the form before the twenty-first session) made every
/// lagged channel lead the continuous filter by half a step (0.125 ms at the
/// 0.25 ms sub-step), which no causal sensor does.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Lag {
    alpha: f64,
    beta: f64,
    x: f64,
    y: f64,
}

impl Lag {
    fn new(tau_s: f64, dt_s: f64, y0: f64) -> Self {
        let alpha = -(-dt_s / tau_s).exp_m1();
        let phi = 1.0 - alpha;
        Lag {
            alpha,
            beta: tau_s / dt_s * alpha - phi,
            x: y0,
            y: y0,
        }
    }
    fn cutoff(f_hz: f64, dt_s: f64, y0: f64) -> Self {
        Self::new(1.0 / (std::f64::consts::TAU * f_hz), dt_s, y0)
    }
    fn update(&mut self, x: f64) -> f64 {
        self.y += self.alpha * (x - self.y) - self.beta * (x - self.x);
        self.x = x;
        self.y
    }
}

/// Second-order Butterworth low pass (bilinear transform, transposed
/// direct form II).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Butter2 {
    b0: f64,
    b1: f64,
    b2: f64,
    a1: f64,
    a2: f64,
    z1: f64,
    z2: f64,
}

impl Butter2 {
    fn new(f_hz: f64, dt_s: f64, y0: f64) -> Self {
        let k = (std::f64::consts::PI * f_hz * dt_s).tan();
        let norm = 1.0 / (1.0 + std::f64::consts::SQRT_2 * k + k * k);
        let b0 = k * k * norm;
        let a1 = 2.0 * (k * k - 1.0) * norm;
        let a2 = (1.0 - std::f64::consts::SQRT_2 * k + k * k) * norm;
        // Steady state for a constant input y0.
        let b1 = 2.0 * b0;
        let b2 = b0;
        let z2 = b2 * y0 - a2 * y0;
        let z1 = b1 * y0 - a1 * y0 + z2;
        Butter2 {
            b0,
            b1,
            b2,
            a1,
            a2,
            z1,
            z2,
        }
    }
    fn update(&mut self, x: f64) -> f64 {
        let y = self.b0 * x + self.z1;
        self.z1 = self.b1 * x - self.a1 * y + self.z2;
        self.z2 = self.b2 * x - self.a2 * y;
        y
    }
}

/// Errors of the rig's sensors, fixed for a campaign seed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigErrors {
    /// Accelerometer 0 g offsets at 20 °C, m/s² (a1, a2).
    pub acc_offset_mps2: [f64; 2],
    /// Accelerometer relative gain errors (a1, a2).
    pub acc_gain: [f64; 2],
    /// Thermocouple offsets, °C (shock, ambient).
    pub tc_offset_c: [f64; 2],
}

impl RigErrors {
    /// Draws the rig errors.
    pub fn draw(p: &PlantParams, rng: &mut ChaCha8Rng) -> Self {
        let mut n = || -> f64 { rng.sample(StandardNormal) };
        let tc_lim = 3.0 * p.tc_offset_sd_c;
        RigErrors {
            acc_offset_mps2: [p.acc_offset_sd_mps2 * n(), p.acc_offset_sd_mps2 * n()],
            acc_gain: [p.acc_gain_sd * n(), p.acc_gain_sd * n()],
            tc_offset_c: [
                (p.tc_offset_sd_c * n()).clamp(-tc_lim, tc_lim),
                (p.tc_offset_sd_c * n()).clamp(-tc_lim, tc_lim),
            ],
        }
    }
}

/// The sensor chain of one run.
#[derive(Debug, Clone)]
pub struct Sensors {
    p: PlantParams,
    rig: RigErrors,
    pos_offset_m: f64,
    force_zero_n: f64,
    acc1: Lag,
    acc2: Lag,
    pos: Lag,
    force: Butter2,
    force_out: f64,
    tc_shock: Lag,
    tc_air: Lag,
    last_temps: (f64, f64, f64),
    rng: ChaCha8Rng,
}

fn quantise(x: f64, lsb: f64) -> f64 {
    if lsb > 0.0 {
        (x / lsb).round() * lsb
    } else {
        x
    }
}

impl Sensors {
    /// Sensors whose filters start settled on `first` (the truth at t = 0).
    #[must_use]
    pub fn new(
        p: &PlantParams,
        rig: RigErrors,
        mut rng: ChaCha8Rng,
        first: &Truth,
        dt_s: f64,
    ) -> Self {
        let pos_offset_m = p.pos_offset_sd_m * rng.sample::<f64, _>(StandardNormal);
        let force_zero_n = p.force_zero_sd_n * rng.sample::<f64, _>(StandardNormal);
        let g = p.acc_g_mps2;
        let nodes = first.nodes.unwrap_or(crate::thermal::Nodes {
            oil_c: first.room_c,
            inner_c: first.room_c,
            outer_c: first.room_c,
        });
        let shock_in =
            p.tc_shock_contact * nodes.outer_c + (1.0 - p.tc_shock_contact) * first.room_c;
        Sensors {
            p: p.clone(),
            rig,
            pos_offset_m,
            force_zero_n,
            acc1: Lag::cutoff(p.acc_bw_hz, dt_s, first.rod_acc_mps2 - g),
            acc2: Lag::cutoff(p.acc_bw_hz, dt_s, first.body_acc_mps2 - g),
            pos: Lag::cutoff(p.pos_bw_hz, dt_s, first.extension_m),
            force: Butter2::new(p.force_bw_hz, dt_s, first.frame_force_n),
            force_out: first.frame_force_n,
            tc_shock: Lag::new(p.tc_shock_tau_s, dt_s, shock_in),
            tc_air: Lag::new(p.tc_air_tau_s, dt_s, first.room_c),
            last_temps: (nodes.oil_c, nodes.outer_c, first.room_c),
            rng,
        }
    }

    /// Feeds the truth of one sub-step through the analogue chains.
    pub fn update(&mut self, t: &Truth) {
        let g = self.p.acc_g_mps2;
        self.acc1.update(t.rod_acc_mps2 - g);
        self.acc2.update(t.body_acc_mps2 - g);
        self.pos.update(t.extension_m);
        self.force_out = self.force.update(t.frame_force_n);
        if let Some(n) = t.nodes {
            let c = self.p.tc_shock_contact;
            self.tc_shock.update(c * n.outer_c + (1.0 - c) * t.room_c);
            self.last_temps = (n.oil_c, n.outer_c, t.room_c);
        }
        self.tc_air.update(t.room_c);
    }

    fn noise(&mut self, sd: f64) -> f64 {
        sd * self.rng.sample::<f64, _>(StandardNormal)
    }

    fn accel(&mut self, i: usize, filtered: f64, sensor_c: f64) -> f64 {
        let p = &self.p;
        let fs = p.acc_range_mps2;
        let u = filtered / fs;
        let v = (1.0 + self.rig.acc_gain[i]) * filtered
            + p.acc_nonlin_fs * fs * u * u * u
            + self.rig.acc_offset_mps2[i]
            + p.acc_offset_tc_mps2_per_k * (sensor_c - 20.0);
        let (lsb, sd) = (p.acc_lsb_mps2, p.acc_noise_mps2);
        let v = v + self.noise(sd);
        quantise(v, lsb).clamp(-fs, fs)
    }

    /// `(a1, a2)` readings, m/s².
    pub fn sample_acceleration(&mut self) -> (f64, f64) {
        let (oil_c, outer_c, room_c) = self.last_temps;
        let t1 = room_c + 0.2 * (oil_c - room_c);
        let t2 = 0.5 * (outer_c + room_c);
        let (f1, f2) = (self.acc1.y, self.acc2.y);
        (self.accel(0, f1, t1), self.accel(1, f2, t2))
    }

    /// Potentiometer reading, m (extension about mid-stroke).
    pub fn sample_position(&mut self) -> f64 {
        let p = &self.p;
        let range = p.pos_range_m;
        let y = self.pos.y;
        let bow = p.pos_nonlin_m * (std::f64::consts::PI * (y / range).clamp(-1.0, 1.0)).sin();
        let v = y + self.pos_offset_m + bow;
        let (lsb, sd) = (p.pos_lsb_m, p.pos_noise_m);
        let v = v + self.noise(sd);
        quantise(v, lsb).clamp(-range, range)
    }

    /// Loadcell reading, N.
    pub fn sample_force(&mut self) -> f64 {
        let (lsb, sd) = (self.p.force_lsb_n, self.p.force_noise_n);
        let v = self.force_out + self.force_zero_n + self.noise(sd);
        quantise(v, lsb)
    }

    fn thermocouple(&mut self, filtered: f64, offset: f64) -> f64 {
        let (lsb, sd) = (self.p.tc_lsb_c, self.p.tc_noise_c);
        let v = filtered + offset + self.noise(sd);
        quantise(v, lsb)
    }

    /// Shock thermocouple reading, °C.
    pub fn sample_temp_shock(&mut self) -> f64 {
        self.thermocouple(self.tc_shock.y, self.rig.tc_offset_c[0])
    }

    /// Ambient thermocouple reading, °C.
    pub fn sample_temp_ambient(&mut self) -> f64 {
        self.thermocouple(self.tc_air.y, self.rig.tc_offset_c[1])
    }
}

#[cfg(test)]
mod tests {
    use super::Lag;

    /// The continuous first-order lag's steady response to `sin ωt` is
    /// `sin(ωt − atan ωτ) / √(1 + (ωτ)²)`; the discrete lag, fed the sine at
    /// the end of each 0.25 ms step, must follow it without a lead.
    fn worst_error(f_hz: f64, cutoff_hz: f64) -> f64 {
        let (dt, w) = (2.5e-4, std::f64::consts::TAU * f_hz);
        let tau = 1.0 / (std::f64::consts::TAU * cutoff_hz);
        let (gain, phase) = (1.0 / (1.0 + (w * tau).powi(2)).sqrt(), -(w * tau).atan());
        let mut lag = Lag::cutoff(cutoff_hz, dt, 0.0);
        let mut worst = 0.0_f64;
        for k in 1..=40_000 {
            let t = f64::from(k) * dt;
            let y = lag.update((w * t).sin());
            if t > 0.5 {
                worst = worst.max((y - gain * (w * t + phase).sin()).abs());
            }
        }
        worst
    }

    #[test]
    fn the_lag_follows_the_continuous_filter_without_a_lead() {
        // The accelerometers' 400 Hz filter at 50 Hz and 200 Hz, the
        // potentiometer's 50 Hz RC at 10 Hz. Holding the step's end value
        // across it (a lead of half a step) misses by 0.035, 0.125 and
        // 0.0076 of the amplitude here; the first-order hold is exact for a
        // ramp and leaves the sine's curvature only (5.1e-4, 7.2e-3, 2.0e-5).
        for (f, fc, bound) in [
            (50.0, 400.0, 1e-3),
            (200.0, 400.0, 1e-2),
            (10.0, 50.0, 5e-5),
        ] {
            let e = worst_error(f, fc);
            assert!(e < bound, "{f} Hz through {fc} Hz: worst error {e:.2e}");
        }
    }

    #[test]
    fn a_settled_lag_stays_settled() {
        let mut lag = Lag::new(10.0, 2.5e-4, 21.5);
        for _ in 0..100_000 {
            assert!((lag.update(21.5) - 21.5).abs() < 1e-12);
        }
    }
}
