"""Refusals a sender can repeat cheaply, or normal traffic hits: counted, audited summed up.

Each was answered or counted only. Now each is counted and audited in records summed up
per source and interval (``count``: how many), never one record per refusal, so a flood
of them cannot flood the audit. The victim is a spawned `FederationPlatform` (the harness
of ``test_member_authz``); the attacker is a member (``uav-m``, in this process, its
messages authenticated), or a plain zenoh client for the start-up check.

- a request an agent of the victim refuses itself (``agent-refuse``);
- a message for no agent there, or for one whose mailbox is full (``delivery``);
- samples that are no samples inside an authentic batch of an agreed stream
  (``import-samples``, per provider and stream);
- a directory event re-sent (normal now and then; dropped before its signature check,
  so in the directory's ``df-events-shed`` summaries, attributed to no member);
- directory events a member signs that are none: logged once per signer per interval;
- answers to the start-up check ``runs_signed`` in a name, not signed with its key.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import time
from pathlib import Path
from typing import Any

import msgpack
import pytest
from test_member_authz import audited, mallory, refusal, world

from agents import FIPA_AGENT_MANAGEMENT, KeyPair, TrustStore, request, runs_signed, wire_key
from agents._acl import ACLMessage, Performative
from agents._df import INVALID_LOG_INTERVAL
from agents._directory_auth import DirectoryAuth
from agents._platform import REFUSAL_AUDIT_INTERVAL
from agents.keys import gen_keys, trust_keys
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
from federation._sessions import InterfaceSessions

pytestmark = pytest.mark.timeout(120)

VICTIM, MEMBER = "uav-b", "uav-m"
N = 30


def summed(stats: dict[str, Any], **match: Any) -> tuple[int, list[dict[str, Any]]]:
    """The refusals the victim's matching records sum up, and the records."""
    recs = audited(stats, **match)
    return sum(r["count"] for r in recs), recs


def bounded(recs: list[dict[str, Any]], seconds: float, interval: float) -> None:
    """At most a record per interval (and the first at once): not one per refusal."""
    assert len(recs) <= 2 + seconds / interval, (len(recs), seconds)
    assert len(recs) < N, recs


async def test_an_agents_own_refusals_are_counted_and_audited_summed_up(tmp_path: Path) -> None:
    """Requests the victim's DF refuses itself (an unknown function): counted, summed up."""
    async with world(tmp_path, [VICTIM]) as w:
        agent = await mallory(w)
        before = (await w.stats(VICTIM))["platform"]["agent_refused"]
        start = time.monotonic()
        ask = {"action": "no-such-function"}
        reasons = await asyncio.gather(
            *(
                refusal(request(agent, f"df@{VICTIM}", ask, ontology=FIPA_AGENT_MANAGEMENT))
                for _ in range(N)
            )
        )
        assert all("unsupported function" in r for r in reasons), reasons
        match = {"verdict": "refused", "stage": "agent-refuse", "from": MEMBER}
        s = await w.until_stats(VICTIM, lambda s: summed(s, **match)[0] >= N, "summed up")
        seconds = time.monotonic() - start
        assert s["platform"]["agent_refused"] - before == N
        total, recs = summed(s, **match)
        assert total == N
        bounded(recs, seconds, REFUSAL_AUDIT_INTERVAL)
        assert all(r["reason"].startswith("refuse: ") for r in recs), recs
        assert "unsupported function" in recs[-1]["reason"]


async def test_an_agents_refusal_echoing_much_is_summed_up_cut_as_a_quoted_reason(
    tmp_path: Path,
) -> None:
    """A refusal echoing what the member asked (a DF function name of 5 000 characters):
    the agent-refuse summary's last reason is cut as a quoted reason is, saying how long
    it was (docs/security.md, "Refusals summed up")."""
    async with world(tmp_path, [VICTIM]) as w:
        agent = await mallory(w)
        ask = {"action": "f" * 5_000}
        reason = await refusal(request(agent, f"df@{VICTIM}", ask, ontology=FIPA_AGENT_MANAGEMENT))
        assert reason == f"unsupported function {ask['action']!r}"
        match = {"verdict": "refused", "stage": "agent-refuse", "from": MEMBER}
        s = await w.until_stats(VICTIM, lambda s: summed(s, **match)[0] >= 1, "summed up")
        (rec,) = summed(s, **match)[1]
        assert rec["reason"].endswith(
            f"(last: df@{VICTIM}: unsupported function 'fff"
            + "f" * (200 - len("unsupported function 'fff"))
            + f"… ({len(reason)} characters, {len(reason) - 200} left out))"
        ), rec["reason"][-300:]


async def test_messages_for_no_agent_or_a_full_mailbox_are_audited_summed_up(
    tmp_path: Path,
) -> None:
    """Informs to an unknown agent, and to one whose mailbox is full: counted, summed up."""
    async with world(tmp_path, [VICTIM]) as w:
        w.pipes[VICTIM].send("stuck", "stuck")
        await w.pipes[VICTIM].expect("stuck")
        agent = await mallory(w)
        before = (await w.stats(VICTIM))["platform"]
        start = time.monotonic()
        for receiver in ("ghost", "stuck"):
            for i in range(N):
                await agent.send(_inform(agent.aid, f"{receiver}@{VICTIM}", i))
        ghosts = {"stage": "delivery", "code": "unknown-receiver", "from": MEMBER}
        full = {"stage": "delivery", "code": "mailbox-full", "from": MEMBER}
        s = await w.until_stats(
            VICTIM,
            lambda s: (
                summed(s, **ghosts)[0] >= N
                and summed(s, **full)[0]
                == s["platform"]["mailbox_full"] - before["mailbox_full"]
                > 0
            ),
            "both summed up",
        )
        seconds = time.monotonic() - start
        assert s["platform"]["unknown_receiver"] - before["unknown_receiver"] == N
        # the stuck agent's handler holds one message, its mailbox two: the rest refused
        assert s["platform"]["mailbox_full"] - before["mailbox_full"] >= N - 3
        for match in (ghosts, full):
            recs = audited(s, **match)
            bounded(recs, seconds, REFUSAL_AUDIT_INTERVAL)
            assert all(r["verdict"] == "dropped" for r in recs)
        assert f"no agent ghost@{VICTIM}" in audited(s, **ghosts)[-1]["reason"]
        assert f"the mailbox of stuck@{VICTIM} is full" in audited(s, **full)[-1]["reason"]


async def test_bad_samples_in_authentic_batches_are_audited_per_stream(tmp_path: Path) -> None:
    """Samples that are no samples, in batches of an agreed stream: counted, summed up."""
    async with world(tmp_path, [VICTIM]) as w:
        assert (await w.ask(VICTIM, MEMBER, ["car7-state"])).startswith("x-")
        m = w.here[MEMBER]
        sessions = InterfaceSessions(m.interface)
        await sessions.ensure(VICTIM)
        key = wire_key(w.federation, "stream", VICTIM) + f"/{MEMBER}/car7-state"
        start = time.monotonic()
        for i in range(N):
            # authentic, of the agreed stream, each sample with no integer valid time
            # (no sequence number: the member's own batches of the stream keep theirs)
            body = msgpack.packb({"v": 1, "s": "car7-state", "b": [["x", "not a time", 0], [i]]})
            await m.transport.publish(key, sessions.seal_bytes(VICTIM, body))
            await asyncio.sleep(0.005)
        match = {
            "stage": "import-samples",
            "code": "malformed",
            "stream": "car7-state",
            "from": MEMBER,
        }
        s = await w.until_stats(VICTIM, lambda s: summed(s, **match)[0] >= 2 * N, "summed up")
        seconds = time.monotonic() - start
        assert s["imports"]["totals"]["dropped_samples"]["malformed"] == 2 * N
        total, recs = summed(s, **match)
        assert total == 2 * N
        bounded(recs, seconds, 0.5)  # the import proxy's report interval
        assert recs[0]["reason"].startswith("malformed: "), recs


def stale_shed(stats: dict[str, Any]) -> tuple[int, list[dict[str, Any]]]:
    """The stale events the victim's ``df-events-shed`` summaries count, and the records."""
    recs = audited(stats, verdict="dropped", stage="df-events-shed")
    return sum(r["by_reason"].get("stale", 0) for r in recs), recs


def checked_stale(stats: dict[str, Any]) -> int:
    """The stale events the victim's directory dropped after their signature check."""
    return int(stats["df_stale"] - stats["df_stale_shed"])


async def test_a_directory_event_sent_again_is_audited_summed_up(tmp_path: Path) -> None:
    """A member's directory event sent again N times: each stale, counted, summed up.

    Dropped before its signature check (anyone may send one under a member's name), so
    summed up with what the gate sheds, never in a record attributed to the member.
    """
    async with world(tmp_path, [VICTIM]) as w:
        pm = w.here[MEMBER].agents
        first = await w.stats(VICTIM)
        event = pm.directory_auth.seal(MEMBER, "df-event", {"op": "bogus"})
        await pm.transport.publish(pm.key("df-events"), event)
        # checked once (invalid); the member's events sent before it are taken by then
        # (in order): one its snapshot reflected already may be stale, but not counted here
        before = await w.until_stats(
            VICTIM, lambda s: s["df_invalid"] > first["df_invalid"], "checked once"
        )
        start = time.monotonic()
        for _ in range(N):  # not newer now: stale, shed before the check
            await pm.transport.publish(pm.key("df-events"), event)
            await asyncio.sleep(0.005)
        s = await w.until_stats(
            VICTIM,
            lambda s: (
                s["df_stale"] - before["df_stale"] >= N
                and stale_shed(s)[0] >= s["df_stale_shed"]
                and summed(s, stage="df-events-stale")[0] >= checked_stale(s)
            ),
            "summed up",
        )
        seconds = time.monotonic() - start
        assert s["df_stale"] - before["df_stale"] == N
        assert checked_stale(s) == checked_stale(before), "one reached the signature check"
        assert s["df_invalid"] - first["df_invalid"] == 1
        # what the gate shed stale is summed up once each (with any shed at the start)
        total, recs = stale_shed(s)
        assert total == s["df_stale_shed"]
        bounded(recs[len(stale_shed(before)[1]) :], seconds, 1.0)  # the report interval
        assert all(r["reason"].startswith("directory events shed: ") for r in recs), recs
        # attributed to the member: only the events checked (at the start, maybe), none of these
        assert summed(s, stage="df-events-stale")[0] == checked_stale(s)


async def test_invalid_directory_events_of_a_signer_are_logged_once_per_interval(
    tmp_path: Path,
) -> None:
    """N events a member signs that are none: each counted and audited, one warning."""
    async with world(tmp_path, [VICTIM]) as w:
        pm = w.here[MEMBER].agents
        before = await w.stats(VICTIM)
        start = time.monotonic()
        for _ in range(N):  # each newer than the last: checked, invalid
            event = pm.directory_auth.seal(MEMBER, "df-event", {"op": "bogus"})
            await pm.transport.publish(pm.key("df-events"), event)
            await asyncio.sleep(0.005)
        s = await w.until_stats(
            VICTIM, lambda s: s["df_invalid"] - before["df_invalid"] >= N, "counted"
        )
        seconds = time.monotonic() - start
        assert s["df_invalid"] - before["df_invalid"] == N
        # the first of a signer at once, the rest summed up a whole interval later
        new = s["df_warnings"][len(before["df_warnings"]) :]
        about = [line for line in new if "unknown op 'bogus'" in line]
        assert seconds < INVALID_LOG_INTERVAL
        assert len(about) == 1, new
        assert MEMBER in about[0]


# -- the start-up check: a plain zenoh client answers in the platform's name -----------------


def _impostor_main(port: int, fed: str, conn: Any) -> None:
    """uav-x's presence, and every directory query for it answered, signed by another key."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    impostor = KeyPair.generate("uav-x")
    auth = DirectoryAuth(fed, impostor, TrustStore(fed, {"uav-x": impostor.public_key}))
    session = zenoh.open(cfg)

    def answer(query: Any) -> None:
        import base64

        import orjson

        nonce = base64.b64decode(orjson.loads(query.payload.to_bytes())["nonce"])
        query.reply(query.key_expr, auth.seal("uav-x", "df", [], nonce=nonce))

    queryable = session.declare_queryable(wire_key(fed, "df", "uav-x"), answer)
    token = session.liveliness().declare_token(wire_key(fed, "alive", "uav-x"))
    conn.send("ready")
    conn.recv()  # stop
    token.undeclare()
    queryable.undeclare()
    session.close()


@pytest.mark.usefixtures("no_leftover_children")
async def test_runs_signed_counts_refused_answers_and_logs_them_in_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Answers in uav-x's name signed by another key: refused, each told, one warning."""
    fed = "startup-check"
    trust_file = tmp_path / "trust.json"
    trust_keys(trust_file, [gen_keys(n, tmp_path)[2] for n in ("uav-x", "uav-y")], federation=fed)
    port = free_tcp_port()
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    proc = ctx.Process(target=_impostor_main, args=(port, fed, there), name="impostor")
    proc.start()
    assert await asyncio.to_thread(here.poll, 30.0), "the impostor did not start"
    assert here.recv() == "ready"
    refused: list[tuple[str | None, str]] = []
    config = ZenohConfig.loopback(free_tcp_port(), connect=[port])
    try:
        async with ZenohTransport(config) as t:
            alive = wire_key(fed, "alive", "uav-x")
            for _ in range(100):  # its presence seen: the route to it is up
                if alive in await t.tokens(alive, timeout=1.0):
                    break
                await asyncio.sleep(0.05)
            else:
                raise AssertionError("the impostor's presence never came")
            keys, trust = KeyPair.load(tmp_path / "uav-y.key"), TrustStore.load(trust_file)
            with caplog.at_level(logging.WARNING, logger="agents._df"):
                runs = await runs_signed(
                    t, keys, trust, "uav-x", timeout=1.0, tries=3, refused=refused
                )
    finally:
        here.send("stop")
        proc.join(timeout=10)
    assert runs is False
    assert len(refused) == 3, refused  # one answer per try, each refused
    assert all(claimed == "uav-x" and "signature" in why for claimed, why in refused), refused
    lines = [r.getMessage() for r in caplog.records if "runs" in r.getMessage()]
    assert len(lines) == 1, lines
    assert "3 directory answer(s) in its name refused" in lines[0]
    assert "no answer signed with its key" in lines[0]


def _inform(sender: str, receiver: str, i: int) -> ACLMessage:
    """An inform from ``sender`` to ``receiver`` (no answer expected)."""
    return ACLMessage(
        performative=Performative.INFORM,
        sender=sender,
        receivers=[receiver],
        content={"i": i},
        conversation_id=f"c-{i}",
    )
