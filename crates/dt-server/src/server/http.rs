//! The HTTP API (axum):
//!
//! | route | answer |
//! | --- | --- |
//! | `GET /healthz` | `200 ok` while the process serves |
//! | `GET /readyz` | `200 ready`, or `503` while starting or draining |
//! | `GET /metrics` | Prometheus metrics (`OpenMetrics` text) |
//! | `GET /v1/assets` | `{"assets": [AssetSummary…]}`: latest pressure, 1 s average, health, last update |
//! | `GET /v1/assets/{id}[?history=N]` | `AssetSummary` + `history` (recent estimates, oldest first); 404 if unknown |
//! | `GET /v1/assets/{id}/history?since=&until=&step_s=` | 1 s history from the fleet store (SPEC §9); times RFC 3339 or Unix s; default the last day of the asset's data |
//! | `GET /v1/assets/{id}/trend` | leak rate, predicted warn/fault crossings with intervals, or why not (SPEC §9) |
//! | `GET /v1/assets/{id}/runs` | runs seen, newest first |
//! | `GET /v1/assets/{id}/health` | health changes, newest first |
//! | `GET /v1/events` | Server-Sent Events: `estimate`, `health`, `run`; `lagged` (data: count) when a slow reader skipped events |
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
use serde::Deserialize;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use tokio_stream::wrappers::BroadcastStream;
use tokio_util::sync::CancellationToken;

use super::config::Config;
use super::metrics::Metrics;
use super::state::LiveState;
use super::store::{parse_time_ms, rfc3339_ms, FleetStore, StoreError, Trends};

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
    /// Cancelled when the HTTP server stops: ends the event streams.
    pub stop: CancellationToken,
}

/// The API's routes.
pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/assets", get(assets))
        .route("/v1/assets/{id}", get(asset))
        .route("/v1/assets/{id}/history", get(history))
        .route("/v1/assets/{id}/trend", get(trend))
        .route("/v1/assets/{id}/runs", get(runs))
        .route("/v1/assets/{id}/health", get(health_changes))
        .route("/v1/events", get(events))
        .with_state(state)
}

async fn readyz(State(app): State<AppState>) -> Response {
    if app.ready.load(Ordering::Relaxed) {
        (StatusCode::OK, "ready\n").into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "not ready\n").into_response()
    }
}

async fn metrics(State(app): State<AppState>) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        app.metrics.encode(SystemTime::now()),
    )
        .into_response()
}

async fn assets(State(app): State<AppState>) -> Response {
    let assets: Vec<serde_json::Value> = app
        .live
        .summaries()
        .into_iter()
        .map(|s| {
            let a = app.config.asset(&s.asset_id);
            let trend = app.trends.get(&s.asset_id);
            let mut v = serde_json::to_value(&s).unwrap_or_default();
            if let Some(o) = v.as_object_mut() {
                o.insert("warn_bar".into(), a.warn_bar.into());
                o.insert("fault_bar".into(), a.fault_bar.into());
                o.insert(
                    "trend".into(),
                    trend.map_or(serde_json::Value::Null, |t| {
                        serde_json::to_value(&*t).unwrap_or_default()
                    }),
                );
            }
            v
        })
        .collect();
    Json(serde_json::json!({ "assets": assets })).into_response()
}

/// Most points one history request may return.
pub const MAX_HISTORY_POINTS: i64 = 200_000;
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
        if (until - since) / step_ms > MAX_HISTORY_POINTS {
            return Err(StoreError::Request(format!(
                "more than {MAX_HISTORY_POINTS} points: raise step_s or narrow since/until"
            )));
        }
        store.history(&asset, since, until, step_ms)
    })
    .await;
    match result {
        Err(r) => r,
        Ok(None) if known(&app, &id) => Json(serde_json::json!({
            "asset_id": id, "step_s": step_s, "points": [] }))
        .into_response(),
        Ok(None) => unknown(&id),
        Ok(Some(points)) => {
            let points: Vec<serde_json::Value> = points
                .iter()
                .map(|p| {
                    serde_json::json!({
                        "t": rfc3339_ms(p.t_ms),
                        "pressure_bar": p.pressure_bar,
                        "pressure_lo_bar": p.pressure_lo_bar,
                        "pressure_hi_bar": p.pressure_hi_bar,
                        "health": p.health,
                        "excited": p.excited,
                    })
                })
                .collect();
            Json(serde_json::json!({ "asset_id": id, "step_s": step_s, "points": points }))
                .into_response()
        }
    }
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
