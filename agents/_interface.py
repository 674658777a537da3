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
from typing import TYPE_CHECKING, Any

from ._acl import ACLMessage, Performative, platform_of
from ._agent import Agent, MessageTemplate, on
from ._aio import call_in_loop, together
from ._audit import AuditLog as AuditLog
from ._audit import accepted_entry as accepted_entry
from ._bucket import TokenBucket as TokenBucket
from ._exceptions import AgentError, SecurityError, TransportClosed, UnknownSession
from ._interface_admit import _Admission
from ._interface_common import _LANES as _LANES
from ._interface_common import _RAW as _RAW
from ._interface_common import AUDIT_HOLD as AUDIT_HOLD
from ._interface_common import INTERFACE_AGENT, INTERFACE_ONTOLOGY, log
from ._interface_common import MAX_BATCH as MAX_BATCH
from ._interface_common import WATCH_RATE as WATCH_RATE
from ._interface_common import RateLimit as RateLimit
from ._interface_lane import _Lane
from ._interface_owner import _Owner
from ._interface_presence import _Presence
from ._interface_receive import _Receiving
from ._interface_sessions import _Sessions
from ._protocols import Refuse, on_query
from ._security import fingerprint
from ._security import seal_owner_batch as seal_owner_batch
from .transports import Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform


_to_json = ACLMessage.to_json


def _batch_body(pending: list[bytes]) -> bytes:
    """The body of an envelope of these messages' JSON: one alone, or a JSON array of them.

    ``b"[" + b",".join(pending) + b"]"`` for two or more, with the brackets joined to the
    first and last (``pending`` is changed): the batch copied once, not three times.
    """
    if len(pending) == 1:
        return pending[0]
    pending[0] = b"[" + pending[0]
    pending[-1] += b"]"
    return b",".join(pending)


class InterfaceAgent(_Sessions, _Receiving, _Lane, _Admission, _Presence, _Owner):
    """Authenticates, access-controls, audits and forwards messages between platforms.

    Give it to the platform as its channel:
    ``AgentPlatform("uav-a", transport, federation="demo", channel=InterfaceAgent(keys, trust))``.
    It joins the platform as agent ``interface@<platform>``, which local agents can ask
    (FIPA-Query, ontology ``interface``) for ``{"audit": n}`` (the last n records) or
    ``{"sessions": true}`` or ``{"senders": true}`` (per platform: accepted, limited,
    refused by the rate limit; missing: ACL envelopes it sent that never arrived,
    also `missing`, and warned of in the log).

    The published audit is signed with this platform's key and sealed to its owner
    (``seal_audit``; see ``docs/wire.md``, "Batches for the owner"): outsiders and other
    members do not read it, nor pass off a batch of their own as this platform's. A
    batch is sealed and published only while the transport may have a subscriber for it
    (`Transport.has_subscribers`; counted in ``audit_published`` and ``audit_unheard``). The
    owner may also ask (``dyknow watch``: a request signed with the platform's key on
    ``watch/<platform>``) to see, for ``watch_lease`` seconds, every ACL message, sample
    batch and stream report this platform receives, opened, sealed to the owner too;
    ``watchable=False`` turns that off.

    ``audit_path``'s file is rotated at ``audit_max_bytes``, ``audit_backups`` older files
    kept (`AuditLog`).

    ``rate_limit`` (default `RateLimit()`; None: no limit) bounds what each other
    platform may send here, after authentication, so one platform's flood is dropped
    before it reaches the agents' mailboxes and others are still served. ``monotonic`` is
    its clock (injectable, as ``clock`` is for the envelopes' timestamps). ``kx_limit``
    (default `KxLimit()`; None: none) sheds key-exchange requests on the transport's
    thread before their signature check (``agents._kxgate``). A trusted peer sealing on a
    session this platform lost makes it agree a new one at most once per
    ``rehandshake_interval`` seconds. Presence is not authenticated: a peer's presence
    changes are acted on (its sessions doubted, never forgotten) within a budget,
    `PRESENCE_BURST` at once, then `PRESENCE_RATE` per ``rehandshake_interval``; the rest
    are counted (``stats.presence_suppressed``) and audited (``presence-limited``).

    ``batch`` (default on): messages for one platform sent in the same turn of the event
    loop after the first leave together, at the end of the turn, sealed in one envelope
    (a JSON array of messages, ``docs/wire.md``); each is still checked, rate-limited and
    audited one by one where it arrives. Off for a federation with platforms of a release
    before batches (they drop them).

    ``binary_acl`` (default on): ACL envelopes are sealed in their binary form (a msgpack
    array, ``docs/wire.md``); off, in the JSON form, for a federation with platforms of a
    release before it (they drop binary ones). Either way both forms are read.

    ``lane`` (default on; zenoh only; one lane a process): an ACL envelope is opened on
    zenoh's receiving thread while nothing waits for the loop, and a plain read an agent
    answers by `Agent.answer_on_thread` is answered there, before the event loop wakes, when
    the loop would answer it at once (`Agent.answer_at_once`) and nothing of its peer waits
    for the loop; counted in ``answered_on_thread`` (docs/agents.md says what runs where).
    With ``lane_replies`` (default on) a reply one of the agents' open conversations waits
    for, opened and parsed there, is taken on the loop in the callback that books what the
    lane answered: no task of the loop's between (counted in ``replies_on_thread``). A
    booking or hand-over there that raises costs only itself (logged, counted in
    ``lane_failed``). So does an envelope whose taking raises on the loop, with or without
    the lane (logged, counted in ``inbox_failed``): the inbox's consumer goes on.
    """

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
        self._acl_keys.clear()  # keys of this platform's federation only
        transport = platform.transport
        self._batching = self.batch and transport.publishes_nowait
        self._seal = self.sessions.seal_binary if self.binary_acl else self.sessions.seal
        self._loop = asyncio.get_running_loop()
        if self._unhook_trust is None:
            self._unhook_trust = self.trust.on_remove(self._trust_removed)
        gate = self.kx_gate
        # Independent, so at once: over MQTT each waits for the broker's answer, and a
        # start made of them one after another took a round trip through it for each.
        # Each is kept as it comes, for `aclose` to undo when another fails.
        got: dict[str, Subscription[Any]] = {}

        async def serve_kx() -> None:
            key = platform.key("kx")
            self._kx = platform.declared(
                await transport.serve(
                    key, self._on_key_exchange, admit=None if gate is None else gate.admit
                ),
                f"key-exchange queryable {key}",
                "no other platform can agree a new session with this one: one that "
                "restarts, or meets it for the first time, can no longer talk to it",
            )

        async def serve_watch() -> None:
            if self.watchable:
                key = platform.key("watch")
                self._watch_handle = platform.declared(
                    await transport.serve(key, self._on_watch, admit=self._admit_watch),
                    f"watch queryable {key}",
                    "this platform's owner can no longer watch it (dyknow watch)",
                )

        async def watch_presence() -> None:
            got["presence"] = sub = await transport.watch_presence(
                platform.key("alive", "*"), history=False
            )
            self._subs.append(sub)

        async def subscribe_inbox() -> None:
            inbox: Subscription[Any] | None = None
            if self.lane:
                inbox = await transport.subscribe_taking(
                    platform.key("acl"), self._lane_take, dropped=self._lane_dropped
                )
            self._lane_on = inbox is not None
            if self._lane_on:
                _LANES.change(1)
            self._lane_inbox = None if inbox is None else inbox.inbox
            if inbox is None:
                inbox = await transport.subscribe(platform.key("acl"))
            got["inbox"] = inbox
            self._subs.append(inbox)

        await together(serve_kx(), serve_watch(), watch_presence(), subscribe_inbox())
        presence, inbox = got["presence"], got["inbox"]
        platform.spawn(self._receive(inbox), "interface.inbox")
        platform.spawn(self._watch(presence), "interface.presence")
        if self.publish_audit:
            # asked once now so that zenoh declares the publisher and learns of the
            # subscribers before the first flush (a client's says none until then)
            transport.has_subscribers(platform.key("audit"))
        if (
            self.publish_audit
            or self.watchable
            or self.audit.path is not None
            or self.rate_limit is not None
            or self.kx_gate is not None
        ):
            platform.spawn(self._flushing(), "interface.audit")
        self.agent = await platform.add(_InterfaceQueries(self))

    async def send(self, platform: str, message: ACLMessage) -> None:
        """Seal ``message`` for ``platform`` (agreeing a session first if need be) and publish.

        The first message for ``platform`` in a turn of the event loop goes at once, alone
        (errors raise here); with batching, those that follow it in the same turn wait for
        its end and go together in one envelope, after it (so in order). A message that
        asks an answer (``reply_with``), the first such to ``platform`` since the last envelope
        opened from it or its last batch, opens no batch: the one after it goes alone too
        and opens it (a lone request costs no turn of the loop more). While a burst
        goes on (the last turn that sent to ``platform`` sent it two or more), the first
        waits in the batch too, once its session is there. A batch that cannot be sent
        then is logged and counted in ``batches_lost``.
        """
        if self._outbox and self.join_batch(platform, message):  # none waits: no call
            return
        body = message.to_json()
        host = self._host  # `_require_host`, inline
        if host is None:
            raise SecurityError("the Interface Agent is not started")
        if self._burst_first(platform, body):
            return
        try:
            payload = self._seal(platform, body)
        except UnknownSession:
            if platform in self._revoked and self._unsent_revoked(platform):
                return
            try:
                await self.agree(platform)
                try:
                    payload = self._seal(platform, body)
                except UnknownSession:
                    # its token's first sight came while we waited (`SessionTable.doubt`):
                    # the session may be a previous process's, so one more is agreed (at
                    # most once: a first sight is seen once until the platform leaves)
                    await self.agree(platform)
                    payload = self._seal(platform, body)
            except SecurityError:
                # revoked while its key exchange ran: dropped as one sent after it
                if platform in self._revoked and self._unsent_revoked(platform):
                    return
                raise
        await host.transport.publish(self._acl_key(host, platform), payload)
        self._sent(platform, message.reply_with is not None)

    def send_now(self, platform: str, message: ACLMessage) -> bool:
        """`send` when it waits for nothing (`sends_now`); else False, and nothing is sent.

        For an answer made as its question came (`Agent.answer_at_once`), and for the
        platform's every message to one other platform (`AgentPlatform.send` tries it
        first): no coroutine, and a message that cannot go at once (no session yet, a
        transport that waits, a session past its lifetime, whose seal fails) is left to
        `send`.
        """
        if self._outbox and self.join_batch(platform, message):
            return True
        host = self._host
        if host is None or not host.transport.publishes_nowait:
            return False
        body = message.to_json()
        # `_burst_first`'s first check, inline: no burst goes on in a round trip's turn
        if platform in self._bursting and self._burst_first(platform, body):
            return True
        try:
            # no session (yet): UnknownSession, left to `send`, which agrees one
            payload = self._seal(platform, body)
            key = self._acl_keys.get(platform)  # `_acl_key`, inline but its first call
            if key is None:
                key = self._acl_key(host, platform)
            host.transport.publish_nowait(key, payload)
        except AgentError:  # `send` meets it again and raises it where it is awaited
            return False
        try:
            self._sent(platform, message.reply_with is not None)
        except Exception:  # it went: True, or the caller would send it a second time
            log.exception("interface[%s]: after sending to %s", self._me, platform)
        return True

    def _burst_first(self, platform: str, body: bytes) -> bool:
        """While a burst to ``platform`` goes on, put the turn's first message in its batch."""
        if (
            platform in self._bursting
            and (size := 3 + len(body)) <= self.max_bytes
            and size <= self.policy.max_body_bytes
            and self.sessions.session_for(platform) is not None
        ):
            # a burst goes on: this first message of the turn waits for its end too, in
            # the batch, rather than in an envelope of its own (a seal, a put and an
            # open more per turn); sealing it then cannot fail for want of a session
            self._outbox[platform] = [body]
            self._outbox_bytes[platform] = size
            (self._loop or asyncio.get_running_loop()).call_soon(self._flush, platform)
            self.renew_if_needed(platform)
            return True
        return False

    def _acl_key(self, host: AgentPlatform, platform: str) -> str:
        """The key ``platform``'s ACL envelopes are published on (made once per peer)."""
        key = self._acl_keys.get(platform)
        if key is None:  # sealed: a peer we hold a session with
            key = self._acl_keys[platform] = host.key("acl", platform)
        return key

    def _sent(self, platform: str, asks: bool = False) -> None:
        """After a message went alone: renew the session if due, batch what follows in the turn.

        ``asks``: the message asks an answer (``reply_with``), so its sender most likely
        waits for it and sends nothing more this turn. The first such since the last
        envelope opened from ``platform`` (or its last batch) opens no batch: no flush,
        no turn of the loop for it; whatever follows goes alone too and opens it.
        """
        # `renew_if_needed`'s first check, inline (most often False): a call less a message
        if self.sessions.needs_renewal(platform):
            self.renew_if_needed(platform)
        if self._batching and platform not in self._outbox:
            if asks and platform not in self._lone:
                self._lone.add(platform)
                self._bursting.discard(platform)  # a turn of one message, as `_flush` ends it
                return
            self._outbox[platform] = []
            self._outbox_bytes[platform] = 2
            (self._loop or asyncio.get_running_loop()).call_soon(self._flush, platform)

    def sends_now(self, platform: str) -> bool:
        """Whether `send` to ``platform`` waits for nothing (no key exchange, no broker).

        A session to seal with is there, and the transport publishes at once (zenoh,
        memory; not MQTT, whose publish may wait for the broker).
        """
        host = self._host
        return (
            host is not None
            and host.transport.publishes_nowait
            and (platform in self._outbox or self.sessions.session_for(platform) is not None)
        )

    def join_batch(self, platform: str, message: ACLMessage) -> bool:
        """Add ``message`` to the batch waiting for ``platform`` in this turn; False if none.

        What `send` does with a message that follows another in the same turn of the
        loop, without a coroutine: a platform sending in a burst calls it first, and
        `send` only when it says False.
        """
        pending = self._outbox.get(platform)
        if pending is None:
            return False
        # the class's function called, not the method fetched from the message (pydantic's
        # attribute hook makes a bound method each time): a subclass's own is called as one
        body = _to_json(message) if type(message) is ACLMessage else message.to_json()
        sizes = self._outbox_bytes
        size = sizes[platform] + len(body) + 1
        # the largest batch body: what a receiver reads at most (both sides' default)
        # (two comparisons rather than min(): ~0.1 µs a message less)
        if len(pending) >= MAX_BATCH or size > self.max_bytes or size > self.policy.max_body_bytes:
            self._flush(platform, again=True)  # full: out now; the turn goes on batching
            pending = self._outbox[platform]
            size = 2 + len(body) + 1  # the brackets, this body and its comma, at most
        pending.append(body)
        sizes[platform] = size
        return True

    def _flush(self, platform: str, again: bool = False) -> None:
        """Seal what waits for ``platform`` in one envelope and publish it (a loop callback).

        ``again``: the turn is not over (the batch was full), keep batching in it.
        """
        pending = self._outbox.pop(platform, None)
        self._outbox_bytes.pop(platform, None)
        self._lone.discard(platform)
        bursting = self._bursting
        if again:
            self._outbox[platform] = []
            self._outbox_bytes[platform] = 2
        elif pending and (len(pending) > 1 or platform not in bursting):
            # the turn sent two or more (the first alone, unless it was bursting already)
            bursting.add(platform)
        else:
            bursting.discard(platform)
        if not pending:
            return
        body = _batch_body(pending)
        host = self._host
        try:
            if host is None:
                raise SecurityError("the Interface Agent is not started")
            payload = self._seal(platform, body)
            host.transport.publish_nowait(host.key("acl", platform), payload)
        except Exception as exc:  # a session lost or a transport closed within the turn
            self.batches_lost += len(pending)
            log.warning(
                "interface[%s]: %d message(s) to %s not sent: %s",
                self._me,
                len(pending),
                platform,
                exc,
            )

    def renew_if_needed(self, peer: str) -> None:
        """Start agreeing a new session with ``peer`` in the background if the current one is old.

        Sending goes on over the current session meanwhile. Nothing is started while the
        platform is stopping, while an exchange with ``peer`` runs, while ``peer`` has
        just made a session with us that it has not used yet, or once it is revoked.
        """
        host = self._host
        if (
            # first: asked after every message sent, and most often False from what the
            # table kept (the checks are reads, their order changes no answer)
            self.sessions.needs_renewal(peer)
            and host is not None
            and host.running  # agents stopping with the platform still send; nothing renews then
            # revoked since (the lane's answer booked at the flush's tick): no session is
            # what asks for one, and no exchange with it is wanted
            and peer in self.trust
            and peer not in self._handshakes
            and not self._peer_renewing(peer)
        ):
            host.spawn(self._renew(peer), f"interface.renew[{peer}]")

    def _trust_removed(self, peer: str) -> None:
        """The trust store's callback: revoke ``peer`` now when called in the platform's event
        loop, else in it, soon (the sessions and batches are that loop's)."""
        call_in_loop(self._loop, self._revoke, peer)

    def _unsent_revoked(self, peer: str) -> bool:
        """Whether a message for ``peer``, revoked here, is dropped (counted in
        ``unsent_revoked``): an answer of an agent to what it asked before its revocation
        is expected, not an error. False once it is trusted again."""
        if peer in self.trust:
            self._revoked.discard(peer)
            return False
        self.unsent_revoked += 1
        log.debug("interface[%s]: a message for %r not sent: it was revoked", self._me, peer)
        return True

    def _revoke(self, peer: str) -> None:
        """``peer`` was removed from the trust store: nothing is sealed for it any more.

        Its sessions are forgotten (a message for it then needs a key exchange, which its
        untrusted name refuses) and what waits for it in a batch is dropped; counted in
        ``revoked`` and audited (``stage: trust``, ``code: untrusted``, ``verdict: revoked``).
        """
        if peer == self._me:
            return  # its own name: no session with itself
        forgotten = self.sessions.forget(peer)
        self._revoked.add(peer)  # bounded by the trust file's platforms
        waiting = len(self._outbox.pop(peer, ()))
        self.unsent_revoked += waiting  # as those its agents send it from now on
        self._outbox_bytes.pop(peer, None)
        self._bursting.discard(peer)
        self._lone.discard(peer)
        self._acl_keys.pop(peer, None)
        # its directory subscriptions end too (it is told nothing): each change would be
        # one more message dropped for it, and one it held would count against its limit
        df = self._host.df if self._host is not None else None
        subscriptions = df.drop_subscriptions_of(peer) if df is not None else 0
        self.revoked += 1
        self.audit.record(
            verdict="revoked",
            stage="trust",
            code="untrusted",
            to=peer,
            reason=(
                f"platform {peer!r} was removed from the trust file (revoked): "
                f"{forgotten} session(s) with it forgotten, {waiting} message(s) for it "
                f"dropped, {subscriptions} directory subscription(s) of it ended"
            ),
        )
        log.warning(
            "interface[%s]: platform %r revoked: %d session(s) forgotten, %d message(s) "
            "dropped, %d directory subscription(s) ended",
            self._me,
            peer,
            forgotten,
            waiting,
            subscriptions,
        )

    async def aclose(self) -> None:
        """Send what waits in a batch, stop receiving and serving key exchanges, flush the audit."""
        if self._unhook_trust is not None:
            self._unhook_trust()
            self._unhook_trust = None
        for platform in list(self._outbox):
            self._flush(platform)
        for sub in self._subs:
            sub.close()
        if self._lane_on:
            self._lane_on = False
            _LANES.change(-1)
        for later in self._presence_later.values():
            later.cancel()
        self._presence_later.clear()
        if self._kx is not None:
            self._kx.close()
        if self._watch_handle is not None:
            self._watch_handle.close()
        for fut in self._handshakes.values():
            if not fut.done():
                # not cancel(): waiters take a cancelled exchange as a cue to run their own
                fut.set_exception(TransportClosed("the Interface Agent is closed"))
                fut.exception()
        host = self._host
        if self._lane_done:
            # what the lane answered since the flush's last tick: the flush is cancelled
            # only after this, so its records would miss the last batch and the file
            self._lane_book()
        data = self.audit.take()
        if host is not None and self.publish_audit:
            try:
                await self._publish_audit(host, data)
            except Exception as exc:  # closing: the transport may be gone already
                log.warning("interface: the last audit records were not published: %s", exc)


class _InterfaceQueries(Agent):
    """The Interface Agent's face on its platform: answers local questions about it."""

    def __init__(self, interface: InterfaceAgent) -> None:
        super().__init__(INTERFACE_AGENT)
        self.interface = interface

    @on_query(INTERFACE_ONTOLOGY)
    async def _answer_query(self, message: ACLMessage) -> Any:
        """Local agents may read the audit, sessions and senders; other platforms may not.

        (Not ``_answer``: that is `Agent`'s own, which answers unhandled messages.)
        """
        if platform_of(message.sender) != self.platform.name:
            raise Refuse("the interface agent answers local agents only")
        content = message.content if isinstance(message.content, dict) else {}
        audit = self.interface.audit
        if "audit" in content:
            asked = content["audit"]
            n = asked if isinstance(asked, int) and not isinstance(asked, bool) else 100
            # copies: local messages are not serialized, and the log keeps changing
            return {"audit": audit.last(n), "counts": dict(audit.counts)}
        if content.get("sessions"):
            return {"peers": sorted(self.interface.sessions.peers())}
        if content.get("senders"):
            senders = self.platform.stats.senders
            missing = self.interface.missing()
            return {
                "senders": {
                    p: {
                        "accepted": s.accepted,
                        "limited": s.limited,
                        "refused": s.refused,
                        "missing": missing.get(p, 0),
                    }
                    for p, s in senders.items()
                }
                | {
                    p: {"accepted": 0, "limited": 0, "refused": 0, "missing": n}
                    for p, n in missing.items()
                    if p not in senders
                }
            }
        raise Refuse("ask for {'audit': n}, {'sessions': true} or {'senders': true}")

    @on(MessageTemplate(Performative.INFORM, ontology=INTERFACE_ONTOLOGY))
    async def _new_session(self, message: ACLMessage) -> None:
        """A peer's announcement of a new session: receiving it was the point."""
