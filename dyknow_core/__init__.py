"""DyKnow core: streams, policies, knowledge processes, locations, states, events, objects.

A local DyKnow instance. Everything public is re-exported here; the underscored modules
are the implementation.
"""

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
from ._refinement import (
    FocusOfAttention,
    RateChange,
    Refinement,
    RefinementProcess,
    add_refinement,
    is_suspended,
    resume_unit,
    suspend_unit,
)
from ._sample import Answer, RawSample, Sample, as_sample
from ._state import Missing, StatePolicy, StateProcess, StateStats, StateStrategy, add_state
from ._stream import StreamGenerator, StreamMetrics, Subscription
from ._time import NS_PER_S, Clock, ManualClock, RealClock, ns_to_seconds, seconds_to_ns

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
    "FocusOfAttention",
    "Input",
    "LateAction",
    "Location",
    "ManualClock",
    "MembershipChange",
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
    "RateChange",
    "RawSample",
    "RealClock",
    "Refinement",
    "RefinementProcess",
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
    "add_refinement",
    "add_state",
    "as_sample",
    "is_suspended",
    "ns_to_seconds",
    "resume_unit",
    "seconds_to_ns",
    "suspend_unit",
]
