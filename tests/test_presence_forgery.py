"""Forged presence buys an outsider no re-handshakes nor key exchanges, real processes.

uav-a (the victim) runs in the test; uav-b, a trusted member, in a spawned process;
uav-c is trusted but never runs. The attacker has no key of the federation: a plain
zenoh session (peer mode on loopback, where anyone may declare a liveliness token under
any name) or a plain MQTT client (a broker without the generated ACL, where anyone may
publish a platform's retained presence). It toggles a trusted name's presence many times
a second. Each change the Interface Agent acted on would doubt that peer's sessions
(one key exchange each, with the real peer when it runs; before, a leave forgot them,
losing what was in flight on them) and lift its
re-handshake limiter (one more key exchange per forged envelope on an unknown session).
Per peer, presence is now acted on within a budget (`PRESENCE_BURST` changes at once,
then `PRESENCE_RATE` per ``rehandshake_interval``) and lifts the limiter at most once per
interval; the rest is counted (``stats.presence_suppressed``) and audited
(``stage`` ``presence-limited``), and the peer's sessions are doubted once, later.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import multiprocessing
import os
import threading
import time
import uuid
from collections import Counter
from collections.abc import AsyncIterator, Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import orjson
import paho.mqtt.client as paho
import pytest
import zenoh
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
from agents._presence import PRESENCE_BURST, PRESENCE_RATE
from agents.keys import gen_keys, trust_keys
from agents.transports import (
    MemoryHub,
    MqttConfig,
    MqttTransport,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)

START = 20.0  # a spawned interpreter imports zenoh and pydantic: seconds when loaded
WAIT = 15.0
VICTIM, MEMBER, ABSENT = "uav-a", "uav-b", "uav-c"
MARKER = "uav-d"  # trusted, never runs: its token marks how far uav-a's presence watch got
INTERVAL = 5.0  # the victim's rehandshake_interval (the default)
ALIVE = b'{"v":1,"alive":true}'  # what an MQTT token publishes (docs/wire.md)
TOGGLES = 300
RESTART_BOUND = 5.0  # s: a restarted member answered, its presence toggled (docs/security.md)
# every child a test spawned is gone after it, whatever the test did
pytestmark = [pytest.mark.timeout(120), pytest.mark.usefixtures("no_leftover_children")]


class Echo(ProtectedEcho):
    """Answers with what it was asked."""

    @on_request("demo")
    async def _echo(self, message: ACLMessage) -> Any:
        """The content."""
        return message.content

    @on_request("gated")
    async def _gated(self, message: ACLMessage) -> Any:
        """The content, once the file it names exists (the test says when to answer)."""
        await asyncio.to_thread(_wait_for, Path(message.content))
        return message.content


def _wait_for(path: Path) -> None:
    """Return once ``path`` exists (within `WAIT`)."""
    deadline = time.monotonic() + WAIT
    while not path.exists() and time.monotonic() < deadline:
        time.sleep(0.01)


def _transport(kind: str, config: dict[str, Any]) -> Transport:
    if kind == "zenoh":
        return ZenohTransport(ZenohConfig.model_validate(config))
    return MqttTransport(MqttConfig.model_validate(config))


def member_main(
    kind: str, config: dict[str, Any], fed: str, keys: str, trust: str, ready: Any
) -> None:
    """uav-b's process: the echo agent until it is killed; says "ready" once it serves."""
    asyncio.run(_member(kind, config, fed, Path(keys), Path(trust), ready))


async def _member(
    kind: str, config: dict[str, Any], fed: str, keys: Path, trust: Path, ready: Connection
) -> None:
    channel = InterfaceAgent(KeyPair.load(keys / f"{MEMBER}.key"), TrustStore.load(trust))
    async with (
        _transport(kind, config) as transport,
        AgentPlatform(MEMBER, transport, federation=fed, channel=channel) as platform,
    ):
        await platform.add(Echo())
        ready.send("ready")
        await asyncio.Event().wait()  # until killed


def _start_member(kind: str, config: dict[str, Any], fed: str, tmp: Path) -> BaseProcess:
    """uav-b in a new process, returned once it serves (bounded by START)."""
    ctx = multiprocessing.get_context("spawn")
    theirs, ours = ctx.Pipe(duplex=False)
    proc = ctx.Process(
        target=member_main,
        args=(kind, config, fed, str(tmp / "keys"), str(tmp / "trust.json"), ours),
        name=MEMBER,
    )
    proc.start()
    ours.close()
    if not theirs.poll(START):
        proc.kill()
        raise AssertionError(f"uav-b did not start within {START} s (exit code {proc.exitcode})")
    assert theirs.recv() == "ready"
    return proc


def _federation(tmp: Path) -> str:
    fed = f"presence-{uuid.uuid4().hex[:8]}"
    pubs = [gen_keys(n, tmp / "keys")[2] for n in (VICTIM, MEMBER, ABSENT, MARKER)]
    trust_keys(tmp / "trust.json", pubs, federation=fed)
    return fed


async def _until(what: str, cond: Callable[[], Any], timeout: float = WAIT) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := cond()):
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.02)
    return value


class Costs:
    """What presence made the victim do, per peer: counted around its session table."""

    def __init__(self, channel: InterfaceAgent) -> None:
        self.channel = channel
        self.forgets: Counter[str] = Counter()
        self.doubts: Counter[str] = Counter()
        self.agreed: Counter[str] = Counter()  # key exchanges the victim started
        table = channel.sessions
        forget, doubt, agree = table.forget, table.doubt, channel.agree

        def counted_forget(peer: str) -> int:
            self.forgets[peer] += 1
            return forget(peer)

        def counted_doubt(peer: str) -> int:
            self.doubts[peer] += 1
            return doubt(peer)

        async def counted_agree(peer: str) -> None:
            self.agreed[peer] += 1
            await agree(peer)

        table.forget = counted_forget  # type: ignore[method-assign]
        table.doubt = counted_doubt  # type: ignore[method-assign]
        channel.agree = counted_agree  # type: ignore[method-assign]

    def acted(self, peer: str) -> int:
        """Presence changes acted on (each forgets or doubts the peer's sessions)."""
        return self.forgets[peer] + self.doubts[peer]


def _limited(channel: InterfaceAgent, peer: str) -> list[dict[str, Any]]:
    return [
        r
        for r in channel.audit.records
        if r.get("stage") == "presence-limited" and r.get("from") == peer
    ]


def _unknown_session(fed: str, claimed: str) -> bytes:
    """An envelope in ``claimed``'s name on a session that does not exist (docs/wire.md)."""
    return orjson.dumps(
        {
            "v": 1,
            "from": claimed,
            "to": VICTIM,
            "sid": base64.urlsafe_b64encode(os.urandom(16)).rstrip(b"=").decode(),
            "ts_ms": int(time.time() * 1000),
            "n": 1,
            "body": '{"performative":"inform"}',
            "mac": base64.b64encode(os.urandom(32)).decode(),
        }
    )


def _zenoh_outsider(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(conf)


def _bound(seconds: float) -> int:
    """Presence changes a peer's budget lets act on in ``seconds`` (deferred doubts included)."""
    return PRESENCE_BURST + int(seconds * PRESENCE_RATE / INTERVAL) + 1


def _kill(procs: list[BaseProcess]) -> None:
    """Kill those of ``procs`` still running, and wait for each."""
    for proc in procs:
        if proc.is_alive():
            proc.kill()
        proc.join(timeout=10)


@contextlib.asynccontextmanager
async def _mqtt_victim(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> AsyncIterator[tuple[str, MqttConfig, list[BaseProcess], InterfaceAgent, AgentPlatform, Agent]]:
    """uav-a on MQTT, uav-b spawned and answering it: (fed, config, procs, channel, pa, asker).

    The processes in ``procs`` (uav-b's, and any the test adds) are killed on the way out.
    """
    host, port = mosquitto
    fed = _federation(tmp_path)
    procs: list[BaseProcess] = []
    channel = InterfaceAgent(
        KeyPair.load(tmp_path / "keys" / f"{VICTIM}.key"), TrustStore.load(tmp_path / "trust.json")
    )
    config = MqttConfig(host=host, port=port, keepalive=5)
    try:
        async with (
            MqttTransport(config) as transport,
            AgentPlatform(VICTIM, transport, federation=fed, channel=channel) as pa,
        ):
            procs.append(
                await asyncio.to_thread(_start_member, "mqtt", config.model_dump(), fed, tmp_path)
            )
            await _until("uav-a seeing uav-b's presence", lambda: MEMBER in channel._alive)
            asker = await pa.add(Agent("asker"))
            assert await request(asker, f"echo@{MEMBER}", 0, ontology="demo", timeout=10) == 0
            yield fed, config, procs, channel, pa, asker
    finally:
        _kill(procs)


def _mqtt_attacker(host: str, port: int) -> paho.Client:
    """A plain MQTT client, no key of the federation, connected and looping (stop it)."""
    attacker = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"x-{os.getpid()}")
    attacker.connect(host, port)
    attacker.loop_start()
    return attacker


async def test_presence_changes_over_the_budget_are_counted_audited_and_doubt_later() -> None:
    """In memory, an explicit count: 20 changes of uav-c's token at once, 4 acted on."""
    hub = MemoryHub()
    keys = {n: KeyPair.generate(n) for n in (VICTIM, ABSENT)}
    trust = TrustStore("fed", {n: k.public_key for n, k in keys.items()})
    clock = [1000.0]  # the budget's clock: still while the changes come, however loaded
    channel = InterfaceAgent(keys[VICTIM], trust, audit_interval=0.02, monotonic=lambda: clock[0])
    async with (
        asyncio.timeout(WAIT),
        hub.transport() as transport,
        hub.transport() as outsider,
        AgentPlatform(VICTIM, transport, federation="fed", channel=channel) as pa,
    ):
        costs = Costs(channel)
        channel._last_rehandshake[ABSENT] = time.monotonic()  # a re-handshake just ran
        key = wire_key("fed", "alive", ABSENT)
        for _ in range(10):
            token = await outsider.declare_token(key)
            token.close()
            channel.rehandshake(ABSENT)  # a forged envelope on an unknown session, each time
            await asyncio.sleep(0.001)
        await _until(
            "20 changes seen", lambda: costs.acted(ABSENT) + pa.stats.presence_suppressed >= 20
        )
        assert costs.acted(ABSENT) == PRESENCE_BURST
        assert pa.stats.presence_suppressed == 20 - PRESENCE_BURST
        # the limiter lifted once (per 5 s): one re-handshake, not one per change
        assert pa.stats.rehandshakes <= 1
        assert pa.stats.rehandshakes + pa.stats.rehandshakes_suppressed <= 10
        await _until("the audit record", lambda: _limited(channel, ABSENT))
        # once the budget allows (2.5 s on), one doubt stands for the changes ignored
        doubts = costs.doubts[ABSENT]
        clock[0] += INTERVAL
        await _until("the doubt that stands in", lambda: costs.doubts[ABSENT] == doubts + 1)
        # every change ignored is audited: all 16 in the first record, or (when the audit
        # ticked while they still came in, on a loaded machine) the rest in the next one,
        # a second of the budget's clock later
        ignored = 20 - PRESENCE_BURST
        await _until(
            "all the changes ignored audited",
            lambda: sum(r["count"] for r in _limited(channel, ABSENT)) >= ignored,
        )
        await asyncio.sleep(0.3)
        assert costs.doubts[ABSENT] == doubts + 1 and not channel._presence_later
        records = _limited(channel, ABSENT)
        assert sum(r["count"] for r in records) == ignored, records
        for r in records:
            assert r["verdict"] == "dropped"
            assert r["reason"].startswith(f"presence changes of {ABSENT!r} ignored: {r['count']} ")


@pytest.mark.timeout(180)
async def test_forged_tokens_on_zenoh_rekey_within_the_bound(tmp_path: Path) -> None:
    """Token toggles: none reach the victim while uav-b runs; for uav-c, bounded and counted."""
    fed = _federation(tmp_path)
    port = free_tcp_port()
    procs: list[BaseProcess] = []
    channel = InterfaceAgent(
        KeyPair.load(tmp_path / "keys" / f"{VICTIM}.key"), TrustStore.load(tmp_path / "trust.json")
    )
    try:
        async with (
            ZenohTransport(ZenohConfig.loopback(port)) as transport,
            AgentPlatform(VICTIM, transport, federation=fed, channel=channel) as pa,
        ):
            member_config = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
            procs.append(
                await asyncio.to_thread(_start_member, "zenoh", member_config, fed, tmp_path)
            )
            await _until("uav-a seeing uav-b's token", lambda: MEMBER in channel._alive)
            asker = await pa.add(Agent("asker"))
            assert await request(asker, f"echo@{MEMBER}", 0, ontology="demo", timeout=10) == 0
            costs = Costs(channel)
            outsider = _zenoh_outsider(port)
            try:
                prefix = f"dyknow/{fed}/v1"
                await _until(
                    "the outsider reaching uav-a",
                    # the get's replies as a list: a get no one answered yet (not linked)
                    # ends its channel empty, where a bare recv() raises
                    lambda: bool(
                        list(outsider.liveliness().get(f"{prefix}/alive/{VICTIM}", timeout=1.0))
                    ),
                )

                # 1. uav-b runs: zenoh keeps its key alive while any token holds it, so no
                #    forged declare or undeclare of it reaches the victim's presence watch
                def toggle(name: str, n: int, cue: bool) -> float:
                    start = time.monotonic()
                    for _ in range(n):
                        token = outsider.liveliness().declare_token(f"{prefix}/alive/{name}")
                        time.sleep(0.005)
                        token.undeclare()
                        if cue:
                            outsider.put(f"{prefix}/acl/{VICTIM}", _unknown_session(fed, name))
                        time.sleep(0.005)
                    return time.monotonic() - start

                await asyncio.to_thread(toggle, MEMBER, 100, False)
                # uav-d's token, declared after the toggles, is seen after whatever they made
                marker = outsider.liveliness().declare_token(f"{prefix}/alive/{MARKER}")
                await _until("the marker seen", lambda: MARKER in channel._alive)
                assert costs.acted(MEMBER) == 0, (costs.forgets, costs.doubts)
                # 2. uav-c is trusted and not running: each declare and undeclare is a change
                before = pa.stats.rehandshakes
                seconds = await asyncio.to_thread(toggle, ABSENT, 200, True)
                marker.undeclare()
                await _until("the marker gone", lambda: MARKER not in channel._alive)
                await _until(
                    "most of 400 changes suppressed", lambda: pa.stats.presence_suppressed >= 200
                )
                rekeys = pa.stats.rehandshakes - before
                print(
                    f"\nzenoh, uav-c's token toggled 200 times in {seconds:.1f} s: "
                    f"{costs.acted(ABSENT)} presence change(s) acted on "
                    f"({pa.stats.presence_suppressed} suppressed), {rekeys} re-handshake(s) "
                    f"({pa.stats.rehandshakes_suppressed} cues ignored), "
                    f"{costs.agreed[ABSENT]} key exchange(s) started"
                )
                assert costs.acted(ABSENT) <= _bound(seconds + 1.0)
                assert rekeys <= 2 + 2 * int((seconds + 1.0) / INTERVAL)
                records = await _until(
                    "the suppressed changes audited", lambda: _limited(channel, ABSENT)
                )
                assert sum(r["count"] for r in records) <= pa.stats.presence_suppressed
                assert records[0]["verdict"] == "dropped"
                assert "presence changes" in records[0]["reason"]
                # uav-b is still served, on its session
                assert await request(asker, f"echo@{MEMBER}", 1, ontology="demo", timeout=10) == 1
            finally:
                outsider.close()
    finally:
        _kill(procs)


@pytest.mark.timeout(180)
async def test_forged_presence_on_mqtt_costs_the_member_few_key_exchanges(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    """uav-b's retained presence cleared and set again, many times, while uav-a asks it."""
    async with _mqtt_victim(tmp_path, mosquitto) as (fed, _, _, channel, pa, asker):
        costs = Costs(channel)
        attacker = _mqtt_attacker(*mosquitto)
        stop = threading.Event()
        topic = f"dyknow/{fed}/v1/alive/{MEMBER}"

        def toggle() -> float:
            start = time.monotonic()
            for _ in range(TOGGLES):
                attacker.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)
                attacker.publish(topic, ALIVE, qos=1, retain=True).wait_for_publish(5)
                time.sleep(0.01)
            stop.set()
            return time.monotonic() - start

        try:
            before = pa.stats.rehandshakes
            attack = asyncio.create_task(asyncio.to_thread(toggle))
            answered, failed = 0, []
            while not stop.is_set():  # uav-a keeps asking uav-b meanwhile
                answered += 1
                try:
                    got = await request(
                        asker, f"echo@{MEMBER}", answered, ontology="demo", timeout=5
                    )
                    assert got == answered
                except Exception as exc:  # what the forgery cost, reported below
                    failed.append(repr(exc))
                await asyncio.sleep(0.05)
            seconds = await attack
            await asyncio.sleep(1.0)
            rekeys = pa.stats.rehandshakes - before
            print(
                f"\nmqtt, uav-b's presence toggled {TOGGLES} times in {seconds:.1f} s while "
                f"uav-a asked {answered} times: {costs.acted(MEMBER)} presence change(s) "
                f"acted on ({costs.forgets[MEMBER]} forgets, {costs.doubts[MEMBER]} doubts; "
                f"{pa.stats.presence_suppressed} suppressed), {rekeys} re-handshake(s), "
                f"{costs.agreed[MEMBER]} key exchange(s) started, "
                f"{len(failed)} request(s) failed"
            )
            print("\n".join(failed[:3]))
            # presence forgets no session: nothing in flight on one is lost
            assert costs.forgets[MEMBER] == 0 and not failed, failed
            assert costs.acted(MEMBER) <= _bound(seconds + 1.0)
            assert costs.agreed[MEMBER] <= _bound(seconds + 1.0) + 2
            assert rekeys <= 2 + 2 * int((seconds + 1.0) / INTERVAL)
            assert pa.stats.presence_suppressed >= 100
            records = await _until(
                "the suppressed changes audited", lambda: _limited(channel, MEMBER)
            )
            assert sum(r["count"] for r in records) <= pa.stats.presence_suppressed
            # and uav-b is still served once the attack stops
            got = await request(asker, f"echo@{MEMBER}", -1, ontology="demo", timeout=10)
            assert got == -1
        finally:
            attacker.loop_stop()
            attacker.disconnect()


async def test_a_forged_leave_loses_no_answer_in_flight(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    """uav-b's presence cleared by an outsider while uav-a waits for uav-b's answer.

    The leave is within the budget, so it is acted on: uav-b's sessions are doubted, not
    forgotten (forgetting them refused the answer uav-b then sealed on one: it was lost).
    """
    async with _mqtt_victim(tmp_path, mosquitto) as (fed, _, _, channel, pa, asker):
        costs = Costs(channel)
        gate = tmp_path / "answer-now"
        sent = pa.stats.sent_remote
        asking = asyncio.create_task(
            request(asker, f"echo@{MEMBER}", str(gate), ontology="gated", timeout=5)
        )
        attacker = _mqtt_attacker(*mosquitto)
        try:
            # sealed on uav-a's session with uav-b: uav-b answers on it, whenever it gets it
            await _until("the request sent", lambda: pa.stats.sent_remote > sent)
            attacker.publish(
                f"dyknow/{fed}/v1/alive/{MEMBER}", b"", qos=1, retain=True
            ).wait_for_publish(5)
            await _until("the forged leave acted on", lambda: costs.acted(MEMBER) >= 1)
            assert pa.stats.presence_suppressed == 0
            gate.touch()  # uav-b answers now, on the session it holds with uav-a
            assert await asking == str(gate)
            assert costs.forgets[MEMBER] == 0
            # and the next request agrees a new session, answered as well
            assert await request(asker, f"echo@{MEMBER}", 1, ontology="demo", timeout=5) == 1
        finally:
            attacker.loop_stop()
            attacker.disconnect()


@pytest.mark.timeout(120)
async def test_forged_tokens_cost_the_global_directory_few_queries_and_hold_up_no_member(
    tmp_path: Path,
) -> None:
    """uav-c's token toggled, its directory key answered by a silent queryable; uav-b joins.

    Each appearance of uav-c's token had uav-a's global directory ask uav-c a signed
    query (three, each to its timeout: the queryable never answers), one change after the
    other for every platform: uav-b's presence waited behind all of them. Now each
    platform's changes are taken on a task of their own, and those costing a query within
    uav-c's budget; the rest are counted and audited, the latest acted on.
    """
    fed = _federation(tmp_path)
    port = free_tcp_port()
    procs: list[BaseProcess] = []
    channel = InterfaceAgent(
        KeyPair.load(tmp_path / "keys" / f"{VICTIM}.key"), TrustStore.load(tmp_path / "trust.json")
    )
    prefix = f"dyknow/{fed}/v1"
    try:
        async with (
            ZenohTransport(ZenohConfig.loopback(port)) as transport,
            AgentPlatform(
                VICTIM, transport, federation=fed, channel=channel, query_timeout=0.25
            ) as pa,
        ):
            view = pa.global_df
            assert view is not None
            asked: Counter[str] = Counter()
            real_query = view._query

            async def query(platform: str, *args: Any, **kw: Any) -> Any:
                asked[platform] += 1
                return await real_query(platform, *args, **kw)

            view._query = query  # type: ignore[method-assign]
            outsider = _zenoh_outsider(port)
            stop = threading.Event()

            def toggle() -> float:
                start = time.monotonic()
                while not stop.is_set():
                    token = outsider.liveliness().declare_token(f"{prefix}/alive/{ABSENT}")
                    time.sleep(0.005)
                    token.undeclare()
                    time.sleep(0.005)
                return time.monotonic() - start

            held: list[Any] = []  # a query dropped is ended: kept, it waits its timeout
            silent = outsider.declare_queryable(f"{prefix}/df/{ABSENT}", held.append)
            attack = asyncio.create_task(asyncio.to_thread(toggle))
            try:
                await _until("uav-c's forged token asked about", lambda: asked[ABSENT] >= 1)
                member_config = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
                procs.append(
                    await asyncio.to_thread(_start_member, "zenoh", member_config, fed, tmp_path)
                )
                serving = time.monotonic()
                await _until("uav-b listed", lambda: MEMBER in view.platforms, timeout=5.0)
                listed = time.monotonic() - serving
                records = await _until(
                    "uav-c's changes audited",
                    lambda: [
                        r
                        for r in channel.audit.records
                        if r.get("stage") == "df-presence-limited" and r.get("from") == ABSENT
                    ],
                )
            finally:
                stop.set()
                seconds = await attack
                silent.undeclare()
                held.clear()
                outsider.close()
            print(
                f"\nuav-c's token toggled for {seconds:.1f} s: uav-b listed {listed:.2f} s after "
                f"it serves; {asked[ABSENT]} signed queries to uav-c, "
                f"{view.presence_limited} changes not acted on one by one"
            )
            assert records[0]["verdict"] == "dropped" and records[0]["count"] >= 1
            assert sum(r["count"] for r in records) <= view.presence_limited
            # a fetch asks up to three times; one change more acted on as the latest
            assert asked[ABSENT] <= 3 * _bound(seconds)
    finally:
        _kill(procs)


@pytest.mark.timeout(180)
async def test_a_real_restart_recovers_as_fast_while_its_name_is_toggled(tmp_path: Path) -> None:
    """uav-b started, then killed and started again twice: calm, then its token toggled.

    A real restart is two changes (gone, back), within the budget. On zenoh the toggling
    reaches uav-a only while uav-b is down (its gone acted on first): it spends the
    budget, and the new process's token may then be ignored. The first request after the
    new process serves is answered either way, about as fast as after the calm restart.
    (Over MQTT the budget can be spent while uav-b runs: the test after this one.)
    """
    fed = _federation(tmp_path)
    port = free_tcp_port()
    procs: list[BaseProcess] = []
    channel = InterfaceAgent(
        KeyPair.load(tmp_path / "keys" / f"{VICTIM}.key"), TrustStore.load(tmp_path / "trust.json")
    )
    prefix = f"dyknow/{fed}/v1"
    try:
        async with (
            ZenohTransport(ZenohConfig.loopback(port)) as transport,
            AgentPlatform(VICTIM, transport, federation=fed, channel=channel) as pa,
        ):
            asker = await pa.add(Agent("asker"))
            outsider = _zenoh_outsider(port)
            recovery: dict[str, float] = {}
            try:
                for run in ("first", "calm", "toggled"):  # the first start is not a restart
                    config = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
                    proc = await asyncio.to_thread(_start_member, "zenoh", config, fed, tmp_path)
                    procs.append(proc)
                    started = time.monotonic()
                    got = await request(asker, f"echo@{MEMBER}", run, ontology="demo", timeout=10)
                    assert got == run
                    recovery[run] = time.monotonic() - started
                    await _until("uav-a seeing uav-b", lambda: MEMBER in channel._alive)
                    proc.kill()
                    await asyncio.to_thread(proc.join, 10)
                    await _until("uav-a seeing uav-b go", lambda: MEMBER not in channel._alive)
                    if run == "calm":
                        # while uav-b is down, its name's token toggled: its budget spent
                        suppressed = pa.stats.presence_suppressed
                        for _ in range(50):
                            token = outsider.liveliness().declare_token(f"{prefix}/alive/{MEMBER}")
                            await asyncio.sleep(0.005)
                            token.undeclare()
                            await asyncio.sleep(0.005)
                        await _until(
                            "the toggling suppressed",
                            lambda n=suppressed + 50: pa.stats.presence_suppressed > n,
                        )
            finally:
                outsider.close()
            print(
                f"\nfirst answer after uav-b serves again: calm {recovery['calm']:.3f} s, "
                f"its token toggled while it was down {recovery['toggled']:.3f} s"
            )
            # a fresh platform's first request agrees a session (as the calm one did)
            assert recovery["toggled"] < max(2.0, 3 * recovery["calm"])
    finally:
        _kill(procs)


@pytest.mark.timeout(240)
async def test_mqtt_restart_while_the_budget_is_spent_recovers_within_the_bound(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    """uav-b's presence toggled while it runs, then uav-b killed and started again.

    The toggling spends uav-b's budget and goes on through the restart, so the real gone
    and back are over it and ignored: uav-a still holds the killed process's session. Its
    first request on it is lost; the new process's re-handshake cue (an envelope on a
    session it does not know) and the doubt that stands in for the ignored changes
    (`_presence_catch_up`) agree a new one. A request is answered within `RESTART_BOUND`.
    """
    async with _mqtt_victim(tmp_path, mosquitto) as (fed, config, procs, channel, pa, asker):
        costs = Costs(channel)
        attacker = _mqtt_attacker(*mosquitto)
        stop = threading.Event()
        topic = f"dyknow/{fed}/v1/alive/{MEMBER}"

        def toggle() -> None:
            while not stop.is_set():
                attacker.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)
                attacker.publish(topic, ALIVE, qos=1, retain=True).wait_for_publish(5)
                time.sleep(0.02)

        attack = asyncio.create_task(asyncio.to_thread(toggle))
        try:
            await _until("uav-b's budget spent", lambda: pa.stats.presence_suppressed >= 20)
            # uav-a goes on asking: the answer is on a session with this process, which
            # the restart's ignored changes do not forget
            assert await request(asker, f"echo@{MEMBER}", 0, ontology="demo", timeout=10) == 0
            assert channel.sessions.session_for(MEMBER) is not None
            suppressed, acted = pa.stats.presence_suppressed, costs.acted(MEMBER)
            procs[0].kill()
            await asyncio.to_thread(procs[0].join, 10)
            new = await asyncio.to_thread(_start_member, "mqtt", config.model_dump(), fed, tmp_path)
            procs.append(new)
            started = time.monotonic()
            asked, failed = 0, []
            while True:  # uav-a asks until answered, each request bounded
                asked += 1
                try:
                    got = await request(
                        asker, f"echo@{MEMBER}", asked, ontology="demo", timeout=1.0
                    )
                except Exception as exc:  # the first is lost: sealed on the old session
                    failed.append(repr(exc))
                    assert time.monotonic() - started < RESTART_BOUND + 5.0, failed
                    continue
                assert got == asked
                break
            recovery = time.monotonic() - started
            restart = (costs.acted(MEMBER) - acted, pa.stats.presence_suppressed - suppressed)
            stop.set()
            await attack
        finally:
            stop.set()
            await asyncio.wait([attack], timeout=10)
            attacker.loop_stop()
            attacker.disconnect()
        print(
            f"\nmqtt, uav-b killed and restarted while its presence is toggled: answered "
            f"{recovery:.2f} s after the new process serves ({asked} request(s)); "
            f"{costs.acted(MEMBER)} change(s) acted on ({costs.forgets[MEMBER]} forgets, "
            f"{costs.doubts[MEMBER]} doubts), {pa.stats.presence_suppressed} suppressed, "
            f"{pa.stats.rehandshakes} re-handshake(s); during the restart "
            f"{restart[0]} acted on, {restart[1]} suppressed"
        )
        print("\n".join(failed[:3]))
        assert recovery < RESTART_BOUND
