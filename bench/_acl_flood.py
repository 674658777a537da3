"""``bench.acl``'s one-way flood alone: ``python -m bench._acl_flood [N] [ROUNDS]``.

The zenoh flood of ``bench.acl`` (``N`` informs from ``asker@bench-a`` to ``sink@bench-b``,
a spawned node; encryption on) after the same warm-up, ``ROUNDS`` times, without the rest
of the benchmark. Prints one JSON object per round: the end-to-end rate, what was lost,
and each side's CPU per message (the whole process, its loop thread), as `acl.flood`
measures them.

``python -m bench._acl_flood --ab TREE_A TREE_B [--pairs 5] [N] [ROUNDS]`` runs it in a
fresh process per run with ``PYTHONPATH`` set to each source tree in turn, in alternated
pairs (A B, B A, A B ...), and prints each run's median over its rounds, then each tree's
medians and B's over A's: for comparing two states of the code on a loaded machine.
"""

from __future__ import annotations

import asyncio
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

N = 100_000
ROUNDS = 3
KEYS = ("rate", "sender_cpu_us", "sender_loop_us", "node_cpu_us", "node_loop_us", "received")


async def _floods(keydir: Path, n: int, rounds: int) -> list[dict[str, Any]]:
    """``rounds`` floods of ``n`` informs to a spawned node, after bench.acl's warm-up."""
    from bench import acl

    out: list[dict[str, Any]] = []
    async with acl.asker_side(keydir) as side:
        _, _, asker, presence, config = side
        child = acl.node("zenoh", config, keydir).start()
        try:
            await acl.wait_alive(presence, child, True)
            await acl.first_reply(asker, child)
            await acl.round_trips(asker, acl.WARMUP, "warm-up")
            await acl.flood(asker, 5000)  # the sink's path warmed up too
            acl.settle_gc()
            for _ in range(rounds):
                got: dict[str, Any] = dict(await acl.flood(asker, n))
                got.pop("gc_by_gen")
                out.append(got)
        finally:
            await asyncio.to_thread(child.close)
    return out


def measure(n: int = N, rounds: int = ROUNDS) -> list[dict[str, Any]]:
    """The rounds' figures, as `acl.flood` returns them (without the collector's detail)."""
    from agents import run as run_loop
    from bench import acl

    with tempfile.TemporaryDirectory() as tmp:
        keydir = Path(tmp)
        acl.make_keys(keydir)
        result: list[dict[str, Any]] = run_loop(_floods(keydir, n, rounds))
        return result


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    if argv[:1] == ["--ab"]:
        from bench import ab_main  # the parent's only: a child may run an older tree

        ab_main(argv, lambda rest: [sys.executable, "-m", "bench._acl_flood", *rest], KEYS)
        return
    n = int(argv[0]) if argv else N
    rounds = int(argv[1]) if len(argv) > 1 else ROUNDS
    for got in measure(n, rounds):
        print(json.dumps(got), flush=True)


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
