"""A request that goes alone opens no batch: the order of a platform's messages is kept.

The first message asking an answer (``reply_with``) to a platform since the last message
taken from it goes alone, at once, and leaves nothing for the end of the turn; what
follows it goes alone too and opens the batch (docs/wire.md, "Batches of ACL messages").
Several platforms share one MemoryHub (one process); the envelopes are counted on the
wire by a plain subscriber, as anyone on the network sees them. Around a lone request:
its put failing, the put after it failing, two tasks sending to one platform in the same
turns, and an asker's replies taken one at a time from the lane over zenoh.
"""

from __future__ import annotations

import asyncio
import itertools
from typing import Any

import pytest

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    Conversation,
    ConversationError,
    MemoryHub,
    MemoryTransport,
    MessageTemplate,
    Performative,
    SecurityPolicy,
    ServiceDescription,
    TransportError,
    on,
    on_request,
    wire_key,
)
from tests.test_answer_on_thread import LATEST, pair, sealed_requests
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


class FailingTransport(MemoryTransport):
    """A memory transport whose ACL puts fail while ``failing`` is set (a transport closing)."""

    def __init__(self, hub: MemoryHub) -> None:
        super().__init__(hub)
        self.failing = False

    def _put(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        if self.failing and "/acl/" in key:
            raise TransportError("memory: the link is down")
        super()._put(key, payload, attachment)


async def test_a_lone_request_whose_put_fails_raises_at_its_send_and_leaves_nothing() -> None:
    """Its error reaches the sender, nothing waits or is counted lost, and the next
    request goes alone again (no stale state makes a later message wait)."""
    async with federation("uav-a", "uav-b") as fed:
        ta = FailingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta)
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            ta.failing = True
            with pytest.raises(TransportError, match="link is down"):
                await conv.send(_request(asker, 0))
            ta.failing = False
            assert "uav-b" not in interface._lone and "uav-b" not in interface._outbox
            assert interface.batches_lost == 0
            wire = await (await fed.raw()).subscribe(wire_key(FED, "acl", "uav-b"))
            await conv.send(_request(asker, 1))
            assert "uav-b" in interface._lone and "uav-b" not in interface._outbox
            assert await _answers(conv, 1) == [1]
        assert len(wire.inbox.drain()) == 1
        assert rec.got == [("request", -1), ("request", 1)]


async def test_the_put_after_a_lone_request_failing_raises_there_and_the_rest_keeps_order() -> None:
    """Request, then an inform whose put fails (raised at its send), then two more in the
    turn: the failed one is the only one missing, the rest arrive in order."""
    async with federation("uav-a", "uav-b") as fed:
        ta = FailingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta)
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            rec.got.clear()
            # one turn: nothing here suspends once the session is there
            await conv.send(_request(asker, 0))  # alone, no batch
            ta.failing = True
            with pytest.raises(TransportError):
                await asker.send(_inform(asker, 1))  # alone: its error raises here
            ta.failing = False
            assert "uav-b" not in interface._outbox
            await asker.send(_inform(asker, 2))  # alone, and opens the batch
            await asker.send(_inform(asker, 3))  # in the batch
            assert interface._outbox["uav-b"] != []
            assert await _answers(conv, 1) == [0]
        await until(lambda: len(rec.got) == 3, "the three messages sent")
        assert rec.got == [("request", 0), ("inform", 2), ("inform", 3)]
        assert interface.batches_lost == 0


async def test_a_batch_opened_after_a_lone_request_failing_is_counted_and_ends_the_lone() -> None:
    """The batch the message after a lone request opened fails at the turn's end: its
    messages are counted in ``batches_lost`` and the next request still goes."""
    async with federation("uav-a", "uav-b") as fed:
        ta = FailingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta)
        rec = await _recorder(await fed.start("uav-b"))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            rec.got.clear()
            await conv.send(_request(asker, 0))  # alone
            await asker.send(_inform(asker, 1))  # alone, opens the batch
            await asker.send(_inform(asker, 2))  # waits in it
            await asker.send(_inform(asker, 3))  # waits in it
            ta.failing = True  # before the turn's end
            await asyncio.sleep(0)  # the turn ends: the flush runs (and fails)
            ta.failing = False
            assert interface.batches_lost == 2
            assert "uav-b" not in interface._outbox and "uav-b" not in interface._lone
            assert await _answers(conv, 1) == [0]
            # the burst goes on (that turn sent two): the request waits for the turn's
            # end in the batch, and goes then (nothing stale holds it)
            await conv.send(_request(asker, 4))
            assert await _answers(conv, 1) == [4]
            assert interface.batches_lost == 2
        assert rec.got[:2] == [("request", 0), ("inform", 1)]
        assert rec.got[2:] == [("request", 4)]


async def test_two_tasks_sending_to_one_platform_turn_by_turn_keep_each_ones_order() -> None:
    """Two agents interleave requests and informs to one platform, a turn apart: every
    message arrives once, each agent's in the order it sent them."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        rec = await _recorder(await fed.start("uav-b"))
        askers = [await pa.add(Agent(f"asker{k}")) for k in range(2)]
        interface = ia(pa)
        with askers[0].conversation(peers=["rec@uav-b"], timeout=WAIT) as warm:
            await warm.send(_request(askers[0], -1))
            assert await _answers(warm, 1) == [-1]
        rec.got.clear()

        async def run(k: int, asker: Agent) -> list[Any]:
            with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
                for i in range(6):
                    tag = k * 100 + i
                    if i % 3 == 2:
                        await asker.send(_inform(asker, tag))
                    else:
                        await conv.send(_request(asker, tag))
                    await asyncio.sleep(0)  # a turn between, the other task's in it
                return sorted(await _answers(conv, 4))

        got = await asyncio.gather(*(run(k, a) for k, a in enumerate(askers)))
        assert got == [[0, 1, 3, 4], [100, 101, 103, 104]]
        await until(lambda: len(rec.got) == 12, "the twelve messages")
        for k in range(2):
            mine = [tag for _, tag in rec.got if tag // 100 == k]
            assert mine == [k * 100 + i for i in range(6)]
        assert interface.batches_lost == 0 and not interface._outbox


async def test_an_askers_round_trips_over_zenoh_each_go_alone_and_come_back_on_the_lane() -> None:
    """Each request of an asker awaiting its answer is one envelope and opens no batch; each
    reply is taken as it comes from the lane (one at a time), which ends the lone."""
    async with pair(lane=False, asker_lane=True) as p:  # one lane a process: the asker's
        op = p.ia_op
        for _ in range(3):  # warm: sessions, publishers, the directory's decisions
            await p.fed_op.request_from("uav-a", LATEST)
        await until(lambda: not op._lane_done, "the replies booked")
        before = op.replies_on_thread
        for _ in range(12):
            answer = await p.fed_op.request_from("uav-a", LATEST)
            assert answer["heli-altitude"]["samples"][0][0] == 120.0
            assert "uav-a" not in op._outbox
            await until(lambda: "uav-a" not in op._lone, "the reply ends the lone")
        assert op.replies_on_thread - before >= 10  # the lane hands replies over
        assert op.batches_lost == 0 and op.missing() == {}


OP_LATEST = {"action": "get-latest", "labels": ["op-heading"]}


async def _sealed_ask_of_uav_a(p: Any, conv: str) -> tuple[bytes, Any]:
    """uav-a's request to operator in ``conv``, answered by operator and sealed for uav-a
    but not sent; the request's future."""
    sealed: list[bytes] = []
    transport = p.provider.transport
    real_put, real_put_now = transport.publish, transport.publish_nowait

    async def capture(key: str, payload: bytes, **kw: Any) -> None:
        if key.endswith("/acl/operator"):
            sealed.append(payload)
            return
        await real_put(key, payload, **kw)

    def capture_now(key: str, payload: bytes) -> None:
        # a request that waits for nothing goes out this way (`InterfaceAgent.send_now`)
        if key.endswith("/acl/operator"):
            sealed.append(payload)
            return
        real_put_now(key, payload)

    transport.publish = capture
    transport.publish_nowait = capture_now
    batching, p.ia_a._batching = p.ia_a._batching, False
    asked = asyncio.ensure_future(p.fed_a.request_from("operator", OP_LATEST, conversation_id=conv))
    try:
        await until(lambda: len(sealed) == 1, "uav-a's request sealed")
    finally:
        transport.publish = real_put
        transport.publish_nowait = real_put_now
        p.ia_a._batching = batching
    _, body = p.ia_op.sessions.open(sealed[0])
    request = ACLMessage.from_json(body)
    answer = request.reply(Performative.INFORM, {"op-heading": 1}, sender=request.receivers[0])
    return p.ia_op.sessions.seal("uav-a", answer.to_json()), asked


async def _mixed(together: bool, closed: bool) -> tuple[Any, ...]:
    """A read of operator's answered on uav-a's lane and a reply to uav-a's own request,
    handed to the loop in one booking (``together``) or one booking each (``closed``: its
    conversation ends after the hand-over, before the booking)."""
    async with pair() as p:
        ia = p.ia_a
        for _ in range(3):  # warm: the next plain read is answerable on the thread
            await p.fed_op.request_from("uav-a", LATEST)
            await p.fed_a.request_from("operator", OP_LATEST)
        await until(lambda: ia.answered_on_thread >= 1 and not ia._lane_done, "warm")
        (read,), (asked_read,) = await sealed_requests(p, [(LATEST, "mix-read")])
        reply, asked = await _sealed_ask_of_uav_a(p, "mix-ask")
        await until(lambda: not ia._lane_done and ia._lane_queued == {}, "quiet")
        stats, fed = p.provider.stats, p.fed_a.stats
        before = (
            ia.answered_on_thread,
            ia.replies_on_thread,
            stats.received_remote,
            stats.senders["operator"].accepted,
            fed.received,
            fed.answered_at_once,
            len(ia.audit.records),
        )
        # here, on the loop's thread: the loop books nothing between the two unless awaited
        assert ia._lane_take(read) is None  # answered on the lane
        if not together:
            await until(lambda: not ia._lane_done, "the answer booked")
        assert ia._lane_take(reply) is None  # handed over
        if together:
            assert [len(item) for item in ia._lane_done] == [3, 4]  # the general path
        late = fed.late
        if closed:
            p.fed_a._by_conv["mix-ask"].close()
            with pytest.raises(ConversationError):
                await asyncio.wait_for(asked, WAIT)
            await until(lambda: fed.late == late + 1, "the reply dropped as late")
            answer = None
        else:
            answer = await asyncio.wait_for(asked, WAIT)
        read_answer = await asyncio.wait_for(asked_read, WAIT)
        await until(lambda: not ia._lane_done and ia._lane_queued == {}, "all booked")
        after = (
            ia.answered_on_thread,
            ia.replies_on_thread,
            stats.received_remote,
            stats.senders["operator"].accepted,
            fed.received,
            fed.answered_at_once,
            len(ia.audit.records),
        )
        records = [
            (r["verdict"], r.get("performative"), r.get("conversation_id"))
            for r in list(ia.audit.records)[before[-1] :]
            if r.get("conversation_id") in ("mix-read", "mix-ask")
        ]
        return (
            answer,
            sorted(read_answer),
            tuple(a - b for a, b in zip(after, before, strict=True))[:-1],
            sorted(records),
            "operator" in ia._lone,
            fed.late - late,
        )


@pytest.mark.parametrize("closed", [False, True], ids=["open", "closed-meanwhile"])
async def test_a_reply_booked_with_the_lanes_answers_is_taken_as_one_booked_alone(
    closed: bool,
) -> None:
    """The general booking (answers and a reply) and the single reply's: the same result,
    counts and audit records, the reply's conversation open or ended meanwhile."""
    together = await _mixed(True, closed)
    alone = await _mixed(False, closed)
    assert together == alone
    assert together[2][0] == 1  # one answered on the lane
    assert together[-1] == int(closed)


async def test_a_pipelined_asker_sends_every_request_once_in_order() -> None:
    """Requests sent back to back without awaiting answers (with informs between, over
    several turns): each arrives once, in order, and each is answered."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        # unlimited: uav-b's default rate limit refuses part of a burst this size
        rec = await _recorder(await fed.start("uav-b", rate_limit=None))
        asker = await pa.add(Agent("asker"))
        interface = ia(pa)
        with asker.conversation(peers=["rec@uav-b"], timeout=WAIT) as conv:
            await conv.send(_request(asker, -1))
            assert await _answers(conv, 1) == [-1]
            rec.got.clear()
            sent = []
            for i in range(300):
                if i % 7 == 3:
                    await asker.send(_inform(asker, i))
                    sent.append(("inform", i))
                else:
                    await conv.send(_request(asker, i))
                    sent.append(("request", i))
                if i % 50 == 49:
                    await asyncio.sleep(0)  # a turn ends here and there
            asked = [i for kind, i in sent if kind == "request"]
            got = [await conv.receive(timeout=WAIT) for _ in asked]
            odd = [(m.performative, m.content) for m in got if type(m.content) is not int]
            assert not odd
            assert sorted(m.content for m in got) == asked
        await until(lambda: len(rec.got) == len(sent), "every message")
        assert rec.got == sent
        assert interface.batches_lost == 0 and not interface._outbox
