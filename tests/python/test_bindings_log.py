"""shocktwin.read_log / Log: metadata, topics as numpy columns, t_s, problems, errors.

Logs are written here with the Python ``mcap`` package (conftest), not the
Rust writer, so the reader is checked against an independent producer.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import synthetic_run, write_mcap_log

import shocktwin

META = {
    "asset_id": "unit-7",
    "run_id": "r-2hz_12bar",
    "charge_pressure_bar": "11.5",
    "frequency_hz": "2",
    "stroke_pp_m": "0.08",
    "excitation": "sine 2 Hz 80 mm p-p",
    "operator": "dyno bay 3",
}


@pytest.fixture
def run_topics():
    topics = synthetic_run(duration_s=3.0)
    # The ambient thermocouple starts 0.5 s before everything else: t_s = 0 is its first sample.
    t, fields = topics["/temperature/ambient"]
    topics["/temperature/ambient"] = (np.concatenate([[t[0] - 500_000_000], t]), {
        "temperature_c": np.concatenate([[21.0], fields["temperature_c"]])
    })
    return topics


@pytest.mark.parametrize("chunked", [True, False])
def test_columns_round_trip(tmp_path: Path, run_topics, chunked):
    path = write_mcap_log(tmp_path / "run.mcap", META, run_topics, chunked=chunked)
    log = shocktwin.read_log(path)  # a pathlib.Path is accepted
    t0 = min(int(t[0]) for t, _ in run_topics.values())
    assert log.t0_ns == t0
    assert log.topics == ["/position", "/acceleration", "/force", "/temperature/shock", "/temperature/ambient"]
    for topic, (t_ns, fields) in run_topics.items():
        got = log.topic(topic)
        assert set(got) == {"t_s", *fields}
        np.testing.assert_array_equal(got["t_s"], (t_ns - t0) / 1e9)
        for name, values in fields.items():
            assert got[name].dtype == np.float64 and got[name].flags.c_contiguous
            np.testing.assert_array_equal(got[name], np.asarray(values, dtype=float))
    assert log.topic("/temperature/ambient")["t_s"][0] == 0.0
    assert log.topic("/position")["t_s"][0] == pytest.approx(0.5)
    assert log.problems == []


def test_truth_topics_are_listed_and_returned(tmp_path: Path):
    topics = synthetic_run(duration_s=1.0, topics=["/position", "/truth/gas_pressure", "/truth/velocity"])
    log = shocktwin.read_log(write_mcap_log(tmp_path / "run.mcap", META, topics))
    assert log.topics == ["/position", "/truth/gas_pressure", "/truth/velocity"]
    got = log.topic("/truth/velocity")
    assert set(got) == {"t_s", "velocity_mps"}
    t_ns, fields = topics["/truth/velocity"]
    assert got["velocity_mps"].size == 100
    np.testing.assert_array_equal(got["t_s"], (t_ns - t_ns[0]) / 1e9)
    np.testing.assert_array_equal(got["velocity_mps"], fields["velocity_mps"])
    # same instants as /position, and a velocity (2 Hz, 40 mm amplitude), not the pressure
    np.testing.assert_array_equal(got["t_s"], log.topic("/position")["t_s"])
    assert np.max(np.abs(got["velocity_mps"])) == pytest.approx(0.04 * 2 * np.pi * 2, rel=1e-9)
    assert set(log.topic("/truth/gas_pressure")) == {"t_s", "static_bar"}


def test_metadata_types_and_label(tmp_path: Path, run_topics):
    log = shocktwin.read_log(str(write_mcap_log(tmp_path / "run.mcap", META, run_topics)))
    md = log.metadata
    assert md["asset_id"] == "unit-7" and md["run_id"] == "r-2hz_12bar"
    assert md["charge_pressure_bar"] == 11.5 and isinstance(md["charge_pressure_bar"], float)
    assert md["frequency_hz"] == 2.0 and md["stroke_pp_m"] == 0.08
    assert md["excitation"] == "sine 2 Hz 80 mm p-p"
    assert md["operator"] == "dyno bay 3"  # unknown keys kept verbatim as str
    assert log.label == 11.5
    assert "unit-7" in repr(log)


def test_unlabelled_run(tmp_path: Path, run_topics):
    log = shocktwin.read_log(write_mcap_log(tmp_path / "run.mcap", {"asset_id": "a", "run_id": "b"}, run_topics))
    assert log.label is None
    assert "charge_pressure_bar" not in log.metadata


def test_absent_topic_is_a_key_error_naming_what_exists(tmp_path: Path):
    topics = synthetic_run(duration_s=1.0, topics=["/position", "/acceleration"])
    log = shocktwin.read_log(write_mcap_log(tmp_path / "run.mcap", META, topics))
    assert log.topics == ["/position", "/acceleration"]
    with pytest.raises(KeyError, match="/force.*/position"):
        log.topic("/force")


def test_unknown_topic_is_counted_and_reported(tmp_path: Path):
    topics = synthetic_run(duration_s=1.0, topics=["/position"])
    path = write_mcap_log(tmp_path / "run.mcap", META, {
        **topics, "/dyno/setpoint": (np.arange(5) + topics["/position"][0][0], {"x": np.zeros(5)})
    })
    log = shocktwin.read_log(path)
    assert log.unknown_topics == {"/dyno/setpoint": 5}
    assert any("/dyno/setpoint" in p for p in log.problems)
    assert log.topics == ["/position"]


def test_bad_message_is_skipped_and_named(tmp_path: Path):
    from mcap.writer import Writer

    path = tmp_path / "bad.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("shocktwin.run", {"asset_id": "a", "run_id": "b"})
        schema = {"type": "object", "properties": {"position_m": {"type": "number"}}}
        sid = w.register_schema("pos", "jsonschema", json.dumps(schema).encode())
        cid = w.register_channel("/position", "json", sid)
        for i, msg in enumerate([{"position_m": 0.01}, {"position": 0.02}, {"position_m": "x"}, {"position_m": 0.03}]):
            w.add_message(cid, log_time=10_000_000 * (i + 1), data=json.dumps(msg).encode(), publish_time=0)
        w.finish()
    log = shocktwin.read_log(path)
    np.testing.assert_array_equal(log.topic("/position")["position_m"], [0.01, 0.03])
    assert any("/position" in p and "position_m" in p for p in log.problems), log.problems


def test_not_mcap_is_a_log_error_naming_the_file(tmp_path: Path):
    path = tmp_path / "notes.mcap"
    path.write_text("this is not an MCAP file\n")
    with pytest.raises(shocktwin.LogError, match="notes.mcap") as info:
        shocktwin.read_log(path)
    assert isinstance(info.value, ValueError) and isinstance(info.value, shocktwin.ShocktwinError)


def test_missing_metadata_is_a_log_error(tmp_path: Path):
    from mcap.writer import Writer

    path = tmp_path / "nometa.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    with pytest.raises(shocktwin.LogError, match="shocktwin.run"):
        shocktwin.read_log(path)


def test_invalid_run_id_names_the_key(tmp_path: Path, run_topics):
    path = write_mcap_log(tmp_path / "run.mcap", {"asset_id": "a", "run_id": "no spaces please"}, run_topics)
    with pytest.raises(shocktwin.LogError, match="run_id"):
        shocktwin.read_log(path)


def test_missing_file_is_an_os_error(tmp_path: Path):
    with pytest.raises(OSError, match="absent.mcap") as info:
        shocktwin.read_log(tmp_path / "absent.mcap")
    assert isinstance(info.value, shocktwin.LogReadError)


def test_log_is_immutable(tmp_path: Path, run_topics):
    log = shocktwin.read_log(write_mcap_log(tmp_path / "run.mcap", META, run_topics))
    with pytest.raises(AttributeError):
        log.label = 3.0  # type: ignore[misc]
    log.metadata["run_id"] = "changed"  # a fresh dict each time
    assert log.metadata["run_id"] == "r-2hz_12bar"
