"""`shocktwin import`: dyno CSV exports into run logs, read back with Python's ``mcap``
reader (independent of the Rust writer), resampling held against scipy, bad input named
by file, line and column. The crank-dyno exports come from ``shocktwin simulate --format
dyno-csv`` (simulated data)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

REPO = Path(__file__).resolve().parents[2]
BIN = REPO / "target" / "release" / "shocktwin"
MAP = REPO / "docs" / "import.example.toml"
PSI_PER_BAR = 14.503773773020923


def shocktwin(*args: object, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([str(BIN), *map(str, args)], capture_output=True, text=True, env={"CI": "true"})
    if check and done.returncode != 0:
        raise AssertionError(f"shocktwin {args} failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return done


def read_mcap(path: Path) -> tuple[dict[str, str], dict[str, tuple[np.ndarray, list[dict]]]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {}
        for record in reader.iter_metadata():
            if record.name == "shocktwin.run":
                meta = dict(record.metadata)
        topics: dict[str, tuple[list[int], list[dict]]] = {}
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            t, rows = topics.setdefault(channel.topic, ([], []))
            t.append(message.log_time)
            rows.append(json.loads(message.data))
    return meta, {k: (np.array(t, dtype=np.int64), rows) for k, (t, rows) in topics.items()}


@pytest.fixture(scope="module")
def exports(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two simulated crank-dyno exports and the same runs as shocktwin logs."""
    root = tmp_path_factory.mktemp("dyno")
    shocktwin("simulate", "--quick", "--format", "dyno-csv", "--pressures", "3,7", "--frequencies", "2",
              "--out", root / "csv")
    shocktwin("simulate", "--quick", "--pressures", "3,7", "--frequencies", "2", "--out", root / "mcap")
    return {"csv": root / "csv", "mcap": root / "mcap", "root": root}


def test_dyno_export_imports_with_the_example_map(exports: dict[str, Path], tmp_path: Path) -> None:
    files = sorted(exports["csv"].glob("*.csv"))
    assert [f.name for f in files] == ["dyno-unit-A_101.5psi_2Hz_s1.csv", "dyno-unit-A_43.5psi_2Hz_s1.csv"]
    done = shocktwin("import", "--map", MAP, "--meta", "simulated=true", "--out", tmp_path, *files)
    assert "imported 2 of 2 files" in done.stdout
    assert "no accelerometers" in done.stdout
    meta, topics = read_mcap(tmp_path / "dyno-unit-A_101.5psi_2Hz_s1.mcap")
    assert meta["asset_id"] == "dyno-unit-A"
    assert meta["charge_label"] == "101.5 psi"
    assert float(meta["charge_pressure_bar"]) == pytest.approx(101.5 / PSI_PER_BAR, abs=1e-9)
    assert meta["source_file"] == "dyno-unit-A_101.5psi_2Hz_s1.csv"
    assert meta["simulated"] == "true"
    assert set(topics) == {"/position", "/force", "/temperature/shock"}
    for topic, rate in [("/position", 100), ("/force", 50), ("/temperature/shock", 1)]:
        t = topics[topic][0]
        assert np.median(np.diff(t)) == pytest.approx(1e9 / rate, rel=1e-6), topic


def test_imported_run_matches_the_same_run_logged_directly(exports: dict[str, Path], tmp_path: Path) -> None:
    """The export flips force and displacement and counts from full extension; after the
    map's conventions the import must agree with the simulator's own log of that run
    (different sensor-noise draws and no aliasing, so within the sensors' noise)."""
    shocktwin("import", "--map", MAP, "--out", tmp_path, exports["csv"] / "dyno-unit-A_101.5psi_2Hz_s1.csv")
    _, imported = read_mcap(tmp_path / "dyno-unit-A_101.5psi_2Hz_s1.mcap")
    _, direct = read_mcap(exports["mcap"] / "p7.0-f2.0-s1.mcap")
    for topic, field, tolerance in [
        ("/position", "position_m", 5e-5),
        ("/force", "force_n", 40.0),
        ("/temperature/shock", "temperature_c", 0.3),
    ]:
        t_i, rows_i = imported[topic]
        t_d, rows_d = direct[topic]
        x_i = np.array([r[field] for r in rows_i])
        x_d = np.array([r[field] for r in rows_d])
        on_direct = np.interp(t_d, t_i, x_i)
        inner = slice(3, -3)
        rms = float(np.sqrt(np.mean((on_direct[inner] - x_d[inner]) ** 2)))
        assert rms < tolerance, f"{topic}: rms difference {rms} (signal sd {x_d.std()})"


def test_resampling_matches_scipy_and_removes_the_alias(tmp_path: Path) -> None:
    """A 2 Hz stroke plus a 130 Hz tone, logged at 300 Hz: at 100 Hz the tone would alias
    to 30 Hz. The import must keep the stroke as scipy.signal.resample_poly does and
    leave nothing at 30 Hz."""
    fs, n = 300, 300 * 40
    t = np.arange(n) / fs
    stroke_mm = 40 * np.sin(2 * np.pi * 2 * t)
    tone_mm = 2 * np.sin(2 * np.pi * 130 * t)
    csv = tmp_path / "tone_7bar.csv"
    csv.write_text("t,x\n" + "".join(f"{a:.6f},{b:.9f}\n" for a, b in zip(t, stroke_mm + tone_mm)))
    shocktwin("import", "--time", "t", "--time-format", "elapsed_s", "--position", "x", "--position-unit", "mm",
              "--asset-id", "bench", "--charge", "from-name", "--out", tmp_path / "out", csv)
    meta, topics = read_mcap(tmp_path / "out" / "tone_7bar.mcap")
    assert float(meta["charge_pressure_bar"]) == 7.0
    t_ns, rows = topics["/position"]
    x = np.array([r["position_m"] for r in rows])
    ref = scipy.signal.resample_poly((stroke_mm + tone_mm) * 1e-3, 1, 3, padtype="line")
    assert len(x) == len(ref)
    inner = slice(100, -100)
    # resample_poly's default Kaiser filter droops 0.044 % at 2 Hz; ours is flatter.
    assert np.max(np.abs(x[inner] - ref[inner])) < 5e-4 * 0.04
    assert np.max(np.abs(x[inner] - stroke_mm[::3][inner] * 1e-3)) < 1e-6
    freqs, power = scipy.signal.periodogram(x[inner] - stroke_mm[::3][inner] * 1e-3, fs=100)
    alias = power[np.argmin(np.abs(freqs - 30))]
    tone_power = (2e-3) ** 2 / 2 / (freqs[1] - freqs[0])  # the tone's power had it aliased
    assert alias < 1e-8 * tone_power


@pytest.mark.parametrize("fs", [500, 1000, 2000])
def test_a_fast_loggers_tones_keep_their_amplitude(fs: int, tmp_path: Path) -> None:
    """Tones across the band, logged at 0.5–2 kHz: each topic's output keeps their
    amplitude as scipy.signal.resample_poly does (within 1 % up to 0.8 of the output's
    Nyquist frequency; resample_poly is within 0.2 %). Before, at 1 kHz -> 50 Hz an 8 Hz
    force kept 0.48 of its amplitude and the first temperature sample was dropped (a helper
    trying the import as a test engineer)."""
    secs = 60
    t = np.arange(secs * fs) / fs
    tones = {"/position": [2.0, 8.0, 20.0, 32.0, 40.0], "/force": [1.0, 4.0, 8.0, 12.5, 16.0, 20.0]}
    pos_mm = 40 + sum(np.sin(2 * np.pi * f * t + 0.3 * i) for i, f in enumerate(tones["/position"]))
    force_n = sum(100 * np.sin(2 * np.pi * f * t + 0.7 * i) for i, f in enumerate(tones["/force"]))
    temp_c = 30 + 5 * t / secs
    csv = tmp_path / f"sweep_{fs}_12bar.csv"
    csv.write_text("t,pos,F,T\n" + "".join(f"{a:.6f},{b:.6f},{c:.5f},{d:.5f}\n"
                                          for a, b, c, d in zip(t, pos_mm, force_n, temp_c)))
    shocktwin("import", "--time", "t", "--time-format", "elapsed_s", "--position", "pos", "--position-unit", "mm",
              "--mid-stroke", "40", "--force", "F", "--temp-shock", "T", "--asset-id", "bench", "--charge",
              "from-name", "--out", tmp_path / "out", csv)
    _, topics = read_mcap(tmp_path / "out" / f"sweep_{fs}_12bar.mcap")
    for topic, field, rate, scale in [("/position", "position_m", 100, 1e-3), ("/force", "force_n", 50, 100.0)]:
        t_ns, rows = topics[topic]
        x = np.array([r[field] for r in rows]) / scale
        t_out = (np.array(t_ns) - t_ns[0]) * 1e-9
        assert t_out[0] == 0 and np.median(np.diff(t_out)) == pytest.approx(1 / rate)
        inner = slice(len(x) // 5, -len(x) // 5)
        # every tone's amplitude at once, by least squares (the tones are orthogonal here)
        ti = t_out[inner]
        basis = np.column_stack([np.ones_like(ti)] + [g(2 * np.pi * f * ti) for f in tones[topic]
                                                      for g in (np.sin, np.cos)])
        coef = np.linalg.lstsq(basis, x[inner], rcond=None)[0]
        for i, f in enumerate(tones[topic]):
            gain = float(np.hypot(coef[1 + 2 * i], coef[2 + 2 * i]))
            ref = scipy.signal.resample_poly(np.sin(2 * np.pi * f * t), 1, fs // rate, padtype="line")
            ref_coef = np.linalg.lstsq(basis[:, [1 + 2 * i, 2 + 2 * i]], ref[inner], rcond=None)[0]
            ref_gain = float(np.hypot(*ref_coef))
            assert abs(gain - 1) < 0.01, f"{fs} Hz -> {rate} Hz, {topic} {f} Hz: gain {gain:.4f} " \
                                         f"(resample_poly {ref_gain:.4f})"
    # the temperature's first sample at the run's start, as the twin needs it
    t_ns, rows = topics["/temperature/shock"]
    assert t_ns[0] == topics["/position"][0][0] and rows[0]["temperature_c"] == pytest.approx(30.0, abs=0.05)


def write_export(path: Path, rows: list[str]) -> Path:
    header = "Timestamp,Force [N],Displacement [mm],Temperature [°C]\n"
    path.write_text("Test,hand-made fixture\n" + header + "".join(r + "\n" for r in rows))
    return path


def good_rows(n: int = 600, start_ms: int = 0) -> list[str]:
    rows = []
    for k in range(n):
        ms = start_ms + round(k * 1000 / 300)
        s, frac = divmod(ms, 1000)
        rows.append(f"2024-05-01T10:{s // 60:02d}:{s % 60:02d}.{frac:03d}Z,"
                    f"{500 * np.cos(4 * np.pi * ms / 1000):.1f},{40 - 30 * np.sin(4 * np.pi * ms / 1000):.3f},25.0")
    return rows


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        # (an empty thermocouple cell holds the value above it: a slow channel's export style)
        (lambda r: r.__setitem__(100, ",".join([r[100].split(",")[0], "", *r[100].split(",")[2:]])),
         [":103:", "Force [N]", "empty"]),
        (lambda r: r.__setitem__(200, r[200].replace("25.0", "hot")), [":203:", "Temperature [°C]", '"hot"']),
        (lambda r: r.__setitem__(300, r[290]), [":303:", "Timestamp", "not after line 302"]),
        (lambda r: r.__setitem__(50, "yesterday" + r[50][24:]), [":53:", "Timestamp", "yesterday"]),
    ],
    ids=["empty-cell", "not-a-number", "time-goes-back", "unreadable-time"],
)
def test_bad_rows_are_named_and_can_be_skipped(tmp_path: Path, damage, expected: list[str]) -> None:
    rows = good_rows()
    damage(rows)
    bad = write_export(tmp_path / "bad_150psi.csv", rows)
    good = write_export(tmp_path / "good_150psi.csv", good_rows())
    out = tmp_path / "out"
    done = shocktwin("import", "--map", MAP, "--out", out, bad, good, check=False)
    assert done.returncode == 1
    line = [l for l in done.stderr.splitlines() if "bad_150psi.csv" in l]
    assert line, done.stderr
    for word in expected:
        assert word in line[0], line[0]
    # The good file around it is still imported.
    assert (out / "good_150psi.mcap").exists() and not (out / "bad_150psi.mcap").exists()
    assert "imported 1 of 2 files" in done.stdout

    done = shocktwin("import", "--map", MAP, "--skip-bad-rows", "--out", out, bad)
    assert "skipped 1 rows" in done.stdout and "first at line" in done.stdout
    assert "(1 bad rows skipped)" in done.stdout


def test_a_log_from_other_data_is_not_replaced_without_overwrite(tmp_path: Path) -> None:
    """Two days' `run_150psi.csv` imported into one directory: the second replaced the first
    day's log without a word (a helper's trial). Other bytes under the same run id are now an
    error naming the way out; the same bytes again (a re-import) replace it."""
    (tmp_path / "day1").mkdir()
    (tmp_path / "day2").mkdir()
    day1 = write_export(tmp_path / "day1" / "run_150psi.csv", good_rows())
    day2 = write_export(tmp_path / "day2" / "run_150psi.csv", good_rows(start_ms=7))
    out = tmp_path / "out"
    shocktwin("import", "--map", MAP, "--out", out, day1)
    first = (out / "run_150psi.mcap").read_bytes()
    meta, _ = read_mcap(out / "run_150psi.mcap")
    assert len(meta["source_sha256"]) == 64
    done = shocktwin("import", "--map", MAP, "--out", out, day2, check=False)
    assert done.returncode == 1
    assert "run_150psi.mcap exists, imported from another run_150psi.csv" in done.stderr, done.stderr
    assert "--overwrite" in done.stderr and "--run-id" in done.stderr
    assert (out / "run_150psi.mcap").read_bytes() == first
    shocktwin("import", "--map", MAP, "--out", out, day1)  # the same bytes: a re-import
    shocktwin("import", "--map", MAP, "--out", out, "--overwrite", day2)
    assert read_mcap(out / "run_150psi.mcap")[0]["source_sha256"] != meta["source_sha256"]


def test_sign_and_mid_stroke_mistakes_are_warned(tmp_path: Path) -> None:
    """A flipped position or force sign and a missing mid-stroke offset were imported without a
    word (a helper's trial: a flipped position read a 12 bar unit as −17 bar). The data shows
    them: the rod accelerometer against the position's second derivative, the force against
    the velocity, positions that never cross mid-stroke. A correct import warns of nothing."""
    fs, secs, w = 1000, 10, 2 * np.pi * 2.0
    t = np.arange(secs * fs) / fs
    ext_m = 0.04 * np.sin(w * t)  # extension positive (SPEC §2), 80 mm stroke
    travel_mm = 40 + ext_m * 1e3  # the logger counts 0 at full compression, extension positive
    force_n = 1500 * 0.04 * w * np.cos(w * t) + 200  # tension positive, with the velocity
    a1 = -(w**2) * ext_m
    csv = tmp_path / "stroke_12bar.csv"
    csv.write_text("t,travel,F,a1,a2\n" + "".join(f"{a:.4f},{b:.5f},{c:.3f},{d:.5f},0\n"
                                                for a, b, c, d in zip(t, travel_mm, force_n, a1)))

    def run(*flags: str, accels: tuple[str, str] = ("a1", "a2")) -> str:
        done = shocktwin("import", "--time", "t", "--time-format", "elapsed_s", "--position", "travel",
                         "--position-unit", "mm", "--force", "F", "--a1", accels[0], "--a2", accels[1],
                         "--accel-unit", "m/s2",
                         "--stroke-pp-mm", "80", "--asset-id", "b", "--charge", "from-name", "--overwrite",
                         "--out", tmp_path / "out", *flags, csv)
        return done.stdout

    assert "warning" not in run("--mid-stroke", "40")
    flipped = run("--mid-stroke", "40", "--position-positive", "compression")
    assert "(a1 − a2) and the position's second derivative disagree in sign (correlation -1.00)" in flipped, flipped
    assert "the force is against the velocity" in flipped
    force = run("--mid-stroke", "40", "--force-positive", "compression")
    assert "the force is against the velocity" in force and "second derivative" not in force, force
    no_mid = run()
    assert "the positions never cross mid-stroke (0.1 to 79.9 mm for a 80.0 mm stroke)" in no_mid, no_mid
    # The two accelerometer columns swapped (a helper's trial): the body end's near-still column
    # read as the rod's passed the rod accelerometer's own check; a1 − a2 against the stroke does not.
    body = 0.05 * np.sin(7 * t)  # the body end: a slow sway, not the stroke
    csv.write_text("t,travel,F,rod,body\n" + "".join(f"{a:.4f},{b:.5f},{c:.3f},{d:.5f},{e:.5f}\n"
                                                  for a, b, c, d, e in zip(t, travel_mm, force_n, a1, body)))
    assert "warning" not in run("--mid-stroke", "40", accels=("rod", "body"))
    swapped = run("--mid-stroke", "40", accels=("body", "rod"))
    assert "the accelerometers look swapped: the body-end column (a2) follows the stroke (correlation 1.00" \
        in swapped and "swap `[acceleration] a1` and `a2`" in swapped, swapped


def test_a_time_of_day_crosses_midnight(tmp_path: Path) -> None:
    """A logger stamping the time of day alone, from 23:59:50 to 00:00:10: the file failed at
    midnight ("not after line …'s", a helper's trial). A time of day going back by more than
    12 h is the next day's; the report says where."""
    rows = []
    for k in range(2000):  # 100 Hz, 20 s
        s = (86390 + k / 100) % 86400
        h, rem = divmod(s, 3600)
        m, sec = divmod(rem, 60)
        rows.append(f"{int(h):02d}:{int(m):02d}:{sec:06.3f},{40 + 20 * np.sin(k / 10):.4f}")
    csv = tmp_path / "night_7bar.csv"
    csv.write_text("clock,x\n" + "\n".join(rows) + "\n")
    done = shocktwin("import", "--time", "clock", "--time-format", "[hour]:[minute]:[second].[subsecond]",
                     "--position", "x", "--position-unit", "mm", "--mid-stroke", "40", "--asset-id", "n",
                     "--charge", "from-name", "--out", tmp_path / "out", csv)
    assert "crossed midnight at line 1002: read as the next day" in done.stdout, done.stdout
    _, topics = read_mcap(tmp_path / "out" / "night_7bar.mcap")
    t_ns, _ = topics["/position"]
    assert len(t_ns) == 2000 and np.all(np.diff(t_ns) == 10_000_000)
    # a time going back by less than 12 h is still refused
    back = tmp_path / "back_7bar.csv"
    back.write_text("clock,x\n10:00:00.000,1\n10:00:00.010,1\n09:59:00.000,1\n")
    refused = shocktwin("import", "--time", "clock", "--time-format", "[hour]:[minute]:[second].[subsecond]",
                        "--position", "x", "--position-unit", "mm", "--asset-id", "n", "--charge", "from-name",
                        "--out", tmp_path / "out", back, check=False)
    assert refused.returncode == 1 and "is not after line 3's" in refused.stderr, refused.stderr


def test_missing_column_unit_and_gap_are_named(tmp_path: Path) -> None:
    export = write_export(tmp_path / "run_150psi.csv", good_rows())
    out = tmp_path / "out"
    done = shocktwin("import", "--map", MAP, "--temp-ambient", "Ambient [°C]", "--out", out, export, check=False)
    assert done.returncode == 1
    assert "run_150psi.csv" in done.stderr and "Ambient [°C]" in done.stderr
    # ... with the nearest header row and what it lacks
    assert "the nearest, has no [\"Ambient [°C]\"]" in done.stderr, done.stderr

    # A unit the header names, contradicted by the mapping: refused before anything is written
    # (read in inches, the export's millimetres made a 2 m stroke that replayed without a word).
    done = shocktwin("import", "--map", MAP, "--position-unit", "in", "--out", out, export, check=False)
    assert done.returncode == 1 and "Displacement [mm]" in done.stderr and '"in"' in done.stderr, done.stderr
    assert not out.exists() or not list(out.glob("*.mcap"))

    done = shocktwin("import", "--map", MAP, "--force-unit", "stone", "--out", out, export, check=False)
    assert done.returncode == 1 and '"stone"' in done.stderr and "lbf" in done.stderr

    done = shocktwin("import", "--map", MAP, "--charge", "150 atm", "--out", out, export, check=False)
    assert done.returncode == 1 and '"atm"' in done.stderr

    # A NaN stretch of 0.5 s, skipped row by row, leaves a gap the import will not bridge: the
    # rows on either side are kept, each stretch resampled on its own, and the log has the gap.
    rows = good_rows()
    for k in range(200, 350):
        rows[k] = rows[k].replace(",25.0", ",NaN")
    gap = write_export(tmp_path / "gap_150psi.csv", rows)
    done = shocktwin("import", "--map", MAP, "--skip-bad-rows", "--out", out, gap)
    assert "gap of 0.50" in done.stdout and "after line 202" in done.stdout, done.stdout
    whole = write_export(tmp_path / "whole_150psi.csv", good_rows())
    shocktwin("import", "--map", MAP, "--out", out, whole)
    t0 = np.datetime64("2024-05-01T10:00:00", "ns").astype(np.int64)
    (tg, rg), (tw, rw) = (read_mcap(out / f"{n}_150psi.mcap")[1]["/position"] for n in ("gap", "whole"))
    sg = (tg - t0) * 1e-9
    # rows 199 and 350 are at 0.663 and 1.167 s: nothing between, both sides there
    assert not np.any((sg > 0.664) & (sg < 1.166)), sg[(sg > 0.6) & (sg < 1.2)]
    assert np.sum(sg < 0.664) >= 60 and np.sum(sg > 1.166) >= 80, (np.sum(sg < 0.664), np.sum(sg > 1.166))
    # away from each stretch's cut ends, the stroke as written (30 mm at 2 Hz about mid-stroke,
    # extension positive), as close as the file without the gap reads it there
    def error(t: np.ndarray, recs: list[dict], keep: np.ndarray) -> float:
        x = np.array([r["position_m"] for r in recs])
        return float(np.max(np.abs(x[keep] - 0.03 * np.sin(4 * np.pi * t[keep]))))

    sw = (tw - t0) * 1e-9
    inner = lambda s: ((s > 0.15) & (s < 0.55)) | ((s > 1.3) & (s < 1.85))  # noqa: E731
    assert np.sum(inner(sg)) >= 60
    with_gap, without = error(sg, rg, inner(sg)), error(sw, rw, inner(sw))
    print(f"position error away from the cut ends: {with_gap:.2e} m with the gap, {without:.2e} m without")
    assert with_gap < 2 * without + 1e-6, (with_gap, without)


def test_flags_alone_with_imperial_units(tmp_path: Path) -> None:
    """lbf, °F, inches and epoch seconds by flags, no map file."""
    csv = tmp_path / "imperial.csv"
    t0 = 1_714_557_600.0
    lines = ["time_s,load_lbf,travel_in,case_F"]
    for k in range(1000):
        lines.append(f"{t0 + k / 100:.2f},{-10 * np.sin(k / 10):.4f},{np.sin(k / 10):.5f},{212.0}")
    csv.write_text("\n".join(lines) + "\n")
    shocktwin("import", "--time", "time_s", "--force", "load_lbf", "--force-unit", "lbf", "--force-positive",
              "compression", "--position", "travel_in", "--position-unit", "in", "--temp-shock", "case_F",
              "--temp-unit", "F", "--asset-id", "u1", "--run-id", "r1", "--charge", "10.3 bar", "--out",
              tmp_path / "out", csv)
    meta, topics = read_mcap(tmp_path / "out" / "r1.mcap")
    assert meta["run_id"] == "r1" and float(meta["charge_pressure_bar"]) == 10.3
    assert topics["/position"][0][0] == round(t0 * 1e9, -4) or abs(topics["/position"][0][0] - t0 * 1e9) < 1e4
    pos = np.array([r["position_m"] for r in topics["/position"][1]])
    # 5 decimals of an inch (1.3e-7 m) and epoch seconds in f64 (2e-7 s) limit the match.
    assert np.allclose(pos, 0.0254 * np.sin(np.arange(1000) / 10), atol=3e-7)
    temps = np.array([r["temperature_c"] for r in topics["/temperature/shock"][1]])
    assert np.allclose(temps, 100.0)
    t_force, rows = topics["/force"]
    force = np.array([r["force_n"] for r in rows])
    k = (t_force - t0 * 1e9) / 1e7  # in input samples (100 Hz), with the resampler's lag
    assert np.median(np.diff(k)) == pytest.approx(2.0)  # 100 Hz -> 50 Hz
    # The band-limited filter rings at a cut end: in this 10 s file 0.023 N (0.05 % of the
    # amplitude) 15 output samples in; 6e-4 N in the middle.
    err = np.abs(force - 4.4482216152605 * 10 * np.sin(k / 10))
    assert err[15:-15].max() < 0.05 and err[100:-100].max() < 0.002, (err[15:-15].max(), err[100:-100].max())


def test_positions_beyond_the_stated_stroke_are_refused(tmp_path: Path) -> None:
    """A stated stroke (`--stroke-pp-mm`, `[run] stroke_pp_mm`) bounds the positions' range: a
    column read in a unit it is not in (no unit in its header to contradict) is refused, naming
    the column, its span and the stroke; a spike does not refuse the file."""
    csv = tmp_path / "travel.csv"
    rows = [f"{k / 100:.2f},{np.sin(k / 10):.5f}" for k in range(1000)]  # ±1 in: 50.8 mm peak to peak
    rows[500] = "5.00,5.00000"  # one spike of 5 in
    csv.write_text("t,travel\n" + "\n".join(rows) + "\n")
    out = tmp_path / "out"

    def run(unit: str, stroke: str) -> subprocess.CompletedProcess[str]:
        return shocktwin("import", "--time", "t", "--time-format", "elapsed_s", "--position", "travel",
                         "--position-unit", unit, "--stroke-pp-mm", stroke, "--asset-id", "u1", "--run-id",
                         f"r-{unit}-{stroke}", "--charge", "10 bar", "--out", out, csv, check=False)

    done = run("in", "60")
    assert done.returncode == 0, done.stderr
    assert (out / "r-in-60.mcap").exists()
    done = run("m", "60")  # 2 m where the dyno strokes 60 mm
    assert done.returncode == 1, done.stdout
    assert "travel.csv" in done.stderr and '"travel"' in done.stderr, done.stderr
    assert "spans 2000.0 mm" in done.stderr and "stroke of 60.0 mm" in done.stderr, done.stderr
    assert not (out / "r-m-60.mcap").exists()
    done = run("in", "40")  # 50.8 mm is more than 1.25 × 40 mm
    assert done.returncode == 1 and "spans 50.8 mm" in done.stderr, done.stderr
    done = run("in", "0")
    assert done.returncode == 1 and "stroke_pp_mm = 0" in done.stderr, done.stderr


def test_a_european_windows_export_reads_as_its_plain_twin(tmp_path: Path) -> None:
    """The same run written two ways: as a Western-European Windows DAQ writes it (Windows-1252,
    `;` between fields, decimal commas, `\\r\\n`, a preamble, a units row, units in capitals and
    daN, time in ms starting 0.5 s before the trigger) and as plain UTF-8 CSV in SI-ish units.
    Both import to the same log, read back with Python's `mcap`; nothing is left half-written."""
    n = 1500
    t_s = np.arange(n) / 500.0  # 500 Hz
    pos_mm = 40.0 + 20.0 * np.sin(2 * np.pi * 2 * t_s)
    force_n = 300.0 * np.cos(2 * np.pi * 2 * t_s)
    temp_c = 25.0 + 0.001 * np.arange(n)
    plain = tmp_path / "plain.csv"
    plain.write_text("t [s],pos [mm],force [N],T [°C]\n" + "".join(
        f"{t:.3f},{p:.4f},{f:.3f},{c:.3f}\n" for t, p, f, c in zip(t_s, pos_mm, force_n, temp_c)), encoding="utf-8")
    de = tmp_path / "prüfstand.csv"
    rows = ["Prüfstand 3;Stoßdämpfer µ-Serie", "Zeit [ms];Weg [MM];Kraft [daN];Temperatur [°C]", "ms;mm;daN;°C"]
    rows += [f"{1000 * t - 500:.0f};{p:.4f};{f / 10:.4f};{c:.3f}".replace(".", ",")
             for t, p, f, c in zip(t_s, pos_mm, force_n, temp_c)]
    de.write_bytes(("\r\n".join(rows) + "\r\n").encode("cp1252"))
    common = ("--asset-id", "u1", "--charge", "10 bar")
    shocktwin("import", *common, "--run-id", "plain", "--time", "t [s]", "--position", "pos [mm]",
              "--position-unit", "mm", "--force", "force [N]", "--temp-shock", "T [°C]", "--temp-unit", "C",
              "--out", tmp_path / "out", plain)
    # Without the encoding: refused, naming the line and the option; nothing written.
    refused = shocktwin("import", *common, "--run-id", "de", "--delimiter", ";", "--decimal", ",",
                        "--time", "Zeit [ms]", "--out", tmp_path / "out", de, check=False)
    assert refused.returncode == 1 and "line 1 is not UTF-8" in refused.stderr and "--encoding" in refused.stderr
    done = shocktwin("import", *common, "--run-id", "de", "--encoding", "windows-1252", "--delimiter", ";",
                     "--decimal", ",", "--time", "Zeit [ms]", "--position", "Weg [MM]", "--position-unit", "MM",
                     "--force", "Kraft [daN]", "--force-unit", "daN", "--temp-shock", "Temperatur [°C]",
                     "--temp-unit", "C", "--out", tmp_path / "out", de)
    # the units row is passed over and said (until the sixty-third session it needed
    # --skip-bad-rows, and without it failed the file as "not an ISO-8601 time")
    assert "line 3 read as a units row (ms, mm, daN, °C): not data" in done.stdout, done.stdout
    assert "skipped" not in done.stdout, done.stdout
    assert "moved by +0.500000 s" in done.stdout, done.stdout
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["de.mcap", "plain.mcap"]
    _, a = read_mcap(tmp_path / "out" / "plain.mcap")
    _, b = read_mcap(tmp_path / "out" / "de.mcap")
    assert a.keys() == b.keys()
    for topic, (t, rows) in a.items():
        tb, rows_b = b[topic]
        assert np.array_equal(t, tb), topic
        for key in rows[0]:
            va = np.array([r[key] for r in rows])
            vb = np.array([r[key] for r in rows_b])
            assert np.allclose(va, vb, rtol=0, atol=1e-9), (topic, key)


def test_a_slow_logger_keeps_its_rate_and_a_stub_is_refused(tmp_path: Path) -> None:
    """A logger every 2 s is written every 2 s, its rows as they are (it was interpolated onto
    1 Hz while the report said "not upsampled"); three rows are refused by name (they made a
    log of one message), and the file beside them is still imported."""
    header = "t [s],travel [mm],case [C]\n"
    slow = tmp_path / "slow.csv"
    slow.write_text(header + "".join(f"{2 * k},{40 + k % 7},{25 + 0.5 * k}\n" for k in range(30)))
    stub = tmp_path / "stub.csv"
    stub.write_text(header + "".join(f"{k / 300:.5f},{40 + k},25\n" for k in range(3)))
    flags = ("--time", "t [s]", "--time-format", "elapsed_s", "--position", "travel [mm]", "--position-unit",
             "mm", "--mid-stroke", "40", "--temp-shock", "case [C]", "--asset-id", "u1", "--out", tmp_path / "out")
    done = shocktwin("import", *flags, stub, slow, check=False)
    assert done.returncode == 1
    assert "stub.csv: 3 rows over 0.007 s give no topic two samples (/position 1 at 100 Hz, " \
        "/temperature/shock 1 at 1 Hz): too short to import" in done.stderr, done.stderr
    assert "58.0 s at 0.5 Hz; /position 0.5 Hz (source slower than the nominal 100 Hz: not upsampled), " \
        "/temperature/shock 0.5 Hz (source slower than the nominal 1 Hz: not upsampled)" in done.stdout, done.stdout
    assert "imported 1 of 2 files" in done.stdout
    _, topics = read_mcap(tmp_path / "out" / "slow.mcap")
    for topic, field, want in [("/position", "position_m", [1e-3 * (k % 7) for k in range(30)]),
                               ("/temperature/shock", "temperature_c", [25 + 0.5 * k for k in range(30)])]:
        t, rows = topics[topic]
        assert np.array_equal(t, np.arange(30) * 2_000_000_000), (topic, t[:5])
        assert np.allclose([r[field] for r in rows], want, rtol=0, atol=1e-12), topic


def test_a_glitch_in_a_slow_channel_is_dropped_and_said(exports: dict[str, Path], tmp_path: Path) -> None:
    """One row of a logger's glitch (a displacement of 25 m; a thermocouple's -999 degC error
    value over a few rows) was imported as read: the resampler smeared the displacement over
    0.1 s of +-65 mm, and a run's estimate read 2,509 bar there and stayed 4 bar off (a helper's
    trial). The position's row is dropped and counted in the report, the thermocouple's error
    values are read as blank cells (held), and the run is imported as its clean twin is."""
    src = exports["csv"] / "dyno-unit-A_101.5psi_2Hz_s1.csv"
    lines = src.read_text().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if line.startswith("Timestamp,"))
    cols = lines[header].strip().split(",")
    bad = list(lines)
    n_rows = len(lines) - header - 1
    spike_at = header + 1 + n_rows // 3
    row = bad[spike_at].rstrip("\n").split(",")
    row[cols.index("Displacement [mm]")] = "25000.0"
    bad[spike_at] = ",".join(row) + "\n"
    for k in range(3):
        row = bad[header + 1 + 2 * n_rows // 3 + k].rstrip("\n").split(",")
        row[cols.index("Temperature [°C]")] = "-999.0"
        bad[header + 1 + 2 * n_rows // 3 + k] = ",".join(row) + "\n"
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / src.name).write_text("".join(bad))
    done = shocktwin("import", "--map", MAP, "--out", tmp_path / "bad-out", tmp_path / "bad" / src.name)
    assert 'skipped 1 rows: column "Displacement [mm]": far outside the stroke' in done.stdout, done.stdout
    # a thermocouple's error value is read as a blank cell: the row (and its other channels) kept
    assert 'column "Temperature [°C]": 3 cells outside -273.15..300 °C' in done.stdout, done.stdout
    assert "skipped 3 rows" not in done.stdout, done.stdout
    shocktwin("import", "--map", MAP, "--out", tmp_path / "clean-out", src)
    _, got = read_mcap(tmp_path / "bad-out" / (src.stem + ".mcap"))
    _, want = read_mcap(tmp_path / "clean-out" / (src.stem + ".mcap"))
    # (one row fewer moves the resampled positions beside it by a tenth of a millimetre)
    for topic, field, tolerance in [("/position", "position_m", 5e-4), ("/temperature/shock", "temperature_c", 0.5)]:
        x_got = np.array([r[field] for r in got[topic][1]])
        x_want = np.interp(got[topic][0], want[topic][0], np.array([r[field] for r in want[topic][1]]))
        assert np.max(np.abs(x_got - x_want)) < tolerance, (topic, np.max(np.abs(x_got - x_want)))


def test_a_time_column_in_milliseconds_read_as_seconds_is_warned_of(tmp_path: Path) -> None:
    """A time column in ms without a unit in its header imported a 70 s run as 19 h at 1 Hz
    without a word, and its replay wrote 3.5 M rows (a helper's trial); the report warns now."""
    t_ms = np.arange(3000) * (1000.0 / 300.0)
    pos = 40.0 * np.sin(2 * np.pi * 2.0 * t_ms / 1000.0)
    csv = tmp_path / "ms.csv"
    csv.write_text("Time,Pos\n" + "".join(f"{t:.3f},{p:.3f}\n" for t, p in zip(t_ms, pos)))
    done = shocktwin("import", "--time", "Time", "--position", "Pos", "--position-unit", "mm", "--asset-id", "u1",
                     "--charge", "12 bar", "--out", tmp_path / "out", csv)
    assert "warning: the rows come at" in done.stdout and "--time-format elapsed_ms" in done.stdout, done.stdout
    done = shocktwin("import", "--time", "Time", "--time-format", "elapsed_ms", "--position", "Pos", "--position-unit",
                     "mm", "--asset-id", "u1", "--charge", "12 bar", "--out", tmp_path / "out2", csv)
    assert "warning: the rows come at" not in done.stdout, done.stdout
    done = shocktwin("import", "--time", "Time", "--time-format", "elapsed_ms", "--position", "Pos", "--position-unit",
                     "mm", "--asset-id", "u1", "--charge=-3 bar", "--out", tmp_path / "out3", csv, check=False)
    assert done.returncode != 0 and "below vacuum" in done.stderr, done.stderr


def test_a_thermocouple_written_every_so_many_rows_holds_its_value(exports: dict[str, Path], tmp_path: Path) -> None:
    """A slow channel written once in so many rows, blank between (a common export style): each
    blank cell was a bad row, and `--skip-bad-rows` kept 71 rows of 70,001 (a helper's trial).
    Blank thermocouple cells now hold the value above them (the first value, before it), the
    report says how many, and the run imports as its twin with every cell written does."""
    src = exports["csv"] / "dyno-unit-A_101.5psi_2Hz_s1.csv"
    lines = src.read_text().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if line.startswith("Timestamp,"))
    k = lines[header].strip().split(",").index("Temperature [°C]")
    sparse = lines[: header + 1]
    blanks = 0
    for i, line in enumerate(lines[header + 1:]):
        cells = line.rstrip("\n").split(",")
        if i % 300 != 5:  # written once a second (the first five rows blank too)
            cells[k] = ""
            blanks += 1
        sparse.append(",".join(cells) + "\n")
    (tmp_path / "sparse").mkdir()
    (tmp_path / "sparse" / src.name).write_text("".join(sparse))
    done = shocktwin("import", "--map", MAP, "--out", tmp_path / "sparse-out", tmp_path / "sparse" / src.name)
    assert f'column "Temperature [°C]": {blanks} blank cells read as the value above them' in done.stdout, done.stdout
    assert "skipped" not in done.stdout, done.stdout
    shocktwin("import", "--map", MAP, "--out", tmp_path / "clean-out", src)
    _, got = read_mcap(tmp_path / "sparse-out" / (src.stem + ".mcap"))
    _, want = read_mcap(tmp_path / "clean-out" / (src.stem + ".mcap"))
    assert len(got["/position"][1]) == len(want["/position"][1])
    t_got = np.array([r["temperature_c"] for r in got["/temperature/shock"][1]])
    t_want = np.array([r["temperature_c"] for r in want["/temperature/shock"][1]])
    # the thermocouple reads in 0.25 degC steps and changes slowly: a second's hold moves it by a step
    assert len(t_got) == len(t_want) and np.max(np.abs(t_got - t_want)) <= 0.5, np.max(np.abs(t_got - t_want))


def test_a_stroke_with_few_samples_a_cycle_is_not_taken_for_glitches(tmp_path: Path) -> None:
    """The first glitch rule (half the span off the median of seven samples) dropped every row of
    a sine sampled four times a cycle, half of them at five or six (the review). A stroke's own
    samples are never taken for glitches, however few a cycle has."""
    for per_cycle in (4, 5, 6, 7):
        t_s = np.arange(600) / (2.0 * per_cycle)  # a 2 Hz stroke
        pos = 40.0 * np.sin(2 * np.pi * 2.0 * t_s + 0.3)
        csv = tmp_path / f"few{per_cycle}.csv"
        csv.write_text("Time,Pos\n" + "".join(f"{t:.4f},{p:.3f}\n" for t, p in zip(t_s, pos)))
        done = shocktwin("import", "--time", "Time", "--time-format", "elapsed_s", "--position", "Pos",
                         "--position-unit", "mm", "--asset-id", "u1", "--charge", "12 bar", "--out",
                         tmp_path / f"out{per_cycle}", csv)
        assert "skipped" not in done.stdout and "600 rows" in done.stdout, done.stdout


def test_a_closed_pipe_ends_the_printing_not_the_import(exports: dict[str, Path], tmp_path: Path) -> None:
    """`shocktwin import … | head -1` panicked at its second report (a helper's trial):
    `println!` on a pipe whose reader has gone. The files after it must still be imported,
    and the pipe's end is no error."""
    files = sorted(exports["csv"].glob("*.csv"))
    proc = subprocess.Popen([str(BIN), "import", "--map", MAP, "--out", tmp_path, *files],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={"CI": "true"})
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader goes before the first report
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 0, err
    assert "panicked" not in err and "Broken pipe" not in err, err
    assert sorted(p.name for p in tmp_path.glob("*.mcap")) == [f.with_suffix(".mcap").name for f in files]
