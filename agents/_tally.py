"""Refusals summed up per key and interval: bounded audit records (or log lines) under a flood.

Some refusals are part of normal traffic (a directory event re-sent), or cost a sender
little to repeat (a request an agent refuses, a message for a full mailbox): a record
each would let a flood of them flood the audit. `Tally` counts each one (a dict
increment under a lock) and hands the counts to its ``emit`` callback once per
``interval`` at most, one call per key: the first refusal after a quiet spell at once,
what follows within the interval summed up into the next call. The quiet spell is the
tally's as a whole, not the key's: within ``interval`` of any flush, a key's first
refusal waits for the next one too. `Tally.close` flushes for the last time.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
from collections.abc import Callable, Hashable
from typing import Any

log = logging.getLogger(__name__)

OVERFLOW = "*"
"""The key refusals share once a tally holds ``max_keys`` others in one interval."""

Emit = Callable[[Hashable, int, str, "float | None"], None]
"""``emit(key, count, detail, seconds)``: ``count`` refusals of ``key`` since the last
call (``seconds`` ago; None for the first), ``detail`` the last one's."""


class Tally:
    """Counts refusals per key; ``emit`` is called at most once per key per ``interval``.

    `add` may be called from any thread once the tally is bound to its event loop
    (`bind`; the first `add` on the loop binds it too); ``emit`` runs on the loop. Keys
    are bounded by ``max_keys`` per interval (the rest are summed under `OVERFLOW`).
    """

    __slots__ = (
        "_closed", "_emit", "_handle", "_last", "_lock", "_loop", "_pending", "_scheduled",
        "interval", "max_keys",
    )  # fmt: skip

    def __init__(self, emit: Emit, *, interval: float = 1.0, max_keys: int = 256) -> None:
        if not (interval > 0 and math.isfinite(interval)):
            raise ValueError(f"a tally's interval must be a positive number of s, not {interval}")
        self.interval = interval
        self.max_keys = max_keys
        self._emit = emit
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending: dict[Hashable, list[Any]] = {}  # key -> [count, last detail]
        self._scheduled = False  # a flush is due (or being scheduled)
        self._last = -math.inf  # loop time of the last flush
        self._handle: asyncio.TimerHandle | None = None  # the flush armed for later
        self._closed = False  # `close`d: refusals are counted only, never emitted

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Flush on ``loop`` (for `add` from other threads)."""
        self._loop = loop

    def add(self, key: Hashable, detail: str, n: int = 1) -> None:
        """Count ``n`` refusals of ``key`` (``detail``: why, the latest kept)."""
        with self._lock:
            pending = self._pending
            entry = pending.get(key)
            if entry is None:
                if len(pending) >= self.max_keys:
                    key = OVERFLOW
                    entry = pending.get(key)
                if entry is None:
                    entry = pending[key] = [0, detail]
            entry[0] += n
            entry[1] = detail
            schedule = not self._scheduled and not self._closed
            if schedule:
                self._scheduled = True
        if schedule:
            self._schedule()

    def _schedule(self) -> None:
        loop = self._loop
        if loop is None:
            try:
                loop = self._loop = asyncio.get_running_loop()
            except RuntimeError:  # not bound, not on a loop: flushed by the next add on one
                with self._lock:
                    self._scheduled = False
                return
        with contextlib.suppress(RuntimeError):  # the loop is closed: nothing flushes now
            loop.call_soon_threadsafe(self._arm)

    def _arm(self) -> None:
        """On the loop: flush now if an interval passed since the last, else when it has."""
        loop = self._loop
        assert loop is not None
        if self._closed:
            return  # armed before `close`, which flushed
        wait = self._last + self.interval - loop.time()
        if wait > 0:
            self._handle = loop.call_later(wait, self.flush)
        else:
            self.flush()

    def flush(self) -> None:
        """Emit what is pending now, one call per key (on the loop)."""
        loop = self._loop
        now = loop.time() if loop is not None else 0.0
        handle, self._handle = self._handle, None
        if handle is not None:
            handle.cancel()  # a no-op when it is what runs this flush
        with self._lock:
            pending, self._pending = self._pending, {}
            self._scheduled = False
        seconds = None if math.isinf(self._last) else now - self._last
        if pending:
            self._last = now
        for key, (count, detail) in pending.items():
            try:
                self._emit(key, count, detail, seconds)
            except Exception:  # one key's record failing must not lose the others'
                log.exception("could not report %d refusal(s) of %r", count, key)

    def close(self) -> None:
        """Flush for the last time; what is added later is counted (`pending`), not emitted.

        Its owner calls it where it closes, before its audit does: no flush is left armed
        on a loop that may close with it.
        """
        with self._lock:
            if self._closed:
                return  # flushed when it closed (only a `flush` of its own emits what came since)
            self._closed = True
        self.flush()

    @property
    def pending(self) -> int:
        """Refusals counted and not yet emitted."""
        with self._lock:
            return sum(e[0] for e in self._pending.values())


def since(seconds: float | None) -> str:
    """`` in 1.0 s`` for a tally's ``seconds`` (nothing for the first report)."""
    return "" if seconds is None else f" in {seconds:.1f} s"
