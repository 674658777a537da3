"""What the flood benchmarks share: the federation's processes, the pipes, the attacker's pace.

``bench.kxflood`` (key exchanges) and ``bench.dfflood`` (directory events) each run a
victim platform, a member and an attacker as spawned processes on loopback zenoh, told
what to do over pipes; the attacker is a plain zenoh client with no key of the
federation, sending at a steady rate until told to stop.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import sys
import time
import uuid
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import orjson

from agents._security import TrustStore
from agents.keys import gen_keys, trust_keys
from agents.transports import ZenohConfig, free_tcp_port

VICTIM, MEMBER, ABSENT = "uav-v", "uav-m", "uav-q"  # uav-q: trusted, never runs
START = 30.0  # a spawned interpreter imports zenoh and pydantic: seconds when loaded
WAIT = 15.0  # the bound on any other wait
FLOOD_RATE, FLOOD_SECONDS = 10_000.0, 25.0  # what the attacker sends per second, how long


def quick_run(doc: str | None) -> bool:
    """Whether ``--quick`` was given (only the victim that sheds); ``--help`` prints ``doc``."""
    args = sys.argv[1:]
    if "--help" in args or "-h" in args:
        print(f"{doc or ''}\n--quick: only the victim that sheds (no comparison); --help: this")
        raise SystemExit(0)
    return "--quick" in args


def recv(conn: Connection, what: str, timeout: float = WAIT) -> Any:
    """The next message on ``conn``; fails naming ``what`` after ``timeout`` s."""
    if not conn.poll(timeout):
        raise AssertionError(f"timed out waiting for {what}")
    return conn.recv()


def summed_up(victim: Connection, counter: str, stage: str, ask: Any = "report") -> dict[str, Any]:
    """The victim's report once its ``stage`` audit summaries add up to its ``counter``.

    The victim sums a flood up once a second: its last summary comes up to a second
    after the flood. Bounded by WAIT; the report as it is then, whatever it says.
    ``ask`` is what the victim's pipe takes for a report.
    """
    deadline = time.monotonic() + WAIT
    while True:
        victim.send(ask)
        report: dict[str, Any] = recv(victim, "the victim's report")
        summed = sum(r["count"] for r in report["records"] if r.get("stage") == stage)
        if summed == report[counter] or time.monotonic() > deadline:
            return report
        time.sleep(0.1)  # the summaries are written on the victim's clock: nothing to await


def zenoh_client(endpoint: str) -> Any:
    """A plain zenoh session in client mode connected to ``endpoint``: the attacker's."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", orjson.dumps([endpoint]).decode())
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def flood_at(
    conn: Connection,
    send: Callable[[int], object],
    *,
    rate: float = FLOOD_RATE,
    seconds: float = FLOOD_SECONDS,
    most: int | None = None,
) -> None:
    """Call ``send(i)`` ``rate`` times a second until told to stop on ``conn`` (or
    ``seconds`` or ``most`` sends are reached); then send ``(sent, seconds taken)`` on it.
    """
    sent, start = 0, time.monotonic()
    chunk = max(1, int(rate / 100))  # a chunk every 10 ms
    while (most is None or sent < most) and time.monotonic() - start < seconds:
        if conn.poll():
            break  # told to stop
        for _ in range(chunk):
            send(sent)
            sent += 1
        time.sleep(max(0.0, sent / rate - (time.monotonic() - start)))
    conn.send((sent, time.monotonic() - start))


class FloodFederation:
    """A federation of the victim, the member and uav-q, with its spawned processes.

    A subclass names the platforms' process entry (``node_main``, called with the role,
    its zenoh config, the federation, the key directory, the trust file, its pipe and
    whether the victim sheds) and the prefix of the federation's and the processes' names.
    """

    prefix = "flood"

    @staticmethod
    def node_main(
        role: str, config: dict[str, Any], fed: str, keys: str, trust: str, conn: Any, shed: bool
    ) -> None:
        """A platform's process (the subclass's)."""
        raise NotImplementedError

    def __init__(self, tmp_path: Path) -> None:
        self.fed = f"{self.prefix}-{uuid.uuid4().hex[:8]}"
        self.keydir, self.trust_file = tmp_path / "keys", tmp_path / "trust.json"
        trust_keys(
            self.trust_file,
            [gen_keys(n, self.keydir)[2] for n in (VICTIM, MEMBER, ABSENT)],
            federation=self.fed,
        )
        self.trust = TrustStore.load(self.trust_file)
        self.port = free_tcp_port()
        self.ctx = multiprocessing.get_context("spawn")
        self.procs: list[Any] = []

    def spawn(self, target: Callable[..., None], args: tuple[Any, ...], name: str) -> Connection:
        """Start ``target(*args, pipe)`` in a process of its own; our end of the pipe."""
        here, there = self.ctx.Pipe()
        proc = self.ctx.Process(target=target, args=(*args, there), name=name)
        proc.start()
        self.procs.append(proc)
        return here

    def node(self, role: str, listen: int, connect: list[int], *, shed: bool = True) -> Connection:
        """Start platform ``role``; its pipe (it says "ready" when it is)."""
        config = ZenohConfig.loopback(listen, connect=connect).model_dump()
        keys, trust = str(self.keydir), str(self.trust_file)
        return self.spawn(
            _node_entry,
            (type(self).node_main, role, config, self.fed, keys, trust, shed),
            f"{self.prefix}-{role}",
        )

    def close(self, pipes: list[Connection], stop: Any = "stop") -> None:
        """Send ``stop`` on each of ``pipes``, then make sure every child ends."""
        for pipe in pipes:
            with contextlib.suppress(OSError):
                pipe.send(stop)
        for proc in self.procs:
            proc.join(timeout=15)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=5)


def _node_entry(
    main: Callable[..., None],
    role: str,
    config: dict[str, Any],
    fed: str,
    keys: str,
    trust: str,
    shed: bool,
    conn: Connection,
) -> None:
    """A platform's process: ``main`` with its arguments in the order it takes them."""
    main(role, config, fed, keys, trust, conn, shed)
