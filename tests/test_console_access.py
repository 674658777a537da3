"""Who may use the operator console: attacks on a real `dyknow console` process.

The console runs as the compose files' operator does (`dyknow console --config F`), in a
process of its own; the attacker is a plain HTTP client (`http.client`, every header
its own: a DNS-rebinding page sends ``Host`` and ``Origin`` of ``evil.example``, a local
process has no token). Each refusal is asserted with its status, its count in
``GET /api/stats`` and its record in the platform's audit file (``stage: "console"``).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import hmac
import http.client
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from federation import PlatformConfig
from federation._cli_app import app
from federation._local import _LINE, channel_path
from federation.console import (
    ALLOW_HOSTS_ENV,
    MAX_CLIENTS,
    MAX_CLIENTS_PER_ADDRESS,
    TOKEN_ENV,
    allowed_names,
    configured_token,
)
from federation.console._access import AUDIT_BURST, REPORT_INTERVAL, _client_key

ROOT = Path(__file__).resolve().parent.parent
WAIT = 20.0  # s: the bound on any single wait
IDLE = 3.0  # s a quick console gives a connection to send a whole request
ALLOWED = "operator.test"  # the config's console.allow_hosts


def write_operator(tmp_path: Path, console: str = "") -> Path:
    """A federation of its own with one platform, the operator, auditing to a file.

    ``console``: more lines of its ``[console]`` table.
    """
    fed = f"console{os.getpid()}x{time.monotonic_ns() % 10**6}"
    pub = gen_keys("operator", tmp_path / "keys")[2]
    trust_keys(tmp_path / "trust.json", [pub], federation=fed)
    (tmp_path / "vocabulary.toml").write_text(
        f'name = "{fed}"\n[labels]\n"heli-altitude" = "altitude, m"\n'
    )
    (tmp_path / "labels.toml").write_text(
        f'vocabulary = "{fed}"\n[labels]\n"heli-altitude" = "operator/alt"\n'
    )
    config = tmp_path / "operator.toml"
    config.write_text(
        f'name = "operator"\nfederation = "{fed}"\nkey = "keys/operator.key"\n'
        'trust = "trust.json"\nvocabulary = "vocabulary.toml"\nmapping = "labels.toml"\n'
        'audit = "audit.jsonl"\n\n'
        f'[console]\nallow_hosts = ["{ALLOWED}"]\n{console}\n'
        f'[transport]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{free_tcp_port()}"]\n'
    )
    return config


@dataclass
class Console:
    """A running `dyknow console`: its port, token, login URL and audit file."""

    proc: subprocess.Popen[str]
    port: int
    token: str
    login_url: str
    audit: Path

    def request(
        self,
        method: str,
        path: str,
        headers: dict[str, str] | None = None,
        body: Any = None,
        *,
        host: str | None = None,
    ) -> tuple[int, http.client.HTTPMessage, Any]:
        """One request with exactly these headers (``host``: the Host header; default ours)."""
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=WAIT)
        try:
            conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
            conn.putheader("Host", host if host is not None else f"127.0.0.1:{self.port}")
            data = b"" if body is None else json.dumps(body).encode()
            if body is not None:
                conn.putheader("Content-Type", "application/json")
            for k, v in (headers or {}).items():
                conn.putheader(k, v)
            conn.putheader("Content-Length", str(len(data)))
            conn.endheaders(data)
            r = conn.getresponse()
            raw = r.read()
            try:
                answer: Any = json.loads(raw)
            except ValueError:
                answer = raw.decode(errors="replace")
            return r.status, r.headers, answer
        finally:
            conn.close()

    def bearer(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def stats(self) -> dict[str, Any]:
        status, _, answer = self.request("GET", "/api/stats", self.bearer())
        assert status == 200, answer
        return dict(answer)

    def audit_records(self) -> list[dict[str, Any]]:
        if not self.audit.exists():
            return []
        lines = self.audit.read_text().splitlines()
        return [r for r in map(json.loads, lines) if r.get("stage") == "console"]

    def wait_audit(self, want: int) -> list[dict[str, Any]]:
        """The console's audit records once at least ``want`` are in the file."""
        deadline = time.monotonic() + WAIT
        while len(records := self.audit_records()) < want:
            if time.monotonic() > deadline:
                raise AssertionError(f"{len(records)} console audit records, wanted {want}")
            time.sleep(0.1)  # the audit file is written in batches: poll it
        return records


@pytest.fixture
def console(tmp_path: Path) -> Iterator[Console]:
    """`dyknow console --config operator.toml --port 0`, its token made at random."""
    yield from _console(write_operator(tmp_path), tmp_path)


@pytest.fixture
def quick_console(tmp_path: Path) -> Iterator[Console]:
    """The same console, closing a connection without a whole request after IDLE s."""
    yield from _console(write_operator(tmp_path, f"idle_timeout = {IDLE}"), tmp_path)


def _console(config: Path, tmp_path: Path) -> Iterator[Console]:
    """Run `dyknow console` with ``config`` until the test is done; it must stop cleanly."""
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
    proc = subprocess.Popen(
        [sys.executable, "-m", "federation.cli", "console", "--config", str(config), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**env, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        ready = proc.stdout.readline()  # bounded by the test's timeout
        m = re.search(r"ready in federation \S+: (http://127\.0\.0\.1:(\d+)/\?token=(\S+))", ready)
        assert m, (ready, proc.stderr.read() if proc.stderr else "")
        yield Console(proc, int(m[2]), m[3], m[1], tmp_path / "audit.jsonl")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WAIT)
        assert proc.returncode == 0 and "Traceback" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)


@pytest.mark.timeout(90)
def test_a_rebinding_page_a_local_process_and_a_foreign_page_are_refused(
    console: Console,
) -> None:
    c = console
    evil_host = f"evil.example:{c.port}"
    evil = {"Origin": f"http://evil.example:{c.port}"}
    policy = {"platform": "uav-a", "label": "tracked-cars", "sample_period": 60}
    seen = {"host": 0, "origin": 0, "no-token": 0, "bad-token": 0}

    def refused(kind: str, status: int, answer: Any, want: int) -> None:
        assert status == want and isinstance(answer, dict), (kind, status, answer)
        assert "platforms" not in answer and "error" in answer  # nothing of the state
        seen[kind] += 1

    # DNS rebinding: Host and Origin evil.example, reading the state, changing a policy
    # (with the token too: a name not ours is refused whoever asks)
    for path, body in (("/api/state", None), ("/api/policy", policy), ("/", None)):
        status, _, answer = c.request("POST" if body else "GET", path, evil, body, host=evil_host)
        refused("host", status, answer, 403)
        assert "Host" in answer["error"] and "--allow-host" in answer["error"]
    status, _, answer = c.request("GET", "/api/state", {**evil, **c.bearer()}, host=evil_host)
    refused("host", status, answer, 403)

    # a local process without the token
    for method, path, body in (
        ("GET", "/api/state", None),
        ("GET", "/api/events", None),
        ("POST", "/api/observation", {"x": 1, "y": 2, "text": "fake"}),
        ("POST", "/api/policy", policy),
    ):
        status, headers, answer = c.request(method, path, body=body)
        refused("no-token", status, answer, 401)
        assert headers["WWW-Authenticate"].startswith("Bearer")

    # a cookie is no credential: a browser sends a host's cookies to every port of it, so
    # any local server got the one the console used to set (and replayed it, no Origin)
    old = hmac.new(c.token.encode(), b"console-cookie", "sha256").hexdigest()
    for method, path, cookie, body in (
        ("GET", "/api/state", old, None),
        ("GET", "/api/events", old, None),
        ("POST", "/api/policy", old, policy),
        ("GET", "/api/state", c.token, None),
    ):
        jar = {"Cookie": f"dyknow_console_{c.port}={cookie}"}
        status, headers, answer = c.request(method, path, jar, body)
        refused("no-token", status, answer, 401)
        assert "cookie is not accepted" in answer["error"], answer

    # a wrong token: in the URL, as a Bearer, not a Bearer
    wrong = "w" * len(c.token)
    for path, headers in (
        (f"/?token={wrong}", {}),
        ("/api/state", {"Authorization": f"Bearer {wrong}"}),
        ("/api/state", {"Authorization": f"Basic {c.token}"}),
    ):
        status, _, answer = c.request("GET", path, headers)
        refused("bad-token", status, answer, 403)

    # the token with a foreign Origin (a page of another site that has it somehow)
    fake = {"x": 1, "y": 2, "text": "fake"}
    for path, body in (("/api/observation", fake), ("/api/state", None)):
        status, _, answer = c.request(
            "POST" if body else "GET", path, {**c.bearer(), "Origin": "http://evil.example"}, body
        )
        refused("origin", status, answer, 403)
        assert "Origin" in answer["error"]

    # the page and its files are the same for all and hold nothing of the state: no token
    # needed (a reload, once the page took the token out of its URL), never a cookie
    for path in ("/", "/static/app.js", f"/?token={c.token}"):
        status, headers, text = c.request("GET", path)
        assert status == 200 and "Set-Cookie" not in headers, (path, headers)
        assert isinstance(text, str) and c.token not in text  # a file, not the state (JSON)
    assert headers["Referrer-Policy"] == "no-referrer" and "no-store" in headers["Cache-Control"]
    status, _, js = c.request("GET", "/static/app.js")
    assert "sessionStorage" in js and "Authorization: `Bearer" in js and "EventSource(" not in js

    # the operator: the printed URL's token, as a Bearer (what the page sends)
    assert c.login_url == f"http://127.0.0.1:{c.port}/?token={c.token}"
    own = {"Origin": f"http://127.0.0.1:{c.port}"}
    for host in (f"127.0.0.1:{c.port}", f"localhost:{c.port}", f"[::1]:{c.port}", ALLOWED):
        status, _, state = c.request("GET", "/api/state", c.bearer(), host=host)
        assert status == 200 and state["operator"] == "operator", (host, state)
    status, _, answer = c.request(
        "POST", "/api/observation", {**c.bearer(), **own}, {"x": 1.0, "y": 2.0, "text": "mine"}
    )
    assert status == 200, answer
    status, _, state = c.request("GET", "/api/state", c.bearer())
    assert status == 200 and [o["text"] for o in state["observations"]] == ["mine"]

    # every refusal counted, and in the platform's audit with why
    stats = c.stats()
    assert stats["refused"] == seen and stats["refused_total"] == sum(seen.values()) == 17
    records = c.wait_audit(17)
    assert len(records) == 17 and stats["audited"] == 17
    assert [r["refusal"] for r in records] == (
        ["host"] * 4 + ["no-token"] * 8 + ["bad-token"] * 3 + ["origin"] * 2
    )
    for r in records:
        assert r["verdict"] == "refused" and r["platform"] == "operator"
        assert r["client"] == "127.0.0.1" and r["reason"] and r["ts"] > 0
        assert c.token not in json.dumps(r) and wrong not in json.dumps(r)  # no secret
    assert records[0]["host"] == evil_host and records[0]["origin"] == evil["Origin"]
    assert records[0]["path"] == "/api/state" and records[1]["method"] == "POST"


@pytest.mark.timeout(90)
def test_a_flood_of_bad_requests_is_counted_not_audited_one_by_one(console: Console) -> None:
    c = console
    flood = 300
    start = time.monotonic()
    conn = http.client.HTTPConnection("127.0.0.1", c.port, timeout=WAIT)
    try:
        for i in range(flood):  # one connection, kept alive: as fast as the console answers
            conn.request("GET", "/api/state", headers={"Authorization": f"Bearer guess{i:012d}"})
            r = conn.getresponse()
            r.read()
            assert r.status == 403
    finally:
        conn.close()
    elapsed = time.monotonic() - start
    stats = c.stats()
    assert stats["refused"]["bad-token"] == flood
    # a record each within the budget (a burst, then a few a second), the rest summed up
    budget = AUDIT_BURST + 2.0 * (elapsed + 1)
    assert AUDIT_BURST <= stats["audited"] <= budget, (stats, elapsed)
    deadline = time.monotonic() + REPORT_INTERVAL + WAIT
    while True:
        records = c.audit_records()
        summed = sum(r.get("count", 0) for r in records if "count" in r)
        single = sum(1 for r in records if "count" not in r)
        if single + summed == flood:
            break
        assert time.monotonic() < deadline, (single, summed, records[-1:])
        time.sleep(0.2)  # the summary comes within REPORT_INTERVAL s: poll the file
    assert single == stats["audited"] and len(records) <= budget + 2
    summary = next(r for r in records if "count" in r)
    assert summary["verdict"] == "refused" and "without a record each" in summary["reason"]


def _closed(sock: socket.socket) -> bool:
    """Whether the peer closed ``sock`` (what it answered first is read and dropped)."""
    sock.settimeout(0.0)
    try:
        while data := sock.recv(65536):
            del data
        return True
    except BlockingIOError:
        return False
    except OSError:  # reset
        return True


@pytest.mark.timeout(120)
def test_slow_and_silent_clients_cost_the_console_bounded_connections(
    quick_console: Console,
) -> None:
    # Anyone who can reach the port, no token: connections that start a request and never
    # finish it (slowloris). Each holds a file descriptor of the node's process; unbounded,
    # and kept for aiohttp's hour, they were the node's every descriptor (its sessions, its
    # audit file too). Now: MAX_CLIENTS at most, the next answered 503, each closed after
    # idle_timeout s without a whole request (15 s, `IDLE_TIMEOUT`; IDLE here, to be quick).
    c = quick_console
    held = []
    # from as many loopback addresses as one may hold its share each (Linux answers on all
    # of 127/8), the extra ones from one more: the bound in all, not one address's
    sources = MAX_CLIENTS // MAX_CLIENTS_PER_ADDRESS
    try:
        for i in range(MAX_CLIENTS):
            s = socket.create_connection(
                ("127.0.0.1", c.port),
                timeout=WAIT,
                source_address=(f"127.0.0.{i % sources + 2}", 0),
            )
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # never ended
            held.append(s)
        deadline = time.monotonic() + WAIT
        while True:  # once the console took the held ones in, one more is refused
            extra = socket.create_connection(
                ("127.0.0.1", c.port), timeout=0.5, source_address=(f"127.0.0.{sources + 2}", 0)
            )
            try:
                answer = extra.recv(4096)
            except TimeoutError:  # served: some held ones were still in the backlog
                held.append(extra)
            else:
                extra.close()
                if answer.startswith(b"HTTP/1.1 503"):
                    break
            assert time.monotonic() < deadline
        assert b"too many connections" in answer
        fds = len(os.listdir(f"/proc/{c.proc.pid}/fd"))
        assert fds < MAX_CLIENTS + 100, fds  # the held ones, and what the node had
        time.sleep(IDLE)  # none is closed before its idle time (the earliest opened first)
        deadline = time.monotonic() + IDLE + WAIT
        while still := [s for s in held if not _closed(s)]:
            assert time.monotonic() < deadline, f"{len(still)} of {len(held)} still open"
            time.sleep(0.2)  # no event to await from here: poll the sockets
    finally:
        for s in held:
            s.close()
    stats = c.stats()  # served again
    assert stats["busy"] >= 1 and stats["refused_total"] == 0, stats
    assert stats["busy_address"] == 0, stats


@pytest.mark.timeout(90)
def test_one_address_cannot_take_every_connection(console: Console) -> None:
    # One client address held MAX_CLIENTS connections, each unfinished: the console had
    # none left for anyone. Now MAX_CLIENTS_PER_ADDRESS of them, the next one refused,
    # while another address (127.0.0.2, a loopback address too) is still served.
    c = console
    held = []
    try:
        for _ in range(MAX_CLIENTS_PER_ADDRESS):
            s = socket.create_connection(("127.0.0.1", c.port), timeout=WAIT)
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # never ended
            held.append(s)
        deadline = time.monotonic() + WAIT
        while True:  # once the console took the held ones in, one more is refused
            extra = socket.create_connection(("127.0.0.1", c.port), timeout=0.5)
            try:
                answer = extra.recv(4096)
            except TimeoutError:  # served: some held ones were still in the backlog
                held.append(extra)
            else:
                extra.close()
                if answer.startswith(b"HTTP/1.1 503"):
                    break
            assert time.monotonic() < deadline
        assert b"too many connections open from this address" in answer
        assert len(held) == MAX_CLIENTS_PER_ADDRESS  # none of the held ones was refused
        with socket.create_connection(
            ("127.0.0.1", c.port), timeout=WAIT, source_address=("127.0.0.2", 0)
        ) as other:
            other.sendall(
                b"GET /api/stats HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
            )
            assert other.recv(4096).startswith(b"HTTP/1.1 401")  # served: asked for its token
    finally:
        for s in held:
            s.close()
    stats = c.stats()
    assert stats["busy_address"] >= 1 and stats["busy"] == 0, stats


@pytest.mark.timeout(60)
def test_malformed_requests_are_answered_400_without_a_traceback(console: Console) -> None:
    # the fixture's end asserts no traceback in the console's log: neither the outsider's
    # broken request (aiohttp logs it) nor the token holder's odd body (ours) leaves one
    c = console

    def raw(request: bytes) -> bytes:
        with socket.create_connection(("127.0.0.1", c.port), timeout=WAIT) as s:
            s.sendall(request)
            return s.recv(4096)

    host = f"Host: 127.0.0.1:{c.port}\r\n".encode()
    for _ in range(3):
        answer = raw(b"GET /api/state HTTP/1.1\r\n" + host + b"Host: evil.example\r\n\r\n")
        assert answer.startswith(b"HTTP/1.0 400") and b"Duplicate 'Host'" in answer, answer
    post = {**c.bearer(), "Content-Type": "application/json"}
    deep = b"[" * 100_000 + b"]" * 100_000
    for path, headers, body, want in [
        ("/api/query", post, deep, "body: JSON nested too deep"),
        ("/api/search", post, b'{"a":' * 50_000 + b"1" + b"}" * 50_000, "nested too deep"),
        (  # a formula the page passes on to every member: parsed here first
            "/api/search",
            post,
            json.dumps({"formula": "(not " * 5_000 + "(Car x)" + ")" * 5_000}).encode(),
            "nested deeper than 64",
        ),
        (
            "/api/observation",
            {**post, "Content-Type": "application/json; charset=bogus"},
            b"{}",
            "charset 'bogus'",
        ),
    ]:
        conn = http.client.HTTPConnection("127.0.0.1", c.port, timeout=WAIT)
        try:
            conn.request("POST", path, body=body, headers=headers)
            r = conn.getresponse()
            answer = json.loads(r.read())
        finally:
            conn.close()
        assert r.status == 400 and want in answer["error"], (path, r.status, answer)
    assert c.stats()["refused_total"] == 0


def test_an_unknown_endpoint_or_method_of_the_api_is_answered_in_json(console: Console) -> None:
    # docs/console.md, "HTTP API": every body is JSON, so a client reads one error shape
    c = console
    status, headers, answer = c.request("GET", "/api/nothing", c.bearer())
    assert status == 404 and answer == {"error": "path: no endpoint /api/nothing"}, answer
    assert headers["Content-Type"].startswith("application/json")
    status, headers, answer = c.request("GET", "/api/query", c.bearer())
    assert status == 405, answer
    assert answer == {"error": "method: GET is not one of /api/query's (POST)"}, answer
    assert headers["Allow"] == "POST"
    # without the token the same path is refused as any other of the API, naming nothing
    status, _, answer = c.request("GET", "/api/nothing")
    assert status == 401 and answer["error"].startswith("token: missing"), answer


@pytest.mark.timeout(60)
def test_an_overlong_request_on_the_local_channel_is_answered_not_a_traceback(
    console: Console, tmp_path: Path
) -> None:
    # the console is a node: its local channel (same user only) reads one request line of
    # at most 1 MiB; a longer one was a ValueError out of the handler, logged with a
    # traceback (the fixture's end checks the log), and the client got no answer
    path = channel_path(PlatformConfig.load(tmp_path / "operator.toml"))
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(WAIT)
        s.connect(str(path))
        hello = s.makefile("rb").readline()
        assert b'"node"' in hello
        # shut our side once sent: the node's answer then comes as its close, no reset
        s.sendall(b"x" * (_LINE + 10))
        s.shutdown(socket.SHUT_WR)
        answer = b""
        with contextlib.suppress(ConnectionResetError):
            while chunk := s.recv(65536):
                answer += chunk
    assert not answer or b"longer than" in answer, answer


# -- choosing the token ----------------------------------------------------------------------

runner = CliRunner()


def test_a_token_chosen_by_the_operator_is_checked(tmp_path: Path) -> None:
    config = write_operator(tmp_path)
    r = runner.invoke(app, ["console", "--config", str(config)], env={TOKEN_ENV: "short"})
    assert r.exit_code == 2 and f"{TOKEN_ENV}: a console token has at least 16" in r.output
    bad = tmp_path / "bad.token"
    bad.write_text("has spaces in it, and is long\n")
    bad.chmod(0o600)
    r = runner.invoke(app, ["console", "--config", str(config), "--token-file", str(bad)])
    assert r.exit_code == 2 and f"{bad}: a console token uses only" in r.output
    shared = tmp_path / "shared.token"
    shared.write_text("a-good-token-0123456789\n")
    for mode in (0o644, 0o640, 0o604, 0o620):
        shared.chmod(mode)
        r = runner.invoke(app, ["console", "--config", str(config), "--token-file", str(shared)])
        assert r.exit_code == 2 and "Traceback" not in r.output, r.output
        assert (
            f"console token file {shared}: its mode {mode:04o} lets group or others read or "
            f"change it: keep it yours only (chmod 600 {shared})"
        ) in " ".join(r.output.split()), r.output
    r = runner.invoke(
        app, ["console", "--config", str(config), "--token-file", str(tmp_path / "none")]
    )
    assert r.exit_code == 2 and "cannot be read" in r.output
    r = runner.invoke(app, ["console", "--config", str(config), "--allow-host", "http://x:80"])
    assert r.exit_code == 2 and "'http://x:80' is not a host name" in r.output


def test_a_token_file_of_another_owner_is_refused(tmp_path: Path) -> None:
    # as ssh's StrictModes: its owner could write another token into it, or open it to all
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        # giving a file away needs root; CI runs the tests as root, so there it is a failure
        if os.environ.get("CI"):
            pytest.fail("a token file of another owner needs root to make", pytrace=False)
        pytest.skip("giving a file to another user needs root")
    config = write_operator(tmp_path)
    theirs = tmp_path / "theirs.token"
    theirs.write_text("a-good-token-0123456789\n")
    theirs.chmod(0o600)
    os.chown(theirs, 65534, 65534)
    with pytest.raises(ValueError, match="its owner is "):
        configured_token(theirs, None, {})
    for command in ("console", "foxglove"):
        r = runner.invoke(app, [command, "--config", str(config), "--token-file", str(theirs)])
        said = " ".join(r.output.split())
        assert r.exit_code == 2 and "Traceback" not in r.output, r.output
        assert f"console token file {theirs}: its owner is " in said, r.output
        assert (
            f"(uid 65534): only the user running this command, root (uid 0), may own it "
            f"(chown root {theirs})"
        ) in said, r.output
    # the owner is told first: a chmod would not make another's file usable
    theirs.chmod(0o644)
    with pytest.raises(ValueError, match=r"its owner is .*\(chown root ") as told:
        configured_token(theirs, None, {})
    assert "chmod" not in str(told.value)
    os.chown(theirs, 0, 0)  # its user's own (root here): taken
    theirs.chmod(0o600)
    assert configured_token(theirs, None, {}) == "a-good-token-0123456789"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_token_file_that_is_no_regular_file_is_refused(tmp_path: Path) -> None:
    # a FIFO would block the open until someone writes it: refused at once instead
    fifo = tmp_path / "token.fifo"
    os.mkfifo(fifo, 0o600)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        checked = pool.submit(configured_token, fifo, None, {})
        try:
            with pytest.raises(ValueError, match=f"console token file {fifo}: is not a regular"):
                checked.result(timeout=10)
        finally:
            if not checked.done():  # a writer unblocks the open: the test ends, failed
                with contextlib.suppress(OSError):
                    os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    config = write_operator(tmp_path)
    r = runner.invoke(app, ["console", "--config", str(config), "--token-file", str(fifo)])
    assert r.exit_code == 2 and "is not a regular file" in r.output, r.output


def test_a_bad_console_section_is_named(tmp_path: Path) -> None:
    # what the console streams comes from [console]: a wrong one stops it at start, named
    config = write_operator(tmp_path)
    text = config.read_text()
    for section, key, words in [
        ('streams = ["heli-altitude"]\nroles = {tracks = "x"}', "console.roles", "tracks = 'x'"),
        ('roles = {weather = "heli-altitude"}', "console.roles.weather", "unknown key"),
        ('streams = "heli-altitude"', "console.streams", "tuple"),
        ('streams = ["heli-altitude", "heli-altitude"]', "console.streams", "twice"),
        ('streams = ["tracked-cars"]', "console.streams", "'tracked-cars' is not a label"),
    ]:  # fmt: skip
        config.write_text(text.replace("[console]\n", f"[console]\n{section}\n"))
        r = runner.invoke(app, ["console", "--config", str(config), "--port", "0"])
        assert r.exit_code == 2, (section, r.output)
        assert f"{config}: {key}: " in r.output and words in r.output, (section, r.output)


def test_where_the_token_and_the_allowed_names_come_from(tmp_path: Path) -> None:
    assert configured_token(None, None, {}) is None  # a random one, then
    assert configured_token(None, None, {TOKEN_ENV: ""}) is None  # compose's default
    chosen = tmp_path / "console.token"
    chosen.write_text("from-a-file-0123456789\n")
    chosen.chmod(0o600)
    env = {TOKEN_ENV: "from-the-env-0123456789"}
    assert configured_token(chosen, None, env) == "from-a-file-0123456789"  # --token-file
    assert configured_token(None, chosen, env) == "from-the-env-0123456789"  # env, config
    assert configured_token(None, chosen, {}) == "from-a-file-0123456789"
    names = allowed_names(["Operator.Example.org.", "[::1]"], {ALLOW_HOSTS_ENV: "a.test, b"})
    assert names == ["operator.example.org", "::1", "a.test", "b"]


@pytest.mark.timeout(60)
def test_the_token_from_the_environment_is_the_one_printed_and_accepted(tmp_path: Path) -> None:
    # as compose passes it: DYKNOW_CONSOLE_TOKEN, bound to every address
    config = write_operator(tmp_path)
    token = "compose-token-0123456789"
    args = ["console", "--config", str(config), "--host", "0.0.0.0", "--port", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "federation.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, TOKEN_ENV: token, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        ready = proc.stdout.readline()
        m = re.search(r"(http://127\.0\.0\.1:(\d+)/)\?token=(\S+)", ready)
        assert m and m[3] == token, ready
        c = Console(proc, int(m[2]), token, m[0], tmp_path / "audit.jsonl")
        status, _, state = c.request("GET", "/api/state", c.bearer())
        assert status == 200 and state["operator"] == "operator"
        status, _, answer = c.request("GET", "/api/state", host=f"evil.example:{c.port}")
        assert status == 403 and "Host" in answer["error"]
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=WAIT)
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)


@pytest.mark.parametrize(
    ("host", "key"),
    [
        ("192.0.2.7", "192.0.2.7"),
        ("::ffff:192.0.2.7", "192.0.2.7"),  # an IPv4 client on a dual-stack socket
        ("2001:db8:1:2:aaaa::1", "2001:db8:1:2::/64"),
        ("2001:db8:1:2:bbbb::9", "2001:db8:1:2::/64"),  # the same host, a fresh address
        ("2001:db8:1:3::1", "2001:db8:1:3::/64"),
    ],
)
def test_a_client_counts_by_its_ipv4_address_or_its_ipv6_64(host: str, key: str) -> None:
    # regression: each IPv6 address counted apart (one host holds a /64), and an IPv4
    # client arriving IPv4-mapped counted apart from itself over IPv4
    assert _client_key(host) == key
