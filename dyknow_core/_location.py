"""Locations: where fluent approximations live, each with a cache per stream."""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from ._exceptions import DuplicateLabelError, PolicyError, UnknownLabelError
from ._policy import Approximation, CacheSpec
from ._sample import Answer, as_sample
from ._stream import StreamGenerator


class Capability(StrEnum):
    """How a location makes its streams available."""

    PUSH = "push"
    PULL = "pull"


class Location:
    """A named place holding stream generators (a sensor interface, the DOR, an import).

    It declares its capabilities and the default cache each of its streams gets, and
    answers queries: latest, value at t (through a fluent generator), all between t1 and
    t2 — each optionally as believed at a query time (only samples available by then).
    """

    def __init__(
        self,
        name: str,
        *,
        cache: CacheSpec | None = None,
        capabilities: frozenset[Capability] = frozenset({Capability.PUSH, Capability.PULL}),
    ) -> None:
        self.name = name
        self.cache_spec = cache or CacheSpec()
        self.capabilities = capabilities
        self.generators: dict[str, StreamGenerator] = {}

    def add(
        self, label: str, *, cache: CacheSpec | None = None, value_type: type | None = None
    ) -> StreamGenerator:
        """Create the stream generator for ``label`` here."""
        if label in self.generators:
            raise DuplicateLabelError(f"label {label!r} is already published at {self.name!r}")
        gen = StreamGenerator(
            label, cache or self.cache_spec, value_type=value_type, location=self.name
        )
        self.generators[label] = gen
        return gen

    def remove(self, label: str) -> None:
        """Close and forget the stream generator for ``label``."""
        gen = self.generators.pop(label, None)
        if gen is None:
            raise UnknownLabelError(label, list(self.generators))
        gen.close()

    def generator(self, label: str) -> StreamGenerator:
        """The stream generator for ``label``, or UnknownLabelError."""
        try:
            return self.generators[label]
        except KeyError:
            raise UnknownLabelError(label, list(self.generators)) from None

    def latest(self, label: str, *, query_time: int, as_of: int | None = None) -> Answer:
        """The newest value (greatest valid time) as believed at ``as_of``."""
        s = self.generator(label).cache.latest(as_of)
        return Answer(label, query_time, [] if s is None else [as_sample(s)])

    def at(
        self,
        label: str,
        t: int,
        *,
        query_time: int,
        approximation: Approximation = Approximation.MOST_RECENT,
        as_of: int | None = None,
    ) -> Answer:
        """The value at valid time ``t`` through a fluent generator with ``approximation``."""
        try:
            s = self.generator(label).cache.at(t, approximation, as_of)
        except TypeError as exc:
            raise PolicyError(
                "approximation", f"{approximation.value} needs numeric values in {label!r}: {exc}"
            ) from exc
        return Answer(label, query_time, [] if s is None else [as_sample(s)])

    def between(
        self,
        label: str,
        t1: int,
        t2: int,
        *,
        query_time: int,
        as_of: int | None = None,
        all_estimates: bool = False,
    ) -> Answer:
        """Samples with valid time in [t1, t2]: newest estimate of each, or ``all_estimates``."""
        if t1 > t2:
            raise PolicyError("t1", f"interval start {t1} is after its end {t2}")
        cache = self.generator(label).cache
        samples = cache.history(t1, t2, as_of) if all_estimates else cache.between(t1, t2, as_of)
        return Answer(label, query_time, [as_sample(s) for s in samples])

    def describe(self) -> dict[str, Any]:
        """What this location is and holds, for listings."""
        return {
            "name": self.name,
            "capabilities": sorted(c.value for c in self.capabilities),
            "cache": self.cache_spec.model_dump(),
            "labels": sorted(self.generators),
        }
