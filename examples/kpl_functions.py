"""Computational-unit functions referenced by ``examples/traffic.kpl``."""

from __future__ import annotations

from collections.abc import Callable


def make_smoother(alpha: float = 0.5) -> Callable[[float], float]:
    """A unit smoothing a value exponentially with weight ``alpha`` on the newest sample."""
    last: list[float] = []

    def smooth(value: float) -> float:
        last[:] = [value if not last else alpha * value + (1 - alpha) * last[0]]
        return last[0]

    return smooth


def on_road(distance: float) -> bool:
    """Whether a car whose distance from the road centre line is ``distance`` m is on it."""
    return abs(distance) < 5.0
