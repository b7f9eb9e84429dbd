//! Prometheus metrics (`GET /metrics`, `OpenMetrics` text), kept with the
//! `prometheus-client` crate.

use std::collections::HashMap;
use std::sync::atomic::AtomicU64;
use std::sync::{Mutex, PoisonError};
use std::time::{SystemTime, UNIX_EPOCH};

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::Registry;

use dt_core::estimate::Health;

use super::twin::TwinCounters;

/// Label set `{kind="..."}`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct KindLabel {
    /// The kind (error kind, run outcome, ...).
    pub kind: String,
}

/// Label set `{source="tcp"|"inbox"}`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct SourceLabel {
    /// Source kind.
    pub source: String,
}

/// Label set `{asset="..."}`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct AssetLabel {
    /// Asset id.
    pub asset: String,
}

/// Label set `{asset="...", health="ok"|"low"|"leak"|"unknown"}`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct HealthLabel {
    /// Asset id.
    pub asset: String,
    /// One of the four health states (SPEC §6).
    pub health: String,
}

/// Bucket bounds of `shocktwin_estimate_delay_seconds`, s: 0.1 ms to 5 s,
/// with the 50 ms target of the load test on a bound.
pub const DELAY_BUCKETS_S: [f64; 15] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0,
];

fn delay_histogram() -> Histogram {
    Histogram::new(DELAY_BUCKETS_S)
}

/// Every metric the daemon exports (names get the `shocktwin_` prefix;
/// counters also get `_total`).
#[derive(Debug)]
pub struct Metrics {
    registry: Registry,
    /// Sensor samples decoded, by source.
    pub messages: Family<SourceLabel, Counter>,
    /// Messages on topics the format does not know (ignored).
    pub unknown_messages: Counter,
    /// Estimates (50 Hz ticks) emitted.
    pub ticks: Family<AssetLabel, Counter>,
    /// Errors, by kind (`not_mcap`, `truncated`, `too_large`, `schema`, ...).
    pub errors: Family<KindLabel, Counter>,
    /// Ingest connections open now.
    pub connections_active: Gauge,
    /// Ingest connections accepted.
    pub connections: Counter,
    /// Runs ended, by outcome (`completed`, `failed`, `interrupted`).
    pub runs: Family<KindLabel, Counter>,
    /// Inbox files moved, by destination (`done`, `failed`).
    pub files: Family<KindLabel, Counter>,
    /// Input anomalies the twins counted (`nan_samples`, `out_of_order`,
    /// `dropped_late`, `clock_jumps`, `timestamp_outliers`, `ticks_without_inputs`).
    pub input: Family<KindLabel, Counter>,
    /// The charge observer's velocity reversals, by what became of them
    /// (`used`, `spared`, `skipped`, `rejected`, `uncalibrated`: at an
    /// excitation the calibration does not cover), counted when a run ends.
    pub observer_reversals: Family<KindLabel, Counter>,
    /// Per asset: now − time of the last sample processed, s.
    pub asset_lag_seconds: Family<AssetLabel, Gauge<f64, AtomicU64>>,
    /// Per asset, one observation per estimate: wall time from the arrival
    /// of the bytes holding the sample that completed its tick (the socket
    /// or file read that returned them) until every sink has taken the
    /// estimate, s. Time the bytes spent in the kernel's socket buffer
    /// before that read is not seen here (see `asset_lag_seconds`).
    pub estimate_delay_seconds: Family<AssetLabel, Histogram, fn() -> Histogram>,
    /// Per asset: leak rate from the trend, bar/day (absent: no trend).
    pub leak_rate_bar_per_day: Family<AssetLabel, Gauge<f64, AtomicU64>>,
    /// Per asset: days from its newest run to the predicted fault crossing.
    pub days_to_fault: Family<AssetLabel, Gauge<f64, AtomicU64>>,
    /// Per asset and health state: 1 for the asset's health now, 0 for
    /// the other three (a state set, so that an alert can fire on `leak`).
    pub asset_health: Family<HealthLabel, Gauge>,
    /// Per asset: the charge shown now (the 1 s average), bar gauge.
    pub asset_pressure_bar: Family<AssetLabel, Gauge<f64, AtomicU64>>,
    /// Per asset: `log_time` of the newest sample processed, and when (wall clock).
    last_sample_ns: Mutex<HashMap<String, (i64, SystemTime)>>,
    /// One scrape at a time sets the per-asset states and encodes them.
    scrape: Mutex<()>,
}

/// An asset that has sent nothing for this long (wall clock) loses its
/// per-asset series (`asset_lag_seconds`, `estimate_delay_seconds`) at the
/// next scrape, so that a gateway serving a changing fleet for months does
/// not keep a series per vehicle it ever saw. They come back with its next run.
pub const ASSET_IDLE_EVICT: std::time::Duration = std::time::Duration::from_secs(3600);

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// Registers every metric.
    #[must_use]
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("shocktwin");
        let m = Self {
            registry: Registry::default(),
            messages: Family::default(),
            unknown_messages: Counter::default(),
            ticks: Family::default(),
            errors: Family::default(),
            connections_active: Gauge::default(),
            connections: Counter::default(),
            runs: Family::default(),
            files: Family::default(),
            input: Family::default(),
            observer_reversals: Family::default(),
            asset_lag_seconds: Family::default(),
            estimate_delay_seconds: Family::new_with_constructor(delay_histogram),
            leak_rate_bar_per_day: Family::default(),
            days_to_fault: Family::default(),
            asset_health: Family::default(),
            asset_pressure_bar: Family::default(),
            last_sample_ns: Mutex::new(HashMap::new()),
            scrape: Mutex::new(()),
        };
        registry.register("messages", "Sensor samples decoded", m.messages.clone());
        registry.register(
            "unknown_messages",
            "Messages on unknown topics (ignored)",
            m.unknown_messages.clone(),
        );
        registry.register("ticks", "Estimates emitted (50 Hz ticks)", m.ticks.clone());
        registry.register("errors", "Errors by kind", m.errors.clone());
        registry.register(
            "connections_active",
            "Ingest connections open",
            m.connections_active.clone(),
        );
        registry.register(
            "connections",
            "Ingest connections accepted",
            m.connections.clone(),
        );
        registry.register("runs", "Runs ended, by outcome", m.runs.clone());
        registry.register(
            "inbox_files",
            "Inbox files moved, by destination",
            m.files.clone(),
        );
        registry.register(
            "input_anomalies",
            "Input anomalies counted by the twins",
            m.input.clone(),
        );
        registry.register(
            "observer_reversals",
            "The charge observer's velocity reversals by what became of them, counted at the end of each run",
            m.observer_reversals.clone(),
        );
        registry.register(
            "asset_lag_seconds",
            "Wall-clock now minus the time of the last sample processed, per asset",
            m.asset_lag_seconds.clone(),
        );
        registry.register(
            "estimate_delay_seconds",
            "Wall time from the arrival of the sample that completed a tick to its estimate \
             being taken by every sink, per asset",
            m.estimate_delay_seconds.clone(),
        );
        registry.register(
            "leak_rate_bar_per_day",
            "Charge lost per day from the asset's trend over its runs",
            m.leak_rate_bar_per_day.clone(),
        );
        registry.register(
            "days_to_fault",
            "Days from the asset's newest run to the predicted crossing of its fault threshold",
            m.days_to_fault.clone(),
        );
        registry.register(
            "asset_health",
            "1 for the asset's health now (ok, low, leak, unknown), 0 for the other states",
            m.asset_health.clone(),
        );
        registry.register(
            "asset_pressure_bar",
            "The asset's charge now (its 1 s average), bar gauge; absent while it has none",
            m.asset_pressure_bar.clone(),
        );
        Self { registry, ..m }
    }

    /// Publishes an asset's trend (a `None` removes the series).
    pub fn set_trend(&self, asset: &str, leak_rate: Option<f64>, days_to_fault: Option<f64>) {
        let label = AssetLabel {
            asset: asset.to_owned(),
        };
        for (family, value) in [
            (&self.leak_rate_bar_per_day, leak_rate),
            (&self.days_to_fault, days_to_fault),
        ] {
            match value {
                Some(v) => {
                    family.get_or_create(&label).set(v);
                }
                None => {
                    family.remove(&label);
                }
            }
        }
    }

    /// [`Metrics::encode`], with the assets' health and charge now (from
    /// the live view; an asset no longer in it loses its series).
    pub fn encode_with_assets<'a>(
        &self,
        now: SystemTime,
        assets: impl IntoIterator<Item = (&'a str, Health, Option<f64>)>,
    ) -> String {
        let _one = self.scrape.lock().unwrap_or_else(PoisonError::into_inner);
        self.set_assets(assets);
        self.encode(now)
    }

    fn set_assets<'a>(&self, assets: impl IntoIterator<Item = (&'a str, Health, Option<f64>)>) {
        self.asset_health.clear();
        self.asset_pressure_bar.clear();
        for (asset, health, pressure) in assets {
            for state in [Health::Ok, Health::Low, Health::Leak, Health::Unknown] {
                self.asset_health
                    .get_or_create(&HealthLabel {
                        asset: asset.to_owned(),
                        health: state.as_str().to_owned(),
                    })
                    .set(i64::from(state == health));
            }
            if let Some(p) = pressure.filter(|p| p.is_finite()) {
                self.asset_pressure_bar
                    .get_or_create(&AssetLabel {
                        asset: asset.to_owned(),
                    })
                    .set(p);
            }
        }
    }

    /// Counts one error of `kind`.
    pub fn error(&self, kind: &str) {
        self.errors
            .get_or_create(&KindLabel {
                kind: kind.to_owned(),
            })
            .inc();
    }

    /// Adds `n` to a `{kind}` family.
    pub fn add(family: &Family<KindLabel, Counter>, kind: &str, n: u64) {
        if n > 0 {
            family
                .get_or_create(&KindLabel {
                    kind: kind.to_owned(),
                })
                .inc_by(n);
        }
    }

    /// Adds a finished run's twin counters.
    pub fn add_twin_counters(&self, c: &TwinCounters) {
        Self::add(&self.input, "nan_samples", c.nan_samples);
        Self::add(&self.input, "out_of_order", c.out_of_order);
        Self::add(&self.input, "dropped_late", c.dropped_late);
        Self::add(&self.input, "clock_jumps", c.clock_jumps);
        Self::add(&self.input, "timestamp_outliers", c.timestamp_outliers);
        Self::add(&self.input, "ticks_without_inputs", c.ticks_without_inputs);
        if let Some(o) = c.observer.filter(|o| o.detected > 0) {
            Self::add(&self.observer_reversals, "used", o.used);
            Self::add(&self.observer_reversals, "spared", o.spared);
            Self::add(&self.observer_reversals, "skipped", o.skipped);
            Self::add(&self.observer_reversals, "rejected", o.rejected);
            Self::add(&self.observer_reversals, "uncalibrated", o.uncalibrated);
        }
    }

    /// Counts `n` estimates of `asset` that took `delay_s` from arrival to the sinks.
    pub fn observe_delay(&self, asset: &AssetLabel, delay_s: f64, n: usize) {
        let h = self.estimate_delay_seconds.get_or_create(asset);
        for _ in 0..n {
            h.observe(delay_s);
        }
    }

    /// Records the time of the last sample processed for `asset`.
    pub fn set_last_sample(&self, asset: &str, t_ns: i64) {
        self.set_last_sample_at(asset, t_ns, SystemTime::now());
    }

    fn set_last_sample_at(&self, asset: &str, t_ns: i64, wall: SystemTime) {
        let mut map = self
            .last_sample_ns
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        match map.get_mut(asset) {
            Some(v) => *v = (t_ns, wall),
            None => {
                map.insert(asset.to_owned(), (t_ns, wall));
            }
        }
    }

    /// `OpenMetrics` text of every metric, lags computed against `now`.
    #[must_use]
    pub fn encode(&self, now: SystemTime) -> String {
        let now_ns = now
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX));
        {
            let mut map = self
                .last_sample_ns
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            map.retain(|asset, &mut (t_ns, wall)| {
                let label = AssetLabel {
                    asset: asset.clone(),
                };
                if now.duration_since(wall).unwrap_or_default() > ASSET_IDLE_EVICT {
                    self.asset_lag_seconds.remove(&label);
                    self.estimate_delay_seconds.remove(&label);
                    return false;
                }
                let lag_s = now_ns.saturating_sub(t_ns) as f64 * 1e-9;
                self.asset_lag_seconds.get_or_create(&label).set(lag_s);
                true
            });
        }
        let mut text = String::new();
        if let Err(e) = prometheus_client::encoding::text::encode(&mut text, &self.registry) {
            tracing::error!("cannot encode the metrics: {e}");
        }
        text
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[test]
    fn idle_assets_lose_their_series_and_get_them_back_when_they_return() {
        let m = Metrics::new();
        let t0 = UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let t_ns = 1_700_000_000_000_000_000;
        for asset in ["car-1", "car-2"] {
            m.set_last_sample_at(asset, t_ns, t0);
            m.observe_delay(
                &AssetLabel {
                    asset: asset.into(),
                },
                0.001,
                3,
            );
        }
        let text = m.encode(t0 + Duration::from_secs(10));
        assert!(text.contains("asset=\"car-1\"") && text.contains("asset=\"car-2\""));
        // car-2 keeps sending; car-1 goes quiet for longer than the horizon.
        let later = t0 + ASSET_IDLE_EVICT + Duration::from_secs(60);
        m.set_last_sample_at("car-2", t_ns, later);
        let text = m.encode(later);
        assert!(!text.contains("asset=\"car-1\""), "{text}");
        assert!(text.contains("shocktwin_estimate_delay_seconds_count{asset=\"car-2\"} 3"));
        m.set_last_sample_at("car-1", t_ns, later);
        assert!(m
            .encode(later)
            .contains("shocktwin_asset_lag_seconds{asset=\"car-1\"}"));
    }
}
