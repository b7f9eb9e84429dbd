//! Energy balance: the mechanical work the dyno does on the damper equals
//! the heat stored in the nodes plus the heat lost to the room, plus the
//! reversible work stored in the gas spring, the cavitation void and done
//! against the atmosphere.
//!
//! Every term is computed here from the plant's truth (force, velocity,
//! gas pressure, void, node temperatures), not from the plant's own heat
//! accounting, so a force that does not match the valves' dissipation, or a
//! heat network that leaks energy, fails the test.

use crate::{plant, run_for};
use dt_sim::params::P_ATM_PA;
use dt_sim::PlantParams;

/// Relative tolerance on the balance (discretisation of the 4 kHz step
/// and of the void clamp).
const REL_TOL: f64 = 5e-3;

fn balance(charge_bar: f64, frequency_hz: f64, seconds: f64) -> (f64, f64, f64) {
    let p = PlantParams::nominal();
    let a_rod = p.rod_area_m2();
    let p_cav = p.cavitation_pa;
    let mut plant = plant(&p, charge_bar, frequency_hz);
    let net = plant.network().clone();
    let u0 = net.stored_j(&plant.nodes());
    let (mut work, mut reversible, mut void_seconds) = (0.0, 0.0, 0.0);
    run_for(&mut plant, seconds, |t| {
        let dt = t.dt_s;
        work += t.force_n * t.velocity_mps * dt;
        // Gas volume change due to the rod and the void (not oil expansion).
        let dv_gas = a_rod * t.velocity_mps * dt - t.dvoid_m3;
        reversible +=
            -t.gas_pa * dv_gas - p_cav * t.dvoid_m3 + P_ATM_PA * a_rod * t.velocity_mps * dt;
        if t.void_m3 > 0.0 {
            void_seconds += dt;
        }
    });
    let heat = net.stored_j(&plant.nodes()) - u0 + plant.heat_to_room_j();
    (work - reversible, heat, void_seconds)
}

#[test]
fn work_equals_heat_without_cavitation() {
    let (mech, heat, void_s) = balance(12.0, 2.0, 20.0);
    assert!(void_s == 0.0);
    assert!(heat > 5e3, "a 2 Hz run dissipates kJ: {heat}");
    let err = (mech - heat).abs() / heat;
    assert!(
        err < REL_TOL,
        "work {mech:.1} J vs heat {heat:.1} J: {err:.2e}"
    );
}

#[test]
fn work_equals_heat_with_cavitation() {
    let (mech, heat, void_s) = balance(0.5, 4.0, 12.0);
    assert!(void_s > 2.0, "0.5 bar at 4 Hz must cavitate: {void_s} s");
    let err = (mech - heat).abs() / heat;
    assert!(
        err < REL_TOL,
        "work {mech:.1} J vs heat {heat:.1} J: {err:.2e}"
    );
}
