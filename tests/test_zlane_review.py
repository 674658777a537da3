"""A review's probes of the lane (`InterfaceAgent.lane`): plain reads answered on zenoh's thread.

Real zenoh sessions on loopback (the pair of `tests/test_answer_on_thread.py`): what the
lane must not change of the loop's decisions (a revoked or re-keyed platform), the seal
counter when two threads seal at once, and closing a platform while its thread answers.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import threading
from typing import Any

import pytest
from test_answer_on_thread import LATEST, WAIT, _until, pair, sealed_requests

from agents._security import Handshake, KeyPair, SessionTable, TrustStore


async def _sealed_by_operator(p: Any, content: dict[str, Any], conv: str) -> tuple[bytes, Any]:
    """An envelope operator seals for uav-a's inbox, captured rather than published."""
    sealed, asked = await sealed_requests(p, [(content, conv)], timeout=1.0)
    return sealed[0], asked[0]


async def test_a_request_opened_before_its_platform_is_revoked_is_not_taken_after_it() -> None:
    """Revoked on the loop (a SIGHUP's trust reload) while a request of it waits, opened on
    zenoh's thread, in the lane's queue: the loop must not take it as from a trusted platform.

    On the loop's path the envelope opens after the revocation and is dropped (untrusted);
    on the lane it opened before, and was accepted, audited and handled after it.
    """
    async with pair() as p:
        await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: not p.ia_a._lane_done)
        sender = p.provider.stats.senders["operator"]
        accepted, handled = sender.accepted, p.fed_a.stats.handled
        unauthenticated = p.provider.stats.unauthenticated
        envelope, asked = await _sealed_by_operator(p, {"action": "list-labels"}, "rv-1")
        item = await asyncio.to_thread(p.ia_a._lane_take, envelope)
        assert item is not None and item[0] == "operator"  # no plain read: for the loop
        p.trust_a.remove("operator")  # on the loop, as `reload_trust` does
        inbox = p.ia_a._lane_inbox
        assert inbox is not None
        inbox.put(item)
        await _until(lambda: p.ia_a._lane_queued == {})
        with contextlib.suppress(TimeoutError):
            await asked
        assert sender.accepted == accepted
        assert p.fed_a.stats.handled == handled
        assert p.provider.stats.unauthenticated == unauthenticated + 1
        late = [
            r
            for r in p.ia_a.audit.records
            if r.get("from") == "operator" and r["verdict"] == "accepted"
            if r.get("conversation_id") == "rv-1"
        ]
        assert late == []


async def test_a_read_on_a_session_of_a_replaced_key_is_not_answered_on_the_thread() -> None:
    """`TrustStore.remove` then `add` with a new key from another thread (the old key lost):
    a read on a session agreed with the old key, opened before the loop forgot those
    sessions, is answered on zenoh's thread; the loop's path opens it after and drops it."""
    async with pair() as p:
        for _ in range(3):
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: p.ia_a.answered_on_thread >= 1 and not p.ia_a._lane_done)
        envelope, asked = await _sealed_by_operator(p, LATEST, "rk-1")
        before = p.ia_a.answered_on_thread
        new_key = KeyPair.generate("operator").public_key
        took: list[Any] = []

        def rekey_then_read() -> None:
            p.trust_a.remove("operator")
            p.trust_a.add("operator", new_key)
            took.append(p.ia_a._lane_take(envelope))

        # the loop is held (joined here) as a busy loop is: the revocation waits for it
        worker = threading.Thread(target=rekey_then_read)
        worker.start()
        worker.join(WAIT)
        assert took
        asked.cancel()
        with contextlib.suppress(asyncio.CancelledError, TimeoutError):
            await asked
        await _until(lambda: not p.ia_a._lane_done)
        assert took[0] is not None  # not answered on the thread
        assert p.ia_a.answered_on_thread == before


def test_two_threads_sealing_for_one_peer_never_repeat_a_counter() -> None:
    """The loop and zenoh's thread seal for the same peer at once: every counter once.

    Threads switched every microsecond, so an unlocked read-modify-write of the counter
    shows as a repeated ``n`` (a nonce twice under one key).
    """
    fed = "seal-race"
    keys = {n: KeyPair.generate(n) for n in ("a", "b")}
    trust = TrustStore(fed, {n: k.public_key for n, k in keys.items()})
    ta, tb = SessionTable("a", trust), SessionTable("b", trust)
    ha, hb = Handshake(keys["a"], trust), Handshake(keys["b"], trust)
    hello = ha.initiate("b")
    reply, sb = hb.respond(hello)
    sa = ha.finish(reply)
    ta.add(sa)
    tb.add(sb)
    tb.open(ta.seal("b", b"{}"))  # b confirms it: it may seal for a now
    seen: list[int] = []
    lock = threading.Lock()
    per_thread = 25000

    def seal_many() -> None:
        mine = []
        for _ in range(per_thread):
            env = ta.seal("b", b'{"x":1}')
            mine.append(int(env.split(b'"n":', 1)[1].split(b",", 1)[0].rstrip(b"}")))
        with lock:
            seen.extend(mine)

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        threads = [threading.Thread(target=seal_many) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(WAIT * 6)
    finally:
        sys.setswitchinterval(switch)
    assert len(seen) == 4 * per_thread
    assert len(set(seen)) == len(seen)


async def test_closing_the_provider_while_its_thread_answers_ends_in_time(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """uav-a closes (agents, interface, zenoh) while operator's reads pour in and its thread
    answers them: it ends within the bound, and the thread's answering raised nothing."""
    async with pair() as p:
        for _ in range(3):
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: p.ia_a.answered_on_thread >= 1)
        stop = asyncio.Event()

        async def pour() -> None:
            while not stop.is_set():
                # one at a time: a read behind another of the same peer is the loop's
                try:
                    await p.fed_op.request_from("uav-a", LATEST, timeout=0.3)
                except Exception:
                    # uav-a gone, a key exchange with it fails without a suspension (no
                    # queryable answers): a retry loop that never yields would starve the
                    # loop, and the close under test with it
                    await asyncio.sleep(0.005)

        pourer = asyncio.ensure_future(pour())
        try:
            await _until(lambda: p.ia_a.answered_on_thread >= 30)
            async with asyncio.timeout(WAIT):
                await p.provider.__aexit__(None, None, None)
                await p.provider.transport.aclose()
            stop.set()
            async with asyncio.timeout(WAIT):
                await pourer
        finally:
            pourer.cancel()
    # an answer whose put failed once booked is a warning (its answer lost, as a
    # handler's); an exception out of the thread's answering is an error
    assert not [
        r for r in caplog.records if r.levelname == "ERROR" and "receiving thread" in r.getMessage()
    ]
