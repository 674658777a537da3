"""Online chronicle recognition against pychronicles re-run on a sliding window, same events.

The chronicle: ``a`` then ``b`` within [1, 3] s, then ``c`` within [0.5, 2] s of ``b``, ``c``
within [1.5, 4] s of ``a`` (a simple temporal network of three events). The sequence:
``N`` events drawn from ``a``, ``b``, ``c`` and a noise label ``d``, strictly increasing
times, gaps of 1–1000 ms (integer milliseconds, so both tools compare exactly).

- ours: ``ChronicleRecognizer.feed`` once per event, in time order — what a DyKnow
  chronicle process does per sample.
- pychronicles 0.2 is batch only. Online use means, per event, re-running
  ``Chronicle.recognize`` on the window of the events that may still be part of an
  occurrence ending at it (the last ``SPAN`` of time) and keeping the occurrences that end
  at this event. Measured that way on a 2-core machine (Python 3.11, November 2026),
  pychronicles 0.2 (the peer project, on PyPI) recognized 37 k events/s; batch (one
  ``recognize`` over the whole sequence) 444 k events/s. The batch figure is printed for
  orientation only.

Both must find the same occurrences (all of them: every assignment of events that meets
the constraints, pychronicles' semantics and ours) before anything is reported. Best of
``REPEAT`` interleaved runs each.
"""

from __future__ import annotations

import bisect
import gc
import random
from functools import partial
from typing import Any

import numpy as np
from pychronicles import Chronicle, TimedSequence

from bench import fmt, progress, report, timed
from dyknow_core.reasoning.chronicles import ChronicleRecognizer, Recognition, compile_chronicle

N = 20_000
REPEAT = 5
LABELS = ("a", "b", "c", "d")
# (start, end, lo, hi) in milliseconds
CONSTRAINTS = ((0, 1, 1000, 3000), (1, 2, 500, 2000), (0, 2, 1500, 4000))
SPAN_MS = 4000  # the longest an occurrence can last
NS_PER_MS = 1_000_000

SPEC: dict[str, Any] = {
    "name": "abc",
    "events": [{"name": n, "event": n} for n in ("a", "b", "c")],
    "constraints": [
        {"start": "abc"[i], "end": "abc"[j], "lo": lo / 1000, "hi": hi / 1000}
        for i, j, lo, hi in CONSTRAINTS
    ],
}


def make_events(n: int = N, seed: int = 11) -> list[tuple[str, int]]:
    """``n`` (label, time in ms) pairs, times strictly increasing."""
    rng = random.Random(seed)
    t = 0
    out = []
    for _ in range(n):
        t += rng.randint(1, 1000)
        out.append((rng.choice(LABELS), t))
    return out


def pychronicle() -> Chronicle:
    """The same chronicle for pychronicles (float milliseconds)."""
    c = Chronicle()
    for i, label in enumerate(("a", "b", "c")):
        c.add_event(i, label)
    for i, j, lo, hi in CONSTRAINTS:
        c.add_constraint(i, j, (float(lo), float(hi)))
    return c


def ours(events: list[tuple[str, int]]) -> list[Recognition]:
    """Online recognition, one ``feed`` per event (times in ns, as an instance has them)."""
    rec = ChronicleRecognizer(compile_chronicle(SPEC))
    feed = rec.feed
    found: list[Recognition] = []
    for label, t in events:
        r = feed(label, t)
        if r:
            found += r
    found += rec.advance(1 << 62)
    return found


def ours_set(found: list[Recognition]) -> set[tuple[int, ...]]:
    """Our recognitions as (ta, tb, tc) in ms, to compare."""
    return {tuple(r.times[k] // NS_PER_MS for k in "abc") for r in found}


def sliding(events: list[tuple[str, int]]) -> list[Any]:
    """pychronicles re-run per event on the window that can end at it."""
    c = pychronicle()
    dates = np.array([float(t) for _, t in events])
    data = np.array([label for label, _ in events])
    times = [t for _, t in events]
    found = []
    for i, t in enumerate(times):
        lo = bisect.bisect_left(times, t - SPAN_MS)
        seq = TimedSequence(dates[lo : i + 1], data[lo : i + 1])
        for occ in c.recognize(seq):
            if max(occ) == t:  # the ones this event completes; the rest were seen
                found.append(occ)
    return found


def batch(events: list[tuple[str, int]]) -> list[Any]:
    """pychronicles once over the whole sequence."""
    c = pychronicle()
    seq = TimedSequence(
        np.array([float(t) for _, t in events]), np.array([label for label, _ in events])
    )
    return list(c.recognize(seq))


def peer_set(found: list[Any]) -> set[tuple[int, ...]]:
    """pychronicles' occurrences as (ta, tb, tc) in ms, to compare."""
    return {tuple(int(x) for x in occ) for occ in found}


def run() -> None:
    """Measure, check both find the same occurrences, and print the BENCH line."""
    events = make_events()
    ns_events = [(label, t * NS_PER_MS) for label, t in events]
    progress(f"chronicle: {N} events, best of {REPEAT}")
    best_ours = best_slide = best_batch = float("inf")
    ref: set[tuple[int, ...]] | None = None
    for _ in range(REPEAT):
        for name, fn, data, conv in (
            ("ours", ours, ns_events, ours_set),
            ("sliding", sliding, events, peer_set),
            ("batch", batch, events, peer_set),
        ):
            gc.collect()
            dt, raw = timed(partial(fn, data))
            got = conv(raw)
            if ref is None:
                ref = got
            elif got != ref:
                raise AssertionError(
                    f"{name} found {len(got)} occurrences, expected {len(ref)}: "
                    f"{sorted(got ^ ref)[:5]}"
                )
            if name == "ours":
                best_ours = min(best_ours, dt)
            elif name == "sliding":
                best_slide = min(best_slide, dt)
            else:
                best_batch = min(best_batch, dt)
    assert ref is not None
    print(
        f"chronicle: {len(ref)} occurrences in {N} events, all tools agree; "
        f"pychronicles batch {fmt(N / best_batch)} events/s"
    )
    report(
        "chronicle",
        N / best_ours,
        "pychronicles-sliding",
        N / best_slide,
        "events/s",
        better="higher",
    )


if __name__ == "__main__":
    run()
