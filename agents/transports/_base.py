"""The one transport interface, and the inbox every implementation delivers into.

Key expressions use zenoh's syntax everywhere (``/``-separated chunks, ``*`` matches one
chunk, ``**`` any number); the MQTT transport maps them to ``+`` and ``#``.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import contextlib
import logging
import random
import socket
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, Generic, NamedTuple, Self, TypeVar

from .._aio import KeepCancelled
from .._exceptions import TransportClosed, TransportError

log = logging.getLogger(__name__)

T = TypeVar("T")


class Message(NamedTuple):
    """What a subscription yields: the key it was published under, payload, attachment."""

    key: str
    payload: bytes
    attachment: bytes | None = None


class Reply(NamedTuple):
    """One reply to a query: the replier's key and payload; ``ok`` is False for an error reply."""

    key: str
    payload: bytes
    ok: bool = True


class Presence(NamedTuple):
    """A liveliness change: the token's key, and whether it appeared (True) or went (False)."""

    key: str
    alive: bool


QueryHandler = Callable[[str, bytes], Awaitable[bytes | None]]
"""Answers a query: gets the query's key and payload, returns the reply (None: no reply)."""

QueryFilter = Callable[[bytes], bool]
"""Screens a query's (or a published message's) payload where it arrives (the library's
receiving thread, any thread), before it is queued for the event loop: False drops it
(a query unanswered). Thread-safe, cheap, never raises."""


class Inbox(Generic[T]):
    """A bounded queue filled from any thread and drained by one asyncio consumer.

    Transport callbacks run on the library's threads. Waking the loop for every item
    (``call_soon_threadsafe``) caps at ~70-100 k items/s; here the producer appends to a
    deque and wakes the loop only when the consumer is waiting and no wake-up is already
    pending, which keeps up with several hundred thousand items/s. When full, the oldest
    item is dropped and counted: a producer never blocks on a slow consumer.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        maxlen: int = 65536,
        convert: Callable[[Any], T] | None = None,
        dropped: Callable[[Any], None] | None = None,
    ) -> None:
        self._loop = loop
        # told of each item dropped when full (under the inbox's lock: cheap, never raising)
        self._on_drop = dropped
        # With ``convert``, the producer puts the library's raw objects and the consumer
        # converts them on the way out: the producer's thread (and the GIL) is held less.
        self._convert = convert
        self._items: deque[Any] = deque()
        self._maxlen = maxlen
        self._lock = threading.Lock()
        self._waiter: asyncio.Future[None] | None = None
        # The loop's thread, recorded by the consumer (which runs in it): a producer in
        # that thread wakes the consumer directly, others through call_soon_threadsafe.
        self._loop_thread: int | None = None
        self._wake_pending = False
        self.dropped = 0
        self.received = 0
        self.closed = False

    def put(self, item: T) -> None:
        """Add an item (from any thread); drops the oldest when full."""
        with self._lock:
            if self.closed:
                return
            if len(self._items) >= self._maxlen:
                lost = self._items.popleft()
                self.dropped += 1
                if self._on_drop is not None:
                    self._on_drop(lost)
            self._items.append(item)
            self.received += 1
            if self._waiter is None or self._wake_pending:
                return
            self._wake_pending = True
        self._wake_threadsafe()

    def _wake_threadsafe(self) -> None:
        try:
            if threading.get_ident() == self._loop_thread:
                self._wake()
            else:
                self._loop.call_soon_threadsafe(self._wake)
        except RuntimeError:  # the loop is closed: nobody is waiting any more
            pass

    def _wake(self) -> None:
        with self._lock:
            self._wake_pending = False
            w = self._waiter
            # the consumer's wait ends here: it need not take the lock again to say so
            self._waiter = None
        if w is not None and not w.done():
            w.set_result(None)

    def close(self) -> None:
        """End the consumer's iteration once it has drained what is queued (any thread)."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            waiting = self._waiter is not None
        if waiting:
            self._wake_threadsafe()

    def get(self) -> Coroutine[Any, Any, T]:
        """The next item (await it); TransportClosed once closed and drained."""
        return self._get(TransportClosed)

    async def _get(self, end: type[Exception]) -> T:
        """`get`, raising ``end`` once closed and drained (StopAsyncIteration for a loop)."""
        while True:
            with self._lock:
                if self._items:
                    item = self._items.popleft()
                    return item if self._convert is None else self._convert(item)
                if self.closed:
                    raise end("subscription closed")
                self._waiter = self._loop.create_future()
                waiter = self._waiter
                if self._loop_thread is None:
                    self._loop_thread = threading.get_ident()
            try:
                await waiter
            except BaseException:  # cancelled: no wake-up cleared it
                with self._lock:
                    if self._waiter is waiter:
                        self._waiter = None
                raise

    def put_front(self, items: list[T]) -> None:
        """Put ``items`` back before everything queued, in order (any thread); never drops.

        For a consumer's own items it took aside and hands back to be taken next: they
        were counted in ``received`` when first put.
        """
        with self._lock:
            self._items.extendleft(reversed(items))
            if self._waiter is None or self._wake_pending:
                return
            self._wake_pending = True
        self._wake_threadsafe()

    def take(self, limit: int) -> list[T]:
        """Up to ``limit`` of the items queued now, oldest first, without waiting.

        For a consumer that handles what arrived in one go: one lock, not one per item.
        """
        with self._lock:
            items = self._items
            popleft = items.popleft
            got = [popleft() for _ in range(min(limit, len(items)))]
        convert = self._convert
        return got if convert is None else [convert(i) for i in got]

    def drain(self) -> list[T]:
        """Everything queued now, without waiting."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items if self._convert is None else [self._convert(i) for i in items]

    def __len__(self) -> int:
        return len(self._items)


class Screened:
    """An inbox behind its subscription's ``admit``: what that refuses is never queued."""

    __slots__ = ("admit", "inbox")

    def __init__(self, inbox: Inbox[Message], admit: QueryFilter) -> None:
        self.inbox = inbox
        self.admit = admit

    def put(self, msg: Message) -> None:
        """Queue ``msg`` if ``admit`` lets its payload through."""
        if self.admit(msg.payload):
            self.inbox.put(msg)


class Subscription(Generic[T]):
    """An async iterator over what a transport delivers; ends cleanly when closed.

    Use as ``async with await transport.subscribe(k) as sub: async for m in sub: …``.
    """

    def __init__(self, inbox: Inbox[T], on_close: Callable[[], None]) -> None:
        self.inbox = inbox
        self._on_close = on_close
        self._closed = False

    def __aiter__(self) -> Self:
        return self

    def __anext__(self) -> Coroutine[Any, Any, T]:
        # the inbox's own coroutine: no second one per item to translate its end
        return self.inbox._get(StopAsyncIteration)

    async def get(self, timeout: float | None = None) -> T:
        """The next item, TimeoutError after ``timeout`` s, TransportClosed at the end."""
        async with asyncio.timeout(timeout):
            return await self.inbox.get()

    @property
    def dropped(self) -> int:
        """Items lost because the consumer fell behind."""
        return self.inbox.dropped

    @property
    def closed(self) -> bool:
        """Whether `close` closed it; an iterator that ended otherwise, the transport ended."""
        return self._closed

    def close(self) -> None:
        """Stop receiving; the iterator ends after what is queued."""
        if self._closed:
            return
        self._closed = True
        try:
            self._on_close()
        finally:
            self.inbox.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


class Replies(Subscription[Reply]):
    """The replies to one query, as they come (see `Transport.ask`); ends with the query.

    Use as ``async with await transport.ask(k, p, timeout=t) as replies: async for r in
    replies: …``; leaving the block early ends the query (late replies are dropped).
    """

    def __init__(
        self,
        inbox: Inbox[Reply],
        on_close: Callable[[], None],
        on_aclose: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        super().__init__(inbox, on_close)
        self._on_aclose = on_aclose

    async def aclose(self) -> None:
        """End the query and wait until it is over (memory: until its handlers ended)."""
        self.close()
        if self._on_aclose is not None:
            await self._on_aclose()

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()


class Handle:
    """Something declared on a transport (a queryable, a liveliness token): close to undeclare.

    ``on_aclose``, when given, is the asynchronous way to undeclare (for transports whose
    undeclaring needs I/O, like MQTT's); ``close`` then only starts it. A transport that
    can no longer serve it ends it itself (`_end`): ``closed``, ``ended`` says why, and
    the ``on_end`` callbacks are called.
    """

    def __init__(
        self,
        on_close: Callable[[], None],
        on_aclose: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        self._on_close = on_close
        self._on_aclose = on_aclose
        self.closed = False
        self.ended: str | None = None  # why the transport ended it; None: it did not
        self._on_end: list[Callable[[str], None]] = []

    def on_end(self, callback: Callable[[str], None]) -> None:
        """Have ``callback(reason)`` called if the transport ends this itself, never at a close.

        At once when it ended already. Only MQTT ends one: a queryable whose topic filter
        the broker refuses when subscribed anew after a reconnection, a liveliness token
        that cannot announce itself again after its connection dropped, and every one
        when the transport's connection dropped and could not be made again.
        """
        if self.ended is not None:
            callback(self.ended)
        elif not self.closed:
            self._on_end.append(callback)

    def _end(self, reason: str) -> None:
        """Undeclared by the transport itself, for ``reason``: closed, its owner told."""
        if self.closed:
            return
        self.close()
        self.ended = reason
        callbacks, self._on_end = self._on_end, []
        for callback in callbacks:
            try:
                callback(reason)
            except Exception:  # one owner's bug must not keep the others untold
                log.warning("a callback told that a declaration ended raised", exc_info=True)

    def close(self) -> None:
        """Undeclare it."""
        if not self.closed:
            self.closed = True
            self._on_close()

    async def aclose(self) -> None:
        """Undeclare it and wait until that is done."""
        if self.closed:
            return
        if self._on_aclose is None:
            self.close()
            return
        self.closed = True
        await self._on_aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()


class _Keeps:
    """What a transport declared and ends when it closes: subscriptions and handles (sets)."""

    _subs: set[Subscription[Any]]
    _handles: set[Handle]

    def _subscription(self, inbox: Inbox[T], undeclare: Callable[[], None]) -> Subscription[T]:
        """A subscription that this transport ends when it closes."""
        sub: Subscription[T]

        def on_close() -> None:
            self._subs.discard(sub)
            undeclare()

        sub = Subscription(inbox, on_close)
        self._subs.add(sub)
        return sub

    def _handle(
        self, undeclare: Callable[[], None], aundeclare: Callable[[], Awaitable[None]] | None = None
    ) -> Handle:
        """A handle that this transport closes when it closes."""
        handle: Handle

        def on_close() -> None:
            self._handles.discard(handle)
            undeclare()

        async def on_aclose() -> None:
            self._handles.discard(handle)
            assert aundeclare is not None
            await aundeclare()

        handle = Handle(on_close, on_aclose if aundeclare is not None else None)
        self._handles.add(handle)
        return handle


class Transport(ABC):
    """Moves bytes between platforms: publish/subscribe, query/serve, liveliness.

    A transport is an async context manager: entering opens it (connects), leaving
    closes it and ends every subscription; it cannot be reopened. Errors of the
    underlying library are raised as TransportError.
    """

    name = "transport"
    forgeable_presence = False
    """True when any client may make a presence look gone (MQTT: an empty retained message).

    On zenoh (and in memory) a presence is gone only when every token on the key is: a
    client may add a token, never remove another's.
    """
    asks_end_when_answered = True
    """Whether an `ask` ends once every queryable that heard it answered (zenoh, memory).

    False on MQTT, which cannot tell how many heard it. On any transport a queryable that
    never answers (anyone may declare one) holds an `ask` to its timeout: a caller that
    knows whom to expect (the tokens alive, `tokens`) leaves once they answered.
    """

    def __init__(self) -> None:
        self._state = "unopened"
        self._tg: asyncio.TaskGroup | None = None
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group
        self._tasks: set[asyncio.Task[Any]] = set()

    async def __aenter__(self) -> Self:
        if self._state != "unopened":
            raise TransportClosed(f"{self.name} transport is {self._state}; it cannot reopen")
        await self.open()
        self._state = "opened"
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def _check_open(self) -> None:
        if self._state != "opened":
            raise TransportClosed(f"{self.name} transport is {self._state}")

    # -- the transport's own tasks (for implementations that need some) ------------------

    async def _start_tasks(self) -> None:
        """Enter the task group that owns this transport's tasks (from ``open``)."""
        async with contextlib.AsyncExitStack() as stack:
            self._tg = await stack.enter_async_context(asyncio.TaskGroup())
            self._stack = stack.pop_all()

    def _spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any]:
        """Run ``coro`` as a task of this transport, named ``name``; failures are logged.

        The task is cancelled when the transport closes. A failure is logged and ends that
        task only: the others, and whoever opened the transport, go on.
        """
        if self._tg is None:
            coro.close()  # never to run: not left to warn that it was never awaited
            raise TransportClosed(f"{self.name} transport is {self._state}")
        task = self._tg.create_task(_logged(coro, name), name=name)
        # cancelled before it ran, the wrapper never awaits ``coro``: close it then
        task.add_done_callback(lambda _: coro.close())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _end_tasks(self) -> None:
        """Cancel this transport's tasks and wait until they are done (from ``aclose``)."""
        for task in list(self._tasks):
            task.cancel()
        stack, self._stack, self._tg = self._stack, None, None
        if stack is not None:
            again = KeepCancelled(lambda: self._tasks)  # one that lost it: `KeepCancelled`
            try:
                await stack.aclose()
            finally:
                again.stop()

    @abstractmethod
    async def open(self) -> None:
        """Connect (called by ``__aenter__``)."""

    @abstractmethod
    async def aclose(self) -> None:
        """Close everything declared on this transport and disconnect."""

    @abstractmethod
    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Send ``payload`` to every subscriber whose key expression matches ``key``."""

    async def publish_blocking(
        self, key: str, payload: bytes | Callable[[], Awaitable[bytes]]
    ) -> None:
        """Publish ``payload``, waiting for room on the way rather than dropping it.

        For what a receiver asked for and is waiting for (a resend): `publish` may drop
        what a congested link cannot take at once, so that a frozen subscriber never
        stalls the publisher; this waits instead, within the transport's own bound
        (zenoh: 5 s for room in its queue), and never blocks the event loop. Here, and
        on transports whose `publish` never drops (MQTT, memory), it is `publish`.

        ``payload`` may be a function making it, awaited once the put can start: an
        envelope sealed then carries the time and counter it leaves with, not those of
        when it began to wait (behind other receivers' puts), which the receiver's skew
        and replay window would refuse.
        """
        await self.publish(key, payload if isinstance(payload, bytes) else await payload())

    @property
    def publishes_nowait(self) -> bool:
        """Whether `publish_nowait` works here: a put that never waits for the event loop.

        True on zenoh and in memory, unless a subclass overrides ``publish`` (a test's
        lossy link must see every put) without overriding this too.
        """
        return False

    def publish_nowait(self, key: str, payload: bytes) -> None:
        """Publish ``payload`` at once, from the loop's thread (see `publishes_nowait`).

        For callers that batch: a batch goes out from a loop callback, in order with what
        `publish` sent before it. Errors as `publish`; TransportError where unsupported.
        """
        raise TransportError(f"{self.name} transport cannot publish without waiting")

    async def subscribe_taking(
        self,
        key_expr: str,
        take: Callable[[bytes], Any],
        *,
        buffer_size: int = 65536,
        dropped: Callable[[Any], None] | None = None,
    ) -> Subscription[Any] | None:
        """`subscribe`, each payload given to ``take`` on the transport's own receiving thread.

        ``take`` returns what to queue for the event loop (as is), or None when it dealt
        with the payload there; ``dropped`` is told of each item the full queue drops
        (`Inbox`). None (here): this transport has no receiving thread of its own (the
        memory hub calls back on the loop, MQTT's client is read by it).
        """
        return None

    def declared_publisher(self, key: str) -> Callable[[bytes], None] | None:
        """A put on ``key`` that any thread may call, if its publisher is already declared.

        None: none is (declaring changes the transport's state: only the event loop's
        `publish` does it), or this transport cannot publish from another thread. The put
        raises as `publish` does.
        """
        return None

    def has_subscribers(self, key: str) -> bool:
        """Whether a put on ``key`` now may reach a subscriber; True when the transport cannot tell.

        For a publisher that would rather skip work nobody receives (the Interface Agent's
        audit batches). zenoh knows (the matching status its put is routed by), as does
        the memory hub; MQTT does not, so the answer there is always True.
        """
        return True

    @abstractmethod
    async def subscribe(
        self, key_expr: str, *, buffer_size: int = 65536, admit: QueryFilter | None = None
    ) -> Subscription[Message]:
        """Receive what is published under keys matching ``key_expr``.

        ``admit`` screens each payload where it arrives, before it is queued: one it
        refuses is dropped there (neither queued nor counted in ``dropped``).
        """

    @abstractmethod
    async def ask(self, key_expr: str, payload: bytes = b"", *, timeout: float) -> Replies:
        """Ask every queryable matching ``key_expr``; its replies as they come.

        The iteration ends once every queryable answered (zenoh, memory), at the latest
        after ``timeout`` s (always then on MQTT, which cannot tell how many queryables
        heard the query, and anywhere one never answers); a caller that has what it needs
        leaves early, which ends the query. Errors sending the query are raised here, not
        by the iteration.
        """

    async def query(self, key_expr: str, payload: bytes = b"", *, timeout: float) -> list[Reply]:
        """Ask every queryable matching ``key_expr``; all the replies `ask` yields."""
        async with await self.ask(key_expr, payload, timeout=timeout) as replies:
            return [reply async for reply in replies]

    @abstractmethod
    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Answer queries on ``key_expr`` with ``handler``; ``admit`` screens them first."""

    @abstractmethod
    async def declare_token(self, key: str) -> Handle:
        """Announce presence under ``key`` until closed or this process dies."""

    @abstractmethod
    async def watch_presence(
        self, key_expr: str, *, history: bool = True, buffer_size: int = 4096
    ) -> Subscription[Presence]:
        """Be told when tokens matching ``key_expr`` appear and go (the current ones first)."""

    async def tokens(
        self, key_expr: str, *, timeout: float, keep: Callable[[str], bool] | None = None
    ) -> list[str]:
        """The keys of the tokens matching ``key_expr`` alive now, as known by ``timeout`` s.

        zenoh asks its peers and routers and returns once they all answered; MQTT once
        the broker has sent its retained ones. ``keep`` (cheap, never raising) screens
        the keys: only those it keeps are answered, and on a transport that bounds what
        it remembers (MQTT) others cannot crowd them out. This default, for a transport
        whose history has no end, listens to `watch_presence` for ``timeout`` s.
        """
        presence = await self.watch_presence(key_expr, history=True)
        alive: set[str] = set()
        try:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(timeout):
                    async for change in presence:
                        if keep is None or keep(change.key):
                            (alive.add if change.alive else alive.discard)(change.key)
        finally:
            presence.close()
        return sorted(alive)


def key_matches(key_expr: str, key: str) -> bool:
    """Whether concrete ``key`` matches zenoh-style ``key_expr`` (``*`` one chunk, ``**`` any)."""
    return _match(key_expr.split("/"), key.split("/"))


def key_intersects(a: str, b: str) -> bool:
    """Whether two zenoh-style key expressions (wildcards on either side) share a key."""
    # A walk over (chunk of a, chunk of b) pairs, each visited once: O(len(a) * len(b)).
    # Either key may come from anyone on the network (an MQTT query's ``key``): a
    # recursion over `**` chunks took exponential time, or blew the stack, on a long one.
    x, y = a.split("/"), b.split("/")
    n, m = len(x), len(y)
    todo, seen = [(0, 0)], set()
    while todo:
        state = todo.pop()
        if state in seen:
            continue
        seen.add(state)
        i, j = state
        if i == n and j == m:
            return True
        xi = x[i] if i < n else None
        yj = y[j] if j < m else None
        if xi == "**":
            todo.append((i + 1, j))  # matching no chunk
            if yj is not None:
                todo.append((i, j + 1))  # taking b's chunk
        if yj == "**":
            todo.append((i, j + 1))
            if xi is not None:
                todo.append((i + 1, j))
        if (
            xi is not None
            and yj is not None
            and "**" not in (xi, yj)
            and (xi == "*" or yj == "*" or xi == yj)
        ):
            todo.append((i + 1, j + 1))
    return False


_PORTS_FROM = 10_000  # free_tcp_port picks from here up to the ephemeral range
_handed_ports: set[int] = set()
_ports_lock = threading.Lock()
_port_random = random.SystemRandom()  # not the global generator: tests seed that one


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now, for a listener of this process (tests, local setups).

    It is below the system's ephemeral range: a port from ``bind(0)`` would be free to
    be given to any other socket's ``bind(0)`` or outgoing connection between this call
    and the caller's listen. Never the same port twice in one process.
    """
    end = _ephemeral_start()
    with _ports_lock:
        for _ in range(1000):
            port = _port_random.randrange(_PORTS_FROM, end) if end > _PORTS_FROM else 0
            if port in _handed_ports:
                continue
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                try:
                    s.bind((host, port))
                except OSError:  # in use, or kept by a recent connection
                    continue
                port = int(s.getsockname()[1])
            _handed_ports.add(port)
            return port
    raise OSError(f"no free TCP port on {host}")


def _ephemeral_start() -> int:
    """The first port of the range the kernel picks from for ``bind(0)`` and connections."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default; BSDs and macOS start higher


def _match(pat: list[str], key: list[str]) -> bool:
    if not pat:
        return not key
    head = pat[0]
    if head == "**":
        return any(_match(pat[1:], key[i:]) for i in range(len(key) + 1))
    if not key:
        return False
    if head == "*" or head == key[0]:
        return _match(pat[1:], key[1:])
    return False


def _ignore(*_: Any) -> None:
    """A no-op close callback."""


async def _logged(coro: Awaitable[Any], name: str) -> None:
    try:
        await coro
    except Exception:
        log.exception("transport task %s failed", name)
