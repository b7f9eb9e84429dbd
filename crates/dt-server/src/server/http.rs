//! The HTTP API (axum):
//!
//! | route | answer |
//! | --- | --- |
//! | `GET /healthz` | `200 ok` while the process serves |
//! | `GET /readyz` | `200 ready`, or `503` while starting or draining |
//! | `GET /metrics` | Prometheus metrics (`OpenMetrics` text) |
//! | `GET /v1/assets` | `{"assets": [AssetSummary…]}`: latest pressure, 1 s average, health, last update |
//! | `GET /v1/assets/{id}[?history=N]` | `AssetSummary` + `history` (recent estimates, oldest first); 404 if unknown |
//! | `GET /v1/events` | Server-Sent Events: `estimate`, `health`, `run`; `lagged` (data: count) when a slow reader skipped events |
//!
//! Values the estimator could not give are `null`.

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

use super::metrics::Metrics;
use super::state::LiveState;

/// What the handlers share.
#[derive(Debug, Clone)]
pub struct AppState {
    /// The fleet's live view.
    pub live: Arc<LiveState>,
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
    Json(serde_json::json!({ "assets": app.live.summaries() })).into_response()
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
