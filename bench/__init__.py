"""Benchmarks: ours against a peer measured in the same run, reported as ``BENCH`` lines.

Each benchmark is a module of this package with a ``run()`` function; ``python -m bench``
runs them all, ``python -m bench <name>`` one of them. The machines we run on are noisy
(2x drift between runs), so a benchmark never reports an absolute figure alone: it runs
the peer in the same process, on the same data, interleaved with ours, and prints the
ratio, one line per comparison, always in this form (so runs can be compared by script)::

    BENCH <name> ours=<number> <peer>=<number> ratio=<ours/peer> unit=<unit> better=<higher|lower>
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def helped(argv: list[str], doc: str | None) -> bool:
    """Print a tool's description when ``-h`` or ``--help`` is asked; True: run nothing."""
    if "-h" not in argv and "--help" not in argv:
        return False
    print((doc or "(no description)").strip())
    return True


def alternate(
    trees: list[str], pairs: int, cmd: list[str], keys: tuple[str, ...]
) -> dict[str, dict[str, float]]:
    """Run ``cmd`` against each source tree in turn (A B, B A, ...), in fresh processes with
    ``PYTHONPATH`` the tree; each of ``keys``' median per tree over its runs' medians over
    the JSON lines each run prints. For A/Bs of two states of the code on a busy machine."""
    runs: dict[str, list[dict[str, float]]] = {t: [] for t in trees}
    for i in range(pairs):
        for tree in trees if i % 2 == 0 else trees[::-1]:
            env = {**os.environ, "PYTHONPATH": tree}
            proc = subprocess.run(
                cmd, cwd=tree, env=env, capture_output=True, text=True, check=True
            )
            got = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
            run = {k: statistics.median(r[k] for r in got) for k in keys}
            runs[tree].append(run)
            shown = " ".join(f"{k}={v:.4g}" for k, v in run.items())
            print(f"pair {i + 1} {tree}: {shown}", flush=True)
    return {t: {k: statistics.median(r[k] for r in rs) for k in keys} for t, rs in runs.items()}


def ab_main(argv: list[str], cmd: Callable[[list[str]], list[str]], keys: tuple[str, ...]) -> None:
    """``--ab TREE_A TREE_B [--pairs P] ARGS...``: `alternate` ``cmd(ARGS)``, print B over A."""
    trees = [str(Path(t).resolve()) for t in argv[1:3]]
    rest = argv[3:]
    pairs = 5
    if rest[:1] == ["--pairs"]:
        pairs, rest = int(rest[1]), rest[2:]
    med = alternate(trees, pairs, cmd(rest), keys)
    for tree, figures in med.items():
        shown = ", ".join(f"{k} {v:.4g}" for k, v in figures.items())
        print(f"median of {pairs} {tree}: {shown}")
    a, b = (med[t] for t in trees)
    print("B / A: " + ", ".join(f"{k} {b[k] / a[k]:.3f}" for k in keys if a[k]))


def fmt(x: float) -> str:
    """A number as BENCH lines print it: three significant digits, ``1.94e6`` when big."""
    if x != 0 and (abs(x) >= 1e4 or abs(x) < 1e-3):
        mantissa, exp = f"{x:.2e}".split("e")
        return f"{mantissa}e{int(exp)}"
    return f"{x:.3g}"


def report(name: str, ours: float, peer_name: str, peer: float, unit: str, *, better: str) -> str:
    """Print (and return) one summary line in the exact form the issues and CI grep for."""
    if better not in ("higher", "lower"):
        raise ValueError(f"better must be 'higher' or 'lower', got {better!r}")
    ratio = ours / peer if peer else float("inf")
    line = (
        f"BENCH {name} ours={fmt(ours)} {peer_name}={fmt(peer)} "
        f"ratio={ratio:.2f} unit={unit} better={better}"
    )
    print(line, flush=True)
    return line


def progress(message: str) -> None:
    """Say what a long run is doing, on stderr so stdout stays the report."""
    print(f"  … {message}", file=sys.stderr, flush=True)


def timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    """Seconds one call of ``fn`` took (perf_counter), and what it returned."""
    t0 = time.perf_counter()
    result = fn()
    return time.perf_counter() - t0, result
