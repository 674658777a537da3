"""A policy compiled into a per-subscription filter: every field, their combinations, and
hypothesis properties of the emitted stream (order, delay, change, grid, bounds, window)."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from itertools import pairwise
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dyknow_core import (
    NS_PER_S,
    CacheSpec,
    DyKnowInstance,
    ManualClock,
    Policy,
    PolicyFilter,
    Sample,
    seconds_to_ns,
)
from dyknow_core._filter import MAX_GRID_BURST
from dyknow_core._stream import StreamGenerator

S = NS_PER_S
MS = NS_PER_S // 1000
STEP = 100 * MS  # the time step of generated samples


def smp(value: Any, tv: float, ta: float | None = None) -> Sample:
    """A sample with times in seconds (available time defaults to the valid time)."""
    return Sample(value, seconds_to_ns(tv), seconds_to_ns(tv if ta is None else ta))


def run(policy: Policy, *batches: Sequence[Sample]) -> tuple[list[tuple[Any, int, int]], Any]:
    """Feed ``batches`` through a fresh filter for ``policy``; return what it emitted."""
    f = PolicyFilter(policy)
    out: list[tuple[Any, int, int]] = []
    for b in batches:
        if b:
            out.extend(tuple(s) for s in f.process(list(b)))
    return out, f


def values(out: Sequence[Sequence[Any]]) -> list[Any]:
    return [s[0] for s in out]


def valid_s(out: Sequence[Sequence[Any]]) -> list[float]:
    return [s[1] / S for s in out]


# -- each field on concrete samples ------------------------------------------------------------


def test_default_policy_passes_every_sample_unchanged() -> None:
    batch = [smp(3, 2.0, 2.5), smp(3, 1.0, 2.6), smp("x", 5.0, 2.7), smp(None, 0.0, 1.0)]
    out, f = run(Policy(), batch)
    assert out == [tuple(s) for s in batch]
    assert f.stats.dropped == 0
    assert f.stats.emitted == 4


def test_window_is_inclusive_on_valid_time() -> None:
    p = Policy(start=seconds_to_ns(1.0), end=seconds_to_ns(3.0))
    out, f = run(p, [smp(v, t) for v, t in [(0, 0.5), (1, 1.0), (2, 2.0), (3, 3.0), (4, 3.5)]])
    assert values(out) == [1, 2, 3]
    assert f.stats.window == 2


def test_window_end_ends_the_filter() -> None:
    p = Policy(end=seconds_to_ns(2.0))
    _, f = run(p, [smp(1, 1.0), smp(2, 2.0)])
    assert not f.ended
    f.process([smp(3, 2.5)])
    assert f.ended


def test_late_samples_are_dropped_and_on_time_ones_kept() -> None:
    p = Policy(max_delay=0.5)
    batch = [
        smp("on-time", 1.0, 1.2),
        smp("exactly-max", 2.0, 2.5),
        smp("late", 3.0, 3.5 + 1e-9),
        smp("prediction", 5.0, 4.0),
    ]
    out, f = run(p, batch)
    assert values(out) == ["on-time", "exactly-max", "prediction"]
    assert f.stats.late == 1


def test_monotone_order_keeps_equal_valid_times() -> None:
    out, f = run(
        Policy(order="monotone"), [smp(v, t) for v, t in [(1, 1), (2, 1), (3, 0.5), (4, 2)]]
    )
    assert values(out) == [1, 2, 4]
    assert f.stats.order == 1


def test_strict_order_drops_equal_valid_times() -> None:
    out, f = run(Policy(order="strict"), [smp(v, t) for v, t in [(1, 1), (2, 1), (3, 0.5), (4, 2)]])
    assert values(out) == [1, 4]
    assert f.stats.order == 2


def test_order_is_against_the_last_emitted_sample() -> None:
    # the sample at 5.0 is out of bounds: it is not emitted, so it does not raise the bar
    p = Policy(order="strict", upper=10)
    out, _ = run(p, [smp(1, 1.0), smp(99, 5.0), smp(2, 2.0)])
    assert values(out) == [1, 2]


def test_bounds_are_inclusive() -> None:
    p = Policy(lower=0.0, upper=10.0)
    out, f = run(p, [smp(v, i) for i, v in enumerate([-0.1, 0.0, 5, 10.0, 10.1])])
    assert values(out) == [0.0, 5, 10.0]
    assert f.stats.bounds == 2


def test_lower_bound_only_and_upper_bound_only() -> None:
    batch = [smp(v, i) for i, v in enumerate([-5, 0, 5])]
    assert values(run(Policy(lower=0), batch)[0]) == [0, 5]
    assert values(run(Policy(upper=0), batch)[0]) == [-5, 0]


def test_bounds_drop_values_that_cannot_be_compared() -> None:
    out, f = run(Policy(lower=0), [smp("text", 0), smp(1, 1)])
    assert values(out) == [1]
    assert f.stats.type == 1
    assert f.stats.dropped == 1


def test_any_change_drops_repeats_of_the_last_emitted_value() -> None:
    out, f = run(Policy(change="any_change"), [smp(v, i) for i, v in enumerate("aabbbaac")])
    assert values(out) == ["a", "b", "a", "c"]
    assert f.stats.change == 4


def test_absolute_change_is_measured_from_the_last_emitted_value() -> None:
    # a slow drift is caught once it adds up to more than delta
    out, _ = run(
        Policy(change="absolute(0.5)"),
        [smp(v, i) for i, v in enumerate([0, 0.4, 0.8, 1.2, 1.4, 0.2])],
    )
    assert values(out) == [0, 0.8, 1.4, 0.2]


def test_absolute_change_equal_to_delta_is_not_a_change() -> None:
    out, _ = run(Policy(change="absolute(1)"), [smp(v, i) for i, v in enumerate([0, 1, 2.5])])
    assert values(out) == [0, 2.5]


def test_relative_change() -> None:
    # 10 -> 10.5 is 5 %, 10 -> 11.5 is 15 %, 11.5 -> 10.4 is about 9.6 %
    out, _ = run(
        Policy(change="relative(0.1)"), [smp(v, i) for i, v in enumerate([10, 10.5, 11.5, 10.4, 5])]
    )
    assert values(out) == [10, 11.5, 5]


def test_relative_change_from_zero() -> None:
    out, _ = run(Policy(change="relative(0.1)"), [smp(v, i) for i, v in enumerate([0, 0, 1, 1.05])])
    assert values(out) == [0, 1]


def test_change_on_values_that_cannot_be_subtracted_is_dropped_and_counted() -> None:
    out, f = run(Policy(change="absolute(1)"), [smp(1, 0), smp("x", 1), smp(5, 2)])
    assert values(out) == [1, 5]
    assert f.stats.type == 1


@pytest.mark.parametrize(
    "policy",
    [Policy(), Policy(order="strict"), Policy(sample_period=1.0, approximation="linear")],
    ids=["identity", "strict", "periodic"],
)
def test_an_empty_batch_emits_nothing(policy: Policy) -> None:
    f = PolicyFilter(policy)
    assert list(f.process([])) == []
    assert f.stats.emitted == 0


def test_the_filter_keeps_its_state_across_batches() -> None:
    p = Policy(order="strict", change="any_change")
    out, _ = run(p, [smp(1, 1), smp(2, 2)], [smp(2, 3), smp(9, 1.5), smp(3, 4)])
    assert values(out) == [1, 2, 3]


# -- combinations ------------------------------------------------------------------------------


def test_bounds_then_any_change() -> None:
    # the out-of-bounds 99 is never emitted, so the next 1 repeats the last emitted value
    out, _ = run(
        Policy(lower=0, upper=10, change="any_change"),
        [smp(v, i) for i, v in enumerate([1, 99, 1, 2])],
    )
    assert values(out) == [1, 2]


def test_late_samples_do_not_count_as_emitted_for_change_or_order() -> None:
    p = Policy(max_delay=1.0, order="monotone", change="any_change")
    batch = [smp(1, 1.0), smp(2, 5.0, 9.0), smp(1, 2.0), smp(3, 3.0)]
    out, f = run(p, batch)
    assert values(out) == [1, 3]
    assert f.stats.late == 1 and f.stats.change == 1


def test_window_order_bounds_change_together() -> None:
    p = Policy(
        start=seconds_to_ns(1.0),
        end=seconds_to_ns(9.0),
        order="strict",
        lower=0,
        upper=100,
        change="absolute(5)",
    )
    batch = [
        smp(50, 0.5),  # before the window
        smp(50, 1.0),  # first
        smp(52, 2.0),  # change too small
        smp(200, 3.0),  # out of bounds
        smp(60, 4.0),  # emitted
        smp(70, 3.5),  # out of order
        smp(10, 9.5),  # after the window
    ]
    out, f = run(p, batch)
    assert [(v, t) for v, t in zip(values(out), valid_s(out), strict=True)] == [
        (50, 1.0),
        (60, 4.0),
    ]
    assert f.stats.as_dict() | {"emitted": 0} == {
        "window": 2,
        "late": 0,
        "order": 1,
        "bounds": 1,
        "change": 1,
        "type": 0,
        "approximated": 0,
        "skipped": 0,
        "emitted": 0,
    }
    assert f.stats.emitted == 2


# -- periodic sampling -------------------------------------------------------------------------


def test_exact_grid_samples_pass_unchanged() -> None:
    batch = [smp(v, t, t + 0.01) for v, t in [(1, 0.0), (2, 0.5), (3, 1.0)]]
    out, _ = run(Policy(sample_period=0.5), batch)
    assert out == [tuple(s) for s in batch]


def test_periodic_most_recent() -> None:
    p = Policy(sample_period=0.5, approximation="most_recent")
    out, _ = run(p, [smp("a", 0.1), smp("b", 0.7), smp("c", 1.6), smp("d", 2.2)])
    assert list(zip(valid_s(out), values(out), strict=True)) == [
        (0.5, "a"),
        (1.0, "b"),
        (1.5, "b"),
        (2.0, "c"),
    ]


def test_periodic_closest() -> None:
    p = Policy(sample_period=0.5, approximation="closest")
    out, _ = run(p, [smp("a", 0.1), smp("b", 0.7), smp("c", 1.1), smp("d", 1.45)])
    # 0.5: b (0.2 away) beats a (0.4); 1.0: c (0.1) beats b (0.3); 1.5: d (0.05)
    assert list(zip(valid_s(out), values(out), strict=True)) == [(0.5, "b"), (1.0, "c")]
    out, _ = run(p, [smp("a", 0.4), smp("b", 0.9)])
    assert list(zip(valid_s(out), values(out), strict=True)) == [(0.5, "a")]


def test_periodic_linear() -> None:
    p = Policy(sample_period=0.25, approximation="linear")
    out, _ = run(p, [smp(0.0, 0.0), smp(10.0, 1.0)])
    assert valid_s(out) == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert values(out) == pytest.approx([0.0, 2.5, 5.0, 7.5, 10.0])


def test_periodic_without_approximation_skips_empty_periods() -> None:
    p = Policy(sample_period=0.5)
    out, _ = run(p, [smp("a", 0.1), smp("b", 0.7), smp("c", 1.6), smp("d", 2.0)])
    # nothing was measured in (1.0, 1.5]: no value at 1.5
    assert 1.5 not in valid_s(out)
    assert valid_s(out)[-1] == 2.0 and values(out)[-1] == "d"
    assert set(values(out)) <= {"a", "b", "c", "d"}


def test_periodic_grid_is_anchored_at_time_zero() -> None:
    p = Policy(sample_period=1.0, approximation="most_recent")
    out, _ = run(p, [smp(v, t) for v, t in [(1, 10.3), (2, 11.7), (3, 13.2)]])
    assert valid_s(out) == [11.0, 12.0, 13.0]
    assert values(out) == [1, 2, 2]


def test_periodic_output_available_time_is_when_it_could_be_computed() -> None:
    p = Policy(sample_period=1.0, approximation="linear")
    out, _ = run(p, [smp(0.0, 0.0, 0.1), smp(2.0, 2.0, 2.3)])
    # the value at 1.0 needs the sample available at 2.3
    assert out[1] == (1.0, S, seconds_to_ns(2.3))


def test_periodic_late_approximate_fills_a_grid_point_once_max_delay_passed() -> None:
    p = Policy(sample_period=1.0, approximation="closest", max_delay=0.5, late="approximate")
    out, f = run(p, [smp("a", 0.0)])
    assert values(out) == ["a"]
    assert f.deadline() == seconds_to_ns(1.5)
    assert f.tick(seconds_to_ns(1.4)) == []
    ticked = [tuple(s) for s in f.tick(seconds_to_ns(1.6))]
    assert ticked == [("a", S, seconds_to_ns(1.5))]
    assert f.stats.approximated == 1
    assert f.deadline() == seconds_to_ns(2.5)


def test_periodic_late_drop_leaves_a_late_grid_point_out() -> None:
    p = Policy(sample_period=1.0, approximation="closest", max_delay=0.5)
    _, f = run(p, [smp("a", 0.0)])
    assert f.tick(seconds_to_ns(1.6)) == []
    # b arrives on time for itself, but too late for the grid point at 1.0
    out2 = [tuple(s) for s in f.process([smp("b", 1.9, 2.0)])]
    assert 1.0 not in valid_s(out2)
    out3 = [tuple(s) for s in f.process([smp("c", 2.0, 2.1)])]
    assert values(out3) == ["c"]


def test_periodic_late_input_samples_are_dropped() -> None:
    p = Policy(sample_period=1.0, approximation="most_recent", max_delay=0.5)
    out, f = run(p, [smp("a", 0.0), smp("late", 0.5, 1.2), smp("b", 1.0, 1.3)])
    assert values(out) == ["a", "b"]
    assert f.stats.late == 1


def test_periodic_with_any_change() -> None:
    p = Policy(sample_period=1.0, approximation="most_recent", change="any_change")
    out, _ = run(p, [smp(v, t) for v, t in [(1, 0.0), (1, 1.5), (2, 2.5), (2, 3.5), (2, 4.5)]])
    assert list(zip(valid_s(out), values(out), strict=True)) == [(0.0, 1), (3.0, 2)]


def test_periodic_with_bounds_filters_the_input() -> None:
    p = Policy(sample_period=1.0, approximation="most_recent", upper=10)
    out, _ = run(p, [smp(v, t) for v, t in [(1, 0.0), (50, 0.5), (2, 1.5), (3, 2.5)]])
    assert values(out) == [1, 1, 2]


def test_periodic_window_keeps_the_grid_point_at_its_end() -> None:
    """The grid points in [start, end] are 1, 2 and 3 s; all three have a most recent value."""
    p = Policy(sample_period=1.0, approximation="most_recent", end=seconds_to_ns(3.0))
    out, f = run(p, [smp(i, i + 0.5) for i in range(6)])
    assert list(zip(valid_s(out), values(out), strict=True)) == [(1.0, 0), (2.0, 1), (3.0, 2)]
    assert f.ended


def test_periodic_window_keeps_the_grid_point_at_its_start() -> None:
    p = Policy(sample_period=1.0, approximation="most_recent", start=seconds_to_ns(1.0))
    out, _ = run(p, [smp(i, i + 0.5) for i in range(3)])
    assert list(zip(valid_s(out), values(out), strict=True)) == [(1.0, 0), (2.0, 1)]


def test_order_applies_to_the_inputs_before_the_grid() -> None:
    """A second sample at the same valid time is out of strict order: it never reaches the
    grid, so it cannot become the most recent value of the grid points after it."""
    p = Policy(
        sample_period=0.1,
        approximation="most_recent",
        max_delay=0.3,
        order="strict",
        change="absolute(2.5)",
    )
    f = PolicyFilter(p)
    out = [tuple(s) for s in f.process([Sample(9.0, 0, 291666), Sample(16.0, 0, 78870027)])]
    out += [tuple(s) for s in f.tick(seconds_to_ns(3.18))]
    assert out == [(9.0, 0, 291666)]
    assert f.stats.order == 1
    # monotone keeps the equal valid time: 16.0 is the most recent value from 0.1 s on
    f = PolicyFilter(p.replace(order="monotone"))
    out = [tuple(s) for s in f.process([Sample(9.0, 0, 291666), Sample(16.0, 0, 78870027)])]
    out += [tuple(s) for s in f.tick(seconds_to_ns(3.18))]
    assert out == [(9.0, 0, 291666), (16.0, seconds_to_ns(0.1), seconds_to_ns(0.4))]


def test_order_before_the_grid_compares_with_the_last_admitted_input() -> None:
    """An input the bounds refuse, or a late one, does not move the order forward."""
    p = Policy(sample_period=1.0, approximation="most_recent", order="strict", upper=10)
    out, f = run(p, [smp(1, 0.0), smp(50, 2.5), smp(2, 1.5), smp(3, 1.2), smp(4, 3.0)])
    # 50 is out of bounds (2.5 s is not admitted), so 2 at 1.5 s is in order; 3 at 1.2 s is not
    assert list(zip(valid_s(out), values(out), strict=True)) == [
        (0.0, 1),
        (1.0, 1),
        (2.0, 2),
        (3.0, 4),
    ]
    assert f.stats.order == 1 and f.stats.bounds == 1


def test_end_within_one_batch_ends_the_stream_as_single_pushes_do() -> None:
    p = Policy(end=10)
    samples = [(1.0, 5, 1), (2.0, 11, 2), (3.0, 9, 3)]
    out, f = run(p, samples)
    assert out == [(1.0, 5, 1)]
    assert f.ended and f.stats.window == 1
    out, f = run(p, *[[s] for s in samples])
    assert out == [(1.0, 5, 1)]
    assert f.stats.window == 1


def test_a_past_start_replays_history_and_ends_at_the_first_sample_past_end() -> None:
    gen = StreamGenerator("x", CacheSpec())
    gen.publish_batch([(1.0, 5, 1), (2.0, 11, 2), (3.0, 9, 3)])
    got: list[tuple[Any, int, int]] = []
    sub = gen.subscribe(Policy(start=0, end=10), callback=got.extend)
    assert got == [(1.0, 5, 1)]
    assert sub.closed and gen.subscriptions == []


def test_a_long_gap_is_decided_in_one_bounded_burst_the_same_for_every_buffer() -> None:
    """A gap of more grid points than MAX_GRID_BURST yields the last MAX_GRID_BURST of them;
    the earlier ones are counted as skipped. The buffer plays no part in it."""
    period = 0.001
    gap = MAX_GRID_BURST + 10
    p = Policy(sample_period=period, approximation="most_recent")
    out, f = run(p, [smp("a", 0.0)], [smp("b", (gap + 1) * period)])
    assert len(out) == 1 + MAX_GRID_BURST + 1
    assert f.stats.skipped == gap - MAX_GRID_BURST
    assert out[1][1] == seconds_to_ns((gap - MAX_GRID_BURST + 1) * period)
    assert out[-1][:2] == ("b", seconds_to_ns((gap + 1) * period))
    # `none` has a value at one grid point of a gap at most: nothing to skip, however long
    out, f = run(Policy(sample_period=period), [smp("a", 0.0005)], [smp("b", 10_000.0)])
    assert [(v, t / S) for v, t, _ in out] == [("a", 0.001), ("b", 10_000.0)]
    assert f.stats.skipped == 0


# -- replacing the policy of a live filter -----------------------------------------------------


def test_replaced_policy_keeps_order() -> None:
    f = PolicyFilter(Policy(order="strict"))
    f.process([smp(1, 5.0)])
    g = PolicyFilter(Policy(order="monotone", change="any_change"), previous=f)
    out = [tuple(s) for s in g.process([smp(2, 4.0), smp(3, 5.0), smp(4, 6.0)])]
    assert values(out) == [3, 4]


def test_replaced_policy_keeps_change_state_and_counters() -> None:
    f = PolicyFilter(Policy(change="any_change"))
    f.process([smp("a", 1.0), smp("a", 2.0)])
    g = PolicyFilter(Policy(change="any_change", order="monotone"), previous=f)
    out = [tuple(s) for s in g.process([smp("a", 3.0), smp("b", 4.0)])]
    assert values(out) == ["b"]
    assert g.stats.change == 2 and g.stats.emitted == 2


def test_replacing_with_a_periodic_policy_continues_after_the_last_emitted_sample() -> None:
    f = PolicyFilter(Policy())
    f.process([smp(1, 0.0), smp(2, 2.2)])
    g = PolicyFilter(Policy(sample_period=1.0, approximation="most_recent"), previous=f)
    out = [tuple(s) for s in g.process([smp(3, 3.1), smp(4, 4.5)])]
    # the grid goes on after 2.2 s; the most recent value at 3.0 s is the 2 emitted at 2.2 s
    assert list(zip(valid_s(out), values(out), strict=True)) == [(3.0, 2), (4.0, 3)]


# -- properties --------------------------------------------------------------------------------

PERIODS = [0.1, 0.25, 0.5, 1.0]


@st.composite
def arrivals(draw: st.DrawFn, max_size: int = 40, span: int = 60) -> list[Sample]:
    """Samples in arrival order: small int values, valid times on a 0.1 s step, any delay
    (predictions included), unique increasing available times as a location guarantees."""
    raw = draw(
        st.lists(
            st.tuples(st.integers(-5, 5), st.integers(0, span), st.integers(-3, 15)),
            max_size=max_size,
        )
    )
    items = sorted(
        ((v, k * STEP, k * STEP + d * STEP + j) for j, (v, k, d) in enumerate(raw)),
        key=lambda s: s[2],
    )
    out: list[Sample] = []
    last = -(2**62)
    for v, tv, ta in items:
        ta = max(ta, last + 1)
        out.append(Sample(v, tv, ta))
        last = ta
    return out


@st.composite
def splits(draw: st.DrawFn, samples: list[Sample]) -> list[list[Sample]]:
    """Cut the samples into consecutive batches of random sizes."""
    cuts = sorted(draw(st.sets(st.integers(1, max(1, len(samples) - 1)), max_size=5)))
    bounds = [0, *[c for c in cuts if c < len(samples)], len(samples)]
    return [samples[a:b] for a, b in pairwise(bounds) if b > a]


change_texts = st.sampled_from(
    [
        "any_update",
        "any_change",
        "absolute(0)",
        "absolute(1)",
        "absolute(2.5)",
        "relative(0.2)",
        "relative(1)",
    ]
)


@st.composite
def policies(draw: st.DrawFn, periodic: bool | None = None) -> Policy:
    fields: dict[str, Any] = {}
    if draw(st.booleans()):
        a, b = sorted(draw(st.lists(st.integers(0, 60), min_size=2, max_size=2)))
        if draw(st.booleans()):
            fields["start"] = a * STEP
        if draw(st.booleans()):
            fields["end"] = b * STEP
    if draw(st.booleans()):
        fields["max_delay"] = draw(st.sampled_from([0.0, 0.1, 0.3, 0.5, 1.0]))
    fields["order"] = draw(st.sampled_from(["any", "monotone", "strict"]))
    fields["change"] = draw(change_texts)
    if draw(st.booleans()):
        lo, hi = sorted(draw(st.lists(st.integers(-5, 5), min_size=2, max_size=2)))
        if draw(st.booleans()):
            fields["lower"] = lo
        if draw(st.booleans()):
            fields["upper"] = hi
    if periodic is None:
        periodic = draw(st.booleans())
    if periodic:
        fields["sample_period"] = draw(st.sampled_from(PERIODS))
        fields["approximation"] = draw(
            st.sampled_from(["none", "most_recent", "closest", "linear"])
        )
        if fields["approximation"] != "none" and "max_delay" in fields and draw(st.booleans()):
            fields["late"] = "approximate"
    return Policy(**fields)


def drive(
    f: PolicyFilter, batches: list[list[Sample]], tick_after: list[int]
) -> list[tuple[Any, int, int]]:
    """Feed the batches; after each, tick the filter at the newest available time plus an offset
    (how the instance's ticker would move periodic streams along)."""
    out: list[tuple[Any, int, int]] = []
    for i, b in enumerate(batches):
        out.extend(tuple(s) for s in f.process(b))
        if i < len(tick_after) and tick_after[i] >= 0:
            out.extend(tuple(s) for s in f.tick(b[-1][2] + tick_after[i] * STEP))
    return out


def reference(policy: Policy, samples: list[Sample]) -> list[tuple[Any, int, int]]:
    """What a non-periodic policy means, sample by sample, written plainly."""
    out: list[tuple[Any, int, int]] = []
    last_tv: int | None = None
    last_v: Any = None
    maxd = None if policy.max_delay is None else seconds_to_ns(policy.max_delay)
    for v, tv, ta in samples:
        if policy.start is not None and tv < policy.start:
            continue
        if policy.end is not None and tv > policy.end:
            break  # the first sample past `end` ends the stream
        if maxd is not None and ta - tv > maxd:
            continue
        if last_tv is not None and policy.order.value == "monotone" and tv < last_tv:
            continue
        if last_tv is not None and policy.order.value == "strict" and tv <= last_tv:
            continue
        if policy.lower is not None and v < policy.lower:
            continue
        if policy.upper is not None and v > policy.upper:
            continue
        if out and not is_change(policy, last_v, v):
            continue
        out.append((v, tv, ta))
        last_tv, last_v = tv, v
    return out


def is_change(policy: Policy, before: Any, now: Any) -> bool:
    kind = policy.change.kind.value
    delta = policy.change.delta
    if kind == "any_update":
        return True
    if kind == "any_change":
        return bool(now != before)
    assert delta is not None
    if kind == "absolute":
        return abs(now - before) > delta
    if before == 0:
        return bool(now != 0)
    return abs(now - before) / abs(before) > delta


def check_stream(policy: Policy, out: list[tuple[Any, int, int]], inputs: list[Sample]) -> None:
    """Every guarantee the policy gives on its emitted stream."""
    tvs = [s[1] for s in out]
    if policy.order.value == "monotone":
        assert tvs == sorted(tvs)
    if policy.order.value == "strict":
        assert all(a < b for a, b in pairwise(tvs))
    if policy.max_delay is not None:
        maxd = seconds_to_ns(policy.max_delay)
        assert all(ta - tv <= maxd for _, tv, ta in out), out
    for a, b in pairwise(out):
        assert is_change(policy, a[0], b[0]), (a, b)
    if policy.lower is not None:
        assert all(v >= policy.lower for v, _, _ in out)
    if policy.upper is not None:
        assert all(v <= policy.upper for v, _, _ in out)
    if policy.start is not None:
        assert all(tv >= policy.start for tv in tvs)
    if policy.end is not None:
        assert all(tv <= policy.end for tv in tvs)
    if policy.sample_period is not None:
        p = seconds_to_ns(policy.sample_period)
        assert all(tv % p == 0 for tv in tvs), tvs
        assert all(a < b for a, b in pairwise(tvs)), tvs
        if policy.approximation.value != "linear":
            assert {v for v, _, _ in out} <= {s[0] for s in inputs}


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_non_periodic_filter_matches_the_policy_meaning(data: st.DataObject) -> None:
    policy = data.draw(policies(periodic=False))
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    out, _ = run(policy, *batches)
    assert out == reference(policy, samples)


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_every_policy_guarantee_holds_on_the_output(data: st.DataObject) -> None:
    policy = data.draw(policies())
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    ticks = data.draw(st.lists(st.integers(-1, 20), max_size=len(batches)))
    f = PolicyFilter(policy)
    out = drive(f, batches, ticks)
    check_stream(policy, out, samples)
    assert f.stats.emitted == len(out)


@settings(max_examples=100, deadline=None)
@given(
    samples=arrivals(),
    order=st.sampled_from(["monotone", "strict"]),
    period=st.sampled_from([None, *PERIODS]),
)
def test_order_holds_in_output(samples: list[Sample], order: str, period: float | None) -> None:
    extra: dict[str, Any] = (
        {} if period is None else {"sample_period": period, "approximation": "closest"}
    )
    out, _ = run(Policy(order=order, **extra), samples)
    tvs = [s[1] for s in out]
    assert tvs == sorted(tvs)
    if order == "strict":
        assert len(set(tvs)) == len(tvs)


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    max_delay=st.sampled_from([0.0, 0.1, 0.35, 1.0]),
    period=st.sampled_from([None, *PERIODS]),
    approx=st.sampled_from(["none", "most_recent", "closest", "linear"]),
    late=st.sampled_from(["drop", "approximate"]),
)
def test_max_delay_is_never_exceeded_in_output(
    data: st.DataObject, max_delay: float, period: float | None, approx: str, late: str
) -> None:
    if period is None:
        policy = Policy(max_delay=max_delay)
    else:
        policy = Policy(
            max_delay=max_delay,
            sample_period=period,
            approximation=approx,
            late=late if approx != "none" else "drop",
        )
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    ticks = data.draw(st.lists(st.integers(-1, 30), max_size=len(batches)))
    out = drive(PolicyFilter(policy), batches, ticks)
    maxd = seconds_to_ns(max_delay)
    assert all(ta - tv <= maxd for _, tv, ta in out)


@settings(max_examples=100, deadline=None)
@given(samples=arrivals(), period=st.sampled_from([None, *PERIODS]))
def test_no_two_consecutive_equal_values_under_any_change(
    samples: list[Sample], period: float | None
) -> None:
    extra: dict[str, Any] = (
        {} if period is None else {"sample_period": period, "approximation": "most_recent"}
    )
    out, _ = run(Policy(change="any_change", **extra), samples)
    assert all(a[0] != b[0] for a, b in pairwise(out))
    if period is None:
        # and nothing more is dropped: each run of equal values gives exactly one sample
        runs = [v for i, (v, _, _) in enumerate(samples) if i == 0 or samples[i - 1][0] != v]
        assert values(out) == runs


@settings(max_examples=100, deadline=None)
@given(
    samples=arrivals(),
    delta=st.sampled_from([0.0, 0.5, 1.0, 3.0]),
    kind=st.sampled_from(["absolute", "relative"]),
)
def test_change_threshold_is_respected(samples: list[Sample], delta: float, kind: str) -> None:
    policy = Policy(change=f"{kind}({delta})")
    out, _ = run(policy, samples)
    for a, b in pairwise(out):
        diff = abs(b[0] - a[0])
        assert (
            (diff > delta)
            if kind == "absolute"
            else (diff > delta * abs(a[0]) if a[0] else b[0] != 0)
        )
    if samples:
        assert out[0] == tuple(samples[0])


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    period=st.sampled_from(PERIODS),
    approx=st.sampled_from(["none", "most_recent", "closest", "linear"]),
    max_delay=st.sampled_from([None, 0.2, 1.0]),
)
def test_periodic_output_is_on_the_grid_and_strictly_increasing(
    data: st.DataObject, period: float, approx: str, max_delay: float | None
) -> None:
    late = "approximate" if approx != "none" and max_delay is not None else "drop"
    policy = Policy(sample_period=period, approximation=approx, max_delay=max_delay, late=late)
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    ticks = data.draw(st.lists(st.integers(-1, 30), max_size=len(batches)))
    out = drive(PolicyFilter(policy), batches, ticks)
    p = seconds_to_ns(period)
    tvs = [s[1] for s in out]
    assert all(tv % p == 0 for tv in tvs)
    assert all(a < b for a, b in pairwise(tvs))


@settings(max_examples=60, deadline=None)
@given(
    samples=arrivals(),
    period=st.sampled_from(PERIODS),
)
def test_periodic_most_recent_fills_every_grid_point_of_an_ordered_stream(
    samples: list[Sample], period: float
) -> None:
    ordered = sorted(samples, key=lambda s: (s[1], s[2]))
    ordered = [Sample(s[0], s[1], i) for i, s in enumerate(ordered)]
    out, _ = run(Policy(sample_period=period, approximation="most_recent"), ordered)
    if not ordered:
        assert out == []
        return
    p = seconds_to_ns(period)
    first = -(-ordered[0][1] // p) * p
    last = ordered[-1][1]
    expected = [g for g in range(first, last + 1, p) if g < last or any(s[1] == g for s in ordered)]
    assert [s[1] for s in out] == expected
    for v, g, _ in out:
        exact = [s for s in ordered if s[1] == g]
        # an exact sample is emitted as it arrives; otherwise the newest estimate before g
        expected_value = exact[0][0] if exact else [s for s in ordered if s[1] < g][-1][0]
        assert v == expected_value


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    lo=st.integers(-5, 5),
    width=st.integers(0, 6),
    period=st.sampled_from([None, *PERIODS]),
)
def test_bounds_are_respected(
    data: st.DataObject, lo: int, width: int, period: float | None
) -> None:
    extra: dict[str, Any] = {}
    if period is not None:
        extra = {
            "sample_period": period,
            "approximation": data.draw(st.sampled_from(["closest", "linear"])),
        }
    samples = data.draw(arrivals())
    out, _ = run(Policy(lower=lo, upper=lo + width, **extra), samples)
    assert all(lo <= v <= lo + width for v, _, _ in out)
    if period is None:
        assert values(out) == [s[0] for s in samples if lo <= s[0] <= lo + width]


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    a=st.integers(0, 60),
    b=st.integers(0, 60),
    period=st.sampled_from([None, *PERIODS]),
)
def test_window_is_respected(data: st.DataObject, a: int, b: int, period: float | None) -> None:
    start, end = min(a, b) * STEP, max(a, b) * STEP
    extra: dict[str, Any] = (
        {} if period is None else {"sample_period": period, "approximation": "closest"}
    )
    samples = data.draw(arrivals())
    out, _ = run(Policy(start=start, end=end, **extra), samples)
    assert all(start <= s[1] <= end for s in out)


@pytest.mark.parametrize(
    ("lower", "last", "expected"),
    [
        # interpolated between the last value emitted (0 at 0 s) and the waiting one (-1 at
        # 0.2 s), not extrapolated back from the next (-2 at 0.1 s, below the bound)
        (-1.0, Sample(0, seconds_to_ns(0.3), seconds_to_ns(0.3) + 2), [-0.5, -1, 0]),
        # the next one at the waiting one's valid time: a division by zero before
        (None, Sample(0, seconds_to_ns(0.2), seconds_to_ns(0.2) + 3), [0.0, 0]),
    ],
)
def test_a_sample_waiting_on_the_old_grid_is_fed_to_the_new_one(
    lower: float | None, last: Sample, expected: list[Any]
) -> None:
    """Found by the property below: the old grid's waiting sample was taken for the one
    before the new grid's next point, which it is not (it is newer)."""
    first = Policy(sample_period=0.25)
    second = Policy(sample_period=0.1, approximation="linear", lower=lower)
    waiting = Sample(-1 if lower is not None else 0, seconds_to_ns(0.2), seconds_to_ns(0.2) + 2)
    f = PolicyFilter(first)
    assert [tuple(x) for x in f.process([Sample(0, 0, 0), Sample(0, 0, 1), waiting])] == [(0, 0, 0)]
    g = PolicyFilter(second, previous=f)
    out = [tuple(x) for x in g.process([last])]
    assert [x[0] for x in out] == expected
    assert [x[1] for x in out] == [seconds_to_ns(0.1 * (i + 1)) for i in range(len(out))]
    check_stream(second, out, [waiting, last])


@pytest.mark.parametrize("replacements", [1, 2, 3])
def test_a_waiting_sample_survives_replacements_with_nothing_between(replacements: int) -> None:
    """Replaced again before a sample or tick, the filter still has the waiting sample (it
    was held, not yet on the grid, where the next replacement did not look)."""
    f = PolicyFilter(Policy(sample_period=0.25))
    assert [tuple(x) for x in f.process([smp(0, 0), smp(5.0, 0.2)])] == [(0, 0, 0)]
    second = Policy(sample_period=0.1, approximation="linear")
    for _ in range(replacements):
        f = PolicyFilter(second, previous=f)
    out = [tuple(x) for x in f.process([smp(2.0, 0.4)])]
    assert [x[1] for x in out] == [seconds_to_ns(t) for t in (0.1, 0.2, 0.3, 0.4)]
    assert [x[0] for x in out] == pytest.approx([2.5, 5.0, 3.5, 2.0])


def test_a_waiting_sample_survives_a_replacement_before_anything_was_emitted() -> None:
    f = PolicyFilter(Policy(sample_period=1.0))
    assert f.process([smp(1.0, 0.5)]) == []  # waits for the grid point at 1 s
    second = Policy(sample_period=0.25, approximation="linear")
    g = PolicyFilter(second, previous=f)
    out = [tuple(x) for x in g.process([smp(2.0, 1.0)])]
    assert [x[1] for x in out] == [seconds_to_ns(t) for t in (0.5, 0.75, 1.0)]
    assert [x[0] for x in out] == pytest.approx([1.0, 1.5, 2.0])


def test_a_waiting_sample_late_for_the_new_policy_is_dropped() -> None:
    f = PolicyFilter(Policy(sample_period=0.25))
    late = smp(5.0, 0.2, 0.5)  # 0.3 s after its valid time: late for the new policy
    assert [tuple(x) for x in f.process([smp(0, 0), late])] == [(0, 0, 0)]
    second = Policy(sample_period=0.1, approximation="most_recent", max_delay=0.25)
    g = PolicyFilter(second, previous=f)
    out = [tuple(x) for x in g.process([smp(2.0, 0.4, 0.5)])]
    assert [x[1] for x in out] == [seconds_to_ns(t) for t in (0.1, 0.2, 0.3, 0.4)]
    assert [x[0] for x in out] == [0, 0, 0, 2.0]  # never the late 5.0


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_replacing_the_policy_keeps_order_and_change_guarantees(data: st.DataObject) -> None:
    first = data.draw(policies())
    second = data.draw(policies())
    samples = data.draw(arrivals())
    cut = data.draw(st.integers(0, len(samples)))
    f = PolicyFilter(first)
    before = [tuple(s) for s in f.process(samples[:cut])] if cut else []
    g = PolicyFilter(second, previous=f)
    after = [tuple(s) for s in g.process(samples[cut:])] if cut < len(samples) else []
    check_stream(second, after, samples)
    if before and after:
        a, b = before[-1], after[0]
        if second.order.value == "monotone":
            assert b[1] >= a[1]
        if second.order.value == "strict":
            assert b[1] > a[1]
        assert is_change(second, a[0], b[0]), (a, b)


def admitted(policy: Policy, samples: list[Sample]) -> list[Sample]:
    """The inputs a periodic policy lets onto its grid, written plainly: on time, in order
    with the last admitted input, within the bounds."""
    out: list[Sample] = []
    last: int | None = None
    maxd = None if policy.max_delay is None else seconds_to_ns(policy.max_delay)
    for s in samples:
        v, tv, ta = s
        if maxd is not None and ta - tv > maxd:
            continue
        if last is not None and policy.order.value == "monotone" and tv < last:
            continue
        if last is not None and policy.order.value == "strict" and tv <= last:
            continue
        if policy.lower is not None and v < policy.lower:
            continue
        if policy.upper is not None and v > policy.upper:
            continue
        out.append(s)
        last = tv
    return out


@settings(max_examples=300, deadline=None)
@given(
    policy=policies(periodic=True),
    order=st.sampled_from(["monotone", "strict"]),
    # few valid times: many samples share one, and many arrive out of order
    samples=arrivals(span=12),
)
@example(
    policy=Policy(sample_period=0.1, approximation="most_recent"),
    order="strict",
    samples=[Sample(0, STEP, STEP), Sample(1, STEP, STEP + 2), Sample(0, 3 * STEP, 3 * STEP + 1)],
)
def test_order_is_applied_before_the_sample_period_grid(
    policy: Policy, order: str, samples: list[Sample]
) -> None:
    policy = policy.replace(order=order)
    out, _ = run(policy, samples)
    unordered, _ = run(policy.replace(order="any"), admitted(policy, samples))
    assert out == unordered


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_any_batch_split_gives_the_same_output_as_single_pushes(data: st.DataObject) -> None:
    policy = data.draw(policies())
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    ticks = data.draw(st.lists(st.integers(-1, 20), max_size=len(batches)))
    # a tick after a batch happens, for single pushes, after that batch's last sample
    singles: list[list[Sample]] = []
    single_ticks: list[int] = []
    for i, b in enumerate(batches):
        singles += [[s] for s in b]
        single_ticks += [-1] * (len(b) - 1) + [ticks[i] if i < len(ticks) else -1]
    f, g = PolicyFilter(policy), PolicyFilter(policy)
    assert drive(f, batches, ticks) == drive(g, singles, single_ticks)
    assert f.ended == g.ended


def publish(gen: StreamGenerator, batches: list[list[Sample]], ticks: list[int]) -> None:
    """Publish the batches; after each, tick every subscription as the instance's ticker would."""
    for i, b in enumerate(batches):
        gen.publish_batch([tuple(s) for s in b])
        if i < len(ticks) and ticks[i] >= 0:
            for sub in gen.subscriptions:
                sub.tick(b[-1][2] + ticks[i] * STEP)


@settings(max_examples=200, deadline=None)
@given(
    data=st.data(),
    size=st.integers(1, 12),
    overflow=st.sampled_from(["drop_oldest", "drop_newest"]),
)
def test_the_buffer_only_decides_what_is_lost_when_it_is_full(
    data: st.DataObject, size: int, overflow: str
) -> None:
    """Whatever its size, a buffer holds a part of exactly what the policy emits (the first
    ones with drop_newest, the last ones with drop_oldest) and counts every other one; a
    buffer large enough holds all of it."""
    policy = data.draw(policies())
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    ticks = data.draw(st.lists(st.integers(-1, 20), max_size=len(batches)))
    gen = StreamGenerator("x", CacheSpec())
    emitted: list[tuple[Any, int, int]] = []
    gen.subscribe(policy, callback=emitted.extend)
    small = gen.subscribe(policy.replace(buffer_size=size, overflow=overflow))
    large = gen.subscribe(policy.replace(buffer_size=len(samples) * 70 + 1, overflow=overflow))
    publish(gen, batches, ticks)
    assert list(large.buffer) == emitted and large.overflowed == 0
    kept = emitted[:size] if overflow == "drop_newest" else emitted[-size:]
    assert list(small.buffer) == kept
    assert small.overflowed == len(emitted) - len(kept)
    assert small.delivered == len(kept)
    assert small.filter.stats.as_dict() == large.filter.stats.as_dict()


@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_subscribers_are_independent_of_what_a_callback_does_to_its_batch(
    data: st.DataObject,
) -> None:
    policy = data.draw(policies())
    samples = data.draw(arrivals())
    batches = data.draw(splits(samples))
    gen = StreamGenerator("x", CacheSpec())
    vandal_saw: list[tuple[Any, int, int]] = []

    def vandal(batch: list[tuple[Any, int, int]]) -> None:
        vandal_saw.extend(batch)
        batch.clear()

    first: list[tuple[Any, int, int]] = []
    second: list[tuple[Any, int, int]] = []
    gen.subscribe(policy, callback=first.extend)
    gen.subscribe(policy, callback=vandal)
    gen.subscribe(policy, callback=second.extend)
    buffered = gen.subscribe(policy.replace(buffer_size=10_000))
    published = [[tuple(s) for s in b] for b in batches]
    for b in published:
        gen.publish_batch(b)
    expected, _ = run(policy, *batches)
    assert first == second == vandal_saw == list(buffered.buffer) == expected
    # the publisher's own lists are untouched, and so is the cache
    assert [s for b in published for s in b] == [tuple(s) for s in samples]
    assert gen.cache.samples() == [tuple(s) for s in samples]


def test_a_callback_clearing_its_batch_leaves_the_next_subscriber_its_samples() -> None:
    gen = StreamGenerator("x", CacheSpec())
    got: list[tuple[Any, int, int]] = []
    gen.subscribe(Policy(), callback=lambda batch: batch.clear())
    gen.subscribe(Policy(), callback=got.extend)
    mine = [(1, 1, 1), (2, 2, 2)]
    gen.publish_batch(mine)
    assert got == [(1, 1, 1), (2, 2, 2)]
    assert mine == [(1, 1, 1), (2, 2, 2)]


def test_a_gap_in_the_data_never_floods_a_fine_grid() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")
    out: list = []
    sub = dk.subscribe(
        "x",
        Policy(sample_period=1e-6, approximation="most_recent", buffer_size=100),
        callback=out.extend,
    )
    src.push(1.0, 0, 0)
    src.push(2.0, S, S)  # 1 s later: 999 999 grid points in between
    # at most MAX_GRID_BURST of them (whatever the buffer), plus the two exact hits;
    # the rest counted
    assert len(out) == 1 + MAX_GRID_BURST + 1
    assert sub.filter.stats.skipped == 999_999 - MAX_GRID_BURST
    assert out[-1][0] == 2.0


async def test_instance_loop_is_not_blocked_by_one_push_after_a_gap() -> None:
    # the same fine grid inside a running instance: the event loop stays responsive
    async with DyKnowInstance(clock=ManualClock()) as dk:
        src = dk.add_source("x")
        dk.subscribe("x", Policy(sample_period=1e-9, approximation="most_recent"))
        src.push(1.0, 0, 0)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        src.push(2.0, 10_000_000, 10_000_000)
        assert loop.time() - t0 < 1.0
