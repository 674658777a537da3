"""osBrain 0.6.5 between two agent processes: the agent peer ``bench.acl`` measures beside ours.

osBrain (ZeroMQ, Pyro4 for its proxies, no security) is the fastest Python agent
framework we know of. Its own API only: a name server, two agents each in its own OS
process (``run_agent``), a REP socket bound by the server agent and connected to by the
client (REQ-REP round trip), a PUSH socket bound by the sender and connected to by the
receiver's PULL handler (one-way throughput); TCP on loopback, as ours (osBrain's
default would be IPC sockets). The loops run inside the agents' own
processes (``execute_as_method``), so no proxy call is on the measured path.

osBrain starts its agents with ``fork``: this runs in a child of its own, started with
``spawn`` by ``bench.acl`` before any zenoh session of that child exists (never fork
once a session is open).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

ANSWER = {"label": "bench/speed", "samples": [[1795000000.0, 13.1]]}
"""What the server answers to every request (about the size of our gateway's inform)."""


def _answer(agent: Any, message: Any) -> Any:
    """The REP handler: the answer, whatever was asked."""
    return ANSWER


def _count(agent: Any, message: Any) -> None:
    """The PULL handler: one more message, and when (one clock for every process)."""
    now = time.monotonic()
    if not agent.n:
        agent.t0 = now
    agent.n += 1
    agent.t1 = now


def _round_trips(agent: Any, n: int, query: dict[str, Any]) -> list[float]:
    """``n`` REQ-REP round trips from inside the client agent, each in ms."""
    out = []
    perf = time.perf_counter
    send, recv = agent.send, agent.recv
    for _ in range(n):
        t = perf()
        send("rpc", query)
        recv("rpc")
        out.append((perf() - t) * 1e3)
    return out


def _push(agent: Any, n: int, pad: str) -> tuple[float, float]:
    """Push ``n`` messages as fast as PUSH takes them; (first send, seconds spent sending)."""
    send = agent.send
    t0 = time.monotonic()
    for i in range(n):
        send("flood", {"seq": i, "speed": 12.5, "pad": pad})
    return t0, time.monotonic() - t0


def _reset(agent: Any) -> None:
    agent.n = 0
    agent.t0 = 0.0
    agent.t1 = 0.0


def osbrain_main(
    n_rtt: int, warmup: int, rounds: int, n_flood: int, pad: str, reports: Any, stop: Any
) -> None:
    """The child: measure round trips and a flood per round, report them, then stop."""
    import traceback

    try:
        reports.put(("result", 0, _measure(n_rtt, warmup, rounds, n_flood, pad)))
    except Exception:
        reports.put(("error", 0, traceback.format_exc()))


def _measure(n_rtt: int, warmup: int, rounds: int, n_flood: int, pad: str) -> dict[str, Any]:
    from osbrain import run_agent, run_nameserver

    query = {"action": "query", "label": "bench/speed", "kind": "latest"}
    ns = run_nameserver()
    try:
        server = run_agent("osb-server")
        client = run_agent("osb-client")
        sink = run_agent("osb-sink")
        source = run_agent("osb-source")
        rpc = server.bind("REP", alias="rpc", handler=_answer, transport="tcp")
        client.connect(rpc, alias="rpc")
        sink.execute_as_method(_reset)
        sink.connect(source.bind("PUSH", alias="flood", transport="tcp"), handler=_count)
        client.execute_as_method(_round_trips, warmup, query)
        res: dict[str, Any] = {"rtt": [], "flood": []}
        for _ in range(rounds):
            ms = client.execute_as_method(_round_trips, n_rtt, query)
            res["rtt"].append(statistics.median(ms))
            res.setdefault("p99", []).append(sorted(ms)[int(0.99 * len(ms))])
            sink.execute_as_method(_reset)
            t0, _sending_s = source.execute_as_method(_push, n_flood, pad)
            deadline = time.monotonic() + 60
            while sink.get_attr("n") < n_flood and time.monotonic() < deadline:
                time.sleep(0.05)
            got = sink.get_attr("n")
            t1 = sink.get_attr("t1")
            res["flood"].append(got / max(t1 - t0, 1e-9))
        return res
    finally:
        ns.shutdown()
