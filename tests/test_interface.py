"""The Interface Agent: authenticated sessions, access control and audit between platforms.

Several platforms share one MemoryHub (one process); one test runs over zenoh on loopback,
two over MQTT (the conftest's mosquitto).
Hostile envelopes are built from real ones captured on the wire, or sealed with the
sender's own session table, so each check of the receiving side is hit on purpose.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import os
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import orjson
import paho.mqtt.client as paho
import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    MessageError,
    MessageTemplate,
    Performative,
    RateLimit,
    Refused,
    ReplyTimeout,
    SecurityError,
    ServiceDescription,
    TransportError,
    on,
    on_request,
    query_ref,
    request,
    search_services,
    wire_key,
)
from agents import Performative as P
from agents import _interface as interface_module
from agents._exceptions import Forged
from agents._interface import AuditLog, InterfaceAgent, accepted_entry
from agents._security import Handshake, KeyPair, OwnerBatches, SecurityPolicy, TrustStore
from agents.transports import (
    Handle,
    MemoryHub,
    MemoryTransport,
    Message,
    MqttConfig,
    MqttTransport,
    Presence,
    QueryFilter,
    QueryHandler,
    Replies,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)

FED = "demo"  # on a MemoryHub of one test's own; over zenoh or a broker: `unique_federation`
WAIT = 5.0  # the bound on any single wait; every test finishes far below it

T = TypeVar("T")


# -- helpers ---------------------------------------------------------------------------------


class Echo(Agent):
    """Answers ``demo`` requests and remembers every message that reached its handlers."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.calls: list[ACLMessage] = []
        self.informs: list[ACLMessage] = []

    @on_request("demo")
    async def _echo(self, message: ACLMessage) -> Any:
        self.calls.append(message)
        return {"echo": message.content, "by": self.aid}

    @on(MessageTemplate(Performative.INFORM, ontology="demo"))
    async def _inform(self, message: ACLMessage) -> None:
        self.informs.append(message)


class Listener(Agent):
    """Keeps every not-understood it gets, and wakes whoever waits for one."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.not_understood: list[ACLMessage] = []
        self.got = asyncio.Event()
        self.add_handler(MessageTemplate(Performative.NOT_UNDERSTOOD), self._keep)

    async def _keep(self, message: ACLMessage) -> None:
        self.not_understood.append(message)
        self.got.set()


class CountingTransport(MemoryTransport):
    """A memory transport that counts key-exchange queries and makes them a little slow."""

    def __init__(self, hub: MemoryHub, delay: float = 0.0) -> None:
        super().__init__(hub)
        self.kx_queries = 0
        self.delay = delay

    async def ask(self, key_expr: str, payload: bytes = b"", *, timeout: float) -> Replies:
        """Count (and delay) key exchanges, then ask as usual."""
        if "/kx/" in key_expr:
            self.kx_queries += 1
            if self.delay:
                # long enough for concurrent senders to pile up behind one exchange
                await asyncio.sleep(self.delay)
        return await super().ask(key_expr, payload, timeout=timeout)


class DeafTransport(MemoryTransport):
    """A memory transport that never hears liveliness changes (as when events are lost)."""

    async def watch_presence(
        self, key_expr: str, *, history: bool = True, buffer_size: int = 4096
    ) -> Subscription[Presence]:
        """A watch on a key nobody declares: it never yields."""
        return await super().watch_presence(
            "nothing/matches/this", history=history, buffer_size=buffer_size
        )


class LateTokenTransport(MemoryTransport):
    """A memory transport whose liveliness tokens others see only once ``show`` is awaited.

    As zenoh on a loaded machine may deliver a platform's token after its first messages.
    """

    def __init__(self, hub: MemoryHub) -> None:
        super().__init__(hub)
        self.hidden: list[str] = []

    async def declare_token(self, key: str) -> Handle:
        """Keep the token back (until ``show``)."""
        self.hidden.append(key)
        return Handle(lambda: None)

    async def show(self) -> None:
        """Declare the tokens kept back."""
        for key in self.hidden:
            await super().declare_token(key)


class Fed:
    """A federation on one MemoryHub: keys, one trust file, platforms opened and closed."""

    def __init__(self, *names: str) -> None:
        self.hub = MemoryHub()
        self.keys = {n: KeyPair.generate(n) for n in names}
        self.trust = TrustStore(FED, {n: k.public_key for n, k in self.keys.items()})
        self._stacks: dict[str, contextlib.AsyncExitStack] = {}
        self._extra: list[contextlib.AsyncExitStack] = []

    def trust_copy(self) -> TrustStore:
        """Each platform reads its own copy of the trust file."""
        return TrustStore(FED, {p: self.trust.public_key(p) for p in self.trust})

    async def start(
        self, name: str, *, transport: MemoryTransport | None = None, **options: Any
    ) -> AgentPlatform:
        """Open transport and platform ``name`` with an Interface Agent as its channel."""
        stack = contextlib.AsyncExitStack()
        try:
            t = await stack.enter_async_context(transport or self.hub.transport())
            options.setdefault("audit_interval", 0.02)
            channel = InterfaceAgent(self.keys[name], self.trust_copy(), **options)
            p = await stack.enter_async_context(
                AgentPlatform(name, t, federation=FED, channel=channel)
            )
        except BaseException:
            await stack.aclose()
            raise
        self._stacks[name] = stack
        return p

    async def stop(self, name: str) -> None:
        """Close platform ``name`` and its transport (as a process exit would)."""
        await self._stacks.pop(name).aclose()

    async def raw(self) -> MemoryTransport:
        """A plain transport on the hub: what anyone on the network can do."""
        stack = contextlib.AsyncExitStack()
        self._extra.append(stack)
        return await stack.enter_async_context(self.hub.transport())

    async def aclose(self) -> None:
        """Close everything, newest first."""
        for name in reversed(list(self._stacks)):
            await self.stop(name)
        for stack in reversed(self._extra):
            await stack.aclose()


@contextlib.asynccontextmanager
async def federation(*names: str) -> AsyncIterator[Fed]:
    """A federation of ``names`` (not started), closed on exit, every wait bounded."""
    fed = Fed(*names)
    try:
        async with asyncio.timeout(WAIT * 2):
            yield fed
    finally:
        await fed.aclose()


def ia(platform: AgentPlatform) -> InterfaceAgent:
    """The platform's Interface Agent."""
    assert isinstance(platform.channel, InterfaceAgent)
    return platform.channel


async def until(predicate: Callable[[], T], what: str, timeout: float = WAIT) -> T:
    """Poll ``predicate`` (cheap, in memory) until it is truthy; fail after ``timeout`` s."""
    try:
        async with asyncio.timeout(timeout):
            # the audit and session tables have no events to await: poll them, briefly
            while not (value := predicate()):  # noqa: ASYNC110
                await asyncio.sleep(0.005)
            return value
    except TimeoutError:
        raise AssertionError(f"timed out waiting for {what}") from None


def records(platform: AgentPlatform, **match: Any) -> list[dict[str, Any]]:
    """The audit records of ``platform`` whose fields equal ``match``."""
    return [r for r in ia(platform).audit.records if all(r.get(k) == v for k, v in match.items())]


async def audited(platform: AgentPlatform, code: str | None = None, **match: Any) -> dict[str, Any]:
    """Wait for the audit record matching ``match`` (and whose reason starts with ``code``)."""

    def find() -> dict[str, Any] | None:
        for r in records(platform, **match):
            if code is None or str(r.get("reason")).startswith(f"{code}:"):
                return r
        return None

    found = await until(find, f"an audit record {match} {code or ''} on {platform.name}")
    return found


async def serve(platform: AgentPlatform, name: str, visibility: str | None = "protected") -> Echo:
    """Start an Echo agent; register a service of ``visibility`` (None: no service)."""
    agent = await platform.add(Echo(name))
    if visibility is not None:
        assert platform.df is not None
        await platform.df.register(
            ServiceDescription(
                name=f"{name}-svc", type="demo", provider=agent.aid, visibility=visibility
            )
        )
    return agent


def untouched(agent: Echo, calls: int, received: int) -> None:
    """Nothing more reached ``agent``: no handler call, nothing queued, nothing counted."""
    assert len(agent.calls) == calls
    assert agent.informs == []
    assert len(agent._mailbox) == 0
    assert agent.stats.received == received


def acl(sender: str, receiver: str, content: Any = None, **fields: Any) -> ACLMessage:
    """A request as a sender's platform would put it in an envelope."""
    fields.setdefault("ontology", "demo")
    fields.setdefault("protocol", "fipa-request")
    return ACLMessage(
        performative=fields.pop("performative", Performative.REQUEST),
        sender=sender,
        receivers=[receiver],
        content=content,
        conversation_id=fields.pop("conversation_id", f"c-test-{os.urandom(4).hex()}"),
        **fields,
    )


# -- request and inform, audit ------------------------------------------------------------


async def test_request_inform_both_ways_audited_and_published() -> None:
    """Requests are answered both ways; each accepted message is audited and published."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-b"))
        echo_a = await serve(pa, "echo")
        echo_b = await serve(pb, "echo")

        assert await request(echo_a, "echo@uav-b", {"x": 1}, ontology="demo") == {
            "echo": {"x": 1},
            "by": "echo@uav-b",
        }
        assert await request(echo_b, "echo@uav-a", [2], ontology="demo") == {
            "echo": [2],
            "by": "echo@uav-a",
        }
        assert [m.sender for m in echo_b.calls] == ["echo@uav-a"]
        assert [m.sender for m in echo_a.calls] == ["echo@uav-b"]

        # each side accepted one request and one inform, refused and dropped nothing
        for p, peer in ((pa, "uav-b"), (pb, "uav-a")):
            audit = ia(p).audit
            assert audit.counts == {"accepted": 2, "refused": 0, "dropped": 0}
            assert [r["performative"] for r in audit.records] == (
                ["request", "inform"] if p is pb else ["inform", "request"]
            )
            for r in audit.records:
                assert r["verdict"] == "accepted"
                assert r["from"] == peer
                assert r["platform"] == p.name
                assert r["reason"] is None
                assert r["v"] == 1
                assert isinstance(r["ts"], float)
        req = records(pb, performative="request")[0]
        assert req["sender"] == "echo@uav-a"
        assert req["receivers"] == ["echo@uav-b"]
        assert req["conversation_id"] == echo_b.calls[0].conversation_id

        # the same records go out on dyknow/<fed>/v1/audit/<platform>, as JSON lines sealed
        # to the platform's owner: only its key opens them
        seen: list[dict[str, Any]] = []
        async with asyncio.timeout(WAIT):
            while not any(r["performative"] == "request" for r in seen):
                msg = await feed.get()
                with pytest.raises(Forged):
                    ia(pa).keys.open_sealed(msg.payload)
                lines = _opened(ia(pb).keys, msg)
                assert lines.endswith(b"\n")
                seen += [orjson.loads(line) for line in lines.splitlines()]
        published = next(r for r in seen if r["performative"] == "request")
        assert published == req


async def test_an_idle_audit_flush_sleeps_and_wakes_for_the_next_record() -> None:
    """Nothing to flush: the task sleeps; what comes next is published within an interval."""
    async with federation("uav-a") as fed:
        pa = await fed.start("uav-a", audit_interval=0.05)
        channel = ia(pa)
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-a"))
        await until(lambda: channel._flush_idle, "the audit flush asleep")
        await asyncio.sleep(0.3)  # six intervals: it does not tick meanwhile
        assert channel._flush_idle

        async def published(stage: str) -> float:
            """Seconds until a record of ``stage`` is published."""
            t0 = time.monotonic()
            async with asyncio.timeout(WAIT):
                while True:
                    lines = _opened(channel.keys, await feed.get())
                    if any(orjson.loads(x).get("stage") == stage for x in lines.splitlines()):
                        return time.monotonic() - t0

        channel.audit.record(verdict="dropped", stage="test", reason="after an idle spell")
        assert await published("test") < 1.0  # an interval (0.05 s), with room for a loaded CI
        await until(lambda: channel._flush_idle, "the audit flush asleep again")
        # watch requests shed on the transport's thread wake it too
        shed = threading.Thread(target=lambda: [channel._admit_watch(b"") for _ in range(50)])
        shed.start()
        shed.join()
        assert channel.watch_shed > 0
        assert await published("watch-shed") < 1.0


async def test_accepted_messages_alone_or_batched_wake_an_asleep_audit_flush() -> None:
    """A request that comes alone, or a batch: their accepted records are published soon."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b", audit_interval=0.05)
        channel = ia(pb)
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-b"))
        asker = await serve(pa, "asker", None)
        echo = await serve(pb, "echo")

        async def accepted_published(n: int) -> None:
            """Until ``n`` accepted records from uav-a came in published audit batches."""
            seen = 0
            async with asyncio.timeout(1.0):  # an interval (0.05 s), room for a loaded CI
                while seen < n:
                    lines = _opened(channel.keys, await feed.get()).splitlines()
                    seen += sum(
                        1
                        for x in lines
                        if (r := orjson.loads(x))["verdict"] == "accepted" and r["from"] == "uav-a"
                    )

        for round_ in range(2):
            await until(lambda: channel._flush_idle, "the audit flush asleep")
            feed.inbox.drain()
            # alone: the request and its reply take the one-message path
            assert await request(asker, "echo@uav-b", {"r": round_}, ontology="demo") is not None
            await accepted_published(1)
            await until(lambda: channel._flush_idle, "the audit flush asleep again")
            feed.inbox.drain()
            informs = len(echo.informs)
            # a batch (as a burst's second envelope is) is the first thing after the sleep
            batch = [
                asker.message(Performative.INFORM, "echo@uav-b", {"i": i}, ontology="demo")
                for i in range(20)
            ]
            body = b"[" + b",".join(m.to_json() for m in batch) + b"]"
            await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
            want = informs + 20
            await until(lambda w=want: len(echo.informs) == w, "the 20 informs")
            await accepted_published(20)


# -- hostile envelopes ----------------------------------------------------------------------


@dataclass
class Pair:
    """uav-a (its clock can be moved) and uav-b, with a session and a captured envelope."""

    pa: AgentPlatform
    pb: AgentPlatform
    asker: Echo
    echo: Echo
    envelope: bytes
    offset: list[float]


def envelope_from(envelope: bytes) -> str:
    """The claimed sender of an ACL envelope, in either form (JSON, or binary: msgpack)."""
    if envelope[:1] == b"{":
        return str(orjson.loads(envelope)["from"])
    return str(msgpack.unpackb(envelope)[1])


async def _captured_session(fed: Fed, *, binary_acl: bool = True) -> Pair:
    """uav-a and uav-b with a session, and the envelope of a real request captured on the wire.

    ``binary_acl``: the form uav-a seals in (False: JSON, for the tests that edit its fields).
    """
    offset = [0.0]
    pa = await fed.start("uav-a", clock=lambda: time.time() + offset[0], binary_acl=binary_acl)
    pb = await fed.start("uav-b")
    raw = await fed.raw()
    wire = await raw.subscribe(wire_key(FED, "acl", "uav-b"))
    asker = await serve(pa, "asker", None)
    echo = await serve(pb, "echo")
    assert await request(asker, "echo@uav-b", {"x": 1}, ontology="demo") is not None
    envelope = (await wire.get(WAIT)).payload
    wire.close()
    assert envelope_from(envelope) == "uav-a"
    return Pair(pa, pb, asker, echo, envelope, offset)


async def test_forged_tampered_replayed_expired_and_untrusted_envelopes_are_dropped() -> None:
    """Hostile envelopes never reach an agent and are audited as dropped, with their code.

    JSON envelopes; the binary form's are attacked in tests/test_binary_acl.py.
    """
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed, binary_acl=False)
        pb, asker, echo, envelope = pair.pb, pair.asker, pair.echo, pair.envelope
        raw = await fed.raw()
        inbox = wire_key(FED, "acl", "uav-b")
        env = orjson.loads(envelope)
        calls, received = len(echo.calls), echo.stats.received

        # encrypted by default: a made-up box, and one with a flipped ciphertext byte
        box = base64.b64decode(env["box"])
        forged = {
            **env,
            "n": env["n"] + 100,
            "box": base64.b64encode(os.urandom(len(box))).decode(),
        }
        await raw.publish(inbox, orjson.dumps(forged))
        rec = await audited(pb, "forged", verdict="dropped")
        assert rec["from"] == "uav-a"

        flipped = bytes([box[0] ^ 1]) + box[1:]
        tampered = {**env, "n": env["n"] + 101, "box": base64.b64encode(flipped).decode()}
        await raw.publish(inbox, orjson.dumps(tampered))
        await until(lambda: len(records(pb, verdict="dropped")) == 2, "the tampered envelope")
        assert str(records(pb, verdict="dropped")[1]["reason"]).startswith("forged:")

        await raw.publish(inbox, envelope)  # the very bytes, again
        rec = await audited(pb, "replayed", verdict="dropped")
        assert rec["from"] == "uav-a"

        untrusted = {**env, "from": "evil"}
        await raw.publish(inbox, orjson.dumps(untrusted))
        rec = await audited(pb, "untrusted", verdict="dropped")
        assert rec["from"] == "evil"

        # a sealed envelope held back (here: a sender clock two minutes late) is too old
        pair.offset[0] = -120.0
        await asker.send(acl("asker@uav-a", "echo@uav-b", {"x": 2}))
        rec = await audited(pb, "expired", verdict="dropped")
        assert rec["from"] == "uav-a"
        pair.offset[0] = 0.0

        # revoking a platform in the trust file refuses its live session at once
        ia(pb).trust.remove("uav-a")
        await asker.send(acl("asker@uav-a", "echo@uav-b", {"x": 3}))
        await until(lambda: len(records(pb, verdict="dropped")) == 6, "the revoked sender")
        assert str(records(pb, verdict="dropped")[-1]["reason"]).startswith("untrusted:")

        untouched(echo, calls, received)
        # and the revocation itself, once: its sessions forgotten
        assert ia(pb).audit.counts == {"accepted": 1, "refused": 0, "dropped": 6, "revoked": 1}


async def test_garbage_on_the_inbox_is_dropped_and_the_inbox_keeps_working() -> None:
    """Bytes that are no envelope are dropped and audited; the inbox lives on."""
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pb, envelope = pair.pb, pair.envelope
        raw = await fed.raw()
        inbox = wire_key(FED, "acl", "uav-b")
        for payload in (b"", b"not json", b"[1, 2]", b'{"v": 1}', b"\xff" * 10, envelope[:-5]):
            await raw.publish(inbox, payload)
        await until(lambda: ia(pb).audit.counts["dropped"] == 6, "six dropped envelopes")
        assert all(
            str(r["reason"]).startswith("malformed:") for r in records(pb, verdict="dropped")
        )
        assert await request(pair.asker, "echo@uav-b", 5, ontology="demo") == {
            "echo": 5,
            "by": "echo@uav-b",
        }


async def test_key_exchanges_from_untrusted_or_forged_keys_are_dropped() -> None:
    """Key exchanges not signed by the trusted key make no session, on either side."""
    async with federation("uav-a", "uav-b", "uav-c") as fed:
        pb = await fed.start("uav-b")
        echo = await serve(pb, "echo")
        raw = await fed.raw()
        kx = wire_key(FED, "kx", "uav-b")

        # a platform missing from the trust file
        evil = KeyPair.generate("evil")
        evil_trust = TrustStore(
            FED, {"evil": evil.public_key, "uav-b": fed.keys["uav-b"].public_key}
        )
        replies = await raw.query(kx, Handshake(evil, evil_trust).initiate("uav-b"), timeout=1.0)
        assert not [r for r in replies if r.ok]
        rec = await audited(pb, "untrusted", verdict="dropped", stage="kx")
        assert rec["from"] == "evil"

        # a trusted name, signed with a key the trust file does not hold for it
        impostor = KeyPair.generate("uav-a")
        imp_trust = TrustStore(
            FED, {"uav-a": impostor.public_key, "uav-b": fed.keys["uav-b"].public_key}
        )
        replies = await raw.query(kx, Handshake(impostor, imp_trust).initiate("uav-b"), timeout=1.0)
        assert not [r for r in replies if r.ok]
        rec = await audited(pb, "forged", verdict="dropped", stage="kx")
        assert rec["from"] == "uav-a"
        assert ia(pb).sessions.peers() == []

        # the initiator's side: uav-c answered by an impostor holding another key
        pa = await fed.start("uav-a")
        fake_c = KeyPair.generate("uav-c")
        fake_trust = TrustStore(
            FED, {"uav-c": fake_c.public_key, "uav-a": fed.keys["uav-a"].public_key}
        )
        fake_hs = Handshake(fake_c, fake_trust)

        async def answer(key: str, payload: bytes) -> bytes | None:
            reply, _ = fake_hs.respond(payload)
            return reply

        await raw.serve(wire_key(FED, "kx", "uav-c"), answer)
        asker = await pa.add(Agent("asker"))
        with pytest.raises(SecurityError, match="key exchange with 'uav-c' refused"):
            await request(asker, "echo@uav-c", 1, ontology="demo", timeout=2)
        rec = await audited(pa, "forged", verdict="dropped", stage="kx")
        assert rec["from"] == "uav-c"
        assert ia(pa).sessions.peers() == []
        untouched(echo, 0, 0)


async def test_an_authenticated_platform_cannot_speak_for_another_ones_agents() -> None:
    """A platform's envelope cannot carry a message from another platform's agent."""
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb, echo = pair.pa, pair.pb, pair.echo
        raw = await fed.raw()
        calls, received = len(echo.calls), echo.stats.received
        for sender in ("spy@uav-c", "df@uav-b"):
            payload = ia(pa).sessions.seal("uav-b", acl(sender, "echo@uav-b", 9).to_json())
            await raw.publish(wire_key(FED, "acl", "uav-b"), payload)
            rec = await audited(pb, verdict="dropped", sender=sender)
            assert rec["from"] == "uav-a"
            assert "not an agent of 'uav-a'" in str(rec["reason"])
        untouched(echo, calls, received)
        assert pb.stats.forged == 0  # stopped by the Interface Agent, before the platform


async def test_a_message_for_no_agent_of_the_platform_is_not_accepted() -> None:
    """A message with no receiver here is dropped, not audited as accepted."""
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb = pair.pa, pair.pb
        payload = ia(pa).sessions.seal(
            "uav-b", acl("asker@uav-a", "x@uav-c", performative=Performative.INFORM).to_json()
        )
        raw = await fed.raw()
        await raw.publish(wire_key(FED, "acl", "uav-b"), payload)
        rec = await audited(pb, verdict="dropped", receivers=["x@uav-c"])
        assert "no receiver" in str(rec["reason"])


# -- access control ---------------------------------------------------------------------------


async def test_access_follows_service_visibility() -> None:
    """Outside askers reach public and protected services only; refusals are audited."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        asker = await serve(pa, "asker", None)
        private = await serve(pb, "private", "private")
        protected = await serve(pb, "protected", "protected")
        await serve(pb, "public", "public")
        bare = await serve(pb, "bare", None)

        with pytest.raises(Refused, match="access denied") as refused:
            await request(asker, "private@uav-b", 1, ontology="demo", timeout=2)
        assert refused.value.message is not None
        assert refused.value.message.sender == "private@uav-b"
        assert private.calls == []
        rec = await audited(pb, verdict="refused", receivers=["private@uav-b"])
        assert rec["performative"] == "request"
        assert rec["sender"] == "asker@uav-a"

        assert await request(asker, "protected@uav-b", 2, ontology="demo") == {
            "echo": 2,
            "by": "protected@uav-b",
        }
        assert await request(asker, "public@uav-b", 3, ontology="demo") == {
            "echo": 3,
            "by": "public@uav-b",
        }

        # an agent without a service gets replies (continuing acts), never requests
        with pytest.raises(Refused, match="access denied"):
            await request(asker, "bare@uav-b", 4, ontology="demo", timeout=2)
        assert bare.calls == []
        await asker.send(asker.message(Performative.INFORM, "bare@uav-b", 5, ontology="demo"))
        await until(lambda: bare.informs, "the inform to bare@uav-b")

        # replies may not be steered to local agents: that would reach the private one
        steered = asker.message(
            Performative.REQUEST,
            "protected@uav-b",
            6,
            ontology="demo",
            protocol="fipa-request",
            reply_to=["private@uav-b"],
        )
        answer = await asker.ask(steered, timeout=2)
        assert answer.performative is Performative.REFUSE
        assert "reply_to" in str(answer.content)
        assert len(protected.calls) == 1
        assert private.stats.received == 0

        # the DF answers searches from outside: what the asker may see, not the private one
        found = await search_services(asker, df="df@uav-b")
        assert sorted(s.name for s in found) == ["protected-svc", "public-svc"]

        assert ia(pb).audit.counts["refused"] == 3


async def test_a_platform_without_a_directory_admits_no_requests_from_outside() -> None:
    """No directory means no service offered: access control fails closed."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        stack = contextlib.AsyncExitStack()
        async with stack:
            tb = await stack.enter_async_context(fed.hub.transport())
            pb = await stack.enter_async_context(
                AgentPlatform(
                    "uav-b",
                    tb,
                    federation=FED,
                    directory=False,
                    channel=InterfaceAgent(fed.keys["uav-b"], fed.trust_copy()),
                )
            )
            echo = await pb.add(Echo("echo"))
            asker = await pa.add(Agent("asker"))
            with pytest.raises(Refused, match="access denied"):
                await request(asker, "echo@uav-b", 1, ontology="demo", timeout=2)
            assert echo.calls == []


async def test_malformed_acl_in_a_valid_envelope_is_answered_not_understood() -> None:
    """An authenticated sender of a bad message is told why; nobody else is."""
    async with federation("uav-a", "uav-b", "uav-c") as fed:
        pair = await _captured_session(fed)
        pa, pb, asker, echo = pair.pa, pair.pb, pair.asker, pair.echo
        pc = await fed.start("uav-c")
        listener = await pa.add(Listener("listener"))
        victim = await pc.add(Listener("victim"))
        echo_c = await serve(pc, "echo")
        raw = await fed.raw()
        bad = orjson.dumps(
            {
                "performative": "shout",
                "sender": "listener@uav-a",
                "receivers": ["echo@uav-b"],
                "conversation_id": "c-bad",
                "reply_with": "r-bad",
            }
        )
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", bad))
        async with asyncio.timeout(WAIT):
            await listener.got.wait()
        answer = listener.not_understood[0]
        assert answer.sender == "echo@uav-b"
        assert answer.conversation_id == "c-bad"
        assert answer.in_reply_to == "r-bad"
        assert "performative" in str(answer.content)
        rec = await audited(pb, verdict="refused", **{"from": "uav-a"})
        assert "performative" in str(rec["reason"])
        assert echo.calls[-1].content == {"x": 1}  # only the request of the setup

        # a malformed body naming a sender of another platform: nobody is told
        spoofed = bad.replace(b"listener@uav-a", b"victim@uav-c")
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", spoofed))
        rec = await audited(pb, verdict="dropped", sender="victim@uav-c")
        assert "not an agent of 'uav-a'" in str(rec["reason"])

        # a malformed failure is never answered (no not-understood to a not-understood or a
        # failure): audited dropped, since "refused" means its sender was told
        stray = orjson.dumps(
            {
                "performative": "failure",
                "sender": "listener@uav-a",
                "receivers": ["echo@uav-b"],
                "surprise": 1,
            }
        )
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", stray))
        rec = await audited(pb, verdict="dropped", sender="listener@uav-a")
        assert "surprise" in str(rec["reason"])
        assert ia(pb).audit.counts["refused"] == 1  # the shout above only
        # uav-b's inbox is in order, and so is uav-c's: round trips after it flush both
        assert await request(asker, "echo@uav-b", 1, ontology="demo")
        assert await request(echo, "echo@uav-c", 1, ontology="demo")
        assert echo_c.calls
        assert victim.not_understood == []
        assert len(listener.not_understood) == 1


@pytest.mark.parametrize("n", [1, 2, 3, 256])
def test_a_batch_body_is_the_array_of_its_messages(n: int) -> None:
    """_batch_body: one message alone as it is; two or more as b"[" + b",".join + b"]"."""
    from agents._interface import _batch_body

    bodies = [orjson.dumps({"i": i, "pad": "x" * (i % 7)}) for i in range(n)]
    expected = bodies[0] if n == 1 else b"[" + b",".join(bodies) + b"]"
    got = _batch_body(list(bodies))
    assert got == expected
    assert orjson.loads(got) == (
        orjson.loads(bodies[0]) if n == 1 else [orjson.loads(b) for b in bodies]
    )


async def test_a_burst_goes_in_batches_each_message_checked_and_audited() -> None:
    """Messages sent in one turn after the first share an envelope; each is admitted alone."""
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb, asker, echo = pair.pa, pair.pb, pair.asker, pair.echo
        raw = await fed.raw()
        wire = await raw.subscribe(wire_key(FED, "acl", "uav-b"))
        accepted = ia(pb).audit.counts["accepted"]
        for i in range(300):  # one turn: more than one batch holds (MAX_BATCH is 256)
            await asker.send(
                asker.message(Performative.INFORM, "echo@uav-b", {"i": i}, ontology="demo")
            )
        await until(lambda: len(echo.informs) == 300, "the 300 informs")
        assert [m.content for m in echo.informs] == [{"i": i} for i in range(300)]  # in order
        assert ia(pb).audit.counts["accepted"] == accepted + 300
        envelopes = [m.payload for m in wire.inbox.drain()]
        assert 3 <= len(envelopes) < 300  # the first alone, then batches of at most 256

        # large messages: a batch is closed before it outgrows what a receiver reads
        big = "x" * 100_000
        echo.informs.clear()
        for i in range(7):
            await asker.send(
                asker.message(Performative.INFORM, "echo@uav-b", [i, big], ontology="demo")
            )
        await until(lambda: len(echo.informs) == 7, "the 7 large informs")
        assert [m.content[0] for m in echo.informs] == list(range(7))

        # a batch sealed by a real session, with one bad message and one over the line:
        # the good ones arrive, the bad one is answered not-understood, the forged
        # sender is dropped; each has its own audit record
        listener = await pa.add(Listener("listener"))
        good = acl("listener@uav-a", "echo@uav-b", {"k": 1}, performative=Performative.INFORM)
        bad = {"performative": "shout", "sender": "listener@uav-a", "receivers": ["echo@uav-b"]}
        other = acl("victim@uav-c", "echo@uav-b", performative=Performative.INFORM)
        batch = b"[" + b",".join([good.to_json(), orjson.dumps(bad), other.to_json()]) + b"]"
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", batch))
        async with asyncio.timeout(WAIT):
            await listener.got.wait()
        await until(lambda: echo.informs[-1].content == {"k": 1}, "the good message")
        await audited(pb, verdict="refused", sender="listener@uav-a")
        rec = await audited(pb, verdict="dropped", sender="victim@uav-c")
        assert "not an agent of 'uav-a'" in str(rec["reason"])

        # a batch that is no array of messages is dropped whole, audited
        for body in (b"[]", b"[" + b",".join([good.to_json()] * 257) + b"]", b"[1,"):
            await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
        await until(
            lambda: len(records(pb, verdict="dropped", sender=None, **{"from": "uav-a"})) >= 3,
            "three malformed batches",
        )
        assert await request(asker, "echo@uav-b", 2, ontology="demo")


async def test_a_batch_of_one_header_is_still_checked_message_by_message() -> None:
    """Messages repeating one header: each taken as its own, an equal but invalid one refused.

    ``v`` as 1.0 or true equals 1 in JSON's numbers but is no wire version: those are
    answered not-understood and audited, the ones around them go in order, and each
    message taken holds its own fields (its own list of receivers).
    """
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb, echo = pair.pa, pair.pb, pair.echo
        raw = await fed.raw()
        listener = await pa.add(Listener("listener"))
        head = orjson.loads(
            acl(
                "listener@uav-a",
                "echo@uav-b",
                performative=Performative.INFORM,
                conversation_id=None,
            ).to_json()
        )
        head.pop("content", None)
        items: list[dict[str, Any]] = [{**head, "content": {"i": i}} for i in range(6)]
        items[2] = {**head, "v": 1.0, "content": {"i": "float"}}
        items[4] = {**head, "v": True, "content": {"i": "bool"}}
        items.append(head)  # the same header, no content
        accepted = ia(pb).audit.counts["accepted"]
        body = b"[" + b",".join(orjson.dumps(item) for item in items) + b"]"
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
        await until(lambda: len(listener.not_understood) == 2, "two not-understood")
        await until(lambda: len(echo.informs) == 5, "the 5 valid informs")
        assert [m.content for m in echo.informs] == [{"i": 0}, {"i": 1}, {"i": 3}, {"i": 5}, None]
        assert len({id(m.receivers) for m in echo.informs}) == 5
        assert all(m.receivers == ["echo@uav-b"] and m.v == 1 for m in echo.informs)
        assert ia(pb).audit.counts["accepted"] == accepted + 5
        refused = records(pb, verdict="refused", sender="listener@uav-a")
        assert [str(r["reason"]) for r in refused] == [
            "unsupported wire version 1.0 (this side speaks 1)",
            "unsupported wire version True (this side speaks 1)",
        ]


async def test_a_batch_of_one_header_gives_the_messages_a_full_parse_gives() -> None:
    """The messages taken as copies of the header before them are those a full parse makes.

    One header again and again (the path of a flood), with contents of every shape (a dict
    of scalars, a nested one, a list, a scalar, null, none at all): each message delivered
    equals, field by field, with the same fields set and the same JSON, what
    `ACLMessage.from_obj` makes of its item, and holds its own set of fields.
    """
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb, echo = pair.pa, pair.pb, pair.echo
        raw = await fed.raw()
        await pa.add(Listener("listener"))
        head = orjson.loads(
            acl(
                "listener@uav-a",
                "echo@uav-b",
                performative=Performative.INFORM,
                conversation_id="c-one",
            ).to_json()
        )
        head.pop("content", None)
        contents: list[Any] = [
            {"i": 0},
            {"i": 1, "nested": {"deep": [1, {"x": None}]}},
            [2, "two", 2.5, True, None],
            [{"i": 3}],
            "four",
            5,
            None,
            {"i": 7},
        ]
        items: list[dict[str, Any]] = [{**head, "content": c} for c in contents]
        items.insert(7, dict(head))  # no content at all
        items.append({**head, "content": {"i": 9}})
        accepted = ia(pb).audit.counts["accepted"]
        body = b"[" + b",".join(orjson.dumps(item) for item in items) + b"]"
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
        await until(lambda: len(echo.informs) == len(items), "every inform")
        for got, item in zip(echo.informs, items, strict=True):
            want = ACLMessage.from_obj(item)
            assert (got, got.model_fields_set, got.to_json()) == (
                want,
                want.model_fields_set,
                want.to_json(),
            )
        assert len({id(m.model_fields_set) for m in echo.informs}) == len(items)
        assert len({id(m.__dict__) for m in echo.informs}) == len(items)
        assert ia(pb).audit.counts["accepted"] == accepted + len(items)

        # a header without a content first, then the same with one, and without again
        echo.informs.clear()
        items = [dict(head), dict(head), {**head, "content": [1]}, dict(head)]
        body = b"[" + b",".join(orjson.dumps(item) for item in items) + b"]"
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
        await until(lambda: len(echo.informs) == len(items), "every inform")
        for got, item in zip(echo.informs, items, strict=True):
            want = ACLMessage.from_obj(item)
            assert (got, got.model_fields_set) == (want, want.model_fields_set)
        assert len({id(m.model_fields_set) for m in echo.informs}) == len(items)


async def test_each_message_of_a_batch_is_checked_for_depth_however_deep_the_batch() -> None:
    """A batch nesting deeper than any message may: the shallow ones taken, the deep one not.

    The batch holds more brackets than a message may nest levels (so no bound of the whole
    batch spares the check): each message's content is checked on its own.
    """
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb, echo = pair.pa, pair.pb, pair.echo
        raw = await fed.raw()
        listener = await pa.add(Listener("listener"))

        def inform(content: Any) -> bytes:
            return acl(
                "listener@uav-a", "echo@uav-b", content, performative=Performative.INFORM
            ).to_json()

        # deeper than pydantic takes (255 levels), in JSON made by hand (orjson makes none)
        deep = inform("DEEP").replace(b'"DEEP"', b"[" * 300 + b"1" + b"]" * 300)
        shallow = [inform({"i": i, "v": [i, {"w": i}]}) for i in range(60)]  # 4 brackets each
        body = b"[" + b",".join([*shallow[:30], deep, *shallow[30:]]) + b"]"
        assert body.count(b"[") + body.count(b"{") > 500
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
        async with asyncio.timeout(WAIT):
            await listener.got.wait()
        await until(lambda: len(echo.informs) == 60, "the 60 shallow informs")
        assert [m.content["i"] for m in echo.informs] == list(range(60))  # in order
        rec = await audited(pb, verdict="refused", sender="listener@uav-a")
        assert "depth" in str(rec["reason"])

        # a message that is itself too deep a list: dropped (nobody to tell); the rest go
        body = b"[" + b"[" * 300 + b"]" * 300 + b"," + shallow[0] + b"]"
        await raw.publish(wire_key(FED, "acl", "uav-b"), ia(pa).sessions.seal("uav-b", body))
        await until(lambda: len(echo.informs) == 61, "the inform after the deep list")
        await audited(pb, verdict="dropped", sender=None, **{"from": "uav-a"})
        assert await request(pair.asker, "echo@uav-b", 1, ontology="demo")


async def test_a_burst_that_goes_on_sends_one_envelope_a_turn() -> None:
    """After a turn that sent two or more, the next turn's first message joins its batch."""
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        asker, echo = pair.asker, pair.echo
        raw = await fed.raw()
        wire = await raw.subscribe(wire_key(FED, "acl", "uav-b"))
        echo.informs.clear()
        got = 0
        envelopes = []
        # turns of 5, 5, 1, 3, 3 messages: the first alone then a batch, then one batch
        # while the burst goes on, a turn of one ends it, and the next starts alone again
        for k in (5, 5, 1, 3, 3):
            for _ in range(k):
                await asker.send(
                    asker.message(Performative.INFORM, "echo@uav-b", {"i": got}, ontology="demo")
                )
                got += 1
            await until(lambda n=got: len(echo.informs) == n, f"{got} informs")
            envelopes.append(len(wire.inbox.drain()))
        assert envelopes == [2, 1, 1, 2, 1]
        assert [m.content["i"] for m in echo.informs] == list(range(got))  # in order


async def test_a_tight_loop_of_sends_goes_in_full_envelopes_in_order() -> None:
    """A sender looping on `send` lets the loop turn once per 256: envelopes of a full batch.

    1024 informs in a loop that never waits otherwise: at most a partial batch at each end
    and full ones of 256 between (a turn per 64 sent sixteen), each message delivered in
    order and audited on its own.
    """
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pb, asker, echo = pair.pb, pair.asker, pair.echo
        raw = await fed.raw()
        wire = await raw.subscribe(wire_key(FED, "acl", "uav-b"))
        echo.informs.clear()
        accepted = ia(pb).audit.counts["accepted"]
        loop = asyncio.get_running_loop()
        turns = 0

        def tick() -> None:  # counts the turns of the loop while the sender loops
            nonlocal turns
            turns += 1
            if not sending.done():
                loop.call_soon(tick)

        sending = loop.create_future()
        loop.call_soon(tick)
        n = 4 * 256
        for i in range(n):
            await asker.send(
                asker.message(Performative.INFORM, "echo@uav-b", {"i": i}, ontology="demo")
            )
        sending.set_result(None)
        assert 4 <= turns <= 5  # other tasks still run, once per 256 sent
        await until(lambda: len(echo.informs) == n, f"the {n} informs")
        assert [m.content for m in echo.informs] == [{"i": i} for i in range(n)]
        assert ia(pb).audit.counts["accepted"] == accepted + n
        envelopes = wire.inbox.drain()
        assert 4 <= len(envelopes) <= 6


async def _three_with_sessions(fed: Fed) -> tuple[AgentPlatform, Echo, Echo, Echo]:
    """uav-a with a session to uav-b and to uav-c, an echo on each."""
    pa = await fed.start("uav-a")
    asker = await serve(pa, "asker", None)
    echo_b = await serve(await fed.start("uav-b"), "echo")
    echo_c = await serve(await fed.start("uav-c"), "echo")
    for peer in ("uav-b", "uav-c"):
        assert await request(asker, f"echo@{peer}", 1, ontology="demo") is not None
    echo_b.informs.clear()
    echo_c.informs.clear()
    return pa, asker, echo_b, echo_c


async def test_a_batch_that_cannot_go_keeps_no_other_platform_s_batch(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """One platform's envelope failing at the end of the turn: logged, counted, the rest go."""
    async with federation("uav-a", "uav-b", "uav-c") as fed:
        pa, asker, echo_b, echo_c = await _three_with_sessions(fed)
        interface = ia(pa)
        transport = pa.transport
        publish_nowait = transport.publish_nowait
        refused = wire_key(FED, "acl", "uav-b")

        def failing(key: str, payload: bytes) -> None:
            if key == refused:
                raise TransportError("the link to uav-b is gone")
            publish_nowait(key, payload)

        transport.publish_nowait = failing  # type: ignore[method-assign]
        try:
            for i in range(4):  # uav-b first: its batch fails before uav-c's is sealed
                for peer in ("uav-b", "uav-c"):
                    await asker.send(
                        asker.message(
                            Performative.INFORM, f"echo@{peer}", {"i": i}, ontology="demo"
                        )
                    )
            await until(lambda: len(echo_c.informs) == 4, "uav-c's 4 informs")
        finally:
            transport.publish_nowait = publish_nowait  # type: ignore[method-assign]
        assert [m.content["i"] for m in echo_c.informs] == [0, 1, 2, 3]
        assert interface.batches_lost == 3  # uav-b's batch; its first went alone, at once
        assert "3 message(s) to uav-b not sent: the link to uav-b is gone" in caplog.text
        await until(lambda: len(echo_b.informs) == 1, "uav-b's first inform")
        assert echo_b.informs[0].content == {"i": 0}
        # the next turn to uav-b goes as ever (a burst: its one message waits for the
        # end of the turn, then goes alone)
        await asker.send(
            asker.message(Performative.INFORM, "echo@uav-b", {"i": 9}, ontology="demo")
        )
        await until(lambda: len(echo_b.informs) == 2, "uav-b's next inform")


async def test_a_message_that_is_no_json_is_refused_at_send_in_a_burst_too() -> None:
    """First of its turn or joining the batch: MessageError where it is sent; the rest go."""
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        asker, echo = pair.asker, pair.echo
        # (each round starts a turn of the loop: its first message goes alone, the
        # others join the batch)
        for position in (0, 1, 5):
            echo.informs.clear()
            for i in range(8):
                content = 2**70 if i == position else {"i": i}  # a Python int, not JSON
                message = asker.message(Performative.INFORM, "echo@uav-b", content, ontology="demo")
                if i == position:
                    with pytest.raises(MessageError, match="cannot be sent as JSON"):
                        await asker.send(message)
                else:
                    await asker.send(message)
            await until(lambda: len(echo.informs) == 7, "the 7 good informs")
            assert [m.content["i"] for m in echo.informs] == [i for i in range(8) if i != position]


async def test_batches_are_rate_limited_message_by_message() -> None:
    """A batch counts as its messages against the sender's limits."""
    from agents._interface import RateLimit

    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start(
            "uav-b", rate_limit=RateLimit(rate=1.0, burst=1.0, total_rate=5.0, total_burst=5.0)
        )
        asker = await serve(pa, "asker", None)
        echo = await serve(pb, "echo")
        await asker.send(asker.message(Performative.INFORM, "echo@uav-b", 0, ontology="demo"))
        for i in range(1, 20):
            await asker.send(asker.message(Performative.INFORM, "echo@uav-b", i, ontology="demo"))
        await until(lambda: pb.stats.rate_limited >= 15, "the limited informs")
        await asyncio.sleep(0.05)
        assert len(echo.informs) == 5  # the burst of the total bucket, one by one
        assert pb.stats.senders["uav-a"].accepted == 5


def test_no_batches_over_a_transport_that_must_await_its_puts() -> None:
    """A memory transport whose publish is overridden cannot publish from a loop callback."""

    class Slow(MemoryTransport):
        async def publish(self, key: str, payload: bytes, **kw: Any) -> None:
            await super().publish(key, payload, **kw)

    hub = MemoryHub()
    assert hub.transport().publishes_nowait
    assert not Slow(hub).publishes_nowait
    with pytest.raises(TransportError):
        Slow(hub).publish_nowait("a/b", b"x")


# -- sessions --------------------------------------------------------------------------------


async def test_concurrent_first_sends_share_one_key_exchange() -> None:
    """Many first sends to a peer wait for one key exchange."""
    async with federation("uav-a", "uav-b") as fed:
        ta = CountingTransport(fed.hub, delay=0.05)
        tb = CountingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta)
        pb = await fed.start("uav-b", transport=tb)
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        results = await asyncio.gather(
            *(request(asker, "echo@uav-b", i, ontology="demo") for i in range(20))
        )
        assert [r["echo"] for r in results] == list(range(20))  # type: ignore[index]
        assert ta.kx_queries == 1
        assert tb.kx_queries == 0  # uav-b answers on the session uav-a made
        assert len(ia(pa).sessions.sessions("uav-b")) == 1
        assert len(ia(pb).sessions.sessions("uav-a")) == 1


async def test_a_first_sight_during_the_key_exchange_loses_no_send() -> None:
    """A peer's token first seen between its session's agreement and the seal: sent anyway.

    The first sight doubts the peer's sessions (they may be a previous process's); the
    senders that waited for the exchange then find none to seal on, and agree one more.
    """
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        sessions = ia(pa).sessions
        add = sessions.add
        sights = 0

        def add_then_first_sight(session: Any) -> None:
            nonlocal sights
            add(session)
            if sights == 0:  # what `_watch` does on uav-b's token's first sight, in this turn
                sights += 1
                asyncio.get_running_loop().call_soon(sessions.doubt, "uav-b")

        sessions.add = add_then_first_sight  # type: ignore[method-assign]
        results = await asyncio.gather(
            *(request(asker, "echo@uav-b", i, ontology="demo") for i in range(3))
        )
        assert [r["echo"] for r in results] == list(range(3))  # type: ignore[index]
        assert sights == 1 and len(sessions.sessions("uav-b")) == 2


async def test_sessions_renew_while_messages_keep_flowing() -> None:
    """Renewing sessions loses no message."""
    async with federation("uav-a", "uav-b") as fed:
        policy = SecurityPolicy(renew_after_messages=5)
        ta, tb = CountingTransport(fed.hub), CountingTransport(fed.hub)
        pa = await fed.start("uav-a", transport=ta, policy=policy)
        pb = await fed.start("uav-b", transport=tb, policy=policy)
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        for i in range(30):
            assert await request(asker, "echo@uav-b", i, ontology="demo", timeout=2) == {
                "echo": i,
                "by": "echo@uav-b",
            }
        assert 2 <= ta.kx_queries + tb.kx_queries <= 2 * (30 // 5 + 1)
        for p in (pa, pb):
            assert ia(p).audit.counts == {"accepted": 30, "refused": 0, "dropped": 0}
            assert len(ia(p).sessions) <= policy.max_sessions_per_peer
            assert ia(p).missing() == {}  # renewed and dropped sessions lost nothing


class LossyAcl(MemoryTransport):
    """Loses the ACL envelopes to ``to`` numbered in ``lose`` (1, 2, …); holds those in ``hold``."""

    def __init__(self, hub: MemoryHub, to: str) -> None:
        super().__init__(hub)
        self.key = wire_key(FED, "acl", to)
        self.sent = 0
        self.lose: set[int] = set()
        self.hold: set[int] = set()
        self.held: list[bytes] = []

    async def publish(self, key: str, payload: bytes, **kw: Any) -> None:
        """Publish, but for what this link loses or holds back (to publish late)."""
        if key == self.key:
            self.sent += 1
            if self.sent in self.lose:
                return
            if self.sent in self.hold:
                self.held.append(payload)
                return
        await super().publish(key, payload, **kw)

    async def release(self) -> None:
        """Publish what was held back, after what followed it."""
        for payload in self.held:
            await super().publish(self.key, payload)
        self.held.clear()


async def test_envelopes_lost_on_the_way_are_counted_and_warned_of(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The receiver counts a peer's envelopes that never came; a late one is not counted."""
    async with federation("uav-a", "uav-b") as fed:
        link = LossyAcl(fed.hub, "uav-b")
        pa = await fed.start("uav-a", transport=link, batch=False)
        pb = await fed.start("uav-b", batch=False)
        asker = await serve(pa, "asker", None)
        echo = await serve(pb, "echo")
        local = await pb.add(Agent("ops"))
        await request(asker, "echo@uav-b", 0, ontology="demo")
        assert ia(pb).missing() == {}

        def inform(i: int) -> ACLMessage:
            return asker.message(Performative.INFORM, "echo@uav-b", i, ontology="demo")

        def warnings() -> list[str]:
            return [
                r.getMessage()
                for r in caplog.records
                if r.levelname == "WARNING" and "missing" in r.getMessage()
            ]

        caplog.set_level("WARNING", logger="agents")
        start = link.sent
        link.lose = {start + 2, start + 5, start + 6}  # 3 of the next 10 envelopes
        for i in range(10):
            await asker.send(inform(i))
        await until(lambda: len(echo.informs) == 7, "the 7 that came through")
        await until(lambda: ia(pb).missing() == {"uav-a": 3}, "3 missing")
        await until(warnings, "the warning")
        assert len(warnings()) == 1  # the first growth; then at most one a minute
        assert "from uav-a missing" in warnings()[0]
        seen = await query_ref(local, "interface@uav-b", {"senders": True}, ontology="interface")
        assert isinstance(seen, dict) and seen["senders"]["uav-a"]["missing"] == 3
        ia(pb).missing_warn_interval = 0.0
        await until(lambda: any("3 ACL envelope(s) from uav-a" in w for w in warnings()), "3")

        # out of order within the window: missing while late, not once it came
        link.hold = {link.sent + 1}
        for i in range(10, 13):
            await asker.send(inform(i))
        await until(lambda: len(echo.informs) == 9, "the 2 not held")
        assert ia(pb).missing() == {"uav-a": 4}
        await link.release()
        await until(lambda: len(echo.informs) == 10, "the late one")
        assert ia(pb).missing() == {"uav-a": 3}
        assert echo.informs[-1].content == 10


@pytest.mark.parametrize("binary_acl", [True, False])
async def test_encrypted_sessions_carry_no_readable_body(binary_acl: bool) -> None:
    """With encryption on, plain tools see headers but no body, in either envelope form."""
    async with federation("uav-a", "uav-b") as fed:
        policy = SecurityPolicy(encrypt=True, require_encryption=True)
        pa = await fed.start("uav-a", policy=policy, binary_acl=binary_acl)
        pb = await fed.start("uav-b", policy=policy, binary_acl=binary_acl)
        raw = await fed.raw()
        wire = await raw.subscribe(wire_key(FED, "acl", "*"))
        asker = await serve(pa, "asker", "protected")
        echo = await serve(pb, "echo")
        secret = {"secret": "do not print"}
        assert await request(asker, "echo@uav-b", secret, ontology="demo") == {
            "echo": secret,
            "by": "echo@uav-b",
        }
        assert await request(echo, "asker@uav-a", 1, ontology="demo") == {
            "echo": 1,
            "by": "asker@uav-a",
        }
        for _ in range(4):
            payload = (await wire.get(WAIT)).payload
            assert b"do not print" not in payload
            if binary_acl:  # [v, from, to, sid, ts_ms, n, box]: no body, no MAC
                env = msgpack.unpackb(payload)
                assert payload[0] == 0x97 and type(env[6]) is bytes
            else:
                env = orjson.loads(payload)
                assert "box" in env
                assert "body" not in env


async def test_a_cancelled_first_sender_does_not_fail_the_others() -> None:
    """Cancelling the sender that runs the key exchange does not fail the others."""
    async with federation("uav-a", "uav-b") as fed:
        ta = CountingTransport(fed.hub, delay=0.1)
        pa = await fed.start("uav-a", transport=ta)
        pb = await fed.start("uav-b")
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        first = asyncio.create_task(request(asker, "echo@uav-b", 1, ontology="demo"))
        await until(lambda: ta.kx_queries == 1, "the first key exchange")
        second = asyncio.create_task(request(asker, "echo@uav-b", 2, ontology="demo"))
        await asyncio.sleep(0.01)  # let the second sender join the exchange under way
        first.cancel()
        assert await second == {"echo": 2, "by": "echo@uav-b"}
        with pytest.raises(asyncio.CancelledError):
            await first


async def test_concurrent_sends_to_a_peer_that_is_not_running_all_fail_fast() -> None:
    """Sending to a platform that does not run fails at once, with a clear error."""
    async with federation("uav-a", "uav-b") as fed:
        ta = CountingTransport(fed.hub, delay=0.05)
        pa = await fed.start("uav-a", transport=ta, handshake_timeout=0.5)
        asker = await pa.add(Agent("asker"))
        started = time.monotonic()
        results = await asyncio.gather(
            *(request(asker, "echo@uav-b", i, ontology="demo") for i in range(5)),
            return_exceptions=True,
        )
        assert time.monotonic() - started < 2.0
        for r in results:
            assert isinstance(r, TransportError)
            assert "did not answer the key exchange" in str(r)
        assert ta.kx_queries == 1
        # a platform outside the trust file is refused before anything goes out
        with pytest.raises(SecurityError, match="not in the trust file"):
            await request(asker, "x@nowhere", 1, ontology="demo")
        assert ta.kx_queries == 1


async def test_a_restarted_platform_is_reachable_again() -> None:
    """A platform restarted under the same name and keys is reachable again."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        asker = await serve(pa, "asker", "protected")
        await serve(pb, "echo")
        assert await request(asker, "echo@uav-b", 1, ontology="demo")
        assert ia(pa).sessions.peers() == ["uav-b"]

        await fed.stop("uav-b")
        # its sessions doubted, not forgotten (a leave may be forged): none is sealed on
        await until(
            lambda: "uav-b" not in ia(pa)._alive and ia(pa).sessions.session_for("uav-b") is None,
            "uav-a seeing uav-b go",
        )

        pb = await fed.start("uav-b")  # same keys, same name, a new process
        echo = await serve(pb, "echo")
        async with asyncio.timeout(WAIT):
            assert await request(asker, "echo@uav-b", 2, ontology="demo") == {
                "echo": 2,
                "by": "echo@uav-b",
            }
            assert await request(echo, "asker@uav-a", 3, ontology="demo") == {
                "echo": 3,
                "by": "asker@uav-a",
            }


async def test_a_token_seen_after_the_key_exchange_leaves_its_session() -> None:
    """A peer's token that arrives after its first key exchange does not undo the session.

    The request sealed on that session is answered (zenoh on a loaded machine delivers a
    token that late; forgetting the session there lost the request).
    """
    async with federation("uav-a", "uav-b") as fed:
        pb = await fed.start("uav-b")
        await serve(pb, "echo")
        late = LateTokenTransport(fed.hub)
        pa = await fed.start("uav-a", transport=late)
        asker = await serve(pa, "asker", None)
        await ia(pa).agree("uav-b")  # the first request's key exchange
        await late.show()
        await until(lambda: "uav-a" in ia(pb)._alive, "uav-b seeing uav-a's token")
        assert ia(pb).sessions.peers() == ["uav-a"]
        answer = await request(asker, "echo@uav-b", 1, ontology="demo", timeout=WAIT)
        assert answer == {"echo": 1, "by": "echo@uav-b"}
        assert pb.stats.unauthenticated == pb.stats.rehandshakes == 0


async def _eventually(call: Callable[[], Any], what: str) -> Any:
    """Retry ``call`` (short timeouts) until it answers: messages flow again, in bounded time.

    A request of a platform that said, signed, that it left is refused until its signed
    snapshot lists it again: retried too.
    """
    async with asyncio.timeout(WAIT):
        while True:
            try:
                return await call()
            except ReplyTimeout:
                continue
            except Refused as exc:
                if "said, signed, that it left" not in str(exc):
                    raise
                await asyncio.sleep(0.05)


@pytest.mark.parametrize("direction", ["to-restarted", "from-restarted"])
async def test_a_restart_nobody_noticed_heals_itself(direction: str) -> None:
    """Lost liveliness events delay, but do not stop, messages after a restart."""
    async with federation("uav-a", "uav-b") as fed:
        # uav-a hears no liveliness changes: it keeps its sessions with the old uav-b, and
        # lists it again (after its signed leave) only when its recheck finds it answering
        pa = await fed.start("uav-a", transport=DeafTransport(fed.hub))
        assert pa.global_df is not None
        pa.global_df.recheck_interval = 0.5
        pb = await fed.start("uav-b")
        asker = await serve(pa, "asker", "protected")
        await serve(pb, "echo")
        assert await request(asker, "echo@uav-b", 1, ontology="demo")
        await fed.stop("uav-b")
        pb = await fed.start("uav-b")
        echo = await serve(pb, "echo")
        assert ia(pa).sessions.peers() == ["uav-b"]  # stale, and uav-a does not know

        if direction == "to-restarted":
            answer = await _eventually(
                lambda: request(asker, "echo@uav-b", 2, ontology="demo", timeout=0.3),
                "a request to the restarted platform",
            )
            assert answer == {"echo": 2, "by": "echo@uav-b"}
        else:
            answer = await _eventually(
                lambda: request(echo, "asker@uav-a", 3, ontology="demo", timeout=0.3),
                "a request from the restarted platform",
            )
            assert answer == {"echo": 3, "by": "asker@uav-a"}
        # and from then on both ways work (once the recheck listed uav-b again)
        assert await request(asker, "echo@uav-b", 4, ontology="demo", timeout=2)
        await _eventually(
            lambda: request(echo, "asker@uav-a", 5, ontology="demo", timeout=2), "listed again"
        )
        assert await request(echo, "asker@uav-a", 6, ontology="demo", timeout=2)


# -- configuration ---------------------------------------------------------------------------


async def test_keys_of_another_platform_or_another_federation_fail_at_start() -> None:
    """Mismatched keys or trust file fail at start, naming both sides."""
    async with federation("uav-a", "uav-b") as fed:
        t = await fed.raw()
        wrong_keys = InterfaceAgent(fed.keys["uav-b"], fed.trust_copy())
        with pytest.raises(SecurityError) as err:
            async with AgentPlatform("uav-a", t, federation=FED, channel=wrong_keys):
                pass
        assert "'uav-b'" in str(err.value)
        assert "'uav-a'" in str(err.value)

        other_fed = TrustStore("other", {"uav-a": fed.keys["uav-a"].public_key})
        wrong_trust = InterfaceAgent(fed.keys["uav-a"], other_fed)
        with pytest.raises(SecurityError) as err:
            async with AgentPlatform("uav-a", t, federation=FED, channel=wrong_trust):
                pass
        assert "'other'" in str(err.value)
        assert f"'{FED}'" in str(err.value)

        # the trust file holds another key for this platform: its peers would refuse it
        stale = TrustStore(FED, {"uav-a": KeyPair.generate("uav-a").public_key})
        with pytest.raises(SecurityError, match="another key"):
            async with AgentPlatform(
                "uav-a", t, federation=FED, channel=InterfaceAgent(fed.keys["uav-a"], stale)
            ):
                pass
        # nothing of the failed starts is left on the network
        assert fed.hub.queryables == []
        assert fed.hub.tokens == {}
        assert fed.hub.subscribers == []


async def test_local_agents_read_the_audit_and_remote_ones_cannot() -> None:
    """Local agents query the audit; other platforms are refused."""
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        for i in range(3):
            await request(asker, "echo@uav-b", i, ontology="demo")
        local = await pb.add(Agent("local"))

        answer = await query_ref(local, "interface@uav-b", {"audit": 2}, ontology="interface")
        assert isinstance(answer, dict)
        assert len(answer["audit"]) == 2
        assert answer["audit"] == list(ia(pb).audit.records)[-2:]
        assert answer["counts"] == {"accepted": 3, "refused": 0, "dropped": 0}
        before = dict(answer["counts"])
        await request(asker, "echo@uav-b", 9, ontology="demo")
        assert answer["counts"] == before  # a snapshot, not the live counters

        for n in (0, -3):
            nothing = await query_ref(local, "interface@uav-b", {"audit": n}, ontology="interface")
            assert isinstance(nothing, dict)
            assert nothing["audit"] == []
        peers = await query_ref(local, "interface@uav-b", {"sessions": True}, ontology="interface")
        assert peers == {"peers": ["uav-a"]}

        with pytest.raises(Refused):
            await query_ref(asker, "interface@uav-b", {"audit": 5}, ontology="interface")
        rec = await audited(pb, verdict="refused", receivers=["interface@uav-b"])
        assert rec["sender"] == "asker@uav-a"


async def test_the_audit_file_is_written_even_when_not_published(tmp_path: Path) -> None:
    """The audit file is written even when nothing is published."""
    async with federation("uav-a", "uav-b") as fed:
        path = tmp_path / "audit.jsonl"
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b", publish_audit=False, audit_path=path)
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-b"))
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        await request(asker, "echo@uav-b", 1, ontology="demo")
        await until(lambda: path.exists() and path.read_bytes().count(b"\n") == 1, "the file")
        (line,) = path.read_bytes().splitlines()
        assert orjson.loads(line)["sender"] == "asker@uav-a"
        assert len(feed.inbox) == 0
        assert len(ia(pb).audit._pending) == 0


class LaggingTransport(MemoryTransport):
    """A memory transport told of a new subscriber one question late, as zenoh's publisher is."""

    def __init__(self, hub: MemoryHub) -> None:
        super().__init__(hub)
        self._said = False

    def has_subscribers(self, key: str) -> bool:
        """What the hub said the last time it was asked."""
        now = super().has_subscribers(key)
        said, self._said = self._said, now
        return said


def _count_seals(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the Interface Agents' seals for the owner (audit and watch): a list of one count."""
    seals = [0]
    real = interface_module.seal_owner_batch

    def counting(keys: KeyPair, key: str, data: bytes, **kw: Any) -> bytes:
        seals[0] += 1
        return real(keys, key, data, **kw)

    monkeypatch.setattr("agents._interface_owner.seal_owner_batch", counting)
    return seals


def _opened(keys: KeyPair, msg: Message) -> bytes:
    """An audit batch published on ``msg.key``: opened with ``keys`` and its signature checked."""
    return OwnerBatches(keys, keys.public_key).open(msg.key, msg.payload)


async def _published_records(feed: Subscription[Message], keys: KeyPair) -> list[dict[str, Any]]:
    """The records of the next audit batch published on ``feed`` (sealed to ``keys``)."""
    msg = await feed.get(timeout=WAIT)
    return [orjson.loads(x) for x in _opened(keys, msg).splitlines()]


async def test_no_audit_batch_is_sealed_while_nobody_subscribes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Nobody subscribes to the audit: no seal, no put; a watcher then gets what comes next."""
    seals = _count_seals(monkeypatch)
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b")
        channel = ia(pb)
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        for i in range(3):
            await request(asker, "echo@uav-b", i, ontology="demo")
        await until(
            lambda: channel.audit_unheard and not channel._audit_held and channel._flush_idle,
            "the audit batches flushed unheard, the last one no longer held",
        )
        assert channel.audit.counts["accepted"] == 3  # the audit itself is kept
        assert (seals[0], channel.audit_published, ia(pa).audit_published) == (0, 0, 0)

        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-b"))
        await request(asker, "echo@uav-b", "watched", ontology="demo")
        (got,) = await _published_records(feed, channel.keys)
        assert (got["verdict"], got["sender"]) == ("accepted", "asker@uav-a")
        assert got == records(pb)[-1]
        assert (seals[0], channel.audit_published) == (1, 1)
        feed.close()
        channel.audit.record(verdict="dropped", stage="test", reason="nobody watches again")
        await until(lambda: channel.audit_unheard >= 2 and channel._flush_idle, "unheard again")
        assert (seals[0], channel.audit_published) == (1, 1)


async def test_a_watcher_the_transport_tells_of_late_loses_no_audit_batch() -> None:
    """The transport says "nobody" just after a watcher came: the batch goes out next flush."""
    async with federation("uav-a") as fed:
        pa = await fed.start("uav-a", transport=LaggingTransport(fed.hub))
        channel = ia(pa)
        await until(lambda: channel._flush_idle, "the audit flush asleep")
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-a"))
        channel.audit.record(verdict="dropped", stage="test", reason="made once watched")
        got = await _published_records(feed, channel.keys)
        assert [r["stage"] for r in got] == ["test"]
        assert (channel.audit_unheard, channel.audit_published) == (1, 1)


class SlowToTell(MemoryTransport):
    """A memory transport told of a new subscriber ``lag`` seconds late (several flushes)."""

    def __init__(self, hub: MemoryHub, lag: float) -> None:
        super().__init__(hub)
        self.lag = lag
        self._since: float | None = None

    def has_subscribers(self, key: str) -> bool:
        """What the hub says, once it has said so for ``lag`` seconds."""
        if not super().has_subscribers(key):
            self._since = None
            return False
        if self._since is None:
            self._since = time.monotonic()
        return time.monotonic() - self._since >= self.lag


async def test_a_watcher_told_of_up_to_the_audit_hold_late_gets_every_record() -> None:
    """Batches flushed while the transport lags a watcher (under `AUDIT_HOLD`) all reach it."""
    lag = interface_module.AUDIT_HOLD * 0.6  # more than one flush (0.25 s), less than the hold
    async with federation("uav-a") as fed:
        pa = await fed.start("uav-a", transport=SlowToTell(fed.hub, lag))
        channel = ia(pa)
        await until(lambda: channel._flush_idle, "the audit flush asleep")
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-a"))
        for n in range(3):  # one record per flush while the transport still says "nobody"
            channel.audit.record(verdict="dropped", stage="test", reason=f"made once watched {n}")
            await asyncio.sleep(channel.audit_interval)
        got = []
        while len(got) < 3:
            got += await _published_records(feed, channel.keys)
        assert [r["reason"] for r in got] == [f"made once watched {n}" for n in range(3)]
        assert channel.audit_unheard >= 2


# -- over zenoh --------------------------------------------------------------------------------


def unique_federation(kind: str) -> str:
    """A federation name of this test alone: over a network two runs must not meet."""
    return f"{kind}-{os.urandom(6).hex()}"


async def _sees(t: Transport, fed: str, platform: str) -> None:
    """Wait until ``t`` sees ``platform``'s liveliness token (declared once it serves)."""
    watch = await t.watch_presence(wire_key(fed, "alive", platform))
    try:
        async with asyncio.timeout(WAIT):
            while not (await watch.get()).alive:
                pass
    finally:
        watch.close()


async def test_request_inform_over_zenoh_between_two_sessions() -> None:
    """The same round trips over zenoh, between two sessions on loopback."""
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b", "uav-c")}
    trust = {n: k.public_key for n, k in keys.items()}
    fed = unique_federation("zenoh")
    seed = free_tcp_port()
    ta = ZenohTransport(ZenohConfig.loopback(seed))
    tb = ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed]))
    async with asyncio.timeout(WAIT * 2), ta, tb:
        feed = await ta.subscribe(wire_key(fed, "audit", "uav-b"))
        ia_a = InterfaceAgent(
            keys["uav-a"], TrustStore(fed, trust), audit_interval=0.02, handshake_timeout=0.5
        )
        ia_b = InterfaceAgent(keys["uav-b"], TrustStore(fed, trust), audit_interval=0.02)
        async with (
            AgentPlatform("uav-a", ta, federation=fed, channel=ia_a) as pa,
            AgentPlatform("uav-b", tb, federation=fed, channel=ia_b) as pb,
        ):
            await _sees(ta, fed, "uav-b")
            await _sees(tb, fed, "uav-a")
            echo_a = await serve(pa, "echo")
            echo_b = await serve(pb, "echo")
            assert await request(echo_a, "echo@uav-b", {"z": 1}, ontology="demo") == {
                "echo": {"z": 1},
                "by": "echo@uav-b",
            }
            assert await request(echo_b, "echo@uav-a", {"z": 2}, ontology="demo") == {
                "echo": {"z": 2},
                "by": "echo@uav-a",
            }
            assert ia_b.audit.counts == {"accepted": 2, "refused": 0, "dropped": 0}
            async with asyncio.timeout(WAIT):
                while True:
                    msg: Message = await feed.get()
                    opened = _opened(keys["uav-b"], msg)
                    lines = [orjson.loads(x) for x in opened.splitlines()]
                    if any(r["performative"] == "request" for r in lines):
                        break
            # a trusted platform that is not running: a clear error in bounded time
            started = time.monotonic()
            with pytest.raises(TransportError, match="did not answer the key exchange"):
                await request(echo_a, "echo@uav-c", 1, ontology="demo")
            assert time.monotonic() - started < 3.0


async def test_a_retry_loop_against_a_platform_gone_lets_the_other_tasks_run() -> None:
    """A request to a platform that has gone fails at once (zenoh ends the key exchange's
    query nobody serves inside its call), yet only after it suspended: a caller retrying
    it in a loop without a pause lets another task of its loop go on between tries."""
    fed = f"gone-{os.urandom(6).hex()}"
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    trust = {n: k.public_key for n, k in keys.items()}
    seed = free_tcp_port()
    ta = ZenohTransport(ZenohConfig.loopback(seed))
    tb = ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed]))
    ia_a = InterfaceAgent(keys["uav-a"], TrustStore(fed, trust))
    ia_b = InterfaceAgent(keys["uav-b"], TrustStore(fed, trust))
    async with (
        asyncio.timeout(WAIT * 2),
        ta,
        AgentPlatform("uav-a", ta, federation=fed, channel=ia_a) as pa,
    ):
        asker = await pa.add(Agent("asker"))
        async with tb, AgentPlatform("uav-b", tb, federation=fed, channel=ia_b) as pb:
            await serve(pb, "echo")
            answer = await request(asker, "echo@uav-b", 1, ontology="demo")
            assert answer == {"echo": 1, "by": "echo@uav-b"}
        await until(lambda: ia_a.sessions.session_for("uav-b") is None, "uav-b gone")
        ticks = 0

        async def other() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                await asyncio.sleep(0)

        ticking = asyncio.create_task(other())
        await asyncio.sleep(0)  # it runs once before the tries start
        per_try: list[int] = []
        try:
            for i in range(20):  # no pause between tries: what the caller forgot
                before = ticks
                with pytest.raises(TransportError, match="did not answer the key exchange"):
                    await request(asker, "echo@uav-b", i, ontology="demo", timeout=WAIT)
                per_try.append(ticks - before)
        finally:
            ticking.cancel()
        assert min(per_try) >= 1, per_try


async def test_over_zenoh_the_audit_is_sealed_only_while_someone_subscribes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """zenoh's matching status: no seal while nobody subscribes; a watcher gets what follows."""
    seals = _count_seals(monkeypatch)
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    trust = {n: k.public_key for n, k in keys.items()}
    fed = unique_federation("zenoh")
    seed = free_tcp_port()
    ta = ZenohTransport(ZenohConfig.loopback(seed))
    tb = ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed]))
    async with asyncio.timeout(WAIT * 2), ta, tb:
        ia_a = InterfaceAgent(keys["uav-a"], TrustStore(fed, trust), audit_interval=0.02)
        ia_b = InterfaceAgent(keys["uav-b"], TrustStore(fed, trust), audit_interval=0.02)
        async with (
            AgentPlatform("uav-a", ta, federation=fed, channel=ia_a) as pa,
            AgentPlatform("uav-b", tb, federation=fed, channel=ia_b) as pb,
        ):
            await _sees(ta, fed, "uav-b")
            echo_a = await serve(pa, "echo")
            await serve(pb, "echo")
            await request(echo_a, "echo@uav-b", 1, ontology="demo")
            await until(lambda: ia_b.audit_unheard and ia_b._flush_idle, "an unheard batch")
            assert (seals[0], ia_b.audit_published) == (0, 0)

            feed = await ta.subscribe(wire_key(fed, "audit", "uav-b"))
            await until(lambda: tb.has_subscribers(wire_key(fed, "audit", "uav-b")), "matched")
            await request(echo_a, "echo@uav-b", 2, ontology="demo")
            got = await _published_records(feed, keys["uav-b"])
            assert [(r["verdict"], r["sender"]) for r in got] == [("accepted", "echo@uav-a")]
            assert ia_b.audit_published == 1 and seals[0] == 1


# -- over MQTT ---------------------------------------------------------------------------------


class HeldKx(MqttTransport):
    """An MQTT transport whose key-exchange answers wait until ``release`` is set."""

    def __init__(self, config: MqttConfig) -> None:
        super().__init__(config)
        self.release = asyncio.Event()
        self.release.set()

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Serve as MqttTransport does; a key exchange is answered once released."""
        if "/kx/" not in key_expr:
            return await super().serve(key_expr, handler, admit=admit)

        async def held(key: str, payload: bytes) -> bytes | None:
            async with asyncio.timeout(WAIT):
                await self.release.wait()
            return await handler(key, payload)

        return await super().serve(key_expr, held, admit=admit)


@contextlib.asynccontextmanager
async def mqtt_pair(
    host: str, port: int, fed: str, keys: dict[str, KeyPair], handshake_timeout: float
) -> AsyncIterator[tuple[AgentPlatform, AgentPlatform, HeldKx]]:
    """uav-a and uav-b of ``fed`` on one broker, each seeing the other; uav-b's a HeldKx."""
    trust = {n: k.public_key for n, k in keys.items()}
    ta = MqttTransport(MqttConfig(host=host, port=port, client_id="uav-a"))
    tb = HeldKx(MqttConfig(host=host, port=port, client_id="uav-b"))
    async with ta, tb:
        ia_a = InterfaceAgent(
            keys["uav-a"],
            TrustStore(fed, trust),
            audit_interval=0.02,
            handshake_timeout=handshake_timeout,
        )
        ia_b = InterfaceAgent(keys["uav-b"], TrustStore(fed, trust), audit_interval=0.02)
        async with (
            AgentPlatform("uav-a", ta, federation=fed, channel=ia_a) as pa,
            AgentPlatform("uav-b", tb, federation=fed, channel=ia_b) as pb,
        ):
            await _sees(ta, fed, "uav-b")
            await _sees(tb, fed, "uav-a")
            yield pa, pb, tb


# Long enough that a first request waiting for the whole key-exchange query, as MQTT's
# query does, is far over the bound these tests set (half of it), on any machine.
MQTT_KX_TIMEOUT = 8.0  # s: half of it bounds a first request on a loaded machine


async def test_a_first_request_over_mqtt_does_not_wait_for_the_kx_timeout(
    mosquitto: tuple[str, int],
) -> None:
    """The key exchange ends at its first authenticated reply, not at the query's timeout."""
    host, port = mosquitto
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    fed = unique_federation("mqtt")
    async with (
        asyncio.timeout(WAIT * 3),
        mqtt_pair(host, port, fed, keys, MQTT_KX_TIMEOUT) as (pa, pb, _),
    ):
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        started = time.monotonic()
        answer = await request(asker, "echo@uav-b", 1, ontology="demo", timeout=WAIT * 2)
        took = time.monotonic() - started
        assert answer == {"echo": 1, "by": "echo@uav-b"}
        assert took < MQTT_KX_TIMEOUT / 2, f"the first request took {took:.2f} s"
        assert len(ia(pa).sessions.sessions("uav-b")) == 1
        assert ia(pa).audit.counts["dropped"] == 0


async def test_forged_mqtt_kx_replies_first_do_not_hide_the_real_one(
    mosquitto: tuple[str, int],
) -> None:
    """Junk and a forged reply, answered before the peer, are refused and audited; the real
    reply still ends the exchange at once."""
    host, port = mosquitto
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    fed = unique_federation("mqtt")
    fake_b = KeyPair.generate("uav-b")  # uav-b's name, another key
    fake_hs = Handshake(
        fake_b, TrustStore(fed, {"uav-b": fake_b.public_key, "uav-a": keys["uav-a"].public_key})
    )
    answered: list[bytes] = []

    def answer(client: paho.Client, userdata: Any, m: paho.MQTTMessage) -> None:
        # what anyone may do: read the query off the broker, answer on its response topic
        props = Properties(PacketTypes.PUBLISH)
        props.CorrelationData = m.properties.CorrelationData
        forged, _ = fake_hs.respond(m.payload)
        for junk in (b"not a key exchange", forged):
            client.publish(m.properties.ResponseTopic, junk, properties=props)
        answered.append(m.payload)

    attacker = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
    attacker.on_message = answer
    subscribed = threading.Event()
    attacker.on_subscribe = lambda *_: subscribed.set()
    attacker.connect(host, port)
    attacker.subscribe(f"@query/{wire_key(fed, 'kx', 'uav-b')}")
    attacker.loop_start()
    try:
        # the attacker listens before the query is asked (else it never answers first)
        assert await asyncio.to_thread(subscribed.wait, WAIT), "the attacker's subscription"
        async with (
            asyncio.timeout(WAIT * 3),
            mqtt_pair(host, port, fed, keys, MQTT_KX_TIMEOUT) as (pa, pb, tb),
        ):
            asker = await serve(pa, "asker", None)
            await serve(pb, "echo")
            # uav-b answers only once uav-a refused both: the forgeries come first
            tb.release.clear()
            started = time.monotonic()
            asking = asyncio.create_task(
                request(asker, "echo@uav-b", 1, ontology="demo", timeout=WAIT * 2)
            )
            await until(lambda: ia(pa).audit.counts["dropped"] >= 2, "the forgeries refused")
            tb.release.set()
            assert await asking == {"echo": 1, "by": "echo@uav-b"}
            took = time.monotonic() - started
            assert took < MQTT_KX_TIMEOUT / 2, f"the first request took {took:.2f} s"
            assert len(answered) == 1
            refused = records(pa, verdict="dropped", stage="kx")
            assert [str(r["reason"]).split(":")[0] for r in refused] == ["malformed", "forged"]
            assert all(r["from"] == "uav-b" for r in refused)
            assert ia(pa).audit.counts["dropped"] == 2
            assert len(ia(pa).sessions.sessions("uav-b")) == 1
    finally:
        attacker.loop_stop()
        attacker.disconnect()


def test_audit_lines_of_long_names_are_written_not_kept() -> None:
    """A line made of names another platform made up, a message long, is not kept."""
    audit = AuditLog(platform="uav-b")
    for i in range(20):
        sender = f"{i}" + "x" * 200_000 + "@uav-a"
        message = ACLMessage.build(
            performative=Performative.INFORM, sender=sender, receivers=["b@uav-b"]
        )
        audit.accepted("uav-a", message, 1.5)
    audit.accepted(
        "uav-a",
        ACLMessage.build(performative="inform", sender="a@uav-a", receivers=["b@uav-b"]),
        1.5,
    )
    lines = audit.take().splitlines()
    assert lines == [orjson.dumps(r) for r in audit.records]
    assert sum(len(middle) for middle in audit._lines.values()) < 1024


def test_the_flush_a_record_wakes_finds_it_pending() -> None:
    """Each record's wake comes once it is pending: a flush woken on another thread finds it."""
    audit = AuditLog(platform="uav-b")
    found: list[int] = []
    # the flush, run the moment it is woken (as one on another thread may be)
    audit.wake = lambda: found.append(len(audit.take().splitlines()))
    message = ACLMessage.build(performative="inform", sender="a@uav-a", receivers=["b@uav-b"])
    audit.record(verdict="dropped", reason="one")
    audit.accepted("uav-a", message)
    audit.add_accepted([accepted_entry(1.5, "uav-a", message)] * 2)
    assert found == [1, 1, 2]
    assert audit.counts == {"accepted": 3, "refused": 0, "dropped": 1}
    assert audit.take() == b""


def test_audit_lines_of_accepted_messages_are_the_records_as_json() -> None:
    """The lines pieced together for accepted messages are orjson's bytes of the records."""
    audit = AuditLog(platform="uav-b")
    messages = [
        ACLMessage.build(
            performative=Performative.INFORM, sender="a@uav-a", receivers=["b@uav-b"], content=1
        ),
        ACLMessage.build(
            performative=Performative.REQUEST,
            sender="a@uav-a",
            receivers=["b@uav-b"],
            conversation_id='c-"ö\\\u2028',
        ),
        ACLMessage.build(
            performative=Performative.INFORM, sender="a@uav-a", receivers=["b@uav-b", "c@uav-b"]
        ),
    ]
    for ts in (1795000000.125, 1795000000.125, 0.1 + 0.2, 1e-7, 0.0):
        for message in messages:
            for _ in range(2):  # a record again: its line again
                audit.accepted("uav-a", message, ts)
    audit.record(verdict="dropped", reason="something else")
    lines = audit.take().splitlines()
    assert lines == [orjson.dumps(r) for r in audit.records]
    assert audit.counts["accepted"] == 30 and len(lines) == 31
    assert audit.last(1)[0]["verdict"] == "dropped"


# -- InterfaceAgent: a batch's messages decided as each alone -------------------------------


async def _decisions(batched: bool, runs: bool = False) -> dict[str, Any]:
    """What uav-b decides about one hostile mix of messages from uav-a, batched or one by one.

    With ``runs``: runs of messages for two agents from two senders, interleaved, with a
    forged sender or receiver in the middle of a run (the batch path caches both).
    """
    async with federation("uav-a", "uav-b") as fed:
        limit = RateLimit(rate=1e-3, burst=4.0, total_rate=1e-3, total_burst=14.0, refusals=1e-3)
        pair = await _captured_session(fed)
        pa, pb = pair.pa, pair.pb
        # a fresh sender state with these limits (the captured request used the default one)
        ib = ia(pb)
        ib.rate_limit = limit
        ib._senders.clear()
        await pa.add(Listener("l"))
        await serve(pb, "private", None)
        stopped = await serve(pb, "stopped")
        await stopped.stop()
        echo = pair.echo
        echo.calls.clear()
        echo.informs.clear()
        inform, req = P.INFORM, P.REQUEST
        items: list[Any] = [
            _m("l@uav-a", "echo@uav-b", inform, {"i": 1}),
            _m("l@uav-a", "echo@uav-b", req, {"i": 2}),
            _m("l@uav-a", "private@uav-b", req, {"i": 3}),  # no service: refused
            _m("victim@uav-c", "echo@uav-b", inform, {"i": 4}),  # forged sender
            _m("l@uav-a", "echo@uav-b", req, {"i": 5}, reply_to=["x@uav-c"]),  # reflection
            _m("l@uav-a", "echo@uav-b", inform, {"i": 6}, reply_to=["echo@uav-b"]),
            _m("l@uav-a", "ghost@uav-b", inform, {"i": 7}),  # no such agent
            _m("l@uav-a", "stopped@uav-b", inform, {"i": 8}),  # stopped
            {"performative": "shout", "sender": "l@uav-a", "receivers": ["echo@uav-b"]},
            _m("l@uav-a", "echo@uav-c", inform, {"i": 10}),  # for another platform
            _m("l@uav-a", "echo@uav-b", req, {"i": 11}),
            _m("l@uav-a", "echo@uav-b", req, {"i": 12}),  # over the request limit
            _m("l@uav-b", "echo@uav-b", inform, {"i": 13}),  # claims the receiver's platform
        ]
        items += [_m("l@uav-a", "echo@uav-b", inform, {"i": i}) for i in range(14, 24)]
        other = None
        if runs:
            ib.rate_limit = RateLimit(rate=1e-3, burst=6.0, total_rate=1e-3, total_burst=40.0)
            other = await serve(pb, "echo2")
            items = [
                _m("l@uav-a", "echo@uav-b", inform, {"i": 1}),
                _m("m@uav-a", "echo2@uav-b", inform, {"i": 2}),
                _m("l@uav-a", "echo@uav-b", inform, {"i": 3}),
                _m("l@uav-a", "echo@uav-b", req, {"i": 4}),
                _m("victim@uav-c", "echo@uav-b", inform, {"i": 5}),  # forged, mid-run
                _m("l@uav-a", "echo@uav-b", inform, {"i": 6}),
                _m("l@uav-a", "echo2@uav-b", req, {"i": 7}),
                _m("l@uav-a", "private@uav-b", req, {"i": 8}),  # no service, mid-run
                _m("l@uav-a", "echo2@uav-b", req, {"i": 9}),
                _m("m@uav-a", "echo@uav-b", inform, {"i": 10}),
                _m("m@uav-a", "echo@uav-b", inform, {"i": 11}, reply_to=["m@uav-a"]),
                _m("m@uav-a", "ghost@uav-b", inform, {"i": 12}),  # no such agent, mid-run
                _m("m@uav-a", "echo@uav-b", inform, {"i": 13}),
                _m("m@uav-a", "echo@uav-c", inform, {"i": 14}),  # another platform, mid-run
                _m("m@uav-a", "echo2@uav-b", inform, {"i": 15}),
                _m("l@uav-b", "echo2@uav-b", inform, {"i": 16}),  # claims uav-b, mid-run
                _m("l@uav-a", "echo2@uav-b", inform, {"i": 17}),
                _m("l@uav-a", "echo@uav-b", req, {"i": 18}),
                _m("l@uav-a", "echo@uav-b", req, {"i": 19}),
                _m("l@uav-a", "echo2@uav-b", req, {"i": 20}),  # over the request limit
                _m("m@uav-a", "echo2@uav-b", inform, {"i": 21}),
            ]
        bodies = [orjson.dumps(i) if isinstance(i, dict) else i.to_json() for i in items]
        key = wire_key(FED, "acl", "uav-b")
        raw = await fed.raw()
        seal = ia(pa).sessions.seal
        before = len(ib.audit.last(10_000))
        if batched:
            await raw.publish(key, seal("uav-b", b"[" + b",".join(bodies) + b"]"))
        else:
            for body in bodies:
                await raw.publish(key, seal("uav-b", body))
        sender = pb.stats.senders["uav-a"]
        await until(
            lambda: sender.accepted + sender.limited >= len(items) - 1, "every message decided"
        )
        # settled: the accepted delivered; uav-a's answers to the refusals and
        # not-understoods that went out taken (over the limit without runs); every record
        # written, the last summed up a second on (the answers limited, or, with runs, those
        # in no conversation)
        delivered = [echo.informs, echo.calls]
        if other is not None:
            delivered += [other.informs, other.calls]
        due = ([6, 3, 4, 2], 28, 1, 30) if runs else ([2, 2], 13, 15, 16)

        def now() -> tuple[list[int], int, int, int]:
            audited = len(ib.audit.last(10_000)) - before
            return [len(d) for d in delivered], sender.accepted, sender.limited, audited

        await until(lambda: now() == due, f"deliveries, accepted, limited, records {due}")
        records = [
            {k: v for k, v in r.items() if k != "ts"} for r in ib.audit.last(10_000)[before:]
        ]
        stats = pb.stats
        return {
            "records": records,
            "informs": [m.content for m in echo.informs],
            "informs2": None if other is None else [m.content for m in other.informs],
            "calls2": None if other is None else [m.content for m in other.calls],
            "calls": [m.content for m in echo.calls],
            "accepted": sender.accepted,
            "limited": sender.limited,
            "refused": sender.refused,
            "counts": dict(ib.audit.counts),
            "platform": (
                stats.received_remote,
                stats.local,
                stats.forged,
                stats.unknown_receiver,
                stats.rate_limited,
            ),
        }


def _m(sender: str, receiver: str, performative: P, content: Any, **fields: Any) -> ACLMessage:
    return ACLMessage.build(
        performative=performative,
        sender=sender,
        receivers=[receiver],
        content=content,
        ontology="demo",
        protocol="fipa-request",
        conversation_id=f"c-{content}",
        reply_with=f"r-{content}",
        **fields,
    )


async def test_a_hostile_batch_is_decided_as_its_messages_one_by_one() -> None:
    """Limits, sender binding, reply_to, access, unknown agents, audit: batch == one by one."""
    alone = await _decisions(batched=False)
    together = await _decisions(batched=True)
    assert together == alone
    assert alone["limited"] >= 2  # both limits reached


async def test_interleaved_runs_of_a_hostile_batch_are_decided_as_one_by_one() -> None:
    """Two receivers, two senders, a bad one mid-run: batch == one by one, order kept."""
    alone = await _decisions(batched=False, runs=True)
    together = await _decisions(batched=True, runs=True)
    assert together == alone
    assert alone["informs"] == [{"i": 1}, {"i": 3}, {"i": 6}, {"i": 10}, {"i": 11}, {"i": 13}]
    assert alone["informs2"] == [{"i": 2}, {"i": 15}, {"i": 17}, {"i": 21}]
    assert alone["limited"] == 1


# -- InterfaceAgent: a lone message's quick parse decides as the full one ------------------


def _deep(levels: int) -> bytes:
    return b"[" * levels + b"1" + b"]" * levels


def _hostile_bodies() -> list[bytes]:
    """Bodies that open (sealed by uav-a) but are no message `_take_now` may take."""
    ok = (
        b'{"performative":"inform","sender":"l@uav-a","receivers":["echo@uav-b"],'
        b'"conversation_id":"c","content":%b}'
    )
    return [
        ok % b"1",  # a good one, for reference
        ok % _deep(198),
        ok % _deep(199),
        ok % _deep(200),
        ok % _deep(260),  # deeper than pydantic takes
        ok % _deep(1100),  # deeper than orjson reads
        b"[1,2,3]",
        b"42",
        b'"inform"',
        b"null",
        ok % b"1" + b" trailing",
        ok % b"1" * 2,
        ok % b"123456789012345678901234567890",  # bigger than 64 bits
        ok % b"1e400",
        ok.replace(b'"sender":"l@uav-a"', b'"sender":"l@uav-a","sender":"x@uav-c"') % b"2",
        ok.replace(b'"sender":"l@uav-a"', b'"sender":"x@uav-c","sender":"l@uav-a"') % b"3",
        ok.replace(b'"l@uav-a"', b"7") % b"4",
        ok.replace(b'["echo@uav-b"]', b'"echo@uav-b"') % b"5",
        ok.replace(b'"l@uav-a"', b'"l@uav-a\\n"') % b"6",
        ok.replace(b'["echo@uav-b"]', b'["echo@uav-b\\n"]') % b"7",
        ok.replace(b'"inform"', b'"INFORM"') % b"8",
        ok.replace(b'"conversation_id":"c"', b'"conversation_id":7') % b"9",
        ok.replace(b'"conversation_id":"c"', b'"v":2') % b"10",
        ok.replace(b'"conversation_id":"c"', b'"v":true') % b"11",
        ok.replace(b'"conversation_id":"c"', b'"extra":1') % b"12",
        ok.replace(b'"conversation_id":"c"', b'"reply_by":"soon"') % b"13",
        ok % b'"\\ud800"',
        ok.replace(b'"l@uav-a"', b'"l@uav-b"') % b"14",  # claims the receiver's platform
        ok.replace(b'"inform"', b'"request"') % b"15",
        ok.replace(b'"conversation_id":"c"', b'"reply_to":["x@uav-c"]') % b"16",
        ok.replace(b'"echo@uav-b"', b'"ghost@uav-b"') % b"17",
        ok % b"2",  # a good one at the end: everything before it was decided
    ]


async def _lone_decisions(
    quick: bool, batchable: bool = False, batched: bool = False
) -> dict[str, Any]:
    """What uav-b decides about the hostile bodies, each alone; ``quick`` False: in full.

    ``batchable``: only those a batch can hold (JSON within orjson's depth, no batch);
    ``batched``: those, in one batch.
    """
    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb = pair.pa, pair.pb
        ib = ia(pb)
        ib._senders.clear()
        if not quick:
            # `_take_now` takes nothing while mirroring: every message goes through `_take`
            ib.mirroring = True
            ib._mirror_until = float("inf")
        key = wire_key(FED, "acl", "uav-b")
        raw = await fed.raw()
        seal = ia(pa).sessions.seal
        before = len(ib.audit.last(10_000))
        bodies = _hostile_bodies()
        if batchable or batched:
            bodies = [b for b in bodies if _batchable(b)]
        if batched:
            await raw.publish(key, seal("uav-b", b"[" + b",".join(bodies) + b"]"))
        else:
            for body in bodies:
                await raw.publish(key, seal("uav-b", body))
        # one record each, three for the batch of three numbers
        want = len(bodies) + (0 if batchable or batched else 2)
        # and the platform's tally of what its agents dropped: the unknown receiver and the
        # first not-understoods at once, the last one summed up a second on
        await until(lambda: len(ib.audit.last(10_000)) - before == want + 3, "every one decided")
        records = [
            {k: v for k, v in r.items() if k != "ts"} for r in ib.audit.last(10_000)[before:]
        ]
        sender = pb.stats.senders["uav-a"]
        stats = pb.stats
        return {
            "records": records,
            "accepted": sender.accepted,
            "refused": sender.refused,
            "counts": dict(ib.audit.counts),
            "platform": (
                stats.received_remote,
                stats.local,
                stats.forged,
                stats.unknown_receiver,
            ),
        }


def _batchable(body: bytes) -> bool:
    """Whether ``body`` is one JSON value a batch can hold, and no batch itself."""
    try:
        orjson.loads(body)
    except orjson.JSONDecodeError:
        return False
    return not body.startswith(b"[")


async def test_a_lone_hostile_message_is_decided_by_the_quick_parse_as_in_full() -> None:
    quick = await _lone_decisions(quick=True)
    full = await _lone_decisions(quick=False)
    assert quick == full


async def test_hostile_messages_in_a_batch_are_decided_as_each_alone() -> None:
    alone = await _lone_decisions(quick=True, batchable=True)
    together = await _lone_decisions(quick=True, batched=True)
    assert together == alone
