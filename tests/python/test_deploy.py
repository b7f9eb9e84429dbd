"""The deployment examples in deploy/ (docs/daemon.md, "systemd"), run by the real tools."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TMPFILES = ROOT / "deploy" / "shocktwin.tmpfiles"
DAY_S = 86_400


def test_the_tmpfiles_example_removes_old_recordings_and_done_files_only(tmp_path: Path) -> None:
    """`systemd-tmpfiles --clean` with `deploy/shocktwin.tmpfiles` over a state directory laid
    out as the unit's (a DynamicUser's: /var/lib/shocktwin links into /var/lib/private):
    recordings and processed inbox files 40 days old go; those of today, a recording being
    written, failed/ and the fleet store stay."""
    exe = shutil.which("systemd-tmpfiles")
    if exe is None:
        pytest.fail("systemd-tmpfiles is missing (Debian's systemd package): sudo apt-get install systemd")
    root = tmp_path / "root"
    state = root / "var" / "lib" / "private" / "shocktwin"
    (root / "var" / "lib" / "shocktwin").parent.mkdir(parents=True, exist_ok=True)
    state.mkdir(parents=True)
    (root / "var" / "lib" / "shocktwin").symlink_to("private/shocktwin")
    old = time.time() - 40 * DAY_S

    def file(rel: str, age_s: float | None = None) -> Path:
        p = state / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"\x89MCAP0\r\n")
        if age_s is not None:
            os.utime(p, (age_s, age_s))
        return p

    gone = [file("estimates/van-07/run-1.mcap", old), file("inbox/done/van-07-d001.mcap", old),
            file("estimates/van-03/run-0.mcap", old)]
    kept = [file("estimates/van-07/run-9.mcap"), file("estimates/van-07/run-10.mcap.part"),
            file("inbox/done/van-07-d040.mcap"), file("inbox/failed/broken.mcap", old),
            file("inbox/failed/broken.mcap.reason.txt", old), file("fleet.sqlite", old),
            file("inbox/waiting.mcap", old)]
    proc = subprocess.run([exe, "--clean", f"--root={root}", str(TMPFILES)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert [p for p in gone if p.exists()] == []
    assert [p for p in kept if not p.exists()] == []
    assert (state / "estimates" / "van-07").is_dir() and (state / "inbox" / "done").is_dir()


def test_a_processed_inbox_file_is_dated_when_it_is_moved(shocktwin_bin: Path, tmp_path: Path) -> None:
    """`done/` is cleaned by age: a run copied in with its logger's date kept (`rsync -a`,
    `scp -p`) is dated when the daemon moves it there, or the next clean would remove it."""
    from conftest import ServeProcess

    runs = tmp_path / "runs"
    subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--pressures", "12", "--frequencies", "2",
                    "--out", str(runs)], check=True, capture_output=True, timeout=300)
    (run,) = runs.glob("*.mcap")
    old = time.time() - 40 * DAY_S
    os.utime(run, (old, old))
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    bundle = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"
    d = ServeProcess([str(shocktwin_bin), "serve", "--inbox", str(inbox), "--model", str(bundle), "--listen",
                      "127.0.0.1:0", "--http", "127.0.0.1:0", "--no-db"])
    try:
        import httpx

        deadline = time.monotonic() + 60
        while httpx.get(f"http://{d.http}/readyz", timeout=5).status_code != 200:
            assert time.monotonic() < deadline, d.text()[-3000:]
            time.sleep(0.2)
        os.replace(run, inbox / run.name)  # renamed in: taken at once, its date kept
        deadline = time.monotonic() + 120
        while not (done := inbox / "done" / run.name).exists():
            assert time.monotonic() < deadline, d.text()[-3000:]
            time.sleep(0.2)
        assert time.time() - done.stat().st_mtime < 600, done.stat().st_mtime
    finally:
        d.stop()
