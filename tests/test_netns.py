"""deploy/netns.py: the zenoh topology for real, one Linux network namespace per service.

The script is run as a user runs it (a subprocess of this interpreter): ``up`` builds the
namespaces, the bridge and the five processes; ``check`` asks from the operator's namespace
which platforms are alive; ``down`` must leave no namespace, link or process behind.

Needs root and iproute2 (CI runs as root): without them the test is skipped on a developer's
machine and FAILS when CI is set, saying what is missing. Runs in parallel with anything:
names carry this process's id, and the namespaces share nothing with the machine's network
(nor with another run's, even on the same subnet).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "deploy" / "netns.py"
PREFIX = f"dkt{os.getpid()}"
SUBNET = "10.231.0"
ADDRESSES = {"router": 10, "uav-a": 11, "uav-b": 12, "uav-c": 13, "operator": 20}
UAVS = {"uav-a", "uav-b", "uav-c"}


def _missing() -> str | None:
    """What this machine lacks for network namespaces, or None."""
    if sys.platform != "linux":
        return "network namespaces are Linux only"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root (CI runs the tests as root)"
    return None


def _unavailable(reason: str) -> None:
    """Skip on a developer's machine; in CI a missing prerequisite is a failure."""
    if os.environ.get("CI"):
        pytest.fail(f"deploy/netns.py cannot run in CI: {reason}", pytrace=False)
    pytest.skip(reason)


def _script(*args: str | Path, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def _in_namespace(ns: str, code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["ip", "netns", "exec", ns, sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=20,
        check=False,
    )


def _leftovers(rundir: Path) -> list[str]:
    """Namespaces, links in this namespace and live processes the run left behind."""
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True)
    left = [f"namespace {n}" for n in out.stdout.split() if n.startswith(f"{PREFIX}-")]
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True, check=True)
    left += [f"link {line}" for line in links.stdout.splitlines() if PREFIX in line]
    marker = f"{rundir}/".encode()
    for proc in Path("/proc").iterdir():
        try:
            if marker in (proc / "cmdline").read_bytes():
                state = (proc / "stat").read_text().rsplit(")", 1)[-1].split()[0]
                if state != "Z":
                    left.append(f"process {proc.name}")
        except OSError:
            continue  # gone meanwhile, or not a process directory
    return left


def _connects(ns: str, host: str, port: int) -> subprocess.CompletedProcess[str]:
    return _in_namespace(
        ns, f"import socket; socket.create_connection(({host!r}, {port}), timeout=5).close()"
    )


@pytest.mark.timeout(60)
def test_the_operator_sees_the_uavs_across_namespaces_and_down_leaves_nothing(
    tmp_path: Path,
) -> None:
    reason = _missing()
    if reason:
        _unavailable(reason)
    rundir = tmp_path / "run"
    try:
        up = _script(
            *("up", "--dir", rundir, "--prefix", PREFIX, "--subnet", SUBNET, "--timeout", "15"),
            timeout=40,
        )
        if up.returncode == 2:  # the arguments are valid: the machine lacks something
            _unavailable(up.stderr.strip())
        assert up.returncode == 0, f"up failed:\n{up.stdout}\n{up.stderr}"
        assert "all up" in up.stdout

        # Each service alone in its namespace: lo plus one address on our bridge, and no
        # route but the subnet's, so nothing can go anywhere but through the bridge.
        for service, host in ADDRESSES.items():
            ns = f"{PREFIX}-{service}"
            addrs = subprocess.run(
                ["ip", "-n", ns, "-4", "-o", "addr"], capture_output=True, text=True, check=True
            ).stdout
            assert sorted(line.split()[3] for line in addrs.splitlines()) == sorted(
                ["127.0.0.1/8", f"{SUBNET}.{host}/24"]
            ), addrs
            routes = subprocess.run(
                ["ip", "-n", ns, "-4", "route"], capture_output=True, text=True, check=True
            ).stdout
            assert [r.split()[0] for r in routes.splitlines()] == [f"{SUBNET}.0/24"], routes

        # The federation formed only through the router, from the operator's namespace.
        check = _script("check", "--dir", rundir, "--json", "--timeout", "15", timeout=30)
        assert check.returncode == 0, f"check failed:\n{check.stdout}\n{check.stderr}"
        result = json.loads(check.stdout.splitlines()[-1])
        assert set(result["platforms"]) >= UAVS, result
        for uav in UAVS:  # each is listed with its federation service
            assert {s["type"] for s in result["platforms"][uav]} == {"dyknow-federation"}
        assert isinstance(result["labels"]["uav-a"]["labels"], list)  # uav-a answered

        # The router is in its own namespace: the operator reaches it at its address on
        # the bridge, not on its own loopback (where a wrongly configured client would look).
        router = f"{SUBNET}.{ADDRESSES['router']}"
        reach = _connects(f"{PREFIX}-operator", router, 7447)
        assert reach.returncode == 0, reach.stderr
        loopback = _connects(f"{PREFIX}-operator", "127.0.0.1", 7447)
        assert "ConnectionRefusedError" in loopback.stderr, loopback

        status = _script("status", "--prefix", PREFIX)
        assert status.returncode == 0, status.stdout + status.stderr
        assert status.stdout.count("running (pid") == len(ADDRESSES), status.stdout

        # By prefix only, as after a crash that lost the run directory's state.
        down = _script("down", "--prefix", PREFIX, timeout=40)
        assert down.returncode == 0, f"down failed:\n{down.stdout}\n{down.stderr}"
        assert _leftovers(rundir) == []
        again = _script("down", "--prefix", PREFIX)
        assert again.returncode == 0, again.stderr
        assert "no namespace of" in again.stdout
    finally:
        if _missing() is None and _leftovers(rundir):
            _script("down", "--prefix", PREFIX, "--dir", rundir, "--grace", "2", timeout=40)
            assert _leftovers(rundir) == []


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["up", "--dir", "RUN", "--subnet", "8.8.8"], "--subnet '8.8.8'"),
        (["up", "--dir", "RUN", "--prefix", "Not-OK"], "--prefix 'Not-OK'"),
        (["up"], "--dir is required"),
        (["down"], "--prefix"),
    ],
)
def test_bad_arguments_are_named_and_exit_2(tmp_path: Path, args: list[str], message: str) -> None:
    result = _script(*(str(tmp_path) if a == "RUN" else a for a in args))
    assert result.returncode == 2, result
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_without_root_it_says_so_and_exits_2(tmp_path: Path) -> None:
    # The unprivileged user must be able to read the script wherever this checkout lives
    # (a clone in a 0700 directory is not readable by it): it runs a copy from a directory
    # of its own that everyone may read.
    with tempfile.TemporaryDirectory(prefix="netns-test-") as readable:
        os.chmod(readable, 0o755)
        script = Path(readable) / "netns.py"
        shutil.copyfile(SCRIPT, script)
        script.chmod(0o644)
        command = [sys.executable, str(script), "up", "--dir", str(tmp_path / "run")]
        if os.geteuid() == 0:
            setpriv = shutil.which("setpriv")
            if setpriv is None:
                _unavailable("setpriv (util-linux) is needed to drop root for this test")
            command = [str(setpriv), "--reuid=65534", "--regid=65534", "--clear-groups", *command]
        result = subprocess.run(
            command, capture_output=True, text=True, timeout=30, check=False, cwd=readable
        )
    assert result.returncode == 2, result
    assert "need root" in result.stderr or "`ip` command" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "run").exists()  # nothing was made
