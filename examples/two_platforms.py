"""Two platforms, one authenticated request: the agent layer in thirty lines.

Run it with ``python -m examples.two_platforms``. Each platform has its own key pair,
both trust the same federation trust file, and they talk over zenoh in peer mode on
loopback (no router, no broker): UAV B asks UAV A's ``weather`` agent for the wind; the
request is sealed by B's Interface Agent, opened and access-checked by A's, answered,
and both sides keep an audit.
"""

from __future__ import annotations

import asyncio
from typing import Any

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    InterfaceAgent,
    KeyPair,
    ServiceDescription,
    TrustStore,
    on_request,
    request,
)
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port


class Weather(Agent):
    """Answers requests for the wind where this UAV flies."""

    @on_request("weather")
    async def wind(self, message: ACLMessage) -> Any:
        """The inform's content: what was asked, and the answer."""
        return {"asked": message.content, "wind_m_s": 4.2}


async def run() -> dict[str, Any]:
    """Start both platforms, send one request, return the answer and A's audit counts."""
    keys = {p: KeyPair.generate(p) for p in ("uav-a", "uav-b")}
    trust = TrustStore("demo")
    for p, k in keys.items():
        trust.add(p, k.public_key)  # `python -m agents.keys trust` does this with files
    port_a, port_b = free_tcp_port(), free_tcp_port()
    za = ZenohTransport(ZenohConfig.loopback(port_a))
    zb = ZenohTransport(ZenohConfig.loopback(port_b, connect=[port_a]))
    async with za, zb:
        ia, ib = InterfaceAgent(keys["uav-a"], trust), InterfaceAgent(keys["uav-b"], trust)
        async with (
            AgentPlatform("uav-a", za, federation="demo", channel=ia) as a,
            AgentPlatform("uav-b", zb, federation="demo", channel=ib) as b,
        ):
            weather = await a.add(Weather("weather"))
            assert a.df is not None
            # protected: other platforms may use it, but only through the Interface Agent
            await a.df.register(
                ServiceDescription(
                    name="wind", type="weather", provider=weather.aid, visibility="protected"
                )
            )
            asker = await b.add(Agent("pilot"))
            answer = await request(asker, "weather@uav-a", {"where": "area X"}, ontology="weather")
            print(f"uav-b asked uav-a for the wind: {answer}")
            print(f"uav-a's audit: {ia.audit.counts}")
            return {"answer": answer, "audit": dict(ia.audit.counts)}


def main() -> None:
    """Run the example."""
    asyncio.run(run())


if __name__ == "__main__":
    main()
