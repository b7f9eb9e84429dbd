"""Force model (SPEC §3.3, paper eqs. 4–9) against a numpy transcription.

The reference below is written from the SPEC text, not from the Rust code:

    nu     = nu_40 * exp(-beta * (T_oil - 40))
    F_port = smin(k_leak nu |v|, f_preload + k_spring |v|)
    smin(a, b) = a b / (a^k_tr + b^k_tr)^(1/k_tr)   (0 when a or b is 0)
    F_main = k_main nu^0.25 |v|^1.75
    p_s    = (charge_bar 1e5 + p_atm) (T_oil + 273.15) / 293.15
    F_gas  = p_s a_rod (v_gas / (v_gas + a_rod y))^1.4 - p_atm a_rod
    F      = sign(v) (F_port + F_main) - k_hys a - F_gas

with the rebound coefficients for v >= 0 and the compression ones for v < 0.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import shocktwin

P_ATM = 101325.0
# Named tolerance: the model is a closed form; only the order of floating
# point operations may differ.
RTOL = 1e-12
ATOL_N = 1e-9

PARAMS = {
    "k_leak_reb": 320.0,
    "k_leak_com": 150.0,
    "f_preload_reb": 420.0,
    "f_preload_com": 180.0,
    "k_spring_reb": 1600.0,
    "k_spring_com": 700.0,
    "k_main_reb": 900.0,
    "k_main_com": 400.0,
    "k_tr": 2.5,
    "k_hys": 4.0,
    "nu_40": 32.0,
    "beta": 0.021,
    "charge_bar": 12.0,
    "a_rod": np.pi * 0.006**2,
    "v_gas": 1.6e-4,
}


def reference_force(v, a, y, t_oil_c, p):
    """Returns (total, port, main, gas) per SPEC §3.3."""
    v, a, y, t_oil_c = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (v, a, y, t_oil_c)))
    reb = v >= 0
    pick = lambda name: np.where(reb, p[name + "_reb"], p[name + "_com"])  # noqa: E731
    speed = np.abs(v)
    nu = p["nu_40"] * np.exp(-p["beta"] * (t_oil_c - 40.0))
    leak = pick("k_leak") * nu * speed
    shim = pick("f_preload") + pick("k_spring") * speed
    k = p["k_tr"]
    with np.errstate(divide="ignore", invalid="ignore"):
        port = np.where((leak == 0) | (shim == 0), 0.0, leak * shim / (leak**k + shim**k) ** (1.0 / k))
    main = pick("k_main") * nu**0.25 * speed**1.75
    p_s = (p["charge_bar"] * 1e5 + P_ATM) * (t_oil_c + 273.15) / 293.15
    gas = p_s * p["a_rod"] * (p["v_gas"] / (p["v_gas"] + p["a_rod"] * y)) ** 1.4 - P_ATM * p["a_rod"]
    total = np.sign(v) * (port + main) - p["k_hys"] * a - gas
    return total, port, main, gas


def grid():
    v = np.array([-1.2, -0.5, -0.05, -1e-4, 0.0, 1e-4, 0.05, 0.5, 1.2])
    a = np.array([-25.0, 0.0, 6.3])
    y = np.array([-0.04, 0.0, 0.04])
    t = np.array([-10.0, 20.0, 40.0, 85.0])  # cold to hot oil
    return [g.ravel() for g in np.meshgrid(v, a, y, t, indexing="ij")]


def test_force_matches_reference_on_grid():
    v, a, y, t = grid()
    model = shocktwin.ForceModel(**PARAMS)
    got = model.force(v, a, y, t)
    want, *_ = reference_force(v, a, y, t, PARAMS)
    assert got.dtype == np.float64 and got.shape == v.shape
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL_N)


def test_grid_separates_the_directions():
    """The grid is sensitive to the rebound/compression split (so the test above can fail)."""
    v, a, y, t = grid()
    swapped = {k: PARAMS[k.replace("_reb", "_TMP").replace("_com", "_reb").replace("_TMP", "_com")] for k in PARAMS}
    want, *_ = reference_force(v, a, y, t, PARAMS)
    other, *_ = reference_force(v, a, y, t, swapped)
    assert np.max(np.abs(want - other)) > 100.0


def test_components_add_up_and_match_reference():
    v, a, y, t = grid()
    parts = shocktwin.ForceModel(**PARAMS).components(v, a, y, t)
    total, port, main, gas = reference_force(v, a, y, t, PARAMS)
    sign = np.where(v >= 0, 1.0, -1.0)
    assert set(parts) == {"force_n", "port_n", "main_n", "hysteresis_n", "gas_n", "power_w"}
    # each term signed as it enters eq. 9
    np.testing.assert_allclose(parts["port_n"], sign * port, rtol=RTOL, atol=ATOL_N)
    np.testing.assert_allclose(parts["main_n"], sign * main, rtol=RTOL, atol=ATOL_N)
    np.testing.assert_allclose(parts["gas_n"], -gas, rtol=RTOL, atol=ATOL_N)
    np.testing.assert_allclose(parts["hysteresis_n"], -PARAMS["k_hys"] * a, rtol=RTOL, atol=ATOL_N)
    np.testing.assert_allclose(parts["force_n"], total, rtol=RTOL, atol=ATOL_N)
    # the heat input: dissipative force times speed (ARCHITECTURE.md), never negative
    np.testing.assert_allclose(parts["power_w"], (port + main) * np.abs(v), rtol=RTOL, atol=ATOL_N)
    assert parts["power_w"].min() >= 0


def test_force_at_another_charge():
    v, a, y, t = grid()
    got = shocktwin.ForceModel(**PARAMS).force(v, a, y, t, charge_bar=4.0)
    want, *_ = reference_force(v, a, y, t, {**PARAMS, "charge_bar": 4.0})
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL_N)


def test_zero_velocity_is_gas_and_hysteresis_only():
    model = shocktwin.ForceModel(**PARAMS)
    f = model.force([0.0], [2.0], [0.0], [20.0])
    gas = (PARAMS["charge_bar"] * 1e5) * PARAMS["a_rod"]  # at 20 °C, y = 0
    np.testing.assert_allclose(f, [-gas - 2.0 * PARAMS["k_hys"]], rtol=1e-12)


def test_hot_oil_damps_less():
    model = shocktwin.ForceModel(**{**PARAMS, "k_hys": 0.0})
    cold, hot = model.force([0.5, 0.5], [0.0, 0.0], [0.0, 0.0], [0.0, 80.0])
    gas_cold = reference_force(0.5, 0.0, 0.0, 0.0, PARAMS)[3]
    gas_hot = reference_force(0.5, 0.0, 0.0, 80.0, PARAMS)[3]
    assert cold + gas_cold > hot + gas_hot > 0


finite = dict(allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(
    v=hnp.arrays(np.float64, 16, elements=st.floats(-3.0, 3.0, **finite)),
    a=hnp.arrays(np.float64, 16, elements=st.floats(-200.0, 200.0, **finite)),
    y=hnp.arrays(np.float64, 16, elements=st.floats(-0.08, 0.08, **finite)),
    t=hnp.arrays(np.float64, 16, elements=st.floats(-30.0, 120.0, **finite)),
    k_tr=st.floats(1.0, 6.0),
    scale=st.floats(0.1, 10.0),
    charge_bar=st.floats(0.0, 30.0),
)
def test_force_matches_reference_hypothesis(v, a, y, t, k_tr, scale, charge_bar):
    params = {**PARAMS, "k_tr": k_tr, "charge_bar": charge_bar}
    for name in ("k_leak_reb", "k_leak_com", "k_main_reb", "k_main_com"):
        params[name] = PARAMS[name] * scale
    got = shocktwin.ForceModel(**params).force(v, a, y, t)
    want, *_ = reference_force(v, a, y, t, params)
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-8)


def test_length_mismatch_is_an_error():
    with pytest.raises(shocktwin.InputError, match="position"):
        shocktwin.ForceModel(**PARAMS).force([0.1, 0.2], [0.0, 0.0], [0.0], [20.0, 20.0])


def test_invalid_parameter_is_named():
    with pytest.raises(shocktwin.ParamsError, match="v_gas"):
        shocktwin.ForceModel(**{**PARAMS, "v_gas": -1.0})
    with pytest.raises(TypeError, match="k_leak"):
        shocktwin.ForceModel(k_leak=1.0)  # not a SPEC name


def test_defaults_are_the_core_priors():
    prior = shocktwin.default_params()["force"]
    assert shocktwin.ForceModel().params == prior
    assert shocktwin.ForceModel(charge_bar=7.0).params == {**prior, "charge_bar": 7.0}
