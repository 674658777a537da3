"""The import side: the streams other platforms export to this one, added locally.

The receiver's `ImportProxy` opens each batch (`federation._batch`), translates the
semantic label to a local one and adds the samples to that local stream, which is to
its instance just another source. Every stream's numbering is followed by its
`SequenceTracker`: gaps are counted lost and reported to the sender every
``report_interval`` (the reports are the sender's lease), and, when the sender keeps a
history, asked back and filled when they come.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import traceback
from collections.abc import Awaitable, Callable
from typing import Any, Self

import msgpack

from agents import AuthenticationError, check_name, wire_key
from agents.transports import Message, Presence, Transport
from agents.transports import Subscription as TransportSubscription
from dyknow_core import (
    CacheSpec,
    DuplicateLabelError,
    DyKnowInstance,
    ProcessError,
    RawSample,
    Source,
)

from ._batch import BATCH_VERSION, check_semantic_label, read_batch
from ._proxy_base import ProxyBase
from ._proxy_stats import DropReason, ImportProxyStats, ImportStats, ImportTotals, tally
from ._quote import quoted
from ._sequence import SequenceTracker
from ._sessions import SessionsProvider

__all__ = ["Import", "ImportProxy"]

log = logging.getLogger(__name__)

Translate = Callable[[str, str], str | None]
"""``translate(sender, semantic_label)``: the local label to import into, None if never agreed."""

OnSenderGone = Callable[[str, list[str]], Awaitable[None] | None]
"""``on_sender_gone(sender, semantic_labels)``: told when a sender's streams were ended."""

OnExportEnded = Callable[[str, str], Awaitable[None] | None]
"""``on_export_ended(sender, semantic_label)``: the sender ended that export by itself."""

OnRefused = Callable[[str, str, int, int], None]
"""``on_refused(sender, reason, batches, samples)``: whole batches dropped since last told."""

OnBadSamples = Callable[[str, str, str, int], None]
"""``on_bad_samples(sender, semantic_label, reason, samples)``: samples of authentic,
agreed batches dropped (malformed, or rejected by the stream) since last told."""

# How many payloads the import loop handles before letting other tasks run.
_YIELD_EVERY = 64
_MAX_REFUSED_KEYS = 32  # (claimed sender, reason) pairs summed up between two on_refused
# calls: the rest (invented sender names of an outsider's flood) share one "*" entry per
# reason. An authenticated sender (a member: bounded by the trust file) has its own up to
# _MAX_AUTHENTIC_KEYS, or such a flood would hide a member's refusals among the invented
# names' (that bound for sessions that prove nothing: PlainSessions, in tests)
_MAX_AUTHENTIC_KEYS = 1024


class Import:
    """What arrives for one (sender, semantic label): where it lands, and its counters.

    ``batches`` payloads arrived; ``received`` samples were read from authentic batches,
    ``injected`` added to the local stream; ``lost`` samples never arrived (gaps in the
    sender's numbering: dropped on the way, or cut off) and were not recovered;
    ``recovered`` arrived late, resent from the sender's history; ``gaps`` counts the
    gaps seen (all three kept by its `SequenceTracker`, ``sequence``);
    ``dropped_batches`` / ``dropped_samples`` by reason. ``local_label`` is None for a
    stream that was never agreed.
    """

    def __init__(self, sender: str, semantic_label: str, local_label: str | None) -> None:
        self.sender = sender
        self.semantic_label = semantic_label
        self.local_label = local_label
        self.source: Source | None = None
        self.batches = 0
        self.received = 0
        self.injected = 0
        self.sequence = SequenceTracker()
        self.history = 0  # what the sender says it keeps to resend
        self.dropped_batches: dict[str, int] = {}
        self.dropped_samples: dict[str, int] = {}
        self.ended = False
        self.first_arrival: int | None = None
        self.last_arrival: int | None = None
        self._last_ta = -(2**63)

    @property
    def lost(self) -> int:
        """Samples that never arrived (gaps in the sender's numbering) and were not recovered."""
        return self.sequence.lost

    @property
    def recovered(self) -> int:
        """Samples that arrived late, resent from the sender's history."""
        return self.sequence.recovered

    @property
    def gaps(self) -> int:
        """The gaps seen in the sender's numbering."""
        return self.sequence.gaps

    @property
    def lost_now(self) -> int:
        """Samples lost (and not recovered) from the sender's current numbering: reported."""
        return self.sequence.lost_now

    def __repr__(self) -> str:
        return (
            f"<Import {self.sender}:{self.semantic_label} -> {self.local_label} "
            f"injected={self.injected}{' ended' if self.ended else ''}>"
        )

    @property
    def location(self) -> str:
        """The instance location its stream lives at (one per sender platform)."""
        return f"import/{self.sender}"

    def stats(self) -> ImportStats:
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
        """Count one whole batch dropped for ``reason`` (a DropReason or an authentication code)."""
        if tally(self.dropped_batches, reason, 1):
            log.warning(
                "import %s:%s: dropping batches (%s)", self.sender, self.semantic_label, reason
            )

    def _drop_samples(self, reason: DropReason, n: int) -> None:
        """Count ``n`` samples dropped for ``reason``."""
        if tally(self.dropped_samples, reason, n):
            log.warning(
                "import %s:%s: dropping samples (%s)", self.sender, self.semantic_label, reason
            )


class ImportProxy(ProxyBase):
    """Receives the streams other platforms export to this one and adds them locally.

    ``translate(sender, semantic_label)`` names the local label (None: never agreed, the
    batch is dropped); `expect` agrees one in advance. Each sender's streams live at
    location ``import/<sender>``, made with ``cache``; the first sample creates the source.
    When a sender's liveliness token goes, its streams are ended (their subscribers'
    iterators end; with ``keep_ended`` the label and its cache stay queryable) and
    ``on_sender_gone(sender, semantic_labels)`` is told. When a sender ends an export by
    itself (its lease expired: we did not report in time) and says so, the stream ends
    and ``on_export_ended(sender, semantic_label)`` is told. Batches dropped whole
    (never agreed, not authentic, under another sender's name, malformed) are summed up per sender
    and reason and told to ``on_refused(sender, reason, batches, samples)`` once per
    ``report_interval`` (an audit, bounded whatever the flood); samples dropped from
    authentic batches of an agreed stream, per sender, stream and reason, to
    ``on_bad_samples(sender, semantic_label, reason, samples)`` likewise. Use as an async
    context manager (or ``start`` / ``aclose``).
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
        on_bad_samples: OnBadSamples | None = None,
        cache: CacheSpec | None = None,
        keep_ended: bool = True,
        buffer_size: int = 1024,
        max_strays: int = 1024,
        report_interval: float = 0.5,
        presence: Callable[[], TransportSubscription[Presence]] | None = None,
    ) -> None:
        super().__init__(
            "import", platform_name, federation, transport, instance, sessions_provider
        )
        self.translate = translate
        self.on_sender_gone = on_sender_gone
        self.on_export_ended = on_export_ended
        self.on_refused = on_refused
        # (sender, reason) -> [batches, samples] not yet told to on_refused (bounded keys)
        self._refused: dict[tuple[str, str], list[int]] = {}
        self.on_bad_samples = on_bad_samples
        # (sender, semantic label, reason) -> samples not yet told (bounded: agreed imports)
        self._bad: dict[tuple[str, str, str], int] = {}
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
        # set when there is something to report on: until then the report task sleeps
        self._reportable = asyncio.Event()
        self._subs: list[TransportSubscription[Message] | TransportSubscription[Presence]] = []
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
        spawn, me = self._tasks.spawn, f"import[{self.platform}]"
        spawn(self._watch(presence), f"{me}.presence")
        spawn(self._receive(streams), f"{me}.receive")
        spawn(self._report_losses(), f"{me}.loss-reports")

    async def aclose(self) -> None:
        """Stop receiving and end every imported stream."""
        if self._state == "closed":
            return
        self._state = "closed"
        for sub in self._subs:
            sub.close()
        await self._tasks.aclose()
        for rec in self._imports.values():
            self._end(rec)
        # what was refused since the last report is told, not lost with the proxy
        self._tell_refused()

    async def _report_losses(self) -> None:
        """Report to each sender, every ``report_interval``, on every stream it sends here.

        The report is the sender's lease (an export not reported on is ended there) and
        carries this side's running total of its samples that never arrived.
        """
        while True:
            if not self._imports and not self._refused:
                # nothing imported, nothing refused: an idle platform does not wake for this
                self._reportable.clear()
                await self._reportable.wait()
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
                # the resent batches may have been dropped on the way too: ask again
                span = rec.sequence.ask_again()
                if span is not None:
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
        self._tasks.spawn(self._report(rec.sender, report), f"import[{self.platform}].resend")

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

    def stats(self) -> ImportProxyStats:
        """Every import's counters, those of unagreed traffic, and the totals."""
        imports = [r.stats() for r in self._imports.values()]
        strays = [r.stats() for r in self._strays.values()]
        totals: ImportTotals = {
            "batches": 0,
            "received": 0,
            "injected": 0,
            "lost": 0,
            "dropped_batches": {},
            "dropped_samples": {},
        }
        for s in imports + strays:
            totals["batches"] += s["batches"]
            totals["received"] += s["received"]
            totals["injected"] += s["injected"]
            totals["lost"] += s["lost"]
            for reason, n in s["dropped_batches"].items():
                tally(totals["dropped_batches"], reason, n)
            for reason, n in s["dropped_samples"].items():
                tally(totals["dropped_samples"], reason, n)
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
        self._reportable.set()
        return rec

    def _refuse(self, sender: str, label: str, reason: str, by: str | None = None) -> None:
        """Count one whole batch dropped, and why, against what it claimed to be.

        ``by``: the member that sealed it (authenticated), told to `on_refused` instead
        of the name it claimed.
        """
        counts = self._counts(sender, label)
        counts.batches += 1
        counts._drop_batch(reason)
        self._note_refused(sender if by is None else by, reason, 0, authentic=by is not None)

    def _note_refused(
        self, sender: str, reason: str, samples: int, *, authentic: bool = False
    ) -> None:
        """Sum up a dropped batch for the next `on_refused` (bounded: a flood costs nothing).

        ``authentic``: ``sender`` is proven (a member): invented names do not push it
        into the ``"*"`` entry.
        """
        if self.on_refused is None:
            return
        reason = str(reason)  # told as the plain string it always was (audit records keep it)
        key = (sender, reason)
        entry = self._refused.get(key)
        if entry is None:
            if len(self._refused) >= (_MAX_AUTHENTIC_KEYS if authentic else _MAX_REFUSED_KEYS):
                key = ("*", reason)
                entry = self._refused.get(key)
            if entry is None:
                entry = self._refused[key] = [0, 0]
                self._reportable.set()
        entry[0] += 1
        entry[1] += samples

    def _bad_samples(self, rec: Import, reason: DropReason, n: int) -> None:
        """Count ``n`` samples of an authentic batch dropped; sum them up for `on_bad_samples`."""
        rec._drop_samples(reason, n)
        if self.on_bad_samples is not None:
            key = (rec.sender, rec.semantic_label, str(reason))
            self._bad[key] = self._bad.get(key, 0) + n

    def _tell_refused(self) -> None:
        """Tell ``on_refused`` what was dropped since last time, one call per sender and reason."""
        bad, hook_bad = self._bad, self.on_bad_samples
        if bad and hook_bad is not None:
            self._bad = {}
            for (sender, label, why), samples in bad.items():
                try:
                    hook_bad(sender, label, why, samples)
                except Exception:
                    log.exception("import[%s]: on_bad_samples failed", self.platform)
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
        take = sub.inbox.take
        wait = sub.__anext__
        n = 0
        while True:
            try:
                first = await wait()
            except StopAsyncIteration:
                break
            # what else arrived meanwhile, taken at once (one lock), up to the next yield
            for key, payload, _ in [first, *take(_YIELD_EVERY - 1 - n % _YIELD_EVERY)]:
                try:
                    handle(key, payload)
                except Exception as exc:  # never let one payload end the loop
                    # its type and where, never its text: it may quote the samples, which
                    # came encrypted (another platform's, in a log)
                    log.error(
                        "import[%s]: handling a payload of %d bytes on %s failed: %s (its "
                        "text left out), raised at:\n%s",
                        self.platform,
                        len(payload),
                        key,
                        type(exc).__qualname__,
                        "".join(traceback.format_tb(exc.__traceback__)).rstrip(),
                    )
                n += 1
            if n % _YIELD_EVERY == 0:
                # the inbox hands out what is queued without suspending: let others run
                await asyncio.sleep(0)
        self._ended(
            sub,
            f"streams subscription {self._prefix}*/**",
            "other platforms' streams to this platform are no longer received: its imports "
            "get no more samples and count none lost, while its loss reports still renew "
            "their senders' leases (the senders go on exporting)",
        )

    def _handle(self, key: str, payload: bytes) -> None:
        """One payload: open, check, decode, translate, inject; or drop and count why."""
        sender, _, label = key[len(self._prefix) :].partition("/")
        if not sender or not label:
            self._refuse(sender or "?", label or "?", DropReason.MALFORMED)
            return
        try:
            frm, body = self.sessions.open_bytes(payload)
        except AuthenticationError as exc:
            self._refuse(sender, label, exc.code)
            return
        except Exception:
            self._refuse(sender, label, DropReason.MALFORMED)
            return
        if frm != sender:
            # authentic, but published under another platform's name: trust neither; the
            # audit names who sealed it (proven), not whom it would pass for
            self._refuse(sender, label, DropReason.WRONG_SENDER, by=frm)
            return
        try:
            batch = read_batch(body)
        except ValueError:
            self._refuse(frm, label, DropReason.MALFORMED, by=frm)
            return
        semantic, seq, samples, history, recovered, ended = batch
        if semantic != label:
            self._refuse(frm, label, DropReason.WRONG_LABEL, by=frm)
            return
        rec = self._imports.get((frm, semantic))
        if rec is None:
            local = self._translate(frm, semantic)
            if local is None:
                counts = self._counts(frm, semantic)
                counts.batches += 1
                counts.received += len(samples)
                counts._drop_samples(DropReason.UNAGREED, len(samples))
                self._note_refused(frm, DropReason.UNAGREED, len(samples), authentic=True)
                return
            rec = self._new_import(frm, semantic, local)
        n = len(samples)
        rec.batches += 1
        rec.received += n
        if frm in self._gone:
            # still in flight when the sender's token went (its streams are ended), or sent
            # by a member after it said it left: summed up in the audit too
            self._bad_samples(rec, DropReason.SENDER_GONE, n)
            return
        if recovered:
            assert seq is not None  # read_batch checks it
            self._inject_resent(rec, seq, samples)
            return
        rec.history = history
        if seq is not None:
            sequence = rec.sequence
            if seq == sequence.next:
                # the usual batch, right after the last: `arrived` would only move `next`
                sequence.next = seq + n
            else:
                wanted = sequence.arrived(seq, n, history)
                if wanted is not None:
                    self._ask_resend(rec, *wanted)
        if n:  # else a keepalive
            self._add(rec, samples)
        if ended is not None and not rec.ended:
            # the sender ended the export by itself (we did not report in time)
            # its word, bounded: one line, however long and whatever it holds
            log.warning("import[%s]: %s ended %s: %s", self.platform, frm, semantic, quoted(ended))
            self._end(rec)
            if self.on_export_ended is not None:
                self._tasks.spawn(
                    self._tell("on_export_ended", frm, semantic), f"import[{self.platform}].ended"
                )

    def _translate(self, sender: str, semantic: str) -> str | None:
        try:
            return self.translate(sender, semantic)
        except Exception:
            log.exception("import[%s]: translate(%r, %r) failed", self.platform, sender, semantic)
            return None

    def _inject_resent(self, rec: Import, first: int, samples: list[Any]) -> None:
        """Add resent samples that are still missing here; count them recovered."""
        wanted: list[Any] = []
        for lo, hi in rec.sequence.fill(first, first + len(samples)):
            wanted += samples[lo - first : hi - first]
        if not wanted:
            rec._drop_samples(DropReason.DUPLICATE, len(samples))
            return
        if len(wanted) < len(samples):
            rec._drop_samples(DropReason.DUPLICATE, len(samples) - len(wanted))
        injected = rec.injected
        self._add(rec, wanted)
        rec.sequence.recover(rec.injected - injected)

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
            self._bad_samples(rec, DropReason.MALFORMED, n - len(out))
        if not out:
            return
        source = rec.source
        if source is None or not source.running or source.generator.closed:
            source = self._open_source(rec)
            if source is None:
                rec._drop_samples(DropReason.LABEL_TAKEN, len(out))
                return
        try:
            # the source's own push_batch, one call less (this runs per batch)
            source.generator.publish_batch(out, ordered=True)
        except Exception as exc:
            log.warning("import %s:%s: not injected: %s", rec.sender, rec.semantic_label, exc)
            self._bad_samples(rec, DropReason.REJECTED, len(out))
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
        if self._presence is None:  # its own watch (one it is given, its giver watches)
            self._ended(
                presence,
                f"presence watch {wire_key(self.federation, 'alive', '*')}",
                "senders coming and going are no longer seen: the streams of one that goes "
                "are no longer ended here (on_sender_gone untold), and one seen gone before "
                "that comes back has its samples dropped (sender-gone) and no loss reports "
                "(its exports here end at their lease)",
            )

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
