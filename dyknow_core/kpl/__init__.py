"""KPL: a small declarative language describing a DyKnow application, and its setup service.

A KPL text declares sources, computational units, derived streams, states, monitors,
chronicles, object classes and link types (anchoring). ``parse`` gives a plain AST,
``check`` every error with its line and column (policies validated by their pydantic
models, labels resolved, formulas parsed, chronicles compiled), ``setup`` creates the
declarations on an instance in dependency order and ``KPLApplication.remove`` undoes it.
The grammar and an example are in ``docs/kpl.md``.
"""

from ._checker import check, provides
from ._parser import (
    AnchoringDecl,
    ChangesDecl,
    ChronicleDecl,
    ClassDecl,
    CUDecl,
    Decl,
    FuncRef,
    KPLCheckError,
    KPLError,
    KPLSetupError,
    LinkDecl,
    MonitorDecl,
    Program,
    SourceDecl,
    StateDecl,
    StreamDecl,
    UnsupportedDecl,
    parse,
)
from ._setup import KPLApplication, resolve_callable, setup

__all__ = [
    "AnchoringDecl",
    "CUDecl",
    "ChangesDecl",
    "ChronicleDecl",
    "ClassDecl",
    "Decl",
    "FuncRef",
    "KPLApplication",
    "KPLCheckError",
    "KPLError",
    "KPLSetupError",
    "LinkDecl",
    "MonitorDecl",
    "Program",
    "SourceDecl",
    "StateDecl",
    "StreamDecl",
    "UnsupportedDecl",
    "check",
    "parse",
    "provides",
    "resolve_callable",
    "setup",
]
