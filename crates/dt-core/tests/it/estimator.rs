//! The streaming estimator: streaming = batch (`compute_features`) in order
//! and shuffled within the re-order window; late, NaN and missing data and
//! clock jumps counted, not fatal; the SPEC §6 health state machine on
//! synthetic ticks.

use std::sync::Arc;

use dt_core::bundle::{mlp_f32_agrees, Bundle, HealthConfig};
use dt_core::estimate::Health;
use dt_core::estimator::{Estimator, EstimatorConfig, HealthMachine, Tick};
use dt_core::features::{
    col, column_indices, compute_features, sorted_samples, FeatureTable, TICK_NS,
};
use dt_core::log::{RunLog, RunMetadata, Sample};
use dt_core::thermal::{ThermalModel, ThermalState, MAX_STEP_S};

/// Streaming and batch features must agree to this (SPEC: 1e-9).
const TOL: f64 = 1e-9;
const T0: i64 = 1_700_000_000_000_000_000;
const MS: i64 = 1_000_000;

fn bundle(name: &str) -> Arc<Bundle> {
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name);
    Arc::new(Bundle::load(dir).unwrap())
}

/// Deterministic pseudo-random numbers (`SplitMix64`).
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn noise(&mut self) -> f64 {
        self.uniform() * 2.0 - 1.0
    }
}

/// A dyno-like run at SPEC rates: a sine of `amp_m` at 2 Hz from `t0`, with
/// sensor noise, an accelerometer bias, a warming shock body, jittered
/// loadcell times and accelerometer/potentiometer samples at equal times.
fn synth_log(t0: i64, seconds: i64, amp_m: f64, seed: u64) -> RunLog {
    let mut rng = Rng(seed);
    let w = 2.0 * std::f64::consts::PI * 2.0;
    let secs = |t: i64| (t - t0) as f64 / 1e9;
    let mut log = RunLog {
        metadata: RunMetadata {
            asset_id: "unit-1".into(),
            run_id: "synthetic".into(),
            ..RunMetadata::default()
        },
        ..RunLog::default()
    };
    for i in 0..seconds * 1000 {
        let t = t0 + i * MS;
        let a = -amp_m * w * w * (w * secs(t)).sin();
        log.acceleration
            .push((t, a + 0.3 + 0.05 * rng.noise(), 0.05 * rng.noise()));
    }
    for i in 0..seconds * 100 {
        let t = t0 + i * 10 * MS;
        log.position
            .push((t, amp_m * (w * secs(t)).sin() + 5e-4 * rng.noise()));
    }
    for i in 0..seconds * 50 {
        let t = t0 + 3 * MS + i * 20 * MS + (rng.noise() * 2e5) as i64;
        let v = amp_m * w * (w * secs(t)).cos();
        log.force.push((t, 6000.0 * v - 380.0 + 20.0 * rng.noise()));
    }
    for i in 0..seconds {
        let t = t0 + 250 * MS + i * 1000 * MS;
        log.temp_shock.push((t, 25.0 + 0.05 * i as f64));
        log.temp_ambient
            .push((t + 7 * MS, 21.5 + 0.1 * rng.noise()));
        log.truth_pressure.push((t, 12.0));
    }
    log
}

/// Pushes `samples` in the order given, collecting every tick.
fn stream(est: &mut Estimator, samples: &[Sample]) -> Vec<Tick> {
    let mut ticks = Vec::new();
    for s in samples {
        est.push(*s).unwrap();
        ticks.extend(est.drain_ticks());
    }
    est.finish().unwrap();
    ticks.extend(est.drain_ticks());
    ticks
}

fn estimator(b: &Arc<Bundle>) -> Estimator {
    Estimator::new(Arc::clone(b), EstimatorConfig::from_bundle(b)).unwrap()
}

/// Every batch row has its tick, with the same features (to `TOL`, NaN
/// where NaN) and the same pressure as the network on the batch row.
fn assert_same_as_batch(b: &Bundle, ticks: &[Tick], table: &FeatureTable) {
    let idx = column_indices(&b.groups);
    let k = idx.len();
    assert_eq!(table.columns.len(), k);
    assert_eq!(ticks.len(), table.n_rows(), "every tick accounted for");
    let pressures = b.predict(&table.values).unwrap();
    let mut finite = 0;
    for (i, tick) in ticks.iter().enumerate() {
        assert_eq!(tick.row.t_ns, table.t_ns[i], "tick {i}");
        assert_eq!(tick.estimate.t_ns, table.t_ns[i], "tick {i}");
        for (j, &c) in idx.iter().enumerate() {
            let (s, bt) = (tick.row.values[c], table.row(i)[j]);
            assert!(
                (s - bt).abs() <= TOL || (s.is_nan() && bt.is_nan()),
                "tick {i} column {}: streaming {s} vs batch {bt}",
                table.columns[j]
            );
        }
        let p = tick.estimate.pressure_bar;
        if table.row(i).iter().all(|x| x.is_finite()) {
            assert_eq!(p.to_bits(), pressures[i].to_bits(), "tick {i}: {p}");
            finite += 1;
        } else {
            assert!(p.is_nan(), "tick {i}");
        }
    }
    // Most ticks carry a pressure (all but the ones before the thermal
    // model starts and the Kalman filter's first sample).
    assert!(finite + 20 > ticks.len(), "{finite} of {}", ticks.len());
}

/// The estimator runs the float32 network: on a replayed run every tick's
/// pressure is within `MLP_F32_PARITY_BAR` of the float64 network (what it
/// ran before) on the same feature row.
#[test]
fn replay_in_float32_stays_within_the_parity_bar_of_float64() {
    for name in ["bundle-mlp13", "bundle-force-skl"] {
        let b = bundle(name);
        assert_eq!(b.precision(), "float32", "{name}");
        let log = synth_log(T0, 30, 0.04, 3);
        let ticks = stream(&mut estimator(&b), &sorted_samples(&log));
        let idx = column_indices(&b.groups);
        let (mut n, mut worst) = (0, 0.0_f64);
        for tick in &ticks {
            let row: Vec<f64> = idx.iter().map(|&c| tick.row.values[c]).collect();
            if !row.iter().all(|x| x.is_finite()) {
                continue;
            }
            let p64 = b.predict_f64(&row).unwrap()[0];
            let p32 = tick.estimate.pressure_bar;
            assert!(
                mlp_f32_agrees(p32, p64),
                "{name} t {}: {p32} vs {p64}",
                tick.row.t_ns
            );
            worst = worst.max((p32 - p64).abs());
            n += 1;
        }
        assert!(n + 20 > ticks.len(), "{name}: {n} of {}", ticks.len());
        eprintln!("{name}: {n} ticks, worst |p32 − p64| = {worst:.2e} bar");
    }
}

#[test]
fn streaming_in_order_equals_batch() {
    for name in ["bundle-mlp13", "bundle-force-skl"] {
        let b = bundle(name);
        let log = synth_log(T0, 12, 0.04, 1);
        let table = compute_features(&log, b.physics(), &b.groups).unwrap();
        let mut est = estimator(&b);
        let ticks = stream(&mut est, &sorted_samples(&log));
        assert_same_as_batch(&b, &ticks, &table);
        let c = est.counters();
        assert_eq!((c.late_dropped, c.reordered, c.clock_jumps), (0, 0, 0));
        assert_eq!(c.ticks, ticks.len() as u64);
        assert_eq!(c.samples, sorted_samples(&log).len() as u64);
    }
}

/// Arrival order: each sample delayed by a random time below `max_delay_ns`
/// (so topics interleave arbitrarily and a topic's own samples may swap).
fn shuffled(samples: &[Sample], max_delay_ns: i64, seed: u64) -> Vec<Sample> {
    let mut rng = Rng(seed);
    let mut arrivals: Vec<(i64, Sample)> = samples
        .iter()
        .map(|s| {
            let d = (rng.uniform() * max_delay_ns as f64) as i64;
            (s.t_ns() + d.min(max_delay_ns - 1), *s)
        })
        .collect();
    arrivals.sort_by_key(|a| a.0);
    arrivals.into_iter().map(|a| a.1).collect()
}

#[test]
fn streaming_shuffled_within_the_window_equals_batch() {
    let b = bundle("bundle-mlp13");
    let log = synth_log(T0, 12, 0.04, 2);
    let table = compute_features(&log, b.physics(), &b.groups).unwrap();
    let cfg = EstimatorConfig::from_bundle(&b);
    for seed in 0..3 {
        let samples = shuffled(&sorted_samples(&log), cfg.reorder_window_ns, seed);
        let mut est = estimator(&b);
        let ticks = stream(&mut est, &samples);
        assert_same_as_batch(&b, &ticks, &table);
        let c = est.counters();
        assert_eq!(c.late_dropped, 0);
        assert!(c.reordered > 10_000, "{c:?}");
    }
    // The estimates are the same too, health included.
    let mut a = estimator(&b);
    let in_order: Vec<_> = stream(&mut a, &sorted_samples(&log));
    let mut z = estimator(&b);
    let shuffled = stream(
        &mut z,
        &shuffled(&sorted_samples(&log), cfg.reorder_window_ns, 9),
    );
    for (x, y) in in_order.iter().zip(&shuffled) {
        assert_eq!(x.estimate.health, y.estimate.health);
        assert_eq!(
            x.estimate.pressure_avg_bar.to_bits(),
            y.estimate.pressure_avg_bar.to_bits()
        );
    }
}

#[test]
fn late_samples_beyond_the_window_are_counted_and_dropped() {
    let b = bundle("bundle-mlp13");
    let log = synth_log(T0, 6, 0.04, 3);
    let mut samples = sorted_samples(&log);
    // One potentiometer sample (t = 2 s) arrives 300 ms late: beyond the
    // 100 ms window.
    let i = samples
        .iter()
        .position(|s| matches!(s, Sample::Position { t_ns, .. } if *t_ns == T0 + 2000 * MS))
        .unwrap();
    let late = samples.remove(i);
    let j = samples
        .iter()
        .position(|s| s.t_ns() > T0 + 2300 * MS)
        .unwrap();
    samples.insert(j, late);
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &samples);
    let c = est.counters();
    assert_eq!(c.late_dropped, 1);
    // Exactly what the batch gives without that sample.
    let mut without = log.clone();
    without.position.retain(|p| p.0 != T0 + 2000 * MS);
    let table = compute_features(&without, b.physics(), &b.groups).unwrap();
    assert_same_as_batch(&b, &ticks, &table);
}

#[test]
fn backward_clock_jump_is_late_data() {
    let b = bundle("bundle-mlp13");
    let log = synth_log(T0, 4, 0.04, 4);
    let samples = sorted_samples(&log);
    let mut est = estimator(&b);
    let mut n_ticks = 0;
    for (i, s) in samples.iter().enumerate() {
        est.push(*s).unwrap();
        if i == samples.len() / 2 {
            // The logger's clock jumps 5 s back for a few samples.
            for k in 0..10 {
                est.push(Sample::Force {
                    t_ns: T0 - 5_000 * MS + k * 20 * MS,
                    force_n: 100.0,
                })
                .unwrap();
            }
        }
        n_ticks += est.drain().count();
    }
    est.finish().unwrap();
    n_ticks += est.drain().count();
    let c = est.counters();
    assert_eq!(c.late_dropped, 10);
    assert_eq!(c.clock_jumps, 0);
    assert_eq!(n_ticks, 200);
}

#[test]
fn forward_clock_jump_starts_a_new_segment() {
    let b = bundle("bundle-mlp13");
    let first = synth_log(T0, 5, 0.04, 5);
    // A logger restart: the second part starts 10 s after the first ends.
    let t1 = T0 + 15_000 * MS + 7 * MS;
    let second = synth_log(t1, 6, 0.04, 6);
    let mut samples = sorted_samples(&first);
    samples.extend(sorted_samples(&second));
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &samples);
    let c = est.counters();
    assert_eq!(c.clock_jumps, 1);
    assert_eq!(c.late_dropped, 0);
    let ta = compute_features(&first, b.physics(), &b.groups).unwrap();
    let tb = compute_features(&second, b.physics(), &b.groups).unwrap();
    assert_eq!(ticks.len(), ta.n_rows() + tb.n_rows());
    assert_same_as_batch(&b, &ticks[..ta.n_rows()], &ta);
    // The segment after the jump has a new tick origin, and its Kalman
    // filter and windows start afresh: their columns are the second part's
    // read on its own.
    let (before, after) = ticks.split_at(ta.n_rows());
    assert_eq!(after[0].row.t_ns, t1 + TICK_NS);
    let idx = column_indices(&b.groups);
    let fresh = [
        col::FORCE_N,
        col::POSITION_M,
        col::ACCEL_REL_MPS2,
        col::VELOCITY_MPS,
        col::ACCEL_HF_RMS_MPS2,
        col::VELOCITY_RMS_MPS,
    ];
    for (i, tick) in after.iter().enumerate() {
        assert_eq!(tick.row.t_ns, tb.t_ns[i]);
        for (j, &c) in idx.iter().enumerate().filter(|(_, c)| fresh.contains(c)) {
            let (s, bt) = (tick.row.values[c], tb.row(i)[j]);
            assert!(
                (s - bt).abs() <= TOL || (s.is_nan() && bt.is_nan()),
                "tick {i} column {}: streaming {s} vs batch {bt}",
                tb.columns[j]
            );
        }
    }
    // The damper's heat is not restarted from the thermocouple but carried
    // through the gap by the thermal model, with no damping power.
    let last = &before[before.len() - 1].row.values;
    let model = ThermalModel::new(b.physics().thermal);
    let gap_s = (sorted_samples(&second)[0].t_ns() - last_sample_ns(&first)) as f64 * 1e-9;
    let steps = (gap_s / MAX_STEP_S).ceil();
    let mut s = ThermalState {
        oil_c: last[col::OIL_TEMP_MODEL_C],
        cyl_c: last[col::CYL_TEMP_MODEL_C],
    };
    for _ in 0..steps as usize {
        s = model.step(s, gap_s / steps, 0.0, last[col::TEMP_AMBIENT_C]);
    }
    s = model.step(s, TICK_NS as f64 * 1e-9, 0.0, last[col::TEMP_AMBIENT_C]);
    let oil = after[0].row.values[col::OIL_TEMP_MODEL_C];
    assert!((oil - s.oil_c).abs() < 1e-9, "{oil} vs {}", s.oil_c);
    assert!(
        (oil - tb.row(0)[idx
            .iter()
            .position(|&c| c == col::OIL_TEMP_MODEL_C)
            .unwrap()])
        .abs()
            > 1e-3
            || tb.row(0)[idx
                .iter()
                .position(|&c| c == col::OIL_TEMP_MODEL_C)
                .unwrap()]
            .is_nan(),
        "the oil restarted as the second part read alone"
    );
    // Health and average restart: unknown, the average of the new
    // segment's ticks alone (the first one's pressure, or none).
    let first_b = &after[0].estimate;
    assert_eq!(first_b.health, Health::Unknown);
    assert!(
        first_b.pressure_avg_bar.to_bits() == first_b.pressure_bar.to_bits()
            || first_b.pressure_avg_bar.is_nan(),
        "{first_b:?}"
    );
    assert_ne!(before[before.len() - 1].estimate.health, Health::Unknown);
}

#[test]
fn past_six_hours_the_thermal_model_restarts_from_the_new_thermocouple() {
    // The review: the carried first shock reading stayed past the limit, and
    // the model restarted from the first segment's, hours old.
    let b = bundle("bundle-mlp13");
    let first = synth_log(T0, 5, 0.04, 5);
    let t1 = T0 + 5_000 * MS + 7 * 3_600_000 * MS;
    let mut second = synth_log(t1, 6, 0.04, 6);
    for s in &mut second.temp_shock {
        s.1 += 25.0; // the damper warmer after the gap
    }
    let mut samples = sorted_samples(&first);
    samples.extend(sorted_samples(&second));
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &samples);
    let ta = compute_features(&first, b.physics(), &b.groups).unwrap();
    let tb = compute_features(&second, b.physics(), &b.groups).unwrap();
    assert_eq!(est.counters().clock_jumps, 1);
    assert_same_as_batch(&b, &ticks[ta.n_rows()..], &tb);
}

/// The time of the last sample of `log`, ns.
fn last_sample_ns(log: &RunLog) -> i64 {
    sorted_samples(log).last().unwrap().t_ns()
}

#[test]
fn nan_samples_are_counted_not_fatal() {
    let b = bundle("bundle-mlp13");
    let mut log = synth_log(T0, 6, 0.04, 7);
    for i in [500, 1500, 2500] {
        log.acceleration[i].1 = f64::NAN;
    }
    log.position[300].1 = f64::NAN;
    log.force[100].1 = f64::INFINITY;
    log.temp_shock[3].1 = f64::NAN;
    let table = compute_features(&log, b.physics(), &b.groups).unwrap();
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &sorted_samples(&log));
    assert_eq!(est.counters().missing_samples, 6);
    assert_same_as_batch(&b, &ticks, &table);
    assert!(ticks.last().unwrap().estimate.pressure_avg_bar.is_finite());
}

#[test]
fn dropout_is_left_out_of_the_average_and_goes_unknown() {
    let b = bundle("bundle-mlp13");
    let mut log = synth_log(T0, 16, 0.04, 8);
    // The loadcell drops out from 6 s to 11 s.
    log.force
        .retain(|f| !(T0 + 6_000 * MS..T0 + 11_000 * MS).contains(&f.0));
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &sorted_samples(&log));
    let at = |t_ms: i64| {
        ticks
            .iter()
            .find(|t| t.row.t_ns == T0 + t_ms * MS)
            .unwrap()
            .estimate
    };
    assert_ne!(at(5_900).health, Health::Unknown);
    assert!(at(5_900).pressure_avg_bar.is_finite());
    // The features hold the last loadcell value: the network still answers…
    assert!(at(8_000).pressure_bar.is_finite());
    // …but after 1 s there is nothing to average, and after the dwell the
    // state is unknown.
    assert!(at(7_100).pressure_avg_bar.is_nan());
    assert_eq!(at(10_900).health, Health::Unknown);
    // Back after the dropout.
    assert!(at(11_500).pressure_avg_bar.is_finite());
    let c = est.counters();
    assert_eq!(c.ticks_stale, 250);
    assert!(c.gaps >= 250, "{c:?}");
}

#[test]
fn unknown_without_excitation() {
    let b = bundle("bundle-mlp13");
    // 0.1 mm amplitude: the 1 s velocity RMS stays far below 0.05 m/s.
    let log = synth_log(T0, 8, 1e-4, 9);
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &sorted_samples(&log));
    assert_eq!(ticks.len(), 400);
    assert!(ticks.iter().all(|t| t.estimate.health == Health::Unknown));
    assert!(ticks.iter().all(|t| t.estimate.pressure_avg_bar.is_nan()));
    // The network still gives an instantaneous value.
    assert!(ticks[399].estimate.pressure_bar.is_finite());
    // Excited, the same estimator judges (after the 3 s dwell).
    let log = synth_log(T0, 8, 0.04, 9);
    let mut est = estimator(&b);
    let ticks = stream(&mut est, &sorted_samples(&log));
    assert_ne!(ticks[399].estimate.health, Health::Unknown);
}

/// `bundle-mlp13` with a held-out interval of half-width `q` (as
/// `train.train --split runs` writes it).
fn bundle_with_interval(q: f64) -> (tempfile::TempDir, Arc<Bundle>) {
    let src =
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/bundle-mlp13");
    let dir = tempfile::tempdir().unwrap();
    for f in ["twin.json", "mlp.onnx"] {
        std::fs::copy(src.join(f), dir.path().join(f)).unwrap();
    }
    let path = dir.path().join("twin.json");
    let mut twin: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    twin["interval"] = serde_json::json!({
        "half_width_bar": q, "level": 0.95, "runs": ["held-out"], "ticks": 1000
    });
    std::fs::write(&path, twin.to_string()).unwrap();
    let b = Arc::new(Bundle::load(dir.path()).unwrap());
    (dir, b)
}

/// SPEC §2a/§6a for a bundle without the observer (a helper's audit: a
/// bundle trained now gave no interval and judged on the average alone):
/// its held-out half-width around the 1 s average, none while there is no
/// average, and the verdict by the interval.
#[test]
fn a_held_out_interval_brackets_the_average_and_decides_health() {
    let log = synth_log(T0, 8, 0.04, 9);
    let (_dir, b) = bundle_with_interval(0.5);
    let ticks = stream(&mut estimator(&b), &sorted_samples(&log));
    let plain = stream(
        &mut estimator(&bundle("bundle-mlp13")),
        &sorted_samples(&log),
    );
    let mut bracketed = 0;
    for (t, p) in ticks.iter().zip(&plain) {
        let (e, v1) = (&t.estimate, &p.estimate);
        assert!(
            v1.pressure_lo_bar.is_nan() && v1.pressure_hi_bar.is_nan(),
            "no interval without one"
        );
        assert_eq!(e.pressure_bar.to_bits(), v1.pressure_bar.to_bits());
        if v1.pressure_avg_bar.is_nan() {
            assert!(
                e.pressure_lo_bar.is_nan() && e.pressure_hi_bar.is_nan(),
                "{e:?}"
            );
        } else if v1.pressure_avg_bar > 0.5 {
            assert!(
                (e.pressure_hi_bar - v1.pressure_avg_bar - 0.5).abs() < 1e-12,
                "{e:?}"
            );
            assert!(
                (v1.pressure_avg_bar - e.pressure_lo_bar - 0.5).abs() < 1e-12,
                "{e:?}"
            );
            bracketed += 1;
        }
    }
    assert!(bracketed > 100, "{bracketed} ticks with an interval");
    // An interval wider than the thresholds' span decides nothing: `unknown`
    // where the average alone judged.
    let (_dir, wide) = bundle_with_interval(50.0);
    let ticks = stream(&mut estimator(&wide), &sorted_samples(&log));
    assert_ne!(plain[399].estimate.health, Health::Unknown);
    assert!(ticks.iter().all(|t| t.estimate.health == Health::Unknown));
    // Its lower bound is floored at 0 bar; the store's run summary takes the
    // estimate and half-width from before the floor (`Estimate::unfloored_*`).
    let mut floored = 0;
    for (t, p) in ticks.iter().zip(&plain) {
        let (e, v1) = (&t.estimate, &p.estimate);
        assert_eq!(e.unfloored_bar.to_bits(), v1.pressure_bar.to_bits());
        assert_eq!(v1.unfloored_bar.to_bits(), v1.pressure_bar.to_bits());
        assert!(v1.unfloored_half_bar.is_nan(), "no interval, no half");
        if e.pressure_avg_bar.is_finite() {
            assert!((e.unfloored_half_bar - 50.0).abs() < 1e-9, "{e:?}");
            if e.pressure_lo_bar == 0.0 {
                assert!(e.pressure_hi_bar - e.pressure_lo_bar < 100.0);
                floored += 1;
            }
        } else {
            assert!(e.unfloored_half_bar.is_nan(), "{e:?}");
        }
    }
    assert!(floored > 100, "{floored} floored ticks");
}

// ---- the health state machine on synthetic ticks ----

const TICK: i64 = TICK_NS;

/// Feeds `avg(t_s)` (excited) for `seconds` from `*t`; returns the states.
fn feed(
    m: &mut HealthMachine,
    t: &mut i64,
    seconds: f64,
    avg: impl Fn(f64) -> f64,
    excited: bool,
) -> Vec<Health> {
    let n = (seconds * 50.0).round() as usize;
    (0..n)
        .map(|_| {
            *t += TICK;
            m.update(*t, avg(*t as f64 / 1e9), excited)
        })
        .collect()
}

fn transitions(states: &[Health]) -> usize {
    states.windows(2).filter(|w| w[0] != w[1]).count()
}

#[test]
fn health_dwell_delays_every_change() {
    let mut m = HealthMachine::new(HealthConfig::default());
    let mut t = 0;
    assert_eq!(m.state(), Health::Unknown);
    let s = feed(&mut m, &mut t, 2.98, |_| 12.0, true);
    assert!(s.iter().all(|&h| h == Health::Unknown), "dwell 3 s");
    let s = feed(&mut m, &mut t, 0.04, |_| 12.0, true);
    assert_eq!(s.last(), Some(&Health::Ok));
    // A 2 s dip to 3 bar does not change the state…
    let s = feed(&mut m, &mut t, 2.0, |_| 3.0, true);
    assert!(s.iter().all(|&h| h == Health::Ok));
    feed(&mut m, &mut t, 1.0, |_| 12.0, true);
    // …a 3 s one does, at 3 s.
    let s = feed(&mut m, &mut t, 3.02, |_| 3.0, true);
    assert_eq!(s.iter().position(|&h| h == Health::Leak), Some(150));
}

#[test]
fn health_levels_and_hysteresis() {
    let mut m = HealthMachine::new(HealthConfig::default());
    let mut t = 0;
    let mut go =
        |m: &mut HealthMachine, avg: f64| *feed(m, &mut t, 3.1, |_| avg, true).last().unwrap();
    assert_eq!(go(&mut m, 8.0), Health::Low);
    assert_eq!(go(&mut m, 9.3), Health::Low, "left at warn + 0.5");
    assert_eq!(go(&mut m, 9.6), Health::Ok);
    assert_eq!(go(&mut m, 8.99), Health::Low);
    assert_eq!(go(&mut m, 4.9), Health::Leak);
    assert_eq!(go(&mut m, 5.4), Health::Leak, "left at fault + 0.5");
    assert_eq!(
        go(&mut m, 9.2),
        Health::Low,
        "from leak, ok only at warn + 0.5"
    );
    assert_eq!(go(&mut m, 4.0), Health::Leak);
    assert_eq!(go(&mut m, 12.0), Health::Ok);
}

#[test]
fn health_does_not_flap_at_the_threshold() {
    // A 1 s average hovering at the warn threshold: slow drift ±0.3 bar
    // (period 20 s) plus tick noise ±0.1 bar, for 10 minutes.
    let hover = |t_s: f64| {
        let mut r = Rng(t_s.to_bits());
        9.0 + 0.3 * (2.0 * std::f64::consts::PI * t_s / 20.0).sin() + 0.1 * r.noise()
    };
    let cfg = HealthConfig::default();
    let mut m = HealthMachine::new(cfg);
    let mut t = 0;
    let states = feed(&mut m, &mut t, 600.0, hover, true);
    assert!(
        transitions(&states) <= 2,
        "{} transitions",
        transitions(&states)
    );
    // Without hysteresis the same signal flaps (the test can fail).
    let mut m = HealthMachine::new(HealthConfig {
        hysteresis_bar: 0.0,
        ..cfg
    });
    let mut t = 0;
    let states = feed(&mut m, &mut t, 600.0, hover, true);
    assert!(transitions(&states) > 20, "{}", transitions(&states));
}

#[test]
fn health_unknown_without_excitation_or_average() {
    let mut m = HealthMachine::new(HealthConfig::default());
    let mut t = 0;
    feed(&mut m, &mut t, 4.0, |_| 12.0, true);
    assert_eq!(m.state(), Health::Ok);
    // A 1 s pause in excitation is bridged…
    let s = feed(&mut m, &mut t, 1.0, |_| 12.0, false);
    assert!(s.iter().all(|&h| h == Health::Ok));
    feed(&mut m, &mut t, 1.0, |_| 12.0, true);
    // …a long one is unknown after the dwell, whatever the average says.
    let s = feed(&mut m, &mut t, 3.02, |_| 3.0, false);
    assert_eq!(s.iter().position(|&h| h == Health::Unknown), Some(150));
    assert!(s.iter().all(|&h| h != Health::Leak));
    // No average (no usable data): unknown too.
    feed(&mut m, &mut t, 4.0, |_| 12.0, true);
    assert_eq!(m.state(), Health::Ok);
    feed(&mut m, &mut t, 3.1, |_| f64::NAN, true);
    assert_eq!(m.state(), Health::Unknown);
}

#[test]
fn one_far_future_timestamp_is_an_outlier_not_the_end_of_the_run() {
    let b = bundle("bundle-mlp13");
    let log = synth_log(T0, 4, 0.04, 4);
    let samples = sorted_samples(&log);
    let reference = {
        let mut est = estimator(&b);
        stream(&mut est, &samples)
    };
    let mut est = estimator(&b);
    let mut ticks = Vec::new();
    for (i, s) in samples.iter().enumerate() {
        est.push(*s).unwrap();
        if i == samples.len() / 3 || i == samples.len() / 2 {
            // A corrupt time stamp (a flipped high bit), then the stream goes on.
            est.push(Sample::Force {
                t_ns: T0 + (1_i64 << 60),
                force_n: 100.0,
            })
            .unwrap();
        }
        ticks.extend(est.drain());
    }
    est.finish().unwrap();
    ticks.extend(est.drain());
    let c = est.counters();
    assert_eq!(c.timestamp_outliers, 2);
    assert_eq!((c.late_dropped, c.clock_jumps), (0, 0));
    assert_eq!(
        ticks.len(),
        reference.len(),
        "ticks lost after the outliers"
    );
    let p = |e: &[dt_core::estimate::Estimate]| {
        e.iter()
            .map(|e| e.pressure_bar.to_bits())
            .collect::<Vec<_>>()
    };
    assert_eq!(
        p(&ticks),
        p(&reference.iter().map(|t| t.estimate).collect::<Vec<_>>())
    );
}

/// Checkpoint and restore at any point (here: several cuts, one inside the
/// re-order window with estimates not yet drained) continue exactly: every
/// later tick is bit-identical to the uninterrupted run's.
#[test]
fn checkpoint_restore_continues_bit_for_bit() {
    for name in ["bundle-mlp13", "bundle-force-skl"] {
        let b = bundle(name);
        let log = synth_log(T0, 8, 0.04, 7);
        let samples = sorted_samples(&log);
        let whole = stream(&mut estimator(&b), &samples);
        for cut in [1, 517, samples.len() / 2, samples.len() - 3] {
            let mut est = estimator(&b);
            let mut ticks = Vec::new();
            for s in &samples[..cut] {
                est.push(*s).unwrap();
                if cut != samples.len() / 2 {
                    ticks.extend(est.drain_ticks());
                }
            }
            let bytes = est.checkpoint();
            drop(est);
            let mut est = Estimator::restore(Arc::clone(&b), &bytes).unwrap();
            ticks.extend(stream(&mut est, &samples[cut..]));
            assert_eq!(ticks.len(), whole.len(), "{name} cut {cut}");
            for (i, (a, w)) in ticks.iter().zip(&whole).enumerate() {
                let same = |x: f64, y: f64| x.to_bits() == y.to_bits();
                assert!(
                    a.row.t_ns == w.row.t_ns
                        && a.estimate.health == w.estimate.health
                        && same(a.estimate.pressure_bar, w.estimate.pressure_bar)
                        && same(a.estimate.pressure_avg_bar, w.estimate.pressure_avg_bar)
                        && same(a.estimate.velocity_mps, w.estimate.velocity_mps)
                        && same(a.estimate.oil_temp_c, w.estimate.oil_temp_c)
                        && a.row
                            .values
                            .iter()
                            .zip(&w.row.values)
                            .all(|(x, y)| same(*x, *y)),
                    "{name} cut {cut} tick {i}: {a:?} vs {w:?}"
                );
            }
            assert_eq!(est.counters(), estimator_counters(&b, &samples), "{name}");
        }
    }
}

fn estimator_counters(
    b: &Arc<Bundle>,
    samples: &[Sample],
) -> dt_core::estimator::EstimatorCounters {
    let mut est = estimator(b);
    stream(&mut est, samples);
    est.counters()
}

/// A checkpoint of another model, or bytes that are not one, are refused
/// with a reason; nothing panics.
#[test]
fn checkpoint_of_another_model_or_garbage_is_refused() {
    let a = bundle("bundle-mlp13");
    let b = bundle("bundle-force-skl");
    let mut est = estimator(&a);
    for s in sorted_samples(&synth_log(T0, 2, 0.04, 3)) {
        est.push(s).unwrap();
    }
    let bytes = est.checkpoint();
    let err = Estimator::restore(Arc::clone(&b), &bytes).unwrap_err();
    assert!(
        err.to_string().contains("another model") || err.to_string().contains("model"),
        "{err}"
    );
    for bad in [&[][..], &bytes[..bytes.len() / 2], &[0xff; 64][..]] {
        let err = Estimator::restore(Arc::clone(&a), bad).unwrap_err();
        assert!(!err.to_string().is_empty());
    }
    assert!(Estimator::restore(Arc::clone(&a), &bytes).is_ok());
}

/// An estimator with the road calibration fixture, its blocks shortened to
/// 2 s (settling 1 s) so that a 12 s synthetic run reads several.
/// The road calibration fixture with 2 s blocks.
fn road_calibration() -> dt_core::road::RoadCalibration {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/road.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir).unwrap()).unwrap();
    v["block_s"] = 2.0.into();
    v["settle_s"] = 1.0.into();
    dt_core::road::RoadCalibration::from_json("road.json", &v.to_string()).unwrap()
}

fn road_estimator(b: &Arc<Bundle>) -> Estimator {
    estimator(b).with_road(road_calibration()).unwrap()
}

/// With the road observer the estimates carry its estimate and interval
/// (the prior's until its first block, then narrower); shuffled within the
/// re-order window, and checkpointed and restored anywhere, every tick is
/// the same bit for bit (the NATS workers' failover).
#[test]
fn the_road_observer_streams_and_checkpoints_bit_for_bit() {
    let b = bundle("bundle-mlp13");
    let samples = sorted_samples(&synth_log(T0, 12, 0.04, 11));
    let whole = stream(&mut road_estimator(&b), &samples);
    let first = whole[0].estimate;
    let last = whole.last().unwrap().estimate;
    // the prior's interval, no lower than ambient (0 bar gauge)
    let (prior_lo, prior_hi) = road_calibration().prior_interval();
    assert!(prior_hi - prior_lo > 20.0 && prior_lo < 0.0);
    assert_eq!(
        (first.pressure_lo_bar, first.pressure_hi_bar),
        (0.0, prior_hi),
        "{first:?}"
    );
    assert!(
        last.pressure_hi_bar - last.pressure_lo_bar < first.pressure_hi_bar - first.pressure_lo_bar,
        "{last:?}"
    );
    assert!(whole
        .iter()
        .all(|t| t.estimate.pressure_bar.to_bits() == t.estimate.pressure_avg_bar.to_bits()));
    let same = |a: &[Tick], w: &[Tick], what: &str| {
        assert_eq!(a.len(), w.len(), "{what}");
        for (i, (a, w)) in a.iter().zip(w).enumerate() {
            let (x, y) = (a.estimate, w.estimate);
            assert!(
                x.t_ns == y.t_ns
                    && x.health == y.health
                    && x.pressure_bar.to_bits() == y.pressure_bar.to_bits()
                    && x.pressure_lo_bar.to_bits() == y.pressure_lo_bar.to_bits()
                    && x.pressure_hi_bar.to_bits() == y.pressure_hi_bar.to_bits(),
                "{what} tick {i}: {x:?} vs {y:?}"
            );
        }
    };
    same(
        &stream(&mut road_estimator(&b), &shuffled(&samples, 60 * MS, 5)),
        &whole,
        "shuffled",
    );
    for cut in [1, 4_321, samples.len() / 2, samples.len() - 3] {
        let mut est = road_estimator(&b);
        let mut ticks = Vec::new();
        for s in &samples[..cut] {
            est.push(*s).unwrap();
            ticks.extend(est.drain_ticks());
        }
        let bytes = est.checkpoint();
        drop(est);
        let mut est = Estimator::restore(Arc::clone(&b), &bytes).unwrap();
        ticks.extend(stream(&mut est, &samples[cut..]));
        same(&ticks, &whole, &format!("cut {cut}"));
    }
}

/// After a service the road estimator reads the unit's road baseline from
/// every block it reads: the same, to the bit, as the calibration's
/// `read_baseline` over the blocks the observer reads of the whole run, and
/// across a checkpoint.
#[test]
fn a_road_baseline_is_read_block_by_block_and_survives_a_checkpoint() {
    let b = bundle("bundle-mlp13");
    let samples = sorted_samples(&synth_log(T0, 12, 0.04, 11));
    let mut est = road_estimator(&b).read_road_baseline(12.0);
    stream(&mut est, &samples);
    let read = est.road_baseline().unwrap().unwrap();
    assert!(read.blocks >= 3 && read.offset_n.is_finite(), "{read:?}");

    let cal = road_calibration();
    let mut obs = dt_core::road::RoadObserver::new(cal.clone(), HealthConfig::default()).unwrap();
    for s in &samples {
        obs.push(s);
    }
    obs.finish();
    assert_eq!(cal.read_baseline(&obs.drain(), 12.0).unwrap(), read);

    let cut = samples.len() / 2;
    let mut est = road_estimator(&b).read_road_baseline(12.0);
    for s in &samples[..cut] {
        est.push(*s).unwrap();
    }
    let mut est = Estimator::restore(Arc::clone(&b), &est.checkpoint()).unwrap();
    stream(&mut est, &samples[cut..]);
    assert_eq!(est.road_baseline().unwrap().unwrap(), read);
    assert!(road_estimator(&b).road_baseline().is_none());
}

/// The road observer counts its blocks: a drive reads them; a stroke of a
/// tenth of a millimetre (a parked car's engine) reads none, and says why.
#[test]
fn the_road_observer_says_why_it_read_no_block() {
    let b = bundle("bundle-mlp13");
    let mut est = road_estimator(&b);
    stream(&mut est, &sorted_samples(&synth_log(T0, 12, 0.04, 11)));
    let drive = est.counters().road.unwrap();
    assert!(drive.read >= 3 && drive.why_none().is_none(), "{drive:?}");
    let mut est = road_estimator(&b);
    stream(&mut est, &sorted_samples(&synth_log(T0, 12, 0.000_1, 11)));
    let rest = est.counters().road.unwrap();
    assert_eq!(rest.read, 0, "{rest:?}");
    assert!(rest.at_rest > 0, "{rest:?}");
    assert!(rest.why_none().unwrap().contains("at rest"), "{rest:?}");
    assert!(estimator(&b).counters().road.is_none());
    // the same drive (0.36 m/s stroke RMS) with a calibration whose slowest
    // block was faster, then slower, than that
    let read_with = |slowest: f64| {
        let mut cal = road_calibration();
        cal.filters.slowest_calibrated_stroke_rms_mps = Some(slowest);
        let mut est = estimator(&b).with_road(cal).unwrap();
        stream(&mut est, &sorted_samples(&synth_log(T0, 12, 0.04, 11)));
        est.counters().road.unwrap()
    };
    let slow = read_with(0.5);
    assert_eq!((slow.read, slow.at_rest), (0, 0), "{slow:?}");
    assert_eq!(slow.slower_than_calibrated, drive.read, "{slow:?}");
    let why = slow.why_none().unwrap();
    assert!(
        why.contains("slower than the calibration's slowest"),
        "{why}"
    );
    assert_eq!(read_with(0.3), drive);
}
