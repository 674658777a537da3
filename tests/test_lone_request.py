"""A request that goes alone opens no batch: the order of a platform's messages is kept.

The first message asking an answer (``reply_with``) to a platform since the last message
taken from it goes alone, at once, and leaves nothing for the end of the turn; what
follows it goes alone too and opens the batch (docs/wire.md, "Batches of ACL messages").
Several platforms share one MemoryHub (one process); the envelopes are counted on the
wire by a plain subscriber, as anyone on the network sees them.
"""

from __future__ import annotations

import itertools
from typing import Any

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    Conversation,
    MessageTemplate,
    Performative,
    SecurityPolicy,
    ServiceDescription,
    on,
    on_request,
    wire_key,
)
from tests.test_interface import FED, WAIT, CountingTransport, federation, ia, until

_ids = itertools.count()


class Recorder(Agent):
    """Keeps every ``demo`` request and inform in the order its handlers got them."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.got: list[tuple[str, Any]] = []

    @on_request("demo")
    async def _ask(self, message: ACLMessage) -> Any:
        self.got.append(("request", message.content))
        return message.content

    @on(MessageTemplate(Performative.INFORM, ontology="demo"))
    async def _inform(self, message: ACLMessage) -> None:
        self.got.append(("inform", message.content))


async def _recorder(platform: AgentPlatform) -> Recorder:
    """A Recorder on ``platform`` offering a ``demo`` service others may use."""
    agent = await platform.add(Recorder("rec"))
    assert platform.df is not None
    await platform.df.register(
        ServiceDescription(name="rec-svc", type="demo", provider=agent.aid, visibility="protected")
    )
    return agent


def _request(asker: Agent, i: int) -> ACLMessage:
    """A request to ``rec@uav-b`` asking an answer (its own reply_with)."""
    return asker.message(
        Performative.REQUEST,
        "rec@uav-b",
        i,
        ontology="demo",
        protocol="fipa-request",
        reply_with=f"r{next(_ids)}",
    )


def _inform(asker: Agent, i: int) -> ACLMessage:
    return asker.message(Performative.INFORM, "rec@uav-b", i, ontology="demo")


async def _answers(conv: Conversation, n: int) -> list[Any]:
    """The contents of the next ``n`` answers in ``conv`` (each within the test's bound)."""
    return [(await conv.receive(timeout=WAIT)).content for _ in range(n)]


async def test_lone_requests_go_alone_and_open_no_batch() -> None:
    """Each request of an asker awaiting its answer is one envelope, at once, nothing after it."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))  # agrees the session first
            assert await _answers(conv, 1) == [-1]
            wire = await (await fed.raw()).subscribe(wire_key(FED, "acl", "uav-b"))
            for i in range(3):
                await conv.send(_request(asker, i))
                assert "uav-b" not in interface._outbox  # no batch for the turn's end
                assert await _answers(conv, 1) == [i]
        assert len(wire.inbox.drain()) == 3
        assert rec.got == [("request", i) for i in range(-1, 3)]
        assert interface.batches_lost == 0


async def test_what_follows_a_lone_request_in_its_turn_goes_after_it_in_order() -> None:
    """A request, then informs and a request in the same turn: three envelopes, in order."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            rec.got.clear()
            wire = await (await fed.raw()).subscribe(wire_key(FED, "acl", "uav-b"))
            # one turn: nothing here suspends once the session is there
            await conv.send(_request(asker, 0))  # alone, no batch
            await asker.send(_inform(asker, 1))  # alone too, and opens the batch
            await conv.send(_request(asker, 2))  # in the batch
            await asker.send(_inform(asker, 3))  # in the batch
            assert sorted(await _answers(conv, 2)) == [0, 2]
        await until(lambda: len(rec.got) == 4, "the four messages")
        assert rec.got == [("request", 0), ("inform", 1), ("request", 2), ("inform", 3)]
        assert len(wire.inbox.drain()) == 3


async def test_a_request_while_a_batch_waits_joins_it_behind_what_waits() -> None:
    """A request sent while the turn's batch for its platform waits goes in it, after the rest."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            rec.got.clear()
            wire = await (await fed.raw()).subscribe(wire_key(FED, "acl", "uav-b"))
            await asker.send(_inform(asker, 0))  # alone, opens the batch
            await asker.send(_inform(asker, 1))  # waits in it
            await conv.send(_request(asker, 2))
            assert interface._outbox["uav-b"] != []  # the request waits there too
            assert "uav-b" not in interface._lone
            assert await _answers(conv, 1) == [2]
        await until(lambda: len(rec.got) == 3, "the three messages")
        assert rec.got == [("inform", 0), ("inform", 1), ("request", 2)]
        assert len(wire.inbox.drain()) == 2


async def test_a_platform_revoked_after_a_lone_request_is_sent_nothing_then_again() -> None:
    """Revoked while its answer is awaited: what follows is dropped and counted; trusted
    again, a request agrees a new session, goes alone and is answered."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            await conv.send(_request(asker, 0))  # alone; its answer is awaited
            key = interface.trust.public_key("uav-b")
            assert interface.trust.remove("uav-b")  # revoked in the same turn
            assert interface.revoked == 1
            unsent = interface.unsent_revoked
            await asker.send(_inform(asker, 1))  # dropped: nothing is sealed for uav-b
            assert interface.unsent_revoked == unsent + 1
            assert "uav-b" not in interface._outbox and "uav-b" not in interface._lone
            await until(lambda: ("request", 0) in rec.got, "the request sent before")
            assert interface.trust.add("uav-b", key)
            await conv.send(_request(asker, 2))  # a new key exchange first
            answers = await _answers(conv, 1)
        # the answer to 0 came from a platform revoked then: refused, never delivered
        assert answers == [2]
        assert ("inform", 1) not in rec.got
        assert rec.got[-1] == ("request", 2)


async def test_lone_requests_renew_their_session_as_they_go() -> None:
    """Requests going alone still renew the session when due; none is lost, all in order."""
    async with federation("uav-a", "uav-b") as fed:
        policy = SecurityPolicy(renew_after_messages=3)
        ta = CountingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta, policy=policy)
        rec = await _recorder(await fed.start("uav-b", policy=policy))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            for i in range(12):
                await conv.send(_request(asker, i))
                await asker.send(_inform(asker, i))  # in the same turn: alone, after it
                assert await _answers(conv, 1) == [i]
        await until(lambda: len(rec.got) == 24, "the 24 messages")
        assert rec.got == [(kind, i) for i in range(12) for kind in ("request", "inform")]
        assert ta.kx_queries >= 2  # renewed by uav-a, over the requests that went alone
        assert interface.missing() == {} and ia(pa).batches_lost == 0


async def test_a_message_that_waits_for_nothing_goes_without_the_channels_coroutine() -> None:
    """With a session agreed, requests go through `InterfaceAgent.send_now` (no coroutine of
    the channel's), alone and in order; with none (forgotten), through `send`, which agrees
    one first."""
    async with federation("uav-a", "uav-b") as fed:
        ta = CountingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta)
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        awaited: list[str] = []
        send = interface.send

        async def counted(platform: str, message: ACLMessage) -> None:
            awaited.append(platform)
            await send(platform, message)

        interface.send = counted  # type: ignore[method-assign]
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))  # no session yet: `send` agrees it
            assert await _answers(conv, 1) == [-1]
            assert awaited == ["uav-b"]
            exchanges = ta.kx_queries
            wire = await (await fed.raw()).subscribe(wire_key(FED, "acl", "uav-b"))
            for i in range(3):
                await conv.send(_request(asker, i))
                assert "uav-b" not in interface._outbox  # alone, no batch opened
                assert await _answers(conv, 1) == [i]
            assert awaited == ["uav-b"]  # each sealed and put at once
            assert ta.kx_queries == exchanges
            interface.sessions.forget("uav-b")
            await conv.send(_request(asker, 3))  # `send` again: a key exchange first
            assert await _answers(conv, 1) == [3]
            assert awaited == ["uav-b", "uav-b"]
            assert ta.kx_queries == exchanges + 1
        assert len(wire.inbox.drain()) == 4
        assert rec.got == [("request", i) for i in range(-1, 4)]
        assert interface.batches_lost == 0
