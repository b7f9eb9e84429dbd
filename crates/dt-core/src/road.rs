//! The charge read on a road from the cheap suite: the seal friction's flip
//! in the body accelerometer, regressed over blocks of drive, streaming.
//!
//! The dyno observer ([`crate::charge`]) fits one window per velocity
//! reversal of a sine and refuses a road. This observer reads any excitation
//! with enough stroke: over each block of `block_s` seconds (10 s) the body
//! accelerometer is modelled as the damper force through the calibrated
//! body-end mount and the accelerometer's first-order filter, the force linear
//! in its parameters:
//!
//! ```text
//! F(t) = α tanh(ẏ/v_s) + Σ_j (c_j + d_j τ) b_j(ẏ) + k y + f_0      τ = t / 100 s
//! a2   = H_mount * F + c_0 + ε
//! ```
//!
//! `b_j` a damping law flexible enough for a valve's knee (slopes each side,
//! hinges every 1 cm/s to 0.3 m/s, coarser to 1 m/s), `d_j` its drift across
//! the block (the oil heats), all unknown per block; `α` (N) the friction
//! amplitude, which grows with the gas pressure (a pressure-energised seal):
//! `α = a + b p_g`, `p_g = (p + p_atm) θ(T) − p_atm` the gas pressure at the
//! shock thermocouple's temperature ([`gas_ratio`], mid-stroke). Least squares
//! per block (columns scaled, normal equations by Cholesky refined once,
//! Householder QR when they are not positive definite) gives `α` and its
//! variance; a block moving less than `min_stroke_rms_mps` (a rest), slower
//! than the slowest block of the calibration's drives
//! (`slowest_calibrated_stroke_rms_mps`: the reading falls short of the
//! calibration's line the slower the stroke) or within `settle_s` of the
//! stream's start is not read.
//!
//! **Stroke velocity.** At the friction's 5 mm/s scale a 0.25 ms lag halves
//! `α`, so the velocity comes from a Kalman filter of its own (not
//! [`crate::kalman`]'s): state `x = [y, ẏ, b_a, y_f]` (m, m/s, m/s², m) with
//! `y_f` the potentiometer's reading behind its first-order RC, driven every
//! millisecond by `u = a1 − a2` (m/s²) with the accelerometers' first-order
//! filter inverted and averaged over the millisecond (trapezoid), updated at
//! the potentiometer's 100 Hz with steady-state gains; then a Rauch–Tung–
//! Striebel pass back from `lag_s` (0.5 s) after the block's end. A block's
//! reading uses no data later than that, and the shock thermocouple's next
//! sample (1 Hz): the estimate at a block's end is final about `lag_s` later.
//!
//! **Estimate.** Each reading `p_i` (bar gauge at 20 °C) with its spread
//! `s_i = block_sd_n / (b θ)` updates a random walk (`walk_bar2_per_s`) from a
//! wide prior; the 95 % interval is `p̂ ± z95 √(P + σ_sys² + (r (p̂ − p_b))²)`
//! with the calibration's systematic part `σ_sys` (another drive, another
//! unit's seal) and relative part `r`; with a unit's baseline drive at a known
//! charge `p_b` ([`RoadCalibration::with_baseline`]) the seal's offset is read
//! and only its slope's tolerance stays relative to `p̂ − p_b`. Health is
//! SPEC §6a's machine on that interval at each block's end.
//!
//! **Constants.** The filters' matrices, the mount's discrete coefficients
//! (first-order hold at 4 kHz) and the hinges come with the calibration
//! (`python -m train.road_observer fit` writes them beside `a`, `b`), so this
//! module applies exactly the filters its Python reference does
//! (`train.road_observer.block_readings`, checked against it in
//! `tests/python/test_road_observer.py`).
//!
//! **Input.** Samples in time order, as [`crate::log::RunLog::samples_in_order`]
//! yields them; the accelerometers at 1 kHz and the potentiometer at 100 Hz
//! (SPEC §2) are placed on their nominal grids by time. A missing or
//! non-finite accelerometer sample is bridged linearly (its `a2` is not
//! regressed); a missing position is a step without update (a block with
//! positions at fewer than half its steps is not read); a gap longer than
//! `MAX_GAP_NS` or time going backwards restarts the filters (the estimate and
//! health carry on).

use std::collections::{BTreeMap, VecDeque};
use std::f64::consts::PI;

use nalgebra::{DMatrix, DVector, Matrix4, SMatrix, Vector4};
use serde::{Deserialize, Serialize};

use crate::bundle::HealthConfig;
use crate::charge::{gas_ratio, ObserverParams, Z95};
use crate::error::PhysicsError;
use crate::estimate::Health;
use crate::estimator::HealthMachine;
use crate::log::{RunLog, Sample};

/// The accelerometers' period (SPEC §2), ns.
pub const ACC_DT_NS: i64 = 1_000_000;
/// Accelerometer samples per potentiometer sample (1 kHz / 100 Hz).
pub const POT_PER_ACC: usize = 10;
/// A stream gap longer than this (or time going backwards) restarts the
/// filters, ns.
pub const MAX_GAP_NS: i64 = 1_000_000_000;
/// Atmospheric pressure, bar (the gauge/absolute conversion of the gas law).
pub const P_ATM_BAR: f64 = 1.01325;
/// A block waits this long past its end for the thermocouple's next sample
/// before it is read with the last one, s.
pub const TEMP_WAIT_S: f64 = 2.0;

const NS_PER_S: f64 = 1e9;

/// The filters' constants, written by `train.road_observer fit`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoadFilters {
    /// State transition over one accelerometer period (4×4, rows).
    pub phi1: Vec<Vec<f64>>,
    /// Input gain over one accelerometer period (4).
    pub g1: Vec<f64>,
    /// State transition over one potentiometer period (4×4, rows).
    pub phi: Vec<Vec<f64>>,
    /// Gains of the period's ten inputs (4×10, rows).
    pub gs: Vec<Vec<f64>>,
    /// Steady-state Kalman gain (4).
    pub gain: Vec<f64>,
    /// Steady-state RTS smoother gain (4×4, rows).
    pub smoother: Vec<Vec<f64>>,
    /// The mount and accelerometer filter at `fine` samples per millisecond:
    /// numerator (`lfilter` convention).
    pub mount_b: Vec<f64>,
    /// Its denominator.
    pub mount_a: Vec<f64>,
    /// Force samples per accelerometer sample.
    pub fine: usize,
    /// Damping-law hinges, m/s.
    pub hinges_mps: Vec<f64>,
    /// A block whose stroke velocity RMS is below this is not read, m/s.
    pub min_stroke_rms_mps: f64,
    /// The slowest stroke velocity RMS among the blocks the calibration
    /// read, m/s: a slower block is not read (absent in calibrations fitted
    /// before it: `min_stroke_rms_mps` alone). The friction read falls short
    /// of the calibration's line the slower the stroke (measured down to
    /// 0.04 m/s: about 10 % short at 0.06 m/s, docs/history.md "Nineteenth session"),
    /// and nothing in a calibration at faster strokes says by how much.
    #[serde(default)]
    pub slowest_calibrated_stroke_rms_mps: Option<f64>,
}

fn default_prior_mean() -> f64 {
    6.0
}
fn default_prior_sd() -> f64 {
    6.0
}
fn default_walk() -> f64 {
    1e-4
}

/// A road calibration (`python -m train.road_observer fit`'s JSON); fields
/// not listed here (its held-out reads, campaign) are ignored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoadCalibration {
    /// Friction amplitude at zero gas pressure, N.
    pub a_n: f64,
    /// Friction amplitude per bar of gas pressure, N/bar.
    pub b_n_per_bar: f64,
    /// One block's reading spread, N.
    pub block_sd_n: f64,
    /// Block length, s.
    pub block_s: f64,
    /// Smoother lag after a block's end, s.
    pub lag_s: f64,
    /// Blocks starting within this of the stream's start are not read, s.
    pub settle_s: f64,
    /// Systematic standard deviation, bar.
    pub systematic_sd_bar: f64,
    /// Systematic part relative to the charge (or to its distance from the
    /// baseline's).
    #[serde(default)]
    pub systematic_rel: f64,
    /// Drive-to-drive part of the systematic, bar.
    #[serde(default)]
    pub held_out_sd_bar: f64,
    /// The charge of the unit's baseline drive, bar (after
    /// [`with_baseline`](Self::with_baseline)).
    #[serde(default)]
    pub baseline_bar: Option<f64>,
    /// Prior mean of the charge, bar.
    #[serde(default = "default_prior_mean")]
    pub prior_mean_bar: f64,
    /// Prior standard deviation, bar.
    #[serde(default = "default_prior_sd")]
    pub prior_sd_bar: f64,
    /// The charge's random walk, bar²/s.
    #[serde(default = "default_walk")]
    pub walk_bar2_per_s: f64,
    /// Whether the calibration runs were simulated.
    #[serde(default)]
    pub simulated: bool,
    /// Observer parameters: gas ratio, mount, accelerometer filter, `v_s`.
    pub observer: ObserverParams,
    /// The filters' constants.
    pub filters: RoadFilters,
}

impl RoadCalibration {
    /// Reads a calibration from JSON; `source` names it in errors.
    ///
    /// # Errors
    /// Not JSON, a field missing or out of its domain (a file from before
    /// the streaming constants: fit again).
    pub fn from_json(source: &str, text: &str) -> Result<Self, String> {
        let v: serde_json::Value =
            serde_json::from_str(text).map_err(|e| format!("{source}: not JSON: {e}"))?;
        if v.get("filters").is_none() && (v.get("force").is_some() || v.get("thermal").is_some()) {
            // a helper's trial: physics.json given here read "written by an older fit"
            return Err(format!(
                "{source}: a physics file (`thermal`, `force`: train.fit_physics), not a road \
                 calibration (`python -m train.road_observer fit` writes one)"
            ));
        }
        if v.get("filters").is_none() {
            return Err(format!(
                "{source}: no `filters` section: written by an older `python -m train.road_observer fit`; fit again"
            ));
        }
        let cal: Self = serde_json::from_value(v)
            .map_err(|e| format!("{source}: not a road calibration: {e}"))?;
        cal.validate().map_err(|e| format!("{source}: {e}"))?;
        Ok(cal)
    }

    /// Checks shapes and domains.
    ///
    /// # Errors
    /// The first field out of its domain, named.
    pub fn validate(&self) -> Result<(), String> {
        let f = &self.filters;
        let square = |m: &Vec<Vec<f64>>, r: usize, c: usize| {
            m.len() == r
                && m.iter()
                    .all(|row| row.len() == c && row.iter().all(|x| x.is_finite()))
        };
        let checks: [(&str, bool); 12] = [
            ("filters.phi1", square(&f.phi1, 4, 4)),
            ("filters.phi", square(&f.phi, 4, 4)),
            ("filters.smoother", square(&f.smoother, 4, 4)),
            ("filters.gs", square(&f.gs, 4, POT_PER_ACC)),
            ("filters.g1", f.g1.len() == 4),
            ("filters.gain", f.gain.len() == 4),
            (
                "filters.mount_a",
                !f.mount_a.is_empty() && f.mount_a[0] != 0.0 && f.mount_a.len() >= f.mount_b.len(),
            ),
            ("filters.fine", f.fine >= 1),
            (
                "b_n_per_bar",
                self.b_n_per_bar.is_finite() && self.b_n_per_bar > 0.0,
            ),
            ("block_s", self.block_s.is_finite() && self.block_s >= 0.1),
            ("lag_s", self.lag_s.is_finite() && self.lag_s >= 0.0),
            (
                "block_sd_n / systematic_sd_bar / prior_sd_bar",
                self.block_sd_n > 0.0 && self.systematic_sd_bar >= 0.0 && self.prior_sd_bar > 0.0,
            ),
        ];
        match checks.iter().find(|(_, ok)| !ok) {
            Some((name, _)) => Err(format!(
                "road calibration field `{name}` is missing, malformed or out of its domain"
            )),
            None => self.observer.validate().map_err(|e| e.to_string()),
        }
    }

    /// The calibration for one unit, from its drive at a known charge
    /// `charge_bar` (after a service) read into `blocks`: the seal's offset is
    /// read, so that only the slope's tolerance stays systematic (relative to
    /// the distance from `charge_bar`).
    ///
    /// # Errors
    /// No block was read (no stroke).
    pub fn with_baseline(&self, blocks: &[RoadBlock], charge_bar: f64) -> Result<Self, String> {
        Ok(self.apply(&self.read_baseline(blocks, charge_bar)?))
    }

    /// A unit's baseline from its drive at a known charge `charge_bar` read
    /// into `blocks` (by this calibration, without a baseline).
    ///
    /// # Errors
    /// No block was read (no stroke).
    pub fn read_baseline(
        &self,
        blocks: &[RoadBlock],
        charge_bar: f64,
    ) -> Result<RoadBaseline, String> {
        let mut reading = RoadBaselineReading::new(charge_bar);
        for b in blocks {
            reading.add(self, b);
        }
        reading.baseline()
    }

    /// This calibration for the unit of `baseline`: its seal's offset, and
    /// only the slope's tolerance systematic.
    #[must_use]
    pub fn apply(&self, baseline: &RoadBaseline) -> Self {
        let stat = self.block_sd_n / (baseline.blocks.max(1) as f64).sqrt() / self.b_n_per_bar;
        Self {
            a_n: self.a_n + baseline.offset_n,
            baseline_bar: Some(baseline.charge_bar),
            systematic_sd_bar: self.held_out_sd_bar.hypot(stat),
            ..self.clone()
        }
    }

    /// The prior's 95 % interval (before any block), bar.
    #[must_use]
    pub fn prior_interval(&self) -> (f64, f64) {
        let rel = self.systematic_rel * (self.prior_mean_bar - self.baseline_bar.unwrap_or(0.0));
        let half =
            Z95 * (self.prior_sd_bar.powi(2) + self.systematic_sd_bar.powi(2) + rel * rel).sqrt();
        (self.prior_mean_bar - half, self.prior_mean_bar + half)
    }

    /// One block's charge reading (bar gauge at 20 °C) and its spread, bar.
    #[must_use]
    pub fn charge_of(&self, alpha_n: f64, temp_c: f64) -> (f64, f64) {
        let th = gas_ratio(&self.observer, temp_c, 0.0);
        let p = ((alpha_n - self.a_n) / self.b_n_per_bar + P_ATM_BAR) / th - P_ATM_BAR;
        (p, self.block_sd_n / (self.b_n_per_bar * th))
    }
}

/// One unit's road baseline: what a drive at a known charge (after a
/// service) read of its seal ([`RoadCalibration::read_baseline`]); kept in
/// the daemon's configuration (`[assets.<id>] road_baseline`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoadBaseline {
    /// The charge of the drive, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// The unit's friction offset from the calibration's, N.
    pub offset_n: f64,
    /// Blocks the drive read (the offset's precision).
    pub blocks: u64,
}

impl RoadBaseline {
    /// Checks the domain.
    ///
    /// # Errors
    /// A non-finite value or no block, named.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.charge_bar.is_finite() && self.charge_bar >= 0.0) {
            return Err(format!(
                "road_baseline.charge_bar = {}: a charge in bar, at least 0",
                self.charge_bar
            ));
        }
        if !self.offset_n.is_finite() {
            return Err(format!(
                "road_baseline.offset_n = {}: must be finite",
                self.offset_n
            ));
        }
        if self.blocks == 0 {
            return Err("road_baseline.blocks = 0: a baseline reads at least one block".into());
        }
        Ok(())
    }
}

/// A unit's road baseline read as its drive goes (after a service at a known
/// charge), block by block in O(1): the mean over the blocks of
/// `α_i − (a + b p_g(T_i))`, the seal's offset at `charge_bar`
/// ([`RoadCalibration::read_baseline`] for a whole drive). The blocks must be
/// read by the calibration without a baseline.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RoadBaselineReading {
    charge_bar: f64,
    sum_offset_n: f64,
    blocks: u64,
}

impl RoadBaselineReading {
    /// Nothing read yet, for a unit filled to `charge_bar` (bar gauge at
    /// 20 °C).
    #[must_use]
    pub fn new(charge_bar: f64) -> Self {
        Self {
            charge_bar,
            sum_offset_n: 0.0,
            blocks: 0,
        }
    }

    /// Adds one block read by `cal`.
    pub fn add(&mut self, cal: &RoadCalibration, block: &RoadBlock) {
        let p_g =
            (self.charge_bar + P_ATM_BAR) * gas_ratio(&cal.observer, block.temp_c, 0.0) - P_ATM_BAR;
        self.sum_offset_n += block.alpha_n - (cal.a_n + cal.b_n_per_bar * p_g);
        self.blocks += 1;
    }

    /// The baseline read so far.
    ///
    /// # Errors
    /// No block was read (no stroke).
    pub fn baseline(&self) -> Result<RoadBaseline, String> {
        if self.blocks == 0 {
            return Err("the baseline drive has no block to read (no stroke?)".into());
        }
        Ok(RoadBaseline {
            charge_bar: self.charge_bar,
            offset_n: self.sum_offset_n / self.blocks as f64,
            blocks: self.blocks,
        })
    }
}

/// What the road observer made of a stream's blocks: how many it read and
/// why the others were not read.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RoadCounters {
    /// Blocks read (each updated the estimate).
    pub read: u64,
    /// Not read: within `settle_s` of the stream's start or of a restart.
    pub settling: u64,
    /// Not read: the stroke moved less than `min_stroke_rms_mps` (a rest).
    pub at_rest: u64,
    /// Not read: the stroke slower than the slowest the calibration read
    /// (`slowest_calibrated_stroke_rms_mps`).
    #[serde(default)]
    pub slower_than_calibrated: u64,
    /// Not read: positions at fewer than half its steps (a silent
    /// potentiometer).
    pub without_positions: u64,
    /// Not read: no solution, or a reading that was not finite.
    pub unsolved: u64,
}

impl RoadCounters {
    /// Why no block was read although some were complete, when so: the
    /// estimate then keeps its prior (`unknown`).
    #[must_use]
    pub fn why_none(&self) -> Option<String> {
        if self.read > 0 {
            return None;
        }
        let reasons = [
            (self.at_rest, "the stroke too small (at rest)"),
            (
                self.slower_than_calibrated,
                "the stroke slower than the calibration's slowest (drive faster or on rougher roads, or calibrate there)",
            ),
            (
                self.without_positions,
                "positions at fewer than half its steps (the potentiometer silent)",
            ),
            (self.unsolved, "no solution"),
            (
                self.settling,
                "within the settling time of the drive's start",
            ),
        ];
        let total: u64 = reasons.iter().map(|r| r.0).sum();
        let (n, why) = reasons.iter().max_by_key(|r| r.0)?;
        (*n > 0).then(|| {
            format!("the road observer read none of {total} blocks: {n} with {why}; the estimate keeps its prior")
        })
    }
}

/// One block's reading and the estimate after it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RoadBlock {
    /// The block's last accelerometer sample, ns.
    pub t_ns: i64,
    /// The same, s since the stream's first sample.
    pub t_s: f64,
    /// Friction amplitude, N.
    pub alpha_n: f64,
    /// Its standard deviation from the block's regression alone, N.
    pub alpha_sd_n: f64,
    /// RMS residual of `a2`, m/s².
    pub residual_mps2: f64,
    /// Mean shock temperature over the block, °C.
    pub temp_c: f64,
    /// Stroke velocity RMS, m/s.
    pub stroke_rms_mps: f64,
    /// The block's charge reading, bar gauge at 20 °C.
    pub reading_bar: f64,
    /// Its spread, bar.
    pub reading_sd_bar: f64,
    /// The estimate after this block, bar.
    pub estimate_bar: f64,
    /// Its central 95 % interval, bar.
    pub lo_bar: f64,
    /// Upper end.
    pub hi_bar: f64,
    /// SPEC §6a health after this block.
    pub health: Health,
}

/// The current estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RoadEstimate {
    /// Charge, bar gauge at 20 °C (the prior's mean before any block).
    pub estimate_bar: f64,
    /// Central 95 % interval.
    pub lo_bar: f64,
    /// Upper end.
    pub hi_bar: f64,
    /// Health.
    pub health: Health,
    /// Blocks read so far.
    pub blocks: u64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct AccRow {
    t_s: f64,
    a2: f64,
    u: f64,
}

/// The per-stretch pipeline: restarted by a gap or a clock going backwards.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct Stretch {
    acc0_ns: i64,
    next_j: i64,
    started_s: f64,
    pending_nan: Vec<(i64, f64, f64)>,
    last_finite: Option<(f64, f64)>,
    prev_r: Option<f64>,
    held: Option<(f64, f64, f64)>,
    rows: VecDeque<AccRow>,
    rows_base: i64,
    pos0: Option<(i64, i64)>,
    last_pos_k: i64,
    pos: BTreeMap<usize, f64>,
    xf: VecDeque<Vector4<f64>>,
    /// Whether the step to each state of `xf` had a position.
    updated: VecDeque<bool>,
    xp: VecDeque<Vector4<f64>>,
    x_base: usize,
    next_block: usize,
    zi: Vec<Vec<f64>>,
}

/// The streaming road observer (see the module's documentation);
/// serialisable, so that a checkpointed estimator goes on reading.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RoadObserver {
    cal: RoadCalibration,
    phi1: Matrix4<f64>,
    g1: Vector4<f64>,
    phi: Matrix4<f64>,
    gs: SMatrix<f64, 4, POT_PER_ACC>,
    gain: Vector4<f64>,
    smoother: Matrix4<f64>,
    mount_b: Vec<f64>,
    mount_a: Vec<f64>,
    per_block: usize,
    lag: usize,
    origin_ns: Option<i64>,
    last_acc_ns: i64,
    stretch: Option<Stretch>,
    temps: VecDeque<(f64, f64)>,
    mean: f64,
    var: f64,
    last_t_s: Option<f64>,
    health: HealthMachine,
    blocks: u64,
    out: Vec<RoadBlock>,
    #[serde(default)]
    counters: RoadCounters,
}

/// A block's large buffers (a block's regression is ~10 000 × 150, 35 MB
/// in all): allocated afresh each block, their pages were faulted in and
/// returned every time. One set per thread, lent to whichever observer reads
/// a block there (kept in each observer, a daemon's thousand assets would
/// hold 35 MB each).
#[derive(Debug, Default)]
struct Scratch {
    /// The regressors, column after column (`n_cols × m`).
    cols: Vec<f64>,
    /// The regression's matrix and its transpose (their storage).
    xm: Vec<f64>,
    xt: Vec<f64>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::default();
}

fn mat4(rows: &[Vec<f64>]) -> Matrix4<f64> {
    Matrix4::from_fn(|r, c| rows[r][c])
}

/// `numpy.interp` on sorted `xp` (clamped at both ends), for ascending `x`.
fn interp_sorted(x: &[f64], xp: &[f64], fp: &[f64], out: &mut Vec<f64>) {
    out.clear();
    let mut j = 0;
    for &xi in x {
        while j + 1 < xp.len() && xp[j + 1] <= xi {
            j += 1;
        }
        out.push(if xi <= xp[0] {
            fp[0]
        } else if j + 1 >= xp.len() || xi.total_cmp(&xp[j]).is_eq() {
            fp[j]
        } else {
            (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]) * (xi - xp[j]) + fp[j]
        });
    }
}

impl RoadObserver {
    /// An observer with `cal` and SPEC §6a's health thresholds `health`.
    ///
    /// # Errors
    /// The calibration is out of its domain.
    pub fn new(cal: RoadCalibration, health: HealthConfig) -> Result<Self, String> {
        cal.validate()?;
        let f = &cal.filters;
        let mut mount_b = f.mount_b.clone();
        let mut mount_a = f.mount_a.clone();
        let a0 = mount_a[0];
        for v in mount_b.iter_mut().chain(mount_a.iter_mut()) {
            *v /= a0;
        }
        mount_b.resize(mount_a.len(), 0.0);
        let per_block =
            (cal.block_s / (ACC_DT_NS as f64 / NS_PER_S * POT_PER_ACC as f64)).round() as usize;
        let lag = (cal.lag_s / (ACC_DT_NS as f64 / NS_PER_S * POT_PER_ACC as f64)).round() as usize;
        Ok(Self {
            phi1: mat4(&f.phi1),
            g1: Vector4::from_column_slice(&f.g1),
            phi: mat4(&f.phi),
            gs: SMatrix::from_fn(|r, c| f.gs[r][c]),
            gain: Vector4::from_column_slice(&f.gain),
            smoother: mat4(&f.smoother),
            mount_b,
            mount_a,
            per_block,
            lag,
            origin_ns: None,
            last_acc_ns: i64::MIN,
            stretch: None,
            temps: VecDeque::new(),
            mean: cal.prior_mean_bar,
            var: cal.prior_sd_bar * cal.prior_sd_bar,
            last_t_s: None,
            health: HealthMachine::new(health),
            blocks: 0,
            out: Vec::new(),
            counters: RoadCounters::default(),
            cal,
        })
    }

    /// The calibration in use.
    #[must_use]
    pub fn calibration(&self) -> &RoadCalibration {
        &self.cal
    }

    /// Takes one sample (time order); blocks read because of it are queued
    /// for [`drain`](Self::drain). Topics it does not use are ignored.
    pub fn push(&mut self, sample: &Sample) {
        let t_ns = sample.t_ns();
        let origin = *self.origin_ns.get_or_insert(t_ns);
        let t_s = (t_ns - origin) as f64 / NS_PER_S;
        match *sample {
            Sample::Acceleration {
                a1_mps2, a2_mps2, ..
            } => self.accel(t_ns, t_s, a1_mps2 - a2_mps2, a2_mps2),
            Sample::Position { position_m, .. } => self.position(t_ns, position_m),
            Sample::TempShock { temperature_c, .. } if temperature_c.is_finite() => {
                if self.temps.back().is_none_or(|&(t, _)| t_s > t) {
                    self.temps.push_back((t_s, temperature_c));
                }
                self.advance(false);
            }
            _ => {}
        }
    }

    /// The end of the stream: reads every block whose lag has passed, with
    /// the temperatures there are.
    pub fn finish(&mut self) {
        if let Some(s) = self.stretch.as_mut() {
            for (_, t_s, a2) in std::mem::take(&mut s.pending_nan) {
                let r = s.last_finite.map_or(f64::NAN, |(_, r)| r);
                Self::stage_inverse(&self.cal.observer, s, t_s, r, a2);
            }
            if let Some((t_s, a2, ri)) = s.held.take() {
                s.rows.push_back(AccRow { t_s, a2, u: ri });
            }
        }
        self.advance(true);
    }

    /// What it made of the blocks so far.
    #[must_use]
    pub fn counters(&self) -> RoadCounters {
        self.counters
    }

    /// Blocks read since the last call, oldest first.
    pub fn drain(&mut self) -> Vec<RoadBlock> {
        std::mem::take(&mut self.out)
    }

    /// The estimate now.
    #[must_use]
    pub fn estimate(&self) -> RoadEstimate {
        let (lo, hi) = self.interval();
        RoadEstimate {
            estimate_bar: self.mean,
            lo_bar: lo,
            hi_bar: hi,
            health: self.health.state(),
            blocks: self.blocks,
        }
    }

    fn interval(&self) -> (f64, f64) {
        let c = &self.cal;
        let rel = c.systematic_rel * (self.mean - c.baseline_bar.unwrap_or(0.0));
        let half = Z95 * (self.var + c.systematic_sd_bar * c.systematic_sd_bar + rel * rel).sqrt();
        (self.mean - half, self.mean + half)
    }

    fn accel(&mut self, t_ns: i64, t_s: f64, r: f64, a2: f64) {
        let restart = match &self.stretch {
            None => true,
            Some(s) => {
                let j = (t_ns - s.acc0_ns + ACC_DT_NS / 2).div_euclid(ACC_DT_NS);
                t_ns < self.last_acc_ns || j > s.next_j + MAX_GAP_NS / ACC_DT_NS
            }
        };
        if restart {
            self.restart(t_ns, t_s);
        }
        self.last_acc_ns = self.last_acc_ns.max(t_ns);
        let obs = self.cal.observer;
        let s = self.stretch.as_mut().expect("a stretch is running");
        let j = (t_ns - s.acc0_ns + ACC_DT_NS / 2).div_euclid(ACC_DT_NS);
        if j < s.next_j {
            return; // a duplicate of a slot already taken
        }
        for missing in s.next_j..j {
            let tm = s.started_s + (missing as f64) * ACC_DT_NS as f64 / NS_PER_S;
            s.pending_nan.push((missing, tm, f64::NAN));
        }
        s.next_j = j + 1;
        if r.is_finite() {
            for (_, tq, a2q) in std::mem::take(&mut s.pending_nan) {
                let rq = match s.last_finite {
                    Some((tl, rl)) => (r - rl) / (t_s - tl) * (tq - tl) + rl,
                    None => r,
                };
                Self::stage_inverse(&obs, s, tq, rq, a2q);
            }
            s.last_finite = Some((t_s, r));
            Self::stage_inverse(&obs, s, t_s, r, a2);
        } else {
            s.pending_nan.push((j, t_s, a2));
        }
        if s.pos0.is_none() {
            // no position yet: keep two seconds of rows, not the whole drive
            while s.rows.len() > 2_000 {
                s.rows.pop_front();
                s.rows_base += 1;
            }
        }
        self.advance(false);
    }

    /// The accelerometers' filter inverted, then each millisecond's mean.
    fn stage_inverse(obs: &ObserverParams, s: &mut Stretch, t_s: f64, r: f64, a2: f64) {
        let ri = match s.prev_r {
            Some(prev) => {
                r + (r - prev) / (2.0 * PI * obs.accel_bw_hz * (ACC_DT_NS as f64 / NS_PER_S))
            }
            None => r,
        };
        s.prev_r = Some(r);
        if let Some((th, a2h, rh)) = s.held.replace((t_s, a2, ri)) {
            s.rows.push_back(AccRow {
                t_s: th,
                a2: a2h,
                u: 0.5 * (ri + rh),
            });
        }
    }

    fn restart(&mut self, t_ns: i64, t_s: f64) {
        self.stretch = Some(Stretch {
            acc0_ns: t_ns,
            started_s: t_s,
            last_pos_k: -1,
            ..Stretch::default()
        });
        self.last_acc_ns = t_ns;
    }

    fn position(&mut self, t_ns: i64, y: f64) {
        let Some(s) = self.stretch.as_mut() else {
            return; // the filter starts at a position after the accelerometers' first sample
        };
        let pot_ns = ACC_DT_NS * POT_PER_ACC as i64;
        let p0_ns = if let Some((p0, _)) = s.pos0 {
            p0
        } else {
            if !y.is_finite() || t_ns < s.acc0_ns - 1_000 {
                return;
            }
            // the first accelerometer slot at or after the position (numpy's searchsorted)
            let j0 = (t_ns - 1_000 - s.acc0_ns + ACC_DT_NS - 1).div_euclid(ACC_DT_NS);
            if j0 < s.rows_base {
                return; // older than the rows kept: start at a later position
            }
            s.pos0 = Some((t_ns, j0));
            t_ns
        };
        let k = (t_ns - p0_ns + pot_ns / 2).div_euclid(pot_ns);
        if k <= s.last_pos_k || (k as usize) < s.x_base + s.xf.len() {
            return; // a repeat, or too late: its step was taken without it
        }
        s.last_pos_k = k;
        s.pos.insert(k as usize, y);
        self.advance(false);
    }

    /// Runs the forward filter as far as its inputs allow, then reads every
    /// block whose lag has passed.
    fn advance(&mut self, finishing: bool) {
        loop {
            if !self.step_forward(finishing) {
                break;
            }
        }
        while self.block_ready(finishing) {
            self.read_block();
        }
    }

    /// One potentiometer step of the forward filter, if its inputs are in.
    fn step_forward(&mut self, finishing: bool) -> bool {
        let Some(s) = self.stretch.as_mut() else {
            return false;
        };
        let Some((_, j0)) = s.pos0 else {
            return false;
        };
        if s.xf.is_empty() {
            let Some(&z0) = s.pos.get(&0) else {
                return false;
            };
            let x = Vector4::new(z0, 0.0, 0.0, z0);
            s.xf.push_back(x);
            s.xp.push_back(x);
            s.updated.push_back(true);
            s.x_base = 0;
        }
        let k = s.x_base + s.xf.len() - 1; // the last filtered step
        let first = j0 + (k * POT_PER_ACC) as i64;
        let last_row = s.rows_base + s.rows.len() as i64 - 1;
        if last_row < first + POT_PER_ACC as i64 - 1 || first < s.rows_base {
            return false;
        }
        // a position not in by 20 ms after its time is missing: a step without update
        // (at the stream's end, no step past its last position)
        let z = match s.pos.get(&(k + 1)) {
            Some(&z) => z,
            None if s.last_pos_k > (k + 1) as i64 => f64::NAN,
            None if !finishing && last_row >= first + 3 * POT_PER_ACC as i64 => f64::NAN,
            None => return false,
        };
        let off = (first - s.rows_base) as usize;
        let u = SMatrix::<f64, POT_PER_ACC, 1>::from_fn(|i, _| s.rows[off + i].u);
        let x = *s.xf.back().expect("started");
        let p = self.phi * x + self.gs * u;
        let xn = if z.is_finite() {
            p + self.gain * (z - p[3])
        } else {
            p
        };
        s.xp.push_back(p);
        s.xf.push_back(xn);
        s.updated.push_back(z.is_finite());
        s.pos.remove(&k);
        true
    }

    fn block_ready(&self, finishing: bool) -> bool {
        let Some(s) = &self.stretch else {
            return false;
        };
        let Some((_, j0)) = s.pos0 else {
            return false;
        };
        let k0 = s.next_block * self.per_block;
        if s.xf.is_empty() || s.x_base + s.xf.len() <= k0 + self.per_block + self.lag {
            return false;
        }
        let last = j0 + ((k0 + self.per_block) * POT_PER_ACC) as i64 - 1;
        let t_end = s.rows[(last - s.rows_base) as usize].t_s;
        finishing
            || self.temps.back().is_some_and(|&(t, _)| t >= t_end)
            || s.rows.back().is_some_and(|r| r.t_s > t_end + TEMP_WAIT_S)
    }

    fn read_block(&mut self) {
        let (per_block, lag) = (self.per_block, self.lag);
        let s = self.stretch.as_mut().expect("ready");
        let (_, j0) = s.pos0.expect("ready");
        let k0 = s.next_block * per_block;
        s.next_block += 1;
        // smooth back from the lag's end, keep the block's 1 + per_block states
        let i0 = k0 - s.x_base;
        let n = per_block + lag;
        let mut xs = vec![Vector4::zeros(); n + 1];
        xs[n] = s.xf[i0 + n];
        for k in (0..n).rev() {
            xs[k] = s.xf[i0 + k] + self.smoother * (xs[k + 1] - s.xp[i0 + k + 1]);
        }
        // every millisecond between the smoothed samples
        let off = (j0 + (k0 * POT_PER_ACC) as i64 - s.rows_base) as usize;
        let m = per_block * POT_PER_ACC;
        let rows: Vec<AccRow> = s.rows.range(off..off + m).copied().collect();
        let mut x = Vec::with_capacity(m);
        for i in 0..per_block {
            let mut cur = [Vector4::zeros(); POT_PER_ACC + 1];
            cur[0] = xs[i];
            for j in 0..POT_PER_ACC {
                cur[j + 1] = self.phi1 * cur[j] + self.g1 * rows[i * POT_PER_ACC + j].u;
            }
            let miss = xs[i + 1] - cur[POT_PER_ACC];
            for (j, c) in cur.iter().take(POT_PER_ACC).enumerate() {
                x.push(c + miss * (j as f64 / POT_PER_ACC as f64));
            }
        }
        // a block with positions at fewer than half its steps is not read (a dead potentiometer)
        let positions = s
            .updated
            .range(i0 + 1..=i0 + per_block)
            .filter(|&&u| u)
            .count();
        // drop what no later block needs
        let keep_from = k0 + per_block;
        while s.x_base < keep_from {
            s.xf.pop_front();
            s.xp.pop_front();
            s.updated.pop_front();
            s.x_base += 1;
        }
        let keep_rows = j0 + (keep_from * POT_PER_ACC) as i64;
        while s.rows_base < keep_rows && !s.rows.is_empty() {
            s.rows.pop_front();
            s.rows_base += 1;
        }
        let t: Vec<f64> = rows.iter().map(|r| r.t_s).collect();
        let mut scratch = SCRATCH.with_borrow_mut(std::mem::take);
        let mut cols = std::mem::take(&mut scratch.cols);
        self.columns(&t, &x, &mut cols);
        let stroke = (x.iter().map(|v| v[1] * v[1]).sum::<f64>() / m as f64).sqrt();
        let started = self.stretch.as_ref().expect("running").started_s;
        let t_end = t[m - 1];
        let temp_c = self.mean_temp(&t);
        while self.temps.len() > 1 && self.temps[1].0 <= t_end {
            self.temps.pop_front();
        }
        let skip = if t[0] - started < self.cal.settle_s {
            Some(&mut self.counters.settling)
        } else if stroke < self.cal.filters.min_stroke_rms_mps {
            Some(&mut self.counters.at_rest)
        } else if self
            .cal
            .filters
            .slowest_calibrated_stroke_rms_mps
            .is_some_and(|slowest| stroke < slowest)
        {
            Some(&mut self.counters.slower_than_calibrated)
        } else if 2 * positions < per_block {
            Some(&mut self.counters.without_positions)
        } else {
            None
        };
        let skip = skip.map(|n| *n += 1).is_some();
        let a2: Vec<f64> = rows.iter().map(|r| r.a2).collect();
        let read = (!skip)
            .then(|| regress(&cols, m, &a2, &mut scratch))
            .flatten();
        scratch.cols = cols;
        SCRATCH.with_borrow_mut(|s| *s = scratch);
        let Some((alpha, alpha_sd, resid)) = read else {
            self.counters.unsolved += u64::from(!skip);
            return;
        };
        let origin = self.origin_ns.expect("samples seen");
        self.update(RoadBlock {
            t_ns: origin + (t_end * NS_PER_S).round() as i64,
            t_s: t_end,
            alpha_n: alpha,
            alpha_sd_n: alpha_sd,
            residual_mps2: resid,
            temp_c,
            stroke_rms_mps: stroke,
            reading_bar: f64::NAN,
            reading_sd_bar: f64::NAN,
            estimate_bar: f64::NAN,
            lo_bar: f64::NAN,
            hi_bar: f64::NAN,
            health: Health::Unknown,
        });
    }

    /// The regressors at the accelerometer's samples, into `cols` (column
    /// after column, `t.len()` rows each): the force basis at `fine` samples
    /// per millisecond through the mount's filter (state kept from block to
    /// block), then sampled.
    fn columns(&mut self, t: &[f64], x: &[Vector4<f64>], cols: &mut Vec<f64>) {
        let fine = self.cal.filters.fine;
        let m = t.len();
        let dt = ACC_DT_NS as f64 / NS_PER_S;
        let tf: Vec<f64> = (0..m * fine)
            .map(|q| t[0] + (q as f64 * dt) / fine as f64)
            .collect();
        let (mut vf, mut yf) = (Vec::new(), Vec::new());
        let v: Vec<f64> = x.iter().map(|s| s[1]).collect();
        let y: Vec<f64> = x.iter().map(|s| s[0]).collect();
        interp_sorted(&tf, t, &v, &mut vf);
        interp_sorted(&tf, t, &y, &mut yf);
        let hinges = &self.cal.filters.hinges_mps;
        let n_law = 2 + 2 * hinges.len();
        let n_cols = 1 + 2 * n_law + 1;
        let order = self.mount_a.len();
        let s = self.stretch.as_mut().expect("running");
        // the filter's state, one row per delay and one entry per column
        if s.zi.len() != order - 1 || s.zi.first().is_some_and(|z| z.len() != n_cols) {
            s.zi = vec![vec![0.0; n_cols]; order - 1];
        }
        let vs = self.cal.observer.friction_v_smooth_mps;
        cols.clear();
        cols.resize(n_cols * m, 0.0);
        let (b, a) = (&self.mount_b, &self.mount_a);
        let (mut f, mut out) = (vec![0.0; n_cols], vec![0.0; n_cols]);
        for q in 0..m * fine {
            // the force basis at this instant: friction, the law, its drift, the gas spring
            let (v, tau) = (vf[q], tf[q] / 100.0);
            f[0] = (v / vs).tanh();
            f[1] = v.max(0.0);
            f[2] = v.min(0.0);
            for (k, h) in hinges.iter().enumerate() {
                f[3 + k] = (v - h).max(0.0);
                f[3 + hinges.len() + k] = (v + h).min(0.0);
            }
            for k in 0..n_law {
                f[1 + n_law + k] = f[1 + k] * tau;
            }
            f[n_cols - 1] = yf[q];
            // scipy.signal.lfilter's transposed direct form II, every column at once
            if let [z0, z1, z2] = &mut s.zi[..] {
                // the mount and the accelerometer's filter: third order (the same sums as
                // `lfilter_step`); slices of one length and the coefficients in locals, so
                // that the columns go through in SIMD lanes (each column's arithmetic, and
                // so every bit, unchanged)
                let (z0, z1, z2) = (&mut z0[..n_cols], &mut z1[..n_cols], &mut z2[..n_cols]);
                let (fs, os) = (&f[..n_cols], &mut out[..n_cols]);
                let (b0, b1, b2, b3) = (b[0], b[1], b[2], b[3]);
                let (a1, a2, a3) = (a[1], a[2], a[3]);
                for c in 0..n_cols {
                    let fc = fs[c];
                    let y = b0 * fc + z0[c];
                    z0[c] = z1[c] + b1 * fc - a1 * y;
                    z1[c] = z2[c] + b2 * fc - a2 * y;
                    z2[c] = 0.0 + b3 * fc - a3 * y;
                    os[c] = y;
                }
            } else {
                lfilter_step(b, a, &mut s.zi, &f, &mut out);
            }
            if q % fine == 0 {
                let row = q / fine;
                for (c, o) in out.iter().enumerate() {
                    cols[c * m + row] = *o;
                }
            }
        }
    }

    fn mean_temp(&self, t: &[f64]) -> f64 {
        if self.temps.is_empty() {
            return f64::NAN;
        }
        let (tt, tv): (Vec<f64>, Vec<f64>) = self.temps.iter().copied().unzip();
        let mut out = Vec::new();
        interp_sorted(t, &tt, &tv, &mut out);
        out.iter().sum::<f64>() / out.len() as f64
    }

    /// The random walk updated by a block's reading; health at its end.
    fn update(&mut self, mut b: RoadBlock) {
        let (p, sd) = self.cal.charge_of(b.alpha_n, b.temp_c);
        if !(p.is_finite() && sd.is_finite()) {
            self.counters.unsolved += 1;
            return;
        }
        self.counters.read += 1;
        let last = *self.last_t_s.get_or_insert(b.t_s);
        self.var += self.cal.walk_bar2_per_s * (b.t_s - last).max(0.0);
        self.last_t_s = Some(b.t_s);
        let k = self.var / (self.var + sd * sd);
        self.mean += k * (p - self.mean);
        self.var *= 1.0 - k;
        let (lo, hi) = self.interval();
        b.reading_bar = p;
        b.reading_sd_bar = sd;
        b.estimate_bar = self.mean;
        b.lo_bar = lo;
        b.hi_bar = hi;
        b.health = self.health.update_interval(b.t_ns, self.mean, lo, hi, true);
        self.blocks += 1;
        self.out.push(b);
    }
}

/// One sample of every column through the filter (`lfilter`'s transposed
/// direct form II, any order; `zi` one row per delay).
fn lfilter_step(b: &[f64], a: &[f64], zi: &mut [Vec<f64>], f: &[f64], out: &mut [f64]) {
    for c in 0..f.len() {
        out[c] = b[0] * f[c] + zi.first().map_or(0.0, |z| z[c]);
    }
    for k in 0..zi.len() {
        let (head, tail) = zi.split_at_mut(k + 1);
        let zk = &mut head[k];
        let next = tail.first();
        for c in 0..f.len() {
            zk[c] = next.map_or(0.0, |z| z[c]) + b[k + 1] * f[c] - a[k + 1] * out[c];
        }
    }
}

/// Refuses a run whose metadata says it is a dyno sine run (`excitation`
/// `sine …`): the road observer reads road drives, and read a healthy 6 bar
/// unit's 1 Hz sine as `leak` (sixty-second session). The batch
/// [`read_run`] and the daemon's road assets both ask.
///
/// # Errors
/// [`PhysicsError::NotARoadRun`], naming the run and its excitation.
pub fn refuse_dyno_run(meta: &crate::log::RunMetadata) -> Result<(), PhysicsError> {
    match meta
        .excitation
        .as_deref()
        .filter(|e| e.trim_start().to_ascii_lowercase().starts_with("sine"))
    {
        Some(excitation) => Err(PhysicsError::NotARoadRun {
            run_id: meta.run_id.clone(),
            excitation: excitation.to_owned(),
        }),
        None => Ok(()),
    }
}

/// Every block of a recorded run, read as the stream would be (then
/// [`RoadObserver::finish`]).
///
/// # Errors
/// The run lacks `/acceleration`, `/position` or `/temperature/shock`
/// (named); its metadata says it is a dyno sine run (`excitation`
/// `sine …`); the calibration is out of its domain.
pub fn read_run(
    log: &RunLog,
    cal: &RoadCalibration,
    health: HealthConfig,
) -> Result<Vec<RoadBlock>, PhysicsError> {
    read_run_counted(log, cal, health).map(|(blocks, _)| blocks)
}

/// [`read_run`], with what the observer made of the run's blocks (why it
/// read none, when so).
///
/// # Errors
/// As [`read_run`].
pub fn read_run_counted(
    log: &RunLog,
    cal: &RoadCalibration,
    health: HealthConfig,
) -> Result<(Vec<RoadBlock>, RoadCounters), PhysicsError> {
    refuse_dyno_run(&log.metadata)?;
    let missing: Vec<String> = [
        ("/acceleration", log.acceleration.is_empty()),
        ("/position", log.position.is_empty()),
        ("/temperature/shock", log.temp_shock.is_empty()),
    ]
    .into_iter()
    .filter(|&(_, empty)| empty)
    .map(|(t, _)| t.to_owned())
    .collect();
    if !missing.is_empty() {
        return Err(PhysicsError::MissingTopics {
            run_id: log.metadata.run_id.clone(),
            missing,
            groups: vec!["road observer".to_owned()],
        });
    }
    let mut obs =
        RoadObserver::new(cal.clone(), health).map_err(|what| PhysicsError::Numerical {
            model: "road calibration",
            t_ns: 0,
            what,
        })?;
    let mut out = Vec::new();
    for (k, s) in log.samples_in_order().enumerate() {
        if crate::cancel::requested_at(k) {
            break; // nobody waits for it any more (`cancel`)
        }
        obs.push(&s);
        out.append(&mut obs.drain());
    }
    obs.finish();
    out.append(&mut obs.drain());
    Ok((out, obs.counters()))
}

/// Least squares of `a2` on the columns (`cols`: column after column, `m`
/// rows each; friction first) and a constant over the rows where `a2` is
/// finite; columns that are zero there are left out. Returns `α`, its
/// standard deviation and the residuals' RMS. `scratch` lends the matrices'
/// storage.
///
/// The columns are scaled to unit norm (which leaves the solution's
/// condition about 10⁴–10⁵ on a road); the normal equations are formed by a
/// matrix product (nalgebra's blocked `gemm`) and solved by Cholesky, then
/// refined once with the residual (corrected semi-normal equations: the
/// accuracy of a QR solution at a tenth of its cost). When the Gram matrix
/// is not positive definite in floating point, Householder QR of the rows
/// instead.
fn regress(cols: &[f64], m: usize, a2: &[f64], scratch: &mut Scratch) -> Option<(f64, f64, f64)> {
    let col = |c: usize| &cols[c * m..(c + 1) * m];
    let good: Vec<usize> = (0..a2.len()).filter(|&i| a2[i].is_finite()).collect();
    let every_row = good.len() == m;
    let active: Vec<usize> = (0..cols.len() / m)
        .filter(|&c| {
            c == 0
                || if every_row {
                    col(c).iter().any(|x| x.abs() > 1e-12)
                } else {
                    good.iter().any(|&i| col(c)[i].abs() > 1e-12)
                }
        })
        .collect();
    let (n, p) = (good.len(), active.len() + 1);
    if n <= p {
        return None;
    }
    let mut data = std::mem::take(&mut scratch.xm);
    data.clear();
    for &c in &active {
        if every_row {
            data.extend_from_slice(col(c));
        } else {
            data.extend(good.iter().map(|&i| col(c)[i]));
        }
    }
    data.resize(n * p, 1.0);
    let mut xm = DMatrix::from_vec(n, p, data);
    let scale: Vec<f64> = (0..p)
        .map(|c| {
            let norm = xm.column(c).norm();
            if norm > 0.0 {
                1.0 / norm
            } else {
                1.0
            }
        })
        .collect();
    for (c, k) in scale.iter().enumerate() {
        xm.column_mut(c).scale_mut(*k);
    }
    let rhs = DVector::from_iterator(n, good.iter().map(|&i| a2[i]));
    let mut xt_data = std::mem::take(&mut scratch.xt);
    xt_data.resize(n * p, 0.0);
    let mut xt = DMatrix::from_vec(p, n, xt_data);
    xm.transpose_to(&mut xt);
    let solved = semi_normal(&xm, &xt, &rhs).or_else(|| householder(&xm, &rhs));
    let out = solved.map(|(coef, w)| {
        let resid = &rhs - &xm * &coef;
        let s2 = resid.norm_squared() / (n - p) as f64;
        (coef[0] * scale[0], (s2 * w).sqrt() * scale[0], s2.sqrt())
    });
    scratch.xm = xm.data.into();
    scratch.xt = xt.data.into();
    out.filter(|o| o.0.is_finite() && o.1.is_finite())
}

/// Solution and `(XᵀX)⁻¹₀₀` by Cholesky of the Gram matrix, refined once.
fn semi_normal(
    xm: &DMatrix<f64>,
    xt: &DMatrix<f64>,
    rhs: &DVector<f64>,
) -> Option<(DVector<f64>, f64)> {
    let chol = (xt * xm).cholesky()?;
    let mut coef = chol.solve(&(xt * rhs));
    let r = rhs - xm * &coef;
    coef += chol.solve(&(xt * r));
    let mut e0 = DVector::zeros(xm.ncols());
    e0[0] = 1.0;
    let w = chol.l().solve_lower_triangular(&e0)?;
    Some((coef, w.norm_squared()))
}

/// Solution and `(XᵀX)⁻¹₀₀` by Householder QR.
fn householder(xm: &DMatrix<f64>, rhs: &DVector<f64>) -> Option<(DVector<f64>, f64)> {
    let p = xm.ncols();
    let qr = xm.clone().qr();
    let mut qtb = rhs.clone();
    qr.q_tr_mul(&mut qtb);
    let r = qr.r();
    let coef = r.solve_upper_triangular(&qtb.rows(0, p).into_owned())?;
    let mut e0 = DVector::zeros(p);
    e0[0] = 1.0;
    let w = r.transpose().solve_lower_triangular(&e0)?;
    Some((coef, w.norm_squared()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interp_matches_numpy_semantics() {
        let xp = [0.0, 1.0, 2.0];
        let fp = [1.0, 3.0, 2.0];
        let mut out = Vec::new();
        interp_sorted(&[-1.0, 0.0, 0.5, 1.0, 1.5, 2.0, 3.0], &xp, &fp, &mut out);
        assert_eq!(out, vec![1.0, 1.0, 2.0, 3.0, 2.5, 2.0, 2.0]);
    }

    #[test]
    fn regression_recovers_a_planted_coefficient() {
        // a2 = 2.5 c0 − 1.0 c1 + 0.3 exactly: α = 2.5, no residual
        let c0: Vec<f64> = (0..200).map(|i| (f64::from(i) * 0.1).sin()).collect();
        let c1: Vec<f64> = (0..200).map(|i| (f64::from(i) * 0.037).cos()).collect();
        let zero = vec![0.0; 200];
        let mut a2: Vec<f64> = (0..200).map(|i| 2.5 * c0[i] - c1[i] + 0.3).collect();
        a2[7] = f64::NAN;
        let cols = [c0, c1, zero].concat();
        let (alpha, sd, resid) =
            regress(&cols, 200, &a2, &mut Scratch::default()).expect("solvable");
        assert!((alpha - 2.5).abs() < 1e-12, "{alpha}");
        assert!(sd < 1e-12 && resid < 1e-12);
    }
}
