"""Directory-event load shedding: most of a flood of forged ``df-events`` is dropped unread.

A directory event under a trusted name costs its receiver a signature check; anyone on
the network can publish on ``df-events/<platform>``, so a flood of forged ones would take
the platform's CPU, and push real events out of the subscription's queue. The
`DfEventGate` runs on the transport's receiving thread, before the event is queued for
the event loop and before any signature check: it drops what is malformed, not a
directory event of this federation, from an untrusted name, unsigned or expired, or not
newer than the last accepted event of its platform (``stale``: it changes nothing, and
anyone may send one under any name), a few microseconds each, and lets through only
as many of the rest as a budget allows, per claimed platform and in all. All it drops is
summed up in the same audit records (``df-events-shed``), none attributed to the
platform it claims. An event of a member shed for its budget (a forger claiming that
member's name), or of one joining (its first snapshot under way) shed for the shared
budget, is made good by asking the member again (`GlobalDirectory` takes a fresh signed
snapshot). See ``docs/security.md`` ("Directory-event load shedding").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import orjson

from ._directory_auth import MAX_STATEMENT_BYTES, WIRE_VERSION, DirectoryAuth
from ._gate import TOTAL_BUDGET as TOTAL_BUDGET  # the other budget an event is shed by
from ._gate import ShedGate, check_limit
from ._records import Frozen


@dataclass(init=False, repr=False, eq=False)
class DfEventLimit(Frozen):
    """How many directory events a platform checks the signature of, per second.

    An event that passes the cheap checks (well formed, of this federation, from a
    trusted name, signed, stamped within the skew, newer than the last accepted one of
    its platform) still needs a token: ``per_platform`` per second (bursts of
    ``per_platform_burst``) for each claimed platform, and, for a platform not alive in
    the global directory, one of the ``total`` per second (bursts of ``total_burst``) all
    such share. A member alive in the directory (its signed snapshot came) is held to its
    own budget only: a forger claiming other names cannot spend it. Of the events
    dropped, up to ``detailed`` per ``report_interval`` are audited one by one (with
    their reason); all are counted and summed up in one audit record per
    ``report_interval``; a member whose events were shed over its budget is asked for a
    fresh snapshot, at most once per ``report_interval``.
    """

    __slots__ = (
        "detailed",
        "per_platform",
        "per_platform_burst",
        "report_interval",
        "total",
        "total_burst",
    )
    per_platform: float
    per_platform_burst: float
    total: float
    total_burst: float
    detailed: int
    report_interval: float

    # a member registering its services at start sends a burst: its own, within these
    def __init__(
        self,
        per_platform: float = 20.0,
        per_platform_burst: float = 50.0,
        total: float = 20.0,
        total_burst: float = 20.0,
        detailed: int = 20,
        report_interval: float = 1.0,
    ) -> None:
        object.__setattr__(self, "per_platform", per_platform)
        object.__setattr__(self, "per_platform_burst", per_platform_burst)
        object.__setattr__(self, "total", total)
        object.__setattr__(self, "total_burst", total_burst)
        object.__setattr__(self, "detailed", detailed)
        object.__setattr__(self, "report_interval", report_interval)
        self.__post_init__()

    def __post_init__(self) -> None:
        check_limit(self, "DfEventLimit", "per_platform", "every event")


DEFAULT_DF_EVENT_LIMIT = DfEventLimit()

# Reasons an event is shed besides the cheap checks' own.
PLATFORM_BUDGET = "over-platform-budget"
_WHY = {
    "malformed": "not a directory statement",
    "misdirected": "not a directory event of this federation",
    "untrusted": "from a platform not in the trust file",
    "unsigned": "unsigned statement",
    "expired": "timestamp outside the allowed skew",
}
STALE = "stale"  # not newer than the last accepted event of its platform: counted only


class DfEventGate(ShedGate):
    """Decides, on the transport's thread, which directory events are worth checking.

    ``admit(payload)`` is thread-safe and never raises; ``take_report(now)`` (the event
    loop's side) returns what to audit and which members to ask again. ``priority`` (a
    frozenset of platform names, replaced whole by the owner) names the platforms alive
    in the directory: exempt from the shared budget. ``joining`` (likewise) names those
    whose presence was taken and whose first signed snapshot is still asked: held to the
    shared budget (anyone may make a presence appear), but an event of theirs shed over
    it has them asked again.
    """

    CLAIMED_BUDGET = PLATFORM_BUDGET
    limit: DfEventLimit

    def __init__(
        self,
        auth: DirectoryAuth,
        limit: DfEventLimit,
        *,
        monotonic: Callable[[], float] = time.monotonic,
        on_shed: Callable[[], None] | None = None,
    ) -> None:
        super().__init__(limit, limit.per_platform, limit.per_platform_burst, monotonic, on_shed)
        self.auth = auth
        self.joining: frozenset[str] = frozenset()
        self._resync: set[str] = set()  # members shed over their budget since the last take

    def admit(self, payload: bytes) -> bool:
        """Whether the directory event ``payload`` goes on to its signature check."""
        try:
            screened = self._screen(payload)
        except Exception:  # whatever it is, it is not an event to check
            screened = ("malformed", None)
        reason, frm = screened
        if reason:
            # a stale one too: already reflected, or replayed, and its signature unchecked,
            # so counted with the rest, never attributed to the platform it claims
            return self._drop(reason, frm)
        assert frm is not None
        now = self._monotonic()
        with self._lock:
            over = self._spend_locked(frm, now)
            if over is not None:
                if (over is PLATFORM_BUDGET and frm in self.priority) or frm in self.joining:
                    self._resync.add(frm)  # a real event may be among those shed
                return self._drop_locked(over, frm)
        return True

    def _screen(self, payload: bytes) -> tuple[str, str | None]:
        """``("", from)`` for an event worth a look, else ``(why not, claimed platform)``.

        `DirectoryAuth.open`'s checks without the signature: comparisons only. What they
        refuse, ``open`` refuses too.
        """
        if len(payload) > MAX_STATEMENT_BYTES:
            return "malformed", None
        obj = orjson.loads(payload)
        if type(obj) is not dict:
            return "malformed", None
        auth = self.auth
        frm = obj.get("from")
        if type(frm) is not str:
            return "malformed", None
        if obj.get("v") != WIRE_VERSION or obj.get("kind") != "df-event":
            return "malformed", frm
        if obj.get("fed") != auth.federation:
            return "misdirected", frm
        if not auth.trusted(frm):
            return "untrusted", frm
        boot, seq, ts_ms = obj.get("boot"), obj.get("seq"), obj.get("ts_ms")
        if type(boot) is not int or type(seq) is not int or type(ts_ms) is not int:
            return "malformed", frm
        if auth.authenticates:
            if type(obj.get("sig")) is not str:
                return "unsigned", frm
            if abs(time.time() - ts_ms / 1000) > auth.skew:
                return "expired", frm
        newest = auth.newest(frm)
        if newest is not None and (boot, seq) <= newest:
            return STALE, frm
        return "", frm

    @property
    def stale(self) -> int:
        """Events dropped as not newer than the last accepted of their platform, since start."""
        return self.shed[STALE]

    def _explain(self, reason: str, claimed: str | None) -> str | None:
        """Why an event was shed, for its audit record (None: a stale one, counted only)."""
        if reason == STALE:
            return None  # normal now and then (one re-sent): never a record of its own
        why = _WHY.get(reason) or (
            f"over {claimed!r}'s budget of {self.limit.per_platform:g}/s"
            if reason == PLATFORM_BUDGET
            else f"over the shared budget of {self.limit.total:g}/s"
        )
        return f"{reason}: {why}"

    @property
    def shed_total(self) -> int:
        """Every event shed since start, whatever the reason."""
        return sum(self.shed.values())

    def take_report(
        self, now: float, *, final: bool = False
    ) -> tuple[list[tuple[str | None, str]], dict[str, Any] | None, set[str]]:
        """The shed events to audit one by one, a summary once per interval (else None),
        and the members to ask again (their events were shed over their budget).
        ``final``: the owner closes, the summary of what is pending is due now.

        The summary has ``count`` (events shed since the last one), ``by_reason`` and
        ``seconds`` (since the last summary; None for the first).
        """
        with self._lock:
            resync, self._resync = self._resync, set()
            details, summary = self._report_locked(now, final)
        return details, summary, resync
