"""The exports' batches sent in one call per loop turn, not one task per stream.

An export whose path is clear sends its batch from the proxy's flush; anything else is
its task's. What a receiver sees must not depend on which of them sent a batch: each
stream's batches in order, numbered without holes, the same bytes for the same samples;
a session renewed in the middle of a flow, a receiver that stops reporting, a put that
raises and a failure while packing handled as the task handles them.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import types
import uuid
from collections.abc import AsyncIterator
from typing import Any

import msgpack
import pytest

from agents import Expired, TransportClosed, TransportError, UnknownSession
from agents.transports import MemoryTransport
from dyknow_core import Source
from federation import ExportProxy, ImportProxy, _export
from federation._batch import pack_batch
from federation._proxy_stats import DropReason
from federation._sessions import PlainSessions
from tests.test_proxies import LOCAL, SEM, WAIT, Net, agreed, network, until

Wire = dict[str, list[dict[str, Any]]]


@contextlib.asynccontextmanager
async def flow(labels: int) -> AsyncIterator[tuple[Net, list[Source], str]]:
    """A Net with ``uav-a``'s ``labels`` sources (local ``l/<i>``) and a unique federation."""
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT * 3):
            net = Net(stack)
            _, a = await net.platform("uav-a")
            await net.platform("uav-b")
            await net.platform("uav-c")
            yield net, [a.add_source(f"l/{i}") for i in range(labels)], f"flush-{uuid.uuid4().hex}"


async def wire(net: Net, stack: contextlib.AsyncExitStack, fed: str) -> Wire:
    """Every stream body published in ``fed``, by key, decoded, as they arrive."""
    listener = await stack.enter_async_context(net.hub.transport())
    sub = await listener.subscribe(f"dyknow/{fed}/v1/stream/**")
    seen: Wire = {}

    async def read() -> None:
        async for item in sub:
            body = msgpack.unpackb(item.payload, raw=False)[3]  # [1, from, to, body]
            seen.setdefault(item.key, []).append(
                {**msgpack.unpackb(body, raw=False), "bytes": body}
            )

    task = asyncio.create_task(read())

    async def close() -> None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        sub.close()

    stack.push_async_callback(close)
    return seen


def exporter(net: Net, fed: str, sessions: Any = None, **options: Any) -> ExportProxy:
    """``uav-a``'s export proxy in ``fed`` (unauthenticated sessions unless given)."""
    proxy = ExportProxy(
        "uav-a",
        fed,
        net.transports["uav-a"],
        net.instances["uav-a"],
        sessions or PlainSessions("uav-a"),
        **options,
    )
    net.stack.push_async_callback(proxy.aclose)
    return proxy


def key(fed: str, receiver: str, label: str) -> str:
    return f"dyknow/{fed}/v1/stream/{receiver}/uav-a/{label}"


def check_stream(batches: list[dict[str, Any]], values: list[Any], batch_size: int) -> None:
    """In order, numbered without holes, each body what `pack_batch` makes of its samples."""
    q = 0
    got: list[Any] = []
    for b in batches:
        assert b["q"] == q, f"batch numbered {b['q']} after {q} samples"
        assert 1 <= len(b["b"]) <= batch_size
        assert b["bytes"] == pack_batch(b["s"], [tuple(s) for s in b["b"]], q)
        q += len(b["b"])
        got += [s[0] for s in b["b"]]
    assert got == values


async def test_each_streams_batches_go_in_order_numbered_the_same_bytes_as_one_task_would() -> None:
    # ten exports, ticks of one sample each and bursts over a batch: one flush per turn
    # sends every export's batch; a burst goes on next turn, as the task's batches did
    async with flow(10) as (net, sources, fed):
        seen = await wire(net, net.stack, fed)
        proxy = exporter(net, fed, batch_size=4, lease=None)
        exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(10)]
        pushed: list[list[int]] = [[] for _ in sources]
        n = 0
        for tick in range(60):
            burst = 11 if tick % 7 == 3 else 1  # 11: three batches of at most 4
            for i, source in enumerate(sources):
                for _ in range(burst):
                    source.push(n)
                    pushed[i].append(n)
                    n += 1
            if tick % 3:  # two ticks in one turn now and then
                await asyncio.sleep(0)
        await until(
            lambda: all(e.sent == len(p) for e, p in zip(exports, pushed, strict=True)),
            "every sample sent",
        )
        await until(
            lambda: (
                sum(len(seen.get(key(fed, "uav-b", f"s/{i}"), [])) for i in range(10))
                == sum(e.batches for e in exports)
            ),
            "every batch seen",
        )
        for i, export in enumerate(exports):
            check_stream(seen[key(fed, "uav-b", f"s/{i}")], pushed[i], 4)
            assert export.dropped_total == 0 and export.active


class Renewing(PlainSessions):
    """Sessions that lapse on demand: sealing raises until `ensure` agrees a new one."""

    def __init__(self, me: str, error: type[Exception]) -> None:
        super().__init__(me)
        self.error = error
        self.valid = True
        self.agreed = asyncio.Event()
        self.asked = 0
        self.refused = 0

    async def ensure(self, peer: str) -> None:
        self.asked += 1
        await self.agreed.wait()
        self.valid = True

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        if not self.valid:
            self.refused += 1
            raise self.error(f"no session with {peer!r}", peer)
        return super().seal_bytes(peer, body)


@pytest.mark.parametrize("error", [UnknownSession, Expired])
async def test_a_session_renewed_in_the_middle_of_a_flow_loses_nothing_and_keeps_the_order(
    error: type[Exception],
) -> None:
    async with flow(2) as (net, sources, fed):
        seen = await wire(net, net.stack, fed)
        sessions = Renewing("uav-a", error)
        proxy = exporter(net, fed, sessions, batch_size=8, lease=None)
        exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(2)]
        pushed: list[list[int]] = [[], []]

        async def ticks(n: int) -> None:
            for _ in range(n):
                for i, source in enumerate(sources):
                    v = len(pushed[i])
                    source.push(v)
                    pushed[i].append(v)
                await asyncio.sleep(0)

        await ticks(5)
        await until(lambda: all(e.sent == 5 for e in exports), "the first samples sent")
        sessions.valid = False  # lapsed: the next seal refuses, a new session is agreed
        await ticks(1)
        await until(lambda: sessions.asked == 2, "both exports agreeing a session")
        await ticks(6)  # queued meanwhile, behind the batch that could not be sealed
        assert all(e.sent == 5 for e in exports)
        sessions.agreed.set()
        await ticks(5)
        await until(lambda: all(e.sent == 17 for e in exports), "every sample sent")
        await until(
            lambda: (
                sum(
                    sum(len(b["b"]) for b in seen.get(key(fed, "uav-b", f"s/{i}"), []))
                    for i in range(2)
                )
                == 34
            ),
            "every sample seen",
        )
        for i, export in enumerate(exports):
            check_stream(seen[key(fed, "uav-b", f"s/{i}")], pushed[i], 8)
            assert export.dropped_total == 0 and export.active
        # one agreement per export: the batch that met the lapsed session went first once
        # agreed, the samples queued meanwhile after it
        assert sessions.asked == 2 and sessions.refused > 0


async def test_a_receiver_that_stops_reporting_ends_its_export_only() -> None:
    async with flow(1) as (net, sources, fed):
        seen = await wire(net, net.stack, fed)
        proxy = exporter(net, fed, lease=0.6)
        importers = {}
        for receiver in ("uav-b", "uav-c"):
            importers[receiver] = await net.stack.enter_async_context(_importer(net, receiver, fed))
        to_b = proxy.start_exporting("l/0", "s/0", "uav-b")
        to_c = proxy.start_exporting("l/0", "s/0", "uav-c")
        source = sources[0]
        stop = asyncio.Event()

        async def push() -> None:
            n = 0
            while not stop.is_set():
                source.push(n)
                n += 1
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.01):
                        await stop.wait()

        pusher = asyncio.create_task(push())
        try:
            await until(lambda: to_c.sent > 20 and to_b.sent > 20, "the flow under way")
            await importers["uav-c"].aclose()  # uav-c stops reporting; the flow goes on
            ended = await until(lambda: to_c.ended, "uav-c's lease to expire", timeout=3.0)
            assert ended.startswith("lease-expired: no report from uav-c")
            assert list(proxy.ended) == [to_c] and proxy.find("uav-c", "s/0") is None
            sent_to_b = to_b.sent
            await until(lambda: to_b.sent > sent_to_b + 20, "uav-b's flow going on")
        finally:
            stop.set()
            await pusher
        assert to_b.active and to_b.dropped_total == 0
        # the end marker is the last batch uav-c was sent: nothing after it
        to_c_batches = await until(
            lambda: (b := seen.get(key(fed, "uav-c", "s/0"))) and "e" in b[-1] and b,
            "uav-c told",
        )
        assert [b for b in to_c_batches if "e" in b] == [to_c_batches[-1]]
        assert sum(len(b["b"]) for b in to_c_batches) == to_c.sent


@contextlib.asynccontextmanager
async def _importer(net: Net, name: str, fed: str) -> AsyncIterator[Any]:
    proxy = ImportProxy(
        name,
        fed,
        net.transports[name],
        net.instances[name],
        PlainSessions(name),
        agreed("s/0"),
        report_interval=0.1,
    )
    async with proxy:
        yield proxy


async def test_a_put_that_raises_costs_its_batch_only_and_numbering_goes_on() -> None:
    async with flow(2) as (net, sources, fed):
        seen = await wire(net, net.stack, fed)
        transport = net.transports["uav-a"]
        put = transport._put  # under `publish` and `publish_nowait` alike
        failing = key(fed, "uav-b", "s/0")
        fail = {"n": 0}

        def flaky(k: str, payload: bytes, attachment: bytes | None) -> None:
            if k == failing and fail["n"]:
                fail["n"] -= 1
                raise TransportError(f"zenoh: put on {k!r}: no room")
            put(k, payload, attachment)

        transport._put = flaky  # type: ignore[method-assign]
        dropped: list[tuple[str, str, int]] = []
        proxy = exporter(
            net, fed, lease=None, on_drop=lambda e, r, n: dropped.append((e.semantic_label, r, n))
        )
        exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(2)]
        for tick in range(30):
            if tick == 10:
                fail["n"] = 2  # ticks 10 and 11's batches of s/0 fail
            for source in sources:
                source.push(tick)
            await asyncio.sleep(0)
        await until(lambda: exports[1].sent == 30, "s/1 sent")
        await until(lambda: exports[0].sent == 28, "s/0 sent")
        assert exports[0].dropped == {DropReason.SEND_FAILED: 2} and exports[0].active
        assert exports[0].last_error == f"TransportError: zenoh: put on {failing!r}: no room"
        assert dropped == [("s/0", DropReason.SEND_FAILED, 1)] * 2
        assert exports[1].dropped_total == 0
        await until(lambda: len(seen.get(failing, [])) == 28, "s/0's batches seen")
        # the receiver sees the gap: numbers 10 and 11 never came
        assert [b["q"] for b in seen[failing]] == [*range(10), *range(12, 30)]


async def test_a_transport_closing_in_a_flow_ends_the_exports_as_closed() -> None:
    async with flow(2) as (net, sources, fed):
        proxy = exporter(net, fed, lease=None)
        exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(2)]
        for tick in range(5):
            for source in sources:
                source.push(tick)
            await asyncio.sleep(0)
        await until(lambda: all(e.sent == 5 for e in exports), "the first samples sent")
        await net.transports["uav-a"].aclose()
        for source in sources:
            source.push(5)
        for export in exports:
            ended = await until(lambda e=export: e.ended, f"{export.name} to end")
            assert ended.startswith("the transport closed:"), ended
            assert export.sent == 5
        assert proxy.exports() == []
        with pytest.raises(TransportClosed):
            await net.transports["uav-a"].publish("x", b"")


async def test_a_failure_while_packing_ends_that_export_and_tells_its_receiver(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pack = _export.pack_batch

    def broken(label: str, samples: list[Any], *args: Any, **kwargs: Any) -> bytes:
        if label == "s/0" and any(s[0] == 3 for s in samples):
            raise RuntimeError("a bug, quoting the sample 3")
        return pack(label, samples, *args, **kwargs)

    monkeypatch.setattr(_export, "pack_batch", broken)
    async with flow(2) as (net, sources, fed):
        seen = await wire(net, net.stack, fed)
        proxy = exporter(net, fed, lease=None)
        exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(2)]
        for tick in range(8):
            for source in sources:
                source.push(tick)
            await asyncio.sleep(0)
        ended = await until(lambda: exports[0].ended, "s/0 to end")
        assert ended.startswith("failed: RuntimeError at test_export_flush.py:")
        assert ended.endswith("in broken (its text left out)")
        await until(lambda: exports[1].sent == 8, "s/1 going on")
        batches = await until(
            lambda: (b := seen.get(key(fed, "uav-b", "s/0"))) and "e" in b[-1] and b,
            "the receiver told",
        )
        assert [b["q"] for b in batches] == [0, 1, 2, 3] and batches[-1]["e"] == ended
        assert "sample 3" not in ended and list(proxy.ended) == [exports[0]]


async def test_over_a_transport_whose_put_waits_each_export_sends_from_its_task() -> None:
    # MQTT's put waits for its client: no flush may put past it, every batch goes
    # through `publish`, in order, as before
    class Waiting(MemoryTransport):
        puts = 0

        async def publish(self, key: str, payload: bytes, *, attachment: Any = None) -> None:
            Waiting.puts += "/stream/" in key
            await asyncio.sleep(0)  # as a client handing the put to its own loop would
            await super().publish(key, payload, attachment=attachment)

    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT * 3):
            net = Net(stack)
            fed = f"flush-{uuid.uuid4().hex}"
            _, a = await net.platform("uav-a", transport=Waiting(net.hub))
            sources = [a.add_source(f"l/{i}") for i in range(3)]
            assert not net.transports["uav-a"].publishes_nowait
            seen = await wire(net, stack, fed)
            proxy = exporter(net, fed, batch_size=4, lease=None)
            exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(3)]
            for tick in range(20):
                for source in sources:
                    for k in range(1 + tick % 6):  # up to 6: some batches split in two
                        source.push(10 * tick + k)
                await asyncio.sleep(0)
            pushed = [10 * t + k for t in range(20) for k in range(1 + t % 6)]
            await until(lambda: all(e.sent == len(pushed) for e in exports), "every sample sent")
            await until(
                lambda: (
                    sum(len(seen.get(key(fed, "uav-b", f"s/{i}"), [])) for i in range(3))
                    == sum(e.batches for e in exports)
                ),
                "every batch seen",
            )
            for i in range(3):
                check_stream(seen[key(fed, "uav-b", f"s/{i}")], pushed, 4)
            assert Waiting.puts == sum(e.batches for e in exports)


async def within_turns(predicate: Any, what: str, turns: int = 30) -> None:
    """``predicate`` true within ``turns`` turns of the loop (no clock: a stall cannot hide)."""
    for _ in range(turns):
        if predicate():
            return
        await asyncio.sleep(0)
    assert predicate(), f"{what}: not within {turns} turns of the loop"


async def test_what_the_flush_cannot_send_goes_on_in_the_next_turns_not_at_the_idle_check(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the tasks' idle check pushed out of reach: whatever the flush leaves (a burst's
    # tail, a session to agree, a closed transport, a lease ended) must be taken up at
    # once, as the woken task took it up, not when the export next looks by itself
    monkeypatch.setattr(_export, "_IDLE_CHECK", 3600.0)
    async with flow(2) as (net, sources, fed):
        sessions = Renewing("uav-a", UnknownSession)
        proxy = exporter(net, fed, sessions, batch_size=4, lease=3600.0)
        exports = [proxy.start_exporting(f"l/{i}", f"s/{i}", "uav-b") for i in range(2)]
        sources[0].push(0)
        sources[1].push(0)
        await within_turns(lambda: all(e.sent == 1 for e in exports), "the first samples")
        # a burst of 11 over batches of 4: the rest goes on next turn, and the next
        for v in range(1, 12):
            sources[0].push(v)
        await within_turns(lambda: exports[0].sent == 12, "a burst's tail")
        # a lapsed session: the task agrees one at once, and sends once agreed
        sessions.valid = False
        sources[0].push(12)
        await within_turns(lambda: sessions.asked == 1, "a session asked for")
        sessions.agreed.set()
        await within_turns(lambda: exports[0].sent == 13, "the batch once agreed")
        # a receiver silent for longer than the lease: the export ends at its next sample
        exports[1].last_heard -= 7200.0
        sources[1].push(1)
        await within_turns(lambda: exports[1].ended, "the lease ended")
        assert exports[1].sent == 1 and exports[1].dropped == {DropReason.LEASE_EXPIRED: 1}
        # a closed transport ends the export at its next sample
        await net.transports["uav-a"].aclose()
        sources[0].push(13)
        await within_turns(lambda: exports[0].ended, "the export ended")
        assert (exports[0].ended or "").startswith("the transport closed:")
        assert exports[0].sent == 13 and exports[0].dropped_total == 0


async def test_a_sample_pushed_while_a_keepalive_agrees_a_session_goes_out_once_agreed() -> None:
    # an idle export not reported on yet sends a keepalive, which waits for a session
    # with its receiver: a sample pushed meanwhile woke nobody (the task was not
    # waiting), and went out only at the export's next idle check, a second later
    async with network() as net:
        await net.platform("uav-a")
        await net.platform("uav-b")
        src = net.instances["uav-a"].add_source(LOCAL)
        sessions = Renewing("uav-a", UnknownSession)
        sessions.valid = False  # no session yet: the first seal agrees one
        exporter = await net.exporter("uav-a", sessions, lease=30.0)  # idle check: 1 s
        importer = await net.importer("uav-b")
        export = exporter.start_exporting(LOCAL, SEM, "uav-b")
        await until(lambda: sessions.asked == 1, "the keepalive agreeing a session")
        assert export.sent == 0 and export.batches == 0
        src.push("while agreeing")
        assert list(export.queue) and export.sent == 0  # queued, nobody woken
        sessions.agreed.set()

        def arrived() -> bool:
            rec = importer.get("uav-a", SEM)
            return rec is not None and rec.injected == 1

        await within_turns(arrived, "the sample at the receiver")
        assert export.sent == 1 and export.dropped_total == 0 and sessions.asked == 1


def keeps(owner: object, target: object, beside: tuple[object, ...]) -> bool:
    """Whether ``target`` is reachable from ``owner`` other than through ``beside`` (or code)."""
    stop = (types.ModuleType, type, types.FunctionType, asyncio.AbstractEventLoop)
    seen = {id(owner), *map(id, beside)}
    todo = [owner]
    while todo:
        for ref in gc.get_referents(todo.pop()):
            if ref is target:
                return True
            if id(ref) not in seen and not isinstance(ref, stop):
                seen.add(id(ref))
                todo.append(ref)
    return False


async def test_an_export_ended_by_what_its_flush_met_does_not_keep_its_last_batch() -> None:
    # ended exports stay listed in `proxy.ended` (256 of them): what ended one must not
    # hold on to its last batch (the flush's frames and the samples in them)
    async with flow(1) as (net, sources, fed):
        proxy = exporter(net, fed, lease=None)
        export = proxy.start_exporting("l/0", "s/0", "uav-b")
        sources[0].push("first")
        await until(lambda: export.sent == 1, "the first sample sent")
        await net.transports["uav-a"].aclose()
        last = "the last sample, " + uuid.uuid4().hex
        sources[0].push(last)  # the flush meets the closed transport
        await until(lambda: export.ended, "the export to end")
        assert list(proxy.ended) == [export]
        # its local stream (whose cache holds the sample), its proxy and the test aside
        beside = (export.subscription, export._proxy, export.task, net.instances["uav-a"])
        assert not keeps(export, last, (*beside, asyncio.current_task()))
