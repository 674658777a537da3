"""MTL progression: a formula compiled to nodes, progressed state by state."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeAlias

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
