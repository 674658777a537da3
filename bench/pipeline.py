"""Source → policy (bounds + any-change) → CU (map) → subscriber, against reactivex and a loop.

All three run in the same process on the same pre-generated data, interleaved, best of
``REPEAT`` runs each (the best run is the one least disturbed by the noisy machine; the
median is printed too). They must produce the same output values, or the figures mean
nothing, so that is checked before anything is reported.

- ours: a DyKnow instance on a manual clock; a source pushes batches of 1000 samples
  ⟨value, valid time, available time⟩; a CU reads it with
  ``Policy(lower, upper, change="any_change")`` and maps each value; a subscriber gets the
  CU's output through a callback. Each stage carries the times and caches its stream.
- reactivex: ``from_iterable(values) | filter(bounds) | distinct_until_changed() | map``,
  the subscriber appends: plain values, what a reactivex user would write.
- loop: the same tests written by hand over the same samples, keeping the times: the
  floor of what pure Python can do here.
"""

from __future__ import annotations

import asyncio
import gc
import random
import statistics
from collections.abc import Callable
from typing import Any, TypeVar

import reactivex as rx
from reactivex import Observable
from reactivex import operators as ops

from bench import fmt, progress, report, timed
from dyknow_core import (
    DyKnowInstance,
    Input,
    ManualClock,
    Policy,
    RawSample,
    Sample,
    Source,
    Subscription,
)

N = 1_000_000
BATCH = 1000
REPEAT = 3
LOWER, UPPER = 0.0, 100.0
PERIOD_NS = 1_000_000  # 1 kHz valid time
DELAY_NS = 400_000  # available 0.4 ms after valid

_In = TypeVar("_In")
_Out = TypeVar("_Out")
# A reactivex operator. Its functions (filter, map...) are generic in the element type and
# are called before pipe() sees the source, so mypy cannot bind that type from the source:
# each operator is annotated with this instead.
Operator = Callable[[Observable[_In]], Observable[_Out]]


def scale(v: float) -> float:
    """The CU's map: a unit conversion, cheap so the pipeline's own cost dominates."""
    return v * 2.5 + 1.0


def make_data(n: int = N, seed: int = 7) -> list[float]:
    """Values that repeat in runs (so any-change matters) and stray outside the bounds."""
    rng = random.Random(seed)
    values: list[float] = []
    v = 50.0
    for _ in range(n):
        # ~60% of samples repeat the previous value; ~15% of new values are out of bounds
        if rng.random() < 0.4:
            v = float(rng.randint(-20, 120))
        values.append(v)
    return values


def make_batches(values: list[float]) -> list[list[Sample]]:
    """The samples ours and the loop consume, cut into push batches."""
    samples = [Sample(v, i * PERIOD_NS, i * PERIOD_NS + DELAY_NS) for i, v in enumerate(values)]
    return [samples[i : i + BATCH] for i in range(0, len(samples), BATCH)]


def build_ours(
    callback: Callable[[list[RawSample]], None] | None = None,
) -> tuple[DyKnowInstance, Source, Subscription]:
    """A fresh instance with the chain wired; returns (instance, source, subscription)."""
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("bench/raw")
    policy = Policy(lower=LOWER, upper=UPPER, change="any_change")
    dk.add_cu("scale", scale, [Input("bench/raw", policy)], "bench/scaled")
    # the default buffer would overflow (drop oldest) if nobody drained it; the callback
    # form never buffers, and the async run drains after every push
    sub = dk.subscribe("bench/scaled", Policy(buffer_size=4 * BATCH), callback=callback)
    return dk, src, sub


def run_ours(batches: list[list[Sample]]) -> list[RawSample]:
    """Push every batch through the chain; the subscriber callback collects what arrives."""
    got: list[RawSample] = []
    _, src, _ = build_ours(got.extend)
    push = src.push_batch
    for b in batches:
        push(b)
    return got


def run_ours_async(batches: list[list[Sample]]) -> list[RawSample]:
    """The same chain, the subscriber an asyncio task draining ``sub.batches()``."""

    async def main() -> list[RawSample]:
        got: list[RawSample] = []
        _, src, sub = build_ours()

        async def consume() -> None:
            async for batch in sub.batches():
                got.extend(batch)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(consume())
            for b in batches:
                src.push_batch(b)
                await asyncio.sleep(0)  # let the consumer drain, as a live producer would
            sub.close()
        return got

    return asyncio.run(main())


def run_reactivex(values: list[float]) -> list[float]:
    """Filter bounds → distinct_until_changed → map on plain values; the subscriber appends."""
    got: list[float] = []
    in_bounds: Operator[float, float] = ops.filter(lambda v: LOWER <= v <= UPPER)
    changed: Operator[float, float] = ops.distinct_until_changed()
    mapped: Operator[float, float] = ops.map(scale)
    rx.from_iterable(values).pipe(in_bounds, changed, mapped).subscribe(got.append)
    return got


def run_reactivex_samples(batches: list[list[Sample]]) -> list[Sample]:
    """The reactivex chain carrying the times too, as ours does (for the detail line)."""
    got: list[Sample] = []
    in_bounds: Operator[Sample, Sample] = ops.filter(lambda s: LOWER <= s[0] <= UPPER)
    changed: Operator[Sample, Sample] = ops.distinct_until_changed(lambda s: s[0])
    mapped: Operator[Sample, Sample] = ops.map(lambda s: Sample(scale(s[0]), s[1], s[2]))
    rx.from_iterable(s for b in batches for s in b).pipe(in_bounds, changed, mapped).subscribe(
        got.append
    )
    return got


def run_loop(batches: list[list[Sample]]) -> list[tuple[float, int, int]]:
    """The chain written by hand: bounds, any-change, map, keeping each sample's times."""
    got: list[tuple[float, int, int]] = []
    append = got.append
    last: Any = None
    for batch in batches:
        for s in batch:
            v = s[0]
            if v < LOWER or v > UPPER or v == last:
                continue
            last = v
            append((scale(v), s[1], s[2]))  # a plain tuple: what a hand-writer would use
    return got


def run() -> None:
    """Measure the four chains, check they agree, print samples/s and the BENCH lines."""
    progress(f"generating {N:,} samples")
    values = make_data()
    batches = make_batches(values)

    contenders: dict[str, Callable[[], list[Any]]] = {
        "ours": lambda: run_ours(batches),
        "reactivex": lambda: run_reactivex(values),
        "loop": lambda: run_loop(batches),
        "ours-async": lambda: run_ours_async(batches),
        "reactivex-samples": lambda: run_reactivex_samples(batches),
    }
    times: dict[str, list[float]] = {name: [] for name in contenders}
    outputs: dict[str, list[float]] = {}
    for rep in range(REPEAT):
        # interleaved, so a slow spell of the machine hits every contender alike
        for name, fn in contenders.items():
            gc.collect()
            seconds, got = timed(fn)
            times[name].append(seconds)
            progress(f"run {rep + 1}/{REPEAT} {name}: {seconds:.2f} s")
            if rep == 0:
                outputs[name] = [x[0] if isinstance(x, tuple) else x for x in got]
            del got

    expected = outputs["loop"]
    for name, out in outputs.items():
        if out != expected:
            i = next(
                (i for i, (a, b) in enumerate(zip(out, expected, strict=False)) if a != b), None
            )
            where = (
                "" if i is None else f"; first difference at #{i}: {out[i]!r} != {expected[i]!r}"
            )
            raise AssertionError(
                f"{name} produced {len(out)} values, the loop {len(expected)}{where}; "
                "they must agree before any figure means anything"
            )
    print(
        f"{N:,} samples in, {len(expected):,} out (bounds [{LOWER}, {UPPER}] + any-change); "
        f"all {len(outputs)} chains produced the same {len(expected):,} values"
    )
    rate = {name: N / min(ts) for name, ts in times.items()}
    print(f"samples/s, best of {REPEAT} interleaved runs (median in brackets):")
    for name, ts in times.items():
        print(f"  {name:<18} {fmt(rate[name]):>8}  ({fmt(N / statistics.median(ts))})")
    report("pipeline", rate["ours"], "reactivex", rate["reactivex"], "samples/s", better="higher")
    report("pipeline-vs-loop", rate["ours"], "loop", rate["loop"], "samples/s", better="higher")
    print(
        f"detail: ours-async/reactivex={rate['ours-async'] / rate['reactivex']:.2f} "
        f"ours/reactivex-samples={rate['ours'] / rate['reactivex-samples']:.2f}"
    )
