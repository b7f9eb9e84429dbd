//! `dt-sim` owns the dyno simulator: the truth plant (a twin-tube damper on a
//! displacement-controlled dyno) and its sensors. It writes shocktwin log v1
//! campaigns through `dt_core::log` and never uses the twin's own models.
//!
//! The plant is deliberately richer than the twin (SPEC §3), so that fitting
//! and learning are real work:
//!
//! | effect | twin (SPEC §3) | plant (module) |
//! | --- | --- | --- |
//! | viscosity | `ν40 exp(−β(T−40))` | Walther/ASTM D341 (`oil`) |
//! | valves | power laws + smooth minimum | laminar+orifice bleed ∥ blow-off shim with saturation; piston rebound, piston compression, base compression, base intake valves (`valve`, `hydraulics`) |
//! | gas | ideal gas at oil temperature, adiabatic | lagging gas temperature, speed-dependent polytropic index, oil thermal expansion (`gas`) |
//! | cavitation | none | refill-limited void at low charge and high speed, force dead band after reversal (`hydraulics`) |
//! | friction | none | Coulomb (gas-pressure dependent) + viscous, tanh-smoothed (`hydraulics`) |
//! | heat | 2 nodes | oil, inner tube, outer tube (+ gas lag), convection, radiation, frame conduction, drifting room (`thermal`) |
//! | dyno | rigid | compliant body-end mount, actuator ramp and distortion (`dyno`); sine or a road drive file (ISO 8608 road through a quarter-car, `road`) |
//! | sensors | ideal | filters, noise, offsets, drift, quantisation, clipping, thermocouple lag (`sensors`) |
//!
//! All parameters live in one table: [`params`] / [`parameter_table`] /
//! `PARAMETERS.md`.
//!
//! API:
//! * [`simulate_campaign`]`(&CampaignSpec, out_dir)` — a campaign in
//!   parallel (rayon), one MCAP per run;
//! * [`simulate_run`]`(&RunSpec, &PlantParams, out_path)` — one run to a file;
//! * [`simulate_leak_history`]`(&LeakHistorySpec, out_dir)` — a unit losing gas,
//!   one run a day on the calendar;
//! * [`simulate_run_with`] — one run into any sample sink (in memory);
//! * [`Plant`] — the truth plant, stepped by hand (tests, studies).
//!
//! All data produced here is **simulated**; the metadata says so
//! (`simulated = "true"`).

pub mod dyno;
pub mod export;
pub mod gas;
pub mod hydraulics;
pub mod oil;
pub mod params;
pub mod plant;
pub mod road;
pub mod run;
pub mod sensors;
pub mod thermal;
pub mod valve;

pub use export::{simulate_dyno_csv, simulate_dyno_csv_campaign};
pub use params::{parameter_table, ParamInfo, PlantParams};
pub use plant::{Plant, PlantConfig, Truth};
pub use road::{RoadClass, RoadDrive};
pub use run::{
    simulate_campaign, simulate_campaign_with, simulate_leak_history, simulate_run,
    simulate_run_with, CampaignSpec, LeakHistorySpec, RunSpec, RunSummary, StopReason,
};

/// Everything that can go wrong in the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A plant parameter is out of range.
    #[error("invalid plant parameter {name} = {value}: {reason}")]
    InvalidParameter {
        /// Parameter name (as in the table).
        name: &'static str,
        /// Its value.
        value: f64,
        /// What is wrong.
        reason: &'static str,
    },
    /// A run or campaign field is out of range.
    #[error("invalid run spec: {field} = {value}: {reason}")]
    InvalidSpec {
        /// Field name.
        field: &'static str,
        /// Its value.
        value: f64,
        /// What is wrong.
        reason: &'static str,
    },
    /// A numerical failure (non-convergence, non-finite state).
    #[error("numerical failure: {what} = {value}")]
    Numerical {
        /// What failed.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// Writing the run log failed.
    #[error("run {run_id}: {source}")]
    Log {
        /// The run.
        run_id: String,
        /// The log error (names the file).
        #[source]
        source: Box<dt_core::log::LogError>,
    },
    /// A file-system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: String,
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

/// Mixes several words into one seed (`SplitMix64` finaliser chained over
/// the parts): deterministic, order-sensitive.
#[must_use]
pub fn mix_seed(parts: &[u64]) -> u64 {
    let mut h: u64 = 0x9E37_79B9_7F4A_7C15;
    for &p in parts {
        let mut z = h ^ p.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        h = z ^ (z >> 31);
    }
    h
}
