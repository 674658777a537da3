"""The operator's web console: a live picture of the federation, served by the operator.

`OperatorConsole` is the operator platform's application. It follows the federation's
membership, asks every other member for the streams of the config's ``[console]``
section (`ConsoleSettings`: ``streams``, and the ``roles`` the page draws them as:
positions, areas, tracks, violations), keeps a model of what they send, and serves it
over HTTP (aiohttp, in the node's own event loop) to a plain HTML/JS page with no build
step: a map, the platforms and their streams, the violations, a query box, a policy
editor and an observation form.

Only who holds the console's token may use it (`ConsoleAccess`: a random token printed
with the URL at start, which the page keeps and sends as ``Authorization: Bearer``, never
a cookie; the ``Host`` must be one of the console's names; a foreign ``Origin`` is refused).

HTTP API (see docs/console.md): ``GET /`` the page, ``GET /static/…`` its files,
``GET /api/state`` the model as JSON, ``GET /api/events`` the model as Server-Sent Events
(one ``state`` event per change, at most every `PUSH_INTERVAL` s), ``POST /api/query``,
``POST /api/search``, ``POST /api/policy``, ``POST /api/observation``, ``GET /api/stats``
(the refusals counted). A bad request body
is answered 400 ``{"error": "<field>: …"}``; a federation error (refusal, timeout) 502
with the reason. Nothing a client sends or a platform streams can stop the node.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Self, cast

from aiohttp import web

from agents.transports import Subscription
from dyknow_core import NS_PER_S, Source
from ontology import OntologyError, parse

from .._follow import (
    REQUEST_TIMEOUT,
    BadValues,
    FollowedStream,
    agreed,
    cancel_export,
    follow,
    reason,
)
from .._platform import ConsoleSettings, FederationPlatform
from .._proxy_base import OwnedTasks
from .._service import MembershipEvent
from ._access import ConsoleAccess, serve

__all__ = ["OperatorConsole"]

log = logging.getLogger("federation.console")

OBSERVATION = "observation"
"""The semantic label of the operator's own observations."""
LOCAL_OBSERVATIONS = "operator/observations"
"""Their local label when the federation's vocabulary has no ``observation``."""

STATIC_DIR = Path(__file__).parent / "static"
PUSH_INTERVAL = 0.25  # s: the fastest the page is sent a new state (bounds its redraws)
KEEPALIVE = 1.0  # s: a state is sent at least this often (ages and rates move on)
SEARCH_DEADLINE = 2.0  # s: a label search waits this long for every platform
RATE_WINDOW = 5.0  # s: the arrival rate shown is measured over this window
# s: closing waits this long at most for its cancels to be answered (a provider behind a
# router gone never answers; it stops exporting once our liveliness token goes anyway)
CLOSE_WAIT = 1.0
MAX_VIOLATIONS = 200
MAX_OBSERVATIONS = 200
MAX_TEXT = 500

PlatformState = Literal["alive", "gone", "left"]
Role = Literal["positions", "areas", "tracks", "violations"]


class BadRequest(ValueError):
    """A request body the console cannot use; the message names the field."""


@dataclass(slots=True)
class _Stream(FollowedStream):
    """One stream a platform exports to us: its export, policy and what arrived."""

    role: Role | None = None  # how the page draws it; None: its latest value is shown
    samples: int = 0
    last: float | None = None  # wall-clock time of the last arrival
    arrivals: deque[float] = field(default_factory=lambda: deque(maxlen=256))
    value: Any = None  # the latest value, kept for a stream with no role only

    def to_json(self, now: float) -> dict[str, Any]:
        """The stream as the page shows it."""
        recent = sum(1 for t in self.arrivals if now - t <= RATE_WINDOW)
        return {
            "label": self.label,
            "state": self.state,
            "export_id": self.export_id,
            "sample_period": self.sample_period,
            "error": self.error,
            "samples": self.samples,
            "last": self.last,
            "rate": round(recent / RATE_WINDOW, 2),
            "value": self.value,
        }


@dataclass(slots=True)
class _Platform:
    """A member of the federation as the console knows it."""

    name: str
    state: PlatformState = "alive"
    streams: dict[str, _Stream] = field(default_factory=dict)
    position: dict[str, Any] | None = None
    area: dict[str, Any] | None = None
    cars: list[dict[str, Any]] = field(default_factory=list)
    tasks: set[asyncio.Task[None]] = field(default_factory=set)

    def to_json(self, now: float) -> dict[str, Any]:
        """The platform as the page shows it."""
        lasts = [s.last for s in self.streams.values() if s.last is not None]
        return {
            "name": self.name,
            "state": self.state,
            "samples": sum(s.samples for s in self.streams.values()),
            "last": max(lasts) if lasts else None,
            "streams": [s.to_json(now) for s in self.streams.values()],
            "position": self.position,
            "area": self.area,
            "cars": self.cars,
        }


class OperatorConsole:
    """The operator's web console over ``platform``, as an async context manager.

    ``settings`` say which labels it streams from every other member and how the page
    draws them (None: the platform config's ``[console]``, ``platform.config.console``).
    ``world_map`` (the simulator's ``to_dict``: width, height, roads, crossings, areas)
    is drawn under everything; without it the map scales to what it has seen. The
    server listens on ``host``:``port`` (0: a free port; `url` says which).
    ``sample_period`` is the period asked for every new stream (None: every sample).
    ``token`` is the secret a client must present (None: a random one; `login_url` carries
    it); ``allow_hosts`` are host names, besides localhost and IP addresses, that a
    request's ``Host`` may name (the name the console is reached by, behind a proxy).
    """

    def __init__(
        self,
        platform: FederationPlatform,
        *,
        settings: ConsoleSettings | None = None,
        world_map: dict[str, Any] | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        sample_period: float | None = None,
        token: str | None = None,
        allow_hosts: Iterable[str] = (),
    ) -> None:
        if sample_period is not None and not sample_period > 0:
            raise ValueError(f"sample_period must be > 0 seconds, got {sample_period}")
        interface = getattr(platform, "interface", None)
        self.access = ConsoleAccess(
            token=token,
            allow_hosts=[*allow_hosts, *([] if _is_wildcard(host) else [host])],
            audit=interface.audit if interface is not None else None,
        )
        self.platform = platform
        self.name = platform.name
        self.settings = platform.config.console if settings is None else settings
        unknown = [label for label in self.settings.streams if label not in platform.vocabulary]
        if unknown:
            raise ValueError(
                f"console.streams: {unknown[0]!r} is not in the federation's vocabulary"
            )
        # several labels may be violations (one per kind): all go to the one list
        self._roles: dict[str, Role] = {
            label: cast(Role, role) for role, label in self.settings.roles.assigned()
        }
        self.world_map = world_map
        self.host = host
        self.port = port
        self.sample_period = sample_period
        self._platforms: dict[str, _Platform] = {}
        self._violations: deque[dict[str, Any]] = deque(maxlen=MAX_VIOLATIONS)
        self._observations: deque[dict[str, Any]] = deque(maxlen=MAX_OBSERVATIONS)
        self._bad = BadValues(log)  # samples that did not fit their role
        self._version = 0
        self._changed_event = asyncio.Event()
        self._closing = asyncio.Event()
        self._tasks = OwnedTasks(f"console of {self.name}")
        self._observation_source: Source | None = None
        self._observation_label: str | None = None
        self._observation_semantic: str | None = None  # None: the vocabulary has none
        self._stack: contextlib.AsyncExitStack | None = None
        self.url: str = ""

    @property
    def token(self) -> str:
        """The secret a client presents: ``Authorization: Bearer`` (the page's from its URL)."""
        return self.access.token

    @property
    def login_url(self) -> str:
        """`url` with the token: what the operator opens (printed at start)."""
        return f"{self.url}?token={self.token}" if self.url else ""

    def __repr__(self) -> str:
        return f"<OperatorConsole of {self.name} at {self.url or 'not started'}>"

    # -- lifecycle ------------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        if self._stack is not None:
            raise RuntimeError(f"{self!r} was started already; a console cannot restart")
        stack = self._stack = contextlib.AsyncExitStack()
        try:
            stack.push_async_callback(self._close_tasks)
            self._start_observations()
            events = await stack.enter_async_context(self.platform.membership())
            self._spawn(self._follow_membership(events), f"console[{self.name}].membership")
            for member in self.platform.members:
                self._platform_alive(member)
            await self._start_server(stack)
        except BaseException:
            await stack.aclose()
            raise
        log.info("console of %s: %s", self.name, self.url)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Stop serving, cancel the streams we asked for, end every task of ours."""
        stack = self._stack
        if stack is None:
            return
        self._closing.set()
        try:
            await stack.aclose()
        finally:
            self._bad.close()

    async def _start_server(self, stack: contextlib.AsyncExitStack) -> None:
        app = web.Application(middlewares=[self.access.middleware, _errors_as_json])
        app.router.add_get("/", self._index)
        app.router.add_static("/static/", STATIC_DIR, name="static")
        app.router.add_get("/api/state", self._get_state)
        app.router.add_get("/api/events", self._get_events)
        app.router.add_post("/api/query", self._post_query)
        app.router.add_post("/api/search", self._post_search)
        app.router.add_post("/api/policy", self._post_policy)
        app.router.add_post("/api/observation", self._post_observation)
        app.router.add_get("/api/stats", self._get_stats)
        # Event streams end as soon as we close (they watch `_closing`): no long wait.
        self.port = await serve(
            app,
            self.host,
            self.port,
            stack,
            self.access,
            max_per_address=self.settings.max_clients_per_address,
            idle_timeout=self.settings.idle_timeout,
        )
        # a wildcard address is no place to open: the same server on loopback is
        host = "127.0.0.1" if _is_wildcard(self.host) else self.host
        host = f"[{host}]" if ":" in host else host
        self.url = f"http://{host}:{self.port}/"
        self._spawn(self.access.run_reports(self._closing), f"console[{self.name}].refusals")

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        return self._tasks.spawn(coro, name)

    async def _close_tasks(self) -> None:
        # Best effort, bounded: a provider still alive stops streaming to a closed console.
        cancels = [
            cancel_export(self.platform, p.name, s)
            for p in self._platforms.values()
            if p.state != "gone"  # one that left still streams to us
            for s in p.streams.values()
            if s.export_id is not None
        ]
        await self._tasks.aclose()
        if cancels:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CLOSE_WAIT):
                    await asyncio.gather(*cancels, return_exceptions=True)

    # -- the model ------------------------------------------------------------------------

    def _changed(self) -> None:
        self._version += 1
        # Every waiter wakes; the next ones wait on a fresh event.
        self._changed_event.set()
        self._changed_event = asyncio.Event()

    def state(self) -> dict[str, Any]:
        """The whole model as JSON-able data (what ``GET /api/state`` answers)."""
        now = time.time()
        return {
            "operator": self.name,
            "version": self._version,
            "now": now,
            "streams": list(self.settings.streams),
            "roles": self.settings.roles.model_dump(),
            "observation_label": self._observation_semantic,
            "world": self.world_map,
            "platforms": [
                p.to_json(now) for _, p in sorted(self._platforms.items()) if p.name != self.name
            ],
            "violations": list(self._violations),
            "observations": list(self._observations),
        }

    # -- membership -----------------------------------------------------------------------

    async def _follow_membership(self, events: Subscription[MembershipEvent]) -> None:
        async for event in events:
            try:
                if event.kind == "joined":
                    self._platform_alive(event.platform)
                elif event.kind == "gone":
                    self._platform_gone(event.platform)
                else:
                    self._platform_left(event.platform)
            except Exception:
                log.exception("console: membership event %s failed", event)

    def _platform_alive(self, name: str) -> None:
        if name == self.name:
            return
        p = self._platforms.get(name)
        if p is None:
            p = self._platforms[name] = _Platform(name)
        elif p.state == "alive":
            return
        p.state = "alive"
        for label in self.settings.streams:
            stream = p.streams.get(label)
            if stream is None:
                stream = p.streams[label] = _Stream(
                    label, self.sample_period, role=self._roles.get(label)
                )
            if any(t.get_name().endswith(f":{label}]") for t in p.tasks):
                continue  # after a leave it kept flowing: nothing to ask again
            stream.state, stream.export_id, stream.error = "requesting", None, None
            task = self._spawn(self._follow_stream(p, stream), f"console.stream[{name}:{label}]")
            p.tasks.add(task)
            task.add_done_callback(p.tasks.discard)
        self._changed()

    def _platform_left(self, name: str) -> None:
        # Streams already agreed keep flowing after a leave: the subscriptions stay.
        p = self._platforms.get(name)
        if p is None or p.state != "alive":
            return
        p.state = "left"
        self._changed()

    def _platform_gone(self, name: str) -> None:
        p = self._platforms.get(name)
        if p is None:
            return
        p.state = "gone"
        p.cars = []
        for task in list(p.tasks):
            task.cancel()
        # forgotten now, not when they finish: a return right after asks anew
        p.tasks.clear()
        for stream in p.streams.values():
            stream.state, stream.export_id = "ended", None
        self._changed()

    # -- streams --------------------------------------------------------------------------

    async def _follow_stream(self, p: _Platform, stream: _Stream) -> None:
        """Ask ``p`` for the stream (again while refused or ended), take in its samples."""
        await follow(
            self.platform,
            p.name,
            stream,
            lambda batch: self._take(p, stream, batch),
            alive=lambda: p.state == "alive",
            changed=self._changed,
        )
        if p.state != "gone":  # left: what was agreed has ended
            stream.state = "ended"
            self._changed()

    def _take(self, p: _Platform, stream: _Stream, batch: list[Any]) -> None:
        now = time.time()
        stream.samples += len(batch)
        stream.last = now
        stream.arrivals.extend(now for _ in range(min(len(batch), 64)))
        role = stream.role
        if role is None:
            if batch:  # only the latest is shown
                stream.value = _clean(batch[-1][0])
        else:
            for value, valid, _ in batch:
                try:
                    self._apply(p, role, value, valid)
                except Exception as exc:
                    # A malformed value from a platform is its problem, never the console's:
                    # counted, its kind logged (bounded), never the value nor the error's text
                    where = f"console: {p.name} {stream.label}"
                    self._bad.add(f"{p.name}/{stream.label}", where, value, exc)
        self._changed()

    def _apply(self, p: _Platform, role: Role, value: Any, valid: int) -> None:
        """Take one sample into the model as what ``role`` says it is."""
        if role == "positions":
            p.position = {k: _finite(value[k]) for k in ("x", "y", "z") if k in value}
        elif role == "areas":
            p.area = {
                "index": value.get("index"),
                "polygon": [[_finite(x), _finite(y)] for x, y in value["polygon"]],
                "delegated-by": value.get("delegated-by"),
            }
        elif role == "tracks":
            cars = value["cars"]
            if not isinstance(cars, list):
                raise TypeError("'cars' is not a list")
            p.cars = [
                _clean({**c, "x": _finite(c["x"]), "y": _finite(c["y"])})
                for c in cars
                if isinstance(c, dict) and _is_finite(c.get("x")) and _is_finite(c.get("y"))
            ]
        else:  # violations
            if not isinstance(value, dict):
                raise TypeError("not an object")
            entry = {**value, "reported-by": p.name, "valid": valid / NS_PER_S}
            self._violations.appendleft(_clean(entry))

    # -- observations ---------------------------------------------------------------------

    def _start_observations(self) -> None:
        """The operator's own stream of observations, watched like any other."""
        try:
            label = self.platform.labels.to_local(OBSERVATION)
            self._observation_semantic = OBSERVATION
        except OntologyError as exc:
            # a federation whose vocabulary has no 'observation': kept local, still queryable
            label = LOCAL_OBSERVATIONS
            log.info("console %s: %s; observations go to %s", self.name, exc, label)
        instance = self.platform.instance
        if instance.has_label(label):
            # The application made it already: push through its source when it is one.
            found = [
                p for p in instance.processes.values() if isinstance(p, Source) and p.label == label
            ]
            self._observation_source = found[0] if found else None
        else:
            self._observation_source = instance.add_source(label, name="console:observations")
        self._observation_label = label
        sub = instance.subscribe(label, callback=self._observed)
        self._spawn(self._hold(sub), f"console[{self.name}].observations")

    async def _hold(self, sub: Any) -> None:
        with sub:
            await self._closing.wait()

    def _observed(self, batch: list[Any]) -> None:
        for value, valid, _ in batch:
            if isinstance(value, dict):
                self._observations.appendleft({**value, "valid": valid / NS_PER_S})
        self._changed()

    # -- HTTP -----------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.StreamResponse:
        # the URL may hold the token: no Referer of it anywhere, no copy in a cache
        return web.FileResponse(
            STATIC_DIR / "index.html",
            headers={"Referrer-Policy": "no-referrer", "Cache-Control": "no-store"},
        )

    async def _get_state(self, request: web.Request) -> web.Response:
        return _json(self.state())

    async def _get_stats(self, request: web.Request) -> web.Response:
        return _json({**self.access.stats(), **self._bad.stats()})

    async def _get_events(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": "text/event-stream",
                "Cache-Control": "no-cache",
                "X-Accel-Buffering": "no",
            }
        )
        await response.prepare(request)
        sent = -1
        loop = asyncio.get_running_loop()
        last_push = 0.0
        with contextlib.suppress(ConnectionError, asyncio.CancelledError):
            while not self._closing.is_set():
                idle = loop.time() - last_push
                if self._version == sent and idle < KEEPALIVE:
                    changed = self._changed_event  # checked with the version: no lost wake-up
                    await _first(changed.wait(), self._closing.wait(), timeout=KEEPALIVE - idle)
                    continue
                sent, last_push = self._version, loop.time()
                data = _dumps(self.state(), separators=(",", ":"))
                await response.write(f"event: state\ndata: {data}\n\n".encode())
                await asyncio.sleep(PUSH_INTERVAL)  # coalesce a burst of changes into one push
        return response

    async def _post_query(self, request: web.Request) -> web.Response:
        body = await _body(request)
        platform = self._member(body)
        label = self._label(body)
        kind = body.get("kind", "latest")
        if kind not in ("latest", "at", "between"):
            raise BadRequest(f"kind: {kind!r} is not one of 'latest', 'at', 'between'")
        content: dict[str, Any] = {"labels": [label]}
        if kind == "latest":
            content["action"] = "get-latest"
        elif kind == "at":
            content.update(action="get-value-at", t=_number(body, "at", 0.0), relative=True)
        else:
            start, end = _number(body, "from", -30.0), _number(body, "to", 0.0)
            if start > end:
                raise BadRequest(f"from: {start} is after to ({end})")
            content.update(action="get-trajectory", relative=True, **{"from": start, "to": end})
        answer = await self._ask(
            lambda: self.platform.federation_agent.request_from(
                platform, content, timeout=REQUEST_TIMEOUT
            )
        )
        part = answer.get(label, {}) if isinstance(answer, dict) else {}
        rows = part.get("samples", []) if isinstance(part, dict) else []
        return _json(
            {
                "platform": platform,
                "label": label,
                "kind": kind,
                "query_time": part.get("query_time") if isinstance(part, dict) else None,
                "samples": [
                    {"value": r[0], "valid": r[1], "available": r[2]}
                    for r in rows
                    if isinstance(r, list) and len(r) == 3
                ],
            }
        )

    async def _post_search(self, request: web.Request) -> web.Response:
        body = await _body(request)
        formula = body.get("formula")
        if not isinstance(formula, str) or not formula.strip():
            raise BadRequest("formula: expected a FIPA-SL formula, e.g. (all ?x (Car ?x))")
        try:
            # malformed, or a concept the vocabulary does not have: named before anyone
            # is asked (whether anything matches is each platform's answer, ours too)
            self.platform.vocabulary.check(parse(formula))
        except OntologyError as exc:
            raise BadRequest(f"formula: {reason(exc)}") from exc
        result = await self._ask(
            lambda: self.platform.federation_agent.global_request(
                {"action": "search-labels", "formula": formula},
                deadline=SEARCH_DEADLINE,
                include_self=True,
            )
        )
        answers = {
            p: (a.get("labels", []) if isinstance(a, dict) else a)
            for p, a in result.answers.items()
        }
        return _json(
            {
                "formula": formula,
                "answers": answers,
                "refused": result.refused,
                "no_answer": result.no_answer,
                "unlisted": result.unlisted,
            }
        )

    async def _post_policy(self, request: web.Request) -> web.Response:
        body = await _body(request)
        name = body.get("platform")
        p = self._platforms.get(name) if isinstance(name, str) else None
        if p is None:
            raise BadRequest(f"platform: {name!r} is not a platform the console follows")
        if p.state != "alive":
            raise BadRequest(f"platform: {name} is {p.state}")
        label = body.get("label")
        stream = p.streams.get(label) if isinstance(label, str) else None
        if stream is None:
            streams = ", ".join(self.settings.streams) or "none"
            raise BadRequest(f"label: {label!r} is not one of the console's streams ({streams})")
        if "sample_period" not in body:
            raise BadRequest("sample_period: missing (seconds, or null for every sample)")
        period = body["sample_period"]
        if period is not None:
            period = _number(body, "sample_period", 0.0)
            if not period > 0:
                raise BadRequest(f"sample_period: must be > 0 seconds, got {period}")
        await self._ask(lambda: self._change_policy(p, stream, period))
        return _json({"platform": p.name, "stream": stream.to_json(time.time())})

    async def _change_policy(self, p: _Platform, stream: _Stream, period: float | None) -> None:
        """Cancel the export and ask for it again with the new period (the old one if refused)."""
        fed = self.platform.federation_agent
        async with stream.lock:
            old = stream.sample_period
            await cancel_export(self.platform, p.name, stream)
            try:
                stream.export_id = await fed.create_stream(
                    p.name, [stream.label], sample_period=period, timeout=REQUEST_TIMEOUT
                )
            except Exception:
                with contextlib.suppress(Exception):
                    stream.export_id = await fed.create_stream(
                        p.name, [stream.label], sample_period=old, timeout=REQUEST_TIMEOUT
                    )
                    agreed(stream, p.name, self.platform.name)  # a refused one may flow now
                raise
            finally:
                self._changed()
            stream.sample_period = period
            agreed(stream, p.name, self.platform.name)
            stream.arrivals.clear()  # the rate shown is the new policy's

    async def _post_observation(self, request: web.Request) -> web.Response:
        body = await _body(request)
        x, y = _number(body, "x"), _number(body, "y")
        text = body.get("text")
        if not isinstance(text, str) or not text.strip():
            raise BadRequest("text: expected a non-empty string")
        if len(text) > MAX_TEXT:
            raise BadRequest(f"text: longer than {MAX_TEXT} characters")
        source = self._observation_source
        if source is None:
            return _json({"error": "the observation stream is not this console's"}, status=500)
        value = {"x": x, "y": y, "text": text.strip()}
        source.push(value)
        # the semantic label it is shared under: None when the vocabulary has none (kept local)
        return _json({"observation": value, "label": self._observation_semantic})

    def _member(self, body: dict[str, Any]) -> str:
        name = body.get("platform")
        if not isinstance(name, str) or not name:
            raise BadRequest("platform: expected a platform's name")
        if name != self.name and name not in self.platform.members:
            raise BadRequest(f"platform: {name!r} is not a member of the federation now")
        return name

    def _label(self, body: dict[str, Any]) -> str:
        label = body.get("label")
        if not isinstance(label, str) or not label:
            raise BadRequest("label: expected a semantic label of the federation's vocabulary")
        if label not in self.platform.vocabulary:
            raise BadRequest(f"label: {label!r} is not in the federation's vocabulary")
        return label

    async def _ask(self, call: Callable[[], Awaitable[Any]]) -> Any:
        """The federation's answer; a refusal, failure or timeout becomes a 502."""
        try:
            return await call()
        except (BadRequest, asyncio.CancelledError):
            raise
        except Exception as exc:
            raise _FederationError(reason(exc)) from exc


class _FederationError(Exception):
    """Another platform refused, failed or did not answer."""


def _json(data: Any, status: int = 200) -> web.Response:
    return web.Response(text=_dumps(data), status=status, content_type="application/json")


@web.middleware
async def _errors_as_json(
    request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
) -> web.StreamResponse:
    try:
        return await handler(request)
    except BadRequest as exc:
        return _json({"error": str(exc)}, status=400)
    except _FederationError as exc:
        return _json({"error": str(exc)}, status=502)
    except web.HTTPException as exc:
        if exc.status < 400 or not request.path.startswith("/api/"):
            raise
        # every answer of the API is JSON, its errors too: a client parses one shape
        answer = _json({"error": _http_error(request, exc)}, status=exc.status)
        if "Allow" in exc.headers:  # a 405 says which methods the endpoint takes
            answer.headers["Allow"] = exc.headers["Allow"]
        return answer
    except Exception as exc:
        log.exception("console: %s %s failed", request.method, request.path)
        return _json({"error": f"internal error: {type(exc).__name__}: {exc}"}, status=500)


def _http_error(request: web.Request, exc: web.HTTPException) -> str:
    """The API's words for an error of the router (no such endpoint, a wrong method)."""
    if isinstance(exc, web.HTTPNotFound):
        return f"path: no endpoint {request.path}"
    if isinstance(exc, web.HTTPMethodNotAllowed):
        allowed = ", ".join(sorted(exc.allowed_methods))
        return f"method: {request.method} is not one of {request.path}'s ({allowed})"
    return f"{exc.status}: {exc.reason}"


async def _body(request: web.Request) -> dict[str, Any]:
    # A page on another site can POST text/plain without asking (no CORS preflight);
    # application/json it cannot, and a browser names the page's origin
    if request.content_type != "application/json":
        raise BadRequest(f"body: Content-Type must be application/json, not {request.content_type}")
    # (a foreign Origin was refused before: `ConsoleAccess.middleware`)
    try:
        body = await request.json()
    except (ValueError, UnicodeDecodeError) as exc:
        raise BadRequest(f"body: not JSON: {exc}") from exc
    except RecursionError:
        raise BadRequest("body: JSON nested too deep") from None
    except LookupError:  # the Content-Type's charset
        raise BadRequest(f"body: charset {request.charset!r} is not one Python knows") from None
    if not isinstance(body, dict):
        raise BadRequest("body: expected a JSON object")
    return body


def _is_wildcard(host: str) -> bool:
    return host in ("", "0.0.0.0", "::")


def _number(body: dict[str, Any], key: str, default: float | None = None) -> float:
    value = body.get(key, default)
    if value is None:
        raise BadRequest(f"{key}: missing (a number)")
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise BadRequest(f"{key}: expected a finite number, got {json.dumps(value)}")
    return float(value)


def _finite(value: Any) -> float:
    """A finite float, or ValueError (NaN and infinities are not JSON: the page would stop)."""
    f = float(value)
    if not math.isfinite(f):
        raise ValueError(f"{value!r} is not a finite number")
    return f


def _is_finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _clean(value: Any, depth: int = 0) -> Any:
    """``value`` with non-finite floats as None (and nesting cut at 32): valid JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if depth >= 32:
        return None
    if isinstance(value, dict):
        return {str(k): _clean(v, depth + 1) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v, depth + 1) for v in value]
    return value


def _dumps(data: Any, **options: Any) -> str:
    """JSON for the page: never NaN or Infinity (a browser's JSON.parse refuses them)."""
    try:
        return json.dumps(data, default=str, allow_nan=False, **options)
    except ValueError:
        return json.dumps(_clean(data), default=str, allow_nan=False, **options)


async def _first(*aws: Coroutine[Any, Any, Any], timeout: float) -> None:
    """Wait until the first of ``aws`` is done, or ``timeout`` s; cancel the rest."""
    loop = asyncio.get_running_loop()
    tasks = [loop.create_task(a, name=f"console.first[{i}]") for i, a in enumerate(aws)]
    try:
        await asyncio.wait(tasks, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
