"""A local DyKnow pipeline to watch: a simulated car's sensors, policies, CUs, a live table.

Run it with ``python examples/local_pipeline.py [--fast]``. It drives a
car for 40 s of simulated time in about 10 s of real time, then queries what the
instance knows and prints its per-stream metrics::

    car5/speed     (source, 10 Hz, noisy, glitches, delayed)
        │ policy: bounds [0, 250] km/h, max delay 0.3 s, monotone valid time
        ▼
    CU smoother ──► car5/speed_smooth ──► CU speeding ──► car5/speeding
                        │ policy: one sample per 1 s, linear      │ policy: any change
                        ▼                                         ▼
                    the table below                          the ⚠ lines

    car5/position  (source, 10 Hz GPS, lost in a tunnel from 24 s to 29 s)
        │ policy: one sample per 1 s, closest, max delay 0.5 s, late ones approximated
        ▼
    CU odometer ──► car5/odometer

Time is a ManualClock the simulation moves, and the noise comes from a seeded random
generator, so every run prints the same thing.
"""

from __future__ import annotations

import argparse
import asyncio
import heapq
import itertools
import math
import random
from collections.abc import Callable
from typing import Any

from dyknow_core import (
    NS_PER_S,
    Approximation,
    DyKnowInstance,
    Input,
    ManualClock,
    Policy,
    Sample,
    Source,
    Subscription,
    ns_to_seconds,
    seconds_to_ns,
)

SEED = 5
DRIVE_S = 40.0
TICK_S = 0.1  # both sensors sample at 10 Hz
SPEED_LIMIT_KMH = 50.0
TUNNEL_S = (24.0, 29.0)  # no GPS fix in here
# (time s, km/h) corners of the speed profile: start, cruise, speed up past the limit, slow down
PROFILE = [(0, 0), (8, 45), (16, 45), (22, 62), (30, 62), (36, 40), (DRIVE_S, 40)]


def true_speed(t: float) -> float:
    """The speed the car really has at ``t`` (km/h): what the sensor tries to measure."""
    for (t0, v0), (t1, v1) in itertools.pairwise(PROFILE):
        if t <= t1:
            return v0 + (v1 - v0) * (t - t0) / (t1 - t0)
    return PROFILE[-1][1]


def make_smoother(alpha: float) -> Callable[[float], float]:
    """An exponential moving average: a CU may keep state between the samples it sees."""
    state: float | None = None

    def smooth(v: float) -> float:
        nonlocal state
        state = v if state is None else state + alpha * (v - state)
        return round(state, 1)

    return smooth


def make_odometer() -> Callable[[tuple[float, float]], float]:
    """Distance travelled from GPS fixes; fed once per second, so GPS noise adds up little."""
    last: tuple[float, float] | None = None
    total = 0.0

    def odometer(pos: tuple[float, float]) -> float:
        nonlocal last, total
        if last is not None:
            total += math.dist(last, pos)
        last = pos
        return round(total, 1)

    return odometer


async def drive(
    clock: ManualClock, speed: Source, position: Source, rng: random.Random, pace: float
) -> None:
    """Move the world and the clock; sensors sample it and their samples arrive late."""
    in_flight: list[tuple[int, int, Source, Sample]] = []  # a heap on available time
    x = y = heading = 0.0
    seq = 0
    for step in range(round(DRIVE_S / TICK_S) + 1):
        t = step * TICK_S
        now = seconds_to_ns(t)
        clock.set(now)
        v = true_speed(t)
        heading += 0.01  # a gentle left curve, so position is not just one axis
        x += v / 3.6 * TICK_S * math.cos(heading)
        y += v / 3.6 * TICK_S * math.sin(heading)

        # The speed sensor: noise, a rare error code, and a transport delay that is
        # sometimes long enough for the policy's max delay to reject the sample.
        measured = rng.gauss(v, 1.5) if rng.random() > 0.02 else rng.choice([-1.0, 255.0])
        delay = rng.uniform(0.03, 0.12) if rng.random() > 0.04 else rng.uniform(0.4, 0.7)
        seq += 1
        sample = Sample(round(measured, 1), now, now + seconds_to_ns(delay))
        heapq.heappush(in_flight, (sample.available_time, seq, speed, sample))

        if not TUNNEL_S[0] <= t < TUNNEL_S[1]:
            fix = (round(rng.gauss(x, 2.0), 1), round(rng.gauss(y, 2.0), 1))
            seq += 1
            sample = Sample(fix, now, now + seconds_to_ns(rng.uniform(0.05, 0.2)))
            heapq.heappush(in_flight, (sample.available_time, seq, position, sample))

        # Samples become available at this location in available-time order.
        while in_flight and in_flight[0][0] <= now:
            _, _, source, sample = heapq.heappop(in_flight)
            source.push_batch([sample])

        # Yield to the printers (and the instance's timer); sleep so a person can watch.
        await asyncio.sleep(pace)


async def print_table(dk: DyKnowInstance, rows: Subscription) -> None:
    """One row per second of valid time, from the 1 s grid, joined with queries at that time."""
    print(f"{'t [s]':>5} {'raw km/h':>9} {'smoothed':>9} {'GPS x, y [m]':>16} {'odometer [m]':>13}")
    # Each column is "the value at t as known right now": what a live display can show.
    async for row in rows:
        t = row.valid_time
        raw = dk.at("car5/speed", t).latest  # what the sensor last said, glitches and all
        fix = dk.at("car5/position", t, approximation=Approximation.CLOSEST).latest
        odo = dk.at("car5/odometer", t).latest
        pos = f"{fix.value[0]:7.1f},{fix.value[1]:7.1f}" if fix else "—"
        print(
            f"{ns_to_seconds(t):5.1f} {raw.value if raw else '—':>9} {row.value:9.1f} "
            f"{pos:>16} {odo.value if odo else 0.0:13.1f}"
        )


async def print_alerts(changes: Subscription) -> None:
    """Only the moments speeding starts or stops: the any-change policy drops the rest."""
    async for s in changes:
        mark, state = ("⚠", "speeding") if s.value else ("✓", "within the limit")
        print(f"  {mark} {ns_to_seconds(s.valid_time):5.1f} s  {state} ({SPEED_LIMIT_KMH:g} km/h)")


def show_queries(dk: DyKnowInstance) -> None:
    """The three kinds of query a location answers, plus one 'as believed at' query."""
    print("\nQueries at the end of the drive (times in s):")
    latest = dk.latest("car5/speed_smooth")
    s = latest.samples[0]
    print(
        f"  latest car5/speed_smooth      = {s.value} km/h  (valid {ns_to_seconds(s.valid_time)},"
        f" available {ns_to_seconds(s.available_time):.3f}, asked at "
        f"{ns_to_seconds(latest.query_time)})"
    )
    t = seconds_to_ns(12.25)  # between two samples: the fluent generator interpolates
    s = dk.at("car5/speed_smooth", t, approximation=Approximation.LINEAR).samples[0]
    print(f"  car5/speed_smooth at 12.25    = {s.value:.2f} km/h  (linear)")
    window = dk.between("car5/speed", seconds_to_ns(20.0), seconds_to_ns(20.4)).samples
    shown = ", ".join(
        f"{x.value}@{ns_to_seconds(x.valid_time):.1f}"
        f"+{(x.available_time - x.valid_time) / 1e6:.0f}ms"
        for x in window
    )
    print(f"  car5/speed between 20.0, 20.4 = {shown}")
    # Bitemporal: what did we believe at 20.0 s? Only samples available by then count.
    then = dk.latest("car5/speed", as_of=seconds_to_ns(20.0)).samples[0]
    print(
        f"  car5/speed as believed at 20.0 = {then.value} km/h, valid at "
        f"{ns_to_seconds(then.valid_time):.1f} (the newer ones were still in flight)"
    )


def show_metrics(dk: DyKnowInstance, metrics: dict[str, Any], smoother_input: Subscription) -> None:
    """What every stream saw, and why the smoother's policy held samples back."""
    print("\nPer-stream metrics (out: delivered to the subscribers, after their policies):")
    print(
        f"  {'label':<18} {'in':>5} {'out':>5} {'dropped':>7} {'cached':>6} {'delay p50/p99':>15}"
    )
    for label, m in metrics.items():
        p50, p99 = m["delay_p50"], m["delay_p99"]
        delay = "—" if p50 is None else f"≤{p50 * 1e3:.0f}/≤{p99 * 1e3:.0f} ms"
        print(
            f"  {label:<18} {m['samples_in']:>5} {m['samples_out']:>5} {m['dropped']:>7} "
            f"{m['cached']:>6} {delay:>15}"
        )
    why = {k: v for k, v in smoother_input.stats().items() if k.startswith("dropped_") and v}
    print(f"  the smoother's input policy dropped: {why}")
    print(f"  process failures: {dk.failure_count}")


async def run(pace: float = 0.025) -> dict[str, Any]:
    """Build the pipeline, drive, print; return the per-stream metrics (for tests)."""
    rng = random.Random(SEED)
    clock = ManualClock()
    async with DyKnowInstance("demo", clock=clock) as dk:
        speed = dk.add_source("car5/speed")
        position = dk.add_source("car5/position")
        smoother = dk.add_cu(
            "smoother",
            make_smoother(alpha=0.3),
            # error codes are out of bounds; a stale reading would drag the average back
            [Input("car5/speed", Policy(lower=0, upper=250, max_delay=0.3, order="monotone"))],
            "car5/speed_smooth",
        )
        dk.add_cu(
            "speeding",
            lambda v: v > SPEED_LIMIT_KMH,
            ["car5/speed_smooth"],
            "car5/speeding",
        )
        dk.add_cu(
            "odometer",
            make_odometer(),
            # one fix a second is enough; in the tunnel the last fix stands in once the
            # max delay has passed, so the odometer keeps reporting instead of falling silent
            [
                Input(
                    "car5/position",
                    Policy(
                        sample_period=1.0,
                        approximation="closest",
                        max_delay=0.5,
                        late="approximate",
                    ),
                )
            ],
            "car5/odometer",
        )
        rows = dk.subscribe("car5/speed_smooth", Policy(sample_period=1.0, approximation="linear"))
        alerts = dk.subscribe("car5/speeding", Policy(change="any_change"))

        async with asyncio.TaskGroup() as tg:
            tg.create_task(print_table(dk, rows), name="demo.table")
            tg.create_task(print_alerts(alerts), name="demo.alerts")
            await drive(clock, speed, position, rng, pace)
            # read before closing: a stream counts only its live subscribers' deliveries
            metrics = dk.metrics()
            # ending a subscription ends its printer once it has printed what is buffered
            rows.close()
            alerts.close()

        show_queries(dk)
        show_metrics(dk, metrics, smoother.subscriptions[0])
        return metrics


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run the demo."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="do not pace the drive for watching")
    args = parser.parse_args(argv)
    print(
        f"Driving car5 for {DRIVE_S:g} s of simulated time (speed limit "
        f"{SPEED_LIMIT_KMH:g} km/h, seed {SEED}, clock tick {NS_PER_S * TICK_S / 1e6:g} ms)\n"
    )
    asyncio.run(run(pace=0.0 if args.fast else 0.025))


if __name__ == "__main__":
    main()
