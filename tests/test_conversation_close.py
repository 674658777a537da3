"""A closed conversation: a late reply to it is dropped and counted as late while the agent
remembers it (its last 4096 closed conversation ids and reply keys), not understood after; a
receive after the close raises, with the close's error when it had one."""

from __future__ import annotations

import asyncio

import pytest

from agents import ConversationError, MessageTemplate, new_id
from agents._agent import _CLOSED_KEPT
from tests.test_agents import P, Recorder, _keep, msg, platforms


async def test_late_replies_count_as_late_for_the_last_closed_conversations_only() -> None:
    async with asyncio.timeout(20), platforms("p") as [p]:
        asker = await p.add(Recorder("asker"))
        asker.add_handler(MessageTemplate(P.QUERY_REF), _keep(asker, "query"))
        answerer = await p.add(Recorder("answerer"))
        keys = []
        for _ in range(_CLOSED_KEPT // 2 + 1):  # two ids each: one more than it keeps
            with asker.conversation(new_id("c"), peers=[answerer.aid]) as conv:
                key = new_id("r")
                conv.expect(key)
                keys.append((conv.id, key))
        oldest, newest = keys[0], keys[-1]
        for conversation_id, key in (newest, oldest):
            late = msg(answerer, asker.aid, P.INFORM, conversation_id=conversation_id)
            await answerer.send(late.model_copy(update={"in_reply_to": key}))
        # taken after both (one mailbox, in order): by then both were decided
        await answerer.send(msg(answerer, asker.aid, P.QUERY_REF))
        assert (await asker.next())[0] == "query"
        assert (asker.stats.late, asker.stats.not_understood) == (1, 1)


async def test_a_receive_after_the_close_raises_its_error() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        asker = await p.add(Recorder("asker"))
        plain = asker.conversation(new_id("c"))
        plain.close()
        failed = asker.conversation(new_id("c"))
        failed.close(ConnectionError("gone"))
        for _ in range(2):  # and again: it stays ended
            with pytest.raises(ConversationError):
                await plain.receive()
            with pytest.raises(ConnectionError, match="gone"):
                await failed.receive()


async def test_a_full_conversation_drops_its_oldest_reply_counts_and_logs_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        asker = await p.add(Recorder("asker"))
        answerer = await p.add(Recorder("answerer"))
        conv = asker.conversation(new_id("c"), peers=[answerer.aid], maxlen=2)
        with conv, caplog.at_level("WARNING", logger="agents._agent"):
            for i in range(3):  # none read meanwhile: the third finds it full
                reply = msg(answerer, asker.aid, P.INFORM, conversation_id=conv.id)
                await answerer.send(reply.model_copy(update={"content": i}))
            assert [(await conv.receive()).content for _ in range(2)] == [1, 2]
            assert asker.stats.conversation_overflow == 1
            assert conv._items.dropped == 1
            assert conv.pending() == 0
        assert sum("oldest reply dropped" in r.getMessage() for r in caplog.records) == 1
        with pytest.raises(ConversationError):  # closed: the end marker went in
            await conv.receive()
