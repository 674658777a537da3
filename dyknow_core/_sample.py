"""Samples: the unit of a fluent stream, kept as plain tuples for the hot path."""

from __future__ import annotations

from typing import Any, NamedTuple


class Sample(NamedTuple):
    """One value of a fluent stream: ⟨value, valid time, available time⟩ in nanoseconds.

    ``valid_time`` is when the value holds in the world; ``available_time`` when it became
    available at this location. ``available_time < valid_time`` is a prediction.
    """

    value: Any
    valid_time: int
    available_time: int


class Answer(NamedTuple):
    """The answer to a query at a location: the samples and the query time they were read at."""

    label: str
    query_time: int
    samples: list[Sample]

    @property
    def latest(self) -> Sample | None:
        """The last sample of the answer, or None when it is empty."""
        return self.samples[-1] if self.samples else None
