"""The asker's reply hand-over, on and off in one process: ``python -m bench._acl_replies``.

``bench.acl``'s zenoh round trip (``request`` from ``asker@bench-a`` to the gateway of
``bench-b``, a spawned node; encryption on), in alternating blocks with the asker's
``InterfaceAgent.lane_replies`` on and off (its reply taken on the loop in one callback, or
queued for the inbox's consumer task): both modes meet the same load of a shared machine,
block by block, where two processes run one after the other do not. Prints each mode's
median, p90 and p99 round trip (µs) and the asker's loop-thread CPU per round trip, and on
over off. ``python -m bench._acl_replies [BLOCKS] [PER_BLOCK]`` (default 40 × 100).
"""

from __future__ import annotations

import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

BLOCKS = 40
PER_BLOCK = 100
SETTLE = 20  # round trips after each switch, not timed


async def _measure(keydir: Path, blocks: int, per: int) -> dict[str, Any]:
    from agents import InterfaceAgent, request
    from bench import acl

    async with acl.asker_side(keydir) as asking:
        _, host, asker, presence, config = asking
        interface = host.channel
        assert isinstance(interface, InterfaceAgent)
        child = acl.node("zenoh", config, keydir).start()
        try:
            await acl.wait_alive(presence, child, True)
            await acl.first_reply(asker, child)
            await acl.round_trips(asker, acl.WARMUP, "warm-up")
            acl.settle_gc()
            rtts: dict[bool, list[float]] = {True: [], False: []}
            cpu = {True: 0.0, False: 0.0}
            ns = time.perf_counter_ns

            async def ask() -> None:
                await request(asker, acl.GATEWAY, acl.QUERY, ontology="dyknow", timeout=5.0)

            for block in range(blocks):
                for on in (True, False) if block % 2 == 0 else (False, True):
                    interface.lane_replies = on
                    for _ in range(SETTLE):
                        await ask()
                    c0 = time.thread_time()
                    for _ in range(per):
                        t = ns()
                        await ask()
                        rtts[on].append((ns() - t) / 1e3)
                    cpu[on] += time.thread_time() - c0
            taken = interface.replies_on_thread
        finally:
            await asyncio.to_thread(child.close)
    out: dict[str, Any] = {}
    for on, xs in rtts.items():
        xs.sort()
        out["on" if on else "off"] = {
            "median": round(statistics.median(xs), 1),
            "p90": round(xs[int(0.9 * (len(xs) - 1))], 1),
            "p99": round(xs[int(0.99 * (len(xs) - 1))], 1),
            "loop_cpu": round(cpu[on] / len(xs) * 1e6, 1),
        }
    out["on/off"] = {k: round(out["on"][k] / out["off"][k], 3) for k in out["on"]}
    out["replies_on_thread"] = taken
    return out


def main(argv: list[str]) -> None:
    """Run the blocks (see the module's docstring) and print the figures as JSON."""
    from agents import run as run_loop
    from bench import acl

    blocks = int(argv[0]) if argv else BLOCKS
    per = int(argv[1]) if len(argv) > 1 else PER_BLOCK
    with tempfile.TemporaryDirectory() as tmp:
        keydir = Path(tmp)
        acl.make_keys(keydir)
        res = run_loop(_measure(keydir, blocks, per))
    print(json.dumps(res))


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
