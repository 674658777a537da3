"""The token bucket every limit of the agent layer uses (rate limits, load shedding)."""

from __future__ import annotations

__all__ = ["TokenBucket"]


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
            self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
            self.stamp = now
        return self.tokens

    def ready(self, now: float, n: float = 1.0) -> bool:
        """Whether ``n`` tokens are there at ``now``, taking none (check several, then take)."""
        return self._refill(now) >= n

    def take(self, now: float, n: float = 1.0) -> bool:
        """Take ``n`` tokens at time ``now`` (seconds, monotonic) if there are; else False."""
        if self._refill(now) >= n:
            self.tokens -= n
            return True
        return False
