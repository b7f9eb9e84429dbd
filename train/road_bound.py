"""How much the cheap suite could know of the charge on a road: a Cramér–Rao bound.

The observer (dt-core `charge`) reads the seal friction's flip at each velocity reversal, one
window at a time, and only at the dyno's sines; on a road it reads nothing (docs/history.md, "Fifteenth
session"). This asks whether the information is there at all. The body accelerometer `a2`
is modelled over a whole stretch of drive, every reversal at once:

    F(t)  = α tanh(ẏ/v_s) + Σ_j c_j b_j(ẏ) + k_g y + f_0        (damper force on the body)
    a2    = H_acc * F + c_0 + ε,   ε ~ N(0, σ²) white at 1 kHz

with `H_acc` the calibrated body-end mount (mass, natural frequency, damping) followed by the
accelerometer's first-order filter, `b_j` a flexible damping law (the extension and
compression slopes and hinges at ±0.05 and ±0.15 m/s, all unknown), `k_g` the gas spring's
stiffness and `f_0`, `c_0` offsets, all unknown. The model is linear in its parameters, so
the Fisher information is `RᵀR/σ²` with `R` the regressors; the bound on `α` has the others
profiled out, and the charge's follows through `dα/dp` (the calibration's `step_per_bar_n`).
Noise only, one unit, the stroke velocity taken as known: a lower bound on what any estimator
could reach from these sensors, not a promise. The drive files are drawn here again with
numpy from ISO 8608 and the quarter-car of dt-sim (`crates/dt-sim/README.md`); the dyno's sine
is computed the same way for comparison. Simulated parameters throughout.

    python -m train.road_bound --physics out/physics.json [--seconds 60,600]
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import signal

from train.campaign import read_json
from train.observer_report import ACC_LSB_MPS2, ACC_NOISE_MPS2

FS_HZ = 1000.0           # the accelerometer's rate: the bound's samples
FINE_HZ = 4000.0         # the drive and the mount are computed at this rate, then sampled
M_S, M_U, K_S, K_T, C_S = 350.0, 45.0, 22e3, 200e3, 1.8e3
CLASS_GD_N0 = {"A": 16e-6, "B": 64e-6, "C": 256e-6, "D": 1024e-6, "E": 4096e-6}
BAND_HZ = (0.5, 20.0)
HINGES_MPS = (0.05, 0.15)


def stroke_psd(f: np.ndarray, speed_kmh: float, road_class: str) -> np.ndarray:
    """ISO 8608 displacement PSD at ``speed_kmh`` through the quarter-car's deflection, m²/Hz."""
    v = speed_kmh / 3.6
    road = CLASS_GD_N0[road_class] * ((f / v) / 0.1) ** -2 / v
    s = 2j * np.pi * f
    a, b, c = M_S * s**2 + C_S * s + K_S, C_S * s + K_S, M_U * s**2 + C_S * s + K_S + K_T
    return np.abs(K_T * M_S * s**2 / (a * c - b**2)) ** 2 * road


def road_drive(t: np.ndarray, speed_kmh: float, road_class: str, seed: int,
               n: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """Extension and its rate of a road drive file (random phases), m and m/s."""
    rng = np.random.default_rng(seed)
    edges = BAND_HZ[0] * (BAND_HZ[1] / BAND_HZ[0]) ** (np.arange(n + 1) / n)
    f = edges[:-1] + np.diff(edges) * rng.random(n)
    amp = np.sqrt(2 * stroke_psd(f, speed_kmh, road_class) * np.diff(edges))
    phase = 2 * np.pi * rng.random(n)
    y, yd = np.empty_like(t), np.empty_like(t)
    for i in range(0, len(t), 20_000):  # in pieces: 240 sines × 600 s at 1 kHz is 1 GB at once
        arg = 2 * np.pi * np.outer(t[i:i + 20_000], f) + phase
        y[i:i + 20_000], yd[i:i + 20_000] = np.sin(arg) @ amp, np.cos(arg) @ (amp * 2 * np.pi * f)
    return y, yd


def sine_drive(t: np.ndarray, freq_hz: float, amp_m: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    w = 2 * np.pi * freq_hz
    return amp_m * np.sin(w * t), amp_m * w * np.cos(w * t)


def mount_filter(obs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Body acceleration per newton of damper force, ``s² / (m s² + c s + k)``, through the
    accelerometer's first-order filter: the calibrated ``observer`` section's mount, discretised
    at ``FINE_HZ`` with a first-order hold (``lfilter`` coefficients)."""
    m, wn, wc = obs["mount_mass_kg"], 2 * np.pi * obs["mount_freq_hz"], 2 * np.pi * obs["accel_bw_hz"]
    num = np.polymul([1.0, 0.0, 0.0], [wc])
    den = np.polymul([m, 2 * obs["mount_zeta"] * m * wn, m * wn**2], [1.0, wc])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", signal.BadCoefficients)
        b, a, _ = signal.cont2discrete((num, den), 1 / FINE_HZ, method="foh")
    return np.ravel(b), np.ravel(a)


def regressors(y: np.ndarray, yd: np.ndarray, obs: dict[str, Any]) -> np.ndarray:
    """Columns of `a2` per unit of each parameter, at the accelerometer's 1 kHz, from the drive
    at ``FINE_HZ`` (the friction flips within a millisecond: the mount is integrated at 4 kHz,
    first-order hold, 0.5 % from an ODE solver); the first column is the friction amplitude."""
    vs = obs["friction_v_smooth_mps"]
    forces = [np.tanh(yd / vs), np.maximum(yd, 0.0), np.minimum(yd, 0.0)]
    for h in HINGES_MPS:
        forces += [np.maximum(yd - h, 0.0), np.minimum(yd + h, 0.0)]
    forces += [y, np.ones_like(y)]
    b, a = mount_filter(obs)
    step = round(FINE_HZ / FS_HZ)
    cols = [signal.lfilter(b, a, f)[::step] for f in forces]
    cols.append(np.ones_like(cols[0]))  # the accelerometer's offset c0
    return np.column_stack(cols)


def sd_bar(y: np.ndarray, yd: np.ndarray, obs: dict[str, Any], settle_s: float = 1.0) -> float:
    """The bound's standard deviation of the charge, bar, from the whole stretch (the drive
    ``y``, ``yd`` at ``FINE_HZ``; the first ``settle_s`` left out)."""
    r = regressors(y, yd, obs)[int(settle_s * FS_HZ):]
    sigma2 = ACC_NOISE_MPS2**2 + ACC_LSB_MPS2**2 / 12
    info = r.T @ r / sigma2
    i_alpha = info[0, 0] - info[0, 1:] @ np.linalg.solve(info[1:, 1:], info[1:, 0])
    return float(1.0 / np.sqrt(i_alpha) / obs["step_per_bar_n"])


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m train.road_bound", description=__doc__.split("\n\n")[0])
    ap.add_argument("--physics", required=True, type=Path, help="physics.json with a calibrated observer")
    ap.add_argument("--seconds", default="60,600", help="stretch lengths, s, comma separated")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    obs = read_json(args.physics).get("observer")
    if not obs:
        raise SystemExit(f"{args.physics}: no `observer` section: run `python -m train.observer fit` first")
    drives = {
        "dyno sine 1 Hz, 80 mm p-p": lambda t: sine_drive(t, 1.0),
        "dyno sine 2 Hz, 80 mm p-p": lambda t: sine_drive(t, 2.0),
        "road class B, 90 km/h": lambda t: road_drive(t, 90.0, "B", args.seed),
        "road class C, 60 km/h": lambda t: road_drive(t, 60.0, "C", args.seed),
        "road class C, 30 km/h": lambda t: road_drive(t, 30.0, "C", args.seed),
    }
    seconds = [float(s) for s in args.seconds.split(",")]
    print("Cramér–Rao bound on the charge from the body accelerometer (friction channel, every "
          "reversal, flexible damping law, noise only, one unit; simulated parameters), sd in bar:")
    print(f"{'drive':32s}" + "".join(f"{f'after {s:g} s':>14s}" for s in seconds) + f"{'reversals/s':>14s}")
    for name, drive in drives.items():
        row = []
        for s in seconds:
            t = np.arange(0.0, s + 1.0, 1 / FINE_HZ)
            y, yd = drive(t)
            row.append(sd_bar(y, yd, obs))
        t = np.arange(0.0, 60.0, 1 / FINE_HZ)
        rev = np.count_nonzero(np.diff(np.sign(drive(t)[1])) != 0) / 60.0
        print(f"{name:32s}" + "".join(f"{v:14.3f}" for v in row) + f"{rev:14.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
