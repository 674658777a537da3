"""The processes of ``bench.federation``: one exporting platform, importing platforms.

Module-level code only: these run in processes started with the ``spawn`` method (forking
after a zenoh session is open hangs the child). Each node runs one asyncio loop and one
`ZenohTransport` (peer mode, loopback) and does what the parent asks through a command
queue: ``(id, op, args)`` in, ``(id, "ok" | "error", result)`` out on the node's own reply
queue (one per node, so a node stopped with SIGSTOP blocks nobody else's replies).
Every command runs as its own task, so the parent can ask for a snapshot while a flood
runs. Reply id 0 is the start: ``"ready"``, or the traceback of what failed.

- ``Exporter``: a DyKnow instance with a source on ``LOCAL``, an `ExportProxy` exporting it
  as ``SEM`` to every receiver, sealed with a real session agreed by a `Handshake` run
  over a zenoh query (``KX/<receiver>``); raw zenoh publishers beside it, on the same
  session.
- ``Receiver``: answers that handshake, runs an `ImportProxy` into its own instance and a
  subscriber with bounds on the imported label (the policy applied on the receiving
  side), and counts what that subscriber gets; raw zenoh subscribers beside it. Every
  2 ms it publishes its counts on ``ACK/<receiver>`` (raw zenoh): the bench's own flow
  control for floods, not part of the measured stack, and silent while latencies are
  recorded.

Time stamps for latency are ``time.time_ns()`` in both processes (one host, one clock).
"""

from __future__ import annotations

import asyncio
import contextlib
import cProfile
import gc
import os
import queue
import struct
import time
import traceback
from typing import Any

import msgpack
import zenoh
from nacl.signing import SigningKey

from agents import AuthenticationError
from agents._security import Handshake, KeyPair, SecurityPolicy, SessionTable, TrustStore
from agents.transports import ZenohConfig, ZenohTransport
from dyknow_core import DyKnowInstance, Policy, RawSample
from federation._batch import pack_batch
from federation._export import ExportProxy
from federation._import import ImportProxy
from federation._proxy_stats import ImportProxyStats
from federation._sessions import TableSessions

FED = "bench"
LOCAL = "bench/speed"  # the exporter's local label
SEM = "speed"  # the semantic label it travels as
KX = "bench/kx"  # handshake queryables: KX/<receiver>
RAW_FLOOD = "bench/raw/flood"  # raw zenoh, 64-byte messages, counted in the callback
RAW_BATCH = "bench/raw/batch"  # raw zenoh, msgpack sample batches, unpacked and counted
RAW_LAT = "bench/raw/lat"  # raw zenoh, time-stamped 64-byte messages at 1 kHz
ACK = "bench/ack"  # ACK/<receiver>: its counts (ours, raw, raw batch), every ACK_EVERY s
ACK_EVERY = 0.002
CREDIT = 32_768  # items a flood may have sent beyond what a watched receiver counted
_ACKS = struct.Struct("<QQQ")
_KIND = {"ours": 0, "raw": 1, "rawbatch": 2}  # index in an ack
BATCH = 256  # samples per push (and the export proxy's batch size)
RAW_PAYLOAD = 64
LOWER, UPPER = 0.0, 100.0  # the receiving subscriber's bounds (every value is inside)
_STAMP = struct.Struct("<q")


def imported_label(sender: str) -> str:
    """The local label a receiver imports ``sender``'s stream into."""
    return f"fed/{sender}/{SEM}"


def _values(n: int) -> list[float]:
    """Sample values inside the bounds, varied so nothing is constant."""
    return [float((i * 37) % 100) + 0.5 for i in range(n)]


def node_main(role: str, name: str, spec: dict[str, Any], cmds: Any, replies: Any) -> None:
    """A node process's entry point: serve the parent's commands until told to stop."""
    try:
        asyncio.run(_serve(role, name, spec, cmds, replies))
    except BaseException:
        replies.put((0, "error", traceback.format_exc()))
        raise SystemExit(1) from None


async def _serve(role: str, name: str, spec: dict[str, Any], cmds: Any, replies: Any) -> None:
    config = ZenohConfig.loopback(spec["port"], connect=spec.get("connect", ()))
    parent = os.getppid()
    async with ZenohTransport(config) as transport:
        node: Exporter | Receiver = (Exporter if role == "exporter" else Receiver)(
            name, spec, transport
        )
        tasks: set[asyncio.Task[None]] = set()
        try:
            await node.start()
            replies.put((0, "ok", "ready"))
            while True:
                msg = await asyncio.to_thread(_next_command, cmds)
                if msg is None:
                    if os.getppid() != parent:  # orphaned: the parent is gone
                        break
                    continue
                cid, op, args = msg
                if op == "stop":
                    break
                task = asyncio.create_task(_do(node, cid, op, args, replies))
                tasks.add(task)
                task.add_done_callback(tasks.discard)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await node.close()


def _next_command(cmds: Any) -> Any:
    try:
        return cmds.get(timeout=0.5)
    except queue.Empty:
        return None


async def _do(node: Any, cid: int, op: str, args: tuple[Any, ...], replies: Any) -> None:
    try:
        result = await getattr(node, "op_" + op.replace("-", "_"))(*args)
    except asyncio.CancelledError:
        raise
    except Exception:
        replies.put((cid, "error", traceback.format_exc()))
    else:
        replies.put((cid, "ok", result))


def _thread_cpu() -> dict[str, float]:
    """CPU seconds used by each thread of this process (``/proc/self/task``), by name."""
    tick = os.sysconf("SC_CLK_TCK")
    used: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):
            with open(f"/proc/self/task/{tid}/stat") as f:
                stat = f.read()
            comm = stat[stat.index("(") + 1 : stat.rindex(")")]
            fields = stat[stat.rindex(")") + 2 :].split()
            cpu = (int(fields[11]) + int(fields[12])) / tick  # utime, stime
            name = "python (event loop)" if tid == str(os.getpid()) else comm
            used[name] = used.get(name, 0.0) + cpu
    return used


class _GcClock:
    """Time spent in the cyclic garbage collector since installed, and how many runs."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self.runs = [0, 0, 0]
        self._t = 0.0
        gc.callbacks.append(self)

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._t = time.perf_counter()
        else:
            self.seconds += time.perf_counter() - self._t
            self.runs[info["generation"]] += 1


class _Node:
    """What both roles share: keys, trust, handshake, session table, instance, profiler."""

    def __init__(self, name: str, spec: dict[str, Any], transport: ZenohTransport) -> None:
        self.name = name
        self.transport = transport
        self.keys = KeyPair(name, SigningKey(spec["seed"]))
        self.trust = TrustStore(FED, spec["trust"])
        # encrypted by default, as platforms are; the bench's plain variant turns it off
        policy = SecurityPolicy(encrypt=spec.get("encrypt", True))
        self.handshake = Handshake(self.keys, self.trust, policy=policy)
        self.table = SessionTable(name, self.trust, policy=policy)
        self.instance = DyKnowInstance(name)
        self.stack = contextlib.AsyncExitStack()
        self.zenoh_entities: list[Any] = []
        self.profiler: cProfile.Profile | None = None
        self.gc_clock = _GcClock()

    async def close(self) -> None:
        """Undeclare the raw entities and leave what was entered (the transport closes after)."""
        for entity in self.zenoh_entities:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        await self.stack.aclose()

    async def op_encrypt(self, on: bool) -> str:
        """Make new sessions encrypted (``on``) or MAC-only; accept both forms from now on.

        The exporter also agrees a new session with each receiver, which its export then
        seals on (the newest session it made); the sid of the last one.
        """
        policy = SecurityPolicy(encrypt=on, require_encryption=False)
        self.handshake.policy = policy
        self.table.policy = policy
        return ""

    async def op_gc(self) -> dict[str, Any]:
        """Seconds spent in the garbage collector so far, runs per generation, objects tracked."""
        return {
            "seconds": self.gc_clock.seconds,
            "runs": list(self.gc_clock.runs),
            "tracked": len(gc.get_objects()),
        }

    async def op_threads(self) -> dict[str, float]:
        """CPU seconds used so far by each thread of this process, summed by thread name."""
        return _thread_cpu()

    async def op_profile(self, path: str | None) -> str | None:
        """Start cProfile on this loop's thread (``path`` None), or stop and dump it to ``path``."""
        if path is None:
            self.profiler = cProfile.Profile()
            self.profiler.enable()
            return None
        if self.profiler is None:
            raise RuntimeError("the profiler was not started")
        self.profiler.disable()
        self.profiler.dump_stats(path)
        self.profiler = None
        return path


class Exporter(_Node):
    """The providing platform: a source, an export proxy to each receiver, raw publishers."""

    def __init__(self, name: str, spec: dict[str, Any], transport: ZenohTransport) -> None:
        super().__init__(name, spec, transport)
        self.source = self.instance.add_source(LOCAL)
        self.sessions = TableSessions(self.table, self._agree)
        # no lease: a frozen phase must not end the export the bench measures after it
        self.proxy = ExportProxy(
            name, FED, transport, self.instance, self.sessions, batch_size=BATCH, lease=None
        )
        self.values = _values(BATCH)

    async def start(self) -> None:
        """Enter the instance and the proxy; declare the raw publishers (DROP, reliable)."""
        await self.stack.enter_async_context(self.instance)
        await self.stack.enter_async_context(self.proxy)
        session = self.transport.session
        self.raw: dict[str, zenoh.Publisher] = {}
        for key in (RAW_FLOOD, RAW_BATCH, RAW_LAT):
            pub = session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.RELIABLE,
            )
            self.raw[key] = pub
            self.zenoh_entities.append(pub)
        self.acks: dict[str, tuple[int, int, int]] = {}
        acks, unpack = self.acks, _ACKS.unpack

        def on_ack(sample: zenoh.Sample) -> None:
            acks[str(sample.key_expr).rpartition("/")[2]] = unpack(sample.payload.to_bytes())

        self.zenoh_entities.append(session.declare_subscriber(f"{ACK}/*", on_ack))

    async def _agree(self, peer: str) -> None:
        """Run the key exchange with ``peer`` over a zenoh query; keep the session.

        As the Interface Agent does: each reply is tried as it comes, and the first that
        finishes the exchange ends the query.
        """
        request = self.handshake.initiate(peer)
        detail: bytes | None = None  # the first error reply's
        refused: AuthenticationError | None = None
        try:
            async with await self.transport.ask(f"{KX}/{peer}", request, timeout=2.0) as replies:
                async for reply in replies:
                    if not reply.ok:
                        detail = detail or reply.payload[:200]
                        continue
                    try:
                        session = self.handshake.finish(reply.payload)
                    except AuthenticationError as exc:
                        refused = refused or exc
                        continue
                    self.table.add(session)
                    return
        except BaseException:
            self.handshake.cancel(peer)
            raise
        self.handshake.cancel(peer)
        if refused is not None:
            raise refused
        detail = detail or b"no reply"
        raise ConnectionError(f"{peer} did not answer the key exchange: {detail!r}")

    async def op_export(self, receivers: list[str], timeout: float) -> dict[str, str]:
        """Agree a session with each receiver (retrying until ``timeout``), then export to it."""
        sids: dict[str, str] = {}
        for peer in receivers:
            deadline = time.monotonic() + timeout
            while True:
                try:
                    await self.sessions.ensure(peer)
                    break
                except (ConnectionError, OSError):
                    if time.monotonic() > deadline:
                        raise
                    await asyncio.sleep(0.1)
            session = self.table.session_for(peer)
            assert session is not None
            sids[peer] = session.sid
            self.proxy.start_exporting(LOCAL, SEM, peer, Policy())
        return sids

    async def op_encrypt(self, on: bool) -> str:
        """As `_Node.op_encrypt`, then a new session with each receiver under that policy."""
        await super().op_encrypt(on)
        sid = ""
        for peer in sorted({receiver for receiver, _ in self.proxy._exports}):
            await self._agree(peer)
            session = self.table.session_for(peer)
            assert session is not None and session._encrypt == on
            sid = session.sid
        return sid

    async def op_acked(self) -> list[str]:
        """The receivers whose acknowledgements reached this exporter so far."""
        return sorted(self.acks)

    async def op_push(self, n: int) -> int:
        """Push ``n`` samples stamped now (to make the receivers' streams exist)."""
        t = time.time_ns()
        self.source.push_batch([(self.values[i % BATCH], t + i, t + i) for i in range(n)])
        return n

    async def op_flood(self, kind: str, seconds: float, watch: list[str]) -> dict[str, Any]:
        """Send as fast as the receivers in ``watch`` take it for ``seconds``: ours or raw.

        Flow control (the bench's, the same for every kind): at most ``CREDIT`` items beyond
        what each watched receiver has acknowledged counting, so a fast sender does not
        pile up a backlog in a receiver (and take a CPU from it on a small machine).
        An acknowledgement that stops moving for 50 ms (items lost on the way) is given up
        on. ``ours`` pushes batches of ``BATCH`` samples into the source, and also holds
        back while an export to a watched receiver has more than half its queue filled.
        """
        idx = _KIND[kind]
        acks = self.acks
        if any(r not in acks for r in watch):
            raise RuntimeError(f"no acknowledgement yet from one of {watch}: {sorted(acks)}")
        base = {r: acks[r][idx] for r in watch}
        end = time.monotonic() + seconds
        cpu0, t0 = time.process_time(), time.perf_counter()
        sent = 0
        waits = forgiven = 0
        monotonic = time.monotonic
        sleep = asyncio.sleep
        progress_seen = (tuple(acks[r][idx] for r in watch), monotonic())

        def behind() -> int:
            return sent - min(acks[r][idx] - base[r] for r in watch)

        async def hold_back() -> bool:
            """True when the flood must wait for the receivers (after waiting a little)."""
            nonlocal progress_seen, waits, forgiven
            late = behind()
            if late <= CREDIT:
                return False
            now = monotonic()
            seen = tuple(acks[r][idx] for r in watch)
            if seen != progress_seen[0]:
                progress_seen = (seen, now)
            elif now - progress_seen[1] > 0.05:  # lost on the way: stop waiting for it
                for r in watch:
                    gap = sent - (acks[r][idx] - base[r])
                    if gap > 0:
                        base[r] -= gap
                forgiven += late
                progress_seen = (seen, now)
                return False
            waits += 1
            await sleep(0.001)
            return True

        if kind == "ours":
            exports = [self.proxy.find(r, SEM) for r in watch]
            if any(e is None for e in exports):
                raise RuntimeError(f"no active export to one of {watch}: {self.proxy.stats()}")
            queues = [e.queue for e in exports if e is not None]
            high = self.proxy.queue_size // 2
            push, values = self.source.push_batch, self.values
            while monotonic() < end:
                if await hold_back():
                    continue
                if any(len(q) > high for q in queues):
                    await sleep(0)
                    continue
                t = time.time_ns()
                times = range(t, t + BATCH)  # unique, rising: the ordered fast path
                push(list(zip(values, times, times, strict=True)), ordered=True)
                sent += BATCH
                await sleep(0)
        elif kind == "raw":
            put = self.raw[RAW_FLOOD].put
            body = bytes(RAW_PAYLOAD)
            while monotonic() < end:
                if await hold_back():
                    continue
                for _ in range(BATCH):
                    put(body)
                sent += BATCH
                await sleep(0)
        elif kind == "rawbatch":
            put = self.raw[RAW_BATCH].put
            t = time.time_ns()
            body = pack_batch(SEM, [(v, t + i, t + i) for i, v in enumerate(self.values)], 0)
            while monotonic() < end:
                if await hold_back():
                    continue
                for _ in range(8):
                    put(body)
                sent += 8 * BATCH
                await sleep(0)
        else:
            raise ValueError(f"unknown flood kind {kind!r}")
        return {
            "sent": sent,
            "seconds": time.perf_counter() - t0,
            "cpu": time.process_time() - cpu0,
            "credit_waits": waits,
            "forgiven": forgiven,
        }

    async def op_paced(self, blocks: list[tuple[str, int]], hz: float) -> dict[str, int]:
        """Publish one sample every 1/``hz`` s, ours or raw per block; how many of each."""
        period = int(1e9 / hz)
        due = time.monotonic_ns()
        source = self.source
        put = self.raw[RAW_LAT].put
        pad = bytes(RAW_PAYLOAD - _STAMP.size)
        counts = {"ours": 0, "raw": 0}
        for kind, n in blocks:
            for i in range(n):
                due += period
                if kind == "ours":
                    source.push(self.values[i % BATCH], valid_time=time.time_ns())
                else:
                    put(_STAMP.pack(time.time_ns()) + pad)
                counts[kind] += 1
                wait = due - time.monotonic_ns()
                await asyncio.sleep(wait / 1e9 if wait > 0 else 0)
        return counts

    async def op_snap(self) -> dict[str, Any]:
        """CPU time of this process (all threads) and every export's counters, now."""
        return {
            "t": time.monotonic(),
            "cpu": time.process_time(),
            "exports": {s["receiver"]: s for s in self.proxy.stats()},
        }


class Receiver(_Node):
    """An importing platform: answers the handshake, imports, subscribes with bounds, counts."""

    def __init__(self, name: str, spec: dict[str, Any], transport: ZenohTransport) -> None:
        super().__init__(name, spec, transport)
        self.sender = spec["exporter"]
        self.local = imported_label(self.sender)
        self.importer = ImportProxy(
            name,
            FED,
            transport,
            self.instance,
            TableSessions(self.table),
            translate=lambda sender, semantic: imported_label(sender),
        )
        self.ours = 0  # samples the bounded subscriber got
        self.raw = [0]  # raw 64-byte messages counted in zenoh's callback
        self.raw_batch = [0]  # samples in the raw batches, unpacked in zenoh's callback
        self.recording = False
        self.lat: list[int] = []
        self.raw_lat: list[int] = []
        self.subscription: Any = None

    async def start(self) -> None:
        """Answer the key exchange, start importing, and declare the raw subscribers."""
        await self.stack.enter_async_context(self.instance)
        await self.stack.enter_async_context(self.importer)
        await self.transport.serve(f"{KX}/{self.name}", self._kx)
        raw, raw_batch, raw_lat = self.raw, self.raw_batch, self.raw_lat
        unpackb = msgpack.unpackb
        unstamp = _STAMP.unpack_from

        def on_raw(_sample: zenoh.Sample) -> None:
            raw[0] += 1

        def on_raw_batch(sample: zenoh.Sample) -> None:
            raw_batch[0] += len(unpackb(sample.payload.to_bytes())["b"])

        def on_raw_lat(sample: zenoh.Sample) -> None:
            now = time.time_ns()
            if self.recording:
                raw_lat.append(now - unstamp(sample.payload.to_bytes())[0])

        session = self.transport.session
        self.ack_pub = session.declare_publisher(f"{ACK}/{self.name}")
        self.zenoh_entities.append(self.ack_pub)
        self.acker = asyncio.create_task(self._ack(), name="ack")
        for key, callback in (
            (RAW_FLOOD, on_raw),
            (RAW_BATCH, on_raw_batch),
            (RAW_LAT, on_raw_lat),
        ):
            self.zenoh_entities.append(session.declare_subscriber(key, callback))

    async def close(self) -> None:
        """Stop acknowledging, then close as every node does."""
        self.acker.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.acker
        await super().close()

    async def _ack(self) -> None:
        """Tell the exporter what was counted (for the flood's flow control), when it moved.

        Quiet while latencies are recorded: nothing but the measured path then.
        """
        last, last_t = None, 0.0
        put, pack = self.ack_pub.put, _ACKS.pack
        while True:
            now = (self.ours, self.raw[0], self.raw_batch[0])
            t = time.monotonic()
            if not self.recording and (now != last or t - last_t > 0.25):
                put(pack(*now))
                last, last_t = now, t
            await asyncio.sleep(ACK_EVERY)

    async def _kx(self, _key: str, request: bytes) -> bytes:
        reply, session = self.handshake.respond(request)
        self.table.add(session)
        return reply

    def _on_batch(self, batch: list[RawSample]) -> None:
        self.ours += len(batch)
        if self.recording:
            now = time.time_ns()
            self.lat.extend([now - s[1] for s in batch])

    async def op_ready(self) -> bool:
        """Whether the imported label exists; subscribe to it (with bounds) the first time."""
        if self.subscription is None:
            if not self.instance.has_label(self.local):
                return False
            policy = Policy(lower=LOWER, upper=UPPER)
            self.subscription = self.instance.subscribe(self.local, policy, callback=self._on_batch)
        return True

    async def op_snap(self) -> dict[str, Any]:
        """Counts now (ours, raw, raw batches), this process's CPU time, import counters."""
        totals = self.importer.stats()["totals"]
        return {
            "t": time.monotonic(),
            "cpu": time.process_time(),
            "ours": self.ours,
            "raw": self.raw[0],
            "rawbatch": self.raw_batch[0],
            "lost": totals["lost"],
            "injected": totals["injected"],
            "dropped_samples": totals["dropped_samples"],
            "dropped_batches": totals["dropped_batches"],
            "inbox_dropped": sum(s.dropped for s in self.importer._subs),
        }

    async def op_record(self, on: bool) -> dict[str, list[int]]:
        """Start recording latencies (``on``), or stop and hand over what was recorded (ns)."""
        self.recording = on
        if on:
            self.lat.clear()
            self.raw_lat.clear()
            return {}
        got = {"ours": list(self.lat), "raw": list(self.raw_lat)}
        self.lat.clear()
        self.raw_lat.clear()
        return got

    async def op_stats(self) -> ImportProxyStats:
        """The import proxy's counters."""
        return self.importer.stats()
