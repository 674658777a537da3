"""The Interface Agent: the single entry point for every message from another platform.

It is the platform's `RemoteChannel`: outgoing messages are sealed under a session
key agreed with the receiving platform by a signed key exchange; incoming envelopes are
opened (authenticity, integrity, replay, expiry), the ACL message's sender is checked
against the authenticated platform, access is controlled by service visibility, every
decision goes into the audit log, and only then is the message delivered to the local
agent. A refused message never reaches an agent. See ``docs/security.md``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

import orjson

from ._acl import MAX_MESSAGE_BYTES, WIRE_VERSION, ACLMessage, Performative, platform_of
from ._agent import Agent
from ._exceptions import (
    AuthenticationError,
    MessageError,
    SecurityError,
    TransportError,
    UnknownSession,
)
from ._protocols import Refuse, on_query
from ._security import Handshake, KeyPair, SecurityPolicy, SessionTable, TrustStore
from .transports import Handle, Message, Presence, Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform

log = logging.getLogger(__name__)

INTERFACE_AGENT = "interface"

# Performatives that open a conversation: they ask a local agent to do something, so
# they need a service the asker may use. Everything else continues a conversation.
INITIATING = frozenset(
    {
        Performative.REQUEST,
        Performative.REQUEST_WHEN,
        Performative.REQUEST_WHENEVER,
        Performative.QUERY_IF,
        Performative.QUERY_REF,
        Performative.SUBSCRIBE,
        Performative.CFP,
        Performative.PROPAGATE,
        Performative.PROXY,
    }
)


class AuditLog:
    """What the Interface Agent decided about each remote message: kept, written, published.

    The last ``keep`` records stay in memory; with ``path`` they are appended to a
    JSON-lines file; with a platform they are published in batches on
    ``dyknow/<fed>/v1/audit/<platform>`` (one JSON record per line), so one publish
    carries many records and auditing does not double the transport's load.
    """

    def __init__(self, *, keep: int = 10_000, path: str | Path | None = None) -> None:
        self.records: deque[dict[str, Any]] = deque(maxlen=keep)
        self.counts: dict[str, int] = {"accepted": 0, "refused": 0, "dropped": 0}
        self.path = Path(path) if path is not None else None
        self._pending: list[dict[str, Any]] = []

    def record(self, **fields: Any) -> None:
        """Add one decision (``verdict`` is accepted, refused or dropped)."""
        rec = {"v": WIRE_VERSION, "ts": time.time(), **fields}
        self.records.append(rec)
        self._pending.append(rec)
        verdict = fields.get("verdict", "accepted")
        self.counts[verdict] = self.counts.get(verdict, 0) + 1

    def take(self) -> bytes:
        """The records not yet flushed, as JSON lines (empty when none)."""
        if not self._pending:
            return b""
        pending, self._pending = self._pending, []
        data = b"".join(orjson.dumps(r) + b"\n" for r in pending)
        if self.path is not None:
            with self.path.open("ab") as f:
                f.write(data)
        return data


class InterfaceAgent:
    """Authenticates, access-controls, audits and forwards messages between platforms.

    Give it to the platform as its channel:
    ``AgentPlatform("uav-a", transport, federation="demo", channel=InterfaceAgent(keys, trust))``.
    It joins the platform as agent ``interface@<platform>``, which local agents can ask
    (FIPA-Query, ontology ``interface``) for ``{"audit": n}`` (the last n records) or
    ``{"sessions": true}``.
    """

    def __init__(
        self,
        keys: KeyPair,
        trust: TrustStore,
        *,
        policy: SecurityPolicy | None = None,
        audit_path: str | Path | None = None,
        publish_audit: bool = True,
        audit_interval: float = 0.25,
        handshake_timeout: float = 2.0,
        rehandshake_interval: float = 1.0,
        max_bytes: int = MAX_MESSAGE_BYTES,
    ) -> None:
        self.keys = keys
        self.trust = trust
        self.policy = policy or SecurityPolicy()
        self.audit = AuditLog(path=audit_path)
        self.publish_audit = publish_audit
        self.audit_interval = audit_interval
        self.handshake_timeout = handshake_timeout
        self.rehandshake_interval = rehandshake_interval
        self.max_bytes = max_bytes
        self.handshake = Handshake(keys, trust, policy=self.policy)
        self.sessions = SessionTable(keys.platform, trust, policy=self.policy)
        self._handshakes: dict[str, asyncio.Future[None]] = {}
        self._last_rehandshake: dict[str, float] = {}
        self._subs: list[Subscription[Message] | Subscription[Presence]] = []
        self._kx: Handle | None = None
        self._host: AgentPlatform | None = None
        self.agent: Agent | None = None

    # -- RemoteChannel ----------------------------------------------------------------

    async def start(self, platform: AgentPlatform) -> None:
        """Serve key exchanges, watch membership, receive the inbox, join the platform."""
        if self.keys.platform != platform.name:
            raise SecurityError(
                f"key pair is uav {self.keys.platform!r}, but the platform is {platform.name!r}"
            )
        if self.trust.federation != platform.federation:
            raise SecurityError(
                f"trust file is for federation {self.trust.federation!r}, "
                f"but the platform is in {platform.federation!r}"
            )
        self._host = platform
        transport = platform.transport
        self._kx = await transport.serve(platform.key("kx"), self._on_key_exchange)
        presence = await transport.watch_presence(platform.key("alive", "*"), history=False)
        inbox = await transport.subscribe(platform.key("acl"))
        self._subs = [presence, inbox]
        platform.spawn(self._receive(inbox), "interface.inbox")
        platform.spawn(self._watch(presence), "interface.presence")
        if self.publish_audit:
            platform.spawn(self._flush_audit(), "interface.audit")
        self.agent = await platform.add(_InterfaceQueries(self))

    async def send(self, platform: str, message: ACLMessage) -> None:
        """Seal ``message`` for ``platform`` (agreeing a session first if need be) and publish."""
        host = self._require_host()
        body = message.to_json()
        try:
            payload = self.sessions.seal(platform, body)
        except UnknownSession:
            await self._agree(platform)
            payload = self.sessions.seal(platform, body)
        if self.sessions.needs_renewal(platform) and platform not in self._handshakes:
            # keep sending on the current session while the new one is agreed
            host.spawn(self._renew(platform), f"interface.renew[{platform}]")
        await host.transport.publish(host.key("acl", platform), payload)

    async def aclose(self) -> None:
        """Stop receiving, stop serving key exchanges, flush the audit."""
        for sub in self._subs:
            sub.close()
        if self._kx is not None:
            self._kx.close()
        for fut in self._handshakes.values():
            if not fut.done():
                fut.cancel()
        host = self._host
        data = self.audit.take()
        if data and host is not None and self.publish_audit:
            with contextlib.suppress(Exception):
                await host.transport.publish(host.key("audit"), data)

    # -- sessions ---------------------------------------------------------------------------

    @property
    def _me(self) -> str:
        return self.keys.platform

    def _require_host(self) -> AgentPlatform:
        if self._host is None:
            raise SecurityError("the Interface Agent is not started")
        return self._host

    async def _agree(self, peer: str) -> None:
        """Run one key exchange with ``peer``; concurrent senders wait for the same one."""
        fut = self._handshakes.get(peer)
        if fut is None:
            fut = asyncio.get_running_loop().create_future()
            self._handshakes[peer] = fut
            try:
                await self._exchange(peer)
                fut.set_result(None)
            except BaseException as exc:
                fut.set_exception(exc)
                # the waiters get the error; nobody else needs to retrieve it
                fut.exception()
                raise
            finally:
                self._handshakes.pop(peer, None)
        else:
            await asyncio.shield(fut)

    async def _exchange(self, peer: str) -> None:
        host = self._require_host()
        request = self.handshake.initiate(peer)
        try:
            replies = await host.transport.query(
                host.key("kx", peer), request, timeout=self.handshake_timeout
            )
        except BaseException:
            self.handshake.cancel(peer)
            raise
        good = [r for r in replies if r.ok]
        if not good:
            self.handshake.cancel(peer)
            raise TransportError(f"platform {peer!r} did not answer the key exchange")
        try:
            self.sessions.add(self.handshake.finish(good[0].payload))
        except AuthenticationError as exc:
            self.audit.record(
                verdict="dropped", stage="kx", peer=peer, reason=f"{exc.code}: {exc.reason}"
            )
            raise SecurityError(f"key exchange with {peer!r} refused: {exc.reason}") from exc

    async def _renew(self, peer: str) -> None:
        try:
            await self._agree(peer)
        except Exception as exc:
            log.warning(
                "interface[%s]: renewing the session with %s failed: %s", self._me, peer, exc
            )

    async def _on_key_exchange(self, key: str, payload: bytes) -> bytes | None:
        """Answer a key-exchange request (the kx queryable); refused ones get no answer."""
        try:
            reply, session = self.handshake.respond(payload)
        except AuthenticationError as exc:
            self.audit.record(
                verdict="dropped",
                stage="kx",
                **{"from": exc.platform},
                reason=f"{exc.code}: {exc.reason}",
            )
            return None
        self.sessions.add(session)
        return reply

    def _rehandshake(self, peer: str) -> None:
        """A trusted peer sends on a session we lost (we restarted): agree a new one, rarely."""
        host = self._host
        if host is None or peer not in self.trust or peer in self._handshakes:
            return
        now = time.monotonic()
        if now - self._last_rehandshake.get(peer, -1e9) < self.rehandshake_interval:
            return
        self._last_rehandshake[peer] = now
        host.spawn(self._renew(peer), f"interface.rehandshake[{peer}]")

    # -- receiving ----------------------------------------------------------------------------

    async def _receive(self, inbox: Subscription[Message]) -> None:
        host = self._require_host()
        open_envelope = self.sessions.open
        from_json = ACLMessage.from_json
        async for item in inbox:
            try:
                peer, body = open_envelope(item.payload)
            except AuthenticationError as exc:
                self.audit.record(
                    verdict="dropped",
                    **{"from": exc.platform},
                    reason=f"{exc.code}: {exc.reason}",
                )
                if isinstance(exc, UnknownSession) and exc.platform is not None:
                    self._rehandshake(exc.platform)
                continue
            except Exception as exc:  # never let one envelope end the loop
                self.audit.record(verdict="dropped", reason=f"malformed: {exc}")
                continue
            try:
                message = from_json(body, max_bytes=self.max_bytes)
            except MessageError as exc:
                self.audit.record(verdict="refused", **{"from": peer}, reason=exc.reason)
                await host.reject(body, exc.reason)
                continue
            try:
                await self._admit(host, peer, message)
            except Exception:
                log.exception("interface[%s]: delivering from %s failed", self._me, peer)

    async def _admit(self, host: AgentPlatform, peer: str, message: ACLMessage) -> None:
        """Check the sender and access, audit, and deliver."""
        base = {
            "from": peer,
            "sender": message.sender,
            "receivers": message.receivers,
            "performative": message.performative.value,
            "conversation_id": message.conversation_id,
        }
        if platform_of(message.sender) != peer:
            # the envelope proves the platform; an agent of another one is impersonated
            self.audit.record(
                verdict="dropped", **base, reason=f"sender is not an agent of {peer!r}"
            )
            return
        if message.performative in INITIATING and host.df is not None:
            denied = [
                r
                for r in message.receivers
                if platform_of(r) == host.name and not host.df.reachable(r, peer)
            ]
            if denied:
                reason = (
                    f"access denied: {', '.join(denied)} offers no service "
                    f"that platform {peer!r} may use"
                )
                self.audit.record(verdict="refused", **base, reason=reason)
                with contextlib.suppress(Exception):
                    await host.send(message.reply(Performative.REFUSE, reason, sender=denied[0]))
                return
        self.audit.record(verdict="accepted", **base, reason=None)
        await host.deliver(message)

    async def _watch(self, presence: Subscription[Presence]) -> None:
        """Forget a platform's sessions when it leaves or reappears (a new process)."""
        host = self._require_host()
        async for change in presence:
            peer = change.key.rpartition("/")[2]
            if peer == host.name:
                continue
            self.sessions.forget(peer)
            self.handshake.cancel(peer)
            self._last_rehandshake.pop(peer, None)

    async def _flush_audit(self) -> None:
        host = self._require_host()
        while True:
            await asyncio.sleep(self.audit_interval)
            data = self.audit.take()
            if data:
                try:
                    await host.transport.publish(host.key("audit"), data)
                except TransportError as exc:
                    log.debug("interface[%s]: audit not published: %s", self._me, exc)


class _InterfaceQueries(Agent):
    """The Interface Agent's face on its platform: answers local questions about it."""

    def __init__(self, interface: InterfaceAgent) -> None:
        super().__init__(INTERFACE_AGENT)
        self.interface = interface

    @on_query("interface")
    async def _answer(self, message: ACLMessage) -> Any:
        """Local agents may read the audit and the sessions; other platforms may not."""
        if platform_of(message.sender) != self.platform.name:
            raise Refuse("the interface agent answers local agents only")
        content = message.content if isinstance(message.content, dict) else {}
        audit = self.interface.audit
        if "audit" in content:
            n = content["audit"] if isinstance(content["audit"], int) else 100
            return {"audit": list(audit.records)[-n:], "counts": audit.counts}
        if content.get("sessions"):
            return {"peers": sorted(self.interface.sessions.peers())}
        raise Refuse("ask for {'audit': n} or {'sessions': true}")
