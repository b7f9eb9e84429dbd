"""`shocktwin serve` killed with SIGKILL (issue 13, item 3: crash safety).

The daemon (`target/release/shocktwin`, or `SHOCKTWIN_BIN`) runs with the fixture bundle
`crates/dt-core/tests/fixtures/bundle-mlp13` (not the placeholder twin: the real estimator,
about 65 ms per quick run on a 2-core machine), an inbox, a recording directory and a fleet
store, and is killed with `kill -9` at random moments (seeded; the seed is printed, set
`CRASH_SEED` to replay one).

What the daemon promises, and what is asserted here:

* Inbox (at-least-once, never lost): a file is moved to `done/` (or `failed/`) only after its
  run has ended in every sink, so a file the kill caught mid-way is still in the inbox and is
  processed again from the start at the next start. Every file dropped ends in exactly one of
  `inbox/`, `done/`, `failed/`, with no temporary file left anywhere.
* Fleet store: the run a kill cut stays in `runs` as `interrupted` (the daemon marks every
  `running` row so when it reopens the store), and the re-processing adds a new `completed`
  row (keys are per boot and run, not per file). "Processed twice" therefore means two
  `completed` rows for one file: that must never happen. A file in `done/` must have exactly
  one `completed` row — the store is the only record that it was processed. The store sink
  commits a run's end before it returns (`StoreSink::run_ended`), and the inbox moves the file
  only then; what remains is the gap between that commit and the rename (microseconds), where
  a kill would make the file's run be processed, and recorded, once more.
* Recordings: names are deterministic (`<asset>/<run_id>.<part>.mcap`), so re-processing
  rewrites the same files and no `.part` is left once every file is done. A `.part` cut by a
  kill is a valid MCAP prefix: its complete chunks read back (no summary, no footer) and hold
  a prefix of what a clean run records.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import IO, Any, Iterator, cast

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from conftest import ServeProcess

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("SHOCKTWIN_BIN", ROOT / "target" / "release" / "shocktwin"))
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"
ITERATIONS = 6
FILES_PER_ITERATION = 3
# Inbox files taken at once (they are renamed into place), rescanned often: the test is about
# kills, not about settling.
CONFIG = "[server]\ninbox_settle_s = 0.0\ninbox_rescan_s = 0.2\n"

sys.path.insert(0, str(ROOT))
from train.demo_serve import SocketStream  # noqa: E402  (the demo's socket writer, shared)

sys.path.remove(str(ROOT))


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """18 quick simulated runs of one unit, distinct run ids."""
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: build it with `cargo build --release -p dt-server --bins`")
    out = tmp_path_factory.mktemp("sim")
    subprocess.run([str(BIN), "simulate", "--quick", "--pressures", "3,4,5,6,7,8", "--frequencies", "1,2,3",
                    "--out", str(out)], check=True, stdout=subprocess.DEVNULL, timeout=300)
    files = sorted(out.glob("*.mcap"))
    assert len(files) == ITERATIONS * FILES_PER_ITERATION, files
    return files


@pytest.fixture()
def started() -> Iterator[list[ServeProcess]]:
    procs: list[ServeProcess] = []
    yield procs
    for p in procs:
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.wait(10)


def seed() -> int:
    s = int(os.environ.get("CRASH_SEED", random.SystemRandom().randrange(2**32)))
    print(f"crash-safety seed: {s} (replay with CRASH_SEED={s})")
    return s


def serve(started: list[ServeProcess], tmp: Path, *extra: str) -> ServeProcess:
    config = tmp / "shocktwin.toml"
    if not config.exists():
        config.write_text(CONFIG)
    p = ServeProcess([str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http",
                      "127.0.0.1:0", "--model", str(BUNDLE), "--record-dir", str(tmp / "records"),
                      "--db", str(tmp / "fleet.sqlite"), *extra])
    started.append(p)
    return p


def kill9(p: ServeProcess) -> None:
    p.proc.send_signal(signal.SIGKILL)
    p.proc.wait(10)


def drop(src: Path, inbox: Path) -> None:
    """Copies under a name the inbox ignores, then renames into place (docs/daemon.md)."""
    part = inbox / (src.name + ".part")
    shutil.copyfile(src, part)
    os.replace(part, inbox / src.name)


def store_runs(db: Path) -> list[tuple[str, str, str, int]]:
    """(run_id, source, status, ticks) of every run in the store."""
    c = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return c.execute("SELECT run_id, source, status, ticks FROM runs").fetchall()
    finally:
        c.close()


def wait_inbox_empty(inbox: Path, timeout_s: float = 30) -> None:
    deadline = time.monotonic() + timeout_s
    while list(inbox.glob("*.mcap")):
        assert time.monotonic() < deadline, f"inbox not drained: {sorted(inbox.iterdir())}"
        time.sleep(0.1)


def test_kill9_at_random_moments_never_loses_or_doubles_an_inbox_file(
        runs: list[Path], tmp_path: Path, started: list[ServeProcess]) -> None:
    rng = random.Random(seed())
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    t0 = time.monotonic()
    kills: list[tuple[float, int]] = []
    for i in range(ITERATIONS):
        p = serve(started, tmp_path, "--inbox", str(inbox))
        for src in runs[i * FILES_PER_ITERATION:(i + 1) * FILES_PER_ITERATION]:
            drop(src, inbox)
        # From at once (mid-file) to past the whole batch (about 65 ms a file) and a store commit.
        delay = rng.uniform(0.0, 0.5)
        time.sleep(delay)
        kill9(p)
        kills.append((round(delay, 3), len(list((inbox / "done").glob("*.mcap")))))
    print(f"kills (delay s, files done so far): {kills}")
    # The last start processes what is left; a clean stop ends it.
    p = serve(started, tmp_path, "--inbox", str(inbox))
    wait_inbox_empty(inbox)
    assert p.stop() == 0, p.text()
    print(f"{ITERATIONS} kills + final drain: {time.monotonic() - t0:.1f} s")

    names = {f.name for f in runs}
    places = {d: {f.name for f in (inbox / d).glob("*.mcap")} for d in ("", "done", "failed")}
    for name in names:
        where = [d or "inbox" for d, found in places.items() if name in found]
        assert len(where) == 1, f"{name} is in {where}"
    assert places["done"] == names, f"not done: {names - places['done']}; failed: {places['failed']}"
    assert set().union(*places.values()) == names, "a file appeared that was never dropped"
    leftovers = [p for p in inbox.rglob("*")
                 if p.is_file() and not p.name.endswith(".mcap") and p.name != ".shocktwin-serve.lock"]
    assert not leftovers, f"temporary or reason files left in the inbox: {leftovers}"

    # Recordings: one finished file per run, rewritten in place by re-processing; its length
    # is the run's tick count.
    rec = tmp_path / "records" / "dyno-unit-A"
    assert not list(rec.glob("*.part")), f"unfinished recordings left: {list(rec.glob('*.part'))}"
    assert {f.name for f in rec.iterdir()} == {f"{Path(n).stem}.0000.mcap" for n in names}
    full_ticks = {f.name.split(".0000.")[0]: len(read_estimates(f)) for f in rec.iterdir()}
    assert min(full_ticks.values()) > 0, full_ticks

    rows = store_runs(tmp_path / "fleet.sqlite")
    assert {r[1] for r in rows} <= {f"inbox {n}" for n in names}, rows
    assert all(status in ("completed", "interrupted") for _, _, status, _ in rows), rows
    completed: dict[str, int] = {}
    for run_id, source, status, ticks in rows:
        name = source.removeprefix("inbox ")
        assert run_id == Path(name).stem, (run_id, source)
        if status == "completed":
            completed[name] = completed.get(name, 0) + 1
            assert ticks == full_ticks[run_id], (source, ticks, full_ticks[run_id])
        else:
            assert ticks < full_ticks[run_id], f"an interrupted run has every tick: {source} {ticks}"
    doubled = {n: k for n, k in completed.items() if k > 1}
    assert not doubled, f"processed to completion more than once: {doubled}"
    # Every file in done/ has its completed row: a run's end is committed before the move.
    unrecorded = sorted(names - set(completed))
    print(f"store: {len(rows)} rows, {sum(s == 'interrupted' for _, _, s, _ in rows)} interrupted")
    assert not unrecorded, f"in done/ without a completed run in the store: {unrecorded}"


def test_a_file_in_done_has_its_completed_run_in_the_store_even_after_kill9(
        runs: list[Path], tmp_path: Path, started: list[ServeProcess]) -> None:
    """Kills the daemon right after its first move to done/ (well within `flush_ms`), up to
    3 times (a store commit may happen to land in the few ms between), then reopens the store
    as the next start does: every file in done/ must have its completed run."""
    missing: list[str] = []
    for attempt in range(3):
        tmp = tmp_path / f"attempt{attempt}"
        inbox = tmp / "inbox"
        inbox.mkdir(parents=True)
        for src in runs[:2]:
            drop(src, inbox)
        p = serve(started, tmp, "--inbox", str(inbox))
        deadline = time.monotonic() + 30
        while not list((inbox / "done").glob("*.mcap")):
            assert time.monotonic() < deadline, p.text()
            time.sleep(0.005)
        kill9(p)
        done = {f.name for f in (inbox / "done").glob("*.mcap")}
        p = serve(started, tmp, "--inbox", str(inbox))
        wait_inbox_empty(inbox)
        assert p.stop() == 0, p.text()
        completed = {src.removeprefix("inbox ") for _, src, s, _ in store_runs(tmp / "fleet.sqlite")
                     if s == "completed"}
        missing += sorted(done - completed)
        if missing:
            break
    assert not missing, f"in done/ with no completed run in the store: {missing}"


def test_a_file_completed_in_the_store_but_not_yet_moved_is_not_processed_again(
        runs: list[Path], tmp_path: Path, started: list[ServeProcess]) -> None:
    """The state a kill -9 leaves between the store's commit of a completed run and the move
    of its file to done/ (seen once in the random-kill test above: one file completed twice),
    made on purpose: a file processed once is put back into the inbox. The next start moves
    it to done/ without a second run; a file the store does not know under that inbox name
    is processed as usual."""
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    first, other = runs[0], runs[1]
    drop(first, inbox)
    p = serve(started, tmp_path, "--inbox", str(inbox))
    wait_inbox_empty(inbox)
    assert p.stop() == 0, p.text()
    os.replace(inbox / "done" / first.name, inbox / first.name)  # completed, not moved
    shutil.copyfile(other, inbox / "renamed.mcap")  # a run the store has not seen from this name
    p = serve(started, tmp_path, "--inbox", str(inbox))
    wait_inbox_empty(inbox)
    with urllib.request.urlopen(f"http://{p.http}/metrics", timeout=10) as r:
        metrics = r.read().decode()
    assert 'shocktwin_inbox_files_total{kind="done"} 2' in metrics, metrics  # both counted as moved
    assert p.stop() == 0, p.text()
    assert {f.name for f in (inbox / "done").glob("*.mcap")} == {first.name, "renamed.mcap"}
    rows = store_runs(tmp_path / "fleet.sqlite")
    by_source = {src: [s for _, so, s, _ in rows if so == src] for src in {r[1] for r in rows}}
    assert by_source == {f"inbox {first.name}": ["completed"], "inbox renamed.mcap": ["completed"]}, rows
    assert "already processed to completion from this name" in p.text()


# --- recordings cut by kill -9 ---

def read_estimates(path: Path) -> list[dict[str, Any]]:
    """The `/estimate` messages of a recording, finished or cut: the indexed reader when the
    file has its summary, else a stream read of every complete record (a chunk cut in the
    middle ends the read)."""
    with open(path, "rb") as fh:
        try:
            reader = make_reader(fh)
            return [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/estimate"],
                                                                            log_time_order=False)]
        except (McapError, ValueError, OSError):
            if not path.name.endswith(".part"):
                raise
    out: list[dict[str, Any]] = []
    estimate_channels: set[int] = set()
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh, skip_magic=False).records:
                if isinstance(record, Channel) and record.topic == "/estimate":
                    estimate_channels.add(record.id)
                elif isinstance(record, Message) and record.channel_id in estimate_channels:
                    est = json.loads(record.data)
                    assert est["t_ns"] == record.log_time, path
                    out.append(est)
        except McapError:
            pass  # the end of what reached the disk
    return out


def recording_metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh).records:
                if isinstance(record, Metadata) and record.name == "shocktwin.run":
                    return dict(record.metadata)
        except McapError:
            pass
    return {}


def send_partial(addr: str, path: Path, fraction: float, run_id: str) -> socket.socket:
    """Re-encodes the first `fraction` of the run's messages onto a socket, left open."""
    host, port = addr.rsplit(":", 1)
    sock = socket.create_connection((host, int(port)), timeout=60)
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        msgs = list(reader.iter_messages(log_time_order=True))
        writer = Writer(cast(IO[bytes], SocketStream(sock)), compression=CompressionType.ZSTD, chunk_size=4096)
        writer.start(profile="", library="shocktwin crash test (python mcap)")
        for meta in reader.iter_metadata():
            data = dict(meta.metadata)
            if meta.name == "shocktwin.run":
                data["run_id"] = run_id
            writer.add_metadata(meta.name, data)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, m in msgs[:int(len(msgs) * fraction)]:
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0))
            writer.add_message(channels[channel.id], m.log_time, m.data, m.publish_time, m.sequence)
        # Push out the open chunk without finishing the file (no summary, no footer).
        writer._Writer__finalize_chunk()  # type: ignore[attr-defined]  # noqa: SLF001  (mcap 1.3.0 has no public flush)
    return sock


def test_recordings_cut_by_kill9_read_back_up_to_their_last_complete_chunk(
        runs: list[Path], tmp_path: Path, started: list[ServeProcess]) -> None:
    # Small parts (rotation at 100 kB, 25 kB chunks): a cut run leaves finished parts and a .part.
    (tmp_path / "shocktwin.toml").write_text(CONFIG + "[record]\nmax_file_bytes = 100000\n")
    src = runs[0]
    # The clean recording of the same run: the reference.
    clean_dir = tmp_path / "clean"
    clean_dir.mkdir()
    (clean_dir / "shocktwin.toml").write_text(CONFIG + "[record]\nmax_file_bytes = 100000\n")
    inbox = clean_dir / "inbox"
    inbox.mkdir()
    drop(src, inbox)
    p = serve(started, clean_dir, "--inbox", str(inbox))
    wait_inbox_empty(inbox)
    assert p.stop() == 0, p.text()
    clean_parts = sorted((clean_dir / "records" / "dyno-unit-A").glob("*.mcap"))
    assert len(clean_parts) >= 2, f"rotation expected: {clean_parts}"
    clean = [e for f in clean_parts for e in read_estimates(f)]
    assert clean, "the clean run recorded nothing"

    p = serve(started, tmp_path)
    sock = send_partial(p.listen, src, 0.7, Path(src).stem)
    rec = tmp_path / "records" / "dyno-unit-A"
    deadline = time.monotonic() + 20
    # Wait until the daemon has written a finished part and a .part with bytes on disk.
    while not (list(rec.glob("*.mcap")) and any(f.stat().st_size > 0 for f in rec.glob("*.part"))):
        assert time.monotonic() < deadline, (p.text(), list(rec.glob("*")) if rec.exists() else None)
        time.sleep(0.02)
    time.sleep(0.3)
    kill9(p)
    sock.close()

    parts = sorted(rec.iterdir())
    assert any(f.name.endswith(".part") for f in parts), parts
    got: list[dict[str, Any]] = []
    counts: list[str] = []
    for i, f in enumerate(parts):
        assert f.name.startswith(f"{src.stem}.{i:04d}.mcap"), parts  # parts in order, none missing
        meta = recording_metadata(f)
        assert meta.get("shocktwin.recording_part") == str(i), (f, meta)
        assert meta.get("shocktwin.content") == "estimates", (f, meta)
        est = read_estimates(f)
        assert est, f"{f} ({f.stat().st_size} bytes) reads back no estimate"
        counts.append(f"{f.name}: {f.stat().st_size} B, {len(est)} estimates")
        got.extend(est)
    print(f"cut recording: {counts}; {len(got)} of {len(clean)} estimates")
    assert 0 < len(got) < len(clean), (len(got), len(clean))
    t = [e["t_ns"] for e in got]
    assert all(b > a for a, b in zip(t, t[1:])), "times not strictly increasing"
    for k, (a, b) in enumerate(zip(got, clean)):
        assert a.keys() == b.keys(), (k, a, b)
        assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True), (k, a, b)
