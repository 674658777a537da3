"""Per round of the global get-latest: which UAV answered last, and what its process was doing.

Not a benchmark of its own (``make bench`` does not run it): ``python -m bench._scale_trace
[--workers 32] [--queries 200] [--no-flow] [--raw] [--idle 10] [--out FILE]``. The operator
and 32 UAVs of ``bench.scale`` (``--workers`` processes host them: one each by default),
every UAV exporting its 10 streams to the operator meanwhile (as in the benchmark's window,
unless ``--no-flow``); ``--raw`` alternates ``bench.scale``'s raw zenoh get with ours. Each
process notes ``time.perf_counter_ns()`` (CLOCK_MONOTONIC: one clock for every process of
the host), so one round reads as a timeline across them:

- the operator: each round's start, and when each UAV's answer reached the conversation;
- each UAV (its Interface Agent): when the subscription's callback got the request
  (``_lane_take`` called) and when it was done with it (answered there, or left for the
  loop), with that thread's CPU, its wait for a core and the loop thread's CPU over it
  (``schedstat``); when the loop took it (``_take_now``) if the lane did not; its
  garbage collections.

Printed: context switches (wake-ups) and CPU per thread kind of the workers (each) and of
the operator, per s over ``--idle`` s without rounds and per round beyond that rate; the
rounds' p50 / p90 / p99 / max; per round, when the first, median and last UAV got the
request, answered and was heard back; where the lane's time went (its CPU, its wait for a
core, the loop's CPU meanwhile: the GIL held); and for the slowest rounds the last UAV's
timeline and any collection during it. ``--out`` keeps every note (JSON).
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import gc
import json
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from agents import run as run_loop
from agents._agent import Conversation
from agents.transports import free_tcp_port
from bench import progress
from bench._child import _CTX, Child
from bench._scale_node import semantic_label, uav_main
from bench.scale import OPERATOR, START_TIMEOUT, _our_query, _plan, _raw_get, _wait_members
from federation import FederationPlatform, PlatformConfig
from federation._cli_common import settle_gc

_EVENTS: list[tuple[Any, ...]] = []  # (ns, kind, …) in this process


def _ns() -> int:
    return time.perf_counter_ns()


def _hook_uav() -> None:
    """Wrap this process's Interface Agent steps and collections to note their times."""
    from agents._interface import InterfaceAgent

    note = _EVENTS.append
    take = InterfaceAgent._lane_take
    loop_take = InterfaceAgent._take_now
    tid = threading.get_native_id

    fds: dict[int, int] = {}
    main = os.open(f"/proc/self/task/{os.getpid()}/schedstat", os.O_RDONLY)

    def sched(fd: int) -> tuple[int, int]:
        ran, waited = os.pread(fd, 128, 0).split()[:2]
        return int(ran), int(waited)

    def lane_take(self: Any, payload: bytes) -> Any:
        me = tid()
        fd = fds.get(me)
        if fd is None:
            fd = fds[me] = os.open(f"/proc/self/task/{me}/schedstat", os.O_RDONLY)
        s0, m0 = sched(fd), sched(main)
        t0, c0 = _ns(), time.thread_time_ns()
        got = take(self, payload)
        t1, c1 = _ns(), time.thread_time_ns()
        s1, m1 = sched(fd), sched(main)
        # None: answered there; (peer, …): left for the loop (opened or not); then the
        # thread's run-queue wait over it, and the loop thread's CPU meanwhile
        note((t0, "lane", t1, c1 - c0, got is None, me, s1[1] - s0[1], m1[0] - m0[0]))
        return got

    def take_now(self: Any, host: Any, peer: str, state: Any, body: bytes) -> bool:
        t0 = _ns()
        got = loop_take(self, host, peer, state, body)
        note((t0, "loop", _ns(), peer, got))
        return got

    InterfaceAgent._lane_take = lane_take  # type: ignore[method-assign]
    InterfaceAgent._take_now = take_now  # type: ignore[method-assign]

    began = [0]

    def on_gc(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            began[0] = _ns()
        else:
            note((began[0], "gc", _ns(), info["generation"]))

    gc.callbacks.append(on_gc)


_ARRIVALS: list[tuple[Any, ...]] = []  # the operator's: `_hook_operator`


def _hook_operator() -> None:
    """Note when the operator's subscription got each answer its lane handed to the loop.

    ``(ns the callback got the envelope, "reply", UAV)``; one the callback left unopened
    for the loop (a burst: `InterfaceAgent._lane_take`) is noted ``(ns, "raw", None)``.
    Noted in `_ARRIVALS`; for the rest of this process's life.
    """
    from agents._interface import _RAW, InterfaceAgent

    notes = _ARRIVALS
    take = InterfaceAgent._lane_take
    hand = InterfaceAgent._lane_reply
    entered = threading.local()

    def lane_take(self: Any, payload: bytes) -> Any:
        entered.t = _ns()
        got = take(self, payload)
        if got is not None and got[0] is _RAW:
            notes.append((entered.t, "raw", None))
        return got

    def lane_reply(
        self: Any, peer: str, body: bytes, message: Any, fields: Any, forgets: int
    ) -> bool:
        handed = hand(self, peer, body, message, fields, forgets)
        if handed:
            notes.append((entered.t, "reply", peer))
        return handed

    InterfaceAgent._lane_take = lane_take  # type: ignore[method-assign]
    InterfaceAgent._lane_reply = lane_reply  # type: ignore[method-assign]


def traced_uav_main(spec: dict[str, Any], quiet: Any, reports: Any, stop: Any) -> None:
    """`uav_main` with its steps noted (`_hook_uav`); the notes written to ``spec["trace"]``."""
    _hook_uav()
    try:
        uav_main(spec, quiet, reports, stop)
    finally:
        with open(spec["trace"], "w") as f:
            json.dump(_EVENTS, f)


def _threads(pid: int) -> dict[str, list[int]]:
    """Process ``pid``'s threads by kind (zenoh names its own; ``loop``: the main thread,
    ``python``: a thread zenoh-python starts for a callback): voluntary and involuntary
    context switches, CPU ns, summed per kind."""
    kinds: dict[str, list[int]] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                comm = f.read().strip()
            with open(f"/proc/{pid}/task/{tid}/status") as f:
                status = f.read()
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                cpu = int(f.read().split()[0])
        except (FileNotFoundError, ProcessLookupError):
            continue  # ended meanwhile
        switches = [int(line.split()[1]) for line in status.splitlines() if "ctxt_switches" in line]
        kind = "loop" if int(tid) == pid else comm.rstrip("0123456789-")
        acc = kinds.setdefault(kind, [0, 0, 0])
        acc[0] += switches[0]
        acc[1] += switches[1]
        acc[2] += cpu
    return kinds


def _wakeups(pids: list[int]) -> dict[str, list[int]]:
    """`_threads` summed over ``pids``."""
    total: dict[str, list[int]] = {}
    for pid in pids:
        for kind, got in _threads(pid).items():
            acc = total.setdefault(kind, [0, 0, 0])
            for i in range(3):
                acc[i] += got[i]
    return total


def _less(a: dict[str, list[int]], b: dict[str, list[int]]) -> dict[str, list[int]]:
    return {k: [x - y for x, y in zip(v, b.get(k, [0, 0, 0]), strict=True)] for k, v in a.items()}


def _close_all(children: list[Child]) -> None:
    for c in children:
        c.close()


class _Round:
    __slots__ = ("arrived", "kind", "t0", "t1")

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.t0 = _ns()
        self.t1 = 0
        self.arrived: dict[str, int] = {}  # UAV → ns its answer reached the conversation


async def _trace(
    tmp: str, workers: int, queries: int, flow: bool, raw: bool, idle: float
) -> tuple[list[_Round], list[list[str]], list[str]]:
    """Run the rounds; each worker's notes are left in a file of ``tmp`` (their paths)."""
    streams = 10
    platforms = 32
    plan = _plan(Path(tmp), platforms, streams, workers)
    labels = [semantic_label(j) for j in range(streams)]
    seed = free_tcp_port()
    config = PlatformConfig.from_dict(plan.config(OPERATOR, seed), source="trace")
    children: list[Child] = []
    quiets: list[Any] = []
    rounds: list[_Round] = []
    traces = [os.path.join(tmp, f"trace-{i}.json") for i in range(len(plan.groups))]
    _hook_operator()  # before the platform subscribes: its lane's callback is bound then
    async with FederationPlatform(config) as op:
        try:
            for i, group in enumerate(plan.groups):
                spec: dict[str, Any] = {
                    "configs": [plan.config(g, seed) for g in group],
                    "streams": streams,
                    "hz": 10.0,
                    "trace": traces[i],
                }
                quiets.append(_CTX.Event())
                children.append(Child(traced_uav_main, (spec, quiets[-1]), f"trace-uavs-{i}"))
            for c in children:
                c.start()
            await _wait_members(op, plan.names, children, {})
            await asyncio.gather(
                *(asyncio.to_thread(c.wait_report, "ready", START_TIMEOUT) for c in children)
            )
            for _ in range(20):  # sessions agreed, caches warm
                got = await _our_query(op, labels, platforms)
                assert not isinstance(got, str), got
            if flow:
                await asyncio.gather(
                    *(op.federation_agent.create_stream(u, labels, timeout=30) for u in plan.names)
                )
                await asyncio.sleep(1.0)
            settle_gc()
            current: list[_Round | None] = [None]
            put = Conversation._put

            def timed_put(self: Conversation, message: Any) -> None:
                r = current[0]
                if r is not None:
                    r.arrived[message.sender.rpartition("@")[2]] = _ns()
                put(self, message)

            pids = [c.pid for c in children]
            progress(f"{idle:g} s without rounds (the streams flow)")
            counts = [_wakeups(pids), _wakeups([os.getpid()])]
            await asyncio.sleep(idle)
            counts += [_wakeups(pids), _wakeups([os.getpid()])]
            Conversation._put = timed_put  # type: ignore[method-assign]
            session = op.transport.session  # type: ignore[attr-defined]
            t_rounds = time.perf_counter()
            try:
                progress(f"{queries} rounds")
                for i in range(queries):
                    kinds = ("ours", "raw")[:: 1 if i % 2 else -1] if raw else ("ours",)
                    for kind in kinds:
                        r = _Round(kind)
                        current[0] = r
                        if kind == "ours":
                            got = await _our_query(op, labels, platforms)
                            assert not isinstance(got, str), got
                        else:
                            await _raw_get(session, platforms)
                        r.t1 = _ns()
                        current[0] = None
                        rounds.append(r)
                        await asyncio.sleep(0.01)
            finally:
                Conversation._put = put  # type: ignore[method-assign]
            span = time.perf_counter() - t_rounds
            counts += [_wakeups(pids), _wakeups([os.getpid()])]
            _print_wakeups(counts, idle, span, len(rounds), len(pids))
            for q in quiets:
                q.set()
            await asyncio.gather(*(asyncio.to_thread(c.wait_report, "quiet", 30) for c in children))
        finally:
            await asyncio.to_thread(_close_all, children)
    return rounds, plan.groups, traces


def _print_wakeups(
    counts: list[dict[str, list[int]]], idle: float, span: float, rounds: int, workers: int
) -> None:
    """Context switches (wake-ups) and CPU by thread kind: per s without rounds, per round."""
    for who, a, b, c, per in (
        ("the worker processes (each)", counts[0], counts[2], counts[4], workers),
        ("the operator", counts[1], counts[3], counts[5], 1),
    ):
        quiet = _less(b, a)
        busy = _less(c, b)
        print(
            f"{who}: context switches voluntary / involuntary, and CPU ms, per s without "
            f"rounds ({idle:g} s) | per round, less the rate without ({rounds} in {span:.1f} s)"
        )
        for kind in sorted(quiet, key=lambda k: -sum(quiet[k][:2])):
            q = [x / per / idle for x in quiet[kind]]
            r = [
                (x / per - y * span) / rounds
                for x, y in zip(busy.get(kind, [0, 0, 0]), q, strict=True)
            ]
            print(
                f"  {kind:8s} {q[0]:7.1f} / {q[1]:6.1f}  {q[2] / 1e6:6.2f} ms | "
                f"{r[0]:6.2f} / {r[1]:5.2f}  {r[2] / 1e6:6.3f} ms"
            )


class _Heard:
    """The operator's callback times per UAV: the first at or after a time."""

    def __init__(self, by_peer: dict[str, list[int]]) -> None:
        self.by_peer = {k: sorted(v) for k, v in by_peer.items()}

    def get(self, key: tuple[str, int]) -> int | None:
        """The first callback time of UAV ``key[0]`` at or after ``key[1]`` ns."""
        times = self.by_peer.get(key[0], [])
        i = bisect.bisect_left(times, key[1])
        return times[i] if i < len(times) else None


def _q(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def _dist(xs: list[float]) -> str:
    return f"p50 {_q(xs, 0.5):5.1f}  p90 {_q(xs, 0.9):5.1f}  max {max(xs, default=0.0):5.1f}"


def _report(
    rounds: list[_Round],
    events: dict[str, list[Any]],
    host: dict[str, int],
    arrivals: list[tuple[Any, ...]],
) -> None:
    """The rounds' spread (ms from each round's start) and where the slow UAVs' time went."""
    for kind in ("ours", "raw"):
        xs = [(r.t1 - r.t0) / 1e6 for r in rounds if r.kind == kind]
        if xs:
            print(f"{kind}: {len(xs)} rounds, ms: {_dist(xs)}, p99 {_q(xs, 0.99):.1f}")
    lanes = {uav: [e for e in ev if e[1] == "lane"] for uav, ev in events.items()}
    starts = {uav: [e[0] for e in ls] for uav, ls in lanes.items()}
    loops = {uav: [e for e in ev if e[1] == "loop"] for uav, ev in events.items()}
    loop_starts = {uav: [e[0] for e in ls] for uav, ls in loops.items()}
    gcs = {uav: [(e[0], e[2]) for e in ev if e[1] == "gc"] for uav, ev in events.items()}
    spread: dict[str, list[float]] = {}
    seen: list[Any] = []  # every request's lane note, in ours' rounds
    # round ms, the last UAV, its lane note, out, back (ns)
    slow: list[tuple[float, str, _Round, Any, int, int]] = []
    by_peer: dict[str, list[int]] = {}
    for t, kind, peer in arrivals:
        if kind == "reply":
            by_peer.setdefault(peer, []).append(t)
    heard: _Heard = _Heard(by_peer)
    for r in rounds:
        if r.kind != "ours" or not r.arrived:
            continue
        per: list[tuple[int, int, int, str, Any]] = []  # in, out, back (ns from the start)
        for uav, back in r.arrived.items():
            # this round's request at this UAV: its first lane note since the round's start
            i = bisect.bisect_left(starts[uav], r.t0)
            if i == len(lanes[uav]) or lanes[uav][i][0] > back:
                continue
            note = lanes[uav][i]
            seen.append(note)
            out = note[2]
            if not note[4]:  # left for the loop: out when the loop had taken it
                k = bisect.bisect_left(loop_starts[uav], note[0])
                out = loops[uav][k][2] if k < len(loops[uav]) else back
            per.append((note[0] - r.t0, out - r.t0, back - r.t0, uav, note))
        if not per:
            continue
        for name, got in (
            ("request in", [p[0] for p in per]),
            ("answer out", [p[1] for p in per]),
            ("answer back", [p[2] for p in per]),
        ):
            xs = sorted(x / 1e6 for x in got)
            for at, x in (("first", xs[0]), ("median", xs[len(xs) // 2]), ("last", xs[-1])):
                spread.setdefault(f"{name}, {at}", []).append(x)
        # the way back, for the answers the operator's lane handed to the loop: from the
        # UAV's put to the operator's callback, and from there to the conversation
        for _, out, back, uav, _ in per:
            heard_at = heard.get((uav, r.t0 + out))
            if heard_at is not None and heard_at <= r.t0 + back:
                spread.setdefault("back: out → the operator's callback", []).append(
                    (heard_at - r.t0 - out) / 1e6
                )
                spread.setdefault("back: callback → the conversation", []).append(
                    (r.t0 + back - heard_at) / 1e6
                )
        last = max(per, key=lambda p: p[2])
        spread.setdefault("the last answer's UAV: in → out", []).append((last[1] - last[0]) / 1e6)
        slow.append(((r.t1 - r.t0) / 1e6, last[3], r, last[4], r.t0 + last[1], r.t0 + last[2]))
    if not seen:
        return
    print("per round, ms after its start (first / median / last of the UAVs), over the rounds:")
    for name, xs in spread.items():
        print(f"  {name:34s} {_dist(xs)}")
    raws = sum(1 for a in arrivals if a[1] == "raw")
    print(
        f"at the operator: {sum(1 for a in arrivals if a[1] == 'reply')} answers handed to the"
        f" loop by its lane, {raws} left unopened for the loop (in a burst)"
    )
    on_lane = sum(1 for e in seen if e[4])
    print(f"answered on zenoh's thread (the lane): {on_lane} of {len(seen)}")
    seen.sort(key=lambda e: e[2] - e[0])
    print(
        "a request at a UAV, in the subscription's callback (answered there by the lane, "
        "else left for the loop; ms, medians): "
        "wall, its thread's CPU, its thread's wait for a core, the loop thread's CPU meanwhile"
    )
    for name, part in (
        ("all", seen),
        ("slowest 10%", seen[int(0.9 * len(seen)) :]),
        ("slowest 1%", seen[int(0.99 * len(seen)) :]),
    ):
        print(
            f"  {name:12s} wall {statistics.median((e[2] - e[0]) / 1e6 for e in part):5.2f}  "
            f"CPU {statistics.median(e[3] / 1e6 for e in part):5.2f}  "
            f"waited for a core {statistics.median(e[6] / 1e6 for e in part):5.2f}  "
            f"loop's CPU {statistics.median(e[7] / 1e6 for e in part):5.2f}"
        )
    slow.sort(key=lambda x: x[0], reverse=True)
    print("the slowest rounds: the UAV answered last (ms after the round's start)")
    for ms, uav, r, note, out, back in slow[: max(5, len(slow) // 50)]:
        during = [
            f"gen {g} collection {(b - a) / 1e6:.1f} ms"
            for a, b in gcs[uav]
            for g in [next(e[3] for e in events[uav] if e[1] == "gc" and e[0] == a)]
            if a < out and b > note[0]
        ]
        print(
            f"  {ms:5.1f}  {uav} (process {host[uav]}): request in {(note[0] - r.t0) / 1e6:.1f}, "
            f"out {(out - r.t0) / 1e6:.1f} ({'the lane' if note[4] else 'the loop'}; "
            f"the callback's CPU {note[3] / 1e6:.2f}, waited for a core {note[6] / 1e6:.2f}), back "
            f"{(back - r.t0) / 1e6:.1f}" + (f"; {', '.join(during)}" if during else "")
        )


def main() -> None:
    """Parse the options and trace."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=32)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--no-flow", action="store_true")
    ap.add_argument("--raw", action="store_true", help="raw zenoh gets alternately with ours")
    ap.add_argument(
        "--idle", type=float, default=10.0, help="s the wake-ups are counted without rounds"
    )
    ap.add_argument("--out", help="write the rounds and every process's notes (JSON) here")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-scale-trace-") as tmp:
        rounds, groups, traces = run_loop(
            _trace(tmp, a.workers, a.queries, not a.no_flow, a.raw, a.idle)
        )
        events: dict[str, list[Any]] = {}
        for group, path in zip(groups, traces, strict=True):
            with open(path) as f:
                got = json.load(f)
            for name in group:
                events[name] = got  # one process's notes, shared by its UAVs
    host = {n: i for i, g in enumerate(groups) for n in g}
    if a.out:
        with open(a.out, "w") as f:
            kept = [(r.kind, r.t0, r.t1, r.arrived) for r in rounds]
            json.dump({"rounds": kept, "events": events, "host": host}, f)
    _report(rounds, events, host, _ARRIVALS)


if __name__ == "__main__":
    main()
