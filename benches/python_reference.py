"""The estimator's work done the way an analyst would without shocktwin, timed
side by side with ``shocktwin replay`` on the same MCAP file.

Python side, written straightforwardly (no shocktwin code):

1. read the MCAP with the ``mcap`` package, ``json.loads`` every message;
2. Kalman filter (SPEC §3.1) with filterpy, one predict per accelerometer
   event and a predict + update per potentiometer event;
3. 50 Hz boxcar means with numpy (``bincount``), held over empty ticks;
4. thermal model (SPEC §3.2) with scipy ``solve_ivp`` (RK45) over the run,
   the heat input from the force model at the interpolated tick velocity;
5. force model (SPEC §3.3) in numpy at the ticks;
6. the bundle's network with onnxruntime on all rows at once; 1 s average.

Rust side: ``shocktwin replay --model BUNDLE LOG --out OUT.csv`` on the whole
file (decode, estimator, CSV out), wall time of the process.

The Python pipeline runs on the first ``--seconds`` of the log (default 300 s;
``--seconds 3600`` for the full hour) and its time is scaled linearly to the
log's duration; the ratio printed is (scaled Python time) / (replay time).
Without ``--log``, a synthetic 1 h run of one asset at SPEC rates (2 Hz,
80 mm p-p, ≈ 4.15 M messages) is written once with the ``mcap`` package to
``target/python-reference/synthetic-1h.mcap``.

Run from the repository root after ``make build``:
``.venv/bin/python benches/python_reference.py [--seconds N] [--log FILE] [--model DIR]``
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_MODEL = ROOT / "crates/dt-core/tests/fixtures/bundle-mlp13"
DEFAULT_LOG = ROOT / "target/python-reference/synthetic-1h.mcap"
TICK_NS = 20_000_000
P_ATM = 101_325.0


def write_synthetic(path: Path, seconds: int) -> None:
    """A synthetic run with the mcap package (the same signals as benches/benches/estimator.rs)."""
    from mcap.writer import CompressionType, Writer

    path.parent.mkdir(parents=True, exist_ok=True)
    fields = {
        "/acceleration": ("a1_mps2", "a2_mps2"),
        "/position": ("position_m",),
        "/force": ("force_n",),
        "/temperature/shock": ("temperature_c",),
        "/temperature/ambient": ("temperature_c",),
    }
    w_rad = 2 * math.pi * 2.0
    amp = 0.04
    rng = np.random.default_rng(1)
    tmp = path.with_suffix(".partial")
    with open(tmp, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="benches/python_reference.py")
        writer.add_metadata("shocktwin.run", {"asset_id": "bench-unit", "run_id": "synthetic-1h"})
        ch = {}
        for topic, fs in fields.items():
            schema = {"type": "object", "properties": {f: {"type": ["number", "null"]} for f in fs}, "required": list(fs)}
            sid = writer.register_schema(name=topic, encoding="jsonschema", data=json.dumps(schema).encode())
            ch[topic] = writer.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for block in range(seconds):
            i = np.arange(block * 1000, (block + 1) * 1000)
            x = i * 1e-3
            noise = rng.uniform(-1, 1, size=(4, 1000))
            a1 = -amp * w_rad**2 * np.sin(w_rad * x) + 0.3 + 0.05 * noise[0]
            a2 = 0.05 * noise[1]
            pos = amp * np.sin(w_rad * x) + 5e-4 * noise[2]
            force = 6000 * amp * w_rad * np.cos(w_rad * x) - 380 + 20 * noise[3]
            a1, a2, pos, force = a1.tolist(), a2.tolist(), pos.tolist(), force.tolist()
            for j in range(1000):
                ms = int(i[j])
                t = ms * 1_000_000
                writer.add_message(ch["/acceleration"], log_time=t, publish_time=t,
                                   data=f'{{"a1_mps2":{a1[j]!r},"a2_mps2":{a2[j]!r}}}'.encode())
                if ms % 10 == 0:
                    writer.add_message(ch["/position"], log_time=t, publish_time=t,
                                       data=f'{{"position_m":{pos[j]!r}}}'.encode())
                if ms % 20 == 3:
                    writer.add_message(ch["/force"], log_time=t, publish_time=t,
                                       data=f'{{"force_n":{force[j]!r}}}'.encode())
                if ms % 1000 == 250:
                    temp = 25.0 + float(x[j]) * 0.01
                    writer.add_message(ch["/temperature/shock"], log_time=t, publish_time=t,
                                       data=f'{{"temperature_c":{temp!r}}}'.encode())
                    writer.add_message(ch["/temperature/ambient"], log_time=t, publish_time=t,
                                       data=b'{"temperature_c":21.5}')
        writer.finish()
    tmp.rename(path)


# ---------------------------------------------------------------- the analyst's pipeline


def read_mcap(path: Path, seconds: float) -> dict[str, list]:
    from mcap.reader import make_reader

    data: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        t_end = None
        for _schema, channel, message in reader.iter_messages():
            if t_end is None:
                t_end = message.log_time + int(seconds * 1e9)
            if message.log_time >= t_end:
                break
            data.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    return data


def kalman(t_acc, a_rel, t_pos, pos, kp):
    """SPEC §3.1 with filterpy: state [y, v, b] at each accelerometer sample."""
    from filterpy.kalman import KalmanFilter

    sa, sb, sz = kp["sigma_accel"], kp["sigma_bias"], kp["sigma_position"]
    events = sorted([(t, 0, i) for i, t in enumerate(t_acc)] + [(t, 1, i) for i, t in enumerate(t_pos)])
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.H = np.array([[1.0, 0.0, 0.0]])
    kf.R = np.array([[sz**2]])
    out = np.full((len(t_acc), 3), np.nan)
    started, u, t_last = False, 0.0, None
    pending = []
    for n, (t, kind, i) in enumerate(events):
        if started:
            dt = (t - t_last) * 1e-9
            if dt > 0:
                F = np.array([[1, dt, -dt * dt / 2], [0, 1, -dt], [0, 0, 1]])
                G = np.array([[dt * dt / 2], [dt], [0.0]])
                Q = sa**2 * (G @ G.T) + np.diag([0, 0, sb**2 * dt])
                kf.predict(u=np.array([[u]]), B=G, F=F, Q=Q)
        if kind == 0:
            u = a_rel[i]
            pending.append(i)
        elif not started:
            kf.x = np.array([[pos[i]], [0.0], [0.0]])
            kf.P = np.diag([sz**2, 1.0, 1.0])
            started = True
        else:
            kf.update(np.array([[pos[i]]]))
        t_last = t
        if n + 1 == len(events) or events[n + 1][0] != t:
            if started:
                for j in pending:
                    out[j] = kf.x[:, 0]
            pending = []
    return out


def boxcar(t, v, t0, n_ticks):
    """Mean over (t_{k-1}, t_k] for ticks k = 1..n; empty ticks hold."""
    k = -((t0 - np.asarray(t)) // TICK_NS)  # ceil((t - t0) / tick)
    ok = (k >= 1) & (k <= n_ticks) & np.isfinite(v)
    s = np.bincount(k[ok] - 1, weights=np.asarray(v)[ok], minlength=n_ticks)
    c = np.bincount(k[ok] - 1, minlength=n_ticks)
    mean = np.where(c > 0, s / np.maximum(c, 1), np.nan)
    idx = np.where(c > 0, np.arange(n_ticks), 0)
    np.maximum.accumulate(idx, out=idx)
    held = mean[idx]
    held[: np.argmax(c > 0) if c.any() else n_ticks] = np.nan
    return held


def force_model(v, a, y, oil_c, fp):
    reb = v >= 0
    pick = lambda name: np.where(reb, fp[name + "_reb"], fp[name + "_com"])  # noqa: E731
    nu = fp["nu_40"] * np.exp(-fp["beta"] * (oil_c - 40.0))
    av = np.abs(v)
    a_ = pick("k_leak") * nu * av
    b_ = pick("f_preload") + pick("k_spring") * av
    k = fp["k_tr"]
    with np.errstate(invalid="ignore", divide="ignore"):
        port = np.where((a_ > 0) & (b_ > 0), a_ * b_ / (a_**k + b_**k) ** (1 / k), 0.0)
    main = pick("k_main") * nu**0.25 * av**1.75
    ps = (fp["charge_bar"] * 1e5 + P_ATM) * (oil_c + 273.15) / 293.15
    gas = ps * fp["a_rod"] * (fp["v_gas"] / (fp["v_gas"] + fp["a_rod"] * y)) ** 1.4 - P_ATM * fp["a_rod"]
    damping = np.sign(v) * (port + main) - fp["k_hys"] * a
    return damping - gas, damping, -gas, (port + main) * av


def thermal(t_s, v_tick, amb_c, oil0, tp, fp):
    from scipy.integrate import solve_ivp

    def rhs(t, T):
        v = np.interp(t, t_s, v_tick)
        ta = np.interp(t, t_s, amb_c) + 273.15
        power = force_model(np.array([v]), np.zeros(1), np.zeros(1), np.array([T[0]]), fp)[3][0]
        oil, cyl = T[0] + 273.15, T[1] + 273.15
        d_oil = (tp["ha_in"] * (cyl - oil) + power) / tp["c_oil"]
        d_cyl = (tp["ha_in"] * (oil - cyl) + tp["ha_out"] * (ta - cyl) + tp["eps_sigma_a"] * (ta**4 - cyl**4)) / tp["c_cyl"]
        return [d_oil, d_cyl]

    sol = solve_ivp(rhs, (t_s[0], t_s[-1]), [oil0, oil0], t_eval=t_s, max_step=1.0)
    return sol.y[0], sol.y[1]


def python_pipeline(log: Path, model: Path, seconds: float) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
    import onnxruntime as ort

    twin = json.loads((model / "twin.json").read_text())
    phys = twin["physics"]
    times: dict[str, float] = {}

    t = time.perf_counter()
    data = read_mcap(log, seconds)
    times["read MCAP + json (mcap)"] = time.perf_counter() - t

    t = time.perf_counter()
    acc = data["/acceleration"]
    t_acc = np.array([m[0] for m in acc])
    a_rel = np.array([m[1]["a1_mps2"] - m[1]["a2_mps2"] for m in acc])
    t_pos = np.array([m[0] for m in data["/position"]])
    pos = np.array([m[1]["position_m"] for m in data["/position"]])
    t_f = np.array([m[0] for m in data["/force"]])
    force = np.array([m[1]["force_n"] for m in data["/force"]])
    t_ts = np.array([m[0] for m in data["/temperature/shock"]])
    temp_s = np.array([m[1]["temperature_c"] for m in data["/temperature/shock"]])
    t_ta = np.array([m[0] for m in data["/temperature/ambient"]])
    temp_a = np.array([m[1]["temperature_c"] for m in data["/temperature/ambient"]])
    t0 = min(int(v[0][0]) for v in data.values())
    t_last = max(int(v[-1][0]) for v in data.values())
    n = -((t0 - t_last) // TICK_NS)
    ticks = t0 + TICK_NS * np.arange(1, n + 1)
    times["arrays"] = time.perf_counter() - t

    t = time.perf_counter()
    state = kalman(t_acc, a_rel, t_pos, pos, phys["kalman"])
    times["Kalman filter (filterpy)"] = time.perf_counter() - t

    t = time.perf_counter()
    f_b, y_raw, a_b = boxcar(t_f, force, t0, n), boxcar(t_pos, pos, t0, n), boxcar(t_acc, a_rel, t0, n)
    y_b, v_b = boxcar(t_acc, state[:, 0], t0, n), boxcar(t_acc, state[:, 1], t0, n)
    ac_b = boxcar(t_acc, a_rel - state[:, 2], t0, n)
    hold = lambda ts, vs: np.where(  # noqa: E731
        np.searchsorted(ts, ticks, side="right") > 0, vs[np.maximum(np.searchsorted(ts, ticks, side="right") - 1, 0)], np.nan
    )
    shock_c, amb_c = hold(t_ts, temp_s), hold(t_ta, temp_a)
    times["50 Hz boxcars (numpy)"] = time.perf_counter() - t

    t = time.perf_counter()
    start = int(np.argmax(ticks >= t_ts[0]))
    t_s = (ticks[start:] - t0) * 1e-9
    amb_filled = np.where(np.isnan(amb_c[start:]), temp_s[0], amb_c[start:])
    v_filled = np.nan_to_num(v_b[start:])
    oil, cyl = np.full(n, np.nan), np.full(n, np.nan)
    oil[start:], cyl[start:] = thermal(t_s, v_filled, amb_filled, temp_s[0], phys["thermal"], phys["force"])
    times["thermal model (solve_ivp)"] = time.perf_counter() - t

    t = time.perf_counter()
    total, damping, gas, power = force_model(v_b, ac_b, y_b, oil, phys["force"])
    times["force model (numpy)"] = time.perf_counter() - t

    t = time.perf_counter()
    cols = {
        "force_n": f_b, "position_m": y_raw, "accel_rel_mps2": a_b, "velocity_mps": v_b,
        "force_model_n": total, "force_damping_model_n": damping, "force_gas_model_n": gas,
        "temp_shock_c": shock_c, "temp_ambient_c": amb_c, "oil_temp_model_c": oil,
        "cyl_temp_model_c": cyl, "heat_rate_model_w": power,
    }
    x = np.column_stack([cols[c] for c in twin["permutation"]["columns"]])
    mean, std = np.array(twin["normalisation"]["mean"]), np.array(twin["normalisation"]["std"])
    ok = np.all(np.isfinite(x), axis=1)
    sess = ort.InferenceSession(str(model / twin["onnx"]["file"]), providers=["CPUExecutionProvider"])
    p = np.full(n, np.nan)
    p[ok] = sess.run([twin["onnx"]["output"]], {twin["onnx"]["input"]: (x[ok] - mean) / std})[0][:, 0]
    v2 = np.where(np.isfinite(v_b), v_b**2, 0.0)
    rms = np.sqrt(np.convolve(v2, np.ones(50), "full")[:n] / np.minimum(np.arange(1, n + 1), 50))
    excited = rms >= twin["health"]["min_excitation_mps"]
    pe = np.where(excited & ok, p, 0.0)
    cnt = np.convolve((excited & ok).astype(float), np.ones(50), "full")[:n]
    avg = np.where(cnt > 0, np.convolve(pe, np.ones(50), "full")[:n] / np.maximum(cnt, 1), np.nan)
    times["network (onnxruntime) + 1 s average"] = time.perf_counter() - t
    return times, (ticks - t0) * 1e-9, np.column_stack([p, avg])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", type=Path, default=None, help="shocktwin log (default: synthetic 1 h run)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="bundle directory")
    ap.add_argument("--seconds", type=float, default=300.0, help="seconds of the log the Python side processes")
    ap.add_argument("--shocktwin", type=Path, default=ROOT / "target/release/shocktwin")
    args = ap.parse_args()

    log = args.log
    if log is None:
        log = DEFAULT_LOG
        if not log.exists():
            print(f"writing {log.relative_to(ROOT)} (synthetic 1 h run, once) …", flush=True)
            t = time.perf_counter()
            write_synthetic(log, 3600)
            print(f"  {time.perf_counter() - t:.0f} s", flush=True)
    if not args.shocktwin.exists():
        print(f"{args.shocktwin}: not built (run `make build`)", file=sys.stderr)
        return 1

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "replay.csv"
        t = time.perf_counter()
        subprocess.run([str(args.shocktwin), "replay", "--model", str(args.model), str(log), "--out", str(out)],
                       check=True, stdout=subprocess.DEVNULL)
        replay_s = time.perf_counter() - t
        with open(out) as f:
            rows = list(csv.DictReader(f))
    dur_s = float(rows[-1]["t_s"])
    rust_p = np.array([float(r["pressure_bar"] or "nan") for r in rows])

    times, t_py, p_py = python_pipeline(log, args.model, args.seconds)
    py_s = sum(times.values())
    covered = float(t_py[-1])
    scaled = py_s * dur_s / covered

    print(f"log: {log} ({dur_s:.0f} s of one asset)")
    print(f"shocktwin replay (whole log, decode + estimator + CSV): {replay_s:8.2f} s  "
          f"= {dur_s / replay_s:7.0f}x real time")
    print(f"Python reference on the first {covered:.0f} s:          {py_s:8.2f} s  "
          f"-> scaled to {dur_s:.0f} s: {scaled:8.1f} s = {dur_s / scaled:5.1f}x real time")
    for name, s in times.items():
        print(f"    {name:40s} {s:8.2f} s")
    print(f"ratio (Python scaled / shocktwin replay): {scaled / replay_s:.0f}x")
    m = min(len(p_py), len(rust_p))
    both = np.isfinite(p_py[:m, 0]) & np.isfinite(rust_p[:m])
    if both.any():
        d = p_py[:m, 0][both] - rust_p[:m][both]
        print(f"same work? instantaneous pressure, Python vs shocktwin over {both.sum()} ticks: "
              f"RMS diff {np.sqrt(np.mean(d * d)):.3g} bar, median |diff| {np.median(np.abs(d)):.3g} bar")
    return 0


if __name__ == "__main__":
    sys.exit(main())
