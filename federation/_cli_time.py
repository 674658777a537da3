"""How the ``dyknow`` commands show times to people: one format everywhere.

A point in time is ISO 8601 in the platform's time zone with its offset and milliseconds
(``2026-11-27T09:30:05.250+01:00``); a duration is seconds (``12.5 s``). JSON output keeps
the numbers (seconds or nanoseconds, as each command documents): these are for text only.
"""

from __future__ import annotations

import datetime as dt

from dyknow_core import ns_to_seconds

__all__ = ["seconds", "when", "when_ns"]


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
