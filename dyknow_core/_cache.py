"""A location's per-stream cache and the fluent generator queries over it."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from itertools import islice
from typing import Any

from ._policy import Approximation, CacheSpec
from ._sample import RawSample, Sample
from ._time import seconds_to_ns


class Cache:
    """The last N samples and/or last T seconds (by available time) of one stream.

    T is counted back from the newest arrival, not from the clock: a stream that went quiet
    keeps its last T seconds. Samples are kept in arrival order, which is available-time
    order, so eviction is a ``popleft``. Superseded estimates (same valid time, later
    available time) are kept: that is what answers "what did we believe at tq about tv".
    """

    __slots__ = ("_buf", "_max_age", "_memo", "_watched", "evicted")

    def __init__(self, spec: CacheSpec) -> None:
        self._buf: deque[RawSample] = deque(maxlen=spec.max_samples)
        self._max_age = None if spec.max_age is None else seconds_to_ns(spec.max_age)
        self.evicted = 0
        # `latest` over everything cached, kept so that each update reads only what arrived
        # since (a query per stream per request must not scan the whole cache): the best
        # sample, its index among all ever added (evicted + cached), how many read, and the
        # newest arrival's available time. One tuple, replaced whole by `extend` (the
        # stream's one writer, on its event loop): `latest_now` reads it from any thread.
        self._memo: tuple[RawSample | None, int, int, int] = (None, -1, 0, 0)
        # kept up by every `extend` only once `latest_now` was asked (a stream another
        # thread reads): a stream nobody asks so pays nothing per batch (the pipeline's)
        self._watched = False

    def __len__(self) -> int:
        return len(self._buf)

    def extend(self, batch: list[RawSample]) -> None:
        """Add newly available samples (available times increasing) and evict what is too old."""
        buf = self._buf
        maxlen = buf.maxlen
        if maxlen is not None:
            over = len(buf) + len(batch) - maxlen
            if over > 0:
                self.evicted += min(over, len(buf) + len(batch))
        buf.extend(batch)
        if self._max_age is not None and buf:
            cutoff = buf[-1][2] - self._max_age
            while buf and buf[0][2] <= cutoff:
                # counted before it goes: evicted + len(buf) never dips to what a stale best
                # had read, which `latest_now` (another thread) would take as up to date
                self.evicted += 1
                buf.popleft()
        if self._watched:
            self._update()

    def _update(self) -> None:
        """Bring the best of everything cached up to date, reading only what arrived since."""
        buf = self._buf
        if not buf:
            self._memo = (None, -1, self.evicted, 0)
            return
        # indices among all samples ever added: buf[0] is the first not evicted (counted
        # from `evicted`, so extend keeps no count of its own)
        first = self.evicted
        appended = first + len(buf)
        best, best_at, start, _ = self._memo
        if start == appended and best is not None and best_at >= first:
            return  # nothing arrived since, and the best is still cached
        if start == appended - 1 and best is not None and best_at >= first:
            # one arrived since (a stream in flow): the loop below, without its iterators
            s = buf[-1]
            if s[1] >= best[1]:  # a later arrival wins a tie
                best, best_at = s, start
            self._memo = (best, best_at, appended, s[2])
            return
        if best is None or best_at < first:  # none yet, or evicted since: read it all
            best, best_at, start = None, -1, first
        # newest first, so a later arrival wins a tie with an earlier one ("newest")
        for j, s in enumerate(islice(reversed(buf), appended - start)):
            if best is None or s[1] > best[1] or (best_at < start and s[1] == best[1]):
                best, best_at = s, appended - 1 - j
        self._memo = (best, best_at, appended, buf[-1][2])

    def latest_now(self, as_of: int) -> tuple[bool, RawSample | None]:
        """`latest` (``as_of``) from any thread: ``(True, sample)``, or ``(False, None)`` when
        only the stream's event loop can tell (a sample available after ``as_of``).

        It reads the best sample `extend` keeps, replaced whole: never the cache itself.
        The first ask of a stream is ``(False, None)``: from then on `extend` keeps it.
        """
        best, _, scanned, newest = self._memo
        if not self._watched:
            self._watched = True  # a flag only ever set: any thread may set it
            return False, None
        if newest > as_of or scanned != self.evicted + len(self._buf):
            # a sample available later, or arriving now (read half-way): the loop decides
            return False, None
        return True, best

    def samples(self, as_of: int | None = None) -> list[RawSample]:
        """All cached samples in arrival order, only those available by ``as_of`` if given."""
        if as_of is None:
            return list(self._buf)
        return [s for s in self._buf if s[2] <= as_of]

    def _believed(self, as_of: int | None) -> Iterable[RawSample]:
        """Samples visible at ``as_of``, newest arrival first."""
        if as_of is None:
            return reversed(self._buf)
        return (s for s in reversed(self._buf) if s[2] <= as_of)

    def latest(self, as_of: int | None = None) -> RawSample | None:
        """The sample with the greatest valid time (newest estimate on ties) seen by ``as_of``."""
        buf = self._buf
        if not buf:
            return None
        if as_of is None or buf[-1][2] <= as_of:  # all of it: only what is new is read
            self._update()
            return self._memo[0]
        best = None
        for s in self._believed(as_of):
            if best is None or s[1] > best[1]:
                best = s
        return best

    def between(self, t1: int, t2: int, as_of: int | None = None) -> list[RawSample]:
        """Samples with valid time in [t1, t2] seen by ``as_of``: current estimates, tv order.

        Where several estimates share a valid time, the newest one (by ``as_of``) is kept.
        """
        best: dict[int, RawSample] = {}
        for s in self._believed(as_of):
            tv = s[1]
            if t1 <= tv <= t2 and tv not in best:
                best[tv] = s
        return [best[t] for t in sorted(best)]

    def history(self, t1: int, t2: int, as_of: int | None = None) -> list[RawSample]:
        """Every sample (superseded estimates too) with valid time in [t1, t2], arrival order."""
        return [s for s in self._buf if t1 <= s[1] <= t2 and (as_of is None or s[2] <= as_of)]

    def at(
        self, t: int, approximation: Approximation, as_of: int | None = None
    ) -> RawSample | None:
        """The value at valid time ``t`` through a fluent generator; None if it has no answer.

        The answer's valid time is ``t``; its available time is that of the newest sample
        it was computed from.
        """
        before: RawSample | None = None
        after: RawSample | None = None
        seen: set[int] = set()
        for s in self._believed(as_of):
            tv = s[1]
            if tv in seen:
                continue  # an older estimate of a valid time already answered
            seen.add(tv)
            if tv == t:
                return s
            if tv < t:
                if before is None or tv > before[1]:
                    before = s
            elif after is None or tv < after[1]:
                after = s
        return _approximate(t, before, after, approximation)


def _approximate(
    t: int, b: RawSample | None, a: RawSample | None, how: Approximation
) -> RawSample | None:
    """Fill valid time ``t`` from the samples around it, per ``how``."""
    if how is Approximation.NONE:
        return None
    if how is Approximation.MOST_RECENT:
        return None if b is None else Sample(b[0], t, b[2])
    if how is Approximation.CLOSEST:
        if b is None and a is None:
            return None
        if a is None or (b is not None and t - b[1] <= a[1] - t):
            assert b is not None
            return Sample(b[0], t, b[2])
        return Sample(a[0], t, a[2])
    if b is None or a is None:
        return None
    value: Any = b[0] + (a[0] - b[0]) * ((t - b[1]) / (a[1] - b[1]))
    return Sample(value, t, max(b[2], a[2]))
