"""The Interface Agent's presence: other platforms' comings and goings, within a budget."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from typing import TYPE_CHECKING

from ._interface_common import _PRESENCE_REPORT_INTERVAL
from ._interface_state import _InterfaceState
from ._presence import PRESENCE_BURST, PRESENCE_RATE, presence_bucket
from .transports import Presence, Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _Presence(_InterfaceState):
    """Other platforms' presence, unauthenticated: acted on within a budget, audited."""

    # -- presence: peers' liveliness, acted on within a budget -----------------------------

    async def _watch(self, presence: Subscription[Presence]) -> None:
        """Doubt a platform's sessions when its presence changes: it left, came or came back.

        Send on none of them until it sends on one: they may be a previous process's.
        Nothing is forgotten, nor a pending key exchange cancelled, as anyone may write a
        presence: a forged leave must not lose the answer in flight on a session (a real
        leave is signed: `peer_left` retires the sessions then). Changes over a peer's budget
        (`_presence_admits`) are counted and audited, and stand for one doubt of its
        sessions once the budget allows.
        """
        host = self._require_host()
        async for change in presence:
            peer = change.key.rpartition("/")[2]
            if peer == host.name or peer not in self.trust:
                continue  # no session with an untrusted name to doubt (the directory audits it)
            if self._presence_admits(host, peer):
                # Doubt, not forget: a request or an answer may be in flight on a session,
                # sealed before a leave (forged, or the peer's token late at a first sight:
                # zenoh on a loaded machine). But the sessions may be a previous process's,
                # whose token we never saw (the tokens alive when we started are not
                # reported) nor its end, which the new process cannot open. So none is sent
                # on until the peer sends on one; the next message agrees a new session.
                self._doubt(peer)
                self._lift_rehandshake_limit(peer)
            if change.alive:
                self._alive.add(peer)
            else:
                self._alive.discard(peer)
            self._kx_priority()
        host.ended(
            presence,
            f"session presence watch {host.key('alive', '*')}",
            "other platforms' restarts without their signed leave (a crash) are no longer "
            "seen: messages to one that restarted so are sealed on its previous process's "
            "session, which the new process cannot open",
        )

    def peer_left(self, peer: str, at: float | None = None) -> None:
        """``peer`` said, signed at ``at`` (POSIX s; now when None), that it leaves.

        Its global directory tells (a signed leave cannot be forged, unlike a presence
        cleared): none of its sessions agreed before ``at`` is sealed on again, nor
        trusted again by an envelope of its that comes late (they open within
        ``grace``, then go), so the next message to it agrees a new session, and finds
        nobody at once if it is gone; a key exchange with it begun before ``at`` ends.
        What began since is its next process's (a leave replayed by anyone within the
        skew, or late after a restart): kept. Sessions are judged by the time the peer
        signed its half of the key exchange (its clock, as ``at``); a key exchange under
        way, by our clock with ``at`` moved by the peer's offset its newest session shows.
        """
        if peer == self._me or peer not in self.trust:
            return
        if peer in self._outbox:
            self._flush(peer)  # what waits in this turn's batch goes as the message before it
        self.sessions.retire(peer, at)
        under_way = self._exchanging.get(peer)
        now = self._clock()
        begun_by = now if at is None else at - self.sessions.peer_clock_offset(peer)
        if under_way is not None and under_way[1] <= begun_by:
            with contextlib.suppress(RuntimeError):  # it is just ending anyway
                under_way[0].reschedule(asyncio.get_running_loop().time())  # ends it at once

    def _doubt(self, peer: str) -> None:
        """Seal for ``peer`` on none of its sessions until it sends on one (`SessionTable.doubt`).

        What waits in this turn's batch goes as the message before it did.
        """
        if peer in self._outbox:
            self._flush(peer)
        self.sessions.doubt(peer)

    def _presence_admits(self, host: AgentPlatform, peer: str) -> bool:
        """Whether a presence change of trusted ``peer`` is acted on now: within its budget.

        Presence is not authenticated (a forged zenoh token, a retained MQTT message), and
        each change acted on costs a key exchange with the peer, so at most
        `PRESENCE_BURST` at once, then `PRESENCE_RATE` per ``rehandshake_interval``. A
        genuine restart (gone, then back) fits; the rest of a toggling is counted
        (``stats.presence_suppressed``), audited, and doubts the peer's sessions once,
        when the budget allows, as its last change may have been true.
        """
        now = self._monotonic()
        bucket = self._presence_buckets.get(peer)
        if bucket is None:
            bucket = self._presence_buckets[peer] = presence_bucket(self.rehandshake_interval, now)
        later = self._presence_later.pop(peer, None)
        if bucket.take(now):
            if later is not None:
                later.cancel()  # this change brings the peer's sessions up to date
            return True
        host.stats.presence_suppressed += 1
        self._presence_ignored[peer] = self._presence_ignored.get(peer, 0) + 1
        self._presence_later[peer] = later or asyncio.get_running_loop().call_later(
            (1.0 - bucket.tokens) / bucket.rate, self._presence_catch_up, peer
        )
        self._wake_flush()  # to audit it
        return False

    def _presence_catch_up(self, peer: str) -> None:
        """Doubt ``peer``'s sessions for the presence changes ignored, once its budget allows."""
        self._presence_later.pop(peer, None)
        host = self._host
        if host is None or not host.running:
            return
        bucket = self._presence_buckets[peer]
        if not bucket.take(self._monotonic()):
            delay = max((1.0 - bucket.tokens) / bucket.rate, 0.05)
            self._presence_later[peer] = asyncio.get_running_loop().call_later(
                delay, self._presence_catch_up, peer
            )
            return
        self._doubt(peer)

    def _lift_rehandshake_limit(self, peer: str) -> None:
        """Let ``peer``'s next re-handshake cue act at once: at most once per interval.

        After a presence change the peer may be a new process, sealing on a session
        unknown here; an outsider toggling the presence must not make `rehandshake` run
        more often.
        """
        now = time.monotonic()  # the limiter's clock (`rehandshake`)
        if now - self._presence_lifted.get(peer, -math.inf) >= self.rehandshake_interval:
            self._presence_lifted[peer] = now
            self._last_rehandshake.pop(peer, None)

    def _report_presence_ignored(self, now: float) -> None:
        """Audit the presence changes ignored, one record per peer and interval."""
        if (
            not self._presence_ignored
            or now - self._presence_last_report < _PRESENCE_REPORT_INTERVAL
        ):
            return
        interval = self.rehandshake_interval
        for peer, n in self._presence_ignored.items():
            self.audit.record(
                verdict="dropped",
                stage="presence-limited",
                count=n,
                reason=(
                    f"presence changes of {peer!r} ignored: {n} over the budget of "
                    f"{PRESENCE_BURST} at once and {PRESENCE_RATE:g} per {interval:g} s "
                    "(presence is not authenticated); its sessions are doubted once instead"
                ),
                **{"from": peer},
            )
        self._presence_ignored.clear()
        self._presence_last_report = now
