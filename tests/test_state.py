"""States: component streams of different rates and delays synchronized on a period grid."""

from __future__ import annotations

import asyncio
import itertools
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dyknow_core._exceptions import (
    DuplicateLabelError,
    PolicyError,
    ProcessError,
    UnknownLabelError,
)
from dyknow_core._instance import DyKnowInstance
from dyknow_core._policy import Approximation, LateAction
from dyknow_core._state import Missing, StatePolicy, StateProcess, StateStrategy, add_state
from dyknow_core._time import NS_PER_S, ManualClock

S = NS_PER_S
MS = NS_PER_S // 1000


def states(inst: DyKnowInstance, label: str = "s") -> list[tuple[Any, int, int]]:
    """Every state published so far, as plain (value, valid, available) tuples."""
    return list(inst.stream(label).cache.samples())


def two_sources(inst: DyKnowInstance, **kw: Any) -> tuple[Any, Any]:
    return inst.add_source("a", **kw), inst.add_source("b", **kw)


# -- the state policy -------------------------------------------------------------------


def test_state_policy_defaults_and_component_policy() -> None:
    p = StatePolicy(period=0.5)
    assert p.strategy is StateStrategy.LATEST
    assert p.missing is Missing.SKIP
    assert p.max_delay is None
    cp = p.component_policy()
    assert cp.sample_period == 0.5
    assert cp.approximation is Approximation.MOST_RECENT
    assert cp.late is LateAction.DROP

    timed = StatePolicy(period=1, strategy="interpolate", max_delay=0.2, start=5, end=10)
    cp = timed.component_policy()
    assert cp.approximation is Approximation.LINEAR
    assert cp.late is LateAction.APPROXIMATE
    assert (cp.max_delay, cp.start, cp.end) == (0.2, 5, 10)
    assert StateStrategy("closest").approximation is Approximation.CLOSEST


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"period": 0}, "period"),
        ({"period": -1.0}, "period"),
        ({"period": 1e-12}, "period"),
        ({"period": float("inf")}, "period"),
        ({"period": float("nan")}, "period"),
        ({"period": 1, "max_delay": float("inf")}, "max_delay"),
        ({}, "period"),
        ({"period": 1, "max_delay": -0.1}, "max_delay"),
        ({"period": 1, "strategy": "cubic"}, "strategy"),
        ({"period": 1, "missing": "guess"}, "missing"),
        ({"period": 1, "start": 10, "end": 5}, "start"),
        ({"period": 1, "colour": "red"}, "colour"),
    ],
)
def test_state_policy_refuses_impossible_values_naming_the_field(
    data: dict[str, Any], field: str
) -> None:
    with pytest.raises(PolicyError) as err:
        StatePolicy(**data)
    assert err.value.field == field
    with pytest.raises(PolicyError) as err2:
        StatePolicy.parse(data)
    assert err2.value.field == field


def test_state_policy_is_frozen_and_parses_mappings() -> None:
    p = StatePolicy.parse({"period": 2, "strategy": "closest", "missing": "last"})
    assert p.strategy is StateStrategy.CLOSEST and p.missing is Missing.LAST
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen error
        p.period = 3  # type: ignore[misc]


# -- creating and removing --------------------------------------------------------------


def test_add_state_registers_a_process_and_publishes_a_stream() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    two_sources(inst)
    proc = add_state(inst, "s", {"a": "a", "b": "b"}, {"period": 1})
    assert isinstance(proc, StateProcess)
    assert inst.processes["state:s"] is proc
    assert inst.has_label("s") and inst.stream("s").value_type is dict
    d = proc.describe()
    assert d["kind"] == "state" and d["components"] == {"a": "a", "b": "b"}
    assert d["output"] == "s" and d["emitted"] == 0

    inst.remove_process("state:s")
    assert not inst.has_label("s")
    assert not proc.running
    assert all(sub.closed for sub in proc.subscriptions)
    assert inst.stream("a").subscriptions == []


def test_add_state_refusals_leave_nothing_behind() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    two_sources(inst)
    with pytest.raises(UnknownLabelError):
        add_state(inst, "s", {"a": "a", "x": "nope"}, StatePolicy(period=1))
    with pytest.raises(ProcessError):
        add_state(inst, "s", {}, StatePolicy(period=1))
    with pytest.raises(ProcessError):
        add_state(inst, "a", {"a": "a"}, StatePolicy(period=1))
    with pytest.raises(DuplicateLabelError):
        add_state(inst, "b", {"a": "a"}, StatePolicy(period=1), name="other")
    assert not inst.has_label("s")
    assert set(inst.processes) == {"source:a", "source:b"}
    assert inst.stream("a").subscriptions == []

    add_state(inst, "s", {"a": "a"}, StatePolicy(period=1))
    with pytest.raises(ProcessError):
        add_state(inst, "s2", {"a": "a"}, StatePolicy(period=1), name="state:s")
    assert not inst.has_label("s2")


def test_interpolating_a_declared_non_numeric_component_is_refused() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("speed", value_type=float)
    inst.add_source("name", value_type=str)
    policy = StatePolicy(period=1, strategy="interpolate")
    with pytest.raises(PolicyError) as err:
        add_state(inst, "s", {"speed": "speed", "name": "name"}, policy)
    assert err.value.field == "strategy"
    assert "'name'" in str(err.value)
    assert not inst.has_label("s")
    # the latest value is fine for any type
    add_state(inst, "s", {"speed": "speed", "name": "name"}, StatePolicy(period=1))


def test_interpolating_undeclared_non_numeric_values_is_counted_not_fatal() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    a, b = two_sources(inst)
    proc = add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, strategy="interpolate"))
    a.push("x", 0, 0)
    b.push(0.0, 0, 0)
    a.push("y", 2 * S, 2 * S)
    b.push(2.0, 2 * S, 2 * S)
    got = states(inst)
    assert [v for v, _, _ in got] == [
        {"a": "x", "b": 0.0},
        {"a": "x", "b": 1.0},  # "x" could not be interpolated: the latest before is used
        {"a": "y", "b": 2.0},
    ]
    assert proc.type_errors == 1
    assert proc.describe()["type_errors"] == 1
    assert inst.failure_count == 0


# -- data-driven joining ------------------------------------------------------------------


def test_state_is_emitted_once_every_component_has_the_grid_point() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    a, b = two_sources(inst)
    add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1))
    a.push(1, 0, 10 * MS)
    assert states(inst) == []  # b has not said anything about t=0 yet
    b.push(10, 0, 30 * MS)
    assert states(inst) == [({"a": 1, "b": 10}, 0, 30 * MS)]  # available with its last part
    b.push(11, 1 * S, 1 * S + 5 * MS)
    a.push(2, 1 * S, 1 * S + 20 * MS)
    assert states(inst)[-1] == ({"a": 2, "b": 11}, S, S + 20 * MS)


def test_different_rates_are_sampled_on_the_state_grid() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    fast, slow = two_sources(inst)
    add_state(inst, "s", {"fast": "a", "slow": "b"}, StatePolicy(period=0.5))
    for i in range(31):  # 10 Hz, value = its time in tenths
        fast.push(i, i * S // 10, i * S // 10 + MS)
    for i in range(4):  # 1 Hz
        slow.push(100 + i, i * S, i * S + 2 * MS)
    got = states(inst)
    assert [tv for _, tv, _ in got] == [k * S // 2 for k in range(7)]
    assert [v for v, _, _ in got] == [{"fast": 5 * k, "slow": 100 + k // 2} for k in range(7)]
    assert all(tv % (S // 2) == 0 for _, tv, _ in got)


def test_closest_and_interpolate_strategies() -> None:
    for strategy, expected in [
        ("latest", [0.0, 0.0, 0.0, 0.0, 4.0]),
        ("closest", [0.0, 0.0, 0.0, 4.0, 4.0]),  # a tie goes to the earlier sample
        ("interpolate", [0.0, 1.0, 2.0, 3.0, 4.0]),
    ]:
        inst = DyKnowInstance(clock=ManualClock())
        a, b = two_sources(inst)
        add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=0.25, strategy=strategy))
        for k in range(5):  # b has every grid point
            b.push(k, k * S // 4, k * S // 4)
        a.push(0.0, 0, 0)
        a.push(4.0, S, S)
        got = states(inst)
        assert [v["a"] for v, _, _ in got] == expected, strategy
        assert [v["b"] for v, _, _ in got] == [0, 1, 2, 3, 4]


def test_component_starting_later_is_missing_until_it_starts() -> None:
    for missing, first in [("skip", 2 * S), ("none", 0)]:
        inst = DyKnowInstance(clock=ManualClock())
        a, b = two_sources(inst)
        add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, missing=missing))
        for k in range(4):
            a.push(k, k * S, k * S)
        b.push(20, 2 * S, 2 * S)  # b starts at 2 s: it has moved past 0 s and 1 s
        b.push(30, 3 * S, 3 * S)
        got = states(inst)
        assert got[0][1] == first
        assert got[-1] == ({"a": 3, "b": 30}, 3 * S, 3 * S)
        if missing == "none":
            assert [v for v, _, _ in got[:2]] == [{"a": 0, "b": None}, {"a": 1, "b": None}]


def test_pending_grid_points_are_bounded_when_a_component_is_silent() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    a, _b = two_sources(inst)
    proc = add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, missing="none"))
    proc.max_pending = 3
    for k in range(6):  # b never speaks and there is no max delay to give up on it
        a.push(k, k * S, k * S)
    assert [v["a"] for v, _, _ in states(inst)] == [0, 1, 2]
    assert all(v["b"] is None for v, _, _ in states(inst))
    assert proc.stats.forced == 3
    assert len(proc._rows) == 3  # never more than max_pending wait


def test_state_respects_start_and_end_and_replays_history() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    a, b = two_sources(inst)
    for k in range(3):  # history, in the cache before the state exists
        a.push(k, k * S, k * S)
        b.push(10 + k, k * S, k * S)
    add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, start=1 * S, end=3 * S))
    assert [tv for _, tv, _ in states(inst)] == [1 * S, 2 * S]
    for k in range(3, 6):
        a.push(k, k * S, k * S)
        b.push(10 + k, k * S, k * S)
    assert [tv for _, tv, _ in states(inst)] == [1 * S, 2 * S, 3 * S]


def test_state_stream_is_an_ordinary_stream() -> None:
    inst = DyKnowInstance(clock=ManualClock(10 * S))
    a, b = two_sources(inst)
    add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1))
    for k in range(3):
        a.push(k, k * S, k * S)
        b.push(-k, k * S, k * S)
    assert inst.latest("s").samples[0].value == {"a": 2, "b": -2}
    assert inst.at("s", S).samples[0].value == {"a": 1, "b": -1}
    assert [s.valid_time for s in inst.between("s", 0, 2 * S).samples] == [0, S, 2 * S]
    assert inst.metrics("s")["samples_in"] == 3


# -- time-driven: the max delay ----------------------------------------------------------


async def test_max_delay_approximates_a_silent_component_on_the_clock() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        a, b = two_sources(inst)
        proc = add_state(inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, max_delay=0.5))
        out = inst.subscribe("s")
        a.push(1.0, 0, 0)
        b.push(10.0, 0, 0)
        assert await out.get(timeout=1) == ({"a": 1.0, "b": 10.0}, 0, 0)
        a.push(2.0, S, S)  # b goes silent
        clock.set(2 * S)  # the deadline of 1 s (1.5 s) has passed
        s1 = await out.get(timeout=1)
        assert s1 == ({"a": 2.0, "b": 10.0}, S, S + S // 2)
        clock.set(4 * S)
        s2 = await out.get(timeout=1)
        s3 = await out.get(timeout=1)
        assert (s2.valid_time, s3.valid_time) == (2 * S, 3 * S)
        assert s3.available_time - s3.valid_time == S // 2
        assert proc.stats.late == 0
    assert not proc.running


async def test_missing_component_per_policy_when_max_delay_passes() -> None:
    results: dict[str, list[Any]] = {}
    for missing in ("skip", "none", "last"):
        clock = ManualClock()
        async with DyKnowInstance(clock=clock) as inst:
            a, b = two_sources(inst)
            b.push("parked", -5 * S, -5 * S)  # before the state exists: only in the cache
            proc = add_state(
                inst,
                "s",
                {"a": "a", "b": "b"},
                StatePolicy(period=1, max_delay=0.25, missing=missing),
            )
            out = inst.subscribe("s")
            a.push(1, 0, 0)
            a.push(2, S, S)
            clock.set(S + S // 2)  # deadlines of 0 s and 1 s passed: only the timer can act
            got = []
            if missing != "skip":
                got = [await out.get(timeout=1), await out.get(timeout=1)]
            # b comes back at 2 s: that state is complete
            a.push(3, 2 * S, 2 * S)
            b.push("back", 2 * S, 2 * S)
            got.append(await out.get(timeout=1))
            results[missing] = [tuple(x) for x in got]
            if missing == "skip":
                assert proc.stats.skipped == 2
            else:
                assert proc.stats.filled == 2
    back = ({"a": 3, "b": "back"}, 2 * S, 2 * S)
    assert results["skip"] == [back]
    assert results["none"] == [
        ({"a": 1, "b": None}, 0, S // 4),
        ({"a": 2, "b": None}, S, S + S // 4),
        back,
    ]
    assert results["last"] == [
        ({"a": 1, "b": "parked"}, 0, S // 4),
        ({"a": 2, "b": "parked"}, S, S + S // 4),
        back,
    ]


async def test_missing_last_skips_the_state_while_a_component_was_never_known() -> None:
    """``last`` takes the newest value at or before the grid point that was available by
    the state's available time; a component never known by then (or known only by a later
    valid time) leaves nothing to take: that state is skipped, as with ``skip``, and
    counted in ``stats.skipped``."""
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        a, b = two_sources(inst)
        proc = add_state(
            inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, max_delay=0.25, missing="last")
        )
        out = inst.subscribe("s")
        a.push(1, 0, 0)
        a.push(2, S, S)
        clock.set(S + S // 2)  # 0 s and 1 s decided by time; b was never known: skipped
        proc.tick(clock.now())  # what the instance's timer does (at once, deterministically)
        assert states(inst) == []
        assert proc.stats.skipped == 2 and proc.stats.filled == 0
        # b known from 2.5 s on (valid time): still nothing at or before 2 s for the state at 2
        a.push(3, 2 * S, 2 * S)
        b.push("late start", 2 * S + S // 2, 2 * S + S // 2)
        clock.set(2 * S + S // 2)
        proc.tick(clock.now())
        assert states(inst) == []
        assert proc.stats.skipped == 3
        # at 3 s b has a value of its own (its latest sample before the grid point)
        a.push(4, 3 * S, 3 * S)
        clock.set(3 * S + S // 2)
        proc.tick(clock.now())
        assert tuple(await out.get(timeout=1)) == (
            {"a": 4, "b": "late start"},
            3 * S,
            3 * S + S // 4,
        )
        assert proc.stats.skipped == 3


async def test_state_decided_by_later_data_is_still_available_within_max_delay() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        a, b = two_sources(inst)
        add_state(
            inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, max_delay=0.5, missing="none")
        )
        a.push(0, 0, 0)
        b.push(7, 2 * S, 2 * S)  # b starts at 2 s, so it has no value at 0 s
        assert states(inst) == [({"a": 0, "b": None}, 0, S // 2)]


async def test_late_component_data_for_a_decided_grid_point_is_counted() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        a, b = two_sources(inst)
        proc = add_state(
            inst, "s", {"a": "a", "b": "b"}, StatePolicy(period=1, max_delay=0.5, missing="none")
        )
        out = inst.subscribe("s")
        a.push(1, 0, 0)
        clock.set(S)
        assert await out.get(timeout=1) == ({"a": 1, "b": None}, 0, S // 2)
        b.push(5, 0, S // 2)  # on time by its own delay, but the state at 0 s was decided
        assert proc.stats.late == 1
        assert [tv for _, tv, _ in states(inst)] == [0]


async def test_removing_a_timed_state_stops_its_timer() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        a, _b = two_sources(inst)
        proc = add_state(inst, "s", {"a": "a"}, StatePolicy(period=1, max_delay=0.5))
        a.push(1, 0, 0)
        await asyncio.sleep(0)
        inst.remove_process(proc.name)
        clock.set(10 * S)
        assert proc.deadline() is None
        tasks = [t for t in asyncio.all_tasks() if "state[" in t.get_name()]
        async with asyncio.timeout(1):
            await asyncio.gather(*tasks)
        a.push(2, 10 * S, 10 * S)  # no state process left to feed
        assert not inst.has_label("s")


# -- properties -------------------------------------------------------------------------

_component = st.tuples(
    st.integers(min_value=20, max_value=700),  # sample period, ms
    st.integers(min_value=0, max_value=300),  # offset of its first sample, ms
    st.lists(st.integers(min_value=0, max_value=400), min_size=1, max_size=12),  # delays, ms
)


async def _run_scenario(
    comps: list[tuple[int, int, list[int]]],
    period_ms: int,
    max_delay_ms: int | None,
    strategy: str,
    missing: str,
) -> tuple[list[tuple[Any, int, int]], StateProcess]:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        names = {f"c{i}": f"c{i}" for i in range(len(comps))}
        srcs = [inst.add_source(label) for label in names.values()]
        policy = StatePolicy(
            period=period_ms / 1000,
            strategy=strategy,
            missing=missing,
            max_delay=None if max_delay_ms is None else max_delay_ms / 1000,
        )
        proc = add_state(inst, "s", names, policy)
        pushes = []
        for i, (p, off, delays) in enumerate(comps):
            for k, d in enumerate(delays):
                tv = (off + k * p) * MS
                pushes.append((tv + d * MS, i, k, tv))
        pushes.sort()
        for ta, i, k, tv in pushes:
            # the clock reads the available time of what is pushed; the process decides
            # what is due first, exactly as its timer would have
            clock.set(max(clock.now(), ta))
            proc.tick(clock.now())
            srcs[i].push(float(k), tv, ta)
        clock.set(clock.now() + 10 * S)
        proc.tick(clock.now())
        return states(inst), proc


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    comps=st.lists(_component, min_size=1, max_size=3),
    period_ms=st.integers(min_value=50, max_value=500),
    max_delay_ms=st.one_of(st.none(), st.integers(min_value=0, max_value=350)),
    strategy=st.sampled_from(["latest", "closest", "interpolate"]),
    missing=st.sampled_from(["skip", "none", "last"]),
)
def test_property_states_are_on_the_grid_ordered_and_timely(
    comps: list[tuple[int, int, list[int]]],
    period_ms: int,
    max_delay_ms: int | None,
    strategy: str,
    missing: str,
) -> None:
    got, proc = asyncio.run(_run_scenario(comps, period_ms, max_delay_ms, strategy, missing))
    period = period_ms * MS
    for value, tv, ta in got:
        assert tv % period == 0
        assert set(value) == {f"c{i}" for i in range(len(comps))}
        if missing == "skip":
            assert None not in value.values()
        if max_delay_ms is not None:
            assert ta - tv <= max_delay_ms * MS
    tvs = [tv for _, tv, _ in got]
    assert all(x < y for x, y in itertools.pairwise(tvs))
    tas = [ta for _, _, ta in got]
    assert all(x < y for x, y in itertools.pairwise(tas))
    # the clock always read the available time of what arrived: nothing came too late
    assert proc.stats.late == 0
    assert proc.stats.emitted == len(got)
