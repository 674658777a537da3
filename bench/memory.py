"""Peak memory of a stream cached as "the last 10 s" while 1 M samples go through it.

A 1 kHz stream pushed for 1000 s of valid time through a source whose cache is
``CacheSpec(max_samples=None, max_age=10)``, with one subscriber, against the least
any program could hold for the same question: the last 10 s of samples in a
``deque(maxlen=10_000)`` fed the same batches. Both are measured with tracemalloc (Python
allocations only, so the figure does not depend on what the interpreter had mapped
before) from just before the first push; the in-flight batch counts for both.
Memory is printed at a few points of the run: it must level off once 10 s are cached.
"""

from __future__ import annotations

import gc
import math
import resource
import tracemalloc
from collections import deque
from collections.abc import Callable, Iterator

from bench import progress, report
from dyknow_core import CacheSpec, DyKnowInstance, ManualClock, Policy, RawSample, Sample

N = 1_000_000
BATCH = 1000
PERIOD_NS = 1_000_000  # 1 kHz valid and available time
DELAY_NS = 2_000_000  # available 2 ms after valid
MAX_AGE_S = 10.0
CHECKPOINTS = (10_000, 100_000, 250_000, 500_000, 1_000_000)
MB = 1024 * 1024


def batches(n: int = N) -> Iterator[list[Sample]]:
    """The stream, made batch by batch so the input itself is never all in memory."""
    for start in range(0, n, BATCH):
        yield [
            Sample(20.0 + 5.0 * math.sin(i / 500.0), i * PERIOD_NS, i * PERIOD_NS + DELAY_NS)
            for i in range(start, min(start + BATCH, n))
        ]


def measure(
    push: Callable[[list[Sample]], None], size: Callable[[], int], name: str
) -> tuple[float, list[tuple[int, float, int]]]:
    """Push every batch; return the peak MB above baseline and (pushed, MB, held) checkpoints."""
    gc.collect()
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    points: list[tuple[int, float, int]] = []
    pushed = 0
    for batch in batches():
        push(batch)
        pushed += len(batch)
        if pushed in CHECKPOINTS:
            current = (tracemalloc.get_traced_memory()[0] - base) / MB
            points.append((pushed, current, size()))
            progress(f"{name}: {pushed:,} pushed, {current:.2f} MB, {size():,} held")
    peak = (tracemalloc.get_traced_memory()[1] - base) / MB
    tracemalloc.stop()
    return peak, points


def run() -> None:
    """Measure ours and the deque reference, print the checkpoints and the BENCH line."""
    clock = ManualClock()
    dk = DyKnowInstance(clock=clock)
    src = dk.add_source("bench/speed", cache=CacheSpec(max_samples=None, max_age=MAX_AGE_S))
    received = 0

    def count(batch: list[RawSample]) -> None:
        nonlocal received
        received += len(batch)

    dk.subscribe("bench/speed", Policy(), callback=count)

    def push_ours(batch: list[Sample]) -> None:
        clock.set(batch[-1][2])  # the platform's now follows the data, as it would live
        src.push_batch(batch)

    def cached() -> int:
        return int(dk.metrics("bench/speed")["cached"])

    ours, ours_points = measure(push_ours, cached, "ours")
    if received != N:
        raise AssertionError(f"the subscriber got {received:,} samples of {N:,}")

    window: deque[Sample] = deque(maxlen=round(MAX_AGE_S * 1e9 / PERIOD_NS))
    ref, ref_points = measure(window.extend, lambda: len(window), "deque")

    print(
        f"{N:,} samples at 1 kHz through a stream cached as the last {MAX_AGE_S:g} s "
        f"(tracemalloc, MB above the baseline before the first push):"
    )
    print(f"  {'pushed':>10}  {'ours MB':>8}  {'cached':>7}  {'deque MB':>8}  {'held':>7}")
    for (n, mb, held), (_, ref_mb, ref_held) in zip(ours_points, ref_points, strict=True):
        print(f"  {n:>10,}  {mb:>8.2f}  {held:>7,}  {ref_mb:>8.2f}  {ref_held:>7,}")
    # bounded: what is held once the window is full must not grow with what went through
    settled, final = ours_points[1][1], ours_points[-1][1]
    bounded = final <= 1.25 * settled + 0.5
    per_sample = ref_points[-1][1] * MB / max(ref_points[-1][2], 1)
    print(
        f"  peak ours {ours:.2f} MB, deque {ref:.2f} MB; keeping all {N:,} samples would take "
        f"~{per_sample * N / MB:.0f} MB; process max RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"
    )
    print(f"  bounded: {'yes' if bounded else 'NO'} ({settled:.2f} MB at 100k, {final:.2f} at 1M)")
    report("cache-memory", ours, "deque-10s", ref, "MB", better="lower")
    if not bounded:
        raise AssertionError("the 10 s cache kept growing with the stream: it is not bounded")
