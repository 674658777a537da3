"""The asker's lane: a reply opened and parsed on zenoh's thread, taken on the loop in one
callback into the conversation waiting for it (`InterfaceAgent.lane_replies`).

Two platforms over two real zenoh sessions on loopback (one process, `test_answer_on_thread`'s
pair): the asker ``operator`` has the lane (one lane a process: the provider ``uav-a`` has
none). Each test compares ``lane_replies`` on and off where the decision matters: the same
results, refusals, counts and audit records; the replies crafted here are sealed with
uav-a's own session table, as its agents' answers are, and given to operator's lane as
zenoh's thread gives them.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import orjson
import pytest

from agents import ACLMessage, Performative
from agents._agent import ConversationError
from agents._interface import _RAW
from tests.test_answer_on_thread import LATEST, WAIT, Pair, _until, pair, sealed_requests

ANSWER = {"heli-altitude": {"samples": [[120.0, 1.0]]}}  # any content: the request returns it


async def _warm(p: Pair) -> None:
    """Two real round trips (operator's sender state, uav-a's publisher), then quiet."""
    for _ in range(2):
        await p.fed_op.request_from("uav-a", LATEST)
    await _quiet(p)


async def _quiet(p: Pair) -> None:
    ia = p.ia_op
    await _until(lambda: not ia._lane_done and ia._lane_queued == {})


async def _asked(p: Pair, conv: str, **kw: Any) -> tuple[ACLMessage, Any]:
    """operator's request in ``conv``, captured (not sent) and opened as uav-a would; its future."""
    sealed, (asked,) = await sealed_requests(p, [(LATEST, conv)], **kw)
    _, body = p.ia_a.sessions.open(sealed[0])
    return ACLMessage.from_json(body), asked


def _reply(p: Pair, request: ACLMessage, content: Any = ANSWER) -> bytes:
    """uav-a's inform answering ``request``, sealed for operator."""
    answer = request.reply(Performative.INFORM, content, sender=request.receivers[0])
    return p.ia_a.sessions.seal("operator", answer.to_json())


async def _on_thread(p: Pair, envelopes: list[bytes]) -> list[Any]:
    """operator's lane takes ``envelopes`` on another thread; what it queues is queued."""
    ia = p.ia_op
    took = await asyncio.to_thread(lambda: [ia._lane_take(e) for e in envelopes])
    inbox = ia._lane_inbox
    assert inbox is not None
    for item in took:
        if item is not None:
            inbox.put(item)
    return took


def _records(p: Pair, skip: int = 0) -> list[tuple[Any, ...]]:
    """operator's audit records after the first ``skip``: those of uav-a's messages it
    accepted and every refusal, as (verdict, performative, conversation, code)."""
    return [
        (
            r["verdict"],
            r.get("performative"),
            r.get("conversation_id"),
            r.get("code") or (r.get("reason") or "").partition(":")[0] or None,
        )
        for r in list(p.ia_op.audit.records)[skip:]
        if r.get("from") == "uav-a" or r["verdict"] != "accepted"
    ]


def _counts(p: Pair) -> tuple[int, ...]:
    stats, sender = p.asker.stats, p.asker.stats.senders["uav-a"]
    agent = p.fed_op.stats
    return (
        sender.accepted,
        stats.received_remote,
        stats.local,
        stats.unauthenticated,
        stats.malformed,
        agent.received,
        agent.late,
        agent.dropped,
    )


def _delta(after: tuple[int, ...], before: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(a - b for a, b in zip(after, before, strict=True))


async def _round_trips(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        loop_thread = threading.get_ident()
        handed: list[list[Any]] = []  # per reply seen there: [on the loop, handed]
        real = ia._lane_reply

        def watched(*args: Any) -> bool:
            seen = [threading.get_ident() == loop_thread, None]
            handed.append(seen)
            seen[1] = got = real(*args)
            return got

        ia._lane_reply = watched  # type: ignore[method-assign]
        before, skip, taken = _counts(p), len(ia.audit.records), ia.replies_on_thread
        answers = [await p.fed_op.request_from("uav-a", LATEST) for _ in range(8)]
        await _quiet(p)
        await _until(lambda: len(_records(p, skip)) >= 8)
        informs = [r for r in _records(p, skip) if r[1] == "inform"]
        on_thread = ia.replies_on_thread - taken
        # (the thread notes what it handed over once the loop may have taken it already)
        await _until(lambda: all(got is not None for _, got in handed))
        if replies:
            assert on_thread == 8  # warm: every one of them
            assert handed and all(not on_loop for on_loop, _ in handed)
            assert sum(got for _, got in handed) == on_thread
        else:
            assert on_thread == 0 and not any(got for _, got in handed)
        return (
            [a["heli-altitude"]["samples"][0][0] for a in answers],
            _delta(_counts(p), before),
            [(v, perf, code) for v, perf, _, code in informs],
            len({conv for _, _, conv, _ in informs}),
        )


async def test_a_reply_taken_on_the_lane_resolves_the_request_as_the_loop_does() -> None:
    """The same answers, counts and audit records; each reply opened and parsed off the loop."""
    lane = await _round_trips(True)
    assert lane == await _round_trips(False)
    answers, counts, informs, conversations = lane
    assert answers == [120.0] * 8
    assert counts[:3] == (8, 8, 8) and counts[3:5] == (0, 0)
    assert informs == [("accepted", "inform", None)] * 8 and conversations == 8


async def test_a_reply_never_overtakes_nor_is_overtaken_by_its_peers_messages() -> None:
    """Behind a message of uav-a queued for the loop a reply waits for it; a message of uav-a
    after a reply handed to the loop waits for that reply."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        taken = ia.replies_on_thread
        for order in ("behind", "ahead"):
            request, asked = await _asked(p, f"order-{order}")
            other = p.fed_a.message(
                Performative.INFORM, p.fed_op.aid, "unsolicited", conversation_id=f"o-{order}"
            )
            other_env = p.ia_a.sessions.seal("operator", other.to_json())
            reply_env = _reply(p, request)
            skip = len(ia.audit.records)
            envelopes = [other_env, reply_env] if order == "behind" else [reply_env, other_env]
            # taken here, one after the other, as zenoh's thread takes them: the loop runs
            # nothing between (on another thread it might book the first before the second)
            took = [ia._lane_take(x) for x in envelopes]
            if order == "behind":
                # both held for uav-a until the loop took them: the second waits for the first
                assert ia._lane_queued == {"uav-a": 2}
                assert [t[0] if t else t for t in took] == ["uav-a", "uav-a"]  # both queued
            else:
                # handed over (held for uav-a until the loop took it); the loop has work,
                # so the next goes to it unopened, and it books the reply before opening it
                assert ia._lane_queued == {"uav-a": 1} and ia._lane_raw == 1
                assert took[0] is None and took[1][0] is _RAW
            inbox = ia._lane_inbox
            assert inbox is not None
            for item in took:
                if item is not None:
                    inbox.put(item)
            assert await asyncio.wait_for(asked, WAIT) == ANSWER
            await _quiet(p)
            await _until(lambda s=skip: len(_records(p, s)) >= 2)
            convs = [conv for v, _, conv, _ in _records(p, skip) if v == "accepted"]
            expected = [f"o-{order}", f"order-{order}"]
            assert convs == (expected if order == "behind" else expected[::-1])
        assert ia.replies_on_thread == taken + 1  # only the one nothing was ahead of


async def _refusals(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip, taken = _counts(p), len(ia.audit.records), ia.replies_on_thread
        request, asked = await _asked(p, "refused")
        genuine = _reply(p, request)
        env = orjson.loads(genuine)
        box = env["box"]
        forged = orjson.dumps(
            {**env, "box": box[:20] + ("A" if box[20] != "A" else "B") + box[21:]}
        )
        stranger = orjson.dumps({**env, "from": "stranger"})
        await _on_thread(p, [forged, stranger])
        await _until(lambda: _counts(p)[3] == before[3] + 2)
        assert not asked.done()  # neither resolved it
        await _on_thread(p, [genuine, genuine])  # the second a replay
        assert await asyncio.wait_for(asked, WAIT) == ANSWER
        await _until(lambda: _counts(p)[3] == before[3] + 3)
        await _quiet(p)
        return (
            _delta(_counts(p), before),
            [(v, perf, code) for v, perf, _, code in _records(p, skip)],
            ia.replies_on_thread - taken,
        )


async def test_forged_replayed_and_unknown_replies_are_refused_as_on_the_loop() -> None:
    """A forged box, an untrusted sender and a replayed reply: the same refusals either way."""
    lane = await _refusals(True)
    loop = await _refusals(False)
    assert lane[:2] == loop[:2]
    assert lane[0][3] == 3 and lane[2] == 1 and loop[2] == 0
    assert lane[0][:3] == (1, 1, 1)  # the genuine reply alone accepted


async def _ended(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, taken = _counts(p), ia.replies_on_thread
        # timed out before its reply came: the reply is the loop's, dropped as late
        request, asked = await _asked(p, "timed-out", timeout=0.3)
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asked, WAIT)
        took = await _on_thread(p, [_reply(p, request)])
        assert took[0] is not None  # nobody waits: queued for the loop
        await _until(lambda: _counts(p)[6] == before[6] + 1)
        # closed after the lane handed its reply over, before the loop took it
        request, asked = await _asked(p, "closed")
        envelope = _reply(p, request)
        handed = ia._lane_take(envelope)  # here: the loop runs nothing before the close
        if replies:
            assert handed is None and len(ia._lane_done) == 1
        else:
            assert handed is not None
            inbox = ia._lane_inbox
            assert inbox is not None
            inbox.put(handed)
        p.fed_op._by_conv["closed"].close()
        with pytest.raises(ConversationError):
            await asyncio.wait_for(asked, WAIT)
        await _until(lambda: _counts(p)[6] == before[6] + 2)
        await _quiet(p)  # nothing held for uav-a, nothing left to book
        return _delta(_counts(p), before), ia.replies_on_thread - taken


async def test_a_reply_to_a_conversation_ended_meanwhile_is_dropped_as_late_either_way() -> None:
    """Timed out before the reply came, or closed between the thread and the loop: late."""
    lane = await _ended(True)
    loop = await _ended(False)
    assert lane[0] == loop[0]
    assert lane[0][6] == 2 and lane[0][:3] == (2, 2, 2)
    # the closed one was handed over and taken on the loop (its conversation gone by then)
    assert (lane[1], loop[1]) == (1, 0)


async def _malformed(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip = _counts(p), len(ia.audit.records)
        request, asked = await _asked(p, "malformed")
        answer = orjson.loads(
            request.reply(Performative.INFORM, ANSWER, sender=request.receivers[0]).to_json()
        )
        answer["receivers"] = answer["receivers"][0]  # a string, not a list
        took = await _on_thread(p, [p.ia_a.sessions.seal("operator", orjson.dumps(answer))])
        assert took[0] is not None  # not the lane's: the loop's full parse says why
        await _until(lambda: _counts(p)[4] > before[4])
        await _until(lambda: len(_records(p, skip)) >= 1)
        assert not asked.done()
        asked.cancel()
        await _quiet(p)
        return (
            _delta(_counts(p), before),
            [(v, perf, code) for v, perf, _, code in _records(p, skip)],
        )


async def test_a_malformed_reply_is_refused_as_on_the_loop() -> None:
    """A reply the model refuses: the same not-understood or drop, counts and record either way."""
    lane = await _malformed(True)
    assert lane == await _malformed(False)
    counts, records = lane
    assert counts[4] == 1 and records and records[0][0] in ("refused", "dropped")


async def _revoked(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip = _counts(p), len(ia.audit.records)
        request, asked = await _asked(p, "revoked", timeout=0.5)
        envelope = _reply(p, request)
        handed = ia._lane_take(envelope)  # opened: uav-a was trusted then
        assert handed is None if replies else handed is not None
        ia.trust.remove("uav-a")  # revoked here, on the loop, before the loop takes the reply
        if handed is not None:
            inbox = ia._lane_inbox
            assert inbox is not None
            inbox.put(handed)
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asked, WAIT)
        await _until(lambda: _counts(p)[3] == before[3] + 1)
        await _quiet(p)
        return (
            _delta(_counts(p), before),
            sorted({(v, code) for v, _, _, code in _records(p, skip)}),
        )


async def test_a_reply_whose_platform_was_revoked_after_it_opened_is_refused() -> None:
    """Revoked between the thread's open and the loop's take: refused as the loop refuses it."""
    lane = await _revoked(True)
    assert lane == await _revoked(False)
    assert lane[0][:4] == (0, 0, 0, 1)


async def test_a_reply_the_loop_cannot_take_at_once_goes_back_ahead_of_what_followed() -> None:
    """Handed over, then the loop may not take it so (the owner started watching): back to
    the inbox's front, the message of its peer that the inbox's consumer held behind it,
    and both taken in full, in order."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        taken = ia.replies_on_thread
        request, asked = await _asked(p, "back")
        later = p.fed_a.message(
            Performative.INFORM, p.fed_op.aid, "unsolicited", conversation_id="after-back"
        )
        skip = len(ia.audit.records)
        # here, one after the other: the loop runs nothing between
        assert ia._lane_take(_reply(p, request)) is None  # handed over
        held = ia._lane_take(p.ia_a.sessions.seal("operator", later.to_json()))
        assert held is not None and held[0] is _RAW  # behind the reply: the loop opens it
        ia._mirror_until = ia._monotonic() + WAIT
        ia.mirroring = True  # each message is now taken in full (and copied for the owner)
        # as the inbox's consumer books before taking ``held``: both go back, in order
        assert ia._lane_book(held) is True
        inbox = ia._lane_inbox
        assert inbox is not None
        assert [item[0] for item in inbox._items] == ["uav-a", _RAW]
        assert inbox._items[1] is held
        assert await asyncio.wait_for(asked, WAIT) == ANSWER
        await _quiet(p)
        await _until(lambda: len(_records(p, skip)) >= 2)
        accepted = [conv for v, _, conv, _ in _records(p, skip) if v == "accepted"]
        assert accepted == ["back", "after-back"]
        assert ia.replies_on_thread == taken  # the loop's full path took it
        ia.mirroring = False


async def test_a_reply_is_taken_at_once_while_answers_wait_for_the_audit_flush() -> None:
    """A platform that answers reads on the lane and asks too: the answers' bookings wait for
    the audit flush's tick, a reply handed over never does (its request would wait a tick)."""
    async with pair(lane=False, asker_lane=True, asker_replies=True) as p:
        ia = p.ia_op
        await _warm(p)
        ia.audit_interval = 3600.0  # taken at the flush's next tick: no tick within the test
        await asyncio.sleep(0.1)  # the flush's last short tick passes; the next is an hour off
        taken = ia.replies_on_thread
        with ia._lane_lock:
            # the state an answer of the lane leaves: its booking is due at the flush's tick
            ia._lane_posted = True
        answer = await asyncio.wait_for(p.fed_op.request_from("uav-a", LATEST), WAIT)
        assert answer["heli-altitude"]["samples"]
        assert ia.replies_on_thread == taken + 1  # handed over, and taken without the tick


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
