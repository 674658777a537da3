"""Where an ACL round trip's time goes, stage by stage: ``python -m bench._acl_trace [N]``.

The zenoh round trip of ``bench.acl`` (``request`` from ``asker@bench-a`` to the gateway of
``bench-b``, a spawned node), with probes wrapped around the steps a message takes in
both processes. Each probe notes ``time.perf_counter_ns()`` (CLOCK_MONOTONIC: one clock
for every process of the host), so one round trip reads as a timeline across both:

    asker: request → send → put ─┐                      ┌→ callback → wake → got → open
                                 └→ node: callback → wake → got → open → take → deliver
         → handler → reply → send → put ──────────────────┘        → take → deliver → resumed

``callback``: zenoh's thread queues the sample in the inbox; ``wake``: the event loop runs
the inbox's wake-up; ``got``: the Interface Agent's receive task has the item; ``take``:
its one-call path (``_take_now``) starts; ``deliver``: the agent's mailbox (or the waiting
conversation) gets the message. Printed: each gap's median and p90 (µs) over N round
trips after a warm-up, the round trip itself, each side's event-loop thread CPU per round
trip (load-robust), the put's own thread CPU, how often the one-call path declined a
message, and from the scheduler (``/proc/<pid>/task/*/schedstat``) each side's time
runnable but waiting for a CPU and the CPU of all its threads (zenoh's included) per
round trip. With ``DYKNOW_EVENT_LOOP=asyncio`` also the loop iterations per round trip
on each side (uvloop's cannot be counted from Python).

The probes cost ~0.2-0.5 µs each (about 15 a side per round trip): the round trip here is
a little slower than ``bench.acl``'s. For a measurement, not for a production process:
it wraps private methods of the agents' classes in both processes.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

N = 2000
WARMUP = 300

_NS = time.perf_counter_ns
MARKS: list[tuple[str, int]] = []  # (probe, perf_counter_ns), in this process
PUT_CPU: list[int] = []  # thread CPU (ns) of each ACL put
LOOP_TURNS = [0]  # asyncio loop iterations (DYKNOW_EVENT_LOOP=asyncio only)
AT_TAKE: list[tuple[int, int]] = []  # (loop thread CPU ns, loop iterations) at each take

# the timeline of one round trip: (side, probe), in order; "A" asks, "B" answers
TIMELINE = [
    ("A", "request"),
    ("A", "send"),
    ("A", "put"),
    ("A", "put-done"),
    ("A", "send-done"),
    ("A", "flush"),
    ("B", "callback"),
    ("B", "wake"),
    ("B", "got"),
    ("B", "take"),
    ("B", "deliver"),
    ("B", "take-done"),
    ("B", "handler"),
    ("B", "send"),
    ("B", "put"),
    ("B", "put-done"),
    ("B", "send-done"),
    ("B", "flush"),
    ("A", "callback"),
    ("A", "wake"),
    ("A", "got"),
    ("A", "take"),
    ("A", "deliver"),
    ("A", "take-done"),
    ("A", "resumed"),
]


def mark(probe: str) -> None:
    """Note that ``probe`` was reached now."""
    MARKS.append((probe, _NS()))


def _wrap(cls: Any, name: str, before: str | None, after: str | None = None) -> None:
    """Mark ``before`` on entering ``cls.name`` (a plain method) and ``after`` on leaving."""
    inner = getattr(cls, name)

    @functools.wraps(inner)
    def probed(*args: Any, **kwargs: Any) -> Any:
        if before:
            mark(before)
        result = inner(*args, **kwargs)
        if after:
            mark(after if result is not False else after + "-declined")
        return result

    setattr(cls, name, probed)


def install() -> None:
    """Wrap the probes around the steps of an ACL message (in this process, for good)."""
    from agents import InterfaceAgent
    from agents._agent import Agent
    from agents.transports import ZenohTransport
    from agents.transports._base import Inbox, Subscription
    from federation import GatewayService

    put = ZenohTransport._put

    def probed_put(self: ZenohTransport, key: str, payload: bytes, att: bytes | None) -> None:
        if "/acl/" not in key:
            put(self, key, payload, att)
            return
        mark("put")
        cpu = time.thread_time_ns()
        put(self, key, payload, att)
        mark("put-done")
        PUT_CPU.append(time.thread_time_ns() - cpu)

    setattr(ZenohTransport, "_put", probed_put)  # noqa: B010 - a probe on a method

    subscribe = ZenohTransport.subscribe

    async def probed_subscribe(self: ZenohTransport, key_expr: str, **kw: Any) -> Any:
        sub = await subscribe(self, key_expr, **kw)
        if "/acl/" in key_expr:
            setattr(sub.inbox, "traced", True)  # noqa: B010 - a probe's mark
        return sub

    setattr(ZenohTransport, "subscribe", probed_subscribe)  # noqa: B010
    setattr(Inbox, "traced", False)  # noqa: B010
    inbox_put, inbox_wake = Inbox.put, Inbox._wake

    def probed_inbox_put(self: Any, item: Any) -> None:
        if self.traced:
            mark("callback")
        inbox_put(self, item)

    def probed_wake(self: Any) -> None:
        if self.traced:
            mark("wake")
        inbox_wake(self)

    setattr(Inbox, "put", probed_inbox_put)  # noqa: B010
    setattr(Inbox, "_wake", probed_wake)  # noqa: B010
    anext = Subscription.__anext__

    async def probed_anext(self: Any) -> Any:
        item = await anext(self)
        if self.inbox.traced:
            mark("got")
        return item

    setattr(Subscription, "__anext__", probed_anext)  # noqa: B010
    _wrap(InterfaceAgent, "_take_now", "take", "take-done")
    take_now = InterfaceAgent._take_now

    def counted_take(*args: Any) -> Any:
        AT_TAKE.append((time.thread_time_ns(), LOOP_TURNS[0]))
        return take_now(*args)

    setattr(InterfaceAgent, "_take_now", counted_take)  # noqa: B010
    _wrap(InterfaceAgent, "_flush", "flush")
    _wrap(Agent, "_deliver", "deliver")
    _wrap(GatewayService, "perform", "handler")
    send = InterfaceAgent.send

    async def probed_send(self: Any, platform: str, message: Any) -> None:
        mark("send")
        await send(self, platform, message)
        mark("send-done")

    setattr(InterfaceAgent, "send", probed_send)  # noqa: B010
    run_once = getattr(asyncio.BaseEventLoop, "_run_once", None)
    if run_once is not None:

        def counted(self: Any) -> None:
            LOOP_TURNS[0] += 1
            run_once(self)

        setattr(asyncio.BaseEventLoop, "_run_once", counted)  # noqa: B010


def trace_node_main(*args: Any) -> None:
    """The node of ``bench.acl`` with the probes, reporting its marks once stopped."""
    from bench._acl_node import node_main

    install()
    reports = args[-2]
    node_main(*args)
    reports.put(("trace", os.getpid(), (MARKS, PUT_CPU, AT_TAKE)))


def schedstat(pid: int | str) -> dict[int, tuple[int, int, int]]:
    """Per thread of process ``pid``: (CPU ns, ns waiting for a CPU, times run) from /proc."""
    out: dict[int, tuple[int, int, int]] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            cpu, wait, runs = Path(task, "schedstat").read_text().split()[:3]
        except OSError:  # a thread that ended meanwhile
            continue
        out[int(task.name)] = (int(cpu), int(wait), int(runs))
    return out


def _sched_delta(
    before: dict[int, tuple[int, int, int]], after: dict[int, tuple[int, int, int]], main: int
) -> dict[str, float]:
    """The loop thread's and all threads' waiting for a CPU, and their CPU (ns), over a span."""
    d = {
        tid: tuple(a - b for a, b in zip(after[tid], before.get(tid, (0, 0, 0)), strict=True))
        for tid in after
    }
    loop = d.get(main, (0, 0, 0))
    return {
        "loop_wait": loop[1],
        "loop_runs": loop[2],
        "all_cpu": sum(v[0] for v in d.values()),
        "all_wait": sum(v[1] for v in d.values()),
        "threads": len(after),
    }


async def _asker(keydir: Path, n: int) -> dict[str, Any]:
    """N round trips from this process to a spawned node; this side's and the node's marks."""
    from agents import request
    from bench import acl
    from bench._child import Child

    async with acl.asker_side(keydir) as side:
        _, _, asker, presence, config = side
        args = ("zenoh", config, str(keydir), acl.THERE, acl.FEDERATION)
        child = Child(trace_node_main, args, "acl-trace-node").start()
        try:
            await acl.wait_alive(presence, child, True)
            await acl.first_reply(asker, child)
            await acl.round_trips(asker, WARMUP, "warm-up")
            acl.settle_gc()
            MARKS.clear()
            PUT_CPU.clear()
            turns0 = LOOP_TURNS[0]
            rtts = []
            here, there = os.getpid(), child.pid
            sched0 = schedstat(here), schedstat(there)
            cpu0 = time.thread_time()
            for _ in range(n):
                mark("request")
                t = _NS()
                await request(asker, acl.GATEWAY, acl.QUERY, ontology="dyknow", timeout=5.0)
                rtts.append(_NS() - t)
                mark("resumed")
            cpu = time.thread_time() - cpu0
            sched = {
                "A": _sched_delta(sched0[0], schedstat(here), here),
                "B": _sched_delta(sched0[1], schedstat(there), there),
            }
            turns = LOOP_TURNS[0] - turns0
            mine = list(MARKS)
            child.stop.set()
            theirs, their_put_cpu, at_take = await asyncio.to_thread(
                child.wait_report, "trace", 30.0
            )
        finally:
            await asyncio.to_thread(child.close)
    return {
        "A": mine,
        "B": theirs,
        "rtts": rtts,
        "cpu_a": cpu / n,
        "sched": sched,
        "put_cpu_a": list(PUT_CPU),
        "put_cpu_b": their_put_cpu[-n:],
        "turns_a": turns / n,
        "cpu_b": [c for c, _ in at_take],
        "turns_b": [t for _, t in at_take],
    }


def _rounds(marks: list[tuple[str, int]], start: str) -> list[dict[str, int]]:
    """The marks cut into round trips, each starting at ``start`` (first of each probe kept)."""
    out: list[dict[str, int]] = []
    for probe, ns in marks:
        if probe == start:
            out.append({})
        if out and probe not in out[-1]:
            out[-1][probe] = ns
    return out


def _median_p90(values: list[float]) -> tuple[float, float]:
    s = sorted(values)
    return statistics.median(s), s[min(len(s) - 1, int(0.9 * len(s)))]


def _step(probe: tuple[str, str]) -> str:
    return f"{'asker' if probe[0] == 'A' else 'node'}.{probe[1]}"


def report(res: dict[str, Any], n: int, loop: str) -> list[str]:
    """The timeline's gaps (µs) and the totals, as lines."""
    sides = {"A": _rounds(res["A"], "request"), "B": _rounds(res["B"], "callback")[-n:]}
    lines = [f"ACL round trip over zenoh, stage by stage ({n} round trips, {loop} loop), µs:"]
    count = min(len(sides["A"]), len(sides["B"]))
    for here, there in itertools.pairwise(TIMELINE):
        gaps = [
            (b[there[1]] - a[here[1]]) / 1e3
            for a, b in ((sides[here[0]][i], sides[there[0]][i]) for i in range(count))
            if here[1] in a and there[1] in b
        ]
        if gaps:
            med, p90 = _median_p90(gaps)
            lines.append(f"  {_step(here):<20} → {_step(there):<20} {med:7.1f}  p90 {p90:7.1f}")
    for side, who in (("A", "asker"), ("B", "node")):
        declined = sum(1 for r in sides[side] if "take-done-declined" in r)
        total = len(sides[side])
        lines.append(f"  {who}: messages the one-call path declined: {declined} of {total}")
    med, p90 = _median_p90([r / 1e3 for r in res["rtts"]])
    lines.append(f"  round trip: median {med:.1f}  p90 {p90:.1f}")
    lines.append(f"  asker's loop thread CPU per round trip: {res['cpu_a'] * 1e6:.1f}")
    took = res["cpu_b"][-(n + 1) :]
    if len(took) > 1:
        per = (took[-1] - took[0]) / (len(took) - 1) / 1e3
        lines.append(f"  node's loop thread CPU per round trip: {per:.1f}")
    for side in ("a", "b"):
        pm, pp = _median_p90([c / 1e3 for c in res[f"put_cpu_{side}"]])
        who = "asker" if side == "a" else "node"
        lines.append(f"  {who}'s put, thread CPU: {pm:.1f}  p90 {pp:.1f}")
    for side, who in (("A", "asker"), ("B", "node")):
        st = res["sched"][side]
        lines.append(
            f"  {who}: loop thread waiting for a CPU {st['loop_wait'] / n / 1e3:.1f} per round "
            f"trip ({st['loop_runs'] / n:.1f} times run); all {st['threads']} threads: CPU "
            f"{st['all_cpu'] / n / 1e3:.1f}, waiting for a CPU {st['all_wait'] / n / 1e3:.1f}"
        )
    if res["turns_a"]:
        lines.append(f"  asker's loop iterations per round trip: {res['turns_a']:.2f}")
        took = res["turns_b"][-(n + 1) :]
        per = (took[-1] - took[0]) / (len(took) - 1)
        lines.append(f"  node's loop iterations per round trip: {per:.2f}")
    return lines


def run(n: int = N) -> None:
    """Trace ``n`` round trips and print the stages."""
    from agents import event_loop_name
    from agents import run as run_loop
    from bench import acl

    with tempfile.TemporaryDirectory() as tmp:
        keydir = Path(tmp)
        acl.make_keys(keydir)
        install()
        res = run_loop(_asker(keydir, n))
    print("\n".join(report(res, n, event_loop_name())))


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        run(int(sys.argv[1]) if len(sys.argv) > 1 else N)
