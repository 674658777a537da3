"""The DyKnow instance: labels to stream generators, processes, subscriptions, queries."""

from __future__ import annotations

import asyncio
import contextlib
import fnmatch
import logging
from collections import deque
from collections.abc import AsyncIterable, Callable, Mapping, Sequence
from typing import Any

from . import _events, _state
from ._aio import sleep_until_woken
from ._events import EventProcess
from ._exceptions import ClosedError, DuplicateLabelError, ProcessError, UnknownLabelError
from ._filter import Mapper
from ._location import Location
from ._objects import ObjectManager
from ._policy import Approximation, CacheSpec, Change, Policy
from ._process import ComputationalUnit, Input, Process, ProcessFailure, Source, error_text
from ._sample import Answer, RawSample
from ._state import StatePolicy, StateProcess
from ._stream import BatchCallback, StreamGenerator, Subscription
from ._time import Clock, RealClock

DEFAULT_LOCATION = "local"

log = logging.getLogger(__name__)


class DyKnowInstance:
    """One platform's DyKnow: the facade over locations, streams and knowledge processes.

    Use it as an async context manager: entering starts the tasks it owns (async
    processes, the timer that emits periodic samples once their max delay passes);
    leaving stops them and ends every subscription. Synchronous parts (publishing,
    subscribing, queries) work without entering it.
    """

    def __init__(
        self,
        name: str = "local",
        *,
        clock: Clock | None = None,
        cache: CacheSpec | None = None,
        max_failures: int = 1000,
    ) -> None:
        self.name = name
        self.clock: Clock = clock or RealClock()
        self.locations: dict[str, Location] = {}
        self._labels: dict[str, Location] = {}
        self.processes: dict[str, Process] = {}
        self.failures: deque[ProcessFailure] = deque(maxlen=max_failures)
        self.failure_count = 0
        self._failure_listeners: list[Callable[[ProcessFailure], None]] = []
        self._label_listeners: list[Callable[[str, bool], None]] = []
        self._periodic: set[Subscription] = set()
        self._tick_wake = asyncio.Event()
        self._tg: asyncio.TaskGroup | None = None
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group
        self._pending_tasks: list[tuple[str, Any]] = []
        self._tasks: set[asyncio.Task[Any]] = set()
        self._state = "unopened"
        self.add_location(DEFAULT_LOCATION, cache=cache)
        self.objects = ObjectManager(self)

    # -- lifecycle ---------------------------------------------------------------
    async def __aenter__(self) -> DyKnowInstance:
        if self._state != "unopened":
            raise ClosedError(f"instance {self.name!r} is {self._state}; it cannot be opened again")
        self._state = "opened"
        stack = contextlib.AsyncExitStack()
        self._tg = await stack.enter_async_context(asyncio.TaskGroup())
        self._stack = stack
        self._own(self._tg.create_task(self._ticker(), name=f"dyknow[{self.name}].ticker"))
        for name, coro in self._pending_tasks:
            self._own(self._tg.create_task(coro, name=name))
        self._pending_tasks.clear()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        self._state = "closed"
        for proc in list(self.processes.values()):
            proc._stop()
        for loc in self.locations.values():
            for gen in loc.generators.values():
                gen.close()
        self.objects.close()
        stack, self._stack, self._tg = self._stack, None, None
        if stack is not None:
            for task in list(self._tasks):
                task.cancel()
            # the body's own error is not handed to the group: it would come back wrapped
            await stack.aclose()

    def spawn(self, name: str, coro: Any) -> None:
        """Run ``coro`` as a task this instance owns (named ``dyknow[<instance>].<name>``).

        For knowledge processes written outside the core: the task starts when the
        instance is entered (at once if it is running) and is cancelled when it closes.
        """
        self._spawn(name, coro)

    def _spawn(self, name: str, coro: Any) -> None:
        if self._state == "closed":
            coro.close()
            raise ClosedError(f"instance {self.name!r} is closed")
        full = f"dyknow[{self.name}].{name}"
        if self._tg is None:
            self._pending_tasks.append((full, coro))
        else:
            self._own(self._tg.create_task(coro, name=full))

    def _own(self, task: asyncio.Task[Any]) -> None:
        # only this instance's tasks are cancelled on exit, never another instance's
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- locations and labels ------------------------------------------------------
    def add_location(self, name: str, *, cache: CacheSpec | None = None) -> Location:
        """Add a location (a sensor interface, the DOR, an import location)."""
        if name in self.locations:
            raise DuplicateLabelError(f"location {name!r} exists already")
        loc = Location(name, cache=cache)
        self.locations[name] = loc
        return loc

    def create_stream(
        self,
        label: str,
        *,
        location: str = DEFAULT_LOCATION,
        cache: CacheSpec | None = None,
        value_type: type | None = None,
    ) -> StreamGenerator:
        """Publish a new stream generator under ``label`` at ``location``."""
        if label in self._labels:
            raise DuplicateLabelError(f"label {label!r} is already published")
        try:
            loc = self.locations[location]
        except KeyError:
            raise UnknownLabelError(location, list(self.locations)) from None
        gen = loc.add(label, cache=cache, value_type=value_type)
        gen.on_subscriber_error = self._subscriber_failed
        self._labels[label] = loc
        self.objects.label_created(label)  # set subscriptions waiting for this member's stream
        self._label_changed(label, True)
        return gen

    def stream(self, label: str) -> StreamGenerator:
        """The stream generator published under ``label``."""
        try:
            return self._labels[label].generators[label]
        except KeyError:
            raise UnknownLabelError(label, list(self._labels)) from None

    def has_label(self, label: str) -> bool:
        """Whether a stream is published under ``label``."""
        return label in self._labels

    def labels(self, pattern: str | None = None) -> list[str]:
        """Published labels, optionally filtered by a glob pattern (``car/*/position``)."""
        names = sorted(self._labels)
        return names if pattern is None else [n for n in names if fnmatch.fnmatchcase(n, pattern)]

    def _location_of(self, label: str) -> Location:
        try:
            return self._labels[label]
        except KeyError:
            raise UnknownLabelError(label, list(self._labels)) from None

    def remove_stream(self, label: str) -> None:
        """Close the stream under ``label`` and forget it."""
        self._location_of(label).remove(label)
        del self._labels[label]
        self._label_changed(label, False)

    def on_label_change(self, listener: Callable[[str, bool], None]) -> Callable[[], None]:
        """Be told ``(label, True)`` when a stream is published, ``(label, False)`` when it
        is removed; returns a function that stops telling."""
        # copy-on-write: a listener may stop listening while being told
        self._label_listeners = [*self._label_listeners, listener]

        def stop() -> None:
            self._label_listeners = [x for x in self._label_listeners if x is not listener]

        return stop

    def _label_changed(self, label: str, published: bool) -> None:
        for listener in self._label_listeners:
            try:
                listener(label, published)
            except Exception as exc:  # the stream exists either way: never fail its creator
                self._report_error(f"label listener[{label}]", exc)

    # -- subscriptions -------------------------------------------------------------
    def subscribe(
        self,
        label: str,
        policy: Policy | None = None,
        *,
        callback: BatchCallback | None = None,
        mapper: Mapper | None = None,
    ) -> Subscription:
        """Subscribe to ``label`` with ``policy``: an async iterator, or batches to ``callback``."""
        policy = policy or Policy()
        gen = self.stream(label)
        sub = gen.subscribe(policy, callback, self._arm, mapper)
        self._arm(sub)
        return sub

    def _arm(self, sub: Subscription) -> None:
        """Have the ticker emit ``sub``'s grid points once their max delay passes."""
        p = sub.policy
        if p.sample_period is None or p.max_delay is None:
            self._periodic.discard(sub)
            return
        self._periodic.add(sub)
        self._tick_wake.set()

    async def _ticker(self) -> None:
        """Emit periodic samples whose max delay passed (approximated or dropped per policy)."""
        clock = self.clock
        while True:
            self._tick_wake.clear()
            now = clock.now()
            soonest: int | None = None
            for sub in list(self._periodic):
                if sub.closed:
                    self._periodic.discard(sub)
                    continue
                d = sub.deadline()
                if d is not None and d < now:
                    try:
                        sub.tick(now)
                    except Exception as exc:  # a failing callback (a CU) is isolated
                        self._report_error(f"tick[{sub.label}]", exc)
                    d = sub.deadline()
                if d is not None and (soonest is None or d < soonest):
                    soonest = d
            # strictly after the deadline: data available exactly at it is on time
            wake_at = None if soonest is None else soonest + 1
            await sleep_until_woken(clock, wake_at, self._tick_wake)

    # -- processes -------------------------------------------------------------------
    def add_process(self, process: Process) -> None:
        """Register a knowledge process written outside the core (listed, removable)."""
        self._add_process(process)

    def _add_process(self, proc: Process) -> None:
        if proc.name in self.processes:
            raise ProcessError(f"a process named {proc.name!r} exists already")
        self.processes[proc.name] = proc

    def add_source(
        self,
        label: str,
        *,
        name: str | None = None,
        iterator: AsyncIterable[Any] | None = None,
        location: str = DEFAULT_LOCATION,
        cache: CacheSpec | None = None,
        value_type: type | None = None,
    ) -> Source:
        """Add a source publishing under ``label``: push to it, or give an async iterator."""
        name = name or f"source:{label}"
        if name in self.processes:
            raise ProcessError(f"a process named {name!r} exists already")
        gen = self.create_stream(label, location=location, cache=cache, value_type=value_type)
        src = Source(name, self, gen)
        self._add_process(src)
        if iterator is not None:
            self._spawn(f"source[{name}]", src._pump(iterator))
        return src

    def add_cu(
        self,
        name: str,
        fn: Callable[..., Any],
        inputs: Sequence[Input | str | tuple[str, Policy]],
        output: str,
        *,
        pass_samples: bool = False,
        location: str = DEFAULT_LOCATION,
        cache: CacheSpec | None = None,
        value_type: type | None = None,
    ) -> ComputationalUnit:
        """Add a computational unit computing ``output`` from ``inputs`` (each with a policy)."""
        if name in self.processes:
            raise ProcessError(f"a process named {name!r} exists already")
        if not inputs:
            raise ProcessError(f"computational unit {name!r} needs at least one input")
        norm = [
            i if isinstance(i, Input) else Input(i) if isinstance(i, str) else Input(*i)
            for i in inputs
        ]
        for i in norm:
            self.stream(i.label)  # unknown input labels fail before anything is created
        gen = self.create_stream(output, location=location, cache=cache, value_type=value_type)
        cu = ComputationalUnit(name, self, fn, norm, gen, pass_samples=pass_samples)
        try:
            for idx, inp in enumerate(norm):
                cu.subscriptions.append(
                    self.subscribe(
                        inp.label, inp.policy, callback=cu._callback(idx), mapper=cu._mapper()
                    )
                )
        except Exception:
            for sub in cu.subscriptions:
                sub.close()
            self.remove_stream(output)
            raise
        self._add_process(cu)
        if cu.is_async:
            self._spawn(f"cu[{name}]", cu._run_async())
        return cu

    def add_state(
        self,
        label: str,
        components: Mapping[str, str],
        policy: StatePolicy | Mapping[str, Any],
        *,
        name: str | None = None,
        location: str | None = None,
        cache: CacheSpec | None = None,
    ) -> StateProcess:
        """Synchronize component streams (name -> label) into one state stream under ``label``."""
        return _state.add_state(
            self, label, components, policy, name, location=location, cache=cache
        )

    def add_change_events(
        self,
        label: str,
        change: Change | str | Mapping[str, Any],
        *,
        output: str | None = None,
        name: str | None = None,
        policy: Policy | None = None,
        location: str | None = None,
        cache: CacheSpec | None = None,
    ) -> EventProcess:
        """Publish the changes of ``label`` per ``change`` (default ``events/changed/<label>``)."""
        return _events.add_change_events(
            self, label, change, output, name, policy=policy, location=location, cache=cache
        )

    def add_arrival_events(
        self,
        label: str,
        *,
        output: str | None = None,
        name: str | None = None,
        policy: Policy | None = None,
        location: str | None = None,
        cache: CacheSpec | None = None,
    ) -> EventProcess:
        """Publish an event per sample of ``label`` (default ``events/arrived/<label>``)."""
        return _events.add_arrival_events(
            self, label, output, name, policy=policy, location=location, cache=cache
        )

    def remove_process(self, name: str) -> None:
        """Stop a process and close the stream it published."""
        try:
            proc = self.processes.pop(name)
        except KeyError:
            raise ProcessError(f"no process named {name!r}") from None
        proc._stop()
        label = getattr(proc, "label", None) or getattr(
            getattr(proc, "output", None), "label", None
        )
        if label is not None and label in self._labels:
            self.remove_stream(label)

    # -- failures -------------------------------------------------------------------------
    def _report(self, proc: Process, error: str) -> None:
        self._record(ProcessFailure(proc.name, error, self.clock.now()))

    def _subscriber_failed(self, label: str, exc: BaseException) -> None:
        self._report_error(f"subscriber[{label}]", exc)

    def _report_error(self, where: str, exc: BaseException) -> None:
        self._record(ProcessFailure(where, error_text(exc), self.clock.now()))

    def _record(self, failure: ProcessFailure) -> None:
        self.failures.append(failure)
        self.failure_count += 1
        for listener in list(self._failure_listeners):
            try:
                listener(failure)
            except Exception:  # not a failure of its own: that would tell the listener again
                log.exception("dyknow[%s]: a failure listener failed", self.name)

    def on_failure(self, listener: Callable[[ProcessFailure], None]) -> Callable[[], None]:
        """Be told of every process failure; returns a function that stops telling."""
        self._failure_listeners.append(listener)
        return lambda: self._failure_listeners.remove(listener)

    # -- queries ------------------------------------------------------------------------------
    def _as_of(self, label: str, now: int, as_of: int | None) -> int:
        """The query time: ``as_of``, else now — extended to the newest available time
        this location stamped itself on ``label`` (a 1 ns uniqueness bump, a computational
        unit's output), which it knows even before the clock gets there."""
        if as_of is not None:
            return as_of
        return max(now, self.stream(label).made_ta)

    def latest(self, label: str, *, as_of: int | None = None) -> Answer:
        """The newest value of ``label``, as believed at ``as_of`` (default: now; `_as_of`)."""
        now = self.clock.now()
        try:
            location = self._labels[label]
            if as_of is None:  # `_as_of`, inline (`stream` is this location's generator)
                as_of = max(now, location.generators[label].made_ta)
        except KeyError:
            raise UnknownLabelError(label, list(self._labels)) from None
        return location.latest(label, query_time=now, as_of=as_of)

    def latest_many(self, labels: Sequence[str]) -> tuple[int, list[RawSample | None]]:
        """`latest` of each of ``labels`` at one clock reading: the query time, then each
        label's newest raw ``(value, valid, available)`` sample (None: none yet).

        The same answers as one `latest` per label made at that time, without an `Answer`
        or a `Sample` for each (a provider answers many labels at once). An unknown label
        raises `UnknownLabelError` naming it.
        """
        now = self.clock.now()
        where = self._labels
        out: list[RawSample | None] = []
        add = out.append
        label = ""
        try:
            for label in labels:
                # `latest` with its default ``as_of``, inline
                gen = where[label].generators[label]
                made = gen.made_ta
                add(gen.cache.latest(now if now >= made else made))
        except KeyError:
            raise UnknownLabelError(label, list(where)) from None
        return now, out

    def latest_now(self, label: str) -> tuple[int, RawSample | None] | None:
        """`latest_many_now` of one label: ``(now, sample or None)``, or None when it cannot tell.

        The same reading without the lists (a plain read answered on another thread).
        """
        now = self.clock.now()
        location = self._labels.get(label)
        gen = None if location is None else location.generators.get(label)
        if gen is None:
            return None
        made = gen.made_ta
        known, sample = gen.cache.latest_now(now if now >= made else made)
        if not known:
            return None
        return now, sample

    def latest_many_now(self, labels: Sequence[str]) -> tuple[int, list[RawSample | None]] | None:
        """`latest_many` from any thread, from what each stream's cache keeps (`Cache.latest_now`);
        None when that cannot tell (a label not here, a sample available later than now, a
        stream read here for the first time: every label's is watched from this ask on).

        Reads only references the event loop replaces whole, so a caller on another thread
        gets the answers of some moment while samples arrive, never a torn one.
        """
        now = self.clock.now()
        where = self._labels
        out: list[RawSample | None] = []
        add = out.append
        known_all = True
        for label in labels:
            location = where.get(label)
            gen = None if location is None else location.generators.get(label)
            if gen is None:  # None, but the streams asked after it are watched too
                known_all = False
                continue
            made = gen.made_ta
            known, sample = gen.cache.latest_now(now if now >= made else made)
            # on past one it cannot tell: each stream asked is watched from now on
            # (`Cache.latest_now`), so the next ask of these labels can tell, not only
            # the one after each of them came first
            known_all = known_all and known
            add(sample)
        return (now, out) if known_all else None

    def at(
        self,
        label: str,
        t: int,
        *,
        approximation: Approximation = Approximation.MOST_RECENT,
        as_of: int | None = None,
    ) -> Answer:
        """The value of ``label`` at valid time ``t`` (fluent generator), believed at ``as_of``."""
        now = self.clock.now()
        return self._location_of(label).at(
            label,
            t,
            query_time=now,
            approximation=approximation,
            as_of=self._as_of(label, now, as_of),
        )

    def between(
        self, label: str, t1: int, t2: int, *, as_of: int | None = None, all_estimates: bool = False
    ) -> Answer:
        """All samples of ``label`` with valid time in [t1, t2], as believed at ``as_of``."""
        now = self.clock.now()
        return self._location_of(label).between(
            label,
            t1,
            t2,
            query_time=now,
            as_of=self._as_of(label, now, as_of),
            all_estimates=all_estimates,
        )

    # -- metrics ------------------------------------------------------------------------------
    def metrics(self, label: str | None = None) -> dict[str, Any]:
        """Per-stream metrics (one label, or all of them keyed by label)."""
        if label is not None:
            return self.stream(label).stats()
        return {lab: loc.generators[lab].stats() for lab, loc in sorted(self._labels.items())}
