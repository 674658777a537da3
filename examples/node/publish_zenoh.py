"""Feed the zenoh example: put JSON readings on ``weather/station1`` (any zenoh client can).

Run: python examples/node/publish_zenoh.py tcp/127.0.0.1:7450 [COUNT]

COUNT (20) readings 0.1 s apart span over a second: the node's state (every 1 s) is
decided once its inputs pass a whole second, so at least one state is put out.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import zenoh


def main(endpoint: str, count: int) -> None:
    """Connect to the node's endpoint and put ``count`` readings, 0.1 s apart."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        publisher = session.declare_publisher("weather/station1")
        _await_subscriber(publisher, f"weather/station1 at {endpoint}")
        for n in range(count):
            reading = {"time": time.time(), "temperature": 18.0 + n, "wind": 2.0 + n}
            publisher.put(json.dumps(reading))
            time.sleep(0.1)
        publisher.put(b"not json")  # counted as bad, the node goes on


def _await_subscriber(publisher: zenoh.Publisher, what: str, timeout: float = 30.0) -> None:
    """Return once a subscription matches: zenoh drops a put that none routes."""
    matched = threading.Event()

    def status(change: zenoh.MatchingStatus) -> None:
        if change.matching:  # told at once when one matches already
            matched.set()

    with publisher.declare_matching_listener(status):
        if not matched.wait(timeout):
            sys.exit(f"no subscriber of {what} within {timeout:g} s")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 20)
