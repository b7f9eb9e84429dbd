//! The HTTP API (axum):
//!
//! | route | answer |
//! | --- | --- |
//! | `GET /` | the dashboard (HTML; its script, styles and the vendored uPlot under `/assets/`, compiled into the binary) |
//! | `GET /healthz` | `200 ok` while the process serves |
//! | `GET /readyz` | `200 ready` once every source takes work (the inbox: once its directory is watched, or rescanned when it cannot be; a NATS part: once connected), or `503` while starting (`not ready: starting <source>`) or draining, or `503 degraded: …` with the reason while the fleet store cannot be written (disk full) or once a source has stopped with an error (`degraded: source <name> stopped: <why>`) |
//! | `GET /metrics` | Prometheus metrics (`OpenMetrics` text) |
//! | `GET /v1/assets` | `{"assets": [AssetSummary…]}`: latest pressure, 1 s average, health, last update (an upload of older data than shown does not replace it; a live stream always does) |
//! | `GET /v1/assets/{id}[?history=N]` | `AssetSummary` + `history` (recent estimates, oldest first); 404 if unknown |
//! | `GET /v1/assets/{id}/history?since=&until=&step_s=` | 1 s history from the fleet store (SPEC §9); times RFC 3339 or Unix s; default the last day of the asset's data |
//! | `GET /v1/assets/{id}/trend` | leak rate, predicted warn/fault crossings with intervals, or why not (SPEC §9) |
//! | `GET /v1/assets/{id}/runs` | runs seen, newest first, each with what the charge observer made of it (`observer`), or a road asset's road observer (`road`: its blocks, and `why_none` when it read none) |
//! | `GET /v1/assets/{id}/health` | health changes, newest first |
//! | `GET /v1/assets/{id}/baseline` | the unit baseline in effect (`kind`: `observer` with `read_bar`, `read_sd_bar`, `own_damping_law`, `second` (a reading at another known charge, when there is one), `runs_averaged` (how many runs the reading averages, when more than one), `split_bar` (the stroke's ends apart at the reading, when read), `other_excitations` (its readings at other excitations, when any) and, when known, `accel_range_mps2`, or `road` with `offset_n`, `blocks`; `source`: `api` or `config`), 404 if none |
//! | `PUT /v1/assets/{id}/baseline` | sets the asset's unit baseline after a service (body: `{"charge_bar", "read_bar", "read_sd_bar"}` and optionally `"accel_range_mps2"`, `"damping_law"` (the unit's own), `"runs_averaged"`, `"split_bar"` (the stroke's ends apart at the reading), `"second"` (a reading at another known charge) and `"other_excitations"` (readings at other excitations), bare or under `observer_baseline` as `train.observer baseline` writes it; for a road asset `{"charge_bar", "offset_n", "blocks"}`, bare or under `road_baseline` as `shocktwin road --baseline` prints it; `409` for the other kind); kept in the fleet store (in a NATS group: in its bucket `shocktwin_baselines`, for every daemon), used from the asset's next run; the ingest role when tokens are on |
//! | `DELETE /v1/assets/{id}/baseline` | forgets the API's baseline (a `config` one applies again); answers the baseline now in effect or `null` |
//! | `PUT /v1/assets/{id}/service` | reports a service (body: `{"charge_bar": …, "at": …}`, the charge the unit was filled to and, optionally, when (RFC 3339 or Unix s; default now); runs recorded before it are not read): kept in the fleet store as pending; the asset's runs that start after it run without a baseline, and the first that reads the unit completes it into the asset's baseline (read with the unit's own damping law when its baseline before had one; a road asset's drive is read by the road observer into a road baseline; see [`super::baselines`]); the trend restarts at it; in a NATS group it goes to the group's bucket `shocktwin_services` and the worker that takes the asset's next run reads it; the ingest role when tokens are on; `409` with a model that does not read the observer |
//! | `GET /v1/assets/{id}/service` | the pending service (`charge_bar`, `set_at`, `state`, `last_refusal`: why the last run gave no baseline), 404 if none |
//! | `DELETE /v1/assets/{id}/service` | withdraws the pending service (the API baseline before it applies again) |
//! | `GET /v1/events` | Server-Sent Events: `estimate`, `health`, `run`; `lagged` (data: count) when a slow reader skipped events |
//! | `POST /v1/runs` | upload one run (the body is an MCAP stream, as on the TCP ingest); answers its `RunReport`; the ingest role when tokens are on |
//!
//! With bearer tokens configured (`[auth]`, see [`super::security`]) every
//! route but `/healthz` and the dashboard's static files (`/`, `/assets/…`,
//! which carry no fleet data) answers `401` without a read token.
//!
//! Values the estimator could not give are `null`. The store-backed routes
//! answer 404 for an unknown asset and 503 when the daemon runs without a
//! store.

use std::convert::Infallible;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::SystemTime;

use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use futures_util::{Stream, StreamExt};
use serde::{Deserialize, Serialize};
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use tokio_stream::wrappers::BroadcastStream;
use tokio_util::sync::CancellationToken;

use dt_core::estimate::Health;

use super::baselines::{BaselineView, Baselines, ServiceView};
use super::config::Config;
use super::estimator::EstimatorFactory;
use super::metrics::Metrics;
use super::security::{Role, Tokens};
use super::state::{AssetSummary, LiveState};
use super::store::{
    parse_time_ms, rfc3339_ms, AssetBaseline, FleetStore, HistoryPoint, PendingService, StoreError,
    StoredBaseline, TrendSummary, TrendView, Trends,
};

/// What the handlers share.
#[derive(Debug, Clone)]
pub struct AppState {
    /// The fleet's live view.
    pub live: Arc<LiveState>,
    /// The fleet store, if any.
    pub store: Option<Arc<dyn FleetStore>>,
    /// Every asset's trend.
    pub trends: Arc<Trends>,
    /// The configuration (thresholds per asset).
    pub config: Arc<Config>,
    /// Metrics.
    pub metrics: Arc<Metrics>,
    /// Ready to take work (false while starting and draining).
    pub ready: Arc<AtomicBool>,
    /// The sources not yet taking work (`/readyz` waits for them).
    pub starting: super::source::Starting,
    /// Cancelled when the HTTP server stops: ends the event streams.
    pub stop: CancellationToken,
    /// Bearer tokens (none configured: the API is open).
    pub tokens: Arc<Tokens>,
    /// Where uploads go (`POST /v1/runs`).
    pub uploads: Uploads,
    /// Unit baselines set over the API.
    pub baselines: Arc<Baselines>,
    /// The model, when the twin is the estimator (to check a baseline
    /// against it).
    pub model: Option<EstimatorFactory>,
    /// The NATS group's baseline bucket, when the daemon is in one: baselines
    /// are written there, and reach this daemon through its watcher.
    pub group: Option<crate::nats::baselines::BaselineBucket>,
}

/// The ingest behind `POST /v1/runs`, until the daemon stops taking runs.
#[derive(Debug, Clone)]
pub struct Uploads {
    ingest: Arc<std::sync::Mutex<Option<super::ingest::Ingest>>>,
    cancel: CancellationToken,
}

impl Uploads {
    /// Uploads into `ingest`; `cancel` ends the ones in progress (shutdown).
    #[must_use]
    pub fn new(ingest: super::ingest::Ingest, cancel: CancellationToken) -> Self {
        Self {
            ingest: Arc::new(std::sync::Mutex::new(Some(ingest))),
            cancel,
        }
    }

    /// Takes no upload (`503`): an API without ingest (benches, read-only views).
    #[must_use]
    pub fn disabled() -> Self {
        Self {
            ingest: Arc::new(std::sync::Mutex::new(None)),
            cancel: CancellationToken::new(),
        }
    }

    /// No upload is taken any more (the sinks may then close).
    pub fn close(&self) {
        self.ingest
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take();
    }

    fn get(&self) -> Option<super::ingest::Ingest> {
        self.ingest
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }
}

/// `POST /v1/runs`: the body is one run's MCAP stream.
async fn post_run(State(app): State<AppState>, req: axum::extract::Request) -> Response {
    let source = format!("http upload from {}", Peer::of(&req));
    let body = req.into_body();
    let Some(ingest) = app.uploads.get() else {
        // Not drained: the daemon is stopping and waits for no upload.
        return (StatusCode::SERVICE_UNAVAILABLE, "the daemon is stopping\n").into_response();
    };
    let stream = body
        .into_data_stream()
        .map(|r| r.map_err(std::io::Error::other));
    let mut reader = tokio_util::io::StreamReader::new(stream);
    let idle = std::time::Duration::from_secs_f64(app.config.limits.idle_timeout_s);
    let report = ingest
        .ingest_stream(
            super::sink::SourceKind::Http,
            source,
            &mut reader,
            &app.uploads.cancel,
            Some(idle),
        )
        .await;
    let status = if report.status == "completed" {
        StatusCode::OK
    } else {
        StatusCode::UNPROCESSABLE_ENTITY
    };
    // A refused stream stops being read where it went wrong; what the
    // client still sends is read and dropped, so that it reaches the answer.
    drain(&mut reader).await;
    (status, Json(report)).into_response()
}

/// Reads and drops what is left of a refused request's body (within the
/// TCP ingest's bounds: 64 MiB, 2 s), so that its client sees the refusal.
///
/// A client that sends its whole body before it reads the answer (curl and
/// httpx over HTTP/2, HTTP/1.1 clients without `Expect: 100-continue`)
/// otherwise never sees a refusal sent before the body is read: over HTTP/2
/// the stream is reset under it (curl: "Stream error in the HTTP/2 framing
/// layer"; httpx waits on a flow-control window that never opens).
async fn drain<R: tokio::io::AsyncRead + Unpin>(body: R) {
    super::tcp::discard_rest(body).await;
}

/// [`drain`] for a request refused before its handler ran.
async fn drain_request(req: axum::extract::Request) {
    let stream = req
        .into_body()
        .into_data_stream()
        .map(|r| r.map_err(std::io::Error::other));
    drain(tokio_util::io::StreamReader::new(stream)).await;
}

// The dashboard, compiled in (no build step; uPlot vendored from its npm
// package, see assets/vendor/README.md).
const DASHBOARD_HTML: &str = include_str!("../../assets/index.html");
const DASHBOARD_JS: &str = include_str!("../../assets/app.js");
const DASHBOARD_CSS: &str = include_str!("../../assets/app.css");
const UPLOT_JS: &str = include_str!("../../assets/vendor/uplot.min.js");
const UPLOT_CSS: &str = include_str!("../../assets/vendor/uplot.min.css");
const JS: &str = "text/javascript; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";

fn static_file(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
        .into_response()
}

/// The API's routes.
pub fn router(state: AppState) -> Router {
    Router::new()
        .route(
            "/",
            get(|| async { static_file("text/html; charset=utf-8", DASHBOARD_HTML) }),
        )
        .route(
            "/assets/app.js",
            get(|| async { static_file(JS, DASHBOARD_JS) }),
        )
        .route(
            "/assets/app.css",
            get(|| async { static_file(CSS, DASHBOARD_CSS) }),
        )
        .route(
            "/assets/uplot.min.js",
            get(|| async { static_file(JS, UPLOT_JS) }),
        )
        .route(
            "/assets/uplot.min.css",
            get(|| async { static_file(CSS, UPLOT_CSS) }),
        )
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/assets", get(assets))
        .route("/v1/assets/{id}", get(asset))
        .route("/v1/assets/{id}/history", get(history))
        .route("/v1/assets/{id}/trend", get(trend))
        .route("/v1/assets/{id}/runs", get(runs))
        .route("/v1/assets/{id}/health", get(health_changes))
        .route(
            "/v1/assets/{id}/baseline",
            get(get_baseline).put(put_baseline).delete(delete_baseline),
        )
        .route(
            "/v1/assets/{id}/service",
            get(get_service).put(put_service).delete(delete_service),
        )
        .route("/v1/events", get(events))
        .route("/v1/runs", axum::routing::post(post_run))
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            require_token,
        ))
        .with_state(state)
}

/// Routes open without a token: liveness and the dashboard's static files.
fn is_open(path: &str) -> bool {
    path == "/healthz" || path == "/" || path.starts_with("/assets/")
}

/// Requests that change what the daemon computes (the ingest role's):
/// uploads and setting or removing a baseline or a service.
fn is_write(method: &axum::http::Method, path: &str) -> bool {
    use axum::http::Method;
    (method == Method::POST && path == "/v1/runs")
        || ((method == Method::PUT || method == Method::DELETE)
            && (path.ends_with("/baseline") || path.ends_with("/service")))
}

/// The bearer token of a request: `Authorization: Bearer …`, else the
/// `access_token` query parameter (for `EventSource`). Never logged.
fn bearer(req: &axum::extract::Request) -> Option<String> {
    if let Some(value) = req.headers().get(header::AUTHORIZATION) {
        let value = value.to_str().ok()?;
        let (scheme, token) = value.split_once(' ')?;
        return scheme
            .eq_ignore_ascii_case("bearer")
            .then(|| token.trim().to_owned());
    }
    form_urlencoded::parse(req.uri().query()?.as_bytes())
        .find(|(k, _)| k == "access_token")
        .map(|(_, v)| v.into_owned())
}

fn unauthorized(error: Option<&str>) -> Response {
    let (challenge, body) = match error {
        Some(e) => (
            format!("Bearer realm=\"shocktwin\", error=\"{e}\""),
            // a wrong token was told the same as none (a helper's trial)
            "this bearer token is not one of the daemon's (check the token file it was given)\n",
        ),
        None => (
            "Bearer realm=\"shocktwin\"".to_owned(),
            "a bearer token is needed (Authorization: Bearer <token>)\n",
        ),
    };
    (
        StatusCode::UNAUTHORIZED,
        [(header::WWW_AUTHENTICATE, challenge)],
        body,
    )
        .into_response()
}

/// A request's peer address, as the listener accepted it (absent when the
/// router is driven without a listener, as in unit tests).
struct Peer(Option<std::net::SocketAddr>);

impl Peer {
    fn of(req: &axum::extract::Request) -> Self {
        Self(
            req.extensions()
                .get::<axum::extract::ConnectInfo<std::net::SocketAddr>>()
                .map(|info| info.0),
        )
    }
}

impl std::fmt::Display for Peer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            Some(addr) => write!(f, "{addr}"),
            None => f.write_str("an unknown peer"),
        }
    }
}

/// Token check in front of every route (a no-op while auth is off). Every
/// refusal is logged with the peer, the method and the path (never the
/// token), one line each, for an operator or fail2ban to read.
async fn require_token(
    State(app): State<AppState>,
    req: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    if !app.tokens.enabled() || is_open(req.uri().path()) {
        return next.run(req).await;
    }
    let upload = is_write(req.method(), req.uri().path());
    let (refusal, why) = match bearer(&req).map(|token| app.tokens.role(&token)) {
        None => (unauthorized(None), "no token"),
        Some(Some(Role::Read)) if !upload => return next.run(req).await,
        Some(Some(Role::Ingest)) if upload => return next.run(req).await,
        Some(Some(Role::Ingest)) => (
            (
                StatusCode::FORBIDDEN,
                "this token may ingest runs and set baselines, not read the API\n",
            )
                .into_response(),
            "an ingest token on a read route",
        ),
        Some(Some(Role::Read)) => (
            (
                StatusCode::FORBIDDEN,
                "this token may read the API, not upload runs or set baselines\n",
            )
                .into_response(),
            "a read token on an ingest route",
        ),
        Some(None) => {
            app.metrics.error("auth");
            (unauthorized(Some("invalid_token")), "an unknown token")
        }
    };
    let (peer, method, path) = (Peer::of(&req), req.method(), req.uri().path());
    let status = refusal.status().as_u16();
    if why == "no token" {
        // a client not yet given its token: said, but not as a warning
        tracing::info!(%peer, %method, path, "HTTP {status}: {why}");
    } else {
        tracing::warn!(%peer, %method, path, "HTTP {status}: {why}");
    }
    // The client of a refused upload sees the refusal (see `drain`).
    if upload {
        drain_request(req).await;
    }
    refusal
}

async fn readyz(State(app): State<AppState>) -> Response {
    if !app.ready.load(Ordering::Relaxed) {
        return (StatusCode::SERVICE_UNAVAILABLE, "not ready\n").into_response();
    }
    // sources that stopped, then those that cannot take work for now
    let stopped = app
        .starting
        .failed()
        .into_iter()
        .map(|(name, why)| format!("source {name} stopped: {why}"));
    let troubled = app
        .starting
        .troubled()
        .into_iter()
        .map(|(name, why)| format!("source {name}: {why}"));
    let said: Vec<String> = stopped.chain(troubled).collect();
    if !said.is_empty() {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("degraded: {}\n", said.join("; ")),
        )
            .into_response();
    }
    let starting = app.starting.pending();
    if !starting.is_empty() {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("not ready: starting {}\n", starting.join(", ")),
        )
            .into_response();
    }
    match app.trends.store_problem() {
        Some(problem) => (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("degraded: history is not being kept: {problem}\n"),
        )
            .into_response(),
        None => (StatusCode::OK, "ready\n").into_response(),
    }
}

async fn metrics(State(app): State<AppState>) -> Response {
    let assets = app.live.summaries();
    let text = app.metrics.encode_with_assets(
        SystemTime::now(),
        assets
            .iter()
            .map(|a| (a.asset_id.as_str(), a.health, a.pressure_avg_bar)),
    );
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        text,
    )
        .into_response()
}

/// One asset of `GET /v1/assets`: its live summary, thresholds and trend summary.
#[derive(Serialize)]
struct AssetRow<'a> {
    #[serde(flatten)]
    summary: &'a AssetSummary,
    warn_bar: f64,
    fault_bar: f64,
    /// Driven on roads (`road = true`): the road observer reads its charge.
    road: bool,
    trend: Option<TrendSummary<'a>>,
    /// The unit baseline in effect, if any.
    baseline: Option<BaselineView>,
    /// A service whose baseline is still to be read, if any.
    service: Option<ServiceView>,
}

async fn assets(State(app): State<AppState>) -> Response {
    let summaries = app.live.summaries();
    let trends: Vec<_> = summaries
        .iter()
        .map(|s| app.trends.get(&s.asset_id))
        .collect();
    let rows: Vec<AssetRow<'_>> = summaries
        .iter()
        .zip(&trends)
        .map(|(s, t)| {
            let a = app.config.asset(&s.asset_id);
            AssetRow {
                summary: s,
                warn_bar: a.warn_bar,
                fault_bar: a.fault_bar,
                road: a.road,
                trend: t.as_deref().map(TrendView::summary),
                baseline: app.baselines.view(&app.config, &s.asset_id),
                service: app
                    .baselines
                    .service(&s.asset_id)
                    .as_ref()
                    .map(ServiceView::from),
            }
        })
        .collect();
    Json(Assets { assets: rows }).into_response()
}

#[derive(Serialize)]
struct Assets<'a> {
    assets: Vec<AssetRow<'a>>,
}

/// Most points one history request may return.
pub const MAX_HISTORY_POINTS: usize = 200_000;
/// Default span of a history request, ms (one day back from the newest point).
const DEFAULT_SPAN_MS: i64 = 86_400_000;

fn error(status: StatusCode, message: impl Into<String>) -> Response {
    (status, Json(serde_json::json!({ "error": message.into() }))).into_response()
}

fn no_store() -> Response {
    error(
        StatusCode::SERVICE_UNAVAILABLE,
        "no fleet store: the daemon keeps no history (start it with --db PATH or [store] path)",
    )
}

fn unknown(id: &str) -> Response {
    error(StatusCode::NOT_FOUND, format!("unknown asset `{id}`"))
}

fn store_error(e: &StoreError) -> Response {
    match e {
        StoreError::Request(m) => error(StatusCode::BAD_REQUEST, m.clone()),
        other => {
            tracing::error!("{other}");
            error(StatusCode::INTERNAL_SERVER_ERROR, other.to_string())
        }
    }
}

/// Runs a store query off the async workers.
async fn blocking<R: Send + 'static>(
    app: &AppState,
    f: impl FnOnce(&dyn FleetStore) -> Result<R, StoreError> + Send + 'static,
) -> Result<R, Response> {
    let Some(store) = app.store.clone() else {
        return Err(no_store());
    };
    match tokio::task::spawn_blocking(move || f(store.as_ref())).await {
        Ok(Ok(r)) => Ok(r),
        Ok(Err(e)) => Err(store_error(&e)),
        Err(e) => Err(error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string())),
    }
}

fn known(app: &AppState, id: &str) -> bool {
    app.live.detail(id, Some(0)).is_some() || app.trends.get(id).is_some()
}

async fn get_baseline(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    match app.baselines.view(&app.config, &id) {
        Some(v) => Json(v).into_response(),
        None if app.baselines.service(&id).is_some() => error(
            StatusCode::NOT_FOUND,
            format!(
                "asset `{id}` has no unit baseline in effect: a service is pending, and its \
                 baseline is read from the asset's next run (GET …/service)"
            ),
        ),
        None => error(
            StatusCode::NOT_FOUND,
            format!("asset `{id}` has no unit baseline"),
        ),
    }
}

/// `400` for an asset id outside SPEC §2's charset.
fn bad_asset_id(id: &str) -> Option<Response> {
    (!dt_core::log::is_valid_id(id)).then(|| {
        error(
            StatusCode::BAD_REQUEST,
            format!(
                "asset id {id:?} is not {} (SPEC §2)",
                dt_core::log::ID_FORMAT
            ),
        )
    })
}

/// `409` when this daemon's model cannot take `baseline` for `id`. A fleet
/// view of a NATS group runs no model: the workers check it when they use it.
fn refuse_here(app: &AppState, id: &str, baseline: &AssetBaseline) -> Option<Response> {
    let checkable = app.model.is_some() || app.group.is_none();
    checkable
        .then(|| refuse_baseline(app.model.as_ref(), &app.config, id, baseline))
        .flatten()
        .map(|why| error(StatusCode::CONFLICT, why))
}

/// Why `model` cannot take `baseline` for `id`, if it cannot: a road asset
/// (`road = true`) takes a road baseline, any other an observer baseline,
/// when the model reads that observer.
fn refuse_baseline(
    model: Option<&EstimatorFactory>,
    config: &Config,
    id: &str,
    baseline: &AssetBaseline,
) -> Option<String> {
    let Some(model) = model else {
        return Some(
            "this daemon runs no estimator (no --model), so a baseline has nothing to correct"
                .into(),
        );
    };
    let mut asset = config.asset(id);
    match *baseline {
        AssetBaseline::Road(r) if asset.road => asset.road_baseline = Some(r),
        AssetBaseline::Road(_) => {
            return Some(format!(
                "asset `{id}` is not driven on roads (`road = true` in [assets.{id}]): a road \
                 baseline (offset_n, blocks) has nothing to correct; an observer baseline is \
                 {{charge_bar, read_bar, read_sd_bar}}"
            ))
        }
        AssetBaseline::Observer(_) if asset.road => {
            return Some(format!(
                "asset `{id}` is driven on roads (`road = true`): the road observer reads it, and \
                 its baseline is {{charge_bar, offset_n, blocks}} (`shocktwin road --baseline`), \
                 or report a service (PUT /v1/assets/{id}/service) and its next drive is read"
            ))
        }
        AssetBaseline::Observer(_)
            if !model
                .bundle()
                .groups
                .contains(&dt_core::features::Group::Observer) =>
        {
            return Some(format!(
                "the model {} does not read the charge observer (no `observer` group), so a \
                 baseline has nothing to correct",
                model.bundle().dir.display()
            ));
        }
        AssetBaseline::Observer(u) => asset.observer_baseline = Some(u),
    }
    model
        .estimator_of(id, &asset)
        .err()
        .map(|e| format!("the model cannot use this baseline: {e}"))
}

/// A baseline from a request's body: `{charge_bar, read_bar, read_sd_bar}`
/// (bare or under `observer_baseline`, as `train.observer baseline` writes
/// it) or `{charge_bar, offset_n, blocks}` (bare or under `road_baseline`, as
/// `shocktwin road --baseline` prints it).
fn baseline_from_document(doc: serde_json::Value) -> Result<AssetBaseline, String> {
    let road = match &doc {
        serde_json::Value::Object(map) if map.contains_key("road_baseline") => {
            Some(map["road_baseline"].clone())
        }
        serde_json::Value::Object(map) if map.contains_key("offset_n") => Some(doc.clone()),
        _ => None,
    };
    match road {
        Some(inner) => {
            let b: dt_core::road::RoadBaseline = serde_json::from_value(inner).map_err(|e| {
                format!("a road baseline needs charge_bar (bar), offset_n (N) and blocks: {e}")
            })?;
            b.validate()?;
            Ok(AssetBaseline::Road(b))
        }
        None => dt_core::charge::UnitBaseline::from_document(doc).map(AssetBaseline::Observer),
    }
}

async fn put_baseline(
    State(app): State<AppState>,
    Path(id): Path<String>,
    body: axum::body::Bytes,
) -> Response {
    if let Some(r) = bad_asset_id(&id) {
        return r;
    }
    let doc: serde_json::Value = match serde_json::from_slice(&body) {
        Ok(v) => v,
        Err(e) => return error(StatusCode::BAD_REQUEST, format!("body: not JSON ({e})")),
    };
    let baseline = match baseline_from_document(doc) {
        Ok(b) => b,
        Err(e) => return error(StatusCode::UNPROCESSABLE_ENTITY, format!("body: {e}")),
    };
    let charges = match &baseline {
        AssetBaseline::Road(r) => super::config::charge_in_range("charge_bar", r.charge_bar),
        AssetBaseline::Observer(u) => super::config::baseline_charges_in_range(u),
    };
    if let Err(e) = charges {
        return error(StatusCode::UNPROCESSABLE_ENTITY, format!("body: {e}"));
    }
    if let Some(r) = refuse_here(&app, &id, &baseline) {
        return r;
    }
    let set_ms = super::store::wall_now_ms();
    let stored = StoredBaseline { baseline, set_ms };
    if let Err(r) = change_unit(&app, &id, UnitChange::Baseline(Some(stored))).await {
        return r;
    }
    tracing::info!(asset = %id, baseline = %baseline, "unit baseline set; used from the asset's next run");
    Json(BaselineView::api(baseline, set_ms)).into_response()
}

async fn delete_baseline(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if app.baselines.get(&id).is_none() {
        return error(
            StatusCode::NOT_FOUND,
            format!("asset `{id}` has no baseline set over the API"),
        );
    }
    if let Err(r) = change_unit(&app, &id, UnitChange::Baseline(None)).await {
        return r;
    }
    tracing::info!(asset = %id, "unit baseline removed; used from the asset's next run");
    let now = app.baselines.view(&app.config, &id);
    Json(serde_json::json!({ "baseline": now })).into_response()
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ServiceBody {
    charge_bar: f64,
    /// When the unit was serviced (RFC 3339 or Unix s); default: now.
    at: Option<String>,
}

async fn get_service(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    match app.baselines.service(&id) {
        Some(s) => Json(ServiceView::from(&s)).into_response(),
        None => error(
            StatusCode::NOT_FOUND,
            format!("asset `{id}` has no pending service"),
        ),
    }
}

async fn put_service(
    State(app): State<AppState>,
    Path(id): Path<String>,
    body: axum::body::Bytes,
) -> Response {
    if let Some(r) = bad_asset_id(&id) {
        return r;
    }
    let (charge_bar, at) = match serde_json::from_slice::<ServiceBody>(&body) {
        Ok(b) => match super::config::charge_in_range("charge_bar", b.charge_bar) {
            Ok(()) => (b.charge_bar, b.at),
            Err(e) => return error(StatusCode::UNPROCESSABLE_ENTITY, format!("body: {e}")),
        },
        Err(e) => {
            return error(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!(
                    "body: need {{\"charge_bar\": <the charge filled, bar>, \"at\": <when, \
                     optional>}} ({e})"
                ),
            )
        }
    };
    let now = super::store::wall_now_ms();
    let set_ms = match at.as_deref().map(parse_time_ms) {
        None => now,
        Some(Ok(t)) if t <= now + 60_000 => t,
        Some(Ok(_)) => {
            return error(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!("body: at {:?} is in the future", at.unwrap_or_default()),
            )
        }
        Some(Err(e)) => return error(StatusCode::UNPROCESSABLE_ENTITY, format!("body: at: {e}")),
    };
    let probe = if app.config.asset(&id).road {
        AssetBaseline::Road(dt_core::road::RoadBaseline {
            charge_bar,
            offset_n: 0.0,
            blocks: 1,
        })
    } else {
        AssetBaseline::Observer(dt_core::charge::UnitBaseline {
            charge_bar,
            read_bar: charge_bar,
            read_sd_bar: 1.0,
            accel_range_mps2: None,
            damping_law: None,
            second: None,
            runs_averaged: 1.0,
            split_bar: None,
            other_excitations: Default::default(),
        })
    };
    if let Some(r) = refuse_here(&app, &id, &probe) {
        return r;
    }
    let service = PendingService {
        charge_bar,
        set_ms,
        refusal: None,
    };
    let view = ServiceView::from(&service);
    if let Err(r) = change_unit(&app, &id, UnitChange::Service(Some(service))).await {
        return r;
    }
    tracing::info!(asset = %id, charge_bar, "service reported; the unit's baseline is read from its next run");
    let mut answer = serde_json::to_value(&view).unwrap_or_default();
    // A mistyped asset id was accepted like any other (a helper's trial):
    // its service would wait for a run that never comes.
    if app.live.detail(&id, Some(0)).is_none() && !app.config.assets.contains_key(&id) {
        let note = format!(
            "asset `{id}` has not been seen by this daemon nor is it in its configuration: the \
             service waits for its first run (is the id right? GET /v1/assets lists the known ones)"
        );
        tracing::warn!(asset = %id, "{note}");
        answer["note"] = note.into();
    }
    (StatusCode::ACCEPTED, Json(answer)).into_response()
}

async fn delete_service(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if app.baselines.service(&id).is_none() {
        return error(
            StatusCode::NOT_FOUND,
            format!("asset `{id}` has no pending service"),
        );
    }
    if let Err(r) = change_unit(&app, &id, UnitChange::Service(None)).await {
        return r;
    }
    tracing::info!(asset = %id, "pending service withdrawn");
    Json(serde_json::json!({ "baseline": app.baselines.view(&app.config, &id) })).into_response()
}

/// A change to an asset's unit baseline or pending service over the API.
// A unit's own damping law makes an observer baseline ≈ 0.4 kB; one is made per
// change of an asset's baseline, never per sample, and stays `Copy`.
#[allow(clippy::large_enum_variant)]
enum UnitChange {
    /// Keep (`Some`) or forget (`None`) the API baseline; one given outright
    /// supersedes a service still to be read.
    Baseline(Option<StoredBaseline>),
    /// Report (`Some`) or withdraw (`None`) a service.
    Service(Option<PendingService>),
}

/// Applies `change` to the store and this daemon's copy, then recomputes
/// the asset's trend; in a NATS group, writes it to the group's buckets
/// instead (this daemon's watcher then applies it like every other
/// daemon's).
async fn change_unit(app: &AppState, id: &str, change: UnitChange) -> Result<(), Response> {
    let supersedes =
        matches!(change, UnitChange::Baseline(Some(_))) && app.baselines.service(id).is_some();
    if let Some(group) = &app.group {
        let unavailable = |e: crate::nats::NatsError| {
            tracing::error!("{e}");
            error(StatusCode::SERVICE_UNAVAILABLE, e.to_string())
        };
        if supersedes {
            group.write_service(id, None).await.map_err(unavailable)?;
        }
        return match change {
            UnitChange::Baseline(b) => group.write(id, b).await,
            UnitChange::Service(s) => group.write_service(id, s).await,
        }
        .map_err(unavailable);
    }
    let (baselines, trends) = (Arc::clone(&app.baselines), Arc::clone(&app.trends));
    let (config, metrics, asset) = (
        Arc::clone(&app.config),
        Arc::clone(&app.metrics),
        id.to_owned(),
    );
    blocking(app, move |store| {
        if supersedes {
            baselines.set_service(Some(store), &trends, &asset, None)?;
        }
        match change {
            UnitChange::Baseline(b) => baselines.set(Some(store), &trends, &asset, b)?,
            UnitChange::Service(s) => baselines.set_service(Some(store), &trends, &asset, s)?,
        }
        trends.refresh(store, &config, &metrics, &asset);
        Ok(())
    })
    .await
}

#[derive(Debug, Deserialize)]
struct RangeQuery {
    since: Option<String>,
    until: Option<String>,
    step_s: Option<f64>,
}

async fn history(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<RangeQuery>,
) -> Response {
    let parse = |name: &str, v: &Option<String>| -> Result<Option<i64>, String> {
        v.as_deref()
            .map(|t| parse_time_ms(t).map_err(|e| format!("{name}: {e}")))
            .transpose()
    };
    let (since, until) = match (parse("since", &q.since), parse("until", &q.until)) {
        (Ok(s), Ok(u)) => (s, u),
        (Err(e), _) | (_, Err(e)) => return error(StatusCode::BAD_REQUEST, e),
    };
    let step_s = q.step_s.unwrap_or(1.0);
    if !(step_s.is_finite() && step_s >= 1.0) {
        return error(
            StatusCode::BAD_REQUEST,
            format!("step_s: {step_s} is not a number ≥ 1"),
        );
    }
    let step_ms = (step_s * 1e3).round() as i64;
    let asset = id.clone();
    let result = blocking(&app, move |store| {
        let until = match until {
            Some(u) => u,
            None => match store.newest_ms(&asset)? {
                Some(t) => t,
                None => return Ok(None),
            },
        };
        let since = since.unwrap_or(until - DEFAULT_SPAN_MS);
        if until < since {
            return Err(StoreError::Request(format!(
                "until ({until} ms) is before since ({since} ms)"
            )));
        }
        store.history(&asset, (since, until), step_ms, MAX_HISTORY_POINTS)
    })
    .await;
    match result {
        Err(r) => r,
        Ok(None) if known(&app, &id) => Json(serde_json::json!({
            "asset_id": id, "step_s": step_s, "points": [] }))
        .into_response(),
        Ok(None) => unknown(&id),
        Ok(Some(points)) => (
            [(header::CONTENT_TYPE, "application/json")],
            history_json(&id, step_s, &points),
        )
            .into_response(),
    }
}

/// One point of `GET /v1/assets/{id}/history`.
#[derive(Serialize)]
struct HistoryRow {
    t: String,
    pressure_bar: Option<f64>,
    pressure_lo_bar: Option<f64>,
    pressure_hi_bar: Option<f64>,
    health: Health,
    excited: bool,
}

#[derive(Serialize)]
struct HistoryBody<'a> {
    asset_id: &'a str,
    step_s: f64,
    points: Vec<HistoryRow>,
}

/// The body of `GET /v1/assets/{id}/history` for `points`.
#[must_use]
pub fn history_json(asset_id: &str, step_s: f64, points: &[HistoryPoint]) -> Vec<u8> {
    let body = HistoryBody {
        asset_id,
        step_s,
        points: points
            .iter()
            .map(|p| HistoryRow {
                t: rfc3339_ms(p.t_ms),
                pressure_bar: p.pressure_bar,
                pressure_lo_bar: p.pressure_lo_bar,
                pressure_hi_bar: p.pressure_hi_bar,
                health: p.health,
                excited: p.excited,
            })
            .collect(),
    };
    serde_json::to_vec(&body).unwrap_or_default()
}

async fn trend(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    if app.store.is_none() {
        return no_store();
    }
    match app.trends.get(&id) {
        Some(t) => {
            let mut v = serde_json::to_value(&*t).unwrap_or_default();
            if let Some(o) = v.as_object_mut() {
                o.insert("asset_id".into(), id.into());
            }
            Json(v).into_response()
        }
        // Known live, no run ended yet: no trend, said as such.
        None if known(&app, &id) => {
            let a = app.config.asset(&id);
            let mut v = serde_json::to_value(TrendView::compute(&[], a.warn_bar, a.fault_bar))
                .unwrap_or_default();
            if let Some(o) = v.as_object_mut() {
                o.insert("asset_id".into(), id.into());
            }
            Json(v).into_response()
        }
        None => unknown(&id),
    }
}

/// Rows returned by `/runs` and `/health`.
const LIST_LIMIT: usize = 500;

async fn runs(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    let asset = id.clone();
    match blocking(&app, move |store| store.runs(&asset, LIST_LIMIT)).await {
        Err(r) => r,
        Ok(runs) if runs.is_empty() && !known(&app, &id) => unknown(&id),
        Ok(runs) => {
            let runs: Vec<serde_json::Value> = runs
                .iter()
                .map(|r| {
                    serde_json::json!({
                        "run_id": r.run_id,
                        "source": r.source,
                        "start": rfc3339_ms(r.start_ms),
                        "end": r.end_ms.map(rfc3339_ms),
                        "ticks": r.ticks,
                        "status": r.status,
                        "reason": r.reason,
                        "summary_bar": r.summary.map(|s| s.pressure_bar),
                        "summary_sd_bar": r.summary.map(|s| s.sd_bar),
                        "observer": r.observer,
                        "road": r.road,
                        "simulated": r.simulated,
                    })
                })
                .collect();
            Json(serde_json::json!({ "asset_id": id, "runs": runs })).into_response()
        }
    }
}

async fn health_changes(State(app): State<AppState>, Path(id): Path<String>) -> Response {
    let asset = id.clone();
    match blocking(&app, move |store| store.health_changes(&asset, LIST_LIMIT)).await {
        Err(r) => r,
        Ok(c) if c.is_empty() && !known(&app, &id) => unknown(&id),
        Ok(changes) => {
            let changes: Vec<serde_json::Value> = changes
                .iter()
                .map(|c| {
                    serde_json::json!({
                        "t": rfc3339_ms(c.t_ms), "run_id": c.run_id, "from": c.from, "to": c.to })
                })
                .collect();
            Json(serde_json::json!({ "asset_id": id, "changes": changes })).into_response()
        }
    }
}

#[derive(Debug, Deserialize)]
struct HistoryQuery {
    history: Option<usize>,
}

async fn asset(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Response {
    match app.live.detail(&id, q.history) {
        Some(d) => Json(d).into_response(),
        None => (
            StatusCode::NOT_FOUND,
            Json(serde_json::json!({ "error": format!("unknown asset `{id}`") })),
        )
            .into_response(),
    }
}

async fn events(State(app): State<AppState>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let stream = BroadcastStream::new(app.live.subscribe())
        .map(|item| {
            Ok(match item {
                Ok(ev) => Event::default()
                    .event(ev.name())
                    .json_data(&*ev)
                    .unwrap_or_else(|e| Event::default().comment(format!("encoding failed: {e}"))),
                Err(BroadcastStreamRecvError::Lagged(n)) => {
                    Event::default().event("lagged").data(n.to_string())
                }
            })
        })
        .take_until(app.stop.cancelled_owned());
    Sse::new(stream).keep_alive(KeepAlive::default())
}
