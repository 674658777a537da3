"""The full agent stack between two platforms in two OS processes, against raw transports.

Two platforms, ``bench-a`` (this process) and ``bench-b`` (a child started with
``spawn``, see ``bench/_acl_node.py``), each with its own Ed25519 key pair, the federation's
trust file, and the Interface Agent as its channel: every message is sealed under a
session key agreed by a signed key exchange, opened and checked (MAC, replay, expiry),
access-controlled against the Directory Facilitator, audited, then delivered. What is
measured, each beside a peer measured in the same run:

- round trip: ``request(asker@bench-a, gateway@bench-b, {"action": "query", ...})``, a
  FIPA-Request answered with an ``inform`` by the Gateway Agent (a stand-in doing the
  same through `GatewayService` while ``federation/_gateway.py`` is missing) querying the
  latest sample of a label on a DyKnow instance, over zenoh (peer mode, loopback):
  median, p90, p99 of ``N_RTT`` round trips after a warm-up, best of ``ROUNDS`` rounds
  interleaved with raw zenoh ``get`` on a queryable and put/sub ping-pong
  (``bench/_zenoh_raw.py``);
- one-way throughput: ``N_FLOOD`` ``inform`` messages (362 B of JSON each) from an agent
  here to ``sink@bench-b``, counted as they reach the agent's handler there; the rate is
  end to end (first send to last delivery, so the slower side sets it), against raw
  zenoh put/sub one way (counted in the subscriber's callback);
- start to ready: from just before the spawn to the first ``inform`` answering a request
  (so: interpreter, imports, keys, transport, platform, agents, key exchange), against a
  bare zenoh process (open a session, declare a queryable) answering its first ``get``;
  median of ``READY_REPEAT`` spawns each, interleaved; the node runs from a copy of our
  packages with their bytecode compiled, as an installed node has it (`install`);
- idle RSS of that node (VmRSS of the child, ready and idle), against the bare zenoh one;
- the same round trip over MQTT through a mosquitto of our own (free loopback port),
  against a raw aiomqtt ping-pong through the same broker;
- the agent peer: osBrain 0.6.5 (ZeroMQ over loopback TCP, no security), its REQ-REP
  round trip and its PUSH-PULL one-way throughput between two agent processes, the same
  counts (``bench/_osbrain.py``), beside our zenoh round trip (median) and flood
  (``acl-rtt-median-vs-osbrain``, ``acl-throughput-vs-osbrain``);
- encryption's cost: the zenoh round trip with encrypted sessions (ChaCha20-Poly1305, the
  default everywhere above) against MAC-only sessions, both sides restarted for each,
  alternating (``acl-rtt-median-encrypted``);
- the floor: the same two-process round trip built from the design's blocks alone, none
  of our code (``bench/_acl_floor.py``: both sides on an event loop with our transport's
  hand-over, with and without our envelope's crypto and JSON, the replier on zenoh's
  thread ...), each against a raw zenoh get measured in turns with it, and our whole
  stack's round trip in the same turns (``acl-floor-<variant>-vs-get``,
  ``acl-floor-ours-vs-get``): what part of ``acl-rtt-median`` the design costs.

Event loops: both agent sides (this process and the node) run on `agents.run`'s loop,
uvloop where installed (the node runner's too), asyncio's own with
``DYKNOW_EVENT_LOOP=asyncio``; the loop is printed with the results. The raw zenoh peers
use no event loop (zenoh's threads, blocking calls); osBrain is ZeroMQ in its own
processes. Both agent sides put what their start-up built out of the collector's sight
before the timed round trips (``gc.freeze``), as a started node does.

``python -m bench.acl --profile`` profiles the zenoh round trip and the throughput path
instead (cProfile on both sides, plus the per-stage costs measured one by one);
``python -m bench._acl_trace [N]`` times one round trip stage by stage in both processes.
``python -m bench._acl_flood [N] [ROUNDS]`` runs the one-way flood alone (``--ab`` for two trees).
``python -m bench._acl_oneway_cpu`` runs it with both platforms in one process (memory
transport): both sides' CPU per message on one thread, free of the machine's load.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import statistics
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, NamedTuple, TypedDict

import aiomqtt
import zenoh

from agents import (
    Agent,
    AgentPlatform,
    Failed,
    NotUnderstood,
    Performative,
    Refused,
    ReplyTimeout,
    SecurityError,
    TransportError,
    event_loop_name,
    request,
)
from agents import run as run_loop
from agents._interface import InterfaceAgent
from agents._security import KeyPair, SecurityPolicy, TrustStore
from agents.transports import (
    MqttConfig,
    MqttTransport,
    Presence,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from bench import _zenoh_raw, fmt, progress, report
from bench._acl_floor import measure as measure_floor
from bench._acl_floor import print_floor
from bench._acl_node import CONTROL_ONTOLOGY, FLOOD_ONTOLOGY, LABEL, node_main
from bench._bare_node import bare_zenoh_main, mqtt_echo_main
from bench._child import Child, ChildFailed
from bench._mosquitto import executable as mosquitto_executable
from bench._mosquitto import mosquitto
from bench._osbrain import osbrain_main
from bench.memory import _installed as installed

N_RTT = 2000
WARMUP = 300
ROUNDS = 2
N_FLOOD = 100_000
RAW_FLOOD = 200_000
READY_REPEAT = 3
IDLE_S = 1.0  # how long a ready node idles before its RSS is read
START_TIMEOUT = 30.0  # a spawned interpreter on a loaded 2-core machine: generous
SITE = "site"  # the compiled copy of our packages the node runs from, in the key directory
ACL_BYTES = 362  # the flood's ACL message size, as ANCHORS.md's per-message costs
FEDERATION = "bench"
HERE, THERE = "bench-a", "bench-b"
GATEWAY = f"gateway@{THERE}"
SINK = f"sink@{THERE}"
CONTROL = f"control@{THERE}"
QUERY = {"action": "query", "label": LABEL, "kind": "latest"}
# what a probe for readiness may meet before the node answers: not there yet, agent
# not added yet, service not registered yet, key exchange not served yet
NOT_READY = (Refused, Failed, NotUnderstood, ReplyTimeout, TransportError, SecurityError)


# --------------------------------------------------------------------------- helpers


def quantile(xs: list[float], q: float) -> float:
    """The ``q`` quantile (nearest rank) of ``xs``."""
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


def summary(ms: list[float]) -> dict[str, float]:
    """Median, p90, p99 and max of round trips in ms."""
    return {
        "median": statistics.median(ms),
        "p90": quantile(ms, 0.90),
        "p99": quantile(ms, 0.99),
        "max": max(ms),
        "n": len(ms),
    }


def _line(name: str, s: dict[str, float]) -> str:
    return (
        f"  {name:<22} median {s['median']:.3f}  p90 {s['p90']:.3f}  p99 {s['p99']:.3f}  "
        f"max {s['max']:.2f} ms  (n={int(s['n'])})"
    )


def settle_gc() -> None:
    """What this side built so far out of the collector's sight, as a node does once started.

    The node does it too (``bench/_acl_node.py``); without it a full collection here walks
    the interpreter's whole start-up (zenoh, pydantic, the agents) inside a round trip.
    """
    gc.collect()
    gc.freeze()


def make_keys(directory: Path) -> None:
    """Both platforms' key pairs and the federation's trust file, as `agents.keys` makes them."""
    trust = TrustStore(FEDERATION)
    for platform in (HERE, THERE):
        pair = KeyPair.generate(platform)
        pair.save(directory)
        trust.add(platform, pair.public_key)
    trust.save(directory / "trust.json")


def interface(keydir: Path, *, encrypt: bool = True) -> InterfaceAgent:
    """This platform's Interface Agent (authentication, encryption and audit on: the defaults)."""
    return InterfaceAgent(
        KeyPair.load(keydir / f"{HERE}.key"),
        TrustStore.load(keydir / "trust.json"),
        policy=SecurityPolicy(encrypt=encrypt),
    )


def install(keydir: Path) -> None:
    """Our packages, compiled, where `node` runs them from (``keydir``'s ``site``).

    As an installed node has them: compiling ~70 modules from source (when
    ``PYTHONDONTWRITEBYTECODE`` keeps the tree free of bytecode) would cost every spawn
    ~0.5 s of its start to ready, which the bare zenoh node does not pay.
    """
    installed(keydir / SITE)


def node(kind: str, config: dict[str, Any], keydir: Path, *, encrypt: bool = True) -> Child:
    """The remote platform's process (not started); from the compiled copy once `install`-ed."""
    args = (kind, config, str(keydir), THERE, FEDERATION)
    site = keydir / SITE
    return Child(
        functools.partial(node_main, encrypt=encrypt),
        args,
        f"acl-node-{kind}",
        path=[str(site)] if site.is_dir() else [],
    )


class AskerSide(NamedTuple):
    """The asking platform of a round-trip benchmark, and the config its node connects with."""

    transport: ZenohTransport
    host: AgentPlatform
    asker: Agent
    presence: Subscription[Presence]
    node_config: dict[str, Any]


@contextlib.asynccontextmanager
async def asker_side(keydir: Path, *, encrypt: bool = True) -> AsyncIterator[AskerSide]:
    """The asking platform over zenoh on loopback, its ``asker`` and a watch for the node.

    ``node_config`` is the zenoh config of a node (`node`) that connects to it.
    """
    port = free_tcp_port()
    node_config = ZenohConfig.loopback(free_tcp_port(), connect=[port]).model_dump()
    async with (
        ZenohTransport(ZenohConfig.loopback(port)) as transport,
        AgentPlatform(
            HERE, transport, federation=FEDERATION, channel=interface(keydir, encrypt=encrypt)
        ) as host,
    ):
        asker = await host.add(Agent("asker"))
        presence = await transport.watch_presence(host.key("alive", THERE))
        yield AskerSide(transport, host, asker, presence, node_config)


async def wait_alive(presence: Subscription[Presence], child: Child, alive: bool) -> None:
    """Until the node's liveliness token appears (or goes); ChildFailed if it dies first."""
    deadline = time.monotonic() + START_TIMEOUT
    while True:
        try:
            p = await presence.get(timeout=0.1)
        except TimeoutError:
            if alive:
                child.check()
            if time.monotonic() > deadline:
                raise ChildFailed(
                    f"{child.name}: presence did not become alive={alive} in {START_TIMEOUT:g} s"
                ) from None
            continue
        if p.alive == alive:
            return


async def first_reply(asker: Agent, child: Child) -> float:
    """Seconds from the child's spawn to the first inform answering a gateway request."""
    deadline = time.monotonic() + START_TIMEOUT
    while True:
        try:
            answer = await request(asker, GATEWAY, QUERY, ontology="dyknow", timeout=1.0)
        except NOT_READY as exc:
            child.check()
            if time.monotonic() > deadline:
                raise ChildFailed(
                    f"{child.name} did not answer in {START_TIMEOUT:g} s: {exc}"
                ) from exc
            await asyncio.sleep(0.002)
            continue
        elapsed = time.perf_counter() - child.started
        check_answer(answer)
        return elapsed


def check_answer(answer: Any) -> None:
    """The gateway's answer must be the latest sample of the label, or nothing counts."""
    if not (isinstance(answer, dict) and answer.get("label") == LABEL and answer.get("samples")):
        raise AssertionError(f"unexpected answer from {GATEWAY}: {answer!r}")


async def round_trips(asker: Agent, n: int, what: str) -> list[float]:
    """``n`` request → inform round trips to the gateway, each in ms."""
    out: list[float] = []
    perf = time.perf_counter
    for i in range(n):
        t = perf()
        await request(asker, GATEWAY, QUERY, ontology="dyknow", timeout=5.0)
        out.append((perf() - t) * 1e3)
        if i and i % 1000 == 0:
            progress(f"{what}: {i}/{n}")
    return out


async def control(asker: Agent, op: str, timeout: float = 10.0, **fields: Any) -> Any:
    """Ask the node's control agent to do ``op``."""
    return await request(
        asker, CONTROL, {"op": op, **fields}, ontology=CONTROL_ONTOLOGY, timeout=timeout
    )


async def control_retrying(asker: Agent, op: str, *, attempts: int, timeout: float) -> Any:
    """``control`` asked again after a lost request or answer (bounded: attempts x timeout)."""
    for attempt in range(1, attempts + 1):
        try:
            return await control(asker, op, timeout=timeout)
        except ReplyTimeout:
            progress(f"control {op!r}: no answer in {timeout:g} s (try {attempt}/{attempts})")
    raise RuntimeError(f"control {op!r} unanswered after {attempts} tries of {timeout:g} s")


def flood_content(asker: Agent) -> Callable[[int], Any]:
    """The flood's content for message ``i``, padded so the ACL JSON is about ACL_BYTES."""

    def content(i: int, pad: str = "") -> dict[str, Any]:
        return {"seq": i, "speed": 12.5, "pad": pad}

    probe = asker.message(Performative.INFORM, SINK, content(10**5), ontology=FLOOD_ONTOLOGY)
    pad = "x" * max(0, ACL_BYTES - len(probe.to_json()))
    return lambda i: content(i, pad)


class Flood(TypedDict):
    """What one ``flood`` delivered, how fast, and at what CPU on each side."""

    sent: int
    received: int
    inbox_dropped: int
    mailbox_full: int
    rate_limited: int
    rate: float
    sent_rate: float
    recv_rate: float
    sender_cpu_us: float
    sender_loop_us: float
    node_cpu_us: float
    node_loop_us: float
    gc_share: float
    gc_full: int
    gc_by_gen: list[tuple[int, float]]  # per generation: (collections, ms collecting)


async def flood(asker: Agent, n: int) -> Flood:
    """Send ``n`` informs to the sink as fast as the stack takes them; what arrived, how fast.

    ``rate`` is end to end: messages delivered to the sink over the time from our first
    send to its last delivery (``time.monotonic`` is one clock for both processes), so it
    is bounded by the slower of the two sides; ``sent_rate`` and ``recv_rate`` (first to
    last delivery) tell which one that is. CPU per message is each whole process's
    (zenoh's threads included) over the flood.
    """
    await control(asker, "reset")
    content = flood_content(asker)
    message, send = asker.message, asker.send
    inform = Performative.INFORM
    cpu0, main0 = time.process_time(), time.thread_time()
    t0 = time.monotonic()
    for i in range(n):
        await send(message(inform, SINK, content(i), ontology=FLOOD_ONTOLOGY))
    sent_s = time.monotonic() - t0
    sender_cpu, sender_main = time.process_time() - cpu0, time.thread_time() - main0
    # The count request queues behind the flood on the node's inbox: its answer comes once
    # the node has worked through what reached it (what was dropped never will). zenoh
    # drops under congestion (DROP: a frozen peer must not stall us), and the request
    # itself can be the message dropped: ask again rather than wait for ever.
    counted = await control_retrying(asker, "count", attempts=12, timeout=10.0)
    got = counted["n"]
    if not got:
        raise RuntimeError(f"none of the {n:,} informs reached {SINK}")
    recv_s = max(counted["t1"] - counted["t0"], 1e-9)
    return {
        "sent": n,
        "received": got,
        "inbox_dropped": counted["inbox_dropped"],
        "mailbox_full": counted["mailbox_full"],
        "rate_limited": counted["rate_limited"],
        "rate": got / max(counted["t1"] - t0, 1e-9),
        "sent_rate": n / sent_s,
        "recv_rate": got / recv_s,
        "sender_cpu_us": sender_cpu / n * 1e6,
        "sender_loop_us": sender_main / n * 1e6,
        "node_cpu_us": counted["cpu_s"] / got * 1e6,
        "node_loop_us": counted["main_s"] / got * 1e6,
        "gc_share": sum(counted["gc_s"]) / max(counted["main_s"], 1e-9),
        "gc_full": counted["gc_runs"][2],
        "gc_by_gen": [
            (runs, secs * 1e3)
            for runs, secs in zip(counted["gc_runs"], counted["gc_s"], strict=True)
        ],
    }


# --------------------------------------------------------------------------- zenoh


def bare_ready(prefix: str) -> tuple[float, float, dict[str, float]]:
    """A bare zenoh process: seconds from spawn to its first get answered, idle RSS, marks."""
    port, child_port = free_tcp_port(), free_tcp_port()
    with zenoh.open(_zenoh_raw._config([f"tcp/127.0.0.1:{port}"], [])) as s:
        alive = threading.Event()
        watcher = s.liveliness().declare_subscriber(
            f"{prefix}/alive",
            lambda sample: alive.set() if sample.kind == zenoh.SampleKind.PUT else None,
        )
        args = (f"tcp/127.0.0.1:{child_port}", f"tcp/127.0.0.1:{port}", prefix)
        with Child(bare_zenoh_main, args, "bare-zenoh").start() as child:
            deadline = time.monotonic() + START_TIMEOUT
            while not alive.wait(0.1):
                child.check()
                if time.monotonic() > deadline:
                    raise ChildFailed(f"bare zenoh node not alive in {START_TIMEOUT:g} s")
            while not [r for r in s.get(f"{prefix}/ready", timeout=1.0) if r.ok is not None]:
                child.check()
                if time.monotonic() > deadline:
                    raise ChildFailed(f"bare zenoh node did not answer in {START_TIMEOUT:g} s")
                time.sleep(0.002)
            ready = time.perf_counter() - child.started
            marks = child.wait_report("ready", START_TIMEOUT)["marks"]
            time.sleep(IDLE_S)
            rss = child.rss_mb()
            marks = {k: (v - child.started_wall) * 1e3 for k, v in marks.items()}
        watcher.undeclare()
    return ready, rss, marks


async def zenoh_phase(keydir: Path) -> dict[str, Any]:
    """Node ready/RSS rounds, then round trips and floods, each beside raw zenoh."""
    res: dict[str, Any] = {
        "ready": [],
        "rss": [],
        "bare_ready": [],
        "bare_rss": [],
        "marks": [],
        "bare_marks": [],
        "rtt": [],
        "raw": [],
        "flood": [],
    }
    async with asker_side(keydir) as side:
        _, host, asker, presence, child_config = side
        the_node: Child | None = None
        try:
            for i in range(READY_REPEAT):
                progress(f"node start-to-ready, spawn {i + 1}/{READY_REPEAT}: bare zenoh")
                prefix = f"bench/bare/{uuid.uuid4().hex[:8]}"
                ready, rss, marks = await asyncio.to_thread(bare_ready, prefix)
                res["bare_ready"].append(ready)
                res["bare_rss"].append(rss)
                res["bare_marks"].append(marks)
                progress(f"node start-to-ready, spawn {i + 1}/{READY_REPEAT}: our node")
                child = node("zenoh", child_config, keydir).start()
                try:
                    await wait_alive(presence, child, True)
                    res["ready"].append(await first_reply(asker, child))
                    got = await asyncio.to_thread(child.wait_report, "ready", START_TIMEOUT)
                    res["responder"] = got["responder"]
                    res["marks"].append(
                        {k: (v - child.started_wall) * 1e3 for k, v in got["marks"].items()}
                    )
                    await asyncio.sleep(IDLE_S)
                    res["rss"].append(child.rss_mb())
                except BaseException:
                    await asyncio.to_thread(child.close)
                    raise
                if i < READY_REPEAT - 1:
                    await asyncio.to_thread(child.close)
                    await wait_alive(presence, child, False)
                else:
                    the_node = child  # the last one stays for the round trips
            assert the_node is not None
            progress(f"zenoh round trips: warm-up ({WARMUP})")
            await round_trips(asker, WARMUP, "warm-up")
            settle_gc()
            for r in range(ROUNDS):
                progress(f"round {r + 1}/{ROUNDS}: raw zenoh ping-pong, get, one-way")
                res["raw"].append(
                    await asyncio.to_thread(
                        _zenoh_raw.measure,
                        round_trips=N_RTT,
                        flood=RAW_FLOOD,
                        payload=ACL_BYTES,
                    )
                )
                progress(f"round {r + 1}/{ROUNDS}: ours, {N_RTT} round trips")
                res["rtt"].append(summary(await round_trips(asker, N_RTT, "round trips")))
                progress(f"round {r + 1}/{ROUNDS}: ours, {N_FLOOD:,} informs one way")
                res["flood"].append(await flood(asker, N_FLOOD))
            await asyncio.sleep(IDLE_S)
            res["rss_after"] = the_node.rss_mb()
            res["stats"] = {
                "audit": dict(host.channel.audit.counts)
                if isinstance(host.channel, InterfaceAgent)
                else {},
                "platform": host.stats,
            }
        finally:
            if the_node is not None:
                await asyncio.to_thread(the_node.close)
    return res


# --------------------------------------------------------------------------- mqtt


async def mqtt_pingpong(host: str, port: int, n: int, payload: int = ACL_BYTES) -> list[float]:
    """Raw aiomqtt ping-pong through the broker with the echo child: ``n`` round trips in ms."""
    body = b"x" * payload
    async with aiomqtt.Client(
        host,
        port,
        identifier=f"raw-ping-{uuid.uuid4().hex[:8]}",
        protocol=aiomqtt.ProtocolVersion.V5,
    ) as client:
        await client.subscribe("raw/pong")
        messages = client.messages
        out: list[float] = []
        perf = time.perf_counter
        for i in range(WARMUP + n):
            t = perf()
            await client.publish("raw/ping", body)
            async with asyncio.timeout(5):
                await anext(messages)
            if i >= WARMUP:
                out.append((perf() - t) * 1e3)
    return out


async def mqtt_phase(keydir: Path, host: str, port: int) -> dict[str, Any]:
    """Round trips over MQTT, interleaved with raw aiomqtt ping-pong through the same broker."""
    res: dict[str, Any] = {"rtt": [], "raw": []}
    config = MqttConfig(host=host, port=port)
    child_config = MqttConfig(host=host, port=port).model_dump(mode="json")
    transport: Transport = MqttTransport(config)
    async with (
        transport,
        AgentPlatform(
            HERE, transport, federation=FEDERATION, channel=interface(keydir)
        ) as platform,
    ):
        asker = await platform.add(Agent("asker"))
        presence = await transport.watch_presence(platform.key("alive", THERE))
        with node("mqtt", child_config, keydir).start() as child:
            await wait_alive(presence, child, True)
            # over MQTT a query waits its whole timeout: the first request pays for the
            # key exchange (2 s), the warm-up absorbs it
            res["ready"] = await first_reply(asker, child)
            progress(f"mqtt round trips: warm-up ({WARMUP})")
            await round_trips(asker, WARMUP, "warm-up")
            with Child(mqtt_echo_main, (host, port), "mqtt-echo").start() as echo:
                await asyncio.to_thread(echo.wait_report, "ready", START_TIMEOUT)
                for r in range(ROUNDS):
                    progress(f"round {r + 1}/{ROUNDS}: raw aiomqtt ping-pong")
                    res["raw"].append(summary(await mqtt_pingpong(host, port, N_RTT)))
                    progress(f"round {r + 1}/{ROUNDS}: ours over mqtt, {N_RTT} round trips")
                    res["rtt"].append(summary(await round_trips(asker, N_RTT, "round trips")))
    return res


# --------------------------------------------------------------------------- report


def _best(rounds: list[dict[str, float]], key: str, *, higher: bool = False) -> float:
    values = [r[key] for r in rounds]
    return max(values) if higher else min(values)


def print_zenoh(z: dict[str, Any]) -> None:
    """The zenoh detail and its BENCH lines."""
    print(f"responder: {z['responder']}; event loop of both agent sides: {event_loop_name()}")
    print(f"round trips over zenoh, {N_RTT} per round after {WARMUP} warm-up, ms:")
    for r in range(ROUNDS):
        raw = z["raw"][r]
        print(_line(f"round {r + 1} ours (acl)", z["rtt"][r]))
        print(
            f"  {'round ' + str(r + 1) + ' zenoh get':<22} median {raw['get_median']:.3f}  "
            f"p99 {raw['get_p99']:.3f} ms"
        )
        print(
            f"  {'round ' + str(r + 1) + ' zenoh ping':<22} median {raw['ping_median']:.3f}  "
            f"p99 {raw['ping_p99']:.3f} ms"
        )
    ours_med, ours_p99 = _best(z["rtt"], "median"), _best(z["rtt"], "p99")
    get_med, get_p99 = _best(z["raw"], "get_median"), _best(z["raw"], "get_p99")
    ping_med, ping_p99 = _best(z["raw"], "ping_median"), _best(z["raw"], "ping_p99")
    print(f"one-way, {N_FLOOD:,} informs of {ACL_BYTES} B JSON per round (raw: {RAW_FLOOD:,}):")
    for r in range(ROUNDS):
        f, raw = z["flood"][r], z["raw"][r]
        lost = f["sent"] - f["received"]
        in_zenoh = lost - f["inbox_dropped"] - f["mailbox_full"] - f["rate_limited"]
        print(
            f"  round {r + 1}: ours {fmt(f['rate'])} msgs/s end to end, "
            f"{f['received']:,}/{f['sent']:,} delivered; lost: {f['inbox_dropped']:,} by the "
            f"node's full inbox, {f['mailbox_full']:,} by the full mailbox, "
            f"{f['rate_limited']:,} by its rate limit, {in_zenoh:,} before "
            f"the node saw them (zenoh's congestion control DROP)"
        )
        print(
            f"           sender {fmt(f['sent_rate'])}/s at {f['sender_cpu_us']:.0f} µs CPU/msg"
            f" ({f['sender_loop_us']:.0f} on its loop thread); node {fmt(f['recv_rate'])}/s at"
            f" {f['node_cpu_us']:.0f} µs CPU/msg ({f['node_loop_us']:.0f} on its loop thread,"
            f" {f['gc_share'] * 100:.0f}% of that in GC, {f['gc_full']} full collections);"
            f" raw zenoh {fmt(raw['oneway_rate'])}/s"
        )
    ours_rate = _best(z["flood"], "rate", higher=True)
    raw_rate = _best(z["raw"], "oneway_rate", higher=True)
    print(f"node start to ready, {READY_REPEAT} spawns each, s; idle RSS, MB:")
    for i in range(READY_REPEAT):
        m, b = z["marks"][i], z["bare_marks"][i]
        steps = " ".join(f"{k}={v:.0f}" for k, v in m.items())
        print(
            f"  spawn {i + 1}: ours {z['ready'][i]:.3f} s {z['rss'][i]:.1f} MB "
            f"(ms after spawn: {steps}, first inform)"
        )
        print(
            f"           bare zenoh {z['bare_ready'][i]:.3f} s {z['bare_rss'][i]:.1f} MB "
            f"(ms after spawn: {' '.join(f'{k}={v:.0f}' for k, v in b.items())}, first get)"
        )
    print(f"  our node after the load: {z['rss_after']:.1f} MB")
    print(f"  this side: audit {z['stats']['audit']}, {z['stats']['platform']}")
    report("acl-rtt-median", ours_med, "zenoh-get", get_med, "ms", better="lower")
    report("acl-rtt-p99", ours_p99, "zenoh-get", get_p99, "ms", better="lower")
    report("acl-rtt-median-vs-pingpong", ours_med, "zenoh-pingpong", ping_med, "ms", better="lower")
    report("acl-rtt-p99-vs-pingpong", ours_p99, "zenoh-pingpong", ping_p99, "ms", better="lower")
    report("acl-throughput", ours_rate, "zenoh-raw", raw_rate, "msgs/s", better="higher")
    report(
        "node-ready",
        statistics.median(z["ready"]),
        "bare-zenoh",
        statistics.median(z["bare_ready"]),
        "s",
        better="lower",
    )
    report(
        "node-rss",
        statistics.median(z["rss"]),
        "bare-zenoh",
        statistics.median(z["bare_rss"]),
        "MB",
        better="lower",
    )


def print_mqtt(m: dict[str, Any]) -> None:
    """The MQTT detail and its BENCH lines."""
    print(f"round trips over mqtt (mosquitto on loopback), {N_RTT} per round, ms:")
    for r in range(ROUNDS):
        print(_line(f"round {r + 1} ours (acl)", m["rtt"][r]))
        print(_line(f"round {r + 1} aiomqtt ping", m["raw"][r]))
    print(f"  first request answered {m['ready']:.2f} s after the node's spawn (key exchange)")
    report(
        "acl-rtt-mqtt-median",
        _best(m["rtt"], "median"),
        "mqtt-raw",
        _best(m["raw"], "median"),
        "ms",
        better="lower",
    )
    report(
        "acl-rtt-mqtt-p99",
        _best(m["rtt"], "p99"),
        "mqtt-raw",
        _best(m["raw"], "p99"),
        "ms",
        better="lower",
    )


ENC_ROUNDS = 4
N_RTT_ENC = 1000


async def encryption_phase(keydir: Path) -> dict[str, list[dict[str, float]]]:
    """Round trips with encrypted and with MAC-only sessions, both sides new each time."""
    res: dict[str, list[dict[str, float]]] = {"encrypted": [], "plain": []}
    kinds = [("encrypted", True), ("plain", False)]
    for r in range(ENC_ROUNDS):
        # each kind goes first every other round: neither gets the fresher machine
        for kind, encrypt in kinds if r % 2 == 0 else kinds[::-1]:
            progress(f"encryption round {r + 1}/{ENC_ROUNDS}: {kind} sessions, {N_RTT_ENC} trips")
            async with asker_side(keydir, encrypt=encrypt) as side:
                _, _, asker, presence, child_config = side
                child = node("zenoh", child_config, keydir, encrypt=encrypt).start()
                try:
                    await wait_alive(presence, child, True)
                    await first_reply(asker, child)
                    await round_trips(asker, WARMUP, "warm-up")
                    res[kind].append(summary(await round_trips(asker, N_RTT_ENC, kind)))
                finally:
                    await asyncio.to_thread(child.close)
    return res


def print_encryption(e: dict[str, list[dict[str, float]]]) -> None:
    """The encrypted/plain round trips and their BENCH line."""
    print(f"round trips over zenoh, encrypted vs MAC-only sessions, {N_RTT_ENC} per round, ms:")
    for r in range(ENC_ROUNDS):
        print(_line(f"round {r + 1} encrypted", e["encrypted"][r]))
        print(_line(f"round {r + 1} plain", e["plain"][r]))
    enc = statistics.median(s["median"] for s in e["encrypted"])
    plain = statistics.median(s["median"] for s in e["plain"])
    report("acl-rtt-median-encrypted", enc, "plain", plain, "ms", better="lower")


def osbrain_phase() -> dict[str, list[float]]:
    """osBrain's round trips and flood, ROUNDS rounds, in a child of its own (osBrain forks)."""
    progress(f"osBrain: {ROUNDS} rounds of {N_RTT} REQ-REP round trips and {N_FLOOD:,} pushes")
    pad = "x" * max(0, ACL_BYTES - len('{"seq":100000,"speed":12.5,"pad":""}'))
    child = Child(osbrain_main, (N_RTT, WARMUP, ROUNDS, N_FLOOD, pad), "osbrain")
    child.proc.daemon = False  # osBrain's agents are its children: a daemon may have none
    with child.start():
        result: dict[str, list[float]] = child.wait_report("result", 300)
    return result


def print_osbrain(o: dict[str, list[float]], z: dict[str, Any]) -> None:
    """osBrain's detail and the two BENCH lines against it."""
    print("osBrain 0.6.5 (ZeroMQ on loopback TCP, no security), two agent processes:")
    for r in range(ROUNDS):
        print(
            f"  round {r + 1}: REQ-REP median {o['rtt'][r]:.3f} p99 {o['p99'][r]:.3f} ms; "
            f"PUSH-PULL {fmt(o['flood'][r])} msgs/s"
        )
    report(
        "acl-throughput-vs-osbrain",
        _best(z["flood"], "rate", higher=True),
        "osbrain",
        max(o["flood"]),
        "msgs/s",
        better="higher",
    )
    report(
        "acl-rtt-median-vs-osbrain",
        _best(z["rtt"], "median"),
        "osbrain",
        min(o["rtt"]),
        "ms",
        better="lower",
    )


def run() -> None:
    """Measure the zenoh figures, then the MQTT ones; print the detail and the BENCH lines."""
    mosquitto_executable()  # fail now, not after a minute of zenoh, when it is missing
    with tempfile.TemporaryDirectory(prefix="bench-acl-") as tmp:
        keydir = Path(tmp)
        make_keys(keydir)
        install(keydir)
        o = osbrain_phase()
        z = _run_async(zenoh_phase(keydir))
        print_zenoh(z)
        print_osbrain(o, z)
        progress("the floor: the round trip from the design's blocks alone")
        print_floor(measure_floor(ours=True))
        e = _run_async(encryption_phase(keydir))
        print_encryption(e)
        progress("starting mosquitto")
        with mosquitto() as (host, port):
            m = _run_async(mqtt_phase(keydir, host, port))
        print_mqtt(m)


def _run_async(coro: Awaitable[Any]) -> Any:
    async def main() -> Any:
        return await coro

    return run_loop(main())


if __name__ == "__main__":
    if "--profile" in sys.argv[1:]:
        from bench._acl_profile import profile

        profile()
    else:
        run()
