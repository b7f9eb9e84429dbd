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
//!
//! Services reported at a known charge (`PUT /v1/assets/{id}/service`) go the
//! same way through [`SERVICE_BUCKET`] ([`ServiceEntry`]). The worker whose run
//! reads the unit writes the result back: the baseline to [`BASELINE_BUCKET`]
//! and the service's key deleted, or the service again with the reason it
//! gave none ([`BaselineBucket::complete_service`]).

use std::sync::{Arc, OnceLock};

use async_nats::jetstream::{self, kv};
use dt_core::charge::UnitBaseline;
use dt_core::road::RoadBaseline;
use futures_util::future::BoxFuture;
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};

use super::{
    baseline_bucket, connect_patiently, service_bucket, NatsConfig, NatsError, SetUpError,
    SetUpRetries, BASELINE_BUCKET, SERVICE_BUCKET,
};
use crate::server::config::ServiceToRead;
use crate::server::source::{Source, SourceContext};
use crate::server::store::{AssetBaseline, FleetStore, PendingService, StoredBaseline, Trends};
use crate::server::ServeError;

/// One value of the bucket: an observer baseline (`read_bar`, `read_sd_bar`)
/// or a road asset's (`offset_n`, `blocks`). Unknown fields are ignored, as in
/// the run payloads: a later daemon's entry is read for what this one knows,
/// so a group can be upgraded one daemon at a time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BaselineEntry {
    /// The charge the unit held, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// See [`UnitBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub read_bar: Option<f64>,
    /// See [`UnitBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub read_sd_bar: Option<f64>,
    /// See [`UnitBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accel_range_mps2: Option<[f64; 2]>,
    /// See [`UnitBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub damping_law: Option<dt_core::charge::DampingLaw>,
    /// See [`UnitBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub second: Option<dt_core::charge::BaselineReading>,
    /// See [`UnitBaseline`] (left out: one run).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runs_averaged: Option<f64>,
    /// See [`UnitBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub split_bar: Option<f64>,
    /// See [`UnitBaseline`] (left out: none).
    #[serde(
        default,
        skip_serializing_if = "dt_core::charge::no_other_excitations",
        with = "dt_core::charge::other_excitations_serde"
    )]
    pub other_excitations:
        [Option<dt_core::charge::ExcitationBaseline>; dt_core::charge::OTHER_EXCITATIONS],
    /// See [`RoadBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_n: Option<f64>,
    /// See [`RoadBaseline`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blocks: Option<u64>,
    /// When it was set, ms since the Unix epoch.
    pub set_ms: i64,
}

impl From<StoredBaseline> for BaselineEntry {
    fn from(b: StoredBaseline) -> Self {
        let (read, road) = match b.baseline {
            AssetBaseline::Observer(u) => (Some(u), None),
            AssetBaseline::Road(r) => (None, Some(r)),
        };
        Self {
            charge_bar: b.baseline.charge_bar(),
            read_bar: read.map(|u| u.read_bar),
            read_sd_bar: read.map(|u| u.read_sd_bar),
            accel_range_mps2: read.and_then(|u| u.accel_range_mps2),
            damping_law: read.and_then(|u| u.damping_law),
            second: read.and_then(|u| u.second),
            runs_averaged: read.map(|u| u.runs_averaged).filter(|&n| n > 1.0),
            split_bar: read.and_then(|u| u.split_bar),
            other_excitations: read.map(|u| u.other_excitations).unwrap_or_default(),
            offset_n: road.map(|r| r.offset_n),
            blocks: road.map(|r| r.blocks),
            set_ms: b.set_ms,
        }
    }
}

impl BaselineEntry {
    /// The baseline, checked.
    fn stored(self) -> Result<StoredBaseline, String> {
        let baseline = match (self.read_bar, self.read_sd_bar, self.offset_n, self.blocks) {
            (Some(read_bar), Some(read_sd_bar), None, None) => {
                let b = UnitBaseline {
                    charge_bar: self.charge_bar,
                    read_bar,
                    read_sd_bar,
                    accel_range_mps2: self.accel_range_mps2,
                    damping_law: self.damping_law,
                    second: self.second,
                    runs_averaged: self.runs_averaged.unwrap_or(1.0),
                    split_bar: self.split_bar,
                    other_excitations: self.other_excitations,
                };
                b.validate().map_err(|e| e.to_string())?;
                AssetBaseline::Observer(b)
            }
            (None, None, Some(offset_n), Some(blocks)) => {
                let b = RoadBaseline {
                    charge_bar: self.charge_bar,
                    offset_n,
                    blocks,
                };
                b.validate()?;
                AssetBaseline::Road(b)
            }
            _ => {
                return Err(
                    "neither an observer baseline (read_bar, read_sd_bar) nor a road baseline \
                     (offset_n, blocks)"
                        .into(),
                )
            }
        };
        Ok(StoredBaseline {
            baseline,
            set_ms: self.set_ms,
        })
    }
}

/// One value of the service bucket (unknown fields ignored, as above).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ServiceEntry {
    /// See [`PendingService`].
    pub charge_bar: f64,
    /// See [`PendingService`].
    pub set_ms: i64,
    /// See [`PendingService`].
    pub refusal: Option<String>,
}

impl From<PendingService> for ServiceEntry {
    fn from(s: PendingService) -> Self {
        Self {
            charge_bar: s.charge_bar,
            set_ms: s.set_ms,
            refusal: s.refusal,
        }
    }
}

impl ServiceEntry {
    /// The service, checked.
    fn pending(self) -> Result<PendingService, String> {
        if !(self.charge_bar.is_finite() && self.charge_bar >= 0.0) {
            return Err(format!("charge_bar {} is not a charge", self.charge_bar));
        }
        Ok(PendingService {
            charge_bar: self.charge_bar,
            set_ms: self.set_ms,
            refusal: self.refusal,
        })
    }
}

/// The buckets, once the watcher has connected (for the API's writes).
#[derive(Debug, Clone, Default)]
pub struct BaselineBucket(Arc<OnceLock<kv::Store>>, Arc<OnceLock<kv::Store>>);

impl BaselineBucket {
    /// The bucket, if connected.
    #[must_use]
    pub fn get(&self) -> Option<&kv::Store> {
        self.0.get()
    }

    /// Writes (`Some`) or deletes (`None`) the asset's pending service for
    /// the whole group.
    pub async fn write_service(
        &self,
        asset_id: &str,
        service: Option<PendingService>,
    ) -> Result<(), NatsError> {
        let kv = self.1.get().ok_or_else(|| {
            NatsError::new(
                format!("bucket {SERVICE_BUCKET}"),
                "not connected to the NATS group yet",
            )
        })?;
        put_or_delete(
            kv,
            SERVICE_BUCKET,
            asset_id,
            service.map(ServiceEntry::from),
        )
        .await
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

async fn put_or_delete<T: Serialize>(
    kv: &kv::Store,
    bucket: &str,
    key: &str,
    value: Option<T>,
) -> Result<(), NatsError> {
    let what = format!("bucket {bucket}, key `{key}`");
    match value {
        Some(v) => {
            let bytes = serde_json::to_vec(&v).map_err(|e| NatsError::new(&what, e))?;
            kv.put(key, bytes.into())
                .await
                .map(drop)
                .map_err(|e| NatsError::new(&what, e))
        }
        None => kv.delete(key).await.map_err(|e| NatsError::new(&what, e)),
    }
}

/// What a worker's run read for a pending service, written back to the
/// group: the baseline (and the service forgotten) or the reason it gave
/// none (kept with the service). A service replaced or withdrawn since the
/// run started is left alone. `baselines` and `services` are the group's
/// buckets.
pub async fn complete_service(
    baselines: &kv::Store,
    services: &kv::Store,
    asset_id: &str,
    service: ServiceToRead,
    read: Result<AssetBaseline, String>,
) -> Result<bool, NatsError> {
    let what = format!("bucket {SERVICE_BUCKET}, key `{asset_id}`");
    let current = services
        .get(asset_id)
        .await
        .map_err(|e| NatsError::new(&what, e))?
        .and_then(|v| serde_json::from_slice::<ServiceEntry>(&v).ok());
    let Some(mut entry) = current.filter(|e| e.set_ms == service.set_ms) else {
        return Ok(false);
    };
    match read {
        Ok(b) => {
            let stored = StoredBaseline {
                baseline: b,
                set_ms: service.set_ms,
            };
            put_or_delete(
                baselines,
                BASELINE_BUCKET,
                asset_id,
                Some(BaselineEntry::from(stored)),
            )
            .await?;
            put_or_delete::<ServiceEntry>(services, SERVICE_BUCKET, asset_id, None).await?;
        }
        Err(why) => {
            entry.refusal = Some(why);
            put_or_delete(services, SERVICE_BUCKET, asset_id, Some(entry)).await?;
        }
    }
    Ok(true)
}

/// One value of either bucket, parsed.
// A unit's own damping law makes an observer baseline ≈ 0.4 kB; one is made per
// change of an asset's baseline, never per sample, and stays `Copy`.
#[allow(clippy::large_enum_variant)]
enum UnitChange {
    Baseline(Option<StoredBaseline>),
    Service(Option<PendingService>),
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
        const NAME: &str = "shocktwin baselines";
        let Some(client) = connect_patiently(&self.cfg, NAME, &ctx).await? else {
            return Ok(()); // stopped before the server came
        };
        let js = jetstream::new(client);
        let mut retries = SetUpRetries::default();
        let (kv, services) = loop {
            let buckets = async {
                Ok::<_, SetUpError>((baseline_bucket(&js).await?, service_bucket(&js).await?))
            };
            match buckets.await {
                Ok(buckets) => break buckets,
                Err(e) => {
                    if !retries.after(NAME, e, &ctx).await? {
                        return Ok(()); // stopped while waiting
                    }
                }
            }
        };
        ctx.started.signal(); // connected, buckets there (a review: not before)
        let config = Arc::new(ctx.ingest.config().clone());
        // The work that applies one value on a blocking thread: `change` on
        // the daemon's copy and store, then the asset's trend.
        let work = |key: String, change: UnitChange| {
            let (baselines, store, trends) = (
                Arc::clone(ctx.ingest.baselines()),
                self.store.clone(),
                Arc::clone(&self.trends),
            );
            let (config, ingest) = (Arc::clone(&config), ctx.ingest.clone());
            move || {
                let what = match change {
                    UnitChange::Baseline(b) => {
                        baselines.set(store.as_deref(), &trends, &key, b)?;
                        format!(
                            "unit baseline from the group (set: {}); used from the asset's next run",
                            b.is_some()
                        )
                    }
                    UnitChange::Service(s) => {
                        let pending = s.is_some();
                        baselines.set_service(store.as_deref(), &trends, &key, s)?;
                        format!("service from the group (pending: {pending})")
                    }
                };
                if let Some(store) = &store {
                    trends.refresh(store.as_ref(), &config, ingest.metrics(), &key);
                }
                Ok(what)
            }
        };
        let apply_baseline = |key: String, value: Option<&[u8]>| {
            let b = value
                .map(|v| {
                    serde_json::from_slice::<BaselineEntry>(v)
                        .map_err(|e| e.to_string())
                        .and_then(BaselineEntry::stored)
                        .map_err(|e| format!("not a unit baseline ({e})"))
                })
                .transpose()?;
            Ok(work(key, UnitChange::Baseline(b)))
        };
        let apply_service = |key: String, value: Option<&[u8]>| {
            let s = value
                .map(|v| {
                    serde_json::from_slice::<ServiceEntry>(v)
                        .map_err(|e| e.to_string())
                        .and_then(ServiceEntry::pending)
                        .map_err(|e| format!("not a service ({e})"))
                })
                .transpose()?;
            Ok(work(key, UnitChange::Service(s)))
        };
        // A second connection of the same daemon cannot have set them first.
        let _ = self.bucket.0.set(kv.clone());
        let _ = self.bucket.1.set(services.clone());
        tokio::try_join!(
            watch_bucket(&kv, BASELINE_BUCKET, &ctx, apply_baseline),
            watch_bucket(&services, SERVICE_BUCKET, &ctx, apply_service),
        )?;
        Ok(())
    }
}

/// Applies every value of `kv` (its current ones, then each change) with
/// `apply` (key, value or `None` for a deletion → the work to run on a
/// blocking thread, or why the value is bad) until `ctx` is cancelled. A bad
/// value is counted and logged, never stops the watcher; a broken watch is
/// started again from the bucket's current values (applying them twice is
/// harmless).
async fn watch_bucket<F, W>(
    kv: &kv::Store,
    name: &str,
    ctx: &SourceContext,
    apply: F,
) -> Result<(), NatsError>
where
    F: Fn(String, Option<&[u8]>) -> Result<W, String>,
    W: FnOnce() -> Result<String, crate::server::store::StoreError> + Send + 'static,
{
    let mut entries = kv
        .watch_with_history(">")
        .await
        .map_err(|e| NatsError::new(format!("watch bucket {name}"), e))?;
    loop {
        let entry = tokio::select! {
            () = ctx.cancel.cancelled() => break,
            e = entries.next() => e,
        };
        let entry = match entry {
            Some(Ok(entry)) => entry,
            other => {
                if let Some(Err(e)) = other {
                    tracing::warn!("bucket {name}: {e}; watching again");
                }
                tokio::select! {
                    () = ctx.cancel.cancelled() => break,
                    () = tokio::time::sleep(std::time::Duration::from_secs(1)) => {}
                }
                match kv.watch_with_history(">").await {
                    Ok(w) => entries = w,
                    Err(e) => tracing::warn!("watch bucket {name}: {e}"),
                }
                continue;
            }
        };
        let value = match entry.operation {
            kv::Operation::Put => Some(&entry.value[..]),
            kv::Operation::Delete | kv::Operation::Purge => None,
        };
        let work = match apply(entry.key.clone(), value) {
            Ok(w) => w,
            Err(e) => {
                ctx.ingest.metrics().error("baseline");
                tracing::error!("bucket {name}, key `{}`: {e}; ignored", entry.key);
                continue;
            }
        };
        match tokio::task::spawn_blocking(work).await {
            Ok(Ok(what)) => tracing::info!(asset = %entry.key, "{what}"),
            Ok(Err(e)) => tracing::error!(asset = %entry.key, "bucket {name}: {e}"),
            Err(e) => tracing::error!(asset = %entry.key, "bucket {name}: {e}"),
        }
    }
    Ok(())
}

impl Source for NatsBaselines {
    fn name(&self) -> String {
        format!(
            "nats baselines ({})",
            super::without_credentials(self.cfg.url.as_deref().unwrap_or(""))
        )
    }

    fn says_started(&self) -> bool {
        true // once connected
    }

    fn run(self: Box<Self>, ctx: SourceContext) -> BoxFuture<'static, Result<(), ServeError>> {
        Box::pin(async move {
            Box::pin(self.watch(ctx))
                .await
                .map_err(|e| ServeError::Invalid {
                    key: "nats".into(),
                    reason: e.to_string(),
                })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The observer baseline of these tests: 12 bar read as 10.84 ± 0.65,
    /// with the excitation range given.
    fn observer_baseline(accel_range_mps2: Option<[f64; 2]>) -> StoredBaseline {
        StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                charge_bar: 12.0,
                read_bar: 10.84,
                read_sd_bar: 0.65,
                accel_range_mps2,
                damping_law: None,
                second: None,
                runs_averaged: 1.0,
                split_bar: None,
                other_excitations: Default::default(),
            }),
            set_ms: 1_700_000_000_000,
        }
    }

    #[test]
    fn a_bucket_value_carries_either_kind_and_refuses_a_mix() {
        let observer = observer_baseline(None);
        let ranged = observer_baseline(Some([1.45, 1.62]));
        let road = StoredBaseline {
            baseline: AssetBaseline::Road(RoadBaseline {
                charge_bar: 12.0,
                offset_n: -0.26,
                blocks: 238,
            }),
            set_ms: 1_700_000_000_001,
        };
        // with a second reading at another charge
        let mut two = ranged;
        if let AssetBaseline::Observer(u) = &mut two.baseline {
            u.second = Some(dt_core::charge::BaselineReading {
                charge_bar: 4.0,
                read_bar: 3.4,
                read_sd_bar: 0.3,
                runs_averaged: 7.0 / 3.0,
            });
            // each reading averaging several runs
            u.runs_averaged = 2.0 / 0.7;
            // and a reading at another excitation
            u.other_excitations[0] = Some(dt_core::charge::ExcitationBaseline {
                accel_range_mps2: [5.8, 6.3],
                charge_bar: 12.0,
                read_bar: 11.2 / 0.9,
                read_sd_bar: 0.2,
                runs_averaged: 1.0,
                second: None,
                split_bar: Some(-0.3),
            });
        }
        for b in [observer, ranged, two, road] {
            let json = serde_json::to_string(&BaselineEntry::from(b)).unwrap();
            let back: BaselineEntry = serde_json::from_str(&json).unwrap();
            assert_eq!(back.stored().unwrap(), b, "{json}");
        }
        // what a daemon before road baselines wrote is read as it was
        let old =
            r#"{"charge_bar":12.0,"read_bar":10.84,"read_sd_bar":0.65,"set_ms":1700000000000}"#;
        let entry: BaselineEntry = serde_json::from_str(old).unwrap();
        assert_eq!(entry.stored().unwrap(), observer);
        let mixed = r#"{"charge_bar":12.0,"read_bar":10.84,"read_sd_bar":0.65,"offset_n":1.0,"blocks":3,"set_ms":1}"#;
        let entry: BaselineEntry = serde_json::from_str(mixed).unwrap();
        assert!(entry.stored().unwrap_err().contains("neither"));
        let empty = r#"{"charge_bar":12.0,"offset_n":1.0,"blocks":0,"set_ms":1}"#;
        let entry: BaselineEntry = serde_json::from_str(empty).unwrap();
        assert!(entry.stored().unwrap_err().contains("blocks"));
    }

    #[test]
    fn a_later_daemons_entry_is_read_for_what_this_one_knows() {
        let ranged = observer_baseline(Some([1.45, 1.62]));
        let later = r#"{"charge_bar":12.0,"read_bar":10.84,"read_sd_bar":0.65,"accel_range_mps2":[1.45,1.62],"excitation_hz":1.0,"set_ms":1700000000000}"#;
        let entry: BaselineEntry = serde_json::from_str(later).unwrap();
        assert_eq!(entry.stored().unwrap(), ranged);
        let later = r#"{"charge_bar":12.0,"set_ms":5,"refusal":null,"read_by":"worker-2"}"#;
        let entry: ServiceEntry = serde_json::from_str(later).unwrap();
        assert_eq!(
            (entry.charge_bar, entry.set_ms, entry.refusal),
            (12.0, 5, None)
        );
        // a known field with a bad value is still refused
        let bad = r#"{"charge_bar":"twelve","set_ms":5,"refusal":null}"#;
        assert!(serde_json::from_str::<ServiceEntry>(bad).is_err());
    }
}
