"""The Interface Agent's audit flush and the owner's view (sealed audit, watch)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import TYPE_CHECKING, Any

import msgpack

from ._aio import Ticker
from ._exceptions import AuthenticationError, TransportError
from ._interface_common import _MIRROR_CHUNK, AUDIT_HOLD, WATCH_RATE, log
from ._interface_state import _InterfaceState
from ._security import seal_owner_batch, sign_owner_batch, watch_answer

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _Owner(_InterfaceState):
    """The audit flushed and published, and what the platform's owner may watch."""

    # -- the audit flush -------------------------------------------------------------------

    def _wake_flush(self) -> None:
        """Wake the audit flush if it sleeps for want of work (from any thread)."""
        loop = self._flush_loop
        if not self._flush_idle or loop is None:
            return  # ticking anyway: what is new is flushed at its next tick
        self._flush_idle = False
        with contextlib.suppress(RuntimeError):  # the loop is closed: nothing flushes now
            loop.call_soon_threadsafe(self._flush_due.set)

    def _flush_has_work(self) -> bool:
        """Whether the audit flush has anything to do at its next tick, or soon after."""
        return bool(
            self._lane_done
            or self.audit._pending
            or self.mirroring
            or self._mirror
            or self._unauth_pending
            or self._watch_shed_pending
            or self._presence_ignored
            or self._audit_held  # published, or dropped once older than AUDIT_HOLD
            or (self.kx_gate is not None and self.kx_gate.pending)
            or any(sender.pending for sender in self._senders.values())
        )

    async def _flush_idle_sleep(self) -> None:
        """Sleep until there is something to flush: an idle platform does not tick for it."""
        self._flush_loop = asyncio.get_running_loop()
        self._flush_due.clear()
        self._flush_idle = True
        if self._flush_has_work():  # came meanwhile, from another thread
            self._flush_idle = False
            return
        await self._flush_due.wait()

    async def _flushing(self) -> None:
        """`_flush_audit` until the platform stops; then what the lane answered is booked here."""
        try:
            await self._flush_audit()
        finally:
            self._flush_loop = None  # the lane posts its bookings to the loop again
            if self._lane_done:
                self._lane_book()

    async def _flush_audit(self) -> None:
        """Write and publish the audit now and then (batched: one publish, many records).

        Every ``audit_interval`` while there is something to write, publish or sum up;
        a tick that finds nothing sends the task to sleep until something comes (the
        first record after that is flushed within an interval, as before).
        """
        host = self._require_host()
        ticker = Ticker(self.audit_interval)
        self._flush_loop = asyncio.get_running_loop()  # the lane's bookings wait for it
        while True:
            await ticker.tick()
            ticker.period = self.audit_interval  # it may be changed while running
            if self._lane_done:
                self._lane_book()  # what the lane answered, counted and audited
            if not self._flush_has_work():
                await self._flush_idle_sleep()
                ticker = Ticker(self.audit_interval)  # the next tick an interval from now
                continue
            if self.rate_limit is not None:
                # what a flood that stopped left uncounted in the audit
                now = self._monotonic()
                for peer, sender in self._senders.items():
                    self._report_limited(peer, sender, now)
                self._report_unauthenticated(now)
            if self._mirror or self.mirroring:
                await self._flush_mirror(host)
            if self.kx_gate is not None:
                self._report_kx_shed(self._monotonic())
                self.kx_gate.forget_seen(time.time())
            self._report_watch_shed()
            self._report_presence_ignored(self._monotonic())
            self._report_missing(self._monotonic())
            if not self.publish_audit and self.audit.path is None:
                continue
            data = self.audit.take()
            if self.publish_audit:
                try:
                    await self._publish_audit(host, data)
                except TransportError as exc:
                    log.debug("interface[%s]: audit not published: %s", self._me, exc)

    # -- the owner's view -------------------------------------------------------------------

    async def _publish_audit(self, host: AgentPlatform, data: bytes) -> None:
        """Seal and publish an audit batch (and those held back) if anyone may receive it.

        A batch no subscriber could receive costs no signature and seal (~100 µs a KiB) and
        no put: it is held `AUDIT_HOLD` s instead (at most `_AUDIT_HELD` batches, the oldest
        dropped first), and dropped then if still nobody listens. The transport's answer may
        lag a subscriber that just came (zenoh tells the publisher a moment after the subscriber
        declared); the batches held cover a lag of up to `AUDIT_HOLD` s less one flush.
        """
        held = self._audit_held
        now = time.monotonic()  # real time, whatever clock the budgets run on
        while held and now - held[0][0] > AUDIT_HOLD:
            held.popleft()
        if not data and not held:
            return
        key = host.key("audit")
        if not host.transport.has_subscribers(key):
            if data:
                self.audit_unheard += 1
                held.append((now, data))
            return
        if held:
            data = b"".join(batch for _, batch in held) + data
            held.clear()
        await host.transport.publish(key, self._audit_payload(key, data))
        self.audit_published += 1

    def _audit_payload(self, key: str, data: bytes) -> bytes:
        """The published audit batch: signed, and sealed to this platform's owner unless plain."""
        if not self.seal_audit:
            return sign_owner_batch(self.keys, key, data, int(self._owner_clock() * 1000))
        return seal_owner_batch(self.keys, key, data, clock=self._owner_clock)

    def mirror_bytes(self, peer: str, body: bytes) -> None:
        """Show the owner an opened binary envelope (a sample batch or stream report)."""
        if self.mirroring:
            self._mirror.append(("bin", peer, time.time(), body))

    def _admit_watch(self, payload: bytes) -> bool:
        """Whether a watch request goes on to the event loop (the transport's thread)."""
        with self._watch_lock:
            if self._watch_bucket.take(self._monotonic()):
                return True
            self.watch_shed += 1
            self._watch_shed_pending += 1
        self._wake_flush()  # to audit them
        return False

    def _report_watch_shed(self) -> None:
        """Audit the watch requests shed since the last record, summed up in one."""
        with self._watch_lock:
            n, self._watch_shed_pending = self._watch_shed_pending, 0
        if n:
            self.audit.record(
                verdict="dropped",
                stage="watch-shed",
                count=n,
                reason=(
                    f"watch requests shed: {n} dropped before the event loop "
                    f"(over {WATCH_RATE:g}/s, bursts of {WATCH_RATE:g})"
                ),
            )

    async def _on_watch(self, key: str, payload: bytes) -> bytes | None:
        """The owner asks to watch: a request signed with this platform's key renews a lease."""
        try:
            nonce = self._watch_gate.check(payload)
        except AuthenticationError as exc:
            self.watch_refused += 1
            self._drop_unauthenticated(exc.platform, f"{exc.code}: {exc.reason}", stage="watch")
            return None
        if not self.mirroring:
            self.audit.record(verdict="accepted", stage="watch", reason="the owner watches")
        self._mirror_until = self._monotonic() + self.watch_lease
        self.mirroring = True
        # the time the batches are signed with, so the owner bounds them on this clock
        return watch_answer(
            self.keys, self._watch_gate.federation, nonce, self.watch_lease, clock=self._owner_clock
        )

    async def _flush_mirror(self, host: AgentPlatform) -> None:
        """Publish what the owner watches, signed and sealed to the owner; end an expired lease."""
        if self.mirroring and self._monotonic() > self._mirror_until:
            self.mirroring = False
        items = list(self._mirror)
        self._mirror.clear()
        chunk: list[list[Any]] = []
        size = 0
        for i, item in enumerate(items):
            chunk.append(list(item))
            size += len(item[3]) + 64
            if size < _MIRROR_CHUNK and i + 1 < len(items):
                continue
            # one sealed publish per ~half a MiB: a busy platform's lease stays a few puts
            data = msgpack.packb(chunk, use_bin_type=True)
            chunk, size = [], 0
            try:
                key = host.key("watch")
                await host.transport.publish(
                    key, seal_owner_batch(self.keys, key, data, clock=self._owner_clock)
                )
            except TransportError as exc:
                log.debug("interface[%s]: watch not published: %s", self._me, exc)
