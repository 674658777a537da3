"""The operator's import of the scale flow, CPU per batch: ``python -m bench._import_cpu``.

Not a benchmark of its own (``make bench`` does not run it). The receive side of
``bench.scale``'s stream flow without zenoh or a second process, so that it can be
measured on a loaded machine (thread CPU) or counted (callgrind): 32 senders × 10
streams export to ``operator``, one sample a batch, sealed by real sessions (the default
policy, encrypted, but a skew of an hour). The batches are queued beforehand in the
import's own subscription inbox, as zenoh's callback queues them (key expression,
payload, attachment), then the import's receive loop drains them: the Message made,
opened, read, sequence checked, added to the instance, given to a subscriber per stream
(a counter, as the benchmark's).

Printed as one JSON object: thread CPU µs per batch (median of ``--runs`` runs of
``--rounds`` batches per stream each) and the batches imported. ``--ab TREE_A TREE_B
[--pairs 5]`` runs it in a fresh process per run with ``PYTHONPATH`` set to each tree in
turn, alternated, and prints each tree's median and B's over A's. Under callgrind
(``PYTHONHASHSEED=0``, ``--runs 1``) the instructions of the measured imports are a run's
count less that of the same run with ``--seal-only`` (everything but those imports).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Any

import zenoh

from agents._security import Handshake, KeyPair, SecurityPolicy, SessionTable, TrustStore
from agents.transports import MemoryHub, MemoryTransport
from agents.transports._base import Inbox, Subscription
from agents.transports._zenoh import _message
from dyknow_core import DyKnowInstance
from federation._batch import pack_batch
from federation._import import ImportProxy
from federation._sessions import TableSessions

FED = "bench-import-cpu"
ME = "operator"
SENDERS = 32
STREAMS = 10


def _sessions(trust: TrustStore, keys: dict[str, KeyPair], senders: list[str]) -> Any:
    """A receiving table with one session per sender, and each sender's sending table."""
    # the default policy but for the skew: under callgrind the sealing beforehand takes
    # longer than the default 30 s, and batches stamped that long ago would be refused
    policy = SecurityPolicy(skew=3600.0)
    rx = SessionTable(ME, trust, policy=policy)
    txs: dict[str, SessionTable] = {}
    me = Handshake(keys[ME], trust, policy=policy)
    for s in senders:
        hs = Handshake(keys[s], trust, policy=policy)
        reply, session = me.respond(hs.initiate(ME))
        tx = SessionTable(s, trust, policy=policy)
        tx.add(hs.finish(reply))
        rx.add(session)
        txs[s] = tx
    return rx, txs


async def _run(rounds: int, runs: int, seal_only: bool = False) -> dict[str, float]:
    senders = [f"uav{i:02d}" for i in range(SENDERS)]
    keys = {n: KeyPair.generate(n) for n in [ME, *senders]}
    trust = TrustStore(FED, {n: k.public_key for n, k in keys.items()})
    rx, txs = _sessions(trust, keys, senders)
    instance = DyKnowInstance(ME)
    proxy = ImportProxy(
        ME,
        FED,
        MemoryTransport(MemoryHub()),
        instance,
        TableSessions(rx),
        translate=lambda sender, semantic: f"{sender}.{semantic.replace('/', '.')}",
    )
    prefix = proxy._prefix
    streams = [(s, f"uav/s{j}") for s in senders for j in range(STREAMS)]
    keyexprs = {(s, sem): zenoh.KeyExpr(f"{prefix}{s}/{sem}") for s, sem in streams}
    loop = asyncio.get_running_loop()
    got = [0]

    def count(batch: list[Any]) -> None:
        got[0] += len(batch)

    seq = 0

    def sealed(n: int) -> list[Any]:
        nonlocal seq
        out = []
        for _ in range(n):
            t = time.time_ns()
            for s, sem in streams:
                body = pack_batch(sem, [(seq, t, t)], seq)
                out.append((keyexprs[s, sem], txs[s].seal_bytes(ME, body), None))
            seq += 1
        return out

    async def drain(raw: list[Any]) -> float:
        inbox: Inbox[Any] = Inbox(loop, len(raw) + 1, convert=_message)
        for r in raw:
            inbox.put(r)
        sub: Subscription[Any] = Subscription(inbox, lambda: None)
        sub.close()  # drained to its end, then the loop returns (closed: not a loss)
        t0 = time.thread_time()
        await proxy._receive(sub)
        return time.thread_time() - t0

    await drain(sealed(1))  # the first batches make the sources
    for s, sem in streams:
        instance.subscribe(proxy._imports[s, sem].local_label or "", callback=count)
    await drain(sealed(2))
    per: list[float] = []
    for _ in range(runs):
        raw = sealed(rounds)
        gc.collect()
        if seal_only:  # what callgrind counts besides the import: subtracted from a full run
            continue
        per.append(1e6 * await drain(raw) / len(raw))
    if seal_only:
        return {"us_per_batch": 0.0, "batches": 0.0}
    injected = sum(r.injected for r in proxy._imports.values())
    if injected != (3 + rounds * runs) * len(streams) or got[0] != (2 + rounds * runs) * len(
        streams
    ):
        raise SystemExit(f"imported {injected}, subscribers got {got[0]}: batches were dropped")
    return {"us_per_batch": statistics.median(per), "batches": float(rounds * runs * len(streams))}


def ab(trees: list[str], pairs: int, extra: list[str]) -> dict[str, float]:
    """Alternated runs of the trees in fresh processes; each tree's median µs per batch."""
    runs: dict[str, list[float]] = {t: [] for t in trees}
    for i in range(pairs):
        for tree in trees if i % 2 == 0 else trees[::-1]:
            env = {**os.environ, "PYTHONPATH": tree}
            proc = subprocess.run(
                [sys.executable, "-m", "bench._import_cpu", *extra],
                cwd=tree,
                env=env,
                capture_output=True,
                text=True,
                check=True,
            )
            got = json.loads(proc.stdout.strip().splitlines()[-1])
            runs[tree].append(got["us_per_batch"])
            print(f"pair {i + 1} {tree}: {got['us_per_batch']:.2f} µs/batch")
    return {t: statistics.median(v) for t, v in runs.items()}


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    p = argparse.ArgumentParser(prog="python -m bench._import_cpu")
    p.add_argument("--rounds", type=int, default=20, help="batches per stream per run")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--ab", nargs=2, metavar="TREE")
    p.add_argument("--pairs", type=int, default=5)
    p.add_argument("--seal-only", action="store_true", help="all but the measured imports")
    a = p.parse_args(argv)
    if a.ab:
        med = ab(a.ab, a.pairs, ["--rounds", str(a.rounds), "--runs", str(a.runs)])
        ta, tb = a.ab
        print(f"A {ta}: {med[ta]:.2f} µs/batch; B {tb}: {med[tb]:.2f}; B/A {med[tb] / med[ta]:.3f}")
        return
    print(json.dumps(asyncio.run(_run(a.rounds, a.runs, a.seal_only))))


if __name__ == "__main__":
    main(sys.argv[1:])
