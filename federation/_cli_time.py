"""How the ``dyknow`` commands show times to people: one format everywhere.

A point in time is ISO 8601 in the platform's time zone with its offset and milliseconds
(``2026-11-27T09:30:05.250+01:00``); a duration is seconds (``12.5 s``). JSON output keeps
the numbers (seconds or nanoseconds, as each command documents): these are for text only.
A time given to a command may be written as they show it (`parse_time`).
"""

from __future__ import annotations

import datetime as dt
import re

from dyknow_core import ns_to_seconds

__all__ = ["asked", "parse_time", "seconds", "when", "when_ns"]

_RELATIVE = re.compile(r"^-(\d+(?:\.\d+)?)(ms|s|m|h)?$")
_UNITS = {"ms": 0.001, "s": 1.0, "m": 60.0, "h": 3600.0, None: 1.0}


def when(t: float) -> str:
    """A POSIX time in seconds as ISO 8601 with the local offset, to the millisecond."""
    try:
        stamp = dt.datetime.fromtimestamp(t, dt.UTC).astimezone()
    except (OverflowError, OSError, ValueError):
        return f"{t!r} s"  # outside what a calendar date can show: the number itself
    return stamp.isoformat(timespec="milliseconds")


def when_ns(ns: int) -> str:
    """A POSIX time in nanoseconds (a sample's valid or available time) as ``when`` shows it."""
    return when(ns_to_seconds(ns))


def seconds(value: float) -> str:
    """A duration in seconds, to the millisecond without trailing zeros: ``12 s``, ``0.25 s``."""
    text = f"{value:.3f}".rstrip("0").rstrip(".")
    return f"{'0' if text in ('', '-0') else text} s"


def asked(value: float, relative: bool) -> str:
    """A time `parse_time` read, shown back: ``when``'s form, or ``now``/``now - 90 s``."""
    if not relative:
        return when(value)
    return "now" if value == 0 else f"now - {seconds(-value)}"


def parse_time(text: str) -> tuple[float, bool]:
    """A time given to a command, as ``(value, relative)``.

    ``now`` and ``-90s``/``-2m``/``-1h``/``-500ms`` are relative (seconds before now);
    ISO 8601 with its UTC offset, as `when` shows a time (``2026-11-27T09:30:05.250+01:00``,
    or ``Z`` for UTC), and POSIX seconds are absolute (seconds since the epoch). A date
    and time without an offset is refused: whose local time it is would be a guess.
    """
    text = text.strip()
    if text == "now":
        return 0.0, True
    m = _RELATIVE.fullmatch(text)
    if m:
        return -float(m.group(1)) * _UNITS[m.group(2)], True
    try:
        return float(text), False
    except ValueError:
        pass
    try:
        stamp = dt.datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(
            f"{text!r} is not a time (ISO 8601 with its offset, e.g. "
            "2026-11-27T09:30:05+01:00; POSIX seconds; now; or e.g. -90s, -2m)"
        ) from None
    if stamp.tzinfo is None:
        raise ValueError(f"{text!r} has no UTC offset: add one, e.g. {text}+01:00 or {text}Z")
    return stamp.timestamp(), False
