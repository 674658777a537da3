"""Chronicle recognition as a knowledge process, and over a whole list of events."""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

from ..._events import ChangeEvent
from ..._exceptions import ProcessError
from ..._policy import Order, Policy
from ..._process import Process
from ..._sample import RawSample
from ..._stream import StreamGenerator, Subscription

if TYPE_CHECKING:
    from ..._instance import DyKnowInstance

from ._compile import CompiledChronicle, compile_chronicle
from ._recognizer import ChronicleRecognizer, Recognition
from ._spec import ChronicleError, ChronicleSpec
from ._stn import _INF

# -- as a knowledge process -----------------------------------------------------------------


def _decode(value: Any, prev: Any) -> tuple[Mapping[str, Any], Any, Any]:
    """An input sample's value as (arguments, old, new)."""
    if isinstance(value, ChangeEvent):
        return {}, value.old, value.new
    if isinstance(value, Recognition):
        return value.bindings, None, value
    if isinstance(value, Mapping):
        return value, value.get("old"), value.get("new")
    return {}, prev, value


class ChronicleProcess(Process):
    """Recognizes one chronicle over input event streams and publishes each recognition."""

    kind = "chronicle"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        recognizer: ChronicleRecognizer,
        output: StreamGenerator,
    ) -> None:
        super().__init__(name, instance)
        self.recognizer = recognizer
        self.output = output
        self.label = output.label
        self.subscriptions: list[Subscription] = []
        self._last_ta = -(2**63)

    def _callback(self, kind: str, label_args: Mapping[str, Any]) -> Any:
        feed = self.recognizer.feed
        prev: list[Any] = [None]

        def on_samples(batch: list[RawSample]) -> None:
            if not self.running:
                return
            found: list[RawSample] = []
            try:
                for value, tv, ta in batch:
                    args, old, new = _decode(value, prev[0])
                    prev[0] = value
                    if label_args:
                        args = {**args, **label_args}
                    for rec in feed(kind, tv, args, old, new):
                        found.append(self._sample(rec, ta))
            except Exception as exc:
                self._fail(exc)
            if found:
                try:
                    self.output.publish_batch(found)
                except Exception as exc:
                    self._fail(exc)

        return on_samples

    def _sample(self, rec: Recognition, ta: int) -> RawSample:
        if ta <= self._last_ta:
            ta = self._last_ta + 1  # available times are unique per stream
        self._last_ta = ta
        return (rec, max(rec.times.values()), ta)

    def flush(self, now: int | None = None) -> int:
        """Advance the recognizer's clock (default: the instance's) and publish what it releases."""
        t = self.instance.clock.now() if now is None else now
        recs = self.recognizer.advance(t)
        if recs:
            self.output.publish_batch([self._sample(r, t) for r in recs])
        return len(recs)

    def _stop(self) -> None:
        super()._stop()
        for sub in self.subscriptions:
            sub.close()

    def describe(self) -> dict[str, Any]:
        """Adds the inputs, output and the recognizer's counters to the description."""
        d = super().describe()
        d["inputs"] = [s.label for s in self.subscriptions]
        d["output"] = self.label
        d.update(self.recognizer.stats()._asdict())
        return d


def _expand(instance: DyKnowInstance, label: str) -> list[tuple[str, dict[str, str]]]:
    """A label, or the published labels matching its ``{param}`` placeholders, with their values."""
    if "{" not in label:
        return [(label, {})]
    names: list[str] = []
    pattern = ""
    for part in re.split(r"(\{[A-Za-z_][A-Za-z0-9_]*\})", label):
        if part.startswith("{") and part.endswith("}"):
            names.append(part[1:-1])
            pattern += r"([^/]+)"
        else:
            pattern += re.escape(part)
    rx = re.compile(pattern + r"\Z")
    out = []
    for lab in instance.labels():
        m = rx.match(lab)
        if m:
            out.append((lab, dict(zip(names, m.groups(), strict=True))))
    return out


def add_chronicle(
    instance: DyKnowInstance,
    definition: ChronicleSpec | CompiledChronicle | Mapping[str, Any],
    inputs: Mapping[str, str],
    *,
    output: str | None = None,
    name: str | None = None,
) -> ChronicleProcess:
    """Recognize ``definition`` over ``inputs`` (event name → label) and publish recognitions.

    Recognitions (``Recognition`` values) go to ``output``, default ``chronicles/<name>``.
    A label may hold ``{param}`` placeholders (``events/changed/car/{car}/incross``): every
    label published now that matches is read, its placeholders giving the event's
    arguments. Other arguments come from the sample: a ``Recognition``'s bindings (for
    chronicles over chronicles) or a mapping value's keys.
    """
    compiled = (
        definition if isinstance(definition, CompiledChronicle) else compile_chronicle(definition)
    )
    missing = sorted(compiled.kinds - set(inputs))
    if missing:
        # a misspelt input name shows as an unused one
        unused = sorted(set(inputs) - compiled.kinds)
        stray = f" (no event reads {', '.join(map(repr, unused))})" if unused else ""
        raise ChronicleError("inputs", f"no label for event(s) {', '.join(missing)}{stray}")
    output = output or f"chronicles/{compiled.name}"
    name = name or f"chronicle:{compiled.name}"
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    expanded = {kind: _expand(instance, label) for kind, label in inputs.items()}
    for kind, labels in expanded.items():
        if not labels:
            raise ChronicleError(f"inputs.{kind}", f"no published label matches {inputs[kind]!r}")
        for label, _ in labels:
            instance.stream(label)  # UnknownLabelError naming it, before the output exists
    gen = instance.create_stream(output, value_type=Recognition)
    proc = ChronicleProcess(name, instance, ChronicleRecognizer(compiled), gen)
    policy = Policy(order=Order.MONOTONE)
    try:
        for kind, labels in expanded.items():
            for label, label_args in labels:
                proc.subscriptions.append(
                    instance.subscribe(label, policy, callback=proc._callback(kind, label_args))
                )
    except Exception:
        proc._stop()
        instance.remove_stream(output)
        raise
    instance.add_process(proc)
    return proc


def recognize_all(
    chronicle: CompiledChronicle | ChronicleSpec | Mapping[str, Any],
    events: Iterable[tuple[str, int, Mapping[str, Any] | None, Any, Any]],
) -> list[Recognition]:
    """Feed ``(kind, time, args, old, new)`` events in order and return every recognition."""
    rec = ChronicleRecognizer(chronicle)
    out: list[Recognition] = []
    for kind, t, args, old, new in events:
        out.extend(rec.feed(kind, t, args, old, new))
    out.extend(rec.advance(_INF))
    return out
