"""DyKnow core: streams, policies, knowledge processes, locations, states, events, objects.

A local DyKnow instance. Everything public in the core is re-exported here; the
underscored modules are the implementation. The layers above are packages of their own
that the core does not import: ``dyknow_core.reasoning`` (MTL, chronicles, anchoring,
refinement) and ``dyknow_core.kpl`` (the declarative application language).

The recording names (``Recorder``, ``replay``, ``sample_json``, …) are imported on first
use: most processes (a node that records nothing) never need their ~1 300 lines.
"""

from typing import TYPE_CHECKING, Any

from ._aio import sleep_until_woken
from ._cache import Cache
from ._events import ChangeEvent, EventProcess, add_arrival_events, add_change_events
from ._exceptions import (
    ClosedError,
    DuplicateLabelError,
    DyKnowError,
    ObjectError,
    PolicyError,
    ProcessError,
    UnknownLabelError,
)
from ._filter import FilterStats, PolicyFilter
from ._instance import DEFAULT_LOCATION, DyKnowInstance
from ._location import Capability, Location
from ._objects import (
    DOM,
    Domain,
    DomainChange,
    DomainSubscription,
    MembershipChange,
    ObjectManager,
    SetSubscription,
)
from ._policy import (
    Approximation,
    CacheSpec,
    Change,
    ChangeKind,
    LateAction,
    Order,
    Overflow,
    Policy,
)
from ._process import ComputationalUnit, Input, Process, ProcessFailure, Source
from ._sample import Answer, RawSample, Sample, as_sample
from ._state import Missing, StatePolicy, StateProcess, StateStats, StateStrategy, add_state
from ._stream import StreamGenerator, StreamMetrics, Subscription
from ._time import NS_PER_S, Clock, ManualClock, RealClock, ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    from ._record import (
        MessageDecoder,
        RecordedSample,
        Recorder,
        RecordError,
        RecordHeader,
        Recording,
        RecordWriter,
        ReplaySummary,
        advance_to,
        label_schema,
        read_recording,
        recording_info,
        register_record_type,
        replay,
        sample_json,
        topic_label,
    )

_RECORD_NAMES = frozenset(
    (
        "MessageDecoder",
        "RecordedSample",
        "Recorder",
        "RecordError",
        "RecordHeader",
        "Recording",
        "RecordWriter",
        "ReplaySummary",
        "advance_to",
        "label_schema",
        "read_recording",
        "recording_info",
        "register_record_type",
        "replay",
        "sample_json",
        "topic_label",
    )
)

__all__ = [
    "DEFAULT_LOCATION",
    "DOM",
    "NS_PER_S",
    "Answer",
    "Approximation",
    "Cache",
    "CacheSpec",
    "Capability",
    "Change",
    "ChangeEvent",
    "ChangeKind",
    "Clock",
    "ClosedError",
    "ComputationalUnit",
    "Domain",
    "DomainChange",
    "DomainSubscription",
    "DuplicateLabelError",
    "DyKnowError",
    "DyKnowInstance",
    "EventProcess",
    "FilterStats",
    "Input",
    "LateAction",
    "Location",
    "ManualClock",
    "MembershipChange",
    "MessageDecoder",
    "Missing",
    "ObjectError",
    "ObjectManager",
    "Order",
    "Overflow",
    "Policy",
    "PolicyError",
    "PolicyFilter",
    "Process",
    "ProcessError",
    "ProcessFailure",
    "RawSample",
    "RealClock",
    "RecordError",
    "RecordHeader",
    "RecordWriter",
    "RecordedSample",
    "Recorder",
    "Recording",
    "ReplaySummary",
    "Sample",
    "SetSubscription",
    "Source",
    "StatePolicy",
    "StateProcess",
    "StateStats",
    "StateStrategy",
    "StreamGenerator",
    "StreamMetrics",
    "Subscription",
    "UnknownLabelError",
    "add_arrival_events",
    "add_change_events",
    "add_state",
    "advance_to",
    "as_sample",
    "label_schema",
    "ns_to_seconds",
    "read_recording",
    "recording_info",
    "register_record_type",
    "replay",
    "sample_json",
    "seconds_to_ns",
    "sleep_until_woken",
    "topic_label",
]


def __getattr__(name: str) -> Any:
    """A recording name, imported from ``_record`` on first use (then a plain attribute)."""
    if name in _RECORD_NAMES:
        from . import _record

        value = getattr(_record, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
