"""Each side's loop thread's instructions per ACL round trip: ``python -m bench._acl_cg``.

Runs ``bench._acl_cpu``'s measurement (``N`` round trips, default 500) under
``valgrind --tool=callgrind --separate-threads=yes``, zeroing the counters when the timed
round trips start and dumping them when they end, so the figure is of the measured
window alone (no start-up, no warm-up, no shut-down). Instruction counts hardly depend
on the load of the machine, which makes them the figure to compare two states of the
code with (what runs on timers, the audit flush's ticks and the like, counts per second
of the window, not per round trip: a loaded run counts a few thousand more; alternate
and compare medians). Prints one JSON object: the loop thread's instructions (Ir) per
round trip, beside it the busiest other thread's (``rx_thread_ir_per_round_trip``:
zenoh's callback thread, where the reply is opened, parsed and handed to the loop) and
all other threads' summed (zenoh's own included), and the files written (``--out DIR``,
default a new temporary directory), for ``callgrind_annotate`` to show per function.

``--side replier`` measures the other side instead: the spawned node runs under
callgrind, the asker does not, over the same window. The gateway's plain read is
answered on zenoh's callback thread (the lane: the request opened, checked, answered,
sealed and put there), so the figure to compare there is that thread's,
``lane_thread_ir_per_round_trip`` (the node's busiest thread but its loop); beside it
the loop thread's (``ir_per_round_trip``: the lane's bookings at the audit flush's
ticks, its idle polls) and all other threads' summed (zenoh's own included).

``python -m bench._acl_cg --ab TREE_A TREE_B [--side replier] [--pairs 3] [N]`` runs
both trees in alternated pairs (A B, B A, ...) with ``PYTHONPATH`` set to each in turn
and prints each run's figure, each tree's median and B's over A's.
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
_MARK_REPLIER = "--_inside-replier"  # this module spawning its node under valgrind
_VALGRIND = ("valgrind", "--tool=callgrind", "--separate-threads=yes")


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


def _inside_replier(out: str, n: int) -> None:
    """The measurement with the node spawned under callgrind, its window marked from here."""
    here = str(Path(__file__).resolve().parent)
    sys.path[:] = [p for p in sys.path if p != here]  # run by path: bench/ is no package root
    import bench._acl_cpu as cpu
    from bench import _child, acl

    # a node under callgrind starts ~50x slower than the 30 s a plain one is given
    acl.START_TIMEOUT = 900.0
    wrapper = Path(out, "python-under-callgrind")
    wrapper.write_text(
        "#!/bin/sh\n"
        f'exec {" ".join(_VALGRIND)} --callgrind-out-file={out}/cg.%p {sys.executable} "$@"\n'
    )
    wrapper.chmod(0o700)
    _child._CTX.set_executable(str(wrapper))
    inner = cpu._main_thread_cpu
    calls = [0]
    me = os.getpid()

    def marked(pid: int) -> float:
        # _measure reads the node's loop thread's CPU once before and once after the window
        if pid != me:
            calls[0] += 1
            if calls[0] == 2:
                _control("-d", "measured", pid=pid)
        got = inner(pid)
        if pid != me and calls[0] == 1:
            _control("-z", pid=pid)
        return got

    cpu._main_thread_cpu = marked
    print(json.dumps(cpu.measure(n)))


def _control(*args: str, pid: int | None = None) -> None:
    """Run ``callgrind_control`` on a process (it answers once the process polls)."""
    cmd = ["callgrind_control", *args, str(os.getpid() if pid is None else pid)]
    subprocess.run(cmd, check=True, capture_output=True, timeout=600)


def _dump_ir(path: Path) -> int:
    """The instructions a dump file holds."""
    for line in path.read_text().splitlines():
        if line.startswith("summary:") or line.startswith("totals:"):
            return int(line.split()[1])
    raise RuntimeError(f"no totals in {path}")


def _loop_thread_ir(out: Path) -> int:
    """The instructions of the loop thread (the main thread, ``-01``) in the window's dump."""
    dumps = sorted(out.glob("cg.*.1-01"))  # dump 1 (the window's), thread 1
    if len(dumps) != 1:
        raise RuntimeError(f"expected one dump of the window's loop thread in {out}, got {dumps}")
    return _dump_ir(dumps[0])


def _other_threads_ir(out: Path) -> list[int]:
    """The instructions of every other thread (zenoh's) in the window's dump, most first."""
    others = (p for p in out.glob("cg.*.1-*") if not p.name.endswith("-01"))
    return sorted((_dump_ir(p) for p in others), reverse=True)


def run(tree: str, n: int, out: Path, side: str = "asker") -> dict[str, Any]:
    """One run of the source ``tree``, ``side`` under callgrind; its loop thread's Ir per trip."""
    out.mkdir(parents=True, exist_ok=True)
    if side == "replier":
        # this file by its path (a tree before ``--side`` has none), the rest from ``tree``
        cmd = [sys.executable, __file__, _MARK_REPLIER, str(out), str(n)]
    else:
        cmd = [*_VALGRIND, f"--callgrind-out-file={out}/cg.%p", sys.executable]
        cmd += ["-m", "bench._acl_cg", _MARK, str(n)]
    env = {**os.environ, "PYTHONPATH": tree}
    proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=3000)
    if proc.returncode != 0:
        raise RuntimeError(f"callgrind run of {tree} failed: {proc.stderr[-2000:]}")
    got: dict[str, Any] = {"side": side, "ir_per_round_trip": _loop_thread_ir(out) / n}
    others = _other_threads_ir(out)
    # the busiest: zenoh's callback thread, where the lane opens and answers a request
    # (the replier) or opens the reply and hands it to the loop (the asker)
    busiest = "lane_thread" if side == "replier" else "rx_thread"
    got[f"{busiest}_ir_per_round_trip"] = others[0] / n if others else 0.0
    got["other_threads_ir_per_round_trip"] = sum(others) / n
    return {**got, "n": n, "tree": tree, "out": str(out)}


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    if argv[:1] == [_MARK]:
        _inside(int(argv[1]))
        return
    if argv[:1] == [_MARK_REPLIER]:
        _inside_replier(argv[1], int(argv[2]))
        return
    args = list(argv)
    side = "asker"
    if "--side" in args:
        i = args.index("--side")
        side = args[i + 1]
        if side not in ("asker", "replier"):
            raise SystemExit(f"--side: asker or replier, not {side!r}")
        del args[i : i + 2]
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
        figures: dict[str, list[dict[str, Any]]] = {t: [] for t in trees}
        for i in range(pairs):
            for k, tree in enumerate(trees if i % 2 == 0 else trees[::-1]):
                got = run(tree, n, out / f"pair{i + 1}-{k}", side)
                figures[tree].append(got)
                print(f"pair {i + 1} {tree}: {json.dumps(got)}", flush=True)
        keys = [k for k in figures[trees[0]][0] if k.endswith("_per_round_trip")]
        med = {t: {k: statistics.median(r[k] for r in v) for k in keys} for t, v in figures.items()}
        for tree, irs in med.items():
            shown = ", ".join(f"{k} {ir:.0f}" for k, ir in irs.items())
            print(f"median of {pairs} {tree}: {shown}")
        a, b = (med[t] for t in trees)
        print("B / A: " + ", ".join(f"{k} {b[k] / a[k]:.3f}" for k in keys if a[k]))
        return
    n = int(args[0]) if args else N
    print(json.dumps(run(str(Path.cwd()), n, out, side)))


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
