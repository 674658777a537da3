"""Key-exchange floods and re-key cues from outsiders, against real processes over zenoh.

A victim platform (``uav-v``) and a member (``uav-m``) run in spawned processes; an
attacker process with a plain zenoh session (no key of the federation) floods the
victim's ``kx/uav-v`` queryable with junk, untrusted and forged handshake requests as fast
as it can (about 10 000/s), or its ``acl/uav-v`` inbox with envelopes claiming to be the
member's on sessions that do not exist. The member's request round trips stay within
their bound during the flood; the victim sheds the flood before any signature check,
counts it and audits it in a few records; junk envelopes make it re-key at most once
per ``rehandshake_interval``.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import math
import multiprocessing
import os
import statistics
import time
import uuid
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import orjson
import pytest

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    ServiceDescription,
    on_request,
    request,
    wire_key,
)
from agents._interface import InterfaceAgent
from agents._kxgate import KxGate, KxLimit
from agents._security import Handshake, KeyPair, TrustStore
from agents.keys import gen_keys, trust_keys
from agents.transports import MemoryHub, ZenohConfig, ZenohTransport, free_tcp_port

VICTIM, MEMBER, ABSENT = "uav-v", "uav-m", "uav-q"  # uav-q: trusted, never runs
ECHO = f"echo@{VICTIM}"
START = 30.0  # a spawned interpreter imports zenoh and pydantic: seconds when loaded
WAIT = 15.0  # the bound on any other wait
PACE_N, PACE_PERIOD = 150, 0.02  # the member's requests: 50/s for 3 s, calm then flooded
FLOOD_RATE, FLOOD_MAX, FLOOD_SECONDS = 10_000.0, 250_000, 25.0
# The member's p99 bound during the flood, on loopback. Calm, its p99 is ~2 ms here; a
# victim that verified every forged signature reached ~1.2 s. Scaled by load (below).
P99_MS = 20.0


def latency_bound() -> float:
    """P99_MS, scaled up when the machine is oversubscribed (load above its CPU count).

    The three processes of this test keep about two cores busy themselves; a load above
    the CPU count means others share them, and every wall-clock wait stretches with it.
    """
    return P99_MS * max(1.0, os.getloadavg()[0] / (os.cpu_count() or 1))


def p99(ms: list[float]) -> float:
    """The 99th percentile (nearest rank)."""
    s = sorted(ms)
    return s[min(len(s) - 1, int(0.99 * len(s)))]


def figures(ms: list[float]) -> str:
    """p50 and p99 of round trips, for printing."""
    return f"p50 {statistics.median(ms):.2f} ms, p99 {p99(ms):.2f} ms (n={len(ms)})"


def recv(conn: Connection, what: str, timeout: float = WAIT) -> Any:
    """The next message on ``conn``; fails naming ``what`` after ``timeout`` s."""
    if not conn.poll(timeout):
        raise AssertionError(f"timed out waiting for {what}")
    return conn.recv()


# -- the victim and the member (our library) ---------------------------------------------------


class Echo(Agent):
    """Answers ``demo`` requests of the federation's platforms."""

    def __init__(self) -> None:
        super().__init__("echo")

    async def setup(self) -> None:
        """Offer a protected service: other platforms of the federation may use it."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(name="echo", type="demo", provider=self.aid, visibility="protected")
        )

    @on_request("demo")
    async def _echo(self, message: ACLMessage) -> Any:
        return {"echo": message.content}


def node_main(
    role: str, config: dict[str, Any], fed: str, keys: str, trust: str, conn: Any
) -> None:
    """A spawned platform: the victim (``uav-v``, serves echo) or the member (``uav-m``)."""
    asyncio.run(_node(role, config, fed, Path(keys), Path(trust), conn))


async def _node(
    role: str, config: dict[str, Any], fed: str, keys: Path, trust: Path, conn: Connection
) -> None:
    channel = InterfaceAgent(
        KeyPair.load(keys / f"{role}.key"), TrustStore.load(trust), audit_interval=0.1
    )
    async with (
        ZenohTransport(ZenohConfig.model_validate(config)) as t,
        AgentPlatform(role, t, federation=fed, channel=channel) as pf,
    ):
        asker = await pf.add(Echo() if role == VICTIM else Agent("asker"))
        if role == MEMBER:  # the victim's inbox and kx are served once its token shows
            watch = await t.watch_presence(pf.key("alive", VICTIM))
            async with watch, asyncio.timeout(START):
                while not (await watch.get()).alive:
                    pass
        conn.send("ready")
        while True:
            cmd = await asyncio.to_thread(conn.recv)
            if cmd == "stop":
                return
            if cmd == "report":
                gate = channel.kx_gate
                assert gate is not None
                conn.send(
                    {
                        "cpu": time.process_time(),
                        "kx_shed": pf.stats.kx_shed,
                        "shed": dict(gate.shed),
                        "admitted": gate.admitted,
                        "rehandshakes": pf.stats.rehandshakes,
                        "suppressed": pf.stats.rehandshakes_suppressed,
                        "unauthenticated": pf.stats.unauthenticated,
                        "sessions": sorted(channel.sessions.peers()),
                        "records": [r for r in channel.audit.records if r["verdict"] == "dropped"],
                    }
                )
            elif cmd == "pace":  # the member: requests one after the other, round trips
                conn.send(await pace(asker))


async def pace(asker: Agent) -> list[float]:
    """PACE_N requests to the victim's echo, one every PACE_PERIOD s; round trips in ms."""
    rtts: list[float] = []
    start = time.monotonic()
    for i in range(PACE_N):
        t0 = time.monotonic()
        answer = await request(asker, ECHO, {"n": i}, ontology="demo", timeout=WAIT)
        rtts.append((time.monotonic() - t0) * 1000)
        assert answer == {"echo": {"n": i}}
        await asyncio.sleep(max(0.0, start + (i + 1) * PACE_PERIOD - time.monotonic()))
    return rtts


# -- the attacker: a plain zenoh session, no key of the federation -------------------------------


def attacker_main(endpoint: str, key: str, payloads: list[bytes], conn: Any) -> None:
    """Send ``payloads`` round and round to ``key`` at FLOOD_RATE until told to stop."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", orjson.dumps([endpoint]).decode())
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    try:
        conn.send("ready")
        conn.recv()  # go
        kind = "put" if "/acl/" in key else "get"
        publisher = session.declare_publisher(key) if kind == "put" else None

        sent, start, n = 0, time.monotonic(), len(payloads)
        chunk = int(FLOOD_RATE / 100)  # every 10 ms
        while sent < FLOOD_MAX and time.monotonic() - start < FLOOD_SECONDS:
            if conn.poll():
                break  # told to stop
            for _ in range(chunk):
                payload = payloads[sent % n]
                if publisher is not None:
                    publisher.put(payload)
                else:
                    # zenoh's default handler: a Python callback would cost ~10x per query
                    session.get(key, payload=payload, timeout=1.0)
                sent += 1
            time.sleep(max(0.0, sent / FLOOD_RATE - (time.monotonic() - start)))
        conn.send((sent, time.monotonic() - start))
    finally:
        session.close()


def kx_payloads(keydir: Path, fed: str, trust: TrustStore) -> list[bytes]:
    """Handshake requests to the victim: forged under trusted names, untrusted, junk.

    Forged: signed with a key of the attacker's own under a trusted name (the member's,
    or uav-q's, trusted but never running), with fresh timestamps and fresh nonces:
    they pass every check but the signature. Untrusted: a well-formed request of uav-x.
    Junk: random bytes and half-made JSON. One forged request is repeated (a replay).
    """
    out: list[bytes] = []
    for name in (MEMBER, ABSENT, "uav-x"):
        mine = KeyPair.generate(name)
        own = TrustStore(fed, {name: mine.public_key, VICTIM: trust.public_key(VICTIM)})
        hs = Handshake(mine, own)
        out += [hs.initiate(VICTIM) for _ in range(300)]
    replayed = out[0]
    out += [replayed] * 100
    out += [os.urandom(200) for _ in range(150)]
    out += [b'{"v":1,"kx":"init","from":"uav-m","to":"uav-v"}'] * 150
    order = list(range(len(out)))
    # interleaved, so every kind arrives all along the flood
    order.sort(key=lambda i: (i * 7919) % len(out))
    return [out[i] for i in order]


def acl_payloads(fed: str) -> list[bytes]:
    """Envelopes claiming to be the member's, on session ids that do not exist."""
    now = int(time.time() * 1000)
    return [
        orjson.dumps(
            {
                "v": 1,
                "from": MEMBER,
                "to": VICTIM,
                "sid": base64.urlsafe_b64encode(os.urandom(16)).rstrip(b"=").decode(),
                "ts_ms": now,
                "n": i + 1,
                "body": '{"performative":"inform"}',
                "mac": base64.b64encode(os.urandom(32)).decode(),
            }
        )
        for i in range(2000)
    ]


class Federation:
    """The victim, the member and the attacker as spawned processes, with their pipes."""

    def __init__(self, tmp_path: Path) -> None:
        self.fed = f"kx-{uuid.uuid4().hex[:8]}"
        self.keydir, self.trust_file = tmp_path / "keys", tmp_path / "trust.json"
        trust_keys(
            self.trust_file,
            [gen_keys(n, self.keydir)[2] for n in (VICTIM, MEMBER, ABSENT)],
            federation=self.fed,
        )
        self.trust = TrustStore.load(self.trust_file)
        self.port = free_tcp_port()
        self.ctx = multiprocessing.get_context("spawn")
        self.procs: list[Any] = []

    def node(self, role: str, listen: int, connect: list[int]) -> Connection:
        """Start platform ``role``; its pipe, once it says it is ready."""
        here, there = self.ctx.Pipe()
        config = ZenohConfig.loopback(listen, connect=connect).model_dump()
        proc = self.ctx.Process(
            target=node_main,
            args=(role, config, self.fed, str(self.keydir), str(self.trust_file), there),
            name=f"kx-{role}",
        )
        proc.start()
        self.procs.append(proc)
        return here

    def attacker(self, what: str, payloads: list[bytes]) -> Connection:
        """Start the attacker on ``what`` (kx or acl) of the victim."""
        here, there = self.ctx.Pipe()
        proc = self.ctx.Process(
            target=attacker_main,
            args=(f"tcp/127.0.0.1:{self.port}", wire_key(self.fed, what, VICTIM), payloads, there),
            name=f"kx-attacker-{what}",
        )
        proc.start()
        self.procs.append(proc)
        return here

    def close(self, pipes: list[Connection]) -> None:
        """Ask every child to stop, then make sure."""
        for pipe in pipes:
            with contextlib.suppress(OSError):
                pipe.send("stop")
        for proc in self.procs:
            proc.join(timeout=15)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=5)


@pytest.fixture(autouse=True)
def _no_leftover_children() -> Iterator[None]:
    yield
    for proc in multiprocessing.active_children():
        proc.kill()
        proc.join(timeout=5)


def test_kx_flood_is_shed_and_a_member_is_still_served(tmp_path: Path) -> None:
    """10 000 handshake requests/s from an outsider: the member's p99 stays in its bound.

    The victim drops them before any signature check (all but a few per second), counts
    each one and sums them up in a few audit records; its session with the member and
    the member's requests are unaffected.
    """
    f = Federation(tmp_path)
    pipes: list[Connection] = []
    try:
        victim = f.node(VICTIM, f.port, [])
        pipes.append(victim)
        assert recv(victim, "the victim", START) == "ready"
        # a zenoh client: it needs the victim listening
        attacker = f.attacker("kx", kx_payloads(f.keydir, f.fed, f.trust))
        pipes.append(attacker)
        member = f.node(MEMBER, free_tcp_port(), [f.port])
        pipes.append(member)
        assert recv(member, "the member", START) == "ready"
        assert recv(attacker, "the attacker", START) == "ready"
        member.send("pace")
        recv(member, "the member's first requests", WAIT + PACE_N * PACE_PERIOD)
        member.send("pace")  # a second calm run: the first had the key exchange in it
        calm = recv(member, "the member's calm requests", WAIT + PACE_N * PACE_PERIOD)
        victim.send("report")
        cpu0 = recv(victim, "the victim's report")["cpu"]
        attacker.send("go")
        time.sleep(0.5)  # the flood under way
        member.send("pace")
        during = recv(member, "the member's requests during the flood", 3 * WAIT)
        with contextlib.suppress(OSError):  # it may have ended its bounded flood already
            attacker.send("stop")
        sent, seconds = recv(attacker, "the attacker's count")
        victim.send("report")
        cpu = (recv(victim, "the victim's report")["cpu"] - cpu0) / seconds
        time.sleep(1.5)  # the last summary (one per second)
        victim.send("report")
        report = recv(victim, "the victim's report")
        # a machine busy with others' work shows in the calm run first: never bound the
        # flooded run below three times that (without the shedding it is ~600 times)
        bound = max(latency_bound(), 3 * p99(calm))
        ratio = p99(during) / p99(calm)
        print(
            f"\nmember calm:         {figures(calm)}\n"
            f"member during flood: {figures(during)}\n"
            f"attacker: {sent} requests in {seconds:.1f} s ({sent / seconds:.0f}/s); victim "
            f"shed {report['kx_shed']} ({report['shed']}), checked {report['admitted']} "
            f"signatures; victim CPU {cpu:.0%} during the flood; bound {bound:.0f} ms\n"
            f"BENCH kx-flood-member-p99 ours={p99(during):.2f} calm={p99(calm):.2f} "
            f"ratio={ratio:.2f} unit=ms better=lower"
        )
        assert sent / seconds > 5000, "the attacker did not flood"
        assert p99(during) <= bound, figures(during)
        # all but the budget is shed: per trusted name claimed (2/s, burst 10), and the
        # member's name is exempt from the shared budget only (it has a session)
        assert report["admitted"] <= 2 * (10 + 2 * (seconds + 2)) + 20
        assert report["kx_shed"] == sum(report["shed"].values())
        # most of the flood reached the victim (zenoh may drop some on a loaded machine)
        assert report["kx_shed"] >= 0.5 * sent
        for reason in ("untrusted", "malformed", "replayed", "over-peer-budget"):
            assert report["shed"].get(reason, 0) > 0, (reason, report["shed"])
        assert MEMBER in report["sessions"]
        summaries = [r for r in report["records"] if r.get("stage") == "kx-shed"]
        assert summaries, report["records"]
        # one summary a second at most: a flood of requests is not a flood of records
        assert len(summaries) <= seconds + 3
        assert sum(r["count"] for r in summaries) == report["kx_shed"]
        first = summaries[0]
        assert first["verdict"] == "dropped" and first["from"] is None
        assert first["reason"].startswith("key-exchange requests shed: ")
        assert sum(first["by_reason"].values()) == first["count"]
        # a few of them one by one, with why, within the budget of unauthenticated records
        detailed = [r for r in report["records"] if r.get("stage") == "kx"]
        assert any(r["reason"].startswith("untrusted: ") for r in detailed)
        assert len(detailed) <= 20 * (len(summaries) + 1) + report["admitted"]
    finally:
        f.close(pipes)


def test_junk_envelopes_claiming_a_member_rekey_at_most_once_per_interval(
    tmp_path: Path,
) -> None:
    """Envelopes in the member's name on unknown sessions: one re-key per 5 s, the rest counted."""
    f = Federation(tmp_path)
    pipes: list[Connection] = []
    try:
        victim = f.node(VICTIM, f.port, [])
        pipes.append(victim)
        assert recv(victim, "the victim", START) == "ready"
        attacker = f.attacker("acl", acl_payloads(f.fed))
        pipes.append(attacker)
        member = f.node(MEMBER, free_tcp_port(), [f.port])
        pipes.append(member)
        assert recv(member, "the member", START) == "ready"
        assert recv(attacker, "the attacker", START) == "ready"
        member.send("pace")
        recv(member, "the member's requests", START + PACE_N * PACE_PERIOD)
        victim.send("report")
        before = recv(victim, "the victim's report")
        attacker.send("go")
        time.sleep(6.0)
        attacker.send("stop")
        sent, seconds = recv(attacker, "the attacker's count")
        time.sleep(0.5)
        victim.send("report")
        after = recv(victim, "the victim's report")
        member.send("pace")  # and the member is still served
        recv(member, "the member's requests after", WAIT + PACE_N * PACE_PERIOD)
        rekeys = after["rehandshakes"] - before["rehandshakes"]
        suppressed = after["suppressed"] - before["suppressed"]
        print(
            f"\njunk envelopes: {sent} in {seconds:.1f} s; victim re-keyed {rekeys} time(s), "
            f"ignored {suppressed} cue(s); unauthenticated {after['unauthenticated']}"
        )
        assert sent > 1000
        # the interval is 5 s: one at the start, one at most after it
        assert 1 <= rekeys <= 1 + int(seconds / 5.0)
        assert suppressed > 0
        assert rekeys + suppressed <= after["unauthenticated"] - before["unauthenticated"]
        unknown = [
            r
            for r in after["records"]
            if str(r.get("reason")).startswith("unknown-session") and r["from"] == MEMBER
        ]
        assert unknown, after["records"]
    finally:
        f.close(pipes)


# -- the gate on its own, with an explicit clock ------------------------------------------------


class Clock:
    """A monotonic clock the test moves."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def gate_for(limit: KxLimit) -> tuple[KxGate, Clock, dict[str, Handshake]]:
    """A gate for ``uav-v`` trusting uav-m, uav-q and uav-r; forgers' handshakes by name."""
    keys = {n: KeyPair.generate(n) for n in (VICTIM, MEMBER, ABSENT, "uav-r")}
    trust = TrustStore("f", {n: k.public_key for n, k in keys.items()})
    clock = Clock()
    gate = KxGate(Handshake(keys[VICTIM], trust), limit, monotonic=clock)
    forgers = {}
    for name in (MEMBER, ABSENT, "uav-r", "uav-x"):
        mine = KeyPair.generate(name)
        own = TrustStore("f", {name: mine.public_key, VICTIM: keys[VICTIM].public_key})
        forgers[name] = Handshake(mine, own)
    return gate, clock, forgers


def test_gate_budgets_per_claimed_platform_and_shared() -> None:
    """Per-name buckets; names without a session share one; the priority ones do not."""
    limit = KxLimit(per_peer=1, per_peer_burst=3, total=1, total_burst=4, detailed=2)
    gate, clock, forgers = gate_for(limit)

    def admitted(name: str, n: int) -> int:
        return sum(gate.admit(forgers[name].initiate(VICTIM)) for _ in range(n))

    assert admitted(ABSENT, 10) == 3  # its own burst
    assert admitted("uav-r", 10) == 1  # the shared bucket had 4: 3 went to uav-q
    assert gate.shed["over-peer-budget"] == 7 and gate.shed["over-total-budget"] == 9
    gate.priority = frozenset({MEMBER})
    assert admitted(MEMBER, 10) == 3  # exempt from the spent shared bucket
    clock.now += 1.0  # one second: one more each, and one shared
    assert admitted(ABSENT, 5) == 1 and admitted("uav-r", 5) == 0 and admitted(MEMBER, 5) == 1
    assert gate.admitted == 3 + 1 + 3 + 2
    assert sum(gate.shed.values()) == 45 - gate.admitted


def test_gate_drops_junk_replays_and_strangers_without_budget_and_explains_a_few() -> None:
    """Cheap refusals spend no budget; the first few are explained, the rest counted."""
    gate, clock, forgers = gate_for(KxLimit(per_peer=0, per_peer_burst=5, detailed=3))
    request = forgers[MEMBER].initiate(VICTIM)
    assert gate.admit(request)
    assert not gate.admit(request)  # the same request again: before any signature check
    for junk in (b"", b"{", b"[]", os.urandom(64), b"x" * 5000, b'{"v":1,"kx":"init"}'):
        assert not gate.admit(junk)
    stale = orjson.loads(forgers[MEMBER].initiate(VICTIM))
    stale["ts_ms"] -= 120_000
    assert not gate.admit(orjson.dumps(stale))
    assert not gate.admit(forgers["uav-x"].initiate(VICTIM))
    other = orjson.loads(forgers[MEMBER].initiate(VICTIM))
    other["to"] = "uav-r"  # for another platform
    assert not gate.admit(orjson.dumps(other))
    assert gate.admitted == 1
    assert gate.shed == {"replayed": 1, "malformed": 6, "expired": 1, "untrusted": 1,
                         "misdirected": 1}  # fmt: skip
    details, summary = gate.take_report(clock.now)
    assert [d[1].split(":")[0] for d in details] == ["replayed", "malformed", "malformed"]
    assert details[0][0] == MEMBER
    assert summary is not None and summary["count"] == 10 and summary["seconds"] is None
    assert summary["by_reason"] == dict(gate.shed)
    # the next interval's details at once, its summary once the interval is over
    assert not gate.admit(b"{")
    details, summary = gate.take_report(clock.now + 0.5)
    assert [d[1].split(":")[0] for d in details] == ["malformed"] and summary is None
    clock.now += 1.0
    details, summary = gate.take_report(clock.now)
    assert details == [] and summary is not None and summary["count"] == 1
    assert summary["seconds"] == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("per_peer", -1.0, "KxLimit.per_peer: -1.0 is not a finite number >= 0"),
        ("total", math.nan, "KxLimit.total: nan"),
        ("per_peer_burst", 0.5, "KxLimit.per_peer_burst: 0.5 < 1 would refuse every request"),
        ("report_interval", 0, "KxLimit.report_interval: 0 is not > 0"),
        ("detailed", 1.5, "KxLimit.detailed: 1.5 is not an integer"),
    ],
)
def test_bad_kx_limits_are_refused_by_name(field: str, value: Any, words: str) -> None:
    """A wrong setting names the field and the value."""
    with pytest.raises(ValueError, match=words.replace(".", r"\.")):
        KxLimit(**{field: value})


async def test_a_member_agrees_a_session_while_a_forger_floods_in_other_names() -> None:
    """The reserve: forged requests under other trusted names leave a member's exchange be.

    Over a MemoryHub: an outsider floods the victim with forged requests claiming uav-q
    (trusted, not running), far beyond the shared budget; meanwhile the member, alive,
    agrees a new session with the victim, and the victim answers it.
    """
    hub = MemoryHub()
    keys = {n: KeyPair.generate(n) for n in (VICTIM, MEMBER, ABSENT)}
    trust = {n: k.public_key for n, k in keys.items()}
    forger = KeyPair.generate(ABSENT)
    forged = Handshake(forger, TrustStore("f", {ABSENT: forger.public_key, VICTIM: trust[VICTIM]}))
    async with contextlib.AsyncExitStack() as stack, asyncio.timeout(WAIT):
        platforms = {}
        for name in (VICTIM, MEMBER):
            t = await stack.enter_async_context(hub.transport())
            channel = InterfaceAgent(keys[name], TrustStore("f", dict(trust)))
            platforms[name] = await stack.enter_async_context(
                AgentPlatform(name, t, federation="f", channel=channel)
            )
        raw = await stack.enter_async_context(hub.transport())
        victim = platforms[VICTIM].channel
        member = platforms[MEMBER].channel
        assert isinstance(victim, InterfaceAgent) and isinstance(member, InterfaceAgent)
        assert victim.kx_gate is not None
        key = wire_key("f", "kx", VICTIM)
        for _ in range(200):
            assert await raw.query(key, forged.initiate(VICTIM), timeout=1.0) == []
        assert victim.kx_gate.shed["over-peer-budget"] > 150
        await member._agree(VICTIM)  # a fresh exchange, through the gate
        assert MEMBER in victim.sessions.peers()
        assert platforms[VICTIM].stats.kx_shed == sum(victim.kx_gate.shed.values())
