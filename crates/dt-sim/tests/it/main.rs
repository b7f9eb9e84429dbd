//! dt-sim integration tests (one binary, `tests/it/`): plausibility of the
//! truth plant and of the sensors, determinism, the parameter table and the
//! written logs. Runs are kept short (CI has 2 cores).

mod cavitation;
mod determinism;
mod energy;
mod gas;
mod logs;
mod params;
mod sensors;
mod step;
mod thermal;

use dt_sim::{Plant, PlantConfig, PlantParams};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// A plant excited from t = 0 (after the actuator ramp) at 80 mm p-p.
pub(crate) fn plant(params: &PlantParams, charge_bar: f64, frequency_hz: f64) -> Plant {
    let config = PlantConfig {
        charge_bar,
        frequency_hz,
        stroke_pp_m: 0.08,
        excitation_start_s: 0.0,
        road: None,
    };
    Plant::new(params, &config, ChaCha8Rng::seed_from_u64(7)).expect("plant")
}

/// Steps `plant` for `seconds`, calling `f` on every truth.
pub(crate) fn run_for(plant: &mut Plant, seconds: f64, mut f: impl FnMut(&dt_sim::Truth)) {
    let n = (seconds / plant.dt_s()).round() as u64;
    for _ in 0..n {
        let t = plant.step().expect("step");
        f(&t);
    }
}
