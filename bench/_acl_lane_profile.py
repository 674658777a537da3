"""cProfile of the replier's lane (zenoh's thread): ``python -m bench._acl_lane_profile [N]``.

The round trip of ``bench.acl`` (``request`` from ``asker@bench-a`` to the gateway of a
spawned ``bench-b``), N times once it first answered; in the node, every call of the
Interface Agent's ``take`` (its lane: the request opened, checked, answered, sealed and
put, on zenoh's thread) runs under one ``cProfile.Profile``, which ``bench.acl --profile``
cannot see (it profiles the loop thread). Prints the profile's costliest functions, by
own time and by cumulative time, with their calls. The replier's instructions per round
trip: ``python -m bench._acl_cg --side replier``.
"""

from __future__ import annotations

import asyncio
import cProfile
import os
import pstats
import sys
import tempfile
from pathlib import Path
from typing import Any

N = 2000


def lane_node_main(*args: Any) -> None:
    """The node of ``bench.acl`` with its lane's calls profiled, dumped to a file once stopped."""
    import threading

    from agents import InterfaceAgent
    from bench._acl_node import node_main

    prof = cProfile.Profile()
    take = InterfaceAgent._lane_take
    loop_thread = threading.main_thread().ident

    def profiled(self: Any, payload: bytes) -> Any:
        if threading.get_ident() == loop_thread or not PROFILING[0]:
            return take(self, payload)
        return prof.runcall(take, self, payload)

    InterfaceAgent._lane_take = profiled  # type: ignore[method-assign]
    reports, path = args[-2], args[2] + "/lane.prof"
    node_main(*args)
    prof.dump_stats(path)
    reports.put(("lane", os.getpid(), path))


PROFILING = [True]


async def _measure(keydir: Path, n: int) -> str:
    from bench import acl
    from bench._child import Child

    async with acl.asker_side(keydir) as asking:
        _, _, asker, presence, config = asking
        args = ("zenoh", config, str(keydir), acl.THERE, acl.FEDERATION)
        child = Child(lane_node_main, args, "acl-lane-profile").start()
        try:
            await acl.wait_alive(presence, child, True)
            await acl.first_reply(asker, child)
            await acl.round_trips(asker, n, "profiled")
            child.stop.set()
            path: str = await asyncio.to_thread(child.wait_report, "lane", 30.0)
        finally:
            await asyncio.to_thread(child.close)
    return path


def main(argv: list[str]) -> None:
    """Run, then print the lane's profile per round trip."""
    from agents import run
    from bench import acl

    n = int(argv[0]) if argv else N
    with tempfile.TemporaryDirectory() as tmp:
        keydir = Path(tmp)
        acl.make_keys(keydir)
        path = run(_measure(keydir, n))
        st = pstats.Stats(path)
        st.sort_stats("tottime").print_stats(40)
        st.sort_stats("cumulative").print_stats(30)


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
