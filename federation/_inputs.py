"""Inputs of a node's application: outside messages pushed into the application's sources.

Each ``[[inputs]]`` table of a node's config (docs/application.md) names where messages
come from (a zenoh key expression, an MQTT topic, a recorded file, a Python async
generator) and how their fields map to source labels. A message's valid time is its own
time stamp where it has one (the ``time`` field, else the transport's stamp), else its
arrival. A message that cannot be used is counted by reason and logged, never raised:
a bad sensor must not stop the node.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import contextlib
import inspect
import itertools
import json
import logging
import re
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import msgpack
from pydantic import BaseModel, ConfigDict, Field, field_validator

from dyknow_core import ClosedError

from ._quote import quoted

if TYPE_CHECKING:
    from dyknow_core import DyKnowInstance, Source

__all__ = [
    "FileInput",
    "InputRunner",
    "InputSettings",
    "InputStats",
    "MqttInput",
    "PythonInput",
    "Ros2Input",
    "RosbagInput",
    "ZenohInput",
    "input_runner",
]

log = logging.getLogger(__name__)

_UNITS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}
_PLACEHOLDER = re.compile(r"\{([^{}]+)\}")
_WHOLE = "."  # the field path meaning the whole message
_ERRNO = re.compile(r"\[Errno -?\d+\] ")  # an OS error's number, not for a person
# a valid time more than this many times the wall clock's (after the year 2500) is a unit
# mistake (ms read as s: 1000 times), not a forecast or a fast simulation: pushed, it would
# stay its stream's latest sample for ever, hiding every correct one
_MAX_AHEAD_FACTOR = 10
_LOGGED_PER_REASON = 5  # then one log line every _LOG_EVERY messages of that reason
_LOG_EVERY = 1000
_TOPIC_SHOWN = 120  # characters of a topic a warning names (an MQTT topic may be 64 KiB)
_QUEUE = 10_000  # messages waiting between a transport's thread and the loop
# what a placeholder may put in a label: one chunk as dyknow_core's object identifiers
# are (no whitespace, '/', braces or glob characters), bounded; {topic} may hold '/'. No
# lone surrogate either (JSON's "\ud800"): no UTF-8, such a label could go nowhere (a
# topic, a key, a JSON or msgpack answer listing it would fail)
_CHUNK_MAX = 200
_CHUNK = re.compile(rf"[^\s/{{}}*?\[\]\ud800-\udfff]{{1,{_CHUNK_MAX}}}")
_TOPIC_CHUNKS = re.compile(rf"[^\s{{}}*?\[\]\ud800-\udfff]{{1,{_CHUNK_MAX}}}")
_VALUE_SHOWN = 40  # characters of a refused placeholder value a warning shows
_INT_CHUNK = 10 ** (_CHUNK_MAX - 1)  # an integer below it in size is one chunk, sign and all


# -- the config ------------------------------------------------------------------------------


class _InputBase(BaseModel):
    """What every input has: the field→label map and where the valid time comes from."""

    # defer_build: a config's inputs are checked by PlatformConfig's own schema, so this
    # model's validator is built only if something validates one on its own (~0.3 MB of
    # a node's memory for the inputs, outputs and sharing rules together)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True)

    name: str | None = Field(default=None, description="A name for logs and counts.")
    fields: dict[str, str] = Field(
        min_length=1,
        description="message field (dotted path, '.' = whole message) -> source label",
    )
    time: str | None = Field(default=None, description="The message field holding valid time.")
    time_unit: Literal["s", "ms", "us", "ns"] = "s"
    create: bool = Field(
        default=False, description="Labels not declared as sources are created on first use."
    )
    max_streams: int = Field(
        default=1024,
        ge=1,
        description="With create: at most this many of the streams it made at once (one "
        "removed no longer counts); a new object's message past it is a bad message "
        "(too-many-streams).",
    )

    @field_validator("fields")
    @classmethod
    def _labels(cls, value: dict[str, str]) -> dict[str, str]:
        for path, label in value.items():
            if not path or not label:
                raise ValueError("field paths and labels must not be empty")
            for name in _PLACEHOLDER.findall(label):
                if not name.strip():
                    raise ValueError(f"label {label!r}: empty placeholder {{}}")
        return value

    def title(self) -> str:
        """How logs and counts name this input."""
        return self.name or self.default_title()

    def default_title(self) -> str:
        """The name when none is given."""
        raise NotImplementedError

    def relative_to(self, base: Path) -> "_InputBase":
        """A copy whose relative paths are resolved against ``base`` (files only have some)."""
        return self


class ZenohInput(_InputBase):
    """``kind = "zenoh"``: what zenoh publishers put on ``key`` (JSON or msgpack payloads).

    Without ``connect`` the node's own zenoh session subscribes (its transport must then
    be zenoh); with it, a session of the input's own (client mode) connects there.
    """

    kind: Literal["zenoh"]
    key: str = Field(min_length=1)
    format: Literal["json", "msgpack"] = "json"
    connect: tuple[str, ...] | None = None

    def default_title(self) -> str:
        """``zenoh KEY``."""
        return f"zenoh {self.key}"


class MqttInput(_InputBase):
    """``kind = "mqtt"``: JSON messages on an MQTT topic (``+``/``#`` wildcards)."""

    kind: Literal["mqtt"]
    topic: str = Field(min_length=1)
    host: str = "127.0.0.1"
    port: int = Field(default=1883, gt=0, lt=65536)
    qos: Literal[0, 1, 2] = 0
    username: str | None = None
    password_file: Path | None = None

    def default_title(self) -> str:
        """``mqtt TOPIC``."""
        return f"mqtt {self.topic}"

    def relative_to(self, base: Path) -> "MqttInput":
        """The password file resolved against ``base``."""
        if self.password_file is not None and not self.password_file.is_absolute():
            return self.model_copy(update={"password_file": base / self.password_file})
        return self


class FileInput(_InputBase):
    """``kind = "file"``: a recorded JSON-lines or CSV file, replayed once (or looped).

    ``pace = "recorded"`` keeps the recorded gaps between messages (by the ``time``
    field, which it then needs); ``"fast"`` pushes everything at once. Valid times are
    the recorded ones, shifted by ``shift`` seconds (``"now"``: the first message's time
    becomes the start of the replay).
    """

    kind: Literal["file"]
    path: Path
    format: Literal["jsonl", "csv"] | None = None
    pace: Literal["recorded", "fast"] = "recorded"
    speed: float = Field(default=1.0, gt=0)
    loop: bool = False
    shift: Literal["none", "now"] = "none"

    def default_title(self) -> str:
        """``file PATH``."""
        return f"file {self.path}"

    def file_format(self) -> str:
        """``jsonl`` or ``csv``: the given format, or the file's suffix."""
        if self.format is not None:
            return self.format
        return "csv" if self.path.suffix.lower() == ".csv" else "jsonl"

    def relative_to(self, base: Path) -> "FileInput":
        """The file resolved against ``base``."""
        if not self.path.is_absolute():
            return self.model_copy(update={"path": base / self.path})
        return self


class PythonInput(_InputBase):
    """``kind = "python"``: ``entry = "module:callable"`` returning an async iterator of messages.

    The callable is called with ``args`` as keyword arguments; each item it yields is a
    message (a mapping, or any value with ``fields = {"." = label}``).
    """

    kind: Literal["python"]
    entry: str = Field(pattern=r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")
    args: dict[str, Any] = Field(default_factory=dict)

    def default_title(self) -> str:
        """``python ENTRY``."""
        return f"python {self.entry}"


class Ros2Input(_InputBase):
    """``kind = "ros2"``: a ROS 2 topic through rmw_zenoh, CDR decoded (federation/_ros.py).

    Subscribes to ``<domain>/<topic>/<type>/<type hash>`` as rmw_zenoh puts it (any type
    and hash unless ``type`` is given); a message's ``header.stamp`` is its valid time.
    """

    kind: Literal["ros2"]
    topic: str = Field(pattern=r"^/?[A-Za-z_~][A-Za-z0-9_/~]*$")
    domain: int = Field(default=0, ge=0, le=232)
    type: str | None = Field(default=None, pattern=r"^[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+$")
    distro: str = "humble"
    connect: tuple[str, ...] | None = None

    def default_title(self) -> str:
        """``ros2 TOPIC``."""
        return f"ros2 {self.topic}"


class RosbagInput(_InputBase):
    """``kind = "rosbag"``: one topic of a rosbag2 directory or an MCAP file, replayed."""

    kind: Literal["rosbag"]
    path: Path
    topic: str = Field(min_length=1)
    pace: Literal["recorded", "fast"] = "recorded"
    speed: float = Field(default=1.0, gt=0)
    shift: Literal["none", "now"] = "none"
    distro: str = "humble"

    def default_title(self) -> str:
        """``rosbag PATH TOPIC``."""
        return f"rosbag {self.path} {self.topic}"

    def relative_to(self, base: Path) -> "RosbagInput":
        """The bag resolved against ``base``."""
        if not self.path.is_absolute():
            return self.model_copy(update={"path": base / self.path})
        return self


InputSettings = Annotated[
    ZenohInput | MqttInput | FileInput | PythonInput | Ros2Input | RosbagInput,
    Field(discriminator="kind"),
]


# -- mapping messages to samples (the hot path: plain code) ----------------------------------


class BadMessage(Exception):
    """A message that cannot be used; the reason is counted and logged."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(reason)
        self.reason = reason
        self.detail = detail


_MISSING = object()


def _get(message: Any, path: str) -> Any:
    """The field at a dotted path (``pose.position.x``, ``items.0``), or _MISSING."""
    if path == _WHOLE:
        return message
    value = message
    for part in path.split("."):
        if isinstance(value, Mapping):
            value = value.get(part, _MISSING)
        elif (
            isinstance(value, list | tuple)
            and part.isdecimal()
            and part.isascii()  # "²" is a digit int() refuses
            and int(part) < len(value)
        ):
            value = value[int(part)]
        else:
            value = getattr(value, part, _MISSING)
        if value is _MISSING:
            return _MISSING
    return value


def _shape(message: Any, most: int = 10) -> str:
    """What a message holds, for the warning that none of the fields is in it."""
    if isinstance(message, Mapping):
        keys = [str(k)[:40] for k in itertools.islice(message, most + 1)]
        more = ", …" if len(keys) > most else ""
        return f"it has {', '.join(keys[:most]) or 'no field'}{more}"
    if isinstance(message, list | tuple):
        return "a list"
    return f"a {type(message).__name__}"


class InputStats:
    """What an input received: messages, samples pushed, bad messages by reason."""

    def __init__(self, title: str) -> None:
        self.title = title
        self.received = 0
        self.samples = 0
        self.bad: Counter[str] = Counter()

    def as_dict(self) -> dict[str, Any]:
        """The counts, as JSON-able data."""
        return {
            "input": self.title,
            "received": self.received,
            "samples": self.samples,
            "bad": dict(self.bad),
        }


class _Mapper:
    """Turns one message into samples pushed to the instance's sources."""

    def __init__(self, settings: _InputBase, instance: "DyKnowInstance", stats: InputStats) -> None:
        self.instance = instance
        self.stats = stats
        self.title = settings.title()
        self.fields = [
            (path, label, _PLACEHOLDER.findall(label)) for path, label in settings.fields.items()
        ]
        self.time = settings.time
        self.unit = _UNITS[settings.time_unit]
        self.unit_name = settings.time_unit
        self.create = settings.create
        self.max_streams = settings.max_streams
        # the streams this input made that still exist: whoever publishes names the objects
        self.made: set[str] = set()
        self.sources: dict[str, Source] = {}
        # the fixed labels whose stream was removed while the input ran: their messages'
        # warning says so (a set no larger than `fields`)
        self.fixed = {label for _, label, holes in self.fields if not holes}
        self.removed: set[str] = set()
        # a stream removed while the input runs (an import that ended, an object removed)
        # is forgotten at once: its closed source would refuse every later message
        self._stop_listening = instance.on_label_change(self._label_changed)

    def close(self) -> None:
        """Stop following the instance's label changes: the input is done with it."""
        # the instance outlives the input (an application stopped or refused): its
        # listener kept the mapper and every source it knew for the instance's life
        self._stop_listening()

    def _label_changed(self, label: str, published: bool) -> None:
        if not published:
            self.sources.pop(label, None)
            self.made.discard(label)
            if label in self.fixed:
                self.removed.add(label)

    def source(self, label: str) -> "Source":
        """The source publishing ``label`` (created when the input may create it)."""
        src = self.sources.get(label)
        if src is not None:
            return src
        proc = self.instance.processes.get(f"source:{label}")
        from dyknow_core import Source

        if isinstance(proc, Source):
            src = proc
        elif self.instance.has_label(label):
            raise BadMessage("not-a-source", f"{label!r} is computed here, not a source")
        elif self.create:
            if len(self.made) >= self.max_streams:
                why = (
                    f"{label!r} would be a new stream: this input has "
                    f"max_streams = {self.max_streams} of its own already"
                )
                raise BadMessage("too-many-streams", why)
            src = self.instance.add_source(label)
            self.made.add(label)
        elif label in self.removed:
            why = f"the stream {label!r} was removed: no source here until one is made again"
            raise BadMessage("no-source", why)
        else:
            why = f"no source {label!r} (declare it in the application, or create = true)"
            raise BadMessage("no-source", why)
        self.removed.discard(label)
        self.sources[label] = src
        return src

    def valid_time(self, message: Any, stamp: int | None) -> int | None:
        """The message's own time (its ``time`` field, else ``stamp``); None: its arrival."""
        if self.time is not None:
            t = _get(message, self.time)
            if t is not _MISSING and t is not None:
                if isinstance(t, bool) or not isinstance(t, int | float):
                    try:
                        t = float(t)
                    except (TypeError, ValueError):
                        why = f"{self.time} = {t!r} is not a number"
                        raise BadMessage("bad-time", why) from None
                if t != t or t in (float("inf"), float("-inf")):
                    raise BadMessage("bad-time", f"{self.time} = {t!r}")
                if isinstance(t, int):
                    return t * self.unit
                whole = int(t)  # apart: epoch seconds times 1e9 lose the fraction in a float
                return whole * self.unit + round((t - whole) * self.unit)
        return stamp

    def push(
        self,
        message: Any,
        *,
        stamp: int | None = None,
        topic: str | None = None,
        valid: int | None = None,
    ) -> None:
        """Map one message to samples and push them, each field on its own.

        A field that cannot be used costs its own sample only: the others are pushed and
        counted all the same, then BadMessage names the first field's reason (so does
        a message none of whose fields is in it, or whose time is bad).
        """
        if valid is None:  # still None after this: the source stamps the arrival
            valid = self.valid_time(message, stamp)
            now = time.time_ns()
            if valid is not None and valid > now * _MAX_AHEAD_FACTOR:
                ahead = (valid - now) / 86_400e9
                why = (
                    f"{self.time or 'the stamp'} is {ahead:.3g} days after the message's arrival "
                    f"(time_unit {self.unit_name!r}: is the time in another unit?)"
                )
                raise BadMessage("bad-time", why)
        pushed = 0
        failed: BadMessage | None = None
        for path, label, holes in self.fields:
            value = _get(message, path)
            if value is _MISSING:
                continue
            try:
                if holes:
                    label = self._fill(label, holes, message, topic)
                self.source(label).push(value, valid)
            except BadMessage as exc:
                failed = failed or exc
            except ClosedError:  # a source that ended keeping its stream (an import's)
                why = f"the stream {label!r} is closed: its source ended"
                failed = failed or BadMessage("no-source", why)
            except Exception as exc:  # a value the stream refuses
                failed = failed or BadMessage("refused", f"{type(exc).__name__}: {exc}")
            else:
                pushed += 1
        self.stats.samples += pushed
        if failed is not None:
            raise failed
        if not pushed:
            names = ", ".join(p for p, _, _ in self.fields)
            raise BadMessage(
                "no-field", f"none of the fields {names} in the message ({_shape(message)})"
            )

    @staticmethod
    def _fill(label: str, holes: list[str], message: Any, topic: str | None) -> str:
        out = label
        for hole in holes:
            if hole == "topic" and topic is not None:
                part: Any = topic
            else:
                part = _get(message, hole)
            if part is _MISSING or part is None or isinstance(part, Mapping | list | tuple):
                why = f"label {label!r} needs field {hole!r}"
                raise BadMessage("no-label-field", why + (" (it is null)" if part is None else ""))
            if isinstance(part, str):
                text = part
            elif isinstance(part, int) and not isinstance(part, bool):
                # an id is often a number: 7 names "7"; str() of a huge one would raise
                if not -_INT_CHUNK < part < _INT_CHUNK:
                    why = (
                        f"label {label!r}: {hole} is an integer of over {_CHUNK_MAX - 1} "
                        "digits: not one chunk of a label"
                    )
                    raise BadMessage("bad-label-field", why)
                text = str(part)
            else:
                # "True", "None" or "1.0" would name a stream the sender hardly meant
                why = (
                    f"label {label!r}: {hole} = {repr(part)[:_VALUE_SHOWN]} is a "
                    f"{type(part).__name__}, not a string or an integer"
                )
                raise BadMessage("bad-label-field", why)
            if not (_TOPIC_CHUNKS if hole == "topic" else _CHUNK).fullmatch(text):
                # the sender names the stream: a label no pattern could reach, or a
                # megabyte's, is refused here, never made
                shown = text[:_VALUE_SHOWN] + "…" if len(text) > _VALUE_SHOWN else text
                why = (
                    f"label {label!r}: {hole} = {shown!r} is not one chunk of a label "
                    f"(1-{_CHUNK_MAX} characters, no whitespace, '/', braces or *?[])"
                )
                raise BadMessage("bad-label-field", why)
            out = out.replace("{" + hole + "}", text)
        return out

    def handle(
        self,
        message: Any,
        *,
        stamp: int | None = None,
        topic: str | None = None,
        valid: int | None = None,
    ) -> None:
        """`push`, counting (and logging) a bad message instead of raising."""
        self.stats.received += 1
        try:
            self.push(message, stamp=stamp, topic=topic, valid=valid)
        except BadMessage as exc:
            self.bad(exc.reason, exc.detail, topic=topic)
        except Exception as exc:  # a value the stream refuses (closed, wrong type, …)
            self.bad("refused", f"{type(exc).__name__}: {exc}", topic=topic)

    def bad(self, reason: str, detail: str, *, topic: str | None = None) -> None:
        """Count a bad message; log the first few of each reason, then one in _LOG_EVERY."""
        n = self.stats.bad[reason] = self.stats.bad[reason] + 1
        if n <= _LOGGED_PER_REASON or n % _LOG_EVERY == 0:
            # the topic it came on: of many sensors on a wildcard, which one misbehaves
            on = ""
            if topic is not None:
                cut = topic[:_TOPIC_SHOWN] + "…" if len(topic) > _TOPIC_SHOWN else topic
                # escaped too: a zenoh key may hold a newline (whoever puts on it chooses)
                on = f" on {quoted(cut)}"
            # the detail may quote the message: one line, bounded (a sender's newline would
            # forge a log line; a megabyte's value would be logged whole)
            log.warning(
                "input %s: bad message #%d (%s)%s: %s", self.title, n, reason, on, quoted(detail)
            )

    def decode(self, payload: bytes, fmt: str) -> Any:
        """A JSON or msgpack payload as data; BadMessage naming why not."""
        try:
            if fmt == "msgpack":
                return msgpack.unpackb(payload, raw=False, strict_map_key=False)
            return json.loads(payload)
        except Exception as exc:
            # JSON's words say where it stopped; msgpack's errors are often their class only
            words = str(exc) if isinstance(exc, json.JSONDecodeError) else ""
            raise BadMessage(f"not-{fmt}", words or f"{type(exc).__name__}: {exc}") from None


# -- running the inputs ----------------------------------------------------------------------


class InputRunner:
    """One input, running as a task of the node; `stats` tells what it received."""

    def __init__(self, settings: _InputBase, instance: "DyKnowInstance") -> None:
        self.settings = settings
        self.stats = InputStats(settings.title())
        self.mapper = _Mapper(settings, instance, self.stats)
        self.done = asyncio.Event()

    def check(self) -> list[str]:
        """Problems found before starting: fixed labels that are not sources here."""
        problems = []
        for _, label, holes in self.mapper.fields:
            if holes:
                continue
            try:
                self.mapper.source(label)
            except BadMessage as exc:
                problems.append(exc.detail)
        return problems

    async def run(self, zenoh_session: Any | None) -> None:
        """Receive until cancelled (or the end of a file / generator)."""
        try:
            await self._run(zenoh_session)
        finally:
            self.close()
            self.done.set()

    def close(self) -> None:
        """Let go of the instance (one that never ran too); calling it again does nothing."""
        self.mapper.close()

    async def _run(self, zenoh_session: Any | None) -> None:
        raise NotImplementedError


class _Queue:
    """Messages handed over from a transport's thread to the loop, bounded."""

    def __init__(self, mapper: _Mapper) -> None:
        self.loop = asyncio.get_running_loop()
        self.queue: asyncio.Queue[tuple[Any, int | None, str | None]] = asyncio.Queue(_QUEUE)
        self.mapper = mapper

    def put_threadsafe(self, item: tuple[Any, int | None, str | None]) -> None:
        """From a transport's thread."""
        self.loop.call_soon_threadsafe(self._put, item)

    def _put(self, item: tuple[Any, int | None, str | None]) -> None:
        try:
            self.queue.put_nowait(item)
        except asyncio.QueueFull:
            self.mapper.stats.received += 1
            self.mapper.bad("overflow", f"more than {_QUEUE} messages waiting")


@contextlib.asynccontextmanager
async def zenoh_subscriber(
    settings: Any, zenoh_session: Any | None, key: str, on_sample: Callable[[Any], None]
) -> AsyncIterator[Any]:
    """A subscriber for a zenoh-based input: on the node's session, or its own (``connect``).

    Yields the session it is on.
    """
    import zenoh

    from agents.transports import ZenohConfig

    own = None
    if settings.connect is not None or zenoh_session is None:
        if not settings.connect:
            raise ValueError(
                f"input {settings.title()}: the node's transport is not zenoh: give connect = [...]"
            )
        cfg = ZenohConfig(mode="client", connect=settings.connect).to_zenoh()
        own = zenoh_session = await asyncio.to_thread(zenoh.open, cfg)
    assert zenoh_session is not None
    sub = zenoh_session.declare_subscriber(key, on_sample)
    try:
        yield zenoh_session
    finally:
        with contextlib.suppress(zenoh.ZError):  # the session may be closing already
            sub.undeclare()
        if own is not None:
            await asyncio.to_thread(own.close)


class _ZenohRunner(InputRunner):
    settings: ZenohInput

    async def _run(self, zenoh_session: Any | None) -> None:
        import zenoh

        s = self.settings
        q = _Queue(self.mapper)

        def on_sample(sample: zenoh.Sample) -> None:
            ts = sample.timestamp
            stamp = None
            if ts is not None:
                stamp = int(ts.get_time().timestamp() * 1e9)
            q.put_threadsafe((sample.payload.to_bytes(), stamp, str(sample.key_expr)))

        async with zenoh_subscriber(s, zenoh_session, s.key, on_sample):
            mapper, fmt = self.mapper, s.format
            while True:
                payload, stamp, key = await q.queue.get()
                try:
                    message = mapper.decode(payload, fmt)
                except BadMessage as exc:
                    mapper.stats.received += 1
                    mapper.bad(exc.reason, exc.detail, topic=key)
                    continue
                mapper.handle(message, stamp=stamp, topic=key)


class _MqttRunner(InputRunner):
    settings: MqttInput

    async def _run(self, zenoh_session: Any | None) -> None:
        import aiomqtt

        from agents.transports import mqtt_client

        s = self.settings
        password = None
        if s.password_file is not None:
            password = s.password_file.read_text(encoding="utf-8").strip()
        mapper = self.mapper
        delay = 0.5
        while True:  # reconnects: a broker restart must not end the input
            try:
                async with mqtt_client(
                    s.host, s.port, username=s.username, password=password
                ) as client:
                    await client.subscribe(s.topic, qos=s.qos)
                    log.info("input %s: subscribed on %s:%d", s.title(), s.host, s.port)
                    delay = 0.5
                    async for msg in client.messages:
                        payload = msg.payload
                        if not isinstance(payload, bytes | bytearray):
                            payload = str(payload).encode()
                        topic = str(msg.topic)
                        try:
                            message = mapper.decode(bytes(payload), "json")
                        except BadMessage as exc:
                            mapper.stats.received += 1
                            mapper.bad(exc.reason, exc.detail, topic=topic)
                            continue
                        mapper.handle(message, topic=topic)
            except aiomqtt.MqttError as exc:
                why = _ERRNO.sub("", str(exc)) or type(exc).__name__
                log.warning(
                    "input %s: MQTT broker %s:%d: %s; reconnecting in %.1f s",
                    s.title(),
                    s.host,
                    s.port,
                    why,
                    delay,
                )
                await asyncio.sleep(delay)
                delay = min(delay * 2, 10.0)


def _rows(path: Path, fmt: str) -> list[Any]:
    """Every message of a recorded file (JSON lines or CSV with a header row)."""
    # utf-8-sig: a byte-order mark (Excel writes one) is not the first column's name
    with path.open(encoding="utf-8-sig", newline="") as f:
        if fmt == "csv":
            return _csv_rows(f, path)
        rows: list[Any] = []
        for n, line in enumerate(f, 1):
            if line.strip():
                try:
                    rows.append(json.loads(line))
                except ValueError as exc:
                    rows.append(BadMessage("not-json", f"line {n}: {exc}"))
                except RecursionError:  # one line must not end the whole file's replay
                    rows.append(BadMessage("not-json", f"line {n}: nested too deep"))
        return rows


class _Lines:
    """The physical lines under a csv reader, counted, with those of the record being read."""

    __slots__ = ("_it", "n", "record")

    def __init__(self, f: Iterable[str]) -> None:
        self._it = iter(f)
        self.n = 0
        self.record: list[str] = []

    def __iter__(self) -> "_Lines":
        return self

    def __next__(self) -> str:
        line = next(self._it)
        self.n += 1
        self.record.append(line)
        return line

    def skip_record(self) -> None:
        """Skip the lines left of a record the reader gave up on, to where its quote closes.

        The reader starts again at the next physical line after an error: without this,
        the tail of a quoted field spanning lines would be read as rows of its own.
        """
        state = _START
        for line in self.record:
            state = _quote_state(line, state)
        while state == _QUOTED:
            try:
                line = next(self._it)
            except StopIteration:
                return  # the quote never closes: the rest of the file was that row
            self.n += 1
            state = _quote_state(line, state)


# where a line of the csv module's default dialect leaves a record: only _QUOTED goes on
_START, _FIELD, _QUOTED, _QUOTE_IN_QUOTED = range(4)


def _quote_state(line: str, state: int) -> int:
    """The parse state after one physical line of CSV (excel dialect), from ``state``."""
    if state != _QUOTED:
        state = _START  # a line outside quotes starts a record
    for ch in line:
        if state == _QUOTED:
            if ch == '"':
                state = _QUOTE_IN_QUOTED
        elif ch in "\r\n":
            return _START
        elif state == _START:
            state = _QUOTED if ch == '"' else _START if ch == "," else _FIELD
        elif state == _FIELD:
            if ch == ",":
                state = _START
        else:  # _QUOTE_IN_QUOTED: a doubled quote, the next field or the field goes on
            state = _QUOTED if ch == '"' else _START if ch == "," else _FIELD
    return state


def _csv_rows(f: Iterable[str], path: Path) -> list[Any]:
    """The rows of a CSV file with a header row; a row that cannot be read is a BadMessage.

    A field over ``csv.field_size_limit()`` (128 KiB) or a row of more cells than the
    header costs that row only (a quoted field over several lines up to where its quote
    closes): the rest of the file is still replayed. Errors name the row's first line.
    """
    import csv  # only for a CSV file: not at every node's start

    lines = _Lines(f)
    reader = csv.reader(lines)
    header: list[str] | None = None
    rows: list[Any] = []
    while True:
        lines.record.clear()
        first = lines.n + 1
        try:
            cells = next(reader)
        except StopIteration:
            return rows
        except csv.Error as exc:
            where = f"{path}:{first}"
            # without its header no row can be read: the rest of the file is not tried
            skipped = "row skipped" if header is not None else "no header row: file skipped"
            if "field limit" in str(exc):
                limit = csv.field_size_limit()
                why = f"{where}: a field over the {limit}-character limit; {skipped}"
                rows.append(BadMessage("field-too-large", why))
            else:
                rows.append(BadMessage("not-csv", f"{where}: {exc}; {skipped}"))
            if header is None:
                return rows
            lines.skip_record()
            continue
        if header is None:
            header = cells or None  # blank lines before the header are no header
        elif len(cells) > len(header):
            why = f"{path}:{first}: {len(cells)} cells, the header names {len(header)}"
            rows.append(BadMessage("not-csv", why))
        elif cells:  # a blank line is no row (as csv.DictReader)
            cells += [""] * (len(header) - len(cells))  # missing cells are empty
            rows.append({k: _number(v) for k, v in zip(header, cells, strict=True)})


def _missing_columns(header: list[str], settings: _InputBase) -> list[str]:
    """What the input reads that the CSV header lacks: a misspelt column maps nothing."""
    where = f"(its columns: {', '.join(header)})"
    problems = []
    for path, label in settings.fields.items():
        if path != _WHOLE and path.split(".", 1)[0] not in header:
            problems.append(f"no column {path!r} {where}: fields.{path} gives {label!r} nothing")
        for hole in _PLACEHOLDER.findall(label):
            # a file has no topic: `{topic}` too is a column here
            if hole.split(".", 1)[0] not in header:
                why = " (a file input has no topic)" if hole == "topic" else ""
                problems.append(f"no column {hole!r} {where}: no row can fill label {label!r}{why}")
    t = settings.time
    if t is not None and t.split(".", 1)[0] not in header:
        problems.append(f"no column {t!r} {where}: time = {t!r}: rows are valid at their arrival")
    return problems


def _number(text: str | None) -> Any:
    """A CSV cell as int, float, bool or the text."""
    if text is None or text == "":
        return None
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


class _FileRunner(InputRunner):
    settings: FileInput

    async def _run(self, zenoh_session: Any | None) -> None:
        s = self.settings
        rows = await asyncio.to_thread(_rows, s.path, s.file_format())
        mapper = self.mapper
        if s.file_format() == "csv":
            header = next((list(r) for r in rows if isinstance(r, dict)), None)
            if header is not None:
                # the path once: the title is `file PATH` unless the input is named
                title = s.title() if s.name is None else f"{s.title()}: {s.path}"
                for problem in _missing_columns(header, s):
                    log.warning("input %s: %s", title, problem)
        last: int | None = None
        while True:
            last = await self._replay(rows, mapper, s, last)
            if not s.loop:
                break
        log.info("input %s: replayed %d messages", s.title(), len(rows))

    async def _replay(
        self, rows: list[Any], mapper: _Mapper, s: FileInput, after: int | None
    ) -> int | None:
        """One pass over ``rows``; the latest valid time it gave (``shift = "now"``).

        A pass after another gives valid times strictly after ``after``, the last pass's
        latest: the clock may have woken that pass's last sleep a little early, ``speed``
        or ``pace = "fast"`` run its valid times ahead of the wall clock, or a row be
        earlier than the first. Each pass starts at the wall clock (a pass that takes
        less time than it spans would otherwise run ahead of it further each time), and
        a time that would not be after ``after`` is moved up to just after it.
        """
        now = time.time_ns()
        # a pass paced at speed 1 takes as long as it spans: starting after the last one's
        # latest keeps each valid time when it is due (pushed no earlier than it)
        at_pace = s.pace == "recorded" and s.speed == 1
        base = now if after is None or not at_pace else max(now, after + 1)
        start_wall = base if s.speed == 1 else now
        floor = None if after is None else after + 1  # of this pass's valid times
        first: int | None = None
        latest = after
        for row in rows:
            if isinstance(row, BadMessage):
                mapper.stats.received += 1
                mapper.bad(row.reason, row.detail)
                continue
            try:
                t = mapper.valid_time(row, None)
            except BadMessage:
                t = None
            t = -1 if t is None else t
            if t >= 0 and first is None:
                first = t
            if s.pace == "recorded" and t >= 0 and first is not None:
                due = start_wall + int((t - first) / s.speed)
                delay = (due - time.time_ns()) / 1e9
                while delay > 0:  # the event loop may wake a timer a little early
                    await asyncio.sleep(delay)
                    delay = (due - time.time_ns()) / 1e9
            elif s.pace == "fast" and mapper.stats.received % 1000 == 999:
                await asyncio.sleep(0)  # let the node answer queries meanwhile
            if s.shift == "now" and t >= 0 and first is not None:
                valid = base + (t - first)
                if floor is not None and valid < floor:
                    valid = floor  # never back past the last pass: one ns apart, in order
                    floor += 1
                latest = valid if latest is None else max(latest, valid)
                mapper.handle(row, valid=valid)
            else:
                mapper.handle(row)
        return latest


class _PythonRunner(InputRunner):
    settings: PythonInput

    async def _run(self, zenoh_session: Any | None) -> None:
        from dyknow_core.kpl import resolve_callable

        s = self.settings
        module, attr = s.entry.split(":", 1)
        made = resolve_callable(module, attr)(**s.args)
        if inspect.isawaitable(made) and not hasattr(made, "__aiter__"):
            made = await made
        if not hasattr(made, "__aiter__"):
            raise TypeError(f"input {s.title()}: {s.entry} did not give an async iterator")
        items: AsyncIterator[Any] = made.__aiter__()
        async for message in items:
            self.mapper.handle(message)


def input_runner(settings: _InputBase, instance: "DyKnowInstance") -> InputRunner:
    """The runner of one ``[[inputs]]`` table of a kind other than ROS 2 (``ros2``, ``rosbag``).

    Those are `federation._ros.ros_runner`'s: that module builds on this one, so this one
    does not import it (a node picks between the two, ``federation/_application.py``).
    """
    if isinstance(settings, Ros2Input | RosbagInput):
        raise TypeError(f"input {settings.title()}: a ROS 2 input's runner is ros_runner's")
    kinds: dict[type[_InputBase], Callable[..., InputRunner]] = {
        ZenohInput: _ZenohRunner,
        MqttInput: _MqttRunner,
        FileInput: _FileRunner,
        PythonInput: _PythonRunner,
    }
    return kinds[type(settings)](settings, instance)
