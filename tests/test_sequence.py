"""The import's sequence tracker: a sender's numbering, its gaps and their late filling."""

from __future__ import annotations

import pytest

from federation._sequence import SequenceTracker, cover, uncovered


def test_in_order_batches_lose_nothing() -> None:
    seq = SequenceTracker()
    assert seq.arrived(0, 3, history=10) is None
    assert seq.arrived(3, 0, history=10) is None  # a keepalive carries the next number
    assert seq.arrived(3, 2, history=10) is None
    assert (seq.next, seq.lost, seq.gaps, seq.missing, seq.lost_now) == (5, 0, 0, [], 0)


def test_a_first_batch_after_zero_is_not_a_gap() -> None:
    seq = SequenceTracker()
    assert seq.arrived(40, 2, history=10) is None  # joined late: nothing expected yet
    assert (seq.next, seq.lost) == (42, 0)


def test_a_gap_is_lost_and_asked_back_within_the_history() -> None:
    seq = SequenceTracker()
    seq.arrived(0, 5, history=3)
    assert seq.arrived(10, 2, history=3) == (7, 10)  # only the last 3 before the gap are kept
    assert (seq.lost, seq.gaps, seq.missing, seq.next) == (5, 1, [(7, 10)], 12)
    assert seq.ask_again() == [7, 10]


def test_without_history_a_gap_is_only_counted() -> None:
    seq = SequenceTracker()
    seq.arrived(0, 5, history=0)
    assert seq.arrived(8, 1, history=0) is None
    assert (seq.lost, seq.gaps, seq.missing) == (3, 1, [])
    assert seq.ask_again() is None


def test_a_late_fill_splits_what_is_missing() -> None:
    seq = SequenceTracker()
    seq.arrived(0, 2, history=100)
    seq.arrived(10, 1, history=100)  # missing [2, 10)
    assert seq.fill(4, 6) == [(4, 6)]
    assert seq.missing == [(2, 4), (6, 10)]
    seq.recover(2)
    assert (seq.lost, seq.recovered, seq.lost_now) == (6, 2, 6)
    # a resend overlapping both pieces and beyond fills only what is missing
    assert seq.fill(0, 8) == [(2, 4), (6, 8)]
    assert seq.missing == [(8, 10)]


def test_a_duplicate_fills_nothing() -> None:
    seq = SequenceTracker()
    seq.arrived(0, 1, history=10)
    seq.arrived(4, 1, history=10)
    assert seq.fill(1, 4) == [(1, 4)]
    seq.recover(3)
    assert seq.fill(1, 4) == []  # resent twice: the second copy is a duplicate
    assert (seq.lost, seq.recovered, seq.missing) == (0, 3, [])


def test_asks_are_bounded_and_renewed_by_a_new_gap() -> None:
    seq = SequenceTracker()
    seq.arrived(0, 1, history=10)
    seq.arrived(3, 1, history=10)
    asks = [seq.ask_again() for _ in range(10)]
    assert asks[:6] == [[1, 3]] * 6 and asks[6:] == [None] * 4
    seq.arrived(6, 1, history=10)
    assert seq.ask_again() == [1, 6]  # the span of everything still missing


def test_a_lower_number_is_a_new_numbering() -> None:
    seq = SequenceTracker()
    seq.arrived(0, 5, history=10)
    seq.arrived(8, 2, history=10)  # 3 lost, missing [5, 8)
    assert seq.arrived(0, 2, history=10) is None  # the export started again
    assert seq.missing == [] and seq.next == 2
    assert (seq.lost, seq.lost_now, seq.gaps) == (3, 0, 1)  # reports count the new numbering
    seq.arrived(4, 1, history=10)
    assert (seq.lost, seq.lost_now) == (5, 2)


@pytest.mark.parametrize(
    ("ranges", "first", "end", "free", "merged"),
    [
        ([], 0, 5, [(0, 5)], [(0, 5)]),
        ([(2, 4)], 0, 6, [(0, 2), (4, 6)], [(0, 6)]),
        ([(0, 3), (5, 8)], 3, 5, [(3, 5)], [(0, 8)]),
        ([(0, 10)], 2, 4, [], [(0, 10)]),
        ([(6, 9)], 0, 2, [(0, 2)], [(0, 2), (6, 9)]),
    ],
)
def test_range_helpers(
    ranges: list[tuple[int, int]],
    first: int,
    end: int,
    free: list[tuple[int, int]],
    merged: list[tuple[int, int]],
) -> None:
    assert uncovered(ranges, first, end) == free
    assert cover(ranges, first, end) == merged
