"""The computational units of the deployed UAV application (``deploy/config/traffic-app.kpl``).

The KPL file holds the application; these are its CUs (``module:callable``, factories
called with the KPL arguments), each over ``camera/cars``, the camera's view of every car
in the UAV's area at one instant (``{car: state}``, fed by
`federation.demo._feed.world_feed`). They apply the demo's own definitions
(`federation.demo._traffic`), so the deployment recognizes what ``dyknow demo traffic``
recognizes:

* `tracked_cars`: the cars in sight as the console shows them (``tracked-cars``);
* `car_names` and `fast`: the speed monitor's domain and predicate;
* `relations`: one relation kind (behind, beside, beside-fast, in-front) as events
  ``{"a", "b"}`` when a pair of cars comes into it;
* `crossings`: one crossing event kind (enter, turn, pass) as ``{"car", "crossing"}``;
* `speeding`: the speed monitor's violations, as the cars that made it;
* `violations`: the chronicles' recognitions as violation records, once each.

The map (roads, speed limits, crossings) is the traffic world's of ``seed`` (what a UAV
would load as its map). An event unit publishes one event per input sample: when several
pairs change at the same instant, the others follow on the next samples (one camera
period later each), well inside the chronicles' windows.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from dyknow_core import NS_PER_S

from ._traffic import CROSSING_EVENTS, RELATIONS, RelationChanges, crossing_step, is_fast, is_repeat
from ._world import World

__all__ = ["car_names", "crossings", "fast", "relations", "speeding", "tracked_cars", "violations"]

Cars = Mapping[str, dict[str, Any]]
MAX_QUEUED = 256  # events waiting for their sample: beyond, the oldest go
RECENT = 200  # violations remembered to report each once


def _world(seed: int, uavs: int, duration: float) -> World:
    return World.generate(seed, uavs, duration)


def _cars(value: Any) -> Cars:
    if not isinstance(value, Mapping):
        raise TypeError(f"expected camera/cars as {{car: state}}, got {type(value).__name__}")
    return value


_CAR_KEYS = ("x", "y", "speed", "colour", "road")


def tracked_cars(cars: Any) -> dict[str, list[dict[str, Any]]]:
    """The cars in sight, ``{"cars": [{"id", "x", "y", "speed", "colour", "road"}]}``."""
    return {
        "cars": [
            {"id": c, **{k: s.get(k) for k in _CAR_KEYS}} for c, s in sorted(_cars(cars).items())
        ]
    }


def car_names(cars: Any) -> list[str]:
    """The cars the camera sees now: the speed monitor's domain ``Cars``."""
    return sorted(_cars(cars))


def fast(seed: int = 7, uavs: int = 3, duration: float = 120.0) -> Callable[[Any], Any]:
    """A unit: each car seen now → whether it is over 1.2 x its road's speed limit."""
    world = _world(seed, uavs, duration)

    def unit(cars: Any) -> dict[str, bool]:
        return {c: is_fast(s, world) for c, s in _cars(cars).items()}

    return unit


def relations(
    kind: str, seed: int = 7, uavs: int = 3, duration: float = 120.0
) -> Callable[[Any], Any]:
    """A unit: ``{"a", "b"}`` each time car ``a`` comes ``kind`` (e.g. behind) of car ``b``."""
    if kind not in RELATIONS:
        raise ValueError(f"kind {kind!r}: expected one of {', '.join(RELATIONS)}")
    changes = RelationChanges(_world(seed, uavs, duration))
    queue: deque[dict[str, str]] = deque(maxlen=MAX_QUEUED)

    def unit(cars: Any) -> dict[str, str] | None:
        for rel, a, b in changes.update(_cars(cars)):
            if rel == kind:
                queue.append({"a": a, "b": b})
        return queue.popleft() if queue else None

    return unit


@dataclass(slots=True)
class _Crossing:
    crossing: str | None = None
    entry_road: str | None = None
    last_road: str | None = None


def crossings(
    kind: str, seed: int = 7, uavs: int = 3, duration: float = 120.0
) -> Callable[[Any], Any]:
    """A unit: ``{"car", "crossing"}`` each time a car enters, turns in or passes a crossing."""
    if kind not in CROSSING_EVENTS:
        raise ValueError(f"kind {kind!r}: expected one of {', '.join(CROSSING_EVENTS)}")
    world = _world(seed, uavs, duration)
    memory: dict[str, _Crossing] = {}
    queue: deque[dict[str, str]] = deque(maxlen=MAX_QUEUED)

    def unit(cars: Any) -> dict[str, str] | None:
        for car, state in sorted(_cars(cars).items()):
            event = crossing_step(memory.setdefault(car, _Crossing()), state, world)
            if event is not None and event[0] == kind:
                queue.append({"car": car, "crossing": event[1]})
        return queue.popleft() if queue else None

    return unit


def speeding() -> Callable[[Any, Any], Any]:
    """A unit over (the speed monitor's verdicts, `fast`): the cars that made a violation.

    Called on either input; only a new ``False`` verdict reports, naming the cars fast
    then. A car is reported once while it stays fast, again if it speeds again later.
    """
    flagged: set[str] = set()
    last: list[Any] = [None]

    def unit(verdict: Any, fast_now: Any) -> dict[str, Any] | None:
        fast_cars = (
            {c for c, f in fast_now.items() if f} if isinstance(fast_now, Mapping) else set()
        )
        flagged.intersection_update(fast_cars)
        if verdict is last[0]:
            return None  # a new `fast`, not a new verdict
        last[0] = verdict
        if not isinstance(verdict, Mapping) or verdict.get("verdict") is not False:
            return None
        cars = sorted(fast_cars - flagged)
        flagged.update(cars)
        return {"kind": "speeding", "cars": cars} if cars else None

    return unit


def violations() -> Callable[[Any], Any]:
    """A unit over the state ``{cars, <chronicle>: latest recognition, …}``: violation records.

    Each recognition becomes ``{"kind", "car", "other", "start", "end", "x", "y"}``, once:
    ``kind`` the chronicle's name with ``-`` for ``_`` (``reckless-overtake``), times in
    seconds since the epoch (an overtake starts when the cars are beside), x, y where the
    camera saw ``car`` last. A recognition repeating one reported (same cars, ending
    within 20 s: an overtake also seen as reckless) is left out, as in the demo.
    """
    done: deque[Any] = deque(maxlen=RECENT)
    found: deque[dict[str, Any]] = deque(maxlen=RECENT)
    queue: deque[dict[str, Any]] = deque(maxlen=MAX_QUEUED)

    def unit(state: Any) -> dict[str, Any] | None:
        if not isinstance(state, Mapping):
            raise TypeError(f"expected a state mapping, got {type(state).__name__}")
        cars = state.get("cars") or {}
        new = [r for k, r in state.items() if k != "cars" and r is not None and r not in done]
        # reckless first: the same overtake seen as both is reported once, as reckless
        new.sort(key=lambda r: "reckless" not in str(r[0]))
        for rec in new:
            done.append(rec)
            chronicle, bindings, times = rec
            name = str(chronicle).replace("_", "-")
            car, other = bindings.get("a", bindings.get("car")), bindings.get("b")
            end = max(times.values()) / NS_PER_S
            start = (times["beside"] if "beside" in times else min(times.values())) / NS_PER_S
            if is_repeat(found, name, car, other, end):
                continue
            where = cars.get(car, {}) if isinstance(cars, Mapping) else {}
            value = {
                "kind": name,
                "car": car,
                "other": other,
                "start": round(start, 2),
                "end": round(end, 2),
                "x": where.get("x"),
                "y": where.get("y"),
            }
            found.append(value)
            queue.append(value)
        return queue.popleft() if queue else None

    return unit
