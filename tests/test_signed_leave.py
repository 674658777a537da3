"""A platform's signed leave retires its sessions: a request to it then fails fast.

A presence that goes may be forged, so it only doubts the peer's sessions (none sealed on
until the peer sends on one), and any late envelope of the peer trusted one again: after
a real leave, the next request to the peer was sealed on a session nobody holds any
more and waited its timeout. The leave the peer's directory signs cannot be forged: on
it the sessions are retired (an envelope that comes late still opens, within ``grace``,
but trusts none again), so the next message agrees a new session, and the key exchange
finds nobody at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from _echo import ProtectedEcho
from _victim import trusted

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    GlobalDirectory,
    InterfaceAgent,
    KeyPair,
    TransportError,
    TrustStore,
    on_request,
    request,
    wire_key,
)
from agents._acl import Performative
from agents._df import DirectoryFacilitator
from agents._exceptions import AuthenticationError
from agents._security import Handshake, SessionTable
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port

TIMEOUT = 5.0  # the request's: what it waited after a real leave


def _outsider(port: int) -> zenoh.Session:
    """A plain zenoh session on loopback (no key of the federation)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    return zenoh.open(conf)


class Echo(ProtectedEcho):
    """Answers with what it was asked."""

    @on_request("demo")
    async def _echo(self, message: ACLMessage) -> object:
        """The content."""
        return message.content


async def test_a_request_to_a_platform_that_left_fails_at_once(tmp_path: Path) -> None:
    """uav-b leaves (signed); an envelope it sealed before comes late; uav-a asks it again."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, port = federation.fed, federation.port
    channel = federation.channel

    ca = channel("uav-a")
    async with (
        asyncio.timeout(60),
        ZenohTransport(ZenohConfig.loopback(port)) as ta,
        AgentPlatform("uav-a", ta, federation=fed, channel=ca) as pa,
    ):
        view = pa.global_df
        assert view is not None
        asker = await pa.add(Agent("asker"))
        late = b""
        async with (
            ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[port])) as tb,
            AgentPlatform("uav-b", tb, federation=fed, channel=channel("uav-b")) as pb,
        ):
            await pb.add(Echo())
            while "uav-b" not in view.platforms:  # noqa: ASYNC110
                await asyncio.sleep(0.02)
            assert await request(asker, "echo@uav-b", 1, ontology="demo", timeout=TIMEOUT) == 1
            # sealed now, delivered after uav-b left (held up on the way)
            inform = ACLMessage(
                performative=Performative.INFORM,
                sender="echo@uav-b",
                receivers=["asker@uav-a"],
                content={"late": True},
            )
            cb = pb.channel
            assert isinstance(cb, InterfaceAgent)
            late = cb.sessions.seal("uav-a", inform.to_json())
            events = view._event_counts.get("uav-b", 0)
        # uav-b is gone: its signed leave taken (an event), its presence too
        while (  # noqa: ASYNC110
            view._event_counts.get("uav-b", 0) == events
            or "uav-b" in view.platforms
            or "uav-b" in ca._alive
        ):
            await asyncio.sleep(0.02)
        received = pa.stats.received_remote
        with _outsider(port) as relay:  # whoever held it up lets it go now
            relay.put(wire_key(fed, "acl", "uav-a"), late)
            async with asyncio.timeout(5):
                while pa.stats.received_remote == received:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)  # opened: it is authentic, within grace
        start = time.monotonic()
        with pytest.raises((TransportError, TimeoutError)):
            await request(asker, "echo@uav-b", 2, ontology="demo", timeout=TIMEOUT)
        waited = time.monotonic() - start
        print(f"\na request to uav-b after it left failed in {waited:.2f} s")
        assert waited < TIMEOUT / 2, waited  # its key exchange found nobody


async def test_a_key_exchange_under_way_ends_when_the_peer_leaves(tmp_path: Path) -> None:
    """uav-a agrees a session with uav-b; no answer comes (a silent queryable holds the
    query open); uav-b leaves, signed: the key exchange ends then, not at its timeout."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, port = federation.fed, federation.port
    ca = federation.channel("uav-a", handshake_timeout=TIMEOUT)
    cb = federation.channel("uav-b")

    def refuse(payload: bytes) -> Any:
        raise AuthenticationError("not now", "uav-a")  # uav-b answers no key exchange

    cb.handshake.respond = refuse  # type: ignore[method-assign]
    held: list[Any] = []  # a query dropped is ended: kept, it waits its timeout
    async with (
        asyncio.timeout(60),
        ZenohTransport(ZenohConfig.loopback(port)) as ta,
        AgentPlatform("uav-a", ta, federation=fed, channel=ca) as pa,
    ):
        view = pa.global_df
        assert view is not None
        with _outsider(port) as outsider:
            silent = outsider.declare_queryable(wire_key(fed, "kx", "uav-b"), held.append)
            config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
            async with (
                ZenohTransport(config) as tb,
                AgentPlatform("uav-b", tb, federation=fed, channel=cb),
            ):
                while "uav-b" not in view.platforms:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)
                agreeing = asyncio.create_task(ca.agree("uav-b"))
                while not held:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)  # the exchange is under way
                start = time.monotonic()
            # uav-b closed: its signed leave sent
            with pytest.raises(TransportError):
                await agreeing
            waited = time.monotonic() - start
            silent.undeclare()
            held.clear()
        print(f"\nthe key exchange with uav-b ended {waited:.2f} s after it began to leave")
        assert waited < TIMEOUT / 2, waited


def _leave_refusals(view: GlobalDirectory) -> asyncio.Queue[str]:
    """The reasons of the leaves ``view`` refuses from now on, as it refuses them."""
    reasons: asyncio.Queue[str] = asyncio.Queue()
    refuse = view._refuse

    def spy(claimed: str | None, reason: str, stage: str) -> None:
        refuse(claimed, reason, stage)
        if stage == "df-events" and "leave" in reason:
            reasons.put_nowait(reason)

    view._refuse = spy  # type: ignore[method-assign]
    return reasons


def _leaves_heard(channel: InterfaceAgent) -> list[tuple[str, float | None]]:
    """The signed leaves the channel is told of (`InterfaceAgent.peer_left`), as told."""
    told: list[tuple[str, float | None]] = []
    peer_left = channel.peer_left

    def spy(peer: str, at: float | None = None) -> None:
        told.append((peer, at))
        peer_left(peer, at)

    channel.peer_left = spy  # type: ignore[method-assign]
    return told


def _leave_records(channel: InterfaceAgent) -> list[dict[str, Any]]:
    """The audit records of the leaves ``channel``'s directory refused."""
    return [
        r
        for r in channel.audit.records
        if r.get("stage") == "df-events" and "leave" in str(r.get("reason"))
    ]


def _signed_at(leave: bytes) -> float:
    """When a recorded leave was signed (POSIX s, the leaver's clock)."""
    return float(json.loads(leave)["ts_ms"]) / 1000


def _is_leave(payload: bytes) -> bool:
    """Whether a directory event's payload is a leave."""
    return json.loads(json.loads(payload)["body"]).get("op") == "leave"


def _held_directory(
    name: str,
) -> tuple[asyncio.Event, Callable[[DirectoryFacilitator, str, bytes], Awaitable[bytes | None]]]:
    """A `DirectoryFacilitator._serve_public` under which ``name``'s directory answers once
    the event is set (the others at once), and that event."""
    busy = asyncio.Event()
    serve = DirectoryFacilitator._serve_public

    async def slow(self: DirectoryFacilitator, key: str, payload: bytes) -> bytes | None:
        if self.platform.name == name:
            await busy.wait()
        return await serve(self, key, payload)

    return busy, slow


async def _recorded_leave(tmp_path: Path, fed: str, port: int, trust: TrustStore) -> bytes:
    """A signed leave of a process of uav-b's, as anyone on the network records it."""
    got: list[bytes] = []
    with _outsider(port) as outsider:
        sub = outsider.declare_subscriber(
            wire_key(fed, "df-events", "uav-b"), lambda s: got.append(bytes(s.payload))
        )
        config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
        channel = InterfaceAgent(KeyPair.load(tmp_path / "uav-b.key"), trust)
        async with (
            ZenohTransport(config) as tb,
            AgentPlatform("uav-b", tb, federation=fed, channel=channel),
        ):
            pass
        while not any(_is_leave(p) for p in got):  # noqa: ASYNC110
            await asyncio.sleep(0.02)
        sub.undeclare()
    return next(p for p in got if _is_leave(p))


async def test_a_leave_replayed_or_late_keeps_the_next_processs_session(tmp_path: Path) -> None:
    """uav-b's earlier processes left, signed; its next one agrees a session with uav-a;
    such a leave (replayed by an outsider, or held up on the way) then reaches uav-a: the
    session agreed since stays, and a key exchange begun since goes on."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, trust, port = federation.fed, federation.trust, federation.port
    ca = federation.channel("uav-a", handshake_timeout=TIMEOUT)
    held: list[Any] = []  # a query dropped is ended: kept, it waits its timeout
    async with asyncio.timeout(60), ZenohTransport(ZenohConfig.loopback(port)) as ta:
        # two processes' leaves, the second newer: each is news to uav-a once
        leaves = [await _recorded_leave(tmp_path, fed, port, trust) for _ in range(2)]
        async with AgentPlatform("uav-a", ta, federation=fed, channel=ca) as pa:
            view = pa.global_df
            assert view is not None
            asker = await pa.add(Agent("asker"))
            cb = federation.channel("uav-b")
            config = ZenohConfig.loopback(free_tcp_port(), connect=[port])

            async def deliver(leave: bytes) -> None:
                """The leave reaches uav-a now, and is read (signed, within the skew).

                As in a view that has not read the next process's directory yet (its
                presence late): else the leave, older, would be dropped as stale.
                """
                events = view._event_counts.get("uav-b", 0)
                with _outsider(port) as outsider:
                    # again until taken: a session just opened may not be routed yet (the
                    # copies after the first are stale, dropped); forgotten again each time,
                    # as the view may have read uav-b's directory meanwhile (a slow machine)
                    while view._event_counts.get("uav-b", 0) == events:
                        view._auth.forget("uav-b")
                        outsider.put(wire_key(fed, "df-events", "uav-b"), leave)
                        await asyncio.sleep(0.1)

            # uav-b's next process
            async with (
                ZenohTransport(config) as tb,
                AgentPlatform("uav-b", tb, federation=fed, channel=cb) as pb,
            ):
                await pb.add(Echo())
                assert await request(asker, "echo@uav-b", 1, ontology="demo", timeout=TIMEOUT) == 1
                refused_before = view.refused
                session = ca.sessions.session_for("uav-b")
                assert session is not None
                refusals = _leave_refusals(view)
                told = _leaves_heard(ca)
                await deliver(leaves[0])
                # uav-b's running process answers the check: replayed, or late after a restart
                reason = await asyncio.wait_for(refusals.get(), 30)
                assert "replayed or late" in reason and "answers" in reason, reason
                # the channel still hears it: it retires only what was agreed before it
                assert told == [("uav-b", _signed_at(leaves[0]))]
                assert ca.sessions.session_for("uav-b") is session  # not retired
                assert not pa.df.said_left("uav-b")  # type: ignore[union-attr]
                assert await request(asker, "echo@uav-b", 2, ontology="demo", timeout=TIMEOUT) == 2
                assert ca.sessions.session_for("uav-b") is session

                # a key exchange begun after the leave was signed: not ended by it
                def refuse(payload: bytes) -> Any:
                    raise AuthenticationError("not now", "uav-a")

                cb.handshake.respond = refuse  # type: ignore[method-assign]
                with _outsider(port) as outsider:
                    silent = outsider.declare_queryable(wire_key(fed, "kx", "uav-b"), held.append)
                    agreeing = asyncio.create_task(ca.agree("uav-b"))
                    while not held:  # until the exchange is under way
                        if agreeing.done():  # it joined one begun before (a re-handshake)
                            with contextlib.suppress(Exception):
                                agreeing.result()
                            agreeing = asyncio.create_task(ca.agree("uav-b"))
                        await asyncio.sleep(0.01)
                    await deliver(leaves[1])
                    assert "replayed or late" in await asyncio.wait_for(refusals.get(), 30)
                    # it ends at its own timeout: not as if uav-b had left
                    with pytest.raises(TransportError, match="did not answer"):
                        await agreeing
                    silent.undeclare()
                    held.clear()
                assert view.refused - refused_before == 2
            # uav-b's running process leaves: that leave, of the process read, is taken
            df = pa.df
            assert df is not None
            while not df.said_left("uav-b"):  # noqa: ASYNC110
                await asyncio.sleep(0.02)  # bounded by the test's timeout
            assert told[-1][0] == "uav-b" and told[-1][1] is not None
            assert ca.sessions.session_for("uav-b") is None  # retired: agreed before it


async def test_a_restarted_platform_is_served_at_once_after_its_leave(tmp_path: Path) -> None:
    """uav-b leaves, signed, and starts again: its first request to uav-a is served, on
    the session its new process agreed (not refused until its directory answers)."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, port = federation.fed, federation.port
    channel = federation.channel

    async with (
        asyncio.timeout(60),
        ZenohTransport(ZenohConfig.loopback(port)) as ta,
        AgentPlatform("uav-a", ta, federation=fed, channel=channel("uav-a")) as pa,
    ):
        await pa.add(Echo())
        df = pa.df
        assert df is not None

        async def ask(value: int) -> object:
            """A new process of uav-b asks uav-a (its first request), then leaves, signed."""
            config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
            async with (
                ZenohTransport(config) as tb,
                AgentPlatform("uav-b", tb, federation=fed, channel=channel("uav-b")) as pb,
            ):
                asker = await pb.add(Agent("asker"))
                return await request(asker, "echo@uav-a", value, ontology="demo", timeout=TIMEOUT)

        assert await ask(1) == 1
        while not df.said_left("uav-b"):  # noqa: ASYNC110
            await asyncio.sleep(0.02)  # its signed leave taken
        assert await ask(2) == 2  # at once, before its presence or directory is read
        assert pa.stats.from_left == 0


@pytest.mark.parametrize("offset", [-20.0, 20.0])
def test_the_leave_cut_off_is_in_the_leavers_clock(offset: float) -> None:
    """uav-b's clock is 20 s behind (or ahead of) uav-a's: what it agreed before the time
    it signed its leave is retired, what its next process agreed after is kept."""
    now = [1_700_000_000.0]
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    trust = TrustStore("demo", {n: k.public_key for n, k in keys.items()})

    def a_clock() -> float:
        return now[0]

    def b_clock() -> float:
        return now[0] + offset

    a_hs = Handshake(keys["uav-a"], trust, clock=a_clock)
    a_table = SessionTable("uav-a", trust, clock=a_clock)
    b_hs = Handshake(keys["uav-b"], trust, clock=b_clock)
    tables = [SessionTable("uav-b", trust, clock=b_clock)]

    def agree() -> None:
        """uav-b begins a session with uav-a, and sends on it."""
        reply, on_a = a_hs.respond(b_hs.initiate("uav-a"))
        a_table.add(on_a)
        tables[-1].add(b_hs.finish(reply))
        a_table.open(tables[-1].seal("uav-a", b"{}"))

    agree()
    now[0] += 10
    agree()  # in uav-b's last 5 s (its clock)
    last = a_table.session_for("uav-b")
    assert last is not None
    now[0] += 5
    a_table.retire("uav-b", b_clock())  # the leave, signed at uav-b's time
    assert a_table.session_for("uav-b") is None  # its last session too
    assert not a_table.back_since_left("uav-b")
    a_table.open(tables[-1].seal("uav-a", b"{}"))  # late, on the last session: opens
    assert a_table.session_for("uav-b") is None
    now[0] += 1
    tables.append(SessionTable("uav-b", trust, clock=b_clock))  # its next process
    agree()
    assert a_table.back_since_left("uav-b")
    assert a_table.session_for("uav-b") not in (None, last)


async def test_a_leave_replayed_before_the_first_snapshot_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An outsider recorded the signed leave of uav-b's earlier process; uav-b's next one
    runs, and uav-a, started since, is taking its first snapshot of it (uav-b's directory
    slow to answer) when the outsider replays that leave: uav-b answers a fresh query, so
    the leave is refused, counted and audited; uav-b is listed and served."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, trust, port = federation.fed, federation.trust, federation.port
    busy, slow = _held_directory("uav-b")
    async with asyncio.timeout(60), ZenohTransport(ZenohConfig.loopback(port)) as ta:
        leave = await _recorded_leave(tmp_path, fed, port, trust)
        ca = federation.channel("uav-a")
        # its queries of uav-b's held directory outlast the replay on a loaded machine
        async with AgentPlatform("uav-a", ta, federation=fed, channel=ca, query_timeout=3.0) as pa:
            await pa.add(Echo())
            view, df = pa.global_df, pa.df
            assert view is not None and df is not None
            assert view._auth.newest("uav-b") is None  # nothing read of uav-b yet
            monkeypatch.setattr(DirectoryFacilitator, "_serve_public", slow)
            config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
            cb = federation.channel("uav-b")
            async with (
                ZenohTransport(config) as tb,
                AgentPlatform("uav-b", tb, federation=fed, channel=cb) as pb,
            ):
                while "uav-b" not in view._joining:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)  # its first snapshot is under way
                assert view._auth.newest("uav-b") is None  # no event of its own since
                refused = view.refused
                refusals = _leave_refusals(view)
                with _outsider(port) as outsider:
                    # again until it arrived: the outsider's session may not be routed yet
                    # (the copies after the first are stale, dropped)
                    while not view._event_counts.get("uav-b", 0):
                        outsider.put(wire_key(fed, "df-events", "uav-b"), leave)
                        await asyncio.sleep(0.05)
                busy.set()
                # the check's query answered (or the snapshot's, read meanwhile)
                reason = await asyncio.wait_for(refusals.get(), 30)
                assert "replayed or late" in reason, reason
                while "uav-b" not in view.platforms:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)  # bounded by the test's timeout
                assert refusals.empty() and view.refused > refused
                assert not df.said_left("uav-b")
                records = [
                    r
                    for r in ca.audit.records
                    if r.get("stage") == "df-events" and "leave" in str(r.get("reason"))
                ]
                assert len(records) == 1, records
                assert records[0]["from"] == "uav-b" and records[0]["verdict"] == "dropped"
                # uav-b is served: its request is not refused as from a platform that left
                asker = await pb.add(Agent("asker"))
                assert await request(asker, "echo@uav-a", 3, ontology="demo", timeout=TIMEOUT) == 3
                assert pa.stats.from_left == 0


async def test_a_leave_of_a_process_never_read_is_taken_once_nobody_answers(
    tmp_path: Path,
) -> None:
    """uav-b's process left, signed, before uav-a's view read its directory (the leave held
    up on the way): nobody answers for uav-b any more, so the leave is taken, not refused."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, trust, port = federation.fed, federation.trust, federation.port
    async with asyncio.timeout(60), ZenohTransport(ZenohConfig.loopback(port)) as ta:
        leave = await _recorded_leave(tmp_path, fed, port, trust)
        ca = federation.channel("uav-a")
        async with AgentPlatform("uav-a", ta, federation=fed, channel=ca) as pa:
            view, df = pa.global_df, pa.df
            assert view is not None and df is not None
            refused = view.refused
            checks: list[tuple[bool, bool]] = []  # (answered, said left by then)
            answers = view._answers

            async def check(platform: str) -> bool:
                answered = await answers(platform)
                checks.append((answered, df.said_left(platform)))
                return answered

            view._answers = check  # type: ignore[method-assign]
            with _outsider(port) as relay:  # whoever held it up lets it go now
                while not view._event_counts.get("uav-b", 0):
                    relay.put(wire_key(fed, "df-events", "uav-b"), leave)
                    await asyncio.sleep(0.05)
            while not df.said_left("uav-b"):  # noqa: ASYNC110
                await asyncio.sleep(0.02)  # bounded by the test's timeout
            assert view.refused == refused
            # taken only after uav-b was asked, three times, and answered none
            assert checks == [(False, False)] * 3, checks


@contextlib.contextmanager
def _flooding(port: int, key: str) -> Iterator[None]:
    """Anyone's plain zenoh client asking ``key`` as fast as it can, from two threads."""
    stop = threading.Event()
    with _outsider(port) as flooder:

        def flood() -> None:
            while not stop.is_set():
                flooder.get(key, handler=lambda reply: None, timeout=0.2)

        threads = [threading.Thread(target=flood, daemon=True) for _ in range(2)]
        for t in threads:
            t.start()
        try:
            yield
        finally:
            stop.set()
            for t in threads:
                t.join(timeout=10)


async def test_a_leave_replayed_while_a_flood_sheds_its_check_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An outsider floods uav-b's directory queryable (its budget is everyone's, 50/s) and
    replays uav-b's recorded leave before uav-a read uav-b's directory: the check's query
    goes unanswered. uav-b talks to uav-a meanwhile, so it runs: the leave is refused,
    counted and audited; uav-b stays listed. Before, the unanswered check took the leave
    (and abandoned the snapshot under way)."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, trust, port = federation.fed, federation.trust, federation.port
    busy, slow = _held_directory("uav-b")
    async with asyncio.timeout(90), ZenohTransport(ZenohConfig.loopback(port)) as ta:
        leave = await _recorded_leave(tmp_path, fed, port, trust)
        ca = federation.channel("uav-a")
        async with AgentPlatform("uav-a", ta, federation=fed, channel=ca, query_timeout=3.0) as pa:
            await pa.add(Echo())
            view, df = pa.global_df, pa.df
            assert view is not None and df is not None
            refusals = _leave_refusals(view)
            monkeypatch.setattr(DirectoryFacilitator, "_serve_public", slow)
            config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
            cb = federation.channel("uav-b")
            async with (
                ZenohTransport(config) as tb,
                AgentPlatform("uav-b", tb, federation=fed, channel=cb) as pb,
            ):
                while "uav-b" not in view._joining:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)  # its first snapshot is under way
                asker = await pb.add(Agent("asker"))
                talked = asyncio.Event()

                async def talk() -> None:
                    """uav-b asks uav-a, again and again, as a member at work does."""
                    n = 0
                    while True:
                        n += 1
                        with contextlib.suppress(Exception):
                            await request(asker, "echo@uav-a", n, ontology="demo", timeout=2)
                        talked.set()
                        await asyncio.sleep(0.2)

                talking = asyncio.create_task(talk())
                try:
                    await asyncio.wait_for(talked.wait(), 20)
                    refused = view.refused
                    records = len(_leave_records(ca))
                    with (
                        _flooding(port, wire_key(fed, "df", "uav-b")),
                        _outsider(port) as outsider,
                    ):
                        while not view._event_counts.get("uav-b", 0):
                            outsider.put(wire_key(fed, "df-events", "uav-b"), leave)
                            await asyncio.sleep(0.05)
                        reason = await asyncio.wait_for(refusals.get(), 30)
                finally:
                    talking.cancel()
                assert "talks to this platform" in reason and "replayed or late" in reason
                assert pb.df is not None and pb.df.queries_shed > 0
                # one leave refused (its snapshot held, its presence may be refused too)
                assert refusals.empty() and view.refused > refused
                audited = _leave_records(ca)
                assert len(audited) == records + 1, audited
                assert audited[-1]["from"] == "uav-b" and audited[-1]["verdict"] == "dropped"
                assert not df.said_left("uav-b")
                busy.set()
                while "uav-b" not in view.platforms:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)  # its snapshot, not abandoned (or the recheck)
                assert not df.said_left("uav-b")
                assert await request(asker, "echo@uav-a", 0, ontology="demo", timeout=TIMEOUT) == 0


async def test_a_restart_with_its_signed_leave_is_seen_without_the_session_presence_watch(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """uav-a's session presence watch ended by its transport (MQTT: refused after a
    reconnection): uav-b restarted after its signed leave is still asked on a session
    its new process agreed; the loss's meaning says only a restart without one is unseen."""
    federation = trusted(tmp_path, "leave", ["uav-a", "uav-b"])
    fed, port = federation.fed, federation.port
    channel = federation.channel

    async def serve() -> AsyncIterator[None]:
        """A process of uav-b serving echo until the caller goes on, then leaving, signed."""
        config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
        async with (
            ZenohTransport(config) as tb,
            AgentPlatform("uav-b", tb, federation=fed, channel=channel("uav-b")) as pb,
        ):
            await pb.add(Echo())
            yield

    async with (
        asyncio.timeout(60),
        ZenohTransport(ZenohConfig.loopback(port)) as ta,
        AgentPlatform("uav-a", ta, federation=fed, channel=channel("uav-a")) as pa,
    ):
        view, df = pa.global_df, pa.df
        assert view is not None and df is not None
        asker = await pa.add(Agent("asker"))
        lost: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        pa.on_lost(lambda what, why: lost.done() or lost.set_result(what))
        (task,) = [t for t in pa._tasks if t.get_name().endswith(".interface.presence")]
        watch = task.get_coro().cr_frame.f_locals["coro"]  # type: ignore[union-attr]
        watch.cr_frame.f_locals["presence"].inbox.close()  # as MQTT's `_end` does
        assert await lost == f"session presence watch {pa.key('alive', '*')}"
        for value in (1, 2):  # uav-b's first process, then its next one
            async with contextlib.asynccontextmanager(serve)():
                while "uav-b" not in view.platforms:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)
                got = await request(asker, "echo@uav-b", value, ontology="demo", timeout=TIMEOUT)
                assert got == value
            while "uav-b" in view.platforms:  # noqa: ASYNC110
                await asyncio.sleep(0.02)  # its signed leave taken
    (said,) = [
        r.getMessage() for r in caplog.records if r.name == "agents._platform" and "lost" in r.msg
    ]
    assert said.endswith(
        "other platforms' restarts without their signed leave (a crash) are no longer seen: "
        "messages to one that restarted so are sealed on its previous process's session, "
        "which the new process cannot open"
    ), said
