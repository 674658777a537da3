"""Computational units: processes that compute a stream from other streams, as they change.

Run: python examples/cu.py

A weather station publishes its temperature (°C) and wind speed (m/s) once a second.
Two units compute from them:

    wx/wind ──(bounds 0..60 m/s)──► kmh ──► wx/wind_kmh ─┐
    wx/temperature ─────────────────────────────────────┴─► chill ──► wx/wind_chill

``kmh`` has one input, read through a policy that drops the sensor's error code (-1).
``chill`` has two: it runs each time either emits, once both have a value, with the
latest value of each; its output is valid when the sample that triggered it is, and
returning None (too warm for a wind chill) emits nothing. At 2 s the thermometer sends
None: ``chill`` raises, the sample is skipped, the failure is recorded, and it goes on.
"""

from __future__ import annotations

import asyncio
from typing import Any

from dyknow_core import NS_PER_S, DyKnowInstance, Input, ManualClock, Policy

# (temperature °C, wind m/s) each second; None: no reading, -1: the anemometer's error code
READINGS = [(5.0, 5.0), (12.0, 5.0), (None, 6.0), (2.0, -1.0), (0.0, 10.0)]


def wind_chill(temperature: float, wind_kmh: float) -> float | None:
    """The felt temperature (°C), or None where the formula does not apply."""
    if temperature > 10.0 or wind_kmh <= 4.8:
        return None
    v = wind_kmh**0.16
    return round(13.12 + 0.6215 * temperature - 11.37 * v + 0.3965 * temperature * v, 1)


async def run() -> dict[str, Any]:
    """Feed the readings; return the units' outputs and failures."""
    clock = ManualClock()
    async with DyKnowInstance("station", clock=clock) as dk:
        temperature = dk.add_source("wx/temperature")
        wind = dk.add_source("wx/wind")
        dk.add_cu(
            "kmh",
            lambda v: round(v * 3.6, 1),
            [Input("wx/wind", Policy(lower=0, upper=60))],
            "wx/wind_kmh",
        )
        chill = dk.add_cu("chill", wind_chill, ["wx/temperature", "wx/wind_kmh"], "wx/wind_chill")
        outputs: dict[str, list[Any]] = {"wx/wind_kmh": [], "wx/wind_chill": []}
        for label, got in outputs.items():
            dk.subscribe(label, callback=got.extend)

        for second, (t, w) in enumerate(READINGS):
            clock.set(second * NS_PER_S)
            temperature.push(t)
            wind.push(w)

        for label, got in outputs.items():
            shown = ", ".join(f"{v} at {tv // NS_PER_S} s" for v, tv, _ in got)
            print(f"{label}: {shown}")
        for failure in dk.failures:
            print(f"failure of {failure.process} at {failure.time // NS_PER_S} s: {failure.error}")
        print(f"chill: {chill.errors} samples skipped, still running: {chill.running}")
        return {
            label: [(v, tv // NS_PER_S) for v, tv, _ in got] for label, got in outputs.items()
        } | {"failures": [f.process for f in dk.failures]}


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
