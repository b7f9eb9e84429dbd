"""The Foxglove layout (``docs/foxglove/shocktwin-layout.json``) against what the
real writer produces (issue 12, item 4).

A short run is simulated with ``shocktwin simulate --quick --pressures 7
--frequencies 2`` and replayed with the fixture bundle ``bundle-mlp13`` into an
``.mcap`` (inputs + ``/estimate``); that file is read with the Python ``mcap``
package, independently of our Rust reader. Every message path of the layout must
name a topic of that file and a field its channel's JSON schema declares with the
type the panel needs (numeric for a Plot, string for State Transitions), present in
every message with such a value (``null`` only where SPEC §2/§2a allow a missing
value). Renaming a topic or a field on either side fails here.

The binary is ``target/release/shocktwin`` (built when missing) or ``SHOCKTWIN_BIN``.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterator

import pytest

ROOT = Path(__file__).resolve().parents[2]
LAYOUT = ROOT / "docs" / "foxglove" / "shocktwin-layout.json"
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"

# Fields whose value may be null in every message: a bundle without the charge
# observer has no interval (SPEC §2a).
MAY_BE_ALL_NULL = {("/estimate", "pressure_lo_bar"), ("/estimate", "pressure_hi_bar")}
# Other numeric fields may be null now and then (a missing sample; the 1 s average
# while the twin is not excited: the quick run ends with 10 s at rest) but must be
# numbers in most messages.
MIN_NUMERIC_FRACTION = 0.5
# What a panel plots, by panel type (the part of the panel id before "!").
PANEL_VALUE_TYPE = {"Plot": "number", "StateTransitions": "string"}
# Foxglove's message-path syntax: `/topic.field`; a bare number is a reference line.
FIELD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
TOPIC = re.compile(r"/[A-Za-z0-9_/-]+")


def layout_paths(layout: dict[str, Any]) -> Iterator[tuple[str, str, str, str]]:
    """(panel id, panel type, topic, field) for every message path of the layout;
    numeric reference lines (e.g. "9") are skipped, as Foxglove draws them as lines."""
    for panel_id, config in layout["configById"].items():
        panel_type = panel_id.split("!", 1)[0]
        for path in config.get("paths", []):
            value = path["value"]
            try:
                float(value)
                continue
            except ValueError:
                pass
            topic, _, field = value.partition(".")
            assert TOPIC.fullmatch(topic), f"{panel_id}: {value!r} does not start with a plain topic"
            assert FIELD.fullmatch(field), f"{panel_id}: {value!r} is not `/topic.field`"
            yield panel_id, panel_type, topic, field


def mosaic_leaves(node: Any) -> Iterator[str]:
    if isinstance(node, str):
        yield node
    else:
        assert node["direction"] in ("row", "column"), node
        yield from mosaic_leaves(node["first"])
        yield from mosaic_leaves(node["second"])


def read_mcap(path: Path) -> dict[str, dict[str, Any]]:
    """topic -> {message_encoding, schema_name, schema_encoding, schema, log_times, messages}."""
    from mcap.reader import make_reader

    out: dict[str, dict[str, Any]] = {}
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=False):
            entry = out.get(channel.topic)
            if entry is None:
                entry = out[channel.topic] = {
                    "message_encoding": channel.message_encoding,
                    "schema_name": schema.name if schema else None,
                    "schema_encoding": schema.encoding if schema else None,
                    "schema": json.loads(schema.data) if schema and schema.data else None,
                    "log_times": [],
                    "messages": [],
                }
            entry["log_times"].append(message.log_time)
            entry["messages"].append(json.loads(message.data))
    return out


def declared_types(schema: dict[str, Any], field: str) -> set[str]:
    kind = schema["properties"][field].get("type")
    return set(kind) if isinstance(kind, list) else {kind}


@pytest.fixture(scope="module")
def logs(shocktwin_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The simulated run log and its replay (.mcap: inputs + /estimate)."""
    tmp = tmp_path_factory.mktemp("foxglove")
    run = subprocess.run(
        [str(shocktwin_bin), "simulate", "--quick", "--pressures", "7", "--frequencies", "2",
         "--out", str(tmp / "campaign")],
        capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 0, run.stderr
    (log,) = sorted((tmp / "campaign").glob("*.mcap"))
    replay = subprocess.run(
        [str(shocktwin_bin), "replay", "--model", str(BUNDLE), str(log), "--out", str(tmp / "replay.mcap")],
        capture_output=True, text=True, timeout=120,
    )
    assert replay.returncode == 0, replay.stderr
    return {"run": log, "replay": tmp / "replay.mcap"}


@pytest.fixture(scope="module")
def replay(logs: dict[str, Path]) -> dict[str, dict[str, Any]]:
    return read_mcap(logs["replay"])


@pytest.fixture(scope="module")
def layout() -> dict[str, Any]:
    return json.loads(LAYOUT.read_text(encoding="utf-8"))


def test_layout_is_a_foxglove_layout(layout: dict[str, Any]):
    assert {"configById", "layout", "globalVariables", "userNodes"} <= layout.keys()
    panels = set(layout["configById"])
    leaves = list(mosaic_leaves(layout["layout"]))
    assert sorted(leaves) == sorted(panels), "every panel is placed once, and only configured panels"
    for panel_id, config in layout["configById"].items():
        panel_type = panel_id.split("!", 1)[0]
        assert panel_type in PANEL_VALUE_TYPE, f"{panel_id}: a panel type this test does not check"
        assert config["paths"], f"{panel_id} plots nothing"
        for path in config["paths"]:
            # our logs have no header stamps: Foxglove must use the MCAP log_time
            assert path["timestampMethod"] == "receiveTime", (panel_id, path)
        if panel_type == "Plot":
            assert config["xAxisVal"] == "timestamp" and all(p["enabled"] for p in config["paths"])


def test_the_layout_plots_what_the_issue_asks(layout: dict[str, Any]):
    got = {(topic, field) for _, _, topic, field in layout_paths(layout)}
    assert got >= {
        ("/estimate", "pressure_bar"), ("/estimate", "pressure_lo_bar"), ("/estimate", "pressure_hi_bar"),
        ("/truth/gas_pressure", "static_bar"), ("/position", "position_m"),
        ("/force", "force_n"), ("/estimate", "force_model_n"),
        ("/temperature/shock", "temperature_c"), ("/temperature/ambient", "temperature_c"),
        ("/estimate", "oil_temp_c"),
    }


def test_every_layout_path_is_in_the_real_files(layout: dict[str, Any], replay: dict[str, dict[str, Any]]):
    checked = 0
    for panel_id, panel_type, topic, field in layout_paths(layout):
        where = f"{panel_id}: {topic}.{field}"
        assert topic in replay, f"{where}: no topic {topic} in the replay (has {sorted(replay)})"
        channel = replay[topic]
        assert channel["message_encoding"] == "json", where
        assert channel["schema_encoding"] == "jsonschema", where
        schema = channel["schema"]
        assert schema is not None and schema.get("type") == "object", where
        assert field in schema.get("properties", {}), f"{where}: the channel's schema does not declare it"
        want = PANEL_VALUE_TYPE[panel_type]
        assert want in declared_types(schema, field) or (
            want == "number" and "integer" in declared_types(schema, field)
        ), f"{where}: declared {declared_types(schema, field)}, the panel needs {want}"

        values = [m.get(field, "<missing>") for m in channel["messages"]]
        assert values, f"{where}: no messages"
        missing = sum(v == "<missing>" for v in values)
        assert missing == 0, f"{where}: absent from {missing} of {len(values)} messages"
        if want == "string":
            assert all(isinstance(v, str) for v in values), where
        else:
            bad = [v for v in values if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)))]
            assert not bad, f"{where}: non-numeric values {bad[:3]}"
            numeric = sum(v is not None and math.isfinite(v) for v in values)
            if (topic, field) not in MAY_BE_ALL_NULL:
                assert numeric >= MIN_NUMERIC_FRACTION * len(values), (
                    f"{where}: only {numeric} of {len(values)} messages hold a number"
                )
        checked += 1
    assert checked >= 10


def test_the_raw_run_log_has_the_layouts_input_topics(layout: dict[str, Any], logs: dict[str, Path]):
    """A run log without /estimate (what `simulate` writes) still fills the input panels."""
    run = read_mcap(logs["run"])
    for panel_id, _, topic, field in layout_paths(layout):
        if topic != "/estimate":
            assert topic in run and field in run[topic]["schema"]["properties"], f"{panel_id}: {topic}.{field}"


def test_log_time_is_the_sample_time(replay: dict[str, dict[str, Any]]):
    """Foxglove plots against log_time: monotonic within a topic and, for /estimate,
    the tick time the message carries."""
    for topic, channel in replay.items():
        times = channel["log_times"]
        assert all(a <= b for a, b in zip(times, times[1:])), f"{topic}: log_time goes back"
    estimate = replay["/estimate"]
    assert [m["t_ns"] for m in estimate["messages"]] == estimate["log_times"]


def foxglove_schema_problems(schema: dict[str, Any], where: str) -> list[str]:
    """The checks of Foxglove's JSON-schema parser (``parseJsonSchema`` in
    foxglove/studio ``packages/mcap-support``, also in Lichtblick): the root is
    ``"type": "object"`` and each property's ``type`` one string of boolean, string,
    number, integer, object, array. Anything else (e.g. ``["number", "null"]``) makes
    Foxglove reject the whole channel ("Error in topic …")."""
    if schema.get("type") != "object":
        return [f"{where}: root type {schema.get('type')!r}"]
    problems = []
    for name, prop in schema.get("properties", {}).items():
        kind = prop.get("type")
        if kind == "object":
            problems += foxglove_schema_problems(prop, f"{where}.{name}")
        elif kind not in ("boolean", "string", "number", "integer", "array"):
            problems.append(f"{where}.{name}: type {kind!r}")
    return problems


def test_foxglove_can_parse_every_channel_schema(replay: dict[str, dict[str, Any]]):
    problems: dict[str, list[str]] = defaultdict(list)
    for topic, channel in replay.items():
        problems[topic] += foxglove_schema_problems(channel["schema"], topic)
    assert not any(problems.values()), {t: p for t, p in problems.items() if p}
