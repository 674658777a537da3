"""MQTT ``tokens()``: when the retained replay comes, what it holds, and what it keeps.

MQTT orders the messages of one topic, not a subscription's retained replay against
what the broker routes to it later (a clustered broker may not). A relay between the
client and a real mosquitto holds back the retained replay and the client's own round
trip while a live change (a token cleared, one announced) goes through, then lets them
go: ``tokens()`` still answers what is alive now. With a quiet time, a replay that comes
just after a slow round trip is still waited for; and a flood of invented retained keys
does not crowd out those a caller keeps.
"""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import aiomqtt
import pytest
from pydantic import ValidationError

from agents import wire_key
from agents.transports import MqttConfig, MqttTransport
from agents.transports._mqtt import _MAX_PRESENCE_KEYS, REPLY_PREFIX
from federation._local import PlatformAliveError, refuse_duplicate

WAIT = 10.0  # the bound on any single wait: generous for a loaded 2-core machine
_PUBLISH = 3  # MQTT control packet type


async def _packet(reader: asyncio.StreamReader) -> bytes | None:
    """One whole MQTT control packet as read off the stream; None at its end."""
    try:
        head = await reader.readexactly(1)
        length_bytes = b""
        length, shift = 0, 0
        while True:
            b = await reader.readexactly(1)
            length_bytes += b
            length |= (b[0] & 0x7F) << shift
            shift += 7
            if not b[0] & 0x80:
                break
        return head + length_bytes + await reader.readexactly(length)
    except asyncio.IncompleteReadError:
        return None


def _publish(packet: bytes) -> tuple[str, bool] | None:
    """A PUBLISH packet's topic and retain flag; None for another packet."""
    if packet[0] >> 4 != _PUBLISH:
        return None
    i = 1
    while packet[i] & 0x80:  # the remaining length's bytes
        i += 1
    i += 1
    size = int.from_bytes(packet[i : i + 2], "big")
    return packet[i + 2 : i + 2 + size].decode(), bool(packet[0] & 1)


class HoldingRelay:
    """A TCP relay to the broker holding back what the broker owes a subscribing client.

    The retained PUBLISHes and the client's own round trip (a PUBLISH on its reply topic)
    wait until ``release`` is set; every other packet goes through at once. Then the
    round trip goes first when ``echo_first`` (the replay ``replay_after`` s after it),
    else last. ``delivered`` is what the client got, in order: (topic, retained) of each
    PUBLISH.
    """

    def __init__(
        self, host: str, port: int, *, echo_first: bool = False, replay_after: float = 0.0
    ) -> None:
        self.broker = (host, port)
        self.echo_first = echo_first
        self.replay_after = replay_after
        self.release = asyncio.Event()
        self.held = 0
        self.holding = asyncio.Event()  # set at the first retained PUBLISH held
        self.echo_held = asyncio.Event()
        self.delivered: list[tuple[str, bool]] = []
        self.passed = asyncio.Condition()
        self.port = 0
        self._tasks: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> HoldingRelay:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *_: Any) -> None:
        self._server.close()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection(*self.broker)
        for coro in (self._up(reader, up_writer), self._down(up_reader, writer)):
            task = asyncio.create_task(coro)
            self._tasks.add(task)

    async def _up(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        writer.close()

    async def _down(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        replay: list[bytes] = []
        echo: list[bytes] = []
        release = asyncio.ensure_future(self.release.wait())
        try:
            while True:
                read = asyncio.ensure_future(_packet(reader))
                if not release.done():
                    await asyncio.wait({read, release}, return_when=asyncio.FIRST_COMPLETED)
                if release.done() and (replay or echo):
                    first, then = (echo, replay) if self.echo_first else (replay, echo)
                    for packet in first:
                        await self._deliver(writer, packet)
                    if self.echo_first and replay and self.replay_after:
                        # a broker whose replay trails the echo: the delay is the case
                        await asyncio.sleep(self.replay_after)
                    for packet in then:
                        await self._deliver(writer, packet)
                    replay.clear()
                    echo.clear()
                packet = await read
                if packet is None:
                    return
                publish = _publish(packet)
                if publish is not None and not release.done():
                    if publish[1]:
                        replay.append(packet)
                        self.held += 1
                        self.holding.set()
                        continue
                    if publish[0].startswith(REPLY_PREFIX):
                        echo.append(packet)
                        self.echo_held.set()
                        continue
                await self._deliver(writer, packet)
        except ConnectionError:
            return
        finally:
            release.cancel()
            writer.close()

    async def _deliver(self, writer: asyncio.StreamWriter, packet: bytes) -> None:
        writer.write(packet)
        await writer.drain()
        publish = _publish(packet)
        if publish is not None:
            async with self.passed:
                self.delivered.append(publish)
                self.passed.notify_all()

    async def wait_delivered(self, topic: str, retained: bool) -> None:
        """Until a PUBLISH on ``topic`` with that retain flag reached the client."""
        async with asyncio.timeout(WAIT), self.passed:
            await self.passed.wait_for(lambda: (topic, retained) in self.delivered)


async def test_a_live_change_during_the_retained_replay_wins_whatever_the_order(
    mosquitto: tuple[str, int],
) -> None:
    host, port = mosquitto
    prefix = f"test/{uuid.uuid4().hex[:10]}/alive"
    stays = [f"{prefix}/s{i}" for i in range(5)]
    goes, comes = f"{prefix}/goes", f"{prefix}/comes"
    async with contextlib.AsyncExitStack() as stack:
        holder = await stack.enter_async_context(
            MqttTransport(MqttConfig(host=host, port=port, keepalive=5))
        )
        for key in stays:
            await holder.declare_token(key)
        gone = await holder.declare_token(goes)
        relay = await stack.enter_async_context(HoldingRelay(host, port))
        # the round trip is held with the replay: tokens() cannot end before the release
        asker = await stack.enter_async_context(
            MqttTransport(MqttConfig(host="127.0.0.1", port=relay.port, keepalive=5))
        )
        asking = asyncio.create_task(asker.tokens(f"{prefix}/*", timeout=WAIT))
        async with asyncio.timeout(WAIT):
            await relay.holding.wait()  # the replay has begun, and is held
            await relay.echo_held.wait()
        await gone.aclose()  # routed live: it overtakes the replay's retained 'alive'
        await relay.wait_delivered(goes, retained=False)
        await holder.declare_token(comes)
        await relay.wait_delivered(comes, retained=False)
        relay.release.set()
        alive = await asyncio.wait_for(asking, WAIT)
        assert relay.held == len(stays) + 1  # every retained one came after the live ones
        order = relay.delivered
        assert order.index((goes, False)) < order.index((goes, True))
        assert alive == sorted([*stays, comes])


async def test_a_replay_just_after_a_slow_round_trip_is_waited_for(
    mosquitto: tuple[str, int],
) -> None:
    host, port = mosquitto
    prefix = f"test/{uuid.uuid4().hex[:10]}/alive"
    quiet = 0.5
    async with contextlib.AsyncExitStack() as stack:
        holder = await stack.enter_async_context(MqttTransport(MqttConfig(host=host, port=port)))
        await holder.declare_token(f"{prefix}/a")
        # the replay a tenth of the quiet time after the echo: within it, so waited for
        relay = await stack.enter_async_context(
            HoldingRelay(host, port, echo_first=True, replay_after=quiet / 10)
        )
        asker = await stack.enter_async_context(
            MqttTransport(MqttConfig(host="127.0.0.1", port=relay.port, retained_quiet=quiet))
        )
        loop = asyncio.get_running_loop()
        started = loop.time()
        asking = asyncio.create_task(asker.tokens(f"{prefix}/*", timeout=WAIT))
        async with asyncio.timeout(WAIT):
            await relay.holding.wait()
            await relay.echo_held.wait()
        # a broker far away: the round trip takes longer than the quiet time
        await asyncio.sleep(max(0.0, started + 2 * quiet - loop.time()))
        relay.release.set()
        assert await asyncio.wait_for(asking, WAIT) == [f"{prefix}/a"]
        echo, replay = relay.delivered[-2:]
        assert echo[0].startswith(REPLY_PREFIX) and replay == (f"{prefix}/a", True)


async def test_no_quiet_time_answers_at_the_echo_on_mosquitto(mosquitto: tuple[str, int]) -> None:
    host, port = mosquitto
    prefix = f"test/{uuid.uuid4().hex[:10]}/alive"
    assert MqttConfig().retained_quiet == 0.0  # the default: mosquitto sends retained first
    with pytest.raises(ValidationError, match="retained_quiet"):
        MqttConfig(retained_quiet=-0.1)
    keys = [f"{prefix}/p{i:02d}" for i in range(40)]
    async with contextlib.AsyncExitStack() as stack:
        holder = await stack.enter_async_context(MqttTransport(MqttConfig(host=host, port=port)))
        for key in keys:
            await holder.declare_token(key)
        asker = await stack.enter_async_context(
            MqttTransport(MqttConfig(host=host, port=port, retained_quiet=0))
        )
        for _ in range(3):  # every time, not once by luck
            assert await asker.tokens(f"{prefix}/*", timeout=WAIT) == keys


async def test_a_flood_of_invented_presences_does_not_hide_the_kept_ones(
    mosquitto: tuple[str, int],
) -> None:
    host, port = mosquitto
    fed = f"flood-{uuid.uuid4().hex[:10]}"
    prefix = wire_key(fed, "alive", "")
    members = {f"{prefix}member-early", f"{prefix}member-late"}
    junk = [f"{prefix}junk{i:05d}" for i in range(_MAX_PRESENCE_KEYS + 100)]
    async with contextlib.AsyncExitStack() as stack:
        holder = await stack.enter_async_context(MqttTransport(MqttConfig(host=host, port=port)))
        await holder.declare_token(f"{prefix}member-early")
        # an attacker on the broker: more retained presences than a call remembers
        async with aiomqtt.Client(host, port) as attacker:
            for key in junk:
                await attacker.publish(key, b'{"v":1,"alive":true}', retain=True)
        await holder.declare_token(f"{prefix}member-late")
        asker = await stack.enter_async_context(MqttTransport(MqttConfig(host=host, port=port)))
        try:
            every = wire_key(fed, "alive", "*")
            unscreened = await asker.tokens(every, timeout=WAIT)
            assert len(unscreened) == _MAX_PRESENCE_KEYS  # bounded: some are crowded out
            hidden = sorted(members - set(unscreened))
            assert hidden  # the flood does hide a member from a call that keeps every key
            kept = await asker.tokens(every, timeout=WAIT, keep=members.__contains__)
            assert kept == sorted(members)
            # a start's check of its name keeps only its own key: the flood hides it not
            name = hidden[0].rpartition("/")[2]
            with pytest.raises(PlatformAliveError, match=name):
                # no key to read: no local channel to look at, only the broker's presences
                config = SimpleNamespace(federation=fed, name=name, key=Path("no-such.key"))
                await refuse_duplicate(asker, config, wait=WAIT)  # type: ignore[arg-type]
        finally:
            async with aiomqtt.Client(host, port) as attacker:  # leave the broker clean
                for key in junk:
                    await attacker.publish(key, b"", retain=True)
