//! The truth plant: the damper (hydraulics, gas, heat) on the dyno (actuator
//! and compliant mount), stepped at a fixed sub-step. Sensors are separate
//! (`sensors`); this module only knows the physical truth.
//!
//! One call of [`Plant::step`] returns the truth at the current time `t`
//! (the state before the step, and the powers acting over `[t, t + dt]`) and
//! advances the state to `t + dt`:
//!
//! 1. rod-end kinematics from the actuator; `y = x_rod − x_body`,
//!    `ẏ = v_rod − v_body`;
//! 2. gas pressure (`gas`), valve pressures, force, heat (`hydraulics`);
//! 3. mount step under the force (`dyno`); void volume update (clamped at 0);
//! 4. every 1 ms: heat network step with the heat of that millisecond
//!    (`thermal`), gas-temperature lag, viscosity update; every 1 s: room
//!    random walk.

use rand_chacha::ChaCha8Rng;

use crate::dyno::{Actuator, Mount};
use crate::gas::GasSpring;
use crate::hydraulics::TwinTube;
use crate::params::{PlantParams, P_ATM_PA};
use crate::thermal::{HeatNetwork, Nodes, Room};
use crate::SimError;

/// The operating condition of one run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlantConfig {
    /// Charge pressure, bar gauge at 20 °C (the label).
    pub charge_bar: f64,
    /// Excitation frequency, Hz.
    pub frequency_hz: f64,
    /// Stroke, peak to peak, m.
    pub stroke_pp_m: f64,
    /// Start of the excitation, s.
    pub excitation_start_s: f64,
    /// A road drive file instead of the sine: `frequency_hz` and
    /// `stroke_pp_m` are then not used, and the gas's heat exchange takes
    /// the drive's mean frequency ([`crate::road::mean_frequency_hz`]).
    pub road: Option<crate::road::RoadDrive>,
}

/// The physical truth at one instant (and the powers over the step from it).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Truth {
    /// Time since the start of the run, s.
    pub t_s: f64,
    /// Rod-end position, velocity, acceleration along the axis (m, m/s, m/s²).
    pub rod_pos_m: f64,
    /// See `rod_pos_m`.
    pub rod_vel_mps: f64,
    /// See `rod_pos_m`.
    pub rod_acc_mps2: f64,
    /// Body-end position, velocity, acceleration along the axis.
    pub body_pos_m: f64,
    /// See `body_pos_m`.
    pub body_vel_mps: f64,
    /// Body-end acceleration over this step, m/s².
    pub body_acc_mps2: f64,
    /// Extension `y`, m.
    pub extension_m: f64,
    /// Extension rate `ẏ`, m/s.
    pub velocity_mps: f64,
    /// Damper force, N, positive in tension (SPEC §1).
    pub force_n: f64,
    /// Friction part of the force, N.
    pub friction_n: f64,
    /// Force carried by the mount to the frame (loadcell), N.
    pub frame_force_n: f64,
    /// Instantaneous gas pressure, Pa abs.
    pub gas_pa: f64,
    /// Static gas pressure (mid-stroke, current gas and oil temperature), bar gauge.
    pub static_gas_bar: f64,
    /// Gas volume, m³.
    pub gas_volume_m3: f64,
    /// Gas temperature, °C.
    pub gas_c: f64,
    /// Cavitation void volume at `t`, m³.
    pub void_m3: f64,
    /// Change of the void over this step, m³.
    pub dvoid_m3: f64,
    /// The compression chamber is at the cavitation pressure.
    pub cavitating: bool,
    /// Rebound / compression chamber pressures, Pa abs.
    pub p_reb_pa: f64,
    /// See `p_reb_pa`.
    pub p_comp_pa: f64,
    /// Valve heat, W.
    pub valve_power_w: f64,
    /// Friction heat, W.
    pub friction_power_w: f64,
    /// Node temperatures at `t`.
    pub nodes: Option<Nodes>,
    /// Room temperature, °C.
    pub room_c: f64,
    /// Heat lost to the room from the start up to `t`, J.
    pub heat_to_room_j: f64,
    /// Sub-step, s.
    pub dt_s: f64,
}

/// The plant of one run.
#[derive(Debug, Clone)]
pub struct Plant {
    params: PlantParams,
    actuator: Actuator,
    mount: Mount,
    gas: GasSpring,
    hyd: TwinTube,
    net: HeatNetwork,
    room: Room,
    nodes: Nodes,
    gas_c: f64,
    void_m3: f64,
    nu_ratio: f64,
    room_c: f64,
    step_index: u64,
    substeps_per_ms: u64,
    dt_s: f64,
    heat_oil_j: f64,
    heat_inner_j: f64,
    heat_to_room_j: f64,
}

impl Plant {
    /// A plant at rest at mid-stroke, all nodes within
    /// `start_offset_max_c` of the room temperature; `room_rng` drives the
    /// room temperature and the start offset.
    pub fn new(
        params: &PlantParams,
        config: &PlantConfig,
        room_rng: ChaCha8Rng,
    ) -> Result<Self, SimError> {
        params.validate()?;
        for (name, value, ok) in [
            ("charge_bar", config.charge_bar, config.charge_bar > -1.0),
            (
                "frequency_hz",
                config.frequency_hz,
                config.frequency_hz >= 0.0,
            ),
            ("stroke_pp_m", config.stroke_pp_m, config.stroke_pp_m >= 0.0),
        ] {
            if !(value.is_finite() && ok) {
                return Err(SimError::InvalidSpec {
                    field: name,
                    value,
                    reason: "out of range",
                });
            }
        }
        let substeps_per_ms = (1e-3 / params.substep_s).round().max(1.0) as u64;
        let dt_s = 1e-3 / substeps_per_ms as f64;
        let mut room = Room::new(params, room_rng);
        let room_c = room.temp_c(0.0);
        let start_c = room_c + params.start_offset_max_c * room.uniform_pm1();
        let nodes = Nodes {
            oil_c: start_c,
            inner_c: start_c,
            outer_c: start_c,
        };
        let road: Option<std::sync::Arc<[crate::road::Component]>> =
            config.road.map(|r| r.components().into());
        // The gas's heat exchange sees the displacement's mean frequency.
        let gas_hz = road
            .as_deref()
            .map_or(config.frequency_hz, crate::road::mean_frequency_hz);
        let gas = GasSpring::new(params, config.charge_bar, gas_hz);
        let mut hyd = TwinTube::new(params);
        let nu_ratio = hyd.oil.ratio_to_40(start_c);
        let p_g = gas.pressure_pa(start_c, start_c, 0.0, 0.0)?;
        let f0 = hyd.evaluate(0.0, p_g, 0.0, nu_ratio)?.force_n;
        let mount = Mount::new(
            params.mount_mass_kg,
            params.mount_stiffness_n_per_m,
            params.mount_damping_ns_per_m,
            f0,
        );
        let actuator = Actuator {
            amp_m: 0.5 * config.stroke_pp_m,
            omega: std::f64::consts::TAU * config.frequency_hz,
            h3: params.actuator_h3,
            ramp_s: params.actuator_ramp_s,
            start_s: config.excitation_start_s,
            road,
        };
        if let Some(r) = actuator.road.as_deref() {
            // A Gaussian stroke passes 5 sd about once in 3.5 million samples.
            let rms = crate::road::rms_m(r);
            if 5.0 * rms >= params.pos_range_m {
                return Err(SimError::InvalidSpec {
                    field: "road",
                    value: rms,
                    reason: "stroke rms too large for the damper's travel (5 sd past 75 mm)",
                });
            }
        } else if actuator.amp_m * (1.0 + actuator.h3) >= params.pos_range_m {
            return Err(SimError::InvalidSpec {
                field: "stroke_pp_m",
                value: config.stroke_pp_m,
                reason: "exceeds the damper's travel (150 mm)",
            });
        }
        Ok(Plant {
            params: params.clone(),
            actuator,
            mount,
            gas,
            hyd,
            net: HeatNetwork::new(params),
            room,
            nodes,
            gas_c: start_c,
            void_m3: 0.0,
            nu_ratio,
            room_c,
            step_index: 0,
            substeps_per_ms,
            dt_s,
            heat_oil_j: 0.0,
            heat_inner_j: 0.0,
            heat_to_room_j: 0.0,
        })
    }

    /// [`Plant::new`] with the room stream seeded from `seed`.
    pub fn with_seed(
        params: &PlantParams,
        config: &PlantConfig,
        seed: u64,
    ) -> Result<Self, SimError> {
        use rand::SeedableRng as _;
        Self::new(params, config, ChaCha8Rng::seed_from_u64(seed))
    }

    /// Sub-step, s.
    #[must_use]
    pub fn dt_s(&self) -> f64 {
        self.dt_s
    }

    /// Sub-steps per millisecond.
    #[must_use]
    pub fn substeps_per_ms(&self) -> u64 {
        self.substeps_per_ms
    }

    /// Current time, s.
    #[must_use]
    pub fn t_s(&self) -> f64 {
        self.step_index as f64 * self.dt_s
    }

    /// The plant's parameters.
    #[must_use]
    pub fn params(&self) -> &PlantParams {
        &self.params
    }

    /// The gas spring (polytropic index, volumes).
    #[must_use]
    pub fn gas(&self) -> &GasSpring {
        &self.gas
    }

    /// The heat network (capacities).
    #[must_use]
    pub fn network(&self) -> &HeatNetwork {
        &self.net
    }

    /// Current node temperatures.
    #[must_use]
    pub fn nodes(&self) -> Nodes {
        self.nodes
    }

    /// Current cavitation void, m³.
    #[must_use]
    pub fn void_m3(&self) -> f64 {
        self.void_m3
    }

    /// Heat lost to the room so far, J.
    #[must_use]
    pub fn heat_to_room_j(&self) -> f64 {
        self.heat_to_room_j
    }

    /// Sets every node (and the gas) to the given temperatures, e.g. to
    /// start a study near its thermal steady state; the gas takes the oil
    /// temperature.
    pub fn set_temperatures(&mut self, nodes: Nodes) {
        self.nodes = nodes;
        self.gas_c = nodes.oil_c;
        self.nu_ratio = self.hyd.oil.ratio_to_40(nodes.oil_c);
    }

    /// Returns the truth at the current time and advances one sub-step.
    pub fn step(&mut self) -> Result<Truth, SimError> {
        let t = self.t_s();
        let dt = self.dt_s;
        let (x_r, v_r, a_r) = self.actuator.kinematics(t);
        let y = x_r - self.mount.x_m;
        let v_body = self.mount.velocity_now(dt);
        let ydot = v_r - v_body;
        let oil_c = self.nodes.oil_c;
        let p_g = self.gas.pressure_pa(self.gas_c, oil_c, y, self.void_m3)?;
        let hyd = self.hyd.evaluate(ydot, p_g, self.void_m3, self.nu_ratio)?;
        if !hyd.force_n.is_finite() {
            return Err(SimError::Numerical {
                what: "damper force",
                value: hyd.force_n,
            });
        }
        let frame_force_n = self.mount.frame_force_n(dt);
        let body = (self.mount.x_m, v_body);
        self.mount.step(hyd.force_n, dt);
        let void_before = self.void_m3;
        self.void_m3 = (self.void_m3 + hyd.dvoid_m3_per_s * dt).max(0.0);
        let truth = Truth {
            t_s: t,
            rod_pos_m: x_r,
            rod_vel_mps: v_r,
            rod_acc_mps2: a_r,
            body_pos_m: body.0,
            body_vel_mps: body.1,
            body_acc_mps2: self.mount.a_mps2,
            extension_m: y,
            velocity_mps: ydot,
            force_n: hyd.force_n,
            friction_n: hyd.friction_n,
            frame_force_n,
            gas_pa: p_g,
            static_gas_bar: (self.gas.static_pa(self.gas_c, oil_c) - P_ATM_PA) / 1e5,
            gas_volume_m3: self.gas.volume_m3(oil_c, y, void_before),
            gas_c: self.gas_c,
            void_m3: void_before,
            dvoid_m3: self.void_m3 - void_before,
            cavitating: hyd.cavitating,
            p_reb_pa: hyd.p_reb_pa,
            p_comp_pa: hyd.p_comp_pa,
            valve_power_w: hyd.valve_power_w,
            friction_power_w: hyd.friction_power_w,
            nodes: Some(self.nodes),
            room_c: self.room_c,
            heat_to_room_j: self.heat_to_room_j,
            dt_s: dt,
        };
        self.heat_oil_j += hyd.valve_power_w * dt;
        self.heat_inner_j += hyd.friction_power_w * dt;
        self.step_index += 1;
        if self.step_index % self.substeps_per_ms == 0 {
            self.thermal_tick()?;
        }
        Ok(truth)
    }

    fn thermal_tick(&mut self) -> Result<(), SimError> {
        let dt_th = 1e-3;
        let lost = self.net.step(
            &mut self.nodes,
            self.heat_oil_j / dt_th,
            self.heat_inner_j / dt_th,
            self.room_c,
            dt_th,
        );
        self.heat_to_room_j += lost;
        self.heat_oil_j = 0.0;
        self.heat_inner_j = 0.0;
        if !self.nodes.oil_c.is_finite() || self.nodes.oil_c > 250.0 {
            return Err(SimError::Numerical {
                what: "oil temperature (C)",
                value: self.nodes.oil_c,
            });
        }
        self.gas_c = self.gas.lag_gas_c(self.gas_c, self.nodes.oil_c, dt_th);
        self.nu_ratio = self.hyd.oil.ratio_to_40(self.nodes.oil_c);
        let ms = self.step_index / self.substeps_per_ms;
        if ms % 1000 == 0 {
            self.room.advance(1.0);
        }
        self.room_c = self.room.temp_c(self.t_s());
        Ok(())
    }
}
