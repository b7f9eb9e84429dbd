//! `serve --nats`: one worker of the group that estimates the fleet.
//!
//! **Partitions.** The telemetry stream maps `shocktwin.telemetry.<asset>`
//! to `shocktwin.telemetry.<p>.<asset>` with the server's own
//! `partition(P, 1)` subject transform (a hash of the asset token), so each
//! asset belongs to exactly one of `P` partitions whatever client published
//! it (MQTT included). A worker holds a partition through a lease in the KV
//! bucket `shocktwin_leases` (`p<n>`, created with compare-and-set, renewed
//! every second, expiring after [`super::LEASE_TTL`]); each worker aims at
//! `ceil(P / live workers)` partitions (live: heartbeat keys `worker.<id>`)
//! and gives away extras, so a joining worker gets its share and a dead one's
//! partitions are taken over once its leases expire.
//!
//! **Processing.** A partition is read with an ordered consumer filtered to
//! `shocktwin.telemetry.<p>.*`, from the stream sequence after its
//! checkpoint. Every estimate goes to `shocktwin.estimate.<asset>` and every
//! health change to `shocktwin.health.<asset>` (stream
//! `SHOCKTWIN_ESTIMATES`) with a message id (`e/<asset>/<run>/<seq>/<t_ns>`,
//! `h/…`, run events `r/<asset>/<run>/<seq>/<event>`, `<seq>` the stream
//! sequence of the run's batch 0; [`msg_id`]): a batch processed twice
//! (after a failover) yields the same estimates with the same ids, which
//! `JetStream` drops as duplicates, while a run sent again gets new ones.
//!
//! **Checkpoints.** Every second, and when a partition is given away, the
//! worker waits for the acknowledgements of everything it published, then
//! writes the partition's checkpoint — each open run's metadata, last batch,
//! health and its whole estimator ([`Estimator::checkpoint`]) with the
//! stream sequence they cover — to `shocktwin_checkpoints` with revision
//! compare-and-set. A failed compare-and-set means another worker owns the
//! partition: this one drops it. A new owner restores the estimators and
//! replays from the next sequence, so the estimates after a failover equal
//! those of an uninterrupted run, bit for bit (no tick lost, none
//! duplicated).
//!
//! **Bad input** (undecodable, another payload version, ids outside the
//! charset, subject and payload disagreeing, a batch going back in time or
//! without its run's start) is counted and sent to
//! `shocktwin.deadletter.<asset token>` with the reason in headers; the
//! partition and its other assets carry on.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use async_nats::jetstream::{self, consumer, kv, message::PublishMessage as Publish};
use bytes::Bytes;
use dt_core::charge::UnitBaseline;
use dt_core::estimate::{Estimate, Health};
use dt_core::estimator::Estimator;
use dt_core::service::ServiceReading;
use futures_util::future::BoxFuture;
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};
use tokio_util::sync::CancellationToken;

use super::payload::{PayloadError, TelemetryBatch};
use super::{
    checkpoint_bucket, connect_patiently, ensure_topology, lease_bucket, NatsConfig, NatsError,
    SetUpError, SetUpRetries, RENEW_EVERY, TELEMETRY_STREAM,
};
use crate::server::baselines::recorded_before;
use crate::server::config::{Config, ServiceToRead};
use crate::server::metrics::Metrics;
use crate::server::source::{Source, SourceContext};
use crate::server::store::AssetBaseline;
use crate::server::{EstimatorFactory, ServeError};

/// Version of the partition checkpoint encoding.
const CHECKPOINT_VERSION: u32 = 1;

/// How long a stopping worker waits for its final checkpoints and for
/// giving its leases back (systemd's unit allows 60 s for the whole stop).
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(10);
/// A partition waits for its publish acknowledgements once this many are
/// outstanding (the context allows [`MAX_ACKS_IN_FLIGHT`] for all partitions
/// together: a partition never waits for a permit another one holds).
const MAX_PENDING_ACKS: usize = 256;
/// The `JetStream` context's limit of unacknowledged publishes.
const MAX_ACKS_IN_FLIGHT: usize = 1 << 16;
/// The most partitions a worker group can have (`[nats] partitions`): a
/// worker holding them all keeps within [`MAX_ACKS_IN_FLIGHT`].
#[allow(clippy::cast_possible_truncation)] // 128
pub const MAX_PARTITIONS: u32 = (MAX_ACKS_IN_FLIGHT / MAX_PENDING_ACKS / 2) as u32;

/// A worker of the group (a [`Source`] of the daemon).
pub struct NatsWorker {
    cfg: NatsConfig,
    factory: EstimatorFactory,
    id: String,
    /// The bundle's digest (what checkpoints are tied to): the heartbeat's value.
    model: String,
}

impl NatsWorker {
    /// A worker with a fresh id (`<host>-<pid>-<random>`).
    #[must_use]
    pub fn new(cfg: NatsConfig, factory: EstimatorFactory) -> Self {
        let host = std::env::var("HOSTNAME").unwrap_or_else(|_| "worker".into());
        let id = format!(
            "{}-{}-{}",
            host.chars()
                .filter(char::is_ascii_alphanumeric)
                .take(24)
                .collect::<String>(),
            std::process::id(),
            nuid_suffix()
        );
        let model = dt_core::estimator::model_digest(factory.bundle());
        Self {
            cfg,
            factory,
            id,
            model,
        }
    }
}

fn nuid_suffix() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    format!("{nanos:08x}")
}

impl Source for NatsWorker {
    fn name(&self) -> String {
        format!(
            "nats worker {} ({})",
            self.id,
            super::without_credentials(self.cfg.url.as_deref().unwrap_or(""))
        )
    }

    fn says_started(&self) -> bool {
        true // once connected
    }

    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>> {
        Box::pin(async move {
            let me = *self;
            Box::pin(me.serve(ctx))
                .await
                .map_err(|e| ServeError::Invalid {
                    key: "nats".into(),
                    reason: e.to_string(),
                })
        })
    }
}

struct Held {
    revision: u64,
    stop: CancellationToken,
    lost: Arc<AtomicBool>,
    task: tokio::task::JoinHandle<Result<(), NatsError>>,
}

/// What a partition task needs.
#[derive(Clone)]
struct PartCtx {
    js: jetstream::Context,
    checkpoints: kv::Store,
    /// The group's baselines and pending services (a run that reads a
    /// service writes its result there).
    baseline_kv: kv::Store,
    service_kv: kv::Store,
    factory: EstimatorFactory,
    config: Arc<Config>,
    baselines: Arc<crate::server::baselines::Baselines>,
    metrics: Arc<MetricsHandle>,
}

/// The daemon's metrics, shared with the partition tasks.
struct MetricsHandle(crate::server::ingest::Ingest);

impl MetricsHandle {
    fn m(&self) -> &Metrics {
        self.0.metrics()
    }
}

impl NatsWorker {
    /// The group's streams and buckets (created when missing): the
    /// partitions, the lease bucket and what a partition task needs.
    async fn set_up(
        &self,
        js: &jetstream::Context,
        ctx: &SourceContext,
    ) -> Result<(u32, kv::Store, PartCtx), SetUpError> {
        let partitions = ensure_topology(js, &self.cfg).await?;
        if partitions > MAX_PARTITIONS {
            // the count of a stream made elsewhere (the configuration's is
            // checked at start), fixed when it was made: not mended by a retry
            return Err(SetUpError::Stop(NatsError::new(
                format!("stream {TELEMETRY_STREAM}"),
                format!("{partitions} partitions: at most {MAX_PARTITIONS} per worker group"),
            )));
        }
        let leases = lease_bucket(js).await?;
        let part = PartCtx {
            checkpoints: checkpoint_bucket(js).await?,
            baseline_kv: super::baseline_bucket(js).await?,
            service_kv: super::service_bucket(js).await?,
            js: js.clone(),
            factory: self.factory.clone(),
            config: Arc::new(ctx.ingest.config().clone()),
            baselines: Arc::clone(ctx.ingest.baselines()),
            metrics: Arc::new(MetricsHandle(ctx.ingest.clone())),
        };
        Ok((partitions, leases, part))
    }

    /// [`Self::set_up`], tried again (see [`SetUpRetries`]) until it works;
    /// `None` once the daemon stops first.
    async fn set_up_patiently(
        &self,
        js: &jetstream::Context,
        ctx: &SourceContext,
        name: &str,
        retries: &mut SetUpRetries,
    ) -> Result<Option<(u32, kv::Store, PartCtx)>, NatsError> {
        loop {
            match self.set_up(js, ctx).await {
                Ok(set_up) => return Ok(Some(set_up)),
                Err(e) => {
                    if !retries.after(name, e, ctx).await? {
                        return Ok(None);
                    }
                }
            }
        }
    }

    async fn serve(self, ctx: SourceContext) -> Result<(), NatsError> {
        let name = format!("shocktwin worker {}", self.id);
        let Some(client) = connect_patiently(&self.cfg, &name, &ctx).await? else {
            return Ok(()); // stopped before the server came
        };
        let js = jetstream::ContextBuilder::new()
            .max_ack_inflight(MAX_ACKS_IN_FLIGHT)
            .build(client);
        let mut retries = SetUpRetries::default();
        let Some((mut partitions, mut leases, mut part)) =
            Box::pin(self.set_up_patiently(&js, &ctx, &name, &mut retries)).await?
        else {
            return Ok(()); // stopped while waiting
        };
        tracing::info!(worker = %self.id, partitions, "joined the worker group");
        if partitions != self.cfg.partitions {
            // the stream's count is fixed when it is made (a helper's trial:
            // `partitions = 8` against a stream of 16 said nothing)
            tracing::warn!(
                "nats.partitions = {} is not used: the telemetry stream exists with {partitions} \
                 partitions, fixed when it was made (delete the stream SHOCKTWIN_TELEMETRY, \
                 losing its telemetry, to change it)",
                self.cfg.partitions
            );
        }
        ctx.started.signal(); // connected and set up (a review: not before)
        let mut held: BTreeMap<u32, Held> = BTreeMap::new();
        let heartbeat = format!("worker.{}", self.id);
        // the heartbeat's value is this worker's model, which the others
        // compare now and then (every listing of the bucket is a consumer)
        let mut others = BTreeMap::new();
        let mut beats = 0u32;
        let mut gone_in_a_row = 0u32;
        let mut tick = tokio::time::interval(RENEW_EVERY / 2);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                () = ctx.cancel.cancelled() => break,
                _ = tick.tick() => {}
            }
            // A step waits on the server (each request up to the client's
            // timeout): a stop during an outage must not wait for it.
            let step = async {
                let gone = self
                    .renew_and_rebalance(&leases, &heartbeat, &mut held, partitions, &part, &ctx)
                    .await;
                if !gone && beats % MODEL_CHECK_EVERY_BEATS == 0 {
                    check_models(&leases, &self.model, &mut others).await;
                }
                gone
            };
            let gone = tokio::select! {
                () = ctx.cancel.cancelled() => break,
                gone = step => gone,
            };
            beats = beats.wrapping_add(1);
            // three beats in a row (1.5 s): a JetStream still recovering after
            // a restart that kept its store can answer "not found" once
            gone_in_a_row = if gone { gone_in_a_row + 1 } else { 0 };
            if gone_in_a_row >= 3 {
                gone_in_a_row = 0;
                // The server lost the group's streams and buckets (restarted
                // with an empty store): they are made again, and the
                // partitions start afresh (a helper's trial: the workers
                // logged "no stream found" twice a second for ever while
                // `/readyz` said ready, and no run was estimated again).
                tracing::warn!(
                    worker = %self.id,
                    "the worker group's buckets are gone (a NATS server restarted with an empty \
                     store?): setting the group up again; its partitions start afresh"
                );
                for (_, h) in std::mem::take(&mut held) {
                    h.lost.store(true, Ordering::SeqCst); // nothing to write to
                    h.stop.cancel();
                    h.task.abort();
                }
                let again = tokio::select! {
                    () = ctx.cancel.cancelled() => break,
                    again = Box::pin(self.set_up_patiently(&js, &ctx, &name, &mut retries)) => again?,
                };
                let Some(again) = again else {
                    break;
                };
                (partitions, leases, part) = again;
                ctx.started.note(None);
                tracing::info!(worker = %self.id, partitions, "joined the worker group again");
            }
        }
        // Shutdown: final checkpoints, then the leases go back at once;
        // bounded, for a server that is away (a helper's trial: a SIGTERM
        // during an outage waited until NATS came back, or for ever). Without
        // them a partition restarts from its last periodic checkpoint once
        // its lease expires, as after `kill -9`.
        let leave = async {
            for (p, h) in std::mem::take(&mut held) {
                release(&leases, p, h).await;
            }
            let _ = leases.delete(&heartbeat).await;
        };
        if tokio::time::timeout(SHUTDOWN_GRACE, leave).await.is_err() {
            tracing::warn!(
                worker = %self.id,
                "left the worker group without its final checkpoints: NATS did not answer within {} s \
                 (the partitions restart from their last checkpoints once their leases expire)",
                SHUTDOWN_GRACE.as_secs()
            );
        } else {
            tracing::info!(worker = %self.id, "left the worker group");
        }
        Ok(())
    }
}

impl NatsWorker {
    /// One beat: the heartbeat, the held leases renewed (a partition whose
    /// lease is lost is dropped without writing), then [`Self::rebalance`].
    /// Returns whether the lease bucket is gone (the heartbeat found no
    /// stream): the caller sets the group up again.
    async fn renew_and_rebalance(
        &self,
        leases: &kv::Store,
        heartbeat: &str,
        held: &mut BTreeMap<u32, Held>,
        partitions: u32,
        part: &PartCtx,
        ctx: &SourceContext,
    ) -> bool {
        if let Err(e) = leases.put(heartbeat, Bytes::from(self.model.clone())).await {
            // "no stream found" is also a moment without a leader in a
            // cluster (the review): the bucket's stream is looked up
            if e.to_string().contains("no stream found") && lease_stream_gone(&part.js).await {
                return true;
            }
            tracing::warn!(worker = %self.id, "heartbeat: {e}");
        }
        // Renew; a lease we cannot renew is lost: drop the partition
        // without writing (another worker may own it already).
        let mut lost = Vec::new();
        // one line for the leases lost together (every one after an
        // outage longer than their lifetime: a line each before)
        let mut lost_why: Option<String> = None;
        for (&p, h) in held.iter_mut() {
            if h.task.is_finished() {
                lost.push((p, true));
                continue;
            }
            match leases
                .update(lease_key(p), Bytes::from(self.id.clone()), h.revision)
                .await
            {
                Ok(r) => h.revision = r,
                Err(e) => {
                    lost_why.get_or_insert_with(|| e.to_string());
                    lost.push((p, false));
                }
            }
        }
        if let Some(why) = lost_why {
            let partitions: Vec<u32> = lost.iter().filter(|l| !l.1).map(|l| l.0).collect();
            tracing::warn!(worker = %self.id, ?partitions, "leases lost (taken again when free): {why}");
        }
        for (p, finished) in lost {
            if let Some(h) = held.remove(&p) {
                h.lost.store(!finished, Ordering::SeqCst);
                h.stop.cancel();
                match h.task.await {
                    Ok(Err(e)) => tracing::warn!(partition = p, "partition stopped: {e}"),
                    Err(e) => tracing::error!(partition = p, "partition task: {e}"),
                    Ok(Ok(())) => {}
                }
                if finished {
                    // The task ended by itself (checkpoint refused, stream
                    // error): give the lease back so that the partition
                    // restarts from its last checkpoint.
                    let _ = leases.delete(lease_key(p)).await;
                }
            }
        }
        self.rebalance(leases, held, partitions, part, ctx).await;
        false
    }

    /// Gives away one partition above the fair share, or takes free ones up
    /// to it.
    async fn rebalance(
        &self,
        leases: &kv::Store,
        held: &mut BTreeMap<u32, Held>,
        partitions: u32,
        part: &PartCtx,
        ctx: &SourceContext,
    ) {
        let live = live_workers(leases).await.max(1);
        let share = partitions.div_ceil(live) as usize;
        if held.len() > share {
            if let Some((&p, _)) = held.iter().next_back() {
                if let Some(h) = held.remove(&p) {
                    release(leases, p, h).await;
                    tracing::info!(worker = %self.id, partition = p, share, "partition handed over");
                }
            }
        } else if held.len() < share {
            let offset = hash32(&self.id) % partitions;
            for k in 0..partitions {
                let p = (offset + k) % partitions;
                if held.contains_key(&p) {
                    continue;
                }
                if let Ok(revision) = leases
                    .create(lease_key(p), Bytes::from(self.id.clone()))
                    .await
                {
                    let stop = ctx.cancel.child_token();
                    let lost = Arc::new(AtomicBool::new(false));
                    let task = tokio::spawn(run_partition(
                        p,
                        part.clone(),
                        stop.clone(),
                        Arc::clone(&lost),
                    ));
                    tracing::info!(worker = %self.id, partition = p, "partition taken");
                    held.insert(
                        p,
                        Held {
                            revision,
                            stop,
                            lost,
                            task,
                        },
                    );
                    if held.len() >= share {
                        break;
                    }
                }
            }
        }
    }
}

async fn release(leases: &kv::Store, p: u32, h: Held) {
    h.stop.cancel();
    match h.task.await {
        Ok(Err(e)) => tracing::warn!(partition = p, "partition stopped: {e}"),
        Err(e) => tracing::error!(partition = p, "partition task: {e}"),
        Ok(Ok(())) => {}
    }
    let _ = leases.delete(lease_key(p)).await;
}

fn lease_key(p: u32) -> String {
    format!("p{p}")
}

async fn live_workers(leases: &kv::Store) -> u32 {
    let Ok(mut keys) = leases.keys().await else {
        return 1;
    };
    let mut n = 0;
    while let Some(k) = keys.next().await {
        if k.is_ok_and(|k| k.starts_with("worker.")) {
            n += 1;
        }
    }
    n
}

/// Beats (half a lease renewal each) between two looks at the group's models.
const MODEL_CHECK_EVERY_BEATS: u32 = 20;

/// The message id of what a run publishes: `<kind>/<asset>/<run>/<seq>/<what>`,
/// `<seq>` the stream sequence of the run's batch 0; without it (0: a run
/// restored from a checkpoint written before it was kept) the ids the worker
/// that wrote the checkpoint used, `<kind>/<asset>/<run>/<what>`, so that a
/// rolling upgrade's replay is still taken for duplicates (the review).
fn msg_id(
    kind: char,
    asset: &str,
    run: &str,
    start_seq: u64,
    what: impl std::fmt::Display,
) -> String {
    if start_seq == 0 {
        format!("{kind}/{asset}/{run}/{what}")
    } else {
        format!("{kind}/{asset}/{run}/{start_seq}/{what}")
    }
}

/// Whether the lease bucket's stream is gone (the server lost its store),
/// not merely without a leader for a moment.
async fn lease_stream_gone(js: &jetstream::Context) -> bool {
    match js.get_stream(format!("KV_{}", super::LEASE_BUCKET)).await {
        Ok(_) => false,
        Err(e) => matches!(
            e.kind(),
            jetstream::context::GetStreamErrorKind::JetStream(ref j)
                if j.error_code() == jetstream::ErrorCode::STREAM_NOT_FOUND
        ),
    }
}

/// Warns when a worker of the group runs another model than `model` (read
/// from the heartbeats; said once per worker and model). A failover between
/// two such workers cannot restore the runs (the checkpoints belong to one
/// model): they restart with their next batch 0, and batches before it are
/// dead-lettered (a helper's trial: a worker started with another bundle
/// joined without a word, and a failover onto it lost two runs).
async fn check_models(leases: &kv::Store, model: &str, seen: &mut BTreeMap<String, String>) {
    let Ok(mut keys) = leases.keys().await else {
        return;
    };
    let mut workers = Vec::new();
    while let Some(k) = keys.next().await {
        if let Ok(k) = k {
            if k.starts_with("worker.") {
                workers.push(k);
            }
        }
    }
    for key in workers {
        let Ok(Some(value)) = leases.get(&key).await else {
            continue;
        };
        let theirs = String::from_utf8_lossy(&value).into_owned();
        // "1": a worker from before the heartbeat carried its model
        if theirs != model && theirs != "1" && seen.get(&key) != Some(&theirs) {
            tracing::warn!(
                "{}: runs model {theirs}, this worker {model}: the group's workers need one \
                 bundle (a failover between them restarts the runs it moves, and loses their \
                 batches until the next run starts)",
                key.trim_start_matches("worker.")
            );
        }
        seen.insert(key, theirs);
    }
}

/// FNV-1a: a stable spread of the workers' first choices.
fn hash32(s: &str) -> u32 {
    s.bytes().fold(0x811c_9dc5_u32, |h, b| {
        (h ^ u32::from(b)).wrapping_mul(0x0100_0193)
    })
}

/// One open run of a partition, as checkpointed.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SavedRun {
    run_id: String,
    meta: BTreeMap<String, String>,
    last_batch: u64,
    health: Health,
    estimator: serde_bytes::ByteBuf,
    /// The service this run reads, and what it read so far.
    #[serde(default)]
    service: Option<(ServiceToRead, ServiceReading)>,
    /// The run's first sample time, ns.
    #[serde(default)]
    first_t_ns: Option<i64>,
    /// The telemetry stream sequence of the run's batch 0 (0 in a
    /// checkpoint written before it was kept).
    #[serde(default)]
    start_seq: u64,
}

#[derive(Debug, Default, Serialize, Deserialize)]
struct PartitionCheckpoint {
    version: u32,
    /// The telemetry stream sequence everything here covers.
    seq: u64,
    assets: BTreeMap<String, SavedRun>,
}

struct OpenRun {
    run_id: String,
    meta: BTreeMap<String, String>,
    last_batch: u64,
    health: Health,
    /// Boxed: the estimator (observer windows included) is large, and an
    /// `OpenRun` moves through the partition's futures.
    est: Box<Estimator>,
    /// The pending service this run reads the unit for, and its reading.
    service: Option<(ServiceToRead, ServiceReading)>,
    /// The run's first sample time, ns.
    first_t_ns: Option<i64>,
    /// The telemetry stream sequence of the run's batch 0: part of the
    /// message ids of what the run publishes, so that a run sent again (a
    /// new batch 0) is not taken for a duplicate of its first sending by the
    /// stream's de-duplication window, while a failover's replay of the same
    /// batches still is (a helper's trial: a run re-sent within 5 minutes
    /// stayed "running" in every fleet view, its `ended` event dropped).
    start_seq: u64,
}

impl OpenRun {
    /// Appends the estimates completed so far to `out`, feeding the
    /// service's reading with their ticks.
    fn drain_into(&mut self, out: &mut Vec<Estimate>) {
        match self.service.as_mut() {
            // a road asset's unit is read by the road observer's blocks
            Some((_, reading)) if self.est.road().is_none() => {
                reading.drain_from(&mut self.est, out);
            }
            _ => out.extend(self.est.drain()),
        }
    }
}

/// A partition's work: assets, publishing, checkpoints.
struct Partition {
    p: u32,
    ctx: PartCtx,
    runs: HashMap<String, OpenRun>,
    seq: u64,
    pending: Vec<async_nats::jetstream::context::PublishAckFuture>,
    buf: Vec<Estimate>,
}

async fn run_partition(
    p: u32,
    ctx: PartCtx,
    stop: CancellationToken,
    lost: Arc<AtomicBool>,
) -> Result<(), NatsError> {
    let (mut revision, mut part) = restore_partition(p, ctx).await?;
    let stream = part
        .ctx
        .js
        .get_stream(TELEMETRY_STREAM)
        .await
        .map_err(|e| NatsError::new(format!("stream {TELEMETRY_STREAM}"), e))?;
    let deliver_policy = if part.seq == 0 {
        consumer::DeliverPolicy::All
    } else {
        consumer::DeliverPolicy::ByStartSequence {
            start_sequence: part.seq + 1,
        }
    };
    let mut messages = stream
        .create_consumer(consumer::pull::OrderedConfig {
            filter_subject: format!("shocktwin.telemetry.{p}.*"),
            deliver_policy,
            ..Default::default()
        })
        .await
        .map_err(|e| NatsError::new(format!("consumer of partition {p}"), e))?
        .messages()
        .await
        .map_err(|e| NatsError::new(format!("consumer of partition {p}"), e))?;
    let mut tick = tokio::time::interval(RENEW_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut dirty = false;
    loop {
        tokio::select! {
            biased;
            () = stop.cancelled() => break,
            _ = tick.tick() => {
                if dirty {
                    revision = Some(part.checkpoint(revision).await?);
                    dirty = false;
                }
            }
            m = messages.next() => match m {
                None => return Err(NatsError::new(format!("partition {p}"), "the consumer ended")),
                Some(Err(e)) => return Err(NatsError::new(format!("partition {p}"), e)),
                Some(Ok(msg)) => {
                    let seq = msg.info().map_or(part.seq + 1, |i| i.stream_sequence);
                    Box::pin(part.handle(&msg.subject, &msg.payload, seq)).await?;
                    part.seq = seq;
                    dirty = true;
                    if part.pending.len() >= MAX_PENDING_ACKS {
                        part.await_acks().await?;
                    }
                }
            }
        }
    }
    if !lost.load(Ordering::SeqCst) && dirty {
        part.checkpoint(revision).await?;
    }
    Ok(())
}

/// The partition's state from its checkpoint (empty without one) and the
/// checkpoint's revision.
async fn restore_partition(p: u32, ctx: PartCtx) -> Result<(Option<u64>, Partition), NatsError> {
    let key = lease_key(p);
    let (revision, saved) = match ctx.checkpoints.entry(&key).await {
        Ok(Some(e)) if e.operation == kv::Operation::Put => {
            let ck: PartitionCheckpoint = rmp_serde::from_slice(&e.value).map_err(|err| {
                NatsError::new(format!("checkpoint {key}"), format!("undecodable: {err}"))
            })?;
            (Some(e.revision), ck)
        }
        Ok(_) => (None, PartitionCheckpoint::default()),
        Err(e) => return Err(NatsError::new(format!("checkpoint {key}"), e)),
    };
    let mut part = Partition {
        p,
        ctx,
        runs: HashMap::new(),
        seq: saved.seq,
        pending: Vec::new(),
        buf: Vec::new(),
    };
    let bundle = Arc::clone(part.ctx.factory.bundle());
    for (asset, s) in saved.assets {
        match Estimator::restore(Arc::clone(&bundle), &s.estimator) {
            Ok(est) => {
                part.runs.insert(
                    asset,
                    OpenRun {
                        run_id: s.run_id,
                        meta: s.meta,
                        last_batch: s.last_batch,
                        health: s.health,
                        est: Box::new(est),
                        service: s.service,
                        first_t_ns: s.first_t_ns,
                        start_seq: s.start_seq,
                    },
                );
            }
            Err(e) => {
                part.ctx.metrics.m().error("nats_checkpoint");
                tracing::error!(partition = p, asset, run = %s.run_id, "cannot restore: {e}; the run restarts with its next batch 0");
            }
        }
    }
    tracing::info!(
        partition = p,
        from_seq = part.seq + 1,
        runs = part.runs.len(),
        "partition restored"
    );
    Ok((revision, part))
}

impl Partition {
    /// Waits for every publish acknowledgement.
    async fn await_acks(&mut self) -> Result<(), NatsError> {
        for f in self.pending.drain(..) {
            f.await
                .map_err(|e| NatsError::new(format!("publish (partition {})", self.p), e))?;
        }
        Ok(())
    }

    /// Writes the checkpoint (after every publish is acknowledged) with
    /// compare-and-set on `revision`; returns the new revision.
    async fn checkpoint(&mut self, revision: Option<u64>) -> Result<u64, NatsError> {
        self.await_acks().await?;
        let ck = PartitionCheckpoint {
            version: CHECKPOINT_VERSION,
            seq: self.seq,
            assets: self
                .runs
                .iter()
                .map(|(a, r)| {
                    (
                        a.clone(),
                        SavedRun {
                            run_id: r.run_id.clone(),
                            meta: r.meta.clone(),
                            last_batch: r.last_batch,
                            health: r.health,
                            estimator: serde_bytes::ByteBuf::from(r.est.checkpoint()),
                            service: r.service,
                            first_t_ns: r.first_t_ns,
                            start_seq: r.start_seq,
                        },
                    )
                })
                .collect(),
        };
        let bytes =
            rmp_serde::to_vec_named(&ck).map_err(|e| NatsError::new("checkpoint encoding", e))?;
        let key = lease_key(self.p);
        let kv = &self.ctx.checkpoints;
        let r = match revision {
            Some(rev) => kv
                .update(&key, bytes.into(), rev)
                .await
                .map_err(|e| e.to_string()),
            None => kv
                .create(&key, bytes.into())
                .await
                .map_err(|e| e.to_string()),
        };
        r.map_err(|e| {
            NatsError::new(
                format!("checkpoint {key}"),
                format!("compare-and-set refused ({e}): another worker owns the partition"),
            )
        })
    }

    async fn handle(&mut self, subject: &str, payload: &[u8], seq: u64) -> Result<(), NatsError> {
        let token = subject.rsplit('.').next().unwrap_or_default();
        match TelemetryBatch::decode(token, payload) {
            Err(e) => {
                self.dead_letter(token, e.kind(), &e.to_string(), payload, seq)
                    .await
            }
            Ok(b) => match Box::pin(self.apply(b, seq)).await {
                Ok(()) => Ok(()),
                Err(Refused::Publish(e)) => Err(e),
                Err(Refused::Input(kind, reason)) => {
                    self.dead_letter(token, kind, &reason, payload, seq).await
                }
            },
        }
    }

    async fn dead_letter(
        &mut self,
        token: &str,
        kind: &str,
        reason: &str,
        payload: &[u8],
        seq: u64,
    ) -> Result<(), NatsError> {
        self.ctx.metrics.m().error("nats_deadletter");
        tracing::warn!(
            partition = self.p,
            asset = token,
            seq,
            kind,
            "dead-lettered: {reason}"
        );
        let mut headers = async_nats::HeaderMap::new();
        headers.insert("Shocktwin-Kind", kind);
        headers.insert(
            "Shocktwin-Reason",
            reason.replace(['\r', '\n'], " ").as_str(),
        );
        headers.insert("Shocktwin-Stream-Seq", seq.to_string().as_str());
        let publish = Publish::build()
            .payload(Bytes::copy_from_slice(payload))
            .headers(headers)
            .message_id(format!("d/{seq}"));
        self.publish(format!("shocktwin.deadletter.{token}"), publish)
            .await
    }

    async fn publish(&mut self, subject: String, msg: Publish) -> Result<(), NatsError> {
        let ack = self
            .ctx
            .js
            .send_publish(subject.clone(), msg)
            .await
            .map_err(|e| NatsError::new(format!("publish to {subject}"), e))?;
        self.pending.push(ack);
        Ok(())
    }

    /// A new run's twin for `asset`, and the pending service it reads the
    /// unit for (a road asset's by the road observer, any other's by the dyno
    /// observer when the bundle has one).
    fn start_twin(
        &self,
        asset: &str,
    ) -> Result<(Estimator, Option<(ServiceToRead, ServiceReading)>), Refused> {
        let asset_cfg = self.ctx.baselines.asset_config(&self.ctx.config, asset);
        let twin = self.ctx.factory.estimator_of(asset, &asset_cfg);
        let mut est = twin.map_err(|e| {
            Refused::Input("twin", format!("cannot start the twin for `{asset}`: {e}"))
        })?;
        let mut service = None;
        if let Some(s) = asset_cfg.read_service {
            if est.road().is_some() {
                est = est.read_road_baseline(s.charge_bar);
                service = Some((s, ServiceReading::new()));
            } else if est.observer().is_some() {
                service = Some((s, ServiceReading::new()));
            }
        }
        Ok((est, service))
    }

    async fn apply(&mut self, b: TelemetryBatch, seq: u64) -> Result<(), Refused> {
        let asset = b.asset_id.clone();
        if b.batch == 0 {
            if let Some(open) = self.runs.get(&asset) {
                if open.run_id == b.run_id {
                    return Err(Refused::Input(
                        "back_in_time",
                        format!(
                            "batch 0 of run `{}` again after batch {}: going back in time",
                            b.run_id, open.last_batch
                        ),
                    ));
                }
                // A new run of the asset: the open one was cut off.
                if let Some(open) = self.runs.remove(&asset) {
                    self.end_run(&asset, open, "interrupted").await?;
                }
            }
            let meta = b
                .metadata()
                .map_err(|e| Refused::Input(e.kind(), e.to_string()))?;
            let (est, service) = self.start_twin(&asset)?;
            let mut map = meta.to_map();
            map.remove("asset_id");
            map.remove("run_id");
            self.run_event(&asset, &b.run_id, seq, "started", &map, None)
                .await?;
            tracing::info!(partition = self.p, asset, run = %b.run_id, "run started");
            self.runs.insert(
                asset.clone(),
                OpenRun {
                    run_id: b.run_id.clone(),
                    meta: map,
                    last_batch: 0,
                    health: Health::Unknown,
                    est: Box::new(est),
                    service,
                    first_t_ns: None,
                    start_seq: seq,
                },
            );
        } else {
            match self.runs.get(&asset) {
                Some(open) if open.run_id == b.run_id => {
                    if b.batch <= open.last_batch {
                        return Err(Refused::Input(
                            "back_in_time",
                            format!(
                                "batch {} of run `{}` after batch {}: going back in time",
                                b.batch, b.run_id, open.last_batch
                            ),
                        ));
                    }
                }
                _ => {
                    return Err(Refused::Input(
                        "no_start",
                        format!(
                            "batch {} of run `{}` without the run's batch 0",
                            b.batch, b.run_id
                        ),
                    ))
                }
            }
        }
        let Some(mut open) = self.runs.remove(&asset) else {
            return Ok(());
        };
        open.last_batch = b.batch;
        let mut failed = None;
        for s in b.samples() {
            open.first_t_ns.get_or_insert(s.t_ns());
            if let Err(e) = open.est.push(s) {
                failed = Some(e.to_string());
                break;
            }
        }
        self.buf.clear();
        open.drain_into(&mut self.buf);
        self.publish_estimates(&asset, &mut open).await?;
        if let Some(reason) = failed {
            tracing::warn!(partition = self.p, asset, "the twin failed: {reason}");
            self.end_run(&asset, open, "failed").await?;
        } else if b.end {
            self.end_run(&asset, open, "completed").await?;
        } else {
            self.runs.insert(asset, open);
        }
        Ok(())
    }

    async fn end_run(
        &mut self,
        asset: &str,
        mut open: OpenRun,
        outcome: &str,
    ) -> Result<(), Refused> {
        let finished = open.est.finish();
        self.buf.clear();
        open.drain_into(&mut self.buf);
        self.publish_estimates(asset, &mut open).await?;
        let outcome = if finished.is_err() { "failed" } else { outcome };
        if outcome == "completed" {
            self.complete_service(asset, &open).await;
        }
        let mut map = open.meta.clone();
        map.insert("outcome".into(), outcome.into());
        let counters = open.est.counters();
        // on a road asset the road observer reads the charge (see EstimatorTwin::counters)
        let observer = (open.est.observer().is_some() && open.est.road().is_none())
            .then_some(counters.observer);
        let ended = RunEnded {
            ticks: counters.ticks,
            observer,
            road: counters.road,
        };
        self.run_event(
            asset,
            &open.run_id,
            open.start_seq,
            "ended",
            &map,
            Some(ended),
        )
        .await?;
        tracing::info!(partition = self.p, asset, run = %open.run_id, outcome, "run ended");
        Ok(())
    }

    /// After a run that read the unit for a pending service: its result
    /// goes to the group's buckets (see [`super::baselines::complete_service`]).
    /// A bucket error is logged: the service stays pending.
    async fn complete_service(&self, asset: &str, open: &OpenRun) {
        let Some((service, reading)) = open.service else {
            return;
        };
        let read_here = match open.est.road_baseline() {
            Some(road) => road.map(AssetBaseline::Road),
            None => match open.est.bundle().physics().observer {
                Some(params) => reading
                    .finish(service.charge_bar, &params)
                    .map(|r| {
                        AssetBaseline::Observer(crate::server::estimator::with_earlier_readings(
                            &UnitBaseline {
                                damping_law: open.est.config().observer_damping_law,
                                ..r.baseline
                            },
                            open.est.config().observer_service_earlier.as_ref(),
                            params.accel_cluster_rel,
                        ))
                    })
                    .map_err(|e| e.to_string()),
                None => return,
            },
        };
        // The run's processing start is not kept across a failover: now
        // stands for it (it matters only to a run whose clock is not
        // calendar time).
        let started = std::time::SystemTime::now();
        let read = match recorded_before(&open.run_id, open.first_t_ns, started, service) {
            Some(why) => Err(why),
            None => read_here.map_err(|why| format!("run `{}`: {why}", open.run_id)),
        };
        let done = super::baselines::complete_service(
            &self.ctx.baseline_kv,
            &self.ctx.service_kv,
            asset,
            service,
            read.clone(),
        )
        .await;
        match (done, read) {
            (Ok(true), Ok(b)) => tracing::info!(
                partition = self.p, asset, run = %open.run_id, baseline = %b,
                "unit baseline read after the service, for the group"
            ),
            (Ok(true), Err(why)) => tracing::warn!(
                partition = self.p,
                asset,
                "no unit baseline from this run, the service stays pending: {why}"
            ),
            (Ok(false), _) => tracing::info!(
                partition = self.p, asset, run = %open.run_id,
                "the service this run read for was replaced or withdrawn meanwhile"
            ),
            (Err(e), _) => tracing::error!(partition = self.p, asset, "{e}"),
        }
    }

    async fn publish_estimates(&mut self, asset: &str, open: &mut OpenRun) -> Result<(), Refused> {
        let token = super::payload::subject_token(asset);
        let subject = format!("shocktwin.estimate.{token}");
        let buf = std::mem::take(&mut self.buf);
        for e in &buf {
            let payload = serde_json::to_vec(&EstimateMsg {
                run_id: &open.run_id,
                e,
                unfloored_bar: e.unfloored_bar,
                unfloored_half_bar: e.unfloored_half_bar,
            })
            .map_err(|err| Refused::Publish(NatsError::new("estimate encoding", err)))?;
            let id = msg_id('e', asset, &open.run_id, open.start_seq, e.t_ns);
            self.publish(
                subject.clone(),
                Publish::build().payload(payload.into()).message_id(id),
            )
            .await
            .map_err(Refused::Publish)?;
            if e.health != open.health {
                let msg = HealthMsg {
                    run_id: &open.run_id,
                    t_ns: e.t_ns,
                    from: open.health,
                    to: e.health,
                };
                let payload = serde_json::to_vec(&msg)
                    .map_err(|err| Refused::Publish(NatsError::new("health encoding", err)))?;
                let id = msg_id('h', asset, &open.run_id, open.start_seq, e.t_ns);
                self.publish(
                    format!("shocktwin.health.{token}"),
                    Publish::build().payload(payload.into()).message_id(id),
                )
                .await
                .map_err(Refused::Publish)?;
                open.health = e.health;
            }
        }
        self.buf = buf;
        Ok(())
    }

    async fn run_event(
        &mut self,
        asset: &str,
        run_id: &str,
        start_seq: u64,
        event: &str,
        meta: &BTreeMap<String, String>,
        ended: Option<RunEnded>,
    ) -> Result<(), Refused> {
        let token = super::payload::subject_token(asset);
        let payload = serde_json::to_vec(&RunEvent {
            event,
            asset_id: asset,
            run_id,
            meta,
            ticks: ended.map(|e| e.ticks),
            observer: ended.and_then(|e| e.observer),
            road: ended.and_then(|e| e.road),
        })
        .map_err(|e| Refused::Publish(NatsError::new("run event encoding", e)))?;
        let id = msg_id('r', asset, run_id, start_seq, event);
        self.publish(
            format!("shocktwin.run.{token}"),
            Publish::build().payload(payload.into()).message_id(id),
        )
        .await
        .map_err(Refused::Publish)
    }
}

/// Why a batch was not taken.
enum Refused {
    /// Bad input: dead-lettered with this kind and reason.
    Input(&'static str, String),
    /// Publishing failed: the partition stops (and restarts from its
    /// checkpoint).
    Publish(NatsError),
}

/// `shocktwin.estimate.<asset>`: `run_id` and the `/estimate` fields (SPEC §10).
#[derive(Serialize)]
pub struct EstimateMsg<'a> {
    /// The run.
    pub run_id: &'a str,
    /// The estimate (`t_ns` and the SPEC §2/§2a fields).
    #[serde(flatten)]
    pub e: &'a Estimate,
    /// [`Estimate::unfloored_bar`], which `/estimate` does not carry: the
    /// gateway's store summarises runs with it (`docs/nats.md`).
    pub unfloored_bar: f64,
    /// [`Estimate::unfloored_half_bar`], likewise.
    pub unfloored_half_bar: f64,
}

/// `shocktwin.health.<asset>`: a change of the reported state.
#[derive(Debug, Serialize)]
pub struct HealthMsg<'a> {
    /// The run.
    pub run_id: &'a str,
    /// Tick of the change, ns.
    pub t_ns: i64,
    /// Previous state.
    pub from: Health,
    /// New state.
    pub to: Health,
}

/// `shocktwin.run.<asset>`: a run started or ended (with its metadata).
#[derive(Debug, Serialize)]
pub struct RunEvent<'a> {
    /// `started` or `ended`.
    pub event: &'a str,
    /// The asset.
    pub asset_id: &'a str,
    /// The run.
    pub run_id: &'a str,
    /// The `shocktwin.run` record (and `outcome` when ended).
    pub meta: &'a BTreeMap<String, String>,
    /// Estimates emitted (when ended).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ticks: Option<u64>,
    /// What the charge observer made of the run's reversals (when ended,
    /// with a model that reads the observer; kept in the estimator's
    /// checkpoint across a failover).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub observer: Option<dt_core::charge::ObserverCounters>,
    /// What the road observer made of the run's blocks (when ended, on a
    /// road asset; kept in the estimator's checkpoint likewise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub road: Option<dt_core::road::RoadCounters>,
}

/// What an `ended` run event carries beyond the metadata.
#[derive(Debug, Clone, Copy)]
struct RunEnded {
    ticks: u64,
    observer: Option<dt_core::charge::ObserverCounters>,
    road: Option<dt_core::road::RoadCounters>,
}

impl From<PayloadError> for Refused {
    fn from(e: PayloadError) -> Self {
        Refused::Input(e.kind(), e.to_string())
    }
}
