"""Classes and links (anchoring): membership, links, codesignation and the scenario's chain."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from dyknow_core import DyKnowInstance, ManualClock, PolicyError, Source
from dyknow_core._time import NS_PER_S
from dyknow_core.reasoning import Anchoring, LinkType, ObjectClass, add_anchoring

Feed = Callable[[int], None]


async def settle(anch: Anchoring, t: int) -> None:
    """Let the anchoring task run until it has stepped at ``t`` (bounded, no sleeping)."""
    for _ in range(200):
        if anch.last_step is not None and anch.last_step >= t:
            return
        await asyncio.sleep(0)
    raise AssertionError(f"anchoring did not step at {t}")


async def run(clock: ManualClock, anch: Anchoring, seconds: int, feed: Feed | None = None) -> None:
    """Advance one second at a time, feeding the sensors at each new time first."""
    for _ in range(seconds):
        t = clock.now() + NS_PER_S
        if feed is not None:
            feed(t)
        clock.set(t)
        await settle(anch, t)


def events(dk: DyKnowInstance, kind: str) -> list[dict[str, Any]]:
    """The anchoring events of one kind published so far."""
    answer = dk.between("events/anchoring", 0, 10**15, all_estimates=True)
    return [s.value for s in answer.samples if s.value["event"] == kind]


@pytest.fixture
async def world() -> AsyncIterator[tuple[DyKnowInstance, ManualClock]]:
    clock = ManualClock()
    async with DyKnowInstance("anchoring", clock=clock) as dk:
        yield dk, clock


ON_ROAD = ObjectClass(
    name="OnRoadObject",
    base="WorldObject",
    add="always[0,10] on_road",
    maintain="eventually[0,5] on_road",
)


async def test_on_road_timing_join_survive_gap_and_leave(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    dk, clock = world
    wo = ObjectClass(name="WorldObject", features={"on_road": "wo/{id}/on_road"})
    road = dk.add_source("wo/wo1/on_road")
    anch = add_anchoring(dk, [wo, ON_ROAD])
    dk.objects.reserve("wo1")
    dk.objects.domain("WorldObject").add("wo1")
    off = set(range(20, 23)) | set(range(40, 60))  # a 3 s gap, then off for good

    def feed(t: int) -> None:
        road.push(t // NS_PER_S not in off, valid_time=t)

    feed(0)
    await settle(anch, 0)
    await run(clock, anch, 9, feed)
    assert "wo1" not in anch.members("OnRoadObject")  # 9 s on the road is not enough
    await run(clock, anch, 1, feed)
    assert "wo1" in anch.members("OnRoadObject")  # t = 10: on the road for [0, 10]
    await run(clock, anch, 29, feed)  # through the 3 s gap, up to t = 39
    assert "wo1" in anch.members("OnRoadObject")
    await run(clock, anch, 5, feed)  # t = 44: off the road for 4 s
    assert "wo1" in anch.members("OnRoadObject")
    await run(clock, anch, 1, feed)  # t = 45: off over a whole 5 s window
    assert "wo1" not in anch.members("OnRoadObject")
    assert "wo1" in anch.members("WorldObject")  # leaving a subclass keeps the base
    joined = [e for e in events(dk, "joined") if e["class"] == "OnRoadObject"]
    left = [e for e in events(dk, "left") if e["class"] == "OnRoadObject"]
    assert [e["id"] for e in joined] == ["wo1"] and [e["id"] for e in left] == ["wo1"]
    changes = dk.between("domain/OnRoadObject", 0, 10**15).samples
    assert [(c.value.kind, c.valid_time // NS_PER_S) for c in changes] == [
        ("added", 10),
        ("removed", 45),
    ]


def to_world(pixel: tuple[float, float]) -> tuple[float, float]:
    """A toy camera model: 0.5 m per pixel."""
    return (pixel[0] * 0.5, pixel[1] * 0.5)


def compute_world(vo: dict[str, Any]) -> dict[str, Any] | None:
    """A world object's features from its vision object's: position and on-road."""
    if vo["pixel"] is None:
        return None
    pos = to_world(vo["pixel"])
    return {"pos": pos, "on_road": 0 <= pos[1] <= 10}


VISION = ObjectClass(
    name="VisionObject",
    features={"pixel": "vo/{id}/pixel", "confidence": "vo/{id}/confidence"},
    create="confidence > 0.5",
    create_from="blobs",
)
WORLD = ObjectClass(
    name="WorldObject", features={"pos": "wo/{id}/pos", "on_road": "wo/{id}/on_road"}
)
VO_WO = LinkType(
    name="vo2wo",
    from_class="VisionObject",
    to_class="WorldObject",
    establish="confidence > 0.5",
    maintain="a_confidence > 0.2",
    compute=compute_world,
)


async def test_create_and_establish_compute_features_then_maintain_unlinks(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    dk, clock = world
    blobs = dk.add_source("blobs")
    anch = add_anchoring(dk, [VISION, WORLD], [VO_WO])
    conf = {"b7": 0.9}

    def feed(t: int) -> None:
        s = t // NS_PER_S
        blobs.push({"b7": {"pixel": (10.0 * s, 8.0), "confidence": conf["b7"]}}, valid_time=t)

    blobs.push({"b7": {"pixel": (0.0, 8.0), "confidence": 0.3}}, valid_time=0)  # too unsure
    await settle(anch, 0)
    assert anch.members("VisionObject") == frozenset()
    await run(clock, anch, 2, feed)
    vo = anch.identifier_of("VisionObject", "b7")
    assert vo == "visionobject1" and vo in anch.members("VisionObject")
    [(lt, f, wo)] = anch.linked(vo)
    assert (lt, f) == ("vo2wo", vo) and wo in anch.members("WorldObject")
    assert dk.latest(f"vo/{vo}/pixel").latest.value == (20.0, 8.0)
    assert anch.features("WorldObject", wo) == {"pos": (10.0, 4.0), "on_road": True}
    conf["b7"] = 0.1
    await run(clock, anch, 1, feed)
    assert anch.linked(vo) == []  # the link is gone ...
    assert vo in anch.members("VisionObject") and wo in anch.members("WorldObject")  # not them
    assert [(e["from"], e["to"]) for e in events(dk, "unlinked")] == [(vo, wo)]
    await run(clock, anch, 1, feed)
    assert anch.features("WorldObject", wo)["pos"] == (10.0, 4.0)  # no longer computed


def close(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Two tracks are close when their x differs by less than 1 m."""
    return a["x"] is not None and b["x"] is not None and abs(a["x"] - b["x"]) < 1


async def _tracks(
    dk: DyKnowInstance, mode: str
) -> tuple[Anchoring, Source, Source, Callable[[int], None], dict[str, float]]:
    track = ObjectClass(
        name="Track",
        features={"x": "trk/{id}/x", "color": "trk/{id}/color"},
        codesignate="always[0,2] close",
        codesignation=mode,
        relations={"close": close},
    )
    x1, x2 = dk.add_source("trk/trk1/x"), dk.add_source("trk/trk2/x")
    color = dk.add_source("trk/trk2/color")
    anch = add_anchoring(dk, [track])
    for ident in ("trk1", "trk2"):
        dk.objects.reserve(ident)
        dk.objects.domain("Track").add(ident)
    gap = {"d": 0.5}

    def feed(t: int) -> None:
        x1.push(float(t // NS_PER_S), valid_time=t)
        x2.push(t // NS_PER_S + gap["d"], valid_time=t)

    feed(0)
    color.push("red", valid_time=0)
    await settle(anch, 0)
    return anch, x1, x2, feed, gap


async def test_codesignation_once_fuses_for_good(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    dk, clock = world
    anch, _, _, feed, gap = await _tracks(dk, "once")
    await run(clock, anch, 1, feed)
    assert anch.members("Track") == {"trk1", "trk2"}  # close for 1 s only
    await run(clock, anch, 1, feed)  # t = 2: close over [0, 2]
    assert anch.members("Track") == {"trk1"}
    assert anch.fused_with("Track", "trk1") == {"trk1", "trk2"}
    merged = anch.features("Track", "trk1")
    assert merged == {"x": 2.0, "color": "red"}  # equal times: trk1 wins; trk2 has color
    gap["d"] = 50.0
    await run(clock, anch, 3, feed)
    assert anch.fused_with("Track", "trk1") == {"trk1", "trk2"}  # once: for good
    assert [e["ids"] for e in events(dk, "codesignated")] == [["trk1", "trk2"]]


async def test_codesignation_continuous_separates_when_it_fails(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    dk, clock = world
    anch, _, _, feed, gap = await _tracks(dk, "continuous")
    await run(clock, anch, 2, feed)
    assert anch.members("Track") == {"trk1", "trk2"}  # both stay members
    assert anch.fused_with("Track", "trk1") == {"trk1", "trk2"}
    assert anch.features("Track", "trk1")["color"] == "red"
    gap["d"] = 50.0
    await run(clock, anch, 1, feed)
    assert anch.fused_with("Track", "trk1") == {"trk1"}
    assert anch.features("Track", "trk1")["color"] is None
    assert [e["ids"] for e in events(dk, "separated")] == [["trk1", "trk2"]]


async def test_the_scenario_chain(world: tuple[DyKnowInstance, ManualClock]) -> None:
    dk, clock = world
    blobs = dk.add_source("blobs")
    car = ObjectClass(name="Car", features={"pos": "car/{id}/pos"})
    to_car = LinkType(
        name="onroad2car",
        from_class="OnRoadObject",
        to_class="Car",
        establish="true",
        compute=lambda f: {"pos": f["pos"]},
    )
    anch = add_anchoring(dk, [VISION, WORLD, ON_ROAD, car], [VO_WO, to_car])

    def feed(t: int) -> None:
        s = t // NS_PER_S
        y = 8.0 if s < 30 else 80.0  # drives off the road at t = 30
        blobs.push({"b1": {"pixel": (2.0 * s, y), "confidence": 0.9}}, valid_time=t)

    feed(0)
    await settle(anch, 0)
    vo = anch.identifier_of("VisionObject", "b1")
    assert vo is not None
    [(_, _, wo)] = anch.linked(vo)
    await run(clock, anch, 10, feed)
    assert wo in anch.members("OnRoadObject")  # on the road over [0, 10]
    assert anch.members("Car") == frozenset()  # the link is established on the next step
    await run(clock, anch, 1, feed)
    [(cr,)] = [(to,) for lt, f, to in anch.linked(wo) if lt == "onroad2car"]
    assert cr in anch.members("Car")
    assert anch.features("Car", cr)["pos"] == (11.0, 4.0)  # from the pixels, through wo
    await run(clock, anch, 24, feed)  # t = 35: off the road over [30, 35]
    assert wo not in anch.members("OnRoadObject")
    assert not [x for x in anch.linked(wo) if x[0] == "onroad2car"]  # link gone with it
    assert cr in anch.members("Car") and wo in anch.members("WorldObject")
    assert anch.describe()["steps"] == 36


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"name": "Bad name"}, "name"),
        ({"name": "C", "features": {"pixel": "vo/pixel"}}, "features.pixel"),
        ({"name": "C", "add": "on_road"}, "add"),
        ({"name": "C", "base": "B", "add": "always[0,10 on_road"}, "add"),
        ({"name": "C", "create": "p"}, "create_from"),
        ({"name": "C", "codesignation": "sometimes"}, "codesignation"),
        ({"name": "C", "colour": 1}, "colour"),
    ],
)
def test_bad_classes_are_refused_naming_the_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(PolicyError) as err:
        ObjectClass(**kwargs)
    assert err.value.field == field


async def test_bad_models_are_refused_naming_the_field(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    dk, _ = world
    with pytest.raises(PolicyError) as err:
        LinkType(name="l", from_class="A", to_class="A")
    assert err.value.field == "to_class"
    a = ObjectClass(name="A")
    with pytest.raises(PolicyError) as err:
        add_anchoring(dk, [a], [LinkType(name="l", from_class="A", to_class="B")])
    assert err.value.field == "links.0.to_class"
    with pytest.raises(PolicyError) as err:
        add_anchoring(dk, [ObjectClass(name="S", base="A"), a])
    assert err.value.field == "classes.0.base"
    with pytest.raises(PolicyError) as err:
        add_anchoring(dk, [a], period=0)
    assert err.value.field == "period"
    assert not dk.has_label("events/anchoring")  # nothing was set up


async def test_reestablish_relinks_existing_objects_and_removal_cleans_up(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    dk, clock = world
    blobs = dk.add_source("blobs")
    link = VO_WO.model_copy(update={"reestablish": "a_confidence > 0.5 and b_on_road"})
    anch = add_anchoring(dk, [VISION, WORLD], [link])
    conf = {"b7": 0.9}

    def feed(t: int) -> None:
        blobs.push({"b7": {"pixel": (4.0, 8.0), "confidence": conf["b7"]}}, valid_time=t)

    feed(0)
    await settle(anch, 0)
    vo = anch.identifier_of("VisionObject", "b7")
    assert vo is not None
    [(_, _, wo)] = anch.linked(vo)
    conf["b7"] = 0.1
    await run(clock, anch, 1, feed)
    assert anch.linked(vo) == []
    conf["b7"] = 0.9
    await run(clock, anch, 1, feed)
    assert anch.linked(vo) == [("vo2wo", vo, wo)]  # the same world object, not a new one
    assert anch.members("WorldObject") == {wo}
    # the scheduler catches up when the clock jumps several periods at once
    feed(5 * NS_PER_S)
    clock.set(5 * NS_PER_S)
    await settle(anch, 5 * NS_PER_S)
    assert anch.steps == 6
    dk.remove_process("anchoring")
    assert not dk.has_label("events/anchoring") and not dk.has_label(f"wo/{wo}/pos")
    clock.set(6 * NS_PER_S)
    for _ in range(5):
        await asyncio.sleep(0)
    assert anch.steps == 6


async def test_a_late_anchoring_catches_up_one_step_per_loop_turn(
    world: tuple[DyKnowInstance, ManualClock],
) -> None:
    # After a jump of the clock the missed grid points are stepped one per turn of the
    # event loop: a producer beside it (a camera feeding it) keeps its pace meanwhile
    # instead of waiting for the whole catch-up.
    dk, clock = world
    wo = ObjectClass(name="WorldObject", features={"on_road": "wo/{id}/on_road"})
    anch = add_anchoring(dk, [wo, ON_ROAD])
    await run(clock, anch, 1)
    turns: list[int] = []  # the anchoring's step count at each of the producer's turns

    async def producer() -> None:
        while True:
            turns.append(anch.steps)
            await asyncio.sleep(0)

    task = asyncio.create_task(producer())
    try:
        await asyncio.sleep(0)  # the producer is running
        before = anch.steps
        clock.set(clock.now() + 20 * NS_PER_S)
        await settle(anch, clock.now())
        assert anch.steps == before + 20  # every missed grid point stepped, none twice
        await asyncio.sleep(0)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    per_turn = [b - a for a, b in itertools.pairwise(turns)]
    assert sum(per_turn) == 20 and max(per_turn) == 1, per_turn
