//! A unit's baseline read from one run after a service, by whatever runs the
//! estimator (the daemon; `python -m train.observer baseline` reads the same
//! quantities from the feature rows).
//!
//! After a service the maintainer knows the charge `p_s` the unit was filled
//! to. The run that follows, read by the charge observer *without* a baseline,
//! gives what the observer makes of that unit at `p_s`: its reading `m` and how
//! sure it is from the reversals alone. That pair is the unit's
//! [`UnitBaseline`] (`charge_bar = p_s`, `read_bar = m`, `read_sd_bar = s`),
//! which conditions the unit's systematic offset and gain on every later run
//! (`charge` module, "A unit baseline").
//!
//! Fed one 50 Hz tick at a time ([`ServiceReading::push`]: time, whether the
//! stroke is excited, the observer's mean `m_k` and reported sd `σ_k`, bar),
//! it keeps O(1) state:
//! - onset `t_0`: the first excited tick; the reading is taken at the last
//!   excited tick `k*`: `m = m_{k*}`;
//! - the reading's own variance is the reported one without the systematic
//!   part, `v = max(σ_{k*}² − σ_sys² − (ρ m)², 10⁻⁴)`, with `σ_sys`
//!   = [`ObserverParams::systematic_sd_bar`], `ρ` =
//!   [`ObserverParams::systematic_rel`];
//! - the drift `d`: the RMS of `m_k − m` over the ticks from
//!   `t_0 + `[`SETTLE_S`] up to `k*` (how far the reading wanders while the
//!   charge is constant: the error of a unit changes as it heats, and a
//!   constant correction cannot follow it), kept as running sums
//!   `Σ 1, Σ m_k, Σ m_k²` snapshotted at each excited tick;
//! - `s = √(v + d²)`.
//!
//! The reading is refused (and the baseline stays to be read) when no tick
//! was excited, when the observer used a reversal at an excitation with a
//! measurement model of its own (a baseline conditions the shared model
//! only), or when `s` exceeds [`MAX_SD_SHARE`] of the prior's sd (the
//! observer used almost no reversals: an excitation it was not calibrated
//! at). These are the rules, constants and formulas of
//! `train.observer.baseline_of` for one run; the Python tool takes its onset
//! and end from the position instead of the excitation flag.

use serde::{Deserialize, Serialize};

use crate::charge::{ChargeObserver, ObserverParams, UnitBaseline};
use crate::estimate::Estimate;
use crate::estimator::Estimator;
use crate::features::col;

/// A reading must have taught the observer something: its own sd (without
/// the systematic part) at most this share of the prior's.
pub const MAX_SD_SHARE: f64 = 0.25;

/// The drift counts the ticks from this long after the excitation onset, s
/// (as `train.observer evaluate --settle-s`).
pub const SETTLE_S: f64 = 60.0;

/// Floor of the reading's own variance, bar².
const MIN_VAR_BAR2: f64 = 1e-4;

/// Running sums of the settled readings.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
struct Sums {
    n: f64,
    sum: f64,
    sum_sq: f64,
}

impl Sums {
    /// RMS of `m_k − m` over the summed readings.
    fn rms_about(&self, m: f64) -> f64 {
        if self.n == 0.0 {
            return 0.0;
        }
        let ms = (self.sum_sq - 2.0 * m * self.sum + self.n * m * m) / self.n;
        ms.max(0.0).sqrt()
    }
}

/// One run's reading of the unit for a baseline (see the module doc);
/// serialisable, so that a checkpointed run goes on reading.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ServiceReading {
    onset_ns: Option<i64>,
    settled: Sums,
    at_last_excited: Sums,
    last: Option<(f64, f64)>,
    own: bool,
    /// The `|ÿ_r|` range of the reversals read, m/s².
    #[serde(default)]
    accel_range: Option<[f64; 2]>,
    /// The stroke's ends apart, bar, when last noted.
    #[serde(default)]
    split_bar: Option<f64>,
}

/// What one run read of the unit at its known charge.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReadBaseline {
    /// The unit's baseline.
    pub baseline: UnitBaseline,
    /// The drift part of `read_sd_bar`, bar.
    pub drift_sd_bar: f64,
}

/// Why a run gave no baseline.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ServiceRefusal {
    /// No tick was excited with an observer reading.
    #[error("no excited tick with a charge reading: no baseline from this run")]
    NotExcited,
    /// A reversal was read at an excitation with a model of its own.
    #[error(
        "the observer read reversals at an excitation with a measurement model of its own, \
         which a baseline does not condition: take the baseline at one of the shared \
         model's excitations"
    )]
    OwnExcitation,
    /// The reading is hardly narrower than the prior.
    #[error(
        "the observer used (almost) no reversals (reading {read_bar:.2} ± {sd_bar:.2} bar from \
         its reversals alone, more than {share} of the prior's sd): an excitation it was not \
         calibrated at?"
    )]
    TooWide {
        /// The reading, bar.
        read_bar: f64,
        /// Its sd from the reversals alone, bar.
        sd_bar: f64,
        /// [`MAX_SD_SHARE`].
        share: f64,
    },
}

impl ServiceReading {
    /// An empty reading.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds one tick: its time, whether the stroke is excited, and the
    /// observer's mean and reported sd (bar; NaN: no reading, skipped).
    pub fn push(&mut self, t_ns: i64, excited: bool, mean_bar: f64, sd_bar: f64) {
        if !(mean_bar.is_finite() && sd_bar.is_finite()) {
            return;
        }
        if excited && self.onset_ns.is_none() {
            self.onset_ns = Some(t_ns);
        }
        let Some(onset) = self.onset_ns else {
            return;
        };
        // Seconds since onset; ns differences of one run fit f64 exactly.
        #[allow(clippy::cast_precision_loss)]
        let since_s = (t_ns - onset) as f64 * 1e-9;
        if since_s >= SETTLE_S {
            self.settled.n += 1.0;
            self.settled.sum += mean_bar;
            self.settled.sum_sq += mean_bar * mean_bar;
        }
        if excited {
            self.at_last_excited = self.settled;
            self.last = Some((mean_bar, sd_bar));
        }
    }

    /// Notes that the observer used a reversal at an excitation with a model
    /// of its own ([`crate::charge::ChargeObserver::used_own`]).
    pub fn note_own(&mut self, used_own: bool) {
        self.own |= used_own;
    }

    /// Notes the range of `|ÿ_r|` the observer's used reversals span so far
    /// ([`crate::charge::ChargeObserver::used_accel_range`]), m/s²: the
    /// baseline records it ([`UnitBaseline::accel_range_mps2`]).
    pub fn note_accel_range(&mut self, range: [f64; 2]) {
        self.accel_range = Some(crate::charge::widen_range(self.accel_range, range));
    }

    /// Notes the split of the stroke's ends so far
    /// ([`crate::charge::ChargeObserver::ends_split_bar`]): the baseline
    /// records the last one noted ([`UnitBaseline::split_bar`]).
    pub fn note_split(&mut self, split_bar: f64) {
        self.split_bar = Some(split_bar);
    }

    /// Drains the estimator's completed ticks into `out`, reading each (the
    /// estimator's excitation threshold decides `excited`).
    pub fn drain_from(&mut self, est: &mut Estimator, out: &mut Vec<Estimate>) {
        let min_excitation = est.config().health.min_excitation_mps;
        for tick in est.drain_ticks() {
            let row = &tick.row;
            self.push(
                row.t_ns,
                row.twin.velocity_rms_1s_mps >= min_excitation,
                row.values[col::OBSERVER_BAR],
                row.values[col::OBSERVER_SD_BAR],
            );
            out.push(tick.estimate);
        }
        self.note_own(est.observer().is_some_and(ChargeObserver::used_own));
        if let Some(r) = est.observer().and_then(ChargeObserver::used_accel_range) {
            self.note_accel_range(r);
        }
        if let Some(split) = est.observer().and_then(ChargeObserver::ends_split_bar) {
            self.note_split(split);
        }
    }

    /// The unit's baseline at `charge_bar`, or why this run gives none.
    pub fn finish(
        &self,
        charge_bar: f64,
        p: &ObserverParams,
    ) -> Result<ReadBaseline, ServiceRefusal> {
        let (m, sd) = self.last.ok_or(ServiceRefusal::NotExcited)?;
        if self.own {
            return Err(ServiceRefusal::OwnExcitation);
        }
        let sys2 = p.systematic_sd_bar.powi(2) + (p.systematic_rel * m).powi(2);
        let drift = self.at_last_excited.rms_about(m);
        let sd_read = ((sd * sd - sys2).max(MIN_VAR_BAR2) + drift * drift).sqrt();
        if sd_read > MAX_SD_SHARE * p.prior_sd_bar {
            return Err(ServiceRefusal::TooWide {
                read_bar: m,
                sd_bar: sd_read,
                share: MAX_SD_SHARE,
            });
        }
        Ok(ReadBaseline {
            baseline: UnitBaseline {
                charge_bar,
                read_bar: m,
                read_sd_bar: sd_read,
                accel_range_mps2: self.accel_range,
                // the law the run was read with is the caller's to add (the
                // daemon carries a unit's own through a service)
                damping_law: None,
                second: None,
                runs_averaged: 1.0,
                split_bar: self.split_bar,
                other_excitations: Default::default(),
            },
            drift_sd_bar: drift,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: i64 = 1_000_000_000;

    fn params() -> ObserverParams {
        ObserverParams {
            systematic_sd_bar: 2.0,
            systematic_rel: 0.1,
            prior_sd_bar: 6.0,
            ..ObserverParams::default()
        }
    }

    /// Reference: the formulas of the module doc over the whole arrays.
    fn reference(
        t_s: &[f64],
        excited: &[bool],
        m: &[f64],
        sd: &[f64],
        p: &ObserverParams,
    ) -> (f64, f64) {
        let onset = t_s[excited.iter().position(|&e| e).unwrap()];
        let last = excited.iter().rposition(|&e| e).unwrap();
        let settled: Vec<f64> = (0..=last)
            .filter(|&i| t_s[i] - onset >= SETTLE_S)
            .map(|i| (m[i] - m[last]).powi(2))
            .collect();
        #[allow(clippy::cast_precision_loss)]
        let drift = (settled.iter().sum::<f64>() / settled.len().max(1) as f64).sqrt();
        let sys2 = p.systematic_sd_bar.powi(2) + (p.systematic_rel * m[last]).powi(2);
        (
            m[last],
            ((sd[last].powi(2) - sys2).max(1e-4) + drift * drift).sqrt(),
        )
    }

    #[test]
    fn a_run_reads_its_last_excited_tick_with_the_drift_since_it_settled() {
        let p = params();
        // 10 s at rest, 200 s excited with a reading drifting from 10.6 to
        // 11.8 bar and its sd narrowing, then 20 s at rest (the reading holds).
        let n = 11_500;
        let mut rows = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut r = ServiceReading::new();
        for k in 0..n {
            let t = f64::from(k) * 0.02;
            let excited = (10.0..210.0).contains(&t);
            let m = 10.6 + 1.2 * ((t - 10.0).clamp(0.0, 200.0) / 200.0).sqrt();
            let sd = (2.0f64.powi(2) + (0.1 * m).powi(2) + 9.0 / (1.0 + t)).sqrt();
            r.push(i64::from(k) * 20_000_000, excited, m, sd);
            rows.0.push(t);
            rows.1.push(excited);
            rows.2.push(m);
            rows.3.push(sd);
        }
        let got = r.finish(12.0, &p).unwrap();
        let (m, s) = reference(&rows.0, &rows.1, &rows.2, &rows.3, &p);
        assert!((got.baseline.read_bar - m).abs() < 1e-12, "{got:?}");
        assert!(
            (got.baseline.read_sd_bar - s).abs() < 1e-9,
            "{got:?} vs {s}"
        );
        assert!(got.drift_sd_bar > 0.05, "{got:?}");
        assert!((got.baseline.charge_bar - 12.0).abs() < f64::EPSILON);
    }

    #[test]
    fn a_run_without_excitation_or_reversals_or_at_an_own_excitation_gives_none() {
        let p = params();
        let mut rest = ServiceReading::new();
        for k in 0..1000 {
            rest.push(k * S / 50, false, 6.0, 6.4);
        }
        assert_eq!(rest.finish(12.0, &p), Err(ServiceRefusal::NotExcited));
        let mut prior = ServiceReading::new();
        for k in 0..1000 {
            prior.push(k * S / 50, true, 6.0, (36.0f64 + 4.0 + 0.36).sqrt());
        }
        assert!(matches!(
            prior.finish(12.0, &p),
            Err(ServiceRefusal::TooWide { .. })
        ));
        let mut own = ServiceReading::new();
        for k in 0..1000 {
            own.push(k * S / 50, true, 11.0, 2.3);
        }
        own.note_own(true);
        own.note_own(false);
        assert_eq!(own.finish(12.0, &p), Err(ServiceRefusal::OwnExcitation));
        let mut nan = ServiceReading::new();
        nan.push(0, true, f64::NAN, 1.0);
        assert_eq!(nan.finish(12.0, &p), Err(ServiceRefusal::NotExcited));
    }
}
