"""Fusion: an imported stream merged with a local one, preferring local samples.

The paper's car5 example: UAV B fuses the car states UAV A exports with its own, and
where both describe the same moment (within a window of valid time) B keeps its own.
"""

from __future__ import annotations

import asyncio
import heapq
from collections.abc import Callable
from typing import Any

from dyknow_core import (
    CacheSpec,
    DyKnowInstance,
    Policy,
    Process,
    RawSample,
    Sample,
    Subscription,
    seconds_to_ns,
    sleep_until_woken,
)

_EARLIEST = -(2**63)  # a subscription start before any valid time: the whole cache


class Fusion(Process):
    """Publishes ``output``: every local sample, and imported ones where no local one is near.

    A local sample is emitted at once. An imported sample with valid time t waits until
    the window has passed (the clock reaches t + window, or local data has moved past
    t + window) and is emitted only if no local sample lies within ``window`` of t;
    otherwise it is suppressed and counted. ``combine`` (optional) may instead merge a
    suppressed imported value into nothing or into a value of its own choosing:
    ``combine(local_value, imported_value) -> value | None`` is called with the nearest
    local sample, and a non-None result is emitted at the imported valid time.
    With ``replay``, the imported samples already in the stream's cache are fused too (at
    start, before the live ones): a fusion made once an import's first sample arrived
    (`FederationPlatform.fuse`) does not miss that sample.
    """

    kind = "fusion"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        local: str,
        imported: str,
        output: str,
        *,
        window: float,
        combine: Callable[[Any, Any], Any] | None = None,
        cache: CacheSpec | None = None,
        replay: bool = False,
    ) -> None:
        super().__init__(name, instance)
        self.local_label = local
        self.imported_label = imported
        self.window = seconds_to_ns(window)
        self.combine = combine
        self.replay = replay
        self.label = output
        self.output = instance.create_stream(output, cache=cache)
        self.local_emitted = 0
        self.imported_emitted = 0
        self.suppressed = 0
        self._pending: list[tuple[int, int, RawSample]] = []  # (due, seq, sample)
        self._seq = 0
        self._local_high = -(2**63)  # the newest local valid time seen
        self._wake = asyncio.Event()
        self._subs: list[Subscription] = []

    def _start(self) -> None:
        dk = self.instance
        self._subs = [
            dk.subscribe(self.local_label, Policy(), callback=self._on_local),
            # a past start replays what the cache holds, then the live samples follow
            dk.subscribe(
                self.imported_label,
                Policy(start=_EARLIEST) if self.replay else Policy(),
                callback=self._on_imported,
            ),
        ]
        dk.spawn(f"fusion[{self.name}].timer", self._timer())

    def _emit(self, batch: list[RawSample]) -> None:
        ta = max(self.instance.clock.now(), self.output.last_available_time + 1)
        self.output.publish_batch(
            [(v, tv, ta + i) for i, (v, tv, _) in enumerate(batch)], ordered=True
        )

    def _on_local(self, batch: list[RawSample]) -> None:
        try:
            self._emit(batch)
            self.local_emitted += len(batch)
            self._local_high = max(self._local_high, max(s[1] for s in batch))
            self._decide(self.instance.clock.now())
        except Exception as exc:
            self._fail(exc)

    def _on_imported(self, batch: list[RawSample]) -> None:
        for s in batch:
            self._seq += 1
            heapq.heappush(self._pending, (s[1] + self.window, self._seq, s))
        try:
            self._decide(self.instance.clock.now())
        except Exception as exc:
            self._fail(exc)
        self._wake.set()

    def _nearest_local(self, t: int) -> Sample | None:
        answer = self.instance.between(
            self.local_label, t - self.window, t + self.window, as_of=2**62
        )
        if not answer.samples:
            return None
        return min(answer.samples, key=lambda s: abs(s.valid_time - t))

    def _decide(self, now: int) -> None:
        """Emit or suppress every imported sample whose window has passed."""
        out: list[RawSample] = []
        while self._pending:
            due, _, s = self._pending[0]
            if due > now and due > self._local_high:
                break
            heapq.heappop(self._pending)
            near = self._nearest_local(s[1])
            if near is None:
                out.append(s)
                continue
            merged = self.combine(near.value, s[0]) if self.combine is not None else None
            if merged is None:
                self.suppressed += 1
            else:
                out.append((merged, s[1], s[2]))
        if out:
            self._emit(out)
            self.imported_emitted += len(out)

    async def _timer(self) -> None:
        """Decide when the first pending import's window has passed (or on new imports)."""
        clock = self.instance.clock
        wake = self._wake
        while self.running:
            wake.clear()
            # strictly after the due time, as the core's timers wait: the window includes it
            due = self._pending[0][0] + 1 if self._pending else None
            await sleep_until_woken(clock, due, wake)
            try:
                self._decide(clock.now())
            except Exception as exc:
                self._fail(exc)

    def _stop(self) -> None:
        super()._stop()
        for sub in self._subs:
            sub.close()
        self._wake.set()

    def describe(self) -> dict[str, Any]:
        """What it fuses and how much came from where."""
        d = super().describe()
        d.update(
            local=self.local_label,
            imported=self.imported_label,
            output=self.label,
            local_emitted=self.local_emitted,
            imported_emitted=self.imported_emitted,
            suppressed=self.suppressed,
        )
        return d


def add_fusion(
    instance: DyKnowInstance,
    local: str,
    imported: str,
    output: str,
    *,
    window: float = 0.5,
    combine: Callable[[Any, Any], Any] | None = None,
    name: str | None = None,
    cache: CacheSpec | None = None,
    replay: bool = False,
) -> Fusion:
    """Add a fusion process: ``output`` = ``local`` plus ``imported`` where local is silent.

    ``replay``: the imported samples already arrived are fused too (see `Fusion`).
    """
    instance.stream(local)  # unknown labels fail before anything is created
    instance.stream(imported)
    fusion = Fusion(
        name or f"fusion:{output}",
        instance,
        local,
        imported,
        output,
        window=window,
        combine=combine,
        cache=cache,
        replay=replay,
    )
    instance.add_process(fusion)
    fusion._start()
    return fusion
