//! Runs and campaigns: the dyno procedure of paper §4, the sensors'
//! sampling schedule and the log files.
//!
//! A run: `rest_s` at rest (the paper records from one minute before the
//! excitation), then the sine until the shock thermocouple reads
//! `stop_temp_c` (80 °C), or until thermal equilibrium — the 30 s mean of
//! that thermocouple rose less than `equilibrium_rise_c` (0.5 °C) over the
//! last `equilibrium_window_s` (5 min), tested after `equilibrium_min_s` of
//! excitation — or the safety cap `max_excitation_s`. `quick` runs rest 10 s
//! and excite at most 60 s.
//!
//! Sampling (SPEC §2): acceleration every 1 ms, position 10 ms, force 20 ms,
//! temperatures 1 s; simulator truth (labels for analysis, never used by the
//! twin): static gas pressure `/truth/gas_pressure` (`static_bar`, bar
//! gauge) every 100 ms and the plant's extension rate `ẏ` `/truth/velocity`
//! (`velocity_mps`, m/s, positive in extension) every 10 ms, at the position
//! instants. All on one clock from `T0_NS`; at equal times samples come in
//! topic-rank order (acceleration first, truth velocity last). Every run
//! draws its randomness from `ChaCha8` streams seeded by
//! `(seed, charge, frequency, unit)` (room, sensors) and by `seed` alone (the
//! rig's sensor errors), so runs are independent of each other and of the
//! thread count.

use std::path::{Path, PathBuf};

use dt_core::log::{LogWriter, RunMetadata, Sample, WriteOptions};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::params::PlantParams;
use crate::plant::{Plant, PlantConfig};
use crate::road::RoadDrive;
use crate::sensors::{RigErrors, Sensors};
use crate::{mix_seed, SimError};

/// `log_time` of the first sample of every run, ns (2023-11-14T22:13:20Z).
pub const T0_NS: i64 = 1_700_000_000_000_000_000;
/// Version of the simulator, written to each run's metadata.
pub const SIM_VERSION: &str = concat!("dt-sim ", env!("CARGO_PKG_VERSION"));
/// The paper's stroke: 80 mm peak to peak.
pub const PAPER_STROKE_PP_M: f64 = 0.080;
/// The paper's charge pressures, bar gauge.
pub const PAPER_PRESSURES_BAR: [f64; 5] = [0.5, 4.0, 7.0, 10.0, 12.0];
/// The paper's frequencies, Hz.
pub const PAPER_FREQUENCIES_HZ: [f64; 3] = [1.0, 2.0, 4.0];

/// One dyno run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunSpec {
    /// Charge pressure, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// Sine frequency, Hz.
    pub frequency_hz: f64,
    /// Stroke, peak to peak, m.
    pub stroke_pp_m: f64,
    /// Campaign seed.
    pub seed: u64,
    /// `None`: the nominal unit; `Some(n)`: unit `n` (parameters varied).
    pub unit: Option<u64>,
    /// Shortened run (10 s rest, at most 60 s excitation).
    pub quick: bool,
    /// Repeat take of the run: 0 is the first; take `k > 0` is the same
    /// condition on the same rig and unit with independent noise and room.
    pub repeat: u32,
    /// A road drive file instead of the sine ([`crate::road`]);
    /// `frequency_hz` and `stroke_pp_m` are then not used.
    pub road: Option<RoadDrive>,
    /// Rate of the logged `/truth/velocity`, Hz: a divisor of 1000
    /// ([`DEFAULT_TRUTH_VELOCITY_HZ`]; 1000 for studying the stroke velocity
    /// estimate's error at the accelerometers' rate). Logging only: the
    /// plant, the sensors and every other topic do not change.
    pub truth_velocity_hz: u32,
    /// With `road`: the drive file's own seed (`road.seed`), apart from the
    /// campaign's `seed`, which keeps drawing the rig's sensor errors, the
    /// room and the noise: another road on the same vehicle. `None`: the
    /// drive file follows the campaign's seed (or the leak history's day).
    pub drive_seed: Option<u64>,
    /// The rig's own seed: its sensor errors (accelerometer offsets and
    /// gains, thermocouple offsets) drawn from it instead of from `seed`,
    /// which keeps drawing the room and the noise: the same run on another
    /// set of sensors. `None`: the rig of `seed`.
    pub rig_seed: Option<u64>,
}

/// `/truth/velocity`'s rate unless asked otherwise, Hz.
pub const DEFAULT_TRUTH_VELOCITY_HZ: u32 = 100;

/// Why a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// The shock thermocouple read `stop_temp_c`.
    Temperature,
    /// Thermal equilibrium.
    Equilibrium,
    /// The safety cap on the excitation time.
    SafetyCap,
    /// The excitation limit of a quick run.
    QuickLimit,
}

impl std::fmt::Display for StopReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            StopReason::Temperature => "stop temperature",
            StopReason::Equilibrium => "thermal equilibrium",
            StopReason::SafetyCap => "safety cap",
            StopReason::QuickLimit => "quick limit",
        })
    }
}

/// What a run did.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    /// Run id (also the file stem).
    pub run_id: String,
    /// Asset id.
    pub asset_id: String,
    /// File written, if any.
    pub path: Option<PathBuf>,
    /// Logged duration, s.
    pub duration_s: f64,
    /// Excitation time, s.
    pub excitation_s: f64,
    /// Why it ended.
    pub stop: StopReason,
    /// Last shock thermocouple reading, °C.
    pub final_shock_reading_c: f64,
    /// Final true oil temperature, °C.
    pub final_oil_c: f64,
    /// Final true outer-tube temperature, °C.
    pub final_outer_c: f64,
    /// Final true static gas pressure, bar gauge.
    pub final_static_bar: f64,
    /// Heat dissipated in the damper (valves and friction), J.
    pub energy_dissipated_j: f64,
    /// Heat lost to the room, J.
    pub heat_to_room_j: f64,
    /// Messages produced.
    pub messages: u64,
    /// Time with the compression chamber cavitating or a void present, s.
    pub cavitation_s: f64,
    /// Largest void, m³.
    pub max_void_m3: f64,
}

fn fmt_num(x: f64) -> String {
    format!("{x:.1}")
}

impl RunSpec {
    /// The paper's excitation at `charge_bar`, `frequency_hz`.
    #[must_use]
    pub fn paper(charge_bar: f64, frequency_hz: f64, seed: u64) -> Self {
        RunSpec {
            charge_bar,
            frequency_hz,
            stroke_pp_m: PAPER_STROKE_PP_M,
            seed,
            unit: None,
            quick: false,
            repeat: 0,
            road: None,
            truth_velocity_hz: DEFAULT_TRUTH_VELOCITY_HZ,
            drive_seed: None,
            rig_seed: None,
        }
    }

    /// `dyno-unit-A` for the nominal unit, `dyno-unit-U<n>` for unit `n`.
    #[must_use]
    pub fn asset_id(&self) -> String {
        match self.unit {
            None => "dyno-unit-A".to_owned(),
            Some(n) => format!("dyno-unit-U{n}"),
        }
    }

    /// E.g. `p12.0-f2.0-s1`, `p12.0-roadC60-s1` (`-d<k>` appended for a drive file of seed `k`
    /// on the campaign's rig, `-g<k>` for the sensors of rig seed `k`, `-u<n>` for a varied unit,
    /// `-r<k>` for repeat take `k > 0`).
    #[must_use]
    pub fn run_id(&self) -> String {
        let excitation = match self.road {
            Some(r) => r.tag(),
            None => format!("f{}", fmt_num(self.frequency_hz)),
        };
        let mut id = format!("p{}-{excitation}-s{}", fmt_num(self.charge_bar), self.seed);
        if let Some(d) = self.drive_seed {
            id = format!("{id}-d{d}");
        }
        if let Some(g) = self.rig_seed {
            id = format!("{id}-g{g}");
        }
        if let Some(n) = self.unit {
            id = format!("{id}-u{n}");
        }
        if self.repeat > 0 {
            id = format!("{id}-r{}", self.repeat);
        }
        id
    }

    /// The run's `shocktwin.run` metadata.
    #[must_use]
    pub fn metadata(&self) -> RunMetadata {
        let mut meta = RunMetadata {
            asset_id: self.asset_id(),
            run_id: self.run_id(),
            charge_pressure_bar: Some(self.charge_bar),
            excitation: Some(format!(
                "sine {} Hz {} mm p-p",
                self.frequency_hz,
                self.stroke_pp_m * 1e3
            )),
            frequency_hz: Some(self.frequency_hz),
            stroke_pp_m: Some(self.stroke_pp_m),
            ..RunMetadata::default()
        };
        if let Some(r) = self.road {
            let rms_mm = crate::road::rms_m(&r.components()) * 1e3;
            meta.excitation = Some(format!(
                "road: ISO 8608 class {} at {} km/h, quarter-car suspension stroke {rms_mm:.1} mm rms, {}-{} Hz",
                r.class.letter(),
                r.speed_kmh,
                crate::road::BAND_HZ.0,
                crate::road::BAND_HZ.1
            ));
            meta.frequency_hz = None;
            meta.stroke_pp_m = None;
            meta.extra
                .insert("road_class".into(), r.class.letter().to_string());
            meta.extra
                .insert("road_speed_kmh".into(), r.speed_kmh.to_string());
        }
        meta.extra.insert("simulated".into(), "true".into());
        meta.extra.insert("simulator".into(), SIM_VERSION.into());
        meta.extra.insert("seed".into(), self.seed.to_string());
        if let Some(d) = self.drive_seed {
            meta.extra.insert("drive_seed".into(), d.to_string());
        }
        if let Some(g) = self.rig_seed {
            meta.extra.insert("rig_seed".into(), g.to_string());
        }
        meta.extra.insert("quick".into(), self.quick.to_string());
        if let Some(n) = self.unit {
            meta.extra.insert("unit_seed".into(), n.to_string());
        }
        if self.repeat > 0 {
            meta.extra.insert("repeat".into(), self.repeat.to_string());
        }
        meta
    }

    fn run_seed(&self) -> u64 {
        let excitation = match self.road {
            None => self.frequency_hz.to_bits(),
            Some(r) => mix_seed(&[
                r.speed_kmh.to_bits(),
                u64::from(r.class.letter()),
                0x726f_6164,
            ]),
        };
        let excitation = match self.drive_seed {
            // a drive file of its own: its own noise and room (runs made before it keep theirs)
            Some(d) => mix_seed(&[excitation, d, 0x0064_7269_7665]),
            None => excitation,
        };
        let base = [
            self.seed,
            self.charge_bar.to_bits(),
            excitation,
            self.unit.map_or(u64::MAX, |n| n),
        ];
        if self.repeat == 0 {
            // The first take keeps the seeds of campaigns made before repeats existed.
            mix_seed(&base)
        } else {
            mix_seed(&[
                base[0],
                base[1],
                base[2],
                base[3],
                0x7265_7065_6174,
                u64::from(self.repeat),
            ])
        }
    }

    /// The plant parameters of this run's unit.
    #[must_use]
    pub fn params(&self) -> PlantParams {
        let p = PlantParams::nominal();
        match self.unit {
            None => p,
            Some(n) => p.varied(n),
        }
    }
}

/// Seconds of rest and maximum excitation for `spec` under `p`.
fn schedule(spec: &RunSpec, p: &PlantParams) -> (f64, f64) {
    if spec.quick {
        (p.rest_s.min(10.0), p.max_excitation_s.min(60.0))
    } else {
        (p.rest_s, p.max_excitation_s)
    }
}

/// Simulates one run of `spec` with the plant `params`, handing every
/// sample, in time order, to `sink`.
pub fn simulate_run_with<F>(
    spec: &RunSpec,
    params: &PlantParams,
    mut sink: F,
) -> Result<RunSummary, SimError>
where
    F: FnMut(&Sample) -> Result<(), SimError>,
{
    let hz = spec.truth_velocity_hz;
    if hz == 0 || 1000 % hz != 0 {
        return Err(SimError::InvalidSpec {
            field: "truth_velocity_hz",
            value: f64::from(hz),
            reason: "must divide 1000 (the simulator's millisecond)",
        });
    }
    let every_ms = u64::from(1000 / hz);
    drive(spec, params, |ms, truth, sensors, summary| {
        emit_tick(ms, every_ms, truth, sensors, summary, &mut sink)
    })
}

/// Runs the plant of `spec` through its dyno procedure, calling `tick` once
/// per millisecond with the truth and the sensors; `tick` samples what is
/// due and returns the shock thermocouple reading on whole seconds (the
/// procedure's stop rule reads it).
pub(crate) fn drive<E>(
    spec: &RunSpec,
    params: &PlantParams,
    mut tick: E,
) -> Result<RunSummary, SimError>
where
    E: FnMut(
        u64,
        &crate::plant::Truth,
        &mut Sensors,
        &mut RunSummary,
    ) -> Result<Option<f64>, SimError>,
{
    let (rest_s, max_exc_s) = schedule(spec, params);
    let config = PlantConfig {
        charge_bar: spec.charge_bar,
        frequency_hz: spec.frequency_hz,
        stroke_pp_m: spec.stroke_pp_m,
        excitation_start_s: rest_s,
        road: spec.road,
    };
    let run_seed = spec.run_seed();
    let room_rng = ChaCha8Rng::seed_from_u64(mix_seed(&[run_seed, 1]));
    let sensor_rng = ChaCha8Rng::seed_from_u64(mix_seed(&[run_seed, 2]));
    let rig_seed = spec.rig_seed.unwrap_or(spec.seed);
    let mut rig_rng = ChaCha8Rng::seed_from_u64(mix_seed(&[rig_seed, 0x0072_6967]));
    let rig = RigErrors::draw(params, &mut rig_rng);

    let mut plant = Plant::new(params, &config, room_rng)?;
    let n_sub = plant.substeps_per_ms();
    let dt = plant.dt_s();
    let mut truth = plant.step()?;
    let mut sensors = Sensors::new(params, rig, sensor_rng, &truth, dt);
    let rest_ms = (rest_s * 1000.0).round() as u64;
    let max_ms = rest_ms + (max_exc_s * 1000.0).round() as u64;
    let eq_window_s = params.equilibrium_window_s.round() as usize;
    let eq_min_s = params.equilibrium_min_s.round() as usize;

    let mut summary = RunSummary {
        run_id: spec.run_id(),
        asset_id: spec.asset_id(),
        path: None,
        duration_s: 0.0,
        excitation_s: 0.0,
        stop: StopReason::SafetyCap,
        final_shock_reading_c: f64::NAN,
        final_oil_c: f64::NAN,
        final_outer_c: f64::NAN,
        final_static_bar: f64::NAN,
        energy_dissipated_j: 0.0,
        heat_to_room_j: 0.0,
        messages: 0,
        cavitation_s: 0.0,
        max_void_m3: 0.0,
    };
    // Shock thermocouple readings since the excitation started (1 Hz).
    let mut shock_history: Vec<f64> = Vec::new();
    let mut i: u64 = 0;
    loop {
        sensors.update(&truth);
        summary.energy_dissipated_j += (truth.valve_power_w + truth.friction_power_w) * dt;
        if truth.cavitating || truth.void_m3 > 0.0 {
            summary.cavitation_s += dt;
        }
        summary.max_void_m3 = summary.max_void_m3.max(truth.void_m3);
        if i % n_sub == 0 {
            let ms = i / n_sub;
            let shock_c = tick(ms, &truth, &mut sensors, &mut summary)?;
            if let (Some(shock_c), true) = (shock_c, ms > rest_ms) {
                shock_history.push(shock_c);
                let at_cap = ms >= max_ms;
                if let Some(reason) =
                    check_stop(spec, params, &shock_history, eq_window_s, eq_min_s, at_cap)
                {
                    summary.stop = reason;
                    summary.duration_s = ms as f64 * 1e-3;
                    summary.excitation_s = (ms - rest_ms) as f64 * 1e-3;
                    break;
                }
            }
        }
        truth = plant.step()?;
        i += 1;
    }
    let nodes = plant.nodes();
    summary.final_oil_c = nodes.oil_c;
    summary.final_outer_c = nodes.outer_c;
    summary.final_static_bar = truth.static_gas_bar;
    summary.heat_to_room_j = plant.heat_to_room_j();
    Ok(summary)
}

/// Samples the sensors due at millisecond `ms` and hands them to `sink` in
/// topic-rank order; returns the shock thermocouple reading on 1 s ticks.
fn emit_tick<F>(
    ms: u64,
    truth_velocity_every_ms: u64,
    truth: &crate::plant::Truth,
    sensors: &mut Sensors,
    summary: &mut RunSummary,
    sink: &mut F,
) -> Result<Option<f64>, SimError>
where
    F: FnMut(&Sample) -> Result<(), SimError>,
{
    let t_ns = T0_NS + (ms as i64) * 1_000_000;
    let mut emit = |s: Sample| -> Result<(), SimError> {
        summary.messages += 1;
        sink(&s)
    };
    let (a1, a2) = sensors.sample_acceleration();
    emit(Sample::Acceleration {
        t_ns,
        a1_mps2: a1,
        a2_mps2: a2,
    })?;
    if ms % 10 == 0 {
        let position_m = sensors.sample_position();
        emit(Sample::Position { t_ns, position_m })?;
    }
    if ms % 20 == 0 {
        let force_n = sensors.sample_force();
        emit(Sample::Force { t_ns, force_n })?;
    }
    let mut shock = None;
    if ms % 1000 == 0 {
        let shock_c = sensors.sample_temp_shock();
        emit(Sample::TempShock {
            t_ns,
            temperature_c: shock_c,
        })?;
        let temperature_c = sensors.sample_temp_ambient();
        emit(Sample::TempAmbient {
            t_ns,
            temperature_c,
        })?;
        shock = Some(shock_c);
    }
    if ms % 100 == 0 {
        emit(Sample::TruthPressure {
            t_ns,
            static_bar: truth.static_gas_bar,
        })?;
    }
    if ms % truth_velocity_every_ms == 0 {
        emit(Sample::TruthVelocity {
            t_ns,
            velocity_mps: truth.velocity_mps,
        })?;
    }
    if let Some(c) = shock {
        summary.final_shock_reading_c = c;
    }
    Ok(shock)
}

fn check_stop(
    spec: &RunSpec,
    p: &PlantParams,
    history: &[f64],
    window_s: usize,
    min_s: usize,
    at_cap: bool,
) -> Option<StopReason> {
    let last = *history.last()?;
    if last >= p.stop_temp_c {
        return Some(StopReason::Temperature);
    }
    let n = history.len();
    let avg = 30usize;
    if n >= min_s.max(window_s + avg) {
        let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
        let now = mean(&history[n - avg..]);
        let before = mean(&history[n - avg - window_s..n - window_s]);
        if now - before < p.equilibrium_rise_c {
            return Some(StopReason::Equilibrium);
        }
    }
    if at_cap {
        return Some(if spec.quick {
            StopReason::QuickLimit
        } else {
            StopReason::SafetyCap
        });
    }
    None
}

/// Simulates one run into the MCAP file `out_path` (shocktwin log v1).
pub fn simulate_run(
    spec: &RunSpec,
    params: &PlantParams,
    out_path: &Path,
) -> Result<RunSummary, SimError> {
    let run_id = spec.run_id();
    let log_err = |source: dt_core::log::LogError| SimError::Log {
        run_id: run_id.clone(),
        source: Box::new(source),
    };
    let mut writer =
        LogWriter::create(out_path, &spec.metadata(), WriteOptions::default()).map_err(log_err)?;
    let mut summary = simulate_run_with(spec, params, |s| {
        writer.write_sample(s).map_err(|source| SimError::Log {
            run_id: spec.run_id(),
            source: Box::new(source),
        })
    })?;
    writer.finish().map_err(log_err)?;
    summary.path = Some(out_path.to_path_buf());
    Ok(summary)
}

/// A unit in service losing gas: one run a day for `days` days, the charge
/// falling linearly (`shocktwin simulate --leak-rate --days`).
#[derive(Debug, Clone, PartialEq)]
pub struct LeakHistorySpec {
    /// Charge on day 0, bar gauge at 20 °C.
    pub start_bar: f64,
    /// Charge lost per day, bar (≥ 0).
    pub leak_bar_per_day: f64,
    /// Days (one run each).
    pub days: u32,
    /// Excitation of every run, Hz.
    pub frequency_hz: f64,
    /// Seed.
    pub seed: u64,
    /// Quick runs.
    pub quick: bool,
    /// Unit (`None` = nominal).
    pub unit: Option<u64>,
    /// Asset id written to the metadata (`None`: the unit's, see
    /// [`RunSpec::asset_id`]).
    pub asset_id: Option<String>,
    /// A vehicle on roads instead of the sine: every day a drive of this
    /// speed and road class, each day's drive file its own (drawn from the
    /// drive's seed and the day); the rig and unit stay the same.
    pub road: Option<RoadDrive>,
}

/// Hour of the day (UTC) at which the day's run starts, before a jitter of
/// up to ± 2 h drawn from the seed.
pub const HISTORY_RUN_HOUR: f64 = 9.0;

impl LeakHistorySpec {
    /// Day `d`'s run: its spec (the day is the repeat take, so noise and
    /// room differ from day to day), its start time and its charge.
    #[must_use]
    pub fn run(&self, day: u32) -> (RunSpec, i64) {
        let charge_bar = (self.start_bar - self.leak_bar_per_day * f64::from(day)).max(0.0);
        let spec = RunSpec {
            charge_bar,
            unit: self.unit,
            quick: self.quick,
            repeat: day,
            road: self.road.map(|r| RoadDrive {
                seed: mix_seed(&[r.seed, u64::from(day), 0x726f_6164]),
                ..r
            }),
            ..RunSpec::paper(charge_bar, self.frequency_hz, self.seed)
        };
        let jitter =
            mix_seed(&[self.seed, u64::from(day), 0x6a69_7474_6572]) as f64 / u64::MAX as f64;
        let start_s =
            f64::from(day) * 86_400.0 + (HISTORY_RUN_HOUR + 4.0 * (jitter - 0.5)) * 3600.0;
        (spec, T0_NS + (start_s * 1e9) as i64)
    }
}

/// Simulates a [`LeakHistorySpec`] into `out_dir`, one
/// `d<day>-<run_id>.mcap` per day; each run's samples start at its day's
/// time (Unix epoch, from `T0_NS`). The metadata adds `day` and
/// `leak_bar_per_day`.
pub fn simulate_leak_history(
    spec: &LeakHistorySpec,
    out_dir: &Path,
    on_run: &(dyn Fn(&RunSummary) + Sync),
) -> Result<Vec<RunSummary>, SimError> {
    if !(spec.leak_bar_per_day.is_finite() && spec.leak_bar_per_day >= 0.0) {
        return Err(SimError::InvalidSpec {
            field: "leak_bar_per_day",
            value: spec.leak_bar_per_day,
            reason: "must be finite and ≥ 0",
        });
    }
    std::fs::create_dir_all(out_dir).map_err(|source| SimError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    let days: Vec<u32> = (0..spec.days).collect();
    days.par_iter()
        .map(|&day| {
            let (run, start_ns) = spec.run(day);
            let run_id = format!("d{day:03}-{}", run.run_id());
            let mut meta = run.metadata();
            meta.run_id.clone_from(&run_id);
            if let Some(a) = &spec.asset_id {
                meta.asset_id.clone_from(a);
            }
            meta.extra.insert("day".into(), day.to_string());
            meta.extra
                .insert("leak_bar_per_day".into(), spec.leak_bar_per_day.to_string());
            let path = out_dir.join(format!("{run_id}.mcap"));
            let log_err = |source: dt_core::log::LogError| SimError::Log {
                run_id: run_id.clone(),
                source: Box::new(source),
            };
            let mut writer =
                LogWriter::create(&path, &meta, WriteOptions::default()).map_err(log_err)?;
            let mut summary = simulate_run_with(&run, &run.params(), |s| {
                writer
                    .write_sample(&s.shifted(start_ns - T0_NS))
                    .map_err(log_err)
            })?;
            writer.finish().map_err(log_err)?;
            summary.run_id = run_id;
            // the asset the file names (`simulate --asset-id` printed the unit's)
            summary.asset_id.clone_from(&meta.asset_id);
            summary.path = Some(path);
            on_run(&summary);
            Ok(summary)
        })
        .collect()
}

/// A campaign: every pressure × every frequency.
#[derive(Debug, Clone, PartialEq)]
pub struct CampaignSpec {
    /// Charge pressures, bar gauge.
    pub pressures_bar: Vec<f64>,
    /// Frequencies, Hz.
    pub frequencies_hz: Vec<f64>,
    /// Stroke, peak to peak, m.
    pub stroke_pp_m: f64,
    /// Seed.
    pub seed: u64,
    /// Quick runs.
    pub quick: bool,
    /// Unit (`None` = nominal).
    pub unit: Option<u64>,
    /// Repeat take of every run (see [`RunSpec::repeat`]).
    pub repeat: u32,
    /// A road drive file instead of the sines: one run per pressure (the
    /// frequencies are not used), every run the same drive file.
    pub road: Option<RoadDrive>,
    /// Rate of the logged `/truth/velocity`, Hz (see
    /// [`RunSpec::truth_velocity_hz`]).
    pub truth_velocity_hz: u32,
    /// With `road`: the drive file's seed apart from the rig's (see
    /// [`RunSpec::drive_seed`]).
    pub drive_seed: Option<u64>,
    /// The rig's own seed (see [`RunSpec::rig_seed`]).
    pub rig_seed: Option<u64>,
}

impl CampaignSpec {
    /// The paper's campaign: 5 pressures × 3 frequencies, 80 mm p-p.
    #[must_use]
    pub fn paper(seed: u64) -> Self {
        CampaignSpec {
            pressures_bar: PAPER_PRESSURES_BAR.to_vec(),
            frequencies_hz: PAPER_FREQUENCIES_HZ.to_vec(),
            stroke_pp_m: PAPER_STROKE_PP_M,
            seed,
            quick: false,
            unit: None,
            repeat: 0,
            road: None,
            truth_velocity_hz: DEFAULT_TRUTH_VELOCITY_HZ,
            drive_seed: None,
            rig_seed: None,
        }
    }

    /// The runs, pressure-major.
    #[must_use]
    pub fn runs(&self) -> Vec<RunSpec> {
        let mut out = Vec::new();
        let frequencies: &[f64] = if self.road.is_some() {
            &[0.0]
        } else {
            &self.frequencies_hz
        };
        for &charge_bar in &self.pressures_bar {
            for &frequency_hz in frequencies {
                out.push(RunSpec {
                    charge_bar,
                    frequency_hz,
                    stroke_pp_m: self.stroke_pp_m,
                    seed: self.seed,
                    unit: self.unit,
                    quick: self.quick,
                    repeat: self.repeat,
                    road: self.road.map(|r| RoadDrive {
                        seed: self.drive_seed.unwrap_or(r.seed),
                        ..r
                    }),
                    truth_velocity_hz: self.truth_velocity_hz,
                    drive_seed: self.road.and(self.drive_seed),
                    rig_seed: self.rig_seed,
                });
            }
        }
        out
    }
}

/// Simulates every run of `spec` in parallel (rayon) into `out_dir`
/// (created if missing), one `<run_id>.mcap` per run. The summaries come in
/// the order of [`CampaignSpec::runs`]; the files do not depend on the
/// number of threads.
pub fn simulate_campaign(spec: &CampaignSpec, out_dir: &Path) -> Result<Vec<RunSummary>, SimError> {
    simulate_campaign_with(spec, out_dir, &|_| {})
}

/// [`simulate_campaign`], calling `on_run` as each run is written (from the
/// worker threads, in completion order): a progress bar's hook.
pub fn simulate_campaign_with(
    spec: &CampaignSpec,
    out_dir: &Path,
    on_run: &(dyn Fn(&RunSummary) + Sync),
) -> Result<Vec<RunSummary>, SimError> {
    let (runs, params) = prepare(spec, out_dir)?;
    runs.par_iter()
        .map(|run| {
            let summary = simulate_run(
                run,
                &params,
                &out_dir.join(format!("{}.mcap", run.run_id())),
            )?;
            on_run(&summary);
            Ok(summary)
        })
        .collect()
}

/// Checks `spec`, creates `out_dir`, and returns the runs and their unit's
/// plant parameters.
pub(crate) fn prepare(
    spec: &CampaignSpec,
    out_dir: &Path,
) -> Result<(Vec<RunSpec>, PlantParams), SimError> {
    std::fs::create_dir_all(out_dir).map_err(|source| SimError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    for (field, values) in [
        ("pressures_bar", &spec.pressures_bar),
        ("frequencies_hz", &spec.frequencies_hz),
    ] {
        // Run ids carry one decimal: values equal at one decimal would
        // overwrite each other's files.
        let mut seen: Vec<String> = Vec::new();
        for &v in values {
            let key = fmt_num(v);
            if seen.contains(&key) {
                return Err(SimError::InvalidSpec {
                    field,
                    value: v,
                    reason:
                        "repeated (run ids use one decimal, so values must differ at one decimal)",
                });
            }
            seen.push(key);
        }
    }
    let runs = spec.runs();
    let params = runs
        .first()
        .map_or_else(PlantParams::nominal, RunSpec::params);
    Ok((runs, params))
}
