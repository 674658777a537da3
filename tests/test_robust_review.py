"""A review's probes of the lane's bookings (`InterfaceAgent._lane_book`): a reply handed over
whose peer's next message is queued is left to the inbox's consumer, and a booking that
raises costs only itself.

Real zenoh sessions on loopback (the pair of `tests/test_answer_on_thread.py`, the asker
``operator`` with the lane). Envelopes are sealed with uav-a's own session table and taken
by operator's lane one after the other, as zenoh's thread takes them, the loop running
nothing between; ``ia._lane_book()`` called here is the callback the hand-over posted.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import pytest

from agents import Performative
from agents._interface import _RAW
from tests.test_answer_on_thread import WAIT, Pair, _until, pair
from tests.test_lane_bookings import _round_trip_on_thread
from tests.test_reply_on_thread import ANSWER, _asked, _counts, _quiet, _records, _reply, _warm


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
