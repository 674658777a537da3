"""``transport.ask`` with its reply callback on a thread of its own or on zenoh's.

``python -m bench._ask_threads [--rounds R] [--block B] [--loaded L] [--switch S] [--only
direct|indirect]`` (R, B, L whole numbers from 1; S seconds above 0). zenoh-python runs a
``zenoh.handlers.Callback`` in a Python thread of its own unless ``indirect=False``, so
each ``ZenohTransport.ask`` starts and ends a thread; with ``indirect=False`` the callback
runs on zenoh's network thread, which must then take the GIL (``tokens`` keeps a thread
each: agents/transports/_zenoh.py). Two spawned processes, an asker and a replier (our
`ZenohTransport` each, peer mode, loopback TCP, a 1 s link lease so that a stalled link
shows as a lease expiry within the run). The replier answers ``ask`` through its event
loop (our ``serve``) and raw ``get`` on zenoh's thread; on demand it floods puts of an ACL
message's size.

Quiet, in alternating blocks of ``B`` round trips: raw zenoh ``get`` (blocking, zenoh's
default handler, as ``bench/_zenoh_raw.py``), ``ask`` with ``indirect=True`` (zenoh's
default) and ``ask`` with ``indirect=False``; per variant the round trip (median, p99, µs)
and the asker's CPU per round trip (the whole process's, every thread's, ended ones
included: ``time.process_time``; and the loop thread's, ``time.thread_time``).

Loaded: the asker's loop thread busy (a task spinning pure Python for 20 ms between
yields), a pure-Python thread competing for the GIL, the replier flooding puts that the
asker subscribes to (its callback thread takes the GIL for each), and 4 asks in flight;
the variants alternate in blocks of ``L`` asks. Per variant: round trips (median, p99,
max), asks that got no reply, flood samples received per second; over the whole run,
how often the replier's liveliness token was seen gone (a lease expiry), the links now.
``--switch S`` sets ``sys.setswitchinterval`` in the asker (default: Python's, 5 ms);
``--only`` runs the loaded phase alone, with one of the two (a lease expiry is then that
one's: the link is fresh).
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import statistics
import sys
import threading
import time
from typing import Any

from bench import progress, report
from bench._zenoh_raw import free_port

_LEASE_MS = 1000
_FLOOD_BODY = 600  # about a sealed ACL request's size
_TIMEOUT = 2.0


def _overrides() -> dict[str, Any]:
    return {"transport/link/tx/lease": _LEASE_MS}


def _replier(port: int, ready: Any, commands: Any, reports: Any) -> None:
    """Answer asks through the loop and raw gets on zenoh's thread; flood when told."""
    asyncio.run(_replier_main(port, ready, commands, reports))


async def _replier_main(port: int, ready: Any, commands: Any, reports: Any) -> None:
    from agents.transports._zenoh import ZenohTransport

    t = ZenohTransport({"listen": [f"tcp/127.0.0.1:{port}"], "overrides": _overrides()})
    await t.__aenter__()
    loop = asyncio.get_running_loop()

    async def echo(key: str, body: bytes) -> bytes:
        return body

    await t.serve("askb/q", echo)
    raw = t.session.declare_queryable("askb/raw", lambda q: q.reply(q.key_expr, b"x"))
    await t.declare_token("askb/alive/replier")
    flooding = asyncio.Event()
    sent = 0

    async def flood() -> None:
        nonlocal sent
        body = b"f" * _FLOOD_BODY
        while True:
            await flooding.wait()
            for _ in range(64):
                await t.publish("askb/flood", body)
            sent += 64
            await asyncio.sleep(0.01)  # ~6 k puts/s at most: a flood the asker keeps up with

    flooder = loop.create_task(flood())
    ready.put(True)
    while (cmd := await loop.run_in_executor(None, commands.get)) is not None:
        if cmd == "flood-on":
            flooding.set()
        elif cmd == "flood-off":
            flooding.clear()
            reports.put(sent)
    flooder.cancel()
    raw.undeclare()
    await t.aclose()


def _spin(seconds: float) -> int:
    """Pure Python work for ``seconds`` of wall time (holds the GIL but for switches)."""
    end = time.perf_counter() + seconds
    n = 0
    while time.perf_counter() < end:
        for i in range(200):
            n += i * i
    return n


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


async def _main(rounds: int, block: int, loaded: int, only: str | None) -> None:
    import agents.transports._zenoh as zt

    ctx = mp.get_context("spawn")
    port = free_port()
    ready, commands, reports = ctx.Queue(), ctx.Queue(), ctx.Queue()
    child = ctx.Process(target=_replier, args=(port, ready, commands, reports))
    child.start()
    t = None
    try:
        ready.get(timeout=60)
        t = zt.ZenohTransport(
            {"listen": [], "connect": [f"tcp/127.0.0.1:{port}"], "overrides": _overrides()}
        )
        await t.__aenter__()
        session = t.session
        gone = 0

        async def watch() -> None:
            nonlocal gone
            async for p in await t.watch_presence("askb/alive/**"):
                gone += not p.alive

        watcher = asyncio.get_running_loop().create_task(watch())

        async def ask(indirect: bool) -> int:
            zt._REPLIES_INDIRECT = indirect
            n = 0
            async with await t.ask("askb/q", b"r" * 400, timeout=_TIMEOUT) as replies:
                async for _ in replies:
                    n += 1
            return n

        def get() -> int:
            return sum(1 for _ in session.get("askb/raw", payload=b"r" * 400, timeout=_TIMEOUT))

        deadline = time.monotonic() + 30
        while await ask(True) == 0 or get() == 0:
            if time.monotonic() > deadline:
                raise RuntimeError("the replier never answered")
            await asyncio.sleep(0.05)
        if only is None:
            await _quiet(rounds, block, ask, get)

        # Loaded: the loop busy, a thread competing for the GIL, a flood, asks in flight.
        received = 0
        sub = await t.subscribe("askb/flood")

        async def drain() -> None:
            nonlocal received
            async for _ in sub:
                received += 1

        busy = True

        async def hog_loop() -> None:
            while busy:
                _spin(0.02)
                await asyncio.sleep(0)

        def hog_thread() -> None:
            while busy:
                _spin(0.05)

        loop = asyncio.get_running_loop()
        tasks = [loop.create_task(drain()), loop.create_task(hog_loop())]
        hog = threading.Thread(target=hog_thread, daemon=True)
        hog.start()
        commands.put("flood-on")
        lwall: dict[str, list[float]] = {
            v: [] for v in ("ask-indirect", "ask-direct") if only in (None, v)
        }
        llost = {v: 0 for v in lwall}
        rate: dict[str, list[float]] = {v: [] for v in lwall}
        progress(f"loaded: {rounds} rounds of {loaded} asks a variant, 4 in flight")

        async def timed_ask(name: str, flag: bool) -> None:
            t0 = time.perf_counter()
            n = await ask(flag)
            lwall[name].append(time.perf_counter() - t0)
            llost[name] += n == 0

        for r in range(rounds):
            for name in lwall if r % 2 == 0 else reversed(list(lwall)):
                flag = name == "ask-indirect"
                r0, w0 = received, time.perf_counter()
                for _ in range(max(1, loaded // 4)):
                    await asyncio.gather(*(timed_ask(name, flag) for _ in range(4)))
                rate[name].append((received - r0) / (time.perf_counter() - w0))
        busy = False
        commands.put("flood-off")
        sent = reports.get(timeout=30)
        hog.join()
        for task in tasks:
            task.cancel()
        links = len(list(session.info.peers_zid()))
        print(f"loaded (switch interval {sys.getswitchinterval() * 1e3:g} ms), µs")
        print(f"{'variant':14} {'median':>8} {'p99':>8} {'max':>8} {'flood/s':>8} lost")
        for name in lwall:
            print(
                f"{name:14} {statistics.median(lwall[name]) * 1e6:8.0f} "
                f"{_pct(lwall[name], 0.99) * 1e6:8.0f} {max(lwall[name]) * 1e6:8.0f} "
                f"{statistics.median(rate[name]):8.0f} {llost[name]}"
            )
        print(
            f"flood: {sent} sent, {received} received; replier seen gone {gone} times; "
            f"links now {links}"
        )
        if only is None:
            report(
                "ask-loaded-direct-vs-indirect",
                statistics.median(lwall["ask-direct"]),
                "indirect",
                statistics.median(lwall["ask-indirect"]),
                "s",
                better="lower",
            )
        watcher.cancel()
    finally:
        commands.put(None)
        if t is not None:
            await t.aclose()
        child.join(30)
        if child.is_alive():
            child.kill()
            child.join()


async def _quiet(rounds: int, block: int, ask: Any, get: Any) -> None:
    """Raw get and both ways of ``ask`` in alternating blocks, the machine as it is."""
    variants: dict[str, Any] = {"get": None, "ask-indirect": True, "ask-direct": False}
    wall: dict[str, list[float]] = {v: [] for v in variants}
    cpu: dict[str, list[float]] = {v: [] for v in variants}
    loop_cpu: dict[str, list[float]] = {v: [] for v in variants}
    lost = {v: 0 for v in variants}
    progress(f"quiet: {rounds} rounds of {block} round trips a variant")
    for r in range(rounds):
        order = list(variants) if r % 2 == 0 else list(reversed(variants))
        for name in order:
            flag = variants[name]
            c0, l0 = time.process_time(), time.thread_time()
            for _ in range(block):
                t0 = time.perf_counter()
                n = get() if flag is None else await ask(flag)
                wall[name].append(time.perf_counter() - t0)
                lost[name] += n == 0
            cpu[name].append((time.process_time() - c0) / block)
            loop_cpu[name].append((time.thread_time() - l0) / block)
    print(f"quiet, {rounds}x{block} round trips each (µs; CPU: median of blocks)")
    print(f"{'variant':14} {'median':>8} {'p99':>8} {'proc CPU':>9} {'loop CPU':>9} lost")
    for name in variants:
        print(
            f"{name:14} {statistics.median(wall[name]) * 1e6:8.0f} "
            f"{_pct(wall[name], 0.99) * 1e6:8.0f} "
            f"{statistics.median(cpu[name]) * 1e6:9.0f} "
            f"{statistics.median(loop_cpu[name]) * 1e6:9.0f} {lost[name]}"
        )
    base = statistics.median(wall["get"])
    for name in ("ask-indirect", "ask-direct"):
        report(
            f"ask-{name[4:]}-vs-get",
            statistics.median(wall[name]),
            "zenoh-get",
            base,
            "s",
            better="lower",
        )
    report(
        "ask-direct-cpu-vs-indirect",
        statistics.median(cpu["ask-direct"]),
        "indirect",
        statistics.median(cpu["ask-indirect"]),
        "s",
        better="lower",
    )


def _count(text: str) -> int:
    """A whole number of at least 1 (rounds, asks, round trips)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{n} is less than 1")
    return n


def _interval(text: str) -> float:
    """A switch interval in seconds, above 0 (``sys.setswitchinterval`` refuses 0)."""
    try:
        s = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0 < s < 1e9:  # also refuses nan and inf
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    return s


def main(argv: list[str]) -> None:
    """Run both phases with the options in ``argv`` (a bad option: its error, exit 2)."""
    ap = argparse.ArgumentParser(
        prog="python -m bench._ask_threads", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--rounds", type=_count, default=10, help="rounds of each phase")
    ap.add_argument("--block", type=_count, default=100, help="round trips a quiet block")
    ap.add_argument("--loaded", type=_count, default=40, help="asks a loaded block")
    ap.add_argument("--switch", type=_interval, help="the asker's switch interval, s")
    ap.add_argument(
        "--only", choices=("direct", "indirect"), help="the loaded phase alone, one variant"
    )
    a = ap.parse_args(argv)
    if a.switch is not None:
        sys.setswitchinterval(a.switch)
    asyncio.run(_main(a.rounds, a.block, a.loaded, None if a.only is None else f"ask-{a.only}"))


if __name__ == "__main__":
    main(sys.argv[1:])
