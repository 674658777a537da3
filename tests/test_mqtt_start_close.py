"""The MQTT transport's start and close over a slow or stalled broker.

A platform's start subscribes some 15 topic filters, each confirmed by the broker: one
after another, each cost a round trip, and a slow link or a starved broker made a start
take a second or more. A relay here delays what the broker sends by a known time; a
``SIGSTOP``ped mosquitto (``own_mosquitto``) stands for a broker that stopped answering.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import signal
import subprocess
import time
import uuid
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from agents import AgentPlatform, InterfaceAgent, KeyPair, TrustStore
from agents._exceptions import TransportError
from agents.transports import MqttConfig, MqttTransport

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
