"""Export and import proxies: agreed streams flow platform to platform, bypassing the agents.

Once the Federation Agents agreed a stream, the provider's `ExportProxy` subscribes to the
local label with the agreed policy and pushes what it emits to the receiver as sealed
msgpack batches on ``dyknow/<fed>/v1/stream/<receiver>/<sender>/<semantic-label>``; the
receiver's `ImportProxy` opens them, translates the semantic label to a local one and
adds the samples to that local stream, which is to its instance just another source.
The bytes are in ``docs/wire.md`` ("Sample batches").

Isolation: every export has its own bounded queue and its own task. The local instance
hands samples to the queue and returns at once; the task packs, seals and publishes.
A receiver that is slow, frozen or gone costs its own queue's oldest samples (counted
and reported), never the instance's time or another receiver's.

Faults: a receiver reports on every stream it gets every 0.5 s, with what never arrived
(gaps in the sender's numbering). The reports are the export's lease (an export not
reported on for ``lease`` s ends, ``lease-expired``); an export made with ``history``
resends, after a gap, the samples before its end the receiver asks for.

Sessions: batches are sealed per receiver with the session the Interface Agents agreed
(`InterfaceSessions`); anything implementing `SessionsProvider` may stand in for it
(`TableSessions` over a bare `SessionTable`; `PlainSessions`, unauthenticated, for tests).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import inspect
import logging
import re
import time
from collections import deque
from collections.abc import Awaitable, Callable
from enum import Enum
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, Self, runtime_checkable

import msgpack

from agents import (
    AuthenticationError,
    Expired,
    Malformed,
    Misdirected,
    SessionTable,
    TokenBucket,
    TransportClosed,
    Unencrypted,
    UnknownPlatform,
    UnknownSession,
    check_name,
    wire_key,
)
from agents.transports import Message, Presence, Transport
from agents.transports import Subscription as TransportSubscription
from dyknow_core import (
    CacheSpec,
    DuplicateLabelError,
    DyKnowInstance,
    Policy,
    ProcessError,
    RawSample,
    Source,
)
from dyknow_core import Subscription as StreamSubscription

if TYPE_CHECKING:
    from agents import InterfaceAgent

__all__ = [
    "BATCH_VERSION",
    "Batch",
    "Export",
    "ExportProxy",
    "Import",
    "ImportProxy",
    "InterfaceSessions",
    "PlainSessions",
    "SessionsProvider",
    "TableSessions",
    "pack_batch",
    "read_batch",
    "unpack_batch",
]

log = logging.getLogger(__name__)

BATCH_VERSION = 1

Translate = Callable[[str, str], str | None]
"""``translate(sender, semantic_label)``: the local label to import into, None if never agreed."""

OnDrop = Callable[["Export", str, int], None]
"""``on_drop(export, reason, count)``: told in the publisher's call; keep it short."""

OnSenderGone = Callable[[str, list[str]], Awaitable[None] | None]
"""``on_sender_gone(sender, semantic_labels)``: told when a sender's streams were ended."""

OnExportEnded = Callable[[str, str], Awaitable[None] | None]
"""``on_export_ended(sender, semantic_label)``: the sender ended that export by itself."""

OnRefused = Callable[[str, str, int, int], None]
"""``on_refused(sender, reason, batches, samples)``: whole batches dropped since last told."""

# A semantic label becomes key chunks: no wildcard or MQTT-special characters, no spaces.
_LABEL = re.compile(r"^[^\s/*$?#+\x00-\x1f\x7f]+(?:/[^\s/*$?#+\x00-\x1f\x7f]+)*$")
_MAX_LABEL = 256
_packb = msgpack.packb
_unpackb = msgpack.unpackb
_BACKOFF_MIN = 0.05
_BACKOFF_MAX = 2.0
# How often an idle export looks whether its local stream ended (no event tells it).
_IDLE_CHECK = 1.0
# How many payloads the import loop handles before letting other tasks run.
_YIELD_EVERY = 64
# An idle export not acknowledged for this long sends an empty batch (receivers report
# every 0.5 s by default): a live receiver learns of the stream and answers.
_KEEPALIVE_AFTER = 1.0
# Pending resend requests kept per export, and missing ranges tracked per import.
_MAX_RECOVER = 16
_MAX_HISTORY = 1_000_000
_MAX_FAILED = 256  # failed ranges remembered per export (older ones stay counted)
_HISTORY_SLACK = 256
_MAX_MISSING = 64
_MAX_ASKS = 6  # the import proxy's reports that ask again for what is still missing
# Resend requests a receiver may make per second (all its exports), and at once: one per
# gap plus the re-asks of its reports (2/s per stream) fit; a flood of them does not.
RESEND_RATE = 20.0
RESEND_BURST = 40.0
# A receiver's refused resend requests are audited at most once per this many seconds.
RESEND_REPORT_INTERVAL = 1.0


def _uncovered(ranges: list[tuple[int, int]], first: int, end: int) -> list[tuple[int, int]]:
    """The parts of [first, end) that no range of ``ranges`` (sorted, disjoint) covers."""
    out: list[tuple[int, int]] = []
    for a, b in ranges:
        if b <= first:
            continue
        if a >= end:
            break
        if a > first:
            out.append((first, a))
        first = max(first, b)
        if first >= end:
            return out
    if first < end:
        out.append((first, end))
    return out


def _cover(ranges: list[tuple[int, int]], first: int, end: int) -> list[tuple[int, int]]:
    """``ranges`` (sorted, disjoint) with [first, end) added, touching ranges merged."""
    out: list[tuple[int, int]] = []
    for a, b in ranges:
        if b < first or a > end:
            out.append((a, b))
        else:
            first, end = min(a, first), max(b, end)
    out.append((first, end))
    out.sort()
    return out


_MAX_REFUSED_KEYS = 32  # (sender, reason) pairs summed up between two on_refused calls: the
# rest (invented sender names of an outsider's flood) share one "*" entry per reason


def check_semantic_label(label: str) -> str:
    """Check that a semantic label can travel as key chunks, and return it."""
    if not isinstance(label, str) or len(label) > _MAX_LABEL or not _LABEL.match(label):
        raise ValueError(
            f"semantic label {label!r} must be 1-{_MAX_LABEL} characters, '/'-separated "
            "non-empty chunks without spaces or any of * $ ? # +"
        )
    return label


# --------------------------------------------------------------------------- batches


def _encode_value(obj: Any) -> Any:
    """What msgpack cannot carry itself, as something it can (else TypeError)."""
    if isinstance(obj, Enum):
        return obj.value
    if isinstance(obj, set | frozenset):
        return list(obj)
    dump = getattr(obj, "model_dump", None)
    if callable(dump):  # a pydantic model
        return dump(mode="json")
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    raise TypeError(f"a {type(obj).__name__} value cannot travel in a sample batch")


def pack_batch(
    semantic_label: str,
    samples: list[RawSample],
    seq: int = 0,
    *,
    history: int = 0,
    recovered: bool = False,
    ended: str | None = None,
) -> bytes:
    """The msgpack body of one batch: ``{"v": 1, "s": label, "q": seq, "b": [[v, tv, ta]…]}``.

    ``history`` (the sender keeps that many samples to resend) adds ``"h"``; a batch
    resent from that history is marked ``"r": true``; the last batch of an export the
    sender ended by itself (its lease expired) carries the reason as ``"e"``.
    """
    obj: dict[str, Any] = {"v": BATCH_VERSION, "s": semantic_label, "q": seq, "b": samples}
    if history:
        obj["h"] = history
    if recovered:
        obj["r"] = True
    if ended is not None:
        obj["e"] = ended
    body: bytes = _packb(obj, default=_encode_value)
    return body


class Batch(NamedTuple):
    """A batch as read: label, first sequence number, samples, history, resent, end reason."""

    label: str
    seq: int | None
    samples: list[Any]
    history: int = 0
    recovered: bool = False
    ended: str | None = None


def read_batch(body: bytes) -> Batch:
    """Read a batch body with all its fields; ValueError when it is not a batch of version 1.

    The samples themselves are checked by whoever uses them (each should be
    ``[value, valid_ns, available_ns]``).
    """
    try:
        obj = _unpackb(body, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several kinds on bad input
        raise ValueError(f"not msgpack: {type(exc).__name__}: {exc}") from None
    if type(obj) is not dict:
        raise ValueError("a batch is a msgpack map")
    v = obj.get("v")
    if type(v) is not int or v != BATCH_VERSION:
        raise ValueError(f"unsupported batch version {v!r} (this side reads {BATCH_VERSION})")
    label = obj.get("s")
    samples = obj.get("b")
    seq = obj.get("q")
    if type(label) is not str or type(samples) is not list:
        raise ValueError("a batch needs 's' (a string) and 'b' (an array)")
    if seq is not None and (type(seq) is not int or seq < 0):
        raise ValueError("'q' must be a non-negative integer")
    history = obj.get("h", 0)
    if type(history) is not int or history < 0:
        raise ValueError("'h' must be a non-negative integer")
    recovered = obj.get("r", False)
    if type(recovered) is not bool or (recovered and seq is None):
        raise ValueError("'r' must be a boolean, and a resent batch needs 'q'")
    ended = obj.get("e")
    if ended is not None and (type(ended) is not str or len(ended) > 1024):
        raise ValueError("'e' must be a string (why the sender ended the export)")
    return Batch(label, seq, samples, history, recovered, ended)


def unpack_batch(body: bytes) -> tuple[str, int | None, list[Any]]:
    """Read a batch body: ``(semantic label, first sequence number or None, samples)``.

    Raises ValueError when it is not a batch of version 1 (see `read_batch`).
    """
    batch = read_batch(body)
    return batch.label, batch.seq, batch.samples


# --------------------------------------------------------------------------- sessions


@runtime_checkable
class SessionsProvider(Protocol):
    """How the proxies seal and open batches: this platform's sessions with its peers."""

    async def ensure(self, peer: str) -> None:
        """Make sure there is a session to seal for ``peer`` (agree one if need be)."""
        ...

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal ``body`` for ``peer``; UnknownSession or Expired when one must be agreed."""
        ...

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """``(authenticated sender platform, body)``, or an AuthenticationError."""
        ...


class TableSessions:
    """Seals and opens with a `SessionTable`; ``agree(peer)``, if given, makes a session."""

    def __init__(
        self, table: SessionTable, agree: Callable[[str], Awaitable[None]] | None = None
    ) -> None:
        self.table = table
        self.agree = agree

    async def ensure(self, peer: str) -> None:
        """Agree a session with ``peer`` unless one can seal already."""
        if self.table.session_for(peer) is not None:
            return
        if self.agree is None:
            raise UnknownSession(f"no session with {peer!r}, and no way to agree one", peer)
        await self.agree(peer)

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal with the table's current session for ``peer``."""
        return self.table.seal_bytes(peer, body)

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Open with the table."""
        return self.table.open_bytes(envelope)


class InterfaceSessions(TableSessions):
    """The sessions of a platform's Interface Agent: agreed, renewed and recovered by it."""

    def __init__(self, agent: InterfaceAgent, *, renew_check: float = 1.0) -> None:
        super().__init__(agent.sessions, agent.agree)
        self.agent = agent
        self.renew_check = renew_check
        self._checked: dict[str, float] = {}

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal for ``peer``; now and then, have the agent renew a session that asks for it."""
        envelope = self.table.seal_bytes(peer, body)
        now = time.monotonic()
        if now - self._checked.get(peer, -1e9) >= self.renew_check:
            # what the agent's own send does per message, here once a second: batches
            # come by the thousand and the session's age changes slowly
            self._checked[peer] = now
            self.agent.renew_if_needed(peer)
        return envelope

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Open; a trusted peer sealing on a session we lost gets a new one agreed.

        What opens is shown to the owner while it watches; a plain envelope where
        encryption is required is audited (a misconfigured or downgrading peer).
        """
        try:
            frm, body = self.table.open_bytes(envelope)
        except UnknownSession as exc:
            if exc.platform is not None:
                self.agent.rehandshake(exc.platform)  # rate-limited by the agent
            raise
        except Unencrypted as exc:
            self.agent.audit_unauthenticated(
                exc.platform, f"{exc.code}: {exc.reason}", stage="stream"
            )
            raise
        if self.agent.mirroring:
            self.agent.mirror_bytes(frm, body)
        return frm, body


class PlainSessions:
    """No authentication at all: ``[1, from, to, body]``. For tests and local benchmarks only.

    ``trusted``, when given, is the set of senders accepted (others: UnknownPlatform).
    """

    def __init__(self, me: str, trusted: set[str] | None = None) -> None:
        self.me = check_name(me)
        self.trusted = trusted

    async def ensure(self, peer: str) -> None:
        """Nothing to agree."""

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Wrap ``body`` with sender and receiver."""
        envelope: bytes = _packb([1, self.me, peer, body])
        return envelope

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Unwrap, checking the receiver and (when set) the trusted senders."""
        try:
            env = _unpackb(envelope, raw=False)
        except Exception as exc:
            raise Malformed(f"not msgpack: {exc}") from None
        if type(env) is not list or len(env) != 4 or env[0] != 1:
            raise Malformed("a plain envelope is [1, from, to, body]")
        _, frm, to, body = env
        if type(frm) is not str or type(to) is not str or type(body) is not bytes:
            raise Malformed("a plain envelope is [1, from, to, body]")
        if to != self.me:
            raise Misdirected(f"envelope for {to!r} reached {self.me!r}", frm)
        if self.trusted is not None and frm not in self.trusted:
            raise UnknownPlatform(f"platform {frm!r} is not trusted", frm)
        return frm, body


# --------------------------------------------------------------------------- export


class Export:
    """One agreed stream to one receiver: its queue, its task and its counters.

    Counters: ``sent`` samples in ``batches`` published; ``dropped`` by reason
    (``queue-full``: the receiver's queue overflowed, oldest first; ``no-session``: no
    session could be agreed; ``send-failed``: the transport refused; ``unencodable``:
    a value msgpack cannot carry; ``too-large``: one sample over the batch size limit;
    ``lost-in-transit``: published, but reported missing by the receiver, less what was
    recovered; ``lease-expired``: what was still queued when the receiver's lease
    expired). With ``history`` N the receiver asks, after each gap, for the N samples
    before its end: they are resent from the last 2N + 256 kept here, each sequence
    number at most once, and no more than the receiver reports lost (``recovered``
    counts the samples resent; ``resend_refused`` the requests refused in whole or in
    part, by reason: ``not-a-gap``, ``over-loss``, ``already-resent``, ``rate``).
    ``last_heard``: the monotonic time of the receiver's latest report (or the export's
    start).
    """

    def __init__(
        self,
        proxy: ExportProxy,
        local_label: str,
        semantic_label: str,
        receiver: str,
        policy: Policy,
        queue_size: int,
        history: int = 0,
    ) -> None:
        self.local_label = local_label
        self.semantic_label = semantic_label
        self.receiver = receiver
        self.policy = policy
        self.key = (
            f"{wire_key(proxy.federation, 'stream', receiver)}/{proxy.platform}/{semantic_label}"
        )
        self.name = f"export[{proxy.platform}→{receiver}:{semantic_label}]"
        self.queue: deque[RawSample] = deque(maxlen=queue_size)
        self.sent = 0
        self.batches = 0
        self.dropped: dict[str, int] = {}
        self.lost_in_transit = 0  # the receiver's latest report of samples missing on the way
        self.history = history
        self.recovered = 0  # samples resent from the history because the receiver missed them
        self.last_heard = time.monotonic()
        self.last_error: str | None = None
        self.ended: str | None = None
        self.started = time.time()
        self.subscription: StreamSubscription | None = None
        self.task: asyncio.Task[None] | None = None
        self._proxy = proxy
        self._cap = queue_size
        self._seq = 0
        # samples numbered and then dropped here: the receiver sees them as a gap too, and
        # they must not be counted again when it reports its losses
        self._numbered_drops = 0
        # numbered ranges that failed to go out, while the history may still resend them
        self._failed: deque[tuple[int, int, str]] = deque(maxlen=_MAX_FAILED)
        self._waiter: asyncio.Future[None] | None = None
        self._backoff = 0.0
        # the last numbered samples: more than the receiver asks for, since the sender goes
        # on numbering while its request travels
        self._kept: deque[RawSample] = deque(maxlen=2 * history + _HISTORY_SLACK if history else 0)
        self._recover: list[tuple[int, int]] = []  # ranges the receiver asked to be resent
        self._resent_ranges: list[tuple[int, int]] = []  # numbers resent: never again
        # the receiver's latest loss report, as far as it can be true: what it may ask back
        self._claimed = 0
        self.resend_refused: dict[str, int] = {}
        self._refusals_pending: dict[str, int] = {}
        self._refusals_reported = -1e9
        self._keepalive_at = 0.0

    def __repr__(self) -> str:
        state = f"ended: {self.ended}" if self.ended else "active"
        return f"<{self.name} sent={self.sent} dropped={self.dropped_total} {state}>"

    @property
    def active(self) -> bool:
        """True until stopped, or until its local stream or the transport ended."""
        return self.ended is None

    @property
    def dropped_total(self) -> int:
        """Samples this export lost, all reasons."""
        return sum(self.dropped.values())

    def stats(self) -> dict[str, Any]:
        """A snapshot of the counters."""
        return {
            "name": self.name,
            "receiver": self.receiver,
            "semantic_label": self.semantic_label,
            "local_label": self.local_label,
            "sent": self.sent,
            "batches": self.batches,
            "queued": len(self.queue),
            "dropped": self.dropped_total,
            "dropped_by_reason": dict(self.dropped),
            "history": self.history,
            "recovered": self.recovered,
            "resend_refused": dict(self.resend_refused),
            "last_heard": self.last_heard,
            "last_error": self.last_error,
            "active": self.active,
            "ended": self.ended,
        }

    # -- the publisher's side: never waits -------------------------------------------------

    def _on_batch(self, batch: list[RawSample]) -> None:
        q = self.queue
        over = len(q) + len(batch) - self._cap
        q.extend(batch)  # a full deque drops from its left: the oldest go first
        if over > 0:
            self._drop("queue-full", over)
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def _drop(self, reason: str, count: int, error: str | None = None) -> None:
        if reason not in self.dropped:
            log.warning(
                "%s: dropping samples (%s)%s", self.name, reason, f": {error}" if error else ""
            )
        self.dropped[reason] = self.dropped.get(reason, 0) + count
        if error is not None:
            self.last_error = error
        on_drop = self._proxy.on_drop
        if on_drop is not None:
            try:
                on_drop(self, reason, count)
            except Exception:
                log.exception("%s: on_drop failed", self.name)

    # -- the export's own task -------------------------------------------------------------

    async def _run(self) -> None:
        q = self.queue
        sub = self.subscription
        batch_size = self._proxy.batch_size
        lease = self._proxy.lease
        # idle, look often enough to send keepalives and expire the lease in time
        idle = _IDLE_CHECK if lease is None else min(_IDLE_CHECK, lease / 3)
        try:
            while True:
                if lease is not None and self._lease_expired(lease):
                    await self._tell_ended()
                    return
                if self._recover:
                    await self._resend()
                if not q:
                    if sub is None or sub.closed:
                        self._end("the local stream ended")
                        return
                    if lease is not None:
                        await self._keepalive(idle)
                    await self._wait(idle)
                    continue
                n = min(len(q), batch_size)
                await self._send([q.popleft() for _ in range(n)])
                # a transport that never suspends (memory) would otherwise hold the loop
                await asyncio.sleep(0)
        except TransportClosed as exc:
            self._end(f"the transport closed: {exc}")
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            log.exception("%s: failed", self.name)
            self._end(f"failed: {type(exc).__name__}: {exc}")

    def _lease_expired(self, lease: float) -> bool:
        """End the export when its receiver has not reported for ``lease`` s (frozen, gone)."""
        silent = time.monotonic() - self.last_heard
        if silent <= lease:
            return False
        log.warning(
            "%s: lease expired: no report from %s for %.1f s; export stopped",
            self.name,
            self.receiver,
            silent,
        )
        self._drop("lease-expired", len(self.queue), f"no report for {silent:.1f} s")
        self.queue.clear()
        self._end(f"lease-expired: no report from {self.receiver} for {silent:.1f} s")
        return True

    async def _tell_ended(self) -> None:
        """Best effort: the receiver, if it comes back, learns the export ended and why."""
        body = pack_batch(self.semantic_label, [], self._seq, ended=self.ended or "ended")
        try:
            async with asyncio.timeout(1.0):
                envelope = await self._seal(body)
                await self._proxy.transport.publish(self.key, envelope)
        except (Exception, TimeoutError) as exc:
            log.debug("%s: telling %s the export ended: %s", self.name, self.receiver, exc)

    async def _keepalive(self, every: float) -> None:
        """An idle stream not acknowledged lately sends an empty batch: the receiver answers.

        It carries the next sequence number, so the receiver also learns of a lost tail.
        """
        now = time.monotonic()
        if now - self.last_heard < min(_KEEPALIVE_AFTER, every) or now - self._keepalive_at < every:
            return
        self._keepalive_at = now
        await self._send([])

    def _want_resent(self, first: int, end: int) -> None:
        """The receiver reports [first, end) missing: resend what a gap can have lost.

        That is: numbers this export gave out (``end`` at most the next one), at most
        ``history`` before the gap's end (what the receiver asks for), at most what the
        receiver reports lost, and only those not resent before. What is cut is counted
        in ``resend_refused``.
        """
        if not self.history:
            return
        if end <= first or first < 0 or end > self._seq:
            self._refuse_resend("not-a-gap")
            return
        lo = max(first, end - self.history)
        if lo > first:
            self._refuse_resend("not-a-gap")
        if end - lo > self._claimed:
            lo = end - self._claimed
            self._refuse_resend("over-loss")
            if lo >= end:
                return
        # the oldest number still kept: older ones are gone, not refused
        lo = max(lo, self._seq - len(self._kept))
        if lo >= end:
            return
        wanted = _uncovered(self._resent_ranges, lo, end)
        if sum(b - a for a, b in wanted) < end - lo:
            self._refuse_resend("already-resent")
        if not wanted:
            return
        self._recover += wanted
        del self._recover[:-_MAX_RECOVER]  # a flood of requests costs a bounded list
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def _refuse_resend(self, reason: str) -> None:
        """Count a resend request refused (in whole or in part) for ``reason``."""
        self.resend_refused[reason] = self.resend_refused.get(reason, 0) + 1
        self._refusals_pending[reason] = self._refusals_pending.get(reason, 0) + 1

    async def _resend(self) -> None:
        """Publish, as batches marked resent, the asked ranges the history still holds."""
        ranges, self._recover = self._recover, []
        kept = list(self._kept)
        oldest = self._seq - len(kept)  # the sequence number of kept[0]
        # forget what is no longer kept: it cannot be asked back anyway
        self._resent_ranges = [(a, b) for a, b in self._resent_ranges if b > oldest]
        for asked_first, asked_end in ranges:
            # asked twice before this ran: resent once
            for first, end in _uncovered(self._resent_ranges, max(asked_first, oldest), asked_end):
                samples = kept[first - oldest : end - oldest]
                start = first
                for body, count in self._pack_resent(first, samples):
                    try:
                        envelope = await self._seal(body)
                        await self._proxy.transport.publish(self.key, envelope)
                    except (asyncio.CancelledError, TransportClosed):
                        raise
                    except Exception as exc:  # the receiver may ask again
                        log.debug("%s: resending failed: %s", self.name, exc)
                        break
                    self.recovered += count
                    self._resent_ranges = _cover(self._resent_ranges, start, start + count)
                    if self._failed:
                        self._resent(start, start + count)
                    start += count

    def _numbered_drop(self, reason: str, first: int, count: int, exc: Exception) -> None:
        """Numbered samples that never left: counted here, not as lost in transit."""
        self._drop(reason, count, f"{type(exc).__name__}: {exc}")
        self._numbered_drops += count
        if self.history:  # they may be resent from the history: remember which
            self._failed.append((first, first + count, reason))

    def _resent(self, first: int, end: int) -> None:
        """Samples [first, end) went out from the history: no longer dropped here."""
        kept: list[tuple[int, int, str]] = []
        for a, b, reason in self._failed:
            lo, hi = max(a, first), min(b, end)
            if lo >= hi:
                kept.append((a, b, reason))
                continue
            n = hi - lo
            self._numbered_drops -= n
            left = self.dropped.get(reason, 0) - n
            if left > 0:
                self.dropped[reason] = left
            else:
                self.dropped.pop(reason, None)
            if a < lo:
                kept.append((a, lo, reason))
            if hi < b:
                kept.append((hi, b, reason))
        self._failed = deque(kept, maxlen=_MAX_FAILED)

    def _pack_resent(self, first: int, samples: list[RawSample]) -> list[tuple[bytes, int]]:
        """Resent bodies of at most ``max_batch_bytes``, numbered from ``first``."""
        body = pack_batch(self.semantic_label, samples, first, history=self.history, recovered=True)
        if len(body) <= self._proxy.max_batch_bytes or len(samples) == 1:
            return [(body, len(samples))]
        half = len(samples) // 2
        return self._pack_resent(first, samples[:half]) + self._pack_resent(
            first + half, samples[half:]
        )

    async def _wait(self, timeout: float) -> None:
        fut = asyncio.get_running_loop().create_future()
        self._waiter = fut
        try:
            async with asyncio.timeout(timeout):
                await fut
        except TimeoutError:
            pass
        finally:
            self._waiter = None

    async def _send(self, samples: list[RawSample]) -> None:
        proxy = self._proxy
        packed = self._pack(samples)
        first = self._seq - sum(count for _, count in packed)  # numbered as packed
        for body, count in packed:
            start, first = first, first + count
            try:
                envelope = await self._seal(body)
            except (asyncio.CancelledError, TransportClosed):
                raise
            except Exception as exc:  # no session: the receiver is gone, or refuses us
                if count:
                    self._numbered_drop("no-session", start, count, exc)
                self._backoff = min(max(2 * self._backoff, _BACKOFF_MIN), _BACKOFF_MAX)
                # meanwhile the queue keeps the newest samples, the oldest are dropped
                await asyncio.sleep(self._backoff)
                continue
            try:
                await proxy.transport.publish(self.key, envelope)
            except TransportClosed:
                raise
            except Exception as exc:
                if count:
                    self._numbered_drop("send-failed", start, count, exc)
                continue
            self._backoff = 0.0
            if count:
                self.sent += count
                self.batches += 1

    async def _seal(self, body: bytes) -> bytes:
        sessions = self._proxy.sessions
        try:
            return sessions.seal_bytes(self.receiver, body)
        except (UnknownSession, Expired):
            async with asyncio.timeout(self._proxy.agree_timeout):
                await sessions.ensure(self.receiver)
            return sessions.seal_bytes(self.receiver, body)

    def _pack(self, samples: list[RawSample]) -> list[tuple[bytes, int]]:
        """Bodies of at most ``max_batch_bytes``: ``(body, sample count)``; bad samples dropped."""
        label = self.semantic_label
        history = self.history
        if not samples:  # a keepalive
            return [(pack_batch(label, [], self._seq, history=history), 0)]
        try:
            body = pack_batch(label, samples, self._seq, history=history)
        except (TypeError, ValueError, OverflowError):
            good = []
            for s in samples:
                try:
                    _packb(s, default=_encode_value)
                except (TypeError, ValueError, OverflowError) as exc:
                    self._drop("unencodable", 1, f"{type(exc).__name__}: {exc}")
                else:
                    good.append(s)
            if not good:
                return []
            samples = good
            body = pack_batch(label, samples, self._seq, history=history)
        if len(body) > self._proxy.max_batch_bytes:
            if len(samples) == 1:
                self._drop("too-large", 1, f"one sample of {len(body)} bytes")
                return []
            half = len(samples) // 2
            return self._pack(samples[:half]) + self._pack(samples[half:])
        self._seq += len(samples)
        if history:
            self._kept.extend(samples)
        return [(body, len(samples))]

    def _end(self, why: str) -> None:
        if self.ended is None:
            self.ended = why
            if why != "stopped":
                self._proxy.ended.append(self)
        if self.subscription is not None:
            self.subscription.close()
        self._proxy._forget(self)


class ExportProxy:
    """Pushes agreed local streams to receiving platforms, each receiver independently.

    ``sessions`` seals each batch for its receiver (`InterfaceSessions` on a platform).
    Per export: a queue of ``queue_size`` samples, batches of at most ``batch_size``
    samples and ``max_batch_bytes`` bytes; a session is awaited at most
    ``agree_timeout`` s. ``on_drop(export, reason, count)`` is told of every loss.

    Lease: receivers' import proxies report on every stream they receive every 0.5 s;
    an export whose receiver has not reported for ``lease`` s (frozen, cut off, gone
    without a word) is ended (``ended`` ``"lease-expired: …"``, its queue counted as
    dropped for ``lease-expired``, ``on_drop`` told, a warning logged) and listed in
    ``ended`` (the latest exports that ended by themselves). None: no lease.
    Use as an async context manager, or call ``aclose``: it stops every export.
    """

    def __init__(
        self,
        platform_name: str,
        federation: str,
        transport: Transport,
        instance: DyKnowInstance,
        sessions_provider: SessionsProvider,
        *,
        queue_size: int = 8192,
        batch_size: int = 256,
        max_batch_bytes: int = 64 * 1024,
        agree_timeout: float = 5.0,
        on_drop: OnDrop | None = None,
        lease: float | None = 10.0,
    ) -> None:
        if queue_size < 1 or batch_size < 1 or max_batch_bytes < 256:
            raise ValueError("queue_size and batch_size must be >= 1, max_batch_bytes >= 256")
        if lease is not None and not lease > 0:
            raise ValueError(f"lease must be a positive number of seconds or None, not {lease!r}")
        self.platform = check_name(platform_name)
        self.federation = check_name(federation, "federation")
        self.transport = transport
        self.instance = instance
        self.sessions = sessions_provider
        self.queue_size = queue_size
        self.batch_size = batch_size
        self.max_batch_bytes = max_batch_bytes
        self.agree_timeout = agree_timeout
        self.on_drop = on_drop
        self.lease = lease
        self.ended: deque[Export] = deque(maxlen=256)
        self._exports: dict[tuple[str, str], Export] = {}
        self._reports: asyncio.Task[None] | None = None
        self.reports_refused = 0  # loss reports that did not open or parse
        self._resend_buckets: dict[str, TokenBucket] = {}  # per receiver (authenticated)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def start_exporting(
        self,
        local_label: str,
        semantic_label: str,
        receiver: str,
        policy: Policy | None = None,
        *,
        history: int = 0,
    ) -> Export:
        """Subscribe to ``local_label`` with ``policy``, push it to ``receiver`` as semantic label.

        ``history`` N keeps the last N samples sent, to resend those the receiver reports
        missing (a partition, a congested link). Call on the event loop. Raises
        UnknownLabelError or PolicyError from the instance, ValueError for a bad name, a
        bad history or when this label already goes to that receiver (stop that first).
        """
        check_name(receiver)
        check_semantic_label(semantic_label)
        if type(history) is not int or not 0 <= history <= _MAX_HISTORY:
            raise ValueError(f"history must be an integer 0-{_MAX_HISTORY}, not {history!r}")
        if receiver == self.platform:
            raise ValueError("a platform does not export to itself")
        if (receiver, semantic_label) in self._exports:
            raise ValueError(f"{semantic_label!r} is already exported to {receiver!r}")
        loop = asyncio.get_running_loop()
        policy = policy or Policy()
        export = Export(
            self, local_label, semantic_label, receiver, policy, self.queue_size, history
        )
        # subscribed before the task exists: history a past 'start' replays is queued too
        export.subscription = self.instance.subscribe(
            local_label, policy, callback=export._on_batch
        )
        export.task = loop.create_task(export._run(), name=export.name)
        self._exports[(receiver, semantic_label)] = export
        if self._reports is None:
            self._reports = loop.create_task(
                self._receive_reports(), name=f"export[{self.platform}].loss-reports"
            )
        return export

    async def _receive_reports(self) -> None:
        """Read receivers' reports: their lease, what they lost, what they want resent.

        Each report is ``{"v": 1, "lost": {label: total}, "resend": {label: [first, end]}}``
        (``resend`` optional). Every label named renews that export's lease. ``lost`` is
        the receiver's running total of samples missing from its numbering and not
        recovered: the change is counted on the export as ``lost-in-transit`` (and
        ``on_drop`` told), so the provider learns of losses only receivers see.
        """
        key = wire_key(self.federation, "stream-report", self.platform) + "/*"
        sub = await self.transport.subscribe(key, buffer_size=1024)
        try:
            async for item in sub:
                try:
                    sender, body = self.sessions.open_bytes(item.payload)
                    report = msgpack.unpackb(body, raw=False)
                    lost = report["lost"]
                    resend = report.get("resend", {})
                    if (
                        item.key.rpartition("/")[2] != sender
                        or report.get("v") != BATCH_VERSION
                        or type(lost) is not dict
                        or type(resend) is not dict
                    ):
                        raise ValueError("not a loss report from its sender")
                except Exception:
                    self.reports_refused += 1
                    continue
                now = time.monotonic()
                for label, total in lost.items():
                    export = self._exports.get((sender, label))
                    if export is None or type(total) is not int:
                        continue
                    export.last_heard = now
                    self._count_lost(export, total)
                for label, wanted in resend.items():
                    export = self._exports.get((sender, label))
                    if export is None or not export.history:
                        continue
                    if not self._resend_bucket(sender, now).take(now):
                        export._refuse_resend("rate")
                    elif (
                        type(wanted) is list
                        and len(wanted) == 2
                        and all(type(x) is int for x in wanted)
                    ):
                        export._want_resent(wanted[0], wanted[1])
                    else:
                        export._refuse_resend("not-a-gap")
                    self._audit_resend_refusals(export, now)
        finally:
            sub.close()

    def _resend_bucket(self, receiver: str, now: float) -> TokenBucket:
        """The resend requests ``receiver`` may still make (one bucket per trusted platform)."""
        bucket = self._resend_buckets.get(receiver)
        if bucket is None:
            bucket = self._resend_buckets[receiver] = TokenBucket(RESEND_RATE, RESEND_BURST, now)
        return bucket

    def _audit_resend_refusals(self, export: Export, now: float) -> None:
        """Audit an export's refused resend requests, at most once per interval, with counts."""
        pending = export._refusals_pending
        if not pending or now - export._refusals_reported < RESEND_REPORT_INTERVAL:
            return
        export._refusals_pending = {}
        export._refusals_reported = now
        count = sum(pending.values())
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(pending.items()))
        log.info("%s: %d resend request(s) refused (%s)", export.name, count, reasons)
        sessions = self.sessions
        if isinstance(sessions, InterfaceSessions):
            sessions.agent.audit.record(
                verdict="refused",
                stage="resend",
                count=count,
                by_reason=pending,
                **{"from": export.receiver},
                reason=(
                    f"resend requests for {export.semantic_label!r} refused in whole or in "
                    f"part: {count} ({reasons}); each sample is resent once, within history "
                    f"{export.history} and the receiver's reported losses, at most "
                    f"{RESEND_RATE:g} requests/s"
                ),
            )

    @staticmethod
    def _count_lost(export: Export, total: int) -> None:
        # a receiver cannot have missed more than this export numbered
        total = min(max(total, 0), export._seq)
        export._claimed = total
        transit = total - export._numbered_drops
        delta = transit - export.lost_in_transit
        if delta > 0:
            export.lost_in_transit = transit
            export._drop("lost-in-transit", delta)
        elif delta < 0 and export.dropped.get("lost-in-transit"):
            # reported lost, then recovered from the history: no longer a loss
            export.lost_in_transit = max(transit, 0)
            left = export.dropped["lost-in-transit"] + delta
            if left > 0:
                export.dropped["lost-in-transit"] = left
            else:
                del export.dropped["lost-in-transit"]

    async def stop(self, export: Export) -> None:
        """End ``export``: unsubscribe, drop what is queued, wait for its task to finish."""
        export._end("stopped")
        task = export.task
        if task is not None and task is not asyncio.current_task():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def stop_all(self, receiver: str | None = None) -> list[Export]:
        """Stop every export to ``receiver`` (every export when None); the stopped ones."""
        stopped = self.exports(receiver)
        for export in stopped:
            await self.stop(export)
        return stopped

    def exports(self, receiver: str | None = None) -> list[Export]:
        """The active exports (to ``receiver`` only, when given)."""
        return [e for (r, _), e in self._exports.items() if receiver is None or r == receiver]

    def find(self, receiver: str, semantic_label: str) -> Export | None:
        """The active export of ``semantic_label`` to ``receiver``, if any."""
        return self._exports.get((receiver, semantic_label))

    def stats(self) -> list[dict[str, Any]]:
        """Every active export's counters."""
        return [e.stats() for e in self._exports.values()]

    async def aclose(self) -> None:
        """Stop every export and stop listening to loss reports."""
        await self.stop_all()
        task, self._reports = self._reports, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def _forget(self, export: Export) -> None:
        key = (export.receiver, export.semantic_label)
        if self._exports.get(key) is export:
            del self._exports[key]


# --------------------------------------------------------------------------- import


class Import:
    """What arrives for one (sender, semantic label): where it lands, and its counters.

    ``batches`` payloads arrived; ``received`` samples were read from authentic batches,
    ``injected`` added to the local stream; ``lost`` samples never arrived (gaps in the
    sender's numbering: dropped on the way, or cut off) and were not recovered;
    ``recovered`` arrived late, resent from the sender's history; ``gaps`` counts the
    gaps seen; ``dropped_batches`` / ``dropped_samples`` by reason. ``local_label`` is
    None for a stream that was never agreed.
    """

    def __init__(self, sender: str, semantic_label: str, local_label: str | None) -> None:
        self.sender = sender
        self.semantic_label = semantic_label
        self.local_label = local_label
        self.source: Source | None = None
        self.batches = 0
        self.received = 0
        self.injected = 0
        self.lost = 0
        self.recovered = 0
        self.gaps = 0
        self.history = 0  # what the sender says it keeps to resend
        self.dropped_batches: dict[str, int] = {}
        self.dropped_samples: dict[str, int] = {}
        self.ended = False
        self.first_arrival: int | None = None
        self.last_arrival: int | None = None
        self._last_ta = -(2**63)
        self._next_seq: int | None = None
        self._missing: list[tuple[int, int]] = []  # [first, end) not arrived, may be resent
        self._asks = 0  # resend requests for them so far
        self._lost_base = 0  # `lost` when the sender's current numbering began

    @property
    def lost_now(self) -> int:
        """Samples lost (and not recovered) from the sender's current numbering: reported."""
        return max(self.lost - self._lost_base, 0)

    def __repr__(self) -> str:
        return (
            f"<Import {self.sender}:{self.semantic_label} -> {self.local_label} "
            f"injected={self.injected}{' ended' if self.ended else ''}>"
        )

    @property
    def location(self) -> str:
        """The instance location its stream lives at (one per sender platform)."""
        return f"import/{self.sender}"

    def stats(self) -> dict[str, Any]:
        """A snapshot of the counters."""
        return {
            "sender": self.sender,
            "semantic_label": self.semantic_label,
            "local_label": self.local_label,
            "batches": self.batches,
            "received": self.received,
            "injected": self.injected,
            "lost": self.lost,
            "recovered": self.recovered,
            "gaps": self.gaps,
            "dropped_batches": dict(self.dropped_batches),
            "dropped_samples": dict(self.dropped_samples),
            "ended": self.ended,
            "first_arrival": self.first_arrival,
            "last_arrival": self.last_arrival,
        }

    def _drop_batch(self, reason: str) -> None:
        if reason not in self.dropped_batches:
            log.warning(
                "import %s:%s: dropping batches (%s)", self.sender, self.semantic_label, reason
            )
        self.dropped_batches[reason] = self.dropped_batches.get(reason, 0) + 1

    def _drop_samples(self, reason: str, count: int) -> None:
        if reason not in self.dropped_samples:
            log.warning(
                "import %s:%s: dropping samples (%s)", self.sender, self.semantic_label, reason
            )
        self.dropped_samples[reason] = self.dropped_samples.get(reason, 0) + count


class ImportProxy:
    """Receives the streams other platforms export to this one and adds them locally.

    ``translate(sender, semantic_label)`` names the local label (None: never agreed, the
    batch is dropped); `expect` agrees one in advance. Each sender's streams live at
    location ``import/<sender>``, made with ``cache``; the first sample creates the source.
    When a sender's liveliness token goes, its streams are ended (their subscribers'
    iterators end; with ``keep_ended`` the label and its cache stay queryable) and
    ``on_sender_gone(sender, semantic_labels)`` is told. When a sender ends an export by
    itself (its lease expired: we did not report in time) and says so, the stream ends
    and ``on_export_ended(sender, semantic_label)`` is told. Batches dropped whole
    (never agreed, not authentic, under another sender's name) are summed up per sender
    and reason and told to ``on_refused(sender, reason, batches, samples)`` once per
    ``report_interval`` (an audit, bounded whatever the flood). Use as an async context
    manager (or ``start`` / ``aclose``).
    """

    def __init__(
        self,
        platform_name: str,
        federation: str,
        transport: Transport,
        instance: DyKnowInstance,
        sessions_provider: SessionsProvider,
        translate: Translate,
        *,
        on_sender_gone: OnSenderGone | None = None,
        on_export_ended: OnExportEnded | None = None,
        on_refused: OnRefused | None = None,
        cache: CacheSpec | None = None,
        keep_ended: bool = True,
        buffer_size: int = 1024,
        max_strays: int = 1024,
        report_interval: float = 0.5,
        presence: Callable[[], TransportSubscription[Presence]] | None = None,
    ) -> None:
        self.platform = check_name(platform_name)
        self.federation = check_name(federation, "federation")
        self.transport = transport
        self.instance = instance
        self.sessions = sessions_provider
        self.translate = translate
        self.on_sender_gone = on_sender_gone
        self.on_export_ended = on_export_ended
        self.on_refused = on_refused
        # (sender, reason) -> [batches, samples] not yet told to on_refused (bounded keys)
        self._refused: dict[tuple[str, str], list[int]] = {}
        self.cache = cache
        self.keep_ended = keep_ended
        self.buffer_size = buffer_size  # batches, not samples: ~256 k samples by default
        self.max_strays = max_strays
        self.report_interval = report_interval
        # where senders' comings and goings are learnt: an authenticated source (the
        # global directory's `watch_presence`) rather than raw presence, which on MQTT
        # anyone can clear
        self._presence = presence
        self._prefix = wire_key(self.federation, "stream", self.platform) + "/"
        self._imports: dict[tuple[str, str], Import] = {}
        # counters of what matches no agreed import (unauthenticated claims included):
        # bounded, since anyone on the network can invent keys
        self._strays: dict[tuple[str, str], Import] = {}
        self._gone: set[str] = set()
        self._subs: list[TransportSubscription[Message] | TransportSubscription[Presence]] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._state = "unopened"

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def start(self) -> None:
        """Watch senders' presence and receive this platform's streams (tasks owned here)."""
        if self._state != "unopened":
            raise RuntimeError(f"the import proxy is {self._state}; it cannot start again")
        self._state = "started"
        if self._presence is not None:
            presence = self._presence()
        else:
            presence = await self.transport.watch_presence(
                wire_key(self.federation, "alive", "*"), history=False
            )
        self._subs.append(presence)
        streams = await self.transport.subscribe(
            self._prefix + "*/**", buffer_size=self.buffer_size
        )
        self._subs.append(streams)
        self._spawn(self._watch(presence), f"import[{self.platform}].presence")
        self._spawn(self._receive(streams), f"import[{self.platform}].receive")
        self._spawn(self._report_losses(), f"import[{self.platform}].loss-reports")

    def _spawn(self, coro: Any, name: str) -> None:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def aclose(self) -> None:
        """Stop receiving and end every imported stream."""
        if self._state == "closed":
            return
        self._state = "closed"
        for sub in self._subs:
            sub.close()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for rec in self._imports.values():
            self._end(rec)

    async def _report_losses(self) -> None:
        """Report to each sender, every ``report_interval``, on every stream it sends here.

        The report is the sender's lease (an export not reported on is ended there) and
        carries this side's running total of its samples that never arrived.
        """
        while True:
            await asyncio.sleep(self.report_interval)
            self._tell_refused()
            reports: dict[str, dict[str, Any]] = {}
            for rec in self._imports.values():
                # an ended import whose sender is back is reported on too: a stream created
                # again must not lose its lease while it is idle
                if not rec.batches or rec.sender in self._gone:
                    continue
                report = reports.setdefault(rec.sender, {"v": BATCH_VERSION, "lost": {}})
                report["lost"][rec.semantic_label] = rec.lost_now
                if rec._missing and rec._asks < _MAX_ASKS:
                    # the resent batches may have been dropped on the way too: ask again
                    rec._asks += 1
                    span = [rec._missing[0][0], rec._missing[-1][1]]
                    report.setdefault("resend", {})[rec.semantic_label] = span
            for sender, report in reports.items():
                await self._report(sender, report)

    async def _report(self, sender: str, report: dict[str, Any]) -> None:
        body = msgpack.packb(report)
        topic = f"{wire_key(self.federation, 'stream-report', sender)}/{self.platform}"
        try:
            await self.transport.publish(topic, self.sessions.seal_bytes(sender, body))
        except Exception as exc:  # the sender is going: its report can wait or go
            log.debug("import[%s]: report to %s: %s", self.platform, sender, exc)

    def _ask_resend(self, rec: Import, first: int, end: int) -> None:
        """Ask the sender now for the samples [first, end) that did not arrive."""
        report = {
            "v": BATCH_VERSION,
            "lost": {rec.semantic_label: rec.lost_now},
            "resend": {rec.semantic_label: [first, end]},
        }
        self._spawn(self._report(rec.sender, report), f"import[{self.platform}].resend")

    # -- agreements ---------------------------------------------------------------------

    def expect(self, sender: str, semantic_label: str, local_label: str) -> Import:
        """Agree in advance that ``sender``'s ``semantic_label`` lands in ``local_label``.

        DuplicateLabelError when ``local_label`` is published by something else here;
        ValueError when this stream already lands in another live label.
        """
        check_name(sender)
        check_semantic_label(semantic_label)
        key = (sender, semantic_label)
        rec = self._imports.get(key)
        if rec is not None and rec.local_label == local_label:
            return rec
        if rec is not None and rec.source is not None and not rec.ended:
            raise ValueError(
                f"{semantic_label!r} from {sender!r} already lands in {rec.local_label!r}"
            )
        if self.instance.has_label(local_label) and not self._owns(local_label):
            raise DuplicateLabelError(f"label {local_label!r} is already published here")
        if rec is None:
            rec = self._new_import(sender, semantic_label, local_label)
        else:
            rec.local_label = local_label
        return rec

    def forget(self, sender: str, semantic_label: str) -> Import | None:
        """Undo an agreement: end the stream; later batches count as never agreed."""
        rec = self._imports.pop((sender, semantic_label), None)
        if rec is not None:
            self._end(rec)
        return rec

    def get(self, sender: str, semantic_label: str) -> Import | None:
        """The import of ``sender``'s ``semantic_label``, if agreed."""
        return self._imports.get((sender, semantic_label))

    def imports(self, sender: str | None = None) -> list[Import]:
        """The agreed imports (from ``sender`` only, when given)."""
        return [r for r in self._imports.values() if sender is None or r.sender == sender]

    def stats(self) -> dict[str, Any]:
        """Every import's counters, those of unagreed traffic, and the totals."""
        imports = [r.stats() for r in self._imports.values()]
        strays = [r.stats() for r in self._strays.values()]
        totals: dict[str, Any] = {
            "batches": 0,
            "received": 0,
            "injected": 0,
            "lost": 0,
            "dropped_batches": {},
            "dropped_samples": {},
        }
        for s in imports + strays:
            for k in ("batches", "received", "injected", "lost"):
                totals[k] += s[k]
            for k in ("dropped_batches", "dropped_samples"):
                for reason, n in s[k].items():
                    totals[k][reason] = totals[k].get(reason, 0) + n
        return {"imports": imports, "strays": strays, "totals": totals}

    def _owns(self, local_label: str) -> bool:
        """Whether ``local_label`` is one of our imports, live or ended."""
        if any(
            r.local_label == local_label and r.source is not None for r in self._imports.values()
        ):
            return True
        return bool(self._ended_sources(local_label, None))

    def _ended_sources(self, local_label: str, name: str | None) -> list[str]:
        """Our ended import sources named ``name`` or publishing ``local_label``."""
        return [
            p.name
            for p in self.instance.processes.values()
            if isinstance(p, Source)
            and not p.running
            and p.name.startswith("import[")
            and (p.name == name or p.label == local_label)
        ]

    def _new_import(self, sender: str, semantic_label: str, local_label: str) -> Import:
        rec = Import(sender, semantic_label, local_label)
        stray = self._strays.pop((sender, semantic_label), None)
        if stray is not None:  # what arrived before the agreement stays counted
            rec.batches = stray.batches
            rec.received = stray.received
            rec.dropped_batches = stray.dropped_batches
            rec.dropped_samples = stray.dropped_samples
        self._imports[(sender, semantic_label)] = rec
        return rec

    def _refuse(self, sender: str, label: str, reason: str) -> None:
        """Count one whole batch dropped, and why, against what it claimed to be."""
        counts = self._counts(sender, label)
        counts.batches += 1
        counts._drop_batch(reason)
        self._note_refused(sender, reason, 0)

    def _note_refused(self, sender: str, reason: str, samples: int) -> None:
        """Sum up a dropped batch for the next `on_refused` (bounded: a flood costs nothing)."""
        if self.on_refused is None:
            return
        key = (sender, reason)
        entry = self._refused.get(key)
        if entry is None:
            if len(self._refused) >= _MAX_REFUSED_KEYS:
                key = ("*", reason)
                entry = self._refused.get(key)
            if entry is None:
                entry = self._refused[key] = [0, 0]
        entry[0] += 1
        entry[1] += samples

    def _tell_refused(self) -> None:
        """Tell ``on_refused`` what was dropped since last time, one call per sender and reason."""
        hook, refused = self.on_refused, self._refused
        if hook is None or not refused:
            return
        self._refused = {}
        for (sender, reason), (batches, samples) in refused.items():
            try:
                hook(sender, reason, batches, samples)
            except Exception:
                log.exception("import[%s]: on_refused failed", self.platform)

    def _counts(self, sender: str, label: str) -> Import:
        """Where to count a payload for (sender, label): its import, or a bounded stray."""
        key = (sender, label)
        rec = self._imports.get(key)
        if rec is not None:
            return rec
        rec = self._strays.get(key)
        if rec is None:
            if len(self._strays) >= self.max_strays:
                key = ("*", "*")
                rec = self._strays.get(key)
            if rec is None:
                rec = self._strays[key] = Import(key[0], key[1], None)
        return rec

    # -- receiving ----------------------------------------------------------------------

    async def _receive(self, sub: TransportSubscription[Message]) -> None:
        handle = self._handle
        n = 0
        async for msg in sub:
            try:
                handle(msg.key, msg.payload)
            except Exception:  # never let one payload end the loop
                log.exception("import[%s]: handling a payload on %s failed", self.platform, msg.key)
            n += 1
            if n % _YIELD_EVERY == 0:
                # the inbox hands out what is queued without suspending: let others run
                await asyncio.sleep(0)

    def _handle(self, key: str, payload: bytes) -> None:
        """One payload: open, check, decode, translate, inject; or drop and count why."""
        sender, _, label = key[len(self._prefix) :].partition("/")
        if not sender or not label:
            self._counts(sender or "?", label or "?")._drop_batch("malformed")
            return
        try:
            frm, body = self.sessions.open_bytes(payload)
        except AuthenticationError as exc:
            self._refuse(sender, label, exc.code)
            return
        except Exception:
            self._refuse(sender, label, "malformed")
            return
        if frm != sender:
            # authentic, but published under another platform's name: trust neither
            self._refuse(sender, label, "wrong-sender")
            return
        try:
            batch = read_batch(body)
        except ValueError:
            self._refuse(frm, label, "malformed")
            return
        semantic, samples = batch.label, batch.samples
        if semantic != label:
            self._refuse(frm, label, "wrong-label")
            return
        rec = self._imports.get((frm, semantic))
        if rec is None:
            local = self._translate(frm, semantic)
            if local is None:
                counts = self._counts(frm, semantic)
                counts.batches += 1
                counts.received += len(samples)
                counts._drop_samples("unagreed", len(samples))
                self._note_refused(frm, "unagreed", len(samples))
                return
            rec = self._new_import(frm, semantic, local)
        rec.batches += 1
        rec.received += len(samples)
        if frm in self._gone:
            # still in flight when the sender's token went: its streams are ended
            rec._drop_samples("sender-gone", len(samples))
            return
        if batch.recovered:
            assert batch.seq is not None  # read_batch checks it
            self._inject_resent(rec, batch.seq, samples)
            return
        rec.history = batch.history
        self._inject(rec, batch.seq, samples)
        if batch.ended is not None and not rec.ended:
            # the sender ended the export by itself (we did not report in time)
            log.warning("import[%s]: %s ended %s: %s", self.platform, frm, semantic, batch.ended)
            self._end(rec)
            if self.on_export_ended is not None:
                self._spawn(
                    self._tell("on_export_ended", frm, semantic), f"import[{self.platform}].ended"
                )

    def _translate(self, sender: str, semantic: str) -> str | None:
        try:
            return self.translate(sender, semantic)
        except Exception:
            log.exception("import[%s]: translate(%r, %r) failed", self.platform, sender, semantic)
            return None

    def _inject(self, rec: Import, seq: int | None, samples: list[Any]) -> None:
        """Count gaps (asking for a resend when the sender keeps history), then add."""
        n = len(samples)
        if seq is not None:
            expected = rec._next_seq
            if expected is not None and seq > expected:
                rec.lost += seq - expected
                rec.gaps += 1
                if rec.history:
                    first = max(expected, seq - rec.history)  # older ones are not kept
                    rec._missing.append((first, seq))
                    del rec._missing[:-_MAX_MISSING]
                    rec._asks = 0
                    self._ask_resend(rec, first, seq)
            elif expected is not None and seq < expected:
                # the sender restarted the export: a new numbering, whose losses alone
                # its reports count (the new export's own counters start at 0)
                rec._missing.clear()
                rec._lost_base = rec.lost
            rec._next_seq = seq + n
        if not n:  # a keepalive
            return
        self._add(rec, samples)

    def _inject_resent(self, rec: Import, first: int, samples: list[Any]) -> None:
        """Add resent samples that are still missing here; count them recovered."""
        wanted: list[Any] = []
        missing: list[tuple[int, int]] = []
        end = first + len(samples)
        for a, b in rec._missing:
            lo, hi = max(a, first), min(b, end)
            if lo >= hi:
                missing.append((a, b))
                continue
            wanted += samples[lo - first : hi - first]
            if a < lo:
                missing.append((a, lo))
            if hi < b:
                missing.append((hi, b))
        rec._missing = missing
        if not wanted:
            rec._drop_samples("duplicate", len(samples))
            return
        if len(wanted) < len(samples):
            rec._drop_samples("duplicate", len(samples) - len(wanted))
        injected = rec.injected
        self._add(rec, wanted)
        got = rec.injected - injected
        rec.recovered += got
        rec.lost -= got

    def _add(self, rec: Import, samples: list[Any]) -> None:
        """Add the samples: valid time kept, available time = arrival here (unique, rising)."""
        n = len(samples)
        now = self.instance.clock.now()
        if rec.first_arrival is None:
            rec.first_arrival = now
        rec.last_arrival = now
        ta = now if now > rec._last_ta else rec._last_ta + 1
        out: list[RawSample] = []
        append = out.append
        for s in samples:
            if type(s) is list and len(s) == 3 and type(s[1]) is int:
                append((s[0], s[1], ta))
                ta += 1
        if len(out) != n:
            rec._drop_samples("malformed", n - len(out))
        if not out:
            return
        source = rec.source
        if source is None or not source.running or source.generator.closed:
            source = self._open_source(rec)
            if source is None:
                rec._drop_samples("label-taken", len(out))
                return
        try:
            source.push_batch(out, ordered=True)
        except Exception as exc:
            log.warning("import %s:%s: not injected: %s", rec.sender, rec.semantic_label, exc)
            rec._drop_samples("rejected", len(out))
            return
        rec._last_ta = ta - 1
        rec.injected += len(out)

    def _open_source(self, rec: Import) -> Source | None:
        """The first sample's source (again after an end), at location ``import/<sender>``."""
        instance = self.instance
        assert rec.local_label is not None
        if rec.location not in instance.locations:
            instance.add_location(rec.location, cache=self.cache)
        name = f"import[{rec.sender}:{rec.semantic_label}]"
        for stale in self._ended_sources(rec.local_label, name):
            instance.remove_process(stale)  # an ended stream of ours: make room for a new one
        try:
            source = instance.add_source(rec.local_label, name=name, location=rec.location)
        except (DuplicateLabelError, ProcessError) as exc:
            log.warning("import %s:%s: %s", rec.sender, rec.semantic_label, exc)
            return None
        rec.source = source
        rec.ended = False
        return source

    # -- membership ---------------------------------------------------------------------

    async def _watch(self, presence: TransportSubscription[Presence]) -> None:
        async for change in presence:
            sender = change.key.rpartition("/")[2]
            if sender == self.platform:
                continue
            if change.alive:
                self._gone.discard(sender)
                continue
            recs = [r for r in self._imports.values() if r.sender == sender]
            if not recs:
                continue
            self._gone.add(sender)
            labels = []
            for rec in recs:
                if not rec.ended:
                    self._end(rec)
                    labels.append(rec.semantic_label)
            if labels:
                await self._tell("on_sender_gone", sender, labels)

    async def _tell(self, hook_name: str, *args: Any) -> None:
        """Call the user's hook (sync or async); its failure is logged, never ours."""
        hook = getattr(self, hook_name)
        if hook is None:
            return
        try:
            result = hook(*args)
            if inspect.isawaitable(result):
                await result
        except Exception:
            log.exception("import[%s]: %s%r failed", self.platform, hook_name, args)

    def _end(self, rec: Import) -> None:
        """Mark a stream ended: its subscribers' iterators end; the cache stays if kept."""
        rec.ended = True
        source = rec.source
        if source is None:
            return
        source.running = False
        if self.keep_ended:
            source.generator.close()
        else:
            with contextlib.suppress(ProcessError):
                self.instance.remove_process(source.name)
            rec.source = None
