//! Unit baselines in a NATS group (see [`crate::server::baselines`]).
//!
//! The key-value bucket [`BASELINE_BUCKET`] is the group's record: key =
//! asset id, value = [`BaselineEntry`] as JSON, the latest only. A
//! `PUT /v1/assets/{id}/baseline` on any daemon writes there (and `DELETE`
//! deletes the key); every daemon of the group watches the bucket — its
//! current values at start-up, then every change — and applies each to its
//! own copy (which its worker's runs use), its store and its trends. A run
//! takes the baseline the daemon that starts it has at that moment: one set
//! milliseconds before may not have reached it yet.

use std::sync::{Arc, OnceLock};

use async_nats::jetstream::{self, kv};
use dt_core::charge::UnitBaseline;
use futures_util::future::BoxFuture;
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};

use super::{baseline_bucket, connect, NatsConfig, NatsError, BASELINE_BUCKET};
use crate::server::source::{Source, SourceContext};
use crate::server::store::{FleetStore, StoredBaseline, Trends};
use crate::server::ServeError;

/// One value of the bucket.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BaselineEntry {
    /// See [`UnitBaseline`].
    pub charge_bar: f64,
    /// See [`UnitBaseline`].
    pub read_bar: f64,
    /// See [`UnitBaseline`].
    pub read_sd_bar: f64,
    /// When it was set, ms since the Unix epoch.
    pub set_ms: i64,
}

impl From<StoredBaseline> for BaselineEntry {
    fn from(b: StoredBaseline) -> Self {
        Self {
            charge_bar: b.baseline.charge_bar,
            read_bar: b.baseline.read_bar,
            read_sd_bar: b.baseline.read_sd_bar,
            set_ms: b.set_ms,
        }
    }
}

impl BaselineEntry {
    /// The baseline, checked.
    fn stored(self) -> Result<StoredBaseline, String> {
        let baseline = UnitBaseline {
            charge_bar: self.charge_bar,
            read_bar: self.read_bar,
            read_sd_bar: self.read_sd_bar,
        };
        baseline.validate().map_err(|e| e.to_string())?;
        Ok(StoredBaseline {
            baseline,
            set_ms: self.set_ms,
        })
    }
}

/// The bucket, once the watcher has connected (for the API's writes).
#[derive(Debug, Clone, Default)]
pub struct BaselineBucket(Arc<OnceLock<kv::Store>>);

impl BaselineBucket {
    /// The bucket, if connected.
    #[must_use]
    pub fn get(&self) -> Option<&kv::Store> {
        self.0.get()
    }

    /// Writes (`Some`) or deletes (`None`) the asset's baseline for the
    /// whole group.
    pub async fn write(
        &self,
        asset_id: &str,
        baseline: Option<StoredBaseline>,
    ) -> Result<(), NatsError> {
        let kv = self.get().ok_or_else(|| {
            NatsError::new(
                format!("bucket {BASELINE_BUCKET}"),
                "not connected to the NATS group yet",
            )
        })?;
        let what = format!("bucket {BASELINE_BUCKET}, key `{asset_id}`");
        match baseline {
            Some(b) => {
                let value = serde_json::to_vec(&BaselineEntry::from(b))
                    .map_err(|e| NatsError::new(&what, e))?;
                kv.put(asset_id, value.into())
                    .await
                    .map(drop)
                    .map_err(|e| NatsError::new(&what, e))
            }
            None => kv
                .delete(asset_id)
                .await
                .map_err(|e| NatsError::new(&what, e)),
        }
    }
}

/// The watcher, a [`Source`] of every daemon of a NATS group.
pub struct NatsBaselines {
    cfg: NatsConfig,
    bucket: BaselineBucket,
    store: Option<Arc<dyn FleetStore>>,
    trends: Arc<Trends>,
}

impl NatsBaselines {
    /// Watches the group at `cfg.url`; publishes the bucket in `bucket` once
    /// connected; applies the values to the daemon's baselines (through its
    /// ingest), `store` and `trends`.
    #[must_use]
    pub fn new(
        cfg: NatsConfig,
        bucket: BaselineBucket,
        store: Option<Arc<dyn FleetStore>>,
        trends: Arc<Trends>,
    ) -> Self {
        Self {
            cfg,
            bucket,
            store,
            trends,
        }
    }

    async fn watch(self, ctx: SourceContext) -> Result<(), NatsError> {
        let client = connect(&self.cfg, "shocktwin baselines").await?;
        let js = jetstream::new(client);
        let kv = baseline_bucket(&js).await?;
        let mut entries = kv
            .watch_with_history(">")
            .await
            .map_err(|e| NatsError::new(format!("watch bucket {BASELINE_BUCKET}"), e))?;
        // A second connection of the same daemon cannot have set it first.
        let _ = self.bucket.0.set(kv.clone());
        let config = Arc::new(ctx.ingest.config().clone());
        loop {
            let entry = tokio::select! {
                () = ctx.cancel.cancelled() => break,
                e = entries.next() => e,
            };
            let entry = match entry {
                Some(Ok(entry)) => entry,
                // The watch ended or failed (a server restart): watch again,
                // from the bucket's current values (applying them twice is
                // harmless).
                other => {
                    if let Some(Err(e)) = other {
                        tracing::warn!("baselines: {e}; watching again");
                    }
                    tokio::select! {
                        () = ctx.cancel.cancelled() => break,
                        () = tokio::time::sleep(std::time::Duration::from_secs(1)) => {}
                    }
                    match kv.watch_with_history(">").await {
                        Ok(w) => entries = w,
                        Err(e) => tracing::warn!("baselines: watch bucket {BASELINE_BUCKET}: {e}"),
                    }
                    continue;
                }
            };
            let baseline = match entry.operation {
                kv::Operation::Put => {
                    match serde_json::from_slice::<BaselineEntry>(&entry.value)
                        .map_err(|e| e.to_string())
                        .and_then(BaselineEntry::stored)
                    {
                        Ok(b) => Some(b),
                        Err(e) => {
                            // One bad value never stops the watcher.
                            ctx.ingest.metrics().error("baseline");
                            tracing::error!(
                                "bucket {BASELINE_BUCKET}, key `{}`: not a unit baseline ({e}); ignored",
                                entry.key
                            );
                            continue;
                        }
                    }
                }
                kv::Operation::Delete | kv::Operation::Purge => None,
            };
            let (baselines, store, trends) = (
                Arc::clone(ctx.ingest.baselines()),
                self.store.clone(),
                Arc::clone(&self.trends),
            );
            let (config, ingest, asset) =
                (Arc::clone(&config), ctx.ingest.clone(), entry.key.clone());
            let applied = tokio::task::spawn_blocking(move || {
                baselines.set(store.as_deref(), &trends, &asset, baseline)?;
                if let Some(store) = &store {
                    trends.refresh(store.as_ref(), &config, ingest.metrics(), &asset);
                }
                Ok::<_, crate::server::store::StoreError>(())
            })
            .await;
            match applied {
                Ok(Ok(())) => tracing::info!(
                    asset = %entry.key,
                    set = baseline.is_some(),
                    "unit baseline from the group; used from the asset's next run"
                ),
                Ok(Err(e)) => tracing::error!(asset = %entry.key, "baselines: {e}"),
                Err(e) => tracing::error!(asset = %entry.key, "baselines: {e}"),
            }
        }
        Ok(())
    }
}

impl Source for NatsBaselines {
    fn name(&self) -> String {
        format!("nats baselines ({})", self.cfg.url.as_deref().unwrap_or(""))
    }

    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>> {
        Box::pin(async move {
            self.watch(ctx).await.map_err(|e| ServeError::Invalid {
                key: "nats".into(),
                reason: e.to_string(),
            })
        })
    }
}
