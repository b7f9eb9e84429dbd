//! The 50 Hz feature pipeline (SPEC §4; ARCHITECTURE.md "Design decisions"):
//! sensor samples in time order in, one feature row per 20 ms tick out.
//! Batch features ([`compute_features`], used for training) and the streaming
//! estimator run this same [`FeaturePipeline`].
//!
//! # Input groups and columns
//!
//! Every row carries all [`N_COLUMNS`] columns of [`COLUMNS`]; a group's
//! columns are NaN when the pipeline was not given the topics it needs.
//!
//! | group | columns | needs topics (sensors) |
//! | --- | --- | --- |
//! | `force` | `force_n` | `/force` (loadcell) |
//! | `position` | `position_m` | `/position` (potentiometer) |
//! | `acceleration` | `accel_rel_mps2` | `/acceleration` (accelerometer pair) |
//! | `velocity` | `velocity_mps` | `/position`, `/acceleration` |
//! | `mechanical` | `force_model_n`, `force_damping_model_n`, `force_gas_model_n` | `/position`, `/acceleration`, `/temperature/shock` (+ thermocouples) |
//! | `thermal` | `temp_shock_c`, `temp_ambient_c`, `oil_temp_model_c`, `cyl_temp_model_c`, `heat_rate_model_w` | `/position`, `/acceleration`, `/temperature/shock`, `/temperature/ambient` |
//! | `signature` | `accel_hf_rms_mps2`, `velocity_rms_mps`, `temp_resid_c`, `temp_resid_rate_cps` | as `thermal` (potentiometer, accelerometers, thermocouples) |
//! | `residual` | `force_resid_mean_n`, `force_resid_rms_n` | `/force` + those of `mechanical` (loadcell, potentiometer, accelerometers, thermocouples) |
//!
//! The first six are the paper's ([`Group::PAPER`]); `signature` and
//! `residual` are ours, causal windows over past ticks (issue 4 "beyond
//! memoryless inputs"): where the gas charge shows without absolute
//! quantities that fingerprint a run.
//!
//! - `force_n`: boxcar mean of the loadcell, N (tension positive).
//! - `position_m`: boxcar mean of the potentiometer (raw sensor), m.
//! - `accel_rel_mps2`: boxcar mean of the raw `a1 − a2`, m/s² (not bias-corrected).
//! - `velocity_mps`: boxcar mean of the Kalman velocity (SPEC §3.1), m/s.
//! - `force_model_n`: eq. 9 total of the nominal force model at the tick, N.
//! - `force_damping_model_n`: its damping part `sign(ẏ)(F_port+F_main) − k_hys ÿ`, N.
//! - `force_gas_model_n`: its gas part `−F_gas`, N.
//! - `temp_shock_c`, `temp_ambient_c`: thermocouples, zero-order held, °C.
//! - `oil_temp_model_c`, `cyl_temp_model_c`: thermal model (SPEC §3.2) at the tick, °C.
//! - `heat_rate_model_w`: heat input at the tick, `(F_port+F_main)·|ẏ|`, W.
//! - `accel_hf_rms_mps2`: RMS over the last 1 s (50 ticks: this one and the
//!   49 before, NaN ticks skipped) of the within-tick standard deviation of
//!   the raw `a_rel`, `sqrt(max(E[a²] − E[a]², 0))` over the samples of the
//!   tick's interval (NaN for a tick without one), m/s²: the high-frequency
//!   energy, e.g. the mount ringing after the friction step at each velocity
//!   reversal (seal friction grows with the gas pressure).
//! - `velocity_rms_mps`: the excitation measure
//!   [`TwinState::velocity_rms_1s_mps`], m/s.
//! - `temp_resid_c`: `temp_shock_c − cyl_temp_model_c`, °C: how far the
//!   measured temperature is from the nominal thermal model (less damping
//!   force, less heat). With a calibrated thermocouple model (`tc_gain`,
//!   `tc_lag_s` in the thermal parameters, an extension of SPEC §3.2) the
//!   model side is what the thermocouple should read instead of
//!   `cyl_temp_model_c` (`FeaturePipeline::thermocouple_model_c`).
//! - `temp_resid_rate_cps`: `(temp_resid_c(t_k) − temp_resid_c(t_k − 10 s)) /
//!   10 s` (500 ticks back), °C/s; NaN until 10 s of history.
//! - `force_resid_mean_n`: mean over the last 1 s (50 ticks, NaN ticks
//!   skipped) of `force_n − force_model_n`, N: the force the nominal model
//!   misses (gas force offset).
//! - `force_resid_rms_n`: the RMS of those 50 differences about that mean, N.
//!
//! # Algorithm (what a transcription must reproduce)
//!
//! 0. **Suite.** The pipeline takes the values of the topics in its
//!    [`TopicSet`] only; samples of other topics still advance the clock.
//! 1. **Order.** Samples arrive in time order; at equal times acceleration,
//!    position, force, shock temperature, ambient temperature, truth
//!    ([`sorted_samples`]). A sample earlier than the previous one is an error.
//! 2. **Clock.** `t_origin` = time of the first sample (any topic); ticks at
//!    `t_k = t_origin + k·20 ms`, `k ≥ 1`. Tick `k` covers `(t_{k−1}, t_k]` and
//!    is emitted when a sample with `t > t_k` arrives, or by
//!    [`FeaturePipeline::finish`] (the last tick, if it holds any sample).
//!    Nothing after `t_k` influences row `k`: no look-ahead.
//! 3. **Kalman filter** at sensor rates, exactly [`crate::kalman`]: with the
//!    `/acceleration` topic available the SPEC §3.1 filter (accelerometer and
//!    position events); without it the position-only filter
//!    ([`crate::kalman::POSITION_ONLY_JERK_PSD`]). Its state is *sampled* at
//!    each accelerometer sample time (position-only: each position sample
//!    time), after every event at that time — the rows of
//!    [`crate::kalman::run_kalman`] — skipping times before the filter's
//!    first position sample.
//! 4. **Boxcar.** Fast channels are averaged over `(t_{k−1}, t_k]`: loadcell,
//!    potentiometer, raw `a_rel`, and the sampled Kalman position `ŷ`,
//!    velocity `ẏ̂` and bias-corrected acceleration `a_rel − b̂` (position-only:
//!    the filter's `ÿ̂`). A channel with no sample in the interval holds its
//!    previous mean and counts a gap ([`GapCounters`]); NaN until its first
//!    sample. Non-finite samples are skipped (counted in
//!    [`TwinState::missing_samples`]).
//! 5. **Temperatures** (1 Hz) are zero-order held: the last sample at or
//!    before `t_k`.
//! 6. **Thermal model.** It starts at the first tick at or after the first
//!    shock temperature with `T_oil = T_cyl =` that temperature. At every later
//!    tick it takes one RK4 step of 20 ms from `t_{k−1}` with the heat input and
//!    ambient of tick `k−1` held. Ambient: the ambient thermocouple's held
//!    value; before its first sample, or without one, the first shock
//!    temperature (a unit starting at ambient, as in the paper's tests).
//! 7. **Force model** at the tick (SPEC §3.3) from the boxcar means: velocity
//!    `ẏ̂`, acceleration `a_rel − b̂`, position `ŷ` (the Kalman position, not
//!    the raw potentiometer) and `T_oil` of the thermal model at `t_k` (NaN
//!    before it starts).
//! 8. **Heat input** at the tick `P_k = (F_port + F_main)(ẏ̂_k, T_oil,k)·|ẏ̂_k|`
//!    — the power at the boxcar-mean velocity (for a 4 Hz, 80 mm p-p sine
//!    this is within ≈ 2 % of the mean power over the interval) — held over
//!    the next RK4 step. Before the filter's first velocity, 0 W is used.
//!
//! 9. **Windows** (`signature`, `residual`): per tick the within-tick
//!    variance of the raw `a_rel` (from the boxcar's `Σa`, `Σa²`, `n`), the
//!    temperature residual and the force residual go into fixed rings of the
//!    last 50 (500 for the temperature rate) ticks; the columns are
//!    statistics of the rings, so row `k` still depends on nothing after
//!    `t_k`.
//!
//! Per tick the twin's internal state ([`TwinState`]) is reported too:
//! Kalman estimates, the modelled force and oil temperature, an excitation
//! measure (RMS of the tick velocities over the last 1 s = 50 ticks) and gap
//! counters. The truth label `/truth/gas_pressure` (simulator only) is held
//! at each tick in [`TickRow::truth_static_bar`]; the simulator-truth
//! velocity `/truth/velocity` is ignored entirely (not even the clock).
//!
//! # Sensor suites
//!
//! [`Sensor`] costs (AUD, paper Table 3): loadcell 3995, potentiometer 275,
//! accelerometer pair 11, thermocouples (both) 11. [`paper_permutations`] are
//! the 13 input permutations of SPEC §4 / paper Table 2;
//! [`extra_permutations`] (14–16) add the causal-window groups.

use std::borrow::Cow;
use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use crate::charge::{ChargeObserver, ObserverCounters, ObserverParams, Reversal};
use crate::error::PhysicsError;
use crate::force::ForceModel;
use crate::kalman::{KalmanFilter, POSITION_ONLY_JERK_PSD};
use crate::log::{topic, RunLog, Sample};
use crate::params::PhysicsParams;
use crate::thermal::{ThermalModel, ThermalState};

/// Tick period of the feature clock, ns (50 Hz).
pub const TICK_NS: i64 = 20_000_000;
/// Tick period, s.
pub const TICK_S: f64 = 0.02;
/// Ticks in the excitation window (1 s).
pub const EXCITATION_WINDOW_TICKS: usize = 50;

/// Ticks in the temperature-residual rate window (10 s).
pub const TEMP_RATE_WINDOW_TICKS: usize = 500;

/// Number of feature columns.
pub const N_COLUMNS: usize = 20;

/// All feature columns, in group order (force, position, acceleration,
/// velocity, mechanical, thermal, signature, residual); a group's columns
/// are contiguous.
pub const COLUMNS: [&str; N_COLUMNS] = [
    "force_n",
    "position_m",
    "accel_rel_mps2",
    "velocity_mps",
    "force_model_n",
    "force_damping_model_n",
    "force_gas_model_n",
    "temp_shock_c",
    "temp_ambient_c",
    "oil_temp_model_c",
    "cyl_temp_model_c",
    "heat_rate_model_w",
    "accel_hf_rms_mps2",
    "velocity_rms_mps",
    "temp_resid_c",
    "temp_resid_rate_cps",
    "force_resid_mean_n",
    "force_resid_rms_n",
    "observer_bar",
    "observer_sd_bar",
];

/// Indices into [`COLUMNS`] / [`TickRow::values`].
pub mod col {
    /// `force_n`.
    pub const FORCE_N: usize = 0;
    /// `position_m`.
    pub const POSITION_M: usize = 1;
    /// `accel_rel_mps2`.
    pub const ACCEL_REL_MPS2: usize = 2;
    /// `velocity_mps`.
    pub const VELOCITY_MPS: usize = 3;
    /// `force_model_n`.
    pub const FORCE_MODEL_N: usize = 4;
    /// `force_damping_model_n`.
    pub const FORCE_DAMPING_MODEL_N: usize = 5;
    /// `force_gas_model_n`.
    pub const FORCE_GAS_MODEL_N: usize = 6;
    /// `temp_shock_c`.
    pub const TEMP_SHOCK_C: usize = 7;
    /// `temp_ambient_c`.
    pub const TEMP_AMBIENT_C: usize = 8;
    /// `oil_temp_model_c`.
    pub const OIL_TEMP_MODEL_C: usize = 9;
    /// `cyl_temp_model_c`.
    pub const CYL_TEMP_MODEL_C: usize = 10;
    /// `heat_rate_model_w`.
    pub const HEAT_RATE_MODEL_W: usize = 11;
    /// `accel_hf_rms_mps2`.
    pub const ACCEL_HF_RMS_MPS2: usize = 12;
    /// `velocity_rms_mps`.
    pub const VELOCITY_RMS_MPS: usize = 13;
    /// `temp_resid_c`.
    pub const TEMP_RESID_C: usize = 14;
    /// `temp_resid_rate_cps`.
    pub const TEMP_RESID_RATE_CPS: usize = 15;
    /// `force_resid_mean_n`.
    pub const FORCE_RESID_MEAN_N: usize = 16;
    /// `force_resid_rms_n`.
    pub const FORCE_RESID_RMS_N: usize = 17;
    /// `observer_bar`.
    pub const OBSERVER_BAR: usize = 18;
    /// `observer_sd_bar`.
    pub const OBSERVER_SD_BAR: usize = 19;
}

/// A sensor of a suite (paper Table 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sensor {
    /// 20 t strain-gauge loadcell (`/force`).
    Loadcell,
    /// Linear potentiometer (`/position`).
    Potentiometer,
    /// The 8 g accelerometer pair (`/acceleration`).
    Accelerometers,
    /// Both K-type thermocouples (`/temperature/shock`, `/temperature/ambient`).
    Thermocouples,
}

impl Sensor {
    /// All sensors.
    pub const ALL: [Sensor; 4] = [
        Sensor::Loadcell,
        Sensor::Potentiometer,
        Sensor::Accelerometers,
        Sensor::Thermocouples,
    ];

    /// Cost, AUD (derived from paper Table 3).
    #[must_use]
    pub fn cost_aud(self) -> u32 {
        match self {
            Sensor::Loadcell => 3995,
            Sensor::Potentiometer => 275,
            Sensor::Accelerometers | Sensor::Thermocouples => 11,
        }
    }

    /// Lower-case name.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Sensor::Loadcell => "loadcell",
            Sensor::Potentiometer => "potentiometer",
            Sensor::Accelerometers => "accelerometers",
            Sensor::Thermocouples => "thermocouples",
        }
    }
}

/// An input group: the paper's six of SPEC §4 ([`Group::PAPER`]) and two
/// causal-window groups of ours (`signature`, `residual`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Group {
    /// Loadcell force.
    Force,
    /// Potentiometer position.
    Position,
    /// Relative acceleration `a1 − a2`.
    Acceleration,
    /// Kalman velocity.
    Velocity,
    /// Modelled force and its parts.
    Mechanical,
    /// Measured and modelled temperatures, modelled heat rate.
    Thermal,
    /// Causal 1 s / 10 s window signatures of the gas charge without a
    /// loadcell: high-frequency acceleration energy, excitation level,
    /// measured-minus-modelled temperature and its rate.
    Signature,
    /// Causal 1 s mean and RMS of measured minus modelled force (loadcell).
    Residual,
    /// The gas-charge observer's posterior mean and standard deviation
    /// ([`crate::charge`]).
    Observer,
}

impl Group {
    /// All groups, in column order.
    pub const ALL: [Group; 9] = [
        Group::Force,
        Group::Position,
        Group::Acceleration,
        Group::Velocity,
        Group::Mechanical,
        Group::Thermal,
        Group::Signature,
        Group::Residual,
        Group::Observer,
    ];

    /// The paper's six groups (SPEC §4), in column order.
    pub const PAPER: [Group; 6] = [
        Group::Force,
        Group::Position,
        Group::Acceleration,
        Group::Velocity,
        Group::Mechanical,
        Group::Thermal,
    ];

    /// SPEC name (`force`, `position`, ...).
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Group::Force => "force",
            Group::Position => "position",
            Group::Acceleration => "acceleration",
            Group::Velocity => "velocity",
            Group::Mechanical => "mechanical",
            Group::Thermal => "thermal",
            Group::Signature => "signature",
            Group::Residual => "residual",
            Group::Observer => "observer",
        }
    }

    /// The group named `name` (SPEC names, case-sensitive).
    pub fn from_name(name: &str) -> Result<Group, PhysicsError> {
        Group::ALL
            .into_iter()
            .find(|g| g.name() == name)
            .ok_or_else(|| PhysicsError::UnknownGroup(name.to_owned()))
    }

    /// Indices of the group's columns in [`COLUMNS`] (contiguous).
    #[must_use]
    pub fn column_range(self) -> std::ops::Range<usize> {
        match self {
            Group::Force => 0..1,
            Group::Position => 1..2,
            Group::Acceleration => 2..3,
            Group::Velocity => 3..4,
            Group::Mechanical => 4..7,
            Group::Thermal => 7..12,
            Group::Signature => 12..16,
            Group::Residual => 16..18,
            Group::Observer => 18..20,
        }
    }

    /// The group's column names, in order.
    #[must_use]
    pub fn columns(self) -> &'static [&'static str] {
        &COLUMNS[self.column_range()]
    }

    /// The topics the group needs (SPEC §4 table).
    #[must_use]
    pub fn required_topics(self) -> &'static [&'static str] {
        match self {
            Group::Force => &[topic::FORCE],
            Group::Position => &[topic::POSITION],
            Group::Acceleration => &[topic::ACCELERATION],
            Group::Velocity => &[topic::POSITION, topic::ACCELERATION],
            Group::Mechanical | Group::Observer => {
                &[topic::POSITION, topic::ACCELERATION, topic::TEMP_SHOCK]
            }
            Group::Residual => &[
                topic::FORCE,
                topic::POSITION,
                topic::ACCELERATION,
                topic::TEMP_SHOCK,
            ],
            Group::Thermal | Group::Signature => &[
                topic::POSITION,
                topic::ACCELERATION,
                topic::TEMP_SHOCK,
                topic::TEMP_AMBIENT,
            ],
        }
    }

    /// The sensors the group needs.
    #[must_use]
    pub fn sensors(self) -> &'static [Sensor] {
        match self {
            Group::Force => &[Sensor::Loadcell],
            Group::Position => &[Sensor::Potentiometer],
            Group::Acceleration => &[Sensor::Accelerometers],
            Group::Velocity => &[Sensor::Potentiometer, Sensor::Accelerometers],
            Group::Mechanical | Group::Thermal | Group::Signature | Group::Observer => &[
                Sensor::Potentiometer,
                Sensor::Accelerometers,
                Sensor::Thermocouples,
            ],
            Group::Residual => &[
                Sensor::Loadcell,
                Sensor::Potentiometer,
                Sensor::Accelerometers,
                Sensor::Thermocouples,
            ],
        }
    }
}

impl std::str::FromStr for Group {
    type Err = PhysicsError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Group::from_name(s)
    }
}

impl std::fmt::Display for Group {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The distinct sensors a set of groups needs, in [`Sensor::ALL`] order.
#[must_use]
pub fn suite_sensors(groups: &[Group]) -> Vec<Sensor> {
    Sensor::ALL
        .into_iter()
        .filter(|s| groups.iter().any(|g| g.sensors().contains(s)))
        .collect()
}

/// Cost of the sensor suite a set of groups needs, AUD.
#[must_use]
pub fn suite_cost_aud(groups: &[Group]) -> u32 {
    suite_sensors(groups).iter().map(|s| s.cost_aud()).sum()
}

/// Indices into [`COLUMNS`] of the columns of `groups`, in the order given
/// (a repeated group is taken once).
#[must_use]
pub fn column_indices(groups: &[Group]) -> Vec<usize> {
    let mut seen = [false; Group::ALL.len()];
    let mut out = Vec::new();
    for g in groups {
        let i = *g as usize;
        if !seen[i] {
            seen[i] = true;
            out.extend(g.column_range());
        }
    }
    out
}

/// Names of the columns of `groups`, in the order of [`column_indices`].
#[must_use]
pub fn column_names(groups: &[Group]) -> Vec<&'static str> {
    column_indices(groups)
        .into_iter()
        .map(|i| COLUMNS[i])
        .collect()
}

/// The values of `groups`' columns in `row`, in the order of
/// [`column_indices`].
#[must_use]
pub fn select(row: &TickRow, groups: &[Group]) -> Vec<f64> {
    column_indices(groups)
        .into_iter()
        .map(|i| row.values[i])
        .collect()
}

/// An input permutation: a named set of groups (data, not code; users define
/// their own).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Permutation {
    /// Identifier (1–13 for the paper's, 14–16 for
    /// [`extra_permutations`]).
    pub id: u32,
    /// Human-readable name.
    pub name: Cow<'static, str>,
    /// Input groups, in column order.
    pub groups: Cow<'static, [Group]>,
}

impl Permutation {
    /// Its feature column names.
    #[must_use]
    pub fn columns(&self) -> Vec<&'static str> {
        column_names(&self.groups)
    }

    /// Its sensor suite's cost, AUD.
    #[must_use]
    pub fn cost_aud(&self) -> u32 {
        suite_cost_aud(&self.groups)
    }
}

macro_rules! perm {
    ($id:expr, $name:expr, [$($g:ident),*]) => {
        Permutation {
            id: $id,
            name: Cow::Borrowed($name),
            groups: Cow::Borrowed(&[$(Group::$g),*]),
        }
    };
}

/// The 13 permutations of SPEC §4 (paper Table 2). Names of models 3, 7, 9,
/// 11, 12 and 13 are the paper's; the paper gives none for the others, so
/// theirs are ours, in the same style.
pub static PAPER_PERMUTATIONS: [Permutation; 13] = [
    perm!(1, "Force DNN", [Force]),
    perm!(2, "Position DNN", [Position]),
    perm!(3, "Force and Position DNN", [Force, Position]),
    perm!(4, "Acceleration DNN", [Acceleration]),
    perm!(5, "Force and Acceleration DNN", [Force, Acceleration]),
    perm!(6, "Position and Acceleration DNN", [Position, Acceleration]),
    perm!(
        7,
        "Force, Position and Acceleration DNN",
        [Force, Position, Acceleration]
    ),
    perm!(
        8,
        "Kalman-Velocity Hybrid DNN (No Force)",
        [Position, Acceleration, Velocity]
    ),
    perm!(
        9,
        "Kalman-Velocity Hybrid DNN",
        [Force, Position, Acceleration, Velocity]
    ),
    perm!(
        10,
        "Mechanical Hybrid DNN (No Force)",
        [Position, Acceleration, Velocity, Mechanical]
    ),
    perm!(
        11,
        "Mechanical Hybrid DNN",
        [Force, Position, Acceleration, Velocity, Mechanical]
    ),
    perm!(
        12,
        "Thermomechanical Hybrid DNN (No Force)",
        [Position, Acceleration, Velocity, Mechanical, Thermal]
    ),
    perm!(
        13,
        "Thermomechanical Hybrid DNN",
        [Force, Position, Acceleration, Velocity, Mechanical, Thermal]
    ),
];

/// The 13 permutations of SPEC §4.
#[must_use]
pub fn paper_permutations() -> &'static [Permutation] {
    &PAPER_PERMUTATIONS
}

/// Our permutations beyond the paper's (ids 14–19): the paper's hybrids
/// with the causal-window groups `signature` and `residual` (14–16) and with
/// the gas-charge observer (17–19).
pub static EXTRA_PERMUTATIONS: [Permutation; 6] = [
    perm!(
        14,
        "Causal signature hybrid (no force)",
        [Velocity, Mechanical, Signature]
    ),
    perm!(
        15,
        "Causal residual hybrid",
        [Force, Velocity, Mechanical, Residual]
    ),
    perm!(
        16,
        "Causal full hybrid",
        [Force, Velocity, Mechanical, Residual, Signature]
    ),
    perm!(17, "Charge observer (no force)", [Observer]),
    perm!(
        18,
        "Observer thermomechanical hybrid (no force)",
        [
            Position,
            Acceleration,
            Velocity,
            Mechanical,
            Thermal,
            Observer
        ]
    ),
    perm!(
        19,
        "Observer thermomechanical hybrid",
        [
            Force,
            Position,
            Acceleration,
            Velocity,
            Mechanical,
            Thermal,
            Observer
        ]
    ),
];

/// Our permutations beyond the paper's 13 ([`EXTRA_PERMUTATIONS`], ids
/// 14–19); [`paper_rmse_bar`] has no figure for them.
#[must_use]
pub fn extra_permutations() -> &'static [Permutation] {
    &EXTRA_PERMUTATIONS
}

/// The paper's test RMSE for permutation `id` (SPEC §4 table), bar.
#[must_use]
pub fn paper_rmse_bar(id: u32) -> Option<f64> {
    const RMSE: [f64; 13] = [
        3.34, 3.53, 2.51, 3.52, 3.18, 3.18, 2.27, 3.18, 1.84, 3.08, 1.72, 1.40, 0.85,
    ];
    (1..=13).contains(&id).then(|| RMSE[id as usize - 1])
}

/// Which topics a pipeline gets (decides the Kalman mode and which groups'
/// columns are filled).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[allow(clippy::struct_excessive_bools)] // a set of independent flags, one per topic
pub struct TopicSet {
    /// `/position`.
    pub position: bool,
    /// `/acceleration`.
    pub acceleration: bool,
    /// `/force`.
    pub force: bool,
    /// `/temperature/shock`.
    pub temp_shock: bool,
    /// `/temperature/ambient`.
    pub temp_ambient: bool,
}

impl TopicSet {
    /// Every sensor topic.
    #[must_use]
    pub fn all() -> Self {
        Self {
            position: true,
            acceleration: true,
            force: true,
            temp_shock: true,
            temp_ambient: true,
        }
    }

    /// The topics of `log` that have at least one sample.
    #[must_use]
    pub fn from_log(log: &RunLog) -> Self {
        Self {
            position: !log.position.is_empty(),
            acceleration: !log.acceleration.is_empty(),
            force: !log.force.is_empty(),
            temp_shock: !log.temp_shock.is_empty(),
            temp_ambient: !log.temp_ambient.is_empty(),
        }
    }

    /// The topics the given sensors provide.
    #[must_use]
    pub fn from_sensors(sensors: &[Sensor]) -> Self {
        let has = |s| sensors.contains(&s);
        Self {
            position: has(Sensor::Potentiometer),
            acceleration: has(Sensor::Accelerometers),
            force: has(Sensor::Loadcell),
            temp_shock: has(Sensor::Thermocouples),
            temp_ambient: has(Sensor::Thermocouples),
        }
    }

    /// The set with `sample`'s topic in it (truth topics are no sensor's).
    #[must_use]
    pub fn with(mut self, sample: &crate::log::Sample) -> Self {
        use crate::log::Sample;
        match sample {
            Sample::Position { .. } => self.position = true,
            Sample::Acceleration { .. } => self.acceleration = true,
            Sample::Force { .. } => self.force = true,
            Sample::TempShock { .. } => self.temp_shock = true,
            Sample::TempAmbient { .. } => self.temp_ambient = true,
            Sample::TruthPressure { .. } | Sample::TruthVelocity { .. } => {}
        }
        self
    }

    /// Whether `topic` (a SPEC §2 sensor topic name) is in the set.
    #[must_use]
    pub fn contains(&self, name: &str) -> bool {
        match name {
            topic::POSITION => self.position,
            topic::ACCELERATION => self.acceleration,
            topic::FORCE => self.force,
            topic::TEMP_SHOCK => self.temp_shock,
            topic::TEMP_AMBIENT => self.temp_ambient,
            _ => false,
        }
    }

    /// The topics that `groups` need (the sensors of their suite).
    #[must_use]
    pub fn for_groups(groups: &[Group]) -> Self {
        let needs = |name: &str| groups.iter().any(|g| g.required_topics().contains(&name));
        Self {
            position: needs(topic::POSITION),
            acceleration: needs(topic::ACCELERATION),
            force: needs(topic::FORCE),
            temp_shock: needs(topic::TEMP_SHOCK),
            temp_ambient: needs(topic::TEMP_AMBIENT),
        }
    }

    /// The topics in both sets.
    #[must_use]
    pub fn intersect(self, other: Self) -> Self {
        Self {
            position: self.position && other.position,
            acceleration: self.acceleration && other.acceleration,
            force: self.force && other.force,
            temp_shock: self.temp_shock && other.temp_shock,
            temp_ambient: self.temp_ambient && other.temp_ambient,
        }
    }

    /// The topics `groups` need that are not in the set, each once, in the
    /// order the groups name them.
    #[must_use]
    pub fn missing_for(&self, groups: &[Group]) -> Vec<&'static str> {
        let mut missing: Vec<&'static str> = Vec::new();
        for g in groups {
            for t in g.required_topics() {
                if !self.contains(t) && !missing.contains(t) {
                    missing.push(t);
                }
            }
        }
        missing
    }
}

/// Cumulative counts of ticks in which a fast channel had no sample (after
/// its first one) and held its previous mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct GapCounters {
    /// `/force`.
    pub force: u64,
    /// `/position`.
    pub position: u64,
    /// `/acceleration`.
    pub acceleration: u64,
    /// Sampled Kalman states.
    pub kalman: u64,
}

/// The twin's internal state at a tick (for the estimator: excitation,
/// diagnostics, `/estimate` fields).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TwinState {
    /// Boxcar mean of the Kalman position, m.
    pub position_m: f64,
    /// Boxcar mean of the Kalman velocity, m/s (position-only filter without
    /// accelerometers).
    pub velocity_mps: f64,
    /// Boxcar mean of the bias-corrected acceleration `a_rel − b̂` (or the
    /// position-only filter's `ÿ̂`), m/s².
    pub accel_mps2: f64,
    /// Last sampled accelerometer-bias estimate `b̂`, m/s² (NaN in
    /// position-only mode).
    pub bias_mps2: f64,
    /// Modelled force (eq. 9), N.
    pub force_model_n: f64,
    /// Modelled oil temperature, °C.
    pub oil_temp_c: f64,
    /// Modelled cylinder temperature, °C.
    pub cyl_temp_c: f64,
    /// Heat input at the tick, W.
    pub heat_rate_w: f64,
    /// RMS of the tick velocities over the last 1 s (50 ticks, NaN ticks
    /// skipped), m/s: the excitation measure.
    pub velocity_rms_1s_mps: f64,
    /// Whether the position-only filter runs (no accelerometers).
    pub position_only: bool,
    /// Gap counters so far.
    pub gaps: GapCounters,
    /// Non-finite samples skipped so far.
    pub missing_samples: u64,
}

/// One 50 Hz row.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TickRow {
    /// Tick time `t_k`, ns.
    pub t_ns: i64,
    /// All feature columns, in [`COLUMNS`] order (NaN where not available).
    pub values: [f64; N_COLUMNS],
    /// The twin's internal state.
    pub twin: TwinState,
    /// `/truth/gas_pressure` `static_bar` held at the tick (NaN without).
    pub truth_static_bar: f64,
}

/// Boxcar (first-order CIC) mean with hold-on-empty; it also keeps the
/// sum of squares of the samples given by [`Boxcar::add`] (the within-tick
/// variance of the raw `a_rel`).
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct Boxcar {
    sum: f64,
    sum_sq: f64,
    n: f64,
    last: f64,
    gaps: u64,
}

impl Boxcar {
    const fn new() -> Self {
        Self {
            sum: 0.0,
            sum_sq: 0.0,
            n: 0.0,
            last: f64::NAN,
            gaps: 0,
        }
    }

    fn add(&mut self, x: f64) {
        self.sum += x;
        self.sum_sq += x * x;
        self.n += 1.0;
    }

    /// Population variance `max(E[x²] − E[x]², 0)` of the samples of the
    /// current interval (before [`take`](Self::take)); NaN when empty.
    fn variance(&self) -> f64 {
        if self.n > 0.0 {
            let mean = self.sum / self.n;
            (self.sum_sq / self.n - mean * mean).max(0.0)
        } else {
            f64::NAN
        }
    }

    fn add_sum(&mut self, sum: f64, n: f64) {
        self.sum += sum;
        self.n += n;
    }

    /// The mean of the interval, or the held value (a gap) when empty.
    fn take(&mut self) -> f64 {
        if self.n > 0.0 {
            self.last = self.sum / self.n;
            self.sum = 0.0;
            self.sum_sq = 0.0;
            self.n = 0.0;
        } else if !self.last.is_nan() {
            self.gaps += 1;
        }
        self.last
    }
}

/// The last `N` per-tick values in a ring (no allocation); the statistics
/// skip NaN entries (and the slots not yet written, which are NaN).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct TickWindow<const N: usize> {
    #[serde(with = "serde_big_array::BigArray")]
    values: [f64; N],
    next: usize,
}

impl<const N: usize> TickWindow<N> {
    const fn new() -> Self {
        Self {
            values: [f64::NAN; N],
            next: 0,
        }
    }

    /// Stores `x` and returns the value it replaces: the one pushed `N`
    /// ticks before (NaN in the first `N` ticks).
    fn push(&mut self, x: f64) -> f64 {
        let old = std::mem::replace(&mut self.values[self.next], x);
        self.next = (self.next + 1) % N;
        old
    }

    /// `(mean, RMS about the mean)` from the [`non_nan_sums`] of the values
    /// (the second pass); NaN when there is none.
    fn rms_about(&self, sum: f64, n: f64) -> (f64, f64) {
        if n == 0.0 {
            return (f64::NAN, f64::NAN);
        }
        let mean = sum / n;
        let ss = self
            .values
            .iter()
            .filter(|x| !x.is_nan())
            .map(|x| (x - mean) * (x - mean))
            .sum::<f64>();
        (mean, (ss / n).sqrt())
    }
}

/// `(sum, count)` of the non-NaN values of each of `K` windows of `N`
/// values, each summed in index order: the same sums as `K` separate loops,
/// taken in one loop so that the `K` chains of additions run side by side.
fn non_nan_sums<const N: usize, const K: usize>(windows: [&[f64; N]; K]) -> [(f64, f64); K] {
    let mut acc = [(0.0, 0.0); K];
    for i in 0..N {
        for ((sum, n), w) in acc.iter_mut().zip(&windows) {
            let x = w[i];
            if !x.is_nan() {
                *sum += x;
                *n += 1.0;
            }
        }
    }
    acc
}

/// Mean of `sum` over `n` values; NaN when `n` is 0.
fn mean_of(sum: f64, n: f64) -> f64 {
    if n == 0.0 {
        f64::NAN
    } else {
        sum / n
    }
}

/// The longest gap across which [`FeaturePipeline::carry_over`] carries the
/// thermal state (6 h), s: past it the thermal model starts again from the
/// thermocouple, as a fresh run's does.
pub const CARRY_THERMAL_MAX_S: f64 = 6.0 * 3600.0;

/// The incremental 50 Hz feature pipeline (see the module docs for the
/// algorithm). Feed samples in time order with [`push`](Self::push), take
/// rows with [`pop`](Self::pop) / [`drain`](Self::drain), call
/// [`finish`](Self::finish) at the end of the stream.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FeaturePipeline {
    available: TopicSet,
    force_model: ForceModel,
    thermal_model: ThermalModel,
    kf: KalmanFilter,
    position_only: bool,
    column_mask: [bool; N_COLUMNS],

    origin_ns: Option<i64>,
    next_tick_ns: i64,
    last_t_ns: i64,
    sample_since_tick: bool,

    bx_force: Boxcar,
    bx_pos: Boxcar,
    bx_acc: Boxcar,
    bx_kf_y: Boxcar,
    bx_kf_v: Boxcar,
    bx_kf_a: Boxcar,

    pending_t_ns: Option<i64>,
    pending_n: f64,
    pending_a_sum: f64,
    pending_a2: f64,
    bias_mps2: f64,
    observer: Option<ChargeObserver>,

    temp_shock_c: f64,
    temp_ambient_c: f64,
    first_shock_c: f64,
    truth_bar: f64,

    thermal: Option<ThermalState>,
    prev_power_w: f64,
    prev_ambient_c: f64,
    /// The shock thermocouple as modelled (`tc_gain`, `tc_lag_s`): its
    /// offset against the ambient when the thermal model started and its
    /// lagged reading, °C. `None` before the model starts (and in a
    /// checkpoint written before it existed: restarted then).
    #[serde(default)]
    tc_model: Option<(f64, f64)>,

    #[serde(with = "serde_big_array::BigArray")]
    v_sq: [f64; EXCITATION_WINDOW_TICKS],
    v_idx: usize,
    missing_samples: u64,

    acc_var: TickWindow<EXCITATION_WINDOW_TICKS>,
    force_resid: TickWindow<EXCITATION_WINDOW_TICKS>,
    temp_resid: TickWindow<TEMP_RATE_WINDOW_TICKS>,

    out: VecDeque<TickRow>,
}

impl FeaturePipeline {
    /// A pipeline for a run whose log has the topics in `available`. The
    /// Kalman filter runs the SPEC §3.1 model when `/acceleration` is
    /// available, the position-only model otherwise.
    pub fn new(params: &PhysicsParams, available: TopicSet) -> Result<Self, PhysicsError> {
        params.validate()?;
        let position_only = !available.acceleration;
        let kf = if position_only {
            KalmanFilter::position_only(params.kalman, POSITION_ONLY_JERK_PSD)
        } else {
            KalmanFilter::new(params.kalman)
        };
        let mut column_mask = [false; N_COLUMNS];
        for g in Group::ALL {
            if available.missing_for(&[g]).is_empty() {
                for i in g.column_range() {
                    column_mask[i] = true;
                }
            }
        }
        let observer = match params.observer {
            Some(o) if column_mask[col::OBSERVER_BAR] && !position_only => {
                Some(ChargeObserver::new(o)?)
            }
            _ => None,
        };
        if observer.is_none() {
            column_mask[col::OBSERVER_BAR] = false;
            column_mask[col::OBSERVER_SD_BAR] = false;
        }
        Ok(Self {
            available,
            force_model: ForceModel::new(params.force),
            thermal_model: ThermalModel::new(params.thermal),
            kf,
            position_only,
            column_mask,
            origin_ns: None,
            next_tick_ns: 0,
            last_t_ns: i64::MIN,
            sample_since_tick: false,
            bx_force: Boxcar::new(),
            bx_pos: Boxcar::new(),
            bx_acc: Boxcar::new(),
            bx_kf_y: Boxcar::new(),
            bx_kf_v: Boxcar::new(),
            bx_kf_a: Boxcar::new(),
            pending_t_ns: None,
            pending_n: 0.0,
            pending_a_sum: 0.0,
            pending_a2: f64::NAN,
            bias_mps2: f64::NAN,
            observer,
            temp_shock_c: f64::NAN,
            temp_ambient_c: f64::NAN,
            first_shock_c: f64::NAN,
            truth_bar: f64::NAN,
            thermal: None,
            tc_model: None,
            prev_power_w: 0.0,
            prev_ambient_c: f64::NAN,
            v_sq: [f64::NAN; EXCITATION_WINDOW_TICKS],
            v_idx: 0,
            missing_samples: 0,
            acc_var: TickWindow::new(),
            force_resid: TickWindow::new(),
            temp_resid: TickWindow::new(),
            out: VecDeque::with_capacity(64),
        })
    }

    /// Takes over the slow state of `prev`, the pipeline of the segment
    /// before a forward clock jump of `gap_s` seconds (a logger's dropout, a
    /// lost link), into this fresh one. The Kalman filter, the boxcars and
    /// the windows start afresh, as they must after a gap; but the damper's
    /// heat and its charge do not restart with the data:
    /// - the thermal state is carried through the gap by the thermal model
    ///   with no damping power (the damper cools towards the last ambient),
    ///   in RK4 steps of at most [`crate::thermal::MAX_STEP_S`]; past
    ///   [`CARRY_THERMAL_MAX_S`] it starts again from the thermocouple, as
    ///   a fresh run's does (after hours it is at the ambient anyway);
    /// - the modelled thermocouple keeps its offset and follows its lag
    ///   through the gap;
    /// - the charge observer keeps its state ([`ChargeObserver::resume_after_gap`]),
    ///   whatever the gap;
    /// - the last temperatures are held until new ones come (with the thermal
    ///   state only).
    ///
    /// Restarted from the shock thermocouple instead, a 2 s dropout left the
    /// modelled oil 3–4 °C low for the rest of a run and the estimate 1.3 bar
    /// off (a helper's trial on an imported dyno run).
    pub fn carry_over(&mut self, prev: FeaturePipeline, gap_s: f64) {
        if self.observer.is_some() {
            if let Some(mut obs) = prev.observer {
                obs.resume_after_gap();
                self.observer = Some(obs);
            }
        }
        let Some(mut state) = prev.thermal else {
            return;
        };
        let carried = gap_s.is_finite()
            && gap_s > 0.0
            && gap_s <= CARRY_THERMAL_MAX_S
            && prev.prev_ambient_c.is_finite();
        if !carried {
            return; // the thermal model starts from the new segment's thermocouple
        }
        // the shock's first reading stands for the ambient without an
        // ambient thermocouple, and the thermocouple model's offset is taken
        // from it: both the carried state's; the last readings are held
        self.first_shock_c = prev.first_shock_c;
        self.temp_shock_c = prev.temp_shock_c;
        self.temp_ambient_c = prev.temp_ambient_c;
        self.prev_ambient_c = prev.prev_ambient_c;
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)] // ≤ 10,800
        let steps = (gap_s / crate::thermal::MAX_STEP_S).ceil().max(1.0) as u32;
        let h = gap_s / f64::from(steps);
        for _ in 0..steps {
            state = self.thermal_model.step(state, h, 0.0, prev.prev_ambient_c);
        }
        self.thermal = Some(state);
        let p = *self.thermal_model.params();
        if let Some((offset_c, last_c)) = prev.tc_model {
            let ambient_c = prev.prev_ambient_c;
            let target_c =
                ambient_c + p.tc_gain * (state.cyl_c - ambient_c) + (1.0 - p.tc_gain) * offset_c;
            let reading_c = if last_c.is_nan() || p.tc_lag_s == 0.0 {
                target_c
            } else {
                last_c + (1.0 - (-gap_s / p.tc_lag_s).exp()) * (target_c - last_c)
            };
            self.tc_model = Some((offset_c, reading_c));
        }
    }

    /// The gas-charge observer, when the parameters configure one and the
    /// suite feeds it.
    #[must_use]
    pub fn observer(&self) -> Option<&ChargeObserver> {
        self.observer.as_ref()
    }

    /// Keeps the observer's fitted reversals (see [`ChargeObserver::reversals`]).
    pub fn record_reversals(&mut self) {
        if let Some(obs) = self.observer.as_mut() {
            obs.record_reversals();
        }
    }

    /// Whether the position-only Kalman filter runs.
    #[must_use]
    pub fn is_position_only(&self) -> bool {
        self.position_only
    }

    /// Time of the first sample (the tick origin), once one has arrived.
    #[must_use]
    pub fn origin_ns(&self) -> Option<i64> {
        self.origin_ns
    }

    /// Time of the next tick to be emitted, once a sample has arrived.
    #[must_use]
    pub fn next_tick_ns(&self) -> Option<i64> {
        self.origin_ns.map(|_| self.next_tick_ns)
    }

    /// Takes one sample (time order; see the module docs). Completes every
    /// tick before the sample's time.
    pub fn push(&mut self, sample: &Sample) -> Result<(), PhysicsError> {
        // Simulator-truth velocity is for analysis only: it neither drives
        // the clock nor feeds anything (features are the same without it).
        if let Sample::TruthVelocity { .. } = sample {
            return Ok(());
        }
        let t = sample.t_ns();
        if self.origin_ns.is_none() {
            self.origin_ns = Some(t);
            self.next_tick_ns = t + TICK_NS;
            self.last_t_ns = t;
        }
        if t < self.last_t_ns {
            return Err(PhysicsError::OutOfOrder {
                what: format!("feature pipeline sample on {}", sample.topic()),
                t_ns: t,
                last_t_ns: self.last_t_ns,
            });
        }
        if self.pending_t_ns.is_some_and(|p| t > p) {
            self.commit_kalman_sample();
        }
        while t > self.next_tick_ns {
            self.complete_tick();
        }
        self.last_t_ns = t;
        // A topic outside the pipeline's set drives the clock but not the
        // twin: a model uses only the sensors of its suite.
        let topic_name = sample.topic();
        if topic_name != topic::TRUTH_PRESSURE && !self.available.contains(topic_name) {
            return Ok(());
        }
        // A sample at the origin belongs to (t_-1, t_0], whose tick is not
        // emitted: it feeds the filter and the held values, not a boxcar.
        let in_tick = t > self.next_tick_ns - TICK_NS;
        self.sample_since_tick |= in_tick;

        match *sample {
            Sample::Acceleration {
                a1_mps2, a2_mps2, ..
            } => {
                let a = a1_mps2 - a2_mps2;
                if a.is_finite() {
                    if in_tick {
                        self.bx_acc.add(a);
                    }
                    if !self.position_only {
                        self.kf.accel(t, a)?;
                        self.pending_t_ns = Some(t);
                        self.pending_n += 1.0;
                        self.pending_a_sum += a;
                        self.pending_a2 = a2_mps2;
                    }
                } else {
                    self.missing_samples += 1;
                }
            }
            Sample::Position { position_m, .. } => {
                if position_m.is_finite() {
                    if in_tick {
                        self.bx_pos.add(position_m);
                    }
                    self.kf.position(t, position_m)?;
                    if let Some(obs) = self.observer.as_mut() {
                        obs.position(t, position_m);
                    }
                    if self.position_only {
                        self.pending_t_ns = Some(t);
                        self.pending_n += 1.0;
                    }
                } else {
                    self.missing_samples += 1;
                }
            }
            Sample::Force { force_n, .. } => {
                if force_n.is_finite() {
                    if in_tick {
                        self.bx_force.add(force_n);
                    }
                } else {
                    self.missing_samples += 1;
                }
            }
            Sample::TempShock { temperature_c, .. } => {
                if temperature_c.is_finite() {
                    self.temp_shock_c = temperature_c;
                    if self.first_shock_c.is_nan() {
                        self.first_shock_c = temperature_c;
                    }
                } else {
                    self.missing_samples += 1;
                }
            }
            Sample::TempAmbient { temperature_c, .. } => {
                if temperature_c.is_finite() {
                    self.temp_ambient_c = temperature_c;
                } else {
                    self.missing_samples += 1;
                }
            }
            Sample::TruthPressure { static_bar, .. } => self.truth_bar = static_bar,
            Sample::TruthVelocity { .. } => {} // returned above
        }
        Ok(())
    }

    /// End of stream: emits the last tick if any sample fell into it.
    pub fn finish(&mut self) {
        if self.pending_t_ns.is_some() {
            self.commit_kalman_sample();
        }
        if self.sample_since_tick {
            self.complete_tick();
        }
    }

    /// The oldest emitted row not yet taken.
    pub fn pop(&mut self) -> Option<TickRow> {
        self.out.pop_front()
    }

    /// All emitted rows not yet taken.
    pub fn drain(&mut self) -> impl Iterator<Item = TickRow> + '_ {
        self.out.drain(..)
    }

    /// Number of emitted rows not yet taken.
    #[must_use]
    pub fn rows_ready(&self) -> usize {
        self.out.len()
    }

    /// Adds the filter state after every event at the pending sample time to
    /// the Kalman boxcars (once per sample at that time).
    fn commit_kalman_sample(&mut self) {
        let in_tick = self
            .pending_t_ns
            .is_some_and(|t| t > self.next_tick_ns - TICK_NS);
        if let (Some(obs), Some(t), Some(x)) =
            (self.observer.as_mut(), self.pending_t_ns, self.kf.state())
        {
            let arel = self.pending_a_sum / self.pending_n - x[2];
            obs.sample(t, self.pending_a2, x[0], x[1], arel);
        }
        if let Some(x) = self.kf.state().filter(|_| in_tick) {
            let n = self.pending_n;
            self.bx_kf_y.add_sum(x[0] * n, n);
            self.bx_kf_v.add_sum(x[1] * n, n);
            if self.position_only {
                self.bx_kf_a.add_sum(x[2] * n, n);
            } else {
                self.bx_kf_a.add_sum(self.pending_a_sum - x[2] * n, n);
                self.bias_mps2 = x[2];
            }
        }
        self.pending_t_ns = None;
        self.pending_n = 0.0;
        self.pending_a_sum = 0.0;
        self.pending_a2 = f64::NAN;
    }

    /// What the shock thermocouple should read with the cylinder at `cyl_c`
    /// (°C): `T_amb + κ (T_cyl − T_amb) + (1 − κ) (T_shock,0 − T_amb,0)`
    /// through a first-order lag of `tc_lag_s`, with `T_amb` the ambient
    /// thermocouple (the first shock reading without one). With the SPEC's
    /// κ = 1 and no lag it is `cyl_c` exactly.
    // The exact defaults mean "the SPEC's thermocouple": the cylinder itself.
    #[allow(clippy::float_cmp)]
    fn thermocouple_model_c(&mut self, cyl_c: f64) -> f64 {
        let p = *self.thermal_model.params();
        if (p.tc_gain == 1.0 && p.tc_lag_s == 0.0) || cyl_c.is_nan() {
            return cyl_c;
        }
        let ambient_c = if self.temp_ambient_c.is_nan() {
            self.first_shock_c
        } else {
            self.temp_ambient_c
        };
        let (offset_c, last_c) = *self
            .tc_model
            .get_or_insert((self.first_shock_c - ambient_c, f64::NAN));
        let target_c = ambient_c + p.tc_gain * (cyl_c - ambient_c) + (1.0 - p.tc_gain) * offset_c;
        let reading_c = if last_c.is_nan() || p.tc_lag_s == 0.0 {
            target_c
        } else {
            last_c + (1.0 - (-TICK_S / p.tc_lag_s).exp()) * (target_c - last_c)
        };
        self.tc_model = Some((offset_c, reading_c));
        reading_c
    }

    /// Pushes the tick velocity `v`, the tick's within-tick `a_rel`
    /// variance, temperature residual and force residual into the causal
    /// windows (this tick and the ones before it only) of the excitation
    /// measure and of the `signature` and `residual` groups; returns
    /// `[velocity_rms_1s_mps, accel_hf_rms_mps2, temp_resid_c,
    /// temp_resid_rate_cps, force_resid_mean_n, force_resid_rms_n]`.
    ///
    /// The velocity RMS is that of the last second's tick velocities (NaN
    /// ticks left out; NaN when all are).
    fn window_columns(
        &mut self,
        v: f64,
        acc_var: f64,
        temp_resid_c: f64,
        force_resid_n: f64,
    ) -> [f64; 6] {
        self.v_sq[self.v_idx] = v * v;
        self.v_idx = (self.v_idx + 1) % EXCITATION_WINDOW_TICKS;
        self.acc_var.push(acc_var);
        self.force_resid.push(force_resid_n);
        let [(v_sum, v_n), (acc_sum, acc_n), (force_sum, force_n)] =
            non_nan_sums([&self.v_sq, &self.acc_var.values, &self.force_resid.values]);
        let velocity_rms = mean_of(v_sum, v_n).sqrt();
        let accel_hf_rms = mean_of(acc_sum, acc_n).sqrt();
        let (mean, rms) = self.force_resid.rms_about(force_sum, force_n);
        let temp_resid_10s_ago = self.temp_resid.push(temp_resid_c);
        #[allow(clippy::cast_precision_loss)] // 500
        let temp_resid_rate =
            (temp_resid_c - temp_resid_10s_ago) / (TEMP_RATE_WINDOW_TICKS as f64 * TICK_S);
        [
            velocity_rms,
            accel_hf_rms,
            temp_resid_c,
            temp_resid_rate,
            mean,
            rms,
        ]
    }

    fn complete_tick(&mut self) {
        let t_k = self.next_tick_ns;
        self.next_tick_ns += TICK_NS;
        self.sample_since_tick = false;

        let force_n = self.bx_force.take();
        let pos_m = self.bx_pos.take();
        let acc_var = self.bx_acc.variance();
        let acc = self.bx_acc.take();
        let y = self.bx_kf_y.take();
        let v = self.bx_kf_v.take();
        let a_corr = self.bx_kf_a.take();

        // Thermal model: one RK4 step from t_{k-1} with tick k-1's inputs.
        self.thermal = match self.thermal {
            Some(s) => {
                Some(
                    self.thermal_model
                        .step(s, TICK_S, self.prev_power_w, self.prev_ambient_c),
                )
            }
            None if !self.first_shock_c.is_nan() => Some(ThermalState {
                oil_c: self.first_shock_c,
                cyl_c: self.first_shock_c,
            }),
            None => None,
        };
        let (oil_c, cyl_c) = self
            .thermal
            .map_or((f64::NAN, f64::NAN), |s| (s.oil_c, s.cyl_c));
        let charge = self.observer.as_mut().map(|obs| {
            obs.set_gas_temp_c(oil_c);
            obs.estimate(t_k)
        });

        let fb = self.force_model.force(v, a_corr, y, oil_c);
        let power_w = self.force_model.dissipative_power_w(v, oil_c);
        self.prev_power_w = if power_w.is_finite() { power_w } else { 0.0 };
        self.prev_ambient_c = if self.temp_ambient_c.is_nan() {
            self.first_shock_c
        } else {
            self.temp_ambient_c
        };

        let tc_model_c = self.thermocouple_model_c(cyl_c);
        let [velocity_rms_1s_mps, accel_hf_rms, temp_resid_c, temp_resid_rate, force_resid_mean, force_resid_rms] =
            self.window_columns(
                v,
                acc_var,
                self.temp_shock_c - tc_model_c,
                force_n - fb.total_n,
            );

        let mut values = [
            force_n,
            pos_m,
            acc,
            v,
            fb.total_n,
            fb.damping_n(),
            fb.gas_n,
            self.temp_shock_c,
            self.temp_ambient_c,
            oil_c,
            cyl_c,
            power_w,
            accel_hf_rms,
            velocity_rms_1s_mps,
            temp_resid_c,
            temp_resid_rate,
            force_resid_mean,
            force_resid_rms,
            charge.map_or(f64::NAN, |c| c.mean_bar),
            charge.map_or(f64::NAN, |c| c.sd_bar),
        ];
        for (value, keep) in values.iter_mut().zip(self.column_mask) {
            if !keep {
                *value = f64::NAN;
            }
        }
        let twin = TwinState {
            position_m: y,
            velocity_mps: v,
            accel_mps2: a_corr,
            bias_mps2: self.bias_mps2,
            force_model_n: fb.total_n,
            oil_temp_c: oil_c,
            cyl_temp_c: cyl_c,
            heat_rate_w: power_w,
            velocity_rms_1s_mps,
            position_only: self.position_only,
            gaps: GapCounters {
                force: self.bx_force.gaps,
                position: self.bx_pos.gaps,
                acceleration: self.bx_acc.gaps,
                kalman: self.bx_kf_v.gaps,
            },
            missing_samples: self.missing_samples,
        };
        self.out.push_back(TickRow {
            t_ns: t_k,
            values,
            twin,
            truth_static_bar: self.truth_bar,
        });
    }
}

/// Feature rows of one run (row-major), with the twin's state per tick.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FeatureTable {
    /// `run_id` of the log.
    pub run_id: String,
    /// Time of the run's first sample, ns (`t_s = (t_ns − t_origin_ns)/1e9`).
    pub t_origin_ns: i64,
    /// Tick times, ns.
    pub t_ns: Vec<i64>,
    /// Column names, in the order of the values of each row.
    pub columns: Vec<String>,
    /// `t_ns.len() × columns.len()` values, row-major.
    pub values: Vec<f64>,
    /// The twin's state at each tick.
    pub twin: Vec<TwinState>,
    /// `/truth/gas_pressure` held at each tick (label for analysis; NaN without).
    pub truth_static_bar: Vec<f64>,
}

impl FeatureTable {
    /// Number of rows (ticks).
    #[must_use]
    pub fn n_rows(&self) -> usize {
        self.t_ns.len()
    }

    /// Row `i`'s values.
    #[must_use]
    pub fn row(&self, i: usize) -> &[f64] {
        let k = self.columns.len();
        &self.values[i * k..(i + 1) * k]
    }

    /// The column named `name`, if present.
    #[must_use]
    pub fn column(&self, name: &str) -> Option<Vec<f64>> {
        let j = self.columns.iter().position(|c| c == name)?;
        let k = self.columns.len();
        Some((0..self.n_rows()).map(|i| self.values[i * k + j]).collect())
    }
}

/// All samples of `log` in processing order: stable sort by
/// `(t_ns, topic rank)` (ARCHITECTURE.md "Event order"); the same as
/// [`RunLog::samples_sorted`], which it calls.
#[must_use]
pub fn sorted_samples(log: &RunLog) -> Vec<Sample> {
    log.samples_sorted()
}

/// What the charge observer made of a whole run ([`compute_reversals`]).
#[derive(Debug, Clone)]
pub struct RunReversals {
    /// The fitted reversals, in order.
    pub reversals: Vec<Reversal>,
    /// What the observer did.
    pub counters: ObserverCounters,
    /// Its accelerometer scale at the end ([`ChargeObserver::rod_accel_scale`]).
    pub rod_accel_scale: Option<f64>,
    /// The split of the stroke's ends at the end ([`ChargeObserver::ends_split_bar`]).
    pub ends_split_bar: Option<f64>,
}

/// The gas-charge observer's fitted reversals over a whole run (for
/// calibration and analysis): the [`FeaturePipeline`] on the observer
/// group's topics, with `params.observer` or its defaults, and what the
/// observer holds at the end ([`RunReversals`]).
/// An error names the run and the topics it lacks.
///
/// # Panics
/// Never: the observer group's pipeline always has an observer.
pub fn compute_reversals(
    log: &RunLog,
    params: &PhysicsParams,
) -> Result<RunReversals, PhysicsError> {
    let groups = [Group::Observer];
    let available = TopicSet::from_log(log);
    let missing = available.missing_for(&groups);
    if !missing.is_empty() {
        return Err(PhysicsError::MissingTopics {
            run_id: log.metadata.run_id.clone(),
            missing: missing.into_iter().map(str::to_owned).collect(),
            groups: vec![Group::Observer.name().to_owned()],
        });
    }
    let mut params = *params;
    params.observer.get_or_insert_with(ObserverParams::default);
    let mut pipe =
        FeaturePipeline::new(&params, available.intersect(TopicSet::for_groups(&groups)))?;
    pipe.record_reversals();
    for (k, s) in sorted_samples(log).iter().enumerate() {
        if crate::cancel::requested_at(k) {
            break; // nobody waits for it any more (`cancel`)
        }
        pipe.push(s)?;
        pipe.drain().for_each(drop);
    }
    pipe.finish();
    let obs = pipe
        .observer()
        .expect("the observer group makes an observer");
    Ok(RunReversals {
        reversals: obs.reversals().to_vec(),
        counters: obs.counters(),
        rod_accel_scale: obs.rod_accel_scale(),
        ends_split_bar: obs.ends_split_bar(),
    })
}

/// Batch features of one run: checks that the log has every topic `groups`
/// need (an error names the run and the missing topics), then runs the
/// [`FeaturePipeline`] over the log's samples in order and keeps the columns
/// of `groups` (in [`column_indices`] order). The pipeline is given only the
/// topics of the groups' suite ([`TopicSet::for_groups`]): a model uses only
/// its own sensors (e.g. `mechanical` without `thermal` holds the first shock
/// temperature as ambient even when the log has an ambient thermocouple), and
/// the streaming estimator, which knows only its bundle's groups, computes the
/// same features.
pub fn compute_features(
    log: &RunLog,
    params: &PhysicsParams,
    groups: &[Group],
) -> Result<FeatureTable, PhysicsError> {
    let available = TopicSet::from_log(log);
    let missing = available.missing_for(groups);
    if !missing.is_empty() {
        return Err(PhysicsError::MissingTopics {
            run_id: log.metadata.run_id.clone(),
            missing: missing.into_iter().map(str::to_owned).collect(),
            groups: groups.iter().map(|g| g.name().to_owned()).collect(),
        });
    }
    let suite = available.intersect(TopicSet::for_groups(groups));
    // The observer is costly: it runs only when its group is asked for; without
    // `params.observer` it runs with the defaults, whose uncalibrated
    // measurement model keeps the prior (a wide interval, never a confident number).
    let mut params = *params;
    if groups.contains(&Group::Observer) {
        params.observer.get_or_insert_with(ObserverParams::default);
    } else {
        params.observer = None;
    }
    run_pipeline(log, &params, suite, &column_indices(groups))
}

/// The twin's state at every tick of a run, from every sensor topic the log
/// has — the twin's *reduced models* when sensors are missing: the
/// position-only Kalman filter without `/acceleration` (step 3), the first
/// shock temperature as ambient without `/temperature/ambient` (step 6).
/// Unlike [`compute_features`] it asks for no group and never fails for a
/// missing topic: the table has every column of [`COLUMNS`] but the
/// observer's, NaN where the log lacks what the column's group needs (as in
/// the streaming pipeline), and [`FeatureTable::twin`] holds the Kalman
/// estimates and the modelled force and temperatures, which need only
/// `/position` (and `/temperature/shock` for the thermal model). For
/// calibrating the physics on a campaign without the full suite
/// (`train.fit_physics`).
pub fn compute_twin(log: &RunLog, params: &PhysicsParams) -> Result<FeatureTable, PhysicsError> {
    let mut params = *params;
    params.observer = None;
    let idx: Vec<usize> = (0..col::OBSERVER_BAR).collect();
    run_pipeline(log, &params, TopicSet::from_log(log), &idx)
}

/// Runs a [`FeaturePipeline`] given `suite` over the log's samples in order,
/// keeping the columns `idx` of each row.
fn run_pipeline(
    log: &RunLog,
    params: &PhysicsParams,
    suite: TopicSet,
    idx: &[usize],
) -> Result<FeatureTable, PhysicsError> {
    let mut pipe = FeaturePipeline::new(params, suite)?;
    let samples = sorted_samples(log);
    let n_ticks = samples.last().map_or(0, |last| {
        ((last.t_ns() - samples[0].t_ns()) / TICK_NS + 1) as usize
    });
    let mut table = FeatureTable {
        run_id: log.metadata.run_id.clone(),
        t_origin_ns: 0, // the pipeline's origin, set at the end
        columns: idx.iter().map(|&i| COLUMNS[i].to_owned()).collect(),
        t_ns: Vec::with_capacity(n_ticks),
        values: Vec::with_capacity(n_ticks * idx.len()),
        twin: Vec::with_capacity(n_ticks),
        truth_static_bar: Vec::with_capacity(n_ticks),
    };
    let mut take = |pipe: &mut FeaturePipeline| {
        for row in pipe.drain() {
            table.t_ns.push(row.t_ns);
            table.values.extend(idx.iter().map(|&i| row.values[i]));
            table.twin.push(row.twin);
            table.truth_static_bar.push(row.truth_static_bar);
        }
    };
    for (k, s) in samples.iter().enumerate() {
        if crate::cancel::requested_at(k) {
            break; // nobody waits for it any more (`cancel`)
        }
        pipe.push(s)?;
        take(&mut pipe);
    }
    pipe.finish();
    take(&mut pipe);
    // The pipeline's origin: its first sample (simulator-truth velocity is
    // not one), 0 for an empty log.
    table.t_origin_ns = pipe.origin_ns().unwrap_or(0);
    Ok(table)
}

#[cfg(test)]
// Exact float equality is intended in these tests: same arithmetic, same result.
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;
    use crate::kalman::run_kalman;
    use crate::log::RunMetadata;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    const T0: i64 = 1_700_000_000_000_000_000;
    const MS: i64 = 1_000_000;
    const AMP_M: f64 = 0.04;
    const FREQ_HZ: f64 = 2.0;

    fn omega() -> f64 {
        2.0 * PI * FREQ_HZ
    }

    /// Deterministic noise in [-1, 1].
    fn noise(i: i64) -> f64 {
        let x = (i as u64)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .rotate_left(17);
        (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    /// A 2 Hz, 80 mm p-p sine at SPEC rates, with the given topics.
    fn synth_log(seconds: i64, topics: TopicSet) -> RunLog {
        let w = omega();
        let mut log = RunLog {
            metadata: RunMetadata {
                asset_id: "unit-1".into(),
                run_id: "run-7".into(),
                ..RunMetadata::default()
            },
            ..RunLog::default()
        };
        let secs = |t_ns: i64| (t_ns - T0) as f64 / 1e9;
        if topics.acceleration {
            for i in 0..seconds * 1000 {
                let t = T0 + i * MS;
                let a = -AMP_M * w * w * (w * secs(t)).sin();
                log.acceleration
                    .push((t, a + 0.3 + 0.05 * noise(i), 0.05 * noise(i + 7)));
            }
        }
        if topics.position {
            for i in 0..seconds * 100 {
                let t = T0 + i * 10 * MS;
                log.position
                    .push((t, AMP_M * (w * secs(t)).sin() + 5e-4 * noise(3 * i)));
            }
        }
        if topics.force {
            for i in 0..seconds * 50 {
                let t = T0 + 3 * MS + i * 20 * MS;
                log.force.push((t, 3000.0 * (w * secs(t)).cos() - 380.0));
            }
        }
        for i in 0..seconds {
            let t = T0 + 250 * MS + i * 1000 * MS;
            if topics.temp_shock {
                log.temp_shock.push((t, 25.0 + 0.05 * i as f64));
            }
            if topics.temp_ambient {
                log.temp_ambient.push((t, 21.5));
            }
            log.truth_pressure.push((t, 12.0 + 0.01 * i as f64));
        }
        log
    }

    fn run_rows(samples: &[Sample], available: TopicSet, finish: bool) -> Vec<TickRow> {
        let mut pipe = FeaturePipeline::new(&PhysicsParams::default(), available).unwrap();
        let mut rows = Vec::new();
        for s in samples {
            pipe.push(s).unwrap();
            rows.extend(pipe.drain());
        }
        if finish {
            pipe.finish();
            rows.extend(pipe.drain());
        }
        rows
    }

    fn same(a: f64, b: f64) -> bool {
        a == b || (a.is_nan() && b.is_nan())
    }

    #[test]
    fn ticks_are_on_the_20_ms_grid() {
        let log = synth_log(3, TopicSet::all());
        let table = compute_features(&log, &PhysicsParams::default(), &Group::ALL).unwrap();
        // The first message (t = T0) is the origin; ticks at T0 + k·20 ms, k ≥ 1,
        // the last one holding the last sample (T0 + 2999 ms).
        assert_eq!(table.t_origin_ns, T0);
        assert_eq!(table.n_rows(), 150);
        for (k, &t) in table.t_ns.iter().enumerate() {
            assert_eq!(t, T0 + (k as i64 + 1) * TICK_NS);
        }
        assert_eq!(table.columns, COLUMNS.to_vec());
        assert_eq!(table.values.len(), 150 * N_COLUMNS);
    }

    #[test]
    fn boxcar_of_a_constant_is_the_constant() {
        let mut log = synth_log(2, TopicSet::all());
        for s in &mut log.position {
            s.1 = 0.0125;
        }
        for s in &mut log.acceleration {
            s.1 = 1.75;
            s.2 = -0.5;
        }
        for s in &mut log.force {
            s.1 = -420.0;
        }
        let table = compute_features(
            &log,
            &PhysicsParams::default(),
            &[Group::Force, Group::Position, Group::Acceleration],
        )
        .unwrap();
        for i in 0..table.n_rows() {
            let r = table.row(i);
            assert!(
                (r[0] + 420.0).abs() < 1e-12
                    && (r[1] - 0.0125).abs() < 1e-15
                    && (r[2] - 2.25).abs() < 1e-13,
                "row {i}: {r:?}"
            );
        }
    }

    #[test]
    fn boxcar_averages_each_interval_and_holds_gaps() {
        let mut log = synth_log(2, TopicSet::all());
        // Drop the loadcell between 400 and 500 ms: ticks 20..=24 hold.
        log.force
            .retain(|&(t, _)| !(T0 + 400 * MS..T0 + 500 * MS).contains(&t));
        let table = compute_features(&log, &PhysicsParams::default(), &Group::ALL).unwrap();
        let force = table.column("force_n").unwrap();
        let pos = table.column("position_m").unwrap();
        for (k, &t_k) in table.t_ns.iter().enumerate() {
            let in_interval = |t: i64| t > t_k - TICK_NS && t <= t_k;
            let p: Vec<f64> = log
                .position
                .iter()
                .filter(|s| in_interval(s.0))
                .map(|s| s.1)
                .collect();
            let mean = p.iter().sum::<f64>() / p.len() as f64;
            assert!((pos[k] - mean).abs() < 1e-15, "tick {k}");
        }
        // Force samples at T0 + 3 ms + i·20 ms: the one for tick 19 is at 383 ms.
        assert_eq!(force[19], log.force[19].1);
        for k in 20..25 {
            assert_eq!(force[k], force[19], "tick {k} holds");
        }
        assert_eq!(table.twin[24].gaps.force, 5);
        assert_eq!(table.twin[24].gaps.position, 0);
        assert_ne!(force[25], force[19]);
    }

    #[test]
    fn kalman_columns_are_boxcars_of_run_kalman() {
        let log = synth_log(3, TopicSet::all());
        let params = PhysicsParams::default();
        let table = compute_features(&log, &params, &Group::ALL).unwrap();
        let t_acc: Vec<i64> = log.acceleration.iter().map(|s| s.0).collect();
        let a_rel: Vec<f64> = log.acceleration.iter().map(|s| s.1 - s.2).collect();
        let t_pos: Vec<i64> = log.position.iter().map(|s| s.0).collect();
        let pos: Vec<f64> = log.position.iter().map(|s| s.1).collect();
        let trace = run_kalman(params.kalman, &t_acc, &a_rel, &t_pos, &pos).unwrap();
        let vel = table.column("velocity_mps").unwrap();
        for (k, &t_k) in table.t_ns.iter().enumerate() {
            let idx: Vec<usize> = (0..t_acc.len())
                .filter(|&i| t_acc[i] > t_k - TICK_NS && t_acc[i] <= t_k)
                .collect();
            let n = idx.len() as f64;
            let v = idx.iter().map(|&i| trace.velocity_mps[i]).sum::<f64>() / n;
            let y = idx.iter().map(|&i| trace.position_m[i]).sum::<f64>() / n;
            let a = idx
                .iter()
                .map(|&i| a_rel[i] - trace.bias_mps2[i])
                .sum::<f64>()
                / n;
            assert!((vel[k] - v).abs() < 1e-12, "tick {k}: {} vs {v}", vel[k]);
            let tw = &table.twin[k];
            assert!(
                (tw.position_m - y).abs() < 1e-12 && (tw.accel_mps2 - a).abs() < 1e-9,
                "tick {k}"
            );
        }
        // And the velocity is right: against the true velocity at the
        // interval centre (the boxcar delays by 10 ms), after convergence.
        let w = omega();
        let max_err = (100..150)
            .map(|k| {
                let tc = (table.t_ns[k] - T0 - TICK_NS / 2) as f64 / 1e9;
                (vel[k] - AMP_M * w * (w * tc).cos()).abs()
            })
            .fold(0.0, f64::max);
        assert!(
            max_err < 0.02,
            "velocity error {max_err} m/s (peak 0.5 m/s)"
        );
        // The 0.3 m/s² bias was learned.
        assert!(
            (table.twin[149].bias_mps2 - 0.3).abs() < 0.1,
            "{}",
            table.twin[149].bias_mps2
        );
    }

    #[test]
    fn models_run_at_the_tick_with_held_inputs() {
        let log = synth_log(4, TopicSet::all());
        let params = PhysicsParams::default();
        let table = compute_features(&log, &params, &Group::ALL).unwrap();
        let col = |name| table.column(name).unwrap();
        let (oil, cyl, power, amb) = (
            col("oil_temp_model_c"),
            col("cyl_temp_model_c"),
            col("heat_rate_model_w"),
            col("temp_ambient_c"),
        );
        // First shock temperature at 250 ms: thermal model starts at tick 13 (260 ms).
        assert!(oil[..12].iter().all(|x| x.is_nan()));
        assert_eq!((oil[12], cyl[12]), (25.0, 25.0));
        // From there it is ThermalModel::simulate on the tick grid with the
        // heat input and ambient of each tick held over the next step.
        let t_s: Vec<f64> = table.t_ns[12..]
            .iter()
            .map(|&t| (t - T0) as f64 / 1e9)
            .collect();
        let model = ThermalModel::new(params.thermal);
        let (oil_ref, cyl_ref) = model
            .simulate(&t_s, &power[12..], &amb[12..], 25.0, 25.0)
            .unwrap();
        for i in 0..t_s.len() {
            assert!(
                (oil[12 + i] - oil_ref[i]).abs() < 1e-9 && (cyl[12 + i] - cyl_ref[i]).abs() < 1e-9,
                "tick {}",
                12 + i
            );
        }
        // Heat flows in: the oil warms.
        assert!(oil[199] > 25.05, "{}", oil[199]);
        // Force model at the tick from the boxcar means and the oil temperature.
        let fm = ForceModel::new(params.force);
        for k in 12..table.n_rows() {
            let tw = &table.twin[k];
            let fb = fm.force(tw.velocity_mps, tw.accel_mps2, tw.position_m, oil[k]);
            let r = table.row(k);
            assert_eq!(r[col::FORCE_MODEL_N], fb.total_n);
            assert_eq!(r[col::FORCE_DAMPING_MODEL_N], fb.damping_n());
            assert_eq!(r[col::FORCE_GAS_MODEL_N], fb.gas_n);
            assert_eq!(power[k], fm.dissipative_power_w(tw.velocity_mps, oil[k]));
        }
        // Truth label held at each tick.
        assert!(table.truth_static_bar[..12].iter().all(|x| x.is_nan()));
        assert_eq!(table.truth_static_bar[60], 12.0);
        assert_eq!(table.truth_static_bar[62], 12.01);
    }

    #[test]
    fn no_ambient_thermocouple_uses_first_shock_temperature() {
        let topics = TopicSet {
            temp_ambient: false,
            ..TopicSet::all()
        };
        let log = synth_log(3, topics);
        let table =
            compute_features(&log, &PhysicsParams::default(), &[Group::Mechanical]).unwrap();
        assert!(table.twin[100].oil_temp_c.is_finite());
        let full = FeaturePipeline::new(&PhysicsParams::default(), topics).unwrap();
        drop(full);
        let rows = run_rows(&sorted_samples(&log), topics, true);
        assert!(rows[100].values[col::TEMP_AMBIENT_C].is_nan());
        assert!(
            rows[100].values[col::OIL_TEMP_MODEL_C].is_nan(),
            "thermal group needs both thermocouples"
        );
        assert!(rows[100].values[col::FORCE_MODEL_N].is_finite());
    }

    #[test]
    fn position_only_filter_without_accelerometers() {
        let topics = TopicSet {
            acceleration: false,
            ..TopicSet::all()
        };
        let log = synth_log(3, topics);
        let table = compute_features(
            &log,
            &PhysicsParams::default(),
            &[Group::Force, Group::Position],
        )
        .unwrap();
        let tw = &table.twin[149];
        assert!(tw.position_only);
        let w = omega();
        let tc = (table.t_ns[149] - T0 - TICK_NS / 2) as f64 / 1e9;
        assert!(
            (tw.velocity_mps - AMP_M * w * (w * tc).cos()).abs() < 0.05,
            "{}",
            tw.velocity_mps
        );
        assert!(
            tw.velocity_rms_1s_mps > 0.3 && tw.velocity_rms_1s_mps < 0.4,
            "{}",
            tw.velocity_rms_1s_mps
        );
        let rows = run_rows(&sorted_samples(&log), topics, true);
        assert!(
            rows[149].values[col::VELOCITY_MPS].is_nan(),
            "velocity group needs accelerometers"
        );
    }

    /// The error for a name that is no group lists every group (it listed
    /// the paper's six, not `signature`, `residual`, `observer`).
    #[test]
    fn an_unknown_group_lists_every_group() {
        let text = PhysicsError::UnknownGroup("forcee".into()).to_string();
        for g in Group::ALL {
            assert!(text.contains(g.name()), "{text} lacks {}", g.name());
        }
    }

    #[test]
    fn missing_topics_are_named() {
        let log = synth_log(
            1,
            TopicSet {
                force: false,
                temp_ambient: false,
                ..TopicSet::all()
            },
        );
        let err = compute_features(
            &log,
            &PhysicsParams::default(),
            &[Group::Force, Group::Thermal],
        )
        .unwrap_err();
        match &err {
            PhysicsError::MissingTopics {
                run_id, missing, ..
            } => {
                assert_eq!(run_id, "run-7");
                assert_eq!(missing, &["/force", "/temperature/ambient"]);
            }
            other => panic!("{other}"),
        }
        let msg = err.to_string();
        assert!(
            msg.contains("run-7") && msg.contains("/force") && msg.contains("/temperature/ambient"),
            "{msg}"
        );
        // Those groups that the log does support work.
        compute_features(
            &log,
            &PhysicsParams::default(),
            &[Group::Position, Group::Mechanical],
        )
        .unwrap();
    }

    #[test]
    fn out_of_order_sample_is_an_error() {
        let mut pipe = FeaturePipeline::new(&PhysicsParams::default(), TopicSet::all()).unwrap();
        pipe.push(&Sample::Force {
            t_ns: 100,
            force_n: 1.0,
        })
        .unwrap();
        let err = pipe
            .push(&Sample::Position {
                t_ns: 50,
                position_m: 0.0,
            })
            .unwrap_err();
        assert!(err.to_string().contains("/position"), "{err}");
    }

    #[test]
    fn truth_velocity_changes_nothing() {
        let mut log = synth_log(2, TopicSet::all());
        let params = PhysicsParams::default();
        let clean = compute_features(&log, &params, &Group::ALL).unwrap();
        // before the first sensor sample, between samples, after the last one
        for t in [
            T0 - 7 * MS,
            T0 + 5 * MS + 1,
            T0 + 1234 * MS + 17,
            T0 + 2500 * MS,
        ] {
            log.truth_velocity.push((t, 0.5));
        }
        log.truth_velocity.sort_by_key(|s| s.0);
        let with = compute_features(&log, &params, &Group::ALL).unwrap();
        assert_eq!(with.t_origin_ns, T0);
        // Debug prints floats exactly (and NaN equal to NaN)
        assert_eq!(format!("{clean:?}"), format!("{with:?}"));
    }

    #[test]
    fn nan_samples_are_skipped() {
        let mut log = synth_log(1, TopicSet::all());
        let clean = compute_features(&log, &PhysicsParams::default(), &Group::ALL).unwrap();
        // Make the last position sample of tick 10's interval NaN.
        let i = log
            .position
            .iter()
            .position(|s| s.0 == T0 + 200 * MS)
            .unwrap();
        log.position[i].1 = f64::NAN;
        let dirty = compute_features(&log, &PhysicsParams::default(), &Group::ALL).unwrap();
        assert_eq!(
            dirty.column("position_m").unwrap()[9],
            log.position[i - 1].1
        );
        assert!(clean
            .row(5)
            .iter()
            .zip(dirty.row(5))
            .all(|(a, b)| same(*a, *b)));
        assert_eq!(dirty.twin[49].missing_samples, 1);
        assert_eq!(clean.twin[49].missing_samples, 0);
    }

    #[test]
    fn groups_sensors_costs_and_permutations() {
        for g in Group::ALL {
            assert_eq!(Group::from_name(g.name()).unwrap(), g);
            assert_eq!(
                serde_json::to_string(&g).unwrap(),
                format!("\"{}\"", g.name())
            );
        }
        assert!(Group::from_name("Force")
            .unwrap_err()
            .to_string()
            .contains("Force"));
        let all: Vec<&str> = Group::ALL
            .iter()
            .flat_map(|g| g.columns().iter().copied())
            .collect();
        assert_eq!(all, COLUMNS.to_vec());
        let perms = paper_permutations();
        assert_eq!(perms.len(), 13);
        let cost = |id: u32| perms[id as usize - 1].cost_aud();
        // Paper Table 3.
        assert_eq!(
            [cost(3), cost(7), cost(9), cost(11), cost(12), cost(13)],
            [4270, 4281, 4281, 4292, 297, 4292]
        );
        assert_eq!(perms[11].name, "Thermomechanical Hybrid DNN (No Force)");
        assert_eq!(perms[12].groups.len(), 6);
        assert_eq!(paper_rmse_bar(12), Some(1.40));
        assert_eq!(perms[2].columns(), vec!["force_n", "position_m"]);
        // Permutations are data: a user-defined one round-trips through JSON.
        let json = r#"{"id": 42, "name": "mine", "groups": ["velocity", "force"]}"#;
        let p: Permutation = serde_json::from_str(json).unwrap();
        assert_eq!(p.columns(), vec!["velocity_mps", "force_n"]);
        assert_eq!(p.cost_aud(), 3995 + 275 + 11);
        assert_eq!(
            column_indices(&[Group::Thermal, Group::Force, Group::Thermal]),
            vec![7, 8, 9, 10, 11, 0]
        );
    }

    /// Replaces the accelerometer samples (1 kHz from `T0`): `a1 = f(k, i)`
    /// with `k` the row whose interval holds sample `i`, `a2 = 0`.
    fn set_acceleration(log: &mut RunLog, f: impl Fn(usize, usize) -> f64) {
        for (i, s) in log.acceleration.iter_mut().enumerate() {
            assert_eq!(s.0, T0 + i as i64 * MS);
            let k = i.saturating_sub(1) / 20;
            *s = (s.0, f(k, i), 0.0);
        }
    }

    #[test]
    fn accel_hf_rms_of_tick_constant_and_alternating_signals() {
        // Quarter multiples: every sum below is exact in binary.
        let level = |k: usize| 0.25 * (k % 7) as f64 - 1.0;
        let mut log = synth_log(3, TopicSet::all());
        set_acceleration(&mut log, |k, _| level(k));
        let table = compute_features(&log, &PhysicsParams::default(), &[Group::Signature]).unwrap();
        let hf = table.column("accel_hf_rms_mps2").unwrap();
        assert_eq!(hf.len(), 150);
        assert!(hf.iter().all(|&x| x == 0.0), "{hf:?}");

        // ±c_k about the tick's level, c_k = 0.5 on even ticks, 0.25 on odd
        // ones: the within-tick std is c_k (10 samples of each sign), the
        // column the RMS of c over the last 50 ticks. Tick 60 has only NaN
        // samples: skipped.
        let c = |k: usize| if k % 2 == 0 { 0.5 } else { 0.25 };
        set_acceleration(&mut log, |k, i| {
            if k == 60 {
                f64::NAN
            } else {
                level(k) + c(k) * if i % 2 == 0 { 1.0 } else { -1.0 }
            }
        });
        let table = compute_features(&log, &PhysicsParams::default(), &[Group::Signature]).unwrap();
        let hf = table.column("accel_hf_rms_mps2").unwrap();
        assert_eq!(hf[0], 0.5);
        // (The last row, 149, holds 19 samples: not a balanced alternation.)
        for (r, &got) in hf[..149].iter().enumerate() {
            let ticks: Vec<usize> = (r.saturating_sub(49)..=r).filter(|&k| k != 60).collect();
            let want =
                (ticks.iter().map(|&k| c(k) * c(k)).sum::<f64>() / ticks.len() as f64).sqrt();
            assert!((got - want).abs() < 1e-12, "row {r}: {got} vs {want}");
        }
        assert!(hf[60].is_finite(), "a NaN tick is skipped, not propagated");
        // The excitation column is the twin's 1 s velocity RMS.
        let v = table.column("velocity_rms_mps").unwrap();
        for (k, tw) in table.twin.iter().enumerate() {
            assert!(same(v[k], tw.velocity_rms_1s_mps), "row {k}");
        }
    }

    #[test]
    fn temp_resid_is_measured_minus_model_and_its_rate_looks_back_10_s() {
        let log = synth_log(14, TopicSet::all());
        let table = compute_features(
            &log,
            &PhysicsParams::default(),
            &[Group::Thermal, Group::Signature],
        )
        .unwrap();
        let col = |name| table.column(name).unwrap();
        let (shock, cyl, resid, rate) = (
            col("temp_shock_c"),
            col("cyl_temp_model_c"),
            col("temp_resid_c"),
            col("temp_resid_rate_cps"),
        );
        assert_eq!(table.n_rows(), 700);
        for k in 0..700 {
            assert!(same(resid[k], shock[k] - cyl[k]), "row {k}");
        }
        // The thermal model starts at row 12; the rate needs the residual
        // 500 rows (10 s) back.
        assert!(resid[..12].iter().all(|x| x.is_nan()) && resid[12].is_finite());
        assert!(
            rate[..512].iter().all(|x| x.is_nan()),
            "NaN until 10 s of history"
        );
        for k in 512..700 {
            let want = (resid[k] - resid[k - 500]) / 10.0;
            assert!(
                (rate[k] - want).abs() < 1e-12,
                "row {k}: {} vs {want}",
                rate[k]
            );
        }
        // The thermocouple rises 0.05 °C/s, the model otherwise: not zero.
        assert!(rate[699].abs() > 1e-3, "{}", rate[699]);
    }

    #[test]
    fn temp_resid_reads_the_model_through_the_thermocouple_gain_and_lag() {
        let log = synth_log(14, TopicSet::all());
        let mut params = PhysicsParams::default();
        params.thermal.tc_gain = 0.9;
        let groups = [Group::Thermal, Group::Signature];
        let table = compute_features(&log, &params, &groups).unwrap();
        let col = |name| table.column(name).unwrap();
        let (shock, amb, cyl, resid) = (
            col("temp_shock_c"),
            col("temp_ambient_c"),
            col("cyl_temp_model_c"),
            col("temp_resid_c"),
        );
        // The model starts at row 12 from the shock reading there; the
        // offset against the ambient at that row is carried unchanged.
        let offset = shock[12] - amb[12];
        for k in 12..700 {
            let reading = amb[k] + 0.9 * (cyl[k] - amb[k]) + 0.1 * offset;
            assert!((resid[k] - (shock[k] - reading)).abs() < 1e-9, "row {k}");
        }
        // A lag of 2 s: a first-order filter of that reading, tick by tick.
        params.thermal.tc_lag_s = 2.0;
        let lagged = compute_features(&log, &params, &groups).unwrap();
        let resid_lag = lagged.column("temp_resid_c").unwrap();
        let a = 1.0 - (-TICK_S / 2.0f64).exp();
        let mut reading = shock[12];
        for k in 12..700 {
            let target = amb[k] + 0.9 * (cyl[k] - amb[k]) + 0.1 * offset;
            if k > 12 {
                reading += a * (target - reading);
            }
            assert!(
                (resid_lag[k] - (shock[k] - reading)).abs() < 1e-9,
                "row {k}"
            );
        }
        assert!((resid_lag[699] - resid[699]).abs() > 1e-4, "the lag shows");
    }

    #[test]
    fn force_resid_of_model_plus_offset() {
        let params = PhysicsParams::default();
        let groups = [Group::Mechanical, Group::Residual];
        let mut log = synth_log(4, TopicSet::all());
        let model = compute_features(&log, &params, &groups)
            .unwrap()
            .column("force_model_n")
            .unwrap();
        // One loadcell sample per tick interval (at +3 ms): row i's boxcar is
        // sample i. The loadcell does not feed the model.
        assert_eq!(log.force.len(), model.len());
        for (offset, ripple) in [(100.0, 0.0), (100.0, 30.0)] {
            for (i, s) in log.force.iter_mut().enumerate() {
                let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
                s.1 = model[i] + offset + ripple * sign;
            }
            let table = compute_features(&log, &params, &groups).unwrap();
            let again = table.column("force_model_n").unwrap();
            assert!(again.iter().zip(&model).all(|(a, b)| same(*a, *b)));
            let mean = table.column("force_resid_mean_n").unwrap();
            let rms = table.column("force_resid_rms_n").unwrap();
            // The model starts at row 12; 1 s later the window is full.
            assert!(
                model[..12].iter().all(|x| x.is_nan()) && mean[..12].iter().all(|x| x.is_nan())
            );
            assert!(mean[12].is_finite());
            for k in 61..table.n_rows() {
                assert!((mean[k] - offset).abs() < 1e-9, "row {k}: {}", mean[k]);
                assert!((rms[k] - ripple).abs() < 1e-9, "row {k}: {}", rms[k]);
            }
        }
    }

    #[test]
    fn window_groups_need_their_topics() {
        let no_force = TopicSet {
            force: false,
            ..TopicSet::all()
        };
        let log = synth_log(2, no_force);
        let params = PhysicsParams::default();
        match compute_features(&log, &params, &[Group::Signature, Group::Residual]).unwrap_err() {
            PhysicsError::MissingTopics { missing, .. } => assert_eq!(missing, ["/force"]),
            other => panic!("{other}"),
        }
        compute_features(&log, &params, &[Group::Signature]).unwrap();
        let log = synth_log(
            2,
            TopicSet {
                temp_ambient: false,
                ..TopicSet::all()
            },
        );
        let err = compute_features(&log, &params, &[Group::Signature]).unwrap_err();
        assert!(err.to_string().contains("/temperature/ambient"), "{err}");
        compute_features(&log, &params, &[Group::Residual]).unwrap();
        // A pipeline without the loadcell leaves the residual columns NaN.
        let rows = run_rows(&sorted_samples(&synth_log(2, no_force)), no_force, true);
        let r = &rows[80].values;
        assert!(r[Group::Residual.column_range()].iter().all(|x| x.is_nan()));
        assert!(r[Group::Signature.column_range()][..3]
            .iter()
            .all(|x| x.is_finite()));
    }

    #[test]
    fn window_columns_do_not_look_ahead() {
        // Long enough for the 10 s temperature rate.
        let log = synth_log(12, TopicSet::all());
        let samples = sorted_samples(&log);
        let full = run_rows(&samples, TopicSet::all(), true);
        assert!(full[599].values[col::TEMP_RESID_RATE_CPS].is_finite());
        for frac in [0.05, 0.4, 0.87, 0.999] {
            let cut = (frac * samples.len() as f64) as usize;
            let prefix = run_rows(&samples[..cut], TopicSet::all(), false);
            assert!(prefix.len() + 1 >= full.len() * cut / samples.len());
            for (a, b) in prefix.iter().zip(&full) {
                assert!(
                    a.values.iter().zip(&b.values).all(|(x, y)| same(*x, *y)),
                    "cut {cut}, row at {}",
                    a.t_ns
                );
            }
        }
    }

    #[test]
    fn twin_of_a_reduced_log_runs_the_reduced_models() {
        let params = PhysicsParams::default();
        // With every topic, the twin is the full suite's.
        let log = synth_log(3, TopicSet::all());
        let full = compute_features(&log, &params, &Group::PAPER).unwrap();
        let twin = compute_twin(&log, &params).unwrap();
        assert_eq!(twin.columns.len(), col::OBSERVER_BAR);
        assert_eq!(format!("{:?}", full.twin), format!("{:?}", twin.twin));
        for name in &full.columns {
            let (a, b) = (full.column(name).unwrap(), twin.column(name).unwrap());
            assert!(a.iter().zip(&b).all(|(x, y)| same(*x, *y)), "{name}");
        }

        // No accelerometers, no ambient thermocouple: compute_features refuses
        // the mechanical group, compute_twin runs the position-only filter and
        // the thermal model with the first shock temperature (25 °C) as ambient —
        // exactly as with an ambient thermocouple reading 25 °C throughout.
        let reduced = TopicSet {
            acceleration: false,
            temp_ambient: false,
            ..TopicSet::all()
        };
        let log = synth_log(3, reduced);
        assert!(compute_features(&log, &params, &[Group::Mechanical]).is_err());
        let twin = compute_twin(&log, &params).unwrap();
        let mut at_25 = log.clone();
        at_25.temp_ambient = log.temp_shock.iter().map(|s| (s.0, 25.0)).collect();
        let with_ambient = compute_twin(&at_25, &params).unwrap();
        assert_eq!(twin.n_rows(), 150);
        let tw = &twin.twin[149];
        assert!(tw.position_only);
        let w = omega();
        let tc = (twin.t_ns[149] - T0 - TICK_NS / 2) as f64 / 1e9;
        assert!((tw.velocity_mps - AMP_M * w * (w * tc).cos()).abs() < 0.05);
        assert!(tw.force_model_n.is_finite() && tw.oil_temp_c > 25.0);
        for (a, b) in twin.twin.iter().zip(&with_ambient.twin) {
            assert!(same(a.oil_temp_c, b.oil_temp_c) && same(a.cyl_temp_c, b.cyl_temp_c));
            assert!(same(a.force_model_n, b.force_model_n));
        }
        // Columns whose group lacks a sensor stay NaN, as in the estimator.
        let v = twin.column("velocity_mps").unwrap();
        assert!(v.iter().all(|x| x.is_nan()));
        assert!(twin.column("force_n").unwrap()[100].is_finite());
    }

    #[test]
    fn extra_permutations_are_ours() {
        let perms = extra_permutations();
        assert_eq!(
            perms.iter().map(|p| p.id).collect::<Vec<_>>(),
            [14, 15, 16, 17, 18, 19]
        );
        assert_eq!(
            perms[0].groups.as_ref(),
            [Group::Velocity, Group::Mechanical, Group::Signature]
        );
        assert_eq!(perms[0].name, "Causal signature hybrid (no force)");
        assert_eq!(
            perms.iter().map(Permutation::cost_aud).collect::<Vec<_>>(),
            [297, 4292, 4292, 297, 297, 4292]
        );
        assert_eq!(
            perms[1].columns(),
            [
                "force_n",
                "velocity_mps",
                "force_model_n",
                "force_damping_model_n",
                "force_gas_model_n",
                "force_resid_mean_n",
                "force_resid_rms_n"
            ]
        );
        assert_eq!(perms[2].columns().len(), 11);
        assert_eq!(perms[3].columns(), ["observer_bar", "observer_sd_bar"]);
        assert!(perms.iter().all(|p| paper_rmse_bar(p.id).is_none()));
        assert_eq!(paper_permutations().len(), 13);
        assert_eq!(Group::from_name("signature").unwrap(), Group::Signature);
        assert_eq!(
            serde_json::to_string(&Group::Residual).unwrap(),
            "\"residual\""
        );
        assert_eq!(Group::PAPER, Group::ALL[..6]);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// Features of a prefix of the stream are the prefix of the features.
        #[test]
        fn no_look_ahead(cut_frac in 0.0..1.0f64) {
            let log = synth_log(2, TopicSet::all());
            let samples = sorted_samples(&log);
            let full = run_rows(&samples, TopicSet::all(), true);
            let cut = (cut_frac * samples.len() as f64) as usize;
            let prefix = run_rows(&samples[..cut], TopicSet::all(), false);
            prop_assert!(prefix.len() <= full.len());
            for (a, b) in prefix.iter().zip(&full) {
                prop_assert_eq!(a.t_ns, b.t_ns);
                prop_assert!(a.values.iter().zip(&b.values).all(|(x, y)| same(*x, *y)));
                prop_assert!(same(a.twin.velocity_rms_1s_mps, b.twin.velocity_rms_1s_mps));
            }
            // Every tick whose interval the prefix has passed is out.
            if cut > 0 {
                let last_t = samples[cut - 1].t_ns();
                let complete = full.iter().filter(|r| r.t_ns < last_t).count();
                prop_assert_eq!(prefix.len(), complete);
            }
        }
    }
}
