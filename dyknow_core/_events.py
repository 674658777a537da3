"""Primitive events as event streams: a sample arrived, a value changed per a change policy.

An event stream is an ordinary stream (cached, subscribable, queryable). Each event is a
sample whose value is a ``ChangeEvent(old, new)``, whose valid time is the valid time
of the change (the sample that made it) and whose available time is when that sample
became available here.

``old`` is the value the change is measured from — the ``new`` of the previous event,
which under ``absolute(δ)``/``relative(δ)`` is the last value that counted as a change,
not merely the previous sample. The first event of a stream has ``old=None``: the value
became known.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

from ._exceptions import ProcessError
from ._policy import CacheSpec, Change, ChangeKind, Order, Policy
from ._process import Process
from ._sample import RawSample
from ._stream import StreamGenerator, Subscription

if TYPE_CHECKING:
    from ._instance import DyKnowInstance

_NEG_INF = -(2**63)


class ChangeEvent(NamedTuple):
    """One event's value: what the value was (None at the first event) and what it became."""

    old: Any
    new: Any


class EventProcess(Process):
    """Watches one stream through a policy and publishes an event for each sample it lets by."""

    kind = "event"

    def __init__(
        self, name: str, instance: DyKnowInstance, source: str, output: StreamGenerator
    ) -> None:
        super().__init__(name, instance)
        self.source = source
        self.output = output
        self.label = output.label
        self.subscription: Subscription | None = None
        self._old: Any = None
        self._last_ta = _NEG_INF

    def _on_samples(self, batch: list[RawSample]) -> None:
        """Turn the samples the change policy let through into events."""
        if not self.running:
            return
        out: list[RawSample] = []
        append = out.append
        old = self._old
        last_ta = self._last_ta
        for new, tv, ta in batch:
            if ta <= last_ta:
                ta = last_ta + 1  # available times are unique per stream
            append((ChangeEvent(old, new), tv, ta))
            old = new
            last_ta = ta
        self._old = old
        self._last_ta = last_ta
        if out:
            try:
                self.output.publish_batch(out)
            except Exception as exc:
                self._fail(exc)

    def _stop(self) -> None:
        super()._stop()
        if self.subscription is not None:
            self.subscription.close()

    @property
    def type_errors(self) -> int:
        """Values the change test could not compare (non-numeric under absolute/relative)."""
        sub = self.subscription
        return 0 if sub is None else sub.filter.stats.type

    def describe(self) -> dict[str, Any]:
        """Adds the watched stream, the event stream and the counters to the description."""
        d = super().describe()
        d["source"] = self.source
        d["output"] = self.label
        sub = self.subscription
        if sub is not None:
            d["change"] = sub.policy.change.model_dump(mode="json")
            d["events"] = sub.delivered
            d["held_back"] = sub.filter.stats.dropped
        d["type_errors"] = self.type_errors
        return d


def _add_events(
    instance: DyKnowInstance,
    label: str,
    policy: Policy,
    output: str,
    name: str,
    location: str | None,
    cache: CacheSpec | None,
) -> EventProcess:
    """Subscribe to ``label`` with ``policy`` and publish its samples as events on ``output``."""
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    if output == label:
        raise ProcessError(f"event process {name!r} cannot publish on the stream it watches")
    gen = instance.stream(label)
    gen._check_policy(policy)  # a numeric change on a non-numeric stream fails up front
    kwargs: dict[str, Any] = {"cache": cache, "value_type": ChangeEvent}
    if location is not None:
        kwargs["location"] = location
    out = instance.create_stream(output, **kwargs)
    proc = EventProcess(name, instance, label, out)
    try:
        proc.subscription = instance.subscribe(label, policy, callback=proc._on_samples)
    except Exception:
        proc._stop()
        instance.remove_stream(output)
        raise
    instance._add_process(proc)
    return proc


def add_change_events(
    instance: DyKnowInstance,
    label: str,
    change: Change | str | Mapping[str, Any],
    output: str | None = None,
    name: str | None = None,
    *,
    policy: Policy | None = None,
    location: str | None = None,
    cache: CacheSpec | None = None,
) -> EventProcess:
    """Publish an event on ``output`` each time ``label``'s value changes per ``change``.

    ``change`` is a ``Change`` or its text (``"any_change"``, ``"absolute(0.5)"``,
    ``"relative(0.1)"``). ``output`` defaults to ``events/changed/<label>``. ``policy`` is
    the base policy the stream is read with (its ``change`` is replaced); the default
    keeps strictly increasing valid time, so a revised estimate or an out-of-order
    sample is held back rather than read as a change.
    """
    ch = Change.parse(change)
    base = policy if policy is not None else Policy(order=Order.STRICT)
    output = output or f"events/changed/{label}"
    return _add_events(
        instance,
        label,
        base.replace(change=ch),
        output,
        name or f"events:{output}",
        location,
        cache,
    )


def add_arrival_events(
    instance: DyKnowInstance,
    label: str,
    output: str | None = None,
    name: str | None = None,
    *,
    policy: Policy | None = None,
    location: str | None = None,
    cache: CacheSpec | None = None,
) -> EventProcess:
    """Publish an event on ``output`` (default ``events/arrived/<label>``) per arriving sample.

    Every sample counts (its ``change`` is ``any_update``), in arrival order, unless
    ``policy`` says otherwise; the event's ``old`` is the previous sample's value.
    """
    base = policy if policy is not None else Policy()
    output = output or f"events/arrived/{label}"
    return _add_events(
        instance,
        label,
        base.replace(change=Change(kind=ChangeKind.ANY_UPDATE)),
        output,
        name or f"events:{output}",
        location,
        cache,
    )
