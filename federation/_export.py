"""The export side: agreed local streams pushed to receiving platforms, each on its own.

Once the Federation Agents agreed a stream, the provider's `ExportProxy` subscribes to the
local label with the agreed policy and pushes what it emits to the receiver as sealed
batches (`federation._batch`) on
``dyknow/<fed>/v1/stream/<receiver>/<sender>/<semantic-label>``.

Isolation: every export has its own bounded queue and its own task. The local instance
hands samples to the queue and returns at once. When an export's path is clear (its task
idle, a session to seal with, nothing to resend, not backing off, a transport whose put
never waits), its batch goes out in one call per loop turn that packs, seals and
publishes every such export's batch in turn (`ExportProxy._flush`): no task woken per
stream and sample. Anything else (a session to agree, a resend, a backoff, a lease to
end, a keepalive) is the export's task's, woken as the samples come. A receiver that is
slow, frozen or gone costs its own queue's oldest samples (counted and reported), never
the instance's time or another receiver's.

Faults: a receiver reports on every stream it gets every 0.5 s, with what never arrived
(gaps in the sender's numbering). The reports are the export's lease (an export not
reported on for ``lease`` s ends, ``lease-expired``); an export made with ``history``
resends, after a gap, the samples before its end the receiver asks for.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import traceback
from collections import deque
from collections.abc import Callable
from functools import partial
from typing import Self

import msgpack

from agents import (
    AuthenticationError,
    Expired,
    TokenBucket,
    TransportClosed,
    Unencrypted,
    UnknownSession,
    check_name,
    wire_key,
)
from agents.transports import Message, Subscription, Transport
from dyknow_core import DyKnowInstance, Policy, RawSample
from dyknow_core import Subscription as StreamSubscription

from ._batch import BATCH_VERSION, check_sample, check_semantic_label, pack_batch
from ._proxy_base import ProxyBase
from ._proxy_stats import DropReason, ExportStats, ResendRefusal, tally, untally
from ._sequence import cover, uncovered
from ._sessions import InterfaceSessions, SessionsProvider

__all__ = ["RESEND_BURST", "RESEND_RATE", "RESEND_REPORT_INTERVAL", "Export", "ExportProxy"]

log = logging.getLogger(__name__)

OnDrop = Callable[["Export", DropReason, int], None]
"""``on_drop(export, reason, count)``: told in the publisher's call; keep it short."""

_BACKOFF_MIN = 0.05
_BACKOFF_MAX = 2.0
# How often an idle export looks whether its local stream ended (no event tells it).
_IDLE_CHECK = 1.0
# An idle export not acknowledged for this long sends an empty batch (receivers report
# every 0.5 s by default): a live receiver learns of the stream and answers.
_KEEPALIVE_AFTER = 1.0
# A wait timer firing this close (s) before its deadline ends the wait: not re-armed.
_CLOCK_SLACK = 1e-3
# Pending resend requests kept per export.
_MAX_RECOVER = 16
_MAX_HISTORY = 1_000_000
_MAX_FAILED = 256  # failed ranges remembered per export (older ones stay counted)
_HISTORY_SLACK = 256
# Resend requests a receiver may make per second (all its exports), and at once: one per
# gap plus the re-asks of its reports (2/s per stream) fit; a flood of them does not.
RESEND_RATE = 20.0
RESEND_BURST = 40.0
# A receiver's refused resend requests are audited at most once per this many seconds.
RESEND_REPORT_INTERVAL = 1.0


class Export:
    """One agreed stream to one receiver: its queue, its task and its counters.

    Counters: ``sent`` samples in ``batches`` published; ``dropped`` by `DropReason`
    (``queue-full``: the receiver's queue overflowed, oldest first; ``no-session``: no
    session could be agreed; ``send-failed``: the transport refused; ``unencodable``:
    a value msgpack cannot carry; ``too-large``: one sample over the batch size limit;
    ``lost-in-transit``: published, but reported missing by the receiver, less what was
    recovered; ``lease-expired``: what was still queued when the receiver's lease
    expired). With ``history`` N the receiver asks, after each gap, for the N samples
    before its end: they are resent from the last 2N + 256 kept here, each sequence
    number at most once, and no more than the receiver reports lost (``recovered``
    counts the samples resent; ``resend_refused`` the requests refused in whole or in
    part, by `ResendRefusal`: ``not-a-gap``, ``over-loss``, ``already-resent``, ``rate``).
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
        # the lease's previous look; the report a look past due spared the export on, and
        # until when (the reports that came in the stall are read meanwhile)
        self._looked_at = self.last_heard
        self._spared = -math.inf
        self._spared_until = -math.inf
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
        self._failed: deque[tuple[int, int, DropReason]] = deque(maxlen=_MAX_FAILED)
        self._waiter: asyncio.Future[None] | None = None
        # the current wait's deadline (loop time), and the one timer that enforces it
        self._deadline = 0.0
        self._timer: asyncio.TimerHandle | None = None
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
        # listed for the proxy's next flush (`ExportProxy._flush`)
        self._listed = False
        # numbered bodies the flush could not seal, from the first one's number, and why:
        # the task sends them first, in order, the way `_send` goes on after that error
        self._unsent: tuple[list[tuple[bytes, int]], int, Exception] | None = None
        # what a flush met that ends the export (a closed transport, a failure): the task
        # raises it, as if it had met it sending
        self._crashed: Exception | None = None

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

    def stats(self) -> ExportStats:
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
            self._drop(DropReason.QUEUE_FULL, over)
        w = self._waiter
        # an idle task: the proxy's flush sends the batch, or wakes the task if it cannot;
        # a busy one finds the samples when it is done
        if w is not None and not self._listed and not w.done():
            self._listed = True
            self._proxy._list(self)

    def _wake(self) -> None:
        """Wake the export's task if it waits for samples or requests."""
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def _drop(self, reason: DropReason, n: int, error: str | None = None) -> None:
        """Count ``n`` samples lost for ``reason`` (a warning the first time), tell ``on_drop``."""
        if tally(self.dropped, reason, n):
            log.warning(
                "%s: dropping samples (%s)%s", self.name, reason, f": {error}" if error else ""
            )
        if error is not None:
            self.last_error = error
        on_drop = self._proxy.on_drop
        if on_drop is not None:
            try:
                on_drop(self, reason, n)
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
                if self._crashed is not None:
                    # let go of it: its traceback holds the flush's frames and last batch
                    crashed, self._crashed = self._crashed, None
                    raise crashed
                if self._unsent is not None:
                    (packed, first, error), self._unsent = self._unsent, None
                    await self._send_packed(packed, first, error)
                if lease is not None and self._lease_expired(lease, idle):
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
                        # what came while it waited (a session, a backoff) woke nobody:
                        # the task was not waiting then, so it goes out now, not at `idle`
                        if q or self._recover:
                            continue
                    await self._wait(idle)
                    continue
                n = min(len(q), batch_size)
                await self._send([q.popleft() for _ in range(n)])
                if q:  # a transport that never suspends (memory) would otherwise hold the loop
                    await asyncio.sleep(0)
        except TransportClosed as exc:
            self._end(f"the transport closed: {exc}")
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            log.exception("%s: failed", self.name)  # our own log: the text, samples and all
            # told to the receiver: the error's type and where, never its text (it may
            # quote a sample, which goes to the receiver sealed only)
            self._end(f"failed: {_raised(exc)} (its text left out)")
            await self._tell_ended()
        finally:
            self._disarm()

    def _lease_expired(self, lease: float, every: float) -> bool:
        """End the export when its receiver has not reported for ``lease`` s (frozen, gone).

        The lease is looked at every ``every`` s at most. A look that comes so late that
        the lease ran out only while this process was not looking (it stalled: busy,
        descheduled) spares the export, once per report heard, for ``every / 2`` s: the
        reports that came meanwhile are read before a look decides, rather than a live
        receiver's export ended. A time, not a number of looks: with samples queued the
        task looks again after each batch, before the loop has read any report.
        """
        now = time.monotonic()
        silent = now - self.last_heard
        due = self._looked_at + every  # when this look was due
        self._looked_at = now
        if silent <= lease or now < self._spared_until:
            return False
        if due - self.last_heard <= lease and self._spared != self.last_heard:
            self._spared = self.last_heard
            self._spared_until = now + every / 2  # the next regular look decides
            return False
        log.warning(
            "%s: lease expired: no report from %s for %.1f s; export stopped",
            self.name,
            self.receiver,
            silent,
        )
        self._drop(DropReason.LEASE_EXPIRED, len(self.queue), f"no report for {silent:.1f} s")
        self.queue.clear()
        self._end(f"lease-expired: no report from {self.receiver} for {silent:.1f} s")
        return True

    async def _tell_ended(self) -> None:
        """Best effort: the receiver, if it comes back, learns the export ended and why."""
        body = pack_batch(self.semantic_label, [], self._seq, ended=self.ended or "ended")
        try:
            async with asyncio.timeout(1.0):
                await self._publish(body)
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
            self._refuse_resend(ResendRefusal.NOT_A_GAP)
            return
        lo = max(first, end - self.history)
        if lo > first:
            self._refuse_resend(ResendRefusal.NOT_A_GAP)
        if end - lo > self._claimed:
            lo = end - self._claimed
            self._refuse_resend(ResendRefusal.OVER_LOSS)
            if lo >= end:
                return
        # the oldest number still kept: older ones are gone, not refused
        lo = max(lo, self._seq - len(self._kept))
        if lo >= end:
            return
        wanted = uncovered(self._resent_ranges, lo, end)
        if sum(b - a for a, b in wanted) < end - lo:
            self._refuse_resend(ResendRefusal.ALREADY_RESENT)
        if not wanted:
            return
        self._recover += wanted
        del self._recover[:-_MAX_RECOVER]  # a flood of requests costs a bounded list
        self._wake()

    def _refuse_resend(self, reason: ResendRefusal) -> None:
        """Count a resend request refused (in whole or in part) for ``reason``."""
        tally(self.resend_refused, reason, 1)
        tally(self._refusals_pending, reason, 1)

    def _take_refusals(self, now: float) -> dict[str, int] | None:
        """The resend refusals to audit now (once per interval), forgotten here; else None."""
        pending = self._refusals_pending
        if not pending or now - self._refusals_reported < RESEND_REPORT_INTERVAL:
            return None
        self._refusals_pending = {}
        self._refusals_reported = now
        return pending

    def _reported_lost(self, total: int) -> None:
        """The receiver reports ``total`` samples missing: count the change as lost in transit."""
        # a receiver cannot have missed more than this export numbered
        total = min(max(total, 0), self._seq)
        self._claimed = total
        transit = total - self._numbered_drops
        delta = transit - self.lost_in_transit
        if delta > 0:
            self.lost_in_transit = transit
            self._drop(DropReason.LOST_IN_TRANSIT, delta)
        elif delta < 0 and self.dropped.get(DropReason.LOST_IN_TRANSIT):
            # reported lost, then recovered from the history: no longer a loss
            self.lost_in_transit = max(transit, 0)
            untally(self.dropped, DropReason.LOST_IN_TRANSIT, -delta)

    async def _resend(self) -> None:
        """Publish, as batches marked resent, the asked ranges the history still holds."""
        ranges, self._recover = self._recover, []
        kept = list(self._kept)
        oldest = self._seq - len(kept)  # the sequence number of kept[0]
        # forget what is no longer kept: it cannot be asked back anyway
        self._resent_ranges = [(a, b) for a, b in self._resent_ranges if b > oldest]
        transport = self._proxy.transport
        # one blocking put per receiver at a time: a frozen one, however many streams it
        # imports, holds one of the transport's few worker threads, not all of them
        turn = self._proxy._resend_turn(self.receiver)
        for asked_first, asked_end in ranges:
            # asked twice before this ran: resent once
            for first, end in uncovered(self._resent_ranges, max(asked_first, oldest), asked_end):
                samples = kept[first - oldest : end - oldest]
                start = first
                for body, count in self._pack_resent(first, samples):
                    try:
                        # each number is resent once: it waits for room on a congested
                        # link rather than being dropped there, as `publish` would; sealed
                        # when it can go, so the wait cannot age it out of the receiver's
                        # skew or replay window
                        async with turn:
                            await transport.publish_blocking(self.key, partial(self._seal, body))
                    except (asyncio.CancelledError, TransportClosed):
                        raise
                    except Exception as exc:  # the receiver may ask again
                        log.debug("%s: resending failed: %s", self.name, exc)
                        break
                    self.recovered += count
                    self._resent_ranges = cover(self._resent_ranges, start, start + count)
                    if self._failed:
                        self._resent(start, start + count)
                    start += count

    def _numbered_drop(self, reason: DropReason, first: int, n: int, exc: Exception) -> None:
        """Numbered samples that never left: counted here, not as lost in transit."""
        self._drop(reason, n, f"{type(exc).__name__}: {exc}")
        self._numbered_drops += n
        if self.history:  # they may be resent from the history: remember which
            self._failed.append((first, first + n, reason))

    def _resent(self, first: int, end: int) -> None:
        """Samples [first, end) went out from the history: no longer dropped here."""
        kept: list[tuple[int, int, DropReason]] = []
        for a, b, reason in self._failed:
            lo, hi = max(a, first), min(b, end)
            if lo >= hi:
                kept.append((a, b, reason))
                continue
            n = hi - lo
            self._numbered_drops -= n
            untally(self.dropped, reason, n)
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
        """Wait until woken (samples, a resend request) or ``timeout`` s have passed."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        self._waiter = fut
        self._deadline = deadline = loop.time() + timeout
        # This runs once per batch sent, and samples usually wake it long before the
        # deadline: rather than a timer made and cancelled per wait, one timer stays armed,
        # and when it fires early for a later wait it re-arms for that wait's deadline.
        timer = self._timer
        if timer is None or timer.when() > deadline:
            if timer is not None:
                timer.cancel()
            self._timer = loop.call_at(deadline, self._on_deadline)
        try:
            await fut
        finally:
            self._waiter = None

    def _on_deadline(self) -> None:
        """The wait timer fired: end the wait if its deadline passed, else re-arm for it."""
        self._timer = None
        fut = self._waiter
        if fut is None or fut.done():
            return  # not waiting: the next wait arms a timer
        loop = fut.get_loop()
        # a loop's timers round to its clock (uvloop: to the millisecond): within that, due
        if loop.time() + _CLOCK_SLACK >= self._deadline:
            fut.set_result(None)
        else:
            self._timer = loop.call_at(self._deadline, self._on_deadline)

    def _disarm(self) -> None:
        """Cancel the wait timer: the export's task is done."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    async def _send(self, samples: list[RawSample]) -> None:
        packed = self._pack(samples)
        # numbered as packed (one body, but for a batch over max_batch_bytes)
        first = self._seq - (packed[0][1] if len(packed) == 1 else sum(c for _, c in packed))
        await self._send_packed(packed, first)

    def _send_now(
        self,
        samples: list[RawSample],
        seal: Callable[[str, bytes], bytes],
        publish: Callable[[str, bytes], None],
    ) -> None:
        """`_send` without waiting: pack, ``seal`` and ``publish`` (a put that never waits).

        A body that cannot be sealed now (no session, one to renew: `_seal` waits for it)
        is left, with those after it, to the task, which goes on from that error as
        `_send` does; a closed transport ends the export from the task. Called by the
        proxy's flush only while the task waits, with no backoff and nothing left unsent.
        """
        packed = self._pack(samples)
        if not packed:
            return
        first = self._seq - (packed[0][1] if len(packed) == 1 else sum(c for _, c in packed))
        receiver, key = self.receiver, self.key
        for i, (body, count) in enumerate(packed):
            try:
                envelope = seal(receiver, body)
            except Exception as exc:  # no session, or one to renew: `_seal` waits for one
                self._unsent = (packed[i:], first, exc)
                self._wake()
                return
            try:
                publish(key, envelope)
            except TransportClosed as exc:  # the task ends the export, as `_send` would
                self._crashed = exc
                self._wake()
                return
            except Exception as exc:
                self._numbered_drop(DropReason.SEND_FAILED, first, count, exc)
                first += count
                continue
            first += count
            self.sent += count
            self.batches += 1

    async def _send_packed(
        self, packed: list[tuple[bytes, int]], first: int, failed: Exception | None = None
    ) -> None:
        """Seal and publish ``packed`` (numbered from ``first``), as `_send` does.

        ``failed``: what sealing the first body raised already (in the proxy's flush).
        """
        proxy = self._proxy
        for body, count in packed:
            start, first = first, first + count
            error, failed = failed, None
            try:
                envelope = await self._seal(body, error)
            except (asyncio.CancelledError, TransportClosed):
                raise
            except Exception as exc:  # no session: the receiver is gone, or refuses us
                if count:
                    self._numbered_drop(DropReason.NO_SESSION, start, count, exc)
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
                    self._numbered_drop(DropReason.SEND_FAILED, start, count, exc)
                continue
            self._backoff = 0.0
            if count:
                self.sent += count
                self.batches += 1

    async def _publish(self, body: bytes) -> None:
        """Seal ``body`` for the receiver and publish it on the export's key."""
        await self._proxy.transport.publish(self.key, await self._seal(body))

    async def _seal(self, body: bytes, failed: Exception | None = None) -> bytes:
        """Seal ``body``, agreeing a session if need be (``failed``: the first try's error)."""
        sessions = self._proxy.sessions
        try:
            if failed is not None:
                raise failed
            return sessions.seal_bytes(self.receiver, body)
        except (UnknownSession, Expired):
            async with asyncio.timeout(self._proxy.agree_timeout):
                await sessions.ensure(self.receiver)
            try:
                return sessions.seal_bytes(self.receiver, body)
            except UnknownSession:
                # the receiver's token first seen while we waited: its sessions doubted
                # (`SessionTable.doubt`), so one more is agreed, once
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
                    check_sample(s)
                except (TypeError, ValueError, OverflowError) as exc:
                    self._drop(DropReason.UNENCODABLE, 1, f"{type(exc).__name__}: {exc}")
                else:
                    good.append(s)
            if not good:
                return []
            samples = good
            body = pack_batch(label, samples, self._seq, history=history)
        if len(body) > self._proxy.max_batch_bytes:
            if len(samples) == 1:
                self._drop(DropReason.TOO_LARGE, 1, f"one sample of {len(body)} bytes")
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


def _raised(exc: BaseException) -> str:
    """``exc``'s type and the place it was raised (file, line, function): not its text."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return type(exc).__qualname__
    last = frames[-1]
    file = last.filename.rsplit("/", 1)[-1]
    return f"{type(exc).__qualname__} at {file}:{last.lineno} in {last.name}"


class ExportProxy(ProxyBase):
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
        super().__init__(
            "export", platform_name, federation, transport, instance, sessions_provider
        )
        self.queue_size = queue_size
        self.batch_size = batch_size
        self.max_batch_bytes = max_batch_bytes
        self.agree_timeout = agree_timeout
        self.on_drop = on_drop
        self.lease = lease
        self.ended: deque[Export] = deque(maxlen=256)
        self._exports: dict[tuple[str, str], Export] = {}
        self._reports: asyncio.Task[None] | None = None  # started with the first export
        # loss reports that did not open or parse (audited: `_refuse_report`)
        self.reports_refused = 0
        # the loss reports' subscription failed to be made, or the transport ended it
        self.reports_subscription_failures = 0
        self._resend_buckets: dict[str, TokenBucket] = {}  # per receiver (authenticated)
        self._resend_turns: dict[str, asyncio.Lock] = {}  # per receiver: its blocking puts
        # exports whose idle task got samples this turn, and the one flush that sends them
        self._listed: list[Export] = []
        self._flush_due = False
        self._loop: asyncio.AbstractEventLoop | None = None

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
        policy = policy or Policy()
        self._loop = asyncio.get_running_loop()
        export = Export(
            self, local_label, semantic_label, receiver, policy, self.queue_size, history
        )
        # subscribed before the task exists: history a past 'start' replays is queued too
        export.subscription = self.instance.subscribe(
            local_label, policy, callback=export._on_batch
        )
        export.task = self._tasks.spawn(export._run(), export.name)
        self._exports[(receiver, semantic_label)] = export
        if self._reports is None:
            self._reports = self._tasks.spawn(
                self._receive_reports(), f"export[{self.platform}].loss-reports"
            )
        return export

    def _list(self, export: Export) -> None:
        """``export``'s idle task got samples: have the turn's flush send them."""
        if not self._flush_due:
            if not self._puts_at_once():  # MQTT: its task sends, woken now as ever
                export._listed = False
                export._wake()
                return
            assert self._loop is not None  # set by `start_exporting`, on the loop
            self._flush_due = True
            self._loop.call_soon(self._flush)
        self._listed.append(export)

    def _puts_at_once(self) -> bool:
        """Whether the transport's put never waits (`Transport.publishes_nowait`)."""
        transport = self.transport
        # a `publish` set on the transport itself (a test's lossy link) must see every put
        return transport.publishes_nowait and "publish" not in vars(transport)

    def _flush(self) -> None:
        """Send each listed export's next batch where its path is clear; else wake its task.

        Clear: its task still waits (not sending, resending, agreeing a session or
        backing off), nothing is left unsent, nothing to resend, its lease holds, and the
        transport's put never waits (`Transport.publishes_nowait`). One batch per export
        and turn, as the task sends one per turn of the loop: a long queue goes on next turn.
        """
        self._flush_due = False
        listed, self._listed = self._listed, []
        publish = self.transport.publish_nowait if self._puts_at_once() else None
        seal = self.sessions.seal_bytes
        lease = self.lease
        now = time.monotonic() if lease is not None else 0.0
        batch_size = self.batch_size
        for export in listed:
            export._listed = False
            w = export._waiter
            if export.ended is not None or w is None or w.done():
                continue  # ended, or its task is awake: it finds the samples queued
            if (
                publish is None
                or export._backoff
                or export._recover
                or export._unsent is not None
                or (lease is not None and now - export.last_heard > lease)
            ):
                w.set_result(None)
                continue
            q = export.queue
            if not q:
                continue
            if len(q) <= batch_size:
                samples = list(q)
                q.clear()
            else:
                samples = [q.popleft() for _ in range(batch_size)]
            try:
                export._send_now(samples, seal, publish)
            except Exception as exc:  # the task ends the export with it, as if it had sent
                export._crashed = exc
                export._wake()
                continue
            if q and not w.done():
                export._listed = True
                self._list(export)

    async def _receive_reports(self) -> None:
        """Read receivers' reports: their lease, what they lost, what they want resent.

        Each report is ``{"v": 1, "lost": {label: total}, "resend": {label: [first, end]}}``
        (``resend`` optional). Every label named renews that export's lease. ``lost`` is
        the receiver's running total of samples missing from its numbering and not
        recovered: the change is counted on the export as ``lost-in-transit`` (and
        ``on_drop`` told), so the provider learns of losses only receivers see.

        The subscription is made again when making it fails or the transport ends it (a
        broker that refused it after a reconnection, then takes it again): after
        `_BACKOFF_MIN` s, doubling to `_BACKOFF_MAX` s while it keeps failing, each
        failure counted in ``reports_subscription_failures`` and logged (a warning at the
        first of a run and when it is made again). A closed transport ends it.
        """
        key = wire_key(self.federation, "stream-report", self.platform) + "/*"
        delay = 0.0
        failed = 0  # failures in a row
        while True:
            if delay:
                await asyncio.sleep(delay)
            try:
                sub = await self.transport.subscribe(key, buffer_size=1024)
            except TransportClosed:
                return  # every export ends with the transport
            except Exception as exc:
                delay = self._reports_failed(failed, delay, f"cannot subscribe to {key}: {exc}")
                failed += 1
                continue
            if failed:
                log.warning(
                    "export[%s]: subscribed to receivers' loss reports again (%s) after "
                    "%d failure(s)",
                    self.platform,
                    key,
                    failed,
                )
                failed = 0
            try:
                if await self._read_reports(sub):
                    delay = 0.0  # it served: a next failure starts the backoff over
                self._ended(
                    sub,
                    f"loss reports subscription {key}",
                    "receivers' loss reports are not heard until the subscription is made "
                    "again (tried with backoff): meanwhile this platform's exports may end "
                    "at their lease as if their receivers were gone, their losses in "
                    "transit not counted nor resent",
                )
                if sub.closed:
                    return  # closed with the transport
            finally:
                sub.close()
            delay = self._reports_failed(failed, delay, f"the transport ended {key}")
            failed += 1

    def _reports_failed(self, failed: int, delay: float, why: str) -> float:
        """Count a failure of the loss reports' subscription, log it; the next backoff."""
        self.reports_subscription_failures += 1
        delay = min(max(2 * delay, _BACKOFF_MIN), _BACKOFF_MAX)
        log.log(
            logging.DEBUG if failed else logging.WARNING,
            "export[%s]: receivers' loss reports not heard: %s; subscribing again in %.2f s",
            self.platform,
            why,
            delay,
        )
        return delay

    async def _read_reports(self, sub: Subscription[Message]) -> bool:
        """Handle the reports ``sub`` brings until it ends; whether one was a report."""
        heard = False
        async for item in sub:
            sender = None  # until the envelope opens: then authenticated
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
            except Exception as exc:
                self._refuse_report(sender, exc)
                continue
            heard = True
            now = time.monotonic()
            for label, total in lost.items():
                export = self._exports.get((sender, label))
                if export is None or type(total) is not int:
                    continue
                export.last_heard = now
                export._reported_lost(total)
            for label, wanted in resend.items():
                export = self._exports.get((sender, label))
                if export is None or not export.history:
                    continue
                if not self._resend_bucket(sender, now).take(now):
                    export._refuse_resend(ResendRefusal.RATE)
                elif (
                    type(wanted) is list
                    and len(wanted) == 2
                    and all(type(x) is int for x in wanted)
                ):
                    export._want_resent(wanted[0], wanted[1])
                else:
                    export._refuse_resend(ResendRefusal.NOT_A_GAP)
                self._audit_resend_refusals(export, now)
        return heard

    def _refuse_report(self, sender: str | None, exc: Exception) -> None:
        """Count a report refused; audit it within the budget of unauthenticated input.

        ``sender`` is the authenticated one when the envelope opened (its body was no
        report), else None. Anyone can publish under ``stream-report/<me>/…``: a flood
        of them is summed up by the Interface Agent's budget, not one record each.
        """
        self.reports_refused += 1
        sessions = self.sessions
        if not isinstance(sessions, InterfaceSessions) or isinstance(exc, Unencrypted):
            return  # no audit here; a plain envelope the sessions audited already
        if isinstance(exc, AuthenticationError):
            claimed, reason = exc.platform, f"{exc.code}: {exc.reason}"
        else:
            claimed, reason = sender, f"malformed: not a stream report: {exc}"
        sessions.agent.audit_unauthenticated(claimed, reason[:300], stage="stream-report")

    def _resend_turn(self, receiver: str) -> asyncio.Lock:
        """The lock ``receiver``'s resends take turns with (made on first use)."""
        turn = self._resend_turns.get(receiver)
        if turn is None:
            turn = self._resend_turns[receiver] = asyncio.Lock()
        return turn

    def _resend_bucket(self, receiver: str, now: float) -> TokenBucket:
        """The resend requests ``receiver`` may still make (one bucket per trusted platform)."""
        bucket = self._resend_buckets.get(receiver)
        if bucket is None:
            bucket = self._resend_buckets[receiver] = TokenBucket(RESEND_RATE, RESEND_BURST, now)
        return bucket

    def _audit_resend_refusals(self, export: Export, now: float) -> None:
        """Audit an export's refused resend requests, at most once per interval, with counts."""
        pending = export._take_refusals(now)
        if not pending:
            return
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

    async def stop(self, export: Export, *, why: str | None = None) -> None:
        """End ``export``: unsubscribe, drop what is queued, wait for its task to finish.

        With ``why``, the receiver is told (an end marker naming it), as when the export
        ends by itself: its import ends there. Without, it learns nothing (a cancel it
        asked for, or a platform going away).
        """
        told = why is not None and export.ended is None
        if told:
            export.ended = why  # ended by this platform's decision, not listed in `ended`
        export._end("stopped")
        task = export.task
        if task is not None and task is not asyncio.current_task():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if told:
            await export._tell_ended()  # after its task: no batch follows the marker

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

    def stats(self) -> list[ExportStats]:
        """Every active export's counters."""
        return [e.stats() for e in self._exports.values()]

    async def aclose(self) -> None:
        """Stop every export and stop listening to loss reports."""
        await self.stop_all()
        self._reports = None
        await self._tasks.aclose()

    def _forget(self, export: Export) -> None:
        key = (export.receiver, export.semantic_label)
        if self._exports.get(key) is export:
            del self._exports[key]
