"""A policy compiled into a per-subscription filter: the per-sample hot path.

A policy is checked once (pydantic) and then turned into a small Python function that
contains only the tests that policy needs, run over whole batches with local variables.
Generating the loop is what lets a chain of policies keep up with per-item libraries:
every ``if policy.x is not None`` that a generic loop would test per sample is decided
here, once.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ._policy import Approximation, ChangeKind, LateAction, Order, Policy
from ._sample import RawSample
from ._time import seconds_to_ns

MISSING: Any = object()
_NEG_INF = -(2**63)
# The most grid points one publish or tick decides: a gap of a million periods must not
# make one call build a million samples. It is a property of the grid, never of a
# subscription's buffer, so every subscriber with the same policy gets the same samples.
MAX_GRID_BURST = 1 << 16


class FilterStats:
    """Counts of what a subscription's policy dropped, by reason, and what it emitted."""

    __slots__ = (
        "approximated",
        "bounds",
        "change",
        "emitted",
        "late",
        "order",
        "skipped",
        "type",
        "window",
    )

    def __init__(self) -> None:
        self.window = self.late = self.order = self.bounds = 0
        self.change = self.type = self.approximated = self.emitted = 0
        # grid points never produced: a gap longer than MAX_GRID_BURST periods
        self.skipped = 0

    @property
    def dropped(self) -> int:
        """Samples the policy held back, whatever the reason."""
        return self.window + self.late + self.order + self.bounds + self.change + self.type

    def as_dict(self) -> dict[str, int]:
        """A plain snapshot for metrics and reports."""
        return {k: getattr(self, k) for k in self.__slots__}


class Mapper:
    """A single-input computational unit fused into its input's filter loop.

    ``fn`` maps a value (None: emit nothing); ``fail`` is told of each exception;
    ``next_ta`` gives the first available time for a batch's outputs, which then count up
    by 1 ns so they stay unique.
    """

    __slots__ = ("fail", "fn", "next_ta")

    def __init__(
        self,
        fn: Callable[[Any], Any],
        fail: Callable[[Exception], None],
        next_ta: Callable[[list[RawSample]], int],
    ) -> None:
        self.fn = fn
        self.fail = fail
        self.next_ta = next_ta


def _compile(
    policy: Policy,
    *,
    stages: tuple[str, ...],
    mapper: Mapper | None = None,
    order_attr: str = "last_tv",
) -> Any:
    """Write and compile ``run(self, batch, out)`` applying the named stages of ``policy``.

    ``order_attr`` is the attribute holding the valid time the order test compares with:
    the last emitted sample's, or (before a sample-period grid) the last admitted input's.
    """
    body: list[str] = []
    consts: dict[str, Any] = {"MISSING": MISSING}
    if "window" in stages and policy.start is not None:
        consts["START"] = policy.start
        body.append("if tv < START:\n    n_window += 1\n    continue")
    if "window" in stages and policy.end is not None:
        consts["END"] = policy.end
        # the subscription ends at the first sample past `end`: what follows in the same
        # batch is never looked at, exactly as if each sample had been pushed alone
        body.append("if tv > END:\n    n_window += 1\n    self.ended = True\n    break")
    if "late" in stages and policy.max_delay is not None:
        consts["MAXD"] = seconds_to_ns(policy.max_delay)
        body.append("if ta - tv > MAXD:\n    n_late += 1\n    continue")
    if "order" in stages and policy.order is Order.MONOTONE:
        body.append("if tv < last_tv:\n    n_order += 1\n    continue")
    elif "order" in stages and policy.order is Order.STRICT:
        body.append("if tv <= last_tv:\n    n_order += 1\n    continue")
    if "bounds" in stages and (policy.lower is not None or policy.upper is not None):
        tests = []
        if policy.lower is not None:
            consts["LO"] = policy.lower
            tests.append("v < LO")
        if policy.upper is not None:
            consts["HI"] = policy.upper
            tests.append("v > HI")
        body.append(
            "try:\n"
            f"    if {' or '.join(tests)}:\n"
            "        n_bounds += 1\n"
            "        continue\n"
            "except TypeError:\n"
            "    n_type += 1\n"
            "    continue"
        )
    kind = policy.change.kind
    if "change" in stages and kind is ChangeKind.ANY_CHANGE:
        body.append("if v == last_v:\n    n_change += 1\n    continue")
    elif "change" in stages and kind is not ChangeKind.ANY_UPDATE:
        consts["DELTA"] = policy.change.delta
        if kind is ChangeKind.ABSOLUTE:
            test = "abs(v - last_v) <= DELTA"
        else:
            # relative to the last emitted value; from zero any non-zero value is a change
            test = "(abs(v - last_v) / abs(last_v) <= DELTA) if last_v else v == last_v"
        body.append(
            "if last_v is not MISSING:\n"
            "    try:\n"
            f"        if {test}:\n"
            "            n_change += 1\n"
            "            continue\n"
            "    except TypeError:\n"
            "        n_type += 1\n"
            "        continue"
        )
    emits = "emit" in stages
    prologue = ""
    if mapper is not None and emits:
        consts["FN"] = mapper.fn
        consts["FAIL"] = mapper.fail
        consts["NEXT_TA"] = mapper.next_ta
        prologue = "    out_ta = NEXT_TA(batch)\n"
        body.append(
            "last_tv = tv\n"
            "last_v = v\n"
            "try:\n"
            "    r = FN(v)\n"
            "except Exception as exc:\n"
            "    FAIL(exc)\n"
            "    continue\n"
            "if r is not None:\n"
            "    append((r, tv, out_ta))\n"
            "    out_ta += 1"
        )
    elif emits:
        body.append("append(s)\nlast_tv = tv\nlast_v = v")
    elif "order" in stages and policy.order is not Order.ANY:
        body.append("append(s)\nlast_tv = tv")
    else:
        body.append("append(s)")
    loop = "\n".join(body)
    inner = "\n".join("        " + line for line in loop.splitlines())
    src = (
        "def run(self, batch, out):\n"
        "    append = out.append\n"
        f"    last_tv = self.{order_attr}\n"
        "    last_v = self.last_value\n"
        "    n_window = n_late = n_order = n_bounds = n_change = n_type = 0\n"
        f"{prologue}"
        "    for s in batch:\n"
        "        v, tv, ta = s\n"
        f"{inner}\n"
        "    st = self.stats\n"
        "    if n_window: st.window += n_window\n"
        "    if n_late: st.late += n_late\n"
        "    if n_order: st.order += n_order\n"
        "    if n_bounds: st.bounds += n_bounds\n"
        "    if n_change: st.change += n_change\n"
        "    if n_type: st.type += n_type\n"
        f"    self.{order_attr} = last_tv\n"
        "    self.last_value = last_v\n"
    )
    namespace: dict[str, Any] = dict(consts)
    exec(compile(src, f"<policy-filter {'/'.join(stages)}>", "exec"), namespace)
    return namespace["run"]


def _within_bounds(policy: Policy, value: Any) -> bool:
    """Whether ``value`` passes the policy's bounds (a value that cannot compare does not)."""
    try:
        if policy.lower is not None and value < policy.lower:
            return False
        return not (policy.upper is not None and value > policy.upper)
    except TypeError:
        return False


def _is_identity(policy: Policy) -> bool:
    """Whether the policy lets every sample through unchanged."""
    return (
        policy.start is None
        and policy.end is None
        and policy.sample_period is None
        and policy.max_delay is None
        and policy.order is Order.ANY
        and policy.change.kind is ChangeKind.ANY_UPDATE
        and policy.lower is None
        and policy.upper is None
    )


class _Sampler:
    """Turns accepted samples into one sample per period on a grid of valid times."""

    __slots__ = (
        "approx",
        "before",
        "end",
        "g",
        "late_approx",
        "maxd",
        "period",
        "start",
        "stats",
    )

    def __init__(self, policy: Policy, stats: FilterStats) -> None:
        assert policy.sample_period is not None
        self.period = seconds_to_ns(policy.sample_period)
        self.approx = policy.approximation
        self.maxd = None if policy.max_delay is None else seconds_to_ns(policy.max_delay)
        self.late_approx = policy.late is LateAction.APPROXIMATE
        self.end = policy.end
        self.start = policy.start
        self.g: int | None = None  # the next grid point not yet decided
        self.before: RawSample | None = None  # the newest sample with valid time < g
        self.stats = stats

    def _first_grid(self, tv: int) -> int:
        p = self.period
        return -((-tv) // p) * p  # ceil to the grid anchored at time 0

    def _value(self, g: int, after: RawSample | None) -> tuple[bool, Any]:
        """The value at grid point ``g`` per the approximation; ``after`` is None at a deadline."""
        b = self.before
        a = self.approx
        if a is Approximation.NONE:
            if b is not None and b[1] > g - self.period:
                return True, b[0]
            return False, None
        if a is Approximation.MOST_RECENT:
            return (True, b[0]) if b is not None else (False, None)
        if after is None:  # deadline passed: closest/linear have only the past to go on
            if self.late_approx and b is not None:
                self.stats.approximated += 1
                return True, b[0]
            return False, None
        if b is None:
            if a is Approximation.CLOSEST:
                return True, after[0]
            return False, None
        if a is Approximation.CLOSEST:
            return True, (b[0] if g - b[1] <= after[1] - g else after[0])
        try:
            t0, t1 = b[1], after[1]
            return True, b[0] + (after[0] - b[0]) * ((g - t0) / (t1 - t0))
        except TypeError:
            self.stats.type += 1
            return True, b[0]

    def deadline(self) -> int | None:
        """The time after which the next grid point is decided without waiting for data."""
        if self.maxd is None or self.g is None or self._done(self.g):
            return None
        return self.g + self.maxd

    def _done(self, g: int) -> bool:
        return self.end is not None and g > self.end

    def _skip(self, g: int, upto: int) -> int:
        """Jump over grid points below ``upto`` beyond the last ``MAX_GRID_BURST``: a gap
        must not make one publish produce millions of samples."""
        count = -((g - upto) // self.period)  # grid points g, g+p, … below upto
        if count > MAX_GRID_BURST:
            self.stats.skipped += count - MAX_GRID_BURST
            g += (count - MAX_GRID_BURST) * self.period
        return g

    def tick(self, now: int, out: list[RawSample]) -> None:
        """Decide every grid point whose max delay has passed by ``now``."""
        maxd = self.maxd
        g = self.g
        if maxd is None or g is None:
            return
        p = self.period
        if self.approx is not Approximation.NONE:
            g = self._skip(g, now - maxd)  # `none` jumps over its empty periods below
        while g + maxd < now and not self._done(g):
            if self.approx is Approximation.NONE and (
                self.before is None or self.before[1] <= g - p
            ):
                # nothing in this or later empty periods: jump to the first period that can emit
                g = max(g + p, self._first_grid(now - maxd))
                continue
            ok, v = self._value(g, None)
            if ok:
                out.append((v, g, g + maxd))
            g += p
        self.g = g

    def feed(self, batch: list[RawSample], out: list[RawSample]) -> None:
        """Advance the grid with accepted samples (in arrival order)."""
        p = self.period
        for s in batch:
            tv = s[1]
            if self.g is None:
                self.g = self._first_grid(tv if self.start is None else max(tv, self.start))
            if self.maxd is not None and self.g + self.maxd < s[2]:
                self.tick(s[2], out)
            g = self.g
            if self._done(g):
                return
            if tv < g:
                b = self.before
                if b is None or tv > b[1] or (tv == b[1] and s[2] > b[2]):
                    self.before = s
                continue
            if self.approx is Approximation.NONE:
                # only the grid point whose period holds `before` has a value; the others
                # before tv have none: jump over them (no gap is too long for this)
                b = self.before
                if b is not None and b[1] > g - p and g < tv and not self._done(g):
                    out.append((b[0], g, s[2]))
                    g += p
                g = max(g, self._first_grid(tv))
            else:
                g = self._skip(g, tv)
                while g < tv and not self._done(g):
                    ok, v = self._value(g, s)
                    if ok:
                        out.append((v, g, s[2]))
                    g += p
            if tv == g and not self._done(g):
                out.append(s)
                g += p
            self.g = g
            self.before = s


class PolicyFilter:
    """The state of one subscription's policy: what it emitted last and what it dropped."""

    __slots__ = (
        "_held",
        "_post",
        "_pre",
        "ended",
        "in_tv",
        "last_tv",
        "last_value",
        "mapper",
        "policy",
        "sampler",
        "stats",
    )
    _pre: Any
    _post: Any

    def __init__(
        self, policy: Policy, previous: PolicyFilter | None = None, mapper: Mapper | None = None
    ) -> None:
        self.policy = policy
        if mapper is None and previous is not None:
            mapper = previous.mapper
        self.mapper: Mapper | None = mapper
        self.stats: FilterStats = previous.stats if previous is not None else FilterStats()
        # a replaced policy continues the emitted stream: order and change stay honoured
        self.last_tv: int = previous.last_tv if previous is not None else _NEG_INF
        self.last_value: Any = previous.last_value if previous is not None else MISSING
        # with a sample period, order applies to the inputs before the grid: the valid time
        # of the last input admitted to it (the grid's own output always increases)
        self.in_tv: int = (
            _NEG_INF
            if previous is None
            else previous.in_tv
            if previous.sampler is not None
            else previous.last_tv
        )
        self.ended = False
        # the previous grid's sample still waiting for a grid point: fed to ours first
        self._held: list[RawSample] = []
        if policy.sample_period is None:
            self.sampler: _Sampler | None = None
            self._pre = (
                None
                if _is_identity(policy) and mapper is None
                else _compile(
                    policy,
                    stages=("window", "late", "order", "bounds", "change", "emit"),
                    mapper=mapper,
                )
            )
            self._post = None
        else:
            self.sampler = _Sampler(policy, self.stats)
            if previous is not None and previous.last_tv != _NEG_INF:
                # continue the emitted stream: the next grid point after the last emitted
                # sample, which also serves as the most recent value before it
                first = previous.last_tv + 1
                if policy.start is not None:
                    first = max(first, policy.start)
                self.sampler.g = self.sampler._first_grid(first)
                before = (previous.last_value, previous.last_tv, previous.last_tv)
                if _within_bounds(policy, before[0]):
                    self.sampler.before = before
            pending = previous._waiting() if previous is not None else None
            if pending is not None and _within_bounds(policy, pending[0]):
                maxd = policy.max_delay
                if maxd is None or pending[2] - pending[1] <= seconds_to_ns(maxd):
                    # a newer sample was waiting for the next grid point: it still decides
                    # it, fed to this grid as it came (when this policy admits it). Not as
                    # `before`: that is older than the grid's next point, and our grid
                    # points before it lie between the last one emitted and it
                    # (interpolated, not extrapolated from it)
                    self._held = [pending]
            # the window applies to grid times (in the sampler), not to the inputs: the
            # sample just before `start` or just after `end` decides the edge grid points.
            # Order is the contract's: applied to the inputs, before the grid.
            self._pre = _compile(policy, stages=("late", "order", "bounds"), order_attr="in_tv")
            self._post = _compile(policy, stages=("change", "emit"), mapper=mapper)

    def _waiting(self) -> RawSample | None:
        """The sample newer than the last one emitted that waits for a grid point, or None.

        Still held for the grid (no batch or tick since this policy replaced another), or
        the grid's sample before its next point.
        """
        if self._held:
            return self._held[0]
        pending = self.sampler.before if self.sampler is not None else None
        if pending is not None and pending[1] > self.last_tv:
            return pending
        return None

    def process(self, batch: list[RawSample]) -> list[RawSample]:
        """Apply the policy to a batch of newly available samples; return what to emit.

        Once the policy has ended (past ``end``) nothing more is emitted, whatever comes.
        """
        out: list[RawSample] = []
        if self.ended:
            return out
        if self._pre is None:
            # the identity policy: nothing to test, only remember where the stream is
            if not batch:
                return []
            last = batch[-1]
            self.last_tv = last[1]
            self.last_value = last[0]
            self.stats.emitted += len(batch)
            return batch
        if self.sampler is None:
            self._pre(self, batch, out)
        else:
            accepted, self._held = self._held, []
            self._pre(self, batch, accepted)
            grid: list[RawSample] = []
            self.sampler.feed(accepted, grid)
            if self.sampler.end is not None and self.sampler.g is not None:
                self.ended = self.ended or self.sampler._done(self.sampler.g)
            if grid:
                self._post(self, grid, out)
        self.stats.emitted += len(out)
        return out

    def tick(self, now: int) -> list[RawSample]:
        """Emit grid points whose max delay passed by ``now`` (periodic policies only)."""
        out: list[RawSample] = []
        if self.sampler is not None and not self.ended:
            grid: list[RawSample] = []
            if self._held:
                held, self._held = self._held, []
                self.sampler.feed(held, grid)
            self.sampler.tick(now, grid)
            g = self.sampler.g
            if g is not None and self.sampler._done(g):
                self.ended = True  # time passed `end`: the subscription is over
            if grid:
                self._post(self, grid, out)
            self.stats.emitted += len(out)
        return out

    def deadline(self) -> int | None:
        """When this filter next needs a tick, or None."""
        return self.sampler.deadline() if self.sampler is not None else None
