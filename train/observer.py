"""Calibrate and score the gas-charge observer (dt-core ``charge``) on simulated campaigns.

    python -m train.observer fit --campaign DIR --physics physics.json [--out physics.json]
    python -m train.observer evaluate --physics physics.json --out DIR NAME=DIR [NAME=DIR ...]
    python -m train.observer baseline --physics physics.json --charge-bar 12 RUN.mcap... --out unit.json
    python -m train.observer unit-spread --physics physics.json --unit 4=A.mcap 12=B.mcap --unit ... [--out P]
    python -m train.observer unit-spread --physics physics.json --campaign OTHER_UNITS_DIR [--out P]

``fit`` runs the observer's per-reversal window fit (``shocktwin.charge_reversals``, the
code the daemon runs) over every run of a labelled campaign and fits its measurement
model by robust least squares (scipy ``least_squares``, soft-L1 loss)::

    alpha = f0 + f_d sgn(a) + g |a| + (s + h |a|) p_g,   p_g = (p + p_atm) theta - p_atm

``theta`` from the reversal's gas temperature and extension (the datasheet's ``a_rod``,
``v_gas``). With the damping law, a cold term ``k_c x(T) |a|`` joins the offset
(``x = max(0, r(T)/r(T_c) − 1)``, the law's viscosity ratio; ``T_c`` the grid value that leaves
the calibration runs' cold bins least biased), and what it leaves in those bins is fitted as
``k_b x(T) |a|``, the bias the cold reversals share (dt-core carries it through the filter).
With each end of the stroke filtered apart, ``single_end_sd_bar`` is how far one end sits
from the charge in the warm bins; with ``--single-end``, while only one end has been read at
a calibrated excitation, the observer reports that end with this spread added (off by
default: docs/history.md, "One end alone").
The law's compression side is the twin-tube damper's base and piston valves working together and
its extension side a valve whose knee sits at a force (``--law-form twin-tube``, the default;
``valve``: the extension valve with hinges in compression, the default until the twenty-sixth
session; ``hinges``: knees at fixed velocities only; ``valves``: a single valve on either side:
docs/history.md, "Twenty-third session"), and
each window's two law scales get a Gaussian prior about 1 (``--scale-prior-sd``, 0.2 by
default; 0: free).
The per-reversal spread ``step_sd_n`` is the robust (MAD) spread of the residuals.
Each reversal's slope ``ÿ_r`` is read from the accelerometers, the rod end's own acceleration
(``--reversal-accel accelerometers``, the default; ``velocity-chord``: the Kalman velocity's
chord, biased by end and frequency: docs/history.md, "Twenty-fifth session").
Each excitation is validated leave one run out; one that fails with a gain of its own (``s + h |a|``:
with two runs, one is left to fit it on, at a single charge) is tried with one gain for every
excitation (``h = 0``, each its own offset) before it is dropped (docs/history.md, "Fifty-sixth
session"). An excitation of the campaign that this one model misses (the simulated dyno's 4 Hz) gets a
model of its own per end of the stroke, with a drift in the gas temperature, when it validates
leave one run out; its reversals are then read at that excitation only (``--no-own-excitations``:
skipped as before; docs/history.md, "4 Hz, read").
The systematic spread ``systematic_sd_bar`` is measured, not assumed: every
run's charge is estimated by the model fitted *without that run* (leave one run out), and
the RMS of those errors beyond their statistical part is kept; the unit-to-unit
tolerance of the friction (``--unit-tolerance-pct`` of ``f0`` and ``s``, a datasheet
figure) adds ``systematic_rel`` so that the interval stays honest on another unit.
``unit-spread`` then replaces both with the spread measured on other units at known charges
(``make demo`` and ``make study`` run it).
The mount, sensor filter and friction smoothing stay at the rig's documented values.

``evaluate`` runs the streaming pipeline (``shocktwin.features`` with the ``observer``
group) over held-out sets and reports, from excitation onset on: RMSE of the estimate
over ticks from ``--settle-s`` after onset (instantaneous and 1 s average), 95 %
interval coverage, the time until the SPEC §6a health verdict is right and stays right,
false alarms on nominal runs, the Cramér–Rao bound beside the achieved error, and plots.

``baseline`` reads one unit at a known charge (at installation or after a service, when the
charge was set or gauged): what the observer reads over the given runs and how sure it is
from their reversals alone, written as the unit's ``observer_baseline`` (dt-core
``UnitBaseline``) for ``shocktwin replay --observer-baseline`` and the daemon's
``[assets.<id>] observer_baseline``. The observer then conditions the unit's systematic
offset and gain on it (``evaluate --baseline SET=FILE`` scores with it). Runs at several
excitations give one reading per excitation, and a later run is corrected by the nearest.

The data are simulated (``shocktwin simulate``); the report and figures say so.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing.context import BaseContext
from pathlib import Path
from typing import Any, Iterator, NamedTuple, Sequence

import numpy as np
from scipy.optimize import least_squares, minimize, minimize_scalar
from scipy.stats import chi2 as chi2_dist

import shocktwin

from train.campaign import Run, load_campaign, main_wrapper, read_json
from train.damping_law import LAW_MIN_TEMP_SPAN_K, law_calibrated
from train.progress import progress
from train.fit_physics import rest_end_s

log = logging.getLogger("shocktwin.observer")

P_ATM_BAR = 1.01325
Z95 = 1.959963984540054
T_REF_K = 293.15
# An excitation whose leave-one-run-out charge RMS is worse than this is not used.
CLUSTER_MAX_LORO_BAR = 2.0
MIN_CLUSTER_REVERSALS = 20  # a run with fewer fitted reversals calibrates no excitation
SKIP_AFTER_ONSET_S = 5.0  # the actuator's ramp
WARN_BAR, FAULT_BAR, HYST_BAR, DWELL_S = 9.0, 5.0, 0.5, 3.0
DEFAULT_COLD_REF_C = 50.0  # dt-core charge::DEFAULT_COLD_REF_C
COLD_REF_GRID_C = (30.0, 40.0, 50.0, 60.0, 70.0)
COLD_BIN_K, COLD_BIN_MIN = 3.0, 10
# With a damping law, the window fit's per-side law scales get a prior about 1 of this sd: a
# unit's valves differ from the calibrated law by a few percent (the simulator's scatter is
# 3-5 %), and without it a window at the valve's knee can read the friction step against a
# law twice as stiff (docs/history.md, "The extension valve").
SCALE_PRIOR_SD = 0.2


def theta(rev: dict[str, np.ndarray], obs: dict[str, float]) -> np.ndarray:
    """Gas-pressure ratio per reversal, ``(T / 293.15 K) (v_gas / V) (V / (V + a_rod y))^n`` with
    ``V = v_gas − e (T − 20 °C)`` the gas volume the oil leaves as it expands (dt-core
    ``charge::gas_ratio``)."""
    t_c = rev["gas_temp_c"]
    v_ref = obs["v_gas_m3"] - obs.get("oil_expansion_m3_per_k", 0.0) * (t_c - 20.0)
    spring = (v_ref / (v_ref + obs["a_rod_m2"] * rev["extension_m"])) ** obs["polytropic_n"]
    return (t_c + 273.15) / T_REF_K * obs["v_gas_m3"] / v_ref * spring


def label_at(run: Run, t_s: np.ndarray) -> np.ndarray:
    """The run's charge label (bar gauge at 20 °C, SPEC §1) at every time."""
    if run.label_bar is None:
        raise ValueError(f"{run.path}: no charge label: the observer is calibrated on labelled runs")
    return np.full(len(t_s), float(run.label_bar))


def _reversals(args: tuple[str, dict[str, Any]]) -> dict[str, Any]:
    path, params = args
    rev = shocktwin.charge_reversals(path, params)
    return {k: (np.asarray(v) if isinstance(v, np.ndarray) else v) for k, v in rev.items()}


def reversals(runs: Sequence[Run], params: dict[str, Any], jobs: int,
              mp_context: BaseContext | None = None) -> list[dict[str, Any]]:
    """Per-run reversal fits, with each reversal's label and the run's excitation onset
    (``mp_context``: the worker processes' start method, the platform's default if None)."""
    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp_context) as pool:
        revs = list(progress(pool.map(_reversals, [(str(r.path), params) for r in runs]), total=len(runs),
                             desc="reversal fits", unit="run"))
    out = []
    for run, rev in zip(runs, revs):
        onset = rest_end_s(run)
        keep = rev["t_s"] > onset + SKIP_AFTER_ONSET_S
        rev = {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in rev.items()}
        rev["label_bar"] = label_at(run, rev["t_s"])
        rev["run"] = run.name
        rev["truth_bar"] = float(run.label_bar)  # label_at checked it exists
        out.append(rev)
    return out


def rod_accel_scale(runs: Sequence[Run], physics: dict[str, Any], obs: dict[str, Any], jobs: int,
                    mp_context: BaseContext | None = None) -> tuple[float | None, list[float]]:
    """The accelerometers' scale on the campaign's rig, ``k_cal`` (dt-core
    ``ObserverParams::rod_accel_scale``): the median over its runs of each run's scale against the
    potentiometer (dt-core ``ChargeObserver::rod_accel_scale``), and the runs' scales (NaN: too few
    reversals). Every reversal is spared its window fit (``fit_gain_floor`` 0.99): the scale does not
    need it, and the pass takes about a second a run. None when no run has a scale."""
    params = {**physics, "observer": {**obs, "fit_gain_floor": 0.99, "rod_accel_scale": None}}
    scales = [float(rev["rod_accel_scale"]) for rev in reversals(runs, params, jobs, mp_context)]
    finite = [k for k in scales if np.isfinite(k)]
    return (float(np.median(finite)) if finite else None), scales


def cold_excess(rev: dict[str, np.ndarray], obs: dict[str, Any]) -> np.ndarray:
    """``x(T) |ÿ_r|`` per reversal, the regressor of the cold term (dt-core
    ``ObserverParams::cold_excess``): ``x = max(0, r(T)/r(T_c) − 1)``, ``r`` the damping law's
    viscosity ratio; zero without a calibrated law."""
    a = np.abs(rev["accel_mps2"])
    if not law_calibrated(obs):
        return np.zeros_like(a)
    beta = obs["damping_law"]["beta_per_k"]
    x = np.exp(-beta * (rev["gas_temp_c"] - obs.get("cold_ref_c", DEFAULT_COLD_REF_C))) - 1.0
    return np.maximum(x, 0.0) * a


def design(rev: dict[str, np.ndarray], p_bar: np.ndarray, obs: dict[str, Any]) -> np.ndarray:
    th = theta(rev, obs)
    pg = (p_bar + P_ATM_BAR) * th - P_ATM_BAR
    a = rev["accel_mps2"]
    return np.column_stack([np.ones_like(a), np.sign(a), np.abs(a), pg, np.abs(a) * pg,
                            cold_excess(rev, obs)])


def coef_of(o: dict[str, Any]) -> np.ndarray:
    """The measurement model's coefficients in ``design``'s column order."""
    return np.array([o["step_offset_n"], o["step_dir_n"], o["step_per_accel_ns2pm"], o["step_per_bar_n"],
                     o["step_per_bar_accel"], o.get("cold_per_accel_ns2pm", 0.0)])


def fit_measurement(revs: Sequence[dict[str, Any]], obs: dict[str, Any],
                    with_accel: bool = True, common_gain: bool = False) -> tuple[np.ndarray, float]:
    """Robust LS of ``alpha`` on ``[1, sgn a, |a|, p_g, |a| p_g, x(T) |a|]`` (without the ``|a|``
    terms, which one excitation cannot identify, when not ``with_accel``; without ``|a| p_g``, one
    gain for every excitation, when ``common_gain``; without the cold term when no reversal is
    colder than ``cold_ref_c``); returns the six coefficients and the MAD spread."""
    x = np.vstack([design(r, r["label_bar"], obs) for r in revs])
    y = np.concatenate([r["alpha_n"] for r in revs])
    cols = ([0, 1, 2, 3] if common_gain else [0, 1, 2, 3, 4]) if with_accel else [0, 1, 3]
    if np.count_nonzero(x[:, 5]) >= MIN_CLUSTER_REVERSALS:
        cols.append(5)
    sol, mad = robust_lstsq(x[:, cols], y)
    coef = np.zeros(6)
    coef[cols] = sol
    return coef, mad


def robust_lstsq(xs: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """``y ≈ xs c`` by soft-L1 least squares (scale: the MAD of the plain fit's residuals), from
    the plain fit; returns ``c`` and the MAD spread of its residuals."""
    c0, *_ = np.linalg.lstsq(xs, y, rcond=None)
    res0 = y - xs @ c0
    scale = max(1.4826 * float(np.median(np.abs(res0 - np.median(res0)))), 1e-3)
    sol = least_squares(lambda c: xs @ c - y, c0, loss="soft_l1", f_scale=scale)
    res = y - xs @ sol.x
    return sol.x, 1.4826 * float(np.median(np.abs(res - np.median(res))))


def reading_gain(rev: dict[str, np.ndarray], coef: np.ndarray, obs: dict[str, Any]) -> np.ndarray:
    """``b_r`` (N/bar) per reversal: how much ``alpha`` moves per bar of charge."""
    return (coef[3] + coef[4] * np.abs(rev["accel_mps2"])) * theta(rev, obs)


def batch_charge(alpha: np.ndarray, a: np.ndarray, b: np.ndarray, sd_n: float) -> tuple[float, float]:
    """Weighted LS charge from readings ``alpha = a + b p`` (the observer with no random walk
    and a flat prior), with a 3-sigma-clipped second pass; (estimate, statistical sd), NaN
    under three readings."""
    keep = np.ones(len(a), bool)
    p = np.nan
    for _ in range(2):
        if keep.sum() < 3:
            return np.nan, np.inf
        p = float(np.sum(b[keep] * (alpha[keep] - a[keep])) / np.sum(b[keep] ** 2))
        keep = np.abs(alpha - a - b * p) < 3 * sd_n
    return p, sd_n / float(np.sqrt(np.sum(b[keep] ** 2)))


def charge_from(rev: dict[str, np.ndarray], coef: np.ndarray, sd_n: float, obs: dict[str, float]) -> tuple[float, float]:
    """Batch charge of one run under the shared measurement model (``batch_charge``)."""
    th = theta(rev, obs)
    acc = np.abs(rev["accel_mps2"])
    gain = coef[3] + coef[4] * acc
    a = (coef[0] + coef[1] * np.sign(rev["accel_mps2"]) + coef[2] * acc + coef[5] * cold_excess(rev, obs)
         + gain * P_ATM_BAR * (th - 1.0))
    return batch_charge(rev["alpha_n"], a, reading_gain(rev, coef, obs), sd_n)


def accel_clusters(revs: Sequence[dict[str, Any]], rel: float) -> list[tuple[float, float]]:
    """The excitations the campaign calibrates, each as ``(|ÿ_r|, spacing)``: per run, the
    median ``|ÿ_r|`` and the median spacing (time since the previous reversal, the half
    period) of its fitted reversals; runs within ``rel`` of each other in ``|ÿ_r|`` merged
    (reversal-weighted means). Up to four, most reversals first, sorted by ``|ÿ_r|``."""
    runs = sorted((float(np.median(np.abs(r["accel_mps2"]))), float(np.nanmedian(r["spacing_s"])),
                   len(r["accel_mps2"]))
                  for r in revs if len(r["accel_mps2"]) >= MIN_CLUSTER_REVERSALS)
    clusters: list[list[float]] = []  # [sum of a·n, sum of spacing·n, n]
    for a, h, n in runs:
        if clusters and abs(a - clusters[-1][0] / clusters[-1][2]) <= rel * a:
            clusters[-1][0] += a * n
            clusters[-1][1] += h * n
            clusters[-1][2] += n
        else:
            clusters.append([a * n, h * n, float(n)])
    if len(clusters) > 4:
        log.warning("%d reversal-acceleration clusters; the observer keeps the 4 with most reversals",
                    len(clusters))
    best = sorted(clusters, key=lambda c: -c[2])[:4]
    return sorted((c[0] / c[2], c[1] / c[2]) for c in best)


def in_clusters(rev: dict[str, np.ndarray], clusters: Sequence[tuple[float, float]], rel: float,
                spacing_rel: float) -> np.ndarray:
    """Which reversals the observer takes (dt-core ``ObserverParams::calibrated_at``): within
    ``rel`` of a cluster's ``|ÿ_r|`` and within ``spacing_rel`` of its spacing (NaN: none)."""
    a = np.abs(rev["accel_mps2"])[:, None]
    h = np.asarray(rev["spacing_s"])[:, None]
    acc = np.array([c[0] for c in clusters])
    sp = np.array([c[1] for c in clusters])
    with np.errstate(invalid="ignore"):
        ok = (np.abs(a - acc) <= rel * acc) & (np.abs(h - sp) <= spacing_rel * sp)
    return ok.any(axis=1)


def calibrate(revs: Sequence[dict[str, Any]], obs: dict[str, Any], unit_tol_pct: float,
              leave_out: Sequence[float] = ()) -> dict[str, Any]:
    """The measurement model, validated run by run: leave-one-run-out charge errors per
    excitation (reversal-acceleration cluster); an excitation whose LORO RMS exceeds
    ``CLUSTER_MAX_LORO_BAR`` is dropped (the observer skips its reversals) and the rest refitted.
    ``leave_out``: excitations (``|a|``, m/s², matched within ``accel_cluster_rel``: a centre
    moves a little with the reversals it is found on) kept off the shared model from the start
    (``add_own_excitations`` may give them one of their own)."""
    clusters = [c for c in accel_clusters(revs, obs["accel_cluster_rel"])
                if not any(abs(c[0] - x) <= obs["accel_cluster_rel"] * x for x in leave_out)]
    if not clusters:
        raise ValueError(f"no run has {MIN_CLUSTER_REVERSALS} fitted reversals: nothing to calibrate the observer on")
    rel, spacing_rel = obs["accel_cluster_rel"], obs["spacing_rel"]
    spread = spacing_spread(revs, clusters, rel)
    if spread > spacing_rel:
        log.warning("calibration reversals' spacing spreads %.1f %% from their excitation's, beyond the "
                    "observer's ±%.0f %%: some calibration reversals will be skipped", 100 * spread,
                    100 * spacing_rel)
    dropped: list[dict[str, float]] = []
    common = False
    while True:
        centres = np.array([c[0] for c in clusters])

        def inside(r: dict[str, Any]) -> dict[str, Any]:  # the observer skips the others
            keep = in_clusters(r, clusters, rel, spacing_rel)
            return {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in r.items()}

        used = [inside(r) for r in revs]
        with_accel = len(clusters) > 1
        coef, sd_n, loro, per_cluster = validated(used, obs, centres, with_accel, common_gain=False)
        worst = int(np.argmax(per_cluster))
        if len(clusters) == 1 or per_cluster[worst] <= CLUSTER_MAX_LORO_BAR:
            break
        # An excitation with few runs cannot validate a gain of its own (two runs: one left to
        # fit it on, at one charge); one gain for every excitation, each its own offset, may.
        c_g = validated(used, obs, centres, with_accel, common_gain=True)
        if max(c_g[3]) <= CLUSTER_MAX_LORO_BAR:
            print(f"one gain for every excitation (|a| = {', '.join(f'{c:.2f}' for c in centres)} m/s²): "
                  f"leave-one-run-out RMS {', '.join(f'{v:.2f}' for v in c_g[3])} bar; with a gain each, "
                  f"{', '.join(f'{v:.2f}' for v in per_cluster)}")
            coef, sd_n, loro, per_cluster = c_g
            common = True
            break
        log.warning("one gain for every excitation (|a| = %s m/s²) does not validate either: leave-one-run-out "
                    "RMS %s bar", ", ".join(f"{c:.2f}" for c in centres), ", ".join(f"{v:.1f}" for v in c_g[3]))
        log.warning("reversals at |a| = %.2f m/s², %.3f s apart do not calibrate (leave-one-run-out RMS %.1f bar "
                    "> %.1f): the observer will skip them", *clusters[worst], per_cluster[worst], CLUSTER_MAX_LORO_BAR)
        dropped.append({"accel_mps2": clusters[worst][0], "spacing_s": clusters[worst][1],
                        "loro_rms_bar": per_cluster[worst]})
        clusters.pop(worst)
    err = np.array([row["error_bar"] for row in loro])
    stat = np.array([row["stat_sd_bar"] for row in loro])
    ok = np.isfinite(err)
    if not ok.any():
        raise ValueError("no run gave a charge estimate: the observer found no usable reversals")
    sys_sd = float(np.sqrt(max(np.mean(err[ok] ** 2) - np.mean(stat[ok] ** 2), 0.0)))
    for row in loro:  # JSON has no NaN or infinity: a run without usable reversals says null
        row.update({k: None for k, v in row.items() if isinstance(v, float) and not np.isfinite(v)})
    tol = unit_tol_pct / 100.0
    out = dict(obs)
    out["accel_clusters_mps2"] = [c[0] for c in clusters] + [0.0] * (4 - len(clusters))
    out["reversal_spacings_s"] = [c[1] for c in clusters] + [0.0] * (4 - len(clusters))
    out.update(step_offset_n=float(coef[0]), step_dir_n=float(coef[1]), step_per_accel_ns2pm=float(coef[2]),
               step_per_bar_n=float(coef[3]), step_per_bar_accel=float(coef[4]), step_sd_n=float(sd_n),
               cold_per_accel_ns2pm=float(coef[5]),
               systematic_sd_bar=float(np.hypot(sys_sd, tol * coef[0] / coef[3])))
    out["systematic_rel"] = tol
    out["cold_bias_sd_ns2pm"] = cold_bias_sd(used, out)
    out["single_end_sd_bar"] = single_end_sd(used, out)
    return {"observer": out, "loro": loro, "loro_rms_bar": float(np.sqrt(np.mean(err[ok] ** 2))),
            "loro_rms_per_cluster_bar": [v if np.isfinite(v) else None for v in per_cluster], "dropped_clusters": dropped,
            "systematic_loro_bar": sys_sd, "spacing_spread_rel": spread, "common_gain": common}


def validated(used: Sequence[dict[str, Any]], obs: dict[str, Any], centres: np.ndarray, with_accel: bool,
              common_gain: bool) -> tuple[np.ndarray, float, list[dict[str, Any]], list[float]]:
    """``fit_measurement`` on ``used`` (each run's reversals at the excitations ``centres``), and
    each run's charge read by the model fitted without it: the coefficients, their MAD spread,
    the leave-one-run-out rows and their RMS per excitation (infinite for one no run read)."""
    coef, sd_n = fit_measurement(used, obs, with_accel, common_gain)
    loro = []
    for i, r in enumerate(used):
        others = [q for j, q in enumerate(used) if j != i]
        c_i, sd_i = fit_measurement(others, obs, with_accel, common_gain)
        p_hat, p_sd = charge_from(r, c_i, sd_i, obs)
        a_med = float(np.median(np.abs(r["accel_mps2"]))) if len(r["accel_mps2"]) else np.nan
        loro.append({"run": r["run"], "truth_bar": r["truth_bar"], "estimate_bar": p_hat, "stat_sd_bar": p_sd,
                     "error_bar": p_hat - r["truth_bar"], "reversals": int(len(r["alpha_n"])),
                     "accel_mps2": a_med,
                     "cluster": int(np.argmin(np.abs(centres - a_med))) if np.isfinite(a_med) else -1})
    per_cluster = []
    for k in range(len(centres)):
        e = np.array([row["error_bar"] for row in loro if row["cluster"] == k])
        e = e[np.isfinite(e)]
        per_cluster.append(float(np.sqrt(np.mean(e ** 2))) if len(e) else np.inf)
    return coef, sd_n, loro, per_cluster


def _end_bins(rev: dict[str, np.ndarray], keep: np.ndarray) -> Iterator[np.ndarray]:
    """The masks of one run's bins: end of the stroke × ``COLD_BIN_K`` band of gas
    temperature, among the ``keep`` reversals, ``COLD_BIN_MIN`` reversals or more."""
    band = np.floor(rev["gas_temp_c"] / COLD_BIN_K)
    for end in (1.0, -1.0):
        for k in np.unique(band):
            m = keep & (band == k) & (np.sign(rev["accel_mps2"]) == end)
            if m.sum() >= COLD_BIN_MIN:
                yield m


def _cold_bins(revs: Sequence[dict[str, Any]], obs: dict[str, Any]) -> np.ndarray:
    """Per run, end of the stroke and ``COLD_BIN_K`` band of gas temperature (``COLD_BIN_MIN``
    reversals or more): ``[mean residual of alpha at the label (N), mean x(T) |a|]``."""
    coef = coef_of(obs)
    rows = []
    for r in revs:
        if not len(r["alpha_n"]):
            continue
        res = r["alpha_n"] - design(r, r["label_bar"], obs) @ coef
        d = cold_excess(r, obs)
        for m in _end_bins(r, np.ones(len(res), bool)):
            rows.append((float(np.mean(res[m])), float(np.mean(d[m]))))
    return np.array(rows).reshape(-1, 2)


def cold_bias_sd(revs: Sequence[dict[str, Any]], obs: dict[str, Any]) -> float:
    """``k_b`` (N·s²/m): what the cold term leaves in the calibration's cold bins, scaled to
    ``x(T) |a|`` — the least-squares fit of their squared mean residual on ``(x |a|)²``
    (through 0: warm bins are the systematic sd's). A bias shared by a bin's reversals, not
    their noise: the observer carries it through the filter's weights (module docs)."""
    if not law_calibrated(obs):
        return 0.0
    bins = _cold_bins(revs, obs)
    cold = bins[bins[:, 1] > 0]
    if len(cold) < 2:
        return 0.0
    return float(np.sqrt(np.sum(cold[:, 0] ** 2 * cold[:, 1] ** 2) / np.sum(cold[:, 1] ** 4)))


def single_end_sd(revs: Sequence[dict[str, Any]], obs: dict[str, Any]) -> float:
    """``s_e`` (bar): how far one end of the stroke, read alone, sits from the charge once the
    cold term has done its part — the RMS, over the calibration's warm bins (run × end ×
    ``COLD_BIN_K`` band of gas temperature, ``COLD_BIN_MIN`` reversals or more, the cold term
    zero), of the bin's mean charge error, less the bins' own noise. The cold bins' excess is
    the cold bias's (``cold_bias_sd``), carried apart. dt-core ``ObserverParams::single_end_sd_bar``."""
    coef, sd_n = coef_of(obs), float(obs["step_sd_n"])
    err2, noise2 = [], []
    for r in revs:
        if not len(r["alpha_n"]):
            continue
        b = reading_gain(r, coef, obs)
        err = (r["alpha_n"] - design(r, r["label_bar"], obs) @ coef) / b
        for m in _end_bins(r, cold_excess(r, obs) <= 0.0):
            err2.append(float(np.mean(err[m])) ** 2)
            noise2.append(float(np.mean((sd_n / b[m]) ** 2)) / int(m.sum()))
    if not err2:
        return 0.0
    return float(np.sqrt(max(np.mean(err2) - np.mean(noise2), 0.0)))


def cold_reference(revs: Sequence[dict[str, Any]], obs: dict[str, Any]) -> float:
    """``T_c`` (°C), the oil temperature above which the cold term vanishes: of
    ``COLD_REF_GRID_C``, the one whose fitted measurement model leaves the smallest RMS of the
    per-bin mean residuals (``_cold_bins``) on the calibration runs."""
    best = (np.inf, DEFAULT_COLD_REF_C)
    for t_c in COLD_REF_GRID_C:
        o = {**obs, "cold_ref_c": t_c}
        coef, _ = fit_measurement(revs, o)
        o.update(step_offset_n=coef[0], step_dir_n=coef[1], step_per_accel_ns2pm=coef[2], step_per_bar_n=coef[3],
                 step_per_bar_accel=coef[4], cold_per_accel_ns2pm=coef[5])
        bins = _cold_bins(revs, o)
        rms = float(np.sqrt(np.mean(bins[:, 0] ** 2))) if len(bins) else np.inf
        log.info("cold term at T_c = %.0f °C: per-bin mean residual RMS %.2f N", t_c, rms)
        best = min(best, (rms, t_c))
    return best[1]


def spacing_spread(revs: Sequence[dict[str, Any]], clusters: Sequence[tuple[float, float]], rel: float) -> float:
    """How far the calibration's own reversals spread in spacing: the 99th percentile of
    ``|spacing / its cluster's spacing − 1|`` over the reversals within ``rel`` of a cluster's
    ``|ÿ_r|``, from onset + ``SKIP_AFTER_ONSET_S`` on (the observer's ``spacing_rel`` must
    exceed it, or it would skip reversals it was calibrated on)."""
    dev = []
    for r in revs:
        a = np.abs(r["accel_mps2"])
        for c_a, c_h in clusters:
            m = (np.abs(a - c_a) <= rel * c_a) & np.isfinite(r["spacing_s"])
            dev.append(np.abs(r["spacing_s"][m] / c_h - 1.0))
    d = np.concatenate(dev) if dev else np.array([])
    return float(np.percentile(d, 99)) if len(d) else 0.0


RESIDUAL_BIN_MPS2 = 0.05      # bins of the window residual for choosing the law's cut
RESIDUAL_MAX_BIAS_BAR = 1.5   # a bin whose median charge error is larger starts the cut
RESIDUAL_MIN_CUT_MPS2 = 0.15  # never cut below this (1 Hz windows fit at 0.07)


def residual_cut(revs: Sequence[dict[str, Any]], cal: dict[str, Any]) -> float:
    """The largest window residual (m/s²) below which the calibration's reversals carry an
    unbiased charge: windows in bins of ``RESIDUAL_BIN_MPS2``, from the best fitting up;
    the cut is the lower edge of the first bin (with 20 reversals or more) whose median
    charge error under ``cal``'s measurement model exceeds ``RESIDUAL_MAX_BIAS_BAR``. With
    the damping law the windows the law misses (the simulated dyno's cold 2 Hz reversals)
    read the friction low by several bar; with linear slopes every 2 Hz window does."""
    o = cal["observer"]
    coef = coef_of(o)
    res = np.concatenate([r["residual_mps2"] for r in revs])
    err = np.concatenate([(r["alpha_n"] - design(r, r["label_bar"], o) @ coef)
                          / (coef[3] + coef[4] * np.abs(r["accel_mps2"])) for r in revs])
    edge = RESIDUAL_MIN_CUT_MPS2
    while edge < o["max_residual_mps2"]:
        m = (res >= edge) & (res < edge + RESIDUAL_BIN_MPS2)
        if m.sum() >= 20 and abs(float(np.median(err[m]))) > RESIDUAL_MAX_BIAS_BAR:
            return round(float(edge), 3)
        edge += RESIDUAL_BIN_MPS2
    return float(o["max_residual_mps2"])


# Windows of an excitation the shared model misses are fitted up to this residual for a model of
# their own (the simulated dyno's 4 Hz windows fit at 0.5-1.0 m/s², against 0.07 at 1 Hz).
OWN_MAX_RESIDUAL_MPS2 = 1.5
OWN_CUT_MARGIN = 1.25


def cold_x(rev: dict[str, np.ndarray], obs: dict[str, Any]) -> np.ndarray:
    """``x(T)`` per reversal: the viscosity excess alone (``cold_excess`` without ``|a|``)."""
    a = np.abs(rev["accel_mps2"])
    return np.divide(cold_excess(rev, obs), a, out=np.zeros_like(a), where=a > 0)


def end_terms(rev: dict[str, np.ndarray], coef: np.ndarray, obs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``(a_r, b_r)`` per reversal under one end's own model ``α = A + C x(T) + D (T − T_c) + S p_g``
    (``coef`` = ``[A, S, C, D]``; dt-core ``ExcitationModel``)."""
    th = theta(rev, obs)
    a = (coef[0] + coef[2] * cold_x(rev, obs) + coef[3] * (rev["gas_temp_c"] - obs["cold_ref_c"])
         + coef[1] * P_ATM_BAR * (th - 1.0))
    return a, coef[1] * th


def fit_end(revs: Sequence[dict[str, Any]], obs: dict[str, Any]) -> tuple[np.ndarray, float]:
    """Robust LS of ``alpha`` on ``[1, p_g, x(T), T − T_c]`` over one end's reversals of one
    excitation (the cold column zero when fewer than ``MIN_CLUSTER_REVERSALS`` reversals are
    cold); returns ``[A, S, C, D]`` and the MAD spread."""
    pg = np.concatenate([(r["label_bar"] + P_ATM_BAR) * theta(r, obs) - P_ATM_BAR for r in revs])
    x = np.concatenate([cold_x(r, obs) for r in revs])
    t = np.concatenate([r["gas_temp_c"] - obs["cold_ref_c"] for r in revs])
    y = np.concatenate([r["alpha_n"] for r in revs])
    has_x = np.count_nonzero(x) >= MIN_CLUSTER_REVERSALS
    cols = [0, 1, 2, 3] if has_x else [0, 1, 3]
    sol, mad = robust_lstsq(np.column_stack([np.ones_like(y), pg, x, t])[:, cols], y)
    coef = np.zeros(4)
    coef[cols] = sol
    return coef, mad


def _end_of(rev: dict[str, Any], end: int) -> dict[str, Any]:
    """The reversals of one end of the stroke (``end`` the sign of ``ÿ_r``)."""
    m = np.sign(rev["accel_mps2"]) == end
    return {k: (v[m] if isinstance(v, np.ndarray) else v) for k, v in rev.items()}


def own_excitation(revs: Sequence[dict[str, Any]], obs: dict[str, Any]) -> dict[str, Any] | None:
    """A measurement model of its own for one excitation (``revs``: its runs' reversals, windows
    up to ``OWN_MAX_RESIDUAL_MPS2``), per end of the stroke (``fit_end``), validated leave one
    run out (each end's charge, then their average, as the observer's ``stroke_ends`` reports
    it). Its residual cut is ``OWN_CUT_MARGIN`` × the 99th percentile of its windows' residuals
    (a held-out window must fit about as well as the calibration's): at 4 Hz on the simulated
    dyno the residual grows with the heat while the reading stays unbiased, so the cut of the
    shared model (the first residual bin whose charge is biased) does not apply. None when an
    end has too few reversals."""
    def fit(rs: Sequence[dict[str, Any]]) -> dict[int, tuple[np.ndarray, float]] | None:
        out = {}
        for e in (1, -1):
            ends = [_end_of(r, e) for r in rs]
            if sum(len(r["alpha_n"]) for r in ends) < MIN_CLUSTER_REVERSALS:
                return None
            out[e] = fit_end([r for r in ends if len(r["alpha_n"])], obs)
        return out

    res = np.concatenate([r["residual_mps2"] for r in revs])
    cut = round(min(OWN_CUT_MARGIN * float(np.percentile(res, 99)), OWN_MAX_RESIDUAL_MPS2), 3) if len(res) else 0.0
    models = fit(revs)
    if models is None:
        return None
    loro = []
    for i, r in enumerate(revs):
        others = fit([q for j, q in enumerate(revs) if j != i])
        est = []
        for e in (1, -1):
            rr = _end_of(r, e)
            if others is None or len(rr["alpha_n"]) < 3:
                continue
            a, b = end_terms(rr, others[e][0], obs)
            p, sd = batch_charge(rr["alpha_n"], a, b, others[e][1])
            if np.isfinite(p):
                est.append((p, sd))
        p_hat = float(np.mean([p for p, _ in est])) if est else np.nan
        p_sd = float(np.sqrt(sum(sd ** 2 for _, sd in est)) / len(est)) if est else np.inf
        loro.append({"run": r["run"], "truth_bar": r["truth_bar"], "estimate_bar": p_hat, "stat_sd_bar": p_sd,
                     "error_bar": p_hat - r["truth_bar"], "reversals": int(len(r["alpha_n"])),
                     "accel_mps2": float(np.median(np.abs(r["accel_mps2"]))) if len(r["alpha_n"]) else np.nan})
    err = np.array([row["error_bar"] for row in loro])
    ok = np.isfinite(err)
    return {"models": models, "max_residual_mps2": cut, "loro": loro, "silent_below_bar": silent_bounds(revs),
            "loro_rms_bar": float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else np.inf}


SILENT_WINDOWS = 40  # dt-core charge::SILENT_WINDOWS
SILENT_SHARE = 0.1   # an end that fits under this share of the other end's windows is silent


def silent_bounds(revs: Sequence[dict[str, Any]]) -> dict[int, float]:
    """Per end of the stroke, the charge below which that end falls silent at this excitation
    (dt-core ``ExcitationModel::silent_below_bar``): on a run whose other end fits
    ``SILENT_WINDOWS`` windows or more, the end is silent when it fits under ``SILENT_SHARE`` of
    them. The bound is the lowest charge at which the end fits (half the other end's windows or
    more) above every charge at which it was silent; 0 (no bound) when it was never silent, or
    never fit above."""
    out = {}
    for e in (1, -1):
        silent, fits = [], []
        for r in revs:
            n_e = int(np.sum(np.sign(r["accel_mps2"]) == e))
            n_o = int(np.sum(np.sign(r["accel_mps2"]) == -e))
            if n_o >= SILENT_WINDOWS and n_e < SILENT_SHARE * n_o:
                silent.append(r["truth_bar"])
            elif n_o and n_e >= 0.5 * n_o:
                fits.append(r["truth_bar"])
        above = [p for p in fits if silent and p > max(silent)]
        out[e] = float(min(above)) if above else 0.0
    return out


def warm_terms(obs: dict[str, Any], accel: float) -> tuple[float, float]:
    """``(offset N, gain N/bar)`` of the measurement model at velocity slope ``accel`` with warm oil
    at ``T_c`` (no cold term, no drift), averaged over the two ends of the stroke: dt-core
    ``ObserverParams::terms`` (the table's own excitation within its band, else the shared
    excitations' line, extrapolated at its ends, or held above the fastest with ``held_sd_bar``),
    or the one line without a table."""
    a = abs(accel)
    x = obs.get("excitations")
    if not x:
        return obs["step_offset_n"] + obs["step_per_accel_ns2pm"] * a, obs["step_per_bar_n"] + obs["step_per_bar_accel"] * a
    clusters, rel = obs["accel_clusters_mps2"], obs["accel_cluster_rel"]
    for k, c in enumerate(clusters):
        if x["own"][k] and c > 0 and abs(a - c) <= rel * c:
            return float(np.mean(x["offset_n"][k])), float(np.mean(x["per_bar_n"][k]))
    ks = sorted((k for k, c in enumerate(clusters) if c > 0 and not x["own"][k]), key=lambda k: clusters[k])
    if len(ks) == 1:
        lo = hi = ks[0]
        w = 0.0
    else:
        seg = next((i for i in range(len(ks) - 1) if a <= clusters[ks[i + 1]]), len(ks) - 2)
        lo, hi = ks[seg], ks[seg + 1]
        w = (a - clusters[lo]) / (clusters[hi] - clusters[lo])
        if obs.get("held_sd_bar", 0.0) > 0 and a > clusters[hi] * (1 + rel):
            w = min(w, 1.0)  # held at the line's fastest excitation

    def lerp(v: list[list[float]]) -> float:
        return float(np.mean(v[lo]) + w * (np.mean(v[hi]) - np.mean(v[lo])))
    return lerp(x["offset_n"]), lerp(x["per_bar_n"])


def excitation_table(o: dict[str, Any], own: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """dt-core ``ExcitationModel`` for ``o``'s clusters: the shared model's coefficients at each
    of its excitations (the same model, written per excitation and end), and ``own``'s models
    (by cluster index) at theirs."""
    table = {k: [[0.0, 0.0] for _ in range(4)]
             for k in ("offset_n", "per_bar_n", "cold_n", "per_kelvin_n", "sd_n", "silent_below_bar")}
    table["max_residual_mps2"] = [0.0] * 4
    table["own"] = [k in own for k in range(4)]
    for k, acc in enumerate(o["accel_clusters_mps2"]):
        if acc <= 0:
            continue
        table["max_residual_mps2"][k] = float(own[k]["max_residual_mps2"] if k in own else o["max_residual_mps2"])
        for j, e in enumerate((1, -1)):
            if k in own:
                (a0, s0, c0, d0), sd = own[k]["models"][e]
            else:
                a0 = o["step_offset_n"] + e * o["step_dir_n"] + o["step_per_accel_ns2pm"] * acc
                s0 = o["step_per_bar_n"] + o["step_per_bar_accel"] * acc
                c0, d0, sd = o.get("cold_per_accel_ns2pm", 0.0) * acc, 0.0, o["step_sd_n"]
            table["offset_n"][k][j], table["per_bar_n"][k][j] = float(a0), float(s0)
            table["cold_n"][k][j], table["per_kelvin_n"][k][j] = float(c0), float(d0)
            table["sd_n"][k][j] = float(sd)
            if k in own:
                table["silent_below_bar"][k][j] = float(own[k]["silent_below_bar"][e])
    return table


def add_own_excitations(cal: dict[str, Any], campaign: Any, physics: dict[str, Any], revs: Sequence[dict[str, Any]],
                        jobs: int, unit_tol_pct: float) -> dict[str, Any]:
    """Excitations of the campaign the shared measurement model does not calibrate (dropped by
    ``calibrate``, or too few windows under its residual cut) get a model of their own
    (``own_excitation``) when it validates (leave-one-run-out RMS ≤ ``CLUSTER_MAX_LORO_BAR``)
    and a cluster slot is free; the observer then reads their reversals with that model, at
    that excitation only (dt-core ``ExcitationModel::own``: nothing validates a line between it
    and another). The leave-one-run-out rows and the systematic sd take the new runs in.
    Returns ``cal`` updated."""
    o = cal["observer"]
    rel, spacing_rel = o["accel_cluster_rel"], o["spacing_rel"]
    kept = [(c, h) for c, h in zip(o["accel_clusters_mps2"], o["reversal_spacings_s"]) if c > 0]
    covered = [in_clusters(r, kept, rel, spacing_rel).sum() >= MIN_CLUSTER_REVERSALS for r in revs]
    runs = [run for run, c in zip(campaign.runs, covered) if not c]
    if not runs or len(kept) >= 4:
        return cal
    wide = {**o, "accel_clusters_mps2": [0.0] * 4, "reversal_spacings_s": [0.0] * 4,
            "max_residual_mps2": OWN_MAX_RESIDUAL_MPS2}
    log.info("fitting reversals of %d runs the shared model does not calibrate", len(runs))
    more = reversals(runs, {**physics, "observer": wide}, jobs)
    own_rows, added = [], []
    for c, h in accel_clusters(more, rel):
        if len(kept) + len(added) >= 4 or any(abs(c - k) <= rel * k for k, _ in kept):
            continue
        mine = []
        for r in more:
            keep = in_clusters(r, [(c, h)], rel, spacing_rel)
            if keep.sum() >= MIN_CLUSTER_REVERSALS:
                mine.append({k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in r.items()})
        fit = own_excitation(mine, o) if len(mine) >= 2 else None
        if fit is None or fit["loro_rms_bar"] > CLUSTER_MAX_LORO_BAR:
            log.warning("reversals at |a| = %.2f m/s², %.3f s apart: no model of their own validates "
                        "(leave-one-run-out RMS %s bar): the observer will skip them", c, h,
                        "n/a" if fit is None else f"{fit['loro_rms_bar']:.1f}")
            continue
        print(f"excitation at |a| = {c:.2f} m/s², {h:.3f} s apart: a measurement model of its own "
              f"(windows up to {fit['max_residual_mps2']:.2f} m/s²; leave-one-run-out RMS "
              f"{fit['loro_rms_bar']:.2f} bar over {len(mine)} runs)"
              + "".join(f"; its {'ÿ > 0' if e > 0 else 'ÿ < 0'} end falls silent below {b:g} bar"
                        for e, b in fit["silent_below_bar"].items() if b > 0))
        added.append((c, h, fit))
        own_rows += fit["loro"]
    if not added:
        return cal
    allc = sorted([(c, h, None) for c, h in kept] + added, key=lambda x: x[0])
    o["accel_clusters_mps2"] = [c for c, _, _ in allc] + [0.0] * (4 - len(allc))
    o["reversal_spacings_s"] = [h for _, h, _ in allc] + [0.0] * (4 - len(allc))
    o["excitations"] = excitation_table(o, {k: f for k, (_, _, f) in enumerate(allc) if f is not None})
    for row in own_rows:
        row.update({k: None for k, v in row.items() if isinstance(v, float) and not np.isfinite(v)})
        row["own_excitation"] = True
    with_loro(cal, list(cal["loro"]) + own_rows, unit_tol_pct)
    cal["own_excitations"] = [{"accel_mps2": c, "spacing_s": h, "max_residual_mps2": f["max_residual_mps2"],
                               "loro_rms_bar": f["loro_rms_bar"]} for c, h, f in added]
    return cal


def with_loro(cal: dict[str, Any], loro: list[dict[str, Any]], unit_tol_pct: float) -> None:
    """Sets ``cal``'s leave-one-run-out rows, their RMS and the systematic sd they imply (what the
    errors hold beyond each run's own statistical sd, with the unit tolerance on the offset)."""
    o = cal["observer"]
    err = np.array([np.nan if row["error_bar"] is None else row["error_bar"] for row in loro], float)
    stat = np.array([np.inf if row["stat_sd_bar"] is None else row["stat_sd_bar"] for row in loro], float)
    ok = np.isfinite(err) & np.isfinite(stat)
    sys_sd = float(np.sqrt(max(np.mean(err[ok] ** 2) - np.mean(stat[ok] ** 2), 0.0)))
    tol = unit_tol_pct / 100.0
    o["systematic_sd_bar"] = float(np.hypot(sys_sd, tol * o["step_offset_n"] / o["step_per_bar_n"]))
    cal.update(loro=loro, loro_rms_bar=float(np.sqrt(np.mean(err[ok] ** 2))), systematic_loro_bar=sys_sd)


def own_model_on_the_line(cal: dict[str, Any], alt: dict[str, Any], fastest: float,
                          unit_tol_pct: float) -> dict[str, Any] | None:
    """``cal`` (the fastest excitation on the shared line) with ``alt``'s model of the fastest's
    own (``fastest_on_its_own``) in a free cluster slot: the observer reads the fastest's
    reversals with its own model, and reversals between it and the next excitation on the line,
    which ``cal``'s leave-one-run-out validated through it (dt-core ``ExcitationModel::own``).
    The leave-one-run-out rows: ``cal``'s but for the runs the own model reads, ``alt``'s for
    those. None without a free slot or without the own model."""
    o, a = cal["observer"], alt["observer"]
    rel = o["accel_cluster_rel"]
    ax = a.get("excitations")
    slots = [k for k, c in enumerate(o["accel_clusters_mps2"]) if c <= 0]
    k_own = next((k for k, c in enumerate(a["accel_clusters_mps2"])
                  if ax and c > 0 and ax["own"][k] and abs(c - fastest) <= rel * fastest), None)
    if k_own is None or not slots:
        return None
    out = json.loads(json.dumps(cal))
    h = out["observer"]
    j = slots[0]
    table = h.get("excitations") or excitation_table(h, {})
    h["accel_clusters_mps2"][j] = a["accel_clusters_mps2"][k_own]
    h["reversal_spacings_s"][j] = a["reversal_spacings_s"][k_own]
    for key in ("offset_n", "per_bar_n", "cold_n", "per_kelvin_n", "sd_n", "silent_below_bar"):
        table[key][j] = list(ax[key][k_own])
    table["max_residual_mps2"][j] = ax["max_residual_mps2"][k_own]
    table["own"][j] = True
    h["excitations"] = table
    own_rows = [r for r in alt["loro"] if r.get("own_excitation")]
    own_runs = {r["run"] for r in own_rows}
    with_loro(out, [r for r in cal["loro"] if r["run"] not in own_runs] + own_rows, unit_tol_pct)
    out["own_excitations"] = list(cal.get("own_excitations", [])) + [
        x for x in alt.get("own_excitations", []) if abs(x["accel_mps2"] - fastest) <= rel * fastest]
    return out


def data_kind(campaign: Any) -> str:
    """``simulated data`` or ``dyno data``, as the campaign's logs say (``train.fit_physics``'s
    words): a calibration on a real damper's runs was printed as simulated."""
    return "simulated data" if campaign.simulated else "dyno data"


def damping_law_of(campaign: Any, physics: dict[str, Any], obs: dict[str, Any],
                   per_run: int, min_span_k: float, beta_per_k: float | None = None,
                   form: str = "hinges", loadcell: bool = False, complete: bool = True) -> dict[str, Any] | None:
    """The window model's damping law, fitted on the reversal windows of the nominal runs, with
    ``complete`` (the default) those completed by ``law_runs`` (``train.damping_law``;
    ``beta_per_k``: the oil's viscosity coefficient from the datasheet, held); None (with the
    reason) without nominal windows or when they span less than ``min_span_k`` of oil
    temperature. The hinges' law is fitted in stages
    (``fit_law_staged``); ``form`` ``valve``: that law refined with an extension valve
    (``fit_valve_law_windows``, started from the hinges' fit); ``valves``: that one refined
    with a compression valve too (``fit_valves_law_windows``); ``twin-tube``: that one with
    the compression valve split in two, base and piston (``fit_twin_law_windows``)."""
    from train.damping_law import (LAW_WINDOW_MAX_RESIDUAL_MPS2, fit_law_staged, fit_twin_law_windows,
                                   fit_valve_law_windows, fit_valves_law_windows, loadcell_law_rows,
                                   reversal_windows)

    runs = campaign.nominal(physics.get("nominal_bar", 12.0))
    if complete:
        more = law_runs(campaign.runs, runs)
        if more:
            print("damping law: the nominal runs lack " + ", ".join(f"{r.frequency_hz:g} Hz" for r in more)
                  + "; the highest charge's run there stands in: " + ", ".join(r.name for r in more))
        runs = runs + more
    wins = [w for w in reversal_windows(runs, physics, obs, per_run)
            if w["residual0"] <= LAW_WINDOW_MAX_RESIDUAL_MPS2]
    if not wins:
        log.warning("no reversal window on the nominal runs: no damping law")
        return None
    temps = [w["oil_c"] for w in wins]
    span = max(temps) - min(temps)
    if span < min_span_k:
        print(f"damping law: the nominal runs' reversal windows span {span:.0f} K of oil temperature "
              f"({min(temps):.0f}-{max(temps):.0f} °C), under the {min_span_k:.0f} K its viscosity "
              "coefficient needs (runs that heat up do): linear damping slopes")
        return None
    if span < LAW_MIN_TEMP_SPAN_K and beta_per_k is None:
        log.warning("the damping law is fitted on %.0f K of oil temperature only: its viscosity coefficient "
                    "is poorly determined", span)
    fit = fit_law_staged(wins, physics, obs, beta_per_k=beta_per_k)
    if form in ("valve", "valves", "twin-tube"):
        hinges = fit
        fit = fit_valve_law_windows(wins, physics, obs, fit["law"]["beta_per_k"], start=hinges)
        print(f"damping law, the hinges alone: residual {hinges['residual_rms_mps2']:.3f} m/s² RMS; "
              f"with the extension valve: {fit['residual_rms_mps2']:.3f}"
              + (":" if form == "valve" else ", with both valves:"))
    if form in ("valves", "twin-tube"):
        fit = fit_valves_law_windows(wins, physics, obs, start=fit)
    if form == "twin-tube":
        print(f"damping law with a valve each way: {fit['residual_rms_mps2']:.3f} m/s² RMS; "
              "with the compression valve split in two (base and piston):")
        fit = fit_twin_law_windows(wins, physics, obs, start=fit)
        rows = loadcell_law_rows(runs, physics, obs, fit) if loadcell else None
        if rows is not None:
            print(f"damping law on the windows: {fit['residual_rms_mps2']:.3f} m/s² RMS, the loadcell "
                  f"{np.sqrt(np.mean(np.concatenate(rows.residuals_n(fit['law'])) ** 2)):.1f} N RMS; "
                  "with the loadcell rows:")
            fit = fit_twin_law_windows(wins, physics, obs, start=fit, loadcell=rows)
            print(f"damping law with the loadcell rows: the loadcell {fit['loadcell_rms_n']:.1f} N RMS")
    print(f"damping law near reversals from {fit['windows']} reversal windows of {len(runs)} "
          f"{'runs' if complete else 'nominal runs'} ({data_kind(campaign)}): residual {fit['residual_rms_mps2']:.3f} m/s² RMS "
          f"(viscosity coefficient {fit['law']['beta_per_k']:.4f} /K, "
          f"{'fitted' if beta_per_k is None else 'the datasheet oil'})")
    return fit["law"]


def law_runs(runs: Sequence[Run], nominal: Sequence[Run]) -> list[Run]:
    """The runs that stand in for the nominal runs the campaign lacks, for the damping law: at
    each excitation frequency of ``runs`` that no ``nominal`` run has, the run of the highest
    charge (runs without a frequency are not matched). Each law window has an amplitude of its
    own, so the charge does not enter the law; the highest charge cavitates least. A law
    fitted on one excitation's windows knows the stroke speeds near rest only: in the
    fifty-seventh session (docs/history.md) a fold of the full simulated campaign without its
    2 Hz nominal run fitted its law on the 1 Hz windows alone (the 4 Hz ones miss its cut),
    and its observer then read neither 2 nor 4 Hz; with the 10 bar 2 Hz run standing in it
    calibrated 1, 2 and 4 Hz and read the fold's held-out runs at 0.37 bar RMSE, not 2.20."""
    have = {r.frequency_hz for r in nominal}
    best: dict[float, Run] = {}
    for r in runs:
        f = r.frequency_hz
        if f is None or f in have or r.label_bar is None:
            continue
        if f not in best or r.label_bar > best[f].label_bar:  # type: ignore[operator]
            best[f] = r
    return list(best.values())  # in the campaign's order of the frequencies' first runs


def law_min_span_k(damping: str, beta_per_k: float | None) -> float:
    """The oil temperature span (K) the nominal runs' windows must cover for ``fit --damping
    damping`` to fit the law: ``auto`` needs ``LAW_MIN_TEMP_SPAN_K`` to measure the viscosity
    coefficient, unless the datasheet's oil gives it (``beta_per_k``); ``law`` fits it on any span.
    (Before the thirty-fourth session the span was asked for either way, and the demo's quick
    campaign fell back to linear slopes that read another unit 15 bar low at 2 Hz.)"""
    return LAW_MIN_TEMP_SPAN_K if damping == "auto" and beta_per_k is None else 0.0


def shared_calibration(revs: Sequence[dict[str, Any]], law_obs: dict[str, Any], unit_tol_pct: float,
                       leave_out: Sequence[float] = ()) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """``calibrate`` with the damping law, then again without the windows whose residual reads the
    charge biased on the calibration runs (``residual_cut``; the cut goes into the calibration's
    ``max_residual_mps2``). Returns the calibration and the reversals kept."""
    obs = dict(law_obs)
    cal = calibrate(revs, obs, unit_tol_pct, leave_out)
    kept = list(revs)
    cut = residual_cut(revs, cal)
    if cut < obs["max_residual_mps2"]:
        print(f"damping law: windows that fit worse than {cut:.2f} m/s² read the charge biased on the "
              "calibration runs; the observer skips them")
        obs["max_residual_mps2"] = cut
        kept = [{k: (v[r["residual_mps2"] <= cut] if isinstance(v, np.ndarray) else v) for k, v in r.items()}
                for r in revs]
        cal = calibrate(kept, obs, unit_tol_pct, leave_out)
    return cal, kept


def fastest_on_its_own(cal: dict[str, Any], campaign: Any, physics: dict[str, Any],
                       revs: Sequence[dict[str, Any]], law_obs: dict[str, Any],
                       args: argparse.Namespace) -> dict[str, Any]:
    """With three or more excitations on the shared measurement model, the same calibration with
    the fastest of them left off it and given a model of its own (``add_own_excitations``), its
    residual cut found again without it (``shared_calibration``; ``revs``: the reversals before
    any cut); kept when it covers as many excitations and reads the calibration runs left out one
    at a time better (leave-one-run-out RMS). The fastest excitation is where a line in ``|ÿ|``
    bends (the window law's reach, cavitation at a low charge): on the simulated dyno the
    twin-tube law (``--law-form twin-tube``) fits the 4 Hz windows well enough for them to join
    the line, and read LORO 0.82 bar with 4 Hz on it against 0.08 with a model of its own, which
    also keeps the cavitation bound (docs/history.md, twenty-fourth session). When the own model wins,
    the fastest stays on the line as well (``own_model_on_the_line``): the line, validated
    through it, reads the reversals between it and the next excitation (3 Hz, "unseen": 1.02 →
    0.39 bar with the accelerometers' slope, docs/history.md, twenty-fifth session), the own model reads
    it. ``--fastest-off-the-line`` takes it off the line; ``--keep-fastest-shared`` skips this."""
    o = cal["observer"]
    own = (o.get("excitations") or {}).get("own") or [False] * 4
    shared = [c for k, c in enumerate(o["accel_clusters_mps2"]) if c > 0 and not own[k]]
    if len(shared) < 3:
        return cal
    fastest = max(shared)
    alt, kept = shared_calibration(revs, law_obs, args.unit_tolerance_pct, leave_out=[fastest])
    alt = add_own_excitations(alt, campaign, physics, kept, args.jobs, args.unit_tolerance_pct)
    n = [sum(c > 0 for c in x["observer"]["accel_clusters_mps2"]) for x in (cal, alt)]
    print(f"the fastest excitation (|a| = {fastest:.2f} m/s²) on the shared model: leave-one-run-out RMS "
          f"{cal['loro_rms_bar']:.2f} bar over {n[0]} excitation(s); with a model of its own: "
          f"{alt['loro_rms_bar']:.2f} bar over {n[1]}")
    if not (n[1] >= n[0] and alt["loro_rms_bar"] < cal["loro_rms_bar"]):
        return cal
    both = None if args.fastest_off_the_line else own_model_on_the_line(cal, alt, fastest, args.unit_tolerance_pct)
    if both is None:
        return alt
    print(f"the fastest excitation read by its own model, and kept on the shared line for the reversals "
          f"between it and the next: leave-one-run-out RMS {both['loro_rms_bar']:.2f} bar")
    return both


def held_sd(cal: dict[str, Any], revs: Sequence[dict[str, Any]], law_obs: dict[str, Any],
            unit_tol_pct: float) -> dict[str, Any] | None:
    """What reading above the shared line's fastest excitation ``a_1`` costs with the model held
    there (dt-core ``ObserverParams::held_sd_bar``), measured one step down: the runs at ``a_1``
    read with the shared model calibrated without them (``shared_calibration`` with ``a_1`` left
    out), held at the line's next excitation ``a_0`` (every reversal's terms at ``|ÿ| = a_0``;
    ``cal``'s residual cut, which the observer applies to held reversals too). Returns the RMS of
    their charge errors and the rows; None with fewer than two spaced excitations on the line or
    no run at ``a_1`` read. On the simulated dyno the line extrapolated from 1–2 Hz to 3 Hz reads
    +1.5…+2.2 bar high, a line drawn to the 4 Hz model's terms 2.5–2.9 bar low (docs/history.md, thirtieth
    session): neither can be tested on a campaign without 3 Hz, the hold can."""
    o = cal["observer"]
    own = (o.get("excitations") or {}).get("own") or [False] * 4
    line = sorted((c, h) for k, (c, h) in enumerate(zip(o["accel_clusters_mps2"], o["reversal_spacings_s"]))
                  if c > 0 and h > 0 and not own[k])
    if len(line) < 2:
        return None
    (a0, _), (a1, h1) = line[-2], line[-1]
    low = shared_calibration(revs, law_obs, unit_tol_pct, leave_out=[a1])[0]["observer"]
    rows = []
    for r in revs:
        keep = (in_clusters(r, [(a1, h1)], o["accel_cluster_rel"], o["spacing_rel"])
                & (r["residual_mps2"] <= o["max_residual_mps2"]))
        if keep.sum() < MIN_CLUSTER_REVERSALS:
            continue
        rr = {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in r.items()}
        rr["accel_mps2"] = np.sign(rr["accel_mps2"]) * a0
        p, sd = charge_from(rr, coef_of(low), low["step_sd_n"], low)
        if np.isfinite(p):
            rows.append({"run": r["run"], "truth_bar": r["truth_bar"], "estimate_bar": p, "stat_sd_bar": sd,
                         "error_bar": p - r["truth_bar"]})
    if not rows:
        return None
    err = np.array([row["error_bar"] for row in rows])
    return {"held_sd_bar": float(np.sqrt(np.mean(err ** 2))), "from_accel_mps2": a0, "at_accel_mps2": a1,
            "reach_accel_mps2": a1 * a1 / a0, "rows": rows}


def linear_calibration(runs: Sequence[Run], physics: dict[str, Any], obs: dict[str, Any], jobs: int,
                       unit_tol_pct: float, mp_context: BaseContext | None = None) -> dict[str, Any]:
    """``calibrate`` on the reversals fitted with linear damping slopes (no law)."""
    log.info("fitting reversals of %d runs with linear damping slopes", len(runs))
    return calibrate(reversals(runs, {**physics, "observer": obs}, jobs, mp_context), obs, unit_tol_pct)


def cmd_fit(args: argparse.Namespace) -> int:
    physics = read_json(args.physics)
    campaign = load_campaign(args.campaign)
    obs = dict(shocktwin.default_observer_params())
    beta_per_k = None
    if args.datasheet and args.datasheet.suffix == ".toml":
        # The same datasheet file as fit_physics (docs/datasheet.example.toml).
        from train.datasheet import load_datasheet

        sheet = load_datasheet(args.datasheet)
        geometry, beta_per_k = sheet.geometry, sheet.viscosity_coefficient_per_k
        obs.update({f"{k}_m2" if k == "a_rod" else f"{k}_m3": v for k, v in geometry.items()
                    if k in ("a_rod", "v_gas")})
        if sheet.oil_expansion_m3_per_k is not None:
            obs["oil_expansion_m3_per_k"] = sheet.oil_expansion_m3_per_k
    elif args.datasheet:
        from train.datasheet import check_plausible

        given = read_json(args.datasheet)
        for key, unit in (("a_rod_m2", "m²"), ("v_gas_m3", "m³")):
            if isinstance(given.get(key), (int, float)):
                check_plausible(f"{args.datasheet}: {key}", key, float(given[key]), unit)
        obs.update(given)
    obs["window_sd"] = bool(args.window_sd)
    obs["reversal_accel"] = args.reversal_accel.replace("-", "_")
    rod_scales = None
    if obs["reversal_accel"] == "accelerometers" and not args.no_rod_scale:
        # Before any window is fitted, so that the law and every calibration reversal read `ÿ_r` as
        # the runs the observer will read later, each corrected by its own scale against this one.
        k_cal, rod_scales = rod_accel_scale(campaign.runs, physics, obs, args.jobs)
        if k_cal is not None:
            obs["rod_accel_scale"] = k_cal
            print(f"accelerometer scale against the potentiometer: {k_cal:.5f} (median of "
                  f"{sum(np.isfinite(rod_scales))} runs, {np.nanmin(rod_scales):.5f}–{np.nanmax(rod_scales):.5f}); "
                  "each run's `ÿ_r` is read as these sensors would read it (dt-core "
                  "ObserverParams::rod_accel_scale)")
    cal, law, law_cal = None, None, None
    linear = None
    if args.damping == "auto" and args.jobs > 1:
        # The linear slopes' calibration does not depend on the law's: it runs beside the law's
        # path (whose serial parts leave a core idle about a third of its time) on one worker
        # process of its own, started from a fresh interpreter (forkserver): this process has
        # threads now, which a fork would copy mid-work. With one job, after the law's path.
        background = ThreadPoolExecutor(max_workers=1)
        linear = background.submit(linear_calibration, campaign.runs, copy.deepcopy(physics), copy.deepcopy(obs), 1,
                                   args.unit_tolerance_pct, multiprocessing.get_context("forkserver"))
        background.shutdown(wait=False)
    if args.damping in ("law", "auto"):
        law = damping_law_of(campaign, physics, obs, args.law_windows, law_min_span_k(args.damping, beta_per_k),
                             beta_per_k,
                             args.law_form, args.law_loadcell == "auto", args.law_runs == "complete")
        if law is None and args.damping == "law":
            raise SystemExit("--damping law: no reversal window on the nominal runs to fit the law on")
    if law is not None:
        # Between the excitations the two ends of the stroke can disagree (the window model
        # interpolated, one end high, the other low): each end gets its own filter, the
        # estimate is their average and the interval widens by their split.
        law_obs = {**obs, "damping_law": law, "between_excitations": not args.no_between,
                   "scale_prior_sd": float(args.scale_prior_sd),
                   "stroke_ends": not (args.no_between or args.no_stroke_ends)}
        log.info("fitting reversals of %d runs with the damping law", len(campaign.runs))
        revs = reversals(campaign.runs, {**physics, "observer": law_obs}, args.jobs)
        law_obs["cold_ref_c"] = cold_reference(revs, law_obs)
        cal, kept = shared_calibration(revs, law_obs, args.unit_tolerance_pct)
        if not args.no_own_excitations:
            cal = add_own_excitations(cal, campaign, physics, kept, args.jobs, args.unit_tolerance_pct)
            if not args.keep_fastest_shared:
                cal = fastest_on_its_own(cal, campaign, physics, revs, law_obs, args)
        law_cal = cal
    if args.damping in ("linear", "auto"):
        lin = (linear.result() if linear is not None
               else linear_calibration(campaign.runs, physics, obs, args.jobs, args.unit_tolerance_pct))
        if cal is not None:
            # Keep the window model that calibrates more excitations, then the lower
            # leave-one-run-out error (the calibration campaign's own runs only).
            n_law, n_lin = (sum(c > 0 for c in x["observer"]["accel_clusters_mps2"]) for x in (cal, lin))
            print(f"window model: damping law {n_law} excitation(s), LORO {cal['loro_rms_bar']:.2f} bar; linear "
                  f"slopes {n_lin}, LORO {lin['loro_rms_bar']:.2f} bar")
            if (n_lin, -lin["loro_rms_bar"]) > (n_law, -cal["loro_rms_bar"]):
                cal = lin
        else:
            cal = lin
    o = cal["observer"]
    if cal is law_cal and law_cal is not None and not args.no_held:
        held = held_sd(cal, revs, law_obs, args.unit_tolerance_pct)
        if held is not None:
            o["held_sd_bar"] = held["held_sd_bar"]
            cal["held"] = held
            print(f"above the line's fastest excitation (|a| = {held['at_accel_mps2']:.2f} m/s²) up to "
                  f"{held['reach_accel_mps2']:.2f}, short of an excitation with a model of its own: the "
                  f"measurement model held there, ± {held['held_sd_bar']:.2f} bar (its runs read with the model "
                  f"held at {held['from_accel_mps2']:.2f} m/s², calibrated without them: "
                  + ", ".join(f"{r['error_bar']:+.2f}" for r in held["rows"]) + " bar)")
    cal["single_end_sd_bar"] = o.get("single_end_sd_bar", 0.0)  # measured, kept in `fit` either way
    if not args.single_end:
        o["single_end_sd_bar"] = 0.0
    law_on = law_calibrated(o)
    print("window model: " + ("the damping law" + (", reversals between calibrated excitations used"
                                                   + (", each end of the stroke filtered apart and averaged"
                                                      if o.get("stroke_ends") else "")
                                                   if o.get("between_excitations") else "")
                              if law_on else "linear damping slopes"))
    o["fit_gain_floor"] = float(args.fit_gain_floor)
    physics["observer"] = cal["observer"]
    physics.setdefault("fit", {})["observer"] = {k: v for k, v in cal.items() if k != "observer"}
    if rod_scales is not None:
        physics["fit"]["observer"]["rod_accel_scale_runs"] = {
            r.name: (k if np.isfinite(k) else None) for r, k in zip(campaign.runs, rod_scales)}
    out = args.out or args.physics
    out.write_text(json.dumps(physics, indent=2) + "\n")
    print(f"Charge observer calibration ({data_kind(campaign)}), measurement model alpha = "
          f"{o['step_offset_n']:.2f} {o['step_dir_n']:+.2f} sgn(a) {o['step_per_accel_ns2pm']:+.3f} |a| "
          f"+ ({o['step_per_bar_n']:.3f} {o['step_per_bar_accel']:+.4f} |a|) p_g  (N), per-reversal sd "
          f"{o['step_sd_n']:.2f} N")
    if o.get("cold_per_accel_ns2pm") or o.get("cold_bias_sd_ns2pm"):
        print(f"cold oil (below {o['cold_ref_c']:.0f} °C): {o['cold_per_accel_ns2pm']:+.2f} x(T) |a| N, "
              "what it leaves "
              f"± {o['cold_bias_sd_ns2pm']:.2f} x(T) |a| N, carried as a bias the reversals share")
    if o.get("stroke_ends") and cal["single_end_sd_bar"]:
        print(f"one end of the stroke read alone (at a calibrated excitation): ± {cal['single_end_sd_bar']:.2f} bar "
              "from the charge (the calibration's warm bins); "
              + ("it stands alone until the other end is read" if o["single_end_sd_bar"]
                 else "not used (--single-end to use it)"))
    print("calibrated at reversals " + ", ".join(f"{c:.2f} m/s² {h:.3f} s apart"
                                                   for c, h in zip(o["accel_clusters_mps2"], o["reversal_spacings_s"])
                                                   if c > 0)
          + f" (±{100 * o['accel_cluster_rel']:.0f} % in |a|, ±{100 * o['spacing_rel']:.0f} % in spacing; "
          f"99 % of the calibration reversals within {100 * cal['spacing_spread_rel']:.1f} % of their spacing); "
          + ("reversals elsewhere are skipped, but for those held above the line (above)" if o.get("held_sd_bar")
             else "reversals elsewhere are skipped"))
    print(f"leave-one-run-out charge error RMS {cal['loro_rms_bar']:.2f} bar; systematic sd "
          f"{o['systematic_sd_bar']:.2f} bar (+{100 * o['systematic_rel']:.0f} % of the charge)")
    if o["fit_gain_floor"] > 0:
        print(f"a reversal is fitted when one more reading could narrow the reported variance by "
              f"{100 * o['fit_gain_floor']:g} % of its systematic part or more, else spared "
              "(--fit-gain-floor; dt-core ObserverParams::fit_gain_floor)")
    print(f"wrote {out}")
    return 0


def excitation_end_s(lg: Any, default_s: float) -> float:
    """When the stroke stops for good (s since the run's first message): the last time the
    position moved by more than 0.1 mm between samples; ``default_s`` without a position."""
    pos = lg.topic("/position")
    if len(pos["t_s"]) < 2:
        return default_s
    moving = np.nonzero(np.abs(np.diff(pos["position_m"])) > 1e-4)[0]
    return float(pos["t_s"][moving[-1]]) if len(moving) else default_s


# The window fit is nearly all of the observer's cost: a reversal is fitted only when one more
# reading could narrow the reported variance of the charge by this share of its systematic part.
# Chosen on a validation campaign of its own (docs/history.md, "Thirteenth session"): 1e-4 cost 0.04 bar of
# RMSE there and fitted 19-53 % of the reversals; 1e-3 cost 0.34 bar.
FIT_GAIN_FLOOR = 1e-4

# A baseline run must have taught the observer something: its reading's own sd (without
# the systematic part) below this share of the prior's.
BASELINE_MAX_SD_SHARE = 0.25
BASELINE_SETTLE_S = 60.0  # as `evaluate --settle-s`
# readings a baseline holds at other excitations than its own (dt-core charge::OTHER_EXCITATIONS)
OTHER_EXCITATIONS = 3


def baseline_of(physics: dict[str, Any], paths: Sequence[Path], charge_bar: float,
                jobs: int = 2, unit_law: bool = False,
                second: tuple[float, Sequence[Path]] | None = None) -> dict[str, Any]:
    """The unit's ``observer_baseline`` from ``paths`` (runs of one unit at ``charge_bar``):
    each run's reading at its last excited tick, combined by inverse variance. The sd is
    what stays uncertain once the unit's offset is known: the filter's own variance, the
    drift of the reading within the run (RMS of its departure from the final reading over
    the ticks from ``BASELINE_SETTLE_S`` after onset: the error changes as the unit heats —
    on the simulated second unit it read 7.7 bar for 10 at the cold start and 10.2 hot —
    and a constant correction cannot follow it). Over several runs the baseline records their
    effective number (``runs_averaged``, Kish's ``(Σw)²/Σw²``), by which dt-core divides a run's
    own error (``run_sd_bar``, ``run_rel``: ``run-spread``). With a calibration that carries
    that term, the sd leaves out the runs' spread about their mean (the term holds it), unless
    they spread beyond it (χ² above its 99.9 % point: added, with a warning); without the term,
    their spread is added. So a baseline read over several runs with a run term belongs with
    a calibration that carries it: read with one without, the runs' spread is counted nowhere.

    ``unit_law``: first refit the calibration's damping law on these runs' reversal windows
    (``train.damping_law.unit_law``), read the baseline with it and return it in the baseline
    as the unit's ``damping_law`` (beside it, ``unit_law``: the fit's windows and residuals):
    the law the unit is read with from then on (dt-core ``UnitBaseline::damping_law``:
    ``shocktwin replay --observer-baseline``, ``evaluate --baseline``, the daemon).

    ``second``: ``(charge, runs)``, the same unit's runs at another known charge (an
    end-of-line test at two charges), read the same way into the baseline's ``second``
    reading (dt-core ``UnitBaseline::second``); with ``unit_law`` the law is refitted on the
    runs at both charges.

    Runs at several excitations give one reading per excitation (``excitation_groups``: their
    used reversals' ``|ÿ_r|`` ranges within the calibration's ``accel_cluster_rel`` of each
    other): the first run's is the baseline's own, the others its ``other_excitations`` (dt-core
    ``UnitBaseline::other_excitations``), each with its own ``second`` from the runs at the second
    charge at its excitation. A unit's error moves with the excitation by an amount of its own
    (docs/history.md, "Sixty-fifth session"): one reading averaged over two excitations would
    correct neither."""
    obs = physics["observer"]
    if obs.get("baseline"):
        raise SystemExit("the physics already carries a unit baseline: give the model's own")
    fit = None
    all_paths = list(paths) + (list(second[1]) if second else [])
    seen: dict[Path, Path] = {}
    for p in all_paths:
        # one run given twice would be counted as two (its reading's sd divided by √2)
        if Path(p).resolve() in seen:
            raise SystemExit(f"{p}: given twice (as {seen[Path(p).resolve()]}): each run counts once in a reading")
        seen[Path(p).resolve()] = Path(p)
    if unit_law:
        from train.campaign import read_run
        from train.damping_law import unit_law as refit

        try:
            fit = refit([read_run(p) for p in all_paths], physics)
        except (ValueError, OSError) as err:  # shocktwin's log errors are either
            raise SystemExit(f"{', '.join(str(p) for p in all_paths)}: {err}") from None
        obs = {**obs, "damping_law": fit["law"]}
        physics = {**physics, "observer": obs}
    # A unit's reading takes every reversal (as the daemon's service reading does): its sd
    # is what the baseline will condition the unit on.
    physics = {**physics, "observer": {**obs, "fit_gain_floor": 0.0}}
    obs = physics["observer"]
    own_law = fit is not None
    reads = _read_runs(physics, paths, jobs)
    groups = excitation_groups([r.span for r in reads], obs["accel_cluster_rel"])
    if len(groups) > 1 + OTHER_EXCITATIONS:
        raise SystemExit(f"{', '.join(map(str, paths))}: read at {len(groups)} excitations, a baseline holds at most "
                         f"{1 + OTHER_EXCITATIONS} (dt-core UnitBaseline::other_excitations)")
    seconds: list[list[int]] = [[] for _ in groups]
    second_reads: list[BaselineRead] = []
    if second is not None:
        second_reads = _read_runs(physics, second[1], jobs)
        spans = [[s for s in (reads[i].span for i in grp) if s is not None] for grp in groups]
        hulls = [[min(x[0] for x in sp), max(x[1] for x in sp)] if sp else None for sp in spans]
        for k, r in enumerate(second_reads):
            # the nearest excitation whose runs' range holds this run's (within the calibration's band)
            near = sorted((ln_distance(h, r.span) if r.span is not None else 0.0, g) for g, h in enumerate(hulls)
                          if r.span is None or (h is not None and not away(h, r.span, obs["accel_cluster_rel"])))
            near = [g for _, g in near]
            if not near:
                raise SystemExit(f"{second[1][k]}: read at |ÿ_r| {r.span[0]:.2f}–{r.span[1]:.2f} m/s², where no run at "
                                 f"--charge-bar {charge_bar:g} was read: a second reading pairs with a first at its "
                                 "excitation")
            seconds[near[0]].append(k)
    readings, runs = [], []
    for g, (grp, sec) in enumerate(zip(groups, seconds)):
        first = _reading(obs, [paths[i] for i in grp], [reads[i] for i in grp], charge_bar, own_law=own_law)
        ob = {"charge_bar": float(charge_bar), "read_bar": first["read_bar"], "read_sd_bar": first["read_sd_bar"]}
        if first["runs_effective"] > 1.0:
            ob["runs_averaged"] = first["runs_effective"]  # dt-core UnitBaseline::runs_averaged
        if first["split_bar"] is not None:
            ob["split_bar"] = first["split_bar"]  # dt-core UnitBaseline::split_bar
        ranges = first["ranges"]
        runs += [{**r, "charge_bar": float(charge_bar), "excitation": g} for r in first["runs"]]
        if sec:
            other = _reading(obs, [second[1][k] for k in sec], [second_reads[k] for k in sec], second[0],
                             own_law=own_law)
            # dt-core UnitBaseline::second
            ob["second"] = {"charge_bar": float(second[0]), "read_bar": other["read_bar"],
                            "read_sd_bar": other["read_sd_bar"]}
            if other["runs_effective"] > 1.0:
                ob["second"]["runs_averaged"] = other["runs_effective"]
            ranges = ranges + other["ranges"]
            runs += [{**r, "charge_bar": float(second[0]), "excitation": g} for r in other["runs"]]
        if ranges:
            # the excitations it was read at (dt-core UnitBaseline::accel_range_mps2)
            ob["accel_range_mps2"] = [min(r[0] for r in ranges), max(r[1] for r in ranges)]
        readings.append(ob)
    ranged = [(g, r["accel_range_mps2"]) for g, r in enumerate(readings) if "accel_range_mps2" in r]
    for a, (g, ra) in enumerate(ranged):
        for h, rb in ranged[a + 1:]:
            lo, hi = (ra, rb) if ra[0] <= rb[0] else (rb, ra)
            if hi[0] <= lo[1] * (1.0 + obs["accel_cluster_rel"]):
                # (dt-core charge::same_excitation: a baseline with them would be refused)
                raise SystemExit(f"the readings at |ÿ_r| {ra[0]:.2f}–{ra[1]:.2f} and {rb[0]:.2f}–{rb[1]:.2f} m/s² (runs "
                                 + ", ".join(x["file"] for x in runs if x["excitation"] in (g, h))
                                 + ") reach within the calibration's band of each other once the --second-runs are "
                                 "added: one excitation, or two? Give the runs of one excitation, or read them apart")
    ob = readings[0]
    if len(readings) > 1:
        # one reading per excitation (dt-core UnitBaseline::other_excitations): a run is
        # corrected by the one nearest its excitation
        ob["other_excitations"] = readings[1:]
    out = {"observer_baseline": ob, "runs": runs,
           "note": "one unit's reading at a known charge (simulated data when made from shocktwin simulate)"}
    if fit is not None:
        ob["damping_law"] = fit["law"]  # dt-core UnitBaseline::damping_law
        out["unit_law"] = {"windows": fit["windows"], "residual_rms_mps2": fit["residual_rms_mps2"],
                           "residual_before_mps2": fit["residual_before"], "residual_after_mps2": fit["residual_after"]}
    return out


def reading_var(obs: dict[str, Any], m: float, sd: float, floor: float = 1e-4) -> float:
    """A raw reading's own variance (its reversals), bar²: the observer's reported ``sd²`` at
    reading ``m`` less the systematic part it carried without a baseline (``S² + (ρ m)²``),
    floored at ``floor`` (0.01 bar: a covariance stays invertible where every other term is 0)."""
    return max(sd ** 2 - obs["systematic_sd_bar"] ** 2 - (obs["systematic_rel"] * m) ** 2, floor)


def _read_runs(physics: dict[str, Any], paths: Sequence[Path], jobs: int) -> list[BaselineRead]:
    """Each run's reading of a unit for ``baseline_of``; a run read at an excitation with a
    model of its own is refused."""
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        reads = list(pool.map(_baseline_read, [(str(p), physics) for p in paths]))
    for path, r in zip(paths, reads):
        if r.own:
            raise SystemExit(f"{path}: {r.own} of its reversals were read at an excitation with a measurement model of "
                             "its own, which a baseline does not condition (dt-core UnitBaseline): take the baseline "
                             "at one of the shared model's excitations (the calibration's 1 Hz run is one; leave this "
                             "run out, the others make the baseline)")
    return reads


def excitation_groups(spans: Sequence[Sequence[float] | None], rel: float) -> list[list[int]]:
    """The runs (their indices) grouped by excitation: by their used reversals' ``|ÿ_r|`` ranges
    (``spans``), runs whose ranges lie within ``rel`` of each other's together. The group of the
    first run comes first (the baseline's own reading), the others by excitation; a run without a
    range joins the first group (its reading is refused there for want of reversals)."""
    ranged = sorted((i for i, s in enumerate(spans) if s is not None), key=lambda i: spans[i][0])
    groups: list[list[int]] = []
    hi = -np.inf
    for i in ranged:
        lo_i, hi_i = spans[i]
        if groups and lo_i <= hi * (1.0 + rel):
            groups[-1].append(i)
            hi = max(hi, hi_i)
        else:
            groups.append([i])
            hi = hi_i
    unranged = [i for i, s in enumerate(spans) if s is None]
    if not groups:
        return [unranged]
    first = next((k for k, g in enumerate(groups) if 0 in g), 0)
    groups.insert(0, groups.pop(first))
    groups[0] = sorted(groups[0] + unranged)
    return groups


def _reading(obs: dict[str, Any], paths: Sequence[Path], reads: Sequence[BaselineRead], charge_bar: float,
             own_law: bool = False) -> dict[str, Any]:
    """One reading of a unit at one known charge and excitation for ``baseline_of``: the runs'
    readings (``_read_runs``) combined by inverse variance; the runs, and the ``|ÿ_r|`` range of
    each run's reversals. ``own_law``: the unit is read with its own damping law
    (``--unit-law``); without it, a reading refused for too few reversals suggests it."""
    ranges = [r.span for r in reads if r.span is not None]
    splits = np.array([r.split_bar for r in reads])
    reads = [(r.read_bar, r.sd_bar, r.drift_bar) for r in reads]
    rows = []
    for path, (m, sd, drift) in zip(paths, reads):
        if m is None:
            raise SystemExit(f"{path}: no excited tick: no baseline from it")
        var = reading_var(obs, m, sd) + drift ** 2
        if np.sqrt(var) > BASELINE_MAX_SD_SHARE * obs["prior_sd_bar"]:
            raise SystemExit(f"{path}: the observer used (almost) no reversals (reading {m:.2f} ± "
                             f"{np.sqrt(var):.2f} bar from its reversals alone): an excitation it was not "
                             "calibrated at"
                             + ("?" if own_law else ", or a unit whose valves the calibration's damping law "
                                "does not fit (then `--unit-law` refits the law on these runs)?")
                             + " No baseline from it")
        rows.append((str(path), m, var))
    w = np.array([1.0 / v for _, _, v in rows])
    m = np.array([x for _, x, _ in rows])
    mean = float(np.sum(w * m) / np.sum(w))
    # the runs' effective number (Kish): each carries a run error of its own (R(p₀)², dt-core
    # ObserverParams::run_sd_bar), which their weighted mean holds as R(p₀)² Σw² / (Σw)²
    n_eff = float(np.sum(w) ** 2 / np.sum(w ** 2))
    run2 = obs.get("run_sd_bar", 0.0) ** 2 + (obs.get("run_rel", 0.0) * charge_bar) ** 2
    var = 1.0 / np.sum(w)
    spread = float(np.sum(w * (m - mean) ** 2) / np.sum(w))
    if len(rows) > 1 and run2 > 0.0:
        # the run term holds the runs' spread about their mean (dt-core divides it by
        # `runs_averaged`), unless they spread far more than it and their reversals explain:
        # then their spread is added as without one, and named
        chi2_runs = float(np.sum((m - mean) ** 2 / (1.0 / w + run2)))
        if chi2_runs > chi2_dist.ppf(0.999, len(rows) - 1):
            var += spread
            log.warning("%s: the %d runs read %s bar: further apart than their reversals and the calibration's "
                        "run-to-run error (±%.2f bar) allow (χ² %.1f on %d degrees of freedom): their spread is "
                        "added to the reading's sd; is the charge the same in each?",
                        ", ".join(str(p) for p, _, _ in rows), len(rows), " / ".join(f"{x:.2f}" for x in m),
                        np.sqrt(run2), chi2_runs, len(rows) - 1)
    elif len(rows) > 1:
        # no run term in the calibration: their spread about the mean stands in for it
        var += spread
    # the stroke's ends apart, averaged with the same weights (dt-core UnitBaseline::split_bar);
    # None when a run has no split (no `stroke_ends`, or an end never read)
    split = float(np.sum(w * splits) / np.sum(w)) if np.all(np.isfinite(splits)) else None
    return {"read_bar": mean, "read_sd_bar": float(np.sqrt(var)), "runs_effective": n_eff, "ranges": ranges,
            "split_bar": split,
            "runs": [{"file": Path(p).name, "read_bar": x, "read_sd_bar": float(np.sqrt(v)), "drift_sd_bar": d}
                     for (p, x, v), (_, _, d) in zip(rows, reads)]}


def own_reversals(rev: dict[str, np.ndarray], obs: dict[str, Any]) -> int:
    """How many of ``rev``'s used reversals lie at an excitation with a model of its own
    (dt-core ``ObserverParams::own_excitation``)."""
    x = obs.get("excitations") or {}
    own = [c for c, o in zip(obs["accel_clusters_mps2"], x.get("own", [False] * 4)) if o and c > 0]
    a = np.abs(np.asarray(rev["accel_mps2"]))[np.asarray(rev["used"]) == 1.0]
    return int(sum(np.count_nonzero(np.abs(a - c) <= obs["accel_cluster_rel"] * c) for c in own))


def used_accel_range(rev: dict[str, np.ndarray]) -> list[float] | None:
    """The smallest and largest ``|ÿ_r|`` of ``rev``'s used reversals, m/s² (dt-core
    ``ChargeObserver::used_accel_range``); None when none was used."""
    a = np.abs(np.asarray(rev["accel_mps2"]))[np.asarray(rev["used"]) == 1.0]
    return [float(a.min()), float(a.max())] if len(a) else None


class BaselineRead(NamedTuple):
    """One run's reading of a unit for a baseline (``_baseline_read``); a tuple, so callers that
    take only its first fields unpack them with ``*_`` after."""

    read_bar: float | None  # the reading at the last excited tick; None: no excited tick
    sd_bar: float  # the observer's reported sd there
    drift_bar: float  # RMS of the reading's departure from it over the settled ticks
    own: int  # reversals read at an excitation with a model of its own
    span: list[float] | None  # |ÿ_r| range of the used reversals, m/s²
    split_bar: float  # the stroke's ends apart at the end of the run (NaN: none)


def _baseline_read(args: tuple[str, dict[str, Any]]) -> BaselineRead:
    path, physics = args
    rev = shocktwin.charge_reversals(path, physics)
    own, span, split = own_reversals(rev, physics["observer"]), used_accel_range(rev), float(rev["ends_split_bar"])
    lg = shocktwin.read_log(path)
    x, cols, t = shocktwin.features(lg, physics, ["observer"])
    onset = rest_end_s(Run(path=Path(path), log=lg, run_id="", asset_id="", label_bar=None, frequency_hz=None))
    end = excitation_end_s(lg, float(t[-1]))
    idx = np.nonzero((t >= onset) & (t <= end))[0]
    if len(idx) == 0:
        return BaselineRead(None, float("nan"), float("nan"), own, span, split)
    i = idx[-1]
    mean = x[:, cols.index("observer_bar")]
    # how far the reading wanders at this constant charge, at the ticks a score would count
    scored = idx[t[idx] >= onset + BASELINE_SETTLE_S]
    drift = float(np.sqrt(np.mean((mean[scored] - mean[i]) ** 2))) if len(scored) else 0.0
    return BaselineRead(float(x[i, cols.index("observer_bar")]), float(x[i, cols.index("observer_sd_bar")]), drift,
                        own, span, split)


def away(a: Sequence[float], b: Sequence[float], rel: float) -> bool:
    """Whether the ``|ÿ_r|`` range ``b`` reaches outside range ``a`` by more than ``rel`` of its ends
    (the band of the calibration's excitations, ``accel_cluster_rel``): two runs at different
    excitations."""
    return b[0] < a[0] * (1.0 - rel) or b[1] > a[1] * (1.0 + rel)


def ln_distance(base: Sequence[float], other: Sequence[float]) -> float:
    """The largest distance in ``ln |ÿ_r|`` of reversals spanning ``other`` from a baseline read
    over ``base`` (dt-core ``UnitBaseline::ln_distance``), 0 inside it."""
    return max(0.0, float(np.log(base[0] / other[0])), float(np.log(other[1] / base[1])))


def transfer_spread(physics: dict[str, Any], units: Sequence[Sequence[Path]], charge_bar: float,
                jobs: int = 2) -> dict[str, Any]:
    """How far a unit's error moves between excitations of the shared model (dt-core
    ``ObserverParams::transfer_bar_per_ln_accel``): each unit's runs at ``charge_bar`` read as a
    baseline would be (every reversal, the reading at the last excited tick, no baseline applied),
    and for every pair of one unit's runs whose excitations lie apart (either run's ``|ÿ_r|`` range
    outside the other's band), the difference of their errors. A baseline read on one and used on
    the other is off by that difference, which no interval held before. Each difference is
    modelled as ``d_i ~ N(0, (κ L_i)² + n_i² + 2R²)``: ``L_i`` the runs' distance in ``ln |ÿ_r|`` (as the
    observer measures it, averaged over the two ways round), ``n_i`` the two readings' own noise
    (their variance from the reversals and the held model's, less the unit's systematic part: already
    in the baseline's and the reading's intervals); ``κ`` is its maximum-likelihood value (zero mean: a shift shared by the
    units is part of what a baseline misses). A run the observer barely read (a large ``n_i``) then
    weighs little, where the plain RMS (reported beside it) takes its difference in full. ``R`` is
    each run's own error at ``charge_bar`` (``run_sd_bar``, ``run_rel``: measure it with
    ``run_spread`` first; 0 without), which the interval carries apart. Needs
    units other than the calibration's: its one unit cannot say how units differ."""
    obs = physics["observer"]
    if obs.get("baseline"):
        raise SystemExit("the physics carries a unit baseline: give the model's own")
    physics = {**physics, "observer": {**obs, "fit_gain_floor": 0.0, "transfer_bar_per_ln_accel": 0.0}}
    flat = [(u, Path(p)) for u, runs in enumerate(units) for p in runs]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        reads = list(pool.map(_baseline_read, [(str(p), physics) for _, p in flat]))
    band = obs["accel_cluster_rel"]
    per_unit: dict[int, list[dict[str, Any]]] = {}
    for (u, path), (m, sd, _drift, own, span, _split) in zip(flat, reads):
        if m is None or span is None:
            raise SystemExit(f"{path}: no reversal read: no transfer from it")
        if own:
            raise SystemExit(f"{path}: {own} of its reversals were read at an excitation with a model of its own, "
                             "where no baseline applies: give runs at the shared model's excitations")
        noise2 = reading_var(obs, m, sd, floor=0.0)
        per_unit.setdefault(u, []).append({"file": path.name, "error_bar": m - charge_bar,
                                           "noise_sd_bar": float(np.sqrt(noise2)), "accel_range_mps2": span})
    pairs = []
    for u, rows in per_unit.items():
        for i in range(len(rows)):
            for j in range(i + 1, len(rows)):
                a, b = rows[i], rows[j]
                ra, rb = a["accel_range_mps2"], b["accel_range_mps2"]
                if away(ra, rb, band) or away(rb, ra, band):
                    pairs.append({"unit": u, "runs": [a["file"], b["file"]],
                                  "difference_bar": b["error_bar"] - a["error_bar"],
                                  "ln_distance": 0.5 * (ln_distance(ra, rb) + ln_distance(rb, ra)),
                                  "noise_sd_bar": float(np.hypot(a["noise_sd_bar"], b["noise_sd_bar"]))})
    if len(pairs) < 2:
        raise SystemExit(f"{len(pairs)} pair(s) of runs at different excitations: give at least two units, "
                         "each with runs at two excitations")
    d = np.array([p["difference_bar"] for p in pairs])
    n = np.array([p["noise_sd_bar"] for p in pairs])
    ln_d = np.array([p["ln_distance"] for p in pairs])
    # each run's own error (`run-spread`), when measured: not the excitation's
    run2 = 2.0 * (obs.get("run_sd_bar", 0.0) ** 2 + (obs.get("run_rel", 0.0) * charge_bar) ** 2)

    def nll(log_kappa: float) -> float:
        v = (np.exp(log_kappa) * ln_d) ** 2 + n ** 2 + run2
        return float(0.5 * np.sum(np.log(v) + d ** 2 / v))

    best = minimize_scalar(nll, bounds=(np.log(1e-3), np.log(50.0)), method="bounded", options={"xatol": 1e-6})
    return {"transfer_bar_per_ln_accel": float(np.exp(best.x)), "rms_bar": float(np.sqrt(np.mean(d ** 2))),
            "mean_bar": float(np.mean(d)),
            "noise_rms_bar": float(np.sqrt(np.mean(n ** 2))), "units": len(per_unit), "pairs": pairs,
            "charge_bar": float(charge_bar),
            # the run term it was measured beside: `run-spread` after it makes it stale
            "run_sd_bar": float(obs.get("run_sd_bar", 0.0)), "run_rel": float(obs.get("run_rel", 0.0))}


def run_spread(physics: dict[str, Any], takes: Sequence[tuple[float, Path, Path]], unit_law: bool = False,
               jobs: int = 2) -> dict[str, Any]:
    """A baselined unit's run-to-run error (dt-core ``ObserverParams::run_sd_bar``), from takes
    ``(charge, A, B)``: two runs of one unit at one known charge and one excitation. Each take is
    read as a baseline and a later run would be: the baseline from ``A`` (with ``unit_law``, the
    calibration's law refitted on ``A`` first, as ``baseline --unit-law`` does), ``B`` read with
    the same law. Their difference at the last excited tick, ``d_i = e_B − e_A``, is what a later
    run at the baseline's own charge would miss by (where the baseline's reading outweighs the
    unit's prior, as it does at its charge); the interval already holds ``n_i² =`` A's
    reading variance (its reversals and its drift, as ``baseline`` reports it) plus B's own
    (its reversals). Each is modelled as ``d_i ~ N(0, n_i² + 2R(p_i)²)`` with ``R(p)² = R₀² +
    (r p)²`` (each run carries its own; ``r``: what grows with the charge, as a gas temperature
    read off from run to run does), and ``R₀²``, ``r²`` ≥ 0 are their maximum-likelihood values,
    as ``transfer_spread`` does for ``κ`` (which assumes no ``R``). Takes at one charge cannot
    tell the two apart: then ``r`` is 0. Needs units other than the calibration's, with takes of
    their own run conditions."""
    obs = physics["observer"]
    if obs.get("baseline"):
        raise SystemExit("the physics carries a unit baseline: give the model's own")
    physics = {**physics, "observer": {**obs, "fit_gain_floor": 0.0, "run_sd_bar": 0.0, "run_rel": 0.0}}
    with law_pool(jobs) as pool:
        got = list(progress(pool.map(_take_read, [(c, str(a), str(b), physics, unit_law) for c, a, b in takes]),
                            total=len(takes), desc="takes"))
    band = obs["accel_cluster_rel"]
    pairs = []
    for (charge, a, b), reads in zip(takes, got):
        rows = []
        for path, (m, sd, drift, own, span, _split) in zip((a, b), reads):
            if m is None or span is None:
                raise SystemExit(f"{path}: no reversal read: no run spread from it")
            if own:
                raise SystemExit(f"{path}: {own} of its reversals were read at an excitation with a model of its "
                                 "own, where no baseline applies: give runs at the shared model's excitations")
            rows.append((m, reading_var(obs, m, sd), drift, span))
        (ma, va, da, ra), (mb, vb, _, rb) = rows
        if np.sqrt(va + da ** 2) > BASELINE_MAX_SD_SHARE * obs["prior_sd_bar"]:
            raise SystemExit(f"{a}: the observer used (almost) no reversals (reading {ma:.2f} ± "
                             f"{np.sqrt(va + da ** 2):.2f} bar from its reversals alone): no baseline from it")
        if away(ra, rb, band) or away(rb, ra, band):
            raise SystemExit(f"{a} and {b}: read at different excitations (|ÿ| {ra[0]:.1f}-{ra[1]:.1f} and "
                             f"{rb[0]:.1f}-{rb[1]:.1f} m/s²): a take is two runs at one excitation "
                             "(between excitations: `transfer`)")
        pairs.append({"runs": [Path(a).name, Path(b).name], "charge_bar": float(charge),
                      "error_a_bar": ma - charge, "error_b_bar": mb - charge, "difference_bar": mb - ma,
                      "noise_sd_bar": float(np.sqrt(va + da ** 2 + vb))})
    d = np.array([p["difference_bar"] for p in pairs])
    n = np.array([p["noise_sd_bar"] for p in pairs])
    r0, r_rel = fit_run_spread(d, n, np.array([p["charge_bar"] for p in pairs]))
    return {"run_sd_bar": r0, "run_rel": r_rel, "rms_bar": float(np.sqrt(np.mean(d ** 2))),
            "mean_bar": float(np.mean(d)), "noise_rms_bar": float(np.sqrt(np.mean(n ** 2))), "unit_law": unit_law,
            "charges_bar": sorted({p["charge_bar"] for p in pairs}), "pairs": pairs}


def fit_run_spread(d: np.ndarray, n: np.ndarray, charges: np.ndarray) -> tuple[float, float]:
    """``(R₀, r)`` of ``run_spread``: the maximum-likelihood ``R₀², r² ≥ 0`` of ``d_i ~ N(0, n_i² +
    2(R₀² + r² p_i²))``; ``r`` = 0 when every take is at one charge (nothing tells the two apart)."""
    p2 = np.square(charges)
    both = len(set(p2.tolist())) > 1

    g = np.stack([np.ones_like(p2), p2])

    def nll(x: np.ndarray) -> tuple[float, np.ndarray]:
        """The negative log-likelihood at ``x = [R₀², r²]`` and its gradient (∂v/∂x = 2g)."""
        v = n ** 2 + 2.0 * (x[0] + x[1] * p2)
        return float(0.5 * np.sum(np.log(v) + d ** 2 / v)), g @ (1.0 / v - d ** 2 / v ** 2)

    # R₀² and r² in units that keep them near 1 for the optimiser
    scale = np.array([np.mean(n ** 2), np.mean(n ** 2) / np.mean(p2) if both else 0.0])

    def scaled(y: np.ndarray) -> tuple[float, np.ndarray]:
        f, grad = nll(y * scale)
        return f, grad * scale

    best = minimize(scaled, np.array([0.5, 0.5 if both else 0.0]), jac=True, method="L-BFGS-B",
                    bounds=[(0.0, None), (0.0, None if both else 0.0)], options={"ftol": 1e-15, "gtol": 1e-12})
    # L-BFGS-B's line search can stop at these tolerances at the maximum itself ("ABNORMAL"):
    # what decides is whether the score vanishes there (or points out of a bound it rests on)
    x = best.x * scale
    _, score = nll(x)
    v = n ** 2 + 2.0 * (x[0] + x[1] * p2)
    tol = 1e-6 * np.sum(1.0 / v) * np.array([1.0, np.mean(p2)])
    at_bound = best.x <= 1e-10
    free, held = ~at_bound & np.array([True, both]), at_bound & np.array([True, both])
    if not (np.all(np.abs(score[free]) <= tol[free]) and np.all(score[held] >= -tol[held])):
        raise SystemExit(f"run spread: the likelihood's maximum was not found ({best.message}; score {score} at "
                         f"R₀² {x[0]:.3g}, r² {x[1]:.3g})")
    r0, r_rel = np.sqrt(x)
    return float(r0), float(r_rel)


def unit_spread(physics: dict[str, Any], units: Sequence[Sequence[tuple[float, Path]]],
                jobs: int = 2) -> dict[str, Any]:
    """The unit-to-unit spread of the observer's systematic error (dt-core
    ``ObserverParams::systematic_sd_bar`` ``S`` and ``systematic_rel`` ``ρ``), from units other
    than the calibration's, each run at a known charge and read as a unit without a baseline
    (every reversal, the reading at the last excited tick: ``_baseline_read``).

    dt-core models that error as ``e(p) = u_f + u_s p``, ``u_f ~ N(0, S²)`` (the unit's friction
    offset and the calibration's own error) and ``u_s ~ N(0, ρ²)`` (its relative seal gain), and
    adds ``S² + (ρ p̂)²`` to every unit's interval until a baseline conditions them; ``fit`` sets
    them from the calibration unit's leave-one-run-out error and an assumed tolerance
    (``--unit-tolerance-pct``). Here they are measured: unit ``u``'s errors ``e_u = m_u − p_u`` at
    its charges ``p_u`` are ``N(0, C_u)`` with ``C_u = diag(n_u² + R(p_u)²) + S² 1 1ᵀ + ρ² p_u
    p_uᵀ`` (``n``: each reading's own noise, its variance less the systematic part it carries;
    ``R``: a run's own error, ``run_sd_bar`` and ``run_rel``, when measured), and ``S², ρ² ≥ 0``
    are their maximum-likelihood values (zero mean: a shift every unit shares is part of what an
    interval without a baseline must hold). A unit read at two charges tells its own offset from
    its gain; units at one charge each still tell them apart across charges."""
    obs = physics["observer"]
    if obs.get("baseline"):
        raise SystemExit("the physics carries a unit baseline: give the model's own")
    physics = {**physics, "observer": {**obs, "fit_gain_floor": 0.0}}
    flat = [(u, c, Path(p)) for u, runs in enumerate(units) for c, p in runs]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        reads = list(progress(pool.map(_baseline_read, [(str(p), physics) for _, _, p in flat]),
                              total=len(flat), desc="runs"))
    r0, r_rel = obs.get("run_sd_bar", 0.0), obs.get("run_rel", 0.0)
    rows = []
    for (u, charge, path), (m, sd, _drift, own, _span, _split) in zip(flat, reads):
        if m is None:
            raise SystemExit(f"{path}: no excited tick: no unit spread from it")
        if own:
            raise SystemExit(f"{path}: {own} of its reversals were read at an excitation with a model of its own "
                             "(whose interval this term does not set): give runs at the shared model's excitations")
        # a run the observer barely read (a reading near its prior) carries its own wide noise and
        # so weighs little: kept, not refused
        noise2 = reading_var(obs, m, sd)
        rows.append({"unit": u, "file": path.name, "charge_bar": float(charge), "error_bar": m - charge,
                     "noise_sd_bar": float(np.sqrt(noise2 + r0 ** 2 + (r_rel * charge) ** 2))})
    if len({r["charge_bar"] for r in rows}) < 2:
        raise SystemExit("every run is at one charge: an offset cannot be told from a gain; give units at two or "
                         "more charges")
    groups = [[r for r in rows if r["unit"] == u] for u in range(len(units))]
    s_bar, s_rel = fit_unit_spread([(np.array([r["error_bar"] for r in g]), np.array([r["noise_sd_bar"] for r in g]),
                                     np.array([r["charge_bar"] for r in g])) for g in groups])
    e = np.array([r["error_bar"] for r in rows])
    return {"systematic_sd_bar": s_bar, "systematic_rel": s_rel, "units": len(units), "runs": rows,
            "rms_bar": float(np.sqrt(np.mean(e ** 2))), "mean_bar": float(np.mean(e)),
            "noise_rms_bar": float(np.sqrt(np.mean([r["noise_sd_bar"] ** 2 for r in rows]))),
            "charges_bar": sorted({r["charge_bar"] for r in rows}),
            # what `fit` had set, from the calibration unit and the assumed tolerance
            "replaced": {"systematic_sd_bar": float(obs["systematic_sd_bar"]),
                         "systematic_rel": float(obs["systematic_rel"])},
            "run_sd_bar": float(r0), "run_rel": float(r_rel)}


def fit_unit_spread(units: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[float, float]:
    """``(S, ρ)`` of ``unit_spread``: the maximum-likelihood ``S², ρ² ≥ 0`` of ``e_u ~ N(0, diag(n_u²)
    + S² 1 1ᵀ + ρ² p_u p_uᵀ)`` over units ``(e_u, n_u, p_u)``, with the analytic score
    ``½ Σ_u tr(C⁻¹ ∂C) − e C⁻¹ ∂C C⁻¹ e``; accepted where the score vanishes (or points out of
    a bound it rests on), as ``fit_run_spread`` is."""
    p2_mean = float(np.mean(np.concatenate([p ** 2 for _, _, p in units])))
    n2_mean = float(np.mean(np.concatenate([n ** 2 for _, n, _ in units])))
    e2_mean = float(np.mean(np.concatenate([e ** 2 for e, _, _ in units])))
    # S² and ρ² in units that keep them near 1 for the optimiser
    scale = np.array([max(e2_mean, n2_mean, 1e-6), max(e2_mean, n2_mean, 1e-6) / p2_mean])

    def nll(x: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = 0.0, np.zeros(2)
        for e, n, p in units:
            one = np.ones_like(p)
            c = np.diag(n ** 2) + x[0] * np.outer(one, one) + x[1] * np.outer(p, p)
            ci = np.linalg.inv(c)
            a = ci @ e
            f += 0.5 * (np.linalg.slogdet(c)[1] + e @ a)
            for k, v in enumerate((one, p)):
                g[k] += 0.5 * (v @ ci @ v - (v @ a) ** 2)
        return float(f), g

    # the score's size: its terms' own, so that a vanishing score is judged relative to them
    tol = 1e-6 * np.array([sum(len(e) for e, _, _ in units) / scale[0]] * 2) * np.array([1.0, p2_mean])
    return spread_by_likelihood(nll, scale, tol, "unit spread")


def spread_by_likelihood(nll: Any, scale: np.ndarray, tol: np.ndarray, what: str) -> tuple[float, float]:
    """``(S, ρ)``, the square roots of the variances ``x = [S², ρ²] ≥ 0`` that minimise ``nll(x)`` (its
    value and gradient), found by L-BFGS-B in units of ``scale`` (which keep them near 1) and
    accepted where the score vanishes (``|∂nll| ≤ tol``) or points out of a bound it rests on:
    L-BFGS-B's line search can stop at these tolerances at the maximum itself ("ABNORMAL"), and what
    decides is the score. Otherwise refused, naming ``what``."""

    def scaled(y: np.ndarray) -> tuple[float, np.ndarray]:
        f, grad = nll(y * scale)
        return f, grad * scale

    best = minimize(scaled, np.array([0.5, 0.5]), jac=True, method="L-BFGS-B", bounds=[(0.0, None), (0.0, None)],
                    options={"ftol": 1e-15, "gtol": 1e-12})
    x = best.x * scale
    _, score = nll(x)
    at_bound = best.x <= 1e-10
    if not (np.all(np.abs(score[~at_bound]) <= tol[~at_bound]) and np.all(score[at_bound] >= -tol[at_bound])):
        raise SystemExit(f"{what}: the likelihood's maximum was not found ({best.message}; score {score} at "
                         f"S² {x[0]:.3g}, ρ² {x[1]:.3g})")
    s, rho = np.sqrt(x)
    return float(s), float(rho)


def own_law_spread(physics: dict[str, Any], units: Sequence[Sequence[tuple[float, Path]]],
                   jobs: int = 2) -> dict[str, Any]:
    """The prior on a unit's error when it is read with its own damping law (dt-core
    ``ObserverParams::own_law_spread``), from units other than the calibration's, each run at a
    known charge, as one-charge baselines are used: for every ordered pair of a unit's runs at
    different charges ``(A, B)``, the calibration's law is refitted on ``A`` (as ``baseline
    --unit-law`` does), and ``A`` and ``B`` are read with it (``_take_read``). ``A``'s error is the
    baseline's, ``e_A``, with the variance a baseline carries (its reversals, its drift and
    ``R(p_A)²``); ``B``'s, ``e_B``, is what the baselined unit is later scored by (its reversals
    and ``R(p_B)²``).

    The law fitted on ``A``'s own windows reads ``A`` in sample and ``B`` out of it, so the two
    errors need not spread as readings with the calibration's law do (``unit_spread``). What a
    baseline must get right is ``e_B`` given ``e_A``: under dt-core's model (``e = u_f + u_s p``,
    ``u_f ~ N(0, S²)``, ``u_s ~ N(0, ρ²)``) that is normal with the mean and variance of its
    ``UnitCorrection``'s update, and ``S², ρ² ≥ 0`` are the maximum of the product of those
    conditional densities over the pairs (``fit_own_law_spread``; a composite likelihood: a
    unit's two directions are not independent, which leaves the estimate consistent and its
    sampling error larger than one pair per unit would give)."""
    obs = physics["observer"]
    if obs.get("baseline"):
        raise SystemExit("the physics carries a unit baseline: give the model's own")
    physics = {**physics, "observer": {**obs, "fit_gain_floor": 0.0}}
    pairs = [(u, ca, a, cb, b) for u, runs in enumerate(units) for ca, a in runs for cb, b in runs if ca != cb]
    if not pairs:
        raise SystemExit("no unit has runs at two different charges: a unit read with its own law at one known "
                         "charge is scored at another")
    with law_pool(jobs) as pool:
        got = list(progress(pool.map(_take_read, [(ca, str(a), str(b), physics, True) for _, ca, a, _, b in pairs]),
                            total=len(pairs), desc="pairs"))
    sys2, rel = obs["systematic_sd_bar"] ** 2, obs["systematic_rel"]
    run2 = lambda p: obs.get("run_sd_bar", 0.0) ** 2 + (obs.get("run_rel", 0.0) * p) ** 2  # noqa: E731
    rows = []
    for (u, ca, a, cb, b), reads in zip(pairs, got):
        (ma, sda, da, own_a, *_), (mb, sdb, _, own_b, *_) = reads
        for path, m, own in ((a, ma, own_a), (b, mb, own_b)):
            if m is None:
                raise SystemExit(f"{path}: no excited tick: no own-law spread from it")
            if own:
                raise SystemExit(f"{path}: {own} of its reversals were read at an excitation with a model of its own, "
                                 "where no baseline applies: give runs at the shared model's excitations")
        na2 = reading_var(obs, ma, sda) + da ** 2 + run2(ca)
        if np.sqrt(na2) > BASELINE_MAX_SD_SHARE * obs["prior_sd_bar"]:
            raise SystemExit(f"{a}: the observer used (almost) no reversals with the unit's law (reading {ma:.2f} ± "
                             f"{np.sqrt(na2):.2f} bar from its reversals alone): no baseline from it")
        nb2 = reading_var(obs, mb, sdb) + run2(cb)
        rows.append({"unit": u, "baseline": Path(a).name, "baseline_charge_bar": float(ca),
                     "baseline_error_bar": ma - ca, "baseline_noise_sd_bar": float(np.sqrt(na2)),
                     "scored": Path(b).name, "charge_bar": float(cb), "error_bar": mb - cb,
                     "noise_sd_bar": float(np.sqrt(nb2))})
    cols = {k: np.array([r[k] for r in rows]) for k in rows[0] if k not in ("baseline", "scored")}
    x = (cols["baseline_charge_bar"], cols["baseline_error_bar"], cols["baseline_noise_sd_bar"] ** 2,
         cols["charge_bar"], cols["error_bar"], cols["noise_sd_bar"] ** 2)
    s_bar, s_rel = fit_own_law_spread(*x)
    z = {}
    for name, (s, r) in (("own_law", (s_bar, s_rel)), ("systematic", (np.sqrt(sys2), rel))):
        m, v = own_law_predictive(s * s, r * r, *x)[:2]
        z[name] = float(np.sqrt(np.mean((cols["error_bar"] - m) ** 2 / v)))
    return {"sd_bar": s_bar, "rel": s_rel, "units": len({r["unit"] for r in rows}), "pairs": rows,
            "charges_bar": sorted({r["charge_bar"] for r in rows}),
            # the scored errors ÷ their predictive sd (RMS) under the measured prior, and under the
            # spread of readings with the calibration's law (what the baselines used before)
            "z_rms": z["own_law"], "z_rms_with_systematic": z["systematic"],
            "systematic_sd_bar": float(np.sqrt(sys2)), "systematic_rel": float(rel)}


def own_law_predictive(s2: float, r2: float, pa: np.ndarray, ea: np.ndarray, na2: np.ndarray, pb: np.ndarray,
                       eb: np.ndarray, nb2: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, ...]]]:
    """The mean and variance of ``e_B`` given a baseline ``e_A`` (``own_law_spread``) under the prior
    ``S² = s2``, ``ρ² = r2``, and their derivatives by ``(S², ρ²)``: ``[(∂m, ∂v)]``. The joint
    covariance is ``c_aa = S² + ρ² p_A² + n_A²``, ``c_ab = S² + ρ² p_A p_B``, ``c_bb = S² + ρ² p_B² +
    n_B²``; the conditional ``m = c_ab e_A / c_aa``, ``v = c_bb − c_ab² / c_aa``: dt-core's
    ``UnitCorrection`` for one reading, in the errors' own terms."""
    caa, cab, cbb = s2 + r2 * pa * pa + na2, s2 + r2 * pa * pb, s2 + r2 * pb * pb + nb2
    m, v = cab * ea / caa, cbb - cab * cab / caa
    grads = []
    for d_aa, d_ab, d_bb in ((1.0, 1.0, 1.0), (pa * pa, pa * pb, pb * pb)):
        dm = ea * (d_ab * caa - cab * d_aa) / caa ** 2
        dv = d_bb - (2.0 * cab * d_ab * caa - cab * cab * d_aa) / caa ** 2
        grads.append((dm, dv))
    return m, v, grads


def fit_own_law_spread(pa: np.ndarray, ea: np.ndarray, na2: np.ndarray, pb: np.ndarray, eb: np.ndarray,
                       nb2: np.ndarray) -> tuple[float, float]:
    """``(S, ρ)`` of ``own_law_spread``: the ``S², ρ² ≥ 0`` that maximise ``Π N(e_B; m, v)``
    (``own_law_predictive``), with the analytic score; accepted where the score vanishes (or
    points out of a bound it rests on), as ``fit_unit_spread`` is."""
    e2 = float(np.mean(np.concatenate([ea ** 2, eb ** 2, na2, nb2])))
    p2 = float(np.mean(np.concatenate([pa ** 2, pb ** 2])))
    scale = np.array([max(e2, 1e-6), max(e2, 1e-6) / p2])

    def nll(x: np.ndarray) -> tuple[float, np.ndarray]:
        m, v, grads = own_law_predictive(x[0], x[1], pa, ea, na2, pb, eb, nb2)
        r = eb - m
        f = 0.5 * float(np.sum(np.log(v) + r * r / v))
        g = np.array([0.5 * float(np.sum(dv / v - r * r * dv / v ** 2 - 2.0 * r * dm / v)) for dm, dv in grads])
        return f, g

    return spread_by_likelihood(nll, scale, 1e-6 * len(eb) / scale, "own-law spread")


def law_pool(jobs: int) -> ProcessPoolExecutor:
    """Worker processes for ``_take_read``, each started from a fresh interpreter (forkserver). A
    unit's law is refitted there, and the fit runs the native module's thread pool
    (``shocktwin.reversal_windows``, on every core); a forked worker inherits that pool's state
    from a parent that used it (``baseline --unit-law`` in the same process) without its threads,
    and waits on them forever."""
    return ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("forkserver"))


def _take_read(args: tuple[float, str, str, dict[str, Any], bool]) -> list[BaselineRead]:
    """One take of ``run_spread``: A's and B's readings (``_baseline_read``), with the law refitted
    on A when asked."""
    charge, a, b, physics, unit_law = args
    if unit_law:
        from train.campaign import read_run
        from train.damping_law import unit_law as refit

        try:
            fit = refit([read_run(Path(a))], physics)
        except (ValueError, OSError) as err:
            raise SystemExit(f"{a}: {err}") from None
        physics = {**physics, "observer": {**physics["observer"], "damping_law": fit["law"]}}
    return [_baseline_read((p, physics)) for p in (a, b)]


def cmd_run_spread(args: argparse.Namespace) -> int:
    physics = calibrated_physics(args.physics)
    if len(args.take) < 2:
        raise SystemExit(f"{len(args.take)} take: give at least two (units, or charges of one unit)")
    takes = []
    for charge, a, b in args.take:
        try:
            c = float(charge)
        except ValueError:
            c = float("nan")
        if not (np.isfinite(c) and c > 0.0):
            raise SystemExit(f"--take {charge} {a} {b}: the charge {charge!r} is not a charge (bar gauge, above 0)")
        for p in (Path(a), Path(b)):
            if not p.is_file():
                raise SystemExit(f"{p}: no such run log")
        if Path(a).resolve() == Path(b).resolve():
            raise SystemExit(f"--take {charge} {a} {b}: one run twice: a take is two runs")
        takes.append((c, Path(a), Path(b)))
    t = run_spread(physics, takes, args.unit_law, args.jobs)
    for p in t["pairs"]:
        print(f"{p['runs'][1]} less {p['runs'][0]} at {p['charge_bar']:g} bar: {p['difference_bar']:+.2f} bar "
              f"(the interval's {p['noise_sd_bar']:.2f})")
    one = len(t["charges_bar"]) == 1
    print(f"run spread: ±{t['run_sd_bar']:.3f} bar" + (" (one charge: nothing proportional to it measured)" if one
                                                      else f" + {100 * t['run_rel']:.2f} % of the charge")
          + f" per run (maximum likelihood beside the readings' own noise, RMS {t['noise_rms_bar']:.2f}) over "
          f"{len(t['pairs'])} take(s); the differences' RMS {t['rms_bar']:.2f}, mean {t['mean_bar']:+.2f}"
          f"{'; law refitted on each first take' if args.unit_law else ''}")
    physics["observer"]["run_sd_bar"] = t["run_sd_bar"]
    physics["observer"]["run_rel"] = t["run_rel"]
    if physics["observer"].get("transfer_bar_per_ln_accel"):
        was = physics.get("fit", {}).get("observer_transfer", {})
        before = (was.get("run_sd_bar", 0.0), was.get("run_rel", 0.0))
        if not np.allclose(before, (t["run_sd_bar"], t["run_rel"]), rtol=1e-9, atol=0.0):
            print(f"warning: the transfer spread in {args.physics} was measured beside a run spread of "
                  f"±{before[0]:.3f} bar + {100 * before[1]:.2f} %, not this one: it counts the difference twice "
                  f"(or not at all); run `python -m train.observer transfer` again on this file", file=sys.stderr)
    return _write_measured(physics, "observer_run_spread", t, args.out or args.physics)


def calibrated_physics(path: Path) -> dict[str, Any]:
    """The physics file at ``path``, refused by name when it holds no calibrated observer."""
    physics = read_json(path)
    if not physics.get("observer"):
        raise SystemExit(f"{path}: no `observer` section: run `python -m train.observer fit` first")
    return physics


def _write_measured(physics: dict[str, Any], key: str, record: dict[str, Any], out: Path) -> int:
    """Writes ``physics`` to ``out`` with ``record`` (a term measured on other units) under
    ``fit.<key>``."""
    physics.setdefault("fit", {})[key] = record | {
        "note": "measured on units other than the calibration's (simulated data when made from shocktwin simulate)"}
    out.write_text(json.dumps(physics, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


def cmd_transfer(args: argparse.Namespace) -> int:
    physics = calibrated_physics(args.physics)
    for p in (p for u in args.unit for p in u):
        if not p.is_file():
            raise SystemExit(f"{p}: no such run log")
    t = transfer_spread(physics, args.unit, args.charge_bar, args.jobs)
    for p in t["pairs"]:
        print(f"unit {p['unit'] + 1}: {p['runs'][1]} less {p['runs'][0]}: {p['difference_bar']:+.2f} bar "
              f"(their noise {p['noise_sd_bar']:.2f}; {p['ln_distance']:.2f} apart in ln|ÿ|)")
    k = t["transfer_bar_per_ln_accel"]
    print(f"transfer spread: ±{k:.3f} bar per unit of ln|ÿ| (±{k * np.log(4.0):.2f} bar from 1 to 2 Hz; maximum "
          f"likelihood beside the readings' own noise, RMS {t['noise_rms_bar']:.2f}) over {len(t['pairs'])} pair(s) of "
          f"{t['units']} unit(s); the differences' RMS {t['rms_bar']:.2f}, mean {t['mean_bar']:+.2f}")
    physics["observer"]["transfer_bar_per_ln_accel"] = k
    return _write_measured(physics, "observer_transfer", t, args.out or args.physics)


def units_of(campaign_dir: Path) -> list[list[tuple[float, Path]]]:
    """A directory's runs as ``unit_spread`` takes them: grouped by unit (the log's ``asset_id``),
    each at its labelled charge; a run without a label is refused by name."""
    runs = load_campaign(campaign_dir).runs
    by_unit: dict[str, list[tuple[float, Path]]] = {}
    for r in runs:
        if r.label_bar is None:
            raise SystemExit(f"{r.path}: no charge label: a unit spread needs each run's known charge")
        by_unit.setdefault(r.asset_id, []).append((float(r.label_bar), r.path))
    return [by_unit[k] for k in sorted(by_unit)]


def cmd_unit_spread(args: argparse.Namespace) -> int:
    physics = calibrated_physics(args.physics)
    if bool(args.unit) == bool(args.campaign):
        raise SystemExit("give the units either as --unit CHARGE=RUN ... (repeat per unit) or as --campaign DIR")
    units = [] if args.unit else units_of(args.campaign)
    for runs in args.unit or []:
        unit = []
        for item in runs:
            charge, sep, path = item.partition("=")
            try:
                c = float(charge)
            except ValueError:
                c = float("nan")
            if not sep or not (np.isfinite(c) and c > 0.0):
                raise SystemExit(f"--unit {item}: not CHARGE=RUN with a charge in bar gauge above 0")
            if not Path(path).is_file():
                raise SystemExit(f"{path}: no such run log")
            unit.append((c, Path(path)))
        units.append(unit)
    if len(units) < 2:
        raise SystemExit(f"{len(units)} unit: give at least two (each --unit one unit's runs)")
    if args.unit_law:
        return own_law_command(args, physics, units)
    t = unit_spread(physics, units, args.jobs)
    for r in t["runs"]:
        print(f"unit {r['unit'] + 1}: {r['file']} at {r['charge_bar']:g} bar: {r['error_bar']:+.2f} bar "
              f"(its reading's own {r['noise_sd_bar']:.2f})")
    was = t["replaced"]
    print(f"unit spread: ±{t['systematic_sd_bar']:.3f} bar + {100 * t['systematic_rel']:.2f} % of the charge "
          f"(maximum likelihood beside the readings' own noise, RMS {t['noise_rms_bar']:.2f}) over {t['units']} "
          f"units; the errors' RMS {t['rms_bar']:.2f}, mean {t['mean_bar']:+.2f}; was ±{was['systematic_sd_bar']:.3f} "
          f"bar + {100 * was['systematic_rel']:.2f} % (the calibration unit and --unit-tolerance-pct)")
    physics["observer"]["systematic_sd_bar"] = t["systematic_sd_bar"]
    physics["observer"]["systematic_rel"] = t["systematic_rel"]
    for key in ("observer_run_spread", "observer_transfer", "observer_own_law_spread"):
        if key in physics.get("fit", {}):
            print(f"warning: {args.physics} holds the {key.removeprefix('observer_').replace('_', ' ')} measured "
                  "beside the old unit spread, whose noise it took its readings' less: run it again on this file",
                  file=sys.stderr)
    return _write_measured(physics, "observer_unit_spread", t, args.out or args.physics)


def own_law_command(args: argparse.Namespace, physics: dict[str, Any], units: list[list[tuple[float, Path]]]) -> int:
    """``unit-spread --unit-law``: ``own_law_spread`` measured and written as the physics'
    ``observer.own_law_spread``."""
    t = own_law_spread(physics, units, args.jobs)
    for r in t["pairs"]:
        print(f"unit {r['unit'] + 1}: its own law from {r['baseline']} ({r['baseline_error_bar']:+.2f} bar at "
              f"{r['baseline_charge_bar']:g}); {r['scored']} at {r['charge_bar']:g} bar: {r['error_bar']:+.2f} bar "
              f"(its reading's own {r['noise_sd_bar']:.2f})")
    print(f"own-law spread: ±{t['sd_bar']:.3f} bar + {100 * t['rel']:.2f} % of the charge (maximum likelihood of "
          f"each scored error given its baseline) over {len(t['pairs'])} pairs of {t['units']} units; scored errors ÷ "
          f"their sd RMS {t['z_rms']:.2f}, {t['z_rms_with_systematic']:.2f} with the unit spread "
          f"(±{t['systematic_sd_bar']:.3f} bar + {100 * t['systematic_rel']:.2f} %) as the prior")
    physics["observer"]["own_law_spread"] = {"sd_bar": t["sd_bar"], "rel": t["rel"]}
    return _write_measured(physics, "observer_own_law_spread", t, args.out or args.physics)


def cmd_baseline(args: argparse.Namespace) -> int:
    physics = calibrated_physics(args.physics)
    for flag, c in (("--charge-bar", args.charge_bar), ("--second-charge-bar", args.second_charge_bar)):
        if c is not None and not (np.isfinite(c) and c > 0.0):
            raise SystemExit(f"{flag} {c:g}: not a charge (bar gauge, above 0)")
    for p in args.runs:
        if not p.is_file():
            raise SystemExit(f"{p}: no such run log")
    if (args.second_charge_bar is None) != (not args.second_runs):
        raise SystemExit("--second-charge-bar and --second-runs go together: the unit's runs at a second known charge")
    if args.second_runs and args.second_charge_bar == args.charge_bar:
        raise SystemExit(f"--second-charge-bar {args.second_charge_bar:g} is --charge-bar: a second reading is at "
                         "another charge (give runs at the same charge as more runs)")
    both = {p.resolve() for p in args.runs} & {p.resolve() for p in args.second_runs}
    if both:
        raise SystemExit(f"{', '.join(sorted(str(p) for p in both))}: given at both charges (put --second-runs last, "
                         "or end its list with `--`)")
    for p in args.second_runs:
        if not p.is_file():
            raise SystemExit(f"{p}: no such run log")
    second = (args.second_charge_bar, args.second_runs) if args.second_runs else None
    b = baseline_of(physics, args.runs, args.charge_bar, args.jobs, unit_law=args.unit_law, second=second)
    try:
        text = json.dumps(b, indent=2, allow_nan=False)
    except ValueError:
        raise SystemExit(f"the baseline read from {', '.join(map(str, args.runs))} holds a number that is not finite: "
                         f"not written to {args.out}") from None
    args.out.write_text(text + "\n")
    ob = b["observer_baseline"]
    if "unit_law" in b:
        u = b["unit_law"]
        fmt = lambda d: " / ".join("unread" if d[k] is None else f"{d[k]:.3f}" for k in ("+", "-"))
        print(f"the unit's own damping law from {u['windows']} reversal windows: median residual at the two ends "
              f"of the stroke (ÿ > 0 / ÿ < 0) {fmt(u['residual_before_mps2'])} m/s² with the calibration's law, "
              f"{fmt(u['residual_after_mps2'])} with the unit's")
    runs = b["runs"]
    for k, r in enumerate([ob] + ob.get("other_excitations", [])):
        at = (f" at |ÿ_r| {r['accel_range_mps2'][0]:.2f}–{r['accel_range_mps2'][1]:.2f} m/s²"
              if r.get("accel_range_mps2") else "")
        n_first = sum(1 for x in runs if x.get("excitation", 0) == k and x["charge_bar"] == r["charge_bar"])
        also = ""
        if "second" in r:
            s2 = r["second"]
            n_second = sum(1 for x in runs if x.get("excitation", 0) == k and x["charge_bar"] == s2["charge_bar"])
            also = (f", and {s2['read_bar']:.2f} ± {s2['read_sd_bar']:.2f} bar at a known {s2['charge_bar']:g} bar "
                    f"({n_second} run(s))")
        files = ", ".join(x["file"] for x in runs if x.get("excitation", 0) == k)
        own = " (its own reading)" if k == 0 and "other_excitations" in ob else ""
        print(f"unit baseline{at}: read {r['read_bar']:.2f} ± {r['read_sd_bar']:.2f} bar at a known "
              f"{r['charge_bar']:g} bar ({n_first} run(s)){also}{own}: {files}")
    print(f"wrote {args.out}" + (": one reading per excitation, a run is corrected by the nearest"
                                 if "other_excitations" in ob else ""))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.observer", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fit", help="calibrate the observer's measurement model on a labelled campaign")
    f.add_argument("--campaign", required=True, type=Path)
    f.add_argument("--physics", required=True, type=Path, help="physics.json from train.fit_physics")
    f.add_argument("--out", type=Path, help="physics.json to write (default: --physics, updated)")
    f.add_argument("--datasheet", type=Path, help="the damper's datasheet: TOML as for fit_physics (docs/datasheet.example.toml: geometry; [oil] holds the damping law's viscosity coefficient), or JSON with a_rod_m2 and v_gas_m3")
    f.add_argument("--unit-tolerance-pct", type=float, default=10.0,
                   help="one-sigma unit-to-unit tolerance of the seal friction (datasheet), %%")
    f.add_argument("--jobs", type=int, default=2)
    f.add_argument("--damping", choices=["auto", "law", "linear"], default="auto",
                   help="the window model's damping: a law fitted on the nominal runs' reversal windows, "
                        "linear slopes per window, or (auto) whichever calibrates more excitations, then the "
                        "lower leave-one-run-out error (without the oil's viscosity from a TOML "
                        f"--datasheet, the law only when the nominal runs' windows span {LAW_MIN_TEMP_SPAN_K:.0f} K "
                        "of oil temperature: they measure it)")
    f.add_argument("--window-sd", action="store_true",
                   help="weigh each reversal by its window fit's own sd of the friction amplitude when "
                        "larger than the calibrated one (dt-core ObserverParams::window_sd)")
    f.add_argument("--no-stroke-ends", action="store_true",
                   help="with reversals between excitations, one filter for both ends of the stroke instead "
                        "of one per end, averaged, with their disagreement in the interval (dt-core "
                        "ObserverParams::stroke_ends)")
    f.add_argument("--single-end", action="store_true",
                   help="with the ends apart, let one end read at a calibrated excitation stand alone until "
                        "the other is read (its spread from the warm bins added; dt-core "
                        "ObserverParams::single_end_sd_bar). Off by default: on ten simulated units it called "
                        "`leak` sooner but raised false alarms on nominal runs (docs/history.md)")
    f.add_argument("--no-between", action="store_true",
                   help="with the law, skip reversals between calibrated excitations")
    f.add_argument("--no-held", action="store_true",
                   help="with the law, skip reversals above the shared line's fastest excitation instead of "
                        "reading them with the model held there (dt-core ObserverParams::held_sd_bar; docs/history.md, "
                        "\"Thirtieth session\")")
    f.add_argument("--law-windows", type=int, default=40,
                   help="reversal windows per nominal run the damping law is fitted on")
    f.add_argument("--law-runs", choices=("nominal", "complete"), default="complete",
                   help="the runs the damping law is fitted on: the nominal runs, or (complete, the default) those "
                        "plus, at each excitation frequency they lack, the run of the highest charge (docs/history.md, "
                        "\"Fifty-seventh session\")")
    f.add_argument("--scale-prior-sd", type=float, default=SCALE_PRIOR_SD,
                   help="with a damping law, a prior sd on each window's per-side law scales about 1 "
                        "(dt-core ObserverParams::scale_prior_sd; 0: none)")
    f.add_argument("--no-own-excitations", action="store_true",
                   help="with the damping law: skip the campaign's excitations the shared measurement model does "
                        "not calibrate, instead of fitting each a model of its own (docs/history.md, \"4 Hz, read\")")
    f.add_argument("--fit-gain-floor", type=float, default=FIT_GAIN_FLOOR,
                   help="fit a reversal's window only when one more reading could narrow the reported variance of "
                        "the charge by this share (default %(default)g; 0: fit every reversal; dt-core "
                        "ObserverParams::fit_gain_floor)")
    f.add_argument("--keep-fastest-shared", action="store_true",
                   help="keep the fastest excitation on the shared measurement model even when a model of its own "
                        "reads the calibration runs better: reversals between it and the next excitation are then "
                        "read, and it loses its cavitation bound (docs/history.md, \"Twenty-fourth session\")")
    f.add_argument("--fastest-off-the-line", action="store_true",
                   help="when the fastest excitation gets a model of its own, take it off the shared line too: "
                        "reversals between it and the next excitation are then not read (the twenty-fourth "
                        "session's behaviour; docs/history.md, \"Twenty-fifth session\")")
    f.add_argument("--law-loadcell", choices=("auto", "off"), default="off",
                   help="with --law-form twin-tube: fit the law on the nominal runs' loadcell too (mid-stroke, "
                        "the speeds beyond the reversal windows' reach; auto: when they carry one, off: the "
                        "windows alone; train.damping_law.LoadcellRows)")
    f.add_argument("--law-form", choices=("hinges", "valve", "valves", "twin-tube"), default="twin-tube",
                   help="the damping law's form: hinges at fixed velocities, or those refined with an "
                        "extension valve whose knee sits at a force (docs/history.md, \"The extension valve\"), or a valve "
                        "on either side (docs/history.md, \"Twenty-third session\"), or the compression side as the base "
                        "and piston valves together (the default; docs/history.md, \"Twenty-fourth session\")")
    f.add_argument("--no-rod-scale", action="store_true",
                   help="read each reversal's `ÿ_r` as the accelerometers give it, not scaled against the "
                        "potentiometer to the calibration rig's (dt-core ObserverParams::rod_accel_scale; the "
                        "behaviour before the fifty-first session: a rod-end accelerometer 2 %% low then left half "
                        "of a 12 bar run's windows unfitted, docs/history.md)")
    f.add_argument("--reversal-accel", choices=("velocity-chord", "accelerometers"), default="accelerometers",
                   help="where the velocity slope at a reversal is read: the Kalman velocity's chord over "
                        "±20 ms, or (the default) the rod end's own acceleration from the accelerometers, a1 − a2 (less the "
                        "filter's bias) plus a2 less its running mean, over ±5 ms (dt-core ReversalAccel; docs/history.md, "
                        "\"Twenty-fifth session\")")
    e = sub.add_parser("evaluate", help="score the observer on held-out sets")
    e.add_argument("--physics", required=True, type=Path)
    e.add_argument("--out", required=True, type=Path)
    e.add_argument("--settle-s", type=float, default=60.0, help="score ticks from this long after onset")
    e.add_argument("--jobs", type=int, default=2)
    e.add_argument("--fit-gain-floor", type=float, default=None,
                   help="score with this ObserverParams::fit_gain_floor instead of the physics file's")
    e.add_argument("--baseline", action="append", default=[], metavar="SET=FILE",
                   help="score set SET with this unit baseline (from `baseline`); its own runs are "
                        "not scored")
    e.add_argument("sets", nargs="+", help="NAME=DIR of held-out campaigns")
    b = sub.add_parser("baseline", help="one unit's reading at a known charge (installation, service)")
    b.add_argument("--physics", required=True, type=Path, help="physics.json with a calibrated observer")
    b.add_argument("--charge-bar", required=True, type=float, help="the charge the unit held, bar gauge at 20 °C")
    b.add_argument("--out", required=True, type=Path)
    b.add_argument("--jobs", type=int, default=2)
    b.add_argument("--unit-law", action="store_true",
                   help="refit the calibration's damping law on these runs' reversal windows first and read the "
                        "unit with it from then on (written in the baseline as its `damping_law`)")
    b.add_argument("--second-charge-bar", type=float,
                   help="a second known charge the unit was read at (an end-of-line test at two charges), bar gauge "
                        "at 20 °C: one charge cannot tell the unit's friction offset from its seal gain, two can")
    b.add_argument("--second-runs", nargs="+", type=Path, default=[], metavar="RUN",
                   help="run logs of that unit at --second-charge-bar (it takes every path after it: give it "
                        "after the runs, or end its list with `--`)")
    b.add_argument("runs", nargs="+", type=Path,
                   help="run logs of that unit at that charge; runs at several excitations (say 1 and 2 Hz) give one "
                        "reading each, grouped by their reversals' |ÿ_r| (the calibration's band), the first run's "
                        "the baseline's own and the others its `other_excitations` (up to 4 excitations in all, each "
                        "one the shared measurement model reads): a later run is corrected by the nearest")
    t = sub.add_parser("transfer", help="how far a unit's error moves between excitations, from units other than "
                                        "the calibration's (ObserverParams::transfer_bar_per_ln_accel)")
    t.add_argument("--physics", required=True, type=Path, help="physics.json with a calibrated observer")
    t.add_argument("--charge-bar", required=True, type=float,
                   help="the charge every unit held in these runs, bar gauge at 20 °C")
    t.add_argument("--unit", required=True, action="append", nargs="+", type=Path, metavar="RUN",
                   help="one unit's runs at that charge, at two or more excitations (repeat per unit)")
    t.add_argument("--out", type=Path, help="physics.json to write (default: --physics, updated)")
    t.add_argument("--jobs", type=int, default=2)
    r = sub.add_parser("run-spread", help="a baselined unit's run-to-run error, from repeat takes of units other "
                                          "than the calibration's (ObserverParams::run_sd_bar)")
    r.add_argument("--physics", required=True, type=Path, help="physics.json with a calibrated observer")
    r.add_argument("--take", required=True, action="append", nargs=3, metavar=("CHARGE", "A", "B"),
                   help="one unit's two runs at one known charge (bar gauge at 20 °C) and one excitation, with run "
                        "conditions of their own: the baseline is read from A, B as a later run (repeat per take)")
    r.add_argument("--unit-law", action="store_true",
                   help="refit the damping law on each A first, as `baseline --unit-law` does")
    r.add_argument("--out", type=Path, help="physics.json to write (default: --physics, updated)")
    r.add_argument("--jobs", type=int, default=2)
    us = sub.add_parser("unit-spread", help="the unit-to-unit spread of the observer's error without a baseline, "
                                            "from units other than the calibration's (ObserverParams::"
                                            "systematic_sd_bar, systematic_rel)")
    us.add_argument("--physics", required=True, type=Path, help="physics.json with a calibrated observer")
    us.add_argument("--unit", action="append", nargs="+", metavar="CHARGE=RUN",
                    help="one unit's runs, each at the charge it held (bar gauge at 20 °C), at the shared model's "
                         "excitations (repeat per unit)")
    us.add_argument("--campaign", type=Path, metavar="DIR",
                    help="instead of --unit: a directory of labelled runs, grouped into units by their asset id")
    us.add_argument("--unit-law", action="store_true",
                    help="instead: the prior of a unit read with its own damping law (ObserverParams::"
                         "own_law_spread), each run read as a one-charge baseline with the law refitted on it "
                         "(as `baseline --unit-law`) and the unit's runs at other charges scored with it")
    us.add_argument("--out", type=Path, help="physics.json to write (default: --physics, updated)")
    us.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args(argv)
    if args.cmd == "unit-spread":
        return cmd_unit_spread(args)
    if args.cmd == "run-spread":
        return cmd_run_spread(args)
    if args.cmd == "transfer":
        return cmd_transfer(args)
    if args.cmd == "fit":
        return cmd_fit(args)
    if args.cmd == "baseline":
        return cmd_baseline(args)
    from train.observer_report import cmd_evaluate
    return cmd_evaluate(args)


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
