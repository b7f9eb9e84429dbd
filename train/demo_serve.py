"""The daemon at work: stream a held-out leaking run through ``shocktwin serve``.

    python -m train.demo_serve --bin target/release/shocktwin --bundle BUNDLE --out DIR

1. Simulates one run the network never saw: a unit leaking down to ``--pressure`` bar
   (default 2 bar, below the 5 bar fault threshold; not a campaign pressure).
2. Starts ``shocktwin serve`` on loopback (ephemeral ports) with the bundle.
3. Streams the run into the daemon's TCP ingest with Python's ``mcap`` writer, as a
   vehicle gateway would (the messages re-encoded incrementally onto the socket), while
   listening to the daemon's Server-Sent Events for health changes.
   The leaking unit is another unit of the same model than the calibration's (``--unit``:
   seal friction, valves and mount scattered by a few per cent). Before its run, the
   maintainer reports a service at a known 12 bar charge (``PUT /v1/assets/{id}/service``)
   and the unit's next drive (simulated, full length, at 1 Hz, through the inbox) is read
   by the daemon itself into the unit's baseline.
4. Prints the verdict the daemon reached and when (seconds since the run's first
   message), what ``GET /v1/assets/{id}`` says, and the interval the model alone gives
   at the end of the run (the bindings, without the baseline) beside the daemon's.
5. The fleet's memory: before the live run, a small simulated fleet's past
   (``shocktwin simulate --days --leak-rate``: one run a day per van, one of them
   leaking) goes through the daemon's inbox into its store (``--db``); the trend
   of each van and its predicted crossing dates are printed, and the dashboard
   (``GET /``) is saved as ``dashboard.png`` by headless Chromium (when installed).
6. With ``--road``: a vehicle on roads. The daemon is started with the road calibration
   (``[model] road``) and that vehicle marked ``road = true``; the maintainer reports a
   service at a known charge (``PUT …/service``), the vehicle's drive at that charge goes
   through the inbox and the daemon reads it into the vehicle's road baseline (printed
   beside what ``shocktwin road --baseline`` reads from the same drive); then its held-out
   leaking road run goes through the inbox and the daemon's verdict, estimate and
   interval are printed (the road observer's, dt-core ``road``). A second road vehicle
   (``car-33``) has six days of drives behind it, losing 1 bar a day: a service before the
   first day gives its road baseline, and its leak rate and predicted fault date are printed.
The data are simulated.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any, Sequence, cast

import httpx
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from train.binary import find_shocktwin

ANSI = re.compile(r"\x1b\[[0-9;]*m")


class SocketStream:
    """A write-only, counting file over a socket (the mcap writer asks for ``tell``)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.pos = 0

    def write(self, data: bytes) -> int:
        self.sock.sendall(data)
        self.pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass


# The demo fleet's past: (asset id, charge lost per day in bar); one 1 Hz quick run a day.
FLEET = (("van-07", 0.6), ("van-12", 0.0), ("van-03", 0.25))
FLEET_DAYS = 10


def start_daemon(binary: str, bundle: Path, record_dir: Path,
                 inbox: Path | None = None, config: Path | None = None) -> tuple[subprocess.Popen[str], str, str]:
    cmd = [binary, "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--model", str(bundle),
           "--record-dir", str(record_dir), "--db", str(record_dir.parent / "fleet.sqlite")]
    if inbox is not None:
        cmd += ["--inbox", str(inbox)]
    if config is not None:
        cmd += ["--config", str(config)]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        line = ANSI.sub("", proc.stderr.readline())
        if not line and proc.poll() is not None:
            raise RuntimeError(f"shocktwin serve exited with {proc.returncode}")
        m = re.search(r"listen=(\S+).*http=(\S+)", line)
        if m:
            # Keep draining the daemon's log so that it never blocks on a full pipe.
            threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()  # type: ignore[union-attr]
            # Ready before dropping files: `/readyz` is 200 once the inbox is watched, so that a
            # file renamed into it is taken at once (one renamed before would settle first, 10 s).
            while httpx.get(f"http://{m.group(2)}/readyz", timeout=10).status_code != 200:
                if time.monotonic() > deadline or proc.poll() is not None:
                    proc.kill()
                    raise RuntimeError("shocktwin serve did not become ready")
                time.sleep(0.1)
            return proc, m.group(1), m.group(2)
    proc.kill()
    raise RuntimeError("shocktwin serve did not report its addresses")


def watch_events(http: str, asset_id: str, events: list[dict[str, Any]], ready: threading.Event) -> None:
    with httpx.Client(timeout=None) as client, client.stream("GET", f"http://{http}/v1/events") as resp:
        ready.set()
        name = None
        for line in resp.iter_lines():
            if line.startswith("event:"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("data:") and name == "lagged":
                # The daemon's event buffer overflowed for this slow reader: events were skipped.
                events.append({"event": "lagged", "skipped": int(line.split(":", 1)[1])})
            elif line.startswith("data:") and name in ("health", "run"):
                data = json.loads(line.split(":", 1)[1])
                if data.get("asset_id") == asset_id:
                    events.append({"event": name, **data})
                    if name == "run" and data.get("status") != "started":
                        return


def copy_log(reader: Any, writer: Writer, run_meta: dict[str, str] | None = None) -> int:
    """Re-encodes every metadata record and message of ``reader`` (an mcap reader) with
    ``writer`` (started, not finished), in log-time order; ``run_meta`` updates the
    ``shocktwin.run`` record. Returns the messages written."""
    for meta in reader.iter_metadata():
        data = dict(meta.metadata)
        if meta.name == "shocktwin.run" and run_meta:
            data.update(run_meta)
        writer.add_metadata(meta.name, data)
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    sent = 0
    for schema, channel, message in reader.iter_messages(log_time_order=True):
        if schema is not None and schema.id not in schemas:
            schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
        if channel.id not in channels:
            channels[channel.id] = writer.register_channel(
                channel.topic, channel.message_encoding, schemas.get(channel.schema_id, 0))
        writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                           message.sequence)
        sent += 1
    return sent


def stream_run(addr: str, path: Path) -> dict[str, Any]:
    host, port = addr.rsplit(":", 1)
    with socket.create_connection((host, int(port))) as sock, open(path, "rb") as fh:
        reader = make_reader(fh)
        out = SocketStream(sock)
        writer = Writer(cast(IO[bytes], out), compression=CompressionType.ZSTD, chunk_size=64 * 1024)
        writer.start(profile="", library="shocktwin demo client (python mcap)")
        copy_log(reader, writer)
        writer.finish()
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    return json.loads(reply.decode().strip().splitlines()[-1])


def print_convergence(record_dir: Path, t0_ns: int | None, every_s: float = 10.0, run_id: str = "*") -> None:
    """The daemon's recorded ``/estimate`` stream of ``run_id`` every ``every_s`` seconds: the 1 s
    average, the 95 % interval (SPEC §2a) and the health — how the estimate converges."""
    records = sorted(record_dir.rglob(f"{run_id}.*.mcap"))
    if not records or t0_ns is None:
        return
    rows: list[tuple[float, dict[str, Any]]] = []
    with open(records[-1], "rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages(topics=["/estimate"]):
            rows.append(((message.log_time - t0_ns) * 1e-9, json.loads(message.data)))
    if not rows:
        return
    print("  t (s)   1 s avg (bar)   95 % interval (bar)   health   [daemon's /estimate record]")
    nxt = every_s
    for t, e in rows:
        if t < nxt and (t, e) != rows[-1]:
            continue
        nxt = t + every_s

        def num(key: str) -> str:
            v = e.get(key)
            return "   –  " if v is None else f"{v:6.2f}"
        print(f"  {t:5.0f}   {num('pressure_avg_bar')}          [{num('pressure_lo_bar')}, {num('pressure_hi_bar')}]"
              f"      {e.get('health')}")


def simulate_fleet(binary: str, staging: Path) -> list[Path]:
    """Writes the demo fleet's past runs into ``staging`` (for :func:`drop_into`); returns them."""
    staging.mkdir(parents=True, exist_ok=True)
    for asset, leak in FLEET:
        subprocess.run([binary, "simulate", "--quick", "--days", str(FLEET_DAYS), "--leak-rate", f"{leak:g}",
                        "--frequencies", "1", "--asset-id", asset, "--out", str(staging / asset)],
                       check=True, stdout=subprocess.DEVNULL)
        for f in (staging / asset).glob("*.mcap"):
            f.rename(staging / f"{asset}-{f.name}")
        (staging / asset).rmdir()
    return sorted(staging.glob("*.mcap"))


def drop_into(inbox: Path, src: Path, name: str | None = None, move: bool = False) -> None:
    """``src`` into the daemon's inbox as its documentation asks of an uploader: written under
    another name, then renamed (``move``: renamed from where it is, on the same file system). A
    file renamed into the inbox is taken at once; one written in place waits until it has
    settled (``inbox_settle_s``, 10 s)."""
    dest = inbox / (name or src.name)
    if move:
        os.replace(src, dest)
        return
    part = dest.with_name(dest.name + ".part")
    shutil.copyfile(src, part)
    os.replace(part, dest)


ROAD_VEHICLE = "car-21"
# A road vehicle in service (simulated): asset, charge on day 0 (bar), leak (bar/day), days.
ROAD_HISTORY = ("car-33", 11.0, 1.0, 6)


def road_config(binary: str, road: Path, run: Path, baseline: str, out: Path) -> tuple[Path, Path, Path, str]:
    """The daemon's configuration for a vehicle on roads (``ROAD_VEHICLE``, ``road = true``, no
    baseline yet), its road run and its drive at a known charge written again under that
    vehicle's name, and the ``road_baseline`` line ``shocktwin road --baseline`` reads from that
    drive (what the daemon should read itself after the service)."""
    proc = subprocess.run([binary, "road", "--calibration", str(road), "--baseline", baseline, str(run)],
                          capture_output=True, text=True, check=True)
    line = re.search(r"road_baseline = \{.*\}", proc.stderr)
    if line is None:
        raise RuntimeError(f"shocktwin road --baseline printed no road_baseline line: {proc.stderr}")
    out.mkdir(parents=True, exist_ok=True)
    config = out / "serve.toml"
    config.write_text(f'[model]\nroad = "{road.resolve()}"\n\n[assets.{ROAD_VEHICLE}]\nroad = true\n\n'
                      f'[assets.{ROAD_HISTORY[0]}]\nroad = true\n')
    renamed = []
    for src_path in (run, Path(baseline.rsplit("@", 1)[0])):
        dst_path = out / f"{ROAD_VEHICLE}-{src_path.name}"
        with open(src_path, "rb") as src, open(dst_path, "wb") as dst:
            writer = Writer(dst, compression=CompressionType.ZSTD)
            writer.start(profile="", library="shocktwin demo")
            copy_log(make_reader(src), writer, {"asset_id": ROAD_VEHICLE})
            writer.finish()
        renamed.append(dst_path)
    print(f"vehicle on roads: {ROAD_VEHICLE}, `road = true`, no baseline yet")
    return config, renamed[0], renamed[1], line.group(0)


def road_service(http: str, asset: str, drive: Path, charge_bar: float, inbox: Path,
                 expected: str | None = None) -> dict[str, Any]:
    """A service of the road vehicle ``asset`` at ``charge_bar`` reported to the daemon, then
    its drive at that charge dropped into the inbox: the road baseline the daemon read from it."""
    url = f"http://{http}/v1/assets/{asset}"
    with open(drive, "rb") as fh:
        first_s = next(m for _, _, m in make_reader(fh).iter_messages(log_time_order=True)).log_time * 1e-9
    r = httpx.put(f"{url}/service", json={"charge_bar": charge_bar, "at": f"{first_s - 600.0:.3f}"}, timeout=30)
    r.raise_for_status()
    print(f"service of {asset} reported at {charge_bar:g} bar; its next drive ({drive.name}) goes through the inbox ...")
    drop_into(inbox, drive)
    base = read_baseline(url, drive)
    also = f"; `shocktwin road --baseline` read {expected}" if expected else ""
    print(f"road baseline of {asset}, read by the daemon from that drive (simulated): the seal "
          f"{base['offset_n']:+.3f} N from the calibration's over {base['blocks']} blocks (GET …/baseline: "
          f"kind {base['kind']}, source {base['source']}){also}")
    return base


def road_history(binary: str, http: str, inbox: Path, out: Path) -> None:
    """A road vehicle in service (``ROAD_HISTORY``, simulated: one quick drive a day, each its
    own drive file, the unit losing gas): a service before day 0, whose drive becomes its road
    baseline, then the other days through the inbox; prints its trend."""
    asset, start_bar, leak, days = ROAD_HISTORY
    subprocess.run([binary, "simulate", "--quick", "--road", "60", "--days", str(days), "--leak-rate", f"{leak:g}",
                    "--start-bar", f"{start_bar:g}", "--asset-id", asset, "--seed", "5", "--out", str(out)],
                   check=True, stdout=subprocess.DEVNULL)
    files = sorted(out.glob("d*.mcap"))
    road_service(http, asset, files[0], start_bar, inbox)
    for f in files[1:]:
        drop_into(inbox, f, f"{asset}-{f.name}")
    deadline = time.monotonic() + SERVICE_TIMEOUT_S
    url = f"http://{http}/v1/assets/{asset}"
    while sum(r["status"] == "completed" for r in httpx.get(f"{url}/runs", timeout=10).json()["runs"]) < days:
        if time.monotonic() > deadline:
            raise SystemExit(f"the daemon did not read {asset}'s {days} drives within {SERVICE_TIMEOUT_S:.0f} s")
        time.sleep(0.5)
    tr = httpx.get(f"{url}/trend", timeout=10).json()
    a = httpx.get(url, timeout=10).json()
    head = (f"{asset} on roads ({days} daily drives, simulated; true leak {leak:g} bar/day from {start_bar:g} bar): "
            f"last drive {a['pressure_bar']:.2f} [{a['pressure_lo_bar']:.2f}, {a['pressure_hi_bar']:.2f}] bar "
            f"(true {start_bar - leak * (days - 1):g}), {a['health']}")
    if tr.get("status") != "ok":
        print(f"{head}; trend: {tr.get('reason')}")
        return
    fault = tr.get("fault") or {}
    when = (f"fault (5 bar) at {fault['t'][:16]} [{(fault.get('t_lo') or '?')[:16]} .. {(fault.get('t_hi') or 'open')[:16]}]"
            if fault.get("t") else (fault.get("reason") or "no prediction"))
    print(f"{head}; leak {tr['leak_rate_bar_per_day']:+.2f} bar/day [{tr['leak_rate_lo_bar_per_day']:+.2f}, "
          f"{tr['leak_rate_hi_bar_per_day']:+.2f}]; {when}")


def wait_road(http: str, asset: str, run: Path, inbox: Path, timeout_s: float = 300.0) -> dict[str, Any]:
    """Drops the road run into the inbox; the daemon's view of the vehicle once that run is read."""
    with open(run, "rb") as fh:
        run_id = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["shocktwin.run"]["run_id"]
    drop_into(inbox, run)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        r = httpx.get(f"http://{http}/v1/assets/{asset}/runs", timeout=10)
        if r.status_code == 200 and any(x["run_id"] == run_id and x["status"] == "completed" for x in r.json()["runs"]):
            return cast(dict[str, Any], httpx.get(f"http://{http}/v1/assets/{asset}", timeout=10).json())
        time.sleep(0.5)
    raise RuntimeError(f"the daemon did not read the road run {run.name} in {timeout_s:.0f} s")


def wait_fleet(http: str, n_runs: int, timeout_s: float = 600.0) -> None:
    """Until the store holds ``n_runs`` completed runs of the fleet."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        done = 0
        for asset, _ in FLEET:
            r = httpx.get(f"http://{http}/v1/assets/{asset}/runs", timeout=10)
            if r.status_code == 200:
                done += sum(run["status"] == "completed" for run in r.json()["runs"])
        if done >= n_runs:
            time.sleep(1.0)  # the trends follow the last commit
            return
        time.sleep(1.0)
    raise RuntimeError(f"the daemon did not process the fleet's {n_runs} runs in {timeout_s:.0f} s")


def print_fleet(http: str) -> None:
    """The fleet as the maintainer sees it: leak rate and predicted crossings per van."""
    assets = httpx.get(f"http://{http}/v1/assets", timeout=10).json()["assets"]
    print("fleet memory (simulated data; one quick 1 Hz run a day per van, true leak in brackets):")
    truth = dict(FLEET)
    for a in assets:
        tr = a.get("trend") or {}
        name = a["asset_id"]
        true = f" [true {truth[name]:g} bar/day]" if name in truth else ""
        if tr.get("status") != "ok":
            print(f"  {name:12s} {tr.get('reason') or 'no trend'}")
            continue
        rate = tr["leak_rate_bar_per_day"]
        lo, hi = tr["leak_rate_lo_bar_per_day"], tr["leak_rate_hi_bar_per_day"]
        fault = tr.get("fault") or {}
        when = (f"fault at {fault['t'][:10]} [{(fault.get('t_lo') or '?')[:10]} .. {(fault.get('t_hi') or 'open')[:10]}]"
                if fault.get("t") else (fault.get("reason") or "no prediction"))
        print(f"  {name:12s} leak {rate:+.2f} bar/day [{lo:+.2f}, {hi:+.2f}]{true}; {when}")


def screenshot(url: str, path: Path, select: str | None = None) -> bool:
    """Saves the dashboard at ``url`` as seen by headless Chromium, with asset ``select``
    selected; False if Chromium is not installed."""
    chromium, driver_bin = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
    if not (chromium.exists() and driver_bin.exists()):
        print("dashboard screenshot skipped: chromium and chromedriver are needed "
              "(sudo apt-get install chromium chromium-driver)")
        return False
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(chromium)
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1400,1300"):
        options.add_argument(arg)
    drv = webdriver.Chrome(service=Service(executable_path=str(driver_bin)), options=options)
    try:
        drv.get(url)
        time.sleep(3.0)  # the page's first fetches and charts
        if select is not None:
            from selenium.webdriver.common.by import By

            rows = drv.find_elements(By.CSS_SELECTOR, f'tr[data-asset-id="{select}"]')
            if rows:
                rows[0].click()
                time.sleep(2.0)
        return bool(drv.save_screenshot(str(path)))
    finally:
        drv.quit()


SERVICE_CHARGE_BAR = 12.0


SERVICE_TIMEOUT_S = 600.0


def service_baseline(binary: str, bundle: Path, unit: int, http: str, asset_id: str, out: Path,
                     inbox: Path) -> dict[str, Any] | None:
    """A service at the known ``SERVICE_CHARGE_BAR`` reported to the daemon, and the unit's
    next drive (simulated) dropped into its inbox: the baseline the daemon read from it, or
    None when the bundle does not read the charge observer."""
    physics = json.loads((bundle / "twin.json").read_text())["physics"]
    if not physics.get("observer"):
        return None
    url = f"http://{http}/v1/assets/{asset_id}"
    subprocess.run([binary, "simulate", "--pressures", f"{SERVICE_CHARGE_BAR:g}", "--frequencies", "1",
                    "--seed", "8", "--unit", str(unit), "--out", str(out)], check=True, stdout=subprocess.DEVNULL)
    drive = sorted(out.glob("*.mcap"))[0]
    with open(drive, "rb") as fh:
        first_s = next(m for _, _, m in make_reader(fh).iter_messages(log_time_order=True)).log_time * 1e-9
    # serviced ten minutes before the drive (the simulator's clock); runs recorded before are not read
    body = {"charge_bar": SERVICE_CHARGE_BAR, "at": f"{first_s - 600.0:.3f}"}
    r = httpx.put(f"{url}/service", json=body, timeout=30)
    r.raise_for_status()
    print(f"service reported: PUT /v1/assets/{asset_id}/service {{\"charge_bar\": {SERVICE_CHARGE_BAR:g}, \"at\": "
          f"\"{r.json()['set_at']}\"}} -> {r.status_code} ({r.json()['state']}); the unit's next drive goes through "
          "the inbox ...")
    drop_into(inbox, drive)
    return read_baseline(url, drive)


def read_baseline(url: str, drive: Path) -> dict[str, Any]:
    """The baseline the daemon reads from ``drive`` after a service reported at ``url``
    (``…/v1/assets/{id}``): waits for ``…/baseline``; stops the demo with the daemon's reason
    if the drive gave none, or after ``SERVICE_TIMEOUT_S``."""
    deadline = time.monotonic() + SERVICE_TIMEOUT_S
    while (b := httpx.get(f"{url}/baseline", timeout=10)).status_code != 200:
        pending = httpx.get(f"{url}/service", timeout=10)
        if pending.status_code == 200 and pending.json()["last_refusal"]:
            raise SystemExit(f"no baseline from {drive.name}: {pending.json()['last_refusal']}")
        if time.monotonic() > deadline:
            raise SystemExit(f"the daemon did not read {drive.name} within {SERVICE_TIMEOUT_S:.0f} s")
        time.sleep(0.5)
    return cast("dict[str, Any]", b.json())


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m train.demo_serve", description=__doc__.split("\n")[0])
    p.add_argument("--bin", default=None,
                   help="the shocktwin CLI (default: $SHOCKTWIN_BIN, else this workspace's "
                        "target/release/shocktwin, else shocktwin on PATH)")
    p.add_argument("--bundle", required=True, type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--pressure", type=float, default=2.0, help="charge pressure of the leaking unit (bar)")
    p.add_argument("--frequency", type=float, default=2.0)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--road", type=Path, help="road calibration (python -m train.road_observer fit)")
    p.add_argument("--road-run", type=Path, help="with --road: a vehicle's leaking road run")
    p.add_argument("--road-baseline", help="with --road: that vehicle's drive at a known charge, DRIVE.mcap@BAR")
    p.add_argument("--unit", type=int, default=11,
                   help="unit seed of the leaking unit (another unit of the same model; 0: the calibration's)")
    args = p.parse_args(argv)
    if args.road and not (args.road_run and args.road_baseline):
        p.error("--road needs --road-run and --road-baseline")
    if args.out.exists() and any(args.out.iterdir()):
        # The daemon would open the last demo's fleet store and inbox there and take the
        # drives dropped in again as runs it has read, so a service's baseline never comes.
        p.error(f"--out {args.out} is not empty (a demo ran there before): remove it or give another directory")
    try:
        args.bin = str(find_shocktwin(args.bin))
    except FileNotFoundError as e:
        p.error(str(e))

    run_dir = args.out / "run"
    unit = ["--unit", str(args.unit)] if args.unit else []
    subprocess.run([args.bin, "simulate", "--quick", "--pressures", f"{args.pressure:g}", "--frequencies",
                    f"{args.frequency:g}", "--seed", str(args.seed), *unit, "--out", str(run_dir)],
                   check=True, stdout=subprocess.DEVNULL)
    run_file = sorted(run_dir.glob("*.mcap"))[0]
    with open(run_file, "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["shocktwin.run"]
    asset_id = meta["asset_id"]
    print(f"streaming {run_file.name} (simulated: true charge {meta['charge_pressure_bar']} bar, "
          f"{meta['excitation']}) into shocktwin serve with {args.bundle}")

    inbox = args.out / "inbox"
    inbox.mkdir(parents=True, exist_ok=True)
    fleet = simulate_fleet(args.bin, args.out / "fleet")
    config = road_run = road_drive = None
    if args.road:
        config, road_run, road_drive, road_line = road_config(args.bin, args.road, args.road_run, args.road_baseline,
                                                              args.out / "road")
    proc, listen, http = start_daemon(args.bin, args.bundle, args.out / "records", inbox, config)
    try:
        print(f"the fleet's past: {len(fleet)} runs of {len(FLEET)} vans through the inbox into the store ...")
        for f in fleet:
            drop_into(inbox, f, move=True)
        wait_fleet(http, len(fleet))
        print_fleet(http)
        if road_run is not None and road_drive is not None:
            road_service(http, ROAD_VEHICLE, road_drive, float(args.road_baseline.rsplit("@", 1)[1]), inbox, road_line)
            with open(road_run, "rb") as fh:
                road_meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}["shocktwin.run"]
            v = wait_road(http, ROAD_VEHICLE, road_run, inbox)
            print(f"{ROAD_VEHICLE} on the road ({road_meta['excitation']}, true charge {road_meta['charge_pressure_bar']} bar, "
                  f"simulated): the daemon's road observer reads {v['pressure_bar']:.2f} bar "
                  f"[{v['pressure_lo_bar']:.2f}, {v['pressure_hi_bar']:.2f}], health {v['health']}")
            road_history(args.bin, http, inbox, args.out / "road-history")
        baseline = (service_baseline(args.bin, args.bundle, args.unit, http, asset_id, args.out / "service", inbox)
                    if args.unit else None)
        if baseline is not None:
            print(f"service baseline of {asset_id}, read by the daemon from its drive at a known "
                  f"{baseline['charge_bar']:g} bar (simulated): the observer read {baseline['read_bar']:.2f} ± "
                  f"{baseline['read_sd_bar']:.2f} bar (GET /v1/assets/{asset_id}/baseline: source "
                  f"{baseline['source']}, set at the service, {baseline['set_at']})")
        events: list[dict[str, Any]] = []
        ready = threading.Event()
        watcher = threading.Thread(target=watch_events, args=(http, asset_id, events, ready), daemon=True)
        watcher.start()
        ready.wait(10)
        started = time.perf_counter()
        report = stream_run(listen, run_file)
        watcher.join(10)
        detail = httpx.get(f"http://{http}/v1/assets/{asset_id}", timeout=10).json()
        wall = time.perf_counter() - started
        shot = args.out / "dashboard.png"
        leaking = max(FLEET, key=lambda a: a[1])[0]
        if screenshot(f"http://{http}/", shot, select=leaking):
            again = f" --config {config}" if config is not None else ""
            print(f"dashboard: http://{http}/ (saved as {shot}; to browse it again: "
                  f"{args.bin} serve --db {args.out / 'fleet.sqlite'} --model {args.bundle}{again}, "
                  "then open http://127.0.0.1:7411/)")
    finally:
        proc.terminate()
        proc.wait(30)

    t0_ns = None
    with open(run_file, "rb") as fh:
        for _, _, message in make_reader(fh).iter_messages(log_time_order=True):
            t0_ns = message.log_time
            break
    print(f"daemon: run {report.get('status')}, {report.get('samples')} samples, {report.get('ticks')} estimates "
          f"in {wall:.1f} s wall")
    skipped = sum(e["skipped"] for e in events if e["event"] == "lagged")
    if skipped:
        print(f"  (this reader lagged: the daemon skipped {skipped} live events for it; the verdict below is "
              "read from GET /v1/assets/{id})")
    changes = [e for e in events if e["event"] == "health"]
    for e in changes:
        print(f"  t = {(e['t_ns'] - t0_ns) * 1e-9:6.1f} s: health {e['from']} -> {e['to']}")
    verdict = detail.get("health")
    when = next((e for e in reversed(changes) if e["to"] == verdict), None)
    when_s = f"at t = {(when['t_ns'] - t0_ns) * 1e-9:.1f} s of the run" if when else "(no change event seen)"
    print(f"verdict for {asset_id}: {verdict} {when_s}; 1 s average "
          f"{detail.get('pressure_avg_bar') or float('nan'):.2f} bar against {detail.get('expected_bar')} bar nominal "
          f"(true charge {meta['charge_pressure_bar']} bar; simulated data)")
    print_convergence(args.out / "records" / asset_id, t0_ns, run_id=meta["run_id"])
    if baseline is not None:
        import shocktwin

        alone = shocktwin.estimate(run_file, args.bundle)
        print(f"at the end of the run: the daemon (with the baseline) [{detail.get('pressure_lo_bar') or float('nan'):.2f}, "
              f"{detail.get('pressure_hi_bar') or float('nan'):.2f}] bar, {verdict}; the model alone "
              f"[{alone['pressure_lo_bar'][-1]:.2f}, {alone['pressure_hi_bar'][-1]:.2f}] bar, {alone['health'][-1]} "
              "(shocktwin.estimate without observer_baseline)")
    (args.out / "verdict.json").write_text(json.dumps({"report": report, "health_changes": changes,
                                                         "baseline": baseline,
                                                         "asset": {k: v for k, v in detail.items() if k != "history"}},
                                                        indent=2) + "\n")
    return 0 if report.get("status") == "completed" else 1


if __name__ == "__main__":
    sys.exit(main())
