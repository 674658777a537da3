"""The lane: a plain get-latest answered on zenoh's receiving thread (`InterfaceAgent.lane`).

Two platforms over two real zenoh sessions on loopback (one process): the provider
``uav-a`` (a DyKnow instance, its Federation Agent) and the asker ``operator``. Each test
compares the lane with the event loop's path (``lane=False``) where the decision matters:
the same answers, refusals, counts and audit records; and checks what the lane must keep
(the thread it ran on, the order of a peer's messages, distinct seal counters), what it
must not change of the loop's decisions (a revoked or re-keyed platform), and a close
while its thread answers.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import sys
import threading
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import orjson
import pytest

from agents import LATER, AgentPlatform, RateLimit, Refused, TransportError, request
from agents._interface import InterfaceAgent
from agents._security import Handshake, KeyPair, SessionTable, TrustStore
from agents.transports import Inbox, ZenohConfig, ZenohTransport
from agents.transports import free_tcp_port as free_port
from dyknow_core import DyKnowInstance
from federation._gateway import GatewayAgent
from federation._gateway_service import ONTOLOGY as GATEWAY
from federation._service import FederationAgent
from ontology import LabelMapping, PlatformLabels, Vocabulary

WAIT = 10.0  # the bound on any single wait (a busy machine); each test ends far below it
LATEST = {"action": "get-latest", "labels": ["heli-altitude"]}
HEADING = {"action": "get-latest", "labels": ["op-heading"]}


@dataclass
class Pair:
    """The two platforms, their agents and the provider's DyKnow instance."""

    provider: AgentPlatform
    asker: AgentPlatform
    fed_a: FederationAgent
    fed_op: FederationAgent
    ia_a: InterfaceAgent
    ia_op: InterfaceAgent
    dk: DyKnowInstance
    trust_a: TrustStore
    gateway: GatewayAgent


def _translator(dk: DyKnowInstance, mapping: dict[str, str]) -> PlatformLabels:
    return PlatformLabels(LabelMapping(Vocabulary(list(mapping)), mapping), dk)


@contextlib.asynccontextmanager
async def pair(
    *, lane: bool = True, asker_lane: bool = False, asker_replies: bool = True, **interface: Any
) -> AsyncIterator[Pair]:
    """uav-a and operator over zenoh, members of each other before the test runs
    (``asker_replies``: operator's ``lane_replies``)."""
    fed = f"lane-{uuid.uuid4().hex[:12]}"
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "operator")}
    trusted = {n: k.public_key for n, k in keys.items()}
    seed = free_port()
    ta = ZenohTransport(ZenohConfig.loopback(seed))
    tb = ZenohTransport(ZenohConfig.loopback(free_port(), connect=[seed]))
    trust_a = TrustStore(fed, trusted)
    ia_a = InterfaceAgent(keys["uav-a"], trust_a, audit_interval=0.02, lane=lane, **interface)
    # the asker without a lane: with two in one process neither answers on its thread (`_Lanes`)
    ia_op = InterfaceAgent(
        keys["operator"],
        TrustStore(fed, trusted),
        audit_interval=0.02,
        lane=asker_lane,
        lane_replies=asker_replies,
    )
    async with contextlib.AsyncExitStack() as stack:
        await stack.enter_async_context(ta)
        await stack.enter_async_context(tb)
        dk = await stack.enter_async_context(DyKnowInstance("uav-a"))
        dk_op = await stack.enter_async_context(DyKnowInstance("operator"))
        dk.add_source("a/state/altitude").push(120.0)
        dk_op.add_source("op/state/heading").push(90.0)
        pa = await stack.enter_async_context(
            AgentPlatform("uav-a", ta, federation=fed, channel=ia_a)
        )
        pb = await stack.enter_async_context(
            AgentPlatform("operator", tb, federation=fed, channel=ia_op)
        )
        fed_a = await pa.add(
            FederationAgent(dk, _translator(dk, {"heli-altitude": "a/state/altitude"}))
        )
        gateway = await pa.add(GatewayAgent(dk))
        fed_op = await pb.add(
            FederationAgent(dk_op, _translator(dk_op, {"op-heading": "op/state/heading"}))
        )
        async with asyncio.timeout(WAIT):
            while fed_a.members != ["operator", "uav-a"] or fed_op.members != [  # noqa: ASYNC110
                "operator",
                "uav-a",
            ]:
                await asyncio.sleep(0.02)
        yield Pair(pa, pb, fed_a, fed_op, ia_a, ia_op, dk, trust_a, gateway)


async def _until(what: Any) -> None:
    """Wait (bounded) until ``what()`` holds: the lane's counts are booked on the loop."""
    async with asyncio.timeout(WAIT):
        while not what():  # noqa: ASYNC110
            await asyncio.sleep(0.005)


def _watch_threads(fed: FederationAgent) -> list[tuple[bool, bool]]:
    """Record, per call of ``fed.answer_on_thread``: (on the loop's thread, answered)."""
    calls: list[tuple[bool, bool]] = []
    loop_thread = threading.get_ident()
    answer = fed.answer_on_thread

    def watched(message: Any) -> Any:
        content = answer(message)
        calls.append((threading.get_ident() == loop_thread, content is not LATER))
        return content

    fed.answer_on_thread = watched  # type: ignore[method-assign]
    return calls


async def test_a_plain_get_latest_is_answered_on_zenohs_thread_counted_and_audited() -> None:
    """Answered on zenoh's thread, the same answer as the loop's, counted and audited as it."""
    outcomes = {}
    for lane in (True, False):
        async with pair(lane=lane) as p:
            calls = _watch_threads(p.fed_a)
            answers = [await p.fed_op.request_from("uav-a", LATEST) for _ in range(8)]
            await _until(lambda p=p: not p.ia_a._lane_done and p.fed_a.stats.handled >= 8)
            sender = p.provider.stats.senders["operator"]
            accepted = [
                r
                for r in p.ia_a.audit.records
                if r["verdict"] == "accepted" and r.get("from") == "operator"
            ]
            outcomes[lane] = (
                [sorted(a) for a in answers],
                [a["heli-altitude"]["samples"][0][0] for a in answers],
                p.fed_a.stats.handled,
                sender.accepted,
                len([r for r in accepted if r["performative"] == "request"]),
            )
            if lane:
                # the first asks warm what the thread reads (the translation, the
                # directory's decision, the reply's publisher): the rest are its own
                assert p.ia_a.answered_on_thread >= 6
                assert p.fed_a.stats.answered_at_once == 8
                assert calls and all(not on_loop for on_loop, _ in calls)
                assert sum(answered for _, answered in calls) == p.ia_a.answered_on_thread
            else:
                assert p.ia_a.answered_on_thread == 0
                assert calls == []  # the loop's path never asks it
    assert outcomes[True] == outcomes[False]
    assert outcomes[True][1] == [120.0] * 8
    assert outcomes[True][4] == 8  # one accepted record per request, both ways


async def test_a_read_waits_behind_what_its_peer_has_queued_for_the_loop() -> None:
    """A get-latest behind a message of the same peer queued for the loop is left to the loop."""
    async with pair() as p:
        for _ in range(3):  # warm: the next plain read is answerable on the thread
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: p.ia_a.answered_on_thread >= 1)
        await _until(lambda: not p.ia_a._lane_done)  # what the lane answered is booked
        before = (p.ia_a.answered_on_thread, p.fed_a.stats.handled)
        conv = "lane-order"
        # the envelopes as zenoh's thread would get them, taken by the lane's own hook
        # from another thread: the first is no plain read and is queued for the loop
        sealed, (first, second) = await sealed_requests(
            p, [({"action": "list-labels"}, f"{conv}-1"), (LATEST, f"{conv}-2")]
        )
        took = await asyncio.to_thread(lambda: [p.ia_a._lane_take(e) for e in sealed])
        assert took[0] is not None and took[0][0] == "operator"  # for the loop
        assert took[1] is not None and took[1][0] == "operator"  # behind it: the loop's too
        assert p.ia_a._lane_queued == {"operator": 2}
        inbox = p.ia_a._lane_inbox
        assert inbox is not None
        for item in took:
            inbox.put(item)
        listed, latest = await asyncio.gather(first, second)
        assert "heli-altitude" in str(listed)
        assert latest["heli-altitude"]["samples"][0][0] == 120.0
        await _until(lambda: p.ia_a._lane_queued == {})
        # both were the loop's (the read at once, or by its handler behind the other)
        assert p.fed_a.stats.handled == before[1] + 2
        assert p.ia_a.answered_on_thread == before[0]
        # nothing queued any more: the next read is the thread's again
        await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: p.ia_a.answered_on_thread == before[0] + 1)


async def test_what_the_lane_answers_is_booked_at_the_audit_flush_not_a_wake_up_each() -> None:
    """Reads answered on zenoh's thread one after another wake the loop for none of them:
    the audit flush books them at its tick (when it writes the records anyway), counted
    and audited as the loop's own answers, within an audit interval or two."""
    async with pair() as p:
        ia = p.ia_a
        for _ in range(3):  # warm: the next plain read is answerable on the thread
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: ia.answered_on_thread >= 1 and not ia._lane_done)
        before = (ia.answered_on_thread, p.provider.stats.senders["operator"].accepted)
        records = len(ia.audit.records)
        booked_by: list[str] = []
        real_book = ia._lane_book

        def book() -> None:
            caller = inspect.currentframe()
            caller = caller.f_back if caller is not None else None
            # a callback of the loop's own has no Python caller (uvloop) or the loop's
            booked_by.append("the loop" if caller is None else caller.f_code.co_name)
            real_book()

        ia._lane_book = book  # type: ignore[method-assign]
        ia.audit_interval = 2.0  # an answer's round trip is far below: several per tick
        answers = [await p.fed_op.request_from("uav-a", LATEST) for _ in range(6)]
        assert [a["heli-altitude"]["samples"][0][0] for a in answers] == [120.0] * 6
        await _until(lambda: ia.answered_on_thread >= before[0] + 4 and not ia._lane_done)
        on_thread = ia.answered_on_thread - before[0]
        assert set(booked_by) == {"_flush_audit"}  # never a callback of its own
        assert len(booked_by) < on_thread  # several answers to a booking
        assert p.provider.stats.senders["operator"].accepted == before[1] + 6
        await _until(lambda: len(ia.audit.records) >= records + 6)


async def test_seals_from_the_loop_and_the_thread_never_share_a_counter() -> None:
    """uav-a's loop asks while its thread answers, both sealing for operator: no counter twice."""
    async with pair() as p:
        for _ in range(3):
            await p.fed_op.request_from("uav-a", LATEST)
            await p.fed_a.request_from(
                "operator", {"action": "get-latest", "labels": ["op-heading"]}
            )
        n = 150
        asks = [p.fed_op.request_from("uav-a", LATEST) for _ in range(n)]
        back = [
            p.fed_a.request_from("operator", {"action": "get-latest", "labels": ["op-heading"]})
            for _ in range(n)
        ]
        got = await asyncio.gather(*asks, *back)
        assert [a["heli-altitude"]["samples"][0][0] for a in got[:n]] == [120.0] * n
        assert [a["op-heading"]["samples"][0][0] for a in got[n:]] == [90.0] * n
        await _until(lambda: p.ia_a.answered_on_thread > 0)
        # the receiver refused nothing (a counter twice is refused as replayed), and every
        # envelope uav-a sealed for it opened: none missing
        assert p.asker.stats.unauthenticated == 0
        assert not [r for r in p.ia_op.audit.records if r["verdict"] != "accepted"]
        assert p.ia_op.sessions.missing() == {}
        session = p.ia_a.sessions.session_for("operator")
        assert session is not None
        assert session.sent == p.ia_op.sessions.sessions("uav-a")[-1].received


async def _limited_outcomes(lane: bool) -> tuple[Any, ...]:
    now = [100.0]
    limit = RateLimit(rate=0.0, burst=4.0, refusals=0.0)
    async with pair(lane=lane, rate_limit=limit, monotonic=lambda: now[0]) as p:
        got = []
        for _ in range(7):
            try:
                answer = await p.fed_op.request_from("uav-a", LATEST, timeout=1.0)
                got.append(answer["heli-altitude"]["samples"][0][0])
            except Refused as exc:
                got.append(("refused", exc.message.content if exc.message else None))
            except TimeoutError:
                got.append("dropped")
        await _until(lambda: p.fed_a.stats.answered_at_once >= 4)
        sender = p.provider.stats.senders["operator"]
        records = [
            (r["verdict"], r.get("stage"), r.get("count"))
            for r in p.ia_a.audit.records
            # (the directory's own screens may drop a stale event of operator's: not ours)
            if r.get("from") == "operator" and r.get("stage") == "rate-limit"
        ]
        on_thread = p.ia_a.answered_on_thread
        return (got, sender.accepted, sender.limited, sender.refused, records), on_thread


async def test_a_limited_peer_is_refused_the_same_on_the_lane_as_on_the_loop() -> None:
    """The request limit: the same answers, drops, counts and audit records either way."""
    lane, on_thread = await _limited_outcomes(True)
    loop, none = await _limited_outcomes(False)
    assert lane == loop
    got, accepted, limited, _, records = lane
    assert got[:4] == [120.0] * 4 and accepted == 4 and limited == 3
    assert records == [("dropped", "rate-limit", 1)]  # the first drop at once, the rest later
    assert on_thread >= 1 and none == 0


async def _revoked_outcomes(lane: bool) -> tuple[Any, ...]:
    async with pair(lane=lane) as p:
        for _ in range(3):
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: not p.ia_a._lane_done)  # what the lane answered is booked
        before = p.provider.stats.unauthenticated
        answered = p.fed_a.stats.answered_at_once
        p.trust_a.remove("operator")
        with pytest.raises(TimeoutError):
            await p.fed_op.request_from("uav-a", LATEST, timeout=0.5)
        await _until(lambda: p.provider.stats.unauthenticated > before)
        untrusted = [
            r
            for r in p.ia_a.audit.records
            if r.get("code") == "untrusted" and r["verdict"] in ("dropped", "revoked")
        ]
        return (
            p.provider.stats.unauthenticated - before,
            p.fed_a.stats.answered_at_once - answered,
            sorted({r["verdict"] for r in untrusted}),
        )


async def test_a_revoked_peer_is_refused_the_same_on_the_lane_as_on_the_loop() -> None:
    """Revoked while running: its read opens nowhere, counted and audited either way."""
    lane = await _revoked_outcomes(True)
    assert lane == await _revoked_outcomes(False)
    assert lane[0] == 1 and lane[1] == 0


async def test_a_plain_gateway_query_is_answered_on_zenohs_thread_as_on_the_loop() -> None:
    """The Gateway Agent's query for a label's latest sample: the same answer either way."""
    query = {"action": "query", "label": "a/state/altitude"}
    outcomes = {}
    for lane in (True, False):
        async with pair(lane=lane) as p:
            calls = _watch_threads(p.gateway)  # type: ignore[arg-type]
            got = [
                await request(p.fed_op, "gateway@uav-a", query, ontology=GATEWAY) for _ in range(6)
            ]
            await _until(lambda p=p: p.gateway.stats.answered_at_once >= 6)
            # the one sample pushed, the same in every answer (its times are this run's)
            assert all(a["samples"] == got[0]["samples"] for a in got)
            assert got[0]["query_time"] <= got[-1]["query_time"]
            outcomes[lane] = [(sorted(a), a["label"], a["samples"][0][0]) for a in got]
            if lane:
                assert p.ia_a.answered_on_thread >= 4
                assert calls and all(not on_loop for on_loop, _ in calls)
            else:
                assert p.ia_a.answered_on_thread == 0
    assert outcomes[True] == outcomes[False]
    assert outcomes[True][0][1:] == ("a/state/altitude", 120.0)


async def test_what_the_full_inbox_drops_no_longer_holds_its_peers_reads_back() -> None:
    """An item dropped by the lane's full queue releases its peer (else it waits forever)."""
    seen: list[Any] = []
    inbox: Inbox[Any] = Inbox(asyncio.get_running_loop(), 2, dropped=seen.append)
    for item in ("a", "b", "c"):
        inbox.put(item)
    assert seen == ["a"] and inbox.dropped == 1
    async with pair() as p:
        with p.ia_a._lane_lock:
            p.ia_a._lane_queued["operator"] = 1
        p.ia_a._lane_dropped(("operator", b"{}"))
        p.ia_a._lane_dropped((None, ValueError("did not open")))  # no peer: nothing held
        assert p.ia_a._lane_queued == {}
        for _ in range(3):  # the first two warm what the thread reads (the loop answers)
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: p.ia_a.answered_on_thread >= 1)


async def sealed_requests(
    p: Pair, asks: list[tuple[dict[str, Any], str]], **kw: Any
) -> tuple[list[bytes], list[Any]]:
    """operator's requests to uav-a (content, conversation id), each sealed in an envelope of
    its own and captured rather than published; their futures (``kw``: `request_from`'s)."""
    sealed: list[bytes] = []
    transport = p.asker.transport
    real_put, real_put_now = transport.publish, transport.publish_nowait

    async def capture(key: str, payload: bytes, **kw: Any) -> None:
        if key.endswith("/acl/uav-a"):
            sealed.append(payload)
            return
        await real_put(key, payload, **kw)

    def capture_now(key: str, payload: bytes) -> None:
        # a request that waits for nothing goes out this way (`InterfaceAgent.send_now`)
        if key.endswith("/acl/uav-a"):
            sealed.append(payload)
            return
        real_put_now(key, payload)

    transport.publish = capture  # type: ignore[method-assign]
    transport.publish_nowait = capture_now  # type: ignore[method-assign]
    p.ia_op._batching = False  # each message in an envelope of its own
    asked = [
        asyncio.ensure_future(p.fed_op.request_from("uav-a", content, conversation_id=conv, **kw))
        for content, conv in asks
    ]
    try:
        await _until(lambda: len(sealed) == len(asks))
    finally:
        transport.publish = real_put  # type: ignore[method-assign]
        transport.publish_nowait = real_put_now  # type: ignore[method-assign]
    return sealed, asked


async def _sealed_reads(p: Pair, conv: str, n: int) -> tuple[list[bytes], list[Any]]:
    """``n`` get-latest requests of operator's, sealed for uav-a but not sent; their futures."""
    return await sealed_requests(p, [(LATEST, f"{conv}-{i}") for i in range(n)])


class _Hold(Exception):
    """What holds uav-a's loop in its inbox's consumer (as a long turn of a busy loop)."""


@pytest.mark.parametrize("held", [False, True], ids=["idle-loop", "draining-loop"])
async def test_what_the_peer_sends_once_answered_finds_the_answer_counted(held: bool) -> None:
    """The lane's answer is booked on the loop before the peer's next message is taken.

    The next message enters the inbox the moment the answer is put (the fastest peer),
    and the thread waits until the loop took it: the counts it met there include the
    answer, whether the loop was idle (FIFO behind the posted booking) or busy taking
    from the inbox then (no wake-up of its own: the consumer books what is pending).
    """
    async with pair() as p:
        ia = p.ia_a
        for _ in range(3):  # warm: the next plain read is answerable on the thread
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: ia.answered_on_thread >= 1 and not ia._lane_done)
        before = ia.answered_on_thread
        conv = f"lane-book-{held}"
        sealed, asks = await _sealed_reads(p, conv, 2)
        inbox = ia._lane_inbox
        assert inbox is not None
        seen: list[int] = []  # answered_on_thread when the loop takes the next message
        taken = threading.Event()
        real_take_now = ia._take_now

        def take_now(host: Any, peer: str, state: Any, body: bytes) -> bool:
            if f"{conv}-1".encode() in body:
                seen.append(ia.answered_on_thread)
                taken.set()
            return real_take_now(host, peer, state, body)

        ia._take_now = take_now  # type: ignore[method-assign]
        entered, release = threading.Event(), threading.Event()
        real_not_opened = ia._not_opened

        def not_opened(stats: Any, exc: Exception) -> None:
            if isinstance(exc, _Hold):
                entered.set()
                release.wait(WAIT)
                return
            real_not_opened(stats, exc)

        ia._not_opened = not_opened  # type: ignore[method-assign]
        transport = p.provider.transport
        real_declared = transport.declared_publisher

        def declared(key: str) -> Any:
            put = real_declared(key)
            if put is None:
                return None

            def put_then_the_peer(payload: bytes) -> None:
                put(payload)
                inbox.put(ia._lane_take(sealed[1]))  # behind the first: for the loop
                release.set()
                taken.wait(WAIT)  # the loop took it before this thread goes on

            return put_then_the_peer

        transport.declared_publisher = declared  # type: ignore[method-assign]
        took: list[Any] = []

        def answer() -> None:
            if held:
                entered.wait(WAIT)
            took.append(ia._lane_take(sealed[0]))

        thread = threading.Thread(target=answer)
        thread.start()
        try:
            if held:
                inbox.put((None, _Hold()))
            got = await asyncio.wait_for(asyncio.gather(*asks), WAIT)
        finally:
            release.set()
            taken.set()
            await asyncio.to_thread(thread.join, WAIT)
        assert took == [None]  # the first was answered on the thread
        assert [a["heli-altitude"]["samples"][0][0] for a in got] == [120.0, 120.0]
        assert seen == [before + 1]


@pytest.mark.parametrize("booked_first", [False, True], ids=["put-fails-at-once", "booked-first"])
async def test_an_answer_the_thread_could_not_put_is_sent_and_counted_once(
    booked_first: bool,
) -> None:
    """A put that fails on the thread: the answer still goes, counted and audited once.

    Not booked yet (the usual case): the booking is taken back and the loop decides the
    message. Booked already (the loop ran between): it stays the lane's, and the loop
    sends the answer.
    """
    async with pair() as p:
        ia = p.ia_a
        for _ in range(3):
            await p.fed_op.request_from("uav-a", LATEST)
        await _until(lambda: ia.answered_on_thread >= 1 and not ia._lane_done)
        await _until(lambda: p.fed_a.stats.handled >= 3)
        sender = p.provider.stats.senders["operator"]
        before = (ia.answered_on_thread, sender.accepted, p.fed_a.stats.handled)

        def from_operator() -> int:
            return len([r for r in ia.audit.records if r.get("from") == "operator"])

        records = from_operator()
        booked = threading.Event()
        real_book = ia._lane_book

        def book(*current: Any) -> bool:
            back = real_book(*current)
            booked.set()
            return back

        ia._lane_book = book  # type: ignore[method-assign]
        transport = p.provider.transport
        real_declared = transport.declared_publisher
        failed: list[str] = []

        def declared(key: str) -> Any:
            if real_declared(key) is None:
                return None

            def put(payload: bytes) -> None:
                failed.append(key)
                if booked_first:
                    assert booked.wait(WAIT)  # the loop booked it before the put failed
                raise TransportError("a put that fails")

            return put

        transport.declared_publisher = declared  # type: ignore[method-assign]
        answer = await p.fed_op.request_from("uav-a", LATEST)
        transport.declared_publisher = real_declared  # type: ignore[method-assign]
        assert answer["heli-altitude"]["samples"][0][0] == 120.0
        assert len(failed) == 1  # the thread tried once; the answer went the loop's way
        await _until(lambda: p.fed_a.stats.handled == before[2] + 1)
        await _until(lambda: from_operator() >= records + 1)
        assert (sender.accepted, p.fed_a.stats.handled) == (before[1] + 1, before[2] + 1)
        assert from_operator() == records + 1
        if booked_first:
            assert ia.answered_on_thread == before[0] + 1
        else:  # (the loop may have booked it between, rarely: then as above)
            assert ia.answered_on_thread in (before[0], before[0] + 1)


async def test_an_answer_resent_after_its_put_failed_is_the_one_counted() -> None:
    """The lane's put fails after its answer was booked (counted, audited): the loop
    resends the very bytes the lane wrote, not the answer's content as it is by then (an
    agent's answer it keeps and changes, here changed as the put fails)."""
    async with pair() as p:
        ia = p.ia_a
        good = {"action": "query", "label": "a/state/altitude"}
        for _ in range(20):  # the first read of the stream warms it: the lane's from then on
            await request(p.fed_op, "gateway@uav-a", good, ontology=GATEWAY)
            if ia.answered_on_thread or ia._lane_done:
                break
        await _until(lambda: ia.answered_on_thread >= 1 and not ia._lane_done)
        before = ia.answered_on_thread
        kept = {"label": "a/state/altitude", "query_time": 5.0, "samples": [[120.0, 1.0, 2.0]]}
        counted = {"label": "a/state/altitude", "query_time": 5.0, "samples": [[120.0, 1.0, 2.0]]}
        # not handed over: an answer the agent keeps (copied into the reply's bytes)
        p.gateway.answer_on_thread = lambda message: kept  # type: ignore[method-assign]
        booked = threading.Event()
        real_book = ia._lane_book

        def book(*current: Any) -> bool:
            back = real_book(*current)
            booked.set()
            return back

        ia._lane_book = book  # type: ignore[method-assign]
        sealed: list[bytes] = []
        real_seal = ia._seal

        def seal(peer: str, body: bytes) -> Any:
            if peer == "operator":
                sealed.append(body)
            return real_seal(peer, body)

        ia._seal = seal  # type: ignore[method-assign]
        transport = p.provider.transport
        real_declared = transport.declared_publisher
        failed: list[str] = []

        def declared(key: str) -> Any:
            if real_declared(key) is None:
                return None

            def put(payload: bytes) -> None:
                failed.append(key)
                assert booked.wait(WAIT)  # counted before the put failed: the loop resends
                kept["samples"][0][0] = -1.0  # the agent changes its answer meanwhile
                kept["changed"] = True
                raise TransportError("a put that fails")

            return put

        transport.declared_publisher = declared  # type: ignore[method-assign]
        try:
            got = await request(p.fed_op, "gateway@uav-a", good, ontology=GATEWAY)
        finally:
            transport.declared_publisher = real_declared  # type: ignore[method-assign]
            ia._seal = real_seal  # type: ignore[method-assign]
        assert len(failed) == 1
        assert got == counted  # what was counted, not what the answer became
        assert ia.answered_on_thread == before + 1  # counted once, as the lane's
        # the lane's bytes, sealed again as they were
        assert len(sealed) == 2 and sealed[1] == sealed[0], sealed
        assert orjson.loads(sealed[0])["content"] == counted


async def test_a_sharing_that_decides_in_its_own_check_all_is_asked_on_the_loop() -> None:
    """A `Sharing` subclass (here its `check_all` alone) may read the loop's state: never
    asked on zenoh's thread; the reads it allows are answered by the loop."""
    from federation._sharing import Sharing

    asked_on_loop: list[bool] = []
    loop_thread = threading.get_ident()

    class Watched(Sharing):
        def check_all(self, action: Any, labels: Any, platform: str) -> str | None:
            asked_on_loop.append(threading.get_ident() == loop_thread)
            return super().check_all(action, labels, platform)

    async with pair() as p:
        p.fed_a.sharing = Watched()
        answers = [await p.fed_op.request_from("uav-a", LATEST) for _ in range(8)]
        assert [a["heli-altitude"]["samples"][0][0] for a in answers] == [120.0] * 8
        assert p.ia_a.answered_on_thread == 0
        assert len(asked_on_loop) >= 8 and all(asked_on_loop)


async def test_with_two_lanes_in_one_process_envelopes_open_on_the_loop() -> None:
    """Two platforms of one process with their lanes on: neither opens nor answers on
    zenoh's thread (their threads would contend with the loop for the GIL); the reads are
    answered at once by the loop, the same answers; the lanes' count ends with them."""
    from agents._interface import _LANES

    before = _LANES.open
    async with pair(asker_lane=True) as p:
        assert _LANES.open == before + 2
        opened_on_thread: list[Any] = []
        table = p.ia_a.sessions
        real_open = table.open_noting

        def watched(envelope: Any) -> Any:
            opened_on_thread.append(threading.current_thread().name)
            return real_open(envelope)

        table.open_noting = watched  # type: ignore[method-assign]
        answers = [await p.fed_op.request_from("uav-a", LATEST) for _ in range(6)]
        assert [a["heli-altitude"]["samples"][0][0] for a in answers] == [120.0] * 6
        assert p.ia_a.answered_on_thread == 0
        assert p.fed_a.stats.answered_at_once >= 6  # the loop's own quick answer
        assert opened_on_thread == []  # each opened by the loop (`SessionTable.open`)
    assert _LANES.open == before


async def _gateway_refusals(lane: bool) -> list[Any]:
    """What operator's plain gateway queries the gateway refuses come to: the reasons
    told, the counts, the audit records, and how many the lane answered."""
    async with pair(lane=lane) as p:
        p.dk.add_source("import/uav-b/altitude").push(1.0)  # reserved: readable here only
        good = {"action": "query", "label": "a/state/altitude"}
        # the first read of the stream warms it: the lane's from then on (asked until the
        # lane answered one, so that the lane is shown to be on)
        for _ in range(20):
            await request(p.fed_op, "gateway@uav-a", good, ontology=GATEWAY)
            if not lane or p.ia_a.answered_on_thread or p.ia_a._lane_done:
                break
        if lane:  # and every answer of the lane booked (counted) before the count is read
            await _until(lambda: p.ia_a.answered_on_thread >= 1 and not p.ia_a._lane_done)
        answered = p.ia_a.answered_on_thread
        told: list[str] = []
        for label in ("import/uav-b/altitude", "a/none") * 3:
            with pytest.raises(Refused) as refused:
                await request(
                    p.fed_op, "gateway@uav-a", {"action": "query", "label": label}, ontology=GATEWAY
                )
            told.append(str(refused.value.message.content))
        await p.gateway.set_visibility("private", "closed for the test")
        for _ in range(2):  # a label any other platform could read before
            with pytest.raises(Refused) as refused:
                await request(p.fed_op, "gateway@uav-a", good, ontology=GATEWAY)
            told.append(str(refused.value.message.content))

        def refusals() -> list[tuple[Any, Any, Any, Any]]:
            # the agent's refusals are summed up a record a second (their count below)
            return [
                (r.get("stage"), r.get("code"), r.get("from"), r.get("reason"))
                for r in p.ia_a.audit.records
                if r.get("verdict") == "refused" and r.get("stage") != "agent-refuse"
            ]

        await _until(lambda: len(refusals()) >= 8)
        stats = p.gateway.gateway_stats
        return [
            told,
            (
                stats.reserved_refused,
                stats.unknown_label_refused,
                stats.bad_label_refused,
                p.provider.stats.denied,
                p.provider.stats.agent_refused,
            ),
            refusals(),
            p.ia_a.answered_on_thread - answered,
        ]


async def test_a_gateway_read_the_gateway_refuses_is_refused_the_same_on_the_lane() -> None:
    """A reserved label (here, readable by this platform's agents) and a label not here,
    asked by another platform: refused, counted and audited as the loop does, none of them
    answered on zenoh's thread."""
    lane = await _gateway_refusals(True)
    assert lane == await _gateway_refusals(False)
    assert lane[1] == (3, 3, 0, 2, 6) and lane[3] == 0
    assert [r[:3] for r in lane[2]] == [
        ("gateway", "reserved-label", "operator"),
        ("gateway", "unknown-label", "operator"),
    ] * 3 + [
        (None, None, "operator")  # the private gateway's, by the directory's check
    ] * 2
    # each audited with the reason its asker was told, by its code
    unknown = lane[0][1]
    assert unknown == "unknown label 'a/none' (known labels: a/state/altitude)"
    assert [r[3] for r in lane[2][1:6:2]] == [f"unknown-label: {unknown}"] * 3


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
