"""Replies to our key exchange flooded by an outsider, over zenoh and over MQTT.

Anyone on the network can answer a query on ``kx/<peer>``. An attacker process with a
plain zenoh session, or a plain paho client, and no key of the federation, answers each
of uav-a's key-exchange requests to uav-b with a thousand replies, junk and forged
(signed with a key of its own under uav-b's name), while uav-b's own answer is held
back. uav-a refuses every one of them and counts each, audits the first ones one by one
with why, within the unauthenticated-audit budget, and sums up the rest; uav-b's real
reply, once released, still ends the exchange at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import threading
import time
from collections.abc import AsyncIterator
from multiprocessing.connection import Connection
from typing import Any

import pytest

from agents import Agent, AgentPlatform, ServiceDescription, on_request, request, wire_key
from agents._interface import InterfaceAgent, RateLimit
from agents._security import Handshake, KeyPair, TrustStore
from agents.transports import (
    Handle,
    MqttConfig,
    MqttTransport,
    QueryFilter,
    QueryHandler,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from bench._flood import recv

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

FED = "demo"
START = 30.0  # a spawned interpreter imports zenoh and paho: seconds on a loaded machine
WAIT = 15.0  # the bound on any other wait
N_REPLIES = 1000  # the attacker's replies to each request: half junk, half forged
BUDGET = 20.0  # uav-a's RateLimit.unauthenticated: audit records/s, bursts of as many
# uav-b's answer is held until uav-a refused the flood, well within this; the real reply
# must then end the exchange at once, not when the query ends (the attacker never ends it)
KX_TIMEOUT = 20.0
ATTACKER_READY = "kx-reply-flood/attacker"


# -- the attacker: a plain zenoh session or paho client, in a process of its own ----------------


def attacker_main(
    kind: str, where: tuple[str, int], a_public: bytes, n: int, conn: Connection
) -> None:
    """Answer every query on ``kx/uav-b`` with ``n`` replies, junk and forged, until told to stop.

    Forged: a real reply to the request, signed with a key of the attacker's own under
    uav-b's name (it knows uav-a's public key, as everyone may). The zenoh queries are
    never finished: a querier that waited for their end would wait for its timeout.
    """
    fake_b = KeyPair.generate("uav-b")
    forger = Handshake(fake_b, TrustStore(FED, {"uav-a": a_public, "uav-b": fake_b.public_key}))
    answered: list[Any] = []

    def replies(request: bytes) -> list[bytes]:
        forged, _ = forger.respond(request)
        return [b"not a key exchange" if i % 2 == 0 else forged for i in range(n)]

    key = wire_key(FED, "kx", "uav-b")
    if kind == "zenoh":
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", f'["tcp/{where[0]}:{where[1]}"]')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(cfg)

        def on_query(query: zenoh.Query) -> None:
            body = query.payload
            for payload in replies(b"" if body is None else body.to_bytes()):
                query.reply(key, payload)
            answered.append(query)  # kept: the query is not finished while it is held

        queryable = session.declare_queryable(key, on_query)
        # declared after the queryable, and seen in that order: uav-a waits for it (out of
        # the federation's keys: its platforms would take it for one claiming to be there)
        token = session.liveliness().declare_token(ATTACKER_READY)
        try:
            conn.send("ready")
            conn.recv()  # stop
            conn.send(len(answered))
        finally:
            token.undeclare()
            queryable.undeclare()
            answered.clear()
            session.close()
        return

    import paho.mqtt.client as paho
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.properties import Properties

    def on_message(client: paho.Client, userdata: Any, m: paho.MQTTMessage) -> None:
        # what anyone may do: read the query off the broker, answer on its response topic
        props = Properties(PacketTypes.PUBLISH)
        props.CorrelationData = m.properties.CorrelationData
        for payload in replies(m.payload):
            client.publish(m.properties.ResponseTopic, payload, properties=props)
        answered.append(m.payload)

    subscribed = threading.Event()
    client = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
    client.on_message = on_message
    client.on_subscribe = lambda *_: subscribed.set()
    client.connect(*where)
    client.loop_start()
    try:
        client.subscribe(f"@query/{key}")
        if not subscribed.wait(START):
            raise RuntimeError("the broker did not acknowledge the subscription")
        conn.send("ready")
        conn.recv()  # stop
        conn.send(len(answered))
    finally:
        client.loop_stop()
        client.disconnect()


# -- uav-a and uav-b, in this process ----------------------------------------------------------


class Echo(Agent):
    """Answers ``demo`` requests of the federation's platforms."""

    async def setup(self) -> None:
        """Offer a protected service: other platforms of the federation may use it."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(name="echo", type="demo", provider=self.aid, visibility="protected")
        )

    @on_request("demo")
    async def _echo(self, message: Any) -> Any:
        return {"echo": message.content}


def _held(release: asyncio.Event, key_expr: str, handler: QueryHandler) -> QueryHandler:
    """``handler``, or for a key exchange, ``handler`` once ``release`` is set."""
    if "/kx/" not in key_expr:
        return handler

    async def held(key: str, payload: bytes) -> bytes | None:
        async with asyncio.timeout(KX_TIMEOUT):
            await release.wait()
        return await handler(key, payload)

    return held


class HeldZenoh(ZenohTransport):
    """A zenoh transport whose key-exchange answers wait until ``release`` is set."""

    def __init__(self, config: ZenohConfig) -> None:
        super().__init__(config)
        self.release = asyncio.Event()

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Serve as ZenohTransport does; a key exchange is answered once released."""
        return await super().serve(key_expr, _held(self.release, key_expr, handler), admit=admit)


class HeldMqtt(MqttTransport):
    """An MQTT transport whose key-exchange answers wait until ``release`` is set."""

    def __init__(self, config: MqttConfig) -> None:
        super().__init__(config)
        self.release = asyncio.Event()

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Serve as MqttTransport does; a key exchange is answered once released."""
        return await super().serve(key_expr, _held(self.release, key_expr, handler), admit=admit)


async def _sees(t: Transport, key: str) -> None:
    """Wait until ``t`` sees the liveliness token ``key``."""
    watch = await t.watch_presence(key)
    try:
        async with asyncio.timeout(WAIT):
            while not (await watch.get()).alive:
                pass
    finally:
        watch.close()


@contextlib.asynccontextmanager
async def platforms(
    kind: str, mosquitto: tuple[str, int] | None
) -> AsyncIterator[tuple[AgentPlatform, AgentPlatform, asyncio.Event, tuple[str, int]]]:
    """uav-a and uav-b (its key-exchange answers held), and where the attacker connects."""
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    trust = {n: k.public_key for n, k in keys.items()}
    ta: Transport
    tb: HeldZenoh | HeldMqtt
    if kind == "zenoh":
        seed = free_tcp_port()
        where = ("127.0.0.1", seed)
        ta = ZenohTransport(ZenohConfig.loopback(seed))
        tb = HeldZenoh(
            ZenohConfig.loopback(free_tcp_port(), connect=[seed], serve_timeout=KX_TIMEOUT)
        )
    else:
        assert mosquitto is not None
        where = mosquitto
        host, port = mosquitto
        ta = MqttTransport(MqttConfig(host=host, port=port, client_id="uav-a"))
        tb = HeldMqtt(MqttConfig(host=host, port=port, client_id="uav-b", serve_timeout=KX_TIMEOUT))
    async with ta, tb:
        ia_a = InterfaceAgent(
            keys["uav-a"],
            TrustStore(FED, trust),
            audit_interval=0.02,
            handshake_timeout=KX_TIMEOUT,
            rate_limit=RateLimit(unauthenticated=BUDGET),
        )
        ia_b = InterfaceAgent(keys["uav-b"], TrustStore(FED, trust), audit_interval=0.02)
        async with (
            AgentPlatform("uav-a", ta, federation=FED, channel=ia_a) as pa,
            AgentPlatform("uav-b", tb, federation=FED, channel=ia_b) as pb,
        ):
            await _sees(ta, wire_key(FED, "alive", "uav-b"))
            await _sees(tb, wire_key(FED, "alive", "uav-a"))
            yield pa, pb, tb.release, where


def ia(platform: AgentPlatform) -> InterfaceAgent:
    """The platform's Interface Agent."""
    assert isinstance(platform.channel, InterfaceAgent)
    return platform.channel


def refusals(pa: AgentPlatform) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """uav-a's key-exchange refusals audited one by one, and its summaries of the rest."""
    dropped = [r for r in ia(pa).audit.records if r["verdict"] == "dropped"]
    detailed = [r for r in dropped if r.get("stage") == "kx"]
    summed = [r for r in dropped if r.get("stage") == "unauthenticated"]
    return detailed, summed


@pytest.fixture(params=["zenoh", "mqtt"])
def transport(request: pytest.FixtureRequest) -> tuple[str, tuple[str, int] | None]:
    """The transport's kind, and for MQTT the conftest's mosquitto (started only then)."""
    if request.param == "mqtt":
        return "mqtt", request.getfixturevalue("mosquitto")
    return "zenoh", None


async def test_a_flood_of_forged_kx_replies_is_counted_audited_within_budget_and_ignored(
    transport: tuple[str, tuple[str, int] | None],
) -> None:
    """A thousand junk and forged replies to our key exchange: each refused and counted,
    a few audited one by one and the rest summed up; the real reply still ends it at once."""
    kind, mosquitto = transport
    ctx = multiprocessing.get_context("spawn")  # never fork once a zenoh session is open
    here, there = ctx.Pipe()
    attacker: Any = None
    async with asyncio.timeout(START + KX_TIMEOUT + 3 * WAIT):
        async with platforms(kind, mosquitto) as (pa, pb, release, where):
            attacker = ctx.Process(
                target=attacker_main,
                args=(kind, where, ia(pa).keys.public_key, N_REPLIES, there),
                name=f"kx-reply-attacker-{kind}",
            )
            attacker.start()
            ready = await asyncio.to_thread(recv, here, "the attacker", START)
            assert ready == "ready"
            if kind == "zenoh":
                await _sees(pa.transport, ATTACKER_READY)
            asker = await pa.add(Agent("asker"))
            await pb.add(Echo("echo"))
            started = time.monotonic()
            asking = asyncio.create_task(
                request(asker, "echo@uav-b", 1, ontology="demo", timeout=KX_TIMEOUT)
            )

            def audited() -> int:
                detailed, summed = refusals(pa)
                return len(detailed) + sum(r["count"] for r in summed)

            # every reply of the flood refused and in the audit (the summary comes once
            # per report_interval, 1 s), before uav-b's own answer is let go
            deadline = time.monotonic() + KX_TIMEOUT / 2
            while audited() < N_REPLIES and time.monotonic() < deadline:  # noqa: ASYNC110
                await asyncio.sleep(0.01)  # the audit has no event to await: poll it
            flooded = time.monotonic() - started
            assert not asking.done(), asking
            release.set()
            assert await asking == {"echo": 1}
            took = time.monotonic() - started - flooded
            here.send("stop")
            queries = await asyncio.to_thread(recv, here, "the attacker's count")

            detailed, summed = refusals(pa)
            print(
                f"\n{kind}: {N_REPLIES} replies refused in {flooded:.2f} s, "
                f"{len(detailed)} audited one by one, {len(summed)} summaries "
                f"({sum(r['count'] for r in summed)}); "
                f"the real reply then ended the exchange in {took:.2f} s"
            )
            assert queries == 1  # one request, the flood its answer
            # within the budget: its burst, then BUDGET a second, the rest summed up
            assert len(detailed) <= BUDGET * (1 + flooded) + 1, (len(detailed), flooded)
            assert summed, "the flood was not summed up"
            assert len(summed) <= flooded + 2  # one summary per report_interval at most
            assert ia(pa).audit.counts["dropped"] == len(detailed) + len(summed)
            # every refusal counted, and in the audit: one by one or summed up
            assert pa.stats.kx_replies_refused == N_REPLIES
            assert len(detailed) + sum(r["count"] for r in summed) == N_REPLIES
            # the first ones one by one with why, in uav-b's claimed name
            codes = [str(r["reason"]).split(":")[0] for r in detailed[:4]]
            assert codes == ["malformed", "forged", "malformed", "forged"], detailed[:4]
            assert all(r["from"] == "uav-b" for r in detailed)
            assert all(r["count"] > 0 for r in summed)
            # the real reply ended the exchange at once, not at the query's end
            assert took < KX_TIMEOUT / 4, f"the exchange took {took:.2f} s after the real reply"
            assert len(ia(pa).sessions.sessions("uav-b")) == 1
    if attacker is not None:
        attacker.join(timeout=WAIT)
