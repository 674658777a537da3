"""Scale: 32 UAV platforms and the operator on one machine, each UAV exporting 10 streams.

Every UAV is a whole `FederationPlatform` with its own zenoh session (peer mode, loopback,
gossip; each connects to the operator's endpoint and finds the others by gossip). The
UAVs run in ``workers`` spawned processes (32 / workers platforms each, opened at once
in one asyncio loop); with ``workers=32`` every platform has its own process. The
operator is this process. Measured, in one run:

- ``join``: from launching the workers until the operator's Federation Agent lists all
  UAVs as members; beside it, per platform, launch → interpreter ready (imports) and
  platform open → joined. Peer, in the same run, before ours: the same number of bare
  zenoh sessions with the same settings, launched the same way in as many processes,
  each declaring a liveliness token, seen by a raw session on the operator's endpoint.
- ``query``: the operator's ``global_request({"action": "get-latest", "labels": [all
  10]})`` asked of every UAV (authenticated ACL through each Interface Agent, DyKnow
  query, reply), until all answered; p50 and p99 over ``queries`` requests made while
  every stream flows (and, printed only, the same query before any export flows). Peer,
  in the same rounds (one of each per round, which goes first alternating): a raw zenoh
  ``get`` on ``scale/raw/*`` answered by a queryable on every UAV's own session with its
  latest numbers (JSON), until all replied, on the operator's own session. Both p99s
  come from the same rounds; beside them, what the other side took in the rounds of
  each side's slowest 1% (a stall of the whole machine slows both), which UAV (in which
  worker process) answered last in ours' slowest 1%, and the operator's garbage
  collections over the window.
- ``samples``: the operator asks every UAV ``create-stream`` of its 10 labels; each UAV
  pushes a sequence number into each stream at ``hz``; the operator's subscriber on
  each imported stream counts them end to end, from the import's first sample (what
  arrived before the subscription is read from the stream), with their latency (valid
  time on the UAV → delivery here, one clock). After ``seconds`` the UAVs stop, report their last
  number, and every stream must hold every number from its first counted one to that
  last one: ``lost`` is what is missing.
- The operator and the workers run on `agents.run`'s loop, as ``dyknow node`` does
  (uvloop where installed; ``DYKNOW_EVENT_LOOP=asyncio`` for asyncio's own).
- Loop lag, with ``--probe`` (`bench._scale_node.LoopProbe`): how often a 10 ms timer on
  the loop of each worker (from its platforms' start until they stop pushing) and of the
  operator (over the window) woke more than 5 / 20 ms late, and why, from the loop
  thread's ``schedstat``: ``busy`` (the loop ran something long), ``core`` (the thread
  waited for a core) or ``gil`` (it slept: another thread held the GIL); the worst with
  its parts.
- CPU (process CPU time / wall over the window, from ``/proc`` and ``resource``; of it,
  what the main threads, where the event loops run, used: the rest is zenoh's) and RSS
  of the operator and of the workers, total and per platform (bare sessions beside).

``python -m bench scale`` runs 4 workers (the ``BENCH`` lines: ``scale-32`` is the query's
p99, then ``-query-p50``, ``-join``, ``-rss``, ``-delivered``) and then one process per
platform (lines ``scale-32-procs…``: 33 interpreters on 2 cores spend most of the join
importing); ``--quick`` runs only the first, for 8 s and 100 queries; ``--procs`` runs only
the second (with ``--quick``, for 8 s and 100 queries); ``--probe`` adds the loop-lag probes.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import os
import resource
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from agents import event_loop_name
from agents import run as run_loop
from agents.keys import gen_keys, trust_keys
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
from bench import fmt, progress, report
from bench._child import _CTX, Child, ChildFailed
from bench._scale_node import (
    BARE_KEY,
    RAW_KEY,
    LoopProbe,
    bare_main,
    local_label,
    semantic_label,
    uav_main,
    zenoh_settings,
)
from federation import FederationPlatform, PlatformConfig
from federation._cli_common import settle_gc

PLATFORMS = 32
STREAMS = 10
HZ = 10.0
SECONDS = 30.0
WORKERS = 4
QUERIES = 400  # p99 of 400 is the 4th slowest: one stalled round does not make it
JOIN_TARGET = 10.0  # s, issue 7
QUERY_TARGET_P99 = 25.0  # ms, issue 15 (issue 7 asked 50)
QUERY_TARGET_RATIO = 1.5  # ours / the raw get, p50 and p99 of the same rounds (issue 15)
QUERY_DEADLINE = 2.0  # s a global request (and a raw get) may take
START_TIMEOUT = 180.0  # s for every worker to start and every platform to join
OPERATOR = "operator"


class ScaleError(RuntimeError):
    """The scale benchmark could not run (a worker died, a phase did not finish in time)."""


@dataclass
class ScaleResult:
    """What one scale run measured (times in s unless named ``_ms``; memory in MB)."""

    platforms: int
    streams: int
    hz: float
    workers: int
    join: float = 0.0  # launch → the operator lists every UAV as a member
    bare_join: float = 0.0  # launch → a raw session sees every bare session's token
    spawn_to_imported: list[float] = field(default_factory=list)  # per worker
    open_to_joined: list[float] = field(default_factory=list)  # per platform
    launch_to_joined: list[float] = field(default_factory=list)  # per platform (its own view)
    streams_agreed: float = 0.0  # create-stream to every UAV → every import arrived
    query_ms: list[float] = field(default_factory=list)
    idle_ms: list[float] = field(default_factory=list)  # the same query before exports flow
    raw_ms: list[float] = field(default_factory=list)
    rounds: list[tuple[float | None, float | None]] = field(default_factory=list)  # ours, raw ms
    last_answer: list[str | None] = field(default_factory=list)  # per round: ours' last UAV
    host: dict[str, int] = field(default_factory=dict)  # UAV → the worker process it runs in
    gc_collections: tuple[int, ...] = ()  # the operator's, per generation, over the window
    gc_longest_ms: tuple[float, ...] = ()  # the operator's longest collection, per generation
    rounds_in_gc: list[tuple[float | None, float | None]] = field(default_factory=list)
    query_failures: list[str] = field(default_factory=list)
    raw_failures: int = 0
    window: float = 0.0  # s the streams ran while measured
    counted: int = 0  # samples counted at the operator (all streams, whole run)
    expected: int = 0  # numbers pushed from each stream's first counted one to its last
    lost: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    never_arrived: int = 0  # streams of which not one sample was counted
    import_lost: int = 0  # what the import proxies counted lost (their own sequence numbers)
    late_ticks: int = 0  # UAV push ticks that started more than a period late
    worker_gc_longest_ms: tuple[float, ...] = ()  # longest collection in any worker, per gen
    worker_lag_ms: float = 0.0  # the longest a worker's push loop woke late (a stalled loop)
    worker_probe: dict[str, Any] = field(default_factory=dict)  # `LoopProbe`, all workers
    operator_probe: dict[str, Any] = field(default_factory=dict)  # `LoopProbe`, the window
    window_rate: float = 0.0  # samples/s counted at the operator over the window
    e2e_ms: list[float] = field(default_factory=list)
    cpu_operator: float = 0.0  # cores
    cpu_workers: float = 0.0  # cores, all workers
    cpu_operator_loop: float = 0.0  # cores, the operator's main thread (its event loop)
    cpu_workers_loop: float = 0.0  # cores, the workers' main threads (their event loops)
    rss_operator: float = 0.0
    rss_workers: list[float] = field(default_factory=list)
    rss_bare_workers: list[float] = field(default_factory=list)
    load: tuple[float, float] = (0.0, 0.0)  # 1-min load average at the window's start, end
    at_once: int = 0  # of the UAVs' Federation Agents' messages, answered as they came
    on_thread: int = 0  # of those, answered on zenoh's thread (`InterfaceAgent.lane`)
    handled: int = 0  # every message the UAVs' Federation Agents handled

    @property
    def sent_expected(self) -> int:
        """Samples the UAVs were meant to push over the window: platforms × streams × hz × s."""
        return round(self.platforms * self.streams * self.hz * self.window)


class _GcWatch:
    """Times the operator's garbage collections (``gc.callbacks``) while it is on."""

    def __init__(self) -> None:
        self.longest = [0.0, 0.0, 0.0]
        self.spans: list[tuple[float, float]] = []  # perf_counter start, end of a full one
        self._t0 = 0.0

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        now = time.perf_counter()
        gen = info["generation"]
        self.longest[gen] = max(self.longest[gen], 1e3 * (now - self._t0))
        if gen == 2:
            self.spans.append((self._t0, now))

    def __enter__(self) -> _GcWatch:
        gc.callbacks.append(self)
        return self

    def __exit__(self, *exc: object) -> None:
        gc.callbacks.remove(self)

    def inside(self, start: float, end: float) -> bool:
        """Whether a full collection (generation 2) ran between ``start`` and ``end``."""
        return any(a < end and b > start for a, b in self.spans)


def pct(xs: list[float], q: float) -> float:
    """The ``q`` quantile of ``xs`` (nearest rank; NaN when empty)."""
    if not xs:
        return float("nan")
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


# -- the federation's files -------------------------------------------------------------------


@dataclass
class _Plan:
    federation: str
    names: list[str]
    directory: Path
    vocabulary: dict[str, Any]
    streams: int
    groups: list[list[str]]  # platform names per worker

    def config(self, name: str, seed: int) -> dict[str, Any]:
        """Platform ``name``'s config: the operator listens on ``seed``, UAVs connect to it."""
        if name == OPERATOR:
            mapping: dict[str, str] = {}
            listen, connect = f"tcp/127.0.0.1:{seed}", []
        else:
            mapping = {semantic_label(j): local_label(j) for j in range(self.streams)}
            # Port 0: zenoh binds a free port itself and gossips it. Ports picked here ahead
            # could be taken meanwhile by the outgoing connections of the other peers.
            listen, connect = "tcp/127.0.0.1:0", [f"tcp/127.0.0.1:{seed}"]
        return {
            "name": name,
            "federation": self.federation,
            "key": str(self.directory / "keys" / f"{name}.key"),
            "trust": str(self.directory / "trust.json"),
            "vocabulary": self.vocabulary,
            "mapping": {"labels": mapping},
            "export_limit": max(64, 2 * self.streams),
            "transport": {"kind": "zenoh", "mode": "peer", "listen": [listen], "connect": connect},
        }


def _plan(directory: Path, platforms: int, streams: int, workers: int) -> _Plan:
    """Keys and one trust file for the operator and the UAVs; the UAVs split among workers."""
    federation = f"scale-{uuid.uuid4().hex[:8]}"
    names = [f"uav-{i:02d}" for i in range(platforms)]
    pubs = [gen_keys(n, directory / "keys")[2] for n in [OPERATOR, *names]]
    trust_keys(directory / "trust.json", pubs, federation=federation)
    vocabulary = {
        "name": "scale",
        "labels": {semantic_label(j): f"a UAV's stream {j}" for j in range(streams)},
    }
    per = -(-platforms // workers)
    groups = [names[i : i + per] for i in range(0, platforms, per)]
    return _Plan(federation, names, directory, vocabulary, streams, groups)


# -- measuring processes ------------------------------------------------------------------------


def _proc_cpu(pid: int, where: str = "") -> float:
    """CPU seconds (user + system) process ``pid`` (or its ``/proc/`` ``where``) used so far."""
    with open(f"/proc/{where or pid}/stat") as f:
        stat = f.read()
    fields = stat[stat.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _loop_cpu(pid: int) -> float:
    """CPU seconds process ``pid``'s main thread (where its event loop runs) used so far."""
    return _proc_cpu(pid, f"{pid}/task/{pid}")


def _self_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _rss_mb(pid: int | str = "self") -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise ScaleError(f"no VmRSS for process {pid}")


def _close_all(children: list[Child]) -> None:
    """Ask every child to stop at once, then end each (killing what does not stop)."""
    for c in children:
        c.stop.set()
    for c in children:
        c.close()


def _check(children: list[Child]) -> None:
    try:
        for c in children:
            c.check()
    except ChildFailed as exc:
        raise ScaleError(str(exc)) from None


# -- the peer: bare zenoh sessions ------------------------------------------------------------


def bare_join(plan: _Plan, result: ScaleResult) -> None:
    """Launch bare zenoh sessions like the UAVs; time until a raw session sees every token."""
    n = len(plan.names)
    seed = free_tcp_port()
    config = ZenohConfig.loopback(seed).to_zenoh()
    seen: dict[str, float] = {}
    all_seen = threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            seen.setdefault(str(sample.key_expr), time.time())
            if len(seen) >= n:
                all_seen.set()

    children: list[Child] = []
    with zenoh.open(config) as session:
        sub = session.liveliness().declare_subscriber(f"{BARE_KEY}/*", on_token)
        try:
            for i, group in enumerate(plan.groups):
                sessions = [
                    (
                        name,
                        zenoh_settings(ZenohConfig.loopback(0, connect=[seed])),
                    )
                    for name in group
                ]
                children.append(Child(bare_main, ({"sessions": sessions},), f"scale-bare-{i}"))
            launched = time.time()
            for c in children:
                c.start()
            deadline = time.monotonic() + START_TIMEOUT
            while not all_seen.wait(0.25):
                _check(children)
                if time.monotonic() > deadline:
                    raise ScaleError(
                        f"bare zenoh: {len(seen)}/{n} tokens seen in {START_TIMEOUT} s"
                    )
            result.bare_join = max(seen.values()) - launched
            for c in children:
                c.wait_report("ready", START_TIMEOUT)
            result.rss_bare_workers = [c.rss_mb() for c in children]
        finally:
            _close_all(children)
            sub.undeclare()


# -- ours -------------------------------------------------------------------------------------


class _Counter:
    """Counts one imported stream's sequence numbers as its subscriber gets them."""

    __slots__ = ("duplicates", "first", "latency_ms", "out_of_order", "seen", "top")

    def __init__(self, latency_ms: list[float]) -> None:
        self.seen: set[int] = set()
        self.first: int | None = None
        self.top = -1
        self.duplicates = 0
        self.out_of_order = 0
        self.latency_ms = latency_ms

    def __call__(self, batch: list[tuple[Any, int, int]], *, timed: bool = True) -> None:
        now = time.time_ns()
        for value, valid, _ in batch:
            seq = int(value)
            if self.first is None:
                self.first = seq
            if seq in self.seen:
                self.duplicates += 1
                continue
            if seq < self.top:
                self.out_of_order += 1
            self.seen.add(seq)
            self.top = max(self.top, seq)
            if timed:
                self.latency_ms.append((now - valid) / 1e6)


async def _raw_get(session: zenoh.Session, n: int) -> float | None:
    """Raw zenoh get on every UAV's queryable: ms until all ``n`` replied (None: they did not)."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[float] = loop.create_future()
    count = 0

    def finish(t: float) -> None:
        if not done.done():
            done.set_result(t)

    def on_reply(reply: zenoh.Reply) -> None:
        nonlocal count
        ok = reply.ok
        if ok is None:
            return
        json.loads(ok.payload.to_bytes())  # decoded, as ours decodes its answers
        count += 1
        if count == n:
            loop.call_soon_threadsafe(finish, time.perf_counter())

    t0 = time.perf_counter()
    session.get(
        f"{RAW_KEY}/*",
        on_reply,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=QUERY_DEADLINE,
    )
    try:
        return (await asyncio.wait_for(done, QUERY_DEADLINE)) - t0
    except TimeoutError:
        return None


async def _our_query(
    op: FederationPlatform, labels: list[str], n: int, last: list[str | None] | None = None
) -> float | str:
    """The global get-latest: seconds until every UAV answered, or what went wrong.

    ``last`` gets the UAV whose answer came last (the one the round waited for).
    """
    t0 = time.perf_counter()
    r = await op.federation_agent.global_request(
        {"action": "get-latest", "labels": labels}, deadline=QUERY_DEADLINE
    )
    dt = time.perf_counter() - t0
    if last is not None:
        last.append(next(reversed(r.answers), None))  # answers keep their arrival order
    if len(r.answers) != n:
        return (
            f"{len(r.answers)}/{n} answered; refused {r.refused}; silent {r.no_answer}; "
            f"unlisted {r.unlisted}"
        )
    for platform, answer in r.answers.items():
        if not isinstance(answer, dict) or set(answer) != set(labels):
            return f"{platform} answered {str(answer)[:200]}"
    return dt


async def _wait_members(
    op: FederationPlatform, names: list[str], children: list[Child], joined: dict[str, float]
) -> None:
    """Wait until every UAV is a member and its Federation Agent is in the global directory.

    A global request asks the directory's providers only: a member not listed yet is not
    asked (nor counted refused or silent), and every query would come back short.
    """
    want = set(names)
    deadline = time.monotonic() + START_TIMEOUT
    last_said = 0.0
    while not want <= set(op.members) or not want <= set(op.federation_agent.providers()):
        _check(children)
        members = len(want & set(op.members))
        listed = len(want & set(op.federation_agent.providers()))
        if time.monotonic() > deadline:
            raise ScaleError(
                f"{members}/{len(want)} UAVs joined, {listed} in the directory in {START_TIMEOUT} s"
            )
        if time.monotonic() - last_said > 2.0:
            last_said = time.monotonic()
            progress(f"{members}/{len(want)} UAVs are members, {listed} in the directory")
        await asyncio.sleep(0.05)


async def _federation(
    plan: _Plan, result: ScaleResult, seconds: float, queries: int, probing: bool
) -> None:
    n = len(plan.names)
    labels = [semantic_label(j) for j in range(result.streams)]
    quiets: list[Any] = []
    children: list[Child] = []
    seed = free_tcp_port()
    op_config = PlatformConfig.from_dict(plan.config(OPERATOR, seed), source="bench operator")
    async with FederationPlatform(op_config) as op:
        joined: dict[str, float] = {}

        async def follow() -> None:
            async with op.membership() as events:
                async for e in events:
                    if e.kind == "joined":
                        joined.setdefault(e.platform, time.time())

        follower = asyncio.create_task(follow())
        try:
            for i, group in enumerate(plan.groups):
                quiet = _CTX.Event()
                quiets.append(quiet)
                spec = {
                    "configs": [plan.config(g, seed) for g in group],
                    "streams": result.streams,
                    "hz": result.hz,
                    "probe": probing,
                }
                children.append(Child(uav_main, (spec, quiet), f"scale-uavs-{i}"))
            launched = time.time()
            for c in children:
                c.start()
            progress(f"launched {len(children)} worker processes for {n} UAV platforms")
            await _wait_members(op, plan.names, children, joined)
            result.join = max(joined.get(p, time.time()) for p in plan.names) - launched
            progress(f"all {n} UAVs are members {result.join:.2f} s after launch")
            settle_gc()  # the operator is a long-running node too (`dyknow console`)
            readies = await asyncio.gather(
                *(asyncio.to_thread(c.wait_report, "ready", START_TIMEOUT) for c in children)
            )
            for c, ready in zip(children, readies, strict=True):
                result.spawn_to_imported.append(ready["imported"] - c.started_wall)
                for opened, done in ready["platforms"].values():
                    result.open_to_joined.append(done - opened)
                    result.launch_to_joined.append(done - c.started_wall)

            # Before any export flows: the first request to each UAV agrees the session keys
            # (not counted), then the same query, to see what the streams' load adds.
            await _our_query(op, labels, n)
            for _ in range(max(10, queries // 3)):
                idle = await _our_query(op, labels, n)
                if isinstance(idle, str):
                    result.query_failures.append(f"before the exports: {idle}")
                else:
                    result.idle_ms.append(1e3 * idle)
                await asyncio.sleep(0.02)
            progress(
                f"{len(result.idle_ms)} global queries before the exports: "
                f"p50 {pct(result.idle_ms, 0.5):.1f} ms; create-stream of {len(labels)} labels "
                "to each UAV"
            )
            t0 = time.perf_counter()
            await asyncio.gather(
                *(op.federation_agent.create_stream(u, labels, timeout=30) for u in plan.names)
            )
            latency_ms: list[float] = []
            counters: dict[tuple[str, str], _Counter] = {}

            async def count(uav: str, semantic: str) -> None:
                label = await op.imported(uav, semantic, timeout=30)
                counter = counters[(uav, semantic)] = _Counter(latency_ms)
                # What arrived before the subscription counts too (its latency does not: it
                # waited here). Nothing suspends between the two: no sample is missed or
                # counted twice.
                before = op.instance.between(label, 0, op.instance.clock.now()).samples
                counter([tuple(x) for x in before], timed=False)
                op.instance.subscribe(label, callback=counter)

            await asyncio.gather(*(count(u, s) for u in plan.names for s in labels))
            result.streams_agreed = time.perf_counter() - t0
            progress(
                f"{len(counters)} streams flowing ({result.streams_agreed:.2f} s to agree); "
                f"{queries} global queries and {queries} raw gets over {seconds:g} s"
            )

            pids = [c.pid for c in children]
            load0 = os.getloadavg()[0]
            w0, c0, s0 = time.perf_counter(), [_proc_cpu(p) for p in pids], _self_cpu()
            me = os.getpid()
            loops0 = sum(_loop_cpu(p) for p in pids), _loop_cpu(me)
            got0 = sum(len(c.seen) for c in counters.values())
            gc0 = [g["collections"] for g in gc.get_stats()]
            watch = _GcWatch().__enter__()
            probe = LoopProbe()
            if probing:
                probe.start(asyncio.get_running_loop())
            session = op.transport.session if isinstance(op.transport, ZenohTransport) else None
            assert session is not None
            for i in range(queries):
                # spread what is left of the queries over what is left of the window
                left = w0 + seconds - time.perf_counter()
                gap = max(left / (2 * (queries - i)) - 0.03, 0.01)
                kinds = ("ours", "raw") if i % 2 == 0 else ("raw", "ours")
                ours_ms = raw_ms = None
                round_t0 = time.perf_counter()
                for kind in kinds:
                    if kind == "ours":
                        got = await _our_query(op, labels, n, result.last_answer)
                        if isinstance(got, str):
                            result.query_failures.append(got)
                        else:
                            ours_ms = 1e3 * got
                            result.query_ms.append(ours_ms)
                    else:
                        raw = await _raw_get(session, n)
                        if raw is None:
                            result.raw_failures += 1
                        else:
                            raw_ms = 1e3 * raw
                            result.raw_ms.append(raw_ms)
                    await asyncio.sleep(gap)
                result.rounds.append((ours_ms, raw_ms))
                if watch.inside(round_t0, time.perf_counter()):
                    result.rounds_in_gc.append((ours_ms, raw_ms))
                if (i + 1) % 10 == 0:
                    progress(
                        f"{i + 1}/{queries} queries: ours p50 {pct(result.query_ms, 0.5):.1f} ms, "
                        f"raw p50 {pct(result.raw_ms, 0.5):.1f} ms; "
                        f"{sum(len(c.seen) for c in counters.values())} samples counted"
                    )
            await asyncio.sleep(max(0.0, seconds - (time.perf_counter() - w0)))
            w1, c1, s1 = time.perf_counter(), [_proc_cpu(p) for p in pids], _self_cpu()
            loops1 = sum(_loop_cpu(p) for p in pids), _loop_cpu(me)
            result.load = (load0, os.getloadavg()[0])
            watch.__exit__()
            if probing:
                probe.stop()
                result.operator_probe = probe.summary()
            result.gc_collections = tuple(
                g["collections"] - c for g, c in zip(gc.get_stats(), gc0, strict=True)
            )
            result.gc_longest_ms = tuple(watch.longest)
            got1 = sum(len(c.seen) for c in counters.values())
            result.window = w1 - w0
            result.window_rate = (got1 - got0) / result.window
            result.cpu_workers = (sum(c1) - sum(c0)) / result.window
            result.cpu_operator = (s1 - s0) / result.window
            result.cpu_workers_loop = (loops1[0] - loops0[0]) / result.window
            result.cpu_operator_loop = (loops1[1] - loops0[1]) / result.window
            result.rss_operator = _rss_mb()
            result.rss_workers = [c.rss_mb() for c in children]

            progress("UAVs stop pushing; draining what is in flight")
            for q in quiets:
                q.set()
            finals = await asyncio.gather(
                *(asyncio.to_thread(c.wait_report, "quiet", 30) for c in children)
            )
            last = {
                u: q["last"] for group, q in zip(plan.groups, finals, strict=True) for u in group
            }
            result.late_ticks = sum(q["late"] for q in finals)
            result.worker_gc_longest_ms = tuple(
                max(q["gc_longest"][g] for q in finals) for g in range(3)
            )
            result.worker_lag_ms = max(q["lag"] for q in finals)
            result.at_once = sum(q["at_once"] for q in finals)
            result.on_thread = sum(q.get("on_thread", 0) for q in finals)
            result.handled = sum(q["handled"] for q in finals)
            probes = [q["probe"] for q in finals if q["probe"]]
            if probes:
                result.worker_probe = {
                    k: sum(p[k] for p in probes) for k in probes[0] if k != "worst"
                }
                result.worker_probe["worst"] = max(p["worst"] for p in probes)
            drain = time.monotonic() + 15
            # Polled: waking on every one of 320 streams' samples would cost more than this.
            while time.monotonic() < drain and any(  # noqa: ASYNC110
                k.top < last[u] for (u, _), k in counters.items()
            ):
                await asyncio.sleep(0.05)
            for (uav, semantic), k in counters.items():
                if k.first is None:
                    result.never_arrived += 1
                    continue
                want = last[uav] - k.first + 1
                result.expected += want
                result.lost += want - len(k.seen & set(range(k.first, last[uav] + 1)))
                result.duplicates += k.duplicates
                result.out_of_order += k.out_of_order
                result.counted += len(k.seen)
                rec = op.importer.get(uav, semantic)
                result.import_lost += 0 if rec is None else rec.lost
            result.e2e_ms = latency_ms
        finally:
            follower.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await follower
            # The operator is told every UAV is gone as they stop: expected, not worth a line each.
            quiet_log = logging.getLogger("federation")
            level = quiet_log.level
            quiet_log.setLevel(logging.ERROR)
            try:
                await asyncio.to_thread(_close_all, children)
            finally:
                quiet_log.setLevel(level)


def measure(
    platforms: int = PLATFORMS,
    streams: int = STREAMS,
    hz: float = HZ,
    seconds: float = SECONDS,
    workers: int = WORKERS,
    queries: int = QUERIES,
    *,
    bare: bool = True,
    probe: bool = False,
) -> ScaleResult:
    """Run the scale benchmark once (``workers`` processes host the UAVs); its figures.

    ``probe``: run `LoopProbe` in every worker and at the operator (off by default: its
    timer wakes every process 100 times a second, load on the machine it measures).
    """
    for name, value, low in (
        ("platforms", platforms, 1),
        ("streams", streams, 1),
        ("workers", workers, 1),
        ("queries", queries, 1),
    ):
        if not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int ≥ {low}, got {value!r}")
    if not hz > 0 or not seconds > 0:
        raise ValueError(f"hz and seconds must be positive, got hz={hz!r} seconds={seconds!r}")
    if workers > platforms:
        raise ValueError(f"workers ({workers}) must not exceed platforms ({platforms})")
    result = ScaleResult(platforms, streams, hz, workers)
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
        plan = _plan(Path(tmp), platforms, streams, workers)
        result.workers = len(plan.groups)
        result.host = {name: i for i, group in enumerate(plan.groups) for name in group}
        if bare:
            progress(f"peer: {platforms} bare zenoh sessions in {len(plan.groups)} processes")
            bare_join(plan, result)
        run_loop(_federation(plan, result, seconds, queries, probe))
    return result


# -- the report --------------------------------------------------------------------------------


def _slowest_rounds(r: ScaleResult, side: int) -> str:
    """The other side's times in the rounds of ``side``'s slowest 1% (0: ours, 1: raw)."""
    done = [x for x in r.rounds if x[side] is not None]
    done.sort(key=lambda x: x[side] or 0.0, reverse=True)
    worst = done[: max(1, len(done) // 100)]
    return ", ".join(
        f"{x[side]:.0f}/" + ("-" if x[1 - side] is None else f"{x[1 - side]:.0f}") for x in worst
    )


def _waited_for(r: ScaleResult) -> str:
    """Whose answer came last in ours' slowest 1% of rounds: UAV (its worker process)."""
    done = [(ms, last) for (ms, _), last in zip(r.rounds, r.last_answer, strict=False) if ms]
    done.sort(key=lambda x: x[0], reverse=True)
    worst = done[: max(1, len(done) // 100)]
    return ", ".join(
        f"{ms:.0f} ms {last} (process {r.host.get(last or '', '?')})" for ms, last in worst
    )


def _probe(p: dict[str, Any]) -> str:
    """A `LoopProbe` summary in words."""
    if not p:
        return "not measured"
    late, ran, waited = p["worst"]
    return (
        ", ".join(f"{k} {p[k + '>5']}/{p[k + '>20']}" for k in LoopProbe.KINDS)
        + f"; the worst {late:.0f} ms late: ran {ran:.0f} ms, waited for a core {waited:.0f} ms"
    )


def _dist(xs: list[float], unit: str) -> str:
    if not xs:
        return "none"
    return (
        f"p50 {pct(xs, 0.5):.2f} {unit}, p99 {pct(xs, 0.99):.2f} {unit}, max {max(xs):.2f} {unit}"
    )


def print_result(r: ScaleResult, prefix: str = "scale-32") -> list[str]:
    """Print one run's figures and its BENCH lines (named from ``prefix``); the lines."""
    per = r.platforms / r.workers
    print(
        f"  {r.platforms} UAVs in {r.workers} processes ({per:g} each) + the operator; "
        f"{r.streams} streams each at {r.hz:g} Hz; event loop of the operator and the "
        f"workers: {event_loop_name()}"
    )
    print(
        f"  join: all members {r.join:.2f} s after launch (target ≤ {JOIN_TARGET:g} s: "
        f"{'met' if r.join <= JOIN_TARGET else 'MISSED'}); bare zenoh sessions "
        f"{r.bare_join:.2f} s; launch → interpreter ready (imports) "
        f"{_dist(r.spawn_to_imported, 's')}; platform open → joined "
        f"{_dist(r.open_to_joined, 's')}; launch → joined (own view) "
        f"{_dist(r.launch_to_joined, 's')}"
    )
    print(f"  create-stream to every UAV until every import arrived: {r.streams_agreed:.2f} s")
    print(
        f"  global get-latest of {r.streams} labels from {r.platforms} UAVs: "
        f"{len(r.query_ms)} answered by all, {_dist(r.query_ms, 'ms')} (target p99 ≤ "
        f"{QUERY_TARGET_P99:g} ms: "
        f"{'met' if pct(r.query_ms, 0.99) <= QUERY_TARGET_P99 else 'MISSED'}); "
        f"failed {len(r.query_failures)}"
        + (f" (first: {r.query_failures[0]})" if r.query_failures else "")
    )
    print(f"  the same query before any export flowed: {_dist(r.idle_ms, 'ms')}")
    print(
        f"  the UAVs' Federation Agents answered {r.at_once} of the {r.handled} messages they "
        "handled as they came (`answer_at_once`: no mailbox, no task), "
        f"{r.on_thread} of them on zenoh's thread (the lane: before the event loop woke)"
    )
    print(
        f"  raw zenoh get to {r.platforms} queryables on the same sessions: "
        f"{len(r.raw_ms)} complete, {_dist(r.raw_ms, 'ms')}; incomplete {r.raw_failures}"
    )
    ratios = [pct(r.query_ms, q) / pct(r.raw_ms, q) for q in (0.5, 0.99)] if r.raw_ms else []
    if ratios:
        met = all(x <= QUERY_TARGET_RATIO for x in ratios)
        print(
            f"  ours / raw over the same {len(r.rounds)} rounds: p50 {ratios[0]:.2f}, p99 "
            f"{ratios[1]:.2f} (target ≤ {QUERY_TARGET_RATIO:g}: {'met' if met else 'MISSED'}); "
            f"slowest 1% of rounds, ours/raw ms: by ours {_slowest_rounds(r, 0)}; by raw "
            f"{_slowest_rounds(r, 1)}; ours' slowest rounds waited last for "
            f"{_waited_for(r)}"
        )
    print(
        f"  the workers' longest GC per generation "
        f"{'/'.join(f'{x:.1f}' for x in r.worker_gc_longest_ms)} ms, their push loops woke "
        f"up to {r.worker_lag_ms:.0f} ms late; the operator's GC over the window, per "
        "generation: "
        f"{'/'.join(map(str, r.gc_collections))} collections, the longest "
        f"{'/'.join(f'{x:.1f}' for x in r.gc_longest_ms)} ms; rounds with a collection of "
        f"generation 2 in them, ours/raw ms: "
        + (", ".join(f"{a or 0:.0f}/{b or 0:.0f}" for a, b in r.rounds_in_gc) or "none")
    )
    print(
        f"  loop lag (a {1e3 * LoopProbe().every:g} ms timer late by > 5 / > 20 ms; busy: the "
        "loop thread ran ≥ half of it, core: it waited for a core, gil: it slept, another "
        f"thread held the GIL): workers "
        f"{_probe(r.worker_probe)}; the operator over the window {_probe(r.operator_probe)}"
    )
    print(
        f"  samples: {r.counted} counted at the operator over the run, {r.expected} pushed "
        f"in the counted ranges, lost {r.lost} "
        f"({'none' if r.lost == 0 and r.import_lost == 0 else 'LOST'}), "
        f"duplicates {r.duplicates}, out of order {r.out_of_order}, streams never arrived "
        f"{r.never_arrived}, import proxies counted lost {r.import_lost}; over the "
        f"{r.window:.1f} s window {fmt(r.window_rate)}/s (pushed ≈ "
        f"{fmt(r.platforms * r.streams * r.hz)}/s); UAV ticks late > 1 period {r.late_ticks}"
    )
    print(f"  end to end (UAV valid time → operator's subscriber): {_dist(r.e2e_ms, 'ms')}")
    rss_w = sum(r.rss_workers)
    rss_b = sum(r.rss_bare_workers)
    print(
        f"  CPU over the window: operator {r.cpu_operator:.2f} cores (its loop thread "
        f"{r.cpu_operator_loop:.2f}), workers {r.cpu_workers:.2f} cores (their loop threads "
        f"{r.cpu_workers_loop:.2f}; {1e3 * r.cpu_workers / r.platforms:.1f} ms/s per UAV); "
        f"machine load average {r.load[0]:.1f} → {r.load[1]:.1f} ({os.cpu_count()} CPUs: "
        "other work on this machine shows here)"
    )
    print(
        f"  RSS: operator {r.rss_operator:.0f} MB; workers {rss_w:.0f} MB in all "
        f"({', '.join(f'{x:.0f}' for x in r.rss_workers)}), {rss_w / r.platforms:.1f} MB per "
        f"UAV; bare zenoh workers {rss_b:.0f} MB ({rss_b / r.platforms:.1f} MB per session)"
    )
    lines = [
        report(
            prefix, pct(r.query_ms, 0.99), "zenoh-get", pct(r.raw_ms, 0.99), "ms", better="lower"
        ),
        report(
            f"{prefix}-query-p50",
            pct(r.query_ms, 0.5),
            "zenoh-get",
            pct(r.raw_ms, 0.5),
            "ms",
            better="lower",
        ),
    ]
    if r.bare_join:  # the peer ran
        lines += [
            report(f"{prefix}-join", r.join, "zenoh-bare", r.bare_join, "s", better="lower"),
            report(
                f"{prefix}-rss",
                (rss_w + r.rss_operator) / (r.platforms + 1),
                "zenoh-bare",
                rss_b / r.platforms,
                "MB/platform",
                better="lower",
            ),
        ]
    lines.append(
        report(f"{prefix}-delivered", r.counted, "pushed", r.expected, "samples", better="higher")
    )
    return lines


def run(quick: bool | None = None, procs: bool | None = None) -> None:
    """The scale benchmark: 4 worker processes (BENCH ``scale-32…``), then one per platform.

    ``quick``: the first only, shorter; ``procs``: the second only (shorter if ``quick``).
    Either, when None, is read from the command line (``--quick``, ``--procs``).
    """
    args = sys.argv[1:]
    if quick is None:
        quick = "--quick" in args
    if procs is None:
        procs = "--procs" in args
    probe = "--probe" in args
    seconds, queries = (8.0, 100) if quick else (SECONDS, QUERIES)
    if not procs:
        r = measure(seconds=seconds, queries=queries, workers=WORKERS, probe=probe)
        print_result(r)
        if quick:
            return
        progress("again with one process per platform")
    r = measure(seconds=seconds, queries=queries, workers=PLATFORMS, probe=probe)
    print_result(r, "scale-32-procs")


if __name__ == "__main__":
    run()
