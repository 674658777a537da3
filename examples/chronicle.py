"""A chronicle: a pattern of events with time constraints, recognized as the events come.

Run: python examples/chronicle.py

"A car passed the crossing": it entered the crossing, then left it, at most 20 s later.
Each car's in-crossing flag is a stream (``car/<id>/incross``); its changes are events
(``events/changed/car/<id>/incross``), and the chronicle reads every car's at once: the
``{car}`` in the input label binds the chronicle's ``car``, so an enter of car1 only
pairs with a leave of car1. car1 passes in 6 s; car2 stays 25 s (no recognition: the
constraint expired); car3 passes twice. Each recognition is a sample of the stream
``chronicles/passed-crossing``, valid when the car left. Time is a ManualClock.
"""

from __future__ import annotations

import asyncio

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock
from dyknow_core.reasoning import add_chronicle

PASSED_CROSSING = {
    "name": "passed-crossing",
    "events": [
        {"name": "enter", "event": "incross", "args": ["car"], "from": False, "to": True},
        {"name": "leave", "event": "incross", "args": ["car"], "from": True, "to": False},
    ],
    "constraints": [{"start": "enter", "end": "leave", "lo": 0, "hi": 20}],
}
# (time s, car, in the crossing?) as the cars' trackers report them, in time order
TRACKS = [
    (0, "car1", False), (0, "car2", False), (0, "car3", False),
    (2, "car1", True), (5, "car2", True), (8, "car1", False), (10, "car3", True),
    (14, "car3", False), (30, "car2", False), (41, "car3", True), (50, "car3", False),
]  # fmt: skip


async def run() -> list[tuple[str, int, int]]:
    """Feed the tracks; return the recognitions as (car, entered s, left s)."""
    clock = ManualClock()
    async with DyKnowInstance("crossing", clock=clock) as dk:
        flags = {car: dk.add_source(f"car/{car}/incross") for car in ("car1", "car2", "car3")}
        for car in flags:
            dk.add_change_events(f"car/{car}/incross", "any_change")
        chronicle = add_chronicle(
            dk, PASSED_CROSSING, {"incross": "events/changed/car/{car}/incross"}
        )
        for t, car, inside in TRACKS:
            clock.set(t * NS_PER_S)
            flags[car].push(inside)
        found = []
        for s in dk.between(chronicle.label, 0, clock.now(), all_estimates=True).samples:
            r = s.value  # a Recognition
            car, enter, leave = r.bindings["car"], r.times["enter"], r.times["leave"]
            found.append((car, enter // NS_PER_S, leave // NS_PER_S))
            print("{} passed the crossing: in at {} s, out at {} s".format(*found[-1]))
        counts = chronicle.describe()
        print({k: counts[k] for k in ("events", "recognized", "partial", "expired")})
        return found


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
