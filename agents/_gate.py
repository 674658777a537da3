"""What the load-shedding gates share: per-name and shared budgets, counting, the report.

A gate (`KxGate` for key-exchange requests, `DfEventGate` for directory events) runs on
the transport's receiving thread and drops, before any signature check, what its own
cheap checks refuse and whatever is over budget. Those checks, and who is exempt from
the shared budget, are each gate's own; the budgets and the bookkeeping are here.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

from ._bucket import TokenBucket, check_rates

TOTAL_BUDGET = "over-total-budget"


def check_limit(limit: Any, kind: str, per: str, what: str) -> None:
    """Refuse a gate's limit whose rates, bursts, interval or ``detailed`` are out of range.

    ``per`` names the per-claimed-platform rate (its burst is ``<per>_burst``).
    """
    burst = per + "_burst"
    check_rates(
        limit, kind, (per, burst, "total", "total_burst", "report_interval"),
        (burst, "total_burst"), what,
    )  # fmt: skip
    detailed = limit.detailed
    if isinstance(detailed, bool) or not isinstance(detailed, int):
        raise ValueError(f"{kind}.detailed: {detailed!r} is not an integer")
    if detailed < 0:
        raise ValueError(f"{kind}.detailed: {detailed!r} is not >= 0")


class ShedGate:
    """The budgets and bookkeeping of a load-shedding gate; subclasses screen and admit.

    A message that passed the subclass's cheap checks spends, under ``_lock``, a token of
    its claimed platform's bucket and, unless that platform is in ``priority``, one of
    the shared bucket (`_spend_locked`). What is dropped is counted by reason; up to
    ``limit.detailed`` per interval are kept with a detail (`_drop_locked`), and
    `_report_locked` hands them over with a summary once per ``limit.report_interval``.
    """

    # the reason a message over its claimed platform's own budget is shed
    CLAIMED_BUDGET = ""

    def __init__(
        self,
        limit: Any,
        rate: float,
        burst: float,
        monotonic: Callable[[], float],
        on_shed: Callable[[], object] | None,
    ) -> None:
        self.limit = limit
        self.priority: frozenset[str] = frozenset()
        self._rate = rate
        self._burst = burst
        self._monotonic = monotonic
        self._on_shed = on_shed
        self._lock = threading.Lock()
        self._total = TokenBucket(limit.total, limit.total_burst, monotonic())
        self._buckets: dict[str, TokenBucket] = {}
        self.shed: Counter[str] = Counter()  # every message shed, by reason, since start
        self.admitted = 0  # messages let through to their signature check, since start
        self._pending: Counter[str] = Counter()  # shed since the last summary
        self._details: list[tuple[str | None, str]] = []
        self._detailed = 0  # detailed in the current interval
        self._last_report = -math.inf

    def _spend_locked(self, frm: str, now: float) -> str | None:
        """Take ``frm``'s tokens and count it admitted; else the budget it is over."""
        bucket = self._buckets.get(frm)
        if bucket is None:  # one per trusted name: bounded by the trust file
            bucket = self._buckets[frm] = TokenBucket(self._rate, self._burst, now)
        # `_refill`, not `ready`: saves as many calls as this method adds, per message on
        # the transport's thread
        if bucket._refill(now) < 1.0:
            return self.CLAIMED_BUDGET
        if frm not in self.priority:
            # both or neither: a message shed by one budget spends nothing of the other
            if self._total._refill(now) < 1.0:
                return TOTAL_BUDGET
            self._total.tokens -= 1.0
        bucket.tokens -= 1.0
        self.admitted += 1
        return None

    def _explain(self, reason: str, claimed: str | None) -> str | None:
        """The detail to audit a drop with when the caller gave none (None: count it only)."""
        return None

    def _drop(self, reason: str, claimed: str | None, detail: str | None = None) -> bool:
        with self._lock:
            return self._drop_locked(reason, claimed, detail)

    def _drop_locked(self, reason: str, claimed: str | None, detail: str | None = None) -> bool:
        self.shed[reason] += 1
        self._pending[reason] += 1
        if self._detailed < self.limit.detailed:
            if detail is None:
                detail = self._explain(reason, claimed)
            if detail is not None:
                self._detailed += 1
                self._details.append((claimed, detail))
        if self._on_shed is not None:
            self._on_shed()
        return False

    @property
    def pending(self) -> bool:
        """Whether shed messages wait to be audited (read unlocked: a hint)."""
        return bool(self._pending or self._details)

    def _report_locked(
        self, now: float, final: bool = False
    ) -> tuple[list[tuple[str | None, str]], dict[str, Any] | None]:
        """The details kept since the last call, and a summary once per interval (else None).

        ``final``: the owner closes; a summary of what is pending now, whenever the last.
        """
        details, self._details = self._details, []
        if not self._pending or (
            not final and now - self._last_report < self.limit.report_interval
        ):
            return details, None
        self._detailed = 0
        pending, self._pending = self._pending, Counter()
        last, self._last_report = self._last_report, now
        summary = {
            "count": sum(pending.values()),
            "by_reason": dict(pending.most_common()),
            "seconds": None if math.isinf(last) else now - last,
        }
        return details, summary


def shed_counts(summary: dict[str, Any]) -> str:
    """``in 1.0 s (reason n, …`` of a shed summary, as both gates' audit records say it."""
    seconds = summary["seconds"]
    since = "" if seconds is None else f" in {seconds:.1f} s"
    reasons = ", ".join(f"{k} {v}" for k, v in summary["by_reason"].items())
    return f"{since} ({reasons}"
