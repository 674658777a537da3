"""`Agent.answer_at_once` at its limits: it never answers what the handlers would not.

Each test asserts what the handler path gives (a subclass's handler that refuses, a read
behind a request being handled, a private agent, an answer that cannot go at once): an
answer at once that differed would fail it.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Any

import pytest

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    InterfaceAgent,
    KeyPair,
    MemoryHub,
    Performative,
    Refuse,
    Refused,
    TrustStore,
    on_query,
    on_request,
    query_ref,
    request,
)
from agents.transports import MemoryTransport
from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock
from federation import GatewayAgent
from tests.test_answer_at_once import reader
from tests.test_interface import WAIT, federation

T0 = 1000 * NS_PER_S


class GuardedGateway(GatewayAgent):
    """A deployment's gateway with one more rule: other platforms' reads are refused.

    Its handlers are new methods (subclass routes are matched before the base's), not
    overrides of ``_on_request`` / ``_on_query``.
    """

    def __init__(self, instance: DyKnowInstance) -> None:
        super().__init__(instance)
        self.guarded: list[ACLMessage] = []

    @on_request("dyknow")
    async def _guard_request(self, message: ACLMessage) -> Any:
        self.guarded.append(message)
        raise Refuse("closed to other platforms")

    @on_query("dyknow")
    async def _guard_query(self, message: ACLMessage) -> Any:
        self.guarded.append(message)
        raise Refuse("closed to other platforms")


@contextlib.asynccontextmanager
async def guarded() -> AsyncIterator[tuple[GuardedGateway, Agent]]:
    """uav-a with a `GuardedGateway`, operator's asker, on one in-memory hub."""
    ka, ko = KeyPair.generate("uav-a"), KeyPair.generate("operator")
    fed = "rq-guard"
    trust = TrustStore(fed, {"uav-a": ka.public_key, "operator": ko.public_key})
    hub = MemoryHub()
    async with contextlib.AsyncExitStack() as stack:
        dk = await stack.enter_async_context(DyKnowInstance("uav-a", clock=ManualClock(T0)))
        dk.add_source("car/car5/speed").push(3.0, valid_time=T0)
        ta = await stack.enter_async_context(hub.transport())
        to = await stack.enter_async_context(hub.transport())
        uav = await stack.enter_async_context(
            AgentPlatform("uav-a", ta, federation=fed, channel=InterfaceAgent(ka, trust))
        )
        operator = await stack.enter_async_context(
            AgentPlatform("operator", to, federation=fed, channel=InterfaceAgent(ko, trust))
        )
        gateway = await uav.add(GuardedGateway(dk))
        asker = await operator.add(Agent("asker"))
        yield gateway, asker


@pytest.mark.parametrize("ask", [request, query_ref])
async def test_a_subclass_handler_that_refuses_is_not_bypassed(ask: Any) -> None:
    """A subclass's own handler for the gateway's requests decides them, as it routes first."""
    async with guarded() as (gateway, asker):
        content = {"action": "query", "label": "car/car5/speed"}
        with pytest.raises(Refused, match="closed to other platforms"):
            await ask(asker, "gateway@uav-a", content, ontology="dyknow", timeout=WAIT)
        assert len(gateway.guarded) == 1
        assert gateway.stats.answered_at_once == 0


async def test_a_read_does_not_overtake_the_request_its_agent_is_handling() -> None:
    """Handlers run one at a time: a read that comes while one runs is answered after it."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await reader(pb)
        asker = await pa.add(Agent("asker"))

        first = asyncio.create_task(request(asker, "reader@uav-b", "hold", ontology="demo"))
        async with asyncio.timeout(WAIT):
            await r.blocked.wait()  # the receive loop is in the first handler; mailbox empty
        assert len(r._mailbox) == 0
        second = asyncio.create_task(
            query_ref(asker, "reader@uav-b", {"read": "mode"}, ontology="demo")
        )
        # bounded: the second is either answered (at once) or queued behind the first
        async with asyncio.timeout(WAIT):
            while not second.done() and len(r._mailbox) == 0:  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        overtook = second.done()
        r.release.set()
        assert await first == "released"
        await second
        assert not overtook, "answered while the agent's handler of an earlier request ran"


async def test_a_private_agent_answers_no_inform_of_another_platform() -> None:
    """An inform is no request: no handler answers it with data (not-understood), private or not.

    Informs are admitted without the directory's access check (they are not requests), so
    an answer to one would read a private agent's data out to another platform.
    """
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await reader(pb, visibility="private")
        asker = await pa.add(Agent("asker"))

        # a request is refused by the Interface Agent: the reader is private
        with pytest.raises(Refused, match="access denied"):
            await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        tell = asker.message(
            Performative.INFORM,
            "reader@uav-b",
            {"read": "speed"},
            ontology="demo",
            conversation_id="rq-tell",
        )
        with asker.conversation("rq-tell", peers=["reader@uav-b"], timeout=WAIT) as conv:
            await conv.send(tell)
            answer = await conv.receive()
        assert answer.performative is Performative.NOT_UNDERSTOOD, answer.content
        assert r.stats.answered_at_once == 0


class Broker(MemoryTransport):
    """A transport whose publish may wait (as MQTT's, for the broker): `publishes_nowait` False."""

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        await super().publish(key, payload, attachment=attachment)


async def test_the_hook_is_not_asked_when_its_answer_cannot_go_at_once() -> None:
    """On a transport that waits nothing is sent at once: the read is made once, by the handler."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a", transport=Broker(fed.hub))
        pb = await fed.start("uav-b", transport=Broker(fed.hub))
        r = await reader(pb)
        asker = await pa.add(Agent("asker"))
        got = await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert got == {"value": 12.5, "by": "handler"}
        assert r.asked == []  # asked, its answer thrown away, the read made again
