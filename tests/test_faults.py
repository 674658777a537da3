"""Faults, each with its figure: a UAV SIGKILLed, a receiver frozen, the router restarted.

Every platform that can fail is its own OS process (``spawn``), on zenoh over loopback:

- ``sigkill``: three UAVs and the operator (this process), streams flowing among them.
  uav-a is SIGKILLed mid-stream: the operator and uav-a's peers are told ``gone`` within
  1 s, every other stream loses nothing (sequence numbers in the values, counted end to
  end), and uav-a restarted with the same name and keys rejoins: its old sessions are
  forgotten, a new one is agreed and its stream can be created again.
- ``sigstop``: one exporter (this process), four receivers; one is SIGSTOPped. The others
  and the exporter keep >= 90% of their throughput, the frozen one's export ends when its
  lease expires (``lease-expired``, counted and told), and SIGCONT afterwards harms no one.
- ``router``: a ``dyknow router`` subprocess, two platforms in client mode through it. The
  router is SIGKILLed and started again on the same port: the federation reforms by
  itself (membership back, a request answered, a stream flowing again) within a bound.

Each test prints one ``FAULT …`` line. Readiness is by events; every wait is bounded;
every process is killed in ``finally``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import multiprocessing
import os
import signal
import sys
import time
import uuid
from collections.abc import AsyncIterator, Callable, Iterator
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import msgpack
import pytest
from _load import LoopLag

from agents.keys import gen_keys, trust_keys
from agents.transports import (
    MemoryHub,
    MemoryTransport,
    Subscription,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from dyknow_core import DyKnowInstance, Policy, RawSample
from federation import FederationPlatform, MembershipEvent, PlatformConfig
from federation._batch import read_batch
from federation._export import Export, ExportProxy
from federation._import import ImportProxy
from federation._sessions import PlainSessions

ROOT = Path(__file__).resolve().parent.parent
START = 30.0  # spawned interpreters import zenoh, pydantic and DyKnow: seconds when loaded
WAIT = 10.0  # the bound on any other single wait
TOLD_WITHIN = 1.0  # the bound: peers and operator told of a SIGKILL
LEASE = 2.0  # the export lease in the frozen-receiver test
VOCABULARY = {"name": "fleet", "labels": {"position": "a platform's own position"}}
UAVS = ("uav-a", "uav-b", "uav-c")
PERIOD = 0.01  # a UAV pushes BATCH position samples every PERIOD s
BATCH = 10


# -- config files ---------------------------------------------------------------------------------


def write_federation(
    tmp: Path, federation: str, transports: dict[str, dict[str, Any]]
) -> dict[str, Path]:
    """Keys, a trust file and one JSON config per platform (every UAV maps ``position``)."""
    pubs = [gen_keys(name, tmp / "keys")[2] for name in transports]
    trust_keys(tmp / "trust.json", pubs, federation=federation)
    configs = {}
    for name, transport in transports.items():
        labels = {} if name == "operator" else {"position": "nav/position"}
        data = {
            "name": name,
            "federation": federation,
            "key": str(tmp / "keys" / f"{name}.key"),
            "trust": str(tmp / "trust.json"),
            "vocabulary": VOCABULARY,
            "mapping": {"vocabulary": "fleet", "labels": labels},
            "export_limit": 8,
            # the operator may have a UAV's stream sent to another UAV (the receiver agrees)
            "sharing": {"accept_for": ["operator"]},
            "transport": transport,
        }
        configs[name] = tmp / f"{name}.json"
        configs[name].write_text(json.dumps(data))
    return configs


def load(path: Path | str) -> PlatformConfig:
    """A platform config written by `write_federation`."""
    return PlatformConfig.from_dict(json.loads(Path(path).read_text()), source=str(path))


# -- talking to child processes over a pipe, from asyncio -----------------------------------------


class Pipe:
    """One end of a multiprocessing pipe read from the event loop (messages to a queue)."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.inbox: asyncio.Queue[Any] = asyncio.Queue()
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(conn.fileno(), self._readable)

    def _readable(self) -> None:
        try:
            while self.conn.poll():
                self.inbox.put_nowait(self.conn.recv())
        except (EOFError, OSError):
            self._loop.remove_reader(self.conn.fileno())
            self.inbox.put_nowait(("eof",))

    def send(self, *msg: Any) -> None:
        """Send a tuple to the other end."""
        self.conn.send(msg)

    async def expect(self, kind: str, timeout: float = WAIT) -> tuple[Any, ...]:
        """The next message whose first element is ``kind`` (others are dropped)."""
        async with asyncio.timeout(timeout):
            while True:
                msg = await self.inbox.get()
                if msg[0] == "eof":
                    raise AssertionError(f"the other end closed while waiting for {kind!r}")
                if msg[0] == kind:
                    return tuple(msg)

    def close(self) -> None:
        """Stop reading and close."""
        with contextlib.suppress(Exception):
            self._loop.remove_reader(self.conn.fileno())
        self.conn.close()


@contextlib.contextmanager
def killed_at_exit(procs: list[BaseProcess]) -> Iterator[None]:
    """Kill and reap every started process of ``procs`` (which may grow) on the way out."""
    try:
        yield
    finally:
        for proc in procs:
            if proc.pid is not None and proc.is_alive():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGCONT)  # a stopped process dies only when run
                proc.kill()
        for proc in procs:
            if proc.pid is not None:
                proc.join(timeout=10)


async def until(check: Callable[[], Any], what: str, timeout: float = WAIT) -> Any:
    """Poll ``check`` (counters have no event to await) until true; its value."""
    async with asyncio.timeout(timeout):
        while not (value := check()):  # noqa: ASYNC110
            await asyncio.sleep(0.01)
    return value


# -- the UAV child: a platform publishing numbered positions --------------------------------------


def uav_main(config_path: str, conn: Connection) -> None:
    """A UAV until killed or told to stop: positions ``{"seq": k}``, membership events out."""
    asyncio.run(_uav(load(config_path), conn))


async def _uav(config: PlatformConfig, conn: Connection) -> None:
    pipe = Pipe(conn)
    async with FederationPlatform(config, join=False) as p:
        src = p.instance.add_source("nav/position")

        async def follow(events: Subscription[MembershipEvent]) -> None:
            async with events:
                async for e in events:
                    pipe.send("event", e.kind, e.platform, time.monotonic())

        tasks = [asyncio.create_task(follow(p.membership()))]
        await p.join()
        pipe.send("ready", config.name)
        k = 0
        stop = asyncio.ensure_future(pipe.expect("stop", timeout=1e6))
        while not stop.done():
            t = p.instance.clock.now()
            src.push_batch([({"seq": k + i}, t + i, t + i) for i in range(BATCH)])
            k += BATCH
            await asyncio.sleep(PERIOD)
        pipe.send("stopped", k - 1)
        await pipe.expect("exit", timeout=1e6)
        for task in tasks:
            task.cancel()


class Counter:
    """Counts one imported stream's ``{"seq": k}`` values end to end: received and gaps."""

    def __init__(self) -> None:
        self.first: int | None = None
        self.last = -1
        self.received = 0
        self.gaps = 0

    def __call__(self, batch: list[RawSample]) -> None:
        for value, _, _ in batch:
            seq = value["seq"]
            if self.first is None:
                self.first = seq
            elif seq != self.last + 1:
                self.gaps += 1
            self.last = seq
            self.received += 1

    def lost(self, last_sent: int) -> int:
        """Samples from the first received up to ``last_sent`` that never arrived."""
        assert self.first is not None
        return last_sent - self.first + 1 - self.received


# -- 1. SIGKILL -----------------------------------------------------------------------------------


async def test_sigkilled_uav_is_told_others_lose_nothing_and_it_rejoins(tmp_path: Path) -> None:
    federation = f"kill-{uuid.uuid4().hex[:8]}"
    ports = {name: free_tcp_port() for name in ("operator", *UAVS)}
    seed = f"tcp/127.0.0.1:{ports['operator']}"
    transports = {
        name: {
            "kind": "zenoh",
            "mode": "peer",
            "listen": [f"tcp/127.0.0.1:{port}"],
            "connect": [] if name == "operator" else [seed],
        }
        for name, port in ports.items()
    }
    configs = write_federation(tmp_path, federation, transports)
    ctx = multiprocessing.get_context("spawn")
    procs: list[BaseProcess] = []
    pipes: dict[str, Pipe] = {}

    def spawn(name: str) -> None:
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=uav_main, args=(str(configs[name]), child), name=name)
        procs.append(proc)
        proc.start()
        child.close()
        if name in pipes:
            pipes[name].close()
        pipes[name] = Pipe(parent)

    with killed_at_exit(procs):
        async with (
            asyncio.timeout(90),
            FederationPlatform(load(configs["operator"])) as op,
            op.membership() as events,
        ):
            fed = op.federation_agent
            for name in UAVS:
                spawn(name)
            for name in UAVS:
                await pipes[name].expect("ready", START)
            await until(lambda: set(UAVS) <= set(op.members), "every UAV a member", START)
            # uav-a's stream goes to uav-b and here; uav-b's and uav-c's come here (counted)
            await fed.create_stream("uav-a", ["position"], to_units=["operator", "uav-b"])
            counters = {}
            for name in ("uav-b", "uav-c"):
                await fed.create_stream(name, ["position"], timeout=WAIT)
                label = await op.imported(name, "position", timeout=WAIT)
                counters[name] = Counter()
                op.instance.subscribe(label, Policy(), callback=counters[name])
            await op.imported("uav-a", "position", timeout=WAIT)
            old = op.interface.sessions.session_for("uav-a")
            assert old is not None  # agreed for the create-stream request
            await until(lambda: all(c.received > 200 for c in counters.values()), "flowing")

            proc_a = procs[0]
            assert proc_a.pid is not None
            killed = time.monotonic()
            os.kill(proc_a.pid, signal.SIGKILL)
            async with asyncio.timeout(WAIT):
                while await events.get() != MembershipEvent("gone", "uav-a"):
                    pass
            told = {"operator": time.monotonic() - killed}
            for peer in ("uav-b", "uav-c"):
                while True:
                    _, kind, who, at = await pipes[peer].expect("event")
                    if (kind, who) == ("gone", "uav-a"):
                        told[peer] = at - killed
                        break
            assert max(told.values()) < TOLD_WITHIN, told
            rec = op.importer.get("uav-a", "position")
            assert rec is not None
            # the import proxy and the Interface Agent follow the same token on their own:
            # told a moment after the membership event, not necessarily before it
            await until(lambda: rec.ended, "its stream here ended", WAIT)
            await until(
                lambda: op.interface.sessions.session_for("uav-a") is None,
                "its session forgotten",
                WAIT,
            )

            # the others flow on for a while, then stop: everything they sent arrived
            n = {name: c.received for name, c in counters.items()}
            await until(lambda: all(c.received > n[k] + 1000 for k, c in counters.items()), "on")
            last = {}
            for name in counters:
                pipes[name].send("stop")
                last[name] = (await pipes[name].expect("stopped"))[1]
            await until(
                lambda: all(c.last >= last[k] for k, c in counters.items()), "the last samples"
            )
            lost = {name: c.lost(last[name]) for name, c in counters.items()}
            total = sum(c.received for c in counters.values())
            assert lost == {"uav-b": 0, "uav-c": 0} and all(
                c.gaps == 0 for c in counters.values()
            ), (lost, [c.gaps for c in counters.values()])

            # uav-a again, same name and keys: it rejoins and its stream can be created again
            restarted = time.monotonic()
            spawn("uav-a")
            await pipes["uav-a"].expect("ready", START)
            await until(lambda: "uav-a" in op.members, "uav-a a member again", START)
            rejoined = time.monotonic() - restarted
            await fed.create_stream("uav-a", ["position"], timeout=WAIT)
            new = op.interface.sessions.session_for("uav-a")
            assert new is not None and new.sid != old.sid  # a new key exchange
            rec = await until(
                lambda: (r := op.importer.get("uav-a", "position")) and not r.ended and r, "again"
            )
            injected = rec.injected
            await until(lambda: rec.injected > injected + 100, "uav-a's samples flowing again")
            for name in UAVS:
                pipes[name].send("exit")
    for pipe in pipes.values():
        pipe.close()
    print(
        f"FAULT sigkill: told in {told['operator']:.3f} s (operator), "
        f"{told['uav-b']:.3f} s / {told['uav-c']:.3f} s (peers); other streams lost "
        f"{sum(lost.values())} of {total}; rejoined in {rejoined:.2f} s, stream re-created"
    )


# -- 2. SIGSTOP -----------------------------------------------------------------------------------

RECEIVERS = 4
RATE = 5000  # samples/s the exporter's source gets, to every receiver
RATE_PERIOD = 0.01
WINDOW = 2.5  # s of each throughput measurement


def receiver_main(name: str, port: int, conn: Connection) -> None:
    """A receiving platform: an import proxy on zenoh; answers "count" with what it injected."""
    asyncio.run(_receiver(name, port, conn))


async def _receiver(name: str, port: int, conn: Connection) -> None:
    pipe = Pipe(conn)
    transport = ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[port]))
    async with (
        transport,
        DyKnowInstance(name) as dk,
        ImportProxy(
            name, "frz", transport, dk, PlainSessions(name), lambda s, lab: f"in/{s}/{lab}"
        ) as importer,
    ):
        pipe.send("ready", name)
        while True:
            msg = await pipe.expect("count", timeout=1e6)
            pipe.send("count", msg[1], importer.stats()["totals"]["injected"])


async def test_frozen_receiver_costs_nobody_and_its_lease_expires() -> None:
    port = free_tcp_port()
    ctx = multiprocessing.get_context("spawn")
    procs: list[BaseProcess] = []
    pipes: dict[str, Pipe] = {}
    names = [f"rx{i}" for i in range(RECEIVERS)]
    frozen = names[-1]
    dropped: list[tuple[str, str, int]] = []
    expired: list[float] = []

    def on_drop(export: Export, reason: str, count: int) -> None:
        dropped.append((export.receiver, reason, count))
        if reason == "lease-expired":
            expired.append(time.monotonic())

    with killed_at_exit(procs):
        transport = ZenohTransport(ZenohConfig.loopback(port))
        async with (
            asyncio.timeout(60),
            transport,
            DyKnowInstance("tx") as dk,
            ExportProxy(
                "tx", "frz", transport, dk, PlainSessions("tx"), lease=LEASE, on_drop=on_drop
            ) as exporter,
        ):
            for name in names:
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=receiver_main, args=(name, port, child), name=name)
                procs.append(proc)
                proc.start()
                child.close()
                pipes[name] = Pipe(parent)
            for name in names:
                await pipes[name].expect("ready", START)
            src = dk.add_source("pos")
            exports = {name: exporter.start_exporting("pos", "position", name) for name in names}
            pushed = 0

            async def produce() -> None:
                """RATE samples/s on a schedule: a late tick pushes what it owes."""
                nonlocal pushed
                began = time.monotonic()
                while True:
                    n = int((time.monotonic() - began) * RATE) - pushed
                    t = dk.clock.now()
                    src.push_batch([(pushed + i, t + i, t + i) for i in range(n)])
                    pushed += n
                    await asyncio.sleep(RATE_PERIOD)

            async def counts(who: list[str]) -> dict[str, int]:
                tag = uuid.uuid4().hex
                for name in who:
                    pipes[name].send("count", tag)
                out = {}
                for name in who:
                    while (msg := await pipes[name].expect("count"))[1] != tag:
                        pass
                    out[name] = msg[2]
                return out

            async def rates(who: list[str]) -> dict[str, float]:
                """Samples/s each of ``who`` injected, and the exporter pushed, over WINDOW."""
                c0, p0, t0 = await counts(who), pushed, time.monotonic()
                await asyncio.sleep(WINDOW)
                c1, p1, t1 = await counts(who), pushed, time.monotonic()
                out = {name: (c1[name] - c0[name]) / (t1 - t0) for name in who}
                out["exporter"] = (p1 - p0) / (t1 - t0)
                return out

            producer = asyncio.create_task(produce())
            try:
                healthy = names[:-1]
                await until(lambda: all(e.sent > 0 for e in exports.values()), "flowing", WAIT)
                before = await rates(healthy)
                stopped_at = time.monotonic()
                proc = procs[-1]
                assert proc.pid is not None
                os.kill(proc.pid, signal.SIGSTOP)
                during = await rates(healthy)
                ended = await until(
                    lambda: exports[frozen].ended, "the frozen one's lease", LEASE + WAIT
                )
                expired_after = expired[0] - stopped_at
                # the lease runs from the receiver's last report, which came up to a report
                # interval (more on a busy machine) before the stop, or was in flight during it
                heard = exports[frozen].last_heard
                assert heard < stopped_at + 0.5, heard - stopped_at
                assert LEASE <= expired[0] - heard < LEASE + 1.5, expired[0] - heard
                assert ended.startswith("lease-expired"), ended
                assert exports[frozen] in exporter.ended
                assert any(r == frozen and why == "lease-expired" for r, why, _ in dropped)
                assert exporter.find(frozen, "position") is None
                assert all(exports[n].active for n in healthy)
                os.kill(proc.pid, signal.SIGCONT)
                after = await counts(names)  # the thawed one answers; nothing crashed
                assert proc.is_alive() and all(exports[n].active for n in healthy)
                assert not any(r != frozen for r, _, _ in dropped), dropped
            finally:
                producer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await producer
            for pipe in pipes.values():
                pipe.close()
    kept = {k: during[k] / before[k] for k in before}
    assert min(kept.values()) >= 0.9, (before, during)
    print(
        f"FAULT sigstop: {RECEIVERS - 1} healthy receivers kept "
        f"{100 * min(v for k, v in kept.items() if k != 'exporter'):.0f}% (worst) of "
        f"{min(v for k, v in before.items() if k != 'exporter'):.0f} samples/s, exporter "
        f"{100 * kept['exporter']:.0f}%; frozen one's lease ({LEASE:.0f} s) expired after "
        f"{expired_after:.2f} s, {exports[frozen].dropped_total} samples counted dropped; "
        f"after SIGCONT it answers ({after[frozen]} injected)"
    )


class Lossy(MemoryTransport):
    """Drops the first sending of the stream batches numbered in ``lose``; sends resent twice."""

    def __init__(self, hub: MemoryHub, lose: set[int]) -> None:
        super().__init__(hub)
        self.lose = lose

    async def publish(self, key: str, payload: bytes, **kw: Any) -> None:
        """Publish, but for what this link loses or repeats."""
        if "/stream/" in key:
            batch = read_batch(msgpack.unpackb(payload)[3])
            if batch.recovered:
                await super().publish(key, payload, **kw)  # a duplicate on the way
            elif batch.seq in self.lose:
                return
        await super().publish(key, payload, **kw)


async def test_history_recovers_a_gap_at_most_once_and_late_others_stay_in_order() -> None:
    hub = MemoryHub()
    async with (
        Lossy(hub, lose={3, 4, 5, 6, 12}) as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy("a", "f", ta, ia, PlainSessions("a"), batch_size=1) as exporter,
        ImportProxy(
            "b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}", report_interval=0.05
        ) as importer,
    ):
        src = ia.add_source("x")
        hist = exporter.start_exporting("x", "hist", "b", history=2)
        plain = exporter.start_exporting("x", "plain", "b")
        for k in range(15):
            src.push(k, valid_time=k + 1)
            await asyncio.sleep(0.01)  # one batch each: the link loses some
        h = await until(lambda: importer.get("a", "hist"), "the history stream")
        p = await until(lambda: importer.get("a", "plain"), "the plain stream")
        await until(lambda: h.injected == 13 and p.injected == 10, "every sample it will get")
        await until(lambda: hist.dropped.get("lost-in-transit") == 2, "the loss reported")
        await until(lambda: plain.dropped.get("lost-in-transit") == 5, "the loss reported")

        def arrival(label: str) -> list[int]:
            samples = ib.between(label, 0, 100).samples
            return [s.value for s in sorted(samples, key=lambda s: s.available_time)]

        # plain: what was lost stays lost, the rest in order, each once
        assert arrival("in/plain") == [0, 1, 2, 7, 8, 9, 10, 11, 13, 14]
        assert (p.lost, p.gaps, p.recovered) == (5, 2, 0)
        # history 2: after each gap its last 2 come back, late, once (resent twice)
        got = arrival("in/hist")
        assert sorted(got) == [0, 1, 2, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14]
        assert [k for k in got if k not in (5, 6, 12)] == [0, 1, 2, 7, 8, 9, 10, 11, 13, 14]
        assert got.index(5) > got.index(7) and got.index(12) > got.index(13)
        assert (h.lost, h.gaps, h.recovered) == (2, 2, 3)
        assert h.stats()["dropped_samples"]["duplicate"] >= 3
        assert hist.recovered >= 3


async def test_a_payload_whose_handling_raises_is_logged_without_its_samples(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A fault handling one imported batch is logged with its size, key and the error's
    type and place, never its samples nor the error's text (which may quote them): they
    came encrypted from another platform. The next batch is imported."""
    hub = MemoryHub()
    secret = f"said-in-confidence-{uuid.uuid4().hex}"
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy("a", "f", ta, ia, PlainSessions("a"), batch_size=1) as exporter,
        ImportProxy("b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}") as importer,
    ):
        real = importer._add
        broke: list[int] = []

        def add(rec: Any, samples: list[Any]) -> None:
            if secret in repr(samples):
                broke.append(len(samples))
                raise ValueError(f"cannot inject {samples!r}")  # a fault quoting them
            real(rec, samples)

        importer._add = add  # type: ignore[method-assign]
        src = ia.add_source("x")
        exporter.start_exporting("x", "x", "b")
        with caplog.at_level("DEBUG", logger="federation"):
            src.push(secret, valid_time=1)
            await until(lambda: broke, "the batch that raises")
            src.push("after", valid_time=2)
            stream = await until(lambda: importer.get("a", "x"), "the stream")
            await until(lambda: stream.injected == 1, "the batch after it")
        assert [s.value for s in ib.between("in/x", 0, 10).samples] == ["after"]
        assert secret not in caplog.text
        failed = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
        assert len(failed) == 1
        assert "handling a payload of " in failed[0] and "on dyknow/f/" in failed[0]
        assert ": ValueError (its text left out), raised at:" in failed[0]


async def test_a_reason_the_sender_ended_an_export_with_is_logged_as_one_capped_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The reason in a sender's end marker is its word: the receiver logs it on one line,
    its newline and terminal escape escaped (no forged log line), cut to `QUOTE_MAX`
    characters with how long it was; the import ends all the same."""
    from federation._quote import QUOTE_MAX

    hub = MemoryHub()
    forged = "import[b]: a ended x: stopped\nCRITICAL federation: all keys leaked \x1b[2J"
    why = forged + "x" * (1024 - len(forged))  # the most a marker may carry
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy("a", "f", ta, ia, PlainSessions("a"), batch_size=1) as exporter,
        ImportProxy("b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}") as importer,
    ):
        src = ia.add_source("x")
        export = exporter.start_exporting("x", "x", "b")
        src.push("first", valid_time=1)
        stream = await until(lambda: importer.get("a", "x"), "the stream")
        await until(lambda: stream.injected == 1, "the first batch")
        with caplog.at_level("DEBUG", logger="federation"):
            await exporter.stop(export, why=why)
            await until(lambda: stream.ended, "the end marker")
    said = [r.getMessage() for r in caplog.records if " ended x: " in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0] and "\x1b" not in said[0]
    reason = said[0].split(" ended x: ", 1)[1]
    assert reason.startswith("import[b]: a ended x: stopped\\x0aCRITICAL federation: all ")
    assert "\\x1b[2J" in reason
    kept = QUOTE_MAX - 2 * 3  # two characters escaped, four characters each
    assert reason == f"{why[:kept]}… (1024 characters, {1024 - kept} left out)".replace(
        "\n", "\\x0a"
    ).replace("\x1b", "\\x1b")


async def test_an_export_that_fails_on_a_sample_tells_its_end_without_the_sample(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An export whose sending raises on a sample (a fault whose text quotes it) ends and
    tells its receiver why: the error's type and where it was raised, never its text.
    The receiver's import ends, and nothing of the sample reaches the receiver's log."""
    from federation import _export

    hub = MemoryHub()
    secret = f"said-in-confidence-{uuid.uuid4().hex}"
    real = _export.pack_batch

    def pack_batch(label: str, samples: list[Any], *args: Any, **kwargs: Any) -> bytes:
        if secret in repr(samples):
            raise RuntimeError(f"cannot pack {samples!r}")  # a fault quoting the sample
        return real(label, samples, *args, **kwargs)

    monkeypatch.setattr(_export, "pack_batch", pack_batch)
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy("a", "f", ta, ia, PlainSessions("a"), batch_size=1) as exporter,
        ImportProxy("b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}") as importer,
    ):
        src = ia.add_source("x")
        export = exporter.start_exporting("x", "x", "b")
        src.push("first", valid_time=1)
        stream = await until(lambda: importer.get("a", "x"), "the stream")
        await until(lambda: stream.injected == 1, "the first batch")
        with caplog.at_level("DEBUG", logger="federation"):
            src.push(secret, valid_time=2)
            await until(lambda: stream.ended, "the end marker")
        assert export.ended is not None and secret not in export.ended
        assert export.ended.startswith("failed: RuntimeError at test_faults.py:")
        assert export.ended.endswith(" in pack_batch (its text left out)")
        assert secret not in json.dumps(exporter.stats(), default=str)
    # the sender's own log has its fault's text (its own sample); the receiver's has none
    said = [r.getMessage() for r in caplog.records if r.name == "federation._import"]
    assert said and secret not in "\n".join(said)
    assert [m for m in said if " ended x: " in m] == [f"import[b]: a ended x: {export.ended}"]


async def test_lease_ends_the_export_to_a_silent_receiver_only() -> None:
    hub = MemoryHub()
    ended: list[tuple[str, str]] = []
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy(
            "a",
            "f",
            ta,
            ia,
            PlainSessions("a"),
            lease=0.5,
            on_drop=lambda e, why, n: ended.append((e.receiver, why)),
        ) as exporter,
        ImportProxy(
            "b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}", report_interval=0.05
        ),
    ):
        ia.add_source("x")  # idle: the live receiver hears keepalives and reports
        live = exporter.start_exporting("x", "x", "b")
        silent = exporter.start_exporting("x", "x", "ghost")
        await until(lambda: silent.ended, "the silent receiver's lease", 3.0)
        assert silent.ended.startswith("lease-expired") and ("ghost", "lease-expired") in ended
        assert list(exporter.ended) == [silent] and exporter.exports() == [live]
        started = time.monotonic()
        # two leases more: the live one is still reported on, and kept
        await until(lambda: live.last_heard > started + 1.0 or live.ended, "reports on", WAIT)
        assert live.active, live.ended


def stall(seconds: float) -> None:
    """This whole process stalls, its event loop too (busy, descheduled, a long collection)."""
    time.sleep(seconds)


async def test_a_stall_of_the_exporting_process_ends_no_live_receivers_export() -> None:
    """A process that stalled past the lease reads the reports that came meanwhile before
    its lease decides: a live receiver's export goes on; a silent one's still ends."""
    hub = MemoryHub()
    lease = 0.5
    expired: list[str] = []
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy(
            "a",
            "f",
            ta,
            ia,
            PlainSessions("a"),
            lease=lease,
            batch_size=4,
            on_drop=lambda e, why, n: (
                expired.append(e.receiver) if why == "lease-expired" else None
            ),
        ) as exporter,
        ImportProxy(
            "b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}", report_interval=0.05
        ),
    ):
        src = ia.add_source("x")
        live = exporter.start_exporting("x", "x", "b")
        started = live.last_heard
        await until(lambda: live.last_heard > started, "the first report")
        stall(2 * lease)  # the receiver's report is due meanwhile: it goes out after
        # samples that came in the stall: the export looks at its lease after each batch,
        # sooner than the loop reads the report
        for k in range(40):
            src.push(k, valid_time=k)
        heard = live.last_heard
        await until(lambda: live.last_heard > heard or live.ended, "the report due in the stall")
        assert live.active and expired == [], live.ended
        ghost = exporter.start_exporting("x", "x", "ghost")
        stall(2 * lease)  # spared by the late look, once: the next one ends it
        resumed = time.monotonic()
        async with LoopLag() as lag:
            await until(lambda: ghost.ended, "the silent receiver's lease")
        took = time.monotonic() - resumed
        assert expired == ["ghost"] and ghost.ended.startswith("lease-expired")
        # the late look, then the next regular one (lease / 3 s on), each timer run as
        # late as the loop's lag allows, the looks' own work and this wait's poll in 0.05 s
        assert took <= lease / 3 + 2 * (lag.worst + lag.period) + 0.05, (took, lag.worst)
        assert live.active, live.ended


async def test_a_lease_expires_in_time_after_samples_stop_flowing() -> None:
    """Samples wake the export's waits early; once they stop, its wait still ends in time."""
    hub = MemoryHub()
    lease = 0.6  # the export looks every lease / 3 s while idle
    expired: list[float] = []
    async with (
        hub.transport() as ta,
        DyKnowInstance("a") as ia,
        ExportProxy(
            "a",
            "f",
            ta,
            ia,
            PlainSessions("a"),
            lease=lease,
            on_drop=lambda e, why, n: (
                expired.append(time.monotonic()) if why == "lease-expired" else None
            ),
        ) as exporter,
    ):
        async with LoopLag() as lag:
            src = ia.add_source("x")
            export = exporter.start_exporting("x", "x", "ghost")
            started = export.last_heard
            for k in range(20):  # 0.4 s of samples, well inside the lease
                src.push(k, valid_time=k)
                await asyncio.sleep(0.02)
            await until(lambda: expired, "the silent receiver's lease", 3.0)
        assert export.sent >= 10 and export.ended and export.ended.startswith("lease-expired")
        # a look at most lease / 3 s after the wait began, its timer run as late as the
        # loop's lag allows (a busy machine's), the look's own work within 0.05 s; a look
        # so late that the lease ran out only meanwhile leaves it to the next (as late)
        took = expired[0] - started
        slack = 2 * (lag.worst + lag.period) + 0.05
        assert lease <= took <= lease + lease / 3 + slack, (took, lag.worst)


async def test_an_importer_idle_until_a_stream_comes_reports_on_it_at_once() -> None:
    """The report task sleeps while nothing is imported; the first stream wakes it in time."""
    hub = MemoryHub()
    # The first report comes a keepalive (lease / 3 s) and a report interval after the
    # export starts, and must come within the lease: a lease of 0.5 s left 0.23 s for a
    # busy machine's stalls, and expired. A sleeping report task never reports at all.
    lease, iv = 2.0, 0.1  # the lease, the report interval
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
        ExportProxy("a", "f", ta, ia, PlainSessions("a"), lease=lease) as exporter,
        ImportProxy(
            "b", "f", tb, ib, PlainSessions("b"), lambda s, lab: f"in/{lab}", report_interval=iv
        ) as importer,
    ):
        await asyncio.sleep(0.5)  # an idle spell: nothing imported, nothing to report on
        assert not importer._reportable.is_set()  # the report task sleeps
        ia.add_source("x")
        export = exporter.start_exporting("x", "x", "b")
        started = export.last_heard
        # the first report in time to keep the lease
        await until(lambda: export.last_heard > started, "the first report", lease)
        first = export.last_heard
        # and reports go on, every report interval, without the stream sending anything
        await until(lambda: export.last_heard > first + 3 * iv, "reports after it", lease)
        assert export.active and export.sent == 0


async def test_lease_needs_a_positive_number() -> None:
    async with MemoryHub().transport() as t, DyKnowInstance("x") as dk:
        for bad in (0, -1.0):
            with pytest.raises(ValueError, match="lease must be a positive"):
                ExportProxy("x", "f", t, dk, PlainSessions("x"), lease=bad)
        exporter = ExportProxy("x", "f", t, dk, PlainSessions("x"))
        dk.add_source("s")
        for history in (-1, 1.5, 10**7):
            with pytest.raises(ValueError, match="history must be an integer"):
                exporter.start_exporting("s", "s", "y", history=history)  # type: ignore[arg-type]


# -- 4. the router restarted ----------------------------------------------------------------------


@contextlib.asynccontextmanager
async def router(port: int) -> AsyncIterator[asyncio.subprocess.Process]:
    """``dyknow router`` on ``port`` (loopback), once it says it listens; killed at the end."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "federation.cli",
        "router",
        "--listen",
        f"tcp/127.0.0.1:{port}",
        cwd=ROOT,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )
    try:
        assert proc.stdout is not None
        line = await asyncio.wait_for(proc.stdout.readline(), START)
        assert b"listening" in line, line
        yield proc
    finally:
        if proc.returncode is None:
            proc.kill()
        await asyncio.wait_for(proc.wait(), WAIT)


async def test_router_restarted_federation_reforms(tmp_path: Path) -> None:
    port = free_tcp_port()
    client = {
        "kind": "zenoh",
        "mode": "client",
        "connect": [f"tcp/127.0.0.1:{port}"],
        # a client retries its router every 0.2-0.5 s, not zenoh's default back-off to 4 s
        "overrides": {
            "connect/retry": {
                "period_init_ms": 200,
                "period_max_ms": 500,
                "period_increase_factor": 2,
            }
        },
    }
    configs = write_federation(
        tmp_path, f"rtr-{uuid.uuid4().hex[:8]}", {"operator": client, "uav-a": client}
    )
    async with asyncio.timeout(80), contextlib.AsyncExitStack() as stack:
        first = await stack.enter_async_context(router(port))
        op = await stack.enter_async_context(FederationPlatform(load(configs["operator"])))
        uav = await stack.enter_async_context(FederationPlatform(load(configs["uav-a"])))
        src = uav.instance.add_source("nav/position")
        events = await stack.enter_async_context(op.membership())
        await until(lambda: "uav-a" in op.members, "uav-a a member", START)
        await op.federation_agent.create_stream("uav-a", ["position"], durable=True, timeout=WAIT)
        src.push({"seq": 0})
        await op.imported("uav-a", "position", timeout=WAIT)

        first.kill()
        await asyncio.wait_for(first.wait(), WAIT)
        async with asyncio.timeout(WAIT):
            while await events.get() != MembershipEvent("gone", "uav-a"):
                pass
        restarted = time.monotonic()
        await stack.enter_async_context(router(port))
        async with asyncio.timeout(WAIT):
            while await events.get() != MembershipEvent("joined", "uav-a"):
                pass
        member_after = time.monotonic() - restarted
        answer = await op.federation_agent.request_from(
            "uav-a", {"action": "list-labels"}, timeout=WAIT
        )
        assert answer == {"labels": ["position"]}
        answered_after = time.monotonic() - restarted
        # the exports to a platform gone were stopped; a durable stream is asked for again
        # by itself once its provider is back
        rec = op.importer.get("uav-a", "position")
        assert rec is not None
        injected = rec.injected

        async def pushing() -> None:
            k = 1
            while True:
                src.push({"seq": k})
                k += 1
                await asyncio.sleep(0.01)

        pusher = asyncio.create_task(pushing())
        try:
            await until(lambda: rec.injected > injected and not rec.ended, "flowing again")
        finally:
            pusher.cancel()
        flowing_after = time.monotonic() - restarted
    assert flowing_after < WAIT
    print(
        f"FAULT router: after a restart, membership back in {member_after:.2f} s, a request "
        f"answered in {answered_after:.2f} s, the stream flowing again in "
        f"{flowing_after:.2f} s (bound {WAIT:.0f} s)"
    )
