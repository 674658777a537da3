"""The peers of ``bench.acl``'s node figures and of its MQTT round trip, as child processes.

- ``bare_zenoh_main``: the least a zenoh node can be: an interpreter that opens a
  session, answers ``get`` on one key and declares a liveliness token. Its start-to-ready
  time and idle RSS sit beside our full node's.
- ``mqtt_echo_main``: a raw aiomqtt client echoing ``raw/ping`` to ``raw/pong`` through a
  broker: the MQTT ping-pong our MQTT round trip is compared with.

Only what each needs is imported, inside the function: this module is what the spawned
interpreter imports to find its target, and the bare node must not pay for more.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

_T_MODULE = time.time()


def bare_zenoh_main(listen: str, connect: str, prefix: str, reports: Any, stop: Any) -> None:
    """Open a zenoh session, answer gets on ``<prefix>/ready``, declare a token, idle."""
    import zenoh

    imported = time.time()
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps([listen]))
    c.insert_json5("connect/endpoints", json.dumps([connect]))
    c.insert_json5("scouting/multicast/enabled", "false")
    parent = os.getppid()
    with zenoh.open(c) as s:
        opened = time.time()
        q = s.declare_queryable(f"{prefix}/ready", lambda query: query.reply(query.key_expr, b"1"))
        token = s.liveliness().declare_token(f"{prefix}/alive")
        marks = {"module": _T_MODULE, "imported": imported, "transport": opened}
        marks["ready"] = time.time()
        reports.put(("ready", os.getpid(), {"marks": marks}))
        while not stop.wait(0.1) and os.getppid() == parent:
            pass
        token.undeclare()
        q.undeclare()


def mqtt_echo_main(host: str, port: int, reports: Any, stop: Any) -> None:
    """Echo every ``raw/ping`` to ``raw/pong`` (aiomqtt, MQTT v5, QoS 0) until ``stop``."""
    import asyncio

    import aiomqtt

    async def main() -> None:
        parent = os.getppid()
        async with aiomqtt.Client(
            host, port, identifier=f"raw-echo-{os.getpid()}", protocol=aiomqtt.ProtocolVersion.V5
        ) as client:
            await client.subscribe("raw/ping")
            reports.put(("ready", os.getpid(), {}))

            async def echo() -> None:
                async for m in client.messages:
                    await client.publish("raw/pong", m.payload)

            task = asyncio.create_task(echo())
            # a multiprocessing Event cannot be awaited: poll it (and the parent's life)
            while not stop.is_set() and os.getppid() == parent and not task.done():  # noqa: ASYNC110
                await asyncio.sleep(0.1)
            task.cancel()

    asyncio.run(main())
