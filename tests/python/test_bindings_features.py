"""shocktwin.features and the SPEC §4 tables (groups, columns, sensors, costs,
permutations), and a closed-loop check of the 50 Hz pipeline against the
separately bound models (KalmanFilter, ForceModel, ThermalModel)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_releases_gil, synthetic_run, write_mcap_log

import shocktwin

ALL_TOPICS = ["/position", "/acceleration", "/force", "/temperature/shock", "/temperature/ambient"]
META = {"asset_id": "unit-1", "run_id": "run-1", "charge_pressure_bar": "12"}
TICK_NS = 20_000_000


@pytest.fixture(scope="module")
def full_log(tmp_path_factory) -> shocktwin.Log:
    path = tmp_path_factory.mktemp("logs") / "full.mcap"
    return shocktwin.read_log(write_mcap_log(path, META, synthetic_run(duration_s=6.0)))


@pytest.fixture(scope="module")
def cheap_log(tmp_path_factory) -> shocktwin.Log:
    """The cheap suite of model 12: no loadcell."""
    path = tmp_path_factory.mktemp("logs") / "cheap.mcap"
    topics = [t for t in ALL_TOPICS if t != "/force"]
    return shocktwin.read_log(write_mcap_log(path, META, synthetic_run(duration_s=3.0, topics=topics)))


# --- tables -------------------------------------------------------------------------------


def test_groups_columns_topics():
    assert shocktwin.GROUPS[:6] == ("force", "position", "acceleration", "velocity", "mechanical", "thermal")
    # beyond the paper: causal-window groups and the charge observer
    assert shocktwin.GROUPS[6:] == ("signature", "residual", "observer")
    assert [c for g in shocktwin.GROUPS for c in shocktwin.group_columns(g)] == list(shocktwin.COLUMNS)
    assert shocktwin.group_topics("force") == ["/force"]
    assert shocktwin.group_topics("velocity") == ["/position", "/acceleration"]
    assert set(shocktwin.group_topics("thermal")) == set(ALL_TOPICS) - {"/force"}
    assert shocktwin.group_topics("signature") == shocktwin.group_topics("thermal")
    assert set(shocktwin.group_topics("residual")) == {"/force"} | set(shocktwin.group_topics("mechanical"))
    with pytest.raises(shocktwin.InputError, match="torque"):
        shocktwin.group_columns("torque")


def test_permutations_are_the_papers_table():
    perms = shocktwin.permutations()
    assert [p["id"] for p in perms] == list(range(1, 14))
    by_id = {p["id"]: p for p in perms}
    # the ones the paper's text fixes (SPEC §4)
    assert by_id[3]["groups"] == ["force", "position"]
    assert by_id[7]["groups"] == ["force", "position", "acceleration"]
    assert by_id[12]["groups"] == ["position", "acceleration", "velocity", "mechanical", "thermal"]
    assert by_id[13]["groups"] == list(shocktwin.GROUPS[:6])
    assert by_id[12]["paper_rmse_bar"] == 1.40 and by_id[13]["paper_rmse_bar"] == 0.85
    # paper abstract: suites cost A$297 to A$4,292
    assert by_id[12]["cost_aud"] == 297 and by_id[13]["cost_aud"] == 4292
    assert min(p["cost_aud"] for p in perms) == 11  # accelerometers alone (model 4)
    for p in perms:
        assert p["columns"] == [c for g in p["groups"] for c in shocktwin.group_columns(g)]
        assert p["cost_aud"] == sum(shocktwin.SENSOR_COSTS_AUD[s] for s in p["sensors"])
    assert shocktwin.PERMUTATIONS == tuple(perms)
    perms[0]["groups"].append("thermal")  # a fresh copy each call
    assert shocktwin.permutations()[0]["groups"] == ["force"]


def test_extra_permutations_are_ours():
    extra = {p["id"]: p for p in shocktwin.extra_permutations()}
    assert sorted(extra) == [14, 15, 16, 17, 18, 19]
    assert extra[14]["groups"] == ["velocity", "mechanical", "signature"]
    assert extra[14]["sensors"] == ["potentiometer", "accelerometers", "thermocouples"]
    assert extra[15]["groups"] == ["force", "velocity", "mechanical", "residual"]
    assert extra[16]["groups"] == ["force", "velocity", "mechanical", "residual", "signature"]
    assert [extra[i]["cost_aud"] for i in (14, 15, 16)] == [297, 4292, 4292]
    assert extra[17]["groups"] == ["observer"]
    assert extra[17]["sensors"] == ["potentiometer", "accelerometers", "thermocouples"]
    assert extra[18]["groups"] == [*shocktwin.permutations()[11]["groups"], "observer"]
    assert [extra[i]["cost_aud"] for i in (17, 18, 19)] == [297, 297, 4292]
    assert all(p["paper_rmse_bar"] is None for p in extra.values())
    for p in extra.values():
        assert p["columns"] == [c for g in p["groups"] for c in shocktwin.group_columns(g)]


def test_suite_costs():
    assert shocktwin.SENSOR_COSTS_AUD == {"loadcell": 3995, "potentiometer": 275, "accelerometers": 11, "thermocouples": 11}
    assert shocktwin.suite(["velocity"]) == (["potentiometer", "accelerometers"], 286)
    assert shocktwin.suite(["force", "force"]) == (["loadcell"], 3995)


# --- features: shapes, inputs, errors -----------------------------------------------------


@pytest.mark.parametrize("groups", [[g] for g in shocktwin.GROUPS] + [p["groups"] for p in shocktwin.PERMUTATIONS])
def test_shapes_and_columns_per_group(full_log, groups):
    x, columns, t_s = shocktwin.features(full_log, shocktwin.default_params(), groups)
    assert columns == [c for g in groups for c in shocktwin.group_columns(g)]
    assert x.dtype == np.float64 and x.flags.c_contiguous
    # The pipeline sees only the topics of the groups' suite; its last tick is
    # the one holding the last such sample (6 s at 50 Hz: 300 ticks, or 299
    # for the loadcell alone, whose last sample is at 5.98 s).
    needed = {t for g in groups for t in shocktwin.group_topics(g)}
    t_last = max(full_log.topic(t)["t_s"][-1] for t in needed)
    n_ticks = int(np.ceil(round(t_last / 0.02, 9)))
    assert x.shape == (len(t_s), len(columns)) == (n_ticks, len(columns))
    assert n_ticks in (299, 300)
    np.testing.assert_allclose(t_s, 0.02 * np.arange(1, n_ticks + 1), rtol=0, atol=1e-12)
    # after the first second every column is filled (the 10 s temperature
    # rate of `signature` needs 10 s of history: NaN in this 6 s log)
    late = [i for i, c in enumerate(columns) if c == "temp_resid_rate_cps"]
    assert np.isfinite(np.delete(x[50:], late, axis=1)).all()
    assert np.isnan(x[:, late]).all()


def test_group_order_is_kept(full_log):
    params = shocktwin.default_params()
    x_a, cols_a, _ = shocktwin.features(full_log, params, ["thermal", "force"])
    x_b, cols_b, _ = shocktwin.features(full_log, params, ["force", "thermal"])
    assert cols_a == cols_b[1:] + cols_b[:1]
    np.testing.assert_array_equal(x_a, np.roll(x_b, -1, axis=1))


def test_missing_sensor_names_the_topics(cheap_log):
    params = shocktwin.default_params()
    with pytest.raises(shocktwin.MissingTopicsError, match="/force") as info:
        shocktwin.features(cheap_log, params, ["position", "force"])
    assert info.value.topics == ["/force"]
    assert isinstance(info.value, shocktwin.LogError) and isinstance(info.value, ValueError)
    # the cheap suite's own permutation works on it
    x, cols, _ = shocktwin.features(cheap_log, params, shocktwin.PERMUTATIONS[11]["groups"])
    assert x.shape[1] == len(cols) == 11


def test_missing_several_topics(tmp_path: Path):
    log = shocktwin.read_log(write_mcap_log(tmp_path / "p.mcap", META, synthetic_run(duration_s=1.0, topics=["/position"])))
    with pytest.raises(shocktwin.MissingTopicsError) as info:
        shocktwin.features(log, shocktwin.default_params(), ["velocity", "thermal"])
    assert set(info.value.topics) == {"/acceleration", "/temperature/shock", "/temperature/ambient"}
    for topic in info.value.topics:
        assert topic in str(info.value)
    # position alone needs only the potentiometer
    x, _, _ = shocktwin.features(log, shocktwin.default_params(), ["position"])
    assert x.shape == (50, 1)


def test_unknown_group_is_named(full_log):
    with pytest.raises(shocktwin.InputError, match="gas"):
        shocktwin.features(full_log, shocktwin.default_params(), ["position", "gas"])
    with pytest.raises(TypeError):
        shocktwin.features(full_log, shocktwin.default_params(), "position")  # a str is not a list


def test_params_from_dict_and_file(full_log, tmp_path: Path):
    params = shocktwin.default_params()
    params["force"]["charge_bar"] = 7.0
    groups = ["mechanical"]
    want, _, _ = shocktwin.features(full_log, params, groups)
    # physics.json as train.fit_physics writes it: extra top-level keys are ignored
    physics = tmp_path / "physics.json"
    physics.write_text(json.dumps({"format": "shocktwin-physics/1", **params, "fit": {"runs": []}}))
    got_file, _, _ = shocktwin.features(full_log, physics, groups)
    got_str, _, _ = shocktwin.features(full_log.path, str(physics), groups)  # the log as a path too
    for got in (got_file, got_str):
        np.testing.assert_array_equal(got, want)
    # and the parameters matter: the nominal charge changes the gas force column
    nominal, _, _ = shocktwin.features(full_log, shocktwin.default_params(), groups)
    assert np.nanmax(np.abs(nominal[:, 2] - want[:, 2])) > 10.0
    with pytest.raises(TypeError, match="groups"):
        shocktwin.features(full_log, params)  # groups may be left out only with a bundle


@pytest.mark.filterwarnings("ignore:Stochastic Optimizer")  # 5 iterations: the network is not the point
def test_params_and_groups_from_a_bundle(full_log, tmp_path: Path):
    """A bundle written by train/model.py (SPEC §5): its physics and its permutation's groups."""
    pytest.importorskip("skl2onnx")
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    try:
        from train import model as train_model
    finally:
        sys.path.pop(0)
    params = shocktwin.default_params()
    params["force"]["charge_bar"] = 7.0
    perm = shocktwin.PERMUTATIONS[9]  # model 10: no force
    x, columns, _ = shocktwin.features(full_log, params, perm["groups"])
    rows = np.isfinite(x).all(axis=1)
    trained = train_model.fit(x[rows], np.full(rows.sum(), 12.0), columns, seed=0, max_iter=5)
    bundle = train_model.write_bundle(
        tmp_path / "bundle", trained, permutation=perm, physics=params, nominal_bar=12.0,
        provenance={"campaign_digest": None, "split": "none", "seed": 0, "metrics": {}},
    )
    got, got_columns, _ = shocktwin.features(full_log, bundle)  # groups from the bundle
    assert got_columns == columns
    np.testing.assert_array_equal(got, x)
    got, _, _ = shocktwin.features(full_log, str(bundle), ["position"])  # or as given
    np.testing.assert_array_equal(got[:, 0], x[:, 0])
    (bundle / "mlp.onnx").write_bytes(b"garbage")
    with pytest.raises(shocktwin.BundleError, match="mlp.onnx"):
        shocktwin.features(full_log, bundle)


def test_bad_params_are_named(full_log, tmp_path: Path):
    params = shocktwin.default_params()
    del params["thermal"]["ha_out"]
    with pytest.raises(shocktwin.ParamsError, match="ha_out"):
        shocktwin.features(full_log, params, ["position"])
    params = shocktwin.default_params()
    params["force"]["k_leek_reb"] = 1.0
    with pytest.raises(shocktwin.ParamsError, match="k_leek_reb"):
        shocktwin.features(full_log, params, ["position"])
    params = shocktwin.default_params()
    params["thermal"]["c_oil"] = -5.0
    with pytest.raises(shocktwin.ParamsError, match="c_oil"):
        shocktwin.features(full_log, params, ["position"])
    with pytest.raises(FileNotFoundError, match="nope.json") as missing:
        shocktwin.features(full_log, tmp_path / "nope.json", ["position"])
    # and a ShocktwinError, as the exceptions module says of every error (it was the builtin alone)
    assert isinstance(missing.value, shocktwin.ParamsNotFoundError), type(missing.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="twin.json"):
        shocktwin.features(full_log, tmp_path / "empty", ["position"])
    (tmp_path / "b2").mkdir()
    (tmp_path / "b2" / "twin.json").write_text("{}")
    with pytest.raises(shocktwin.BundleError, match="twin.json"):
        shocktwin.features(full_log, tmp_path / "b2", ["position"])


# --- closed loop: the pipeline against the separately bound models -------------------------


def boxcar(t_ns_rel, values, n_ticks):
    """SPEC §4 / ARCHITECTURE.md: mean over (t_{k-1}, t_k], hold when empty, NaN before."""
    k = -(-t_ns_rel // TICK_NS)  # ceil: the tick whose interval holds the sample
    out = np.full(n_ticks, np.nan)
    last = np.nan
    for tick in range(1, n_ticks + 1):
        sel = (k == tick) & np.isfinite(values)
        last = values[sel].mean() if sel.any() else last
        out[tick - 1] = last
    return out


def test_pipeline_matches_the_bound_models(full_log):
    """velocity = boxcar of KalmanFilter.run; the mechanical columns =
    ForceModel at the boxcar means and the modelled oil temperature; the
    oil/cylinder temperatures = ThermalModel.simulate over the ticks with the
    heat rate and ambient of the previous tick."""
    params = shocktwin.default_params()
    x, cols, t_s = shocktwin.features(full_log, params, list(shocktwin.GROUPS))
    col = {c: x[:, i] for i, c in enumerate(cols)}
    n = len(t_s)

    acc, pos = full_log.topic("/acceleration"), full_log.topic("/position")
    a_rel = acc["a1_mps2"] - acc["a2_mps2"]
    kf = shocktwin.KalmanFilter(**params["kalman"]).run(acc["t_s"], a_rel, pos["t_s"], pos["position_m"])
    t_acc = np.round(acc["t_s"] * 1e9).astype(np.int64)
    t_pos = np.round(pos["t_s"] * 1e9).astype(np.int64)
    tight = dict(rtol=1e-9, atol=1e-9)

    np.testing.assert_allclose(col["position_m"], boxcar(t_pos, pos["position_m"], n), **tight)
    np.testing.assert_allclose(col["accel_rel_mps2"], boxcar(t_acc, a_rel, n), **tight)
    velocity = boxcar(t_acc, kf["velocity_mps"], n)
    np.testing.assert_allclose(col["velocity_mps"], velocity, **tight)
    assert np.nanmax(np.abs(velocity)) > 0.4  # a 2 Hz, 80 mm p-p sine peaks at 0.5 m/s

    y_hat = boxcar(t_acc, kf["position_m"], n)
    a_hat = boxcar(t_acc, a_rel - kf["bias_mps2"], n)
    oil = col["oil_temp_model_c"]
    parts = shocktwin.ForceModel(**params["force"]).components(velocity, a_hat, y_hat, oil)
    np.testing.assert_allclose(col["force_model_n"], parts["force_n"], **tight)
    np.testing.assert_allclose(
        col["force_damping_model_n"], parts["port_n"] + parts["main_n"] + parts["hysteresis_n"], **tight
    )
    np.testing.assert_allclose(col["force_gas_model_n"], parts["gas_n"], **tight)
    np.testing.assert_allclose(col["heat_rate_model_w"], parts["power_w"], **tight)

    t_shock0 = full_log.topic("/temperature/shock")["temperature_c"][0]
    sim_oil, sim_cyl = shocktwin.ThermalModel(**params["thermal"]).simulate(
        t_s, col["heat_rate_model_w"], col["temp_ambient_c"], t_shock0, t_shock0
    )
    np.testing.assert_allclose(oil, sim_oil, **tight)
    np.testing.assert_allclose(col["cyl_temp_model_c"], sim_cyl, **tight)
    assert oil[-1] > oil[0] + 1.0  # it heated: the comparison is not of constants


# --- the GIL ------------------------------------------------------------------------------


def _long_calls():
    n = 3_000_000
    t = np.arange(n) * 1e-3
    zeros = np.zeros(n)
    return {
        "KalmanFilter.run": lambda: shocktwin.KalmanFilter().run(t, zeros, t[::10], zeros[::10]),
        "ThermalModel.simulate": lambda: shocktwin.ThermalModel().simulate(t, zeros + 100.0, zeros, 20.0, 20.0),
        "ForceModel.force": lambda: shocktwin.ForceModel().force(zeros + 0.3, zeros, zeros, zeros + 40.0),
    }


@pytest.mark.parametrize("name", list(_long_calls()))
def test_long_calls_release_the_gil(name):
    """While a long call runs in a thread, this thread keeps running Python:
    the largest pause it sees is far shorter than the call."""
    assert_releases_gil(name, _long_calls()[name])


def test_replay_of_a_log_without_a_sensor_the_model_reads_fails_naming_it(tmp_path: Path):
    """The command line agrees with the bindings: a log without the loadcell replayed with a
    loadcell model (13) fails naming `/force` and exits 1; it printed `final NaN` and exited 0.
    A complete log beside it is still replayed."""
    import subprocess

    repo = Path(__file__).resolve().parents[2]
    topics = [t for t in ALL_TOPICS if t != "/force"]
    cheap = write_mcap_log(tmp_path / "cheap.mcap", META | {"run_id": "cheap"}, synthetic_run(duration_s=3.0, topics=topics))
    whole = write_mcap_log(tmp_path / "whole.mcap", META | {"run_id": "whole"}, synthetic_run(duration_s=3.0))
    done = subprocess.run([str(repo / "target" / "release" / "shocktwin"), "replay", "--model",
                           str(repo / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"),
                           str(cheap), str(whole), "--out", str(tmp_path / "out.csv")],
                          capture_output=True, text=True, env={"CI": "true"})
    assert done.returncode == 1, done
    assert 'cheap.mcap: lacks topics ["/force"] needed by the model' in done.stderr, done.stderr
    assert "replayed 1 run(s)" in done.stdout, done.stdout


def test_the_road_observer_refuses_a_dyno_sine_run(tmp_path: Path):
    """A dyno run (its metadata's excitation a sine) is not read as a road drive: a healthy
    6 bar unit's 1 Hz sine was read `leak` without a word."""
    repo = Path(__file__).resolve().parents[2]
    cal = (repo / "crates" / "dt-core" / "tests" / "fixtures" / "road.json").read_text()
    sine = write_mcap_log(tmp_path / "sine.mcap", META | {"excitation": "sine 1 Hz 80 mm p-p"},
                          synthetic_run(duration_s=3.0, frequency_hz=1.0))
    with pytest.raises(shocktwin.InputError, match=r"run-1.*is a dyno run \(excitation \"sine 1 Hz 80 mm p-p\"\)"):
        shocktwin.road_blocks(str(sine), cal)


def test_road_blocks_takes_the_calibration_as_text_or_path(tmp_path: Path):
    """The calibration as JSON text or as a path (str or Path), like every other argument."""
    repo = Path(__file__).resolve().parents[2]
    cal = repo / "crates" / "dt-core" / "tests" / "fixtures" / "road.json"
    run = write_mcap_log(tmp_path / "drive.mcap", META, synthetic_run(duration_s=3.0))
    by_text = shocktwin.road_blocks(str(run), cal.read_text())
    for given in (cal, str(cal)):
        got = shocktwin.road_blocks(str(run), given)
        assert got.keys() == by_text.keys()
        for k in by_text:
            np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(by_text[k]))
    with pytest.raises(shocktwin.ParamsNotFoundError, match="no-such.json"):
        shocktwin.road_blocks(str(run), tmp_path / "no-such.json")
    # physics.json given as the calibration is said to be one (it read "written by an older fit")
    physics = tmp_path / "physics.json"
    physics.write_text(json.dumps(shocktwin.default_params()))
    with pytest.raises(shocktwin.ParamsError, match=r"physics.json: a physics file .* not a road calibration"):
        shocktwin.road_blocks(str(run), physics)
    # a charge without its drive was ignored without a word
    with pytest.raises(shocktwin.InputError, match="baseline_bar given without baseline"):
        shocktwin.road_blocks(str(run), cal, baseline_bar=12.0)
    with pytest.raises(TypeError, match="calibration: expected JSON text or a path, got int"):
        shocktwin.road_blocks(str(run), 42)


def test_ctrl_c_interrupts_a_long_call(shocktwin_bin: Path, tmp_path: Path):
    """Ctrl-C during a long call (an estimate of a 435 s run with the committed perm-18 bundle)
    raises ``KeyboardInterrupt`` soon after the signal, not when the call ends (a helper's trial
    in a notebook), and the computation stops too: its thread (``shocktwin-call``, read from
    ``/proc``) is gone soon after, where it ran on to the call's end before. Timed against the
    same call uninterrupted, in the same process (ratios)."""
    import subprocess

    repo = Path(__file__).resolve().parents[2]
    subprocess.run([str(shocktwin_bin), "simulate", "--pressures", "12", "--frequencies", "2",
                    "--out", str(tmp_path)], check=True, capture_output=True)
    run = next(tmp_path.glob("*.mcap"))
    script = """
import json, os, signal, sys, threading, time
import shocktwin
log = shocktwin.read_log(sys.argv[1])
bundle = shocktwin.Bundle(sys.argv[2])
t = time.monotonic()
shocktwin.estimate(log, bundle)
whole = time.monotonic() - t
def calls():
    names = []
    for task in os.listdir("/proc/self/task"):
        try:
            names.append(open(f"/proc/self/task/{task}/comm").read().strip())
        except OSError:
            pass  # ended meanwhile
    return names.count("shocktwin-call")
threading.Timer(0.1 * whole, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
t = time.monotonic()
try:
    shocktwin.estimate(log, bundle)
    print(json.dumps({"whole": whole, "completed": time.monotonic() - t}))
except KeyboardInterrupt:
    interrupted = time.monotonic() - t
    running = calls()
    while calls() and time.monotonic() - t < 2.0 * whole:
        time.sleep(0.005)
    print(json.dumps({"whole": whole, "interrupted": interrupted, "running_then": running,
                      "stopped": time.monotonic() - t, "left": calls()}))
"""
    done = subprocess.run([sys.executable, "-c", script, str(run), str(repo / "docs" / "study" / "bundles" / "perm-18")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    print(got)
    assert "interrupted" in got, got
    assert got["whole"] > 0.3, f"the call is too short to tell: {got}"
    assert got["interrupted"] < 0.5 * got["whole"], got
    # the computation stopped well before its end (before, it ran on to it: "stopped" ≈ "whole")
    assert got["left"] == 0 and got["stopped"] < 0.5 * got["whole"], got
