"""Calibrate the twin's physics on the nominal runs of a campaign (paper §5.2.3, §5.3.6).

    python -m train.fit_physics --campaign DIR --out physics.json [--figures DIR]

Steps, all on the runs at the nominal charge pressure (12 bar by default):

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

The data are simulated (``shocktwin simulate``); the figures say so.
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

import shocktwin

from train.campaign import Campaign, CampaignError, Run, load_campaign, main_wrapper, require_topics
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
NEEDED_TOPICS = ["/position", "/acceleration", "/force", "/temperature/shock", "/temperature/ambient"]


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
    sz, sa = [], []
    for run in runs:
        t_end = rest_end_s(run) - 1.0
        pos = run.log.topic("/position")
        acc = run.log.topic("/acceleration")
        z = pos["position_m"][pos["t_s"] < t_end]
        a = (acc["a1_mps2"] - acc["a2_mps2"])[acc["t_s"] < t_end]
        z, a = z[np.isfinite(z)], a[np.isfinite(a)]
        if len(z) > 50 and len(a) > 500:
            sz.append(np.std(z))
            sa.append(np.std(a))
    if not sz:
        log.warning("no rest period found; Kalman noise stays at its prior")
        return dict(prior)
    fitted = dict(prior)
    # Quantisation alone can give a zero std at rest: floors of 1 µm and 1 mm/s².
    fitted["sigma_position"] = max(float(np.median(sz)), 1e-6)
    fitted["sigma_accel"] = max(float(np.median(sa)), 1e-3)
    return fitted


# ---------------------------------------------------------------------------------------
# Feature tables of the nominal runs
# ---------------------------------------------------------------------------------------

FIT_GROUPS = ["force", "position", "acceleration", "velocity", "mechanical", "thermal"]


def table(run: Run, params: dict[str, Any]) -> dict[str, np.ndarray]:
    x, columns, t_s = shocktwin.features(run.log, params, FIT_GROUPS)
    out = {name: x[:, i] for i, name in enumerate(columns)}
    out["t_s"] = np.asarray(t_s)
    return out


# ---------------------------------------------------------------------------------------
# Thermal fit
# ---------------------------------------------------------------------------------------


THERMAL_SIGMA_C = 0.5  # expected model + thermocouple error, °C
THERMAL_PRIOR_FACTOR = 3.0  # a prior is believed to within this factor (one sigma)


def thermal_residuals(
    theta: np.ndarray, tabs: Sequence[dict[str, np.ndarray]], stride: int, theta0: np.ndarray
) -> np.ndarray:
    """Temperature residuals (in units of ``THERMAL_SIGMA_C``) and the log-normal prior terms.

    Only the cylinder temperature is measured: the split of the heat capacity between oil
    and cylinder, and of the conductances, is weakly identified on its own. The priors
    (``shocktwin.default_params``, a typical damper's oil and steel masses) make the fit a
    maximum a posteriori estimate instead of letting those parameters run to their bounds.
    """
    params = dict(zip(THERMAL_NAMES, np.exp(theta)))
    model = shocktwin.ThermalModel(**params)
    res = []
    for tab in tabs:
        power = np.nan_to_num(tab["force_n"] * tab["velocity_mps"])
        t0 = tab["temp_shock_c"][np.isfinite(tab["temp_shock_c"])][0]
        _, cyl = model.simulate(tab["t_s"], power, tab["temp_ambient_c"], t0, t0)
        r = (cyl - tab["temp_shock_c"])[::stride]
        res.append(r[np.isfinite(r)] / THERMAL_SIGMA_C)
    res.append((theta - theta0) / np.log(THERMAL_PRIOR_FACTOR))
    return np.concatenate(res)


def fit_thermal(tabs: Sequence[dict[str, np.ndarray]], prior: dict[str, float]) -> dict[str, float]:
    theta0 = np.log([prior[n] for n in THERMAL_NAMES])
    # Hard bounds: a factor of 30 either side of the prior.
    lo, hi = theta0 - np.log(30.0), theta0 + np.log(30.0)
    sol = least_squares(thermal_residuals, theta0, bounds=(lo, hi), args=(tabs, 50, theta0))
    return dict(zip(THERMAL_NAMES, map(float, np.exp(sol.x))))


# ---------------------------------------------------------------------------------------
# Force fit (with the fitted thermal model's oil temperature)
# ---------------------------------------------------------------------------------------


def oil_temperature(tab: dict[str, np.ndarray], thermal: dict[str, float]) -> np.ndarray:
    power = np.nan_to_num(tab["force_n"] * tab["velocity_mps"])
    t0 = tab["temp_shock_c"][np.isfinite(tab["temp_shock_c"])][0]
    oil, _ = shocktwin.ThermalModel(**thermal).simulate(
        tab["t_s"], power, tab["temp_ambient_c"], t0, t0
    )
    return oil


def _pack(force: dict[str, float]) -> np.ndarray:
    return np.array(
        [force[n] if n in FORCE_LINEAR else np.log(force[n]) for n in FORCE_FIT_NAMES]
    )


def _unpack(theta: np.ndarray, base: dict[str, float]) -> dict[str, float]:
    out = dict(base)
    for n, v in zip(FORCE_FIT_NAMES, theta):
        out[n] = float(v if n in FORCE_LINEAR else np.exp(v))
    return out


def fit_force(
    tabs: Sequence[dict[str, np.ndarray]], oils: Sequence[np.ndarray], prior: dict[str, float]
) -> dict[str, float]:
    stride = 2
    cols = []
    for tab, oil in zip(tabs, oils):
        sel = np.isfinite(tab["force_n"]) & np.isfinite(tab["velocity_mps"])
        idx = np.nonzero(sel)[0][::stride]
        cols.append(
            (tab["velocity_mps"][idx], tab["accel_rel_mps2"][idx], tab["position_m"][idx],
             oil[idx], tab["force_n"][idx])
        )
    v, a, y, oil, f = (np.concatenate(c) for c in zip(*cols))
    a = np.nan_to_num(a)

    def residuals(theta: np.ndarray) -> np.ndarray:
        model = shocktwin.ForceModel(**_unpack(theta, prior))
        return model.force(v, a, y, oil) - f

    theta0 = _pack(prior)
    linear = np.array([n in FORCE_LINEAR for n in FORCE_FIT_NAMES])
    lo = np.where(linear, 0.0, theta0 - np.log(50.0))
    hi = np.where(linear, np.inf, theta0 + np.log(50.0))
    sol = least_squares(residuals, theta0, bounds=(lo, hi), loss="soft_l1", f_scale=100.0)
    return _unpack(sol.x, prior)


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
                "temperature_rmse_c": rmse(tab["cyl_temp_model_c"] - tab["temp_shock_c"]),
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
    acc = run.log.topic("/acceleration")
    pos = run.log.topic("/position")
    kf = shocktwin.KalmanFilter(**params["kalman"])
    return kf.run(acc["t_s"], acc["a1_mps2"] - acc["a2_mps2"], pos["t_s"], pos["position_m"])


def save_figures(runs: Sequence[Run], params: dict[str, Any], out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    by_freq = sorted(runs, key=lambda r: r.frequency_hz or 0.0)
    slow = by_freq[0]
    note = "simulated dyno data (shocktwin simulate)"
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
        ax.plot(tab["t_s"] / 60, tab["cyl_temp_model_c"], "--", color=line.get_color(),
                label=f"modelled cylinder, {run.frequency_hz:g} Hz")
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


def calibrate(campaign: Campaign, *, nominal_bar: float = 12.0) -> dict[str, Any]:
    runs = campaign.nominal(nominal_bar)
    require_topics(runs, NEEDED_TOPICS, "calibration needs the full sensor suite on the nominal runs")
    prior = shocktwin.default_params()
    params: dict[str, Any] = {k: dict(v) for k, v in prior.items()}
    params["force"]["charge_bar"] = nominal_bar
    started = time.perf_counter()

    params["kalman"] = fit_kalman(runs, params["kalman"])
    log.info("Kalman noise: %s", params["kalman"])

    tabs = [table(run, params) for run in progress(runs, desc="features", unit="run")]
    params["thermal"] = fit_thermal(tabs, params["thermal"])
    log.info("thermal: %s", params["thermal"])

    oils = [oil_temperature(tab, params["thermal"]) for tab in tabs]
    params["force"] = fit_force(tabs, oils, params["force"])
    log.info("force: %s", params["force"])

    per_run = evaluate(runs, params)
    elapsed = time.perf_counter() - started
    return {
        "format": PHYSICS_FORMAT,
        "kalman": params["kalman"],
        "thermal": params["thermal"],
        "force": params["force"],
        "nominal_bar": nominal_bar,
        "fit": {
            "campaign": str(campaign.root.name),
            "campaign_digest": campaign.digest(),
            "runs": [r.name for r in runs],
            "per_run": per_run,
            "seconds": round(elapsed, 2),
            "simulated_data": True,
        },
    }


def print_report(physics: dict[str, Any]) -> None:
    print("Calibration on the nominal runs (simulated data) — closed loop through the twin's pipeline")
    print(f"{'run':<32} {'T RMSE (°C)':>12} {'F RMSE (N)':>11} {'v RMSE (m/s)':>13}")
    for row in physics["fit"]["per_run"]:
        v = row["velocity_rmse_mps"]
        print(f"{row['run']:<32} {row['temperature_rmse_c']:>12.2f} {row['force_rmse_n']:>11.1f} "
              f"{'n/a' if v is None else f'{v:.4f}':>13}")
    print(f"calibration took {physics['fit']['seconds']:.1f} s")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.fit_physics", description=__doc__.split("\n")[0])
    parser.add_argument("--campaign", required=True, type=Path, help="campaign directory of *.mcap runs")
    parser.add_argument("--out", required=True, type=Path, help="physics.json to write")
    parser.add_argument("--nominal-bar", type=float, default=12.0, help="nominal charge pressure (bar)")
    parser.add_argument("--figures", type=Path, help="directory for Fig. 2, 3 and 6 (PNG)")
    args = parser.parse_args(argv)

    campaign = load_campaign(args.campaign)
    physics = calibrate(campaign, nominal_bar=args.nominal_bar)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(physics, indent=2) + "\n")
    print_report(physics)
    if args.figures:
        runs = campaign.nominal(args.nominal_bar)
        for path in save_figures(runs, physics, args.figures):
            print(f"figure: {path}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
