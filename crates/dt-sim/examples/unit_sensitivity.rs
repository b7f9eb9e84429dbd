//! Development aid (simulated data): which of a unit's scattered parameters
//! moves the charge observer's reading, and at which charge. For every
//! parameter with a unit-to-unit scatter, the nominal unit with that one
//! parameter moved by `--sigmas` of its scatter is run at each charge (the
//! paper's excitation at `--frequency`, seed `--seed`: the same noise and room
//! for every parameter), one directory per parameter, `nominal` beside them.
//! Read them with `python -m train.observer evaluate … NAME=DIR …` and compare
//! each parameter's errors with `nominal`'s (docs/history.md, "Forty-first session").
//!
//! `cargo run --release -p dt-sim --example unit_sensitivity -- --out DIR
//! [--pressures 2,12] [--frequency 2] [--seed 5] [--sigmas 2] [--only a,b]`

use std::path::PathBuf;

use dt_sim::{simulate_run, PlantParams, RunSpec};

fn arg<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let out = PathBuf::from(arg(&args, "--out").ok_or("--out DIR is required")?);
    let pressures: Vec<f64> = arg(&args, "--pressures")
        .unwrap_or("2,12")
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let frequency: f64 = arg(&args, "--frequency").unwrap_or("2").parse()?;
    let seed: u64 = arg(&args, "--seed").unwrap_or("5").parse()?;
    let sigmas: f64 = arg(&args, "--sigmas").unwrap_or("2").parse()?;
    let only: Option<Vec<&str>> = arg(&args, "--only").map(|s| s.split(',').collect());
    let nominal = PlantParams::nominal();
    let mut units = vec![("nominal".to_owned(), nominal.clone())];
    for info in PlantParams::TABLE {
        if info.scatter_pct <= 0.0 || only.as_ref().is_some_and(|o| !o.contains(&info.name)) {
            continue;
        }
        let factor = 1.0 + sigmas * info.scatter_pct / 100.0;
        let p = nominal
            .scaled(info.name, factor)
            .ok_or("unknown parameter")?;
        units.push((info.name.to_owned(), p));
    }
    for (name, params) in &units {
        let dir = out.join(name);
        std::fs::create_dir_all(&dir)?;
        for &charge in &pressures {
            let spec = RunSpec::paper(charge, frequency, seed);
            let path = dir.join(format!("{}.mcap", spec.run_id()));
            let s = simulate_run(&spec, params, &path)?;
            println!(
                "{name}: {} {:.0} s, cavitating {:.1} s",
                spec.run_id(),
                s.duration_s,
                s.cavitation_s
            );
        }
    }
    Ok(())
}
