//! The fleet view of `serve --nats`: every daemon of the group (workers and
//! read-only ones, `[nats] worker = false`) reads the estimate stream from
//! "now" on and hands each run's estimates to its own sinks — the live API
//! and dashboard, the recorder and the fleet store — as relayed runs
//! ([`crate::server::ingest::Ingest::open_relay`]). So any daemon shows the
//! whole fleet, whichever worker estimated an asset.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use async_nats::jetstream::{self, consumer};
use dt_core::estimate::Estimate;
use dt_core::log::RunMetadata;
use futures_util::future::BoxFuture;
use futures_util::StreamExt;
use serde::Deserialize;

use super::payload::asset_of_token;
use super::{
    connect_patiently, ensure_topology, NatsConfig, NatsError, SetUpError, SetUpRetries,
    ESTIMATES_STREAM,
};
use crate::server::ingest::{Ingest, RunHandle};
use crate::server::sink::{RunOutcome, SourceKind};
use crate::server::source::{Source, SourceContext};
use crate::server::ServeError;

/// Relayed estimates are handed to the sinks at least this often.
const FLUSH_EVERY: Duration = Duration::from_millis(100);

/// The estimate stream as a [`Source`].
pub struct NatsFleetView {
    cfg: NatsConfig,
}

impl NatsFleetView {
    /// A view of the group at `cfg.url`.
    #[must_use]
    pub fn new(cfg: NatsConfig) -> Self {
        Self { cfg }
    }
}

impl Source for NatsFleetView {
    fn name(&self) -> String {
        format!(
            "nats fleet view ({})",
            super::without_credentials(self.cfg.url.as_deref().unwrap_or(""))
        )
    }

    fn says_started(&self) -> bool {
        true // once connected
    }

    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>> {
        Box::pin(async move {
            view(&self.cfg, ctx).await.map_err(|e| ServeError::Invalid {
                key: "nats".into(),
                reason: e.to_string(),
            })
        })
    }
}

#[derive(Deserialize)]
struct EstimateIn {
    run_id: String,
    #[serde(flatten)]
    e: Estimate,
    /// `Estimate::unfloored_bar` (absent from a worker before the
    /// sixty-ninth session's: NaN, and the store takes the floored values).
    #[serde(default)]
    unfloored_bar: Option<f64>,
    /// `Estimate::unfloored_half_bar`, likewise.
    #[serde(default)]
    unfloored_half_bar: Option<f64>,
}

impl EstimateIn {
    /// The estimate with the pair the worker sent beside it.
    fn estimate(&self) -> Estimate {
        Estimate {
            unfloored_bar: self.unfloored_bar.unwrap_or(f64::NAN),
            unfloored_half_bar: self.unfloored_half_bar.unwrap_or(f64::NAN),
            ..self.e
        }
    }
}

#[derive(Deserialize)]
struct RunEventIn {
    event: String,
    run_id: String,
    #[serde(default)]
    meta: std::collections::BTreeMap<String, String>,
    /// What the worker's charge observer made of the run (when ended).
    #[serde(default)]
    observer: Option<dt_core::charge::ObserverCounters>,
    /// What the worker's road observer made of the run (when ended, a road
    /// asset's).
    #[serde(default)]
    road: Option<dt_core::road::RoadCounters>,
}

/// The estimate stream from now on (the streams created when missing).
async fn subscribe(
    js: &jetstream::Context,
    cfg: &NatsConfig,
) -> Result<consumer::pull::Ordered, SetUpError> {
    ensure_topology(js, cfg).await?;
    let stream = js
        .get_stream(ESTIMATES_STREAM)
        .await
        .map_err(|e| NatsError::new(format!("stream {ESTIMATES_STREAM}"), e))?;
    Ok(stream
        .create_consumer(consumer::pull::OrderedConfig {
            filter_subjects: vec!["shocktwin.estimate.*".into(), "shocktwin.run.*".into()],
            deliver_policy: consumer::DeliverPolicy::New,
            ..Default::default()
        })
        .await
        .map_err(|e| NatsError::new(format!("consumer of {ESTIMATES_STREAM}"), e))?
        .messages()
        .await
        .map_err(|e| NatsError::new(format!("consumer of {ESTIMATES_STREAM}"), e))?)
}

/// When the estimate stream was made (ns since 1970), `Some(0)` when it is
/// gone, `None` when the server cannot say (an outage: the ordered consumer
/// resumes by itself then).
async fn stream_made(js: &jetstream::Context) -> Option<i128> {
    match js.get_stream(ESTIMATES_STREAM).await {
        Ok(mut stream) => stream
            .info()
            .await
            .ok()
            .map(|info| info.created.unix_timestamp_nanos()),
        Err(e) => matches!(
            e.kind(),
            jetstream::context::GetStreamErrorKind::JetStream(ref j)
                if j.error_code() == jetstream::ErrorCode::STREAM_NOT_FOUND
        )
        .then_some(0),
    }
}

/// [`subscribe`], tried again (see [`SetUpRetries`]) until it works; `None`
/// once the daemon stops first.
async fn subscribe_patiently(
    js: &jetstream::Context,
    cfg: &NatsConfig,
    ctx: &SourceContext,
    retries: &mut SetUpRetries,
) -> Result<Option<consumer::pull::Ordered>, NatsError> {
    loop {
        match subscribe(js, cfg).await {
            Ok(messages) => return Ok(Some(messages)),
            Err(e) => {
                if !retries.after("shocktwin fleet view", e, ctx).await? {
                    return Ok(None);
                }
            }
        }
    }
}

async fn view(cfg: &NatsConfig, ctx: SourceContext) -> Result<(), NatsError> {
    const NAME: &str = "shocktwin fleet view";
    let Some(client) = connect_patiently(cfg, NAME, &ctx).await? else {
        return Ok(()); // stopped before the server came
    };
    let js = jetstream::new(client);
    let mut retries = SetUpRetries::default();
    let Some(mut messages) = subscribe_patiently(&js, cfg, &ctx, &mut retries).await? else {
        return Ok(()); // stopped while waiting
    };
    // connected and subscribed (a review: not before)
    ctx.started.signal();
    // when the stream read was made: one made again since is another (a
    // helper's trial: after NATS came back with an empty store, the view
    // said "consumer not found" and showed no run again)
    let mut made = stream_made(&js).await;
    let mut runs: HashMap<String, RunHandle> = HashMap::new();
    let mut tick = tokio::time::interval(FLUSH_EVERY);
    // kept with each run and served by the API: no credentials (a review)
    let source = format!(
        "nats {}",
        super::without_credentials(cfg.url.as_deref().unwrap_or(""))
    );
    loop {
        tokio::select! {
            () = ctx.cancel.cancelled() => break,
            _ = tick.tick() => {
                for r in runs.values_mut() {
                    if r.flush().await.is_err() {
                        return Ok(());
                    }
                }
            }
            m = messages.next() => match m {
                None => break,
                Some(Err(e)) => {
                    tracing::warn!("fleet view: {e}");
                    // The ordered consumer resumes by itself after an outage;
                    // not on a stream that is gone or made again, whose
                    // sequences start over (a transient error is not taken
                    // for one: re-subscribing reads from now, the review).
                    let now = stream_made(&js).await;
                    if made.is_some() && now.is_some() && now != made {
                        tracing::warn!("fleet view: the estimate stream is gone or new: subscribing again (runs estimated meanwhile show from their next run)");
                        let again = tokio::select! {
                            () = ctx.cancel.cancelled() => break,
                            again = subscribe_patiently(&js, cfg, &ctx, &mut retries) => again?,
                        };
                        let Some(again) = again else {
                            break;
                        };
                        messages = again;
                        made = stream_made(&js).await;
                    } else {
                        tokio::time::sleep(Duration::from_millis(200)).await;
                    }
                }
                Some(Ok(msg)) => {

                    let arrived = Instant::now();
                    let mut parts = msg.subject.splitn(3, '.');
                    let (kind, token) = (parts.nth(1).unwrap_or_default(), parts.next().unwrap_or_default());
                    let asset = asset_of_token(token);
                    match kind {
                        "estimate" => match serde_json::from_slice::<EstimateIn>(&msg.payload) {
                            Ok(e) => {
                                let r = relay_for(&ctx.ingest, &mut runs, &source, &asset, &e.run_id, None).await;
                                if let Some(r) = r {
                                    r.set_arrival(arrived);
                                    r.relay([e.estimate()]);
                                }
                            }
                            Err(err) => tracing::warn!(subject = %msg.subject, "undecodable estimate: {err}"),
                        },
                        "run" => match serde_json::from_slice::<RunEventIn>(&msg.payload) {
                            Ok(ev) if ev.event == "started" => {
                                relay_for(&ctx.ingest, &mut runs, &source, &asset, &ev.run_id, Some(&ev.meta)).await;
                            }
                            Ok(ev) => {
                                if runs.get(&asset).is_some_and(|r| r.info().meta.run_id == ev.run_id) {
                                    if let Some(mut r) = runs.remove(&asset) {
                                        r.relay_counters(ev.observer, ev.road);
                                        let outcome = match ev.meta.get("outcome").map(String::as_str) {
                                            Some("failed") => RunOutcome::Failed { kind: "twin", reason: format!("{source}: the worker's twin failed") },
                                            Some("interrupted") => RunOutcome::Interrupted,
                                            _ => RunOutcome::Completed,
                                        };
                                        let _ = r.end(outcome).await;
                                    }
                                }
                            }
                            Err(err) => tracing::warn!(subject = %msg.subject, "undecodable run event: {err}"),
                        },
                        _ => {}
                    }
                }
            }
        }
    }
    for (_, r) in runs {
        let _ = r.end(RunOutcome::Interrupted).await;
    }
    Ok(())
}

/// The open relayed run of `asset` for `run_id` (a new one when the asset
/// has none or another run; the other run is ended as interrupted).
async fn relay_for<'a>(
    ingest: &Ingest,
    runs: &'a mut HashMap<String, RunHandle>,
    source: &str,
    asset: &str,
    run_id: &str,
    meta: Option<&std::collections::BTreeMap<String, String>>,
) -> Option<&'a mut RunHandle> {
    if runs
        .get(asset)
        .is_some_and(|r| r.info().meta.run_id != run_id)
    {
        if let Some(old) = runs.remove(asset) {
            let _ = old.end(RunOutcome::Interrupted).await;
        }
    }
    if !runs.contains_key(asset) {
        let mut map = meta.cloned().unwrap_or_default();
        map.remove("outcome");
        map.insert("asset_id".into(), asset.to_owned());
        map.insert("run_id".into(), run_id.to_owned());
        let meta = RunMetadata::from_map("nats", &map).ok()?;
        match ingest
            .open_relay(SourceKind::Nats, source.to_owned(), meta)
            .await
        {
            Ok(r) => {
                runs.insert(asset.to_owned(), r);
            }
            Err(_) => return None,
        }
    }
    runs.get_mut(asset)
}
