"""Who may use the operator console: a secret token, an allowed Host, a same-site Origin.

Every HTTP request passes `ConsoleAccess.middleware` before it reaches a handler. In order:

1. ``Host`` must name this console: ``localhost``, any IP address (``127.0.0.1``,
   ``[::1]``, the machine's own), or a name the operator allowed (``--allow-host``,
   ``console.allow_hosts``). A page of ``evil.example`` whose name now resolves to
   127.0.0.1 (DNS rebinding) sends ``Host: evil.example``: refused (403).
2. ``Origin``, when a browser sends one, must be this console's own
   (``http://<Host>``): a page of another site is refused (403), GET or POST.
3. The token, as ``Authorization: Bearer T`` on every request of the API (``/api/…``).
   None: 401; a wrong one: 403. The page (``GET /``) and its files (``/static/…``) are
   the same for everyone and hold nothing of the state: they need no token (a wrong
   ``?token=`` on the page is still refused, 403). The page keeps the token of its URL in
   its own ``sessionStorage`` and sends it as a Bearer. No cookie, ever: a browser sends
   a host's cookies to every port of it, so any server on another port of this machine
   would get it; a cookie is no credential here (a request with only one: 401).

Every refusal is counted (`refusals`, ``GET /api/stats``) and recorded in the platform's
audit (the Interface Agent's `AuditLog`, ``stage: "console"``) and the log, within a
budget: past it, refusals are counted and summed up in one record per `REPORT_INTERVAL`.

Below all that, `serve` bounds what any client costs before it says anything: at most
`MAX_CLIENTS` connections at once (each holds a file descriptor of the node's process;
past it a new one is answered 503 and closed, counted as ``busy``), at most
`MAX_CLIENTS_PER_ADDRESS` of them from one address (an IPv6 client's /64; past it, 503,
counted as ``busy_address``: one address must not take them all), and a connection that
has sent no whole request within `IDLE_TIMEOUT` seconds is closed (slow headers, an idle
keep-alive). A request that is not HTTP (a duplicate ``Host``, a broken header) is
answered 400 by aiohttp and logged in one line, within the budget above, never with a
traceback: anyone can send one.

The same guard stands before another server's WebSocket upgrades (`check_upgrade`: the
Foxglove relay, ``stage: "foxglove"``): the token in ``?token=`` or a Bearer, no cookie,
and an ``Origin`` of its own list (``origins``) besides its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import logging
import os
import re
import secrets
import stat
import time
from collections.abc import Awaitable, Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, cast

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from agents import AuditLog, TokenBucket

__all__ = [
    "ALLOW_HOSTS_ENV",
    "IDLE_TIMEOUT",
    "MAX_CLIENTS",
    "MAX_CLIENTS_PER_ADDRESS",
    "TOKEN_ENV",
    "ConsoleAccess",
    "allowed_names",
    "check_token",
    "configured_token",
    "new_token",
    "serve",
]

log = logging.getLogger("federation.console")

TOKEN_ENV = "DYKNOW_CONSOLE_TOKEN"
"""The environment variable the ``dyknow`` commands read a console token from."""
ALLOW_HOSTS_ENV = "DYKNOW_CONSOLE_ALLOW_HOSTS"
"""The environment variable of more allowed host names, comma-separated (compose)."""

MIN_TOKEN = 16  # characters: shorter ones could be guessed over the network
LOOPBACK_NAMES = frozenset({"localhost"})  # IP addresses are allowed as such (below)
AUDIT_RATE = 2.0  # refusal records per second in the audit and the log, past the burst
AUDIT_BURST = 20.0
REPORT_INTERVAL = 5.0  # s: refusals past the budget are summed up this often
FIELD_MAX = 200  # characters of a header or path kept in a record (they are the client's)
MAX_CLIENTS = 128
"""Connections one server (the console, a Foxglove relay) keeps at once; past it, 503."""
IDLE_TIMEOUT = 15.0
"""Seconds a connection may stay open without a whole request (slow headers, keep-alive)."""
MAX_CLIENTS_PER_ADDRESS = 32
"""Of those, the connections one client address keeps at once; past it, 503."""


def _unavailable(body: bytes) -> bytes:
    return (
        b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
        b"Content-Length: %d\r\nConnection: close\r\n\r\n%s" % (len(body), body)
    )


_BUSY = _unavailable(b'{"error": "too many connections open"}')
_BUSY_ADDRESS = _unavailable(b'{"error": "too many connections open from this address"}')

_TOKEN_CHARS = re.compile(r"[A-Za-z0-9._~-]+")  # unreserved URL characters: no escaping
_HOST_NAME = re.compile(r"[a-z0-9]([a-z0-9-]*[a-z0-9])?(\.[a-z0-9]([a-z0-9-]*[a-z0-9])?)*")

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def new_token() -> str:
    """A fresh random token (192 bits, URL-safe)."""
    return secrets.token_urlsafe(24)


def check_token(token: str, source: str = "token") -> str:
    """``token`` if usable in a URL and long enough, else ValueError naming ``source``."""
    if not isinstance(token, str) or len(token) < MIN_TOKEN:
        raise ValueError(f"{source}: a console token has at least {MIN_TOKEN} characters")
    if not _TOKEN_CHARS.fullmatch(token):
        raise ValueError(f"{source}: a console token uses only letters, digits and . _ ~ -")
    return token


def configured_token(
    token_file: Path | None,
    config_token_file: Path | None = None,
    environ: Mapping[str, str] = os.environ,
) -> str | None:
    """The token the operator chose, or None (then a random one is made).

    First ``--token-file``, then the environment's `TOKEN_ENV` (when not empty), then the
    config's ``console.token_file``. Never a command-line argument: every local user can
    read a process's arguments. A token file that is not a regular file, that another
    user than the one running this (or root) owns, or that group or others may read or
    change, is refused, as ssh refuses such a key. ValueError names where an unusable
    token came from.
    """
    if token_file is None and environ.get(TOKEN_ENV, "").strip():
        return check_token(environ[TOKEN_ENV].strip(), TOKEN_ENV)
    path = token_file if token_file is not None else config_token_file
    if path is None:
        return None
    try:
        # non-blocking: a FIFO put there would block the open until someone writes it
        with open(path, encoding="utf-8", opener=_open_nonblocking) as f:
            st = os.fstat(f.fileno())
            mode = st.st_mode
            if not stat.S_ISREG(mode):
                raise ValueError(f"console token file {path}: is not a regular file")
            # as ssh's StrictModes: its owner could change it (chmod it, write another token),
            # so the owner is told first: for another's file a chmod would not do
            if os.name == "posix" and st.st_uid not in (0, os.geteuid()):
                me = os.geteuid()
                who = _user(me) if me == 0 else f"{_user(me)}, or root"
                raise ValueError(
                    f"console token file {path}: its owner is {_user(st.st_uid)}: only the "
                    f"user running this command, {who}, may own it (chown {_name(me)} {path})"
                )
            # as ssh does for a private key: a token others may read is no secret any more
            if os.name == "posix" and mode & 0o077:
                raise ValueError(
                    f"console token file {path}: its mode {stat.S_IMODE(mode):04o} lets "
                    f"group or others read or change it: keep it yours only (chmod 600 {path})"
                )
            text = f.read().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"console token file {path}: cannot be read: {exc}") from None
    return check_token(text, f"console token file {path}")


def _open_nonblocking(path: str, flags: int) -> int:
    """``os.open`` for ``open(opener=)``, not waiting for a writer (of a FIFO)."""
    return os.open(path, flags | getattr(os, "O_NONBLOCK", 0))


def _name(uid: int) -> str:
    """A user's name, or its uid when it has none on this host."""
    try:
        import pwd

        return pwd.getpwuid(uid).pw_name
    except (ImportError, KeyError):
        return str(uid)


def _user(uid: int) -> str:
    """A user in words: ``name (uid N)``."""
    return f"{_name(uid)} (uid {uid})"


def host_name(host: str) -> str | None:
    """The name in a ``Host`` header (``name``, ``name:port``, ``[v6]:port``), lower case."""
    h = host.strip().lower()
    if h.startswith("["):
        end = h.find("]")
        name, rest = h[1:end], h[end + 1 :]
        if end < 0 or (rest and not re.fullmatch(r":[0-9]{1,5}", rest)):
            return None
        return name
    name, colon, port = h.partition(":")
    if colon and not re.fullmatch(r"[0-9]{1,5}", port):
        return None
    return name.removesuffix(".")


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def _allowed_name(entry: str) -> str:
    """An allow-list entry as a host name, or ValueError (a port or a scheme is not one)."""
    name = entry.strip().lower().removesuffix(".")
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    if not (_is_ip(name) or _HOST_NAME.fullmatch(name)):
        raise ValueError(f"allow_hosts: {entry!r} is not a host name (no scheme, no port)")
    return name


def allowed_names(entries: Iterable[str], environ: Mapping[str, str] | None = None) -> list[str]:
    """The allow-list entries as host names; ValueError names the first that is not one.

    With ``environ``, the names of its `ALLOW_HOSTS_ENV` (comma-separated) are added.
    """
    extra = (environ or {}).get(ALLOW_HOSTS_ENV, "")
    return [_allowed_name(e) for e in [*entries, *extra.split(",")] if e.strip()]


def _public(path: str) -> bool:
    """Whether ``path`` is the page or one of its files: the same for all, no state."""
    return path == "/" or (path.startswith("/static/") and ".." not in path)


def _clip(value: str | None) -> str | None:
    return value if value is None or len(value) <= FIELD_MAX else value[: FIELD_MAX - 1] + "…"


class ConsoleAccess:
    """The console's guard: the token, the allowed host names, the refusals counted.

    ``stage`` names what it guards (in the audit, the log and the reasons); ``origins``
    are web origins allowed besides the server's own (none for the console's page).
    """

    def __init__(
        self,
        *,
        token: str | None = None,
        allow_hosts: Iterable[str] = (),
        audit: AuditLog | None = None,
        origins: Iterable[str] = (),
        stage: str = "console",
    ) -> None:
        self.token = new_token() if token is None else check_token(token)
        self.allow_hosts = frozenset(LOOPBACK_NAMES | {_allowed_name(h) for h in allow_hosts})
        self.audit = audit
        self.origins = frozenset(origins)  # allowed besides the server's own
        self.stage = stage  # what guarded: the audit's stage, the log's prefix
        self._what = stage if stage == "console" else f"{stage} server"  # in the reasons
        self.refusals: dict[str, int] = {"host": 0, "origin": 0, "no-token": 0, "bad-token": 0}
        self.audited = 0  # refusals with a record of their own
        self.busy = 0  # connections closed unserved: `MAX_CLIENTS` were open (`serve`)
        # connections closed unserved: their address had `MAX_CLIENTS_PER_ADDRESS` open
        self.busy_address = 0
        self._budget = TokenBucket(AUDIT_RATE, AUDIT_BURST, time.monotonic())
        self._unaudited = 0  # refusals since the last summary, past the budget

    def allowed_host(self, host: str) -> bool:
        """Whether a ``Host`` header names this console."""
        name = host_name(host)
        return name is not None and (name in self.allow_hosts or _is_ip(name))

    def _token_is(self, given: str) -> bool:
        return hmac.compare_digest(given.encode(), self.token.encode())

    def stats(self) -> dict[str, Any]:
        """What ``GET /api/stats`` answers: the refusals by kind, how many were audited."""
        return {
            "refused": dict(self.refusals),
            "refused_total": sum(self.refusals.values()),
            "audited": self.audited,
            "busy": self.busy,
            "busy_address": self.busy_address,
            "allow_hosts": sorted(self.allow_hosts),
        }

    def _foreign(self, request: web.Request) -> web.Response | None:
        """The refusal of a request of a foreign host or origin, or None."""
        host = request.headers.get("Host", "")
        if not self.allowed_host(host):
            return self._refuse(
                request,
                "host",
                403,
                f"Host: {_clip(host)!r} is not a name of this {self._what} (use 127.0.0.1 or "
                f"localhost, or allow the name: --allow-host / {self.stage}.allow_hosts)",
            )
        origin = request.headers.get("Origin")
        if (
            origin is not None
            and origin != f"{request.scheme}://{host}"
            and origin not in self.origins
        ):
            return self._refuse(
                request, "origin", 403, f"Origin: {_clip(origin)} is not this {self._what}'s"
            )
        return None

    def check_upgrade(self, request: web.Request) -> web.Response | None:
        """The refusal of a WebSocket upgrade, or None: Host, Origin, then the token.

        The token comes in the URL's ``?token=`` (what a browser's WebSocket can send) or
        ``Authorization: Bearer``; no cookie. None: 401; a wrong one: 403.
        """
        refused = self._foreign(request)
        if refused is not None:
            return refused
        given = request.query.get("token")
        auth = request.headers.get("Authorization")
        if given is None and auth is not None:
            scheme, _, value = auth.strip().partition(" ")
            given = value.strip() if scheme.lower() == "bearer" else ""
        if given is None:
            return self._refuse(
                request,
                "no-token",
                401,
                f"token: missing (open the URL the {self._what} printed, with ?token=…, or "
                "send Authorization: Bearer <token>)",
            )
        if not self._token_is(given):
            return self._refuse(request, "bad-token", 403, f"token: not this {self._what}'s")
        return None

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Refuse a request of a foreign host or origin, or without the token; else serve it."""
        refused = self._foreign(request)
        if refused is not None:
            return refused
        if request.method == "GET" and _public(request.path):
            given = request.query.get("token")
            if given is not None and not self._token_is(given):
                return self._refuse(request, "bad-token", 403, "token: not this console's")
            return await handler(request)
        auth = request.headers.get("Authorization")
        if auth is None:
            # a cookie counts for nothing: any server on another port of this host gets it
            cookie = " (a cookie is not accepted)" if "Cookie" in request.headers else ""
            return self._refuse(
                request,
                "no-token",
                401,
                f"token: missing{cookie} (open the URL the console printed, with ?token=…, "
                "or send Authorization: Bearer <token>)",
            )
        scheme, _, value = auth.strip().partition(" ")
        if scheme.lower() != "bearer" or not self._token_is(value.strip()):
            return self._refuse(
                request, "bad-token", 403, "Authorization: not this console's token"
            )
        return await handler(request)

    def _refuse(self, request: web.Request, kind: str, status: int, reason: str) -> web.Response:
        """Count, audit within the budget, and answer ``status`` with the reason."""
        self.refusals[kind] += 1
        if self._budget.take(time.monotonic()):
            self.audited += 1
            client = request.remote
            self._record(
                reason=reason,
                client=client,
                method=request.method,
                path=_clip(request.path),
                host=_clip(request.headers.get("Host")),
                origin=_clip(request.headers.get("Origin")),
                refusal=kind,
            )
            log.warning(
                "%s: refused %s %s from %s: %s",
                self.stage,
                request.method,
                _clip(request.path),
                client,
                reason,
            )
        else:
            # a flood of bad requests must not become a flood of audit records
            self._unaudited += 1
        realm = f'Bearer realm="dyknow-{self.stage}"'
        headers = {"WWW-Authenticate": realm} if status == 401 else {}
        return web.Response(
            text=json.dumps({"error": reason}),
            status=status,
            content_type="application/json",
            headers=headers,
        )

    def _record(self, **fields: Any) -> None:
        if self.audit is not None:
            self.audit.record(verdict="refused", stage=self.stage, **fields)

    def report(self) -> None:
        """Sum up the refusals past the budget in one record (and one log line), if any."""
        n, self._unaudited = self._unaudited, 0
        if not n:
            return
        reason = (
            f"{n} more {self.stage} request(s) refused without a record each "
            f"(over {AUDIT_RATE:g} records/s)"
        )
        self._record(reason=reason, count=n)
        log.warning("%s: %s; refusals so far %s", self.stage, reason, self.refusals)

    async def run_reports(self, closing: asyncio.Event) -> None:
        """`report` every `REPORT_INTERVAL` s until ``closing``, then a last time."""
        try:
            while not closing.is_set():
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(REPORT_INTERVAL):
                        await closing.wait()
                self.report()
        finally:
            self.report()


class _MalformedRequests(logging.Filter):
    """aiohttp's record of a request that is not HTTP: one line, within a budget."""

    def __init__(self) -> None:
        super().__init__()
        self._budget = TokenBucket(AUDIT_RATE, AUDIT_BURST, time.monotonic())

    def filter(self, record: logging.LogRecord) -> bool:
        """Keep the record without its traceback, or drop it past the budget."""
        exc = record.exc_info[1] if record.exc_info else None
        if not isinstance(exc, HttpProcessingError):
            return True  # an error of ours: its traceback is wanted
        if not self._budget.take(time.monotonic()):
            return False
        record.msg = f"{record.getMessage()}: {exc.code} {_clip(str(exc.message))}"
        record.args, record.exc_info, record.exc_text = (), None, None
        record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True


_http_log = logging.getLogger("federation.console.http")
_http_log.addFilter(_MalformedRequests())


class _Busy(asyncio.Protocol):
    """A connection past `MAX_CLIENTS`: answered 503 and closed, its request never read."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """Answer 503 and close."""
        # a write transport (uvloop's is no subclass of asyncio's: no isinstance check)
        cast(asyncio.WriteTransport, transport).write(_BUSY)
        transport.close()


def _address(transport: asyncio.BaseTransport | None) -> str | None:
    """The client address a connection counts under (`_client_key`), None once it is gone."""
    peer = None if transport is None else transport.get_extra_info("peername")
    return _client_key(str(peer[0])) if isinstance(peer, tuple) and peer else None


def _client_key(host: str) -> str:
    """What one client's connections count under: an IPv4 address, or an IPv6 one's /64.

    One IPv6 host commonly holds a whole /64 (it may pick a fresh address per
    connection), and an IPv4 client on a dual-stack socket arrives IPv4-mapped.
    """
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


class _PerAddress(asyncio.Protocol):
    """A new connection's first protocol: served (handed to aiohttp's) or, past its
    address's share, answered 503 and closed, its request never read."""

    def __init__(self, admit: Callable[[str | None], bool], serve: Callable[[], Any]) -> None:
        self._admit = admit
        self._serve = serve

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """Hand the connection on, or refuse it; nothing has been read yet either way."""
        if not self._admit(_address(transport)):
            cast(asyncio.WriteTransport, transport).write(_BUSY_ADDRESS)
            transport.close()
            return
        handler = self._serve()
        transport.set_protocol(handler)
        handler.connection_made(transport)


async def serve(
    app: web.Application,
    host: str,
    port: int,
    stack: contextlib.AsyncExitStack,
    access: ConsoleAccess,
    *,
    max_clients: int = MAX_CLIENTS,
    max_per_address: int = MAX_CLIENTS_PER_ADDRESS,
    idle_timeout: float = IDLE_TIMEOUT,
) -> int:
    """Serve ``app`` on ``host``:``port`` until ``stack`` closes; the port bound.

    Unlike a plain `aiohttp.web.TCPSite`, what a client costs is bounded before it sends
    a request: ``max_clients`` connections at once (more are answered 503, counted in
    ``access.busy``), ``max_per_address`` of them from one client address (more: 503,
    ``access.busy_address``), and a connection without a whole request within ``idle_timeout`` s is
    closed (aiohttp's own default keeps one for an hour). Requests under way (an event
    stream, a WebSocket) are not timed.
    """
    runner = web.AppRunner(
        app,
        shutdown_timeout=2.0,
        access_log=None,
        keepalive_timeout=idle_timeout,
        logger=_http_log,
    )
    await runner.setup()
    stack.push_async_callback(runner.cleanup)
    server = runner.server
    assert server is not None

    def admit(address: str | None) -> bool:
        # aiohttp's list of the connections open: at most max_clients, walked once each
        same = sum(1 for h in server.connections if _address(h.transport) == address)
        if address is None or same < max_per_address:
            return True
        access.busy_address += 1
        if access._budget.take(time.monotonic()):
            log.warning(
                "%s: %d connections open from %s; one more closed unserved (%d so far)",
                access.stage,
                same,
                address,
                access.busy_address,
            )
        return False

    def connection() -> asyncio.Protocol:
        if len(server.connections) < max_clients:
            return _PerAddress(admit, server)
        access.busy += 1
        if access._budget.take(time.monotonic()):
            log.warning(
                "%s: %d connections open; one more closed unserved (%d so far)",
                access.stage,
                max_clients,
                access.busy,
            )
        return _Busy()

    listener = await asyncio.get_running_loop().create_server(
        connection, host or None, port, reuse_address=True
    )
    # first out: no new connection, then the runner closes those open (never wait_closed
    # here: it waits for every connection, which the runner has not closed yet)
    stack.callback(listener.close)
    return int(listener.sockets[0].getsockname()[1])
