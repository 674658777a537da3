"""A peer restarted in a new process: no request to it is lost, over zenoh, real processes.

uav-b runs in a spawned process; the platform in the test, uav-a, starts after it, so its
presence watch never reports uav-b's token (the tokens alive at its start are not), nor
that token's end when the process is killed. uav-a's session with the killed process
stays; the new process's token is its first sight of uav-b. The request uav-a sends then
must reach the new process on a session it holds: sealed on the old one, the new process
could not open it (refused as unknown-session, then a re-handshake) and its sender would
wait out its timeout.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import signal
import uuid
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import pytest
from _echo import ProtectedEcho

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    InterfaceAgent,
    KeyPair,
    TrustStore,
    on_request,
    request,
    wire_key,
)
from agents.keys import gen_keys, trust_keys
from agents.transports import Presence, Subscription, ZenohConfig, ZenohTransport, free_tcp_port

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

START = 20.0  # a spawned interpreter imports zenoh and pydantic: seconds when loaded
ASKER, ECHO = "uav-a", "uav-b"


class Echo(ProtectedEcho):
    """Answers with what it was asked, its process and what its Interface Agent refused."""

    @on_request("demo")
    async def _echo(self, message: ACLMessage) -> Any:
        """The content, the process id and how many envelopes did not open here."""
        stats = self.platform.stats
        return {
            "echo": message.content,
            "pid": os.getpid(),
            "unauthenticated": stats.unauthenticated,
            "rehandshakes": stats.rehandshakes,
        }


class NoLeaves(Subscription[Presence]):
    """A presence watch that reports tokens appearing, never going (those events lost)."""

    def __init__(self, inner: Subscription[Presence]) -> None:
        self.inner = inner

    def __aiter__(self) -> NoLeaves:
        return self

    async def __anext__(self) -> Presence:
        while True:
            change = await self.inner.__anext__()
            if change.alive:
                return change

    def close(self) -> None:
        """Close the watch it filters."""
        self.inner.close()


class LeavesLost(ZenohTransport):
    """uav-a's zenoh, deaf to tokens going: the killed process's end is never reported."""

    async def watch_presence(
        self, key_expr: str, *, history: bool = True, buffer_size: int = 4096
    ) -> Subscription[Presence]:
        """The watch, without its leaves."""
        return NoLeaves(await super().watch_presence(key_expr, history=history))


def echo_main(config: dict[str, Any], federation: str, keys: str, trust: str, ready: Any) -> None:
    """uav-b's process: the echo agent, until it is killed; says "ready" once it serves."""
    asyncio.run(_echo_platform(config, federation, Path(keys), Path(trust), ready))


async def _echo_platform(
    config: dict[str, Any], federation: str, keys: Path, trust: Path, ready: Connection
) -> None:
    channel = InterfaceAgent(KeyPair.load(keys / f"{ECHO}.key"), TrustStore.load(trust))
    transport = ZenohTransport(ZenohConfig.model_validate(config))
    async with (
        transport,
        AgentPlatform(ECHO, transport, federation=federation, channel=channel) as platform,
    ):
        await platform.add(Echo())
        ready.send("ready")
        await asyncio.Event().wait()  # until killed


def _start(config: ZenohConfig, federation: str, keys: Path, trust: Path) -> BaseProcess:
    """uav-b in a new process, returned once it serves (bounded by START)."""
    ctx = multiprocessing.get_context("spawn")
    theirs, ours = ctx.Pipe(duplex=False)
    proc = ctx.Process(
        target=echo_main,
        args=(config.model_dump(), federation, str(keys), str(trust), ours),
        name="uav-b",
    )
    proc.start()
    ours.close()
    if not theirs.poll(START):
        proc.kill()
        raise AssertionError(f"uav-b did not start within {START} s (exit code {proc.exitcode})")
    assert theirs.recv() == "ready"
    return proc


async def _until(cond: Callable[[], bool], what: str, timeout: float = START) -> None:
    """Poll ``cond`` (in memory) until it holds; fail after ``timeout`` s."""
    try:
        async with asyncio.timeout(timeout):
            while not cond():  # noqa: ASYNC110 (the presence watch has no event to await)
                await asyncio.sleep(0.01)
    except TimeoutError:
        raise AssertionError(f"timed out waiting for {what}") from None


@pytest.mark.timeout(120)
async def test_a_request_to_a_restarted_peer_whose_token_was_never_seen_is_not_lost(
    tmp_path: Path,
) -> None:
    federation = f"restart-{uuid.uuid4().hex[:8]}"
    keys, trust = tmp_path / "keys", tmp_path / "trust.json"
    trust_keys(trust, [gen_keys(name, keys)[2] for name in (ASKER, ECHO)], federation=federation)
    port_a, port_b1 = free_tcp_port(), free_tcp_port()
    procs: list[BaseProcess] = []
    try:
        # the first process of uav-b runs before uav-a exists
        first = await asyncio.to_thread(
            _start, ZenohConfig.loopback(port_b1), federation, keys, trust
        )
        procs.append(first)
        channel = InterfaceAgent(KeyPair.load(keys / f"{ASKER}.key"), TrustStore.load(trust))
        transport = LeavesLost(ZenohConfig.loopback(port_a, connect=[port_b1]))
        async with transport:
            # connected, and uav-b's token known, before uav-a's platform watches presence
            alive = wire_key(federation, "alive", ECHO)
            async with asyncio.timeout(START):
                while alive not in await transport.tokens(alive, timeout=1.0):
                    pass
            async with AgentPlatform(
                ASKER, transport, federation=federation, channel=channel
            ) as pa:
                await _restart(pa, channel, first, procs, port_a, federation, keys, trust)
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.kill()
            proc.join(timeout=10)


async def _restart(
    pa: AgentPlatform,
    channel: InterfaceAgent,
    first: BaseProcess,
    procs: list[BaseProcess],
    port_a: int,
    federation: str,
    keys: Path,
    trust: Path,
) -> None:
    """uav-a asks uav-b's first process, which is killed; then the second one, at once."""
    asker = await pa.add(Agent("asker"))
    answer = await request(asker, f"echo@{ECHO}", 1, ontology="demo", timeout=10)
    assert answer["echo"] == 1 and answer["pid"] == first.pid
    # uav-a's watch never reported the first process's token: it will not see it go either
    assert ECHO not in channel._alive and channel.sessions.peers() == [ECHO]

    assert first.pid is not None
    os.kill(first.pid, signal.SIGKILL)
    await asyncio.to_thread(first.join, 10)
    second = await asyncio.to_thread(
        _start, ZenohConfig.loopback(free_tcp_port(), connect=[port_a]), federation, keys, trust
    )
    procs.append(second)
    # the new process's token: uav-a's first sight of uav-b
    await _until(lambda: ECHO in channel._alive, "uav-a seeing the new uav-b's token")
    # every request is answered at once, by the new process, none refused there
    for i in range(2, 5):
        answer = await request(asker, f"echo@{ECHO}", i, ontology="demo", timeout=10)
        assert answer["echo"] == i and answer["pid"] == second.pid, answer
    assert answer["unauthenticated"] == answer["rehandshakes"] == 0, answer
