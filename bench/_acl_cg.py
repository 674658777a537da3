"""The asker's loop thread's instructions per ACL round trip: ``python -m bench._acl_cg``.

Runs ``bench._acl_cpu``'s measurement (``N`` round trips, default 500) under
``valgrind --tool=callgrind --separate-threads=yes``, zeroing the counters when the timed
round trips start and dumping them when they end, so the figure is of the measured
window alone (no start-up, no warm-up, no shut-down). Instruction counts do not depend
on the load of the machine, which makes them the figure to compare two states of the
code with. Prints one JSON object: the loop thread's instructions (Ir) per round trip,
and the files written (``--out DIR``, default a new temporary directory), for
``callgrind_annotate`` to show per function.

``python -m bench._acl_cg --ab TREE_A TREE_B [--pairs 3] [N]`` runs both trees in
alternated pairs (A B, B A, ...) with ``PYTHONPATH`` set to each in turn and prints
each run's figure, each tree's median and B's over A's.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

N = 500
_MARK = "--_inside"  # this module run by valgrind: mark the window


def _inside(n: int) -> None:
    """The measurement, with callgrind's counters zeroed and dumped around the window."""
    import bench._acl_cpu as cpu

    inner = cpu._main_thread_cpu
    calls = [0]
    me = os.getpid()

    def marked(pid: int) -> float:
        # _measure reads the loop thread's CPU once before and once after the window
        if pid == me:
            calls[0] += 1
            if calls[0] == 2:  # the window's end: dump before reading
                _control("-d", "measured")
        got = inner(pid)
        if pid == me and calls[0] == 1:  # the window's start: zero after reading
            _control("-z")
        return got

    cpu._main_thread_cpu = marked
    print(json.dumps(cpu.measure(n)))


def _control(*args: str) -> None:
    """Run ``callgrind_control`` on this process (it answers once the process polls)."""
    cmd = ["callgrind_control", *args, str(os.getpid())]
    subprocess.run(cmd, check=True, capture_output=True, timeout=600)


def _loop_thread_ir(out: Path) -> int:
    """The instructions of the loop thread (the main thread, ``-01``) in the window's dump."""
    dumps = sorted(out.glob("cg.*.1-01"))  # dump 1 (the window's), thread 1
    if len(dumps) != 1:
        raise RuntimeError(f"expected one dump of the window's loop thread in {out}, got {dumps}")
    for line in dumps[0].read_text().splitlines():
        if line.startswith("summary:") or line.startswith("totals:"):
            return int(line.split()[1])
    raise RuntimeError(f"no totals in {dumps[0]}")


def run(tree: str, n: int, out: Path) -> dict[str, Any]:
    """One run of the source ``tree`` under callgrind; the loop thread's Ir per round trip."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [
        "valgrind",
        "--tool=callgrind",
        "--separate-threads=yes",
        f"--callgrind-out-file={out}/cg.%p",
        sys.executable,
        "-m",
        "bench._acl_cg",
        _MARK,
        str(n),
    ]
    env = {**os.environ, "PYTHONPATH": tree}
    proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=3000)
    if proc.returncode != 0:
        raise RuntimeError(f"callgrind run of {tree} failed: {proc.stderr[-2000:]}")
    ir = _loop_thread_ir(out)
    return {"ir_per_round_trip": ir / n, "n": n, "tree": tree, "out": str(out)}


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    if argv[:1] == [_MARK]:
        _inside(int(argv[1]))
        return
    args = list(argv)
    out = Path(tempfile.mkdtemp(prefix="acl_cg_"))
    if "--out" in args:
        i = args.index("--out")
        out = Path(args[i + 1])
        del args[i : i + 2]
    if args[:1] == ["--ab"]:
        trees = [str(Path(t).resolve()) for t in args[1:3]]
        rest = args[3:]
        pairs = 3
        if rest[:1] == ["--pairs"]:
            pairs, rest = int(rest[1]), rest[2:]
        n = int(rest[0]) if rest else N
        figures: dict[str, list[float]] = {t: [] for t in trees}
        for i in range(pairs):
            for k, tree in enumerate(trees if i % 2 == 0 else trees[::-1]):
                got = run(tree, n, out / f"pair{i + 1}-{k}")
                figures[tree].append(got["ir_per_round_trip"])
                print(f"pair {i + 1} {tree}: {json.dumps(got)}", flush=True)
        med = {t: statistics.median(v) for t, v in figures.items()}
        for tree, ir in med.items():
            print(f"median of {pairs} {tree}: Ir per round trip {ir:.0f}")
        a, b = (med[t] for t in trees)
        print(f"B / A: {b / a:.3f}")
        return
    n = int(args[0]) if args else N
    print(json.dumps(run(str(Path.cwd()), n, out)))


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
