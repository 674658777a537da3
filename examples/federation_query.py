"""A federation query: one question asked of every platform at once, each answering for itself.

Run: python examples/federation_query.py

Three platforms in this process (zenoh peers on loopback, no multicast scouting): two
UAVs that know their altitude, each under a local label of its own, and an operator. The
operator asks the whole federation for the latest ``heli-altitude``, a semantic label of
the shared vocabulary; each UAV translates it to its local label, answers from its own
DyKnow instance, and the operator keeps the newest answer. Asked for ``car5-state``, only
the UAV tracking car5 answers: the other refuses, saying why.
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
from dyknow_core import NS_PER_S
from federation import FederationPlatform, PlatformConfig

VOCABULARY = {"name": "traffic", "labels": {"heli-altitude": "m", "{object}-state": "a car"}}
MAPPINGS = {  # semantic label -> this platform's local label
    "uav-a": {"heli-altitude": "heli/altitude", "{object}-state": "cars/{object}/state"},
    "uav-b": {"heli-altitude": "platform/nav/alt", "{object}-state": "tracks/{object}/state"},
    "operator": {"{object}-state": "picture/{object}"},
}


@contextlib.asynccontextmanager
async def open_federation() -> AsyncIterator[dict[str, FederationPlatform]]:
    """The three platforms as their config files would describe them, once all are members."""
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
                platforms[name] = await stack.enter_async_context(FederationPlatform(config))
            for p in platforms.values():
                async with p.membership() as events:
                    while not set(platforms) <= set(p.members):
                        await events.get()
            yield platforms


def latest(answer: Any, label: str) -> list[list[Any]]:
    """A get-latest answer's samples of ``label``: [value, valid s, available s] each."""
    return answer[label]["samples"]


async def run() -> dict[str, Any]:
    """Ask both questions; return who answered what, and who refused."""
    async with open_federation() as platforms:
        a, b, operator = platforms["uav-a"], platforms["uav-b"], platforms["operator"]
        now = a.instance.clock.now()
        a.instance.add_source("heli/altitude").push(120.0, valid_time=now - NS_PER_S)
        b.instance.add_source("platform/nav/alt").push(85.5, valid_time=now)
        a.instance.add_source("cars/car5/state").push({"x": 104.0, "y": 5.0}, valid_time=now)

        ask = operator.federation_agent.global_request
        altitude = await ask(
            {"action": "get-latest", "labels": ["heli-altitude"]}, deadline=5.0, select="newest"
        )
        for name, answer in altitude.answers.items():
            [[value, valid, _]] = latest(answer, "heli-altitude")
            print(f"{name}: heli-altitude {value} m, valid at now {valid - now / NS_PER_S:+.1f} s")
        print(f"the newest answer is {altitude.chosen}'s\n")

        car5 = await ask({"action": "get-latest", "labels": ["car5-state"]}, deadline=5.0)
        for name, answer in car5.answers.items():
            print(f"{name}: car5-state = {latest(answer, 'car5-state')[0][0]}")
        for name, reason in car5.refused.items():
            print(f"{name} refused: {reason}")
        return {
            "altitude": {n: latest(x, "heli-altitude")[0][0] for n, x in altitude.answers.items()},
            "newest": altitude.chosen,
            "car5": list(car5.answers),
            "refused": car5.refused,
        }


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
