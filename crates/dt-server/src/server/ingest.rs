//! The common path of every source: an MCAP byte stream (a socket, a file)
//! is decoded incrementally with `dt_core::log::LogDecoder`, its samples are
//! fed to the run's [`AssetTwin`] and its estimates go to the sinks through
//! the bounded sink queue.
//!
//! Sources that do not carry MCAP (a message bus partitioned by asset) use
//! [`Ingest::open_run`] and [`RunHandle`] directly.

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use dt_core::estimate::Estimate;
use dt_core::log::{LogDecoder, LogError, LogEvent, ReadLimits, RunMetadata, Sample};
use serde::Serialize;
use tokio::io::{AsyncRead, AsyncReadExt};
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;

use super::baselines::{recorded_before, Baselines, ServiceOutcome};
use super::config::Config;
use super::metrics::{AssetLabel, Metrics, SourceLabel};
use super::sink::{ObserverRead, RoadRead, RunEnd, RunInfo, RunOutcome, SinkMsg, SourceKind};
use super::store::{AssetBaseline, FleetStore};
use super::twin::{AssetTwin, TwinCounters, TwinError, TwinFactory};

/// Bytes read from a stream at a time.
const READ_BUF_BYTES: usize = 64 << 10;

/// The metric label of a decoding error.
#[must_use]
pub fn error_kind(e: &LogError) -> &'static str {
    match e {
        LogError::Io { .. } => "io",
        LogError::Mcap { .. } => "invalid_mcap",
        LogError::Truncated { .. } => "truncated",
        LogError::TooLarge { .. } => "too_large",
        LogError::MissingMetadata { .. } | LogError::InvalidMetadata { .. } => "metadata",
        LogError::Encoding { .. } | LogError::Schema { .. } => "schema",
        LogError::Message { .. } => "message",
        _ => "log",
    }
}

/// What became of one byte stream.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    /// `completed`, `failed` or `interrupted`.
    pub status: &'static str,
    /// Error kind, when failed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kind: Option<&'static str>,
    /// Why it failed (or why the sinks could not keep it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Asset, once the metadata was read.
    pub asset_id: Option<String>,
    /// Run, once the metadata was read.
    pub run_id: Option<String>,
    /// Sensor samples decoded.
    pub samples: u64,
    /// Estimates emitted.
    pub ticks: u64,
    /// Whether every estimate reached every sink (and is durable).
    pub flushed: bool,
    /// Messages that could not be decoded and were skipped (the stream
    /// went on without them).
    pub skipped_messages: u64,
    /// Why the first of them was skipped (topic, field, value).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_skipped: Option<String>,
    /// Samples decoded but not used: too late for the estimator's
    /// reordering window (a clock that jumped back, or samples sent out of
    /// order) or far ahead of the stream (corrupt timestamps). A run can
    /// complete with many of them: it then says so here and in the log.
    pub dropped_samples: u64,
    /// Forward clock jumps, each of which restarted the asset's twin.
    pub clock_jumps: u64,
}

/// Skipped messages of one stream logged each; the rest are counted.
const LOGGED_SKIPS: u64 = 5;

/// Messages a stream skipped: how many, and why the first was.
#[derive(Debug, Default)]
struct Skipped {
    count: u64,
    first: Option<String>,
}

impl RunReport {
    /// True when the stream was complete and everything was flushed.
    #[must_use]
    pub fn ok(&self) -> bool {
        self.status == "completed" && self.flushed
    }
}

/// The sinks are gone (the daemon is stopping abnormally).
#[derive(Debug, Clone, Copy, thiserror::Error)]
#[error("the sink queue is closed")]
pub struct SinkClosed;

struct Inner {
    config: Arc<Config>,
    twins: Arc<dyn TwinFactory>,
    sink_tx: mpsc::Sender<SinkMsg>,
    metrics: Arc<Metrics>,
    baselines: Arc<Baselines>,
    /// Where a service's baseline read by a run is kept.
    store: Option<Arc<dyn FleetStore>>,
    next_seq: AtomicU64,
}

/// Handle shared by the sources; cheap to clone. The daemon's sinks stop
/// once every clone is dropped.
#[derive(Clone)]
pub struct Ingest {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Ingest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ingest")
            .field("twins", &self.inner.twins.describe())
            .finish_non_exhaustive()
    }
}

impl Ingest {
    pub(crate) fn new(
        config: Arc<Config>,
        twins: Arc<dyn TwinFactory>,
        sink_tx: mpsc::Sender<SinkMsg>,
        metrics: Arc<Metrics>,
        baselines: Arc<Baselines>,
        store: Option<Arc<dyn FleetStore>>,
    ) -> Self {
        Self {
            inner: Arc::new(Inner {
                config,
                twins,
                sink_tx,
                metrics,
                baselines,
                store,
                next_seq: AtomicU64::new(1),
            }),
        }
    }

    /// The daemon's metrics.
    #[must_use]
    pub fn metrics(&self) -> &Metrics {
        &self.inner.metrics
    }

    /// The unit baselines set over the API (or from the NATS group).
    #[must_use]
    pub fn baselines(&self) -> &Arc<Baselines> {
        &self.inner.baselines
    }

    /// The daemon's configuration.
    #[must_use]
    pub fn config(&self) -> &Config {
        &self.inner.config
    }

    /// Whether the daemon has a fleet store.
    #[must_use]
    pub fn has_store(&self) -> bool {
        self.inner.store.is_some()
    }

    /// Whether the fleet store already holds asset `asset_id`'s run `run_id`
    /// from `source` as completed (among the asset's last 64 runs): a file
    /// processed to completion just before a crash, still in the inbox.
    /// False without a store, or when the store cannot say.
    pub async fn completed_before(&self, asset_id: &str, run_id: &str, source: &str) -> bool {
        let Some(store) = self.inner.store.clone() else {
            return false;
        };
        let (asset_id, run_id, source) =
            (asset_id.to_owned(), run_id.to_owned(), source.to_owned());
        tokio::task::spawn_blocking(move || {
            store.runs(&asset_id, 64).is_ok_and(|runs| {
                runs.iter()
                    .any(|r| r.run_id == run_id && r.source == source && r.status == "completed")
            })
        })
        .await
        .unwrap_or(false)
    }

    /// Starts a run: creates its twin and tells the sinks.
    pub async fn open_run(
        &self,
        kind: SourceKind,
        source: String,
        meta: RunMetadata,
    ) -> Result<RunHandle, RunOutcome> {
        let asset = self
            .inner
            .baselines
            .asset_config(&self.inner.config, &meta.asset_id);
        let twin = self
            .inner
            .twins
            .create(&meta, &asset)
            .map_err(|e| RunOutcome::Failed {
                kind: "twin",
                reason: format!(
                    "{source}: cannot start the twin for asset `{}` run `{}`: {e}",
                    meta.asset_id, meta.run_id
                ),
            })?;
        let handle = self.start(kind, source, meta, &asset, twin).await?;
        tracing::info!(
            source = %handle.info.source,
            asset = %handle.info.meta.asset_id,
            run = %handle.info.meta.run_id,
            "run started"
        );
        Ok(handle)
    }

    /// Tells the sinks a run starts and makes its handle.
    async fn start(
        &self,
        kind: SourceKind,
        source: String,
        meta: RunMetadata,
        asset: &super::config::AssetConfig,
        twin: Box<dyn AssetTwin>,
    ) -> Result<RunHandle, RunOutcome> {
        let info = Arc::new(RunInfo {
            seq: self.inner.next_seq.fetch_add(1, Ordering::Relaxed),
            kind,
            source,
            meta,
            asset: *asset,
            started: SystemTime::now(),
        });
        self.inner
            .sink_tx
            .send(SinkMsg::Started(Arc::clone(&info)))
            .await
            .map_err(|_| sink_closed_outcome())?;
        Ok(RunHandle {
            ingest: self.clone(),
            asset_label: AssetLabel {
                asset: info.meta.asset_id.clone(),
            },
            info,
            twin,
            out: Vec::new(),
            samples: 0,
            samples_reported: 0,
            ticks: 0,
            first_t_ns: None,
            last_t_ns: None,
            arrived: None,
            relayed_observer: None,
            relayed_road: None,
        })
    }

    /// Starts a relayed run: its estimates were made elsewhere (another
    /// worker of a NATS group) and are handed in with
    /// [`RunHandle::relay`]; the sinks see an ordinary run.
    pub async fn open_relay(
        &self,
        kind: SourceKind,
        source: String,
        meta: RunMetadata,
    ) -> Result<RunHandle, RunOutcome> {
        let asset = self
            .inner
            .baselines
            .asset_config(&self.inner.config, &meta.asset_id);
        self.start(kind, source, meta, &asset, Box::new(RelayTwin))
            .await
    }

    /// Reads one MCAP stream to its end — the file's footer, or the
    /// stream's end (or an error, the idle timeout, or `cancel`) — and
    /// processes it as one run. Every outcome is logged once here and
    /// counted in the metrics.
    pub async fn ingest_stream<R: AsyncRead + Unpin>(
        &self,
        kind: SourceKind,
        source: String,
        mut reader: R,
        cancel: &CancellationToken,
        idle: Option<Duration>,
    ) -> RunReport {
        let limits = ReadLimits {
            max_record_bytes: self.inner.config.limits.max_record_bytes,
            max_chunk_uncompressed_bytes: self.inner.config.limits.max_chunk_uncompressed_bytes,
        };
        let mut decoder = LogDecoder::with_limits(&source, limits);
        let mut buf = vec![0u8; READ_BUF_BYTES];
        let mut run: Option<RunHandle> = None;
        let mut unknown_topics = HashSet::new();
        let mut skipped = Skipped::default();
        // The file's footer came: the run ends with its end magic.
        let mut footer = false;
        // `None`: the stream ended; `finish` judges how.
        let outcome = loop {
            let read = async {
                match idle {
                    Some(d) => tokio::time::timeout(d, reader.read(&mut buf)).await.ok(),
                    None => Some(reader.read(&mut buf).await),
                }
            };
            let n = tokio::select! {
                biased;
                () = cancel.cancelled() => break Some(RunOutcome::Interrupted),
                r = read => match r {
                    None => break Some(RunOutcome::Failed {
                        kind: "idle_timeout",
                        reason: format!(
                            "{source}: no data for {:.0} s",
                            idle.unwrap_or_default().as_secs_f64()
                        ),
                    }),
                    Some(Err(e)) => break Some(RunOutcome::Failed {
                        kind: "io",
                        reason: format!("{source}: read failed: {e}"),
                    }),
                    Some(Ok(n)) => n,
                },
            };
            if n == 0 {
                break None;
            }
            let arrived = Instant::now();
            decoder.feed(&buf[..n]);
            match self
                .handle_events(
                    kind,
                    &source,
                    &mut decoder,
                    &mut run,
                    &mut unknown_topics,
                    &mut skipped,
                )
                .await
            {
                Ok(ended) => footer |= ended,
                Err(outcome) => break Some(outcome),
            }
            if let Some(r) = &mut run {
                r.set_arrival(arrived);
                if r.flush().await.is_err() {
                    break Some(sink_closed_outcome());
                }
            }
            if footer && decoder.at_record_boundary() {
                // The file's footer and end magic (which may come in a
                // later read: `finish` took the run for truncated): the run
                // is whole, whether or not the client closes its side. Over TLS a half-close is not to be
                // had from every client (Python's `ssl` drops the session on
                // `shutdown(SHUT_WR)`), and a client that waited for the
                // report waited for the idle timeout instead.
                break None;
            }
        };
        let outcome = match outcome {
            Some(o) => o,
            None => match decoder.finish() {
                Err(e) => failed(&e),
                Ok(()) if run.is_none() => RunOutcome::Failed {
                    kind: "metadata",
                    reason: format!("{source}: stream ended before the `shocktwin.run` metadata"),
                },
                Ok(()) => RunOutcome::Completed,
            },
        };
        self.end(source, run, outcome, skipped).await
    }

    async fn handle_events(
        &self,
        kind: SourceKind,
        source: &str,
        decoder: &mut LogDecoder,
        run: &mut Option<RunHandle>,
        unknown_topics: &mut HashSet<String>,
        skipped: &mut Skipped,
    ) -> Result<bool, RunOutcome> {
        let mut ended = false;
        while let Some(event) = decoder.next_event() {
            match event {
                Ok(LogEvent::Metadata(meta)) => {
                    if let Some(r) = run.as_ref() {
                        if r.info.meta.asset_id != meta.asset_id {
                            return Err(RunOutcome::Failed {
                                kind: "metadata",
                                reason: format!(
                                    "{source}: a second `shocktwin.run` names asset `{}`, the stream is asset `{}` (one asset per stream)",
                                    meta.asset_id, r.info.meta.asset_id
                                ),
                            });
                        }
                    } else {
                        *run = Some(self.open_run(kind, source.to_owned(), meta).await?);
                    }
                }
                Ok(LogEvent::Sample(sample)) => match run.as_mut() {
                    Some(r) => r.push(&sample).map_err(|e| RunOutcome::Failed {
                        kind: "twin",
                        reason: format!("{source}: the twin failed: {e}"),
                    })?,
                    None => {
                        return Err(RunOutcome::Failed {
                            kind: "metadata",
                            reason: format!(
                                "{source}: message before the `shocktwin.run` metadata record"
                            ),
                        })
                    }
                },
                Ok(LogEvent::Unknown { topic, .. }) => {
                    self.inner.metrics.unknown_messages.inc();
                    if unknown_topics.len() < 64 && unknown_topics.insert(topic.clone()) {
                        tracing::warn!(source, topic, "ignoring unknown topic");
                    }
                }
                Ok(LogEvent::End) => ended = true,
                Err(e) if !e.is_fatal() => {
                    // One undecodable message: skipped, the stream goes on.
                    self.inner.metrics.error("message");
                    // the first few said, the rest counted: a logger that writes one field
                    // wrong wrote a warning a message (a helper's trial); the run's end
                    // says how many
                    if skipped.count < LOGGED_SKIPS {
                        tracing::warn!(source, "skipped message: {e}");
                    } else if skipped.count == LOGGED_SKIPS {
                        tracing::warn!(
                            source,
                            "skipped message: {e} (further skipped messages of this stream are \
                             counted, not logged: the run's end says how many)"
                        );
                    }
                    skipped.count += 1;
                    if skipped.first.is_none() {
                        skipped.first = Some(e.to_string());
                    }
                }
                Err(e) => return Err(failed(&e)),
            }
        }
        Ok(ended)
    }

    async fn end(
        &self,
        source: String,
        run: Option<RunHandle>,
        outcome: RunOutcome,
        skipped: Skipped,
    ) -> RunReport {
        let m = &self.inner.metrics;
        let (outcome, asset_id, run_id, samples, ticks, sink_result, counters) = match run {
            Some(r) => {
                let ids = (r.info.meta.asset_id.clone(), r.info.meta.run_id.clone());
                let (outcome, samples, ticks, result, counters) = r.end(outcome).await;
                (
                    outcome,
                    Some(ids.0),
                    Some(ids.1),
                    samples,
                    ticks,
                    result,
                    counters,
                )
            }
            None => (outcome, None, None, 0, 0, Ok(()), TwinCounters::default()),
        };
        let dropped = counters.dropped_late + counters.timestamp_outliers;
        if dropped > 0 {
            // the fleet-wide counters alone did not say which vehicle lost data
            tracing::warn!(
                source,
                asset = asset_id.as_deref().unwrap_or(""),
                run = run_id.as_deref().unwrap_or(""),
                dropped_late = counters.dropped_late,
                timestamp_outliers = counters.timestamp_outliers,
                "{dropped} of {samples} samples not used: {} too late for the reordering window \
                 (a clock that jumped back, or samples sent out of order), {} far ahead of the \
                 stream (corrupt timestamps)",
                counters.dropped_late,
                counters.timestamp_outliers
            );
        }
        if let RunOutcome::Failed { kind, reason } = &outcome {
            m.error(kind);
            tracing::warn!(source, kind, "stream closed: {reason}");
        }
        Metrics::add(&m.runs, outcome.status(), 1);
        if matches!(outcome, RunOutcome::Completed) {
            if skipped.count > 0 {
                tracing::warn!(
                    source,
                    samples,
                    ticks,
                    skipped = skipped.count,
                    "run completed without {} undecodable message(s); the first: {}",
                    skipped.count,
                    skipped.first.as_deref().unwrap_or("")
                );
            } else {
                tracing::info!(source, samples, ticks, "run completed");
            }
        }
        let (kind, reason) = match &outcome {
            RunOutcome::Failed { kind, reason } => (Some(*kind), Some(reason.clone())),
            _ => (None, None),
        };
        let flushed = sink_result.is_ok();
        RunReport {
            status: outcome.status(),
            kind: kind.or(if flushed { None } else { Some("sink") }),
            reason: reason.or(sink_result.err()),
            asset_id,
            run_id,
            samples,
            ticks,
            flushed,
            skipped_messages: skipped.count,
            first_skipped: skipped.first,
            dropped_samples: dropped,
            clock_jumps: counters.clock_jumps,
        }
    }
}

fn failed(e: &LogError) -> RunOutcome {
    RunOutcome::Failed {
        kind: error_kind(e),
        reason: e.to_string(),
    }
}

fn sink_closed_outcome() -> RunOutcome {
    RunOutcome::Failed {
        kind: "sink",
        reason: SinkClosed.to_string(),
    }
}

/// One run in progress: feeds its twin and forwards its estimates.
pub struct RunHandle {
    ingest: Ingest,
    info: Arc<RunInfo>,
    asset_label: AssetLabel,
    twin: Box<dyn AssetTwin>,
    out: Vec<Estimate>,
    samples: u64,
    samples_reported: u64,
    ticks: u64,
    first_t_ns: Option<i64>,
    last_t_ns: Option<i64>,
    /// When the input pushed since the last flush arrived (earliest).
    arrived: Option<Instant>,
    /// A relayed run's observer counts (its twin is elsewhere).
    relayed_observer: Option<dt_core::charge::ObserverCounters>,
    /// A relayed run's road observer counts (likewise).
    relayed_road: Option<dt_core::road::RoadCounters>,
}

impl std::fmt::Debug for RunHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunHandle")
            .field("info", &self.info)
            .field("samples", &self.samples)
            .finish_non_exhaustive()
    }
}

impl RunHandle {
    /// The run.
    #[must_use]
    pub fn info(&self) -> &RunInfo {
        &self.info
    }

    /// Feeds one sample to the twin (no I/O; call [`RunHandle::flush`] after a batch).
    pub fn push(&mut self, sample: &Sample) -> Result<(), TwinError> {
        self.samples += 1;
        let t = sample.t_ns();
        self.first_t_ns.get_or_insert(t);
        self.last_t_ns = Some(self.last_t_ns.map_or(t, |l| l.max(t)));
        self.twin.push(sample)
    }

    /// Hands in estimates made elsewhere (a relayed run); send them with
    /// [`RunHandle::flush`].
    pub fn relay(&mut self, estimates: impl IntoIterator<Item = Estimate>) {
        for e in estimates {
            self.last_t_ns = Some(self.last_t_ns.map_or(e.t_ns, |l| l.max(e.t_ns)));
            self.out.push(e);
        }
    }

    /// Hands in what the charge observer and the road observer made of a
    /// relayed run, for its end (its twin is elsewhere).
    pub fn relay_counters(
        &mut self,
        observer: Option<dt_core::charge::ObserverCounters>,
        road: Option<dt_core::road::RoadCounters>,
    ) {
        self.relayed_observer = observer;
        self.relayed_road = road;
    }

    /// Says when the samples pushed since the last flush arrived (the read
    /// that returned their bytes); the earliest call before a flush counts.
    /// Without it a flush takes its own time as the arrival. The daemon's
    /// `estimate_delay_seconds` histogram is measured from this instant.
    pub fn set_arrival(&mut self, at: Instant) {
        self.arrived.get_or_insert(at);
    }

    /// Sends the estimates completed so far; waits while the sink queue is full.
    pub async fn flush(&mut self) -> Result<(), SinkClosed> {
        self.twin.drain(&mut self.out);
        self.send_out().await
    }

    async fn send_out(&mut self) -> Result<(), SinkClosed> {
        let m = &self.ingest.inner.metrics;
        let new_samples = self.samples - self.samples_reported;
        if new_samples > 0 {
            m.messages
                .get_or_create(&SourceLabel {
                    source: self.info.kind.as_str().to_owned(),
                })
                .inc_by(new_samples);
            self.samples_reported = self.samples;
        }
        if let Some(t) = self.last_t_ns {
            m.set_last_sample(&self.info.meta.asset_id, t);
        }
        let arrived = self.arrived.take().unwrap_or_else(Instant::now);
        if self.out.is_empty() {
            return Ok(());
        }
        let batch = std::mem::take(&mut self.out);
        let n = batch.len() as u64;
        self.ingest
            .inner
            .sink_tx
            .send(SinkMsg::Estimates(Arc::clone(&self.info), batch, arrived))
            .await
            .map_err(|_| SinkClosed)?;
        self.ticks += n;
        m.ticks.get_or_create(&self.asset_label).inc_by(n);
        Ok(())
    }

    /// Ends the run: the twin's last estimates are sent, and this waits until
    /// the sinks have made everything of the run durable. Returns the
    /// outcome (failed if the twin failed at the end), samples, ticks, the
    /// sinks' verdict and the twin's counters.
    pub async fn end(
        mut self,
        outcome: RunOutcome,
    ) -> (RunOutcome, u64, u64, Result<(), String>, TwinCounters) {
        let mut outcome = outcome;
        if let Err(e) = self.twin.finish(&mut self.out) {
            if !matches!(outcome, RunOutcome::Failed { .. }) {
                outcome = RunOutcome::Failed {
                    kind: "twin",
                    reason: format!("{}: the twin failed: {e}", self.info.source),
                };
            }
        }
        let mut result = self.send_out().await.map_err(|e| e.to_string());
        let counters = self.twin.counters();
        self.ingest.inner.metrics.add_twin_counters(&counters);
        if counters.nan_samples + counters.out_of_order + counters.timestamp_outliers > 0 {
            tracing::info!(
                source = %self.info.source,
                nan_samples = counters.nan_samples,
                out_of_order = counters.out_of_order,
                dropped_late = counters.dropped_late,
                timestamp_outliers = counters.timestamp_outliers,
                "input anomalies"
            );
        }
        if let Some(o) = &counters.observer {
            log_observer(&self.info.source, &self.info.meta.asset_id, o);
        }
        if let Some(r) = &counters.road {
            log_road(&self.info.source, &self.info.meta.asset_id, r);
        }
        if result.is_ok() {
            let (ack_tx, ack_rx) = oneshot::channel();
            let sent = self
                .ingest
                .inner
                .sink_tx
                .send(SinkMsg::Ended(
                    Arc::clone(&self.info),
                    RunEnd {
                        outcome: outcome.clone(),
                        observer: counters
                            .observer
                            .or(self.relayed_observer)
                            .map(ObserverRead::from),
                        road: counters.road.or(self.relayed_road).map(RoadRead::from),
                    },
                    ack_tx,
                ))
                .await;
            result = match sent {
                Err(_) => Err(SinkClosed.to_string()),
                Ok(()) => ack_rx.await.unwrap_or_else(|_| Err(SinkClosed.to_string())),
            };
        }
        let read = self.twin.service_baseline();
        if let (true, Some(read)) = (
            result.is_ok() && matches!(outcome, RunOutcome::Completed),
            read,
        ) {
            complete_service(&self.ingest, &self.info, self.first_t_ns, read).await;
        }
        (outcome, self.samples, self.ticks, result, counters)
    }
}

/// What the charge observer made of a run's reversals, when it saw any. A
/// run whose reversals were all at excitations the calibration does not
/// cover is a warning: the asset's estimate keeps its prior (`unknown`)
/// until the observer is calibrated at that excitation.
fn log_observer(source: &str, asset_id: &str, o: &dt_core::charge::ObserverCounters) {
    if o.detected == 0 {
        return;
    }
    if o.not_calibrated_here() {
        tracing::warn!(
            source = %source,
            asset = %asset_id,
            reversals = o.detected,
            uncalibrated = o.uncalibrated,
            "charge observer read no reversal: most were at an excitation its calibration does \
             not cover, so the estimate keeps its prior; calibrate the observer there \
             (`python -m train.observer fit` on runs at that excitation)"
        );
    } else if let Some(why) = o.why_prior_kept() {
        tracing::warn!(source = %source, asset = %asset_id, "charge observer: {why}");
    } else {
        tracing::info!(
            source = %source,
            asset = %asset_id,
            reversals = o.detected,
            used = o.used,
            spared = o.spared,
            skipped = o.skipped,
            rejected = o.rejected,
            uncalibrated = o.uncalibrated,
            "charge observer"
        );
    }
}

/// What the road observer made of a road asset's run: a warning when it read
/// no block although some were complete (the estimate kept its prior).
fn log_road(source: &str, asset_id: &str, r: &dt_core::road::RoadCounters) {
    if let Some(why) = r.why_none() {
        tracing::warn!(source = %source, asset = %asset_id, "{why}");
    } else if r.read > 0 {
        // the counts as one field, in JSON: the API's `last_run_road`, by name
        let blocks = serde_json::to_string(r).unwrap_or_default();
        tracing::info!(source = %source, asset = %asset_id, blocks = %blocks, "road observer");
    }
}

/// After a run that read the unit for a pending service: its reading
/// becomes the asset's baseline, or the reason it gave none is kept (see
/// [`super::baselines`]). A store error is logged: the service stays
/// pending and the asset's next run reads it again.
async fn complete_service(
    ingest: &Ingest,
    info: &RunInfo,
    first_t_ns: Option<i64>,
    read: Result<AssetBaseline, String>,
) {
    let (Some(service), Some(store)) = (info.asset.read_service, ingest.inner.store.clone()) else {
        return;
    };
    let run_id = &info.meta.run_id;
    let read = match recorded_before(run_id, first_t_ns, info.started, service) {
        Some(why) => Err(why),
        None => read.map_err(|why| format!("run `{run_id}`: {why}")),
    };
    let baselines = Arc::clone(&ingest.inner.baselines);
    let asset = info.meta.asset_id.clone();
    let logged = read.clone();
    let done = tokio::task::spawn_blocking(move || {
        baselines.complete_service(store.as_ref(), &asset, service, read)
    })
    .await;
    let (asset, run) = (&info.meta.asset_id, &info.meta.run_id);
    match (done, logged) {
        (Ok(Ok(ServiceOutcome::Completed)), Ok(b)) => tracing::info!(
            asset = %asset, run = %run, baseline = %b,
            "unit baseline read after the service; used from the asset's next run"
        ),
        (Ok(Ok(ServiceOutcome::StillPending)), Err(why)) => tracing::warn!(
            asset = %asset, run = %run,
            "no unit baseline from this run, the service stays pending: {why}"
        ),
        (Ok(Ok(_)), _) => tracing::info!(
            asset = %asset, run = %run,
            "the service this run read for was replaced or withdrawn meanwhile"
        ),
        (Ok(Err(e)), _) => tracing::error!(
            asset = %asset, run = %run, "the service's baseline was not kept: {e}"
        ),
        (Err(e), _) => tracing::error!(asset = %asset, run = %run, "{e}"),
    }
}

/// The twin of a relayed run: none (its estimates come from elsewhere).
struct RelayTwin;

impl AssetTwin for RelayTwin {
    fn push(&mut self, _sample: &Sample) -> Result<(), TwinError> {
        Ok(())
    }

    fn drain(&mut self, _out: &mut Vec<Estimate>) {}

    fn finish(&mut self, _out: &mut Vec<Estimate>) -> Result<(), TwinError> {
        Ok(())
    }

    fn counters(&self) -> super::twin::TwinCounters {
        super::twin::TwinCounters::default()
    }
}
