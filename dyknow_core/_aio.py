"""Small asyncio building blocks of the core's timers.

`Ticker`: the ticks of a periodic loop, on a fixed grid of loop time (the same as
``agents.Ticker``: the two packages do not import each other).
`sleep_until_woken`: a timer's wait for its next deadline on an instance clock, cut short
when the deadline moves.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from typing import Any, Self

from ._time import NS_PER_S, Clock, RealClock


class Ticker:
    """The ticks of a periodic loop: every ``period`` s of loop time, on a fixed grid.

    ``async for due in Ticker(1.0): ...`` runs the body once per period. The time the
    body takes does not push later ticks back (no drift); a body that overruns whole
    periods skips the ticks it missed (counted in ``skipped``) instead of running them
    back to back. ``period`` may be changed between ticks: it applies from the next one.
    Each tick is the loop time it was due at; the first comes one period after the
    first wait (or at ``first``, a loop time).
    """

    __slots__ = ("_due", "period", "skipped")

    def __init__(self, period: float, *, first: float | None = None) -> None:
        self.period = _check_period(period)
        self._due = first
        self.skipped = 0

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> float:
        return await self.tick()

    async def tick(self) -> float:
        """Wait for the next tick; returns the loop time it was due at."""
        period = _check_period(self.period)
        loop = asyncio.get_running_loop()
        now = loop.time()
        due = now + period if self._due is None else self._due
        if now - due >= period:  # overran: the ticks already past are skipped
            missed = math.floor((now - due) / period)
            due += missed * period
            self.skipped += missed
        if due > now:
            await asyncio.sleep(due - now)
        self._due = due + period
        return due


def _check_period(period: float) -> float:
    if not (period > 0 and math.isfinite(period)):
        raise ValueError(f"a period must be a positive number of seconds, got {period}")
    return period


async def sleep_until_woken(clock: Clock, deadline: int | None, wake: asyncio.Event) -> None:
    """Sleep until ``deadline`` on ``clock`` (ns; None: no deadline) or until ``wake`` is set.

    For timers whose next deadline may move earlier while they sleep: whoever moves it
    sets ``wake`` (the timer clears it before reading its deadline). It always yields to
    the loop at least once, and nothing it starts outlives it.
    """
    if deadline is None or type(clock) is RealClock:
        # The wait for ``wake`` in this task, cut short by a loop timer (the wall clock's
        # deadline is one): no task to start, and none to cancel and wait for once woken,
        # which would resume the timer turns later than the wake.
        delay = None if deadline is None else (deadline - clock.now()) / NS_PER_S
        if wake.is_set() or (delay is not None and delay <= 0):
            await asyncio.sleep(0)  # a timer whose deadline has passed still lets others run
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(delay):
                await wake.wait()
        return
    # Another clock's sleep is a coroutine: it and the wait for ``wake`` run as tasks
    loop = asyncio.get_running_loop()
    me = asyncio.current_task()
    owner = "sleep_until_woken" if me is None else me.get_name()
    waits: set[asyncio.Task[Any]] = {loop.create_task(wake.wait(), name=f"{owner}.wake")}
    if deadline is not None:
        sleeping = clock.sleep_until(deadline)
        waits.add(loop.create_task(sleeping, name=f"{owner}.deadline"))
    try:
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
    finally:
        # both end here: none outlives this call
        for w in waits:
            w.cancel()
        await asyncio.wait(waits)
