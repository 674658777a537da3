"""What the flood, leave and one-identity tests set up alike: a federation of trusted
keys and its Interface Agents (in memory, or with keys on disk); the station whose node's
local channel a test stands in for.

The processes a flood runs (victim, member, attacker) are bench's (``bench._flood``,
``bench.kxflood``); this is the in-process side.
"""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, NamedTuple

import pytest
from _node_example import Station

from agents import AgentPlatform, InterfaceAgent
from agents._security import KeyPair, TrustStore
from agents.keys import gen_keys, trust_keys
from agents.transports import MemoryHub, free_tcp_port
from federation import PlatformConfig


class Trusted(NamedTuple):
    """A test's federation: its name, its trust, the first platform's port, the key directory."""

    fed: str
    trust: TrustStore
    port: int
    keys: Path

    def channel(self, name: str, **options: Any) -> InterfaceAgent:
        """``name``'s Interface Agent, with its key from the directory (``options`` its own)."""
        return InterfaceAgent(KeyPair.load(self.keys / f"{name}.key"), self.trust, **options)


def trusted(tmp_path: Path, prefix: str, names: list[str]) -> Trusted:
    """Keys for ``names`` in ``tmp_path``, all trusted in a federation of its own (``prefix-…``)."""
    fed = f"{prefix}-{uuid.uuid4().hex[:8]}"
    trust_keys(tmp_path / "trust.json", [gen_keys(n, tmp_path)[2] for n in names], federation=fed)
    return Trusted(fed, TrustStore.load(tmp_path / "trust.json"), free_tcp_port(), tmp_path)


def station_channel(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[PlatformConfig, Path]:
    """The station's config, this process's channels where its node's are; its node's channel."""
    from federation._local import channel_path

    station = Station(tmp_path)
    monkeypatch.setenv("XDG_RUNTIME_DIR", station.env["XDG_RUNTIME_DIR"])
    config = PlatformConfig.load(station.dir / "station-python.toml")
    return config, channel_path(config)


@contextlib.asynccontextmanager
async def members(fed: str, *names: str) -> AsyncIterator[list[AgentPlatform]]:
    """Platforms of federation ``fed`` on one in-memory hub, each trusting all of them."""
    hub = MemoryHub()
    keys = {n: KeyPair.generate(n) for n in names}
    trust = {n: k.public_key for n, k in keys.items()}
    async with contextlib.AsyncExitStack() as stack:
        out = []
        for n in names:
            transport = await stack.enter_async_context(hub.transport())
            channel = InterfaceAgent(keys[n], TrustStore(fed, trust))
            platform = AgentPlatform(n, transport, federation=fed, channel=channel)
            out.append(await stack.enter_async_context(platform))
        yield out
