"""The networked ``dyknow`` commands (node, router, platforms, labels, ask, watch) as async code."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import signal
import time
import uuid
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack

from agents import (
    AuthenticationError,
    KeyPair,
    OwnerBatches,
    SecurityError,
    SecurityPolicy,
    TransportClosed,
    TransportError,
    TrustStore,
    UnknownPlatform,
    watch_request,
    watch_time,
    wire_key,
)
from agents.transports import MqttConfig, Transport, ZenohConfig, ZenohTransport

from ._cli_common import (
    NotAnsweredError,
    WatchLostError,
    complain,
    failure_of,
    platforms_of,
    reaching,
    settle_gc,
    wait_for_members,
)
from ._platform import FederationPlatform, PlatformConfig, PlatformConfigError
from ._quote import quoted

if TYPE_CHECKING:
    from ._application import NodeApplication
    from ._local import LocalChannel

log = logging.getLogger(__name__)
_WATCH_ASK = 2.0  # s one watch request waits for the platform's answer
# s below the platform's time when the watch began listening that a batch may be signed:
# the platform signs a batch just before it publishes it (and ms rounding)
_WATCH_MARGIN = 0.25


class _WatchAnchor:
    """When, on the platform's clock, the owner's watch began listening: its batches' bound.

    None reaches a subscriber declared later, so one signed before is recorded and
    replayed. The platform signs its time into each answer to a watch request
    (`watch_time`), somewhere between the request's asking and its answer's arrival here:
    the watch began at least that long before it. A platform of an older release answers
    bare: then this side's clock, less the federation's clock allowance, is the bound.
    """

    def __init__(self, batches: OwnerBatches, listening: float, skew: float) -> None:
        self.batches = batches
        self.listening = listening  # time.monotonic() before subscribing
        self.skew = skew
        self.signed = False

    def answered(self, signed_at: float | None, asked: float, received: float) -> None:
        """Take an answer the platform signed at ``signed_at`` (None: bare), asked/received then."""
        if signed_at is None:
            if self.batches.since is None:
                self.batches.since = time.time() - (received - self.listening) - self.skew
            return
        earliest = signed_at - (received - self.listening)
        latest = signed_at - (asked - self.listening)
        since = self.batches.since
        if not self.signed or since is None:
            self.signed = True
            self.batches.since = earliest - _WATCH_MARGIN
        elif latest < since + _WATCH_MARGIN:
            # its clock stepped back: else its batches would be refused until it caught up
            self.batches.since = earliest - _WATCH_MARGIN


class RelayedError(RuntimeError):
    """An error the running node reported for a command it relayed; its text says what."""


def _stop_event() -> asyncio.Event:
    """An event set on SIGINT or SIGTERM."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    return stop


class PlatformLostError(TransportError):
    """A node stopped because its transport ended one of its platform's declarations.

    Raised once the node closed cleanly; its command exits 1, for a supervisor to start
    it again (a new process declares everything anew, or fails to start naming why).
    """


class _Losses:
    """What the transport ended of a node's platform's declarations, that stops the node.

    A loss before the node says it is ready is a start failure (`started` raises: no
    ready line, exit 1); one after stops it (``stop`` set, said once on stderr); one
    once a stop was asked (SIGINT/SIGTERM) stops nothing more and changes no exit code
    (the platform logs and counts it: `AgentPlatform.declared`).
    """

    def __init__(self, p: FederationPlatform, stop: asyncio.Event, command: str) -> None:
        self.lost: dict[str, str] = {}  # what, why: the losses the node stops for
        self._name, self._stop, self._command = p.name, stop, command
        self._ready = False
        p.agents.on_lost(self._lose)

    def _lose(self, what: str, reason: str) -> None:
        if not self.lost:
            if self._stop.is_set():  # a stop asked before: it exits as asked
                return
            if self._ready:
                complain(
                    f"dyknow {self._command}: {self._name} stopping, to exit with code 1 for "
                    f"its supervisor to restart it: the transport ended its {what}"
                )
            self._stop.set()
        self.lost[what] = reason

    def started(self) -> None:
        """Ready from now on; `PlatformLostError` when something was lost before (a start
        that failed: the node closes and exits 1 with it, never saying it is ready)."""
        if self.lost:
            raise _lost_error(self._name, self.lost, started=False)
        self._ready = True


def _lost_error(name: str, lost: dict[str, str], *, started: bool = True) -> PlatformLostError:
    """The error a node stopped (or failed to start) for ``lost`` ends with: each
    declaration named, each reason said once, after the declarations it ended."""
    by_reason: dict[str, list[str]] = {}
    for what, reason in lost.items():
        by_reason.setdefault(reason, []).append(what)
    ended = "; ".join(
        f"its {', its '.join(whats)} ({reason})" for reason, whats in by_reason.items()
    )
    return PlatformLostError(
        f"platform {name!r} {'stopped' if started else 'could not start'}: the transport "
        f"ended {ended}. Started again, it declares them anew"
    )


def _say_lost(command: str, p: FederationPlatform, say: Callable[[str], None]) -> None:
    """The declarations the transport ended, when any: one line of the node's figures."""
    if p.agents.lost:
        say(
            f"dyknow {command}: declarations lost: {p.agents.stats.declarations_lost} "
            f"({', '.join(p.agents.lost)})"
        )


def endpoints(config: PlatformConfig) -> str:
    """The transport endpoints of a config, for the ready message."""
    t = config.transport
    if isinstance(t, ZenohConfig):
        listen = ",".join(t.listen) if t.listen else "ephemeral"
        connect = ",".join(t.connect) or "-"
        return f"zenoh {t.mode} listen={listen} connect={connect}"
    return f"mqtt {getattr(t, 'host', '?')}:{getattr(t, 'port', '?')}"


def unprovided(platform: FederationPlatform, source: str) -> list[str]:
    """Warnings for the mapping's entries whose local label no stream here has or can have.

    A fixed entry whose local label is no stream yet, and a pattern entry whose local
    pattern matches no stream here and no label an input, an import or the anchoring can
    make (the inputs' ``fields`` labels with their ``{field}`` placeholders,
    ``import_label``, the class features' label patterns with their ``{id}``).
    Not an error: a stream may appear after the start (an input with ``create = true``,
    an imported stream, a source added by the program), but a label the application
    lacks, a typo, is otherwise found only when asked for it ("no stream for it here").
    """
    config, mapping = platform.config, platform.mapping
    instance, vocabulary = platform.instance, platform.vocabulary
    where = (
        f"{source}: mapping: {config.mapping}"
        if isinstance(config.mapping, Path)
        else f"{source}: mapping"
    )
    labels = instance.labels()
    templates = [label for spec in config.inputs for label in spec.fields.values()]
    templates.append(config.import_label)
    # the anchoring makes a stream per feature of each object it creates or links
    # (imported only where there are processes: a node without them does not load the
    # reasoning package)
    processes = list(instance.processes.values())
    if processes:
        from dyknow_core.reasoning import Anchoring
    for process in processes:
        if isinstance(process, Anchoring):
            for cls in process.classes.values():
                templates.extend(cls.features.values())
    warnings = []
    for semantic in mapping.mapped:
        entry = vocabulary.pattern(semantic)
        local_pattern = mapping.local_entry(semantic)
        local = local_pattern.text
        key = _key(semantic)
        if entry is not None and entry.parameterized:
            # a pattern's streams come and go with their objects: only a pattern nothing
            # can ever match is said (a typo on either side of a placeholder)
            if any(local_pattern.overlaps(t) for t in [*labels, *templates]):
                continue
            candidates = sorted({*labels, *templates} - {config.import_label})
            import difflib  # here: only a warning uses it, and a node holds what it imports

            near = difflib.get_close_matches(local, candidates, n=3, cutoff=0.5)
            listed = ", ".join(map(repr, candidates[:5])) + (", …" if len(candidates) > 5 else "")
            could = f"did you mean {', '.join(map(repr, near))}?" if near else f"here: {listed}"
            warnings.append(
                f"{where}: {key}: warning: local pattern {local!r} can match no stream here nor "
                f"any label an input, import or class feature makes ({could}): no "
                f"{semantic!r} label is served until one does"
            )
            continue
        if not instance.has_label(local):
            warnings.append(
                f"{where}: {key}: warning: no stream {local!r} here yet (a label "
                f"the application lacks?): asking for {semantic!r} is refused until one appears"
            )
    return warnings


def _key(semantic: str) -> str:
    """The mapping's entry as a TOML path: ``labels.x`` or ``labels."{object}-state"``."""
    return f"labels.{semantic}" if _BARE_KEY.fullmatch(semantic) else f'labels."{semantic}"'


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


async def _refuse_running_here(config: PlatformConfig) -> None:
    """PlatformAliveError when a node of ``config`` listens on its local channel here.

    Asked before the transport opens: that node holds the config's ``listen`` endpoints,
    so a second start of the same config would otherwise stop on an address in use,
    which does not say that the platform runs already, nor where.
    """
    import socket

    from ._local import (
        NodeUnreachable,
        PlatformAliveError,
        _node_here,
        _since,
        _where,
        channel_path,
    )

    try:
        path = channel_path(config)
    except NodeUnreachable:  # its key unreadable: the platform's own start says why
        return
    here = await _node_here(path)
    if here is None:
        return
    where = _where({"pid": here or "unknown", "host": socket.gethostname(), "since": _since(here)})
    raise PlatformAliveError(
        f"platform {config.name!r} is alive in federation {config.federation!r} already: "
        f"{where}. A platform runs in one process: stop that one first, or give this one a "
        "name of its own (the one-shot commands go through the running node)"
    )


@contextlib.asynccontextmanager
async def _platform(
    config: PlatformConfig, source: str
) -> AsyncIterator[tuple[FederationPlatform, NodeApplication, LocalChannel]]:
    """The config's platform with its application and local channel, not yet joined.

    What ``dyknow node``, ``console`` and ``foxglove`` run; each joins once what it adds
    (a console, a bridge) is up too.
    """
    from ._application import NodeApplication, check_application
    from ._local import LocalChannel, refuse_duplicate

    check_application(config, source)  # before anything opens: exit 2, nothing touched
    await _refuse_running_here(config)
    transport = config.make_transport()
    # Out of the federation until the application is set up: a query must find its streams.
    async with (
        transport,
        _checked(refuse_duplicate(transport, config)),
        FederationPlatform(config, source=source, join=False, transport=transport) as p,
        NodeApplication(p, source) as application,
        LocalChannel(p) as channel,
    ):
        yield p, application, channel


async def run_node(config: PlatformConfig, source: str, say: Callable[[str], None]) -> None:
    """Run one platform and its application until SIGINT/SIGTERM, then shut it down cleanly.

    A declaration of the platform's that the transport ends by itself (MQTT: a filter
    the broker refuses after a reconnection) stops it too, cleanly, then raises
    `PlatformLostError`; one before it is ready fails its start (`_Losses`).

    SIGHUP re-reads the config file's ``[sharing]`` table (only that) and applies it
    (`reload_sharing`); a wrong one is said in one line and the policy in force stays.
    """
    async with _platform(config, source) as (p, application, channel):
        _warn(unprovided(p, source))
        await p.join()
        stop = _stop_event()  # after opening: zenoh installs handlers of its own
        losses = _Losses(p, stop, "node")
        async with _reloading_on_hup(p, source, say, "node"):
            losses.started()
            say(
                f"dyknow node: {p.name} ready in federation {config.federation} "
                f"({endpoints(config)})"
            )
            settle_gc()  # once ready: a full collection is ~15 ms a supervisor need not wait for
            await stop.wait()
        _say_stats("node", application, say)
        say(
            f"dyknow node: local channel: {channel.served} commands served, "
            f"{channel.refused} refused"
        )
        _say_lost("node", p, say)
    say(f"dyknow node: {config.name} stopped")
    if losses.lost:
        raise _lost_error(config.name, losses.lost)


@contextlib.asynccontextmanager
async def _reloading_on_hup(
    p: FederationPlatform, source: str, say: Callable[[str], None], command: str
) -> AsyncIterator[None]:
    """While in it, SIGHUP reloads ``[sharing]`` (`_reload_on_hup`); one held since the
    process started (`federation._hup`) is applied on entry; once out, SIGHUP is ignored
    (the process stops: never the signal's default, which ends it)."""
    from ._hup import on_hup

    hup = asyncio.Event()
    loop = asyncio.get_running_loop()
    # the signal's handler runs between two bytecodes of whatever runs: it only schedules
    on_hup(lambda: loop.call_soon_threadsafe(hup.set))
    reloads = loop.create_task(_reload_on_hup(p, source, hup, say, command), name="sighup")
    try:
        yield
    finally:
        on_hup(None)  # stopping: a SIGHUP is ignored, never a kill
        reloads.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await reloads


async def _reload_on_hup(
    p: FederationPlatform,
    source: str,
    hup: asyncio.Event,
    say: Callable[[str], None],
    command: str = "node",
) -> None:
    """Reload the ``[sharing]`` table of ``source`` each time ``hup`` is set (SIGHUP).

    One reload at a time: signals that come meanwhile make one more after it. Each line
    said starts ``dyknow COMMAND:``.
    """
    from ._platform import load_sharing

    def tell(line: str, out: Callable[[str], None] = say) -> None:
        try:
            out(line)
        except OSError as exc:  # stdout/stderr gone (a closed pipe): the reloads go on
            log.warning("%s (not said: %s)", line, exc)

    def warn(line: str) -> None:
        tell(line, complain)

    me = f"dyknow {command}:"
    while True:
        await hup.wait()
        hup.clear()
        await _reload_trust(p, me, tell, warn)
        try:
            settings = await asyncio.to_thread(
                load_sharing,
                source,
                name=p.name,
                federation=p.config.federation,
                running=p.federation_agent.sharing.settings,
            )
            changes, ended = await p.reload_sharing(settings, source=source)
        except PlatformConfigError as exc:
            warn(f"{me} [sharing] not reloaded, the policy in force stays: {exc}")
            continue
        except Exception as exc:  # a reload must never take the node down
            log.exception("reloading [sharing] from %s", source)
            warn(f"{me} [sharing] reload failed: {source}: {type(exc).__name__}: {exc}")
            continue
        tell(f"{me} [sharing] reloaded from {source}: {'; '.join(changes) or 'no change'}")
        for export_id, semantic, receiver, _ in ended:
            tell(
                f"{me} export {export_id} of {semantic!r} to {receiver} ended: "
                "the reloaded [sharing] no longer allows it"
            )


async def _reload_trust(
    p: FederationPlatform,
    me: str,
    tell: Callable[[str], None],
    warn: Callable[[str], None],
) -> None:
    """Re-read the trust file and apply it (`FederationPlatform.reload_trust`); a broken or
    unreadable one is said in one line and the trust in force stays."""
    path = None
    try:
        path = p.config.trust
        # read in a thread (a regular file only: `TrustStore.load` checks the file it
        # opened); applied before the [sharing] reload, which warns of patterns no
        # trusted platform matches
        store = await asyncio.to_thread(TrustStore.load, path)
        changes = p.reload_trust(store, source=str(path))
    except (SecurityError, ValueError, OSError) as exc:
        warn(f"{me} trust file not reloaded, the trust in force stays: {exc}")
        # audited: a trust file of another federation, or with another key for this
        # platform, is what someone who can write it but not read our key would put there
        p.interface.audit.record(
            verdict="refused",
            stage="trust",
            code="trust-file",
            reason=f"trust file not reloaded, the trust in force stays: {exc}",
        )
        return
    except Exception as exc:  # a reload must never take the node down
        log.exception("reloading the trust file %s", path)
        warn(f"{me} trust file reload failed: {path}: {type(exc).__name__}: {exc}")
        return
    tell(f"{me} trust file reloaded from {path}: {'; '.join(changes) or 'no change'}")


def _say_stats(command: str, application: NodeApplication, say: Callable[[str], None]) -> None:
    """One JSON line per input and output of the application: what it received, published."""
    for row in application.stats():
        say(f"dyknow {command}: {json.dumps(row, sort_keys=True)}")


def _warn(warnings: list[str]) -> None:
    """Print each warning on stderr, flushed (a supervisor may be reading)."""
    for line in warnings:
        complain(line)


@contextlib.asynccontextmanager
async def _checked(check: Any) -> Any:
    """Await ``check`` on entering (a step of an ``async with`` chain)."""
    await check
    yield


async def run_console(
    config: PlatformConfig,
    source: str,
    host: str,
    port: int,
    say: Callable[[str], None],
    *,
    token: str | None = None,
    allow_hosts: Sequence[str] = (),
) -> None:
    """Run one platform with the operator web console until SIGINT/SIGTERM.

    The ready line ends with the URL to open, token included (``…/?token=…``). SIGHUP
    reloads ``[sharing]``, as `run_node`.
    """
    from .console import OperatorConsole

    async with (
        _platform(config, source) as (p, application, channel),
        OperatorConsole(p, host=host, port=port, token=token, allow_hosts=allow_hosts) as console,
    ):
        _warn(unprovided(p, source))
        await p.join()
        stop = _stop_event()
        losses = _Losses(p, stop, "console")
        async with _reloading_on_hup(p, source, say, "console"):
            losses.started()
            say(
                f"dyknow console: {p.name} ready in federation {config.federation}: "
                f"{console.login_url}"
            )
            settle_gc()
            await stop.wait()
        _say_stats("console", application, say)
        say(
            f"dyknow console: local channel: {channel.served} commands served, "
            f"{channel.refused} refused"
        )
        _say_lost("console", p, say)
    say(f"dyknow console: {config.name} stopped")
    if losses.lost:
        raise _lost_error(config.name, losses.lost)


async def run_foxglove(
    config: PlatformConfig,
    source: str,
    host: str,
    port: int,
    say: Callable[[str], None],
    *,
    sample_period: float | None = None,
    token: str | None = None,
    allow_hosts: Sequence[str] = (),
) -> None:
    """Run one platform serving Foxglove (docs/foxglove.md) until SIGINT/SIGTERM.

    The ready line ends with the WebSocket URL to open in Foxglove, token included
    (``…/?token=…``); the connections relayed and refused are said at the end. SIGHUP
    reloads ``[sharing]``, as `run_node`.
    """
    from ._foxglove import FoxgloveBridge

    async with (
        _platform(config, source) as (p, application, _),
        FoxgloveBridge(
            p,
            host=host,
            port=port,
            sample_period=sample_period,
            token=token,
            allow_hosts=allow_hosts,
        ) as bridge,
    ):
        _warn(unprovided(p, source))
        await p.join()
        stop = _stop_event()
        losses = _Losses(p, stop, "foxglove")
        async with _reloading_on_hup(p, source, say, "foxglove"):
            losses.started()
            say(f"dyknow foxglove: serving {', '.join(bridge.served()) or 'no streams'}")
            if bridge.origin is None:
                say("dyknow foxglove: no [foxglove] origin: positions are not drawn on a map")
            say(
                f"dyknow foxglove: {p.name} ready in federation {config.federation}: "
                f"{bridge.login_url}"
            )
            settle_gc()
            await stop.wait()
        _say_stats("foxglove", application, say)
        say(_foxglove_closing(bridge.stats()))
        _say_lost("foxglove", p, say)
    say(f"dyknow foxglove: {config.name} stopped")
    if losses.lost:
        raise _lost_error(config.name, losses.lost)


def _foxglove_closing(stats: dict[str, Any]) -> str:
    """The bridge's count at its close: connections relayed and refused, samples not drawn."""
    refused = ", ".join(f"{kind} {n}" for kind, n in stats["refused"].items())
    return (
        f"dyknow foxglove: connections: {stats['relayed']} relayed, "
        f"{stats['refused_total']} refused ({refused}), {stats['declined']} declined; "
        f"{stats['bad_values_total']} bad values not drawn"
    )


async def run_router(listen: list[str], json5: str | None, say: Callable[[str], None]) -> None:
    """A zenoh session in router mode until SIGINT/SIGTERM."""
    import zenoh

    cfg = ZenohConfig(mode="router", listen=tuple(listen) or None, json5=json5).to_zenoh()
    session = await asyncio.to_thread(zenoh.open, cfg)
    stop = _stop_event()
    try:
        say(f"dyknow router: zid {session.info.zid()} listening on {_endpoints(cfg)}")
        await stop.wait()
    finally:
        await asyncio.to_thread(session.close)
    say("dyknow router: stopped")


def _endpoints(cfg: Any) -> str:
    """The listen endpoints a zenoh config gives the router (the flags' or the file's)."""
    try:
        endpoints = json.loads(cfg.get_json("listen/endpoints"))
    except Exception:
        return "(see the config)"
    if isinstance(endpoints, dict):
        endpoints = endpoints.get("router", [])
    return ", ".join(map(str, endpoints)) or "(nothing)"


@contextlib.asynccontextmanager
async def _opened(path: str) -> AsyncIterator[FederationPlatform]:
    """A platform from a config file, kept out of the federation (an asking console).

    Refused (PlatformAliveError) when a platform of that name is alive elsewhere: acting
    as it would break its sessions. On its own host the commands go through it instead.
    """
    from ._local import refuse_duplicate

    config = PlatformConfig.load(path)
    transport = config.make_transport()
    async with transport:
        await refuse_duplicate(transport, config, command=True)
        async with FederationPlatform(
            config, source=path, join=False, transport=transport
        ) as platform:
            yield platform


@contextlib.asynccontextmanager
async def _exported(
    p: FederationPlatform,
    platform: str,
    semantic_labels: list[str],
    *,
    sample_period: float | None,
    wait: float,
    timeout: float,
) -> AsyncIterator[None]:
    """Create-stream ``semantic_labels`` from ``platform`` to ``p``, cancelled after the block."""
    fed = p.federation_agent
    async with reaching(p, platform, wait):
        export_id = await fed.create_stream(
            platform, semantic_labels, sample_period=sample_period, timeout=timeout
        )
    try:
        yield
    finally:
        try:
            await fed.cancel_stream(platform, export_id, timeout=2.0)
        except Exception as exc:  # the export ends with its lease there anyway
            # the member's word on why: bounded, one line
            log.info("cancelling the export %s at %s: %s", export_id, platform, quoted(exc))


async def _through_node(config_path: str, request: dict[str, Any]) -> tuple[bool, Any]:
    """``(True, result)`` from the running node of this config, or ``(False, None)`` if none.

    The one-shot commands go through a running node of their config (docs/application.md,
    "One platform, one process"): its sessions stay its own.
    """
    from ._local import NodeUnreachable, via_node

    try:
        async for line in via_node(PlatformConfig.load(config_path), request):
            if "error" in line:
                raise RelayedError(line["error"])
            if "ok" in line:
                return True, line["ok"]
    except NodeUnreachable:
        return False, None
    raise RelayedError("the running node closed the local channel without an answer")


async def list_platforms(config_path: str, wait: float) -> dict[str, list[dict[str, Any]]]:
    """As the config's platform: ``{platform: [service, …]}`` of those alive."""
    done, found = await _through_node(config_path, {"op": "platforms", "wait": wait})
    if done:
        return dict(found)
    async with _opened(config_path) as p:
        await wait_for_members(p, None, wait)
        return platforms_of(p)


async def ask_platform(
    config_path: str, platform: str, content: dict[str, Any], wait: float, timeout: float
) -> Any:
    """Send one federation request to ``platform``; the inform's content."""
    request = {
        "op": "request",
        "platform": platform,
        "content": content,
        "wait": wait,
        "timeout": timeout,
    }
    done, answer = await _through_node(config_path, request)
    if done:
        return answer
    async with _opened(config_path) as p, reaching(p, platform, wait):
        return await p.federation_agent.request_from(platform, content, timeout=timeout)


async def stream_through_node(
    config_path: str,
    platform: str,
    semantic_labels: list[str],
    *,
    sample_period: float | None,
    count: int | None,
    wait: float,
    timeout: float,
    emit: Callable[[str, Any, int, int], None],
    stop: asyncio.Event,
) -> int | None:
    """Samples relayed by the running node of this config; None when none runs."""
    from ._local import NodeUnreachable, via_node

    request = {
        "op": "stream",
        "platform": platform,
        "labels": semantic_labels,
        "sample_period": sample_period,
        "count": count,
        "wait": wait,
        "timeout": timeout,
    }
    seen = 0
    lines = via_node(PlatformConfig.load(config_path), request)

    async def next_line() -> dict[str, Any]:
        return await anext(lines)

    loop = asyncio.get_running_loop()
    stopping = loop.create_task(stop.wait(), name="stream.stop")
    nxt: asyncio.Task[dict[str, Any]] | None = None
    try:
        while True:
            nxt = loop.create_task(next_line(), name="stream.next")
            done, _ = await asyncio.wait([nxt, stopping], return_when=asyncio.FIRST_COMPLETED)
            if nxt not in done:
                return seen
            try:
                line = nxt.result()
            except StopAsyncIteration:
                return seen
            except NodeUnreachable:
                return None
            if "error" in line:
                raise RelayedError(line["error"])
            if "end" in line:
                return seen
            label, value, valid, available = line["sample"]
            emit(label, value, valid, available)
            seen += 1
    finally:
        # both waits end here, whatever ended the loop; a read cut short must have ended
        # before the generator can be closed (it cannot be while it still runs)
        waits = [stopping] if nxt is None else [stopping, nxt]
        for w in waits:
            w.cancel()
        await asyncio.wait(waits)
        if nxt is not None and not nxt.cancelled():
            nxt.exception()  # retrieved: what a read cut short raised is no failure
        await lines.aclose()


def own_without_node(config_path: str, platform: str, command: str) -> None:
    """NotAnsweredError when ``platform`` is the config's own and no node of it runs here.

    A platform's streams are made by its running node, and a platform exports to others
    only: the command follows them through that node's local channel, or not at all.
    """
    config = PlatformConfig.load(config_path)
    if platform != config.name:
        return
    raise NotAnsweredError(
        f"platform {platform!r} is this config's own: its streams are made by its running "
        f"node, and no node of {config_path} runs on this host. Start it (dyknow node "
        f"--config {config_path}) and run this command again: 'dyknow {command}' then "
        "follows the streams from the node itself. Or run the command with the config of "
        "another platform of the federation"
    )


def read_json5(path: str | None) -> str | None:
    """The text of a JSON5 zenoh config file (or None)."""
    return None if path is None else Path(path).read_text(encoding="utf-8")


def dumps(value: Any) -> str:
    """JSON for the ``--json`` outputs."""
    return json.dumps(value, indent=2, sort_keys=True, default=str)


async def follow_stream(
    config_path: str,
    platform: str,
    semantic_labels: list[str],
    *,
    sample_period: float | None,
    count: int | None,
    wait: float,
    timeout: float,
    emit: Callable[[str, Any, int, int], None],
) -> int:
    """Create-stream from ``platform`` to us and emit its samples until SIGINT or ``count``."""
    stop = _stop_event()
    relayed = await stream_through_node(
        config_path,
        platform,
        semantic_labels,
        sample_period=sample_period,
        count=count,
        wait=wait,
        timeout=timeout,
        emit=emit,
        stop=stop,
    )
    if relayed is not None:
        return relayed
    own_without_node(config_path, platform, "stream")
    async with (
        _opened(config_path) as p,
        _exported(
            p, platform, semantic_labels, sample_period=sample_period, wait=wait, timeout=timeout
        ),
    ):
        queue: asyncio.Queue[tuple[str, Any, int, int]] = asyncio.Queue()

        async def pump(semantic: str) -> None:
            try:
                label = await p.imported(platform, semantic, timeout=timeout)
            except TimeoutError as exc:  # an answer not given, said in words (exit 1)
                raise NotAnsweredError(str(exc)) from None
            sub = p.instance.subscribe(label)
            try:
                async for s in sub:
                    await queue.put((semantic, s.value, s.valid_time, s.available_time))
            finally:
                sub.close()

        seen = 0
        error: Exception | None = None
        async with asyncio.TaskGroup() as tg:
            pumps = [
                tg.create_task(failure_of(pump, s), name=f"stream[{s}]") for s in semantic_labels
            ]
            stopping = tg.create_task(stop.wait(), name="stream.stop")
            try:
                while count is None or seen < count:
                    getting = tg.create_task(queue.get(), name="stream.next")
                    done, _ = await asyncio.wait(
                        [getting, stopping, *pumps], return_when=asyncio.FIRST_COMPLETED
                    )
                    if getting not in done:
                        getting.cancel()
                        failed = [t.result() for t in pumps if t in done]
                        error = next((e for e in failed if e is not None), None)
                        break
                    emit(*getting.result())
                    seen += 1
            except Exception as exc:  # raised below: the group would wrap it
                error = exc
            finally:
                for t in (stopping, *pumps):
                    t.cancel()
        if error is not None:
            raise error
        return seen


# -- the owner's watch ---------------------------------------------------------------------------

WatchEvent = dict[str, Any]


def watcher_transport(config: PlatformConfig) -> Transport:
    """A transport for the platform's owner next to the running platform, not as it.

    It takes no part in the federation (no presence, no key exchange, no DF): it only
    subscribes and asks. Over zenoh it listens nowhere (the platform holds its ports) and
    connects to the platform's own endpoints as well as its peers or router, with the
    same TLS and password; over MQTT it gets a client id of its own (the platform's would
    evict the running platform from the broker).
    """
    t = config.transport
    if isinstance(t, ZenohConfig):
        local = tuple(_reachable(e) for e in (t.listen or ()))
        connect = tuple(dict.fromkeys((*t.connect, *local)))
        mode = "client" if t.mode == "client" else "peer"
        return ZenohTransport(t.model_copy(update={"listen": (), "connect": connect, "mode": mode}))
    assert isinstance(t, MqttConfig)
    from agents.transports import MqttTransport  # only a platform on MQTT imports it

    return MqttTransport(
        t.model_copy(update={"client_id": f"dyknow-watch-{uuid.uuid4().hex[:12]}"})
    )


def _reachable(endpoint: str) -> str:
    """A listen endpoint as something to connect to on this host (0.0.0.0 is not)."""
    return endpoint.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:")


def _watched_entry(entry: Any) -> tuple[str, str, float, bytes]:
    """One ``[kind, from, ts, body]`` entry of a watch batch; ValueError if it is not one."""
    if not isinstance(entry, list | tuple) or len(entry) != 4:
        raise ValueError("a watch entry is [kind, from, ts, body]")
    kind, peer, ts, body = entry
    if (
        kind not in ("acl", "bin")
        or not isinstance(peer, str)
        or isinstance(ts, bool)
        or not isinstance(ts, int | float)
        or not isinstance(body, bytes)
    ):
        raise ValueError("a watch entry is [kind, from, ts, body]")
    return kind, peer, ts, body


def decode_watched(kind: str, peer: str, ts: float, body: bytes) -> WatchEvent:
    """One opened envelope the platform showed its owner, as an event."""
    if kind == "acl":
        try:
            message: Any = json.loads(body)
        except (ValueError, RecursionError):  # what opened need not be JSON, nor shallow
            message = body.decode(errors="replace")
        return {"kind": "acl", "from": peer, "ts": ts, "message": message}
    try:
        obj = msgpack.unpackb(body, raw=False)
    except Exception as exc:  # what opened need not be a batch a peer should send
        return {"kind": "binary", "from": peer, "ts": ts, "error": str(exc), "bytes": len(body)}
    if isinstance(obj, dict) and "lost" in obj:
        return {"kind": "stream-report", "from": peer, "ts": ts, "report": obj}
    return {"kind": "stream", "from": peer, "ts": ts, "batch": obj}


async def watch_platform(
    config_path: str,
    emit: Callable[[WatchEvent], None],
    *,
    duration: float | None = None,
    renew: float = 3.0,
    timeout: float = 10.0,
) -> int:
    """As the platform's owner: show, opened, what reaches the running platform.

    Asks the platform (a request signed with its key, renewed every ``renew`` s) to show
    its owner every ACL message, sample batch and stream report it opens; those come
    signed by the platform and sealed to the owner's key, as does the audit, which is
    shown too; a batch whose signature does not verify, seen before, or signed before the
    watch began on the platform's clock (`_WatchAnchor`) is shown as unreadable, counted.
    Runs until SIGINT or ``duration`` s; how many events were emitted. TransportError when
    the platform does not answer within ``timeout`` s, or a renewal still cannot be sent
    ``timeout`` s after its last answer; `WatchLostError` when the transport
    ends the watch's subscription or the audit's (MQTT: a filter the broker refuses after
    a reconnection, a connection lost and not made again), each logged at ERROR first: a
    watch that saw nothing more must not look like a quiet platform.
    """
    config = PlatformConfig.load(config_path)
    try:
        keys = KeyPair.load(config.key)
    except (OSError, ValueError, SecurityError) as exc:
        raise PlatformConfigError(config_path, "key", str(exc)) from None
    fed, me = config.federation, config.name
    try:
        # the key members trust as the platform's; a trust file without it leaves the
        # owner's own public key, which its private key vouches for
        public = TrustStore.load(config.trust).public_key(me)
    except UnknownPlatform:
        public = keys.public_key
    except (OSError, ValueError, SecurityError) as exc:
        raise PlatformConfigError(config_path, "trust", str(exc)) from None
    batches = OwnerBatches(keys, public)
    anchored = asyncio.Event()  # batches are read once the platform said when they may begin
    stop = _stop_event()
    queue: asyncio.Queue[WatchEvent] = asyncio.Queue()
    unreadable = 0

    async def refuse(key: str, error: str) -> None:
        # Anyone can seal to the owner's public key: a batch not signed by the platform
        # (or replayed, or that does not decode) is shown as unreadable and counted,
        # never as the platform's, and never ends the watch.
        nonlocal unreadable
        unreadable += 1
        await queue.put({"kind": "unreadable", "key": key, "error": error, "count": unreadable})

    async with watcher_transport(config) as transport:
        anchor = _WatchAnchor(batches, time.monotonic(), SecurityPolicy().skew)
        watch_key, audit_key = wire_key(fed, "watch", me), wire_key(fed, "audit", me)
        watched = await transport.subscribe(watch_key)
        audit = await transport.subscribe(audit_key)
        # what each subscription's end means for the owner
        watching_through = {
            f"watch subscription {watch_key}": (
                watched,
                "the messages, batches and reports the platform opens are no longer shown",
            ),
            f"audit subscription {audit_key}": (
                audit,
                "the platform's audit records are no longer shown",
            ),
        }

        said: set[str] = set()  # the subscriptions whose end was logged

        def transport_ended() -> WatchLostError:
            # every one it ended by now: a lost connection ends both at once
            lost = [
                (what, meaning)
                for what, (sub, meaning) in watching_through.items()
                if sub.inbox.closed and not sub.closed
            ]
            for what, meaning in lost:
                if what in said:  # each pump raises: each end is said once
                    continue
                said.add(what)
                log.error(
                    "watch[%s]: lost its %s (the transport ended the subscription): %s",
                    me,
                    what,
                    meaning,
                )
            return WatchLostError(
                f"the watch of platform {me!r} stopped: the transport ended its "
                f"{', its '.join(what for what, _ in lost)} (the transport ended the "
                "subscription). Run again, it subscribes anew"
            )

        async def pump_watch() -> None:
            await anchored.wait()
            async for item in watched:
                try:
                    entries = msgpack.unpackb(batches.open(item.key, item.payload), raw=False)
                    events = [decode_watched(*_watched_entry(e)) for e in entries]
                except (AuthenticationError, ValueError, TypeError) as exc:
                    await refuse(item.key, str(exc))
                    continue
                for event in events:
                    await queue.put(event)
            if not watched.closed:  # ended by the transport, not by this watch's end
                raise transport_ended()

        plain = config.security.audit == "plain"

        async def pump_audit() -> None:
            await anchored.wait()
            async for item in audit:
                try:
                    try:
                        data = batches.open(item.key, item.payload)
                    except AuthenticationError:
                        if not plain:  # this platform seals its audit: a plain one is not its own
                            raise
                        # [security] audit = "plain": signed, not sealed
                        data = batches.open(item.key, item.payload, sealed=False)
                    records = [json.loads(line) for line in data.splitlines()]
                    if not all(isinstance(r, dict) for r in records):
                        raise ValueError("an audit record is a JSON object")
                except (AuthenticationError, ValueError, RecursionError) as exc:
                    await refuse(item.key, str(exc))
                    continue
                for record in records:
                    await queue.put({"kind": "audit", "record": record})
            if not audit.closed:  # ended by the transport, not by this watch's end
                raise transport_ended()

        def unanswered(waited: float) -> TransportError:
            return TransportError(
                f"platform {me!r} did not answer the watch request in {waited:g} s "
                "(is it running, reachable, with [security] watch = true?)"
            )

        async def lease() -> None:
            deadline = time.monotonic() + timeout
            answered = unrenewed = False
            renewed = 0.0  # when the platform last answered
            while True:
                # the first signed answer ends the query: a queryable that never answers
                # (anyone may declare one) would hold each renewal to its timeout
                ok = False
                signed_at: float | None = None
                request = watch_request(keys, fed)
                asked = time.monotonic()
                try:
                    replies = await transport.ask(watch_key, request, timeout=_WATCH_ASK)
                except TransportError as exc:
                    if not answered or isinstance(exc, TransportClosed):
                        raise
                    waited = time.monotonic() - renewed
                    if waited > timeout:
                        # not a reconnection (it ends, made again or not, within its
                        # connect timeout): a broker that takes the renewal and never
                        # acknowledges it, the platform's lease long run out
                        raise TransportError(
                            f"platform {me!r}: the watch was not renewed in {timeout:g} s "
                            f"(the last time: {exc})"
                        ) from exc
                    # a renewal while the transport reconnects (MQTT): the lease holds
                    # until the next one; a connection not made again ends the
                    # subscriptions, which says so. Said once until one is renewed
                    (log.debug if unrenewed else log.warning)(
                        "watch[%s]: the watch not renewed (asked again every %g s): %s",
                        me,
                        renew,
                        exc,
                    )
                    unrenewed = True
                    await asyncio.sleep(renew)
                    continue
                async with replies:
                    async for reply in replies:
                        if not reply.ok:
                            continue
                        try:
                            signed_at = watch_time(public, fed, request, reply.payload)
                        except AuthenticationError as exc:
                            # anyone may answer: not the platform's, shown and counted
                            await refuse(reply.key, f"watch answer refused: {exc}")
                            continue
                        ok = True
                        if signed_at is not None:
                            break
                        # bare (an older release, or anyone answering first): a signed one
                        # may still come; the query ends when every queryable answered
                if ok:
                    unrenewed = False
                    renewed = time.monotonic()
                    was_signed = anchor.signed
                    anchor.answered(signed_at, asked, time.monotonic())
                    anchored.set()
                    if not answered or anchor.signed != was_signed:
                        # a bare answer bounds batches by this side's clock, looser by the
                        # clock allowance: the owner is told, and told when it tightens
                        await queue.put(
                            {"kind": "watching", "platform": me, "signed": anchor.signed}
                            | ({} if anchor.signed else {"allowance_s": anchor.skew})
                        )
                    answered = True
                elif not answered and time.monotonic() > deadline:
                    raise unanswered(timeout)
                await asyncio.sleep(renew if answered else 0.5)

        seen = 0
        watching = False
        error: Exception | None = None
        try:
            async with asyncio.TaskGroup() as tg:
                jobs = [
                    tg.create_task(failure_of(t), name=f"watch.{t.__name__}")
                    for t in (pump_watch, pump_audit, lease)
                ]
                stopping = tg.create_task(stop.wait(), name="watch.stop")
                ending = tg.create_task(
                    asyncio.sleep(duration if duration is not None else 1e9), name="watch.end"
                )
                try:
                    while True:
                        getting = tg.create_task(queue.get(), name="watch.next")
                        done, _ = await asyncio.wait(
                            [getting, stopping, ending, *jobs], return_when=asyncio.FIRST_COMPLETED
                        )
                        if getting not in done:
                            getting.cancel()
                            failed = [t.result() for t in jobs if t in done]
                            error = next((e for e in failed if e is not None), None)
                            if error is None and ending in done and not watching:
                                # --duration ran out before the platform ever answered:
                                # printing nothing and exiting 0 would look like a quiet one
                                error = unanswered(duration or 0.0)
                            if isinstance(error, WatchLostError):
                                # what came before the end is shown, then the end
                                while not queue.empty():
                                    emit(queue.get_nowait())
                                    seen += 1
                            break
                        event = getting.result()
                        watching = watching or event["kind"] == "watching"
                        emit(event)
                        seen += 1
                except Exception as exc:  # raised below: the group would wrap it
                    error = exc
                finally:
                    for t in (stopping, ending, *jobs):
                        t.cancel()
            if error is not None:
                raise error
        finally:
            watched.close()
            audit.close()
    return seen
