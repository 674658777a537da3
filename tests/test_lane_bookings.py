"""The lane's bookings on the loop (`InterfaceAgent._lane_book`): one that raises costs only
itself, and a reply handed over is counted as the inbox's consumer counts one.

What the lane answered is counted and audited within the interval docs/agents.md promises
(after a put that failed on the thread as well), reaches the audit file when the platform
stops before the audit flush's next tick, and starts a session's renewal at once; a reply
handed over whose peer's next message is queued is left to the inbox's consumer.

Real zenoh sessions on loopback (the pair of `tests/test_answer_on_thread.py`, the asker
``operator`` with the lane). Envelopes are sealed with uav-a's own session table and given
to operator's lane as zenoh's thread gives them: taken and queued on a thread of their own.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import pytest

from agents import ACLMessage, Performative, TransportError
from agents._interface import _RAW
from agents._security import SecurityPolicy
from tests.test_answer_on_thread import (
    HEADING,
    LATEST,
    WAIT,
    Pair,
    _until,
    pair,
    sealed_requests,
)
from tests.test_reply_on_thread import (
    ANSWER,
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


async def _within(what: Any, seconds: float) -> bool:
    """Whether ``what()`` holds within ``seconds`` (polled; never longer)."""
    end = time.monotonic() + seconds
    while not what():
        if time.monotonic() > end:
            return False
        await asyncio.sleep(0.005)
    return True


async def _slow_flush(ia: Any, interval: float) -> None:
    """Set the audit interval and wait until the flush ticks no sooner than ``interval``."""
    ticks: list[float] = []
    real_report = ia._report_missing

    def report(now: float) -> None:
        ticks.append(now)
        real_report(now)

    ia._report_missing = report
    ia.audit_interval = interval
    # a tick after the change (the one due already goes by the old period) took the new one
    await _until(lambda: len(ticks) >= 2 or ia._flush_idle)
    ia._report_missing = real_report


async def _warm_reads(p: Any) -> None:
    """Reads until the next plain one is answerable on the thread, all booked."""
    ia = p.ia_a
    for _ in range(3):
        await p.fed_op.request_from("uav-a", LATEST)
    await _until(lambda: ia.answered_on_thread >= 1 and not ia._lane_done)


async def test_after_a_put_the_thread_took_back_the_next_answers_are_still_booked_in_time() -> None:
    """A put that failed on the thread takes its booking back; the lane's next answer, with
    the flush asleep meanwhile, is counted and audited within an audit interval or two."""
    async with pair() as p:
        ia = p.ia_a
        await _warm_reads(p)
        ia.audit_interval = 0.2  # the flush's tick far behind the failed put: taken back
        transport = p.provider.transport
        real_declared = transport.declared_publisher
        failed: list[str] = []

        def declared(key: str) -> Any:
            if real_declared(key) is None:
                return None

            def put(payload: bytes) -> None:
                failed.append(key)
                raise TransportError("a put that fails")

            return put

        transport.declared_publisher = declared  # type: ignore[method-assign]
        try:
            await p.fed_op.request_from("uav-a", LATEST)  # answered by the loop after all
        finally:
            transport.declared_publisher = real_declared  # type: ignore[method-assign]
        assert len(failed) == 1
        await _until(lambda: ia._flush_idle)  # nothing left to flush: it sleeps
        before = (ia.answered_on_thread, p.provider.stats.senders["operator"].accepted)
        answer = await p.fed_op.request_from("uav-a", LATEST)
        assert answer["heli-altitude"]["samples"][0][0] == 120.0
        # docs/agents.md: "the counts lag the answers by at most `audit_interval`"
        booked = await _within(lambda: ia.answered_on_thread == before[0] + 1, 5 * 0.2)
        assert booked, f"the lane's answer not booked after 5 intervals ({len(ia._lane_done)})"
        assert p.provider.stats.senders["operator"].accepted == before[1] + 1


async def test_what_the_lane_answered_just_before_the_platform_stops_is_in_the_audit_file(
    tmp_path: Path,
) -> None:
    """Reads answered on the thread less than an audit interval before the platform stops:
    their accepted records are in the audit file once it has stopped, as the loop's are."""
    audit = tmp_path / "uav-a.audit.jsonl"
    async with pair(audit_path=audit) as p:
        ia = p.ia_a
        await _warm_reads(p)
        await _slow_flush(ia, 30.0)  # the flush's next tick after the stop
        before = ia.answered_on_thread
        convs = [f"s4-stop-{i}" for i in range(3)]
        for conv in convs:
            answer = await p.fed_op.request_from("uav-a", LATEST, conversation_id=conv)
            assert answer["heli-altitude"]["samples"][0][0] == 120.0
        assert len(ia._lane_done) == 3  # answered on the thread, booked at the next tick
    assert ia.answered_on_thread == before + 3  # booked as the Interface Agent closed
    lines = [json.loads(line) for line in audit.read_text().splitlines()]
    written = {r["conversation_id"] for r in lines if r["verdict"] == "accepted"}
    assert set(convs) <= written, f"not in the audit file: {sorted(set(convs) - written)}"


async def test_a_session_past_its_message_budget_on_the_lane_starts_renewing_at_once() -> None:
    """Reads answered on the thread take uav-a's session past ``renew_after_messages``: its
    renewal starts then (as when the loop answers), not an audit interval later, while the
    old session seals answers past its budget."""
    budget = 20
    async with pair(policy=SecurityPolicy(renew_after_messages=budget)) as p:
        ia = p.ia_a
        await _warm_reads(p)
        await _slow_flush(ia, 5.0)  # a long interval (an owner's choice): the reads fit in one
        old = ia.sessions.session_for("operator")
        assert old is not None and old._n + old._bn < budget
        sealed, asked = await sealed_requests(p, [(LATEST, f"s4-renew-{i}") for i in range(budget)])
        took = await asyncio.to_thread(lambda: [ia._lane_take(s) for s in sealed])
        assert took == [None] * budget  # each answered on zenoh's thread, none left to the loop
        await asyncio.wait_for(asyncio.gather(*asked), WAIT)
        assert old._n + old._bn >= budget
        renewed = await _within(lambda: ia.sessions.session_for("operator") is not old, 1.0)
        used = old._n + old._bn
        assert renewed, f"not renewed: the old session sealed {used} of a budget of {budget}"


async def test_a_platform_revoked_before_the_lane_answer_is_booked_is_not_renewed_with() -> None:
    """uav-a answers operator on the thread, then revokes it (a trust reload) before the
    flush books the answer: the booking opens no key exchange with the revoked platform."""
    async with pair() as p:
        ia = p.ia_a
        await _warm_reads(p)
        await _slow_flush(ia, 1.0)
        agreed: list[str] = []
        real_agree = ia.agree

        async def agree(peer: str, *args: Any, **kw: Any) -> Any:
            agreed.append(peer)
            return await real_agree(peer, *args, **kw)

        ia.agree = agree  # type: ignore[method-assign]
        before = ia.answered_on_thread
        sealed, asked = await sealed_requests(p, [(LATEST, "s4-revoked")])
        took = await asyncio.to_thread(ia._lane_take, sealed[0])
        assert took is None  # answered on zenoh's thread, booked at the flush's tick
        await asyncio.wait_for(asked[0], WAIT)
        p.trust_a.remove("operator")  # on the loop, as `reload_trust` does
        await _until(lambda: ia.answered_on_thread == before + 1)  # the tick booked it
        # a renewal the booking spawned has run its key exchange (refused: untrusted) by now
        await _until(lambda: not [t for t in p.provider._tasks if "renew[" in t.get_name()])
        assert agreed == []


def _unsolicited(p: Pair, conv: str) -> bytes:
    """An inform of uav-a's nobody waits for (the loop's full path), sealed for operator."""
    other = p.fed_a.message(Performative.INFORM, p.fed_op.aid, "unsolicited", conversation_id=conv)
    return p.ia_a.sessions.seal("operator", other.to_json())


def _handed_then_queued(p: Pair, reply: bytes, after: list[bytes]) -> None:
    """``reply`` handed over, ``after`` queued behind it unopened, then the posted callback
    runs: it leaves the reply to the inbox's consumer (nothing taken, nothing cleared)."""
    ia = p.ia_op
    inbox = ia._lane_inbox
    assert inbox is not None
    assert ia._lane_take(reply) is None  # handed over
    for envelope in after:
        item = ia._lane_take(envelope)
        assert item is not None and item[0] is _RAW  # behind the reply: the loop opens it
        inbox.put(item)
    taken = ia.replies_on_thread
    assert ia._lane_book() is False
    assert len(ia._lane_done) == 1 and ia._lane_handed and ia.replies_on_thread == taken


async def test_a_reply_left_to_the_consumer_is_taken_once_before_its_peers_next() -> None:
    """Handed over, then uav-a's next message and a replay of the reply queued: the reply is
    taken once, before the next, the replay refused; every count released, every flag reset."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip, taken = _counts(p), len(ia.audit.records), ia.replies_on_thread
        request, asked = await _asked(p, "deferred")
        reply = _reply(p, request)
        _handed_then_queued(p, reply, [_unsolicited(p, "after-deferred"), reply])
        assert await asyncio.wait_for(asked, WAIT) == ANSWER
        await _until(lambda: _counts(p)[3] == before[3] + 1)  # the replay
        await _quiet(p)
        await _until(lambda: len([r for r in _records(p, skip) if r[0] == "accepted"]) >= 2)
        accepted = [conv for v, _, conv, _ in _records(p, skip) if v == "accepted"]
        assert accepted == ["deferred", "after-deferred"]
        counts = _counts(p)
        assert (counts[0] - before[0], counts[5] - before[5], counts[6] - before[6]) == (2, 2, 0)
        assert ia.replies_on_thread == taken + 1 and ia.lane_failed == 0
        assert ia._lane_raw == 0
        assert not (ia._lane_handed or ia._lane_reply_posted)
        await _round_trip_on_thread(p)  # the lane hands uav-a's replies over again


async def test_a_reply_left_to_the_consumer_of_a_peer_revoked_meanwhile_is_refused() -> None:
    """Revoked after the hand-over, before the consumer took it: the reply and what followed
    it are refused as the loop refuses them; nothing is held for uav-a afterwards."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        before, skip = _counts(p), len(ia.audit.records)
        request, asked = await _asked(p, "deferred-revoked", timeout=0.5)
        _handed_then_queued(p, _reply(p, request), [_unsolicited(p, "after-revoked")])
        ia.trust.remove("uav-a")
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asked, WAIT)
        await _until(lambda: _counts(p)[3] == before[3] + 2)
        await _quiet(p)
        assert ia._lane_raw == 0 and ia.lane_failed == 0
        assert _counts(p)[:3] == before[:3]  # neither accepted
        assert not [r for r in _records(p, skip) if r[0] == "accepted"]


async def test_a_refusal_that_raises_releases_its_peers_count_once() -> None:
    """Refusing a reply of a peer revoked since it opened raises: counted in ``lane_failed``,
    the peer's count released once (a second release would raise out of the booking)."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        request, asked = await _asked(p, "refusal-raises")
        assert ia._lane_take(_reply(p, request)) is None  # handed over
        ia.trust.remove("uav-a")
        real = ia._not_opened

        def not_opened(stats: Any, exc: Exception) -> None:
            ia._not_opened = real  # type: ignore[method-assign]
            raise RuntimeError("the refusal's audit broke")

        ia._not_opened = not_opened  # type: ignore[method-assign]
        assert ia._lane_book() is False  # contained: nothing raises out
        assert ia.lane_failed == 1 and ia._lane_queued == {}
        assert not asked.done()
        asked.cancel()


@pytest.mark.parametrize("fault", [KeyboardInterrupt, asyncio.CancelledError])
async def test_the_containment_lets_interrupts_and_cancellation_through(
    fault: type[BaseException], caplog: pytest.LogCaptureFixture
) -> None:
    """What is no error of one booking (an interrupt, a cancellation) leaves `_lane_book` as
    raised: not counted in ``lane_failed``, not logged as a booking that failed."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        request, asked = await _asked(p, f"fault-{fault.__name__}")
        assert ia._lane_take(_reply(p, request)) is None  # handed over
        real = ia._take_message

        def take(*args: Any) -> bool:
            raise fault()

        ia._take_message = take  # type: ignore[method-assign]
        try:
            with caplog.at_level(logging.ERROR, logger="agents._interface"), pytest.raises(fault):
                ia._lane_book()
        finally:
            ia._take_message = real  # type: ignore[method-assign]
        assert ia.lane_failed == 0
        assert not [r for r in caplog.records if "failed" in r.getMessage()]
        asked.cancel()
