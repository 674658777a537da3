"""A sender's numbering as one receiver sees it: gaps, what is still missing, what came late.

Every batch carries ``q``, the number of its first sample in the export. An import's
`SequenceTracker` follows those numbers: a batch above the next expected number opens a
gap (counted ``lost``), resent samples fill it (``recovered``), and a batch below it is
the sender's new numbering (an export started again). The range helpers below are the
sorted, disjoint ``[first, end)`` lists both proxies keep.
"""

from __future__ import annotations

__all__ = ["SequenceTracker", "cover", "uncovered"]

_MAX_MISSING = 64  # missing ranges tracked per import: the oldest are forgotten
_MAX_ASKS = 6  # the reports that ask again for what is still missing


def uncovered(ranges: list[tuple[int, int]], first: int, end: int) -> list[tuple[int, int]]:
    """The parts of [first, end) that no range of ``ranges`` (sorted, disjoint) covers."""
    out: list[tuple[int, int]] = []
    for a, b in ranges:
        if b <= first:
            continue
        if a >= end:
            break
        if a > first:
            out.append((first, a))
        first = max(first, b)
        if first >= end:
            return out
    if first < end:
        out.append((first, end))
    return out


def cover(ranges: list[tuple[int, int]], first: int, end: int) -> list[tuple[int, int]]:
    """``ranges`` (sorted, disjoint) with [first, end) added, touching ranges merged."""
    out: list[tuple[int, int]] = []
    for a, b in ranges:
        if b < first or a > end:
            out.append((a, b))
        else:
            first, end = min(a, first), max(b, end)
    out.append((first, end))
    out.sort()
    return out


class SequenceTracker:
    """The gaps in one sender's numbering of one stream, and those a resend may still fill.

    ``lost``: samples that never arrived and were not recovered (all numberings);
    ``gaps``: gaps seen; ``recovered``: samples that filled a gap late; ``missing``: the
    ranges a resend may still fill (only while the sender keeps a history); ``asks``:
    how often the reports asked again for them.
    """

    __slots__ = ("_lost_base", "asks", "gaps", "lost", "missing", "next", "recovered")

    def __init__(self) -> None:
        self.next: int | None = None  # the number expected next; None before any
        self.missing: list[tuple[int, int]] = []  # [first, end) not arrived, may be resent
        self.asks = 0
        self.lost = 0
        self.gaps = 0
        self.recovered = 0
        self._lost_base = 0  # `lost` when the sender's current numbering began

    def __repr__(self) -> str:
        return (
            f"<SequenceTracker next={self.next} lost={self.lost} gaps={self.gaps} "
            f"missing={self.missing}>"
        )

    @property
    def lost_now(self) -> int:
        """Samples lost (and not recovered) from the sender's current numbering: reported."""
        return max(self.lost - self._lost_base, 0)

    def arrived(self, seq: int, count: int, history: int) -> tuple[int, int] | None:
        """A batch of ``count`` samples numbered from ``seq``; the range to ask resent, if any.

        A gap is counted lost; with ``history`` (what the sender keeps) the numbers it
        can still resend are remembered as missing and returned, to be asked for at once.
        """
        expected = self.next
        self.next = seq + count
        if expected is None or seq == expected:
            return None
        if seq < expected:
            self.restart()
            return None
        self.lost += seq - expected
        self.gaps += 1
        if not history:
            return None
        first = max(expected, seq - history)  # older ones are not kept
        self.missing.append((first, seq))
        del self.missing[:-_MAX_MISSING]
        self.asks = 0
        return first, seq

    def restart(self) -> None:
        """The sender numbers anew (it restarted the export): its reports count from here.

        What is missing can no longer be resent; the new export's own counters start at 0.
        """
        self.missing.clear()
        self._lost_base = self.lost

    def fill(self, first: int, end: int) -> list[tuple[int, int]]:
        """Resent samples [first, end) arrived: the parts still missing, now no longer."""
        filled: list[tuple[int, int]] = []
        missing: list[tuple[int, int]] = []
        for a, b in self.missing:
            lo, hi = max(a, first), min(b, end)
            if lo >= hi:
                missing.append((a, b))
                continue
            filled.append((lo, hi))
            if a < lo:
                missing.append((a, lo))
            if hi < b:
                missing.append((hi, b))
        self.missing = missing
        return filled

    def recover(self, count: int) -> None:
        """``count`` samples of a filled gap were added after all: no longer lost."""
        self.recovered += count
        self.lost -= count

    def ask_again(self) -> list[int] | None:
        """The span still missing, ``[first, end]``, while the asks left allow; else None.

        A resend and the request for it may both be lost on the way: the reports ask again.
        """
        if not self.missing or self.asks >= _MAX_ASKS:
            return None
        self.asks += 1
        return [self.missing[0][0], self.missing[-1][1]]
