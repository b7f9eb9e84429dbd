//! Development aid: prints what each paper run does (no files written).
use dt_sim::{simulate_run_with, PlantParams, RunSpec};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let p = PlantParams::nominal();
    for &charge in &[0.5, 4.0, 12.0] {
        for &f in &[1.0, 2.0, 4.0] {
            let mut spec = RunSpec::paper(charge, f, 1);
            spec.quick = quick;
            let t = std::time::Instant::now();
            let s = simulate_run_with(&spec, &p, |_| Ok(())).unwrap();
            println!(
                "{} {:>7.1}s exc {:>7.1}s {:?} shockTC {:5.1} oil {:5.1} outer {:5.1} gas {:5.2} bar E {:8.0} kJ msgs {} cav {:6.1}s void {:.2} mL  ({:.2}s wall)",
                s.run_id, s.duration_s, s.excitation_s, s.stop, s.final_shock_reading_c, s.final_oil_c, s.final_outer_c,
                s.final_static_bar, s.energy_dissipated_j / 1e3, s.messages, s.cavitation_s, s.max_void_m3 * 1e6, t.elapsed().as_secs_f64()
            );
        }
    }
}
