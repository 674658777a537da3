"""A platform's view of its federation, served live to Foxglove (docs/foxglove.md).

`FoxgloveBridge` runs beside a `FederationPlatform` (``dyknow foxglove``, or any
application's operator, beside its `OperatorConsole`). It follows the federation's
membership, asks every other member for the streams of the config's ``[foxglove]``
section (`FoxgloveSettings`; by default the ``[console]``'s), and publishes each sample
it imports on a channel of a Foxglove WebSocket server (the official ``foxglove-sdk``):
``/<platform>/<label>``, the sample as a recording holds it (`sample_json`: its value,
valid and available time), its valid time as the message's log time.
With the section's ``origin`` (latitude, longitude of the local frame's x = y = 0),
positions are also published as ``foxglove.LocationFix`` (``…/fix``) and areas, tracks
and violations as ``foxglove.GeoJSON`` (``…/geo``), which Foxglove's Map panel draws;
with or without it, every stream with a role also as a ``foxglove.SceneUpdate``
(``…/scene``) in the local frame, for the 3D panel.

Every channel is JSON-encoded with a JSON schema (``jsonschema``): the well-known
Foxglove ones by their names, a stream's own inferred from its first sample as a
recording's is (`label_schema`; its description the vocabulary's), so that a replayed
recording shows the same fields. The server offers no publishing, services or
parameters to its clients: they only watch.

Only who holds the bridge's token watches: the SDK's server, which has no login, listens
on an ephemeral port of 127.0.0.1, behind a `FoxgloveRelay` on ``host``:``port`` that
lets in a WebSocket only with the token, an allowed ``Host`` and an ``Origin`` absent or
allowed (`ConsoleAccess`, as the web console's; docs/foxglove.md, "Access").
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Coroutine, Iterable
from dataclasses import dataclass, field
from typing import Any, Self

import orjson

from agents.transports import Subscription
from dyknow_core import NS_PER_S, Policy, label_schema, sample_json

from ._follow import REQUEST_TIMEOUT, BadValues, FollowedStream, cancel_export, follow
from ._geo import local_to_geo
from ._platform import ConsoleRoles, FederationPlatform, FoxgloveSettings
from ._proxy_base import OwnedTasks
from ._service import MembershipEvent

__all__ = ["FoxgloveBridge"]

log = logging.getLogger("federation.foxglove")


_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
LOCATION_FIX_SCHEMA: dict[str, Any] = {
    "title": "foxglove.LocationFix",
    "description": "A position on Earth (WGS 84), from a stream of local x, y, z metres",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "latitude": {"type": "number"},
        "longitude": {"type": "number"},
        "altitude": {"type": "number"},
        "position_covariance": {
            "type": "array",
            "items": {"type": "number"},
            "minItems": 9,
            "maxItems": 9,
        },
        "position_covariance_type": {"type": "integer", "minimum": 0, "maximum": 3},
    },
    "required": [
        "timestamp",
        "frame_id",
        "latitude",
        "longitude",
        "altitude",
        "position_covariance",
        "position_covariance_type",
    ],
}
"""Foxglove's well-known ``foxglove.LocationFix`` as a JSON schema (the fields we send)."""

GEOJSON_SCHEMA: dict[str, Any] = {
    "title": "foxglove.GeoJSON",
    "description": "GeoJSON features (areas, tracked cars, violations) on Earth",
    "type": "object",
    "properties": {"geojson": {"type": "string"}},
    "required": ["geojson"],
}
"""Foxglove's well-known ``foxglove.GeoJSON``: one GeoJSON document as a string."""

FRAME = "world"
"""The frame of the 3D scene: the federation's local metres, x east, y north, z up."""
VIOLATION_LIFETIME = 10  # s: how long a violation's marker stays in the 3D scene

_SHAPE_KINDS = ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")
_VECTOR = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_ENTITY = {
    "title": "foxglove.SceneEntity",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "id": {"type": "string"},
        "lifetime": {**_TIME, "title": "duration"},
        "frame_locked": {"type": "boolean"},
        "metadata": {"type": "array", "items": {"type": "object"}},
        **{kind: {"type": "array", "items": {"type": "object"}} for kind in _SHAPE_KINDS},
    },
}
SCENE_UPDATE_SCHEMA: dict[str, Any] = {
    "title": "foxglove.SceneUpdate",
    "description": "Positions, areas, tracked cars and violations in the local frame (metres)",
    "type": "object",
    "properties": {
        "deletions": {"type": "array", "items": {"type": "object"}},
        "entities": {"type": "array", "items": _ENTITY},
    },
    "required": ["deletions", "entities"],
}
"""Foxglove's well-known ``foxglove.SceneUpdate`` (entities' shapes left open here)."""

_NO_COVARIANCE = [0.0] * 9
_UAV = {"r": 0.1, "g": 0.45, "b": 0.95, "a": 1.0}
_CAR = {"r": 0.95, "g": 0.65, "b": 0.1, "a": 1.0}
_AREA = {"r": 0.3, "g": 0.8, "b": 0.4, "a": 0.8}
_VIOLATION = {"r": 0.9, "g": 0.1, "b": 0.1, "a": 0.7}
_TEXT = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}


def _stamp(valid: int) -> dict[str, int]:
    sec, nsec = divmod(max(valid, 0), NS_PER_S)
    return {"sec": sec, "nsec": nsec}


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    f = float(value)
    return f if math.isfinite(f) else None


class _Topic:
    """One served stream: its JSON channel and, with an origin, its map channel."""

    __slots__ = (
        "bridge",
        "fix",
        "geo",
        "label",
        "platform",
        "raw",
        "role",
        "scene",
    )

    def __init__(self, bridge: FoxgloveBridge, platform: str, label: str, role: str | None):
        self.bridge = bridge
        self.platform = platform
        self.label = label
        self.role = role
        self.raw: Any = None  # created with the first sample: its schema is the sample's
        self.fix: Any = None
        self.geo: Any = None
        self.scene: Any = None

    @property
    def topic(self) -> str:
        """The JSON channel's topic."""
        return f"/{self.platform}/{self.label}"

    def publish(self, batch: list[Any]) -> None:
        """Log a batch of ``(value, valid, available)`` samples on the topic's channels."""
        b = self.bridge
        if self.raw is None and batch:
            schema = label_schema(self.label, batch[0][0])
            schema["description"] = b.describe(self)
            self.raw = b.channel(self.topic, schema)
            if b.origin is not None and self.role == "positions":
                self.fix = b.channel(f"{self.topic}/fix", LOCATION_FIX_SCHEMA)
            elif b.origin is not None and self.role is not None:
                self.geo = b.channel(f"{self.topic}/geo", GEOJSON_SCHEMA)
            if self.role is not None:
                self.scene = b.channel(f"{self.topic}/scene", SCENE_UPDATE_SCHEMA)
        raw, fix, geo, scene = self.raw, self.fix, self.geo, self.scene
        for value, valid, available in batch:
            if raw.has_sinks():  # as a recording holds it: a replay looks the same
                raw.log(sample_json(value, valid, available), log_time=valid)
            try:
                if scene is not None and scene.has_sinks():
                    update = self.scene_update(value, valid)
                    if update is not None:
                        scene.log(_dumps(update), log_time=valid)
                if fix is not None and fix.has_sinks():
                    located = self.location_fix(value, valid)
                    if located is not None:
                        fix.log(_dumps(located), log_time=valid)
                elif geo is not None and geo.has_sinks():
                    features = self.geojson(value)
                    if features is not None:
                        geo.log(_dumps({"geojson": _dumps(features).decode()}), log_time=valid)
            except Exception as exc:  # a malformed value is its platform's problem, not ours
                # counted, its kind logged (bounded), never the value nor the error's text
                # (which may quote it): it came encrypted from another platform
                where = f"foxglove: {self.topic}"
                b._bad.add(f"{self.platform}/{self.label}", where, value, exc)

    def location_fix(self, value: Any, valid: int) -> dict[str, Any] | None:
        """A position ``{"x", "y"[, "z"]}`` (metres) as a ``foxglove.LocationFix``."""
        point = self._geo_point(value)
        if point is None:
            return None
        lat, lon = point
        return {
            "timestamp": _stamp(valid),
            "frame_id": self.platform,
            "latitude": lat,
            "longitude": lon,
            "altitude": _number(value.get("z")) or 0.0,
            "position_covariance": _NO_COVARIANCE,
            "position_covariance_type": 0,
        }

    def geojson(self, value: Any) -> dict[str, Any] | None:
        """An area, the tracked cars or a violation as a GeoJSON FeatureCollection."""
        if not isinstance(value, dict):
            return None
        props = {"platform": self.platform, "label": self.label}
        features: list[dict[str, Any]] = []
        if self.role == "areas":
            ring = [self._lon_lat(p) for p in value.get("polygon") or ()]
            ring = [p for p in ring if p is not None]
            if len(ring) >= 3:
                ring.append(ring[0])
                extra = {"index": value.get("index"), "delegated-by": value.get("delegated-by")}
                features.append(_feature("Polygon", [ring], {**props, **extra}))
        elif self.role == "tracks":
            for car in value.get("cars") or ():
                point = self._lon_lat(car)
                if point is not None:
                    features.append(_feature("Point", point, {**props, **_scalars(car)}))
        else:  # violations: one event, where it happened
            point = self._lon_lat(value)
            if point is not None:
                features.append(_feature("Point", point, {**props, **_scalars(value)}))
        return {"type": "FeatureCollection", "features": features}

    def scene_update(self, value: Any, valid: int) -> dict[str, Any] | None:
        """A sample as a ``foxglove.SceneUpdate`` in the local frame (`FRAME`, metres).

        A position is a sphere with the platform's name, an area its outline, the tracked
        cars boxes: each replaces the previous (one entity per stream). A violation is a
        marker of its own, shown for `VIOLATION_LIFETIME` seconds.
        """
        if not isinstance(value, dict):
            return None
        entity_id = f"{self.platform}/{self.label}"
        lifetime = 0
        shapes: dict[str, list[dict[str, Any]]] = {}
        if self.role == "positions":
            at = _xyz(value)
            if at is None:
                return None
            shapes["spheres"] = [_shape(at, (8.0, 8.0, 8.0), _UAV)]
            shapes["texts"] = [_text((at[0], at[1], at[2] + 10.0), self.platform)]
        elif self.role == "areas":
            points = [_xyz(p) for p in value.get("polygon") or ()]
            ring = [{"x": p[0], "y": p[1], "z": 0.0} for p in points if p is not None]
            if len(ring) < 3:
                return None
            shapes["lines"] = [_line_loop(ring)]
        elif self.role == "tracks":
            cars = [_xyz(c) for c in value.get("cars") or () if isinstance(c, dict)]
            shapes["cubes"] = [_shape(c, (4.5, 1.8, 1.5), _CAR) for c in cars if c is not None]
        else:  # violations: one marker each, for a while
            at = _xyz(value)
            if at is None:
                return None
            entity_id = f"{entity_id}/{valid}"
            lifetime = VIOLATION_LIFETIME * NS_PER_S
            shapes["spheres"] = [_shape(at, (12.0, 12.0, 12.0), _VIOLATION)]
            shapes["texts"] = [_text((at[0], at[1], 15.0), str(value.get("kind", "violation")))]
        entity = {
            "timestamp": _stamp(valid),
            "frame_id": FRAME,
            "id": entity_id,
            "lifetime": _stamp(lifetime),
            "frame_locked": False,
            "metadata": [],
            **{kind: shapes.get(kind, []) for kind in _SHAPE_KINDS},
        }
        return {"deletions": [], "entities": [entity]}

    def _geo_point(self, value: Any) -> tuple[float, float] | None:
        origin, at = self.bridge.origin, _xyz(value)
        return None if origin is None or at is None else local_to_geo(origin, at[0], at[1])

    def _lon_lat(self, value: Any) -> list[float] | None:
        point = self._geo_point(value)
        return None if point is None else [point[1], point[0]]  # GeoJSON: longitude first


def _xyz(value: Any) -> tuple[float, float, float] | None:
    """A point ``{"x", "y"[, "z"]}`` or ``[x, y]`` in metres; None when it is none."""
    if isinstance(value, dict):
        x, y, z = _number(value.get("x")), _number(value.get("y")), _number(value.get("z"))
    elif isinstance(value, list | tuple) and len(value) >= 2:
        x, y, z = _number(value[0]), _number(value[1]), None
    else:
        return None
    return None if x is None or y is None else (x, y, z or 0.0)


def _pose(at: tuple[float, float, float]) -> dict[str, Any]:
    return {
        "position": {"x": at[0], "y": at[1], "z": at[2]},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
    }


def _shape(
    at: tuple[float, float, float], size: tuple[float, float, float], color: dict[str, float]
) -> dict[str, Any]:
    return {"pose": _pose(at), "size": dict(zip("xyz", size, strict=True)), "color": color}


def _text(at: tuple[float, float, float], text: str) -> dict[str, Any]:
    return {
        "pose": _pose(at),
        "billboard": True,
        "font_size": 14.0,
        "scale_invariant": True,
        "color": _TEXT,
        "text": text,
    }


def _line_loop(points: list[dict[str, float]]) -> dict[str, Any]:
    return {
        "type": 1,  # LINE_LOOP
        "pose": _pose((0.0, 0.0, 0.0)),
        "thickness": 2.0,
        "scale_invariant": True,
        "points": points,
        "color": _AREA,
        "colors": [],
        "indices": [],
    }


def _feature(kind: str, coordinates: Any, props: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "Feature",
        "geometry": {"type": kind, "coordinates": coordinates},
        "properties": props,
    }


def _scalars(value: dict[str, Any]) -> dict[str, Any]:
    """A value's plain fields (what the Map panel shows of a feature)."""
    return {
        str(k): v for k, v in value.items() if v is None or isinstance(v, str | int | float | bool)
    }


def _is_wildcard(host: str) -> bool:
    return host in ("", "0.0.0.0", "::")


def _dumps(value: Any) -> bytes:
    # orjson writes NaN and infinities as null: a browser's JSON.parse refuses them
    return orjson.dumps(value, default=str)


@dataclass(slots=True)
class _Member:
    """Another platform as the bridge follows it."""

    name: str
    alive: bool = True
    tasks: set[asyncio.Task[None]] = field(default_factory=set)
    streams: dict[str, FollowedStream] = field(default_factory=dict)  # by label


class FoxgloveBridge:
    """Serves ``platform``'s view of its federation over Foxglove's WebSocket protocol.

    An async context manager. ``settings`` say what it serves (None: the platform
    config's ``[foxglove]``, whose streams and roles default to the ``[console]``'s);
    the server listens on ``host``:``port`` (0: a free one; `url` says which).
    ``ask=False`` serves what arrives without asking for it: beside an `OperatorConsole`
    that asks every member for the same streams. ``sample_period`` is the period asked
    for every stream (None: every sample).

    Who may connect: who presents ``token`` (None: a random one; `login_url` carries it),
    to a ``Host`` of localhost, an IP address or ``allow_hosts``, from no web page or one
    of ``origins`` (None: the settings', Foxglove's web app by default).
    """

    def __init__(
        self,
        platform: FederationPlatform,
        *,
        settings: FoxgloveSettings | None = None,
        host: str = "127.0.0.1",
        port: int = 8765,
        ask: bool = True,
        sample_period: float | None = None,
        token: str | None = None,
        allow_hosts: Iterable[str] = (),
        origins: Iterable[str] | None = None,
    ) -> None:
        from .console import ConsoleAccess

        if sample_period is not None and not sample_period > 0:
            raise ValueError(f"sample_period must be > 0 seconds, got {sample_period}")
        self.platform = platform
        self.name = platform.name
        self.settings = platform.config.foxglove if settings is None else settings
        interface = getattr(platform, "interface", None)
        self.access = ConsoleAccess(
            token=token,
            allow_hosts=[*allow_hosts, *([] if _is_wildcard(host) else [host])],
            audit=interface.audit if interface is not None else None,
            origins=self.settings.origins if origins is None else origins,
            stage="foxglove",
        )
        streams, roles = self.settings.resolve(platform.config.console)
        unknown = [label for label in streams if label not in platform.vocabulary]
        if unknown:
            raise ValueError(
                f"foxglove.streams: {unknown[0]!r} is not in the federation's vocabulary"
            )
        self.streams = streams
        self.roles: ConsoleRoles = roles
        self._role_of = {label: role for role, label in roles.assigned()}
        self.origin = self.settings.origin
        self.host = host
        self.port = port
        self.ask = ask
        self.sample_period = sample_period
        self.url = ""
        self._members: dict[str, _Member] = {}
        self._topics: dict[tuple[str, str], _Topic] = {}
        self._bad = BadValues(log)  # samples that could not be drawn
        self._tasks = OwnedTasks(f"foxglove of {self.name}")
        self._context: Any = None
        self._server: Any = None
        self._relay: Any = None
        self._closing = asyncio.Event()
        self._stack: contextlib.AsyncExitStack | None = None

    @property
    def token(self) -> str:
        """The secret a client presents (``?token=`` in the URL, or a Bearer)."""
        return self.access.token

    @property
    def login_url(self) -> str:
        """`url` with the token: what the operator opens in Foxglove (printed at start)."""
        return f"{self.url}/?token={self.token}" if self.url else ""

    def stats(self) -> dict[str, Any]:
        """The connections relayed and refused (by kind) and the samples not drawn."""
        if self._relay is None:
            relay = {"relayed": 0, "open": 0, "declined": 0, **self.access.stats()}
        else:
            relay = dict(self._relay.stats())
        return {**relay, **self._bad.stats()}

    def __repr__(self) -> str:
        return f"<FoxgloveBridge of {self.name} at {self.url or 'not started'}>"

    def served(self) -> list[str]:
        """What it serves, for a start line: the labels, each with its role if any."""
        shown = [f"{s} ({self._role_of[s]})" if s in self._role_of else s for s in self.streams]
        return [*shown, *(f"{label} (local)" for label in self.settings.local)]

    @property
    def topics(self) -> list[str]:
        """The JSON channels' topics so far (a stream's comes with its first sample)."""
        return sorted(t.topic for t in self._topics.values() if t.raw is not None)

    # -- lifecycle ------------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        if self._stack is not None:
            raise RuntimeError(f"{self!r} was started already; a bridge cannot restart")
        import foxglove

        stack = self._stack = contextlib.AsyncExitStack()
        try:
            instance = self.platform.instance
            missing = [label for label in self.settings.local if not instance.has_label(label)]
            if missing:
                raise ValueError(f"foxglove.local: {missing[0]!r} is not a label of {self.name}")
            from ._foxglove_relay import FoxgloveRelay

            # A context of our own: channels of another SDK user in this process (a
            # recorder, a second bridge) are not served here, nor ours there.
            self._context = foxglove.Context()
            # The SDK's server lets in anyone: only on loopback, on a port nobody is
            # told, reached through the relay (another local user can still find it).
            server = self._server = foxglove.start_server(
                name=f"dyknow {self.name} ({self.platform.config.federation})",
                host="127.0.0.1",
                port=0,
                context=self._context,
            )
            stack.callback(server.stop)
            stack.push_async_callback(self._close_tasks)
            self._relay = await stack.enter_async_context(
                FoxgloveRelay(
                    self.access,
                    f"ws://127.0.0.1:{server.port}/",
                    host=self.host,
                    port=self.port,
                    idle_timeout=self.platform.config.console.idle_timeout,  # as its access
                    max_per_address=self.platform.config.console.max_clients_per_address,
                )
            )
            self.port = self._relay.port
            stack.callback(self._closing.set)  # first out: the refusals' last report
            self._spawn(self.access.run_reports(self._closing), f"foxglove[{self.name}].refusals")
            host = "127.0.0.1" if _is_wildcard(self.host) else self.host
            self.url = f"ws://{f'[{host}]' if ':' in host else host}:{self.port}"
            for label in self.settings.local:
                self._spawn(self._serve_local(label), f"foxglove[{self.name}].local[{label}]")
            events = await stack.enter_async_context(self.platform.membership())
            self._spawn(self._follow_membership(events), f"foxglove[{self.name}].membership")
            for member in self.platform.members:
                self._member_alive(member)
        except BaseException:
            await stack.aclose()
            raise
        log.info("foxglove bridge of %s: %s", self.name, self.url)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Cancel the streams we asked for, end every task of ours, stop the server."""
        stack, self._stack = self._stack, None
        if stack is not None:
            try:
                await stack.aclose()
            finally:
                self._bad.close()

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        return self._tasks.spawn(coro, name)

    async def _close_tasks(self) -> None:
        await self._tasks.aclose()
        cancels = [
            cancel_export(self.platform, m.name, s)
            for m in self._members.values()
            if m.alive
            for s in m.streams.values()
            if s.export_id is not None
        ]
        if cancels:  # best effort: a provider still alive stops streaming to a closed bridge
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(REQUEST_TIMEOUT):
                    await asyncio.gather(*cancels, return_exceptions=True)
        for topic in self._topics.values():
            for channel in (topic.raw, topic.fix, topic.geo):
                if channel is not None:
                    channel.close()

    # -- channels -------------------------------------------------------------------------

    def channel(self, topic: str, schema: dict[str, Any]) -> Any:
        """A JSON channel of our server on ``topic``, its messages described by ``schema``."""
        import foxglove

        return foxglove.Channel(topic, schema=schema, context=self._context)

    def describe(self, topic: _Topic) -> str:
        """What a served stream is: the vocabulary's description of its label."""
        try:
            text = self.platform.vocabulary.description(topic.label)
        except Exception:  # a local label is in no vocabulary
            return f"{topic.label} of {topic.platform}"
        return f"{text} (from {topic.platform})"

    def _topic(self, platform: str, label: str, role: str | None) -> _Topic:
        key = (platform, label)
        topic = self._topics.get(key)
        if topic is None:
            topic = self._topics[key] = _Topic(self, platform, label, role)
        return topic

    # -- membership -----------------------------------------------------------------------

    async def _follow_membership(self, events: Subscription[MembershipEvent]) -> None:
        async for event in events:
            try:
                if event.kind == "joined":
                    self._member_alive(event.platform)
                elif event.kind == "gone":
                    self._member_gone(event.platform)
                # a member that left keeps streaming what was agreed: nothing to do
            except Exception:
                log.exception("foxglove: membership event %s failed", event)

    def _member_alive(self, name: str) -> None:
        if name == self.name:
            return
        m = self._members.get(name)
        if m is None:
            m = self._members[name] = _Member(name)
        elif m.tasks:
            return  # still following it
        m.alive = True
        for label in self.streams:
            task = self._spawn(self._follow(m, label), f"foxglove.stream[{name}:{label}]")
            m.tasks.add(task)
            task.add_done_callback(m.tasks.discard)

    def _member_gone(self, name: str) -> None:
        m = self._members.get(name)
        if m is None:
            return
        m.alive = False
        for stream in m.streams.values():
            stream.export_id = None  # stopped at the provider with us gone for it
        for task in list(m.tasks):
            task.cancel()
        m.tasks.clear()  # a return right after asks anew

    # -- streams --------------------------------------------------------------------------

    async def _follow(self, m: _Member, label: str) -> None:
        """Ask ``m`` for the stream (again while refused or ended) and serve its samples."""
        topic = self._topic(m.name, label, self._role_of.get(label))
        stream = m.streams.get(label)
        if stream is None:  # kept when ``m`` goes: a return resumes where it was
            stream = m.streams[label] = FollowedStream(label, self.sample_period)
        await follow(self.platform, m.name, stream, topic.publish, ask=self.ask)

    async def _serve_local(self, label: str) -> None:
        topic = self._topic(self.name, label, self._role_of.get(label))
        with self.platform.instance.subscribe(label, Policy(start=0)) as sub:
            async for batch in sub.batches():
                topic.publish(batch)
