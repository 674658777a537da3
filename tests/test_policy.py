"""Policies: every impossible policy is refused at the edge with a PolicyError naming the field.

A policy that validates must also be usable: subscribing with it never crashes later.
"""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
from pydantic import ValidationError

from dyknow_core import (
    NS_PER_S,
    Approximation,
    CacheSpec,
    Change,
    ChangeKind,
    DyKnowError,
    DyKnowInstance,
    LateAction,
    ManualClock,
    Order,
    Overflow,
    Policy,
    PolicyError,
    PolicyFilter,
    Sample,
)

S = NS_PER_S


def refused(field: str, **fields: object) -> PolicyError:
    """Build a Policy from ``fields``, expect it refused, and check the error names ``field``."""
    with pytest.raises(PolicyError) as info:
        Policy(**fields)  # type: ignore[arg-type]
    err = info.value
    assert field in err.field, f"error names {err.field!r}, expected {field!r}: {err}"
    assert field in str(err)
    return err


# -- the happy path ----------------------------------------------------------------------------


def test_default_policy_is_every_update_in_any_order() -> None:
    p = Policy()
    assert p.start is None and p.end is None
    assert p.sample_period is None
    assert p.approximation is Approximation.NONE
    assert p.max_delay is None
    assert p.late is LateAction.DROP
    assert p.order is Order.ANY
    assert p.change.kind is ChangeKind.ANY_UPDATE
    assert p.lower is None and p.upper is None
    assert p.buffer_size >= 1
    assert p.overflow in (Overflow.DROP_OLDEST, Overflow.DROP_NEWEST)


def test_full_policy_accepts_strings_for_enums() -> None:
    p = Policy(
        start=0,
        end=10 * S,
        sample_period=0.5,
        approximation="linear",
        max_delay=0.2,
        late="approximate",
        order="strict",
        change="any_change",
        lower=-1.0,
        upper=1.0,
        buffer_size=8,
        overflow="drop_newest",
    )
    assert p.approximation is Approximation.LINEAR
    assert p.late is LateAction.APPROXIMATE
    assert p.order is Order.STRICT
    assert p.change.kind is ChangeKind.ANY_CHANGE
    assert p.overflow is Overflow.DROP_NEWEST


def test_equal_bounds_and_equal_window_ends_are_allowed() -> None:
    p = Policy(start=5, end=5, lower=2.0, upper=2.0)
    assert (p.start, p.end, p.lower, p.upper) == (5, 5, 2.0, 2.0)


def test_policy_is_immutable() -> None:
    p = Policy(sample_period=1.0)
    with pytest.raises((ValidationError, AttributeError, TypeError)):
        p.sample_period = 2.0  # type: ignore[misc]
    assert p.sample_period == 1.0


def test_policy_error_is_a_value_error_and_a_dyknow_error() -> None:
    err = refused("sample_period", sample_period=-1.0)
    assert isinstance(err, ValueError)
    assert isinstance(err, DyKnowError)


# -- single fields -----------------------------------------------------------------------------


@pytest.mark.parametrize("period", [-1.0, -0.001, 0.0])
def test_non_positive_sample_period_is_refused(period: float) -> None:
    refused("sample_period", sample_period=period)


@pytest.mark.parametrize("period", [math.nan, math.inf, 1e-12])
def test_unusable_sample_period_is_refused(period: float) -> None:
    # NaN, infinity, or a period shorter than the time line's resolution (1 ns) cannot
    # give a grid of valid times.
    refused("sample_period", sample_period=period)


@pytest.mark.parametrize("delay", [-1.0, -1e-9, math.nan])
def test_negative_max_delay_is_refused(delay: float) -> None:
    refused("max_delay", max_delay=delay)


def test_zero_max_delay_is_allowed() -> None:
    assert Policy(max_delay=0.0).max_delay == 0.0


def test_start_after_end_is_refused() -> None:
    with pytest.raises(PolicyError) as info:
        Policy(start=10 * S, end=5 * S)
    assert info.value.field in ("start", "end")


def test_lower_above_upper_is_refused() -> None:
    with pytest.raises(PolicyError) as info:
        Policy(lower=2.0, upper=1.0)
    assert info.value.field in ("lower", "upper")


@pytest.mark.parametrize("field", ["lower", "upper"])
def test_nan_bound_is_refused(field: str) -> None:
    # a NaN bound compares false with everything: it would silently filter nothing
    refused(field, **{field: math.nan})


@pytest.mark.parametrize("size", [0, -5])
def test_non_positive_buffer_size_is_refused(size: int) -> None:
    refused("buffer_size", buffer_size=size)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("order", "sideways"),
        ("approximation", "cubic"),
        ("late", "ignore"),
        ("overflow", "block"),
        ("start", "yesterday"),
        ("lower", "low"),
    ],
)
def test_wrong_value_is_refused_naming_the_field(field: str, value: object) -> None:
    refused(field, **{field: value})


def test_unknown_field_is_refused_naming_it() -> None:
    # a typo must not silently give the default policy
    refused("sample_perod", sample_perod=1.0)


# -- coherence between fields ------------------------------------------------------------------


@pytest.mark.parametrize("approx", ["most_recent", "closest", "linear"])
def test_approximation_without_sample_period_is_refused(approx: str) -> None:
    refused("approximation", approximation=approx)


def test_late_approximate_without_sample_period_is_refused() -> None:
    refused("late", late="approximate", max_delay=1.0)


def test_late_approximate_without_approximation_is_refused() -> None:
    refused("late", late="approximate", sample_period=1.0, max_delay=1.0)


def test_late_approximate_without_max_delay_is_refused() -> None:
    refused("late", late="approximate", sample_period=1.0, approximation="most_recent")


def test_late_approximate_with_everything_it_needs_is_accepted() -> None:
    p = Policy(late="approximate", sample_period=1.0, approximation="closest", max_delay=0.5)
    assert p.late is LateAction.APPROXIMATE


# -- change ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "kind", "delta"),
    [
        ("any_update", ChangeKind.ANY_UPDATE, None),
        ("any_change", ChangeKind.ANY_CHANGE, None),
        ("absolute(0.5)", ChangeKind.ABSOLUTE, 0.5),
        ("relative(0.1)", ChangeKind.RELATIVE, 0.1),
        ("  absolute ( 2 ) ", ChangeKind.ABSOLUTE, 2.0),
        ("relative(1e-2)", ChangeKind.RELATIVE, 0.01),
        ("absolute(0)", ChangeKind.ABSOLUTE, 0.0),
    ],
)
def test_change_string_forms(text: str, kind: ChangeKind, delta: float | None) -> None:
    for change in (Change.parse(text), Policy(change=text).change):  # type: ignore[arg-type]
        assert change.kind is kind
        assert change.delta == delta


def test_change_from_a_mapping() -> None:
    p = Policy.parse({"change": {"kind": "relative", "delta": 0.25}})
    assert p.change == Change(kind=ChangeKind.RELATIVE, delta=0.25)


@pytest.mark.parametrize("kind", ["absolute", "relative"])
def test_threshold_change_without_delta_is_refused(kind: str) -> None:
    with pytest.raises(PolicyError) as info:
        Change(kind=kind)  # type: ignore[arg-type]
    assert info.value.field == "delta"
    err = refused("delta", change=kind)
    assert err.field.startswith("change")


@pytest.mark.parametrize("kind", ["any_update", "any_change"])
def test_delta_on_a_change_that_takes_none_is_refused(kind: str) -> None:
    with pytest.raises(PolicyError) as info:
        Change(kind=kind, delta=0.5)  # type: ignore[arg-type]
    assert info.value.field == "delta"
    refused("delta", change={"kind": kind, "delta": 0.5})


@pytest.mark.parametrize("text", ["absolute(-0.5)", "relative(-1)"])
def test_negative_delta_is_refused(text: str) -> None:
    err = refused("delta", change=text)
    assert err.field.startswith("change")


def test_nan_delta_is_refused() -> None:
    # |a - b| <= NaN is never true: a NaN delta would silently let every update through
    with pytest.raises(PolicyError) as info:
        Change(kind=ChangeKind.ABSOLUTE, delta=math.nan)
    assert info.value.field == "delta"


@pytest.mark.parametrize("text", ["bogus", "absolute(abc)", "absolute[0.5]", "relative()"])
def test_malformed_change_text_is_refused(text: str) -> None:
    err = refused("change", change=text)
    assert isinstance(err, PolicyError)


# -- parse and replace -------------------------------------------------------------------------


def test_parse_a_config_mapping() -> None:
    p = Policy.parse({"sample_period": 0.5, "approximation": "closest", "change": "absolute(1)"})
    assert p.sample_period == 0.5
    assert p.approximation is Approximation.CLOSEST
    assert p.change == Change(kind=ChangeKind.ABSOLUTE, delta=1.0)
    assert Policy.parse(p) is p


def test_parse_refuses_with_the_field_name() -> None:
    with pytest.raises(PolicyError) as info:
        Policy.parse({"sample_period": -2})
    assert info.value.field == "sample_period"


def test_replace_returns_a_validated_copy() -> None:
    p = Policy(sample_period=1.0, approximation="most_recent")
    q = p.replace(sample_period=2.0)
    assert q.sample_period == 2.0 and q.approximation is Approximation.MOST_RECENT
    assert p.sample_period == 1.0
    with pytest.raises(PolicyError) as info:
        p.replace(sample_period=None)  # approximation without a period
    assert info.value.field == "approximation"
    with pytest.raises(PolicyError) as info:
        p.replace(lower=3.0, upper=1.0)
    assert info.value.field in ("lower", "upper")


# -- accepted policies are usable --------------------------------------------------------------


@pytest.mark.parametrize("periodic", [False, True])
def test_an_accepted_infinite_max_delay_is_usable(periodic: bool) -> None:
    """Either the edge refuses an infinite max_delay, naming it, or nothing is ever late."""
    extra: dict[str, object] = (
        {"sample_period": 1.0, "approximation": "most_recent"} if periodic else {}
    )
    try:
        policy = Policy(max_delay=math.inf, **extra)  # type: ignore[arg-type]
    except PolicyError as exc:
        assert exc.field == "max_delay"
        return
    batch = [Sample(1.0, 0, 0), Sample(2.0, S, 100 * S)]
    out = PolicyFilter(policy).process(batch)
    assert [tuple(s) for s in out] == [tuple(s) for s in batch]


# -- cache spec --------------------------------------------------------------------------------


def test_cache_spec_validation() -> None:
    assert CacheSpec(max_samples=5).max_samples == 5
    assert CacheSpec(max_samples=None, max_age=2.0).max_age == 2.0
    for fields, field in [
        ({"max_samples": 0}, "max_samples"),
        ({"max_age": 0.0}, "max_age"),
        ({"max_age": -1.0}, "max_age"),
        ({"max_samples": None, "max_age": None}, "max_samples"),
    ]:
        with pytest.raises(PolicyError) as info:
            CacheSpec(**fields)  # type: ignore[arg-type]
        assert info.value.field == field


# -- numeric-only policies on non-numeric streams ----------------------------------------------


NUMERIC_ONLY = [
    ({"lower": 0.0}, "lower"),
    ({"upper": 1.0}, "upper"),
    ({"change": "absolute(0.5)"}, "change"),
    ({"change": "relative(0.1)"}, "change"),
    ({"sample_period": 1.0, "approximation": "linear"}, "approximation"),
]


@pytest.mark.parametrize(("fields", "field"), NUMERIC_ONLY)
def test_numeric_policy_on_non_numeric_stream_is_refused(
    fields: dict[str, object], field: str
) -> None:
    dk = DyKnowInstance(clock=ManualClock())
    dk.create_stream("car/car5/color", value_type=str)
    with pytest.raises(PolicyError) as info:
        dk.subscribe("car/car5/color", Policy(**fields))  # type: ignore[arg-type]
    assert info.value.field.startswith(field)
    assert "car/car5/color" in str(info.value)
    assert dk.stream("car/car5/color").subscriptions == []


@pytest.mark.parametrize(
    "fields",
    [
        {"change": "any_change"},
        {"sample_period": 1.0, "approximation": "most_recent"},
        {"sample_period": 1.0, "approximation": "closest"},
        {"order": "strict"},
    ],
)
def test_non_numeric_policy_on_non_numeric_stream_is_accepted(fields: dict[str, object]) -> None:
    dk = DyKnowInstance(clock=ManualClock())
    dk.create_stream("color", value_type=str)
    sub = dk.subscribe("color", Policy(**fields))  # type: ignore[arg-type]
    assert not sub.closed


@pytest.mark.parametrize("value_type", [int, float, bool, Fraction])
def test_numeric_policy_on_numeric_stream_is_accepted(value_type: type) -> None:
    dk = DyKnowInstance(clock=ManualClock())
    dk.create_stream("speed", value_type=value_type)
    for fields, _ in NUMERIC_ONLY:
        dk.subscribe("speed", Policy(**fields))  # type: ignore[arg-type]


def test_numeric_policy_on_undeclared_stream_is_accepted() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    dk.create_stream("anything")
    dk.subscribe("anything", Policy(lower=0.0, change="absolute(1)"))


def test_replacing_with_a_numeric_policy_on_a_non_numeric_stream_is_refused() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    dk.create_stream("color", value_type=str)
    old = Policy(change="any_change")
    sub = dk.subscribe("color", old)
    with pytest.raises(PolicyError) as info:
        sub.replace_policy(Policy(upper=3.0))
    assert info.value.field == "upper"
    assert sub.policy is old


def test_cu_with_numeric_input_policy_on_non_numeric_stream_is_refused_cleanly() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    dk.add_source("color", value_type=str)
    with pytest.raises(PolicyError) as info:
        dk.add_cu("brightness", len, [("color", Policy(lower=1.0))], "color/brightness")
    assert info.value.field == "lower"
    # nothing half-made is left behind: the name and the output label are free again
    assert "brightness" not in dk.processes
    assert not dk.has_label("color/brightness")
    assert dk.stream("color").subscriptions == []
    dk.add_cu("brightness", len, ["color"], "color/brightness")


@pytest.mark.parametrize(
    ("field", "kwargs"),
    [
        ("sample_period", {"sample_period": 1e300}),
        ("max_delay", {"sample_period": 1.0, "max_delay": 1e300}),
    ],
)
def test_durations_too_large_for_the_time_line_are_refused(field: str, kwargs: dict) -> None:  # type: ignore[type-arg]
    # seconds_to_ns would overflow a float: refuse at the edge, naming the field
    with pytest.raises(PolicyError) as info:
        Policy(**kwargs)
    assert info.value.field == field
