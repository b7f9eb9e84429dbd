//! The twin's physics: one Kalman predict+update, one RK4 step of the thermal
//! model, one force-model evaluation, and the 50 Hz feature pipeline over one
//! hour of synthetic sensor data at SPEC rates (acceleration 1 kHz, position
//! 100 Hz, force 50 Hz, two temperatures 1 Hz): a 2 Hz, 80 mm p-p sine with
//! deterministic pseudo-random noise.

#![allow(missing_docs)]

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dt_core::charge::{reversal_window_a2, ChargeObserver, DampingLaw, ObserverParams};
use dt_core::features::{compute_features, FeaturePipeline, Group, TopicSet};
use dt_core::force::ForceModel;
use dt_core::kalman::KalmanFilter;
use dt_core::log::{RunLog, RunMetadata};
use dt_core::params::PhysicsParams;
use dt_core::thermal::{ThermalModel, ThermalState};

const MS: i64 = 1_000_000;

/// xorshift64*: uniform in [-1, 1).
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let x = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D);
        (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

/// `seconds` of a dyno run at SPEC rates.
fn synth_log(seconds: i64) -> RunLog {
    let w = 2.0 * std::f64::consts::PI * 2.0;
    let amp = 0.04;
    let mut noise = Noise(0x5EED_1234_ABCD_0001);
    let mut log = RunLog {
        metadata: RunMetadata {
            asset_id: "bench".into(),
            run_id: "bench-1h".into(),
            ..RunMetadata::default()
        },
        ..RunLog::default()
    };
    for i in 0..seconds * 1000 {
        let t_ns = i * MS;
        let t = t_ns as f64 * 1e-9;
        let a = -amp * w * w * (w * t).sin();
        log.acceleration
            .push((t_ns, a + 0.3 + 0.06 * noise.next(), 0.06 * noise.next()));
        if i % 10 == 0 {
            log.position
                .push((t_ns, amp * (w * t).sin() + 1e-3 * noise.next()));
        }
        if i % 20 == 0 {
            log.force
                .push((t_ns, 2500.0 * (w * t).cos() - 380.0 + 40.0 * noise.next()));
        }
        if i % 1000 == 0 {
            log.temp_shock
                .push((t_ns, 25.0 + 50.0 * (t / 3600.0) + 0.25 * noise.next()));
            log.temp_ambient.push((t_ns, 21.5 + 0.25 * noise.next()));
        }
    }
    log
}

fn bench_models(c: &mut Criterion) {
    let params = PhysicsParams::default();
    let mut group = c.benchmark_group("physics");

    // One position event: propagate 10 ms (F P Fᵀ + Q) and Joseph update.
    group.bench_function("kalman_predict_update", |b| {
        let mut kf = KalmanFilter::new(params.kalman);
        kf.position(0, 0.0).unwrap();
        let mut t = 0i64;
        let mut k = 0u32;
        b.iter(|| {
            t += 10 * MS;
            k = k.wrapping_add(1);
            let z = 0.04 * (f64::from(k % 100) * 0.0628).sin();
            kf.position(black_box(t), black_box(z)).unwrap();
        });
        black_box(kf.state());
    });

    // One accelerometer event: propagate 1 ms, hold the new input.
    group.bench_function("kalman_predict", |b| {
        let mut kf = KalmanFilter::new(params.kalman);
        kf.position(0, 0.0).unwrap();
        let mut t = 0i64;
        b.iter(|| {
            t += MS;
            kf.accel(black_box(t), black_box(1.5)).unwrap();
        });
        black_box(kf.state());
    });

    let thermal = ThermalModel::new(params.thermal);
    group.bench_function("thermal_rk4_step", |b| {
        let s = ThermalState {
            oil_c: 45.0,
            cyl_c: 40.0,
        };
        b.iter(|| {
            thermal.step(
                black_box(s),
                black_box(0.02),
                black_box(250.0),
                black_box(21.0),
            )
        });
    });

    let force = ForceModel::new(params.force);
    group.bench_function("force_eval", |b| {
        b.iter(|| {
            force.force(
                black_box(0.31),
                black_box(-4.2),
                black_box(0.012),
                black_box(55.0),
            )
        });
    });
    group.finish();
}

fn bench_pipeline(c: &mut Criterion) {
    let params = PhysicsParams::default();
    let log = synth_log(3600);
    let samples = dt_core::features::sorted_samples(&log);
    let mut group = c.benchmark_group("features_1h");
    group.sample_size(10);
    group.throughput(Throughput::Elements(samples.len() as u64));

    // The streaming path: push every sample, take every row.
    group.bench_function("pipeline_push", |b| {
        b.iter(|| {
            let mut pipe = FeaturePipeline::new(&params, TopicSet::all()).unwrap();
            let mut acc = 0.0;
            for s in &samples {
                pipe.push(s).unwrap();
                while let Some(row) = pipe.pop() {
                    acc += row.values[3];
                }
            }
            pipe.finish();
            black_box(acc)
        });
    });

    // The batch path (shocktwin.features): topic check, sort, pipeline, table.
    group.bench_function("compute_features_all_groups", |b| {
        b.iter(|| {
            compute_features(black_box(&log), &params, &Group::ALL)
                .unwrap()
                .t_ns
                .len()
        });
    });
    group.finish();
}

/// The damping law `observer fit` calibrated on the simulated default campaign
/// (seed 1, sixth session), rounded: the window fit's cost depends on it.
fn campaign_law() -> DampingLaw {
    DampingLaw {
        knots_mps: [-0.15, -0.09, -0.05, -0.025, 0.025, 0.05, 0.09, 0.15],
        width_mps: 0.008,
        viscous_nspm: [
            -88.1, 1001.4, -1531.1, 5797.5, -4938.6, 684.7, -4582.5, -1725.4, 6335.4,
        ],
        dry_nspm: [
            1520.3, 699.4, 2471.1, -6397.2, 8009.5, 1672.9, 2712.2, 2920.3, -7568.3,
        ],
        beta_per_k: 0.0303,
        valves: None,
    }
}

/// The charge observer's work per reversal, all of it in the window fit
/// (Levenberg–Marquardt on the RK4 window model): a 2 Hz stroke (`|ÿ|` 6.16
/// m/s², reversals 0.25 s apart) and a 4 Hz one (24.2 m/s², 0.125 s: the
/// friction turns over 4x faster, and the RK4 step with it) whose `a2` is the
/// window model itself with the campaign's law, friction amplitude 45 N and
/// 0.05 m/s² of noise, at 1 kHz, and the stroke velocity 4 ms late, as the
/// Kalman filter's is on the simulated dyno (the fits find the reversal
/// 3.8–4.3 ms before the velocity's zero); one observer over 16 reversals per
/// iteration. `window_model_*`: one evaluation of that window model alone
/// (the observer's window, 4 ms shift), which the damping law's fit
/// (`train/damping_law.py`) makes for every window at every residual.
fn bench_charge(c: &mut Criterion) {
    const REVERSALS: usize = 16;
    const KALMAN_LAG_S: f64 = 0.004;
    let params = ObserverParams {
        damping_law: campaign_law(),
        step_offset_n: 26.7,
        step_per_bar_n: 1.3,
        step_sd_n: 2.4,
        ..ObserverParams::default()
    };
    let oil_c = 60.0;
    let mut group = c.benchmark_group("charge");
    group.sample_size(10);
    for (name, half, accel_mag) in [
        ("window_fit_2hz", 0.25, 6.16),
        ("window_fit_4hz", 0.125, 24.2),
    ] {
        let mut noise = Noise(0x5DEE_CE66_D1CE_5EED);
        let mut samples = Vec::new();
        let per_half = (half / 1e-3_f64).round() as u32;
        for k in 0..REVERSALS {
            let accel = if k % 2 == 0 { -accel_mag } else { accel_mag };
            let t0 = k as f64 * half;
            let t_r = t0 + 0.5 * half;
            let times: Vec<f64> = (0..per_half)
                .map(|i| t0 + f64::from(i) * 1e-3 - t_r)
                .collect();
            let a2 = reversal_window_a2(&params, accel, oil_c, [45.0, 1.0, 1.0, 0.0, -9.8], &times);
            for (&s, &a) in times.iter().zip(&a2) {
                let t_ns = ((s + t_r) * 1e9).round() as i64;
                samples.push((t_ns, a + 0.05 * noise.next(), accel * (s - KALMAN_LAG_S)));
            }
        }
        // One window of the model alone, as the damping law's fit calls it
        // (`train/damping_law.py`: every window once per residual evaluation).
        let one: Vec<f64> = (0..per_half)
            .map(|i| f64::from(i) * 1e-3 - 0.5 * half)
            .filter(|s| (-params.window_pre_s..=params.window_post_s).contains(s))
            .collect();
        group.throughput(Throughput::Elements(1));
        group.bench_function(name.replace("fit", "model"), |b| {
            b.iter(|| {
                black_box(reversal_window_a2(
                    &params,
                    black_box(accel_mag),
                    oil_c,
                    [45.0, 1.0, 1.0, -4.0, -9.8],
                    &one,
                ))
            });
        });
        group.throughput(Throughput::Elements(REVERSALS as u64));
        group.bench_function(name, |b| {
            b.iter(|| {
                let mut obs = ChargeObserver::new(params).unwrap();
                obs.set_gas_temp_c(oil_c);
                for &(t_ns, a2, v) in &samples {
                    obs.sample(t_ns, black_box(a2), 0.0, v, f64::NAN);
                }
                let c = obs.counters();
                assert!(c.used + c.rejected >= REVERSALS as u64 - 2, "{c:?}");
                black_box(obs.estimate(samples.last().unwrap().0))
            });
        });
    }
    group.finish();
}

criterion_group!(benches, bench_models, bench_pipeline, bench_charge);
criterion_main!(benches);
