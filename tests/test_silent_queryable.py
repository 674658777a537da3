"""An outsider's queryable that never answers must not hold a one-shot command to its timeouts.

zenoh ends a query once every queryable that heard it answered: a queryable on
``dyknow/<fed>/v1/**`` that keeps its queries unanswered held each query of a one-shot
``dyknow ask`` (the directory snapshot, above all) to its timeout. Each query whose
answerers are known now ends at the last authenticated answer it needs; a junk answer
never ends it. The timeouts are stretched here so that waiting one out cannot pass.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from _node_example import Station, _samples

from agents import AgentPlatform, KeyPair, TrustStore, runs_signed
from federation import PlatformConfig, _cli_net, _local
from federation._cli_net import ask_platform, watch_platform

pytestmark = pytest.mark.timeout(120)

STRETCHED = 10.0  # s: every query timeout the test stretches
BOUND = 5.0  # s: well under it, even on a loaded machine


def _outsider(station: Station) -> tuple[zenoh.Session, list[zenoh.Query], list[Any]]:
    """A plain zenoh peer holding every query on the federation's keys, and answering junk.

    Its junk answers come on the key asked (the directory snapshot's: as the station's).
    """
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{station.port}"]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    held: list[zenoh.Query] = []  # a query ends when dropped: kept, it is never answered
    prefix = f"dyknow/{station.federation}/v1"

    def junk(query: zenoh.Query) -> None:
        key = str(query.key_expr)
        if "*" in key:  # the directory snapshot: as the station's answer
            key = key.rpartition("/")[0] + "/station"
        query.reply(key, b'{"platform": "station", "junk": [')

    entities = [
        session.declare_queryable(f"{prefix}/**", held.append),
        session.declare_queryable(f"{prefix}/df/*", junk),
        session.declare_queryable(f"{prefix}/identity/*", junk),
    ]
    return session, held, entities


def test_a_silent_queryable_does_not_hold_a_one_shot_ask(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    station = Station(tmp_path)
    monkeypatch.setenv("XDG_RUNTIME_DIR", station.env["XDG_RUNTIME_DIR"])
    stretched = AgentPlatform.__init__

    def platform(self: AgentPlatform, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("query_timeout", STRETCHED)
        stretched(self, *args, **kwargs)

    monkeypatch.setattr(AgentPlatform, "__init__", platform)
    monkeypatch.setattr(_local, "_IDENTITY_WAIT", STRETCHED)
    monkeypatch.setattr(_cli_net, "_WATCH_ASK", STRETCHED)
    operator = str(station.dir / "operator.toml")
    session = None
    try:
        station.start("python")
        # the station's samples come paced by the outside world: one before the attack
        station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        session, held, _entities = _outsider(station)
        time.sleep(0.5)  # the outsider's queryables routed

        async def ask() -> tuple[float, Any]:
            start = time.monotonic()
            answer = await ask_platform(
                operator, "station", {"labels": ["temperature"], "action": "get-latest"}, 10, 10
            )
            return time.monotonic() - start, answer

        took, answer = asyncio.run(ask())
        assert held, "the silent queryable heard no query"
        assert took < BOUND, f"the one-shot ask took {took:.2f} s"
        assert 19.0 <= _samples(answer, "temperature")[0][0] <= 21.0

        config = PlatformConfig.load(operator)
        station_config = PlatformConfig.load(station.dir / "station-python.toml")

        async def checks() -> tuple[float, bool, float, str]:
            async with config.make_transport() as transport:
                # as a start's duplicate check does first: once linked, the station seen
                assert await transport.tokens(_local.alive_key(station_config), timeout=5.0)
                start = time.monotonic()
                runs = await runs_signed(
                    transport,
                    KeyPair.load(config.key),
                    TrustStore.load(config.trust),
                    "station",
                    timeout=STRETCHED,
                )
                signed = time.monotonic() - start
                start = time.monotonic()
                error = await _local._alive_error(transport, station_config, None, True)
                return signed, runs, time.monotonic() - start, str(error)

        signed, runs, said, error = asyncio.run(checks())
        assert runs and signed < BOUND, f"the signed directory answer took {signed:.2f} s"
        # the junk identity answer is skipped, the running node's own ends the query
        assert said < BOUND, f"asking where the station runs took {said:.2f} s"
        assert station.node is not None and f"pid {station.node.pid} on host" in error, error

        # the owner's watch: its lease is granted at once, not once the query timed out
        watching: list[float] = []
        start = time.monotonic()

        async def watch() -> None:
            # ended once it watches: only when it began is asked, not what it then shows
            began = asyncio.Event()

            def emit(event: dict[str, Any]) -> None:
                if event.get("kind") == "watching":
                    watching.append(time.monotonic() - start)
                    began.set()

            conf = str(station.dir / "station-python.toml")
            task = asyncio.create_task(watch_platform(conf, emit, duration=3))
            await asyncio.wait(
                [task, asyncio.create_task(began.wait())], return_when=asyncio.FIRST_COMPLETED
            )
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

        asyncio.run(watch())
        assert watching and watching[0] < BOUND, f"the watch began after {watching} s"
    finally:
        if session is not None:
            session.close()
        _, err = station.stop()
    assert "Traceback" not in err
