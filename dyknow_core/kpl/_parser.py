"""KPL: a small declarative language describing a DyKnow application, and its setup service.

A KPL text declares sources, computational units, derived streams, states, monitors,
chronicles, object classes and link types (anchoring). ``parse`` gives a plain AST,
``check`` every error with its line and column (policies validated by their pydantic
models, labels resolved, formulas parsed, chronicles compiled), ``setup`` creates the
declarations on an instance in dependency order and ``KPLApplication.remove`` undoes it.
The grammar and an example are in ``docs/kpl.md``.
"""

from __future__ import annotations

import importlib
import logging
import math
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ._anchoring import LinkType, ObjectClass, add_anchoring
from ._chronicles import ChronicleError, compile_chronicle
from ._exceptions import DyKnowError, PolicyError
from ._mtl import MTLSyntaxError, state_keys
from ._mtl import parse as parse_formula
from ._policy import CacheSpec, Change, Policy, check_duration
from ._process import Input
from ._state import StatePolicy

if TYPE_CHECKING:
    from ._instance import DyKnowInstance

log = logging.getLogger(__name__)

Pos = tuple[int, int]  # (line, column), both 1-based

# -- errors ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class KPLError:
    """One problem in a KPL text: where it is, what is wrong, and the line with a caret."""

    line: int
    column: int
    message: str
    excerpt: str = ""

    def format(self, filename: str = "<kpl>") -> str:
        """``FILE:LINE:COL: message``, the one-line form the command prints."""
        return f"{filename}:{self.line}:{self.column}: {self.message}"

    def __str__(self) -> str:
        head = f"line {self.line}, column {self.column}: {self.message}"
        return f"{head}\n{self.excerpt}" if self.excerpt else head


class KPLCheckError(DyKnowError, ValueError):
    """A KPL text that does not check; ``errors`` holds every problem found."""

    def __init__(self, errors: list[KPLError]) -> None:
        self.errors = errors
        first = errors[0] if errors else None
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        super().__init__(f"KPL: {first}{more}" if first else "KPL: invalid")


class KPLSetupError(DyKnowError):
    """A declaration that checked but could not be created on the instance."""

    def __init__(self, pos: Pos, message: str) -> None:
        self.line, self.column = pos
        self.message = message
        super().__init__(f"line {pos[0]}, column {pos[1]}: {message}")


class _Fail(Exception):
    """Parse failure at a position; the parser stops the declaration and resynchronizes."""

    def __init__(self, pos: Pos, message: str) -> None:
        super().__init__(message)
        self.pos = pos
        self.message = message


def _excerpt(lines: list[str], line: int, column: int) -> str:
    if not 1 <= line <= len(lines):
        return ""
    text = lines[line - 1].expandtabs(1)
    return f"  {text}\n  {' ' * (column - 1)}^"


# -- tokens ---------------------------------------------------------------------------------

_TOKEN = re.compile(
    r"""(?P<ws>[ \t\r\n]+|\#[^\n]*)
      | (?P<num>(?:\d+\.\d*|\.\d+|\d+)(?:[eE][+-]?\d+)?)
      | (?P<str>"(?:[^"\\\n]|\\.)*")
      | (?P<name>[A-Za-z_][A-Za-z0-9_./]*)
      | (?P<op>->|[{}\[\](),:=\-])
    """,
    re.VERBOSE,
)


@dataclass(frozen=True)
class _Tok:
    kind: str  # name, num, str, op, end
    text: str
    pos: Pos


def _unquote(s: str) -> str:
    return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), s[1:-1])


def _tokenize(text: str) -> tuple[list[_Tok], list[KPLError]]:
    toks: list[_Tok] = []
    errs: list[tuple[Pos, str]] = []
    line, line_start, i = 1, 0, 0
    while i < len(text):
        m = _TOKEN.match(text, i)
        pos = (line, i - line_start + 1)
        if m is None:
            ch = text[i]
            msg = "unterminated string" if ch == '"' else f"unexpected character {ch!r}"
            errs.append((pos, msg))
            i = text.find("\n", i) if ch == '"' else i + 1
            if i < 0:
                i = len(text)
            continue
        kind = m.lastgroup or "ws"
        if kind != "ws":
            toks.append(_Tok(kind, m.group(), pos))
        nl = m.group().count("\n")
        if nl:
            line += nl
            line_start = m.start() + m.group().rfind("\n") + 1
        i = m.end()
    toks.append(_Tok("end", "", (line, i - line_start + 1)))
    lines = text.splitlines()
    return toks, [KPLError(p[0], p[1], msg, _excerpt(lines, *p)) for p, msg in errs]


# -- AST ------------------------------------------------------------------------------------


@dataclass
class Entry:
    """One ``key: value`` of a ``{…}`` mapping, with where the key and value are."""

    key: str
    value: Any
    key_pos: Pos
    value_pos: Pos


@dataclass
class MappingNode:
    """A ``{key: value, …}`` mapping in source order."""

    entries: list[Entry]
    pos: Pos

    def as_dict(self) -> dict[str, Any]:
        """The mapping as a plain dict."""
        return {e.key: e.value for e in self.entries}

    def where(self, key: str) -> Pos:
        """Where ``key`` is written (or the mapping's brace)."""
        return next((e.key_pos for e in self.entries if e.key == key), self.pos)


@dataclass
class Ref:
    """A reference to a stream label, where it is written."""

    label: str
    pos: Pos


@dataclass
class SourceDecl:
    """``source LABEL [cache {…}]``."""

    label: str
    cache: MappingNode | None
    pos: Pos
    kind: str = "source"


@dataclass
class InputNode:
    """One CU input: a label and its optional policy."""

    ref: Ref
    policy: MappingNode | None


@dataclass
class CUDecl:
    """``cu NAME = MODULE:CALLABLE[(ARGS)] inputs IN, … output LABEL``."""

    name: str
    module: str
    attr: str
    args: MappingNode | None  # None: the callable itself is the unit, else a factory
    inputs: list[InputNode]
    output: Ref
    pos: Pos
    kind: str = "cu"


@dataclass
class StreamDecl:
    """``stream LABEL = LABEL [with {…}]``: a stream derived from another by a policy."""

    label: str
    source: Ref
    policy: MappingNode | None
    pos: Pos
    kind: str = "stream"


@dataclass
class StateDecl:
    """``state LABEL = {name: label, …} every P [STRATEGY] [max_delay D] [missing M]``."""

    label: str
    components: MappingNode
    policy: MappingNode  # StatePolicy fields collected from the clauses
    pos: Pos
    kind: str = "state"


@dataclass
class MonitorDecl:
    """``monitor NAME = "FORMULA" every P [max_delay D] [with {feature: label}] [output L]``."""

    name: str
    formula: str
    formula_pos: Pos
    period: float
    max_delay: float | None
    components: MappingNode | None
    output: str | None
    pos: Pos
    kind: str = "monitor"

    @property
    def label(self) -> str:
        """The label the verdicts are published under."""
        return self.output or f"monitors/{self.name}"


@dataclass
class ChronicleDecl:
    """``chronicle NAME { event …; constraint …; forbidden …; input …; output … }``."""

    name: str
    events: list[dict[str, Any]]
    constraints: list[dict[str, Any]]
    forbidden: list[dict[str, Any]]
    inputs: dict[str, Ref]
    output: str | None
    pos: Pos
    item_pos: dict[str, Pos] = field(default_factory=dict)  # "events.0" -> where
    kind: str = "chronicle"

    @property
    def label(self) -> str:
        """The label the recognitions are published under."""
        return self.output or f"chronicles/{self.name}"

    def spec(self) -> dict[str, Any]:
        """The definition as a ``ChronicleSpec`` mapping."""
        return {
            "name": self.name,
            "events": self.events,
            "constraints": self.constraints,
            "forbidden": self.forbidden,
        }


@dataclass
class ChangesDecl:
    """``changes LABEL [by CHANGE]``: change events on ``events/changed/LABEL``."""

    source: Ref
    change: str
    change_pos: Pos
    pos: Pos
    kind: str = "changes"

    @property
    def label(self) -> str:
        """The label the change events are published under."""
        return f"events/changed/{self.source.label}"


@dataclass
class UnsupportedDecl:
    """A declaration parsed but not set up (kept for compatibility; none is produced now)."""

    kind: str
    name: str
    pos: Pos


@dataclass
class FuncRef:
    """A ``module:callable`` reference, resolved at setup only."""

    module: str
    attr: str
    pos: Pos


@dataclass
class ClassDecl:
    """``class NAME { base B; prefix P; feature F = "PATTERN"; create/add/maintain … }``."""

    name: str
    fields: MappingNode  # ObjectClass fields written as clauses (key_pos: the clause keyword)
    features: MappingNode  # feature -> label pattern with {id}
    relations: dict[str, FuncRef]
    pos: Pos
    kind: str = "class"


@dataclass
class LinkDecl:
    """``link NAME { from A to B; establish/reestablish/maintain "F"; compute M:C }``."""

    name: str
    fields: MappingNode  # LinkType fields written as clauses
    compute: FuncRef | None
    pos: Pos
    kind: str = "link"


@dataclass
class AnchoringDecl:
    """``anchoring every PERIOD [output LABEL]``: how the classes and links are run."""

    period: float
    period_pos: Pos
    output: str
    pos: Pos
    kind: str = "anchoring"
    name: str = "anchoring"


Decl = (
    SourceDecl
    | CUDecl
    | StreamDecl
    | StateDecl
    | ChangesDecl
    | MonitorDecl
    | ChronicleDecl
    | ClassDecl
    | LinkDecl
    | AnchoringDecl
    | UnsupportedDecl
)

_CLASS_FORMULAS = ("create", "add", "maintain", "codesignate")
_LINK_FORMULAS = ("establish", "reestablish", "maintain")


@dataclass
class Program:
    """A parsed KPL text: its declarations in source order, and the source text."""

    decls: list[Decl]
    text: str = ""


_DECL_KEYWORDS = (
    "source",
    "cu",
    "stream",
    "state",
    "changes",
    "monitor",
    "chronicle",
    "class",
    "link",
    "anchoring",
)
_STATE_STRATEGIES = ("latest", "closest", "interpolate")

# -- parser ---------------------------------------------------------------------------------


class _Parser:
    def __init__(self, toks: list[_Tok]) -> None:
        self.toks = toks
        self.i = 0
        self.errors: list[tuple[Pos, str]] = []

    @property
    def tok(self) -> _Tok:
        return self.toks[self.i]

    def take(self) -> _Tok:
        t = self.toks[self.i]
        if t.kind != "end":
            self.i += 1
        return t

    def at(self, text: str) -> bool:
        t = self.tok
        return t.kind in ("name", "op") and t.text == text

    def accept(self, text: str) -> bool:
        if self.at(text):
            self.i += 1
            return True
        return False

    def expect(self, text: str, what: str | None = None) -> _Tok:
        if not self.at(text):
            raise self.fail(f"expected {what or repr(text)}")
        return self.take()

    def fail(self, expected: str) -> _Fail:
        t = self.tok
        found = "end of file" if t.kind == "end" else repr(t.text)
        return _Fail(t.pos, f"{expected}, found {found}")

    def name(self, what: str) -> _Tok:
        if self.tok.kind != "name":
            raise self.fail(f"expected {what}")
        return self.take()

    def label(self, what: str = "a label") -> Ref:
        t = self.tok
        # A bare declaration keyword here is almost always a missing label: the next
        # declaration starts. Such a label can still be written "quoted".
        if t.kind == "name" and t.text not in _DECL_KEYWORDS:
            self.i += 1
            return Ref(t.text, t.pos)
        if t.kind == "str":
            self.i += 1
            return Ref(_unquote(t.text), t.pos)
        raise self.fail(f"expected {what}")

    def number(self, what: str) -> tuple[float, Pos]:
        pos = self.tok.pos
        sign = -1.0 if self.accept("-") else 1.0
        t = self.tok
        if t.kind == "num":
            self.i += 1
            if re.fullmatch(r"\d+", t.text):
                return int(sign) * int(t.text), pos
            return sign * float(t.text), pos
        if t.kind == "name" and t.text == "inf":
            self.i += 1
            return sign * math.inf, pos
        raise self.fail(f"expected {what}")

    def value(self) -> tuple[Any, Pos]:
        t = self.tok
        if (t.kind == "op" and t.text == "-") or t.kind == "num":
            return self.number("a number")
        if t.kind == "str":
            self.i += 1
            return _unquote(t.text), t.pos
        if t.kind == "name":
            self.i += 1
            consts = {"true": True, "false": False, "none": None, "inf": math.inf}
            if t.text in consts:
                return consts[t.text], t.pos
            if self.accept("("):  # absolute(0.5): a change spec written as in Python
                inner, _ = self.number("a number")
                self.expect(")")
                return f"{t.text}({inner:g})", t.pos
            return t.text, t.pos
        raise self.fail("expected a value")

    def mapping(self, labels: bool = False) -> MappingNode:
        start = self.expect("{").pos
        entries: list[Entry] = []
        seen: set[str] = set()
        while not self.at("}"):
            k = self.name("a key")
            self.expect(":")
            if labels:
                r = self.label()
                v, vpos = r.label, r.pos
            else:
                v, vpos = self.value()
            if k.text in seen:
                self.errors.append((k.pos, f"duplicate key {k.text!r}"))
            seen.add(k.text)
            entries.append(Entry(k.text, v, k.pos, vpos))
            if not self.accept(","):
                break
        self.expect("}", "',' or '}'")
        return MappingNode(entries, start)

    def program(self) -> list[Decl]:
        decls: list[Decl] = []
        while self.tok.kind != "end":
            t = self.tok
            if t.kind == "name" and t.text in _DECL_KEYWORDS:
                try:
                    decls.append(getattr(self, f"decl_{t.text}")())
                except _Fail as exc:
                    self.errors.append((exc.pos, exc.message))
                    self.sync()
            else:
                found = "end of file" if t.kind == "end" else repr(t.text)
                self.errors.append(
                    (t.pos, f"expected a declaration ({', '.join(_DECL_KEYWORDS)}), found {found}")
                )
                self.take()
                self.sync()
        return decls

    def sync(self) -> None:
        # Skip to the next declaration keyword at the start of a line, outside braces.
        depth = 0
        while self.tok.kind != "end":
            t = self.tok
            if t.kind == "name" and t.text in _DECL_KEYWORDS and depth <= 0:
                prev = self.toks[self.i - 1] if self.i else None
                if prev is None or prev.pos[0] < t.pos[0]:
                    return
            if t.kind == "op" and t.text == "{":
                depth += 1
            elif t.kind == "op" and t.text == "}":
                depth -= 1
            self.i += 1

    def decl_source(self) -> SourceDecl:
        pos = self.take().pos
        label = self.label()
        cache = self.mapping() if self.accept("cache") else None
        return SourceDecl(label.label, cache, pos)

    def decl_cu(self) -> CUDecl:
        pos = self.take().pos
        name = self.name("a unit name").text
        self.expect("=")
        mod = self.name("a module (module:callable)")
        self.expect(":", "':' between module and callable")
        attr = self.name("a callable name")
        args: MappingNode | None = None
        if self.at("("):
            apos = self.take().pos
            entries: list[Entry] = []
            while not self.at(")"):
                k = self.name("an argument name")
                self.expect("=")
                v, vpos = self.value()
                if any(e.key == k.text for e in entries):
                    self.errors.append((k.pos, f"duplicate argument {k.text!r}"))
                entries.append(Entry(k.text, v, k.pos, vpos))
                if not self.accept(","):
                    break
            self.expect(")", "',' or ')'")
            args = MappingNode(entries, apos)
        self.expect("inputs")
        inputs = [self.cu_input()]
        while self.accept(","):
            inputs.append(self.cu_input())
        self.expect("output", "',' or 'output'")
        out = self.label("the output label")
        return CUDecl(name, mod.text, attr.text, args, inputs, out, pos)

    def cu_input(self) -> InputNode:
        ref = self.label("an input label")
        return InputNode(ref, self.mapping() if self.accept("with") else None)

    def decl_stream(self) -> StreamDecl:
        pos = self.take().pos
        label = self.label()
        self.expect("=")
        src = self.label("the label it is derived from")
        policy = self.mapping() if self.accept("with") else None
        return StreamDecl(label.label, src, policy, pos)

    def decl_state(self) -> StateDecl:
        pos = self.take().pos
        label = self.label()
        self.expect("=")
        comps = self.mapping(labels=True)
        every = self.expect("every", "'every PERIOD'")
        period, ppos = self.number("a period in seconds")
        entries = [Entry("period", period, every.pos, ppos)]
        while True:
            t = self.tok
            if t.kind != "name" or t.text in _DECL_KEYWORDS:
                break
            self.i += 1
            if t.text in ("max_delay", "start", "end"):
                v, vpos = self.number(f"a number after {t.text!r}")
                entries.append(Entry(t.text, v, t.pos, vpos))
            elif t.text in ("missing", "strategy"):
                w = self.name(f"a value after {t.text!r}")
                entries.append(Entry(t.text, w.text, t.pos, w.pos))
            elif t.text in _STATE_STRATEGIES:
                entries.append(Entry("strategy", t.text, t.pos, t.pos))
            else:
                raise _Fail(
                    t.pos,
                    f"unknown state clause {t.text!r} (expected latest, closest, interpolate, "
                    "strategy, max_delay, missing, start, end)",
                )
        return StateDecl(label.label, comps, MappingNode(entries, every.pos), pos)

    def decl_changes(self) -> ChangesDecl:
        pos = self.take().pos
        src = self.label()
        change, cpos = "any_change", src.pos
        if self.accept("by"):
            v, cpos = self.value()
            change = str(v)
        return ChangesDecl(src, change, cpos, pos)

    def decl_monitor(self) -> MonitorDecl:
        pos = self.take().pos
        name = self.name("a monitor name").text
        self.expect("=")
        f = self.tok
        if f.kind != "str":
            raise self.fail('expected the formula as a "quoted string"')
        self.i += 1
        self.expect("every", "'every PERIOD'")
        period, _ = self.number("a period in seconds")
        max_delay: float | None = None
        comps: MappingNode | None = None
        output: str | None = None
        while True:
            if self.accept("max_delay"):
                max_delay, _ = self.number("a delay in seconds")
            elif self.accept("with"):
                comps = self.mapping(labels=True)
            elif self.accept("output"):
                output = self.label().label
            else:
                break
        return MonitorDecl(name, _unquote(f.text), f.pos, period, max_delay, comps, output, pos)

    def decl_chronicle(self) -> ChronicleDecl:
        pos = self.take().pos
        name = self.name("a chronicle name").text
        c = ChronicleDecl(name, [], [], [], {}, None, pos)
        self.expect("{")
        while not self.accept("}"):
            t = self.name("event, constraint, forbidden, input, output or '}'")
            if t.text == "event":
                n = self.name("an event name")
                self.expect("=")
                ev: dict[str, Any] = {"name": n.text, **self.event_pattern()}
                c.item_pos[f"events.{len(c.events)}"] = n.pos
                c.events.append(ev)
            elif t.text == "constraint":
                a = self.name("an event name")
                self.expect("->")
                b = self.name("an event name")
                lo, hi = self.interval()
                c.item_pos[f"constraints.{len(c.constraints)}"] = a.pos
                c.constraints.append({"start": a.text, "end": b.text, "lo": lo, "hi": hi})
            elif t.text == "forbidden":
                fb = self.event_pattern(kind_required=True)
                if self.accept("between"):
                    fb["start"] = self.name("an event name").text
                    self.expect("and")
                    fb["end"] = self.name("an event name").text
                else:
                    self.expect("after", "'between A and B' or 'after A in [LO, HI]'")
                    fb["start"] = self.name("an event name").text
                    fb["lo"], fb["hi"] = self.interval()
                c.item_pos[f"forbidden.{len(c.forbidden)}"] = t.pos
                c.forbidden.append(fb)
            elif t.text == "input":
                k = self.name("an event kind")
                self.expect("=")
                c.inputs[k.text] = self.label()
            elif t.text == "output":
                c.output = self.label().label
            else:
                raise _Fail(
                    t.pos,
                    f"unknown chronicle item {t.text!r} "
                    "(expected event, constraint, forbidden, input, output)",
                )
        return c

    def event_pattern(self, kind_required: bool = True) -> dict[str, Any]:
        kind = self.name("an event kind")
        out: dict[str, Any] = {"event": kind.text}
        if self.accept("("):
            args: list[str] = []
            while not self.at(")"):
                args.append(self.name("a parameter name").text)
                if not self.accept(","):
                    break
            self.expect(")", "',' or ')'")
            out["args"] = args
        if self.accept("from"):
            out["from"] = self.value()[0]
        if self.accept("to"):
            out["to"] = self.value()[0]
        return out

    def interval(self) -> tuple[float | None, float | None]:
        self.expect("in", "'in [LO, HI]'")
        self.expect("[")
        lo, _ = self.number("a lower bound in seconds (or -inf)")
        self.expect(",")
        hi, _ = self.number("an upper bound in seconds (or inf)")
        self.expect("]")
        return (None if lo == -math.inf else lo), (None if hi == math.inf else hi)

    def formula(self) -> tuple[str, Pos]:
        f = self.tok
        if f.kind != "str":
            raise self.fail('expected the formula as a "quoted string"')
        self.i += 1
        return _unquote(f.text), f.pos

    def funcref(self) -> FuncRef:
        mod = self.name("a module (module:callable)")
        self.expect(":", "':' between module and callable")
        attr = self.name("a callable name")
        return FuncRef(mod.text, attr.text, mod.pos)

    def _body_entry(self, entries: list[Entry], key: str, value: Any, kpos: Pos, vpos: Pos) -> None:
        if any(e.key == key for e in entries):
            self.errors.append((kpos, f"duplicate clause {key!r}"))
        entries.append(Entry(key, value, kpos, vpos))

    def decl_class(self) -> ClassDecl:
        pos = self.take().pos
        n = self.name("a class name")
        fields: list[Entry] = []
        feats: list[Entry] = []
        rels: dict[str, FuncRef] = {}
        self.expect("{")
        while not self.accept("}"):
            t = self.name(
                "base, prefix, feature, create, add, maintain, codesignate, relation or '}'"
            )
            if t.text in ("base", "prefix"):
                v = self.name(f"a name after {t.text!r}")
                self._body_entry(fields, t.text, v.text, t.pos, v.pos)
            elif t.text == "feature":
                f = self.name("a feature name")
                self.expect("=")
                pat = self.label("a label pattern")
                if any(e.key == f.text for e in feats):
                    self.errors.append((f.pos, f"duplicate feature {f.text!r}"))
                feats.append(Entry(f.text, pat.label, f.pos, pat.pos))
            elif t.text in _CLASS_FORMULAS:
                text, fpos = self.formula()
                self._body_entry(fields, t.text, text, t.pos, fpos)
                if t.text == "create" and self.at("from"):
                    fr = self.take()
                    src = self.label("the label percepts are read from")
                    self._body_entry(fields, "create_from", src.label, fr.pos, src.pos)
                if (
                    t.text == "codesignate"
                    and self.tok.kind == "name"
                    and self.tok.text
                    in (
                        "once",
                        "continuous",
                    )
                ):
                    m = self.take()
                    self._body_entry(fields, "codesignation", m.text, m.pos, m.pos)
            elif t.text == "relation":
                r = self.name("a relation name")
                self.expect("=")
                if r.text in rels:
                    self.errors.append((r.pos, f"duplicate relation {r.text!r}"))
                rels[r.text] = self.funcref()
            else:
                raise _Fail(
                    t.pos,
                    f"unknown class clause {t.text!r} (expected base, prefix, feature, create, "
                    "add, maintain, codesignate, relation)",
                )
        return ClassDecl(n.text, MappingNode(fields, pos), MappingNode(feats, pos), rels, pos)

    def decl_link(self) -> LinkDecl:
        pos = self.take().pos
        n = self.name("a link name")
        fields: list[Entry] = []
        compute: FuncRef | None = None
        self.expect("{")
        while not self.accept("}"):
            t = self.name("from, to, establish, reestablish, maintain, compute or '}'")
            if t.text in ("from", "to"):
                c = self.name(f"a class name after {t.text!r}")
                self._body_entry(fields, f"{t.text}_class", c.text, t.pos, c.pos)
            elif t.text in _LINK_FORMULAS:
                text, fpos = self.formula()
                self._body_entry(fields, t.text, text, t.pos, fpos)
            elif t.text == "compute":
                if compute is not None:
                    self.errors.append((t.pos, "duplicate clause 'compute'"))
                compute = self.funcref()
            else:
                raise _Fail(
                    t.pos,
                    f"unknown link clause {t.text!r} (expected from, to, establish, "
                    "reestablish, maintain, compute)",
                )
        return LinkDecl(n.text, MappingNode(fields, pos), compute, pos)

    def decl_anchoring(self) -> AnchoringDecl:
        pos = self.take().pos
        self.expect("every", "'every PERIOD'")
        period, ppos = self.number("a period in seconds")
        output = self.label().label if self.accept("output") else "events/anchoring"
        return AnchoringDecl(period, ppos, output, pos)


def _parse(text: str) -> tuple[Program, list[KPLError]]:
    toks, errors = _tokenize(text)
    p = _Parser(toks)
    decls = p.program()
    lines = text.splitlines()
    errors += [KPLError(pos[0], pos[1], msg, _excerpt(lines, *pos)) for pos, msg in p.errors]
    return Program(decls, text), errors


def parse(text: str) -> Program:
    """Parse a KPL text into a ``Program``; raises ``KPLCheckError`` on a syntax error."""
    prog, errors = _parse(text)
    if errors:
        raise KPLCheckError(_sorted(errors))
    return prog


def _sorted(errors: list[KPLError]) -> list[KPLError]:
    return sorted(errors, key=lambda e: (e.line, e.column))


# -- checking -------------------------------------------------------------------------------


def _provides(d: Decl) -> list[str]:
    if isinstance(d, SourceDecl | StreamDecl | StateDecl | ChangesDecl):
        return [d.label]
    if isinstance(d, CUDecl):
        return [d.output.label]
    if isinstance(d, MonitorDecl):
        return [d.label, f"{d.label}/state"]
    if isinstance(d, ChronicleDecl):
        return [d.label]
    if isinstance(d, AnchoringDecl):
        return [d.output]
    return []


def _monitor_refs(d: MonitorDecl) -> list[Ref]:
    comps = d.components.as_dict() if d.components else {}
    where = {e.key: e.value_pos for e in d.components.entries} if d.components else {}
    try:
        keys = state_keys(parse_formula(d.formula))
    except MTLSyntaxError:
        return []
    return [Ref(comps.get(k, k), where.get(k, d.formula_pos)) for k in keys]


def _needs(d: Decl) -> list[Ref]:
    if isinstance(d, CUDecl):
        return [i.ref for i in d.inputs]
    if isinstance(d, StreamDecl | ChangesDecl):
        return [d.source]
    if isinstance(d, StateDecl):
        return [Ref(e.value, e.value_pos) for e in d.components.entries]
    if isinstance(d, MonitorDecl):
        return _monitor_refs(d)
    if isinstance(d, ChronicleDecl):
        return list(d.inputs.values())
    if isinstance(d, ClassDecl):
        return [Ref(e.value, e.value_pos) for e in d.fields.entries if e.key == "create_from"]
    return []


def _pattern(label: str) -> re.Pattern[str] | None:
    # A chronicle input "car/{car}/behind" reads every label matching it.
    if "{" not in label:
        return None
    parts = re.split(r"\{[A-Za-z_][A-Za-z0-9_]*\}", label)
    return re.compile("[^/]+".join(re.escape(p) for p in parts) + r"\Z")


def _decl_name(d: Decl) -> str:
    return (
        d.name
        if isinstance(
            d,
            CUDecl
            | MonitorDecl
            | ChronicleDecl
            | ClassDecl
            | LinkDecl
            | AnchoringDecl
            | UnsupportedDecl,
        )
        else (d.label)
    )


class _Checker:
    def __init__(self, prog: Program, known: Iterable[str], resolve: bool) -> None:
        self.resolve = resolve
        self.prog = prog
        self.known = set(known)
        self.errors: list[tuple[Pos, str]] = []

    def err(self, pos: Pos, msg: str) -> None:
        self.errors.append((pos, msg))

    def policy(self, node: MappingNode | None, model: type[Any], what: str) -> None:
        if node is None:
            return
        fields = model.model_fields
        ok = True
        for e in node.entries:
            if e.key not in fields:
                self.err(
                    e.key_pos,
                    f"unknown {what} field {e.key!r} (known: {', '.join(fields)})",
                )
                ok = False
        if not ok:
            return
        try:
            model(**node.as_dict())
        except PolicyError as exc:
            top = exc.field.split(".")[0]
            self.err(node.where(top), f"{what} field {exc.field!r}: {exc.reason}")

    def run(self) -> None:
        seen: dict[tuple[str, str], Pos] = {}
        providers: dict[str, Pos] = {}
        for d in self.prog.decls:
            group = "process" if isinstance(d, CUDecl | MonitorDecl | ChronicleDecl) else d.kind
            key = (group, _decl_name(d))
            dup = key in seen and not isinstance(d, SourceDecl | StreamDecl | StateDecl)
            if dup:
                self.err(d.pos, f"duplicate {d.kind} {key[1]!r} (first declared at line "
                         f"{seen[key][0]})")  # fmt: skip
            seen.setdefault(key, d.pos)
            for lab in [] if dup else _provides(d):
                if lab in providers:
                    self.err(d.pos, f"label {lab!r} is declared twice (first at line "
                             f"{providers[lab][0]})")  # fmt: skip
                elif lab in self.known:
                    self.err(d.pos, f"label {lab!r} exists already on the instance")
                providers.setdefault(lab, d.pos)
            self.decl(d)
        self.anchoring()
        if not self.resolve:
            return
        avail = set(providers) | self.known
        for d in self.prog.decls:
            for ref in _needs(d):
                pat = _pattern(ref.label)
                if pat is not None:
                    if not any(pat.match(lab) for lab in avail):
                        self.err(ref.pos, f"no declared or existing label matches {ref.label!r}")
                elif ref.label not in avail:
                    self.err(ref.pos, f"unknown label {ref.label!r}: no declaration provides it")
        self.cycles()

    def decl(self, d: Decl) -> None:
        if isinstance(d, SourceDecl):
            self.policy(d.cache, CacheSpec, "cache")
        elif isinstance(d, CUDecl):
            for i in d.inputs:
                self.policy(i.policy, Policy, "policy")
        elif isinstance(d, StreamDecl):
            self.policy(d.policy, Policy, "policy")
        elif isinstance(d, StateDecl):
            self.policy(d.policy, StatePolicy, "state policy")
            if not d.components.entries:
                self.err(d.components.pos, "a state needs at least one component")
        elif isinstance(d, ChangesDecl):
            try:
                Change.parse(d.change)
            except PolicyError as exc:
                self.err(d.change_pos, f"change: {exc.reason}")
            except ValueError as exc:  # pragma: no cover - Change.parse wraps pydantic's
                self.err(d.change_pos, f"change: {exc}")
        elif isinstance(d, MonitorDecl):
            self.monitor(d)
        elif isinstance(d, ChronicleDecl):
            self.chronicle(d)
        elif isinstance(d, ClassDecl):
            self.model(d, ObjectClass, _CLASS_FORMULAS)
        elif isinstance(d, LinkDecl):
            self.model(d, LinkType, _LINK_FORMULAS)

    def formula(self, text: str, where: Pos, what: str = "formula") -> set[str] | None:
        try:
            return set(state_keys(parse_formula(text)))
        except MTLSyntaxError as exc:
            # The formula sits in a one-line string: its column 1 is just after the quote.
            line, col = where
            pos = (line, col + exc.column) if exc.line == 1 else (line + exc.line - 1, exc.column)
            self.err(pos, f"{what}: {exc.message}")
            return None

    def model(self, d: ClassDecl | LinkDecl, model: type[Any], formulas: tuple[str, ...]) -> None:
        ok = True
        for e in d.fields.entries:
            if e.key in formulas and self.formula(e.value, e.value_pos, e.key) is None:
                ok = False
        if not ok:
            return
        data: dict[str, Any] = {"name": d.name, **d.fields.as_dict()}
        if isinstance(d, ClassDecl):
            data["features"] = d.features.as_dict()
            data["relations"] = {k: _identity for k in d.relations}
        elif d.compute is not None:
            data["compute"] = _identity
        try:
            model(**data)
        except PolicyError as exc:
            top, _, rest = exc.field.partition(".")
            if top == "features" and rest and isinstance(d, ClassDecl):
                pos = d.features.where(rest)
            elif top in ("relations", "compute"):
                ref = d.relations.get(rest) if isinstance(d, ClassDecl) else d.compute
                pos = ref.pos if ref is not None else d.pos
            else:
                # create_from is written in the create clause; a missing one points there too
                written = {e.key for e in d.fields.entries}
                pos = d.fields.where(
                    top if top in written else {"create_from": "create"}.get(top, top)
                )
            self.err(pos, f"{d.kind} {d.name!r}: {exc.field}: {exc.reason}")

    def anchoring(self) -> None:
        classes: dict[str, ClassDecl] = {}
        for d in self.prog.decls:
            if isinstance(d, ClassDecl):
                base = next((e for e in d.fields.entries if e.key == "base"), None)
                if base is not None and base.value != d.name and base.value not in classes:
                    later = any(
                        isinstance(o, ClassDecl) and o.name == base.value for o in self.prog.decls
                    )
                    why = "must be declared before it" if later else "is not declared"
                    self.err(base.value_pos, f"base class {base.value!r} {why}")
                classes.setdefault(d.name, d)
            elif isinstance(d, LinkDecl):
                for e in d.fields.entries:
                    if e.key in ("from_class", "to_class") and not any(
                        isinstance(o, ClassDecl) and o.name == e.value for o in self.prog.decls
                    ):
                        self.err(e.value_pos, f"unknown class {e.value!r}")
            elif isinstance(d, AnchoringDecl):
                try:
                    check_duration("period", d.period, minimum=1e-6)
                except ValueError as exc:
                    self.err(d.period_pos, f"anchoring period: {exc}")
        if not classes:
            for d in self.prog.decls:
                if isinstance(d, LinkDecl | AnchoringDecl):
                    what = "anchoring" if isinstance(d, AnchoringDecl) else f"link {d.name!r}"
                    self.err(d.pos, f"{what} needs at least one class declaration")
        elif "events/anchoring" in self.known and not any(
            isinstance(d, AnchoringDecl) for d in self.prog.decls
        ):
            self.err(
                next(iter(classes.values())).pos,
                "label 'events/anchoring' exists already on the instance "
                "(give another with 'anchoring every P output LABEL')",
            )

    def monitor(self, d: MonitorDecl) -> None:
        keys = self.formula(d.formula, d.formula_pos)
        if keys is None:
            return
        if not keys:
            self.err(d.formula_pos, "formula reads no feature")
        for e in d.components.entries if d.components else []:
            if e.key not in keys:
                self.err(e.key_pos, f"formula reads no feature {e.key!r}")
        try:
            StatePolicy(period=d.period, max_delay=d.max_delay)
        except PolicyError as exc:
            self.err(d.pos, f"monitor {exc.field}: {exc.reason}")

    def chronicle(self, d: ChronicleDecl) -> None:
        try:
            compiled = compile_chronicle(d.spec())
        except ChronicleError as exc:
            m = re.match(r"(events|constraints|forbidden)\.(\d+)", exc.field)
            pos = d.item_pos.get(m.group(0), d.pos) if m else d.pos
            self.err(pos, f"chronicle {d.name!r}: {exc.field}: {exc.reason}")
            return
        for kind in sorted(compiled.kinds - set(d.inputs)):
            self.err(d.pos, f"chronicle {d.name!r}: no 'input {kind} = LABEL' for event {kind!r}")

    def cycles(self) -> None:
        try:
            _order(self.prog.decls, self.known)
        except _Fail as exc:
            self.err(exc.pos, exc.message)


def _order(decls: list[Decl], known: set[str]) -> list[Decl]:
    """The declarations in dependency order (providers first); a cycle is a _Fail."""
    by_label: dict[str, int] = {}
    for n, d in enumerate(decls):
        for lab in _provides(d):
            by_label.setdefault(lab, n)
    deps: list[set[int]] = []
    for d in decls:
        s: set[int] = set()
        for ref in _needs(d):
            pat = _pattern(ref.label)
            if pat is None:
                if ref.label in by_label and ref.label not in known:
                    s.add(by_label[ref.label])
            else:
                s.update(n for lab, n in by_label.items() if pat.match(lab))
        deps.append(s)
    done: list[int] = []
    state = [0] * len(decls)  # 0 new, 1 in progress, 2 done

    def visit(n: int) -> None:
        if state[n] == 2:
            return
        if state[n] == 1:
            raise _Fail(decls[n].pos, f"{decls[n].kind} {_decl_name(decls[n])!r} depends on itself")
        state[n] = 1
        for m in sorted(deps[n]):
            visit(m)
        state[n] = 2
        done.append(n)

    for n in range(len(decls)):
        visit(n)
    return [decls[n] for n in done]


def check(text: str, known_labels: Iterable[str] = ()) -> list[KPLError]:
    """Every problem in a KPL text (syntax, policies, labels, formulas, chronicles), in order.

    ``known_labels`` are streams that exist already (an instance's labels) and may be
    referenced without being declared. CU callables are not imported here.
    """
    prog, errors = _parse(text)
    # A declaration dropped by a syntax error may provide labels others use: resolving
    # references then would only add noise.
    return _sorted(errors + _check_program(prog, known_labels, resolve=not errors))


def _check_program(
    prog: Program, known_labels: Iterable[str], *, resolve: bool = True
) -> list[KPLError]:
    c = _Checker(prog, known_labels, resolve)
    c.run()
    lines = prog.text.splitlines()
    return [KPLError(p[0], p[1], m, _excerpt(lines, *p)) for p, m in c.errors]


# -- setup ----------------------------------------------------------------------------------


def resolve_callable(module: str, attr: str) -> Callable[..., Any]:
    """Import ``module`` and fetch ``attr`` (dotted for nested attributes)."""
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    if not callable(obj):
        raise TypeError(f"{module}:{attr} is not callable")
    return obj


def _identity(value: Any) -> Any:
    return value


@dataclass
class KPLApplication:
    """What ``setup`` created on an instance: process names in creation order, and notes."""

    instance: DyKnowInstance
    program: Program
    processes: list[str] = field(default_factory=list)
    unsupported: list[str] = field(default_factory=list)

    def remove(self) -> None:
        """Remove every process this application created, newest first."""
        for name in reversed(self.processes):
            if name in self.instance.processes:
                self.instance.remove_process(name)
        self.processes.clear()


def setup(instance: DyKnowInstance, source: str | Program) -> KPLApplication:
    """Check a KPL text (or parsed program) against ``instance`` and create its declarations.

    Raises ``KPLCheckError`` with every problem if it does not check (nothing is
    created), or ``KPLSetupError`` naming the declaration that failed at creation (a CU
    callable that does not import, a factory that raises); what was created is removed.
    """
    if isinstance(source, Program):
        prog = source
        errors = _check_program(prog, instance.labels())
    else:
        prog, errors = _parse(source)
        errors += _check_program(prog, instance.labels()) if not errors else []
    if errors:
        raise KPLCheckError(_sorted(errors))
    app = KPLApplication(instance, prog)
    anchoring = [d for d in prog.decls if isinstance(d, ClassDecl | LinkDecl | AnchoringDecl)]
    d: Decl | None = None
    try:
        for d in _order(prog.decls, set(instance.labels())):
            if not isinstance(d, ClassDecl | LinkDecl | AnchoringDecl):
                _create(app, d)
        if anchoring:
            d = anchoring[0]
            _create_anchoring(app, anchoring)
    except Exception as exc:
        app.remove()
        if isinstance(exc, KPLSetupError):
            raise
        pos = d.pos if d is not None else (1, 1)
        what = f"{d.kind} {_decl_name(d)!r}" if d is not None else "setup"
        raise KPLSetupError(pos, f"{what}: {exc}") from exc
    return app


def _resolve(ref: FuncRef, what: str) -> Callable[..., Any]:
    try:
        return resolve_callable(ref.module, ref.attr)
    except Exception as exc:
        raise KPLSetupError(
            ref.pos, f"{what}: {ref.module}:{ref.attr}: {type(exc).__name__}: {exc}"
        ) from exc


def _create_anchoring(
    app: KPLApplication, decls: list[ClassDecl | LinkDecl | AnchoringDecl]
) -> None:
    classes: list[ObjectClass] = []
    links: list[LinkType] = []
    period, output = 1.0, "events/anchoring"
    for d in decls:
        if isinstance(d, ClassDecl):
            rels = {
                k: _resolve(r, f"class {d.name!r} relation {k!r}") for k, r in d.relations.items()
            }
            classes.append(
                ObjectClass(
                    name=d.name,
                    features=d.features.as_dict(),
                    relations=rels,
                    **d.fields.as_dict(),
                )
            )
        elif isinstance(d, LinkDecl):
            compute = _resolve(d.compute, f"link {d.name!r} compute") if d.compute else None
            links.append(LinkType(name=d.name, compute=compute, **d.fields.as_dict()))
        else:
            period, output = d.period, d.output
    proc = add_anchoring(app.instance, classes, links, period=period, output=output)
    app.processes.append(proc.name)


def _create(app: KPLApplication, d: Decl) -> None:
    inst = app.instance
    if isinstance(d, SourceDecl):
        cache = CacheSpec(**d.cache.as_dict()) if d.cache else None
        app.processes.append(inst.add_source(d.label, cache=cache).name)
    elif isinstance(d, CUDecl):
        try:
            target = resolve_callable(d.module, d.attr)
            fn = target(**d.args.as_dict()) if d.args is not None else target
        except Exception as exc:
            raise KPLSetupError(
                d.pos, f"cu {d.name!r}: {d.module}:{d.attr}: {type(exc).__name__}: {exc}"
            ) from exc
        inputs = [
            Input(i.ref.label, Policy(**i.policy.as_dict()) if i.policy else Policy())
            for i in d.inputs
        ]
        app.processes.append(inst.add_cu(d.name, fn, inputs, d.output.label).name)
    elif isinstance(d, StreamDecl):
        policy = Policy(**d.policy.as_dict()) if d.policy else Policy()
        name = f"stream:{d.label}"
        app.processes.append(
            inst.add_cu(name, _identity, [Input(d.source.label, policy)], d.label).name
        )
    elif isinstance(d, StateDecl):
        comps = {e.key: e.value for e in d.components.entries}
        proc = inst.add_state(d.label, comps, StatePolicy(**d.policy.as_dict()))
        app.processes.append(proc.name)
    elif isinstance(d, ChangesDecl):
        ev = inst.add_change_events(d.source.label, d.change, name=f"changes:{d.source.label}")
        app.processes.append(ev.name)
    elif isinstance(d, MonitorDecl):
        mon = inst.add_monitor(
            d.formula,
            label=d.label,
            components=d.components.as_dict() if d.components else None,
            period=d.period,
            max_delay=d.max_delay,
            name=f"monitor:{d.name}",
        )
        app.processes.append(mon.name)
    elif isinstance(d, ChronicleDecl):
        chron = inst.add_chronicle(
            d.spec(),
            {k: r.label for k, r in d.inputs.items()},
            output=d.label,
            name=f"chronicle:{d.name}",
        )
        app.processes.append(chron.name)
    else:
        msg = f"line {d.pos[0]}: {d.kind} {d.name!r} is not yet supported at setup (ignored)"
        app.unsupported.append(msg)
        log.warning("KPL: %s", msg)


__all__ = [
    "AnchoringDecl",
    "CUDecl",
    "ChangesDecl",
    "ChronicleDecl",
    "ClassDecl",
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
    "resolve_callable",
    "setup",
]
