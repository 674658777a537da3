"""Chronicles: patterns of events with metric constraints, recognized online and incrementally.

A chronicle is a set of named events (each an input event kind with parameters and an
optional ``from``/``to`` value change), metric constraints ``lo <= t(end) - t(start) <= hi``
between their times (a simple temporal network), and optionally forbidden events in an
interval. Its definition (``ChronicleSpec``, pydantic, seconds) is checked and compiled
once (``compile_chronicle``: Floyd–Warshall on the distance graph; a negative cycle is a
``ChronicleError`` naming the constraints on it) into the form the hot path reads.

Recognition (``ChronicleRecognizer``) reports every occurrence: every assignment of
distinct input events to the chronicle's events that unifies the parameters, meets all
constraints and has no forbidden event in a forbidden interval. Events must come in
non-decreasing time (their valid time is the clock); an earlier one is counted as late and
ignored. Partial instances are indexed by (expected event, bound parameters), expire as
soon as one of their missing events can no longer come in time, and are capped in number
(the oldest dropped and counted). Because the minimal network of an STN is decomposable,
keeping each missing event's time window, narrowed from the assigned events only, is exact.

Forbidden intervals are open: ``between`` two events ``(t(start), t(end))``, or ``after``
one event ``(t(start) + lo, t(start) + hi)`` with ``0 <= lo``. A forbidden event's
parameters are either bound by its start event or free (any value).
"""

from ._compile import CompiledChronicle, compile_chronicle
from ._process import ChronicleProcess, add_chronicle, recognize_all
from ._recognizer import ChronicleRecognizer, Recognition, RecognizerStats
from ._spec import ChronicleError, ChronicleSpec, ConstraintSpec, EventSpec, ForbiddenSpec

__all__ = [
    "ChronicleError",
    "ChronicleProcess",
    "ChronicleRecognizer",
    "ChronicleSpec",
    "CompiledChronicle",
    "ConstraintSpec",
    "EventSpec",
    "ForbiddenSpec",
    "Recognition",
    "RecognizerStats",
    "add_chronicle",
    "compile_chronicle",
    "recognize_all",
]
