//! The real twin behind [`AssetTwin`]: `dt_core::estimator::Estimator`
//! with a model bundle (SPEC §5), one per run.
//!
//! The asset's nominal pressure and its warn and fault thresholds come from
//! the daemon's configuration (`[defaults]`, `[assets.<id>]`); hysteresis,
//! dwell time, minimum excitation, the re-order window and the gap limit
//! come from the bundle (`EstimatorConfig::from_bundle`).

use std::path::Path;
use std::sync::Arc;

use dt_core::bundle::Bundle;
use dt_core::charge::UnitBaseline;
use dt_core::estimate::Estimate;
use dt_core::estimator::{Estimator, EstimatorConfig};
use dt_core::log::{RunMetadata, Sample};
use dt_core::road::RoadCalibration;
use dt_core::service::{ServiceReading, ServiceRefusal};

use super::config::AssetConfig;
use super::store::AssetBaseline;
use super::twin::{AssetTwin, TwinCounters, TwinError, TwinFactory};
use super::ServeError;

/// How many distinct untrained excitations the daemon says (then no more).
const UNTRAINED_SAID_MAX: usize = 64;

/// Makes one [`Estimator`] per run from a loaded bundle.
#[derive(Debug, Clone)]
pub struct EstimatorFactory {
    bundle: Arc<Bundle>,
    road: Option<Arc<RoadCalibration>>,
    /// The run excitations the bundle's network was not trained on that the
    /// log has said (once each: a fleet's every run may be one).
    untrained_said: Arc<std::sync::Mutex<std::collections::HashSet<String>>>,
}

impl EstimatorFactory {
    /// Loads (and checks) the bundle at `dir` and the road calibration at
    /// `road` (assets with `road = true` are read by the road observer).
    pub fn load(dir: &Path, road: Option<&Path>) -> Result<Self, ServeError> {
        let bundle = Bundle::load(dir).map_err(|e| ServeError::Model {
            path: dir.to_owned(),
            reason: e.to_string(),
        })?;
        let mut factory = Self::new(Arc::new(bundle));
        if let Some(path) = road {
            let bad = |reason: String| ServeError::Model {
                path: path.to_owned(),
                reason,
            };
            let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
            let cal =
                RoadCalibration::from_json(&path.display().to_string(), &text).map_err(bad)?;
            factory.road = Some(Arc::new(cal));
        }
        Ok(factory)
    }

    /// Uses an already loaded bundle (no road calibration).
    #[must_use]
    pub fn new(bundle: Arc<Bundle>) -> Self {
        Self {
            bundle,
            road: None,
            untrained_said: Arc::default(),
        }
    }

    /// The road calibration, when one was loaded.
    #[must_use]
    pub fn road(&self) -> Option<&RoadCalibration> {
        self.road.as_deref()
    }

    /// A fresh estimator for `asset` (with the road observer when the asset
    /// is driven on roads).
    pub fn estimator_for(&self, asset: &AssetConfig) -> Result<Estimator, TwinError> {
        let est = Estimator::new(Arc::clone(&self.bundle), self.config_for(asset))?;
        match (&self.road, asset.road) {
            (Some(cal), true) => Ok(est.with_road(match &asset.road_baseline {
                Some(b) => cal.apply(b),
                None => (**cal).clone(),
            })?),
            (None, true) => Err("the asset is driven on roads (`road = true`) but no road calibration was loaded ([model] road, --road)".into()),
            (_, false) => Ok(est),
        }
    }

    /// [`estimator_for`](Self::estimator_for) asset `id`: what setting it up
    /// warns of names the asset.
    pub fn estimator_of(&self, id: &str, asset: &AssetConfig) -> Result<Estimator, TwinError> {
        tracing::warn_span!("asset", id).in_scope(|| self.estimator_for(asset))
    }

    /// The bundle.
    #[must_use]
    pub fn bundle(&self) -> &Arc<Bundle> {
        &self.bundle
    }

    /// The estimator settings for `asset`.
    #[must_use]
    pub fn config_for(&self, asset: &AssetConfig) -> EstimatorConfig {
        let mut cfg = EstimatorConfig::from_bundle(&self.bundle);
        cfg.nominal_bar = asset.nominal_bar;
        cfg.health.warn_bar = asset.warn_bar;
        cfg.health.fault_bar = asset.fault_bar;
        cfg.observer_baseline = asset.observer_baseline;
        // A service reading takes every reversal: its sd conditions the unit
        // (a road asset's is read by the road observer instead).
        cfg.observer_fit_all = asset.read_service.is_some() && !asset.road;
        // A service reading runs the unit's own law, when its baseline before
        // the service had one that this model's calibration takes.
        cfg.observer_service_earlier = asset.read_service.and_then(|s| s.earlier);
        cfg.observer_damping_law = asset
            .read_service
            .and_then(|s| s.damping_law())
            .filter(|law| {
                let ok = self
                    .bundle
                    .physics()
                    .observer
                    .is_some_and(|o| o.with_unit_law(*law).is_ok());
                if !ok {
                    tracing::warn!(
                        "the unit's own damping law is not of this model's calibration's form: \
                     the service is read with the calibration's law"
                    );
                }
                ok
            });
        cfg
    }
}

impl TwinFactory for EstimatorFactory {
    fn create(
        &self,
        meta: &RunMetadata,
        asset: &AssetConfig,
    ) -> Result<Box<dyn AssetTwin>, TwinError> {
        let mut est = self.estimator_of(&meta.asset_id, asset)?;
        if est.road().is_some() {
            // a dyno run of a road asset is refused, as `shocktwin road` does
            dt_core::road::refuse_dyno_run(meta)?;
        }
        if let Some(why) = est.untrained_excitation(meta) {
            let excitation = meta.excitation.as_deref().unwrap_or_default().trim();
            let mut said = self
                .untrained_said
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            // bounded: a log's free text may differ from run to run
            if said.len() < UNTRAINED_SAID_MAX && said.insert(excitation.to_owned()) {
                tracing::warn!(
                    asset = %meta.asset_id,
                    run = %meta.run_id,
                    "{why} (said once per excitation)"
                );
            }
        }
        let mut service = None;
        if let Some(s) = asset.read_service {
            // a road asset's unit is read by the road observer (its blocks),
            // any other by the dyno observer, when the bundle has one
            if est.road().is_some() {
                est = est.read_road_baseline(s.charge_bar);
            } else if est.observer().is_some() {
                service = Some((s.charge_bar, ServiceReading::new()));
            }
        }
        Ok(Box::new(EstimatorTwin { est, service }))
    }

    fn describe(&self) -> String {
        match &self.road {
            Some(_) => format!(
                "estimator, bundle {}, road observer for assets with `road = true`",
                self.bundle.dir.display()
            ),
            None => format!("estimator, bundle {}", self.bundle.dir.display()),
        }
    }

    fn as_estimator(&self) -> Option<&EstimatorFactory> {
        Some(self)
    }
}

/// [`Estimator`] as an [`AssetTwin`]; after a service it also reads the
/// unit's baseline (the charge the unit was filled to, and the reading).
#[derive(Debug)]
pub struct EstimatorTwin {
    est: Estimator,
    service: Option<(f64, ServiceReading)>,
}

impl EstimatorTwin {
    fn drain_into(&mut self, out: &mut Vec<Estimate>) {
        match self.service.as_mut() {
            Some((_, reading)) => reading.drain_from(&mut self.est, out),
            None => out.extend(self.est.drain()),
        }
    }
}

impl AssetTwin for EstimatorTwin {
    fn push(&mut self, sample: &Sample) -> Result<(), TwinError> {
        Ok(self.est.push(*sample)?)
    }

    fn drain(&mut self, out: &mut Vec<Estimate>) {
        self.drain_into(out);
    }

    fn finish(&mut self, out: &mut Vec<Estimate>) -> Result<(), TwinError> {
        self.est.finish()?;
        self.drain_into(out);
        // A vehicle without a sensor its model reads (a loadcell unplugged):
        // every estimate was NaN, and the run ended `completed`.
        match self.est.missing_topics_reason() {
            Some(reason) => Err(format!("the run {reason}").into()),
            None => Ok(()),
        }
    }

    fn service_baseline(&self) -> Option<Result<AssetBaseline, String>> {
        if let Some(road) = self.est.road_baseline() {
            return Some(road.map(AssetBaseline::Road));
        }
        let (charge_bar, reading) = self.service.as_ref()?;
        let params = self.est.bundle().physics().observer?;
        let law = self.est.config().observer_damping_law;
        Some(
            reading
                .finish(*charge_bar, &params)
                .map(|r| {
                    AssetBaseline::Observer(with_earlier_readings(
                        &UnitBaseline {
                            damping_law: law,
                            ..r.baseline
                        },
                        self.est.config().observer_service_earlier.as_ref(),
                        params.accel_cluster_rel,
                    ))
                })
                .map_err(|e| match e {
                    // read with the calibration's law: the unit's valves may be
                    // what the reversals did not fit
                    ServiceRefusal::TooWide { .. } if law.is_none() => format!(
                        "{e}; or a unit whose valves the calibration's damping law does not \
                         fit: read its baseline with `python -m train.observer baseline \
                         --unit-law` and PUT it to /v1/assets/{{id}}/baseline"
                    ),
                    e => e.to_string(),
                }),
        )
    }

    fn counters(&self) -> TwinCounters {
        let c = self.est.counters();
        TwinCounters {
            samples: c.samples,
            nan_samples: c.missing_samples,
            out_of_order: c.reordered + c.late_dropped,
            dropped_late: c.late_dropped,
            clock_jumps: c.clock_jumps,
            timestamp_outliers: c.timestamp_outliers,
            ticks_without_inputs: c.ticks_without_inputs,
            ticks: c.ticks,
            // on a road asset the road observer reads the charge: the dyno
            // observer's counters (not calibrated at a road) would mislead
            observer: (self.est.observer().is_some() && self.est.road().is_none())
                .then_some(c.observer),
            road: c.road,
        }
    }
}

/// A service reading with the readings the unit's baseline before the
/// service held at other excitations ([`UnitBaseline::keeping_readings_of`]);
/// those it cannot keep are logged.
pub(crate) fn with_earlier_readings(
    read: &UnitBaseline,
    earlier: Option<&UnitBaseline>,
    rel: f64,
) -> UnitBaseline {
    let Some(earlier) = earlier else {
        return *read;
    };
    let (b, left_out) = read.keeping_readings_of(earlier, rel);
    let kept = b.other_excitations.iter().flatten().count();
    if kept > 0 || left_out > 0 {
        tracing::info!(
            kept,
            left_out,
            "the service's reading keeps the earlier baseline's readings at other excitations \
             (left out: at its own excitation, without a range, beyond three, those nearest its \
             own excitation, or all of them when read with another damping law)"
        );
    }
    b
}
