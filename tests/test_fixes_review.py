"""A review's probes of sealing after a re-key and of a node out of file descriptors.

Each asserts what a user relies on, attacking the code the way it would be met: a
session table whose peer was re-keyed from another thread, a second start of a live
node's config in a process that has no file descriptor left.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from _node_example import Station, _samples

from agents import KeyPair
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
