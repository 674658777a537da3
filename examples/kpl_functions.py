"""Computational-unit functions referenced by ``examples/traffic.kpl``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


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


def pixels_to_world(vision: dict[str, Any]) -> dict[str, Any] | None:
    """A world object's features from its vision object's (a toy camera: 0.5 m per pixel)."""
    pixel = vision.get("pixel")
    if pixel is None:
        return None
    pos = (pixel[0] * 0.5, pixel[1] * 0.5)
    return {"pos": pos, "on_road": 0 <= pos[1] <= 10}
