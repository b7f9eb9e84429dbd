//! Unit baselines a maintainer sets over the API after a service
//! (`PUT /v1/assets/{id}/baseline`), kept in the fleet store.
//!
//! A baseline is one reading of the charge observer at a known charge
//! ([`UnitBaseline`], `dt_core::charge`): it conditions the unit's own offset
//! and gain, which narrows every later interval of that asset. An asset's
//! baseline is, in order: the one set over the API (kept in the store,
//! restored at start-up), else `[assets.<id>] observer_baseline` in the
//! configuration, else none. A run takes the baseline in effect when it
//! starts; runs in progress keep theirs. An API baseline also restarts the
//! asset's leak trend: it is fitted on the runs that started after it.
//!
//! A maintainer who knows the charge the unit was filled to, but not what the
//! observer reads of it, reports the service instead
//! (`PUT /v1/assets/{id}/service`, `{"charge_bar": …}`): the service is kept
//! in the store as pending, the asset's trend restarts at it, and the asset's
//! runs that start after it run without a baseline while the daemon reads the
//! unit ([`dt_core::service::ServiceReading`]). A run recorded before the
//! service (`at` in the request, default now) is not read. The first run that
//! ends with a usable reading completes it: the reading becomes the asset's API
//! baseline (set at the service's time) and the service is forgotten, in one
//! store transaction. A run that gives none (no excitation, an excitation the
//! observer is not calibrated at, one with a model of its own) leaves it
//! pending, with the reason kept for `GET …/service`.
//!
//! In a NATS group (`serve --nats`) the group's key-value bucket
//! `shocktwin_baselines` holds them instead: a `PUT` on any daemon writes
//! there, and every daemon of the group (workers and fleet views) applies
//! what the bucket holds to its own copy and store ([`crate::nats::baselines`]),
//! so whichever worker takes the asset's next run uses it.

use std::collections::HashMap;
use std::sync::{PoisonError, RwLock};

use serde::Serialize;

use super::config::{AssetConfig, Config, ServiceToRead};
use super::store::{
    rfc3339_ms, AssetBaseline, CalendarClock, FleetStore, PendingService, StoreError,
    StoredBaseline, Trends,
};

/// Where an asset's baseline comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BaselineSource {
    /// Set over the API, kept in the fleet store.
    Api,
    /// `[assets.<id>] observer_baseline`.
    Config,
}

/// An asset's baseline in effect, as the API shows it: `kind` `observer`
/// carries `read_bar` and `read_sd_bar` ([`dt_core::charge::UnitBaseline`]), `road` carries
/// `offset_n` and `blocks` ([`dt_core::road::RoadBaseline`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BaselineView {
    /// The charge the unit held, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// `observer` (the dyno observer's) or `road` (the road observer's).
    pub kind: &'static str,
    /// What the observer read meanwhile, bar.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub read_bar: Option<f64>,
    /// That reading's standard deviation, bar.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub read_sd_bar: Option<f64>,
    /// The `|ÿ_r|` range the reading's reversals spanned, m/s²
    /// (`null`: unknown).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_range_mps2: Option<[f64; 2]>,
    /// Whether the unit is read with its own damping law
    /// ([`dt_core::charge::UnitBaseline::damping_law`]) instead of the
    /// calibration's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub own_damping_law: Option<bool>,
    /// A second reading at another known charge
    /// ([`dt_core::charge::UnitBaseline::second`]), when the baseline has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub second: Option<dt_core::charge::BaselineReading>,
    /// How many runs the (first) reading averages
    /// ([`dt_core::charge::UnitBaseline::runs_averaged`]), when more than one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub runs_averaged: Option<f64>,
    /// The stroke's ends apart at the reading, bar
    /// ([`dt_core::charge::UnitBaseline::split_bar`]), when read.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub split_bar: Option<f64>,
    /// The unit's readings at other excitations
    /// ([`dt_core::charge::UnitBaseline::other_excitations`]), when it has
    /// any: a run is corrected by the one nearest its excitation.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub other_excitations: Vec<dt_core::charge::ExcitationBaseline>,
    /// The unit's seal friction offset from the road calibration's, N.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub offset_n: Option<f64>,
    /// Blocks of drive the road baseline read.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub blocks: Option<u64>,
    /// `api` or `config`.
    pub source: BaselineSource,
    /// When it was set over the API (RFC 3339), `null` for `config`.
    pub set_at: Option<String>,
}

impl BaselineView {
    /// A baseline set over the API (or read after a service) at `set_ms`.
    #[must_use]
    pub fn api(b: AssetBaseline, set_ms: i64) -> Self {
        Self::of(&b, BaselineSource::Api, Some(rfc3339_ms(set_ms)))
    }

    /// A baseline from the configuration.
    #[must_use]
    pub fn config(b: AssetBaseline) -> Self {
        Self::of(&b, BaselineSource::Config, None)
    }

    fn of(b: &AssetBaseline, source: BaselineSource, set_at: Option<String>) -> Self {
        let (read, road) = match *b {
            AssetBaseline::Observer(u) => (Some(u), None),
            AssetBaseline::Road(r) => (None, Some(r)),
        };
        Self {
            charge_bar: b.charge_bar(),
            kind: b.kind(),
            read_bar: read.map(|u| u.read_bar),
            read_sd_bar: read.map(|u| u.read_sd_bar),
            accel_range_mps2: read.and_then(|u| u.accel_range_mps2),
            own_damping_law: read.map(|u| u.damping_law.is_some()),
            second: read.and_then(|u| u.second),
            runs_averaged: read.map(|u| u.runs_averaged).filter(|&n| n > 1.0),
            split_bar: read.and_then(|u| u.split_bar),
            other_excitations: read
                .map(|u| u.other_excitations.iter().flatten().copied().collect())
                .unwrap_or_default(),
            offset_n: road.map(|r| r.offset_n),
            blocks: road.map(|r| r.blocks),
            source,
            set_at,
        }
    }
}

/// A pending service, as the API shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ServiceView {
    /// The charge the unit was filled to, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// When the unit was serviced (RFC 3339).
    pub set_at: String,
    /// `pending`: the baseline is read from the asset's next run.
    pub state: &'static str,
    /// Why the last run after it gave no baseline, or `null`.
    pub last_refusal: Option<String>,
}

impl From<&PendingService> for ServiceView {
    fn from(s: &PendingService) -> Self {
        Self {
            charge_bar: s.charge_bar,
            set_at: rfc3339_ms(s.set_ms),
            state: "pending",
            last_refusal: s.refusal.clone(),
        }
    }
}

/// What a run made of a pending service.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServiceOutcome {
    /// The run's reading became the asset's baseline.
    Completed,
    /// The run gave no baseline; the service stays pending.
    StillPending,
    /// The service the run read for was replaced or withdrawn meanwhile.
    Superseded,
}

/// Why a run whose first sample is at `first_t_ns` (started processing at
/// `started`) cannot be read for `service`: it was recorded before the
/// service (a backlog uploaded late), as the store places it in calendar
/// time ([`CalendarClock`]); `None` when it can.
#[must_use]
pub fn recorded_before(
    run_id: &str,
    first_t_ns: Option<i64>,
    started: std::time::SystemTime,
    service: ServiceToRead,
) -> Option<String> {
    let t = first_t_ns?;
    let start_ms = CalendarClock::new(t, started).ms(t);
    (start_ms < service.set_ms).then(|| {
        format!(
            "run `{run_id}` was recorded at {}, before the service at {}: it does not show the \
             unit at the service's charge",
            rfc3339_ms(start_ms),
            rfc3339_ms(service.set_ms)
        )
    })
}

/// The baselines set over the API and the pending services, by asset (a
/// copy of the store's tables).
#[derive(Debug, Default)]
pub struct Baselines {
    by_asset: RwLock<HashMap<String, StoredBaseline>>,
    services: RwLock<HashMap<String, PendingService>>,
}

/// Keeps (`Some`) or forgets (`None`) the asset's entry in `map`.
fn put<T>(map: &RwLock<HashMap<String, T>>, asset_id: &str, value: Option<T>) {
    let mut map = map.write().unwrap_or_else(PoisonError::into_inner);
    match value {
        Some(v) => map.insert(asset_id.to_owned(), v),
        None => map.remove(asset_id),
    };
}

impl Baselines {
    /// The baselines and pending services `store` keeps.
    pub fn load(store: &dyn FleetStore) -> Result<Self, StoreError> {
        Ok(Self {
            by_asset: RwLock::new(store.baselines()?.into_iter().collect()),
            services: RwLock::new(store.services()?.into_iter().collect()),
        })
    }

    /// Every asset's trend starts at its API baseline or its pending
    /// service, the later of the two (see [`Trends::set_since`]).
    pub fn restart_trends(&self, trends: &Trends) {
        let assets: Vec<String> = {
            let by_asset = self.by_asset.read().unwrap_or_else(PoisonError::into_inner);
            let services = self.services.read().unwrap_or_else(PoisonError::into_inner);
            by_asset.keys().chain(services.keys()).cloned().collect()
        };
        for asset in assets {
            trends.set_since(&asset, self.trend_start(&asset));
        }
    }

    /// Where the asset's trend starts, ms: at its API baseline or its
    /// pending service, the later of the two; `None` (every run) with
    /// neither. The one rule for a restart and for every change over the API,
    /// so that a trend reads the same before and after a restart.
    fn trend_start(&self, asset_id: &str) -> Option<i64> {
        let baseline = self
            .by_asset
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .map(|b| b.set_ms);
        let service = self
            .services
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .map(|s| s.set_ms);
        baseline.max(service)
    }

    /// Reports (`Some`) or withdraws (`None`) a service of the asset: in the
    /// store first, then here; the asset's trend then starts where
    /// [`Self::trend_start`] says (a reported service restarts it at the
    /// service, unless an API baseline is later).
    pub fn set_service(
        &self,
        store: Option<&dyn FleetStore>,
        trends: &Trends,
        asset_id: &str,
        service: Option<PendingService>,
    ) -> Result<(), StoreError> {
        if let Some(store) = store {
            store.set_service(asset_id, service.as_ref())?;
        }
        put(&self.services, asset_id, service);
        trends.set_since(asset_id, self.trend_start(asset_id));
        Ok(())
    }

    /// The asset's pending service, if any.
    #[must_use]
    pub fn service(&self, asset_id: &str) -> Option<PendingService> {
        self.services
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .cloned()
    }

    /// What a run that read the unit for `service` gives it: the baseline
    /// (kept as the asset's API baseline, set at the service's time, and the
    /// service forgotten) or why not (kept with the service). A service
    /// replaced or withdrawn since the run started is left alone.
    pub fn complete_service(
        &self,
        store: &dyn FleetStore,
        asset_id: &str,
        service: ServiceToRead,
        read: Result<AssetBaseline, String>,
    ) -> Result<ServiceOutcome, StoreError> {
        let mut services = self
            .services
            .write()
            .unwrap_or_else(PoisonError::into_inner);
        let Some(pending) = services
            .get_mut(asset_id)
            .filter(|p| p.set_ms == service.set_ms)
        else {
            return Ok(ServiceOutcome::Superseded);
        };
        match read {
            Ok(baseline) => {
                let stored = StoredBaseline {
                    baseline,
                    set_ms: service.set_ms,
                };
                store.complete_service(asset_id, &stored)?;
                services.remove(asset_id);
                self.by_asset
                    .write()
                    .unwrap_or_else(PoisonError::into_inner)
                    .insert(asset_id.to_owned(), stored);
                Ok(ServiceOutcome::Completed)
            }
            Err(why) => {
                let mut kept = pending.clone();
                kept.refusal = Some(why);
                store.set_service(asset_id, Some(&kept))?;
                *pending = kept;
                Ok(ServiceOutcome::StillPending)
            }
        }
    }

    /// Sets (`Some`) or removes (`None`) the asset's API baseline: in the
    /// store first, if the daemon keeps one, so that what the daemon uses is
    /// always what it would restore; the asset's trend then starts where
    /// [`Self::trend_start`] says (at the baseline, or at a later pending
    /// service, or spans every run again).
    pub fn set(
        &self,
        store: Option<&dyn FleetStore>,
        trends: &Trends,
        asset_id: &str,
        baseline: Option<StoredBaseline>,
    ) -> Result<(), StoreError> {
        if let Some(store) = store {
            store.set_baseline(asset_id, baseline.as_ref())?;
        }
        put(&self.by_asset, asset_id, baseline);
        trends.set_since(asset_id, self.trend_start(asset_id));
        Ok(())
    }

    /// The asset's API baseline, if any.
    #[must_use]
    pub fn get(&self, asset_id: &str) -> Option<StoredBaseline> {
        self.by_asset
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .get(asset_id)
            .copied()
    }

    /// The asset's configuration with the baseline in effect (see the
    /// module doc): while a service is pending, none, and the service to
    /// read. A stored baseline of the other kind than the asset's (a road
    /// baseline on an asset no longer driven on roads, or the reverse) is
    /// not applied.
    #[must_use]
    pub fn asset_config(&self, config: &Config, asset_id: &str) -> AssetConfig {
        let mut asset = config.asset(asset_id);
        if let Some(s) = self.service(asset_id) {
            // the unit's own law, if the baseline it had before carried one
            let before = match self.get(asset_id).map(|b| b.baseline) {
                Some(AssetBaseline::Observer(u)) => Some(u),
                _ => asset.observer_baseline,
            };
            asset.observer_baseline = None;
            asset.road_baseline = None;
            asset.read_service = Some(ServiceToRead {
                charge_bar: s.charge_bar,
                set_ms: s.set_ms,
                earlier: before.filter(|_| !asset.road),
            });
        } else if let Some(b) = self.get(asset_id) {
            match b.baseline {
                AssetBaseline::Observer(u) if !asset.road => asset.observer_baseline = Some(u),
                AssetBaseline::Road(r) if asset.road => asset.road_baseline = Some(r),
                _ => {}
            }
        }
        asset
    }

    /// The asset's baseline in effect, for the API (none while a service is
    /// pending).
    #[must_use]
    pub fn view(&self, config: &Config, asset_id: &str) -> Option<BaselineView> {
        let asset = self.asset_config(config, asset_id);
        if asset.read_service.is_some() {
            return None;
        }
        let in_effect = match (asset.road_baseline, asset.observer_baseline) {
            (Some(r), _) if asset.road => AssetBaseline::Road(r),
            (_, Some(u)) if !asset.road => AssetBaseline::Observer(u),
            _ => return None,
        };
        Some(match self.get(asset_id) {
            Some(b) if b.baseline == in_effect => BaselineView::api(b.baseline, b.set_ms),
            _ => BaselineView::config(in_effect),
        })
    }
}

#[cfg(test)]
mod tests {
    use dt_core::charge::{DampingLaw, UnitBaseline};

    use super::*;
    use crate::server::config::AssetOverrides;
    use crate::server::store::SqliteStore;

    /// The trend starts at the later of the API baseline and the pending
    /// service after every change over the API, as it does after a restart:
    /// withdrawing either falls back to the other, never to a withdrawn one.
    #[test]
    fn a_trend_starts_where_a_restart_would_start_it_after_every_change() {
        let dir = tempfile::tempdir().unwrap();
        let store = SqliteStore::open(&dir.path().join("fleet.sqlite")).unwrap();
        let (baselines, trends) = (Baselines::default(), Trends::default());
        let restarted = || {
            let trends = Trends::default();
            Baselines::load(&store).unwrap().restart_trends(&trends);
            trends.since("van")
        };
        let baseline = |set_ms| StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                charge_bar: 12.0,
                read_bar: 11.5,
                read_sd_bar: 0.4,
                accel_range_mps2: None,
                damping_law: None,
                second: None,
                runs_averaged: 1.0,
                split_bar: None,
                other_excitations: Default::default(),
            }),
            set_ms,
        };
        let service = |set_ms| PendingService {
            charge_bar: 12.0,
            set_ms,
            refusal: None,
        };
        let steps: [(&str, Option<i64>); 6] = [
            ("baseline at 9 s", Some(9_000)),
            ("a service reported earlier, at 5 s", Some(9_000)),
            ("the baseline withdrawn", Some(5_000)),
            ("the service withdrawn", None),
            ("a service at 7 s", Some(7_000)),
            ("a baseline at 3 s", Some(7_000)),
        ];
        for (i, (what, want)) in steps.into_iter().enumerate() {
            let s = Some(&store as &dyn FleetStore);
            match i {
                0 => baselines.set(s, &trends, "van", Some(baseline(9_000))),
                1 => baselines.set_service(s, &trends, "van", Some(service(5_000))),
                2 => baselines.set(s, &trends, "van", None),
                3 => baselines.set_service(s, &trends, "van", None),
                4 => baselines.set_service(s, &trends, "van", Some(service(7_000))),
                _ => baselines.set(s, &trends, "van", Some(baseline(3_000))),
            }
            .unwrap();
            assert_eq!(trends.since("van"), want, "{what}");
            assert_eq!(restarted(), want, "{what}, after a restart");
        }
    }

    #[test]
    fn a_service_is_completed_once_by_its_own_run_and_a_refusal_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.sqlite");
        let store = SqliteStore::open(&path).unwrap();
        let (baselines, trends, config) =
            (Baselines::default(), Trends::default(), Config::default());
        let old = StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                charge_bar: 12.0,
                read_bar: 10.0,
                read_sd_bar: 0.5,
                accel_range_mps2: None,
                damping_law: Some(unit_law()),
                second: None,
                runs_averaged: 1.0,
                split_bar: None,
                other_excitations: Default::default(),
            }),
            set_ms: 1_000,
        };
        baselines
            .set(Some(&store), &trends, "van", Some(old))
            .unwrap();
        assert_eq!(
            baselines.asset_config(&config, "van").observer_baseline,
            Some(read_of(&old))
        );
        let service = PendingService {
            charge_bar: 11.0,
            set_ms: 5_000,
            refusal: None,
        };
        baselines
            .set_service(Some(&store), &trends, "van", Some(service.clone()))
            .unwrap();
        // While it is pending the asset's runs use no baseline and read this one.
        let asset = baselines.asset_config(&config, "van");
        assert_eq!(asset.observer_baseline, None);
        let to_read = asset.read_service.unwrap();
        assert_eq!(
            to_read,
            ServiceToRead {
                charge_bar: 11.0,
                set_ms: 5_000,
                // the unit is read with the law its baseline had (a recharge
                // does not change its valves), and its readings elsewhere kept
                earlier: Some(read_of(&old)),
            }
        );
        assert_eq!(to_read.damping_law(), Some(unit_law()));
        assert_eq!(baselines.view(&config, "van"), None);
        // A run that read for an earlier service changes nothing.
        let stale = ServiceToRead {
            set_ms: 4_000,
            ..to_read
        };
        let read = UnitBaseline {
            charge_bar: 11.0,
            read_bar: 9.4,
            read_sd_bar: 0.3,
            accel_range_mps2: Some([1.4, 1.6]),
            damping_law: None,
            ..read_of(&old)
        };
        assert_eq!(
            baselines
                .complete_service(&store, "van", stale, Ok(AssetBaseline::Observer(read)))
                .unwrap(),
            ServiceOutcome::Superseded
        );
        assert_eq!(
            baselines
                .complete_service(&store, "van", to_read, Err("not excited".into()))
                .unwrap(),
            ServiceOutcome::StillPending
        );
        let kept = Baselines::load(&store).unwrap();
        assert_eq!(
            kept.service("van").unwrap().refusal.as_deref(),
            Some("not excited")
        );
        assert_eq!(kept.get("van"), Some(old));
        assert_eq!(
            baselines
                .complete_service(&store, "van", to_read, Ok(AssetBaseline::Observer(read)))
                .unwrap(),
            ServiceOutcome::Completed
        );
        let done = StoredBaseline {
            baseline: AssetBaseline::Observer(read),
            set_ms: 5_000,
        };
        for b in [&baselines, &Baselines::load(&store).unwrap()] {
            assert_eq!(b.service("van"), None);
            assert_eq!(b.get("van"), Some(done));
            assert_eq!(b.asset_config(&config, "van").observer_baseline, Some(read));
        }
        assert_eq!(
            baselines
                .complete_service(&store, "van", to_read, Ok(AssetBaseline::Observer(read)))
                .unwrap(),
            ServiceOutcome::Superseded
        );
    }

    /// A unit's own damping law (its numbers do not matter here).
    fn unit_law() -> DampingLaw {
        DampingLaw {
            width_mps: 0.008,
            beta_per_k: 0.03,
            ..DampingLaw::default()
        }
    }

    #[test]
    fn a_service_reads_the_unit_with_the_law_of_the_baseline_in_effect_before_it() {
        let (baselines, trends) = (Baselines::default(), Trends::default());
        let from_config = UnitBaseline {
            charge_bar: 12.0,
            read_bar: 11.0,
            read_sd_bar: 0.2,
            accel_range_mps2: None,
            damping_law: Some(unit_law()),
            second: None,
            runs_averaged: 1.0,
            split_bar: None,
            other_excitations: Default::default(),
        };
        let mut config = Config::default();
        for (id, road) in [("van", false), ("car", true)] {
            config.assets.insert(
                id.into(),
                AssetOverrides {
                    observer_baseline: Some(from_config),
                    road: Some(road),
                    ..AssetOverrides::default()
                },
            );
        }
        let service = PendingService {
            charge_bar: 12.0,
            set_ms: 5_000,
            refusal: None,
        };
        for id in ["van", "car", "bus"] {
            baselines
                .set_service(None, &trends, id, Some(service.clone()))
                .unwrap();
        }
        let law_of = |id: &str| {
            baselines
                .asset_config(&config, id)
                .read_service
                .unwrap()
                .damping_law()
        };
        // the configuration's baseline, when none was set over the API; none
        // for a road asset (the road observer has no damping law) or a unit
        // without a law
        assert_eq!(law_of("van"), Some(unit_law()));
        assert_eq!(law_of("car"), None);
        assert_eq!(law_of("bus"), None);
        // an API baseline takes the configuration's place, law or none
        let api = StoredBaseline {
            baseline: AssetBaseline::Observer(UnitBaseline {
                damping_law: None,
                ..from_config
            }),
            set_ms: 1_000,
        };
        baselines.set(None, &trends, "van", Some(api)).unwrap();
        assert_eq!(law_of("van"), None);
    }

    fn read_of(b: &StoredBaseline) -> UnitBaseline {
        match b.baseline {
            AssetBaseline::Observer(u) => u,
            AssetBaseline::Road(_) => panic!("not an observer baseline"),
        }
    }
}
