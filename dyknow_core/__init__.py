"""DyKnow core: streams, policies, knowledge processes, locations, states, events, objects.

A local DyKnow instance. Everything public is re-exported here; the underscored modules
are the implementation.
"""

import importlib
from typing import TYPE_CHECKING, Any

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
from ._record import (
    RecordedSample,
    Recorder,
    RecordError,
    RecordHeader,
    Recording,
    RecordWriter,
    ReplaySummary,
    advance_to,
    read_recording,
    replay,
)
from ._sample import Answer, RawSample, Sample, as_sample
from ._state import Missing, StatePolicy, StateProcess, StateStats, StateStrategy, add_state
from ._stream import StreamGenerator, StreamMetrics, Subscription
from ._time import NS_PER_S, Clock, ManualClock, RealClock, ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    from ._anchoring import Anchoring, Codesignation, LinkType, ObjectClass, add_anchoring
    from ._chronicles import (
        ChronicleError,
        ChronicleProcess,
        ChronicleRecognizer,
        ChronicleSpec,
        CompiledChronicle,
        ConstraintSpec,
        EventSpec,
        ForbiddenSpec,
        Recognition,
        RecognizerStats,
        add_chronicle,
        compile_chronicle,
        recognize_all,
    )
    from ._kpl import KPLApplication, KPLCheckError, KPLError, KPLSetupError
    from ._kpl import check as kpl_check
    from ._kpl import parse as kpl_parse
    from ._kpl import setup as kpl_setup
    from ._mtl import (
        Monitor,
        MonitorProcess,
        MTLSyntaxError,
        Residual,
        StepMonitor,
        Verdict,
        add_monitor,
        compile_formula,
        domains,
        evaluate,
        features,
        progress,
        state_keys,
    )
    from ._mtl import parse as parse_formula
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


# The reasoning layer (MTL, chronicles, anchoring, refinement, KPL) loads on first use:
# `import dyknow_core` (every platform, every `dyknow` command) then costs about half.
_LAZY: dict[str, tuple[str, str]] = {
    "Anchoring": ("_anchoring", "Anchoring"),
    "Codesignation": ("_anchoring", "Codesignation"),
    "LinkType": ("_anchoring", "LinkType"),
    "ObjectClass": ("_anchoring", "ObjectClass"),
    "add_anchoring": ("_anchoring", "add_anchoring"),
    "ChronicleError": ("_chronicles", "ChronicleError"),
    "ChronicleProcess": ("_chronicles", "ChronicleProcess"),
    "ChronicleRecognizer": ("_chronicles", "ChronicleRecognizer"),
    "ChronicleSpec": ("_chronicles", "ChronicleSpec"),
    "CompiledChronicle": ("_chronicles", "CompiledChronicle"),
    "ConstraintSpec": ("_chronicles", "ConstraintSpec"),
    "EventSpec": ("_chronicles", "EventSpec"),
    "ForbiddenSpec": ("_chronicles", "ForbiddenSpec"),
    "Recognition": ("_chronicles", "Recognition"),
    "RecognizerStats": ("_chronicles", "RecognizerStats"),
    "add_chronicle": ("_chronicles", "add_chronicle"),
    "compile_chronicle": ("_chronicles", "compile_chronicle"),
    "recognize_all": ("_chronicles", "recognize_all"),
    "KPLApplication": ("_kpl", "KPLApplication"),
    "KPLCheckError": ("_kpl", "KPLCheckError"),
    "KPLError": ("_kpl", "KPLError"),
    "KPLSetupError": ("_kpl", "KPLSetupError"),
    "kpl_check": ("_kpl", "check"),
    "kpl_parse": ("_kpl", "parse"),
    "kpl_setup": ("_kpl", "setup"),
    "Monitor": ("_mtl", "Monitor"),
    "MonitorProcess": ("_mtl", "MonitorProcess"),
    "MTLSyntaxError": ("_mtl", "MTLSyntaxError"),
    "Residual": ("_mtl", "Residual"),
    "StepMonitor": ("_mtl", "StepMonitor"),
    "Verdict": ("_mtl", "Verdict"),
    "add_monitor": ("_mtl", "add_monitor"),
    "compile_formula": ("_mtl", "compile_formula"),
    "domains": ("_mtl", "domains"),
    "evaluate": ("_mtl", "evaluate"),
    "features": ("_mtl", "features"),
    "progress": ("_mtl", "progress"),
    "state_keys": ("_mtl", "state_keys"),
    "parse_formula": ("_mtl", "parse"),
    "FocusOfAttention": ("_refinement", "FocusOfAttention"),
    "RateChange": ("_refinement", "RateChange"),
    "Refinement": ("_refinement", "Refinement"),
    "RefinementProcess": ("_refinement", "RefinementProcess"),
    "add_refinement": ("_refinement", "add_refinement"),
    "is_suspended": ("_refinement", "is_suspended"),
    "resume_unit": ("_refinement", "resume_unit"),
    "suspend_unit": ("_refinement", "suspend_unit"),
}


def __getattr__(name: str) -> Any:
    """Import a reasoning-layer name (and its module) the first time it is asked for."""
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    globals()[name] = value  # once: later lookups do not come here
    return value


__all__ = [
    "DEFAULT_LOCATION",
    "DOM",
    "NS_PER_S",
    "Anchoring",
    "Answer",
    "Approximation",
    "Cache",
    "CacheSpec",
    "Capability",
    "Change",
    "ChangeEvent",
    "ChangeKind",
    "ChronicleError",
    "ChronicleProcess",
    "ChronicleRecognizer",
    "ChronicleSpec",
    "Clock",
    "ClosedError",
    "Codesignation",
    "CompiledChronicle",
    "ComputationalUnit",
    "ConstraintSpec",
    "Domain",
    "DomainChange",
    "DomainSubscription",
    "DuplicateLabelError",
    "DyKnowError",
    "DyKnowInstance",
    "EventProcess",
    "EventSpec",
    "FilterStats",
    "FocusOfAttention",
    "ForbiddenSpec",
    "Input",
    "KPLApplication",
    "KPLCheckError",
    "KPLError",
    "KPLSetupError",
    "LateAction",
    "LinkType",
    "Location",
    "MTLSyntaxError",
    "ManualClock",
    "MembershipChange",
    "Missing",
    "Monitor",
    "MonitorProcess",
    "ObjectClass",
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
    "Recognition",
    "RecognizerStats",
    "RecordError",
    "RecordHeader",
    "RecordWriter",
    "RecordedSample",
    "Recorder",
    "Recording",
    "Refinement",
    "RefinementProcess",
    "ReplaySummary",
    "Residual",
    "Sample",
    "SetSubscription",
    "Source",
    "StatePolicy",
    "StateProcess",
    "StateStats",
    "StateStrategy",
    "StepMonitor",
    "StreamGenerator",
    "StreamMetrics",
    "Subscription",
    "UnknownLabelError",
    "Verdict",
    "add_anchoring",
    "add_arrival_events",
    "add_change_events",
    "add_chronicle",
    "add_monitor",
    "add_refinement",
    "add_state",
    "advance_to",
    "as_sample",
    "compile_chronicle",
    "compile_formula",
    "domains",
    "evaluate",
    "features",
    "is_suspended",
    "kpl_check",
    "kpl_parse",
    "kpl_setup",
    "ns_to_seconds",
    "parse_formula",
    "progress",
    "read_recording",
    "recognize_all",
    "replay",
    "resume_unit",
    "seconds_to_ns",
    "state_keys",
    "suspend_unit",
]
