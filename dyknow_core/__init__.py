"""DyKnow core: streams, policies, knowledge processes, locations, states, events, objects.

A local DyKnow instance. Everything public is re-exported here; the underscored modules
are the implementation.
"""

from ._cache import Cache
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
    "FilterStats",
    "Input",
    "LateAction",
    "Location",
    "ManualClock",
    "MembershipChange",
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
    "Sample",
    "SetSubscription",
    "Source",
    "StreamGenerator",
    "StreamMetrics",
    "Subscription",
    "UnknownLabelError",
    "as_sample",
    "ns_to_seconds",
    "seconds_to_ns",
]
