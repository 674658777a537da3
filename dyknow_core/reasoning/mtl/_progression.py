"""Metric temporal logic over feature states: parser, progression, monitors, brute force.

Syntax::

    φ ::= true | false | feature | feature OP const | const OP feature | feature OP feature
        | not φ | φ and φ | φ or φ | φ -> φ | ( φ )
        | always[a,b] φ | eventually[a,b] φ | φ until[a,b] φ
        | forall x in Domain: φ | exists x in Domain: φ
    feature ::= name | name(arg, ...)        OP ::= < <= > >= == !=

Bounds are seconds (``[a, b]``, ``b`` may be ``inf``); a missing interval is ``[0, inf]``.
Precedence, loosest first: quantifiers, ``->`` (right associative), ``or``, ``and``,
``until`` (right associative), then the prefix operators ``not``/``always``/``eventually``
which bind one unary operand (so ``always p and q`` is ``(always p) and q``).

States. A state is a mapping feature name → value. A parameterized feature ``speed(x)``
reads ``state["speed"][x]`` (a mapping member → value; several arguments index it by the
tuple of them). A quantifier ``forall x in Cars: φ`` ranges over ``state["Cars"]`` (any
iterable of members) *in the state where the quantifier is evaluated*. A value that is
missing (``None``, absent key or member) or that cannot be compared makes its atom false.

Finite-trace semantics. A trace is a sequence of ``(t_i, state_i)`` with strictly increasing
times (seconds). The window of an operator with interval ``[a, b]`` evaluated at position
``i`` is the set of positions ``j ≥ i`` with ``t_i + a <= t_j <= t_i + b`` (computed exactly
so, in floating point). The trace is a prefix of an unknown future whose states come at
times after ``t_last``; positions there are *unknown*, and a window reaches them iff
``t_i + b > t_last``. Values are three-valued (True, False, None = not yet known), combined
with Kleene's strong tables:

* ``eventually[a,b] φ`` at i: OR of φ at the window's positions, OR ``beyond`` if the
  window reaches beyond the trace;
* ``always[a,b] φ`` at i: AND of the same;
* ``φ until[a,b] ψ`` at i: OR over window positions j of (ψ at j AND φ at every k with
  i <= k < j), OR (φ at every position from i AND ``beyond``) when the window reaches past
  the trace;
* the connectives are Kleene's; ``φ -> ψ`` is ``not φ or ψ``.

``beyond`` is unknown, except where the operand (ψ for until) is constant whatever the
states: an ``always`` of a valid operand gets True, an ``eventually``/``until`` of an
unsatisfiable one gets False (``always[1,2] true`` is True at once, ``eventually[1,2]
true`` is not: the next state may come after the window). Constancy is the syntactic
one of :func:`_fut` (true/false propagation, and ``always[0,b] φ``/``eventually[0,b] φ``
take φ's constant value since the window holds the current position).

:func:`evaluate` computes this by brute force. Progression (:func:`progress`,
:class:`Monitor`) reaches True or False after state ``i`` exactly when :func:`evaluate` on
the trace up to ``i`` is certain: a verdict is reported as soon as the states seen so far
decide it under these semantics (a window closes when a state later than its end arrives,
or at once when ``dt_next`` tells where the next state is). "Certain" is relative to these
tables: a contradiction they do not see (``eventually[0,5] p and always[0,5] not p``) is
reported when its windows decide it, not earlier.
"""

from __future__ import annotations

import bisect
import math
import operator
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, TypeAlias, cast

from ._exceptions import DyKnowError, ProcessError
from ._process import Process
from ._state import StatePolicy
from ._time import NS_PER_S

if TYPE_CHECKING:
    from ._instance import DyKnowInstance
    from ._stream import StreamGenerator, Subscription

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
class And:
    """Conjunction."""

    left: Formula
    right: Formula

    def __str__(self) -> str:
        return f"{_paren(self.left)} and {_paren(self.right)}"


@dataclass(frozen=True, slots=True)
class Or:
    """Disjunction."""

    left: Formula
    right: Formula

    def __str__(self) -> str:
        return f"{_paren(self.left)} or {_paren(self.right)}"


@dataclass(frozen=True, slots=True)
class Implies:
    """Implication ``left -> right``."""

    left: Formula
    right: Formula

    def __str__(self) -> str:
        return f"{_paren(self.left)} -> {_paren(self.right)}"


@dataclass(frozen=True, slots=True)
class Always:
    """``always[lo,hi] operand``."""

    lo: float
    hi: float
    operand: Formula

    def __str__(self) -> str:
        return f"always{_fmt_iv(self.lo, self.hi)} {_paren(self.operand)}"


@dataclass(frozen=True, slots=True)
class Eventually:
    """``eventually[lo,hi] operand``."""

    lo: float
    hi: float
    operand: Formula

    def __str__(self) -> str:
        return f"eventually{_fmt_iv(self.lo, self.hi)} {_paren(self.operand)}"


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

    def parse(self) -> Formula:
        f = self.formula()
        t = self.tok
        if t.kind != "end":
            raise self.error(f"unexpected {_describe(t)}", t.pos)
        return f

    def formula(self) -> Formula:
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
        f = self.conjunction()
        while self.accept("or"):
            f = Or(f, self.conjunction())
        return f

    def conjunction(self) -> Formula:
        f = self.until()
        while self.accept("and"):
            f = And(f, self.until())
        return f

    def until(self) -> Formula:
        left = self.unary()
        if self.accept("until"):
            lo, hi = self.interval()
            return Until(lo, hi, left, self.until())
        return left

    def unary(self) -> Formula:
        t = self.tok
        if t.kind == "kw":
            if t.text == "not":
                self.i += 1
                return Not(self.unary())
            if t.text in ("always", "eventually"):
                self.i += 1
                lo, hi = self.interval()
                body = self.unary()
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


# -- atoms --------------------------------------------------------------------------------

_OPS: dict[str, Callable[[Any, Any], Any]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
    "==": operator.eq,
    "!=": operator.ne,
}


def _read(f: Feature, state: Mapping[str, Any], env: Mapping[str, Any]) -> Any:
    v = state.get(f.name)
    if not f.args or v is None:
        return v
    args = tuple(env.get(a.name) if isinstance(a, Var) else a for a in f.args)
    try:
        return v.get(args[0] if len(args) == 1 else args)
    except (AttributeError, TypeError):
        return None


def _atom_value(f: Feature | Compare, state: Mapping[str, Any], env: Mapping[str, Any]) -> bool:
    if isinstance(f, Feature):
        return _read(f, state, env) is True
    a = _read(f.left, state, env) if isinstance(f.left, Feature) else f.left
    b = _read(f.right, state, env) if isinstance(f.right, Feature) else f.right
    if a is None or b is None:
        return False
    try:
        return bool(_OPS[f.op](a, b))
    except TypeError:
        return False


# -- brute force --------------------------------------------------------------------------

Trace: TypeAlias = Sequence[tuple[float, Mapping[str, Any]]]


def _and3(a: bool | None, b: bool | None) -> bool | None:
    if a is False or b is False:
        return False
    if a is None or b is None:
        return None
    return True


def _or3(a: bool | None, b: bool | None) -> bool | None:
    if a is True or b is True:
        return True
    if a is None or b is None:
        return None
    return False


def _not3(a: bool | None) -> bool | None:
    return None if a is None else not a


def evaluate(formula: Formula | str, trace: Trace, i: int = 0) -> bool | None:
    """The formula's value at position ``i`` of a finite trace: True, False, or None (unknown)."""
    return _eval(_as_formula(formula), trace, i, {})


def _eval(f: Formula, trace: Trace, i: int, env: Mapping[str, Any]) -> bool | None:
    if isinstance(f, BoolConst):
        return f.value
    if isinstance(f, Feature | Compare):
        return _atom_value(f, trace[i][1], env)
    if isinstance(f, Not):
        return _not3(_eval(f.operand, trace, i, env))
    if isinstance(f, And):
        return _and3(_eval(f.left, trace, i, env), _eval(f.right, trace, i, env))
    if isinstance(f, Or):
        return _or3(_eval(f.left, trace, i, env), _eval(f.right, trace, i, env))
    if isinstance(f, Implies):
        return _or3(_not3(_eval(f.left, trace, i, env)), _eval(f.right, trace, i, env))
    if isinstance(f, Quantifier):
        res: bool | None = f.universal
        for m in _members(trace[i][1], f.domain):
            v = _eval(f.body, trace, i, {**env, f.var: m})
            res = _and3(res, v) if f.universal else _or3(res, v)
        return res
    t0 = trace[i][0]
    lo, hi = t0 + f.lo, t0 + f.hi
    beyond = hi > trace[-1][0]
    if isinstance(f, Eventually | Always):
        res = isinstance(f, Always)
        for j in range(i, len(trace)):
            tj = trace[j][0]
            if tj > hi:
                break
            if tj >= lo:
                v = _eval(f.operand, trace, j, env)
                res = _and3(res, v) if isinstance(f, Always) else _or3(res, v)
        if beyond:
            b = _beyond(f)
            res = _and3(res, b) if isinstance(f, Always) else _or3(res, b)
        return res
    # until: every earlier position must satisfy the left side
    res = False
    prefix: bool | None = True
    for j in range(i, len(trace)):
        tj = trace[j][0]
        if tj > hi or prefix is False:
            break
        if tj >= lo:
            res = _or3(res, _and3(prefix, _eval(f.right, trace, j, env)))
        prefix = _and3(prefix, _eval(f.left, trace, j, env))
    else:
        if beyond:
            res = _or3(res, _and3(prefix, _beyond(f)))
    return res


def _fut(f: Formula) -> bool | None:
    """The value of ``f`` at a position whose state and future are unknown, when constant.

    Beyond the trace the states are arbitrary and may come at any later times (so a
    window may hold none of them); only constants decide there.
    """
    if isinstance(f, BoolConst):
        return f.value
    if isinstance(f, Feature | Compare):
        return None
    if isinstance(f, Not):
        return _not3(_fut(f.operand))
    if isinstance(f, And):
        return _and3(_fut(f.left), _fut(f.right))
    if isinstance(f, Or):
        return _or3(_fut(f.left), _fut(f.right))
    if isinstance(f, Implies):
        return _or3(_not3(_fut(f.left)), _fut(f.right))
    if isinstance(f, Always | Eventually):
        v = _fut(f.operand)
        if v is isinstance(f, Always) or f.lo == 0:
            return v
        return None
    if isinstance(f, Until):
        fl, fr = _fut(f.left), _fut(f.right)
        if fr is False or (fr is True and f.lo == 0):
            return fr
        if fl is False:
            return fr if f.lo == 0 else False
        return None
    v = _fut(f.body)
    return v if v is f.universal else None


def _beyond(f: Always | Eventually | Until) -> bool | None:
    """What the unknown positions after the trace contribute to a window reaching them."""
    if isinstance(f, Always):
        return True if _fut(f.operand) is True else None
    if isinstance(f, Eventually):
        return False if _fut(f.operand) is False else None
    return False if _fut(f.right) is False else None


def _members(state: Mapping[str, Any], domain: str) -> Iterable[Any]:
    d = state.get(domain)
    return () if d is None else d


# -- progression ---------------------------------------------------------------------------
#
# Progression runs on a compiled representation (plain slotted classes, not the frozen
# AST) because it builds a few nodes per state on the hot path. A compiled node's
# ``prog(state, t)`` returns True, False or a residual node: what must hold on the states
# strictly after t. Residual temporal nodes carry absolute windows [lo, hi] so that
# boundaries are decided by the same float expressions as in the brute force; once a
# window has started its lo becomes -inf (only later states matter), which lets the
# obligations of one operand merge into a single node (see _conj_into).

Node: TypeAlias = "_Node | bool"


class _Node:
    __slots__ = ()

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        raise NotImplementedError

    def close(self, t_next: float) -> Node:
        """Decide the windows that end before ``t_next`` (no state will fall in them)."""
        return self


class _Atom(_Node):
    # the test itself is the instance's ``prog`` (a slot shadows the method): one call
    __slots__ = ("prog", "text")

    def __init__(self, fn: Callable[[Mapping[str, Any], float], bool], text: str) -> None:
        self.prog = fn  # type: ignore[assignment]
        self.text = text

    def __str__(self) -> str:
        return self.text


class _NotN(_Node):
    __slots__ = ("x",)

    def __init__(self, x: _Node) -> None:
        self.x = x

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        r = self.x.prog(state, t)
        return _neg(r)

    def close(self, t_next: float) -> Node:
        return _neg(self.x.close(t_next))

    def __str__(self) -> str:
        return f"not ({self.x})"


def _neg(r: Node) -> Node:
    if r is True:
        return False
    if r is False:
        return True
    if type(r) is _NotN:
        return r.x
    assert isinstance(r, _Node)
    return _NotN(r)


class _AndN(_Node):
    __slots__ = ("xs",)

    def __init__(self, xs: tuple[_Node, ...]) -> None:
        self.xs = xs

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        out: list[_Node] = []
        for x in self.xs:
            r = x.prog(state, t)
            if r is False:
                return False
            if r is not True:
                _conj_into(out, r)
        return _mk_and(out)

    def close(self, t_next: float) -> Node:
        out: list[_Node] = []
        for x in self.xs:
            r = x.close(t_next)
            if r is False:
                return False
            if r is not True:
                _conj_into(out, r)
        return _mk_and(out)

    def __str__(self) -> str:
        return " and ".join(f"({x})" for x in self.xs)


class _OrN(_Node):
    __slots__ = ("xs",)

    def __init__(self, xs: tuple[_Node, ...]) -> None:
        self.xs = xs

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        out: list[_Node] = []
        for x in self.xs:
            r = x.prog(state, t)
            if r is True:
                return True
            if r is not False:
                _disj_into(out, r)
        return _mk_or(out)

    def close(self, t_next: float) -> Node:
        out: list[_Node] = []
        for x in self.xs:
            r = x.close(t_next)
            if r is True:
                return True
            if r is not False:
                _disj_into(out, r)
        return _mk_or(out)

    def __str__(self) -> str:
        return " or ".join(f"({x})" for x in self.xs)


def _mk_and(out: list[_Node]) -> Node:
    if not out:
        return True
    if len(out) == 1:
        return out[0]
    return _AndN(tuple(out))


def _mk_or(out: list[_Node]) -> Node:
    if not out:
        return False
    if len(out) == 1:
        return out[0]
    return _OrN(tuple(out))


def _conj_into(out: list[_Node], r: _Node) -> None:
    """Add a conjunct, flattening and merging windows of the same operand.

    ``eventually`` windows with one inside the other keep the inner one (it implies the
    outer); overlapping ``always`` windows become their union. Both are exact under the
    three-valued semantics, and they keep the residual of ``always(p -> eventually q)``
    at two nodes however many obligations are pending.
    """
    if type(r) is _AndN:
        for x in r.xs:
            _conj_into(out, x)
        return
    tr = type(r)
    if tr is _EvA or tr is _AlwA:
        body = r.body  # type: ignore[attr-defined]
        for k, o in enumerate(out):
            if type(o) is tr and o.body is body:
                m = _merge_and(o, r)  # type: ignore[arg-type]
                if m is not None:
                    out[k] = m
                    return
    out.append(r)


def _disj_into(out: list[_Node], r: _Node) -> None:
    """Add a disjunct; the dual of :func:`_conj_into`."""
    if type(r) is _OrN:
        for x in r.xs:
            _disj_into(out, x)
        return
    tr = type(r)
    if tr is _EvA or tr is _AlwA:
        body = r.body  # type: ignore[attr-defined]
        for k, o in enumerate(out):
            if type(o) is tr and o.body is body:
                m = _merge_or(o, r)  # type: ignore[arg-type]
                if m is not None:
                    out[k] = m
                    return
    out.append(r)


def _merge_and(a: _EvA | _AlwA, b: _EvA | _AlwA) -> _Node | None:
    if type(a) is _EvA:
        if a.lo >= b.lo and a.hi <= b.hi:
            return a
        if b.lo >= a.lo and b.hi <= a.hi:
            return b
        return None
    if a.lo <= b.hi and b.lo <= a.hi:
        return _AlwA(min(a.lo, b.lo), max(a.hi, b.hi), a.body)
    return None


def _merge_or(a: _EvA | _AlwA, b: _EvA | _AlwA) -> _Node | None:
    if type(a) is _AlwA:
        if a.lo >= b.lo and a.hi <= b.hi:
            return a
        if b.lo >= a.lo and b.hi <= a.hi:
            return b
        return None
    if a.lo <= b.hi and b.lo <= a.hi:
        return _EvA(min(a.lo, b.lo), max(a.hi, b.hi), a.body)
    return None


class _EvF(_Node):
    """``eventually[a,b]`` not yet anchored: anchored at the time it is first progressed."""

    __slots__ = ("a", "b", "body")

    def __init__(self, a: float, b: float, body: _Node) -> None:
        self.a = a
        self.b = b
        self.body = body

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        return _EvA(t + self.a if self.a else -INF, t + self.b, self.body).prog(state, t)


class _EvA(_Node):
    __slots__ = ("body", "hi", "lo")

    def __init__(self, lo: float, hi: float, body: _Node) -> None:
        self.lo = lo
        self.hi = hi
        self.body = body

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        hi = self.hi
        if t > hi:
            return False
        if t >= self.lo:
            r = self.body.prog(state, t)
            if r is True or t == hi:
                return r
            rest = self if self.lo == -INF else _EvA(-INF, hi, self.body)
            if r is False:
                return rest
            tr = type(r)
            if tr is not _OrN and not (tr is _EvA and r.body is self.body):  # type: ignore[attr-defined]
                return _OrN((r, rest))
            out: list[_Node] = []
            _disj_into(out, r)
            _disj_into(out, rest)
            return _mk_or(out)
        return self

    def close(self, t_next: float) -> Node:
        return False if t_next > self.hi else self

    def __str__(self) -> str:
        return f"eventually@[{_fmt_num(self.lo)},{_fmt_num(self.hi)}] ({self.body})"


class _AlwF(_Node):
    __slots__ = ("a", "b", "body")

    def __init__(self, a: float, b: float, body: _Node) -> None:
        self.a = a
        self.b = b
        self.body = body

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        return _AlwA(t + self.a if self.a else -INF, t + self.b, self.body).prog(state, t)


class _AlwA(_Node):
    __slots__ = ("body", "hi", "lo")

    def __init__(self, lo: float, hi: float, body: _Node) -> None:
        self.lo = lo
        self.hi = hi
        self.body = body

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        hi = self.hi
        if t > hi:
            return True
        if t >= self.lo:
            r = self.body.prog(state, t)
            if r is False or t == hi:
                return r
            rest = self if self.lo == -INF else _AlwA(-INF, hi, self.body)
            if r is True:
                return rest
            tr = type(r)
            if tr is not _AndN and not (tr is _AlwA and r.body is self.body):  # type: ignore[attr-defined]
                return _AndN((r, rest))
            out: list[_Node] = []
            _conj_into(out, r)
            _conj_into(out, rest)
            return _mk_and(out)
        return self

    def close(self, t_next: float) -> Node:
        return True if t_next > self.hi else self

    def __str__(self) -> str:
        return f"always@[{_fmt_num(self.lo)},{_fmt_num(self.hi)}] ({self.body})"


class _UntF(_Node):
    __slots__ = ("a", "b", "left", "right")

    def __init__(self, a: float, b: float, left: _Node, right: _Node) -> None:
        self.a = a
        self.b = b
        self.left = left
        self.right = right

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        return _UntA(t + self.a if self.a else -INF, t + self.b, self.left, self.right).prog(
            state, t
        )


class _UntA(_Node):
    __slots__ = ("hi", "left", "lo", "right")

    def __init__(self, lo: float, hi: float, left: _Node, right: _Node) -> None:
        self.lo = lo
        self.hi = hi
        self.left = left
        self.right = right

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        hi = self.hi
        if t > hi:
            return False
        r: Node = False
        if t >= self.lo:
            r = self.right.prog(state, t)
            if r is True or t == hi:
                return r
        lft = self.left.prog(state, t)
        if lft is False:
            return r
        rest: list[_Node] = []
        if lft is not True:
            _conj_into(rest, lft)
        unchanged = self.lo == -INF or t < self.lo
        rest.append(self if unchanged else _UntA(-INF, hi, self.left, self.right))
        out: list[_Node] = []
        if r is not False:
            _disj_into(out, r)  # type: ignore[arg-type]
        out.append(_mk_and(rest))  # type: ignore[arg-type]
        return _mk_or(out)

    def close(self, t_next: float) -> Node:
        return False if t_next > self.hi else self

    def __str__(self) -> str:
        return f"({self.left}) until@[{_fmt_num(self.lo)},{_fmt_num(self.hi)}] ({self.right})"


_QUANT_CACHE = 4096


class _Quant(_Node):
    __slots__ = ("cache", "env", "q")

    def __init__(self, q: Quantifier, env: Mapping[str, Any]) -> None:
        self.q = q
        self.env = env
        self.cache: dict[Any, Node] = {}

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        q = self.q
        out: list[_Node] = []
        for m in _members(state, q.domain):
            try:
                node = self.cache[m]
            except (KeyError, TypeError):
                node = _compile(q.body, {**self.env, q.var: m})
                if len(self.cache) >= _QUANT_CACHE:
                    self.cache.clear()  # members come and go: keep memory bounded
                try:
                    self.cache[m] = node
                except TypeError:
                    pass  # an unhashable member is compiled each time
            r = node if isinstance(node, bool) else node.prog(state, t)
            if q.universal:
                if r is False:
                    return False
                if r is not True:
                    _conj_into(out, r)
            else:
                if r is True:
                    return True
                if r is not False:
                    _disj_into(out, r)
        return _mk_and(out) if q.universal else _mk_or(out)

    def __str__(self) -> str:
        return str(self.q)


def _compile_atom(f: Feature | Compare, env: Mapping[str, Any], negate: bool) -> _Node:
    text = str(f) if not negate else f"not {f}"
    if isinstance(f, Compare) and not env and isinstance(f.left, Feature) and not f.left.args:
        # the common case gets a closure without the generic reader
        name, const, op = f.left.name, f.right, f.op
        if not isinstance(const, Feature):
            cmp = _OPS[op]

            def fn(s: Mapping[str, Any], t: float) -> bool:
                v = s.get(name)
                if v is None:
                    return negate
                try:
                    return bool(cmp(v, const)) is not negate
                except TypeError:
                    return negate

            return _Atom(fn, text)
    if isinstance(f, Feature) and not f.args:
        fname = f.name
        if negate:
            return _Atom(lambda s, t: s.get(fname) is not True, text)
        return _Atom(lambda s, t: s.get(fname) is True, text)
    return _Atom(lambda s, t: _atom_value(f, s, env) is not negate, text)


def _compile(f: Formula, env: Mapping[str, Any]) -> Node:
    if isinstance(f, BoolConst):
        return f.value
    if isinstance(f, Feature | Compare):
        return _compile_atom(f, env, False)
    if isinstance(f, Not):
        if isinstance(f.operand, Feature | Compare):
            return _compile_atom(f.operand, env, True)
        return _neg(_compile(f.operand, env))
    if isinstance(f, And):
        return _static_and(_compile(f.left, env), _compile(f.right, env))
    if isinstance(f, Or):
        return _static_or(_compile(f.left, env), _compile(f.right, env))
    if isinstance(f, Implies):
        return _static_or(_neg(_compile(f.left, env)), _compile(f.right, env))
    if isinstance(f, Always | Eventually):
        body = _compile(f.operand, env)
        always = isinstance(f, Always)
        if body is always:
            return body  # always true / eventually false, whatever the window holds
        if isinstance(body, bool) and f.lo == 0:
            return body  # the window holds the current state, so it decides
        # otherwise the window may be empty (vacuous), so it must be watched
        return (_AlwF if always else _EvF)(f.lo, f.hi, _shared(body))
    if isinstance(f, Until):
        left, right = _compile(f.left, env), _compile(f.right, env)
        if right is False or (right is True and f.lo == 0):
            return right
        if left is False:
            return right if f.lo == 0 else False  # only the current state can satisfy it
        return _UntF(f.lo, f.hi, _shared(left), _shared(right))
    body = _compile(f.body, {**env, f.var: None})
    if body is f.universal:
        return body  # holds (fails) for every member, and for an empty domain too
    return _Quant(f, env)


class _Const(_Node):
    """A constant kept as a node where an operator needs one (``true until p``)."""

    __slots__ = ("value",)

    def __init__(self, value: bool) -> None:
        self.value = value

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        return self.value

    def __str__(self) -> str:
        return "true" if self.value else "false"


class _Shared(_Node):
    """A temporal operator's operand, progressed once per state however many windows hold it.

    Every pending evaluation of one compiled formula (a StepMonitor's, or the obligations
    an ``always`` leaves) progresses the same operand through the same state; the result
    is immutable, so it is computed once and shared (which also lets them merge).
    """

    __slots__ = ("node", "result", "state", "t")

    def __init__(self, node: _Node) -> None:
        self.node = node
        self.state: Mapping[str, Any] | None = None
        self.t = -INF
        self.result: Node = False

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        if state is self.state and t == self.t:
            return self.result
        r = self.node.prog(state, t)
        self.state = state
        self.t = t
        self.result = r
        return r

    def __str__(self) -> str:
        return str(self.node)


def _shared(n: Node) -> _Node:
    if isinstance(n, bool):
        return _Const(n)
    if isinstance(n, _Atom | _Const):
        return n  # as cheap to evaluate as to look up
    return _Shared(n)


def _as_node(n: Node) -> _Node:
    return _Const(n) if isinstance(n, bool) else n


def _static_and(a: Node, b: Node) -> Node:
    if a is False or b is False:
        return False
    if a is True:
        return b
    if b is True:
        return a
    return _AndN((a, b))


def _static_or(a: Node, b: Node) -> Node:
    if a is True or b is True:
        return True
    if a is False:
        return b
    if b is False:
        return a
    return _OrN((a, b))


class Residual:
    """What a formula still requires after progression (neither certainly true nor false)."""

    __slots__ = ("node",)

    def __init__(self, node: _Node) -> None:
        self.node = node

    def __str__(self) -> str:
        return str(self.node)

    def __repr__(self) -> str:
        return f"Residual({self})"


def compile_formula(formula: Formula | str) -> bool | Residual:
    """The formula ready for :func:`progress` (True/False when it is constant)."""
    n = _compile(_as_formula(formula), {})
    return n if isinstance(n, bool) else Residual(n)


def progress(
    formula: Formula | str | Residual | bool,
    state: Mapping[str, Any],
    t: float,
    dt_next: float | None = None,
) -> bool | Residual:
    """Progress through the state at time ``t`` (s): True, False, or what the future must satisfy.

    A formula (text or AST) is anchored at ``t``; a residual carries absolute windows from
    earlier progression, so ``t`` must be the time of the state that follows them. With
    ``dt_next`` (seconds to the next state), windows ending before it are decided now.
    """
    if isinstance(formula, bool):
        return formula
    if isinstance(formula, Residual):
        node: Node = formula.node
    else:
        node = _compile(_as_formula(formula), {})
        if isinstance(node, bool):
            return node
    r = node.prog(state, t)  # type: ignore[union-attr]
    if dt_next is not None and not isinstance(r, bool):
        r = r.close(t + dt_next)
    return r if isinstance(r, bool) else Residual(r)


# -- every-step fast path --------------------------------------------------------------------
#
# For the fragment without quantifiers, unbounded windows or until, StepMonitor evaluates
# bottom-up: each node keeps one value per position (None until certain) and its step
# returns the positions it decided at this state. A bounded always/eventually marks, for a
# child position j holding its dominant value (False/True), every position whose window
# holds j (a contiguous range, found by bisection on the exact window bounds); a position
# whose window has closed is decided the other way once its window holds no undecided child
# position (scanned from the child's first undecided position, then waiting on the blocker).


class _FNode:
    __slots__ = ("val",)

    def __init__(self) -> None:
        self.val: list[bool | None] = []

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        raise NotImplementedError

    def children(self) -> tuple[_FNode, ...]:
        return ()

    def base(self) -> int:
        # the first position this node (or one below) still needs
        val = self.val
        try:
            b = val.index(None)
        except ValueError:
            b = len(val)
        for c in self.children():
            cb = c.base()
            if cb < b:
                b = cb
        return b

    def rebase(self, k: int) -> None:
        # forget positions before k (all decided and out of every open window)
        del self.val[:k]
        for c in self.children():
            c.rebase(k)


class _FAtom(_FNode):
    __slots__ = ("fn",)

    def __init__(self, fn: Callable[[Mapping[str, Any], float], bool]) -> None:
        super().__init__()
        self.fn = fn

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        self.val.append(self.fn(s, t))
        return [n]


class _FConst(_FNode):
    __slots__ = ("value",)

    def __init__(self, value: bool) -> None:
        super().__init__()
        self.value = value

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        self.val.append(self.value)
        return [n]


class _FNot(_FNode):
    __slots__ = ("child",)

    def __init__(self, child: _FNode) -> None:
        super().__init__()
        self.child = child

    def children(self) -> tuple[_FNode, ...]:
        return (self.child,)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        ev = self.child.step(n, t, s)
        val, cv = self.val, self.child.val
        val.append(None)
        for j in ev:
            val[j] = not cv[j]
        return ev


class _FBin(_FNode):
    __slots__ = ("dom", "left", "right")

    def __init__(self, left: _FNode, right: _FNode, dom: bool) -> None:
        super().__init__()
        self.left, self.right, self.dom = left, right, dom

    def children(self) -> tuple[_FNode, ...]:
        return (self.left, self.right)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        el = self.left.step(n, t, s)
        er = self.right.step(n, t, s)
        val, lv, rv, dom = self.val, self.left.val, self.right.val, self.dom
        val.append(None)
        out: list[int] = []
        for j in el:
            if val[j] is None:
                x = lv[j]
                if x is dom:
                    val[j] = dom
                    out.append(j)
                else:
                    y = rv[j]
                    if y is not None:
                        val[j] = y
                        out.append(j)
        for j in er:
            if val[j] is None:
                x = rv[j]
                if x is dom:
                    val[j] = dom
                    out.append(j)
                else:
                    y = lv[j]
                    if y is not None:
                        val[j] = y
                        out.append(j)
        return out


class _FBinAtom(_FNode):
    """``and``/``or`` whose left operand is decided at each state (a fused atom)."""

    __slots__ = ("dom", "fn", "lv", "right")

    def __init__(self, fn: Callable[[Mapping[str, Any], float], bool], right: _FNode, dom: bool):
        super().__init__()
        self.fn, self.right, self.dom = fn, right, dom
        self.lv: list[bool] = []

    def children(self) -> tuple[_FNode, ...]:
        return (self.right,)

    def rebase(self, k: int) -> None:
        del self.lv[:k]
        super().rebase(k)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        x = self.fn(s, t)
        self.lv.append(x)
        er = self.right.step(n, t, s)
        val, dom = self.val, self.dom
        if x is dom:
            val.append(dom)
            out = [n]
        else:
            val.append(None)
            out = []
        if er:
            lv, rv = self.lv, self.right.val
            for j in er:
                if val[j] is None:
                    val[j] = rv[j] if lv[j] is not dom else dom
                    out.append(j)
        return out


class _FWinAtom(_FNode):
    """A bounded always/eventually of an operand decided at each state, in order."""

    __slots__ = (
        "a",
        "b",
        "close",
        "dom",
        "fn",
        "hi_hint",
        "lo_hint",
        "marked",
        "ta",
        "tb",
        "times",
    )

    def __init__(
        self,
        a: float,
        b: float,
        fn: Callable[[Mapping[str, Any], float], bool],
        always: bool,
        times: list[float],
    ):
        super().__init__()
        self.a, self.b, self.fn, self.times = a, b, fn, times
        self.dom = not always
        # window starts t + a; with a == 0 they are the times themselves (t + 0.0 == t)
        self.ta: list[float] = times if a == 0 else []
        self.tb: list[float] = []
        self.close = 0
        self.marked = -1  # every position up to here whose window holds a dominant value is marked
        self.lo_hint = 0
        self.hi_hint = 0

    def base(self) -> int:
        b = super().base()
        return b if b < self.close else self.close

    def rebase(self, k: int) -> None:
        super().rebase(k)
        del self.tb[:k]
        if self.ta is not self.times:
            del self.ta[:k]
        self.close -= k
        self.marked = max(self.marked - k, -1)
        self.lo_hint = max(self.lo_hint - k, 0)
        self.hi_hint = max(self.hi_hint - k, 0)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        x = self.fn(s, t)
        val, ta, tb, dom = self.val, self.ta, self.tb, self.dom
        tb.append(t + self.b)
        if x is not dom:
            val.append(None)
            out: list[int] = []
            if len(ta) <= n:
                ta.append(t + self.a)
        elif ta is self.times and self.marked == n - 1:
            # the window starts here and every earlier window holding t is already marked
            val.append(dom)
            out = [n]
            self.marked = n
        else:
            val.append(None)
            out = []
            if len(ta) <= n:
                ta.append(t + self.a)
            # the positions whose window holds t: a range moving forward with t
            lo = bisect.bisect_left(tb, t, self.lo_hint, n + 1)
            hi = n if ta is self.times else bisect.bisect_right(ta, t, self.hi_hint, n + 1) - 1
            self.lo_hint = lo
            if hi >= 0:
                self.hi_hint = hi
            m = self.marked
            if m >= lo:
                lo = m + 1
            if hi >= lo:
                for i in range(lo, hi + 1):
                    val[i] = dom
                out.extend(range(lo, hi + 1))
                self.marked = hi
        cl = self.close
        if tb[cl] <= t:
            nd = not dom
            while cl <= n and tb[cl] <= t:
                if val[cl] is None:
                    val[cl] = nd
                    out.append(cl)
                cl += 1
            self.close = cl
        return out


class _FWin(_FNode):
    __slots__ = (
        "a",
        "b",
        "child",
        "close",
        "cover_hi",
        "cover_lo",
        "cu",
        "dom",
        "ta",
        "tb",
        "times",
        "waiters",
    )

    def __init__(self, a: float, b: float, child: _FNode, always: bool, times: list[float]):
        super().__init__()
        self.a, self.b, self.child, self.times = a, b, child, times
        self.dom = not always  # the child value that decides a window at once
        self.ta: list[float] = times if a == 0 else []  # as in _FWinAtom
        self.tb: list[float] = []
        self.close = 0  # the first position whose window is still open
        self.cu = 0  # the child's first undecided position
        self.cover_lo, self.cover_hi = 0, -1  # a range of positions all decided
        self.waiters: dict[int, list[tuple[int, int]]] = {}  # blocker -> (position, start)

    def children(self) -> tuple[_FNode, ...]:
        return (self.child,)

    def base(self) -> int:
        b = super().base()
        for x in (self.close, self.cu):
            if x < b:
                b = x
        return b

    def rebase(self, k: int) -> None:
        super().rebase(k)
        del self.tb[:k]
        if self.ta is not self.times:
            del self.ta[:k]
        self.close -= k
        self.cu -= k
        self.cover_lo = max(self.cover_lo - k, 0)
        self.cover_hi = max(self.cover_hi - k, -1)
        # entries of positions already decided (by a dominant value) are stale: drop them
        waiters: dict[int, list[tuple[int, int]]] = {}
        for p, w in self.waiters.items():
            kept = [(i - k, s_i - k) for i, s_i in w if i >= k]
            if kept:
                waiters[p - k] = kept
        self.waiters = waiters

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        ev = self.child.step(n, t, s)
        val, ta, tb, times = self.val, self.ta, self.tb, self.times
        val.append(None)
        if ta is not times:
            ta.append(t + self.a)
        tb.append(t + self.b)
        out: list[int] = []
        if ev:  # only the child's new values can mark positions or unblock windows
            cv, dom = self.child.val, self.dom
            for j in ev:
                if cv[j] is dom:
                    self._mark(j, out)
            cu = self.cu
            while cu <= n and cv[cu] is not None:
                cu += 1
            self.cu = cu
            waiters = self.waiters
            if waiters:
                for j in ev:
                    w = waiters.pop(j, None)
                    if w:
                        for i, s_i in w:
                            if val[i] is None:
                                self._scan(i, s_i, j - 1, out)
        cl = self.close
        if tb[cl] <= t:
            cu = self.cu
            nd = not self.dom
            while cl <= n and tb[cl] <= t:
                if val[cl] is None:
                    # closed, and no dominant value in the window: decided once all are
                    if cu > n:
                        val[cl] = nd
                        out.append(cl)
                    else:
                        e_i = bisect.bisect_right(times, tb[cl], cl) - 1
                        if cu > e_i:
                            val[cl] = nd
                            out.append(cl)
                        else:
                            s_i = cl if ta is times else bisect.bisect_left(times, ta[cl], cl)
                            self._scan(cl, s_i, e_i, out)
                cl += 1
            self.close = cl
        return out

    def _mark(self, j: int, out: list[int]) -> None:
        # every position whose window holds j takes the dominant value
        val, dom, ta, times = self.val, self.dom, self.ta, self.times
        tj = times[j]
        lo = bisect.bisect_left(self.tb, tj, 0, j + 1)
        hi = j if ta is times else bisect.bisect_right(ta, tj, 0, j + 1) - 1
        if lo > hi:
            return
        if self.cover_lo <= lo <= self.cover_hi + 1:
            start = self.cover_hi + 1 if self.cover_hi + 1 > lo else lo
            if hi > self.cover_hi:
                self.cover_hi = hi
        else:
            start = lo
            self.cover_lo, self.cover_hi = lo, hi
        for i in range(start, hi + 1):
            if val[i] is None:
                val[i] = dom
                out.append(i)

    def _scan(self, i: int, s_i: int, p: int, out: list[int]) -> None:
        # backwards from the window's end (or the last blocker) to its start: the child
        # decides mostly in order, so the last undecided position is mostly the last to go
        cv = self.child.val
        cu = self.cu
        lo = s_i if s_i > cu else cu
        while p >= lo and cv[p] is not None:
            p -= 1
        if p < lo:
            self.val[i] = not self.dom
            out.append(i)
        else:
            self.waiters.setdefault(p, []).append((i, s_i))


def _fast_supported(f: Formula) -> bool:
    if isinstance(f, BoolConst | Feature | Compare):
        return True
    if isinstance(f, Not):
        return _fast_supported(f.operand)
    if isinstance(f, And | Or | Implies):
        return _fast_supported(f.left) and _fast_supported(f.right)
    if isinstance(f, Always | Eventually):
        return f.hi != INF and _fast_supported(f.operand)
    return False


_AtomFn: TypeAlias = Callable[[Mapping[str, Any], float], bool]


def _pure(f: Formula) -> bool:
    if isinstance(f, BoolConst | Feature | Compare):
        return True
    if isinstance(f, Not):
        return _pure(f.operand)
    if isinstance(f, And | Or | Implies):
        return _pure(f.left) and _pure(f.right)
    return False


def _pure_fn(f: Formula) -> Callable[[Mapping[str, Any], float], bool]:
    """One test for a formula without temporal operators (two-valued at every state)."""
    if isinstance(f, BoolConst):
        v = f.value
        return lambda s, t: v
    if isinstance(f, Feature | Compare):
        return cast(_AtomFn, _compile_atom(f, {}, False).prog)
    if isinstance(f, Not):
        if isinstance(f.operand, Feature | Compare):
            return cast(_AtomFn, _compile_atom(f.operand, {}, True).prog)
        g = _pure_fn(f.operand)
        return lambda s, t: not g(s, t)
    assert isinstance(f, And | Or | Implies)
    left = _pure_fn(Not(f.left) if isinstance(f, Implies) else f.left)
    right = _pure_fn(f.right)
    if isinstance(f, And):
        return lambda s, t: left(s, t) and right(s, t)
    return lambda s, t: left(s, t) or right(s, t)


def _fast_compile(f: Formula, times: list[float]) -> _FNode:
    c = _fut(f)
    if c is not None:
        return _FConst(c)
    if _pure(f):
        return _FAtom(_pure_fn(f))
    if isinstance(f, And | Or | Implies):
        left = _fast_compile(Not(f.left) if isinstance(f, Implies) else f.left, times)
        right = _fast_compile(f.right, times)
        dom = not isinstance(f, And)
        if isinstance(right, _FAtom):
            left, right = right, left
        if isinstance(left, _FAtom):
            return _FBinAtom(left.fn, right, dom)
        return _FBin(left, right, dom)
    if isinstance(f, Not):
        return _FNot(_fast_compile(f.operand, times))
    assert isinstance(f, Always | Eventually)
    body = _fast_compile(f.operand, times)
    if isinstance(body, _FAtom):
        return _FWinAtom(f.lo, f.hi, body.fn, isinstance(f, Always), times)
    return _FWin(f.lo, f.hi, body, isinstance(f, Always), times)


# -- monitors ------------------------------------------------------------------------------


class Verdict(NamedTuple):
    """A certain verdict: the formula evaluated from ``start`` is ``verdict``, known at ``time``."""

    start: float
    time: float
    verdict: bool


class Monitor:
    """Progresses one formula over (t, state) steps and reports each certain verdict.

    After a verdict the monitor restarts at the next state (``restart=True``), so an
    ``always`` monitor reports every violation, each for the formula evaluated from the
    state after the previous verdict.
    """

    __slots__ = ("_fresh", "_node", "_start", "formula", "restart", "text")

    def __init__(self, formula: Formula | str, *, restart: bool = True) -> None:
        self.formula = _as_formula(formula)
        self.text = formula if isinstance(formula, str) else str(formula)
        self.restart = restart
        self._fresh = _compile(self.formula, {})
        self._node: Node | None = None
        self._start = 0.0

    @property
    def residual(self) -> bool | Residual | None:
        """What the current evaluation still requires (None before the first state)."""
        n = self._node
        if n is None or isinstance(n, bool):
            return n
        return Residual(n)

    def step(self, t: float, state: Mapping[str, Any]) -> Verdict | None:
        """Progress through one state; the verdict it made certain, if any."""
        n = self._node
        if n is None:
            n = self._fresh
            self._start = t
        elif n is True or n is False:
            return None  # decided and not restarting
        r = n if n is True or n is False else n.prog(state, t)
        if r is True or r is False:
            self._node = None if self.restart else r
            return Verdict(self._start, t, r)
        self._node = r
        return None

    def run(self, trace: Iterable[tuple[float, Mapping[str, Any]]]) -> list[Verdict]:
        """Every verdict over a whole trace."""
        out = []
        step = self.step
        for t, s in trace:
            v = step(t, s)
            if v is not None:
                out.append(v)
        return out


_COMPACT = 4096  # every-step fast path: steps between forgetting decided positions


class StepMonitor:
    """Evaluates the formula from every state: one verdict per start time, once certain."""

    __slots__ = ("_compact_at", "_fast", "_fresh", "_times", "formula", "pending")

    def __init__(self, formula: Formula | str) -> None:
        self.formula = _as_formula(formula)
        self._fresh = _compile(self.formula, {})
        self.pending: list[tuple[float, Node]] = []
        self._times: list[float] = []
        self._fast: _FNode | None = None
        self._compact_at = _COMPACT
        # the bottom-up windowed evaluation where the fragment allows it, else progression
        if _fast_supported(self.formula):
            self._fast = _fast_compile(self.formula, self._times)

    def step(self, t: float, state: Mapping[str, Any]) -> list[Verdict]:
        """Start an evaluation at ``t``, progress all pending ones; the verdicts decided now."""
        root = self._fast
        if root is None:
            return self._step_progress(t, state)
        times = self._times
        n = len(times)
        if n >= self._compact_at:
            # drop the positions no window needs any more, so memory follows the windows
            k = root.base()
            if k > 0:
                root.rebase(k)
                del times[:k]
                n -= k
            self._compact_at = n + _COMPACT
        times.append(t)
        ev = root.step(n, t, state)
        if not ev:
            return []
        val = root.val
        new = tuple.__new__  # skips the named tuple's Python-level __new__
        if len(ev) == 1:
            j = ev[0]
            return [new(Verdict, (times[j], t, val[j]))]
        ev.sort()
        return [new(Verdict, (times[j], t, val[j])) for j in ev]

    def _step_progress(self, t: float, state: Mapping[str, Any]) -> list[Verdict]:
        out: list[Verdict] = []
        keep: list[tuple[float, Node]] = []
        self.pending.append((t, self._fresh))
        for start, n in self.pending:
            r = n if isinstance(n, bool) else n.prog(state, t)
            if r is True or r is False:
                out.append(Verdict(start, t, r))
            else:
                keep.append((start, r))
        self.pending = keep
        return out

    def undecided(self) -> list[float]:
        """Start times whose verdict the states so far leave unknown."""
        if self._fast is not None:
            return [t for t, v in zip(self._times, self._fast.val, strict=True) if v is None]
        return [s for s, _ in self.pending]


# -- in an instance ------------------------------------------------------------------------


class MonitorProcess(Process):
    """Monitors a formula over a state stream and publishes its verdicts as a stream."""

    kind = "monitor"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        formula: Formula,
        text: str,
        state_name: str,
        output: StreamGenerator,
    ) -> None:
        super().__init__(name, instance)
        self.formula = formula
        self.text = text
        self.monitor = Monitor(formula)
        self.state_name = state_name
        self.output = output
        self.label = output.label
        self.subscription: Subscription | None = None
        self.verdicts = 0
        self._last_ta = -(2**63)

    def _on_states(self, batch: list[tuple[Any, int, int]]) -> None:
        if not self.running:
            return
        out: list[tuple[Any, int, int]] = []
        step = self.monitor.step
        for value, tv, ta in batch:
            try:
                v = step(tv / NS_PER_S, value)
            except Exception as exc:
                self._fail(exc)
                continue
            if v is not None:
                if ta <= self._last_ta:
                    ta = self._last_ta + 1  # available times are unique per stream
                self._last_ta = ta
                val = {"verdict": v.verdict, "formula": self.text, "start": round(v.start * 1e9)}
                out.append((val, tv, ta))
        if out:
            self.verdicts += len(out)
            try:
                self.output.publish_batch(out)
            except Exception as exc:
                self._fail(exc)

    def _stop(self) -> None:
        super()._stop()
        if self.subscription is not None:
            self.subscription.close()
        if self.state_name in self.instance.processes:
            self.instance.remove_process(self.state_name)

    def describe(self) -> dict[str, Any]:
        """Adds the formula, the state process, the verdict stream and the count."""
        d = super().describe()
        d.update(formula=self.text, state=self.state_name, output=self.label)
        d["verdicts"] = self.verdicts
        return d


def add_monitor(
    instance: DyKnowInstance,
    formula: Formula | str,
    *,
    label: str | None = None,
    state_label: str | None = None,
    components: Mapping[str, str] | None = None,
    period: float = 1.0,
    max_delay: float | None = None,
    name: str | None = None,
) -> MonitorProcess:
    """Monitor ``formula`` on a state of exactly its features; verdicts published on ``label``.

    ``components`` maps each feature (and quantified domain) to the label it is read
    from; a feature not in it is read from the label of its own name. The state is made
    with ``StatePolicy(period, max_delay=max_delay)``; each verdict is a sample with value
    ``{"verdict": bool, "formula": text, "start": ns}`` at the valid time of the state
    that made it certain (a window is closed by the first state after it, so at most a
    period late). A quantified domain is a component too: its stream carries the current
    members (a list), and a parameterized feature's stream a mapping member → value.
    Removing the monitor removes its state process too.
    """
    f = _as_formula(formula)
    text = formula if isinstance(formula, str) else str(formula)
    keys = state_keys(f)
    if not keys:
        raise ProcessError(f"formula {text!r} reads no feature")
    comps = {k: (components or {}).get(k, k) for k in keys}
    if label is None:
        n = 0
        while instance.has_label(f"monitor/{n}") or instance.has_label(f"monitor/{n}/state"):
            n += 1
        label = f"monitor/{n}"
    name = name or f"monitor:{label}"
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    state_label = state_label or f"{label}/state"
    state = instance.add_state(state_label, comps, StatePolicy(period=period, max_delay=max_delay))
    try:
        out = instance.create_stream(label, value_type=dict)
    except Exception:
        instance.remove_process(state.name)
        raise
    proc = MonitorProcess(name, instance, f, text, state.name, out)
    try:
        proc.subscription = instance.subscribe(state_label, callback=proc._on_states)
        instance.add_process(proc)
    except Exception:
        proc._stop()
        instance.remove_stream(label)
        raise
    return proc


__all__ = [
    "INF",
    "Always",
    "And",
    "BoolConst",
    "Compare",
    "Eventually",
    "Feature",
    "Formula",
    "Implies",
    "MTLSyntaxError",
    "Monitor",
    "MonitorProcess",
    "Not",
    "Or",
    "Quantifier",
    "Residual",
    "StepMonitor",
    "Until",
    "Var",
    "Verdict",
    "add_monitor",
    "compile_formula",
    "domains",
    "evaluate",
    "features",
    "parse",
    "progress",
    "state_keys",
]
