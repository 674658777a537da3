"""States: several streams of different rates and delays synchronized into one stream.

A state process subscribes to each component stream with a periodic policy (one sample
per period, filled per the state policy's strategy, approximated once the max delay has
passed), so the core's filter does the per-component sampling. It then joins the
components' grid samples by valid time and publishes one sample per grid point whose
value is a ``dict`` mapping component name to value, in the order the components were
given.

A grid point is decided, strictly in valid-time order, as soon as every component has a
value for it (data-driven), or every component without one has moved past it (it starts
later, or its stream ended), or its max delay has passed (time-driven). A component still
without a value then is *missing* and the state policy's ``missing`` says what happens. A
grid point at which no component has a value is never a state.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import contextlib
from collections.abc import Callable, Mapping
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Self

from pydantic import field_validator, model_validator

from ._aio import sleep_until_woken
from ._exceptions import PolicyError, ProcessError, UnknownLabelError
from ._policy import Approximation, CacheSpec, LateAction, Policy, _EdgeModel, check_duration
from ._process import Process
from ._sample import RawSample
from ._stream import StreamGenerator, Subscription
from ._time import seconds_to_ns

if TYPE_CHECKING:
    from ._instance import DyKnowInstance

_NEG_INF = -(2**63)


class StateStrategy(StrEnum):
    """How each component gets its value at a grid point without an exact sample."""

    LATEST = "latest"
    CLOSEST = "closest"
    INTERPOLATE = "interpolate"

    @property
    def approximation(self) -> Approximation:
        """The per-component approximation this strategy subscribes with."""
        return _APPROXIMATION[self]


_APPROXIMATION = {
    StateStrategy.LATEST: Approximation.MOST_RECENT,
    StateStrategy.CLOSEST: Approximation.CLOSEST,
    StateStrategy.INTERPOLATE: Approximation.LINEAR,
}


class Missing(StrEnum):
    """What a state does with a component that has no value when its grid point is decided."""

    SKIP = "skip"
    NONE = "none"
    LAST = "last"


class StatePolicy(_EdgeModel):
    """How a state synchronizes its components: period, strategy, max delay, missing values.

    ``period`` (s) puts one state per period on a grid of valid times anchored at time 0.
    ``strategy`` fills a component's value at a grid point: the latest sample before it,
    the closest one, or linear interpolation. ``max_delay`` (s), when set, bounds how long
    a grid point waits for its components: once it has passed, components are
    approximated from what they have and those with nothing are ``missing``: the state
    is skipped, the component is None, or it takes its last known value (the newest
    sample at or before the grid point available by then, from the location's cache).
    ``start``/``end`` (ns) bound the valid times of the states.
    """

    period: float
    strategy: StateStrategy = StateStrategy.LATEST
    max_delay: float | None = None
    missing: Missing = Missing.SKIP
    start: int | None = None
    end: int | None = None

    @field_validator("period")
    @classmethod
    def _positive_period(cls, v: float) -> float:
        return check_duration("period", v, minimum=1e-9)

    @field_validator("max_delay")
    @classmethod
    def _non_negative_delay(cls, v: float | None) -> float | None:
        return None if v is None else check_duration("max_delay", v, minimum=0.0)

    @model_validator(mode="after")
    def _coherent(self) -> Self:
        if self.start is not None and self.end is not None and self.start > self.end:
            raise PolicyError("start", f"start {self.start} is after end {self.end}")
        return self

    def component_policy(self) -> Policy:
        """The periodic policy each component stream is subscribed with."""
        timed = self.max_delay is not None
        return Policy(
            start=self.start,
            end=self.end,
            sample_period=self.period,
            approximation=self.strategy.approximation,
            max_delay=self.max_delay,
            late=LateAction.APPROXIMATE if timed else LateAction.DROP,
        )


class StateStats:
    """Counts of what a state process decided: emitted, skipped, filled, forced, late."""

    __slots__ = ("emitted", "filled", "forced", "late", "skipped")

    def __init__(self) -> None:
        self.emitted = self.skipped = self.filled = self.forced = self.late = 0

    def as_dict(self) -> dict[str, int]:
        """A plain snapshot for metrics and reports."""
        return {k: getattr(self, k) for k in self.__slots__}


class _Unset:
    """Marks a component without a value at a grid point (None is a legitimate value)."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "<unset>"


_UNSET: Any = _Unset()


class _Row:
    """The component values gathered so far for one grid point."""

    __slots__ = ("n", "ta", "values")

    def __init__(self, size: int) -> None:
        self.values: list[Any] = [_UNSET] * size
        self.n = 0
        self.ta = _NEG_INF


class StateProcess(Process):
    """Publishes one stream of named value vectors, all valid at the same grid time point.

    Each state is a sample whose value is a fresh ``dict`` (component name → value),
    whose valid time is on the period grid, strictly increasing, and whose available time
    is when its last needed input became available — never more than ``max_delay`` after
    the valid time when a max delay is set (a grid point decided by its deadline is
    available at valid time + max delay, like the core's periodic streams).
    """

    kind = "state"
    #: Grid points that may wait for components at once; beyond it the oldest is decided
    #: with what it has (counted in ``stats.forced``), so a silent component without a
    #: max delay cannot make the process grow without bound.
    max_pending = 10_000

    def __init__(
        self,
        name: str,
        instance: "DyKnowInstance",
        components: Mapping[str, str],
        policy: StatePolicy,
        output: StreamGenerator,
    ) -> None:
        super().__init__(name, instance)
        self.components = dict(components)
        self.names = tuple(self.components)
        self.policy = policy
        self.output = output
        self.label = output.label
        self.subscriptions: list[Subscription] = []
        self.stats = StateStats()
        self._gens = [instance.stream(label) for label in self.components.values()]
        self._size = len(self.names)
        self._period = seconds_to_ns(policy.period)
        self._maxd = None if policy.max_delay is None else seconds_to_ns(policy.max_delay)
        self._end = policy.end
        self._missing = policy.missing
        self._rows: dict[int, _Row] = {}
        self._progress = [_NEG_INF] * self._size  # newest grid point each component emitted
        self._g: int | None = None  # the next grid point to decide
        self._fixed = False  # once a grid point is decided, earlier ones can never be
        self._last_ta = _NEG_INF
        self._wake = asyncio.Event()

    # -- fed by the component subscriptions ----------------------------------------
    def _subscribe(self) -> None:
        """Subscribe to every component; a past ``start`` replays history right here."""
        policy = self.policy.component_policy()
        for index, label in enumerate(self.components.values()):
            self.subscriptions.append(
                self.instance.subscribe(label, policy, callback=self._callback(index))
            )

    def _callback(self, index: int) -> Callable[[list[RawSample]], None]:
        return lambda batch: self._on_samples(index, batch)

    def _on_samples(self, index: int, batch: list[RawSample]) -> None:
        """Gather one component's grid samples, then decide what became decidable."""
        if not self.running:
            return
        rows = self._rows
        progress = self._progress
        size = self._size
        for v, tv, ta in batch:
            g = self._g
            if g is None or tv < g:
                if self._fixed:
                    # its grid point was decided already (its max delay passed)
                    self.stats.late += 1
                    continue
                self._g = tv
                if self._maxd is not None:
                    self._wake.set()  # the timer's deadline moved earlier
            row = rows.get(tv)
            if row is None:
                row = rows[tv] = _Row(size)
            if row.values[index] is _UNSET:
                row.n += 1
            row.values[index] = v
            if ta > row.ta:
                row.ta = ta
            if tv > progress[index]:
                progress[index] = tv
        if batch:
            self._drain(batch[-1][2], None)

    def _passed(self, row: _Row | None, g: int) -> bool:
        """Whether every component without a value at ``g`` has moved past it (or ended)."""
        subs = self.subscriptions
        for i in range(self._size):
            if row is not None and row.values[i] is not _UNSET:
                continue
            if self._progress[i] > g:
                continue
            if i < len(subs) and subs[i].closed:
                continue
            return False
        return True

    def _drain(self, hint: int, now: int | None) -> None:
        """Decide grid points in order while they are decidable; publish the states.

        ``hint`` is when the information that triggered this became available; ``now``
        is given by the timer, which may decide grid points whose max delay passed.
        """
        g = self._g
        if g is None:
            return
        p = self._period
        maxd = self._maxd
        end = self._end
        rows = self._rows
        size = self._size
        out: list[RawSample] = []
        while end is None or g <= end:
            row = rows.get(g)
            if row is not None and row.n == size:
                ta = row.ta
                missing = False
            else:
                if now is not None and maxd is not None and g + maxd < now:
                    ta = g + maxd
                elif self._passed(row, g):
                    ta = hint if maxd is None else min(hint, g + maxd)
                elif len(rows) > self.max_pending:
                    ta = hint if maxd is None else min(hint, g + maxd)
                    self.stats.forced += 1
                else:
                    break
                missing = True
                if row is None:
                    # nothing to emit here; jump to the next point with data or still open
                    nxt = min(rows) if rows else None
                    if now is not None and maxd is not None and g + maxd < now:
                        first_open = -((maxd - now) // p) * p  # ceil((now - maxd) / p) * p
                        nxt = first_open if nxt is None else min(nxt, first_open)
                    if nxt is None:  # cannot happen: a passing component left a row
                        break
                    g = nxt
                    self._fixed = True
                    continue
                ta = max(ta, row.ta)
            del rows[g]
            self._fixed = True
            if ta <= self._last_ta:
                ta = self._last_ta + 1  # available times are unique per stream
            values = row.values
            if missing and not self._fill(values, g, ta):
                self.stats.skipped += 1
            else:
                self._last_ta = ta
                out.append((dict(zip(self.names, values, strict=True)), g, ta))
            g += p
        self._g = g
        if out:
            self.stats.emitted += len(out)
            try:
                self.output.publish_batch(out)
            except Exception as exc:
                self._fail(exc)

    def _fill(self, values: list[Any], g: int, ta: int) -> bool:
        """Fill missing components per the policy; False when the state is to be skipped."""
        how = self._missing
        if how is Missing.SKIP:
            return False
        for i, v in enumerate(values):
            if v is not _UNSET:
                continue
            if how is Missing.NONE:
                values[i] = None
                continue
            known = self._gens[i].cache.at(g, Approximation.MOST_RECENT, as_of=ta)
            if known is None:
                return False
            values[i] = known[0]
        self.stats.filled += 1
        return True

    # -- time-driven ---------------------------------------------------------------
    def deadline(self) -> int | None:
        """When the next grid point is decided without waiting for more data, or None."""
        g = self._g
        if self._maxd is None or g is None or not self.running:
            return None
        if self._end is not None and g > self._end:
            return None
        return g + self._maxd

    def tick(self, now: int) -> None:
        """Decide every grid point whose max delay passed by ``now`` (the timer calls this)."""
        if not self.running or self._maxd is None:
            return
        # Components first, so their approximations for these grid points are in before
        # we call anything missing (the instance's ticker may not have run yet).
        for sub in self.subscriptions:
            if not sub.closed:
                try:
                    sub.tick(now)
                except Exception as exc:
                    self._fail(exc)
        self._drain(now, now)

    async def _run(self) -> None:
        """Sleep until the next deadline on the instance's clock and decide what is due."""
        clock = self.instance.clock
        wake = self._wake
        while self.running:
            wake.clear()
            d = self.deadline()
            # strictly after the deadline: data available exactly at it is on time
            await sleep_until_woken(clock, None if d is None else d + 1, wake)
            if self.running:
                self.tick(clock.now())

    # -- control -------------------------------------------------------------------
    def _stop(self) -> None:
        super()._stop()
        for sub in self.subscriptions:
            sub.close()
        self._wake.set()

    @property
    def type_errors(self) -> int:
        """Component values that could not be interpolated (the latest was used instead)."""
        return sum(sub.filter.stats.type for sub in self.subscriptions)

    def describe(self) -> dict[str, Any]:
        """Adds components, output and counters to the process description."""
        d = super().describe()
        d["components"] = dict(self.components)
        d["output"] = self.label
        d["policy"] = self.policy.model_dump(mode="json")
        d.update(self.stats.as_dict())
        d["type_errors"] = self.type_errors
        return d


def add_state(
    instance: "DyKnowInstance",
    label: str,
    components: Mapping[str, str],
    policy: StatePolicy | Mapping[str, Any],
    name: str | None = None,
    *,
    location: str | None = None,
    cache: CacheSpec | None = None,
) -> StateProcess:
    """Add a state process publishing under ``label`` the components (name → label) in sync."""
    policy = StatePolicy.parse(policy)
    name = name or f"state:{label}"
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    if not components:
        raise ProcessError(f"state {name!r} needs at least one component")
    for cname, clabel in components.items():
        if clabel == label:
            raise ProcessError(
                f"state {name!r} cannot have its own output {label!r} as a component"
            )
        gen = instance.stream(clabel)  # unknown labels fail before anything is created
        vt = gen.value_type
        if (
            policy.strategy is StateStrategy.INTERPOLATE
            and vt is not None
            and not issubclass(vt, int | float)
        ):
            raise PolicyError(
                "strategy",
                f"'interpolate' needs numeric values, but component {cname!r} "
                f"({clabel!r}) carries {vt.__name__}",
            )
    kwargs: dict[str, Any] = {"cache": cache, "value_type": dict}
    if location is not None:
        kwargs["location"] = location
    output = instance.create_stream(label, **kwargs)
    proc = StateProcess(name, instance, components, policy, output)
    try:
        proc._subscribe()
        if proc._maxd is not None:
            instance._spawn(f"state[{name}]", proc._run())
    except Exception:
        proc._stop()
        with contextlib.suppress(UnknownLabelError):  # gone already: nothing to undo
            instance.remove_stream(label)
        raise
    instance._add_process(proc)
    return proc
