//! All physical parameters of the truth plant, in ONE table.
//!
//! The table below is generated from a single list (the `plant_params!`
//! invocation in this file): the struct [`PlantParams`], its
//! [`PlantParams::nominal`] values, the per-unit scatter used by
//! [`PlantParams::varied`] and the printed table of [`parameter_table`]
//! (also committed as `crates/dt-sim/PARAMETERS.md`, kept equal by a test)
//! all come from it, so they cannot drift apart.
//!
//! Sources are cited per line: "notes" = `../shared/reference/physics-notes.md`
//! (with the public source it names), "assumption" = a value chosen by us as
//! plausible for a passenger-car twin-tube damper on a servo-hydraulic dyno
//! with a cooling fan, stated as such.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// One row of the parameter table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamInfo {
    /// Group (physical component).
    pub group: &'static str,
    /// Field name in [`PlantParams`].
    pub name: &'static str,
    /// Nominal value (unit A).
    pub nominal: f64,
    /// Unit of the value.
    pub unit: &'static str,
    /// One-sigma unit-to-unit scatter in per cent applied by
    /// [`PlantParams::varied`] (0: a property of the dyno or of physics, not
    /// of the damper unit).
    pub scatter_pct: f64,
    /// Meaning and source.
    pub doc: &'static str,
}

macro_rules! plant_params {
    ($( $group:literal { $( $name:ident = $value:expr, $unit:literal, $scatter:expr, $doc:literal; )* } )*) => {
        /// All physical parameters of the truth plant (the damper unit, the
        /// dyno, its sensors and the room). See the module docs and
        /// [`parameter_table`] for the table with units and sources.
        // The field docs are the table's plain-text "meaning and source"
        // column (shared with PARAMETERS.md), so they are not markdown-linted.
        #[allow(clippy::doc_markdown)]
        #[derive(Debug, Clone, PartialEq)]
        pub struct PlantParams {
            $( $(
                #[doc = $doc]
                #[doc = concat!("Unit: ", $unit, ".")]
                pub $name: f64,
            )* )*
        }

        impl PlantParams {
            /// The nominal unit (`dyno-unit-A`).
            #[must_use]
            pub fn nominal() -> Self {
                Self { $( $( $name: $value, )* )* }
            }

            /// The table rows, in declaration order.
            pub const TABLE: &'static [ParamInfo] = &[ $( $(
                ParamInfo {
                    group: $group,
                    name: stringify!($name),
                    nominal: $value,
                    unit: $unit,
                    scatter_pct: $scatter,
                    doc: $doc,
                },
            )* )* ];

            /// Mutable references to every value, in table order.
            fn values_mut(&mut self) -> Vec<&mut f64> {
                vec![ $( $( &mut self.$name, )* )* ]
            }

            /// Every value, in table order.
            #[must_use]
            pub fn values(&self) -> Vec<f64> {
                vec![ $( $( self.$name, )* )* ]
            }
        }
    };
}

plant_params! {
    "geometry" {
        piston_diameter_m = 0.032, "m", 0.2,
            "Working-tube bore / piston diameter. Assumption: common passenger-car twin-tube size (the notes' Modelica model uses 28 mm).";
        rod_diameter_m = 0.012, "m", 0.2,
            "Piston-rod diameter (notes: Modelica twin-tube model, 12 mm rod; static gas force 136 N at 12 bar).";
        gas_volume_m3 = 1.5e-4, "m^3", 3.0,
            "Nitrogen volume in the reservoir at mid-stroke, oil at 20 C. Assumption (typical 0.1-0.2 L).";
        oil_volume_m3 = 3.6e-4, "m^3", 2.0,
            "Oil volume (inner tube + reservoir), about 0.31 kg. Assumption (notes' Modelica model: 0.125 kg for a smaller unit).";
    }
    "oil" {
        oil_density_kg_m3 = 860.0, "kg/m^3", 0.0,
            "Oil density (notes: Modelica model, 860 kg/m^3).";
        oil_nu40_cst = 15.0, "mm^2/s", 3.0,
            "Kinematic viscosity at 40 C (a typical damper oil, ISO VG 15 class; assumption).";
        oil_nu100_cst = 4.0, "mm^2/s", 3.0,
            "Kinematic viscosity at 100 C; with nu40 it fixes the Walther/ASTM D341 line log10(log10(nu+0.7)) = A - B log10(T[K]) (notes). Gives 30 mm^2/s at 20 C, about 3 %/K near 40 C.";
        oil_expansion_per_k = 7.0e-4, "1/K", 5.0,
            "Volumetric thermal expansion of the oil; the expanding oil compresses the gas (mineral oil 6.5-7.5e-4; notes' Modelica model uses 1e-3).";
        oil_cp_j_per_kgk = 1900.0, "J/(kg K)", 2.0,
            "Specific heat of mineral oil (textbook 1.8-2.0 kJ/(kg K)).";
    }
    "valves" {
        valve_cd = 0.7, "-", 2.0,
            "Discharge coefficient of every orifice (sharp-edged orifice 0.6-0.8; assumption).";
        reb_lam_pa_s_m3 = 4.0e9, "Pa s/m^3", 5.0,
            "Rebound piston valve: laminar resistance of the bleed at 40 C, scaled by nu(T)/nu40 (the viscous, temperature-dependent part).";
        reb_bleed_area_m2 = 3.4e-6, "m^2", 3.0,
            "Rebound piston valve: bleed orifice area (turbulent part, dp = rho Q^2 / (2 Cd^2 A^2)).";
        reb_crack_pa = 10.0e5, "Pa", 4.0,
            "Rebound piston valve: shim-stack cracking pressure (notes' Modelica: rebound 40 bar on a smaller valve; tuned for about 1.1 kN at 0.26 m/s).";
        reb_shim_gain_m2_pa = 2.5e-12, "m^2/Pa", 5.0,
            "Rebound piston valve: shim opening area per pascal above cracking.";
        reb_shim_max_m2 = 16.0e-6, "m^2", 3.0,
            "Rebound piston valve: full shim opening (the curve turns quadratic again above it).";
        pc_lam_pa_s_m3 = 6.0e8, "Pa s/m^3", 5.0,
            "Compression piston valve (refill of the rebound chamber): laminar resistance at 40 C.";
        pc_bleed_area_m2 = 2.2e-6, "m^2", 3.0,
            "Compression piston valve: bleed area.";
        pc_crack_pa = 2.0e5, "Pa", 4.0,
            "Compression piston valve: cracking pressure (a soft check valve).";
        pc_shim_gain_m2_pa = 1.2e-11, "m^2/Pa", 5.0,
            "Compression piston valve: opening area per pascal.";
        pc_shim_max_m2 = 18.0e-6, "m^2", 3.0,
            "Compression piston valve: full opening.";
        bc_lam_pa_s_m3 = 2.0e10, "Pa s/m^3", 5.0,
            "Base (foot) compression valve: laminar resistance at 40 C. It carries the rod-volume flow A_rod |v| to the reservoir and sets compression damping.";
        bc_bleed_area_m2 = 0.6e-6, "m^2", 3.0,
            "Base compression valve: bleed area.";
        bc_crack_pa = 12.0e5, "Pa", 4.0,
            "Base compression valve: cracking pressure (notes' Modelica: foot valves open at 10 bar).";
        bc_shim_gain_m2_pa = 1.5e-12, "m^2/Pa", 5.0,
            "Base compression valve: opening area per pascal.";
        bc_shim_max_m2 = 3.0e-6, "m^2", 3.0,
            "Base compression valve: full opening.";
        bi_lam_pa_s_m3 = 1.0e8, "Pa s/m^3", 5.0,
            "Base intake (refill) check valve: laminar resistance at 40 C.";
        bi_bleed_area_m2 = 0.3e-6, "m^2", 3.0,
            "Base intake valve: leak area when closed.";
        bi_crack_pa = 0.05e5, "Pa", 10.0,
            "Base intake valve: cracking pressure (a light check disc).";
        bi_shim_gain_m2_pa = 5.0e-10, "m^2/Pa", 5.0,
            "Base intake valve: opening area per pascal.";
        bi_shim_max_m2 = 4.5e-6, "m^2", 3.0,
            "Base intake valve: full opening; with the gas pressure it limits the refill flow, hence the cavitation onset (about 0.52 m/s at 0.5 bar, 1.0 m/s at 4 bar, 1.6 m/s at 12 bar; Guan et al. 2019 in the notes: force drops at 0.31-0.75 m/s at low charge).";
        cavitation_pa = 0.2e5, "Pa abs", 10.0,
            "Effective cavitation pressure (oil vapour plus fast gas release from aerated oil). Assumption: 0.1-0.3 bar absolute.";
    }
    "gas" {
        gas_gamma = 1.4, "-", 0.0,
            "Heat-capacity ratio of nitrogen (upper limit of the polytropic index).";
        gas_ht_tau_s = 0.15, "s", 10.0,
            "Heat-exchange time constant of the gas pocket for cyclic compression: polytropic index n = 1 + (gamma-1) (w tau)^2 / (1 + (w tau)^2) at the excitation angular frequency w (1.19 at 1 Hz, 1.31 at 2 Hz, 1.37 at 4 Hz; isothermal at rest). Assumption in the spirit of accumulator thermal time constants (Pourmovahed and Otis).";
        gas_tau_s = 60.0, "s", 10.0,
            "Thermal lag of the mean gas temperature behind the oil temperature (first order). Assumption.";
    }
    "friction" {
        friction_coulomb_n = 30.0, "N", 10.0,
            "Rod guide, piston band and seal Coulomb friction at zero gas pressure. Assumption (typical 20-60 N).";
        friction_seal_n_per_bar = 1.5, "N/bar", 10.0,
            "Extra seal friction per bar gauge of gas pressure (pressure-energised lip seal). Assumption.";
        friction_viscous_ns_m = 40.0, "N s/m", 10.0,
            "Viscous part of the seal/guide friction.";
        friction_v_smooth_mps = 0.005, "m/s", 0.0,
            "Velocity scale of the tanh that smooths the Coulomb friction through zero.";
    }
    "thermal" {
        inner_tube_c_j_per_k = 250.0, "J/K", 5.0,
            "Heat capacity of the inner (pressure) tube, piston and rod, about 0.52 kg steel at 480 J/(kg K).";
        outer_tube_c_j_per_k = 600.0, "J/K", 5.0,
            "Heat capacity of the outer (reservoir) tube, end caps and eyes, about 1.25 kg steel.";
        g_oil_inner_w_per_k = 60.0, "W/K", 8.0,
            "Oil to inner tube: forced convection on both faces, h about 1200 W/(m^2 K) over 0.05 m^2. Assumption.";
        g_oil_outer_w_per_k = 40.0, "W/K", 8.0,
            "Reservoir oil to outer tube: h about 700 W/(m^2 K) over 0.055 m^2 (oil pumped through the base valve and sloshing). Assumption.";
        g_inner_outer_w_per_k = 1.0, "W/K", 8.0,
            "Inner tube to outer tube by conduction through the end caps and rod guide.";
        g_outer_air_w_per_k = 1.95, "W/K", 8.0,
            "Outer tube to room air by forced convection (dyno cooling fan: h about 32 W/(m^2 K) over 0.06 m^2). Assumption.";
        g_outer_frame_w_per_k = 0.3, "W/K", 10.0,
            "Outer tube to the dyno frame (held at room temperature) by conduction through the eyes.";
        outer_area_m2 = 0.06, "m^2", 2.0,
            "Radiating outer area of the damper.";
        emissivity = 0.85, "-", 3.0,
            "Emissivity of the painted outer tube (radiation eps sigma A (T^4 - Tamb^4)).";
    }
    "ambient" {
        ambient_mean_c = 22.0, "C", 0.0,
            "Room temperature; each run draws its own mean from N(ambient_mean_c, ambient_run_sd_c).";
        ambient_run_sd_c = 1.0, "C", 0.0,
            "Run-to-run spread of the room temperature (runs on different days).";
        ambient_sine_amp_c = 0.5, "C", 0.0,
            "Slow drift: amplitude of a sine of period ambient_sine_period_s with a random phase.";
        ambient_sine_period_s = 3600.0, "s", 0.0,
            "Period of the slow drift.";
        ambient_walk_sd_c = 0.3, "C", 0.0,
            "Stationary standard deviation of an Ornstein-Uhlenbeck random walk added to the room temperature.";
        ambient_walk_tau_s = 900.0, "s", 0.0,
            "Correlation time of that random walk.";
        start_offset_max_c = 1.5, "C", 0.0,
            "The damper starts within this of the room temperature (uniform), inside the paper's 2 C.";
    }
    "dyno" {
        mount_mass_kg = 12.0, "kg", 0.0,
            "Effective moving mass of the body-end mount (damper body, eye, loadcell, crosshead share). Assumption.";
        mount_stiffness_n_per_m = 5.0e6, "N/m", 0.0,
            "Stiffness of the compliant body-end mount (bushings, crosshead): natural frequency about 103 Hz. Assumption.";
        mount_damping_ns_per_m = 1240.0, "N s/m", 0.0,
            "Damping of the mount (damping ratio about 0.08). Assumption.";
        actuator_h3 = 0.003, "-", 0.0,
            "Third-harmonic distortion of the servo actuator's displacement (fraction of the amplitude). Assumption.";
        actuator_ramp_s = 2.0, "s", 0.0,
            "The sine amplitude ramps up smoothly (raised cosine) over this time, as dyno controllers do.";
        substep_s = 2.5e-4, "s", 0.0,
            "Integration step of the plant (4 sub-steps per 1 kHz accelerometer sample; semi-implicit Euler for the mount, omega_n dt = 0.16).";
    }
    "sensors" {
        acc_range_mps2 = 78.45, "m/s^2", 0.0,
            "Accelerometer range, +-8 g; readings clip (notes: ADXL345 class).";
        acc_lsb_mps2 = 0.03826, "m/s^2", 0.0,
            "Accelerometer resolution, 3.9 mg/LSB (notes).";
        acc_noise_mps2 = 0.064, "m/s^2", 0.0,
            "Accelerometer white noise, 290 ug/sqrt(Hz) over 500 Hz = 6.5 mg rms (notes).";
        acc_offset_sd_mps2 = 0.25, "m/s^2", 0.0,
            "Accelerometer 0 g offset, per sensor of the rig, N(0, 25 mg) (notes: +-50 mg typical).";
        acc_offset_tc_mps2_per_k = 0.0017, "m/s^2/K", 0.0,
            "Accelerometer offset drift with the sensor's temperature, 0.17 mg/K (notes); the body-end sensor warms with the damper.";
        acc_gain_sd = 0.01, "-", 0.0,
            "Accelerometer sensitivity error, per sensor, N(0, 1 %). Assumption.";
        acc_nonlin_fs = 0.005, "-", 0.0,
            "Accelerometer nonlinearity, +-0.5 % of full scale at full scale (cubic shape; notes).";
        acc_bw_hz = 400.0, "Hz", 0.0,
            "Accelerometer anti-alias bandwidth (first order; the sensor's digital filter, ODR/2 class).";
        acc_g_mps2 = 9.80665, "m/s^2", 0.0,
            "Gravity: both sensing axes point along extension (body to rod, downward on this rig), so at rest both read -g (specific force); it cancels in a1 - a2.";
        pos_range_m = 0.075, "m", 0.0,
            "Potentiometer half range (150 mm travel, centred on mid-stroke); readings clip.";
        pos_lsb_m = 2.29e-6, "m", 0.0,
            "Potentiometer resolution: 16-bit ADC over 150 mm.";
        pos_noise_m = 1.0e-5, "m", 0.0,
            "Potentiometer noise, 10 um rms (notes: repeatability about 0.01 mm).";
        pos_offset_sd_m = 2.0e-4, "m", 0.0,
            "Potentiometer mid-stroke calibration error, per run, N(0, 0.2 mm).";
        pos_nonlin_m = 1.0e-4, "m", 0.0,
            "Potentiometer linearity error amplitude (a smooth bow over the travel; notes: 0.05-0.1 % FS).";
        pos_bw_hz = 50.0, "Hz", 0.0,
            "Potentiometer RC anti-alias filter before the 100 Hz sampling (first order).";
        force_noise_n = 6.0, "N", 0.0,
            "Loadcell noise after its amplifier, rms. Assumption for a 20 t strain-gauge cell with a 24-bit amplifier.";
        force_zero_sd_n = 15.0, "N", 0.0,
            "Loadcell zero error, per run, N(0, 15 N) (notes: repeatability 0.03 % RO = 59 N worst case).";
        force_lsb_n = 1.0, "N", 0.0,
            "Loadcell output resolution.";
        force_bw_hz = 20.0, "Hz", 0.0,
            "Loadcell amplifier anti-alias filter, 2nd-order Butterworth before 50 Hz sampling. The cell is in series with the mount, so it reads the mount force F - m a_body.";
        tc_lsb_c = 0.25, "C", 0.0,
            "Thermocouple converter resolution (MAX31855, notes).";
        tc_noise_c = 0.1, "C", 0.0,
            "Thermocouple noise, rms.";
        tc_offset_sd_c = 0.5, "C", 0.0,
            "K-type accuracy offset per thermocouple of the rig, N(0, 0.5 C) clipped to +-1.5 C (IEC 60584 class 1, notes).";
        tc_shock_tau_s = 10.0, "s", 0.0,
            "Lag of the surface-mounted shock thermocouple (first order; notes: seconds to tens of seconds).";
        tc_shock_contact = 0.9, "-", 0.0,
            "The surface thermocouple reads contact * T_outer + (1 - contact) * T_room (fin loss). Assumption.";
        tc_air_tau_s = 4.3, "s", 0.0,
            "Lag of the ambient thermocouple (1 mm sheath in air, t0.9 about 10 s: notes).";
    }
    "run" {
        rest_s = 60.0, "s", 0.0,
            "Rest before the excitation (paper 4.2: data from 1 minute before).";
        stop_temp_c = 80.0, "C", 0.0,
            "Stop when the shock thermocouple reads this (paper 4.1).";
        equilibrium_rise_c = 0.5, "C", 0.0,
            "Thermal equilibrium: the 30 s mean of the shock thermocouple rose less than this over equilibrium_window_s.";
        equilibrium_window_s = 300.0, "s", 0.0,
            "Window of the equilibrium test (5 min).";
        equilibrium_min_s = 600.0, "s", 0.0,
            "Equilibrium is not tested before this much excitation.";
        max_excitation_s = 3600.0, "s", 0.0,
            "Safety cap on the excitation time.";
    }
}

/// Atmospheric pressure, Pa (SPEC §3.3).
pub const P_ATM_PA: f64 = 101_325.0;
/// Celsius to kelvin offset.
pub const KELVIN: f64 = 273.15;
/// Reference temperature of the charge pressure (SPEC §1), °C.
pub const CHARGE_REF_C: f64 = 20.0;
/// Stefan–Boltzmann constant, W/(m² K⁴).
pub const STEFAN_BOLTZMANN: f64 = 5.670_374_419e-8;

impl PlantParams {
    /// A second unit of the same model: every parameter with a non-zero
    /// `scatter_pct` is multiplied by `1 + scatter_pct/100 · z`, `z` standard
    /// normal clipped to ±2, drawn from `unit_seed` (deterministic). Rig,
    /// sensor and room parameters (scatter 0) are unchanged.
    #[must_use]
    pub fn varied(&self, unit_seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(crate::mix_seed(&[0x756e_6974, unit_seed]));
        let mut out = self.clone();
        for (value, info) in out.values_mut().into_iter().zip(Self::TABLE) {
            let z: f64 = rng.sample::<f64, _>(StandardNormal).clamp(-2.0, 2.0);
            if info.scatter_pct > 0.0 {
                *value *= 1.0 + info.scatter_pct / 100.0 * z;
            }
        }
        out
    }

    /// This unit with the one parameter `name` multiplied by `factor` (a
    /// sensitivity study: `examples/unit_sensitivity.rs`); `None` for a name
    /// not in [`Self::TABLE`].
    #[must_use]
    pub fn scaled(&self, name: &str, factor: f64) -> Option<Self> {
        let i = Self::TABLE.iter().position(|p| p.name == name)?;
        let mut out = self.clone();
        *out.values_mut()[i] *= factor;
        Some(out)
    }

    /// Piston (bore) area, m².
    #[must_use]
    pub fn piston_area_m2(&self) -> f64 {
        std::f64::consts::FRAC_PI_4 * self.piston_diameter_m * self.piston_diameter_m
    }

    /// Rod area, m².
    #[must_use]
    pub fn rod_area_m2(&self) -> f64 {
        std::f64::consts::FRAC_PI_4 * self.rod_diameter_m * self.rod_diameter_m
    }

    /// Annulus area (piston minus rod), m².
    #[must_use]
    pub fn annulus_area_m2(&self) -> f64 {
        self.piston_area_m2() - self.rod_area_m2()
    }

    /// Heat capacity of the oil, J/K.
    #[must_use]
    pub fn oil_c_j_per_k(&self) -> f64 {
        self.oil_volume_m3 * self.oil_density_kg_m3 * self.oil_cp_j_per_kgk
    }

    /// Checks that every value is finite and that the ones that must be
    /// positive are; names the first offending parameter.
    pub fn validate(&self) -> Result<(), crate::SimError> {
        for (value, info) in self.values().into_iter().zip(Self::TABLE) {
            let may_be_zero = matches!(
                info.name,
                "actuator_h3"
                    | "ambient_sine_amp_c"
                    | "ambient_walk_sd_c"
                    | "ambient_run_sd_c"
                    | "start_offset_max_c"
                    | "friction_seal_n_per_bar"
                    | "friction_viscous_ns_m"
                    | "friction_coulomb_n"
                    | "g_inner_outer_w_per_k"
                    | "g_outer_frame_w_per_k"
                    | "emissivity"
                    | "rest_s"
            ) || info.group == "sensors";
            let ok = value.is_finite() && (value > 0.0 || (may_be_zero && value >= 0.0));
            if !ok {
                return Err(crate::SimError::InvalidParameter {
                    name: info.name,
                    value,
                    reason: "must be finite and positive",
                });
            }
        }
        if self.rod_diameter_m >= self.piston_diameter_m {
            return Err(crate::SimError::InvalidParameter {
                name: "rod_diameter_m",
                value: self.rod_diameter_m,
                reason: "must be smaller than piston_diameter_m",
            });
        }
        Ok(())
    }
}

/// The parameter table as markdown (the same text as `PARAMETERS.md`).
#[must_use]
pub fn parameter_table() -> String {
    use std::fmt::Write as _;
    let mut out = String::from(
        "# dt-sim plant parameters (nominal unit `dyno-unit-A`)\n\n\
         Generated by `dt_sim::parameter_table()` from the one list in \
         `crates/dt-sim/src/params.rs`; a test keeps this file equal to it.\n\
         `scatter` is the one-sigma unit-to-unit spread applied by \
         `PlantParams::varied` (`--unit N`), clipped at two sigma.\n\n\
         | group | parameter | nominal | unit | scatter | meaning and source |\n\
         | --- | --- | --- | --- | --- | --- |\n",
    );
    for p in PlantParams::TABLE {
        let scatter = if p.scatter_pct > 0.0 {
            format!("{} %", p.scatter_pct)
        } else {
            "-".to_owned()
        };
        let mag = p.nominal.abs();
        let nominal = if mag != 0.0 && !(1e-2..1e5).contains(&mag) {
            format!("{:e}", p.nominal)
        } else {
            format!("{}", p.nominal)
        };
        let _ = writeln!(
            out,
            "| {} | `{}` | {} | {} | {} | {} |",
            p.group, p.name, nominal, p.unit, scatter, p.doc
        );
    }
    out
}
