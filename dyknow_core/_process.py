"""Knowledge processes: sources make data available, computational units compute streams."""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import inspect
from collections import deque
from collections.abc import AsyncIterable, Callable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

from ._filter import Mapper
from ._policy import Policy
from ._sample import RawSample, Sample, as_sample
from ._stream import StreamGenerator, Subscription
from ._time import Clock

if TYPE_CHECKING:
    from ._instance import DyKnowInstance


MAX_ERROR_TEXT = 1000  # characters of an error's text kept: it may quote a huge input


def error_text(exc: BaseException) -> str:
    """``<type>: <text>`` of ``exc``, cut to `MAX_ERROR_TEXT` characters (with ``…``)."""
    text = f"{type(exc).__name__}: {exc}"
    return text if len(text) <= MAX_ERROR_TEXT else text[: MAX_ERROR_TEXT - 1] + "…"


class ProcessFailure(NamedTuple):
    """One error of a knowledge process, as reported on the instance."""

    process: str
    error: str
    time: int


class Input(NamedTuple):
    """One input of a computational unit: a label and the policy it is read with."""

    label: str
    policy: Policy = Policy()


class Process:
    """What every knowledge process has: a name, a state, and its error count."""

    kind = "process"

    def __init__(self, name: str, instance: "DyKnowInstance") -> None:
        self.name = name
        self.instance = instance
        self.errors = 0
        self.last_error: str | None = None
        self.running = True

    def _fail(self, exc: BaseException) -> None:
        self.errors += 1
        self.last_error = error_text(exc)
        self.instance._report(self, self.last_error)

    def _stop(self) -> None:
        self.running = False

    def describe(self) -> dict[str, Any]:
        """Name, kind, state and errors, for listings and reports."""
        return {
            "name": self.name,
            "kind": self.kind,
            "running": self.running,
            "errors": self.errors,
            "last_error": self.last_error,
        }


class Source(Process):
    """Makes external data available under one label (a sensor, a database, an import)."""

    kind = "source"

    def __init__(self, name: str, instance: "DyKnowInstance", generator: StreamGenerator) -> None:
        super().__init__(name, instance)
        self.generator = generator
        self.label = generator.label
        self._clock: Clock = instance.clock

    def push(
        self, value: Any, valid_time: int | None = None, available_time: int | None = None
    ) -> None:
        """Make one value available; valid and available time default to now."""
        now = self._clock.now()
        self.generator.publish_batch(
            [
                (
                    value,
                    now if valid_time is None else valid_time,
                    now if available_time is None else available_time,
                )
            ]
        )

    def push_batch(self, samples: Sequence[RawSample], *, ordered: bool = False) -> None:
        """Make many samples available at once (the fast path).

        ``ordered`` promises available times already unique, increasing and later than
        anything pushed before, which skips their check.
        """
        self.generator.publish_batch(samples, ordered=ordered)

    async def _pump(self, items: AsyncIterable[Any]) -> None:
        """Push everything an async iterator yields: values, (value, valid_time) or Samples."""
        try:
            async for item in items:
                if not self.running:
                    break
                if isinstance(item, Sample):
                    self.generator.publish_batch([item])
                elif isinstance(item, tuple) and len(item) == 2:
                    self.push(item[0], item[1])
                else:
                    self.push(item)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self._fail(exc)


class ComputationalUnit(Process):
    """Computes one output stream from N input streams, each read with its own policy.

    ``fn`` is called with the latest value of every input (or the latest Samples with
    ``pass_samples``) each time any input emits, once every input has a value; the output
    sample takes the triggering sample's valid time. Returning None emits nothing. A
    synchronous ``fn`` runs in the publisher's call; an ``async def`` one runs in its own
    task. An exception is counted and reported; the unit and the rest keep running.
    """

    kind = "computational-unit"

    def __init__(
        self,
        name: str,
        instance: "DyKnowInstance",
        fn: Callable[..., Any],
        inputs: Sequence[Input],
        output: StreamGenerator,
        *,
        pass_samples: bool = False,
    ) -> None:
        super().__init__(name, instance)
        self.fn = fn
        self.inputs = list(inputs)
        self.output = output
        self.pass_samples = pass_samples
        self.is_async = inspect.iscoroutinefunction(fn)
        self.subscriptions: list[Subscription] = []
        self._latest: list[Any] = [_NONE] * len(self.inputs)
        self._pending: deque[tuple[int, list[RawSample]]] = deque()
        self._wake: asyncio.Event | None = None
        self._clock = instance.clock

    def _callback(self, index: int) -> Callable[[list[RawSample]], None]:
        if self.is_async:

            def enqueue(batch: list[RawSample]) -> None:
                self._pending.append((index, batch))
                if self._wake is not None:
                    self._wake.set()

            return enqueue
        if self._fused:
            return self._publish
        return lambda batch: self._join_batch(index, batch)

    @property
    def _fused(self) -> bool:
        return len(self.inputs) == 1 and not self.pass_samples and not self.is_async

    def _mapper(self) -> Mapper | None:
        """Fuse a one-input unit into its input's filter loop: one pass per sample."""
        return Mapper(self.fn, self._fail, self._next_ta) if self._fused else None

    def _next_ta(self, batch: list[RawSample]) -> int:
        return max(self._clock.now(), batch[-1][2], self.output._last_ta + 1)

    def _join_batch(self, index: int, batch: list[RawSample]) -> None:
        out: list[RawSample] = []
        ta = self._next_ta(batch)
        latest = self._latest
        for s in batch:
            latest[index] = s
            if _NONE in latest:
                continue
            args = [as_sample(x) for x in latest] if self.pass_samples else [x[0] for x in latest]
            try:
                r = self.fn(*args)
            except Exception as exc:
                self._fail(exc)
                continue
            if r is not None:
                out.append((r, s[1], ta))
                ta += 1
        if out:
            self._publish(out)

    def _publish(self, out: list[RawSample]) -> None:
        try:
            self.output.publish_batch(out, ordered=True)
        except Exception as exc:
            self._fail(exc)

    async def _run_async(self) -> None:
        """Feed an ``async def`` unit from its inputs' queue until it is removed."""
        self._wake = asyncio.Event()
        latest = self._latest
        while self.running:
            if not self._pending:
                self._wake.clear()
                await self._wake.wait()
                continue
            index, batch = self._pending.popleft()
            for s in batch:
                latest[index] = s
                if _NONE in latest:
                    continue
                args = (
                    [as_sample(x) for x in latest] if self.pass_samples else [x[0] for x in latest]
                )
                try:
                    r = await self.fn(*args)
                except asyncio.CancelledError:
                    raise
                except Exception as exc:
                    self._fail(exc)
                    continue
                if r is not None and self.running:
                    ta = max(self._clock.now(), s[2], self.output._last_ta + 1)
                    self._publish([(r, s[1], ta)])

    def _stop(self) -> None:
        super()._stop()
        for sub in self.subscriptions:
            sub.close()
        if self._wake is not None:
            self._wake.set()

    def describe(self) -> dict[str, Any]:
        """Adds inputs and output to the process description."""
        d = super().describe()
        d["inputs"] = [i.label for i in self.inputs]
        d["output"] = self.output.label
        return d


class _NoneYet:
    """Marks an input that has not emitted yet."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "<no value yet>"


_NONE: Any = _NoneYet()
