"""Anchoring: percepts become objects, objects join and leave classes as constraints hold.

Run: python examples/anchoring.py

A camera reports blobs once a second (``{"b1": {"pixel": (x, y), "confidence": c}}``).

    VisionObject  created for a blob seen with confidence > 0.5
        │ link vo2wo: computes its WorldObject's position (0.5 m per pixel) and on_road
        ▼
    WorldObject   pos, on_road
        │ subclass OnRoadObject: joined after 10 s on the road (always[0,10] on_road),
        ▼ left once off it for a whole 5 s window (maintain eventually[0,5] on_road)
    OnRoadObject

b1 is a car on the road that drives off it at 30 s; b2 is too faint to be anything. The
anchoring process steps once a second on the instance's (manual) clock and publishes
what changed on ``events/anchoring``.
"""

from __future__ import annotations

import asyncio
from typing import Any

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock
from dyknow_core.reasoning import LinkType, ObjectClass, add_anchoring

VISION = ObjectClass(
    name="VisionObject",
    features={"pixel": "vo/{id}/pixel", "confidence": "vo/{id}/confidence"},
    create="confidence > 0.5",
    create_from="blobs",
)
WORLD = ObjectClass(
    name="WorldObject", features={"pos": "wo/{id}/pos", "on_road": "wo/{id}/on_road"}
)
ON_ROAD = ObjectClass(
    name="OnRoadObject",
    base="WorldObject",
    add="always[0,10] on_road",
    maintain="eventually[0,5] on_road",
)


def to_world(vo: dict[str, Any]) -> dict[str, Any] | None:
    """A world object's features from its vision object's (a toy camera: 0.5 m per pixel)."""
    if vo["pixel"] is None:
        return None
    x, y = vo["pixel"][0] * 0.5, vo["pixel"][1] * 0.5
    return {"pos": (x, y), "on_road": 0 <= y <= 10}


VO2WO = LinkType(
    name="vo2wo",
    from_class="VisionObject",
    to_class="WorldObject",
    establish="confidence > 0.5",
    maintain="a_confidence > 0.2",
    compute=to_world,
)


def blobs(s: int) -> dict[str, Any]:
    """What the camera sees at ``s`` seconds."""
    y = 8.0 if s < 30 else 80.0  # b1 drives off the road at 30 s
    return {
        "b1": {"pixel": (2.0 * s, y), "confidence": 0.9},
        "b2": {"pixel": (40.0, 3.0), "confidence": 0.2},
    }


async def run() -> list[tuple[int, str, str, str]]:
    """Watch for 40 s; return the anchoring events as (s, event, class or link, id)."""
    clock = ManualClock()
    async with DyKnowInstance("uav", clock=clock) as dk:
        camera = dk.add_source("blobs")
        anchoring = add_anchoring(dk, [VISION, WORLD, ON_ROAD], [VO2WO], period=1.0)
        for s in range(41):
            t = s * NS_PER_S
            camera.push(blobs(s), valid_time=t)
            clock.set(t)
            # the process steps in its own task; a step that changes nothing publishes nothing
            while anchoring.last_step is None or anchoring.last_step < t:  # noqa: ASYNC110
                await asyncio.sleep(0)
        events = []
        for e in dk.between("events/anchoring", 0, clock.now(), all_estimates=True).samples:
            what = e.value.get("class") or e.value.get("link")
            who = e.value.get("id") or f"{e.value.get('from')} -> {e.value.get('to')}"
            events.append((e.valid_time // NS_PER_S, e.value["event"], what, who))
            print("{:2d} s  {:<8} {:<13} {}".format(*events[-1]))
        print(f"on the road now: {sorted(anchoring.members('OnRoadObject')) or 'nothing'}")
        return events


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
