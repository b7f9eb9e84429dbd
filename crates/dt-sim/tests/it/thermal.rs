//! Thermal equilibrium of a long slow run against the analytic steady state
//! of the heat network (solved here independently from the parameter table).

use crate::{plant, run_for};
use dt_sim::params::{KELVIN, STEFAN_BOLTZMANN};
use dt_sim::thermal::Nodes;
use dt_sim::PlantParams;

/// Steady state of the three-node network for heat inputs `p_oil`,
/// `p_inner` (W) and room `t_room` (°C).
fn steady_state(p: &PlantParams, p_oil: f64, p_inner: f64, t_room: f64) -> Nodes {
    let g_amb = p.g_outer_air_w_per_k + p.g_outer_frame_w_per_k;
    let esa = p.emissivity * STEFAN_BOLTZMANN * p.outer_area_m2;
    let loss = |t_out: f64| {
        g_amb * (t_out - t_room) + esa * ((t_out + KELVIN).powi(4) - (t_room + KELVIN).powi(4))
    };
    // All the heat leaves through the outer tube: bisection on T_out.
    let total = p_oil + p_inner;
    let (mut lo, mut hi) = (t_room, t_room + 500.0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if loss(mid) < total {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let t_out = 0.5 * (lo + hi);
    // Oil and inner tube: 2x2 linear system in (T_oil, T_in).
    let (goi, goo, gio) = (
        p.g_oil_inner_w_per_k,
        p.g_oil_outer_w_per_k,
        p.g_inner_outer_w_per_k,
    );
    // (goi + goo) To - goi Ti = p_oil + goo Tout
    // -goi To + (goi + gio) Ti = p_inner + gio Tout
    let (a11, a12, b1) = (goi + goo, -goi, p_oil + goo * t_out);
    let (a21, a22, b2) = (-goi, goi + gio, p_inner + gio * t_out);
    let det = a11 * a22 - a12 * a21;
    Nodes {
        oil_c: (b1 * a22 - a12 * b2) / det,
        inner_c: (a11 * b2 - a21 * b1) / det,
        outer_c: t_out,
    }
}

#[test]
fn slow_run_settles_at_the_analytic_steady_state() {
    let mut p = PlantParams::nominal();
    // A still room, so that a steady state exists.
    p.ambient_sine_amp_c = 0.0;
    p.ambient_walk_sd_c = 0.0;
    let mut plant = plant(&p, 12.0, 1.0);
    // Start near the answer to keep the test short; the transient decays
    // with the slowest time constant (about 9 min).
    plant.set_temperatures(Nodes {
        oil_c: 62.0,
        inner_c: 61.0,
        outer_c: 59.0,
    });
    run_for(&mut plant, 3000.0, |_| {});
    // Average the heat inputs over the last 20 cycles.
    let (mut e_oil, mut e_in, mut room, mut n) = (0.0, 0.0, 0.0, 0.0);
    let start = plant.nodes();
    run_for(&mut plant, 20.0, |t| {
        e_oil += t.valve_power_w * t.dt_s;
        e_in += t.friction_power_w * t.dt_s;
        room += t.room_c;
        n += 1.0;
    });
    let end = plant.nodes();
    assert!(
        (end.outer_c - start.outer_c).abs() < 0.01,
        "not settled: {start:?} -> {end:?}"
    );
    let expect = steady_state(&p, e_oil / 20.0, e_in / 20.0, room / n);
    for (name, got, want) in [
        ("oil", end.oil_c, expect.oil_c),
        ("inner", end.inner_c, expect.inner_c),
        ("outer", end.outer_c, expect.outer_c),
    ] {
        // Within-cycle ripple of the oil temperature is about 0.02 K.
        assert!(
            (got - want).abs() < 0.1,
            "{name}: simulated {got:.3} C, analytic {want:.3} C"
        );
    }
    // The paper's 1 Hz runs settle around 60 C on the shock body.
    assert!(
        (50.0..70.0).contains(&end.outer_c),
        "outer {:.1} C",
        end.outer_c
    );
}
