"""What the Interface Agent's parts share: its constants, rate limits and helpers."""

from __future__ import annotations

import logging
import math
import sys
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import orjson

from ._acl import Performative
from ._agent import failure_of
from ._bucket import TokenBucket, check_rates
from ._records import Frozen

if TYPE_CHECKING:
    from ._platform import SenderStats


# the Interface Agent's logger, whichever of its parts logs: the name operators configure
log = logging.getLogger("agents._interface")

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
