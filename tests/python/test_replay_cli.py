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
    and left a corrupt file; to a table, both runs' rows went under one `run_id`. The one read
    second is refused, naming the other; the other is replayed, and a third run beside them too."""
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
        assert "run id `run-1` is also the run id of" in done.stderr, done.stderr
        assert str(first) in done.stderr and str(again) in done.stderr, done.stderr
        for run_id in ("run-1", "run-2"):
            with open(tmp_path / f"est-{jobs}-{run_id}.mcap", "rb") as fh:  # readable, whole
                n = sum(1 for _ in make_reader(fh).iter_messages(topics=["/estimate"]))
            assert n == 200, (jobs, run_id, n)

    table = tmp_path / "est.csv"
    done = replay(shocktwin_bin, first, again, other, "--out", table)
    assert done.returncode == 1 and str(again) in done.stderr, done.stderr
    got = rows(table)
    assert [sum(r["run_id"] == i for r in got) for i in ("run-1", "run-2")] == [200, 200]


def without_stretch(src: Path, dst: Path, t0_s: float, t1_s: float) -> None:
    """`src` rewritten by the `mcap` package with every message logged in [t0_s, t1_s) after the
    first one left out (a logger's dropout), the rest (metadata, schemas, channels) as it was."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as fh_in, open(dst, "wb") as fh_out:
        reader = make_reader(fh_in)
        writer = Writer(fh_out)
        writer.start(profile="", library="shocktwin tests")
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, dict(meta.metadata))
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        start = None
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            start = message.log_time if start is None else start
            if t0_s <= (message.log_time - start) * 1e-9 < t1_s:
                continue
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0),
                                                               dict(channel.metadata))
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()


def test_a_dropout_does_not_restart_the_damper_s_heat_or_charge(shocktwin_bin: Path, tmp_path: Path):
    """A 2.5 s dropout in a stroked run (a logger's hiccup, a lost link) starts a new segment of
    the estimator (its Kalman filter and windows must start afresh); but the modelled oil
    restarted from the shock thermocouple and the charge observer from its prior. On a helper's
    imported dyno run the oil then stayed 3-4 degC low and the estimate 1.3 bar high to the end.
    Now the heat is carried through the gap and the observer keeps its reading: after the gap
    the run reads as the same run without it does (simulated data; the committed perm-18
    bundle, the cheap suite with the observer)."""
    bundle = Path(__file__).resolve().parents[2] / "docs" / "study" / "bundles" / "perm-18"
    sim = subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--pressures", "7", "--frequencies", "2",
                          "--out", str(tmp_path / "sim")], capture_output=True, text=True, timeout=300)
    assert sim.returncode == 0, sim.stderr
    (clean,) = (tmp_path / "sim").glob("*.mcap")
    holed = tmp_path / "holed.mcap"
    without_stretch(clean, holed, 30.0, 32.5)
    out = {}
    for name, log in (("clean", clean), ("holed", holed)):
        done = subprocess.run([str(shocktwin_bin), "replay", "--model", str(bundle), str(log),
                               "--out", str(tmp_path / f"{name}.csv")], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        out[name] = {round(float(r["t_s"]), 2): r for r in rows(tmp_path / f"{name}.csv")}
    assert "1 clock jumps" in done.stdout, done.stdout
    after = [t for t in out["holed"] if t >= 35.0]
    assert len(after) > 1000
    oil = [abs(float(out["holed"][t]["oil_temp_c"]) - float(out["clean"][t]["oil_temp_c"])) for t in after]
    bar = [abs(float(out["holed"][t]["pressure_bar"]) - float(out["clean"][t]["pressure_bar"])) for t in after]
    # the heat the damper took during the gap is not seen (no data): the modelled oil lags a little
    assert max(oil) < 2.0, max(oil)  # 6.0 degC when the model restarted from the thermocouple
    print(f"after the gap: oil at most {max(oil):.2f} degC and the estimate {sum(bar) / len(bar):.3f} bar off on average")
    assert sum(bar) / len(bar) < 0.3, sum(bar) / len(bar)
