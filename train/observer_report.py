"""Score the gas-charge observer on held-out sets: RMSE, interval coverage, the
maintenance metric and the information bound (``python -m train.observer evaluate``).

Everything here is computed on simulated data (``shocktwin simulate``) and says so.

The health verdict is the SPEC §6a rule of dt-core's ``HealthMachine`` applied to the
observer's 1 s average and its 95 % interval (``leak`` when the interval lies below the
fault threshold, ``low`` below the warn threshold, ``ok`` above it, ``unknown``
otherwise; hysteresis and dwell as §6). The *right* verdict of a run is ``leak`` below
5 bar, ``low`` below 9 bar, ``ok`` from 9 bar.

The information bound (Cramér–Rao) is computed independently of dt-core: the window
model of one reversal (mount, friction flip, damping, accelerometer filter) is
integrated here with scipy's ``solve_ivp`` at the rig's nominal values, its Jacobian
taken by central differences, and the Fisher information of the friction amplitude
after the four nuisance parameters are profiled out (Schur complement) is converted
to bar with the measurement model's gain. Reversals come at twice the excitation
frequency, so after ``t`` seconds the noise-only bound is
``sd(t) = 1 / sqrt(2 f t I_p)``. The *Bayesian* bound adds the prior spread of
what no amount of data from one unit separates from the charge: the unit-to-unit
spread of the observer's error (``systematic_sd_bar`` and ``systematic_rel``: measured on other
units by ``observer unit-spread`` where it was run, as ``make demo`` and ``make study`` do; else
the calibration's leave-one-run-out spread and an assumed tolerance of the seal friction).
The gas-spring channel is bounded the same way (its force amplitude per bar through
the mount at the excitation frequency, white accelerometer noise).
"""

from __future__ import annotations

import argparse
import json
import logging
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq
from scipy.stats import chi2

import shocktwin

from train.campaign import load_campaign, read_json
from train.damping_law import law_calibrated
from train.fit_physics import rest_end_s
from train.progress import progress
from train.observer import DWELL_S, FAULT_BAR, HYST_BAR, P_ATM_BAR, WARN_BAR, Z95, excitation_end_s, warm_terms

log = logging.getLogger("shocktwin.observer")

TICK_S = 0.02
ACC_NOISE_MPS2 = 0.064      # accelerometer white noise at 1 kHz (dt-sim sensor table)
ACC_LSB_MPS2 = 0.038        # quantisation step
STROKE_AMP_M = 0.04         # half stroke of the dyno campaign


# ---------------------------------------------------------------------------------------
# per-run scoring
# ---------------------------------------------------------------------------------------


def expected_health(p_bar: float) -> str:
    return "leak" if p_bar < FAULT_BAR else "low" if p_bar < WARN_BAR else "ok"


def health_series(t: np.ndarray, avg: np.ndarray, lo: np.ndarray, hi: np.ndarray, excited: np.ndarray) -> list[str]:
    """SPEC §6a with hysteresis and dwell (the rule of dt-core's ``HealthMachine``)."""
    state, cand, since = "unknown", "unknown", -np.inf
    out = []
    for ti, a, l, h, e in zip(t, avg, lo, hi, excited):
        if not (e and np.isfinite(a) and np.isfinite(l) and np.isfinite(h)) or h < -P_ATM_BAR:
            # (wholly below vacuum: no charge a damper holds, the model does not read this unit)
            target = "unknown"
        else:
            fault_hi = FAULT_BAR + HYST_BAR if state == "leak" else FAULT_BAR
            warn_hi = WARN_BAR + HYST_BAR if state in ("leak", "low") else WARN_BAR
            warn_lo = WARN_BAR - HYST_BAR if state == "ok" else WARN_BAR
            target = "leak" if h < fault_hi else "low" if h < warn_hi else "ok" if l > warn_lo else "unknown"
        if target != cand:
            cand, since = target, ti
        if cand != state and ti - since >= DWELL_S - 1e-9:
            state = cand
        out.append(state)
    return out


# A run's observer columns as ``shocktwin.features(run, physics, ["observer"])`` gives them:
# tick times (s), ``observer_bar``, ``observer_sd_bar``.
Observed = tuple[np.ndarray, np.ndarray, np.ndarray]


@lru_cache(maxsize=1)
def _campaign_runs(directory: str) -> dict[str, Any]:
    """A held-out set's runs by path, read once per worker process while its runs come one after
    another (the tasks are in set order), not once per run."""
    return {str(r.path): r for r in load_campaign(Path(directory)).runs}


def unit_calibration(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """How the runs' final errors compare with their intervals, unit by unit.

    Most of an unbaselined reading's error is its unit's (the seal's tolerance): the runs of one
    unit share it, so a set's ticks are as many independent draws as it has units, not ticks. The
    per-tick coverage of a set of one or two units says little (at a 95 % interval, 12 units all
    cover more often than not: 0.95¹² = 0.54). What a handful of units can test is the size of the
    interval: ``z = (final − truth) / final sd`` has RMS 1 when the interval is honest. Each unit
    counts once, its runs' ``z²`` averaged first; over K units the RMS then lies within
    ``√(χ²_K(2.5 %, 97.5 %) / K)`` 95 % of the time when each unit's runs share one error (K
    degrees of freedom, one a unit). The range is approximate: runs of one unit whose errors
    differ make it too wide, and units on one rig, which share its sensors' errors, are not
    quite independent draws."""
    scored = [r for r in rows if r.get("final_z") is not None]
    by_unit: dict[str, list[float]] = {}
    for r in scored:
        by_unit.setdefault(r["unit"], []).append(float(r["final_z"]) ** 2)
    units = len(by_unit)
    lo, hi = (np.sqrt(chi2.ppf([0.025, 0.975], units) / units) if units else (np.nan, np.nan))
    zs = np.array([r["final_z"] for r in scored], float)
    return {"units": units,
            "final_z_rms": float(np.sqrt(np.mean([np.mean(v) for v in by_unit.values()]))) if units else None,
            "final_z_rms_calibrated": [float(lo), float(hi)],
            "final_z_runs": len(zs),
            "final_covered_runs": int(np.sum(np.abs(zs) <= Z95))}


def draw_runs(picks: list[dict[str, Any]], path: Path) -> None:
    """The estimate with its interval against time for each of ``picks`` (scored runs)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(picks), 1, figsize=(9, 3.2 * max(1, len(picks))), squeeze=False)
    for ax, r in zip(axes[:, 0], picks):
        tr = r["trace"]
        t, m, s = np.array(tr["t_s"]), np.array(tr["mean"]), np.array(tr["sd"])
        ax.fill_between(t, m - Z95 * s, m + Z95 * s, color="C0", alpha=0.25, label="95 % interval")
        ax.plot(t, m, "C0", lw=1, label="observer estimate")
        ax.plot(t, tr["label"], "k--", lw=1, label="true charge (simulated)")
        ax.axhline(WARN_BAR, color="orange", lw=0.8)
        ax.axhline(FAULT_BAR, color="red", lw=0.8)
        if r["time_to_right_s"] is not None:
            ax.axvline(r["time_to_right_s"], color="green", lw=1, label=f"verdict `{r['expected_health']}` from {r['time_to_right_s']:.0f} s")
        ax.set_xlim(-10, min(t[-1], 600))
        ax.set_ylim(-4, 20)
        ax.set_title(f"{r['set']}: {r['run']} — SIMULATED DATA", fontsize=9)
        ax.set_ylabel("charge (bar)")
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time since excitation onset (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def score_run(args: tuple[str, str, dict[str, Any], float, Observed | None]) -> dict[str, Any]:
    path, set_name, physics, settle_s, observed = args
    run = _campaign_runs(str(Path(path).parent))[path]
    if observed is None:
        x, cols, t = shocktwin.features(path, physics, ["observer"])
        observed = (np.asarray(t), x[:, cols.index("observer_bar")], x[:, cols.index("observer_sd_bar")])
    t, mean, sd = observed
    label = np.full(len(t), float(run.label_bar))
    onset = rest_end_s(run)
    end = excitation_end_s(run.log, float(t[-1]))
    excited = (t >= onset) & (t <= end)
    k = int(round(1.0 / TICK_S))
    avg = np.convolve(mean, np.ones(k) / k, mode="full")[: len(mean)]
    avg[: k - 1] = np.nan
    lo, hi = mean - Z95 * sd, mean + Z95 * sd
    alo, ahi = avg - Z95 * sd, avg + Z95 * sd
    health = health_series(t, avg, alo, ahi, excited)
    scored = excited & (t >= onset + settle_s)
    truth = float(np.median(label[excited])) if excited.any() else float("nan")
    want = expected_health(truth)
    right = np.array([h == want for h in health])
    # time from onset until the verdict is right and stays right while excited
    idx = np.nonzero(excited)[0]
    t_right = None
    if len(idx) and right[idx[-1]]:
        wrong_after = idx[~right[idx]]
        first = idx[0] if len(wrong_after) == 0 else wrong_after[-1] + 1
        t_right = float(t[first] - onset)
    alarms = sum(1 for h in np.array(health)[excited] if h in ("low", "leak")) if want == "ok" else 0
    err = mean[scored] - label[scored]
    err_avg = avg[scored] - label[scored]
    cover = (label[scored] >= lo[scored]) & (label[scored] <= hi[scored])
    return {
        "set": set_name, "run": run.name, "truth_bar": truth, "frequency_hz": run.frequency_hz,
        "onset_s": onset, "excited_s": float(end - onset), "ticks": int(scored.sum()),
        "sq_err": float(np.sum(err ** 2)), "sq_err_avg": float(np.nansum(err_avg ** 2)),
        "covered": int(cover.sum()),
        "rmse_bar": float(np.sqrt(np.mean(err ** 2))) if scored.any() else None,
        "coverage": float(cover.mean()) if scored.any() else None,
        "final_bar": float(mean[idx[-1]]) if len(idx) else None,
        "final_sd_bar": float(sd[idx[-1]]) if len(idx) else None,
        "final_z": (float((mean[idx[-1]] - truth) / sd[idx[-1]])
                    if len(idx) and np.isfinite(mean[idx[-1]]) and sd[idx[-1]] > 0 else None),
        "unit": str(run.log.metadata.get("asset_id", run.name)),
        "expected_health": want, "final_health": health[idx[-1]] if len(idx) else "unknown",
        "time_to_right_s": t_right, "false_alarm_ticks": int(alarms),
        "trace": {"t_s": (t - onset)[::25].tolist(), "mean": mean[::25].tolist(), "sd": sd[::25].tolist(),
                  "label": label[::25].tolist(), "health": health[::25]},
    }


# ---------------------------------------------------------------------------------------
# information bound
# ---------------------------------------------------------------------------------------


def window_model(theta: np.ndarray, accel: float, obs: dict[str, Any], times: np.ndarray,
                 oil_c: float = 40.0) -> np.ndarray:
    """a2 of one reversal window (independent of dt-core: scipy ``solve_ivp``, RK45). With a
    calibrated damping law (``train.damping_law``, evaluated at ``oil_c``) ``c_ext`` and
    ``c_comp`` are its scales; otherwise slopes in N·s/m."""
    alpha, c_ext, c_comp, shift, c0 = theta
    m = obs["mount_mass_kg"]
    wn = 2 * np.pi * obs["mount_freq_hz"]
    k, c = m * wn ** 2, 2 * obs["mount_zeta"] * m * wn
    wc, vs = 2 * np.pi * obs["accel_bw_hz"], obs["friction_v_smooth_mps"]
    if law_calibrated(obs):
        from train.damping_law import law

        from scipy.interpolate import CubicSpline

        d = obs["damping_law"]
        # The law (the valve form solved for its force by bisection, the hinges a sum of
        # softplus terms) costs far more per call than the ODE step: tabulated once per window
        # (0.1 mm/s), a cubic spline per side (the sides meet at rest with their own slopes),
        # the law itself beyond.
        grid = np.arange(0.0, 0.6 + 1e-9, 1e-4)
        ext, comp = CubicSpline(grid, law(grid, oil_c, d)), CubicSpline(grid, law(-grid, oil_c, d))

        def raw(yd: float) -> float:
            if abs(yd) >= 0.6:
                return float(law(yd, oil_c, d))
            return float(ext(yd)) if yd >= 0 else float(comp(-yd))

        def damping(yd: float) -> float:
            return (c_ext if yd > 0 else c_comp) * raw(yd)
    else:
        def damping(yd: float) -> float:
            return (c_ext if yd > 0 else c_comp) * yd

    def force(s: float, vb: float) -> float:
        yd = accel * (s - shift) - vb
        return damping(yd) + alpha * np.tanh(yd / vs)

    def rhs(s: float, x: np.ndarray) -> list[float]:
        a = (force(s, x[1]) - k * x[0] - c * x[1]) / m
        return [x[1], a, wc * (a - x[2])]

    s0 = times[0] - 0.015
    yd0 = accel * (s0 - shift)
    if law_calibrated(obs):
        dslope = (damping(yd0 + 1e-3) - damping(yd0 - 1e-3)) / 2e-3
    else:
        dslope = c_ext if yd0 > 0 else c_comp
    slope = dslope + alpha / vs / np.cosh(yd0 / vs) ** 2
    # quasi-static start: the mount's particular solution under the force's ramp, with the
    # mount's damping and the damper's own (dt-core `ReversalModel::simulate`)
    g_dot = slope * accel
    x0 = [(force(s0, 0.0) - (c + slope) * g_dot / k) / k, g_dot / k, 0.0]
    # max_step: 16 steps through the friction's turn-over at 6 m/s² (v_s / |ÿ| = 0.8 ms); at
    # 2e-5 (before) the windows moved by 4e-8 m/s² at most and took twice as long
    sol = solve_ivp(rhs, (s0, times[-1]), x0, t_eval=times,
                    rtol=1e-9, atol=1e-12, max_step=5e-5)
    return sol.y[2] + c0


def systematic_floor(obs: dict[str, Any], p_bar: float) -> float:
    """The systematic part of the reported sd at a reading ``p_bar`` on a unit never baselined,
    bar: ``hypot(systematic_sd_bar, systematic_rel · p)``, the unit-to-unit spread of the
    observer's error (dt-core ``systematic_var``; see the module's doc for where it comes from)."""
    return float(np.hypot(obs["systematic_sd_bar"], obs.get("systematic_rel", 0.0) * p_bar))


def verdict_reach(obs: dict[str, Any]) -> dict[str, float]:
    """How far the SPEC §6a verdict can reach on a unit never baselined, however many reversals
    it reads: the reported sd never falls below ``systematic_floor``, so the 95 % interval lies
    below the fault threshold (``leak``) only for a reading below ``leak_below_bar`` and above
    the warn threshold (``ok``) only for one above ``ok_above_bar`` (``brentq`` on
    ``p ± Z95 · floor(p) = threshold``; no hysteresis: the first entry into either verdict)."""
    leak = brentq(lambda p: p + Z95 * systematic_floor(obs, p) - FAULT_BAR, FAULT_BAR - 100.0, FAULT_BAR)
    ok = (brentq(lambda p: p - Z95 * systematic_floor(obs, p) - WARN_BAR, WARN_BAR, WARN_BAR + 1000.0)
          if Z95 * obs.get("systematic_rel", 0.0) < 1.0 else float("inf"))
    return {"leak_below_bar": float(leak), "ok_above_bar": float(ok)}


def fisher_per_reversal(obs: dict[str, float], freq_hz: float, p_bar: float) -> float:
    """Fisher information on the charge (1/bar²) of one reversal, nuisances profiled out."""
    accel = STROKE_AMP_M * (2 * np.pi * freq_hz) ** 2
    times = np.arange(-obs["window_pre_s"], obs["window_post_s"] + 1e-9, 1e-3)
    offset, gain = warm_terms(obs, accel)  # the excitation's own model where it has one
    alpha = offset + gain * p_bar
    if law_calibrated(obs):  # the law at 40 °C, its per-side scales at 1
        theta = np.array([alpha, 1.0, 1.0, 0.0, -9.8])
        steps = np.array([0.01 * alpha, 0.01, 0.01, 2e-5, 0.01])
    else:  # linear slopes, N·s/m (typical fitted values)
        theta = np.array([alpha, 1910.0, 542.0, 0.0, -9.8])
        steps = np.array([0.01 * alpha, 20.0, 20.0, 2e-5, 0.01])
    jac = np.column_stack([(window_model(theta + e, accel, obs, times) - window_model(theta - e, accel, obs, times))
                           / (2 * e[i]) for i, e in enumerate(np.diag(steps))])
    sigma2 = ACC_NOISE_MPS2 ** 2 + ACC_LSB_MPS2 ** 2 / 12
    info = jac.T @ jac / sigma2
    i_alpha = info[0, 0] - info[0, 1:] @ np.linalg.solve(info[1:, 1:], info[1:, 0])
    return float(i_alpha * gain ** 2)


def gas_spring_fisher_per_s(obs: dict[str, float], freq_hz: float) -> float:
    """Fisher information per second (1/bar²/s) of the gas-spring force through the mount."""
    w = 2 * np.pi * freq_hz
    wn = 2 * np.pi * obs["mount_freq_hz"]
    dk_dbar = obs["polytropic_n"] * 1e5 * obs["a_rod_m2"] ** 2 / obs["v_gas_m3"]   # N/m per bar
    force_amp = dk_dbar * STROKE_AMP_M                                              # N per bar
    h = w ** 2 / (obs["mount_mass_kg"] * np.abs(wn ** 2 - w ** 2 + 2j * obs["mount_zeta"] * wn * w))
    a_amp = force_amp * h                                                           # m/s² per bar
    sigma2 = ACC_NOISE_MPS2 ** 2 + ACC_LSB_MPS2 ** 2 / 12
    return float(a_amp ** 2 / 2 * 1000.0 / sigma2)


# ---------------------------------------------------------------------------------------


def cmd_evaluate(args: argparse.Namespace) -> int:
    physics = read_json(args.physics)
    if not physics.get("observer"):
        raise SystemExit(f"{args.physics}: no `observer` section: run `python -m train.observer fit` first")
    if getattr(args, "fit_gain_floor", None) is not None:
        physics["observer"]["fit_gain_floor"] = float(args.fit_gain_floor)
    sets = {}
    for spec in args.sets:
        name, _, d = spec.partition("=")
        if not d:
            raise SystemExit(f"{spec!r}: a held-out set is NAME=DIR")
        if name in sets:
            # `--baseline` takes one SET=FILE: a second one after it is read as a set
            raise SystemExit(f"{spec!r}: set {name!r} is given twice (its other: {sets[name]}); a baseline is "
                             "`--baseline SET=FILE`, once per set")
        sets[name] = Path(d)
    baselines = {}
    for spec in args.baseline:
        name, _, f = spec.partition("=")
        if name not in sets or not f:
            raise SystemExit(f"--baseline {spec!r}: need SET=FILE with SET one of {', '.join(sets)}")
        baselines[name] = baseline_document(read_json(f), f)
    lines = evaluate(physics, sets, args.out, args.settle_s, args.jobs, baselines)
    print("\n".join(lines[:4 + len(sets)]))
    print(f"report: {args.out / 'observer.md'}")
    return 0


def baseline_document(doc: Any, source: str) -> dict[str, Any]:
    """``train.observer baseline``'s document, or the bare baseline the daemon and ``shocktwin replay``
    take (``charge_bar``, ``read_bar``, ``read_sd_bar``, …: no runs of its own to leave out), as the
    former; anything else is an error naming ``source`` and the field."""
    if not isinstance(doc, dict):
        raise ValueError(f"{source}: a unit baseline is a JSON object")
    if "observer_baseline" not in doc:
        doc = {"observer_baseline": doc, "runs": []}
    ob = doc["observer_baseline"]
    for key in ("charge_bar", "read_bar", "read_sd_bar"):
        v = ob.get(key) if isinstance(ob, dict) else None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ValueError(f"{source}: the unit baseline's `{key}` is {v!r}, not a finite number")
    runs = doc.get("runs", [])
    if not isinstance(runs, list) or not all(isinstance(r, dict) and isinstance(r.get("file"), str) for r in runs):
        raise ValueError(f"{source}: `runs` is a list of {{\"file\": NAME, …}}")
    return {**doc, "runs": runs}


def evaluate(physics: dict[str, Any], set_dirs: dict[str, Path], out: Path, settle_s: float,
             jobs: int, baselines: dict[str, dict[str, Any]] | None = None,
             observed: dict[str, Observed] | None = None,
             observed_baselined: dict[str, dict[str, Observed]] | None = None) -> list[str]:
    """Scores the observer of ``physics`` on every run of the held-out campaigns ``set_dirs``
    (name → directory), draws ``observer_bound.png`` and ``observer_runs.png`` into ``out`` and
    writes ``observer.md`` / ``observer.json`` there; returns the Markdown lines. A set named
    in ``baselines`` is scored with that unit baseline (``train.observer baseline``'s output),
    without the runs it was made from. ``observed`` (run path → its observer columns with
    ``physics``, computed already) spares recomputing them for the sets without a baseline;
    ``observed_baselined`` (set name → run path → its columns with that set's baseline) likewise
    for the baselined sets."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs = physics["observer"]
    settle = settle_s
    tasks = []
    for name, d in set_dirs.items():
        b = (baselines or {}).get(name)
        own = {r["file"] for r in b["runs"]} if b else set()
        set_physics = ({**physics, "observer": {**physics["observer"], "baseline": b["observer_baseline"]}}
                       if b else physics)
        for run in load_campaign(d).runs:
            if run.path.name in own:
                log.info("%s: %s made the unit baseline: not scored", name, run.path.name)
                continue
            given = (observed_baselined or {}).get(name, {}) if b else (observed or {})
            tasks.append((str(run.path), name, set_physics, settle, given.get(str(run.path))))
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        rows = list(progress(pool.map(score_run, tasks), total=len(tasks), desc="scoring", unit="run"))
    out.mkdir(parents=True, exist_ok=True)

    sets: dict[str, Any] = {}
    for name in dict.fromkeys(r["set"] for r in rows):
        rs = [r for r in rows if r["set"] == name]
        n = sum(r["ticks"] for r in rs)
        leak = [r for r in rs if r["truth_bar"] <= 3.0 and r["frequency_hz"] >= 2.0]
        nominal = [r for r in rs if r["expected_health"] == "ok"]
        sets[name] = {
            "runs": len(rs), "ticks": n,
            "rmse_bar": float(np.sqrt(sum(r["sq_err"] for r in rs) / n)) if n else None,
            "rmse_avg_bar": float(np.sqrt(sum(r["sq_err_avg"] for r in rs) / n)) if n else None,
            "coverage": sum(r["covered"] for r in rs) / n if n else None,
            "leak_runs_le3bar_ge2hz": len(leak),
            "leak_within_120s": sum(1 for r in leak if r["time_to_right_s"] is not None and r["time_to_right_s"] <= 120),
            "nominal_runs": len(nominal),
            "nominal_false_alarm_runs": sum(1 for r in nominal if r["false_alarm_ticks"] > 0),
            **unit_calibration(rs),
        }

    # the information bound
    t_grid = np.linspace(1.0, 600.0, 300)
    freqs = sorted({r["frequency_hz"] for r in rows})
    p_ref = 7.0
    bound: dict[str, Any] = {"p_ref_bar": p_ref, "freq_hz": {}, "gas_spring_sd_600s_bar": {},
                             "verdict_reach_without_baseline": verdict_reach(obs)}
    fig, ax = plt.subplots(figsize=(9, 5.5))
    floor = systematic_floor(obs, p_ref)
    for i, f in enumerate(freqs):
        ip = fisher_per_reversal(obs, f, p_ref)
        crlb = 1.0 / np.sqrt(2 * f * t_grid * ip)
        bound["freq_hz"][str(f)] = {"fisher_per_reversal": ip, "sd_60s_bar": float(1 / np.sqrt(2 * f * 60 * ip)),
                                    "bayes_floor_bar": floor}
        ax.loglog(t_grid, crlb, color=f"C{i}", lw=1, ls="--", label=f"CRLB friction channel, {f:g} Hz")
        ax.loglog(t_grid, np.hypot(crlb, floor), color=f"C{i}", lw=1.5, label=f"+ unit tolerance (Bayesian), {f:g} Hz")
        gs = 1.0 / np.sqrt(gas_spring_fisher_per_s(obs, f) * t_grid)
        bound["gas_spring_sd_600s_bar"][str(f)] = float(gs[-1])
        if i == 0:
            ax.loglog(t_grid, gs, color="k", lw=1, ls=":", label=f"CRLB gas-spring channel, {f:g} Hz")
        # achieved: RMS error across the held-out runs at this frequency, vs time since onset
        # (never baselined: the bound is a unit's without one)
        rs = [r for r in rows if r["frequency_hz"] == f and r["trace"]["t_s"] and r["set"] not in (baselines or {})]
        if rs:
            ts = np.array([5, 10, 20, 40, 60, 90, 120, 180, 240, 360, 480, 600], float)
            ach = []
            for tt in ts:
                e = [np.interp(tt, r["trace"]["t_s"], np.array(r["trace"]["mean"]) - np.array(r["trace"]["label"]))
                     for r in rs if r["trace"]["t_s"][-1] >= tt]
                ach.append(np.sqrt(np.mean(np.square(e))) if e else np.nan)
            ax.loglog(ts, ach, "o", color=f"C{i}", ms=5, label=f"observer RMSE (held out), {f:g} Hz")
    for target in (1.40, 0.67):
        ax.axhline(target, color="grey", lw=0.7)
        ax.text(1.1, target * 1.05, f"target {target} bar", fontsize=7, color="grey")
    ax.set_xlabel("time since excitation onset (s)")
    ax.set_ylabel("charge error sd / RMSE (bar)")
    ax.set_title(f"Information bound vs achieved, cheap suite (p = {p_ref:g} bar) — SIMULATED DATA", fontsize=10)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "observer_bound.png", dpi=110)
    plt.close(fig)

    # estimate with its interval for a leaking and a nominal run
    # the runs where the observer says most (narrowest final interval), fastest excitation first
    def most_said(r: dict[str, Any]) -> tuple[float, float, str]:
        sd = r["final_sd_bar"]
        return (round(sd, 1) if sd is not None else np.inf, -r["frequency_hz"], r["set"])
    # (every set baselined: its runs, rather than no plot)
    plain = [r for r in rows if r["set"] not in (baselines or {})] or rows
    leak_rows = sorted([r for r in plain if r["truth_bar"] <= 3.0], key=most_said)
    nom_rows = sorted([r for r in plain if r["truth_bar"] >= 9.0], key=most_said)
    # (no run low or high enough: the one the observer says most of)
    picks = (leak_rows[:1] + nom_rows[:1]) or sorted(plain, key=most_said)[:1]
    if picks:
        draw_runs(picks, out / "observer_runs.png")

    result = {"simulated_data": True, "settle_s": settle, "sets": sets, "bound": bound,
              "runs": [{k: v for k, v in r.items() if k not in ("trace", "sq_err", "sq_err_avg", "covered")} for r in rows]}
    (out / "observer.json").write_text(json.dumps(result, indent=2) + "\n")
    reach = bound["verdict_reach_without_baseline"]
    lines = [f"# Charge observer, cheap suite (potentiometer, accelerometers, thermocouples) — SIMULATED DATA\n",
             f"Scored ticks: excited, from {settle:g} s after excitation onset. Interval: central 95 %. "
             "A unit's runs share most of its error (its seal's tolerance), so the coverage of ticks counts "
             "units, not ticks: *final error ÷ sd* (the run's last estimate against the truth, in its own "
             "sd) has RMS 1 for an honest interval, and over that many units it lands in the range beside it "
             "95 % of the time (χ², one degree of freedom a unit).\n",
             "| set | runs | RMSE (bar) | RMSE 1 s avg (bar) | coverage | ≤3 bar & ≥2 Hz runs at `leak` ≤ 120 s | nominal runs with a false alarm | units | final error ÷ sd, RMS (honest interval: range) | runs whose final interval covers |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in sets.items():
        f2 = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
        cov = "–" if s["coverage"] is None else f"{100 * s['coverage']:.1f} %"
        lines.append(f"| {name} | {s['runs']} | {f2(s['rmse_bar'])} | {f2(s['rmse_avg_bar'])} | {cov} | "
                     f"{s['leak_within_120s']}/{s['leak_runs_le3bar_ge2hz']} | "
                     f"{s['nominal_false_alarm_runs']}/{s['nominal_runs']} | {s['units']} | "
                     f"{f2(s['final_z_rms'])} ({s['final_z_rms_calibrated'][0]:.2f}–{s['final_z_rms_calibrated'][1]:.2f}) | "
                     f"{s['final_covered_runs']}/{s['final_z_runs']} |")
    lines += ["", "| set | run | truth (bar) | final (bar) | final sd (bar) | RMSE (bar) | coverage | expected | final health | verdict right from (s) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g = lambda v, d=2: "–" if v is None else f"{v:.{d}f}"  # noqa: E731
        lines.append(f"| {r['set']} | {r['run']} | {r['truth_bar']:.2f} | {g(r['final_bar'])} | {g(r['final_sd_bar'])} | "
                     f"{g(r['rmse_bar'])} | {g(r['coverage'])} | {r['expected_health']} | {r['final_health']} | "
                     f"{g(r['time_to_right_s'], 0)} |")
    lines += ["", "Information bound (Cramér–Rao, friction channel, one unit, noise only) after 60 s of excitation:",
              ", ".join(f"{f} Hz: {v['sd_60s_bar']:.3f} bar" for f, v in bound["freq_hz"].items()),
              f"; unit-tolerance floor (Bayesian) {floor:.2f} bar at {p_ref:g} bar. Gas-spring channel after 600 s: "
              + ", ".join(f"{f} Hz: {v:.1f} bar" for f, v in bound["gas_spring_sd_600s_bar"].items()) + ".",
              "", "On a unit never baselined that floor stays in every interval, however many reversals are read: "
              f"the verdict can say `leak` only for a reading below {reach['leak_below_bar']:.2f} bar and `ok` only "
              f"for one above {reach['ok_above_bar']:.2f} bar (95 % interval, fault {FAULT_BAR:g} and warn "
              f"{WARN_BAR:g} bar). A unit baseline (`python -m train.observer baseline`) conditions it"
              + (f" (scored with one here: {', '.join(sorted(baselines))})." if baselines else "."),
              "", "![bound](observer_bound.png)", ""] + (["![runs](observer_runs.png)", ""] if picks else [])
    (out / "observer.md").write_text("\n".join(lines))
    return lines
