"""ROS 2 inputs: topics published through rmw_zenoh, and recorded rosbag2 / MCAP files.

Also what ``dyknow replay`` needs of ROS recordings: ``cdr_decoder`` for the ROS 2
channels of an MCAP file, ``RosbagRecording`` for a rosbag2 bag (docs/record.md).

rmw_zenoh (ROS 2's middleware on zenoh) puts each message of a topic on the key

    <domain id>/<topic without its leading '/'>/<type>/<type hash>

with ``<type>`` the DDS-style name (``geometry_msgs::msg::dds_::PoseStamped_``) and
``<type hash>`` the type's RIHS01 hash (``RIHS01_<64 hex digits>``); the payload is the
message in CDR with its 4-byte encapsulation header. We subscribe to
``<domain>/<topic>/*/*`` (or the one type asked for) and take the type from the key. The
sample's attachment (sequence number, source time stamp, publisher GID) is not used.
Messages are decoded with ``rosbags`` (standard message types without a ROS install)
into plain dicts and lists; ``header.stamp`` is the valid time when the message has one.
docs/application.md, "ROS 2".
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import re
import threading
import time
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dyknow_core import (
    MessageDecoder,
    RecordedSample,
    RecordError,
    RecordHeader,
    recording_info,
    topic_label,
)

from ._inputs import BadMessage, InputRunner, Ros2Input, RosbagInput, _Queue, zenoh_subscriber

if TYPE_CHECKING:
    from dyknow_core import DyKnowInstance

__all__ = [
    "ReplayStarts",
    "RosbagRecording",
    "cdr_decoder",
    "dds_type",
    "ros_runner",
    "ros_topics",
    "ros_type",
    "to_plain",
]

log = logging.getLogger(__name__)


@cache
def _typestore(distro: str) -> Any:
    from rosbags.typesys import Stores, get_typestore

    try:
        store = Stores[f"ROS2_{distro.upper()}"]
    except KeyError:
        raise ValueError(f"distro {distro!r}: not one rosbags knows") from None
    return get_typestore(store)


def ros_type(dds: str) -> str:
    """``geometry_msgs::msg::dds_::PoseStamped_`` → ``geometry_msgs/msg/PoseStamped``."""
    parts = dds.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_"):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    raise ValueError(f"{dds!r} is not a DDS type name like pkg::msg::dds_::Name_")


def dds_type(ros: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` → ``geometry_msgs::msg::dds_::PoseStamped_``."""
    pkg, kind, name = ros.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def to_plain(msg: Any) -> Any:
    """A decoded ROS message as dicts, lists and numbers (what streams and queries carry)."""
    if dataclasses.is_dataclass(msg) and not isinstance(msg, type):
        # ROS field names are lower case, a type's constants upper case: constants left out
        return {
            f.name: to_plain(getattr(msg, f.name))
            for f in dataclasses.fields(msg)
            if not f.name.isupper() and f.name != "__msgtype__"
        }
    if isinstance(msg, list | tuple):
        return [to_plain(x) for x in msg]
    tolist = getattr(msg, "tolist", None)  # numpy arrays (uint8[] data, covariances)
    if tolist is not None:
        return tolist()
    return msg


def header_stamp(plain: Any) -> int | None:
    """``header.stamp`` in nanoseconds, when the message has a header."""
    if not isinstance(plain, dict):
        return None
    header = plain.get("header")
    stamp = header.get("stamp") if isinstance(header, dict) else None
    if not isinstance(stamp, dict):
        return None
    return int(stamp.get("sec", 0)) * 1_000_000_000 + int(stamp.get("nanosec", 0))


class _Decoder:
    def __init__(self, distro: str) -> None:
        self.store = _typestore(distro)

    def decode(self, data: bytes, rostype: str) -> Any:
        if rostype not in self.store.types:
            raise BadMessage("unknown-type", f"{rostype}: not a type rosbags knows")
        try:
            return to_plain(self.store.deserialize_cdr(data, rostype))
        except Exception as exc:
            raise BadMessage("not-cdr", f"{rostype}: {type(exc).__name__}: {exc}") from None


SILENT_WARN = 10.0
"""Seconds a ``ros2`` input waits for its first message before it warns, once."""
_GRAPH_WAIT = 1.0  # s spent looking at the ROS graph for that warning
# How long past its timeout a graph query may take before we stop waiting for zenoh's
# "finished" signal: a backstop, zenoh ends every liveliness get at its timeout.
_GRAPH_GRACE = 1.0


def ros_topics(session: Any, domain: int, wait: float = _GRAPH_WAIT) -> dict[str, str]:
    """Topic → ROS type of what is published in ``domain`` through rmw_zenoh (blocking).

    From the graph's liveliness tokens only (``@ros2_lv/<domain>/…/MP/…/<topic>/<type>/…``,
    a name's '/' written '%'), which rmw_zenoh declares for every publisher, answered
    within ``wait`` seconds: keys, never the messages (a camera's domain would pour its
    images into this session meanwhile).
    """
    import zenoh

    keys: list[str] = []
    done = threading.Event()

    def on_reply(reply: Any) -> None:
        if (ok := reply.ok) is not None:
            keys.append(str(ok.key_expr))

    # Not zenoh's default handler: a FIFO of 256 replies read once get() returns, while
    # zenoh answers the tokens it knows inside get(), holding its session lock: with more
    # than 256 (an rmw_zenoh graph easily has them) get() never returned, the session
    # stuck. A callback on a thread of zenoh-python's own drains them as they come (not
    # on zenoh's thread: see agents/transports/_zenoh.py).
    session.liveliness().get(
        f"@ros2_lv/{domain}/**",
        zenoh.handlers.Callback(on_reply, done.set, indirect=True),
        timeout=wait,
    )
    done.wait(wait + _GRAPH_GRACE)
    found: dict[str, str] = {}
    for key in list(keys):  # as many as came: a late reply only adds to the list
        parts = key.split("/")
        if len(parts) > 10 and parts[5] == "MP":  # a publisher
            try:
                kind = ros_type(parts[10])
            except ValueError:
                kind = parts[10]
            found.setdefault(parts[9].replace("%", "/"), kind)
    return found


_PLAIN_NAME = re.compile(r"[A-Za-z0-9_/]+")


class _Ros2Runner(InputRunner):
    settings: Ros2Input

    def key(self) -> str:
        """The key expression rmw_zenoh publishes this topic on."""
        s = self.settings
        topic = s.topic.strip("/")
        kind = dds_type(s.type) if s.type else "*"
        return f"{s.domain}/{topic}/{kind}/*"

    async def _run(self, zenoh_session: Any | None) -> None:
        s = self.settings
        decoder = _Decoder(s.distro)
        q = _Queue(self.mapper)

        def on_sample(sample: Any) -> None:
            q.put_threadsafe((sample.payload.to_bytes(), None, str(sample.key_expr)))

        async with zenoh_subscriber(s, zenoh_session, self.key(), on_sample) as session:
            log.info("input %s: subscribed to %s", s.title(), self.key())
            mapper = self.mapper
            heard = False
            while True:
                if heard:
                    payload, _, key = await q.queue.get()
                else:
                    try:
                        # not wait_for: on Python 3.11 it may lose a cancellation that
                        # comes with a sample, and this loop would outlive its node
                        async with asyncio.timeout(SILENT_WARN):
                            payload, _, key = await q.queue.get()
                    except TimeoutError:
                        heard = True  # said once: a topic may be quiet for a while
                        log.warning("%s", await self._silent(session))
                        continue
                    heard = True
                try:
                    dds = str(key).split("/")[-2]
                    rostype = s.type or ros_type(dds)
                    message = decoder.decode(payload, rostype)
                except (BadMessage, ValueError, IndexError) as exc:
                    mapper.stats.received += 1
                    if isinstance(exc, BadMessage):
                        mapper.bad(exc.reason, exc.detail)
                    else:
                        mapper.bad("bad-key", f"{key}: {exc}")
                    continue
                mapper.handle(message, stamp=header_stamp(message), topic=s.topic)

    async def _silent(self, session: Any) -> str:
        """The warning of an input that got no message: its topic, and the topics there are."""
        s = self.settings
        try:
            topics = await asyncio.to_thread(ros_topics, session, s.domain)
        except Exception as exc:  # the warning goes out without them
            log.debug("reading the ROS graph: %s", exc)
            topics = {}
        # names from the network: quoted unless plain (a newline could forge a log line)
        seen = ", ".join(
            f"{t!r} ({kind if _PLAIN_NAME.fullmatch(kind) else repr(kind)})"
            for t, kind in sorted(topics.items())
        )
        return (
            f"input {s.title()}: no message on topic {s.topic!r} in {SILENT_WARN:g} s (zenoh key "
            f"{self.key()}); topics published in ROS domain {s.domain}: "
            + (seen or "none seen (no ROS 2 node on rmw_zenoh reaches this node's session)")
        )


def _read_bag(path: Path, topic: str) -> list[tuple[int, str, bytes]]:
    """``(log time ns, ROS type, CDR)`` of every message of ``topic``, in log-time order."""
    out: list[tuple[int, str, bytes]] = []
    if path.is_dir():
        from rosbags.rosbag2 import Reader

        with Reader(path) as bag:
            conns = [c for c in bag.connections if c.topic == topic]
            if not conns:
                topics = sorted({c.topic for c in bag.connections})
                raise ValueError(f"{path}: no topic {topic!r} (it has {', '.join(topics)})")
            for conn, t, data in bag.messages(connections=conns):
                out.append((t, conn.msgtype, bytes(data)))
        return out
    from mcap.reader import make_reader

    with path.open("rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(topics=[topic]):
            if channel.message_encoding != "cdr" or schema is None:
                continue
            out.append((message.log_time, schema.name, bytes(message.data)))
    if not out:
        topics = _mcap_topics(path)
        if topic in topics:
            raise ValueError(f"{path}: no CDR message on topic {topic!r}")
        raise ValueError(f"{path}: no topic {topic!r} (it has {', '.join(topics) or 'none'})")
    return sorted(out, key=lambda m: m[0])


def _mcap_topics(path: Path) -> list[str]:
    """The topics of an MCAP file's channels, sorted (read in full when it has no summary)."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is not None:
            return sorted({c.topic for c in summary.channels.values()})
        return sorted({channel.topic for _, channel, _ in reader.iter_messages()})


ReplayStarts = dict[Path, tuple[int, int]]
"""A node's replays with ``shift = "now"``, by recording: (wall clock, recorded time) of
the first message its first input on that recording handed on (ns)."""


class _RosbagRunner(InputRunner):
    settings: RosbagInput

    def __init__(
        self, settings: RosbagInput, instance: DyKnowInstance, starts: ReplayStarts
    ) -> None:
        super().__init__(settings, instance)
        self._starts = starts

    async def _run(self, zenoh_session: Any | None) -> None:
        s = self.settings
        decoder = _Decoder(s.distro)
        messages = await asyncio.to_thread(_read_bag, s.path, s.topic)
        mapper = self.mapper
        start: int | None = None  # with shift = "now": the valid time of recorded `origin`
        origin = 0
        shared = s.shift == "now"
        key = s.path.resolve()
        # the pace's time zero (wall clock, recorded time). With shift = "now" the
        # recording's shared start, so that a message comes when its valid time does, on a
        # topic that starts later in the recording too; else once this input's first
        # message was handed on, so that each later one comes at least its recorded gap
        # after it, however late the first one was
        zero: tuple[int, int] | None = None
        for n, (logged, rostype, data) in enumerate(messages):
            if s.pace == "recorded":
                if zero is None and shared:
                    zero = self._starts.get(key)
                if zero is not None:
                    delay = (zero[0] + (logged - zero[1]) / s.speed - time.time_ns()) / 1e9
                    if delay > 0:
                        await asyncio.sleep(delay)
            elif n % 1000 == 999:
                await asyncio.sleep(0)  # let the node answer queries meanwhile
            try:
                message = decoder.decode(data, rostype)
            except BadMessage as exc:
                mapper.stats.received += 1
                mapper.bad(exc.reason, exc.detail)
                continue
            if start is None:
                start = origin = logged
                if shared:
                    # the node's inputs on one recording share the first one's start: one
                    # recorded instant is one valid time, whichever topic it was on
                    start, origin = self._starts.setdefault(key, (time.time_ns(), logged))
            stamp = header_stamp(message)
            own = logged if stamp is None else stamp
            valid = start + (own - origin) if shared else None
            mapper.handle(message, stamp=own, topic=s.topic, valid=valid)
            if zero is None:
                zero = (start, origin) if shared else (time.time_ns(), logged)
        log.info("input %s: replayed %d messages", s.title(), len(messages))


def ros_runner(
    settings: Ros2Input | RosbagInput,
    instance: DyKnowInstance,
    starts: ReplayStarts | None = None,
) -> InputRunner:
    """The runner of a ``ros2`` or ``rosbag`` input.

    ``starts`` is shared by the node's inputs (`ReplayStarts`); without it, this input's own.
    """
    if isinstance(settings, Ros2Input):
        return _Ros2Runner(settings, instance)
    return _RosbagRunner(settings, instance, {} if starts is None else starts)


# -- recordings made by ROS tools, replayed by ``dyknow replay`` (docs/record.md) ----------------


def _learn_type(store: Any, rostype: str, encoding: str, text: str) -> None:
    """Register a message type the file defines (``ros2msg`` text) and the store lacks."""
    if rostype in store.types or encoding != "ros2msg" or not text.strip():
        return
    from rosbags.typesys import get_types_from_msg

    # a definition rosbags cannot parse leaves the type unknown: its messages are skipped
    with contextlib.suppress(Exception):
        store.register(get_types_from_msg(text, rostype))


def cdr_decoder(distro: str = "humble") -> MessageDecoder:
    """The decoder of an MCAP file's ROS 2 (``cdr``) channels for ``dyknow_core.Recording``.

    A message becomes plain dicts and lists, its ``header.stamp`` (when it has one) the
    valid time; types the file defines that rosbags lacks are learnt from the file.
    """
    stores: list[Any] = []  # made on first use: rosbags' type store takes a while to load

    def decode(name: str, encoding: str, text: bytes, data: bytes) -> tuple[Any, int | None]:
        if not stores:
            stores.append(_typestore(distro))
        store = stores[0]
        _learn_type(store, name, encoding, text.decode("utf-8", "replace"))
        if name not in store.types:
            raise ValueError(f"{name or 'no schema'}: not a ROS 2 type rosbags knows")
        plain = to_plain(store.deserialize_cdr(data, name))
        return plain, header_stamp(plain)

    return decode


class RosbagRecording:
    """A rosbag2 bag (a directory with ``metadata.yaml``) read as a recording.

    Each topic is a label (``dyknow_core.topic_label``: without its leading ``/``); a
    message becomes plain dicts and lists, its available time the bag's time stamp and
    its valid time its ``header.stamp`` (the bag's time stamp when it has none). Messages
    that do not decode are skipped and counted per label in ``undecodable`` (why in
    ``problems``). Iterates in time-stamp order, as ``dyknow_core.replay`` wants.
    """

    def __init__(self, path: Path, *, distro: str = "humble") -> None:
        from rosbags.rosbag2 import Reader

        self.path = path
        self.distro = distro
        self.truncated = False
        self.undecodable: dict[str, int] = {}
        self.problems: dict[str, str] = {}
        try:
            with Reader(path) as bag:
                labels = sorted({topic_label(c.topic) for c in bag.connections})
                start = bag.start_time if bag.message_count else 0
                ros_distro = bag.ros_distro
        except Exception as exc:  # rosbags raises several kinds on a bad bag
            raise RecordError(
                f"{path}: not a readable rosbag2 bag: {type(exc).__name__}: {exc}"
            ) from None
        self.header = RecordHeader(
            version=0,
            instance="",
            clock="",
            start=start,
            labels=labels,
            created="",
            meta={"ros_distro": ros_distro} if ros_distro else {},
            format="rosbag2",
            library="rosbag2",
        )

    def _skip(self, topic: str, why: str) -> None:
        self.undecodable[topic] = self.undecodable.get(topic, 0) + 1
        self.problems.setdefault(topic, why)

    def __iter__(self) -> Iterator[RecordedSample]:
        from rosbags.rosbag2 import Reader

        self.undecodable.clear()
        self.problems.clear()
        store = _typestore(self.distro)
        with Reader(self.path) as bag:
            messages = bag.messages()
            while True:
                try:
                    conn, t, data = next(messages)
                except StopIteration:
                    break
                except Exception as exc:  # a damaged database: rosbags and SQLite raise many
                    raise RecordError(
                        f"{self.path}: damaged rosbag2 bag: {type(exc).__name__}: {exc}"
                    ) from None
                if type(t) is not int:  # a time stamp that is no integer (a damaged row)
                    raise RecordError(
                        f"{self.path}: damaged rosbag2 bag: a time stamp is {type(t).__name__}"
                    )
                rostype, label = conn.msgtype, topic_label(conn.topic)
                if conn.msgdef is not None:
                    _learn_type(store, rostype, "ros2msg", conn.msgdef.data)
                try:
                    plain = to_plain(store.deserialize_cdr(bytes(data), rostype))
                except Exception as exc:  # an unknown type, a message that is not CDR
                    self._skip(label, f"{rostype}: {type(exc).__name__}: {exc}")
                    continue
                stamp = header_stamp(plain)
                yield RecordedSample(label, plain, t if stamp is None else stamp, t)

    def info(self) -> dict[str, Any]:
        """What ``dyknow_core.Recording.info`` says, of this bag."""
        return recording_info(self, str(self.path))
