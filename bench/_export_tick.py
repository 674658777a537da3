"""What a UAV's stream tick costs its event loop: ``python -m bench._export_tick``.

Not a benchmark of its own (``make bench`` does not run it). One platform's side of
``bench.scale``'s stream flow, in one process and without zenoh's threads: a DyKnow
instance with ``--streams`` sources (10), each exported by an `ExportProxy` to one
receiver over the in-memory transport, sealed with a real session (`Handshake`); a tick
pushes one sample to every source and lets the loop run until every export sent it.
``--watched``: each stream read once from another thread first
(`DyKnowInstance.latest_many_now`), so that its cache keeps its latest sample up to date
as a UAV's does (its lane answers the global get-latest from it).
Printed as JSON: the event-loop thread's CPU per tick (``thread_time``, median of
``--rounds`` rounds of ``--ticks`` ticks), the batches sent and the samples dropped.

For instruction counts run it under callgrind twice, with two tick counts, and divide
the difference by the difference of ticks (what starting up costs cancels out)::

    valgrind --tool=callgrind --callgrind-out-file=/dev/null python bench/_export_tick.py \
        --ticks 2000 --rounds 1

``--ab TREE_A TREE_B [--pairs 3]`` runs it in a fresh process per run with
``PYTHONPATH`` set to each source tree in turn (A B, B A, ...), and prints each tree's
median and B's over A's.
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

FED = "tickfed"
ME, PEER = "uav-0", "operator"


async def _run(streams: int, ticks: int, rounds: int, watched: bool) -> dict[str, Any]:
    """The workload: ``rounds`` × ``ticks`` ticks of ``streams`` exports, timed per round."""
    from agents._security import Handshake, KeyPair, SessionTable, TrustStore
    from agents.transports import MemoryHub, MemoryTransport
    from dyknow_core import DyKnowInstance
    from federation._export import ExportProxy
    from federation._sessions import TableSessions

    keys = {n: KeyPair.generate(n) for n in (ME, PEER)}
    trust = TrustStore(FED, {n: k.public_key for n, k in keys.items()})
    hs = {n: Handshake(k, trust) for n, k in keys.items()}
    table = SessionTable(ME, trust)
    reply, _ = hs[PEER].respond(hs[ME].initiate(PEER))
    table.add(hs[ME].finish(reply))
    instance = DyKnowInstance(ME)
    sources = [instance.add_source(f"local/{j}") for j in range(streams)]
    async with MemoryTransport(MemoryHub()) as transport:
        proxy = ExportProxy(ME, FED, transport, instance, TableSessions(table), lease=None)
        async with proxy:
            exports = [
                proxy.start_exporting(f"local/{j}", f"sem/{j}", PEER) for j in range(streams)
            ]
            loop = asyncio.get_running_loop()
            await asyncio.sleep(0.05)  # every task started and waiting
            if watched:  # as a UAV's lane reads them (`DyKnowInstance.latest_many_now`)
                instance.latest_many_now([f"local/{j}" for j in range(streams)])

            async def tick(seq: int) -> None:
                for source in sources:
                    source.push(seq)
                # the exports run in the next turns of the loop: yield until all sent
                want = (seq + 1) * streams
                for _ in range(100):
                    await asyncio.sleep(0)
                    if sum(e.sent for e in exports) >= want:
                        return
                raise RuntimeError(f"tick {seq}: not every export sent within 100 turns")

            seq = 0
            for _ in range(50):  # warm-up
                await tick(seq)
                seq += 1
            gc.collect()
            gc.freeze()
            per_tick = []
            for _ in range(rounds):
                t0 = time.thread_time()
                for _ in range(ticks):
                    await tick(seq)
                    seq += 1
                per_tick.append((time.thread_time() - t0) / ticks)
            gc.unfreeze()
            del loop
            return {
                "cpu_us_per_tick": 1e6 * statistics.median(per_tick),
                "batches": sum(e.batches for e in exports),
                "sent": sum(e.sent for e in exports),
                "dropped": sum(e.dropped_total for e in exports),
                "ticks": seq,
            }


def _ab(tree_a: str, tree_b: str, pairs: int, rest: list[str]) -> None:
    """Alternate fresh runs on two source trees; print each one's median and B/A."""
    figures: dict[str, list[float]] = {tree_a: [], tree_b: []}
    for i in range(pairs):
        order = (tree_a, tree_b) if i % 2 == 0 else (tree_b, tree_a)
        for tree in order:
            env = {**os.environ, "PYTHONPATH": tree}
            out = subprocess.run(
                [sys.executable, os.path.abspath(__file__), *rest],
                env=env,
                capture_output=True,
                text=True,
                check=True,
                timeout=600,
            ).stdout
            figures[tree].append(json.loads(out)["cpu_us_per_tick"])
    a, b = statistics.median(figures[tree_a]), statistics.median(figures[tree_b])
    print(json.dumps({"A": tree_a, "B": tree_b, "a_us": a, "b_us": b, "b_over_a": b / a}))
    print(json.dumps(figures))


def main() -> None:
    """Parse the arguments; run the workload, or the A/B of two trees."""
    # run as a file (by `--ab`, or under valgrind): its folder, whose `federation.py` would
    # hide the package, off the path; the tree comes from PYTHONPATH
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != here]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--streams", type=int, default=10)
    ap.add_argument("--ticks", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--ab", nargs=2, metavar=("TREE_A", "TREE_B"))
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument(
        "--watched", action="store_true", help="the streams read from another thread, as a UAV's"
    )
    a = ap.parse_args()
    if a.ab:
        rest = ["--streams", str(a.streams), "--ticks", str(a.ticks), "--rounds", str(a.rounds)]
        rest += ["--watched"] if a.watched else []
        _ab(a.ab[0], a.ab[1], a.pairs, rest)
        return
    print(json.dumps(asyncio.run(_run(a.streams, a.ticks, a.rounds, a.watched))))


if __name__ == "__main__":
    main()
