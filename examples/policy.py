"""A policy: what a subscriber asks of a stream, and what the policy drops or fills to give it.

Run: python examples/policy.py

A thermometer reads every 0.25 s for 6 s (the reading of t s is 20 + t degrees, so a
value tells which reading it is). Two readings spend 0.7 s in transit, one arrives after
a newer one, and from 2.5 s to 4.25 s the sensor is silent. A display subscribes with

    Policy(sample_period=1.0, approximation="closest", max_delay=0.5,
           order="monotone", late="approximate")

one value a second, on the grid 0, 1, 2, ... s, never more than 0.5 s late. The policy
drops the late readings and the one out of order; each grid point takes the closest
reading; at 3 s no reading came within 0.5 s, so the closest one known then (2.25 s)
stands in (late="approximate"; late="drop" would leave 3 s out). Time is a ManualClock.
"""

from __future__ import annotations

import asyncio
from typing import Any

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, Policy

MS = NS_PER_S // 1000
PERIOD_MS = 250
DELAY_MS = {3: 700, 21: 700, 5: 350}  # reading k's time in transit (else 50 ms); 5 overtaken
SILENT = range(10, 17)  # 2.5 s to 4.0 s: no reading


def readings() -> list[tuple[float, int, int]]:
    """The thermometer's samples: (value, valid time, available time), in ns."""
    return [
        (20 + k * PERIOD_MS / 1000, k * PERIOD_MS * MS, (k * PERIOD_MS + DELAY_MS.get(k, 50)) * MS)
        for k in range(25)
        if k not in SILENT
    ]


async def run() -> dict[str, Any]:
    """Publish the readings as they arrive; return what the display got and why."""
    clock = ManualClock()
    async with DyKnowInstance("thermo", clock=clock) as dk:
        thermometer = dk.add_source("temperature")
        everything: list[Any] = []
        dk.subscribe("temperature", callback=everything.extend)  # no policy: every reading
        display: list[Any] = []
        policy = Policy(
            sample_period=1.0, approximation="closest", max_delay=0.5, order="monotone",
            late="approximate",
        )  # fmt: skip
        sub = dk.subscribe("temperature", policy, callback=display.extend)
        pending = sorted(readings(), key=lambda s: s[2])
        for now in range(0, 6600 * MS, 50 * MS):  # the clock moves in 50 ms steps
            clock.set(now)
            while pending and pending[0][2] <= now:
                thermometer.push_batch([pending.pop(0)])
            await asyncio.sleep(0)  # the ticker decides grid points whose max delay passed
        print(f"{len(everything)} readings published; the display got one a second:")
        for value, valid, available in display:
            print(
                f"  {valid / NS_PER_S:3.0f} s: {value:5.2f} °C (the reading of {value - 20:4.2f} s,"
                f" decided at {available / NS_PER_S:4.2f} s)"
            )
        stats = sub.stats()
        print(
            f"dropped: {stats['dropped_late']} late, {stats['dropped_order']} out of order; "
            f"approximated: {stats['approximated']}"
        )
        return {"published": len(everything), "display": display, "stats": stats}


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
