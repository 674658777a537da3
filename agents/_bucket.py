"""The token bucket every limit of the agent layer uses (rate limits, load shedding)."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["TokenBucket", "check_rates"]


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up: one message takes one token.

    Not thread-safe: a caller on several threads holds its own lock.
    """

    __slots__ = ("burst", "rate", "stamp", "tokens")

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate = rate
        self.burst = burst
        self.tokens = burst  # a newcomer may send its burst at once
        self.stamp = now

    def _refill(self, now: float) -> float:
        if now > self.stamp:
            # `min(burst, tokens)` spelled out: no call (3.11's min builds a tuple of its args)
            tokens = self.tokens + (now - self.stamp) * self.rate
            self.tokens = tokens if tokens < self.burst else self.burst
            self.stamp = now
        return self.tokens

    def ready(self, now: float, n: float = 1.0) -> bool:
        """Whether ``n`` tokens are there at ``now``, taking none (check several, then take)."""
        # `_refill`, inline: asked for every message, a call less each
        if now > self.stamp:
            tokens = self.tokens + (now - self.stamp) * self.rate
            self.tokens = tokens if tokens < self.burst else self.burst  # min, as in `_refill`
            self.stamp = now
        return self.tokens >= n

    def take(self, now: float, n: float = 1.0) -> bool:
        """Take ``n`` tokens at time ``now`` (seconds, monotonic) if there are; else False."""
        if now > self.stamp:  # `_refill`, inline, as in `ready`
            tokens = self.tokens + (now - self.stamp) * self.rate
            self.tokens = tokens if tokens < self.burst else self.burst  # min, as in `_refill`
            self.stamp = now
        if self.tokens >= n:
            self.tokens -= n
            return True
        return False


def check_rates(
    owner: Any, kind: str, numbers: tuple[str, ...], bursts: tuple[str, ...], what: str
) -> None:
    """Refuse a limit whose ``numbers`` are not finite ≥ 0 or whose ``bursts`` are < 1.

    ``kind`` names the class in the error; ``what`` is what a burst below one would refuse.
    Also checks ``report_interval`` > 0 (every limit reports at some interval).
    """
    for name in numbers:
        value = getattr(owner, name)
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
            or value < 0
        ):
            raise ValueError(f"{kind}.{name}: {value!r} is not a finite number >= 0")
    for name in bursts:
        if getattr(owner, name) < 1:
            raise ValueError(f"{kind}.{name}: {getattr(owner, name)!r} < 1 would refuse {what}")
    interval = owner.report_interval
    if interval <= 0:
        raise ValueError(f"{kind}.report_interval: {interval!r} is not > 0")
