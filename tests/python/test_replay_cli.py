"""`shocktwin replay`'s table output (CSV): written beside the output and renamed over it once
a run is in it, so that a replay of which no run could be read leaves an earlier output as it
was (a helper trying the product as a test engineer lost a 2.4 MB CSV to its header that way)."""

from __future__ import annotations

import csv
import os
import stat
import subprocess
from pathlib import Path

FIXTURES = Path(__file__).resolve().parents[2] / "crates" / "dt-core" / "tests" / "fixtures"
MLP13 = FIXTURES / "bundle-mlp13"


def replay(bin_: Path, *args: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(bin_), "replay", "--model", str(MLP13), *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_a_replay_that_reads_no_run_leaves_the_output_as_it_was(shocktwin_bin: Path, make_log, tmp_path: Path):
    good = make_log("good.mcap", duration_s=4.0)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file")
    out = tmp_path / "est.csv"
    done = replay(shocktwin_bin, good, "--out", out)
    assert done.returncode == 0, done.stderr
    first = out.read_bytes()
    assert len(rows(out)) == 200
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~current_umask()  # as a new file gets

    failed = replay(shocktwin_bin, bad, "--out", out)
    assert failed.returncode == 1 and "bad.mcap" in failed.stderr, failed.stderr
    assert "left as it was" in failed.stderr
    assert out.read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # nothing staged is left

    # a good run beside a bad one: the output holds the good run's rows (and says the bad one failed)
    partly = replay(shocktwin_bin, bad, good, "--out", out)
    assert partly.returncode == 1, partly.stderr
    assert {r["run_id"] for r in rows(out)} == {"run-1"} and len(rows(out)) == 200

    # (a pipe is written directly: `staged_table` in cmd_replay.rs and its test)


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_two_inputs_of_one_run_id_are_not_mixed(shocktwin_bin: Path, make_log, tmp_path: Path):
    """The same run imported into two folders and replayed in one call (a helper trying the
    product as a test engineer): to several MCAP outputs both wrote `out-<run_id>.mcap` at once
    and left a corrupt file; to a table, both runs' rows went under one `run_id`. The later input
    is refused, naming the other; the first is replayed, and a third run beside them too."""
    from mcap.reader import make_reader

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = make_log("a/run.mcap", duration_s=4.0)
    again = make_log("b/run.mcap", duration_s=4.0)
    other = make_log("other.mcap", duration_s=4.0,
                     metadata={"asset_id": "unit-1", "run_id": "run-2", "charge_pressure_bar": "12"})
    for jobs in ("1", "2"):
        out = tmp_path / f"est-{jobs}.mcap"
        done = replay(shocktwin_bin, "--jobs", jobs, first, again, other, "--out", out)
        assert done.returncode == 1, done.stderr
        assert "run id `run-1` is also the run id of" in done.stderr and str(first) in done.stderr, done.stderr
        for run_id in ("run-1", "run-2"):
            with open(tmp_path / f"est-{jobs}-{run_id}.mcap", "rb") as fh:  # readable, whole
                n = sum(1 for _ in make_reader(fh).iter_messages(topics=["/estimate"]))
            assert n == 200, (jobs, run_id, n)

    table = tmp_path / "est.csv"
    done = replay(shocktwin_bin, first, again, other, "--out", table)
    assert done.returncode == 1 and str(again) in done.stderr, done.stderr
    got = rows(table)
    assert [sum(r["run_id"] == i for r in got) for i in ("run-1", "run-2")] == [200, 200]
