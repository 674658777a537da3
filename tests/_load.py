"""How loaded the machine running the tests is, how fast its CPU: for tests run in real time."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import os
import statistics
import threading
import time
from types import TracebackType

# The median CPU time of one `_cpu_work` on the machine the tests' CPU bounds were measured
# on (2 cores of an AMD EPYC, busy with other work as well), in seconds.
CPU_WORK_SECONDS = 0.0033


def slowdown() -> float:
    """How many times slower than on a machine of its own this process runs now (>= 1).

    Measured: a busy loop's CPU time over its wall time is the share of a CPU it gets (a
    tenth with a load of 20 on 2 cores); the load average says the same over the last
    minute, and whichever is worse counts, a busy spell being short or long.
    """
    t0, c0 = time.monotonic(), time.thread_time()
    while time.monotonic() - t0 < 0.2:
        pass
    share = (time.thread_time() - c0) / (time.monotonic() - t0)
    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    return max(1.0, load, 1.0 / max(share, 0.02))


def _cpu_work() -> None:
    """A platform's work on messages, in small: dicts, str and bytes, JSON, a hash."""
    messages = {}
    for i in range(800):
        key = f"uav-{i}/acl/{i * 7919 % 1000}"
        messages[key] = {"n": i, "from": key.split("/")[0], "body": key.encode() * 3}
    for key, m in messages.items():
        text = json.dumps({"key": key, "n": m["n"], "from": m["from"]})
        back = json.loads(text)
        data = m["body"] + text.encode()
        hashlib.sha256(data).digest()
        if back["key"].startswith("uav-1"):
            data.find(b"acl")


def cpu_slowdown(samples: int = 15) -> float:
    """How many times slower this CPU is than the one the CPU bounds were measured on (>= 1).

    For bounds on a process's CPU time (what a flood costs a victim per query, say),
    which a slower CPU stretches and others' load hardly does: the median CPU time of a
    fixed piece of work, run now, against CPU_WORK_SECONDS. Never below 1: a faster CPU
    keeps the bound as it was measured.
    """
    times = []
    for _ in range(samples):
        c0 = time.thread_time()
        _cpu_work()
        times.append(time.thread_time() - c0)
        time.sleep(0.01)  # spread over a while: a busy spell does not make the median
    return max(1.0, statistics.median(times) / CPU_WORK_SECONDS)


class CpuSlowdownMeter:
    """`cpu_slowdown` measured over a stretch of time, in a thread: ``with`` the stretch.

    One measurement before a flood swung from 1.3 to 2.4 on a busy 2-core machine, seconds
    apart (the other core's load and the clock move the CPU time of the same work):
    a bound on a victim's CPU time during the flood takes the slowdown of the same time.
    """

    def __init__(self, pause: float = 0.02) -> None:
        self.times: list[float] = []
        self._pause = pause
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._measure, daemon=True)

    def _measure(self) -> None:
        while not self._stop.is_set():
            c0 = time.thread_time()
            _cpu_work()
            self.times.append(time.thread_time() - c0)
            self._stop.wait(self._pause)  # a share of one core, not all of it

    def __enter__(self) -> CpuSlowdownMeter:
        self._thread.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def slowdown(self) -> float:
        """How many times slower this CPU ran than the reference, on average over the stretch.

        The mean, as the victim's CPU time sums its work over the stretch, slow spells and
        quick ones alike (a median picks one of them); the slowest and quickest tenth are
        left out (a collection of this process's garbage, say). Never below 1.
        """
        times = sorted(self.times)
        assert times, "the stretch measured nothing"
        cut = len(times) // 10
        kept = times[cut : len(times) - cut]
        return max(1.0, statistics.fmean(kept) / CPU_WORK_SECONDS)


class LoopLag:
    """How late this event loop ran its timers over a stretch: ``async with`` the stretch.

    A timer is due at a loop time; a busy machine runs it later, by as much as the loop
    waited for a CPU. ``worst``: the latest this one's own timers, one due every
    ``period`` s, ran meanwhile. Another timer, due up to ``period`` s before one of them
    in the same stall, ran up to ``period`` s later still: a bound on when a timer-driven
    thing happened (a lease's expiry, a wait's end) is the code's promise plus ``worst``
    plus ``period``.
    """

    def __init__(self, period: float = 0.02) -> None:
        self.worst = 0.0
        self.period = period
        self._task: asyncio.Task[None] | None = None

    async def _measure(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            due = loop.time() + self.period
            await asyncio.sleep(self.period)
            self.worst = max(self.worst, loop.time() - due)

    async def __aenter__(self) -> LoopLag:
        self._task = asyncio.create_task(self._measure())
        return self

    async def __aexit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        assert self._task is not None
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
