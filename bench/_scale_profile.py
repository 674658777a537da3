"""Where a global get-latest's time goes: CPU per query in each process, and its timeline.

Not a benchmark of its own (``make bench`` does not run it):
``python -m bench._scale_profile [--workers 4] [--queries 300] [--flow] [--cprofile]
[--stages]``.
The operator and 32 UAVs of ``bench.scale`` (``--workers`` processes host the UAVs); with
``--flow`` every UAV exports its 10 streams to the operator meanwhile, as in the
benchmark's window. Printed, as medians or totals over ``--queries`` global requests made
one after another (a gap between them, so that each starts on a quiet machine):

- CPU per query, load-independent: the operator's event-loop thread (``thread_time``) and
  its other threads (zenoh's: process CPU less the loop's), the UAV processes' CPU from
  ``/proc`` over the queries less the same span measured without queries (that rate
  printed too, per UAV: with ``--flow``, what a second of the flow costs);
- the timeline of one query at the operator: when the last request was handed to zenoh,
  and when the first, median and last answer reached the conversation;
- with ``--cprofile``: the operator loop's functions with the most own time per query
  (cProfile inflates small calls: read the ranking, not the µs);
- with ``--stages``: the CPU (thread time) of each stage of a message, at the operator
  per query and at the first worker per query per UAV: the envelope's open, the quick
  take (`InterfaceAgent._take_now`; at a UAV it holds the quick answer: the answer made,
  then sent, its seal and zenoh's put), and the worker's garbage collections.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import gc
import json
import os
import pstats
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from agents import run as run_loop
from agents._agent import Conversation
from agents.transports import free_tcp_port
from bench import progress
from bench._child import _CTX, Child
from bench._scale_node import semantic_label, uav_main
from bench.scale import (
    OPERATOR,
    START_TIMEOUT,
    _our_query,
    _plan,
    _proc_cpu,
    _raw_get,
    _wait_members,
)
from federation import FederationPlatform, PlatformConfig
from federation._cli_common import settle_gc


def _threads_cpu(pid: int) -> tuple[float, float]:
    """CPU seconds of process ``pid``'s main thread (its event loop) and of all its others."""
    tick = os.sysconf("SC_CLK_TCK")
    main = rest = 0.0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                stat = f.read()
        except FileNotFoundError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        cpu = (int(fields[11]) + int(fields[12])) / tick
        if int(tid) == pid:
            main += cpu
        else:
            rest += cpu
    return main, rest


def _sum_threads(pids: list[int]) -> tuple[float, float]:
    got = [_threads_cpu(p) for p in pids]
    return sum(g[0] for g in got), sum(g[1] for g in got)


def _close_all(children: list[Child]) -> None:
    for c in children:
        c.close()


def profiled_uav_main(
    spec: dict[str, Any], quiet: Any, profiling: Any, reports: Any, stop: Any
) -> None:
    """`uav_main`, cProfile on its loop while ``profiling`` is set; stats to ``spec["profile"]``.

    The loop looks at ``profiling`` each time something sleeps (the push loop does, each
    tick): cProfile can only be turned on from the thread it profiles.
    """
    profiler = cProfile.Profile(time.thread_time)  # CPU: waits for the GIL are not counted
    sleep = asyncio.sleep
    on = False

    async def watching_sleep(delay: float, result: Any = None) -> Any:
        nonlocal on
        if profiling.is_set() != on:
            on = not on
            if on:
                profiler.enable()
            else:
                profiler.disable()
        return await sleep(delay, result)

    asyncio.sleep = watching_sleep
    try:
        uav_main(spec, quiet, reports, stop)
    finally:
        profiler.disable()
        profiler.dump_stats(spec["profile"])


_STAGES: dict[str, list[float]] = {}  # stage → [CPU seconds, calls] in this process


def staged_uav_main(
    spec: dict[str, Any], quiet: Any, profiling: Any, reports: Any, stop: Any
) -> None:
    """`uav_main` with its stages timed (`_time_stages`) while ``profiling`` is set.

    The counts start when ``profiling`` is set and stop when it is cleared (looked at
    each time something sleeps, as `profiled_uav_main`); written as JSON to
    ``spec["stages"]``.
    """
    _time_stages()
    sleep = asyncio.sleep
    on = False
    kept: dict[str, list[float]] = {}
    collecting = _STAGES.setdefault("garbage collection (any stage)", [0.0, 0])
    began = [0.0]

    def on_gc(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            began[0] = time.thread_time()
        else:
            collecting[0] += time.thread_time() - began[0]
            collecting[1] += 1

    gc.callbacks.append(on_gc)

    async def watching_sleep(delay: float, result: Any = None) -> Any:
        nonlocal on
        if profiling.is_set() != on:
            on = not on
            if on:
                for acc in _STAGES.values():
                    acc[:] = [0.0, 0]
            else:
                kept.update({k: list(v) for k, v in _STAGES.items()})
        return await sleep(delay, result)

    asyncio.sleep = watching_sleep
    try:
        uav_main(spec, quiet, reports, stop)
    finally:
        with open(spec["stages"], "w") as f:
            json.dump(kept, f)


def _time_stages() -> None:
    """Wrap the stages of a message (in this process) to count their CPU (thread time).

    Nested: `InterfaceAgent._take_now` holds `_answer_at_once` (a provider's quick answer),
    which holds `FederationAgent.answer_at_once` (the answer made) and
    `InterfaceAgent.send_now` (its send), which holds `SessionTable.seal` and
    `ZenohTransport._put`; on zenoh's thread (the lane: one platform a process)
    `InterfaceAgent._lane_answer` holds `FederationAgent.answer_on_thread` and the seal.
    """
    from agents._interface import InterfaceAgent
    from agents._security import SessionTable
    from agents.transports import ZenohTransport
    from federation._service import FederationAgent

    def timed(cls: Any, name: str) -> None:
        fn = getattr(cls, name)
        acc = _STAGES.setdefault(f"{cls.__name__}.{name}", [0.0, 0])
        clock = time.thread_time

        def wrapper(*a: Any, **k: Any) -> Any:
            t = clock()
            try:
                return fn(*a, **k)
            finally:
                acc[0] += clock() - t
                acc[1] += 1

        setattr(cls, name, wrapper)

    timed(SessionTable, "open")
    timed(SessionTable, "seal")
    timed(InterfaceAgent, "_take_now")
    timed(InterfaceAgent, "_answer_at_once")
    timed(InterfaceAgent, "send_now")
    timed(FederationAgent, "answer_at_once")
    timed(InterfaceAgent, "_lane_answer")
    timed(FederationAgent, "answer_on_thread")
    timed(ZenohTransport, "_put")


def _med(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


async def _profile(
    workers: int,
    queries: int,
    flow: bool,
    cprofile: bool,
    raw: bool,
    stages: bool,
    asked: int = 10,
    platforms: int = 32,
) -> None:
    streams = 10
    if stages:
        _time_stages()
    with tempfile.TemporaryDirectory(prefix="bench-scale-profile-") as tmp:
        plan = _plan(Path(tmp), platforms, streams, workers)
        labels = [semantic_label(j) for j in range(asked)]
        seed = free_tcp_port()
        config = PlatformConfig.from_dict(plan.config(OPERATOR, seed), source="profile")
        children: list[Child] = []
        quiets: list[Any] = []  # kept: a child unpickles its event after the spawn
        profiling = _CTX.Event()
        async with FederationPlatform(config) as op:
            try:
                for i, group in enumerate(plan.groups):
                    spec: dict[str, Any] = {
                        "configs": [plan.config(g, seed) for g in group],
                        "streams": streams,
                        "hz": 10.0,
                    }
                    quiets.append(_CTX.Event())
                    args: tuple[Any, ...] = (spec, quiets[-1])
                    target: Any = uav_main
                    if cprofile and i == 0:
                        spec["profile"] = os.path.join(tmp, "uav.prof")
                        target = profiled_uav_main
                        args = (*args, profiling)
                    elif stages and i == 0:
                        spec["stages"] = os.path.join(tmp, "uav-stages.json")
                        target = staged_uav_main
                        args = (*args, profiling)
                    children.append(Child(target, args, f"profile-uavs-{i}"))
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
                        *(
                            op.federation_agent.create_stream(
                                u, [semantic_label(j) for j in range(streams)], timeout=30
                            )
                            for u in plan.names
                        )
                    )
                    await asyncio.sleep(1.0)
                settle_gc()
                profiling.set()
                await _measure(op, children, labels, platforms, queries, cprofile, raw)
                profiling.clear()
                await asyncio.sleep(0.3)  # a tick of the push loop: the profiler is off
            finally:
                await asyncio.to_thread(_close_all, children)
            if cprofile:
                _print_uav_profile(os.path.join(tmp, "uav.prof"), queries, len(plan.groups[0]))
            elif stages:
                _print_uav_stages(
                    os.path.join(tmp, "uav-stages.json"), queries, len(plan.groups[0])
                )


def _print_uav_stages(path: str, queries: int, uavs: int) -> None:
    """The first worker's CPU per stage, per query per UAV (`staged_uav_main`)."""
    if not os.path.exists(path):
        print("  (the staged worker wrote no stages)")
        return
    with open(path) as f:
        got: dict[str, list[float]] = json.load(f)
    per = queries * uavs
    for name, (cpu, calls) in got.items():
        if not calls:
            continue  # the other path's stage (the loop's or the lane's)
        print(
            f"  worker 0 stage {name}: {1e6 * cpu / per:.1f} µs per query per UAV, "
            f"{calls / per:.2f} calls, {1e6 * cpu / max(calls, 1):.1f} µs each"
        )


def _print_uav_profile(path: str, queries: int, uavs: int) -> None:
    """The first worker's functions with the most own time, per query per UAV (its whole life)."""
    if not os.path.exists(path):
        print("  (the profiled worker wrote no stats)")
        return
    stats = pstats.Stats(path)
    rows = sorted(stats.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:30]  # type: ignore[attr-defined]
    print(
        f"  cProfile of worker 0 ({uavs} UAVs) over the queries (its push loop too); "
        "own time per query per UAV (µs):"
    )
    per = queries * uavs
    for (file, line, name), (_, nc, tt, _, _) in rows:
        where = f"{os.path.basename(file)}:{line} {name}"
        print(f"    {1e6 * tt / per:8.1f}  {nc / per:6.1f} calls  {where}")
    print("  the same, cumulative time of the stages of a query (µs per query per UAV):")
    rows = sorted(stats.stats.items(), key=lambda kv: kv[1][3], reverse=True)[:60]  # type: ignore[attr-defined]
    for (file, line, name), (_, nc, _, ct, _) in rows:
        if 0.5 <= nc / per <= 40:
            where = f"{os.path.basename(file)}:{line} {name}"
            print(f"    {1e6 * ct / per:8.1f}  {nc / per:6.1f} calls  {where}")


async def _measure(
    op: FederationPlatform,
    children: list[Child],
    labels: list[str],
    n: int,
    queries: int,
    cprofile: bool,
    raw: bool,
) -> None:
    gap = 0.02
    session = op.transport.session  # type: ignore[attr-defined]
    pids = [c.pid for c in children]
    # the UAVs' CPU without queries, over as long as the queries will take
    span = queries * (gap + 0.01)
    progress(f"idle for {span:.1f} s (worker processes {' '.join(map(str, pids))})")
    w0, c0 = time.perf_counter(), sum(_proc_cpu(p) for p in pids)
    idle_th0 = _sum_threads(pids)
    await asyncio.sleep(span)
    idle_span = time.perf_counter() - w0
    idle_rate = (sum(_proc_cpu(p) for p in pids) - c0) / idle_span
    idle_th1 = _sum_threads(pids)
    idle_threads = (
        (idle_th1[0] - idle_th0[0]) / idle_span,
        (idle_th1[1] - idle_th0[1]) / idle_span,
    )

    arrivals: list[float] = []
    sent: list[float] = []
    sent_cpu: list[float] = []  # the loop's CPU clock when the last request was out
    send_cpu: list[float] = []
    put, gather = Conversation._put, Conversation.gather

    def timed_put(self: Conversation, message: Any) -> None:
        arrivals.append(time.perf_counter())
        put(self, message)

    async def timed_gather(self: Conversation, *a: Any, **k: Any) -> None:
        sent.append(time.perf_counter())
        sent_cpu.append(time.thread_time())
        await gather(self, *a, **k)

    loop_cpu: list[float] = []
    proc_cpu: list[float] = []
    wall: list[float] = []
    last_sent: list[float] = []
    first: list[float] = []
    median: list[float] = []
    last: list[float] = []
    profiler = cProfile.Profile(time.thread_time) if cprofile else None
    Conversation._put = timed_put  # type: ignore[method-assign]
    Conversation.gather = timed_gather  # type: ignore[method-assign]
    try:
        progress(f"{queries} queries")
        for acc in _STAGES.values():
            acc[:] = [0.0, 0]
        w0, c0 = time.perf_counter(), sum(_proc_cpu(p) for p in pids)
        th0 = _sum_threads(pids)
        for _ in range(queries):
            arrivals.clear()
            sent.clear()
            sent_cpu.clear()
            t0, l0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
            if profiler is not None:
                profiler.enable()
            got: float | str | None
            if raw:
                got = await _raw_get(session, n)
                sent.append(t0)
                arrivals.append(time.perf_counter())
            else:
                got = await _our_query(op, labels, n)
            if profiler is not None:
                profiler.disable()
            t1, l1, p1 = time.perf_counter(), time.thread_time(), time.process_time()
            assert got is not None and not isinstance(got, str), got
            loop_cpu.append(l1 - l0)
            proc_cpu.append(p1 - p0)
            wall.append(t1 - t0)
            last_sent.append(sent[0] - t0)
            if sent_cpu:
                send_cpu.append(sent_cpu[0] - l0)
            a = sorted(x - t0 for x in arrivals)
            first.append(a[0])
            median.append(a[len(a) // 2])
            last.append(a[-1])
            await asyncio.sleep(gap)
        took = time.perf_counter() - w0
        uav_cpu = sum(_proc_cpu(p) for p in pids) - c0 - idle_rate * took
        th1 = _sum_threads(pids)
        uav_loop = th1[0] - th0[0] - idle_threads[0] * took
        uav_rest = th1[1] - th0[1] - idle_threads[1] * took
    finally:
        Conversation._put, Conversation.gather = put, gather  # type: ignore[method-assign]

    def ms(xs: list[float]) -> str:
        return f"{1e3 * _med(xs):.3f}"

    def p99(xs: list[float]) -> str:
        return f"{1e3 * sorted(xs)[min(len(xs) - 1, int(0.99 * len(xs)))]:.2f}"

    print("raw zenoh get:" if raw else "ours:")
    print(
        f"{queries} global get-latest of {len(labels)} labels from {n} UAVs in "
        f"{len(pids)} processes"
    )
    print(f"  wall per query: p50 {ms(wall)} ms, p99 {p99(wall)} ms")
    print(
        f"  operator CPU per query: loop thread {ms(loop_cpu)} ms, other threads (zenoh) "
        f"{1e3 * (_med(proc_cpu) - _med(loop_cpu)):.3f} ms; the loop's until the last "
        f"request was out {ms(send_cpu) if send_cpu else '-'} ms"
    )
    print(
        f"  UAV processes' CPU per query (less idle): {1e3 * uav_cpu / queries:.2f} ms in all, "
        f"{1e6 * uav_cpu / queries / n:.0f} µs per UAV (loop threads "
        f"{1e6 * uav_loop / queries / n:.0f}, other threads {1e6 * uav_rest / queries / n:.0f})"
    )
    print(
        "  UAV processes' CPU per s without queries (with --flow: a second of the flow): "
        f"{1e3 * idle_rate / n:.2f} ms per UAV (loop threads {1e3 * idle_threads[0] / n:.2f}, "
        f"other threads {1e3 * idle_threads[1] / n:.2f})"
    )
    print(
        f"  timeline (median ms from the call): last request out {ms(last_sent)}; answers in: "
        f"first {ms(first)}, median {ms(median)}, last {ms(last)}, the call returns {ms(wall)}"
    )
    print(f"  p99 of the same: last out {p99(last_sent)}, first {p99(first)}, last {p99(last)}")
    for name, (cpu, calls) in _STAGES.items():
        if not calls:
            continue  # a provider's stage: the operator answers nothing here
        print(
            f"  operator stage {name}: {1e3 * cpu / queries:.3f} ms per query, "
            f"{calls / queries:.1f} calls, {1e6 * cpu / max(calls, 1):.1f} µs each"
        )
    if profiler is not None:
        stats = pstats.Stats(profiler)
        stats.sort_stats("tottime")
        rows = sorted(stats.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:25]  # type: ignore[attr-defined]
        print("  cProfile, the operator loop's own time per query (µs):")
        for (file, line, name), (_, nc, tt, _, _) in rows:
            print(
                f"    {1e6 * tt / queries:8.1f}  {nc / queries:6.1f} calls  "
                f"{os.path.basename(file)}:{line} {name}"
            )


def main() -> None:
    """Parse the options and profile."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--queries", type=int, default=300)
    ap.add_argument("--flow", action="store_true")
    ap.add_argument("--cprofile", action="store_true")
    ap.add_argument("--raw", action="store_true", help="the raw zenoh get instead of ours")
    ap.add_argument(
        "--stages", action="store_true", help="CPU per stage: the operator's, worker 0's"
    )
    ap.add_argument("--labels", type=int, default=10, help="labels asked of each UAV (1-10)")
    a = ap.parse_args()
    run_loop(_profile(a.workers, a.queries, a.flow, a.cprofile, a.raw, a.stages, a.labels))


if __name__ == "__main__":
    main()
