"""Export and import proxies: agreed streams between platforms, bypassing the agents.

Platforms share one MemoryHub (one process). Batches are sealed with an unauthenticated
in-memory provider where the test is about streaming, and with real SessionTables (and
real Interface Agents) where it is about what is refused.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
import tracemalloc
import uuid
from collections.abc import AsyncIterator, Callable
from typing import Any, TypeVar

import msgpack
import pytest

from agents import AgentPlatform, TransportError
from agents._exceptions import Expired
from agents._interface import InterfaceAgent
from agents._security import Handshake, KeyPair, SessionTable, TrustStore
from agents.transports import (
    MemoryHub,
    MemoryTransport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from dyknow_core import (
    NS_PER_S,
    DuplicateLabelError,
    DyKnowInstance,
    ManualClock,
    Policy,
    UnknownLabelError,
)
from federation import (
    Export,
    ExportProxy,
    ImportProxy,
    InterfaceSessions,
    PlatformConfig,
    PlatformConfigError,
    SessionsProvider,
    TableSessions,
    _export,
)
from federation._batch import pack_batch, unpack_batch
from federation._sessions import PlainSessions

FED = "demo"
WAIT = 5.0  # the bound on any single wait; every test finishes far below it
LOCAL = "car/car5/state"
SEM = "car5-state"
T = TypeVar("T")


async def until(predicate: Callable[[], T], what: str, timeout: float = WAIT) -> T:
    """Poll ``predicate`` (cheap counters in memory) until truthy; fail after ``timeout`` s."""
    try:
        async with asyncio.timeout(timeout):
            # the proxies' counters have no events to await: poll them, briefly
            while not (value := predicate()):  # noqa: ASYNC110
                await asyncio.sleep(0.002)
            return value
    except TimeoutError:
        raise AssertionError(f"timed out waiting for {what}") from None


def imported(sender: str, semantic: str) -> str:
    """The local label these tests import a stream into."""
    return f"fed/{sender}/{semantic}"


def agreed(*labels: str) -> Callable[[str, str], str | None]:
    """A translate that knows ``labels`` only."""
    return lambda sender, semantic: imported(sender, semantic) if semantic in labels else None


def stream_key(receiver: str, sender: str, semantic: str = SEM) -> str:
    return f"dyknow/{FED}/v1/stream/{receiver}/{sender}/{semantic}"


class Net:
    """Platforms on one MemoryHub: a transport and a DyKnow instance each, closed on exit."""

    def __init__(self, stack: contextlib.AsyncExitStack) -> None:
        self.hub = MemoryHub()
        self.stack = stack
        self.instances: dict[str, DyKnowInstance] = {}
        self.transports: dict[str, MemoryTransport] = {}

    async def platform(
        self, name: str, *, clock: ManualClock | None = None, transport: Any = None
    ) -> tuple[MemoryTransport, DyKnowInstance]:
        t = await self.stack.enter_async_context(transport or self.hub.transport())
        dk = await self.stack.enter_async_context(DyKnowInstance(name, clock=clock))
        self.transports[name], self.instances[name] = t, dk
        return t, dk

    async def exporter(self, name: str, sessions: Any = None, **options: Any) -> ExportProxy:
        proxy = ExportProxy(
            name,
            FED,
            self.transports[name],
            self.instances[name],
            sessions or PlainSessions(name),
            **options,
        )
        return await self.stack.enter_async_context(proxy)

    async def importer(
        self,
        name: str,
        sessions: Any = None,
        translate: Callable[[str, str], str | None] | None = None,
        **options: Any,
    ) -> ImportProxy:
        proxy = ImportProxy(
            name,
            FED,
            self.transports[name],
            self.instances[name],
            sessions or PlainSessions(name),
            translate or agreed(SEM),
            **options,
        )
        return await self.stack.enter_async_context(proxy)


@contextlib.asynccontextmanager
async def network() -> AsyncIterator[Net]:
    """A Net closed on exit, every wait bounded."""
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT * 2):
            yield Net(stack)


# -- real sessions --------------------------------------------------------------------------


KEYS = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b", "uav-c", "mallory")}


def trust(*names: str) -> TrustStore:
    return TrustStore(FED, {n: KEYS[n].public_key for n in names})


class Tables:
    """Each platform's Handshake and SessionTable; ``agree`` runs a handshake in memory."""

    def __init__(self, *names: str, trusted: tuple[str, ...] = ("uav-a", "uav-b", "uav-c")):
        self.hs = {n: Handshake(KEYS[n], trust(*trusted)) for n in names}
        self.tables = {n: SessionTable(n, trust(*trusted)) for n in names}
        self.unreachable: set[str] = set()

    def connect(self, a: str, b: str) -> None:
        reply, sb = self.hs[b].respond(self.hs[a].initiate(b))
        self.tables[a].add(self.hs[a].finish(reply))
        self.tables[b].add(sb)

    def provider(self, name: str) -> TableSessions:
        async def agree(peer: str) -> None:
            if peer in self.unreachable:
                raise ConnectionError(f"{peer} did not answer the key exchange")
            self.connect(name, peer)

        return TableSessions(self.tables[name], agree)


# -- end to end -----------------------------------------------------------------------------


async def test_export_to_import_end_to_end() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b", clock=ManualClock(7 * NS_PER_S))
        src = a.add_source(LOCAL)
        exporter = await net.exporter("uav-a")
        importer = await net.importer("uav-b")
        export = exporter.start_exporting(LOCAL, SEM, "uav-b", Policy())
        assert isinstance(export, Export) and export.name == "export[uav-a→uav-b:car5-state]"
        assert export.task is not None and export.task.get_name() == export.name
        values: list[Any] = [1.5, 7, "blue", {"x": 1.0, "tags": ["a"]}, (1, 2), None, True]
        for i, v in enumerate(values):
            src.push(v, valid_time=(i + 1) * NS_PER_S)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == len(values), "every sample injected")
        label = imported("uav-a", SEM)
        got = b.between(label, 0, 100 * NS_PER_S, all_estimates=True).samples
        assert [s.value for s in got] == [*values[:4], [1, 2], None, True]  # tuples: lists
        assert [s.valid_time for s in got] == [(i + 1) * NS_PER_S for i in range(len(values))]
        # available time is the arrival here, on the receiver's clock (unique per stream)
        arrival = 7 * NS_PER_S
        assert [s.available_time for s in got] == [arrival + i for i in range(len(values))]
        assert b.stream(label).location == "import/uav-a" == rec.location
        assert b.processes[f"import[uav-a:{SEM}]"].kind == "source"
        assert rec.sender == "uav-a" and rec.first_arrival == arrival
        assert export.stats()["sent"] == len(values) and export.dropped_total == 0
        assert importer.stats()["totals"]["injected"] == len(values)


async def test_end_to_end_with_real_sessions_agreed_on_first_send() -> None:
    tables = Tables("uav-a", "uav-b")
    async with network() as net:
        await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        src = net.instances["uav-a"].add_source(LOCAL)
        exporter = await net.exporter("uav-a", tables.provider("uav-a"))
        importer = await net.importer("uav-b", tables.provider("uav-b"))
        assert isinstance(tables.provider("uav-a"), SessionsProvider)
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push_batch([(float(i), i, i) for i in range(1000)])
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 1000, "every sample injected")
        assert [s.value for s in b.between(imported("uav-a", SEM), 0, 10**6).samples] == [
            float(i) for i in range(1000)
        ]
        session = tables.tables["uav-b"].sessions("uav-a")[0]
        assert session.received == rec.batches and session.confirmed


async def test_a_first_sight_while_the_export_agrees_its_session_drops_nothing() -> None:
    # The receiver's token first seen while the exporter waited for the key exchange: its
    # sessions are doubted (they may be a previous process's), and one more is agreed.
    tables = Tables("uav-a", "uav-b")
    provider = tables.provider("uav-a")
    agree = provider.agree
    assert agree is not None
    agreements = 0

    async def agree_then_first_sight(peer: str) -> None:
        nonlocal agreements
        await agree(peer)
        agreements += 1
        if agreements == 1:
            tables.tables["uav-a"].doubt(peer)

    provider.agree = agree_then_first_sight
    async with network() as net:
        await net.platform("uav-a")
        await net.platform("uav-b")
        src = net.instances["uav-a"].add_source(LOCAL)
        exporter = await net.exporter("uav-a", provider)
        importer = await net.importer("uav-b", tables.provider("uav-b"))
        export = exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push_batch([(float(i), i, i) for i in range(100)])
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 100, "every sample injected")
        assert agreements == 2 and export.dropped == {}


async def test_policy_is_applied_at_the_provider() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exporter = await net.exporter("uav-a")
        importer = await net.importer("uav-b")
        exporter.start_exporting(LOCAL, SEM, "uav-b", Policy(sample_period=0.5))
        step = NS_PER_S // 10
        for k in range(21):  # every 0.1 s for 2 s
            src.push(float(k), valid_time=k * step)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 5, "the grid points")
        got = b.between(imported("uav-a", SEM), 0, 10 * NS_PER_S).samples
        assert [s.valid_time for s in got] == [g * NS_PER_S // 2 for g in range(5)]
        assert [s.value for s in got] == [0.0, 5.0, 10.0, 15.0, 20.0]


async def test_history_from_a_past_start_is_exported() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        for k in range(5):
            src.push(k, valid_time=k)
        exporter = await net.exporter("uav-a")
        importer = await net.importer("uav-b")
        exporter.start_exporting(LOCAL, SEM, "uav-b", Policy(start=2))
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 3, "the history since start")


# -- isolation ------------------------------------------------------------------------------


class FreezingTransport(MemoryTransport):
    """Publishing to a frozen platform never returns (as a stalled link would)."""

    def __init__(self, hub: MemoryHub, frozen: str) -> None:
        super().__init__(hub)
        self.frozen_prefix = f"dyknow/{FED}/v1/stream/{frozen}/"
        self.stalled = asyncio.Event()
        self.never = asyncio.Event()

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        if key.startswith(self.frozen_prefix):
            self.stalled.set()
            await self.never.wait()
        await super().publish(key, payload, attachment=attachment)


async def test_a_frozen_receiver_does_not_slow_another() -> None:
    drops: list[tuple[str, str, int]] = []
    async with network() as net:
        hub = net.hub
        transport = FreezingTransport(hub, frozen="uav-c")
        _, a = await net.platform("uav-a", transport=transport)
        await net.platform("uav-b")
        exporter = await net.exporter(
            "uav-a",
            queue_size=64,
            batch_size=16,
            on_drop=lambda e, reason, n: drops.append((e.receiver, reason, n)),
        )
        importer = await net.importer("uav-b")
        # a platform that subscribed and never reads: its transport buffer overflows
        raw = await net.stack.enter_async_context(hub.transport())
        never_read = await raw.subscribe(stream_key("uav-d", "uav-a"), buffer_size=4)
        src = a.add_source(LOCAL)
        to_b = exporter.start_exporting(LOCAL, SEM, "uav-b")
        to_c = exporter.start_exporting(LOCAL, SEM, "uav-c")
        to_d = exporter.start_exporting(LOCAL, SEM, "uav-d")
        total = 4000
        for k in range(0, total, 10):
            # the instance hands samples over and returns: nothing here ever waits
            src.push_batch([(k + i, k + i, k + i) for i in range(10)])
            await asyncio.sleep(0)  # a sensor's pace: the exports get to run in between
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == total, "every sample at uav-b")
        await until(lambda: to_d.sent == total, "every sample published to uav-d")
        assert transport.stalled.is_set()
        assert to_b.dropped_total == 0 and rec.lost == 0 and rec.dropped_samples == {}
        # the frozen receiver lost the oldest samples of its own queue, counted and reported
        assert to_c.sent == 0 and to_c.dropped["queue-full"] >= total - 64 - 16
        assert len(to_c.queue) == 64
        assert (
            sum(n for r, why, n in drops if r == "uav-c" and why == "queue-full")
            == (to_c.dropped["queue-full"])
        )
        assert not [d for d in drops if d[0] != "uav-c"]
        # the one that never reads lost them in its transport buffer, not at the provider
        assert never_read.dropped > 0 and to_d.dropped_total == 0
        assert a.stream(LOCAL).stats()["samples_in"] == total


async def test_an_unreachable_receiver_costs_only_its_own_samples() -> None:
    tables = Tables("uav-a", "uav-b")
    tables.unreachable.add("uav-c")
    async with network() as net:
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        exporter = await net.exporter("uav-a", tables.provider("uav-a"), queue_size=100)
        importer = await net.importer("uav-b", tables.provider("uav-b"))
        src = a.add_source(LOCAL)
        to_b = exporter.start_exporting(LOCAL, SEM, "uav-b")
        to_c = exporter.start_exporting(LOCAL, SEM, "uav-c")
        for k in range(10):
            src.push_batch([(k * 100 + i, k * 100 + i, k * 100 + i) for i in range(100)])
            await asyncio.sleep(0)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 1000, "every sample at uav-b")
        await until(lambda: to_c.dropped.get("no-session"), "the failed agreement counted")
        assert "did not answer" in str(to_c.last_error) and to_c.sent == 0 and to_c.active
        assert to_b.dropped_total == 0


async def test_samples_lost_on_the_way_are_counted_by_the_receiver() -> None:
    class Lossy(MemoryTransport):
        n = 0

        async def publish(self, key: str, payload: bytes, **kw: Any) -> None:
            self.n += 1
            if self.n % 2 == 0:  # every other batch never arrives
                return
            await super().publish(key, payload, **kw)

    async with network() as net:
        _, a = await net.platform("uav-a", transport=Lossy(net.hub))
        await net.platform("uav-b")
        exporter = await net.exporter("uav-a", batch_size=10)
        importer = await net.importer("uav-b")
        src = a.add_source(LOCAL)
        export = exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push_batch([(i, i, i) for i in range(100)])
        await until(lambda: export.sent == 100, "every batch published")
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 50, "half of them")
        assert rec.lost == 40  # the last lost batch shows only when another follows
        src.push(1000, valid_time=1000)
        await until(lambda: rec.injected == 51, "one more")
        assert rec.lost == 50
        # the receiver reports the gap back: the provider counts what it could not see
        await until(
            lambda: export.dropped.get("lost-in-transit") == 50, "the loss reported to uav-a"
        )
        assert export.lost_in_transit == 50


# -- what is refused --------------------------------------------------------------------------


async def test_malformed_forged_unagreed_and_untrusted_batches_are_dropped_and_counted() -> None:
    tables = Tables("uav-a", "uav-b", "uav-c", "mallory", trusted=("uav-a", "uav-b", "uav-c"))
    tables.connect("uav-a", "uav-b")
    tables.connect("uav-c", "uav-b")
    # mallory holds a session table of its own, with keys uav-b does not trust
    outsider = Tables("mallory", "uav-b", trusted=("mallory", "uav-b"))
    outsider.connect("mallory", "uav-b")
    seal_a = tables.tables["uav-a"].seal_bytes
    seal_c = tables.tables["uav-c"].seal_bytes
    async with network() as net:
        await net.platform("uav-b")
        raw = await net.stack.enter_async_context(net.hub.transport())
        importer = await net.importer(
            "uav-b", tables.provider("uav-b"), translate=agreed(SEM, "other")
        )
        b = net.instances["uav-b"]
        good = pack_batch(SEM, [(1.0, 1, 1)])
        key = stream_key("uav-b", "uav-a")

        env = seal_a("uav-b", good)
        forged = env[:-1] + bytes([env[-1] ^ 1])
        bad_samples = pack_batch(SEM, [(2.0, 2, 2), (3.0, "not a time", 3), [4.0]])  # type: ignore[list-item]
        replayed = seal_a("uav-b", pack_batch(SEM, [(5.0, 5, 5)]))
        unknown = pack_batch("unknown", [(1, 1, 1), (2, 2, 2)])
        sends = [
            (key, b"garbage, not an envelope"),
            (key, forged),
            (stream_key("uav-b", "mallory"), outsider.tables["mallory"].seal_bytes("uav-b", good)),
            (stream_key("uav-b", "mallory"), b"\x93\x01\x02\x03"),
            (key, seal_a("uav-b", b"\x01 not a batch")),
            (key, seal_a("uav-b", msgpack.packb({"v": 2, "s": SEM, "b": []}))),
            (key, seal_a("uav-b", pack_batch("other", [(1.0, 1, 1)]))),  # body names another
            (stream_key("uav-b", "uav-a", "unknown"), seal_a("uav-b", unknown)),
            (stream_key("uav-b", "uav-c"), seal_a("uav-b", good)),  # authentic, wrong sender
            (stream_key("uav-b", "uav-c"), seal_c("uav-b", good)),  # uav-c's own: accepted
            (key, replayed),
            (key, replayed),
            (key, bad_samples),
            (key, seal_a("uav-b", bad_samples)),
        ]  # fmt: skip
        for k, payload in sends:
            await raw.publish(k, payload)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 2, "the replayed batch once and the good sample")
        values = [s.value for s in b.between(imported("uav-a", SEM), 0, 100).samples]
        assert values == [2.0, 5.0]
        assert rec.dropped_batches == {
            "malformed": 4,
            "forged": 1,
            "wrong-label": 1,
            "replayed": 1,
        }
        assert rec.dropped_samples == {"malformed": 2}
        by_stream = {(s["sender"], s["semantic_label"]): s for s in importer.stats()["strays"]}
        assert by_stream[("uav-a", "unknown")]["dropped_samples"] == {"unagreed": 2}
        assert by_stream[("mallory", SEM)]["dropped_batches"] == {"untrusted": 1, "malformed": 1}
        # a batch of uav-a's published under uav-c's name: authentic, but not trusted as uav-c's
        from_c = importer.get("uav-c", SEM)
        assert from_c is not None and from_c.dropped_batches == {"wrong-sender": 1}
        assert from_c.injected == 1
        assert not b.has_label(imported("uav-a", "unknown"))
        assert not b.has_label(imported("mallory", SEM))
        totals = importer.stats()["totals"]
        assert totals["injected"] == 3 and totals["batches"] == len(sends)


async def test_a_label_taken_locally_is_not_overwritten() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        mine = b.add_source(imported("uav-a", SEM))
        mine.push("local", valid_time=1)
        src = a.add_source(LOCAL)
        exporter = await net.exporter("uav-a")
        importer = await net.importer("uav-b")
        with pytest.raises(DuplicateLabelError):
            importer.expect("uav-a", SEM, imported("uav-a", SEM))
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push("remote", valid_time=2)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.dropped_samples, "the refusal")
        assert rec.dropped_samples == {"label-taken": 1} and rec.injected == 0
        assert [s.value for s in b.between(imported("uav-a", SEM), 0, 10).samples] == ["local"]


async def test_expect_agrees_an_import_the_translation_does_not_know() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        importer = await net.importer("uav-b", translate=lambda sender, semantic: None)
        rec = importer.expect("uav-a", SEM, "mine/car5")
        assert importer.expect("uav-a", SEM, "mine/car5") is rec
        assert importer.imports("uav-a") == [rec] and rec.source is None
        exporter = await net.exporter("uav-a")
        src = a.add_source(LOCAL)
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push(1, valid_time=1)
        await until(lambda: rec.injected == 1, "the sample")
        assert b.latest("mine/car5").samples[0].value == 1
        with pytest.raises(ValueError, match="already lands"):
            importer.expect("uav-a", SEM, "elsewhere")
        assert importer.forget("uav-a", SEM) is rec and rec.ended
        src.push(2, valid_time=2)
        await until(lambda: importer.stats()["totals"]["dropped_samples"], "the unagreed sample")
        assert importer.stats()["totals"]["dropped_samples"] == {"unagreed": 1}
        # agreed again: a new stream replaces the ended one under the same label
        again = importer.expect("uav-a", SEM, "mine/car5")
        assert again is not rec
        src.push(3, valid_time=3)
        await until(lambda: again.injected == 1, "the sample after the new agreement")
        assert [s.value for s in b.between("mine/car5", 0, 10).samples] == [3]


async def test_an_import_works_through_a_backlog_in_order_letting_other_tasks_run() -> None:
    """300 batches queued at once are all imported, in order, none counted lost, while the
    loop's other tasks still get their turns every 64 batches (not only at the end)."""
    async with network() as net:
        ta, _ = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        importer = await net.importer("uav-b")
        sealer = PlainSessions("uav-a")
        key = stream_key("uav-b", "uav-a")
        seen: list[int] = []  # how many batches the import had taken at each other turn

        async def other_task() -> None:
            while True:
                rec = importer.get("uav-a", SEM)
                seen.append(0 if rec is None else rec.batches)
                await asyncio.sleep(0)

        watcher = asyncio.create_task(other_task())
        try:
            await asyncio.sleep(0)
            for i in range(300):  # queued in the import's inbox without a turn in between
                body = pack_batch(SEM, [(i, i + 1, 0)], i)
                ta.publish_nowait(key, sealer.seal_bytes("uav-b", body))
            rec = await until(lambda: importer.get("uav-a", SEM), "the import")
            await until(lambda: rec.injected == 300, "all the batches")
        finally:
            watcher.cancel()
            await asyncio.wait([watcher])
        got = b.between(imported("uav-a", SEM), 0, 10**6).samples
        assert [s.value for s in got] == list(range(300))
        assert (rec.batches, rec.lost, rec.gaps) == (300, 0, 0)
        between = sorted({n for n in seen if 0 < n < 300})
        assert between[:4] == [64, 128, 192, 256]


# -- membership ---------------------------------------------------------------------------------


async def test_sender_gone_ends_its_imported_streams_and_tells() -> None:
    told: list[tuple[str, list[str]]] = []
    gone = asyncio.Event()

    async def on_gone(sender: str, labels: list[str]) -> None:
        told.append((sender, labels))
        gone.set()

    async with network() as net:
        ta, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        token = await ta.declare_token(f"dyknow/{FED}/v1/alive/uav-a")
        importer = await net.importer("uav-b", on_sender_gone=on_gone)
        exporter = await net.exporter("uav-a")
        src = a.add_source(LOCAL)
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push(1, valid_time=1)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 1, "the first sample")
        label = imported("uav-a", SEM)
        sub = b.subscribe(label)
        reader = asyncio.ensure_future(sub.batches().__anext__())
        src.push(2, valid_time=2)
        assert [v for v, _, _ in await reader] == [2]

        async def drain() -> list[Any]:
            return [s.value async for s in sub]

        ended = asyncio.ensure_future(drain())
        token.close()  # uav-a dies
        await gone.wait()
        assert told == [("uav-a", [SEM])]
        assert await ended == []  # the subscriber's iterator ended
        assert rec.ended and rec.source is not None and not rec.source.running
        # its history stays queryable
        assert [s.value for s in b.between(label, 0, 10).samples] == [1, 2]
        # what was still on its way is not injected into the ended stream
        src.push(3, valid_time=3)
        await until(lambda: rec.dropped_samples, "the late sample")
        assert rec.dropped_samples == {"sender-gone": 1}
        # uav-a comes back and exports again: a new stream under the same label
        await ta.declare_token(f"dyknow/{FED}/v1/alive/uav-a")
        src.push(4, valid_time=4)
        await until(lambda: rec.injected == 3, "the sample after the return")
        assert not rec.ended and [s.value for s in b.between(label, 0, 10).samples] == [4]


async def test_sender_gone_can_remove_the_streams() -> None:
    async with network() as net:
        ta, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        token = await ta.declare_token(f"dyknow/{FED}/v1/alive/uav-a")
        gone = asyncio.Event()
        importer = await net.importer(
            "uav-b", keep_ended=False, on_sender_gone=lambda s, labels: gone.set()
        )
        exporter = await net.exporter("uav-a")
        src = a.add_source(LOCAL)
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push(1, valid_time=1)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 1, "the sample")
        token.close()
        await gone.wait()
        assert not b.has_label(imported("uav-a", SEM)) and rec.ended


# -- stopping -------------------------------------------------------------------------------------


async def test_stop_ends_the_export() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        await net.platform("uav-c")
        exporter = await net.exporter("uav-a")
        importer = await net.importer("uav-b")
        src = a.add_source(LOCAL)
        a.add_source("other")
        export = exporter.start_exporting(LOCAL, SEM, "uav-b")
        other = exporter.start_exporting("other", "other", "uav-b")
        to_c = exporter.start_exporting(LOCAL, SEM, "uav-c")
        assert exporter.find("uav-b", SEM) is export
        assert set(map(id, exporter.exports("uav-b"))) == {id(export), id(other)}
        src.push(1, valid_time=1)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 1, "the first sample")
        await exporter.stop(export)
        assert not export.active and export.ended == "stopped"
        assert export.subscription is not None and export.subscription.closed
        assert export.task is not None and export.task.done()
        assert exporter.find("uav-b", SEM) is None
        src.push(2, valid_time=2)
        await until(lambda: to_c.sent == 2, "the other receiver still served")
        assert export.sent == 1 and rec.injected == 1
        assert await exporter.stop_all("uav-b") == [other] and not other.active
        assert exporter.exports() == [to_c]
        # the same label may be exported again once stopped
        again = exporter.start_exporting(LOCAL, SEM, "uav-b")
        src.push(3, valid_time=3)
        await until(lambda: rec.injected == 2, "the restarted export")
        assert again.sent == 1


async def test_an_export_ends_with_its_local_stream(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_export, "_IDLE_CHECK", 0.01)
    async with network() as net:
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        exporter = await net.exporter("uav-a")
        a.add_source(LOCAL)
        export = exporter.start_exporting(LOCAL, SEM, "uav-b")
        a.remove_process(f"source:{LOCAL}")
        assert export.task is not None
        await export.task
        assert export.ended == "the local stream ended" and exporter.exports() == []


async def test_refused_exports() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        exporter = await net.exporter("uav-a")
        a.add_source(LOCAL)
        with pytest.raises(UnknownLabelError):
            exporter.start_exporting("nope", SEM, "uav-b")
        for label in ("", "car 5", "car/*", "a//b", "x#", "$x"):
            with pytest.raises(ValueError, match="semantic label"):
                exporter.start_exporting(LOCAL, label, "uav-b")
        with pytest.raises(ValueError, match="itself"):
            exporter.start_exporting(LOCAL, SEM, "uav-a")
        with pytest.raises(ValueError):
            exporter.start_exporting(LOCAL, SEM, "uav/b")
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        with pytest.raises(ValueError, match="already exported"):
            exporter.start_exporting(LOCAL, SEM, "uav-b")
        assert len(exporter.exports()) == 1


# -- values and sizes ------------------------------------------------------------------------------


async def test_unencodable_values_are_dropped_and_large_batches_split() -> None:
    async with network() as net:
        _, a = await net.platform("uav-a")
        _, b = await net.platform("uav-b")
        exporter = await net.exporter("uav-a", max_batch_bytes=1024)
        importer = await net.importer("uav-b", translate=agreed(SEM, "multi/chunk/label"))
        src = a.add_source(LOCAL)
        export = exporter.start_exporting(LOCAL, "multi/chunk/label", "uav-b")
        big = "x" * 200
        src.push_batch([(big, i, i) for i in range(20)] + [(object(), 20, 20), (big, 21, 21)])
        src.push("y" * 5000, valid_time=22)  # alone over the limit
        rec = await until(lambda: importer.get("uav-a", "multi/chunk/label"), "the import")
        await until(lambda: rec.injected == 21, "the encodable samples")
        assert export.batches > 4 and export.sent == 21
        assert export.dropped == {"unencodable": 1, "too-large": 1}
        assert "object" in str(export.dropped) or export.last_error is not None
        assert rec.lost == 0
        assert len(b.between(imported("uav-a", "multi/chunk/label"), 0, 100).samples) == 21


def test_batch_format() -> None:
    body = pack_batch(SEM, [(1.5, 10, 11), ({"k": (1, 2)}, 12, 13)], seq=7)
    assert msgpack.unpackb(body) == {
        "v": 1,
        "s": SEM,
        "q": 7,
        "b": [[1.5, 10, 11], [{"k": [1, 2]}, 12, 13]],
    }
    assert unpack_batch(body) == (SEM, 7, [[1.5, 10, 11], [{"k": [1, 2]}, 12, 13]])
    assert unpack_batch(msgpack.packb({"v": 1, "s": SEM, "b": []})) == (SEM, None, [])
    for bad in (b"\xc1", msgpack.packb([1, SEM, []]), msgpack.packb({"v": 2, "s": SEM, "b": []})):
        with pytest.raises(ValueError):
            unpack_batch(bad)


class _Mode(enum.Enum):
    HOVER = "hover"


def test_batches_packed_on_many_threads_at_once_are_each_their_own() -> None:
    """pack_batch from several threads at once (values its encoder turns, Python code run
    mid-pack, while threads switch often): each body is what msgpack alone makes of it, and
    a value it cannot encode raises without spoiling the next body."""

    def expected(label: str, samples: list[Any], seq: int) -> bytes:
        obj = {"v": 1, "s": label, "q": seq, "b": samples}
        body: bytes = msgpack.packb(
            obj, default=lambda v: v.value if isinstance(v, enum.Enum) else list(v)
        )
        return body

    failures: list[str] = []

    def packing(t: int) -> None:
        label = f"stream-{t}"
        for i in range(300):
            # many values for the encoder: many points where another thread may run
            samples = [(_Mode.HOVER, i, j) for j in range(20)] + [({t, i}, i, i + 1)]
            if pack_batch(label, samples, i) != expected(label, samples, i):
                failures.append(f"thread {t}, body {i}")
            if i % 50 == 0:
                with pytest.raises(TypeError):
                    pack_batch(label, [(object(), i, i)], i)

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        threads = [threading.Thread(target=packing, args=(t,)) for t in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=WAIT)
    finally:
        sys.setswitchinterval(switch)
    assert not any(thread.is_alive() for thread in threads)
    assert failures == []


def test_a_large_batch_body_leaves_no_buffer_behind() -> None:
    """A body of many megabytes (a batch of large values, one later dropped as too large,
    or one that fails past them) does not keep its memory once packed: the next small
    batch packs as before, and what packing it held is freed (a packer kept per thread
    keeps the buffer of its largest body for the thread's life, an event loop's: the
    process's)."""
    large = b"x" * (8 << 20)
    pack_batch("cam/frames", [(1.0, 1, 1)])  # this thread has packed before
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        body = pack_batch("cam/frames", [(large, 2, 2)])
        assert len(body) > len(large)
        del body
        assert unpack_batch(pack_batch("cam/frames", [(3.0, 3, 3)]))[2] == [[3.0, 3, 3]]
        kept = tracemalloc.get_traced_memory()[0] - before
        # one that fails past its 8 MiB (a value it cannot encode after it): the same
        with pytest.raises(TypeError):
            pack_batch("cam/frames", [([large, object()], 4, 4)])
        assert unpack_batch(pack_batch("cam/frames", [(5.0, 5, 5)]))[2] == [[5.0, 5, 5]]
        kept_failed = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert kept < 1 << 20, f"{kept} bytes kept after packing an 8 MiB body"
    assert kept_failed < 1 << 20, f"{kept_failed} bytes kept after a pack failed past 8 MiB"


# -- over real Interface Agents -------------------------------------------------------------------


async def test_over_interface_agents_session_agreed_then_sender_gone() -> None:
    hub = MemoryHub()
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}

    def trust_copy() -> TrustStore:
        return TrustStore(FED, {n: k.public_key for n, k in keys.items()})

    told = asyncio.Event()
    async with contextlib.AsyncExitStack() as stack, contextlib.AsyncExitStack() as stack_a:
        async with asyncio.timeout(WAIT):
            platforms = {}
            for n, owner in (("uav-a", stack_a), ("uav-b", stack)):
                t = await owner.enter_async_context(hub.transport())
                channel = InterfaceAgent(keys[n], trust_copy(), publish_audit=False)
                platforms[n] = await owner.enter_async_context(
                    AgentPlatform(n, t, federation=FED, channel=channel)
                )
            a = await stack.enter_async_context(DyKnowInstance("uav-a"))
            b = await stack.enter_async_context(DyKnowInstance("uav-b"))
            pa, pb = platforms["uav-a"], platforms["uav-b"]
            assert isinstance(pa.channel, InterfaceAgent) and isinstance(pb.channel, InterfaceAgent)
            importer = await stack.enter_async_context(
                ImportProxy(
                    "uav-b",
                    FED,
                    pb.transport,
                    b,
                    InterfaceSessions(pb.channel),
                    agreed(SEM),
                    on_sender_gone=lambda s, labels: told.set(),
                )
            )
            exporter = ExportProxy("uav-a", FED, pa.transport, a, InterfaceSessions(pa.channel))
            src = a.add_source(LOCAL)
            export = exporter.start_exporting(LOCAL, SEM, "uav-b")
            src.push_batch([(i, i, i) for i in range(500)])
            rec = await until(lambda: importer.get("uav-a", SEM), "the import")
            await until(lambda: rec.injected == 500, "every sample")
            assert pa.channel.sessions.peers() == ["uav-b"] and export.dropped_total == 0
            await exporter.aclose()
            assert not export.active
            await stack_a.aclose()  # uav-a stops: its liveliness token goes
            await told.wait()
            assert rec.ended


# -- a SIGKILLed sender, over zenoh ---------------------------------------------------------------

START = 20.0  # a spawned interpreter imports zenoh and pydantic: seconds on a loaded machine


def exporting_child_main(config: dict[str, Any], federation: str) -> None:
    """A child platform ``uav-a``: exports ``car5-state`` to ``uav-b`` every 5 ms until killed."""
    asyncio.run(_exporting_child(config, federation))


async def _exporting_child(config: dict[str, Any], federation: str) -> None:
    async with (
        ZenohTransport(ZenohConfig.model_validate(config)) as t,
        DyKnowInstance("uav-a") as dk,
        ExportProxy("uav-a", federation, t, dk, PlainSessions("uav-a")) as exporter,
    ):
        src = dk.add_source(LOCAL)
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        await t.declare_token(f"dyknow/{federation}/v1/alive/uav-a")
        k = 0
        while True:
            src.push(k)
            k += 1
            await asyncio.sleep(0.005)


async def test_a_sigkilled_sender_is_told_within_a_second_over_zenoh() -> None:
    federation = f"t{uuid.uuid4().hex[:8]}"
    port = free_tcp_port()
    child = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
    proc = multiprocessing.get_context("spawn").Process(
        target=exporting_child_main, args=(child, federation), name="proxies-child"
    )
    gone = asyncio.Event()
    told: list[tuple[str, list[str]]] = []

    def on_gone(sender: str, labels: list[str]) -> None:
        told.append((sender, labels))
        gone.set()

    try:
        async with (
            ZenohTransport(ZenohConfig.loopback(port)) as t,
            DyKnowInstance("uav-b") as dk,
            ImportProxy(
                "uav-b", federation, t, dk, PlainSessions("uav-b"), agreed(SEM),
                on_sender_gone=on_gone,
            ) as importer,
        ):  # fmt: skip
            proc.start()
            rec = await until(lambda: importer.get("uav-a", SEM), "the first batch", START)
            await until(lambda: rec.injected >= 3, "a few samples")
            sub = dk.subscribe(imported("uav-a", SEM))
            assert proc.pid is not None
            killed = time.monotonic()
            os.kill(proc.pid, signal.SIGKILL)
            async with asyncio.timeout(1.0):
                await gone.wait()
                async for _ in sub:  # the subscriber's iterator ends
                    pass
            took = time.monotonic() - killed
            assert told == [("uav-a", [SEM])] and rec.ended
            print(f"zenoh: imported stream ended {took * 1000:.1f} ms after SIGKILL")
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join(timeout=10)


async def test_a_resend_waits_for_room_on_a_link_that_drops_what_its_queue_cannot_take() -> None:
    # zenoh publishes with congestion control DROP: resent bodies published back to back
    # overflowed its queue after a partition healed, and a number is resent only once;
    # a resend goes through publish_blocking, which waits for room instead (BLOCK)
    drain = 200_000  # bytes/s the modelled queue takes: slower than a burst
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", max_batch_bytes=1024)
        imp = await net.importer("uav-b", translate=agreed(SEM))
        mode = "ok"
        busy_until = 0.0
        overflowed = waited = 0
        publish = ta.publish

        def room(payload: bytes) -> float:
            """Seconds until the modelled queue takes ``payload`` (0: taken now)."""
            nonlocal busy_until
            if mode != "queue" or len(payload) <= 512:
                return 0.0  # a body near a batch's size takes a batch of its own
            now = time.monotonic()
            if now < busy_until:
                return busy_until - now
            busy_until = now + len(payload) / drain
            return 0.0

        async def queued(key: str, payload: bytes, *args: Any, **kwargs: Any) -> Any:
            nonlocal overflowed
            if "/stream/" in key and mode == "drop":
                return None  # the partition: lost on the way
            if "/stream/" in key and room(payload):  # still taking the previous body
                overflowed += 1
                return None  # dropped, silently
            return await publish(key, payload, *args, **kwargs)

        async def blocking(key: str, payload: Any) -> None:
            nonlocal waited
            if not isinstance(payload, bytes):  # made when the put can start
                payload = await payload()
            while "/stream/" in key and (wait := room(payload)):
                waited += 1
                await asyncio.sleep(wait)
            await publish(key, payload)

        ta.publish = queued  # type: ignore[method-assign]
        ta.publish_blocking = blocking  # type: ignore[method-assign]
        export = exp.start_exporting(LOCAL, SEM, "uav-b", history=10)
        pad = "x" * 300  # about 3 samples a body: the history's 10 go as 4 bodies

        async def push(n: int) -> None:
            for _ in range(n):
                src.push(pad)
                await asyncio.sleep(0.02)

        await push(3)
        mode = "drop"
        await push(20)
        mode = "queue"
        src.push(0)  # the gap's end arrives (a small body): the 10 before it are asked back at once
        rec = await until(lambda: imp.get("uav-a", SEM), "the import")
        await until(lambda: export.recovered == 10, "the history resent")
        await until(lambda: rec.recovered == 10, f"all 10 arrived ({overflowed} dropped)")
        # the bodies came back to back: without waiting, the queue would have dropped some
        assert overflowed == 0 and waited > 0 and rec.lost == 10


async def test_a_proxy_whose_subscription_the_transport_ends_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # a proxy on its own (no platform to count the loss): its streams or loss reports
    # ended by the transport (MQTT: refused after a reconnection), it logged nothing
    async with network() as net:
        t, a = await net.platform("uav-a")
        subs: dict[str, Any] = {}
        subscribe = t.subscribe

        async def subscribed(key: str, **options: Any) -> Any:
            subs[key] = sub = await subscribe(key, **options)
            return sub

        t.subscribe = subscribed  # type: ignore[method-assign]
        a.add_source(LOCAL)
        exporter = await net.exporter("uav-a")
        importer = await net.importer("uav-a")
        exporter.start_exporting(LOCAL, SEM, "uav-b")
        streams, reports = (
            f"dyknow/{FED}/v1/stream/uav-a/*/**",
            f"dyknow/{FED}/v1/stream-report/uav-a/*",
        )
        await until(lambda: reports in subs, "the loss reports subscribed to")
        told: list[tuple[str, str]] = []
        importer.on_lost = lambda sub, what, meaning: told.append((what, meaning))
        subs[streams].inbox.close()  # as a transport ends it
        subs[reports].inbox.close()
        await until(lambda: told, "the import told")
        assert told == [
            (
                f"streams subscription {streams}",
                "other platforms' streams to this platform are no longer received: its "
                "imports get no more samples and count none lost, while its loss reports "
                "still renew their senders' leases (the senders go on exporting)",
            )
        ]
        errors = await until(
            lambda: [r.getMessage() for r in caplog.records if r.name == "federation._proxy_base"],
            "the export's loss logged",
        )
        assert errors == [
            f"export[uav-a]: lost its loss reports subscription {reports} (the transport ended "
            "the subscription): receivers' loss reports are not heard until the subscription "
            "is made again (tried with backoff): meanwhile this platform's exports may end at "
            "their lease as if their receivers were gone, their losses in transit not counted "
            "nor resent"
        ]


class FlakyReports(MemoryTransport):
    """A memory transport on which the first subscription to loss reports fails, then works.

    ``mode`` ``refused``: making it raises (a broker briefly unreachable, or refusing it);
    ``ended``: it is made, and ended by the transport at once (MQTT: refused after a
    reconnection).
    """

    def __init__(self, hub: MemoryHub, mode: str) -> None:
        super().__init__(hub)
        self.mode = mode
        self.failed = 0

    async def subscribe(self, key_expr: str, **options: Any) -> Any:
        first = "/stream-report/" in key_expr and not self.failed
        if first and self.mode == "refused":
            self.failed += 1
            raise TransportError(f"memory: the subscription to {key_expr!r} refused, this once")
        sub = await super().subscribe(key_expr, **options)
        if first:
            self.failed += 1
            sub.inbox.close()  # as a transport ends it: the iterator ends, not closed
        return sub


@pytest.mark.parametrize("mode", ["refused", "ended"])
async def test_loss_reports_whose_subscription_failed_once_are_heard_again(
    mode: str, caplog: pytest.LogCaptureFixture
) -> None:
    # the subscription, failed once, was never made again: every export ended at its
    # lease as if its receiver were gone, however alive and reporting the receiver was
    caplog.set_level(logging.DEBUG, logger="federation._export")
    lease = 1.0
    async with network() as net:
        t = FlakyReports(net.hub, mode)
        _, a = await net.platform("uav-a", transport=t)
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exporter = await net.exporter("uav-a", lease=lease)
        told: list[str] = []
        exporter.on_lost = lambda sub, what, meaning: told.append(what)
        importer = await net.importer("uav-b", report_interval=0.05)
        export = exporter.start_exporting(LOCAL, SEM, "uav-b")
        started = time.monotonic()
        src.push(1.0)
        rec = await until(lambda: importer.get("uav-a", SEM), "the import")
        await until(lambda: rec.injected == 1, "the sample at the receiver")
        # its receiver's reports keep it going past its lease, and half another
        await until(lambda: export.last_heard - started > 1.5 * lease, "reports past its lease")
        assert export.active and export.dropped_total == 0
        assert t.failed == 1 and exporter.reports_subscription_failures == 1
        assert exporter.task_failures == 0
        key = f"dyknow/{FED}/v1/stream-report/uav-a/*"
        # the transport's end is the platform's loss, as ever; a failure to make it is not
        assert told == ([f"loss reports subscription {key}"] if mode == "ended" else [])
        said = [
            (r.levelno, r.getMessage()) for r in caplog.records if r.name == "federation._export"
        ]
        why = (
            f"cannot subscribe to {key}: memory: the subscription to {key!r} refused, this once"
            if mode == "refused"
            else f"the transport ended {key}"
        )
        assert said == [
            (
                logging.WARNING,
                f"export[uav-a]: receivers' loss reports not heard: {why}; subscribing again "
                "in 0.05 s",
            ),
            (
                logging.WARNING,
                f"export[uav-a]: subscribed to receivers' loss reports again ({key}) after "
                "1 failure(s)",
            ),
        ]
        # a closed transport ends it: no subscribing again, no failure
        reports = exporter._reports
        assert reports is not None and not reports.done()
        await t.aclose()
        await until(reports.done, "the loss reports' task ended")
        assert exporter.reports_subscription_failures == 1 and exporter.task_failures == 0
        assert len(told) == (1 if mode == "ended" else 0)


async def test_an_import_proxy_whose_own_presence_watch_the_transport_ends_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # an import proxy on its own watches senders' presence itself: that watch ended by
    # the transport (MQTT: refused after a reconnection), a sender that goes was no longer
    # seen (its streams never ended here) and nothing said so
    async with network() as net:
        t, _ = await net.platform("uav-a")
        watched: dict[str, Any] = {}
        watch = t.watch_presence

        async def watching(key: str, **options: Any) -> Any:
            watched[key] = sub = await watch(key, **options)
            return sub

        t.watch_presence = watching  # type: ignore[method-assign]
        importer = await net.importer("uav-a")
        alive = f"dyknow/{FED}/v1/alive/*"
        meaning = (
            "senders coming and going are no longer seen: the streams of one that goes are "
            "no longer ended here (on_sender_gone untold), and one seen gone before that "
            "comes back has its samples dropped (sender-gone) and no loss reports (its "
            "exports here end at their lease)"
        )
        watched[alive].inbox.close()  # as a transport ends it
        errors = await until(
            lambda: [r.getMessage() for r in caplog.records if r.name == "federation._proxy_base"],
            "the import's loss logged",
        )
        errors_at = [r for r in caplog.records if r.name == "federation._proxy_base"]
        assert errors == [
            f"import[uav-a]: lost its presence watch {alive} (the transport ended the "
            f"subscription): {meaning}"
        ]
        # with on_lost set (a platform's `ended`), it is told instead
        importer = await net.importer("uav-a")
        told: list[tuple[str, str]] = []
        importer.on_lost = lambda sub, what, meaning: told.append((what, meaning))
        watched[alive].inbox.close()
        await until(lambda: told, "the import told")
        assert told == [(f"presence watch {alive}", meaning)]
    # closed by its proxy: no loss
    assert len(told) == 1
    assert [r for r in caplog.records if r.name == "federation._proxy_base"] == errors_at


async def test_the_receiver_is_told_when_its_exports_lease_expires() -> None:
    ended: list[tuple[str, str]] = []
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", lease=1.0)
        imp = await net.importer("uav-b", translate=agreed(SEM))
        imp.on_export_ended = lambda sender, label: ended.append((sender, label))
        export = exp.start_exporting(LOCAL, SEM, "uav-b")
        src.push(0)
        rec = await until(lambda: imp.get("uav-a", SEM), "the first sample")
        real = imp._report

        async def stalled(*_: Any, **__: Any) -> None:
            """The receiver does not report (a long pause): its lease runs out."""

        imp._report = stalled  # type: ignore[method-assign]
        await until(lambda: export.ended, "the lease expired", 5.0)
        imp._report = real  # type: ignore[method-assign]
        await until(lambda: rec.ended, "the receiver told", 5.0)
        assert ended == [("uav-a", SEM)] and export.ended.startswith("lease-expired")


async def test_an_idle_stream_created_again_after_its_sender_was_gone_keeps_its_lease() -> None:
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", lease=1.0)
        imp = await net.importer("uav-b", translate=agreed(SEM))
        first = exp.start_exporting(LOCAL, SEM, "uav-b")
        src.push(1)
        rec = await until(lambda: imp.get("uav-a", SEM), "the first sample")
        # what the importer does when uav-a's token goes (a router restart), then returns
        imp._gone.add("uav-a")
        imp._end(rec)
        imp._gone.discard("uav-a")
        await exp.stop(first)
        again = exp.start_exporting(LOCAL, SEM, "uav-b")  # created again; the source is quiet
        start = again.last_heard
        # reported on past two leases (1 s each), or ended
        await until(lambda: again.last_heard > start + 2.0 or again.ended, "two leases", 2 + WAIT)
        assert again.active, again.ended


async def test_a_new_export_does_not_inherit_the_losses_of_the_old_one() -> None:
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a")
        imp = await net.importer("uav-b", translate=agreed(SEM))
        drop = False
        publish = ta.publish

        async def lossy(key: str, payload: bytes, *args: Any, **kwargs: Any) -> Any:
            if drop and "/stream/" in key:
                return None  # lost on the way
            return await publish(key, payload, *args, **kwargs)

        ta.publish = lossy  # type: ignore[method-assign]
        old = exp.start_exporting(LOCAL, SEM, "uav-b")
        for i in range(10):
            src.push(i)
        await until(lambda: (r := imp.get("uav-a", SEM)) is not None and r.injected == 10, "10")
        drop = True
        for i in range(10):
            src.push(i)
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
        drop = False
        for i in range(10):
            src.push(i)
        await until(lambda: old.dropped.get("lost-in-transit") == 10, "the old one told of 10")
        await exp.stop(old)
        new = exp.start_exporting(LOCAL, SEM, "uav-b")
        for i in range(10):
            src.push(i)
        rec = imp.get("uav-a", SEM)
        assert rec is not None
        await until(lambda: rec.injected == 30, "the new one delivered its 10")
        for report in ("a report", "the next report"):  # each with the receiver's total
            heard = new.last_heard
            await until(lambda heard=heard: new.last_heard > heard, report)
        assert new.dropped == {} and rec.lost == 10  # the receiver's total stays


def test_an_export_lease_shorter_than_four_report_intervals_is_refused() -> None:
    base = {"name": "a", "federation": "f", "key": "k", "trust": "t"}
    base |= {"vocabulary": {}, "mapping": {}}
    with pytest.raises(PlatformConfigError, match="export_lease"):
        PlatformConfig.from_dict({**base, "export_lease": 0.3})
    assert PlatformConfig.from_dict({**base, "export_lease": 2.0}).export_lease == 2.0


async def test_send_failures_recovered_from_history_are_no_longer_counted_dropped() -> None:
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a")
        imp = await net.importer("uav-b", translate=agreed(SEM), report_interval=0.05)
        mode = "ok"
        publish = ta.publish

        async def flaky(key: str, payload: bytes, *args: Any, **kwargs: Any) -> Any:
            if "/stream/" in key and mode == "raise":
                raise RuntimeError("congested")  # a send failure: counted at the sender
            if "/stream/" in key and mode == "drop":
                return None  # lost on the way, silently: the receiver counts it
            return await publish(key, payload, *args, **kwargs)

        ta.publish = flaky  # type: ignore[method-assign]
        export = exp.start_exporting(LOCAL, SEM, "uav-b", history=10)

        def rec() -> Any:
            return imp.get("uav-a", SEM)

        async def push(n: int) -> None:
            for i in range(n):
                src.push(i)
                await asyncio.sleep(0.005)
            await asyncio.sleep(0.05)

        await push(5)
        mode = "raise"
        await push(10)
        mode = "ok"
        await push(5)
        await until(lambda: rec().recovered == 10 and rec().lost == 0, "the 10 failed resent")
        assert "send-failed" not in export.dropped  # they arrived after all
        mode = "drop"
        await push(30)
        mode = "ok"
        await push(5)
        await until(lambda: rec().recovered == 20, "10 of the 30 resent (history 10)")
        await until(
            lambda: export.dropped.get("lost-in-transit", 0) == rec().lost == 20,
            "the sender counts what the receiver lost",
        )


# -- a resend waiting for room: sealed when it leaves, not when it begins to wait -----------

_SKEW = 0.3  # the receiver's allowed age of an envelope, scaled down from 30 s


_FROZEN = 3.0  # how long a put to a frozen receiver holds the worker: far above any bound


class _Pooled(MemoryTransport):
    """A memory transport whose blocking puts share one worker, as zenoh's share a few threads.

    A put to a frozen receiver holds it (zenoh's BLOCK waits for room in that link's
    queue); the others wait for it, as a task waits in zenoh's executor queue.
    """

    def __init__(self, hub: MemoryHub, workers: int = 1) -> None:
        super().__init__(hub)
        self.pool = asyncio.Semaphore(workers)
        self.drop_streams = False
        self.frozen_puts = 0  # puts to a frozen receiver holding a worker now

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Lose stream batches while the link is down (the gap a resend fills)."""
        if self.drop_streams and "/stream/" in key:
            return
        await super().publish(key, payload, attachment=attachment)

    async def publish_blocking(self, key: str, payload: Any) -> None:
        """One at a time; a frozen receiver's put holds the worker for a while."""
        async with self.pool:
            if callable(payload):
                payload = await payload()
            if "/frozen/" in key or "/stream/uav-f/" in key:
                self.frozen_puts += 1
                try:
                    await asyncio.sleep(_FROZEN)
                finally:
                    self.frozen_puts -= 1
                return
            await super().publish(key, payload)


_sealed: dict[bytes, float] = {}


class _Stamped(PlainSessions):
    """Plain envelopes that expire, as a real session's do past the allowed skew."""

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal, remembering when."""
        envelope = super().seal_bytes(peer, body)
        _sealed[envelope] = time.monotonic()
        return envelope

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Open, refusing an envelope sealed longer ago than the skew."""
        frm, body = super().open_bytes(envelope)
        if time.monotonic() - _sealed.get(envelope, time.monotonic()) > _SKEW:
            raise Expired("sealed too long ago", frm)
        return frm, body


async def test_a_resend_waiting_behind_a_frozen_receivers_put_is_not_lost() -> None:
    """A resend sealed, then kept waiting for the worker, would arrive expired: lost for good."""
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta = _Pooled(net.hub)
        _, a = await net.platform("uav-a", transport=ta)
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", sessions=_Stamped("uav-a"), max_batch_bytes=1024)
        imp = await net.importer("uav-b", sessions=_Stamped("uav-b"), translate=agreed(SEM))
        export = exp.start_exporting(LOCAL, SEM, "uav-b", history=10)
        for _ in range(3):
            src.push(1)
            await asyncio.sleep(0.02)
        ta.drop_streams = True
        for _ in range(5):
            src.push(2)
            await asyncio.sleep(0.02)
        ta.drop_streams = False
        # the attacker: a frozen receiver's resend holds the worker when ours is asked
        frozen = asyncio.ensure_future(ta.publish_blocking("dyknow/x/frozen/uav-f", b"x"))
        await asyncio.sleep(0)
        src.push(3)  # the gap's end arrives: the 5 lost are asked back at once
        rec = await until(lambda: imp.get("uav-a", SEM), "the import")
        await until(lambda: export.recovered == 5, "the history resent", _FROZEN + WAIT)
        await frozen
        await asyncio.sleep(0.1)
        assert rec.recovered == 5, "a resend arrived expired: its samples are lost"


async def test_a_frozen_receiver_holds_one_worker_whatever_its_number_of_streams() -> None:
    """Its resends take one worker at a time: another receiver's resend (and stream) goes on."""
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta = _Pooled(net.hub, workers=2)
        _, a = await net.platform("uav-a", transport=ta)
        await net.platform("uav-f")
        await net.platform("uav-b")
        sources = {s: a.add_source(f"car/{s}") for s in ("f1", "f2", "b")}
        exp = await net.exporter("uav-a", max_batch_bytes=1024)
        await net.importer("uav-f", translate=agreed("f1", "f2"))
        await net.importer("uav-b", translate=agreed("b"))
        exports = {
            s: exp.start_exporting(f"car/{s}", s, "uav-b" if s == "b" else "uav-f", history=10)
            for s in sources
        }

        async def push(names: str, value: int) -> None:
            for name in names.split():
                sources[name].push(value)
            await asyncio.sleep(0.02)

        for _ in range(3):
            await push("f1 f2 b", 1)
        ta.drop_streams = True
        for _ in range(5):
            await push("f1 f2 b", 2)
        ta.drop_streams = False
        # the frozen receiver's two streams ask their resends first, and hold workers
        await push("f1 f2", 3)
        await until(lambda: ta.frozen_puts >= 1, "the frozen receiver's resends")
        await asyncio.sleep(0.05)  # both of its streams had their turn to take a worker
        began = time.monotonic()
        await push("b", 3)
        # bounded past both frozen puts: a resend queued behind them fails the bound below
        await until(
            lambda: exports["b"].recovered == 5, "the other receiver's resend", 2 * _FROZEN + WAIT
        )
        took = time.monotonic() - began
        assert took < _FROZEN / 2, f"another receiver's resend waited {took:.2f} s"
