"""Process refinement (focus of attention): lower rates or suspend processes under load.

A ``Refinement`` declares what to watch — a stream's delay (available − valid time) over
the samples published in the last ``window`` seconds, or the backlog of an async
computational unit — a ``threshold`` and a lower ``restore_below`` threshold with a
``hold`` time (hysteresis, so it does not flap), and what to do: replace the policy of
chosen subscriptions with a degraded one, and/or suspend low-priority computational
units. A ``RefinementProcess`` evaluates it on every observed sample and periodically
on the instance clock, applies and restores it, and publishes each change as an event
(``{"state": "degraded" | "restored", "metric": …, "value": …}``).
"""

from __future__ import annotations

import asyncio
import math
import weakref
from collections import deque
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal, Self

from pydantic import field_validator, model_validator

from .._aio import sleep_until_woken
from .._exceptions import PolicyError, ProcessError
from .._policy import CacheSpec, Policy, _EdgeModel, check_duration
from .._process import ComputationalUnit, Process
from .._sample import RawSample
from .._stream import StreamGenerator, Subscription
from .._time import NS_PER_S, seconds_to_ns

if TYPE_CHECKING:
    from .._instance import DyKnowInstance

Statistic = Literal["mean", "max", "p50", "p90", "p95", "p99"]
_QUANTILES = {"p50": 0.5, "p90": 0.9, "p95": 0.95, "p99": 0.99}
# A stream publishing thousands of samples a second would make the window unbounded: the
# most recent ones are representative enough.
_MAX_WINDOW_SAMPLES = 100_000


class RateChange(_EdgeModel):
    """Which subscriptions to slow down: the inputs of a process, and the degraded policy.

    ``input`` picks one input label of the computational unit ``process`` (default: all
    of them). Give either a whole replacement ``policy`` or just a ``sample_period`` (s),
    which replaces that field of the subscription's policy at the time of degradation.
    """

    process: str
    input: str | None = None
    policy: Policy | None = None
    sample_period: float | None = None

    @field_validator("sample_period")
    @classmethod
    def _period(cls, v: float | None) -> float | None:
        return None if v is None else check_duration("sample_period", v, minimum=1e-9)

    @model_validator(mode="after")
    def _one_policy(self) -> Self:
        if (self.policy is None) == (self.sample_period is None):
            raise PolicyError("policy", "give exactly one of policy or sample_period")
        return self

    def degrade(self, current: Policy) -> Policy:
        """The policy a subscription currently read with ``current`` is degraded to."""
        if self.policy is not None:
            return self.policy
        return current.replace(sample_period=self.sample_period)


class Refinement(_EdgeModel):
    """A declarative refinement: what to watch, when to act and restore, and what to do.

    Watch exactly one of ``stream`` (its delay, by ``statistic`` over the samples made
    available in the last ``window`` seconds; ``threshold`` in seconds) or ``unit`` (the
    samples queued for an async computational unit; ``threshold`` in samples). Degrade when
    the value exceeds ``threshold``; restore when it stays below ``restore_below``
    (default: ``threshold``) for ``hold`` seconds. ``period`` (s) is how often it is
    evaluated on the instance clock besides on every observed sample.
    """

    name: str
    stream: str | None = None
    unit: str | None = None
    statistic: Statistic = "p90"
    window: float = 1.0
    threshold: float
    restore_below: float | None = None
    hold: float = 1.0
    period: float = 0.5
    lower_rate: tuple[RateChange, ...] = ()
    suspend: tuple[str, ...] = ()

    @field_validator("name")
    @classmethod
    def _named(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("a refinement needs a non-empty name")
        return v

    @field_validator("window")
    @classmethod
    def _window(cls, v: float) -> float:
        return check_duration("window", v, minimum=1e-9)

    @field_validator("period")
    @classmethod
    def _period(cls, v: float) -> float:
        return check_duration("period", v, minimum=1e-6)

    @field_validator("hold")
    @classmethod
    def _hold(cls, v: float) -> float:
        return check_duration("hold", v, minimum=0.0)

    @field_validator("threshold", "restore_below")
    @classmethod
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ValueError(f"must be finite and >= 0, got {v}")
        return v

    @model_validator(mode="after")
    def _coherent(self) -> Self:
        if (self.stream is None) == (self.unit is None):
            raise PolicyError("stream", "watch exactly one of stream (delay) or unit (backlog)")
        if self.restore_below is not None and self.restore_below > self.threshold:
            raise PolicyError(
                "restore_below",
                f"must not exceed threshold {self.threshold}, got {self.restore_below}",
            )
        if not self.lower_rate and not self.suspend:
            raise PolicyError("lower_rate", "a refinement needs lower_rate and/or suspend")
        return self

    @property
    def low(self) -> float:
        """The threshold the value must stay below (for ``hold``) to restore."""
        return self.threshold if self.restore_below is None else self.restore_below

    @property
    def metric(self) -> str:
        """What is watched, as reported in events: ``delay_p90`` or ``backlog``."""
        return f"delay_{self.statistic}" if self.stream is not None else "backlog"


# -- suspending computational units -------------------------------------------------------


class _Suspension:
    """How many refinements hold a unit suspended, and what it was reading with."""

    __slots__ = ("count", "policies")

    def __init__(self) -> None:
        self.count = 0
        self.policies: list[Policy] = []


def _discard(batch: list[RawSample]) -> None:
    """The callback of a suspended unit's closed input subscription."""


_suspended: weakref.WeakKeyDictionary[ComputationalUnit, _Suspension] = weakref.WeakKeyDictionary()


def is_suspended(cu: ComputationalUnit) -> bool:
    """Whether some refinement holds ``cu`` suspended."""
    s = _suspended.get(cu)
    return s is not None and s.count > 0


def suspend_unit(cu: ComputationalUnit) -> None:
    """Pause ``cu``: close its input subscriptions and drop its queued backlog.

    The core has no pause, so the unit stops being fed; suspensions nest (the unit
    resumes when every suspender has resumed it).
    """
    s = _suspended.setdefault(cu, _Suspension())
    s.count += 1
    if s.count > 1:
        return
    s.policies = [sub.policy for sub in cu.subscriptions]
    for sub in cu.subscriptions:
        sub.close()
        # a publish in progress still hands this batch to the closed subscription
        sub.callback = _discard
    # a paused unit must not compute stale input
    cu._pending.clear()


def resume_unit(cu: ComputationalUnit) -> None:
    """Undo one ``suspend_unit``: the last one re-subscribes its inputs with their policies."""
    s = _suspended.get(cu)
    if s is None or s.count == 0:
        return
    s.count -= 1
    if s.count > 0 or not cu.running:
        return
    now = cu.instance.clock.now()
    subs: list[Subscription] = []
    for idx, (inp, policy) in enumerate(zip(cu.inputs, s.policies, strict=True)):
        if policy.start is not None and policy.start <= now:
            # a past start would replay the cache: the unit resumes with new samples only
            policy = policy.replace(start=None)
        subs.append(
            cu.instance.subscribe(
                inp.label, policy, callback=cu._callback(idx), mapper=cu._mapper()
            )
        )
    cu.subscriptions = subs


# -- what is watched -------------------------------------------------------------------------


class _DelayWindow:
    """The delays of the samples made available in the last window, with running counts.

    Counting the delays above each threshold as samples come and go decides "is the
    quantile above it" in O(1) per sample; the statistic itself is only computed for
    the events.
    """

    def __init__(self, r: Refinement) -> None:
        self.window = seconds_to_ns(r.window)
        self.hi = seconds_to_ns(r.threshold)
        self.lo = seconds_to_ns(r.low)
        self.statistic = r.statistic
        self.items: deque[tuple[int, int]] = deque()  # (available time, delay ns)
        self.total = 0
        self.above_hi = 0  # delay > hi
        self.at_or_above_lo = 0  # delay >= lo

    def add(self, batch: list[RawSample]) -> None:
        items = self.items
        for _, tv, ta in batch:
            d = ta - tv
            items.append((ta, d))
            self.total += d
            self.above_hi += d > self.hi
            self.at_or_above_lo += d >= self.lo
        while len(items) > _MAX_WINDOW_SAMPLES:
            self._pop()

    def _pop(self) -> None:
        _, d = self.items.popleft()
        self.total -= d
        self.above_hi -= d > self.hi
        self.at_or_above_lo -= d >= self.lo

    def trim(self, now: int) -> None:
        cutoff = now - self.window
        items = self.items
        while items and items[0][0] <= cutoff:
            self._pop()

    def _needed(self, n: int) -> int:
        """How many samples must be at or above a value for the statistic to be too."""
        if self.statistic == "max":
            return 1
        q = _QUANTILES[self.statistic]
        rank = max(1, math.ceil(q * n - 1e-9))  # nearest rank, 1-based
        return n - rank + 1

    def above(self) -> bool:
        n = len(self.items)
        if n == 0:
            return False
        if self.statistic == "mean":
            return self.total > self.hi * n
        return self.above_hi >= self._needed(n)

    def below(self) -> bool:
        n = len(self.items)
        if n == 0:
            return True  # nothing made available in the window: no load to relieve
        if self.statistic == "mean":
            return self.total < self.lo * n
        return self.at_or_above_lo < self._needed(n)

    def value(self) -> float | None:
        """The statistic in seconds (None when the window is empty)."""
        n = len(self.items)
        if n == 0:
            return None
        if self.statistic == "mean":
            return self.total / n / NS_PER_S
        ds = sorted(d for _, d in self.items)
        if self.statistic == "max":
            return ds[-1] / NS_PER_S
        return ds[n - self._needed(n)] / NS_PER_S


class _Target:
    """One subscription to slow down, found afresh each time (a resumed unit has new ones)."""

    def __init__(
        self,
        sub: Subscription | None,
        change: RateChange | None,
        policy: Policy | None,
        unit: ComputationalUnit | None = None,
        index: int = 0,
    ) -> None:
        self.sub = sub  # a subscription given directly
        self.change = change
        self.policy = policy
        self.unit = unit  # or the index-th input of a unit
        self.index = index
        self.original: Policy | None = None
        self.degraded: Policy | None = None

    def _live(self) -> Subscription | None:
        if self.unit is None:
            sub = self.sub
        else:
            subs = self.unit.subscriptions
            sub = subs[self.index] if self.index < len(subs) else None
        return None if sub is None or sub.closed else sub

    def current(self) -> Policy | None:
        """The policy the subscription is read with (kept aside while its unit is suspended)."""
        sub = self._live()
        if sub is not None:
            return sub.policy
        if self.unit is not None and is_suspended(self.unit):
            return _suspended[self.unit].policies[self.index]
        return None

    def set(self, policy: Policy) -> None:
        """Read the subscription with ``policy`` (or resume the suspended unit with it)."""
        sub = self._live()
        if sub is not None:
            sub.replace_policy(policy)
        elif self.unit is not None and is_suspended(self.unit):
            _suspended[self.unit].policies[self.index] = policy

    def degraded_policy(self, current: Policy) -> Policy:
        """The policy this target is degraded to from ``current``."""
        if self.change is not None:
            return self.change.degrade(current)
        assert self.policy is not None
        return self.policy


# -- the process ------------------------------------------------------------------------------


class RefinementProcess(Process):
    """Watches a delay or a backlog and degrades/restores per its ``Refinement``; emits events."""

    kind = "refinement"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        refinement: Refinement,
        output: StreamGenerator,
        targets: list[_Target],
        units: list[ComputationalUnit],
    ) -> None:
        super().__init__(name, instance)
        self.refinement = refinement
        self.output = output
        self.label = output.label
        self.degraded = False
        self.changes = 0
        self.last_value: float | None = None
        self._targets = targets
        self._units = units
        self._suspended: list[ComputationalUnit] = []
        self._window = _DelayWindow(refinement) if refinement.stream is not None else None
        self._watched: ComputationalUnit | None = None
        self._observers: list[Subscription] = []
        self._below_since: int | None = None
        self._period = seconds_to_ns(refinement.period)
        self._hold = seconds_to_ns(refinement.hold)
        self._wake = asyncio.Event()

    # -- observing ---------------------------------------------------------------------
    def _on_samples(self, batch: list[RawSample]) -> None:
        if not self.running:
            return
        if self._window is not None:
            self._window.add(batch)
        self.evaluate()

    def _backlog(self) -> int:
        cu = self._watched
        return 0 if cu is None else sum(len(b) for _, b in cu._pending)

    def current_value(self) -> float | None:
        """The watched value now: the delay statistic (s) or the backlog (samples)."""
        if self._window is not None:
            self._window.trim(self.instance.clock.now())
            return self._window.value()
        return float(self._backlog())

    def _above_below(self) -> tuple[bool, bool]:
        r = self.refinement
        if self._window is not None:
            self._window.trim(self.instance.clock.now())
            return self._window.above(), self._window.below()
        b = self._backlog()
        return b > r.threshold, b < r.low

    # -- deciding ---------------------------------------------------------------------
    def evaluate(self) -> bool | None:
        """Check the watched value once; returns True/False when it degraded/restored."""
        if not self.running:
            return None
        try:
            above, below = self._above_below()
            now = self.instance.clock.now()
            if not self.degraded:
                if above:
                    self._degrade()
                    return True
                return None
            if not below:
                self._below_since = None
                return None
            if self._below_since is None:
                self._below_since = now
                self._wake.set()  # the loop must wake when the hold time is over
            if now - self._below_since >= self._hold:
                self._restore()
                return False
        except Exception as exc:
            self._fail(exc)
        return None

    def _degrade(self) -> None:
        self.degraded = True
        self._below_since = None
        for t in self._targets:
            current = t.current()
            if current is None:
                continue
            new = t.degraded_policy(current)
            t.set(new)
            t.original, t.degraded = current, new
        for cu in self._units:
            if cu.running:
                suspend_unit(cu)
                self._suspended.append(cu)
        self._event("degraded")

    def _restore(self) -> None:
        self.degraded = False
        self._below_since = None
        for t in self._targets:
            original, degraded = t.original, t.degraded
            t.original = t.degraded = None
            # someone else replaced the policy meanwhile: theirs stands
            if original is not None and t.current() is degraded:
                t.set(original)
        suspended, self._suspended = self._suspended, []
        for cu in suspended:
            resume_unit(cu)
        self._event("restored")

    def _event(self, state: str) -> None:
        r = self.refinement
        value = self.current_value()
        self.last_value = value
        self.changes += 1
        now = self.instance.clock.now()
        event = {
            "state": state,
            "metric": r.metric,
            "target": r.stream if r.stream is not None else r.unit,
            "value": value,
            "threshold": r.threshold if state == "degraded" else r.low,
        }
        if not self.output.closed:
            self.output.publish(event, now, max(now, self.output.last_available_time + 1))

    # -- running ------------------------------------------------------------------------
    async def _run(self) -> None:
        """Evaluate every period on the instance clock (and when a hold time ends)."""
        clock = self.instance.clock
        while self.running:
            self._wake.clear()
            now = clock.now()
            due = now + self._period
            if self._below_since is not None:
                due = min(due, max(now + 1, self._below_since + self._hold))
            await sleep_until_woken(clock, due, self._wake)
            if self.running and clock.now() >= due:
                self.evaluate()

    def _stop(self) -> None:
        if self.degraded:
            try:
                self._restore()
            except Exception as exc:
                self._fail(exc)
        super()._stop()
        for sub in self._observers:
            sub.close()
        self._wake.set()

    def describe(self) -> dict[str, Any]:
        """Adds the refinement, its state and the last reported value to the description."""
        d = super().describe()
        r = self.refinement
        d["output"] = self.label
        d["metric"] = r.metric
        d["target"] = r.stream if r.stream is not None else r.unit
        d["state"] = "degraded" if self.degraded else "normal"
        d["changes"] = self.changes
        d["last_value"] = self.last_value
        return d


FocusOfAttention = RefinementProcess


def _cu(instance: DyKnowInstance, name: str, field: str) -> ComputationalUnit:
    proc = instance.processes.get(name)
    if proc is None:
        raise PolicyError(field, f"no process named {name!r}")
    if not isinstance(proc, ComputationalUnit):
        raise PolicyError(field, f"process {name!r} is a {proc.kind}, not a computational unit")
    return proc


def _targets(
    instance: DyKnowInstance,
    r: Refinement,
    subscriptions: Mapping[Subscription, Policy | Mapping[str, Any]] | None,
) -> list[_Target]:
    out: list[_Target] = []
    for k, change in enumerate(r.lower_rate):
        cu = _cu(instance, change.process, f"lower_rate.{k}.process")
        idxs = [i for i, inp in enumerate(cu.inputs) if change.input in (None, inp.label)]
        if not idxs:
            raise PolicyError(
                f"lower_rate.{k}.input",
                f"{change.process!r} reads no input {change.input!r} "
                f"(it reads {[i.label for i in cu.inputs]})",
            )
        for i in idxs:
            gen = instance.stream(cu.inputs[i].label)
            if change.policy is not None:
                try:
                    gen._check_policy(change.policy)
                except PolicyError as exc:
                    raise PolicyError(f"lower_rate.{k}.policy.{exc.field}", exc.reason) from None

            out.append(_Target(None, change, None, cu, i))
    for sub, p in (subscriptions or {}).items():
        policy = Policy.parse(p)
        sub.generator._check_policy(policy)
        out.append(_Target(sub, None, policy))
    return out


def add_refinement(
    instance: DyKnowInstance,
    refinement: Refinement | Mapping[str, Any],
    *,
    output: str | None = None,
    name: str | None = None,
    subscriptions: Mapping[Subscription, Policy | Mapping[str, Any]] | None = None,
    cache: CacheSpec | None = None,
) -> RefinementProcess:
    """Add a focus-of-attention process applying ``refinement``; events go to ``output``.

    ``output`` defaults to ``events/refinement/<name>``; ``subscriptions`` adds live
    subscriptions (an application's, not a process's) to degrade, each to its policy.
    Removing the process restores everything it degraded or suspended.
    """
    r = Refinement.parse(refinement)
    name = name or f"refinement:{r.name}"
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    output = output or f"events/refinement/{r.name}"
    watched: ComputationalUnit | None = None
    if r.stream is not None:
        instance.stream(r.stream)  # an unknown label fails before anything is created
        if output == r.stream:
            raise PolicyError("stream", "a refinement cannot publish on the stream it watches")
    else:
        assert r.unit is not None
        watched = _cu(instance, r.unit, "unit")
    targets = _targets(instance, r, subscriptions)
    units = [_cu(instance, n, f"suspend.{k}") for k, n in enumerate(r.suspend)]
    out = instance.create_stream(output, cache=cache, value_type=dict)
    proc = RefinementProcess(name, instance, r, out, targets, units)
    proc._watched = watched
    try:
        labels = [r.stream] if r.stream is not None else []
        if watched is not None:
            labels = [i.label for i in watched.inputs]
        for label in dict.fromkeys(labels):
            proc._observers.append(instance.subscribe(label, callback=proc._on_samples))
    except Exception:
        proc._stop()
        instance.remove_stream(output)
        raise
    instance.add_process(proc)
    instance.spawn(f"refinement[{name}]", proc._run())
    return proc
