"""The traffic world as a node's input: what one UAV's camera sees, as messages.

``world_feed`` is a ``kind = "python"`` input (docs/application.md) for the deployments
(``deploy/config/uav-*.toml``, ``deploy/local``): it runs the demo's simulated world
(`World`) in real time (or ``speed`` times faster), looping every ``duration`` seconds of
the world, and every ``period`` (wall-clock) seconds yields

* ``{"time", "position"}``: the UAV's own position ``{"x", "y", "z"}``, metres (the
  ``heli-position`` shape of `federation.demo._vocabulary`, which the console reads);
* ``{"time", "area"}``: the area it watches, ``{"index", "polygon", "delegated-by"}``
  (``delegated-by`` None: the deployment assigns areas by name), at the start and every
  2 s;
* ``{"time", "id", "state", "speed"}`` for each car inside this UAV's area: its state
  (``x``, ``y``, ``vx``, ``vy``, ``speed``, ``colour``, ``road``, as the demo's tracker
  publishes it: the road is the map's at the seen position) and speed, observed with
  the camera's noise;
* ``{"time", "cars"}``: the same cars at that instant, ``{id: state}`` (empty when none
  is in sight): what the application's units reason over (``camera/cars``,
  `federation.demo._units`) to recognize violations;
* ``{"time", "truth"}`` when a scripted violation ends in this UAV's area: the world's
  ground truth (``kind``, ``car``, ``other``, ``x``, ``y``), to compare what the
  application recognizes with, never an input of the recognition.

``time`` is seconds since the epoch, the wall clock's when the message is yielded: at a
``speed`` over 1 the world's events come that many times sooner while the application's
windows (seconds of ``time``) stay as written, so they span that many more seconds of the
world, and the camera sees the world every ``period * speed`` simulated seconds.
"""

from __future__ import annotations

import asyncio
import math
import random
import time
from collections.abc import AsyncIterator
from typing import Any

from agents import Ticker

from ._world import World

__all__ = ["world_feed"]

AREA_PERIOD = 2.0  # s between two messages of the area (as the demo republishes it)


def _index(uav: str) -> int:
    """``uav-a`` → 0, ``uav-b`` → 1, …"""
    suffix = uav.rsplit("-", 1)[-1]
    if len(suffix) != 1 or not suffix.isalpha():
        raise ValueError(f"uav {uav!r}: expected a name like uav-a, uav-b")
    return ord(suffix.lower()) - ord("a")


async def world_feed(
    uav: str,
    *,
    seed: int = 7,
    uavs: int = 3,
    duration: float = 120.0,
    period: float = 0.2,
    noise: float = 0.5,
    speed: float = 1.0,
) -> AsyncIterator[dict[str, Any]]:
    """What ``uav``'s camera sees of the simulated world, every ``period`` s, for ever."""
    index = _index(uav)
    if isinstance(speed, bool) or not isinstance(speed, int | float):
        raise ValueError(f"speed must be a number (simulated seconds per second), not {speed!r}")
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be a positive number, not {speed}")
    if not 0 <= index < uavs:
        raise ValueError(f"uav {uav!r} is not one of the {uavs} UAVs of the world")
    world = await asyncio.to_thread(World.generate, seed, uavs, duration)
    rng = random.Random(seed * 31 + index)
    violations = [v for v in world.ground_truth() if v.end_area == index]
    area = {"index": index, "polygon": world.areas[index].polygon(), "delegated-by": None}
    area_due = 0.0
    start = time.time()
    lap = -1
    told: set[int] = set()
    ticker = Ticker(period, first=asyncio.get_running_loop().time() + period)
    while True:
        now = time.time()
        elapsed = (now - start) * speed  # of the world's time
        t = elapsed % duration
        if int(elapsed // duration) != lap:
            lap, told = int(elapsed // duration), set()
        x, y, z = world.uav_position(index, t)
        yield {"time": now, "position": {"x": round(x, 2), "y": round(y, 2), "z": round(z, 2)}}
        if now >= area_due:
            area_due = now + AREA_PERIOD
            # the UAV's top speed as the demo's UAVs give it (`heli-max-speed`)
            yield {"time": now, "area": area, "max_speed": 18.0 + 2.0 * index}
        seen: dict[str, dict[str, Any]] = {}
        for car in world.cars_at(t):
            if world.area_of(car.x, car.y) != index:
                continue
            x, y = car.x + rng.gauss(0.0, noise), car.y + rng.gauss(0.0, noise)
            state = {
                "x": round(x, 2),
                "y": round(y, 2),
                "vx": round(car.vx, 2),
                "vy": round(car.vy, 2),
                "speed": round(math.hypot(car.vx, car.vy), 2),
                "colour": car.colour,
                "road": world.road_at(x, y),  # the map at the seen position, as the demo's tracker
            }
            seen[car.id] = state
            yield {"time": now, "id": car.id, "state": state, "speed": state["speed"]}
        yield {"time": now, "cars": seen}
        for n, v in enumerate(violations):
            if n not in told and v.end <= t:
                told.add(n)
                yield {
                    "time": now,
                    "truth": {
                        "kind": v.kind,
                        "car": v.car,
                        "other": v.other,
                        "x": round(v.x, 2),
                        "y": round(v.y, 2),
                    },
                }
        await ticker.tick()
