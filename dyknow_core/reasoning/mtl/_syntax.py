"""MTL formulas: the AST, its text form, the parser and what a formula reads."""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import ClassVar, NamedTuple, TypeAlias

from ..._exceptions import DyKnowError

INF = math.inf

# -- AST ----------------------------------------------------------------------------------

Const: TypeAlias = float | int | str | bool


@dataclass(frozen=True, slots=True)
class BoolConst:
    """The constant ``true`` or ``false``."""

    value: bool

    def __str__(self) -> str:
        return "true" if self.value else "false"


@dataclass(frozen=True, slots=True)
class Var:
    """A quantified variable used as a feature argument."""

    name: str

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True, slots=True)
class Feature:
    """A feature, possibly parameterized: ``speed`` or ``speed(x)``; args are Vars or constants."""

    name: str
    args: tuple[Var | Const, ...] = ()

    def __str__(self) -> str:
        if not self.args:
            return self.name
        return f"{self.name}({', '.join(_fmt_arg(a) for a in self.args)})"


@dataclass(frozen=True, slots=True)
class Compare:
    """``left OP right`` where each side is a Feature or a constant."""

    op: str
    left: Feature | Const
    right: Feature | Const

    def __str__(self) -> str:
        return f"{_fmt_arg(self.left)} {self.op} {_fmt_arg(self.right)}"


@dataclass(frozen=True, slots=True)
class Not:
    """Negation."""

    operand: Formula

    def __str__(self) -> str:
        return f"not {_paren(self.operand)}"


@dataclass(frozen=True, slots=True)
class _Binary:
    """A binary connective; the subclass names its ``word``."""

    word: ClassVar[str]
    left: Formula
    right: Formula

    def __str__(self) -> str:
        return f"{_paren(self.left)} {self.word} {_paren(self.right)}"


@dataclass(frozen=True, slots=True)
class And(_Binary):
    """Conjunction."""

    word = "and"


@dataclass(frozen=True, slots=True)
class Or(_Binary):
    """Disjunction."""

    word = "or"


@dataclass(frozen=True, slots=True)
class Implies(_Binary):
    """Implication ``left -> right``."""

    word = "->"


@dataclass(frozen=True, slots=True)
class _Bounded:
    """A unary temporal operator over ``[lo, hi]`` (seconds); the subclass names its ``word``."""

    word: ClassVar[str]
    lo: float
    hi: float
    operand: Formula

    def __str__(self) -> str:
        return f"{self.word}{_fmt_iv(self.lo, self.hi)} {_paren(self.operand)}"


@dataclass(frozen=True, slots=True)
class Always(_Bounded):
    """``always[lo,hi] operand``."""

    word = "always"


@dataclass(frozen=True, slots=True)
class Eventually(_Bounded):
    """``eventually[lo,hi] operand``."""

    word = "eventually"


@dataclass(frozen=True, slots=True)
class Until:
    """``left until[lo,hi] right``."""

    lo: float
    hi: float
    left: Formula
    right: Formula

    def __str__(self) -> str:
        return f"{_paren(self.left)} until{_fmt_iv(self.lo, self.hi)} {_paren(self.right)}"


@dataclass(frozen=True, slots=True)
class Quantifier:
    """``forall var in domain: body`` (``universal``) or ``exists var in domain: body``."""

    universal: bool
    var: str
    domain: str
    body: Formula

    def __str__(self) -> str:
        q = "forall" if self.universal else "exists"
        return f"{q} {self.var} in {self.domain}: {self.body}"


Formula: TypeAlias = (
    BoolConst | Feature | Compare | Not | And | Or | Implies | Always | Eventually | Until
) | Quantifier


def _fmt_arg(a: object) -> str:
    if isinstance(a, bool):
        return "true" if a else "false"
    if isinstance(a, str):
        return '"' + a.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return str(a)


def _fmt_num(x: float) -> str:
    return "inf" if x == INF else f"{x:g}"


def _fmt_iv(lo: float, hi: float) -> str:
    if lo == 0 and hi == INF:
        return ""
    return f"[{_fmt_num(lo)},{_fmt_num(hi)}]"


def _paren(f: Formula) -> str:
    if isinstance(f, BoolConst | Feature | Compare):
        return str(f)
    return f"({f})"


# -- parser -------------------------------------------------------------------------------


class MTLSyntaxError(DyKnowError, ValueError):
    """A formula that does not parse; ``line`` and ``column`` (1-based) say where."""

    def __init__(self, message: str, line: int, column: int) -> None:
        super().__init__(f"{message} at line {line}, column {column}")
        self.message = message
        self.line = line
        self.column = column


_TOKEN = re.compile(
    r"""(?P<ws>[ \t\r\n]+)
      | (?P<num>(?:\d+\.\d*|\.\d+|\d+)(?:[eE][+-]?\d+)?)
      | (?P<str>"(?:[^"\\\n]|\\.)*"|'(?:[^'\\\n]|\\.)*')
      | (?P<name>[A-Za-z_][A-Za-z0-9_./]*)
      | (?P<op>->|<=|>=|==|!=|<|>|\(|\)|\[|\]|,|:|-)
    """,
    re.VERBOSE,
)
_KEYWORDS = {
    "always", "eventually", "until", "not", "and", "or", "forall", "exists", "in",
    "true", "false", "inf", "implies",
}  # fmt: skip
_COMPARISONS = {"<", "<=", ">", ">=", "==", "!="}
MAX_DEPTH = 64
"""Levels a formula may nest (operators, parentheses, chained ``and``/``or``): the parser
and every walk over a formula recurse, and Python's stack is 1000 frames deep."""


class _Tok(NamedTuple):
    kind: str  # "num", "str", "name", "kw", "op", "end"
    text: str
    pos: int


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.toks = self._lex(text)
        self.i = 0
        self.bound: list[str] = []
        self.depth = 0  # nesting levels entered (`MAX_DEPTH`)

    def where(self, pos: int) -> tuple[int, int]:
        line = self.text.count("\n", 0, pos) + 1
        col = pos - (self.text.rfind("\n", 0, pos) + 1) + 1
        return line, col

    def error(self, message: str, pos: int) -> MTLSyntaxError:
        return MTLSyntaxError(message, *self.where(pos))

    def _lex(self, text: str) -> list[_Tok]:
        toks: list[_Tok] = []
        pos = 0
        while pos < len(text):
            m = _TOKEN.match(text, pos)
            if m is None:
                raise self.error(f"unexpected character {text[pos]!r}", pos)
            kind = m.lastgroup or ""
            if kind != "ws":
                s = m.group()
                if kind == "name" and s in _KEYWORDS:
                    kind = "kw"
                toks.append(_Tok(kind, s, pos))
            pos = m.end()
        toks.append(_Tok("end", "", len(text)))
        return toks

    @property
    def tok(self) -> _Tok:
        return self.toks[self.i]

    def take(self) -> _Tok:
        t = self.toks[self.i]
        self.i += 1
        return t

    def accept(self, text: str) -> bool:
        t = self.tok
        if t.kind in ("kw", "op") and t.text == text:
            self.i += 1
            return True
        return False

    def expect(self, text: str) -> _Tok:
        t = self.tok
        if t.kind in ("kw", "op") and t.text == text:
            self.i += 1
            return t
        raise self.error(f"expected {text!r}, found {_describe(t)}", t.pos)

    def nest(self) -> None:
        """One level deeper, or MTLSyntaxError past `MAX_DEPTH` (the caller restores depth)."""
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.error(f"nested deeper than {MAX_DEPTH} levels", self.tok.pos)

    def parse(self) -> Formula:
        f = self.formula()
        t = self.tok
        if t.kind != "end":
            raise self.error(f"unexpected {_describe(t)}", t.pos)
        return f

    def formula(self) -> Formula:
        depth = self.depth
        self.nest()
        try:
            return self._formula()
        finally:
            self.depth = depth

    def _formula(self) -> Formula:
        t = self.tok
        if t.kind == "kw" and t.text in ("forall", "exists"):
            self.i += 1
            v = self.take()
            if v.kind != "name":
                raise self.error(f"expected a variable name, found {_describe(v)}", v.pos)
            self.expect("in")
            d = self.take()
            if d.kind != "name":
                raise self.error(f"expected a domain name, found {_describe(d)}", d.pos)
            self.expect(":")
            self.bound.append(v.text)
            try:
                body = self.formula()
            finally:
                self.bound.pop()
            return Quantifier(t.text == "forall", v.text, d.text, body)
        return self.implication()

    def implication(self) -> Formula:
        left = self.disjunction()
        if self.accept("->") or self.accept("implies"):
            return Implies(left, self.formula())
        return left

    def disjunction(self) -> Formula:
        depth = self.depth
        f = self.conjunction()
        while self.accept("or"):
            self.nest()  # a chain nests as deep as it is long: Or(Or(a, b), c)
            f = Or(f, self.conjunction())
        self.depth = depth
        return f

    def conjunction(self) -> Formula:
        depth = self.depth
        f = self.until()
        while self.accept("and"):
            self.nest()
            f = And(f, self.until())
        self.depth = depth
        return f

    def until(self) -> Formula:
        left = self.unary()
        if self.accept("until"):
            lo, hi = self.interval()
            depth = self.depth
            self.nest()
            right = self.until()
            self.depth = depth
            return Until(lo, hi, left, right)
        return left

    def unary(self) -> Formula:
        t = self.tok
        if t.kind == "kw":
            if t.text == "not":
                self.i += 1
                depth = self.depth
                self.nest()
                operand = self.unary()
                self.depth = depth
                return Not(operand)
            if t.text in ("always", "eventually"):
                self.i += 1
                lo, hi = self.interval()
                depth = self.depth
                self.nest()
                body = self.unary()
                self.depth = depth
                return Always(lo, hi, body) if t.text == "always" else Eventually(lo, hi, body)
            if t.text in ("forall", "exists"):
                return self.formula()
        return self.atom()

    def interval(self) -> tuple[float, float]:
        if not self.accept("["):
            return 0.0, INF
        start = self.tok.pos
        lo = self.bound_value()
        self.expect(",")
        hi = self.bound_value()
        self.expect("]")
        if lo > hi:
            raise self.error(f"empty interval [{_fmt_num(lo)}, {_fmt_num(hi)}]", start)
        return lo, hi

    def bound_value(self) -> float:
        t = self.take()
        if t.kind == "num":
            return float(t.text)
        if t.kind == "kw" and t.text == "inf":
            return INF
        raise self.error(f"expected a non-negative number of seconds, found {_describe(t)}", t.pos)

    def atom(self) -> Formula:
        t = self.tok
        if self.accept("("):
            f = self.formula()
            self.expect(")")
            return f
        if t.kind == "kw" and t.text in ("true", "false"):
            self.i += 1
            if self.tok.kind == "op" and self.tok.text in _COMPARISONS:
                return self.comparison(t.text == "true")
            return BoolConst(t.text == "true")
        if t.kind in ("num", "str") or (t.kind == "op" and t.text == "-"):
            return self.comparison(self.constant())
        if t.kind == "name":
            feat = self.feature()
            if self.tok.kind == "op" and self.tok.text == "[":
                # `eventualy[0,5] p`: a misspelt operator reads as a feature
                close = difflib.get_close_matches(t.text, ("always", "eventually"), n=1)
                hint = f": did you mean {close[0]!r}?" if close else ""
                raise self.error(
                    f"{t.text!r} is not an operator (an interval follows always, eventually"
                    f" or until){hint}",
                    t.pos,
                )
            if self.tok.kind == "op" and self.tok.text in _COMPARISONS:
                return self.comparison(feat)
            return feat
        raise self.error(f"expected a formula, found {_describe(t)}", t.pos)

    def comparison(self, left: Feature | Const) -> Formula:
        op = self.take()
        if op.kind != "op" or op.text not in _COMPARISONS:
            raise self.error(f"expected a comparison, found {_describe(op)}", op.pos)
        right = self.operand()
        if not isinstance(left, Feature) and not isinstance(right, Feature):
            raise self.error("a comparison needs a feature on one side", op.pos)
        return Compare(op.text, left, right)

    def operand(self) -> Feature | Const:
        t = self.tok
        if t.kind == "name":
            return self.feature()
        return self.constant()

    def constant(self) -> Const:
        t = self.take()
        if t.kind == "op" and t.text == "-":
            n = self.take()
            if n.kind != "num":
                raise self.error(f"expected a number after '-', found {_describe(n)}", n.pos)
            return -_number(n.text)
        if t.kind == "num":
            return _number(t.text)
        if t.kind == "str":
            return _unquote(t.text)
        if t.kind == "kw" and t.text in ("true", "false"):
            return t.text == "true"
        raise self.error(f"expected a constant, found {_describe(t)}", t.pos)

    def feature(self) -> Feature:
        t = self.take()
        if not self.accept("("):
            if t.text in self.bound:
                raise self.error(f"variable {t.text!r} used as a feature", t.pos)
            return Feature(t.text)
        args: list[Var | Const] = []
        while True:
            a = self.tok
            if a.kind == "name":
                self.i += 1
                if a.text not in self.bound:
                    raise self.error(f"{a.text!r} is not a quantified variable", a.pos)
                args.append(Var(a.text))
            else:
                args.append(self.constant())
            if self.accept(")"):
                return Feature(t.text, tuple(args))
            self.expect(",")


def _describe(t: _Tok) -> str:
    return "end of formula" if t.kind == "end" else repr(t.text)


def _number(s: str) -> float | int:
    try:
        return int(s)
    except ValueError:
        return float(s)


def _unquote(s: str) -> str:
    return re.sub(r"\\(.)", r"\1", s[1:-1])


def parse(text: str) -> Formula:
    """Parse a formula; raises MTLSyntaxError with the line and column of the problem."""
    return _Parser(text).parse()


def _as_formula(formula: Formula | str) -> Formula:
    return parse(formula) if isinstance(formula, str) else formula


def _walk(f: Formula) -> Iterator[Formula]:
    yield f
    if isinstance(f, Not):
        yield from _walk(f.operand)
    elif isinstance(f, And | Or | Implies):
        yield from _walk(f.left)
        yield from _walk(f.right)
    elif isinstance(f, Always | Eventually):
        yield from _walk(f.operand)
    elif isinstance(f, Until):
        yield from _walk(f.left)
        yield from _walk(f.right)
    elif isinstance(f, Quantifier):
        yield from _walk(f.body)


def features(formula: Formula | str) -> list[str]:
    """The feature names the formula reads, in order of first use (parameterized once)."""
    out: dict[str, None] = {}
    for node in _walk(_as_formula(formula)):
        if isinstance(node, Feature):
            out[node.name] = None
        elif isinstance(node, Compare):
            for side in (node.left, node.right):
                if isinstance(side, Feature):
                    out[side.name] = None
    return list(out)


def domains(formula: Formula | str) -> list[str]:
    """The domains the formula's quantifiers range over (state keys holding members)."""
    out: dict[str, None] = {}
    for node in _walk(_as_formula(formula)):
        if isinstance(node, Quantifier):
            out[node.domain] = None
    return list(out)


def state_keys(formula: Formula | str) -> list[str]:
    """Every key a state must carry for this formula: its features, then its domains."""
    f = _as_formula(formula)
    return list(dict.fromkeys([*features(f), *domains(f)]))
