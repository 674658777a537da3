"""Recordings: streams written to an MCAP file as they are published, replayed on a manual clock.

A recording is an MCAP file (https://mcap.dev), so Foxglove and every MCAP tool open it:
zstd-compressed chunks, indexed (chunk and message indexes, a summary), one channel per
label with a JSON schema, encoding ``json``. Each message is one sample, ``{"value": …,
"valid_time": {"sec", "nsec"}, "available_time": {"sec", "nsec"}}``, its MCAP log time the
available time and its publish time the valid time, both shifted by the file's time offset
(MCAP times are unsigned). A metadata record ``dyknow``, written before any message, holds
what the recording says about itself (the offset too). A batch is one chunk, written whole
and flushed, so a file whose writer was killed is readable up to its last complete batch.
docs/record.md has the details; old ``.dkr`` files (format version 1) are still read.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import dataclasses
import datetime as _dt
import json
import logging
import math
import os
import struct
import time
import zlib
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from enum import Enum
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, NamedTuple

import msgpack
import orjson

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
    from mcap.records import Message

    from ._instance import DyKnowInstance

log = logging.getLogger(__name__)

FORMAT_NAME = "dyknow-record"
FORMAT_VERSION = 2  # 1 was the .dkr framing, read but no longer written
METADATA_NAME = "dyknow"  # the MCAP metadata record that makes a file one of ours
MCAP_MAGIC = b"\x89MCAP0\r\n"
# A clock on the Unix epoch (any real clock today) is recorded as it is, so Foxglove shows
# the flight's dates and lines it up with other logs of it; any other clock (a manual clock
# at 0, negative valid times) is shifted by 10^9 s, which keeps times down to -31 years
# representable and reads as "1000000000 + seconds" in a viewer.
EPOCH_SINCE = 10**18
SIM_OFFSET = 10**18
_SETTLE_MAX = 10_000  # loop iterations a replay step waits at most for the instance to idle
# the JSON encoding of values: dataclasses come to the default hook, to carry their type name
_JSON_OPTIONS = orjson.OPT_PASSTHROUGH_DATACLASS
_TYPE_KEY = "$type"
_TYPE_MARK = b'"$type"'

# A message decoder for an MCAP message encoding other than ours: (schema name, schema
# encoding, schema data, message data) → (value, valid time in ns or None for the
# message's publish time).
MessageDecoder = Callable[[str, str, bytes, bytes], tuple[Any, int | None]]


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
    """What a recording says about itself (an MCAP file's ``dyknow`` metadata record).

    ``format`` is ``mcap``, ``rosbag2`` or ``dkr`` (version 1); ``time_offset`` is what
    was added to the times to make the MCAP log and publish times; ``library`` the MCAP
    writer's name. A file not written by DyKnow has version 0, its topics as ``labels``
    and its first log time as ``start``.
    """

    version: int
    instance: str
    clock: str
    start: int
    labels: list[str] | None
    created: str
    meta: dict[str, Any]
    format: str = "mcap"
    time_offset: int = 0
    library: str = ""


def default_time_offset(now: int) -> int:
    """The time offset of a recording whose clock reads ``now`` (ns) when it starts."""
    return 0 if now >= EPOCH_SINCE else SIM_OFFSET


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


def _typed(obj: Any) -> dict[str, Any] | None:
    """A named tuple or dataclass instance as ``{"$type": name, field: value, …}``."""
    if isinstance(obj, tuple) and hasattr(obj, "_asdict"):
        return {_TYPE_KEY: type(obj).__name__, **obj._asdict()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        fields = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
        return {_TYPE_KEY: type(obj).__name__, **fields}
    return None


def _special_float(x: float) -> dict[str, str]:
    # JSON has no NaN or infinity: the value's own text, marked
    return {_TYPE_KEY: "float", "value": repr(x)}


class _Encoder:
    """JSON encoding of sample values; a value it cannot carry is recorded as its repr.

    Named tuples and dataclasses become objects with their type name under ``$type``,
    bytes ``{"$type": "bytes", "base64": …}``; a top-level NaN or infinity, an integer
    past 64 bits and a dict with keys other than strings are marked the same way, so
    they come back as they were.
    """

    def __init__(self) -> None:
        self.unencodable = 0

    def encode(self, obj: Any) -> bytes:
        """The JSON bytes of ``obj``."""
        if type(obj) is float and not math.isfinite(obj):
            obj = _special_float(obj)
        try:
            return orjson.dumps(obj, default=self.default, option=_JSON_OPTIONS)
        except TypeError:  # a key that is not a string, an int past 64 bits: the exact way
            pass
        try:
            return orjson.dumps(self._plain(obj), default=self.default, option=_JSON_OPTIONS)
        except (TypeError, RecursionError):  # nested too deep for JSON
            self.unencodable += 1
            return orjson.dumps(repr(obj))

    def default(self, obj: Any) -> Any:
        """orjson's hook: what JSON does not carry as itself, as what it carries."""
        typed = _typed(obj)
        if typed is not None:
            return typed
        if isinstance(obj, bytes | bytearray | memoryview):
            return {_TYPE_KEY: "bytes", "base64": base64.b64encode(obj).decode("ascii")}
        if isinstance(obj, tuple | set | frozenset):
            return list(obj)
        if isinstance(obj, float):  # a subclass
            return float(obj)
        dump = getattr(obj, "model_dump", None)
        if callable(dump):  # a pydantic model
            return dump(mode="json")
        # a recording must not stop for one odd value: keep what it looked like, and count it
        self.unencodable += 1
        return repr(obj)

    def _plain(self, obj: Any) -> Any:
        """``obj`` with what orjson refuses made explicit (walked in Python: slow, rare)."""
        if isinstance(obj, bool) or obj is None or isinstance(obj, str):
            return obj
        if isinstance(obj, int):
            if -(2**63) <= obj < 2**64:
                return int(obj)
            return {_TYPE_KEY: "int", "value": str(int(obj))}
        if isinstance(obj, float):
            return float(obj) if math.isfinite(obj) else _special_float(obj)
        if isinstance(obj, Enum):
            return self._plain(obj.value)
        typed = _typed(obj)
        if typed is not None:
            return {k: self._plain(v) for k, v in typed.items()}
        if isinstance(obj, dict):
            if all(type(k) is str for k in obj):
                return {k: self._plain(v) for k, v in obj.items()}
            items = [[self._plain(k), self._plain(v)] for k, v in obj.items()]
            return {_TYPE_KEY: "dict", "items": items}
        if isinstance(obj, list | tuple | set | frozenset):
            return [self._plain(x) for x in obj]
        return obj  # bytes and the rest: the default hook's


def _hashable(key: Any) -> Any:
    if isinstance(key, list):
        return tuple(_hashable(k) for k in key)
    return key


def _rebuild(obj: Any) -> Any:
    """A decoded JSON value with its ``$type`` objects made what they were recorded as."""
    if isinstance(obj, list):
        return [_rebuild(x) for x in obj]
    if not isinstance(obj, dict):
        return obj
    name = obj.get(_TYPE_KEY)
    if name is None:
        return {k: _rebuild(v) for k, v in obj.items()}
    if name == "bytes":
        return base64.b64decode(obj["base64"])
    if name == "float":
        return float(obj["value"])
    if name == "int":
        return int(obj["value"])
    if name == "dict":
        return {_hashable(_rebuild(k)): _rebuild(v) for k, v in obj["items"]}
    fields = {k: _rebuild(v) for k, v in obj.items() if k != _TYPE_KEY}
    cls = _RECORD_TYPES.get(name)  # read at decode time: a type registered later counts too
    if cls is not None:
        with contextlib.suppress(TypeError):
            return cls(**fields)
    return fields


# -- schemas -----------------------------------------------------------------------------------

_TIME_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "time",
    "description": "nanoseconds as sec * 10^9 + nsec (sec may be negative)",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": NS_PER_S - 1},
    },
    "required": ["sec", "nsec"],
}
_SCHEMA_DEPTH = 6
_SCHEMA_FIELDS = 100


def _schema_of(value: Any, depth: int = 0) -> dict[str, Any] | None:
    """A JSON schema for values shaped like ``value`` (None when nothing useful is known).

    Every JSON schema field names a type (viewers such as Foxglove read the schema to
    know a channel's fields and refuse a field without a type), so what is unknown (None,
    an empty list, past a depth) is left out rather than described as "anything".
    """
    if value is None or depth > _SCHEMA_DEPTH:
        return None
    if isinstance(value, Enum):
        return _schema_of(value.value, depth)
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int | float):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    if isinstance(value, bytes | bytearray | memoryview):
        return {
            "type": "object",
            "properties": {
                _TYPE_KEY: {"type": "string"},
                "base64": {"type": "string", "contentEncoding": "base64"},
            },
        }
    typed = _typed(value)
    if typed is not None or isinstance(value, dict):
        fields = typed if typed is not None else value
        props: dict[str, Any] = {}
        for k, v in list(fields.items())[:_SCHEMA_FIELDS]:
            if k == _TYPE_KEY or not isinstance(k, str):
                continue
            sub = _schema_of(v, depth + 1)
            if sub is not None:
                props[k] = sub
        schema: dict[str, Any] = {"type": "object", "properties": props}
        if typed is not None:
            schema["title"] = typed[_TYPE_KEY]
            props[_TYPE_KEY] = {"type": "string", "const": typed[_TYPE_KEY]}
        return schema
    if isinstance(value, list | tuple | set | frozenset):
        first = next(iter(value), None)
        items = _schema_of(first, depth + 1)
        return None if items is None else {"type": "array", "items": items}
    return None


def label_schema(label: str, value: Any) -> dict[str, Any]:
    """The JSON schema of a label's channel, its value described after ``value`` (the first).

    The value's part describes the first value recorded: a stream whose values change
    shape is still recorded exactly, the schema then describing its first value only.
    """
    props: dict[str, Any] = {"valid_time": _TIME_SCHEMA, "available_time": _TIME_SCHEMA}
    value_schema = _schema_of(value)
    if value_schema is not None:
        props = {"value": value_schema, **props}
    return {
        "title": label,
        "description": f"a sample of the DyKnow stream {label}: value, valid, available time",
        "type": "object",
        "properties": props,
        "required": ["valid_time", "available_time"],
    }


# -- writing -----------------------------------------------------------------------------------


class RecordWriter:
    """Appends samples to an MCAP recording in batches (the writing side of the format).

    ``add`` buffers; a batch is written as one zstd chunk (and flushed to the OS) every
    ``batch_size`` samples and on ``flush``/``close``, so memory stays bounded and a killed
    writer leaves a file readable up to its last batch. ``close`` writes the summary and
    indexes. ``time_offset`` (ns) is added to the times to make the MCAP log (available)
    and publish (valid) times; by default 0 when ``start`` is on the Unix epoch, else
    10^18 (``default_time_offset``).
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
        time_offset: int | None = None,
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
        self._channels: dict[str, int] = {}
        # set when samples may have been buffered out of order (a stream found late)
        self.sort_pending = False
        # mcap (with zstd and lz4, ~3.5 MB) only once a recording is made or read
        from mcap.writer import LIBRARY_IDENTIFIER, CompressionType
        from mcap.writer import Writer as McapWriter

        self.header = RecordHeader(
            version=FORMAT_VERSION,
            instance=instance,
            clock=clock,
            start=start,
            labels=None if labels is None else list(labels),
            created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            meta=dict(meta or {}),
            format="mcap",
            time_offset=default_time_offset(start) if time_offset is None else time_offset,
            library=f"dyknow; {LIBRARY_IDENTIFIER}",
        )
        try:
            self._f: IO[bytes] | None = open(self.path, "wb")  # noqa: SIM115 - see close()
        except OSError as exc:
            raise RecordError(f"{self.path}: cannot be written: {exc.strerror}") from None
        self._mcap = McapWriter(self._f, compression=CompressionType.ZSTD)
        self._mcap.start(profile="", library=self.header.library)
        self._mcap.add_metadata(METADATA_NAME, _header_metadata(self.header))
        self._f.flush()

    @property
    def unencodable(self) -> int:
        """How many values JSON could not carry and were recorded as their repr."""
        return self._enc.unencodable

    @property
    def closed(self) -> bool:
        """Whether the file is closed."""
        return self._f is None

    def add(self, label: str, value: Any, valid_time: int, available_time: int) -> None:
        """Buffer one sample; a full buffer is written as a batch."""
        if self._f is None:
            raise ValueError(f"{self.path}: the recording is closed")
        self._pending.append((label, value, valid_time, available_time))
        if len(self._pending) >= self.batch_size:
            self.flush()

    def _channel(self, label: str, value: Any) -> int:
        schema = orjson.dumps(label_schema(label, value), option=orjson.OPT_SORT_KEYS)
        schema_id = self._mcap.register_schema(label, "jsonschema", schema)
        channel = self._mcap.register_channel(label, "json", schema_id)
        self._channels[label] = channel
        return channel

    def flush(self) -> None:
        """Write what is buffered as one chunk (sorted by available time if ``sort_pending``)."""
        if not self._pending or self._f is None:
            return
        pending, self._pending = self._pending, []
        if self.sort_pending:
            pending.sort(key=lambda s: s[3])
            self.sort_pending = False
        channels, encode, add = self._channels, self._enc.encode, self._mcap.add_message
        dumps, default, options = orjson.dumps, self._enc.default, _JSON_OPTIONS
        offset, ns, message = self.header.time_offset, NS_PER_S, _MESSAGE
        for label, value, tv, ta in pending:
            channel = channels.get(label)
            if channel is None:
                channel = self._channel(label, value)
            vs, vn = divmod(tv, ns)
            as_, an = divmod(ta, ns)
            # the common case inline; a NaN or infinity, or what orjson refuses (a key that
            # is not a string, an int past 64 bits), the encoder's slower, exact way
            if type(value) is float and value - value != 0.0:
                body = encode(value)
            else:
                try:
                    body = dumps(value, default=default, option=options)
                except TypeError:
                    body = encode(value)
            data = message % (body, vs, vn, as_, an)
            log_time, publish_time = ta + offset, tv + offset
            if log_time < 0 or publish_time < 0:
                log_time, publish_time = _clamp(log_time), _clamp(publish_time)
            add(channel, log_time, data, publish_time)
        counts = self.counts
        for label, k in Counter(s[0] for s in pending).items():
            counts[label] = counts.get(label, 0) + k
        self._mcap.flush()
        self.samples += len(pending)
        self.batches += 1

    def close(self) -> None:
        """Write what is buffered, the summary and indexes, and close the file (idempotent)."""
        if self._f is None:
            return
        try:
            self.flush()
            self._mcap.finish()
        finally:
            self._f.close()
            self._f = None


_MESSAGE = b'{"value":%b,"valid_time":{"sec":%d,"nsec":%d},"available_time":{"sec":%d,"nsec":%d}}'


_SHARED_ENCODER = _Encoder()


def sample_json(value: Any, valid_time: int, available_time: int) -> bytes:
    """One sample as a recording's message holds it (JSON bytes; ``label_schema`` is its schema).

    For a live view that should show what a recording shows (the same fields, the same
    layouts in Foxglove).
    """
    vs, vn = divmod(valid_time, NS_PER_S)
    as_, an = divmod(available_time, NS_PER_S)
    return _MESSAGE % (_SHARED_ENCODER.encode(value), vs, vn, as_, an)


def _clamp(t: int) -> int:
    # below what the offset makes representable (an int64 time plus an offset up to 10^18
    # stays below 2^64): the message keeps the exact time
    return max(t, 0)


def _header_metadata(h: RecordHeader) -> dict[str, str]:
    """The ``dyknow`` metadata record of a header (MCAP metadata values are strings)."""
    return {
        "format": FORMAT_NAME,
        "version": str(h.version),
        "instance": h.instance,
        "clock": h.clock,
        "start": str(h.start),
        "labels": json.dumps(h.labels),
        "created": h.created,
        "meta": json.dumps(h.meta, default=repr, sort_keys=True),
        "time_offset": str(h.time_offset),
        "time_unit": "ns",
    }


class Recorder:
    """Records every sample of some streams of an instance to a file, as they are published.

    ``labels`` lists the streams (they must exist); ``None`` records every stream,
    including those created after the recorder started. Use it as an async context
    manager (it then flushes every ``flush_interval`` seconds of wall time), or call
    ``start``/``close`` yourself. ``rename`` records a label under another name (an
    imported stream under its semantic label). ``since`` (ns) also records what the
    streams' caches hold that became available at or after it; ``limit`` stops recording
    after that many samples (``done`` is then set). Values are kept as JSON carries them:
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
        now = clock.now()
        self._t0 = now if self._since is None else self._since
        self.writer = RecordWriter(
            self.path,
            time_offset=default_time_offset(now),
            instance=self.instance.name,
            clock=type(clock).__name__,
            # when it started, not ``since``: a replay's clock starts there (or at the first
            # sample, if earlier), and a ``since`` of 0 on a real clock would have its
            # timers run through every period from 1970
            start=now,
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
        room = None if limit is None else limit - self.recorded
        pending = writer._pending  # appended here in place of add(): this runs per sample
        n = len(pending)
        for value, tv, ta in batch:
            # available times are unique and increasing per stream: this drops what a
            # history replay from the cache would deliver twice
            if ta > last:
                if room is not None and len(pending) - n >= room:
                    break
                pending.append((name, value, tv, ta))
                last = ta
        self._last_ta[label] = last
        self.recorded += len(pending) - n
        if limit is not None and self.recorded >= limit:
            self.done.set()
        if len(pending) >= writer.batch_size:
            writer.flush()
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

# The .dkr format (version 1, read only): the magic line, then frames of a 4-byte big-endian
# payload length, the payload's CRC-32 and the msgpack payload; the first frame the header,
# every later one a batch {"l": [label, …], "s": [[label index, value, valid, available], …]}.
DKR_MAGIC = b"DYKNOW-REC\n"
_DKR_VERSION = 1
_FRAME = struct.Struct(">II")  # payload length, CRC-32 of the payload
_MAX_FRAME = 64 * 1024 * 1024  # larger is a corrupt length, not a batch
_EXT_TYPED = 1  # msgpack extension of .dkr files: a named tuple or dataclass


def _dkr_ext_hook(code: int, data: bytes) -> Any:
    if code != _EXT_TYPED:
        return msgpack.ExtType(code, data)
    name, fields = msgpack.unpackb(data, raw=False, strict_map_key=False, ext_hook=_dkr_ext_hook)
    cls = _RECORD_TYPES.get(name)
    if cls is not None:
        with contextlib.suppress(TypeError):
            return cls(**fields)
    return dict(fields)


class Recording:
    """A recording opened for reading: its header, then its samples in available-time order.

    Reads our MCAP recordings, any other MCAP file, and old ``.dkr`` files. In an MCAP
    file not written by DyKnow every topic is a label (``topic_label``); a ``json``
    channel's messages are the values, with the publish time as the valid time (the log
    time when it is 0) and the log time as the available time. ``decoders`` maps another
    message encoding (``cdr``, ``protobuf``, …) to a ``MessageDecoder``; messages no
    decoder reads are skipped and counted per label in ``undecodable`` (why in
    ``problems``). A file whose writer did not finish (no summary) is read in file order
    up to its last complete chunk (``truncated``).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        decoders: Mapping[str, MessageDecoder] | None = None,
    ) -> None:
        self.path = Path(path)
        self.truncated = False
        self.undecodable: dict[str, int] = {}
        self.problems: dict[str, str] = {}
        self._decoders = dict(decoders or {})
        self._offset = 0
        try:
            with open(self.path, "rb") as f:
                magic = f.read(len(DKR_MAGIC))
                f.seek(0)
                if magic.startswith(MCAP_MAGIC):
                    self.header = self._mcap_header(f)
                elif magic == DKR_MAGIC:
                    f.seek(len(DKR_MAGIC))
                    self.header = self._dkr_header(f)
                    self._offset = f.tell()
                else:
                    raise self._fail(
                        "not a recording (neither an MCAP file nor a DyKnow .dkr recording)"
                    )
        except IsADirectoryError:
            raise RecordError(f"{self.path}: is a directory, not a recording") from None
        except FileNotFoundError:
            raise RecordError(f"{self.path}: no such file") from None
        except OSError as exc:
            raise RecordError(f"{self.path}: cannot be read: {exc.strerror}") from None

    def _fail(self, what: str) -> RecordError:
        return RecordError(f"{self.path}: {what}")

    @property
    def ours(self) -> bool:
        """Whether DyKnow wrote the file (else its topics are labels, its times log times)."""
        return self.header.version > 0

    # -- MCAP ---------------------------------------------------------------------------------
    def _mcap_header(self, f: IO[bytes]) -> RecordHeader:
        from mcap.reader import SeekingReader
        from mcap.records import Chunk, Header, Message, Metadata
        from mcap.stream_reader import StreamReader

        header: Header | None = None
        meta: dict[str, str] | None = None
        first: int | None = None
        try:
            for record in StreamReader(f, emit_chunks=True).records:
                if isinstance(record, Header):
                    header = record
                elif isinstance(record, Metadata) and record.name == METADATA_NAME:
                    meta = dict(record.metadata)
                    break
                elif isinstance(record, Chunk):
                    first = record.message_start_time
                    break
                elif isinstance(record, Message):
                    first = record.log_time
                    break
        except Exception as exc:  # a short read raises one of several kinds
            if header is None:
                raise self._fail(f"corrupt header: {type(exc).__name__}: {exc}") from None
        if header is None:
            raise self._fail("corrupt header: no MCAP header record")
        if meta is not None:
            return self._our_header(meta, header.library)
        labels: list[str] = []
        with contextlib.suppress(Exception):  # no summary: a file whose writer did not finish
            summary = SeekingReader(f).get_summary() if _finished(f) else None
            if summary is not None:
                labels = sorted({topic_label(c.topic) for c in summary.channels.values()})
                stats = summary.statistics
                if stats is not None and stats.message_count:
                    first = stats.message_start_time
        return RecordHeader(
            version=0,
            instance="",
            clock="",
            start=first or 0,
            labels=labels,
            created="",
            meta={"profile": header.profile} if header.profile else {},
            format="mcap",
            time_offset=0,
            library=header.library,
        )

    def _our_header(self, m: dict[str, str], library: str) -> RecordHeader:
        if m.get("format") != FORMAT_NAME:
            raise self._fail("corrupt header: its dyknow metadata is not a dyknow-record header")
        version = m.get("version")
        if version != str(FORMAT_VERSION):
            raise self._fail(
                f"format version {version} is not supported (this dyknow reads version "
                f"{FORMAT_VERSION}, and .dkr files of version {_DKR_VERSION})"
            )
        try:
            labels = json.loads(m.get("labels", "null"))
            return RecordHeader(
                version=FORMAT_VERSION,
                instance=m.get("instance", ""),
                clock=m.get("clock", ""),
                start=int(m.get("start", "0")),
                labels=None if labels is None else [str(x) for x in labels],
                created=m.get("created", ""),
                meta=dict(json.loads(m.get("meta", "{}"))),
                format="mcap",
                time_offset=int(m.get("time_offset", "0")),
                library=library,
            )
        except (TypeError, ValueError) as exc:
            raise self._fail(f"corrupt header: {exc}") from None

    def _mcap_samples(self) -> Iterator[RecordedSample]:
        samples = self._mcap_read()
        if self.ours:
            return samples
        try:
            with open(self.path, "rb") as f:
                if _finished(f):
                    return samples
        except OSError as exc:
            raise self._fail(f"cannot be read: {exc.strerror}") from None
        # another writer's unfinished file, in file order: its log times may not be (an
        # index would have ordered them), so in memory, as mcap's own reader does then
        return iter(sorted(samples, key=lambda s: s.available_time))

    def _mcap_read(self) -> Iterator[RecordedSample]:
        try:
            f = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise self._fail(f"cannot be read: {exc.strerror}") from None
        from mcap.reader import NonSeekingReader, SeekingReader

        with f:
            size = os.fstat(f.fileno()).st_size
            finished = _finished(f)
            messages: Iterator[tuple[Any, Any, Message]]
            chunks: list[tuple[int, int]] = []  # (start, end) byte offsets, to name a bad one
            if finished:
                reader = SeekingReader(f, validate_crcs=True)
                with contextlib.suppress(Exception):  # a bad summary fails in iter_messages
                    summary = reader.get_summary()
                    if summary is not None:
                        chunks = [
                            (c.chunk_start_offset, c.chunk_start_offset + c.chunk_length)
                            for c in summary.chunk_indexes
                        ]
                messages = reader.iter_messages(log_time_order=True)
            else:
                f.seek(0)
                messages = NonSeekingReader(f, validate_crcs=True).iter_messages(
                    log_time_order=False
                )
            decoders: dict[int, Callable[[Message], RecordedSample | None]] = {}
            while True:
                try:
                    schema, channel, message = next(messages)
                except StopIteration:
                    return
                except Exception as exc:  # the reader raises several kinds on bad input
                    if not finished and f.tell() >= size:
                        self.truncated = True  # the writer stopped mid-chunk
                        return
                    where = f.tell()
                    # the reader stops past the chunk it could not read: name where it starts
                    start = next((a for a, b in chunks if a < where <= b), None)
                    if start is None:  # no chunk index: walk the records to it
                        start = _chunk_at(f, where)
                    at = f"chunk at byte {start}" if start is not None else f"near byte {where}"
                    raise self._fail(f"corrupt {at}: {type(exc).__name__}: {exc}") from None
                decode = decoders.get(channel.id)
                if decode is None:
                    decode = decoders[channel.id] = self._channel_decoder(schema, channel)
                sample = decode(message)
                if sample is not None:
                    yield sample

    def _skip(self, topic: str, why: str) -> None:
        self.undecodable[topic] = self.undecodable.get(topic, 0) + 1
        self.problems.setdefault(topic, why)

    def _channel_decoder(
        self, schema: Any, channel: Any
    ) -> Callable[[Message], RecordedSample | None]:
        """How the messages of one channel become samples."""
        topic: str = channel.topic
        encoding: str = channel.message_encoding
        if self.ours and encoding == "json":
            return self._our_decoder(topic)
        topic = topic_label(topic)
        if encoding == "json":

            def foreign_json(m: Message) -> RecordedSample | None:
                try:
                    value = orjson.loads(m.data)
                except orjson.JSONDecodeError as exc:
                    self._skip(topic, f"not JSON: {exc}")
                    return None
                return RecordedSample(topic, value, m.publish_time or m.log_time, m.log_time)

            return foreign_json
        decoder = self._decoders.get(encoding)
        if decoder is None:

            def undecodable(m: Message) -> None:
                self._skip(topic, f"message encoding {encoding!r}: no decoder for it")

            return undecodable
        name, kind, text = (
            ("", "", b"") if schema is None else (schema.name, schema.encoding, bytes(schema.data))
        )

        def decoded(m: Message) -> RecordedSample | None:
            try:
                value, valid = decoder(name, kind, text, bytes(m.data))
            except Exception as exc:  # a foreign decoder's failure skips the message
                self._skip(topic, f"{type(exc).__name__}: {exc}")
                return None
            if valid is None:
                valid = m.publish_time or m.log_time
            return RecordedSample(topic, value, valid, m.log_time)

        return decoded

    def _our_decoder(self, topic: str) -> Callable[[Message], RecordedSample]:
        loads, rebuild, mark, ns = orjson.loads, _rebuild, _TYPE_MARK, NS_PER_S

        def ours(m: Message) -> RecordedSample:
            data = m.data
            try:
                d = loads(data)
                value = d.get("value")
                if mark in data:
                    value = rebuild(value)
                tv, ta = d["valid_time"], d["available_time"]
                return RecordedSample(
                    topic, value, tv["sec"] * ns + tv["nsec"], ta["sec"] * ns + ta["nsec"]
                )
            except (orjson.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
                raise self._fail(
                    f"message {m.sequence} of {topic!r} (log time {m.log_time}) is malformed: "
                    f"{type(exc).__name__}: {exc}"
                ) from None

        return ours

    # -- .dkr (version 1) ---------------------------------------------------------------------
    def _unpack(self, payload: bytes) -> Any:
        return msgpack.unpackb(
            payload, raw=False, strict_map_key=False, ext_hook=_dkr_ext_hook, use_list=True
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

    def _dkr_header(self, f: IO[bytes]) -> RecordHeader:
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
        if version != _DKR_VERSION:
            raise self._fail(
                f"format version {version!r} is not supported (this dyknow reads .dkr files "
                f"of version {_DKR_VERSION}, and MCAP recordings)"
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
                format="dkr",
            )
        except (TypeError, ValueError) as exc:
            raise self._fail(f"corrupt header: {exc}") from None

    def _dkr_samples(self) -> Iterator[RecordedSample]:
        """Each complete batch's samples in file order; stops (``truncated``) at a cut one."""
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
                yield from self._dkr_batch(payload, n, at)

    def _dkr_batch(self, payload: bytes, n: int, at: int) -> list[RecordedSample]:
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

    # -- either -------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[RecordedSample]:
        self.truncated = False
        self.undecodable.clear()
        self.problems.clear()
        if self.header.format == "dkr":
            return self._dkr_samples()
        return self._mcap_samples()

    def info(self) -> dict[str, Any]:
        """The header, samples per label, the valid and available time spans, truncation."""
        return recording_info(self, str(self.path))


def recording_info(rec: Any, file: str) -> dict[str, Any]:
    """What ``Recording.info`` says, of any recording read as samples (one pass over them).

    ``rec`` has a ``header`` (RecordHeader), and ``truncated``, ``undecodable`` and
    ``problems`` once read, as ``Recording`` has.
    """
    counts: dict[str, int] = {}
    tv_lo = tv_hi = ta_lo = ta_hi = None
    for s in rec:
        counts[s.label] = counts.get(s.label, 0) + 1
        tv_lo = s.valid_time if tv_lo is None else min(tv_lo, s.valid_time)
        tv_hi = s.valid_time if tv_hi is None else max(tv_hi, s.valid_time)
        ta_lo = s.available_time if ta_lo is None else min(ta_lo, s.available_time)
        ta_hi = s.available_time if ta_hi is None else max(ta_hi, s.available_time)
    header: RecordHeader = rec.header
    return {
        "file": file,
        **dataclasses.asdict(header),
        "samples": sum(counts.values()),
        "counts": dict(sorted(counts.items())),
        "valid_span": None if tv_lo is None else [tv_lo, tv_hi],
        "available_span": None if ta_lo is None else [ta_lo, ta_hi],
        "truncated": bool(getattr(rec, "truncated", False)),
        "undecodable": dict(sorted(getattr(rec, "undecodable", {}).items())),
        "problems": dict(sorted(getattr(rec, "problems", {}).items())),
    }


def _chunk_at(f: IO[bytes], where: int) -> int | None:
    """The byte the chunk record holding ``where`` (its end included) starts at, if any.

    For a file without a chunk index: walks the records' framing (opcode, length) from the
    magic; a damaged length leads nowhere and gives None.
    """
    pos = len(MCAP_MAGIC)
    while pos < where:
        f.seek(pos)
        head = f.read(9)
        if len(head) < 9:
            return None
        end = pos + 9 + int.from_bytes(head[1:], "little")
        if head[0] == 0x06 and pos < where <= end:  # 0x06: a Chunk record
            return pos
        pos = end
    return None


def _finished(f: IO[bytes]) -> bool:
    """Whether an MCAP file ends with its magic (its writer finished: a summary may follow)."""
    size = os.fstat(f.fileno()).st_size
    done = False
    if size >= 2 * len(MCAP_MAGIC):
        f.seek(size - len(MCAP_MAGIC))
        done = f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    f.seek(0)
    return done


def topic_label(topic: str) -> str:
    """The label of a topic of a file not written by DyKnow: without its leading ``/``.

    (A KPL label does not start with one, and no DyKnow label needs to.)
    """
    return topic.removeprefix("/")


def read_recording(
    path: str | os.PathLike[str], *, decoders: Mapping[str, MessageDecoder] | None = None
) -> Recording:
    """Open a recording for reading (RecordError naming the file and what is wrong)."""
    return Recording(path, decoders=decoders)


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
    path: str | os.PathLike[str] | Iterable[RecordedSample],
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
    Call it inside ``async with instance`` so the instance's periodic tasks run. ``path``
    is a recording's path, or samples in order of available time (a ``Recording``, or any
    other reader's, whose ``truncated`` is then reported if it has one).
    """
    clock = instance.clock
    if not isinstance(clock, ManualClock):
        raise TypeError(
            f"replay needs an instance driven by a ManualClock, not a {type(clock).__name__}"
        )
    if speed is not None and not speed > 0:
        raise ValueError(f"speed must be > 0 (or None for as fast as possible), got {speed}")
    rec = Recording(path) if isinstance(path, str | os.PathLike) else path
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
    summary.truncated = bool(getattr(rec, "truncated", False))
    if tail > 0:
        await advance_to(clock, clock.now() + round(tail * NS_PER_S))
    return summary


__all__ = [
    "FORMAT_VERSION",
    "MessageDecoder",
    "RecordError",
    "RecordHeader",
    "RecordWriter",
    "RecordedSample",
    "Recorder",
    "Recording",
    "ReplaySummary",
    "advance_to",
    "default_time_offset",
    "label_schema",
    "read_recording",
    "recording_info",
    "replay",
    "sample_json",
    "settle",
    "topic_label",
]
