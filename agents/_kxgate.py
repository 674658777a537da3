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

import functools
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ._acl import WIRE_VERSION
from ._exceptions import AuthenticationError, Replayed
from ._gate import TOTAL_BUDGET as TOTAL_BUDGET  # the other budget a request is shed by
from ._gate import ShedGate, check_limit
from ._records import Frozen
from ._security import _INIT_FIELDS, MAX_HANDSHAKE_BYTES, Handshake, _loads, _parse_kx


@dataclass(init=False, repr=False, eq=False)
class KxLimit(Frozen):
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

    __slots__ = (
        "detailed",
        "per_peer",
        "per_peer_burst",
        "report_interval",
        "total",
        "total_burst",
    )
    per_peer: float
    per_peer_burst: float
    total: float
    total_burst: float
    detailed: int
    report_interval: float

    def __init__(
        self,
        per_peer: float = 2.0,
        per_peer_burst: float = 10.0,
        total: float = 20.0,
        total_burst: float = 20.0,
        detailed: int = 20,
        report_interval: float = 1.0,
    ) -> None:
        object.__setattr__(self, "per_peer", per_peer)
        object.__setattr__(self, "per_peer_burst", per_peer_burst)
        object.__setattr__(self, "total", total)
        object.__setattr__(self, "total_burst", total_burst)
        object.__setattr__(self, "detailed", detailed)
        object.__setattr__(self, "report_interval", report_interval)
        self.__post_init__()

    def __post_init__(self) -> None:
        check_limit(self, "KxLimit", "per_peer", "every request")


DEFAULT_KX_LIMIT = KxLimit()

# Reasons a request is shed besides the handshake's own refusal codes.
PEER_BUDGET = "over-peer-budget"
# (from, nonce) of requests let through, kept this long past their timestamp's skew
_SEEN_MAX = 16_384


class KxGate(ShedGate):
    """Decides, on the transport's thread, which key-exchange requests are worth checking.

    ``admit(payload)`` is thread-safe and never raises; ``take_report(now)`` (the event
    loop's side) returns what to audit. ``priority`` (a frozenset of platform names,
    replaced whole by the owner) names the platforms exempt from the shared budget.
    """

    CLAIMED_BUDGET = PEER_BUDGET
    limit: KxLimit

    def __init__(
        self,
        handshake: Handshake,
        limit: KxLimit,
        *,
        monotonic: Callable[[], float] = time.monotonic,
        on_shed: Callable[[int], None] | None = None,
    ) -> None:
        super().__init__(
            limit,
            limit.per_peer,
            limit.per_peer_burst,
            monotonic,
            None if on_shed is None else functools.partial(on_shed, 1),
        )
        self.handshake = handshake
        self._seen: OrderedDict[tuple[str, str], float] = OrderedDict()

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
            over = self._spend_locked(frm, now)
            if over is not None:
                return self._drop_locked(over, frm, None)
            seen[(frm, nonce)] = ts / 1000 + 2 * hs.policy.skew
            while len(seen) > _SEEN_MAX:
                seen.popitem(last=False)
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
            return self._report_locked(now)
