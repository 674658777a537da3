"""Shared test settings."""

import os

from hypothesis import HealthCheck, settings

# Shared 2-core machines stall for tens of milliseconds: a per-example deadline only makes
# noise. In CI the examples are derandomized so a red run can be replayed exactly.
settings.register_profile("dev", deadline=None)
settings.register_profile(
    "ci", deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


# --- mosquitto, for the MQTT transport's tests ----------------------------------------------

import contextlib  # noqa: E402
import multiprocessing  # noqa: E402
import shutil  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from agents.transports import free_tcp_port  # noqa: E402


def _mosquitto_executable() -> str:
    found = shutil.which("mosquitto")
    if found:
        return found
    # Debian installs it in /usr/sbin, which is not on every user's PATH.
    if Path("/usr/sbin/mosquitto").is_file():
        return "/usr/sbin/mosquitto"
    pytest.fail(
        "mosquitto is not installed, and the MQTT transport's tests need a real broker: "
        "run `make test` (it installs mosquitto from Debian's packages when missing) or "
        "`apt-get install -y mosquitto`",
        pytrace=False,
    )


@pytest.fixture
def no_leftover_children() -> Iterator[None]:
    """Kill every multiprocessing child still alive after the test (``usefixtures`` it)."""
    yield
    for proc in multiprocessing.active_children():
        proc.kill()
        proc.join(timeout=5)


@contextlib.contextmanager
def _running_mosquitto(workdir: Path) -> Iterator[tuple[str, int, subprocess.Popen[bytes]]]:
    """A mosquitto broker on a free loopback port, accepting: (host, port, process)."""
    exe = _mosquitto_executable()
    host, port = "127.0.0.1", free_tcp_port()
    conf = workdir / "mosquitto.conf"
    conf.write_text(
        f"listener {port} {host}\n"
        "allow_anonymous true\n"
        "persistence false\n"
        "set_tcp_nodelay true\n"
        "log_dest stdout\n"
    )
    log_path = workdir / "mosquitto.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen([exe, "-c", str(conf)], stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 10.0
        while True:
            if proc.poll() is not None:
                pytest.fail(
                    f"mosquitto exited with {proc.returncode} at start:\n{log_path.read_text()}",
                    pytrace=False,
                )
            try:
                socket.create_connection((host, port), timeout=0.2).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail(
                        f"mosquitto did not accept connections on {host}:{port} within 10 s:\n"
                        f"{log_path.read_text()}",
                        pytrace=False,
                    )
                time.sleep(0.02)  # nothing to await: the port either accepts or not yet
        yield host, port, proc
    finally:
        proc.kill()  # SIGKILL ends a stopped (SIGSTOP) broker too
        proc.wait(timeout=10)


@pytest.fixture(scope="session")
def mosquitto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, int]]:
    """A mosquitto broker of our own on a free loopback port: (host, port)."""
    with _running_mosquitto(tmp_path_factory.mktemp("mosquitto")) as (host, port, _):
        yield host, port


@pytest.fixture
def own_mosquitto(tmp_path: Path) -> Iterator[tuple[str, int, subprocess.Popen[bytes]]]:
    """A broker for this test alone, which it may stall (SIGSTOP): (host, port, process)."""
    with _running_mosquitto(tmp_path) as running:
        yield running


# --- a test about to hit its timeout tells where its tasks wait ----------------------------

_DUMP_BEFORE = 5.0  # s before pytest-timeout's limit


def _dump_tasks(nodeid: str) -> None:
    """Print every asyncio task's stack (a test about to time out: where does it wait?).

    Runs on a timer thread while the test's loop is, as a rule, idle in its selector;
    pytest-timeout shows only threads' stacks, and a hung test's loop thread is always
    in ``select``: the tasks' own stacks are what tells a hang's cause.
    """
    import asyncio
    import gc
    import sys

    tasks = [o for o in gc.get_objects() if isinstance(o, asyncio.Task) and not o.done()]
    print(f"\n--- {nodeid}: {len(tasks)} pending asyncio task(s) ---", file=sys.stderr)
    for task in tasks:
        print(f"{task.get_name()}:", file=sys.stderr)
        try:
            # a task's own stack stops at its coroutine: the awaits below it tell the wait
            awaited: object = task.get_coro()
            for _ in range(40):
                if type(awaited).__name__ == "async_generator_asend":
                    # an ``async with`` over a generator: its frame is the generator's
                    gens = [g for g in gc.get_referents(awaited) if hasattr(g, "ag_frame")]
                    awaited = gens[0] if gens else awaited
                frame = (
                    getattr(awaited, "cr_frame", None)
                    or getattr(awaited, "gi_frame", None)
                    or getattr(awaited, "ag_frame", None)
                )
                if frame is None:
                    break
                code = frame.f_code
                print(f"  {code.co_filename}:{frame.f_lineno} {code.co_name}", file=sys.stderr)
                nxt = (
                    getattr(awaited, "cr_await", None)
                    or getattr(awaited, "gi_yieldfrom", None)
                    or getattr(awaited, "ag_await", None)
                )
                if nxt is None:
                    break
                awaited = nxt
            print(f"  waits on {repr(awaited)[:300]}", file=sys.stderr)
        except Exception as exc:  # the task moved on under us: go on with the others
            print(f"  (stack unreadable: {exc!r})", file=sys.stderr)


@pytest.fixture(autouse=True)
def _tasks_told_before_timeout(request: pytest.FixtureRequest) -> Iterator[None]:
    """Dump the pending asyncio tasks' stacks shortly before pytest-timeout fails the test."""
    import threading

    marker = request.node.get_closest_marker("timeout")
    limit = float(marker.args[0]) if marker and marker.args else request.config.getini("timeout")
    if not limit or float(limit) <= _DUMP_BEFORE:
        yield
        return
    timer = threading.Timer(float(limit) - _DUMP_BEFORE, _dump_tasks, (request.node.nodeid,))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
