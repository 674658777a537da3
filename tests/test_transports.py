"""The same conformance tests over every transport: memory, zenoh and MQTT (own mosquitto)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import pytest
from pydantic import ValidationError

from agents._exceptions import TransportClosed, TransportError
from agents.transports import (
    MemoryHub,
    Message,
    MqttConfig,
    MqttTransport,
    Presence,
    Reply,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
    key_intersects,
)
from agents.transports._base import Inbox
from agents.transports._mqtt import (
    _MAX_PRESENCE_KEYS,
    _Watcher,
    query_topic,
    queryable_filters,
    topic_filter,
)

T = TypeVar("T")

WAIT = 10.0  # the bound on any single wait: generous for a loaded 2-core machine


@dataclass
class Net:
    """One network of transports of one kind, and a key prefix of this test's own."""

    kind: str
    prefix: str
    query_timeout: float
    make: Callable[..., Transport]
    opened: list[Transport] = field(default_factory=list)

    async def open(self, **options: Any) -> Transport:
        t = self.make(**options)
        await t.__aenter__()
        self.opened.append(t)
        return t

    def key(self, rest: str) -> str:
        return f"{self.prefix}/{rest}"


def _zenoh_factory() -> Callable[..., Transport]:
    seed = free_tcp_port()
    made = 0

    def make(**options: Any) -> Transport:
        nonlocal made
        made += 1
        if made == 1:
            return ZenohTransport(ZenohConfig.loopback(seed, **options))
        return ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed], **options))

    return make


def _mqtt_factory(host: str, port: int) -> Callable[..., Transport]:
    def make(**options: Any) -> Transport:
        return MqttTransport(MqttConfig(host=host, port=port, keepalive=5, **options))

    return make


@pytest.fixture(params=["memory", "zenoh", "mqtt"])
async def net(request: pytest.FixtureRequest) -> AsyncIterator[Net]:
    kind = request.param
    prefix = f"test/{uuid.uuid4().hex[:10]}"
    make: Callable[..., Transport]
    if kind == "memory":
        hub = MemoryHub()
        make = lambda **_: hub.transport()  # noqa: E731
        query_timeout = 5.0
    elif kind == "zenoh":
        make = _zenoh_factory()
        query_timeout = 5.0  # zenoh returns as soon as every queryable has answered
    else:
        host, port = request.getfixturevalue("mosquitto")
        make = _mqtt_factory(host, port)
        query_timeout = 0.5  # MQTT always waits until the timeout
    n = Net(kind, prefix, query_timeout, make)
    try:
        yield n
    finally:
        for t in reversed(n.opened):
            await t.aclose()


@pytest.fixture(params=["zenoh", "mqtt"])
async def remote_net(request: pytest.FixtureRequest) -> AsyncIterator[Net]:
    """Only the transports that talk through the network (settings such as serve_timeout)."""
    prefix = f"test/{uuid.uuid4().hex[:10]}"
    if request.param == "zenoh":
        n = Net("zenoh", prefix, 5.0, _zenoh_factory())
    else:
        host, port = request.getfixturevalue("mosquitto")
        n = Net("mqtt", prefix, 0.5, _mqtt_factory(host, port))
    try:
        yield n
    finally:
        for t in reversed(n.opened):
            await t.aclose()


async def ready(net: Net, observer: Transport, *others: Transport) -> None:
    """Wait until ``observer`` knows everything the ``others`` declared so far.

    Each of the others declares a liveliness token after its subscribers and queryables;
    zenoh propagates declarations in order, so once the observer sees the tokens it routes
    to what was declared before them. (MQTT and memory need no wait; it costs them little.)
    """
    tag = uuid.uuid4().hex[:8]
    watch = await observer.watch_presence(net.key(f"ready-{tag}/*"))
    tokens = [await t.declare_token(net.key(f"ready-{tag}/{i}")) for i, t in enumerate(others)]
    try:
        seen: set[str] = set()
        async with asyncio.timeout(WAIT):
            while len(seen) < len(others):
                p = await watch.get()
                if p.alive:
                    seen.add(p.key)
    finally:
        watch.close()
        for tok in tokens:
            await tok.aclose()


async def take(sub: Subscription[T], n: int) -> list[T]:
    async with asyncio.timeout(WAIT):
        return [await sub.get() for _ in range(n)]


async def drain_until_end(sub: Subscription[T]) -> list[T]:
    async with asyncio.timeout(WAIT):
        return [m async for m in sub]


# --- publish / subscribe ---------------------------------------------------------------------


async def test_pubsub_wildcards(net: Net) -> None:
    a, b = await net.open(), await net.open()
    one = await a.subscribe(net.key("p/*/x"))
    many = await a.subscribe(net.key("p/**"))
    await ready(net, b, a)
    for k in ("p/a/x", "p/a/y", "p/a/b/x", "q/a/x"):
        await b.publish(net.key(k), k.encode())
    await b.publish(net.key("p/end/x"), b"end", attachment=b"att")

    got_one = await take(one, 2)
    assert [m.key for m in got_one] == [net.key("p/a/x"), net.key("p/end/x")]
    got_many = await take(many, 4)
    assert [m.payload for m in got_many] == [b"p/a/x", b"p/a/y", b"p/a/b/x", b"end"]
    assert got_many[0] == Message(net.key("p/a/x"), b"p/a/x", None)
    assert got_many[-1].attachment == b"att"


async def test_publish_blocking_delivers_in_order_and_leaves_the_loop_free(net: Net) -> None:
    # what a receiver asked for (a resend): waits for room rather than being dropped
    a, b = await net.open(), await net.open()
    sub = await a.subscribe(net.key("blk/*"))
    await ready(net, b, a)
    ticks = 0

    async def tick() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0)

    ticker = asyncio.create_task(tick())
    try:
        for i in range(50):
            await b.publish_blocking(net.key(f"blk/{i}"), b"x" * 60_000 + bytes([i]))
    finally:
        ticker.cancel()
    got = await take(sub, 50)
    assert [m.payload[-1] for m in got] == list(range(50))
    assert ticks > 0 or net.kind != "zenoh"  # zenoh's puts ran off the loop

    async def made() -> bytes:  # a payload made when the put can start (a sealed resend)
        return b"made"

    await b.publish_blocking(net.key("blk/made"), made)
    assert [m.payload for m in await take(sub, 1)] == [b"made"]
    await b.aclose()
    with pytest.raises(TransportClosed):
        await b.publish_blocking(net.key("blk/x"), b"")


async def test_two_subscribers(net: Net) -> None:
    a, b, c = await net.open(), await net.open(), await net.open()
    key = net.key("s/k")
    sub_a = await a.subscribe(key)
    sub_a2 = await a.subscribe(key)  # the same key twice in one transport
    sub_c = await c.subscribe(net.key("s/*"))
    await ready(net, b, a, c)
    payloads = [str(i).encode() for i in range(50)]
    for p in payloads:
        await b.publish(key, p)
    for sub in (sub_a, sub_a2, sub_c):
        assert [m.payload for m in await take(sub, len(payloads))] == payloads


async def test_admit_screens_published_messages_before_they_are_queued(net: Net) -> None:
    """A message ``admit`` refuses is neither queued nor counted as dropped; others arrive."""
    a, b = await net.open(), await net.open()
    sub = await a.subscribe(net.key("sg/*"), admit=lambda p: not p.startswith(b"junk"))
    plain = await a.subscribe(net.key("sg/*"))
    await ready(net, b, a)
    for p in (b"junk-1", b"one", b"junk-2", b"two"):
        await b.publish(net.key("sg/k"), p)
    assert [m.payload for m in await take(plain, 4)] == [b"junk-1", b"one", b"junk-2", b"two"]
    assert [m.payload for m in await take(sub, 2)] == [b"one", b"two"]
    assert sub.inbox.received == 2 and sub.dropped == 0
    sub.close()
    await b.publish(net.key("sg/k"), b"three")
    assert [m.payload for m in await take(plain, 1)] == [b"three"]
    assert await drain_until_end(sub) == []


async def test_unsubscribe(net: Net) -> None:
    a, b = await net.open(), await net.open()
    key = net.key("u/k")
    gone = await a.subscribe(key)
    stays = await a.subscribe(key)
    await ready(net, b, a)
    await b.publish(key, b"1")
    assert [m.payload for m in await take(gone, 1)] == [b"1"]
    gone.close()
    await b.publish(key, b"2")
    assert [m.payload for m in await take(stays, 2)] == [b"1", b"2"]
    assert await drain_until_end(gone) == []
    # The last subscriber of a key goes, and a new one comes at once: it must not miss out.
    stays.close()
    again = await a.subscribe(key)
    await ready(net, b, a)
    await b.publish(key, b"3")
    assert [m.payload for m in await take(again, 1)] == [b"3"]
    assert [m.payload for m in await drain_until_end(stays)] == []


async def test_has_subscribers_follows_the_subscriptions_where_the_transport_knows(
    net: Net,
) -> None:
    # what the Interface Agent asks before it seals an audit batch (MQTT cannot tell: True)
    a, b = await net.open(), await net.open()
    key = net.key("h/x")
    knows = net.kind != "mqtt"

    async def says(want: bool) -> None:
        async with asyncio.timeout(WAIT):
            # a transport learns of subscribers with no event to await: poll, briefly
            while b.has_subscribers(key) is not want:  # noqa: ASYNC110
                await asyncio.sleep(0.005)

    assert b.has_subscribers(key) is (not knows)
    sub = await a.subscribe(net.key("h/*"))
    await says(True)
    await b.publish(key, b"heard")
    assert [m.payload for m in await take(sub, 1)] == [b"heard"]
    assert b.has_subscribers(net.key("h/y/z")) is (not knows)  # no match: nobody there
    sub.close()
    await says(not knows)
    await b.aclose()
    if knows:
        with pytest.raises(TransportClosed):
            b.has_subscribers(key)


async def test_iterator_ends_when_subscription_closes(net: Net) -> None:
    a, b = await net.open(), await net.open()
    sub = await a.subscribe(net.key("i/k"))
    await ready(net, b, a)
    received: list[Message] = []
    first = asyncio.Event()

    async def consume() -> None:
        async for m in sub:
            received.append(m)
            first.set()

    async with asyncio.TaskGroup() as tg:
        consumer = tg.create_task(consume())
        await b.publish(net.key("i/k"), b"x")
        async with asyncio.timeout(WAIT):
            await first.wait()
        sub.close()
        async with asyncio.timeout(WAIT):
            await consumer
    assert [m.payload for m in received] == [b"x"]


async def test_transport_close_ends_subscriptions(net: Net) -> None:
    a = await net.open()
    sub = await a.subscribe(net.key("c/**"))
    watch = await a.watch_presence(net.key("c/alive/*"))

    async def consume(s: Subscription[Any]) -> int:
        return len([m async for m in s])

    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(consume(sub)), tg.create_task(consume(watch))]
        await a.aclose()
        async with asyncio.timeout(WAIT):
            counts = [await t for t in tasks]
    assert counts == [0, 0]


# --- query / serve ---------------------------------------------------------------------------


async def test_query_replies_from_two_servers(net: Net) -> None:
    s1, s2, q = await net.open(), await net.open(), await net.open()

    def echo(name: bytes) -> Callable[[str, bytes], Any]:
        async def handler(key: str, payload: bytes) -> bytes:
            return name + b":" + payload

        return handler

    await s1.serve(net.key("svc/a"), echo(b"a"))
    await s2.serve(net.key("svc/b"), echo(b"b"))
    await ready(net, q, s1, s2)

    replies = await q.query(net.key("svc/*"), b"hi", timeout=net.query_timeout)
    assert sorted(replies) == [
        Reply(net.key("svc/a"), b"a:hi"),
        Reply(net.key("svc/b"), b"b:hi"),
    ]
    only_a = await q.query(net.key("svc/a"), b"x", timeout=net.query_timeout)
    assert only_a == [Reply(net.key("svc/a"), b"a:x")]


async def test_ask_yields_each_reply_as_it_comes(net: Net) -> None:
    # a caller need not wait for the slow queryables (nor, on MQTT, the timeout); leaving
    # ends the query, and the transport queries on as before
    s1, s2, q = await net.open(), await net.open(), await net.open()
    release = asyncio.Event()

    async def fast(key: str, payload: bytes) -> bytes:
        return b"fast:" + payload

    async def slow(key: str, payload: bytes) -> bytes:
        await release.wait()
        return b"slow"

    await s1.serve(net.key("ask/fast"), fast)
    await s2.serve(net.key("ask/slow"), slow)
    await ready(net, q, s1, s2)
    started = time.monotonic()
    try:
        async with await q.ask(net.key("ask/*"), b"hi", timeout=WAIT * 2) as replies:
            first = await replies.get(timeout=WAIT)
    finally:
        release.set()
    assert first == Reply(net.key("ask/fast"), b"fast:hi")
    assert time.monotonic() - started < WAIT
    again = await q.query(net.key("ask/fast"), b"x", timeout=net.query_timeout)
    assert again == [Reply(net.key("ask/fast"), b"fast:x")]


@pytest.fixture
async def zenoh_net() -> AsyncIterator[Net]:
    """Zenoh transports only (what is zenoh's own: its threads)."""
    n = Net("zenoh", f"test/{uuid.uuid4().hex[:10]}", 5.0, _zenoh_factory())
    try:
        yield n
    finally:
        for t in reversed(n.opened):
            await t.aclose()


@pytest.mark.parametrize("switch", [None, 0.05], ids=["default-switch", "raised-switch"])
async def test_zenoh_replies_and_tokens_come_whatever_the_switch_interval(
    zenoh_net: Net, switch: float | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An ask's replies come on zenoh's thread up to the switch interval, tokens never do.

    Up to Python's switch interval zenoh's network thread calls an ask's reply callback, a
    Python thread of its own above it; a liveliness get's callback always has its own
    (zenoh calls it holding its session lock): every reply and every token comes either way.
    """
    net = zenoh_net
    s1, s2, q = await net.open(), await net.open(), await net.open()

    async def echo(key: str, payload: bytes) -> bytes:
        return key.encode() + b":" + payload

    for s in (s1, s2):
        await s.serve(net.key(f"sw/{id(s)}"), echo)
        await s.declare_token(net.key(f"alive/{id(s)}"))
    await ready(net, q, s1, s2)
    # which thread put each reply and each token into the asker's inbox
    putters: dict[type, set[threading.Thread]] = {Reply: set(), str: set()}
    put = Inbox.put

    def recorded(inbox: Inbox[Any], item: Any) -> None:
        if type(item) in putters:
            putters[type(item)].add(threading.current_thread())
        put(inbox, item)

    monkeypatch.setattr(Inbox, "put", recorded)
    before = sys.getswitchinterval()
    try:
        if switch is not None:
            sys.setswitchinterval(switch)
        for i in range(20):
            replies = await q.query(net.key("sw/*"), b"%d" % i, timeout=WAIT)
            assert sorted(r.payload.rpartition(b":")[2] for r in replies) == [b"%d" % i] * 2
        tokens = await q.tokens(net.key("alive/*"), timeout=WAIT)
        assert tokens == sorted(net.key(f"alive/{id(s)}") for s in (s1, s2))
    finally:
        sys.setswitchinterval(before)
    # a thread Python did not start is a _DummyThread: zenoh's own
    main = threading.main_thread()
    on_zenoh = {isinstance(t, threading._DummyThread) for t in putters[Reply]}
    assert on_zenoh == {switch is None}, putters
    assert putters[str] and main not in putters[str], putters
    assert not any(isinstance(t, threading._DummyThread) for t in putters[str]), putters


async def test_zenoh_declared_publisher_puts_until_its_publisher_is_undeclared(
    zenoh_net: Net, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A thread's put exists once the loop declared the publisher, and no longer once evicted.

    An evicted publisher was undeclared: a put on it would raise, so there is none (the
    lane leaves its answer to the loop, which declares anew); closing drops them all.
    """
    from agents.transports import _zenoh

    monkeypatch.setattr(_zenoh, "_PUBLISHER_CACHE", 2)
    net = zenoh_net
    rx, tx = await net.open(), await net.open()
    assert isinstance(tx, ZenohTransport)
    first, second, third = (net.key(f"pub/{i}") for i in range(3))
    sub = await rx.subscribe(net.key("pub/*"))
    await ready(net, tx, rx)
    assert tx.declared_publisher(first) is None  # never published: nothing declared
    await tx.publish(first, b"declared")
    put = tx.declared_publisher(first)
    assert put is not None
    await asyncio.to_thread(put, b"from a thread")
    assert [m.payload for m in await take(sub, 2)] == [b"declared", b"from a thread"]
    await tx.publish(second, b"2")
    assert tx.declared_publisher(first) is not None  # two fit
    await tx.publish(third, b"3")  # the first evicted, undeclared
    assert tx.declared_publisher(first) is None
    assert tx.declared_publisher(third) is not None
    await tx.publish(first, b"again")  # declared anew: a put of its own again
    assert tx.declared_publisher(first) is not None
    assert tx.declared_publisher(second) is None
    await tx.aclose()
    assert tx.declared_publisher(first) is None
    assert tx.declared_publisher(third) is None


async def test_zenoh_evicts_and_closes_a_publisher_another_thread_is_putting_on(
    zenoh_net: Net, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The loop's undeclare of a publisher a thread is putting on (the lane's answer) fails
    neither the publish that evicts it nor ``aclose``, which still closes the session.

    zenoh refuses to undeclare a publisher in the middle of a put ("Already borrowed", a
    RuntimeError): it is left to undeclare itself when its last put lets go of it.
    """
    from agents.transports import _zenoh

    monkeypatch.setattr(_zenoh, "_PUBLISHER_CACHE", 1)
    net = zenoh_net
    tx = await net.open()
    assert isinstance(tx, ZenohTransport)
    stop, putting = threading.Event(), threading.Event()

    def hammer(put: Callable[[bytes], None]) -> None:
        while not stop.is_set():
            with contextlib.suppress(Exception):  # a put on an undeclared publisher raises
                put(b"answer")
            putting.set()

    async def while_putting(key: str, step: Callable[[], Any]) -> None:
        await tx.publish(key, b"declared")
        put = tx.declared_publisher(key)
        assert put is not None
        stop.clear()
        putting.clear()
        thread = threading.Thread(target=hammer, args=(put,), daemon=True)
        thread.start()
        try:
            assert await asyncio.to_thread(putting.wait, WAIT)
            await step()  # the loop undeclares while the thread puts
        finally:
            stop.set()
            await asyncio.to_thread(thread.join, WAIT)
        assert not thread.is_alive()

    for i in range(10):
        busy = net.key(f"busy/{i}")
        # a cache of one: publishing on another key evicts (undeclares) the busy one
        await while_putting(busy, lambda i=i: tx.publish(net.key(f"other/{i}"), b"evicts"))
        assert tx.declared_publisher(busy) is None
    await while_putting(net.key("busy/closing"), tx.aclose)
    assert tx._session is None  # closed all the same


async def test_zenoh_tokens_come_all_when_more_than_zenoh_s_channel_holds(
    zenoh_net: Net,
) -> None:
    """300 tokens: beyond the 256 replies zenoh's channel to the callback's thread holds.

    zenoh answers them inside the liveliness get, holding its session lock, and waits for
    that thread when the channel is full: the thread drains it while the get waits.
    """
    net = zenoh_net
    holder, q = await net.open(), await net.open()
    for i in range(300):
        await holder.declare_token(net.key(f"many/{i}"))
    await ready(net, q, holder)
    tokens = await q.tokens(net.key("many/*"), timeout=WAIT)
    assert tokens == sorted(net.key(f"many/{i}") for i in range(300))


async def test_query_without_server_returns_nothing_in_bounded_time(net: Net) -> None:
    q = await net.open()
    start = time.monotonic()
    assert await q.query(net.key("nobody/*"), b"?", timeout=0.5) == []
    assert time.monotonic() - start < 3.0


async def test_handler_error_becomes_error_reply(net: Net) -> None:
    s, q = await net.open(), await net.open()

    async def failing(key: str, payload: bytes) -> bytes:
        raise ValueError("boom: cannot answer")

    await s.serve(net.key("err/x"), failing)
    await ready(net, q, s)
    replies = await q.query(net.key("err/x"), b"", timeout=net.query_timeout)
    assert len(replies) == 1
    assert not replies[0].ok
    assert b"boom: cannot answer" in replies[0].payload


async def test_a_memory_query_leaves_no_handler_running() -> None:
    # the query owns its handlers' tasks: the late ones end with it, and all of them
    # when it is cancelled
    hub = MemoryHub()
    async with hub.transport() as s, hub.transport() as q:

        async def stuck(key: str, payload: bytes) -> bytes:
            await asyncio.Event().wait()
            return b"never"

        await s.serve("test/stuck", stuck)
        before = asyncio.all_tasks()
        assert await q.query("test/stuck", timeout=0.05) == []
        assert asyncio.all_tasks() == before
        asking = asyncio.create_task(q.query("test/stuck", timeout=60))
        await asyncio.sleep(0.01)
        names = {t.get_name() for t in asyncio.all_tasks()}
        assert "memory.query[test/stuck].test/stuck" in names
        asking.cancel()
        await asyncio.wait([asking])
        assert asyncio.all_tasks() == before


async def test_handler_may_not_reply(net: Net) -> None:
    s, q = await net.open(), await net.open()

    async def silent(key: str, payload: bytes) -> None:
        return None

    await s.serve(net.key("quiet"), silent)
    await ready(net, q, s)
    assert await q.query(net.key("quiet"), timeout=net.query_timeout) == []


async def test_admit_screens_queries_before_the_handler_runs(net: Net) -> None:
    """A query ``admit`` refuses gets no reply and never reaches the handler."""
    s, q = await net.open(), await net.open()
    handled: list[bytes] = []
    screened: list[bytes] = []

    async def answer(key: str, payload: bytes) -> bytes:
        handled.append(payload)
        return b"ok:" + payload

    def admit(payload: bytes) -> bool:
        screened.append(payload)
        return not payload.startswith(b"junk")

    await s.serve(net.key("gated"), answer, admit=admit)
    await ready(net, q, s)
    assert await q.query(net.key("gated"), b"junk-1", timeout=net.query_timeout) == []
    replies = await q.query(net.key("gated"), b"fine", timeout=net.query_timeout)
    assert replies == [Reply(net.key("gated"), b"ok:fine")]
    assert handled == [b"fine"]
    assert b"junk-1" in screened and b"fine" in screened


async def test_closed_queryable_no_longer_answers(net: Net) -> None:
    s, q = await net.open(), await net.open()

    async def answer(key: str, payload: bytes) -> bytes:
        return b"here"

    handle = await s.serve(net.key("once"), answer)
    await ready(net, q, s)
    assert len(await q.query(net.key("once"), timeout=net.query_timeout)) == 1
    await handle.aclose()
    await ready(net, q, s)
    assert await q.query(net.key("once"), timeout=0.3) == []


# --- presence --------------------------------------------------------------------------------


async def test_mqtt_presence_watcher_remembers_a_bounded_number_of_keys() -> None:
    """An outsider's presences under 5000 new short keys: each reported, 4096 remembered."""
    inbox: Inbox[Presence] = Inbox(asyncio.get_running_loop())
    watcher = _Watcher(inbox, history=False)
    keys = [f"dyknow/f/v1/alive/x{i}" for i in range(5000)]
    for key in keys:
        watcher.feed(key, b'{"v":1,"alive":true}', retained=False)
    assert inbox.received == 5000
    assert len(watcher.known) == _MAX_PRESENCE_KEYS == 4096
    assert list(watcher.known) == keys[-4096:]  # the oldest forgotten first
    watcher.feed(keys[0], b'{"v":1,"alive":true}', retained=False)  # forgotten: a change again
    assert inbox.received == 5001 and len(watcher.known) == 4096


async def test_presence_appears_and_goes_with_history(net: Net) -> None:
    a, b, c = await net.open(), await net.open(), await net.open()
    key_a, key_c = net.key("alive/a"), net.key("alive/c")
    token_a = await a.declare_token(key_a)

    watch = await b.watch_presence(net.key("alive/*"))
    assert await take(watch, 1) == [Presence(key_a, True)]  # the history

    fresh = await b.watch_presence(net.key("alive/*"), history=False)
    token_c = await c.declare_token(key_c)
    assert await take(watch, 1) == [Presence(key_c, True)]
    assert await take(fresh, 1) == [Presence(key_c, True)]  # no history: only the new one

    await token_a.aclose()
    assert await take(watch, 1) == [Presence(key_a, False)]
    assert await take(fresh, 1) == [Presence(key_a, False)]
    await token_c.aclose()
    assert await take(watch, 1) == [Presence(key_c, False)]


async def test_a_second_watcher_gets_the_history_too(net: Net) -> None:
    a, b = await net.open(), await net.open()
    key = net.key("alive/a")
    token = await a.declare_token(key)
    first = await b.watch_presence(net.key("alive/*"))
    assert await take(first, 1) == [Presence(key, True)]
    second = await b.watch_presence(net.key("alive/*"))  # the same key expression again
    assert await take(second, 1) == [Presence(key, True)]
    await token.aclose()
    # Nothing repeated in between: the first watcher's next event is the token going.
    assert await take(first, 1) == [Presence(key, False)]
    assert await take(second, 1) == [Presence(key, False)]


async def test_tokens_are_the_ones_alive_now(net: Net) -> None:
    a, b = await net.open(), await net.open()
    key_a, key_b = net.key("alive/a"), net.key("alive/b")
    token_a = await a.declare_token(key_a)
    await b.declare_token(key_b)
    watch = await b.watch_presence(key_a)
    assert await take(watch, 1) == [Presence(key_a, True)]
    assert await b.tokens(net.key("alive/*"), timeout=net.query_timeout) == [key_a, key_b]
    assert await b.tokens(net.key("alive/c"), timeout=net.query_timeout) == []
    # a caller's screen: only the keys it keeps are answered, on every transport
    kept = await b.tokens(net.key("alive/*"), timeout=net.query_timeout, keep=key_b.__eq__)
    assert kept == [key_b]
    await token_a.aclose()
    assert await take(watch, 1) == [Presence(key_a, False)]
    assert await b.tokens(net.key("alive/*"), timeout=net.query_timeout) == [key_b]


async def test_token_needs_a_concrete_key(net: Net) -> None:
    a = await net.open()
    with pytest.raises(TransportError):
        await a.declare_token(net.key("alive/*"))


# --- lifecycle -------------------------------------------------------------------------------


async def test_transport_cannot_reopen(net: Net) -> None:
    t = net.make()
    async with t:
        pass
    with pytest.raises(TransportClosed):
        async with t:
            pass


async def test_closed_transport_raises_transport_closed(net: Net) -> None:
    unopened = net.make()
    with pytest.raises(TransportClosed):
        await unopened.publish(net.key("x"), b"")
    t = await net.open()
    await t.publish(net.key("x"), b"")
    await t.aclose()
    await t.aclose()  # closing twice is fine

    async def handler(key: str, payload: bytes) -> bytes:
        return b""

    calls = [
        t.publish(net.key("x"), b""),
        t.subscribe(net.key("x")),
        t.query(net.key("x"), timeout=0.1),
        t.serve(net.key("x"), handler),
        t.declare_token(net.key("x")),
        t.watch_presence(net.key("x")),
    ]
    for call in calls:
        with pytest.raises(TransportClosed):
            await call


# --- only the networked transports -----------------------------------------------------------


async def test_slow_handler_becomes_error_reply(remote_net: Net) -> None:
    s = await remote_net.open(serve_timeout=0.2)
    q = await remote_net.open()
    never = asyncio.Event()

    async def stuck(key: str, payload: bytes) -> bytes:
        await never.wait()
        return b"too late"

    await s.serve(remote_net.key("slow"), stuck)
    await ready(remote_net, q, s)
    replies = await q.query(remote_net.key("slow"), timeout=1.0)
    assert len(replies) == 1 and not replies[0].ok
    assert b"timed out" in replies[0].payload


async def test_library_errors_become_transport_errors(remote_net: Net) -> None:
    t = await remote_net.open()
    with pytest.raises(TransportError):
        await t.subscribe("a//b")
    with pytest.raises(TransportError):
        await t.serve("", lambda k, p: asyncio.sleep(0, b""))


async def test_a_subscriber_that_never_reads_does_not_stall_the_publisher(
    remote_net: Net,
) -> None:
    a, b = await remote_net.open(), await remote_net.open()
    await a.subscribe(remote_net.key("flood"), buffer_size=16)  # never read
    await ready(remote_net, b, a)
    start = time.monotonic()
    for _ in range(2000):
        await b.publish(remote_net.key("flood"), b"x" * 64)
    assert time.monotonic() - start < 5.0


# --- configuration and key mapping -----------------------------------------------------------


def test_zenoh_config_errors_name_the_field() -> None:
    with pytest.raises(ValidationError, match="listen"):
        ZenohConfig(listen=("garbage",))
    with pytest.raises(ValidationError, match="connect"):
        ZenohConfig(mode="client")
    with pytest.raises(ValidationError, match="mode"):
        ZenohConfig(mode="bogus")
    with pytest.raises(ValidationError, match="overrides"):
        ZenohConfig(overrides={"no/such/setting": 1})
    with pytest.raises(ValidationError, match="json5"):
        ZenohConfig(json5="{mode: 'nope'}")
    cfg = ZenohConfig(overrides={"transport/link/tx/lease": 1000})
    assert cfg.to_zenoh().get_json("transport/link/tx/lease") == "1000"
    assert ZenohTransport({"mode": "peer"}).config.gossip is True


def test_mqtt_config_errors_name_the_field() -> None:
    with pytest.raises(ValidationError, match="port"):
        MqttConfig(port=0)
    with pytest.raises(ValidationError, match="client_id"):
        MqttConfig(client_id="a/b")
    with pytest.raises(ValidationError, match="password"):
        MqttConfig(password="secret")
    assert MqttConfig().client_id != MqttConfig().client_id


def test_mqtt_key_mapping() -> None:
    assert topic_filter("a/*/b") == "a/+/b"
    assert topic_filter("a/**") == "a/#"
    assert topic_filter("**") == "#"
    with pytest.raises(TransportError, match="last chunk"):
        topic_filter("a/**/b")
    for bad in ("a/b*", "a/+/b", "a/#", "a//b", "$SYS/x", ""):
        with pytest.raises(TransportError):
            topic_filter(bad)
    assert query_topic("a/b/*/c") == "@query/a/b"
    assert query_topic("*/b") == "@query"
    assert queryable_filters("a/*") == ["@query", "@query/a", "@query/a/+"]
    assert queryable_filters("a/**") == ["@query", "@query/a/#"]
    assert queryable_filters("**") == ["@query/#"]


def test_key_intersects() -> None:
    assert key_intersects("a/*", "a/b")
    assert key_intersects("a/*/c", "a/b/*")
    assert key_intersects("a/**", "a")
    assert key_intersects("**", "x/y/z")
    assert key_intersects("a/**/z", "a/b/c/*")
    assert not key_intersects("a/*", "a/b/c")
    assert not key_intersects("a/b", "a/c")
    assert not key_intersects("a/**/z", "a/b/y")


async def test_mqtt_subscription_to_an_unmappable_key_fails_clearly(mosquitto: Any) -> None:
    host, port = mosquitto
    async with MqttTransport(MqttConfig(host=host, port=port)) as t:
        with pytest.raises(TransportError, match="last chunk"):
            await t.subscribe("a/**/b")


async def test_mqtt_a_subscribe_cancelled_before_the_broker_answered_does_not_block_the_next(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]],
) -> None:
    # a caller's timeout around a subscribe over a stalled broker: the next subscriber
    # to the same key used to wait forever for the first one's answer
    host, port, broker = own_mosquitto
    key = f"stall/{uuid.uuid4().hex}"
    async with (
        MqttTransport(MqttConfig(host=host, port=port)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as sender,
    ):
        broker.send_signal(signal.SIGSTOP)
        try:
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(0.5):
                    await t.subscribe(key)
        finally:
            broker.send_signal(signal.SIGCONT)
        async with asyncio.timeout(5.0):  # the broker answers in ms once it runs
            sub = await t.subscribe(key)
        async with sub:
            await sender.publish(key, b"after")
            message = await sub.get(timeout=5.0)
        assert message.payload == b"after"


async def test_mqtt_a_subscriber_waiting_on_one_that_gave_up_subscribes_itself(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]],
) -> None:
    # the first subscriber to a key times out over a stalled broker while a second waits
    # on its answer: the second used to fail with an error the broker never gave
    host, port, broker = own_mosquitto
    key = f"stall/{uuid.uuid4().hex}"
    async with (
        MqttTransport(MqttConfig(host=host, port=port)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as sender,
    ):

        async def impatient() -> Subscription[Message]:
            async with asyncio.timeout(0.5):
                return await t.subscribe(key)

        broker.send_signal(signal.SIGSTOP)
        try:
            first = asyncio.create_task(impatient())
            second = asyncio.create_task(t.subscribe(key))
            with pytest.raises(TimeoutError):
                await first
            assert not second.done()
        finally:
            broker.send_signal(signal.SIGCONT)
        async with asyncio.timeout(5.0):  # the broker answers in ms once it runs
            sub = await second
        async with sub:
            await sender.publish(key, b"after")
            message = await sub.get(timeout=5.0)
        assert message.payload == b"after"


async def test_mqtt_a_subscriber_that_gave_up_waiting_on_another_is_not_left_listening(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]],
) -> None:
    # it would be fed (and keep the topic subscribed at the broker) for the transport's life
    host, port, broker = own_mosquitto
    key = f"stall/{uuid.uuid4().hex}"
    async with MqttTransport(MqttConfig(host=host, port=port)) as t:

        async def impatient() -> Subscription[Message]:
            async with asyncio.timeout(0.5):
                return await t.subscribe(key)

        broker.send_signal(signal.SIGSTOP)
        try:
            first = asyncio.create_task(t.subscribe(key))  # tasks start in order: it subscribes
            with pytest.raises(TimeoutError):
                await asyncio.create_task(impatient())
            assert not first.done()
        finally:
            broker.send_signal(signal.SIGCONT)
        async with asyncio.timeout(5.0):
            sub = await first
        sub.close()
        assert topic_filter(key) not in t._filters, "the topic is still listened to"


async def test_mqtt_unreachable_broker_is_a_transport_error() -> None:
    t = MqttTransport(MqttConfig(port=free_tcp_port(), connect_timeout=2))
    with pytest.raises(TransportError, match="cannot connect"):
        await t.__aenter__()


async def test_zenoh_listen_endpoint_in_use_is_one_clear_line() -> None:
    # a second node on a port in use: the endpoint and what to do, no Rust source paths
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        t = ZenohTransport(ZenohConfig.loopback(port))
        with pytest.raises(TransportError) as raised:
            await t.__aenter__()
    assert str(raised.value) == (
        f"zenoh: cannot listen on tcp/127.0.0.1:{port}: the address is in use (by another "
        "node, maybe this very platform running already, or another program): stop that one "
        "first, or listen on another endpoint"
    )


async def test_zenoh_client_without_its_router_names_the_address_in_one_line() -> None:
    # a misspelt router address: the endpoint and what to check, not zenoh's Rust debug text
    port = free_tcp_port()
    t = ZenohTransport(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    with pytest.raises(TransportError) as raised:
        await t.__aenter__()
    assert str(raised.value) == (
        f"zenoh: cannot open a session: cannot connect to tcp/127.0.0.1:{port} (connect): "
        "no zenoh router or peer accepted a session there (is it running, is the address "
        "right, does it speak zenoh/TLS as configured?)"
    )


async def test_zenoh_client_at_an_address_that_does_not_speak_zenoh_says_it_may_not() -> None:
    # something answers there (here: an HTTP-ish server), but no zenoh session opens:
    # "no router answers" would send one looking for a dead router
    answered: list[int] = []

    async def talk(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        answered.append(1)
        writer.write(b"HTTP/1.1 400 Bad Request\r\n\r\n")
        with contextlib.suppress(ConnectionError):
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(talk, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        t = ZenohTransport(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
        with pytest.raises(TransportError) as raised:
            await t.__aenter__()
    assert answered
    assert str(raised.value) == (
        f"zenoh: cannot open a session: cannot connect to tcp/127.0.0.1:{port} (connect): "
        "no zenoh router or peer accepted a session there (is it running, is the address "
        "right, does it speak zenoh/TLS as configured?)"
    )


def test_zenoh_config_keeps_the_listen_endpoints_of_its_json5_file() -> None:
    # a router started from a JSON5 file (deploy/config/router.json5) listens where the
    # file says, not on the library's loopback default
    json5 = '{ listen: { endpoints: ["tcp/127.0.0.1:17999"] } }'
    cfg = ZenohConfig(mode="router", json5=json5).to_zenoh()
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:17999"]
    flags = ZenohConfig(mode="router", json5=json5, listen=("tcp/127.0.0.1:18000",)).to_zenoh()
    assert json.loads(flags.get_json("listen/endpoints")) == ["tcp/127.0.0.1:18000"]
    default = ZenohConfig(mode="peer").to_zenoh()
    assert json.loads(default.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]


def test_zenoh_reach_is_read_from_the_config_once() -> None:
    # whether a session seeks peers, and how many links its connect endpoints make: what
    # `tokens` waits for, read at open from the one zenoh.Config
    from agents.transports._zenoh import _reach

    def reach(**fields: Any) -> tuple[bool, int]:
        return _reach(ZenohConfig(**fields).to_zenoh())

    alone = {"listen": ("tcp/127.0.0.1:0",), "multicast_scouting": False}
    two = ("tcp/127.0.0.1:7001", "tcp/127.0.0.1:7002")
    assert reach(**alone) == (False, 0)
    assert reach(**{**alone, "multicast_scouting": True}) == (True, 0)
    assert reach(**alone, connect=two) == (True, 2)  # a peer links to each
    assert reach(mode="client", connect=two) == (True, 1)  # a client to one router
    import zenoh  # a config of zenoh's own may give the endpoints per mode

    per_mode = '{mode: "peer", connect: {endpoints: {peer: ["tcp/127.0.0.1:7001"], client: []}}}'
    assert _reach(zenoh.Config.from_json5(per_mode)) == (True, 1)


def test_zenoh_config_gives_the_data_queue_room_unless_the_user_chose() -> None:
    # zenoh's largest send queue for the data priority (16 batches), not its default (2);
    # a size the user's JSON5 or overrides chose stays
    path = "transport/link/tx/queue/size/data"

    def size(**fields: Any) -> Any:
        return json.loads(ZenohConfig(**fields).to_zenoh().get_json(path))

    assert size() == 16
    assert size(json5="{ mode: 'peer' }") == 16
    chosen = "{ transport: { link: { tx: { queue: { size: { data: 4 } } } } } }"
    assert size(json5=chosen) == 4
    assert size(overrides={path: 2}) == 2


def test_zenoh_config_leaves_shared_memory_off_unless_the_user_chose() -> None:
    # zenoh's shared memory, once a link has it, wakes a task every 100 ms for the
    # session's life: off by default; the user's JSON5 or overrides may turn it on
    path = "transport/shared_memory/enabled"

    def enabled(**fields: Any) -> Any:
        return json.loads(ZenohConfig(**fields).to_zenoh().get_json(path))

    assert enabled() is False
    assert enabled(json5="{ mode: 'peer' }") is False
    assert enabled(json5="{ transport: { shared_memory: { enabled: true } } }") is True
    assert enabled(json5='{ "transport": { "shared_memory": { "enabled": false } } }') is False
    # a shared_memory key keeps zenoh's value, its default (on) where the file has none
    assert enabled(json5="{ transport: { shared_memory: { mode: 'init' } } }") is True
    # a comment saying so is not a key
    assert enabled(json5="{\n  // shared_memory: we want it off\n  mode: 'peer',\n}") is False
    assert enabled(json5="{ /* shared_memory: on? */ mode: 'peer' }") is False
    assert enabled(overrides={path: True}) is True


# Two linked sessions idle for two seconds in a fresh interpreter (zenoh's runtime is the
# process's, and its shared-memory task, once started, runs until the process exits):
# how many times zenoh's network threads woke, first with shared memory off (the
# default: the control), then on. Linux: counted in /proc.
_IDLE_WAKEUPS = """
import asyncio, os, time
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port

def net_wakeups():
    # by thread: one may end between the listing and the reading (zenoh's come and go)
    n = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                if not f.read().startswith("net-"):
                    continue
            with open(f"/proc/self/task/{tid}/status") as f:
                n[tid] = sum(
                    int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt")
                )
        except FileNotFoundError:
            continue
    return n

async def idle(overrides, key):
    seed = free_tcp_port()
    a = ZenohTransport(ZenohConfig.loopback(seed, overrides=overrides))
    b = ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed], overrides=overrides))
    async with a, b:
        # the link up, a put that shared memory would carry across it: on a loaded
        # machine the link may come up late, and with it the task
        async with await b.subscribe(key) as sub, asyncio.timeout(30):
            while True:
                await a.publish(key, b"y" * 8192)
                try:
                    await sub.get(timeout=0.2)
                    break
                except TimeoutError:
                    continue
        before = net_wakeups()
        time.sleep(2.0)  # the event loop asleep too: only zenoh's own threads run
        # the threads there at the end (one ended meanwhile took its count with it)
        return sum(n - before.get(tid, 0) for tid, n in net_wakeups().items())

async def main():
    off = await idle({}, "test/idle/off")
    on = await idle({"transport/shared_memory/enabled": True}, "test/idle/on")
    print(off, on)

asyncio.run(main())
"""


@pytest.mark.skipif(sys.platform != "linux", reason="counts wake-ups in Linux's /proc")
def test_zenoh_idle_link_does_not_wake_every_100_ms() -> None:
    """Two linked sessions idle: zenoh's 100 ms shared-memory task wakes only if turned on.

    Counted over 2 s once the link is up, the default's sessions first, then shared
    memory's in the same process: on ~40 wake-ups more than the control (24 to 45 beside
    three busy loops on two cores), which has none or nearly.
    """
    out = subprocess.run(
        [sys.executable, "-c", _IDLE_WAKEUPS],
        capture_output=True,
        text=True,
        timeout=90,
        check=True,
    )
    off, on = map(int, out.stdout.split()[-2:])
    assert off <= 5, (off, on)  # by default the task never starts
    # the count sees zenoh's task, run in this run beside the control
    assert on - off >= 10, (off, on)


async def test_zenoh_burst_behind_a_slow_receiver_waits_in_the_queue() -> None:
    """A burst of 12 puts of 40 kB while the receiver reads nothing: none is lost.

    The receiver's callback holds zenoh's receiving thread until the burst is out, and
    small socket buffers (64 kB) leave the rest to the sender's send queue, where each
    put takes a 64 kB batch of its own. With zenoh's default queue (2 batches) 3 to 10 of
    them were dropped (congestion control DROP; 2 arrived when zenoh's send thread did
    not run during the burst, on a busy machine); ours (16) holds them even then. No
    sleep: a marker put after the burst (BLOCK: waits for room, never dropped) comes in
    order behind it, so when it has come everything that will come has.
    """
    import threading

    import zenoh

    bufs = "#so_sndbuf=65536;so_rcvbuf=65536"
    seed = free_tcp_port()
    key = f"test/{uuid.uuid4().hex[:10]}/burst"
    n, size = 12, 40_000
    gate, seen = threading.Event(), threading.Event()
    loop = asyncio.get_running_loop()
    marker, got = asyncio.Event(), [0]

    def on_sample(sample: zenoh.Sample) -> None:
        body = sample.payload.to_bytes()
        if body == b"probe":
            seen.set()
        elif body == b"marker":
            loop.call_soon_threadsafe(marker.set)
        else:
            gate.wait(30)  # the receiver reads nothing until the burst is out
            got[0] += 1

    rx = ZenohTransport(ZenohConfig(listen=(f"tcp/127.0.0.1:{seed}{bufs}",)))
    tx = ZenohTransport(
        ZenohConfig(
            listen=(f"tcp/127.0.0.1:{free_tcp_port()}{bufs}",),
            connect=(f"tcp/127.0.0.1:{seed}{bufs}",),
        )
    )
    async with rx, tx, asyncio.timeout(60):
        sub = rx.session.declare_subscriber(key, on_sample)
        try:
            while not seen.is_set():  # the link and the subscription are up
                tx.publish_nowait(key, b"probe")
                await asyncio.to_thread(seen.wait, 0.05)
            for _ in range(n):
                tx.publish_nowait(key, b"x" * size)
            gate.set()
            await tx.publish_blocking(key, b"marker")
            await marker.wait()
        finally:
            gate.set()
            sub.undeclare()
    assert got[0] == n


class _Recording(ZenohTransport):
    """A zenoh transport with its own `publish`, noting each payload."""

    def __init__(self, config: ZenohConfig) -> None:
        super().__init__(config)
        self.puts: list[bytes] = []

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        self.puts.append(payload)
        await super().publish(key, payload, attachment=attachment)


async def test_a_zenoh_subclass_s_own_publish_sees_every_put_never_a_put_beside_it() -> None:
    """`publish_nowait` of a subclass with its own `publish` refuses; nothing is put.

    A subclass's `publish` (a test's lossy link, a recording wrapper) must see every put:
    a caller told the transport cannot publish without waiting goes through `publish`.
    """
    seed = free_tcp_port()
    made = iter(
        [
            lambda: _Recording(ZenohConfig.loopback(seed)),
            lambda: ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed])),
        ]
    )
    n = Net("zenoh", f"test/{uuid.uuid4().hex[:10]}", 5.0, lambda **_: next(made)())
    try:
        sender, seer = await n.open(), await n.open()
        assert isinstance(sender, _Recording) and not sender.publishes_nowait
        sub = await seer.subscribe(n.key("x"))
        await ready(n, sender, seer)
        with pytest.raises(TransportError, match="cannot publish without waiting"):
            sender.publish_nowait(n.key("x"), b"beside")
        await sender.publish(n.key("x"), b"through")
        [got] = await take(sub, 1)
        assert got.payload == b"through"  # the refused put never went out before it
        assert sender.puts == [b"through"]
    finally:
        for t in reversed(n.opened):
            await t.aclose()
