"""Memory: a stream cached as "the last 10 s" under 1 M samples; a node's start and idle RSS.

A 1 kHz stream pushed for 1000 s of valid time through a source whose cache is
``CacheSpec(max_samples=None, max_age=10)``, with one subscriber, against the least
any program could hold for the same question: the last 10 s of samples in a
``deque(maxlen=10_000)`` fed the same batches. Both are measured with tracemalloc (Python
allocations only, so the figure does not depend on what the interpreter had mapped
before) from just before the first push; the in-flight batch counts for both.
Memory is printed at a few points of the run: it must level off once 10 s are cached.

Then a whole node: ``dyknow node`` (``python -m federation.cli node``, a platform with its
Interface Agent, encryption on) spawned from its TOML config, from just before the spawn
until it prints that it is ready, and its RSS once idle; beside it, in the same run, the
least a zenoh node can be: a fresh interpreter that opens a session with the same
settings, declares a queryable and a liveliness token, and says it is ready (``BENCH
federation-node-ready`` and ``federation-node-rss``; ``bench.acl``'s ``node-ready`` is an
agent platform without the federation); and the same zenoh node after importing the
third-party packages ``dyknow node`` imports (asyncio, uvloop, pydantic with a model
built, PyNaCl, msgpack, orjson; not typer, which only the other commands use, nor
cryptography, which comes with the first session's cipher, and a node alone has none):
the least a node built on them can hold, so what is above it is our own code and state.
The node runs from a copy of our packages with their bytecode compiled, as an installed
node has it: compiling ~70 modules from source (when ``PYTHONDONTWRITEBYTECODE`` keeps
the tree free of it) costs ~0.5 s at every start.
Beside it, the imports alone (what ``dyknow node`` imports before it reads its config),
to split start → ready into imports and the platform's start. Each one's idle RSS is split
by what holds it (``/proc/<pid>/smaps``): the anonymous memory (Python's objects and the
native heaps: zenoh's, pydantic-core's validators), and the pages of each large shared
library that the process touched (zenoh's, the interpreter's, OpenSSL's, pydantic-core's,
uvloop's), so what a change saves shows where it saved it.
Most of a node's RSS is pages of shared libraries that every Python process of the host
maps from the same files (zenoh's alone is ~15 MB of them), counted whole in each one's
RSS. So each one's PSS (its private pages, plus its share of each shared page: what N
nodes of one host sum to) and its private pages (what one more node on the host costs)
are printed beside it.
"""

from __future__ import annotations

import compileall
import gc
import importlib
import math
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path

from bench import progress, report
from dyknow_core import CacheSpec, DyKnowInstance, ManualClock, Policy, RawSample, Sample

N = 1_000_000
BATCH = 1000
PERIOD_NS = 1_000_000  # 1 kHz valid and available time
DELAY_NS = 2_000_000  # available 2 ms after valid
MAX_AGE_S = 10.0
CHECKPOINTS = (10_000, 100_000, 250_000, 500_000, 1_000_000)
MB = 1024 * 1024
NODE_REPEAT = 3  # spawns of each, alternating; the medians are reported
NODE_IDLE_S = 1.0  # how long a ready node idles before its RSS is read
NODE_TIMEOUT = 60.0  # s for a spawned node to say it is ready (a loaded 2-core machine)

# The peer node: a session, a queryable and a token, then "ready" (the settings of ours).
_BARE_NODE = """
import sys, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"peer"')
c.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
q = s.declare_queryable("bench/bare/ready", lambda query: query.reply(query.key_expr, b"1"))
t = s.liveliness().declare_token("bench/bare/alive")
print("ready", flush=True)
sys.stdin.read()
"""


# The bare node after the third-party packages ``dyknow node`` imports (asyncio imports
# ssl; pydantic's first model imports importlib.metadata for its plugins).
_DEPS_NODE = (
    """
import asyncio, msgpack, orjson, pydantic, uvloop
import nacl.bindings, nacl.signing
class M(pydantic.BaseModel):
    x: int = 0
M(x=1)
"""
    + _BARE_NODE
)


# What ``dyknow node`` imports before it starts anything, then "ready" (its config missing,
# the node's path exits 2 once it has imported all it runs).
_IMPORTS_ONLY = """
import sys
from federation.cli import main
main(["node", "-c", "no-such-config.toml"])
print("ready", flush=True)
sys.stdin.read()
"""


def batches(n: int = N) -> Iterator[list[Sample]]:
    """The stream, made batch by batch so the input itself is never all in memory."""
    for start in range(0, n, BATCH):
        yield [
            Sample(20.0 + 5.0 * math.sin(i / 500.0), i * PERIOD_NS, i * PERIOD_NS + DELAY_NS)
            for i in range(start, min(start + BATCH, n))
        ]


def measure(
    push: Callable[[list[Sample]], None], size: Callable[[], int], name: str
) -> tuple[float, list[tuple[int, float, int]]]:
    """Push every batch; return the peak MB above baseline and (pushed, MB, held) checkpoints."""
    gc.collect()
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    points: list[tuple[int, float, int]] = []
    pushed = 0
    for batch in batches():
        push(batch)
        pushed += len(batch)
        if pushed in CHECKPOINTS:
            current = (tracemalloc.get_traced_memory()[0] - base) / MB
            points.append((pushed, current, size()))
            progress(f"{name}: {pushed:,} pushed, {current:.2f} MB, {size():,} held")
    peak = (tracemalloc.get_traced_memory()[1] - base) / MB
    tracemalloc.stop()
    return peak, points


def _node_config(directory: Path) -> Path:
    """A node's TOML config, key pair and trust file in ``directory``: one platform alone."""
    from agents.keys import gen_keys, trust_keys

    pub = gen_keys("node", directory / "keys")[2]
    trust_keys(directory / "trust.json", [pub], federation="bench-node")
    path = directory / "node.toml"
    path.write_text(
        'name = "node"\nfederation = "bench-node"\n'
        f'key = "{directory / "keys" / "node.key"}"\ntrust = "{directory / "trust.json"}"\n'
        '[vocabulary]\nname = "bench"\n[vocabulary.labels]\nspeed = "a speed"\n'
        '[mapping.labels]\nspeed = "bench/speed"\n'
        '[transport]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:0"]\n'
    )
    return path


_PACKAGES = ("dyknow_core", "ontology", "agents", "federation")


def _installed(directory: Path) -> dict[str, str]:
    """Our packages copied to ``directory`` with their bytecode; the environment to run them.

    Run them with ``directory`` as the working directory: ``python -m`` and ``-c`` put the
    working directory first on the path, and the source tree would be found before the copy.
    """
    for name in _PACKAGES:
        source = Path(importlib.import_module(name).__file__ or "").parent
        target = directory / name
        shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
        compileall.compile_dir(target, quiet=1)
    path = os.pathsep.join(p for p in (str(directory), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path}


# What holds a process's RSS: its anonymous memory (with the brk heap), the pages it touched
# of each large shared library (the first whose pattern is in the mapping's path), the rest.
RSS_ANONYMOUS = "anonymous: Python's objects, native heaps"
RSS_LIBRARIES = (
    ("zenoh's library", ("/zenoh/",)),
    ("the interpreter (libpython)", ("/libpython",)),
    ("OpenSSL (asyncio's and uvloop's ssl)", ("/libcrypto.", "/libssl.", "/_ssl.", "/_hashlib.")),
    ("pydantic-core's library", ("/_pydantic_core.",)),
    ("uvloop's library", ("/uvloop/",)),
)
RSS_OTHER = "other libraries, stacks"
RSS_PARTS = (RSS_ANONYMOUS, *(name for name, _ in RSS_LIBRARIES), RSS_OTHER)


def _part_of(path: str) -> str:
    """The `RSS_PARTS` name a mapping named ``path`` in smaps ("" if anonymous) counts in."""
    if path in ("", "[heap]"):
        return RSS_ANONYMOUS
    return next((n for n, patterns in RSS_LIBRARIES if any(p in path for p in patterns)), RSS_OTHER)


def rss_parts(pid: int) -> dict[str, float]:
    """The RSS of process ``pid`` in MB by `RSS_PARTS`, read from ``/proc/<pid>/smaps``."""
    parts = dict.fromkeys(RSS_PARTS, 0.0)
    part = RSS_OTHER
    with open(f"/proc/{pid}/smaps") as f:
        for line in f:
            head = line.split(maxsplit=5)
            if "-" in head[0] and len(head) >= 5:  # a mapping's first line: its range, perms…
                part = _part_of(head[5].strip() if len(head) > 5 else "")
            elif head[0] == "Rss:":
                parts[part] += int(head[1]) / 1024
    return parts


def pss_private(pid: int) -> tuple[float, float]:
    """The PSS and the private memory (MB) of process ``pid``, from ``/proc/<pid>/smaps_rollup``.

    PSS counts a page shared by n processes as 1/n of it; private is what the process
    alone maps (clean or dirty), what it would give back on exit.
    """
    kb: dict[str, int] = {}
    with open(f"/proc/{pid}/smaps_rollup") as f:
        for line in f:
            words = line.split()
            if len(words) >= 2 and words[1].isdigit():
                kb[words[0]] = int(words[1])
    return kb["Pss:"] / 1024, (kb["Private_Clean:"] + kb["Private_Dirty:"]) / 1024


def _spawn_ready(
    argv: list[str], env: dict[str, str] | None = None, cwd: Path | None = None
) -> tuple[float, float, dict[str, float], tuple[float, float]]:
    """Spawn ``argv``; seconds until it prints a line with "ready", its RSS (MB) idle, by part,
    and its PSS and private memory (MB, `pss_private`)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        argv,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"},
        cwd=cwd,
    )
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + NODE_TIMEOUT
        while "ready" not in (line := proc.stdout.readline()):
            if not line or time.monotonic() > deadline:
                raise AssertionError(f"{argv[-3:]} did not say it is ready (exit {proc.poll()})")
        ready = time.perf_counter() - t0
        time.sleep(NODE_IDLE_S)
        with open(f"/proc/{proc.pid}/status") as f:
            rss = next(int(x.split()[1]) / 1024 for x in f if x.startswith("VmRSS:"))
        return ready, rss, rss_parts(proc.pid), pss_private(proc.pid)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# a spawned process's start → ready (s), idle RSS (MB), RSS by part, (PSS, private) (MB)
_Spawned = tuple[float, float, dict[str, float], tuple[float, float]]


def node_ready() -> None:
    """``dyknow node`` start → ready and idle RSS, beside a bare zenoh node; the BENCH lines."""
    ours: list[_Spawned] = []
    bare: list[_Spawned] = []
    imports: list[_Spawned] = []
    deps: list[_Spawned] = []
    with tempfile.TemporaryDirectory(prefix="bench-node-") as tmp:
        config = _node_config(Path(tmp))
        site = Path(tmp) / "site"
        env = _installed(site)
        for i in range(NODE_REPEAT):
            progress(f"node start-to-ready, spawn {i + 1}/{NODE_REPEAT}: bare zenoh, then ours")
            bare.append(_spawn_ready([sys.executable, "-c", _BARE_NODE]))
            ours.append(
                _spawn_ready(
                    [sys.executable, "-m", "federation.cli", "node", "-c", str(config)], env, site
                )
            )
            imports.append(_spawn_ready([sys.executable, "-c", _IMPORTS_ONLY], env, site))
            deps.append(_spawn_ready([sys.executable, "-c", _DEPS_NODE]))
    print(f"node start to ready ({NODE_REPEAT} spawns each, s) and idle RSS (MB):")
    for (r, m, *_), (br, bm, *_), (ir, im, *_), (_, dm, *_) in zip(
        ours, bare, imports, deps, strict=True
    ):
        print(
            f"  dyknow node {r:.3f} s {m:.1f} MB (its imports alone {ir:.3f} s {im:.1f} MB); "
            f"bare zenoh node {br:.3f} s {bm:.1f} MB, {dm:.1f} MB with our dependencies"
        )
    columns = (ours, imports, deps, bare)
    print(
        "idle RSS by part (MB, medians): dyknow node | its imports alone | "
        "bare zenoh node with our dependencies | bare zenoh node"
    )
    for name in RSS_PARTS:
        cells = (statistics.median(p[name] for _, _, p, _ in runs) for runs in columns)
        print(f"  {name:<44}" + "".join(f"{c:8.1f}" for c in cells))
    totals = (statistics.median(sum(p.values()) for _, _, p, _ in runs) for runs in columns)
    print(f"  {'total':<44}" + "".join(f"{c:8.1f}" for c in totals))
    # the shared pages' share depends on the host's other processes; the private pages do not
    shared = ("PSS (shared pages split among their users)", "private (its own pages)")
    for i, name in enumerate(shared):
        cells = (statistics.median(shares[i] for *_, shares in runs) for runs in columns)
        print(f"  {name:<44}" + "".join(f"{c:8.1f}" for c in cells))
    report(
        "federation-node-ready",
        statistics.median(r for r, *_ in ours),
        "zenoh-bare",
        statistics.median(r for r, *_ in bare),
        "s",
        better="lower",
    )
    report(
        "federation-node-rss",
        statistics.median(m for _, m, *_ in ours),
        "zenoh-bare",
        statistics.median(m for _, m, *_ in bare),
        "MB",
        better="lower",
    )


def run() -> None:
    """The cache's memory against the deque reference, then the node's start and RSS."""
    cache_memory()
    node_ready()


def cache_memory() -> None:
    """Measure ours and the deque reference, print the checkpoints and the BENCH line."""
    clock = ManualClock()
    dk = DyKnowInstance(clock=clock)
    src = dk.add_source("bench/speed", cache=CacheSpec(max_samples=None, max_age=MAX_AGE_S))
    received = 0

    def count(batch: list[RawSample]) -> None:
        nonlocal received
        received += len(batch)

    dk.subscribe("bench/speed", Policy(), callback=count)

    def push_ours(batch: list[Sample]) -> None:
        clock.set(batch[-1][2])  # the platform's now follows the data, as it would live
        src.push_batch(batch)

    def cached() -> int:
        return int(dk.metrics("bench/speed")["cached"])

    ours, ours_points = measure(push_ours, cached, "ours")
    if received != N:
        raise AssertionError(f"the subscriber got {received:,} samples of {N:,}")

    window: deque[Sample] = deque(maxlen=round(MAX_AGE_S * 1e9 / PERIOD_NS))
    ref, ref_points = measure(window.extend, lambda: len(window), "deque")

    print(
        f"{N:,} samples at 1 kHz through a stream cached as the last {MAX_AGE_S:g} s "
        f"(tracemalloc, MB above the baseline before the first push):"
    )
    print(f"  {'pushed':>10}  {'ours MB':>8}  {'cached':>7}  {'deque MB':>8}  {'held':>7}")
    for (n, mb, held), (_, ref_mb, ref_held) in zip(ours_points, ref_points, strict=True):
        print(f"  {n:>10,}  {mb:>8.2f}  {held:>7,}  {ref_mb:>8.2f}  {ref_held:>7,}")
    # bounded: what is held once the window is full must not grow with what went through
    settled, final = ours_points[1][1], ours_points[-1][1]
    bounded = final <= 1.25 * settled + 0.5
    per_sample = ref_points[-1][1] * MB / max(ref_points[-1][2], 1)
    print(
        f"  peak ours {ours:.2f} MB, deque {ref:.2f} MB; keeping all {N:,} samples would take "
        f"~{per_sample * N / MB:.0f} MB; process max RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"
    )
    print(f"  bounded: {'yes' if bounded else 'NO'} ({settled:.2f} MB at 100k, {final:.2f} at 1M)")
    report("cache-memory", ours, "deque-10s", ref, "MB", better="lower")
    if not bounded:
        raise AssertionError("the 10 s cache kept growing with the stream: it is not bounded")
