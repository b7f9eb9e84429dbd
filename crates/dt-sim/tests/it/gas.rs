//! The gas charge: ideal gas, label at 20 °C, lagging gas temperature,
//! polytropic compression by the rod.

use crate::{plant, run_for};
use dt_sim::gas::GasSpring;
use dt_sim::params::{KELVIN, P_ATM_PA};
use dt_sim::thermal::Nodes;
use dt_sim::PlantParams;

#[test]
fn charge_pressure_at_20_c_is_the_label() {
    let p = PlantParams::nominal();
    for charge in [0.5, 4.0, 7.0, 10.0, 12.0] {
        let gas = GasSpring::new(&p, charge, 2.0);
        let gauge_bar = (gas.static_pa(20.0, 20.0) - P_ATM_PA) / 1e5;
        assert!((gauge_bar - charge).abs() < 1e-9, "{charge}: {gauge_bar}");
        // At mid-stroke and 20 C the instantaneous pressure is the static one.
        let inst = gas.pressure_pa(20.0, 20.0, 0.0, 0.0).unwrap();
        assert!((inst - gas.static_pa(20.0, 20.0)).abs() < 1e-6);
    }
}

#[test]
fn pv_over_t_is_constant_at_rest_while_cooling() {
    let p = PlantParams::nominal();
    let mut plant = plant(&p, 7.0, 0.0);
    plant.set_temperatures(Nodes {
        oil_c: 75.0,
        inner_c: 72.0,
        outer_c: 70.0,
    });
    let mut ratios = Vec::new();
    let mut gas_minus_oil: f64 = 0.0;
    let mut k = 0u64;
    run_for(&mut plant, 240.0, |t| {
        k += 1;
        if k % 4000 == 0 {
            ratios.push(t.gas_pa * t.gas_volume_m3 / (t.gas_c + KELVIN));
            let n = t.nodes.unwrap();
            gas_minus_oil = gas_minus_oil.max((t.gas_c - n.oil_c).abs());
        }
    });
    let first = ratios[0];
    for r in &ratios {
        assert!(
            (r / first - 1.0).abs() < 1e-6,
            "pV/T drifted: {r} vs {first}"
        );
    }
    // m R from the label: (p_charge + p_atm) V0 / 293.15 K.
    let mr = (7.0e5 + P_ATM_PA) * p.gas_volume_m3 / (20.0 + KELVIN);
    assert!((first / mr - 1.0).abs() < 1e-6);
    // The gas lags the cooling oil.
    assert!(
        gas_minus_oil > 0.2,
        "gas should lag the oil: {gas_minus_oil}"
    );
}

#[test]
fn hot_gas_raises_the_static_pressure_more_than_ideal_gas_at_fixed_volume() {
    // Oil expansion shrinks the gas volume: at 80 C the pressure exceeds the
    // fixed-volume ideal-gas value (x 353.15/293.15).
    let p = PlantParams::nominal();
    let gas = GasSpring::new(&p, 12.0, 1.0);
    let abs_20 = 12.0e5 + P_ATM_PA;
    let ideal = abs_20 * (80.0 + KELVIN) / (20.0 + KELVIN);
    let got = gas.static_pa(80.0, 80.0);
    assert!(got > ideal * 1.05 && got < ideal * 1.2, "{got} vs {ideal}");
}

#[test]
fn polytropic_index_grows_with_frequency() {
    let p = PlantParams::nominal();
    let n: Vec<f64> = [0.0, 1.0, 2.0, 4.0]
        .iter()
        .map(|&f| GasSpring::new(&p, 12.0, f).n)
        .collect();
    assert!((n[0] - 1.0).abs() < 1e-12);
    assert!(n.windows(2).all(|w| w[1] > w[0]), "{n:?}");
    assert!(n[3] < p.gas_gamma && n[1] > 1.05, "{n:?}");
}
