"""A stream between two platforms: exported by one with the policy the other asked for.

Run: python examples/stream_between_platforms.py

uav-a has tracked car5 for 10 s: a state every 0.1 s under its local label
``cars/car5/state``; those from 4.8 s to 5.2 s reached it 0.8 s late. The operator asks uav-a
for ``car5-state`` (the semantic label both map) from 2 s to 8 s on uav-a's time line, one
sample a second, at most 0.5 s late. uav-a's export proxy subscribes with that policy —
the late states are dropped there, the grid point at 5 s takes the state of 4.7 s — and
sends the 7 samples; the operator's import proxy lands them in ``import/uav-a/car5-state``,
valid times kept, available times its own. Past 8 s the export ends by itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import tempfile
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, Policy
from federation import FederationPlatform, PlatformConfig

VOCABULARY = {"name": "traffic", "labels": {"{object}-state": "a tracked car's state"}}
MAPPINGS = {  # semantic label -> this platform's local label
    "uav-a": {"{object}-state": "cars/{object}/state"},
    "operator": {"{object}-state": "picture/{object}"},
}
LATE = range(48, 53)  # the states from 4.8 s to 5.2 s came 0.8 s late


@contextlib.asynccontextmanager
async def open_federation(uav_a: DyKnowInstance) -> AsyncIterator[dict[str, FederationPlatform]]:
    """Both platforms as their config files would describe them, once both are members."""
    federation = f"traffic-{uuid.uuid4().hex[:8]}"  # a new one per run: two runs never meet
    seed = free_tcp_port()
    with tempfile.TemporaryDirectory() as tmp:
        keys = [gen_keys(name, tmp)[2] for name in MAPPINGS]  # dyknow keys gen ...
        trust_keys(Path(tmp, "trust.json"), keys, federation=federation)
        async with contextlib.AsyncExitStack() as stack:
            platforms = {}
            for name, labels in MAPPINGS.items():
                port = seed if name == "uav-a" else free_tcp_port()
                config = PlatformConfig.from_dict({
                    "name": name, "federation": federation, "vocabulary": VOCABULARY,
                    "key": f"{tmp}/{name}.key", "trust": f"{tmp}/trust.json",
                    "mapping": {"labels": labels},
                    "transport": {"listen": [f"tcp/127.0.0.1:{port}"],
                                  "connect": [f"tcp/127.0.0.1:{seed}"] if port != seed else []},
                })  # fmt: skip
                instance = uav_a if name == "uav-a" else None  # uav-a's time line is ours
                platform = FederationPlatform(config, instance=instance)
                platforms[name] = await stack.enter_async_context(platform)
            for p in platforms.values():
                async with p.membership() as events:
                    while not set(platforms) <= set(p.members):
                        await events.get()
            yield platforms


async def run() -> list[tuple[Any, float]]:
    """Track, ask for the stream, return what the operator imported: (state, valid s)."""
    clock = ManualClock(10 * NS_PER_S)
    async with DyKnowInstance("uav-a", clock=clock) as dk, open_federation(dk) as platforms:
        a, operator = platforms["uav-a"], platforms["operator"]
        tick = NS_PER_S // 10
        a.instance.add_source("cars/car5/state").push_batch(
            [
                (
                    {"x": 12.5 * k / 10, "y": 5.0},
                    k * tick,
                    k * tick + (8 if k in LATE else 1) * tick,
                )
                for k in range(100)
            ]
        )
        await operator.federation_agent.create_stream(
            "uav-a", ["car5-state"], start=2.0, end=8.0, sample_period=1.0, max_delay=0.5
        )
        label = await operator.imported("uav-a", "car5-state", timeout=5)
        print(f"uav-a tracked car5: 100 states; the operator's {label} gets:")
        got = []
        async with asyncio.timeout(5):
            async for s in operator.instance.subscribe(label, Policy(start=0)):  # from the first
                print(f"  {s.value} valid at {s.valid_time / NS_PER_S:3.1f} s (uav-a's clock)")
                got.append(s)
                if len(got) == 7:
                    break
            while a.exporter.exports():  # noqa: ASYNC110 (no event: the export ends by itself)
                await asyncio.sleep(0.01)
        print("and the export has ended, its policy's end passed")
        return [(s.value, s.valid_time / NS_PER_S) for s in got]


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
