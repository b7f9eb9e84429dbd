"""Calibrate the twin's physics on the nominal runs of a campaign (paper §5.2.3, §5.3.6).

    python -m train.fit_physics --campaign DIR --out physics.json
        [--nominal-bar BAR | --nominal "150 psi"] [--datasheet FILE.toml] [--figures DIR]

Steps, all on the runs at the nominal charge pressure (12 bar by default; ``--nominal``
takes any unit of ``train.datasheet.PRESSURE_UNITS_BAR``, and the runs' own label is
then used as the nominal charge):

1. Kalman filter noise (SPEC §3.1) from the minute at rest before excitation: the
   position noise is the potentiometer's standard deviation at rest, the acceleration
   noise that of ``a1 - a2`` at rest; the bias random walk keeps its prior (the
   accelerometer datasheet's offset drift, see ``shocktwin.default_params``).
2. Thermal model (eqs. 2–3): the five lumped parameters minimise the RMSE of the
   modelled cylinder temperature against the shock thermocouple, driven by the
   measured power (loadcell force × Kalman velocity) and the ambient thermocouple,
   as the paper does (scipy ``least_squares`` in log-parameters).
3. Force model (eqs. 4–9): its parameters minimise the RMSE of the modelled force
   against the loadcell, with the oil temperature of the fitted thermal model
   (jointly with the thermal model, §5.3.6); the charge pressure is the nominal one.
4. Closed loop: the twin's own 50 Hz pipeline (``shocktwin.features``, the code the
   daemon runs) is run with the fitted parameters; the per-run RMSE of temperature (°C)
   and force (N) reported and written to ``physics.json`` come from it.
5. Baseline: the force model against what a test engineer makes in five minutes, a
   piecewise-linear damping curve per direction (:class:`PiecewiseLinearDamping`), both
   held out the same way: leave one nominal run out, fit steps 1–3 and the baseline on
   the others, score both on it (the physics through the closed loop of step 4, the
   baseline on the same pipeline velocity and the same ticks).

Geometry: the force model's ``a_rod`` and ``v_gas`` are fitted from their priors
(``shocktwin.default_params``) unless ``--datasheet`` fixes them (``train.datasheet``).

Reduced models (a campaign with only ``/position``, ``/force``, ``/temperature/shock``,
like a crank-dyno rig's): without ``/acceleration`` the Kalman filter is the
position-only one (SPEC §3.1 last sentence; dt-core ``KalmanFilter::position_only``,
a constant-acceleration model driven by white jerk); without ``/temperature/ambient``
each run's first shock temperature stands in for ambient (the unit starts at ambient).
Both are what the twin's pipeline does with such a log (``shocktwin.twin_trace``), a
warning says which is used and ``physics.json`` records it under ``reduced_model``.

Whether the data are simulated is read from the runs' metadata (``simulated``).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

import shocktwin

from train.campaign import Campaign, CampaignError, Run, load_campaign, main_wrapper, require_topics
from train.datasheet import Datasheet, load_datasheet, parse_pressure_bar
from train.progress import progress

log = logging.getLogger("shocktwin.fit_physics")

PHYSICS_FORMAT = "shocktwin-physics/1"
REST_DETECT_M = 0.004  # excitation starts when the position leaves its rest value by 4 mm
THERMAL_NAMES = ["c_oil", "c_cyl", "ha_in", "ha_out", "eps_sigma_a"]
# Force parameters that are fitted; nu_40 stays at its prior (it is degenerate with
# the k_* gains: only their products with the viscosity are observable), and
# charge_bar is the nominal pressure, known for the nominal runs.
FORCE_FIT_NAMES = [
    "k_leak_reb", "k_leak_com", "f_preload_reb", "f_preload_com", "k_spring_reb",
    "k_spring_com", "k_main_reb", "k_main_com", "k_tr", "k_hys", "beta", "a_rod", "v_gas",
]
FORCE_LINEAR = {"k_hys"}  # may be zero: fitted in linear space, bounded below by 0; the rest in log space
#: What calibration cannot do without; accelerometers and the ambient thermocouple have reduced models.
NEEDED_TOPICS = ["/position", "/force", "/temperature/shock"]
ACCEL, AMBIENT = "/acceleration", "/temperature/ambient"


# ---------------------------------------------------------------------------------------
# Kalman noise from the rest period
# ---------------------------------------------------------------------------------------


def rest_end_s(run: Run) -> float:
    """Time (s) at which excitation starts: the position first leaves its rest value."""
    pos = run.log.topic("/position")
    z, t = pos["position_m"], pos["t_s"]
    ok = np.isfinite(z)
    z, t = z[ok], t[ok]
    rest = np.median(z[: max(10, len(z) // 100)])
    moved = np.nonzero(np.abs(z - rest) > REST_DETECT_M)[0]
    return float(t[moved[0]]) if len(moved) else float(t[-1])


def fit_kalman(runs: Sequence[Run], prior: dict[str, float]) -> dict[str, Any]:
    """Noise from the rest periods; without accelerometers only ``sigma_position`` (the one
    the position-only filter uses; ``sigma_accel`` keeps its prior)."""
    sz, sa = [], []
    for run in runs:
        t_end = rest_end_s(run) - 1.0
        pos = run.log.topic("/position")
        z = pos["position_m"][pos["t_s"] < t_end]
        z = z[np.isfinite(z)]
        if len(z) > 50:
            sz.append(np.std(z))
        if ACCEL in run.log.topics:
            acc = run.log.topic(ACCEL)
            a = (acc["a1_mps2"] - acc["a2_mps2"])[acc["t_s"] < t_end]
            a = a[np.isfinite(a)]
            if len(a) > 500:
                sa.append(np.std(a))
    fitted = dict(prior)
    if not sz:
        log.warning("no rest period found; Kalman noise stays at its prior")
        return fitted
    # Quantisation alone can give a zero std at rest: floors of 1 µm and 1 mm/s².
    fitted["sigma_position"] = max(float(np.median(sz)), 1e-6)
    if sa:
        fitted["sigma_accel"] = max(float(np.median(sa)), 1e-3)
    return fitted


# ---------------------------------------------------------------------------------------
# Feature tables of the nominal runs
# ---------------------------------------------------------------------------------------

FIT_GROUPS = ["force", "position", "acceleration", "velocity", "mechanical", "thermal"]


def is_reduced(run: Run) -> bool:
    return ACCEL not in run.log.topics or AMBIENT not in run.log.topics


def table(run: Run, params: dict[str, Any]) -> dict[str, np.ndarray]:
    """The run's 50 Hz table through the twin's pipeline: the feature groups with the
    full suite, the twin's state with its reduced models otherwise (same keys)."""
    if is_reduced(run):
        return reduced_table(run, params)
    x, columns, t_s = shocktwin.features(run.log, params, FIT_GROUPS)
    out = {name: x[:, i] for i, name in enumerate(columns)}
    out["t_s"] = np.asarray(t_s)
    return out


def _held(topic: dict[str, np.ndarray], t_s: np.ndarray) -> np.ndarray:
    """A 1 Hz temperature zero-order held at ``t_s`` (last sample at or before; NaN before)."""
    ok = np.isfinite(topic["temperature_c"])
    ts, tc = topic["t_s"][ok], topic["temperature_c"][ok]
    i = np.searchsorted(ts, t_s, side="right") - 1
    return np.where(i >= 0, tc[np.maximum(i, 0)], np.nan) if len(ts) else np.full(len(t_s), np.nan)


def reduced_table(run: Run, params: dict[str, Any]) -> dict[str, np.ndarray]:
    """``table`` for a run without accelerometers or ambient thermocouple, from
    ``shocktwin.twin_trace`` (the pipeline's position-only Kalman filter and its
    first-shock-temperature ambient); the thermocouples are held as the pipeline holds them."""
    tr = shocktwin.twin_trace(run.log, params)
    t_s = np.asarray(tr["t_s"])
    shock = _held(run.log.topic("/temperature/shock"), t_s)
    first = shock[np.isfinite(shock)][0] if np.isfinite(shock).any() else np.nan
    ambient = _held(run.log.topic(AMBIENT), t_s) if AMBIENT in run.log.topics else np.full(len(t_s), np.nan)
    ambient = np.where(np.isfinite(ambient), ambient, first)
    return {
        "t_s": t_s,
        "force_n": tr["force_n"],
        "position_m": tr["position_m"],  # the Kalman position, as the pipeline's force model uses
        "accel_rel_mps2": tr["accel_mps2"],  # the filter's acceleration
        "velocity_mps": tr["velocity_mps"],
        "force_model_n": tr["force_model_n"],
        "temp_shock_c": shock,
        "temp_ambient_c": ambient,
        "oil_temp_model_c": tr["oil_temp_model_c"],
        "cyl_temp_model_c": tr["cyl_temp_model_c"],
    }


# ---------------------------------------------------------------------------------------
# Thermal fit
# ---------------------------------------------------------------------------------------


THERMAL_SIGMA_C = 0.5  # expected model + thermocouple error, °C
THERMAL_PRIOR_FACTOR = 3.0  # a prior is believed to within this factor (one sigma)
#: One-sigma relative uncertainty of the heat capacities a datasheet implies: oil fill
#: ±2 %, the oil's density and specific heat ±3 %, steel mass ±1 %, its specific heat ±3 %.
DATASHEET_CAPACITY_SD_REL = 0.05
TC_LAG_PRIOR_S = 5.0  # a surface thermocouple's lag: seconds to tens of seconds (factor 3)
TC_GAIN_BOUNDS = (0.5, 1.0)  # a surface sensor reads at most the tube's rise above the air
#: The thermal model's heat balance (SPEC §3.2) and the shock thermocouple's model (tc_*).
TC_NAMES = ["tc_lag_s", "tc_gain"]


def held_ambient(tab: dict[str, np.ndarray]) -> np.ndarray:
    """The ambient temperature on every tick, for the thermal model's integration: a tick
    before the first reading (or between readings) holds the nearest one. Without it a
    thermocouple whose first reading comes a second late (a logger's own start-up, an
    import) made the model's state NaN throughout, and the force fit stopped on it
    ("Residuals are not finite in the initial point")."""
    amb = tab["temp_ambient_c"]
    ok = np.isfinite(amb)
    if ok.all() or not ok.any():
        return amb
    k = np.arange(len(amb))
    return np.interp(k, k[ok], amb[ok])


def heat_balance(thermal: dict[str, float]) -> Any:
    """The node model (``shocktwin.ThermalModel``) of a physics.json ``thermal`` part."""
    return shocktwin.ThermalModel(**{k: thermal[k] for k in THERMAL_NAMES})


def thermocouple_reading(tab: dict[str, np.ndarray], cyl: np.ndarray, gain: float, lag_s: float) -> np.ndarray:
    """What the shock thermocouple reads with the cylinder at ``cyl`` (the pipeline's
    ``thermocouple_model_c``): ``T_amb + κ (T_cyl − T_amb) + (1 − κ) (T_shock,0 − T_amb,0)``
    through a first-order lag ``lag_s``, starting at the first shock reading."""
    amb = tab["temp_ambient_c"]
    shock = tab["temp_shock_c"]
    first = np.flatnonzero(np.isfinite(shock) & np.isfinite(amb))
    k0 = first[0] if len(first) else 0
    target = amb + gain * (cyl - amb) + (1.0 - gain) * (shock[k0] - amb[k0])
    if lag_s <= 0:
        return target
    a = np.exp(-np.median(np.diff(tab["t_s"])) / lag_s)
    read = target.copy()
    read[k0:] = lfilter([1.0 - a], [1.0, -a], target[k0:] - target[k0]) + target[k0]
    return read


def thermal_residuals(
    theta: np.ndarray, names: Sequence[str], fixed: dict[str, float], tabs: Sequence[dict[str, np.ndarray]],
    stride: int, theta0: np.ndarray, prior_sd: np.ndarray,
) -> np.ndarray:
    """Thermocouple residuals (in units of ``THERMAL_SIGMA_C``) and the log-normal prior terms.

    Only the tube's outside temperature is measured, through a thermocouple: the split of
    the heat capacity between oil and cylinder, and of the conductances, is weakly
    identified on its own, and a sensor that reads a fraction ``tc_gain`` of the tube's rise
    is indistinguishable from a damper with ``1/tc_gain`` times the heat capacity. The
    priors (``shocktwin.default_params``, or the datasheet's oil volume and steel mass,
    believed to ``DATASHEET_CAPACITY_SD_REL``) make the fit a maximum a posteriori estimate.
    """
    params = {**fixed, **dict(zip(names, np.exp(theta)))}
    model = heat_balance(params)
    res = []
    for tab in tabs:
        power = np.nan_to_num(tab["force_n"] * tab["velocity_mps"])
        t0 = tab["temp_shock_c"][np.isfinite(tab["temp_shock_c"])][0]
        _, cyl = model.simulate(tab["t_s"], power, held_ambient(tab), t0, t0)
        read = thermocouple_reading(tab, cyl, params["tc_gain"], params["tc_lag_s"])
        r = (read - tab["temp_shock_c"])[::stride]
        res.append(r[np.isfinite(r)] / THERMAL_SIGMA_C)
    res.append((theta - theta0) / prior_sd)
    return np.concatenate(res)


def fit_thermal(
    tabs: Sequence[dict[str, np.ndarray]], prior: dict[str, float], capacities: dict[str, float] | None = None
) -> dict[str, float]:
    """The thermal model and the shock thermocouple's lag; with the datasheet's heat
    capacities (``c_oil`` and ``c_cyl``) also the thermocouple's gain, otherwise that stays 1."""
    capacities = capacities or {}
    pinned = {"c_oil", "c_cyl"} <= set(capacities)
    start = {**prior, **capacities, "tc_lag_s": TC_LAG_PRIOR_S, "tc_gain": 0.95}
    names = THERMAL_NAMES + TC_NAMES[: 2 if pinned else 1]
    fixed = {} if pinned else {"tc_gain": 1.0}
    theta0 = np.log([start[n] for n in names])
    sd = np.array([np.log1p(DATASHEET_CAPACITY_SD_REL) if n in capacities else np.log(THERMAL_PRIOR_FACTOR)
                   for n in names])
    # Hard bounds: a factor of 30 either side of the prior; the gain within its physical range, flat.
    lo, hi = theta0 - np.log(30.0), theta0 + np.log(30.0)
    if pinned:
        lo[-1], hi[-1] = np.log(TC_GAIN_BOUNDS)
        sd[-1] = np.inf
    sol = least_squares(thermal_residuals, theta0, bounds=(lo, hi),
                        args=(names, fixed, tabs, 50, theta0, sd))
    return {**fixed, **dict(zip(names, map(float, np.exp(sol.x))))}


# ---------------------------------------------------------------------------------------
# Force fit (with the fitted thermal model's oil temperature)
# ---------------------------------------------------------------------------------------


def oil_temperature(tab: dict[str, np.ndarray], thermal: dict[str, float]) -> np.ndarray:
    power = np.nan_to_num(tab["force_n"] * tab["velocity_mps"])
    t0 = tab["temp_shock_c"][np.isfinite(tab["temp_shock_c"])][0]
    oil, _ = heat_balance(thermal).simulate(
        tab["t_s"], power, held_ambient(tab), t0, t0
    )
    return oil


def _pack(force: dict[str, float], names: Sequence[str]) -> np.ndarray:
    return np.array([force[n] if n in FORCE_LINEAR else np.log(force[n]) for n in names])


def _unpack(theta: np.ndarray, base: dict[str, float], names: Sequence[str]) -> dict[str, float]:
    out = dict(base)
    for n, v in zip(names, theta):
        out[n] = float(v if n in FORCE_LINEAR else np.exp(v))
    return out


def fit_force(
    tabs: Sequence[dict[str, np.ndarray]],
    oils: Sequence[np.ndarray],
    prior: dict[str, float],
    fixed: Sequence[str] = (),
) -> dict[str, float]:
    """The force parameters of ``FORCE_FIT_NAMES`` but ``fixed`` (kept at ``prior``'s value)."""
    names = [n for n in FORCE_FIT_NAMES if n not in fixed]
    stride = 2
    cols = []
    for tab, oil in zip(tabs, oils):
        sel = (np.isfinite(tab["force_n"]) & np.isfinite(tab["velocity_mps"]) & np.isfinite(tab["position_m"])
               & np.isfinite(oil))
        idx = np.nonzero(sel)[0][::stride]
        cols.append(
            (tab["velocity_mps"][idx], tab["accel_rel_mps2"][idx], tab["position_m"][idx],
             oil[idx], tab["force_n"][idx])
        )
    v, a, y, oil, f = (np.concatenate(c) for c in zip(*cols))
    a = np.nan_to_num(a)

    def residuals(theta: np.ndarray) -> np.ndarray:
        model = shocktwin.ForceModel(**_unpack(theta, prior, names))
        return model.force(v, a, y, oil) - f

    theta0 = _pack(prior, names)
    linear = np.array([n in FORCE_LINEAR for n in names])
    lo = np.where(linear, 0.0, theta0 - np.log(50.0))
    hi = np.where(linear, np.inf, theta0 + np.log(50.0))
    sol = least_squares(residuals, theta0, bounds=(lo, hi), loss="soft_l1", f_scale=100.0)
    return _unpack(sol.x, prior, names)


# ---------------------------------------------------------------------------------------
# Closed-loop evaluation and figures
# ---------------------------------------------------------------------------------------


def rmse(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if len(x) else float("nan")


def evaluate(runs: Sequence[Run], params: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for run in runs:
        tab = table(run, params)
        rows.append(
            {
                "run": run.name,
                "frequency_hz": run.frequency_hz,
                # the thermocouple against what the model says it reads (tc_gain, tc_lag_s)
                "temperature_rmse_c": rmse(thermocouple_reading(
                    tab, tab["cyl_temp_model_c"], params["thermal"].get("tc_gain", 1.0),
                    params["thermal"].get("tc_lag_s", 0.0)) - tab["temp_shock_c"]),
                "force_rmse_n": rmse(tab["force_model_n"] - tab["force_n"]),
                "velocity_rmse_mps": velocity_rmse(run, params),
            }
        )
    return rows


def velocity_rmse(run: Run, params: dict[str, Any]) -> float | None:
    """KF velocity against the simulator's true velocity, when the log carries it."""
    if "/truth/velocity" not in run.log.topics:
        return None
    kf = kalman_trace(run, params)
    truth = run.log.topic("/truth/velocity")
    v_true = np.interp(kf["t_s"], truth["t_s"], truth["velocity_mps"])
    return rmse(kf["velocity_mps"] - v_true)


def kalman_trace(run: Run, params: dict[str, Any]) -> dict[str, np.ndarray]:
    """The Kalman velocity at sensor rate (at the 50 Hz ticks for the position-only filter)."""
    if ACCEL not in run.log.topics:
        tr = shocktwin.twin_trace(run.log, params)
        return {"t_s": tr["t_s"], "velocity_mps": tr["velocity_mps"]}
    acc = run.log.topic("/acceleration")
    pos = run.log.topic("/position")
    kf = shocktwin.KalmanFilter(**params["kalman"])
    return kf.run(acc["t_s"], acc["a1_mps2"] - acc["a2_mps2"], pos["t_s"], pos["position_m"])


def save_figures(runs: Sequence[Run], params: dict[str, Any], out_dir: Path, *, simulated: bool = True) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    by_freq = sorted(runs, key=lambda r: r.frequency_hz or 0.0)
    slow = by_freq[0]
    note = "simulated dyno data (shocktwin simulate)" if simulated else "dyno data"
    paths = []

    # Fig. 2: KF velocity vs time-differenced potentiometer, 1 Hz nominal run.
    kf = kalman_trace(slow, params)
    pos = slow.log.topic("/position")
    t0 = rest_end_s(slow) + 5.0
    win_k = (kf["t_s"] >= t0) & (kf["t_s"] <= t0 + 3.0)
    win_p = (pos["t_s"] >= t0) & (pos["t_s"] <= t0 + 3.0)
    fig, ax = plt.subplots(figsize=(8, 4))
    tp, zp = pos["t_s"][win_p], pos["position_m"][win_p]
    ax.plot(tp[1:], np.diff(zp) / np.diff(tp), ".", ms=3, color="0.6", label="time-differenced potentiometer")
    ax.plot(kf["t_s"][win_k], kf["velocity_mps"][win_k], lw=1.2, label="Kalman filter velocity")
    if "/truth/velocity" in slow.log.topics:
        tv = slow.log.topic("/truth/velocity")
        w = (tv["t_s"] >= t0) & (tv["t_s"] <= t0 + 3.0)
        ax.plot(tv["t_s"][w], tv["velocity_mps"][w], "--", lw=1, color="k", label="simulator truth")
    ax.set(xlabel="time since start of log (s)", ylabel="velocity (m/s)",
           title=f"Fig. 2 — estimated vs measured velocity, {slow.run_id}\n{note}")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "fig2_velocity.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    # Fig. 3: modelled vs measured temperature, each nominal run.
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for run in by_freq:
        tab = table(run, params)
        (line,) = ax.plot(tab["t_s"] / 60, tab["temp_shock_c"], lw=2, alpha=0.5,
                          label=f"measured, {run.frequency_hz:g} Hz")
        ax.plot(tab["t_s"] / 60, tab["cyl_temp_model_c"], ":", lw=1, color=line.get_color(),
                label=f"modelled cylinder, {run.frequency_hz:g} Hz")
        # what the printed T RMSE compares with the measurement (a helper's trial: the figure
        # showed the cylinder alone, 6 K above the reading, beside an RMSE of 0.28 °C)
        reading = thermocouple_reading(tab, tab["cyl_temp_model_c"], params["thermal"].get("tc_gain", 1.0),
                                       params["thermal"].get("tc_lag_s", 0.0))
        ax.plot(tab["t_s"] / 60, reading, "--", color=line.get_color(),
                label=f"modelled thermocouple reading (T RMSE), {run.frequency_hz:g} Hz")
    ax.set(xlabel="time (min)", ylabel="shock temperature (°C)",
           title=f"Fig. 3 — modelled and measured temperature, nominal charge\n{note}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "fig3_temperature.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    # Fig. 6: modelled force vs velocity coloured by oil temperature, measured
    # averages per velocity bin dashed for four temperature ranges.
    tab = table(slow, params)
    v, fm, fmeas, temp = tab["velocity_mps"], tab["force_model_n"], tab["force_n"], tab["oil_temp_model_c"]
    ok = np.isfinite(v) & np.isfinite(fm) & np.isfinite(fmeas)
    v, fm, fmeas, temp = v[ok], fm[ok], fmeas[ok], temp[ok]
    fig, ax = plt.subplots(figsize=(8, 5))
    sc = ax.scatter(v, fm, c=temp, s=2, cmap="plasma")
    fig.colorbar(sc, ax=ax, label="modelled oil temperature (°C)")
    edges = np.quantile(temp, [0, 0.25, 0.5, 0.75, 1.0])
    bins = np.linspace(v.min(), v.max(), 40)
    cmap = plt.get_cmap("plasma")
    for lo_t, hi_t in zip(edges[:-1], edges[1:]):
        sel = (temp >= lo_t) & (temp <= hi_t)
        idx = np.digitize(v[sel], bins)
        centres = [v[sel][idx == k].mean() for k in range(1, len(bins)) if np.sum(idx == k) > 5]
        means = [fmeas[sel][idx == k].mean() for k in range(1, len(bins)) if np.sum(idx == k) > 5]
        mid = 0.5 * (lo_t + hi_t)
        ax.plot(centres, means, "--", color=cmap((mid - edges[0]) / (edges[-1] - edges[0] + 1e-9)),
                lw=1.5, label=f"measured mean, ~{mid:.0f} °C")
    ax.set(xlabel="velocity (m/s), + = rebound", ylabel="force (N), + = tension",
           title=f"Fig. 6 — modelled (colour) and measured (dashed) force, {slow.run_id}\n{note}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "fig6_force.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


# ---------------------------------------------------------------------------------------


class PiecewiseLinearDamping:
    """The five-minute baseline: force against Kalman velocity, one continuous piecewise-linear
    curve of |v| per direction (rebound ``v >= 0``, compression ``v < 0``; the two may differ
    at ``v = 0``), each an offset, a slope and slope changes at ``n_knots`` knots (quantiles of
    the direction's |v|), fitted together by ordinary least squares (``numpy.linalg.lstsq``).
    Linear beyond the outer knots; no temperature, position or acceleration."""

    DESCRIPTION = "piecewise-linear damping force vs Kalman velocity, per direction (OLS)"
    N_KNOTS = 3

    def __init__(self, knots: dict[str, np.ndarray], coef: np.ndarray) -> None:
        self.knots, self.coef = knots, coef

    @staticmethod
    def _design(v: np.ndarray, knots: dict[str, np.ndarray]) -> np.ndarray:
        cols: list[np.ndarray] = []
        for side, k in ((v >= 0, knots["rebound"]), (v < 0, knots["compression"])):
            s = np.abs(v) * side
            cols += [side.astype(float), s] + [np.maximum(s - kj, 0.0) * side for kj in k]
        return np.column_stack(cols)

    @classmethod
    def fit(cls, v: np.ndarray, f: np.ndarray, n_knots: int = N_KNOTS) -> "PiecewiseLinearDamping":
        q = np.linspace(0, 1, n_knots + 2)[1:-1]
        knots = {
            "rebound": np.quantile(v[v >= 0], q) if np.any(v >= 0) else np.zeros(0),
            "compression": np.quantile(-v[v < 0], q) if np.any(v < 0) else np.zeros(0),
        }
        coef, *_ = np.linalg.lstsq(cls._design(v, knots), f, rcond=None)
        return cls(knots, coef)

    def predict(self, v: np.ndarray) -> np.ndarray:
        return self._design(v, self.knots) @ self.coef


def fit_models(
    runs: Sequence[Run], base: dict[str, Any], fixed: Sequence[str], capacities: dict[str, float] | None = None
) -> tuple[dict[str, Any], list[dict[str, np.ndarray]]]:
    """Steps 1–3 on ``runs``: Kalman noise, thermal model (with the datasheet's heat
    ``capacities`` as its prior), force model. Returns the parameters and the runs' tables
    (with the fitted Kalman filter, prior thermal/force)."""
    params: dict[str, Any] = {k: dict(v) for k, v in base.items()}
    params["kalman"] = fit_kalman(runs, params["kalman"])
    tabs = [table(run, params) for run in progress(runs, desc="features", unit="run")]
    params["thermal"] = fit_thermal(tabs, params["thermal"], capacities)
    oils = [oil_temperature(tab, params["thermal"]) for tab in tabs]
    params["force"] = fit_force(tabs, oils, params["force"], fixed)
    return params, tabs


def _force_pairs(tab: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(tab["velocity_mps"]) & np.isfinite(tab["force_n"])
    return tab["velocity_mps"][ok], tab["force_n"][ok]


def held_out_comparison(
    runs: Sequence[Run], base: dict[str, Any], fixed: Sequence[str], capacities: dict[str, float] | None = None
) -> dict[str, Any]:
    """Physics force model vs :class:`PiecewiseLinearDamping`, leave one nominal run out.

    Each fold fits steps 1–3 and the baseline on the other nominal runs only; on the left-out
    run the physics is scored through the twin's pipeline with the fold's parameters, the
    baseline on that pipeline's velocity, both on the same ticks (loadcell and both models
    finite). RMSEs pool the squared errors of every held-out tick."""
    protocol = "leave one nominal run out: fit on the others, score on it (50 Hz ticks)"
    if len(runs) < 2:
        log.warning("one nominal run: no held-out comparison with the piecewise-linear baseline")
        return {"protocol": protocol, "skipped": "needs two nominal runs or more"}
    folds, se_phys, se_base = [], [], []
    for k, run in enumerate(runs):
        train = [r for i, r in enumerate(runs) if i != k]
        params, tabs = fit_models(train, base, fixed, capacities)
        pairs = [_force_pairs(tab) for tab in tabs]
        baseline = PiecewiseLinearDamping.fit(np.concatenate([v for v, _ in pairs]),
                                              np.concatenate([f for _, f in pairs]))
        test = table(run, params)
        ok = np.isfinite(test["force_n"]) & np.isfinite(test["force_model_n"]) & np.isfinite(test["velocity_mps"])
        e_phys = (test["force_model_n"] - test["force_n"])[ok]
        e_base = (baseline.predict(test["velocity_mps"][ok]) - test["force_n"][ok])
        se_phys.append(e_phys**2)
        se_base.append(e_base**2)
        folds.append({"held_out": run.name, "trained_on": [r.name for r in train], "ticks": int(ok.sum()),
                      "physics_rmse_n": rmse(e_phys), "baseline_rmse_n": rmse(e_base)})
    phys = float(np.sqrt(np.mean(np.concatenate(se_phys))))
    base_rmse = float(np.sqrt(np.mean(np.concatenate(se_base))))
    return {
        "protocol": protocol,
        "baseline": {"model": PiecewiseLinearDamping.DESCRIPTION, "knots_per_direction": PiecewiseLinearDamping.N_KNOTS},
        "folds": folds,
        "physics_rmse_n": phys,
        "baseline_rmse_n": base_rmse,
        # > 0: the physics model's held-out RMSE is this much lower than the baseline's
        "physics_improvement_pct": 100.0 * (1.0 - phys / base_rmse),
        "physics_beats_baseline": phys < base_rmse,
    }


def reduced_model(runs: Sequence[Run]) -> dict[str, Any]:
    """Which of the twin's reduced models the nominal runs need (and warn about them)."""
    no_acc = [r.name for r in runs if ACCEL not in r.log.topics]
    no_amb = [r.name for r in runs if AMBIENT not in r.log.topics]
    if no_acc:
        log.warning("reduced model: no %s on %s: position-only Kalman filter (constant-acceleration "
                    "model on the potentiometer alone, SPEC §3.1)", ACCEL, ", ".join(no_acc))
    if no_amb:
        log.warning("reduced model: no %s on %s: each run's first shock temperature stands in for "
                    "ambient in the thermal model", AMBIENT, ", ".join(no_amb))
    return {
        "kalman": "position_only" if no_acc else "accelerometers",
        "ambient": "first_shock_temperature" if no_amb else "thermocouple",
        "runs_without_acceleration": no_acc,
        "runs_without_ambient": no_amb,
    }


def calibrate(
    campaign: Campaign,
    *,
    nominal_bar: float = 12.0,
    datasheet: Datasheet | None = None,
    nominal_input: str | None = None,
) -> dict[str, Any]:
    """Steps 1–5 on the campaign's nominal runs; the ``physics.json`` content."""
    runs = campaign.nominal(nominal_bar)
    # The runs' label is the nominal charge (a value converted from psi is within the tolerance).
    nominal_bar = float(np.median([r.label_bar for r in runs]))
    require_topics(runs, NEEDED_TOPICS,
                   "calibration needs the potentiometer, loadcell and shock thermocouple on the nominal runs")
    reduced = reduced_model(runs)
    prior = shocktwin.default_params()
    base: dict[str, Any] = {k: dict(v) for k, v in prior.items()}
    base["force"]["charge_bar"] = nominal_bar
    geometry = dict(datasheet.geometry) if datasheet else {}
    base["force"].update(geometry)
    started = time.perf_counter()

    capacities = dict(datasheet.heat_capacities) if datasheet else {}
    if not {"c_oil", "c_cyl"} <= set(capacities):
        log.warning("no oil volume and steel mass in a datasheet: the thermal model's heat capacities keep "
                    "their loose priors and the shock thermocouple is taken to read the tube (tc_gain 1); "
                    "the modelled oil can then run tens of kelvin hot")
    params, _ = fit_models(runs, base, fixed=list(geometry), capacities=capacities)
    log.info("Kalman noise: %s", params["kalman"])
    log.info("thermal: %s", params["thermal"])
    log.info("force: %s", params["force"])
    per_run = evaluate(runs, params)
    comparison = held_out_comparison(runs, base, fixed=list(geometry), capacities=capacities)
    elapsed = time.perf_counter() - started
    return {
        "format": PHYSICS_FORMAT,
        "kalman": params["kalman"],
        "thermal": params["thermal"],
        "force": params["force"],
        "nominal_bar": nominal_bar,
        "nominal_input": nominal_input or f"{nominal_bar:g} bar",
        "reduced_model": reduced,
        "geometry": {
            "source": f"datasheet {datasheet.path}" if datasheet else "fitted from the priors",
            "fixed": geometry,
            "datasheet": datasheet.values if datasheet else None,
        },
        "baseline_comparison": comparison,
        "fit": {
            "campaign": str(campaign.root.name),
            "campaign_digest": campaign.digest(),
            "runs": [r.name for r in runs],
            "per_run": per_run,
            "seconds": round(elapsed, 2),
            "simulated_data": campaign.simulated,
        },
    }


def print_report(physics: dict[str, Any]) -> None:
    data = "simulated data" if physics["fit"].get("simulated_data", True) else "dyno data"
    red = physics.get("reduced_model") or {}
    models = []
    if red.get("kalman") == "position_only":
        models.append("position-only Kalman filter")
    if red.get("ambient") == "first_shock_temperature":
        models.append("first shock temperature as ambient")
    print(f"Calibration on the nominal runs at {physics.get('nominal_bar', 12.0):g} bar ({data}) — closed loop "
          "through the twin's pipeline" + (f"; reduced model: {', '.join(models)}" if models else ""))
    print(f"{'run':<32} {'T RMSE (°C)':>12} {'F RMSE (N)':>11} {'v RMSE (m/s)':>13}")
    for row in physics["fit"]["per_run"]:
        v = row["velocity_rmse_mps"]
        print(f"{row['run']:<32} {row['temperature_rmse_c']:>12.2f} {row['force_rmse_n']:>11.1f} "
              f"{'n/a' if v is None else f'{v:.4f}':>13}")
    th = physics["thermal"]
    print(f"thermal model: c_oil {th['c_oil']:.0f} J/K, c_cyl {th['c_cyl']:.0f} J/K, ha_in {th['ha_in']:.1f} W/K, "
          f"ha_out {th['ha_out']:.2f} W/K; shock thermocouple reads {th.get('tc_gain', 1.0):.2f} of the tube's "
          f"rise, lag {th.get('tc_lag_s', 0.0):.1f} s")
    geo = physics.get("geometry") or {}
    if geo.get("fixed"):
        print(f"geometry from {geo['source']}: " + ", ".join(f"{k} = {v:.6g}" for k, v in geo["fixed"].items()))
    cmp = physics.get("baseline_comparison") or {}
    if "physics_rmse_n" in cmp:
        print(f"Force on held-out nominal runs ({cmp['protocol']}):")
        print(f"{'held-out run':<32} {'physics (N)':>12} {'piecewise-linear (N)':>21}")
        for fold in cmp["folds"]:
            print(f"{fold['held_out']:<32} {fold['physics_rmse_n']:>12.1f} {fold['baseline_rmse_n']:>21.1f}")
        print(f"{'pooled':<32} {cmp['physics_rmse_n']:>12.1f} {cmp['baseline_rmse_n']:>21.1f}")
        pct = cmp["physics_improvement_pct"]
        if cmp["physics_beats_baseline"]:
            print(f"the physics model's held-out force RMSE is {pct:.0f} % lower than the piecewise-linear baseline's")
        else:
            print(f"the physics model does NOT beat the piecewise-linear baseline: its held-out force RMSE is "
                  f"{-pct:.0f} % higher")
    elif cmp:
        print(f"no held-out comparison with the baseline: {cmp.get('skipped')}")
    print(f"calibration took {physics['fit']['seconds']:.1f} s")


def resolve_nominal(args: argparse.Namespace, datasheet: Datasheet | None) -> tuple[float, str | None]:
    """The nominal charge (bar) from --nominal-bar, --nominal, the datasheet, or 12 bar."""
    if args.nominal_bar is not None:
        return args.nominal_bar, None
    text = args.nominal or (datasheet.nominal_charge if datasheet else None)
    if text is None:
        return 12.0, None
    try:
        return parse_pressure_bar(text), text
    except ValueError as err:
        raise ValueError(f"--nominal: {err}") from None


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.fit_physics", description=__doc__.split("\n")[0])
    parser.add_argument("--campaign", required=True, type=Path, help="campaign directory of *.mcap runs")
    parser.add_argument("--out", required=True, type=Path, help="physics.json to write")
    nominal = parser.add_mutually_exclusive_group()
    nominal.add_argument("--nominal-bar", type=float, help="nominal charge pressure, bar gauge (default: the "
                         "datasheet's nominal_charge, else 12)")
    nominal.add_argument("--nominal", help='nominal charge with a unit: "150 psi", "10.3 bar", "1.03 MPa", '
                         '"1030 kPa" (gauge)')
    parser.add_argument("--datasheet", type=Path, help="damper datasheet (TOML, see docs/datasheet.example.toml): "
                        "fixes the geometry (a_rod, v_gas) instead of fitting it")
    parser.add_argument("--figures", type=Path, help="directory for Fig. 2, 3 and 6 (PNG)")
    args = parser.parse_args(argv)

    datasheet = load_datasheet(args.datasheet) if args.datasheet else None
    nominal_bar, nominal_input = resolve_nominal(args, datasheet)
    campaign = load_campaign(args.campaign)
    if args.nominal_bar is None and args.nominal is None and nominal_input is not None:
        # the datasheet's nominal charge: say so if no run is at it (a datasheet for another
        # campaign's unit silently replaced the default 12 bar)
        try:
            campaign.nominal(nominal_bar)
        except CampaignError as err:
            raise CampaignError(f"{err} — {nominal_bar:g} bar is the datasheet {args.datasheet}'s nominal_charge "
                                f"{nominal_input!r}; --nominal-bar overrides it") from None
    physics = calibrate(campaign, nominal_bar=nominal_bar, datasheet=datasheet, nominal_input=nominal_input)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(physics, indent=2) + "\n")
    print_report(physics)
    if args.figures:
        runs = campaign.nominal(physics["nominal_bar"])
        for path in save_figures(runs, physics, args.figures, simulated=campaign.simulated):
            print(f"figure: {path}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
