"""Interaction protocols between two platforms in two OS processes, over zenoh and MQTT.

The child process ("spawn": never fork once a zenoh session is open) runs a DyKnow
instance publishing ``car/car5/speed`` at 50 Hz, a public Gateway Agent and a probe that
reports the gateway's state. Both platforms talk through Interface Agents (keys generated
into a temporary directory, one trust file). The parent knows the child is ready when
its global directory lists the child's gateway service, and never sleeps for a fixed time.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
import signal
import time
import uuid
from collections.abc import AsyncIterator
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import pytest

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    DirectoryEvent,
    GlobalDirectory,
    InterfaceAgent,
    KeyPair,
    ServiceDescription,
    SubscriptionEnded,
    TrustStore,
    on_request,
    request,
    subscribe,
)
from agents.keys import gen_keys, trust_keys
from agents.transports import (
    MqttConfig,
    MqttTransport,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from dyknow_core import DyKnowInstance
from federation import GatewayAgent

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

START = 20.0  # a spawned interpreter imports zenoh, pydantic and DyKnow: seconds when loaded
LABEL = "car/car5/speed"
CHILD, PARENT = "uav-child", "operator"
GATEWAY, PROBE = f"gateway@{CHILD}", f"probe@{CHILD}"
RATE = 0.02  # the child's sensor period, s


def _transport(kind: str, config: dict[str, Any]) -> Transport:
    if kind == "zenoh":
        return ZenohTransport(ZenohConfig.model_validate(config))
    return MqttTransport(MqttConfig.model_validate(config))


# -- the child process -----------------------------------------------------------------------


class Probe(Agent):
    """Tells the parent what the child's gateway is doing (test instrumentation)."""

    def __init__(self, gateway: GatewayAgent) -> None:
        super().__init__("probe")
        self.gateway = gateway

    async def setup(self) -> None:
        """Protected: the parent's platform reaches it through the Interface Agent."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(
                name="probe", type="test-probe", provider=self.aid, visibility="protected"
            )
        )

    @on_request("probe")
    async def _report(self, message: ACLMessage) -> Any:
        """The gateway's live subscriptions, the core's, and the informs sent so far."""
        return {
            "subscriptions": len(self.gateway.subscriptions),
            "core_subscriptions": len(self.gateway.instance.stream(LABEL).subscriptions),
            "informs": self.gateway.gateway_stats.informs,
        }


def child_main(kind: str, config: dict[str, Any], federation: str, keys: str, trust: str) -> None:
    """The child process: DyKnow, a public gateway and the probe, until it is killed."""
    asyncio.run(_child(kind, config, federation, Path(keys), Path(trust)))


async def _child(
    kind: str, config: dict[str, Any], federation: str, keys: Path, trust: Path
) -> None:
    channel = InterfaceAgent(KeyPair.load(keys / f"{CHILD}.key"), TrustStore.load(trust))
    async with (
        _transport(kind, config) as t,
        DyKnowInstance(CHILD) as dk,
        AgentPlatform(CHILD, t, federation=federation, channel=channel) as platform,
    ):
        speed = dk.add_source(LABEL)
        speed.push(0.0)
        gateway = GatewayAgent(dk, visibility="public")
        await platform.add(Probe(gateway))  # first: once the gateway shows, both answer
        await platform.add(gateway)
        i = 1
        while True:  # until the parent kills us
            await asyncio.sleep(RATE)
            speed.push(float(i))
            i += 1


# -- the parent ------------------------------------------------------------------------------


@contextlib.asynccontextmanager
async def _exited(proc: BaseProcess) -> AsyncIterator[asyncio.Future[None]]:
    """A future done when ``proc`` exits (its sentinel becomes readable)."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()

    def on_exit() -> None:
        if not done.done():
            done.set_result(None)

    loop.add_reader(proc.sentinel, on_exit)
    try:
        yield done
    finally:
        loop.remove_reader(proc.sentinel)


async def _next_event(
    events: Subscription[DirectoryEvent], exited: asyncio.Future[None], proc: BaseProcess
) -> DirectoryEvent:
    """The next directory event; fails at once if the child died meanwhile."""
    get = asyncio.ensure_future(events.__anext__())
    try:
        await asyncio.wait([get, exited], return_when=asyncio.FIRST_COMPLETED)
        if not get.done():
            raise AssertionError(f"the child exited with {proc.exitcode} before it was ready")
        return get.result()
    finally:
        get.cancel()


async def _gateway_seen(
    gdf: GlobalDirectory,
    events: Subscription[DirectoryEvent],
    exited: asyncio.Future[None],
    proc: BaseProcess,
) -> ServiceDescription:
    """Wait until the global directory lists the child's gateway: the child is ready."""
    async with asyncio.timeout(START):
        while True:
            found = [s for s in gdf.search(type="dyknow-gateway") if s.platform == CHILD]
            if found:
                return found[0]
            await _next_event(events, exited, proc)


async def _probe(asker: Agent) -> dict[str, Any]:
    report = await request(asker, PROBE, None, ontology="probe", timeout=10)
    assert isinstance(report, dict)
    return report


async def _check_request(asker: Agent) -> None:
    """(a) FIPA-Request → inform: a query on the child's stream, a refusal with its reason."""
    answer = await request(
        asker, GATEWAY, {"action": "query", "label": LABEL}, ontology="dyknow", timeout=10
    )
    assert isinstance(answer, dict) and answer["label"] == LABEL
    [[value, valid, available]] = answer["samples"]
    assert isinstance(value, float) and valid <= available <= time.time() + 1
    labels = await request(asker, GATEWAY, {"action": "list-labels"}, ontology="dyknow", timeout=10)
    assert labels == {"labels": [LABEL]}


async def _check_subscribe(asker: Agent) -> None:
    """(b) FIPA-Subscribe: informs on the policy's grid, then cancel, then no more informs."""
    stream = await subscribe(
        asker,
        GATEWAY,
        {"label": LABEL, "policy": {"sample_period": 0.1}},
        ontology="dyknow",
        timeout=10,
    )
    rows: list[list[Any]] = []
    while len(rows) < 5:
        content = await stream.get(timeout=10)
        assert isinstance(content, dict) and content["label"] == LABEL
        rows.extend(content["samples"])
    valid = [row[1] for row in rows]
    assert valid == sorted(set(valid))
    # one sample per 0.1 s of valid time, on the grid (anchored at time 0)
    assert all(abs(v * 10 - round(v * 10)) < 1e-6 for v in valid), valid
    assert await _probe(asker) | {"informs": 0} == {
        "subscriptions": 1,
        "core_subscriptions": 1,
        "informs": 0,
    }

    await stream.cancel(timeout=10)
    after_cancel = await _probe(asker)
    assert after_cancel["subscriptions"] == 0
    assert after_cancel["core_subscriptions"] == 0
    received, late = asker.stats.received, asker.stats.late

    # Let the child publish a few grid periods more. Every answer comes back on the same
    # path as an inform would, after it: an inform sent meanwhile would have arrived.
    last = valid[-1]
    asked = 0
    async with asyncio.timeout(10):
        while True:
            answer = await request(
                asker, GATEWAY, {"action": "query", "label": LABEL}, ontology="dyknow", timeout=10
            )
            asked += 1
            assert isinstance(answer, dict)
            if answer["samples"][0][1] > last + 0.35:
                break
    assert await _probe(asker) == after_cancel
    assert asker.stats.received == received + asked + 1  # the answers and the probe's only
    assert asker.stats.late == late
    # what came before the cancel is still read (none lost), then the end: an inform the
    # child sent while the last probe went round (a loaded machine) is one of those
    with pytest.raises(SubscriptionEnded):
        for _ in range(100):
            await stream.get(timeout=1)


def _keys(tmp_path: Path, federation: str) -> tuple[Path, Path]:
    """Both platforms' key pairs in one directory, and the federation's trust file."""
    keys, trust = tmp_path / "keys", tmp_path / "trust.json"
    pubs = [gen_keys(name, keys)[2] for name in (PARENT, CHILD)]
    trust_keys(trust, pubs, federation=federation)
    return keys, trust


async def _run(
    parent: Transport, kind: str, child_config: dict[str, Any], tmp_path: Path, *, kill: bool
) -> None:
    federation = f"mp-{uuid.uuid4().hex[:8]}"
    keys, trust = _keys(tmp_path, federation)
    proc = multiprocessing.get_context("spawn").Process(
        target=child_main,
        args=(kind, child_config, federation, str(keys), str(trust)),
        name=f"agents-child-{kind}",
    )
    channel = InterfaceAgent(KeyPair.load(keys / f"{PARENT}.key"), TrustStore.load(trust))
    try:
        async with (
            parent,
            AgentPlatform(PARENT, parent, federation=federation, channel=channel) as platform,
        ):
            gdf = platform.global_df
            assert gdf is not None
            asker = await platform.add(Agent("asker"))
            async with gdf.watch() as events:
                proc.start()
                async with _exited(proc) as exited:
                    service = await _gateway_seen(gdf, events, exited, proc)
                    assert (service.provider, service.visibility) == (GATEWAY, "public")

                    await _check_request(asker)
                    await _check_subscribe(asker)

                    if kill:
                        # (c) a platform that dies leaves the global directory by itself
                        assert proc.pid is not None
                        killed = time.monotonic()
                        os.kill(proc.pid, signal.SIGKILL)
                        async with asyncio.timeout(1.0):
                            while [
                                s for s in gdf.search(type="dyknow-gateway") if s.platform == CHILD
                            ]:
                                await events.__anext__()
                        gone = time.monotonic() - killed
                        assert CHILD not in gdf.platforms
                        ms = gone * 1000
                        print(
                            f"{kind}: the child's gateway left the directory {ms:.0f} ms after kill"
                        )
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join(timeout=10)


async def test_gateway_protocols_between_processes_over_zenoh(tmp_path: Path) -> None:
    port = free_tcp_port()
    parent = ZenohTransport(ZenohConfig.loopback(port))
    child = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
    await _run(parent, "zenoh", child, tmp_path, kill=True)


async def test_gateway_protocols_between_processes_over_mqtt(
    mosquitto: tuple[str, int], tmp_path: Path
) -> None:
    host, port = mosquitto
    parent = MqttTransport(MqttConfig(host=host, port=port, keepalive=2))
    child = MqttConfig(host=host, port=port, keepalive=2).model_dump()  # its own client id
    await _run(parent, "mqtt", child, tmp_path, kill=False)
