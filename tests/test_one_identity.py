"""One platform, one process: a second node of a live name is refused; the one-shot
commands run with a running node's config go through it and break none of its sessions."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from _node_example import CLI, Station, _samples
from _victim import station_channel

from agents import KeyPair, wire_key
from federation import PlatformConfig
from federation.cli import main as cli_main


@pytest.mark.timeout(120)
def test_a_second_node_of_a_live_name_is_refused_and_the_first_goes_on(tmp_path: Path) -> None:
    station = Station(tmp_path)
    try:
        station.start("python")
        node = station.node
        assert node is not None
        # the same name, joining through the first one's endpoint (no port of its own)
        twin = station.dir / "twin.toml"
        text = (station.dir / "station-python.toml").read_text()
        twin.write_text(text.replace("listen = [", "connect = ["))
        done = station.command("node", "--config", str(twin), timeout=60)
        assert done.returncode == 2, done.stderr
        err = done.stderr
        assert f"platform 'station' is alive in federation {station.federation!r} already" in err
        assert f"pid {node.pid} on host" in err  # where …
        iso = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d\d:\d\d"  # local time and offset
        assert re.search(rf"since {iso} \(\d+ s ago\)", err), err
        assert "ready" not in done.stdout and "Traceback" not in err
        # a one-shot command as 'station' where the node's channel is not (another host):
        # refused too, rather than acting as the live platform
        elsewhere = {**station.env, "XDG_RUNTIME_DIR": str(tmp_path / "elsewhere")}
        done = station.command(
            "ask", "temperature", "-p", "station", "--config", str(twin), timeout=60, env=elsewhere
        )
        assert done.returncode == 2, done.stderr
        assert "is alive in federation" in done.stderr
        assert "run this command on its host" in done.stderr
        # the running one was not touched: it answers, with data, and has its channel
        answer = station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        assert 19.0 <= _samples(answer, "temperature")[0][0] <= 21.0
        assert node.poll() is None
    finally:
        out, err = station.stop()
    assert "station stopped" in out and "Traceback" not in err


@pytest.mark.timeout(120)
def test_the_same_config_started_twice_is_told_the_platform_runs(tmp_path: Path) -> None:
    """The twin holds the first's listen endpoint too: it is told who runs, not "address in use"."""
    station = Station(tmp_path)
    try:
        station.start("python")
        node = station.node
        assert node is not None
        for command in ("node", "console"):
            done = station.command(
                command,
                "--config",
                "station-python.toml",
                *(["--port", "0"] * (command == "console")),
                timeout=60,
            )
            assert done.returncode == 2, done.stderr
            err = done.stderr
            assert (
                f"platform 'station' is alive in federation {station.federation!r} already" in err
            )
            assert f"pid {node.pid} on host" in err and "address is in use" not in err, err
            assert "ready" not in done.stdout and "Traceback" not in err
        assert node.poll() is None
    finally:
        out, err = station.stop()
    assert "station stopped" in out and "Traceback" not in err


@pytest.mark.timeout(150)
def test_a_flood_of_directory_queries_does_not_let_a_second_node_start(tmp_path: Path) -> None:
    """An outsider emptying the running node's directory limiter does not let its twin start.

    The signed directory answer that confirms a presence goes through the running node's
    directory limiter, shared by everyone: an outsider flooding ``df/<name>`` had it
    shed, the twin started, and it unlinked the running node's socket. On one host the
    node listening on the local channel decides, which nobody outside can flood.
    """
    import threading

    import zenoh

    station = Station(tmp_path)
    stop = threading.Event()
    session = None
    try:
        station.start("python")
        node = station.node
        assert node is not None
        config = PlatformConfig.load(station.dir / "station-python.toml")
        sock = _channel(config, Path(station.env["XDG_RUNTIME_DIR"]))
        assert sock.is_socket()
        cfg = zenoh.Config()  # a plain zenoh client: no key, no trust file
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{station.port}"]))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(cfg)
        key = f"dyknow/{station.federation}/v1/df/station"

        def flood() -> None:
            while not stop.is_set():
                for _ in range(100):
                    session.get(key, lambda _reply: None, timeout=1.0)
                time.sleep(0.01)  # ~10 000 queries/s: the limiter (50/s) stays empty

        flooder = threading.Thread(target=flood, daemon=True)
        flooder.start()
        time.sleep(1.0)
        twin = station.dir / "twin.toml"
        text = (station.dir / "station-python.toml").read_text()
        twin.write_text(text.replace("listen = [", "connect = ["))
        second = station.spawn("node", "--config", str(twin))
        try:
            out, err = second.communicate(timeout=60)
        except subprocess.TimeoutExpired:  # it started: what it says when stopped
            second.send_signal(signal.SIGINT)
            out, err = second.communicate(timeout=20)
        finally:
            stop.set()
            flooder.join(10)
        assert second.returncode == 2, err
        assert "platform 'station' is alive in federation" in err and "already" in err
        assert f"pid {node.pid} on host" in err
        assert "ready" not in out and "Traceback" not in err
        # the first one keeps its socket, and it serves a one-shot command of its config
        assert sock.is_socket()
        done = station.command(
            "labels", "-p", "station", "--config", "station-python.toml", "--json", timeout=40
        )
        assert done.returncode == 0, done.stderr
        assert "temperature" in json.loads(done.stdout)["labels"]
        assert node.poll() is None
    finally:
        stop.set()
        if session is not None:
            session.close()
        out, err = station.stop()
    assert "station stopped" in out and "Traceback" not in err


def _console(station: Station) -> tuple[subprocess.Popen[str], str]:
    """``dyknow console`` as the station's operator, and its ready line (with its URL)."""
    console = station.spawn("console", "--config", "operator.toml", "--port", "0")
    assert console.stdout is not None
    ready = console.stdout.readline()  # bounded by the test's timeout
    assert "operator ready" in ready, console.stderr.read() if console.stderr else ""
    return console, ready


@pytest.mark.timeout(150)
def test_one_shot_commands_run_beside_the_console_with_its_config(tmp_path: Path) -> None:
    station = Station(tmp_path)
    console = None
    try:
        station.start("python")
        console, ready = _console(station)
        url = ready.rsplit(": ", 1)[1].strip()
        record = station.dir / "t.mcap"
        commands = [
            ("platforms",),
            ("labels", "-p", "station"),
            ("ask", "temperature", "wind-speed", "-p", "station"),
            ("stream", "temperature", "-p", "station", "--count", "3"),
            ("record", "temperature", "-p", "station", "-o", str(record), "-n", "3"),
        ]

        def run(args: tuple[str, ...]) -> subprocess.CompletedProcess[str]:
            extra = [] if args[0] == "record" else ["--json"]
            return station.command(
                *args, "--config", "operator.toml", *extra, "--wait", "10", timeout=60
            )

        # all at once, while the console runs as the same platform
        with ThreadPoolExecutor(len(commands)) as pool:
            results = list(pool.map(run, commands))
        for args, done in zip(commands, results, strict=True):
            assert done.returncode == 0, (args, done.stderr)
        platforms, labels, ask, stream, rec = results
        assert "station" in json.loads(platforms.stdout)
        assert "temperature" in json.loads(labels.stdout)["labels"]
        assert _samples(json.loads(ask.stdout), "wind-speed")[0][0] >= 3.0
        rows = [json.loads(line) for line in stream.stdout.splitlines()]
        assert len(rows) == 3 and {r["label"] for r in rows} == {"temperature"}
        assert "3 samples (temperature=3)" in rec.stdout and record.stat().st_size > 0
        # the console still sees the station, and nothing was broken on either side
        base, token = url.split("?token=")
        asked = urllib.request.Request(
            base + "api/state", headers={"Authorization": f"Bearer {token}"}
        )
        with urllib.request.urlopen(asked, timeout=10) as page:
            state = json.loads(page.read())
        assert "station" in [p["name"] for p in state["platforms"]]
        console.send_signal(signal.SIGINT)
        out, err = console.communicate(timeout=20)
        assert console.returncode == 0, err
        assert "local channel: 5 commands served, 0 refused" in out  # each went through the console
        for text in (err, station.stop()[1]):
            assert "unknown-session" not in text and "renewing" not in text, text
            assert "Traceback" not in text
    finally:
        if console is not None and console.poll() is None:
            console.kill()
            console.communicate(timeout=10)
        station.stop()


ATTACKER = """
import json, socket, sys
s = socket.socket(socket.AF_UNIX)
try:
    s.connect(sys.argv[1])
except OSError as exc:
    print("connect:", type(exc).__name__, flush=True)
    sys.exit(0)
ask = {"action": "get-latest", "labels": ["temperature"]}
request = {"op": "request", "platform": "station", "content": ask}
s.sendall(json.dumps(request).encode() + b"\\n")
print("answer:", s.makefile().readline().strip(), flush=True)
"""


@pytest.mark.timeout(120)
def test_another_user_cannot_use_a_nodes_local_channel(tmp_path: Path) -> None:
    import shutil
    import tempfile

    from federation._platform import PlatformConfig

    runtime = Path(tempfile.mkdtemp(prefix="dyknow-xdg-", dir="/tmp"))
    try:
        runtime.chmod(0o755)  # a runtime directory others may traverse
        station = Station(tmp_path)
        station.env["XDG_RUNTIME_DIR"] = str(runtime)
        try:
            station.start("python")
            config = PlatformConfig.load(station.dir / "station-python.toml")
            sock = _channel(config, runtime)

            def attack() -> str:
                done = subprocess.run(
                    # the system's python (the attacker's own; stdlib only)
                    ["/usr/bin/python3", "-c", ATTACKER, str(sock)],
                    cwd="/",
                    user=65534,  # nobody: another OS user on the node's host
                    group=65534,
                    capture_output=True,
                    text=True,
                    timeout=30,
                )
                assert done.returncode == 0, done.stderr
                return done.stdout.strip()

            # the socket's directory is the node's user's only
            assert attack() == "connect: PermissionError"
            # loosened by mistake: the node still refuses, by the peer's uid
            for d in (sock.parent.parent, sock.parent):
                d.chmod(0o755)
            sock.chmod(0o777)
            answer = attack()
            assert answer.startswith("answer: ")
            assert json.loads(answer.removeprefix("answer: ")) == {
                "error": "this node serves its own user only"
            }
            out, err = station.stop()
            assert "local channel: 0 commands served, 1 refused" in out
            assert "local channel: refused a client of uid 65534" in err
        finally:
            station.stop()
    finally:
        shutil.rmtree(runtime, ignore_errors=True)


def _channel(config: object, runtime: Path) -> Path:
    """The node's socket, as the node computes it under ``runtime``."""
    from federation._local import channel_path

    saved = os.environ.get("XDG_RUNTIME_DIR")
    os.environ["XDG_RUNTIME_DIR"] = str(runtime)
    try:
        return channel_path(config)  # type: ignore[arg-type]
    finally:
        if saved is None:
            del os.environ["XDG_RUNTIME_DIR"]
        else:
            os.environ["XDG_RUNTIME_DIR"] = saved


OTHER_LISTENER = """
import os, socket, sys
path, hello = sys.argv[1], sys.argv[2].encode() + b"\\n"
os.makedirs(os.path.dirname(path), exist_ok=True)
s = socket.socket(socket.AF_UNIX)
s.bind(path)
if os.getuid() == 0:  # bound in the victim's place by root: listening as another user
    os.setgid(65534)
    os.setuid(65534)
s.listen()
print("listening", flush=True)
while True:
    c, _ = s.accept()
    c.sendall(hello)  # the victim's node's own hello: a public key, proving nothing
    c.close()
"""


def _other_listener(path: Path, hello: str, *, as_other: bool) -> subprocess.Popen[str]:
    """A process of uid 65534 listening on ``path`` (bound by root when not ``as_other``)."""
    extra: dict[str, Any] = {"user": 65534, "group": 65534} if as_other else {}
    proc = subprocess.Popen(
        ["/usr/bin/python3", "-c", OTHER_LISTENER, str(path), hello],
        cwd="/",
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **extra,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "listening", proc.stderr
    return proc


async def _command(config: PlatformConfig) -> list[Any]:
    from federation._local import via_node

    return [line async for line in via_node(config, {"op": "platforms"})]


@pytest.mark.timeout(90)
def test_another_user_cannot_take_a_nodes_channel_in_a_shared_tmp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ``dyknow-<uid>`` made first by another user in ``<tmp>``: refused by node and command.

    Without ``$XDG_RUNTIME_DIR`` the channel is under the shared ``<tmp>``: another user
    could make the victim's directory there first and listen on the victim's socket.
    """
    import asyncio
    import shutil
    import tempfile

    from federation._local import ForeignNodeError, _hello, channel_path

    shared = Path(tempfile.mkdtemp(prefix="dyknow-tmp-", dir="/tmp"))
    other = None
    try:
        shared.chmod(0o1777)  # like /tmp: everyone may make a directory there
        station = Station(tmp_path)
        monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
        monkeypatch.setattr(tempfile, "tempdir", str(shared))
        config = PlatformConfig.load(station.dir / "station-python.toml")
        path = channel_path(config)
        assert path.is_relative_to(shared / f"dyknow-{os.getuid()}")
        hello = json.dumps(_hello(config, KeyPair.load(config.key).public_key))
        other = _other_listener(path, hello, as_other=True)
        assert (shared / f"dyknow-{os.getuid()}").stat().st_uid == 65534
        with pytest.raises(ForeignNodeError, match=r"dyknow-\d+ belongs to uid 65534, not to"):
            asyncio.run(_command(config))
        # the node refuses to start there, saying why (not that it runs already)
        env = {k: v for k, v in station.env.items() if k != "XDG_RUNTIME_DIR"}
        node = station.command(
            "node",
            "--config",
            str(station.dir / "station-python.toml"),
            timeout=60,
            env={**env, "TMPDIR": str(shared)},
        )
        assert node.returncode == 2, node.stderr
        assert "uid 65534" in node.stderr and "alive" not in node.stderr
        assert "Traceback" not in node.stderr
    finally:
        if other is not None:
            other.kill()
            other.wait()
        shutil.rmtree(shared, ignore_errors=True)


@pytest.mark.timeout(60)
async def test_a_listener_of_another_uid_on_the_channel_is_not_taken_for_the_node(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A socket of ours listened on by another user: commands send nothing, nodes keep off."""
    from federation._local import ForeignNodeError, _hello, _node_here

    config, path = station_channel(tmp_path, monkeypatch)
    hello = json.dumps(_hello(config, KeyPair.load(config.key).public_key))
    other = _other_listener(path, hello, as_other=False)
    try:
        with pytest.raises(ForeignNodeError, match="runs as uid 65534, not as this user"):
            await _command(config)
        with pytest.raises(ForeignNodeError, match="runs as uid 65534"):
            await _node_here(path)
    finally:
        other.kill()
        other.wait()


async def test_a_node_stating_the_configs_key_must_sign_the_commands_nonce(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A hello replayed with a proof signed for another nonce: the request is never sent."""
    import asyncio
    import base64

    from federation._local import ForeignNodeError, _hello, _proof_data

    config, path = station_channel(tmp_path, monkeypatch)
    keys = KeyPair.load(config.key)
    path.parent.mkdir(parents=True, mode=0o700, exist_ok=True)
    recorded = keys.sign(_proof_data(config, b"n" * 32))  # a proof of an earlier command's
    received: list[bytes] = []

    async def replay(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(json.dumps(_hello(config, keys.public_key)).encode() + b"\n")
        received.append(await reader.readline())  # the nonce
        proof = {"proof": base64.b64encode(recorded).decode()}
        writer.write(json.dumps(proof).encode() + b"\n")
        received.append(await reader.read())
        writer.close()

    server = await asyncio.start_unix_server(replay, path=str(path))
    async with asyncio.timeout(20), server:
        with pytest.raises(ForeignNodeError, match="did not sign this command's nonce"):
            await _command(config)
        while len(received) < 2:  # noqa: ASYNC110 (the server's task has no event to await)
            await asyncio.sleep(0.01)
    assert set(json.loads(received[0])) == {"nonce"} and received[1] == b""


async def test_a_node_older_than_the_command_is_said_so_not_called_foreign(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A node from before the nonce step answers it with an error: restart it, not remove it."""
    import asyncio

    from federation._local import _hello

    config, path = station_channel(tmp_path, monkeypatch)
    keys = KeyPair.load(config.key)
    path.parent.mkdir(parents=True, mode=0o700, exist_ok=True)

    async def older(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(json.dumps(_hello(config, keys.public_key)).encode() + b"\n")
        await reader.readline()  # the nonce, taken for a request
        writer.write(b'{"error": "bad request: no op"}\n')
        await reader.read()
        writer.close()

    server = await asyncio.start_unix_server(older, path=str(path))
    async with asyncio.timeout(20), server:
        [line] = await _command(config)
    assert line == {
        "error": f"the node on {path} is older than this command (no nonce step; it "
        "answered: bad request: no op); restart it with this version"
    }


async def test_a_channel_never_unlinks_a_socket_a_node_listens_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only a socket nobody listens on is a dead node's: one that answers is refused, kept."""
    import asyncio
    import socket

    from federation import FederationPlatform
    from federation._local import LocalChannel, PlatformAliveError

    config, path = station_channel(tmp_path, monkeypatch)
    path.parent.mkdir(parents=True, mode=0o700, exist_ok=True)
    async with asyncio.timeout(30):
        # a node that started since refuse_duplicate looked: listening there
        other = await asyncio.start_unix_server(lambda r, w: w.close(), path=str(path))
        async with FederationPlatform(config, join=False) as p:
            with pytest.raises(PlatformAliveError, match=rf"pid {os.getpid()} on host"):
                async with LocalChannel(p):
                    pass
            assert path.is_socket()
            async with asyncio.timeout(5):  # and it still answers
                _, writer = await asyncio.open_unix_connection(str(path))
                writer.close()
            other.close()
            await other.wait_closed()
            # a dead node's socket, left behind: taken over
            stale = socket.socket(socket.AF_UNIX)
            path.unlink(missing_ok=True)
            stale.bind(str(path))
            stale.close()
            async with LocalChannel(p) as channel:
                _, writer = await asyncio.open_unix_connection(str(path))
                writer.close()
                assert channel.path == path
            assert not path.exists()


async def test_a_node_too_busy_to_accept_on_its_channel_is_still_taken_for_running(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A listener whose backlog is full: running (pid unknown), never a dead node's socket."""
    import asyncio
    import socket

    from federation import FederationPlatform
    from federation._local import LocalChannel, PlatformAliveError, _node_here

    config, path = station_channel(tmp_path, monkeypatch)
    path.parent.mkdir(parents=True, mode=0o700, exist_ok=True)
    busy = socket.socket(socket.AF_UNIX)
    busy.bind(str(path))
    busy.listen(0)  # and never accepts: its backlog fills
    waiting: list[socket.socket] = []
    try:
        assert await _node_here(path) == os.getpid()  # room in the backlog: who listens
        for _ in range(64):
            c = socket.socket(socket.AF_UNIX)
            c.setblocking(False)
            waiting.append(c)
            try:
                c.connect(str(path))
            except BlockingIOError:
                break
        else:
            pytest.fail("the listener's backlog never filled")
        assert await _node_here(path) == 0  # someone listens, too busy to say who
        async with asyncio.timeout(30), FederationPlatform(config, join=False) as p:
            with pytest.raises(PlatformAliveError, match="is alive in federation"):
                async with LocalChannel(p):
                    pass
        assert path.is_socket()
    finally:
        for c in waiting:
            c.close()
        busy.close()


# the child scripts' way to run out of file descriptors: RLIMIT_NOFILE lowered to 64 and
# every one left taken; `give_back(held)` once the attempt is made
_HOLD_EVERY_FD = """
import os, resource

def hold_every_fd():
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, hard))
    held = []
    try:
        while len(held) < 64:
            held.append(os.open(os.devnull, os.O_RDONLY))
    except OSError:
        pass
    return held

def give_back(held):
    for fd in held:
        os.close(fd)
"""


_OUT_OF_FDS = """
import asyncio, json, os, resource, socket, sys
from pathlib import Path
from federation._local import _node_here

path = Path(sys.argv[1])
node = socket.socket(socket.AF_UNIX)  # a node listening on the channel: this process
node.bind(str(path))
node.listen(8)
loop = asyncio.new_event_loop()  # its descriptors taken before they run out
held = hold_every_fd()
try:
    outcome = {"here": loop.run_until_complete(_node_here(path))}
except Exception as exc:
    outcome = {"error": type(exc).__name__, "message": str(exc)}
give_back(held)
outcome["after"] = loop.run_until_complete(_node_here(path))
print(json.dumps(outcome))
"""


def test_a_node_looked_for_without_a_file_descriptor_left_is_a_clear_error_not_none(
    tmp_path: Path,
) -> None:
    """Out of file descriptors (RLIMIT_NOFILE), looking at the local channel says so; it
    is never "none listens" (the caller would unlink a live node's socket), nor a crash."""
    import sys

    path = tmp_path / "run" / "station.sock"
    path.parent.mkdir(mode=0o700)
    done = subprocess.run(
        [sys.executable, "-c", _HOLD_EVERY_FD + _OUT_OF_FDS, str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])},
    )
    assert done.returncode == 0, done.stderr
    outcome = json.loads(done.stdout)
    assert outcome.get("error") == "LocalChannelError", outcome
    message = outcome["message"]
    assert "cannot tell whether a node of this platform runs on this host" in message
    assert str(path) in message
    assert "out of file descriptors (at most 64 open at once: RLIMIT_NOFILE" in message
    assert outcome["after"] > 0  # descriptors back: the listener found, as ever
    assert path.is_socket()


_CHANNEL_OUT_OF_FDS = """
import asyncio, json, os, resource, sys
from agents import MemoryHub
from federation import FederationPlatform, PlatformConfig
from federation._local import LocalChannel, channel_path

async def main():
    config = PlatformConfig.load(sys.argv[1])
    path = channel_path(config)
    hub = MemoryHub()
    async with hub.transport() as t, FederationPlatform(config, transport=t, join=False) as p:
        held = hold_every_fd()
        try:
            async with LocalChannel(p):
                outcome = {"opened": True}
        except Exception as exc:
            outcome = {"error": type(exc).__name__, "message": str(exc)}
        give_back(held)
        async with LocalChannel(p):
            outcome["then"] = path.is_socket()
    print(json.dumps(outcome))

asyncio.run(main())
"""


def test_a_node_opening_its_channel_without_a_file_descriptor_left_says_why(
    tmp_path: Path,
) -> None:
    """A node out of file descriptors as it opens its local channel: a clear error naming
    the cause (the node says it in one line), not an OSError's traceback."""
    import sys

    station = Station(tmp_path)
    done = subprocess.run(
        [sys.executable, "-c", _HOLD_EVERY_FD + _CHANNEL_OUT_OF_FDS, "station-python.toml"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=station.dir,
        env={**station.env, "PYTHONPATH": str(Path(__file__).parents[1])},
    )
    assert done.returncode == 0, done.stderr
    outcome = json.loads(done.stdout)
    assert outcome.get("error") == "LocalChannelError", outcome
    assert outcome["message"].startswith("cannot open the local channel "), outcome
    assert "out of file descriptors (at most 64 open at once: RLIMIT_NOFILE" in outcome["message"]
    assert outcome["then"] is True  # descriptors back: it opens, as ever


_ASK_OUT_OF_FDS = """
import asyncio, json, os, resource, sys
from agents import MemoryHub
from federation import FederationPlatform, PlatformConfig
from federation._local import LocalChannel, via_node

async def ask(config):
    return [line async for line in via_node(config, {"op": "platforms"})]

async def main():
    config = PlatformConfig.load(sys.argv[1])
    hub = MemoryHub()
    async with hub.transport() as t, FederationPlatform(config, transport=t, join=False) as p:
        async with LocalChannel(p):
            held = hold_every_fd()
            try:
                outcome = {"lines": await ask(config)}
            except Exception as exc:
                outcome = {"error": type(exc).__name__, "message": str(exc)}
            give_back(held)
            outcome["then"] = len(await ask(config))
    print(json.dumps(outcome))

asyncio.run(main())
"""


def test_a_command_out_of_file_descriptors_never_takes_its_node_for_none(
    tmp_path: Path,
) -> None:
    """A one-shot command out of file descriptors as it looks for the running node: the
    cause named (RLIMIT_NOFILE), never "no node runs" (it would then act as the platform
    itself beside its node); with descriptors back the node answers it."""
    import sys

    station = Station(tmp_path)
    done = subprocess.run(
        [sys.executable, "-c", _HOLD_EVERY_FD + _ASK_OUT_OF_FDS, "station-python.toml"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=station.dir,
        env={**station.env, "PYTHONPATH": str(Path(__file__).parents[1])},
    )
    assert done.returncode == 0, done.stderr
    outcome = json.loads(done.stdout)
    assert outcome.get("error") == "LocalChannelError", outcome
    assert outcome["message"].startswith("cannot read the platform's key "), outcome
    assert "out of file descriptors (at most 64 open at once: RLIMIT_NOFILE" in outcome["message"]
    assert outcome["then"] >= 1  # descriptors back: the node answers, as ever


async def test_a_command_whose_connect_is_short_of_descriptors_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The connect to the node's channel failing for lack of descriptors: LocalChannelError
    naming the channel and the cause, not NodeUnreachable (nor a bare OSError)."""
    import errno

    from federation import PlatformConfig
    from federation._local import LocalChannelError, _private_dir, channel_path, via_node

    station = Station(tmp_path)
    config = PlatformConfig.load(station.dir / "station-python.toml")
    path = channel_path(config)
    _private_dir(path.parent, make=True)

    async def short(*_args: Any, **_kw: Any) -> Any:
        raise OSError(errno.EMFILE, "Too many open files")

    monkeypatch.setattr(asyncio, "open_unix_connection", short)
    with pytest.raises(LocalChannelError, match="cannot reach the node on its local channel"):
        async for _ in via_node(config, {"op": "platforms"}):
            pass


@pytest.mark.timeout(150)
def test_a_stream_asked_again_as_the_last_follower_leaves_gets_samples(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """One command's stream ends (its export cancelled) just as the next asks for it.

    The channel followed the import being cancelled as if it were the node's own, and the
    next command waited for samples for ever (a full suite, loaded: `record` after `stream`).
    The first command is a process; the others run in this process (the same code, without
    an interpreter's start), so that each asks the sooner after the last one ended.
    """
    station = Station(tmp_path)
    console = None
    args = [
        *("stream", "temperature", "-p", "station", "--count", "1"),
        *("--config", "operator.toml", "--json", "--wait", "10"),
    ]
    try:
        station.start("python")
        console, _ = _console(station)
        monkeypatch.chdir(station.dir)
        monkeypatch.setenv("XDG_RUNTIME_DIR", station.env["XDG_RUNTIME_DIR"])
        for n in range(4):  # each ends its stream as the next one asks for it
            if n == 0:
                done = station.command(*args, timeout=40)
            else:
                code = cli_main(args)
                out = capsys.readouterr()
                done = subprocess.CompletedProcess(["dyknow", *args], code, out.out, out.err)
            assert done.returncode == 0, (n, done.stderr)
            assert len(done.stdout.splitlines()) == 1, (n, done.stdout)
    finally:
        if console is not None:
            console.terminate()
            console.communicate(timeout=20)
        station.stop()


@pytest.mark.timeout(150)
def test_a_refused_record_through_the_console_leaves_the_file_there_as_it_was(
    tmp_path: Path,
) -> None:
    """A record the provider refuses (a label it does not map) writes nothing over ``-o``'s file."""
    station = Station(tmp_path)
    vocabulary = station.dir / "weather.toml"  # a label of the vocabulary, no stream of it
    vocabulary.write_text(vocabulary.read_text() + 'no-such-label = "mapped by nobody"\n')
    console = None
    try:
        station.start("python")
        console, _ = _console(station)
        kept = station.dir / "kept.mcap"
        kept.write_bytes(b"an earlier recording")
        done = station.command(
            *("record", "no-such-label", "-p", "station", "-o", str(kept)),
            *("-n", "1", "--config", "operator.toml", "--wait", "10"),
            timeout=60,
        )
        assert done.returncode != 0, done.stdout
        assert "Traceback" not in done.stderr, done.stderr
        assert "0 samples" not in done.stderr, done.stderr  # no progress line before it
        assert kept.read_bytes() == b"an earlier recording"
        assert sorted(p.name for p in station.dir.glob("*kept*")) == ["kept.mcap"]
    finally:
        if console is not None:
            console.terminate()
            console.communicate(timeout=20)
        station.stop()


@pytest.mark.timeout(150)
def test_a_sample_period_the_nodes_import_has_not_is_refused_not_ignored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    station = Station(tmp_path)
    operator = station.dir / "operator.toml"
    operator.write_text(operator.read_text() + '\n[console]\nstreams = ["temperature"]\n')
    console = follower = None
    try:
        station.start("python")
        console, ready = _console(station)
        base, token = ready.rsplit(": ", 1)[1].strip().split("?token=")
        asked = urllib.request.Request(
            base + "api/state", headers={"Authorization": f"Bearer {token}"}
        )

        def samples() -> int:
            with urllib.request.urlopen(asked, timeout=10) as page:
                state = json.loads(page.read())
            return sum(p["samples"] for p in state["platforms"] if p["name"] == "station")

        for _ in range(100):  # until the console's own import of temperature brought samples
            if samples():
                break
            time.sleep(0.2)  # the console offers no event to wait on from outside
        common = ["--config", "operator.toml", "--wait", "10"]

        def process(*args: str) -> subprocess.CompletedProcess[str]:
            return station.command(*args, *common, timeout=60)

        def run(*args: str) -> subprocess.CompletedProcess[str]:
            """The same in this process, without an interpreter's start."""
            code = cli_main([*args, *common])
            out = capsys.readouterr()
            return subprocess.CompletedProcess(["dyknow", *args], code, out.out, out.err)

        monkeypatch.chdir(station.dir)
        monkeypatch.setenv("XDG_RUNTIME_DIR", station.env["XDG_RUNTIME_DIR"])
        rec = station.dir / "t.mcap"
        done = process(
            "record",
            "temperature",
            "-p",
            "station",
            "-o",
            str(rec),
            "-n",
            "1",
            "--sample-period",
            "2",
        )
        assert done.returncode == 1 and not rec.exists(), done.stderr
        assert (
            "'temperature' of platform 'station' is imported by the running node already, for "
            "its own use (the console's streams), and a stream is imported once, at one rate: "
            "--sample-period 2 cannot apply to it. Leave --sample-period out"
        ) in done.stderr
        assert run("stream", "temperature", "-p", "station", "-n", "2").returncode == 0
        # a stream a command follows: another command at another rate is refused too
        follower = station.spawn(
            "stream", "wind-speed", "-p", "station", "--sample-period", "0.5", *common
        )
        assert follower.stdout is not None and follower.stdout.readline()  # a sample came
        done = run("stream", "wind-speed", "-p", "station", "--sample-period", "2", "-n", "1")
        assert done.returncode == 1
        assert "for another command (--sample-period 0.5)" in done.stderr, done.stderr
        same = run("stream", "wind-speed", "-p", "station", "--sample-period", "0.5", "-n", "1")
        assert same.returncode == 0, same.stderr  # at the same rate: it shares the import
    finally:
        for proc in (follower, console):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.communicate(timeout=10)
        station.stop()


@pytest.mark.timeout(150)
def test_a_node_streams_and_records_its_own_streams_through_its_channel(tmp_path: Path) -> None:
    """``stream``/``record`` of the config's own platform follow the node's own instance.

    A platform exports to others only: before, both exited 1 with "a platform does not
    export to itself"; without a running node the command says what to do.
    """
    from dyknow_core import Recording

    station = Station(tmp_path)

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return station.command(
            *args, "-p", "station", "--config", "station-python.toml", "--wait", "10", timeout=60
        )

    done = run("stream", "temperature", "-n", "1")
    assert done.returncode == 1, done.stdout
    assert "is this config's own" in done.stderr and "dyknow node --config" in done.stderr
    assert "export to itself" not in done.stderr and "Traceback" not in done.stderr
    try:
        station.start("python")
        done = run("stream", "temperature", "-n", "2", "--json")
        assert done.returncode == 0, done.stderr
        rows = [json.loads(line) for line in done.stdout.splitlines()]
        assert [r["label"] for r in rows] == ["temperature", "temperature"]
        # at the rate asked (the feed gives one every 0.2 s): one a second, on its grid
        done = run("stream", "temperature", "-n", "2", "--json", "--sample-period", "1")
        assert done.returncode == 0, done.stderr
        valid = [json.loads(line)["valid"] for line in done.stdout.splitlines()]
        assert valid[1] - valid[0] >= 0.9e9, valid
        out = station.dir / "own.mcap"
        done = run("record", "temperature", "wind-speed", "-o", str(out), "-n", "3")
        assert done.returncode == 0, done.stderr
        assert "3 samples" in done.stdout
        assert Recording(out).info()["samples"] == 3
    finally:
        _, err = station.stop()
    assert "Traceback" not in err, err


@pytest.mark.timeout(150)
def test_a_platform_that_never_answers_holds_up_no_other_platforms_stream(
    tmp_path: Path,
) -> None:
    """A command's create-stream waits out its timeout; one for another platform goes on.

    The channel held its lock over the create-stream: every other command's stream waited
    behind a platform that does not answer.
    """
    import threading

    import zenoh

    from agents import TrustStore, wire_key
    from agents._security import Handshake
    from agents.keys import gen_keys, trust_keys

    station = Station(tmp_path)
    keys = station.dir / "keys"
    # "ghost": trusted, it finishes the key exchange, then answers no request
    ghost_keys, _, public = gen_keys("ghost", keys)
    trust_keys(keys / "trust.json", [public], federation=station.federation)
    handshake = Handshake(ghost_keys, TrustStore.load(keys / "trust.json"))
    asked = threading.Event()

    def on_kx(query: zenoh.Query) -> None:
        body = query.payload
        reply, _ = handshake.respond(b"" if body is None else body.to_bytes())
        query.reply(query.key_expr, reply)
        asked.set()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{station.port}"]')
    console = ghost = session = None
    try:
        station.start("python")
        # ghost joins once the station listens, and is linked to it before the operator's
        # node starts: opened before, its session retried the connect on a back-off of up
        # to seconds, and on a loaded machine the command's key exchange to ghost could go
        # out before ghost was linked to anyone (then no answer came)
        session = zenoh.open(conf)
        session.declare_queryable(wire_key(station.federation, "kx", "ghost"), on_kx)
        deadline = time.monotonic() + 30
        while not list(session.info.peers_zid()):
            assert time.monotonic() < deadline, "ghost never linked to the station"
            time.sleep(0.05)  # zenoh has no event for a link made: asked until it is
        console, _ = _console(station)
        ghost = subprocess.Popen(
            [
                *(*CLI, "stream", "temperature", "-p", "ghost", "--config", "operator.toml"),
                *("--json", "--wait", "0.5", "--timeout", "60"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=station.dir,
            env=station.env,
        )
        if not asked.wait(30):  # the node is in its create-stream to ghost
            ghost.kill()
            pytest.fail(f"ghost was never asked: {ghost.communicate(timeout=10)}")
        done = subprocess.run(
            [
                *(*CLI, "stream", "temperature", "-p", "station", "--count", "1"),
                *("--config", "operator.toml", "--json", "--wait", "10", "--timeout", "20"),
            ],
            capture_output=True,
            text=True,
            cwd=station.dir,
            env=station.env,
            timeout=40,  # well within ghost's 60 s
        )
        assert done.returncode == 0, done.stderr
        assert len(done.stdout.splitlines()) == 1, done.stdout
        assert ghost.poll() is None  # still waiting for ghost's answer
    finally:
        if ghost is not None:
            ghost.kill()
            ghost.communicate(timeout=10)
        if console is not None:
            console.terminate()
            console.communicate(timeout=20)
        station.stop()
        if session is not None:
            session.close()


# A second start of the config, its descriptors exhausted just before it looks at the
# local channel and left so (its teardown too), as on a host where they ran out.
_TWIN_OUT_OF_FDS = """
import os, resource, sys
from federation import _local
from federation.cli import main

look = _local._node_here
held = []

async def starved(path):
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 4, hard))
    try:
        while True:
            held.append(os.open(os.devnull, os.O_RDONLY))
    except OSError:
        pass
    return await look(path)

_local._node_here = starved
sys.exit(main(["node", "--config", sys.argv[1]]))
"""


@pytest.mark.timeout(150)
def test_a_twin_out_of_file_descriptors_leaves_the_live_nodes_channel(tmp_path: Path) -> None:
    """The same config started again in a process without a descriptor left: it stops with
    exit status 1 and the cause in one line, never taking the live node's channel for
    none listening (it would unlink its socket), and the live node answers through it."""
    from federation import PlatformConfig

    station = Station(tmp_path)
    try:
        station.start("python")
        config = PlatformConfig.load(station.dir / "station-python.toml")
        env = {**station.env, "PYTHONPATH": str(Path(__file__).parents[1])}
        path = channel_path_in(config, env)
        assert path.is_socket()
        before = path.stat().st_ino
        done = subprocess.run(
            [sys.executable, "-c", _TWIN_OUT_OF_FDS, "station-python.toml"],
            capture_output=True,
            text=True,
            cwd=station.dir,
            env=env,
            timeout=60,
        )
        assert done.returncode == 1, (done.stdout, done.stderr)
        assert "Traceback" not in done.stderr and "ready" not in done.stdout
        (line,) = done.stderr.splitlines()
        assert line.startswith("dyknow node: station-python.toml: cannot tell whether a node")
        assert "out of file descriptors" in line and "RLIMIT_NOFILE" in line
        assert path.is_socket() and path.stat().st_ino == before  # the live node's, kept
        answer = station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        assert _samples(answer, "temperature")
        assert station.node is not None and station.node.poll() is None
    finally:
        out, err = station.stop()
    assert "station stopped" in out and "Traceback" not in err


def channel_path_in(config: object, env: dict[str, str]) -> Path:
    """The local channel of ``config`` under the station's runtime directory."""
    import os
    from unittest import mock

    from federation._local import channel_path

    with mock.patch.dict(os.environ, {"XDG_RUNTIME_DIR": env["XDG_RUNTIME_DIR"]}):
        return channel_path(config)  # type: ignore[arg-type]


# -- one platform, one process: the duplicate seen though its link comes up a little late ----


async def _delaying_proxy(port: int, to: int, delay: float) -> asyncio.Server:
    """A TCP forwarder on ``port`` to ``to`` that connects onward ``delay`` s late."""

    async def pipe(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        with contextlib.suppress(Exception):
            while data := await r.read(65536):
                w.write(data)
                await w.drain()
        w.close()

    async def serve(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await asyncio.sleep(delay)
        r2, w2 = await asyncio.open_connection("127.0.0.1", to)
        await asyncio.gather(pipe(r, w2), pipe(r2, w))

    return await asyncio.start_server(serve, "127.0.0.1", port)


async def test_a_second_node_of_a_name_is_refused_though_its_link_to_the_first_is_late() -> None:
    """A third platform answering first must not hide the running one still being connected."""
    from types import SimpleNamespace

    from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
    from federation._local import PlatformAliveError, refuse_duplicate

    fed = "demo"
    pa, pc, pb, proxy = (free_tcp_port() for _ in range(4))
    async with contextlib.AsyncExitStack() as stack:
        a = await stack.enter_async_context(ZenohTransport(ZenohConfig.loopback(pa)))
        c = await stack.enter_async_context(ZenohTransport(ZenohConfig.loopback(pc)))
        await a.declare_token(wire_key(fed, "alive", "x"))
        await c.declare_token(wire_key(fed, "alive", "c"))
        server = await _delaying_proxy(proxy, pa, 0.4)
        stack.push_async_callback(server.wait_closed)
        stack.callback(server.close)
        b = await stack.enter_async_context(
            ZenohTransport(ZenohConfig.loopback(pb, connect=[pc, proxy]))
        )
        with pytest.raises(PlatformAliveError):
            # no key to read: no local channel to look at, only the network
            config = SimpleNamespace(federation=fed, name="x", key=Path("no-such.key"))
            # the answer's bound: 5 s, not the default 1 s, whose 0.6 s beyond the proxy's
            # delay a loaded machine used up once before the late link was up
            await refuse_duplicate(b, config, wait=5.0)  # type: ignore[arg-type]
