//! The fleet store at fleet scale (issue 10's targets), through the real
//! write path (`SqliteStore::apply`) and the real HTTP handlers (the axum
//! router, called without a socket):
//!
//! - `fleet/assets`: `GET /v1/assets` for every asset, with its trend;
//! - `fleet/history_30d_step{1,60}s`: `GET /v1/assets/{id}/history` over
//!   30 days;
//! - `fleet/in_memory_30d_1s`: the same points read from a `Vec` in memory
//!   and serialised the same way — the baseline the history is compared to.
//!
//! The store: `FLEET_ASSETS` assets (default 1000) × `FLEET_DAYS` days (30)
//! × `FLEET_HOURS` hours of operation a day (1), one run a day, 1 s points
//! (3600 per asset-day at the default), written once to
//! `target/fleet-bench-<assets>x<days>x<hours>.sqlite` and reused; its size
//! per asset-day is printed. Synthetic data (a falling charge with noise),
//! not the estimator's.

#![allow(missing_docs)]

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use axum::body::{to_bytes, Body};
use axum::http::Request;
use criterion::{criterion_group, criterion_main, Criterion};
use dt_core::estimate::Health;
use dt_core::trend::RunPoint;
use dt_server::server::http::{history_json, router, AppState};
use dt_server::server::metrics::Metrics;
use dt_server::server::state::LiveState;
use dt_server::server::store::{
    rfc3339_ms, FleetStore, HistoryPoint, SqliteStore, StoreOp, Trends,
};
use dt_server::server::Config;
use tokio_util::sync::CancellationToken;
use tower::ServiceExt as _;

const T0_MS: i64 = 1_700_000_000_000;
const DAY_MS: i64 = 86_400_000;

fn env(name: &str, default: i64) -> i64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn asset(i: i64) -> String {
    format!("veh-{i:05}")
}

fn point(a: i64, t_ms: i64, day: i64) -> HistoryPoint {
    let p =
        12.0 - 0.05 * day as f64 * (a % 7) as f64 + 0.1 * ((t_ms / 1000 + a) % 13) as f64 / 13.0;
    HistoryPoint {
        t_ms,
        pressure_bar: Some(p),
        pressure_lo_bar: Some(p - 1.5),
        pressure_hi_bar: Some(p + 1.5),
        health: Health::Ok,
        excited: true,
    }
}

fn populate(path: &std::path::Path, assets: i64, days: i64, hours: i64) {
    let store = SqliteStore::open(path).expect("store");
    let per_day = hours * 3600;
    eprintln!(
        "writing {assets} assets × {days} days × {per_day} points to {}",
        path.display()
    );
    for a in 0..assets {
        let id = asset(a);
        let mut ops = Vec::with_capacity((days * (per_day + 2)) as usize);
        for d in 0..days {
            let start = T0_MS + d * DAY_MS + 8 * 3_600_000;
            let key = format!("{id}-{d}");
            ops.push(StoreOp::RunStarted {
                key: key.clone(),
                asset_id: id.clone(),
                run_id: format!("d{d:03}"),
                source: "bench".into(),
                start_ms: start,
                // the bench's fleet is simulated
                simulated: Some(true),
            });
            for s in 0..per_day {
                ops.push(StoreOp::Sample {
                    asset_id: id.clone(),
                    point: point(a, start + s * 1000, d),
                });
            }
            let p = point(a, start, d).pressure_bar.unwrap_or(12.0);
            ops.push(StoreOp::RunEnded {
                key,
                asset_id: id.clone(),
                end_ms: start + per_day * 1000,
                ticks: (per_day * 50) as u64,
                status: "completed".into(),
                reason: None,
                summary: Some(RunPoint {
                    t_unix_s: (start + per_day * 500) as f64 / 1e3,
                    pressure_bar: p,
                    sd_bar: 0.3,
                }),
                observer: None,
                road: None,
            });
        }
        store.apply(&ops).expect("apply");
        if a % 100 == 99 {
            eprintln!("  {} assets written", a + 1);
        }
    }
}

fn fleet(c: &mut Criterion) {
    let (assets, days, hours) = (
        env("FLEET_ASSETS", 1000),
        env("FLEET_DAYS", 30),
        env("FLEET_HOURS", 1),
    );
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!(
        "../target/fleet-bench-{assets}x{days}x{hours}.sqlite"
    ));
    if !path.exists() {
        let part = path.with_extension("part");
        let _ = std::fs::remove_file(&part);
        populate(&part, assets, days, hours);
        std::fs::rename(&part, &path).expect("rename");
    }
    let bytes = std::fs::metadata(&path).map_or(0, |m| m.len());
    eprintln!(
        "store {}: {:.1} MB, {:.1} kB per asset-day ({} points each)",
        path.display(),
        bytes as f64 / 1e6,
        bytes as f64 / (assets * days) as f64 / 1e3,
        hours * 3600
    );
    let store: Arc<dyn FleetStore> = Arc::new(SqliteStore::open(&path).expect("store"));
    let config = Arc::new(Config::default());
    let metrics = Arc::new(Metrics::new());
    let live = Arc::new(LiveState::new(10, 16));
    live.restore(&store.asset_states().expect("states"), &config);
    let trends = Arc::new(Trends::default());
    for a in 0..assets {
        trends.refresh(store.as_ref(), &config, &metrics, &asset(a));
    }
    let app = router(AppState {
        live,
        store: Some(Arc::clone(&store)),
        trends,
        config,
        metrics,
        ready: Arc::new(AtomicBool::new(true)),
        starting: dt_server::server::source::Starting::default(),
        stop: CancellationToken::new(),
        tokens: Arc::new(dt_server::server::security::Tokens::default()),
        uploads: dt_server::server::http::Uploads::disabled(),
        baselines: Arc::default(),
        model: None,
        group: None,
    });
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let get = |uri: String| {
        let app = app.clone();
        async move {
            let resp = app
                .oneshot(Request::get(uri).body(Body::empty()).expect("request"))
                .await
                .expect("response");
            assert!(resp.status().is_success(), "{}", resp.status());
            to_bytes(resp.into_body(), usize::MAX)
                .await
                .expect("body")
                .len()
        }
    };
    let id = asset(assets / 2);
    let (since, until) = (rfc3339_ms(T0_MS), rfc3339_ms(T0_MS + days * DAY_MS));
    let mut g = c.benchmark_group("fleet");
    g.sample_size(20);
    g.bench_function("assets", |b| {
        b.to_async(&rt).iter(|| get("/v1/assets".into()));
    });
    for step in [1, 60] {
        let uri = format!("/v1/assets/{id}/history?since={since}&until={until}&step_s={step}");
        g.bench_function(format!("history_30d_step{step}s"), |b| {
            b.to_async(&rt).iter(|| get(uri.clone()));
        });
    }
    let points: Vec<HistoryPoint> = store
        .history(&id, (T0_MS, T0_MS + days * DAY_MS), 1000, usize::MAX)
        .expect("history")
        .expect("asset");
    g.bench_function("in_memory_30d_1s", |b| {
        b.iter(|| history_json(&id, 1.0, &points).len());
    });
    g.finish();
}

criterion_group!(benches, fleet);
criterion_main!(benches);
