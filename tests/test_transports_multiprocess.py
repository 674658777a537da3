"""Transports between separate OS processes, over zenoh and over MQTT.

A child process (started with "spawn": never fork once a zenoh session is open) serves
queries and publishes; the parent subscribes and queries, then SIGKILLs the child and must
see its presence go within a bounded time.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import signal
import time
import uuid
from typing import Any

import pytest

from agents.transports import (
    MqttConfig,
    MqttTransport,
    Presence,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

START = 20.0  # a spawned interpreter imports zenoh and pydantic: seconds on a loaded machine


def _transport(kind: str, config: dict[str, Any]) -> Transport:
    if kind == "zenoh":
        return ZenohTransport(ZenohConfig.model_validate(config))
    return MqttTransport(MqttConfig.model_validate(config))


def child_main(kind: str, config: dict[str, Any], prefix: str) -> None:
    """The child process: serve ``<prefix>/svc/child``, publish on demand, stay alive."""
    asyncio.run(_child(kind, config, prefix))


async def _child(kind: str, config: dict[str, Any], prefix: str) -> None:
    async with _transport(kind, config) as t:
        parent_seen = asyncio.Event()
        watch = await t.watch_presence(f"{prefix}/alive/parent")

        async def track_parent() -> None:
            async for p in watch:
                if p.alive:
                    parent_seen.set()

        async def publish_on_request(key: str, payload: bytes) -> bytes:
            n = int(payload)
            # The parent declared its token after subscribing: once we see the token we
            # know its subscriber too (zenoh propagates declarations in order).
            async with asyncio.timeout(START):
                await parent_seen.wait()
            for i in range(n):
                await t.publish(f"{prefix}/data/child", str(i).encode())
            return f"published {n} from {os.getpid()}".encode()

        async with asyncio.TaskGroup() as tg:
            tg.create_task(track_parent())
            await t.serve(f"{prefix}/svc/child", publish_on_request)
            await t.declare_token(f"{prefix}/alive/child")  # last: we are ready
            await asyncio.Event().wait()  # until the parent kills us


async def _presence(watch: Subscription[Presence], key: str, alive: bool, bound: float) -> None:
    async with asyncio.timeout(bound):
        async for p in watch:
            if p == Presence(key, alive):
                return
    raise AssertionError(f"the presence watch ended before {key} became alive={alive}")


async def _run(
    parent: Transport,
    kind: str,
    child_config: dict[str, Any],
    prefix: str,
    query_timeout: float,
    gone_within: float,
) -> tuple[float, float]:
    """The parent's side; returns (start-to-ready s, kill-to-gone s)."""
    ctx = multiprocessing.get_context("spawn")
    proc = ctx.Process(
        target=child_main, args=(kind, child_config, prefix), name=f"transport-child-{kind}"
    )
    child_key = f"{prefix}/alive/child"
    try:
        async with parent:
            watch = await parent.watch_presence(child_key)
            data = await parent.subscribe(f"{prefix}/data/*")
            await parent.declare_token(f"{prefix}/alive/parent")
            started = time.monotonic()
            proc.start()
            await _presence(watch, child_key, True, START)
            ready = time.monotonic() - started

            replies = await parent.query(f"{prefix}/svc/child", b"5", timeout=query_timeout)
            assert len(replies) == 1 and replies[0].ok, replies
            assert replies[0].payload == f"published 5 from {proc.pid}".encode()
            async with asyncio.timeout(10):
                got = [(await data.get()).payload for _ in range(5)]
            assert got == [b"0", b"1", b"2", b"3", b"4"]

            assert proc.pid is not None
            killed = time.monotonic()
            os.kill(proc.pid, signal.SIGKILL)
            await _presence(watch, child_key, False, gone_within)
            gone = time.monotonic() - killed
            return ready, gone
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join(timeout=10)


async def test_between_processes_over_zenoh() -> None:
    port = free_tcp_port()
    parent = ZenohTransport(ZenohConfig.loopback(port))
    child = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
    prefix = f"mp/{uuid.uuid4().hex[:8]}"
    ready, gone = await _run(parent, "zenoh", child, prefix, query_timeout=10.0, gone_within=2.0)
    print(f"zenoh: child ready after {ready:.2f} s, seen gone {gone * 1000:.1f} ms after SIGKILL")


async def test_between_processes_over_mqtt(mosquitto: tuple[str, int]) -> None:
    host, port = mosquitto
    parent = MqttTransport(MqttConfig(host=host, port=port, keepalive=2))
    child = MqttConfig(host=host, port=port, keepalive=2).model_dump()  # its own client id
    prefix = f"mp/{uuid.uuid4().hex[:8]}"
    # The broker sends the child's last will when its TCP connection closes (at once on a
    # SIGKILL) or, at worst, 1.5 x keepalive = 3 s after its last packet.
    ready, gone = await _run(parent, "mqtt", child, prefix, query_timeout=1.5, gone_within=4.0)
    print(f"mqtt: child ready after {ready:.2f} s, seen gone {gone * 1000:.1f} ms after SIGKILL")


def frozen_child_main(config: dict[str, Any], prefix: str) -> None:
    """A child that subscribes, announces itself, and is then frozen by the parent."""
    asyncio.run(_frozen_child(config, prefix))


async def _frozen_child(config: dict[str, Any], prefix: str) -> None:
    async with ZenohTransport(ZenohConfig.model_validate(config)) as t:
        await t.subscribe(f"{prefix}/flood")
        await t.declare_token(f"{prefix}/alive/frozen")
        await asyncio.Event().wait()


async def test_frozen_receiver_does_not_stall_the_publisher_over_zenoh() -> None:
    port = free_tcp_port()
    child = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
    prefix = f"mp/{uuid.uuid4().hex[:8]}"
    proc = multiprocessing.get_context("spawn").Process(
        target=frozen_child_main, args=(child, prefix), name="transport-child-frozen"
    )
    try:
        async with ZenohTransport(ZenohConfig.loopback(port)) as parent:
            watch = await parent.watch_presence(f"{prefix}/alive/frozen")
            proc.start()
            await _presence(watch, f"{prefix}/alive/frozen", True, START)
            assert proc.pid is not None
            os.kill(proc.pid, signal.SIGSTOP)
            payload = b"x" * 65536
            worst = 0.0
            for _ in range(1500):  # ~100 MB: far more than the socket buffers hold
                t0 = time.perf_counter()
                await parent.publish(f"{prefix}/flood", payload)
                worst = max(worst, time.perf_counter() - t0)
            # With congestion control BLOCK, one put stalls for 5 s here.
            assert worst < 1.0, f"a put stalled for {worst:.3f} s"
            print(f"zenoh: worst put towards a frozen receiver {worst * 1000:.1f} ms")
            # Kill it before closing: closing towards a frozen peer takes zenoh's ~10 s
            # close timeout, a dead one is seen at once.
            proc.kill()
            await asyncio.to_thread(proc.join, 10)
    finally:
        if proc.is_alive():
            proc.kill()  # SIGKILL ends a stopped process too
        proc.join(timeout=10)
