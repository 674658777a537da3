"""KPL text to AST: errors, tokens, the declaration classes and the parser."""

from __future__ import annotations

import bisect
import difflib
import logging
import math
import re
from dataclasses import dataclass, field
from typing import Any

from .._exceptions import DyKnowError

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

_UNIT = re.compile(r"[A-Za-z_][A-Za-z0-9_./]*")  # right after a number: `1s`, `300ms`


@dataclass(frozen=True)
class _Tok:
    kind: str  # name, num, str, op, end
    text: str
    pos: Pos


def _unquote(s: str) -> str:
    return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), s[1:-1])


def _tokenize(text: str) -> tuple[list[_Tok], list[KPLError], list[tuple[Pos, bool]]]:
    """The tokens, the lexical errors, and where text was dropped (a bad string, character).

    Each drop is its position and whether it ran to its line's end (an unterminated string).
    """
    toks: list[_Tok] = []
    errs: list[tuple[Pos, str]] = []
    dropped: list[tuple[Pos, bool]] = []
    line, line_start, i = 1, 0, 0
    while i < len(text):
        m = _TOKEN.match(text, i)
        pos = (line, i - line_start + 1)
        if m is None:
            ch = text[i]
            msg = "unterminated string" if ch == '"' else f"unexpected character {ch!r}"
            errs.append((pos, msg))
            dropped.append((pos, ch == '"'))
            i = text.find("\n", i) if ch == '"' else i + 1
            if i < 0:
                i = len(text)
            continue
        kind = m.lastgroup or "ws"
        if kind != "ws":
            toks.append(_Tok(kind, m.group(), pos))
        unit = _UNIT.match(text, m.end()) if kind == "num" else None
        if unit is not None:
            # `every 1s`, `max_delay: 0.3s`: report the unit, keep the number, parse on
            written = m.group() + unit.group()
            errs.append((pos, f"'{written}': a number takes no unit (durations are in seconds)"))
            i = unit.end()
            continue
        nl = m.group().count("\n")
        if nl:
            line += nl
            line_start = m.start() + m.group().rfind("\n") + 1
        i = m.end()
    toks.append(_Tok("end", "", (line, i - line_start + 1)))
    lines = text.splitlines()
    return toks, [KPLError(p[0], p[1], msg, _excerpt(lines, *p)) for p, msg in errs], dropped


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
    def __init__(self, toks: list[_Tok], dropped: list[tuple[Pos, bool]]) -> None:
        self.toks = toks
        self.dropped = dropped  # where the tokenizer dropped text, said already
        self.starts = [t.pos for t in toks]
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
            if self._glued("-"):
                # `wind-speed`, a vocabulary's usual spelling, is no bare label: say so
                # rather than fail at the '-' as if a declaration were missing
                word = t.text
                while self._glued("-", "name", "num"):
                    word += self.tok.text
                    self.i += 1
                raise _Fail(
                    t.pos,
                    f"label {word!r} must be quoted: a bare label is letters, digits, '_', "
                    f"'.' and '/' (write \"{word}\")",
                )
            return Ref(t.text, t.pos)
        if t.kind == "str":
            self.i += 1
            return Ref(_unquote(t.text), t.pos)
        raise self.fail(f"expected {what}")

    def _echo(self, start: Pos, at: Pos) -> bool:
        """Whether a failure at ``at``, in a declaration from ``start``, repeats a lexical error."""
        k = bisect.bisect_left(self.starts, at)
        before = self.starts[k - 1] if k else (0, 0)  # the token before the failing one
        # an unterminated string took the rest of its line: whatever its declaration then
        # lacks is its echo; a stray character took only itself, so only the token right
        # after it (`a$b`: 'b') can be its echo, a later failure is an error of its own
        return any(start <= d <= at and (line_end or before < d) for d, line_end in self.dropped)

    def _glued(self, *kinds: str) -> bool:
        """Whether the next token touches the previous one (no space) and is one of ``kinds``.

        A kind is a token kind, or an operator's text.
        """
        prev, t = self.toks[self.i - 1], self.tok
        if t.kind == "end" or t.pos != (prev.pos[0], prev.pos[1] + len(prev.text)):
            return False
        return t.kind in kinds or (t.kind == "op" and t.text in kinds)

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
        start: Pos = (0, 0)  # where the last declaration started
        while self.tok.kind != "end":
            t = self.tok
            if t.kind == "name" and t.text in _DECL_KEYWORDS:
                start = t.pos
                try:
                    decls.append(getattr(self, f"decl_{t.text}")())
                except _Fail as exc:
                    if not self._echo(t.pos, exc.pos):
                        self.errors.append((exc.pos, exc.message))
                    self.sync()
            else:
                found = "end of file" if t.kind == "end" else repr(t.text)
                # `a$b`: 'b'; `stream b = "abc` then `with {…}` on the next line: 'with'
                # taken as its label, then '{': echoes of the drop
                if not self._echo(start, t.pos):
                    self.errors.append(
                        (
                            t.pos,
                            f"expected a declaration ({', '.join(_DECL_KEYWORDS)}), found {found}",
                        )
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
                # a misspelt declaration after a state reads as one of its clauses
                near = difflib.get_close_matches(t.text, _DECL_KEYWORDS, n=1, cutoff=0.75)
                hint = f"; or a misspelt declaration keyword, {near[0]!r}?" if near else ""
                raise _Fail(
                    t.pos,
                    f"unknown state clause {t.text!r} (expected latest, closest, interpolate, "
                    f"strategy, max_delay, missing, start, end){hint}",
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
    toks, errors, dropped = _tokenize(text)
    p = _Parser(toks, dropped)
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
