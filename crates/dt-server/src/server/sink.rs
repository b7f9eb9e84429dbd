//! Outputs behind one small [`Sink`] interface, driven from one blocking
//! thread that drains a bounded queue of [`SinkMsg`]s: the live state of the
//! HTTP API ([`super::state::LiveSink`]) and the rotating MCAP recorder
//! ([`super::record::McapRecorder`]). A full queue makes the ingest tasks
//! wait, which stops them reading their sockets (backpressure).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use dt_core::charge::ObserverCounters;
use dt_core::estimate::Estimate;
use dt_core::log::RunMetadata;
use dt_core::road::RoadCounters;
use serde::Serialize;
use tokio::sync::{mpsc, oneshot};

use super::config::AssetConfig;
use super::metrics::{AssetLabel, Metrics};

/// Where a run's bytes come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceKind {
    /// A TCP ingest connection.
    Tcp,
    /// A file of the inbox directory.
    Inbox,
    /// An upload (`POST /v1/runs`).
    Http,
    /// The estimate stream of a NATS worker group (the fleet view).
    Nats,
}

impl SourceKind {
    /// A stream that is the asset now (TCP, NATS), not an upload of a log
    /// that may be older than what the asset has shown (inbox, HTTP).
    #[must_use]
    pub fn is_live(self) -> bool {
        matches!(self, SourceKind::Tcp | SourceKind::Nats)
    }

    /// `tcp` or `inbox` (metric label).
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            SourceKind::Tcp => "tcp",
            SourceKind::Inbox => "inbox",
            SourceKind::Http => "http",
            SourceKind::Nats => "nats",
        }
    }
}

/// One run being processed (one connection, one inbox file).
#[derive(Debug, Clone)]
pub struct RunInfo {
    /// Unique within this daemon's lifetime.
    pub seq: u64,
    /// Source kind.
    pub kind: SourceKind,
    /// Source name for logs (`tcp 127.0.0.1:50432`, `inbox run.mcap`).
    pub source: String,
    /// The run's `shocktwin.run` metadata.
    pub meta: RunMetadata,
    /// The asset's health settings.
    pub asset: AssetConfig,
    /// When processing started.
    pub started: SystemTime,
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub enum RunOutcome {
    /// The stream ended cleanly; every estimate was emitted.
    Completed,
    /// The stream was bad or broke; the estimates of the good data before the
    /// error were emitted. `kind` is the metric label.
    Failed {
        /// Error kind (`truncated`, `schema`, ...).
        kind: &'static str,
        /// Human-readable reason (names the source, topic, field).
        reason: String,
    },
    /// The daemon is shutting down; the estimates so far were emitted.
    Interrupted,
}

impl RunOutcome {
    /// `completed`, `failed` or `interrupted`.
    #[must_use]
    pub fn status(&self) -> &'static str {
        match self {
            RunOutcome::Completed => "completed",
            RunOutcome::Failed { .. } => "failed",
            RunOutcome::Interrupted => "interrupted",
        }
    }

    /// The failure reason, if any.
    #[must_use]
    pub fn reason(&self) -> Option<&str> {
        match self {
            RunOutcome::Failed { reason, .. } => Some(reason),
            _ => None,
        }
    }
}

/// How a run ended, and what the charge observer made of its reversals.
#[derive(Debug, Clone, PartialEq)]
pub struct RunEnd {
    /// How it ended.
    pub outcome: RunOutcome,
    /// What the observer read, `None` when the model does not read it.
    pub observer: Option<ObserverRead>,
    /// What the road observer read, `None` unless the asset is driven on
    /// roads.
    pub road: Option<RoadRead>,
}

/// What the charge observer made of one run's velocity reversals, as the
/// API and the fleet store tell it: the counts, and whether the estimate
/// kept its prior for want of calibration at the run's excitation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ObserverRead {
    /// The counts (`detected`, `used`, `spared`, `skipped`, `rejected`,
    /// `uncalibrated`, `reacquired`).
    #[serde(flatten)]
    pub counts: ObserverCounters,
    /// No reversal read, most at an excitation the calibration does not
    /// cover ([`ObserverCounters::not_calibrated_here`]): the estimate kept
    /// its prior; calibrate the observer there.
    pub not_calibrated_here: bool,
}

impl From<ObserverCounters> for ObserverRead {
    fn from(counts: ObserverCounters) -> Self {
        Self {
            counts,
            not_calibrated_here: counts.not_calibrated_here(),
        }
    }
}

/// What the road observer made of one run's blocks, as the API and the
/// fleet store tell it: the counts, and why no block was read when none
/// was.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct RoadRead {
    /// The counts (`read`, `settling`, `at_rest`, `slower_than_calibrated`, `without_positions`,
    /// `unsolved`).
    #[serde(flatten)]
    pub counts: RoadCounters,
    /// No block read although some were complete: the main reason
    /// ([`RoadCounters::why_none`]); the estimate kept its prior.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub why_none: Option<String>,
}

impl From<RoadCounters> for RoadRead {
    fn from(counts: RoadCounters) -> Self {
        Self {
            counts,
            why_none: counts.why_none(),
        }
    }
}

/// A sink failed to take or keep a run's estimates.
#[derive(Debug, thiserror::Error)]
#[error("sink `{sink}`: {reason}")]
pub struct SinkError {
    /// The sink's name.
    pub sink: &'static str,
    /// What failed (names the file).
    pub reason: String,
}

/// An output of the daemon. Called from one thread, in order, per run:
/// `run_started`, any number of `estimates`, `run_ended`; runs interleave.
pub trait Sink: Send {
    /// Name for logs and errors.
    fn name(&self) -> &'static str;
    /// A run starts.
    fn run_started(&mut self, run: &RunInfo) -> Result<(), SinkError>;
    /// The next estimates of a run, in time order.
    fn estimates(&mut self, run: &RunInfo, batch: &[Estimate]) -> Result<(), SinkError>;
    /// The run ended: everything of it must be durable when this returns.
    fn run_ended(&mut self, run: &RunInfo, end: &RunEnd) -> Result<(), SinkError>;
    /// The daemon stops: flush and close everything.
    fn close(&mut self) -> Result<(), SinkError>;
}

/// Messages from the ingest tasks to the sink thread.
#[derive(Debug)]
pub(crate) enum SinkMsg {
    Started(Arc<RunInfo>),
    /// A batch and when the input that completed it arrived.
    Estimates(Arc<RunInfo>, Vec<Estimate>, Instant),
    /// The sender gets `Err(reason)` if a sink failed for this run.
    Ended(Arc<RunInfo>, RunEnd, oneshot::Sender<Result<(), String>>),
}

/// Drains `rx` into `sinks` until every sender is gone, then closes them.
/// Runs on a blocking thread.
pub(crate) fn dispatch(
    mut rx: mpsc::Receiver<SinkMsg>,
    mut sinks: Vec<Box<dyn Sink>>,
    metrics: &Metrics,
) {
    // First failure per run (reported in its `Ended` acknowledgement).
    let mut failed: HashMap<u64, String> = HashMap::new();
    let note = |failed: &mut HashMap<u64, String>, seq: u64, err: SinkError| {
        metrics.error("sink");
        failed.entry(seq).or_insert_with(|| {
            tracing::error!(run = seq, "{err}");
            err.to_string()
        });
    };
    while let Some(msg) = rx.blocking_recv() {
        match msg {
            SinkMsg::Started(run) => {
                for sink in &mut sinks {
                    if let Err(e) = sink.run_started(&run) {
                        note(&mut failed, run.seq, e);
                    }
                }
            }
            SinkMsg::Estimates(run, batch, arrived) => {
                for sink in &mut sinks {
                    if let Err(e) = sink.estimates(&run, &batch) {
                        note(&mut failed, run.seq, e);
                    }
                }
                let label = AssetLabel {
                    asset: run.meta.asset_id.clone(),
                };
                metrics.observe_delay(&label, arrived.elapsed().as_secs_f64(), batch.len());
            }
            SinkMsg::Ended(run, end, ack) => {
                for sink in &mut sinks {
                    if let Err(e) = sink.run_ended(&run, &end) {
                        note(&mut failed, run.seq, e);
                    }
                }
                let result = failed.remove(&run.seq).map_or(Ok(()), Err);
                // The ingest task may be gone (shutdown): nothing to tell.
                let _ = ack.send(result);
            }
        }
    }
    for sink in &mut sinks {
        if let Err(e) = sink.close() {
            metrics.error("sink");
            tracing::error!("{e}");
        }
    }
}
