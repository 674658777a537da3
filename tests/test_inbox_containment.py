"""The inbox's consumer (`InterfaceAgent._receive`) never ends on one bad item: an envelope
whose taking raises costs only itself, and what comes after it, of its peer and of another,
is still taken, counted and audited.

Three platforms over real zenoh sessions on loopback (one process): ``hub`` receives, with
the lane on or off, from ``uav-a`` and ``uav-b``. One step of hub's consumer is made to
raise for the message carrying ``POISON`` alone, as a fault of the code would.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import pytest
from pydantic import BaseModel

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    Failed,
    MessageTemplate,
    Performative,
    ServiceDescription,
    on,
    on_request,
    request,
)
from agents._interface import InterfaceAgent
from agents._security import KeyPair, TrustStore
from agents.transports import ZenohConfig, ZenohTransport
from agents.transports import free_tcp_port as free_port

WAIT = 10.0  # the bound on any single wait (a busy machine); each test ends far below it
# what uav-a said in confidence (encrypted on the wire): no log of hub may hold it
POISON = f"poison-{uuid.uuid4().hex}"


class Sink(Agent):
    """Keeps the content of every ``demo`` inform that reached its handler."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.got: list[Any] = []

    @on(MessageTemplate(Performative.INFORM, ontology="demo"))
    async def _keep(self, message: ACLMessage) -> None:
        self.got.append(message.content)


@dataclass
class Trio:
    """hub (its Interface Agent and sink) and the two senders' agents."""

    hub: AgentPlatform
    ia: InterfaceAgent
    sink: Sink
    senders: dict[str, Agent]

    async def tell(self, peer: str, *contents: str) -> None:
        """``peer``'s informs to the sink, sent in one turn (after the first: one batch)."""
        agent = self.senders[peer]
        await asyncio.gather(
            *(
                agent.send(
                    agent.message(
                        Performative.INFORM,
                        self.sink.aid,
                        c,
                        ontology="demo",
                        conversation_id=f"{peer}-{c}",
                    )
                )
                for c in contents
            )
        )

    async def until_got(self, *contents: str) -> None:
        """Wait (bounded) until the sink has ``contents``."""
        async with asyncio.timeout(WAIT):
            while not set(contents) <= set(self.sink.got):  # noqa: ASYNC110
                await asyncio.sleep(0.005)


@contextlib.asynccontextmanager
async def trio(*, lane: bool) -> AsyncIterator[Trio]:
    """hub, uav-a and uav-b over zenoh, each sender's first message taken before the test."""
    fed = f"inbox-{uuid.uuid4().hex[:12]}"
    names = ("hub", "uav-a", "uav-b")
    keys = {n: KeyPair.generate(n) for n in names}
    trusted = {n: k.public_key for n, k in keys.items()}
    seed = free_port()
    async with contextlib.AsyncExitStack() as stack:
        platforms: dict[str, AgentPlatform] = {}
        for name in names:
            config = (
                ZenohConfig.loopback(seed)
                if name == "hub"
                else ZenohConfig.loopback(free_port(), connect=[seed])
            )
            transport = await stack.enter_async_context(ZenohTransport(config))
            # only hub's lane: with two in one process neither opens on its thread
            channel = InterfaceAgent(
                keys[name],
                TrustStore(fed, trusted),
                audit_interval=0.02,
                lane=lane and name == "hub",
            )
            platforms[name] = await stack.enter_async_context(
                AgentPlatform(name, transport, federation=fed, channel=channel)
            )
        sink = await platforms["hub"].add(Sink("sink"))
        senders = {n: await platforms[n].add(Agent("talker")) for n in ("uav-a", "uav-b")}
        ia = platforms["hub"].channel
        assert isinstance(ia, InterfaceAgent) and ia._lane_on is lane
        t = Trio(platforms["hub"], ia, sink, senders)
        for peer in senders:
            await t.tell(peer, "warm")
        await t.until_got("warm")
        async with asyncio.timeout(WAIT):
            while sink.got.count("warm") < 2:  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        yield t


def _poisoned(ia: InterfaceAgent, step: str) -> list[str]:
    """hub's ``step`` raises for the (first) envelope whose message carries `POISON`; the
    list returned names each step that raised."""
    real = getattr(ia, step)
    raised: list[str] = []

    def broken(*args: Any) -> Any:
        if not raised and POISON in repr(args):
            raised.append(step)
            # as a fault's error may quote what it failed on (a value, a key)
            raise RuntimeError(f"{step} broke on {args!r}")
        return real(*args)

    setattr(ia, step, broken)
    return raised


def _accepted(ia: InterfaceAgent, skip: int) -> list[tuple[str, str]]:
    """(from, conversation) of the accepted records of the senders' talkers after ``skip``."""
    return [
        (r["from"], r["conversation_id"])
        for r in list(ia.audit.records)[skip:]
        if r["verdict"] == "accepted" and r.get("sender", "").startswith("talker@")
    ]


@pytest.mark.parametrize(
    ("step", "lane", "batch"),
    [
        ("_take_now", True, False),
        ("_take_now", False, False),
        ("_batch_items", True, True),
        ("_take_batch", False, True),
    ],
    ids=["take-now-lane", "take-now-loop", "batch-items-lane", "take-batch-loop"],
)
async def test_an_envelope_whose_taking_raises_costs_only_itself(
    step: str, lane: bool, batch: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """The envelope that raises is logged once with what failed, counted in
    ``inbox_failed`` and dropped; uav-a's next message and uav-b's are still taken, counted
    and audited, and nothing is held for uav-a (the lane would never answer it again)."""
    async with trio(lane=lane) as t:
        ia, stats = t.ia, t.hub.stats.senders
        before = {p: stats[p].accepted for p in ("uav-a", "uav-b")}
        skip = len(ia.audit.records)
        raised = _poisoned(ia, step)
        with caplog.at_level(logging.DEBUG, logger="agents"):
            # a batch: the first message leaves alone, the two after it together
            await t.tell("uav-a", *(("lead", POISON, "also") if batch else (POISON,)))
            await t.tell("uav-a", "a-after")
            await t.tell("uav-b", "b-after")
            await t.until_got("a-after", "b-after")
        assert raised == [step]
        assert ia.inbox_failed == 1
        failed = [
            r for r in caplog.records if r.levelno >= logging.ERROR and "failed" in r.getMessage()
        ]
        assert len(failed) == 1
        what = "taking the batch" if batch else "taking the message"
        # what failed, on what (its size), and the exception's kind and place, never the
        # plaintext: not in the item's repr, not in the error's text
        assert POISON not in caplog.text
        assert not [r for r in caplog.records if POISON in r.getMessage() + (r.exc_text or "")]
        logged = failed[0].getMessage()
        assert f"{what} from uav-a failed (" in logged
        assert re.search(r"\d+ bytes", logged) and "RuntimeError" in logged
        assert "in broken" in logged  # where it was raised
        assert POISON not in t.sink.got and "also" not in t.sink.got
        taken = ["lead", "a-after"] if batch else ["a-after"]
        # each peer's in its order (zenoh orders no peer's messages with another's)
        assert [c for c in t.sink.got if c not in ("warm", "b-after")] == taken
        assert t.sink.got.count("b-after") == 1
        assert stats["uav-a"].accepted - before["uav-a"] == len(taken)
        assert stats["uav-b"].accepted - before["uav-b"] == 1
        async with asyncio.timeout(WAIT):
            while len(_accepted(ia, skip)) < len(taken) + 1:  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        records = _accepted(ia, skip)
        assert [conv for peer, conv in records if peer == "uav-a"] == [f"uav-a-{c}" for c in taken]
        assert [conv for peer, conv in records if peer == "uav-b"] == ["uav-b-b-after"]
        assert ia._lane_queued == {} and ia._lane_raw == 0
        assert ia.lane_failed == 0


async def test_a_refusal_that_raises_leaves_the_consumer_taking(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Refusing an envelope that does not open raises (the refusal's audit broke): counted
    once in ``inbox_failed``; uav-a's next message is still taken."""
    async with trio(lane=True) as t:
        ia = t.ia
        real = ia._not_opened
        broke: list[Exception] = []

        def not_opened(stats: Any, exc: Exception) -> None:
            ia._not_opened = real  # type: ignore[method-assign]
            broke.append(exc)
            raise RuntimeError("the refusal's audit broke")

        ia._not_opened = not_opened  # type: ignore[method-assign]
        transport = t.senders["uav-a"].platform.transport
        with caplog.at_level(logging.ERROR, logger="agents._interface"):
            # what an outsider writes on hub's ACL key: no envelope at all
            await transport.publish(t.hub.key("acl"), b"not an envelope")
            async with asyncio.timeout(WAIT):
                while not broke:  # noqa: ASYNC110
                    await asyncio.sleep(0.005)
            await t.tell("uav-a", "a-after")
            await t.until_got("a-after")
        assert ia.inbox_failed == 1
        assert sum("refusing the envelope from ? failed" in r.getMessage() for r in caplog.records)
        assert ia._lane_queued == {} and ia._lane_raw == 0


@pytest.mark.parametrize("fault", [KeyboardInterrupt, asyncio.CancelledError])
async def test_interrupts_and_cancellation_pass_through_the_consumer(
    fault: type[BaseException], caplog: pytest.LogCaptureFixture
) -> None:
    """What is no fault of one item (an interrupt, a cancellation) leaves the consumer as
    raised: not counted in ``inbox_failed``, not logged as a failure; the peer's count the
    item held is released all the same."""
    async with trio(lane=True) as t:
        ia = t.ia
        agent = t.senders["uav-a"]
        message = agent.message(Performative.INFORM, t.sink.aid, POISON, ontology="demo")
        seal = agent.platform.channel.sessions.seal  # type: ignore[union-attr]
        item = ia._lane_take(seal("hub", message.to_json()))
        assert item is not None and item[0] == "uav-a" and ia._lane_queued == {"uav-a": 1}

        def take(*args: Any) -> bool:
            raise fault()

        async def one() -> AsyncIterator[Any]:
            yield item

        ia._take_now = take  # type: ignore[method-assign]
        with caplog.at_level(logging.ERROR, logger="agents._interface"), pytest.raises(fault):
            await ia._receive(one())  # type: ignore[arg-type]
        assert ia.inbox_failed == 0 and ia._lane_queued == {}
        assert not [r for r in caplog.records if "failed" in r.getMessage()]


@pytest.mark.parametrize("raw", [False, True], ids=["opened-on-the-lane", "left-unopened"])
async def test_the_lanes_count_an_envelope_held_is_released_when_it_raises(raw: bool) -> None:
    """The consumer driven with what hub's lane queued for it: uav-a's envelope that raises
    (opened there, or left unopened as behind others) releases the count it held, once, and
    the consumer takes uav-a's next envelope after it."""
    async with trio(lane=True) as t:
        ia = t.ia
        agent = t.senders["uav-a"]
        seal = agent.platform.channel.sessions.seal  # type: ignore[union-attr]

        def envelope(content: str) -> bytes:
            message = agent.message(
                Performative.INFORM, t.sink.aid, content, ontology="demo", conversation_id=content
            )
            return seal("hub", message.to_json())

        if raw:
            ia._lane_raw += 1  # as while the loop opens others: this one goes unopened
        items = [ia._lane_take(envelope(POISON)), ia._lane_take(envelope("next"))]
        if raw:
            ia._lane_raw -= 1
        assert all(item is not None for item in items)
        assert ia._lane_raw == (2 if raw else 0)
        assert ia._lane_queued == ({} if raw else {"uav-a": 2})
        raised = _poisoned(ia, "_take_now")

        async def queued() -> AsyncIterator[Any]:
            for item in items:
                yield item

        await ia._receive(queued())  # type: ignore[arg-type]
        await t.until_got("next")
        assert raised == ["_take_now"] and ia.inbox_failed == 1
        assert POISON not in t.sink.got
        assert ia._lane_raw == 0 and ia._lane_queued == {}


class Reading(BaseModel):
    """What the checker expects: its validation error quotes the input it failed on."""

    wind_m_s: float


class Checker(Agent):
    """Answers ``demo`` requests by validating them, in line and in a task of their own."""

    @on_request("demo")
    async def _check(self, message: ACLMessage) -> Any:
        return Reading.model_validate(message.content).model_dump()

    @on_request("demo-concurrent", concurrent=True)
    async def _check_apart(self, message: ACLMessage) -> Any:
        return Reading.model_validate(message.content).model_dump()

    @on(MessageTemplate(Performative.INFORM, where=lambda m: int(m.content["n"]) > 0))
    async def _count(self, message: ACLMessage) -> None:
        """Never reached here: its template raises on what the test sends."""


async def test_a_handler_raising_on_a_remote_message_logs_not_its_content(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A handler (or a template's predicate) that raises on another platform's message,
    decrypted, logs what failed, its sender and the exception's type and place, never
    the exception's text: pydantic's (and int()'s) quote the input they failed on. The
    sender still gets its failure with the reason: the content was its own."""
    async with trio(lane=False) as t:
        checker = await t.hub.add(Checker("checker"))
        assert t.hub.df is not None
        await t.hub.df.register(
            ServiceDescription(
                name="checker-svc", type="demo", provider=checker.aid, visibility="protected"
            )
        )
        asker = t.senders["uav-a"]
        with caplog.at_level(logging.DEBUG, logger="agents"):
            for ontology in ("demo", "demo-concurrent"):
                with pytest.raises(Failed, match="validation error") as failed:
                    await request(
                        asker, "checker@hub", {"wind_m_s": POISON}, ontology=ontology, timeout=WAIT
                    )
                assert POISON in str(failed.value.message.content)  # its own, back to it
            await asker.send(
                asker.message(Performative.INFORM, "checker@hub", {"n": POISON}, ontology="n")
            )
            async with asyncio.timeout(WAIT):
                while not [r for r in caplog.records if "choosing a handler" in r.getMessage()]:  # noqa: ASYNC110
                    await asyncio.sleep(0.005)
        failed_logs = [r for r in caplog.records if "failed on" in r.getMessage()]
        assert len(failed_logs) == 3, [r.getMessage() for r in failed_logs]
        assert POISON not in caplog.text
        assert not [r for r in caplog.records if POISON in r.getMessage() + (r.exc_text or "")]
        logged = [r.getMessage() for r in failed_logs]
        assert sum("ValidationError" in m for m in logged) == 2
        assert "ValueError" in logged[2] and "talker@uav-a" in logged[2]


@pytest.mark.parametrize("step", ["deliver", "admit"])
async def test_a_delivery_that_raises_logs_not_what_it_delivered(
    step: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Handing a message of uav-a to hub's agent raises (a fault quoting what it failed
    on): logged with what failed, its peer and the exception's type and place, never
    the message; uav-a's next message is delivered."""
    async with trio(lane=False) as t:
        raised: list[str] = []
        if step == "deliver":  # the common path: one receiver, taken at once
            target: Any = t.sink
            real = target._deliver

            def broken(message: ACLMessage) -> Any:
                if not raised and POISON in repr(message):
                    raised.append(step)
                    raise RuntimeError(f"cannot deliver {message!r}")
                return real(message)

            target._deliver = broken
        else:  # the full path: a message to two agents here
            target = t.ia
            real_admit = target._admit

            async def broken_admit(host: Any, peer: str, message: ACLMessage) -> Any:
                if not raised and POISON in repr(message):
                    raised.append(step)
                    raise RuntimeError(f"cannot admit {message!r}")
                return await real_admit(host, peer, message)

            target._admit = broken_admit
            target._admit_now = lambda *args: False
        talker = t.senders["uav-a"]
        with caplog.at_level(logging.DEBUG, logger="agents"):
            await talker.send(
                talker.message(
                    Performative.INFORM,
                    ["sink@hub", "nobody@hub"] if step == "admit" else "sink@hub",
                    POISON,
                    ontology="demo",
                )
            )
            async with asyncio.timeout(WAIT):
                while not raised:  # noqa: ASYNC110
                    await asyncio.sleep(0.005)
            await t.tell("uav-a", "a-after")
            await t.until_got("a-after")
        assert raised == [step]
        failed = [r.getMessage() for r in caplog.records if "delivering from" in r.getMessage()]
        assert len(failed) == 1 and "RuntimeError" in failed[0], failed
        assert POISON not in caplog.text
        assert not [r for r in caplog.records if POISON in r.getMessage() + (r.exc_text or "")]


async def test_a_lane_answer_that_raises_on_its_thread_logs_not_what_it_opened(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The lane's answering on zenoh's thread raises (a fault quoting the body it opened):
    logged with its peer and the exception's type and place, never the body; the loop
    takes the message as usual."""
    async with trio(lane=True) as t:
        ia = t.ia
        real = ia._lane_answer
        raised: list[int] = []

        def broken(*args: Any) -> Any:
            if not raised and POISON in repr(args):
                raised.append(1)
                raise RuntimeError(f"cannot answer {args!r}")
            return real(*args)

        ia._lane_answer = broken  # type: ignore[method-assign]
        with caplog.at_level(logging.DEBUG, logger="agents"):
            await t.tell("uav-a", POISON)
            await t.until_got(POISON)
        assert raised == [1]
        said = [r.getMessage() for r in caplog.records if "receiving thread" in r.getMessage()]
        assert len(said) == 1 and "RuntimeError" in said[0], said
        assert POISON not in caplog.text
        assert not [r for r in caplog.records if POISON in r.getMessage() + (r.exc_text or "")]


async def test_a_release_of_the_lanes_count_that_raises_leaves_the_consumer_taking(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The lane's count out of step (a fault of the code: a count released twice raises
    KeyError) ends no consumer: the release that raises is logged and counted in
    ``lane_failed``, and uav-a's and uav-b's next messages are still taken."""
    async with trio(lane=True) as t:
        ia = t.ia
        real = ia._lane_release
        broke: list[str] = []

        def release(peer: str) -> None:
            if not broke:
                broke.append(peer)
                raise KeyError(peer)
            real(peer)

        ia._lane_release = release  # type: ignore[method-assign]
        with caplog.at_level(logging.ERROR, logger="agents._interface"):
            await t.tell("uav-a", "a-first")
            await t.until_got("a-first")
            await t.tell("uav-a", "a-after")
            await t.tell("uav-b", "b-after")
            await t.until_got("a-after", "b-after")
        assert broke == ["uav-a"]
        assert ia.lane_failed == 1 and ia.inbox_failed == 0
        logged = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(logged) == 1
        assert "releasing the lane's count of a message from uav-a failed (" in logged[0]
        assert "KeyError" in logged[0]
