"""The door of a `FoxgloveBridge`: a WebSocket relay that lets in only who may watch.

The foxglove-sdk's server has no login and no ``Origin`` check. It listens on an
ephemeral port of 127.0.0.1 (`FoxgloveRelay.inner_url`); clients connect to this relay,
which accepts a WebSocket upgrade only past a `ConsoleAccess` (``stage: "foxglove"``):
an allowed ``Host``, an ``Origin`` absent or allowed, the token in ``?token=`` or a
Bearer. A refusal is an HTTP answer before any upgrade, counted and audited as the
console's. Then it opens a connection of its own to the SDK's server, offering the
subprotocols the client offered that the SDK speaks, answers the client with the one the
SDK chose, and copies every frame both ways as it is (binary and text, never parsed).

Buffers are bounded: a frame is read only when the previous one was written (aiohttp's
reader pauses the socket past 64 KiB, its writer waits for the peer to drain), so a slow
client slows its inner connection, whose backlog the SDK bounds (it drops the oldest
messages). A message larger than `MAX_MESSAGE` from the server, or `MAX_CLIENT_MESSAGE`
from a client (a client only subscribes), ends the connection.

What a client makes the SDK log (``foxglove.websocket.connected_client`` and the loggers
below it, ``….poller`` and ``….send_lossy``: one line per unknown channel of a
subscribe, so one 1 MiB message could write ~20 000; one per connection closed, per
outbox found full), and its server's (``foxglove.websocket.server``: a "Registered
client" and an "Unregistered client" line per connection, so a client reconnecting in a
loop writes two lines a turn), are each held to one line per `SDK_LOG_INTERVAL` while a
relay runs; the next line let through says how many were held back (`SdkLogThrottle`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from typing import Any

import aiohttp
from aiohttp import WSMsgType, web

from .console import IDLE_TIMEOUT, MAX_CLIENTS_PER_ADDRESS, ConsoleAccess, serve

__all__ = ["MAX_CONNECTIONS", "SDK_LOG_INTERVAL", "SUBPROTOCOLS", "FoxgloveRelay", "SdkLogThrottle"]

log = logging.getLogger("federation.foxglove")

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
"""The Foxglove WebSocket protocol's versions passed on to the SDK's server, which
chooses (foxglove-sdk 0.30 speaks ``foxglove.sdk.v1`` only)."""
MAX_CONNECTIONS = 32  # clients relayed at once: past it, 503
MAX_MESSAGE = 64 * 1024 * 1024  # bytes of one message of the server (a big sample's)
MAX_CLIENT_MESSAGE = 1024 * 1024  # bytes of one message of a client (subscriptions)
CONNECT_TIMEOUT = 5.0  # s: to open the inner connection (and to close one)
HEARTBEAT = 30.0  # s: a client that answers no ping in this time is gone
_SENDABLE = frozenset({1000, 1001, 1003, 1007, 1008, 1009, 1010, 1011})  # close codes


SDK_LOG_INTERVAL = 1.0  # s: at most one line of what clients make the SDK log, per interval
# The SDK's logger per client; its modules log below it (``.poller``, ``.send_lossy``).
_SDK_CLIENT_LOGGER = "foxglove.websocket.connected_client"
# The SDK server's logger: a line per connection registered and per one unregistered.
_SDK_SERVER_LOGGER = "foxglove.websocket.server"


class SdkLogThrottle(logging.Filter):
    """Lets one record through per ``interval``; the next one let through counts the rest.

    Installed on one of the SDK's loggers (``logger``, the per-client one by default) and
    those below it while a relay runs (`installed`): a token holder's messages, or its
    connections, must not flood the log. Thread-safe (the SDK logs from its threads).
    """

    def __init__(
        self, interval: float = SDK_LOG_INTERVAL, logger: str = _SDK_CLIENT_LOGGER
    ) -> None:
        super().__init__()
        self.interval = interval
        self.logger = logger  # the name of the logger whose subtree it holds
        self.held = 0  # records held back since the last one let through
        self._next = 0.0
        self._lock = threading.Lock()
        self._users = 0
        self._gate: _Gate | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        """True for the first record of an interval (saying how many were held before it)."""
        now = time.monotonic()
        with self._lock:
            if now < self._next:
                self.held += 1
                return False
            self._next = now + self.interval
            held, self.held = self.held, 0
        if held:
            record.msg = f"{record.getMessage()} (and {held} more lines held back before it)"
            record.args = ()
        return True

    @contextlib.contextmanager
    def installed(self) -> Any:
        """On ``self.logger`` and those below it while in the block (shared by relays at once).

        A logger's filter sees only what is logged on that logger, not what its children
        propagate to it: the SDK logs below its per-client logger too. So the whole
        subtree goes through one handler there, filtered, which passes what it lets
        through on up the tree, as propagation would have.
        """
        logger = logging.getLogger(self.logger)
        with self._lock:
            self._users += 1
            if self._users == 1:
                gate = self._gate = _Gate(logger, self)
                logger.addHandler(gate)
                logger.propagate = False
        try:
            yield self
        finally:
            with self._lock:
                self._users -= 1
                last = self._users == 0
                ending = self._gate
                if last and ending is not None:
                    logger.removeHandler(ending)
                    logger.propagate = ending.propagate
                    self._gate = None
                held, self.held = (self.held, 0) if last else (0, self.held)
            if held:  # the end of a flood no later line reported
                log.warning(
                    "foxglove: %d more lines of %s (and below) were held back", held, logger.name
                )


class _Gate(logging.Handler):
    """The throttle's handler on the SDK's per-client logger: what it lets through goes up."""

    def __init__(self, logger: logging.Logger, throttle: SdkLogThrottle) -> None:
        super().__init__()
        self._logger = logger
        self.propagate = logger.propagate  # as it was: restored when the last relay ends
        self.addFilter(throttle)

    def emit(self, record: logging.LogRecord) -> None:
        """Hand ``record`` to the handlers above, as propagation would have."""
        above = self._logger.parent  # read now: a logger made later may sit in between
        if self.propagate and above is not None:
            above.callHandlers(record)


_SDK_LOG = SdkLogThrottle()
_SDK_SERVER_LOG = SdkLogThrottle(logger=_SDK_SERVER_LOGGER)  # a budget of its own


def _json_error(status: int, reason: str, **headers: str) -> web.Response:
    return web.json_response({"error": reason}, status=status, headers=headers)


def _offered(request: web.Request) -> list[str]:
    """The subprotocols a client's upgrade offers, in its order."""
    header = ",".join(request.headers.getall("Sec-WebSocket-Protocol", []))
    return [p.strip() for p in header.split(",") if p.strip()]


def _close_code(code: int | None) -> int:
    """A close code to pass on (1005, 1006 and the like are no code one may send)."""
    if code is not None and (code in _SENDABLE or 3000 <= code <= 4999):
        return code
    return 1001  # going away: the other side ended without saying why


class FoxgloveRelay:
    """Serves ``host``:``port``, relaying who passes ``access`` to the SDK's ``inner_url``.

    An async context manager; `port` is the one bound (0: a free one) once entered.
    """

    def __init__(
        self,
        access: ConsoleAccess,
        inner_url: str,
        *,
        host: str,
        port: int,
        idle_timeout: float = IDLE_TIMEOUT,
        max_per_address: int = MAX_CLIENTS_PER_ADDRESS,
    ) -> None:
        self.access = access
        self.max_per_address = max_per_address  # connections one client address may hold
        self.idle_timeout = idle_timeout  # s a connection has to send a whole request
        self.inner_url = inner_url
        self.host = host
        self.port = port
        self.relayed = 0  # connections relayed so far
        self.declined = 0  # upgrades of token holders not relayed (see `_upgrade`)
        self._open: set[web.WebSocketResponse] = set()
        self._taken = 0  # clients opening (the inner connection under way) or open
        self._stack: contextlib.AsyncExitStack | None = None
        self._session: aiohttp.ClientSession | None = None

    def stats(self) -> dict[str, Any]:
        """The connections relayed, open and declined, and the access's refusals."""
        return {
            "relayed": self.relayed,
            "open": len(self._open),
            "declined": self.declined,
            **self.access.stats(),
        }

    async def __aenter__(self) -> FoxgloveRelay:
        stack = self._stack = contextlib.AsyncExitStack()
        try:
            stack.enter_context(_SDK_LOG.installed())  # until the last client is gone
            stack.enter_context(_SDK_SERVER_LOG.installed())
            timeout = aiohttp.ClientTimeout(total=CONNECT_TIMEOUT)  # the inner upgrade
            self._session = await stack.enter_async_context(aiohttp.ClientSession(timeout=timeout))
            app = web.Application()
            app.router.add_get("/{tail:.*}", self._upgrade)
            self.port = await serve(
                app,
                self.host,
                self.port,
                stack,
                self.access,
                max_per_address=self.max_per_address,
                idle_timeout=self.idle_timeout,
            )
            stack.push_async_callback(self._close_all)  # before the runner's cleanup
        except BaseException:
            await stack.aclose()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Close every relayed connection (going away) and stop listening."""
        stack, self._stack = self._stack, None
        if stack is not None:
            await stack.aclose()

    async def _close_all(self) -> None:
        for ws in list(self._open):
            with contextlib.suppress(Exception):
                await ws.close(code=1001, message=b"server stopping")

    async def _upgrade(self, request: web.Request) -> web.StreamResponse:
        """Refuse, or open the inner connection and relay until either side closes."""
        refused = self.access.check_upgrade(request)
        if refused is not None:
            return refused
        # Past the token: what follows is no attack, only counted and logged.
        wanted = [p for p in _offered(request) if p in SUBPROTOCOLS]
        if not web.WebSocketResponse(protocols=wanted).can_prepare(request).ok:
            self.declined += 1
            return _json_error(
                426, "a Foxglove WebSocket connection is served here", Upgrade="websocket"
            )
        if not wanted:
            self.declined += 1
            return _json_error(400, f"offer a subprotocol of {', '.join(SUBPROTOCOLS)}")
        if self._taken >= MAX_CONNECTIONS:
            self.declined += 1
            log.warning("foxglove: %d clients; declined %s", self._taken, request.remote)
            return _json_error(503, f"{MAX_CONNECTIONS} clients are watching already")
        # taken before the first wait: upgrades at once must not all pass the check above
        self._taken += 1
        try:
            return await self._connect(request, wanted)
        finally:
            self._taken -= 1

    async def _connect(self, request: web.Request, wanted: list[str]) -> web.StreamResponse:
        """Open the inner connection, answer the upgrade, relay until either side closes."""
        assert self._session is not None
        try:
            inner = await self._session.ws_connect(
                self.inner_url,
                protocols=wanted,
                max_msg_size=MAX_MESSAGE,
                decode_text=False,
                timeout=aiohttp.ClientWSTimeout(ws_receive=None, ws_close=CONNECT_TIMEOUT),
            )
        except aiohttp.WSServerHandshakeError as exc:
            self.declined += 1
            log.warning("foxglove: the server refused %s (%s)", wanted, exc.status)
            return _json_error(400, f"the server speaks none of {', '.join(wanted)}")
        except (aiohttp.ClientError, OSError, TimeoutError) as exc:
            self.declined += 1
            log.error("foxglove: the server is unreachable: %s", exc)
            return _json_error(502, "the Foxglove server is unreachable")
        async with inner:
            ws = web.WebSocketResponse(
                protocols=[inner.protocol] if inner.protocol else [],
                compress=False,  # on loopback, compressing costs more than it saves
                max_msg_size=MAX_CLIENT_MESSAGE,
                heartbeat=HEARTBEAT,
                decode_text=False,
            )
            await ws.prepare(request)
            self.relayed += 1
            self._open.add(ws)
            try:
                await self._relay(ws, inner)
            finally:
                self._open.discard(ws)
        return ws

    async def _relay(
        self, ws: web.WebSocketResponse, inner: aiohttp.ClientWebSocketResponse[Any]
    ) -> None:
        """Copy frames both ways until one side closes; then close the other alike."""
        loop = asyncio.get_running_loop()
        up = loop.create_task(_pump(ws, inner), name="foxglove.relay.up")
        down = loop.create_task(_pump(inner, ws), name="foxglove.relay.down")
        try:
            done, _ = await asyncio.wait((up, down), return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (up, down):
                task.cancel()
            await asyncio.gather(up, down, return_exceptions=True)
        with contextlib.suppress(Exception):
            if up in done:  # the client closed (or went): the server's side too
                await inner.close(code=_close_code(ws.close_code))
            else:
                await ws.close(code=_close_code(inner.close_code))
        with contextlib.suppress(Exception):
            await inner.close()
            await ws.close()


async def _pump(
    src: web.WebSocketResponse | aiohttp.ClientWebSocketResponse[Any],
    dst: web.WebSocketResponse | aiohttp.ClientWebSocketResponse[Any],
) -> None:
    """Send every data frame of ``src`` to ``dst`` as it came, until ``src`` ends."""
    with contextlib.suppress(ConnectionError, aiohttp.ClientError):
        async for msg in src:  # ends on a close; pings are answered by aiohttp
            if msg.type in (WSMsgType.BINARY, WSMsgType.TEXT):
                await dst.send_frame(msg.data, msg.type)
            else:  # an error (a message too big, a broken frame): the end of it
                return
