"""A task cancelled while it waits for the MQTT broker ends, whenever the answer comes.

aiomqtt waits for the broker through ``asyncio.wait_for``, which on Python 3.11 returns
the answer when it comes in the same turn as a cancellation of the waiting task, and the
cancellation is lost. A platform's audit flush, a loop of publishes, went on after its
platform's close cancelled it; the close then waited for it forever (a CI run hung there,
in two tests). The race is made exact here: the broker's real acknowledgement of a QoS 1
publish cancels the publishing task in the same turn.
"""

from __future__ import annotations

import asyncio
import secrets
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from agents.transports import MqttConfig, MqttTransport, mqtt_client

WAIT = 15.0  # s: the bound on the task's end; it ends in milliseconds when it ends at all


class CancelOnAck(dict[int, asyncio.Event]):
    """aiomqtt's pending publishes, whose acknowledgement also cancels ``victim``.

    aiomqtt takes the publish's event out (``pop``) and sets it when the broker's PUBACK
    comes: the cancellation is scheduled then, so it lands in the same turn as the wake-up
    of whoever waits for the event, the order in which 3.11's wait_for loses it.
    """

    victim: asyncio.Task[Any] | None = None
    acks = 0

    def pop(self, mid: int, *default: Any) -> Any:
        """The event of publish ``mid``, and its publisher cancelled in the same turn."""
        event = super().pop(mid, *default)
        self.acks += 1
        if self.victim is not None:
            asyncio.get_running_loop().call_soon(self.victim.cancel)
        return event


async def _publishing_loop_ends(
    client: Any, publish: Callable[[int], Awaitable[None]]
) -> tuple[int, int]:
    """Publish in a loop as the audit flush does, each ack cancelling it: (publishes, acks)."""
    hook = CancelOnAck()
    client._pending_publishes = hook  # aiomqtt's own table of publishes awaiting a PUBACK
    done = 0

    async def loop() -> None:
        nonlocal done
        while True:
            await publish(done)
            done += 1

    task = asyncio.create_task(loop(), name="publishing-loop")
    hook.victim = task
    try:
        finished, _ = await asyncio.wait([task], timeout=WAIT)
        assert task in finished, (
            f"the cancelled loop still runs after {WAIT:g} s: {done} publishes, "
            f"{hook.acks} acknowledgements each with a cancellation, every one lost"
        )
        assert task.cancelled()
    finally:
        hook.victim = None
        task.cancel()
        await asyncio.wait([task])
    return done, hook.acks


async def test_a_transport_publish_cancelled_as_the_broker_acknowledges_it_ends(
    mosquitto: tuple[str, int],
) -> None:
    """A loop of QoS 1 publishes through MqttTransport ends at the cancellation that
    comes with the first acknowledgement, rather than going on publishing."""
    host, port = mosquitto
    topic = f"cancel-{secrets.token_hex(4)}/audit"
    config = MqttConfig(host=host, port=port, client_id=f"c-{secrets.token_hex(4)}", qos=1)
    async with asyncio.timeout(WAIT * 2), MqttTransport(config) as t:
        done, acks = await _publishing_loop_ends(
            t._client, lambda i: t.publish(topic, str(i).encode())
        )
    assert (done, acks) == (0, 1)  # the first publish raised its cancellation


async def test_an_mqtt_client_for_inputs_and_outputs_keeps_a_cancellation_too(
    mosquitto: tuple[str, int],
) -> None:
    """``mqtt_client`` (what an application's MQTT inputs and outputs speak through) ends
    a publishing loop cancelled as the broker acknowledges."""
    host, port = mosquitto
    topic = f"cancel-{secrets.token_hex(4)}/out"
    async with asyncio.timeout(WAIT * 2), mqtt_client(host, port) as client:
        done, acks = await _publishing_loop_ends(
            client, lambda i: client.publish(topic, str(i).encode(), qos=1)
        )
    assert (done, acks) == (0, 1)


async def test_aiomqtt_still_waits_through_the_method_we_replace() -> None:
    """The fix replaces ``aiomqtt.Client._wait_for``: a release that renames it fails here."""
    import aiomqtt

    from agents.transports import _mqtt

    assert callable(getattr(aiomqtt.Client, "_wait_for", None))
    mqtt_client("127.0.0.1", 1)  # loads the client class
    assert _mqtt._Client._wait_for is not aiomqtt.Client._wait_for


@pytest.fixture
def mosquitto(mosquitto: tuple[str, int]) -> tuple[str, int]:
    """The conftest's broker (named here so the module reads alone)."""
    return mosquitto
