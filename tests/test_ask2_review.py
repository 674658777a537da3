"""A review's probes of the asker's lane (`InterfaceAgent.lane_replies`): replies opened and
parsed on zenoh's thread, taken on the loop in one callback into their conversations.

Real zenoh sessions on loopback (the pair of `tests/test_answer_on_thread.py`, the asker
``operator`` with the lane). Each probe attacks as a peer would (envelopes sealed with
uav-a's own session table, given to operator's lane as zenoh's thread gives them) and
compares ``lane_replies`` on and off: the loop must decide every reply the lane hands over
as it decides one it took from the inbox, and lose or take twice none.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from agents import ACLMessage, Performative
from tests.test_answer_on_thread import WAIT, pair
from tests.test_reply_on_thread import (
    ANSWER,
    _asked,
    _counts,
    _delta,
    _on_thread,
    _quiet,
    _records,
    _reply,
    _until,
    _warm,
)


def _sealed(p: Any, message: ACLMessage) -> bytes:
    """``message`` sealed by uav-a for operator (uav-a's own session: authentic)."""
    return p.ia_a.sessions.seal("operator", message.to_json())


async def _other_agent(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, taken = _counts(p), ia.replies_on_thread
        request, asked = await _asked(p, "other-agent", timeout=1.0)
        # uav-a's gateway, not the federation agent asked, answers in its conversation
        # (its identifiers read off the request the peer received: a guess is as good)
        forged = request.reply(Performative.INFORM, {"forged": True}, sender=p.gateway.aid)
        took = await _on_thread(p, [_sealed(p, forged)])
        await _until(lambda: _counts(p)[0] == before[0] + 1)
        await _quiet(p)
        resolved = asked.done() and not asked.cancelled() and asked.exception() is None
        asked.cancel()
        return (
            _delta(_counts(p), before)[:3],
            resolved,
            ia.replies_on_thread - taken,
            took[0] is None,
        )


async def test_a_reply_from_an_agent_not_asked_is_not_handed_over_as_one_waited_for() -> None:
    """Another agent of the asked platform answers in the conversation: it never resolves
    the request either way, and the lane does not take it for a reply its conversation
    waits for (the conversation refuses it: it is the mailbox's), nor count it so."""
    lane = await _other_agent(True)
    loop = await _other_agent(False)
    assert lane[:2] == loop[:2] == ((1, 1, 1), False)
    assert (lane[2], lane[3]) == (0, False)  # queued for the loop, as any other message


async def _spoofed_platform(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip, taken = _counts(p), len(ia.audit.records), ia.replies_on_thread
        request, asked = await _asked(p, "spoofed", timeout=1.0)
        # in uav-a's authentic envelope, a reply claiming an agent of a third platform
        forged = request.reply(Performative.INFORM, ANSWER, sender="federation@uav-b")
        took = await _on_thread(p, [_sealed(p, forged)])
        assert took[0] is not None and took[0][0] == "uav-a"  # not handed over
        await _until(lambda: len(_records(p, skip)) >= 1)
        await _quiet(p)
        assert not asked.done()
        asked.cancel()
        return (
            _delta(_counts(p), before),
            [(v, perf, code) for v, perf, _, code in _records(p, skip)],
            ia.replies_on_thread - taken,
        )


async def test_a_reply_claiming_a_sender_of_another_platform_is_refused_as_on_the_loop() -> None:
    """A sender of another platform than its envelope's: refused the same way, never taken."""
    lane = await _spoofed_platform(True)
    assert lane == await _spoofed_platform(False)
    counts, records, taken = lane
    assert counts[1:3] == (0, 0) and taken == 0  # nothing of it received
    assert [verdict for verdict, _, _ in records] == ["dropped"]


async def _duplicate(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip, taken = _counts(p), len(ia.audit.records), ia.replies_on_thread
        request, asked = await _asked(p, "twice")
        # the same reply in two envelopes of their own (a peer that sent it twice: each
        # authentic, neither a replay), taken one after the other as zenoh's thread does
        first, second = _reply(p, request), _reply(p, request, {"second": True})
        await _on_thread(p, [first, second])
        assert await asyncio.wait_for(asked, WAIT) == ANSWER
        await _until(lambda: _counts(p)[0] == before[0] + 2)
        await _quiet(p)
        return (
            _delta(_counts(p), before),
            [(v, perf, code) for v, perf, _, code in _records(p, skip)],
            ia.replies_on_thread - taken,
        )


async def test_a_reply_sent_twice_resolves_the_request_with_the_first_either_way() -> None:
    """The first of two replies answers the request; the second is the loop's (the lane has
    handed the first over), with the same counts and records either way."""
    lane = await _duplicate(True)
    loop = await _duplicate(False)
    assert lane[1] == loop[1]  # the same records
    # the same counts but one: the lane's first reply is taken a turn before the second,
    # so the asker's task has closed the conversation when the second comes (late); the
    # loop takes both in one turn, and the second is left in the closed conversation
    assert lane[0][:6] == loop[0][:6] == (2, 2, 2, 0, 0, 2)
    assert lane[0][6] + loop[0][6] <= 1  # late at most once, and only the second
    assert (lane[2], loop[2]) == (1, 0)


async def _batched(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip, taken = _counts(p), len(ia.audit.records), ia.replies_on_thread
        request, asked = await _asked(p, "batched")
        answer = request.reply(Performative.INFORM, ANSWER, sender=request.receivers[0])
        body = b"[" + answer.to_json() + b"]"  # a batch of one (docs/wire.md)
        took = await _on_thread(p, [p.ia_a.sessions.seal("operator", body)])
        assert took[0] is not None and took[0][0] == "uav-a"  # the loop's: a batch
        assert await asyncio.wait_for(asked, WAIT) == ANSWER
        await _quiet(p)
        return (
            _delta(_counts(p), before),
            [(v, perf, code) for v, perf, _, code in _records(p, skip)],
            ia.replies_on_thread - taken,
        )


async def test_a_reply_in_a_batch_is_left_to_the_loop_and_taken_as_there() -> None:
    """A reply in a batch envelope is never the lane's: taken by the loop, the same either way."""
    lane = await _batched(True)
    assert lane == await _batched(False)
    assert lane[0][:3] == (1, 1, 1) and lane[2] == 0


async def test_replies_handed_over_while_the_loop_closes_their_conversations_are_all_decided() -> (
    None
):
    """The thread looks conversations up while the loop opens and closes them: every reply
    handed over is taken once (its request answered, or dropped as late), none lost, no
    count held for its peer, and nothing raised on either thread."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        before = _counts(p)
        n = 24
        asks = [await _asked(p, f"race-{i}", timeout=5.0) for i in range(n)]
        envelopes = [_reply(p, request) for request, _ in asks]
        took: list[Any] = []

        async def hand_over() -> None:
            for envelope in envelopes:  # one a thread's call, the loop running between
                took.extend(await _on_thread(p, [envelope]))
                await _quiet(p)  # taken: the next finds nothing of uav-a held

        async def close_every_other() -> None:
            for i in range(0, n, 2):  # spread over the hand-overs (a millisecond apart)
                p.fed_op._by_conv[f"race-{i}"].close()
                await asyncio.sleep(0.001)

        await asyncio.gather(hand_over(), close_every_other())
        answered = 0
        for i, (_, asked) in enumerate(asks):
            if i % 2:
                assert await asyncio.wait_for(asked, WAIT) == ANSWER
                answered += 1
            else:
                try:
                    await asyncio.wait_for(asked, WAIT)
                except Exception as exc:  # closed: ConversationError
                    assert type(exc).__name__ == "ConversationError"
        assert answered == n // 2
        await _until(lambda: _counts(p)[0] == before[0] + n)
        await _quiet(p)
        assert not ia._lane_handed and not ia._lane_done and ia._lane_queued == {}
        assert _delta(_counts(p), before)[6] == n // 2  # the closed ones' replies: late
        assert sum(t is None for t in took) >= n // 4  # the thread handed many over


async def _stopping(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip = _counts(p), len(ia.audit.records)
        request, asked = await _asked(p, "stopping", timeout=1.0)
        envelope = _reply(p, request)
        handed = ia._lane_take(envelope)  # here: the loop runs nothing before the stop
        stop = asyncio.ensure_future(p.fed_op.stop())  # stops at the loop's next turns
        if handed is not None:
            inbox = ia._lane_inbox
            assert inbox is not None
            inbox.put(handed)
        await asyncio.wait_for(stop, WAIT)
        await asyncio.wait([asked], timeout=WAIT)
        await _quiet(p)
        error = asked.exception()
        outcome = "resolved" if error is None else type(error).__name__
        await _until(lambda: len(_records(p, skip)) >= 1)
        return (
            handed is None,
            outcome,
            _delta(_counts(p), before),
            [(v, perf) for v, perf, _, _ in _records(p, skip)],
        )


async def test_a_reply_handed_over_as_its_agent_stops_is_decided_as_on_the_loop() -> None:
    """Handed over, then its agent stops before the loop takes it: the same outcome, counts
    and records as when the loop takes it from the inbox."""
    lane = await _stopping(True)
    loop = await _stopping(False)
    assert (lane[0], loop[0]) == (True, False)
    assert lane[1:] == loop[1:]


async def _limited(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, taken = _counts(p), ia.replies_on_thread
        request, asked = await _asked(p, "limited", timeout=1.0)
        state = ia._senders["uav-a"]
        assert state.total is not None
        with state.lock:  # uav-a has sent all its limit allows, and gets no more
            state.total.rate = 0.0
            state.total.tokens = 0.0
        took = await _on_thread(p, [_reply(p, request)])
        await _until(lambda: state.stats.limited == 1)
        await _quiet(p)
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asked, WAIT)
        return (
            took[0] is None,
            _delta(_counts(p), before),
            (state.stats.accepted, state.stats.limited),
            p.asker.stats.rate_limited,
            ia.replies_on_thread - taken,
        )


async def test_a_reply_over_its_platforms_limit_is_refused_as_on_the_loop() -> None:
    """Handed over, then found over uav-a's total limit on the loop: back to the inbox and
    limited there, the same counts either way; its request is left to time out."""
    lane = await _limited(True)
    loop = await _limited(False)
    assert (lane[0], loop[0]) == (True, False)
    assert lane[1:] == loop[1:]
    assert lane[1][:3] == (0, 0, 0) and lane[4] == 0
