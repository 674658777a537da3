"""Feed the zenoh example: put JSON readings on ``weather/station1`` (any zenoh client can).

Run: python examples/node/publish_zenoh.py tcp/127.0.0.1:7450 [COUNT]
"""

from __future__ import annotations

import json
import sys
import time

import zenoh


def main(endpoint: str, count: int) -> None:
    """Connect to the node's endpoint and put ``count`` readings, 0.1 s apart."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        time.sleep(0.5)  # let the subscription reach us
        for n in range(count):
            reading = {"time": time.time(), "temperature": 18.0 + n, "wind": 2.0 + n}
            session.put("weather/station1", json.dumps(reading))
            time.sleep(0.1)
        session.put("weather/station1", b"not json")  # counted as bad, the node goes on


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 10)
