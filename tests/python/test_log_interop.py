"""Run-log interoperability (SPEC §2) between Python's `mcap` package and the
Rust log module, through the `shocktwin` binary:

(a) logs written by Python's `mcap` Writer (zstd, lz4, none; chunked and
    unchunked; Python's `NaN` tokens) are read by `shocktwin inspect`;
(b) logs written by our writer (`shocktwin simulate`) are read by Python's
    `mcap` reader, strictly: JSON messages, JSON schemas, metadata first.

The binary is `target/release/shocktwin` (`cargo build --release -p dt-server`),
or the path in `SHOCKTWIN_BIN`.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Message, Metadata
from mcap.writer import CompressionType, Writer

from conftest import SENSOR_FIELDS, synthetic_run

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("SHOCKTWIN_BIN", ROOT / "target" / "release" / "shocktwin"))


@pytest.fixture(scope="module")
def shocktwin() -> Path:
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: build it with `cargo build --release -p dt-server`")
    return BIN


def run(binary: Path, *args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(binary), *map(str, args)], capture_output=True, text=True, timeout=300)


def inspect_json(binary: Path, path: Path) -> dict[str, Any]:
    proc = run(binary, "inspect", "--json", path)
    assert proc.returncode == 0, proc.stderr
    report: dict[str, Any] = json.loads(proc.stdout)
    return report


def counts(report: dict[str, Any]) -> dict[str, int]:
    out: dict[str, int] = {}
    for c in report["channels"]:
        out[c["topic"]] = out.get(c["topic"], 0) + c["message_count"]
    return out


def write_python_log(
    path: Path,
    metadata: dict[str, str],
    topics: dict[str, Any],
    *,
    compression: CompressionType,
    chunked: bool,
    nan_every: int = 0,
) -> dict[str, int]:
    """Writes a shocktwin log with Python's `mcap` Writer; returns message counts by topic.

    Every `nan_every`-th message carries a non-finite value, written by
    `json.dumps` as the (non-standard) tokens `NaN` / `Infinity`.
    """
    written: dict[str, int] = {}
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=compression, use_chunking=chunked, chunk_size=4096)
        writer.start(profile="", library="test_log_interop")
        writer.add_metadata("shocktwin.run", metadata)
        events: list[tuple[int, int, bytes]] = []
        for topic, (t_ns, fields) in topics.items():
            schema = {
                "type": "object",
                "properties": {f: {"type": "number"} for f in fields},
                "required": list(fields),
            }
            sid = writer.register_schema(name=topic, encoding="jsonschema", data=json.dumps(schema).encode())
            cid = writer.register_channel(topic, "json", sid)
            for i, t in enumerate(t_ns):
                msg = {f: float(v[i]) for f, v in fields.items()}
                if nan_every and i % nan_every == 3:
                    first = next(iter(msg))
                    msg[first] = math.nan if i % 2 else math.inf
                events.append((int(t), cid, json.dumps(msg).encode()))
            written[topic] = len(t_ns)
        events.sort(key=lambda e: (e[0], e[1]))
        for t, cid, data in events:
            writer.add_message(cid, log_time=t, data=data, publish_time=t)
        writer.finish()
    return written


LAYOUTS = [
    pytest.param(CompressionType.ZSTD, True, id="zstd-chunked"),
    pytest.param(CompressionType.LZ4, True, id="lz4-chunked"),
    pytest.param(CompressionType.NONE, True, id="none-chunked"),
    pytest.param(CompressionType.NONE, False, id="unchunked"),
]


@pytest.mark.parametrize(("compression", "chunked"), LAYOUTS)
def test_python_written_log_inspects_with_right_counts_and_metadata(
    shocktwin: Path, tmp_path: Path, compression: CompressionType, chunked: bool
) -> None:
    metadata = {"asset_id": "py-unit-7", "run_id": "run.0042", "charge_pressure_bar": "9.5", "excitation": "sine 2 Hz"}
    topics = synthetic_run(duration_s=3.0, topics=tuple(SENSOR_FIELDS))
    path = tmp_path / "py.mcap"
    written = write_python_log(path, metadata, topics, compression=compression, chunked=chunked, nan_every=50)

    report = inspect_json(shocktwin, path)
    assert counts(report) == written
    assert report["message_count"] == sum(written.values())
    assert report["run"]["asset_id"] == "py-unit-7"
    assert report["run"]["run_id"] == "run.0042"
    assert report["run"]["charge_pressure_bar"] == 9.5
    assert dict(report["metadata"])["shocktwin.run"] == metadata
    # NaN / Infinity tokens are missing samples, not problems
    assert report["problems"] == []
    expected_chunks = {"zstd": "zstd", "lz4": "lz4"}.get(compression.name.lower(), "none")
    assert list(report["chunks"]) == ([expected_chunks] if chunked else [])
    rates = {c["topic"]: c["rate_hz"] for c in report["channels"]}
    assert rates["/acceleration"] == pytest.approx(1000, rel=1e-6)
    assert rates["/position"] == pytest.approx(100, rel=1e-6)
    assert report["duration_s"] == pytest.approx(2.999, abs=1e-6)
    for c in report["channels"]:
        assert (c["message_encoding"], c["schema_encoding"]) == ("json", "jsonschema")

    # the text report says the same
    text = run(shocktwin, "inspect", path)
    assert text.returncode == 0, text.stderr
    assert "asset_id = py-unit-7" in text.stdout
    assert "/acceleration" in text.stdout and "3000 msgs" in text.stdout
    assert "problems:  none" in text.stdout


def test_inspect_lists_what_a_log_lacks_but_exits_0(shocktwin: Path, tmp_path: Path) -> None:
    path = tmp_path / "partial.mcap"
    # no shocktwin.run metadata, no /force, an unknown topic, a bad message
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        pos = writer.register_channel("/position", "json", 0)
        other = writer.register_channel("/camera/info", "json", 0)
        writer.add_message(pos, log_time=10, publish_time=10, data=b'{"position_m": 0.01}')
        writer.add_message(pos, log_time=20, publish_time=20, data=b'{"position": 0.02}')
        writer.add_message(other, log_time=20, publish_time=20, data=b"{}")
        writer.finish()
    report = inspect_json(shocktwin, path)
    problems = "\n".join(report["problems"])
    assert "shocktwin.run" in problems
    assert "/force" in problems
    assert "ignored topic /camera/info (1 messages)" in problems
    assert "/position" in problems and "`position_m`" in problems


def test_inspect_rejects_a_non_mcap_file_naming_it(shocktwin: Path, tmp_path: Path) -> None:
    path = tmp_path / "notes.mcap"
    path.write_text("these are notes, not an MCAP file\n")
    proc = run(shocktwin, "inspect", path)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"shocktwin: {path}: "), lines[0]

    truncated = tmp_path / "truncated.mcap"
    good = tmp_path / "good.mcap"
    write_python_log(good, {"asset_id": "a", "run_id": "b"}, synthetic_run(duration_s=1.0),
                     compression=CompressionType.ZSTD, chunked=True)
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    proc = run(shocktwin, "inspect", truncated)
    assert proc.returncode == 1
    assert proc.stderr.startswith(f"shocktwin: {truncated}: ")


@pytest.fixture(scope="module")
def simulated(shocktwin: Path, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    out = tmp_path_factory.mktemp("campaign")
    proc = run(shocktwin, "simulate", "--quick", "--pressures", "12", "--frequencies", "4", "--out", out)
    assert proc.returncode == 0, proc.stderr
    files = sorted(out.glob("*.mcap"))
    assert files, f"simulate wrote no .mcap into {out}"
    return files


def test_our_logs_read_strictly_with_python_mcap(shocktwin: Path, simulated: list[Path]) -> None:
    for path in simulated:
        # record order, streamed: shocktwin.run metadata before the first message
        order = []
        with open(path, "rb") as f:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Metadata):
                    order.append(("metadata", record.name))
                elif isinstance(record, Message):
                    order.append(("message", ""))
        assert order[0] == ("metadata", "shocktwin.run"), order[:3]

        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None and summary.statistics is not None
            metadata = {m.name: m.metadata for m in reader.iter_metadata()}
            run_meta = metadata["shocktwin.run"]
            assert run_meta["charge_pressure_bar"] == "12"
            assert float(run_meta["frequency_hz"]) == 4.0

            seen: dict[str, int] = {}
            last_t: dict[str, int] = {}
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                assert channel.message_encoding == "json"
                assert schema is not None and schema.encoding == "jsonschema"
                js = json.loads(schema.data)
                # strict JSON: no NaN tokens (a missing value is null)
                value = json.loads(message.data, parse_constant=lambda c: pytest.fail(f"token {c}"))
                assert set(value) == set(js["required"]) == set(SENSOR_FIELDS[channel.topic])
                assert set(js["properties"]) == set(SENSOR_FIELDS[channel.topic])
                assert all(v is None or isinstance(v, float | int) for v in value.values())
                assert message.log_time == message.publish_time
                assert message.log_time >= last_t.get(channel.topic, 0), channel.topic
                last_t[channel.topic] = message.log_time
                seen[channel.topic] = seen.get(channel.topic, 0) + 1
            assert sum(seen.values()) == summary.statistics.message_count

        report = inspect_json(shocktwin, path)
        assert counts(report) == seen
        assert report["problems"] == []
        for topic in SENSOR_FIELDS:
            if not topic.startswith("/truth/"):
                assert seen.get(topic, 0) > 0, f"{path.name}: no {topic}"


def test_our_chunks_are_zstd_with_valid_crcs(simulated: list[Path]) -> None:
    from mcap.records import Chunk

    for path in simulated:
        with open(path, "rb") as f:
            chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
        assert chunks and {c.compression for c in chunks} == {"zstd"}
        # Python checks every chunk CRC while decompressing
        with open(path, "rb") as f:
            n = sum(1 for r in StreamReader(f, validate_crcs=True).records if isinstance(r, Message))
        assert n > 0


def test_channels_are_one_per_topic(simulated: list[Path]) -> None:
    for path in simulated:
        with open(path, "rb") as f:
            topics = [r.topic for r in StreamReader(f).records if isinstance(r, Channel)]
        # the summary section repeats channels: count distinct ids per topic
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None
        by_topic = [c.topic for c in summary.channels.values()]
        assert len(by_topic) == len(set(by_topic)), by_topic
        assert set(topics) == set(by_topic)
