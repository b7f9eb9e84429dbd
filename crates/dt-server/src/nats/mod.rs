//! Opt-in scale-out on NATS `JetStream` (SPEC §10; the design, the payload and
//! a local cluster are in `docs/nats.md`).
//!
//! - [`payload`]: the telemetry message (JSON, versioned).
//! - [`publish`]: `shocktwin publish`, runs sent as a vehicle would.
//! - [`worker`]: `serve --nats` estimates the assets of the partitions it
//!   holds, publishes estimates and health changes (de-duplicated by message
//!   id) and checkpoints every estimator to KV with compare-and-set.
//! - [`fleet`]: the fleet view of any `serve --nats`, fed from the estimate
//!   stream into the daemon's usual sinks (live API, dashboard, store).
//!
//! Streams and buckets are created (or checked) by whoever connects first;
//! every definition is here.

pub mod baselines;
pub mod fleet;
pub mod payload;
pub mod publish;
pub mod worker;

use std::path::PathBuf;
use std::time::Duration;

use async_nats::jetstream::{self, kv, stream};
use serde::{Deserialize, Serialize};

/// Telemetry stream.
pub const TELEMETRY_STREAM: &str = "SHOCKTWIN_TELEMETRY";
/// Estimates, health changes and run events.
pub const ESTIMATES_STREAM: &str = "SHOCKTWIN_ESTIMATES";
/// Refused telemetry.
pub const DEADLETTER_STREAM: &str = "SHOCKTWIN_DEADLETTER";
/// Estimator checkpoints, one key per partition.
pub const CHECKPOINT_BUCKET: &str = "shocktwin_checkpoints";
/// Partition leases and worker heartbeats.
pub const LEASE_BUCKET: &str = "shocktwin_leases";
/// Unit baselines set over any daemon's API, one key per asset.
pub const BASELINE_BUCKET: &str = "shocktwin_baselines";
/// Key-value bucket of the services whose baseline is still to be read
/// (key: asset id).
pub const SERVICE_BUCKET: &str = "shocktwin_services";

/// Default number of partitions of the telemetry subject space.
pub const DEFAULT_PARTITIONS: u32 = 16;
/// How long a lease (and a worker's heartbeat) lives without renewal.
pub const LEASE_TTL: Duration = Duration::from_secs(4);
/// How often leases are renewed and checkpoints written.
pub const RENEW_EVERY: Duration = Duration::from_secs(1);
/// `JetStream`'s de-duplication window on the estimate stream (message ids):
/// a failover must complete well within it.
pub const DUPLICATE_WINDOW: Duration = Duration::from_secs(300);

/// `[nats]` of the daemon's configuration (and `--nats URL`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NatsConfig {
    /// Server URL(s), comma separated (`nats://host:4222`, `tls://…`);
    /// none: NATS is off.
    pub url: Option<String>,
    /// Estimate runs (a worker of the group); false: only the fleet view.
    pub worker: bool,
    /// Partitions of the telemetry subject space (fixed when the stream is
    /// created; an existing stream's count wins).
    pub partitions: u32,
    /// How long telemetry is kept, s (the longest outage a failover can
    /// replay across).
    pub telemetry_max_age_s: f64,
    /// CA of the server certificate (PEM); implies TLS.
    pub ca_file: Option<PathBuf>,
    /// Client certificate (PEM), for servers that verify clients.
    pub cert_file: Option<PathBuf>,
    /// Its key (PEM).
    pub key_file: Option<PathBuf>,
    /// File holding a token (first line) for token authentication.
    pub token_file: Option<PathBuf>,
}

impl Default for NatsConfig {
    fn default() -> Self {
        Self {
            url: None,
            worker: true,
            partitions: DEFAULT_PARTITIONS,
            telemetry_max_age_s: 7.0 * 86_400.0,
            ca_file: None,
            cert_file: None,
            key_file: None,
            token_file: None,
        }
    }
}

/// A NATS connection or set-up failure (names the URL, stream or file).
#[derive(Debug, thiserror::Error)]
#[error("NATS {what}: {reason}")]
pub struct NatsError {
    /// What failed (`connect nats://…`, `stream SHOCKTWIN_TELEMETRY`).
    pub what: String,
    /// Why.
    pub reason: String,
}

impl NatsError {
    pub(crate) fn new(what: impl Into<String>, reason: impl std::fmt::Display) -> Self {
        Self {
            what: what.into(),
            reason: reason.to_string(),
        }
    }
}

/// Connects with the configured TLS and credentials.
pub async fn connect(cfg: &NatsConfig, name: &str) -> Result<async_nats::Client, NatsError> {
    let url = cfg
        .url
        .clone()
        .ok_or_else(|| NatsError::new("connect", "no URL configured"))?;
    let what = format!("connect {url}");
    let mut opts = async_nats::ConnectOptions::new()
        .name(name)
        .retry_on_initial_connect()
        .connection_timeout(Duration::from_secs(5));
    if let Some(ca) = &cfg.ca_file {
        opts = opts.add_root_certificates(ca.clone()).require_tls(true);
    }
    if let (Some(cert), Some(key)) = (&cfg.cert_file, &cfg.key_file) {
        opts = opts.add_client_certificate(cert.clone(), key.clone());
    }
    if let Some(f) = &cfg.token_file {
        let text = std::fs::read_to_string(f)
            .map_err(|e| NatsError::new(format!("token file {}", f.display()), e))?;
        let token = text.lines().next().unwrap_or_default().trim().to_owned();
        opts = opts.token(token);
    }
    // `retry_on_initial_connect` makes connect return at once; wait for the
    // first connection (bounded) so that a wrong URL is an error, not a hang.
    let client = opts
        .connect(url.as_str())
        .await
        .map_err(|e| NatsError::new(&what, e))?;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while client.connection_state() != async_nats::connection::State::Connected {
        if tokio::time::Instant::now() > deadline {
            return Err(NatsError::new(&what, "no connection after 10 s"));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Ok(client)
}

/// The streams and buckets, created when missing. Returns the number of
/// partitions of the telemetry stream.
pub async fn ensure_topology(js: &jetstream::Context, cfg: &NatsConfig) -> Result<u32, NatsError> {
    let telemetry = stream::Config {
        name: TELEMETRY_STREAM.into(),
        subjects: vec!["shocktwin.telemetry.*".into()],
        subject_transform: Some(stream::SubjectTransform {
            source: "shocktwin.telemetry.*".into(),
            destination: format!(
                "shocktwin.telemetry.{{{{partition({},1)}}}}.{{{{wildcard(1)}}}}",
                cfg.partitions
            ),
        }),
        storage: stream::StorageType::File,
        max_age: Duration::from_secs_f64(cfg.telemetry_max_age_s),
        duplicate_window: Duration::from_secs(120),
        ..Default::default()
    };
    let mut s = js
        .get_or_create_stream(telemetry)
        .await
        .map_err(|e| NatsError::new(format!("stream {TELEMETRY_STREAM}"), e))?;
    let info = s
        .info()
        .await
        .map_err(|e| NatsError::new(format!("stream {TELEMETRY_STREAM}"), e))?;
    let partitions = info
        .config
        .subject_transform
        .as_ref()
        .and_then(|t| partitions_of(&t.destination))
        .ok_or_else(|| {
            NatsError::new(
                format!("stream {TELEMETRY_STREAM}"),
                "exists without the partition subject transform; delete it or let shocktwin create it",
            )
        })?;
    js.get_or_create_stream(stream::Config {
        name: ESTIMATES_STREAM.into(),
        subjects: vec![
            "shocktwin.estimate.*".into(),
            "shocktwin.health.*".into(),
            "shocktwin.run.*".into(),
        ],
        storage: stream::StorageType::File,
        max_age: Duration::from_secs_f64(cfg.telemetry_max_age_s),
        duplicate_window: DUPLICATE_WINDOW,
        ..Default::default()
    })
    .await
    .map_err(|e| NatsError::new(format!("stream {ESTIMATES_STREAM}"), e))?;
    js.get_or_create_stream(stream::Config {
        name: DEADLETTER_STREAM.into(),
        subjects: vec!["shocktwin.deadletter.>".into()],
        storage: stream::StorageType::File,
        max_age: Duration::from_secs_f64(cfg.telemetry_max_age_s),
        ..Default::default()
    })
    .await
    .map_err(|e| NatsError::new(format!("stream {DEADLETTER_STREAM}"), e))?;
    Ok(partitions)
}

/// The bucket `config.bucket`, created with `config` if missing (an
/// existing bucket's settings win).
async fn bucket(js: &jetstream::Context, config: kv::Config) -> Result<kv::Store, NatsError> {
    if let Ok(s) = js.get_key_value(&config.bucket).await {
        return Ok(s);
    }
    let name = config.bucket.clone();
    js.create_key_value(config)
        .await
        .map_err(|e| NatsError::new(format!("bucket {name}"), e))
}

/// The checkpoint bucket.
pub async fn checkpoint_bucket(js: &jetstream::Context) -> Result<kv::Store, NatsError> {
    let config = kv::Config {
        bucket: CHECKPOINT_BUCKET.into(),
        history: 1,
        storage: stream::StorageType::File,
        max_value_size: 8 << 20,
        ..Default::default()
    };
    bucket(js, config).await
}

/// The unit-baseline bucket (one key per asset, the latest value only).
pub async fn baseline_bucket(js: &jetstream::Context) -> Result<kv::Store, NatsError> {
    let config = kv::Config {
        bucket: BASELINE_BUCKET.into(),
        history: 1,
        storage: stream::StorageType::File,
        ..Default::default()
    };
    bucket(js, config).await
}

/// The bucket of pending services (the latest value per asset).
pub async fn service_bucket(js: &jetstream::Context) -> Result<kv::Store, NatsError> {
    let config = kv::Config {
        bucket: SERVICE_BUCKET.into(),
        history: 1,
        storage: stream::StorageType::File,
        ..Default::default()
    };
    bucket(js, config).await
}

/// The lease bucket (entries expire after [`LEASE_TTL`] without renewal).
pub async fn lease_bucket(js: &jetstream::Context) -> Result<kv::Store, NatsError> {
    let config = kv::Config {
        bucket: LEASE_BUCKET.into(),
        history: 1,
        max_age: LEASE_TTL,
        storage: stream::StorageType::File,
        ..Default::default()
    };
    bucket(js, config).await
}

/// `N` of a `…{{partition(N,1)}}…` transform destination.
fn partitions_of(dest: &str) -> Option<u32> {
    let i = dest.find("partition(")? + "partition(".len();
    let rest = &dest[i..];
    rest[..rest.find(',')?].trim().parse().ok()
}

#[cfg(test)]
mod tests {
    #[test]
    fn partition_count_is_read_from_the_transform() {
        assert_eq!(
            super::partitions_of("shocktwin.telemetry.{{partition(16,1)}}.{{wildcard(1)}}"),
            Some(16)
        );
        assert_eq!(super::partitions_of("x.{{wildcard(1)}}"), None);
    }
}
