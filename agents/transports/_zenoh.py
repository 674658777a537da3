"""The zenoh transport (the default): peer, client or router mode over eclipse-zenoh.

zenoh's Python API is synchronous and calls back on zenoh's own threads. Everything that
comes back (samples, replies, queries, liveliness changes) goes through an ``Inbox``:
the callback appends and wakes the event loop only when the consumer waits and no
wake-up is pending, never one ``call_soon_threadsafe`` per message. No callback ever
waits for the event loop, so undeclaring or closing from the loop cannot deadlock.

Choices that follow from what we measured with eclipse-zenoh 1.10.2 (Python, loopback):

- ``publish`` uses congestion control DROP with reliable reliability: a frozen subscriber
  costs dropped samples, never a publisher stalled for seconds (BLOCK stalled 5 s).
  DROP drops what finds the link's send queue full for zenoh's ``wait_before_drop``
  (1 ms), silently: with zenoh's default queue (2 batches of 64 kB a priority), a burst
  of a few hundred kB (an Interface Agent's batched envelopes) was lost whenever zenoh's
  send thread did not run for a few ms (a busy machine) or the receiver read slowly. So
  the data priority's queue is zenoh's largest, 16 batches of 64 kB a link, unless the
  user's JSON5 or ``overrides`` set it: what a sender promises is that a burst waits in
  that queue rather than being dropped while it fits (16 puts at least, each in a batch
  of its own when zenoh's send thread is starved; up to ~1 MB of small puts packed
  together); beyond that, DROP.
  ``publish_blocking`` (a reply a receiver asked for, such as a resend) uses BLOCK, in a
  worker thread so the event loop never waits: a congested link delays it, up to zenoh's
  ``wait_before_close`` (5 s) for room in the queue, instead of dropping it.
- Every put, ACL envelopes included, goes at zenoh's default priority (data), batched
  (express off). ACL envelopes at ``DATA_HIGH`` (their queue also 16 batches), so that
  a request or reply need not wait behind stream samples in a link's send queue, did not
  help: ``bench scale --quick``, 13 alternated pairs, the global get-latest's p50 and
  p99 over raw get's 1.43 and 1.50 with it, 1.44 and 1.50 without (p50 13.8 / 12.7 ms).
  The tail is not in the send queue. It also ran the one-way ACL flood at 0.75-1.06x
  the rate (3 A/Bs), and 2 of 12 runs lost 2-4% of 30 000 messages (none without).
  ``express`` on the ACL publisher made the two-process round trip 1.01-1.12x as long
  (``bench._acl_cpu``, 2 A/Bs of 5 pairs; 1.08x with ``DATA_HIGH`` too), left the flood's
  rate alone (1.00x) and the scale query's p50 ratio at 1.60 instead of 1.50 (6 rounds).
  The wire is the same whatever the priority, so a peer may pick any.
- Sessions are always closed (``aclose``, and an ``atexit`` safety net): a session with
  callback subscribers left open can hang the interpreter at exit.
- Never ``fork`` a process that has a session open: start children with ``spawn``.
- Closing a session whose peer is frozen (SIGSTOP, not dead) takes zenoh's close timeout,
  about 10 s, whatever the link lease; ``aclose`` waits for it and only logs it.
- Peer mode keeps gossip on, since peers do not forward for other peers.
- ``ask`` has its reply callback called on zenoh's network thread (``indirect=False``):
  zenoh's default starts a Python thread for each handler, so one per get. Measured
  (``bench._ask_threads``, loopback, a busy machine): an ``ask`` round trip 0.5-0.8 ms
  instead of 0.75-1.8 ms (0.59 instead of 4.1 ms when the CPUs were the most contended:
  a new thread waits for one), and 0.52-0.69x the asker's CPU. The callback only appends
  to an ``Inbox``, but zenoh's thread waits for the GIL first, and the link's later
  messages (keep-alives, samples, replies) may wait behind it. With Python's switch
  interval (5 ms), the loop thread and another thread spinning in pure Python and a
  flood of puts on the same link, no reply was lost, the flood's rate differed within
  the runs' noise and a 1 s link lease never expired, either way. With a 50 ms interval,
  replies waited in line for the GIL: asks took 2.1 s (median) instead of 0.4-0.9 s and
  8 of 80 got no answer within 2 s (none with a thread each; the 1 s lease expired in
  one run of two either way); so above 5 ms, a thread per get again.
  This is safe for ``ask`` because zenoh releases its session lock before it calls a
  query's callback (a reply, an error, the timeout, the last replier done), so zenoh's
  thread waits for the GIL holding no lock. Not for ``tokens``: zenoh answers a
  liveliness get (from the tokens it knows, or as they come) calling the callback while
  it holds the session's state write lock, so a callback waiting for the GIL there would
  deadlock against a thread holding the GIL and waiting for that lock. ``tokens`` keeps
  zenoh's thread per get: its callback only pushes the reply into a 256-reply channel
  that thread drains. That channel can fill (more than 256 matching tokens), and zenoh
  then waits under the lock for the thread, which needs the GIL: so the rule for all of
  our code is that nothing calls a zenoh method that takes the session lock without
  releasing the GIL (``Session.is_closed()`` is one: never call it; a get, a put, a
  declare, an undeclare, a cancel, ``close`` and ``info``'s zid lists release it).

What runs on zenoh's threads: a subscriber's ``admit`` screen and the ``take`` of
``subscribe_taking``, a queryable's ``admit``, and the appends to each ``Inbox``. The
Interface Agent's ``take`` (its lane) opens an ACL envelope there while nothing waits for
the loop (else queues it unopened) and may answer a plain read there too: it reads only what
the loop replaces whole or guards by a lock (never waiting for one the loop may hold across
a zenoh call: the sender's buckets are tried without waiting), seals under the session
table's lock, and puts on a publisher the loop declared (``declared_publisher``: it never
declares, which changes the publishers' table). Everything else, counts and audit of what it
answered included, is posted to the event loop (``call_soon_threadsafe``).

Error replies: a zenoh error reply carries no key, so its ``Reply.key`` is the query's
key expression (the memory transport gives the queryable's).
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import atexit
import contextlib
import json
import logging
import re
import sys
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Iterable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Literal, cast

import zenoh
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from .._exceptions import TransportClosed, TransportError
from ._base import (
    Handle,
    Inbox,
    Message,
    Presence,
    QueryFilter,
    QueryHandler,
    Replies,
    Reply,
    Subscription,
    Transport,
    _Keeps,
)

log = logging.getLogger(__name__)


_ENDPOINT = re.compile(r"^[a-z][a-z0-9+-]*/\S+$")
_PUBLISHER_CACHE = 1024
# Threads that may wait in a blocking put at once (one a congested receiver at a time).
_BLOCKING_PUTS = 4
# How long past its own timeout a query may take before we stop waiting for zenoh's
# "finished" signal: a backstop, zenoh ends every query at its timeout.
_QUERY_GRACE = 1.0
# How long after opening zenoh may still route a liveliness get to no one: a link is
# connected before its peer is in the routing (seen: 2-15 ms, 140 ms on a loaded machine).
_LINK_SETTLE = 0.25
# Up to this switch interval (Python's default) an ask's reply callback runs on zenoh's
# network thread, not in a Python thread of its own: see the module's docstring.
_DIRECT_REPLIES_SWITCH = 0.005
# None: by the switch interval; True or False: forced (``bench._ask_threads`` runs both)
_REPLIES_INDIRECT: bool | None = None


def _replies_indirect() -> bool:
    """Whether an ask's reply callback gets a Python thread of its own (zenoh's default)."""
    if _REPLIES_INDIRECT is not None:
        return _REPLIES_INDIRECT
    return sys.getswitchinterval() > _DIRECT_REPLIES_SWITCH


# The data priority's send queue, in batches (zenoh's limit, 16; its default, 2): a burst
# of 16 puts at least, ~1 MB at most, waits for zenoh's send thread instead of being
# dropped (see above).
_TX_QUEUE = "transport/link/tx/queue/size/data"
_TX_QUEUE_BATCHES = 16

# zenoh's shared memory (on by default) carries puts over 3 kB between two sessions of one
# host through /dev/shm; once a link has it, a task of zenoh's wakes every 100 ms for as
# long as the session lives (~20 thread wakeups/s, most of an idle node's), buffers or no
# buffers. Off unless the user's JSON5 sets it or ``overrides`` turn it on: nodes on
# separate hosts never use it, and on one host the link carries the bytes instead.
_SHM = "transport/shared_memory/enabled"
# A JSON5 text that has ``shared_memory`` as a key (quoted or not, followed by a colon),
# once its comments (``/* */``, and ``//`` at a line's start or after a space) are gone
_SHM_KEY = re.compile(r"""(?:^|[\s{,'"])shared_memory['"]?\s*:""")
_JSON5_COMMENT = re.compile(r"/\*.*?\*/|(?:^|(?<=\s))//[^\n]*", re.DOTALL | re.MULTILINE)

# Sessions opened and not yet closed, closed at exit: an unclosed session with callback
# subscribers can hang interpreter shutdown.
_OPEN_SESSIONS: dict[int, zenoh.Session] = {}


def _close_leftover_sessions() -> None:
    for session in list(_OPEN_SESSIONS.values()):
        try:
            session.close()
        except Exception as exc:  # the interpreter is exiting: tell, and close the rest
            log.debug("zenoh: closing a leftover session at exit: %s", exc)
    _OPEN_SESSIONS.clear()


atexit.register(_close_leftover_sessions)

# What a subscriber callback queues: the payload copied, the rest converted later.
_RawSample = tuple[zenoh.KeyExpr, bytes, bytes | None]
_new_tuple = tuple.__new__  # a NamedTuple's own constructor costs ~0.2 µs more per sample


def _message(raw: _RawSample) -> Message:
    """The Message for what a subscriber callback queued (called by the consumer)."""
    return _new_tuple(Message, (str(raw[0]), raw[1], raw[2]))


class ZenohTls(BaseModel):
    """TLS for ``tls/`` endpoints: the CA that vouches for the other side, and our certificate.

    With a certificate (and its key) the session shows it both when connecting and when
    listening, and mutual TLS is on: a listener refuses a client without a certificate
    from the CA. The certificate's common name is what the router's access control
    matches (``cert_common_names``). Files are PEM; ``deploy/make_certs.py`` makes them.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)

    root_ca_certificate: Path = Field(
        description="The CA certificate the other side must chain to."
    )
    certificate: Path | None = Field(default=None, description="This side's certificate.")
    private_key: Path | None = Field(default=None, description="The certificate's private key.")
    verify_name_on_connect: bool = Field(
        default=True,
        description="Check that the router's certificate names the address connected to.",
    )

    @model_validator(mode="after")
    def _pair(self) -> "ZenohTls":
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("certificate and private_key go together (give both or neither)")
        return self

    def files(self) -> dict[str, Path]:
        """The files this needs, by field name."""
        named = {
            "root_ca_certificate": self.root_ca_certificate,
            "certificate": self.certificate,
            "private_key": self.private_key,
        }
        return {name: path for name, path in named.items() if path is not None}

    def settings(self) -> dict[str, Any]:
        """The zenoh ``transport/link/tls`` settings this describes."""
        out: dict[str, Any] = {
            "root_ca_certificate": str(self.root_ca_certificate),
            "verify_name_on_connect": self.verify_name_on_connect,
        }
        if self.certificate is not None and self.private_key is not None:
            cert, key = str(self.certificate), str(self.private_key)
            out |= {
                "connect_certificate": cert,
                "connect_private_key": key,
                "listen_certificate": cert,
                "listen_private_key": key,
                "enable_mtls": True,
            }
        return out


class ZenohUser(BaseModel):
    """User/password authentication to a router (zenoh's ``transport/auth/usrpwd``).

    The password is read from a file when the session opens, so it never sits in the
    platform's config file; ``deploy/make_certs.py`` writes one per platform.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)

    user: str = Field(min_length=1, description="The user name the router knows.")
    password_file: Path = Field(description="A file holding the password (one line).")

    def password(self) -> str:
        """The password from ``password_file``; TransportError says what is wrong with it."""
        try:
            text = self.password_file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) else "not UTF-8 text"
            raise TransportError(
                f"usrpwd.password_file: {self.password_file}: cannot be read: {reason}"
            ) from None
        password = text.strip("\r\n")
        if not password or "\n" in password:
            raise TransportError(
                f"usrpwd.password_file: {self.password_file}: must hold one non-empty line"
            )
        return password


class ZenohConfig(BaseModel):
    """How a zenoh session joins the network; validated once, errors name the field."""

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] | None = Field(
        default=None,
        description="Endpoints to listen on, e.g. tcp/127.0.0.1:7447. Default: peer and "
        "router listen on an ephemeral loopback port, a client listens nowhere.",
    )
    connect: tuple[str, ...] = Field(
        default=(), description="Endpoints to connect to (a seed peer, or a router)."
    )
    multicast_scouting: bool = Field(
        default=False, description="Find peers by UDP multicast (off: explicit endpoints)."
    )
    gossip: bool = Field(
        default=True,
        description="Peers tell each other about peers; needed in peer mode, where peers "
        "do not forward for other peers.",
    )
    wait_for_scouted: bool = Field(
        default=False,
        description="Let opening wait for the peers gossip or multicast finds (zenoh's "
        "scouting delay, 500 ms); off: open returns once the connect endpoints are tried "
        "and peers found later join in the background.",
    )
    overrides: Mapping[str, Any] = Field(
        default_factory=dict,
        description="Raw zenoh settings applied last: config path -> JSON value, e.g. "
        '{"transport/link/tx/lease": 1000}.',
    )
    json5: str | None = Field(
        default=None,
        description="A whole zenoh configuration (JSON5) the fields above are applied on.",
    )
    serve_timeout: float = Field(
        default=10.0,
        gt=0,
        description="Seconds a query handler may run before the query gets an error reply.",
    )
    tls: ZenohTls | None = Field(
        default=None, description="Certificates for tls/ endpoints (mutual TLS with a cert)."
    )
    usrpwd: ZenohUser | None = Field(
        default=None, description="User and password file to authenticate to a router."
    )

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...] | None) -> tuple[str, ...] | None:
        for endpoint in value or ():
            if not _ENDPOINT.fullmatch(endpoint):
                raise ValueError(f"{endpoint!r} is not an endpoint like tcp/127.0.0.1:7447")
            try:
                zenoh.Config().insert_json5("connect/endpoints", json.dumps([endpoint]))
            except zenoh.ZError as exc:
                raise ValueError(f"{endpoint!r} is not a zenoh endpoint: {exc}") from None
        return value

    @field_validator("json5")
    @classmethod
    def _json5(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                zenoh.Config.from_json5(value)
            except zenoh.ZError as exc:
                raise ValueError(f"not a zenoh configuration: {exc}") from None
        return value

    @field_validator("overrides")
    @classmethod
    def _overrides(cls, value: Mapping[str, Any]) -> Mapping[str, Any]:
        for path, setting in value.items():
            try:
                zenoh.Config().insert_json5(path, json.dumps(setting))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{path}: not a JSON value ({exc})") from None
            except zenoh.ZError as exc:
                raise ValueError(f"{path}: {exc}") from None
        return value

    @model_validator(mode="after")
    def _reachable(self) -> "ZenohConfig":
        if self.mode == "client" and not self.connect and not self.multicast_scouting:
            raise ValueError(
                "connect: a client with no connect endpoints and no multicast scouting "
                "reaches nobody"
            )
        return self

    @classmethod
    def loopback(cls, port: int, *, connect: Iterable[int] = (), **fields: Any) -> "ZenohConfig":
        """A peer listening on 127.0.0.1:``port`` and connecting to the given loopback ports."""
        return cls(
            listen=(f"tcp/127.0.0.1:{port}",),
            connect=tuple(f"tcp/127.0.0.1:{p}" for p in connect),
            **fields,
        )

    def relative_to(self, base: str | Path) -> "ZenohConfig":
        """A copy whose relative TLS and password file paths are resolved against ``base``."""
        base = Path(base)
        update: dict[str, Any] = {}
        if self.tls is not None:
            paths = {k: base / p for k, p in self.tls.files().items() if not p.is_absolute()}
            update["tls"] = self.tls.model_copy(update=paths)
        if self.usrpwd is not None and not self.usrpwd.password_file.is_absolute():
            update["usrpwd"] = self.usrpwd.model_copy(
                update={"password_file": base / self.usrpwd.password_file}
            )
        return self.model_copy(update=update)

    def to_zenoh(self) -> zenoh.Config:
        """The zenoh.Config these settings describe."""
        if self.tls is not None:
            for name, file in self.tls.files().items():
                if not file.is_file():
                    raise TransportError(f"tls.{name}: {file}: no such file")
        password = None if self.usrpwd is None else self.usrpwd.password()
        try:
            cfg = zenoh.Config.from_json5(self.json5) if self.json5 else zenoh.Config()
            if not self.json5 or _setting(cfg, _TX_QUEUE) == _setting(zenoh.Config(), _TX_QUEUE):
                # (a size a user's JSON5 chose other than zenoh's stays; ``overrides`` come after)
                cfg.insert_json5(_TX_QUEUE, json.dumps(_TX_QUEUE_BATCHES))
            if not self.json5 or not _SHM_KEY.search(_JSON5_COMMENT.sub("", self.json5)):
                # (zenoh's default read back cannot say whether the user's JSON5 chose it)
                cfg.insert_json5(_SHM, "false")
            listen = self.listen
            if listen is None and not _listens(self.json5, cfg):
                listen = () if self.mode == "client" else ("tcp/127.0.0.1:0",)
            cfg.insert_json5("mode", json.dumps(self.mode))
            if listen is not None:  # else the JSON5 file's own listen endpoints stand
                cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
            cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
            cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
            cfg.insert_json5("scouting/gossip/enabled", json.dumps(self.gossip))
            cfg.insert_json5(
                "open/return_conditions/connect_scouted", json.dumps(self.wait_for_scouted)
            )
            if self.tls is not None:
                for name, value in self.tls.settings().items():
                    cfg.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
            if self.usrpwd is not None:
                cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(self.usrpwd.user))
                cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
            for path, setting in self.overrides.items():
                cfg.insert_json5(path, json.dumps(setting))
        except zenoh.ZError as exc:
            raise TransportError(f"invalid zenoh configuration: {exc}") from exc
        return cfg


def _listens(json5: str | None, cfg: zenoh.Config) -> bool:
    """Whether the user's JSON5 config names listen endpoints of its own."""
    if not json5:
        return False
    try:
        endpoints = json.loads(cfg.get_json("listen/endpoints"))
    except (zenoh.ZError, ValueError):
        return False
    # zenoh's default is a per-mode table; a user's list replaces it
    return isinstance(endpoints, list) and bool(endpoints)


_UNREAD: Any = object()  # a setting of a zenoh.Config that could not be read


def _setting(cfg: zenoh.Config, path: str) -> Any:
    """The setting at ``path`` of ``cfg``, or ``_UNREAD``."""
    try:
        return json.loads(cfg.get_json(path))
    except (zenoh.ZError, ValueError):
        return _UNREAD


def _reach(cfg: zenoh.Config) -> tuple[bool, int]:
    """Whether a session of ``cfg`` seeks peers or routers, and the links it makes once up.

    It seeks them when it connects to endpoints or scouts by multicast (or when that
    cannot be read). The links are those to its ``connect`` endpoints: a peer or a
    router links to each, a client to one router of them. Each setting is read once.
    """
    connect = _setting(cfg, "connect/endpoints")
    multicast = _setting(cfg, "scouting/multicast/enabled")
    mode = _setting(cfg, "mode")
    if connect is _UNREAD:
        return True, 0
    if isinstance(connect, dict):  # per mode
        anywhere = [e for endpoints in connect.values() for e in endpoints or ()]
        connect = None if mode is _UNREAD else connect.get(mode) or ()
    else:
        anywhere = connect
    seeks = bool(anywhere) or multicast is not False  # (unread: not False)
    if mode is _UNREAD or not isinstance(connect, list):
        return seeks, 0
    return seeks, min(len(connect), 1) if mode == "client" else len(connect)


# zenoh's errors end their parts with where in its Rust sources they were raised
_RUST_SOURCE = re.compile(r"\s+at /\S+?\.rs:\d+\.?")
_IN_USE = re.compile(r"bound to (?P<endpoint>[\w-]+/\S+?):? \[")
_UNREACHED = re.compile(r"Unable to connect to any of \[(?P<endpoints>[^\]]*)\]")
_ENDPOINT = re.compile(r"[\w-]+/[^\s,()\[\]]+")


def _zenoh_error(exc: zenoh.ZError) -> str:
    """A zenoh error's text for a person: without Rust source paths; an endpoint in use said so."""
    text = _RUST_SOURCE.sub("", str(exc)).strip()
    if "Address already in use" in text:
        found = _IN_USE.search(text)
        endpoint = found["endpoint"] if found else "a listen endpoint"
        return (
            f"cannot listen on {endpoint}: the address is in use (by another node, maybe "
            "this very platform running already, or another program): stop that one first, "
            "or listen on another endpoint"
        )
    found = _UNREACHED.search(text)
    if found:
        endpoints = ", ".join(_ENDPOINT.findall(found["endpoints"])) or "its connect endpoints"
        return (
            f"cannot connect to {endpoints} (connect): no zenoh router or peer accepted a "
            "session there (is it running, is the address right, does it speak zenoh/TLS "
            "as configured?)"
        )
    return text


@contextlib.contextmanager
def _converted(what: str) -> Iterator[None]:
    """Raise zenoh's errors as TransportError, saying what was being done."""
    try:
        yield
    except zenoh.ZError as exc:
        raise TransportError(f"zenoh: {what}: {_zenoh_error(exc)}") from exc


class ZenohTransport(_Keeps, Transport):
    """The Transport over a zenoh session (peer on loopback by default)."""

    name = "zenoh"

    def __init__(self, config: ZenohConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.config = (
            config if isinstance(config, ZenohConfig) else ZenohConfig.model_validate(config or {})
        )
        self._session: zenoh.Session | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._opened = 0.0  # loop time the session opened (see `tokens`)
        self._seeks = False  # whether the session looks for peers or routers (see `tokens`)
        self._links_wanted = 0  # links its ``connect`` endpoints make, once up (see `tokens`)
        self._publishers: OrderedDict[str, zenoh.Publisher] = OrderedDict()
        # each declared publisher's put for any thread (`declared_publisher`): made once by
        # the loop when it declares, dropped when it undeclares
        self._lone_puts: dict[str, Callable[[bytes], None]] = {}
        self._blocking: ThreadPoolExecutor | None = None  # publish_blocking's puts wait here
        self._slots = asyncio.Semaphore(_BLOCKING_PUTS)  # its threads free for a put
        self._subs: set[Subscription[Any]] = set()
        self._handles: set[Handle] = set()

    @property
    def session(self) -> zenoh.Session:
        """The zenoh session (for what the Transport interface does not cover)."""
        self._check_open()
        assert self._session is not None
        return self._session

    async def open(self) -> None:
        """Open the zenoh session (in a worker thread: connecting may take a while)."""
        loop = asyncio.get_running_loop()
        cfg = self.config.to_zenoh()
        opening = loop.run_in_executor(None, zenoh.open, cfg)
        try:
            session = await asyncio.shield(opening)
        except zenoh.ZError as exc:
            error = _zenoh_error(exc)
            if error.startswith("cannot listen on"):  # the endpoint says all
                raise TransportError(f"zenoh: {error}") from exc
            raise TransportError(f"zenoh: cannot open a session: {error}") from exc
        except asyncio.CancelledError:
            # The session still opens in its thread: close it then, or it is leaked.
            opening.add_done_callback(_close_opened)
            raise
        self._loop = loop
        self._opened = loop.time()
        self._seeks, self._links_wanted = _reach(cfg)
        self._session = session
        _OPEN_SESSIONS[id(session)] = session
        await self._start_tasks()

    async def aclose(self) -> None:
        """Undeclare everything, end every subscription, and close the session."""
        if self._state == "closed":
            return
        self._state = "closed"
        for sub in list(self._subs):
            sub.close()
        for handle in list(self._handles):
            handle.close()
        await self._end_tasks()
        if self._blocking is not None:
            # a put still waiting ends with the session (or its own bound)
            self._blocking.shutdown(wait=False, cancel_futures=True)
            self._blocking = None
        self._lone_puts.clear()
        for pub in self._publishers.values():
            _undeclare_publisher(pub)
        self._publishers.clear()
        session, self._session = self._session, None
        if session is not None:
            _OPEN_SESSIONS.pop(id(session), None)
            try:
                await asyncio.to_thread(session.close)
            except zenoh.ZError as exc:
                # Seen with a frozen peer: zenoh gives up after its close timeout (~10 s)
                # and the session is closed all the same; nothing for the caller to do.
                log.warning("zenoh: closing the session: %s", exc)

    def _open_session(self) -> tuple[zenoh.Session, asyncio.AbstractEventLoop]:
        self._check_open()
        assert self._session is not None and self._loop is not None
        return self._session, self._loop

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Put ``payload`` on ``key`` through a cached publisher (DROP, reliable)."""
        self._put(key, payload, attachment)

    async def publish_blocking(
        self, key: str, payload: bytes | Callable[[], Awaitable[bytes]]
    ) -> None:
        """Put ``payload`` on ``key`` with congestion control BLOCK, from a worker thread.

        zenoh waits for room in the link's queue (up to ``wait_before_close``, 5 s, after
        which it closes the link) instead of dropping; the loop goes on meanwhile. A
        subclass that overrides ``publish`` (a test's lossy link) gets ``publish``.
        ``payload`` as a function is made once a worker thread is free for it (see
        `Transport.publish_blocking`).
        """
        if type(self).publish is not ZenohTransport.publish:
            await self.publish(key, payload if isinstance(payload, bytes) else await payload())
            return
        session, loop = self._open_session()
        if self._blocking is None:
            self._blocking = ThreadPoolExecutor(_BLOCKING_PUTS, thread_name_prefix="zenoh-block")
            self._slots = asyncio.Semaphore(_BLOCKING_PUTS)
        executor, slots = self._blocking, self._slots
        try:
            # a free thread first: the payload is made when the put starts, and waits
            # behind other receivers' puts in the semaphore, never in the executor's queue
            async with slots:
                if not isinstance(payload, bytes):
                    payload = await payload()
                await loop.run_in_executor(executor, self._put_blocking, session, key, payload)
        except zenoh.ZError as exc:
            if self._state != "opened":
                raise TransportClosed(f"{self.name} transport is {self._state}") from exc
            raise TransportError(f"zenoh: put on {key!r}: {exc}") from exc
        except RuntimeError as exc:  # the executor was shut down: the transport closed
            raise TransportClosed(f"{self.name} transport is {self._state}") from exc

    @staticmethod
    def _put_blocking(session: zenoh.Session, key: str, payload: bytes) -> None:
        session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    @property
    def publishes_nowait(self) -> bool:
        """True (a zenoh put never waits for the loop), unless a subclass overrides ``publish``."""
        return type(self).publish is ZenohTransport.publish

    def publish_nowait(self, key: str, payload: bytes) -> None:
        """Publish ``payload`` on ``key`` now."""
        # `publishes_nowait`, inline: the path of every message sent alone
        if type(self).publish is not ZenohTransport.publish:
            # a subclass's own `publish` must see every put: the base refuses
            super().publish_nowait(key, payload)
            return
        # `_put`, inline (no attachment): a call less a message
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._declare_publisher(key)
        try:
            pub.put(payload)
        except zenoh.ZError as exc:
            raise self._put_failed(key, exc) from exc

    def _put(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._declare_publisher(key)
        try:
            if attachment is None:  # zenoh's default: no keyword (its dict costs ~2.5 k Ir)
                pub.put(payload)
            else:
                pub.put(payload, attachment=attachment)
        except zenoh.ZError as exc:
            raise self._put_failed(key, exc) from exc

    def _put_failed(self, key: str, exc: zenoh.ZError) -> TransportError:
        """What a put on ``key`` that zenoh refused raises: closed, or the transport's error."""
        if self._state != "opened":
            return TransportClosed(f"{self.name} transport is {self._state}")
        return TransportError(f"zenoh: put on {key!r}: {exc}")

    def has_subscribers(self, key: str) -> bool:
        """Whether zenoh knows a subscriber matching ``key`` now (its publisher's matching status).

        What zenoh routes a put by: one made while this is False reaches nobody, in peer
        and client mode alike. A client's publisher just declared says False until its
        router answered (a few ms) though its puts do go out meanwhile: a caller that
        skips work on False should keep what it skipped for a moment.
        """
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._declare_publisher(key)
        try:
            # a MatchingStatus, though zenoh's stub says bool (and bool() of it is always True)
            status: Any = pub.matching_status
            return bool(status.matching)
        except zenoh.ZError:
            return True  # cannot tell: as if someone listens

    def _declare_publisher(self, key: str) -> zenoh.Publisher:
        session, _ = self._open_session()
        with _converted(f"declare a publisher on {key!r}"):
            pub = session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.RELIABLE,
            )
        self._publishers[key] = pub
        self._lone_puts[key] = self._lone_put(key, pub)
        if len(self._publishers) > _PUBLISHER_CACHE:
            evicted, oldest = self._publishers.popitem(last=False)
            self._lone_puts.pop(evicted, None)
            _undeclare_publisher(oldest)
        return pub

    def _lone_put(self, key: str, pub: zenoh.Publisher) -> Callable[[bytes], None]:
        """A put on ``pub`` (declared on ``key``) that raises as `publish` does."""

        def put(payload: bytes) -> None:
            try:
                pub.put(payload)
            except zenoh.ZError as exc:
                if self._state != "opened":
                    raise TransportClosed(f"{self.name} transport is {self._state}") from exc
                raise TransportError(f"zenoh: put on {key!r}: {exc}") from exc

        return put

    async def subscribe(
        self, key_expr: str, *, buffer_size: int = 65536, admit: QueryFilter | None = None
    ) -> Subscription[Message]:
        """Receive what is put on keys matching ``key_expr``.

        ``admit`` runs on zenoh's thread for each sample: one it refuses is dropped there,
        never queued for the event loop.
        """
        session, loop = self._open_session()
        # On zenoh's thread only what must be done there: copy the payload out of zenoh's
        # receive buffer (holding the sample would pin that buffer, ~8 kB a sample). The
        # key becomes a str and the tuple a Message on the consumer's side: ~1.5x the
        # throughput of converting everything on zenoh's thread (measured here).
        inbox: Inbox[Message] = Inbox(loop, buffer_size, convert=_message)
        put = cast("Callable[[_RawSample], None]", inbox.put)

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            put(
                (
                    sample.key_expr,
                    sample.payload.to_bytes(),
                    None if att is None else att.to_bytes(),
                )
            )

        if admit is not None:

            def on_sample(sample: zenoh.Sample) -> None:
                payload = sample.payload.to_bytes()
                if admit(payload):
                    att = sample.attachment
                    put((sample.key_expr, payload, None if att is None else att.to_bytes()))

        with _converted(f"declare a subscriber on {key_expr!r}"):
            zsub = session.declare_subscriber(
                key_expr, zenoh.handlers.Callback(on_sample, inbox.close)
            )
        return self._subscription(inbox, lambda: self._undeclare(zsub))

    async def subscribe_taking(
        self,
        key_expr: str,
        take: Callable[[bytes], Any],
        *,
        buffer_size: int = 65536,
        dropped: Callable[[Any], None] | None = None,
    ) -> Subscription[Any] | None:
        """`subscribe`, each payload given to ``take`` on zenoh's thread (what it returns queued).

        ``take`` must never raise, and never wait for the event loop nor call a zenoh
        method that takes the session lock without releasing the GIL (see above).
        """
        session, loop = self._open_session()
        inbox: Inbox[Any] = Inbox(loop, buffer_size, dropped=dropped)
        put = inbox.put

        def on_sample(sample: zenoh.Sample) -> None:
            item = take(sample.payload.to_bytes())
            if item is not None:
                put(item)

        with _converted(f"declare a subscriber on {key_expr!r}"):
            zsub = session.declare_subscriber(
                key_expr, zenoh.handlers.Callback(on_sample, inbox.close)
            )
        return self._subscription(inbox, lambda: self._undeclare(zsub))

    def declared_publisher(self, key: str) -> Callable[[bytes], None] | None:
        """A put on ``key`` for any thread when its publisher is declared already; else None.

        Only reads the puts the event loop made as it declared (it alone adds and evicts;
        each is made once, not per call); a publisher evicted meanwhile was undeclared,
        and its put raises as a closed one.
        """
        if not self.publishes_nowait:
            return None
        # made by the loop alone (a put made here could outlive its publisher's eviction)
        return self._lone_puts.get(key)

    async def ask(self, key_expr: str, payload: bytes = b"", *, timeout: float) -> Replies:
        """Ask every queryable matching ``key_expr``; replies until all answered or ``timeout``."""
        session, loop = self._open_session()
        inbox: Inbox[Reply] = Inbox(loop)
        put = inbox.put

        def on_reply(reply: zenoh.Reply) -> None:
            ok = reply.ok
            if ok is not None:
                put(Reply(str(ok.key_expr), ok.payload.to_bytes()))
            elif (err := reply.err) is not None:
                put(Reply(key_expr, err.payload.to_bytes(), ok=False))

        cancel = zenoh.CancellationToken()
        with _converted(f"query {key_expr!r}"):
            # zenoh closes the inbox when it is "finished": every replier done, or its timeout
            session.get(
                key_expr,
                zenoh.handlers.Callback(on_reply, inbox.close, indirect=_replies_indirect()),
                payload=payload,
                timeout=timeout,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                cancellation_token=cancel,
            )

        def stop() -> None:
            timer.cancel()
            if not inbox.closed:  # the caller left before zenoh finished
                with contextlib.suppress(zenoh.ZError):
                    cancel.cancel()

        def late() -> None:
            if not inbox.closed:
                log.warning("zenoh query on %r did not finish by its timeout", key_expr)
                stop()
                inbox.close()

        timer = loop.call_later(timeout + _QUERY_GRACE, late)
        return Replies(inbox, stop)

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Answer queries on ``key_expr``; a failing or slow handler becomes an error reply.

        ``admit`` runs on zenoh's thread for each query: one it refuses is dropped there
        (the querier gets no reply), never queued for the event loop.
        """
        session, loop = self._open_session()
        queries: Inbox[zenoh.Query] = Inbox(loop, 4096)
        on_query: Callable[[zenoh.Query], None] = queries.put
        if admit is not None:
            put = queries.put

            def on_query(query: zenoh.Query) -> None:
                body = query.payload
                if admit(b"" if body is None else body.to_bytes()):
                    put(query)
                else:
                    with contextlib.suppress(zenoh.ZError):
                        query.drop()

        with _converted(f"declare a queryable on {key_expr!r}"):
            queryable = session.declare_queryable(
                key_expr, zenoh.handlers.Callback(on_query, queries.close)
            )
        self._spawn(self._serve(key_expr, handler, queries), f"zenoh.serve[{key_expr}]")

        def undeclare() -> None:
            self._undeclare(queryable)
            queries.close()

        return self._handle(undeclare)

    async def _serve(
        self, key_expr: str, handler: QueryHandler, queries: Inbox[zenoh.Query]
    ) -> None:
        """Take queries off the inbox and answer each in its own task (handlers may be slow)."""
        try:
            async with asyncio.TaskGroup() as answers:
                while True:
                    try:
                        query = await queries.get()
                    except TransportClosed:
                        break
                    answers.create_task(
                        self._answer(key_expr, handler, query), name=f"zenoh.answer[{key_expr}]"
                    )
        finally:
            # Queries still queued when the transport closes: tell their queriers now
            # rather than leaving them to their timeout.
            for query in queries.drain():
                with contextlib.suppress(zenoh.ZError):
                    query.reply_err(b"the transport is closing")
                    query.drop()

    async def _answer(self, key_expr: str, handler: QueryHandler, query: zenoh.Query) -> None:
        """Run the handler for one query and reply; never raises (the TaskGroup must live)."""
        try:
            body = query.payload
            try:
                async with asyncio.timeout(self.config.serve_timeout):
                    result = await handler(
                        str(query.key_expr), b"" if body is None else body.to_bytes()
                    )
            except TimeoutError:
                query.reply_err(f"handler timed out after {self.config.serve_timeout} s".encode())
            except asyncio.CancelledError:
                query.reply_err(b"the transport is closing")
                raise
            except Exception as exc:
                log.warning("query handler for %r failed", key_expr, exc_info=True)
                query.reply_err(str(exc).encode())
            else:
                if result is not None:
                    query.reply(key_expr, result)
        except zenoh.ZError as exc:
            log.debug("could not reply to a query on %r: %s", key_expr, exc)
        finally:
            with contextlib.suppress(zenoh.ZError):
                query.drop()

    async def declare_token(self, key: str) -> Handle:
        """A liveliness token on ``key``: watchers see it go when closed or this process dies."""
        session, _ = self._open_session()
        if "*" in key:
            raise TransportError(f"a liveliness token needs a concrete key, not {key!r}")
        with _converted(f"declare a liveliness token on {key!r}"):
            token = session.liveliness().declare_token(key)
        return self._handle(lambda: self._undeclare(token))

    async def watch_presence(
        self, key_expr: str, *, history: bool = True, buffer_size: int = 4096
    ) -> Subscription[Presence]:
        """Liveliness changes on ``key_expr`` (the tokens alive now first, if ``history``)."""
        session, loop = self._open_session()
        inbox: Inbox[Presence] = Inbox(loop, buffer_size)
        put = inbox.put
        alive = zenoh.SampleKind.PUT

        def on_sample(sample: zenoh.Sample) -> None:
            put(Presence(str(sample.key_expr), sample.kind == alive))

        with _converted(f"declare a liveliness subscriber on {key_expr!r}"):
            zsub = session.liveliness().declare_subscriber(
                key_expr, zenoh.handlers.Callback(on_sample, inbox.close), history=history
            )
        return self._subscription(inbox, lambda: self._undeclare(zsub))

    async def tokens(
        self, key_expr: str, *, timeout: float, keep: Callable[[str], bool] | None = None
    ) -> list[str]:
        """The tokens alive on ``key_expr``: a liveliness get, done once every peer answered.

        Right after opening, zenoh may still be connecting to the ``connect`` endpoints
        (in the background) or not yet route the get to a just-connected peer or router:
        it finishes at once with nothing. So while the session is younger than
        ``_LINK_SETTLE`` and has, or seeks, a peer or router, an empty answer is asked
        again; a session alone (no ``connect`` endpoints, no multicast) answers at once.
        While fewer links were up, as the get was asked, than its ``connect`` endpoints
        make, any answer is asked again, until ``timeout`` after opening: one peer
        answering first says nothing of the tokens of another whose link was still coming
        up (a link up only while the get ran was not asked).
        """
        session, loop = self._open_session()
        info = session.info

        def linked() -> int:
            """The session's links up now (peers and routers)."""
            return len(list(info.peers_zid())) + len(list(info.routers_zid()))

        # the links up as a get was asked: one that came up while it ran did not answer it
        links = linked()
        keys = await self._tokens(session, loop, key_expr, timeout)

        def again() -> float:
            """Seconds left to ask again (none: the answer is complete)."""
            age = loop.time() - self._opened
            left = 0.0
            if not keys and (self._seeks or linked()):
                left = _LINK_SETTLE - age
            if links < self._links_wanted:
                # a connect endpoint not linked as the get was asked may be the one
                # holding the token asked for (one peer's quick answer says nothing of
                # another's): ask again while it may still come up, within the bound of
                # an answer
                left = max(left, timeout - age)
            return left

        pause = 0.005
        while (left := again()) > 0:
            await asyncio.sleep(min(pause, left))
            pause = min(pause * 2, 0.05)
            links = linked()
            keys = await self._tokens(session, loop, key_expr, timeout)
        # screened last: any key in the answer shows the peers were reached (above)
        return keys if keep is None else [k for k in keys if keep(k)]

    async def _tokens(
        self,
        session: zenoh.Session,
        loop: asyncio.AbstractEventLoop,
        key_expr: str,
        timeout: float,
    ) -> list[str]:
        inbox: Inbox[str] = Inbox(loop)
        put = inbox.put

        def on_reply(reply: zenoh.Reply) -> None:
            if (ok := reply.ok) is not None:
                put(str(ok.key_expr))

        with _converted(f"ask the liveliness tokens on {key_expr!r}"):
            session.liveliness().get(
                key_expr,
                # a thread of zenoh-python's own, never zenoh's: see the module's docstring
                zenoh.handlers.Callback(on_reply, inbox.close, indirect=True),
                timeout=timeout,
            )
        keys: set[str] = set()
        with contextlib.suppress(TransportClosed, TimeoutError):  # closed: all answered
            async with asyncio.timeout(timeout + _QUERY_GRACE):
                while True:
                    keys.add(await inbox.get())
        return sorted(keys)

    @staticmethod
    def _undeclare(entity: Any) -> None:
        # Undeclaring after the session closed is a no-op in zenoh, but it may still raise.
        with contextlib.suppress(zenoh.ZError):
            entity.undeclare()


def _undeclare_publisher(pub: zenoh.Publisher) -> None:
    """Undeclare ``pub``, unless another thread is putting on it now (then it undeclares
    itself once the last reference to it goes, as zenoh drops it)."""
    try:
        pub.undeclare()
    except zenoh.ZError:
        pass  # the session closed already
    except RuntimeError:
        # "Already borrowed": a put of `declared_publisher`'s (the lane's answer) holds it
        # in zenoh's thread; raising here would fail the publish that evicts it, or end
        # `aclose` before its session is closed
        pass


def _close_opened(opening: asyncio.Future[zenoh.Session]) -> None:
    if not opening.cancelled() and opening.exception() is None:
        with contextlib.suppress(zenoh.ZError):
            opening.result().close()
