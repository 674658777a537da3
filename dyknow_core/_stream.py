"""Stream generators (publish under a label) and subscriptions (each with its own policy)."""

from __future__ import annotations

import asyncio
import operator
from collections import deque
from collections.abc import AsyncIterator, Callable, Sequence
from itertools import islice
from numbers import Real
from typing import Any

from ._cache import Cache
from ._exceptions import ClosedError, PolicyError, ProcessError
from ._filter import Mapper, PolicyFilter
from ._policy import CacheSpec, Overflow, Policy
from ._sample import RawSample, Sample, as_sample

BatchCallback = Callable[[list[RawSample]], None]

_DELAY_BUCKETS = 64


class StreamMetrics:
    """Per-stream counters: samples in and out, dropped, and the delay distribution.

    The delay (available − valid time) goes into power-of-two nanosecond buckets: one
    ``int.bit_length`` per sample is all the hot path can afford, and it still answers
    "p99 is between 2 and 4 ms".
    """

    __slots__ = ("delay_buckets", "negative_delays", "samples_in")

    def __init__(self) -> None:
        self.samples_in = 0
        self.delay_buckets = [0] * _DELAY_BUCKETS
        self.negative_delays = 0  # predictions: available before valid

    def delay_quantile(self, q: float) -> float | None:
        """Upper bound (seconds) of the bucket holding quantile ``q`` of the delays."""
        total = sum(self.delay_buckets) + self.negative_delays
        if total == 0:
            return None
        rank = q * total
        acc = self.negative_delays
        if acc >= rank:
            return 0.0
        for i, n in enumerate(self.delay_buckets):
            acc += n
            if acc >= rank:
                return (1 << i) / 1e9
        return (1 << (_DELAY_BUCKETS - 1)) / 1e9


class Subscription:
    """One subscriber's view of a stream: its policy, a bounded buffer, and its counters.

    Iterate with ``async for sample in sub`` (or ``sub.batches()``), or give a callback
    that receives each emitted batch synchronously (how computational units are fed).
    The buffer never makes the publisher wait: when full, ``policy.overflow`` decides which
    sample is lost, and ``overflowed`` counts it.
    """

    def __init__(
        self,
        generator: StreamGenerator,
        policy: Policy,
        callback: BatchCallback | None = None,
        on_ticks: Callable[[Subscription], None] | None = None,
        mapper: Mapper | None = None,
    ) -> None:
        self.generator = generator
        self.label = generator.label
        self.policy = policy
        self.filter = PolicyFilter(policy, mapper=mapper)
        self.callback = callback
        self.buffer: deque[RawSample] = deque()
        self.overflowed = 0
        self.delivered = 0
        self.closed = False
        self._waiter: asyncio.Future[None] | None = None
        self._on_ticks = on_ticks  # tells the owner a periodic deadline may have moved
        self._armed = False

    # -- fed by the generator -------------------------------------------------
    def _deliver(self, batch: list[RawSample]) -> None:
        out = self.filter.process(batch)
        if out:
            if out is batch and self.callback is not None:
                # a policy that lets everything through hands back the publisher's list: a
                # callback gets its own, so what it does to it reaches no other subscriber
                out = batch.copy()
            self._emit(out)
        f = self.filter  # read again: a callback may have replaced the policy
        if f.ended:
            self.close()
        elif (
            not self._armed
            and self._on_ticks is not None
            # `PolicyFilter.deadline` is None without a sampler: no call per sample for it
            and f.sampler is not None
            and f.deadline() is not None
        ):
            # the first sample set the grid: the owner's timer must now watch its deadline
            self._armed = True
            self._on_ticks(self)

    def _emit(self, out: list[RawSample]) -> None:
        if self.callback is not None:
            self.delivered += len(out)
            self.callback(out)
            return
        buf = self.buffer
        size = self.policy.buffer_size
        room = size - len(buf)
        if len(out) > room:
            lost = len(out) - room
            self.overflowed += lost
            if self.policy.overflow is Overflow.DROP_NEWEST:
                out = out[:room]
            else:
                # the evicted ones were counted as delivered when they were buffered
                evicted = min(lost, len(buf))
                self.delivered -= evicted
                for _ in range(evicted):
                    buf.popleft()
                if len(out) > size:
                    out = out[len(out) - size :]
        self.delivered += len(out)
        buf.extend(out)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def tick(self, now: int) -> None:
        """Emit periodic grid points whose max delay passed by ``now``."""
        if self.closed:
            return
        out = self.filter.tick(now)
        if out:
            self._emit(out)
        if self.filter.ended:
            self.close()

    def deadline(self) -> int | None:
        """When this subscription next needs a tick (periodic policy with a max delay)."""
        return None if self.closed else self.filter.deadline()

    # -- control ---------------------------------------------------------------
    def replace_policy(self, policy: Policy) -> None:
        """Swap the policy on the live subscription; order and change carry over."""
        if self.closed:
            raise ClosedError(f"subscription to {self.label!r} is closed")
        self.generator._check_policy(policy)
        self.filter = PolicyFilter(policy, previous=self.filter)
        self.policy = policy
        self._armed = False
        if self._on_ticks is not None:
            self._on_ticks(self)

    def close(self) -> None:
        """Stop receiving; an iterator ends once it has drained what was buffered."""
        if self.closed:
            return
        self.closed = True
        self.generator._unsubscribe(self)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    @property
    def dropped(self) -> int:
        """Samples this subscriber did not get: held back by its policy or lost to overflow."""
        return self.filter.stats.dropped + self.overflowed

    def stats(self) -> dict[str, Any]:
        """A snapshot of this subscription's counters."""
        return {
            "label": self.label,
            "delivered": self.delivered,
            "overflowed": self.overflowed,
            "buffered": len(self.buffer),
            "approximated": self.filter.stats.approximated,
            **{
                f"dropped_{k}": v
                for k, v in self.filter.stats.as_dict().items()
                if k not in ("emitted", "approximated")
            },
        }

    # -- consuming ---------------------------------------------------------------
    async def _wait(self) -> None:
        loop = asyncio.get_running_loop()
        self._waiter = loop.create_future()
        try:
            await self._waiter
        finally:
            self._waiter = None

    def __aiter__(self) -> Subscription:
        return self

    async def __anext__(self) -> Sample:
        while not self.buffer:
            if self.closed:
                raise StopAsyncIteration
            await self._wait()
        return as_sample(self.buffer.popleft())

    async def batches(self) -> AsyncIterator[list[RawSample]]:
        """Yield everything buffered at once, waiting when empty; ends when closed.

        The bulk path: items are plain ``(value, valid_time, available_time)`` tuples
        (unpack them, or view one with ``Sample._make``), saving a Sample per item.
        """
        while True:
            while not self.buffer:
                if self.closed:
                    return
                await self._wait()
            batch = list(self.buffer)
            self.buffer.clear()
            yield batch

    async def get(self, timeout: float | None = None) -> Sample:
        """The next sample, or TimeoutError after ``timeout`` seconds, ClosedError at the end."""
        try:
            async with asyncio.timeout(timeout):
                return await self.__anext__()
        except StopAsyncIteration:
            raise ClosedError(f"subscription to {self.label!r} ended") from None

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class StreamGenerator:
    """The source of one labelled stream at a location: publishes, caches, fans out.

    Publishing never waits for subscribers: it filters each subscriber's share and
    appends it to that subscriber's buffer (or calls its callback) and returns.
    """

    def __init__(
        self, label: str, cache: CacheSpec, *, value_type: type | None = None, location: str = ""
    ) -> None:
        self.label = label
        self.location = location
        self.value_type = value_type
        self.cache = Cache(cache)
        self.metrics = StreamMetrics()
        self._subs: list[Subscription] = []
        self._last_ta = -(2**63)
        # The latest available time this location assigned itself (a 1 ns uniqueness bump,
        # a CU's output): it is known now even if the clock has not reached it.
        self.made_ta = -(2**63)
        self._publishing = False
        self.subscriber_errors = 0
        self.on_subscriber_error: Callable[[str, BaseException], None] | None = None
        self._closed_delivered = 0  # what subscriptions that have ended got and lost
        self._closed_dropped = 0
        self.closed = False

    @property
    def last_available_time(self) -> int:
        """The newest available time published on this stream (new samples must be later)."""
        return self._last_ta

    @property
    def subscriptions(self) -> list[Subscription]:
        """The live subscriptions to this stream."""
        return list(self._subs)

    def _check_policy(self, policy: Policy) -> None:
        field = policy.numeric_field()
        if field and self.value_type is not None and not issubclass(self.value_type, Real):
            raise PolicyError(
                field,
                f"needs numeric values, but stream {self.label!r} carries "
                f"{self.value_type.__name__}",
            )

    def publish_batch(self, batch: Sequence[RawSample], *, ordered: bool = False) -> None:
        """Make samples available: cache them and hand each subscriber its policy's share.

        ``ordered`` promises the available times are already unique and increasing past
        the last one published (computational units guarantee it), skipping the check.
        """
        if self.closed:
            raise ClosedError(f"stream {self.label!r} is closed")
        if not batch:
            return
        if type(batch) is not list:
            batch = list(batch)
        if self._publishing:
            # a CU whose output feeds back into its own input would recurse for ever
            raise ProcessError(f"cycle: stream {self.label!r} published while publishing")
        if ordered:
            self.made_ta = batch[-1][2]  # a computational unit stamped these itself
        elif len(batch) != 1 or batch[0][2] <= self._last_ta:
            # one sample later than the last (a source's push) is unique as it is
            batch = self._unique_available_times(batch)
        self._last_ta = batch[-1][2]
        self._record_delays(batch)
        self.cache.extend(batch)
        self._publishing = True
        try:
            for sub in self._subs:
                try:
                    sub._deliver(batch)
                except Exception as exc:
                    # one failing subscriber (a CU's callback) must not starve the others
                    # of a sample that is already accepted and cached
                    self.subscriber_errors += 1
                    if self.on_subscriber_error is not None:
                        self.on_subscriber_error(self.label, exc)
        finally:
            self._publishing = False

    def _unique_available_times(self, batch: list[RawSample]) -> list[RawSample]:
        """Available times at one location are unique per stream: bump repeats by 1 ns."""
        tas = [s[2] for s in batch]
        if tas[0] > self._last_ta and all(map(operator.lt, tas, islice(tas, 1, None))):
            return batch
        last = self._last_ta
        fixed: list[RawSample] = []
        for s in batch:
            ta = s[2]
            if ta <= last:
                ta = last + 1
                s = (s[0], s[1], ta)
                self.made_ta = ta
            fixed.append(s)
            last = ta
        return fixed

    def _record_delays(self, batch: list[RawSample]) -> None:
        # Large batches are sampled (every 16th): the distribution stays representative
        # and the hot path stays cheap.
        m = self.metrics
        m.samples_in += len(batch)
        view = batch if len(batch) <= 64 else batch[::16]
        weight = 1 if view is batch else 16
        buckets = m.delay_buckets
        for s in view:
            d = s[2] - s[1]
            if d < 0:
                m.negative_delays += weight
            else:
                # a sentinel valid time (e.g. -2**63 from another language) must not crash
                buckets[min(d.bit_length(), _DELAY_BUCKETS - 1)] += weight

    def publish(self, value: Any, valid_time: int, available_time: int) -> None:
        """Make one sample available (prefer ``publish_batch`` on hot paths)."""
        self.publish_batch([(value, valid_time, available_time)])

    def subscribe(
        self,
        policy: Policy,
        callback: BatchCallback | None = None,
        on_ticks: Callable[[Subscription], None] | None = None,
        mapper: Mapper | None = None,
    ) -> Subscription:
        """Add a subscriber; a ``start`` in the past replays history from the cache first.

        With a ``mapper`` (a fused single-input computational unit) the callback receives
        the mapped output samples instead of the input's.
        """
        if self.closed:
            raise ClosedError(f"stream {self.label!r} is closed")
        self._check_policy(policy)
        sub = Subscription(self, policy, callback, on_ticks, mapper)
        if policy.start is not None:
            cached = self.cache.samples()
            history = [s for s in cached if s[1] >= policy.start]
            if policy.sample_period is not None:
                # the grid point at start may be filled from the last sample before it
                before = [s for s in cached if s[1] < policy.start]
                if before:
                    history.insert(0, max(before, key=lambda s: (s[1], s[2])))
            if history:
                sub._deliver(history)
        if not sub.closed:
            self._subs.append(sub)
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        # copy-on-write: publish may be iterating the list
        if sub in self._subs:
            self._subs = [s for s in self._subs if s is not sub]
            self._closed_delivered += sub.delivered
            self._closed_dropped += sub.dropped

    def close(self) -> None:
        """End the stream: every subscription ends after draining its buffer."""
        self.closed = True
        for sub in list(self._subs):
            sub.close()

    def stats(self) -> dict[str, Any]:
        """Per-stream metrics: samples in/out, dropped, cache size, delay quantiles (s)."""
        m = self.metrics
        return {
            "label": self.label,
            "location": self.location,
            "samples_in": m.samples_in,
            "samples_out": self._closed_delivered + sum(s.delivered for s in self._subs),
            "dropped": self._closed_dropped + sum(s.dropped for s in self._subs),
            "subscribers": len(self._subs),
            "cached": len(self.cache),
            "delay_p50": m.delay_quantile(0.5),
            "delay_p99": m.delay_quantile(0.99),
            "predictions": m.negative_delays,
        }
