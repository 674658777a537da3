"""The traffic demo's agreed semantic labels, each platform's local labels, value shapes.

Every value is plain msgpack/JSON data (dicts of numbers and strings):

- ``heli-position``: ``{"x", "y", "z"}`` metres, the UAV's own position (2 Hz).
- ``heli-max-speed``, ``heli-altitude``: numbers (m/s, m), the UAV's limits.
- ``area``: ``{"index": int, "polygon": [[x, y], ...], "delegated-by": str | None}``,
  the area the UAV monitors now (republished every 2 s and when it changes).
- ``tracked-cars``: ``{"cars": [{"id", "x", "y", "speed", "colour", "road"}]}``, every
  car the UAV tracks now (2 Hz); ``id`` is ``<platform>/<object>``.
- ``{object}-state``: ``{"x", "y", "vx", "vy", "speed", "colour", "road"}``, one tracked
  object's state (e.g. ``uav_b_car3-state``: objects are named ``<platform>_<id>`` with
  ``-`` as ``_``, since object names are letters, digits and underscores).
- ``violation``: ``{"kind", "car", "other", "start", "end", "x", "y", "platform",
  "fused"}``: a recognized overtake, reckless overtake or turn in a crossing, or a car the
  speed monitor flagged (kind ``speeding``, ``other`` null, with its ``speed``); ``car``
  and ``other`` are object names, times are world seconds; ``fused`` when the platform
  needed imported states to see it.
- ``observation``: ``{"x", "y", "text"}``, an observation the operator entered.
"""

from __future__ import annotations

from typing import Any

from ._world import ANCHOR

__all__ = ["LABELS", "console_config", "foxglove_config", "local_mapping", "vocabulary"]

LABELS: dict[str, str] = {
    "heli-position": "the platform's own position (x, y, z), metres",
    "heli-max-speed": "the platform's top speed, m/s",
    "heli-altitude": "the platform's altitude, m",
    "area": "the area the platform monitors now (polygon, metres)",
    "tracked-cars": "every car the platform tracks now, with positions",
    "{object}-state": "the state of a tracked car, e.g. uav_b_car3-state",
    "violation": "a recognized overtake, reckless overtake, turn in a crossing or speeding",
    "observation": "an observation entered by a person at the operator console",
}

# Local labels differ between platforms on purpose: only semantic labels cross.
_LOCAL: dict[str, str] = {
    "heli-position": "uav/self/position",
    "heli-max-speed": "uav/self/max-speed",
    "heli-altitude": "uav/self/altitude",
    "area": "uav/self/area",
    "tracked-cars": "tracker/cars",
    "{object}-state": "car/{object}/state",
    "violation": "chronicle/violations",
    "observation": "operator/observations",
}


def vocabulary(name: str = "traffic") -> dict[str, Any]:
    """The federation vocabulary (the shape of docs/ontology.md's TOML file)."""
    return {"name": name, "labels": dict(LABELS), "concepts": {"Car": 1, "Colour": 2}}


def local_mapping(vocabulary_name: str = "traffic") -> dict[str, Any]:
    """A platform's label mapping: semantic label → local label."""
    return {"vocabulary": vocabulary_name, "labels": dict(_LOCAL)}


def console_config() -> dict[str, Any]:
    """The operator's ``[console]`` section: what its console streams and draws as what."""
    return {
        "streams": ["heli-position", "area", "tracked-cars", "violation"],
        "roles": {
            "positions": "heli-position",
            "areas": "area",
            "tracks": "tracked-cars",
            "violations": "violation",
        },
    }


def foxglove_config() -> dict[str, Any]:
    """The operator's ``[foxglove]`` section: the console's streams, on the world's map."""
    return {"origin": list(ANCHOR)}
