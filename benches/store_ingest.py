"""Ingest speed of `shocktwin serve` with the fleet store on and off, side by side.

    .venv/bin/python benches/store_ingest.py [--runs 12] [--rounds 3]

Drops the same simulated quick runs (`shocktwin simulate --quick`) into a fresh
inbox of a fresh daemon (fixture bundle `bundle-mlp13`), once with `--db` and
once with `--no-db`, alternating, and times until every file is in `done/`.
Prints the throughput of each round and the ratio of the medians (store on /
off). A speed comparison, not a test: run it on a quiet machine. Simulated data.
"""

from __future__ import annotations

import argparse
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = ROOT / "target" / "release" / "shocktwin"
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"


def one_round(runs: list[Path], tmp: Path, store: bool) -> float:
    inbox = tmp / ("inbox-db" if store else "inbox-nodb")
    shutil.rmtree(inbox, ignore_errors=True)
    inbox.mkdir()
    db = tmp / "fleet.sqlite"
    for p in tmp.glob("fleet.sqlite*"):
        p.unlink()
    config = tmp / "serve.toml"
    config.write_text("[server]\ninbox_settle_s = 0.0\n")  # files arrive by rename: no need to wait
    cmd = [str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
           "--model", str(BUNDLE), "--inbox", str(inbox), *(["--db", str(db)] if store else ["--no-db"])]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    for line in proc.stderr:
        if re.search(r"\bserving\b", line):
            break
    started = time.perf_counter()
    for r in runs:  # the same bytes each round, appearing at once
        shutil.copy(r, inbox / (r.name + ".part"))
    for r in runs:
        (inbox / (r.name + ".part")).rename(inbox / r.name)
    done = inbox / "done"
    while not done.exists() or len(list(done.glob("*.mcap"))) < len(runs):
        if (inbox / "failed").exists() and list((inbox / "failed").glob("*.mcap")):
            raise RuntimeError(f"a run failed: {list((inbox / 'failed').iterdir())}")
        time.sleep(0.05)
    wall = time.perf_counter() - started
    proc.terminate()
    proc.wait(30)
    return wall


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=12)
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        pressures = ",".join(str(0.5 + i) for i in range(args.runs))
        subprocess.run([str(BIN), "simulate", "--quick", "--pressures", pressures, "--frequencies", "2",
                        "--out", str(tmp / "runs")], check=True, stdout=subprocess.DEVNULL)
        runs = sorted((tmp / "runs").glob("*.mcap"))
        walls: dict[bool, list[float]] = {True: [], False: []}
        for k in range(args.rounds):
            for store in (False, True) if k % 2 == 0 else (True, False):
                w = one_round(runs, tmp, store)
                walls[store].append(w)
                print(f"round {k + 1} store {'on ' if store else 'off'}: {len(runs)} runs in {w:.2f} s "
                      f"({len(runs) * 70 / w:.0f}x real time)")
        on, off = statistics.median(walls[True]), statistics.median(walls[False])
        print(f"ingest speed with the store on / off (medians): {off / on:.3f} — simulated data")
    return 0


if __name__ == "__main__":
    sys.exit(main())
