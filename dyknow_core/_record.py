"""Recordings: streams written to a file as they are published, replayed on a manual clock.

The file (``.dkr``) is the magic line ``DYKNOW-REC\\n`` followed by frames; a frame is a
4-byte big-endian payload length, the payload's 4-byte CRC-32, then the msgpack payload.
The first frame is the header (a map: ``format``, ``version``, ``instance``, ``clock``,
``start``, ``labels``, ``created``, ``meta``); every later frame is one self-contained
batch ``{"l": [label, …], "s": [[label index, value, valid ns, available ns], …]}`` in
order of availability. A batch is written whole and flushed, so a file whose writer was
killed is readable up to its last complete batch.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import datetime as _dt
import logging
import os
import struct
import time
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from enum import Enum
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, NamedTuple

import msgpack

from ._aio import Ticker
from ._events import ChangeEvent
from ._exceptions import DyKnowError
from ._objects import DomainChange
from ._policy import Policy
from ._process import Source
from ._sample import Sample
from ._stream import Subscription
from ._time import NS_PER_S, ManualClock

if TYPE_CHECKING:
    from ._instance import DyKnowInstance

log = logging.getLogger(__name__)

MAGIC = b"DYKNOW-REC\n"
FORMAT_NAME = "dyknow-record"
FORMAT_VERSION = 1
_FRAME = struct.Struct(">II")  # payload length, CRC-32 of the payload
_MAX_FRAME = 64 * 1024 * 1024  # larger is a corrupt length, not a batch
_EXT_TYPED = 1  # msgpack extension: a named tuple or dataclass, [type name, {field: value}]
_SETTLE_MAX = 10_000  # loop iterations a replay step waits at most for the instance to idle


class RecordError(DyKnowError, ValueError):
    """A recording that cannot be read: missing, not a recording, corrupt, wrong version."""


class RecordedSample(NamedTuple):
    """One recorded sample: the label it was published under and the sample itself."""

    label: str
    value: Any
    valid_time: int
    available_time: int


@dataclasses.dataclass(frozen=True)
class RecordHeader:
    """What a recording says about itself (its first frame)."""

    version: int
    instance: str
    clock: str
    start: int
    labels: list[str] | None
    created: str
    meta: dict[str, Any]


# -- values ------------------------------------------------------------------------------------


# The value types a replay gives back as themselves (others come back as dicts), by name.
# The core registers its own below; a layer above registers its types when it is imported
# (a recording can only hold such values if that layer was loaded to make them).
_RECORD_TYPES: dict[str, type] = {}


def register_record_type(cls: type) -> None:
    """Let replays rebuild ``cls`` (a named tuple or dataclass) from its recorded fields."""
    if not (dataclasses.is_dataclass(cls) or hasattr(cls, "_fields")):
        raise TypeError(f"{cls.__name__} is neither a named tuple nor a dataclass")
    _RECORD_TYPES[cls.__name__] = cls


for _cls in (ChangeEvent, DomainChange, Sample):
    register_record_type(_cls)


class _Encoder:
    """msgpack encoding of sample values; a value it cannot carry is recorded as its repr."""

    def __init__(self) -> None:
        self.unencodable = 0
        self._packer = msgpack.Packer(default=self._default, strict_types=True)

    def pack(self, obj: Any) -> bytes:
        """The msgpack bytes of ``obj``."""
        data: bytes = self._packer.pack(obj)
        return data

    def _nested(self, obj: Any) -> bytes:
        # a Packer is not re-entrant: what goes inside an extension gets its own
        data: bytes = msgpack.packb(obj, default=self._default, strict_types=True)
        return data

    def _default(self, obj: Any) -> Any:
        # strict_types: every subclass (NamedTuple, StrEnum, bool is exempt) comes here
        if type(obj) is tuple:
            return list(obj)
        if isinstance(obj, tuple) and hasattr(obj, "_asdict"):
            return msgpack.ExtType(_EXT_TYPED, self._nested([type(obj).__name__, obj._asdict()]))
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            fields = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
            return msgpack.ExtType(_EXT_TYPED, self._nested([type(obj).__name__, fields]))
        if isinstance(obj, Enum):
            return obj.value
        if isinstance(obj, int):  # subclasses of the plain types, as the plain type
            return int(obj)
        if isinstance(obj, float):
            return float(obj)
        if isinstance(obj, str):
            return str(obj)
        if isinstance(obj, bytes):
            return bytes(obj)
        if isinstance(obj, list):
            return list(obj)
        if isinstance(obj, dict):
            return dict(obj)
        if isinstance(obj, tuple | set | frozenset):
            return list(obj)
        dump = getattr(obj, "model_dump", None)
        if callable(dump):  # a pydantic model
            return dump(mode="json")
        # a recording must not stop for one odd value: keep what it looked like, and count it
        self.unencodable += 1
        return repr(obj)


def _decoder() -> Callable[[int, bytes], Any]:
    registry = _RECORD_TYPES  # read at decode time: a type registered later counts too

    def ext_hook(code: int, data: bytes) -> Any:
        if code != _EXT_TYPED:
            return msgpack.ExtType(code, data)
        name, fields = msgpack.unpackb(data, raw=False, strict_map_key=False, ext_hook=ext_hook)
        cls = registry.get(name)
        if cls is not None:
            with contextlib.suppress(TypeError):
                return cls(**fields)
        return dict(fields)

    return ext_hook


# -- writing -----------------------------------------------------------------------------------


class RecordWriter:
    """Appends samples to a recording file in batches (the writing side of the format).

    ``add`` buffers; a batch is written (and flushed to the OS) every ``batch_size``
    samples and on ``flush``/``close``, so memory stays bounded and a killed writer leaves
    a file readable up to its last batch.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        instance: str = "",
        clock: str = "",
        start: int = 0,
        labels: Iterable[str] | None = None,
        meta: Mapping[str, Any] | None = None,
        batch_size: int = 1000,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.path = Path(path)
        self.batch_size = batch_size
        self.counts: dict[str, int] = {}
        self.samples = 0
        self.batches = 0
        self._enc = _Encoder()
        self._pending: list[tuple[str, Any, int, int]] = []
        # set when samples may have been buffered out of order (a stream found late)
        self.sort_pending = False
        self.header = RecordHeader(
            version=FORMAT_VERSION,
            instance=instance,
            clock=clock,
            start=start,
            labels=None if labels is None else list(labels),
            created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            meta=dict(meta or {}),
        )
        try:
            self._f: IO[bytes] | None = open(self.path, "wb")  # noqa: SIM115 - see close()
        except OSError as exc:
            raise RecordError(f"{self.path}: cannot be written: {exc.strerror}") from None
        self._f.write(MAGIC)
        self._frame(
            {"format": FORMAT_NAME, **dataclasses.asdict(self.header)},
        )

    @property
    def unencodable(self) -> int:
        """How many values msgpack could not carry and were recorded as their repr."""
        return self._enc.unencodable

    @property
    def closed(self) -> bool:
        """Whether the file is closed."""
        return self._f is None

    def _frame(self, obj: Any) -> None:
        assert self._f is not None
        payload = self._enc.pack(obj)
        self._f.write(_FRAME.pack(len(payload), zlib.crc32(payload)) + payload)
        self._f.flush()

    def add(self, label: str, value: Any, valid_time: int, available_time: int) -> None:
        """Buffer one sample; a full buffer is written as a batch."""
        if self._f is None:
            raise ValueError(f"{self.path}: the recording is closed")
        self._pending.append((label, value, valid_time, available_time))
        if len(self._pending) >= self.batch_size:
            self.flush()

    def flush(self) -> None:
        """Write what is buffered as one batch (sorted by available time if ``sort_pending``)."""
        if not self._pending or self._f is None:
            return
        pending, self._pending = self._pending, []
        if self.sort_pending:
            pending.sort(key=lambda s: s[3])
            self.sort_pending = False
        index: dict[str, int] = {}
        rows = []
        for label, value, tv, ta in pending:
            i = index.setdefault(label, len(index))
            rows.append([i, value, tv, ta])
            self.counts[label] = self.counts.get(label, 0) + 1
        self._frame({"l": list(index), "s": rows})
        self.samples += len(rows)
        self.batches += 1

    def close(self) -> None:
        """Write what is buffered and close the file (idempotent)."""
        if self._f is None:
            return
        try:
            self.flush()
        finally:
            self._f.close()
            self._f = None


class Recorder:
    """Records every sample of some streams of an instance to a file, as they are published.

    ``labels`` lists the streams (they must exist); ``None`` records every stream,
    including those created after the recorder started. Use it as an async context
    manager (it then flushes every ``flush_interval`` seconds of wall time), or call
    ``start``/``close`` yourself. ``rename`` records a label under another name (an
    imported stream under its semantic label). ``since`` (ns) also records what the
    streams' caches hold that became available at or after it; ``limit`` stops recording
    after that many samples (``done`` is then set). Values are kept as msgpack carries them:
    tuples come back as lists, the core's value types (ChangeEvent, Verdict, …) as
    themselves, other named tuples and dataclasses as dicts.
    """

    def __init__(
        self,
        instance: DyKnowInstance,
        labels: Iterable[str] | None,
        path: str | os.PathLike[str],
        *,
        rename: Mapping[str, str] | None = None,
        meta: Mapping[str, Any] | None = None,
        flush_interval: float = 1.0,
        batch_size: int = 1000,
        discover_interval: float = 0.1,
        since: int | None = None,
        limit: int | None = None,
    ) -> None:
        if not flush_interval > 0:
            raise ValueError(f"flush_interval must be > 0 s, got {flush_interval}")
        self.instance = instance
        self.path = Path(path)
        self.all_labels = labels is None
        self._labels = [] if labels is None else list(labels)
        self._rename = dict(rename or {})
        self._meta = dict(meta or {})
        self.flush_interval = flush_interval
        self.discover_interval = discover_interval
        self.batch_size = batch_size
        self.writer: RecordWriter | None = None
        self._subs: dict[str, Subscription] = {}
        self._last_ta: dict[str, int] = {}
        self._t0 = 0
        self._since = since
        self.limit = limit
        self.recorded = 0
        self.done = asyncio.Event()
        self._known = 0
        self._tasks: list[asyncio.Task[None]] = []
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> Recorder:
        """Open the file, write the header and subscribe to the streams."""
        if self.writer is not None:
            raise ValueError(f"{self.path}: the recorder was started already")
        for label in self._labels:
            self.instance.stream(label)  # an unknown label fails before the file is made
        clock = self.instance.clock
        self._t0 = clock.now() if self._since is None else self._since
        self.writer = RecordWriter(
            self.path,
            instance=self.instance.name,
            clock=type(clock).__name__,
            start=self._t0,
            labels=None if self.all_labels else [self._rename.get(x, x) for x in self._labels],
            meta=self._meta,
            batch_size=self.batch_size,
        )
        for label in self._labels:
            self.follow(label, since=self._since)
        if self.all_labels:
            self._known = -1
            self._discover(initial=True)
        return self

    async def __aenter__(self) -> Recorder:
        self.start()
        async with contextlib.AsyncExitStack() as stack:
            tg = await stack.enter_async_context(asyncio.TaskGroup())
            name = f"recorder[{self.path}]"
            self._tasks.append(tg.create_task(self._flusher(), name=name))
            if self.all_labels:
                self._tasks.append(tg.create_task(self._discoverer(), name=f"{name}.discover"))
            self._stack = stack.pop_all()
        return self

    async def __aexit__(self, *exc: object) -> None:
        for task in self._tasks:
            task.cancel()
        stack, self._stack = self._stack, None
        try:
            if stack is not None:
                await stack.aclose()  # the body's error is not the group's to wrap
        finally:
            self._tasks.clear()
            self.close()

    def close(self) -> None:
        """Stop recording: unsubscribe, write what is buffered, close the file."""
        for sub in self._subs.values():
            sub.close()
        if self.writer is not None:
            self.writer.close()

    def flush(self) -> None:
        """Write what is buffered as a batch now."""
        if self.writer is not None:
            if self.all_labels:
                self._discover()
            self.writer.flush()

    # A failing timer stops that timer only, as before: it must not end the recording (nor
    # the task that entered the recorder, as a failure in a task group would).
    async def _flusher(self) -> None:
        try:
            async for _ in Ticker(self.flush_interval):
                self.flush()
        except Exception:
            log.exception("recorder[%s]: the flush timer failed", self.path)

    async def _discoverer(self) -> None:
        try:
            async for _ in Ticker(self.discover_interval):
                self._discover()
        except Exception:
            log.exception("recorder[%s]: the discovery timer failed", self.path)

    # -- what is recorded --------------------------------------------------------------------
    @property
    def counts(self) -> dict[str, int]:
        """Samples recorded so far per (recorded) label, buffered ones included."""
        if self.writer is None:
            return {}
        counts = dict(self.writer.counts)
        for label, *_ in self.writer._pending:
            counts[label] = counts.get(label, 0) + 1
        return counts

    @property
    def labels(self) -> list[str]:
        """The instance labels being recorded."""
        return list(self._subs)

    def follow(self, label: str, as_: str | None = None, *, since: int | None = None) -> None:
        """Record ``label`` too (under ``as_``), from now on or from available time ``since``.

        With ``since``, what the stream's cache holds that became available at or after it
        is recorded first (a stream found after it was created).
        """
        if self.writer is None:
            raise ValueError(f"{self.path}: the recorder is not started")
        if label in self._subs:
            return
        if as_ is not None:
            self._rename[label] = as_
        name = self._rename.get(label, label)
        policy = Policy() if since is None else Policy(start=-(2**63))
        self._last_ta.setdefault(label, -(2**63) if since is None else since - 1)
        if since is not None:
            self.writer.sort_pending = True
        self._subs[label] = self.instance.subscribe(
            label, policy, callback=self._callback(label, name)
        )

    def _callback(self, label: str, name: str) -> Callable[[list[Any]], None]:
        add = self._add

        def on_batch(batch: list[Any]) -> None:
            add(label, name, batch)

        return on_batch

    def _add(self, label: str, name: str, batch: list[Any]) -> None:
        writer = self.writer
        if writer is None or writer.closed:
            return
        last = self._last_ta[label]
        limit = self.limit
        for value, tv, ta in batch:
            # available times are unique and increasing per stream: this drops what a
            # history replay from the cache would deliver twice
            if ta > last:
                if limit is not None and self.recorded >= limit:
                    self.done.set()
                    break
                writer.add(name, value, tv, ta)
                self.recorded += 1
                last = ta
        self._last_ta[label] = last
        if limit is not None and self.recorded >= limit:
            self.done.set()
        if self.all_labels and self._label_count() != self._known:
            # a stream appeared: subscribe once this publish is over, not inside it
            try:
                asyncio.get_running_loop().call_soon(self._discover)
            except RuntimeError:  # used without an event loop
                self._discover()

    def _label_count(self) -> int:
        return len(self.instance._labels)

    def _discover(self, *, initial: bool = False) -> None:
        """Follow every label of the instance not followed yet (``labels=None``).

        A stream found after it was created is read from its cache since the recorder
        started, so what it published before it was found is recorded too.
        """
        writer = self.writer
        if writer is None or writer.closed or self._label_count() == self._known:
            return
        now = self.instance.labels()
        self._known = len(now)
        for label in now:
            if label not in self._subs:
                self.follow(label, since=self._since if initial else self._t0)


# -- reading -----------------------------------------------------------------------------------


class Recording:
    """A recording file opened for reading: its header, then its samples batch by batch."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.truncated = False
        self._ext_hook = _decoder()
        try:
            with open(self.path, "rb") as f:
                self.header = self._read_header(f)
                self._offset = f.tell()
        except IsADirectoryError:
            raise RecordError(f"{self.path}: is a directory, not a recording") from None
        except FileNotFoundError:
            raise RecordError(f"{self.path}: no such file") from None
        except OSError as exc:
            raise RecordError(f"{self.path}: cannot be read: {exc.strerror}") from None

    def _fail(self, what: str) -> RecordError:
        return RecordError(f"{self.path}: {what}")

    def _unpack(self, payload: bytes) -> Any:
        return msgpack.unpackb(
            payload, raw=False, strict_map_key=False, ext_hook=self._ext_hook, use_list=True
        )

    def _read_frame(self, f: IO[bytes]) -> tuple[bytes | None, str]:
        """The next payload, or None with why: '' at the end, 'truncated', 'corrupt …'."""
        head = f.read(_FRAME.size)
        if not head:
            return None, ""
        if len(head) < _FRAME.size:
            return None, "truncated"
        size, crc = _FRAME.unpack(head)
        if size > _MAX_FRAME:
            return None, f"corrupt frame length {size}"
        payload = f.read(size)
        if len(payload) < size:
            return None, "truncated"
        if zlib.crc32(payload) != crc:
            return None, "corrupt (checksum mismatch)"
        return payload, ""

    def _read_header(self, f: IO[bytes]) -> RecordHeader:
        if f.read(len(MAGIC)) != MAGIC:
            raise self._fail("not a DyKnow recording (it does not start with DYKNOW-REC)")
        payload, why = self._read_frame(f)
        if payload is None:
            raise self._fail(f"corrupt header ({why or 'missing'})")
        try:
            h = self._unpack(payload)
        except Exception as exc:  # msgpack raises several kinds on bad input
            raise self._fail(f"corrupt header: {type(exc).__name__}: {exc}") from None
        if not isinstance(h, dict) or h.get("format") != FORMAT_NAME:
            raise self._fail("corrupt header: not a dyknow-record header")
        version = h.get("version")
        if version != FORMAT_VERSION:
            raise self._fail(
                f"format version {version!r} is not supported (this dyknow reads version "
                f"{FORMAT_VERSION})"
            )
        try:
            labels = h.get("labels")
            return RecordHeader(
                version=int(version),
                instance=str(h.get("instance", "")),
                clock=str(h.get("clock", "")),
                start=int(h.get("start", 0)),
                labels=None if labels is None else [str(x) for x in labels],
                created=str(h.get("created", "")),
                meta=dict(h.get("meta") or {}),
            )
        except (TypeError, ValueError) as exc:
            raise self._fail(f"corrupt header: {exc}") from None

    def batches(self) -> Iterator[list[RecordedSample]]:
        """Each complete batch in file order; stops (``truncated``) at an incomplete one."""
        self.truncated = False
        try:
            f = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise self._fail(f"cannot be read: {exc.strerror}") from None
        with f:
            f.seek(self._offset)
            n = 0
            while True:
                at = f.tell()
                payload, why = self._read_frame(f)
                if payload is None:
                    if why == "truncated":
                        self.truncated = True
                        return
                    if why:
                        raise self._fail(f"batch {n + 1} at byte {at}: {why}")
                    return
                n += 1
                yield self._batch(payload, n, at)

    def _batch(self, payload: bytes, n: int, at: int) -> list[RecordedSample]:
        try:
            obj = self._unpack(payload)
            labels = obj["l"]
            return [
                RecordedSample(labels[i], value, int(tv), int(ta)) for i, value, tv, ta in obj["s"]
            ]
        except Exception as exc:  # anything malformed inside a frame whose checksum held
            raise self._fail(
                f"batch {n} at byte {at} is malformed: {type(exc).__name__}: {exc}"
            ) from None

    def __iter__(self) -> Iterator[RecordedSample]:
        for batch in self.batches():
            yield from batch

    def info(self) -> dict[str, Any]:
        """The header, samples per label, the valid and available time spans, truncation."""
        counts: dict[str, int] = {}
        tv_lo = tv_hi = ta_lo = ta_hi = None
        batches = 0
        for batch in self.batches():
            batches += 1
            for s in batch:
                counts[s.label] = counts.get(s.label, 0) + 1
                tv_lo = s.valid_time if tv_lo is None else min(tv_lo, s.valid_time)
                tv_hi = s.valid_time if tv_hi is None else max(tv_hi, s.valid_time)
                ta_lo = s.available_time if ta_lo is None else min(ta_lo, s.available_time)
                ta_hi = s.available_time if ta_hi is None else max(ta_hi, s.available_time)
        return {
            "file": str(self.path),
            **dataclasses.asdict(self.header),
            "batches": batches,
            "samples": sum(counts.values()),
            "counts": dict(sorted(counts.items())),
            "valid_span": None if tv_lo is None else [tv_lo, tv_hi],
            "available_span": None if ta_lo is None else [ta_lo, ta_hi],
            "truncated": self.truncated,
        }


def read_recording(path: str | os.PathLike[str]) -> Recording:
    """Open a recording for reading (RecordError naming the file and what is wrong)."""
    return Recording(path)


# -- replay ------------------------------------------------------------------------------------


@dataclasses.dataclass
class ReplaySummary:
    """What a replay pushed: samples per label, their valid and available time spans."""

    counts: dict[str, int] = dataclasses.field(default_factory=dict)
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    valid_span: tuple[int, int] | None = None
    available_span: tuple[int, int] | None = None
    truncated: bool = False

    @property
    def samples(self) -> int:
        """How many samples were pushed."""
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready view."""
        return {
            "samples": self.samples,
            "counts": dict(sorted(self.counts.items())),
            "skipped": dict(sorted(self.skipped.items())),
            "valid_span": None if self.valid_span is None else list(self.valid_span),
            "available_span": None if self.available_span is None else list(self.available_span),
            "truncated": self.truncated,
        }


async def settle() -> None:
    """Let the ready tasks of the event loop run until none is left (no time passes)."""
    loop = asyncio.get_running_loop()
    # CPython's queue of ready callbacks tells when everything woken has run; without it
    # a fixed number of yields is the best there is
    ready = getattr(loop, "_ready", None)
    for i in range(_SETTLE_MAX if ready is not None else 50):
        await asyncio.sleep(0)
        if ready is not None and not ready and i >= 1:
            return


def _next_wake(clock: ManualClock, after: int) -> int | None:
    """The earliest time someone sleeps until on ``clock``, later than ``after``."""
    pending = [t for t, _, fut in clock._sleepers if not fut.done() and t > after]
    return min(pending) if pending else None


async def advance_to(clock: ManualClock, t: int) -> None:
    """Move a manual clock to ``t`` as time would pass: every timer due before fires in order.

    Each wake-up time on the way is set and the loop settled before the next, so periodic
    processes (states, monitors, the policy ticker) run at their own times, as on a live
    clock, and the outcome is the same every time.
    """
    while True:
        nxt = _next_wake(clock, clock.now())
        if nxt is None or nxt >= t:
            break
        clock.set(nxt)
        await settle()
    if t > clock.now():
        clock.set(t)
    await settle()


def _source_for(instance: DyKnowInstance, label: str) -> Source:
    """The source publishing ``label`` on ``instance``, added when the label is free."""
    for proc in instance.processes.values():
        if isinstance(proc, Source) and proc.label == label:
            return proc
    if instance.has_label(label):
        raise RecordError(
            f"label {label!r} is published on instance {instance.name!r} by something other "
            "than a source: the replay cannot feed it"
        )
    return instance.add_source(label)


async def replay(
    path: str | os.PathLike[str] | Recording,
    instance: DyKnowInstance,
    *,
    speed: float | None = None,
    labels: Iterable[str] | None = None,
    tail: float = 0.0,
    on_sample: Callable[[RecordedSample], None] | None = None,
) -> ReplaySummary:
    """Push a recording's samples into sources of the same labels on a manual-clock instance.

    Before each sample the clock is advanced (``advance_to``) to its available time, so
    every policy, state, monitor and chronicle sees what it saw when it was recorded, and
    two replays give the same outputs. ``speed``: None as fast as possible, 1.0 real
    time, 2.0 twice as fast. ``labels`` picks the labels fed (default all; the others
    are counted in ``skipped``); a label's source is the instance's existing ``Source``
    for it, or a new one. ``tail`` (s) lets the clock run on after the last sample.
    Call it inside ``async with instance`` so the instance's periodic tasks run.
    """
    clock = instance.clock
    if not isinstance(clock, ManualClock):
        raise TypeError(
            f"replay needs an instance driven by a ManualClock, not a {type(clock).__name__}"
        )
    if speed is not None and not speed > 0:
        raise ValueError(f"speed must be > 0 (or None for as fast as possible), got {speed}")
    rec = path if isinstance(path, Recording) else Recording(path)
    wanted = None if labels is None else set(labels)
    summary = ReplaySummary()
    sources: dict[str, Source] = {}
    first_ta: int | None = None
    wall0 = time.monotonic()
    await settle()
    for s in rec:
        if wanted is not None and s.label not in wanted:
            summary.skipped[s.label] = summary.skipped.get(s.label, 0) + 1
            continue
        src = sources.get(s.label)
        if src is None:
            src = sources[s.label] = _source_for(instance, s.label)
        if speed is not None:
            first_ta = s.available_time if first_ta is None else first_ta
            due = wall0 + (s.available_time - first_ta) / NS_PER_S / speed
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
        await advance_to(clock, s.available_time)
        src.push(s.value, s.valid_time, s.available_time)
        await settle()
        summary.counts[s.label] = summary.counts.get(s.label, 0) + 1
        v, a = summary.valid_span, summary.available_span
        summary.valid_span = (
            (s.valid_time, s.valid_time)
            if v is None
            else (min(v[0], s.valid_time), max(v[1], s.valid_time))
        )
        summary.available_span = (
            (s.available_time, s.available_time)
            if a is None
            else (min(a[0], s.available_time), max(a[1], s.available_time))
        )
        if on_sample is not None:
            on_sample(s)
    summary.truncated = rec.truncated
    if tail > 0:
        await advance_to(clock, clock.now() + round(tail * NS_PER_S))
    return summary


__all__ = [
    "FORMAT_VERSION",
    "RecordError",
    "RecordHeader",
    "RecordWriter",
    "RecordedSample",
    "Recorder",
    "Recording",
    "ReplaySummary",
    "advance_to",
    "read_recording",
    "replay",
    "settle",
]
