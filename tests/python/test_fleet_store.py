"""The fleet store and the leak trend, end to end through the real daemon.

A unit losing 0.5 bar/day is simulated over 10 days (`shocktwin simulate --days
--leak-rate`, one quick 1 Hz run a day), its runs dropped into the daemon's
inbox, estimated by a cheap-suite bundle trained here (observer calibrated on a
quick campaign, permutation 17), and kept in an SQLite store (`--db`). Checked:
the predicted fault crossing's interval brackets the true crossing; the 1 s
history equals `shocktwin replay`'s estimates binned by numpy; `kill -9` and a
restart keep the fleet, its runs and its trend, and the file passes SQLite's
integrity check; a daemon killed in the middle of a run leaves that run
`interrupted` and processes it again; a store that is not one is refused with
its name; a run at an excitation the observer is not calibrated at is said so by
`shocktwin replay`, the API (kept across a restart) and the dashboard in headless
Chromium. Simulated data throughout.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import socket
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import httpx
import numpy as np
import pytest
from mcap.reader import make_reader

import shocktwin

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("SHOCKTWIN_BIN", ROOT / "target" / "release" / "shocktwin"))
ANSI = re.compile(r"\x1b\[[0-9;]*m")
LEAK_BAR_PER_DAY = 0.5
DAYS = 10

sys.path.insert(0, str(ROOT))
from train import train as train_tool  # noqa: E402

sys.path.remove(str(ROOT))


def simulate(out: Path, *args: str) -> None:
    subprocess.run([str(BIN), "simulate", "--quick", "--out", str(out), *args], check=True,
                   stdout=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def world(calibrated_campaign: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A cheap-suite bundle and a leaking unit's 10 days of runs."""
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: run `make build`")
    tmp = tmp_path_factory.mktemp("fleet")
    # a quick campaign (0.5-12 bar, 1 and 2 Hz) with the observer calibrated on it (conftest)
    campaign, physics = calibrated_campaign
    bundle = tmp / "perm17"
    assert train_tool.main(["--campaign", str(campaign), "--permutation", "17", "--physics", str(physics),
                            "--out", str(bundle)]) == 0
    runs = tmp / "leaking"
    simulate(runs, "--days", str(DAYS), "--leak-rate", str(LEAK_BAR_PER_DAY), "--frequencies", "1")
    return {"bundle": bundle, "runs": runs}


class Daemon:
    def __init__(self, bundle: Path, db: Path, inbox: Path, config: Path | None = None) -> None:
        self.proc = subprocess.Popen(
            [str(BIN), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--model", str(bundle),
             "--db", str(db), "--inbox", str(inbox), *(["--config", str(config)] if config else [])],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        assert self.proc.stderr is not None
        self.http = self.tcp = ""
        for _ in range(200):
            line = ANSI.sub("", self.proc.stderr.readline())
            if not line and self.proc.poll() is not None:
                break
            m = re.search(r"http=(\S+)", line)
            if m and "listening" in line:
                self.http = m.group(1)
                tcp = re.search(r"listen=(\S+)", line)
                self.tcp = tcp.group(1) if tcp else ""
                break
        assert self.http, f"the daemon did not start (exit {self.proc.poll()})"
        self.log: list[str] = []  # what it logs after `listening`, without colours
        threading.Thread(target=lambda: [self.log.append(ANSI.sub("", x)) for x in self.proc.stderr],  # type: ignore[union-attr]
                         daemon=True).start()

    def logged(self, *words: str, wait_s: float = 0.0) -> list[str]:
        """The log lines that contain every one of ``words`` (waiting up to ``wait_s`` for one)."""
        deadline = time.monotonic() + wait_s
        while not (found := [x for x in list(self.log) if all(w in x for w in words)]) and time.monotonic() < deadline:
            time.sleep(0.1)
        return found

    def get(self, path: str, **params: Any) -> Any:
        r = httpx.get(f"http://{self.http}{path}", params=params, timeout=10)
        r.raise_for_status()
        return r.json()

    def wait_runs(self, asset: str, n: int, timeout_s: float = 240) -> list[dict[str, Any]]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                runs = self.get(f"/v1/assets/{asset}/runs")["runs"]
            except httpx.HTTPStatusError:
                runs = []
            if sum(r["status"] == "completed" for r in runs) >= n:
                return runs
            time.sleep(0.5)
        raise AssertionError(f"{asset}: fewer than {n} runs completed in {timeout_s} s")

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=30)


@pytest.fixture()
def daemons() -> Iterator[list[Daemon]]:
    started: list[Daemon] = []
    yield started
    for d in started:
        if d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait()


def unix_s(rfc3339: str) -> float:
    return float(np.datetime64(rfc3339.rstrip("Z"), "ms").astype("int64")) / 1e3


def first_log_time_ns(path: Path) -> int:
    with path.open("rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(log_time_order=True):
            return int(message.log_time)
    raise AssertionError(f"{path}: no messages")


def test_trend_history_and_restart(world: dict[str, Path], tmp_path: Path, daemons: list[Daemon]) -> None:
    inbox, db = tmp_path / "inbox", tmp_path / "state" / "fleet.sqlite"
    inbox.mkdir()
    files = sorted(world["runs"].glob("*.mcap"))
    for f in files:
        shutil.copy(f, inbox / f.name)
    d = Daemon(world["bundle"], db, inbox)
    daemons.append(d)
    d.wait_runs("dyno-unit-A", DAYS)
    time.sleep(1.5)  # the trend is refreshed after the last run's commit

    # The true charge against calendar time: the labels at each run's start.
    t_true = np.array([first_log_time_ns(f) / 1e9 for f in files])
    p_true = np.array([shocktwin.read_log(f).label for f in files])
    slope, icpt = np.polyfit(t_true, p_true, 1)
    trend = d.get("/v1/assets/dyno-unit-A/trend")
    assert trend["status"] == "ok", trend
    assert trend["runs_used"] == DAYS
    fault = trend["fault"]
    truth = (trend["fault_bar"] - icpt) / slope
    lo, hi = unix_s(fault["t_lo"]), unix_s(fault["t_hi"])
    print(f"fault crossing: true {truth:.0f}, predicted {unix_s(fault['t']):.0f} [{lo:.0f}, {hi:.0f}] "
          f"(±{(hi - lo) / 2 / 86400:.2f} d); leak rate {trend['leak_rate_bar_per_day']:.3f} "
          f"[{trend['leak_rate_lo_bar_per_day']:.3f}, {trend['leak_rate_hi_bar_per_day']:.3f}] bar/day "
          f"(true {LEAK_BAR_PER_DAY}) — simulated data")
    assert lo <= truth <= hi, f"the fault interval [{lo}, {hi}] misses the true crossing {truth}"
    assert trend["leak_rate_lo_bar_per_day"] > 0.0
    assets = d.get("/v1/assets")["assets"]
    assert assets[0]["trend"]["fault"] == fault

    # The 1 s history of one run equals the replayed estimates binned to calendar seconds.
    day3 = files[3]
    binned = replay_binned(world["bundle"], day3, tmp_path / "day3.csv")
    secs = sorted(binned)
    start, end = (f"{np.datetime64(secs[k], 's')}Z" for k in (0, -1))
    hist = d.get("/v1/assets/dyno-unit-A/history", since=start, until=end, step_s=1)["points"]
    assert len(hist) == len(secs)
    for p in hist:
        assert p["pressure_bar"] == pytest.approx(binned[int(unix_s(p["t"]))], abs=1e-9)
    coarse = d.get("/v1/assets/dyno-unit-A/history", since=start, until=end, step_s=10)["points"]
    assert len(coarse) < len(hist) / 5

    # kill -9, restart on the same file: the same fleet, runs, history and trend.
    before = {
        "runs": d.get("/v1/assets/dyno-unit-A/runs")["runs"],
        "hist": hist,
        "trend": trend,
    }
    d.kill9()
    with sqlite3.connect(db) as c:
        assert c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    d2 = Daemon(world["bundle"], db, tmp_path / "inbox")
    daemons.append(d2)
    assert [a["asset_id"] for a in d2.get("/v1/assets")["assets"]] == ["dyno-unit-A"]
    # The simulator's logs say so, and the mark survives the restart with the rest.
    assert [a["simulated"] for a in d2.get("/v1/assets")["assets"]] == [True]
    # its last update on the gateway's clock, as before the restart (not the 2023 data's)
    seen_s = d2.get("/v1/assets")["assets"][0]["last_update_unix_ms"] / 1e3
    assert time.time() - 600 < seen_s <= time.time(), seen_s
    assert before["runs"] and all(r["simulated"] is True for r in before["runs"]), before["runs"]
    assert d2.get("/v1/assets/dyno-unit-A/runs")["runs"] == before["runs"]
    assert d2.get("/v1/assets/dyno-unit-A/history", since=start, until=end, step_s=1)["points"] == before["hist"]
    again = d2.get("/v1/assets/dyno-unit-A/trend")
    assert again["fault"] == before["trend"]["fault"]
    d2.stop()
    assert d2.proc.returncode == 0


def replay_binned(bundle: Path, run: Path, out: Path, *extra: str) -> dict[int, float]:
    """``shocktwin replay``'s pressure averaged per calendar second."""
    subprocess.run([str(BIN), "replay", "--model", str(bundle), str(run), "--out", str(out), *extra],
                   check=True, stdout=subprocess.DEVNULL)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    t0 = first_log_time_ns(run)
    sec = (t0 + np.array([round(float(r["t_s"]) * 1e9) for r in rows])) // 1_000_000_000
    pressure = np.array([float(r["pressure_bar"]) for r in rows])
    return {int(s): float(pressure[sec == s].mean()) for s in np.unique(sec)}


def assert_history_is(d: Daemon, asset: str, binned: dict[int, float]) -> None:
    """The daemon's 1 s history of ``asset`` is ``binned`` (Unix s -> bar, from ``replay_binned``)
    to 1e-9, second by second."""
    secs = sorted(binned)
    hist = d.get(f"/v1/assets/{asset}/history", since=f"{np.datetime64(secs[0], 's')}Z",
                 until=f"{np.datetime64(secs[-1], 's')}Z", step_s=1)["points"]
    assert len(hist) == len(secs)
    for p in hist:
        assert p["pressure_bar"] == pytest.approx(binned[int(unix_s(p["t"]))], abs=1e-9)


# A damping law of the simulated dyno's shape (dt-core's test law `a_law`): hinges.
UNIT_LAW = {"knots_mps": [-0.15, -0.09, -0.05, -0.025, 0.025, 0.05, 0.09, 0.15], "width_mps": 0.008,
            "viscous_nspm": [2500.0, 0, 0, 0, 0, 5000.0, 0, 0, 0],
            "dry_nspm": [500.0, -5000.0, 0, 2500.0, 0, 0, 0, 0, -6000.0], "beta_per_k": 0.03}


def test_an_older_run_processed_later_does_not_become_the_assets_latest(world: dict[str, Path], tmp_path: Path,
                                                                        daemons: list[Daemon]) -> None:
    """A backlog upload: the leaking unit's last day goes into the inbox first, then its first
    day (12 bar). `/v1/assets` keeps showing the last day (its run, pressure, recent history and
    last run), not the run processed last, as the fleet store does after a restart; nor does a
    middle day processed after that."""
    days = sorted(world["runs"].glob("*.mcap"))
    newest, oldest, middle = days[-1], days[0], days[len(days) // 2]
    inbox, db = tmp_path / "inbox", tmp_path / "fleet.sqlite"
    inbox.mkdir()
    d = Daemon(world["bundle"], db, inbox)
    daemons.append(d)

    def row() -> dict[str, Any]:
        return next(a for a in d.get("/v1/assets")["assets"] if a["asset_id"] == "dyno-unit-A")

    shutil.copy(newest, inbox / newest.name)
    (inbox / "dyno-export.csv").write_text("t,position\n0,0\n")
    d.wait_runs("dyno-unit-A", 1)
    shown = row()
    # said once each (a helper's trial: a mistyped asset id joined without a word; a CSV was ignored)
    assert len(d.logged("a new asset joins the fleet", "dyno-unit-A")) == 1, d.log
    assert d.logged("dyno-export.csv", "shocktwin import", wait_s=20), d.log
    # the same run uploaded again adds nothing to what is shown (a helper's trial: its last tick
    # came into the history twice)
    shutil.copy(newest, inbox / f"again-{newest.name}")
    d.wait_runs("dyno-unit-A", 2)
    deadline = time.monotonic() + 60
    while row()["ticks"] < 2 * shown["ticks"]:  # every tick of it through the live view
        assert time.monotonic() < deadline, d.log
        time.sleep(0.2)
    hist = d.get("/v1/assets/dyno-unit-A", history=100000)["history"]
    assert all(a["t_ns"] < b["t_ns"] for a, b in zip(hist, hist[1:])), "a tick shown twice"
    assert row()["run_id"] == shown["run_id"]
    shutil.copy(oldest, inbox / oldest.name)
    runs = d.wait_runs("dyno-unit-A", 3)
    assert runs[0]["run_id"] == shown["run_id"] != runs[-1]["run_id"], runs
    assert len(d.logged("a new asset joins the fleet")) == 1, d.log
    after = row()
    for k in ("run_id", "pressure_bar", "pressure_lo_bar", "pressure_hi_bar", "health", "last_t_ns"):
        assert after[k] == shown[k], (k, shown, after)
    assert after["ticks"] > shown["ticks"], after
    hist = d.get("/v1/assets/dyno-unit-A", history=100000)["history"]
    assert hist and hist[-1]["t_ns"] == shown["last_t_ns"], hist[-1]
    assert all(a["t_ns"] < b["t_ns"] for a, b in zip(hist, hist[1:])), "history out of order"
    d.stop()
    # the store says the same after a restart
    d2 = Daemon(world["bundle"], db, inbox)
    daemons.append(d2)
    d = d2
    assert row()["run_id"] == shown["run_id"]
    # a run newer than what it shows is shown
    shutil.copy(middle, inbox / middle.name)
    d.wait_runs("dyno-unit-A", 4)
    assert row()["run_id"] == shown["run_id"], "a middle day is older than the last"
    d2.stop()


def test_a_live_stream_shows_whatever_its_clock_says(world: dict[str, Path], tmp_path: Path,
                                                    daemons: list[Daemon]) -> None:
    """A live stream is the asset now: streamed over TCP after a newer log was uploaded, its run,
    pressure and last run are what `/v1/assets` shows, though its clock lies before the upload's
    (the demo's leaking unit, streamed after its service drive went through the inbox). An
    upload of older data after it is not shown."""
    days = sorted(world["runs"].glob("*.mcap"))
    newest, oldest, middle = days[-1], days[0], days[len(days) // 2]
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    d = Daemon(world["bundle"], tmp_path / "fleet.sqlite", inbox)
    daemons.append(d)

    def row() -> dict[str, Any]:
        return next(a for a in d.get("/v1/assets")["assets"] if a["asset_id"] == "dyno-unit-A")

    shutil.copy(newest, inbox / newest.name)
    d.wait_runs("dyno-unit-A", 1)
    uploaded = row()
    host, port = d.tcp.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=60) as sock, open(oldest, "rb") as fh:
        sock.sendall(fh.read())
    runs = d.wait_runs("dyno-unit-A", 2)
    live = row()
    assert live["run_id"] != uploaded["run_id"], (runs, live)
    assert live["run_id"] in {r["run_id"] for r in runs}, (runs, live)
    assert live["last_t_ns"] < uploaded["last_t_ns"], "the streamed day is the older one"
    assert live["last_run_status"] == "completed"
    hist = d.get("/v1/assets/dyno-unit-A", history=1)["history"]
    assert hist[-1]["t_ns"] == live["last_t_ns"]
    # an upload older than the newest data the asset has shown stays in the store
    shutil.copy(middle, inbox / middle.name)
    d.wait_runs("dyno-unit-A", 3)
    assert row()["run_id"] == live["run_id"]
    d.stop()


def test_an_assets_observer_baseline_reaches_its_estimates(world: dict[str, Path], tmp_path: Path,
                                                          daemons: list[Daemon]) -> None:
    """`[assets.<id>] observer_baseline` in the daemon's config: that asset's estimates are
    `shocktwin replay --observer-baseline`'s, not the model's alone."""
    run = sorted(world["runs"].glob("*.mcap"))[0]
    baseline = {"charge_bar": 12.0, "read_bar": 10.5, "read_sd_bar": 0.3}
    (tmp_path / "unit.json").write_text(json.dumps({"observer_baseline": baseline}))
    with_b = replay_binned(world["bundle"], run, tmp_path / "b.csv", "--observer-baseline", str(tmp_path / "unit.json"))
    without = replay_binned(world["bundle"], run, tmp_path / "m.csv")
    assert max(abs(with_b[s] - without[s]) for s in with_b) > 0.1, "the baseline changed nothing"
    # the bindings, as an analyst gives it
    est = shocktwin.estimate(run, world["bundle"], observer_baseline=baseline)
    sec = (first_log_time_ns(run) + np.round(est["t_s"] * 1e9).astype(np.int64)) // 1_000_000_000
    for s in with_b:
        assert est["pressure_bar"][sec == s].mean() == pytest.approx(with_b[s], abs=1e-9)
    # the file `train.observer baseline` writes, as it is; a bad one names the field
    whole = shocktwin.estimate(run, world["bundle"], observer_baseline=json.loads((tmp_path / "unit.json").read_text()))
    assert np.array_equal(whole["pressure_bar"], est["pressure_bar"], equal_nan=True)
    # or its path, str or Path, as `road_blocks` takes its files (it said "invalid type: string")
    for given in (tmp_path / "unit.json", str(tmp_path / "unit.json"), (tmp_path / "unit.json").read_text()):
        by_path = shocktwin.estimate(run, world["bundle"], observer_baseline=given)
        assert np.array_equal(by_path["pressure_bar"], est["pressure_bar"], equal_nan=True)
    with pytest.raises(shocktwin.ParamsNotFoundError, match="nope.json"):
        shocktwin.estimate(run, world["bundle"], observer_baseline=tmp_path / "nope.json")
    with pytest.raises(shocktwin.ParamsError, match=r"observer_baseline: missing field `read_sd_bar` \(a baseline needs charge_bar"):
        shocktwin.estimate(run, world["bundle"], observer_baseline={"charge_bar": 12.0, "read_bar": 10.5})
    config = tmp_path / "serve.toml"
    config.write_text("[assets.dyno-unit-A]\nobserver_baseline = { charge_bar = 12.0, read_bar = 10.5, "
                      "read_sd_bar = 0.3 }\n")
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    shutil.copy(run, inbox / run.name)
    d = Daemon(world["bundle"], tmp_path / "fleet.sqlite", inbox, config)
    daemons.append(d)
    d.wait_runs("dyno-unit-A", 1)
    assert_history_is(d, "dyno-unit-A", with_b)
    d.stop()


def service_baseline(url: str) -> dict[str, Any]:
    """The baseline a daemon read after a service (``url``: ``…/v1/assets/{id}``), once there."""
    deadline = time.monotonic() + 20
    while (b := httpx.get(f"{url}/baseline")).status_code != 200 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert b.status_code == 200, (b.text, httpx.get(f"{url}/service").text)
    return dict(b.json())


def test_a_baseline_set_over_the_api_is_kept_and_used(world: dict[str, Path], tmp_path: Path,
                                                      daemons: list[Daemon]) -> None:
    """A maintainer baselines an asset after a service with `PUT /v1/assets/{id}/baseline`
    (the file `train.observer baseline` writes): refused with the field named when bad; the
    asset's next run is estimated as `replay --observer-baseline`; `/v1/assets` shows it; a
    restart keeps it; `DELETE` forgets it."""
    run = sorted(world["runs"].glob("*.mcap"))[0]
    doc = {"observer_baseline": {"charge_bar": 12.0, "read_bar": 10.5, "read_sd_bar": 0.3},
           "note": "provenance beside the numbers is kept out of the way"}
    (tmp_path / "unit.json").write_text(json.dumps(doc))
    with_b = replay_binned(world["bundle"], run, tmp_path / "b.csv", "--observer-baseline", str(tmp_path / "unit.json"))
    inbox, db = tmp_path / "inbox", tmp_path / "fleet.sqlite"
    inbox.mkdir()
    d = Daemon(world["bundle"], db, inbox)
    daemons.append(d)
    url = f"http://{d.http}/v1/assets/dyno-unit-A/baseline"
    assert httpx.get(url).status_code == 404
    bad = httpx.put(url, json={"charge_bar": 12.0, "read_bar": 10.5})
    assert bad.status_code == 422 and "read_sd_bar" in bad.json()["error"], bad.text
    bad = httpx.put(url, json={"charge_bar": 12.0, "read_bar": 10.5, "read_sd_bar": -1})
    assert bad.status_code == 422 and "observer.baseline.read_sd_bar" in bad.json()["error"], bad.text
    # a charge in psi taken as bar, on the baseline as on the service
    bad = httpx.put(url, json={"charge_bar": 174.0, "read_bar": 160.0, "read_sd_bar": 3.0})
    assert bad.status_code == 422 and "in psi it would be 12.0 bar" in bad.json()["error"], bad.text
    second = {"charge_bar": 58.0 / 0.0689475729, "read_bar": 4.2, "read_sd_bar": 0.3}
    bad = httpx.put(url, json={"charge_bar": 12.0, "read_bar": 10.5, "read_sd_bar": 0.3, "second": second})
    assert bad.status_code == 422 and "second.charge_bar" in bad.json()["error"], bad.text
    assert httpx.put(url, content=b"{").status_code == 400
    assert httpx.put(f"http://{d.http}/v1/assets/van%2007/baseline", json=doc).status_code == 400
    r = httpx.put(url, content=(tmp_path / "unit.json").read_bytes())
    assert r.status_code == 200, r.text
    assert r.json()["source"] == "api" and r.json()["read_bar"] == 10.5
    shutil.copy(run, inbox / run.name)
    d.wait_runs("dyno-unit-A", 1)
    # The trend restarts at the baseline: this run was recorded days before it.
    trend = d.get("/v1/assets/dyno-unit-A/trend")
    assert trend["since"] is not None and trend["status"] == "insufficient_data", trend
    assert "since the unit baseline" in trend["reason"] and trend["points"] == [], trend
    assert_history_is(d, "dyno-unit-A", with_b)
    d.stop()
    d2 = Daemon(world["bundle"], db, inbox)
    daemons.append(d2)
    row = next(a for a in d2.get("/v1/assets")["assets"] if a["asset_id"] == "dyno-unit-A")
    assert row["baseline"]["source"] == "api" and row["baseline"]["charge_bar"] == 12.0, row
    url = f"http://{d2.http}/v1/assets/dyno-unit-A/baseline"
    assert d2.get("/v1/assets/dyno-unit-A/trend")["since"] == trend["since"]
    gone = httpx.delete(url)
    assert gone.status_code == 200 and gone.json() == {"baseline": None}, gone.text
    trend = d2.get("/v1/assets/dyno-unit-A/trend")
    assert trend["since"] is None and len(trend["points"]) == 1, trend
    assert httpx.get(url).status_code == 404
    assert httpx.delete(url).status_code == 404
    # A unit's own damping law (`train.observer baseline --unit-law` writes it in the
    # baseline) is the calibration's refitted: over this model's linear slopes it is refused.
    own = {**doc, "observer_baseline": {**doc["observer_baseline"], "damping_law": UNIT_LAW}}
    r = httpx.put(url, json=own)
    assert r.status_code == 409 and "calibration's damping law's form" in r.json()["error"], r.text
    d2.stop()
    # With a model whose calibration has a law (the full study's, committed), the daemon
    # estimates with the unit's own, as replay does, keeps it across a restart and says so.
    # (with a run-to-run term in its calibration, which a reading of several runs divides)
    bundle = tmp_path / "perm-18-run"
    shutil.copytree(ROOT / "docs" / "study" / "bundles" / "perm-18", bundle)
    twin = json.loads((bundle / "twin.json").read_text())
    twin["physics"]["observer"].update(run_sd_bar=0.1, run_rel=0.02)
    (bundle / "twin.json").write_text(json.dumps(twin))
    cal = twin["physics"]["observer"]["damping_law"]
    ext = cal["valves"]["extension"]
    law = {**cal, "valves": {**cal["valves"], "extension": {**ext, "laminar_nspm": 1.1 * ext["laminar_nspm"],
                                                            "crack_n": 0.95 * ext["crack_n"]}}}
    # (and a second reading at another known charge: `baseline --second-charge-bar`; each
    # reading of several runs, `runs_averaged`, as `baseline` writes it for several runs)
    second = {"charge_bar": 4.0, "read_bar": 3.4, "read_sd_bar": 0.3, "runs_averaged": 2.5}
    # (and a reading at another excitation, far from this run's: `baseline` over runs at several
    # excitations writes one per excitation, each with the range it was read at; this run is
    # corrected by its own)
    other = {"charge_bar": 12.0, "read_bar": 9.0, "read_sd_bar": 0.4, "accel_range_mps2": [20.0, 22.0]}
    own = {**doc, "observer_baseline": {**doc["observer_baseline"], "damping_law": law, "second": second,
                                        "runs_averaged": 3.0, "accel_range_mps2": [1.3, 7.0],
                                        "other_excitations": [other]}}
    (tmp_path / "own.json").write_text(json.dumps(own))
    run2 = sorted(world["runs"].glob("*.mcap"))[1]
    with_own = replay_binned(bundle, run2, tmp_path / "o.csv", "--observer-baseline", str(tmp_path / "own.json"))
    plain = replay_binned(bundle, run2, tmp_path / "p.csv", "--observer-baseline", str(tmp_path / "unit.json"))
    assert max(abs(with_own[s] - plain[s]) for s in plain) > 0.01, "the unit's own law changed nothing"
    once = {**own, "observer_baseline": {k: v for k, v in own["observer_baseline"].items() if k != "runs_averaged"}}
    (tmp_path / "once.json").write_text(json.dumps(once))
    counted_once = replay_binned(bundle, run2, tmp_path / "c.csv", "--observer-baseline", str(tmp_path / "once.json"))
    moved = max(abs(with_own[s] - counted_once[s]) for s in plain)
    print(f"a baseline's readings of 3 and 2.5 runs against one each: the estimate moves by up to {moved:.4f} bar")
    assert moved > 1e-3, "runs_averaged changed nothing"
    inbox3, db3 = tmp_path / "inbox3", tmp_path / "fleet3.sqlite"
    inbox3.mkdir()
    d3 = Daemon(bundle, db3, inbox3)
    daemons.append(d3)
    url = f"http://{d3.http}/v1/assets/dyno-unit-A/baseline"
    bad = {**own, "observer_baseline": {**own["observer_baseline"], "second": {**second, "read_sd_bar": -1}}}
    r = httpx.put(url, json=bad)
    assert r.status_code == 422 and "observer.baseline.second.read_sd_bar" in r.json()["error"], r.text
    overlapping = {**other, "accel_range_mps2": [6.0, 8.0]}
    bad = {**own, "observer_baseline": {**own["observer_baseline"], "other_excitations": [overlapping]}}
    r = httpx.put(url, json=bad)
    assert r.status_code == 422 and "observer.baseline.other_excitations[0].accel_range_mps2" in r.json()["error"], r.text
    r = httpx.put(url, json=own)
    assert r.status_code == 200 and r.json()["own_damping_law"] is True and r.json()["second"] == second, r.text
    assert r.json()["runs_averaged"] == 3.0 and r.json()["other_excitations"] == [other], r.text
    bad = {**own, "observer_baseline": {**own["observer_baseline"], "runs_averaged": 0.5}}
    r = httpx.put(url, json=bad)
    assert r.status_code == 422 and "observer.baseline.runs_averaged" in r.json()["error"], r.text
    shutil.copy(run2, inbox3 / run2.name)
    d3.wait_runs("dyno-unit-A", 1)
    assert_history_is(d3, "dyno-unit-A", with_own)
    d3.stop()
    d4 = Daemon(bundle, db3, inbox3)
    daemons.append(d4)
    kept = d4.get("/v1/assets/dyno-unit-A/baseline")
    assert kept["own_damping_law"] is True and kept["second"] == second and kept["runs_averaged"] == 3.0, kept
    assert kept["other_excitations"] == [other], kept
    # A service (a recharge) does not change the valves: the daemon reads the unit with its
    # own law and the baseline it reads keeps it, as `train.observer baseline` reads the run
    # with that law in the calibration's place.
    from train import observer as observer_tool
    from train.campaign import load_campaign

    day = load_campaign(world["runs"]).runs[0]
    assert day.label_bar is not None
    physics = json.loads((bundle / "twin.json").read_text())["physics"]
    physics["observer"]["damping_law"] = law
    ref = observer_tool.baseline_of(physics, [day.path], day.label_bar, jobs=1)["observer_baseline"]
    url = f"http://{d4.http}/v1/assets/dyno-unit-A"
    r = httpx.put(f"{url}/service", json={"charge_bar": day.label_bar, "at": "2023-11-01T00:00:00Z"})
    assert r.status_code == 202, r.text
    shutil.copy(day.path, inbox3 / day.path.name)
    d4.wait_runs("dyno-unit-A", 2)
    got = service_baseline(url)
    # (a service's reading is one reading: it replaces both; the unit's readings at other excitations
    # are kept, as its law is, but the one whose excitations it overlaps: here the earlier own reading's)
    assert got["own_damping_law"] is True and got["charge_bar"] == day.label_bar and "second" not in got, got
    assert "runs_averaged" not in got, got
    assert got["other_excitations"] == [other], got
    assert d4.logged("keeps the earlier baseline's readings at other excitations", "kept=1", "left_out=1"), d4.log
    assert abs(got["read_bar"] - ref["read_bar"]) < 0.01, (got, ref)
    assert abs(got["read_sd_bar"] - ref["read_sd_bar"]) < 0.02 * ref["read_sd_bar"], (got, ref)
    d4.stop()


def test_a_reported_service_is_read_from_the_next_run_into_a_baseline(
        world: dict[str, Path], calibrated_campaign: tuple[Path, Path], tmp_path: Path,
        daemons: list[Daemon]) -> None:
    """A maintainer who knows only the charge the unit was filled to reports the service
    (`PUT /v1/assets/{id}/service`): bad bodies are refused by field; the service is pending
    across a restart; a run recorded before the service, or one the observer cannot read,
    leaves it pending and says why; the next run is read into the unit's baseline, which
    equals what `python -m train.observer baseline` makes of that run (the reference, in
    Python), and the service is done."""
    from train import observer as observer_tool
    from train.campaign import load_campaign

    days = load_campaign(world["runs"]).runs
    run, older = days[0].path, days[1].path  # day 0 at the start charge; day 1 a day later
    charge = days[0].label_bar
    assert charge is not None
    # the bundle's observer reads the stroke's ends apart: the baseline records their split
    bundle = tmp_path / "bundle"
    shutil.copytree(world["bundle"], bundle)
    twin = json.loads((bundle / "twin.json").read_text())
    physics = twin["physics"]
    assert physics["observer"] == json.loads(calibrated_campaign[1].read_text())["observer"]
    physics["observer"]["stroke_ends"] = True
    (bundle / "twin.json").write_text(json.dumps(twin))
    ref = observer_tool.baseline_of(physics, [run], charge, jobs=1)["observer_baseline"]
    inbox, db = tmp_path / "inbox", tmp_path / "fleet.sqlite"
    inbox.mkdir()
    d = Daemon(bundle, db, inbox)
    daemons.append(d)
    url = f"http://{d.http}/v1/assets/dyno-unit-A"
    assert httpx.get(f"{url}/service").status_code == 404
    # 174: a charge in psi typed as bar (12.0 bar) was taken (a helper's trial)
    for bad, field in (({}, "charge_bar"), ({"charge_bar": -1.0}, "charge_bar"), ({"charge_bar": 174}, "in psi"),
                       ({"charge_bar": 12, "x": 1}, "x"),
                       ({"charge_bar": 12, "at": "soon"}, "at"), ({"charge_bar": 12, "at": "2999-01-01T00:00:00Z"}, "at")):
        r = httpx.put(f"{url}/service", json=bad)
        assert r.status_code == 422 and field in r.json()["error"], r.text
    r = httpx.put(f"{url}/service", json={"charge_bar": charge})  # serviced now
    assert r.status_code == 202 and r.json()["state"] == "pending", r.text
    set_at = r.json()["set_at"]
    d.stop()
    d2 = Daemon(bundle, db, inbox)
    daemons.append(d2)
    url = f"http://{d2.http}/v1/assets/dyno-unit-A"
    pending = d2.get("/v1/assets/dyno-unit-A/service")
    assert pending == {"charge_bar": charge, "set_at": set_at, "state": "pending", "last_refusal": None}, pending

    def refusal() -> str:
        deadline = time.monotonic() + 20
        while (s := d2.get("/v1/assets/dyno-unit-A/service"))["last_refusal"] is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert s["state"] == "pending", s
        return str(s["last_refusal"])

    # The simulated logs are dated 2023: recorded before a service reported now.
    shutil.copy(older, inbox / older.name)
    d2.wait_runs("dyno-unit-A", 1)
    assert "before the service" in refusal()
    # Reported again with the time it was done, before the drives were recorded.
    r = httpx.put(f"{url}/service", json={"charge_bar": charge, "at": "2023-11-01T00:00:00Z"})
    assert r.status_code == 202 and r.json()["last_refusal"] is None, r.text
    set_at = r.json()["set_at"]
    assert set_at.startswith("2023-11-01T00:00:00"), set_at
    assert "service is pending" in httpx.get(f"{url}/baseline").json()["error"]
    # A run at an excitation the observer was not calibrated at (the quick campaign has no
    # 4 Hz) reads nothing: the service stays pending and says why.
    simulate(tmp_path / "fast", "--pressures", str(charge), "--frequencies", "4")
    fast = next((tmp_path / "fast").glob("*.mcap"))
    shutil.copy(fast, inbox / fast.name)
    d2.wait_runs("dyno-unit-A", 2)
    why = refusal()
    assert "no reversals" in why and "p12.0-f4.0" in why, why
    # read with the calibration's law: the other way to get a baseline is named
    assert "baseline --unit-law" in why and "/v1/assets/{id}/baseline" in why, why
    row = next(a for a in d2.get("/v1/assets")["assets"] if a["asset_id"] == "dyno-unit-A")
    assert row["service"]["last_refusal"] == why and row["baseline"] is None, row
    shutil.copy(run, inbox / run.name)
    d2.wait_runs("dyno-unit-A", 3)
    got = service_baseline(url)
    assert got["source"] == "api" and got["set_at"] == set_at and got["charge_bar"] == charge, got
    # the daemon takes onset and end from the excitation flag, the tool from the position (on
    # this run: the same reading, sd 0.1722 against 0.1722)
    assert abs(got["read_bar"] - ref["read_bar"]) < 0.01, (got, ref)
    assert abs(got["read_sd_bar"] - ref["read_sd_bar"]) < 0.02 * ref["read_sd_bar"], (got, ref)
    # and records the excitations it was read at, and how far apart the stroke's ends read, as
    # the tool does
    assert np.allclose(got["accel_range_mps2"], ref["accel_range_mps2"], rtol=1e-3), (got, ref)
    assert abs(got["split_bar"] - ref["split_bar"]) < 1e-6, (got, ref)
    assert httpx.get(f"{url}/service").status_code == 404
    row = next(a for a in d2.get("/v1/assets")["assets"] if a["asset_id"] == "dyno-unit-A")
    assert row["service"] is None and row["baseline"] == got, row
    d2.stop()


def test_kill9_mid_run_leaves_it_interrupted_and_redone(world: dict[str, Path], tmp_path: Path,
                                                       daemons: list[Daemon]) -> None:
    inbox, db = tmp_path / "inbox", tmp_path / "fleet.sqlite"
    # Three days of full-length 2 Hz runs (435 s each, not the world's 60 s quick runs, which
    # a fast machine processes in under half a second, between two polls): the daemon
    # processes them back to back, seconds each, so whenever it is frozen below, one of them
    # is almost surely open.
    subprocess.run([str(BIN), "simulate", "--days", "3", "--leak-rate", str(LEAK_BAR_PER_DAY), "--frequencies", "2",
                    "--out", str(inbox)], check=True, stdout=subprocess.DEVNULL)
    files = sorted(inbox.glob("*.mcap"))
    assert len(files) == 3, files
    d = Daemon(world["bundle"], db, inbox)
    daemons.append(d)
    deadline = time.monotonic() + 120
    open_runs: list[str] = []
    while time.monotonic() < deadline and not open_runs:
        try:  # a run open, with some of its history committed
            running = [r for r in d.get("/v1/assets/dyno-unit-A/runs")["runs"] if r["status"] == "running"]
            caught = bool(running) and bool(d.get("/v1/assets/dyno-unit-A/history")["points"])
        except httpx.HTTPStatusError:  # the asset is not known yet
            caught = False
        if caught:
            # Freeze it, then read which run its store has open: the run the API showed may
            # have ended between the request and the signal (a loaded machine), another begun.
            d.proc.send_signal(signal.SIGSTOP)
            with sqlite3.connect(db) as c:
                open_runs = [r[0] for r in c.execute("SELECT run_id FROM runs WHERE status = 'running'")]
            if not open_runs:
                d.proc.send_signal(signal.SIGCONT)
        time.sleep(0.05)
    assert open_runs, "the daemon was never caught with a run open (nothing to interrupt)"
    d.kill9()
    with sqlite3.connect(db) as c:
        assert c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert c.execute("SELECT count(*) FROM samples").fetchone()[0] > 0
    d2 = Daemon(world["bundle"], db, inbox)
    daemons.append(d2)
    runs = d2.wait_runs("dyno-unit-A", len(files))
    for run_id in open_runs:
        statuses = sorted(r["status"] for r in runs if r["run_id"] == run_id)
        assert statuses == ["completed", "interrupted"], runs
        # what was kept of it is counted (was: 0 ticks, its history kept; a helper's trial)
        cut = next(r for r in runs if r["run_id"] == run_id and r["status"] == "interrupted")
        whole = next(r for r in runs if r["run_id"] == run_id and r["status"] == "completed")
        assert 0 < cut["ticks"] < whole["ticks"] and cut["end"] > cut["start"], (cut, whole)
    assert {r["run_id"] for r in runs if r["status"] == "completed"} == {f.stem for f in files}
    d2.stop()


def test_a_run_relayed_over_nats_is_summarised_as_on_the_daemon_that_read_it(
        world: dict[str, Path], calibrated_campaign: tuple[Path, Path], tmp_path: Path,
        daemons: list[Daemon]) -> None:
    """A near-empty run read by a NATS worker and kept by a read-only fleet view's store has
    the summary a daemon that read the run itself keeps: taken before the floor at 0 bar from
    the pair the worker sends beside each estimate (docs/nats.md). Floored, the summary
    reads high with a narrower sd (the sixty-ninth session's change; simulated data)."""
    from conftest import NatsServer, terminate

    run = calibrated_campaign[0] / "p0.5-f2.0-s1.mcap"
    asset = shocktwin.read_log(run).metadata["asset_id"]
    # the daemon that reads the run itself: through its inbox
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    direct = Daemon(world["bundle"], tmp_path / "direct.sqlite", inbox)
    daemons.append(direct)
    shutil.copy(run, inbox / run.name)
    want = [r for r in direct.wait_runs(asset, 1) if r["status"] == "completed"][0]
    # the run floors: the interval's lower end at 0 bar in its history
    hist = direct.get(f"/v1/assets/{asset}/history", since=want["start"], until=want["end"], step_s=1)["points"]
    assert any(p["pressure_lo_bar"] == 0.0 for p in hist), "the run never floors: the test would prove nothing"

    nats_dir = tmp_path / "nats"
    nats_dir.mkdir()
    server = NatsServer(nats_dir)
    try:
        worker = subprocess.Popen([str(BIN), "serve", "--nats", server.url, "--model", str(world["bundle"]),
                                   "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--no-db"],
                                  stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            config = tmp_path / "view.toml"
            config.write_text(f'[nats]\nurl = "{server.url}"\nworker = false\n')
            (tmp_path / "view-inbox").mkdir()
            view = Daemon(world["bundle"], tmp_path / "view.sqlite", tmp_path / "view-inbox", config)
            daemons.append(view)
            deadline = time.monotonic() + 60
            while httpx.get(f"http://{view.http}/readyz", timeout=5).status_code != 200:
                assert time.monotonic() < deadline, "the fleet view did not become ready"
                time.sleep(0.3)
            proc = subprocess.run([str(BIN), "publish", "--nats", server.url, str(run)],
                                  capture_output=True, text=True, timeout=300)
            assert proc.returncode == 0, proc.stderr
            got = [r for r in view.wait_runs(asset, 1) if r["status"] == "completed"][0]
        finally:
            terminate(worker)
    finally:
        server.stop()
    assert got["ticks"] == want["ticks"]
    for key in ("summary_bar", "summary_sd_bar"):
        assert got[key] == pytest.approx(want[key], rel=1e-9, abs=1e-9), (key, got, want)


def test_a_file_that_is_not_a_store_is_refused_by_name(tmp_path: Path) -> None:
    bad = tmp_path / "fleet.sqlite"
    bad.write_bytes(b"this is not a database\n" * 512)
    proc = subprocess.run([str(BIN), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--db", str(bad)],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 1
    assert str(bad) in proc.stderr and "not a readable SQLite database" in proc.stderr, proc.stderr


def test_a_full_disk_degrades_readyz_and_the_daemon_carries_on(world: dict[str, Path], tmp_path: Path,
                                                               daemons: list[Daemon]) -> None:
    small = tmp_path / "small"
    small.mkdir()
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=96k", "tmpfs", str(small)],
                           capture_output=True, text=True)
    if mount.returncode != 0:
        pytest.skip(f"a full disk needs a small tmpfs, which this machine does not let us mount: {mount.stderr.strip()}")
    try:
        inbox = tmp_path / "inbox"
        inbox.mkdir()
        d = Daemon(world["bundle"], small / "fleet.sqlite", inbox)
        daemons.append(d)
        files = sorted(world["runs"].glob("*.mcap"))
        for f in files:
            shutil.copy(f, inbox / f.name)
        deadline = time.monotonic() + 240
        ready = httpx.get(f"http://{d.http}/readyz", timeout=10)
        # ready (200), or not yet: the inbox still starting (503 "starting inbox"), until the store fills
        while time.monotonic() < deadline and "degraded" not in ready.text:
            time.sleep(0.5)
            ready = httpx.get(f"http://{d.http}/readyz", timeout=10)
        assert ready.status_code == 503 and "degraded" in ready.text, ready.text
        assert "full" in ready.text.lower(), ready.text
        # The runs are still estimated and served live; every file is done.
        while time.monotonic() < deadline and len(list((inbox / "done").glob("*.mcap"))) < len(files):
            time.sleep(0.5)
        assert len(list((inbox / "done").glob("*.mcap"))) == len(files)
        assert d.get("/v1/assets")["assets"][0]["ticks"] > 0
        d.stop()
        assert d.proc.returncode == 0
    finally:
        subprocess.run(["umount", "-l", str(small)], check=False)


@pytest.fixture(scope="module")
def at_2_and_4_hz(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """A 7 bar run at 2 Hz (where the world's observer is calibrated) and one at 4 Hz (not)."""
    out = tmp_path_factory.mktemp("at_2_and_4_hz")
    simulate(out, "--pressures", "7", "--frequencies", "2,4")
    return {2: out / "p7.0-f2.0-s1.mcap", 4: out / "p7.0-f4.0-s1.mcap"}


def test_replay_says_when_the_observer_is_not_calibrated_at_a_runs_excitation(
        world: dict[str, Path], at_2_and_4_hz: dict[int, Path], tmp_path: Path) -> None:
    """The world's bundle reads an observer calibrated at 1 and 2 Hz. A 2 Hz run is read; a
    4 Hz run is not (no model there), and `shocktwin replay` says why its estimate kept the
    prior, instead of a silent `unknown`."""
    lines = {}
    for run in at_2_and_4_hz.values():
        proc = subprocess.run([str(BIN), "replay", "--model", str(world["bundle"]), str(run), "--out",
                               str(tmp_path / f"{run.stem}.csv")], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        lines[run.name] = [ln for ln in proc.stdout.splitlines() if "charge observer:" in ln]
    at2, at4 = lines["p7.0-f2.0-s1.mcap"], lines["p7.0-f4.0-s1.mcap"]
    assert len(at2) == 1 and len(at4) == 1, lines
    read = lambda line: int(re.search(r"(\d+) read", line).group(1))  # noqa: E731
    uncalibrated = lambda line: int(re.search(r"(\d+) at an excitation", line).group(1))  # noqa: E731
    assert read(at2[0]) > 20 and "kept its prior" not in at2[0], at2
    assert read(at4[0]) == 0 and uncalibrated(at4[0]) > 20 and "kept its prior" in at4[0], at4


def test_a_prior_kept_for_reversals_too_weak_to_read_is_said(world: dict[str, Path], tmp_path: Path) -> None:
    """A 0.5 Hz sine: its reversals are too weak to read (|ÿ_r| below the observer's floor),
    so the estimate keeps the observer's prior. The bindings warned only when the calibration
    did not cover the excitation, and a notebook got 6.75 bar for 12 without a word (a
    helper's trial); now they warn, and `replay` says so, for every cause."""
    simulate(tmp_path / "slow", "--pressures", "12", "--frequencies", "0.5", "--seed", "9")
    (run,) = (tmp_path / "slow").glob("*.mcap")
    with pytest.warns(RuntimeWarning, match=r"charge observer: \d+ reversals, none read \((\d+) failed their window"):
        est = shocktwin.estimate(run, world["bundle"])
    assert est["health"][-1] == "unknown"
    proc = subprocess.run([str(BIN), "replay", "--model", str(world["bundle"]), str(run), "--out",
                           str(tmp_path / "slow.csv")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    (line,) = [ln for ln in proc.stdout.splitlines() if "charge observer:" in ln]
    assert " 0 read" in line and "kept its prior" in line, line


def test_a_run_at_an_excitation_the_network_was_not_trained_on_is_said(
        calibrated_campaign: tuple[Path, Path], at_2_and_4_hz: dict[int, Path], daemons: list[Daemon],
        tmp_path: Path) -> None:
    """A bundle without the charge observer answers any run, and a road run or a sine it never
    saw got an extrapolation without a word (the seventieth session's analyst). `train.train`
    now records the excitations it trained on; the bindings warn, `replay` says so and the
    daemon logs it once per excitation. A run at a trained excitation gets no such word."""
    campaign, physics = calibrated_campaign  # 1 and 2 Hz
    bundle = tmp_path / "perm12"
    assert train_tool.main(["--campaign", str(campaign), "--permutation", "12", "--physics", str(physics),
                            "--out", str(bundle), "--split", "none", "--per-run", "50", "--max-iter", "5"]) == 0
    twin = json.loads((bundle / "twin.json").read_text())
    assert twin["provenance"]["trained_excitations"] == ["sine 1 Hz 80 mm p-p", "sine 2 Hz 80 mm p-p"], twin["provenance"]
    untrained = "excitation `sine 4 Hz 80 mm p-p` is none of those the bundle's network was trained on"

    with pytest.warns(RuntimeWarning, match=re.escape(untrained)):
        shocktwin.estimate(at_2_and_4_hz[4], bundle)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        shocktwin.estimate(at_2_and_4_hz[2], bundle)

    said = {}
    for hz, run in at_2_and_4_hz.items():
        proc = subprocess.run([str(BIN), "replay", "--model", str(bundle), str(run), "--out",
                               str(tmp_path / f"{hz}.csv")], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        said[hz] = [ln for ln in proc.stdout.splitlines() if "none of those the bundle's network" in ln]
    assert said[2] == [] and len(said[4]) == 1 and untrained in said[4][0] and "extrapolation" in said[4][0], said

    # the daemon: two runs at 4 Hz, one at 2 Hz; said once
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    d = Daemon(bundle, tmp_path / "fleet.sqlite", inbox)
    daemons.append(d)
    for name, run in [("a.mcap", at_2_and_4_hz[4]), ("b.mcap", at_2_and_4_hz[4]), ("c.mcap", at_2_and_4_hz[2])]:
        shutil.copy(run, inbox / f".{name}")
        (inbox / f".{name}").rename(inbox / name)
    asset = shocktwin.read_log(at_2_and_4_hz[4]).metadata["asset_id"]
    d.wait_runs(asset, 3)
    lines = d.logged("none of those the bundle's network was trained on", wait_s=5.0)
    assert len(lines) == 1 and "sine 4 Hz" in lines[0], lines


def test_on_a_road_the_observer_reads_no_chance_match_and_keeps_an_honest_prior(
        world: dict[str, Path], tmp_path: Path) -> None:
    """A whole 12 bar run on the simulated class C road at 60 km/h (a drive file, not a sine):
    about 19 reversals a second, some matching a calibrated sine's |ÿ| and spacing by chance
    after a short stroke. None may be read (before the stroke check, three were, and the
    unit was called `ok` on no evidence; with the full campaign's calibration, chance reads
    put it at 0.5 bar and `low`): the estimate stays `unknown` and its interval covers the
    truth at every tick."""
    subprocess.run([str(BIN), "simulate", "--road", "60", "--pressures", "12", "--out", str(tmp_path / "road")],
                    check=True, stdout=subprocess.DEVNULL, timeout=600)
    (run,) = (tmp_path / "road").glob("*.mcap")
    out = tmp_path / "road.csv"
    proc = subprocess.run([str(BIN), "replay", "--model", str(world["bundle"]), str(run), "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    (line,) = [ln for ln in proc.stdout.splitlines() if "charge observer:" in ln]
    assert re.search(r" 0 read", line) and "kept its prior" in line, line
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) > 100_000
    assert {r["health"] for r in rows} == {"unknown"}
    assert all(float(r["pressure_lo_bar"]) <= float(r["label_bar"]) <= float(r["pressure_hi_bar"]) for r in rows)


def test_the_api_and_the_dashboard_say_when_the_observer_is_not_calibrated_at_a_runs_excitation(
        world: dict[str, Path], at_2_and_4_hz: dict[int, Path], tmp_path: Path, daemons: list[Daemon],
        driver: Any) -> None:
    """The same two runs through the daemon's inbox, one after the other: the asset summary
    carries what the observer made of its last run, every run in `/runs` its own counts, a
    restart keeps them, and the dashboard (headless Chromium) marks the asset and the run
    the observer could not read."""
    inbox, db = tmp_path / "inbox", tmp_path / "fleet.sqlite"
    inbox.mkdir()
    d = Daemon(world["bundle"], db, inbox)
    daemons.append(d)
    shutil.copy(at_2_and_4_hz[2], inbox / "at2.mcap")
    d.wait_runs("dyno-unit-A", 1)
    first = d.get("/v1/assets/dyno-unit-A")["last_run_observer"]
    assert first["used"] > 20 and not first["not_calibrated_here"], first
    shutil.copy(at_2_and_4_hz[4], inbox / "at4.mcap")
    runs = {r["run_id"]: r for r in d.wait_runs("dyno-unit-A", 2)}
    last = d.get("/v1/assets/dyno-unit-A")["last_run_observer"]
    assert last["not_calibrated_here"] and last["used"] == 0 and last["uncalibrated"] > 20, last
    assert runs["p7.0-f2.0-s1"]["observer"] == first
    assert runs["p7.0-f4.0-s1"]["observer"] == last
    counts = {"detected", "used", "spared", "skipped", "rejected", "uncalibrated", "reacquired"}
    assert counts <= set(last), last

    d.kill9()
    d2 = Daemon(world["bundle"], db, inbox)
    daemons.append(d2)
    assert d2.get("/v1/assets")["assets"][0]["last_run_observer"] == last
    assert {r["run_id"]: r["observer"] for r in d2.get("/v1/assets/dyno-unit-A/runs")["runs"]} == {
        k: r["observer"] for k, r in runs.items()}

    from selenium.webdriver.common.by import By

    driver.get(f"http://{d2.http}/#dyno-unit-A")
    row = 'tr[data-asset-id="dyno-unit-A"]'
    pill = wait_for_element(driver, By.CSS_SELECTOR, f"{row} .obs-uncal")
    assert pill.text == "observer not calibrated here"
    assert f"{last['uncalibrated']} at an excitation the calibration does not cover" in pill.get_attribute("title")
    cells = {r: wait_for_element(driver, By.CSS_SELECTOR, f'tr[data-run-id="{r}"] td.obs').text
             for r in runs}
    assert cells == {"p7.0-f2.0-s1": f"{first['used']}/{first['detected']}",
                     "p7.0-f4.0-s1": "not calibrated here"}, cells
    shot = tmp_path / "observer-not-calibrated.png"
    driver.save_screenshot(str(shot))
    print(f"screenshot: {shot}")
    errors = [e for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    assert not errors, errors
    d2.stop()
    assert d2.proc.returncode == 0


def wait_for_element(driver: Any, by: str, selector: str, timeout_s: float = 20) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = driver.find_elements(by, selector)
        if found:
            return found[0]
        time.sleep(0.2)
    raise AssertionError(f"no `{selector}` on the dashboard within {timeout_s} s")
