"""The damping law the charge observer's reversal window needs, measured where the window
looks: on the reversal windows of the nominal runs themselves (no loadcell needed).

The law (dt-core ``charge::DampingLaw``) is a smooth piecewise-linear function of the
stroke velocity ``v`` with a viscous part that thins with the heat::

    L(v, T) = Σ_j (r(T) a_j + b_j) φ_j(v)                                  (N)
    φ_0(v) = v,  φ_j(v) = ±w [sp(±(v − k_j)/w) − sp(∓k_j/w)]   (hinge at knot k_j, sign of k_j)
    r(T) = exp(−β (T_oil − 40 °C)),  sp(x) = ln(1 + eˣ)

fixed knots ``KNOTS_MPS`` on both sides, smoothing width ``WIDTH_MPS``. ``T_oil`` is the
twin's modelled oil temperature, the one the observer uses at run time. The knots are
where a valve may crack or blow off; their slopes are what is fitted, so the law assumes
nothing about how the valves are built.

The valve form (``fit_valve_law_windows``, ``observer fit --law-form valve``, the
default until the twenty-sixth session)
keeps the hinges for compression and makes the extension side a bleed-and-shim valve
(dt-core ``LawValves``), whose knee sits at a force and so moves to a higher velocity as the
oil thins: hinges at fixed velocities cannot follow it, and the 2 Hz windows at the bottom
of the stroke that cross it failed while the oil was cold.

The two-valve form (``fit_valves_law_windows``, ``--law-form valves``) makes the compression
side a valve too. Hinges extrapolate straight beyond their last knot (0.15 m/s), and at 3 Hz
the windows reach 0.4 m/s: with the hinges the law's compression force at 80 °C was 360 N
too strong at −0.2 m/s and 2,080 N at −0.6 (dt-sim's valves, simulated); with a valve, within
80–120 N over the same speeds.

The fit (``fit_law_windows``, scipy ``least_squares``) runs the observer's own window
model (``shocktwin.reversal_window``) on every window at once: the law shared, per window
the friction amplitude, the time shift and the offset; the per-side scales held at 1.
It runs in stages (``fit_law_staged``): the slowest excitation's windows first, then every
window with its friction amplitude held at what those read at its oil temperature, then
everything free. Fitted at once from the linear law, the 2 Hz windows at the top of the
stroke (most of them in compression) settle where the law carries the friction: on the
corrected simulator (dt-sim 0.2.0) they read 15 N of a seal friction of about 50 N, the law
fell a third short of the plant's compression force at −0.06 m/s (−121 against −183 N at
56 °C), and the observer's measurement model leaned on ``|ÿ|`` to make up for it.

The twin-tube form (``fit_twin_law_windows``, ``--law-form twin-tube``, the default) makes the compression
side the two valves a twin-tube damper works at once, base and piston, their forces added at
the same speed (dt-core ``LawValves::compression_piston``). One valve fitted to dt-sim's
compression force at 80 °C within 7 N still left the 3.5 Hz windows of a noise-free run
0.5–0.7 m/s² off (friction amplitude read within 1 N only with the plant's own law); two valves
fitted the same way left 0.13–0.19 and read the 4 Hz amplitude within 2 N, where one valve read
it 10–17 N low.

The data are simulated (``shocktwin simulate``).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Sequence

import numpy as np

import shocktwin

from train.campaign import Run
from train.fit_physics import rest_end_s

log = logging.getLogger("shocktwin.observer")

KNOTS_MPS = [-0.15, -0.09, -0.05, -0.025, 0.025, 0.05, 0.09, 0.15]
WIDTH_MPS = 0.008
N_COEF = len(KNOTS_MPS) + 1
SKIP_AFTER_ONSET_S = 2.0  # the actuator's ramp
BETA_START = 0.02         # 1/K, start of the viscosity coefficient
# Windows the linear law misses by more than this are left out of the law's fit: on the
# simulated dyno those are the 4 Hz runs (0.9–1.0 m/s²: cavitation at the reversal, which
# no damping law of the velocity holds); 2 Hz windows miss by 0.43–0.7.
LAW_WINDOW_MAX_RESIDUAL_MPS2 = 0.8
RIDGE_NSPM, RIDGE_MPS2 = 10_000.0, 0.5  # the hinges' ridge (see ``fit_law_windows``)
BETA_MIN = 0.005          # 1/K: a viscous part that does not thin with the heat is not viscous
# The oil temperature span (K) the nominal windows must cover for `fit --damping auto` to
# consider the law: its viscosity coefficient is measured on that span. The quick
# campaign's 60 s runs heat 20-46 °C and give β = 0.08 /K (the oil's viscosity falling 7x
# over 25 K: unphysical; oils are nearer 0.02), and with that law the leaking unit's trend
# read 0.30 bar/day against 0.5 (tests/python/test_fleet_store.py); the full campaign's
# runs span 20-120 °C. With the coefficient from the datasheet's oil (held, not fitted) no
# span is needed: the quick campaign's law then reads another unit of the model at 2 Hz
# (10.7 and 2.2 bar at a true 12 and 2) where its linear slopes read 4.4 and -13.2
# (docs/history.md, thirty-fourth session).
LAW_MIN_TEMP_SPAN_K = 40.0


def _sp(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, x)


def law_calibrated(obs: dict[str, Any]) -> bool:
    """Whether the observer parameters ``obs`` carry a calibrated damping law (dt-core
    ``DampingLaw::is_calibrated``)."""
    d = obs.get("damping_law") or {}
    if d.get("valves") and d["valves"].get("extension") and d["valves"].get("compression"):
        return True
    slope0 = (d.get("viscous_nspm") or [0.0])[0] + (d.get("dry_nspm") or [0.0])[0]
    return d.get("width_mps", 0.0) > 0 and slope0 != 0


def law(v: np.ndarray, temp_c: np.ndarray | float, d: dict[str, Any]) -> np.ndarray:
    """The damping force (N, extension positive) at stroke velocity ``v`` and oil
    ``temp_c`` for the law dict ``d`` (the fields of dt-core ``DampingLaw``)."""
    v = np.asarray(v, float)
    r = np.exp(-d["beta_per_k"] * (np.asarray(temp_c, float) - 40.0))
    a, b, w = np.asarray(d["viscous_nspm"]), np.asarray(d["dry_nspm"]), d["width_mps"]
    f = (r * a[0] + b[0]) * v
    for j, k in enumerate(d["knots_mps"]):
        c = r * a[j + 1] + b[j + 1]
        if k > 0:
            f = f + c * w * (_sp((v - k) / w) - _sp(-k / w))
        elif k < 0:
            f = f - c * w * (_sp((k - v) / w) - _sp(k / w))
    vs = d.get("valves")
    if vs:  # a side with a valve takes the valve alone (dt-core ``LawValves``)
        if vs.get("extension"):
            f = np.where(v >= 0, valve_force(np.maximum(v, 0.0), r, vs["extension"], vs["knee_n"]), f)
        if vs.get("compression"):
            speed = np.maximum(-v, 0.0)
            comp = valve_force(speed, r, vs["compression"], vs["knee_n"])
            if vs.get("compression_piston"):  # a second valve, its force added at the same speed
                comp = comp + valve_force(speed, r, vs["compression_piston"], vs["knee_n"])
            f = np.where(v < 0, -comp, f)
    return f


def valve_velocity(f: np.ndarray, ratio: np.ndarray | float, valve: dict[str, float],
                   knee_n: float) -> np.ndarray:
    """The velocity (m/s) through one valve of the valve form (dt-core ``LawValve``) at force
    ``f`` ≥ 0 N: the bleed ``F = r a v + b v²`` and the shims ``g ρ(F − F_c) √F``."""
    f = np.asarray(f, float)
    a = valve["laminar_nspm"] * np.asarray(ratio, float)
    b = valve["turbulent_ns2pm2"]
    vb = 2.0 * f / (a + np.sqrt(a * a + 4.0 * b * f))
    c = valve["crack_n"]
    ramp = np.maximum(0.5 * (f - c + np.hypot(f - c, knee_n)) - 0.5 * (np.hypot(c, knee_n) - c), 0.0)
    return vb + valve["shim_mps_per_n15"] * ramp * np.sqrt(f)


def valve_force(v: np.ndarray, ratio: np.ndarray | float, valve: dict[str, float], knee_n: float) -> np.ndarray:
    """The force (N) of one valve at velocity ``v`` ≥ 0: ``valve_velocity`` inverted by
    bisection (monotone; bracketed by the bleed alone, the shims only add flow) — a
    reference independent of dt-core's Newton iteration."""
    v = np.asarray(v, float)
    r = np.broadcast_to(np.asarray(ratio, float), v.shape)
    lo = np.zeros_like(v)
    hi = valve["laminar_nspm"] * r * v + valve["turbulent_ns2pm2"] * v * v
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        above = valve_velocity(mid, r, valve, knee_n) > v
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return 0.5 * (lo + hi)


# ---------------------------------------------------------------------------------------
# the law measured on the reversal windows themselves
# ---------------------------------------------------------------------------------------

WINDOWS_PER_RUN = 40      # reversal windows per nominal run (spread over the run)


def law_dict(coef: np.ndarray) -> dict[str, Any]:
    """The dt-core ``DampingLaw`` fields for the packed coefficients ``[a_0..a_8, b_0..b_8, β]``."""
    coef = np.asarray(coef, float)
    return {"knots_mps": list(KNOTS_MPS), "width_mps": WIDTH_MPS,
            "viscous_nspm": [float(x) for x in coef[:N_COEF]],
            "dry_nspm": [float(x) for x in coef[N_COEF:2 * N_COEF]], "beta_per_k": float(coef[-1])}


def pick_by_time(t_s: np.ndarray, n: int) -> np.ndarray:
    """Indices of the reversals (times ``t_s``, ascending) nearest to ``n`` times spread
    evenly over their span, at the middles of ``n`` equal parts. A reversal more or less
    (one window fit that converges or fails differently after a change of the fit) moves
    at most the one pick nearest to it; a pick by rank among the reversals, as before,
    moved about half of the picks after it and redrew the law's windows."""
    t_s = np.asarray(t_s, float)
    if len(t_s) <= n:
        return np.arange(len(t_s))
    targets = t_s[0] + (np.arange(n) + 0.5) / n * (t_s[-1] - t_s[0])
    i = np.clip(np.searchsorted(t_s, targets), 1, len(t_s) - 1)
    return np.unique(np.where(targets - t_s[i - 1] <= t_s[i] - targets, i - 1, i))


def reversal_windows(runs: Sequence[Run], physics: dict[str, Any], obs: dict[str, Any],
                     per_run: int = WINDOWS_PER_RUN, law: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The observer's reversal windows of ``runs`` (every detected reversal the window fit
    accepts with any residual), ``per_run`` of them per run spread evenly over its time
    (``pick_by_time``): times (s from the reversal), raw ``a2``, the velocity slope, the
    twin's oil temperature and what the window fit read there (amplitude, shift, residual).
    The windows are found with ``law`` (a ``DampingLaw``'s fields), by default the linear
    slopes of an uncalibrated observer."""
    loose = {**obs, "max_residual_mps2": 1e3,
             "damping_law": law or shocktwin.default_observer_params()["damping_law"]}  # default: linear slopes
    if law is not None:  # a calibration's: every reversal fitted, its own cut per excitation lifted too
        loose["fit_gain_floor"] = 0.0
        if x := obs.get("excitations"):
            loose["excitations"] = {**x, "max_residual_mps2": [1e3 if c else 0.0 for c in x["max_residual_mps2"]]}
    out = []
    # the runs' reversals side by side (dt-core releases the GIL while it reads a run)
    with ThreadPoolExecutor(max_workers=max(1, min(len(runs), os.cpu_count() or 1))) as pool:
        revs = list(pool.map(lambda run: shocktwin.charge_reversals(str(run.path), {**physics, "observer": loose}),
                             runs))
    for run, rev in zip(runs, revs):
        onset = rest_end_s(run) + SKIP_AFTER_ONSET_S
        ok = np.nonzero(rev["t_s"] > onset)[0]
        if len(ok) == 0:
            continue
        pick = ok[pick_by_time(rev["t_s"][ok], per_run)]
        acc = run.log.topic("/acceleration")
        t0 = min(run.log.topic(t)["t_s"][0] for t in run.log.topics if len(run.log.topic(t)["t_s"]))
        for i in pick:
            tr = rev["t_s"][i] + t0
            m = (acc["t_s"] >= tr - obs["window_pre_s"] - 1e-9) & (acc["t_s"] <= tr + obs["window_post_s"] + 1e-9)
            if m.sum() < 8:
                continue
            out.append({"run": run.name, "t_s": float(rev["t_s"][i]), "times": acc["t_s"][m] - tr,
                        "a2": acc["a2_mps2"][m], "accel": float(rev["accel_mps2"][i]),
                        "oil_c": float(rev["gas_temp_c"][i]), "alpha0": float(rev["alpha_n"][i]),
                        "slope_nspm": 0.5 * float(rev["damping_ext_nspm"][i] + rev["damping_comp_nspm"][i]),
                        "shift_ms": 1e3 * float(rev["shift_s"][i]), "residual0": float(rev["residual_mps2"][i])})
    return out


def _fit_windows(windows: Sequence[dict[str, Any]], physics: dict[str, Any], obs: dict[str, Any],
                 law_of: Any, z_law: np.ndarray, bounds_law: tuple[np.ndarray, np.ndarray],
                 penalty: Any, per0: Sequence[tuple[float, float]], max_nfev: int,
                 alpha_held: bool = False) -> dict[str, Any]:
    """The fit both law forms share: the law ``law_of(z[:n_law])`` shared by every window,
    per window the friction amplitude, the time shift and the offset (from ``per0``'s
    amplitudes and shifts, the offset from the data); ``penalty(z_law)`` are extra residual
    rows (the hinges' ridge); scipy ``least_squares``, TRF with a sparse Jacobian, soft-L1."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    n, n_law = len(windows), len(z_law)
    if n == 0:
        raise ValueError("no reversal windows to measure the damping law on")
    sizes = [len(w["times"]) for w in windows]
    offs = np.concatenate([[0], np.cumsum(sizes)])

    accels, oils = [w["accel"] for w in windows], [w["oil_c"] for w in windows]
    times, a2 = [w["times"] for w in windows], np.concatenate([w["a2"] for w in windows])

    def model(z: np.ndarray) -> np.ndarray:
        # every window in one call, on every core (the same bits as one ``reversal_window`` each)
        params = {**physics, "observer": {**obs, "damping_law": law_of(z[:n_law])}}
        per = z[n_law:].reshape(n, 3)
        theta = np.column_stack([per[:, 0] * 10.0, np.ones(n), np.ones(n), per[:, 1], per[:, 2]])
        return np.concatenate([penalty(z[:n_law]), shocktwin.reversal_windows(params, accels, oils, theta, times) - a2])

    n_pen = len(penalty(z_law))
    sparsity = lil_matrix((n_pen + int(offs[-1]), n_law + 3 * n), dtype=int)
    sparsity[:, :n_law] = 1
    for i in range(n):
        sparsity[n_pen + offs[i]:n_pen + offs[i + 1], n_law + 3 * i: n_law + 3 * i + 3] = 1
    z0 = np.concatenate([z_law] + [np.array([a / 10.0, sh, float(np.mean(w["a2"][:5]))])
                                   for w, (a, sh) in zip(windows, per0)])
    lower = np.concatenate([bounds_law[0]] + [np.array([0.0, -10.0, -np.inf])] * n)
    upper = np.concatenate([bounds_law[1]] + [np.array([np.inf, 10.0, np.inf])] * n)
    if alpha_held:  # the amplitudes held at ``per0``'s (a band: least_squares needs lower < upper)
        lower[n_law::3] = z0[n_law::3] * (1.0 - 1e-6)
        upper[n_law::3] = z0[n_law::3] * (1.0 + 1e-6)
    sol = least_squares(model, np.clip(z0, lower + 1e-9, upper - 1e-9), jac_sparsity=sparsity,
                        bounds=(lower, upper), x_scale="jac", loss="soft_l1", f_scale=0.3,
                        max_nfev=max_nfev)
    r = model(sol.x)[n_pen:]
    per = sol.x[n_law:].reshape(n, 3)
    rms = [float(np.sqrt(np.mean(r[offs[i]:offs[i + 1]] ** 2))) for i in range(n)]
    return {"law": law_of(sol.x[:n_law]),
            "residual_rms_mps2": float(np.sqrt(np.mean(r ** 2))), "windows": n, "nfev": int(sol.nfev),
            "per_window": [{"run": w["run"], "t_s": w["t_s"], "accel_mps2": w["accel"], "oil_c": w["oil_c"],
                            "alpha_n": float(q[0] * 10.0), "shift_ms": float(q[1]), "residual_mps2": e}
                           for w, q, e in zip(windows, per, rms)]}


def fit_law_windows(windows: Sequence[dict[str, Any]], physics: dict[str, Any], obs: dict[str, Any],
                    max_nfev: int = 200, beta_per_k: float | None = None,
                    start: dict[str, Any] | None = None,
                    per0: Sequence[tuple[float, float]] | None = None,
                    alpha_held: bool = False) -> dict[str, Any]:
    """The law that fits every window at once (``_fit_windows``): the law shared, per window
    the friction amplitude, the time shift and the offset; the law's per-side scales held at
    1 — the window model as the observer runs it (``shocktwin.reversal_window``).
    ``beta_per_k``: the viscosity coefficient held at the oil's datasheet value
    (``Datasheet.viscosity_coefficient_per_k``) instead of fitted — fitted, it trades against
    the knees the family cannot move and lands where the oil does not (0.073 /K on the full
    campaign, for an oil of 0.030). ``start``: a law (``law_dict``) to start from instead of
    the linear one, its viscosity coefficient then held; ``per0``: each window's start
    amplitude (N) and shift (ms), held at the amplitudes with ``alpha_held`` (see
    ``fit_law_staged``). Returns the law (``law_dict``), the residual RMS and the per-window
    amplitudes and residuals."""
    if not windows:
        raise ValueError("no reversal windows to measure the damping law on")
    n_law = 2 * N_COEF + 1
    scale = np.concatenate([np.full(2 * N_COEF, 1000.0), [0.01]])

    def penalty(z: np.ndarray) -> np.ndarray:
        # ridge on the hinges (``RIDGE_MPS2`` per ``RIDGE_NSPM``): knees of a few kN·s/m cost
        # nothing against the windows, a viscous and a dry hinge cancelling at 50 kN·s/m do
        return RIDGE_MPS2 * np.concatenate([z[1:N_COEF], z[N_COEF + 1:2 * N_COEF]]) * 1000.0 / RIDGE_NSPM

    # start: the linear law the windows were found with (median slopes), half of it viscous
    slope = float(np.median([w["slope_nspm"] for w in windows]))
    c0 = np.zeros(n_law)
    c0[0] = c0[N_COEF] = 0.5 * slope
    c0[-1] = BETA_START if beta_per_k is None else beta_per_k
    lower = np.concatenate([np.full(2 * N_COEF, -np.inf), [BETA_MIN / 0.01]])
    upper = np.concatenate([np.full(2 * N_COEF, np.inf), [10.0]])
    if start is not None:
        c0 = np.concatenate([start["viscous_nspm"], start["dry_nspm"], [start["beta_per_k"]]])
        beta_per_k = start["beta_per_k"]
    if beta_per_k is not None:  # held: a band of 1e-6 relative (least_squares needs lower < upper)
        lower[n_law - 1], upper[n_law - 1] = beta_per_k / 0.01 * (1.0 - 1e-6), beta_per_k / 0.01 * (1.0 + 1e-6)
    if per0 is None:
        per0 = [(max(w["alpha0"], 5.0), 0.0) for w in windows]
    return _fit_windows(windows, physics, obs, lambda z: law_dict(z * scale), c0 / scale, (lower, upper),
                        penalty, per0, max_nfev, alpha_held=alpha_held)


def fit_law_staged(windows: Sequence[dict[str, Any]], physics: dict[str, Any], obs: dict[str, Any],
                   max_nfev: int = 200, beta_per_k: float | None = None) -> dict[str, Any]:
    """``fit_law_windows`` in three stages, so that the faster excitations' windows do not
    send the fit to a minimum where the law carries the friction:

    1. the law on the slowest excitation's windows alone (within ``accel_cluster_rel`` of the
       smallest ``|ÿ|``): they see the law only near rest, where it is well determined, and
       each reads its friction amplitude;
    2. every window, each amplitude held at what the slow windows read at its oil
       temperature (a straight line in the temperature: the seal's friction follows the gas
       pressure, which follows the heat — not the excitation), the law started from stage 1;
    3. every window, everything free, from stage 2.

    The viscosity coefficient is stage 1's (or ``beta_per_k``) throughout. With one
    excitation only, stage 1 is the fit. On the simulated dyno (dt-sim 0.2.0, the full
    campaign's 12 bar runs, 80 windows) a single fit from the linear law ended at 0.48 m/s²
    RMS with the 2 Hz windows at the top of the stroke reading 15 N of friction for about
    50; the stages end at 0.21 (0.105 with the extension valve) with the friction read
    48-52 N at both excitations and both ends. Started from the plant's own law instead
    (dt-sim's valves tabulated at 60 °C), the same fit ends at the same 0.105."""
    if not windows:
        raise ValueError("no reversal windows to measure the damping law on")
    slowest = min(abs(w["accel"]) for w in windows)
    near = 1.0 + float(obs.get("accel_cluster_rel", 0.2))
    slow = [w for w in windows if abs(w["accel"]) <= near * slowest]
    first = fit_law_windows(slow, physics, obs, max_nfev, beta_per_k)
    if len(slow) == len(windows):
        return first
    alpha = np.array([q["alpha_n"] for q in first["per_window"]])
    temp = np.array([q["oil_c"] for q in first["per_window"]])
    per_k, at0 = np.polyfit(temp, alpha, 1) if np.ptp(temp) >= 5.0 else (0.0, float(np.median(alpha)))
    shift = float(np.median([q["shift_ms"] for q in first["per_window"]]))
    held = fit_law_windows(windows, physics, obs, max_nfev, start=first["law"], alpha_held=True,
                           per0=[(max(at0 + per_k * w["oil_c"], 5.0), shift) for w in windows])
    return fit_law_windows(windows, physics, obs, max_nfev, start=held["law"],
                           per0=[(max(q["alpha_n"], 5.0), q["shift_ms"]) for q in held["per_window"]])


VALVE_SCALE = np.array([1000.0, 10_000.0, 100.0, 1e-5])  # a N·s/m, b N·s²/m², F_c N, g m/(s·N^1.5)
VALVE_FIELDS = ("laminar_nspm", "turbulent_ns2pm2", "crack_n", "shim_mps_per_n15")  # dt-core ``LawValve``
# a valve's scaled lower bounds: a bleed with a laminar part (dt-core: not both coefficients 0)
VALVE_LOWER = np.array([1e-3, 0.0, 0.0, 0.0])
VALVE_KNEE_SCALE = 10.0                                   # N
NEG_KNOTS = [j for j, k in enumerate(KNOTS_MPS) if k < 0]


def valve_law_dict(z: np.ndarray, beta_per_k: float) -> dict[str, Any]:
    """The dt-core ``DampingLaw`` fields of the mixed form for the scaled parameters ``z``:
    the hinges for compression (``[a_0, a_j (k_j < 0)…, b_0, b_j…]`` in kN·s/m; the
    positive knots unused) and the extension valve ``[a, b, F_c, g]`` and knee width."""
    nh = len(NEG_KNOTS) + 1
    visc, dry = np.zeros(N_COEF), np.zeros(N_COEF)
    idx = [0] + [j + 1 for j in NEG_KNOTS]
    visc[idx], dry[idx] = np.asarray(z[:nh]) * 1000.0, np.asarray(z[nh:2 * nh]) * 1000.0
    return {"knots_mps": [k if k < 0 else 0.0 for k in KNOTS_MPS], "width_mps": WIDTH_MPS,
            "viscous_nspm": [float(x) for x in visc], "dry_nspm": [float(x) for x in dry],
            "beta_per_k": float(beta_per_k),
            "valves": {"extension": _valve_of(z[2 * nh:2 * nh + 4]),
                       "knee_n": float(z[2 * nh + 4] * VALVE_KNEE_SCALE)}}


def _valve_of(z: np.ndarray) -> dict[str, float]:
    """One valve's fields (dt-core ``LawValve``) from its scaled parameters ``[a, b, F_c, g] / VALVE_SCALE``."""
    return dict(zip(VALVE_FIELDS, (float(x) for x in np.asarray(z) * VALVE_SCALE)))


def fit_valve_law_windows(windows: Sequence[dict[str, Any]], physics: dict[str, Any], obs: dict[str, Any],
                          beta_per_k: float, start: dict[str, Any] | None = None,
                          max_nfev: int = 200) -> dict[str, Any]:
    """As ``fit_law_windows`` with the extension side a valve (dt-core ``LawValves``: a bleed
    and a preloaded shim stack, whose knee sits at a force and so moves with the viscosity)
    and the compression side the hinges (``--law-form valve``); the viscosity coefficient held
    at the oil's (the datasheet). The valve's start assumes nothing of it but the windows'
    median linear slope ``c``: a laminar bleed of slope ``c`` that cracks at ``c · 0.1 m/s``,
    the shims then adding as much flow again; the hinges start as in ``fit_law_windows``, or,
    given ``start`` (a hinges' fit on the same windows: ``fit_law_staged``'s in ``observer
    fit``), from its compression hinges and its windows' amplitudes and shifts: at 2 Hz each
    window has two minima of nearly the same residual (the module docs of dt-core
    ``charge``), and a fit from the linear start lands the compression windows in the one of
    ≈ 15 N — as does a single hinges' fit (``fit_law_windows``) on the corrected simulator."""
    if not windows:
        raise ValueError("no reversal windows to measure the damping law on")
    nh = len(NEG_KNOTS) + 1
    n_law = 2 * nh + 5

    def penalty(z: np.ndarray) -> np.ndarray:
        return RIDGE_MPS2 * np.concatenate([z[1:nh], z[nh + 1:2 * nh]]) * 1000.0 / RIDGE_NSPM

    slope = float(np.median([w["slope_nspm"] for w in windows]))
    crack = slope * 0.1
    z_law = np.zeros(n_law)
    z_law[0] = z_law[nh] = 0.5 * slope / 1000.0
    z_law[2 * nh:2 * nh + 4] = np.array([slope, 0.0, crack, 1.0 / (slope * np.sqrt(crack))]) / VALVE_SCALE
    z_law[2 * nh + 4] = 0.05 * crack / VALVE_KNEE_SCALE
    per0 = [(max(w["alpha0"], 5.0), 0.0) for w in windows]
    if start is not None:
        idx = [0] + [j + 1 for j in NEG_KNOTS]
        z_law[:nh] = np.asarray(start["law"]["viscous_nspm"])[idx] / 1000.0
        z_law[nh:2 * nh] = np.asarray(start["law"]["dry_nspm"])[idx] / 1000.0
        per0 = [(max(q["alpha_n"], 5.0), q["shift_ms"]) for q in start["per_window"]]
    lower = np.concatenate([np.full(2 * nh, -np.inf), VALVE_LOWER, [0.1 / VALVE_KNEE_SCALE]])
    upper = np.full(n_law, np.inf)
    return _fit_windows(windows, physics, obs, lambda z: valve_law_dict(z, beta_per_k), z_law, (lower, upper),
                        penalty, per0, max_nfev)


def _valve_start(v: np.ndarray, f: np.ndarray, ratio: float, knee_n: float, z0: np.ndarray) -> np.ndarray:
    """Scaled valve parameters ``[a, b, F_c, g] / VALVE_SCALE`` whose force best matches
    ``f`` (N, ≥ 0) at speeds ``v`` (m/s, > 0) with the viscosity ratio ``ratio`` (scipy
    ``least_squares`` on the valve's velocity at each force: ``valve_velocity`` is explicit,
    its inverse is not). Started from ``z0`` and from valves that crack at the force of a
    quarter, half and all of the speeds' range (a laminar bleed through that point, shims
    adding as much flow again): from ``z0`` alone the fit can end at a bleed whose crack lies
    beyond every force (docs/history.md, "Twenty-fifth session"). The best of those fits."""
    from scipy.optimize import least_squares

    def resid(z: np.ndarray) -> np.ndarray:
        return (valve_velocity(f, ratio, _valve_of(z), knee_n) - v) / np.maximum(v, 0.01)

    starts = [np.clip(z0, VALVE_LOWER + 1e-9, np.inf)]
    for q in (0.25, 0.5, 1.0):
        i = min(int(q * (len(v) - 1)), len(v) - 1)
        crack = max(float(f[i]), 1.0)
        a = crack / (float(v[i]) * ratio)
        starts.append(np.array([a, 0.0, crack, 1.0 / (a * np.sqrt(crack))]) / VALVE_SCALE)
    fits = [least_squares(resid, np.maximum(z, VALVE_LOWER + 1e-9), bounds=(VALVE_LOWER, np.full(4, np.inf)))
            for z in starts]
    return min(fits, key=lambda r: r.cost).x


def valves_law_dict(z: np.ndarray, beta_per_k: float) -> dict[str, Any]:
    """The dt-core ``DampingLaw`` fields of the two-valve form for the scaled parameters
    ``z = [extension a, b, F_c, g, knee, compression a, b, F_c, g]``: a valve on each side
    (dt-core ``LawValves``), no hinges."""
    return {"knots_mps": [0.0] * len(KNOTS_MPS), "width_mps": WIDTH_MPS,
            "viscous_nspm": [0.0] * N_COEF, "dry_nspm": [0.0] * N_COEF, "beta_per_k": float(beta_per_k),
            "valves": {"extension": _valve_of(z[:4]), "compression": _valve_of(z[5:9]),
                       "knee_n": float(z[4] * VALVE_KNEE_SCALE)}}


def fit_valves_law_windows(windows: Sequence[dict[str, Any]], physics: dict[str, Any], obs: dict[str, Any],
                           start: dict[str, Any], max_nfev: int = 200) -> dict[str, Any]:
    """As ``fit_valve_law_windows`` with a valve on the compression side too (``--law-form
    valves``): hinges extrapolate straight beyond their last knot (0.15 m/s), a valve's bleed
    and shims as a valve does, so the law holds farther than the windows it was fitted on
    reach. Started from ``start`` (the extension valve's fit): its extension valve, knee,
    windows' amplitudes and shifts, and a compression valve matched to its compression hinges
    over the speeds the windows saw (``_valve_start``)."""
    law0 = start["law"]
    ext = law0["valves"]["extension"]
    knee = law0["valves"]["knee_n"]
    beta = law0["beta_per_k"]
    reach = max(abs(w["accel"]) * max(-float(np.min(w["times"])), float(np.max(w["times"]))) for w in windows)
    oil_c = float(np.median([w["oil_c"] for w in windows]))
    ratio = float(np.exp(-beta * (oil_c - 40.0)))  # ``law``'s viscosity ratio there
    v = np.linspace(0.02, reach, 24)
    f = -law(-v, oil_c, law0)
    z_ext = np.array([ext[k] for k in VALVE_FIELDS]) / VALVE_SCALE
    z_comp = _valve_start(v, np.maximum(f, 1e-3), ratio, knee, z_ext)
    z_law = np.concatenate([z_ext, [knee / VALVE_KNEE_SCALE], z_comp])
    lower = np.concatenate([VALVE_LOWER, [0.1 / VALVE_KNEE_SCALE], VALVE_LOWER])
    per0 = [(max(q["alpha_n"], 5.0), q["shift_ms"]) for q in start["per_window"]]
    return _fit_windows(windows, physics, obs, lambda z: valves_law_dict(z, beta), z_law,
                        (lower, np.full(len(z_law), np.inf)), lambda z: np.zeros(0), per0, max_nfev)


def twin_law_dict(z: np.ndarray, beta_per_k: float) -> dict[str, Any]:
    """The dt-core ``DampingLaw`` fields of the twin-tube form for the scaled parameters
    ``z = [extension a, b, F_c, g, knee, compression a, b, F_c, g, piston a, b, F_c, g]``:
    a valve in extension, two in compression whose forces add (dt-core ``LawValves``)."""
    d = valves_law_dict(z[:9], beta_per_k)
    d["valves"]["compression_piston"] = _valve_of(z[9:13])
    return d


def fit_twin_law_windows(windows: Sequence[dict[str, Any]], physics: dict[str, Any], obs: dict[str, Any],
                         start: dict[str, Any], max_nfev: int = 200,
                         loadcell: "LoadcellRows | None" = None) -> dict[str, Any]:
    """As ``fit_valves_law_windows`` with the compression side two valves whose forces add at
    the same speed (``--law-form twin-tube``; the module docs). Started from ``start``
    (``fit_valves_law_windows``'s fit, a valve each way): its extension valve, knee, windows'
    amplitudes and shifts, and its compression valve split in two that sum to it — its bleed
    split 90/10 and 10/90 (one valve takes most of the turbulent bleed, the other most of the
    laminar), its cracking force 45/55, and the shims' gain ×2√2 in each (half the force
    above half the crack passes the same speed). Two equal halves would be a saddle the fit
    cannot leave. A ``start`` that is already this form's fit starts from its own valves.

    ``loadcell``: the nominal runs' loadcell rows (``LoadcellRows``) join the windows' —
    the speeds beyond the windows' reach (``loadcell_law_rows``)."""
    law0 = start["law"]
    vs = law0["valves"]
    z_ext = np.array([vs["extension"][k] for k in VALVE_FIELDS]) / VALVE_SCALE
    if vs.get("compression_piston"):
        base = np.array([vs["compression"][k] for k in VALVE_FIELDS])
        piston = np.array([vs["compression_piston"][k] for k in VALVE_FIELDS])
    else:
        a, b, crack, g = np.array([vs["compression"][k] for k in VALVE_FIELDS])
        base = np.array([0.1 * a, 0.9 * b, 0.45 * crack, 2.0 * np.sqrt(2.0) * g])
        piston = np.array([0.9 * a, 0.1 * b, 0.55 * crack, 2.0 * np.sqrt(2.0) * g])
    z_law = np.concatenate([z_ext, [vs["knee_n"] / VALVE_KNEE_SCALE], base / VALVE_SCALE, piston / VALVE_SCALE])
    lower = np.concatenate([VALVE_LOWER, [0.1 / VALVE_KNEE_SCALE], VALVE_LOWER, VALVE_LOWER])
    per0 = [(max(q["alpha_n"], 5.0), q["shift_ms"]) for q in start["per_window"]]
    beta = law0["beta_per_k"]
    rows = (lambda z: loadcell(twin_law_dict(z, beta))) if loadcell is not None else (lambda z: np.zeros(0))
    fit = _fit_windows(windows, physics, obs, lambda z: twin_law_dict(z, beta), np.maximum(z_law, lower + 1e-9),
                       (lower, np.full(len(z_law), np.inf)), rows, per0, max_nfev)
    if loadcell is not None:
        fit["loadcell_rms_n"] = float(np.sqrt(np.mean(np.concatenate(loadcell.residuals_n(fit["law"])) ** 2)))
    return fit


# ---------------------------------------------------------------------------------------
# a unit's own law: the calibration's law refitted on one unit's windows
# ---------------------------------------------------------------------------------------

UNIT_LAW_WINDOWS_PER_RUN = 80  # a service drive's windows the unit's law is refitted on


def law_form(law: dict[str, Any]) -> str:
    """The form of a ``DampingLaw``'s fields: ``twin-tube``, ``valves``, ``valve``, ``hinges``
    or ``linear`` (uncalibrated)."""
    vs = law.get("valves")
    if vs:
        return "twin-tube" if vs.get("compression_piston") else "valves" if vs.get("compression") else "valve"
    return "hinges" if any(law.get("knots_mps", [])) or any(law.get("viscous_nspm", [])) else "linear"


def unit_law(runs: Sequence[Run], physics: dict[str, Any],
             per_run: int = UNIT_LAW_WINDOWS_PER_RUN) -> dict[str, Any]:
    """The calibration's damping law (``physics["observer"]["damping_law"]``) refitted on one
    unit's reversal windows (``runs``: that unit's, e.g. its service drive): the law's form and
    viscosity coefficient kept, its valves (or hinges) free, from the calibration's; per window
    the friction amplitude, shift and offset, started where the calibration's window fit put
    them. No charge is needed: the amplitudes are free. The windows are found with the
    calibration's law and every residual cut lifted, so that an end of the stroke whose windows
    the calibration's law does not fit (another unit's valves: docs/history.md, "Fortieth session")
    is in the fit too.

    Returns ``fit_twin_law_windows``'s (or ``fit_law_windows``'s) fit with ``residual_before``,
    the windows' median residual with the calibration's law per end of the stroke
    (``"+"``: ``ÿ_r > 0``), and ``residual_after`` likewise. Raises ``ValueError`` when the
    calibration has no law, a form this refit does not take, or no window."""
    obs = physics["observer"]
    law0 = obs.get("damping_law") or {}
    form = law_form(law0)
    if form not in ("twin-tube", "hinges"):
        raise ValueError(f"observer.damping_law: a unit's own law refits the twin-tube or hinges form, "
                         f"not the calibration's {form!r} (`python -m train.observer fit --law-form`)")
    wins = [w for w in reversal_windows(runs, physics, obs, per_run, law=law0)
            if w["residual0"] <= LAW_WINDOW_MAX_RESIDUAL_MPS2]
    if not wins:
        raise ValueError("no reversal window the calibration's law reaches in these runs: no unit law")
    start = {"law": law0, "per_window": [{"alpha_n": max(w["alpha0"], 5.0), "shift_ms": w["shift_ms"]}
                                         for w in wins]}
    if form == "twin-tube":
        fit = fit_twin_law_windows(wins, physics, obs, start=start)
    else:
        fit = fit_law_windows(wins, physics, obs, start=law0,
                              per0=[(q["alpha_n"], q["shift_ms"]) for q in start["per_window"]])
    ends = np.sign([w["accel"] for w in wins])

    def by_end(r: Sequence[float]) -> dict[str, float | None]:
        r = np.asarray(r, float)
        return {k: (float(np.median(r[ends == e])) if np.any(ends == e) else None) for k, e in (("+", 1), ("-", -1))}

    fit["residual_before"] = by_end([w["residual0"] for w in wins])
    fit["residual_after"] = by_end([q["residual_mps2"] for q in fit["per_window"]])
    return fit


# ---------------------------------------------------------------------------------------
# the law's loadcell rows: the nominal runs' loadcell, mid-stroke
# ---------------------------------------------------------------------------------------

# The reversal windows of the 1 and 2 Hz nominal runs reach 0.16 m/s only in their last
# milliseconds; at 3 Hz the windows run to 0.3 m/s, where dt-sim's compression valves have
# blown off (docs/history.md, "Twenty-seventh session"). The dyno's loadcell sees every speed of every
# stroke: mid-stroke its reading is the law, the seal friction, the gas force and the mount's
# inertia, through the amplifier's low pass (dt-sim 0.2.0: within 8 N RMS of the reading, on
# 6 N of noise, with the plant's own static curve and a velocity of the potentiometer's).
LOADCELL_CHUNK_S = 4.0          # s of loadcell per chunk; each chunk has its own nuisances
LOADCELL_CHUNKS_PER_RUN = 6     # spread over the excited part of each nominal run
LOADCELL_GRID_S = 1e-3          # the model force's grid (filtered, then read at the samples)
LOADCELL_LEAD_S = 0.3           # grid before a chunk's first sample (the filter's start)
LOADCELL_SAVGOL = (7, 3)        # the potentiometer's derivative: window (samples), order
LOADCELL_FILTER_HZ = (5.0, 200.0)  # the bounds of the amplifier's low pass, fitted
# A loadcell row's weight against a window's: 10 N of loadcell residual counts as 0.1 m/s²
# of a window's (each at about its noise-free model error).
LOADCELL_MPS2_PER_N = 0.01
# The loadcell's rows start at this speed: the windows hold the law below it.
LOADCELL_MIN_SPEED_MPS = 0.1
# The velocities the law is tabulated at for the loadcell rows: 1 mm/s up to 0.06 m/s (the
# friction's knee), 2.5 mm/s to 0.6 m/s (the valves' knees), 10 mm/s beyond, to 1.5 m/s.
_LV = np.concatenate([np.arange(0.0, 0.06, 0.001), np.arange(0.06, 0.6, 0.0025), np.arange(0.6, 1.5001, 0.01)])
LOADCELL_LAW_V = np.concatenate([-_LV[:0:-1], _LV])


def lag_behind_accel_s(pairs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> float:
    """The lag (s, a 0.1 ms grid to 10 ms) by which a position lags an accelerometer: for each
    ``(t_pos, z, t_acc, acc)`` the position's second derivative (Savitzky–Golay, scipy) against
    the accelerometer read that much earlier, each with its own gain and mean, the squared
    misfit summed over the pairs."""
    from scipy.signal import savgol_filter

    lags = np.arange(0.0, 10.0001, 0.1) * 1e-3
    cost = np.zeros(len(lags))
    for tp, zp, ta, acc in pairs:
        dt = float(np.median(np.diff(tp)))
        y = savgol_filter(zp, LOADCELL_SAVGOL[0], LOADCELL_SAVGOL[1], deriv=2, delta=dt)
        y = y[LOADCELL_SAVGOL[0]:-LOADCELL_SAVGOL[0]]
        t = tp[LOADCELL_SAVGOL[0]:-LOADCELL_SAVGOL[0]]
        y = y - y.mean()
        for i, lag in enumerate(lags):
            x = np.interp(t - lag, ta, acc)
            x = x - x.mean()
            g = (x @ y) / max(x @ x, 1e-12)
            cost[i] += float(np.sum((y - g * x) ** 2))
    return float(lags[int(np.argmin(cost))])


def potentiometer_lag_s(runs: Sequence[Run], accel_bw_hz: float) -> float | None:
    """The potentiometer's lag (s) behind the rod end: its lag behind the rod-end
    accelerometer ``a1`` over the excited parts of ``runs`` (``lag_behind_accel_s``) plus
    ``a1``'s own first-order lag ``1 / (2π accel_bw_hz)``. No law enters it. None without
    accelerometers."""
    pairs = []
    for run in runs:
        if "/acceleration" not in run.log.topics or "/position" not in run.log.topics:
            continue
        pos, acc = run.log.topic("/position"), run.log.topic("/acceleration")
        ok = np.isfinite(pos["position_m"])
        m = ok & (pos["t_s"] > rest_end_s(run) + SKIP_AFTER_ONSET_S)
        if m.sum() < 50:
            continue
        oka = np.isfinite(acc["a1_mps2"])
        pairs.append((pos["t_s"][m], pos["position_m"][m], acc["t_s"][oka], acc["a1_mps2"][oka]))
    if not pairs:
        return None
    return lag_behind_accel_s(pairs) + 1.0 / (2.0 * np.pi * accel_bw_hz)


def loadcell_chunks(runs: Sequence[Run], physics: dict[str, Any], obs: dict[str, Any],
                    lag_s: float, per_run: int = LOADCELL_CHUNKS_PER_RUN) -> list[dict[str, Any]]:
    """``per_run`` chunks of ``LOADCELL_CHUNK_S`` of each run's loadcell, spread over its
    excited part: on a ``LOADCELL_GRID_S`` grid the stroke velocity (the potentiometer's
    Savitzky–Golay derivative, advanced by its lag ``lag_s``: ``potentiometer_lag_s``), the
    position, ``a2`` and the twin's oil temperature (the one the observer uses); the
    loadcell's samples and their indices on the grid. Runs without a loadcell are skipped."""
    from scipy.interpolate import CubicSpline
    from scipy.signal import savgol_filter

    out = []
    for run in runs:
        if not {"/force", "/position", "/acceleration"} <= set(run.log.topics):
            continue
        trace = shocktwin.twin_trace(run.log, physics)
        t0 = min(run.log.topic(t)["t_s"][0] for t in run.log.topics if len(run.log.topic(t)["t_s"]))
        pos, acc, fc = run.log.topic("/position"), run.log.topic("/acceleration"), run.log.topic("/force")
        ok = np.isfinite(pos["position_m"])
        tp, zp = pos["t_s"][ok] - t0, pos["position_m"][ok]
        dt = float(np.median(np.diff(tp)))
        vel = CubicSpline(tp, savgol_filter(zp, LOADCELL_SAVGOL[0], LOADCELL_SAVGOL[1], deriv=1, delta=dt))
        okf = np.isfinite(fc["force_n"])
        tf, ff = fc["t_s"][okf] - t0, fc["force_n"][okf]
        start = rest_end_s(run) - t0 + SKIP_AFTER_ONSET_S + LOADCELL_LEAD_S
        end = min(tp[-1], tf[-1]) - 0.1
        if end - start < LOADCELL_CHUNK_S:
            continue
        for c in range(per_run):
            a = start + (c + 0.5) / per_run * (end - start - LOADCELL_CHUNK_S)
            grid = np.arange(a - LOADCELL_LEAD_S, a + LOADCELL_CHUNK_S, LOADCELL_GRID_S)
            sel = (tf >= a) & (tf < a + LOADCELL_CHUNK_S)
            if sel.sum() < 20:
                continue
            out.append({"run": run.name, "t_s": float(a), "v": vel(grid + lag_s),
                        "y": np.interp(grid + lag_s, tp, zp),
                        "a2": np.interp(grid, acc["t_s"] - t0, acc["a2_mps2"]),
                        "oil_c": np.interp(grid, trace["t_s"], trace["oil_temp_model_c"]),
                        "force": ff[sel],
                        "at": np.clip(np.round((tf[sel] - grid[0]) / LOADCELL_GRID_S).astype(int), 0, len(grid) - 1)})
    return out


class LoadcellRows:
    """The loadcell rows of the law's fit on ``chunks`` (``loadcell_chunks``) through the
    amplifier's low pass, a 2nd-order Butterworth at ``filter_hz`` (scipy, on the grid): per
    chunk the reading ``F = LP[L(v, T) + α tanh(v / v_s) + k y − m a2] + c``, the nuisances
    ``k`` (the gas spring), ``m`` (the mount's mass) and ``c`` (the gas force and the
    loadcell's zero) eliminated by least squares (variable projection), so only the law ``L``
    is left to fit. Only the samples at ``min_speed_mps`` or faster are rows: near a reversal
    the reading turns on the velocity's timing (a potentiometer lag read 0.6 ms long is 15 N
    there at 4 Hz) and the windows hold the law better. The seal friction's amplitude ``α``
    is ``alpha_at(T_oil)`` (N) — what the windows read at that oil temperature — or, without
    it, a nuisance too: mid-stroke
    ``tanh(v / v_s)`` is the sign of the velocity, and a free ``α`` per chunk takes up any
    part of the law that is, so the law then thinned too fast with the heat (dt-sim: 14 %
    weak at 0.16 m/s and 80 °C). Rows in m/s² (``LOADCELL_MPS2_PER_N``)."""

    def __init__(self, chunks: Sequence[dict[str, Any]], v_smooth_mps: float, filter_hz: float,
                 alpha_at: Any = None, min_speed_mps: float = 0.0):
        from scipy.signal import butter

        self.chunks = []
        for ch in chunks:  # only the samples at ``min_speed_mps`` or faster are rows
            keep = np.abs(ch["v"][ch["at"]]) >= min_speed_mps
            if keep.sum() >= 8:
                self.chunks.append({**ch, "at": ch["at"][keep], "force": ch["force"][keep]})
        self.filter_hz, self.min_speed_mps = float(filter_hz), float(min_speed_mps)
        self.ba = butter(2, filter_hz, fs=1.0 / LOADCELL_GRID_S)
        self.q, self.friction = [], []
        for ch in self.chunks:
            tanh = np.tanh(ch["v"] / v_smooth_mps)
            cols = [self.lowpass(ch["y"]), self.lowpass(ch["a2"])]
            if alpha_at is None:
                cols.append(self.lowpass(tanh))
                self.friction.append(np.zeros(len(ch["at"])))
            else:
                self.friction.append(self.lowpass(np.asarray(alpha_at(ch["oil_c"])) * tanh)[ch["at"]])
            x = np.column_stack([c[ch["at"]] for c in cols] + [np.ones(len(ch["at"]))])
            self.q.append(np.linalg.qr(x)[0])

    def lowpass(self, x: np.ndarray) -> np.ndarray:
        from scipy.signal import lfilter, lfilter_zi

        return lfilter(*self.ba, x, zi=lfilter_zi(*self.ba) * x[0])[0]

    def law_forces(self, d: dict[str, Any]) -> list[np.ndarray]:
        """Per chunk, the law dict ``d``'s force on the grid, read off a table of it
        (``LOADCELL_LAW_V``) at the chunk's coldest and hottest oil, linear between (a chunk
        spans about a kelvin): one ``law`` call for every chunk at once (0.42 N from ``law`` at
        most on the tests' twin-tube law, at its extension valve's knee)."""
        n = len(LOADCELL_LAW_V)
        temps = np.array([[np.min(ch["oil_c"]), np.max(ch["oil_c"])] for ch in self.chunks]).ravel()
        table = law(np.tile(LOADCELL_LAW_V, len(temps)), np.repeat(temps, n), d).reshape(len(temps), n)
        out = []
        for k, ch in enumerate(self.chunks):
            lo, hi = temps[2 * k], temps[2 * k + 1]
            f = np.interp(ch["v"], LOADCELL_LAW_V, table[2 * k])
            if hi - lo > 1e-6:
                w = (ch["oil_c"] - lo) / (hi - lo)
                f = (1.0 - w) * f + w * np.interp(ch["v"], LOADCELL_LAW_V, table[2 * k + 1])
            out.append(f)
        return out

    def residuals_n(self, d: dict[str, Any]) -> list[np.ndarray]:
        """Per chunk, the loadcell's residual (N) with the law dict ``d`` (``law_forces``), its
        nuisances projected out."""
        out = []
        for ch, q, f, fr in zip(self.chunks, self.q, self.law_forces(d), self.friction):
            r = ch["force"] - fr - self.lowpass(f)[ch["at"]]
            out.append(r - q @ (q.T @ r))
        return out

    def __call__(self, d: dict[str, Any]) -> np.ndarray:
        return LOADCELL_MPS2_PER_N * np.concatenate(self.residuals_n(d))


def fit_loadcell_filter(chunks: Sequence[dict[str, Any]], v_smooth_mps: float, start: dict[str, Any],
                        max_nfev: int = 60, alpha_at: Any = None) -> tuple[float, dict[str, Any], float]:
    """The loadcell amplifier's low pass (Hz), measured with the twin-tube law on the loadcell
    alone (scipy ``least_squares``, soft-L1): the law's valves and the cut-off fitted
    together from ``start`` (a twin-tube fit on the windows) and 20 Hz. The windows' law is
    wrong beyond their reach, and a cut-off searched with it held read 24 Hz for dt-sim's
    20 (the loadcell alone: 19.4). Returns the cut-off, the law (only the cut-off is kept:
    the loadcell alone holds the law poorly below 0.1 m/s, where the windows hold it) and the
    loadcell's RMS residual (N)."""
    from scipy.optimize import least_squares

    law0 = start["law"]
    vs, beta = law0["valves"], law0["beta_per_k"]
    z0 = np.concatenate([np.array([vs["extension"][k] for k in VALVE_FIELDS]) / VALVE_SCALE,
                         [vs["knee_n"] / VALVE_KNEE_SCALE],
                         np.array([vs["compression"][k] for k in VALVE_FIELDS]) / VALVE_SCALE,
                         np.array([vs["compression_piston"][k] for k in VALVE_FIELDS]) / VALVE_SCALE,
                         [np.log(20.0)]])
    lower = np.concatenate([VALVE_LOWER, [0.1 / VALVE_KNEE_SCALE], VALVE_LOWER, VALVE_LOWER,
                            [np.log(LOADCELL_FILTER_HZ[0])]])
    upper = np.concatenate([np.full(13, np.inf), [np.log(LOADCELL_FILTER_HZ[-1])]])
    cache: dict[float, LoadcellRows] = {}

    def rows_at(log_hz: float) -> LoadcellRows:
        key = round(float(log_hz), 12)
        if key not in cache:
            cache.clear()
            cache[key] = LoadcellRows(chunks, v_smooth_mps, float(np.exp(log_hz)), alpha_at,
                                      LOADCELL_MIN_SPEED_MPS)
        return cache[key]

    def resid(z: np.ndarray) -> np.ndarray:
        return rows_at(z[13])(twin_law_dict(z[:13], beta)) / LOADCELL_MPS2_PER_N

    sol = least_squares(resid, np.clip(z0, lower + 1e-9, upper - 1e-9), bounds=(lower, upper), x_scale="jac",
                        loss="soft_l1", f_scale=20.0, max_nfev=max_nfev)
    return float(np.exp(sol.x[13])), twin_law_dict(sol.x[:13], beta), float(np.sqrt(np.mean(sol.fun ** 2)))


def loadcell_law_rows(runs: Sequence[Run], physics: dict[str, Any], obs: dict[str, Any],
                      start: dict[str, Any]) -> LoadcellRows | None:
    """The loadcell rows of the nominal ``runs`` for the twin-tube law's fit (``start``: its
    fit on the windows alone), or None when they carry no loadcell (or no accelerometers:
    the potentiometer's lag is measured against ``a1``). The potentiometer's lag
    (``potentiometer_lag_s``), the chunks (``loadcell_chunks``) and the amplifier's cut-off
    (``fit_loadcell_filter``) are printed; the seal friction is held at what the windows of
    ``start`` read (``friction_of_windows``)."""
    if not any({"/force", "/position", "/acceleration"} <= set(r.log.topics) for r in runs):
        return None
    lag = potentiometer_lag_s(runs, obs["accel_bw_hz"])
    if lag is None:
        return None
    chunks = loadcell_chunks(runs, physics, obs, lag)
    if not chunks:
        return None
    alpha_at = friction_of_windows(start)
    hz, _, rms = fit_loadcell_filter(chunks, obs["friction_v_smooth_mps"], start, alpha_at=alpha_at)
    print(f"damping law, the loadcell rows: {len(chunks)} chunks of {LOADCELL_CHUNK_S:.0f} s "
          f"({sum(len(c['force']) for c in chunks)} samples) of {len({c['run'] for c in chunks})} nominal runs; "
          f"potentiometer lag {lag * 1e3:.1f} ms, amplifier low pass {hz:.1f} Hz "
          f"(the loadcell alone: {rms:.1f} N RMS)")
    return LoadcellRows(chunks, obs["friction_v_smooth_mps"], hz, alpha_at, LOADCELL_MIN_SPEED_MPS)


def friction_of_windows(fit: dict[str, Any]) -> Any:
    """The seal friction's amplitude (N) the windows of ``fit`` read, as a straight line in
    the oil temperature (numpy ``polyfit`` over its windows; the charge, and so the
    pressure-energised seal, rises with the heat): the loadcell rows' ``alpha_at``."""
    oil = np.array([w["oil_c"] for w in fit["per_window"]])
    alpha = np.array([w["alpha_n"] for w in fit["per_window"]])
    slope, intercept = np.polyfit(oil, alpha, 1)
    return lambda t: slope * np.asarray(t, float) + intercept
