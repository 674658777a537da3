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
one of ``_semantics._fut`` (true/false propagation, and ``always[0,b] φ``/``eventually[0,b] φ``
take φ's constant value since the window holds the current position).

:func:`evaluate` computes this by brute force. Progression (:func:`progress`,
:class:`Monitor`) reaches True or False after state ``i`` exactly when :func:`evaluate` on
the trace up to ``i`` is certain: a verdict is reported as soon as the states seen so far
decide it under these semantics (a window closes when a state later than its end arrives,
or at once when ``dt_next`` tells where the next state is). "Certain" is relative to these
tables: a contradiction they do not see (``eventually[0,5] p and always[0,5] not p``) is
reported when its windows decide it, not earlier.
"""

from ._engine import StepMonitor
from ._monitor import Monitor, MonitorProcess, Verdict, add_monitor
from ._progression import Residual, compile_formula, progress
from ._semantics import evaluate
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
    MTLSyntaxError,
    Not,
    Or,
    Quantifier,
    Until,
    Var,
    domains,
    features,
    parse,
    state_keys,
)

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
