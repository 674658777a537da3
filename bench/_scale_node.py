"""The worker processes of ``bench.scale``: UAV platforms, or bare zenoh sessions beside them.

Module-level imports are light on purpose: this module is what a spawned interpreter
imports to find its target, and the bare worker must not pay for the federation's imports.
Both targets follow `bench._child.Child`: ``target(spec, …, reports, stop)``, reporting
``(kind, pid, data)`` tuples and returning once ``stop`` is set or the parent is gone.

- ``uav_main``: hosts ``spec["configs"]`` UAV platforms, each a whole `FederationPlatform`
  (its own zenoh session, Interface Agent, proxies, Federation Agent), opened at once;
  each provides ``spec["streams"]`` local streams and pushes a sequence number into every
  one at ``spec["hz"]`` until ``quiet`` is set, then reports the last number pushed. Each
  also answers raw zenoh gets on ``scale/raw/<name>`` with its latest numbers, on its own
  session: the raw peer of the operator's global query. Its loop is `agents.run`'s, as
  ``dyknow node``'s: uvloop where installed.
- ``bare_main``: opens the same number of zenoh sessions with the same settings, each
  declaring a liveliness token: the least a member of a zenoh network costs to appear.
"""

from __future__ import annotations

import gc
import json
import os
import time
import traceback
from typing import Any

_T_MODULE = time.time()

RAW_KEY = "scale/raw"  # RAW_KEY/<platform>: that platform's latest numbers, raw zenoh
BARE_KEY = "scale/bare"  # BARE_KEY/<name>: a bare session's liveliness token


def local_label(j: int) -> str:
    """The UAV's local label of its stream ``j``."""
    return f"uav/stream/{j}"


def semantic_label(j: int) -> str:
    """The federation's semantic label of stream ``j``."""
    return f"stream-{j}"


class LoopProbe:
    """Loop-lag probe: a timer every ``every`` s notes how late it fired, and why.

    A late wake-up is a long turn of the loop or a starved thread. Over the span from
    setting the timer to its late firing, from the loop thread's ``schedstat`` (CPU, and
    time runnable but waiting for a core; a few µs a look): ``busy`` when it ran at
    least half of the lag (something long ran on the loop: an export turn, a
    collection), else ``core`` when it waited for a core at least half of it (the
    machine is over-subscribed), else ``gil`` (it slept: another thread of the process
    held the GIL). Kept: the count of lags over 5 and 20 ms of each kind, and the worst
    with its three parts (ms).
    """

    KINDS = ("busy", "core", "gil")

    def __init__(self, every: float = 0.01) -> None:
        self.every = every
        self.counts = {f"{k}>{ms}": 0 for k in self.KINDS for ms in (5, 20)}
        self.worst: tuple[float, float, float] = (0.0, 0.0, 0.0)  # ms late, ran, waited
        self._handle: Any = None

    def start(self, loop: Any) -> None:
        """Start probing on ``loop`` (call from its thread)."""
        import threading

        self._loop = loop
        # kept open and read with pread: 1 µs a look, where open/read/close takes 13
        self._fd = os.open(f"/proc/self/task/{threading.get_native_id()}/schedstat", os.O_RDONLY)
        self._arm()

    def _sched(self) -> tuple[float, float]:
        """The loop thread's CPU and run-queue wait so far (ms)."""
        ran, waited = os.pread(self._fd, 128, 0).split()[:2]
        return int(ran) / 1e6, int(waited) / 1e6

    def _arm(self) -> None:
        self._due = time.perf_counter() + self.every
        self._at = self._sched()
        self._handle = self._loop.call_later(self.every, self._fire)

    def _fire(self) -> None:
        late = 1e3 * (time.perf_counter() - self._due)
        if late > 5.0:
            ran, waited = self._sched()
            ran -= self._at[0]
            waited -= self._at[1]
            kind = "busy" if ran >= late / 2 else "core" if waited >= late / 2 else "gil"
            self.counts[f"{kind}>5"] += 1
            if late > 20.0:
                self.counts[f"{kind}>20"] += 1
            if late > self.worst[0]:
                self.worst = (late, ran, waited)
        self._arm()

    def stop(self) -> None:
        """Stop probing."""
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
            os.close(self._fd)

    def summary(self) -> dict[str, Any]:
        """What the probe saw: the counts and the worst lag (ms late, ran, waited for a core)."""
        return {**self.counts, "worst": self.worst}


def uav_main(spec: dict[str, Any], quiet: Any, reports: Any, stop: Any) -> None:
    """A worker's entry point: run its UAV platforms until ``stop``; errors are reported."""
    t_main = time.time()
    try:
        from agents import run

        run(_uavs(spec, t_main, quiet, reports, stop))
    except BaseException:
        reports.put(("error", os.getpid(), traceback.format_exc()))
        raise SystemExit(1) from None


async def _uavs(spec: dict[str, Any], t_main: float, quiet: Any, reports: Any, stop: Any) -> None:
    import asyncio
    import contextlib

    from agents.transports import ZenohTransport
    from federation import FederationPlatform, PlatformConfig
    from federation._cli_common import settle_gc

    streams = int(spec["streams"])
    parent = os.getppid()
    t_imported = time.time()

    class Uav:
        """One platform and what the bench keeps beside it."""

        def __init__(self, config: dict[str, Any]) -> None:
            self.name = str(config["name"])
            self.config = PlatformConfig.from_dict(config, source=f"bench uav {self.name}")
            self.last = [-1] * streams  # read by zenoh's callback thread: ints, no lock needed
            self.sources: list[Any] = []
            self.opened = self.ready = 0.0
            self.platform: Any = None

        def answer(self, query: Any) -> None:
            """The raw peer of the global query: this platform's latest numbers, as JSON."""
            query.reply(query.key_expr, json.dumps(self.last))

        async def open(self, stack: contextlib.AsyncExitStack) -> None:
            """Open the platform (left on ``stack``), add its sources and queryable, join."""
            self.opened = time.time()
            platform = self.platform = FederationPlatform(self.config, join=False)
            await stack.enter_async_context(platform)
            self.sources = [platform.instance.add_source(local_label(j)) for j in range(streams)]
            transport = platform.transport
            assert isinstance(transport, ZenohTransport)
            queryable = transport.session.declare_queryable(f"{RAW_KEY}/{self.name}", self.answer)
            stack.callback(queryable.undeclare)  # before the platform closes its session
            await platform.join()
            self.ready = time.time()

    async with contextlib.AsyncExitStack() as stack:
        uavs = [Uav(c) for c in spec["configs"]]
        await asyncio.gather(*(u.open(stack) for u in uavs))
        settle_gc()  # as `dyknow node` does once its platform is up
        gc_longest = [0.0, 0.0, 0.0]  # ms, per generation, from here on
        gc_started = 0.0
        worst_lag = 0.0  # ms the push loop woke later than asked

        def on_gc(phase: str, info: dict[str, int]) -> None:
            nonlocal gc_started
            if phase == "start":
                gc_started = time.perf_counter()
            else:
                gen = info["generation"]
                took = 1e3 * (time.perf_counter() - gc_started)
                gc_longest[gen] = max(gc_longest[gen], took)

        gc.callbacks.append(on_gc)
        reports.put(
            (
                "ready",
                os.getpid(),
                {
                    "module": _T_MODULE,
                    "main": t_main,
                    "imported": t_imported,
                    "platforms": {u.name: (u.opened, u.ready) for u in uavs},
                },
            )
        )
        loop = asyncio.get_running_loop()
        probe = LoopProbe()
        if spec.get("probe"):
            probe.start(loop)
        period = 1.0 / float(spec["hz"])
        seq = 0
        late = 0  # ticks that started more than a period behind schedule
        tick = loop.time()
        # A multiprocessing Event cannot be awaited: poll it (and the parent's life) per tick.
        while not quiet.is_set() and not stop.is_set() and os.getppid() == parent:
            for u in uavs:
                for j, source in enumerate(u.sources):
                    source.push(seq)
                    u.last[j] = seq
            seq += 1
            tick += period
            delay = tick - loop.time()
            if delay < -period:
                late += 1
            asked = loop.time() + max(delay, 0.0)
            await asyncio.sleep(max(delay, 0.0))
            worst_lag = max(worst_lag, 1e3 * (loop.time() - asked))
        gc.callbacks.remove(on_gc)
        probe.stop()
        reports.put(
            (
                "quiet",
                os.getpid(),
                {
                    "last": seq - 1,
                    "late": late,
                    "gc_longest": gc_longest,
                    "lag": worst_lag,
                    "probe": probe.summary() if spec.get("probe") else {},
                    # the operator's queries its Federation Agents answered as they came
                    # (`answer_at_once`), of all they handled
                    "at_once": sum(
                        u.platform.federation_agent.stats.answered_at_once for u in uavs
                    ),
                    "handled": sum(u.platform.federation_agent.stats.handled for u in uavs),
                    # of those, answered on zenoh's thread (`InterfaceAgent.lane`)
                    "on_thread": sum(
                        getattr(u.platform.interface, "answered_on_thread", 0) for u in uavs
                    ),
                },
            )
        )
        while not stop.is_set() and os.getppid() == parent:  # noqa: ASYNC110
            await asyncio.sleep(0.1)


def zenoh_settings(config: Any) -> list[tuple[str, str]]:
    """The JSON5 settings (path, value) a `ZenohConfig` applies, for a bare session."""
    return [
        ("mode", json.dumps(config.mode)),
        ("listen/endpoints", json.dumps(list(config.listen or ()))),
        ("connect/endpoints", json.dumps(list(config.connect))),
        ("scouting/multicast/enabled", json.dumps(config.multicast_scouting)),
        ("scouting/gossip/enabled", json.dumps(config.gossip)),
        ("open/return_conditions/connect_scouted", json.dumps(config.wait_for_scouted)),
        # what `ZenohConfig.to_zenoh` sets for every session of ours besides the above
        ("transport/link/tx/queue/size/data", "16"),
        ("transport/shared_memory/enabled", "false"),
    ]


def bare_main(spec: dict[str, Any], reports: Any, stop: Any) -> None:
    """Open ``spec["sessions"]`` bare zenoh sessions at once, each with a token; idle."""
    t_main = time.time()
    try:
        from concurrent.futures import ThreadPoolExecutor

        import zenoh

        imported = time.time()

        def open_one(item: tuple[str, list[tuple[str, str]]]) -> tuple[Any, Any]:
            name, settings = item
            config = zenoh.Config()
            for path, value in settings:
                config.insert_json5(path, value)
            session = zenoh.open(config)
            return session, session.liveliness().declare_token(f"{BARE_KEY}/{name}")

        items = [(n, s) for n, s in spec["sessions"]]
        with ThreadPoolExecutor(max(len(items), 1)) as pool:
            opened = list(pool.map(open_one, items))
        reports.put(
            (
                "ready",
                os.getpid(),
                {"module": _T_MODULE, "main": t_main, "imported": imported, "ready": time.time()},
            )
        )
        parent = os.getppid()
        while not stop.wait(0.1) and os.getppid() == parent:
            pass
        for session, token in opened:
            token.undeclare()
            session.close()
    except BaseException:
        reports.put(("error", os.getpid(), traceback.format_exc()))
        raise SystemExit(1) from None
