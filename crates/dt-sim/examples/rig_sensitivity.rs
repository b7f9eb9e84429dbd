//! Development aid (simulated data): which of the rig's sensor errors moves
//! the charge observer's reading when one unit's run is read on another set
//! of sensors. The same run (unit `--unit`, charge `--pressures`, `--frequency`,
//! room and noise from `--seed`) is simulated on the rigs `--rigs a,b,…`
//! ([`RunSpec::rig_seed`]) once with all of the rig's errors and once with
//! only one kind of them (the others' scatter set to 0; the draws are the same),
//! one directory per kind:
//! `all`, `acc_gain`, `acc_offset`, `tc_offset`, `none`.
//! Read them with `python -m train.observer evaluate … NAME=DIR …` and compare
//! the rigs' readings within each kind (docs/history.md, "Fifty-first session").
//!
//! `cargo run --release -p dt-sim --example rig_sensitivity -- --out DIR
//! --unit 43 --pressures 10 [--frequency 2] [--seed 143] [--rigs 143,243]`

use std::path::PathBuf;

use dt_sim::sensors::RigErrors;
use dt_sim::{mix_seed, simulate_run, PlantParams, RunSpec};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn arg<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

fn list<T: std::str::FromStr>(s: &str) -> Result<Vec<T>, T::Err> {
    s.split(',').map(str::parse).collect()
}

/// The rig's error kinds, by the scatter parameters that draw them.
const KINDS: [(&str, &[&str]); 3] = [
    ("acc_gain", &["acc_gain_sd"]),
    ("acc_offset", &["acc_offset_sd_mps2"]),
    ("tc_offset", &["tc_offset_sd_c"]),
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let out = PathBuf::from(arg(&args, "--out").ok_or("--out DIR is required")?);
    let unit: u64 = arg(&args, "--unit")
        .ok_or("--unit N is required")?
        .parse()?;
    let pressures: Vec<f64> = list(arg(&args, "--pressures").unwrap_or("10"))?;
    let frequency: f64 = arg(&args, "--frequency").unwrap_or("2").parse()?;
    let seed: u64 = arg(&args, "--seed").unwrap_or("143").parse()?;
    let rigs: Vec<u64> = list(arg(&args, "--rigs").unwrap_or("143,243"))?;
    let unit_params = PlantParams::nominal().varied(unit);
    let only = |keep: Option<&str>| -> Result<PlantParams, String> {
        let mut p = unit_params.clone();
        for (kind, names) in KINDS {
            if keep != Some(kind) {
                for name in names {
                    p = p.scaled(name, 0.0).ok_or(format!("no parameter {name}"))?;
                }
            }
        }
        Ok(p)
    };
    for &rig in &rigs {
        // drawn as `run::drive` draws a run's rig
        let mut rng = ChaCha8Rng::seed_from_u64(mix_seed(&[rig, 0x0072_6967]));
        let e = RigErrors::draw(&unit_params, &mut rng);
        println!(
            "rig {rig}: accelerometer gains a1 {:+.4} a2 {:+.4}, offsets a1 {:+.3} a2 {:+.3} m/s², \
             thermocouple offsets shock {:+.2} ambient {:+.2} °C",
            e.acc_gain[0], e.acc_gain[1], e.acc_offset_mps2[0], e.acc_offset_mps2[1],
            e.tc_offset_c[0], e.tc_offset_c[1]
        );
    }
    let mut variants = vec![("all", unit_params.clone()), ("none", only(None)?)];
    for (kind, _) in KINDS {
        variants.push((kind, only(Some(kind))?));
    }
    for (name, params) in &variants {
        let dir = out.join(name);
        std::fs::create_dir_all(&dir)?;
        for &charge in &pressures {
            for &rig in &rigs {
                let spec = RunSpec {
                    unit: Some(unit),
                    rig_seed: Some(rig),
                    ..RunSpec::paper(charge, frequency, seed)
                };
                let path = dir.join(format!("{}.mcap", spec.run_id()));
                let s = simulate_run(&spec, params, &path)?;
                println!(
                    "{name}: {} {:.0} s ({})",
                    spec.run_id(),
                    s.duration_s,
                    s.stop
                );
            }
        }
    }
    Ok(())
}
