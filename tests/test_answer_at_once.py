"""`Agent.answer_at_once`: a read answered as it comes from another platform, or not at all.

Two platforms on one MemoryHub, each with its Interface Agent (the helpers of
`test_interface`). What is asserted is what a user relies on: the answer is the one the
handler would give, counted and audited as any; nothing that the Interface Agent would
refuse reaches the hook; and a message is never answered before one queued ahead of it.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from agents import (
    LATER,
    ACLMessage,
    Agent,
    AgentPlatform,
    Failed,
    HandedOver,
    MessageTemplate,
    Performative,
    RateLimit,
    Refused,
    ServiceDescription,
    on,
    on_query,
    on_request,
    query_ref,
    request,
)
from tests.test_interface import WAIT, audited, federation, ia, records

P = Performative


class Reader(Agent):
    """Answers ``{"read": key}`` query-refs at once from its table; the handler answers the rest."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.table: dict[str, Any] = {"speed": 12.5, "mode": "survey"}
        self.asked: list[ACLMessage] = []  # what reached `answer_at_once`
        self.handled: list[ACLMessage] = []  # what reached the handler
        self.release = asyncio.Event()
        self.blocked = asyncio.Event()

    def answer_at_once(self, message: ACLMessage) -> Any:
        """The table's value for a plain read; LATER for anything else; raises on "boom"."""
        self.asked.append(message)
        content = message.content
        if not isinstance(content, dict) or set(content) != {"read"}:
            return LATER
        if content["read"] == "boom":
            raise RuntimeError("the hook broke")
        if content["read"] == "unsendable":
            return HandedOver({1: "a key JSON cannot carry"})  # a promise broken
        return {"value": self.table.get(content["read"]), "by": "at-once"}

    @on_query("demo")
    async def _read(self, message: ACLMessage) -> Any:
        self.handled.append(message)
        content = message.content
        if isinstance(content, dict) and content.get("read") == "boom":
            raise RuntimeError("the handler broke too")
        if isinstance(content, dict) and "read" in content:
            return {"value": self.table.get(content["read"]), "by": "handler"}
        return {"other": content}

    @on_request("demo")
    async def _block(self, message: ACLMessage) -> Any:
        """Holds the agent's receive loop until ``release``: what comes meanwhile is queued."""
        self.handled.append(message)
        self.blocked.set()
        await self.release.wait()
        return "released"


async def reader(platform: AgentPlatform, visibility: str = "protected") -> Reader:
    """A `Reader` on ``platform``, offering a ``demo`` service of ``visibility``."""
    agent = await platform.add(Reader("reader"))
    assert platform.df is not None
    await platform.df.register(service(agent, visibility))
    return agent


def service(agent: Agent, visibility: str) -> ServiceDescription:
    """The reader's service description, of ``visibility``."""
    return ServiceDescription(
        name="reader-svc", type="demo", provider=agent.aid, visibility=visibility
    )


async def test_a_read_is_answered_at_once_counted_and_audited_as_the_handler_would() -> None:
    """The answer comes from the hook, not the handler; every count and record is as usual."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await reader(pb)
        asker = await pa.add(Agent("asker"))
        sent_before = pb.stats.sent_remote

        got = await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")

        assert got == {"value": 12.5, "by": "at-once"}
        assert r.handled == []
        assert [m.content for m in r.asked] == [{"read": "speed"}]
        assert (r.stats.received, r.stats.handled, r.stats.answered_at_once) == (1, 1, 1)
        assert len(r._mailbox) == 0
        assert pb.stats.sent_remote == sent_before + 1
        # the question accepted and audited on uav-b, the answer on uav-a, as any
        asked = await audited(pb, performative="query-ref", verdict="accepted")
        assert asked["sender"] == "asker@uav-a"
        assert asked["receivers"] == ["reader@uav-b"]
        answer = await audited(pa, performative="inform", verdict="accepted")
        assert answer["sender"] == "reader@uav-b"
        assert answer["conversation_id"] == asked["conversation_id"]
        assert ia(pb).audit.counts == {"accepted": 1, "refused": 0, "dropped": 0}


async def test_what_the_hook_leaves_or_fails_on_goes_to_the_handler() -> None:
    """LATER, or an exception in the hook: the handler answers (or fails) as without the hook."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await reader(pb)
        asker = await pa.add(Agent("asker"))

        assert await query_ref(asker, "reader@uav-b", ["not", "a", "read"], ontology="demo") == {
            "other": ["not", "a", "read"]
        }
        with pytest.raises(Failed, match="the handler broke too"):
            await query_ref(asker, "reader@uav-b", {"read": "boom"}, ontology="demo")

        # an answer that cannot be sent: the handler answers, and the inbox goes on
        assert await query_ref(asker, "reader@uav-b", {"read": "unsendable"}, ontology="demo") == {
            "value": None,
            "by": "handler",
        }
        assert len(r.asked) == 3
        assert [m.content for m in r.handled] == [
            ["not", "a", "read"],
            {"read": "boom"},
            {"read": "unsendable"},
        ]
        assert r.stats.answered_at_once == 0
        assert r.stats.handler_errors == 1
        got = await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert got == {"value": 12.5, "by": "at-once"}


async def test_nothing_is_answered_at_once_ahead_of_what_waits_in_the_mailbox() -> None:
    """While a message waits in the mailbox, a read is queued behind it and answered in order."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await reader(pb)
        asker = await pa.add(Agent("asker"))

        first = asyncio.create_task(request(asker, "reader@uav-b", "hold", ontology="demo"))
        async with asyncio.timeout(WAIT):
            await r.blocked.wait()  # the receive loop is held in the first handler
        second = asyncio.create_task(request(asker, "reader@uav-b", "queued", ontology="demo"))
        # the second request is in the mailbox once uav-b's Interface Agent took it
        async with asyncio.timeout(WAIT):
            while len(r._mailbox) == 0:  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        third = asyncio.create_task(
            query_ref(asker, "reader@uav-b", {"read": "mode"}, ontology="demo")
        )
        async with asyncio.timeout(WAIT):
            while len(r._mailbox) < 2:  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        assert not third.done()
        r.release.set()
        assert await first == "released"
        assert await second == "released"
        assert await third == {"value": "survey", "by": "handler"}
        assert [m.content for m in r.handled] == ["hold", "queued", {"read": "mode"}]
        assert r.stats.answered_at_once == 0
        # the hook was asked of the first (LATER: not a read); not while its handler ran
        assert [m.content for m in r.asked] == ["hold"]


async def test_a_read_the_interface_agent_refuses_never_reaches_the_hook() -> None:
    """Private service, and the per-platform request limit: refused, counted, audited first."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b", rate_limit=RateLimit(rate=0.001, burst=2.0))
        r = await reader(pb, visibility="private")
        asker = await pa.add(Agent("asker"))

        with pytest.raises(Refused, match="access denied"):
            await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert r.asked == []
        refused = await audited(pb, "access denied", verdict="refused")
        assert refused["performative"] == "query-ref"
        assert refused["from"] == "uav-a"
        assert pb.stats.denied == 1

        # made protected: the second request of the burst is answered at once, the third
        # is over the limit and refused before anything reads it
        assert pb.df is not None
        await pb.df.modify(service(r, "protected"))
        got = await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert got == {"value": 12.5, "by": "at-once"}
        with pytest.raises(Refused, match="rate limit exceeded"):
            await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert len(r.asked) == 1
        assert r.handled == []
        assert r.stats.answered_at_once == 1
        assert pb.stats.rate_limited == 1
        limited = await audited(pb, verdict="dropped", stage="rate-limit")
        assert limited["from"] == "uav-a"
        assert limited["count"] == 1
        assert len(records(pb, verdict="accepted", performative="query-ref")) == 1


async def test_an_answer_that_went_is_not_sent_again_when_what_follows_it_fails() -> None:
    """Sent at once, then renewing the session fails: the handler does not answer a second time."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await reader(pb)
        asker = await pa.add(Agent("asker"))

        def broken(platform: str) -> None:
            raise RuntimeError("renewal broke")

        ia(pb)._sent = broken  # type: ignore[method-assign]
        got = await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert got == {"value": 12.5, "by": "at-once"}
        assert r.handled == []
        assert r.stats.answered_at_once == 1
        # one answer only: a second would reach the asker as a late reply
        await query_ref(asker, "reader@uav-b", {"read": "mode"}, ontology="demo")
        assert asker.stats.received == 2
        assert asker.stats.late == 0


class ConcurrentReader(Reader):
    """A `Reader` whose ``slow`` informs each run in a task of their own."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.slow: list[Any] = []

    @on(MessageTemplate(ontology="slow"), concurrent=True)
    async def _slow(self, message: ACLMessage) -> None:
        self.slow.append(message.content)
        if message.content == "boom":
            raise RuntimeError("the concurrent handler broke")


async def test_reads_are_answered_at_once_again_after_a_concurrent_handler_never_started() -> None:
    """A concurrent handler's task cancelled before its first step (its agent's tasks
    cancelled, say), or one that fails: the next read is answered at once, not left to
    the handler as if that task were still to start."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        r = await pb.add(ConcurrentReader("reader"))
        assert pb.df is not None
        await pb.df.register(service(r, "protected"))
        asker = await pa.add(Agent("asker"))
        spawn = r._spawn
        cancelled: list[asyncio.Task[Any]] = []

        def spawn_then_cancel(coro: Any, name: str) -> asyncio.Task[Any]:
            task = spawn(coro, name)
            if name == "handle":
                task.cancel()  # in the turn that made it: it never runs a step
                cancelled.append(task)
            return task

        r._spawn = spawn_then_cancel  # type: ignore[method-assign]
        await asker.send(asker.message(P.INFORM, "reader@uav-b", "never", ontology="slow"))
        async with asyncio.timeout(WAIT):
            while not (cancelled and cancelled[0].done()):  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        assert cancelled[0].cancelled() and r.slow == []
        del r._spawn  # the class's again
        got = await query_ref(asker, "reader@uav-b", {"read": "speed"}, ontology="demo")
        assert got == {"value": 12.5, "by": "at-once"}
        assert r.stats.answered_at_once == 1

        await asker.send(asker.message(P.INFORM, "reader@uav-b", "boom", ontology="slow"))
        async with asyncio.timeout(WAIT):
            while r.stats.handler_errors == 0:  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        got = await query_ref(asker, "reader@uav-b", {"read": "mode"}, ontology="demo")
        assert got == {"value": "survey", "by": "at-once"}
        assert r.stats.answered_at_once == 2 and r.handled == []
