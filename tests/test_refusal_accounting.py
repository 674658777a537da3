"""Refusals are each counted and audited, within the audit's budget, against a real process.

A victim platform (``uav-v``, exporting a stream to ``uav-m``, importing nothing) runs in
a spawned process. An attacker process with a plain zenoh client and no key of the
federation sends it:

- key-exchange requests forged under trusted names (signed with keys of its own), few
  enough that the key-exchange gate lets every one through to the signature check
  (counted: ``platform.stats.kx_requests_refused``);
- junk stream reports on ``stream-report/uav-v/uav-m``, where the export proxy reads
  its receivers' reports (``exporter.reports_refused``);
- forged watch requests and junk directory queries, few enough that their gates let
  every one through to the event loop (``interface.watch_refused``,
  ``df.queries_refused``);
- batches under a stream key with no label (the import proxy's ``malformed``, told to
  ``on_refused``, which the platform audits).

Each is audited within the unauthenticated budget: a few one by one, with why, the rest
summed up. A member (this process, with its own key: an authenticated peer) sends it
sealed messages the Interface Agent refuses for what they claim or ask
(``platform.stats.denied``, ``platform.stats.malformed``), and signed directory events
that are none (``global_df.invalid``); each is audited too.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import orjson
import pytest

from agents import AgentPlatform, watch_request, wire_key
from agents._interface import InterfaceAgent, RateLimit
from agents._security import Handshake, KeyPair, TrustStore
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
from bench._flood import ABSENT, MEMBER, START, VICTIM, WAIT, FloodFederation, recv
from dyknow_core import DyKnowInstance
from federation import ExportProxy, ImportProxy, InterfaceSessions

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

# VICTIM, MEMBER, ABSENT (bench's): trusted, neither runs but the victim
LABEL = "car1-state"
BUDGET = 1.0  # the victim's RateLimit.unauthenticated: audit records/s, bursts of one
N_FORGED = 8  # per trusted name: within the gate's per-platform burst (10), 16 in all
N_REPORTS = 300
N_WATCH = 8  # within the watch gate's burst (20) and its signature checks (10/s)
N_QUERIES = 30  # within the directory's burst (50)
N_EACH = 4  # the member's messages of each kind refused
N_BATCHES = 200


# -- the victim ----------------------------------------------------------------------------------


def victim_main(config: dict[str, Any], fed: str, keys: str, trust: str, conn: Any) -> None:
    """The victim platform: exports ``car1-state`` to uav-m, reports its counters on request."""
    asyncio.run(_victim(config, fed, Path(keys), Path(trust), conn))


async def _victim(
    config: dict[str, Any], fed: str, keys: Path, trust: Path, conn: Connection
) -> None:
    import_refused: list[tuple[str, str, int, int]] = []  # what on_refused was told
    channel = InterfaceAgent(
        KeyPair.load(keys / f"{VICTIM}.key"),
        TrustStore.load(trust),
        audit_interval=0.1,
        rate_limit=RateLimit(unauthenticated=BUDGET, report_interval=0.5),
    )
    async with (
        ZenohTransport(ZenohConfig.model_validate(config)) as t,
        AgentPlatform(VICTIM, t, federation=fed, channel=channel) as pf,
        DyKnowInstance(VICTIM) as dk,
        ExportProxy(VICTIM, fed, t, dk, InterfaceSessions(channel), lease=None) as exporter,
        ImportProxy(
            VICTIM,
            fed,
            t,
            dk,
            InterfaceSessions(channel),
            lambda sender, semantic: None,  # nothing agreed
            on_refused=lambda *told: import_refused.append(told),
            report_interval=0.1,
        ) as importer,
    ):
        dk.add_source("x")
        exporter.start_exporting("x", LABEL, MEMBER)  # its reports are read from now on
        conn.send("ready")
        while True:
            cmd = await asyncio.to_thread(conn.recv)
            if cmd == "stop":
                return
            conn.send(
                {
                    # read by name: a counter missing fails its test, not the other's
                    "kx_requests_refused": getattr(pf.stats, "kx_requests_refused", None),
                    "kx_shed": pf.stats.kx_shed,
                    "reports_refused": exporter.reports_refused,
                    "watch_refused": getattr(channel, "watch_refused", None),
                    "watch_shed": channel.watch_shed,
                    "queries_refused": getattr(pf.df, "queries_refused", None),
                    "queries_shed": pf.df.queries_shed if pf.df is not None else None,
                    "denied": getattr(pf.stats, "denied", None),
                    "import_dropped": importer.stats()["totals"]["dropped_batches"],
                    "import_refused": list(import_refused),
                    "malformed": pf.stats.malformed,
                    "df_invalid": pf.global_df.invalid if pf.global_df is not None else None,
                    "records": [r for r in channel.audit.records if r["verdict"] != "accepted"],
                }
            )


# -- the attacker: a plain zenoh client, no key of the federation -------------------------------


def attacker_main(endpoint: str, key: str, payloads: list[bytes], conn: Any) -> None:
    """Send each payload once to ``key`` (puts on ``stream…``, else queries); the count."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    try:
        puts = "/stream-report/" in key or "/stream/" in key
        publisher = session.declare_publisher(key) if puts else None
        if publisher is not None:  # puts before the victim's subscriber is known go nowhere
            deadline = time.monotonic() + START
            while not publisher.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.05)
        conn.send("ready")
        conn.recv()  # go
        answers = 0
        for payload in payloads:
            if publisher is not None:
                publisher.put(payload)
                time.sleep(0.001)
            else:
                # one after the other, each to its end: the victim answers none of them
                answers += sum(1 for r in session.get(key, payload=payload, timeout=5.0) if r.ok)
        conn.send((len(payloads), answers))
    finally:
        session.close()


class Federation(FloodFederation):
    """The victim and the attacker as spawned processes, with their pipes."""

    prefix = "refusals"

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.pipes: list[Connection] = []

    def _start(self, target: Any, args: tuple[Any, ...], name: str) -> Connection:
        here = self.spawn(target, args, name)
        self.pipes.append(here)
        return here

    def victim(self) -> Connection:
        """Start the victim, listening; its pipe once it says it is ready."""
        config = ZenohConfig.loopback(self.port).model_dump()
        args = (config, self.fed, str(self.keydir), str(self.trust_file))
        pipe = self._start(victim_main, args, "refusals-victim")
        assert recv(pipe, "the victim", START) == "ready"
        return pipe

    def attacker(self, what: str, payloads: list[bytes]) -> Connection:
        """Start the attacker on the victim's ``what`` key; its pipe once it is ready."""
        key = wire_key(self.fed, what, VICTIM)
        if what == "stream-report":
            key += f"/{MEMBER}"  # as if uav-m reported
        elif what == "stream":
            key += "/evil"  # a sender, and no label
        args = (f"tcp/127.0.0.1:{self.port}", key, payloads)
        pipe = self._start(attacker_main, args, f"refusals-attacker-{what}")
        assert recv(pipe, "the attacker", START) == "ready"
        return pipe


@contextlib.contextmanager
def federation(tmp_path: Path) -> Iterator[Federation]:
    """A `Federation` whose children are stopped at the end."""
    f = Federation(tmp_path)
    try:
        yield f
    finally:
        f.close(f.pipes)


def accounted(victim: Connection, counter: str, stage: str, n: int) -> dict[str, Any]:
    """The victim's report once ``counter`` is ``n`` and its audit accounts for all of them.

    Accounted: the refusals audited one by one (``stage``) and those summed up (the
    ``unauthenticated`` summaries, once per report interval) add up to ``counter``.
    Bounded by WAIT; the report as it is then, whatever it says.
    """
    deadline = time.monotonic() + WAIT
    while True:
        victim.send("report")
        report: dict[str, Any] = recv(victim, "the victim's report")
        records = report["records"]
        detailed = [r for r in records if r.get("stage") == stage]
        summed = sum(r["count"] for r in records if r.get("stage") == "unauthenticated")
        report["detailed"], report["summed"] = detailed, summed
        done = report[counter] == n and len(detailed) + summed == n
        if done or time.monotonic() > deadline:
            return report
        time.sleep(0.2)


# -- the tests -----------------------------------------------------------------------------------


def test_forged_kx_requests_past_the_gate_are_counted_and_audited_within_budget(
    tmp_path: Path,
) -> None:
    """Requests the gate lets through and the signature check refuses: each counted, audited."""
    with federation(tmp_path) as f:
        victim = f.victim()
        victim_public = f.trust.public_key(VICTIM)
        forged: list[bytes] = []
        for name in (MEMBER, ABSENT):
            mine = KeyPair.generate(name)  # the attacker's own key, under a trusted name
            own = TrustStore(f.fed, {name: mine.public_key, VICTIM: victim_public})
            forged += [Handshake(mine, own).initiate(VICTIM) for _ in range(N_FORGED)]
        attacker = f.attacker("kx", forged)
        start = time.monotonic()
        attacker.send("go")
        sent, answers = recv(attacker, "the attacker's count", WAIT + len(forged) * 5.0)
        seconds = time.monotonic() - start
        assert (sent, answers) == (len(forged), 0)  # none answered
        report = accounted(victim, "kx_requests_refused", "kx", len(forged))
        print(
            f"\n{sent} forged requests in {seconds:.1f} s: refused "
            f"{report['kx_requests_refused']}, audited {len(report['detailed'])} one by one, "
            f"{report['summed']} summed up"
        )
        # all of them reached the signature check: none shed by the gate
        assert report["kx_shed"] == 0
        assert report["kx_requests_refused"] == len(forged)
        detailed = report["detailed"]
        assert detailed, report["records"]
        for r in detailed:
            assert r["reason"].startswith("forged: "), r
            assert r["from"] in (MEMBER, ABSENT)
        # bounded: one record a second (bursts of one), the rest summed up
        assert len(detailed) <= 1 + BUDGET * (seconds + WAIT)
        assert len(detailed) < len(forged)
        assert len(detailed) + report["summed"] == len(forged)


def test_junk_stream_reports_are_counted_and_audited_within_budget(tmp_path: Path) -> None:
    """Reports under a receiver's name that do not open: each counted, audited within budget."""
    with federation(tmp_path) as f:
        victim = f.victim()
        junk = [os.urandom(64) for _ in range(N_REPORTS // 2)]
        junk += [b"\x94\x01\xa4uav-m\xa4uav-v\xc4\x00"] * (N_REPORTS - len(junk))
        attacker = f.attacker("stream-report", junk)
        start = time.monotonic()
        attacker.send("go")
        sent, _ = recv(attacker, "the attacker's count", WAIT + N_REPORTS * 0.01)
        seconds = time.monotonic() - start
        assert sent == N_REPORTS
        report = accounted(victim, "reports_refused", "stream-report", N_REPORTS)
        print(
            f"\n{sent} junk reports in {seconds:.1f} s: refused {report['reports_refused']}, "
            f"audited {len(report['detailed'])} one by one, {report['summed']} summed up"
        )
        assert report["reports_refused"] == N_REPORTS
        detailed = report["detailed"]
        assert detailed, report["records"]
        for r in detailed:
            assert r["reason"].startswith("malformed: "), r
        assert len(detailed) <= 1 + BUDGET * (seconds + WAIT)
        assert len(detailed) + report["summed"] == N_REPORTS


def test_forged_watch_requests_past_the_gate_are_counted_and_audited_within_budget(
    tmp_path: Path,
) -> None:
    """Watch requests not signed by the owner's key: each counted, audited within budget."""
    with federation(tmp_path) as f:
        victim = f.victim()
        stranger = KeyPair.generate(VICTIM)  # the owner's name, not its key
        forged = [watch_request(stranger, f.fed) for _ in range(N_WATCH)]
        attacker = f.attacker("watch", forged)
        start = time.monotonic()
        attacker.send("go")
        sent, answers = recv(attacker, "the attacker's count", WAIT + N_WATCH * 5.0)
        seconds = time.monotonic() - start
        assert (sent, answers) == (N_WATCH, 0)
        report = accounted(victim, "watch_refused", "watch", N_WATCH)
        assert report["watch_shed"] == 0  # all of them reached the check
        assert report["watch_refused"] == N_WATCH
        detailed = report["detailed"]
        assert detailed, report["records"]
        assert all(r["reason"].startswith("forged: ") for r in detailed), detailed
        assert len(detailed) <= 1 + BUDGET * (seconds + WAIT)
        assert len(detailed) + report["summed"] == N_WATCH


def test_junk_directory_queries_are_counted_and_audited_within_budget(tmp_path: Path) -> None:
    """Directory queries that are no query: unanswered, each counted, audited within budget."""
    with federation(tmp_path) as f:
        victim = f.victim()
        junk = [b"not json", b'{"nonce": "!!"}', b"{}", b'{"nonce": "' + b"QUFB" * 30 + b'"}']
        queries = [junk[i % len(junk)] for i in range(N_QUERIES)]
        attacker = f.attacker("df", queries)
        start = time.monotonic()
        attacker.send("go")
        sent, answers = recv(attacker, "the attacker's count", WAIT + N_QUERIES * 5.0)
        seconds = time.monotonic() - start
        assert (sent, answers) == (N_QUERIES, 0)
        report = accounted(victim, "queries_refused", "df", N_QUERIES)
        assert report["queries_shed"] == 0  # all of them reached the event loop
        assert report["queries_refused"] == N_QUERIES
        detailed = report["detailed"]
        assert detailed, report["records"]
        assert all(r["reason"].startswith("malformed: ") for r in detailed), detailed
        assert len(detailed) <= 1 + BUDGET * (seconds + WAIT)
        assert len(detailed) + report["summed"] == N_QUERIES


def test_batches_under_a_key_without_a_label_are_counted_and_told_to_on_refused(
    tmp_path: Path,
) -> None:
    """What comes on ``stream/uav-v/evil`` (no label): each batch counted and told, summed."""
    with federation(tmp_path) as f:
        victim = f.victim()
        attacker = f.attacker("stream", [os.urandom(32) for _ in range(N_BATCHES)])
        attacker.send("go")
        sent, _ = recv(attacker, "the attacker's count", WAIT + N_BATCHES * 0.01)
        assert sent == N_BATCHES
        deadline = time.monotonic() + WAIT
        while True:
            victim.send("report")
            report = recv(victim, "the victim's report")
            told = report["import_refused"]
            if sum(t[2] for t in told) >= N_BATCHES or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert report["import_dropped"] == {"malformed": N_BATCHES}
        # told summed up, a call per sender and reason per report interval: not one per batch
        assert sum(t[2] for t in told) == N_BATCHES, told
        assert {(t[0], t[1]) for t in told} == {("evil", "malformed")}
        assert len(told) < N_BATCHES


async def test_an_authenticated_peers_refused_messages_are_counted_and_audited(
    tmp_path: Path,
) -> None:
    """Messages of a trusted peer refused for what they claim or ask: each counted, audited."""
    with federation(tmp_path) as f:
        victim = f.victim()
        here = f"asker@{MEMBER}"
        bodies = {
            # impersonation: an agent of another platform than the envelope's
            f"sender is not an agent of {MEMBER!r}": _acl("inform", "spy@uav-q", "x@uav-v"),
            f"no receiver on platform {VICTIM!r}": _acl("inform", here, "x@uav-q"),
            "access denied: nobody@uav-v offers no service": _acl("request", here, "nobody@uav-v"),
            "reply_to may not name agents of this platform": _acl(
                "inform", here, "x@uav-v", reply_to=["x@uav-v"]
            ),
            # not a message, naming a sender of another platform: nobody to tell (the
            # reason says what is wrong with it first)
            "…; and the sender is not an agent of": _acl("bogus", "spy@uav-q", "x@uav-v"),
        }
        channel = InterfaceAgent(KeyPair.load(f.keydir / f"{MEMBER}.key"), f.trust)
        config = ZenohConfig.loopback(free_tcp_port(), connect=[f.port])
        async with (
            ZenohTransport(config) as t,
            AgentPlatform(MEMBER, t, federation=f.fed, channel=channel),
        ):
            await channel.agree(VICTIM)
            inbox = wire_key(f.fed, "acl", VICTIM)
            for body in bodies.values():
                for _ in range(N_EACH):
                    await t.publish(inbox, channel.sessions.seal(VICTIM, body))
            deadline = time.monotonic() + WAIT
            while True:
                victim.send("report")
                report = await asyncio.to_thread(recv, victim, "the victim's report")
                if report["denied"] == 4 * N_EACH and report["malformed"] == N_EACH:
                    break
                if time.monotonic() > deadline:
                    break
                await asyncio.sleep(0.2)
        assert report["denied"] == 4 * N_EACH, report
        assert report["malformed"] == N_EACH, report
        for words in bodies:
            audited = [r for r in report["records"] if _says(str(r.get("reason")), words)]
            assert len(audited) == N_EACH, (words, report["records"])
            assert all(r["from"] == MEMBER for r in audited), audited


async def test_a_members_signed_directory_events_that_are_no_events_are_audited(
    tmp_path: Path,
) -> None:
    """Directory events a trusted member signs, that are none: each counted and audited."""
    with federation(tmp_path) as f:
        victim = f.victim()
        channel = InterfaceAgent(KeyPair.load(f.keydir / f"{MEMBER}.key"), f.trust)
        config = ZenohConfig.loopback(free_tcp_port(), connect=[f.port])
        async with (
            ZenohTransport(config) as t,
            AgentPlatform(MEMBER, t, federation=f.fed, channel=channel) as pm,
        ):
            report: dict[str, Any] = {}
            deadline = time.monotonic() + WAIT
            # the victim reads a member's events once it saw its token and signed answer:
            # sent until it counts one, then N_EACH more
            while time.monotonic() < deadline:
                event = pm.directory_auth.seal(MEMBER, "df-event", {"op": "bogus"})
                await t.publish(pm.key("df-events"), event)
                await asyncio.sleep(0.05)
                victim.send("report")
                report = await asyncio.to_thread(recv, victim, "the victim's report")
                if report["df_invalid"]:
                    break
            for _ in range(N_EACH):
                event = pm.directory_auth.seal(MEMBER, "df-event", {"op": "bogus"})
                await t.publish(pm.key("df-events"), event)
                await asyncio.sleep(0.01)
            want = report["df_invalid"] + N_EACH
            while time.monotonic() < deadline + WAIT:
                victim.send("report")
                report = await asyncio.to_thread(recv, victim, "the victim's report")
                detailed = [r for r in report["records"] if r.get("stage") == "df-events"]
                summed = sum(
                    r["count"] for r in report["records"] if r.get("stage") == "unauthenticated"
                )
                if report["df_invalid"] == want and len(detailed) + summed == want:
                    break
                await asyncio.sleep(0.2)
        assert report["df_invalid"] == want, report
        assert detailed, report["records"]
        assert all(r["reason"].startswith("invalid: directory event: ") for r in detailed)
        assert all(r["from"] == MEMBER for r in detailed), detailed
        assert len(detailed) + summed == want


def _says(reason: str, words: str) -> bool:
    """Whether an audit record's reason is ``words`` (after what ``…`` stands for)."""
    if words.startswith("…"):
        return words[1:] in reason
    return reason.startswith(words)


def _acl(performative: str, sender: str, receiver: str, **fields: Any) -> bytes:
    """An ACL message's JSON, as the wire has it (any performative, valid or not)."""
    return orjson.dumps(
        {
            "v": 1,
            "performative": performative,
            "sender": sender,
            "receivers": [receiver],
            **fields,
        }
    )
