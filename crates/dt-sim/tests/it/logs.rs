//! Written logs read back through dt-core; run procedure and metadata.

use dt_core::log::read_log;
use dt_sim::{simulate_run, PlantParams, RunSpec, StopReason};

#[test]
fn quick_run_file_reads_back_with_metadata() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let spec = RunSpec {
        quick: true,
        ..RunSpec::paper(12.0, 2.0, 1)
    };
    let summary = simulate_run(&spec, &PlantParams::nominal(), &path).unwrap();
    assert_eq!(summary.stop, StopReason::QuickLimit);
    let log = read_log(&path).unwrap();
    let m = &log.metadata;
    assert_eq!(m.asset_id, "dyno-unit-A");
    assert_eq!(m.run_id, "p12.0-f2.0-s1");
    assert_eq!(m.charge_pressure_bar, Some(12.0));
    assert_eq!(m.excitation.as_deref(), Some("sine 2 Hz 80 mm p-p"));
    assert_eq!(m.frequency_hz, Some(2.0));
    assert_eq!(m.stroke_pp_m, Some(0.08));
    assert_eq!(m.extra.get("simulated").map(String::as_str), Some("true"));
    assert_eq!(m.extra.get("seed").map(String::as_str), Some("1"));
    let n = log.position.len()
        + log.acceleration.len()
        + log.force.len()
        + log.temp_shock.len()
        + log.temp_ambient.len()
        + log.truth_pressure.len()
        + log.truth_velocity.len();
    assert_eq!(n as u64, summary.messages);
    assert_eq!(log.acceleration.len(), 70_001);
    // The excitation is visible: +-40 mm on the potentiometer.
    let max = log.position.iter().map(|p| p.1).fold(f64::MIN, f64::max);
    let min = log.position.iter().map(|p| p.1).fold(f64::MAX, f64::min);
    assert!(
        (0.038..0.042).contains(&max) && (-0.042..-0.038).contains(&min),
        "{min} {max}"
    );
    // Rebound force about twice compression (notes), sign convention: tension > 0.
    let fmax = log.force.iter().map(|p| p.1).fold(f64::MIN, f64::max);
    let fmin = log.force.iter().map(|p| p.1).fold(f64::MAX, f64::min);
    let ratio = fmax / -fmin;
    assert!(
        (1.4..2.8).contains(&ratio),
        "rebound {fmax} N, compression {fmin} N"
    );

    // Simulator truth velocity: at the position instants, zero at rest, the
    // 2 Hz, 80 mm p-p sine's peak 0.04 * 4 pi = 0.503 m/s while excited, and
    // the sign of the position's rate (positive in extension).
    let t_pos: Vec<i64> = log.position.iter().map(|p| p.0).collect();
    let t_vel: Vec<i64> = log.truth_velocity.iter().map(|v| v.0).collect();
    assert_eq!(t_vel, t_pos);
    let rest = log.truth_velocity.iter().take(900);
    assert!(rest.map(|v| v.1.abs()).fold(0.0, f64::max) < 1e-3);
    let vmax = log
        .truth_velocity
        .iter()
        .map(|v| v.1.abs())
        .fold(0.0, f64::max);
    assert!((0.48..0.53).contains(&vmax), "peak velocity {vmax}");
    let (mut dot, mut n_rate) = (0.0, 0.0);
    for (w, v) in log.position.windows(3).zip(&log.truth_velocity[1..]) {
        let rate = (w[2].1 - w[0].1) / ((w[2].0 - w[0].0) as f64 * 1e-9);
        dot += rate * v.1;
        n_rate += rate * rate;
    }
    let n_vel: f64 = log.truth_velocity.iter().map(|v| v.1 * v.1).sum();
    let corr = dot / (n_rate * n_vel).sqrt();
    assert!(corr > 0.99, "correlation with the position's rate {corr}");

    let varied = RunSpec {
        unit: Some(3),
        ..spec
    };
    assert_eq!(varied.asset_id(), "dyno-unit-U3");
    assert_eq!(varied.run_id(), "p12.0-f2.0-s1-u3");
}

#[test]
fn full_4_hz_run_stops_at_80_c_within_minutes() {
    let spec = RunSpec::paper(12.0, 4.0, 1);
    let summary = dt_sim::simulate_run_with(&spec, &PlantParams::nominal(), |_| Ok(())).unwrap();
    assert_eq!(summary.stop, StopReason::Temperature);
    assert!(summary.final_shock_reading_c >= 80.0);
    assert!(
        (60.0..600.0).contains(&summary.excitation_s),
        "excitation {} s",
        summary.excitation_s
    );
    // The oil is hotter than the surface reading.
    assert!(summary.final_oil_c > summary.final_shock_reading_c);
    // Energy bookkeeping: stored + lost = dissipated (within 0.5 %).
    assert!(summary.heat_to_room_j < summary.energy_dissipated_j);
}

/// The one run of the campaign `spec`, simulated into `dir/name` and read back.
fn only_run(
    dir: &std::path::Path,
    name: &str,
    spec: &dt_sim::CampaignSpec,
) -> dt_core::log::RunLog {
    let out = dir.join(name);
    dt_sim::simulate_campaign(spec, &out).unwrap();
    let path = std::fs::read_dir(&out)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    read_log(&path).unwrap()
}

/// The body accelerometer's mean over the first 5 s (at rest): the rig's offset and gain.
fn rest_a2(log: &dt_core::log::RunLog) -> f64 {
    let v: Vec<f64> = log.acceleration.iter().take(5000).map(|a| a.2).collect();
    v.iter().sum::<f64>() / v.len() as f64
}

/// A drive file of its own seed on the campaign's rig: the rig's sensor errors
/// stay the campaign seed's (the accelerometers' reading at rest), the road is
/// the drive seed's (the stroke), and the run id and metadata say so.
#[test]
fn a_drive_seed_plays_another_road_on_the_same_sensors() {
    let dir = tempfile::tempdir().unwrap();
    let road = |seed: u64| dt_sim::RoadDrive {
        speed_kmh: 60.0,
        class: dt_sim::RoadClass::C,
        seed,
    };
    let run = |name: &str, seed: u64, drive: Option<u64>| {
        let spec = dt_sim::CampaignSpec {
            pressures_bar: vec![12.0],
            quick: true,
            road: Some(road(seed)),
            drive_seed: drive,
            ..dt_sim::CampaignSpec::paper(seed)
        };
        only_run(dir.path(), name, &spec)
    };
    let (rig4, rig4_road6, rig6) = (run("a", 4, None), run("b", 4, Some(6)), run("c", 6, None));
    assert_eq!(rig4_road6.metadata.run_id, "p12.0-roadC60-s4-d6");
    let extra = |log: &dt_core::log::RunLog, key: &str| log.metadata.extra.get(key).cloned();
    assert_eq!(extra(&rig4_road6, "drive_seed").as_deref(), Some("6"));
    assert_eq!(extra(&rig4_road6, "seed").as_deref(), Some("4"));
    assert_eq!(extra(&rig4, "drive_seed"), None);
    // the body accelerometer at rest: the rig's
    assert!((rest_a2(&rig4_road6) - rest_a2(&rig4)).abs() < 0.005);
    assert!((rest_a2(&rig4_road6) - rest_a2(&rig6)).abs() > 0.03);
    // the stroke while driving: the drive seed's road
    let stroke = |log: &dt_core::log::RunLog| -> Vec<f64> {
        log.position.iter().skip(2000).map(|p| p.1).collect()
    };
    let corr = |a: &[f64], b: &[f64]| {
        let n = a.len().min(b.len());
        let (ma, mb) = (
            a[..n].iter().sum::<f64>() / n as f64,
            b[..n].iter().sum::<f64>() / n as f64,
        );
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for i in 0..n {
            sab += (a[i] - ma) * (b[i] - mb);
            saa += (a[i] - ma) * (a[i] - ma);
            sbb += (b[i] - mb) * (b[i] - mb);
        }
        sab / (saa * sbb).sqrt()
    };
    assert!(corr(&stroke(&rig4_road6), &stroke(&rig6)) > 0.99);
    assert!(corr(&stroke(&rig4_road6), &stroke(&rig4)).abs() < 0.5);
}

/// A rig seed of its own: the sensors' errors are the rig seed's (the body
/// accelerometer's reading at rest is the campaign of that seed's), the room
/// and the noise stay the campaign seed's, and the run id and metadata say so.
#[test]
fn a_rig_seed_reads_the_same_run_on_another_rig() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, seed: u64, rig: Option<u64>| {
        let spec = dt_sim::CampaignSpec {
            pressures_bar: vec![12.0],
            frequencies_hz: vec![2.0],
            quick: true,
            rig_seed: rig,
            ..dt_sim::CampaignSpec::paper(seed)
        };
        only_run(dir.path(), name, &spec)
    };
    let (run4, run4_rig6, run6) = (run("a", 4, None), run("b", 4, Some(6)), run("c", 6, None));
    assert_eq!(run4_rig6.metadata.run_id, "p12.0-f2.0-s4-g6");
    let extra = |log: &dt_core::log::RunLog, key: &str| log.metadata.extra.get(key).cloned();
    assert_eq!(extra(&run4_rig6, "rig_seed").as_deref(), Some("6"));
    assert_eq!(extra(&run4_rig6, "seed").as_deref(), Some("4"));
    assert_eq!(extra(&run4, "rig_seed"), None);
    // the body accelerometer at rest: the rig's
    assert!((rest_a2(&run4_rig6) - rest_a2(&run6)).abs() < 0.005);
    assert!((rest_a2(&run4_rig6) - rest_a2(&run4)).abs() > 0.03);
    // the noise: the campaign seed's (the potentiometer, whose errors are the
    // run's, reads run 4's values at rest, sample for sample)
    let rest_pos = |log: &dt_core::log::RunLog| -> Vec<f64> {
        log.position.iter().take(200).map(|p| p.1).collect()
    };
    assert_eq!(rest_pos(&run4_rig6), rest_pos(&run4));
    assert_ne!(rest_pos(&run4_rig6), rest_pos(&run6));
}

/// A leak history under an asset id of its own reports that asset, as its
/// files name it (it reported the unit's default).
#[test]
fn a_leak_history_reports_the_asset_its_files_name() {
    let dir = tempfile::tempdir().unwrap();
    let spec = dt_sim::LeakHistorySpec {
        start_bar: 12.0,
        leak_bar_per_day: 0.6,
        days: 1,
        frequency_hz: 2.0,
        seed: 1,
        quick: true,
        unit: None,
        asset_id: Some("van-07".into()),
        road: None,
    };
    let runs = dt_sim::simulate_leak_history(&spec, dir.path(), &|_| {}).unwrap();
    let path = runs[0].path.as_ref().unwrap();
    assert_eq!(read_log(path).unwrap().metadata.asset_id, "van-07");
    assert_eq!(runs[0].asset_id, "van-07");
}
