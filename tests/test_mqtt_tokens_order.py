"""MQTT ``tokens()`` does not rely on a broker sending retained messages before live ones.

MQTT orders the messages of one topic, not a subscription's retained replay against
what the broker routes to it later (a clustered broker may not). A relay between the
client and a real mosquitto holds the retained replay back while a live change (a token
cleared, one announced) and the client's own round trip go through, then lets it go:
``tokens()`` still answers what is alive now.
"""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from typing import Any

from agents.transports import MqttConfig, MqttTransport

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
    """A TCP relay to the broker holding back the retained PUBLISHes sent to the client.

    Until ``release`` is set; every other packet goes through at once. ``delivered`` is
    what the client got, in order: (topic, retained) of each PUBLISH.
    """

    def __init__(self, host: str, port: int) -> None:
        self.broker = (host, port)
        self.release = asyncio.Event()
        self.held = 0
        self.holding = asyncio.Event()  # set at the first retained PUBLISH held
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
        held: list[bytes] = []
        release = asyncio.ensure_future(self.release.wait())
        try:
            while True:
                read = asyncio.ensure_future(_packet(reader))
                if not release.done():
                    await asyncio.wait({read, release}, return_when=asyncio.FIRST_COMPLETED)
                if release.done() and held:
                    for packet in held:
                        await self._deliver(writer, packet)
                    held.clear()
                packet = await read
                if packet is None:
                    return
                publish = _publish(packet)
                if publish is not None and publish[1] and not release.done():
                    held.append(packet)
                    self.held += 1
                    self.holding.set()
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
        # quiet long enough for the changes below to happen before the replay is let go
        asker = await stack.enter_async_context(
            MqttTransport(
                MqttConfig(host="127.0.0.1", port=relay.port, keepalive=5, retained_quiet=3.0)
            )
        )
        asking = asyncio.create_task(asker.tokens(f"{prefix}/*", timeout=WAIT))
        async with asyncio.timeout(WAIT):
            await relay.holding.wait()  # the replay has begun, and is held
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
