//! Sensor rates and noise as documented in the parameter table.

use dt_core::log::Sample;
use dt_sim::sensors::{RigErrors, Sensors};
use dt_sim::{simulate_run_with, PlantParams, RunSpec, Truth};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Standard deviation about a least-squares line (removes slow drift).
fn detrended_sd(t: &[f64], x: &[f64]) -> f64 {
    let n = t.len() as f64;
    let (mt, mx) = (t.iter().sum::<f64>() / n, x.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (ti, xi) in t.iter().zip(x) {
        sxy += (ti - mt) * (xi - mx);
        sxx += (ti - mt) * (ti - mt);
    }
    let slope = sxy / sxx;
    let ss: f64 = t
        .iter()
        .zip(x)
        .map(|(ti, xi)| {
            let r = xi - mx - slope * (ti - mt);
            r * r
        })
        .sum();
    (ss / (n - 2.0)).sqrt()
}

/// Expected rms of white noise `sd` quantised with step `lsb`.
fn quantised_sd(sd: f64, lsb: f64) -> f64 {
    (sd * sd + lsb * lsb / 12.0).sqrt()
}

#[test]
#[allow(clippy::too_many_lines)] // one scenario, many documented figures
fn at_rest_rates_and_noise_match_the_table() {
    let mut p = PlantParams::nominal();
    p.rest_s = 60.0;
    p.max_excitation_s = 1.0;
    let spec = RunSpec {
        charge_bar: 12.0,
        frequency_hz: 0.0,
        stroke_pp_m: 0.0,
        seed: 3,
        unit: None,
        quick: false,
        repeat: 0,
        road: None,
        truth_velocity_hz: dt_sim::run::DEFAULT_TRUTH_VELOCITY_HZ,
        drive_seed: None,
        rig_seed: None,
    };
    let mut samples = Vec::new();
    let summary = simulate_run_with(&spec, &p, |s| {
        samples.push(*s);
        Ok(())
    })
    .unwrap();
    assert_eq!(summary.messages as usize, samples.len());
    assert!(
        (summary.duration_s - 61.0).abs() < 1e-9,
        "{}",
        summary.duration_s
    );

    // Time order, and acceleration first at equal times.
    for w in samples.windows(2) {
        let key = |s: &Sample| (s.t_ns(), s.topic_rank());
        assert!(key(&w[0]) < key(&w[1]), "{:?} then {:?}", w[0], w[1]);
    }

    let mut series: std::collections::BTreeMap<&str, (Vec<f64>, Vec<Vec<f64>>)> =
        std::collections::BTreeMap::new();
    for s in &samples {
        let t = s.t_ns() as f64 * 1e-9;
        #[allow(clippy::match_wildcard_for_single_variants)]
        let values = match *s {
            Sample::Acceleration {
                a1_mps2, a2_mps2, ..
            } => vec![a1_mps2, a2_mps2],
            Sample::Position { position_m, .. } => vec![position_m],
            Sample::Force { force_n, .. } => vec![force_n],
            Sample::TempShock { temperature_c, .. } | Sample::TempAmbient { temperature_c, .. } => {
                vec![temperature_c]
            }
            Sample::TruthPressure { static_bar, .. } => vec![static_bar],
            // Other (truth) topics are not sensors.
            _ => continue,
        };
        let e = series.entry(s.topic()).or_default();
        e.0.push(t);
        e.1.push(values);
    }
    // 61 s inclusive of both ends: n = 61 * rate + 1.
    for (topic, rate) in [
        ("/acceleration", 1000.0),
        ("/position", 100.0),
        ("/force", 50.0),
        ("/temperature/shock", 1.0),
        ("/temperature/ambient", 1.0),
        ("/truth/gas_pressure", 10.0),
    ] {
        let (t, _) = &series[topic];
        assert_eq!(t.len(), (61.0 * rate) as usize + 1, "{topic}");
        for w in t.windows(2) {
            assert!((w[1] - w[0] - 1.0 / rate).abs() < 1e-6, "{topic} spacing");
        }
    }
    let col = |topic: &str, i: usize| -> (Vec<f64>, Vec<f64>) {
        let (t, v) = &series[topic];
        (t.clone(), v.iter().map(|row| row[i]).collect())
    };
    let checks = [
        (
            "/acceleration",
            0,
            quantised_sd(p.acc_noise_mps2, p.acc_lsb_mps2),
            0.05,
        ),
        (
            "/acceleration",
            1,
            quantised_sd(p.acc_noise_mps2, p.acc_lsb_mps2),
            0.05,
        ),
        (
            "/position",
            0,
            quantised_sd(p.pos_noise_m, p.pos_lsb_m),
            0.05,
        ),
        (
            "/force",
            0,
            quantised_sd(p.force_noise_n, p.force_lsb_n),
            0.08,
        ),
        (
            "/temperature/shock",
            0,
            quantised_sd(p.tc_noise_c, p.tc_lsb_c),
            0.4,
        ),
        (
            "/temperature/ambient",
            0,
            quantised_sd(p.tc_noise_c, p.tc_lsb_c),
            0.4,
        ),
    ];
    for (topic, i, want, rel) in checks {
        let (t, x) = col(topic, i);
        let sd = detrended_sd(&t, &x);
        assert!(
            (sd / want - 1.0).abs() < rel,
            "{topic}[{i}]: sd {sd:.4e}, documented {want:.4e}"
        );
    }
    // At rest both accelerometers read about -1 g (specific force along the
    // downward extension axis), within the documented offsets.
    for i in 0..2 {
        let (_, x) = col("/acceleration", i);
        let mean = x.iter().sum::<f64>() / x.len() as f64;
        assert!(
            (mean + p.acc_g_mps2).abs() < 4.0 * p.acc_offset_sd_mps2 + 0.05 * p.acc_g_mps2,
            "a{} mean {mean}",
            i + 1
        );
    }
    // The loadcell at rest reads the gas force, -(p - p_atm) A_rod, within
    // its zero error.
    let (_, f) = col("/force", 0);
    let mean_f = f.iter().sum::<f64>() / f.len() as f64;
    let (_, truth) = col("/truth/gas_pressure", 0);
    let gas_n = -truth[0] * 1e5 * p.rod_area_m2();
    let friction_free = mean_f - gas_n;
    assert!(
        friction_free.abs() < 4.0 * p.force_zero_sd_n,
        "force {mean_f} vs gas {gas_n}"
    );
}

#[test]
fn accelerometers_clip_at_8_g() {
    let p = PlantParams::nominal();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let rig = RigErrors::draw(&p, &mut rng);
    let truth = Truth {
        rod_acc_mps2: 200.0,
        body_acc_mps2: -200.0,
        room_c: 20.0,
        ..Truth::default()
    };
    let mut s = Sensors::new(&p, rig, rng, &truth, 2.5e-4);
    s.update(&truth);
    let (a1, a2) = s.sample_acceleration();
    assert!((a1 - p.acc_range_mps2).abs() < 1e-12, "{a1}");
    assert!((a2 + p.acc_range_mps2).abs() < 1e-12, "{a2}");
}

#[test]
fn truth_velocity_at_1_khz_changes_nothing_else() {
    let mut p = PlantParams::nominal();
    p.rest_s = 0.5;
    p.max_excitation_s = 1.5;
    let run = |hz: u32| -> Result<(Vec<Sample>, Vec<Sample>), dt_sim::SimError> {
        let spec = RunSpec {
            truth_velocity_hz: hz,
            ..RunSpec::paper(4.0, 2.0, 5)
        };
        let (mut truth, mut rest) = (Vec::new(), Vec::new());
        simulate_run_with(&spec, &p, |s| {
            match s {
                Sample::TruthVelocity { .. } => truth.push(*s),
                _ => rest.push(*s),
            }
            Ok(())
        })?;
        Ok((truth, rest))
    };
    let (truth_100, rest_100) = run(100).unwrap();
    let (truth_1k, rest_1k) = run(1000).unwrap();
    // Every other topic bit for bit: the truth's rate is logging only.
    assert_eq!(rest_1k, rest_100);
    // Fence posts: the run's last millisecond ends both series.
    assert_eq!(truth_1k.len(), 10 * (truth_100.len() - 1) + 1);
    let every_tenth: Vec<Sample> = truth_1k.iter().step_by(10).copied().collect();
    assert_eq!(every_tenth, truth_100);
    let Some(Sample::TruthVelocity { t_ns: t1, .. }) = truth_1k.get(1) else {
        panic!("no second truth sample")
    };
    let Some(Sample::TruthVelocity { t_ns: t0, .. }) = truth_1k.first() else {
        panic!("no truth sample")
    };
    assert_eq!(t1 - t0, 1_000_000);
    let err = run(300).unwrap_err().to_string();
    assert!(err.contains("truth_velocity_hz = 300"), "{err}");
}
