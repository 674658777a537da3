"""Where the time of ``export-throughput`` goes, per sample, on both sides.

Not a benchmark of its own (``make bench`` does not run it):
``.venv/bin/python -m bench._fed_profile``. With the exporter and one receiver of
``bench.federation``:

0. in this process, unprofiled: each stage of the path timed alone on the same batches
   (pack, seal, the export queue's drain; open, unpack, the import's per-sample loop,
   the whole ``ImportProxy._handle``), beside an alternative batch layout (columns
   instead of rows; not in the stack) for comparison;
1. an unprofiled ours flood: CPU per sample by thread (``/proc/self/task``), so the split
   between the event loop and zenoh's own threads is seen undisturbed;
2. a flood with cProfile on each node's event-loop thread: the functions with the most
   own time, as µs per sample (the exporter's per sample sent, the receiver's per sample
   its subscriber got), and the cumulative time of the stages of the path.

cProfile inflates what it measures, most of all per-sample builtin calls (``append``,
``len``), so its µs are several times the unprofiled ones; step 0 gives the real costs.
"""

from __future__ import annotations

import asyncio
import gc
import os
import pstats
import sys
import tempfile
import time
from collections import deque
from typing import Any

import msgpack

from agents._security import Handshake, KeyPair, SessionTable, TrustStore
from agents.transports import MemoryHub, MemoryTransport
from bench import progress
from bench._fed_node import BATCH, FED, SEM, _values, imported_label
from bench._fed_proc import Node, cluster
from bench.federation import WARM, _settle
from dyknow_core import DyKnowInstance, Policy
from federation._batch import pack_batch, unpack_batch
from federation._import import ImportProxy
from federation._sessions import TableSessions

WINDOW = 3.0

# the stages of the path whose cumulative time is shown (file fragment, function name)
STAGES = {
    "exporter": [
        ("_fed_node.py", "op_flood"),
        ("_stream.py", "publish_batch"),
        ("_export.py", "_on_batch"),
        ("_export.py", "_flush"),
        ("_export.py", "_send_now"),
        ("_export.py", "_run"),
        ("_export.py", "_send"),
        ("_export.py", "_pack"),
        ("_batch.py", "pack_batch"),
        ("_export.py", "_seal"),
        ("_security.py", "seal_bytes"),
        ("_zenoh.py", "publish"),
        ("_zenoh.py", "publish_nowait"),
        ("~", "'put' of"),
    ],
    "receiver": [
        ("_import.py", "_receive"),
        ("_base.py", "__anext__"),
        ("_base.py", "take"),
        ("_zenoh.py", "_message"),
        ("_import.py", "_handle"),
        ("_security.py", "open_bytes"),
        ("_security.py", "_accept_bytes"),
        ("_batch.py", "read_batch"),
        ("_import.py", "_add"),
        ("_stream.py", "publish_batch"),
        ("_filter.py", "__call__"),
        ("_fed_node.py", "_on_batch"),
    ],
}


def _per_sample(label: str, fn: Any, n: int, repeat: int = 3) -> float:
    """Best of ``repeat`` timings of ``fn()``, in µs per sample, printed."""
    best = float("inf")
    for _ in range(repeat):
        gc.collect()
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    us = 1e6 * best / n
    print(f"    {us:7.3f} µs/sample  {label}")
    return us


def in_process(batches: int = 500) -> None:
    """Time each stage of the path alone, unprofiled, on the same sealed batches."""
    keys = {n: KeyPair.generate(n) for n in ("exporter", "receiver")}
    trust = TrustStore(FED, {n: k.public_key for n, k in keys.items()})
    values = _values(BATCH)
    t0 = time.time_ns()
    rows = [
        [(v, t0 + k * BATCH + i, t0 + k * BATCH + i) for i, v in enumerate(values)]
        for k in range(batches)
    ]
    n = batches * BATCH
    gc.collect()
    gc.freeze()  # the inputs out of the collector's way, as a steady heap would be
    try:
        _stages(rows, n, keys, trust)
    finally:
        gc.unfreeze()


def _stages(rows: list[list[Any]], n: int, keys: dict[str, KeyPair], trust: TrustStore) -> None:
    """The timings of `in_process`, on inputs made beforehand."""
    batches = len(rows)
    print(f"  in this process, unprofiled, {batches} batches of {BATCH} samples (best of 3):")
    print("  send side")
    _per_sample(
        "pack_batch (msgpack, rows [v, tv, ta])", lambda: [pack_batch(SEM, r) for r in rows], n
    )
    bodies = [pack_batch(SEM, r, k * BATCH) for k, r in enumerate(rows)]

    def table_pair() -> tuple[SessionTable, SessionTable]:
        hs = {n: Handshake(k, trust) for n, k in keys.items()}
        tx, rx = SessionTable("exporter", trust), SessionTable("receiver", trust)
        reply, session = hs["receiver"].respond(hs["exporter"].initiate("receiver"))
        tx.add(hs["exporter"].finish(reply))
        rx.add(session)
        return tx, rx

    tx, _ = table_pair()
    _per_sample(
        f"seal_bytes (HMAC-SHA256 over {len(bodies[0])} bytes)",
        lambda: [tx.seal_bytes("receiver", b) for b in bodies],
        n,
    )

    def drain(listcomp: bool) -> None:
        for r in rows:
            q = deque(r, maxlen=8192)
            if listcomp:
                popleft = q.popleft
                _ = [popleft() for _ in range(min(len(q), BATCH))]
            else:
                _ = list(q)
                q.clear()

    _per_sample(
        "export queue drain as is: [q.popleft() for ...] (+ deque fill)", lambda: drain(True), n
    )
    _per_sample("  alternative: list(q); q.clear() (+ deque fill)", lambda: drain(False), n)
    print("  receive side")
    # opening consumes the envelopes' counters (a replay is refused): fresh ones each time
    fresh: list[tuple[SessionTable, list[bytes]]] = []
    for _ in range(3):
        tx, rx = table_pair()
        fresh.append((rx, [tx.seal_bytes("receiver", b) for b in bodies]))

    def open_all() -> None:
        rx, envelopes = fresh.pop()
        for e in envelopes:
            rx.open_bytes(e)

    _per_sample("open_bytes (parse, HMAC check, replay window)", open_all, n)

    def unpack_all() -> None:  # results dropped at once: a big live heap would add GC time
        for b in bodies:
            unpack_batch(b)

    _per_sample("unpack_batch (msgpack)", unpack_all, n)
    unpacked = [unpack_batch(b)[2] for b in bodies]

    def inject_loop() -> None:  # the per-sample loop of ImportProxy._add, as it is
        ta = 1
        for samples in unpacked:
            out: list[Any] = []
            append = out.append
            for s in samples:
                if type(s) is list and len(s) == 3 and type(s[1]) is int:
                    append((s[0], s[1], ta))
                    ta += 1

    _per_sample("ImportProxy._add's per-sample check and rebuild", inject_loop, n)
    unpacked.clear()
    asyncio.run(_whole_handle(bodies, table_pair, n))
    print("  alternative batch layout, columns {x: [values], t: [valid times]} (not in the stack)")
    columns = [
        msgpack.packb({"v": 2, "s": SEM, "q": 0, "x": [s[0] for s in r], "t": [s[1] for s in r]})
        for r in rows
    ]
    print(f"    {len(columns[0])} bytes a batch instead of {len(bodies[0])}")

    def receive_rows() -> None:
        ta = 1
        for b in bodies:
            samples = unpack_batch(b)[2]
            out: list[Any] = []
            append = out.append
            for s in samples:
                if type(s) is list and len(s) == 3 and type(s[1]) is int:
                    append((s[0], s[1], ta))
                    ta += 1

    def receive_columns() -> None:
        ta = 1
        for b in columns:
            obj = msgpack.unpackb(b, raw=False, strict_map_key=False)
            xs, ts = obj["x"], obj["t"]
            m = len(ts)
            if len(xs) != m or set(map(type, ts)) != {int}:
                raise ValueError("malformed")
            _ = list(zip(xs, ts, range(ta, ta + m), strict=True))
            ta += m

    _per_sample("rows as now: unpack + per-sample check and rebuild", receive_rows, n)
    _per_sample("columns: unpack + C-level type check + zip with arrival times", receive_columns, n)


async def _whole_handle(bodies: list[bytes], table_pair: Any, n: int) -> None:
    """The whole receive path, ``ImportProxy._handle``, into a subscriber with bounds."""
    key = f"dyknow/{FED}/v1/stream/receiver/exporter/{SEM}"
    runs: list[tuple[ImportProxy, list[bytes], list[int]]] = []
    for _ in range(3):
        tx, rx = table_pair()
        instance = DyKnowInstance("receiver")
        proxy = ImportProxy(
            "receiver",
            FED,
            MemoryTransport(MemoryHub()),
            instance,
            TableSessions(rx),
            translate=lambda sender, _semantic: imported_label(sender),
        )
        envelopes = [tx.seal_bytes("receiver", b) for b in bodies]
        proxy._handle(key, envelopes[0])  # the first batch makes the source
        got = [0]

        def count(batch: list[Any], got: list[int] = got) -> None:
            got[0] += len(batch)

        instance.subscribe(
            imported_label("exporter"), Policy(lower=0.0, upper=100.0), callback=count
        )
        runs.append((proxy, envelopes[1:], got))

    def handle() -> None:
        proxy, envelopes, _ = runs.pop()
        h = proxy._handle
        for e in envelopes:
            h(key, e)

    m = n - BATCH
    _per_sample(
        "ImportProxy._handle whole: open, unpack, inject, cache, bounded subscriber", handle, m
    )


def _threads(node: Node) -> dict[str, float]:
    return dict(node.call("threads"))


def _split(before: dict[str, float], after: dict[str, float], n: int) -> str:
    used = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in after}
    total = sum(used.values())
    parts = sorted(((v, k) for k, v in used.items() if v > 0.005), reverse=True)
    return f"{1e6 * total / n:.3f} µs/sample in all: " + ", ".join(
        f"{k} {1e6 * v / n:.3f}" for v, k in parts
    )


def _flood(exporter: Node, receiver: Node, *, profile: bool) -> dict[str, Any]:
    """One ours flood; counts, thread CPU, and (``profile``) the two pstats files."""
    watch = [receiver.name]
    flood = exporter.send("flood", "ours", WARM + WINDOW + 0.3, watch)
    time.sleep(WARM)
    paths = {}
    if profile:
        exporter.call("profile", None)
        receiver.call("profile", None)
    t0 = {"exporter": _threads(exporter), "receiver": _threads(receiver)}
    g0 = {"exporter": exporter.call("gc"), "receiver": receiver.call("gc")}
    e0, r0 = exporter.call("snap"), receiver.call("snap")
    time.sleep(WINDOW)
    e1, r1 = exporter.call("snap"), receiver.call("snap")
    g1 = {"exporter": exporter.call("gc"), "receiver": receiver.call("gc")}
    t1 = {"exporter": _threads(exporter), "receiver": _threads(receiver)}
    if profile:
        for role, node in (("exporter", exporter), ("receiver", receiver)):
            fd, path = tempfile.mkstemp(prefix=f"fed-{role}-", suffix=".pstats")
            os.close(fd)
            paths[role] = node.call("profile", path, timeout=30)
    exporter.result(flood, WARM + WINDOW + 20)
    _settle([receiver])
    sent = e1["exports"][receiver.name]["sent"] - e0["exports"][receiver.name]["sent"]
    got = r1["ours"] - r0["ours"]
    gcs = {
        role: {
            "seconds": g1[role]["seconds"] - g0[role]["seconds"],
            "runs": [b - a for a, b in zip(g0[role]["runs"], g1[role]["runs"], strict=True)],
            "tracked": g1[role]["tracked"],
        }
        for role in g0
    }
    return {
        "sent": sent,
        "got": got,
        "t0": t0,
        "t1": t1,
        "gc": gcs,
        "paths": paths,
        "dt": r1["t"] - r0["t"],
    }


def _short(key: tuple[str, int, str]) -> str:
    file, line, func = key
    if file == "~":
        return func
    parts = file.split(os.sep)
    return f"{'/'.join(parts[-2:])}:{line}({func})"


def _print_profile(role: str, path: str, n: int, top: int = 22) -> None:
    stats: dict[Any, Any] = pstats.Stats(path).stats  # type: ignore[attr-defined]
    total = sum(v[2] for v in stats.values())
    per = 1e6 * total / n
    print(f"\n  {role}: cProfile of the event-loop thread, {n} samples, {per:.3f} µs/sample")
    print(f"    {'own µs/sample':>13} {'share':>6} {'calls/sample':>12}  function")
    for key, (_cc, nc, tt, _ct, _callers) in sorted(
        stats.items(), key=lambda kv: kv[1][2], reverse=True
    )[:top]:
        print(f"    {1e6 * tt / n:13.4f} {tt / total:6.1%} {nc / n:12.4f}  {_short(key)}")
    print("    stages (cumulative µs/sample):")
    for frag, func in STAGES[role]:
        for key, (_cc, nc, _tt, ct, _callers) in stats.items():
            if (key[2] == func or (frag == "~" and func in key[2])) and frag in key[0]:
                print(f"    {1e6 * ct / n:13.4f} {ct / total:6.1%} {nc / n:12.4f}  {_short(key)}")


def main() -> int:
    """Profile the throughput path on both sides and print where the time goes."""
    in_process()
    with cluster(1) as (exporter, (receiver,)):
        progress("warm-up flood")
        _flood(exporter, receiver, profile=False)
        progress("unprofiled flood: CPU per sample by thread")
        plain = _flood(exporter, receiver, profile=False)
        print(
            f"  unprofiled: exporter sent {plain['sent'] / plain['dt']:.3g}/s, "
            f"receiver got {plain['got'] / plain['dt']:.3g}/s"
        )
        print(
            "  exporter, per sample sent: "
            + _split(plain["t0"]["exporter"], plain["t1"]["exporter"], plain["sent"])
        )
        print(
            "  receiver, per sample got:  "
            + _split(plain["t0"]["receiver"], plain["t1"]["receiver"], plain["got"])
        )
        for role, n in (("exporter", plain["sent"]), ("receiver", plain["got"])):
            g = plain["gc"][role]
            print(
                f"  {role}: garbage collector {1e6 * g['seconds'] / n:.3f} µs/sample "
                f"(runs by generation {g['runs']}, {g['tracked']} objects tracked)"
            )
        progress("profiled flood")
        prof = _flood(exporter, receiver, profile=True)
        print(
            f"\n  profiled: exporter sent {prof['sent'] / prof['dt']:.3g}/s, "
            f"receiver got {prof['got'] / prof['dt']:.3g}/s"
        )
        _print_profile("exporter", prof["paths"]["exporter"], prof["sent"])
        _print_profile("receiver", prof["paths"]["receiver"], prof["got"])
        for path in prof["paths"].values():
            print(f"  pstats kept in {path}")
    return 0


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        sys.exit(main())
