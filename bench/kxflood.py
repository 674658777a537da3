"""The member's request p99 while an outsider floods a platform with key exchanges.

Three spawned processes on loopback zenoh: a victim platform (``uav-v``, an echo agent),
a member (``uav-m``) asking it one request every 20 ms, and an attacker with a plain zenoh
client and no key of the federation sending ~10 000 handshake requests/s to
``kx/uav-v`` (forged under the member's name and under a trusted platform that is not
running, untrusted, replayed, junk). The member's round trips are measured calm, then
during the flood, in the same run; then the same with a victim that does not shed
(``kx_limit=None``), for comparison. ``tests/test_kx_flood.py`` asserts on the same
runs; see docs/security.md, "Key-exchange load shedding".

    BENCH kx-flood-member-p99 ours=<p99 during the flood> calm=<p99 calm> ratio=… unit=ms
    BENCH kx-flood-member-p99-unshed ours=<p99 during, no shedding> calm=<p99 calm> …
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import orjson

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
from agents.transports import (
    Handle,
    QueryFilter,
    QueryHandler,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from bench._flood import (
    ABSENT,
    FLOOD_SECONDS,
    MEMBER,
    START,
    VICTIM,
    WAIT,
    FloodFederation,
    flood_at,
    quick_run,
    recv,
    summed_up,
    zenoh_client,
)

ECHO = f"echo@{VICTIM}"
PACE_N, PACE_PERIOD = 150, 0.02  # the member's requests: 50/s for 3 s, calm then flooded
FLOOD_MAX = 250_000  # requests the attacker sends at most


def p99(ms: list[float]) -> float:
    """The 99th percentile (nearest rank)."""
    s = sorted(ms)
    return s[min(len(s) - 1, int(0.99 * len(s)))]


def figures(ms: list[float]) -> str:
    """p50 and p99 of round trips, for printing."""
    return f"p50 {statistics.median(ms):.2f} ms, p99 {p99(ms):.2f} ms (n={len(ms)})"


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


class CountingZenoh(ZenohTransport):
    """A zenoh transport that counts the queries its handlers got, by kind (kx, watch, df).

    A handler runs on the event loop: what a query costs there, unlike a query shed on
    zenoh's thread. The count is the same on any CPU and however busy the machine.
    """

    def __init__(self, config: ZenohConfig) -> None:
        super().__init__(config)
        self.answered: dict[str, int] = {}

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Serve ``key_expr`` as ZenohTransport does, counting each query the handler gets."""
        answered = self.answered
        kind = key_expr.split("/")[-2]  # dyknow/<federation>/v1/<kind>/<platform>
        answered.setdefault(kind, 0)

        async def counted(key: str, payload: bytes) -> bytes | None:
            answered[kind] += 1
            return await handler(key, payload)

        return await super().serve(key_expr, counted, admit=admit)


def node_main(
    role: str, config: dict[str, Any], fed: str, keys: str, trust: str, conn: Any, shed: bool
) -> None:
    """A spawned platform: the victim (``uav-v``, serves echo) or the member (``uav-m``).

    ``shed`` False: the victim without key-exchange load shedding (for comparison).
    """
    asyncio.run(_node(role, config, fed, Path(keys), Path(trust), conn, shed))


async def _node(
    role: str,
    config: dict[str, Any],
    fed: str,
    keys: Path,
    trust: Path,
    conn: Connection,
    shed: bool,
) -> None:
    channel = InterfaceAgent(
        KeyPair.load(keys / f"{role}.key"),
        TrustStore.load(trust),
        audit_interval=0.1,
        kx_limit=KxLimit() if shed else None,
    )
    async with (
        CountingZenoh(ZenohConfig.model_validate(config)) as t,
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
                gate = channel.kx_gate or KxGate(channel.handshake, KxLimit())  # none: zeros
                conn.send(
                    {
                        "cpu": time.process_time(),
                        "answered": dict(t.answered),
                        "kx_shed": pf.stats.kx_shed,
                        "watch_shed": channel.watch_shed,
                        "df_shed": pf.df.queries_shed if pf.df is not None else 0,
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
            elif cmd == "warm":  # the member: one request, the key exchange in it
                conn.send(await pace(asker, 1))


async def pace(asker: Agent, n: int = PACE_N) -> list[float]:
    """``n`` requests to the victim's echo, one every PACE_PERIOD s; round trips in ms."""
    rtts: list[float] = []
    start = time.monotonic()
    for i in range(n):
        t0 = time.monotonic()
        answer = await request(asker, ECHO, {"n": i}, ontology="demo", timeout=WAIT)
        rtts.append((time.monotonic() - t0) * 1000)
        assert answer == {"echo": {"n": i}}
        await asyncio.sleep(max(0.0, start + (i + 1) * PACE_PERIOD - time.monotonic()))
    return rtts


# -- the attacker: a plain zenoh session, no key of the federation -------------------------------


def attacker_main(endpoint: str, key: str, conn: Any) -> None:
    """Send the payloads `go` hands over round and round to ``key`` at FLOOD_RATE until
    told to stop."""
    session = zenoh_client(endpoint)
    try:
        conn.send("ready")
        go, payloads = conn.recv()
        assert go == "go", go
        n = len(payloads)
        if "/acl/" in key:
            publisher = session.declare_publisher(key)
            flood_at(conn, lambda i: publisher.put(payloads[i % n]), most=FLOOD_MAX)
        else:
            # zenoh's default handler: a Python callback would cost ~10x per query
            flood_at(
                conn,
                lambda i: session.get(key, payload=payloads[i % n], timeout=1.0),
                most=FLOOD_MAX,
            )
    finally:
        session.close()


def go(attacker: Connection, payloads: list[bytes]) -> None:
    """Start the attacker's flood with ``payloads``.

    Made by the caller just before: a forged handshake carries a signed time the victim
    checks against its skew limit, and the calm rounds before a flood take long enough
    to age payloads made at the attacker's spawn past it.
    """
    attacker.send(("go", payloads))


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


class Federation(FloodFederation):
    """The victim, the member and the attacker of a key-exchange flood, with their pipes."""

    prefix = "kx"
    node_main = staticmethod(node_main)

    def attacker(self, what: str) -> Connection:
        """Start the attacker on ``what`` (kx or acl) of the victim; `go` gives it payloads."""
        endpoint = f"tcp/127.0.0.1:{self.port}"
        key = wire_key(self.fed, what, VICTIM)
        return self.spawn(attacker_main, (endpoint, key), f"kx-attacker-{what}")

    def started(
        self, what: str, pipes: list[Connection], *, shed: bool = True
    ) -> tuple[Connection, Connection, Connection]:
        """The victim, the attacker on its ``what`` and the member, all ready; their pipes.

        Each pipe is added to ``pipes`` as soon as its process runs (to be closed). The
        attacker waits for `go` and its payloads.
        """
        victim = self.node(VICTIM, self.port, [], shed=shed)
        pipes.append(victim)
        assert recv(victim, "the victim", START) == "ready"
        # a zenoh client: it needs the victim listening
        attacker = self.attacker(what)
        pipes.append(attacker)
        member = self.node(MEMBER, free_tcp_port(), [self.port])
        pipes.append(member)
        assert recv(member, "the member", START) == "ready"
        assert recv(attacker, "the attacker", START) == "ready"
        return victim, attacker, member


@dataclass
class FloodRun:
    """What one flood measured: the member's round trips (ms), the attacker, the victim."""

    calm: list[float]
    during: list[float]
    sent: int
    seconds: float
    cpu: float  # the victim's CPU during the flood, in cores
    handled: int  # key exchanges that reached the victim's event loop during the flood
    report: dict[str, Any]  # the victim's counters and audit records after it

    def lines(self, name: str = "kx-flood-member-p99") -> str:
        """The figures, and the BENCH line (when the calm run was measured)."""
        r = self.report
        text = (
            f"member during flood: {figures(self.during)}\n"
            f"attacker: {self.sent} requests in {self.seconds:.1f} s "
            f"({self.sent / self.seconds:.0f}/s); victim shed {r['kx_shed']} ({r['shed']}), "
            f"checked {r['admitted']} signatures ({self.handled} on its event loop); "
            f"victim CPU {self.cpu:.0%} during the flood"
        )
        if not self.calm:
            return text
        return (
            f"member calm:         {figures(self.calm)}\n{text}\n"
            f"BENCH {name} ours={p99(self.during):.2f} calm={p99(self.calm):.2f} "
            f"ratio={p99(self.during) / p99(self.calm):.2f} unit=ms better=lower"
        )


def flood(tmp: Path, *, shed: bool = True, calm: bool = True) -> FloodRun:
    """Victim, member and attacker processes; the member's requests calm, then flooded.

    ``calm`` False: no calm run to compare with (the tests, which bound counts and CPU,
    not latency): one request agrees the member's session before the flood instead.
    """
    f = Federation(tmp)
    pipes: list[Connection] = []
    try:
        victim, attacker, member = f.started("kx", pipes, shed=shed)
        member.send("pace" if calm else "warm")
        recv(member, "the member's first requests", WAIT + PACE_N * PACE_PERIOD)
        calmly: list[float] = []
        if calm:
            member.send("pace")  # a second calm run: the first had the key exchange in it
            calmly = recv(member, "the member's calm requests", WAIT + PACE_N * PACE_PERIOD)
        victim.send("report")
        before = recv(victim, "the victim's report")
        go(attacker, kx_payloads(f.keydir, f.fed, f.trust))  # fresh, after the calm rounds
        time.sleep(0.5)  # the flood under way
        member.send("pace")
        during = recv(member, "the member's requests during the flood", 3 * FLOOD_SECONDS)
        with contextlib.suppress(OSError):  # it may have ended its bounded flood already
            attacker.send("stop")
        sent, seconds = recv(attacker, "the attacker's count")
        victim.send("report")
        after = recv(victim, "the victim's report")
        cpu = (after["cpu"] - before["cpu"]) / seconds
        handled = after["answered"]["kx"] - before["answered"]["kx"]
        report = summed_up(victim, "kx_shed", "kx-shed")
        return FloodRun(calmly, during, sent, seconds, cpu, handled, report)
    finally:
        f.close(pipes)


def run() -> None:
    """The flood against a victim that sheds, then against one that does not (not --quick)."""
    runs = ((True, "kx-flood-member-p99"), (False, "kx-flood-member-p99-unshed"))
    for shed, name in runs[:1] if quick_run(__doc__) else runs:
        with tempfile.TemporaryDirectory() as tmp:
            print(flood(Path(tmp), shed=shed).lines(name), flush=True)


if __name__ == "__main__":
    run()
