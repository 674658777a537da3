"""Computational units of ``weather.kpl`` (importable because they sit next to it)."""

from __future__ import annotations


def to_kmh(metres_per_second: float) -> float:
    """A wind speed in km/h."""
    return round(metres_per_second * 3.6, 3)
