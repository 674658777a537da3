"""A member's directory changes, seen by another platform while an outsider floods its events.

Three spawned processes on loopback zenoh: a victim platform (``uav-v``), a member
(``uav-m``) that registers and deregisters a public service when told, and an attacker
with a plain zenoh client and no key of the federation publishing ~10 000 directory
events/s on ``df-events/*``: forged (signed with a key of its own) under the member's
name and under a trusted platform that is not running, under a name not in the trust
file, unsigned, junk. The test measures how long each of the member's changes takes to
show in the victim's global directory during the flood, and the victim's CPU per event
sent, shedding (the default) or not (``event_limit=None``, for comparison).
``tests/test_df_events_flood.py`` asserts on the same runs; see docs/security.md,
"Directory-event load shedding".

    BENCH df-events-flood-cpu ours=<µs per event, shedding> unshed=<µs, not shedding> …
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import os
import tempfile
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import orjson
from nacl.signing import SigningKey

from agents import AgentPlatform, ServiceDescription, wire_key
from agents._df import GlobalDirectory
from agents._interface import InterfaceAgent
from agents._security import KeyPair, TrustStore
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
from bench._flood import (
    ABSENT,
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

CHANGES = 4  # the member's registers (and as many deregisters) during the flood
MIN_FLOOD = 4.0  # seconds the flood lasts at least
SEEN_WITHIN = 5.0  # each must show in the victim's view within this (s): a resync is ~1 s


def node_main(
    role: str, config: dict[str, Any], fed: str, keys: str, trust: str, conn: Any, shed: bool
) -> None:
    """A spawned platform: the victim (``uav-v``) or the member (``uav-m``)."""
    if not shed:  # the comparison: every event reaches the event loop and its signature check
        defaults = GlobalDirectory.__init__.__kwdefaults__
        assert defaults is not None
        defaults["event_limit"] = None
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
        view, df = pf.global_df, pf.df
        assert view is not None and df is not None
        conn.send("ready")
        while True:
            cmd, *args = await asyncio.to_thread(conn.recv)
            if cmd == "stop":
                return
            if cmd == "report":
                gate = view.event_gate
                conn.send(
                    {
                        "cpu": time.process_time(),
                        "platforms": view.platforms,
                        "services": sorted(s.name for s in view.services(MEMBER)),
                        "events_shed": view.events_shed,
                        "shed": {} if gate is None else dict(gate.shed),
                        "admitted": 0 if gate is None else gate.admitted,
                        "refused": view.refused,
                        "stale": view.stale,
                        "resyncs": view.resyncs,
                        "records": [r for r in channel.audit.records if r["verdict"] == "dropped"],
                    }
                )
            elif cmd == "has":  # the victim: whether the member's service is listed
                conn.send(any(s.name == args[0] for s in view.services(MEMBER)))
            elif cmd == "register":  # the member
                await df.register(
                    ServiceDescription(
                        name=args[0], type="demo", provider=f"svc@{role}", visibility="public"
                    )
                )
                conn.send("done")
            elif cmd == "deregister":
                await df.deregister(f"svc@{role}", args[0])
                conn.send("done")


def attacker_main(endpoint: str, fed: str, payloads: list[tuple[str, bytes]], conn: Any) -> None:
    """Publish ``payloads`` (key, payload) round and round at ~10 000/s until told to stop."""
    session = zenoh_client(endpoint)
    try:
        publishers = {key: session.declare_publisher(key) for key, _ in payloads}
        conn.send("ready")
        conn.recv()  # go
        n = len(payloads)

        def send(i: int) -> None:
            key, payload = payloads[i % n]
            publishers[key].put(payload)

        flood_at(conn, send)
    finally:
        session.close()


def _forged(fed: str, name: str, seq: int, body: Any, key: SigningKey | None) -> bytes:
    """A directory event under ``name``, fresh and newer than any real one, signed by ``key``."""
    text = orjson.dumps(body).decode()
    obj: dict[str, Any] = {
        "v": 1,
        "fed": fed,
        "from": name,
        "kind": "df-event",
        "boot": 1 << 60,  # newer than any real boot: only the signature can refuse it
        "seq": seq,
        "ts_ms": int(time.time() * 1000),
        "nonce": "",
        "body": text,
    }
    if key is not None:
        obj["sig"] = base64.b64encode(key.sign(os.urandom(32)).signature).decode()
    return orjson.dumps(obj)


def event_payloads(fed: str) -> list[tuple[str, bytes]]:
    """What the attacker publishes: forged under the member and uav-q, untrusted, junk.

    The forged ones say the member's services are gone (or it left): they pass every
    check but the signature. uav-x is not in the trust file; some are unsigned; junk is
    random bytes.
    """
    rogue = SigningKey.generate()
    gone = {
        "op": "deregister",
        "service": {"name": "x", "type": "demo", "provider": f"svc@{MEMBER}"},
    }
    out: list[tuple[str, bytes]] = []
    for name in (MEMBER, ABSENT, "uav-x"):
        key = wire_key(fed, "df-events", name)
        out += [(key, _forged(fed, name, i + 1, gone, rogue)) for i in range(300)]
        out += [(key, _forged(fed, name, 1, {"op": "leave"}, rogue)) for _ in range(20)]
    member = wire_key(fed, "df-events", MEMBER)
    out += [(member, _forged(fed, MEMBER, 5, gone, None)) for _ in range(100)]
    out += [(member, os.urandom(200)) for _ in range(200)]
    order = list(range(len(out)))
    order.sort(key=lambda i: (i * 7919) % len(out))  # every kind all along the flood
    return [out[i] for i in order]


class DfFederation(FloodFederation):
    """The victim, the member and the attacker of a directory-event flood."""

    prefix = "df"
    node_main = staticmethod(node_main)

    def flooder(self) -> Connection:
        """Start the attacker (it says "ready", then floods on "go" until "stop")."""
        endpoint = f"tcp/127.0.0.1:{self.port}"
        payloads = event_payloads(self.fed)
        return self.spawn(attacker_main, (endpoint, self.fed, payloads), "df-attacker")


def _until_seen(victim: Connection, name: str, listed: bool) -> float:
    """Seconds until the victim lists (or no longer lists) the member's service ``name``."""
    t0 = time.monotonic()
    while True:
        victim.send(("has", name))
        if recv(victim, "the victim's view") == listed:
            return time.monotonic() - t0
        if time.monotonic() - t0 > WAIT:
            raise AssertionError(f"{name} {'not listed' if listed else 'still listed'}")
        time.sleep(0.02)


@dataclass
class FloodRun:
    """What one flood measured: the member's changes (s), the attacker, the victim."""

    seen: list[float]  # seconds until each register and deregister showed at the victim
    sent: int
    seconds: float
    cpu: float  # the victim's CPU during the flood, in seconds
    before: dict[str, Any]
    report: dict[str, Any]  # the victim's counters and audit records after it

    @property
    def cpu_per_event(self) -> float:
        """The victim's CPU per event sent, in µs."""
        return self.cpu / self.sent * 1e6

    def lines(self, name: str = "df-events-flood") -> str:
        """The figures, for printing."""
        r = self.report
        return (
            f"{name}: attacker {self.sent} events in {self.seconds:.1f} s "
            f"({self.sent / self.seconds:.0f}/s); victim CPU {self.cpu_per_event:.1f} µs per "
            f"event; shed {r['events_shed']} ({r['shed']}), checked {r['admitted']}, refused "
            f"{r['refused'] - self.before['refused']}, resyncs "
            f"{r['resyncs'] - self.before['resyncs']}; member's changes seen in "
            f"{', '.join(f'{s:.2f}' for s in self.seen)} s"
        )


def flood(tmp: Path, *, shed: bool = True, changes: int = CHANGES) -> FloodRun:
    """Victim, member and attacker processes; ``changes`` of the member's during the flood.

    Each change after the first waits for a resync (~1 s): the test makes fewer of them.
    """
    f = DfFederation(tmp)
    pipes: list[Connection] = []
    try:
        victim = f.node(VICTIM, f.port, [], shed=shed)
        pipes.append(victim)
        assert recv(victim, "the victim", START) == "ready"
        attacker = f.flooder()
        pipes.append(attacker)
        member = f.node(MEMBER, free_tcp_port(), [f.port], shed=shed)
        pipes.append(member)
        assert recv(member, "the member", START) == "ready"
        assert recv(attacker, "the attacker", START) == "ready"
        deadline = time.monotonic() + START
        while True:  # the victim lists the member
            victim.send(("report",))
            if MEMBER in recv(victim, "the victim's report")["platforms"]:
                break
            assert time.monotonic() < deadline, "the victim never listed the member"
            time.sleep(0.1)
        victim.send(("report",))
        before = recv(victim, "the victim's report")
        attacker.send("go")
        began = time.monotonic()
        time.sleep(1.0)  # the flood under way
        seen: list[float] = []
        for i in range(changes):
            for op, listed in (("register", True), ("deregister", False)):
                member.send((op, f"svc-{i}"))
                recv(member, f"the member's {op}")
                seen.append(_until_seen(victim, f"svc-{i}", listed))
        # long enough to measure the victim's CPU, however fast the changes showed
        time.sleep(max(0.0, began + MIN_FLOOD - time.monotonic()))
        with contextlib.suppress(OSError):  # it may have ended its bounded flood already
            attacker.send("stop")
        sent, seconds = recv(attacker, "the attacker's count")
        victim.send(("report",))
        after = recv(victim, "the victim's report")
        cpu = after["cpu"] - before["cpu"]
        report = summed_up(victim, "events_shed", "df-events-shed", ("report",)) if shed else after
        return FloodRun(seen, sent, seconds, cpu, before, report)
    finally:
        f.close(pipes, ("stop",))


def run() -> None:
    """The flood against a victim that sheds, then against one that does not (not --quick)."""
    runs = {}
    for shed in (True,) if quick_run(__doc__) else (True, False):
        with tempfile.TemporaryDirectory() as tmp:
            runs[shed] = flood(Path(tmp), shed=shed)
            print(runs[shed].lines("df-events-flood" if shed else "df-events-flood-unshed"))
    if False not in runs:
        return
    ours, unshed = runs[True].cpu_per_event, runs[False].cpu_per_event
    print(
        f"BENCH df-events-flood-cpu ours={ours:.1f} unshed={unshed:.1f} "
        f"ratio={ours / unshed:.2f} unit=us better=lower",
        flush=True,
    )


if __name__ == "__main__":
    run()
