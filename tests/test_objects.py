"""Objects: the DOM's identifiers, domains, domain subscriptions and set subscriptions."""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dyknow_core._exceptions import ObjectError, PolicyError
from dyknow_core._instance import DyKnowInstance
from dyknow_core._objects import (
    DOM,
    DomainChange,
    MembershipChange,
    ObjectManager,
    SetSubscription,
)
from dyknow_core._policy import Overflow, Policy
from dyknow_core._sample import Sample
from dyknow_core._stream import StreamGenerator
from dyknow_core._time import ManualClock

ADDED, REMOVED = MembershipChange.ADDED, MembershipChange.REMOVED


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(1_000)


@pytest.fixture
def instance(clock: ManualClock) -> DyKnowInstance:
    return DyKnowInstance(clock=clock)


@pytest.fixture
def objects(instance: DyKnowInstance) -> ObjectManager:
    return ObjectManager(instance)


def create(objects: ObjectManager, label: str, **kw: object) -> StreamGenerator:
    """Create a stream and tell the object manager, as the instance's hook will."""
    gen = objects.instance.create_stream(label, **kw)  # type: ignore[arg-type]
    objects.label_created(label)
    return gen


def cars(objects: ObjectManager, *names: str) -> list[str]:
    """Reserve ``names`` and make them members of a "cars" domain."""
    domain = objects.add_domain("cars")
    for n in names:
        domain.add(objects.reserve(n))
    return list(names)


def drain(sub: SetSubscription) -> list[tuple[str, object]]:
    """What a set subscription buffered so far, as (identifier, value) pairs."""
    out = [(i, s.value) for i, s in sub._buffer]
    sub._buffer.clear()
    return out


# -- DOM: identifiers -----------------------------------------------------------------


def test_new_id_numbers_each_prefix_from_one() -> None:
    dom = DOM()
    assert [dom.new_id("car"), dom.new_id("car"), dom.new_id("blob")] == ["car1", "car2", "blob1"]


def test_reserved_identifier_is_assigned_once() -> None:
    dom = DOM()
    assert dom.reserve("car5") == "car5"
    with pytest.raises(ObjectError, match="'car5'"):
        dom.reserve("car5")
    issued = dom.new_id("car")
    with pytest.raises(ObjectError, match=repr(issued)):
        dom.reserve(issued)


def test_new_id_skips_identifiers_already_reserved() -> None:
    dom = DOM()
    dom.reserve("car2")
    assert [dom.new_id("car") for _ in range(3)] == ["car1", "car3", "car4"]


@pytest.mark.parametrize("bad", ["", "car 5", "car/5", "car{id}", "car*", " "])
def test_identifiers_that_would_break_labels_are_refused(bad: str) -> None:
    with pytest.raises(ObjectError, match="not valid"):
        DOM().reserve(bad)


_ops = st.lists(
    st.one_of(
        st.tuples(st.just("new"), st.sampled_from(["x", "x1", "car", "c"])),
        st.tuples(st.just("reserve"), st.from_regex(r"(x|x1|car|c)[0-9]{1,2}", fullmatch=True)),
    ),
    max_size=60,
)


@settings(max_examples=150, deadline=None)
@given(_ops)
def test_no_identifier_is_ever_issued_twice(ops: list[tuple[str, str]]) -> None:
    dom = DOM()
    seen: set[str] = set()
    for op, arg in ops:
        if op == "new":
            ident = dom.new_id(arg)
            assert ident.startswith(arg)
        elif arg in seen:
            with pytest.raises(ObjectError):
                dom.reserve(arg)
            continue
        else:
            ident = dom.reserve(arg)
        assert ident not in seen
        seen.add(ident)
    assert dom.issued == seen


# -- domains ------------------------------------------------------------------------------


def test_an_identifier_may_be_in_several_domains(objects: ObjectManager) -> None:
    vision, tracked = objects.add_domain("vision"), objects.add_domain("tracked")
    car = objects.new_id("car")
    assert vision.add(car) and tracked.add(car)
    assert objects.domains_of(car) == ["tracked", "vision"]
    tracked.remove(car)
    assert car in vision and car not in tracked
    assert objects.domains_of(car) == ["vision"]


def test_membership_is_a_set(objects: ObjectManager) -> None:
    domain = objects.add_domain("cars")
    car = objects.new_id("car")
    assert domain.add(car) is True
    assert domain.add(car) is False
    assert domain.members == {car} and len(domain) == 1
    assert domain.discard(car) is True
    assert domain.discard(car) is False
    with pytest.raises(ObjectError, match=rf"'{car}' is not a member of domain 'cars'"):
        domain.remove(car)


def test_only_identifiers_the_dom_issued_can_join(objects: ObjectManager) -> None:
    domain = objects.add_domain("cars")
    with pytest.raises(ObjectError, match="'cra5' was not issued"):
        domain.add("cra5")


def test_unknown_and_duplicate_domains_are_named(objects: ObjectManager) -> None:
    objects.add_domain("cars")
    with pytest.raises(ObjectError, match=r"unknown domain 'trucks' \(known domains: cars\)"):
        objects.domain("trucks")
    with pytest.raises(ObjectError, match="'trucks'"):
        objects.subscribe_set("trucks", "truck/{id}/speed")
    with pytest.raises(ObjectError, match="domain 'cars' exists already"):
        objects.add_domain("cars")
    assert objects.domains() == ["cars"]


def test_members_remember_when_they_joined(objects: ObjectManager, clock: ManualClock) -> None:
    domain = objects.add_domain("cars")
    clock.set(5_000)
    domain.add(objects.reserve("car1"))
    domain.add(objects.reserve("car2"), time=4_000)
    assert (domain.joined("car1"), domain.joined("car2")) == (5_000, 4_000)


# -- domain subscriptions ----------------------------------------------------------------------


async def test_domain_subscription_yields_changes_and_ends_when_closed(
    objects: ObjectManager, clock: ManualClock
) -> None:
    domain = objects.add_domain("cars")
    sub = objects.subscribe_domain("cars")
    got: list[DomainChange] = []
    ready = asyncio.Event()

    async def consume() -> None:
        ready.set()
        async for change in sub:
            got.append(change)

    async with asyncio.timeout(2), asyncio.TaskGroup() as tg:
        tg.create_task(consume())
        await ready.wait()
        car = objects.new_id("car")
        clock.set(2_000)
        domain.add(car)
        clock.set(3_000)
        domain.remove(car)
        sub.close()
    assert got == [
        DomainChange(ADDED, car, 2_000, "cars"),
        DomainChange(REMOVED, car, 3_000, "cars"),
    ]


async def test_domain_subscription_can_start_with_current_members(
    objects: ObjectManager, clock: ManualClock
) -> None:
    domain = objects.add_domain("cars")
    domain.add(objects.reserve("car1"))
    clock.set(9_000)
    sub = domain.subscribe(initial=True)
    async with asyncio.timeout(2):
        assert await sub.get() == DomainChange(ADDED, "car1", 1_000, "cars")


@pytest.mark.parametrize(
    ("overflow", "kept"),
    [(Overflow.DROP_OLDEST, ["c4", "c5"]), (Overflow.DROP_NEWEST, ["c1", "c2"])],
)
async def test_a_slow_domain_subscriber_loses_counted_changes_never_blocks(
    objects: ObjectManager, overflow: Overflow, kept: list[str]
) -> None:
    domain = objects.add_domain("cars")
    sub = domain.subscribe(buffer_size=2, overflow=overflow)
    for _ in range(5):
        domain.add(objects.new_id("c"))  # returns at once though nobody reads
    sub.close()
    async with asyncio.timeout(2):
        assert [c.identifier async for c in sub] == kept
    assert sub.overflowed == 3
    assert sub.stats()["delivered"] == 5


def test_domain_subscription_buffer_must_hold_something(objects: ObjectManager) -> None:
    with pytest.raises(PolicyError, match="buffer_size"):
        objects.add_domain("cars").subscribe(buffer_size=0)


async def test_removing_a_domain_ends_its_subscriptions(objects: ObjectManager) -> None:
    domain = objects.add_domain("cars")
    changes = domain.subscribe()
    feature = objects.subscribe_set("cars", "car/{id}/speed")
    objects.remove_domain("cars")
    async with asyncio.timeout(2):
        assert [c async for c in changes] == []
        assert [x async for x in feature] == []
    with pytest.raises(ObjectError, match="domain 'cars' was removed"):
        domain.add(objects.new_id("car"))
    with pytest.raises(ObjectError, match="unknown domain 'cars'"):
        objects.domain("cars")


async def test_closing_the_manager_ends_every_subscription(objects: ObjectManager) -> None:
    objects.add_domain("cars")
    changes = objects.subscribe_domain("cars")
    feature = objects.subscribe_set("cars", "car/{id}/speed")
    objects.close()
    async with asyncio.timeout(2):
        assert [c async for c in changes] == []
        assert [x async for x in feature] == []
    assert objects.set_subscriptions == []


def test_published_domain_changes_are_cached_and_queryable(
    objects: ObjectManager, instance: DyKnowInstance, clock: ManualClock
) -> None:
    domain = objects.add_domain("cars", publish=True)
    car = objects.new_id("car")
    clock.set(2_000)
    domain.add(car)
    clock.set(3_000)
    domain.remove(car)
    answer = instance.between("domain/cars", 0, 10_000)
    assert [(s.value, s.valid_time) for s in answer.samples] == [
        (DomainChange(ADDED, car, 2_000, "cars"), 2_000),
        (DomainChange(REMOVED, car, 3_000, "cars"), 3_000),
    ]
    assert instance.latest("domain/cars", as_of=2_500).samples[0].value.kind is ADDED
    objects.remove_domain("cars")
    assert not instance.has_label("domain/cars")


def test_domain_stream_label_can_be_chosen(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    objects.add_domain("cars", publish="objects/cars/members").add(objects.new_id("car"))
    assert len(instance.between("objects/cars/members", 0, 10_000).samples) == 1


# -- set subscriptions --------------------------------------------------------------------------


async def test_set_subscription_streams_the_feature_of_every_member(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    for n in ("car1", "car2", "car3"):
        create(objects, f"car/{n}/speed")
    cars(objects, "car1", "car2")
    objects.reserve("car3")  # issued, but not a member
    sub = objects.subscribe_set("cars", "car/{id}/speed")
    for i, n in enumerate(("car1", "car2", "car3")):
        instance.stream(f"car/{n}/speed").publish(10 + i, 2_000, 2_000)
    async with asyncio.timeout(2):
        assert await sub.get() == ("car1", Sample(10, 2_000, 2_000))
        assert await sub.get() == ("car2", Sample(11, 2_000, 2_000))
    assert sub.buffered == 0
    assert sorted(sub.attached) == ["car1", "car2"]


async def test_set_subscription_follows_membership(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    speed = {n: create(objects, f"car/{n}/speed") for n in ("car1", "car2")}
    (car1, car2) = cars(objects, "car1")[0], objects.reserve("car2")
    domain = objects.domain("cars")
    sub = objects.subscribe_set("cars", "car/{id}/speed")

    domain.add(car2)  # joins: subscribed from now on
    speed[car2].publish(1, 2_000, 2_000)
    domain.remove(car1)  # leaves: unsubscribed, its stream no longer feeds us
    speed[car1].publish(2, 2_000, 2_000)
    assert instance.metrics(f"car/{car1}/speed")["subscribers"] == 0
    async with asyncio.timeout(2):
        assert await sub.get() == (car2, Sample(1, 2_000, 2_000))
    assert sub.buffered == 0


async def test_member_stream_created_later_is_picked_up(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    cars(objects, "car1")
    sub = objects.subscribe_set("cars", "car/{id}/speed")
    assert sub.waiting == ["car1"] and sub.attached == []
    gen = create(objects, "car/car1/speed")  # label_created tells the set subscription
    assert sub.attached == ["car1"]
    gen.publish(7, 2_000, 2_000)
    async with asyncio.timeout(2):
        assert await sub.get() == ("car1", Sample(7, 2_000, 2_000))


def test_refresh_attaches_waiting_members_without_the_hook(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    cars(objects, "car1", "car2")
    sub = objects.subscribe_set("cars", "car/{id}/speed")
    instance.create_stream("car/car1/speed")  # the manager is not told
    assert sub.refresh() == 1
    assert (sub.attached, sub.waiting) == (["car1"], ["car2"])


def test_member_stream_removed_and_published_again_is_followed(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    cars(objects, "car1")
    create(objects, "car/car1/speed")
    sub = objects.subscribe_set("cars", "car/{id}/speed")
    instance.remove_stream("car/car1/speed")
    assert sub.waiting == ["car1"]
    create(objects, "car/car1/speed").publish(3, 2_000, 2_000)
    assert drain(sub) == [("car1", 3)]


def test_each_member_gets_its_own_policy_state(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    gens = [create(objects, f"car/car{i}/speed") for i in (1, 2)]
    cars(objects, "car1", "car2")
    sub = objects.subscribe_set("cars", "car/{id}/speed", Policy(change="any_change", upper=50))
    for t, (v1, v2) in enumerate([(10, 10), (10, 20), (60, 20), (11, 21)], start=2):
        gens[0].publish(v1, t * 1_000, t * 1_000)
        gens[1].publish(v2, t * 1_000, t * 1_000)
    # the same value on two members is two changes; a repeat on one member is none
    assert drain(sub) == [("car1", 10), ("car2", 10), ("car2", 20), ("car1", 11), ("car2", 21)]
    assert sub.dropped == 3


def test_a_member_joining_late_gets_its_history_per_policy(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    gen = create(objects, "car/car1/speed")
    gen.publish_batch([Sample(1, 100, 100), Sample(2, 2_000, 2_000)])
    objects.add_domain("cars")
    sub = objects.subscribe_set("cars", "car/{id}/speed", Policy(start=1_000))
    objects.domain("cars").add(objects.reserve("car1"))
    assert drain(sub) == [("car1", 2)]


def test_set_subscription_overflow_is_counted(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    gen = create(objects, "car/car1/speed")
    cars(objects, "car1")
    sub = objects.subscribe_set("cars", "car/{id}/speed", Policy(buffer_size=2))
    gen.publish_batch([Sample(v, v, v) for v in range(1, 6)])  # never waits for the reader
    assert drain(sub) == [("car1", 4), ("car1", 5)]
    assert sub.overflowed == 3 and sub.stats()["overflowed"] == 3


def test_set_subscription_callback_gets_batches(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    gen = create(objects, "car/car1/speed")
    cars(objects, "car1")
    got: list[tuple[str, list[Sample]]] = []
    objects.subscribe_set("cars", "car/{id}/speed", callback=lambda i, b: got.append((i, b)))
    gen.publish_batch([Sample(1, 1, 1), Sample(2, 2, 2)])
    assert got == [("car1", [Sample(1, 1, 1), Sample(2, 2, 2)])]


def test_a_member_stream_refusing_the_policy_is_reported_not_raised(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    create(objects, "car/car1/speed", value_type=str)
    create(objects, "car/car2/speed", value_type=float)
    cars(objects)
    sub = objects.subscribe_set("cars", "car/{id}/speed", Policy(lower=0.0))
    domain = objects.domain("cars")
    domain.add(objects.reserve("car1"))  # its stream carries text: the bound cannot apply
    domain.add(objects.reserve("car2"))
    assert (sub.attached, sub.waiting) == (["car2"], ["car1"])
    assert sub.errors == 1 and "lower" in (sub.last_error or "")
    assert instance.failure_count == 1
    assert "car1" in domain


async def test_closing_a_set_subscription_unsubscribes_every_member(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    gen = create(objects, "car/car1/speed")
    cars(objects, "car1")
    sub = objects.subscribe_set("cars", "car/{id}/speed")
    gen.publish(1, 1, 1)
    sub.close()
    gen.publish(2, 2, 2)
    objects.domain("cars").add(objects.new_id("car"))  # no longer followed
    assert instance.metrics("car/car1/speed")["subscribers"] == 0
    async with asyncio.timeout(2):
        assert [(i, s.value) async for i, s in sub] == [("car1", 1)]
    assert objects.set_subscriptions == []


def test_replacing_the_policy_applies_to_present_and_future_members(
    objects: ObjectManager, instance: DyKnowInstance
) -> None:
    gens = {n: create(objects, f"car/{n}/speed") for n in ("car1", "car2")}
    cars(objects, "car1")
    sub = objects.subscribe_set("cars", "car/{id}/speed")
    sub.replace_policy(Policy(lower=10))
    objects.domain("cars").add(objects.reserve("car2"))
    for n in gens:
        gens[n].publish_batch([Sample(5, 1, 1), Sample(15, 2, 2)])
    assert drain(sub) == [("car1", 15), ("car2", 15)]


def test_a_pattern_without_the_identifier_is_refused(objects: ObjectManager) -> None:
    objects.add_domain("cars")
    with pytest.raises(ObjectError, match=r"has no \{id\}"):
        objects.subscribe_set("cars", "car/speed")


_member_ops = st.lists(
    st.tuples(st.sampled_from(["join", "leave", "create", "remove"]), st.integers(0, 4)),
    max_size=40,
)


@settings(max_examples=100, deadline=None)
@given(_member_ops)
def test_set_subscription_feeds_exactly_the_members_with_a_stream(
    ops: list[tuple[str, int]],
) -> None:
    instance = DyKnowInstance(clock=ManualClock())
    objects = ObjectManager(instance)
    names = [objects.reserve(f"car{i}") for i in range(5)]
    domain = objects.add_domain("cars")
    got: list[str] = []
    objects.subscribe_set("cars", "car/{id}/speed", callback=lambda i, b: got.append(i))
    for op, i in ops:
        label = f"car/{names[i]}/speed"
        if op == "join":
            domain.add(names[i])
        elif op == "leave":
            domain.discard(names[i])
        elif op == "create" and not instance.has_label(label):
            create(objects, label)
        elif op == "remove" and instance.has_label(label):
            instance.remove_stream(label)
    for n in names:
        if instance.has_label(f"car/{n}/speed"):
            instance.stream(f"car/{n}/speed").publish(1, 1, 1)
    expected = [n for n in names if n in domain and instance.has_label(f"car/{n}/speed")]
    assert sorted(got) == expected
