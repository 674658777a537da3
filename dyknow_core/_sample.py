"""Samples: the unit of a fluent stream, kept as plain tuples for the hot path."""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
from typing import Any, NamedTuple


class Sample(NamedTuple):
    """One value of a fluent stream: ⟨value, valid time, available time⟩ in nanoseconds.

    ``valid_time`` is when the value holds in the world; ``available_time`` when it became
    available at this location. ``available_time < valid_time`` is a prediction.
    """

    value: Any
    valid_time: int
    available_time: int


# Per-sample paths carry plain ``(value, valid_time, available_time)`` tuples: a tuple of
# scalars is untracked by the cyclic GC after its first collection, a NamedTuple never is,
# and with millions of live samples the GC then costs more than the processing. A Sample
# is made only where a user reads one (iterator items, query answers).
RawSample = tuple[Any, int, int]

_tuple_new: Any = tuple.__new__


def as_sample(raw: RawSample) -> Sample:
    """View a raw ``(value, valid_time, available_time)`` tuple as a Sample."""
    return raw if type(raw) is Sample else _tuple_new(Sample, raw)


class Answer(NamedTuple):
    """The answer to a query at a location: the samples and the query time they were read at."""

    label: str
    query_time: int
    samples: list[Sample]

    @property
    def latest(self) -> Sample | None:
        """The last sample of the answer, or None when it is empty."""
        return self.samples[-1] if self.samples else None
