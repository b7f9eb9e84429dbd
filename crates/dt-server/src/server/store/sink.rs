//! [`StoreSink`]: bins each run's estimates to 1 s, summarises each run, and
//! hands the rows to the store's writer thread through a bounded queue; the
//! writer commits a transaction per flush interval and refreshes the trends
//! ([`Trends`]) of the assets whose runs ended. A run's end is committed at
//! once, and [`StoreSink::run_ended`] returns only when it is: the inbox
//! moves a file to `done/` after that, so a `kill -9` can never leave a file
//! in `done/` whose run the store does not have.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError, SyncSender};
use std::sync::{Arc, Condvar, Mutex, PoisonError, RwLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use dt_core::estimate::{Estimate, Health};
use dt_core::trend::RunPoint;

use super::{
    health_code, CalendarClock, FleetStore, HealthChange, HistoryPoint, RunRecord, StoreOp,
    TrendView, SUMMARY_MIN_BINS, SUMMARY_SETTLE_S,
};
use crate::server::config::Config;
use crate::server::metrics::Metrics;
use crate::server::sink::{RunEnd, RunInfo, Sink, SinkError};

/// Ops queued for the writer at most (a full queue makes the sink thread
/// wait: backpressure, nothing dropped).
pub const QUEUE_OPS: usize = 8192;
/// Ops committed in one transaction at most.
const MAX_BATCH: usize = 20_000;
/// How often the writer applies the retention, s.
const PRUNE_EVERY_S: u64 = 600;

/// What the writer thread publishes for the HTTP handlers: the latest trend
/// of every asset, and the store's last write error while it lasts.
#[derive(Debug, Default)]
pub struct Trends {
    map: RwLock<HashMap<String, Arc<TrendView>>>,
    problem: RwLock<Option<String>>,
    since_ms: RwLock<HashMap<String, i64>>,
}

impl Trends {
    /// Why the last write to the store failed (disk full, I/O error), until
    /// a write succeeds again: `/readyz` reports it.
    #[must_use]
    pub fn store_problem(&self) -> Option<String> {
        self.problem
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    fn set_problem(&self, problem: Option<String>) {
        *self.problem.write().unwrap_or_else(PoisonError::into_inner) = problem;
    }

    /// The asset's trend, if the store has seen it.
    #[must_use]
    pub fn get(&self, asset_id: &str) -> Option<Arc<TrendView>> {
        self.map
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .cloned()
    }

    fn set(&self, asset_id: &str, view: TrendView) {
        self.map
            .write()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(asset_id.to_owned(), Arc::new(view));
    }

    /// From now on the asset's trend is fitted on the runs that started at
    /// or after `since_ms` (calendar ms; its unit baseline was set then: the
    /// runs before were estimated with another correction, and a baseline
    /// usually follows a service that refilled the charge), or on every run
    /// (`None`). Takes effect at the next [`Trends::refresh`].
    pub fn set_since(&self, asset_id: &str, since_ms: Option<i64>) {
        let mut map = self
            .since_ms
            .write()
            .unwrap_or_else(PoisonError::into_inner);
        match since_ms {
            Some(t) => map.insert(asset_id.to_owned(), t),
            None => map.remove(asset_id),
        };
    }

    /// Where the asset's trend starts (see [`Trends::set_since`]).
    #[must_use]
    pub fn since(&self, asset_id: &str) -> Option<i64> {
        self.since_ms
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .copied()
    }

    /// Recomputes the trend of `asset_id` from the store and publishes it
    /// (also to the metrics).
    pub fn refresh(
        &self,
        store: &dyn FleetStore,
        config: &Config,
        metrics: &Metrics,
        asset_id: &str,
    ) {
        let runs = match store.runs(asset_id, usize::MAX) {
            Ok(r) => r,
            Err(e) => {
                metrics.error("store");
                tracing::error!(asset = asset_id, "trend: {e}");
                return;
            }
        };
        let since = self
            .since_ms
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .copied();
        let points = one_point_per_run(
            runs.into_iter()
                .filter(|r| since.is_none_or(|t| r.start_ms >= t)),
            super::wall_now_ms().saturating_add(super::FUTURE_SLACK_MS),
        );
        let a = config.asset(asset_id);
        let view = TrendView::compute(&points, a.warn_bar, a.fault_bar).since(since);
        metrics.set_trend(asset_id, view.leak_rate_bar_per_day, view.days_to_fault);
        self.set(asset_id, view);
    }
}

/// The trend's points: one per run id. A run sent again (a vehicle retrying,
/// a file copied into the inbox under another name, a failed attempt then a
/// whole one) weighed once per copy: three copies of one run narrowed the
/// leak rate's interval and moved the fault date (sixty-second session, a
/// helper trying the daemon). A completed copy wins, then the newest. A run
/// whose reading is dated after `future_ms` (a logger's clock ahead of this
/// gateway's, [`super::FUTURE_SLACK_MS`]) cannot be placed and is left out
/// (days ahead, it would set the leak rate alone) until the wall clock
/// passes its date.
fn one_point_per_run(
    runs: impl Iterator<Item = RunRecord>,
    future_ms: i64,
) -> Vec<(String, RunPoint)> {
    let mut best: std::collections::BTreeMap<String, (bool, i64, RunPoint)> =
        std::collections::BTreeMap::new();
    for r in runs {
        let Some(point) = r.summary else { continue };
        if point.t_unix_s * 1e3 > future_ms as f64 {
            continue;
        }
        let key = (r.status == "completed", r.start_ms);
        match best.get(&r.run_id) {
            Some((done, start, _)) if (*done, *start) >= key => {}
            _ => {
                best.insert(r.run_id, (key.0, key.1, point));
            }
        }
    }
    best.into_iter()
        .map(|(run_id, (_, _, point))| (run_id, point))
        .collect()
}

#[derive(Debug, Default)]
struct Mean {
    sum: f64,
    n: u32,
}

impl Mean {
    fn add(&mut self, v: f64) {
        if v.is_finite() {
            self.sum += v;
            self.n += 1;
        }
    }
    fn get(&self) -> Option<f64> {
        (self.n > 0).then(|| self.sum / f64::from(self.n))
    }
}

#[derive(Debug)]
struct Bin {
    sec: i64,
    n: u32,
    pressure: Mean,
    lo: Mean,
    hi: Mean,
    /// The estimate and the interval's half-width before the floor at 0 bar,
    /// for the run's summary (`Estimate::unfloored_bar`).
    unfloored: Mean,
    unfloored_half: Mean,
    v2_sum: f64,
    health: Health,
}

impl Bin {
    fn new(sec: i64) -> Self {
        Self {
            sec,
            n: 0,
            pressure: Mean::default(),
            lo: Mean::default(),
            hi: Mean::default(),
            unfloored: Mean::default(),
            unfloored_half: Mean::default(),
            v2_sum: 0.0,
            health: Health::Ok,
        }
    }

    /// Takes one estimate's pressures and velocity (not its health).
    fn add(&mut self, e: &Estimate) {
        self.n += 1;
        self.pressure.add(e.pressure_bar);
        self.lo.add(e.pressure_lo_bar);
        self.hi.add(e.pressure_hi_bar);
        if e.pressure_bar.is_finite() {
            self.unfloored.add(e.unfloored_bar);
        }
        if e.pressure_lo_bar.is_finite() && e.pressure_hi_bar.is_finite() {
            self.unfloored_half.add(e.unfloored_half_bar);
        }
        if e.velocity_mps.is_finite() {
            self.v2_sum += e.velocity_mps * e.velocity_mps;
        }
    }

    /// The second's pressure and interval half-width for the run's summary:
    /// before the floor at 0 bar (floored, a run near 0 would read high, with
    /// a narrower interval, and weigh more in the trend than it should), or
    /// the floored ones where the estimates did not carry them (a record, an
    /// older NATS worker).
    fn for_summary(&self) -> Option<(f64, Option<f64>)> {
        let p = self.unfloored.get().or_else(|| self.pressure.get())?;
        let half = self.unfloored_half.get().or_else(|| {
            self.lo
                .get()
                .zip(self.hi.get())
                .map(|(lo, hi)| 0.5 * (hi - lo))
        });
        Some((p, half))
    }
}

#[derive(Debug)]
struct RunAcc {
    key: String,
    clock: Option<CalendarClock>,
    bin: Option<Bin>,
    /// Excited bins: (`t_ms`, mean pressure, mean interval half-width).
    excited: Vec<(i64, f64, Option<f64>)>,
    ticks: u64,
    health: Health,
    last_ms: Option<i64>,
}

/// The [`Sink`] that feeds the fleet store.
#[derive(Debug)]
pub struct StoreSink {
    tx: Option<SyncSender<StoreOp>>,
    writer: Option<JoinHandle<()>>,
    /// Ops sent to the writer so far.
    sent: AtomicU64,
    /// Ops the writer has committed (or given up on), with a wake-up.
    committed: Arc<Committed>,
    runs: HashMap<u64, RunAcc>,
    boot_ms: i64,
    min_excitation_mps: f64,
    metrics: Arc<Metrics>,
}

/// How many ops the writer has handled, for [`StoreSink::run_ended`] to wait on.
#[derive(Debug, Default)]
struct Committed {
    ops: Mutex<u64>,
    cv: Condvar,
}

impl Committed {
    fn set(&self, ops: u64) {
        *self.ops.lock().unwrap_or_else(PoisonError::into_inner) = ops;
        self.cv.notify_all();
    }

    /// Waits until `ops` are handled; false after `timeout`.
    fn wait_for(&self, ops: u64, timeout: Duration) -> bool {
        let guard = self.ops.lock().unwrap_or_else(PoisonError::into_inner);
        let (guard, _) = self
            .cv
            .wait_timeout_while(guard, timeout, |n| *n < ops)
            .unwrap_or_else(PoisonError::into_inner);
        *guard >= ops
    }
}

/// How long a run's end waits for its commit before the sink gives up
/// (a store that slow is reported; the run is not held forever).
const COMMIT_WAIT: Duration = Duration::from_secs(30);

fn wall_ms(t: SystemTime) -> i64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

impl StoreSink {
    /// Computes every known asset's trend, then starts the writer thread.
    pub fn start(
        store: Arc<dyn FleetStore>,
        trends: Arc<Trends>,
        config: Arc<Config>,
        metrics: Arc<Metrics>,
    ) -> std::io::Result<Self> {
        match store.asset_states() {
            Ok(states) => {
                for s in &states {
                    trends.refresh(store.as_ref(), &config, &metrics, &s.asset_id);
                }
            }
            Err(e) => {
                metrics.error("store");
                tracing::error!("{e}");
            }
        }
        let (tx, rx) = mpsc::sync_channel::<StoreOp>(QUEUE_OPS);
        let writer_metrics = Arc::clone(&metrics);
        let committed = Arc::new(Committed::default());
        let writer_committed = Arc::clone(&committed);
        let writer = std::thread::Builder::new()
            .name("shocktwin-store".into())
            .spawn(move || {
                write_loop(
                    &rx,
                    store.as_ref(),
                    &trends,
                    &config,
                    &writer_metrics,
                    &writer_committed,
                );
            })?;
        Ok(Self {
            tx: Some(tx),
            writer: Some(writer),
            sent: AtomicU64::new(0),
            committed,
            runs: HashMap::new(),
            boot_ms: super::wall_now_ms(),
            min_excitation_mps: dt_core::bundle::HealthConfig::default().min_excitation_mps,
            metrics,
        })
    }

    fn send(&self, op: StoreOp) {
        if let Some(tx) = &self.tx {
            if tx.send(op).is_ok() {
                self.sent.fetch_add(1, Ordering::Relaxed);
            } else {
                self.metrics.error("store");
                tracing::error!("the fleet store's writer thread is gone; history is not kept");
            }
        }
    }

    fn flush_bin(&self, run: &RunInfo, acc: &mut RunAcc) {
        let Some(bin) = acc.bin.take() else { return };
        let excited =
            bin.n > 0 && (bin.v2_sum / f64::from(bin.n)).sqrt() >= self.min_excitation_mps;
        let point = HistoryPoint {
            t_ms: bin.sec * 1000,
            pressure_bar: bin.pressure.get(),
            pressure_lo_bar: bin.lo.get(),
            pressure_hi_bar: bin.hi.get(),
            health: bin.health,
            excited,
        };
        if excited {
            // The summary takes the values before the floor at 0 bar: floored,
            // a run near 0 would read high, with a narrower interval, and
            // weigh more in the trend than it should.
            if let Some((p, half)) = bin.for_summary() {
                acc.excited.push((point.t_ms, p, half));
            }
        }
        self.send(StoreOp::Sample {
            asset_id: run.meta.asset_id.clone(),
            point,
        });
        if let Some(end_ms) = acc.last_ms {
            self.send(StoreOp::RunProgress {
                key: acc.key.clone(),
                asset_id: run.meta.asset_id.clone(),
                end_ms,
                ticks: acc.ticks,
            });
        }
    }
}

/// The run's summary (see the module doc of `store`).
fn summarise(excited: &[(i64, f64, Option<f64>)]) -> Option<RunPoint> {
    if excited.len() < SUMMARY_MIN_BINS {
        return None;
    }
    let settle_ms = excited[0].0 + (SUMMARY_SETTLE_S * 1e3) as i64;
    let mut used: Vec<&(i64, f64, Option<f64>)> =
        excited.iter().filter(|b| b.0 >= settle_ms).collect();
    if used.len() < SUMMARY_MIN_BINS {
        let take = (excited.len() / 2).max(SUMMARY_MIN_BINS);
        used = excited[excited.len() - take..].iter().collect();
    }
    let n = used.len() as f64;
    let mean = used.iter().map(|b| b.1).sum::<f64>() / n;
    let t_ms = used.iter().map(|b| b.0 as f64).sum::<f64>() / n;
    let halves: Option<Vec<f64>> = used.iter().map(|b| b.2).collect();
    let sd = match halves {
        Some(h) if !h.is_empty() => h.iter().sum::<f64>() / h.len() as f64 / 1.96,
        _ => (used.iter().map(|b| (b.1 - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(),
    };
    Some(RunPoint {
        t_unix_s: t_ms / 1e3,
        pressure_bar: mean,
        sd_bar: sd.max(0.01),
    })
}

impl Sink for StoreSink {
    fn name(&self) -> &'static str {
        "store"
    }

    fn run_started(&mut self, run: &RunInfo) -> Result<(), SinkError> {
        self.runs.insert(
            run.seq,
            RunAcc {
                key: format!("{}-{}", self.boot_ms, run.seq),
                clock: None,
                bin: None,
                excited: Vec::new(),
                ticks: 0,
                health: Health::Unknown,
                last_ms: None,
            },
        );
        Ok(())
    }

    fn estimates(&mut self, run: &RunInfo, batch: &[Estimate]) -> Result<(), SinkError> {
        let Some(mut acc) = self.runs.remove(&run.seq) else {
            return Ok(());
        };
        for e in batch {
            let clock = *acc.clock.get_or_insert_with(|| {
                let clock = CalendarClock::new(e.t_ns, run.started);
                self.send(StoreOp::RunStarted {
                    key: acc.key.clone(),
                    asset_id: run.meta.asset_id.clone(),
                    run_id: run.meta.run_id.clone(),
                    source: run.source.clone(),
                    start_ms: clock.ms(e.t_ns),
                    simulated: run.meta.simulated(),
                });
                clock
            });
            let t_ms = clock.ms(e.t_ns);
            let sec = t_ms.div_euclid(1000);
            if acc.bin.as_ref().is_some_and(|b| b.sec != sec) {
                self.flush_bin(run, &mut acc);
            }
            let bin = acc.bin.get_or_insert_with(|| Bin::new(sec));
            bin.add(e);
            if health_code(e.health) > health_code(bin.health) || bin.n == 1 {
                bin.health = e.health;
            }
            if e.health != acc.health {
                self.send(StoreOp::Health {
                    asset_id: run.meta.asset_id.clone(),
                    change: HealthChange {
                        t_ms,
                        run_id: run.meta.run_id.clone(),
                        from: acc.health,
                        to: e.health,
                    },
                });
                acc.health = e.health;
            }
            acc.ticks += 1;
            acc.last_ms = Some(t_ms);
        }
        self.runs.insert(run.seq, acc);
        Ok(())
    }

    fn run_ended(&mut self, run: &RunInfo, end: &RunEnd) -> Result<(), SinkError> {
        let outcome = &end.outcome;
        let Some(mut acc) = self.runs.remove(&run.seq) else {
            return Ok(());
        };
        self.flush_bin(run, &mut acc);
        let start_ms = wall_ms(run.started);
        if acc.clock.is_none() {
            self.send(StoreOp::RunStarted {
                key: acc.key.clone(),
                asset_id: run.meta.asset_id.clone(),
                run_id: run.meta.run_id.clone(),
                source: run.source.clone(),
                start_ms,
                simulated: run.meta.simulated(),
            });
        }
        self.send(StoreOp::RunEnded {
            key: acc.key,
            asset_id: run.meta.asset_id.clone(),
            end_ms: acc.last_ms.unwrap_or(start_ms),
            ticks: acc.ticks,
            status: outcome.status().to_owned(),
            reason: outcome.reason().map(str::to_owned),
            summary: summarise(&acc.excited),
            observer: end.observer.map(|o| o.counts),
            road: end.road.as_ref().map(|r| r.counts),
        });
        // Durable before the source takes the run as done (SPEC of `Sink`).
        let ops = self.sent.load(Ordering::Relaxed);
        if self.tx.is_some() && !self.committed.wait_for(ops, COMMIT_WAIT) {
            self.metrics.error("store");
            tracing::error!(
                run_id = %run.meta.run_id,
                "the fleet store did not commit the run's end within {COMMIT_WAIT:?}"
            );
        }
        Ok(())
    }

    fn close(&mut self) -> Result<(), SinkError> {
        // The queue closes: the writer commits what is left and stops.
        self.tx = None;
        if let Some(w) = self.writer.take() {
            if w.join().is_err() {
                return Err(SinkError {
                    sink: "store",
                    reason: "the writer thread panicked".into(),
                });
            }
        }
        Ok(())
    }
}

/// The writer thread: one transaction per `flush_ms` (or [`MAX_BATCH`]
/// ops), then the trends of the assets whose runs ended; retention every
/// [`PRUNE_EVERY_S`].
fn write_loop(
    rx: &mpsc::Receiver<StoreOp>,
    store: &dyn FleetStore,
    trends: &Trends,
    config: &Config,
    metrics: &Metrics,
    committed: &Committed,
) {
    let flush = Duration::from_millis(config.store.flush_ms);
    let mut received: u64 = 0;
    let mut pending: Vec<StoreOp> = Vec::new();
    let mut first_pending = Instant::now();
    let mut last_prune: Option<Instant> = None;
    loop {
        let wait = if pending.is_empty() {
            flush
        } else {
            flush.saturating_sub(first_pending.elapsed())
        };
        let closed = match rx.recv_timeout(wait) {
            Ok(op) => {
                if pending.is_empty() {
                    first_pending = Instant::now();
                }
                received += 1;
                // A run's end is committed at once: its sink waits for it.
                let run_end = matches!(op, StoreOp::RunEnded { .. });
                pending.push(op);
                if !run_end && pending.len() < MAX_BATCH && first_pending.elapsed() < flush {
                    continue;
                }
                false
            }
            Err(RecvTimeoutError::Timeout) => false,
            Err(RecvTimeoutError::Disconnected) => true,
        };
        if !pending.is_empty() {
            commit(&mut pending, store, trends, config, metrics);
        }
        // Committed, or failed and said so: either way nobody waits on it any more.
        committed.set(received);
        if let Some(days) = config.store.retention_days {
            if last_prune.is_none_or(|t| t.elapsed() >= Duration::from_secs(PRUNE_EVERY_S)) {
                last_prune = Some(Instant::now());
                let before = super::wall_now_ms() - (days * 86_400_000.0) as i64;
                match store.prune(before) {
                    Ok(n) if n > 0 => tracing::info!(rows = n, "fleet store: retention applied"),
                    Ok(_) => {}
                    Err(e) => {
                        metrics.error("store");
                        tracing::error!("{e}");
                    }
                }
            }
        }
        if closed {
            break;
        }
    }
}

fn commit(
    pending: &mut Vec<StoreOp>,
    store: &dyn FleetStore,
    trends: &Trends,
    config: &Config,
    metrics: &Metrics,
) {
    let ended: HashSet<String> = pending
        .iter()
        .filter_map(|op| match op {
            StoreOp::RunEnded { asset_id, .. } => Some(asset_id.clone()),
            _ => None,
        })
        .collect();
    match store.apply(pending) {
        Ok(()) => trends.set_problem(None),
        Err(e) => {
            // Disk full, I/O error: said once per batch, the batch is lost,
            // `/readyz` says why until a write succeeds; the daemon carries on
            // (the live view and recordings are unaffected).
            metrics.error("store");
            tracing::error!(ops = pending.len(), "{e}; this batch of history is lost");
            trends.set_problem(Some(e.to_string()));
        }
    }
    pending.clear();
    for asset in ended {
        trends.refresh(store, config, metrics, &asset);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(run_id: &str, status: &str, start_ms: i64, bar: Option<f64>) -> RunRecord {
        RunRecord {
            run_id: run_id.into(),
            source: "tcp 127.0.0.1:1".into(),
            start_ms,
            end_ms: Some(start_ms + 70_000),
            ticks: 3500,
            status: status.into(),
            reason: None,
            summary: bar.map(|pressure_bar| RunPoint {
                t_unix_s: start_ms as f64 * 1e-3,
                pressure_bar,
                sd_bar: 0.1,
            }),
            observer: None,
            road: None,
            simulated: Some(true),
        }
    }

    /// A run sent three times (a failed attempt, two whole copies) is one
    /// point: its completed copy, the newest of them. A run dated ahead of
    /// the gateway's clock is none.
    #[test]
    fn a_run_sent_again_is_one_point() {
        let day = 86_400_000;
        let points = one_point_per_run(
            [
                run("d7", "failed", 7 * day, Some(9.0)),
                run("d7", "completed", 7 * day + 10, Some(8.0)),
                run("d7", "completed", 7 * day + 20, Some(8.1)),
                run("d6", "completed", 6 * day, Some(8.5)),
                run("d5", "failed", 5 * day, Some(9.5)),
                run("d4", "completed", 4 * day, None),
                run("d9", "completed", 9 * day, Some(1.0)),
            ]
            .into_iter(),
            8 * day,
        );
        let got: Vec<(&str, f64)> = points
            .iter()
            .map(|(id, p)| (id.as_str(), p.pressure_bar))
            .collect();
        assert_eq!(got, [("d5", 9.5), ("d6", 8.5), ("d7", 8.1)]);
    }

    fn estimate(shown: [f64; 3], unfloored: f64, half: f64) -> Estimate {
        Estimate {
            t_ns: 0,
            pressure_bar: shown[0],
            pressure_avg_bar: shown[0],
            pressure_lo_bar: shown[1],
            pressure_hi_bar: shown[2],
            expected_bar: 12.0,
            health: Health::Leak,
            velocity_mps: 0.3,
            force_model_n: 0.0,
            oil_temp_c: 30.0,
            unfloored_bar: unfloored,
            unfloored_half_bar: half,
        }
    }

    /// A run near 0 bar is summarised from its estimates before the floor:
    /// shown as 0 [0, 2.0], read −0.5 ± 2.5, it enters the trend as −0.5 with
    /// sd 2.5 / 1.96, not as 0 with sd 1.0 / 1.96.
    #[test]
    fn a_run_near_ambient_is_summarised_before_the_floor() {
        let mut floored = Bin::new(0);
        for _ in 0..50 {
            floored.add(&estimate([0.0, 0.0, 2.0], -0.5, 2.5));
        }
        assert_eq!(floored.for_summary(), Some((-0.5, Some(2.5))));
        let seconds: Vec<(i64, f64, Option<f64>)> = (0..SUMMARY_MIN_BINS as i64 + 60)
            .map(|k| (k * 1000, -0.5, Some(2.5)))
            .collect();
        let p = summarise(&seconds).unwrap();
        assert_eq!(p.pressure_bar.to_bits(), (-0.5_f64).to_bits());
        assert!((p.sd_bar - 2.5 / 1.96).abs() < 1e-12, "{}", p.sd_bar);
        // Estimates without the pair (a record, an older NATS worker): the
        // shown values, as before.
        let mut shown = Bin::new(0);
        shown.add(&estimate([3.0, 1.0, 5.0], f64::NAN, f64::NAN));
        shown.add(&estimate([3.2, 1.2, 5.2], f64::NAN, f64::NAN));
        let (p, half) = shown.for_summary().unwrap();
        assert!((p - 3.1).abs() < 1e-12 && (half.unwrap() - 2.0).abs() < 1e-12);
        // No estimate: nothing to summarise.
        assert_eq!(Bin::new(0).for_summary(), None);
    }
}
