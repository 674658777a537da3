"""Raw zenoh between two OS processes: the transport's ceiling, measured beside ours.

Module-level functions only: they run in processes started with the ``spawn`` method
(forking after a zenoh session is open hangs the child).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import socket
import statistics
import sys
import threading
import time
from typing import Any


def free_port() -> int:
    """A free TCP port on the loopback interface."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(listen: list[str], connect: list[str]) -> Any:
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    c.insert_json5("scouting/multicast/enabled", "false")
    return c


def _responder(port: int, ready: Any, stop: Any) -> None:
    """Echo pings as pongs, answer gets, count one-way messages; until told to stop."""
    import zenoh

    with zenoh.open(_config([f"tcp/127.0.0.1:{port}"], [])) as s:
        pong = s.declare_publisher("raw/pong")
        counter = {"n": 0, "t0": 0.0, "t1": 0.0}

        def on_ping(sample: Any) -> None:
            pong.put(sample.payload)

        def on_flood(sample: Any) -> None:
            if counter["n"] == 0:
                counter["t0"] = time.perf_counter()
            counter["n"] += 1
            counter["t1"] = time.perf_counter()

        def on_count(query: Any) -> None:
            query.reply(query.key_expr, json.dumps(counter).encode())

        subs: list[zenoh.Subscriber[None] | zenoh.Queryable[None]] = [
            s.declare_subscriber("raw/ping", on_ping),
            s.declare_subscriber("raw/flood", on_flood),
            s.declare_queryable("raw/get", lambda q: q.reply(q.key_expr, b"x")),
            s.declare_queryable("raw/count", on_count),
        ]
        ready.set()
        stop.wait(120)
        for x in subs:
            x.undeclare()


def measure(round_trips: int = 2000, flood: int = 200_000, payload: int = 362) -> dict[str, float]:
    """Ping-pong and get round trips (ms) and one-way msgs/s between two processes."""
    import zenoh

    ctx = mp.get_context("spawn")
    port = free_port()
    ready, stop = ctx.Event(), ctx.Event()
    proc = ctx.Process(target=_responder, args=(port, ready, stop), daemon=True)
    proc.start()
    try:
        if not ready.wait(20):
            raise RuntimeError("raw zenoh responder did not start")
        with zenoh.open(_config([], [f"tcp/127.0.0.1:{port}"])) as s:
            got = threading.Event()
            sub = s.declare_subscriber("raw/pong", lambda _s: got.set())
            ping = s.declare_publisher("raw/ping")
            body = b"x" * payload
            time.sleep(0.3)  # let the peers' declarations propagate before timing
            rtts = []
            for _ in range(round_trips):
                got.clear()
                t = time.perf_counter()
                ping.put(body)
                if not got.wait(2):
                    raise RuntimeError("raw ping lost")
                rtts.append((time.perf_counter() - t) * 1e3)
            gets = []
            for _ in range(round_trips):
                t = time.perf_counter()
                replies = list(s.get("raw/get", timeout=2.0))
                if not replies:
                    raise RuntimeError("raw get unanswered")
                gets.append((time.perf_counter() - t) * 1e3)
            pub = s.declare_publisher("raw/flood")
            for _ in range(flood):
                pub.put(body)
            deadline = time.time() + 10
            counted: dict[str, float] = {}
            while time.time() < deadline:
                r = list(s.get("raw/count", timeout=2.0))
                ok = r[0].ok
                if ok is None:
                    raise RuntimeError(f"raw count query failed: {r[0].err}")
                counted = json.loads(ok.payload.to_bytes())
                if counted["n"] >= flood * 0.99:
                    break
                time.sleep(0.05)
            sub.undeclare()
        rate = counted["n"] / max(counted["t1"] - counted["t0"], 1e-9)
        return {
            "ping_median": statistics.median(rtts),
            "ping_p99": _q(rtts, 0.99),
            "get_median": statistics.median(gets),
            "get_p99": _q(gets, 0.99),
            "oneway_rate": rate,
            "oneway_received": counted["n"],
        }
    finally:
        stop.set()
        proc.join(10)
        if proc.is_alive():
            proc.kill()
            proc.join(5)


def _q(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        print(measure())
