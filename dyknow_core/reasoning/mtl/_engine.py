"""The every-step MTL engine (bottom-up windowed evaluation) and the verdicts monitors report."""

from __future__ import annotations

import bisect
import gc
from collections.abc import Callable, Iterable, Mapping
from typing import Any, NamedTuple, TypeAlias, cast

from ..._record import register_record_type
from ._progression import Node, _compile, _compile_atom
from ._semantics import _OPS, _fut
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
    Until,
    _as_formula,
)


class Verdict(NamedTuple):
    """A certain verdict: the formula evaluated from ``start`` is ``verdict``, known at ``time``."""

    start: float
    time: float
    verdict: bool


register_record_type(Verdict)  # a replay gives verdicts back as themselves


_AtomFn: TypeAlias = Callable[[Mapping[str, Any], float], bool]

# -- every-step fast path --------------------------------------------------------------------
#
# For the fragment without quantifiers or unbounded windows, and with until only between
# state formulas, StepMonitor evaluates bottom-up: each node keeps one value per position
# (None until certain, in room reserved at each compaction) and its step returns the
# positions it decided at this state. A bounded always/eventually marks, for a child
# position j holding its dominant value (False/True), every position whose window holds j
# (a contiguous range, found by bisection on the exact window bounds); a position whose
# window has closed is decided the other way once its window holds no undecided child
# position (scanned from the child's first undecided position, then waiting on the
# blocker). Over a state formula, decided in order, the undecided positions of a window
# from the current state (and of an until) are a suffix: no bisection, and a state
# formula joined with such a window is the same node. Every position is decided once:
# amortised, a state costs a few operations per node (and a bisection where a value of a
# temporal operand decides a window).


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

    def reserve(self, size: int) -> None:
        # room for positions up to size - 1, undecided: a step assigns, never appends
        val = self.val
        if len(val) < size:
            val.extend([None] * (size - len(val)))
        for c in self.children():
            c.reserve(size)


class _FAtom(_FNode):
    __slots__ = ("fn",)

    def __init__(self, fn: Callable[[Mapping[str, Any], float], bool]) -> None:
        super().__init__()
        self.fn = fn

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        self.val[n] = self.fn(s, t)
        return [n]


class _FConst(_FNode):
    __slots__ = ("value",)

    def __init__(self, value: bool) -> None:
        super().__init__()
        self.value = value

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        self.val[n] = self.value
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
    """``and``/``or`` whose left operand is decided at each state (a fused atom).

    A position left undecided had the unit on the left (true for ``and``, false for
    ``or``), so the right operand's value, once known, is the value.
    """

    __slots__ = ("dom", "fn", "right")

    def __init__(self, fn: _AtomFn, right: _FNode, dom: bool):
        super().__init__()
        self.fn, self.right, self.dom = fn, right, dom

    def children(self) -> tuple[_FNode, ...]:
        return (self.right,)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        er = self.right.step(n, t, s)
        val = self.val
        if self.fn(s, t) is self.dom:
            val[n] = self.dom
            out = [n]
        else:
            out = []
        if er:
            rv = self.right.val
            for j in er:
                if val[j] is None:
                    val[j] = rv[j]
                    out.append(j)
        return out


class _FWindow(_FNode):
    """What the bounded always/eventually nodes share: window bounds per position."""

    __slots__ = ("a", "b", "close", "dom", "ta", "tb", "times")

    def __init__(self, a: float, b: float, always: bool, times: list[float]) -> None:
        super().__init__()
        self.a, self.b, self.times = a, b, times
        self.dom = not always  # the operand value that decides a window at once
        # window starts t + a; with a == 0 they are the times themselves (t + 0.0 == t)
        self.ta: list[float] = times if a == 0 else []
        self.tb: list[float] = []
        self.close = 0  # the first position whose window is still open

    def base(self) -> int:
        b = super().base()
        return b if b < self.close else self.close

    def rebase(self, k: int) -> None:
        super().rebase(k)
        del self.tb[:k]
        if self.ta is not self.times:
            del self.ta[:k]
        self.close -= k


class _FWinAtom(_FWindow):
    """A bounded always/eventually of an operand decided at each state, in order."""

    __slots__ = ("fn", "hi_hint", "lo_hint", "marked")

    def __init__(
        self,
        a: float,
        b: float,
        fn: Callable[[Mapping[str, Any], float], bool],
        always: bool,
        times: list[float],
    ):
        super().__init__(a, b, always, times)
        self.fn = fn
        self.marked = -1  # every position up to here whose window holds a dominant value is marked
        self.lo_hint = 0
        self.hi_hint = 0

    def rebase(self, k: int) -> None:
        super().rebase(k)
        self.marked = max(self.marked - k, -1)
        self.lo_hint = max(self.lo_hint - k, 0)
        self.hi_hint = max(self.hi_hint - k, 0)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        x = self.fn(s, t)
        val, ta, tb, dom = self.val, self.ta, self.tb, self.dom
        tb.append(t + self.b)
        if x is not dom:
            out: list[int] = []
            if len(ta) <= n:
                ta.append(t + self.a)
        elif ta is self.times and self.marked == n - 1:
            # the window starts here and every earlier window holding t is already marked
            val[n] = dom
            out = [n]
            self.marked = n
        else:
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


class _FWinAtom0(_FWindow):
    """A bounded always/eventually from the current state (``[0, b]``) of a state formula.

    Its window starts at its own position and the operand is decided in order, so the
    undecided positions are always the last ones, ``close`` to ``n``: a dominant value
    decides them all, and otherwise the windows that end by ``t`` close. No bisection.
    """

    __slots__ = ("fn",)

    def __init__(self, b: float, fn: _AtomFn, always: bool, times: list[float]) -> None:
        super().__init__(0.0, b, always, times)
        self.fn = fn

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        # window ends are times[i] + b, the same float expression as everywhere
        val, times, b = self.val, self.times, self.b
        cl = self.close
        if self.fn(s, t) is self.dom:
            if cl == n:
                val[n] = self.dom
                self.close = n + 1
                return [n]
            out: list[int] = []
            nd = not self.dom
            while times[cl] + b < t:  # ended since the last state (not n's: b >= 0)
                val[cl] = nd
                out.append(cl)
                cl += 1
            dom = self.dom
            for i in range(cl, n + 1):
                val[i] = dom
            out.extend(range(cl, n + 1))
            self.close = n + 1
            return out
        if times[cl] + b > t:
            return []
        out = []
        nd = not self.dom
        while cl <= n and times[cl] + b <= t:
            val[cl] = nd
            out.append(cl)
            cl += 1
        self.close = cl
        return out


class _FWin(_FWindow):
    """A bounded always/eventually of any operand: decided once its window's values are."""

    __slots__ = ("child", "cover_hi", "cover_lo", "cu", "end", "waiters")

    def __init__(self, a: float, b: float, child: _FNode, always: bool, times: list[float]):
        super().__init__(a, b, always, times)
        self.child = child
        self.cu = 0  # the child's first undecided position
        self.end = 0  # the first position after the window of the last one closed
        self.cover_lo, self.cover_hi = 0, -1  # a range of positions all decided
        self.waiters: dict[int, list[tuple[int, int]]] = {}  # blocker -> (position, start)

    def children(self) -> tuple[_FNode, ...]:
        return (self.child,)

    def base(self) -> int:
        b = super().base()  # the window's own (and close) already counted
        return b if b < self.cu else self.cu

    def rebase(self, k: int) -> None:
        super().rebase(k)
        self.cu -= k
        self.end = max(self.end - k, 0)
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
        tb = self.tb
        tb.append(t + self.b)
        if self.a:  # else the window starts are the times themselves
            self.ta.append(t + self.a)
        out: list[int] = []
        if ev:  # only the child's new values can mark positions or unblock windows
            cv, dom = self.child.val, self.dom
            for j in ev:
                if cv[j] is dom:
                    if j == self.cover_hi + 1 and not self.a:
                        # the windows holding j before j's own are covered already
                        self.cover_hi = j
                        if self.val[j] is None:
                            self.val[j] = dom
                            out.append(j)
                    else:
                        self._mark(j, out)
            cu = self.cu
            while cu <= n and cv[cu] is not None:
                cu += 1
            self.cu = cu
            if self.waiters:
                self._wake(ev, out)
        cl = self.close
        tbc = tb[cl]
        if tbc <= t:
            val, times, cu = self.val, self.times, self.cu
            nd = not self.dom
            while True:
                if val[cl] is None:
                    # closed, and no dominant value in the window: decided once all are
                    if cu > n or times[cu] > tbc:
                        val[cl] = nd
                        out.append(cl)
                    else:
                        self._wait(cl, tbc, n, out)
                cl += 1
                if cl > n:
                    break
                tbc = tb[cl]
                if tbc > t:
                    break
            self.close = cl
        return out

    def _wake(self, ev: list[int], out: list[int]) -> None:
        # the windows waiting on a child position decided now: scan on from it
        waiters, val = self.waiters, self.val
        for j in ev:
            w = waiters.pop(j, None)
            if w:
                for i, s_i in w:
                    if val[i] is None:
                        self._scan(i, s_i, j - 1, out)

    def _wait(self, i: int, tbc: float, n: int, out: list[int]) -> None:
        # a closed window holding an undecided child position, maybe: scan back from its end
        times, cu = self.times, self.cu
        e = self.end
        if e <= n and times[e] <= tbc:
            e = bisect.bisect_right(times, tbc, e, n + 1)
            self.end = e
        s_i = i if self.ta is times else bisect.bisect_left(times, self.ta[i], i)
        cv = self.child.val
        lo = s_i if s_i > cu else cu
        p = e - 1
        while p >= lo and cv[p] is not None:
            p -= 1
        if p < lo:
            self.val[i] = not self.dom
            out.append(i)
        else:
            w = self.waiters.get(p)
            if w is None:
                self.waiters[p] = [(i, s_i)]
            else:
                w.append((i, s_i))

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


class _FUntAtom(_FWindow):
    """A bounded ``left until right`` of operands decided at each state, in order.

    An undecided position has held ``left`` at every state since it (a false one decides
    all of them false) and seen no ``right`` in its window yet; so a true ``right`` marks
    the range of positions whose window holds it, a false ``left`` decides the rest false,
    and a window that closes first is false: each position is decided once (a bisection
    finds the range a true right marks).
    """

    __slots__ = ("hi_hint", "lfn", "marked", "rfn")

    def __init__(self, a: float, b: float, lfn: _AtomFn, rfn: _AtomFn, times: list[float]):
        super().__init__(a, b, False, times)
        self.lfn, self.rfn = lfn, rfn
        self.marked = -1  # every position up to here whose window held a true right is marked
        self.hi_hint = 0

    def rebase(self, k: int) -> None:
        super().rebase(k)
        self.marked = max(self.marked - k, -1)
        self.hi_hint = max(self.hi_hint - k, 0)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        val, ta, tb = self.val, self.ta, self.tb
        tb.append(t + self.b)
        if ta is not self.times:
            ta.append(t + self.a)
        out: list[int] = []
        cl = self.close
        if self.rfn(s, t):
            # the undecided positions whose window holds t (left held since each of them)
            lo = bisect.bisect_left(tb, t, cl, n + 1)
            if ta is self.times:
                hi = n
            else:
                hi = bisect.bisect_right(ta, t, self.hi_hint, n + 1) - 1
                if hi >= 0:
                    self.hi_hint = hi
            m = self.marked
            if m >= lo:
                lo = m + 1
            if hi >= lo:
                for i in range(lo, hi + 1):
                    val[i] = True
                out.extend(range(lo, hi + 1))
                self.marked = hi
        if not self.lfn(s, t):
            # left fails here: every position still open (window started or not) is false
            for i in range(cl, n + 1):
                if val[i] is None:
                    val[i] = False
                    out.append(i)
            self.close = n + 1
            return out
        if tb[cl] <= t:
            while cl <= n and tb[cl] <= t:
                if val[cl] is None:
                    val[cl] = False
                    out.append(cl)
                cl += 1
            self.close = cl
        return out


class _FUntAtom0(_FWindow):
    """A ``left until[0, b] right`` of state formulas: its undecided positions are a suffix.

    A true right decides every open position true (and the ones whose window ended since
    the last state false), a false left decides them all false, otherwise the windows
    ending by ``t`` close false; as for :class:`_FWinAtom0`, no bisection.
    """

    __slots__ = ("lfn", "rfn")

    def __init__(self, b: float, lfn: _AtomFn, rfn: _AtomFn, times: list[float]) -> None:
        super().__init__(0.0, b, False, times)
        self.lfn, self.rfn = lfn, rfn

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        val, times, b = self.val, self.times, self.b
        cl = self.close
        if self.rfn(s, t):
            if cl == n:
                val[n] = True
                self.close = n + 1
                return [n]
            out: list[int] = []
            while times[cl] + b < t:  # ended since the last state (not n's: b >= 0)
                val[cl] = False
                out.append(cl)
                cl += 1
            for i in range(cl, n + 1):
                val[i] = True
            out.extend(range(cl, n + 1))
            self.close = n + 1
            return out
        if not self.lfn(s, t):
            val[n] = False
            for i in range(cl, n):
                val[i] = False
            self.close = n + 1
            return list(range(cl, n + 1))
        if times[cl] + b > t:
            return []
        out = []
        while cl <= n and times[cl] + b <= t:
            val[cl] = False
            out.append(cl)
            cl += 1
        self.close = cl
        return out


# ``g -> always[0,b] p``, ``g and eventually[0,b] p``, ``g -> (p until[0,b] q)``: a state
# formula joined with a window over state formulas, the usual body of an ``always``. One
# node each (the join's value is the window's where the guard is not decisive), so the
# window's positions a guard decides cost nothing more and no events pass between two.


class _FGuardWin0(_FWindow):
    """``guard or/and always/eventually[0, b] operand``, state formulas: see ``_FWinAtom0``."""

    __slots__ = ("gdom", "tests")

    def __init__(
        self,
        b: float,
        operand: Formula,
        always: bool,
        guard: Formula,
        gdom: bool,
        times: list[float],
    ) -> None:
        super().__init__(0.0, b, always, times)
        self.gdom = gdom
        # one call a state for both tests: (the guard decides, the operand is dominant)
        self.tests = _tests_fn(_is(guard, gdom), _is(operand, self.dom))

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        decides, dominant = self.tests(s, t)
        val = self.val
        if decides:
            val[n] = self.gdom
            out = [n]
        else:
            out = []
        cl = self.close
        if dominant:
            # the window's value is decided for every open position (the ended ones not)
            if cl == n:  # nothing else open (half the states of the bench): no loops
                if not decides:
                    val[n] = self.dom
                    out.append(n)
                self.close = n + 1
                return out
            times, b = self.times, self.b
            nd = not self.dom
            while times[cl] + b < t:  # ended since the last state (not n's: b >= 0)
                if val[cl] is None:
                    val[cl] = nd
                    out.append(cl)
                cl += 1
            dom = self.dom
            for i in range(cl, n + 1):
                if val[i] is None:
                    val[i] = dom
                    out.append(i)
            self.close = n + 1
            return out
        times, b = self.times, self.b
        if times[cl] + b > t:
            return out
        nd = not self.dom
        while cl <= n and times[cl] + b <= t:
            if val[cl] is None:
                val[cl] = nd
                out.append(cl)
            cl += 1
        self.close = cl
        return out


class _FGuardUnt0(_FWindow):
    """``guard or/and (left until[0, b] right)``, all state formulas: see ``_FUntAtom0``."""

    __slots__ = ("gdom", "tests")

    def __init__(
        self,
        b: float,
        left: Formula,
        right: Formula,
        guard: Formula,
        gdom: bool,
        times: list[float],
    ) -> None:
        super().__init__(0.0, b, False, times)
        self.gdom = gdom
        # one call a state for the three tests: (the guard decides, right, left)
        self.tests = _tests_fn(_is(guard, gdom), right, left)

    def step(self, n: int, t: float, s: Mapping[str, Any]) -> list[int]:
        decides, right, left = self.tests(s, t)
        val = self.val
        if decides:
            val[n] = self.gdom
            out = [n]
        else:
            out = []
        cl = self.close
        if right:
            if cl == n:  # nothing else open (most states where right holds): no loops
                if not decides:
                    val[n] = True
                    out.append(n)
                self.close = n + 1
                return out
            times, b = self.times, self.b
            while times[cl] + b < t:  # ended since the last state (not n's: b >= 0)
                if val[cl] is None:
                    val[cl] = False
                    out.append(cl)
                cl += 1
            for i in range(cl, n + 1):
                if val[i] is None:
                    val[i] = True
                    out.append(i)
            self.close = n + 1
            return out
        if not left:
            for i in range(cl, n + 1):
                if val[i] is None:
                    val[i] = False
                    out.append(i)
            self.close = n + 1
            return out
        times, b = self.times, self.b
        if times[cl] + b > t:
            return out
        while cl <= n and times[cl] + b <= t:
            if val[cl] is None:
                val[cl] = False
                out.append(cl)
            cl += 1
        self.close = cl
        return out


def _fast_supported(f: Formula) -> bool:
    if isinstance(f, BoolConst | Feature | Compare):
        return True
    if isinstance(f, Not):
        return _fast_supported(f.operand)
    if isinstance(f, And | Or | Implies):
        return _fast_supported(f.left) and _fast_supported(f.right)
    if isinstance(f, Always | Eventually):
        return f.hi != INF and _fast_supported(f.operand)
    if isinstance(f, Until):
        return f.hi != INF and _pure(f.left) and _pure(f.right)
    return False


def _pure(f: Formula) -> bool:
    if isinstance(f, BoolConst | Feature | Compare):
        return True
    if isinstance(f, Not):
        return _pure(f.operand)
    if isinstance(f, And | Or | Implies):
        return _pure(f.left) and _pure(f.right)
    return False


# A state formula is one generated function whose comparisons of a feature with a number
# are written out (measured: ``on_road and speed < 35`` was three calls a state, a lambda
# over two closures; now one call, a fifth of the until bench's time per state less). A
# value that is not a float (missing, int, another type) goes to the atom's own closure,
# which has the general semantics; every other atom is its closure, called.
_PURE_SRC = "def fn(s, t):\n    return {expr}\n"


def _pure_fn(f: Formula) -> _AtomFn:
    """One test for a formula without temporal operators (two-valued at every state)."""
    scope: dict[str, Any] = {}
    code = _PURE_SRC.format(expr=_pure_expr(f, scope))
    exec(code, scope)  # operators from the whitelist, names and constants passed in scope
    return cast(_AtomFn, scope["fn"])


def _is(f: Formula, value: bool) -> Formula:
    """``f`` as the test that it has ``value``."""
    return f if value else Not(f)


def _tests_fn(*fs: Formula) -> Callable[[Mapping[str, Any], float], tuple[bool, ...]]:
    """One generated function giving the values of several state formulas, in order."""
    scope: dict[str, Any] = {}
    code = _PURE_SRC.format(expr="(" + "".join(_pure_expr(f, scope) + ", " for f in fs) + ")")
    exec(code, scope)  # as for _pure_fn
    return cast(Callable[[Mapping[str, Any], float], tuple[bool, ...]], scope["fn"])


def _pure_expr(f: Formula, scope: dict[str, Any]) -> str:
    # each subexpression is a bool, so ``and``/``or`` give bools and short-circuit as Kleene
    if isinstance(f, BoolConst):
        return "True" if f.value else "False"
    if isinstance(f, Not):
        return f"(not {_pure_expr(f.operand, scope)})"
    if isinstance(f, And | Or | Implies):
        left = _pure_expr(f.left, scope)
        right = _pure_expr(f.right, scope)
        if isinstance(f, And):
            return f"({left} and {right})"
        return f"({'not ' if isinstance(f, Implies) else ''}{left} or {right})"
    assert isinstance(f, Feature | Compare)
    k = len(scope)  # grows with each atom: its names are unique
    scope[f"a{k}"] = _compile_atom(f, {}, False).prog
    if isinstance(f, Feature) and not f.args:
        scope[f"n{k}"] = f.name
        return f"(s.get(n{k}) is True)"
    if (
        isinstance(f, Compare)
        and isinstance(f.left, Feature)
        and not f.left.args
        and type(f.right) in (int, float)
        and f.op in _OPS
    ):
        scope[f"n{k}"], scope[f"c{k}"] = f.left.name, f.right
        v = f"v{k}"
        return f"({v} {f.op} c{k} if type({v} := s.get(n{k})) is float else a{k}(s, t))"
    return f"a{k}(s, t)"


def _fast_compile(f: Formula, times: list[float]) -> _FNode:
    c = _fut(f)
    if c is not None:
        return _FConst(c)
    if _pure(f):
        return _FAtom(_pure_fn(f))
    if isinstance(f, And | Or | Implies):
        lf, rf = Not(f.left) if isinstance(f, Implies) else f.left, f.right
        left, right = _fast_compile(lf, times), _fast_compile(rf, times)
        dom = not isinstance(f, And)
        if isinstance(right, _FAtom):
            left, right, lf, rf = right, left, rf, lf
        if isinstance(left, _FAtom):
            # a window over a state formula is made only from these (see below)
            if type(right) is _FWinAtom0:
                assert isinstance(rf, Always | Eventually)
                return _FGuardWin0(right.b, rf.operand, isinstance(rf, Always), lf, dom, times)
            if type(right) is _FUntAtom0:
                assert isinstance(rf, Until)
                return _FGuardUnt0(right.b, rf.left, rf.right, lf, dom, times)
            return _FBinAtom(left.fn, right, dom)
        return _FBin(left, right, dom)
    if isinstance(f, Not):
        return _FNot(_fast_compile(f.operand, times))
    if isinstance(f, Until):
        if f.lo == 0:
            return _FUntAtom0(f.hi, _pure_fn(f.left), _pure_fn(f.right), times)
        return _FUntAtom(f.lo, f.hi, _pure_fn(f.left), _pure_fn(f.right), times)
    assert isinstance(f, Always | Eventually)
    body = _fast_compile(f.operand, times)
    if isinstance(body, _FAtom):
        if f.lo == 0:
            return _FWinAtom0(f.hi, body.fn, isinstance(f, Always), times)
        return _FWinAtom(f.lo, f.hi, body.fn, isinstance(f, Always), times)
    return _FWin(f.lo, f.hi, body, isinstance(f, Always), times)


_COMPACT = 4096  # every-step fast path: steps between forgetting decided positions


def _run_restarting(
    formula: Formula, trace: Iterable[tuple[float, Mapping[str, Any]]]
) -> tuple[list[Verdict], list[tuple[float, Mapping[str, Any]]]]:
    """:meth:`Monitor.run` (restarting) by this engine: the verdicts, and the states of the
    evaluation still open at the end.

    The engine decides every position exactly when progression does, so the restarting
    monitor's verdict for a start is this position's value, read the state it is set;
    the next evaluation starts at the next position. Measured on the bench formula, this
    costs two thirds of progressing the one evaluation (whose residual is rebuilt at
    every state), though it evaluates from every state.
    """
    times: list[float] = []
    states: list[Mapping[str, Any]] = []  # the states since the last compaction
    root = _fast_compile(formula, times)
    compact_at = _COMPACT
    root.reserve(compact_at)
    val = root.val
    step = root.step
    add_t, add_s = times.append, states.append
    out: list[Verdict] = []
    n = want = 0  # want: the position the current evaluation starts at
    for t, s in trace:
        if n >= compact_at:
            k = root.base()  # at most want, which is undecided or not stepped yet
            if k > 0:
                root.rebase(k)
                del times[:k], states[:k]
                n -= k
                want -= k
            compact_at = n + _COMPACT
            root.reserve(compact_at)
        add_t(t)
        add_s(s)
        step(n, t, s)
        n += 1
        v = val[want]
        if v is not None:
            out.append(Verdict(times[want], t, v))
            want = n
    return out, list(zip(times[want:n], states[want:n], strict=True))


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
            self._fast.reserve(self._compact_at)

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
            root.reserve(self._compact_at)
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

    def run(self, trace: Iterable[tuple[float, Mapping[str, Any]]]) -> list[Verdict]:
        """Step through every ``(t, state)`` of ``trace``: the verdicts, as ``step`` orders them.

        The cycle collector is paused while it runs (and restored after).
        """
        # Every verdict outlives the batch as a tracked object (a named tuple is never
        # untracked), so a long batch alone makes the cycle collector scan the whole heap
        # (a quarter of the time at 100 k states); the loop makes no cycles: pause it.
        paused = gc.isenabled()
        if paused:
            gc.disable()
        try:
            root = self._fast
            if root is None:
                out: list[Verdict] = []
                for t, s in trace:
                    out += self._step_progress(t, s)
                return out
            return self._run_fast(root, trace)
        finally:
            if paused:
                gc.enable()

    def _run_fast(
        self, root: _FNode, trace: Iterable[tuple[float, Mapping[str, Any]]]
    ) -> list[Verdict]:
        # step's loop with its lookups done once
        times = self._times
        n = len(times)
        compact_at = self._compact_at
        append = times.append
        root_step = root.step
        val = root.val
        new = tuple.__new__  # skips the named tuple's Python-level __new__
        out: list[Verdict] = []
        add = out.append
        for t, s in trace:
            if n >= compact_at:
                k = root.base()
                if k > 0:
                    root.rebase(k)
                    del times[:k]
                    n -= k
                compact_at = n + _COMPACT
                root.reserve(compact_at)
            append(t)
            ev = root_step(n, t, s)
            n += 1
            if ev:
                # a loop, not a comprehension: most lists are short, and a comprehension
                # is a call of its own (measured)
                if len(ev) > 1:
                    ev.sort()
                for j in ev:
                    add(new(Verdict, (times[j], t, val[j])))
        self._compact_at = compact_at
        return out

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
            val = self._fast.val[: len(self._times)]  # the rest is room reserved
            return [t for t, v in zip(self._times, val, strict=True) if v is None]
        return [s for s, _ in self.pending]
