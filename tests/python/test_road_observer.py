"""The road observer (train.road_observer): its stroke filter against a trajectory put through
the sensors' filters by scipy, the whole tool on simulated road runs held out by seed, and no
look-ahead beyond a block's lag."""

from __future__ import annotations

import csv
from datetime import datetime
import json
import re
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from mcap.reader import make_reader
from scipy import signal

import shocktwin
from conftest import ServeProcess, write_mcap_log
from train import road_observer as ro
from train.observer_report import health_series

PHYSICS = {**shocktwin.default_params(), "observer": shocktwin.default_observer_params()}


def road_like(t: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extension, rate and acceleration of 60 random sines over 1-20 Hz (about 10 mm rms)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(1.0, 20.0, 60)
    amp = 0.004 / f**0.8
    ph = rng.uniform(0, 2 * np.pi, 60)
    arg = 2 * np.pi * np.outer(t, f) + ph
    w = 2 * np.pi * f
    return np.sin(arg) @ amp, np.cos(arg) @ (amp * w), -np.sin(arg) @ (amp * w**2)


def first_order(x: np.ndarray, t: np.ndarray, f_hz: float) -> np.ndarray:
    """``x`` through a first-order low pass, by scipy's lsim (linear interpolation between samples)."""
    tau = 1 / (2 * np.pi * f_hz)
    return signal.lsim(([1.0], [tau, 1.0]), x, t, X0=[x[0] * tau])[1]


def test_the_stroke_filter_reads_the_velocity_behind_both_sensor_filters() -> None:
    """A road-like stroke seen through the potentiometer's 50 Hz RC (sampled at 100 Hz) and
    the accelerometers' 400 Hz filter (1 kHz), both applied by scipy: the smoothed velocity
    is within 1 mm/s rms and lags less than 20 µs, where dt-core's three-state filter, which models
    neither, is several times further off."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 20.0, 1e-4)  # 10 kHz for the sensors' analogue filters
    y, v, a = road_like(t)
    acc = first_order(a, t, 400.0)[::10] + rng.normal(0, 0.06, t[::10].size)
    pot = first_order(y, t, 50.0)[::100] + rng.normal(0, 1e-5, t[::100].size)
    t_acc, t_pos = t[::10], t[::100]
    u_raw = acc + np.r_[0.0, np.diff(acc)] / (2 * np.pi * 400.0 * 1e-3)
    u_raw = np.r_[0.5 * (u_raw[1:] + u_raw[:-1]), u_raw[-1]]  # as block_readings: each millisecond's mean
    kf = ro.StrokeFilter(50.0, 0.3, 0.005, 1e-5)
    m = len(t_pos) - 1
    u = u_raw[:m * 10].reshape(m, 10)
    xf, xp = kf.forward(u, pot)
    xs = kf.smooth(xf, xp, 500, m)[:1001]
    x = kf.fill(xs, u[500:1500])
    truth = v[::10][5000:15000]
    err = x[:, 1] - truth
    assert np.sqrt(np.mean(err**2)) < 1e-3
    lag = np.polyfit(a[::10][5000:15000], err, 1)[0]  # velocity error per m/s² of acceleration = a lag, s
    assert abs(lag) < 2e-5
    old = shocktwin.KalmanFilter(**shocktwin.default_params()["kalman"]).run(t_acc, acc, t_pos, pot)
    old_err = np.interp(t_acc[5000:15000], old["t_s"], old["velocity_mps"]) - truth
    assert np.sqrt(np.mean(old_err**2)) > 3 * np.sqrt(np.mean(err**2))


def test_the_stroke_filter_is_filterpys_kalman_filter_at_steady_state() -> None:
    """The same model given to filterpy's ``KalmanFilter`` (F, B, Q over one potentiometer
    period, H on the RC's output, started at the steady-state covariance): the same gain to 1e-6 and
    estimates to 1e-7. Across a missing sample the stroke filter keeps its steady gain where
    filterpy's grows: 30 samples (0.3 s) later the velocities agree within 10 µm/s."""
    from filterpy.kalman import KalmanFilter as FilterpyKF

    rng = np.random.default_rng(3)
    kf = ro.StrokeFilter(50.0, 0.3, 0.005, 1e-5)
    u = rng.normal(0, 5.0, (400, 10))
    z = np.cumsum(rng.normal(0, 2e-4, 401))
    for gaps in ([], [50, 51, 200]):
        zz = z.copy()
        zz[gaps] = np.nan
        xf, _ = kf.forward(u, zz)
        ref = FilterpyKF(dim_x=4, dim_z=1, dim_u=10)
        ref.F, ref.B, ref.Q, ref.R = kf.phi, kf.gs, kf.q, np.array([[kf.r]])
        ref.H = np.array([[0.0, 0.0, 0.0, 1.0]])
        ref.x, ref.P = np.array([z[0], 0.0, 0.0, z[0]]), kf.p_post.copy()
        for k in range(400):
            ref.predict(u=u[k])
            if np.isfinite(zz[k + 1]):
                ref.update(zz[k + 1])
            if not gaps:
                np.testing.assert_allclose(ref.K[:, 0], kf.k, rtol=1e-6)
                np.testing.assert_allclose(ref.x, xf[k + 1], rtol=1e-7, atol=1e-10)
            elif all(not (g <= k + 1 < g + 30) for g in gaps):  # m, m/s, m/s², m: far below what moves α
                assert np.all(np.abs(ref.x - xf[k + 1]) < [1e-8, 1e-5, 1e-4, 1e-8]), (k, ref.x - xf[k + 1])


@pytest.fixture(scope="module")
def road_sets(shocktwin_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """Quick simulated road runs: a calibration on two drive files at 0.5-12 bar (60 km/h seed 1,
    45 km/h seed 4), a held-out drive file (seed 2) at 2 and 12 bar, and a third (seed 3) at 12
    bar for the unit's baseline."""
    root = tmp_path_factory.mktemp("road-observer")
    for out, extra in ((root / "cal", ["--road", "60", "--pressures", "0.5,4,7,10,12"]),
                       (root / "cal45", ["--road", "45", "--pressures", "0.5,4,7,10,12", "--seed", "4"]),
                       (root / "held", ["--road", "60", "--pressures", "2,12", "--seed", "2"]),
                       (root / "base", ["--road", "60", "--pressures", "12", "--seed", "3"])):
        proc = subprocess.run([str(shocktwin_bin), "simulate", "--quick", *extra, "--out", str(out)],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
    for run in (root / "cal45").glob("*.mcap"):
        run.rename(root / "cal" / run.name)
    return root / "cal", root / "held", root / "base"


@pytest.fixture(scope="module")
def road_model(road_sets: tuple[Path, Path, Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """physics.json (defaults) and the road calibration fitted on the calibration drive files."""
    root = tmp_path_factory.mktemp("road-model")
    physics = root / "physics.json"
    physics.write_text(json.dumps(PHYSICS))
    model_path = root / "road.json"
    assert ro.main(["fit", "--campaign", str(road_sets[0]), "--physics", str(physics), "--out", str(model_path),
                    "--jobs", "2"]) == 0
    return physics, model_path


def test_fit_then_evaluate_reads_a_held_out_drive(road_sets: tuple[Path, Path, Path], road_model: tuple[Path, Path],
                                                  tmp_path: Path) -> None:
    """Without a baseline the interval carries another unit's seal (10 %) and stays honest; with
    the unit's baseline drive at 12 bar it is narrow, and the verdicts are right."""
    _, held, base = road_sets
    physics, model_path = road_model
    model = json.loads(model_path.read_text())
    assert model["simulated"] is True
    assert 0.5 < model["b_n_per_bar"] < 3.0  # the seal's friction grows with the gas pressure
    assert model["held_out"] == "drive" and len(model["drives"]) == 2
    for row in model["held_out_reads"]:  # each run read by the other drive file's calibration
        # worst 1.53 bar (12 bar C60 read 13.53) since the simulator's step was made second
        # order (docs/history.md, "Twenty-first session"); below 1.5 before
        assert abs(row["read_bar"] - row["label_bar"]) < 2.0, row
    assert 0.0 < model["held_out_sd_bar"] < 1.5  # one drive file reads beside another: measured, kept
    assert model["systematic_sd_bar"] > 1.0  # 10 % of the seal's friction, in bar

    def evaluate(out: Path, *extra: str) -> tuple[dict[str, Any], dict[str, Any]]:
        assert ro.main(["evaluate", "--physics", str(physics), "--road", str(model_path), "--out", str(out),
                        "--score-from-s", "30", "--jobs", "2", *extra, f"held={held}"]) == 0
        rows = {r["run"]: r for r in json.loads((out / "road_observer.json").read_text())["runs"]}
        return rows["p2.0-roadC60-s2.mcap"], rows["p12.0-roadC60-s2.mcap"]

    low, nominal = evaluate(tmp_path / "eval")
    for r in (low, nominal):
        assert r["final_lo_bar"] <= r["label_bar"] <= r["final_hi_bar"], r
        assert abs(r["final_bar"] - r["label_bar"]) < 1.0, r
    assert not nominal["false_alarm"] and nominal["verdict"] in ("ok", "unknown")
    wide = nominal["final_hi_bar"] - nominal["final_lo_bar"]

    out = tmp_path / "eval-baseline"
    low, nominal = evaluate(out, "--baseline", f"held={base / 'p12.0-roadC60-s3.mcap'}@12")
    assert low["verdict"] == "leak" and nominal["verdict"] == "ok"
    assert not nominal["false_alarm"]
    for r in (low, nominal):
        assert r["final_lo_bar"] <= r["label_bar"] <= r["final_hi_bar"], r
    assert nominal["final_hi_bar"] - nominal["final_lo_bar"] < wide / 2
    assert "SIMULATED DATA" in (out / "road_observer.md").read_text()
    assert (out / "road_observer.png").stat().st_size > 10_000


def test_a_block_reads_nothing_after_its_lag(road_sets: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """The same run cut 45 s in: every block that ended with its lag before the cut reads the
    same to 1e-9; later data changes nothing before it."""
    _, held, _ = road_sets
    path = held / "p12.0-roadC60-s2.mcap"
    lg = shocktwin.read_log(str(path))
    cut_s = 45.0
    topics = {}
    for topic in ro.TOPICS:
        d = lg.topic(topic)
        keep = d["t_s"] < cut_s
        topics[topic] = (lg.t0_ns + np.round(d["t_s"][keep] * 1e9).astype(np.int64),
                         {k: v[keep] for k, v in d.items() if k != "t_s"})
    cut = write_mcap_log(tmp_path / "cut.mcap", {k: str(v) for k, v in lg.metadata.items()}, topics)
    opts = {"block_s": 10.0, "lag_s": 0.5, "pot_rc_hz": 50.0, "sigma_accel": 0.3, "settle_s": 10.0}
    full, short = ro.block_readings(str(path), PHYSICS, opts), ro.block_readings(str(cut), PHYSICS, opts)
    assert len(short["t_s"]) >= 2 and len(full["t_s"]) > len(short["t_s"])
    n = len(short["t_s"])
    assert short["t_s"][-1] + opts["lag_s"] < cut_s
    for key in ("alpha_n", "residual_mps2"):
        np.testing.assert_allclose(short[key], full[key][:n], rtol=1e-9, atol=1e-9)


def test_missing_samples_lose_only_themselves(road_sets: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """One accelerometer sample in a hundred, the first potentiometer samples and a
    thermocouple reading missing (NaN): every block is still read, within a block's own spread
    (0.5-0.7 N on these drives) of the whole log."""
    _, held, _ = road_sets
    path = held / "p2.0-roadC60-s2.mcap"
    lg = shocktwin.read_log(str(path))
    topics = {}
    for topic in ro.TOPICS:
        d = {k: v.copy() for k, v in lg.topic(topic).items()}
        field = [k for k in d if k != "t_s"][0]
        hole = {"/acceleration": np.arange(5, len(d[field]), 100), "/position": np.arange(3),
                "/temperature/shock": np.array([30])}[topic]
        d[field][hole] = np.nan
        topics[topic] = (lg.t0_ns + np.round(d["t_s"] * 1e9).astype(np.int64), {k: v for k, v in d.items() if k != "t_s"})
    holed = write_mcap_log(tmp_path / "holed.mcap", {k: str(v) for k, v in lg.metadata.items()}, topics)
    opts = {"block_s": 10.0, "lag_s": 0.5, "pot_rc_hz": 50.0, "sigma_accel": 0.3, "settle_s": 10.0}
    whole, holes = ro.block_readings(str(path), PHYSICS, opts), ro.block_readings(str(holed), PHYSICS, opts)
    assert len(holes["t_s"]) == len(whole["t_s"]) >= 4
    assert np.all(np.isfinite(holes["alpha_n"])) and np.all(np.isfinite(holes["temp_c"]))
    np.testing.assert_allclose(holes["alpha_n"], whole["alpha_n"], atol=0.8)


def test_a_log_without_the_accelerometers_is_refused_by_name(make_log, tmp_path: Path) -> None:
    path = make_log(topics=("/position", "/force", "/temperature/shock"))
    with pytest.raises(ValueError, match="/acceleration"):
        ro.block_readings(str(path), PHYSICS, {"block_s": 10.0, "lag_s": 0.5, "pot_rc_hz": 50.0,
                                              "sigma_accel": 0.3, "settle_s": 10.0})


# ---------------------------------------------------------------------------------------
# dt-core's streaming road observer (shocktwin.road_blocks, `shocktwin road`) against this
# module's batch reading of the same runs
# ---------------------------------------------------------------------------------------


def python_reading(path: Path, model: dict[str, Any], physics: dict[str, Any]) -> dict[str, Any]:
    """The reference: ``block_readings`` (batch, scipy) then ``track`` and the health rule."""
    opts = {k: model[k] for k in ("block_s", "lag_s", "pot_rc_hz", "sigma_accel", "settle_s")}
    r = ro.calibrated_blocks(ro.block_readings(str(path), physics, opts), model)
    p, sd = ro.charge_of(r, model, physics)
    est, lo, hi = ro.track(p, sd, r["t_s"], model, (6.0, 6.0), 1e-4)
    return {**r, "reading_bar": p, "estimate_bar": est, "lo_bar": lo, "hi_bar": hi,
            "health": health_series(r["t_s"], est, lo, hi, np.ones(len(est), bool))}


def test_the_streaming_observer_reads_as_the_python_reference(road_sets: tuple[Path, Path, Path],
                                                              road_model: tuple[Path, Path]) -> None:
    """dt-core ``road`` against ``block_readings`` + ``track`` on held-out runs: the same blocks, the
    friction to 1e-8 N on nine blocks in ten (a block whose rarest hinge column is nearly empty is
    solved by scipy's rank-revealing ``gelsy`` and nalgebra's QR a little apart: within a tenth of
    the block's own standard deviation), the estimate, interval and health alike."""
    _, held, _ = road_sets
    physics, model_path = road_model
    model, phys = json.loads(model_path.read_text()), json.loads(physics.read_text())
    for run in sorted(held.glob("*.mcap")):
        ref = python_reading(run, model, phys)
        got = shocktwin.road_blocks(str(run), model_path.read_text())
        assert len(got["t_s"]) == len(ref["t_s"]) >= 4, run.name
        np.testing.assert_allclose(got["t_s"], ref["t_s"], atol=1e-9)
        for key in ("temp_c", "stroke_rms_mps"):
            np.testing.assert_allclose(got[key], ref[key], rtol=1e-12, atol=1e-12)
        d = np.abs(got["alpha_n"] - ref["alpha_n"])
        assert np.mean(d < 1e-8) >= 0.9 and np.all(d < 0.1 * ref["alpha_sd_n"]), (run.name, d)
        for key in ("reading_bar", "estimate_bar", "lo_bar", "hi_bar"):
            np.testing.assert_allclose(got[key], ref[key], atol=0.1 * ref["alpha_sd_n"].max() / model["b_n_per_bar"])
        assert list(got["health"]) == ref["health"], run.name


def test_the_streaming_observer_reads_nothing_after_a_block_s_lag(road_sets: tuple[Path, Path, Path],
                                                                  road_model: tuple[Path, Path],
                                                                  tmp_path: Path) -> None:
    """The same run cut 45 s in: every block read from the cut log is the whole log's, to 1e-9."""
    _, held, _ = road_sets
    _, model_path = road_model
    path = held / "p12.0-roadC60-s2.mcap"
    lg = shocktwin.read_log(str(path))
    topics = {}
    for topic in ro.TOPICS:
        d = lg.topic(topic)
        keep = d["t_s"] < 45.0
        topics[topic] = (lg.t0_ns + np.round(d["t_s"][keep] * 1e9).astype(np.int64),
                         {k: v[keep] for k, v in d.items() if k != "t_s"})
    cut = write_mcap_log(tmp_path / "cut.mcap", {k: str(v) for k, v in lg.metadata.items()}, topics)
    full = shocktwin.road_blocks(str(path), model_path.read_text())
    short = shocktwin.road_blocks(str(cut), model_path.read_text())
    n = len(short["t_s"])
    assert n >= 2 and len(full["t_s"]) > n
    for key in ("alpha_n", "estimate_bar", "lo_bar", "hi_bar"):
        np.testing.assert_allclose(short[key], full[key][:n], rtol=1e-9, atol=1e-9)


def test_a_gap_restarts_the_filters_and_keeps_the_estimate(road_sets: tuple[Path, Path, Path],
                                                           road_model: tuple[Path, Path], tmp_path: Path) -> None:
    """Three seconds of drive lost (every topic) and the clock jumping 20 s ahead after it: the
    blocks before the gap read as in the whole log; after it the filters restart (and settle), and
    the estimate carries on from where it was, every block finite. One accelerometer sample in a
    hundred missing (NaN) changes a block by less than its own spread."""
    _, held, _ = road_sets
    _, model_path = road_model
    cal = model_path.read_text()
    path = held / "p2.0-roadC60-s2.mcap"
    lg = shocktwin.read_log(str(path))
    gapped, holed = {}, {}
    for topic in ro.TOPICS:
        d = {k: v.copy() for k, v in lg.topic(topic).items()}
        keep = (d["t_s"] < 31.0) | (d["t_s"] >= 34.0)
        t_ns = lg.t0_ns + np.round(d["t_s"] * 1e9).astype(np.int64)
        t_ns = np.where(d["t_s"] >= 34.0, t_ns + 20_000_000_000, t_ns)
        gapped[topic] = (t_ns[keep], {k: v[keep] for k, v in d.items() if k != "t_s"})
        field = [k for k in d if k != "t_s"][-1]
        if topic == "/acceleration":
            d[field][5::100] = np.nan
        holed[topic] = (lg.t0_ns + np.round(d["t_s"] * 1e9).astype(np.int64), {k: v for k, v in d.items() if k != "t_s"})
    meta = {k: str(v) for k, v in lg.metadata.items()}
    whole = shocktwin.road_blocks(str(path), cal)
    gap = shocktwin.road_blocks(str(write_mcap_log(tmp_path / "gap.mcap", meta, gapped)), cal)
    before = int(np.sum(whole["t_s"] < 30.5))
    assert before >= 1
    np.testing.assert_allclose(gap["alpha_n"][:before], whole["alpha_n"][:before], rtol=1e-12)
    after = gap["t_s"] > 54.0
    assert after.any() and np.all(np.isfinite(gap["estimate_bar"]))
    assert gap["hi_bar"][after][0] - gap["lo_bar"][after][0] < whole["hi_bar"][0] - whole["lo_bar"][0]  # carried on
    holes = shocktwin.road_blocks(str(write_mcap_log(tmp_path / "holed.mcap", meta, holed)), cal)
    assert len(holes["t_s"]) == len(whole["t_s"])
    np.testing.assert_array_less(np.abs(holes["alpha_n"] - whole["alpha_n"]), whole["alpha_sd_n"] * 3 + 0.3)


def test_a_dead_potentiometer_stops_the_reading(road_sets: tuple[Path, Path, Path], road_model: tuple[Path, Path],
                                                tmp_path: Path) -> None:
    """The potentiometer silent from 22 s on (its samples gone): the block read before reads as
    in the whole log; no block after it is read (the accelerometers alone would integrate a
    drifting stroke), and the estimate stays where it was."""
    _, held, _ = road_sets
    path = held / "p2.0-roadC60-s2.mcap"
    lg = shocktwin.read_log(str(path))
    topics = {}
    for topic in ro.TOPICS:
        d = lg.topic(topic)
        keep = d["t_s"] < 22.0 if topic == "/position" else np.ones(len(d["t_s"]), bool)
        topics[topic] = (lg.t0_ns + np.round(d["t_s"][keep] * 1e9).astype(np.int64),
                         {k: v[keep] for k, v in d.items() if k != "t_s"})
    dead = write_mcap_log(tmp_path / "dead.mcap", {k: str(v) for k, v in lg.metadata.items()}, topics)
    cal = road_model[1].read_text()
    whole, got = shocktwin.road_blocks(str(path), cal), shocktwin.road_blocks(str(dead), cal)
    assert len(whole["t_s"]) >= 4 and len(got["t_s"]) == int(np.sum(whole["t_s"] < 21.0)) >= 1
    np.testing.assert_allclose(got["alpha_n"], whole["alpha_n"][:len(got["t_s"])], rtol=1e-12)


def test_the_streaming_observer_refuses_a_log_without_accelerometers_by_name(make_log, road_model: tuple[Path, Path]) -> None:
    path = make_log(topics=("/position", "/force", "/temperature/shock"))
    with pytest.raises(shocktwin.MissingTopicsError, match="/acceleration"):
        shocktwin.road_blocks(str(path), road_model[1].read_text())
    with pytest.raises(ValueError, match="fit again"):
        shocktwin.road_blocks(str(path), json.dumps({"a_n": 1.0}))


def test_shocktwin_road_reads_a_held_out_drive_with_a_baseline(shocktwin_bin: Path, road_sets: tuple[Path, Path, Path],
                                                               road_model: tuple[Path, Path], tmp_path: Path) -> None:
    """The CLI as a test engineer runs it: the leaking run `leak`, the nominal one `ok`, each
    interval covering its charge, every block in the CSV."""
    _, held, base = road_sets
    out = tmp_path / "blocks.csv"
    proc = subprocess.run([str(shocktwin_bin), "road", "--calibration", str(road_model[1]), "--baseline",
                           f"{base / 'p12.0-roadC60-s3.mcap'}@12", "--out", str(out), *map(str, sorted(held.glob("*.mcap")))],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "SIMULATED DATA" in proc.stdout
    rows = list(csv.DictReader(out.open()))
    last = {}
    for r in rows:
        last[r["run_id"]] = r
    assert len(last) == 2
    for run_id, r in last.items():
        label = 2.0 if run_id.startswith("p2.0") else 12.0
        assert float(r["pressure_lo_bar"]) <= label <= float(r["pressure_hi_bar"]), r
        assert r["health"] == ("leak" if label < 5 else "ok"), r
    bad = tmp_path / "old.json"
    bad.write_text(json.dumps({k: v for k, v in json.loads(road_model[1].read_text()).items() if k != "filters"}))
    proc = subprocess.run([str(shocktwin_bin), "road", "--calibration", str(bad), str(sorted(held.glob("*.mcap"))[0])],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "old.json" in proc.stderr and "fit again" in proc.stderr


FIXTURE_BUNDLE = Path(__file__).resolve().parents[2] / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"


def test_a_drive_slower_than_the_calibration_s_is_not_read(shocktwin_bin: Path, road_sets: tuple[Path, Path, Path],
                                                           road_model: tuple[Path, Path], tmp_path: Path) -> None:
    """The friction read falls short of the calibration's line the slower the stroke (docs/history.md,
    "Nineteenth session": a healthy 12 bar unit read `low` at 2 km/h). The fit keeps the slowest
    stroke it read; a drive at 5 km/h on the same road class, slower than every calibration
    block, is not read — `unknown`, the reason named by `shocktwin road` and `replay --road` —
    while the held-out drive at the calibration's speed still is."""
    model = json.loads(road_model[1].read_text())
    slowest = model["filters"]["slowest_calibrated_stroke_rms_mps"]
    cal_blocks = ro.readings(sorted(road_sets[0].glob("*.mcap")), json.loads(road_model[0].read_text()),
                             {k: model[k] for k in ("block_s", "lag_s", "pot_rc_hz", "sigma_accel", "settle_s")}, 2)
    assert slowest == pytest.approx(min(float(b["stroke_rms_mps"].min()) for b in cal_blocks if len(b["t_s"])), rel=1e-12)
    proc = subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--road", "5", "--pressures", "12", "--seed", "2",
                           "--out", str(tmp_path / "slow")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    (slow,) = (tmp_path / "slow").glob("*.mcap")
    held = road_sets[1] / "p12.0-roadC60-s2.mcap"
    proc = subprocess.run([str(shocktwin_bin), "road", "--calibration", str(road_model[1]), str(slow), str(held)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = {ln.split("|")[1].strip(): ln for ln in proc.stdout.splitlines() if ln.startswith("| p12")}
    assert "| 0 |" in rows["p12.0-roadC5-s2"] and "slower than the calibration's slowest" in rows["p12.0-roadC5-s2"], rows
    assert "unknown" in rows["p12.0-roadC5-s2"] and "| 0 |" not in rows["p12.0-roadC60-s2"], rows
    proc = subprocess.run([str(shocktwin_bin), "replay", "--model", str(FIXTURE_BUNDLE), "--road", str(road_model[1]),
                           "--out", str(tmp_path / "slow.csv"), str(slow)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert re.search(r"road observer: 0 blocks read, 0 at rest, [1-9]\d* slower than calibrated", proc.stdout), proc.stdout
    assert {r["health"] for r in csv.DictReader((tmp_path / "slow.csv").open())} == {"unknown"}
    # nor is it a baseline: the Python tool names the floor instead of reading nothing
    with pytest.raises(ValueError, match=r"every block of the baseline drive is slower than the calibration's slowest"):
        ro.main(["evaluate", "--physics", str(road_model[0]), "--road", str(road_model[1]), "--out", str(tmp_path / "ev"),
                 "--baseline", f"held={slow}@12", "--jobs", "1", f"held={road_sets[1]}"])


def test_at_a_slow_drive_the_friction_falls_short_by_the_sensors_noise_and_simex_recovers_part_of_it(
        shocktwin_bin: Path, road_model: tuple[Path, Path], tmp_path: Path) -> None:
    """Why a slow drive reads low (docs/history.md, "Twentieth session" and "Twenty-first session"): a
    5 km/h drive at 2 and 12 bar with the simulator's velocity logged at 1 kHz. The stroke
    filter's error there is mostly what the sensors' noise figures give through the filter
    alone; regressed on that velocity, the friction's slope against the gas pressure falls short
    of the true velocity's by more than 5 %, and errors-in-variables SIMEX with those noise
    figures recovers part of it (39 % here; all of it on the simulator's first-order step, whose
    body velocity was half a step old). The study refuses a run whose truth is logged at the
    default 100 Hz, by name."""
    proc = subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--road", "5", "--pressures", "2,12", "--seed", "2",
                           "--truth-velocity-hz", "1000", "--out", str(tmp_path / "slow")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    from train import road_velocity as rv
    out = tmp_path / "study.json"
    runs = sorted((tmp_path / "slow").glob("*.mcap"))
    assert rv.main(["--physics", str(road_model[0]), "--road", str(road_model[1]), "--json", str(out),
                    *map(str, runs)]) == 0
    study = json.loads(out.read_text())
    for row in study["runs"]:
        assert row["noise_only_rms_mps"] >= 0.8 * row["error_rms_mps"], row
    (slope,) = study["slopes"]
    truth = slope["slope_truth_n_per_bar"]
    assert slope["slope_filter_n_per_bar"] < 0.95 * truth, slope
    filt, simex = slope["slope_filter_n_per_bar"], slope["slope_simex_n_per_bar"]
    assert filt + 0.25 * (truth - filt) < simex < 1.03 * truth, slope
    proc = subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--road", "5", "--pressures", "12", "--seed", "2",
                           "--out", str(tmp_path / "plain")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    (plain,) = (tmp_path / "plain").glob("*.mcap")
    with pytest.raises(ValueError, match=r"/truth/velocity is logged at 100 Hz.*--truth-velocity-hz 1000"):
        rv.main(["--physics", str(road_model[0]), "--road", str(road_model[1]), str(plain)])


def test_the_daemon_reads_a_road_asset_with_the_road_observer(shocktwin_bin: Path, road_sets: tuple[Path, Path, Path],
                                                               road_model: tuple[Path, Path], tmp_path: Path) -> None:
    """`shocktwin serve` with `[model] road`, and `road = true` and the unit's `road_baseline` (as
    `shocktwin road --baseline` prints it) for the asset: a leaking run dropped into its inbox ends
    `leak`, with the estimate and interval of `shocktwin replay --road --road-baseline` for the same
    file, covering the charge. Without the baseline a minute of drive leaves the interval wide
    (another unit's seal), yet below `ok`. An asset opted in without a calibration is refused at
    start, naming the key."""
    _, held, base = road_sets
    run, drive = held / "p2.0-roadC60-s2.mcap", f"{base / 'p12.0-roadC60-s3.mcap'}@12"

    def replay(*extra: str) -> dict[str, str]:
        out = tmp_path / f"replay{len(extra)}.csv"
        proc = subprocess.run([str(shocktwin_bin), "replay", "--model", str(FIXTURE_BUNDLE), "--road", str(road_model[1]),
                               *extra, "--out", str(out), str(run)], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        return list(csv.DictReader(out.open()))[-1]

    plain = replay()
    assert plain["health"] in ("leak", "low") and float(plain["pressure_lo_bar"]) <= 2.0 <= float(plain["pressure_hi_bar"])
    last = replay("--road-baseline", drive)
    assert last["health"] == "leak" and float(last["pressure_lo_bar"]) <= 2.0 <= float(last["pressure_hi_bar"]), last
    assert float(last["pressure_hi_bar"]) - float(last["pressure_lo_bar"]) < float(plain["pressure_hi_bar"]) - float(plain["pressure_lo_bar"])

    proc = subprocess.run([str(shocktwin_bin), "road", "--calibration", str(road_model[1]), "--baseline", drive, str(run)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    line = re.search(r"road_baseline = \{.*\}", proc.stderr)
    assert line, proc.stderr

    bad = tmp_path / "bad.toml"
    bad.write_text("[defaults]\nroad = true\n")
    proc = subprocess.run([str(shocktwin_bin), "serve", "--config", str(bad), "--model", str(FIXTURE_BUNDLE), "--no-db",
                           "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "defaults.road" in proc.stderr and "[model] road" in proc.stderr

    config = tmp_path / "serve.toml"
    config.write_text(f'[model]\nroad = "{road_model[1]}"\n\n[assets.dyno-unit-A]\nroad = true\n{line.group(0)}\n')
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    daemon = subprocess.Popen([str(shocktwin_bin), "serve", "--config", str(config), "--model", str(FIXTURE_BUNDLE),
                               "--no-db", "--inbox", str(inbox), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert daemon.stderr is not None
        http = ""
        for _ in range(200):
            text = re.sub(r"\x1b\[[0-9;]*m", "", daemon.stderr.readline())
            m = re.search(r"http=(\S+)", text)
            if m and "listening" in text:
                http = m.group(1)
                break
        assert http, f"the daemon did not start (exit {daemon.poll()})"
        threading.Thread(target=lambda: [None for _ in daemon.stderr], daemon=True).start()  # type: ignore[union-attr]
        (inbox / run.name).write_bytes(run.read_bytes())
        deadline = time.monotonic() + 120
        asset: dict[str, Any] = {}
        while time.monotonic() < deadline:
            r = httpx.get(f"http://{http}/v1/assets/dyno-unit-A", timeout=10)
            if r.status_code == 200:
                asset = r.json()
                if asset.get("last_run_status") == "completed":
                    break
            time.sleep(0.5)
        assert asset.get("last_run_status") == "completed", asset
        assert asset["health"] == "leak", asset
        for key in ("pressure_bar", "pressure_avg_bar", "pressure_lo_bar", "pressure_hi_bar"):
            assert asset[key] == pytest.approx(float(last[key]), abs=1e-9), key
        # Prometheus can alert on it: one series per state, 1 at the asset's (a helper's trial
        # found only fleet-wide counters)
        text = httpx.get(f"http://{http}/metrics", timeout=10).text
        states = {m.group(1): float(m.group(2)) for m in
                  re.finditer(r'^shocktwin_asset_health\{asset="dyno-unit-A",health="(\w+)"\} (\S+)$', text, re.M)}
        assert states == {"ok": 0.0, "low": 0.0, "leak": 1.0, "unknown": 0.0}, text
        shown = re.search(r'^shocktwin_asset_pressure_bar\{asset="dyno-unit-A"\} (\S+)$', text, re.M)
        assert shown and float(shown.group(1)) == pytest.approx(asset["pressure_avg_bar"], abs=1e-9), text
        # A dyno sine run of the road asset is refused naming its excitation, as `shocktwin road`
        # and `replay --road` do (the daemon read it as a drive: a helper's trial, sixty-second session)
        subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--pressures", "6", "--frequencies", "1",
                        "--out", str(tmp_path / "dyno")], check=True, capture_output=True)
        sine = next((tmp_path / "dyno").glob("*.mcap"))
        proc = subprocess.run([str(shocktwin_bin), "replay", "--model", str(FIXTURE_BUNDLE), "--road", str(road_model[1]),
                               "--out", str(tmp_path / "sine.csv"), str(sine)], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 1 and f"{sine}: run `{sine.stem}` is a dyno run (excitation" in proc.stderr, proc.stderr
        (inbox / sine.name).write_bytes(sine.read_bytes())
        reason = inbox / "failed" / f"{sine.name}.reason.txt"
        deadline = time.monotonic() + 60
        while not reason.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert reason.exists() and "is a dyno run (excitation" in reason.read_text(), list(inbox.rglob("*"))
    finally:
        daemon.terminate()
        daemon.wait(timeout=30)


def parked(drive: Path, out: Path) -> Path:
    """The drive's log with the stroke held still (the position at its first value, the body
    accelerometer's reading on the wheel end too): a vehicle standing with its engine on."""
    lg = shocktwin.read_log(str(drive))
    topics = {}
    for topic in lg.topics:
        d = lg.topic(topic)
        fields = {k: v for k, v in d.items() if k != "t_s"}
        if topic == "/position":
            fields["position_m"] = np.full_like(fields["position_m"], fields["position_m"][0])
        if topic == "/acceleration":
            fields["a1_mps2"] = fields["a2_mps2"]
        topics[topic] = (lg.t0_ns + np.round(d["t_s"] * 1e9).astype(np.int64), fields)
    meta = {k: str(v) for k, v in lg.metadata.items()} | {"run_id": "parked"}
    return write_mcap_log(out, meta, topics)


def test_a_service_on_a_road_asset_reads_its_next_drive_into_the_unit_s_road_baseline(
        shocktwin_bin: Path, road_sets: tuple[Path, Path, Path], road_model: tuple[Path, Path], tmp_path: Path,
        driver: Any) -> None:
    """The fleet flow on a road asset: the maintainer reports a service at 12 bar
    (`PUT …/service`); the unit's next drive, dropped into the inbox, is read by the road
    observer into the asset's road baseline — the offset `shocktwin road --baseline` reads from
    the same file, kept in the fleet store across a restart — and the drive after it (2 bar) ends
    `leak` with the estimate and interval of `replay --road --road-baseline`. An observer
    baseline is refused for the road asset, naming the kind it takes; `/v1/assets` marks it.
    What the road observer made of each run is in `/runs` and the asset's `last_run_road`, kept
    across the restart; a parked run (no stroke) says why it read nothing, and the dashboard
    (headless Chromium) marks the asset and gives each run's blocks."""
    _, held, base = road_sets
    drive, run = base / "p12.0-roadC60-s3.mcap", held / "p2.0-roadC60-s2.mcap"
    proc = subprocess.run([str(shocktwin_bin), "road", "--calibration", str(road_model[1]), "--baseline",
                           f"{drive}@12", str(run)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    m = re.search(r"road_baseline = \{ charge_bar = (\S+), offset_n = (\S+), blocks = (\d+) \}", proc.stderr)
    assert m, proc.stderr
    want = {"charge_bar": float(m.group(1)), "offset_n": float(m.group(2)), "blocks": int(m.group(3))}
    out = tmp_path / "replay.csv"
    proc = subprocess.run([str(shocktwin_bin), "replay", "--model", str(FIXTURE_BUNDLE), "--road", str(road_model[1]),
                           "--road-baseline", f"{drive}@12", "--out", str(out), str(run)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    last = list(csv.DictReader(out.open()))[-1]

    config = tmp_path / "serve.toml"
    config.write_text(f'[model]\nroad = "{road_model[1]}"\n\n[assets.dyno-unit-A]\nroad = true\n')
    inbox, db = tmp_path / "inbox", tmp_path / "fleet.sqlite"
    inbox.mkdir()
    argv = [str(shocktwin_bin), "serve", "--config", str(config), "--model", str(FIXTURE_BUNDLE), "--db", str(db),
            "--inbox", str(inbox), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"]

    def settled(http: str, runs: int) -> dict[str, Any]:
        """The asset once `runs` runs of it have completed."""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            r = httpx.get(f"http://{http}/v1/assets/dyno-unit-A/runs", timeout=10)
            if r.status_code == 200 and sum(x["status"] == "completed" for x in r.json()["runs"]) >= runs:
                return httpx.get(f"http://{http}/v1/assets", timeout=10).json()["assets"][0]
            time.sleep(0.5)
        raise AssertionError(f"{runs} runs did not complete")

    daemon = ServeProcess(argv)
    try:
        api = f"http://{daemon.http}/v1/assets/dyno-unit-A"
        # the simulated drives carry 2023 clocks: the service is dated before them
        r = httpx.put(f"{api}/service", json={"charge_bar": 12.0, "at": "2023-01-01T00:00:00Z"}, timeout=10)
        assert r.status_code == 202, r.text
        (inbox / drive.name).write_bytes(drive.read_bytes())
        asset = settled(daemon.http, 1)
        assert asset["road"] is True and asset["service"] is None, asset
        b = asset["baseline"]
        assert (b["kind"], b["source"], b["blocks"]) == ("road", "api", want["blocks"]), (b, daemon.text())
        assert b["charge_bar"] == want["charge_bar"] and b["offset_n"] == pytest.approx(want["offset_n"], abs=1e-9)
        assert "read_bar" not in b
        # the baseline is the mean over the blocks the road observer read of that drive
        assert asset["last_run_road"]["read"] == want["blocks"] and "why_none" not in asset["last_run_road"], asset
        assert "last_run_observer" not in asset, asset
        r = httpx.put(f"{api}/baseline", json={"charge_bar": 12.0, "read_bar": 10.8, "read_sd_bar": 0.3}, timeout=10)
        assert r.status_code == 409 and "offset_n" in r.json()["error"], r.text
    finally:
        daemon.stop()
    daemon = ServeProcess(argv)   # the road baseline comes back from the store
    try:
        (inbox / run.name).write_bytes(run.read_bytes())
        asset = settled(daemon.http, 2)
        assert asset["baseline"]["kind"] == "road" and asset["baseline"]["source"] == "api", asset
        assert asset["health"] == "leak", asset
        for key in ("pressure_bar", "pressure_avg_bar", "pressure_lo_bar", "pressure_hi_bar"):
            assert asset[key] == pytest.approx(float(last[key]), abs=1e-9), key
        assert float(last["pressure_lo_bar"]) <= 2.0 <= float(last["pressure_hi_bar"]), last
        api = f"http://{daemon.http}/v1/assets/dyno-unit-A"
        parked(run, inbox / "parked.mcap")
        asset = settled(daemon.http, 3)
        still = asset["last_run_road"]
        assert still["read"] == 0 and still["at_rest"] >= 3, still
        assert "at rest" in still["why_none"] and "keeps its prior" in still["why_none"], still
        runs = {x["run_id"]: x["road"] for x in httpx.get(f"{api}/runs", timeout=10).json()["runs"]}
        assert runs["parked"] == still and runs[drive.stem]["read"] == want["blocks"], runs
        assert runs[run.stem]["read"] >= 3 and "why_none" not in runs[run.stem], runs

        from selenium.webdriver.common.by import By

        driver.get(f"http://{daemon.http}/#dyno-unit-A")
        pill = wait_for(lambda: driver.find_elements(By.CSS_SELECTOR, 'tr[data-asset-id="dyno-unit-A"] .road-none'))[0]
        assert pill.text == "road: no block read" and "at rest" in pill.get_attribute("title")
        cells = wait_for(lambda: {r: c[0].text for r in runs
                                  if (c := driver.find_elements(By.CSS_SELECTOR, f'tr[data-run-id="{r}"] td.obs.road'))}
                         if len(driver.find_elements(By.CSS_SELECTOR, "td.obs.road")) == 3 else None)
        total = {r: sum(v for k, v in c.items() if k != "why_none") for r, c in runs.items()}
        assert cells == {"parked": "none read", drive.stem: f"{want['blocks']}/{total[drive.stem]}",
                         run.stem: f"{runs[run.stem]['read']}/{total[run.stem]}"}, cells
        shot = tmp_path / "road-runs.png"
        driver.save_screenshot(str(shot))
        print(f"screenshot: {shot}")
        errors = [e for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
        assert not errors, errors
    finally:
        daemon.stop()


def wait_for(probe: Any, timeout_s: float = 20) -> Any:
    """``probe()`` once it returns something truthy."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = probe()
        if got:
            return got
        time.sleep(0.2)
    raise AssertionError("timed out")


def test_a_road_vehicle_losing_gas_gets_its_leak_rate_and_fault_date(
        shocktwin_bin: Path, road_model: tuple[Path, Path], tmp_path: Path) -> None:
    """What a maintainer runs the daemon for, on a road vehicle: six days of simulated drives of
    a unit losing 1 bar a day from 11 bar (`simulate --road 60 --days 6`, each day its own drive
    file; quick runs). A service at 11 bar is reported before day 0, whose drive becomes the road
    baseline; days 1-5 are read with it. Each day's interval covers its charge, the trend's leak
    rate interval covers 1 bar/day and excludes 0, and the predicted fault (5 bar) crossing
    interval covers the true one (day 6, at day 0's hour)."""
    days = tmp_path / "days"
    proc = subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--road", "60", "--days", "6", "--leak-rate", "1",
                           "--start-bar", "11", "--asset-id", "car-33", "--seed", "5", "--out", str(days)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    files = sorted(days.glob("d*.mcap"))
    assert len(files) == 6
    config = tmp_path / "serve.toml"
    config.write_text(f'[model]\nroad = "{road_model[1]}"\n\n[assets.car-33]\nroad = true\n')
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    daemon = ServeProcess([str(shocktwin_bin), "serve", "--config", str(config), "--model", str(FIXTURE_BUNDLE),
                           "--db", str(tmp_path / "fleet.sqlite"), "--inbox", str(inbox), "--listen", "127.0.0.1:0",
                           "--http", "127.0.0.1:0"])
    api = f"http://{daemon.http}/v1/assets/car-33"

    def completed(n: int) -> list[dict[str, Any]]:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            r = httpx.get(f"{api}/runs", timeout=10)
            if r.status_code == 200:
                runs = [x for x in r.json()["runs"] if x["status"] == "completed"]
                if len(runs) >= n:
                    return runs
            time.sleep(0.5)
        raise AssertionError(f"{n} runs did not complete:\n{daemon.text()[-3000:]}")

    try:
        r = httpx.put(f"{api}/service", json={"charge_bar": 11.0, "at": "2023-11-14T00:00:00Z"}, timeout=10)
        assert r.status_code == 202, r.text
        (inbox / files[0].name).write_bytes(files[0].read_bytes())
        completed(1)
        base = httpx.get(f"{api}/baseline", timeout=10).json()
        assert base["kind"] == "road" and base["charge_bar"] == 11.0 and base["blocks"] >= 3, base
        for f in files[1:]:
            (inbox / f.name).write_bytes(f.read_bytes())
        completed(6)
        history = httpx.get(f"{api}/history", params={"since": "2023-11-14T00:00:00Z", "step_s": 1}, timeout=10).json()
        trend = httpx.get(f"{api}/trend", timeout=10).json()
    finally:
        daemon.stop()
    assert trend["status"] == "ok" and trend["runs_used"] == 6, trend
    assert 0 < trend["leak_rate_lo_bar_per_day"] <= 1.0 <= trend["leak_rate_hi_bar_per_day"], trend
    for day, point in enumerate(trend["points"]):
        assert abs(point["pressure_bar"] - (11.0 - day)) < 2 * point["sd_bar"] + 0.5, point
    # each day's last estimate: its interval covers the day's charge
    def unix(t: str) -> float:
        return datetime.fromisoformat(t.replace("Z", "+00:00")).timestamp()

    points = [{**p, "t_s": unix(p["t"])} for p in history["points"] if p["pressure_bar"] is not None]
    assert points, history
    starts = []
    for f in files:
        with open(f, "rb") as fh:
            starts.append(next(m for _, _, m in make_reader(fh).iter_messages(log_time_order=True)).log_time / 1e9)
    for day, (f, start) in enumerate(zip(files, starts)):
        if day == 0:
            continue
        last = [p for p in points if start <= p["t_s"] < start + 3600][-1]
        assert last["pressure_lo_bar"] <= 11.0 - day <= last["pressure_hi_bar"], (f.name, last)
    # the true crossing: the line through the true charges at the runs' times, at 5 bar
    slope, intercept = np.polyfit(np.array(starts) - starts[0], 11.0 - np.arange(6.0), 1)
    true_fault = starts[0] + (5.0 - intercept) / slope
    fault = trend["fault"]
    lo, hi = unix(fault["t_lo"]), unix(fault["t_hi"])
    assert lo <= true_fault <= hi, (fault, true_fault)


def test_a_drive_file_of_its_own_seed_is_its_own_drive_for_the_calibration() -> None:
    """`simulate --drive-seed` runs carry `drive_seed`: the fit's leave-one-drive-out groups by it,
    not by the rig's `seed` (two roads on one rig are two drive files)."""
    class Run:
        def __init__(self, meta: dict[str, str]) -> None:
            self.run_id = meta.get("run_id", "r")
            self.log = type("Log", (), {"metadata": meta})()

    road = "road: ISO 8608 class C at 60 km/h"
    same_rig = [Run({"excitation": road, "seed": "4"}), Run({"excitation": road, "seed": "4", "drive_seed": "6"})]
    other_rig = Run({"excitation": road, "seed": "6"})
    assert ro.drive_of(same_rig[0]) != ro.drive_of(same_rig[1])
    assert ro.drive_of(same_rig[1]) == ro.drive_of(other_rig)


def test_a_sampling_skew_of_a2_behind_a1_beyond_100_us_lowers_the_friction_read(
        road_sets: tuple[Path, Path, Path], road_model: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    """`road_observer skew` (docs/history.md, "Twentieth session" and "Twenty-first session"): read
    unskewed, a run reads as the observer does; `a2` sampled 100 µs after `a1` moves the friction
    read by well under 2 %, 250 µs lowers it (6 % on the demo's quick 60 km/h drive) and so the charge; a skew of
    0 is the plain reading exactly. A fractional shift by FFT moves a sampled sine by its skew."""
    held = road_sets[1] / "p12.0-roadC60-s2.mcap"
    assert ro.main(["skew", "--physics", str(road_model[0]), "--road", str(road_model[1]), "--skew-us", "0,100,250",
                    str(held)]) == 0
    rows = [ln.split("|") for ln in capsys.readouterr().out.splitlines() if ln.startswith(f"| {held.name}")]
    assert [float(r[2]) for r in rows] == [0.0, 100.0, 250.0]
    model = json.loads(road_model[1].read_text())
    opts = {k: model[k] for k in ("block_s", "lag_s", "pot_rc_hz", "sigma_accel", "settle_s")}
    plain = ro.calibrated_blocks(ro.block_readings(str(held), json.loads(road_model[0].read_text()), opts), model)
    assert float(rows[0][4]) == pytest.approx(float(np.mean(plain["alpha_n"])), abs=0.006)  # printed to 0.01 N
    change = [float(r[5].strip().rstrip("%")) for r in rows]
    assert abs(change[1]) < 2.0, rows
    assert change[2] < -2.0 and float(rows[2][7]) < -0.5, rows
    t = np.arange(4000) * 1e-3
    x = np.sin(2 * np.pi * 7.0 * t)
    np.testing.assert_allclose(ro.skewed(x, 250e-6)[500:3500], np.sin(2 * np.pi * 7.0 * (t + 250e-6))[500:3500], atol=1e-3)
