"""MTL progression: a formula compiled to nodes, progressed state by state."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeAlias

from ._semantics import _OPS, _atom_value, _members
from ._syntax import (
    INF,
    Always,
    And,
    BoolConst,
    Compare,
    Eventually,
    Feature,
    Formula,
    Implies,
    Not,
    Or,
    Quantifier,
    Until,
    _as_formula,
    _fmt_num,
)

# -- progression ---------------------------------------------------------------------------
#
# Progression runs on a compiled representation (plain slotted classes, not the frozen
# AST) because it builds a few nodes per state on the hot path. A compiled node's
# ``prog(state, t)`` returns True, False or a residual node: what must hold on the states
# strictly after t. Residual temporal nodes carry absolute windows [lo, hi] so that
# boundaries are decided by the same float expressions as in the brute force; once a
# window has started its lo becomes -inf (only later states matter), which lets the
# obligations of one operand merge into a single node (see _into).

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


class _Junction(_Node):
    """An n-ary ``and`` (``dom`` False: a false operand decides it) or ``or`` (``dom`` True)."""

    __slots__ = ("xs",)
    dom: ClassVar[bool]
    word: ClassVar[str]

    def __init__(self, xs: tuple[_Node, ...]) -> None:
        self.xs = xs

    def close(self, t_next: float) -> Node:
        dom = self.dom
        junction = type(self)
        out: list[_Node] = []
        for x in self.xs:
            r = x.close(t_next)
            if r is dom:
                return dom
            if not isinstance(r, bool):
                _into(out, r, junction)
        return _make(out, junction)

    def __str__(self) -> str:
        return f" {self.word} ".join(f"({x})" for x in self.xs)


class _Window(_Node):
    """A bounded ``always`` (``dom`` False) or ``eventually`` (True) at absolute times.

    ``dom`` is the operand value that decides the window at once; a window that passes
    without one has the other value.
    """

    __slots__ = ("body", "hi", "lo")
    dom: ClassVar[bool]
    word: ClassVar[str]

    def __init__(self, lo: float, hi: float, body: _Node) -> None:
        self.lo = lo
        self.hi = hi
        self.body = body

    def close(self, t_next: float) -> Node:
        return (not self.dom) if t_next > self.hi else self

    def __str__(self) -> str:
        return f"{self.word}@[{_fmt_num(self.lo)},{_fmt_num(self.hi)}] ({self.body})"


# The per-state ``prog`` of the and/or junctions and the always/eventually windows are
# written out once per operator, with the deciding value as a constant. Parameterizing
# them (by closure or class attribute) costs 10-15% of ``bench mtl``'s monitor mode, as
# they run for every node at every state; everything else is shared.


class _AndN(_Junction):
    __slots__ = ()
    dom = False
    word = "and"

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        out: list[_Node] = []
        for x in self.xs:
            r = x.prog(state, t)
            if r is False:
                return False
            if r is not True:
                _into(out, r, _AndN)
        return _make(out, _AndN)


class _OrN(_Junction):
    __slots__ = ()
    dom = True
    word = "or"

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        out: list[_Node] = []
        for x in self.xs:
            r = x.prog(state, t)
            if r is True:
                return True
            if r is not False:
                _into(out, r, _OrN)
        return _make(out, _OrN)


class _AlwA(_Window):
    __slots__ = ()
    dom = False
    word = "always"

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
            _into(out, r, _AndN)
            _into(out, rest, _AndN)
            return _make(out, _AndN)
        return self


class _EvA(_Window):
    __slots__ = ()
    dom = True
    word = "eventually"

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
            _into(out, r, _OrN)
            _into(out, rest, _OrN)
            return _make(out, _OrN)
        return self


def _make(out: list[_Node], junction: type[_Junction]) -> Node:
    """The junction of ``out``: its unit when empty, the one operand, or the node."""
    if len(out) == 1:
        return out[0]
    if out:
        return junction(tuple(out))
    return junction is _AndN  # the empty and is true, the empty or false


def _into(out: list[_Node], r: _Node, junction: type[_Junction]) -> None:
    """Add an operand to a junction's list, flattening and merging windows of one operand.

    A window of the junction's own kind (``always`` in an ``and``, ``eventually`` in an
    ``or``) overlapping another becomes their union; of the other kind, one inside the
    other keeps the inner one (it implies the outer in an ``and``, is implied in an
    ``or``). Both are exact under the three-valued semantics, and they keep the residual
    of ``always(p -> eventually q)`` at two nodes however many obligations are pending.
    """
    tr = type(r)
    if tr is junction:
        for x in r.xs:  # type: ignore[attr-defined]
            _into(out, x, junction)
        return
    if tr is _AlwA or tr is _EvA:
        body = r.body  # type: ignore[attr-defined]
        for k, o in enumerate(out):
            if type(o) is tr and o.body is body:
                own = (tr is _AlwA) is (junction is _AndN)
                m = _union(o, r) if own else _inner(o, r)  # type: ignore[arg-type]
                if m is not None:
                    out[k] = m
                    return
    out.append(r)


def _union(a: _Window, b: _Window) -> _Window | None:
    if a.lo <= b.hi and b.lo <= a.hi:
        return type(a)(min(a.lo, b.lo), max(a.hi, b.hi), a.body)
    return None


def _inner(a: _Window, b: _Window) -> _Window | None:
    if a.lo >= b.lo and a.hi <= b.hi:
        return a
    if b.lo >= a.lo and b.hi <= a.hi:
        return b
    return None


class _Unanchored(_Node):
    """A bounded window not yet anchored: anchored at the time it is first progressed."""

    __slots__ = ("a", "b", "body", "window")

    def __init__(self, window: type[_Window], a: float, b: float, body: _Node) -> None:
        self.window = window
        self.a = a
        self.b = b
        self.body = body

    def prog(self, state: Mapping[str, Any], t: float) -> Node:
        return self.window(t + self.a if self.a else -INF, t + self.b, self.body).prog(state, t)


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
            _into(rest, lft, _AndN)
        unchanged = self.lo == -INF or t < self.lo
        rest.append(self if unchanged else _UntA(-INF, hi, self.left, self.right))
        out: list[_Node] = []
        if r is not False:
            _into(out, r, _OrN)  # type: ignore[arg-type]
        out.append(_make(rest, _AndN))  # type: ignore[arg-type]
        return _make(out, _OrN)

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
        junction = _AndN if q.universal else _OrN  # forall is an and over the members
        dom = not q.universal
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
            if r is dom:
                return dom
            if not isinstance(r, bool):
                _into(out, r, junction)
        return _make(out, junction)

    def __str__(self) -> str:
        return str(self.q)


# ``feature OP const`` with the operator written out (no call to ``operator.lt`` and
# ``bool``): the test every state of every window runs. One factory per operator and
# polarity, from this fixed template and the operators of ``_OPS`` only.
_COMPARE_SRC = """
def make(name, const):
    def fn(s, t):
        v = s.get(name)
        if v is None:
            return {miss}
        try:
            return {yes} if v {op} const else {no}
        except TypeError:
            return {miss}
    return fn
"""
_Test: TypeAlias = Callable[[Mapping[str, Any], float], bool]
_COMPARE: dict[tuple[str, bool], Callable[[str, Any], _Test]] = {}


def _compare_fn(op: str, negate: bool) -> Callable[[str, Any], _Test]:
    make = _COMPARE.get((op, negate))
    if make is None:
        assert op in _OPS
        code = _COMPARE_SRC.format(op=op, miss=negate, yes=not negate, no=negate)
        scope: dict[str, Any] = {}
        exec(code, scope)  # a fixed template and a whitelisted operator
        make = _COMPARE[(op, negate)] = scope["make"]
    return make


def _compile_atom(f: Feature | Compare, env: Mapping[str, Any], negate: bool) -> _Node:
    text = str(f) if not negate else f"not {f}"
    if isinstance(f, Compare) and not env and isinstance(f.left, Feature) and not f.left.args:
        # the common case gets a closure without the generic reader
        name, const, op = f.left.name, f.right, f.op
        if not isinstance(const, Feature):
            return _Atom(_compare_fn(op, negate)(name, const), text)
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
        return _static(_compile(f.left, env), _compile(f.right, env), _AndN)
    if isinstance(f, Or):
        return _static(_compile(f.left, env), _compile(f.right, env), _OrN)
    if isinstance(f, Implies):
        return _static(_neg(_compile(f.left, env)), _compile(f.right, env), _OrN)
    if isinstance(f, Always | Eventually):
        body = _compile(f.operand, env)
        always = isinstance(f, Always)
        if body is always:
            return body  # always true / eventually false, whatever the window holds
        if isinstance(body, bool) and f.lo == 0:
            return body  # the window holds the current state, so it decides
        # otherwise the window may be empty (vacuous), so it must be watched
        return _Unanchored(_AlwA if always else _EvA, f.lo, f.hi, _shared(body))
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


def _static(a: Node, b: Node, junction: type[_Junction]) -> Node:
    """``a and b`` (``a or b``), simplified when either is constant."""
    dom = junction.dom
    if a is dom or b is dom:
        return dom
    if isinstance(a, bool):  # the unit: the other operand decides
        return b
    if isinstance(b, bool):
        return a
    return junction((a, b))


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
