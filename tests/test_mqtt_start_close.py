"""The MQTT transport's start and close over a slow or stalled broker.

A platform's start subscribes some 15 topic filters, each confirmed by the broker: one
after another, each cost a round trip, and a slow link or a starved broker made a start
take a second or more. A relay here delays what the broker sends by a known time; a
``SIGSTOP``ped mosquitto (``own_mosquitto``) stands for a broker that stopped answering.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import logging
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
import uuid
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from agents import AgentPlatform, InterfaceAgent, KeyPair, TrustStore
from agents._exceptions import TransportError
from agents.transports import MqttConfig, MqttTls, MqttTransport

WAIT = 10.0  # the bound on any single wait: generous for a loaded 2-core machine


@contextlib.asynccontextmanager
async def slow_link(
    host: str, port: int, delay: float, *, sent: Callable[[bytes], None] | None = None
) -> AsyncIterator[int]:
    """A relay to the broker at ``host:port`` that holds what the broker sends ``delay`` s.

    Every round trip through it then takes at least ``delay`` s, whatever the machine's
    load: a start's time counts its round trips. ``sent`` is shown what a client sends,
    as it goes to the broker. Yields the relay's port.
    """
    tasks: set[asyncio.Future[Any]] = set()

    async def pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, hold: float) -> None:
        loop = asyncio.get_running_loop()
        queued: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

        async def out() -> None:
            while True:
                due, data = await queued.get()
                if not data:
                    writer.close()
                    return
                if (wait := due - loop.time()) > 0:
                    await asyncio.sleep(wait)  # the link's latency itself, not a wait for an event
                writer.write(data)
                await writer.drain()

        sender = asyncio.create_task(out())
        try:
            while data := await reader.read(65536):
                queued.put_nowait((loop.time() + hold, data))
                if sent is not None and hold == 0.0:
                    sent(data)
        except ConnectionError:
            pass
        except asyncio.CancelledError:  # the relay's close: the sender goes with it
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)
            writer.close()
            raise
        queued.put_nowait((loop.time() + hold, b""))
        with contextlib.suppress(ConnectionError):
            await sender

    async def connected(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(host, port)
        both = asyncio.gather(pipe(reader, up_writer, 0.0), pipe(up_reader, writer, delay))
        task = asyncio.ensure_future(both)
        tasks.add(task)
        # ended by the relay's close (the cancel below): a normal end for this connection
        with contextlib.suppress(ConnectionError, asyncio.CancelledError):
            await task

    server = await asyncio.start_server(connected, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def test_a_queryable_takes_one_round_trip_however_many_filters(
    mosquitto: tuple[str, int],
) -> None:
    # a queryable on a/b/c/d/e listens on 6 filters (one per prefix): they were
    # subscribed one after another, 6 round trips
    host, port = mosquitto
    delay = 0.3
    async with (
        slow_link(host, port, delay) as relayed,
        MqttTransport(MqttConfig(host="127.0.0.1", port=relayed)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as asker,
    ):
        key = f"q/{uuid.uuid4().hex}/c/d/e"
        t0 = time.monotonic()

        async def answer(key: str, payload: bytes) -> bytes:
            return b"here"

        async with await t.serve(key, answer):
            took = time.monotonic() - t0
            # in place when serve returns: a query at once is answered
            answers = []
            async with await asker.ask(key, timeout=WAIT) as replies:
                async for reply in replies:
                    answers.append(reply.payload)
                    break
        assert answers == [b"here"]
    assert took < 3 * delay, f"serve took {took:.2f} s over a {delay} s link"


async def test_a_platform_start_over_a_slow_link_overlaps_its_subscribes(
    mosquitto: tuple[str, int],
) -> None:
    # with an Interface Agent a start made ~22 round trips through the broker, one after
    # another; independent subscribes now go out together (~9 round trips)
    host, port = mosquitto
    delay = 0.15
    federation = f"slow-{secrets.token_hex(4)}"
    keys = KeyPair.generate("uav-a")
    trust = TrustStore(federation, {"uav-a": keys.public_key})
    async with (
        slow_link(host, port, delay) as relayed,
        MqttTransport(MqttConfig(host="127.0.0.1", port=relayed, client_id="uav-a")) as t,
    ):
        platform = AgentPlatform(
            "uav-a", t, federation=federation, channel=InterfaceAgent(keys, trust)
        )
        t0 = time.monotonic()
        async with platform:
            took = time.monotonic() - t0
            assert platform.global_df is not None
            assert platform.global_df.platforms == ["uav-a"]
    assert took < 14 * delay, f"the start took {took:.2f} s, {took / delay:.1f} round trips"


async def test_tokens_over_a_stalled_broker_end_at_the_call_s_own_timeout(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]],
) -> None:
    # the key's subscription is there already (a watcher): tokens() subscribes again for
    # the retained messages, and waited aiomqtt's 10 s for the broker's answer
    host, port, broker = own_mosquitto
    key = f"alive/{uuid.uuid4().hex}/*"
    config = MqttConfig(host=host, port=port)
    async with MqttTransport(config) as t:
        watch = await t.watch_presence(key)
        broker.send_signal(signal.SIGSTOP)
        try:
            for _ in range(2):  # a fresh filter too, once the watcher is gone
                t0 = time.monotonic()
                with pytest.raises(TransportError, match="did not take the subscription"):
                    await t.tokens(key, timeout=0.5)
                took = time.monotonic() - t0
                assert took < config.connect_timeout / 4, f"tokens took {took:.1f} s"
                watch.close()
        finally:
            broker.send_signal(signal.SIGCONT)
        async with asyncio.timeout(WAIT):  # and it answers once the broker runs again
            assert await t.tokens(key, timeout=WAIT) == []


def _errors(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


async def test_a_subscribe_given_up_logs_no_error_when_the_broker_answers_later(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]], caplog: pytest.LogCaptureFixture
) -> None:
    # aiomqtt forgot a cancelled subscribe's packet id and logged the SUBACK that still
    # came as 'Unexpected message ID' at ERROR, with a traceback
    host, port, broker = own_mosquitto
    key = f"stall/{uuid.uuid4().hex}"
    caplog.set_level(logging.DEBUG)
    async with (
        MqttTransport(MqttConfig(host=host, port=port)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as sender,
    ):
        broker.send_signal(signal.SIGSTOP)
        try:
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(0.5):
                    await t.subscribe(key)
        finally:
            broker.send_signal(signal.SIGCONT)
        # the broker answers the given-up subscribe, then its unsubscribe; a subscribe
        # after them is in place when it returns
        async with asyncio.timeout(WAIT):
            sub = await t.subscribe(key)
        async with sub:
            await sender.publish(key, b"after")
            assert (await sub.get(timeout=WAIT)).payload == b"after"
    assert _errors(caplog) == []


async def test_starting_and_closing_platforms_logs_no_error(
    mosquitto: tuple[str, int], caplog: pytest.LogCaptureFixture
) -> None:
    # a platform's close unsubscribes its filters, and the transport's close that follows
    # cancelled those unsubscribes: each UNSUBACK still read was logged at ERROR. And
    # aiomqtt warns of "pending publish calls" past 10 (un)subscribes under way: a
    # start's at once are no backlog
    host, port = mosquitto
    federation = f"close-{secrets.token_hex(4)}"
    names = ["uav-a", "uav-b"]
    keys = {n: KeyPair.generate(n) for n in names}
    trust = {n: k.public_key for n, k in keys.items()}
    caplog.set_level(logging.DEBUG)
    for n in names:
        async with (
            MqttTransport(MqttConfig(host=host, port=port, client_id=n)) as t,
            AgentPlatform(
                n,
                t,
                federation=federation,
                channel=InterfaceAgent(keys[n], TrustStore(federation, trust)),
            ),
        ):
            pass
    assert _errors(caplog) == []
    aiomqtt_said = [r.getMessage() for r in caplog.records if r.name == "mqtt"]
    assert [m for m in aiomqtt_said if "pending" in m] == []


async def test_platforms_with_sends_under_way_close_in_bounded_time_over_a_stalled_broker(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]], caplog: pytest.LogCaptureFixture
) -> None:
    """Each platform has publishes the stopped broker does not read: its socket is full.

    The DISCONNECT could not go out behind them, and aiomqtt waited ``connect_timeout``
    for it, one platform after another. Their tokens are cleared all the same (the
    broker sees the connection lost and publishes the will).
    """
    host, port, broker = own_mosquitto
    caplog.set_level(logging.DEBUG, logger="agents.transports._mqtt")
    federation = f"stall-{secrets.token_hex(4)}"
    names = ["uav-a", "uav-b", "uav-c"]
    config = MqttConfig(host=host, port=port)
    loop = asyncio.get_running_loop()
    sends: list[asyncio.Task[None]] = []
    transports: list[MqttTransport] = []
    stack = contextlib.AsyncExitStack()
    try:
        async with stack:
            for n in names:
                transport = MqttTransport(config.model_copy(update={"client_id": n}))
                transports.append(await stack.enter_async_context(transport))
                await stack.enter_async_context(AgentPlatform(n, transport, federation=federation))
                await transport.subscribe(f"dyknow/{federation}/v1/extra/{n}/*")
            broker.send_signal(signal.SIGSTOP)
            for n, transport in zip(names, transports, strict=True):
                for _ in range(64):  # 64 x 256 kB: more than the sockets' buffers take
                    key = f"dyknow/{federation}/v1/bulk/{n}"
                    sends.append(asyncio.create_task(transport.publish(key, bytes(256 * 1024))))
            await asyncio.sleep(0)  # the publishes start (queued, not waited for)
            t0 = loop.time()
        took = loop.time() - t0
    finally:
        broker.send_signal(signal.SIGCONT)
        for task in sends:
            task.cancel()
        await asyncio.gather(*sends, return_exceptions=True)
    # each one waited connect_timeout for its DISCONNECT; now at most a second more
    assert took < config.connect_timeout, f"{len(names)} platforms closed in {took:.1f} s"
    # by closing their sockets: the DISCONNECTs could not go out
    hard = [r.getMessage() for r in caplog.records if "no graceful disconnect" in r.getMessage()]
    assert hard.count("mqtt: no graceful disconnect (timed out): closing the socket") >= len(names)
    async with MqttTransport(config) as watcher:
        key = f"dyknow/{federation}/v1/alive/*"
        deadline = loop.time() + config.connect_timeout
        alive = await watcher.tokens(key, timeout=5.0)
        while alive and loop.time() < deadline:  # each waits for a trip through the broker
            alive = await watcher.tokens(key, timeout=5.0)
        assert alive == [], f"still alive once the broker runs again: {alive}"


async def test_a_subscribe_under_way_when_the_transport_closes_fails_as_closed(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]],
) -> None:
    # the close cancelled the subscribe's wait for the broker's answer, and the caller,
    # which nobody cancelled, got that CancelledError: not caught as a TransportError,
    # and taken for its own cancellation (by a TaskGroup, by asyncio.run)
    host, port, broker = own_mosquitto
    async with MqttTransport(MqttConfig(host=host, port=port)) as t:
        broker.send_signal(signal.SIGSTOP)
        try:
            call = asyncio.create_task(t.subscribe(f"stall/{uuid.uuid4().hex}"))
            done, _ = await asyncio.wait([call], timeout=0.2)
            assert not done  # under way: the stopped broker does not answer
            async with asyncio.timeout(WAIT):
                await t.aclose()
                with pytest.raises(TransportError, match="closed"):
                    await call
            assert not call.cancelled()
        finally:
            broker.send_signal(signal.SIGCONT)


async def test_a_token_whose_declaration_is_given_up_is_not_left_alive(
    mosquitto: tuple[str, int],
) -> None:
    # cancelled once its alive message was out (a platform's start cut short), the
    # token's connection was left open, unreferenced by anyone who could close it: the
    # key stayed alive, a platform that never started seen as a member
    host, port = mosquitto
    u = uuid.uuid4().hex
    out = asyncio.Event()

    def sent(data: bytes) -> None:
        if data[:1] == b"\x33":  # PUBLISH, QoS 1, retained: the token's alive message
            out.set()

    async with (
        slow_link(host, port, 0.5, sent=sent) as relayed,
        MqttTransport(MqttConfig(host="127.0.0.1", port=relayed)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as watcher,
    ):
        declaring = asyncio.create_task(t.declare_token(f"alive/{u}/x"))
        async with asyncio.timeout(WAIT):
            await out.wait()
        declaring.cancel()
        with pytest.raises(asyncio.CancelledError):
            await declaring
        loop = asyncio.get_running_loop()
        deadline = loop.time() + WAIT
        alive = await watcher.tokens(f"alive/{u}/*", timeout=WAIT)
        while alive and loop.time() < deadline:  # each waits for a trip through the broker
            alive = await watcher.tokens(f"alive/{u}/*", timeout=WAIT)
        assert alive == []


def _packets(buf: bytearray) -> list[bytes]:
    """The whole MQTT packets at the front of ``buf``, taken out of it (the rest stays)."""
    out = []
    while len(buf) >= 2:
        length, mult, i = 0, 1, 1
        while True:
            if i >= len(buf):
                return out
            byte = buf[i]
            length += (byte & 0x7F) * mult
            mult *= 128
            i += 1
            if not byte & 0x80:
                break
        if len(buf) < i + length:
            return out
        out.append(bytes(buf[: i + length]))
        del buf[: i + length]
    return out


def _varint_end(packet: bytes, at: int) -> tuple[int, int]:
    """The variable byte integer at ``at``: (its value, where it ends)."""
    value, mult = 0, 1
    while True:
        byte = packet[at]
        value += (byte & 0x7F) * mult
        mult *= 128
        at += 1
        if not byte & 0x80:
            return value, at


class Relay:
    """A relay to a broker that a test steers: refuse filters, drop or stall connections.

    ``refuse[filter] = code`` rewrites the reason codes of the SUBACK answering a
    SUBSCRIBE of that filter (a strict broker: mosquitto 2.0 grants what its ACL denies).
    ``stall`` holds the connections made from then on: their CONNECT is never answered;
    a SUBSCRIBE of a filter starting with one of ``hold`` is never answered either.
    ``open`` counts the client connections not yet closed by the client, ``held`` what
    was held (connections and SUBSCRIBEs). ``forge``, when set, goes to the client once,
    right after the next SUBACK (a broker's packet the client never asked for).
    ``down`` closes the connections made from then on at once (a broker restarting).
    A PUBLISH on a topic starting with one of ``swallow`` goes nowhere: never passed on,
    never acknowledged (a broker that takes it and refuses it for good).
    """

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.refuse: dict[str, int] = {}
        self.stall = False
        self.hold: tuple[str, ...] = ()
        self.open = 0
        self.held = 0
        self.forge = b""
        self.down = False
        self.swallow: tuple[str, ...] = ()
        self.changed = asyncio.Event()
        self.writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[Any]] = set()

    async def wait_for(self, ready: Callable[[], bool]) -> None:
        """Until ``ready()`` holds after a change of connections (TimeoutError past WAIT)."""
        async with asyncio.timeout(WAIT):
            while not ready():
                self.changed.clear()
                await self.changed.wait()

    def drop(self) -> None:
        """Cut every client connection, as a broker or a network that went would."""
        for writer in list(self.writers):
            writer.transport.abort()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._tasks.add(task := asyncio.current_task())  # type: ignore[arg-type]
        self.open += 1
        self.changed.set()
        self.writers.add(writer)
        try:
            if self.down:
                return
            if self.stall:
                self.held += 1
                self.changed.set()
                while await reader.read(65536):  # until the client closes
                    pass
                return
            up_reader, up_writer = await asyncio.open_connection(self.host, self.port)
            refused: dict[bytes, int] = {}  # packet id of a SUBSCRIBE -> the code to answer
            held: set[bytes] = set()  # packet ids of SUBSCRIBEs never answered

            def to_broker(packet: bytes) -> bytes:
                if packet[0] & 0xF0 == 0x30 and self.swallow:  # PUBLISH
                    _, at = _varint_end(packet, 1)
                    n = int.from_bytes(packet[at : at + 2], "big")
                    if packet[at + 2 : at + 2 + n].decode().startswith(self.swallow):
                        return b""
                if packet[0] == 0x82:  # SUBSCRIBE
                    _, at = _varint_end(packet, 1)
                    pid = packet[at : at + 2]
                    props, at = _varint_end(packet, at + 2)
                    at += props
                    while at < len(packet):
                        n = int.from_bytes(packet[at : at + 2], "big")
                        topic = packet[at + 2 : at + 2 + n].decode()
                        if topic.startswith(self.hold) and self.hold:
                            held.add(pid)
                            self.held += 1
                            self.changed.set()
                        code = self.refuse.get(topic)
                        if code is not None:
                            refused[pid] = code
                        at += 2 + n + 1
                return packet

            def to_client(packet: bytes) -> bytes:
                if packet[0] == 0x90:  # SUBACK
                    _, at = _varint_end(packet, 1)
                    if packet[at : at + 2] in held:
                        return b""
                    code = refused.pop(packet[at : at + 2], None)
                    if code is not None:
                        props, start = _varint_end(packet, at + 2)
                        start += props
                        packet = packet[:start] + bytes([code]) * (len(packet) - start)
                    packet, self.forge = packet + self.forge, b""
                return packet

            async def pipe(
                src: asyncio.StreamReader, dst: asyncio.StreamWriter, edit: Callable[[bytes], bytes]
            ) -> None:
                buf = bytearray()
                with contextlib.suppress(ConnectionError):
                    while data := await src.read(65536):
                        buf += data
                        dst.write(b"".join(edit(p) for p in _packets(buf)))
                        await dst.drain()
                dst.close()

            await asyncio.gather(
                pipe(reader, up_writer, to_broker), pipe(up_reader, writer, to_client)
            )
        except ConnectionError:
            pass
        finally:
            self.writers.discard(writer)
            writer.close()
            self.open -= 1
            self.changed.set()
            self._tasks.discard(task)  # type: ignore[arg-type]

    @contextlib.asynccontextmanager
    async def running(self) -> AsyncIterator[int]:
        """Serve on a free loopback port (yielded) until the block ends."""
        server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        try:
            yield server.sockets[0].getsockname()[1]
        finally:
            server.close()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)


async def test_a_subscription_the_broker_refuses_raises_and_leaves_nothing_behind(
    mosquitto: tuple[str, int],
) -> None:
    # the SUBACK's reason codes were not read: a refused subscription counted as
    # confirmed, and its caller waited for messages that would never come
    host, port = mosquitto
    u = uuid.uuid4().hex
    relay = Relay(host, port)
    relay.refuse[f"refused/{u}"] = 0x87  # not authorized
    async with (
        relay.running() as relayed,
        MqttTransport(MqttConfig(host="127.0.0.1", port=relayed)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as sender,
    ):
        filters, sids = dict(t._filters), dict(t._by_sid)
        async with asyncio.timeout(WAIT):
            # two callers sharing the filter: the one waiting on the other's subscribe too
            outcomes = await asyncio.gather(
                t.subscribe(f"refused/{u}"), t.subscribe(f"refused/{u}"), return_exceptions=True
            )
        for outcome in outcomes:
            assert isinstance(outcome, TransportError)
            assert str(outcome) == (
                f"mqtt: the broker refused the subscription to 'refused/{u}': Not authorized (0x87)"
            )
        assert (t._filters, t._by_sid) == (filters, sids)  # nothing of it left
        assert not t._unsubscribing  # nor an unsubscribe of what the broker never held
        # the connection serves on: another subscription works
        async with asyncio.timeout(WAIT):
            sub = await t.subscribe(f"granted/{u}")
        async with sub:
            await sender.publish(f"granted/{u}", b"heard")
            assert (await sub.get(timeout=WAIT)).payload == b"heard"
        # and the refused filter is asked anew, not taken from a filter left behind
        relay.refuse[f"refused/{u}"] = 0x97  # quota exceeded
        with pytest.raises(TransportError, match=r"'refused/.*': Quota exceeded \(0x97\)"):
            async with asyncio.timeout(WAIT):
                await t.watch_presence(f"refused/{u}")
        assert (t._filters, t._by_sid) == (filters, sids)
        # a watcher with history subscribes again to a filter others listen through:
        # refused, it fails, the others keep theirs
        async with asyncio.timeout(WAIT):
            sub = await t.subscribe(f"shared/{u}")
        relay.refuse[f"shared/{u}"] = 0x87
        with pytest.raises(TransportError, match=r"'shared/.*': Not authorized \(0x87\)"):
            async with asyncio.timeout(WAIT):
                await t.watch_presence(f"shared/{u}")
        assert t._filters[f"shared/{u}"].watchers == []
        async with sub:
            await sender.publish(f"shared/{u}", b"kept")
            assert (await sub.get(timeout=WAIT)).payload == b"kept"


async def test_a_subscription_refused_again_after_a_reconnection_ends(
    mosquitto: tuple[str, int], caplog: pytest.LogCaptureFixture
) -> None:
    # subscribed anew after a reconnection, a refused filter's subscribers waited in
    # silence for messages that would never come
    host, port = mosquitto
    u = uuid.uuid4().hex
    relay = Relay(host, port)
    caplog.set_level(logging.WARNING, logger="agents.transports._mqtt")
    async with (
        relay.running() as relayed,
        MqttTransport(MqttConfig(host="127.0.0.1", port=relayed)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as sender,
    ):
        kept = await t.subscribe(f"kept/{u}")
        ended = await t.subscribe(f"ended/{u}")
        watcher = await t.watch_presence(f"ended/{u}")
        relay.refuse[f"ended/{u}"] = 0x8F  # topic filter invalid
        relay.drop()
        async with asyncio.timeout(WAIT):  # the consumers see the end
            assert [m async for m in ended] == []
            assert [p async for p in watcher] == []
        assert f"ended/{u}" not in t._filters
        assert [f.topic for f in t._by_sid.values()] == [f"kept/{u}"]
        said = [r.getMessage() for r in caplog.records]
        assert any(f"'ended/{u}' again after reconnecting (Topic filter invalid" in m for m in said)
        async with asyncio.timeout(WAIT):
            await relay.wait_for(lambda: t.reconnects == 1)
        await sender.publish(f"kept/{u}", b"still")
        assert (await kept.get(timeout=WAIT)).payload == b"still"
        kept.close()
        ended.close()  # closing what ended already is harmless
        watcher.close()


def _aiomqtt_tasks() -> list[asyncio.Task[Any]]:
    return [t for t in asyncio.all_tasks() if "_misc_loop" in repr(t.get_coro())]


@pytest.mark.parametrize("stalled", ["connect", "reply subscribe"])
async def test_a_close_while_reconnecting_leaves_no_connection_behind(
    mosquitto: tuple[str, int], stalled: str
) -> None:
    # the close took the connection it knew (the lost one) and cancelled the
    # reconnection: the new connection, its socket and aiomqtt's task, were left open
    host, port = mosquitto
    relay = Relay(host, port)
    async with relay.running() as relayed:
        t = MqttTransport(MqttConfig(host="127.0.0.1", port=relayed))
        await t.__aenter__()
        await t.subscribe(f"k/{uuid.uuid4().hex}")
        assert len(_aiomqtt_tasks()) == 1
        if stalled == "connect":
            relay.stall = True  # the reconnection's CONNECT is never answered
        else:  # connected, its subscription to its replies is never confirmed
            relay.hold = ("@reply/",)
        relay.drop()
        await relay.wait_for(lambda: relay.held == 1 and relay.open == 1)
        async with asyncio.timeout(WAIT):
            await t.aclose()
        await relay.wait_for(lambda: relay.open == 0)  # its socket closed
        assert _aiomqtt_tasks() == []


@contextlib.contextmanager
def _black_hole() -> Iterator[int]:
    """A listening port whose backlog is full: a client's TCP handshake goes unanswered.

    Its SYN is dropped and retried (after ~1 s, then ~3 s), never answered: paho's own
    connect waits 5 s for it. Yields the port; `_handshaking` leaves out its fillers.
    """
    listener = socket.socket()
    fillers = []
    try:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)  # one connection waiting, never accepted: the next ones dropped
        port = listener.getsockname()[1]
        for _ in range(3):
            filler = socket.socket()
            fillers.append(filler)
            filler.setblocking(False)
            filler.connect_ex(("127.0.0.1", port))
            _fillers.add(filler.getsockname()[1])
        yield port
    finally:
        for s in [*fillers, listener]:
            s.close()


_fillers: set[int] = set()  # the local ports of `_black_hole`'s own connections


def _handshaking(port: int) -> int:
    """How many sockets here, but the fillers, wait for the TCP handshake to ``port``."""
    remote = f"0100007F:{port:04X}"
    with open("/proc/net/tcp") as f:
        rows = [line.split() for line in f.readlines()[1:]]
    return sum(
        1
        for row in rows
        if row[2] == remote and row[3] == "02" and int(row[1][-4:], 16) not in _fillers
    )  # 02: SYN_SENT


def _connecting() -> list[int]:
    """The threads still in paho's connect (`_client_connect`)."""
    return [
        ident
        for ident, frame in sys._current_frames().items()
        if any(f.f_code.co_name == "_client_connect" for f, _ in traceback.walk_stack(frame))
    ]


async def _nothing_left_of(opening: asyncio.Task[Any], port: int, bound: float) -> None:
    """Cancel ``opening`` (an open under way); fail unless nothing is left of it soon.

    Nothing: no TCP handshake to ``port`` under way, no thread in paho's connect, every
    worker thread of the loop's executor joined, no aiomqtt task: within ``bound`` s.
    """
    assert not opening.done()
    loop = asyncio.get_running_loop()
    t0 = time.monotonic()
    opening.cancel()
    with pytest.raises(asyncio.CancelledError):
        await opening
    returned = time.monotonic() - t0
    assert returned < bound, f"the cancelled open took {returned:.2f} s"
    try:
        async with asyncio.timeout(bound):
            # a thread of paho's and the kernel's handshake: no event to await
            while _handshaking(port) or _connecting():  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            if left := _aiomqtt_tasks():
                await asyncio.wait(left)
            await loop.shutdown_default_executor()  # its workers join, or this waits
    except TimeoutError:
        raise AssertionError(
            f"{bound:g} s after the cancel: {_handshaking(port)} handshake(s) under way, "
            f"{len(_connecting())} thread(s) in paho's connect"
        ) from None


async def test_an_open_cancelled_while_the_broker_does_not_accept_leaves_nothing() -> None:
    # paho made the TCP connection in an executor thread, which a cancel does not stop:
    # the cancelled open returned at once, but the thread went on in the connect, its
    # handshake retried, up to paho's 5 s (a black-holed port), holding a worker thread,
    # and the connection made at a retry stayed open until then
    with _black_hole() as port:
        t = MqttTransport(MqttConfig(host="127.0.0.1", port=port, connect_timeout=5.0))
        opening = asyncio.create_task(t.__aenter__())
        async with asyncio.timeout(WAIT):  # its handshake under way (a loaded machine: late)
            while not _handshaking(port):  # noqa: ASYNC110 (the kernel's: no event)
                await asyncio.sleep(0.01)
        # within 1 s: before the handshake's first retry, far from paho's 5 s
        await _nothing_left_of(opening, port, bound=1.0)


async def test_an_open_timed_out_while_the_broker_does_not_accept_leaves_nothing() -> None:
    # the same, for a caller whose own timeout gives up on the open
    with _black_hole() as port:
        t = MqttTransport(MqttConfig(host="127.0.0.1", port=port, connect_timeout=0.2))
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(0.3):  # a caller giving up on the open
                await t.__aenter__()
        async with asyncio.timeout(1.0):
            while _handshaking(port) or _connecting():  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            await asyncio.get_running_loop().shutdown_default_executor()


def _root_ca(path: Path) -> Path:
    """A CA certificate at ``path``, for a client's TLS context (no server ever shows one)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "test ca")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return path


async def test_an_open_cancelled_while_the_broker_never_answers_tls_leaves_nothing(
    tmp_path: Path,
) -> None:
    # a listener that takes the connection and never answers: paho's TLS handshake, in
    # its thread, waited for the server's hello up to 5 s after the open was cancelled
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    listener.setblocking(False)
    port = listener.getsockname()[1]
    loop = asyncio.get_running_loop()
    accepted: list[socket.socket] = []
    try:
        tls = MqttTls(root_ca_certificate=_root_ca(tmp_path / "ca.crt"))
        config = MqttConfig(host="127.0.0.1", port=port, connect_timeout=5.0, tls=tls)
        opening = asyncio.create_task(MqttTransport(config).__aenter__())
        async with asyncio.timeout(WAIT):
            conn, _ = await loop.sock_accept(listener)
            accepted.append(conn)
            conn.setblocking(False)
            assert await loop.sock_recv(conn, 65536)  # its hello, never answered
            while not _connecting():  # noqa: ASYNC110 (a thread of paho's: no event)
                await asyncio.sleep(0.01)
        await _nothing_left_of(opening, port, bound=1.0)
        async with asyncio.timeout(1.0):  # the client's end of it closed
            while await loop.sock_recv(conn, 65536):
                pass
    finally:
        for s in [*accepted, listener]:
            s.close()


async def test_an_open_cancelled_as_paho_s_thread_starts_makes_no_connection_of_its_own(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # cancelled after paho's thread started but before it took the connection made on the
    # loop (a loaded machine: the thread not scheduled yet), the open put paho's own
    # connect back in place, and the thread made a connection of its own: a black hole's
    # held the thread up to paho's 5 s
    import aiomqtt

    started, go = threading.Event(), threading.Event()
    tls_params = aiomqtt.Client._set_tls_params

    def late(self: Any) -> None:  # the first thing paho's thread does
        started.set()
        go.wait(WAIT)
        tls_params(self)

    monkeypatch.setattr(aiomqtt.Client, "_set_tls_params", late)
    listener = socket.socket()
    try:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)  # takes the open's own connection; any next one goes unanswered
        port = listener.getsockname()[1]
        t = MqttTransport(MqttConfig(host="127.0.0.1", port=port, connect_timeout=5.0))
        opening = asyncio.create_task(t.__aenter__())
        async with asyncio.timeout(WAIT):
            while not started.is_set():  # noqa: ASYNC110 (a thread's: no event to await)
                await asyncio.sleep(0.01)
        opening.cancel()
        with pytest.raises(asyncio.CancelledError):
            await opening
        go.set()  # the thread goes on, as its turn comes
        async with asyncio.timeout(2.0):  # far below paho's 5 s
            while _connecting():  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        assert _handshaking(port) == 0
    finally:
        go.set()
        listener.close()
