"""An outsider's query floods on the watch, directory and identity keys: shed before the loop.

The victim and a member run in spawned processes (the harness of `bench.kxflood`, as in
`tests/test_kx_flood.py`), or a `dyknow node` runs (`_node_example.Station`); an attacker
process with a plain zenoh session (no key of the federation) queries the key as fast as
it can. The member is still served; the flood is shed cheaply, counted and summed up in
the audit; the key answers again once the flood is over.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import multiprocessing
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import orjson
import pytest
from _load import CpuSlowdownMeter, cpu_slowdown
from _node_example import Station

from agents import wire_key
from agents._df import DF_QUERY_RATE
from agents._interface import WATCH_RATE
from agents._security import KeyPair, watch_request
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
from bench._flood import (
    FLOOD_SECONDS,
    START,
    VICTIM,
    WAIT,
    recv,
    summed_up,
)
from bench.kxflood import (
    PACE_N,
    Federation,
    attacker_main,
    figures,
    go,
)
from federation._local import IDENTITY_RATE

pytestmark = pytest.mark.timeout(180)


# The victim's CPU per query of a flood below, in µs, on the CPU of
# `_load.CPU_WORK_SECONDS` (scaled by `CpuSlowdownMeter` on a slower one). Measured there:
# ~11-31 for both when shed; ~47-53 (watch) and ~75 (directory) when every query reaches
# the event loop. Others' load stretches CPU time far less than latency, yet up to ~2x
# (a core shared): the slowdown is measured over the flood itself.
WATCH_SHED_CPU_US = 35.0
DF_SHED_CPU_US = 40.0


def _forged_watch_requests(fed: str) -> list[bytes]:
    """Well-formed watch requests in the victim's name, signed with the attacker's keys."""
    out = [watch_request(KeyPair.generate(VICTIM), fed) for _ in range(2000)]
    return out + [os.urandom(200) for _ in range(200)]


async def _ask(port: int, key: str, payload: bytes) -> list[bytes]:
    """A plain query of ``key`` from a transport of our own: the replies' payloads."""
    config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
    async with ZenohTransport(config) as t:
        for _ in range(20):  # the first query may go out before the route is known
            replies = await t.query(key, payload, timeout=2.0)
            if replies:
                return [r.payload for r in replies]
            await asyncio.sleep(0.2)
    return []


@dataclass
class _Flooded:
    """A flood of queries on one key of the victim, and what it did."""

    f: Federation
    during: list[float]
    sent: int
    seconds: float
    cpu: float  # the victim's CPU seconds from the flood's start to its end
    handled: int  # queries of the flood's kind that reached the victim's event loop meanwhile
    report: dict[str, Any]
    slower: float  # how much slower this CPU ran than `_load`'s reference during the flood

    def check(self, shed: int, stage: str, cpu_us: float, rate: float) -> None:
        """The member served; the flood shed cheaply, counted, summed up.

        Before the event loop: at most ``rate`` a second (bursts of as many) reached it.
        A count, whatever the CPU and the load: a victim starved of CPU costs little per
        query sent even when it sheds nothing, zenoh dropping the rest. Cheaply: at most
        ``cpu_us`` of the victim's CPU per query sent, times how much slower this CPU ran
        during the flood than the one it was measured on (measured before it, the
        slowdown swung 1.3-2.4 on a busy 2-core machine, the other core's load moving it
        within seconds). Bounded by CPU time, not by the member's latency: with three
        processes and the attacker's on a busy machine that measures the machine; CPU time
        is what the flood takes from the victim, whatever else runs.
        """
        cost = self.cpu / self.sent * 1e6
        slower = self.slower
        bound = cpu_us * slower
        print(
            f"\nmember during flood: {figures(self.during)}"
            f"\nattacker: {self.sent} in {self.seconds:.1f} s; victim shed {shed}, "
            f"{self.handled} on its event loop, "
            f"CPU {cost:.1f} µs per query (bound {bound:.1f}: {cpu_us:g} times this "
            f"CPU's slowdown {slower:.2f} during the flood; {cpu_slowdown():.2f} after)"
        )
        # a flood however busy the machine: the attacker too gets less CPU on a loaded one
        assert self.sent / self.seconds > 5000 / slower, "the attacker did not flood"
        # every one of the member's requests answered during the flood (pace asserts each)
        assert len(self.during) == PACE_N
        budget = rate * (1 + self.seconds + 2)  # a burst, and the flood's time with a margin
        assert self.handled <= budget, (self.handled, budget)
        assert cost <= bound, (cost, bound, figures(self.during))
        assert shed >= 0.5 * self.sent, (shed, self.sent)
        summaries = [r for r in self.report["records"] if r.get("stage") == stage]
        assert summaries and sum(r["count"] for r in summaries) == shed
        assert all(r["verdict"] == "dropped" for r in summaries)
        # summed up: a flood of queries is not a flood of records
        assert len(summaries) <= 10 * (self.seconds + 3)


@contextlib.contextmanager
def _flood(tmp_path: Path, what: str, payloads: Callable[[str], list[bytes]]) -> Iterator[_Flooded]:
    """Victim and member spawned; a plain zenoh attacker floods ``what`` of the victim."""
    f = Federation(tmp_path)
    pipes: list[Connection] = []
    try:
        victim, attacker, member = f.started(what, pipes)
        member.send("warm")  # its session with the victim agreed before the flood
        recv(member, "the member's first request")
        victim.send("report")
        before = recv(victim, "the victim's report")
        with CpuSlowdownMeter() as meter:
            go(attacker, payloads(f.fed))
            time.sleep(0.5)
            member.send("pace")
            during = recv(member, "the member's requests during the flood", 3 * FLOOD_SECONDS)
            with contextlib.suppress(OSError):
                attacker.send("stop")
        sent, seconds = recv(attacker, "the attacker's count")
        victim.send("report")
        after = recv(victim, "the victim's report")
        cpu = after["cpu"] - before["cpu"]
        handled = after["answered"][what] - before["answered"][what]
        report = summed_up(victim, f"{what}_shed", f"{what}-shed")
        yield _Flooded(f, during, sent, seconds, cpu, handled, report, meter.slowdown())
    finally:
        f.close(pipes)


@pytest.mark.usefixtures("no_leftover_children")
def test_a_watch_request_flood_is_shed_before_the_event_loop(tmp_path: Path) -> None:
    """10 000 forged watch requests/s (the watch key, not kx): shed, counted, audited.

    Unshed, each request reaches the event loop as a task: the victim's CPU doubled
    against a key-exchange flood and a member's p99 neared 20 ms. At most WATCH_RATE/s
    go on; the owner can watch once the flood is over.
    """
    with _flood(tmp_path, "watch", _forged_watch_requests) as run:
        run.check(run.report["watch_shed"], "watch-shed", WATCH_SHED_CPU_US, WATCH_RATE)
        first = next(r for r in run.report["records"] if r.get("stage") == "watch-shed")
        assert first["reason"].startswith("watch requests shed: ")
        owner = KeyPair.load(run.f.keydir / f"{VICTIM}.key")
        key = wire_key(run.f.fed, "watch", VICTIM)
        replies = asyncio.run(_ask(run.f.port, key, watch_request(owner, run.f.fed)))
        assert replies and orjson.loads(replies[0])["watching"] is True


@pytest.mark.usefixtures("no_leftover_children")
def test_a_directory_query_flood_is_shed_before_the_event_loop(tmp_path: Path) -> None:
    """10 000 queries/s of the victim's ``df/<platform>`` by an outsider: shed, counted.

    Unshed, each is answered (a task and the public directory's JSON): the victim took
    ~76% of a core and a member's p99 went from ~3 ms to ~250 ms. At most DF_QUERY_RATE/s
    are answered; the directory is answered again once the flood is over.
    """
    with _flood(tmp_path, "df", lambda fed: [b""] * 100) as run:
        run.check(run.report["df_shed"], "df-shed", DF_SHED_CPU_US, DF_QUERY_RATE)
        first = next(r for r in run.report["records"] if r.get("stage") == "df-shed")
        assert first["reason"].startswith("directory queries shed: ")
        replies = asyncio.run(_ask(run.f.port, wire_key(run.f.fed, "df", VICTIM), b""))
        assert replies  # a signed directory statement whose body is the public services
        statement = orjson.loads(replies[0])
        assert statement["kind"] == "df" and isinstance(orjson.loads(statement["body"]), list)


@pytest.mark.timeout(150)
def test_an_identity_query_flood_on_a_node_is_shed_before_the_event_loop(
    tmp_path: Path,
) -> None:
    """10 000 queries/s of a `dyknow node`'s ``identity/<platform>`` by an outsider.

    Unshed, each is answered on the event loop (the node's host name and pid): ~54% of a
    core. At most IDENTITY_RATE/s are answered; the rest are counted and summed up in the
    node's audit; a second node of the same name is still told who runs it.
    """
    station = Station(tmp_path)
    conf = station.dir / "station-python.toml"
    text = conf.read_text()
    conf.write_text(text.replace("\n[transport]", '\naudit = "audit.jsonl"\n\n[transport]', 1))
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    key = wire_key(station.federation, "identity", "station")
    attacker = ctx.Process(target=attacker_main, args=(f"tcp/127.0.0.1:{station.port}", key, there))
    try:
        station.start("python")
        attacker.start()
        assert recv(here, "the attacker", START) == "ready"
        go(here, [b""] * 10)
        time.sleep(3.0)
        here.send("stop")
        sent, seconds = recv(here, "the attacker's count")
        # a flood: far more than the node answers, however slow this machine ran the
        # attacker (a throughput bound failed on a busy one, the shedding unchanged)
        assert sent > 20 * IDENTITY_RATE * seconds, f"the attacker did not flood: {sent}"
        audit = station.dir / "audit.jsonl"

        def shed() -> list[dict[str, Any]]:
            lines = audit.read_text().splitlines() if audit.exists() else []
            return [r for r in map(json.loads, lines) if r.get("stage") == "identity-shed"]

        deadline = time.monotonic() + WAIT
        while sum(r["count"] for r in shed()) < 0.5 * sent and time.monotonic() < deadline:
            time.sleep(0.2)
        records = shed()
        total = sum(r["count"] for r in records)
        assert total >= 0.5 * sent, (total, sent)
        assert all(r["verdict"] == "dropped" for r in records)
        assert records[0]["reason"].startswith("identity queries shed: ")
        assert len(records) <= seconds + 5  # summed up, once a second
        # the query still answers once the flood is over: a twin is told who runs it
        twin = station.dir / "twin.toml"
        twin.write_text(conf.read_text().replace("listen = [", "connect = ["))
        node = station.node
        assert node is not None
        done = station.command("node", "--config", str(twin), timeout=60)
        assert done.returncode == 2, done.stderr
        assert f"pid {node.pid} on host" in done.stderr
    finally:
        with contextlib.suppress(OSError):
            here.send("stop")
        attacker.join(timeout=10)
        if attacker.is_alive():
            attacker.kill()
        _, err = station.stop()
    assert "Traceback" not in err
