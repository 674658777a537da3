"""A review's probes of sealing after a re-key and of a node out of file descriptors.

Each asserts what a user relies on, attacking the code the way it would be met: a
session table whose peer was re-keyed from another thread, a second start of a live
node's config in a process that has no file descriptor left.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from _node_example import Station, _samples

from agents import KeyPair, TrustStore
from tests.test_security import ACL, KEYS, Clock, connect, make_platform


def test_a_session_of_a_key_no_longer_trusted_asks_for_renewal() -> None:
    """`needs_renewal` is True when there is no session to seal with (its docstring),
    as `session_for` says after a re-key: the renewal asked after each message sent must
    not take the session of the old key for a fresh one."""
    clock = Clock()
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    assert not a.table.needs_renewal("uav-b")  # fresh, of the key trusted
    assert a.trust.add("uav-b", KeyPair.generate("uav-x").public_key, replace=True)
    assert a.table.session_for("uav-b") is None
    assert a.table.needs_renewal("uav-b")
    # the agreed key back, in another key object (as another store holds it): by value
    assert a.trust.add("uav-b", KEYS["uav-b"].public_key, replace=True)
    assert a.table.session_for("uav-b") is not None
    assert not a.table.needs_renewal("uav-b")
    a.trust.remove("uav-b")
    assert a.table.needs_renewal("uav-b")


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


@pytest.mark.timeout(90)
async def test_a_batch_waiting_as_its_platform_is_rekeyed_is_lost_and_counted(
    tmp_path: Path,
) -> None:
    """A batch for the operator waits for its turn's end as a trust reload (SIGHUP's own
    thread) gives the operator another key: it is not sealed on the old key's session,
    and it is lost and counted in ``batches_lost`` (docs/security.md), not dropped
    unsaid; the revocation that follows finds nothing more of it waiting."""
    import threading

    from federation._cli_common import wait_for_members
    from tests.test_revoke_races import _hello, _pair
    from tests.test_sharing_reload import _until

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(o, "station", 30)
        ia = s.interface
        await ia.send("operator", _hello(s, "operator"))  # a session agreed
        await _until("the turn's batch closed", lambda: "operator" not in ia._outbox)
        await ia.send("operator", _hello(s, "operator"))  # alone: the turn's batch opens
        assert ia.join_batch("operator", _hello(s, "operator"))  # waits for the turn's end
        trust = ia.trust
        new = TrustStore(
            trust.federation,
            {
                "station": trust.public_key("station"),
                "operator": KeyPair.generate("operator").public_key,
            },
        )
        lost, unsent = ia.batches_lost, ia.unsent_revoked
        worker = threading.Thread(target=s.reload_trust, args=(new,))
        worker.start()
        worker.join(10)  # the loop held meanwhile, as a busy one is
        assert not worker.is_alive()
        assert "operator" in ia._outbox and ia.revoked == 0
        await _until("the batch's turn ended", lambda: "operator" not in ia._outbox)
        assert ia.batches_lost == lost + 1
        await _until("the revocation", lambda: ia.revoked == 1)
        assert ia.unsent_revoked == unsent
        assert ia.sessions.session_for("operator") is None
