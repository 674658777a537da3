"""The MQTT transport: the same interface over an MQTT v5 broker (mosquitto), with aiomqtt.

Keys and topics
    A concrete key is the topic itself. In subscriptions ``*`` becomes ``+`` and ``**``
    becomes ``#``; MQTT has ``#`` only as the last level, so a key expression with ``**``
    elsewhere cannot be subscribed to (TransportError). Chunks with a partial wildcard
    (``a*``, zenoh's ``$*``) and keys containing ``+`` or ``#`` are refused too.

Subscriptions
    One connection per transport, one broker subscription per distinct topic filter, each
    with its own MQTT v5 subscription identifier. One task (``mqtt[<client id>].receive``,
    owned by the transport, cancelled on close) reads every incoming message and hands it,
    by subscription identifier, to the matching subscriptions' ``Inbox``es. Subscriptions
    deliver live messages only: retained messages a broker replays on subscribing are
    presence history, not publications.
    A call returns once the broker confirmed its subscription; the filters of one
    ``serve`` are subscribed together (one round trip, not one per filter). A
    subscription the broker refuses (a SUBACK reason code of 0x80 or more: not
    authorized, topic filter invalid, quota exceeded) raises TransportError naming the
    filter and the broker's reason, and leaves nothing behind; refused again when
    subscribing anew after a reconnection, it is logged and ends what listened through
    it: its subscriptions' and watchers' iterators end, and its queryables end whole
    (every filter of theirs unsubscribed), their `Handle` closed, its ``ended`` the
    reason (the TransportError's text and "(after reconnecting)"), its ``on_end``
    callbacks called with it. A subscribe
    its caller gave up on still takes the broker's answer, in the background: aiomqtt
    logs an answer to a call it no longer waits for as an error. An answer later than
    ``connect_timeout`` (a stalled broker: the background call gave up too) is logged
    at DEBUG as late; one to no call of this client stays aiomqtt's error.

Query / serve (a topic convention on MQTT v5 request/response)
    A query on key expression ``Q`` is published on ``@query/<P>``, where ``<P>`` is ``Q``
    up to its first wildcard chunk, with the whole ``Q`` in the user property ``key``,
    the response topic ``@reply/<client id>`` and a fresh correlation data. A queryable on
    ``S`` subscribes to ``@query`` followed by every prefix of ``S`` (``*`` as ``+``, a
    ``**`` ending it as ``#``), so it hears every query that could intersect ``S``, and
    answers those that do on the response topic, with the correlation data and user
    properties ``key`` = ``S`` and ``ok`` = ``1`` or ``0`` (an error reply: a handler
    that raised or ran past ``serve_timeout``).

Client ids
    Every connection's id is the configured ``client_id`` followed by ``-`` and 64 random
    bits, drawn again on each reconnection; the reply topic is ``@reply/<client_id>/``
    and 96 random bits: it names the configured prefix (a broker ACL can give each
    platform its own replies), never a connection's id. A broker evicts a client when
    another connects with its id: an id nobody knows cannot be taken over.

TLS
    ``tls`` (`MqttTls`): the CA that signed the broker's certificate and, for mutual TLS,
    this client's certificate and key (with the generated broker config its CN is the
    platform's name and the broker's user name for it).

Presence
    ``declare_token`` opens one more connection per token, whose last will is an empty
    retained message on the key; it then publishes ``{"v":1,"alive":true}`` retained on the
    key, and announces again when someone else clears the key or its connection drops.
    It hears the clearing through its own subscription to the key: one the broker
    refuses fails the declaration (TransportError, as any refused subscription) before
    anything is announced, its connection closed. A token that cannot announce itself
    again after its connection dropped (the reconnection failed, the subscription
    refused) ends: its `Handle` closed, its ``ended`` the error's text and
    "(after reconnecting)", its ``on_end`` callbacks called with it.
    Closing the token publishes the empty retained message (which clears it; QoS 0, its
    acknowledgement not waited for: a close does not wait on a slow broker); a process
    that dies loses its connection and the broker publishes the will.
    ``watch_presence`` subscribes to the key expression: retained messages are the
    history, live ones the changes; a watcher reports only changes. ``tokens`` tells the
    two apart by each message's retain flag, not by their order (MQTT orders messages of
    one topic, not a subscription's retained ones against what it routes later): a live
    message is newer than the retained snapshot of its key, whichever came first. The
    history is taken as complete once a message it sends itself through the broker is
    back and, when ``retained_quiet`` is set (default 0: a broker such as mosquitto
    sends the replay first), no retained message came for that long after it (within
    its timeout).

Closing
    Tokens are cleared together, within ``connect_timeout``; then the connection is
    closed with a DISCONNECT, or, when that cannot go out within a second (a broker
    that stopped reading a full socket), by closing the socket: the broker sees the
    connection lost. Only then are the transport's tasks and calls under way cancelled.
    An open (or a reconnection) given up returns at once and holds no thread: its TCP
    connection is made on the loop, where a cancel ends it; given up while paho's
    thread does TLS's handshake, the connection is shut down, which ends it, and the
    socket is closed on the loop as it returns, aiomqtt's task with it.

What MQTT cannot guarantee, compared to zenoh
    - Everything goes through the broker: it is a single point of failure and one more
      hop (about twice zenoh's peer-to-peer latency on loopback).
    - A query cannot know how many queryables there are, so `query` always waits until
      its timeout (zenoh returns once every matching queryable has answered); `ask`
      yields each reply as it comes, for a caller that stops at the first it can use
      (the key exchange: the first authenticated reply) or once those it expects
      answered (a platform's start: every platform whose token is alive).
      ``asks_end_when_answered`` is False here for such callers.
    - A dead process is seen gone when the broker notices: at once when its TCP connection
      closes (a killed process), but only after 1.5 x keepalive for a frozen one or a lost
      network; and a broker that restarts without persistence forgets every token.
    - Presence is one retained message per key: two tokens on the same key are not
      counted, the first to go clears the key.
    - QoS 0 (the default) is at most once; nothing is redelivered after a reconnection.
      A lost connection is reconnected once at once (a new client id, every subscription
      again; a token announces itself again); when that fails, every subscription ends,
      every queryable and token ends (`Handle.on_end`: nothing answers for them any
      more, and a token's own connection would announce the platform alive again once
      the broker is back) and later calls raise TransportClosed. A close during the
      reconnection ends the new connection too.
    - Attachments travel base64-encoded in a user property.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import logging
import math
import os
import secrets
import socket
import threading
from collections.abc import Callable, Coroutine, Iterator, Mapping
from typing import TYPE_CHECKING, Any

from .._aio import together
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
    Screened,
    Subscription,
    Transport,
    _Keeps,
    key_intersects,
)
from ._mqtt_config import MqttConfig

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    import aiomqtt

    _Client = aiomqtt.Client
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.properties import Properties
    from paho.mqtt.subscribeoptions import SubscribeOptions


def _load_client() -> None:
    """Import the MQTT client when a transport is made, not with this module.

    Every platform imports this module (its config is one of the transports'), most never
    speak MQTT: aiomqtt and paho cost them ~11 MB and tens of ms of start-up.
    """
    if "_Client" in globals():  # loaded: one client class for every transport
        return
    import aiomqtt
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.properties import Properties
    from paho.mqtt.subscribeoptions import SubscribeOptions

    class Client(aiomqtt.Client):
        """aiomqtt's client, whose waits for the broker never lose a cancellation."""

        _connect_ended: threading.Event | None = None  # set when paho's connect returns

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            # packet ids of (un)subscribes given up, whose answer is late (`_pending_call`)
            self._late_subscribes: set[int] = set()
            self._late_unsubscribes: set[int] = set()

        async def _wait_for(self, fut: Any, timeout: float | None) -> Any:
            return await _wait_keeping_cancel(self, fut, timeout)

        async def __aenter__(self) -> Any:
            self._connect_ended = threading.Event()
            paho = self._client
            if paho._transport != "tcp" or paho._get_proxy() is not None:
                return await super().__aenter__()  # paho connects, all in its thread
            # TCP's handshake on the loop, where a cancel ends it at once: in paho's
            # thread it went on after a cancel, up to 5 s per address (a black hole)
            try:
                sock = await _open_socket(
                    self._hostname,
                    self._port,
                    paho._connect_timeout,
                    (self._bind_address, self._bind_port),
                )
            except BaseException as exc:
                self._connect_ended.set()  # no thread started: nothing to wait for
                if isinstance(exc, OSError):
                    raise aiomqtt.MqttError(str(exc)) from None  # as aiomqtt's own connect
                raise
            handed = _Handed(sock)
            # paho's connect takes it: in its thread only TLS's handshake and the CONNECT
            vars(paho)["_create_socket_connection"] = handed.take
            try:
                return await super().__aenter__()
            except BaseException:
                # given up with the thread perhaps still in TLS's handshake (a broker that
                # never answers): the connection ends now, and the thread with it
                handed.drop()
                raise
            finally:
                handed.close()
                # paho's thread, started but not yet at the socket, finds `take` (which
                # refuses a dropped one), not paho's own connect: that made one in the thread
                if self._connect_ended.is_set():
                    vars(paho).pop("_create_socket_connection", None)

        _given_up = False  # `_abandon` did not wait for paho's connect (see there)

        def _client_connect(self) -> None:
            # in an executor thread, which a cancel does not stop (`_Handed.drop` ends its
            # TLS handshake): a connection given up meanwhile (`_abandon`) has the socket
            # it opens closed on the loop from here
            try:
                super()._client_connect()
            finally:
                vars(self._client).pop("_create_socket_connection", None)  # `__aenter__`'s
                if self._connect_ended is not None:
                    self._connect_ended.set()
                if self._given_up:  # after what this connect scheduled on the loop
                    with contextlib.suppress(RuntimeError):  # the loop closed: gone with it
                        self._loop.call_soon_threadsafe(self._drop_socket)

        def _give_up(self) -> None:
            """Have the socket paho's connect may still open closed when it comes."""
            self._given_up = True
            if self._connect_ended is not None and self._connect_ended.is_set():
                # ended meanwhile, perhaps before it saw ``_given_up``: dropped from here
                self._loop.call_soon(self._drop_socket)

        # A SUBACK or UNSUBACK whose call aiomqtt stopped waiting for (its timeout,
        # ``connect_timeout``, passed: a stalled broker) is late, not unexpected: aiomqtt
        # logs it at ERROR with a traceback, which reads as a failure of ours. Only the
        # packet ids of calls given up are late: any other stays aiomqtt's error.
        @contextlib.contextmanager
        def _pending_call(
            self, mid: int, value: Any, pending_dict: dict[int, Any]
        ) -> Iterator[None]:
            with super()._pending_call(mid, value, pending_dict):
                try:
                    yield
                except BaseException:  # timed out or cancelled: its answer may still come
                    if pending_dict is self._pending_subscribes:
                        self._late_subscribes.add(mid)
                    elif pending_dict is self._pending_unsubscribes:
                        self._late_unsubscribes.add(mid)
                    raise

        def _on_subscribe(self, client: Any, userdata: Any, mid: int, *args: Any) -> None:
            if mid not in self._pending_subscribes and mid in self._late_subscribes:
                self._late_subscribes.discard(mid)
                log.debug("mqtt: the broker answered subscribe %d after it was given up", mid)
                return
            super()._on_subscribe(client, userdata, mid, *args)

        def _on_unsubscribe(self, client: Any, userdata: Any, mid: int, *args: Any) -> None:
            if mid not in self._pending_unsubscribes and mid in self._late_unsubscribes:
                self._late_unsubscribes.discard(mid)
                log.debug("mqtt: the broker answered unsubscribe %d after it was given up", mid)
                return
            super()._on_unsubscribe(client, userdata, mid, *args)

        def _drop_socket(self) -> None:
            # paho's own close: aiomqtt stops watching the socket and ends its task
            with contextlib.suppress(OSError):
                self._client._sock_close()

    globals().update(
        aiomqtt=aiomqtt,
        PacketTypes=PacketTypes,
        Properties=Properties,
        SubscribeOptions=SubscribeOptions,
        _Client=Client,
    )


async def _open_socket(
    host: str, port: int, timeout: float, bind: tuple[str, int]
) -> socket.socket:
    """A TCP connection to ``host``, as `socket.create_connection` makes it for paho.

    Each address in turn, ``timeout`` s each; the last one's error, worded as that
    function's (``[Errno 111] Connection refused``, ``timed out``). On the loop: a cancel
    ends it at once, its socket closed.
    """
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    failure: OSError = OSError(f"no address for {host!r}")
    for family, kind, proto, _, address in infos:
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            if any(bind):
                sock.bind(bind)
            async with asyncio.timeout(timeout):
                await loop.sock_connect(sock, address)
        except TimeoutError:
            sock.close()
            failure = TimeoutError("timed out")
            continue
        except OSError as exc:
            sock.close()
            # asyncio words it "Connect call failed (address)": the system's words here
            failure = OSError(exc.errno, os.strerror(exc.errno)) if exc.errno else exc
            continue
        except BaseException:
            sock.close()
            raise
        sock.settimeout(timeout)  # paho's TLS handshake is bounded by it, as before
        return sock
    raise failure


class _Handed:
    """A connected socket handed to paho's connect in its thread, or dropped on the loop.

    `take` (paho's thread) and `drop` (the loop, when the open is given up) under one
    lock: a socket never taken is closed here, one taken is shut down, which ends a TLS
    handshake under way in the thread at once (paho closes its own socket later).
    """

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self._lock = threading.Lock()
        self._taken = False
        self._dropped = False
        # the same connection for the loop to shut down: paho's TLS takes the socket's own
        self._twin = sock.dup()

    def take(self) -> socket.socket:
        """The socket, once (paho's `_create_socket_connection`, in its thread)."""
        with self._lock:
            if self._dropped:
                raise OSError("the connection was given up")
            self._taken = True
        return self._sock

    def drop(self) -> None:
        """End the connection: the open was given up (the loop)."""
        with self._lock:
            self._dropped = True
            taken = self._taken
        with contextlib.suppress(OSError):
            self._twin.shutdown(socket.SHUT_RDWR)
        if not taken:
            self._sock.close()

    def close(self) -> None:
        """Let go of the loop's handle on the connection (not of the connection)."""
        self._twin.close()


def mqtt_client(*args: Any, **kwargs: Any) -> aiomqtt.Client:
    """An ``aiomqtt.Client`` (same arguments) whose waits never lose a cancellation.

    For code beside the transport that speaks MQTT itself (an application's inputs and
    outputs): a task cancelled while it waits for the broker ends, on Python 3.11 too.
    """
    _load_client()
    return _Client(*args, **kwargs)


async def _wait_keeping_cancel(client: aiomqtt.Client, fut: Any, timeout: float | None) -> Any:
    """aiomqtt's wait for the broker's answer (``Client._wait_for``), by ``asyncio.timeout``.

    aiomqtt waits through ``asyncio.wait_for``, which on Python 3.11 returns the answer when
    it comes in the same turn as a cancellation of the waiting task: the cancellation is
    lost. A platform's task looping over publishes (the audit's flush) then went on after
    the close cancelled it, and the close waited for it forever. ``asyncio.timeout`` has
    no such gap; the errors are aiomqtt's own.
    """
    if timeout is None:
        timeout = client.timeout
    try:
        async with asyncio.timeout(None if timeout == math.inf else timeout):
            return await fut
    except TimeoutError:
        raise aiomqtt.MqttError("Operation timed out") from None


QUERY_PREFIX = "@query"
REPLY_PREFIX = "@reply"
ALIVE = b'{"v":1,"alive":true}'
_REPLY_SID = 1  # the subscription identifier of this client's reply topic
_PENDING_CALLS_WARN = 64  # calls awaiting the broker before aiomqtt warns (`_new_client`)
_DISCONNECT_WAIT = 1.0  # s: a DISCONNECT not out by then is not waited for (`_disconnect`)


def _connection_id(prefix: str) -> str:
    """A client id for one connection: the configured prefix and 64 random bits.

    A broker drops a client when another connects with its id (MQTT's session takeover):
    an id nobody can guess cannot be taken, and a new one is drawn on every reconnection.
    """
    return f"{prefix}-{secrets.token_hex(8)}"


def _chunks(key_expr: str) -> list[str]:
    """The chunks of a key expression MQTT can carry; TransportError otherwise."""
    if not key_expr or key_expr.startswith("$"):
        raise TransportError(f"{key_expr!r} cannot be an MQTT topic")
    chunks = key_expr.split("/")
    for chunk in chunks:
        if not chunk:
            raise TransportError(f"{key_expr!r} has an empty chunk")
        if "+" in chunk or "#" in chunk or "\0" in chunk:
            raise TransportError(f"{key_expr!r}: '+', '#' and NUL are not allowed in keys")
        if "*" in chunk and chunk not in ("*", "**"):
            raise TransportError(f"{key_expr!r}: MQTT has no wildcard inside a chunk")
    return chunks


def topic_filter(key_expr: str) -> str:
    """The MQTT topic filter for a key expression (``*`` → ``+``, a final ``**`` → ``#``)."""
    chunks = _chunks(key_expr)
    out = []
    for i, chunk in enumerate(chunks):
        if chunk == "**":
            if i != len(chunks) - 1:
                raise TransportError(
                    f"{key_expr!r}: MQTT has a multi-level wildcard ('#') only at the end, "
                    "so '**' can only be the last chunk"
                )
            out.append("#")
        else:
            out.append("+" if chunk == "*" else chunk)
    return "/".join(out)


def query_topic(key_expr: str) -> str:
    """The topic a query on ``key_expr`` is published on: its chunks up to the first wildcard."""
    prefix = list(itertools.takewhile(lambda c: c not in ("*", "**"), _chunks(key_expr)))
    return "/".join([QUERY_PREFIX, *prefix])


def queryable_filters(key_expr: str) -> list[str]:
    """The filters a queryable on ``key_expr`` listens on: one per prefix (see the module doc)."""
    chunks = _chunks(key_expr)
    filters = [QUERY_PREFIX]
    for i, chunk in enumerate(chunks):
        if chunk == "**":
            # '#' also matches its parent level: it replaces the previous filter.
            filters[-1] = "/".join([QUERY_PREFIX, *_plus(chunks[:i]), "#"])
            break
        filters.append("/".join([QUERY_PREFIX, *_plus(chunks[: i + 1])]))
    return filters


def _plus(chunks: list[str]) -> list[str]:
    return ["+" if c == "*" else c for c in chunks]


def _user_properties(props: Properties | None) -> dict[str, str]:
    pairs = getattr(props, "UserProperty", None) if props is not None else None
    return dict(pairs) if pairs else {}


_MAX_PRESENCE_KEYS = 4096  # remembered per watcher: well above any federation's size
_MAX_PRESENCE_KEY = 1024  # characters: ours are ``dyknow/<fed>/v1/alive/<name>``, < 300


def _alive(key: str, payload: bytes) -> bool | None:
    """What a presence message on ``key`` says: alive or not; None (warned) if malformed."""
    if not payload:
        return False  # the empty retained message that clears a token
    try:
        return bool(json.loads(payload)["alive"])
    except (ValueError, TypeError, KeyError, RecursionError):  # nested too deep
        log.warning("mqtt: ignoring a malformed presence message on %r", key)
        return None


class _Watcher:
    """A presence watcher: turns retained presence messages into changes."""

    def __init__(self, inbox: Inbox[Presence], history: bool) -> None:
        self.inbox = inbox
        self.history = history
        self.known: dict[str, bool] = {}

    def feed(self, key: str, payload: bytes, retained: bool) -> None:
        """Take one message on a presence key; report it if it changes what is known."""
        if retained and not self.history:
            return
        alive = _alive(key, payload)
        if alive is None:
            return
        known = self.known
        if known.get(key) == alive:
            return
        # Anyone on the broker can publish under invented keys: what is remembered is
        # bounded (the oldest forgotten first; a platform's key is short). A key not
        # remembered is reported again when it repeats, which consumers take as a hint.
        if len(key) <= _MAX_PRESENCE_KEY:
            known.pop(key, None)
            known[key] = alive
            if len(known) > _MAX_PRESENCE_KEYS:
                del known[next(iter(known))]
        self.inbox.put(Presence(key, alive))


class _Server:
    """One queryable served through a broker subscription."""

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start, each; nothing compares or prints these
    __slots__ = ("admit", "end", "handler", "key_expr")

    def __init__(self, key_expr: str, handler: QueryHandler, admit: QueryFilter | None) -> None:
        self.key_expr = key_expr
        self.handler = handler
        self.admit = admit
        # ends the queryable (all its filters) when the broker refuses one of them
        self.end: Callable[[str], None] | None = None


class _Alive:
    """The tokens seen on a presence subscription: its retained snapshot, then live changes.

    A live message (retain flag unset) was routed after the subscription was made, so it
    is newer than the retained message of its key, even one that arrives after it.
    """

    def __init__(
        self, loop: asyncio.AbstractEventLoop, keep: Callable[[str], bool] | None = None
    ) -> None:
        self.loop = loop
        self.keep = keep
        self.retained: dict[str, bool] = {}
        self.live: dict[str, bool] = {}
        self.last_retained = loop.time()  # the replay's latest message (the start before)
        self.came = asyncio.Event()  # set at each retained message

    def feed(self, key: str, payload: bytes, retained: bool) -> None:
        """Take one message on a presence key (a `_Watcher`'s interface)."""
        alive = _alive(key, payload)
        if alive is None:
            return
        if self.keep is not None and not self.keep(key):
            return  # screened before the bound below: junk keys cannot crowd these out
        seen = self.retained if retained else self.live
        if key not in seen and len(self.retained) + len(self.live) >= _MAX_PRESENCE_KEYS:
            return  # an outsider's flood of invented keys: what is kept stays bounded
        seen[key] = alive
        if retained:
            self.last_retained = self.loop.time()
            self.came.set()

    def alive(self) -> list[str]:
        """The keys alive: each one's latest live message, else its retained one."""
        return sorted(k for k, v in (self.retained | self.live).items() if v)


class _Filter:
    """One broker subscription and everything in this transport that listens through it."""

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start, each; nothing compares or prints these
    __slots__ = ("inboxes", "ready", "refused", "servers", "sid", "topic", "watchers")

    def __init__(self, topic: str, sid: int, ready: asyncio.Future[bool | None]) -> None:
        self.topic = topic
        self.sid = sid
        self.ready = ready
        self.refused: str | None = None  # the broker's reason, when it refused the filter
        self.inboxes: list[Inbox[Message] | Screened] = []
        self.watchers: list[_Watcher | _Alive] = []
        self.servers: list[_Server] = []

    def empty(self) -> bool:
        return not (self.inboxes or self.watchers or self.servers)


class MqttTransport(_Keeps, Transport):
    """The Transport over one MQTT v5 broker connection (plus one per liveliness token)."""

    name = "mqtt"
    forgeable_presence = True
    asks_end_when_answered = False

    def __init__(self, config: MqttConfig | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        _load_client()
        self.config = (
            config if isinstance(config, MqttConfig) else MqttConfig.model_validate(config or {})
        )
        self._client: aiomqtt.Client | None = None
        self._connection: contextlib.AsyncExitStack | None = None  # disconnects _client
        self._loop: asyncio.AbstractEventLoop | None = None
        # not derived from the client id: queries show it to every queryable
        self._reply_topic = f"{REPLY_PREFIX}/{self.config.client_id}/{secrets.token_hex(12)}"
        self.reconnects = 0
        self._up: asyncio.Event | None = None  # set while the main connection serves
        self._filters: dict[str, _Filter] = {}
        self._by_sid: dict[int, _Filter] = {}
        self._sids = itertools.count(_REPLY_SID + 1)
        self._unsubscribing: dict[str, asyncio.Task[None]] = {}
        self._pending: dict[bytes, Inbox[Reply]] = {}
        self._correlation = itertools.count(1)
        self._subs: set[Subscription[Any]] = set()
        self._handles: set[Handle] = set()
        self._lost: BaseException | None = None
        # subscribes and unsubscribes waiting for the broker's answer, see `_acked`
        self._acks: set[asyncio.Task[Any]] = set()

    def _new_client(self, identifier: str, will: aiomqtt.Will | None = None) -> aiomqtt.Client:
        c = self.config
        client = _Client(
            c.host,
            c.port,
            identifier=identifier,
            username=c.username,
            password=None if c.password is None else c.password.get_secret_value(),
            protocol=aiomqtt.ProtocolVersion.V5,
            keepalive=c.keepalive,
            timeout=c.connect_timeout,
            will=will,
            tls_context=None if c.tls is None else c.tls.context(),
        )
        # aiomqtt warns of "pending publish calls" past 10 calls awaiting the broker's
        # answer; a platform's start (and close) has one (un)subscribe per topic filter
        # under way at once, ~15: no sign of a backlog
        client.pending_calls_threshold = _PENDING_CALLS_WARN
        return client

    async def open(self) -> None:
        """Connect to the broker, subscribe to this client's reply topic, start receiving."""
        loop = asyncio.get_running_loop()
        client, self._connection = await self._connect_main()
        self._client = client
        self._loop = loop
        self._up = asyncio.Event()
        self._up.set()
        await self._start_tasks()
        self._spawn(self._receive(client), f"mqtt[{self.config.client_id}].receive")

    async def _connect_main(self) -> tuple[aiomqtt.Client, contextlib.AsyncExitStack]:
        """Connect with a fresh client id and subscribe to this transport's reply topic.

        Returns the client and the exit stack that disconnects it.
        """
        client = self._new_client(_connection_id(self.config.client_id))
        where = f"{self.config.host}:{self.config.port}"
        try:
            connection = await _connect(client)
        except aiomqtt.MqttError as exc:
            raise TransportError(f"mqtt: cannot connect to {where}: {exc}") from exc
        try:
            refused = await self._subscribe(client, self._reply_topic, _REPLY_SID)
        except aiomqtt.MqttError as exc:
            await _disconnect(client, connection)
            raise TransportError(f"mqtt: cannot subscribe to replies on {where}: {exc}") from exc
        except BaseException:
            # cancelled (a close while reconnecting): nobody else holds this connection
            await _disconnect(client, connection)
            raise
        if refused is not None:
            await _disconnect(client, connection)
            raise TransportError(
                f"mqtt: {where} refused the subscription to this client's replies: {refused}"
            )
        return client, connection

    async def aclose(self) -> None:
        """Clear this transport's tokens, end every subscription and query, and disconnect.

        Bounded however many tokens, subscriptions and calls are under way and however
        stalled the broker: ``connect_timeout`` for the tokens together, then `_disconnect`.
        """
        if self._state == "closed":
            return
        self._state = "closed"
        for sub in list(self._subs):
            sub.close()
        handles = list(self._handles)
        if handles:  # clearing tokens needs the broker: bounded, in case it is gone
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.config.connect_timeout), asyncio.TaskGroup() as tg:
                    for n, h in enumerate(handles):
                        name = f"mqtt[{self.config.client_id}].close[{n}]"
                        tg.create_task(_closing(h), name=name)
        for inbox in self._pending.values():
            inbox.close()
        # Disconnected before the tasks and calls under way are cancelled: an
        # (un)subscribe cancelled first made aiomqtt forget its packet id, and the
        # broker's answer, still read until the disconnect, was logged as an error.
        client, connection = self._client, self._connection
        self._connection, self._client = None, None
        if client is not None and connection is not None:
            await _disconnect(client, connection)
        await self._end_tasks()
        acks = list(self._acks)
        for task in acks:
            task.cancel()
        if acks:  # each ends at its cancel: they wait on nothing else
            await asyncio.wait(acks, timeout=_DISCONNECT_WAIT)

    def _check_open(self) -> None:
        super()._check_open()
        if self._lost is not None:
            raise TransportClosed(f"mqtt: the connection to the broker was lost: {self._lost}")

    def _connected(self) -> tuple[aiomqtt.Client, asyncio.AbstractEventLoop]:
        self._check_open()
        assert self._client is not None and self._loop is not None
        return self._client, self._loop

    def _error(self, what: str, exc: BaseException) -> TransportError:
        if self._state != "opened" or self._lost is not None:
            return TransportClosed(f"mqtt: {what}: the transport is closed ({exc})")
        return TransportError(f"mqtt: {what}: {exc}")

    def _options(self) -> SubscribeOptions:
        return SubscribeOptions(qos=self.config.qos)

    async def _receive(self, client: aiomqtt.Client) -> None:
        """Hand every incoming message to whatever listens through its subscription.

        A lost connection (the broker went, or dropped us for another client) is
        reconnected once, with a new client id and every subscription again; only when
        that fails are the subscriptions ended.
        """
        while True:
            try:
                async for message in client.messages:
                    try:
                        self._dispatch(message)
                    except Exception:  # one message, from anyone on the broker, never ends this
                        log.warning("mqtt: dropping a message on %r", message.topic, exc_info=True)
                return
            except aiomqtt.MqttError as exc:
                if self._state != "opened":
                    return
                log.warning("mqtt: connection to the broker lost (%s); reconnecting", exc)
                if self._up is not None:
                    self._up.clear()
                try:
                    client = await self._reconnect()
                except (TransportError, aiomqtt.MqttError) as again:
                    if self._state != "opened":  # closed meanwhile: its close ended it
                        return
                    log.warning("mqtt: could not reconnect: %s", again)
                    self._lost = exc
                    for sub in list(self._subs):
                        sub.inbox.close()
                    for inbox in self._pending.values():
                        inbox.close()
                    # nothing is served any more: each queryable and token ends, its owner
                    # told (a token's own connection, made again once the broker is back,
                    # would otherwise announce alive what no longer answers)
                    reason = (
                        f"mqtt: the connection to the broker was lost ({exc}) and could "
                        f"not be made again ({again})"
                    )
                    for handle in list(self._handles):
                        handle._end(reason)
                    return

    async def _reconnect(self) -> aiomqtt.Client:
        old, self._connection = self._connection, None
        if old is not None:
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
                async with asyncio.timeout(1.0):
                    await old.aclose()
        # no await between the connection and keeping it: a close from then on ends it
        client, self._connection = await self._connect_main()
        self._client = client
        for f in list(self._filters.values()):
            if self._filters.get(f.topic) is not f:
                continue  # a queryable ended by a refusal before took it with it
            refused = await self._subscribe(client, f.topic, f.sid)
            if refused is not None:
                log.warning(
                    "mqtt: the broker refused the subscription to %r again after "
                    "reconnecting (%s): what listened through it ends",
                    f.topic,
                    refused,
                )
                self._end(f, f"{_refusal(f.topic, refused)} (after reconnecting)")
        self.reconnects += 1
        if self._up is not None:
            self._up.set()
        log.warning("mqtt: reconnected to the broker (%d time(s))", self.reconnects)
        return client

    def _dispatch(self, m: aiomqtt.Message) -> None:
        props = m.properties
        sids = getattr(props, "SubscriptionIdentifier", None) if props is not None else None
        if not sids:
            return
        topic = m.topic.value
        payload = m.payload
        for sid in sids:
            if sid == _REPLY_SID:
                self._on_reply(payload, props)
                continue
            f = self._by_sid.get(sid)
            if f is None:  # unsubscribed meanwhile
                continue
            if f.inboxes and not m.retain:
                attachment = None
                if getattr(props, "UserProperty", None):
                    att = _user_properties(props).get("att")
                    try:
                        attachment = None if att is None else base64.b64decode(att)
                    except ValueError:  # binascii.Error: anyone on the broker can send one
                        log.debug("mqtt: a message on %r: attachment not base64", topic)
                        continue
                msg = Message(topic, payload, attachment)
                for inbox in f.inboxes:
                    inbox.put(msg)
            for watcher in f.watchers:
                watcher.feed(topic, payload, m.retain)
            for server in f.servers:
                self._offer(server, payload, props)

    def _on_reply(self, payload: bytes, props: Properties | None) -> None:
        correlation = getattr(props, "CorrelationData", None)
        inbox = self._pending.get(correlation) if correlation else None
        if inbox is None:  # late: its query is over
            return
        up = _user_properties(props)
        inbox.put(Reply(up.get("key", ""), payload, up.get("ok", "1") == "1"))

    # --- subscriptions shared per topic filter -------------------------------------------

    async def _attach(
        self,
        topic: str,
        add: Callable[[_Filter], None],
        remove: Callable[[_Filter], None],
        *,
        resubscribe: bool = False,
    ) -> None:
        """Listen through the broker subscription on ``topic``, subscribing if it is new.

        Fails (or is cancelled) having listened to nothing: ``remove`` undoes ``add``.
        """
        client, loop = self._connected()
        while True:
            # An unsubscribe still on its way would cancel a subscribe sent now: wait for it.
            while (pending := self._unsubscribing.get(topic)) is not None:
                await asyncio.wait([pending])
            f = self._filters.get(topic)
            if f is None:
                break
            add(f)
            try:
                ready = await asyncio.shield(f.ready)
                if ready is None:  # its subscriber gave up before the broker answered
                    self._leave(f, remove)
                    continue
                if not ready:
                    if f.refused is not None:
                        raise _refusal(topic, f.refused)
                    raise self._error(f"subscribe to {topic!r}", RuntimeError("subscribe failed"))
                if resubscribe:  # makes the broker send the retained messages again
                    try:
                        refused = await self._subscribe(client, topic, f.sid)
                    except aiomqtt.MqttError as exc:
                        raise self._error(f"subscribe to {topic!r}", exc) from exc
                    if refused is not None:
                        raise _refusal(topic, refused)
            except BaseException:
                # cancelled too: left in the filter, it would keep the topic subscribed
                # and be fed forever
                self._leave(f, remove)
                raise
            return
        f = _Filter(topic, next(self._sids), loop.create_future())
        self._filters[topic] = f
        self._by_sid[f.sid] = f
        add(f)
        try:
            refused = await self._subscribe(client, topic, f.sid)
        except aiomqtt.MqttError as exc:
            f.ready.set_result(False)
            self._forget(f)
            raise self._error(f"subscribe to {topic!r}", exc) from exc
        except BaseException:
            # cancelled (a caller's timeout): those waiting on ``ready`` subscribe anew,
            # rather than wait forever or fail for a caller that gave up
            f.ready.set_result(None)
            self._forget(f)
            raise
        if refused is not None:
            # the others waiting on ``ready`` fail with the same reason and leave it
            f.refused = refused
            f.ready.set_result(False)
            self._forget(f, unsubscribe=False)  # the broker holds no such subscription
            raise _refusal(topic, refused)
        f.ready.set_result(True)

    def _detach(self, topic: str, remove: Callable[[_Filter], None]) -> None:
        """Stop listening through ``topic``; unsubscribe (in the background) when nobody does."""
        f = self._filters.get(topic)
        if f is None:
            return
        with contextlib.suppress(ValueError):
            remove(f)
        if f.empty():
            self._forget(f)

    def _leave(self, f: _Filter, remove: Callable[[_Filter], None]) -> None:
        """Stop listening through ``f`` itself (``topic`` may have a newer filter by now)."""
        with contextlib.suppress(ValueError):
            remove(f)
        if self._filters.get(f.topic) is f and f.empty():
            self._forget(f)

    def _forget(self, f: _Filter, *, unsubscribe: bool = True) -> None:
        if self._filters.get(f.topic) is f:
            del self._filters[f.topic]
        self._by_sid.pop(f.sid, None)
        if not unsubscribe or self._state != "opened" or self._lost is not None:
            return
        if self._loop is None:
            return
        task = self._spawn(self._unsubscribe(f.topic), f"mqtt[{self.config.client_id}].unsubscribe")
        self._unsubscribing[f.topic] = task
        task.add_done_callback(lambda t: self._unsubscribing.pop(f.topic, None))

    def _end(self, f: _Filter, reason: str) -> None:
        """Forget ``f``, which the broker no longer serves, and end what listened through it.

        Its subscriptions' and watchers' iterators end rather than wait in silence; its
        queryables end whole (every filter of theirs), their handles closed with
        ``ended`` = ``reason`` and their owners' ``on_end`` callbacks called.
        """
        self._forget(f, unsubscribe=False)
        for entry in f.inboxes:
            (entry.inbox if isinstance(entry, Screened) else entry).close()
        for watcher in f.watchers:
            if isinstance(watcher, _Watcher):
                watcher.inbox.close()
        for server in list(f.servers):
            if server.end is not None:
                server.end(reason)

    async def _subscribe(self, client: aiomqtt.Client, topic: str, sid: int) -> str | None:
        """Subscribe ``client`` to ``topic`` as ``sid`` (`_acked`); the broker's refusal, if any."""
        granted = await self._acked(
            client.subscribe(topic, options=self._options(), properties=_sid(sid))
        )
        return _refused(granted)

    async def _unsubscribe(self, topic: str) -> None:
        if self._client is None:
            return
        try:
            await self._acked(self._client.unsubscribe(topic))
        except aiomqtt.MqttError as exc:
            log.debug("mqtt: unsubscribing from %r failed: %s", topic, exc)

    async def _acked(self, call: Coroutine[Any, Any, Any]) -> Any:
        """Await an aiomqtt (un)subscribe, which waits for the broker's answer, shielded.

        A caller that gives up (its timeout, its cancel) leaves the call waiting for the
        answer rather than cancel it: cancelled, aiomqtt forgets the packet id, and the
        SUBACK/UNSUBACK that still comes is logged at ERROR with a traceback ("Unexpected
        message ID"), which reads as a failure. The call ends at the answer or at
        aiomqtt's timeout (``connect_timeout``); `aclose` cancels those left once
        disconnected, when no answer is read any more: a caller still waiting gets an
        ``MqttError``, as any call on a closed transport, not that cancel.
        """
        task = asyncio.ensure_future(call)
        self._acks.add(task)
        task.add_done_callback(self._settled)
        try:
            return await asyncio.shield(task)
        except asyncio.CancelledError:
            current = asyncio.current_task()
            if task.cancelled() and current is not None and not current.cancelling():
                # `aclose` cancelled the wait, not the caller's own cancel: for the
                # caller, a call that failed on a closed transport
                raise aiomqtt.MqttError("the transport closed before the broker answered") from None
            raise

    def _settled(self, task: asyncio.Task[Any]) -> None:
        self._acks.discard(task)
        if not task.cancelled():
            task.exception()  # retrieved: a caller that gave up no longer awaits it

    # --- the Transport interface ---------------------------------------------------------

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Publish ``payload`` on the topic ``key`` (QoS from the config, not retained)."""
        client, _ = self._connected()
        if not key or "*" in key or "+" in key or "#" in key:
            raise TransportError(f"mqtt: cannot publish on {key!r}: not a concrete key")
        props = None
        if attachment is not None:
            props = Properties(PacketTypes.PUBLISH)
            props.UserProperty = [("att", base64.b64encode(attachment).decode())]
        try:
            await client.publish(key, payload, qos=self.config.qos, properties=props)
        except aiomqtt.MqttError as exc:
            raise self._error(f"publish on {key!r}", exc) from exc

    async def subscribe(
        self, key_expr: str, *, buffer_size: int = 65536, admit: QueryFilter | None = None
    ) -> Subscription[Message]:
        """Receive what is published on topics matching ``key_expr``.

        ``admit`` screens each message as it is read off the connection, before it is
        queued: one it refuses is dropped there.
        """
        _, loop = self._connected()
        topic = topic_filter(key_expr)
        inbox: Inbox[Message] = Inbox(loop, buffer_size)
        entry = inbox if admit is None else Screened(inbox, admit)

        def remove(f: _Filter) -> None:
            f.inboxes.remove(entry)

        await self._attach(topic, lambda f: f.inboxes.append(entry), remove)
        return self._subscription(inbox, lambda: self._detach(topic, remove))

    async def ask(self, key_expr: str, payload: bytes = b"", *, timeout: float) -> Replies:
        """Ask every queryable intersecting ``key_expr``; replies as they come, for ``timeout``.

        MQTT cannot tell how many queryables heard the query: the replies end only at the
        timeout, unless the caller leaves as soon as it has what it needs.
        """
        client, loop = self._connected()
        topic = query_topic(key_expr)
        correlation = next(self._correlation).to_bytes(8, "big")
        props = Properties(PacketTypes.PUBLISH)
        props.ResponseTopic = self._reply_topic
        props.CorrelationData = correlation
        props.UserProperty = [("key", key_expr)]
        inbox: Inbox[Reply] = Inbox(loop)
        self._pending[correlation] = inbox
        try:
            await client.publish(topic, payload, qos=self.config.qos, properties=props)
        except BaseException as exc:
            del self._pending[correlation]
            if isinstance(exc, aiomqtt.MqttError):
                raise self._error(f"query {key_expr!r}", exc) from exc
            raise

        def stop() -> None:
            timer.cancel()
            self._pending.pop(correlation, None)  # a reply still to come is late: dropped

        def end() -> None:
            stop()
            inbox.close()

        timer = loop.call_later(timeout, end)
        return Replies(inbox, stop)

    async def _round_trip(self, timeout: float) -> bool:
        """Whether a message to this client through the broker came back within ``timeout`` s.

        The broker sends a client what it owes it in order, the retained messages of a
        subscription as it takes it: once this is back, those of every subscription
        made before it have arrived here, and were handed on.
        """
        client, loop = self._connected()
        correlation = secrets.token_bytes(16)  # random: nobody else can end it early
        inbox: Inbox[Reply] = Inbox(loop, 1)
        self._pending[correlation] = inbox
        try:
            props = Properties(PacketTypes.PUBLISH)
            props.CorrelationData = correlation
            try:
                await client.publish(self._reply_topic, b"", qos=self.config.qos, properties=props)
            except aiomqtt.MqttError as exc:
                raise self._error("a round trip through the broker", exc) from exc
            try:
                async with asyncio.timeout(timeout):
                    await inbox.get()
            except (TimeoutError, TransportClosed):
                return False
            return True
        finally:
            self._pending.pop(correlation, None)

    async def tokens(
        self, key_expr: str, *, timeout: float, keep: Callable[[str], bool] | None = None
    ) -> list[str]:
        """The tokens alive on ``key_expr``: the retained ones, once the broker sent them all.

        All sent: a round trip through the broker after subscribing is back
        (`_round_trip`, a few ms) and no retained message came for ``retained_quiet`` s
        after it (0: none waited for); what came by ``timeout`` s when that takes longer.
        A live change that comes in the meantime wins over its key's retained message,
        before or after it. ``keep`` screens each key as it comes, before the bound on
        the keys remembered (`_MAX_PRESENCE_KEYS`).
        """
        _, loop = self._connected()
        deadline = loop.time() + timeout
        topic = topic_filter(key_expr)
        seen = _Alive(loop, keep)

        def remove(f: _Filter) -> None:
            f.watchers.remove(seen)

        try:
            # the call's own timeout, not aiomqtt's (connect_timeout) for its (re)subscribe
            async with asyncio.timeout_at(deadline):
                await self._attach(
                    topic, lambda f: f.watchers.append(seen), remove, resubscribe=True
                )
        except TimeoutError as exc:
            raise self._error(
                f"tokens on {key_expr!r}",
                RuntimeError(f"the broker did not take the subscription within {timeout} s"),
            ) from exc
        try:
            await self._round_trip(max(0.0, deadline - loop.time()))
            # the quiet time runs from the echo, not from the start: a slow round trip
            # must not end the wait for a replay that comes just after it
            seen.last_retained = max(seen.last_retained, loop.time())
            while (end := min(seen.last_retained + self.config.retained_quiet, deadline)) > (
                now := loop.time()
            ):
                seen.came.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(end - now):
                        await seen.came.wait()
        finally:
            self._detach(topic, remove)
        return seen.alive()

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Answer queries intersecting ``key_expr``; a failing or slow handler → error reply.

        ``admit`` screens each query as it is read off the connection, before a task is
        made for it: one it refuses is dropped unanswered.
        """
        self._connected()
        filters = queryable_filters(key_expr)
        server = _Server(key_expr, handler, admit)

        def remove(f: _Filter) -> None:
            f.servers.remove(server)

        attached: list[str] = []

        async def attach(topic: str) -> None:
            await self._attach(topic, lambda f: f.servers.append(server), remove)
            attached.append(topic)

        try:
            # the filters' subscribes go out together: one round trip through the broker,
            # not one per filter (a queryable has one per chunk of its key, ~6)
            await together(*(attach(topic) for topic in filters))
        except BaseException:
            for topic in attached:
                self._detach(topic, remove)
            raise

        def undeclare() -> None:
            for topic in filters:
                self._detach(topic, remove)

        handle = self._handle(undeclare)
        server.end = handle._end
        return handle

    def _offer(self, server: _Server, payload: bytes, props: Properties | None) -> None:
        """A query heard through one of ``server``'s filters: answer it if it intersects."""
        key = _user_properties(props).get("key")
        response_topic = getattr(props, "ResponseTopic", None)
        correlation = getattr(props, "CorrelationData", None)
        if not key or not response_topic or not key_intersects(server.key_expr, key):
            return
        if "+" in response_topic or "#" in response_topic:
            return  # no topic to publish on: the answer could not go out
        if server.admit is not None and not server.admit(payload):
            return
        self._spawn(
            self._answer(server, key, payload, response_topic, correlation),
            f"mqtt[{self.config.client_id}].serve[{server.key_expr}]",
        )

    async def _answer(
        self,
        server: _Server,
        key: str,
        payload: bytes,
        response_topic: str,
        correlation: bytes | None,
    ) -> None:
        """Run the handler for one query and publish its reply; never raises but on cancel."""
        ok = True
        try:
            async with asyncio.timeout(self.config.serve_timeout):
                result = await server.handler(key, payload)
        except TimeoutError:
            ok, result = False, f"handler timed out after {self.config.serve_timeout} s".encode()
        except Exception as exc:
            log.warning("query handler for %r failed", server.key_expr, exc_info=True)
            ok, result = False, str(exc).encode()
        if result is None or self._client is None:
            return
        props = Properties(PacketTypes.PUBLISH)
        if correlation is not None:
            props.CorrelationData = correlation
        props.UserProperty = [("key", server.key_expr), ("ok", "1" if ok else "0")]
        try:
            await self._client.publish(
                response_topic, result, qos=self.config.qos, properties=props
            )
        except aiomqtt.MqttError as exc:
            log.debug("mqtt: could not reply to a query on %r: %s", server.key_expr, exc)

    async def declare_token(self, key: str) -> Handle:
        """Announce ``key`` (retained), cleared on close or, through a last will, on death.

        The token's connection is watched: dropped (another client took its id, or the
        broker restarted) it reconnects with a new id and announces again; a presence
        message on its key that is not its own (someone cleared it) is answered by
        announcing again.
        """
        self._connected()
        if "*" in key:
            raise TransportError(f"a liveliness token needs a concrete key, not {key!r}")
        _chunks(key)
        token = _Token(self, key)
        await token.connect()
        token.task = self._spawn(token.keep(), f"mqtt.token[{key}].keep")

        def start_clearing() -> None:
            if self._tg is not None:
                self._spawn(token.clear(), f"mqtt.token[{key}].clear")

        handle = self._handle(start_clearing, token.clear)
        token.end = handle._end
        return handle

    async def watch_presence(
        self, key_expr: str, *, history: bool = True, buffer_size: int = 4096
    ) -> Subscription[Presence]:
        """Presence changes on ``key_expr`` (the retained ones first, if ``history``)."""
        _, loop = self._connected()
        topic = topic_filter(key_expr)
        inbox: Inbox[Presence] = Inbox(loop, buffer_size)
        watcher = _Watcher(inbox, history)

        def remove(f: _Filter) -> None:
            f.watchers.remove(watcher)

        await self._attach(topic, lambda f: f.watchers.append(watcher), remove, resubscribe=history)
        return self._subscription(inbox, lambda: self._detach(topic, remove))


class _Token:
    """One presence token: its own connection, whose last will clears the key."""

    def __init__(self, transport: MqttTransport, key: str) -> None:
        self.transport = transport
        self.key = key
        self.client: aiomqtt.Client | None = None
        self.connection: contextlib.AsyncExitStack | None = None  # disconnects client
        self.task: asyncio.Task[None] | None = None
        self.closing = False
        self.reconnects = 0
        self.end: Callable[[str], None] | None = None  # its handle's, when it cannot go on

    async def connect(self) -> None:
        t = self.transport
        client = t._new_client(
            _connection_id(t.config.client_id),
            will=aiomqtt.Will(self.key, b"", qos=1, retain=True),
        )
        try:
            connection = await _connect(client)
        except aiomqtt.MqttError as exc:
            raise t._error(f"connect for the token on {self.key!r}", exc) from exc
        # kept before announcing: ``clear`` clears and closes it (a cancel while
        # announcing, ``clear``'s of a reconnection too, clears and closes it below)
        self.client, self.connection = client, connection
        try:
            # its own key, to hear another client clear it: refused, nobody would
            # announce it again, so the declaration fails before anything is announced
            refused = _refused(await t._acked(client.subscribe(self.key, qos=1)))
            if refused is None:
                await client.publish(self.key, ALIVE, qos=1, retain=True)
        except aiomqtt.MqttError as exc:
            self.client = self.connection = None
            await _disconnect(client, connection)
            raise t._error(f"declare the token on {self.key!r}", exc) from exc
        except BaseException:
            # cancelled (a start given up) with the alive message maybe out: cleared and
            # closed here, as `clear` does, for nobody else holds this connection when
            # it is a declaration's; a reconnection's is cleared here too, not by `clear`
            self.client = self.connection = None
            with contextlib.suppress(aiomqtt.MqttError):  # not out in time: the will clears
                await client.publish(self.key, b"", qos=0, retain=True, timeout=_DISCONNECT_WAIT)
            await _disconnect(client, connection)
            raise
        if refused is not None:
            # a DISCONNECT, not a lost connection: the will (clearing a key never
            # announced here) does not go out either
            self.client = self.connection = None
            await _disconnect(client, connection)
            raise _refusal(self.key, refused)

    async def keep(self) -> None:
        """Announce again when the key is cleared by another; reconnect when dropped."""
        while not self.closing:
            client, connection = self.client, self.connection
            assert client is not None and connection is not None
            try:
                async for message in client.messages:
                    if not message.payload and not self.closing:
                        log.warning("mqtt: presence %r cleared by another client", self.key)
                        await client.publish(self.key, ALIVE, qos=1, retain=True)
                return
            except aiomqtt.MqttError as exc:
                if self.closing or self.transport._state != "opened":
                    return
                log.warning("mqtt: the token's connection on %r was lost: %s", self.key, exc)
            # gone (the broker's will clears the key): nothing for `clear` to clear on it,
            # should the token end or close before it is connected again
            self.client = self.connection = None
            await _disconnect(client, connection)
            # announced again only once this platform answers again (queries, DF)
            up = self.transport._up
            if up is not None:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(self.transport.config.connect_timeout):
                        await asyncio.sleep(0.1)  # the main connection's loss may come next
                        await up.wait()
            try:
                await self.connect()
            except TransportError as exc:
                log.warning("mqtt: could not announce %r again: %s", self.key, exc)
                if self.end is not None:  # its owner learns it is no longer announced
                    self.end(f"{exc} (after reconnecting)")
                return
            self.reconnects += 1

    async def clear(self) -> None:
        self.closing = True
        task = self.task
        if task is not None and task is not asyncio.current_task() and not task.done():
            # a reconnection under way would otherwise announce again on a connection
            # nobody clears or closes: alive for as long as this process runs
            task.cancel()
            await asyncio.wait([task], timeout=self.transport.config.connect_timeout)
        client, connection = self.client, self.connection
        if client is None or connection is None:
            return
        try:
            # QoS 0: the broker's acknowledgement adds nothing. It reads the clear before
            # the disconnect that follows on the same connection; a connection lost before
            # either is read fires the last will, which clears the key too. Waiting for it
            # made each close over a slow broker wait up to connect_timeout, one by one.
            await client.publish(self.key, b"", qos=0, retain=True)
        except aiomqtt.MqttError as exc:
            log.warning("mqtt: could not clear the token on %r: %s", self.key, exc)
        finally:
            await _disconnect(client, connection)


async def _closing(handle: Handle) -> None:
    """Close ``handle`` on the transport's way out; a failure (the broker gone) is no error."""
    try:
        await handle.aclose()
    except Exception as exc:
        log.debug("mqtt: closing a token on the way out: %s", exc)


def _refused(granted: Any) -> str | None:
    """The broker's reason for refusing a subscription, from its SUBACK's codes; None: granted.

    A reason code of 0x80 or more is a refusal (MQTT v5: 0x87 not authorized, 0x8F topic
    filter invalid, 0x97 quota exceeded, ...); v3.1.1 has only 0x80.
    """
    for code in granted or ():
        value = getattr(code, "value", code)
        if isinstance(value, int) and value >= 0x80:
            return f"{code} (0x{value:02X})"
    return None


def _refusal(topic: str, reason: str) -> TransportError:
    return TransportError(f"mqtt: the broker refused the subscription to {topic!r}: {reason}")


def _sid(sid: int) -> Properties:
    props = Properties(PacketTypes.SUBSCRIBE)
    props.SubscriptionIdentifier = sid
    return props


async def _connect(client: aiomqtt.Client) -> contextlib.AsyncExitStack:
    """Connect ``client``; closing the returned stack disconnects it.

    Disconnecting also waits for the client's socket task, so nothing outlives the
    transport; the stack outlives this call because a connection outlives any one task.
    """
    try:
        async with contextlib.AsyncExitStack() as stack:
            stack.push_async_callback(_reap_misc_task, client)  # runs after the client's exit
            await stack.enter_async_context(client)
            _no_delay(client)
            return stack.pop_all()
    except BaseException:
        # refused, timed out or cancelled (a close while reconnecting): aiomqtt leaves its
        # socket open, watched by the loop, and its task running, for the process's life
        await _abandon(client)
        raise


async def _abandon(client: aiomqtt.Client) -> None:
    """Close the socket and end aiomqtt's task of a connection that did not come up.

    When paho's connect is still in its thread (TLS's handshake: the open given up shut
    its connection down, which ends it), this returns at once: the socket is closed on
    the loop when the connect returns, and aiomqtt's task ends with it. Waiting for it
    held the caller (a cancelled open) up to ``connect_timeout``.
    """
    ended = getattr(client, "_connect_ended", None)
    if isinstance(ended, threading.Event) and not ended.is_set():
        getattr(client, "_give_up")()  # noqa: B009  our client's, not aiomqtt's
        return
    await asyncio.sleep(0)  # what the connect scheduled on the loop (its reader, task) runs
    sock_close = getattr(client._client, "_sock_close", None)
    if sock_close is not None:
        with contextlib.suppress(OSError):
            sock_close()
    await _reap_misc_task(client)


async def _disconnect(client: aiomqtt.Client, connection: contextlib.AsyncExitStack) -> None:
    """Disconnect ``client`` (closing ``connection``): gracefully, or drop its socket.

    The DISCONNECT goes out at once unless the socket's buffer is full: a broker that
    stopped reading while this client had much to send (a flood, a stalled broker).
    aiomqtt would then wait ``connect_timeout`` for it, one connection after another (a
    close of several platforms: tens of seconds); past `_DISCONNECT_WAIT` the socket is
    closed instead, which the broker sees as a lost connection (a token's last will
    then clears its key, as the DISCONNECT's clear would have).
    """
    try:
        async with asyncio.timeout(_DISCONNECT_WAIT):
            await connection.aclose()
        return
    except (aiomqtt.MqttError, TimeoutError) as exc:
        log.debug("mqtt: no graceful disconnect (%s): closing the socket", str(exc) or "timed out")
    # paho's own socket close: it also tells aiomqtt to stop watching the socket
    sock_close = getattr(client._client, "_sock_close", None)
    if sock_close is not None:
        with contextlib.suppress(OSError):
            sock_close()


async def _reap_misc_task(client: aiomqtt.Client) -> None:
    # aiomqtt cancels its misc-loop task through call_soon_threadsafe and returns
    # before the task has ended; a caller checking for leaked tasks would see it.
    misc = getattr(client, "_misc_task", None)
    if isinstance(misc, asyncio.Task) and not misc.done():
        misc.cancel()
        await asyncio.wait([misc], timeout=1.0)


def _no_delay(client: aiomqtt.Client) -> None:
    """Turn off Nagle's algorithm on the client's socket (paho leaves it on).

    Small request/reply messages otherwise meet the peer's delayed ACK: 40 ms stalls that
    took the p99 round trip from ~2 ms to ~43 ms.
    """
    setsockopt = getattr(client._client.socket(), "setsockopt", None)  # None: not TCP
    if setsockopt is not None:
        with contextlib.suppress(OSError):
            setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
