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

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use async_nats::jetstream::{self, kv, stream};
use serde::{Deserialize, Serialize};

use crate::server::source::{SourceContext, Trouble};

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

impl NatsConfig {
    /// Checks the settings ([`Self::check_settings`]), then the files
    /// ([`Self::check_files`]). Returns the key (`nats.ca_file`, …) and why.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        self.check_settings()?;
        self.check_files()
    }

    /// `partitions` and `telemetry_max_age_s` within what the group can
    /// use: before, 200 partitions made a stream no worker could join, and a
    /// negative age stopped the part with a panic.
    pub fn check_settings(&self) -> Result<(), (&'static str, String)> {
        if let Some(url) = &self.url {
            server_addrs(url).map_err(|why| ("nats.url", why))?;
        }
        if !(1..=worker::MAX_PARTITIONS).contains(&self.partitions) {
            return Err((
                "nats.partitions",
                format!(
                    "{}: must be 1 to {} (a worker holds at most that many)",
                    self.partitions,
                    worker::MAX_PARTITIONS
                ),
            ));
        }
        let age = self.telemetry_max_age_s;
        let least = DUPLICATE_WINDOW.as_secs_f64();
        if !(age.is_finite() && age >= least && age <= 100.0 * 365.0 * 86_400.0) {
            // the server refuses a stream kept for less than its de-duplication
            // window, and the set-up would be tried again for ever (a review)
            return Err((
                "nats.telemetry_max_age_s",
                format!(
                    "{age}: must be {least} s (the estimate stream's de-duplication window) to 100 years"
                ),
            ));
        }
        Ok(())
    }

    /// Reads the files the connection will need, so that a wrong path, a
    /// file that is not PEM or an empty token is said at once, naming the
    /// setting and the file (a helper's trial: a missing `ca_file` gave 39
    /// lines of "TLS error" and "no connection after 10 s", an empty
    /// `token_file` "authorization violation" over and over). Returns the
    /// key (`ca_file`, …) and why.
    pub fn check_files(&self) -> Result<(), (&'static str, String)> {
        use crate::server::security::{pem_certificates, pem_problem};
        use rustls::pki_types::pem::PemObject as _;
        use rustls::pki_types::PrivateKeyDer;

        let certs = |key: &'static str, path: &Path| -> Result<(), (&'static str, String)> {
            pem_certificates(path)
                .map(drop)
                .map_err(|why| (key, format!("{}: {why}", path.display())))
        };
        if let Some(ca) = &self.ca_file {
            certs("nats.ca_file", ca)?;
        }
        match (&self.cert_file, &self.key_file) {
            (Some(cert), Some(key)) => {
                certs("nats.cert_file", cert)?;
                PrivateKeyDer::from_pem_file(key).map_err(|e| {
                    (
                        "nats.key_file",
                        format!("{}: {}", key.display(), pem_problem(&e)),
                    )
                })?;
            }
            (Some(_), None) => {
                return Err(("nats.key_file", "missing: `cert_file` needs its key".into()))
            }
            (None, Some(_)) => {
                return Err((
                    "nats.cert_file",
                    "missing: `key_file` needs its certificate".into(),
                ))
            }
            (None, None) => {}
        }
        if let Some(f) = &self.token_file {
            read_token(f).map_err(|why| ("nats.token_file", why))?;
        }
        Ok(())
    }
}

/// The token on the first line of `path`; else why not, naming the file.
fn read_token(path: &Path) -> Result<String, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let token = text.lines().next().unwrap_or_default().trim();
    if token.is_empty() {
        return Err(format!("{}: no token on its first line", path.display()));
    }
    Ok(token.to_owned())
}

/// `url` (comma-separated server URLs) with any `user:password@` or
/// `token@` written as `***@`, for messages and logs: a token in a URL is a
/// secret (a helper's trial: the error printed it back).
#[must_use]
pub fn without_credentials(url: &str) -> String {
    url.split(',')
        .map(|u| {
            // async-nats takes a URL without a scheme too (`token@host:4222`)
            let start = u.find("://").map_or(0, |s| s + 3);
            match u[start..].rfind('@') {
                Some(at) if at > 0 => format!("{}***{}", &u[..start], &u[start + at..]),
                _ => u.to_owned(),
            }
        })
        .collect::<Vec<_>>()
        .join(",")
}

/// The server addresses of `url` (comma separated), or why one is not one,
/// its credentials hidden. Before, `nat://…` (a typo) started the daemon,
/// whose NATS parts then stopped with "invalid scheme" behind `/healthz` 200
/// (a helper's trial): the client is made with `retry_on_initial_connect`,
/// which parses the URL only once it runs.
pub fn server_addrs(url: &str) -> Result<Vec<async_nats::ServerAddr>, String> {
    url.split(',')
        .map(|u| {
            u.trim().parse::<async_nats::ServerAddr>().map_err(|e| {
                format!(
                    "{}: not a NATS server URL ({e}; nats://host:4222 or tls://host:4222)",
                    without_credentials(u.trim())
                )
            })
        })
        .collect()
}

/// The credentials written in the first server URL that has any: a
/// `user:password@` pair, or a `token@` alone (the NATS clients' convention).
/// async-nats reads neither from the URL (a helper's trial: `nats://token@host`
/// was refused with "authorization violation", where nats-py connects).
fn url_credentials(url: &str) -> Option<(String, Option<String>)> {
    server_addrs(url).ok()?.into_iter().find_map(|a| {
        a.username()
            .map(|u| (u.to_owned(), a.password().map(str::to_owned)))
    })
}

/// Connects with the configured TLS and credentials, waiting at most 10 s
/// for the first connection (`shocktwin publish`: a wrong URL is an error,
/// not a hang).
pub async fn connect(cfg: &NatsConfig, name: &str) -> Result<async_nats::Client, NatsError> {
    let (client, what, last) = client_for(cfg, name, Trouble::default()).await?;
    let limit = Duration::from_secs(10);
    let never = tokio_util::sync::CancellationToken::new();
    match wait_connected(&client, &never, Some(limit), |_| {}).await {
        Some(true) => Ok(client),
        _ => Err(NatsError::new(
            &what,
            format!("no connection after 10 s{}", last.said()),
        )),
    }
}

/// Connects as [`connect`], but waits for the server as long as the daemon
/// runs: a gateway's daemon may start before its NATS server, or the server
/// be down a while (a helper's trial: after 10 s the daemon's NATS parts
/// stopped for good while `/readyz` said ready). Every
/// [`PATIENT_WARN_EVERY`] it warns that it is still trying, and `/readyz`
/// says why beside the part's name. `None` once the daemon stops first
/// (nothing to report); `Err` only for a client that cannot be made at all.
pub async fn connect_patiently(
    cfg: &NatsConfig,
    name: &str,
    ctx: &SourceContext,
) -> Result<Option<async_nats::Client>, NatsError> {
    let (client, what, last) = client_for(cfg, name, ctx.started.trouble()).await?;
    let still = |waited: Duration| {
        let why = format!(
            "{what}: no connection after {} s{}",
            waited.as_secs(),
            last.said()
        );
        tracing::warn!("{name}: NATS {why}; still trying (`/readyz` says not ready meanwhile)");
        ctx.started.note(Some(why));
    };
    let began = tokio::time::Instant::now();
    let connected = wait_connected(&client, &ctx.cancel, None, still).await;
    ctx.started.note(None);
    if connected.is_some() && began.elapsed() >= PATIENT_WARN_EVERY {
        tracing::info!(
            "{name}: NATS {what}: connected after {} s",
            began.elapsed().as_secs()
        );
    }
    Ok(connected.and(Some(client)))
}

/// Waits until `client` is connected (`Some(true)`); `None` once `cancel`
/// is cancelled first, `Some(false)` after `limit`. Calls `still` with the
/// time waited every [`PATIENT_WARN_EVERY`].
async fn wait_connected(
    client: &async_nats::Client,
    cancel: &tokio_util::sync::CancellationToken,
    limit: Option<Duration>,
    mut still: impl FnMut(Duration),
) -> Option<bool> {
    let started = tokio::time::Instant::now();
    let mut say_at = started + PATIENT_WARN_EVERY;
    while client.connection_state() != async_nats::connection::State::Connected {
        if cancel.is_cancelled() {
            return None;
        }
        let now = tokio::time::Instant::now();
        if limit.is_some_and(|limit| now - started > limit) {
            return Some(false);
        }
        if now >= say_at {
            still(now - started);
            say_at += PATIENT_WARN_EVERY;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Some(true)
}

/// How often [`connect_patiently`] says that it is still trying.
pub const PATIENT_WARN_EVERY: Duration = Duration::from_secs(10);

/// How long a daemon's NATS part waits before it tries a failed set-up
/// again ([`SetUpRetries::after`]).
pub const SET_UP_RETRY_EVERY: Duration = Duration::from_secs(5);

/// Why a NATS part's set-up (streams, buckets, consumer) failed: tried again
/// while the daemon runs (the server may gain `JetStream`, a stream be
/// mended) or, for what only a new configuration mends, the part stops.
#[derive(Debug)]
pub enum SetUpError {
    /// Tried again after [`SET_UP_RETRY_EVERY`].
    Retry(NatsError),
    /// The part stops (`/readyz` then says "degraded").
    Stop(NatsError),
}

impl From<NatsError> for SetUpError {
    fn from(e: NatsError) -> Self {
        Self::Retry(e)
    }
}

/// How often a set-up that keeps failing the same way is said again.
pub const SET_UP_WARN_EVERY: Duration = Duration::from_secs(60);

/// A NATS part's failed set-ups: what it said last, and when.
#[derive(Debug, Default)]
pub struct SetUpRetries {
    said: Option<(String, tokio::time::Instant)>,
    tries: u32,
}

impl SetUpRetries {
    /// After a failed set-up of part `name`: for [`SetUpError::Retry`],
    /// warns (when the reason is new, else every [`SET_UP_WARN_EVERY`]),
    /// says why in `/readyz` and waits [`SET_UP_RETRY_EVERY`] (`Ok(true)`:
    /// try again; `Ok(false)`: the daemon stops); for [`SetUpError::Stop`],
    /// the error. Before, any set-up error stopped the part for good (a
    /// gateway whose NATS server came up without `JetStream` needed the
    /// daemon restarted once the server was mended).
    pub async fn after(
        &mut self,
        name: &str,
        error: SetUpError,
        ctx: &SourceContext,
    ) -> Result<bool, NatsError> {
        let e = match error {
            SetUpError::Retry(e) => e.to_string(),
            SetUpError::Stop(e) => return Err(e),
        };
        self.tries += 1;
        let every = SET_UP_RETRY_EVERY.as_secs();
        let now = tokio::time::Instant::now();
        let due = self
            .said
            .as_ref()
            .is_none_or(|(said, at)| *said != e || now - *at >= SET_UP_WARN_EVERY);
        if due {
            tracing::warn!(
                "{name}: set-up failed (try {}): {e}; trying again every {every} s (`/readyz` says not ready meanwhile)",
                self.tries
            );
            self.said = Some((e.clone(), now));
        }
        ctx.started.note(Some(format!(
            "set-up failed: {e}; trying again every {every} s"
        )));
        tokio::select! {
            () = ctx.cancel.cancelled() => Ok(false),
            () = tokio::time::sleep(SET_UP_RETRY_EVERY) => Ok(true),
        }
    }
}

/// What the client met, for the log and for the messages that say it could
/// not connect (a helper's trial: "no connection after 10 s", the cause
/// only in dozens of lines of the client's own log). The client logs every
/// event at info; the daemon's default filter keeps only its warnings
/// (`bin/shocktwin.rs`), and this says the events that matter once, naming
/// the part: a lost connection, a reconnection, a server's error while
/// connected.
#[derive(Debug, Clone, Default)]
struct LastError(Arc<std::sync::Mutex<Seen>>);

#[derive(Debug, Default)]
struct Seen {
    /// Where a lost connection is said to `/readyz`.
    trouble: Trouble,
    /// The last client or server error.
    error: Option<String>,
    /// Connected now.
    connected: bool,
    /// Connected before: a connection now is a reconnection.
    was_connected: bool,
    /// When a failing reconnection was last said in the log.
    said_at: Option<std::time::Instant>,
}

impl LastError {
    fn said(&self) -> String {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .error
            .as_ref()
            .map_or_else(String::new, |e| format!(" (last: {e})"))
    }

    /// Keeps an error event's text; logs what part `name` should say.
    fn take(&self, event: &async_nats::Event, name: &str) {
        use async_nats::Event;
        let mut seen = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        match event {
            Event::Connected => {
                if seen.was_connected {
                    tracing::info!("{name}: NATS reconnected");
                }
                (seen.connected, seen.was_connected) = (true, true);
                seen.trouble.set(None);
            }
            Event::Disconnected => {
                seen.connected = false;
                seen.said_at = Some(std::time::Instant::now());
                if seen.trouble.is_said() {
                    tracing::warn!(
                        "{name}: NATS connection lost; reconnecting (`/readyz` says degraded if it lasts {} s)",
                        crate::server::source::TROUBLE_GRACE.as_secs()
                    );
                } else {
                    // a CLI (`shocktwin publish`) has no `/readyz`
                    tracing::warn!("{name}: NATS connection lost; reconnecting");
                }
                seen.trouble
                    .set(Some("NATS connection lost; reconnecting".into()));
            }
            Event::ClientError(_) | Event::ServerError(_) => {
                seen.error = Some(event.to_string());
                if seen.connected {
                    tracing::warn!("{name}: NATS {event}");
                } else if seen.was_connected {
                    // reconnecting: why it fails, in `/readyz` and, every
                    // PATIENT_WARN_EVERY, in the log (a review: one "lost"
                    // line, then silence)
                    let now = std::time::Instant::now();
                    if seen.said_at.is_none_or(|at| now - at >= PATIENT_WARN_EVERY) {
                        tracing::warn!("{name}: NATS still reconnecting (last: {event})");
                        seen.said_at = Some(now);
                    }
                    seen.trouble.set(Some(format!(
                        "NATS connection lost; reconnecting (last: {event})"
                    )));
                } else {
                    // the first connection's waits say the last one
                    tracing::debug!("{name}: NATS {event}");
                }
            }
            Event::Draining | Event::Closed => tracing::debug!("{name}: NATS {event}"),
            Event::LameDuckMode | Event::SlowConsumer(_) => tracing::warn!("{name}: NATS {event}"),
        }
    }
}

/// The client (it connects, and reconnects, in the background), what to
/// call the connection in messages (its URL without credentials) and its
/// last error.
async fn client_for(
    cfg: &NatsConfig,
    name: &str,
    trouble: Trouble,
) -> Result<(async_nats::Client, String, LastError), NatsError> {
    let url = cfg
        .url
        .clone()
        .ok_or_else(|| NatsError::new("connect", "no URL configured"))?;
    let what = format!("connect {}", without_credentials(&url));
    let last = LastError(Arc::new(std::sync::Mutex::new(Seen {
        trouble,
        ..Seen::default()
    })));
    let (seen, part) = (last.clone(), name.to_owned());
    let mut opts = async_nats::ConnectOptions::new()
        .name(name)
        .retry_on_initial_connect()
        .connection_timeout(Duration::from_secs(5))
        .event_callback(move |event| {
            seen.take(&event, &part);
            async {}
        });
    if let Some(ca) = &cfg.ca_file {
        opts = opts.add_root_certificates(ca.clone()).require_tls(true);
    }
    if let (Some(cert), Some(key)) = (&cfg.cert_file, &cfg.key_file) {
        opts = opts.add_client_certificate(cert.clone(), key.clone());
    }
    if let Some(f) = &cfg.token_file {
        let token = read_token(f).map_err(|why| NatsError::new("token file", why))?;
        opts = opts.token(token);
    } else {
        match url_credentials(&url) {
            Some((user, Some(password))) => opts = opts.user_and_password(user, password),
            Some((token, None)) => opts = opts.token(token),
            None => {}
        }
    }
    // `retry_on_initial_connect` makes connect return at once; the callers
    // wait for the first connection. The servers are given one by one (the
    // whole string is read as one URL) and without their credentials, which
    // went into `opts` (the client logs its addresses at debug: the review)
    let servers: Vec<String> = url
        .split(',')
        .map(|u| {
            let u = u.trim();
            let start = u.find("://").map_or(0, |s| s + 3);
            match u[start..].rfind('@') {
                Some(at) => format!("{}{}", &u[..start], &u[start + at + 1..]),
                None => u.to_owned(),
            }
        })
        .collect();
    let client = opts
        .connect(servers)
        .await
        .map_err(|e| NatsError::new(&what, e))?;
    Ok((client, what, last))
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

    #[test]
    fn credentials_in_a_url_are_not_repeated() {
        assert_eq!(
            super::without_credentials("tls://s3cret@h:4222,nats://u:p@g:1,nats://plain:2"),
            "tls://***@h:4222,nats://***@g:1,nats://plain:2"
        );
        assert_eq!(
            super::without_credentials("s3cret@h:4222,plain:2"),
            "***@h:4222,plain:2"
        );
    }

    /// A URL that is not a NATS server's is refused at start, its
    /// credentials hidden; those written in it are used.
    #[test]
    fn a_mistyped_url_is_refused_and_its_credentials_are_used() {
        assert_eq!(
            super::server_addrs("nats://a:1, tls://b:2,c:3")
                .unwrap()
                .len(),
            3
        );
        let why = super::server_addrs("nats://a:1,nat://s3cret@b:2").unwrap_err();
        assert!(
            why.starts_with("nat://***@b:2: not a NATS server URL"),
            "{why}"
        );
        assert!(!why.contains("s3cret"), "{why}");
        let cfg = super::NatsConfig {
            url: Some("nat://127.0.0.1:4222".into()),
            ..super::NatsConfig::default()
        };
        assert_eq!(cfg.check_settings().unwrap_err().0, "nats.url");
        assert_eq!(
            super::url_credentials("nats://plain:1,nats://s3cret@h:2"),
            Some(("s3cret".into(), None))
        );
        assert_eq!(
            super::url_credentials("tls://u:p@h:2"),
            Some(("u".into(), Some("p".into())))
        );
        assert_eq!(super::url_credentials("nats://h:2"), None);
    }

    /// A wrong file is said at once, naming the setting and the file.
    #[test]
    fn the_connection_files_are_read_before_connecting() {
        let dir = tempfile::tempdir().unwrap();
        let file = |name: &str, text: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            p
        };
        let cfg = |f: &dyn Fn(&mut super::NatsConfig)| {
            let mut c = super::NatsConfig::default();
            f(&mut c);
            c.check_files()
        };
        assert_eq!(cfg(&|_| {}), Ok(()));
        // the settings, before the files
        let settings = |f: &dyn Fn(&mut super::NatsConfig)| {
            let mut c = super::NatsConfig::default();
            f(&mut c);
            c.check().map_err(|(key, _)| key)
        };
        assert_eq!(settings(&|_| {}), Ok(()));
        assert_eq!(settings(&|c| c.partitions = 128), Ok(()));
        assert_eq!(settings(&|c| c.partitions = 129), Err("nats.partitions"));
        assert_eq!(settings(&|c| c.partitions = 0), Err("nats.partitions"));
        assert_eq!(settings(&|c| c.telemetry_max_age_s = 300.0), Ok(()));
        for age in [0.0, -1.0, 60.0, f64::NAN, f64::INFINITY] {
            let refused = settings(&|c| c.telemetry_max_age_s = age);
            assert_eq!(refused, Err("nats.telemetry_max_age_s"), "{age}");
        }
        // refused for `key`, the reason saying each of `says`
        let refused = |f: &dyn Fn(&mut super::NatsConfig), key: &str, says: &[&str]| {
            let (k, why) = cfg(f).unwrap_err();
            assert_eq!(k, key, "{why}");
            assert!(says.iter().all(|w| why.contains(w)), "{why}");
        };
        let missing = dir.path().join("caX.pem");
        refused(
            &|c| c.ca_file = Some(missing.clone()),
            "nats.ca_file",
            &["caX.pem", "cannot read"],
        );
        let junk = file("junk.pem", "not a certificate\n");
        refused(
            &|c| c.ca_file = Some(junk.clone()),
            "nats.ca_file",
            &["junk.pem"],
        );
        // a certificate without its key
        refused(&|c| c.cert_file = Some(junk.clone()), "nats.key_file", &[]);
        let empty = file("empty.token", "\n");
        refused(
            &|c| c.token_file = Some(empty.clone()),
            "nats.token_file",
            &["empty.token", "no token"],
        );
        let token = file("ok.token", "s3cret\n");
        assert_eq!(cfg(&|c| c.token_file = Some(token.clone())), Ok(()));
    }
}
