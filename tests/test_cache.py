"""A location's cache and its queries: bounds, bitemporal "as believed at tq", fluent generators."""

from __future__ import annotations

from collections import deque
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dyknow_core import (
    NS_PER_S,
    Answer,
    Approximation,
    Cache,
    CacheSpec,
    DyKnowInstance,
    ManualClock,
    Policy,
    PolicyError,
    Sample,
    UnknownLabelError,
    seconds_to_ns,
)

S = NS_PER_S
MS = NS_PER_S // 1000
STEP = 100 * MS

Raw = tuple[Any, int, int]


def rows(samples: list[Any]) -> list[Raw]:
    return [tuple(s) for s in samples]  # type: ignore[misc]


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(100 * S)


@pytest.fixture
def dk(clock: ManualClock) -> DyKnowInstance:
    return DyKnowInstance(clock=clock)


# -- bounds ------------------------------------------------------------------------------------


def test_last_n_samples() -> None:
    cache = Cache(CacheSpec(max_samples=3))
    cache.extend([Sample(i, i, i) for i in range(5)])
    assert rows(cache.samples()) == [(2, 2, 2), (3, 3, 3), (4, 4, 4)]
    cache.extend([Sample(5, 5, 5)])
    assert [s[0] for s in cache.samples()] == [3, 4, 5]
    assert len(cache) == 3
    assert cache.evicted == 3


def test_last_t_seconds_by_available_time() -> None:
    cache = Cache(CacheSpec(max_samples=None, max_age=1.0))
    cache.extend([Sample(i, 0, i * 300 * MS) for i in range(5)])  # available 0 .. 1.2 s
    # kept: everything available within the last second before the newest (0.3 .. 1.2 s)
    assert [s[0] for s in cache.samples()] == [1, 2, 3, 4]
    cache.extend([Sample(9, 0, 5 * S)])
    assert [s[0] for s in cache.samples()] == [9]
    assert cache.evicted == 5


def test_both_bounds_apply() -> None:
    cache = Cache(CacheSpec(max_samples=2, max_age=10.0))
    cache.extend([Sample(i, i, i * MS) for i in range(4)])
    assert [s[0] for s in cache.samples()] == [2, 3]
    cache = Cache(CacheSpec(max_samples=100, max_age=0.5))
    cache.extend([Sample(i, i, i * 400 * MS) for i in range(4)])
    assert [s[0] for s in cache.samples()] == [2, 3]


@st.composite
def arrival_batches(draw: st.DrawFn) -> list[list[Sample]]:
    """Batches of samples with strictly increasing available times (gaps up to 0.8 s)."""
    gaps = draw(st.lists(st.integers(1, 8 * STEP // MS), min_size=1, max_size=60))
    ta = 0
    samples = []
    for i, g in enumerate(gaps):
        ta += g * MS
        samples.append(Sample(i, ta - draw(st.integers(0, 3)) * STEP, ta))
    cuts = sorted(draw(st.sets(st.integers(1, len(samples)), max_size=6)) | {len(samples)})
    out, a = [], 0
    for c in cuts:
        if c > a:
            out.append(samples[a:c])
            a = c
    return out


@settings(max_examples=150, deadline=None)
@given(
    batches=arrival_batches(),
    max_samples=st.one_of(st.none(), st.integers(1, 12)),
    max_age=st.one_of(st.none(), st.sampled_from([0.1, 0.5, 1.0, 2.5])),
)
def test_cache_bounds_are_respected(
    batches: list[list[Sample]], max_samples: int | None, max_age: float | None
) -> None:
    if max_samples is None and max_age is None:
        max_samples = 5
    cache = Cache(CacheSpec(max_samples=max_samples, max_age=max_age))
    seen: list[Sample] = []
    for batch in batches:
        cache.extend(batch)
        seen.extend(batch)
        kept = rows(cache.samples())
        newest = seen[-1][2]
        # what is kept is the most recent part of the stream, in arrival order
        assert kept == rows(seen[len(seen) - len(kept) :])
        assert kept[-1] == tuple(seen[-1])
        if max_samples is not None:
            assert len(kept) <= max_samples
        candidates = seen if max_samples is None else seen[-max_samples:]
        if max_age is not None:
            t = seconds_to_ns(max_age)
            assert all(ta >= newest - t for _, _, ta in kept)
            # nothing young enough (and among the last N) was thrown away
            assert len(kept) >= sum(1 for s in candidates if s[2] > newest - t)
        else:
            assert len(kept) == len(candidates)
        assert cache.evicted == len(seen) - len(kept)


@settings(max_examples=150, deadline=None)
@given(
    batches=arrival_batches(),
    max_samples=st.one_of(st.none(), st.integers(1, 12)),
    max_age=st.one_of(st.none(), st.sampled_from([0.1, 0.5, 1.0, 2.5])),
    asks=st.lists(st.integers(0, 3), min_size=1, max_size=40),
)
def test_latest_between_arrivals_is_the_full_scan(
    batches: list[list[Sample]], max_samples: int | None, max_age: float | None, asks: list[int]
) -> None:
    """latest() reads only what arrived since its last call: it must equal a full scan."""
    cache = Cache(CacheSpec(max_samples=max_samples or (None if max_age else 5), max_age=max_age))
    for i, batch in enumerate(batches):
        cache.extend(batch)
        for _ in range(asks[i % len(asks)]):
            kept = cache.samples()
            want = None
            for s in reversed(kept):  # newest arrival first: it wins a tie
                if want is None or s[1] > want[1]:
                    want = s
            assert cache.latest() is want
            assert cache.latest(as_of=kept[-1][2] if kept else None) is want


def test_instance_streams_use_their_cache_spec(dk: DyKnowInstance) -> None:
    src = dk.add_source("x", cache=CacheSpec(max_samples=10))
    src.push_batch([(i, i * STEP, i * STEP) for i in range(100)])
    assert dk.metrics("x")["cached"] == 10
    assert [s.value for s in dk.between("x", 0, 100 * STEP).samples] == list(range(90, 100))


def test_location_default_cache_spec_applies_to_its_streams(dk: DyKnowInstance) -> None:
    dk.add_location("sensors", cache=CacheSpec(max_samples=4))
    src = dk.add_source("camera", location="sensors")
    src.push_batch([(i, i, i) for i in range(9)])
    assert dk.metrics("camera")["cached"] == 4
    assert dk.metrics("camera")["location"] == "sensors"


# -- queries -----------------------------------------------------------------------------------


def test_latest_is_the_greatest_valid_time_not_the_last_arrival(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    src.push("new", 5 * S, 10 * S)
    src.push("old-but-late", 3 * S, 11 * S)
    ans = dk.latest("x")
    assert isinstance(ans, Answer)
    assert ans.label == "x"
    assert ans.query_time == dk.clock.now()
    assert ans.latest == Sample("new", 5 * S, 10 * S)


def test_latest_of_an_empty_stream_is_empty(dk: DyKnowInstance) -> None:
    dk.add_source("x")
    ans = dk.latest("x")
    assert ans.samples == [] and ans.latest is None


def test_superseded_estimates_are_kept_and_the_newest_wins(dk: DyKnowInstance) -> None:
    src = dk.add_source("car/car5/position")
    src.push("quick", 10 * S, 10 * S)
    src.push("improved", 10 * S, 12 * S)
    src.push("other", 11 * S, 12 * S + 1)
    src.push("best", 10 * S, 15 * S)
    label = "car/car5/position"
    assert [s.value for s in dk.between(label, 0, 20 * S).samples] == ["best", "other"]
    everything = dk.between(label, 10 * S, 10 * S, all_estimates=True).samples
    assert [s.value for s in everything] == ["quick", "improved", "best"]
    assert dk.at(label, 10 * S).latest == Sample("best", 10 * S, 15 * S)
    assert dk.latest(label).latest.value == "other"  # type: ignore[union-attr]
    # what did we believe at 13 s about 10 s?
    assert dk.at(label, 10 * S, as_of=13 * S).latest.value == "improved"  # type: ignore[union-attr]
    assert [s.value for s in dk.between(label, 0, 20 * S, as_of=11 * S).samples] == ["quick"]
    assert [s.value for s in dk.between(label, 0, 20 * S, as_of=12 * S).samples] == ["improved"]


def test_as_of_before_anything_was_available_sees_nothing(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    src.push(1.0, 5 * S, 6 * S)
    assert dk.latest("x", as_of=6 * S - 1).samples == []
    assert dk.at("x", 5 * S, as_of=6 * S - 1).samples == []
    assert dk.between("x", 0, 10 * S, as_of=6 * S - 1).samples == []
    assert dk.latest("x", as_of=6 * S).latest == Sample(1.0, 5 * S, 6 * S)


def test_what_was_just_pushed_is_queryable_at_once(dk: DyKnowInstance) -> None:
    """Several pushes at one clock reading: all of them are available when the query runs."""
    src = dk.add_source("x")
    for i in range(3):
        src.push(float(i), valid_time=i * S)
    assert [s.value for s in dk.between("x", 0, 10 * S).samples] == [0.0, 1.0, 2.0]
    assert dk.latest("x").latest.value == 2.0  # type: ignore[union-attr]
    assert dk.at("x", 2 * S).latest.value == 2.0  # type: ignore[union-attr]


def test_queries_without_as_of_are_as_believed_now(dk: DyKnowInstance, clock: ManualClock) -> None:
    """A replayed log is pushed ahead of the clock; a query answers with what is known now."""
    src = dk.add_source("x")
    now = clock.now()
    src.push("known", now - S, now - S)
    src.push("not yet", now + S, now + 2 * S)
    assert dk.latest("x").latest.value == "known"  # type: ignore[union-attr]
    assert [s.value for s in dk.between("x", 0, now + 10 * S).samples] == ["known"]
    clock.set(now + 2 * S)
    assert dk.latest("x").latest.value == "not yet"  # type: ignore[union-attr]


def test_the_default_query_time_includes_what_this_location_stamped_past_the_clock(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    """Two pushes at one clock reading: the second is stamped 1 ns past now. Without
    ``as_of`` it is known (this location stamped it); ``as_of=now`` is strictly the clock."""
    src = dk.add_source("x")
    now = clock.now()
    src.push("first", now - S)
    src.push("second", now)
    assert [s.available_time for s in dk.between("x", 0, now).samples] == [now, now + 1]
    ans = dk.latest("x")
    assert ans.latest == Sample("second", now, now + 1) and ans.query_time == now
    assert dk.latest("x", as_of=now).latest == Sample("first", now - S, now)
    # a sample pushed with a future available time of its own is not known before then
    src.push("future", now + S, available_time=now + 5 * S)
    assert dk.latest("x").latest.value == "second"  # type: ignore[union-attr]


def test_max_age_is_counted_back_from_the_newest_arrival_not_from_the_query(
    dk: DyKnowInstance, clock: ManualClock
) -> None:
    """A cache is the stream's history: a stream that went quiet keeps its last T seconds,
    however long ago they came; queries judge staleness by the answer's times."""
    src = dk.add_source("x", cache=CacheSpec(max_samples=None, max_age=1.0))
    now = clock.now()
    src.push_batch([(i, now - (3 - i) * 400 * MS, now - (3 - i) * 400 * MS) for i in range(4)])
    assert [s.value for s in dk.between("x", 0, now).samples] == [1, 2, 3]  # the last second
    clock.set(now + 3600 * S)
    assert [s.value for s in dk.between("x", 0, now).samples] == [1, 2, 3]
    assert dk.latest("x").latest == Sample(3, now, now)
    src.push(9, now + 3600 * S)  # a new arrival moves the window
    assert [s.value for s in dk.between("x", 0, now + 3600 * S).samples] == [9]


@pytest.fixture
def ramp(dk: DyKnowInstance) -> DyKnowInstance:
    """A stream with 0.0 at 1 s, 10.0 at 2 s, 20.0 at 4 s."""
    src = dk.add_source("ramp")
    for v, t in [(0.0, 1), (10.0, 2), (20.0, 4)]:
        src.push(v, t * S, t * S)
    return dk


@pytest.mark.parametrize(
    ("t", "approximation", "expected"),
    [
        (2.0, Approximation.NONE, 10.0),
        (2.0, Approximation.LINEAR, 10.0),
        (3.0, Approximation.NONE, None),
        (3.0, Approximation.MOST_RECENT, 10.0),
        (3.5, Approximation.CLOSEST, 20.0),
        (2.4, Approximation.CLOSEST, 10.0),
        (3.0, Approximation.LINEAR, 15.0),
        (1.5, Approximation.LINEAR, 5.0),
        (0.5, Approximation.MOST_RECENT, None),
        (0.5, Approximation.CLOSEST, 0.0),
        (0.5, Approximation.LINEAR, None),
        (9.0, Approximation.MOST_RECENT, 20.0),
        (9.0, Approximation.CLOSEST, 20.0),
        (9.0, Approximation.LINEAR, None),
    ],
)
def test_value_at_through_a_fluent_generator(
    ramp: DyKnowInstance, t: float, approximation: Approximation, expected: float | None
) -> None:
    ans = ramp.at("ramp", seconds_to_ns(t), approximation=approximation)
    if expected is None:
        assert ans.samples == []
    else:
        s = ans.latest
        assert s is not None
        assert s.value == pytest.approx(expected)
        assert s.valid_time == seconds_to_ns(t)


def test_value_at_defaults_to_most_recent(ramp: DyKnowInstance) -> None:
    assert ramp.at("ramp", 3 * S).latest.value == 10.0  # type: ignore[union-attr]


def test_value_at_carries_the_available_time_of_what_it_was_computed_from(
    dk: DyKnowInstance,
) -> None:
    src = dk.add_source("x")
    src.push(0.0, 0, 1 * S)
    src.push(10.0, 10 * S, 12 * S)
    assert dk.at("x", 5 * S, approximation=Approximation.LINEAR).latest == Sample(
        5.0, 5 * S, 12 * S
    )
    assert dk.at("x", 5 * S, approximation=Approximation.MOST_RECENT).latest == Sample(
        0.0, 5 * S, 1 * S
    )


def test_between_is_inclusive_and_in_valid_time_order(dk: DyKnowInstance) -> None:
    src = dk.add_source("x")
    for k, (v, tv) in enumerate([("c", 3), ("a", 1), ("d", 4), ("b", 2)]):
        src.push(v, tv * S, 10 * S + k)
    assert [s.value for s in dk.between("x", 2 * S, 4 * S).samples] == ["b", "c", "d"]
    assert dk.between("x", 5 * S, 9 * S).samples == []


def test_between_refuses_a_reversed_interval(dk: DyKnowInstance) -> None:
    dk.add_source("x")
    with pytest.raises(PolicyError) as info:
        dk.between("x", 5 * S, 1 * S)
    assert info.value.field == "t1"


def test_linear_on_non_numeric_values_is_a_clear_policy_error(dk: DyKnowInstance) -> None:
    src = dk.add_source("car/car5/color")
    src.push("red", 1 * S, 1 * S)
    src.push("blue", 3 * S, 3 * S)
    with pytest.raises(PolicyError) as info:
        dk.at("car/car5/color", 2 * S, approximation=Approximation.LINEAR)
    assert info.value.field == "approximation"
    assert "car/car5/color" in str(info.value)
    # the other fluent generators work on any value
    assert dk.at("car/car5/color", 2 * S, approximation=Approximation.CLOSEST).latest.value in (  # type: ignore[union-attr]
        "red",
        "blue",
    )


def test_queries_read_the_cache_not_a_policy(dk: DyKnowInstance) -> None:
    # a subscriber's policy does not change what the location remembers
    src = dk.add_source("x")
    dk.subscribe("x", Policy(change="any_change", upper=0))
    for i in range(3):
        src.push(1.0, i * S, i * S)
    assert len(dk.between("x", 0, 10 * S).samples) == 3


# -- unknown labels ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "query",
    [
        lambda dk: dk.latest("car/car9/speed"),
        lambda dk: dk.at("car/car9/speed", 0),
        lambda dk: dk.between("car/car9/speed", 0, 1),
        lambda dk: dk.subscribe("car/car9/speed"),
        lambda dk: dk.metrics("car/car9/speed"),
        lambda dk: dk.stream("car/car9/speed"),
        lambda dk: dk.remove_stream("car/car9/speed"),
        lambda dk: dk.add_cu("cu", abs, ["car/car9/speed"], "out"),
    ],
    ids=["latest", "at", "between", "subscribe", "metrics", "stream", "remove", "cu-input"],
)
def test_unknown_label_is_named_in_the_error(dk: DyKnowInstance, query: Any) -> None:
    dk.add_source("car/car5/speed")
    with pytest.raises(UnknownLabelError) as info:
        query(dk)
    assert info.value.label == "car/car9/speed"
    assert "car/car9/speed" in str(info.value)
    assert "car/car5/speed" in str(info.value)  # the known labels, as a hint
    assert isinstance(info.value, KeyError)
    assert not dk.has_label("out")


# -- bitemporal property -----------------------------------------------------------------------


@st.composite
def estimates(draw: st.DrawFn) -> list[Sample]:
    """Samples in arrival order; valid times repeat (re-estimates) and may be predictions."""
    items = draw(
        st.lists(
            st.tuples(st.integers(-50, 50), st.integers(0, 20), st.integers(1, 10)),
            min_size=1,
            max_size=40,
        )
    )
    ta = 0
    out = []
    for v, k, gap in items:
        ta += gap * STEP // 4
        out.append(Sample(v, k * STEP, ta))
    return out


def believed(samples: list[Sample], tq: int) -> dict[int, Sample]:
    """The newest estimate of each valid time available by ``tq``."""
    best: dict[int, Sample] = {}
    for s in samples:
        if s.available_time <= tq:
            best[s.valid_time] = s  # arrival order: later replaces earlier
    return best


def expected_at(best: dict[int, Sample], t: int, how: Approximation) -> tuple[Any, int] | None:
    if t in best:
        return best[t].value, best[t].available_time
    before = max((tv for tv in best if tv < t), default=None)
    after = min((tv for tv in best if tv > t), default=None)
    b = best[before] if before is not None else None
    a = best[after] if after is not None else None
    if how is Approximation.NONE:
        return None
    if how is Approximation.MOST_RECENT:
        return None if b is None else (b.value, b.available_time)
    if how is Approximation.CLOSEST:
        if b is None and a is None:
            return None
        if a is None or (b is not None and t - b.valid_time <= a.valid_time - t):
            assert b is not None
            return b.value, b.available_time
        return a.value, a.available_time
    if a is None or b is None:
        return None
    frac = (t - b.valid_time) / (a.valid_time - b.valid_time)
    return b.value + (a.value - b.value) * frac, max(a.available_time, b.available_time)


@settings(max_examples=150, deadline=None)
@given(
    samples=estimates(),
    data=st.data(),
)
def test_bitemporal_queries_never_see_the_future(
    samples: list[Sample], data: st.DataObject
) -> None:
    dk = DyKnowInstance(clock=ManualClock(10**6 * S))
    src = dk.add_source("x")
    src.push_batch(samples)
    # query times right at, just before and just after an availability, and anywhere
    tas = [s.available_time for s in samples]
    near = st.builds(lambda ta, d: ta + d, st.sampled_from(tas), st.sampled_from([-1, 0, 1]))
    tq = data.draw(st.one_of(near, st.integers(-1, tas[-1] + 1)), label="tq")
    t = data.draw(st.integers(-1, 21), label="t") * STEP
    t1, t2 = sorted(data.draw(st.lists(st.integers(0, 20), min_size=2, max_size=2), label="t1t2"))
    t1, t2 = t1 * STEP, t2 * STEP
    best = believed(samples, tq)

    latest = dk.latest("x", as_of=tq).samples
    between = dk.between("x", t1, t2, as_of=tq).samples
    history = dk.between("x", t1, t2, as_of=tq, all_estimates=True).samples
    answers = list(latest) + list(between) + list(history)
    for how in Approximation:
        answers += dk.at("x", t, approximation=how, as_of=tq).samples
    assert all(s.available_time <= tq for s in answers)

    # and, within what was known by tq, each query gives the right answer
    if best:
        top = max(best)
        assert latest == [best[top]]
    else:
        assert latest == []
    assert between == [best[tv] for tv in sorted(best) if t1 <= tv <= t2]
    assert history == [s for s in samples if s.available_time <= tq and t1 <= s.valid_time <= t2]
    for how in Approximation:
        got = dk.at("x", t, approximation=how, as_of=tq).samples
        want = expected_at(best, t, how)
        if want is None:
            assert got == []
        else:
            assert len(got) == 1
            assert got[0].valid_time == t
            assert got[0].value == pytest.approx(want[0])
            assert got[0].available_time == want[1]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.lists(st.tuples(st.integers(0, 20), st.integers(0, 3)), min_size=1, max_size=4),
        min_size=1,
        max_size=8,
    ),
    st.sampled_from([(2, None), (5, None), (None, 3.0)]),
)
def test_latest_now_is_latest_once_asked_and_unknown_before(
    batches: list[list[tuple[int, int]]], bounds: tuple[int | None, float | None]
) -> None:
    """Another thread's read (`Cache.latest_now`): unknown at its first ask (the stream is
    not kept up for it yet: a stream nobody reads so pays nothing per batch), then what
    `latest` says after every batch, while no sample is available later than asked."""
    cache = Cache(CacheSpec(max_samples=bounds[0], max_age=bounds[1]))
    ta = 0
    asked = False
    for batch in batches:
        raws = []
        for tv, gap in batch:
            ta += gap + 1
            raws.append((float(tv), tv * S, ta * S))
        cache.extend(raws)
        if not asked:
            assert cache.latest_now(ta * S) == (False, None)
            asked = True
            continue
        assert cache.latest_now(ta * S) == (True, cache.latest())
        assert cache.latest_now(ta * S - 1) == (False, None)  # the newest came after it


def test_latest_now_follows_samples_arriving_one_at_a_time() -> None:
    """A read stream in flow (one sample per batch): a later arrival of the same valid time
    is the latest, an older valid time is not, and a latest evicted gives way to the best
    of what is left."""
    cache = Cache(CacheSpec(max_samples=3))
    cache.extend([(0.0, 5 * S, 1 * S)])
    assert cache.latest_now(1 * S) == (False, None)  # the first ask: watched from now on
    cache.extend([(1.0, 5 * S, 2 * S)])
    assert cache.latest_now(2 * S) == (True, (1.0, 5 * S, 2 * S))
    cache.extend([(2.0, 5 * S, 3 * S)])  # the same valid time, arrived later: it wins
    assert cache.latest_now(3 * S) == (True, (2.0, 5 * S, 3 * S))
    cache.extend([(3.0, 4 * S, 4 * S)])  # an older valid time: not the latest
    assert cache.latest_now(4 * S) == (True, (2.0, 5 * S, 3 * S))
    cache.extend([(4.0, 3 * S, 5 * S)])
    cache.extend([(5.0, 2 * S, 6 * S)])  # (2.0, 5 s) evicted: the best of the three left
    assert cache.latest_now(6 * S) == (True, (3.0, 4 * S, 4 * S))
    assert cache.latest_now(6 * S)[1] == cache.latest()


def test_latest_now_read_while_old_samples_are_evicted_is_never_older_than_the_read() -> None:
    """Another thread's read that runs while `extend` evicts by age (a thread switch between
    two evictions) gets the latest of some moment of the read or (False, None): never a
    best kept before samples that had arrived before the read began."""
    cache = Cache(CacheSpec(max_age=1.0))
    reads: list[tuple[bool, Raw | None]] = []

    class Switching(deque[Raw]):
        """The cache's buffer, with the other thread's read at each eviction."""

        def popleft(self) -> Raw:
            s = super().popleft()
            reads.append(cache.latest_now(20 * S))
            return s

    cache._buf = Switching(maxlen=None)
    cache.extend([(1.0, 1 * S, 10 * STEP), (2.0, 2 * S, 11 * STEP), (3.0, 3 * S, 12 * STEP)])
    assert cache.latest() == (3.0, 3 * S, 12 * STEP)  # the loop's own query
    cache.extend([(4.0, 4 * S, 13 * STEP), (5.0, 5 * S, 14 * STEP)])  # nobody watched yet
    assert cache.latest_now(20 * S) == (False, None)  # the first ask
    cache.extend([(6.0, 6 * S, 10 * S)])  # the five before it are older than 1 s: evicted
    assert len(reads) == 5
    # before this extend the latest was (5.0, 5 s); after it, (6.0, 6 s)
    told = [sample for known, sample in reads if known]
    assert all(s in ((5.0, 5 * S, 14 * STEP), (6.0, 6 * S, 10 * S)) for s in told), told
    assert cache.latest_now(20 * S) == (True, (6.0, 6 * S, 10 * S))
