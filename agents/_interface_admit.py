"""The Interface Agent's admission: access control, rate limits, refusals, their audit."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from ._acl import ACLMessage, Performative, platform_of
from ._agent import Agent
from ._exceptions import MessageError, UnknownPlatform
from ._interface_common import (
    _UNTRUSTED_LOGGED,
    _UNTRUSTED_NAME,
    ANSWERED,
    INITIATING,
    RATE_LIMIT_REASON,
    UNTRUSTED_LOG_INTERVAL,
    _claimed_sender,
    _Sender,
    _written,
    log,
)
from ._interface_state import _InterfaceState
from ._quote import quoted

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _Admission(_InterfaceState):
    """Who may send what here: access, rate limits, refusals and their audit records."""

    # -- admission: access, rate limits, refusals, the unauthenticated budget --------------

    def _admit_target(self, host: AgentPlatform, peer: str, message: ACLMessage) -> Agent | None:
        """The agent `_admit` would hand ``message`` to at once, in the common case; else None.

        One receiver here, running with room in its mailbox; no reply_to; the sender an
        agent of ``peer``; a request only to a service ``peer`` may use. Changes nothing.
        """
        if message.reply_to or platform_of(message.sender) != peer:
            return None
        agent = host._ready_receiver(message)
        if agent is not None and message.performative in INITIATING:
            df = host.df
            if df is None or not df.reachable(message.receivers[0], peer):
                return None
        return agent

    def _admit_now(self, host: AgentPlatform, peer: str, message: ACLMessage) -> bool:
        """`_admit` for the common case, without waiting: False (nothing done) otherwise."""
        agent = self._admit_target(host, peer, message)
        if agent is None:
            return False
        self.audit.accepted(peer, message)
        host._deliver_now(agent, message)
        return True

    async def _malformed(self, host: AgentPlatform, peer: str, raw: Any, exc: MessageError) -> None:
        """A message that opened but is not valid: refuse it (not-understood) or drop it."""
        body = raw if type(raw) is bytes else _written(raw)
        sender = _claimed_sender(body)
        if sender is not None and platform_of(sender) != peer:
            # the envelope proves only the platform: a not-understood to another
            # one's agent would be sent on the word of this one
            host.stats.malformed += 1
            self.audit.record(
                verdict="dropped",
                **{"from": peer},
                sender=sender,
                reason=f"{exc.reason}; and the sender is not an agent of {peer!r}",
            )
            return
        # refused when answered with not-understood (there is someone to tell and
        # the body is no not-understood or failure itself), else dropped
        answered = await host.reject(body, exc.reason)
        self.audit.record(
            verdict="refused" if answered else "dropped",
            **{"from": peer},
            sender=sender,
            reason=exc.reason,
        )

    def _sender(self, host: AgentPlatform, peer: str) -> _Sender:
        """The rate-limit state of ``peer`` (authenticated, so one per trusted platform)."""
        from ._platform import SenderStats

        stats = host.stats.senders.setdefault(peer, SenderStats())
        sender = _Sender(self.rate_limit, stats, self._monotonic())
        self._senders[peer] = sender
        return sender

    async def _limited(
        self,
        host: AgentPlatform,
        peer: str,
        sender: _Sender,
        raw: Any,
        message: ACLMessage | None,
        now: float,
    ) -> None:
        """Drop a message over ``peer``'s rate; refuse a few requests; audit now and then."""
        sender.stats.limited += 1
        host.stats.rate_limited += 1
        sender.pending += 1
        refusals = sender.refusals
        if refusals is not None and refusals.take(now):
            if message is None:
                try:
                    if type(raw) is bytes:
                        message = ACLMessage.from_json(raw, max_bytes=self.max_bytes)
                    else:
                        message = ACLMessage.from_parsed(raw)
                except MessageError:
                    message = None  # not worth a not-understood: it was over the limit
            if message is not None and self._refuse_limited(host, peer, message):
                sender.stats.refused += 1
                sender.pending_refused += 1
                answer = message.reply(
                    Performative.REFUSE,
                    RATE_LIMIT_REASON,
                    sender=next(r for r in message.receivers if platform_of(r) == host.name),
                )
                answer = answer.model_copy(update={"receivers": [message.sender]})
                try:
                    await host.send(answer)
                except Exception as exc:
                    log.debug("interface[%s]: could not refuse %s: %s", self._me, peer, exc)
        self._report_limited(peer, sender, now)
        if sender.pending and self._flush_idle:
            # summed up later, by the flush: it sleeps, and no record came to wake it
            self._wake_flush()

    def _refuse_limited(self, host: AgentPlatform, peer: str, message: ACLMessage) -> bool:
        """Whether a dropped message is a request its sender can be told about."""
        # never to our own platform: its agents do not send from outside (see _admit)
        return (
            message.performative in INITIATING
            and peer != host.name
            and platform_of(message.sender) == peer
            and any(platform_of(r) == host.name for r in message.receivers)
        )

    def _report_limited(self, peer: str, sender: _Sender, now: float) -> None:
        """Audit ``peer``'s limiting at most once per interval (its first drop at once)."""
        limit = self.rate_limit
        if limit is None or not sender.pending:
            return
        if now - sender.last_report < limit.report_interval:
            return
        since = "" if math.isinf(sender.last_report) else f" in {now - sender.last_report:.1f} s"
        self.audit.record(
            verdict="dropped",
            stage="rate-limit",
            count=sender.pending,
            **{"from": peer},
            reason=(
                f"{RATE_LIMIT_REASON}: {sender.pending} message(s) from {peer!r} dropped{since} "
                f"({sender.pending_refused} answered with refuse; limit {limit.rate:g} "
                f"requests/s, burst {limit.burst:g}; {limit.total_rate:g} messages/s, "
                f"burst {limit.total_burst:g})"
            ),
        )
        sender.pending = 0
        sender.pending_refused = 0
        sender.last_report = now

    def audit_unauthenticated(self, claimed: str | None, reason: str, stage: str) -> None:
        """Audit input that did not authenticate (directory, presence, streams), within budget."""
        self._drop_unauthenticated(claimed, reason, stage=stage)

    def _drop_unauthenticated(
        self, claimed: str | None, reason: str, *, stage: str | None = None
    ) -> None:
        """Audit an envelope or handshake that did not authenticate, within a global budget."""
        if claimed is not None and reason.startswith(UnknownPlatform.code + ":"):
            self._log_untrusted(claimed, reason)
        extra = {} if stage is None else {"stage": stage}
        bucket = self._unauth
        if bucket is None or bucket.take(self._monotonic()):
            if type(claimed) is str and (
                len(claimed) > _UNTRUSTED_NAME or not claimed.isprintable()
            ):
                # anyone's claim, not a name checked: on one line, bounded
                claimed = quoted(claimed, _UNTRUSTED_NAME)
            self.audit.record(verdict="dropped", **{"from": claimed}, reason=reason, **extra)
            return
        # a flood of garbage must not become a flood of audit records: count, sum up later
        self._unauth_pending += 1
        self._report_unauthenticated(self._monotonic())
        if self._unauth_pending and self._flush_idle:
            # summed up later, by the flush: it sleeps, and no record came to wake it
            self._wake_flush()

    def _log_untrusted(self, claimed: str, reason: str) -> None:
        """Log a refused untrusted sender: once per name per interval, the rest summed up."""
        now = self._monotonic()
        if now - self._untrusted_since >= UNTRUSTED_LOG_INTERVAL:
            if self._untrusted_unlogged:
                log.warning(
                    "interface[%s]: %d more refusal(s) of senders not in the trust file in "
                    "%.0f s, not logged one by one (the audit has them)",
                    self._me,
                    self._untrusted_unlogged,
                    now - self._untrusted_since,
                )
            self._untrusted_logged.clear()
            self._untrusted_unlogged = 0
            self._untrusted_since = now
        name = claimed[:_UNTRUSTED_NAME]
        logged = self._untrusted_logged
        if name in logged:
            return
        if len(logged) >= _UNTRUSTED_LOGGED:
            self._untrusted_unlogged += 1
            return
        logged.add(name)
        log.warning(
            "interface[%s]: refused a platform calling itself %r (a claimed name, not "
            "authenticated): not in this platform's trust file (%s); if it is one of yours, "
            "trust its key, then SIGHUP its node (dyknow node) or restart this platform "
            "(logged once per %.0f s)",
            self._me,
            name,
            reason[:200],
            UNTRUSTED_LOG_INTERVAL,
        )

    def _report_unauthenticated(self, now: float) -> None:
        """Audit the unauthenticated input dropped without a record, once per interval."""
        limit = self.rate_limit
        if limit is None or not self._unauth_pending:
            return
        if now - self._unauth_last_report < limit.report_interval:
            return
        self.audit.record(
            verdict="dropped",
            stage="unauthenticated",
            count=self._unauth_pending,
            reason=(
                f"{self._unauth_pending} more envelope(s) or handshake(s) that did not "
                f"authenticate dropped without a record each (over {limit.unauthenticated:g} "
                "records/s)"
            ),
        )
        self._unauth_pending = 0
        self._unauth_last_report = now

    async def _admit(self, host: AgentPlatform, peer: str, message: ACLMessage) -> None:
        """Check the sender and access, audit, and deliver."""
        receivers = message.receivers
        if (
            len(receivers) == 1
            and not message.reply_to
            and platform_of(message.sender) == peer
            and peer != host.name
            and platform_of(receivers[0]) == host.name
        ):
            # the common case, decided as below without building the lists and records
            df = host.df
            if message.performative not in INITIATING or (
                df is not None and df.reachable(receivers[0], peer)
            ):
                self.audit.accepted(peer, message)
                await host.deliver(message)
                return
        base = {
            "from": peer,
            "sender": message.sender,
            "receivers": message.receivers,
            "performative": message.performative.value,
            "conversation_id": message.conversation_id,
        }
        if platform_of(message.sender) != peer:
            # the envelope proves the platform; an agent of another one is impersonated
            host.stats.denied += 1
            self.audit.record(
                verdict="dropped", **base, reason=f"sender is not an agent of {peer!r}"
            )
            return
        if peer == host.name:
            # local messages never come through a channel (`deliver` drops them as forged):
            # refused here, before anything could audit it as accepted, and counted as forged
            host.stats.forged += 1
            self.audit.record(
                verdict="dropped",
                **base,
                reason=f"sender claims this platform {peer!r}: its agents never send from outside",
            )
            return
        local = [r for r in message.receivers if platform_of(r) == host.name]
        if not local:
            host.stats.denied += 1
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
        if (
            message.reply_to
            and message.performative in ANSWERED
            and any(platform_of(r) != peer for r in message.reply_to)
        ):
            # answers go to the platform that asked: otherwise small requests would make
            # this platform send large answers to a third one (a reflection)
            self.reply_to_refused += 1
            await self._refuse(
                host,
                message,
                base,
                local[0],
                f"reply_to may name agents of the requesting platform {peer!r} only",
            )
            return
        if message.performative in INITIATING:
            df = host.df
            if df is not None and df.said_left(peer) and self.sessions.back_since_left(peer):
                # a restarted process, on a session it agreed after its leave: served at
                # once, not after its directory answers (its start-up requests would fail)
                df.set_left(peer, False)
            if df is not None and df.said_left(peer):
                host.stats.from_left += 1
                reason = (
                    f"left: {peer!r} said, signed, that it left the federation; it is served "
                    "again once its signed directory snapshot lists it"
                )
                await self._refuse(host, message, base, local[0], reason)
                return
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
        host.stats.denied += 1
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
