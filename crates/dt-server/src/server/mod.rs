//! The fleet-gateway daemon (`shocktwin serve`), shaped like tokio's
//! mini-redis: the binary parses arguments, sets up tracing, binds the
//! listeners and calls [`run`] with a shutdown future.
//!
//! ```text
//!  sources ──────────────► Ingest ──► AssetTwin per run ──► bounded queue ──► sink thread
//!  (TcpSource: MCAP per    (LogDecoder,                     (backpressure)     ├─ LiveSink ─► HTTP API, SSE
//!   connection; InboxSource) metadata → run)                                    ├─ McapRecorder (rotating)
//!                                                                                 └─ StoreSink ─► writer thread ─► SQLite
//!                                                                                    (1 s history, runs, health changes, trends)
//! ```
//!
//! Shutdown: the future resolves → `/readyz` turns 503, the sources'
//! [`CancellationToken`] is cancelled (stop accepting; each run in progress
//! ends with its estimates so far), a [`TaskTracker`] says when every
//! connection task is done, then the sink queue closes and every sink flushes
//! (finishes its MCAP files), then the HTTP server stops. Every queue is
//! bounded; a semaphore caps connections; record sizes are limited.

pub mod baselines;
pub mod config;
pub mod estimator;
pub mod http;
pub mod http_limits;
pub mod inbox;
pub mod ingest;
pub mod lock;
pub mod metrics;
pub mod record;
pub mod security;
pub mod sink;
pub mod source;
pub mod state;
pub mod store;
pub mod tcp;
pub mod twin;

use std::future::{Future, IntoFuture};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

pub use config::{AssetConfig, Config, ConfigOverrides};
pub use estimator::EstimatorFactory;
pub use twin::{AssetTwin, TickCounterFactory, TickCounterTwin, TwinCounters, TwinFactory};

use self::baselines::Baselines;
use self::http::AppState;
use self::ingest::Ingest;
use self::metrics::Metrics;
use self::record::McapRecorder;
use self::sink::Sink;
use self::source::{Source, SourceContext, Started, Starting};
use self::state::{LiveSink, LiveState};
use self::store::{FleetStore, SqliteStore, StoreSink, Trends};

/// The daemon's one error type (configuration and start-up; a bad input
/// stream is not an error of the daemon, it closes that stream).
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The configuration file cannot be parsed.
    #[error("{}: {reason}", file.display())]
    Config {
        /// The file.
        file: PathBuf,
        /// toml's message (names key and line).
        reason: String,
    },
    /// An environment variable has an invalid value.
    #[error("environment variable {var}={value:?}: {reason}")]
    Env {
        /// The variable.
        var: String,
        /// Its value.
        value: String,
        /// Why it is invalid.
        reason: String,
    },
    /// A configuration value is invalid.
    #[error("configuration `{key}`: {reason}")]
    Invalid {
        /// The key (`limits.queue_depth`, `assets.<id>`, ...).
        key: String,
        /// Why.
        reason: String,
    },
    /// A listener cannot be bound.
    #[error("cannot listen on {addr}: {error}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The OS error (in the message, not a `source()`: `{:#}` printed
        /// it twice).
        error: std::io::Error,
    },
    /// A file or directory operation failed.
    #[error("{}: {error}", path.display())]
    Io {
        /// The path.
        path: PathBuf,
        /// The OS error (in the message, not a `source()`).
        error: std::io::Error,
    },
    /// The model bundle cannot be loaded.
    #[error("model bundle {}: {reason}", path.display())]
    Model {
        /// The bundle directory.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// A sink cannot be set up.
    #[error(transparent)]
    Sink(#[from] sink::SinkError),
    /// The fleet store cannot be opened.
    #[error(transparent)]
    Store(#[from] store::StoreError),
    /// Another process holds a place this daemon would write (its lock).
    #[error("another shocktwin serve uses this {what} ({}{}): stop it, or give this daemon a {what} of its own", path.display(), if holder.is_empty() { String::new() } else { format!("; its lock says {holder}") })]
    Locked {
        /// `fleet store`, `inbox` or `recording directory`.
        what: &'static str,
        /// The lock file.
        path: PathBuf,
        /// What the holder wrote in it (`pid N`), if readable.
        holder: String,
    },
    /// A listener would be exposed without TLS and authentication.
    #[error("refusing to start: {0}. Configure TLS and authentication (see docs/daemon.md, \"Exposing the daemon\"), or give --insecure to serve anyway")]
    Insecure(String),
}

/// The daemon's two listeners, bound by the caller (tests bind `127.0.0.1:0`).
#[derive(Debug)]
pub struct Listeners {
    /// MCAP ingest.
    pub ingest: TcpListener,
    /// HTTP API.
    pub http: TcpListener,
}

impl Listeners {
    /// Binds the configured addresses.
    pub async fn bind(config: &Config) -> Result<Self, ServeError> {
        let bind = |addr: SocketAddr| async move {
            TcpListener::bind(addr)
                .await
                .map_err(|source| ServeError::Bind {
                    addr,
                    error: source,
                })
        };
        Ok(Self {
            ingest: bind(config.server.listen).await?,
            http: bind(config.server.http).await?,
        })
    }
}

/// The TCP listener and, if configured, the inbox and the NATS worker group
/// (a worker and the fleet view).
fn sources(
    config: &Config,
    ingest: TcpListener,
    tls: Option<&security::TlsConfigs>,
    twins: &dyn TwinFactory,
) -> Result<Vec<Box<dyn Source>>, ServeError> {
    let mut sources: Vec<Box<dyn Source>> = vec![Box::new(
        tcp::TcpSource::new(ingest, tcp::ConnectionLimits::from_config(&config.limits))
            .with_tls(tls.map(|t| Arc::clone(&t.ingest)))
            .with_rate(tcp::peer_rate(
                config.limits.max_ingest_bytes_per_s_per_peer,
            )),
    )];
    if let Some(dir) = &config.server.inbox {
        sources.push(Box::new(inbox::InboxSource::new(
            dir,
            Duration::from_secs_f64(config.server.inbox_rescan_s),
            Duration::from_secs_f64(config.server.inbox_settle_s),
        )?));
    }
    if config.nats.url.is_some() {
        if config.nats.worker {
            let factory = twins.as_estimator().ok_or_else(|| ServeError::Invalid {
                key: "nats.worker".into(),
                reason: "a NATS worker needs a model bundle (`--model`); set `worker = false` for a read-only fleet view".into(),
            })?;
            sources.push(Box::new(crate::nats::worker::NatsWorker::new(
                config.nats.clone(),
                factory.clone(),
            )));
        }
        sources.push(Box::new(crate::nats::fleet::NatsFleetView::new(
            config.nats.clone(),
        )));
    }
    Ok(sources)
}

/// Tokens and TLS configurations, after the exposure rule (see [`security`]).
fn secure(
    config: &Config,
    listeners: &Listeners,
) -> Result<(Arc<security::Tokens>, Option<security::TlsConfigs>), ServeError> {
    let tokens = Arc::new(security::Tokens::load(config)?);
    let addr = |l: &TcpListener| {
        l.local_addr().map_err(|source| ServeError::Io {
            path: PathBuf::from("<listener>"),
            error: source,
        })
    };
    security::check_exposure(
        config,
        addr(&listeners.ingest)?,
        addr(&listeners.http)?,
        &tokens,
        config.insecure,
    )?;
    Ok((tokens, security::server_configs(config)?))
}

/// HTTPS through axum-server's rustls acceptor (handshakes run per
/// connection, not in the accept loop); stops gracefully with `stop`.
/// Serves the HTTP API: plain, or HTTPS with its bounds ([`spawn_https`]).
fn spawn_http(
    listener: TcpListener,
    app: axum::Router,
    tls: Option<Arc<rustls::ServerConfig>>,
    limits: &config::Limits,
    metrics: Arc<Metrics>,
    stop: CancellationToken,
) -> Result<tokio::task::JoinHandle<std::io::Result<()>>, ServeError> {
    match tls {
        None => Ok(tokio::spawn(
            axum::serve(
                listener,
                app.into_make_service_with_connect_info::<std::net::SocketAddr>(),
            )
            .with_graceful_shutdown(stop.cancelled_owned())
            .into_future(),
        )),
        Some(tls) => spawn_https(listener, app, tls, limits, metrics, stop),
    }
}

fn spawn_https(
    listener: TcpListener,
    app: axum::Router,
    tls: Arc<rustls::ServerConfig>,
    limits: &config::Limits,
    metrics: Arc<Metrics>,
    stop: CancellationToken,
) -> Result<tokio::task::JoinHandle<std::io::Result<()>>, ServeError> {
    let io = |source| ServeError::Io {
        path: PathBuf::from("<https listener>"),
        error: source,
    };
    let listener = listener.into_std().map_err(io)?;
    let handle = axum_server::Handle::new();
    let mut server = axum_server::from_tcp_rustls(
        listener,
        axum_server::tls_rustls::RustlsConfig::from_config(tls),
    )
    .map_err(io)?
    .map(|tls| {
        http_limits::Bounded::new(
            tls,
            limits.max_http_connections,
            Duration::from_secs_f64(limits.first_data_timeout_s),
            Arc::new(move |e: &std::io::Error| {
                metrics.error("https_handshake");
                tracing::warn!("HTTPS: TLS handshake failed: {e}");
            }),
        )
    })
    .handle(handle.clone());
    http_limits::bound_requests(server.http_builder(), limits);
    tokio::spawn(async move {
        stop.cancelled().await;
        handle.graceful_shutdown(Some(Duration::from_secs(5)));
    });
    Ok(tokio::spawn(server.serve(
        app.into_make_service_with_connect_info::<std::net::SocketAddr>(),
    )))
}

/// The fleet store, if any, and the unit baselines it keeps.
type OpenedStore = (Option<Arc<dyn FleetStore>>, Arc<Baselines>);

/// Opens the fleet store, if configured: restores the live view and the
/// unit baselines from it and adds its sink.
fn open_store(
    config: &Arc<Config>,
    live: &LiveState,
    trends: &Arc<Trends>,
    metrics: &Arc<Metrics>,
    sinks: &mut Vec<Box<dyn Sink>>,
) -> Result<OpenedStore, ServeError> {
    let Some(path) = &config.store.path else {
        return Ok((None, Arc::default()));
    };
    let store: Arc<dyn FleetStore> = Arc::new(SqliteStore::open(path)?);
    let baselines = Arc::new(Baselines::load(store.as_ref())?);
    baselines.restart_trends(trends);
    let states = store.asset_states()?;
    tracing::info!(store = %path.display(), assets = states.len(), "fleet store opened");
    live.restore(&states, config);
    let sink = StoreSink::start(
        Arc::clone(&store),
        Arc::clone(trends),
        Arc::clone(config),
        Arc::clone(metrics),
    )
    .map_err(|source| ServeError::Io {
        path: PathBuf::from("<store writer thread>"),
        error: source,
    })?;
    sinks.push(Box::new(sink));
    Ok((Some(store), baselines))
}

/// In a NATS group: the watcher of the group's baseline bucket (a source)
/// and the bucket's handle for the API.
fn group_baselines(
    config: &Config,
    store: Option<&Arc<dyn FleetStore>>,
    trends: &Arc<Trends>,
    sources: &mut Vec<Box<dyn Source>>,
) -> Option<crate::nats::baselines::BaselineBucket> {
    config.nats.url.as_ref()?;
    let bucket = crate::nats::baselines::BaselineBucket::default();
    sources.push(Box::new(crate::nats::baselines::NatsBaselines::new(
        config.nats.clone(),
        bucket.clone(),
        store.cloned(),
        Arc::clone(trends),
    )));
    Some(bucket)
}

/// The sink thread (a dedicated thread: the sinks do blocking file I/O);
/// the receiver resolves when it has drained the queue and flushed.
fn spawn_sinks(
    sink_rx: mpsc::Receiver<sink::SinkMsg>,
    sinks: Vec<Box<dyn Sink>>,
    metrics: Arc<Metrics>,
) -> Result<oneshot::Receiver<()>, ServeError> {
    let (done_tx, done) = oneshot::channel::<()>();
    std::thread::Builder::new()
        .name("shocktwin-sinks".into())
        .spawn(move || {
            sink::dispatch(sink_rx, sinks, &metrics);
            let _ = done_tx.send(());
        })
        .map_err(|source| ServeError::Io {
            path: PathBuf::from("<sink thread>"),
            error: source,
        })?;
    Ok(done)
}

/// Spawns every source on `tracker`; the sources that say when they take
/// work and have not yet are in the returned [`Starting`] (for `/readyz`).
fn spawn_sources(
    sources: Vec<Box<dyn Source>>,
    ingest: &Ingest,
    cancel: &CancellationToken,
    tracker: &TaskTracker,
) -> Starting {
    let starting = Starting::default();
    for source in sources {
        let name = source.name();
        tracing::info!(source = %name, "source started");
        let started = if source.says_started() {
            starting.enter(&name)
        } else {
            Started::default()
        };
        let ctx = SourceContext {
            ingest: ingest.clone(),
            cancel: cancel.clone(),
            tracker: tracker.clone(),
            started,
        };
        // The context goes with the source: when it ends (or panics), a
        // start it did not signal is signalled.
        let (cancel, starting) = (cancel.clone(), starting.clone());
        // held until the stop is recorded: with the context's gone first,
        // `/readyz` could answer ready in between (a review)
        let held = ctx.started.clone();
        tracker.spawn(async move {
            // a panic is a stop too (a review: it left `/readyz` ready)
            let ran = std::panic::AssertUnwindSafe(source.run(ctx));
            let why = match futures_util::FutureExt::catch_unwind(ran).await {
                Err(panic) => {
                    let what = panic
                        .downcast_ref::<String>()
                        .map(String::as_str)
                        .or_else(|| panic.downcast_ref::<&str>().copied())
                        .unwrap_or("a panic");
                    tracing::error!(source = %name, "source panicked: {what}");
                    Some(format!("panicked: {what}"))
                }
                Ok(Err(e)) => {
                    tracing::error!(source = %name, "source stopped: {e}");
                    Some(e.to_string())
                }
                // every source runs until the daemon stops; one that ends
                // before takes no more work either (a review: the fleet
                // view's stream ending left `/readyz` ready)
                Ok(Ok(())) if !cancel.is_cancelled() => {
                    tracing::error!(source = %name, "source ended while the daemon runs");
                    Some("ended".to_owned())
                }
                Ok(Ok(())) => None,
            };
            if let Some(why) = why.filter(|_| !cancel.is_cancelled()) {
                starting.stopped(&name, &why);
            }
            drop(held);
        });
    }
    starting
}

/// Runs the daemon until `shutdown` resolves, then drains and flushes.
/// `twins` makes the estimator of each run.
pub async fn run(
    config: Config,
    listeners: Listeners,
    twins: Arc<dyn TwinFactory>,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServeError> {
    config.validate()?;
    let (tokens, tls) = secure(&config, &listeners)?;
    // held until `run` returns: one daemon per store, inbox and recording directory
    let _locks = lock::hold(&config)?;
    // said once the daemon may serve (a refused exposure logged `listening` first)
    let addr = |l: &TcpListener| {
        l.local_addr()
            .map_or_else(|e| e.to_string(), |a| a.to_string())
    };
    // what protects them, said where an operator looks first (a helper's
    // trial: nothing in the log told a TLS + token daemon from a plain one)
    let on = |b: bool| if b { "on" } else { "off" };
    tracing::info!(
        listen = %addr(&listeners.ingest),
        http = %addr(&listeners.http),
        tls = %on(tls.is_some()),
        client_certificates = %on(config.tls.client_ca.is_some() && tls.is_some()),
        tokens = %on(tokens.enabled()),
        "listening"
    );
    let config = Arc::new(config);
    let limits = &config.limits;
    let metrics = Arc::new(Metrics::new());
    let live = Arc::new(LiveState::new(limits.history_len, limits.queue_depth));

    let trends = Arc::new(Trends::default());
    let mut sinks: Vec<Box<dyn Sink>> = vec![Box::new(LiveSink::new(Arc::clone(&live)))];
    if let Some(dir) = &config.server.record_dir {
        sinks.push(Box::new(McapRecorder::new(dir, config.record.clone())?));
    }
    let (store, baselines) = open_store(&config, &live, &trends, &metrics, &mut sinks)?;
    let mut sources = sources(&config, listeners.ingest, tls.as_ref(), twins.as_ref())?;
    let group = group_baselines(&config, store.as_ref(), &trends, &mut sources);

    let (sink_tx, sink_rx) = mpsc::channel(limits.queue_depth);
    let sinks_done = spawn_sinks(sink_rx, sinks, Arc::clone(&metrics))?;
    let ingest = Ingest::new(
        Arc::clone(&config),
        Arc::clone(&twins),
        sink_tx,
        Arc::clone(&metrics),
        Arc::clone(&baselines),
        store.clone(),
    );

    let cancel = CancellationToken::new();
    let tracker = TaskTracker::new();
    let starting = spawn_sources(sources, &ingest, &cancel, &tracker);

    let ready = Arc::new(AtomicBool::new(false));
    let http_stop = CancellationToken::new();
    let app_uploads = http::Uploads::new(ingest.clone(), cancel.clone());
    let https_metrics = Arc::clone(&metrics);
    let app = http::router(AppState {
        live,
        store,
        trends,
        config: Arc::clone(&config),
        metrics,
        ready: Arc::clone(&ready),
        starting,
        stop: http_stop.clone(),
        tokens,
        uploads: app_uploads.clone(),
        baselines,
        model: twins.as_estimator().cloned(),
        group,
    });
    let uploads = app_uploads;
    let http_addr = listeners
        .http
        .local_addr()
        .map_or_else(|e| e.to_string(), |a| a.to_string());
    // Ready before the API is served, so that its first `/readyz` says so.
    ready.store(true, Ordering::Relaxed);
    let http_task = spawn_http(
        listeners.http,
        app,
        tls.map(|t| t.http),
        &config.limits,
        https_metrics,
        http_stop.clone(),
    )?;
    tracing::info!(http = %http_addr, twin = %twins.describe(), "serving");

    shutdown.await;
    tracing::info!("shutting down: ending runs in progress");
    ready.store(false, Ordering::Relaxed);
    cancel.cancel();
    tracker.close();
    tracker.wait().await;
    // The last sender goes: the sink thread drains the queue and flushes.
    uploads.close();
    drop(ingest);
    if sinks_done.await.is_err() {
        tracing::error!("the sink thread panicked");
    }
    http_stop.cancel();
    match http_task.await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => tracing::error!("HTTP server failed: {e}"),
        Err(e) => tracing::error!("HTTP task failed: {e}"),
    }
    tracing::info!("stopped");
    Ok(())
}
