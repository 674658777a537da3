"""Small asyncio building blocks the agents and their users share.

`Mailbox`: a bounded queue whose one consumer waits for the next item up to a deadline.
`Deadlines`: the deadlines of a loop's waits, kept by one timer at the earliest.
`Ticker`: the ticks of a periodic loop, on a fixed grid of loop time.
`Pending`: a count other threads add to, taken by one task at most once per period.
`run`: ``asyncio.run`` on uvloop when it is installed (what long-running processes use).
`KeepCancelled`: cancels again what outlived its cancellation, so that a close ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import threading
from collections import deque
from collections.abc import Callable, Coroutine, Iterable
from heapq import heapify, heappop, heappush
from typing import Any, Generic, Self, TypeVar

T = TypeVar("T")

_TIMED_OUT: Any = object()

LOOP_ENV = "DYKNOW_EVENT_LOOP"
"""Set to ``asyncio`` to run `run` on asyncio's own loop even where uvloop is installed."""


def event_loop_name() -> str:
    """The loop `run` uses here: ``uvloop`` when installed and not turned off, else ``asyncio``."""
    if os.environ.get(LOOP_ENV, "").strip().lower() == "asyncio":
        return "asyncio"
    try:
        import uvloop  # noqa: F401
    except ImportError:
        return "asyncio"
    return "uvloop"


def run(main: Coroutine[Any, Any, T]) -> T:
    """Run ``main`` to completion on a new event loop, as ``asyncio.run``: uvloop's if it can.

    uvloop's loop wakes and turns faster than asyncio's (libuv's self-pipe and epoll, its
    callbacks in C): an ACL round trip between two processes spends ~10-20 % less on
    both sides. ``DYKNOW_EVENT_LOOP=asyncio`` keeps asyncio's own loop.
    """
    if event_loop_name() == "uvloop":
        import uvloop

        return uvloop.run(main)
    return asyncio.run(main)


async def together(*steps: Coroutine[Any, Any, Any]) -> None:
    """Run independent ``steps`` at once; the first failure is raised, the others cancelled.

    For starts that wait on a remote peer at each step (an MQTT subscribe is a round trip
    through the broker): the steps' waits overlap rather than add up. A step undoes
    itself when cancelled or failing; what those that succeeded set up is the caller's
    to undo, as after a failing sequence. The failure is raised as the step raised it,
    not in an exception group, so callers catch what they caught before; but a caller
    that is itself being cancelled gets its `CancelledError`, whatever the steps raised.
    """
    # not a TaskGroup: on Python 3.11 it raises its steps' errors over its own task's
    # cancellation, and a step failing while it waits for the others leaves that task
    # counted as cancelling for good: the caller could not tell it was being cancelled
    failed: list[BaseException] = []

    def settled(task: asyncio.Task[Any]) -> None:
        if not task.cancelled() and (exc := task.exception()) is not None:
            failed.append(exc)

    tasks = [asyncio.ensure_future(step) for step in steps]
    for task in tasks:
        task.add_done_callback(settled)
    cancelled = False
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
    except asyncio.CancelledError:
        cancelled = True
    running = [t for t in tasks if not t.done()]
    if cancelled or failed:
        for task in running:
            task.cancel()
    while running:  # each step undoes itself: waited for, even by a caller cancelled now
        try:
            await asyncio.wait(running)
        except asyncio.CancelledError:
            cancelled = True
        running = [t for t in running if not t.done()]
    current = asyncio.current_task()
    if cancelled or (failed and current is not None and current.cancelling()):
        # the caller's cancellation wins over a step's failure: it would otherwise take
        # that failure for the outcome and go on, its cancellation lost
        raise asyncio.CancelledError from (failed[0] if failed else None)
    if failed:
        first = failed[0]
        raise first from first.__cause__


def call_in_loop(
    loop: asyncio.AbstractEventLoop | None, fn: Callable[..., object], *args: Any
) -> None:
    """Call ``fn(*args)`` in ``loop``: now when it runs this thread (or is None), else soon.

    For callbacks any thread may make (a trust store changed from another thread) into
    state that belongs to one event loop.
    """
    try:
        here = asyncio.get_running_loop() is loop
    except RuntimeError:  # no loop runs in this thread
        here = False
    if here or loop is None:
        fn(*args)
    else:
        loop.call_soon_threadsafe(fn, *args)


def _expire(waiter: asyncio.Future[Any]) -> None:
    if not waiter.done():
        waiter.set_result(_TIMED_OUT)


_COMPACT_AT = 1024  # entries in a `Deadlines` heap before the ended waits are dropped


class Deadlines:
    """The deadlines of the waits of one event loop, kept by one timer at the earliest.

    A timer per wait costs its creation and its cancel each time a wait ends early, the
    common case (a reply comes well before its timeout). Here a wait adds an entry to a
    heap and a wait that ends cancels nothing: its entry is dropped when its time comes,
    or sooner once the heap holds many more entries than waits. One loop timer, at the
    earliest deadline, ends the waits whose deadline passed, as their own timers would.
    """

    __slots__ = ("_at", "_heap", "_limit", "_loop", "_timer")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._heap: list[tuple[float, int, asyncio.Future[Any]]] = []
        self._timer: asyncio.TimerHandle | None = None
        self._at = math.inf  # the timer's deadline (none armed: infinity)
        self._limit = _COMPACT_AT

    def add(self, deadline: float, waiter: asyncio.Future[Any]) -> None:
        """End ``waiter`` as timed out at ``deadline`` (loop time) if it is not done by then."""
        # refused before it is in the heap: a NaN there (or what is no number) breaks its
        # order, and no wait would end at its deadline any more
        if not deadline <= math.inf:
            raise ValueError(f"a deadline must be a number (loop time), got {deadline!r}")
        heap = self._heap
        if len(heap) >= self._limit:
            self._compact()
        # id: entries of one deadline never compare their futures (each is in once)
        heappush(heap, (deadline, id(waiter), waiter))
        if deadline < self._at:
            if self._timer is not None:
                self._timer.cancel()
            self._at = deadline
            self._timer = self._loop.call_at(deadline, self._expire)

    def __len__(self) -> int:
        return len(self._heap)

    def drop_ended(self) -> None:
        """Drop the waits that ended; disarm the timer when none waits any more (a stop)."""
        self._compact()
        if not self._heap and self._timer is not None:
            self._timer.cancel()
            self._timer = None
            self._at = math.inf

    def _compact(self) -> None:
        """Drop the entries of waits that ended; the next compaction at twice what is left."""
        heap = self._heap
        heap[:] = [e for e in heap if not e[2].done()]
        heapify(heap)
        self._limit = max(_COMPACT_AT, 2 * len(heap))

    def _expire(self) -> None:
        """The timer: end the waits whose deadline passed, arm it for the next one."""
        heap = self._heap
        # the timer fired for `_at`: that deadline has come, whatever the loop's clock
        # rounding; so has any other up to now
        due = max(self._at, self._loop.time())
        # a pop per entry due, not a pass over all: the waits still far from their deadline
        # may be many, and each timer would cost them all (each entry is popped only once)
        while heap and heap[0][0] <= due:
            waiter = heappop(heap)[2]
            if not waiter.done():  # in deadline order, as their own timers would
                waiter.set_result(_TIMED_OUT)
        # the next wake for a wait still waiting, not for one that ended early: popped one
        # by one (a pop compares ~2 log n entries), but once a share of the heap went so,
        # the rest goes in one pass (`_compact`: a look an entry, ~20x cheaper than a pop),
        # which costs at most about what the pops before it did
        budget = max(16, len(heap) >> 5)
        while heap and heap[0][2].done():
            if not budget:
                self._compact()
                break
            budget -= 1
            heappop(heap)
        # what is left holds every wait still waiting: the next compaction at twice that
        self._limit = max(_COMPACT_AT, 2 * len(heap))
        if heap:
            self._at = heap[0][0]
            self._timer = self._loop.call_at(self._at, self._expire)
        else:
            self._at = math.inf
            self._timer = None


class Mailbox(Generic[T]):
    """A bounded FIFO with one asyncio consumer, who waits for the next item up to a deadline.

    `put` never blocks: when the box is full it refuses the item, or with ``drop_oldest``
    drops the oldest to make room; either way it returns False and counts the loss in
    ``dropped``. Every call is made on the loop's thread (a transport's ``Inbox`` is the
    one filled from other threads).
    """

    __slots__ = ("_items", "_waiter", "drop_oldest", "dropped", "maxlen")

    def __init__(self, maxlen: int, *, drop_oldest: bool = False) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen must be at least 1, got {maxlen}")
        self._items: deque[T] = deque()
        self._waiter: asyncio.Future[Any] | None = None
        self.maxlen = maxlen
        self.drop_oldest = drop_oldest
        self.dropped = 0

    def put(self, item: T, *, force: bool = False) -> bool:
        """Add ``item`` at the end; False when full (refused, or the oldest dropped).

        ``force`` adds it even to a full box (an end marker must not be refused).
        """
        items = self._items
        added = True
        if len(items) >= self.maxlen and not force:
            self.dropped += 1
            if not self.drop_oldest:
                return False
            items.popleft()
            added = False
        items.append(item)
        w = self._waiter  # `_wake`, inline
        if w is not None and not w.done():
            w.set_result(None)
        return added

    def put_many(self, batch: Iterable[T]) -> int:
        """`put` each item of ``batch``, in order, waking the consumer once; how many fitted.

        The same accounting as a `put` per item: past ``maxlen`` the rest are refused, or
        with ``drop_oldest`` each drops the oldest; every loss is counted in ``dropped``.
        Returns how many of the puts would have returned True.
        """
        items = self._items
        before = len(items)
        items.extend(batch)
        n = len(items) - before
        lost = min(len(items) - self.maxlen, n)
        if lost > 0:
            self.dropped += lost
            if self.drop_oldest:  # each one past maxlen pushed the oldest out
                for _ in range(lost):
                    items.popleft()
            else:  # the last ones found the box full
                for _ in range(lost):
                    items.pop()
        if n and (lost < n or self.drop_oldest):
            self._wake()
        return n - max(lost, 0)

    def put_front(self, item: T) -> None:
        """Put ``item`` back in front, to be taken next (even when full)."""
        self._items.appendleft(item)
        self._wake()

    def _wake(self) -> None:
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    async def get(
        self,
        deadline: float | None = None,
        *,
        loop: asyncio.AbstractEventLoop | None = None,
        deadlines: Deadlines | None = None,
    ) -> T:
        """The next item; TimeoutError if none came by ``deadline`` (loop time; None: never).

        ``loop``: the running loop, when the caller has it at hand (Python 3.11 pays a
        system call, getpid, for each ``asyncio.get_running_loop``). ``deadlines``: that
        loop's `Deadlines`, to keep the deadline with instead of a timer of its own.
        """
        items = self._items
        if not items:
            if loop is None:
                loop = asyncio.get_running_loop()
            while not items:
                self._waiter = w = loop.create_future()
                timer = None
                try:  # a deadline refused leaves no waiter behind
                    if deadline is None:
                        pass
                    elif deadlines is not None:
                        deadlines.add(deadline, w)
                    else:
                        # a timer setting the future is cheaper than asyncio.timeout on a hot path
                        timer = loop.call_at(deadline, _expire, w)
                    await w
                finally:
                    self._waiter = None
                    if timer is not None:
                        timer.cancel()
                if w.result() is _TIMED_OUT and not items:
                    raise TimeoutError("nothing came by the deadline")
        return items.popleft()

    def get_nowait(self) -> T:
        """The next item if there is one; asyncio.QueueEmpty otherwise."""
        if not self._items:
            raise asyncio.QueueEmpty
        return self._items.popleft()

    def get_all_nowait(self) -> list[T]:
        """Every item queued now, in order (none: an empty list), taken without waiting."""
        items = list(self._items)
        self._items.clear()
        return items

    def __len__(self) -> int:
        return len(self._items)


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


class Pending:
    """A count any thread adds to, summed up by one task at most once per ``period`` s.

    For a periodic report of what happened (queries shed, messages dropped) that has
    nothing to say most of the time: ``n = await pending.take()`` sleeps while nothing
    is pending, so an idle process does not wake for it. The first count after a quiet
    spell is taken at once; what comes within ``period`` of a take is summed up into the
    next one.
    """

    __slots__ = ("_event", "_lock", "_loop", "_n", "_next", "period")

    def __init__(self, period: float) -> None:
        self.period = _check_period(period)
        self._lock = threading.Lock()
        self._n = 0
        self._loop: asyncio.AbstractEventLoop | None = None  # the taker's, once it waits
        self._event = asyncio.Event()
        self._next = -math.inf  # loop time the next take may return at

    def add(self, n: int = 1) -> None:
        """Count ``n`` more (from any thread); wakes the taking task if it sleeps."""
        with self._lock:
            self._n += n
            first = self._n == n
        loop = self._loop
        if first and loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closed: nothing takes now
                loop.call_soon_threadsafe(self._event.set)

    async def take(self) -> int:
        """Wait until something is pending and a period has passed since the last take."""
        loop = self._loop = asyncio.get_running_loop()
        while True:
            with self._lock:
                pending = self._n > 0
            if pending:
                break
            self._event.clear()
            with self._lock:  # an add between the check and the clear has set it again
                pending = self._n > 0
            if not pending:
                await self._event.wait()
        wait = self._next - loop.time()
        if wait > 0:
            await asyncio.sleep(wait)
        with self._lock:
            n, self._n = self._n, 0
        self._next = loop.time() + self.period
        return n


RECANCEL_AFTER = 5.0
"""Seconds a cancelled task may run on (its cleanup) before it is cancelled again."""


class KeepCancelled:
    """Every ``after`` s, cancel again each of ``tasks()`` still running, until `stop`.

    A cancellation can be lost: Python 3.11's ``asyncio.wait_for`` returns a result that
    comes in the same turn as the cancellation and drops it, and code may swallow one by
    mistake. A task that lost the one its owner's close sent ran on, and the task group
    closing waited for it forever. Cancelled again, it ends (trio's and anyio's
    cancellations likewise stay in force until the task ends), ``after`` s given to
    its cleanup each time.
    """

    __slots__ = ("_after", "_handle", "_loop", "_tasks")

    def __init__(
        self, tasks: Callable[[], Iterable[asyncio.Task[Any]]], after: float = RECANCEL_AFTER
    ) -> None:
        self._tasks = tasks
        self._after = after
        self._loop = asyncio.get_running_loop()
        self._handle: asyncio.TimerHandle | None = self._loop.call_later(after, self._again)

    def _again(self) -> None:
        for task in list(self._tasks()):
            if not task.done():
                task.cancel()
        self._handle = self._loop.call_later(self._after, self._again)

    def stop(self) -> None:
        """Cancel nothing more."""
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None


def _check_period(period: float) -> float:
    if not (period > 0 and math.isfinite(period)):
        raise ValueError(f"a period must be a positive number of seconds, got {period}")
    return period
