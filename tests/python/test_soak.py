"""A bounded soak of ``shocktwin serve`` over loopback: runs streamed back to back by
several vehicles at once while SSE clients subscribe to ``/v1/events`` and never read.
The daemon's resident memory must level off (bounded queues: a slow reader skips events
and is told ``lagged``, it does not make the daemon buffer them), and every run must
complete. Memory is compared between the second and last quarters of the soak, not
timed: a leak of the event stream alone would add tens of MB here."""

from __future__ import annotations

import json
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from conftest import ServeProcess

ROOT = Path(__file__).resolve().parents[2]
BIN = ROOT / "target" / "release" / "shocktwin"
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"
ROUNDS = 10
VEHICLES = 4



def send_file(addr: str, path: Path) -> dict:
    """The run's bytes as they are (written by the simulator) onto a connection; the report."""
    host, port = addr.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=60) as sock:
        sock.sendall(path.read_bytes())
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    return json.loads(reply)


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads RSS from /proc")
def test_memory_levels_off_with_stalled_event_readers(tmp_path: Path) -> None:
    sim = tmp_path / "sim"
    done = subprocess.run([str(BIN), "simulate", "--quick", "--pressures", "7", "--frequencies", "4", "--out", str(sim)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    original = next(sim.glob("*.mcap"))
    config = tmp_path / "shocktwin.toml"
    config.write_text("[limits]\nqueue_depth = 256\n")
    d = ServeProcess([str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
                      "--model", str(BUNDLE), "--db", str(tmp_path / "fleet.sqlite")])
    stalled: list[socket.socket] = []
    try:
        host, port = d.http.rsplit(":", 1)
        for _ in range(3):  # subscribe, then never read
            s = socket.create_connection((host, int(port)), timeout=10)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(f"GET /v1/events HTTP/1.1\r\nHost: {d.http}\r\nAccept: text/event-stream\r\n\r\n".encode())
            stalled.append(s)
        samples: list[int] = []
        reports: list[dict] = []
        errors: list[BaseException] = []

        def vehicle(k: int) -> None:
            try:
                for _ in range(ROUNDS):
                    # One asset, one run id: each round is the same run again (a re-sent log).
                    reports.append(send_file(d.listen, original))
                    samples.append(rss_kb(d.proc.pid))
            except BaseException as e:  # noqa: BLE001 (reported below)
                errors.append(e)

        threads = [threading.Thread(target=vehicle, args=(k,)) for k in range(VEHICLES)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
        assert not errors, errors
        assert len(reports) == ROUNDS * VEHICLES
        assert all(r["status"] == "completed" for r in reports), [r for r in reports if r["status"] != "completed"]
        q = len(samples) // 4
        second, last = max(samples[q:2 * q]), max(samples[3 * q:])
        print(f"RSS by run (kB): {samples}")
        assert last - second < 12_000, f"RSS grew {last - second} kB from the second to the last quarter: {samples}"
        assert d.proc.poll() is None
    finally:
        for s in stalled:
            s.close()
        assert d.stop() == 0, d.text()
