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
//! In a NATS group (`serve --nats`) the group's key-value bucket
//! `shocktwin_baselines` holds them instead: a `PUT` on any daemon writes
//! there, and every daemon of the group (workers and fleet views) applies
//! what the bucket holds to its own copy and store ([`crate::nats::baselines`]),
//! so whichever worker takes the asset's next run uses it.

use std::collections::HashMap;
use std::sync::{PoisonError, RwLock};

use dt_core::charge::UnitBaseline;
use serde::Serialize;

use super::config::{AssetConfig, Config};
use super::store::{rfc3339_ms, FleetStore, StoreError, StoredBaseline, Trends};

/// Where an asset's baseline comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BaselineSource {
    /// Set over the API, kept in the fleet store.
    Api,
    /// `[assets.<id>] observer_baseline`.
    Config,
}

/// An asset's baseline in effect, as the API shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BaselineView {
    /// The charge the unit held, bar gauge at 20 °C.
    pub charge_bar: f64,
    /// What the observer read meanwhile, bar.
    pub read_bar: f64,
    /// That reading's standard deviation, bar.
    pub read_sd_bar: f64,
    /// `api` or `config`.
    pub source: BaselineSource,
    /// When it was set over the API (RFC 3339), `null` for `config`.
    pub set_at: Option<String>,
}

impl BaselineView {
    /// A baseline set over the API at `set_ms`.
    #[must_use]
    pub fn api(b: UnitBaseline, set_ms: i64) -> Self {
        Self::of(b, BaselineSource::Api, Some(rfc3339_ms(set_ms)))
    }

    /// A baseline from the configuration.
    #[must_use]
    pub fn config(b: UnitBaseline) -> Self {
        Self::of(b, BaselineSource::Config, None)
    }

    fn of(b: UnitBaseline, source: BaselineSource, set_at: Option<String>) -> Self {
        Self {
            charge_bar: b.charge_bar,
            read_bar: b.read_bar,
            read_sd_bar: b.read_sd_bar,
            source,
            set_at,
        }
    }
}

/// The baselines set over the API, by asset (a copy of the store's table).
#[derive(Debug, Default)]
pub struct Baselines {
    by_asset: RwLock<HashMap<String, StoredBaseline>>,
}

impl Baselines {
    /// The baselines `store` keeps.
    pub fn load(store: &dyn FleetStore) -> Result<Self, StoreError> {
        Ok(Self {
            by_asset: RwLock::new(store.baselines()?.into_iter().collect()),
        })
    }

    /// Every asset's trend starts at its API baseline (see
    /// [`Trends::set_since`]).
    pub fn restart_trends(&self, trends: &Trends) {
        for (asset, b) in self
            .by_asset
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
        {
            trends.set_since(asset, Some(b.set_ms));
        }
    }

    /// Sets (`Some`) or removes (`None`) the asset's API baseline: in the
    /// store first, if the daemon keeps one, so that what the daemon uses is
    /// always what it would restore; the asset's trend then starts at the
    /// baseline (or spans every run again).
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
        trends.set_since(asset_id, baseline.map(|b| b.set_ms));
        let mut map = self
            .by_asset
            .write()
            .unwrap_or_else(PoisonError::into_inner);
        match baseline {
            Some(b) => map.insert(asset_id.to_owned(), b),
            None => map.remove(asset_id),
        };
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
    /// module doc).
    #[must_use]
    pub fn asset_config(&self, config: &Config, asset_id: &str) -> AssetConfig {
        let mut asset = config.asset(asset_id);
        if let Some(b) = self.get(asset_id) {
            asset.observer_baseline = Some(b.baseline);
        }
        asset
    }

    /// The asset's baseline in effect, for the API.
    #[must_use]
    pub fn view(&self, config: &Config, asset_id: &str) -> Option<BaselineView> {
        match self.get(asset_id) {
            Some(b) => Some(BaselineView::api(b.baseline, b.set_ms)),
            None => config
                .asset(asset_id)
                .observer_baseline
                .map(BaselineView::config),
        }
    }
}
