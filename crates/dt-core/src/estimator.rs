//! The incremental estimator: one per asset, fed samples as they arrive,
//! one [`Estimate`] out per 50 Hz tick (SPEC §2 `/estimate`, §6 health).
//!
//! ```text
//! samples (any interleaving) ─► re-order window ─► FeaturePipeline ─► row ─► MLP (bundle)
//!                                   │ late: counted, dropped                      │
//!                                   │ clock jump: new segment                     ▼
//!                                                   1 s moving average ─► health state machine
//! ```
//!
//! - **Re-ordering.** Samples are held in a buffer sorted by
//!   `(t_ns, topic rank, arrival)` and released once the newest time seen is
//!   at least `reorder_window_ns` past them, so the pipeline sees exactly the
//!   order of [`crate::features::sorted_samples`]; that is why batch features
//!   (`compute_features`, the Python `features`) and streaming agree. A
//!   sample that arrives less than the window after the newest one seen is
//!   never late. A sample ordered before the last released one is late:
//!   counted and dropped (a backward clock jump is late data). In-order
//!   arrivals cost O(1); an out-of-order one a binary search and a short move.
//! - **Clock jumps.** A forward jump of more than `max_gap_ns` between
//!   released samples (a logger restart, a lost link) starts a new segment:
//!   a fresh pipeline (new tick origin), average and health (`unknown` until
//!   excited again), which takes over the damper's slow state — its heat,
//!   carried through the gap by the thermal model, and the charge
//!   observer's reading ([`FeaturePipeline::carry_over`]). Counted. A sample that far ahead of the newest one is
//!   first held aside: the jump is taken once [`JUMP_CONFIRM`] samples
//!   agree on the new time; if the stream goes on at its old time instead,
//!   the held samples were corrupt timestamps — counted as
//!   `timestamp_outliers` and dropped, so one bad time cannot make the rest
//!   of a run "late".
//! - **Inputs the suite lacks** never reach the pipeline: it is built with the
//!   topics that the bundle's groups need, so a model uses only its suite's
//!   sensors (the batch path does the same, see `compute_features`).
//! - **Pressure.** The network reads the permutation's columns of the row; a
//!   row with a non-finite input gives a NaN pressure (a sensor not yet seen)
//!   and is counted.
//! - **1 s average**: the mean of the finite pressures of the *usable* ticks
//!   among the last 50: excited (1 s velocity RMS ≥ `min_excitation_mps`)
//!   and fresh (every fast channel of the suite — loadcell, potentiometer,
//!   accelerometers — had a sample in the tick; a held value from a dropout
//!   is not averaged). NaN when no tick of the last second is usable.
//! - **Health** ([`HealthMachine`], SPEC §6) is judged on the 1 s average:
//!   `leak` below the fault threshold, `low` below the warn threshold, else
//!   `ok`; a state is left only when the average is `hysteresis_bar` past its
//!   threshold, and a new state is reported only after it has been the
//!   candidate for `dwell_s`. Without excitation or without an average (no
//!   usable data in the last second) the candidate is `unknown`.
//! - **The physical floor.** A gas charge does not leak below ambient, 0 bar
//!   gauge: when the 95 % interval reaches above 0, its lower bound and the
//!   estimate and average are reported no lower than 0 ([`at_ambient_floor`];
//!   health is judged before, and no verdict changes, the thresholds being
//!   above 0). A truth at or above 0 inside the interval is inside the floored
//!   one, and a floored estimate is never further from it. An interval wholly
//!   below 0 is reported as read: the model does not hold for the unit, and
//!   that is shown, not hidden at 0. Without an interval nothing is floored.

use std::collections::VecDeque;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::bundle::{Bundle, BundleError, HealthConfig};
use crate::charge::Z95;
use crate::error::PhysicsError;
use crate::estimate::{Estimate, Health};
use crate::features::{
    col, column_indices, FeaturePipeline, GapCounters, Group, TickRow, TopicSet,
    EXCITATION_WINDOW_TICKS, N_COLUMNS,
};
use crate::log::Sample;
use crate::params::PhysicsParams;
use crate::road::{
    RoadBaseline, RoadBaselineReading, RoadBlock, RoadCalibration, RoadEstimate, RoadObserver,
};

/// Errors of the estimator (a bad bundle or a numerical failure).
#[derive(Debug, thiserror::Error)]
pub enum EstimatorError {
    /// The bundle's network failed.
    #[error(transparent)]
    Bundle(#[from] BundleError),
    /// The physics failed.
    #[error(transparent)]
    Physics(#[from] PhysicsError),
}

/// Version of the [`Estimator::checkpoint`] encoding.
pub const CHECKPOINT_FORMAT: u32 = 1;

/// A checkpoint could not be restored.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Not a checkpoint (truncated, corrupted, another encoding).
    #[error("not an estimator checkpoint: {0}")]
    Decode(String),
    /// Another checkpoint format version.
    #[error("estimator checkpoint format {0}, this build reads {CHECKPOINT_FORMAT}")]
    Format(u32),
    /// Taken with another model bundle.
    #[error("the checkpoint was taken with model {checkpoint}, the bundle is {bundle}")]
    Model {
        /// The checkpoint's model digest.
        checkpoint: String,
        /// The bundle's.
        bundle: String,
    },
}

#[derive(Serialize)]
struct CheckpointRef<'a> {
    format: u32,
    model: String,
    state: &'a EstimatorState,
}

#[derive(Deserialize)]
struct Checkpoint {
    format: u32,
    model: String,
    state: EstimatorState,
}

/// SHA-256 (hex, first 16 bytes) of the bundle's `twin.json` contents: the
/// model a checkpoint belongs to (the network file's digest is in it when
/// the bundle records one).
#[must_use]
pub fn model_digest(bundle: &Bundle) -> String {
    use sha2::{Digest, Sha256};
    use std::fmt::Write as _;
    let json = serde_json::to_vec(&bundle.twin).unwrap_or_default();
    Sha256::digest(&json)[..16]
        .iter()
        .fold(String::with_capacity(32), |mut s, b| {
            let _ = write!(s, "{b:02x}");
            s
        })
}

/// Samples (within `max_gap_ns` of each other) that must agree on a forward
/// clock jump before it is taken; fewer are timestamp outliers.
pub const JUMP_CONFIRM: usize = 5;

/// Per-asset settings of an estimator.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EstimatorConfig {
    /// The asset's nominal charge pressure (`expected_bar`), bar gauge.
    pub nominal_bar: f64,
    /// Health thresholds and timing.
    pub health: HealthConfig,
    /// Samples are held this long for re-ordering, ns (the estimate latency).
    pub reorder_window_ns: i64,
    /// A forward gap longer than this starts a new segment, ns.
    pub max_gap_ns: i64,
    /// This unit's reading at a known charge, for the charge observer
    /// ([`crate::charge::UnitBaseline`]); `None`: the model's spread alone.
    #[serde(default)]
    pub observer_baseline: Option<crate::charge::UnitBaseline>,
    /// Fit every reversal's window, whatever the observer's
    /// [`fit_gain_floor`](crate::charge::ObserverParams::fit_gain_floor)
    /// says: a run that reads the unit's baseline after a service, whose sd
    /// is what the unit will be conditioned on.
    #[serde(default)]
    pub observer_fit_all: bool,
    /// The unit's own damping law for a run read without a baseline
    /// ([`ObserverParams::with_unit_law`](crate::charge::ObserverParams::with_unit_law)):
    /// a service reading takes the law of the unit's baseline before the
    /// service. Not used when [`observer_baseline`](Self::observer_baseline)
    /// is set (a baseline carries its own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observer_damping_law: Option<crate::charge::DampingLaw>,
    /// The unit's baseline before the service a run reads: the baseline
    /// read keeps its readings at other excitations
    /// ([`UnitBaseline::keeping_readings_of`](crate::charge::UnitBaseline::keeping_readings_of)).
    /// Not used by the estimator itself.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observer_service_earlier: Option<crate::charge::UnitBaseline>,
}

impl EstimatorConfig {
    /// The bundle's nominal pressure and thresholds; a 100 ms re-order window
    /// and a 2 s gap limit.
    #[must_use]
    pub fn from_bundle(bundle: &Bundle) -> Self {
        Self {
            nominal_bar: bundle.twin.nominal_bar,
            health: bundle.twin.health,
            reorder_window_ns: 100_000_000,
            max_gap_ns: 2_000_000_000,
            observer_baseline: None,
            observer_fit_all: false,
            observer_damping_law: None,
            observer_service_earlier: None,
        }
    }
}

/// What an estimator has counted so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct EstimatorCounters {
    /// Samples taken by [`Estimator::push`] (incl. late and held ones).
    pub samples: u64,
    /// Samples ordered before the last released one: dropped.
    pub late_dropped: u64,
    /// Samples that arrived out of time order but inside the window (re-ordered).
    pub reordered: u64,
    /// Forward clock jumps that started a new segment.
    pub clock_jumps: u64,
    /// Samples far ahead of the stream that the stream did not follow
    /// (corrupt timestamps): dropped.
    pub timestamp_outliers: u64,
    /// Ticks emitted.
    pub ticks: u64,
    /// Ticks whose network inputs were not all finite (pressure NaN).
    pub ticks_without_inputs: u64,
    /// Ticks left out of the 1 s average because a fast channel of the suite
    /// had no sample in them (a dropout; the pipeline held its value).
    pub ticks_stale: u64,
    /// Non-finite samples skipped by the pipeline (all segments).
    pub missing_samples: u64,
    /// What the charge observer made of the velocity reversals, all
    /// segments (zero when the bundle does not read it).
    #[serde(default)]
    pub observer: crate::charge::ObserverCounters,
    /// What the road observer made of the blocks, on a road asset
    /// ([`Estimator::with_road`]).
    #[serde(default)]
    pub road: Option<crate::road::RoadCounters>,
    /// Ticks on which a fast channel had no sample (held value), summed over
    /// the loadcell, potentiometer and accelerometers, all segments.
    pub gaps: u64,
}

/// One emitted tick: the estimate and the pipeline's full feature row (all
/// [`crate::features::COLUMNS`]; the network read the bundle's columns of it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tick {
    /// The `/estimate` fields.
    pub estimate: Estimate,
    /// The feature row and the twin's state at the tick.
    pub row: TickRow,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct Queued {
    key: (i64, u8),
    sample: Sample,
}

/// Vacuum as a gauge pressure, bar (SPEC §1: charges are bar gauge): no
/// charge a damper holds reads below it.
pub const VACUUM_GAUGE_BAR: f64 = -crate::params::P_ATM_PA / 1e5;

/// The health state machine of SPEC §6 and §6a, fed one tick at a time.
///
/// Without an interval (a bundle with neither the charge observer nor a
/// held-out interval, [`crate::bundle::HeldOutInterval`]), the *level*
/// of a 1 s average is `leak` below `fault_bar`, `low` below `warn_bar`, else
/// `ok`, with hysteresis around the reported state: `leak` is left only at
/// `fault_bar + hysteresis_bar`, `low` (upwards) only at
/// `warn_bar + hysteresis_bar`.
///
/// With the central 95 % interval `[lo, hi]` of the 1 s average (SPEC §6a)
/// the level is `leak` when `hi < fault`, else `low` when `hi < warn`, else
/// `ok` when `lo > warn`, else `unknown` (the interval straddles a
/// threshold); an interval wholly below vacuum is `unknown` too
/// ([`HealthMachine::level_interval`]). Hysteresis: in state `leak` the fault threshold is
/// `fault_bar + hysteresis_bar`, in `leak` or `low` the warn threshold for
/// `hi` is `warn_bar + hysteresis_bar`, and in `ok` the warn threshold for
/// `lo` is `warn_bar − hysteresis_bar`.
///
/// Not excited or no average: `unknown`. The level becomes the reported state
/// once it has been the same for `dwell_s`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct HealthMachine {
    cfg: HealthConfig,
    state: Health,
    candidate: Health,
    candidate_since_ns: i64,
}

impl HealthMachine {
    /// A machine in state `unknown`.
    #[must_use]
    pub fn new(cfg: HealthConfig) -> Self {
        Self {
            cfg,
            state: Health::Unknown,
            candidate: Health::Unknown,
            candidate_since_ns: i64::MIN,
        }
    }

    /// The reported state.
    #[must_use]
    pub fn state(&self) -> Health {
        self.state
    }

    /// The level `avg_bar` points to, with hysteresis around the reported state.
    #[must_use]
    pub fn level(&self, avg_bar: f64) -> Health {
        let h = self.cfg.hysteresis_bar;
        let (warn, fault) = (self.cfg.warn_bar, self.cfg.fault_bar);
        let (fault_up, warn_up) = match self.state {
            Health::Leak => (fault + h, warn + h),
            Health::Low => (fault, warn + h),
            Health::Ok | Health::Unknown => (fault, warn),
        };
        if avg_bar < fault_up {
            Health::Leak
        } else if avg_bar < warn_up {
            Health::Low
        } else {
            Health::Ok
        }
    }

    /// The level the interval `[lo_bar, hi_bar]` points to, with hysteresis
    /// around the reported state (SPEC §6a). An interval wholly below
    /// vacuum ([`VACUUM_GAUGE_BAR`]) reads no charge a damper can hold: the
    /// model does not hold for this unit, and the verdict is `unknown`, not
    /// `leak` (thirty-fourth session: another unit read −13.2 ± 2.1 bar for a
    /// true 2 by a quick calibration's linear damping slopes).
    #[must_use]
    pub fn level_interval(&self, lo_bar: f64, hi_bar: f64) -> Health {
        if hi_bar < VACUUM_GAUGE_BAR {
            return Health::Unknown;
        }
        let h = self.cfg.hysteresis_bar;
        let (warn, fault) = (self.cfg.warn_bar, self.cfg.fault_bar);
        let fault_hi = if self.state == Health::Leak {
            fault + h
        } else {
            fault
        };
        let warn_hi = if matches!(self.state, Health::Leak | Health::Low) {
            warn + h
        } else {
            warn
        };
        let warn_lo = if self.state == Health::Ok {
            warn - h
        } else {
            warn
        };
        if hi_bar < fault_hi {
            Health::Leak
        } else if hi_bar < warn_hi {
            Health::Low
        } else if lo_bar > warn_lo {
            Health::Ok
        } else {
            Health::Unknown
        }
    }

    /// Takes the tick at `t_ns` with its 1 s average (NaN: none) and whether
    /// the damper is excited; returns the reported state.
    pub fn update(&mut self, t_ns: i64, avg_bar: f64, excited: bool) -> Health {
        self.update_interval(t_ns, avg_bar, f64::NAN, f64::NAN, excited)
    }

    /// As [`update`](Self::update), with the 95 % interval of the average
    /// (NaN bounds: the rule without an interval).
    pub fn update_interval(
        &mut self,
        t_ns: i64,
        avg_bar: f64,
        lo_bar: f64,
        hi_bar: f64,
        excited: bool,
    ) -> Health {
        let target = if !(excited && avg_bar.is_finite()) {
            Health::Unknown
        } else if lo_bar.is_finite() && hi_bar.is_finite() {
            self.level_interval(lo_bar, hi_bar)
        } else {
            self.level(avg_bar)
        };
        if target != self.candidate {
            self.candidate = target;
            self.candidate_since_ns = t_ns;
        }
        let dwell_ns = (self.cfg.dwell_s * 1e9).round() as i64;
        if self.candidate != self.state && t_ns.saturating_sub(self.candidate_since_ns) >= dwell_ns
        {
            self.state = self.candidate;
        }
        self.state
    }
}

/// One asset's streaming twin. See the module docs.
pub struct Estimator {
    bundle: Arc<Bundle>,
    s: EstimatorState,
}

/// Everything of an [`Estimator`] but its bundle: what a checkpoint holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct EstimatorState {
    cfg: EstimatorConfig,
    topics: TopicSet,
    columns: Vec<usize>,
    /// The bundle reads the charge observer: its standard deviation gives
    /// the interval.
    uses_observer: bool,
    pipe: FeaturePipeline,
    /// The re-order buffer, sorted by key (ties in arrival order).
    queue: VecDeque<Queued>,
    newest_ns: i64,
    /// Samples far ahead of `newest_ns`, held until the jump is confirmed.
    jump: Vec<Sample>,
    released: Option<(i64, u8)>,
    /// After [`Estimator::finish`]: the next released sample starts a segment.
    finished: bool,
    #[serde(with = "serde_big_array::BigArray")]
    avg: [f64; EXCITATION_WINDOW_TICKS],
    avg_idx: usize,
    health: HealthMachine,
    prev_gaps: GapCounters,
    out: VecDeque<Tick>,
    counters: EstimatorCounters,
    seg_missing: u64,
    seg_gaps: u64,
    /// The road observer, when the asset is read on a road
    /// ([`Estimator::with_road`]).
    #[serde(default)]
    road: Option<RoadLane>,
    /// The sensor topics samples have come on (all segments).
    #[serde(default)]
    seen: TopicSet,
}

/// The road observer beside the pipeline: fed the released samples, its
/// blocks held until the tick at or after the sample that completed them.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct RoadLane {
    obs: RoadObserver,
    /// Blocks read, with the time of the sample that completed each.
    pending: VecDeque<(i64, RoadBlock)>,
    current: Option<RoadBlock>,
    /// The unit's baseline read from this run, after a service
    /// ([`Estimator::read_road_baseline`]).
    #[serde(default)]
    reading: Option<RoadBaselineReading>,
}

impl RoadLane {
    /// Queues the blocks the observer has read, completed at `t_ns`.
    fn take_blocks(&mut self, t_ns: i64) {
        for b in self.obs.drain() {
            if let Some(r) = self.reading.as_mut() {
                r.add(self.obs.calibration(), &b);
            }
            self.pending.push_back((t_ns, b));
        }
    }
}

impl std::fmt::Debug for Estimator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Estimator")
            .field("bundle", &self.bundle.dir)
            .field("cfg", &self.s.cfg)
            .field("counters", &self.s.counters)
            .finish_non_exhaustive()
    }
}

/// The bundle's physics for its pipeline: the charge observer runs only when
/// the bundle reads it.
fn pipeline_params(bundle: &Bundle, cfg: &EstimatorConfig) -> Result<PhysicsParams, PhysicsError> {
    let mut params = *bundle.physics();
    if !bundle.groups.contains(&Group::Observer) {
        params.observer = None;
    }
    if let (Some(o), Some(b)) = (params.observer.as_mut(), cfg.observer_baseline) {
        o.baseline = Some(b);
    } else if let (Some(o), Some(law)) = (params.observer.as_mut(), cfg.observer_damping_law) {
        *o = o.with_unit_law(law)?;
    }
    if let (Some(o), true) = (params.observer.as_mut(), cfg.observer_fit_all) {
        o.fit_gain_floor = 0.0;
    }
    Ok(params)
}

impl Estimator {
    /// An estimator for one asset with the bundle's model.
    pub fn new(bundle: Arc<Bundle>, cfg: EstimatorConfig) -> Result<Self, EstimatorError> {
        let topics = TopicSet::for_groups(&bundle.groups);
        let pipe = FeaturePipeline::new(&pipeline_params(&bundle, &cfg)?, topics)?;
        let columns = column_indices(&bundle.groups);
        let uses_observer = bundle.groups.contains(&Group::Observer) && pipe.observer().is_some();
        Ok(Self {
            bundle,
            s: EstimatorState {
                health: HealthMachine::new(cfg.health),
                uses_observer,
                columns,
                pipe,
                topics,
                cfg,
                queue: VecDeque::with_capacity(256),
                newest_ns: i64::MIN,
                jump: Vec::new(),
                released: None,
                finished: false,
                avg: [f64::NAN; EXCITATION_WINDOW_TICKS],
                avg_idx: 0,
                prev_gaps: GapCounters::default(),
                out: VecDeque::with_capacity(16),
                counters: EstimatorCounters::default(),
                seg_missing: 0,
                seg_gaps: 0,
                road: None,
                seen: TopicSet::default(),
            },
        })
    }

    /// This estimator with the road observer ([`crate::road`]) beside the
    /// network: from then on every estimate's pressure, 1 s average, interval
    /// and health are the road observer's (its estimate after the last block
    /// completed by the tick's time; before any block its prior, `unknown`).
    /// The network's columns are still computed (the bundle's features).
    ///
    /// # Errors
    /// The calibration is out of its domain.
    pub fn with_road(mut self, cal: RoadCalibration) -> Result<Self, String> {
        self.s.road = Some(RoadLane {
            obs: RoadObserver::new(cal, self.s.cfg.health)?,
            pending: VecDeque::new(),
            current: None,
            reading: None,
        });
        Ok(self)
    }

    /// This road estimator also reads the unit's road baseline at
    /// `charge_bar` (a service's known charge) from every block it reads
    /// ([`RoadBaselineReading`]); a no-op without the road observer. Its
    /// calibration must carry no baseline.
    #[must_use]
    pub fn read_road_baseline(mut self, charge_bar: f64) -> Self {
        if let Some(lane) = self.s.road.as_mut() {
            lane.reading = Some(RoadBaselineReading::new(charge_bar));
        }
        self
    }

    /// The road baseline read so far (after
    /// [`read_road_baseline`](Self::read_road_baseline)), or why there is
    /// none; `None` when no baseline is being read.
    #[must_use]
    pub fn road_baseline(&self) -> Option<Result<RoadBaseline, String>> {
        let reading = self.s.road.as_ref()?.reading?;
        Some(reading.baseline())
    }

    /// The road observer's estimate now (all blocks read so far), when the
    /// asset is read on a road.
    #[must_use]
    pub fn road(&self) -> Option<RoadEstimate> {
        self.s.road.as_ref().map(|l| l.obs.estimate())
    }

    /// The whole state of this estimator (Kalman filter, thermal model,
    /// charge observer, pipeline buffers, re-order window, health state
    /// machine and the estimates not yet drained) as bytes, tied to its
    /// bundle. [`Estimator::restore`] with the same bundle continues exactly
    /// (bit for bit) where this one is.
    #[must_use]
    pub fn checkpoint(&self) -> Vec<u8> {
        let ck = CheckpointRef {
            format: CHECKPOINT_FORMAT,
            model: model_digest(&self.bundle),
            state: &self.s,
        };
        // Serialising plain numbers, vectors and enums cannot fail.
        rmp_serde::to_vec_named(&ck).unwrap_or_default()
    }

    /// The estimator a [`checkpoint`](Self::checkpoint) was taken of. Fails
    /// when the bytes are not a checkpoint of this format or were taken with
    /// another model.
    pub fn restore(bundle: Arc<Bundle>, bytes: &[u8]) -> Result<Self, CheckpointError> {
        let ck: Checkpoint =
            rmp_serde::from_slice(bytes).map_err(|e| CheckpointError::Decode(e.to_string()))?;
        if ck.format != CHECKPOINT_FORMAT {
            return Err(CheckpointError::Format(ck.format));
        }
        let model = model_digest(&bundle);
        if ck.model != model {
            return Err(CheckpointError::Model {
                checkpoint: ck.model,
                bundle: model,
            });
        }
        Ok(Self {
            bundle,
            s: ck.state,
        })
    }

    /// The charge observer of the current segment, when the bundle reads it.
    #[must_use]
    pub fn observer(&self) -> Option<&crate::charge::ChargeObserver> {
        self.s.pipe.observer()
    }

    /// The counters so far.
    #[must_use]
    pub fn counters(&self) -> EstimatorCounters {
        let mut c = self.s.counters;
        c.missing_samples += self.s.seg_missing;
        c.gaps += self.s.seg_gaps;
        if let Some(o) = self.s.pipe.observer() {
            c.observer += o.counters();
        }
        c.road = self.s.road.as_ref().map(|l| l.obs.counters());
        c
    }

    /// The topics the bundle's groups need that no sample has come on so
    /// far, in the order the groups name them: a run without a sensor its
    /// model reads has a NaN pressure throughout (the batch path refuses it
    /// upfront, `compute_features`; a stream can only tell at its end).
    #[must_use]
    pub fn missing_topics(&self) -> Vec<&'static str> {
        self.s.seen.missing_for(&self.bundle.groups)
    }

    /// [`missing_topics`](Self::missing_topics) as the reason a run has no
    /// estimate (naming the bundle's groups), `None` when none is missing.
    #[must_use]
    pub fn missing_topics_reason(&self) -> Option<String> {
        let missing = self.missing_topics();
        (!missing.is_empty()).then(|| {
            let groups: Vec<&str> = self.bundle.groups.iter().map(|g| g.name()).collect();
            format!(
                "lacks topics {missing:?} needed by the model's feature groups {groups:?}: no estimate"
            )
        })
    }

    /// The settings.
    #[must_use]
    pub fn config(&self) -> &EstimatorConfig {
        &self.s.cfg
    }

    /// The bundle.
    #[must_use]
    pub fn bundle(&self) -> &Arc<Bundle> {
        &self.bundle
    }

    /// Why this estimator's answer for a run with metadata `meta` is an
    /// extrapolation of the bundle's network ([`Bundle::untrained_excitation`]);
    /// `None` on a road asset, which the road observer reads instead.
    #[must_use]
    pub fn untrained_excitation(&self, meta: &crate::log::RunMetadata) -> Option<String> {
        if self.road().is_some() {
            return None;
        }
        self.bundle.untrained_excitation(meta)
    }

    /// Samples held in the re-order window.
    #[must_use]
    pub fn held(&self) -> usize {
        self.s.queue.len()
    }

    /// Takes one sample (any topic, any order within the re-order window).
    /// Late samples are counted and dropped, not an error; an error is a
    /// numerical failure of the twin or the network.
    pub fn push(&mut self, sample: Sample) -> Result<(), EstimatorError> {
        self.s.counters.samples += 1;
        self.s.seen = self.s.seen.with(&sample);
        let t = sample.t_ns();
        if self.s.newest_ns != i64::MIN
            && t.saturating_sub(self.s.newest_ns) > self.s.cfg.max_gap_ns
        {
            if self
                .s
                .jump
                .first()
                .is_some_and(|f| f.t_ns().abs_diff(t) > self.s.cfg.max_gap_ns.unsigned_abs())
            {
                self.drop_jump();
            }
            self.s.jump.push(sample);
            if self.s.jump.len() >= JUMP_CONFIRM {
                for s in std::mem::take(&mut self.s.jump) {
                    self.accept(s)?;
                }
            }
            return Ok(());
        }
        self.drop_jump();
        self.accept(sample)
    }

    /// The held "jump" samples were not followed by the stream: outliers.
    fn drop_jump(&mut self) {
        self.s.counters.timestamp_outliers += self.s.jump.len() as u64;
        self.s.jump.clear();
    }

    fn accept(&mut self, sample: Sample) -> Result<(), EstimatorError> {
        let t = sample.t_ns();
        let key = (t, sample.topic_rank());
        if self.s.released.is_some_and(|r| key < r) {
            self.s.counters.late_dropped += 1;
            return Ok(());
        }
        if t < self.s.newest_ns {
            self.s.counters.reordered += 1;
        }
        self.s.newest_ns = self.s.newest_ns.max(t);
        let q = Queued { key, sample };
        if self.s.queue.back().is_none_or(|b| b.key <= key) {
            self.s.queue.push_back(q);
        } else {
            let at = self.s.queue.partition_point(|x| x.key <= key);
            self.s.queue.insert(at, q);
        }
        let horizon = self
            .s
            .newest_ns
            .saturating_sub(self.s.cfg.reorder_window_ns);
        while self.s.queue.front().is_some_and(|q| q.key.0 <= horizon) {
            if let Some(q) = self.s.queue.pop_front() {
                self.release(q)?;
            }
        }
        Ok(())
    }

    /// End of stream: releases everything held and emits the last tick. A
    /// later [`push`](Self::push) starts a new segment (samples before the
    /// last released one are still late). Samples held aside as a possible
    /// clock jump that fewer than [`JUMP_CONFIRM`] agreed on are counted as
    /// timestamp outliers.
    pub fn finish(&mut self) -> Result<(), EstimatorError> {
        self.drop_jump();
        while let Some(q) = self.s.queue.pop_front() {
            self.release(q)?;
        }
        if let (Some(lane), Some((t, _))) = (self.s.road.as_mut(), self.s.released) {
            lane.obs.finish();
            lane.take_blocks(t);
        }
        self.s.pipe.finish();
        self.take_rows()?;
        self.s.finished = true;
        Ok(())
    }

    /// The estimates emitted so far and not yet taken.
    pub fn drain(&mut self) -> impl Iterator<Item = Estimate> + '_ {
        self.s.out.drain(..).map(|t| t.estimate)
    }

    /// The ticks (estimate and feature row) emitted so far and not yet taken.
    pub fn drain_ticks(&mut self) -> impl Iterator<Item = Tick> + '_ {
        self.s.out.drain(..)
    }

    /// Number of estimates waiting.
    #[must_use]
    pub fn ready(&self) -> usize {
        self.s.out.len()
    }

    fn release(&mut self, q: Queued) -> Result<(), EstimatorError> {
        if let Some((last_t, _)) = self.s.released {
            if self.s.finished {
                self.new_run_segment()?;
            } else if q.key.0.saturating_sub(last_t) > self.s.cfg.max_gap_ns {
                self.s.counters.clock_jumps += 1;
                self.s.pipe.finish();
                self.take_rows()?;
                #[allow(clippy::cast_precision_loss)] // a gap in ns, read in s
                let gap_s = q.key.0.saturating_sub(last_t) as f64 * 1e-9;
                let prev = self.new_segment()?;
                self.s.pipe.carry_over(prev, gap_s);
            }
        }
        self.s.released = Some(q.key);
        if let Some(lane) = self.s.road.as_mut() {
            lane.obs.push(&q.sample);
            lane.take_blocks(q.key.0);
        }
        self.s.pipe.push(&q.sample)?;
        self.take_rows()
    }

    /// Starts a new segment: a fresh pipeline, 1 s average and health; the
    /// segment's pipeline before is returned, for the slow state a clock
    /// jump carries over ([`FeaturePipeline::carry_over`], whose observer
    /// goes on counting: its counts are then not added here).
    fn new_segment(&mut self) -> Result<FeaturePipeline, EstimatorError> {
        self.s.finished = false;
        self.s.counters.missing_samples += self.s.seg_missing;
        self.s.counters.gaps += self.s.seg_gaps;
        self.s.seg_missing = 0;
        self.s.seg_gaps = 0;
        self.s.prev_gaps = GapCounters::default();
        let pipe =
            FeaturePipeline::new(&pipeline_params(&self.bundle, &self.s.cfg)?, self.s.topics)?;
        let prev = std::mem::replace(&mut self.s.pipe, pipe);
        self.s.avg = [f64::NAN; EXCITATION_WINDOW_TICKS];
        self.s.avg_idx = 0;
        self.s.health = HealthMachine::new(self.s.cfg.health);
        Ok(prev)
    }

    /// A new segment after [`finish`](Self::finish): a run of its own,
    /// nothing carried over (its observer's counts added to the totals).
    fn new_run_segment(&mut self) -> Result<(), EstimatorError> {
        let prev = self.new_segment()?;
        if let Some(o) = prev.observer() {
            self.s.counters.observer += o.counters();
        }
        Ok(())
    }

    fn take_rows(&mut self) -> Result<(), EstimatorError> {
        while let Some(row) = self.s.pipe.pop() {
            let estimate = self.estimate(&row)?;
            self.s.out.push_back(Tick { estimate, row });
        }
        Ok(())
    }

    fn estimate(&mut self, row: &TickRow) -> Result<Estimate, EstimatorError> {
        self.s.counters.ticks += 1;
        let twin = &row.twin;
        let g = twin.gaps;
        self.s.seg_missing = twin.missing_samples;
        self.s.seg_gaps = g.force + g.position + g.acceleration;
        let p = self.s.prev_gaps;
        let stale = (self.s.topics.force && g.force > p.force)
            || (self.s.topics.position && g.position > p.position)
            || (self.s.topics.acceleration && g.acceleration > p.acceleration);
        self.s.prev_gaps = g;

        let k = self.s.columns.len();
        let mut x = [0.0; N_COLUMNS];
        for (xi, &i) in x.iter_mut().zip(&self.s.columns) {
            *xi = row.values[i];
        }
        let pressure_bar = if x[..k].iter().all(|v| v.is_finite()) {
            self.bundle.predict_one(&x[..k])?
        } else {
            self.s.counters.ticks_without_inputs += 1;
            f64::NAN
        };
        if stale {
            self.s.counters.ticks_stale += 1;
        }
        let excited = twin.velocity_rms_1s_mps >= self.s.cfg.health.min_excitation_mps;
        self.s.avg[self.s.avg_idx] = if excited && !stale {
            pressure_bar
        } else {
            f64::NAN
        };
        self.s.avg_idx = (self.s.avg_idx + 1) % EXCITATION_WINDOW_TICKS;
        let (sum, n) = self
            .s
            .avg
            .iter()
            .filter(|x| x.is_finite())
            .fold((0.0, 0.0), |(s, n), x| (s + x, n + 1.0));
        let pressure_avg_bar = if n > 0.0 { sum / n } else { f64::NAN };
        // The interval (SPEC §2a): the charge observer's standard deviation
        // around the estimate, when the bundle reads the observer; else the
        // held-out error of the 1 s average around it, when the bundle was
        // sized on held-out runs (NaN while there is no average: no excited
        // tick in the last second); else none.
        let (lo, hi, avg_lo, avg_hi) = if self.s.uses_observer {
            let half = Z95 * row.values[col::OBSERVER_SD_BAR];
            (
                pressure_bar - half,
                pressure_bar + half,
                pressure_avg_bar - half,
                pressure_avg_bar + half,
            )
        } else if let Some(i) = &self.bundle.twin.interval {
            let (lo, hi) = (
                pressure_avg_bar - i.half_width_bar,
                pressure_avg_bar + i.half_width_bar,
            );
            (lo, hi, lo, hi)
        } else {
            (f64::NAN, f64::NAN, f64::NAN, f64::NAN)
        };
        let health =
            self.s
                .health
                .update_interval(row.t_ns, pressure_avg_bar, avg_lo, avg_hi, excited);
        // On a road asset: the road observer's estimate after the last block
        // completed by this tick (before any, its prior), for all four.
        let (pressure_bar, pressure_avg_bar, lo, hi, health) = match self.s.road.as_mut() {
            Some(lane) => {
                while lane.pending.front().is_some_and(|(t, _)| *t <= row.t_ns) {
                    lane.current = lane.pending.pop_front().map(|(_, b)| b);
                }
                if let Some(b) = lane.current {
                    (b.estimate_bar, b.estimate_bar, b.lo_bar, b.hi_bar, b.health)
                } else {
                    let cal = lane.obs.calibration();
                    let (lo, hi) = cal.prior_interval();
                    (
                        cal.prior_mean_bar,
                        cal.prior_mean_bar,
                        lo,
                        hi,
                        Health::Unknown,
                    )
                }
            }
            None => (pressure_bar, pressure_avg_bar, lo, hi, health),
        };
        let (unfloored_bar, unfloored_half_bar) = unfloored(pressure_bar, lo, hi);
        let [pressure_bar, pressure_avg_bar, lo] =
            at_ambient_floor([pressure_bar, pressure_avg_bar, lo], hi);
        Ok(Estimate {
            t_ns: row.t_ns,
            pressure_bar,
            pressure_avg_bar,
            pressure_lo_bar: lo,
            pressure_hi_bar: hi,
            expected_bar: self.s.cfg.nominal_bar,
            health,
            velocity_mps: twin.velocity_mps,
            force_model_n: twin.force_model_n,
            oil_temp_c: twin.oil_temp_c,
            unfloored_bar,
            unfloored_half_bar,
        })
    }
}

/// `values` (estimate, average, lower bound; bar gauge) no lower than 0 when
/// the interval's upper bound `hi_bar` is above 0, else as they are (see the
/// module docs). NaN stays NaN.
#[must_use]
pub fn at_ambient_floor(values: [f64; 3], hi_bar: f64) -> [f64; 3] {
    if hi_bar >= 0.0 {
        values.map(|v| if v < 0.0 { 0.0 } else { v })
    } else {
        values
    }
}

/// The estimate and its interval's half-width as read, before
/// [`at_ambient_floor`] (`Estimate::unfloored_bar`, `unfloored_half_bar`):
/// the fleet store summarises runs with them. NaN half without an interval.
#[must_use]
pub fn unfloored(pressure_bar: f64, lo_bar: f64, hi_bar: f64) -> (f64, f64) {
    (pressure_bar, 0.5 * (hi_bar - lo_bar))
}

/// Runs a whole log through a fresh estimator (what `replay` does per file).
pub fn estimate_log(
    bundle: Arc<Bundle>,
    cfg: EstimatorConfig,
    log: &crate::log::RunLog,
) -> Result<(Vec<Estimate>, EstimatorCounters), EstimatorError> {
    let mut est = Estimator::new(bundle, cfg)?;
    let mut out = Vec::new();
    for (k, s) in crate::features::sorted_samples(log).into_iter().enumerate() {
        if crate::cancel::requested_at(k) {
            break; // nobody waits for it any more (`cancel`)
        }
        est.push(s)?;
        out.extend(est.drain());
    }
    est.finish()?;
    out.extend(est.drain());
    Ok((out, est.counters()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_interval_below_vacuum_is_no_verdict() {
        let m = HealthMachine::new(HealthConfig::default());
        assert_eq!(m.level_interval(-16.6, -8.6), Health::Unknown);
        assert_eq!(m.level_interval(-1.5, -1.1), Health::Unknown);
        // reaching above vacuum it is a reading of an empty damper
        assert_eq!(m.level_interval(-3.0, -0.5), Health::Leak);
        assert_eq!(m.level_interval(-1.2, 4.9), Health::Leak);
        assert_eq!(m.level_interval(9.5, 14.0), Health::Ok);
    }

    #[test]
    #[allow(clippy::float_cmp)] // the floor is exact: 0, or the value itself
    fn a_reading_reaching_above_ambient_is_shown_no_lower_than_it() {
        // estimate, average, lower bound
        assert_eq!(
            at_ambient_floor([-0.03, -0.2, -3.88], 3.59),
            [0.0, 0.0, 0.0]
        );
        assert_eq!(at_ambient_floor([1.9, 2.1, -0.93], 4.82), [1.9, 2.1, 0.0]);
        // what the store's run summary takes instead: the reading as read
        // (a review: a test on a run that never went below 0 checked nothing)
        let (p, lo, hi) = (-0.5, -3.0, 2.0);
        assert_eq!(at_ambient_floor([p, p, lo], hi), [0.0, 0.0, 0.0]);
        assert_eq!(unfloored(p, lo, hi), (-0.5, 2.5));
        assert!(unfloored(3.0, f64::NAN, f64::NAN).1.is_nan());
        assert_eq!(at_ambient_floor([2.94, 2.9, 0.62], 5.37), [2.94, 2.9, 0.62]);
        // wholly below ambient: shown as read (the model does not hold)
        assert_eq!(
            at_ambient_floor([-12.3, -12.4, -16.6], -8.56),
            [-12.3, -12.4, -16.6]
        );
        // no interval, or no estimate: nothing floored, NaN kept
        assert_eq!(
            at_ambient_floor([-0.5, -0.4, f64::NAN], f64::NAN)[..2],
            [-0.5, -0.4]
        );
        assert!(at_ambient_floor([f64::NAN; 3], 2.0)
            .iter()
            .all(|v| v.is_nan()));
        // a truth at or above 0 inside the interval stays inside, and the
        // floored estimate is never further from it
        for (p, lo, hi) in [(-1.0, -4.0, 2.0), (0.5, -3.0, 4.0), (-0.2, -0.4, 0.0)] {
            let [fp, _, flo] = at_ambient_floor([p, p, lo], hi);
            for truth in [0.0, 0.1, 1.0, 1.99] {
                if lo <= truth && truth <= hi {
                    assert!(flo <= truth && truth <= hi);
                }
                assert!((fp - truth).abs() <= (p - truth).abs());
            }
        }
    }
}
