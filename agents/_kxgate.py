"""Key-exchange load shedding: most of a flood of handshake requests is dropped unread.

Answering a key-exchange request costs a signature check (and, when it verifies, a
key agreement); a flood of them from anyone on the network would take the platform's
CPU. The `KxGate` runs on the transport's receiving thread, before the request is queued
for the event loop and before any signature check: it drops what is malformed, not for
this platform, from an untrusted name, stale or a replay (a few microseconds each), and
lets through only as many of the rest as a budget allows, per claimed platform and in
all. See ``docs/security.md`` ("Key-exchange load shedding").
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ._acl import WIRE_VERSION
from ._bucket import TokenBucket, check_rates
from ._exceptions import AuthenticationError, Replayed
from ._security import _INIT_FIELDS, MAX_HANDSHAKE_BYTES, Handshake, _loads, _parse_kx


@dataclass(frozen=True, slots=True)
class KxLimit:
    """How many key-exchange requests a platform checks the signature of, per second.

    A request that passes the cheap checks (well formed, for this platform and
    federation, from a trusted name, timestamp within the skew, not seen before) still
    needs a token: ``per_peer`` per second (bursts of ``per_peer_burst``) for each claimed
    platform, and, for a platform this one holds no session with and has not seen alive,
    one of the ``total`` per second (bursts of ``total_burst``) all such share. Trusted
    platforms with a session or alive are held to their own budget only: a forger
    claiming other names cannot spend it. Of the requests dropped, up to ``detailed`` per
    ``report_interval`` are audited one by one (with their reason); all of them are
    counted, and summed up in one audit record per ``report_interval``.
    """

    per_peer: float = 2.0
    per_peer_burst: float = 10.0
    total: float = 20.0
    total_burst: float = 20.0
    detailed: int = 20
    report_interval: float = 1.0

    def __post_init__(self) -> None:
        check_rates(
            self,
            "KxLimit",
            ("per_peer", "per_peer_burst", "total", "total_burst", "report_interval"),
            ("per_peer_burst", "total_burst"),
            "every request",
        )
        if isinstance(self.detailed, bool) or not isinstance(self.detailed, int):
            raise ValueError(f"KxLimit.detailed: {self.detailed!r} is not an integer")
        if self.detailed < 0:
            raise ValueError(f"KxLimit.detailed: {self.detailed!r} is not >= 0")


DEFAULT_KX_LIMIT = KxLimit()

# Reasons a request is shed besides the handshake's own refusal codes.
PEER_BUDGET = "over-peer-budget"
TOTAL_BUDGET = "over-total-budget"
# (from, nonce) of requests let through, kept this long past their timestamp's skew
_SEEN_MAX = 16_384


class KxGate:
    """Decides, on the transport's thread, which key-exchange requests are worth checking.

    ``admit(payload)`` is thread-safe and never raises; ``take_report(now)`` (the event
    loop's side) returns what to audit. ``priority`` (a frozenset of platform names,
    replaced whole by the owner) names the platforms exempt from the shared budget.
    """

    def __init__(
        self,
        handshake: Handshake,
        limit: KxLimit,
        *,
        monotonic: Callable[[], float] = time.monotonic,
        on_shed: Callable[[int], None] | None = None,
    ) -> None:
        self.handshake = handshake
        self.limit = limit
        self.priority: frozenset[str] = frozenset()
        self._monotonic = monotonic
        self._on_shed = on_shed
        self._lock = threading.Lock()
        now = monotonic()
        self._total = TokenBucket(limit.total, limit.total_burst, now)
        self._peers: dict[str, TokenBucket] = {}
        self._seen: OrderedDict[tuple[str, str], float] = OrderedDict()
        self.shed: Counter[str] = Counter()  # every request shed, by reason, since start
        self.admitted = 0
        self._pending: Counter[str] = Counter()  # shed since the last summary
        self._details: list[tuple[str | None, str]] = []
        self._detailed = 0  # detailed in the current interval
        self._last_report = -math.inf

    def admit(self, payload: bytes) -> bool:
        """Whether the key-exchange request ``payload`` goes on to its signature check."""
        hs = self.handshake
        try:
            screened = self._screen(payload)
        except Exception:  # whatever it is, it is not a request to answer
            screened = "malformed"
        if isinstance(screened, str):
            if self._detailed >= self.limit.detailed:  # read unlocked: a hint is enough
                return self._drop(screened, None, None)
            return self._drop_explained(screened, payload)
        frm, ts, nonce = screened
        now = self._monotonic()
        with self._lock:
            seen = self._seen
            if (frm, nonce) in seen:
                why = f"handshake request from {frm!r} was already answered"
                return self._drop_locked(Replayed.code, frm, f"{Replayed.code}: {why}")
            bucket = self._peers.get(frm)
            if bucket is None:  # one per trusted name: bounded by the trust file
                bucket = self._peers[frm] = TokenBucket(
                    self.limit.per_peer, self.limit.per_peer_burst, now
                )
            if not bucket.ready(now):
                return self._drop_locked(PEER_BUDGET, frm, None)
            if frm not in self.priority:
                # both or neither: a request shed by one budget spends nothing of the other
                if not self._total.ready(now):
                    return self._drop_locked(TOTAL_BUDGET, frm, None)
                self._total.tokens -= 1.0
            bucket.tokens -= 1.0
            seen[(frm, nonce)] = ts / 1000 + 2 * hs.policy.skew
            while len(seen) > _SEEN_MAX:
                seen.popitem(last=False)
            self.admitted += 1
        return True

    def _screen(self, payload: bytes) -> tuple[str, int, str] | str:
        """``(from, ts_ms, nonce)`` of a request worth a look, else why not (a refusal code).

        The handshake's own checks without their messages: comparisons only, about a
        third of their cost. What they refuse, they refuse too (the signature aside).
        """
        if len(payload) > MAX_HANDSHAKE_BYTES:
            return "malformed"
        msg = _loads(payload)
        if type(msg) is not dict or msg.keys() != _INIT_FIELDS:
            return "malformed"
        if msg["v"] != WIRE_VERSION or type(msg["v"]) is not int or msg["kx"] != "init":
            return "malformed"
        hs = self.handshake
        frm = msg["from"]
        if msg["fed"] != hs.federation or msg["to"] != hs.me.platform or frm == hs.me.platform:
            return "misdirected"
        if type(frm) is not str or frm not in hs.trust:
            return "untrusted"
        ts, nonce = msg["ts_ms"], msg["nonce"]
        if type(ts) is not int or type(nonce) is not str:
            return "malformed"
        if abs(time.time() - ts / 1000) > hs.policy.skew:
            return "expired"
        return frm, ts, nonce

    def _drop_explained(self, code: str, payload: bytes) -> bool:
        """Drop a request, audited one by one: the handshake's own checks say exactly why."""
        try:
            self.handshake._check_kx(_parse_kx(payload, "init", _INIT_FIELDS))
        except AuthenticationError as exc:
            return self._drop(exc.code, exc.platform, f"{exc.code}: {exc.reason}")
        except Exception as exc:
            return self._drop("malformed", None, f"malformed: {exc}")
        return self._drop(code, None, f"{code}: handshake request refused")

    def _drop(self, reason: str, claimed: str | None, detail: str | None) -> bool:
        with self._lock:
            return self._drop_locked(reason, claimed, detail)

    def _drop_locked(self, reason: str, claimed: str | None, detail: str | None) -> bool:
        self.shed[reason] += 1
        self._pending[reason] += 1
        if detail is not None and self._detailed < self.limit.detailed:
            self._detailed += 1
            self._details.append((claimed, detail))
        if self._on_shed is not None:
            self._on_shed(1)
        return False

    @property
    def pending(self) -> bool:
        """Whether shed requests wait to be audited (read unlocked: a hint)."""
        return bool(self._pending or self._details)

    def forget_seen(self, wall: float) -> None:
        """Drop remembered requests whose timestamps are now past the skew (``wall``: time.time)."""
        with self._lock:
            seen = self._seen
            # in about the order of their timestamps: stop at the first still fresh (one
            # out of order waits for the next call, or for the size bound)
            while seen:
                key, until = next(iter(seen.items()))
                if until >= wall:
                    break
                del seen[key]

    def take_report(self, now: float) -> tuple[list[tuple[str | None, str]], dict[str, Any] | None]:
        """The shed requests to audit one by one, and a summary once per interval (else None).

        The summary has ``count`` (requests shed since the last one), ``by_reason`` and
        ``seconds`` (since the last summary; None for the first).
        """
        with self._lock:
            details, self._details = self._details, []
            if not self._pending or now - self._last_report < self.limit.report_interval:
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
