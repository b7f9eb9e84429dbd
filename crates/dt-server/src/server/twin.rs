//! What the daemon drives per run: an [`AssetTwin`] made by a
//! [`TwinFactory`]. The real estimator (`dt_core::estimator`) plugs in behind
//! these traits ([`super::estimator::EstimatorFactory`]);
//! [`TickCounterTwin`] is a clearly-named placeholder that keeps the 50 Hz
//! clock but estimates nothing (tests, and a daemon started without a model).

use dt_core::estimate::{Estimate, Health};
use dt_core::log::{RunMetadata, Sample};

use super::config::AssetConfig;

/// Counters a twin keeps about its input; the daemon adds them to its metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TwinCounters {
    /// Samples pushed.
    pub samples: u64,
    /// Samples holding a NaN value (treated as missing).
    pub nan_samples: u64,
    /// Samples older than one already seen (re-ordered within the window, or
    /// dropped when too late).
    pub out_of_order: u64,
    /// Out-of-order samples too late to use, dropped.
    pub dropped_late: u64,
    /// Forward clock jumps that restarted the twin.
    pub clock_jumps: u64,
    /// Samples far ahead of the stream that it did not follow (corrupt
    /// timestamps), dropped.
    pub timestamp_outliers: u64,
    /// Ticks whose model inputs were not all available (pressure NaN).
    pub ticks_without_inputs: u64,
    /// Estimates emitted.
    pub ticks: u64,
    /// What the charge observer made of the velocity reversals (`None`
    /// when the bundle does not read it).
    pub observer: Option<dt_core::charge::ObserverCounters>,
    /// What the road observer made of the blocks (`None` unless the asset
    /// is read on roads).
    pub road: Option<dt_core::road::RoadCounters>,
}

/// One asset's estimator for one run: fed samples in any interleaving, it
/// emits one [`Estimate`] per 50 Hz tick.
pub trait AssetTwin: Send {
    /// Feeds one sample (any topic; NaN values are missing data). An error
    /// is a numerical failure of the twin: the run ends with it.
    fn push(&mut self, sample: &Sample) -> Result<(), TwinError>;
    /// Appends the estimates completed so far to `out`.
    fn drain(&mut self, out: &mut Vec<Estimate>);
    /// End of the run: appends every remaining estimate to `out`.
    fn finish(&mut self, out: &mut Vec<Estimate>) -> Result<(), TwinError>;
    /// Counters so far.
    fn counters(&self) -> TwinCounters;
    /// After [`finish`](Self::finish): the unit's baseline this run read for
    /// a pending service (`AssetConfig::read_service`), or why it read none;
    /// `None` when the run was not reading one.
    fn service_baseline(&self) -> Option<Result<super::store::AssetBaseline, String>> {
        None
    }
}

/// Error creating a twin (e.g. the run lacks a sensor the model needs).
pub type TwinError = Box<dyn std::error::Error + Send + Sync>;

/// Makes one [`AssetTwin`] per run.
pub trait TwinFactory: Send + Sync {
    /// A twin for the run described by `meta`, judged with `asset`'s thresholds.
    fn create(
        &self,
        meta: &RunMetadata,
        asset: &AssetConfig,
    ) -> Result<Box<dyn AssetTwin>, TwinError>;
    /// Human-readable name, logged at start.
    fn describe(&self) -> String;
    /// The real estimator's factory, when this is one (the NATS workers
    /// checkpoint its estimators).
    fn as_estimator(&self) -> Option<&super::EstimatorFactory> {
        None
    }
}

/// The 50 Hz tick period, ns (SPEC §4, ARCHITECTURE "50 Hz clock").
pub const TICK_NS: i64 = 20_000_000;

/// **Placeholder, not an estimator.** Keeps the 50 Hz clock of the real
/// estimator (ticks at `t_origin + k·20 ms`, `k ≥ 1`, `t_origin` = first
/// sample; a tick is emitted once a later sample arrives, the rest at the end
/// of the run) and emits for each tick an [`Estimate`] with NaN values,
/// `expected_bar` = the asset's nominal pressure and [`Health::Unknown`].
/// It lets the daemon run and be tested end to end before the estimator
/// exists. Samples older than the newest one seen count as out of order and
/// are ignored.
#[derive(Debug, Clone)]
pub struct TickCounterTwin {
    expected_bar: f64,
    /// Time of the newest sample.
    newest_ns: Option<i64>,
    /// Next tick to emit.
    next_tick_ns: i64,
    counters: TwinCounters,
}

impl TickCounterTwin {
    /// A placeholder twin for an asset whose nominal pressure is `expected_bar`.
    #[must_use]
    pub fn new(expected_bar: f64) -> Self {
        Self {
            expected_bar,
            newest_ns: None,
            next_tick_ns: 0,
            counters: TwinCounters::default(),
        }
    }

    fn estimate(&self, t_ns: i64) -> Estimate {
        Estimate {
            t_ns,
            pressure_bar: f64::NAN,
            pressure_avg_bar: f64::NAN,
            pressure_lo_bar: f64::NAN,
            pressure_hi_bar: f64::NAN,
            expected_bar: self.expected_bar,
            health: Health::Unknown,
            velocity_mps: f64::NAN,
            force_model_n: f64::NAN,
            oil_temp_c: f64::NAN,
            unfloored_bar: f64::NAN,
            unfloored_half_bar: f64::NAN,
        }
    }

    /// Emits ticks `<= up_to_ns` (inclusive) or `< up_to_ns`.
    fn emit(&mut self, up_to_ns: i64, inclusive: bool, out: &mut Vec<Estimate>) {
        if self.newest_ns.is_none() {
            return;
        }
        while self.next_tick_ns < up_to_ns || (inclusive && self.next_tick_ns == up_to_ns) {
            out.push(self.estimate(self.next_tick_ns));
            self.counters.ticks += 1;
            self.next_tick_ns += TICK_NS;
        }
    }
}

/// Whether any input value of `s` is NaN.
fn has_nan(s: &Sample) -> bool {
    match *s {
        Sample::Acceleration {
            a1_mps2, a2_mps2, ..
        } => a1_mps2.is_nan() || a2_mps2.is_nan(),
        Sample::Position { position_m: v, .. }
        | Sample::Force { force_n: v, .. }
        | Sample::TempShock {
            temperature_c: v, ..
        }
        | Sample::TempAmbient {
            temperature_c: v, ..
        } => v.is_nan(),
        // Simulator truth channels are not inputs of the twin.
        _ => false,
    }
}

impl AssetTwin for TickCounterTwin {
    fn push(&mut self, sample: &Sample) -> Result<(), TwinError> {
        self.counters.samples += 1;
        if has_nan(sample) {
            self.counters.nan_samples += 1;
        }
        let t = sample.t_ns();
        match self.newest_ns {
            None => {
                self.newest_ns = Some(t);
                self.next_tick_ns = t.saturating_add(TICK_NS);
            }
            Some(newest) if t < newest => {
                self.counters.out_of_order += 1;
                // Older than a tick already emitted: too late to use.
                if t <= self.next_tick_ns - TICK_NS {
                    self.counters.dropped_late += 1;
                }
            }
            Some(_) => self.newest_ns = Some(t),
        }
        Ok(())
    }

    fn drain(&mut self, out: &mut Vec<Estimate>) {
        if let Some(newest) = self.newest_ns {
            self.emit(newest, false, out);
        }
    }

    fn finish(&mut self, out: &mut Vec<Estimate>) -> Result<(), TwinError> {
        if let Some(newest) = self.newest_ns {
            self.emit(newest, true, out);
        }
        Ok(())
    }

    fn counters(&self) -> TwinCounters {
        self.counters
    }
}

/// Makes [`TickCounterTwin`]s (placeholder; see its docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct TickCounterFactory;

impl TwinFactory for TickCounterFactory {
    fn create(
        &self,
        _meta: &RunMetadata,
        asset: &AssetConfig,
    ) -> Result<Box<dyn AssetTwin>, TwinError> {
        Ok(Box::new(TickCounterTwin::new(asset.nominal_bar)))
    }

    fn describe(&self) -> String {
        "placeholder TickCounterTwin (50 Hz clock only: NaN pressure, health unknown)".to_owned()
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // values are copied through, not computed
mod tests {
    use super::*;

    fn pos(t_ns: i64, position_m: f64) -> Sample {
        Sample::Position { t_ns, position_m }
    }

    #[test]
    fn one_tick_per_20_ms_of_sample_time() {
        let mut twin = TickCounterTwin::new(12.0);
        let mut out = Vec::new();
        // 1 kHz for 1 s: samples at 0, 1, ..., 999 ms (+ offset).
        let t0 = 5_000_000_000;
        for i in 0..1000 {
            twin.push(&pos(t0 + i * 1_000_000, 0.0)).unwrap();
            twin.drain(&mut out);
        }
        // Ticks at 20, 40, ..., 980 ms are complete (a later sample arrived).
        assert_eq!(out.len(), 49);
        twin.finish(&mut out).unwrap();
        // Last sample at 999 ms: no tick at 1000 ms.
        assert_eq!(out.len(), 49);
        assert_eq!(out[0].t_ns, t0 + TICK_NS);
        assert!(out.windows(2).all(|w| w[1].t_ns - w[0].t_ns == TICK_NS));
        assert!(out.iter().all(|e| e.pressure_bar.is_nan()
            && e.health == Health::Unknown
            && e.expected_bar == 12.0));
        assert_eq!(twin.counters().ticks, 49);
    }

    #[test]
    fn finish_emits_a_tick_at_the_last_sample() {
        let mut twin = TickCounterTwin::new(12.0);
        let mut out = Vec::new();
        twin.push(&pos(0, 0.0)).unwrap();
        twin.push(&pos(40_000_000, 0.0)).unwrap();
        twin.drain(&mut out);
        assert_eq!(out.len(), 1, "tick at 40 ms is not complete yet");
        twin.finish(&mut out).unwrap();
        assert_eq!(out.len(), 2);
        let mut more = Vec::new();
        twin.finish(&mut more).unwrap();
        assert!(more.is_empty(), "finish twice emits nothing new");
    }

    #[test]
    fn counts_nan_and_out_of_order() {
        let mut twin = TickCounterTwin::new(12.0);
        let mut out = Vec::new();
        twin.push(&pos(0, 0.0)).unwrap();
        twin.push(&pos(50_000_000, f64::NAN)).unwrap();
        twin.drain(&mut out);
        twin.push(&pos(45_000_000, 0.1)).unwrap(); // out of order, after tick 40 ms: usable
        twin.push(&pos(10_000_000, 0.1)).unwrap(); // before tick 40 ms: too late
        let c = twin.counters();
        assert_eq!(c.samples, 4);
        assert_eq!(c.nan_samples, 1);
        assert_eq!(c.out_of_order, 2);
        assert_eq!(c.dropped_late, 1);
    }
}
