"""Throughput of the NATS worker group, one worker beside two (a bench, minutes).

For each worker count, on a fresh `nats-server` (JetStream, file storage, loopback):
the workers start and share the partitions, then `shocktwin publish` sends N copies
of one simulated run (N assets) as fast as it can; the time from the publish's start
until every run's `ended` event is in the estimate stream gives the group's throughput in ticks per second, and ÷ 50 Hz its capacity in real-time
assets. Both counts run in one invocation, side by side, on the same machine
(the NATS server and the workers share its cores). Simulated data.

    .venv/bin/python benches/nats_scale.py [--assets 200] [--workers 1,2]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "python"))
from conftest import NatsServer, ServeProcess  # noqa: E402  (the tests' real-server helpers)

BIN = ROOT / "target" / "release" / "shocktwin"
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"


async def _ended(url: str) -> dict[str, int]:
    import nats

    nc = await nats.connect(url)
    js = nc.jetstream()
    out: dict[str, int] = {}
    try:
        info = await js.stream_info("SHOCKTWIN_ESTIMATES", subjects_filter="shocktwin.run.*")
        total = sum((info.state.subjects or {}).values())
        if total:
            sub = await js.pull_subscribe("shocktwin.run.*", stream="SHOCKTWIN_ESTIMATES")
            got = 0
            while got < total:
                msgs = await sub.fetch(min(500, total - got), timeout=5)
                for m in msgs:
                    ev = json.loads(m.data)
                    if ev["event"] == "ended":
                        out[ev["asset_id"]] = int(ev.get("ticks") or 0)
                got += len(msgs)
    finally:
        await nc.close()
    return out


def measure(run: Path, assets: int, workers: int, work: Path) -> dict[str, float]:
    server = NatsServer(work)
    procs: list[ServeProcess] = []
    try:
        procs = [ServeProcess([str(BIN), "serve", "--nats", server.url, "--model", str(BUNDLE), "--listen",
                               "127.0.0.1:0", "--http", "127.0.0.1:0", "--no-db"]) for _ in range(workers)]
        # Wait until the workers share the partitions evenly (leases settle).
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            held = [p.text().count("partition taken") - p.text().count("handed over") for p in procs]
            if sum(held) == 16 and max(held) - min(held) <= 1:
                break
            time.sleep(0.25)
        t0 = time.monotonic()
        pub = subprocess.run([str(BIN), "publish", "--nats", server.url, "--rename-assets", "scale-",
                              *[str(run)] * assets], capture_output=True, text=True, timeout=1200)
        if pub.returncode != 0:
            raise SystemExit(pub.stderr)
        while True:
            ended = asyncio.run(_ended(server.url))
            if len(ended) >= assets:
                break
            if time.monotonic() - t0 > 1800:
                raise SystemExit(f"{workers} worker(s): only {len(ended)} of {assets} runs ended in 30 min")
            time.sleep(0.5)
        wall = time.monotonic() - t0
        ticks = sum(ended.values())
        return {"workers": workers, "assets": assets, "ticks": ticks, "wall_s": wall,
                "ticks_per_s": ticks / wall, "realtime_assets": ticks / wall / 50.0}
    finally:
        for p in procs:
            p.stop()
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--assets", type=int, default=200)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--out", type=Path, default=ROOT / "target" / "nats-scale.json")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sim = Path(tmp) / "sim"
        subprocess.run([str(BIN), "simulate", "--quick", "--pressures", "12", "--frequencies", "2", "--out", str(sim)],
                       check=True, capture_output=True, timeout=600)
        run = sorted(sim.glob("*.mcap"))[0]
        rows = []
        for k in (int(x) for x in args.workers.split(",")):
            work = Path(tmp) / f"w{k}"
            work.mkdir()
            rows.append(measure(run, args.assets, k, work))
            r = rows[-1]
            print(f"{k} worker(s): {r['ticks']:.0f} ticks of {args.assets} assets in {r['wall_s']:.1f} s = "
                  f"{r['ticks_per_s']:.0f} ticks/s = {r['realtime_assets']:.0f} real-time assets (simulated data)",
                  flush=True)
    if len(rows) >= 2:
        print(f"ratio {rows[-1]['workers']:.0f} vs {rows[0]['workers']:.0f} workers: "
              f"{rows[-1]['ticks_per_s'] / rows[0]['ticks_per_s']:.2f}x")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
