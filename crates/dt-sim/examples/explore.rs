//! Development aid (simulated data): force-velocity curves of the plant,
//! cavitation onset speeds, and a summary of each paper run (no files).
//!
//! `cargo run --release -p dt-sim --example explore [-- --quick] [-- --curves]`
//! `cargo run --release -p dt-sim --example explore -- --units 2,3,4`: the
//! friction parameters of those units (`simulate --unit N`) beside unit A's.

use dt_sim::hydraulics::TwinTube;
use dt_sim::params::{KELVIN, P_ATM_PA};
use dt_sim::{simulate_run_with, PlantParams, RunSpec};

fn curves(p: &PlantParams) {
    let mut hyd = TwinTube::new(p);
    let a_r = p.rod_area_m2();
    for temp_c in [20.0, 40.0, 80.0] {
        let nu = hyd.oil.ratio_to_40(temp_c);
        print!("{temp_c:>4} C (nu {:5.1} cSt):", hyd.oil.nu_cst(temp_c));
        for v in [0.05, 0.13, 0.26, 0.5, 1.0] {
            // Damping only: subtract the static gas force at 12 bar.
            let p_g = 12.0e5 + P_ATM_PA;
            let f0 = -(p_g - P_ATM_PA) * a_r;
            let reb = hyd.evaluate(v, p_g, 0.0, nu).unwrap().force_n - f0;
            let com = hyd.evaluate(-v, p_g, 0.0, nu).unwrap().force_n - f0;
            print!("  {v:.2} m/s {reb:5.0}/{com:5.0} N");
        }
        println!();
    }
    for charge in [0.5, 4.0, 7.0, 12.0] {
        let onset: Vec<String> = [20.0, 80.0]
            .iter()
            .map(|&t: &f64| {
                let p_g = (charge * 1e5 + P_ATM_PA) * (t + KELVIN) / (20.0 + KELVIN);
                let q = hyd.max_refill_m3s(p_g, hyd.oil.ratio_to_40(t));
                format!("{:.2} m/s at {t} C", q / a_r)
            })
            .collect();
        println!("cavitation onset {charge:>4} bar: {}", onset.join(", "));
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let p = PlantParams::nominal();
    if args.iter().any(|a| a == "--curves") {
        curves(&p);
        return;
    }
    if let Some(i) = args.iter().position(|a| a == "--units") {
        let list = args.get(i + 1).map_or("", String::as_str);
        println!("unit  friction_coulomb_n  friction_seal_n_per_bar  friction_viscous_ns_m");
        let row = |name: &str, q: &PlantParams| {
            println!(
                "{name:>4}  {:17.3}  {:23.4}  {:21.2}",
                q.friction_coulomb_n, q.friction_seal_n_per_bar, q.friction_viscous_ns_m
            );
        };
        row("A", &p);
        for seed in list.split(',').filter_map(|s| s.trim().parse::<u64>().ok()) {
            row(&seed.to_string(), &p.varied(seed));
        }
        return;
    }
    let quick = args.iter().any(|a| a == "--quick");
    for &charge in &[0.5, 4.0, 12.0] {
        for &f in &[1.0, 2.0, 4.0] {
            let spec = RunSpec {
                quick,
                ..RunSpec::paper(charge, f, 1)
            };
            let t = std::time::Instant::now();
            let s = simulate_run_with(&spec, &p, |_| Ok(())).expect("run");
            println!(
                "{} {:7.1} s (exc {:7.1} s, {}) shock TC {:5.1} oil {:5.1} outer {:5.1} gas {:5.2} bar, {:6.0} kJ, {} msgs, cavitating {:5.1} s, void {:.2} mL ({:.2} s wall)",
                s.run_id,
                s.duration_s,
                s.excitation_s,
                s.stop,
                s.final_shock_reading_c,
                s.final_oil_c,
                s.final_outer_c,
                s.final_static_bar,
                s.energy_dissipated_j / 1e3,
                s.messages,
                s.cavitation_s,
                s.max_void_m3 * 1e6,
                t.elapsed().as_secs_f64()
            );
        }
    }
}
