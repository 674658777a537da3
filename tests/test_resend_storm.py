"""A member's stream reports cannot make a provider resend more than a gap lost.

The provider (``uav-p``) runs in a spawned process and exports ``car1-state`` to the
member (``uav-m``) with a history of 50. The member (this process, our library with its
own key and the session the provider agreed with it) receives the stream and sends,
sealed, what an attacker would: a storm of reports claiming huge losses and asking for
every range, again and again. The provider resends each sample at most once, within its
history and the member's reported losses, at most RESEND_RATE requests a second; its
counters match what it really resent, and its refusals are counted and audited. Both
sides then shut down in order, logging no failure.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import uuid
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import msgpack
import pytest

from agents import AgentPlatform, wire_key
from agents._exceptions import AuthenticationError
from agents._interface import InterfaceAgent
from agents._security import KeyPair, TrustStore
from agents.keys import gen_keys, trust_keys
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
from bench._flood import recv
from dyknow_core import DyKnowInstance
from federation import ExportProxy, InterfaceSessions
from federation._batch import read_batch
from federation._export import RESEND_RATE

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

PROVIDER, MEMBER = "uav-p", "uav-m"
LABEL, HISTORY = "car1-state", 50
START = 30.0  # a spawned interpreter imports zenoh and pydantic: seconds when loaded
WAIT = 15.0


class _Failures(logging.Handler):
    """The provider's records of something that failed, once it was told to stop."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.stopping = False
        self.seen: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if self.stopping and "failed" in record.getMessage():
            self.seen.append(f"{record.name}: {record.getMessage()}")


def provider_main(config: dict[str, Any], fed: str, keys: str, trust: str, conn: Any) -> None:
    """The provider: exports ``car1-state`` to the member, 200 samples/s, history 50.

    Once stopped it sends what it logged as failed while shutting down (nothing, in order).
    """
    logging.basicConfig(level=logging.WARNING)  # its warnings still shown on stderr
    failures = _Failures()
    logging.getLogger().addHandler(failures)
    asyncio.run(_provider(config, fed, Path(keys), Path(trust), conn, failures))
    conn.send({"failed at shutdown": failures.seen})


async def _provider(
    config: dict[str, Any], fed: str, keys: Path, trust: Path, conn: Connection, failures: _Failures
) -> None:
    channel = InterfaceAgent(KeyPair.load(keys / f"{PROVIDER}.key"), TrustStore.load(trust))
    async with (
        ZenohTransport(ZenohConfig.model_validate(config)) as t,
        AgentPlatform(PROVIDER, t, federation=fed, channel=channel) as pf,
        DyKnowInstance(PROVIDER) as dk,
        ExportProxy(PROVIDER, fed, t, dk, InterfaceSessions(channel)) as exporter,
    ):
        watch = await t.watch_presence(pf.key("alive", MEMBER))
        async with watch, asyncio.timeout(START):
            while not (await watch.get()).alive:
                pass
        src = dk.add_source("x")
        export = exporter.start_exporting("x", LABEL, MEMBER, history=HISTORY)

        async def produce() -> None:
            i = 0
            while True:
                src.push(i)
                i += 1
                await asyncio.sleep(0.005)

        # the instance owns what pushes into it: it ends the producer as it closes its
        # streams (owned by the platform, which closes after the instance, it would push
        # into a closed stream and fail)
        dk.spawn("produce", produce())
        conn.send("ready")
        while True:
            cmd = await asyncio.to_thread(conn.recv)
            if cmd == "stop":
                failures.stopping = True
                return
            conn.send(
                {
                    "stats": export.stats(),
                    "numbered": export._seq,
                    "records": [r for r in channel.audit.records if r.get("stage") == "resend"],
                }
            )


async def ask(conn: Connection, what: str) -> Any:
    """The provider's answer to a report request."""
    conn.send("report")
    return await asyncio.to_thread(recv, conn, what)


async def test_a_storm_of_resend_requests_resends_each_sample_at_most_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Reports asking everything back, thousands of times: bounded resends, honest counters."""
    fed = f"rs-{uuid.uuid4().hex[:8]}"
    keydir, trust = tmp_path / "keys", tmp_path / "trust.json"
    trust_keys(trust, [gen_keys(n, keydir)[2] for n in (PROVIDER, MEMBER)], federation=fed)
    port = free_tcp_port()
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    child = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
    proc = ctx.Process(
        target=provider_main,
        args=(child, fed, str(keydir), str(trust), there),
        name="resend-provider",
    )
    channel = InterfaceAgent(KeyPair.load(keydir / f"{MEMBER}.key"), TrustStore.load(trust))
    resent: list[int] = []  # the sequence numbers that came back, one per sample
    fresh = 0
    first = asyncio.Event()  # the first batch came: the provider agreed a session with us
    try:
        async with (
            asyncio.timeout(START + 6 * WAIT),
            ZenohTransport(ZenohConfig.loopback(port)) as t,
            AgentPlatform(MEMBER, t, federation=fed, channel=channel) as pm,
        ):
            stream = await t.subscribe(f"{wire_key(fed, 'stream', MEMBER)}/{PROVIDER}/{LABEL}")
            report_key = f"{wire_key(fed, 'stream-report', PROVIDER)}/{MEMBER}"

            async def receive() -> None:
                nonlocal fresh
                async for item in stream:
                    try:
                        sender, body = channel.sessions.open_bytes(item.payload)
                    except AuthenticationError:
                        continue  # sealed on a session being replaced: not ours to judge
                    assert sender == PROVIDER
                    batch = read_batch(body)
                    assert batch.seq is not None
                    if batch.recovered:
                        resent.extend(range(batch.seq, batch.seq + len(batch.samples)))
                    else:
                        fresh += len(batch.samples)
                        first.set()

            async def report(lost: int, resend: list[int] | None = None) -> int:
                body: dict[str, Any] = {"v": 1, "lost": {LABEL: lost}}
                if resend is not None:
                    body["resend"] = {LABEL: resend}
                envelope = channel.sessions.seal_bytes(PROVIDER, msgpack.packb(body))
                await t.publish(report_key, envelope)
                return len(envelope)

            pm.spawn(receive(), "receive")
            proc.start()
            assert await asyncio.to_thread(recv, here, "the provider", START) == "ready"
            # an honest member first: the stream flows (the provider agrees the session),
            # and its reports are the lease
            async with asyncio.timeout(START):
                await first.wait()
            async with asyncio.timeout(WAIT):
                while fresh < 2 * HISTORY + 300:
                    await report(0)
                    await asyncio.sleep(0.25)
            assert resent == []
            before = await ask(here, "the provider's counters")
            numbered = before["numbered"]
            # the storm: every request asks for all that was numbered, or the last
            # history's worth, claiming a billion samples lost
            sent_bytes = 0
            for i in range(3000):
                span = [0, numbered] if i % 2 else [numbered - HISTORY, numbered]
                sent_bytes += await report(10**9, span)
                if i % 50 == 0:
                    await asyncio.sleep(0.01)  # let the provider keep up, as a sender would
            # and asking back what it never reported lost, and what was never numbered
            await asyncio.sleep(1.1)
            sent_bytes += await report(0, [numbered - 10, numbered])
            sent_bytes += await report(10**9, [numbered + 10**6, numbered + 2 * 10**6])
            # the last resends arrived and the refusals were audited (a record a second)
            reasons = ("rate", "already-resent", "over-loss", "not-a-gap")
            async with asyncio.timeout(WAIT):
                while True:
                    after = await ask(here, "the provider's counters")
                    stats = after["stats"]
                    refused = stats["resend_refused"]
                    if (
                        all(refused.get(r, 0) for r in reasons)
                        and after["records"]
                        and stats["recovered"] == len(resent)
                    ):
                        break
                    await asyncio.sleep(0.1)  # counters in another process: polled
            print(
                f"\nresend storm: {sent_bytes} bytes of reports (3002) made the provider resend "
                f"{len(resent)} samples (history {HISTORY}, {after['numbered']} numbered); "
                f"recovered {stats['recovered']}, lost-in-transit "
                f"{stats['dropped_by_reason'].get('lost-in-transit', 0)}; refused "
                f"{stats['resend_refused']}"
            )
            # each sample at most once, and only what the history held (2N + 256 kept)
            assert len(resent) == len(set(resent)), "a sample resent twice"
            assert 0 < len(resent) <= 2 * HISTORY + 256
            assert all(0 <= n < numbered for n in resent)
            # the counters say what really happened
            assert stats["recovered"] == len(resent)
            lost = stats["dropped_by_reason"].get("lost-in-transit", 0)
            assert lost <= after["numbered"], "a loss larger than the stream"
            for reason in reasons:
                assert refused.get(reason, 0) > 0, (reason, refused)
            # at most the bucket's burst plus its rate over the storm went through
            assert sum(refused.values()) >= 3002 - (40 + RESEND_RATE * 10)
            records = after["records"]
            assert records, "no audit record of the refusals"
            assert len(records) <= 15, "one record per second at most"
            rec = records[0]
            assert rec["verdict"] == "refused" and rec["from"] == MEMBER
            assert rec["reason"].startswith(f"resend requests for {LABEL!r} refused")
            assert sum(r["count"] for r in records) <= sum(refused.values())
            assert sum(rec["by_reason"].values()) == rec["count"]
            # the stream itself went on
            assert after["stats"]["active"] and fresh > before["stats"]["sent"] - HISTORY
            stream.close()
            caplog.clear()
        # an orderly shutdown, on both sides: nothing logged as failed
        assert [r.getMessage() for r in caplog.records if "failed" in r.getMessage()] == []
        here.send("stop")
        report = await asyncio.to_thread(recv, here, "the provider's shutdown")
        assert report == {"failed at shutdown": []}
    finally:
        with contextlib.suppress(OSError):
            here.send("stop")
        if proc.pid is not None:
            proc.join(timeout=15)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=5)
