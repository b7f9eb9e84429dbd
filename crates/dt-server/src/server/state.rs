//! The live view of the fleet served by the HTTP API: per asset the latest
//! estimate, a bounded history and the health; and the live event stream
//! (`GET /v1/events`), a bounded broadcast whose slow readers skip ahead.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::{Arc, PoisonError, RwLock};
use std::time::{SystemTime, UNIX_EPOCH};

use dt_core::estimate::{Estimate, Health};
use serde::Serialize;
use tokio::sync::broadcast;

use super::config::Config;
use super::sink::{ObserverRead, RoadRead, RunEnd, RunInfo, Sink, SinkError};
use super::store::{wall_now_ms, AssetState, CalendarClock, HistoryPoint, FUTURE_SLACK_MS};

/// One event of the live stream; the SSE event name is [`LiveEvent::name`].
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum LiveEvent {
    /// A new estimate.
    Estimate {
        /// Asset.
        asset_id: String,
        /// Run.
        run_id: String,
        /// This processing of the run ([`RunInfo::seq`]): two copies of one
        /// run streamed together (a file uploaded twice) have the same
        /// `run_id` and different `seq`s.
        seq: u64,
        /// The estimate (its fields inline).
        #[serde(flatten)]
        estimate: Estimate,
    },
    /// An asset's health changed.
    Health {
        /// Asset.
        asset_id: String,
        /// Run.
        run_id: String,
        /// Tick of the change.
        t_ns: i64,
        /// Previous health.
        from: Health,
        /// New health.
        to: Health,
    },
    /// A run started or ended.
    Run {
        /// Asset.
        asset_id: String,
        /// Run.
        run_id: String,
        /// See [`LiveEvent::Estimate`]'s.
        seq: u64,
        /// Source (`tcp ADDR`, `inbox FILE`).
        source: String,
        /// `started`, `completed`, `failed`, `interrupted`.
        status: &'static str,
        /// Why it failed.
        #[serde(skip_serializing_if = "Option::is_none")]
        reason: Option<String>,
        /// Whether its log says it is simulated ([`AssetSummary::simulated`]).
        simulated: Option<bool>,
    },
}

impl LiveEvent {
    /// SSE event name: `estimate`, `health` or `run`.
    #[must_use]
    pub fn name(&self) -> &'static str {
        match self {
            LiveEvent::Estimate { .. } => "estimate",
            LiveEvent::Health { .. } => "health",
            LiveEvent::Run { .. } => "run",
        }
    }
}

/// What the API tells about one asset.
#[derive(Debug, Clone, Serialize)]
pub struct AssetSummary {
    /// Asset.
    pub asset_id: String,
    /// Run of the latest estimate.
    pub run_id: String,
    /// Latest instantaneous pressure, bar (null: no estimate yet / NaN).
    pub pressure_bar: Option<f64>,
    /// Latest 1 s average pressure, bar.
    pub pressure_avg_bar: Option<f64>,
    /// Latest central 95 % interval of the pressure, bar (SPEC §2a).
    pub pressure_lo_bar: Option<f64>,
    /// See `pressure_lo_bar`.
    pub pressure_hi_bar: Option<f64>,
    /// Nominal pressure, bar.
    pub expected_bar: f64,
    /// Latest health.
    pub health: Health,
    /// Tick time of the latest estimate, ns (run clock).
    pub last_t_ns: Option<i64>,
    /// Wall-clock time of the latest update, ms since the Unix epoch.
    pub last_update_unix_ms: u64,
    /// Estimates received.
    pub ticks: u64,
    /// Runs of this asset being processed now.
    pub active_runs: u32,
    /// How its last run ended (`completed`, `failed`, `interrupted`), if any.
    pub last_run_status: Option<&'static str>,
    /// Why its last run failed, if it did.
    pub last_run_reason: Option<String>,
    /// What the charge observer made of its last run's reversals (absent
    /// when the model does not read the observer): with
    /// `not_calibrated_here`, why an excited asset stays `unknown`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_run_observer: Option<ObserverRead>,
    /// What the road observer made of its last run's blocks (a road asset):
    /// with `why_none`, why a driven asset stays `unknown`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_run_road: Option<RoadRead>,
    /// Whether the run it shows says it is simulated (its log's metadata
    /// `simulated` key); null: the log does not say. The dashboard marks
    /// simulated assets one by one, so that a fleet mixing real and
    /// simulated runs cannot pass one for the other.
    pub simulated: Option<bool>,
}

/// [`AssetSummary`] with the recent estimates, oldest first.
#[derive(Debug, Clone, Serialize)]
pub struct AssetDetail {
    /// Summary.
    #[serde(flatten)]
    pub summary: AssetSummary,
    /// Recent estimates (bounded ring buffer).
    pub history: Vec<Estimate>,
}

#[derive(Debug)]
struct AssetView {
    summary: AssetSummary,
    history: VecDeque<Estimate>,
    /// Calendar ms of the newest estimate shown ([`CalendarClock`]):
    /// an upload's summary and recent history follow the asset's newest
    /// data, not the run processed last (a backlog of old logs uploaded
    /// after newer ones must not show an old charge as the current one);
    /// a live stream always shows.
    shown_ms: i64,
}

/// The live state shared by the sink thread (writer) and the HTTP handlers.
#[derive(Debug)]
pub struct LiveState {
    assets: RwLock<BTreeMap<String, AssetView>>,
    events: broadcast::Sender<Arc<LiveEvent>>,
    history_len: usize,
}

fn unix_ms(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

impl LiveState {
    /// Keeps `history_len` estimates per asset; the event stream buffers
    /// `event_capacity` events per reader.
    #[must_use]
    pub fn new(history_len: usize, event_capacity: usize) -> Self {
        Self {
            assets: RwLock::new(BTreeMap::new()),
            events: broadcast::channel(event_capacity.max(1)).0,
            history_len,
        }
    }

    /// A new reader of the live events.
    #[must_use]
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<LiveEvent>> {
        self.events.subscribe()
    }

    /// Every asset, by id.
    #[must_use]
    pub fn summaries(&self) -> Vec<AssetSummary> {
        let assets = self.assets.read().unwrap_or_else(PoisonError::into_inner);
        assets.values().map(|a| a.summary.clone()).collect()
    }

    /// One asset with its last `history` estimates (all kept if `None`).
    #[must_use]
    pub fn detail(&self, asset_id: &str, history: Option<usize>) -> Option<AssetDetail> {
        let assets = self.assets.read().unwrap_or_else(PoisonError::into_inner);
        let a = assets.get(asset_id)?;
        let n = history.unwrap_or(a.history.len()).min(a.history.len());
        Some(AssetDetail {
            summary: a.summary.clone(),
            history: a
                .history
                .iter()
                .skip(a.history.len() - n)
                .copied()
                .collect(),
        })
    }

    /// Seeds the view with what the fleet store remembers (at start-up):
    /// every asset with its latest 1 s point and its last run.
    pub fn restore(&self, states: &[AssetState], config: &Config) {
        let mut assets = self.assets.write().unwrap_or_else(PoisonError::into_inner);
        for st in states {
            let last = st.last.as_ref();
            let at = |f: fn(&HistoryPoint) -> Option<f64>| last.and_then(f);
            let summary = AssetSummary {
                asset_id: st.asset_id.clone(),
                run_id: st.run_id.clone(),
                pressure_bar: at(|p| p.pressure_bar),
                pressure_avg_bar: at(|p| p.pressure_bar),
                pressure_lo_bar: at(|p| p.pressure_lo_bar),
                pressure_hi_bar: at(|p| p.pressure_hi_bar),
                expected_bar: config.asset(&st.asset_id).nominal_bar,
                health: last.map_or(Health::Unknown, |p| p.health),
                last_t_ns: None,
                // wall-clock time, as while the daemon runs (the data's own
                // clock before: an old upload read "1107 d ago" after a
                // restart; a helper's trial); 0, unknown, for older stores
                last_update_unix_ms: st.seen_ms.map_or(0, |ms| u64::try_from(ms).unwrap_or(0)),
                ticks: st.ticks,
                active_runs: 0,
                // An asset known only by its baseline has no run yet.
                last_run_status: match st.last_run_status.as_str() {
                    "completed" => Some("completed"),
                    "failed" => Some("failed"),
                    "running" => Some("running"),
                    _ if st.run_id.is_empty() => None,
                    _ => Some("interrupted"),
                },
                last_run_reason: st.last_run_reason.clone(),
                last_run_observer: st.last_run_observer,
                last_run_road: st.last_run_road.clone(),
                simulated: st.simulated,
            };
            assets.insert(
                st.asset_id.clone(),
                AssetView {
                    summary,
                    history: VecDeque::new(),
                    shown_ms: st.shown_ms.unwrap_or(i64::MIN),
                },
            );
        }
    }

    fn publish(&self, event: LiveEvent) {
        // No reader is not an error.
        let _ = self.events.send(Arc::new(event));
    }

    /// Whether anyone reads the live events (an SSE client): without one, the
    /// sink does not build them.
    fn listened(&self) -> bool {
        self.events.receiver_count() > 0
    }

    fn with_asset<R>(&self, run: &RunInfo, f: impl FnOnce(&mut AssetView) -> R) -> R {
        let mut assets = self.assets.write().unwrap_or_else(PoisonError::into_inner);
        // The asset is known after its first batch: no key to copy then.
        if let Some(view) = assets.get_mut(run.meta.asset_id.as_str()) {
            return f(view);
        }
        // said once, so that a mistyped asset id is seen (it joins the fleet as any other)
        tracing::info!(asset = %run.meta.asset_id, run = %run.meta.run_id, source = %run.source,
            "a new asset joins the fleet");
        let view = assets
            .entry(run.meta.asset_id.clone())
            .or_insert_with(|| AssetView {
                summary: AssetSummary {
                    asset_id: run.meta.asset_id.clone(),
                    run_id: run.meta.run_id.clone(),
                    pressure_bar: None,
                    pressure_avg_bar: None,
                    pressure_lo_bar: None,
                    pressure_hi_bar: None,
                    expected_bar: run.asset.nominal_bar,
                    health: Health::Unknown,
                    last_t_ns: None,
                    last_update_unix_ms: unix_ms(SystemTime::now()),
                    ticks: 0,
                    active_runs: 0,
                    last_run_status: None,
                    last_run_reason: None,
                    last_run_observer: None,
                    last_run_road: None,
                    simulated: run.meta.simulated(),
                },
                history: VecDeque::with_capacity(self.history_len.min(4096)),
                shown_ms: i64::MIN,
            });
        f(view)
    }

    fn run_event(run: &RunInfo, status: &'static str, reason: Option<String>) -> LiveEvent {
        LiveEvent::Run {
            asset_id: run.meta.asset_id.clone(),
            run_id: run.meta.run_id.clone(),
            seq: run.seq,
            source: run.source.clone(),
            status,
            reason,
            simulated: run.meta.simulated(),
        }
    }
}

/// The [`Sink`] that keeps [`LiveState`] up to date.
#[derive(Debug)]
pub struct LiveSink {
    state: Arc<LiveState>,
    /// Each run in progress.
    runs: HashMap<u64, RunSeen>,
}

/// What [`LiveSink`] keeps of a run in progress.
#[derive(Debug, Default)]
struct RunSeen {
    /// Its calendar clock (from its first estimate).
    clock: Option<CalendarClock>,
    /// Whether any of its estimates was the asset's newest.
    shown_any: bool,
    /// How far its newest calendar time ran ahead of this gateway's clock, ms.
    ahead_ms: i64,
}

impl LiveSink {
    /// The sink that keeps `state` up to date.
    #[must_use]
    pub fn new(state: Arc<LiveState>) -> Self {
        Self {
            state,
            runs: HashMap::new(),
        }
    }
}

impl Sink for LiveSink {
    fn name(&self) -> &'static str {
        "live"
    }

    fn run_started(&mut self, run: &RunInfo) -> Result<(), SinkError> {
        self.runs.insert(run.seq, RunSeen::default());
        self.state.with_asset(run, |v| {
            v.summary.active_runs += 1;
            v.summary.expected_bar = run.asset.nominal_bar;
        });
        self.state
            .publish(LiveState::run_event(run, "started", None));
        Ok(())
    }

    fn estimates(&mut self, run: &RunInfo, batch: &[Estimate]) -> Result<(), SinkError> {
        let Some(first) = batch.first() else {
            return Ok(());
        };
        let state = &self.state;
        let seen = self.runs.entry(run.seq).or_default();
        let clock = *seen
            .clock
            .get_or_insert_with(|| CalendarClock::new(first.t_ns, run.started));
        // An estimate further ahead of this gateway's clock (a logger's
        // forward jump, a wrong date) is shown, but what comes after it is
        // judged against the time before it ([`FUTURE_SLACK_MS`]).
        let future_ms = wall_now_ms().saturating_add(FUTURE_SLACK_MS);
        let mut changes = Vec::new();
        state.with_asset(run, |v| {
            let mut health = v.summary.health;
            let mut newest = None;
            // An upload (inbox, `POST /v1/runs`) shows only what is not
            // older than what the asset shows: a backlog of older logs
            // processed later keeps its estimates to the store. The run the
            // asset shows, sent again (streamed, then its file uploaded),
            // does not repeat its last tick in the history; another run at
            // the same time (simulated runs share a clock) takes its place.
            // A live stream (TCP, NATS) is the asset now, whatever its clock
            // says.
            let live = run.kind.is_live();
            let again = v.summary.run_id == run.meta.run_id;
            for e in batch {
                let ms = clock.ms(e.t_ns);
                if !live && (ms < v.shown_ms || (again && ms == v.shown_ms)) {
                    continue;
                }
                if ms > future_ms {
                    seen.ahead_ms = seen.ahead_ms.max(ms - future_ms + FUTURE_SLACK_MS);
                } else {
                    v.shown_ms = v.shown_ms.max(ms);
                }
                if e.health != health {
                    changes.push((e.t_ns, health, e.health));
                    health = e.health;
                }
                if v.history.len() == state.history_len {
                    v.history.pop_front();
                }
                v.history.push_back(*e);
                newest = Some(e);
            }
            let s = &mut v.summary;
            s.ticks += batch.len() as u64;
            let Some(last) = newest else { return };
            seen.shown_any = true;
            s.run_id.clone_from(&run.meta.run_id);
            s.simulated = run.meta.simulated();
            s.pressure_bar = finite(last.pressure_bar);
            s.pressure_avg_bar = finite(last.pressure_avg_bar);
            s.pressure_lo_bar = finite(last.pressure_lo_bar);
            s.pressure_hi_bar = finite(last.pressure_hi_bar);
            s.expected_bar = last.expected_bar;
            s.health = health;
            s.last_t_ns = Some(last.t_ns);
            s.last_update_unix_ms = unix_ms(SystemTime::now());
        });
        if !state.listened() {
            return Ok(());
        }
        // Events are published outside the lock, in order.
        let mut changes = changes.into_iter().peekable();
        for e in batch {
            while let Some(&(t_ns, from, to)) = changes.peek() {
                if t_ns > e.t_ns {
                    break;
                }
                changes.next();
                state.publish(LiveEvent::Health {
                    asset_id: run.meta.asset_id.clone(),
                    run_id: run.meta.run_id.clone(),
                    t_ns,
                    from,
                    to,
                });
            }
            state.publish(LiveEvent::Estimate {
                asset_id: run.meta.asset_id.clone(),
                run_id: run.meta.run_id.clone(),
                seq: run.seq,
                estimate: *e,
            });
        }
        Ok(())
    }

    fn run_ended(&mut self, run: &RunInfo, end: &RunEnd) -> Result<(), SinkError> {
        let outcome = &end.outcome;
        // A run whose every estimate was older than the asset's newest is
        // not its last run; one with no estimate at all cannot be placed and
        // is reported (a failure to read a new upload must show).
        let seen = self.runs.remove(&run.seq).unwrap_or_default();
        let last = seen.clock.is_none() || seen.shown_any;
        if seen.ahead_ms > 0 {
            tracing::warn!(
                asset = %run.meta.asset_id,
                run_id = %run.meta.run_id,
                "its clock ran up to {:.0} s ahead of this gateway's: shown, but an upload \
                 of the asset's later data is not hidden behind it",
                seen.ahead_ms as f64 / 1e3
            );
        }
        self.state.with_asset(run, |v| {
            v.summary.active_runs = v.summary.active_runs.saturating_sub(1);
            if last {
                v.summary.last_run_status = Some(outcome.status());
                v.summary.last_run_reason = outcome.reason().map(str::to_owned);
                v.summary.last_run_observer = end.observer;
                v.summary.last_run_road.clone_from(&end.road);
            }
        });
        self.state.publish(LiveState::run_event(
            run,
            outcome.status(),
            outcome.reason().map(str::to_owned),
        ));
        Ok(())
    }

    fn close(&mut self) -> Result<(), SinkError> {
        Ok(())
    }
}
