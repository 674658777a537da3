"""MTL finite-trace semantics: atoms over a state, and the brute-force evaluator."""

from __future__ import annotations

import operator
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, TypeAlias

from ._syntax import (
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
    Var,
    _as_formula,
)

# -- atoms --------------------------------------------------------------------------------

_OPS: dict[str, Callable[[Any, Any], Any]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
    "==": operator.eq,
    "!=": operator.ne,
}


_ABSENT = object()  # a member not there at all (one there may hold None)


def _read(f: Feature, state: Mapping[str, Any], env: Mapping[str, Any]) -> Any:
    v = state.get(f.name)
    if not f.args or v is None:
        return v
    args = tuple(env.get(a.name) if isinstance(a, Var) else a for a in f.args)
    key = args[0] if len(args) == 1 else args
    try:
        r = v.get(key, _ABSENT)
    except (AttributeError, TypeError):
        return None
    if r is _ABSENT:
        # a member of that whole name wins, even a null one; else a dotted path's field
        return _field_at(v, key) if type(key) is str and "." in key else None
    return r


def _field_at(value: Any, path: str) -> Any:
    """Field ``path`` (``pose.position.x``, ``ranges.0``) of a nested message; None if absent."""
    for part in path.split("."):
        if isinstance(value, Mapping):
            value = value.get(part)
        elif (
            isinstance(value, list | tuple)
            and part.isdecimal()
            and part.isascii()  # "²" is a digit int() refuses
            and int(part) < len(value)
        ):
            value = value[int(part)]
        else:
            return None
        if value is None:
            return None
    return value


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


def _join3(a: bool | None, b: bool | None, dom: bool) -> bool | None:
    """Kleene's ``a and b`` (``dom`` False: false decides) or ``a or b`` (``dom`` True)."""
    if a is dom or b is dom:
        return dom
    if a is None or b is None:
        return None
    return not dom


def _and3(a: bool | None, b: bool | None) -> bool | None:
    return _join3(a, b, False)


def _or3(a: bool | None, b: bool | None) -> bool | None:
    return _join3(a, b, True)


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
        dom = not f.universal  # forall is an and over the members
        res: bool | None = f.universal
        for m in _members(trace[i][1], f.domain):
            res = _join3(res, _eval(f.body, trace, i, {**env, f.var: m}), dom)
        return res
    t0 = trace[i][0]
    lo, hi = t0 + f.lo, t0 + f.hi
    beyond = hi > trace[-1][0]
    if isinstance(f, Eventually | Always):
        dom = isinstance(f, Eventually)  # always is an and over the window, eventually an or
        res = not dom
        for j in range(i, len(trace)):
            tj = trace[j][0]
            if tj > hi:
                break
            if tj >= lo:
                res = _join3(res, _eval(f.operand, trace, j, env), dom)
        if beyond:
            res = _join3(res, _beyond(f), dom)
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
