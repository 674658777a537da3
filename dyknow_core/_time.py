"""Time on an instance's time line: integer nanoseconds inside, seconds at the edges."""

from __future__ import annotations

import asyncio
import heapq
import time
from typing import Protocol, runtime_checkable

NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    """Convert seconds (an API edge value) to integer nanoseconds."""
    return round(seconds * NS_PER_S)


def ns_to_seconds(ns: int) -> float:
    """Convert integer nanoseconds to seconds for display and API edges."""
    return ns / NS_PER_S


@runtime_checkable
class Clock(Protocol):
    """The source of "now" for an instance; injectable so tests and replays control time."""

    def now(self) -> int:
        """Return the current time point in nanoseconds."""
        ...

    async def sleep_until(self, t: int) -> None:
        """Wait until the clock reads at least ``t`` (nanoseconds)."""
        ...


class RealClock:
    """Wall-clock time (``time.time_ns``), for live platforms."""

    __slots__ = ()

    def now(self) -> int:
        """Return the wall-clock time in nanoseconds since the epoch."""
        return time.time_ns()

    async def sleep_until(self, t: int) -> None:
        """Sleep on the event loop until the wall clock reaches ``t``."""
        delay = (t - time.time_ns()) / NS_PER_S
        if delay > 0:
            await asyncio.sleep(delay)


class ManualClock:
    """A clock that only moves when told to: tests, replays and deterministic demos."""

    def __init__(self, start: int = 0) -> None:
        self._now = start
        self._sleepers: list[tuple[int, int, asyncio.Future[None]]] = []
        self._seq = 0

    def now(self) -> int:
        """Return the time the clock was last set to."""
        return self._now

    def set(self, t: int) -> None:
        """Move the clock to ``t`` (never backwards) and wake sleepers whose time came."""
        if t < self._now:
            raise ValueError(f"a manual clock does not go back: {t} < {self._now}")
        self._now = t
        while self._sleepers and self._sleepers[0][0] <= t:
            _, _, fut = heapq.heappop(self._sleepers)
            if not fut.done():
                fut.set_result(None)

    def advance(self, dt: int) -> None:
        """Move the clock forward by ``dt`` nanoseconds."""
        self.set(self._now + dt)

    def advance_seconds(self, dt: float) -> None:
        """Move the clock forward by ``dt`` seconds."""
        self.advance(seconds_to_ns(dt))

    async def sleep_until(self, t: int) -> None:
        """Wait until someone moves the clock to ``t`` or later."""
        if t <= self._now:
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._seq += 1
        heapq.heappush(self._sleepers, (t, self._seq, fut))
        await fut
