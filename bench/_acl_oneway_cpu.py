"""The one-way flood's CPU per message, both sides in one thread.

``python -m bench._acl_oneway_cpu [N] [ROUNDS]``: ``bench.acl``'s flood (``N`` informs
of ~362 B from ``asker@bench-a`` to ``sink@bench-b`` through the public API: ``await
asker.send(asker.message(...))`` in a loop), but both platforms in this process over the
in-memory transport, their Interface Agents authenticating and encrypting as over zenoh.
Everything both sides do (build, to_json, batch, seal; open, parse, admit, audit,
deliver, the sink's handler) runs on the one event-loop thread, so its CPU time per
message (``time.thread_time``) is the two loop threads' of the zenoh flood together,
without zenoh's own threads and without the machine's load in it: a figure to compare
two states of the code on a loaded machine. Prints one JSON object per round.

``--sender-only`` (first, or after ``--ab``'s trees and pairs): the sender's part alone.
After a warm-up round of 2000 (the session agreed, the sink's count checked), the receiving
platform's inbox leaves the hub: what the sender publishes then goes nowhere, and a round
is the sender's build, to_json, batch, seal and publish only, its last batch flushed.

``python -m bench._acl_oneway_cpu --ab TREE_A TREE_B [--pairs 5] [N] [ROUNDS]`` runs this
file in a fresh process per run with ``PYTHONPATH`` set to each tree in turn (a tree
without it too), in alternated pairs (A B, B A, A B ...), and prints each tree's medians
and B's over A's.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from pathlib import Path

N = 30_000
ROUNDS = 5
WAIT_S = 60.0  # for the sink to count the round's last message
WARM_UP = 2_000  # messages of a --sender-only run's warm-up round
KEYS = ("us_per_msg",)


async def _rounds(n: int, rounds: int, sender_only: bool = False) -> list[dict[str, float]]:
    """``rounds`` floods of ``n`` informs, each one's loop-thread CPU per message (µs)."""
    from agents import (
        ACLMessage,
        Agent,
        AgentPlatform,
        MemoryHub,
        MessageTemplate,
        Performative,
        on,
    )
    from agents._interface import InterfaceAgent, RateLimit
    from agents._security import KeyPair, SecurityPolicy, TrustStore
    from bench import acl
    from bench._acl_node import FLOOD_ONTOLOGY, Sink

    class CountingSink(Sink):
        """The node's sink, telling when it has counted ``target`` informs."""

        target = 0
        done: asyncio.Event | None = None

        @on(MessageTemplate(Performative.INFORM, ontology=FLOOD_ONTOLOGY))
        async def count(self, message: ACLMessage) -> None:  # the sink's handler, extended
            await super().count(message)
            if self.n >= self.target and self.done is not None:
                self.done.set()

    ka, kb = KeyPair.generate(acl.HERE), KeyPair.generate(acl.THERE)
    trust = TrustStore(acl.FEDERATION, {acl.HERE: ka.public_key, acl.THERE: kb.public_key})
    # one process sends faster than the default limit of one platform's messages
    unlimited = RateLimit(rate=1e6, burst=1e6, total_rate=1e7, total_burst=1e7)
    hub = MemoryHub()

    def channel(k: KeyPair) -> InterfaceAgent:
        # a key exchange with room for a slow run (under valgrind on a loaded machine)
        return InterfaceAgent(
            k,
            trust,
            policy=SecurityPolicy(encrypt=True),
            rate_limit=unlimited,
            handshake_timeout=30.0,
        )

    out: list[dict[str, float]] = []
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        AgentPlatform(acl.HERE, ta, federation=acl.FEDERATION, channel=channel(ka)) as pa,
        AgentPlatform(acl.THERE, tb, federation=acl.FEDERATION, channel=channel(kb)) as pb,
    ):
        sink = await pb.add(CountingSink("sink"))
        asker = await pa.add(Agent("asker"))
        content = acl.flood_content(asker)
        message, send = asker.message, asker.send
        inform = Performative.INFORM
        for r in range(rounds + 1):  # the first warms up
            # sender alone: a warm-up of the same size whatever n (it delivers, the rounds
            # do not), so that two runs' difference is the rounds' alone
            size = WARM_UP if sender_only and not r else n
            sink.reset()
            sink.target, sink.done = size, asyncio.Event()
            t = time.thread_time()
            for i in range(size):
                await send(message(inform, acl.SINK, content(i), ontology=FLOOD_ONTOLOGY))
            if r and sender_only:
                for _ in range(3):  # the turn's last batch, flushed at its end
                    await asyncio.sleep(0)
            else:
                await asyncio.wait_for(sink.done.wait(), WAIT_S)
            used = time.thread_time() - t
            if not r and sender_only:
                # the sink's platform stops hearing: the rounds measure the sender alone
                inbox = pb.key("acl")
                hub.subscribers[:] = [s for s in hub.subscribers if s[0] != inbox]
            if r:
                out.append({"us_per_msg": used / size * 1e6})
    return out


def measure(n: int = N, rounds: int = ROUNDS, sender_only: bool = False) -> list[dict[str, float]]:
    """Each round's figures."""
    from agents import run as run_loop

    result: list[dict[str, float]] = run_loop(_rounds(n, rounds, sender_only))
    return result


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    if argv[:1] == ["--ab"]:
        from bench import ab_main  # the parent's only: a child may run an older tree

        # this file, run against the tree's packages (a tree older than it lacks it)
        ab_main(argv, lambda rest: [sys.executable, __file__, *rest], KEYS)
        return
    sender_only = argv[:1] == ["--sender-only"]
    if sender_only:
        argv = argv[1:]
    n = int(argv[0]) if argv else N
    rounds = int(argv[1]) if len(argv) > 1 else ROUNDS
    for got in measure(n, rounds, sender_only):
        print(json.dumps(got), flush=True)


if __name__ == "__main__":
    # run as a file (by `ab`): its folder, first on the path, would shadow our packages
    here = str(Path(__file__).resolve().parent)
    sys.path[:] = [p for p in sys.path if p != here]
    # not `bench.helped`: a child of `--ab` runs this file against an older tree's bench
    if "-h" in sys.argv or "--help" in sys.argv:
        print((__doc__ or "").strip())
    else:
        main(sys.argv[1:])
