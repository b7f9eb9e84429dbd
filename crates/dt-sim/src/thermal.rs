//! Heat path of the damper on the dyno, and the room temperature.
//!
//! Three energy nodes (richer than the twin's two, SPEC §3.2), °C:
//!
//! ```text
//!   valve heat ──► oil ──G_oi──► inner tube ◄── friction heat (rod guide)
//!                   │               │
//!                  G_oo            G_io (end caps)
//!                   ▼               ▼
//!                 outer tube ──G_air + εσA(T⁴ − T_room⁴) + G_frame──► room
//! ```
//!
//! `C_oil dT_oil/dt = P_valves − G_oi (T_oil − T_in) − G_oo (T_oil − T_out)`
//! `C_in dT_in/dt = P_fric + G_oi (T_oil − T_in) − G_io (T_in − T_out)`
//! `C_out dT_out/dt = G_oo (T_oil − T_out) + G_io (T_in − T_out)
//!                   − (G_air + G_frame)(T_out − T_room) − εσA (T_out⁴ − T_room⁴)` (K in the radiation term).
//!
//! Integrated with explicit Euler at 1 ms (the fastest node time constant,
//! `C_in / (G_oi + G_io)`, is about 10 s); each exchange is subtracted from
//! one node and added to the other, so energy is conserved to rounding. The
//! gas temperature is a lag on the oil (see `gas`), not an energy node (its
//! heat capacity, about 2 J/K, is 0.1 % of the total).
//!
//! Room: `T_room(t) = T_mean + A sin(2π t / P + φ) + OU(t)`, an
//! Ornstein–Uhlenbeck walk updated once per second (seeded).

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::params::{PlantParams, KELVIN, STEFAN_BOLTZMANN};

/// Node temperatures, °C.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nodes {
    /// Oil (working and reservoir, well mixed).
    pub oil_c: f64,
    /// Inner (pressure) tube, piston and rod.
    pub inner_c: f64,
    /// Outer (reservoir) tube, end caps, eyes.
    pub outer_c: f64,
}

/// The heat network's constants.
#[derive(Debug, Clone, PartialEq)]
pub struct HeatNetwork {
    /// Heat capacities, J/K: oil, inner, outer.
    pub c_j_per_k: [f64; 3],
    g_oi: f64,
    g_oo: f64,
    g_io: f64,
    g_amb: f64,
    eps_sigma_a: f64,
}

impl HeatNetwork {
    /// The network of `p`.
    #[must_use]
    pub fn new(p: &PlantParams) -> Self {
        HeatNetwork {
            c_j_per_k: [
                p.oil_c_j_per_k(),
                p.inner_tube_c_j_per_k,
                p.outer_tube_c_j_per_k,
            ],
            g_oi: p.g_oil_inner_w_per_k,
            g_oo: p.g_oil_outer_w_per_k,
            g_io: p.g_inner_outer_w_per_k,
            g_amb: p.g_outer_air_w_per_k + p.g_outer_frame_w_per_k,
            eps_sigma_a: p.emissivity * STEFAN_BOLTZMANN * p.outer_area_m2,
        }
    }

    /// Heat flow from the outer tube to the room, W.
    #[must_use]
    pub fn to_room_w(&self, outer_c: f64, room_c: f64) -> f64 {
        let (to, ta) = (outer_c + KELVIN, room_c + KELVIN);
        self.g_amb * (outer_c - room_c) + self.eps_sigma_a * (to.powi(4) - ta.powi(4))
    }

    /// One explicit step of `dt_s` with heat inputs `p_oil_w`, `p_inner_w`
    /// held; returns the heat lost to the room over the step, J.
    pub fn step(&self, n: &mut Nodes, p_oil_w: f64, p_inner_w: f64, room_c: f64, dt_s: f64) -> f64 {
        let q_oi = self.g_oi * (n.oil_c - n.inner_c);
        let q_oo = self.g_oo * (n.oil_c - n.outer_c);
        let q_io = self.g_io * (n.inner_c - n.outer_c);
        let q_room = self.to_room_w(n.outer_c, room_c);
        n.oil_c += dt_s * (p_oil_w - q_oi - q_oo) / self.c_j_per_k[0];
        n.inner_c += dt_s * (p_inner_w + q_oi - q_io) / self.c_j_per_k[1];
        n.outer_c += dt_s * (q_oo + q_io - q_room) / self.c_j_per_k[2];
        q_room * dt_s
    }

    /// Stored heat relative to 0 °C, J.
    #[must_use]
    pub fn stored_j(&self, n: &Nodes) -> f64 {
        self.c_j_per_k[0] * n.oil_c + self.c_j_per_k[1] * n.inner_c + self.c_j_per_k[2] * n.outer_c
    }
}

/// The room temperature: slow sine plus a seeded random walk.
#[derive(Debug, Clone)]
pub struct Room {
    mean_c: f64,
    amp_c: f64,
    omega: f64,
    phase: f64,
    walk_c: f64,
    walk_sd_c: f64,
    walk_tau_s: f64,
    rng: ChaCha8Rng,
}

impl Room {
    /// A room for one run; draws the run's mean and phase from `rng`.
    #[must_use]
    pub fn new(p: &PlantParams, mut rng: ChaCha8Rng) -> Self {
        let z: f64 = rng.sample(StandardNormal);
        let phase = rng.random::<f64>() * std::f64::consts::TAU;
        let z2: f64 = rng.sample(StandardNormal);
        Room {
            mean_c: p.ambient_mean_c + p.ambient_run_sd_c * z,
            amp_c: p.ambient_sine_amp_c,
            omega: std::f64::consts::TAU / p.ambient_sine_period_s,
            phase,
            walk_c: p.ambient_walk_sd_c * z2,
            walk_sd_c: p.ambient_walk_sd_c,
            walk_tau_s: p.ambient_walk_tau_s,
            rng,
        }
    }

    /// Room temperature at `t_s` (walk as last advanced), °C.
    #[must_use]
    pub fn temp_c(&self, t_s: f64) -> f64 {
        self.mean_c + self.amp_c * (self.omega * t_s + self.phase).sin() + self.walk_c
    }

    /// Advances the random walk by `dt_s` (exact OU step).
    pub fn advance(&mut self, dt_s: f64) {
        let a = (-dt_s / self.walk_tau_s).exp();
        let z: f64 = self.rng.sample(StandardNormal);
        self.walk_c = a * self.walk_c + self.walk_sd_c * (1.0 - a * a).sqrt() * z;
    }

    /// A uniform draw in `[-1, 1)` from the room's stream (start offsets).
    pub fn uniform_pm1(&mut self) -> f64 {
        2.0 * self.rng.random::<f64>() - 1.0
    }
}
