//! The fleet's memory: every run, the estimates downsampled to 1 s, the
//! health changes, and per asset the leak trend computed from them.
//!
//! ```text
//!  sink thread ──► StoreSink (1 s bins, run summaries) ──► bounded queue ──► writer thread
//!                                                                            ├─ one SQLite transaction per ≤ flush interval
//!                                                                            └─ trends of the assets whose runs ended ──► Trends (HTTP, metrics)
//! ```
//!
//! [`FleetStore`] is the small interface the daemon needs; [`SqliteStore`]
//! is the embedded implementation (WAL mode, versioned schema). The writer
//! thread commits at most every `[store] flush_ms` (default 500 ms), so a
//! `kill -9` loses at most the batch not yet committed and the 1 s bin in
//! progress; `SQLite`'s WAL keeps the file consistent whatever the moment.
//!
//! **Calendar time.** Estimates carry the run's own clock (`t_ns`, SPEC §2:
//! any epoch). When a run's first tick is a plausible Unix time (after
//! 2001-09-09 and not more than a day ahead of the wall clock) the store uses
//! it as is, so that logs copied in days later land on the days they were
//! recorded; otherwise the run is placed at the wall-clock time its
//! processing started.
//!
//! **Run summary** (what the trend fits, [`dt_core::trend`]): the mean of
//! the run's excited 1 s bins from [`SUMMARY_SETTLE_S`] after its first
//! excited bin (or the later half of them in a shorter run; at least
//! [`SUMMARY_MIN_BINS`]); its sd is the mean half-width of the 95 % interval
//! / 1.96 when the estimator gives one, else the bins' standard deviation.

mod sink;
mod sqlite;

use std::fmt::Debug;
use std::path::PathBuf;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use dt_core::charge::ObserverCounters;
use dt_core::estimate::Health;
use dt_core::road::RoadCounters;
use dt_core::trend::{Crossing, RunPoint, Trend, DAY_S};
use serde::Serialize;

pub use sink::{StoreSink, Trends};
pub use sqlite::{SqliteStore, SCHEMA_VERSION};

/// Seconds after the first excited bin from which a run's summary is taken.
pub const SUMMARY_SETTLE_S: f64 = 60.0;
/// The fewest excited bins a run summary is made from.
pub const SUMMARY_MIN_BINS: usize = 10;

/// What can go wrong with the store; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The file cannot be opened or is not a shocktwin fleet store.
    #[error("fleet store {}: {reason}", path.display())]
    Open {
        /// The database file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The file was written by a newer shocktwin.
    #[error(
        "fleet store {}: schema version {found} is newer than this shocktwin's ({SCHEMA_VERSION}); \
         run the newer shocktwin or point --db elsewhere",
        path.display()
    )]
    NewerSchema {
        /// The database file.
        path: PathBuf,
        /// Its `user_version`.
        found: i64,
    },
    /// A query or write failed (disk full, I/O error, ...).
    #[error("fleet store {}: {source}", path.display())]
    Sqlite {
        /// The database file.
        path: PathBuf,
        /// `SQLite`'s error.
        #[source]
        source: rusqlite::Error,
    },
    /// A request the store cannot answer as asked.
    #[error("{0}")]
    Request(String),
}

/// One run as the store keeps it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunRecord {
    /// Run id (from the log's metadata).
    pub run_id: String,
    /// Where it came from (`tcp ADDR`, `inbox FILE`).
    pub source: String,
    /// Calendar start, ms since the Unix epoch.
    pub start_ms: i64,
    /// Calendar end, if it ended.
    pub end_ms: Option<i64>,
    /// Estimates (50 Hz ticks).
    pub ticks: u64,
    /// `running`, `completed`, `failed`, `interrupted`.
    pub status: String,
    /// Why it failed.
    pub reason: Option<String>,
    /// The run's summary (see the module doc), if it had one.
    pub summary: Option<RunPoint>,
    /// What the charge observer made of its reversals, if the model read it.
    pub observer: Option<crate::server::sink::ObserverRead>,
    /// What the road observer made of its blocks, if the asset is a road one.
    pub road: Option<crate::server::sink::RoadRead>,
    /// Whether the log says it is simulated (its metadata's `simulated`
    /// key, [`dt_core::log::RunMetadata::simulated`]); null: it does not say.
    pub simulated: Option<bool>,
}

/// A unit's baseline: what the dyno observer read of the unit at a known
/// charge, or what the road observer read of its seal (a road asset).
#[derive(Debug, Clone, Copy, PartialEq)]
// A unit's own damping law makes an observer baseline ≈ 0.4 kB; one is made per
// change of an asset's baseline, never per sample, and stays `Copy`.
#[allow(clippy::large_enum_variant)]
pub enum AssetBaseline {
    /// [`dt_core::charge::UnitBaseline`] (`observer_baseline`).
    Observer(dt_core::charge::UnitBaseline),
    /// [`dt_core::road::RoadBaseline`] (`road_baseline`).
    Road(dt_core::road::RoadBaseline),
}

impl AssetBaseline {
    /// The charge the unit held, bar gauge at 20 °C.
    #[must_use]
    pub fn charge_bar(&self) -> f64 {
        match self {
            Self::Observer(b) => b.charge_bar,
            Self::Road(b) => b.charge_bar,
        }
    }

    /// `observer` or `road`.
    #[must_use]
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Observer(_) => "observer",
            Self::Road(_) => "road",
        }
    }
}

impl std::fmt::Display for AssetBaseline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Observer(b) => {
                write!(
                    f,
                    "observer read {:.2} ± {:.2} bar at a known {:.2} bar",
                    b.read_bar, b.read_sd_bar, b.charge_bar
                )?;
                if let Some(r) = b.second {
                    write!(
                        f,
                        " and {:.2} ± {:.2} bar at a known {:.2} bar",
                        r.read_bar, r.read_sd_bar, r.charge_bar
                    )?;
                }
                let others = b.other_excitations.iter().flatten().count();
                if others > 0 {
                    write!(f, " (and at {others} other excitation(s))")?;
                }
                if b.damping_law.is_some() {
                    write!(f, ", with the unit's own damping law")?;
                }
                Ok(())
            }
            Self::Road(b) => write!(
                f,
                "road: seal offset {:+.2} N over {} blocks at a known {:.2} bar",
                b.offset_n, b.blocks, b.charge_bar
            ),
        }
    }
}

/// A unit baseline set over the API (`PUT /v1/assets/{id}/baseline`) or read
/// after a service.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StoredBaseline {
    /// The baseline.
    pub baseline: AssetBaseline,
    /// When it was set (wall clock), ms since the Unix epoch.
    pub set_ms: i64,
}

/// A service reported over the API (`PUT /v1/assets/{id}/service`): the
/// unit was filled to a known charge, and the daemon reads its baseline from
/// the asset's next run (see [`super::baselines`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PendingService {
    /// The charge the unit was filled to, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// When the unit was serviced (the `at` reported, else when it was
    /// reported), ms since the Unix epoch: runs recorded before it are not
    /// read, and the asset's trend restarts at it.
    pub set_ms: i64,
    /// Why the last run after it gave no baseline, if one did not.
    pub refusal: Option<String>,
}

/// One 1 s point of an asset's history (or the mean of several).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HistoryPoint {
    /// Calendar time of the bin's start, ms since the Unix epoch.
    pub t_ms: i64,
    /// Mean instantaneous estimate, bar.
    pub pressure_bar: Option<f64>,
    /// Mean lower end of the interval, bar.
    pub pressure_lo_bar: Option<f64>,
    /// Mean upper end of the interval, bar.
    pub pressure_hi_bar: Option<f64>,
    /// The worst health in the bin (`leak` > `low` > `unknown` > `ok`).
    pub health: Health,
    /// Whether the damper was excited (velocity RMS ≥ the health threshold).
    pub excited: bool,
}

/// A change of an asset's health.
#[derive(Debug, Clone, PartialEq)]
pub struct HealthChange {
    /// Calendar time, ms since the Unix epoch.
    pub t_ms: i64,
    /// Run.
    pub run_id: String,
    /// From.
    pub from: Health,
    /// To.
    pub to: Health,
}

/// What the store knows of an asset at start-up (to restore the live view).
#[derive(Debug, Clone, PartialEq)]
pub struct AssetState {
    /// Asset.
    pub asset_id: String,
    /// Its latest run.
    pub run_id: String,
    /// Latest 1 s point, if any (one dated ahead of the gateway's clock only
    /// when there is no other, [`FUTURE_SLACK_MS`]).
    pub last: Option<HistoryPoint>,
    /// Calendar ms of the latest 1 s point not dated ahead of the gateway's
    /// clock: what an upload must not be older than to show.
    pub shown_ms: Option<i64>,
    /// Ticks over every run.
    pub ticks: u64,
    /// Latest run's status and reason.
    pub last_run_status: String,
    /// See `last_run_status`.
    pub last_run_reason: Option<String>,
    /// What the observer made of the latest run, if the model read it.
    pub last_run_observer: Option<crate::server::sink::ObserverRead>,
    /// What the road observer made of the latest run, if a road asset's.
    pub last_run_road: Option<crate::server::sink::RoadRead>,
    /// Whether the latest run's log says it is simulated.
    pub simulated: Option<bool>,
    /// The gateway's wall-clock time (Unix ms) of the latest write of any of
    /// its runs; `None` for runs kept before the store's schema 14.
    pub seen_ms: Option<i64>,
}

/// One write of the daemon, applied in order by the writer thread.
#[derive(Debug, Clone, PartialEq)]
pub enum StoreOp {
    /// A run starts.
    RunStarted {
        /// Unique key of this processing of the run.
        key: String,
        /// Asset.
        asset_id: String,
        /// Run.
        run_id: String,
        /// Source.
        source: String,
        /// Calendar start, ms.
        start_ms: i64,
        /// Whether its log says it is simulated ([`RunRecord::simulated`]).
        simulated: Option<bool>,
    },
    /// One 1 s bin.
    Sample {
        /// Asset.
        asset_id: String,
        /// The point.
        point: HistoryPoint,
    },
    /// A health change.
    Health {
        /// Asset.
        asset_id: String,
        /// The change.
        change: HealthChange,
    },
    /// A run in progress, at the end of one of its 1 s bins: what a
    /// `kill -9` leaves of it (was: `interrupted` with 0 ticks, its history
    /// kept; a helper's trial).
    RunProgress {
        /// The key of its `RunStarted`.
        key: String,
        /// Asset.
        asset_id: String,
        /// Calendar time of its newest estimate so far, ms.
        end_ms: i64,
        /// Ticks so far.
        ticks: u64,
    },
    /// A run ended.
    RunEnded {
        /// The key of its `RunStarted`.
        key: String,
        /// Asset.
        asset_id: String,
        /// Calendar end, ms.
        end_ms: i64,
        /// Ticks.
        ticks: u64,
        /// `completed`, `failed`, `interrupted`.
        status: String,
        /// Why it failed.
        reason: Option<String>,
        /// Its summary.
        summary: Option<RunPoint>,
        /// What the charge observer made of its reversals.
        observer: Option<ObserverCounters>,
        /// What the road observer made of its blocks.
        road: Option<RoadCounters>,
    },
}

impl StoreOp {
    /// The asset written.
    #[must_use]
    pub fn asset_id(&self) -> &str {
        match self {
            Self::RunStarted { asset_id, .. }
            | Self::Sample { asset_id, .. }
            | Self::Health { asset_id, .. }
            | Self::RunProgress { asset_id, .. }
            | Self::RunEnded { asset_id, .. } => asset_id,
        }
    }
}

/// The daemon's durable fleet memory. Writes come from one thread (the
/// store's writer), reads from the HTTP handlers; implementations are
/// shared across threads. `SQLite` today; a distributed deployment puts
/// another implementation behind the same interface.
pub trait FleetStore: Send + Sync + Debug {
    /// Where it lives (for messages).
    fn describe(&self) -> String;
    /// Applies `ops` atomically (one transaction).
    fn apply(&self, ops: &[StoreOp]) -> Result<(), StoreError>;
    /// Every asset's latest state.
    fn asset_states(&self) -> Result<Vec<AssetState>, StoreError>;
    /// The asset's history in `[since_ms, until_ms]`, averaged over
    /// `step_ms` (≥ 1000); `None` for an unknown asset; a
    /// [`StoreError::Request`] when it would be more than `max_points`.
    fn history(
        &self,
        asset_id: &str,
        range_ms: (i64, i64),
        step_ms: i64,
        max_points: usize,
    ) -> Result<Option<Vec<HistoryPoint>>, StoreError>;
    /// Calendar time of the asset's newest point, ms.
    fn newest_ms(&self, asset_id: &str) -> Result<Option<i64>, StoreError>;
    /// The asset's runs, newest first, at most `limit`.
    fn runs(&self, asset_id: &str, limit: usize) -> Result<Vec<RunRecord>, StoreError>;
    /// The asset's health changes, newest first, at most `limit`.
    fn health_changes(&self, asset_id: &str, limit: usize)
        -> Result<Vec<HealthChange>, StoreError>;
    /// Keeps (`Some`) or forgets (`None`) the asset's unit baseline set over
    /// the API (see [`super::baselines`]); committed before it returns.
    fn set_baseline(
        &self,
        asset_id: &str,
        baseline: Option<&StoredBaseline>,
    ) -> Result<(), StoreError>;
    /// Every asset's unit baseline set over the API.
    fn baselines(&self) -> Result<Vec<(String, StoredBaseline)>, StoreError>;
    /// Keeps (`Some`) or forgets (`None`) the asset's pending service;
    /// committed before it returns.
    fn set_service(
        &self,
        asset_id: &str,
        service: Option<&PendingService>,
    ) -> Result<(), StoreError>;
    /// Every asset's pending service.
    fn services(&self) -> Result<Vec<(String, PendingService)>, StoreError>;
    /// Completes the asset's pending service with the baseline read from its
    /// run: the baseline is kept and the service forgotten, in one
    /// transaction.
    fn complete_service(&self, asset_id: &str, baseline: &StoredBaseline)
        -> Result<(), StoreError>;
    /// Deletes points and health changes older than `before_ms`; returns
    /// how many rows went.
    fn prune(&self, before_ms: i64) -> Result<usize, StoreError>;
}

/// Earliest `t_ns` taken as a Unix time (2001-09-09).
const PLAUSIBLE_UNIX_NS: i64 = 1_000_000_000_000_000_000;

/// Maps a run's tick times to calendar milliseconds (see the module doc).
#[derive(Debug, Clone, Copy)]
pub struct CalendarClock {
    offset_ns: i64,
}

impl CalendarClock {
    /// The clock of a run whose first tick is `first_t_ns` and whose
    /// processing started at `started`.
    #[must_use]
    pub fn new(first_t_ns: i64, started: SystemTime) -> Self {
        let wall_ns = started
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX));
        let plausible =
            (PLAUSIBLE_UNIX_NS..=wall_ns.saturating_add(86_400_000_000_000)).contains(&first_t_ns);
        Self {
            offset_ns: if plausible { 0 } else { wall_ns - first_t_ns },
        }
    }

    /// Calendar ms of tick `t_ns`.
    #[must_use]
    pub fn ms(&self, t_ns: i64) -> i64 {
        t_ns.saturating_add(self.offset_ns).div_euclid(1_000_000)
    }
}

/// How far ahead of this gateway's clock a calendar time may be and still
/// order an asset's runs and summary, ms. A clock further ahead (a logger's
/// forward jump, a wrong date) would otherwise make its run the asset's
/// newest, and hide every later upload until the wall clock caught up.
pub const FUTURE_SLACK_MS: i64 = 60_000;

/// This gateway's clock, Unix ms.
#[must_use]
pub fn wall_now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// RFC 3339 (UTC, ms) of a calendar time in ms.
#[must_use]
pub fn rfc3339_ms(t_ms: i64) -> String {
    let t = if t_ms >= 0 {
        UNIX_EPOCH + Duration::from_millis(t_ms.unsigned_abs())
    } else {
        UNIX_EPOCH
    };
    humantime::format_rfc3339_millis(t).to_string()
}

/// RFC 3339 of Unix seconds.
#[must_use]
pub fn rfc3339_s(t_s: f64) -> String {
    rfc3339_ms((t_s * 1e3).round() as i64)
}

/// Parses a time query parameter: RFC 3339 (`2026-11-23T08:00:00Z`) or
/// Unix seconds.
pub fn parse_time_ms(text: &str) -> Result<i64, String> {
    if let Ok(s) = text.parse::<f64>() {
        if s.is_finite() {
            return Ok((s * 1e3).round() as i64);
        }
    }
    humantime::parse_rfc3339_weak(text)
        .map_err(|e| format!("`{text}` is neither RFC 3339 nor Unix seconds: {e}"))
        .and_then(|t| {
            t.duration_since(UNIX_EPOCH)
                .map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
                .map_err(|_| format!("`{text}` is before 1970"))
        })
}

/// A predicted crossing as the API gives it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CrossingView {
    /// Predicted time (RFC 3339), or null.
    pub t: Option<String>,
    /// 95 % interval, lower end.
    pub t_lo: Option<String>,
    /// Upper end (null: unbounded).
    pub t_hi: Option<String>,
    /// Why not predicted, or a note.
    pub reason: Option<String>,
}

impl From<Crossing> for CrossingView {
    fn from(c: Crossing) -> Self {
        Self {
            t: c.t_unix_s.map(rfc3339_s),
            t_lo: c.lo_unix_s.map(rfc3339_s),
            t_hi: c.hi_unix_s.map(rfc3339_s),
            reason: c.reason.map(str::to_owned),
        }
    }
}

/// One run summary as the API gives it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrendPoint {
    /// Run.
    pub run_id: String,
    /// Calendar time (RFC 3339).
    pub t: String,
    /// Summary estimate, bar.
    pub pressure_bar: f64,
    /// Its sd, bar.
    pub sd_bar: f64,
}

/// The fitted line as the API gives it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrendFit {
    /// Reference time (the newest run), RFC 3339.
    pub t0: String,
    /// Charge at `t0`, bar.
    pub intercept_bar: f64,
    /// Rate of change, bar/day (since `onset`, when there is one).
    pub slope_bar_per_day: f64,
    /// When the rate changed (RFC 3339; dt-core `trend`: a significant
    /// hinge): the line before it has `slope_before_bar_per_day`.
    /// `null`: one line through every run.
    pub onset: Option<String>,
    /// The rate before `onset`, bar/day.
    pub slope_before_bar_per_day: Option<f64>,
}

/// `GET /v1/assets/{id}/trend` (SPEC §9), also in `GET /v1/assets`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrendView {
    /// `ok` or `insufficient_data`.
    pub status: &'static str,
    /// Why not `ok`.
    pub reason: Option<String>,
    /// Run summaries fitted.
    pub runs_used: usize,
    /// Leak rate (charge lost per day), bar/day.
    pub leak_rate_bar_per_day: Option<f64>,
    /// Its 95 % interval.
    pub leak_rate_lo_bar_per_day: Option<f64>,
    /// See `leak_rate_lo_bar_per_day`.
    pub leak_rate_hi_bar_per_day: Option<f64>,
    /// The fitted charge at the newest run, bar.
    pub pressure_now_bar: Option<f64>,
    /// The asset's warn threshold, bar.
    pub warn_bar: f64,
    /// The asset's fault threshold, bar.
    pub fault_bar: f64,
    /// Predicted crossing of `warn_bar`.
    pub warn: Option<CrossingView>,
    /// Predicted crossing of `fault_bar`.
    pub fault: Option<CrossingView>,
    /// Days from the newest run to the predicted fault crossing (negative:
    /// already below).
    pub days_to_fault: Option<f64>,
    /// The run summaries, oldest first.
    pub points: Vec<TrendPoint>,
    /// The line.
    pub fit: Option<TrendFit>,
    /// The trend uses the runs from this time on (RFC 3339): the asset's
    /// unit baseline was set then. `null`: every run.
    pub since: Option<String>,
    /// The leak rate changed at this run (RFC 3339): the rate, the charge
    /// now and the crossings are those of the line since then. `null`: one
    /// rate through every run.
    pub onset: Option<String>,
}

/// The part of a [`TrendView`] that `GET /v1/assets` gives per asset
/// (without the points and the line).
#[derive(Debug, Clone, Serialize)]
pub struct TrendSummary<'a> {
    /// See [`TrendView`].
    pub status: &'static str,
    /// See [`TrendView`].
    pub reason: Option<&'a str>,
    /// See [`TrendView`].
    pub runs_used: usize,
    /// See [`TrendView`].
    pub leak_rate_bar_per_day: Option<f64>,
    /// See [`TrendView`].
    pub leak_rate_lo_bar_per_day: Option<f64>,
    /// See [`TrendView`].
    pub leak_rate_hi_bar_per_day: Option<f64>,
    /// See [`TrendView`].
    pub pressure_now_bar: Option<f64>,
    /// See [`TrendView`].
    pub warn: Option<&'a CrossingView>,
    /// See [`TrendView`].
    pub fault: Option<&'a CrossingView>,
    /// See [`TrendView`].
    pub days_to_fault: Option<f64>,
    /// See [`TrendView`].
    pub since: Option<&'a str>,
    /// See [`TrendView`].
    pub onset: Option<&'a str>,
}

impl TrendView {
    /// The summary `GET /v1/assets` gives.
    #[must_use]
    pub fn summary(&self) -> TrendSummary<'_> {
        TrendSummary {
            status: self.status,
            reason: self.reason.as_deref(),
            runs_used: self.runs_used,
            leak_rate_bar_per_day: self.leak_rate_bar_per_day,
            leak_rate_lo_bar_per_day: self.leak_rate_lo_bar_per_day,
            leak_rate_hi_bar_per_day: self.leak_rate_hi_bar_per_day,
            pressure_now_bar: self.pressure_now_bar,
            warn: self.warn.as_ref(),
            fault: self.fault.as_ref(),
            days_to_fault: self.days_to_fault,
            since: self.since.as_deref(),
            onset: self.onset.as_deref(),
        }
    }

    /// This trend, fitted on the runs from `since_ms` on (see
    /// [`Trends::set_since`]); the reason it has no line then says so.
    #[must_use]
    pub fn since(mut self, since_ms: Option<i64>) -> Self {
        if let Some(t) = since_ms {
            let at = rfc3339_ms(t);
            if let Some(reason) = &mut self.reason {
                // read by people (the dashboard shows it): to the minute,
                // without the `T` and milliseconds of the `since` field
                reason.push_str(" since the unit baseline or service of ");
                reason.push_str(&at.get(..16).unwrap_or(&at).replace('T', " "));
                reason.push_str(" UTC");
            }
            self.since = Some(at);
        }
        self
    }

    /// The trend of run summaries `points` (`(run_id, point)`) against the
    /// thresholds.
    #[must_use]
    pub fn compute(points: &[(String, RunPoint)], warn_bar: f64, fault_bar: f64) -> Self {
        let mut sorted: Vec<&(String, RunPoint)> = points.iter().collect();
        sorted.sort_by(|a, b| a.1.t_unix_s.total_cmp(&b.1.t_unix_s));
        let view_points = sorted
            .iter()
            .map(|(run_id, p)| TrendPoint {
                run_id: run_id.clone(),
                t: rfc3339_s(p.t_unix_s),
                pressure_bar: p.pressure_bar,
                sd_bar: p.sd_bar,
            })
            .collect();
        let raw: Vec<RunPoint> = sorted.iter().map(|(_, p)| *p).collect();
        match Trend::fit(&raw) {
            Err(e) => Self {
                status: "insufficient_data",
                reason: Some(e.to_string()),
                runs_used: 0,
                leak_rate_bar_per_day: None,
                leak_rate_lo_bar_per_day: None,
                leak_rate_hi_bar_per_day: None,
                pressure_now_bar: None,
                warn_bar,
                fault_bar,
                warn: None,
                fault: None,
                days_to_fault: None,
                points: view_points,
                fit: None,
                since: None,
                onset: None,
            },
            Ok(tr) => {
                let (lo, hi) = tr.slope_interval();
                let fault = tr.crossing(fault_bar);
                Self {
                    status: "ok",
                    reason: None,
                    runs_used: tr.runs_used,
                    leak_rate_bar_per_day: Some(-tr.slope_bar_per_day),
                    leak_rate_lo_bar_per_day: Some(-hi),
                    leak_rate_hi_bar_per_day: Some(-lo),
                    pressure_now_bar: Some(tr.intercept_bar),
                    warn_bar,
                    fault_bar,
                    warn: Some(tr.crossing(warn_bar).into()),
                    fault: Some(fault.into()),
                    days_to_fault: fault.t_unix_s.map(|t| (t - tr.t_ref_unix_s) / DAY_S),
                    points: view_points,
                    fit: Some(TrendFit {
                        t0: rfc3339_s(tr.t_ref_unix_s),
                        intercept_bar: tr.intercept_bar,
                        slope_bar_per_day: tr.slope_bar_per_day,
                        onset: tr.onset_unix_s.map(rfc3339_s),
                        slope_before_bar_per_day: tr.slope_before_bar_per_day,
                    }),
                    since: None,
                    onset: tr.onset_unix_s.map(rfc3339_s),
                }
            }
        }
    }
}

/// Severity order of a health (`ok` 0 < `unknown` 1 < `low` 2 < `leak` 3).
#[must_use]
pub fn health_code(h: Health) -> i64 {
    match h {
        Health::Ok => 0,
        Health::Unknown => 1,
        Health::Low => 2,
        Health::Leak => 3,
    }
}

/// The inverse of [`health_code`] (anything else: `unknown`).
#[must_use]
pub fn health_from_code(code: i64) -> Health {
    match code {
        0 => Health::Ok,
        2 => Health::Low,
        3 => Health::Leak,
        _ => Health::Unknown,
    }
}

/// Parses a health name (anything else: `unknown`).
#[must_use]
pub fn health_from_str(s: &str) -> Health {
    match s {
        "ok" => Health::Ok,
        "low" => Health::Low,
        "leak" => Health::Leak,
        _ => Health::Unknown,
    }
}
