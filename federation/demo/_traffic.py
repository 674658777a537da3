"""The traffic reasoning both UAV applications share: relations, crossings, speed, chronicles.

The demo's UAV (`federation.demo._uav`) and the deployed application
(``deploy/config/traffic-app.kpl`` with its units in `federation.demo._units`) recognize
violations with the same definitions, kept here once:

* the qualitative relation between two cars' states (`relation`: behind, beside,
  beside-fast, in-front), published when it changes (`RelationChanges`);
* a car entering a crossing and leaving it on another road (turn) or the same (pass)
  (`crossing_step`);
* a car is fast when over `FAST` x its road's speed limit (`is_fast`), and the speed
  monitor `SPEEDING` says when one stays fast for 2 s;
* the chronicles over those events (`CHRONICLES`: overtake, reckless overtake, turn).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from ._world import World

__all__ = [
    "BESIDE",
    "CHRONICLES",
    "CROSSING_EVENTS",
    "FAST",
    "NEAR",
    "OTHER_LANE",
    "RELATIONS",
    "SAME_LANE",
    "SPEEDING",
    "RelationChanges",
    "crossing_step",
    "far",
    "is_fast",
    "is_repeat",
    "relation",
]

FAST = 1.2  # beside at more than FAST x the speed limit: reckless
SAME_LANE, OTHER_LANE = 1.5, (2.0, 6.0)  # lateral offsets, m
NEAR = (6.0, 40.0)  # longitudinal gap for behind / in front, m
BESIDE = 10.0  # |dx| below which two cars in different lanes are beside
SPEEDING = "always not (exists c in Cars: always[0,2] fast(c))"
"""The UAV's temporal-logic monitor: no car over FAST x its road's limit for 2 s."""
RELATIONS = ("behind", "beside", "beside-fast", "in-front")
CROSSING_EVENTS = ("enter", "turn", "pass")

_OVERTAKE = {
    "events": [
        {"name": "behind", "event": "behind", "args": ["a", "b"]},
        {"name": "beside", "event": "beside", "args": ["a", "b"]},
        {"name": "ahead", "event": "ahead", "args": ["a", "b"]},
    ],
    "constraints": [
        {"start": "behind", "end": "beside", "lo": 0, "hi": 20},
        {"start": "beside", "end": "ahead", "lo": 0, "hi": 15},
    ],
}
CHRONICLES: dict[str, tuple[dict[str, Any], dict[str, str]]] = {
    "overtake": (
        {"name": "overtake", **_OVERTAKE},
        {"behind": "relations/behind", "beside": "relations/beside", "ahead": "relations/in-front"},
    ),
    "reckless-overtake": (
        {"name": "reckless-overtake", **_OVERTAKE},
        {
            "behind": "relations/behind",
            "beside": "relations/beside-fast",
            "ahead": "relations/in-front",
        },
    ),
    "turn": (
        {
            "name": "turn",
            "events": [
                {"name": "enter", "event": "enter", "args": ["car", "crossing"]},
                {"name": "turn", "event": "turn", "args": ["car", "crossing"]},
            ],
            "constraints": [{"start": "enter", "end": "turn", "lo": 0, "hi": 30}],
        },
        {"enter": "crossing/enter", "turn": "crossing/turn"},
    ),
}
"""The chronicles each UAV recognizes: definition and inputs (event name → label)."""


def is_fast(state: dict[str, Any], world: World) -> bool:
    """Whether a car's state is over `FAST` x its road's speed limit."""
    road = state.get("road")
    return road is not None and state["speed"] > FAST * world.speed_limit(road)


def relation(a: dict[str, Any], b: dict[str, Any], fast: bool) -> str | None:
    """Where car ``a`` is relative to ``b`` (``fast``: ``a`` is fast), or None."""
    dx, lat = a["x"] - b["x"], abs(a["y"] - b["y"])
    if lat < SAME_LANE:
        if -NEAR[1] < dx < -NEAR[0]:
            return "behind"
        if NEAR[0] < dx < NEAR[1]:
            return "in-front"
        return None
    if OTHER_LANE[0] < lat < OTHER_LANE[1] and abs(dx) < BESIDE:
        return "beside-fast" if fast else "beside"
    return None


def far(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two cars are too far apart for their last relation to matter."""
    return abs(a["x"] - b["x"]) > 2 * NEAR[1] or abs(a["y"] - b["y"]) > 2 * OTHER_LANE[1]


class RelationChanges:
    """The relations between eastbound cars and the others, reported as they change."""

    __slots__ = ("current", "world")

    def __init__(self, world: World) -> None:
        self.world = world
        self.current: dict[tuple[str, str], str] = {}

    def update(self, cars: Mapping[str, dict[str, Any]]) -> list[tuple[str, str, str]]:
        """The (relation, a, b) that hold now and did not before, in a stable order."""
        out: list[tuple[str, str, str]] = []
        names = sorted(cars)
        current = self.current
        for a in names:
            sa = cars[a]
            if sa["vx"] <= 0:
                continue
            fast = is_fast(sa, self.world)
            for b in names:
                if a == b:
                    continue
                sb = cars[b]
                rel = relation(sa, sb, fast)
                key = (a, b)
                if rel == current.get(key) or rel is None:
                    if rel is None and key in current and far(sa, sb):
                        del current[key]
                    continue
                current[key] = rel
                out.append((rel, a, b))
        return out


class CrossingMemory(Protocol):
    """What `crossing_step` remembers of one car."""

    crossing: str | None
    entry_road: str | None
    last_road: str | None


def crossing_step(
    memory: CrossingMemory, state: dict[str, Any], world: World
) -> tuple[str, str] | None:
    """The crossing event (kind, crossing) of a car's new state, if any; updates ``memory``."""
    event = None
    here = world.crossing_at(state["x"], state["y"])
    if here is not None and memory.crossing is None:
        memory.crossing, memory.entry_road = here, memory.last_road
        event = ("enter", here)
    elif here is None and memory.crossing is not None:
        # first seen inside the crossing: where it came from is unknown
        if memory.entry_road is not None and state["road"] is not None:
            event = ("turn" if state["road"] != memory.entry_road else "pass", memory.crossing)
        memory.crossing = None
    if here is None and state["road"] is not None:
        memory.last_road = state["road"]
    return event


def is_repeat(
    found: Any, kind: str, car: Any, other: Any, end: float, *, end_key: str = "end"
) -> bool:
    """Whether a recognition was reported already: same cars, ending within 20 s.

    A reckless overtake is also seen as an overtake when noise makes the beside slow:
    reported once, as reckless (recognitions reckless first). ``found``: the violations
    so far, each with ``kind``, ``car``, ``other`` and its end (seconds) under ``end_key``.
    """
    return any(
        v["car"] == car and v["other"] == other and abs(v[end_key] - end) < 20
        for v in found
        if v["kind"] in (kind, "reckless-overtake")
    )
