"""The lane's bookings on the loop (`InterfaceAgent._lane_book`): one that raises costs only
itself, and a reply handed over is counted as the inbox's consumer counts one.

Real zenoh sessions on loopback (the pair of `tests/test_answer_on_thread.py`, the asker
``operator`` with the lane). Envelopes are sealed with uav-a's own session table and given
to operator's lane as zenoh's thread gives them: taken and queued on a thread of their own.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import uuid
from typing import Any

import pytest

from agents import ACLMessage, Performative
from tests.test_answer_on_thread import HEADING, LATEST, WAIT, Pair, _until, pair
from tests.test_reply_on_thread import (
    _asked,
    _counts,
    _delta,
    _quiet,
    _records,
    _reply,
    _warm,
)


def _arrive(p: Pair, envelopes: list[bytes]) -> None:
    """``envelopes`` reach operator's lane on a thread, as zenoh's thread takes and queues
    them, all before the loop runs anything again (this call blocks the loop meanwhile)."""
    ia = p.ia_op
    inbox = ia._lane_inbox
    assert inbox is not None

    def zenoh() -> None:
        for envelope in envelopes:
            item = ia._lane_take(envelope)
            if item is not None:
                inbox.put(item)

    thread = threading.Thread(target=zenoh)
    thread.start()
    thread.join(WAIT)
    assert not thread.is_alive()


async def _duplicate(replies: bool) -> tuple[Any, ...]:
    async with pair(lane=False, asker_lane=True, asker_replies=replies) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip = _counts(p), len(ia.audit.records)
        request, asked = await _asked(p, "twice-at-once")
        # the same answer sent twice (two authentic envelopes, neither a replay), both here
        # before the loop runs: the loop takes the first, then the second
        _arrive(p, [_reply(p, request), _reply(p, request, {"second": True})])
        await asyncio.wait_for(asked, WAIT)
        # what the asker reads once its request returned
        read = (_delta(_counts(p), before), _records(p, skip))
        await _quiet(p)
        return read, (_delta(_counts(p), before), _records(p, skip))


async def test_a_reply_sent_twice_is_counted_alike_with_the_hand_over_on_and_off() -> None:
    """Both replies came before the loop ran: either way the second is in the conversation
    before its request returns (not late after it), the same counts and records read then."""
    lane = await _duplicate(True)
    loop = await _duplicate(False)
    assert lane == loop
    (counts, records), _ = lane
    assert counts[:3] == (2, 2, 2) and counts[5:8] == (2, 0, 0)  # received twice, none late
    assert [(v, perf, conv) for v, perf, conv, _ in records] == [
        ("accepted", "inform", "twice-at-once")
    ] * 2


def _break_reply(p: Pair, conv: str) -> None:
    """Taking a reply of ``conv`` raises on operator's loop (a fault of the delivery)."""
    ia = p.ia_op
    real = ia._take_message

    def take(host: Any, peer: str, state: Any, message: ACLMessage, now: float) -> bool:
        if message.conversation_id == conv:
            # as a fault's error may quote what it failed on
            raise RuntimeError(f"delivery of {conv} broke on {message.content!r}")
        return real(host, peer, state, message, now)

    ia._take_message = take  # type: ignore[method-assign]


async def _round_trip_on_thread(p: Pair) -> None:
    """A request of operator answered, its reply handed over and taken on the lane."""
    taken = p.ia_op.replies_on_thread
    answer = await asyncio.wait_for(p.fed_op.request_from("uav-a", LATEST), WAIT)
    assert answer["heli-altitude"]["samples"]
    assert p.ia_op.replies_on_thread == taken + 1


async def test_a_reply_whose_hand_over_raises_costs_only_itself(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Taking a reply handed over raises: logged once, counted, its peer's count released;
    the message of its peer behind it is taken, the inbox's consumer lives on, and the
    lane hands that peer's next reply over again."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        request, asked = await _asked(p, "broken")
        _break_reply(p, "broken")
        after = p.fed_a.message(
            Performative.INFORM, p.fed_op.aid, "unsolicited", conversation_id="after-broken"
        )
        skip = len(ia.audit.records)
        with caplog.at_level(logging.ERROR, logger="agents._interface"):
            _arrive(p, [_reply(p, request), p.ia_a.sessions.seal("operator", after.to_json())])
            await _until(lambda: ia.lane_failed == 1)
            await _until(lambda: len(_records(p, skip)) >= 1)
            await _quiet(p)  # uav-a's count released: nothing held for it
        assert [conv for v, _, conv, _ in _records(p, skip) if v == "accepted"] == ["after-broken"]
        failed = [r for r in caplog.records if "taking the reply handed over" in r.getMessage()]
        assert len(failed) == 1 and "uav-a" in failed[0].getMessage()
        assert not asked.done()
        asked.cancel()
        await _round_trip_on_thread(p)
        assert ia.lane_failed == 1


async def test_a_reply_whose_hand_over_raises_alone_leaves_the_lane_working(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The same fault in the callback posted for a reply alone: the peer's count released
    (else the lane would never hand its replies over again), the next taken there."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        request, asked = await _asked(p, "broken-alone")
        _break_reply(p, "broken-alone")
        secret = f"said-in-confidence-{uuid.uuid4().hex}"  # encrypted on the wire
        with caplog.at_level(logging.DEBUG, logger="agents"):
            _arrive(p, [_reply(p, request, {"secret": secret})])
            await _until(lambda: ia.lane_failed == 1)
            await _quiet(p)
        failed = [r for r in caplog.records if "taking the reply handed over" in r.getMessage()]
        assert len(failed) == 1
        assert "from uav-a failed (ACLMessage): RuntimeError" in failed[0].getMessage()
        # neither the message's repr nor the error's text (which quotes it) is logged
        assert secret not in caplog.text
        assert not [r for r in caplog.records if secret in r.getMessage() + (r.exc_text or "")]
        asked.cancel()
        await _round_trip_on_thread(p)


async def test_an_answers_booking_that_raises_leaves_the_audit_flush_running(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Renewing the session of an answer the lane made raises at the flush's tick: the answer
    is still counted and audited, and the flush goes on writing later records."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        for _ in range(2):  # operator's publisher for uav-a, and its sender state there
            await p.fed_a.request_from("operator", HEADING)
        await _quiet(p)
        answered = ia.answered_on_thread

        def renew(peer: str) -> None:
            raise RuntimeError(f"renewal with {peer} broke")

        ia.renew_if_needed = renew  # type: ignore[method-assign]
        skip = len(ia.audit.records)
        with caplog.at_level(logging.ERROR, logger="agents._interface"):
            answer = await asyncio.wait_for(p.fed_a.request_from("operator", HEADING), WAIT)
            assert answer["op-heading"]["samples"]
            await _until(lambda: ia.lane_failed >= 1)
        assert ia.answered_on_thread == answered + 1
        assert [(v, perf, code) for v, perf, _, code in _records(p, skip)] == [
            ("accepted", "request", None)
        ]
        flushed = ia.audit_published + ia.audit_unheard
        ia.audit.record(verdict="dropped", reason="a later record")
        await _until(lambda: ia.audit_published + ia.audit_unheard > flushed)
        assert any("renewing the session" in r.getMessage() for r in caplog.records)
