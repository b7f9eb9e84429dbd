"""`shocktwin serve` exposed: TLS on both listeners (rustls), client certificates for
vehicles on the ingest listener (mTLS), bearer tokens with two roles on the HTTP API,
and the refusal to start off loopback without them unless ``--insecure``.

Certificates are made in the test (trustme: a server CA and a vehicles' CA); the clients
are real and independent of the daemon: httpx over HTTPS, Python's ssl with the mcap
writer for the ingest stream."""

from __future__ import annotations

import json
import secrets
import socket
import ssl
import subprocess
import sys
import time
from pathlib import Path
from typing import IO, Any, Iterator, cast

import httpx
import pytest
import trustme
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from conftest import ServeProcess

ROOT = Path(__file__).resolve().parents[2]
BIN = ROOT / "target" / "release" / "shocktwin"
BUNDLE = ROOT / "crates" / "dt-core" / "tests" / "fixtures" / "bundle-mlp13"

sys.path.insert(0, str(ROOT))
from train.demo_serve import SocketStream, copy_log  # noqa: E402

sys.path.remove(str(ROOT))


class Pki:
    def __init__(self, root: Path) -> None:
        self.server_ca = trustme.CA()
        self.vehicle_ca = trustme.CA()
        server = self.server_ca.issue_cert("127.0.0.1", "localhost")
        self.vehicle = self.vehicle_ca.issue_cert("vehicle-1.fleet.example")
        self.stranger = trustme.CA().issue_cert("stranger.example")  # signed by an unknown CA
        self.ca_pem = root / "server-ca.pem"
        self.server_ca.cert_pem.write_to_path(str(self.ca_pem))
        self.cert = root / "server.pem"
        self.key = root / "server.key"
        server.cert_chain_pems[0].write_to_path(str(self.cert))
        server.private_key_pem.write_to_path(str(self.key))
        self.client_ca = root / "vehicle-ca.pem"
        self.vehicle_ca.cert_pem.write_to_path(str(self.client_ca))


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("tls")
    pki = Pki(root)
    read, ingest = "r-" + secrets.token_hex(16), "i-" + secrets.token_hex(16)
    (root / "read.tokens").write_text(f"# dashboard\n{read}\n")
    (root / "ingest.tokens").write_text(f"{ingest}\n")
    config = root / "shocktwin.toml"
    config.write_text(
        f'[tls]\ncert = "{pki.cert}"\nkey = "{pki.key}"\nclient_ca = "{pki.client_ca}"\n'
        f'[auth]\nread_tokens_file = "{root / "read.tokens"}"\ningest_tokens_file = "{root / "ingest.tokens"}"\n'
        "[limits]\nidle_timeout_s = 120.0\n"
    )
    sim = root / "sim"
    done = subprocess.run([str(BIN), "simulate", "--quick", "--pressures", "7", "--frequencies", "2", "--out", str(sim)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return {"root": root, "pki": pki, "read": read, "ingest": ingest, "config": config,
            "run": next(sim.glob("*.mcap"))}


@pytest.fixture(scope="module")
def daemon(setup: dict[str, Any]) -> Iterator[ServeProcess]:
    d = ServeProcess([str(BIN), "serve", "--config", str(setup["config"]), "--listen", "127.0.0.1:0",
                      "--http", "127.0.0.1:0", "--model", str(BUNDLE), "--no-db"])
    yield d
    assert d.stop() == 0, d.text()
    # Tokens are never logged.
    assert setup["read"] not in d.text() and setup["ingest"] not in d.text()


def client(setup: dict[str, Any]) -> httpx.Client:
    return httpx.Client(verify=ssl.create_default_context(cafile=str(setup["pki"].ca_pem)), timeout=20)


def test_https_api_needs_a_read_token(daemon: ServeProcess, setup: dict[str, Any]) -> None:
    base = f"https://{daemon.http}"
    with client(setup) as http:
        assert http.get(f"{base}/healthz").status_code == 200
        assert http.get(f"{base}/").status_code == 200  # the dashboard page: no fleet data
        for path in ["/v1/assets", "/metrics", "/readyz", "/v1/events"]:
            r = http.get(f"{base}{path}")
            assert r.status_code == 401, path
            assert r.headers["www-authenticate"].startswith("Bearer")
            assert "a bearer token is needed" in r.text, r.text
        r = http.get(f"{base}/v1/assets", headers={"Authorization": "Bearer not-a-token"})
        assert r.status_code == 401 and "invalid_token" in r.headers["www-authenticate"]
        assert "not one of the daemon's" in r.text, r.text  # told apart from no token at all
        assert http.get(f"{base}/v1/assets", headers={"Authorization": f"Bearer {setup['ingest']}"}).status_code == 403
        ok = http.get(f"{base}/v1/assets", headers={"Authorization": f"Bearer {setup['read']}"})
        assert ok.status_code == 200 and "assets" in ok.json()
        assert http.get(f"{base}/metrics", params={"access_token": setup["read"]}).status_code == 200
    # Each refusal is logged with the peer, method and path (for an operator or fail2ban);
    # the token never is (the fixture checks the whole log).
    log = daemon.text()
    for why in ["HTTP 401: no token", "HTTP 401: an unknown token", "HTTP 403: an ingest token on a read route"]:
        line = next((l for l in log.splitlines() if why in l and "/v1/assets" in l), None)
        assert line is not None and "peer=127.0.0.1:" in line and "method=GET" in line, (why, log[-3000:])
    assert "not-a-token" not in log
    # Plain HTTP on the TLS port gets nothing.
    with pytest.raises(httpx.HTTPError):
        httpx.get(f"http://{daemon.http}/healthz", timeout=5)


def stream_tls(addr: str, run: Path, context: ssl.SSLContext, asset_id: str) -> dict[str, Any]:
    host, port = addr.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=60) as raw:
        with context.wrap_socket(raw, server_hostname="localhost") as sock, open(run, "rb") as fh:
            writer = Writer(cast(IO[bytes], SocketStream(cast(socket.socket, sock))), compression=CompressionType.ZSTD,
                            chunk_size=4096)
            writer.start(profile="", library="shocktwin test client (python ssl + mcap)")
            copy_log(make_reader(fh), writer, {"asset_id": asset_id, "run_id": "tls-run"})
            writer.finish()
            reply = b""
            while chunk := sock.recv(65536):
                reply += chunk
    return json.loads(reply.decode().strip())


def test_vehicles_stream_over_mtls(daemon: ServeProcess, setup: dict[str, Any]) -> None:
    pki = setup["pki"]
    vehicle = ssl.create_default_context(cafile=str(pki.ca_pem))
    pki.vehicle.configure_cert(vehicle)
    # The client sends its file and waits, without a half-close (Python's `ssl` has none): the
    # file's footer completes the run (it waited for the idle timeout and ended `failed`).
    report = stream_tls(daemon.listen, setup["run"], vehicle, "tls-unit-1")
    assert report["status"] == "completed" and report["ticks"] > 1000, report

    # A client without a certificate, or with one from an unknown CA, is refused at the handshake.
    for name, ctx in [("no certificate", ssl.create_default_context(cafile=str(pki.ca_pem))),
                      ("unknown CA", ssl.create_default_context(cafile=str(pki.ca_pem)))]:
        if name == "unknown CA":
            pki.stranger.configure_cert(ctx)
        with pytest.raises((ssl.SSLError, ConnectionError, json.JSONDecodeError)):
            stream_tls(daemon.listen, setup["run"], ctx, "intruder")

    with client(setup) as http:
        assets = http.get(f"https://{daemon.http}/v1/assets",
                          headers={"Authorization": f"Bearer {setup['read']}"}).json()["assets"]
    ids = {a["asset_id"] for a in assets}
    assert "tls-unit-1" in ids and "intruder" not in ids
    assert "TLS handshake failed" in daemon.text()


def test_refuses_to_expose_without_tls_unless_insecure(tmp_path: Path) -> None:
    argv = [str(BIN), "serve", "--listen", "0.0.0.0:0", "--http", "127.0.0.1:0", "--no-db"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert "TLS" in done.stderr and "--insecure" in done.stderr and "0.0.0.0:" in done.stderr
    # a daemon that refuses to serve never said it was listening
    assert "listening" not in done.stderr, done.stderr
    d = ServeProcess([*argv, "--insecure"])
    try:
        for _ in range(100):  # the warning follows the listening line
            if "--insecure:" in d.text():
                break
            time.sleep(0.05)
        assert "--insecure:" in d.text() and "0.0.0.0:" in d.text()
    finally:
        assert d.stop() == 0


@pytest.mark.parametrize(("days_from_now", "said"), [(-3, "expired on"), (5, "expires on"), (None, None)],
                         ids=["expired", "near-its-end", "fine"])
def test_a_server_certificate_near_or_past_its_end_is_warned_of(setup: dict[str, Any], tmp_path: Path,
                                                                days_from_now: int | None, said: str | None) -> None:
    """An expired server certificate started without a word: every client's handshake then
    failed (a helper's trial). The daemon still starts (the operator tests a renewal with
    it up), but says so at start, naming the file; a certificate valid for months is not named."""
    import datetime

    pki = setup["pki"]
    now = datetime.datetime.now(datetime.timezone.utc)
    not_after = now + datetime.timedelta(days=days_from_now if days_from_now is not None else 200)
    leaf = pki.server_ca.issue_cert("127.0.0.1", not_before=now - datetime.timedelta(days=30), not_after=not_after)
    cert, key = tmp_path / "server.pem", tmp_path / "server.key"
    leaf.cert_chain_pems[0].write_to_path(str(cert))
    leaf.private_key_pem.write_to_path(str(key))
    config = tmp_path / "shocktwin.toml"
    config.write_text(f'[tls]\ncert = "{cert}"\nkey = "{key}"\n')
    d = ServeProcess([str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
                      "--model", str(BUNDLE), "--no-db"])
    try:
        warned = [line for line in d.log if "the server certificate" in line]
        if said is None:
            assert not warned, d.text()
        else:
            assert len(warned) == 1 and str(cert) in warned[0] and said in warned[0], d.text()
            assert f"{abs(days_from_now):.0f}." in warned[0] or f"{abs(days_from_now) - 1}." in warned[0], warned[0]
    finally:
        assert d.stop() == 0, d.text()


def test_a_token_file_others_can_read_is_warned_of(setup: dict[str, Any], tmp_path: Path) -> None:
    """A token file other users of the machine can read gives them its role: the daemon warns,
    naming the file and its mode, and says what to do; a file only its owner reads is not named.
    The tokens themselves are never logged."""
    shared, private = tmp_path / "shared.tokens", tmp_path / "private.tokens"
    shared.write_text(f"{setup['read']}\n")
    private.write_text(f"{setup['ingest']}\n")
    shared.chmod(0o644)
    private.chmod(0o600)
    pki = setup["pki"]
    config = tmp_path / "shocktwin.toml"
    config.write_text(f'[tls]\ncert = "{pki.cert}"\nkey = "{pki.key}"\nclient_ca = "{pki.client_ca}"\n'
                      f'[auth]\nread_tokens_file = "{shared}"\ningest_tokens_file = "{private}"\n')
    d = ServeProcess([str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
                      "--model", str(BUNDLE), "--no-db"])
    try:
        warned = [line for line in d.log if "can be read by other users" in line]
        assert len(warned) == 1 and str(shared) in warned[0] and "0644" in warned[0] and "chmod 600" in warned[0], d.text()
        assert str(private) not in d.text()
    finally:
        assert d.stop() == 0, d.text()
    assert setup["read"] not in d.text() and setup["ingest"] not in d.text()


def test_a_wrong_tls_or_token_file_is_named_for_what_it_is(setup: dict[str, Any], tmp_path: Path) -> None:
    """A helper's trial: a missing key file read "not a PEM private key: I/O error", a client CA
    that was a key file "no root trust anchors were provided", a missing token file had no
    `auth` context. Each now names the setting, the file and what is wrong with it; and the
    start-up line says what protects the listeners."""
    pki = setup["pki"]

    def refusal(tls: str, auth: str) -> str:
        config = tmp_path / "bad.toml"
        config.write_text(tls + auth)
        done = subprocess.run([str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http",
                               "127.0.0.1:0", "--model", str(BUNDLE), "--no-db"], capture_output=True, text=True,
                              timeout=60)
        assert done.returncode != 0, done.stderr
        return done.stderr

    tokens = f'[auth]\nread_tokens_file = "{setup["root"] / "read.tokens"}"\n'
    missing = tmp_path / "serverX.key"
    err = refusal(f'[tls]\ncert = "{pki.cert}"\nkey = "{missing}"\n', tokens)
    assert "`tls`" in err and "serverX.key" in err and "cannot read it" in err and "not a PEM" not in err, err
    err = refusal(f'[tls]\ncert = "{pki.cert}"\nkey = "{pki.key}"\nclient_ca = "{pki.key}"\n', tokens)
    assert "no CA certificate in the file" in err and str(pki.key) in err and "trust anchors" not in err, err
    err = refusal(f'[tls]\ncert = "{pki.cert}"\nkey = "{pki.key}"\n',
                  f'[auth]\nread_tokens_file = "{tmp_path / "nope.tokens"}"\n')
    assert "configuration `auth`" in err and "nope.tokens" in err, err
    # token files as operators get them wrong (another helper's trial): the header's `Bearer `
    # copied in (the real token then failed with 401), one token in both files (it had the read
    # role alone), a short token (accepted without a word)
    tls = f'[tls]\ncert = "{pki.cert}"\nkey = "{pki.key}"\n'
    bearer = tmp_path / "bearer.tokens"
    bearer.write_text("# dashboard\nBearer " + "x" * 32 + "\n")
    err = refusal(tls, f'[auth]\nread_tokens_file = "{bearer}"\n')
    assert "bearer.tokens:2: the line starts with `Bearer `" in err, err
    both = tmp_path / "both.tokens"
    both.write_text("y" * 32 + "\n")
    err = refusal(tls, f'[auth]\nread_tokens_file = "{both}"\ningest_tokens_file = "{both}"\n')
    assert "in both the read_tokens_file and the ingest_tokens_file" in err, err
    short = tmp_path / "short.tokens"
    short.write_text("abc12\n")
    short.chmod(0o600)
    d = ServeProcess([str(BIN), "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--model", str(BUNDLE),
                      "--no-db", "--config", str(_write(tmp_path / "short.toml", tls + f'[auth]\nread_tokens_file = "{short}"\n'))])
    try:
        assert any("a token of 5 characters is easy to guess" in line for line in d.log), d.text()
        assert "abc12" not in d.text()
    finally:
        assert d.stop() == 0, d.text()
    # a protected daemon says so when it starts
    d = ServeProcess([str(BIN), "serve", "--config", str(setup["config"]), "--listen", "127.0.0.1:0",
                      "--http", "127.0.0.1:0", "--model", str(BUNDLE), "--no-db"])
    try:
        line = next(line for line in d.log if "listening" in line)
        assert "tls=on" in line and "client_certificates=on" in line and "tokens=on" in line, line
    finally:
        assert d.stop() == 0, d.text()


def test_runs_upload_over_https_with_the_ingest_role(daemon: ServeProcess, setup: dict[str, Any]) -> None:
    """`POST /v1/runs`: the body is a run's MCAP bytes, as on the TCP ingest; only the ingest
    role may upload, and the run then shows to the read role."""
    url = f"https://{daemon.http}/v1/runs"
    body = setup["run"].read_bytes()
    with client(setup) as http:
        assert http.post(url, content=body).status_code == 401
        assert http.post(url, content=body, headers={"Authorization": f"Bearer {setup['read']}"}).status_code == 403
        r = http.post(url, content=body, headers={"Authorization": f"Bearer {setup['ingest']}"})
        assert r.status_code == 200, r.text
        report = r.json()
        assert report["status"] == "completed" and report["ticks"] > 1000, report
        bad = http.post(url, content=b"not an mcap", headers={"Authorization": f"Bearer {setup['ingest']}"})
        assert bad.status_code == 422 and bad.json()["status"] == "failed", bad.text
        assets = http.get(f"https://{daemon.http}/v1/assets",
                          headers={"Authorization": f"Bearer {setup['read']}"}).json()["assets"]
    assert report["asset_id"] in {a["asset_id"] for a in assets}
    # The upload's source names its peer (it was "http upload" for every client).
    assert "source=http upload from 127.0.0.1:" in daemon.text(), daemon.text()[-3000:]
    assert "HTTP 403: a read token on an ingest route" in daemon.text()


def test_a_refused_upload_is_seen_over_http2(daemon: ServeProcess, setup: dict[str, Any]) -> None:
    """A client that sends its whole body before reading (httpx and curl over HTTP/2) sees
    the refusal of an upload that is refused before or while its body is read: the daemon
    reads the rest and drops it. Before, the stream was reset under the client (curl: exit 92,
    "Stream error in the HTTP/2 framing layer"; httpx waited for a flow-control window)."""
    url = f"https://{daemon.http}/v1/runs"
    body = setup["run"].read_bytes()
    cut = body[:100_000] + b"\0garbage" * 100_000  # a run that goes bad after 100 kB, 0.9 MB left
    ctx = ssl.create_default_context(cafile=str(setup["pki"].ca_pem))
    with httpx.Client(http2=True, verify=ctx, timeout=20) as http:
        r = http.post(url, content=body)
        assert (r.http_version, r.status_code) == ("HTTP/2", 401), r.text
        r = http.post(url, content=body, headers={"Authorization": f"Bearer {setup['read']}"})
        assert (r.http_version, r.status_code) == ("HTTP/2", 403), r.text
        r = http.post(url, content=cut, headers={"Authorization": f"Bearer {setup['ingest']}"})
        assert (r.http_version, r.status_code) == ("HTTP/2", 422), r.text
        assert r.json()["status"] == "failed" and r.json()["kind"] == "invalid_mcap", r.text
        # The connection is still good for the next request.
        ok = http.get(f"https://{daemon.http}/healthz")
        assert ok.status_code == 200


def test_baselines_are_set_with_the_ingest_role(daemon: ServeProcess, setup: dict[str, Any]) -> None:
    """`PUT /v1/assets/{id}/baseline` changes what the daemon computes: the ingest role's, as
    uploads are; the read role only sees it. This daemon's model (the paper's model 13) has
    no charge observer, so the baseline is refused with the reason."""
    url = f"https://{daemon.http}/v1/assets/van-07/baseline"
    body = {"charge_bar": 12.0, "read_bar": 10.8, "read_sd_bar": 0.7}
    with client(setup) as http:
        assert http.put(url, json=body).status_code == 401
        assert http.put(url, json=body, headers={"Authorization": f"Bearer {setup['read']}"}).status_code == 403
        r = http.put(url, json=body, headers={"Authorization": f"Bearer {setup['ingest']}"})
        assert r.status_code == 409 and "observer" in r.json()["error"], r.text
        assert http.get(url, headers={"Authorization": f"Bearer {setup['read']}"}).status_code == 404
        assert http.delete(url, headers={"Authorization": f"Bearer {setup['read']}"}).status_code == 403


def test_silent_https_connections_are_bounded_and_closed(setup: dict[str, Any], tmp_path: Path) -> None:
    """Connections to the HTTPS API that finish their handshake and send no request (a helper
    trying the daemon as a gateway operator held 377 of them for minutes, until the daemon ran
    out of file descriptors and its ingest, inbox and API failed): at most
    `limits.max_http_connections` are held, one beyond them is closed at once, and a silent one
    is closed after `limits.first_data_timeout_s`; the API then answers again."""
    pki = setup["pki"]
    config = tmp_path / "shocktwin.toml"
    config.write_text(setup["config"].read_text().replace(
        "[limits]\n", "[limits]\nmax_http_connections = 3\nfirst_data_timeout_s = 2.0\nmax_connections = 1\n"))
    d = ServeProcess([str(BIN), "serve", "--config", str(config), "--listen", "127.0.0.1:0",
                      "--http", "127.0.0.1:0", "--model", str(BUNDLE), "--no-db"])
    try:
        host, port = d.http.rsplit(":", 1)
        context = ssl.create_default_context(cafile=str(pki.ca_pem))
        context.set_alpn_protocols(["http/1.1"])

        def silent() -> ssl.SSLSocket:
            sock = context.wrap_socket(socket.create_connection((host, int(port)), timeout=10),
                                       server_hostname="127.0.0.1")
            sock.settimeout(10)
            return sock

        held = [silent() for _ in range(3)]
        t0 = time.monotonic()
        with pytest.raises((ssl.SSLError, ConnectionError, OSError)):  # the fourth: closed at once
            silent().recv(1)
        assert time.monotonic() - t0 < 5
        for _ in range(50):  # the log's reader thread may lag
            if any("serving its limit of 3 connections" in line for line in d.log):
                break
            time.sleep(0.05)
        assert any("serving its limit of 3 connections" in line for line in d.log), d.text()
        for sock in held:  # closed by the daemon after first_data_timeout_s without a request
            try:
                assert sock.recv(1) == b""
            except (ssl.SSLError, ConnectionError):
                pass
        assert time.monotonic() - t0 < 8, "the silent connections were held past their timeout"
        for sock in held:
            sock.close()
        with client(setup) as http:
            assert http.get(f"https://{d.http}/healthz").status_code == 200
            # a failed HTTPS handshake (plain HTTP on the TLS port) is logged and counted: they
            # were dropped without a word, so an expired server certificate showed only at clients
            with pytest.raises(httpx.HTTPError):
                httpx.get(f"http://{d.http}/healthz", timeout=5)
            metrics = http.get(f"https://{d.http}/metrics", headers={"Authorization": f"Bearer {setup['read']}"}).text
            assert 'shocktwin_errors_total{kind="https_handshake"} 1' in metrics, metrics
        assert any("HTTPS: TLS handshake failed" in line for line in d.log), d.text()

        # The same on the TCP ingest: a vehicle with its certificate that sends nothing after its
        # handshake was held for the whole idle timeout (120 s), not first_data_timeout_s.
        vehicle = ssl.create_default_context(cafile=str(pki.ca_pem))
        pki.vehicle.configure_cert(vehicle)
        ihost, iport = d.listen.rsplit(":", 1)
        # beyond the ingest's max_connections (1 here), a TLS client is closed at once: a plain
        # `refused` line read to it as a broken handshake (WRONG_VERSION_NUMBER)
        with vehicle.wrap_socket(socket.create_connection((ihost, int(iport)), timeout=10),
                                 server_hostname="localhost"):
            with pytest.raises((ssl.SSLError, ConnectionError, OSError)) as refused:
                with vehicle.wrap_socket(socket.create_connection((ihost, int(iport)), timeout=10),
                                         server_hostname="localhost") as second:
                    second.recv(1)
            assert "WRONG_VERSION_NUMBER" not in str(refused.value), refused.value
        time.sleep(0.2)  # the first one's slot given back
        t1 = time.monotonic()
        with vehicle.wrap_socket(socket.create_connection((ihost, int(iport)), timeout=10),
                                 server_hostname="localhost") as sock:
            sock.settimeout(10)
            reply = b""
            try:
                while chunk := sock.recv(65536):
                    reply += chunk
            except (ssl.SSLError, ConnectionError):
                pass
        assert time.monotonic() - t1 < 6, "a silent vehicle was held past first_data_timeout_s"
        assert reply == b"", reply  # closed as a silent plain connection is, not a failed run
        for _ in range(50):
            if any("nothing sent within" in line and "TLS handshake" in line for line in d.log):
                break
            time.sleep(0.05)
        assert any("nothing sent within" in line and "TLS handshake" in line for line in d.log), d.text()
    finally:
        assert d.stop() == 0, d.text()


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path
