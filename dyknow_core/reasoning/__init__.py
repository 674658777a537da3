"""The reasoning layer over the core: MTL monitors, chronicles, anchoring, refinement.

It builds on the core (streams, states, processes) and the core does not import it:
``import dyknow_core`` stays cheap for a platform that never reasons. Each function here
takes the instance as its first argument (``add_monitor(instance, "always[0,5] p")``).
Importing this package registers its value types (``Verdict``, ``Recognition``) with the
recorder, so a replay gives them back as themselves.
"""

from ._anchoring import Anchoring, Codesignation, LinkType, ObjectClass, add_anchoring
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
from .chronicles import (
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
from .mtl import (
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
from .mtl import parse as parse_formula

__all__ = [
    "Anchoring",
    "ChronicleError",
    "ChronicleProcess",
    "ChronicleRecognizer",
    "ChronicleSpec",
    "Codesignation",
    "CompiledChronicle",
    "ConstraintSpec",
    "EventSpec",
    "FocusOfAttention",
    "ForbiddenSpec",
    "LinkType",
    "MTLSyntaxError",
    "Monitor",
    "MonitorProcess",
    "ObjectClass",
    "RateChange",
    "Recognition",
    "RecognizerStats",
    "Refinement",
    "RefinementProcess",
    "Residual",
    "StepMonitor",
    "Verdict",
    "add_anchoring",
    "add_chronicle",
    "add_monitor",
    "add_refinement",
    "compile_chronicle",
    "compile_formula",
    "domains",
    "evaluate",
    "features",
    "is_suspended",
    "parse_formula",
    "progress",
    "recognize_all",
    "resume_unit",
    "state_keys",
    "suspend_unit",
]
