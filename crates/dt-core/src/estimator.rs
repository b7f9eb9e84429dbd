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
//! - **Re-ordering.** Samples are held in a min-heap keyed by
//!   `(t_ns, topic rank, arrival)` and released once the newest time seen is
//!   more than `reorder_window_ns` past them, so the pipeline sees exactly the
//!   order of [`crate::features::sorted_samples`]; that is why batch features
//!   (`compute_features`, the Python `features`) and streaming agree. A
//!   sample older than the last released one is late: counted and dropped.
//! - **Clock jumps.** A forward jump of more than `max_gap_ns` between
//!   released samples (a logger restart, a lost link) starts a new segment:
//!   a fresh pipeline, average and health (`unknown` until excited again).
//!   Counted.
//! - **Inputs the suite lacks** never reach the pipeline: it is built with the
//!   topics that the bundle's groups need, so a model uses only its suite's
//!   sensors (the batch path does the same, see `compute_features`).
//! - **Pressure.** The network reads the permutation's columns of the row; a
//!   row with a non-finite input gives a NaN pressure (a sensor not yet seen,
//!   a dropout) and is counted. The 1 s average is the mean of the finite
//!   pressures of excited ticks in the last 50 ticks.
//! - **Health** (SPEC §6) is judged on the 1 s average: `leak` below the fault
//!   threshold, `low` below the warn threshold, else `ok`; a state is left only
//!   when the average is `hysteresis_bar` past its threshold, and a new state
//!   is reported only after it has held for `dwell_s`. Without excitation
//!   (1 s velocity RMS below `min_excitation_mps`) or without an average the
//!   candidate state is `unknown`.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::sync::Arc;

use crate::bundle::{Bundle, BundleError, HealthConfig};
use crate::error::PhysicsError;
use crate::estimate::{Estimate, Health};
use crate::features::{
    column_indices, FeaturePipeline, TickRow, TopicSet, EXCITATION_WINDOW_TICKS, TICK_NS,
};
use crate::log::Sample;

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

/// Per-asset settings of an estimator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EstimatorConfig {
    /// The asset's nominal charge pressure (`expected_bar`), bar gauge.
    pub nominal_bar: f64,
    /// Health thresholds and timing.
    pub health: HealthConfig,
    /// Samples are held this long for re-ordering, ns.
    pub reorder_window_ns: i64,
    /// A forward gap longer than this starts a new segment, ns.
    pub max_gap_ns: i64,
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
        }
    }
}

/// What an estimator has counted so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EstimatorCounters {
    /// Samples accepted (incl. those still in the re-order window).
    pub samples: u64,
    /// Samples older than the last released one: dropped.
    pub late_dropped: u64,
    /// Samples that arrived out of order but inside the window (re-ordered).
    pub reordered: u64,
    /// Forward clock jumps that started a new segment.
    pub clock_jumps: u64,
    /// Ticks emitted.
    pub ticks: u64,
    /// Ticks whose network inputs were not all finite (pressure NaN).
    pub ticks_without_inputs: u64,
    /// Non-finite samples skipped by the pipeline (all segments).
    pub missing_samples: u64,
    /// Ticks on which a fast channel had no sample (held value), all segments.
    pub gaps: u64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Queued {
    t_ns: i64,
    rank: u8,
    seq: u64,
    sample: Sample,
}

impl Eq for Queued {}
impl Ord for Queued {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.t_ns, self.rank, self.seq).cmp(&(other.t_ns, other.rank, other.seq))
    }
}
impl PartialOrd for Queued {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

/// Topic rank at equal times (SPEC §3.1: the accelerometer first).
fn rank(s: &Sample) -> u8 {
    match s {
        Sample::Acceleration { .. } => 0,
        Sample::Position { .. } => 1,
        Sample::Force { .. } => 2,
        Sample::TempShock { .. } => 3,
        Sample::TempAmbient { .. } => 4,
        Sample::TruthPressure { .. } => 5,
    }
}

/// The health state machine of SPEC §6.
#[derive(Debug, Clone, Copy)]
struct HealthMachine {
    cfg: HealthConfig,
    state: Health,
    candidate: Health,
    candidate_since_ns: i64,
}

impl HealthMachine {
    fn new(cfg: HealthConfig) -> Self {
        Self {
            cfg,
            state: Health::Unknown,
            candidate: Health::Unknown,
            candidate_since_ns: i64::MIN,
        }
    }

    /// The level the average points to, with hysteresis around the current state.
    fn level(&self, avg_bar: f64) -> Health {
        let h = self.cfg.hysteresis_bar;
        let (warn, fault) = (self.cfg.warn_bar, self.cfg.fault_bar);
        match self.state {
            Health::Leak if avg_bar < fault + h => Health::Leak,
            Health::Low if avg_bar < fault => Health::Leak,
            Health::Low if avg_bar < warn + h => Health::Low,
            _ if avg_bar < fault => Health::Leak,
            _ if avg_bar < warn => Health::Low,
            _ => Health::Ok,
        }
    }

    fn update(&mut self, t_ns: i64, avg_bar: f64, excited: bool) -> Health {
        let target = if excited && avg_bar.is_finite() {
            self.level(avg_bar)
        } else {
            Health::Unknown
        };
        if target != self.candidate {
            self.candidate = target;
            self.candidate_since_ns = t_ns;
        }
        let dwell_ns = (self.cfg.dwell_s * 1e9) as i64;
        if self.candidate != self.state && t_ns - self.candidate_since_ns >= dwell_ns {
            self.state = self.candidate;
        }
        self.state
    }
}

/// One asset's streaming twin. See the module docs.
pub struct Estimator {
    bundle: Arc<Bundle>,
    cfg: EstimatorConfig,
    topics: TopicSet,
    columns: Vec<usize>,
    pipe: FeaturePipeline,
    heap: BinaryHeap<Reverse<Queued>>,
    seq: u64,
    newest_ns: i64,
    released_ns: Option<(i64, u8)>,
    avg: VecDeque<f64>,
    health: HealthMachine,
    row: Vec<f64>,
    out: VecDeque<Estimate>,
    counters: EstimatorCounters,
    seg_missing: u64,
    seg_gaps: u64,
}

impl std::fmt::Debug for Estimator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Estimator")
            .field("bundle", &self.bundle.dir)
            .field("cfg", &self.cfg)
            .field("counters", &self.counters)
            .finish_non_exhaustive()
    }
}

impl Estimator {
    /// An estimator for one asset with the bundle's model.
    pub fn new(bundle: Arc<Bundle>, cfg: EstimatorConfig) -> Result<Self, EstimatorError> {
        let topics = TopicSet::for_groups(&bundle.groups);
        let pipe = FeaturePipeline::new(bundle.physics(), topics)?;
        let columns = column_indices(&bundle.groups);
        Ok(Self {
            health: HealthMachine::new(cfg.health),
            row: Vec::with_capacity(columns.len()),
            columns,
            pipe,
            topics,
            bundle,
            cfg,
            heap: BinaryHeap::new(),
            seq: 0,
            newest_ns: i64::MIN,
            released_ns: None,
            avg: VecDeque::with_capacity(EXCITATION_WINDOW_TICKS),
            out: VecDeque::new(),
            counters: EstimatorCounters::default(),
            seg_missing: 0,
            seg_gaps: 0,
        })
    }

    /// The counters so far.
    #[must_use]
    pub fn counters(&self) -> EstimatorCounters {
        let mut c = self.counters;
        c.missing_samples += self.seg_missing;
        c.gaps += self.seg_gaps;
        c
    }

    /// The settings.
    #[must_use]
    pub fn config(&self) -> &EstimatorConfig {
        &self.cfg
    }

    /// Takes one sample (any topic, any order within the re-order window).
    pub fn push(&mut self, sample: Sample) -> Result<(), EstimatorError> {
        let t = sample.t_ns();
        self.counters.samples += 1;
        let key = (t, rank(&sample));
        if self.released_ns.is_some_and(|r| key < r) {
            self.counters.late_dropped += 1;
            return Ok(());
        }
        if t < self.newest_ns {
            self.counters.reordered += 1;
        }
        self.newest_ns = self.newest_ns.max(t);
        self.seq += 1;
        self.heap.push(Reverse(Queued {
            t_ns: t,
            rank: key.1,
            seq: self.seq,
            sample,
        }));
        let horizon = self.newest_ns.saturating_sub(self.cfg.reorder_window_ns);
        while let Some(Reverse(q)) = self.heap.peek().copied() {
            if q.t_ns > horizon {
                break;
            }
            self.heap.pop();
            self.release(q)?;
        }
        Ok(())
    }

    /// End of stream: releases everything held and emits the last tick.
    pub fn finish(&mut self) -> Result<(), EstimatorError> {
        while let Some(Reverse(q)) = self.heap.pop() {
            self.release(q)?;
        }
        self.pipe.finish();
        self.take_rows()
    }

    /// The estimates emitted so far and not yet taken.
    pub fn drain(&mut self) -> impl Iterator<Item = Estimate> + '_ {
        self.out.drain(..)
    }

    /// Number of estimates waiting.
    #[must_use]
    pub fn ready(&self) -> usize {
        self.out.len()
    }

    fn release(&mut self, q: Queued) -> Result<(), EstimatorError> {
        if let Some((last_t, _)) = self.released_ns {
            if q.t_ns - last_t > self.cfg.max_gap_ns {
                self.new_segment()?;
            }
        }
        self.released_ns = Some((q.t_ns, q.rank));
        self.pipe.push(&q.sample)?;
        self.take_rows()
    }

    fn new_segment(&mut self) -> Result<(), EstimatorError> {
        self.pipe.finish();
        self.take_rows()?;
        self.counters.clock_jumps += 1;
        self.counters.missing_samples += self.seg_missing;
        self.counters.gaps += self.seg_gaps;
        self.seg_missing = 0;
        self.seg_gaps = 0;
        self.pipe = FeaturePipeline::new(self.bundle.physics(), self.topics)?;
        self.avg.clear();
        self.health = HealthMachine::new(self.cfg.health);
        Ok(())
    }

    fn take_rows(&mut self) -> Result<(), EstimatorError> {
        while let Some(row) = self.pipe.pop() {
            let est = self.estimate(&row)?;
            self.out.push_back(est);
        }
        Ok(())
    }

    fn estimate(&mut self, row: &TickRow) -> Result<Estimate, EstimatorError> {
        self.counters.ticks += 1;
        let twin = &row.twin;
        self.seg_missing = twin.missing_samples;
        self.seg_gaps = twin.gaps.force + twin.gaps.position + twin.gaps.acceleration;
        self.row.clear();
        self.row.extend(self.columns.iter().map(|&i| row.values[i]));
        let pressure_bar = if self.row.iter().all(|x| x.is_finite()) {
            self.bundle.predict_one(&self.row)?
        } else {
            self.counters.ticks_without_inputs += 1;
            f64::NAN
        };
        let excited = twin.velocity_rms_1s_mps >= self.cfg.health.min_excitation_mps;
        if self.avg.len() == EXCITATION_WINDOW_TICKS {
            self.avg.pop_front();
        }
        self.avg
            .push_back(if excited { pressure_bar } else { f64::NAN });
        let (sum, n) = self
            .avg
            .iter()
            .filter(|x| x.is_finite())
            .fold((0.0, 0.0), |(s, n), x| (s + x, n + 1.0));
        let pressure_avg_bar = if n > 0.0 { sum / n } else { f64::NAN };
        let health = self.health.update(row.t_ns, pressure_avg_bar, excited);
        Ok(Estimate {
            t_ns: row.t_ns,
            pressure_bar,
            pressure_avg_bar,
            expected_bar: self.cfg.nominal_bar,
            health,
            velocity_mps: twin.velocity_mps,
            force_model_n: twin.force_model_n,
            oil_temp_c: twin.oil_temp_c,
        })
    }
}

/// Runs a whole log through a fresh estimator (what `replay` does per file).
pub fn estimate_log(
    bundle: Arc<Bundle>,
    cfg: EstimatorConfig,
    log: &crate::log::RunLog,
) -> Result<(Vec<Estimate>, EstimatorCounters), EstimatorError> {
    let mut est = Estimator::new(bundle, cfg)?;
    let mut out = Vec::new();
    for s in crate::features::sorted_samples(log) {
        est.push(s)?;
        out.extend(est.drain());
    }
    est.finish()?;
    out.extend(est.drain());
    Ok((out, est.counters()))
}

const _: () = assert!(TICK_NS == 20_000_000);
