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
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import msgpack
import orjson

from ._acl import (
    _SHALLOW_JSON_BYTES,
    _TRUSTED_NESTING,
    MAX_MESSAGE_BYTES,
    WIRE_VERSION,
    ACLMessage,
    Performative,
    _all_scalars,
    _constructed,
    _nests_less,
    _new_message,
    _quick_fields,
    _set_dict,
    _set_extra,
    _set_fields_set,
    _set_private,
    nesting_bound,
    platform_of,
    reply_json,
)
from ._agent import _RUNNING, LATER, Agent, MessageTemplate, failure_of, on
from ._aio import Ticker, call_in_loop, together
from ._bucket import TokenBucket, check_rates
from ._exceptions import (
    AgentError,
    AuthenticationError,
    MessageError,
    SecurityError,
    TransportClosed,
    TransportError,
    UnknownPlatform,
    UnknownSession,
)
from ._gate import shed_counts
from ._kxgate import DEFAULT_KX_LIMIT, KxGate, KxLimit
from ._presence import PRESENCE_BURST, PRESENCE_RATE, presence_bucket
from ._protocols import Refuse, on_query
from ._quote import quoted
from ._records import Frozen
from ._security import (
    Clock,
    Handshake,
    KeyPair,
    SecurityPolicy,
    SessionTable,
    TrustStore,
    WatchGate,
    _untrusted,
    fingerprint,
    seal_owner_batch,
    sign_owner_batch,
    watch_answer,
)
from .transports import Handle, Inbox, Presence, Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform, SenderStats

log = logging.getLogger(__name__)
# read once: an enum member read from its class costs ~8x a global's read in 3.11 (the lane
# answers with it)
_INFORM = Performative.INFORM

_loads = orjson.loads

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

# What local agents answer to: the opening performatives and a cancel (answered inform).
ANSWERED = INITIATING | {Performative.CANCEL}

RATE_LIMIT_REASON = "rate limit exceeded"

WATCH_RATE = 20.0
"""Watch requests per second (bursts as many) handed to the event loop; the rest are shed."""

AUDIT_HOLD = 1.0
"""Seconds an unheard audit batch is kept for a subscriber the transport tells of late."""
_AUDIT_HELD = 16  # unheard audit batches kept at most: memory, if ``audit_interval`` is short
_PRESENCE_REPORT_INTERVAL = 1.0  # seconds between audit records of ignored changes

_MIRROR_CHUNK = 512 * 1024

_KX_ERRORS_KEPT = 8  # error replies to a key exchange quoted when none finishes it

# An operator asking "why does it not answer me" reads the log, not the sealed audit: a
# refused untrusted sender is logged once per name per interval, a few names an interval,
# the others summed up in one line (anyone may claim any name, as often as it likes).
UNTRUSTED_LOG_INTERVAL = 30.0
"""Seconds between two log lines about one untrusted sender."""
_UNTRUSTED_LOGGED = 8  # names logged one by one per interval
_UNTRUSTED_NAME = 64  # characters of a claimed name logged

MAX_BATCH = 256
"""At most this many ACL messages in one envelope (a batch: ``docs/wire.md``)."""


@dataclass(init=False, repr=False, eq=False)
class RateLimit(Frozen):
    """How much each other platform may send here, enforced after authentication.

    Token buckets per authenticated platform: ``rate`` initiating messages (requests,
    queries, subscribes, calls for proposals: each makes this platform work and answer)
    per second with bursts of ``burst``, and ``total_rate``/``total_burst`` for all of its
    messages (replies and informs included; checked before the body is parsed, so
    over-limit input costs little more than its MAC). Of what is dropped, at most
    ``refusals`` requests per second per platform are answered with ``refuse``
    (reason ``"rate limit exceeded"``); the rest are only counted. A platform's limiting
    is audited once per ``report_interval`` seconds (with the count), not per message.
    ``unauthenticated`` bounds the audit records per second for envelopes that do not
    open (all sources together: their claimed sender is not proven); the rest are counted
    and summed up once per ``report_interval``. See ``docs/security.md``.
    """

    __slots__ = (
        "burst",
        "rate",
        "refusals",
        "report_interval",
        "total_burst",
        "total_rate",
        "unauthenticated",
    )
    rate: float
    burst: float
    total_rate: float
    total_burst: float
    refusals: float
    report_interval: float
    unauthenticated: float

    def __init__(
        self,
        rate: float = 5_000.0,
        burst: float = 200.0,
        total_rate: float = 50_000.0,
        total_burst: float = 50_000.0,
        refusals: float = 10.0,
        report_interval: float = 1.0,
        unauthenticated: float = 200.0,
    ) -> None:
        object.__setattr__(self, "rate", rate)
        object.__setattr__(self, "burst", burst)
        object.__setattr__(self, "total_rate", total_rate)
        object.__setattr__(self, "total_burst", total_burst)
        object.__setattr__(self, "refusals", refusals)
        object.__setattr__(self, "report_interval", report_interval)
        object.__setattr__(self, "unauthenticated", unauthenticated)
        self.__post_init__()

    def __post_init__(self) -> None:
        check_rates(
            self,
            "RateLimit",
            (
                "rate",
                "burst",
                "total_rate",
                "total_burst",
                "refusals",
                "report_interval",
                "unauthenticated",
            ),
            ("burst", "total_burst"),
            "every message",
        )


DEFAULT_RATE_LIMIT = RateLimit()  # frozen: one instance serves every channel


def _burst_of(rate: float) -> float:
    """A second's worth, and at least one when any: a rate of 0.5/s still allows one."""
    return max(1.0, rate) if rate > 0 else 0.0


class _Sender:
    """The rate-limit state of one authenticated platform."""

    __slots__ = (
        "last_report",
        "lock",
        "pending",
        "pending_refused",
        "refusals",
        "requests",
        "stats",
        "total",
    )

    def __init__(self, limit: RateLimit | None, stats: SenderStats, now: float) -> None:
        self.stats = stats
        self.requests = TokenBucket(limit.rate, limit.burst, now) if limit else None
        self.total = TokenBucket(limit.total_rate, limit.total_burst, now) if limit else None
        self.refusals = (
            TokenBucket(limit.refusals, _burst_of(limit.refusals), now) if limit else None
        )
        self.pending = 0  # limited since the last audit record
        self.pending_refused = 0
        self.last_report = -math.inf
        # held around every check-then-take of ``requests`` and ``total``: zenoh's thread
        # takes from them too (`InterfaceAgent.lane`), never waiting for this lock
        self.lock = threading.Lock()


class AuditLog:
    """What the Interface Agent decided about each remote message: kept, written, published.

    The last ``keep`` records stay in memory (`records`); with ``path`` they are appended
    to a JSON-lines file; with a platform they are published in batches on
    ``dyknow/<fed>/v1/audit/<platform>`` (one JSON record per line), so one publish
    carries many records and auditing does not double the transport's load.

    The file holds at most ``max_bytes`` (whole records; one longer record alone): the
    record that would pass it goes to a new file, the full one becomes ``<path>.1``, the
    older ones ``<path>.2`` ... ``<path>.<backups>``, and the oldest beyond is deleted.
    """

    DEFAULT_MAX_BYTES = 64 * 1024 * 1024
    DEFAULT_BACKUPS = 4

    def __init__(
        self,
        *,
        keep: int = 10_000,
        path: str | Path | None = None,
        platform: str | None = None,
        max_bytes: int = DEFAULT_MAX_BYTES,
        backups: int = DEFAULT_BACKUPS,
    ) -> None:
        if max_bytes < 1:
            raise ValueError(f"the audit file's max_bytes must be at least 1, not {max_bytes}")
        if backups < 0:
            raise ValueError(f"the audit file's backups must be 0 or more, not {backups}")
        self.max_bytes = max_bytes
        self.backups = backups
        # each entry a record (a dict), or an accepted message as a tuple (`accepted_entry`):
        # the common record of a flood, made a dict or a JSON line only when read
        self._log: deque[Any] = deque(maxlen=keep)
        self.counts: dict[str, int] = {"accepted": 0, "refused": 0, "dropped": 0}
        self.path = Path(path) if path is not None else None
        self.platform = platform
        # bounded too: records pile up here if nothing flushes them
        self._pending: deque[Any] = deque(maxlen=keep)
        # called when a record comes while none is pending: wakes a flush asleep while idle
        self.wake: Callable[[], None] | None = None
        # the JSON of an accepted record between "ts" and "conversation_id", per
        # (peer, sender, receiver, performative): a platform hears few such combinations
        self._lines: dict[tuple[Any, ...], bytes] = {}

    @property
    def records(self) -> deque[dict[str, Any]]:
        """The last records kept in memory, oldest first (a copy: the log goes on)."""
        log = self._log
        return deque((self._as_dict(e) for e in log), maxlen=log.maxlen)

    def last(self, n: int) -> list[dict[str, Any]]:
        """Copies of the last ``n`` records (none for n <= 0)."""
        entries = list(self._log)[-n:] if n > 0 else []
        return [dict(self._as_dict(e)) for e in entries]

    def record(self, **fields: Any) -> None:
        """Add one decision (``verdict`` is accepted, refused or dropped).

        Every record has the fields of ``docs/wire.md`` (None when unknown), so readers
        of the JSON lines need not guess which ones a kind of refusal leaves out. A
        ``reason`` holding characters that are not printable has them escaped (`quoted`).
        """
        reason = fields.get("reason")
        if type(reason) is str and not reason.isprintable():
            # a reason may echo another platform's words: whatever a site failed to
            # bound, a record's reason holds no raw newline or escape (each escaped, none cut)
            fields["reason"] = quoted(reason, 10 * len(reason))
        rec = self._new_record(**{"verdict": "accepted", **fields})
        self._log.append(rec)
        first = not self._pending  # the first since the flush took them: it may sleep
        self._pending.append(rec)
        if first and self.wake is not None:
            self.wake()  # after the append: a flush woken from another thread finds it
        verdict = rec["verdict"]
        self.counts[verdict] = self.counts.get(verdict, 0) + 1

    def _new_record(self, **fields: Any) -> dict[str, Any]:
        """A record with every field of ``docs/wire.md``, None where ``fields`` say nothing."""
        return {
            "v": WIRE_VERSION,
            "ts": time.time(),
            "platform": self.platform,
            "from": None,
            "sender": None,
            "receivers": None,
            "performative": None,
            "conversation_id": None,
            "verdict": None,
            "reason": None,
            **fields,
        }

    def accepted(self, peer: str, message: ACLMessage, ts: float | None = None) -> None:
        """Record that ``message`` from platform ``peer`` was admitted (at ``ts``, Unix s)."""
        self.add_accepted((accepted_entry(time.time() if ts is None else ts, peer, message),))

    def add_accepted(self, entries: Sequence[tuple[Any, ...]]) -> None:
        """Record admitted messages given as their `accepted_entry` tuples (a batch's at once)."""
        self._log.extend(entries)
        first = not self._pending  # a flush may sleep for want of records
        self._pending.extend(entries)
        if first and self.wake is not None:
            self.wake()  # after the append: a flush woken from another thread finds them
        self.counts["accepted"] += len(entries)

    def _as_dict(self, entry: Any) -> dict[str, Any]:
        """A log entry as its record."""
        if type(entry) is not tuple:
            return entry
        ts, peer, sender, receivers, performative, conversation_id = entry
        return {
            "v": WIRE_VERSION,
            "ts": ts,
            "platform": self.platform,
            "from": peer,
            "sender": sender,
            "receivers": [receivers] if type(receivers) is str else list(receivers),
            "performative": performative,
            "conversation_id": conversation_id,
            "verdict": "accepted",
            "reason": None,
        }

    def _middle(self, key: tuple[Any, ...]) -> bytes:
        """The JSON of an accepted record from "platform" to "performative" (no braces)."""
        lines = self._lines
        if len(lines) >= _MAX_AUDIT_LINES:
            lines.clear()
        peer, sender, receiver, performative = key
        middle = orjson.dumps(
            {
                "platform": self.platform,
                "from": peer,
                "sender": sender,
                "receivers": [receiver],
                "performative": performative,
            }
        )[1:-1]
        if len(middle) <= _MAX_AUDIT_LINE:  # a long one (names made up by a peer) is not kept
            lines[key] = middle
        return middle

    def take(self) -> bytes:
        """The records not yet flushed, as JSON lines (empty when none); appended to ``path``."""
        if not self._pending:
            return b""
        pending = list(self._pending)
        self._pending.clear()
        out: list[bytes] = []
        add = out.append
        dumps, lines = orjson.dumps, self._lines
        last_ts, ts_json = None, b""
        last: Any = None  # the last accepted entry pieced together, and its line
        line = b""
        for e in pending:
            if type(e) is tuple:
                if e == last:
                    # the same record again: a batch's messages of one conversation
                    # (equal times make the same JSON, as ``ts_json`` below assumes)
                    add(line)
                    continue
                ts, peer, sender, receivers, performative, conv = e
                if type(receivers) is str:
                    # an accepted message to one agent: its line pieced together, the
                    # same bytes orjson makes of the record (fields in the same order)
                    key = (peer, sender, receivers, performative)
                    middle = lines.get(key) or self._middle(key)
                    if ts != last_ts:  # a batch's records share theirs
                        last_ts, ts_json = ts, dumps(ts)
                    line = (
                        b'{"v":%d,"ts":%b,%b,"conversation_id":%b,"verdict":"accepted",'
                        b'"reason":null}\n'
                        % (WIRE_VERSION, ts_json, middle, b"null" if conv is None else dumps(conv))
                    )
                    add(line)
                    last = e
                    continue
                e = self._as_dict(e)
            add(dumps(e) + b"\n")
        data = b"".join(out)
        if self.path is not None:
            try:
                self._append(self.path, data)
            except OSError as exc:
                # a full disk must not stop the Interface Agent, nor the published audit
                log.warning("audit file %s not written: %s", self.path, exc)
        return data

    def _append(self, path: Path, data: bytes) -> None:
        """Append the JSON lines ``data`` to ``path``, rotating it at ``max_bytes``."""
        fresh = False  # the file was rotated just now: it takes a line whatever its length
        if not path.parent.is_dir():
            # a config's `audit = "audit/<platform>.jsonl"` names a folder nobody made yet
            path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            with path.open("ab") as f:
                size = f.tell()  # the file's end (append mode), whoever wrote or truncated it
                room = self.max_bytes - size
                if len(data) <= room:
                    f.write(data)
                    return
                # the whole lines that fit; the rest goes to the next file
                cut = data.rfind(b"\n", 0, max(room, 0)) + 1
                if not cut and (fresh or not size):
                    cut = data.find(b"\n") + 1 or len(data)  # longer than the bound: alone
                if cut:
                    f.write(data[:cut])
                    data = data[cut:]
                    if not data:
                        return
                # before its name changes: what is written stays written, even on power loss
                f.flush()
                os.fsync(f.fileno())
            self._rotate(path)
            fresh = True

    def _rotate(self, path: Path) -> None:
        """Move ``path`` to ``path.1`` (and each backup one up), and begin it anew.

        Each step is one atomic rename, the oldest last to go (overwritten): a crash
        between two leaves a gap in the numbers, never a record lost.
        """
        names = [path, *(path.with_name(f"{path.name}.{i}") for i in range(1, self.backups + 1))]
        # read before the names change; the highest of all, not the current file's: a
        # crash between the renames and the record leaves a current file without one
        number = max(_rotated_number(n) for n in names) + 1
        if self.backups == 0:
            path.unlink(missing_ok=True)
        for i in range(self.backups, 0, -1):
            with contextlib.suppress(FileNotFoundError):
                os.replace(names[i - 1], names[i])
        previous = names[1].name if self.backups else None
        note = f"audit file rotated at {self.max_bytes} bytes: the records before this one " + (
            f"are in {previous}" if previous else "were deleted (no backups kept)"
        )
        # `previous` names the file as it is now; the next rotation renames it, so the
        # chain is followed by `file`, which no rename changes: file n follows file n - 1
        record = self._new_record(
            reason=note, stage="audit-rotated", previous=previous, file=number
        )
        with path.open("ab") as f:
            f.write(orjson.dumps(record) + b"\n")
        _fsync_dir(path.parent)


def _rotated_number(path: Path) -> int:
    """The ``file`` number of the audit file ``path`` (its rotation record's); 0 without one.

    0 is a file no rotation began: the first one, or a file written by an earlier release.
    """
    try:
        with path.open("rb") as f:
            first = f.readline(_MAX_FIRST_LINE)
    except OSError:
        return 0
    try:
        record = orjson.loads(first)
    except orjson.JSONDecodeError:
        return 0
    if not isinstance(record, dict) or record.get("stage") != "audit-rotated":
        return 0
    number = record.get("file")
    return max(number, 0) if isinstance(number, int) and not isinstance(number, bool) else 0


_MAX_FIRST_LINE = 65536  # bytes read of an audit file's first line: a rotation record is < 1 KB


def _fsync_dir(directory: Path) -> None:
    """Make the renames in ``directory`` durable (where the system allows it)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # e.g. Windows opens no directory: its renames stand as they are
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def accepted_entry(ts: float, peer: str, message: ACLMessage) -> tuple[Any, ...]:
    """The audit log's entry for an accepted message: what its record says, and no more.

    Strings and a float only (one receiver as a str, several as a tuple): the garbage
    collector stops tracking such a tuple, and the message itself is not kept alive.
    """
    receivers = message.receivers
    return (
        ts,
        peer,
        message.sender,
        receivers[0] if len(receivers) == 1 else tuple(receivers),
        _NAMES[message.performative],
        message.conversation_id,
    )


_NAMES = {p: p.value for p in Performative}
_ABSENT = object()  # a key a decoded message lacks (`dict.pop`'s default)


class _Lanes:
    """How many Interface Agents of this process have their lane on (any loop, any thread).

    With more than one, their envelopes are opened on the event loop again, not on
    zenoh's threads: the several sessions' threads opening there contended with the
    loops for the GIL (bench scale, 8 platforms a process: p50 and p99 slower than the
    loop's own path), where one platform a process gained (round trip 0.83x).
    """

    __slots__ = ("lock", "open")

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.open = 0

    def change(self, by: int) -> None:
        """One more (``by`` 1) or one fewer (-1) lane open in this process."""
        with self.lock:
            self.open += by


_LANES = _Lanes()
# a queued item the lane did not open (`_LANES.open` > 1): its payload, for the loop to open
_RAW: Any = object()
# what `_lane_answer` did with a message: answered there; a reply handed to the loop in
# `_lane_book`; neither (the loop decides it, queued as always)
_ANSWERED, _HANDED, _LEFT = object(), object(), object()
"""Each performative's name, a plain str (cheaper to look up than ``.value``)."""


class _Written:
    """An answer's JSON bytes, written already, to send as its message (`send`, `send_now`
    and `join_batch` ask a message for ``to_json()`` and ``reply_with`` only): a reply the
    lane counted, resent as it was counted (`_lane_answer`)."""

    __slots__ = ("body",)
    reply_with = None  # a reply asks no answer

    def __init__(self, body: bytes) -> None:
        self.body = body

    def to_json(self) -> bytes:
        """The bytes, as written."""
        return self.body


_MAX_AUDIT_LINES = 4096
_MAX_AUDIT_LINE = 1024  # bytes of a kept line's middle: 4096 of a message's size would be 1 GiB


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


class InterfaceAgent:
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

    def __init__(
        self,
        keys: KeyPair,
        trust: TrustStore,
        *,
        policy: SecurityPolicy | None = None,
        audit_path: str | Path | None = None,
        audit_max_bytes: int = AuditLog.DEFAULT_MAX_BYTES,
        audit_backups: int = AuditLog.DEFAULT_BACKUPS,
        publish_audit: bool = True,
        seal_audit: bool = True,
        watchable: bool = True,
        watch_lease: float = 10.0,
        audit_interval: float = 0.25,
        handshake_timeout: float = 2.0,
        rehandshake_interval: float = 5.0,
        max_bytes: int = MAX_MESSAGE_BYTES,
        clock: Clock = time.time,
        rate_limit: RateLimit | None = DEFAULT_RATE_LIMIT,
        monotonic: Callable[[], float] = time.monotonic,
        kx_limit: KxLimit | None = DEFAULT_KX_LIMIT,
        batch: bool = True,
        lane: bool = True,
        binary_acl: bool = True,
        lane_replies: bool = True,
    ) -> None:
        self.keys = keys
        self.trust = trust
        self.policy = policy or SecurityPolicy()
        self.audit = AuditLog(
            path=audit_path,
            platform=keys.platform,
            max_bytes=audit_max_bytes,
            backups=audit_backups,
        )
        self.audit.wake = self._wake_flush
        # the audit flush sleeps while it has nothing to do (`_flush_audit`); any thread wakes it
        self._flush_idle = False
        self._flush_due = asyncio.Event()
        self._flush_loop: asyncio.AbstractEventLoop | None = None
        self.publish_audit = publish_audit
        self.seal_audit = seal_audit
        # Audit batches nobody could receive are not sealed nor published, but kept for
        # `AUDIT_HOLD` s (at most `_AUDIT_HELD` of them): a watcher that came meanwhile
        # (the transport tells of it late) gets them with the next batch published
        self._audit_held: deque[tuple[float, bytes]] = deque(maxlen=_AUDIT_HELD)
        self.audit_published = 0  # audit batches sealed and published, since start
        self.audit_unheard = 0  # audit batches not published: no subscriber, since start
        self.watchable = watchable
        self.watch_lease = watch_lease
        # what the owner watches: (kind, peer, time, body) while a lease runs; bounded, as
        # nothing drains it faster than the flush interval (an overflow loses the oldest)
        self.mirroring = False
        self._mirror: deque[tuple[str, str, float, bytes]] = deque(maxlen=16_384)
        self._mirror_until = -math.inf
        self._watch_handle: Handle | None = None
        self._watch_gate = WatchGate(keys, trust.federation, policy=self.policy, clock=clock)
        self._owner_clock = clock  # the time signed into the batches for the owner
        # watch requests are screened on the transport's thread, as key exchanges are: a
        # flood of them would cost the event loop a task each (the owner asks once a lease)
        self._watch_lock = threading.Lock()
        self._watch_bucket = TokenBucket(WATCH_RATE, WATCH_RATE, monotonic())
        self.watch_shed = 0  # watch requests dropped before the event loop, since start
        self.watch_refused = 0  # watch requests let through whose check refused them
        self._watch_shed_pending = 0  # since the last audit record
        self.audit_interval = audit_interval
        self.handshake_timeout = handshake_timeout
        self.rehandshake_interval = rehandshake_interval
        self.max_bytes = max_bytes
        self.handshake = Handshake(keys, trust, policy=self.policy, clock=clock)
        self.sessions = SessionTable(keys.platform, trust, policy=self.policy, clock=clock)
        self.binary_acl = binary_acl
        # how every ACL envelope is sealed (the form a receiver tells by its first byte);
        # chosen again at start, as batching is
        self._seal = self.sessions.seal_binary if binary_acl else self.sessions.seal
        self._handshakes: dict[str, asyncio.Future[None]] = {}
        # the key exchange under way with each peer, ended at once by its signed leave
        # per peer, the key exchange under way with it and when it began (clock s)
        self._exchanging: dict[str, tuple[asyncio.Timeout, float]] = {}
        self._clock = clock
        self._last_rehandshake: dict[str, float] = {}
        # Liveliness is not authenticated: per trusted peer, the presence changes acted on
        # (`_presence_admits`), when one last lifted its re-handshake limiter, the changes
        # ignored since the last audit record, and the doubt that stands in for them later
        self._presence_buckets: dict[str, TokenBucket] = {}
        self._presence_lifted: dict[str, float] = {}
        self._presence_ignored: dict[str, int] = {}
        self._presence_last_report = -math.inf
        self._presence_later: dict[str, asyncio.TimerHandle] = {}
        self._subs: list[Subscription[Any]] = []
        self._kx: Handle | None = None
        self._host: AgentPlatform | None = None
        self.agent: Agent | None = None
        if rate_limit is not None and not isinstance(rate_limit, RateLimit):
            raise TypeError(f"rate_limit: expected a RateLimit or None, got {rate_limit!r}")
        self.rate_limit = rate_limit
        self._monotonic = monotonic
        self._senders: dict[str, _Sender] = {}
        # envelopes that do not open: their audit records share one budget (any source)
        self._unauth = (
            TokenBucket(rate_limit.unauthenticated, _burst_of(rate_limit.unauthenticated), 0.0)
            if rate_limit is not None
            else None
        )
        self._unauth_pending = 0
        self._unauth_last_report = -math.inf
        self._untrusted_logged: set[str] = set()  # names logged in the current interval
        self._untrusted_unlogged = 0  # refusals of other names since, summed up next
        self._untrusted_since = -math.inf
        if kx_limit is not None and not isinstance(kx_limit, KxLimit):
            raise TypeError(f"kx_limit: expected a KxLimit or None, got {kx_limit!r}")
        # key-exchange requests are screened on the transport's thread (see _kxgate)
        self.kx_gate = (
            KxGate(self.handshake, kx_limit, monotonic=monotonic, on_shed=self._count_shed)
            if kx_limit is not None
            else None
        )
        self._alive: set[str] = set()
        self.reply_to_refused = 0  # requests whose reply_to named a third platform
        self.batch = batch
        self._batching = False  # batch, and the transport can publish from a loop callback
        # per platform: the messages waiting for the end of this turn of the loop (the
        # entry exists while a flush is scheduled: a message went out alone this turn)
        self._outbox: dict[str, list[bytes]] = {}
        # the platform's loop, once started (each asyncio.get_running_loop is a getpid
        # system call in Python 3.11, and every first message of a turn needs the loop)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._outbox_bytes: dict[str, int] = {}
        # the platforms the last turn that sent to them sent two messages or more: a burst,
        # whose next turn (however late) batches its first message too (one envelope a turn)
        self._bursting: set[str] = set()
        # the platforms a message asking an answer went to alone, opening no batch, since
        # the last envelope opened from them or their last batch: the next one opens it
        self._lone: set[str] = set()
        # each peer's ACL key (``host.key("acl", peer)``), made once: one per trusted peer
        self._acl_keys: dict[str, str] = {}
        self.batches_lost = 0  # batched messages a failed flush did not send
        # per peer, the missing count last warned of and when (`_report_missing`)
        self._missing_warned: dict[str, tuple[int, float]] = {}
        self.missing_warn_interval = 60.0
        self.revoked = 0  # platforms removed from the trust store while running, since start
        self.unsent_revoked = 0  # messages for a platform revoked then, not sent, since start
        self._revoked: set[str] = set()  # revoked while running: what is for them is dropped
        self._unhook_trust: Callable[[], None] | None = None
        self.lane = lane
        self._lane_on = False  # the inbox is opened on the transport's thread (`_lane_take`)
        self._lane_inbox: Inbox[Any] | None = None  # its queue for the loop, then
        self._lane_lock = threading.Lock()
        # per peer: its ACL envelopes queued for the event loop or being taken there, and
        # the one the lane is deciding; the lane answers only when it is the peer's only one
        # (its key exchanges, directory statements and leave come on keys of their own,
        # which zenoh orders with none of these: not counted)
        self._lane_queued: dict[str, int] = {}
        self._lane_raw = 0  # queued unopened (`_RAW`) or taken by the loop: none answered before
        # answered on the transport's thread, to be counted and audited on the loop
        # and the replies it handed to the loop to be taken into their conversations:
        # ``(peer, entry, agent)`` and ``(peer, body, message, forgotten)``, in order
        self._lane_done: deque[tuple[Any, ...]] = deque()
        # `_lane_book` is due (the audit flush woken or ticking, or posted) and has not run
        self._lane_posted = False
        # `_lane_book` is posted to the loop for a reply and has not run: a reply is never
        # left for the audit flush's tick, where the answers' bookings may wait
        self._lane_reply_posted = False
        # the session the lane took to its message budget and asked the loop to renew once
        self._lane_renewing: object = None
        self.answered_on_thread = 0  # of ``answered_at_once``, on the transport's thread
        self.lane_replies = lane_replies
        # a reply handed to the loop waits in `_lane_done`: the loop has work, so what comes
        # meanwhile goes to it unopened, as while the inbox holds anything
        self._lane_handed = False
        self.replies_on_thread = 0  # replies opened and parsed there, taken by `_lane_book`
        self.lane_failed = 0  # bookings and hand-overs `_lane_book` skipped as they raised
        self.inbox_failed = 0  # items the inbox's consumer (`_receive`) skipped as they raised

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

    # -- receiving ----------------------------------------------------------------------------

    async def _receive(self, inbox: Subscription[Any]) -> None:
        """The inbox's consumer: each ACL envelope opened (unless the lane did), taken.

        An item whose taking raises costs only itself: logged with what failed, counted in
        ``inbox_failed``, the lane's count it held released; the consumer goes on (else
        nothing of any peer would be taken any more)."""
        host = self._require_host()
        open_envelope = self.sessions.open
        stats = host.stats
        lane = self._lane_on
        lone = self._lone
        n = 0
        async for item in inbox:
            n += 1
            if not n & 63:
                # Getting a queued item never suspends, and dropping one is cheap: without
                # this a flood would hold the loop, and no agent would run to answer others.
                await asyncio.sleep(0)
            peer = None
            # the lane's count the item holds until it is done with: its peer's (an
            # envelope the lane opened) or one of those left unopened (`_RAW`)
            held: Any = None
            what = "opening the envelope"
            try:
                if lane:  # opened on the transport's thread (`_lane_take`)
                    if self._lane_done and self._lane_book_before(item):
                        # what the lane answered or handed over before this came is booked
                        # (and the replies taken) before it is taken: its posted booking
                        # waits behind this turn when the inbox was being drained (no
                        # wake-up of its own put it in the queue). True: a reply went back
                        # to the inbox, and this item behind it
                        continue
                    peer, body = item[0], item[1]  # (None, error): it did not open
                    if peer is _RAW:  # several lanes in this process: opened here (`_Lanes`)
                        held, peer = _RAW, None
                        try:
                            peer, body = open_envelope(body)
                        except Exception as exc:
                            held = None
                            self._lane_raw_release()
                            what = "refusing the envelope"
                            self._not_opened(stats, exc)
                            continue
                    elif peer is None:
                        what = "refusing the envelope"
                        self._not_opened(stats, body)
                        continue
                    else:
                        held = peer
                        if item[2] != self.sessions.forgotten(peer):
                            # its sessions were forgotten since it opened (revoked): refused
                            # as the loop's own open of it now would refuse it
                            held = None
                            self._lane_release(peer)
                            what = "refusing the envelope"
                            self._not_opened(stats, self._forgotten_since(peer))
                            continue
                else:
                    try:
                        peer, body = open_envelope(item.payload)
                    except Exception as exc:
                        what = "refusing the envelope"
                        self._not_opened(stats, exc)
                        continue
                what = "taking the message"
                lone.discard(peer)  # a turn of the loop after what went to it (`_sent`)
                state = self._senders.get(peer)
                if state is None:
                    state = self._sender(host, peer)
                if body[:1] != b"[":
                    with state.lock:
                        taken = self._take_now(host, peer, state, body)
                    if not taken:
                        await self._take(host, peer, state, body)
                    continue
                what = "taking the batch"
                items = await self._batch_items(host, peer, body)
                now = self._monotonic()  # one reading: the batch arrived at once
                i, end = 0, len(items)
                while i < end:
                    with state.lock:
                        done = self._take_batch(host, peer, state, items, i, now)
                    n += done - i
                    i = done
                    if i < end:  # one the quick path leaves (a limit, a refusal …): in full
                        await self._take(host, peer, state, items[i], now)
                        i += 1
                        n += 1
                    if n >= 64:
                        n = 0
                        await asyncio.sleep(0)
            except Exception:
                self._inbox_failed(what, peer, item)
            finally:
                if held is not None:
                    self._release_held(held, item)
        host._inbox_ended(inbox)

    def _release_held(self, held: Any, item: Any) -> None:
        """The lane's count ``item`` held, released; a release that raises (a fault of the
        code: the count out of step) costs only itself, else it would end the inbox's
        consumer and nothing of any peer would be taken any more."""
        try:
            if held is _RAW:
                self._lane_raw_release()
            else:
                self._lane_release(held)
        except Exception:
            self._lane_failed(
                "releasing the lane's count of a message", "?" if held is _RAW else held, item
            )

    def _lane_book_before(self, item: tuple[Any, ...]) -> bool:
        """`_lane_book` before the inbox's consumer takes ``item``; one that raises (beyond
        what it contains itself) costs only itself, and ``item`` is taken as usual."""
        try:
            return self._lane_book(item)
        except Exception:
            self._lane_failed("booking what the lane took before an envelope", "?", item)
            return False

    def _inbox_failed(self, what: str, peer: str | None, item: Any) -> None:
        """Taking one item of the inbox raised: logged once (never what it holds), counted,
        skipped."""
        self.inbox_failed += 1
        log.error(
            "interface[%s]: %s from %s failed (%s): %s",
            self._me,
            what,
            peer or "?",
            _shape(item),
            _failure(),
        )

    def _forgotten_since(self, peer: str) -> AuthenticationError:
        """What opening an envelope of ``peer`` says now that its sessions are forgotten."""
        if peer not in self.trust:
            return _untrusted(peer)
        return UnknownSession(f"the session with {peer!r} was forgotten since it opened", peer)

    def _not_opened(self, stats: Any, exc: Exception) -> None:
        """An ACL envelope that did not open: counted, audited (within budget), dropped."""
        stats.unauthenticated += 1
        if isinstance(exc, AuthenticationError):
            self._drop_unauthenticated(exc.platform, f"{exc.code}: {exc.reason}")
            if isinstance(exc, UnknownSession) and exc.platform is not None:
                self.rehandshake(exc.platform)
        else:
            self._drop_unauthenticated(None, f"malformed: {exc}")

    # -- the lane: plain reads answered on the transport's thread ---------------------

    def _lane_release(self, peer: str) -> None:
        """One message of ``peer`` the loop or the lane took is done with."""
        with self._lane_lock:
            left = self._lane_queued[peer] - 1
            if left:
                self._lane_queued[peer] = left
            else:
                del self._lane_queued[peer]

    def _lane_dropped(self, item: tuple[Any, ...]) -> None:
        """The inbox was full and dropped ``item`` (oldest first): the loop never takes it."""
        if item[0] is _RAW:
            self._lane_raw_release()
        elif item[0] is not None:
            self._lane_release(item[0])

    def _lane_raw_release(self) -> None:
        """An unopened item (`_RAW`) the loop took is done with (or was dropped)."""
        with self._lane_lock:
            self._lane_raw -= 1

    def _lane_take(self, payload: bytes) -> tuple[str | None, Any, int] | None:
        """On zenoh's thread: open ``payload``; a plain read answered here (None), else
        ``(peer, body, forgotten)`` (``(None, error, 0)``: it did not open) for the event
        loop, in order (`SessionTable.open_noting`: the loop refuses it if the peer's
        sessions were forgotten since).

        An envelope opens here while nothing waits for the loop; else (or with several lanes
        in this process, `_Lanes`) it goes unopened (`_RAW`), in order, and the loop opens
        it under the same table lock. A read is answered here only while nothing of its peer
        is queued for the loop or taken there (it overtakes nothing), by `_lane_answer`.
        """
        inbox = self._lane_inbox
        if (
            _LANES.open > 1
            or self._lane_raw
            or self._lane_handed
            or (inbox is not None and inbox._items)
        ):
            # The loop is draining (or several lanes share this process): it opens this
            # one too. Opening it here would only hand the GIL to and fro (a burst of
            # replies at an asker, a flood) where the lane gains nothing: no answer here
            # can go before what waits for the loop.
            with self._lane_lock:
                self._lane_raw += 1
            return _RAW, payload, 0
        try:
            peer, body, forgets = self.sessions.open_noting(payload)
        except Exception as exc:  # the loop counts and audits it
            return None, exc, 0
        # the lock taken and released by its methods, not by `with`: ~0.8 k instructions
        # less a section on the path of every envelope the lane opens (and of what it
        # answers, `_lane_answer`, or hands over to the loop, `_lane_reply`). On zenoh's
        # thread only: on the loop's (the main thread) a signal's handler runs right after
        # a call returns, and an interrupt raised between `acquire()` and `try` would leave
        # the lock held for ever; `with` leaves no such gap (`_lane_book`, `_lane_take_reply`)
        lock = self._lane_lock
        lock.acquire()
        try:
            queued = self._lane_queued.get(peer, 0)
            self._lane_queued[peer] = queued + 1
            raw = self._lane_raw
        finally:
            lock.release()
        if queued == 0 and not raw:
            try:
                answered = self._lane_answer(peer, body, forgets)
            except Exception:  # never into zenoh's thread: the loop decides it
                # never the error's text: it may quote the body, decrypted
                log.error(
                    "interface[%s]: answering %s on the receiving thread: %s",
                    self._me,
                    peer,
                    _failure(),
                )
                answered = _LEFT
            if answered is _ANSWERED:
                lock.acquire()  # `_lane_release`, inline: every answer the lane puts
                try:
                    left = self._lane_queued[peer] - 1
                    if left:
                        self._lane_queued[peer] = left
                    else:
                        del self._lane_queued[peer]
                finally:
                    lock.release()
                return None
            if answered is _HANDED:  # a reply: its count stands until `_lane_book` takes it
                return None
        return peer, body, forgets  # its count stands until the loop has taken it

    def _lane_answer(self, peer: str, body: bytes, forgets: int) -> object:
        """`_take_now` and `_answer_at_once` of a plain read, on zenoh's thread: `_ANSWERED`;
        a reply an open conversation waits for handed to the loop (`_lane_reply`):
        `_HANDED`; else `_LEFT`, nothing taken (the loop then decides it as always).

        The same checks, limits and answer, reading only what is safe beside the loop:
        its dicts and sets by one lookup each, the sender's buckets under their lock, the
        sessions under the table's, the directory's decisions made before
        (`DirectoryFacilitator.reachable_now`), the agent's `Agent.answer_on_thread`, and
        a publisher the loop declared. What the loop alone changes (the counts, the audit
        log, a session's renewal) it does in `_lane_book`, booked before the answer is put
        and run at the audit flush's next tick (or before the loop's next take).
        """
        host = self._host
        if host is None or self.mirroring or len(body) > self.max_bytes or body[:1] == b"[":
            return _LEFT
        state = self._senders.get(peer)
        if state is None:
            return _LEFT
        try:
            obj = _loads(body)
        except orjson.JSONDecodeError:
            return _LEFT
        if (
            type(obj) is not dict
            or (fields := _quick_fields(obj)) is None
            or (len(body) >= _SHALLOW_JSON_BYTES and nesting_bound(body) >= _TRUSTED_NESTING)
        ):
            return _LEFT  # the full model's parse, on the loop
        message = _constructed(ACLMessage, fields, set(obj))
        # ``fields`` is the message's __dict__: each read a dict lookup, not a pass through
        # pydantic's attribute hook
        performative = fields["performative"]
        if performative not in INITIATING:
            return _HANDED if self._lane_reply(peer, body, message, fields, forgets) else _LEFT
        receivers = fields["receivers"]
        if len(receivers) != 1 or fields["reply_to"] or fields["in_reply_to"] is not None:
            return _LEFT
        receiver = receivers[0]
        sender = fields["sender"]
        here = host.name
        at = receiver.rpartition("@")
        if at[2] != here or sender.rpartition("@")[2] != peer or peer == here:
            return _LEFT
        agent = host._agents.get(at[0])
        if agent is None or agent._state != _RUNNING:
            return _LEFT
        answer = agent.answer_on_thread
        mailbox = agent._mailbox
        if (
            answer is None
            or agent.answer_at_once is None
            or mailbox._items
            or mailbox._waiter is None  # its receive loop is in a handler
            or agent._handlers_starting
            or fields["conversation_id"] in agent._by_conv
        ):
            return _LEFT
        df = host.df
        if df is None or not df.reachable_now(receiver, peer):
            return _LEFT
        transport = host.transport
        key = self._acl_keys.get(peer)  # made by the loop's first send to it
        if key is None or peer in self._outbox:
            # a batch of the loop's for it this turn: the answer would join it there (a
            # burst of the loop's sends is no reason: the lane's answer is in no turn)
            return _LEFT
        put = transport.declared_publisher(key)
        if put is None:
            return _LEFT
        try:
            content = answer(message)
            if content is LATER:
                return _LEFT
            # the reply's bytes alone: the message is made only if the put fails (resent)
            reply = reply_json(message, _INFORM, content, agent.aid)
            if reply is None:
                reply = message.reply(_INFORM, content, sender=agent.aid).to_json()
        except Exception:  # the loop's `answer_at_once` and handler meet it again
            return _LEFT
        total, requests = state.total, state.requests
        now = 0.0 if total is None else self._monotonic()
        lock = state.lock
        if not lock.acquire(False):
            return _LEFT  # the loop is taking from these buckets: it decides this one too
        try:
            if (total is not None and not total.ready(now)) or (
                requests is not None and not requests.ready(now)
            ):
                return _LEFT  # limited: refused, counted and audited on the loop
            if requests is not None:
                requests.tokens -= 1.0
            if total is not None:
                total.tokens -= 1.0
        finally:
            lock.release()
        entry = (
            time.time(),
            peer,
            sender,
            receiver,
            _NAMES[performative],
            fields["conversation_id"],
        )
        try:
            sealed = self._seal(peer, reply)
        except Exception:  # no session, or one past its lifetime: the loop decides it
            self._lane_give_back(state)
            return _LEFT
        # Booked before the answer leaves: whatever the peer sends once it has the answer
        # reaches the loop behind this booking (`_receive`'s check, or the posted booking's
        # FIFO place when no audit flush runs).
        done = (peer, entry, agent)
        lane_lock = self._lane_lock  # not `with`: see `_lane_take`
        lane_lock.acquire()
        try:
            self._lane_done.append(done)
            posted, self._lane_posted = self._lane_posted, True
        finally:
            lane_lock.release()
        if not posted:
            if self._flush_loop is not None:
                # booked at the audit flush's next tick (it writes the record then anyway),
                # or before the loop takes the peer's next message (`_receive`): a wake-up
                # of the loop per answer cost it more than the answer (bench scale)
                self._wake_flush()
            else:
                loop = self._loop
                try:
                    if loop is not None:
                        loop.call_soon_threadsafe(self._lane_book)
                except RuntimeError:  # the loop is closed: nobody reads the counts any more
                    pass
        session = self.sessions._tx.get(peer)  # the one just sealed on (one lookup, no lock)
        if (
            session is not None
            and session._n + session._bn >= self.policy.renew_after_messages
            and self._lane_renewing is not session
        ):
            # past its message budget: booked (and so renewed) now, once a session, not at
            # the flush's tick, which may come many answers on that session later
            self._lane_renewing = session
            with contextlib.suppress(RuntimeError):  # the loop is closed: nothing renews
                if (loop := self._loop) is not None:
                    loop.call_soon_threadsafe(self._lane_book)
        try:
            put(sealed)
        except Exception as exc:  # a transport closing
            booked = True
            with self._lane_lock:
                pending = self._lane_done
                for i, item in enumerate(pending):
                    if item is done:  # not booked yet: taken back, the loop decides it
                        del pending[i]
                        booked = False
                        if not pending:
                            # nothing left to book: the next answer wakes a booking again
                            # (a flush woken for this one finds none and does not clear it)
                            self._lane_posted = False
                        break
            if booked:
                # booked already (the loop ran between): counted once, as answered; the
                # loop sends the answer its own way (a publisher evicted meanwhile is
                # declared again there)
                log.info("interface[%s]: the lane's put to %s failed: %s", self._me, peer, exc)
                try:
                    loop = self._loop
                    if loop is not None:
                        # the very bytes counted and audited: ``content`` may have changed
                        # since they were written (an agent's shared answer), a copy or a
                        # message made of it now would send what was not counted
                        answered = cast(ACLMessage, _Written(reply))
                        loop.call_soon_threadsafe(self._lane_resend, peer, answered)
                except RuntimeError:  # the loop is closed: nobody waits for the answer
                    pass
                return _ANSWERED
            self._lane_give_back(state)
            return _LEFT
        return _ANSWERED

    def _lane_resend(self, peer: str, answer: ACLMessage) -> None:
        """On the loop: send an answer the lane booked but could not put (`send`; its bytes
        as the lane wrote them, `_Written`)."""
        host = self._host
        if host is None or self.send_now(peer, answer):
            return
        try:
            host.spawn(self._lane_send(peer, answer), "interface.lane-resend")
        except AgentError:  # the platform is closing: nobody waits for the answer
            pass

    async def _lane_send(self, peer: str, answer: ACLMessage) -> None:
        try:
            await self.send(peer, answer)
        except Exception as exc:  # as a handler's answer that could not be sent
            log.warning("interface[%s]: could not send an answer to %s: %s", self._me, peer, exc)

    @staticmethod
    def _lane_give_back(state: _Sender) -> None:
        """The tokens the lane took for a message it leaves to the loop after all."""
        total, requests = state.total, state.requests
        with state.lock:
            if requests is not None:
                requests.tokens = min(requests.burst, requests.tokens + 1.0)
            if total is not None:
                total.tokens = min(total.burst, total.tokens + 1.0)

    def _lane_reply(
        self, peer: str, body: bytes, message: ACLMessage, fields: dict[str, Any], forgets: int
    ) -> bool:
        """On zenoh's thread: hand ``message``, a reply an open conversation waits for, to
        the loop's `_lane_book`, which takes it (`_lane_take_reply`); False: not such a one.

        Only read here (one dict lookup each); the loop decides everything again.
        ``fields`` is the message's __dict__: each read a dict lookup, not a pass through
        pydantic's attribute hook.
        """
        if not self.lane_replies or fields["reply_to"]:
            return False
        host = self._host
        receivers = fields["receivers"]
        if host is None or len(receivers) != 1:
            return False
        here = host.name
        at = receivers[0].rpartition("@")
        sender = fields["sender"]
        if at[2] != here or sender.rpartition("@")[2] != peer or peer == here:
            return False
        agent = host._agents.get(at[0])
        if agent is None or agent._state != _RUNNING:
            return False
        conv = None
        if (key := fields["in_reply_to"]) is not None:
            conv = agent._by_reply.get(key)
        if conv is None and (key := fields["conversation_id"]) is not None:
            conv = agent._by_conv.get(key)
        # `conv.accepts(message)`, inline, as `Agent._deliver` has it
        if (
            conv is None
            or conv.closed
            or ((peers := conv.peers) is not None and sender not in peers)
            or ((rw := fields["reply_with"]) is not None and rw in conv._keys)
        ):
            # a reply nobody waits for, or one its conversation refuses (not from one of
            # its peers): the loop's way, as any other message
            return False
        loop = self._loop
        if loop is None:
            return False
        lock = self._lane_lock  # not `with`: see `_lane_take`
        lock.acquire()
        try:
            self._lane_done.append((peer, body, message, forgets))
            self._lane_handed = True
            posted, self._lane_reply_posted = self._lane_reply_posted, True
        finally:
            lock.release()
        if not posted:
            try:
                loop.call_soon_threadsafe(self._lane_book)
            except RuntimeError:  # the loop is closed: nobody waits for the reply
                pass
        return True

    def _lane_take_reply(
        self, host: AgentPlatform, peer: str, body: bytes, message: ACLMessage, forgets: int
    ) -> bool:
        """On the loop: what `_receive` does with a reply the lane opened and parsed; False:
        nothing taken, `_receive` must take it in full (`_lane_book` queues it back)."""
        if forgets != self.sessions.forgotten(peer):
            # revoked since it opened: refused as `_receive` refuses it (released last: one
            # that raises is released by `_lane_book`, once)
            self._not_opened(host.stats, self._forgotten_since(peer))
            self._lane_release(peer)
            return True
        if self.mirroring or len(body) > self.max_bytes:
            return False
        state = self._senders.get(peer)
        if state is None:
            return False
        total = state.total
        with state.lock:  # `with` on the loop's thread: see `_lane_take`
            now = 0.0
            if total is not None:
                now = self._monotonic()
                if not total.ready(now):
                    return False
            taken = self._take_message(host, peer, state, message, now)
        if taken:
            with self._lane_lock:  # `_lane_release`, inline: every reply the lane hands over
                left = self._lane_queued[peer] - 1
                if left:
                    self._lane_queued[peer] = left
                else:
                    del self._lane_queued[peer]
            self.replies_on_thread += 1
        return taken

    def _lane_book(self, current: tuple[Any, ...] | None = None) -> bool:
        """On the loop: count, audit and renew for what the lane answered, as `_take_now` would,
        and take the replies it handed over; True: one went back to the inbox (the loop
        takes it in full), with ``current``, the item `_receive` took, behind it.

        A booking or hand-over that raises costs only itself: logged with what failed,
        counted in ``lane_failed``, its peer's count released; the others are made."""
        inbox = self._lane_inbox
        with self._lane_lock:  # `with` on the loop's thread: see `_lane_take`
            if (
                current is None
                and self._lane_handed
                and self._lane_on
                and inbox is not None
                and inbox._items
            ):
                # A reply handed over, and what came after it already queued: the inbox's
                # consumer books it before its next take, in the same turn as what follows
                # it, as it takes a reply and what follows from the inbox (a duplicate is
                # then in the conversation before its task runs, not late after it)
                return False
            self._lane_posted = self._lane_reply_posted = self._lane_handed = False
            done = self._lane_done
            lone = None
            if len(done) == 1 and len(done[0]) == 4:
                # one reply alone, nothing booked before it (an asker's round trip): taken
                # out of the queue the lane keeps, no new one made for it
                lone = done.popleft()
            else:
                self._lane_done = deque()
        host = self._host
        if host is None:
            if lone is None:  # the queue swapped out (the lane's own is not touched here)
                done.clear()
            return False
        if lone is not None:
            peer, body, message, forgets = lone
            self._lone.discard(peer)  # a turn of the loop after what went to it (`_sent`)
            try:
                if self._lane_take_reply(host, peer, body, message, forgets):
                    return False
            except Exception:
                self._lane_failed("taking the reply handed over", peer, message)
                self._lane_release(peer)
                return False
            again: list[tuple[Any, ...]] = [(peer, body, forgets)]  # taken in full, as below
            if current is not None:
                again.append(current)
            inbox = self._lane_inbox
            if inbox is not None:
                inbox.put_front(again)
            return True
        stats = host.stats
        entries: list[tuple[Any, ...]] = []
        peers = set()
        back: list[tuple[Any, ...]] = []  # replies `_receive` takes in full after all
        behind: set[str] = set()  # their peers: what follows of them goes back too
        while done:
            item = done.popleft()
            if len(item) == 4:  # a reply (`_lane_reply`)
                if entries:  # the records in arrival order
                    self._lane_records(entries)
                    entries = []
                peer, body, message, forgets = item
                self._lone.discard(peer)  # a turn of the loop after what went to it (`_sent`)
                if peer in behind:
                    back.append((peer, body, forgets))
                    continue
                try:
                    taken = self._lane_take_reply(host, peer, body, message, forgets)
                except Exception:
                    self._lane_failed("taking the reply handed over", peer, message)
                    self._lane_release(peer)
                    continue
                if not taken:
                    back.append((peer, body, forgets))
                    behind.add(peer)
                continue
            peer, entry, agent = item
            try:
                state = self._senders.get(peer)
                if state is not None:
                    state.stats.accepted += 1
                stats.received_remote += 1
                stats.local += 1
                stats.sent_remote += 1
                agent_stats = agent.stats
                agent_stats.received += 1
                agent_stats.handled += 1
                agent_stats.answered_at_once += 1
            except Exception:
                self._lane_failed("counting the answer", peer, entry)
            self.answered_on_thread += 1
            entries.append(entry)
            peers.add(peer)
        if entries:
            self._lane_records(entries)
        for peer in peers:
            self._lone.discard(peer)  # its request, answered on the lane, came after (`_sent`)
            try:
                self.renew_if_needed(peer)
            except Exception:
                self._lane_failed("renewing the session of its answers", peer, None)
        if not back:
            return False
        if current is not None:
            back.append(current)
        if inbox is not None:
            inbox.put_front(back)
        return True

    def _lane_records(self, entries: list[tuple[Any, ...]]) -> None:
        """The audit records of what the lane answered; one add that raises costs only itself
        (not made again one by one: records kept before it raised would be doubled)."""
        try:
            self.audit.add_accepted(entries)
        except Exception:
            self._lane_failed(f"recording {len(entries)} answers", entries[0][1], entries[0])

    def _lane_failed(self, what: str, peer: str, item: Any) -> None:
        """One booking or hand-over of `_lane_book` raised: logged once (never what it
        holds), counted, skipped."""
        self.lane_failed += 1
        log.error(
            "interface[%s]: %s from %s failed (%s): %s",
            self._me,
            what,
            peer,
            _shape(item),
            _failure(),
        )

    async def _batch_items(self, host: AgentPlatform, peer: str, body: bytes) -> list[Any]:
        """The messages (decoded, not yet checked) of a batch; none when it is malformed."""
        reason = None
        if len(body) > self.max_bytes:
            reason = f"batch of {len(body)} bytes exceeds the limit of {self.max_bytes}"
        else:
            try:
                items = orjson.loads(body)
            except orjson.JSONDecodeError as exc:
                reason = f"not JSON: {exc}"
            else:
                if type(items) is list and 1 <= len(items) <= MAX_BATCH:
                    return items
                reason = f"a batch is a JSON array of 1 to {MAX_BATCH} messages"
        await host.reject(body, reason)  # counted and logged; nobody to answer
        self.audit.record(verdict="dropped", **{"from": peer}, reason=reason)
        return []

    async def _take(
        self,
        host: AgentPlatform,
        peer: str,
        state: _Sender,
        raw: Any,
        now: float = 0.0,
    ) -> None:
        """One message from ``peer`` (JSON bytes, or decoded in a batch): limit, parse, admit."""
        if self.mirroring:
            body = raw if type(raw) is bytes else _written(raw)
            self._mirror.append(("acl", peer, time.time(), body))
        if state.total is not None:
            now = now or self._monotonic()
            with state.lock:
                taken = state.total.take(now)
            if not taken:
                await self._limited(host, peer, state, raw, None, now)
                return
        try:
            if type(raw) is bytes:
                message = ACLMessage.from_json(raw, max_bytes=self.max_bytes)
            else:
                message = ACLMessage.from_parsed(raw)
        except MessageError as exc:
            await self._malformed(host, peer, raw, exc)
            return
        requests = state.requests
        if requests is not None and message.performative in INITIATING:
            with state.lock:
                taken = requests.take(now)
            if not taken:
                await self._limited(host, peer, state, raw, message, now)
                return
        state.stats.accepted += 1
        try:
            if not self._admit_now(host, peer, message):
                await self._admit(host, peer, message)
        except Exception:
            # never the error's text: it may quote the message, decrypted
            log.error("interface[%s]: delivering from %s failed: %s", self._me, peer, _failure())

    def _take_now(self, host: AgentPlatform, peer: str, state: _Sender, body: bytes) -> bool:
        """`_take` of one message (JSON bytes) in the common case, at once; else False.

        The common case is `_admit_now`'s, within ``peer``'s limits: the message valid,
        one receiver here, running with room in its mailbox; no reply_to; the sender an
        agent of ``peer``; a request only to a service ``peer`` may use. Every check is
        made before anything is taken or counted, so False leaves everything as it was,
        for `_take` to decide the message in full. Taken, the message is limited,
        counted, audited and delivered as `_take` does, without its calls per step (the
        path of every request and reply that comes alone).
        """
        if self.mirroring or len(body) > self.max_bytes:
            return False
        total = state.total
        now = 0.0
        if total is not None:
            now = self._monotonic()
            if not total.ready(now):
                return False
        # `ACLMessage.from_json`, inline (its size check is made above): the quick parse
        try:
            obj = _loads(body)
        except orjson.JSONDecodeError:
            return False
        if (
            type(obj) is dict
            and (fields := _quick_fields(obj)) is not None
            and (len(body) < _SHALLOW_JSON_BYTES or nesting_bound(body) < _TRUSTED_NESTING)
        ):
            message = _constructed(ACLMessage, fields, set(obj))
        else:
            try:
                message = ACLMessage.from_parsed(obj, nesting=nesting_bound(body))
            except MessageError:
                return False
        return self._take_message(host, peer, state, message, now)

    def _take_message(
        self, host: AgentPlatform, peer: str, state: _Sender, message: ACLMessage, now: float
    ) -> bool:
        """`_take_now` of a message parsed already, its total limit found ready at ``now``."""
        total, requests = state.total, state.requests
        # a parsed message holds every field in its __dict__: read there, each read is a
        # dict lookup rather than a pass through pydantic's attribute hook
        fields = message.__dict__
        receivers = fields["receivers"]
        if len(receivers) != 1 or fields["reply_to"]:
            return False
        receiver = receivers[0]
        sender = fields["sender"]
        here = host.name
        at = receiver.rpartition("@")
        if at[2] != here or sender.rpartition("@")[2] != peer or peer == here:
            return False
        agent = host._agents.get(at[0])
        if agent is None or agent._state != _RUNNING:  # `agent.running`, inline
            return False
        mailbox = agent._mailbox
        if len(mailbox._items) >= mailbox.maxlen >> 1:
            return False
        performative = fields["performative"]
        initiating = performative in INITIATING
        if initiating:
            if requests is not None and not requests.ready(now):
                return False
            df = host.df
            if df is None or not df.reachable(receiver, peer):
                return False
            if requests is not None:
                requests.tokens -= 1.0
        if total is not None:
            total.tokens -= 1.0
        state.stats.accepted += 1
        audit = self.audit
        # accepted_entry, inline (one receiver, this sender)
        conversation_id = fields["conversation_id"]
        entry = (time.time(), peer, sender, receiver, _NAMES[performative], conversation_id)
        audit.add_accepted((entry,))
        stats = host.stats
        stats.received_remote += 1
        if (
            agent.answer_at_once is not None
            and initiating  # admitted by the directory's access check, as no answer is
            and not mailbox._items
            and mailbox._waiter is not None  # its receive loop is in no handler
            and not agent._handlers_starting  # nor will a concurrent handler's task
            and self.sends_now(peer)  # else the read would be made twice
            and fields["in_reply_to"] is None
            and conversation_id not in agent._by_conv
            and self._answer_at_once(host, peer, agent, message)
        ):
            stats.local += 1
            return True
        try:
            agent._deliver(message)  # running, room in its mailbox: taken
        except Exception:
            log.error("interface[%s]: delivering from %s failed: %s", self._me, peer, _failure())
        else:
            stats.local += 1
        return True

    def _answer_at_once(
        self, host: AgentPlatform, peer: str, agent: Agent, message: ACLMessage
    ) -> bool:
        """Answer ``message`` by ``agent.answer_at_once`` and send it now; False: not so.

        Called for an admitted message only when the mailbox route would queue it (not a
        reply to one of the agent's conversations) and nothing waits before it: False
        leaves it to the mailbox, which then decides it as if this was never asked.
        """
        try:
            content = agent.answer_at_once(message)  # type: ignore[misc]
        except Exception:  # the handler meets it again and answers for it
            return False
        if content is LATER:
            return False
        try:
            reply = message.reply(Performative.INFORM, content, sender=agent.aid)
            if not self.send_now(peer, reply):
                return False
        except Exception:  # content an inform cannot carry: the handler's path says why
            return False
        agent_stats = agent.stats
        agent_stats.received += 1
        agent_stats.handled += 1
        agent_stats.answered_at_once += 1
        host.stats.sent_remote += 1
        return True

    def _take_batch(
        self,
        host: AgentPlatform,
        peer: str,
        state: _Sender,
        items: list[Any],
        i: int,
        now: float,
    ) -> int:
        """`_take` of a batch's decoded messages from ``items[i]`` on, while none needs a wait.

        Returns the index of the first message it left (``len(items)``: none), untouched,
        for `_take`: a bad message, a limit reached, a receiver that is not ready, anything
        but the common case of `_admit`. Each message taken is checked, counted against
        the limits, audited and delivered as `_take` would, in one loop without a call per
        step (this is the path a flood takes, message after message); the messages for
        one agent are handed over together (`Agent._deliver_batch`), once decided.
        """
        end = len(items)
        if self.mirroring:
            return i
        total, requests = state.total, state.requests
        if total is not None:
            total.ready(now)  # refilled once: ``now`` stays the same for the batch
        from_parsed = ACLMessage.from_parsed
        agents = host._agents
        here = host.name
        if peer == here:  # a message claiming this platform's sender: `_take` drops it
            return i
        df = host.df
        audit = self.audit
        entries: list[tuple[Any, ...]] = []  # logged together, at the end
        add_entry = entries.append
        ts = time.time()  # one decision time for the batch, as one arrival time
        start = i
        # The messages taken for one agent, handed over together when the next is for
        # another one, or at the end (nothing runs in between: the same as one by one).
        run: list[ACLMessage] = []
        run_agent: Agent | None = None
        # what was found of the last receiver and sender, unchanged within the batch (an
        # agent neither starts nor stops meanwhile): a batch is mostly one conversation
        last_receiver: str | None = None
        last_sender: str | None = None
        room = 0  # how many more the receiver's mailbox takes before it is half full
        # A batch is mostly one header (all but the content) again and again: a message
        # whose header equals that of the last one taken (the first of a run) is valid
        # and admitted as that one was, its fields a copy of that one's: only what is
        # its own is checked (content's depth, the limits' tokens, room in the mailbox).
        # The first header that differs ends this for the batch (requests, replies vary).
        head: dict[str, Any] | None = None  # the header of the message taken last
        head_fields: dict[str, Any] = {}  # its fields
        head_entry: tuple[Any, ...] = ()  # its audit entry
        head_names: set[str] = set()  # its keys (`__pydantic_fields_set__`)
        head_bare = False  # whether it has no content
        head_initiating = False
        reuse = True
        try:
            while i < end:
                if total is not None and total.tokens < 1.0:
                    break
                obj = items[i]
                if head is not None and type(obj) is dict:
                    rest = obj.copy()
                    content = rest.pop("content", _ABSENT)
                    bare = content is _ABSENT  # no content (None, as the model's default)
                    if bare:
                        content = None
                    # equal to a header taken: valid, but for a number equal to its ``v``
                    # that is no int (1.0, true); `_nests_less`'s common case (a dict of
                    # scalars) told here, without its call
                    if (
                        rest == head
                        and type(rest["v"]) is int
                        and (
                            (type(content) is dict and _all_scalars(map(type, content.values())))
                            or _nests_less(content)
                        )
                    ):
                        if room <= 0:
                            break
                        if head_initiating and requests is not None:
                            if not requests.ready(now):
                                break
                            requests.tokens -= 1.0
                        if total is not None:
                            total.tokens -= 1.0
                        copied = head_fields.copy()
                        # its own list, the decoded batch's, not copied: nothing else
                        # keeps the batch's items once they are taken
                        copied["receivers"] = rest["receivers"]
                        copied["content"] = content
                        add_entry(head_entry)
                        # `_constructed`, inline; its keys those of the header's message
                        # when both have a content or neither has: a copy of that one's set
                        message = _new_message(ACLMessage)
                        _set_dict(message, copied)
                        _set_fields_set(
                            message, head_names.copy() if bare is head_bare else set(obj)
                        )
                        _set_extra(message, None)
                        _set_private(message, None)
                        run.append(message)
                        room -= 1
                        i += 1
                        continue
                    head = None
                    reuse = False
                # `from_parsed`'s quick path, inline
                quick = False
                if (
                    type(obj) is dict
                    and (fields := _quick_fields(obj)) is not None
                    and _nests_less(fields["content"])  # each message's depth, not the batch's
                ):
                    message = _constructed(ACLMessage, fields, set(obj))
                    quick = True
                else:
                    try:
                        message = from_parsed(obj)
                    except MessageError:
                        break
                    fields = message.__dict__
                # the message's fields read from its dict: cheaper than its attributes
                receivers = fields["receivers"]
                if len(receivers) != 1 or fields["reply_to"]:
                    break
                receiver = receivers[0]
                if receiver != last_receiver:
                    at = receiver.rpartition("@")
                    if at[2] != here:
                        break
                    agent = agents.get(at[0])
                    if agent is None or not agent.running:
                        break
                    if agent is not run_agent:
                        if run_agent is not None and run:
                            run_agent._deliver_batch(run)
                            run = []
                        run_agent = agent
                    mailbox = agent._mailbox
                    room = (mailbox.maxlen >> 1) - len(mailbox._items) - len(run)
                    last_receiver = receiver
                sender = fields["sender"]
                if sender != last_sender:
                    if sender.rpartition("@")[2] != peer:
                        break
                    last_sender = sender
                if room <= 0:  # counting those not yet handed over
                    break
                performative = fields["performative"]
                initiating = performative in INITIATING
                if initiating:
                    if requests is not None and not requests.ready(now):
                        break
                    if df is None or not df.reachable(receiver, peer):
                        break
                    if requests is not None:
                        requests.tokens -= 1.0
                if total is not None:
                    total.tokens -= 1.0
                # accepted_entry, inline (one receiver, this sender)
                entry = (
                    ts,
                    peer,
                    sender,
                    receiver,
                    _NAMES[performative],
                    fields["conversation_id"],
                )
                add_entry(entry)
                run.append(message)  # running, room in its mailbox: taken
                room -= 1
                i += 1
                if reuse and quick:
                    if "v" in obj and "reply_to" not in obj and "reply_by" not in obj:
                        head = obj.copy()
                        head.pop("content", None)
                        head_fields, head_entry, head_initiating = fields, entry, initiating
                        head_names = set(obj)  # its own: the message's is the message's
                        head_bare = "content" not in obj
                    else:
                        reuse = False
        finally:
            taken = i - start
            if taken:
                audit.add_accepted(entries)  # one per message taken
                state.stats.accepted += taken
                stats = host.stats
                stats.received_remote += taken
                stats.local += taken
            if run_agent is not None and run:
                run_agent._deliver_batch(run)  # audited first, as `_admit_now` does
        return i

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


def _shape(item: Any) -> str:
    """What a failed item is, for a log: its size (or kind), never its content.

    What the inbox holds was decrypted (another platform's confidential message): its
    bytes, or a repr of them, in a log would leak them to whoever reads the logs."""
    bytes_like = bytes | bytearray | memoryview
    body = getattr(item, "payload", None)  # a transport's message: the sealed envelope
    if isinstance(item, bytes_like):
        body = item
    elif body is None and isinstance(item, tuple):  # a lane's item: (peer, body, …)
        body = next((x for x in item if isinstance(x, bytes_like)), None)
    if isinstance(body, bytes_like):
        return f"{len(body)} bytes"
    if item is None:
        return "nothing"
    if isinstance(item, tuple | list | dict):
        return f"{type(item).__name__} of {len(item)}"
    return type(item).__name__


def _failure() -> str:
    """The exception being handled, for a log: its type and where it was raised, not its
    text (an error may quote the decrypted message it failed on: a value, a key)."""
    exc = sys.exc_info()[1]
    return "no exception" if exc is None else failure_of(exc)


def _written(obj: Any) -> bytes:
    """A batch's decoded message as JSON again, even one nesting deeper than orjson writes.

    orjson reads 1024 levels but writes 254: such a message is written with its deep
    values left out (null in their place), keeping the scalar and flat fields that tell
    its sender, receivers and conversation (enough to answer it not-understood).
    """
    try:
        return orjson.dumps(obj)
    except orjson.JSONEncodeError:
        if type(obj) is not dict:
            return b"null"
        return orjson.dumps(
            {
                key: None
                if type(value) is dict
                or (type(value) is list and any(type(v) in (dict, list) for v in value))
                else value
                for key, value in obj.items()
            }
        )


def _claimed_sender(body: bytes) -> str | None:
    """The ``sender`` a body that is not a valid message names, if it can be read."""
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError:
        return None
    sender = obj.get("sender") if isinstance(obj, dict) else None
    return sender if isinstance(sender, str) else None
