"""A state: several streams, at different rates and delays, synchronized into one.

Run: python examples/state.py

A car's speed comes at 10 Hz (50 ms in transit), its GPS position at 2 Hz (200 ms in
transit, lost from 2 s to 3.5 s) and its on-road flag at 1 Hz, from 1 s on. A monitor
wants them together, one value per half second, all valid at the same time:

    add_state(dk, "car5/state", {"speed": ..., "pos": ..., "on_road": ...},
              StatePolicy(period=0.5, strategy="latest", max_delay=0.4, missing="skip"))

Each state holds, for every component, its newest value at or before the grid point. A
state comes out once every component has a sample past its grid point, or 0.4 s after
it, whichever is first: those at x.5 s wait for the next on-road flag, and while the GPS
is lost the states wait the 0.4 s and then take the newest position known (of 1.5 s).
Before 1 s there is no on-road flag at all: those states are skipped (missing="none"
would fill None). Time is a ManualClock moved in 50 ms steps.
"""

from __future__ import annotations

import asyncio
import heapq
from typing import Any

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, StatePolicy, add_state

MS = NS_PER_S // 1000


def sensors() -> list[tuple[int, str, Any, int]]:
    """Every sample of the drive: (available ms, label, value, valid ms)."""
    out: list[tuple[int, str, Any, int]] = []
    out += [(t + 50, "car5/speed", 40 + t / 1000, t) for t in range(0, 5001, 100)]
    out += [
        (t + 200, "car5/pos", (round(11.1 * t / 1000, 1), 0.0), t)
        for t in range(0, 5001, 500)
        if not 2000 <= t < 3500  # lost
    ]
    out += [(t + 20, "car5/on_road", t < 4000, t) for t in range(1000, 5001, 1000)]
    return out


async def run() -> dict[str, Any]:
    """Drive for 5 s; return the states and the state process's counts."""
    clock = ManualClock()
    async with DyKnowInstance("car", clock=clock) as dk:
        labels = ("car5/speed", "car5/pos", "car5/on_road")
        sources = {label: dk.add_source(label) for label in labels}
        state = add_state(
            dk,
            "car5/state",
            {"speed": "car5/speed", "pos": "car5/pos", "on_road": "car5/on_road"},
            StatePolicy(period=0.5, strategy="latest", max_delay=0.4, missing="skip"),
        )
        states: list[Any] = []
        dk.subscribe("car5/state", callback=states.extend)
        pending = sensors()
        heapq.heapify(pending)
        for now in range(0, 5600, 50):
            clock.set(now * MS)
            while pending and pending[0][0] <= now:
                _, label, value, valid = heapq.heappop(pending)
                sources[label].push(value, valid_time=valid * MS)
            await asyncio.sleep(0)  # the state's timer decides what waited its max delay
        for value, valid, available in states:
            print(f"{valid / NS_PER_S:3.1f} s (out at {available / NS_PER_S:4.2f} s): {value}")
        counts = state.stats.as_dict()
        print(counts)
        return {"states": [(v, tv / NS_PER_S, ta / NS_PER_S) for v, tv, ta in states], **counts}


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
