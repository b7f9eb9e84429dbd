"""Where the road observer's stroke velocity goes wrong, and what that costs the friction it
reads (a study on simulated runs that log the truth velocity at 1 kHz:
``shocktwin simulate --road SPEED --truth-velocity-hz 1000``).

    python -m train.road_velocity --physics physics.json --road road.json RUN.mcap ...

The road observer (:mod:`train.road_observer`) regresses the body accelerometer on force
columns built from its stroke filter's velocity; the friction's flip lives within ±5 mm/s of a
reversal, so the velocity's error matters there. For each run this compares the filter's
velocity with the simulator's and reads every block's friction amplitude ``α`` three ways:

- **truth**: the simulator's velocity, aligned with the sensors: the part of the error
  proportional to the stroke acceleration is taken as a lead, fitted per run and printed. It
  was 0.12 ms on ``dt-sim`` 0.1.0 (its sensors' lags led the continuous filter by half a
  sub-step) and is a few microseconds since 0.2.0;
- **filter**: the stroke filter's velocity, as the observer reads;
- **SIMEX**: the filter's, each block's ``α`` corrected for errors in variables by
  simulation–extrapolation (Cook & Stefanski, JASA 1994;
  :func:`train.road_observer.simex_alpha`): noise of the sensors' own figures (white noise and
  quantisation of both accelerometers and the potentiometer: datasheet values, the simulated
  rig's by default) is put through the same filter alone and added ``λ − 1`` more times, and
  ``α`` is extrapolated quadratically in ``λ`` (1, 2, 3) back to 0.

Printed per run: the error's RMS against the aligned truth, the RMS that the sensors' noise
alone gives through the filter, each way's mean ``α`` and the charge it reads (the
calibration's ``α = a + b p_g``, :func:`train.road_observer.charge_of`). Per drive with runs
at two or more charges: the slope of ``α`` against the gas pressure each way (N/bar, at the
thermocouple's temperature), which is what the calibration's line needs to hold across speeds.
``--json`` writes it all.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import shocktwin

from train.campaign import main_wrapper, read_json
from train.observer import P_ATM_BAR
from train.progress import progress
from train.road_observer import (ACC_DT_S, block_readings, calibration_options, charge_of, gas_ratio,
                                 velocity_noise)

TRUTH_TOPIC = "/truth/velocity"


def truth_velocity(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's stroke velocity (s, m/s), refused unless logged at 1 kHz."""
    lg = shocktwin.read_log(str(path))
    if TRUTH_TOPIC not in lg.topics:
        raise ValueError(f"{path}: no {TRUTH_TOPIC} (a simulated run with --truth-velocity-hz 1000 is needed)")
    tv = lg.topic(TRUTH_TOPIC)
    dt = float(np.median(np.diff(tv["t_s"])))
    if dt > 1.5 * ACC_DT_S:
        raise ValueError(f"{path}: {TRUTH_TOPIC} is logged at {1 / dt:.0f} Hz; this study needs 1000 Hz "
                         "(shocktwin simulate --truth-velocity-hz 1000)")
    return tv["t_s"], tv["velocity_mps"]


def study_run(path: Path, physics: dict[str, Any], model: dict[str, Any], figures: dict[str, float],
              seed: int) -> dict[str, Any]:
    """One run's row: the velocity error's parts and each way's α and charge reading."""
    opts = calibration_options(model)
    t_true, v_true = truth_velocity(path)
    seen: list[tuple[np.ndarray, np.ndarray]] = []

    def record(t: np.ndarray, v: np.ndarray) -> np.ndarray:
        seen.append((t, v))
        return v

    ways: dict[str, dict[str, np.ndarray]] = {"filter": block_readings(str(path), physics, opts, record)}
    if not len(ways["filter"]["alpha_n"]):
        raise ValueError(f"{path}: the road observer reads no block of this run (a rest, or too short)")
    t = np.concatenate([s[0] for s in seen])
    v = np.concatenate([s[1] for s in seen])
    acc_true = np.gradient(v_true, t_true)
    # the error's part proportional to the stroke acceleration is a time offset (v(t + δ) ≈ v + δ a)
    x = np.column_stack([np.interp(t, t_true, acc_true), np.interp(t, t_true, v_true), np.ones_like(t)])
    err = v - np.interp(t, t_true, v_true)
    coef = np.linalg.lstsq(x, err, rcond=None)[0]
    lead_s = float(coef[0])
    aligned = np.interp(t + lead_s, t_true, v_true)
    ways["truth"] = block_readings(str(path), physics, opts, lambda tb, vb: np.interp(tb + lead_s, t_true, v_true))
    noise_only = velocity_noise(len(t), np.random.default_rng(seed), physics, opts, figures)
    ways["simex"] = block_readings(str(path), physics, opts, simex={"figures": figures, "reps": 2, "seed": seed})
    meta = shocktwin.read_log(str(path)).metadata
    row: dict[str, Any] = {
        "run": path.name, "excitation": meta.get("excitation"), "seed": meta.get("drive_seed", meta.get("seed")),
        "charge_bar": meta.get("charge_pressure_bar"), "blocks": int(len(ways["filter"]["alpha_n"])),
        "stroke_rms_mps": float(np.sqrt(np.mean(v ** 2))),
        "lead_ms": lead_s * 1e3,
        "error_rms_mps": float(np.sqrt(np.mean((v - aligned) ** 2))),
        "noise_only_rms_mps": float(np.sqrt(np.mean(noise_only ** 2))),
    }
    for name, r in ways.items():
        row[f"alpha_{name}_n"] = float(np.mean(r["alpha_n"]))
        row[f"read_{name}_bar"] = float(np.mean(charge_of(r, model, physics)[0]))
        row[f"_blocks_{name}"] = r
    return row


def slopes(rows: list[dict[str, Any]], physics: dict[str, Any]) -> list[dict[str, Any]]:
    """Per drive (excitation and seed) with two or more charges: α against p_g, N/bar, each way."""
    out = []
    for drive in sorted({(r["excitation"], r["seed"]) for r in rows}, key=str):
        runs = [r for r in rows if (r["excitation"], r["seed"]) == drive and r["charge_bar"] is not None]
        if len({r["charge_bar"] for r in runs}) < 2:
            continue
        entry: dict[str, Any] = {"excitation": drive[0], "seed": drive[1], "runs": len(runs)}
        for way in ("truth", "filter", "simex"):
            alpha = np.concatenate([r[f"_blocks_{way}"]["alpha_n"] for r in runs])
            p_g = np.concatenate([(r["charge_bar"] + P_ATM_BAR) * gas_ratio(r[f"_blocks_{way}"]["temp_c"], physics)
                                  - P_ATM_BAR for r in runs])
            entry[f"slope_{way}_n_per_bar"] = float(np.polyfit(p_g, alpha, 1)[0])
        out.append(entry)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m train.road_velocity", description=__doc__.split("\n\n")[0])
    ap.add_argument("--physics", required=True, type=Path, help="physics.json (mount, filter, Kalman noise)")
    ap.add_argument("--road", required=True, type=Path, help="a road calibration (train.road_observer fit)")
    ap.add_argument("--accel-noise-mps2", type=float, default=0.064, help="each accelerometer's white noise (datasheet)")
    ap.add_argument("--accel-lsb-mps2", type=float, default=0.03826, help="each accelerometer's quantisation step")
    ap.add_argument("--pos-noise-m", type=float, default=1.0e-5, help="the potentiometer's white noise")
    ap.add_argument("--pos-lsb-m", type=float, default=2.29e-6, help="the potentiometer's quantisation step")
    ap.add_argument("--seed", type=int, default=17, help="the seed of the noise (SIMEX, and the noise-alone RMS)")
    ap.add_argument("--json", type=Path, help="write the rows and slopes here")
    ap.add_argument("runs", nargs="+", type=Path, help="simulated runs with /truth/velocity at 1 kHz")
    args = ap.parse_args(argv)
    physics = read_json(args.physics)
    physics.setdefault("observer", shocktwin.default_observer_params())
    physics.setdefault("kalman", shocktwin.default_params()["kalman"])
    model = read_json(args.road)
    figures = {"accel_noise_mps2": args.accel_noise_mps2, "accel_lsb_mps2": args.accel_lsb_mps2,
               "pos_noise_m": args.pos_noise_m, "pos_lsb_m": args.pos_lsb_m}
    rows = [study_run(p, physics, model, figures, args.seed) for p in progress(args.runs, desc="runs", unit="run")]
    print("The road observer's stroke velocity against the simulator's (SIMULATED DATA)\n")
    print("| run | charge | stroke rms | sensors' lead | error rms | noise alone | alpha: truth | filter | SIMEX "
          "| read: truth | filter | SIMEX |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['run']} | {r['charge_bar']} | {1e3 * r['stroke_rms_mps']:.0f} mm/s | {r['lead_ms']:.3f} ms "
              f"| {1e3 * r['error_rms_mps']:.2f} mm/s | {1e3 * r['noise_only_rms_mps']:.2f} mm/s "
              f"| {r['alpha_truth_n']:.2f} N | {r['alpha_filter_n']:.2f} N | {r['alpha_simex_n']:.2f} N "
              f"| {r['read_truth_bar']:.2f} bar | {r['read_filter_bar']:.2f} bar | {r['read_simex_bar']:.2f} bar |")
    sl = slopes(rows, physics)
    if sl:
        print("\n| drive | runs | slope of alpha on p_g: truth | filter | SIMEX |")
        print("| --- | --- | --- | --- | --- |")
        for s in sl:
            print(f"| {s['excitation']} (seed {s['seed']}) | {s['runs']} | {s['slope_truth_n_per_bar']:.4f} N/bar "
                  f"| {s['slope_filter_n_per_bar']:.4f} | {s['slope_simex_n_per_bar']:.4f} |")
    if args.json:
        clean = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
        args.json.write_text(json.dumps({"simulated": True, "figures": figures, "runs": clean, "slopes": sl}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_wrapper(main)())
