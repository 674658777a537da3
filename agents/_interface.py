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
from ._agent import Agent, MessageTemplate, on
from ._exceptions import (
    AuthenticationError,
    MessageError,
    SecurityError,
    TransportClosed,
    TransportError,
    UnknownSession,
)
from ._protocols import Refuse, on_query
from ._security import (
    Clock,
    Handshake,
    KeyPair,
    SecurityPolicy,
    SessionTable,
    TrustStore,
    fingerprint,
)
from .transports import Handle, Message, Presence, Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform

log = logging.getLogger(__name__)

INTERFACE_AGENT = "interface"
INTERFACE_ONTOLOGY = "interface"

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

    def __init__(
        self, *, keep: int = 10_000, path: str | Path | None = None, platform: str | None = None
    ) -> None:
        self.records: deque[dict[str, Any]] = deque(maxlen=keep)
        self.counts: dict[str, int] = {"accepted": 0, "refused": 0, "dropped": 0}
        self.path = Path(path) if path is not None else None
        self.platform = platform
        # bounded too: records pile up here if nothing flushes them
        self._pending: deque[dict[str, Any]] = deque(maxlen=keep)

    def record(self, **fields: Any) -> None:
        """Add one decision (``verdict`` is accepted, refused or dropped).

        Every record has the fields of ``docs/wire.md`` (None when unknown), so readers
        of the JSON lines need not guess which ones a kind of refusal leaves out.
        """
        rec: dict[str, Any] = {
            "v": WIRE_VERSION,
            "ts": time.time(),
            "platform": self.platform,
            "from": None,
            "sender": None,
            "receivers": None,
            "performative": None,
            "conversation_id": None,
            "verdict": "accepted",
            "reason": None,
            **fields,
        }
        self.records.append(rec)
        self._pending.append(rec)
        verdict = rec["verdict"]
        self.counts[verdict] = self.counts.get(verdict, 0) + 1

    def take(self) -> bytes:
        """The records not yet flushed, as JSON lines (empty when none); appended to ``path``."""
        if not self._pending:
            return b""
        pending = list(self._pending)
        self._pending.clear()
        data = b"".join(orjson.dumps(r) + b"\n" for r in pending)
        if self.path is not None:
            try:
                with self.path.open("ab") as f:
                    f.write(data)
            except OSError as exc:
                # a full disk must not stop the Interface Agent, nor the published audit
                log.warning("audit file %s not written: %s", self.path, exc)
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
        clock: Clock = time.time,
    ) -> None:
        self.keys = keys
        self.trust = trust
        self.policy = policy or SecurityPolicy()
        self.audit = AuditLog(path=audit_path, platform=keys.platform)
        self.publish_audit = publish_audit
        self.audit_interval = audit_interval
        self.handshake_timeout = handshake_timeout
        self.rehandshake_interval = rehandshake_interval
        self.max_bytes = max_bytes
        self.handshake = Handshake(keys, trust, policy=self.policy, clock=clock)
        self.sessions = SessionTable(keys.platform, trust, policy=self.policy, clock=clock)
        self._handshakes: dict[str, asyncio.Future[None]] = {}
        self._last_rehandshake: dict[str, float] = {}
        self._subs: list[Subscription[Message] | Subscription[Presence]] = []
        self._kx: Handle | None = None
        self._host: AgentPlatform | None = None
        self.agent: Agent | None = None

    # -- RemoteChannel ----------------------------------------------------------------

    async def start(self, platform: AgentPlatform) -> None:
        """Serve key exchanges, watch membership, receive the inbox, join the platform."""
        me = self.keys.platform
        if me != platform.name:
            raise SecurityError(
                f"the key pair is for platform {me!r}, but this platform is {platform.name!r}"
            )
        if self.trust.federation != platform.federation:
            raise SecurityError(
                f"the trust file is for federation {self.trust.federation!r}, "
                f"but this platform is in federation {platform.federation!r}"
            )
        if me in self.trust:
            trusted = self.trust.public_key(me)
            if trusted != self.keys.public_key:
                # every peer would refuse our handshakes as forged: say so now, and why
                raise SecurityError(
                    f"the trust file holds another key for {me!r} (fingerprint "
                    f"{fingerprint(trusted)}) than this key pair ({self.keys.fingerprint})"
                )
        else:
            log.warning(
                "interface[%s]: this platform is not in the trust file of federation %r: "
                "no peer will accept it",
                me,
                self.trust.federation,
            )
        self._host = platform
        transport = platform.transport
        self._kx = await transport.serve(platform.key("kx"), self._on_key_exchange)
        presence = await transport.watch_presence(platform.key("alive", "*"), history=False)
        self._subs.append(presence)
        inbox = await transport.subscribe(platform.key("acl"))
        self._subs.append(inbox)
        platform.spawn(self._receive(inbox), "interface.inbox")
        platform.spawn(self._watch(presence), "interface.presence")
        if self.publish_audit or self.audit.path is not None:
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
        await host.transport.publish(host.key("acl", platform), payload)
        if (
            host.running  # agents stopping with the platform still send; nothing renews then
            and platform not in self._handshakes
            and self.sessions.needs_renewal(platform)
            and not self._peer_renewing(platform)
        ):
            # keep sending on the current session while the new one is agreed
            host.spawn(self._renew(platform), f"interface.renew[{platform}]")

    async def aclose(self) -> None:
        """Stop receiving, stop serving key exchanges, flush the audit."""
        for sub in self._subs:
            sub.close()
        if self._kx is not None:
            self._kx.close()
        for fut in self._handshakes.values():
            if not fut.done():
                # not cancel(): waiters take a cancelled exchange as a cue to run their own
                fut.set_exception(TransportClosed("the Interface Agent is closed"))
                fut.exception()
        host = self._host
        data = self.audit.take()
        if data and host is not None and self.publish_audit:
            with contextlib.suppress(Exception):
                await host.transport.publish(host.key("audit"), data)

    # -- sessions ---------------------------------------------------------------------------

    @property
    def _me(self) -> str:
        return self.keys.platform

    def _peer_renewing(self, peer: str) -> bool:
        """Whether ``peer`` just made a session with us that it has not used yet.

        It will, at once: renewing as well would only add a session, and a table at its
        limit of sessions per peer makes room by dropping unused ones, such as the one the
        peer is about to use. (A replayed request can make such a session too; that only
        postpones our renewal by ``grace``.)
        """
        grace = self.policy.grace
        return any(
            not s.initiator and not s.confirmed and s.age() < grace
            for s in self.sessions.sessions(peer)
        )

    def _require_host(self) -> AgentPlatform:
        if self._host is None:
            raise SecurityError("the Interface Agent is not started")
        return self._host

    async def _agree(self, peer: str) -> None:
        """Run one key exchange with ``peer``; concurrent senders wait for the same one."""
        while (fut := self._handshakes.get(peer)) is not None and not fut.done():
            try:
                await asyncio.shield(fut)
                return
            except asyncio.CancelledError:
                task = asyncio.current_task()
                if (task is not None and task.cancelling()) or not fut.cancelled():
                    raise
                # the sender running the exchange was cancelled, not us: run one ourselves
        fut = asyncio.get_running_loop().create_future()
        self._handshakes[peer] = fut
        try:
            await self._exchange(peer)
        except asyncio.CancelledError:
            fut.cancel()
            raise
        except BaseException as exc:
            if not fut.done():
                fut.set_exception(exc)
                # the waiters get the error; nobody else needs to retrieve it
                fut.exception()
            raise
        else:
            if not fut.done():
                fut.set_result(None)
        finally:
            if self._handshakes.get(peer) is fut:
                del self._handshakes[peer]

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
            errors = [r.payload[:200].decode(errors="replace") for r in replies if not r.ok]
            detail = f" (error replies, not authenticated: {'; '.join(errors)})" if errors else ""
            raise TransportError(f"platform {peer!r} did not answer the key exchange{detail}")
        # Anyone on the network can answer a query on kx/<peer>: a bad reply must not hide
        # the good one, so each is tried (a refused one leaves our request pending).
        refusals: list[AuthenticationError] = []
        for reply in good:
            try:
                session = self.handshake.finish(reply.payload)
            except AuthenticationError as exc:
                self.audit.record(
                    verdict="dropped",
                    stage="kx",
                    **{"from": exc.platform or peer},
                    reason=f"{exc.code}: {exc.reason}",
                )
                refusals.append(exc)
                continue
            self.sessions.add(session)
            return
        self.handshake.cancel(peer)
        first = refusals[0]
        raise SecurityError(f"key exchange with {peer!r} refused: {first.reason}") from first

    async def _renew(self, peer: str, *, announce: bool = False) -> None:
        if not announce and (not self.sessions.needs_renewal(peer) or self._peer_renewing(peer)):
            return  # the peer renewed between our decision and now
        try:
            await self._agree(peer)
        except Exception as exc:
            log.warning(
                "interface[%s]: renewing the session with %s failed: %s", self._me, peer, exc
            )
            return
        agent = self.agent
        if announce and agent is not None and agent.running:
            # The peer seals on a session we no longer hold and never sends first on one
            # we made with it: a message on the new session is what makes it switch.
            try:
                await agent.send(
                    agent.message(
                        Performative.INFORM,
                        f"{INTERFACE_AGENT}@{peer}",
                        {"session": "new"},
                        ontology=INTERFACE_ONTOLOGY,
                    )
                )
            except Exception as exc:
                log.warning(
                    "interface[%s]: announcing the new session to %s failed: %s",
                    self._me,
                    peer,
                    exc,
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
        if (
            host is None
            or not host.running
            or peer == self._me
            or peer not in self.trust
            or peer in self._handshakes
        ):
            return
        now = time.monotonic()
        if now - self._last_rehandshake.get(peer, -1e9) < self.rehandshake_interval:
            return
        self._last_rehandshake[peer] = now
        host.spawn(self._renew(peer, announce=True), f"interface.rehandshake[{peer}]")

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
                sender = _claimed_sender(body)
                if sender is not None and platform_of(sender) != peer:
                    # the envelope proves only the platform: a not-understood to another
                    # one's agent would be sent on the word of this one
                    self.audit.record(
                        verdict="dropped",
                        **{"from": peer},
                        sender=sender,
                        reason=f"{exc.reason}; and the sender is not an agent of {peer!r}",
                    )
                    continue
                # refused: answered with not-understood, when there is someone to tell
                self.audit.record(
                    verdict="refused" if sender is not None else "dropped",
                    **{"from": peer},
                    sender=sender,
                    reason=exc.reason,
                )
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
        local = [r for r in message.receivers if platform_of(r) == host.name]
        if not local:
            self.audit.record(
                verdict="dropped", **base, reason=f"no receiver on platform {host.name!r}"
            )
            return
        if message.reply_to and any(platform_of(r) == host.name for r in message.reply_to):
            # replies would go from local agents to local agents on another platform's
            # word, reaching agents whose services that platform may not use
            await self._refuse(
                host, message, base, local[0], "reply_to may not name agents of this platform"
            )
            return
        if message.performative in INITIATING:
            df = host.df
            # without a directory no service is offered, so no request is admitted
            denied = [r for r in local if df is None or not df.reachable(r, peer)]
            if denied:
                reason = (
                    f"access denied: {', '.join(denied)} offers no service "
                    f"that platform {peer!r} may use"
                )
                await self._refuse(host, message, base, denied[0], reason)
                return
        self.audit.record(verdict="accepted", **base, reason=None)
        await host.deliver(message)

    async def _refuse(
        self,
        host: AgentPlatform,
        message: ACLMessage,
        base: dict[str, Any],
        receiver: str,
        reason: str,
    ) -> None:
        """Refuse an authenticated message: tell its sender if it asked something, audit."""
        if message.performative not in INITIATING:
            self.audit.record(verdict="dropped", **base, reason=reason)
            return
        self.audit.record(verdict="refused", **base, reason=reason)
        # to the sender only, whose platform is authenticated, whatever its reply_to says
        answer = message.reply(Performative.REFUSE, reason, sender=receiver)
        answer = answer.model_copy(update={"receivers": [message.sender]})
        try:
            await host.send(answer)
        except Exception as exc:
            log.warning("interface[%s]: could not refuse %s: %s", self._me, message.sender, exc)

    async def _watch(self, presence: Subscription[Presence]) -> None:
        """Forget a platform's sessions when it leaves or reappears (a new process)."""
        host = self._require_host()
        async for change in presence:
            peer = change.key.rpartition("/")[2]
            if peer == host.name:
                continue
            self.sessions.forget(peer)
            self._last_rehandshake.pop(peer, None)
            if not change.alive:
                # a request still pending when a platform reappears may be answered by the
                # new process (it serves kx before its token shows): keep it then
                self.handshake.cancel(peer)

    async def _flush_audit(self) -> None:
        """Write and publish the audit now and then (batched: one publish, many records)."""
        host = self._require_host()
        while True:
            await asyncio.sleep(self.audit_interval)
            data = self.audit.take()
            if data and self.publish_audit:
                try:
                    await host.transport.publish(host.key("audit"), data)
                except TransportError as exc:
                    log.debug("interface[%s]: audit not published: %s", self._me, exc)


class _InterfaceQueries(Agent):
    """The Interface Agent's face on its platform: answers local questions about it."""

    def __init__(self, interface: InterfaceAgent) -> None:
        super().__init__(INTERFACE_AGENT)
        self.interface = interface

    @on_query(INTERFACE_ONTOLOGY)
    async def _answer(self, message: ACLMessage) -> Any:
        """Local agents may read the audit and the sessions; other platforms may not."""
        if platform_of(message.sender) != self.platform.name:
            raise Refuse("the interface agent answers local agents only")
        content = message.content if isinstance(message.content, dict) else {}
        audit = self.interface.audit
        if "audit" in content:
            asked = content["audit"]
            n = asked if isinstance(asked, int) and not isinstance(asked, bool) else 100
            # copies: local messages are not serialized, and the log keeps changing
            last = list(audit.records)[-n:] if n > 0 else []
            return {"audit": [dict(r) for r in last], "counts": dict(audit.counts)}
        if content.get("sessions"):
            return {"peers": sorted(self.interface.sessions.peers())}
        raise Refuse("ask for {'audit': n} or {'sessions': true}")

    @on(MessageTemplate(Performative.INFORM, ontology=INTERFACE_ONTOLOGY))
    async def _new_session(self, message: ACLMessage) -> None:
        """A peer's announcement of a new session: receiving it was the point."""


def _claimed_sender(body: bytes) -> str | None:
    """The ``sender`` a body that is not a valid message names, if it can be read."""
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError:
        return None
    sender = obj.get("sender") if isinstance(obj, dict) else None
    return sender if isinstance(sender, str) else None
