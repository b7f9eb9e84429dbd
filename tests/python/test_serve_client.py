"""`shocktwin serve` driven by a Python client, as a vehicle gateway would.

The daemon (`target/release/shocktwin`, or `SHOCKTWIN_BIN`) runs on loopback
ephemeral ports with the fixture model bundle, a configuration file and a
recording directory. A simulated run (`shocktwin simulate --quick`) is
re-encoded incrementally by Python's `mcap` Writer straight onto the ingest
socket (chunked zstd and unchunked), the daemon's one-line JSON report is
read back, and every tick is accounted for three ways: the report, the HTTP
API (`/v1/assets/{id}?history=N`) and the recorded `/estimate` MCAP file
read with Python's `mcap` reader; all three equal what `shocktwin replay`
(the batch path of the same estimator) computes for the file. SIGTERM ends
the daemon with status 0.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO, Any, Iterator, cast

import httpx
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("SHOCKTWIN_BIN", ROOT / "target" / "release" / "shocktwin"))
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"
TICK_NS = 20_000_000
ANSI = re.compile(r"\x1b\[[0-9;]*m")

sys.path.insert(0, str(ROOT))
from train.demo_serve import SocketStream, copy_log  # noqa: E402  (the demo's socket writer, shared)

sys.path.remove(str(ROOT))


class Daemon:
    def __init__(self, proc: subprocess.Popen[str], listen: str, http: str, record_dir: Path) -> None:
        self.proc = proc
        self.listen = listen
        self.http = http
        self.record_dir = record_dir
        self.log: list[str] = []

    def url(self, path: str) -> str:
        return f"http://{self.http}{path}"


@pytest.fixture(scope="module")
def shocktwin() -> Path:
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: build it with `cargo build --release -p dt-server`")
    return BIN


@pytest.fixture(scope="module")
def sim_run(shocktwin: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim")
    proc = subprocess.run(
        [str(shocktwin), "simulate", "--quick", "--pressures", "4", "--frequencies", "2", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    files = sorted(out.glob("*.mcap"))
    assert len(files) == 1, files
    return files[0]


@pytest.fixture(scope="module")
def replayed(shocktwin: Path, sim_run: Path, tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    """The estimates of the batch path (`shocktwin replay`) for the simulated run."""
    out = tmp_path_factory.mktemp("replay") / "replayed.mcap"
    proc = subprocess.run([str(shocktwin), "replay", "--model", str(BUNDLE), str(sim_run), "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    with open(out, "rb") as fh:
        rows = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=["/estimate"],
                                                                                 log_time_order=True)]
    assert rows, "replay emitted no estimates"
    return rows


@pytest.fixture()
def daemon(shocktwin: Path, tmp_path: Path) -> Iterator[Daemon]:
    config = tmp_path / "shocktwin.toml"
    # The history must hold a whole quick run (about 70 s = 3500 ticks) to read it back.
    config.write_text("[limits]\nhistory_len = 10000\nidle_timeout_s = 30.0\n")
    record_dir = tmp_path / "records"
    proc = subprocess.Popen(
        [str(shocktwin), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
         "--model", str(BUNDLE), "--record-dir", str(record_dir), "--db", str(tmp_path / "fleet.sqlite")],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    assert proc.stderr is not None
    listen = http = None
    head: list[str] = []
    for _ in range(200):  # bounded: the line comes among the first few
        line = ANSI.sub("", proc.stderr.readline())
        if not line and proc.poll() is not None:
            break
        head.append(line)
        m = re.search(r"listening listen=(\S+) http=(\S+)", line)
        if m:
            listen, http = m.group(1), m.group(2)
            break
    if listen is None or http is None:
        proc.kill()
        proc.wait(10)
        pytest.fail("shocktwin serve did not log its addresses:\n" + "".join(head))
    d = Daemon(proc, listen, http, record_dir)
    # Drain the log so that the daemon never blocks on a full pipe.
    drain = threading.Thread(target=lambda: d.log.extend(proc.stderr), daemon=True)  # type: ignore[arg-type]
    drain.start()
    try:
        yield d
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def stream_run(addr: str, path: Path, asset_id: str, run_id: str, *, chunked: bool) -> tuple[dict[str, Any], int]:
    """Re-encodes ``path`` onto a socket with Python's mcap Writer as its own asset and run;
    returns the daemon's report and the messages sent."""
    host, port = addr.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=60) as sock, open(path, "rb") as fh:
        reader = make_reader(fh)
        writer = Writer(cast(IO[bytes], SocketStream(sock)), compression=CompressionType.ZSTD if chunked else CompressionType.NONE,
                        chunk_size=4096, use_chunking=chunked)
        writer.start(profile="", library="shocktwin test client (python mcap)")
        sent = copy_log(reader, writer, {"asset_id": asset_id, "run_id": run_id})
        writer.finish()
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    lines = reply.decode().strip().splitlines()
    assert len(lines) == 1, reply
    return json.loads(lines[0]), sent


def recorded_estimates(record_dir: Path, asset_id: str, run_id: str) -> list[dict[str, Any]]:
    parts = sorted((record_dir / asset_id).glob(f"{run_id}.*.mcap"))
    assert parts, f"no recording of {asset_id}/{run_id} in {record_dir}"
    assert not list((record_dir / asset_id).glob("*.part")), "an unfinished recording is left"
    out: list[dict[str, Any]] = []
    for part in parts:
        with open(part, "rb") as fh:
            reader = make_reader(fh)
            meta = {m.name: m.metadata for m in reader.iter_metadata()}["shocktwin.run"]
            assert (meta["asset_id"], meta["run_id"]) == (asset_id, run_id)
            for _, channel, message in reader.iter_messages(topics=["/estimate"], log_time_order=True):
                est = json.loads(message.data)
                assert message.log_time == est["t_ns"]
                out.append(est)
    return out


def same_value(a: Any, b: Any) -> bool:
    """Equal, with JSON null standing for a value the estimator could not give."""
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, float) or isinstance(b, float):
        return math.isclose(a, b, rel_tol=0, abs_tol=0) or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


@pytest.mark.parametrize("chunked", [True, False], ids=["chunked-zstd", "unchunked"])
def test_python_client_every_tick_accounted_for(daemon: Daemon, sim_run: Path,
                                               replayed: list[dict[str, Any]], chunked: bool) -> None:
    asset_id, run_id = f"py-client-{'c' if chunked else 'u'}", "r1"
    with open(sim_run, "rb") as fh:
        n_messages = sum(1 for _ in make_reader(fh).iter_messages())
    report, sent = stream_run(daemon.listen, sim_run, asset_id, run_id, chunked=chunked)
    assert sent == n_messages

    # The one-line report: every message decoded, every tick emitted and flushed.
    assert report["status"] == "completed", report
    assert report["flushed"] is True and "kind" not in report, report
    assert (report["asset_id"], report["run_id"]) == (asset_id, run_id)
    assert report["samples"] == n_messages
    ticks = report["ticks"]
    assert ticks == len(replayed), "the daemon and the batch path emit the same ticks"
    # The 50 Hz clock: t_origin + k * 20 ms, k = 1..ticks, none missing.
    t0 = replayed[0]["t_ns"] - TICK_NS
    assert [r["t_ns"] for r in replayed] == [t0 + k * TICK_NS for k in range(1, ticks + 1)]

    # The HTTP API: the summary and the whole history (history_len 10000 > ticks).
    with httpx.Client(timeout=30) as client:
        detail = client.get(daemon.url(f"/v1/assets/{asset_id}"), params={"history": 100_000}).json()
        assert detail["ticks"] == ticks
        assert detail["run_id"] == run_id
        assert detail["active_runs"] == 0 and detail["last_run_status"] == "completed"
        history = detail["history"]
        assert len(history) == ticks
        assert [e["t_ns"] for e in history] == [r["t_ns"] for r in replayed]
        assert detail["last_t_ns"] == history[-1]["t_ns"]
        last5 = client.get(daemon.url(f"/v1/assets/{asset_id}"), params={"history": 5}).json()["history"]
        assert last5 == history[-5:]
        assert client.get(daemon.url("/v1/assets/no-such-asset")).status_code == 404
        metrics = client.get(daemon.url("/metrics")).text
    assert f'shocktwin_ticks_total{{asset="{asset_id}"}} {ticks}' in metrics
    assert f'shocktwin_estimate_delay_seconds_count{{asset="{asset_id}"}} {ticks}' in metrics

    # The recording, read with Python's mcap reader.
    recorded = recorded_estimates(daemon.record_dir, asset_id, run_id)
    assert len(recorded) == ticks
    for rec, api, ref in zip(recorded, history, replayed):
        for key in ("t_ns", "pressure_bar", "pressure_avg_bar", "expected_bar", "health"):
            assert same_value(rec[key], ref[key]), (key, rec, ref)
            assert same_value(api[key], ref[key]), (key, api, ref)

    # SIGTERM: drain, flush, exit 0.
    daemon.proc.send_signal(signal.SIGTERM)
    assert daemon.proc.wait(30) == 0, "".join(daemon.log[-20:])


def test_bad_stream_gets_a_failed_report(daemon: Daemon) -> None:
    host, port = daemon.listen.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(b"this is not an MCAP stream at all" * 4)
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    report = json.loads(reply.decode())
    assert report["status"] == "failed"
    assert report["ticks"] == 0 and report["asset_id"] is None
    assert report["kind"] and report["reason"]
    daemon.proc.send_signal(signal.SIGTERM)
    assert daemon.proc.wait(30) == 0


def test_sigterm_right_after_start_is_a_clean_stop(shocktwin: Path, tmp_path: Path) -> None:
    # The handlers are installed before the daemon says it listens: a SIGTERM
    # sent the moment it does must not kill it by the default action.
    for _ in range(5):
        proc = subprocess.Popen([str(shocktwin), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
                                 "--db", str(tmp_path / "fleet.sqlite")],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        assert proc.stderr is not None
        for line in proc.stderr:
            if "listening" in line:
                proc.send_signal(signal.SIGTERM)
                break
        assert proc.wait(30) == 0


def test_a_run_sent_again_keeps_its_recording(daemon: Daemon, sim_run: Path) -> None:
    """A vehicle's retries (a helper trying the daemon as a gateway operator): a second copy of a
    run streamed while the first was still being recorded wrote the same `.part` file (a corrupt
    recording, and a `sink` error in the report); a cut copy after a complete one replaced the
    run's whole recording by its first 20 s. Now the copy is recorded apart
    (`<run_id>~<seq>.<part>.mcap`) and the run's own recording stays whole."""
    import io

    asset_id, run_id = "van-retry", "r1"
    rec_dir = daemon.record_dir / asset_id

    # the first copy, all but its last chunk sent; the second, whole, meanwhile
    host, port = daemon.listen.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=60) as sock, open(sim_run, "rb") as fh:
        writer = Writer(cast(IO[bytes], SocketStream(sock)), compression=CompressionType.ZSTD, chunk_size=4096)
        writer.start(profile="", library="shocktwin test client (python mcap)")
        copy_log(make_reader(fh), writer, {"asset_id": asset_id, "run_id": run_id})
        second, _ = stream_run(daemon.listen, sim_run, asset_id, run_id, chunked=True)
        writer.finish()
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    first = json.loads(reply.decode())
    for report in (first, second):
        assert report["status"] == "completed" and report["flushed"] is True and "kind" not in report, report
    ticks = first["ticks"]
    assert len(recorded_estimates(daemon.record_dir, asset_id, run_id)) == ticks  # the first copy's, whole
    (aside,) = rec_dir.glob(f"{run_id}~*.0000.mcap")
    with open(aside, "rb") as fh:
        assert sum(1 for _ in make_reader(fh).iter_messages(topics=["/estimate"])) == ticks

    # a copy cut half way (the vehicle powered off): failed, recorded apart
    buf = io.BytesIO()
    with open(sim_run, "rb") as fh:
        writer = Writer(cast(IO[bytes], buf), compression=CompressionType.ZSTD, chunk_size=4096)
        writer.start(profile="", library="shocktwin test client (python mcap)")
        copy_log(make_reader(fh), writer, {"asset_id": asset_id, "run_id": run_id})
        writer.finish()
    with socket.create_connection((host, int(port)), timeout=60) as sock:
        sock.sendall(buf.getvalue()[: len(buf.getvalue()) // 2])
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    cut = json.loads(reply.decode())
    assert cut["status"] == "failed" and 0 < cut["ticks"] < ticks, cut
    assert len(recorded_estimates(daemon.record_dir, asset_id, run_id)) == ticks
    copies = sorted(rec_dir.glob(f"{run_id}~*.0000.mcap"))
    assert len(copies) == 2, copies
    counts = []
    for path in copies:
        with open(path, "rb") as fh:
            counts.append(sum(1 for _ in make_reader(fh).iter_messages(topics=["/estimate"])))
    assert sorted(counts) == sorted([ticks, cut["ticks"]]), (counts, ticks, cut)
    assert any("recorded apart" in line for line in daemon.log), "".join(daemon.log[-20:])


def test_sighup_is_said_and_survived(daemon: Daemon, sim_run: Path) -> None:
    """SIGHUP (what operators send after rotating certificates) ended the daemon at once, with
    no log line, no drain and no report to its clients (a helper's trial). It is said, and the
    daemon goes on serving; SIGTERM still stops it cleanly."""
    import time

    daemon.proc.send_signal(signal.SIGHUP)
    for _ in range(100):
        if any("SIGHUP received" in line for line in daemon.log):
            break
        time.sleep(0.1)
    assert any("SIGHUP received" in line and "restart it" in line for line in daemon.log), "".join(daemon.log[-20:])
    assert daemon.proc.poll() is None
    report, _ = stream_run(daemon.listen, sim_run, "after-hup", "r1", chunked=True)
    assert report["status"] == "completed", report
    daemon.proc.send_signal(signal.SIGTERM)
    assert daemon.proc.wait(30) == 0, "".join(daemon.log[-20:])


def test_a_missing_inbox_is_said_when_created(shocktwin: Path, tmp_path: Path) -> None:
    """A mistyped inbox path was created without a word (a helper's trial: the warning the inbox
    had was never reached, the lock file having made the directory first), and files dropped
    into the real inbox were never taken."""
    from conftest import ServeProcess

    d = ServeProcess([str(shocktwin), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
                      "--model", str(BUNDLE), "--no-db", "--inbox", str(tmp_path / "nope-inbox")])
    try:
        assert any("the inbox's directory did not exist: created it" in line and "nope-inbox" in line
                   for line in d.log), d.text()
    finally:
        assert d.stop() == 0, d.text()


def test_a_service_for_an_asset_never_seen_is_noted(shocktwin: Path, sim_run: Path, tmp_path: Path) -> None:
    """A service reported for a mistyped asset id was answered `202` like any other (a helper's
    trial): it would wait for a run that never comes. The answer (and the log) now says the
    asset has not been seen; one the daemon knows gets no such note."""
    from conftest import ServeProcess

    d = ServeProcess([str(shocktwin), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
                      "--model", str(ROOT / "docs" / "study" / "bundles" / "perm-18"),
                      "--db", str(tmp_path / "fleet.sqlite")])
    try:
        with httpx.Client(timeout=30) as client:
            r = client.put(f"http://{d.http}/v1/assets/van-O7/service", json={"charge_bar": 12})
            assert r.status_code == 202, r.text
            assert "has not been seen by this daemon" in r.json()["note"], r.json()
            report, _ = stream_run(d.listen, sim_run, "van-07", "r1", chunked=True)
            assert report["status"] == "completed", report
            r = client.put(f"http://{d.http}/v1/assets/van-07/service", json={"charge_bar": 12})
            assert r.status_code == 202 and "note" not in r.json(), r.json()
    finally:
        assert d.stop() == 0, d.text()
