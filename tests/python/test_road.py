"""The simulator's road drive file against an independent reference.

`shocktwin simulate --road V --road-class C` plays, instead of the paper's sine, the
suspension stroke of a car at V km/h over an ISO 8608 road through a linear quarter-car
(dt-sim `road`). Checked here with numpy/scipy only: the potentiometer's position over the
excitation has the power spectrum (Welch) of ISO 8608's displacement PSD through the
quarter-car's deflection transfer, written out again below from the textbook formulas, in
four bands and in total; the metadata names the road and no frequency; a class that does not
exist is refused by name. Simulated data throughout.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from scipy.signal import welch

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("SHOCKTWIN_BIN", ROOT / "target" / "release" / "shocktwin"))

# The drive file's documented quarter-car (crates/dt-sim/README.md, dt-sim `road`).
M_S, M_U, K_S, K_T, C_S = 350.0, 45.0, 22e3, 200e3, 1.8e3
CLASS_GD_N0 = {"A": 16e-6, "B": 64e-6, "C": 256e-6, "D": 1024e-6, "E": 4096e-6}
BAND = (0.5, 20.0)


def stroke_psd(f: np.ndarray, speed_kmh: float, road_class: str) -> np.ndarray:
    """ISO 8608 road PSD at the vehicle's speed, through the quarter-car's deflection."""
    v = speed_kmh / 3.6
    road = CLASS_GD_N0[road_class] * ((f / v) / 0.1) ** -2 / v
    s = 2j * np.pi * f
    a = M_S * s**2 + C_S * s + K_S
    b = C_S * s + K_S
    c = M_U * s**2 + C_S * s + K_S + K_T
    h = K_T * M_S * s**2 / (a * c - b**2)
    return np.abs(h) ** 2 * road


def simulate(out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN), "simulate", "--quick", "--out", str(out), *args], capture_output=True,
                          text=True, timeout=300)


@pytest.mark.parametrize(("speed", "road_class"), [(60.0, "C"), (90.0, "B")])
def test_the_road_drive_has_the_iso_8608_spectrum_through_the_quarter_car(
        tmp_path: Path, speed: float, road_class: str) -> None:
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: run `make build`")
    proc = simulate(tmp_path, "--road", f"{speed:g}", "--road-class", road_class, "--pressures", "12")
    assert proc.returncode == 0, proc.stderr
    (run,) = tmp_path.glob("*.mcap")
    assert run.name == f"p12.0-road{road_class}{speed:g}-s1.mcap"
    with run.open("rb") as f:
        reader = make_reader(f)
        meta = next(m for m in reader.iter_metadata() if m.name == "shocktwin.run").metadata
        t, y = [], []
        for _, _, m in reader.iter_messages(topics=["/position"]):
            t.append(m.log_time / 1e9)
            y.append(json.loads(m.data)["position_m"])
    assert meta["excitation"].startswith(f"road: ISO 8608 class {road_class} at {speed:g} km/h"), meta
    assert "frequency_hz" not in meta and meta["road_class"] == road_class, meta
    t_s, y_m = np.array(t) - t[0], np.array(y)
    # The quick run rests 10 s, then ramps the drive in over 2 s.
    y_m = y_m[t_s >= 13.0]
    fs = 100.0
    f, pxx = welch(y_m - y_m.mean(), fs=fs, nperseg=1024)
    want = stroke_psd(np.where(f > 0, f, 1.0), speed, road_class) * ((f >= BAND[0]) & (f <= BAND[1]))
    ratios = []
    for lo, hi in [(1.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 15.0)]:
        sel = (f >= lo) & (f < hi)
        ratios.append(np.trapezoid(pxx[sel], f[sel]) / np.trapezoid(want[sel], f[sel]))
    fine = np.linspace(*BAND, 20_000)
    rms_want = np.sqrt(np.trapezoid(stroke_psd(fine, speed, road_class), fine))
    print(f"class {road_class} {speed:g} km/h: stroke rms {y_m.std() * 1e3:.2f} mm (ISO 8608 through the "
          f"quarter-car: {rms_want * 1e3:.2f} mm); band power ratios {np.round(ratios, 2)} — simulated data")
    assert all(0.75 < r < 1.33 for r in ratios), ratios
    assert abs(y_m.std() / rms_want - 1.0) < 0.1


def test_a_road_class_that_does_not_exist_is_refused_by_name(tmp_path: Path) -> None:
    proc = simulate(tmp_path, "--road", "60", "--road-class", "F")
    assert proc.returncode != 0
    assert "`F` is not an ISO 8608 road class" in proc.stderr, proc.stderr
    proc = simulate(tmp_path, "--road-class", "C")
    assert proc.returncode != 0 and "--road" in proc.stderr, proc.stderr


# The observer's calibrated mount and friction, typical of the simulated dyno (physics.json).
OBS = {"friction_v_smooth_mps": 0.005, "mount_mass_kg": 12.0, "mount_freq_hz": 102.7, "mount_zeta": 0.08,
       "accel_bw_hz": 400.0, "step_per_bar_n": 1.33}


def test_the_road_bounds_regressor_is_the_mount_driven_by_the_friction_flip() -> None:
    """`train.road_bound`'s friction column (a discretised transfer function) against the mount's
    ODE integrated by scipy's solve_ivp: body acceleration under `tanh(ẏ/v_s)` through the
    accelerometer's first-order filter, on a 2 Hz sine."""
    from scipy.integrate import solve_ivp

    from train import road_bound

    y, yd = road_bound.sine_drive(np.arange(0.0, 2.0, 1 / road_bound.FINE_HZ), 2.0)
    col = road_bound.regressors(y, yd, OBS)[:, 0]
    t = np.arange(len(col)) / road_bound.FS_HZ
    m, wn, wc = OBS["mount_mass_kg"], 2 * np.pi * OBS["mount_freq_hz"], 2 * np.pi * OBS["accel_bw_hz"]
    k, c = m * wn**2, 2 * OBS["mount_zeta"] * m * wn

    def rhs(s: float, x: np.ndarray) -> list[float]:
        f = np.tanh(0.04 * 4 * np.pi * np.cos(4 * np.pi * s) / OBS["friction_v_smooth_mps"])
        a = (f - k * x[0] - c * x[1]) / m
        return [x[1], a, wc * (a - x[2])]

    ref = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0, 0.0], t_eval=t, rtol=1e-9, atol=1e-12, max_step=5e-5).y[2]
    settled = t > 0.3
    err = np.abs(col[settled] - ref[settled]).max() / np.abs(ref[settled]).max()
    assert err < 0.01, err


def test_the_road_bound_shrinks_as_one_over_root_time_and_a_road_carries_more_than_a_sine() -> None:
    from train import road_bound

    def sd(drive: str, seconds: float) -> float:
        t = np.arange(0.0, seconds + 1.0, 1 / road_bound.FINE_HZ)
        y, yd = road_bound.road_drive(t, 60.0, "C", 1) if drive == "road" else road_bound.sine_drive(t, 2.0)
        return road_bound.sd_bar(y, yd, OBS)

    short, long = sd("road", 20.0), sd("road", 80.0)
    assert abs(long / short - 0.5) < 0.1, (short, long)
    assert short < sd("sine", 20.0)
