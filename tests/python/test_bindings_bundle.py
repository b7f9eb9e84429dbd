"""``shocktwin.Bundle`` and ``shocktwin.estimate`` on dt-core's fixture bundles
(``crates/dt-core/tests/fixtures/bundle-*``: random weights, outputs from a numpy
forward pass cross-checked with onnxruntime) and synthetic logs. Bundles trained
by ``train/`` are tested in ``test_train_tools.py``."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import shocktwin
from conftest import assert_releases_gil

FIXTURES = Path(__file__).resolve().parents[2] / "crates" / "dt-core" / "tests" / "fixtures"
MLP13 = FIXTURES / "bundle-mlp13"
ESTIMATE_KEYS = {
    "t_s", "pressure_bar", "pressure_avg_bar", "expected_bar", "health",
    "velocity_mps", "force_model_n", "oil_temp_c", "pressure_lo_bar", "pressure_hi_bar",
}


def expected(name: str) -> tuple[np.ndarray, np.ndarray]:
    data = json.loads((FIXTURES / name / "expected.json").read_text())
    return np.array(data["rows"], dtype=float), np.array(data["pressure_bar"], dtype=float)


#: |float32 − float64| ≤ BAR · (1 + |float64|): the float32 network's parity bar.
BAR = shocktwin.MLP_F32_PARITY_BAR


@pytest.mark.parametrize(
    ("name", "backend", "precision"),
    [
        ("bundle-mlp13", "dense", "float32"),
        ("bundle-force-skl", "dense", "float32"),
        ("bundle-force-tanh", "tract", "float64"),
    ],
)
def test_predict_matches_the_fixture_outputs(name: str, backend: str, precision: str):
    bundle = shocktwin.Bundle(FIXTURES / name)
    rows, want = expected(name)
    assert bundle.backend == backend and bundle.precision == precision
    got = bundle.predict(rows)
    assert got.dtype == np.float64 and got.shape == (len(rows),)
    tol = BAR if precision == "float32" else 0.0
    np.testing.assert_allclose(got, want, rtol=tol, atol=max(tol, 1e-9))
    np.testing.assert_allclose(bundle.predict_f64(rows), want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(bundle.predict_reference(rows), want, rtol=0, atol=1e-9)
    assert np.ptp(want) > 0.1  # the outputs differ: the comparison is not of one constant


@pytest.mark.parametrize("name", ["bundle-mlp13", "bundle-force-skl"])
def test_float32_network_within_the_parity_bar_of_onnxruntime(name: str):
    """The bundle's mlp.onnx run by onnxruntime (float64) against the float32 dense path,
    on the fixture rows and on rows far from the data (±20 standard deviations)."""
    ort = pytest.importorskip("onnxruntime")
    bundle = shocktwin.Bundle(FIXTURES / name)
    rows, _ = expected(name)
    norm = bundle.twin["normalisation"]
    mean, std = np.array(norm["mean"]), np.array(norm["std"])
    far = mean + std * np.random.default_rng(7).uniform(-20, 20, size=(500, len(mean)))
    session = ort.InferenceSession(str(FIXTURES / name / "mlp.onnx"), providers=["CPUExecutionProvider"])
    (inp,) = session.get_inputs()
    for x in (rows, far):
        want = session.run(None, {inp.name: (x - mean) / std})[0][:, 0]
        np.testing.assert_allclose(bundle.predict(x), want, rtol=BAR, atol=BAR)
        np.testing.assert_allclose(bundle.predict_f64(x), want, rtol=0, atol=1e-9 * (1 + np.abs(want)).max())


def test_properties_are_twin_json():
    bundle = shocktwin.Bundle(str(MLP13))
    twin = json.loads((MLP13 / "twin.json").read_text())
    perm = twin["permutation"]
    assert bundle.columns == perm["columns"]
    assert bundle.groups == perm["groups"]
    assert bundle.permutation == perm
    assert bundle.columns == [c for g in perm["groups"] for c in shocktwin.group_columns(g)]
    # parameters added since the bundle was written (the thermocouple's tc_gain, tc_lag_s)
    # read as their defaults, which reproduce the older model exactly
    defaults = shocktwin.default_params()
    assert bundle.physics == {k: {**defaults[k], **twin["physics"][k]} for k in ("kalman", "thermal", "force")}
    assert set(bundle.physics["thermal"]) - set(twin["physics"]["thermal"]) == {"tc_gain", "tc_lag_s"}
    assert bundle.nominal_bar == twin["nominal_bar"]
    assert bundle.health == twin["health"]
    got = bundle.twin
    assert got["normalisation"] == twin["normalisation"]
    assert got["onnx"] == twin["onnx"] and got["provenance"] == twin["provenance"]
    assert Path(bundle.path) == MLP13
    assert "permutation=13" in repr(bundle) and "backend=dense" in repr(bundle)
    # a fresh dict each time: mutating it changes nothing
    bundle.twin["nominal_bar"] = 1.0
    bundle.physics["force"]["charge_bar"] = 1.0
    assert bundle.twin["nominal_bar"] == twin["nominal_bar"]
    assert bundle.physics["force"]["charge_bar"] == twin["physics"]["force"]["charge_bar"]


def test_predict_inputs():
    bundle = shocktwin.Bundle(MLP13)
    rows, want = expected("bundle-mlp13")
    np.testing.assert_array_equal(bundle.predict(rows.tolist()), bundle.predict(rows))  # lists
    np.testing.assert_array_equal(bundle.predict(np.asfortranarray(rows)), bundle.predict(rows))
    np.testing.assert_array_equal(bundle.predict(rows[::2]), bundle.predict(rows)[::2])  # strided
    assert bundle.predict(np.empty((0, 12))).shape == (0,)
    nan_row = rows[:2].copy()
    nan_row[1, 3] = np.nan
    got = bundle.predict(nan_row)
    assert got[0] == pytest.approx(want[0], abs=BAR * (1 + abs(want[0]))) and np.isnan(got[1])
    with pytest.raises(shocktwin.InputError, match="11 columns.*reads 12"):
        bundle.predict(rows[:, :11])
    # one row must still be 2-D, and the error says so (numpy's own said only
    # that an ndarray "cannot be converted to 'PyArray<T, D>'")
    with pytest.raises(TypeError, match=r"argument 'x': expected a 2-D .* 1-D value of shape \(12,\).*reshape\(1, -1\)"):
        bundle.predict(rows[0])
    with pytest.raises(TypeError, match=r"expected a 2-D .* 3-D value of shape \(1, 2, 12\)"):
        bundle.predict(rows[:2][None])
    with pytest.raises(TypeError, match="dtype `<U1`, which is not a real number type"):
        bundle.predict([["a"] * 12])


def test_missing_and_bad_bundles_are_named(tmp_path: Path):
    with pytest.raises(shocktwin.BundleNotFoundError, match="twin.json") as err:
        shocktwin.Bundle(tmp_path / "nope")
    # a BundleError and a FileNotFoundError
    assert isinstance(err.value, shocktwin.BundleError) and isinstance(err.value, FileNotFoundError)
    copy = tmp_path / "b"
    shutil.copytree(MLP13, copy)
    (copy / "mlp.onnx").unlink()
    with pytest.raises(shocktwin.BundleNotFoundError, match="mlp.onnx"):
        shocktwin.Bundle(copy)
    with pytest.raises(TypeError, match="bundle"):
        shocktwin.estimate(str(tmp_path / "x.mcap"), 12)  # type: ignore[arg-type]


def test_estimate_on_a_synthetic_log(make_log):
    log = shocktwin.read_log(make_log(duration_s=6.0))
    bundle = shocktwin.Bundle(MLP13)
    out = shocktwin.estimate(log, bundle)
    assert set(out) == ESTIMATE_KEYS
    n = len(out["t_s"])
    assert n == 300  # 6 s at 50 Hz
    for key, values in out.items():
        assert values.shape == (n,), key
        assert values.dtype.kind == "U" if key == "health" else values.dtype == np.float64, key
    np.testing.assert_allclose(out["t_s"], 0.02 * np.arange(1, n + 1), rtol=0, atol=1e-12)
    assert set(out["health"]) <= {"ok", "low", "leak", "unknown"}
    assert (out["expected_bar"] == bundle.nominal_bar).all()
    assert np.isfinite(out["pressure_bar"][60:]).all()
    # a bundle without the charge observer has no interval (SPEC §2a: NaN)
    assert np.isnan(out["pressure_lo_bar"]).all() and np.isnan(out["pressure_hi_bar"]).all()
    # the same from paths, and features() takes the Bundle object like its path
    again = shocktwin.estimate(log.path, str(MLP13))
    for key in ESTIMATE_KEYS:
        np.testing.assert_array_equal(again[key], out[key])
    x, columns, t_s = shocktwin.features(log, bundle)
    x_path, _, _ = shocktwin.features(log, MLP13)
    np.testing.assert_array_equal(x, x_path)
    assert columns == bundle.columns
    np.testing.assert_array_equal(t_s, out["t_s"])


def _estimate_in_a_worker(log: shocktwin.Log, bundle: shocktwin.Bundle) -> np.ndarray:
    return shocktwin.estimate(log, bundle)["pressure_bar"]


def test_log_and_bundle_pickle_into_worker_processes(make_log, tmp_path: Path, monkeypatch):
    """A notebook's ``ProcessPoolExecutor`` (spawn: a fresh interpreter, as on macOS and
    Windows) takes ``Log`` and ``Bundle`` objects as arguments: each is pickled as its
    absolute path and read again in the worker. Before, ``cannot pickle 'Log' object``."""
    import concurrent.futures
    import multiprocessing
    import pickle

    path = make_log(duration_s=4.0)
    monkeypatch.chdir(path.parent)
    log = shocktwin.read_log(path.name)  # relative: the pickle holds the absolute path
    # relative too: pickled after the chdir below, it must still name this directory (a
    # helper's trial: the path was made absolute at pickling, against the new directory)
    bundle = shocktwin.Bundle(os.path.relpath(MLP13, path.parent))
    log2, bundle2 = pickle.loads(pickle.dumps((log, bundle)))
    assert isinstance(log2, shocktwin.Log) and isinstance(bundle2, shocktwin.Bundle)
    assert log2.metadata == log.metadata and bundle2.columns == bundle.columns
    here = shocktwin.estimate(log, bundle)["pressure_bar"]
    monkeypatch.chdir(tmp_path.parent)  # the worker starts in another directory
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=ctx) as pool:
        there = pool.submit(_estimate_in_a_worker, log, bundle).result(timeout=120)
    np.testing.assert_array_equal(there, here)


def test_estimate_names_missing_topics(make_log):
    log = make_log(topics=["/position", "/acceleration"])
    with pytest.raises(shocktwin.MissingTopicsError, match="run-1.*/force") as err:
        shocktwin.estimate(log, MLP13)  # a whole log: known up front, as in features()
    assert err.value.topics == ["/force", "/temperature/shock", "/temperature/ambient"]


def test_predict_releases_the_gil():
    """While ``predict`` runs in a thread, this thread keeps running Python."""
    bundle = shocktwin.Bundle(MLP13)
    rows = np.random.default_rng(0).normal(size=(100_000, 12)) * 100
    assert_releases_gil("predict", lambda: bundle.predict(rows))
