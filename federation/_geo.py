"""Local metres to geographic coordinates: where a federation's flat frame lies on Earth.

A federation whose positions are metres in a local frame (x east, y north of an origin)
gets them on a map from the latitude and longitude of that origin. The projection is
equirectangular around the origin: over a few kilometres its error is centimetres,
well under what a map panel draws.
"""

from __future__ import annotations

import math

__all__ = ["EARTH_RADIUS", "check_origin", "local_to_geo"]

EARTH_RADIUS = 6_371_008.8
"""The Earth's mean radius in metres (IUGG), the sphere the projection uses."""


def check_origin(latitude: float, longitude: float) -> tuple[float, float]:
    """``(latitude, longitude)`` in degrees when they name a point a frame can start at.

    ValueError otherwise: not finite, outside [-90, 90] x [-180, 180], or a pole (east
    is no direction there).
    """
    if not (math.isfinite(latitude) and math.isfinite(longitude)):
        raise ValueError(f"({latitude}, {longitude}) is not a finite latitude, longitude")
    if not -90.0 < latitude < 90.0:
        raise ValueError(f"latitude {latitude} is not between -90 and 90 (poles excluded)")
    if not -180.0 <= longitude <= 180.0:
        raise ValueError(f"longitude {longitude} is not between -180 and 180")
    return float(latitude), float(longitude)


def local_to_geo(origin: tuple[float, float], x: float, y: float) -> tuple[float, float]:
    """Latitude and longitude (degrees) of the point ``x`` m east, ``y`` m north of ``origin``."""
    lat0, lon0 = origin
    lat = lat0 + math.degrees(y / EARTH_RADIUS)
    lon = lon0 + math.degrees(x / (EARTH_RADIUS * math.cos(math.radians(lat0))))
    return lat, (lon + 180.0) % 360.0 - 180.0
