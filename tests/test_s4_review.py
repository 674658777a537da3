"""A review's probes of the lane's bookings at the audit flush's tick (`InterfaceAgent._lane_book`).

Real zenoh sessions on loopback (the pair of `tests/test_answer_on_thread.py`): what the
lane answered must be counted and audited within the interval docs/agents.md promises,
after a put that failed on the thread as well, and must reach the audit file when the
platform stops before the flush's next tick.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

from test_answer_on_thread import LATEST, WAIT, _until, pair, sealed_requests

from agents import TransportError
from agents._security import SecurityPolicy


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


async def _warm(p: Any) -> None:
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
        await _warm(p)
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
        await _warm(p)
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
        await _warm(p)
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
        await _warm(p)
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
