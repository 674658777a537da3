"""An ACL round trip's latency and each side's CPU, without probes: ``python -m bench._acl_cpu``.

The zenoh round trip of ``bench.acl`` (``request`` from ``asker@bench-a`` to the gateway
of ``bench-b``, a spawned node; encryption on), N times after a warm-up, nothing wrapped:
what ``bench._acl_trace`` measures minus its probes, so it also runs a tree whose classes
cannot be patched (compiled modules). Printed as one JSON object: the round trip's median
and p90 (µs), each side's event-loop thread CPU per round trip, split into user and
system time (``/proc/<pid>/task/<pid>/stat``), and the CPU of all of each side's
threads (``schedstat``: zenoh's included). With ``--raw`` also raw zenoh's get median
(``bench._zenoh_raw``) measured in the same run, and the ratio.

``--stages`` adds, in both processes, thread-CPU probes around the steps an ACL message
takes (`SessionTable.open` and ``seal``, ``to_json``, the one-call path ``_take_now``,
a reply taken from zenoh's thread: ``_lane_book`` → ``_lane_take_reply`` →
``_take_message`` → ``Agent._deliver``, the asker's conversation opened and closed,
composing, ``_sent`` and the turn's ``_flush``, zenoh's put): each step's median µs as
it runs inside the round trip, on the loop thread, or on zenoh's thread (marked so),
caches cold from everything else the round trip touches, which is several times what
the same step costs timed alone (``python -m bench.acl --profile``). Steps made fewer
times than there were round trips are left out. The probes cost ~0.5 µs each (nested
ones add theirs to the step around them) and wrap methods of the classes (not for
compiled modules).

``python -m bench._acl_cpu --ab TREE_A TREE_B [--pairs 5] [N]`` runs the measurement in
a fresh process per run with ``PYTHONPATH`` set to each source tree in turn, in
alternated pairs (A B, B A, A B ...), and prints each tree's medians and B's over A's:
for comparing two states of the code (a change, or compiled modules beside the pure
Python ones) on a machine that other work loads.
"""

from __future__ import annotations

import asyncio
import functools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

N = 3000
WARMUP = 300
KEYS = ("rtt_median", "rtt_p90", "cpu_a", "cpu_b", "user_a", "sys_a", "user_b", "sys_b")


def _user_sys(pid: int) -> tuple[float, float]:
    """The user and system CPU seconds of process ``pid``'s main thread."""
    stat = Path(f"/proc/{pid}/task/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return int(stat[11]) / tick, int(stat[12]) / tick


def _all_threads_cpu(pid: int) -> float:
    """The CPU seconds of all of process ``pid``'s threads (those alive now)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int(Path(task, "schedstat").read_text().split()[0])
        except OSError:  # a thread that ended meanwhile
            continue
    return total / 1e9


def _main_thread_cpu(pid: int) -> float:
    """The CPU seconds of process ``pid``'s main thread (its event loop's), in ns precision."""
    return int(Path(f"/proc/{pid}/task/{pid}/schedstat").read_text().split()[0]) / 1e9


STAGE_CPU: dict[str, list[int]] = {}  # step → thread CPU (ns) of each call, in this process


def _probe(cls: Any, name: str, label: str) -> None:
    """Note the thread CPU of each call of ``cls.name`` (a method or classmethod) in STAGE_CPU."""
    inner = cls.__dict__[name]
    fn = inner.__func__ if isinstance(inner, classmethod) else inner
    calls = STAGE_CPU.setdefault(label, [])
    # zenoh's threads open envelopes and parse replies too: theirs are noted apart
    elsewhere = STAGE_CPU.setdefault(f"{label} [zenoh's thread]", [])
    cpu = time.thread_time_ns
    ident, loop_thread = threading.get_ident, threading.main_thread().ident

    @functools.wraps(fn)
    def probed(*args: Any, **kwargs: Any) -> Any:
        t = cpu()
        try:
            return fn(*args, **kwargs)
        finally:
            (calls if ident() == loop_thread else elsewhere).append(cpu() - t)

    setattr(cls, name, classmethod(probed) if isinstance(inner, classmethod) else probed)


def install_stage_probes() -> None:
    """Wrap the thread-CPU probes around the steps of an ACL message (in this process)."""
    from agents import ACLMessage, InterfaceAgent
    from agents import _agent as agent_module
    from agents._agent import Agent, Conversation
    from agents._security import SessionTable
    from agents.transports import ZenohTransport

    _probe(SessionTable, "open", "open: SessionTable.open (envelope, AEAD, replay)")
    _probe(SessionTable, "seal", "seal: SessionTable.seal (JSON form)")
    _probe(SessionTable, "seal_binary", "seal: SessionTable.seal_binary (binary form)")
    _probe(ACLMessage, "to_json", "ACLMessage.to_json")
    _probe(InterfaceAgent, "_take_now", "_take_now (parse, checks, audit, deliver)")
    _probe(InterfaceAgent, "_lane_book", "_lane_book (a reply opened on zenoh's thread)")
    _probe(InterfaceAgent, "_lane_take_reply", "  of which _lane_take_reply")
    _probe(InterfaceAgent, "_take_message", "    of which _take_message (checks, audit)")
    _probe(Agent, "_deliver", "      of which Agent._deliver")
    _probe(Conversation, "close", "Conversation.close (the asker's)")
    _probe(Agent, "conversation", "Agent.conversation (the asker's, open)")
    _probe(agent_module, "compose", "compose (an agent's message)")
    _probe(ACLMessage, "build", "ACLMessage.build (compose)")
    _probe(ACLMessage, "reply", "ACLMessage.reply (compose)")
    _probe(InterfaceAgent, "_sent", "InterfaceAgent._sent (renew check, batch after)")
    _probe(InterfaceAgent, "_flush", "InterfaceAgent._flush (the turn's batch)")
    _probe(ZenohTransport, "_put", "ZenohTransport._put (zenoh's put)")
    cpu = time.thread_time_ns
    empty = STAGE_CPU.setdefault("a probe's own cost", [])
    for _ in range(1000):
        t = cpu()
        empty.append(cpu() - t)


def stage_node_main(*args: Any) -> None:
    """The node of ``bench.acl`` with the stage probes, reporting them once stopped."""
    from bench._acl_node import node_main

    install_stage_probes()
    reports = args[-2]
    node_main(*args)
    reports.put(("stages", os.getpid(), STAGE_CPU))


def _stage_medians(calls: dict[str, list[int]], n: int) -> dict[str, float]:
    """Each step's median thread CPU (µs) over its last ``n`` calls (the timed round trips).

    A step made fewer than ``n`` times in all is not one of every round trip (the
    warm-up's, a first message's): it is left out rather than shown beside those.
    """
    return {k: statistics.median(v[-n:]) / 1e3 for k, v in calls.items() if len(v) >= n}


async def _measure(keydir: Path, n: int, stages: bool = False) -> dict[str, Any]:
    """``n`` round trips to a spawned node; latency (µs) and each side's CPU (µs) per trip."""
    from agents import request
    from bench import acl
    from bench._child import Child

    async with acl.asker_side(keydir) as asking:
        _, _, asker, presence, config = asking
        if stages:
            args = ("zenoh", config, str(keydir), acl.THERE, acl.FEDERATION)
            child = Child(stage_node_main, args, "acl-stages-node").start()
        else:
            child = acl.node("zenoh", config, keydir).start()
        try:
            await acl.wait_alive(presence, child, True)
            await acl.first_reply(asker, child)
            await acl.round_trips(asker, WARMUP, "warm-up")
            acl.settle_gc()
            here, there = os.getpid(), child.pid
            before = [f(p) for p in (here, there) for f in (_main_thread_cpu, _all_threads_cpu)]
            times0 = _user_sys(here), _user_sys(there)
            rtts = []
            ns = time.perf_counter_ns
            for _ in range(n):
                t = ns()
                await request(asker, acl.GATEWAY, acl.QUERY, ontology="dyknow", timeout=5.0)
                rtts.append((ns() - t) / 1e3)
            after = [f(p) for p in (here, there) for f in (_main_thread_cpu, _all_threads_cpu)]
            times1 = _user_sys(here), _user_sys(there)
            theirs: dict[str, list[int]] = {}
            if stages:
                child.stop.set()
                theirs = await asyncio.to_thread(child.wait_report, "stages", 30.0)
        finally:
            await asyncio.to_thread(child.close)
    per = [(b - a) / n * 1e6 for a, b in zip(before, after, strict=True)]
    rtts.sort()
    out: dict[str, Any] = {
        "rtt_median": statistics.median(rtts),
        "rtt_p90": rtts[int(0.9 * (len(rtts) - 1))],
        "cpu_a": per[0],
        "all_threads_a": per[1],
        "cpu_b": per[2],
        "all_threads_b": per[3],
    }
    for side, t0, t1 in (("a", times0[0], times1[0]), ("b", times0[1], times1[1])):
        out[f"user_{side}"] = (t1[0] - t0[0]) / n * 1e6
        out[f"sys_{side}"] = (t1[1] - t0[1]) / n * 1e6
    if stages:
        out["stages_a"] = _stage_medians(STAGE_CPU, n)
        out["stages_b"] = _stage_medians(theirs, n)
    return out


def measure(n: int = N, *, raw: bool = False, stages: bool = False) -> dict[str, Any]:
    """One measurement (a spawned node, ``n`` round trips), as `_measure` returns it."""
    from agents import run as run_loop
    from bench import _zenoh_raw, acl

    with tempfile.TemporaryDirectory() as tmp:
        keydir = Path(tmp)
        acl.make_keys(keydir)
        if stages:
            install_stage_probes()
        res = run_loop(_measure(keydir, n, stages))
    if raw:
        got = _zenoh_raw.measure(round_trips=n, flood=1000, payload=acl.ACL_BYTES)
        res["raw_get_median"] = got["get_median"] * 1e3
        res["ratio_vs_raw_get"] = res["rtt_median"] / res["raw_get_median"]
    return res


def ab(trees: list[str], pairs: int, n: int, raw: bool) -> dict[str, dict[str, float]]:
    """Alternated runs of the trees in fresh processes; each figure's median per tree."""
    runs: dict[str, list[dict[str, float]]] = {t: [] for t in trees}
    for i in range(pairs):
        for tree in trees if i % 2 == 0 else trees[::-1]:
            cmd = [sys.executable, "-m", "bench._acl_cpu", str(n)] + (["--raw"] if raw else [])
            env = {**os.environ, "PYTHONPATH": tree}
            proc = subprocess.run(
                cmd, cwd=tree, env=env, capture_output=True, text=True, check=True
            )
            got = json.loads(proc.stdout.strip().splitlines()[-1])
            runs[tree].append(got)
            print(f"pair {i + 1} {tree}: {json.dumps({k: round(v, 1) for k, v in got.items()})}")
    return {t: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for t, rs in runs.items()}


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    raw, stages = "--raw" in argv, "--stages" in argv
    args = [a for a in argv if a not in ("--raw", "--stages")]
    if args and args[0] == "--ab":
        trees = [str(Path(t).resolve()) for t in args[1:3]]
        rest = args[3:]
        pairs = 5
        if rest[:1] == ["--pairs"]:
            pairs, rest = int(rest[1]), rest[2:]
        n = int(rest[0]) if rest else N
        med = ab(trees, pairs, n, raw)
        for tree, figures in med.items():
            shown = ", ".join(f"{k} {v:.1f}" for k, v in figures.items())
            print(f"median of {pairs} {tree}: {shown}")
        a, b = (med[t] for t in trees)
        print("B / A: " + ", ".join(f"{k} {b[k] / a[k]:.3f}" for k in KEYS if a.get(k)))
        return
    res = measure(int(args[0]) if args else N, raw=raw, stages=stages)
    if stages:
        for side, who in (("a", "asker"), ("b", "node")):
            print(f"{who}'s loop thread, each step's thread CPU inside the round trip (median µs):")
            for step, us in res.pop(f"stages_{side}").items():
                print(f"  {step:<52} {us:6.2f}")
    print(json.dumps(res))


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
