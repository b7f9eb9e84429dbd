"""The dashboard (`GET /`) in a real browser, against the real daemon.

`shocktwin serve` runs on loopback ephemeral ports with the fixture bundle and a
fresh fleet store (`--db`); a small simulated fleet (`shocktwin simulate --quick
--unit N`, three units) is streamed over the TCP ingest with Python's `mcap`
writer, two runs at a time. Headless Chromium from Debian's packages
(`/usr/bin/chromium`, driven through `/usr/bin/chromedriver` by selenium) loads
the page and the test checks: the page and its compiled-in assets are served
with their content types and equal the files in `crates/dt-server/assets`; the
fleet table lists the assets (`data-asset-id`), riskiest first; the live
estimate counter (`#live-count`, fed by Server-Sent Events) grows while runs
stream, and an asset first seen while the page is open appears without a
reload; a click selects an asset; each asset and run whose log says it is
simulated (`simulated = true` in its metadata, as `shocktwin simulate` writes) is
marked so, one by one: dyno-unit-U3's run is streamed with `simulated = false`, as
a real dyno's log would say, and stays unmarked; the browser console holds no
error or warning. A screenshot is saved to `out/dashboard.png` and to the test's tmp
directory. Simulated data throughout.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any, Callable, Iterator, cast

import httpx
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("SHOCKTWIN_BIN", ROOT / "target" / "release" / "shocktwin"))
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"
ASSETS = ROOT / "crates" / "dt-server" / "assets"
ANSI = re.compile(r"\x1b\[[0-9;]*m")
UNITS = (1, 2, 3)
TICKS_PER_QUICK_RUN = 3500

sys.path.insert(0, str(ROOT))
from train.demo_serve import SocketStream, copy_log  # noqa: E402  (the demo's socket writer, shared)

sys.path.remove(str(ROOT))

# URL -> (file served, content type it must carry)
SERVED = {
    "/": ("index.html", "text/html"),
    "/assets/app.js": ("app.js", "javascript"),
    "/assets/app.css": ("app.css", "text/css"),
    "/assets/uplot.min.js": ("vendor/uplot.min.js", "javascript"),
    "/assets/uplot.min.css": ("vendor/uplot.min.css", "text/css"),
}


def wait_for(what: str, cond: Callable[[], Any], timeout: float = 20.0, every: float = 0.1,
             explain: Callable[[], str] = lambda: "") -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(every)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}{explain()}")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> dict[int, dict[float, Path]]:
    """unit -> charge pressure -> its quick 2 Hz run (asset `dyno-unit-U<unit>`)."""
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: build it with `make build`")
    runs: dict[int, dict[float, Path]] = {}
    for unit in UNITS:
        out = tmp_path_factory.mktemp(f"unit{unit}")
        subprocess.run([str(BIN), "simulate", "--quick", "--pressures", "3,12", "--frequencies", "2",
                        "--unit", str(unit), "--out", str(out)], check=True, stdout=subprocess.DEVNULL, timeout=120)
        runs[unit] = {3.0: next(out.glob("p3.0-*.mcap")), 12.0: next(out.glob("p12.0-*.mcap"))}
    return runs


@pytest.fixture()
def daemon(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """`shocktwin serve` with a fresh store; yields (ingest address, HTTP address)."""
    proc = subprocess.Popen(
        [str(BIN), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--model", str(BUNDLE),
         "--record-dir", str(tmp_path / "records"), "--db", str(tmp_path / "fleet.sqlite")],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    assert proc.stderr is not None
    head: list[str] = []
    addrs = None
    for _ in range(200):  # bounded: the line comes among the first few
        line = ANSI.sub("", proc.stderr.readline())
        if not line and proc.poll() is not None:
            break
        head.append(line)
        m = re.search(r"listening listen=(\S+) http=(\S+)", line)
        if m:
            addrs = (m.group(1), m.group(2))
            break
    if addrs is None:
        proc.kill()
        proc.wait(10)
        pytest.fail("shocktwin serve did not log its addresses:\n" + "".join(head))
    threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()  # type: ignore[union-attr]
    try:
        yield addrs
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


def stream_run(addr: str, path: Path, run_meta: dict[str, str] | None = None) -> dict[str, Any]:
    """Re-encodes ``path`` onto the ingest socket (``run_meta`` updates its ``shocktwin.run``
    metadata); returns the daemon's one-line report."""
    host, port = addr.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=120) as sock, open(path, "rb") as fh:
        writer = Writer(cast(IO[bytes], SocketStream(sock)), compression=CompressionType.ZSTD, chunk_size=64 * 1024)
        writer.start(profile="", library="shocktwin dashboard test (python mcap)")
        copy_log(make_reader(fh), writer, run_meta)
        writer.finish()
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    return cast(dict[str, Any], json.loads(reply.decode().strip().splitlines()[-1]))


def stream_concurrently(addr: str, paths: list[Path], metas: dict[Path, dict[str, str]] | None = None
                        ) -> tuple[list[threading.Thread], list[dict[str, Any]]]:
    reports: list[dict[str, Any]] = []
    threads = [threading.Thread(target=lambda p=p: reports.append(stream_run(addr, p, (metas or {}).get(p))))
               for p in paths]
    for t in threads:
        t.start()
    return threads, reports


def check_reports(reports: list[dict[str, Any]], n: int) -> None:
    assert len(reports) == n, reports
    for r in reports:
        assert r["status"] == "completed" and r["ticks"] == TICKS_PER_QUICK_RUN, r


def test_dashboard_in_chromium(daemon: tuple[str, str], driver: Any, fleet: dict[int, dict[float, Path]],
                               tmp_path: Path) -> None:
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.common.by import By

    listen, http = daemon
    base = f"http://{http}"

    # The page and its compiled-in assets, as the repository has them.
    for url, (name, ctype) in SERVED.items():
        resp = httpx.get(base + url, timeout=10)
        assert resp.status_code == 200, f"GET {url}: {resp.status_code} {resp.text[:200]}"
        assert ctype in resp.headers.get("content-type", ""), f"GET {url}: {resp.headers.get('content-type')}"
        if resp.content != (ASSETS / name).read_bytes():  # compiled in: the binary is older than the file
            pytest.fail(f"GET {url} is not crates/dt-server/assets/{name}: rebuild the binary (`make build`)")

    # Two units known before the page opens.
    threads, reports = stream_concurrently(listen, [fleet[1][12.0], fleet[2][12.0]])
    for t in threads:
        t.join(120)
    check_reports(reports, 2)

    # The table is redrawn as events arrive: read it in one script, not element by element.
    def rows() -> list[dict[str, str]]:
        return cast(list[dict[str, str]], driver.execute_script(
            "return [...document.querySelectorAll('#fleet tr[data-asset-id]')].map((tr) => ({id: tr.dataset.assetId,"
            " cls: tr.className, health: tr.querySelector('.badge').textContent.trim().toLowerCase()}))"))

    def row_ids() -> list[str]:
        return [r["id"] for r in rows()]

    def click_row(asset_id: str) -> None:
        for _ in range(10):
            try:
                driver.find_element(By.CSS_SELECTOR, f'#fleet tr[data-asset-id="{asset_id}"]').click()
                return
            except StaleElementReferenceException:  # redrawn between the find and the click
                time.sleep(0.05)
        pytest.fail(f"could not click {asset_id}'s row")

    def live_count() -> int:
        return int(driver.find_element(By.ID, "live-count").text or 0)

    def page_state() -> str:  # for a failure's message: what the page says, and its console
        shown = {k: driver.find_element(By.ID, k).get_attribute("textContent") for k in ("error", "asset-error", "conn")}
        return f"\npage: {shown}\nconsole: {driver.get_log('browser')}"

    def wait(what: str, cond: Callable[[], Any], timeout: float = 20.0, every: float = 0.1) -> Any:
        return wait_for(what, cond, timeout, every, explain=page_state)

    driver.get(base + "/")
    wait("the fleet table", lambda: len(row_ids()) >= 2)
    assert sorted(row_ids()) == ["dyno-unit-U1", "dyno-unit-U2"], row_ids()
    wait("the event stream to open", lambda: driver.find_element(By.ID, "conn").text == "live")
    wait("the first asset's runs", lambda: driver.find_elements(By.CSS_SELECTOR, "#runs tr[data-run-id]"))
    before = live_count()

    # Two more runs while the page is open; dyno-unit-U3 is new to the daemon.
    threads, reports = stream_concurrently(listen, [fleet[3][3.0], fleet[1][3.0]],
                                           {fleet[3][3.0]: {"simulated": "false"}})

    def grown() -> str | None:  # "streaming" or "ended" once the counter has grown
        if live_count() <= before:
            return None
        return "streaming" if any(t.is_alive() for t in threads) else "ended"

    when = wait("#live-count to grow", grown, timeout=60, every=0.05)
    for t in threads:
        t.join(120)
    check_reports(reports, 2)
    assert when == "streaming", "#live-count grew only after the runs had ended"
    wait("dyno-unit-U3 in the table", lambda: "dyno-unit-U3" in row_ids())
    last = driver.find_element(By.ID, "last-event").text
    assert "dyno-unit-" in last, last

    # A click selects an asset: its row is marked and its section shows it.
    click_row("dyno-unit-U2")
    wait("dyno-unit-U2 selected", lambda: driver.find_element(By.ID, "asset-title").text == "dyno-unit-U2")
    wait("dyno-unit-U2's row marked", lambda: [r["id"] for r in rows() if "sel" in r["cls"]] == ["dyno-unit-U2"])
    click_row("dyno-unit-U1")
    wait("dyno-unit-U1's runs", lambda: len(driver.find_elements(By.CSS_SELECTOR, "#runs tr[data-run-id]")) >= 2)
    time.sleep(1.5)  # let the charts draw the selection

    # Sorted by risk: every health rank is no better than the next row's.
    rank = {"leak": 0, "low": 1, "unknown": 2, "ok": 3}
    healths = [r["health"] for r in rows()]
    assert [rank[h] for h in healths] == sorted(rank[h] for h in healths), healths
    assert sorted(row_ids()) == ["dyno-unit-U1", "dyno-unit-U2", "dyno-unit-U3"], row_ids()

    # The keyboard alone selects an asset: Tab reaches the fleet's rows, the arrows move between
    # them, Enter selects (a helper's trial: without a mouse no asset could be selected).
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    def focused_row() -> str | None:
        return cast(str | None, driver.execute_script(
            "const r = document.activeElement?.closest?.('#fleet tr[data-asset-id]'); return r ? r.dataset.assetId : null"))

    driver.execute_script("document.activeElement?.blur(); window.scrollTo(0, 0)")
    for _ in range(40):
        ActionChains(driver).send_keys(Keys.TAB).perform()
        if focused_row():
            break
    # (Chrome starts Tab from the row clicked last, so which row comes first is the browser's)
    order, at = row_ids(), focused_row()
    assert at in order, (at, order)
    i = order.index(at)
    key, want = (Keys.ARROW_DOWN, order[i + 1]) if i + 1 < len(order) else (Keys.ARROW_UP, order[i - 1])
    ActionChains(driver).send_keys(key).perform()
    assert focused_row() == want, (focused_row(), order)
    ActionChains(driver).send_keys(Keys.ENTER).perform()
    wait(f"{want} selected from the keyboard", lambda: driver.find_element(By.ID, "asset-title").text == want)
    time.sleep(1.5)  # redrawn at least once: the focus stays on the row
    assert focused_row() == want, focused_row()
    click_row("dyno-unit-U1")
    wait("dyno-unit-U1 selected again", lambda: driver.find_element(By.ID, "asset-title").text == "dyno-unit-U1")
    time.sleep(1.0)

    # Simulated assets and runs are marked one by one; U3's log said it was not simulated.
    marked = cast(dict[str, bool], driver.execute_script(
        "return Object.fromEntries([...document.querySelectorAll('#fleet tr[data-asset-id]')]"
        ".map((tr) => [tr.dataset.assetId, !!tr.querySelector('.pill.sim')]))"))
    assert marked == {"dyno-unit-U1": True, "dyno-unit-U2": True, "dyno-unit-U3": False}, marked
    assert driver.find_element(By.ID, "asset-sub").text.startswith("simulated data · run "), \
        driver.find_element(By.ID, "asset-sub").text
    runs_marked = driver.execute_script(
        "return [...document.querySelectorAll('#runs tr[data-run-id]')].map((tr) => !!tr.querySelector('.pill.sim'))")
    assert runs_marked and all(runs_marked), runs_marked
    u3 = httpx.get(f"{base}/v1/assets/dyno-unit-U3/runs", timeout=10).json()
    assert [r["simulated"] for r in u3["runs"]] == [False], u3
    fleet_json = {a["asset_id"]: a["simulated"] for a in httpx.get(f"{base}/v1/assets", timeout=10).json()["assets"]}
    assert fleet_json == {"dyno-unit-U1": True, "dyno-unit-U2": True, "dyno-unit-U3": False}, fleet_json

    # A run longer than the live chart keeps (3,000 points, 60 s) streamed while its asset is
    # shown: every series keeps the same points (a helper's trial: past 60 s the pressure and
    # its band kept their oldest values while the times moved on).
    click_row("dyno-unit-U2")
    wait("dyno-unit-U2 selected", lambda: driver.find_element(By.ID, "asset-title").text == "dyno-unit-U2")
    time.sleep(1.0)  # its history seeded
    check_reports([stream_run(listen, fleet[2][3.0])], 1)
    time.sleep(1.0)  # the last events drawn
    lengths = driver.execute_script("return [S.live.x, S.live.p, S.live.lo, S.live.hi].map((a) => a.length)")
    assert lengths == [3000] * 4, lengths
    last = driver.execute_script("return [S.live.x.at(-1), S.live.p.at(-1)]")
    newest = httpx.get(f"{base}/v1/assets/dyno-unit-U2?history=1", timeout=10).json()["history"][-1]
    assert abs(last[0] - newest["t_ns"] / 1e9) < 1e-6, (last, newest)
    assert abs(last[1] - newest["pressure_avg_bar"]) < 1e-9, (last, newest)

    # One run sent twice at once (a file uploaded twice): two processings of one run id on the
    # same clock. The chart keeps to one of them until it ends, and says the other streams too (a
    # helper's trial: the chart started afresh at each of their interleaved estimates, a step
    # back in time, and held a few dozen points at the end).
    seen: list[tuple[int | None, int, int | None, str]] = []  # (seq drawn, points, other seq, note)
    before = driver.execute_script("return S.liveSeq")  # the 70 s run's
    reports = []
    threads = [threading.Thread(target=lambda: reports.append(stream_run(listen, fleet[2][3.0], {"run_id": "copy"})))
               for _ in range(2)]
    for t in threads:
        t.start()
    sample = ("return [S.liveSeq, S.live.x.length, S.otherSeq, document.getElementById('live-note').textContent]")
    while any(t.is_alive() for t in threads):
        seen.append(tuple(driver.execute_script(sample)))  # type: ignore[arg-type]
        time.sleep(0.1)
    for _ in range(15):  # the note outlasts the other run by up to 3 s
        seen.append(tuple(driver.execute_script(sample)))  # type: ignore[arg-type]
        time.sleep(0.1)
    check_reports(reports, 2)
    drawn_id, xs = driver.execute_script("return [S.liveRunId, S.live.x]")
    assert drawn_id == "copy", drawn_id
    assert all(b > a for a, b in zip(xs, xs[1:]))
    # started afresh once when the copies began on the earlier run's clock, and at most once more
    # if the copy drawn ended first and the other took the chart over
    drawn = [d for d, _, _, _ in seen if d not in (None, before)]
    switches = sum(a != b for a, b in zip(drawn, drawn[1:]))
    drops = sum(b < a for (_, a, _, _), (_, b, _, _) in zip(seen, seen[1:]))
    assert switches <= 1 and drops <= 2, (switches, drops, [(d, n) for d, n, _, _ in seen])
    assert any(o is not None and o != d for d, _, o, _ in seen), "the other copy was never seen streaming"
    assert any("run copy drawn; another copy of it is streaming too" in n for *_, n in seen), seen[-3:]
    wait("the note to go with the other copy", lambda: "streaming too" not in driver.find_element(By.ID, "live-note").text,
         timeout=10)

    # Listed twice, and the copy the trend does not count says so.
    def copy_rows() -> list[bool]:  # per row of the run: marked as a repeat
        return cast(list[bool], driver.execute_script(
            "return [...document.querySelectorAll('#runs tr[data-run-id=\"copy\"]')].map((tr) => !!tr.querySelector('.pill.repeat'))"))

    wait("the run listed twice, one copy marked", lambda: sorted(copy_rows()) == [False, True])
    marked = driver.execute_script("return document.querySelectorAll('#runs .pill.repeat').length")
    assert marked == 1, marked

    out = ROOT / "out"
    out.mkdir(exist_ok=True)
    for path in (out / "dashboard.png", tmp_path / "dashboard.png"):
        assert driver.save_screenshot(str(path)), path

    logs = driver.get_log("browser")
    bad = [entry for entry in logs if entry.get("level") in ("SEVERE", "WARNING")]
    assert not bad, "browser console:\n" + "\n".join(f"{e['level']}: {e['message']}" for e in bad)
