"""Primitive events as event streams: a sample arrived, a value changed per a change policy."""

from __future__ import annotations

import itertools
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dyknow_core._events import (
    ChangeEvent,
    EventProcess,
    add_arrival_events,
    add_change_events,
)
from dyknow_core._exceptions import (
    DuplicateLabelError,
    PolicyError,
    ProcessError,
    UnknownLabelError,
)
from dyknow_core._instance import DyKnowInstance
from dyknow_core._policy import Change, ChangeKind, Policy
from dyknow_core._time import NS_PER_S, ManualClock

S = NS_PER_S


def events(inst: DyKnowInstance, label: str) -> list[tuple[Any, int, int]]:
    """Every event published on ``label`` so far, as (value, valid, available) tuples."""
    return list(inst.stream(label).cache.samples())


def feed(src: Any, values: list[Any]) -> None:
    for k, v in enumerate(values):
        src.push(v, k * S, k * S + 1)


def test_any_change_emits_one_event_per_change_with_old_and_new() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("light")
    proc = add_change_events(inst, "light", "any_change")
    assert isinstance(proc, EventProcess)
    assert proc.label == "events/changed/light"
    feed(src, ["red", "red", "green", "green", "amber", "red"])
    assert events(inst, "events/changed/light") == [
        (ChangeEvent(None, "red"), 0, 1),  # the first value: it became known
        (ChangeEvent("red", "green"), 2 * S, 2 * S + 1),
        (ChangeEvent("green", "amber"), 4 * S, 4 * S + 1),
        (ChangeEvent("amber", "red"), 5 * S, 5 * S + 1),
    ]


def test_absolute_change_measures_from_the_last_event() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("x", value_type=float)
    add_change_events(inst, "x", Change(kind=ChangeKind.ABSOLUTE, delta=1.0), output="x/jumps")
    feed(src, [0.0, 0.6, 0.9, 1.2, 1.5, 3.0, 2.5])
    assert [e for e, _, _ in events(inst, "x/jumps")] == [
        (None, 0.0),
        (0.0, 1.2),  # 0.6 and 0.9 were within 1.0 of 0.0; 1.2 is not
        (1.2, 3.0),
    ]


def test_relative_change_and_change_spec_texts() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("speed")
    add_change_events(inst, "speed", "relative(0.1)")
    add_change_events(inst, "speed", {"kind": "absolute", "delta": 5}, output="speed/abs")
    feed(src, [20.0, 21.0, 23.0, 25.0, 26.0, 20.0])
    assert [e.new for e, _, _ in events(inst, "events/changed/speed")] == [20.0, 23.0, 26.0, 20.0]
    assert [e.new for e, _, _ in events(inst, "speed/abs")] == [20.0, 26.0, 20.0]


@pytest.mark.parametrize(
    ("change", "field"),
    [("absolute", "delta"), ("absolute(-1)", "delta"), ("sometimes", "kind")],
)
def test_impossible_change_is_refused_naming_the_field(change: str, field: str) -> None:
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("x")
    with pytest.raises(PolicyError) as err:
        add_change_events(inst, "x", change)
    assert err.value.field == field
    assert not inst.has_label("events/changed/x")


def test_numeric_change_on_a_declared_non_numeric_stream_is_refused() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("name", value_type=str)
    with pytest.raises(PolicyError) as err:
        add_change_events(inst, "name", "absolute(0.5)")
    assert err.value.field == "change"
    assert not inst.has_label("events/changed/name")
    assert "events:events/changed/name" not in inst.processes
    add_change_events(inst, "name", "any_change")  # comparing for equality is fine


def test_numeric_change_on_undeclared_non_numeric_values_is_counted() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("x")
    proc = add_change_events(inst, "x", "absolute(1)")
    feed(src, [0.0, "oops", 5.0])
    assert [e.new for e, _, _ in events(inst, "events/changed/x")] == [0.0, 5.0]
    assert proc.type_errors == 1
    assert proc.describe()["type_errors"] == 1
    assert inst.failure_count == 0


def test_arrival_events_fire_for_every_sample() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("ping")
    proc = add_arrival_events(inst, "ping")
    assert proc.label == "events/arrived/ping"
    src.push(1, 5 * S, 5 * S)
    src.push(1, 6 * S, 6 * S)
    src.push(0, 4 * S, 7 * S)  # out of order in valid time: it still arrived
    assert events(inst, "events/arrived/ping") == [
        (ChangeEvent(None, 1), 5 * S, 5 * S),
        (ChangeEvent(1, 1), 6 * S, 6 * S),
        (ChangeEvent(1, 0), 4 * S, 7 * S),
    ]


def test_change_events_hold_back_revisions_and_out_of_order_samples() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("x")
    proc = add_change_events(inst, "x", "any_change")
    src.push(1, 2 * S, 2 * S)
    src.push(2, 2 * S, 3 * S)  # a revised estimate of 2 s
    src.push(3, 1 * S, 4 * S)  # older than what was seen
    src.push(4, 3 * S, 5 * S)
    assert events(inst, "events/changed/x") == [
        (ChangeEvent(None, 1), 2 * S, 2 * S),
        (ChangeEvent(1, 4), 3 * S, 5 * S),
    ]
    assert proc.describe()["held_back"] == 2
    # a base policy can choose otherwise
    add_change_events(inst, "x", "any_change", output="x/all", policy=Policy(start=0))
    assert [e.new for e, _, _ in events(inst, "x/all")] == [1, 2, 3, 4]  # replayed history


async def test_event_streams_are_ordinary_streams() -> None:
    clock = ManualClock(100 * S)
    async with DyKnowInstance(clock=clock) as inst:
        src = inst.add_source("door")
        add_change_events(inst, "door", "any_change")
        sub = inst.subscribe("events/changed/door")
        src.push("closed", 1 * S, 1 * S)
        src.push("open", 2 * S, 2 * S)
        first = await sub.get(timeout=1)
        second = await sub.get(timeout=1)
        assert (first.value, first.valid_time) == (ChangeEvent(None, "closed"), S)
        assert (second.value.old, second.value.new) == ("closed", "open")
        assert inst.latest("events/changed/door").samples[0].value.new == "open"
        assert len(inst.between("events/changed/door", 0, 3 * S).samples) == 2
        assert inst.stream("events/changed/door").value_type is ChangeEvent
        # a chained change event on an event stream: when did it last change at all
        add_arrival_events(inst, "events/changed/door")
        src.push("closed", 3 * S, 3 * S)
        assert events(inst, "events/arrived/events/changed/door")[-1][0].new == ChangeEvent(
            "open", "closed"
        )


def test_process_lifecycle_and_refusals() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("x")
    with pytest.raises(UnknownLabelError):
        add_change_events(inst, "nope", "any_change")
    with pytest.raises(ProcessError):
        add_change_events(inst, "x", "any_change", output="x")
    proc = add_change_events(inst, "x", "any_change", name="watch-x")
    assert inst.processes["watch-x"] is proc
    d = proc.describe()
    assert d["kind"] == "event" and d["source"] == "x" and d["change"]["kind"] == "any_change"
    with pytest.raises(DuplicateLabelError):
        add_change_events(inst, "x", "any_update", name="other")
    assert "other" not in inst.processes
    with pytest.raises(ProcessError):
        add_change_events(inst, "x", "any_update", output="else", name="watch-x")
    assert not inst.has_label("else")

    src.push(1, 0, 0)
    inst.remove_process("watch-x")
    assert not proc.running
    assert not inst.has_label("events/changed/x")
    assert inst.stream("x").subscriptions == []
    src.push(2, S, S)  # nothing left to feed


# -- properties -------------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(min_value=-3, max_value=3), max_size=40))
def test_property_any_change_never_repeats_a_value(values: list[int]) -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("x")
    add_change_events(inst, "x", "any_change")
    feed(src, values)
    got = events(inst, "events/changed/x")
    news = [e.new for e, _, _ in got]
    assert all(a != b for a, b in itertools.pairwise(news))
    assert [e.old for e, _, _ in got] == [None, *news][: len(got)]
    # every change in the input is there: collapsing runs gives the same sequence
    assert news == [k for k, _ in itertools.groupby(values)]
    tvs = [tv for _, tv, _ in got]
    assert all(a < b for a, b in itertools.pairwise(tvs))


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.floats(min_value=-100, max_value=100), max_size=40),
    st.floats(min_value=0, max_value=20),
)
def test_property_absolute_changes_exceed_delta(values: list[float], delta: float) -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("x", value_type=float)
    add_change_events(inst, "x", Change(kind=ChangeKind.ABSOLUTE, delta=delta))
    feed(src, values)
    got = [e for e, _, _ in events(inst, "events/changed/x")]
    if values:
        assert got[0] == ChangeEvent(None, values[0])
    for e in got[1:]:
        assert abs(e.new - e.old) > delta
    # nothing that was skipped differed by more than δ from the last event
    last = None
    it = iter(got)
    expected = next(it, None)
    for v in values:
        if last is None or abs(v - last) > delta:
            assert expected is not None and expected.new == v
            last = v
            expected = next(it, None)
    assert expected is None
