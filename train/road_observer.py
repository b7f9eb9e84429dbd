"""Read the gas charge on a road from the cheap suite: the seal friction's flip in the body
accelerometer, regressed over ten-second blocks of drive (a research tool; simulated data).

    python -m train.road_observer fit --campaign DIR --physics physics.json --out road.json
    python -m train.road_observer evaluate --physics physics.json --road road.json --out DIR NAME=DIR ...
    python -m train.road_observer skew --physics physics.json --road road.json RUN.mcap ...

The dyno observer (dt-core ``charge``) fits one window per velocity reversal of a sine and
refuses a road (docs/history.md, "Fifteenth session"); ``train.road_bound`` says the information is
there. This reads it. Over each block of ``--block-s`` seconds the body accelerometer is
modelled as the damper force through the calibrated body-end mount and the accelerometer's
first-order filter (the ``observer`` section of physics.json), the force linear in its
parameters::

    F(t) = α tanh(ẏ/v_s) + Σ_j (c_j + d_j τ) b_j(ẏ) + k y + f_0,     τ = t / 100 s (the run's time)
    a2   = H_acc * F + c_0 + ε

``b_j`` a damping law flexible enough for a valve's knee (slopes each side and hinges every
1 cm/s up to 0.3 m/s, coarser beyond), its drift ``d_j`` across the block (the oil heats),
all unknown per block; ``α`` the friction amplitude, which grows with the gas pressure (a
pressure-energised seal). Least squares per block gives ``α``.

The regression is only as good as the stroke velocity it is given: at the friction's
5 mm/s scale, a 0.25 ms lag or 1 mm/s of noise halves ``α``. The velocity comes from a
Kalman filter of its own (not dt-core's three-state filter, which is unchanged): state
``[y, ẏ, b_a, y_f]`` with ``y_f`` the potentiometer's reading behind its first-order RC
(``--pot-rc-hz``), driven at 1 kHz by ``a1 − a2`` with the accelerometers' own first-order
filter inverted, updated at the potentiometer's 100 Hz; then a Rauch–Tung–Striebel pass
back from ``--lag-s`` after the block's end. Every block's reading therefore uses data up
to ``--lag-s`` after that block and none later: the estimate at a block's end is available
``lag-s`` later (no look-ahead beyond it).

``fit`` calibrates ``α = a + b p_g`` on road runs at known charges, ``p_g = (p + p_atm) θ −
p_atm`` the gas pressure at the shock thermocouple's temperature (``θ`` as in
``train.observer``: temperature, the oil's expansion into the gas; the datasheet geometry of
physics.json), by robust least squares (soft-L1); the per-block spread is the residuals'
robust (MAD) spread; the systematic part is measured leaving one drive file out (every run
of it; one run when the campaign has a single drive file), and another unit's
seal adds ``--unit-tolerance-pct`` of the friction (offset and slope: a datasheet figure, as
``train.observer`` does). ``evaluate`` reads held-out road sets block by block into a
recursive estimate of the charge (a random-walk state updated by each block's reading and its
spread) with a 95 % interval widened by the systematic part, and reports error, coverage and
the SPEC §6a verdict over time. ``--baseline SET=RUN.mcap@BAR`` gives a drive of that set's
unit at a known charge (after a service): its seal's offset is read from it, and only the
slope's tolerance stays systematic. Blocks are kept under ``OUT/blocks`` and read back.

A calibration vouches only for strokes as fast as those it read: ``fit`` keeps the slowest
block's stroke velocity RMS (``filters.slowest_calibrated_stroke_rms_mps``), and a slower block
is not read (here by :func:`calibrated_blocks`, in dt-core by the streaming observer). Driven
slower, the friction read falls short of the calibration's line by a factor: errors in
variables, the sensors' noise in the stroke velocity weighing more on a slow stroke
(:mod:`train.road_velocity` measures it; :func:`simex_alpha` corrects for the noise's part, about
40 % of the loss on the corrected simulator, in this reference only; docs/history.md, "Twentieth session"
and "Twenty-first session"): calibrate with drives at the speeds the vehicles drive.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import scipy.linalg
from scipy import signal
from scipy.linalg import expm, solve_discrete_are
from scipy.optimize import least_squares

import shocktwin

from train.campaign import load_campaign, main_wrapper, read_json, require_topics
from train.fit_physics import rest_end_s
from train.observer import P_ATM_BAR, Z95, theta
from train.observer_report import expected_health, health_series
from train.progress import progress
from train.road_bound import FINE_HZ, mount_filter

ACC_DT_S = 1e-3          # the accelerometers' period (SPEC §2)
POT_PER_ACC = 10         # accelerometer samples per potentiometer sample
FINE = round(FINE_HZ * ACC_DT_S)  # the force is built at 4 kHz (the flip is sub-millisecond), then sampled
HINGES_MPS = tuple(np.round(np.arange(0.02, 0.3005, 0.01), 3)) + (0.35, 0.4, 0.5, 0.6, 0.8, 1.0)
TOPICS = ("/acceleration", "/position", "/temperature/shock")
MIN_STROKE_RMS_MPS = 0.02  # a block moving less than this is not read (a rest)


# ---------------------------------------------------------------------------------------
# the stroke velocity: potentiometer behind its RC, accelerometers behind theirs
# ---------------------------------------------------------------------------------------


class StrokeFilter:
    """Steady-state Kalman filter and smoother of ``x = [y, ẏ, b_a, y_f]`` over one
    potentiometer period, with the accelerometer input integrated exactly per millisecond."""

    def __init__(self, pot_rc_hz: float, sigma_accel: float, sigma_bias: float, sigma_pos: float):
        tau = 1.0 / (2 * np.pi * pot_rc_hz)
        a = np.array([[0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 0], [1 / tau, 0, 0, -1 / tau]], float)
        m = np.zeros((5, 5))
        m[:4, :4], m[1, 4] = a, 1.0
        e = expm(m * ACC_DT_S)
        self.phi1, self.g1 = e[:4, :4], e[:4, 4]
        q1 = sigma_accel**2 * np.outer(self.g1, self.g1) + np.diag([0, 0, sigma_bias**2 * ACC_DT_S, 0])
        self.phi, q, self.gs = np.eye(4), np.zeros((4, 4)), np.zeros((4, POT_PER_ACC))
        for j in range(POT_PER_ACC):
            self.phi, q = self.phi1 @ self.phi, self.phi1 @ q @ self.phi1.T + q1
            self.gs = self.phi1 @ self.gs
            self.gs[:, j] = self.g1
        h = np.array([[0, 0, 0, 1.0]])
        self.q, self.r = q, sigma_pos**2  # per potentiometer period
        p_prior = solve_discrete_are(self.phi.T, h.T, q, np.array([[sigma_pos**2]]))
        self.k = (p_prior @ h.T / (p_prior[3, 3] + sigma_pos**2))[:, 0]
        self.p_post = (np.eye(4) - np.outer(self.k, h)) @ p_prior
        self.c = self.p_post @ self.phi.T @ np.linalg.inv(p_prior)

    def forward(self, u: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filtered and predicted states at each potentiometer sample; ``u`` (m, 10) the inputs
        after sample k, ``z`` (m + 1) the samples (NaN: no update; the gain stays the steady one,
        a little below the optimum for the few samples after a gap)."""
        m = len(u)
        xf, xp = np.empty((m + 1, 4)), np.empty((m + 1, 4))
        x = np.array([z[0], 0.0, 0.0, z[0]])
        xf[0] = xp[0] = x
        for k in range(m):
            p = self.phi @ x + self.gs @ u[k]
            xp[k + 1] = p
            x = p + self.k * (z[k + 1] - p[3]) if np.isfinite(z[k + 1]) else p
            xf[k + 1] = x
        return xf, xp

    def smooth(self, xf: np.ndarray, xp: np.ndarray, start: int, end: int) -> np.ndarray:
        """RTS states at samples ``start..end`` from a backward pass begun at ``end``."""
        xs = xf[start:end + 1].copy()
        for k in range(end - start - 1, -1, -1):
            xs[k] = xf[start + k] + self.c @ (xs[k + 1] - xp[start + k + 1])
        return xs

    def fill(self, xs: np.ndarray, u: np.ndarray) -> np.ndarray:
        """States at every millisecond between consecutive smoothed samples: integrated forward
        from each, the mismatch at the next spread linearly (shape (len(xs) − 1) · 10 × 4)."""
        n = len(xs) - 1
        out = np.empty((n, POT_PER_ACC, 4))
        cur = xs[:-1].copy()
        for j in range(POT_PER_ACC):
            out[:, j] = cur
            cur = cur @ self.phi1.T + np.outer(u[:n, j], self.g1)
        out += (np.arange(POT_PER_ACC) / POT_PER_ACC)[None, :, None] * (xs[1:] - cur)[:, None, :]
        return out.reshape(-1, 4)


# ---------------------------------------------------------------------------------------
# one run: a reading of the friction amplitude per block
# ---------------------------------------------------------------------------------------


def law_forces(v: np.ndarray, y: np.ndarray, tau: np.ndarray, v_s: float) -> list[np.ndarray]:
    """The force basis: friction first, then the damping law, its drift, the gas spring."""
    law = [np.maximum(v, 0.0), np.minimum(v, 0.0)]
    law += [np.maximum(v - h, 0.0) for h in HINGES_MPS] + [np.minimum(v + h, 0.0) for h in HINGES_MPS]
    return [np.tanh(v / v_s)] + law + [f * tau for f in law] + [y]


def stroke_input(ra: np.ndarray, obs: dict[str, Any]) -> np.ndarray:
    """The stroke filter's input from ``a1 − a2`` sampled at 1 kHz (m/s²): the accelerometers'
    first-order lag inverted, then each millisecond's mean (trapezoid), not its first sample held."""
    ra = ra + np.r_[0.0, np.diff(ra)] / (2 * np.pi * obs["accel_bw_hz"] * ACC_DT_S)
    return np.r_[0.5 * (ra[1:] + ra[:-1]), ra[-1]]


def block_columns(t: np.ndarray, v: np.ndarray, y: np.ndarray, obs: dict[str, Any],
                  mount: tuple[np.ndarray, np.ndarray], zi: list[np.ndarray] | None
                  ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A block's force columns at the accelerometer's samples (built at ``FINE_HZ`` from the
    velocity ``v`` and extension ``y`` at the block's millisecond times ``t``, through the mount
    and accelerometer filter ``mount``), and the filters' state after it (``zi``: before it)."""
    b, a = mount
    tf = t[0] + np.arange(len(t) * FINE) * ACC_DT_S / FINE
    forces = law_forces(np.interp(tf, t, v), np.interp(tf, t, y), tf / 100.0, obs["friction_v_smooth_mps"])
    state = [np.zeros(max(len(a), len(b)) - 1) for _ in forces] if zi is None else zi
    cols, after = [], []
    for f, z in zip(forces, state):
        col, z_end = signal.lfilter(b, a, f, zi=z)
        cols.append(col[::FINE])
        after.append(z_end)
    return cols, after


def block_alpha(cols: list[np.ndarray], a2: np.ndarray) -> tuple[float, float, float]:
    """Least squares of ``a2`` on the columns and a constant: ``α`` (the first column's), its
    standard deviation and the residual variance (samples where ``a2`` is missing left out)."""
    good = np.isfinite(a2)
    xm = np.column_stack(cols + [np.ones(len(a2))])[good]
    active = np.abs(xm).max(axis=0) > 1e-12
    active[0] = True
    xm = xm[:, active]
    coef = scipy.linalg.lstsq(xm, a2[good], lapack_driver="gelsy")[0]  # QR: ten times an SVD's speed
    r = a2[good] - xm @ coef
    s2 = float(r @ r) / max(1, len(r) - xm.shape[1])
    # var(α) = s² / |the part of α's column the other columns do not explain|²
    rest = xm[:, 0] - xm[:, 1:] @ scipy.linalg.lstsq(xm[:, 1:], xm[:, 0], lapack_driver="gelsy")[0]
    return float(coef[0]), float(np.sqrt(s2 / max(float(rest @ rest), 1e-300))), s2


def velocity_noise(n_ms: int, rng: np.random.Generator, physics: dict[str, Any], opts: dict[str, float],
                   figures: dict[str, float], warm_ms: int = 2000) -> np.ndarray:
    """The stroke filter's velocity (m/s, one per millisecond) when its sensors read noise alone:
    white noise and uniform quantisation at ``figures`` (``accel_noise_mps2``, ``accel_lsb_mps2``
    on ``a1`` and ``a2``, ``pos_noise_m``, ``pos_lsb_m``), through the same input, filter and
    smoother as the observer's; the first ``warm_ms`` (the filter settling) dropped."""
    obs = physics.get("observer") or shocktwin.default_observer_params()
    kal = physics.get("kalman") or shocktwin.default_params()["kalman"]
    m = (n_ms + warm_ms) // POT_PER_ACC + 1
    n = m * POT_PER_ACC

    def acc() -> np.ndarray:
        lsb = figures["accel_lsb_mps2"]
        return rng.normal(0.0, figures["accel_noise_mps2"], n) + rng.uniform(-lsb / 2, lsb / 2, n)

    u = stroke_input(acc() - acc(), obs).reshape(m, POT_PER_ACC)
    lsb = figures["pos_lsb_m"]
    z = rng.normal(0.0, figures["pos_noise_m"], m + 1) + rng.uniform(-lsb / 2, lsb / 2, m + 1)
    kf = StrokeFilter(opts["pot_rc_hz"], opts["sigma_accel"], kal["sigma_bias"], kal["sigma_position"])
    xf, xp = kf.forward(u, z)
    return kf.fill(kf.smooth(xf, xp, 0, m), u)[warm_ms:warm_ms + n_ms, 1]


def simex_alpha(alpha: float, t: np.ndarray, v: np.ndarray, y: np.ndarray, a2: np.ndarray, obs: dict[str, Any],
                mount: tuple[np.ndarray, np.ndarray], zi: list[np.ndarray] | None, physics: dict[str, Any],
                opts: dict[str, float], simex: dict[str, Any], block: int) -> float:
    """``α`` corrected for the velocity's noise by SIMEX (Cook & Stefanski 1994): the block read
    again with the sensors' noise (:func:`velocity_noise`, ``simex["figures"]``) added once and
    twice more (``simex["reps"]`` draws each, seeded by ``simex["seed"]`` and the block), and the
    reads at noise variance λ = 1, 2, 3 times the data's extrapolated quadratically to λ = 0:
    ``3 α₁ − 3 α₂ + α₃``."""
    rng = np.random.default_rng([int(simex["seed"]), block])
    means = [alpha]
    for extra in (1, 2):
        reads = []
        for _ in range(int(simex["reps"])):
            noise = sum(velocity_noise(len(t), rng, physics, opts, simex["figures"]) for _ in range(extra))
            reads.append(block_alpha(block_columns(t, v + noise, y, obs, mount, zi)[0], a2)[0])
        means.append(float(np.mean(reads)))
    return 3 * means[0] - 3 * means[1] + means[2]


def skewed(x: np.ndarray, skew_s: float) -> np.ndarray:
    """``x`` (sampled at 1 kHz) as sampled ``skew_s`` later: a band-limited fractional shift by
    FFT (padded to twice its length with its last value; missing samples bridged, then left
    missing)."""
    ok = np.isfinite(x)
    idx = np.arange(len(x))
    filled = np.interp(idx, idx[ok], x[ok]) if ok.any() else np.zeros(len(x))
    n = len(filled)
    size = 1 << int(np.ceil(np.log2(2 * max(n, 1))))
    padded = np.r_[filled, np.full(size - n, filled[-1] if n else 0.0)]
    f = np.fft.rfftfreq(size, ACC_DT_S)
    out = np.fft.irfft(np.fft.rfft(padded) * np.exp(2j * np.pi * f * skew_s), size)[:n]
    out[~ok] = np.nan
    return out


def block_readings(path: str, physics: dict[str, Any], opts: dict[str, float],
                   velocity: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                   simex: dict[str, Any] | None = None, a2_skew_s: float = 0.0) -> dict[str, np.ndarray]:
    """Per block of a run: ``t_s`` (block end), ``alpha_n``, ``alpha_sd_n`` (the regression's own),
    ``residual_mps2``, ``temp_c`` (shock thermocouple), ``stroke_rms_mps``.

    ``velocity`` (a study's hook, :mod:`train.road_velocity`): called with each block's
    millisecond times (s) and the stroke filter's velocity there, returns the velocity to regress
    instead (the simulator's truth, or the filter's with more noise); the blocks read and their
    stroke RMS stay the filter's. ``simex`` (``{"figures", "reps", "seed"}``): each block's ``α``
    corrected for the velocity's noise (:func:`simex_alpha`; its sd stays the regression's).
    ``a2_skew_s``: read as if ``a2`` had been sampled this much after ``a1`` (:func:`skewed`; a
    study of the data acquisition)."""
    lg = shocktwin.read_log(path)
    missing = [t for t in TOPICS if t not in lg.topics]
    if missing:
        raise ValueError(f"{path}: the road observer needs {', '.join(missing)}, which this log lacks")
    obs = physics.get("observer") or shocktwin.default_observer_params()
    kal = physics.get("kalman") or shocktwin.default_params()["kalman"]
    acc, pos, tc = lg.topic("/acceleration"), lg.topic("/position"), lg.topic("/temperature/shock")
    t_acc = acc["t_s"]
    if a2_skew_s:
        acc = {**acc, "a2_mps2": skewed(acc["a2_mps2"], a2_skew_s)}
    ra = acc["a1_mps2"] - acc["a2_mps2"]
    ok = np.isfinite(ra)
    if ok.sum() < 2 or not np.isfinite(pos["position_m"]).any() or not np.isfinite(tc["temperature_c"]).any():
        raise ValueError(f"{path}: no usable /acceleration, /position or /temperature/shock samples")
    ra = stroke_input(np.interp(t_acc, t_acc[ok], ra[ok]), obs)  # a missing sample: its neighbours' line
    first = int(np.argmax(np.isfinite(pos["position_m"])))  # the filter starts at the first position read
    pos = {k: v[first:] for k, v in pos.items()}
    tc_ok = np.isfinite(tc["temperature_c"])
    tc = {k: v[tc_ok] for k, v in tc.items()}
    i0 = int(np.searchsorted(t_acc, pos["t_s"][0] - 1e-6))
    m = min((len(t_acc) - i0) // POT_PER_ACC, len(pos["t_s"]) - 1)
    u = ra[i0:i0 + m * POT_PER_ACC].reshape(m, POT_PER_ACC)
    kf = StrokeFilter(opts["pot_rc_hz"], opts["sigma_accel"], kal["sigma_bias"], kal["sigma_position"])
    xf, xp = kf.forward(u, pos["position_m"][:m + 1])
    b, a = mount_filter(obs)
    per_block = int(round(opts["block_s"] / (ACC_DT_S * POT_PER_ACC)))
    lag = int(round(opts["lag_s"] / (ACC_DT_S * POT_PER_ACC)))
    zi: list[np.ndarray] | None = None
    out: dict[str, list[float]] = {k: [] for k in ("t_s", "alpha_n", "alpha_sd_n", "residual_mps2", "temp_c", "stroke_rms_mps")}
    for k0 in range(0, m - per_block - lag, per_block):
        xs = kf.smooth(xf, xp, k0, k0 + per_block + lag)[:per_block + 1]
        x = kf.fill(xs, u[k0:k0 + per_block])
        t = t_acc[i0 + k0 * POT_PER_ACC:i0 + (k0 + per_block) * POT_PER_ACC]
        v = x[:, 1] if velocity is None else velocity(t, x[:, 1])
        zi_start = zi
        cols, zi = block_columns(t, v, x[:, 0], obs, (b, a), zi)
        stroke = float(np.sqrt(np.mean(x[:, 1] ** 2)))
        if t[0] < opts["settle_s"] or stroke < MIN_STROKE_RMS_MPS:
            continue
        a2 = acc["a2_mps2"][i0 + k0 * POT_PER_ACC:i0 + (k0 + per_block) * POT_PER_ACC]
        alpha, sd, s2 = block_alpha(cols, a2)
        if simex is not None:
            alpha = simex_alpha(alpha, t, v, x[:, 0], a2, obs, (b, a), zi_start, physics, opts, simex, k0 // per_block)
        out["t_s"].append(float(t[-1]))
        out["alpha_n"].append(alpha)
        out["alpha_sd_n"].append(sd)
        out["residual_mps2"].append(float(np.sqrt(s2)))
        out["temp_c"].append(float(np.mean(np.interp(t, tc["t_s"], tc["temperature_c"]))))
        out["stroke_rms_mps"].append(stroke)
    return {k: np.asarray(v) for k, v in out.items()}


def calibrated_blocks(r: dict[str, np.ndarray], model: dict[str, Any]) -> dict[str, np.ndarray]:
    """The blocks a calibration vouches for: none slower than the slowest it read (dt-core's rule,
    ``slowest_calibrated_stroke_rms_mps``). The friction read falls short of the calibration's
    line the slower the stroke, and a calibration at faster strokes cannot say by how much."""
    slowest = model.get("filters", {}).get("slowest_calibrated_stroke_rms_mps")
    if slowest is None:
        return r
    keep = r["stroke_rms_mps"] >= slowest
    return {k: v[keep] for k, v in r.items()}


def _readings(args: tuple[str, dict[str, Any], dict[str, float]]) -> dict[str, np.ndarray]:
    return block_readings(*args)


def readings(paths: Sequence[Path], physics: dict[str, Any], opts: dict[str, float], jobs: int,
             cache: Path | None = None) -> list[dict[str, np.ndarray]]:
    """Every run's blocks; with ``cache``, kept there per run (keyed by the file's name, size and
    time, the options and the physics) and read back instead of computed again."""
    def key(p: Path) -> Path | None:
        if cache is None:
            return None
        st = p.stat()
        h = hashlib.sha256(json.dumps([p.name, st.st_size, st.st_mtime_ns, opts, physics], sort_keys=True).encode())
        return cache / f"{p.stem}-{h.hexdigest()[:16]}.npz"

    keys = [key(Path(p)) for p in paths]
    todo = [p for p, k in zip(paths, keys) if k is None or not k.exists()]
    done = {}
    if todo:  # all cached: no worker pool
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            done = dict(zip(todo, progress(pool.map(_readings, [(str(p), physics, opts) for p in todo]), total=len(todo),
                                           desc="road blocks", unit="run")))
    out = []
    for p, k in zip(paths, keys):
        if p in done:
            if k is not None:
                k.parent.mkdir(parents=True, exist_ok=True)
                np.savez(k, **done[p])
            out.append(done[p])
        else:
            with np.load(k) as z:  # type: ignore[arg-type]
                out.append({name: z[name] for name in z.files})
    return out


# ---------------------------------------------------------------------------------------
# the measurement model: alpha = a + b p_g
# ---------------------------------------------------------------------------------------


def gas_ratio(temp_c: np.ndarray, physics: dict[str, Any]) -> np.ndarray:
    obs = physics.get("observer") or shocktwin.default_observer_params()
    return theta({"gas_temp_c": temp_c, "extension_m": np.zeros_like(temp_c)}, obs)


def fit_model(blocks: Sequence[dict[str, np.ndarray]], labels: Sequence[float], physics: dict[str, Any]) -> tuple[np.ndarray, float]:
    """(a, b) and the robust spread of the residuals, N."""
    alpha = np.concatenate([r["alpha_n"] for r in blocks])
    p_g = np.concatenate([(p + P_ATM_BAR) * gas_ratio(r["temp_c"], physics) - P_ATM_BAR for r, p in zip(blocks, labels)])
    x = np.column_stack([np.ones_like(p_g), p_g])
    c0 = np.linalg.lstsq(x, alpha, rcond=None)[0]
    scale = 1.4826 * np.median(np.abs(alpha - x @ c0)) + 1e-9
    coef = least_squares(lambda c: (alpha - x @ c) / scale, c0, loss="soft_l1").x
    r = alpha - x @ coef
    return coef, float(1.4826 * np.median(np.abs(r - np.median(r))))


def charge_of(r: dict[str, np.ndarray], model: dict[str, Any], physics: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Each block's charge reading (bar gauge at 20 °C) and its spread, bar."""
    th = gas_ratio(r["temp_c"], physics)
    a, b = model["a_n"], model["b_n_per_bar"]
    p = ((r["alpha_n"] - a) / b + P_ATM_BAR) / th - P_ATM_BAR
    return p, np.full_like(p, model["block_sd_n"]) / (b * th)


def streaming_constants(physics: dict[str, Any], opts: dict[str, float]) -> dict[str, Any]:
    """What dt-core's streaming ``road`` observer needs beside the fit, so that it applies the
    same filters as :func:`block_readings` without rebuilding them: the observer parameters (gas
    ratio, mount, accelerometer filter), the stroke filter's matrices and steady gains, the mount
    filter's coefficients at ``FINE_HZ``, the hinges."""
    obs = physics.get("observer") or shocktwin.default_observer_params()
    kal = physics.get("kalman") or shocktwin.default_params()["kalman"]
    kf = StrokeFilter(opts["pot_rc_hz"], opts["sigma_accel"], kal["sigma_bias"], kal["sigma_position"])
    b, a = mount_filter(obs)
    return {"observer": obs, "filters": {
        "phi1": kf.phi1.tolist(), "g1": kf.g1.tolist(), "phi": kf.phi.tolist(), "gs": kf.gs.tolist(),
        "gain": kf.k.tolist(), "smoother": kf.c.tolist(), "mount_b": b.tolist(), "mount_a": a.tolist(),
        "fine": FINE, "hinges_mps": [float(h) for h in HINGES_MPS], "min_stroke_rms_mps": MIN_STROKE_RMS_MPS}}


def cmd_fit(args: argparse.Namespace) -> int:
    physics = read_json(args.physics)
    campaign = load_campaign(args.campaign)
    campaign.require_labels()
    require_topics(campaign.runs, TOPICS, "the road observer")
    opts = options(args)
    blocks = readings([r.path for r in campaign.runs], physics, opts, args.jobs, args.cache)
    labels = [float(r.label_bar) for r in campaign.runs]  # type: ignore[arg-type]
    use = [i for i, b in enumerate(blocks) if len(b["alpha_n"]) > 0]
    if len({labels[i] for i in use}) < 2:
        raise ValueError(f"{args.campaign}: road runs at two charges at least are needed (read: "
                         f"{', '.join(campaign.runs[i].name for i in use) or 'none'})")
    coef, sd = fit_model([blocks[i] for i in use], [labels[i] for i in use], physics)
    model = {"a_n": float(coef[0]), "b_n_per_bar": float(coef[1]), "block_sd_n": sd, **opts,
             **streaming_constants(physics, opts)}
    # What one drive file reads beside another is measured by leaving each drive out (every run
    # of it, at every charge); a campaign of one drive file can only leave one run out.
    drive = [drive_of(campaign.runs[i]) for i in range(len(campaign.runs))]
    by_drive = len({drive[i] for i in use}) >= 2
    held = []
    for i in use:
        rest = [j for j in use if (drive[j] != drive[i] if by_drive else j != i)]
        if len({labels[j] for j in rest}) < 2:
            continue
        ci, sdi = fit_model([blocks[j] for j in rest], [labels[j] for j in rest], physics)
        p, s = charge_of(blocks[i], {**model, "a_n": ci[0], "b_n_per_bar": ci[1], "block_sd_n": sdi}, physics)
        w = 1 / s**2
        mean, stat = float(np.sum(w * p) / np.sum(w)), float(1 / np.sqrt(np.sum(w)))
        held.append((campaign.runs[i].name, labels[i], mean, stat))
    excess = [max(0.0, (m - lab) ** 2 - s**2) for _, lab, m, s in held]
    held_sd = float(np.sqrt(np.mean(excess))) if excess else 0.0
    tol = args.unit_tolerance_pct / 100.0
    # another unit's seal: its friction off by the datasheet tolerance, offset and slope alike
    model["systematic_sd_bar"] = float(np.hypot(held_sd, tol * coef[0] / coef[1]))
    model["systematic_rel"] = tol
    model["held_out"] = "drive" if by_drive else "run"
    model["held_out_sd_bar"] = held_sd
    model["held_out_reads"] = [{"run": n, "label_bar": lab, "read_bar": m, "sd_bar": s} for n, lab, m, s in held]
    model["drives"] = sorted({drive[i] for i in use})
    model["campaign"] = str(args.campaign)
    model["blocks"] = int(sum(len(blocks[i]["alpha_n"]) for i in use))
    model["filters"]["slowest_calibrated_stroke_rms_mps"] = float(min(blocks[i]["stroke_rms_mps"].min() for i in use))
    model["simulated"] = campaign.simulated
    args.out.write_text(json.dumps(model, indent=2) + "\n")
    print(f"road observer: alpha = {coef[0]:.2f} N + {coef[1]:.3f} N/bar · p_g over {model['blocks']} blocks of "
          f"{opts['block_s']:g} s; block spread {sd:.2f} N ({sd / coef[1]:.2f} bar); systematic "
          f"{held_sd:.2f} bar leaving one {model['held_out']} out ({len(model['drives'])} drive files), "
          f"{model['systematic_sd_bar']:.2f} bar + {100 * tol:g} % of the charge with another unit's seal "
          f"(--unit-tolerance-pct); blocks slower than {model['filters']['slowest_calibrated_stroke_rms_mps']:.3f} m/s "
          f"stroke RMS (the slowest read here) will not be read")
    for n, lab, m, s in held:
        print(f"  {n}: {lab:g} bar read as {m:.2f} ± {s:.2f} bar without its {model['held_out']}")
    print(f"wrote {args.out}" + (" (simulated data)" if campaign.simulated else ""))
    return 0


# ---------------------------------------------------------------------------------------
# held-out roads: a recursive estimate with its interval
# ---------------------------------------------------------------------------------------


def track(p: np.ndarray, sd: np.ndarray, t: np.ndarray, model: dict[str, Any], prior: tuple[float, float],
          walk_bar2_per_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random-walk estimate after each block: (mean, lo, hi), the 95 % interval widened by the
    systematic part, ``systematic_sd_bar² + (systematic_rel p̂)²`` (as dt-core's observer), or with a
    unit's baseline at ``p_b`` only its slope's part, ``(systematic_rel (p̂ − p_b))²``, beside what is
    left of the rest."""
    mean, var = prior[0], prior[1] ** 2
    out = np.empty((len(p), 3))
    last = t[0] if len(t) else 0.0
    sys2, rel = model["systematic_sd_bar"] ** 2, model.get("systematic_rel", 0.0)
    for i, (pi, si, ti) in enumerate(zip(p, sd, t)):
        var += walk_bar2_per_s * max(0.0, ti - last)
        last = ti
        k = var / (var + si**2)
        mean, var = mean + k * (pi - mean), (1 - k) * var
        half = Z95 * np.sqrt(var + sys2 + (rel * (mean - model.get("baseline_bar", 0.0))) ** 2)
        out[i] = (mean, mean - half, mean + half)
    return out[:, 0], out[:, 1], out[:, 2]


def with_baseline(model: dict[str, Any], physics: dict[str, Any], path: Path, bar: float,
                  r: dict[str, np.ndarray]) -> dict[str, Any]:
    """The model for one unit, from a drive of it at a known charge ``bar`` (its blocks ``r``):
    its seal's offset read, so that only the slope's tolerance is left systematic."""
    if len(r["alpha_n"]) == 0:
        raise ValueError(f"{path}: the baseline drive has no block to read (no stroke?)")
    p_g = (bar + P_ATM_BAR) * gas_ratio(r["temp_c"], physics) - P_ATM_BAR
    offset = r["alpha_n"] - (model["a_n"] + model["b_n_per_bar"] * p_g)
    stat = model["block_sd_n"] / np.sqrt(len(offset)) / model["b_n_per_bar"]
    return {**model, "a_n": model["a_n"] + float(np.mean(offset)), "baseline_bar": bar,
            "systematic_sd_bar": float(np.hypot(model["held_out_sd_bar"], stat))}


def drive_of(run: Any) -> str:
    """The drive file a run played: its excitation and seed (every charge of a simulated road
    campaign plays the same file; ``drive_seed`` when it was chosen apart from the rig's)."""
    meta = run.log.metadata
    return f"{meta.get('excitation', run.run_id)} (seed {meta.get('drive_seed', meta.get('seed', '?'))})"


def calibration_options(model: dict[str, Any]) -> dict[str, float]:
    """The block options a calibration was fitted with (what :func:`block_readings` needs)."""
    return {k: model[k] for k in ("block_s", "lag_s", "pot_rc_hz", "sigma_accel", "settle_s")}


def options(args: argparse.Namespace) -> dict[str, float]:
    return {"block_s": args.block_s, "lag_s": args.lag_s, "pot_rc_hz": args.pot_rc_hz,
            "sigma_accel": args.sigma_accel, "settle_s": args.settle_s}


def cmd_evaluate(args: argparse.Namespace) -> int:
    physics = read_json(args.physics)
    model = read_json(args.road)
    opts = calibration_options(model)
    args.out.mkdir(parents=True, exist_ok=True)
    cache = args.out / "blocks"
    baselines = {}
    for spec in args.baseline:
        name, _, rest = spec.partition("=")
        path, _, bar = rest.rpartition("@")
        if not name or not path or not bar:
            raise ValueError(f"--baseline {spec!r}: expected SET=RUN.mcap@BAR")
        baselines[name] = (Path(path), float(bar))
    unknown = set(baselines) - {s.partition("=")[0] for s in args.sets}
    if unknown:
        raise ValueError(f"--baseline for {', '.join(sorted(unknown))}: no such set among {', '.join(args.sets)}")
    rows, traces = [], {}
    for spec in args.sets:
        name, _, d = spec.partition("=")
        campaign = load_campaign(Path(d))
        campaign.require_labels()
        blocks = [calibrated_blocks(r, model) for r in readings([r.path for r in campaign.runs], physics, opts, args.jobs, cache)]
        set_model = dict(model)
        if name in baselines:
            raw = readings([baselines[name][0]], physics, opts, 1, cache)[0]
            base = calibrated_blocks(raw, model)
            if len(raw["alpha_n"]) and not len(base["alpha_n"]):
                raise ValueError(
                    f"{baselines[name][0]}: every block of the baseline drive is slower than the calibration's slowest "
                    f"({model['filters']['slowest_calibrated_stroke_rms_mps']:.3f} m/s stroke RMS, fastest here "
                    f"{float(raw['stroke_rms_mps'].max()):.3f}): drive it faster, or calibrate at its speed")
            set_model = with_baseline(model, physics, *baselines[name], base)
        for run, r in zip(campaign.runs, blocks):
            lab = float(run.label_bar)  # type: ignore[arg-type]
            if len(r["alpha_n"]) == 0:
                rows.append({"set": name, "run": run.name, "label_bar": lab, "blocks": 0})
                continue
            p, sd = charge_of(r, set_model, physics)
            t = r["t_s"]
            est, lo, hi = track(p, sd, t, set_model, (args.prior_mean_bar, args.prior_sd_bar), args.walk_bar2_per_s)
            since = t - rest_end_s(run)  # drive since the excitation's onset, at each block's end
            late = since >= args.score_from_s
            health = health_series(t, est, lo, hi, np.ones(len(t), bool))
            want = expected_health(lab)
            right = np.array([h == want for h in health])
            settled = next((float(since[i]) for i in range(len(t)) if right[i:].all()), None)
            rows.append({
                "set": name, "run": run.name, "label_bar": lab, "blocks": int(len(t)),
                "block_rmse_bar": float(np.sqrt(np.mean((p - lab) ** 2))),
                "rmse_bar": float(np.sqrt(np.mean((est[late] - lab) ** 2))) if late.any() else None,
                "final_bar": float(est[-1]), "final_lo_bar": float(lo[-1]), "final_hi_bar": float(hi[-1]),
                "coverage": float(np.mean((lo[late] <= lab) & (lab <= hi[late]))) if late.any() else None,
                "verdict": health[-1], "expected": want, "right_from_s": settled,
                "false_alarm": bool(want == "ok" and any(h in ("leak", "low") for h in health)),
                "baseline": str(baselines[name][0].name) if name in baselines else None,
                "residual_mps2": float(np.median(r["residual_mps2"])),
            })
            half0 = Z95 * np.hypot(args.prior_sd_bar, set_model["systematic_sd_bar"])
            traces[f"{name}/{run.name}"] = (since, p, np.r_[args.prior_mean_bar, est], np.r_[args.prior_mean_bar - half0, lo],
                                            np.r_[args.prior_mean_bar + half0, hi], lab)
    report(args.out, rows, traces, model, args)
    return 0


def report(out: Path, rows: list[dict[str, Any]], traces: dict[str, Any], model: dict[str, Any], args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (out / "road_observer.json").write_text(json.dumps({"model": model, "runs": rows}, indent=2) + "\n")
    lines = ["# Reading the charge on a road (SIMULATED DATA: dt-sim road drive files)", "",
             f"Calibration: `{model['campaign']}`, alpha = {model['a_n']:.2f} N + {model['b_n_per_bar']:.3f} N/bar p_g, "
             f"block spread {model['block_sd_n']:.2f} N, systematic {model['held_out_sd_bar']:.2f} bar (leaving one "
             f"{model['held_out']} out, {len(model['drives'])} drive files), {model['systematic_sd_bar']:.2f} bar + "
             f"{100 * model['systematic_rel']:g} % of the charge with another unit's seal. "
             f"Blocks of {model['block_s']:g} s, each read {model['lag_s']:g} s after its end; scored from "
             f"{args.score_from_s:g} s of drive on.", "",
             "| set | run | charge, bar | blocks | one block, RMSE bar | estimate RMSE, bar | final | 95 % interval | coverage | verdict | right from |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if not r["blocks"]:
            lines.append(f"| {r['set']} | {r['run']} | {r['label_bar']:g} | 0 | | | | | | | |")
            continue
        fmt = lambda v, f="{:.2f}": "—" if v is None else f.format(v)  # noqa: E731
        lines.append(f"| {r['set']} | {r['run']} | {r['label_bar']:g} | {r['blocks']} | {r['block_rmse_bar']:.2f} | "
                     f"{fmt(r['rmse_bar'])} | {r['final_bar']:.2f} | [{r['final_lo_bar']:.2f}, {r['final_hi_bar']:.2f}] | "
                     f"{fmt(r['coverage'], '{:.0%}')} | {r['verdict']} (want {r['expected']}) | {fmt(r['right_from_s'], '{:.0f} s')} |")
    (out / "road_observer.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    if traces:
        n = len(traces)
        fig, axes = plt.subplots(n, 1, figsize=(9, 2.2 * n), sharex=True, squeeze=False)
        for ax, (name, (since, p, est, lo, hi, lab)) in zip(axes[:, 0], traces.items()):
            steps = np.r_[0.0, since]  # the prior at the drive's start, then each block's end
            ax.plot(since, p, ".", ms=4, color="0.5", label="one block's reading")
            ax.fill_between(steps, lo, hi, step="post", alpha=0.3, label="95 % interval")
            ax.step(steps, est, where="post", label="estimate")
            ax.axhline(lab, color="k", lw=0.8, ls="--", label="true charge")
            ax.set_ylim(-4, 18)
            ax.set_ylabel("bar")
            ax.set_title(name, fontsize=8)
        axes[0, 0].legend(fontsize=7, ncol=4)
        axes[-1, 0].set_xlabel("drive, s")
        fig.suptitle("The charge read on a road from the cheap suite (SIMULATED DATA)", fontsize=9)
        fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.3 / (2.2 * n)))
        fig.savefig(out / "road_observer.png", dpi=90)
        plt.close(fig)
    print(f"wrote {out / 'road_observer.md'}, road_observer.json, road_observer.png (simulated data)")


def cmd_skew(args: argparse.Namespace) -> int:
    """Each run read with ``a2`` taken later than ``a1`` by each skew: the mean friction read and
    the charge it gives, against the unskewed read. A calibration absorbs a skew its drives
    share; this says how closely the vehicles' acquisition must match the rig's."""
    physics = read_json(args.physics)
    model = read_json(args.road)
    opts = calibration_options(model)
    skews = [float(v) for v in args.skew_us.split(",")]
    print("The friction read against a sampling skew of a2 behind a1"
          + (" (SIMULATED DATA)" if model.get("simulated") else "") + "\n")
    print("| run | skew, µs | blocks | alpha, N | change | charge read, bar | change, bar |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for path in args.runs:
        base: tuple[float, float] | None = None
        for us in skews:
            r = calibrated_blocks(block_readings(str(path), physics, opts, a2_skew_s=us * 1e-6), model)
            if not len(r["alpha_n"]):
                print(f"| {path.name} | {us:g} | 0 | | | | |")
                continue
            alpha, bar = float(np.mean(r["alpha_n"])), float(np.mean(charge_of(r, model, physics)[0]))
            base = base or (alpha, bar)
            print(f"| {path.name} | {us:g} | {len(r['alpha_n'])} | {alpha:.2f} | {100 * (alpha / base[0] - 1):+.2f} % "
                  f"| {bar:.2f} | {bar - base[1]:+.2f} |")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m train.road_observer", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("fit", "evaluate"):
        s = sub.add_parser(name)
        s.add_argument("--physics", required=True, type=Path, help="physics.json (mount, filter, geometry)")
        s.add_argument("--out", required=True, type=Path)
        s.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
        if name == "fit":
            s.add_argument("--campaign", required=True, type=Path, help="labelled road runs (simulate --road)")
            s.add_argument("--block-s", type=float, default=10.0, help="block length, s")
            s.add_argument("--lag-s", type=float, default=0.5, help="smoother lag after a block's end, s")
            s.add_argument("--pot-rc-hz", type=float, default=50.0,
                           help="the potentiometer's first-order anti-alias cutoff, Hz (the rig's: dt-sim sensor table)")
            s.add_argument("--sigma-accel", type=float, default=0.3, help="relative acceleration noise, m/s²")
            s.add_argument("--settle-s", type=float, default=10.0, help="blocks before this time are not read, s")
            s.add_argument("--cache", type=Path, help="keep each run's blocks here and read them back")
            s.add_argument("--unit-tolerance-pct", type=float, default=10.0,
                           help="the seal friction's unit-to-unit tolerance, %% (a datasheet figure, as in train.observer)")
        else:
            s.add_argument("--road", required=True, type=Path, help="the fit's output")
            s.add_argument("--prior-mean-bar", type=float, default=6.0)
            s.add_argument("--prior-sd-bar", type=float, default=6.0)
            s.add_argument("--walk-bar2-per-s", type=float, default=1e-4, help="the charge's random walk")
            s.add_argument("--score-from-s", type=float, default=60.0, help="score the estimate from this much drive on")
            s.add_argument("--baseline", action="append", default=[], metavar="SET=RUN.mcap@BAR",
                           help="a drive of that set's unit at a known charge (after a service): reads its seal's offset")
            s.add_argument("sets", nargs="+", help="NAME=DIR of held-out road runs")
    s = sub.add_parser("skew", help="how a sampling skew of a2 behind a1 moves the read (a data-acquisition study)")
    s.add_argument("--physics", required=True, type=Path, help="physics.json (mount, filter, geometry)")
    s.add_argument("--road", required=True, type=Path, help="a road calibration (the fit's output)")
    s.add_argument("--skew-us", default="0,25,50,100,250", help="skews of a2 behind a1 to read at, µs (comma separated)")
    s.add_argument("runs", nargs="+", type=Path, help="road runs at known charges")
    args = ap.parse_args(argv)
    return {"fit": cmd_fit, "evaluate": cmd_evaluate, "skew": cmd_skew}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
