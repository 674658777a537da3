"""The DyKnow instance: sources, computational units, subscriptions, metrics, the ticker, lifecycle.

Every wait is bounded: a sample is awaited with ``sub.get(timeout=WAIT)``, an event with
``asyncio.timeout(WAIT)``; nothing sleeps for time to pass.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from collections.abc import AsyncIterator
from typing import Any

import pytest

import dyknow_core
from dyknow_core import (
    NS_PER_S,
    ClosedError,
    ComputationalUnit,
    DuplicateLabelError,
    DyKnowInstance,
    Input,
    ManualClock,
    Policy,
    ProcessError,
    ProcessFailure,
    Sample,
    Source,
    Subscription,
    seconds_to_ns,
)
from dyknow_core._process import error_text

S = NS_PER_S
MS = NS_PER_S // 1000
WAIT = 2.0  # seconds: the bound on every wait for something that should happen
BASE = 1000 * S  # where the manual clock starts (a multiple of every period used here)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(BASE)


@pytest.fixture
async def dk(clock: ManualClock) -> AsyncIterator[DyKnowInstance]:
    async with DyKnowInstance(clock=clock) as instance:
        yield instance


async def take(sub: Subscription, n: int) -> list[Sample]:
    return [await sub.get(timeout=WAIT) for _ in range(n)]


async def drain(sub: Subscription) -> list[Sample]:
    """Everything until the subscription ends (bounded)."""
    async with asyncio.timeout(WAIT):
        return [s async for s in sub]


def failure_event(dk: DyKnowInstance) -> tuple[asyncio.Event, list[ProcessFailure]]:
    seen: list[ProcessFailure] = []
    event = asyncio.Event()

    def listener(f: ProcessFailure) -> None:
        seen.append(f)
        event.set()

    dk.on_failure(listener)
    return event, seen


async def settle() -> None:
    """Let every ready task of the instance run until it waits: yields only, no time passes."""
    for _ in range(20):
        await asyncio.sleep(0)


class Feed:
    """An async iterator the test feeds by hand (a sensor driver)."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[Any] = asyncio.Queue()

    def __aiter__(self) -> Feed:
        return self

    async def __anext__(self) -> Any:
        item = await self.queue.get()
        if isinstance(item, BaseException):
            raise item
        return item


# -- sources -----------------------------------------------------------------------------------


async def test_push_defaults_to_now_and_reaches_the_subscriber(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    src = dk.add_source("uav/altitude")
    assert isinstance(src, Source)
    sub = dk.subscribe("uav/altitude")
    src.push(120.0)
    clock.advance(S)
    src.push(121.0, valid_time=BASE + S // 2)
    assert await take(sub, 2) == [
        Sample(120.0, BASE, BASE),
        Sample(121.0, BASE + S // 2, BASE + S),
    ]


async def test_available_times_are_unique_per_stream(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x")
    for v in range(3):
        src.push(v)  # the clock does not move: same "now" each time
    got = await take(sub, 3)
    tas = [s.available_time for s in got]
    assert len(set(tas)) == 3 and tas == sorted(tas)
    assert [s.valid_time for s in got] == [BASE] * 3


async def test_publishing_never_waits_for_a_consumer(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(buffer_size=10))
    for i in range(1000):  # nobody reads: push still returns at once
        src.push(i, valid_time=i)
    assert sub.stats()["buffered"] == 10


async def test_each_subscriber_gets_its_own_policy(dk: DyKnowInstance) -> None:
    src = dk.add_source("speed")
    everything = dk.subscribe("speed")
    changes = dk.subscribe("speed", Policy(change="any_change"))
    fast = dk.subscribe("speed", Policy(lower=30))
    for i, v in enumerate([10, 10, 40, 40, 20]):
        src.push(v, valid_time=BASE + i)
    assert [s.value for s in await take(everything, 5)] == [10, 10, 40, 40, 20]
    assert [s.value for s in await take(changes, 3)] == [10, 40, 20]
    assert [s.value for s in await take(fast, 2)] == [40, 40]


async def test_source_from_an_async_iterator(dk: DyKnowInstance) -> None:
    async def camera() -> AsyncIterator[Any]:
        yield "plain"  # valid and available now
        yield ("pair", BASE - S)  # (value, valid time)
        yield Sample("sample", BASE - 2 * S, BASE + 5)  # as given

    dk.add_source("camera", iterator=camera())
    sub = dk.subscribe("camera")
    got = await take(sub, 3)
    assert got[0] == Sample("plain", BASE, BASE)
    assert (got[1].value, got[1].valid_time) == ("pair", BASE - S)
    assert got[2] == Sample("sample", BASE - 2 * S, BASE + 5)


async def test_source_iterator_given_before_entering_starts_on_enter(clock: ManualClock) -> None:
    async def three() -> AsyncIterator[int]:
        for i in range(3):
            yield i

    dk = DyKnowInstance(clock=clock)
    dk.add_source("x", iterator=three())
    sub = dk.subscribe("x")
    async with dk:
        assert [s.value for s in await take(sub, 3)] == [0, 1, 2]


async def test_failing_source_iterator_is_reported_and_others_keep_running(
    dk: DyKnowInstance,
) -> None:
    event, seen = failure_event(dk)
    feed = Feed()
    broken = dk.add_source("lidar", iterator=feed)
    healthy = dk.add_source("gps")
    lidar = dk.subscribe("lidar")
    gps = dk.subscribe("gps")
    feed.queue.put_nowait(1.0)
    assert (await lidar.get(timeout=WAIT)).value == 1.0
    feed.queue.put_nowait(OSError("lidar unplugged"))
    async with asyncio.timeout(WAIT):
        await event.wait()
    assert broken.errors == 1
    assert seen[0].process == broken.name
    assert "lidar unplugged" in seen[0].error
    assert dk.failures[-1] == seen[0]
    assert dk.failure_count == 1
    healthy.push(2.0)
    assert (await gps.get(timeout=WAIT)).value == 2.0


# -- computational units -----------------------------------------------------------------------


async def test_sync_cu_with_one_input(dk: DyKnowInstance) -> None:
    src = dk.add_source("pixels")
    cu = dk.add_cu("colocate", lambda v: v * 2, ["pixels"], "world")
    assert isinstance(cu, ComputationalUnit)
    out = dk.subscribe("world")
    src.push(1, valid_time=BASE - 3 * S)
    src.push(5, valid_time=BASE - 2 * S)
    got = await take(out, 2)
    assert [(s.value, s.valid_time) for s in got] == [(2, BASE - 3 * S), (10, BASE - 2 * S)]
    assert all(s.available_time >= BASE for s in got)
    assert got[0].available_time < got[1].available_time


async def test_cu_returning_none_emits_nothing(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    dk.add_cu("evens", lambda v: v if v % 2 == 0 else None, ["x"], "y")
    out = dk.subscribe("y")
    src.push_batch([(i, BASE + i, BASE + i) for i in range(6)])
    assert [s.value for s in await take(out, 3)] == [0, 2, 4]
    assert out.stats()["buffered"] == 0


async def test_async_cu(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")

    async def lookup(v: int) -> str:
        await asyncio.sleep(0)  # yields to the loop, as a database lookup would
        return f"segment-{v}"

    cu = dk.add_cu("road_segment", lookup, ["x"], "y")
    assert cu.is_async
    out = dk.subscribe("y")
    src.push(7, valid_time=BASE - S)
    src.push(8, valid_time=BASE)
    got = await take(out, 2)
    assert [(s.value, s.valid_time) for s in got] == [("segment-7", BASE - S), ("segment-8", BASE)]


async def test_cu_with_several_inputs_each_with_its_own_policy(dk: DyKnowInstance) -> None:
    a = dk.add_source("a")
    b = dk.add_source("b")
    dk.add_cu(
        "fuse",
        lambda x, y: x + y,
        [Input("a", Policy(change="any_change")), ("b", Policy(lower=0))],
        "a+b",
    )
    out = dk.subscribe("a+b")
    a.push(1, valid_time=BASE + 1)  # b has no value yet: nothing
    b.push(-5, valid_time=BASE + 2)  # below b's lower bound: not seen by the CU
    b.push(10, valid_time=BASE + 3)  # 1 + 10
    a.push(1, valid_time=BASE + 4)  # not a change for a's policy: not seen
    a.push(2, valid_time=BASE + 5)  # 2 + 10
    got = await take(out, 2)
    # the output takes the valid time of the sample that triggered it
    assert [(s.value, s.valid_time) for s in got] == [(11, BASE + 3), (12, BASE + 5)]
    assert out.stats()["buffered"] == 0


async def test_async_cu_with_several_inputs(dk: DyKnowInstance) -> None:
    a = dk.add_source("a")
    b = dk.add_source("b")

    async def fuse(x: float, y: float) -> float:
        return (x + y) / 2

    dk.add_cu("fuse", fuse, ["a", "b"], "fused")
    out = dk.subscribe("fused")
    a.push(10.0, valid_time=BASE + 1)
    b.push(20.0, valid_time=BASE + 2)
    a.push(30.0, valid_time=BASE + 3)
    got = await take(out, 2)
    assert [(s.value, s.valid_time) for s in got] == [(15.0, BASE + 2), (25.0, BASE + 3)]


async def test_cu_can_be_given_samples(dk: DyKnowInstance) -> None:
    a = dk.add_source("a")
    b = dk.add_source("b")
    # with pass_samples the function sees each input's latest Sample, times included
    dk.add_cu(
        "age",
        lambda x, y: abs(x.valid_time - y.valid_time),
        ["a", "b"],
        "age",
        pass_samples=True,
    )
    out = dk.subscribe("age")
    a.push("p", valid_time=BASE)
    b.push("q", valid_time=BASE + 3 * S)  # a sync unit runs in the publisher's call
    assert list(dk.failures) == []
    assert (await out.get(timeout=WAIT)).value == 3 * S


async def test_one_input_cu_reads_through_its_policy(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    dk.add_cu("scale", lambda v: v * 10, [("x", Policy(change="any_change", lower=0))], "y")
    out = dk.subscribe("y")
    for i, v in enumerate([1, 1, -1, 1, 2]):
        src.push(v, valid_time=BASE + i)
    # the policy applies to the input values: the second 1 and the -1 never reach the unit
    got = await take(out, 2)
    assert [(s.value, s.valid_time - BASE) for s in got] == [(10, 0), (20, 4)]
    assert out.stats()["buffered"] == 0


async def test_cu_gets_approximated_input_when_its_source_goes_silent(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    src = dk.add_source("x")
    dk.add_cu("echo", lambda v: f"saw {v}", [("x", Policy(**LATE_APPROX))], "y")  # type: ignore[arg-type]
    out = dk.subscribe("y")
    src.push("a", valid_time=BASE, available_time=BASE)
    assert (await out.get(timeout=WAIT)).value == "saw a"
    clock.set(BASE + seconds_to_ns(1.6))
    s = await out.get(timeout=WAIT)
    assert (s.value, s.valid_time) == ("saw a", BASE + S)


async def test_cu_reading_a_periodic_input(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    dk.add_cu(
        "sampled",
        lambda v: v,
        [("x", Policy(sample_period=1.0, approximation="most_recent"))],
        "y",
    )
    out = dk.subscribe("y")
    for v, t in [(1, 0.2), (2, 1.4), (3, 3.1)]:
        src.push(v, valid_time=BASE + seconds_to_ns(t))
    got = await take(out, 3)
    assert [(s.value, s.valid_time - BASE) for s in got] == [(1, S), (2, 2 * S), (2, 3 * S)]


@pytest.mark.parametrize("is_async", [False, True], ids=["sync", "async"])
async def test_a_failing_cu_is_isolated_and_reported(dk: DyKnowInstance, is_async: bool) -> None:
    event, seen = failure_event(dk)
    src = dk.add_source("x")

    def inverse(v: float) -> float:
        return 1 / v

    async def async_inverse(v: float) -> float:
        return 1 / v

    bad = dk.add_cu("inverse", async_inverse if is_async else inverse, ["x"], "inv")
    good = dk.add_cu("double", lambda v: 2 * v, ["x"], "dbl")
    inv = dk.subscribe("inv")
    dbl = dk.subscribe("dbl")
    for v in [1.0, 0.0, 4.0]:
        src.push(v)
    # the failing unit keeps going with the next sample, and so does everything else
    assert [s.value for s in await take(inv, 2)] == [1.0, 0.25]
    assert [s.value for s in await take(dbl, 3)] == [2.0, 0.0, 8.0]
    async with asyncio.timeout(WAIT):
        await event.wait()
    assert bad.errors == 1 and good.errors == 0
    assert bad.describe()["errors"] == 1
    assert "ZeroDivisionError" in (bad.last_error or "")
    assert len(seen) == 1
    assert seen[0].process == "inverse"
    assert "ZeroDivisionError" in seen[0].error
    assert seen[0].time == dk.clock.now()
    assert list(dk.failures) == seen
    assert bad.running and "inverse" in dk.processes


async def test_a_failures_text_is_kept_bounded_whatever_the_input_it_quotes(
    dk: DyKnowInstance,
) -> None:
    # a unit's error often quotes the value it could not take: a huge one, failing on every
    # sample, would otherwise hold max_failures copies of it
    event, seen = failure_event(dk)
    src = dk.add_source("x")

    def parse(v: str) -> float:
        return float(v)

    cu = dk.add_cu("parse", parse, ["x"], "y")
    huge = "w" * 1_000_000
    src.push(huge)
    async with asyncio.timeout(WAIT):
        await event.wait()
    text = seen[0].error
    assert len(text) == 1000 and text.endswith("…"), len(text)
    assert text.startswith("ValueError: could not convert string to float: 'www")
    assert cu.last_error == text and cu.errors == 1
    # a short one is kept whole
    assert error_text(ValueError("x" * 988)) == "ValueError: " + "x" * 988


async def test_process_names_and_labels_are_unique(dk: DyKnowInstance) -> None:
    dk.add_source("x")
    with pytest.raises(DuplicateLabelError):
        dk.add_source("x", name="another")
    dk.add_cu("cu", abs, ["x"], "y")
    with pytest.raises(ProcessError):
        dk.add_cu("cu", abs, ["x"], "z")
    with pytest.raises(DuplicateLabelError):
        dk.add_cu("cu2", abs, ["x"], "y")
    with pytest.raises(ProcessError):
        dk.add_cu("cu3", abs, [], "w")
    assert set(dk.processes) == {"source:x", "cu"}


# -- adding and removing at run time -----------------------------------------------------------


async def test_processes_added_while_running(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    src.push(1)

    async def plus_one(v: int) -> int:
        return v + 1

    dk.add_cu("later", plus_one, ["x"], "y")
    dk.add_cu("later-sync", lambda v: -v, ["y"], "z")
    out = dk.subscribe("z")
    src.push(5)
    assert (await out.get(timeout=WAIT)).value == -6


async def test_label_listeners_hear_streams_come_and_go(dk: DyKnowInstance) -> None:
    heard: list[tuple[str, bool]] = []
    stop = dk.on_label_change(lambda label, published: heard.append((label, published)))

    def broken(label: str, published: bool) -> None:
        raise RuntimeError("listener bug")

    dk.on_label_change(broken)
    dk.add_source("x").push(1)  # a failing listener is reported, never in the way
    dk.remove_process("source:x")
    assert heard == [("x", True), ("x", False)]
    assert [f.process for f in dk.failures] == ["label listener[x]", "label listener[x]"]
    stop()
    dk.add_source("y")
    assert heard == [("x", True), ("x", False)]


async def test_removing_a_source_ends_its_subscribers(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x")
    src.push(1)
    src.push(2)
    dk.remove_process(src.name)
    # what was buffered is still delivered, then the iterator ends
    assert [s.value for s in await drain(sub)] == [1, 2]
    assert not dk.has_label("x")
    assert src.name not in dk.processes
    with pytest.raises(ClosedError):
        src.push(3)
    with pytest.raises(ClosedError):
        await sub.get(timeout=WAIT)


async def test_removing_a_source_fed_by_an_iterator_stops_it(dk: DyKnowInstance) -> None:
    event, _ = failure_event(dk)
    feed = Feed()
    src = dk.add_source("x", iterator=feed)
    sub = dk.subscribe("x")
    feed.queue.put_nowait(1)
    assert (await sub.get(timeout=WAIT)).value == 1
    dk.remove_process(src.name)
    assert [s async for s in sub] == []
    replacement = dk.add_source("x")  # the label is free again
    fresh = dk.subscribe("x")
    feed.queue.put_nowait(2)  # the old driver produces once more
    await settle()
    # it neither fails on the closed stream nor leaks into the new one
    assert not event.is_set()
    assert src.errors == 0 and replacement.errors == 0
    assert fresh.stats()["buffered"] == 0


async def test_removing_a_cu_ends_its_output_and_leaves_the_rest_running(
    dk: DyKnowInstance,
) -> None:
    src = dk.add_source("x")
    dk.add_cu("gone", lambda v: v + 1, ["x"], "y")

    async def kept(v: int) -> int:
        return v * 10

    dk.add_cu("kept", kept, ["x"], "z")
    y = dk.subscribe("y")
    z = dk.subscribe("z")
    inputs_before = len(dk.stream("x").subscriptions)
    src.push(1)
    dk.remove_process("gone")
    assert [s.value for s in await drain(y)] == [2]
    assert len(dk.stream("x").subscriptions) == inputs_before - 1
    assert not dk.has_label("y")
    src.push(2)
    assert [s.value for s in await take(z, 2)] == [10, 20]
    with pytest.raises(ProcessError):
        dk.remove_process("gone")


async def test_removing_an_async_cu_stops_it(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    calls: list[int] = []

    async def record(v: int) -> int:
        calls.append(v)
        return v

    dk.add_cu("rec", record, ["x"], "y")
    y = dk.subscribe("y")
    src.push(1)
    assert (await y.get(timeout=WAIT)).value == 1
    dk.remove_process("rec")
    assert [s async for s in y] == []
    src.push(2)
    await settle()
    assert calls == [1]


# -- history, window, buffers ------------------------------------------------------------------


async def test_history_replay_when_start_is_in_the_past(dk: DyKnowInstance) -> None:
    src = dk.add_source("car5/state")
    for i in range(10):
        src.push(i, valid_time=BASE - (10 - i) * S)  # the last ten seconds
    sub = dk.subscribe("car5/state", Policy(start=BASE - 3 * S))
    src.push(10, valid_time=BASE)
    assert [s.value for s in await take(sub, 4)] == [7, 8, 9, 10]


async def test_history_window_in_the_past_replays_and_ends(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    for i in range(10):
        src.push(i, valid_time=BASE - (10 - i) * S)
    sub = dk.subscribe("x", Policy(start=BASE - 8 * S, end=BASE - 6 * S))
    src.push(99, valid_time=BASE)
    assert [s.value for s in await drain(sub)] == [2, 3, 4]


async def test_subscription_ends_after_its_window(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(end=BASE + 2 * S))
    for i in range(4):
        src.push(i, valid_time=BASE + i * S)
    assert [s.value for s in await drain(sub)] == [0, 1, 2]
    assert sub.closed
    assert dk.stream("x").subscriptions == []


async def test_closing_a_subscription(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    with dk.subscribe("x") as sub:
        src.push(1)
    src.push(2)
    assert [s.value for s in await drain(sub)] == [1]
    assert dk.stream("x").subscriptions == []


async def test_overflow_drop_oldest_keeps_the_newest_and_counts(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(buffer_size=4, overflow="drop_oldest"))
    src.push_batch([(i, BASE + i, BASE + i) for i in range(3)])
    src.push_batch([(i, BASE + i, BASE + i) for i in range(3, 6)])
    src.push_batch([(i, BASE + i, BASE + i) for i in range(6, 16)])
    assert sub.overflowed == 12
    assert [s.value for s in await take(sub, 4)] == [12, 13, 14, 15]
    assert sub.stats()["overflowed"] == 12
    assert sub.dropped == 12
    assert dk.metrics("x")["dropped"] == 12


async def test_overflow_drop_newest_keeps_the_oldest_and_counts(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(buffer_size=4, overflow="drop_newest"))
    src.push_batch([(i, BASE + i, BASE + i) for i in range(3)])
    src.push_batch([(i, BASE + i, BASE + i) for i in range(3, 6)])
    assert sub.overflowed == 2
    assert [s.value for s in await take(sub, 4)] == [0, 1, 2, 3]
    src.push(6)
    assert [s.value for s in await take(sub, 1)] == [6]
    assert dk.metrics("x")["dropped"] == 2


async def test_overflow_of_one_subscriber_does_not_touch_another(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    small = dk.subscribe("x", Policy(buffer_size=1))
    large = dk.subscribe("x")
    src.push_batch([(i, BASE + i, BASE + i) for i in range(5)])
    assert [s.value for s in await take(large, 5)] == [0, 1, 2, 3, 4]
    assert large.overflowed == 0 and small.overflowed == 4


async def test_a_small_buffer_never_changes_which_samples_the_policy_emits(
    dk: DyKnowInstance,
) -> None:
    """The buffer decides only what is lost when it is full; the policy's output is the same
    for every subscriber with that policy, whatever its buffer."""
    src = dk.add_source("x")
    policy = Policy(sample_period=0.5, approximation="none", change="any_change", lower=2, upper=15)
    got: list[tuple[Any, int, int]] = []
    dk.subscribe("x", policy, callback=got.extend)
    small = dk.subscribe("x", policy.replace(buffer_size=2, overflow="drop_newest"))
    for v, tv, ta in [(5.0, 0, 339145), (4.5, 44436733, 166113133), (4.5, 1879286806, 2073381743)]:
        src.push(v, valid_time=tv, available_time=ta)
    assert got == [(5.0, 0, 339145), (4.5, 500_000_000, 2073381743)]
    assert [tuple(s) for s in await take(small, 2)] == got
    assert small.overflowed == 0 and small.stats()["dropped_skipped"] == 0
    # a third emitted sample does not fit in two places: lost, and counted
    tiny = dk.subscribe("x", Policy(buffer_size=2, overflow="drop_newest"))
    src.push_batch([(float(i), BASE + i * S, BASE + i * S) for i in range(5)])
    assert tiny.overflowed == 3 and [s.value for s in await take(tiny, 2)] == [0.0, 1.0]


async def test_end_is_one_behaviour_for_a_batch_and_for_single_pushes(dk: DyKnowInstance) -> None:
    samples = [(1.0, 5, 1), (2.0, 11, 2), (3.0, 9, 3)]
    batched, single = dk.add_source("batched"), dk.add_source("single")
    subs = [dk.subscribe(label, Policy(end=10)) for label in ("batched", "single")]
    batched.push_batch(samples)
    for v, tv, ta in samples:
        single.push(v, valid_time=tv, available_time=ta)
    for sub in subs:
        assert [tuple(s) for s in await drain(sub)] == [(1.0, 5, 1)]
        assert sub.stats()["dropped_window"] == 1
    # a late subscriber replaying the cache from a past start: the same
    late = dk.subscribe("batched", Policy(start=0, end=10))
    assert [tuple(s) for s in await drain(late)] == [(1.0, 5, 1)]


# -- metrics -----------------------------------------------------------------------------------


async def test_stream_metrics(dk: DyKnowInstance, clock: ManualClock) -> None:
    src = dk.add_source("x")
    dk.subscribe("x", Policy(lower=0))
    dk.subscribe("x")
    for i in range(100):
        delay = S if i % 10 == 9 else MS  # 90 samples 1 ms late, 10 samples 1 s late
        src.push(i - 50, valid_time=BASE + i * 2 * S, available_time=BASE + i * 2 * S + delay)
    m = dk.metrics("x")
    assert m["samples_in"] == 100
    assert m["subscribers"] == 2
    assert m["samples_out"] == 50 + 100
    assert m["dropped"] == 50
    assert MS / S <= m["delay_p50"] <= 2 * MS / S
    assert 1.0 <= m["delay_p99"] <= 2.0
    assert dk.metrics()["x"] == m


async def test_metrics_of_a_silent_stream(dk: DyKnowInstance) -> None:
    dk.add_source("x")
    m = dk.metrics("x")
    assert m["samples_in"] == 0 and m["samples_out"] == 0 and m["dropped"] == 0
    assert m["delay_p50"] is None and m["delay_p99"] is None


async def test_predictions_are_counted(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    src.push(1, valid_time=BASE + 5 * S, available_time=BASE)
    src.push(2, valid_time=BASE, available_time=BASE + 1)
    assert dk.metrics("x")["predictions"] == 1


async def test_samples_out_counts_what_subscribers_received(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(buffer_size=2, overflow="drop_newest"))
    src.push_batch([(i, BASE + i, BASE + i) for i in range(5)])
    got = await take(sub, 2)
    m = dk.metrics("x")
    # each sample either reached the subscriber or is counted as dropped, never both
    assert m["samples_out"] == len(got) == 2
    assert m["dropped"] == 3
    assert m["samples_out"] + m["dropped"] == m["samples_in"]


async def test_stream_counters_do_not_go_back_when_a_subscriber_leaves(
    dk: DyKnowInstance,
) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(change="any_change"))
    for v in [1, 1, 2]:
        src.push(v)
    before = dk.metrics("x")
    assert before["samples_out"] == 2 and before["dropped"] == 1
    sub.close()
    after = dk.metrics("x")
    assert after["subscribers"] == 0
    assert after["samples_out"] >= before["samples_out"]
    assert after["dropped"] >= before["dropped"]


# -- periodic subscriptions and the ticker -----------------------------------------------------

LATE_APPROX = {
    "sample_period": 1.0,
    "approximation": "closest",
    "max_delay": 0.5,
    "late": "approximate",
}


async def test_ticker_approximates_once_the_deadline_passes(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    src = dk.add_source("x")
    src.push("a", valid_time=BASE)
    sub = dk.subscribe("x", Policy(start=BASE, **LATE_APPROX))  # type: ignore[arg-type]
    assert await sub.get(timeout=WAIT) == Sample("a", BASE, BASE)
    clock.set(BASE + seconds_to_ns(1.6))  # the grid point at 1 s is 0.5 s late now
    assert await sub.get(timeout=WAIT) == Sample("a", BASE + S, BASE + seconds_to_ns(1.5))
    clock.set(BASE + seconds_to_ns(3.6))
    got = await take(sub, 2)
    assert [s.valid_time - BASE for s in got] == [2 * S, 3 * S]
    assert all(s.available_time - s.valid_time <= seconds_to_ns(0.5) for s in got)
    assert sub.filter.stats.approximated == 3


async def test_ticker_approximates_a_live_stream_that_goes_silent(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(**LATE_APPROX))  # type: ignore[arg-type]
    await settle()  # the subscriber waits a little before the sensor's first sample
    src.push("a", valid_time=BASE, available_time=BASE)
    assert await sub.get(timeout=WAIT) == Sample("a", BASE, BASE)
    clock.set(BASE + seconds_to_ns(1.6))  # then the sensor goes silent
    assert await sub.get(timeout=WAIT) == Sample("a", BASE + S, BASE + seconds_to_ns(1.5))


async def test_ticker_serves_a_policy_replaced_with_a_periodic_one(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x")
    src.push("a", valid_time=BASE)
    assert (await sub.get(timeout=WAIT)).value == "a"
    # level-4 refinement: latency grew, so ask for one sample a second, approximated if late
    sub.replace_policy(Policy(**LATE_APPROX))  # type: ignore[arg-type]
    src.push("b", valid_time=BASE + S, available_time=BASE + S)
    assert await sub.get(timeout=WAIT) == Sample("b", BASE + S, BASE + S)
    clock.set(BASE + seconds_to_ns(2.6))
    assert await sub.get(timeout=WAIT) == Sample("b", BASE + 2 * S, BASE + seconds_to_ns(2.5))


async def test_replacing_the_policy_on_a_live_subscription(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    sub = dk.subscribe("x", Policy(order="monotone"))
    src.push(1, valid_time=BASE + 5)
    sub.replace_policy(Policy(order="strict", change="any_change"))
    assert sub.policy.order.value == "strict"
    src.push(2, valid_time=BASE + 4)  # older than what was emitted: order carries over
    src.push(1, valid_time=BASE + 6)  # equal to the last emitted value: change carries over
    src.push(3, valid_time=BASE + 7)
    assert [s.value for s in await take(sub, 2)] == [1, 3]
    sub.close()
    with pytest.raises(ClosedError):
        sub.replace_policy(Policy())


# -- lifecycle ---------------------------------------------------------------------------------


async def test_instance_cannot_be_reopened_after_close(clock: ManualClock) -> None:
    dk = DyKnowInstance(clock=clock)
    async with dk:
        src = dk.add_source("x")
        sub = dk.subscribe("x")
        src.push(1)
    # leaving ends every subscription (after what was buffered) and every stream
    assert [s.value for s in await drain(sub)] == [1]
    with pytest.raises(ClosedError):
        src.push(2)
    with pytest.raises(ClosedError):
        async with dk:
            pass


async def test_instance_cannot_be_entered_twice(dk: DyKnowInstance) -> None:
    with pytest.raises(ClosedError):
        await dk.__aenter__()


async def test_closing_ends_async_processes(clock: ManualClock) -> None:
    dk = DyKnowInstance(clock=clock)
    started = asyncio.Event()
    cancelled = asyncio.Event()

    async def slow(v: int) -> int:
        started.set()
        try:
            await asyncio.Event().wait()  # never returns on its own
        except asyncio.CancelledError:
            cancelled.set()
            raise
        return v

    async with asyncio.timeout(WAIT):
        async with dk:
            src = dk.add_source("x")
            dk.add_cu("slow", slow, ["x"], "y")
            src.push(1)
            await started.wait()
    assert cancelled.is_set()


async def test_closing_one_instance_leaves_another_running() -> None:
    # both use the default name
    first = DyKnowInstance(clock=ManualClock(BASE))
    second = DyKnowInstance(clock=ManualClock(BASE))

    async def double(v: int) -> int:
        return 2 * v

    async with second:
        src = second.add_source("x")
        second.add_cu("double", double, ["x"], "y")
        out = second.subscribe("y")
        async with first:
            first.add_source("x")
        src.push(21)
        assert (await out.get(timeout=WAIT)).value == 42


async def test_instance_facade_builds_states_and_change_events() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        speed = dk.add_source("speed")
        on_road = dk.add_source("on_road")
        state = dk.add_state(
            "car5/state",
            {"speed": "speed", "on_road": "on_road"},
            {"period": 1, "strategy": "latest", "max_delay": 0.5, "missing": "last"},
        )
        changes = dk.add_change_events("speed", "absolute(5)")
        states = dk.subscribe("car5/state")
        events = dk.subscribe(changes.label)
        for i, v in enumerate([0.0, 2.0, 10.0, 12.0]):
            clock.set(i * NS_PER_S + 10)
            speed.push(v, i * NS_PER_S)
            on_road.push(i % 2 == 0, i * NS_PER_S)
        first = await states.get(timeout=2)
        assert first.value == {"speed": 0.0, "on_road": True} and first.valid_time == 0
        got = [(await events.get(timeout=2)).value for _ in range(2)]
        assert [(e.old, e.new) for e in got] == [(None, 0.0), (0.0, 10.0)]
        assert state.name in dk.processes
        dk.remove_process(state.name)
        assert not dk.has_label("car5/state")


def test_importing_the_core_loads_no_reasoning_and_no_kpl() -> None:
    # a fresh interpreter: this one has imported everything the other tests use
    code = (
        "import sys, dyknow_core; "
        "print(sorted(m for m in sys.modules if m.startswith(('dyknow_core.reasoning', "
        "'dyknow_core.kpl'))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]"
    assert not hasattr(dyknow_core, "add_monitor")
    assert not hasattr(DyKnowInstance, "add_monitor")


async def test_latest_many_now_tells_at_the_second_ask_of_many_labels(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    """Another thread's read of many labels (`latest_many_now`) cannot tell at their first
    ask; once each stream has had a sample since, it tells every label's latest, not only
    the first one's (a provider's get-latest of many streams in flow is answered on
    zenoh's thread from its second ask on, not from its tenth)."""
    sources = [dk.add_source(f"uav/s{j}") for j in range(4)]
    labels = [f"uav/s{j}" for j in range(4)]
    for j, src in enumerate(sources):
        src.push(float(j))
    assert dk.latest_many_now(labels) is None  # the first ask: the loop's to answer
    clock.advance(S)
    for j, src in enumerate(sources):
        src.push(10.0 + j)
    new = BASE + S
    assert dk.latest_many_now(labels) == (new, [(10.0 + j, new, new) for j in range(4)])
    assert dk.latest_many_now([*labels, "uav/none"]) is None  # a label not here


async def test_latest_many_now_watches_the_streams_asked_after_a_label_not_here(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    """A label not here makes the read None, but every stream asked with it is watched
    from then on, as docs/core.md says: the next ask of those streams alone tells."""
    src = dk.add_source("uav/s0")
    src.push(1.0)
    assert dk.latest_many_now(["uav/none", "uav/s0"]) is None
    clock.advance(S)
    src.push(2.0)
    new = BASE + S
    assert dk.latest_many_now(["uav/s0"]) == (new, [(2.0, new, new)])


async def test_latest_now_reads_one_label_as_latest_many_now_does(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    """A plain read on another thread (`latest_now`) tells what `latest_many_now` tells of
    that label: nothing for a label not here or asked the first time, then its latest."""
    src = dk.add_source("uav/altitude")
    assert dk.latest_now("uav/none") is None
    assert dk.latest_many_now(("uav/none",)) is None
    assert dk.latest_now("uav/altitude") is None  # the first ask: the loop's to answer
    assert dk.latest_now("uav/altitude") == (BASE, None)  # watched since: none yet
    src.push(120.0)
    clock.advance(S)
    src.push(121.0, valid_time=BASE - S)  # older in valid time: not the latest
    read = dk.latest_now("uav/altitude")
    assert read == (BASE + S, (120.0, BASE, BASE))
    many = dk.latest_many_now(("uav/altitude",))
    assert many is not None and read == (many[0], many[1][0])
    assert dk.latest("uav/altitude").samples == [Sample(120.0, BASE, BASE)]


async def test_periodic_subscription_with_end_and_max_delay_ends_on_the_clock() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        src = dk.add_source("x")
        sub = dk.subscribe(
            "x",
            Policy(sample_period=1.0, approximation="most_recent", max_delay=0.5, end=3 * S),
        )
        src.push(1.0, 0, 0)
        clock.set(10 * S)  # no more data: time alone passes `end`
        got = [s.valid_time async for s in sub]  # ends instead of waiting for ever
        assert got == [0, 1 * S, 2 * S, 3 * S]
        assert sub.closed and sub.deadline() is None


def test_replacing_a_periodic_policy_keeps_the_sample_waiting_for_the_next_grid_point() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")
    p = Policy(sample_period=1.0, approximation="most_recent")
    unchanged, replaced = dk.subscribe("x", p), dk.subscribe("x", p)
    src.push(0.0, 0, 0)
    src.push(5.0, S // 2, S // 2)  # the newest before grid point 1 s
    replaced.replace_policy(p)
    src.push(9.0, 3 * S // 2, 3 * S // 2)  # decides grid point 1 s
    assert [tuple(s[:2]) for s in replaced.buffer] == [(0.0, 0), (5.0, S)]
    assert list(replaced.buffer) == list(unchanged.buffer)


def test_a_failing_subscriber_does_not_starve_the_others() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")

    def broken(batch: list) -> None:  # type: ignore[type-arg]
        raise RuntimeError("subscriber bug")

    dk.subscribe("x", callback=broken)
    other = dk.subscribe("x")
    src.push(1.0)  # the producer is not told of a consumer's bug
    assert len(other.buffer) == 1
    assert dk.failure_count == 1 and "subscriber bug" in dk.failures[-1].error


def test_a_sentinel_valid_time_is_accepted_like_any_other() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")
    sub = dk.subscribe("x")
    src.push(1.0, -(2**63), 0)  # "no time" from another language: ta - tv >= 2**63
    assert len(sub.buffer) == 1 and len(dk.stream("x").cache) == 1
