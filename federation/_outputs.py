"""Outputs of a node's application: chosen streams published as JSON for outside consumers.

Each ``[[outputs]]`` table of a node's config (docs/application.md) names local labels
(glob patterns allowed: a stream appearing later is followed from its first sample) and
where their samples go: an MQTT topic or a zenoh key, ``{label}`` in either replaced by
the sample's label.
Each sample is one JSON object ``{"label", "value", "valid", "available"}`` (times in
seconds since the epoch), so a dashboard needs no DyKnow library to read it.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import contextlib
import fnmatch
import json
import logging
import re
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from dyknow_core import Policy

from ._quote import quoted

if TYPE_CHECKING:
    from dyknow_core import DyKnowInstance

__all__ = ["MqttOutput", "OutputRunner", "OutputSettings", "ZenohOutput", "output_runner"]

log = logging.getLogger(__name__)

_NS = 1_000_000_000  # an int: int / int is correctly rounded, epoch times keep their fraction
_QUEUE = 10_000  # samples waiting to be published; beyond, the oldest are dropped
_MQTT_TOPIC_MAX = 65_535  # bytes of an MQTT topic (UTF-8)
# what a broker closes the connection on in a topic (MQTT 5, 1.5.4; mosquitto does): the
# C0 and C1 controls and DEL, and the Unicode non-characters. NUL is said on its own
_MQTT_UNSAFE = re.compile(
    "[\x01-\x1f\x7f-\x9f\ufdd0-\ufdef"
    + "".join(f"{chr(p * 0x10000 + 0xFFFE)}{chr(p * 0x10000 + 0xFFFF)}" for p in range(17))
    + "]"
)
_LOGGED_REFUSED = 5  # streams not published said one by one, then one in _LOG_EVERY
_LOG_EVERY = 1000


class _OutputBase(BaseModel):
    # defer_build: a config's outputs are checked by PlatformConfig's own schema, so this
    # model's validator is built only if something validates one on its own (~0.3 MB of
    # a node's memory for the inputs, outputs and sharing rules together)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True)

    labels: list[str] = Field(min_length=1, description="Local labels or glob patterns.")
    sample_period: float | None = Field(default=None, gt=0)


class MqttOutput(_OutputBase):
    """``kind = "mqtt"``: samples as JSON on ``topic`` (``{label}`` allowed) at a broker."""

    kind: Literal["mqtt"]
    topic: str = Field(min_length=1)
    host: str = "127.0.0.1"
    port: int = Field(default=1883, gt=0, lt=65536)
    qos: Literal[0, 1, 2] = 0
    retain: bool = False

    def title(self) -> str:
        """``mqtt TOPIC``."""
        return f"mqtt {self.topic}"


class ZenohOutput(_OutputBase):
    """``kind = "zenoh"``: samples as JSON put on ``key`` (``{label}`` allowed)."""

    kind: Literal["zenoh"]
    key: str = Field(min_length=1)
    connect: tuple[str, ...] | None = None

    def title(self) -> str:
        """``zenoh KEY``."""
        return f"zenoh {self.key}"


OutputSettings = Annotated[MqttOutput | ZenohOutput, Field(discriminator="kind")]


def sample_json(label: str, value: Any, valid: int, available: int) -> bytes:
    """One sample as the outputs publish it."""
    row = {"label": label, "value": value, "valid": valid / _NS, "available": available / _NS}
    try:
        return json.dumps(row, default=str, allow_nan=False).encode()
    except ValueError:  # NaN or infinity somewhere in the value: not JSON, sent as text
        row["value"] = str(value)
        return json.dumps(row, default=str).encode()


class OutputRunner:
    """One output: follows the matching streams and publishes their samples."""

    def __init__(self, settings: MqttOutput | ZenohOutput, instance: "DyKnowInstance") -> None:
        self.settings = settings
        self.instance = instance
        self.published = 0
        self.dropped = 0
        self.refused = 0  # streams matched but not published: no plain topic or key of their own
        self._queue: asyncio.Queue[tuple[str, bytes]] = asyncio.Queue(_QUEUE)
        self._subs: dict[str, Any] = {}  # label -> the subscription following it

    def matching(self) -> list[str]:
        """The local labels this output publishes now."""
        return [label for label in self.instance.labels() if self.wants(label)]

    def wants(self, label: str) -> bool:
        """Whether ``label`` is one of this output's: a fixed label, or one a pattern matches."""
        return any(
            fnmatch.fnmatchcase(label, p) if any(c in p for c in "*?[") else label == p
            for p in self.settings.labels
        )

    def check(self) -> list[str]:
        """Fixed labels (not patterns) that are no stream here."""
        return [
            f"no stream {label!r} here"
            for label in self.settings.labels
            if not any(c in label for c in "*?[") and not self.instance.has_label(label)
        ]

    def check_destination(self) -> str | None:
        """Why the topic or key is no plain one whatever the label, if so (the operator's)."""
        # a plain one-chunk label ("x") stands for any: what is wrong then is the template's
        _, why = self.destination("x")
        if why is None:
            return None
        s = self.settings
        word, where = ("topic", s.topic) if isinstance(s, MqttOutput) else ("key", s.key)
        return f"the {word} {where!r} {why}, whatever the label"

    def destination(self, label: str) -> tuple[str, str | None]:
        """The topic or key ``label``'s samples go to, and why it cannot be published, if so.

        An input with ``create = true`` lets whoever publishes to it name streams: a name
        holding an MQTT wildcard or a NUL makes a topic no broker takes (the client raises,
        and the output would stop for good); one holding ``$`` is no zenoh key, or a
        wildcard one whose put would reach the subscribers of other keys; a lone surrogate
        (JSON's ``\\ud800``) is no UTF-8 for either. A control character or a Unicode
        non-character in a topic makes the broker close the connection (mosquitto does).
        """
        s = self.settings
        where = s.topic if isinstance(s, MqttOutput) else s.key
        where = where.replace("{label}", label)
        try:
            size = len(where.encode())
        except UnicodeEncodeError:
            return where, "is not UTF-8 (a lone surrogate)"
        if isinstance(s, MqttOutput):
            if "+" in where or "#" in where:
                return where, "holds an MQTT wildcard (+ or #)"
            if "\x00" in where:
                return where, "holds a NUL character"
            if _MQTT_UNSAFE.search(where):
                return where, "holds a control character or a Unicode non-character"
            if where.startswith("$"):
                return where, "starts with $ (the broker's own topics)"
            if size > _MQTT_TOPIC_MAX:
                return where, f"is longer than {_MQTT_TOPIC_MAX} bytes"
            return where, None
        import zenoh

        if "*" in where:
            return where, "is a zenoh wildcard ($*, *): its put would reach other keys"
        try:
            zenoh.KeyExpr(where)
        except zenoh.ZError as exc:
            return where, f"is no zenoh key ({str(exc).split(' at ', 1)[0]})"
        return where, None

    def _follow(self, label: str) -> None:
        if label in self._subs:
            return
        where, why = self.destination(label)
        if why is not None:
            # counted, never kept: the names come from outside, each one a new one
            self.refused += 1
            n = self.refused
            if n <= _LOGGED_REFUSED or n % _LOG_EVERY == 0:
                word = "topic" if isinstance(self.settings, MqttOutput) else "key"
                log.warning(
                    "output %s: stream %s not published: its %s %s %s (#%d)",
                    self.settings.title(),
                    quoted(repr(label)),
                    word,
                    quoted(repr(where)),
                    why,
                    n,
                )
            return

        def deliver(batch: list[Any], label: str = label) -> None:
            for value, valid, available in batch:
                self._enqueue(label, sample_json(label, value, valid, available))

        policy = Policy(sample_period=self.settings.sample_period)
        self._subs[label] = self.instance.subscribe(label, policy, callback=deliver)

    def _label_changed(self, label: str, published: bool) -> None:
        # told as the stream is made, before its first sample is pushed: none is missed
        if not published:
            # its subscription ended with it (a new one may come): kept, it would hold the
            # removed stream and its cache for as long as the output runs
            sub = self._subs.pop(label, None)
            if sub is not None:
                sub.close()
        elif self.wants(label):
            self._follow(label)

    def _enqueue(self, label: str, payload: bytes) -> None:
        if self._queue.full():  # a slow broker: the newest samples matter most
            self._queue.get_nowait()
            self.dropped += 1
        self._queue.put_nowait((label, payload))

    async def run(self, zenoh_session: Any | None) -> None:
        """Publish until cancelled."""
        try:
            if isinstance(self.settings, MqttOutput):
                await self._run_mqtt(self.settings)
            else:
                await self._run_zenoh(self.settings, zenoh_session)
        finally:
            subs, self._subs = list(self._subs.values()), {}  # a second run follows anew
            for sub in subs:
                sub.close()

    @contextlib.asynccontextmanager
    async def _scanning(self) -> AsyncIterator[None]:
        """Follow the streams that match now, and those that come to, while the body publishes."""
        stop = self.instance.on_label_change(self._label_changed)
        try:
            for label in self.matching():
                self._follow(label)
            yield
        finally:
            stop()

    async def _run_mqtt(self, s: MqttOutput) -> None:
        import aiomqtt

        from agents.transports import mqtt_client

        async with self._scanning():
            while True:  # reconnects: the broker may restart
                try:
                    async with mqtt_client(s.host, s.port) as client:
                        while True:
                            label, payload = await self._queue.get()
                            topic = s.topic.replace("{label}", label)
                            await client.publish(topic, payload, qos=s.qos, retain=s.retain)
                            self.published += 1
                except aiomqtt.MqttError as exc:
                    log.warning("output %s: %s; reconnecting in 1 s", s.title(), exc)
                    await asyncio.sleep(1.0)

    async def _run_zenoh(self, s: ZenohOutput, session: Any | None) -> None:
        import zenoh

        from agents.transports import ZenohConfig

        own = None
        if s.connect is not None or session is None:
            if not s.connect:
                raise ValueError(
                    f"output {s.title()}: the node's transport is not zenoh: give connect = [...]"
                )
            cfg = ZenohConfig(mode="client", connect=s.connect).to_zenoh()
            own = session = await asyncio.to_thread(zenoh.open, cfg)
        assert session is not None
        try:
            async with self._scanning():
                while True:
                    label, payload = await self._queue.get()
                    session.put(s.key.replace("{label}", label), payload)
                    self.published += 1
        finally:
            if own is not None:
                await asyncio.to_thread(own.close)


def output_runner(settings: MqttOutput | ZenohOutput, instance: "DyKnowInstance") -> OutputRunner:
    """The runner of one ``[[outputs]]`` table."""
    return OutputRunner(settings, instance)
