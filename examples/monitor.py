"""A monitor: a metric temporal logic formula checked over a stream of states, as it comes.

Run: python examples/monitor.py

A car's speed (km/h) and on-road flag come once a second for 40 s. The monitor checks

    always[0,10](speed < 30 -> eventually[0,5] on_road)

"for 10 s, whenever the car is slow, it is on the road within 5 s". It synchronizes the
two streams into a state (one a second), progresses the formula over each state, and
publishes a verdict as soon as it is certain, then starts again from the next state, so
every violation is reported. The car slows down twice and leaves the road each time:
for 3 s (back in time: no violation), then for 7 s (a violation, reported at the state
that made it certain, 5 s after leaving). Time is a ManualClock.
"""

from __future__ import annotations

import asyncio
from typing import Any

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock
from dyknow_core.reasoning import add_monitor

FORMULA = "always[0,10](speed < 30 -> eventually[0,5] on_road)"
SLOW = range(12, 21), range(26, 36)  # s
OFF_ROAD = range(14, 17), range(28, 35)  # s


async def run() -> list[tuple[bool, int, int]]:
    """Drive; return the verdicts as (verdict, decided at s, start of the checked run s)."""
    clock = ManualClock()
    async with DyKnowInstance("car", clock=clock) as dk:
        speed, on_road = dk.add_source("car5/speed"), dk.add_source("car5/on_road")
        monitor = add_monitor(
            dk, FORMULA, components={"speed": "car5/speed", "on_road": "car5/on_road"}, period=1.0
        )
        verdicts: list[Any] = []
        dk.subscribe(monitor.label, callback=verdicts.extend)
        for t in range(41):
            clock.set(t * NS_PER_S)
            speed.push(20.0 if any(t in r for r in SLOW) else 50.0)
            on_road.push(not any(t in r for r in OFF_ROAD))
        out = []
        for value, valid, _ in verdicts:
            decided, start = valid // NS_PER_S, value["start"] // NS_PER_S
            word = "holds" if value["verdict"] else "VIOLATED"
            print(f"{decided:2d} s: {word} for the 10 s from {start} s")
            out.append((value["verdict"], decided, start))
        return out


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
