"""What the proxies count: why samples and batches are dropped, and the shape of their stats.

The reasons are `StrEnum` members whose values are the counter names the CLI, the
console and the docs print; the stats are `TypedDict` s, so ``stats()`` stays the plain
JSON-ready dict it always was.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
from enum import StrEnum
from typing import TypedDict

__all__ = [
    "DropReason",
    "ExportStats",
    "ImportProxyStats",
    "ImportStats",
    "ImportTotals",
    "ResendRefusal",
    "tally",
    "untally",
]


class DropReason(StrEnum):
    """Why a proxy dropped samples or whole batches (counted under the value)."""

    # the export side
    QUEUE_FULL = "queue-full"  # the receiver's queue overflowed, oldest first
    NO_SESSION = "no-session"  # no session could be agreed
    SEND_FAILED = "send-failed"  # the transport refused
    UNENCODABLE = "unencodable"  # a value msgpack cannot carry
    TOO_LARGE = "too-large"  # one sample over the batch size limit
    LOST_IN_TRANSIT = "lost-in-transit"  # published, reported missing by the receiver
    LEASE_EXPIRED = "lease-expired"  # still queued when the receiver's lease expired
    # the import side (whole batches that do not open are counted under the
    # AuthenticationError's own code)
    MALFORMED = "malformed"
    WRONG_SENDER = "wrong-sender"  # authentic, but published under another's name
    WRONG_LABEL = "wrong-label"  # the batch names another label than its key
    UNAGREED = "unagreed"  # a stream never agreed
    SENDER_GONE = "sender-gone"  # in flight when the sender's token went
    DUPLICATE = "duplicate"  # resent, but no longer missing
    LABEL_TAKEN = "label-taken"  # the local label is published by something else
    REJECTED = "rejected"  # the instance refused the samples


class ResendRefusal(StrEnum):
    """Why an export refused (in whole or in part) a receiver's resend request."""

    NOT_A_GAP = "not-a-gap"  # not numbers a gap can have lost, or beyond the history
    OVER_LOSS = "over-loss"  # more than the receiver reports lost
    ALREADY_RESENT = "already-resent"  # each number is resent once
    RATE = "rate"  # over the receiver's request rate


def tally(counter: dict[str, int], reason: str, n: int) -> bool:
    """Add ``n`` to ``counter[reason]``; True when the reason is new there (warn once)."""
    key = str(reason)  # a plain str key: the counters print as they always did
    old = counter.get(key)
    counter[key] = n if old is None else old + n
    return old is None


def untally(counter: dict[str, int], reason: str, n: int) -> None:
    """Take ``n`` back from ``counter[reason]`` (recovered after all); no entry below 1."""
    key = str(reason)
    left = counter.get(key, 0) - n
    if left > 0:
        counter[key] = left
    else:
        counter.pop(key, None)


class ExportStats(TypedDict):
    """`Export.stats`: one export's counters."""

    name: str
    receiver: str
    semantic_label: str
    local_label: str
    sent: int
    batches: int
    queued: int
    dropped: int
    dropped_by_reason: dict[str, int]
    history: int
    recovered: int
    resend_refused: dict[str, int]
    last_heard: float
    last_error: str | None
    active: bool
    ended: str | None


class ImportStats(TypedDict):
    """`Import.stats`: one import's counters."""

    sender: str
    semantic_label: str
    local_label: str | None
    batches: int
    received: int
    injected: int
    lost: int
    recovered: int
    gaps: int
    dropped_batches: dict[str, int]
    dropped_samples: dict[str, int]
    ended: bool
    first_arrival: int | None
    last_arrival: int | None


class ImportTotals(TypedDict):
    """The sums over every import and stray of an `ImportProxy`."""

    batches: int
    received: int
    injected: int
    lost: int
    dropped_batches: dict[str, int]
    dropped_samples: dict[str, int]


class ImportProxyStats(TypedDict):
    """`ImportProxy.stats`: every import, the unagreed traffic, and the totals."""

    imports: list[ImportStats]
    strays: list[ImportStats]
    totals: ImportTotals
