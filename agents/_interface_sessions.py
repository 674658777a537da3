"""The Interface Agent's sessions: the key exchanges that agree them, their renewal."""

from __future__ import annotations

import asyncio
import math
import time
from typing import TYPE_CHECKING

from ._acl import Performative
from ._exceptions import AuthenticationError, SecurityError, TransportError
from ._gate import shed_counts
from ._interface_common import _KX_ERRORS_KEPT, INTERFACE_AGENT, INTERFACE_ONTOLOGY, log
from ._interface_state import _InterfaceState

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _Sessions(_InterfaceState):
    """The Interface Agent's sessions with other platforms: agreed, renewed, reported."""

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

    async def agree(self, peer: str) -> None:
        """Agree a session with ``peer`` (one key exchange; concurrent callers share it).

        One that fails has suspended at least once before it raises (`docs/agents.md`)."""
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
            if isinstance(exc, Exception):
                # A query nobody serves (the platform gone) ends inside zenoh's call: the
                # caller would get the failure without ever suspending, and one retrying in
                # a loop without a pause would starve every other task of its loop
                await asyncio.sleep(0)
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
        errors: list[str] = []
        first: AuthenticationError | None = None
        stats = host.stats
        # Anyone on the network can answer a query on kx/<peer>: a bad reply must not hide
        # the good one, so each is tried as it comes (a refused one leaves our request
        # pending), and the first that finishes the exchange ends it, without waiting for
        # the query's end (on MQTT, its whole timeout).
        ended = asyncio.timeout(None)  # `peer_left` ends it
        self._exchanging[peer] = (ended, self._clock())
        try:
            async with (
                ended,
                await host.transport.ask(
                    host.key("kx", peer), request, timeout=self.handshake_timeout
                ) as replies,
            ):
                async for reply in replies:
                    if not reply.ok:
                        if len(errors) < _KX_ERRORS_KEPT:  # anyone may send them, unbounded
                            errors.append(reply.payload[:200].decode(errors="replace"))
                        continue
                    try:
                        session = self.handshake.finish(reply.payload)
                    except AuthenticationError as exc:
                        # as cheap to send as any unauthenticated input: a flood of them
                        # must not become a flood of audit records (the shared budget)
                        stats.kx_replies_refused += 1
                        self._drop_unauthenticated(
                            exc.platform or peer, f"{exc.code}: {exc.reason}", stage="kx"
                        )
                        if first is None:
                            first = exc
                        continue
                    self.sessions.add(session)
                    self._kx_priority()
                    return
        except TimeoutError:
            self.handshake.cancel(peer)
            if not ended.expired():
                raise
            raise TransportError(
                f"platform {peer!r} left the federation (signed): no key exchange with it"
            ) from None
        except BaseException:
            self.handshake.cancel(peer)
            raise
        finally:
            under_way = self._exchanging.get(peer)
            if under_way is not None and under_way[0] is ended:
                del self._exchanging[peer]
        self.handshake.cancel(peer)
        if first is None:
            detail = f" (error replies, not authenticated: {'; '.join(errors)})" if errors else ""
            raise TransportError(f"platform {peer!r} did not answer the key exchange{detail}")
        raise SecurityError(f"key exchange with {peer!r} refused: {first.reason}") from first

    async def _renew(self, peer: str, *, announce: bool = False) -> None:
        if not announce and (not self.sessions.needs_renewal(peer) or self._peer_renewing(peer)):
            return  # the peer renewed between our decision and now
        try:
            await self.agree(peer)
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
            host = self._host
            if host is not None:
                host.stats.kx_requests_refused += 1
            self._drop_unauthenticated(exc.platform, f"{exc.code}: {exc.reason}", stage="kx")
            return None
        self.sessions.add(session)
        self._kx_priority()
        return reply

    def _kx_priority(self) -> None:
        """Tell the key-exchange gate which platforms are exempt from its shared budget."""
        gate = self.kx_gate
        if gate is not None:
            # replaced whole: the transport's thread reads it without a lock
            gate.priority = frozenset(self._alive) | frozenset(self.sessions.peers())

    def _count_shed(self, n: int) -> None:
        """Count key-exchange requests the gate dropped (called on the transport's thread)."""
        host = self._host
        if host is not None:
            host.stats.kx_shed += n
        self._wake_flush()  # to audit them

    def missing(self) -> dict[str, int]:
        """Per peer, the ACL envelopes it sent that never arrived (``docs/wire.md``, ``n``)."""
        return self.sessions.missing()

    def _report_missing(self, now: float) -> None:
        """Warn of envelopes lost from a peer: when its count first grows, then once a while."""
        warned = self._missing_warned
        for peer, count in self.sessions.missing().items():
            last, at = warned.get(peer, (0, -math.inf))
            if count > last and now - at >= self.missing_warn_interval:
                warned[peer] = (count, now)
                log.warning(
                    "interface[%s]: %d ACL envelope(s) from %s missing (sent, never arrived)",
                    self._me,
                    count,
                    peer,
                )

    def _report_kx_shed(self, now: float) -> None:
        """Audit what the key-exchange gate dropped: a few one by one, the rest summed up."""
        gate = self.kx_gate
        if gate is None:
            return
        details, summary = gate.take_report(now)
        for claimed, reason in details:
            self._drop_unauthenticated(claimed, reason, stage="kx")
        if summary is None:
            return
        limit = gate.limit
        self.audit.record(
            verdict="dropped",
            stage="kx-shed",
            count=summary["count"],
            by_reason=summary["by_reason"],
            reason=(
                f"key-exchange requests shed: {summary['count']} dropped before any "
                f"signature check{shed_counts(summary)}; budget {limit.per_peer:g}/s per "
                f"platform, burst {limit.per_peer_burst:g}; {limit.total:g}/s for "
                f"platforms without a session, burst {limit.total_burst:g})"
            ),
        )

    def rehandshake(self, peer: str) -> None:
        """A trusted peer seals on a session we lost (we restarted): agree a new one, rarely.

        Runs in the background, at most once per ``rehandshake_interval`` seconds per peer;
        an untrusted or unknown ``peer`` is ignored.
        """
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
            host.stats.rehandshakes_suppressed += 1
            return
        self._last_rehandshake[peer] = now
        host.stats.rehandshakes += 1
        host.spawn(self._renew(peer, announce=True), f"interface.rehandshake[{peer}]")
