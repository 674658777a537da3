"""A member that misbehaves costs a victim bounded logs and audit records, every drop counted.

The attacker is a *member* (``uav-m``, authenticated, running our own library); the victim
a spawned platform (the harness of test_member_authz, whose victim here also counts the
log records of our packages). Each test floods the victim with what it drops and asserts
the drop, its count, its summed-up audit record and a bounded log.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
from collections import Counter
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import pytest
import test_member_authz as authz
import zenoh
from test_faults import until
from test_member_authz import WAIT, audited, in_file, mallory, world

from agents import FIPA_REQUEST, Performative, wire_key
from federation._batch import pack_batch
from federation._service_content import ONTOLOGY
from federation._sessions import InterfaceSessions

pytestmark = pytest.mark.timeout(180)

P = Performative
_LOGGED: Counter[str] = Counter()  # in the victim: records logged, per logger


class _Counted(logging.Handler):
    """Counts what our packages log (WARNING and above) in the victim, per logger."""

    def emit(self, record: logging.LogRecord) -> None:
        _LOGGED[record.name] += 1


def victim_main(config_path: str, conn: Connection) -> None:
    """test_member_authz's victim, whose stats also say what it logged and its agents' stats."""
    for name in ("agents", "federation"):
        logging.getLogger(name).addHandler(_Counted(logging.WARNING))
    stats = authz._stats

    def more(p: Any) -> dict[str, Any]:
        agents = {a.name: dataclasses.asdict(a.stats) for a in p.agents.agents}
        return {**stats(p), "logged": dict(_LOGGED), "agent_stats": agents}

    authz._stats = more
    authz.victim_main(config_path, conn)


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> None:
    """Victims spawned by `world` run `victim_main` above."""
    monkeypatch.setattr(authz, "victim_main", victim_main)


async def test_unsolicited_answers_are_counted_audited_and_logged_boundedly(
    tmp_path: Path, counted: None
) -> None:
    n = 600
    big = "x" * 20_000  # what each would make the victim log, were it logged
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"]) as w:
        mal = await mallory(w)
        for i in range(n):
            kind = P.FAILURE if i % 2 else P.NOT_UNDERSTOOD
            await mal.send(mal.message(kind, "federation@uav-a", f"{i} {big}"))
            if i % 20 == 0:
                await asyncio.sleep(0.01)

        def unsolicited(s: dict[str, Any]) -> int:
            return int(s["agent_stats"]["federation"]["unsolicited"])

        def told(s: dict[str, Any]) -> int:
            return sum(r["count"] for r in audited(s, code="unsolicited", **{"from": "uav-m"}))

        # what reached the victim (the transport may shed some of such a burst), every one
        # counted and summed up in the audit
        s = await w.until_stats(
            "uav-a",
            lambda s: unsolicited(s) >= n * 0.9 and told(s) == unsolicited(s),
            "every unsolicited answer counted and summed up in the audit",
        )
        assert unsolicited(s) == s["platform"]["received_remote"]
        recs = audited(s, verdict="dropped", stage="delivery", code="unsolicited")
        assert len(recs) <= 20, len(recs)  # summed up, not one record each
        assert recs[-1]["reason"].startswith("unsolicited: ")
        assert len(recs[-1]["reason"]) < 1000  # the last one's content, cut short
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
        # logged once, then once per 1000: not a line (of 20 kB) each
        assert s["logged"].get("agents._agent", 0) <= 2, s["logged"]


async def test_invented_senders_neither_hide_nor_frame_a_members_dropped_batches(
    tmp_path: Path,
) -> None:
    rounds, ghosts = 12, 64
    async with asyncio.timeout(150), world(tmp_path, ["uav-b"], ["uav-c", "uav-m"]) as w:
        m = w.here["uav-m"]
        sessions = InterfaceSessions(m.interface)
        await sessions.ensure("uav-b")
        stream = wire_key(w.federation, "stream", "uav-b")
        for r in range(rounds):
            # an outsider's junk under invented sender names (any zenoh client may publish
            # it): each name its own summing-up key, until the proxy's bound
            for g in range(ghosts):
                await m.transport.publish(f"{stream}/ghost{r}-{g}/car1-state", b"junk")
            # then the member: a batch nobody agreed to, and one sealed by it but published
            # under uav-c's name
            for claimed in ("uav-m", "uav-c"):
                body = pack_batch("car1-state", [({"r": r}, r + 1, 0)], 0)
                await m.transport.publish(
                    f"{stream}/{claimed}/car1-state", sessions.seal_bytes("uav-b", body)
                )
            await asyncio.sleep(0.1)

        def told(s: dict[str, Any], code: str, frm: str) -> int:
            return sum(r["count"] for r in audited(s, stage="import", code=code, **{"from": frm}))

        s = await w.until_stats(
            "uav-b",
            lambda s: sum(r["count"] for r in audited(s, stage="import")) >= rounds * (ghosts + 2),
            "every dropped batch summed up in the audit",
        )
        # the member's own refusals are never summed up with the invented names' ("*")
        assert told(s, "unagreed", "uav-m") == rounds
        # and the batches it published as uav-c are its own, not uav-c's
        assert told(s, "wrong-sender", "uav-m") == rounds
        assert told(s, "wrong-sender", "uav-c") == 0
        recs = audited(s, stage="import")
        assert sum(r["count"] for r in recs) == rounds * (ghosts + 2)
        assert len(recs) <= 40 * 8, len(recs)  # the invented names are still bounded
        (last,) = audited(s, stage="import", code="wrong-sender")[-1:]
        await until(lambda: in_file(tmp_path, "uav-b", last), "the record in the audit file")


async def test_a_create_stream_cancelled_at_once_exports_nothing(tmp_path: Path) -> None:
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"]) as w:
        fed = w.here["uav-m"].federation_agent
        await fed.create_stream("uav-a", ["car0-state"], timeout=WAIT)  # sessions agreed
        mal = await mallory(w)
        to = fed.provider_of("uav-a")
        for i in range(1, 6):
            # a requester that gives up at once (a command interrupted): its create-stream
            # and the FIPA cancel in its conversation reach the provider together
            conversation = f"c-gave-up-{i}"
            create = {"action": "create-stream", "labels": [f"car{i}-state"]}
            fields = {"protocol": FIPA_REQUEST, "ontology": ONTOLOGY}
            fields["conversation_id"] = conversation
            await mal.send(mal.message(P.REQUEST, to, create, reply_with=f"r{i}", **fields))
            await mal.send(mal.message(P.CANCEL, to, None, **fields))
        await asyncio.sleep(2.0)
        # none of them runs (the exports' lease would end them only after 10 s)
        s = await w.stats("uav-a")
        assert [e[:2] for e in s["exports"]] == [("uav-m", "car0-state")], s["exports"]
        assert len(s["agreed"]) == 1 and s["refusals"] == {}


async def test_a_member_streaming_after_its_leave_is_counted_and_audited(tmp_path: Path) -> None:
    async with asyncio.timeout(150), world(tmp_path, ["uav-b"]) as w:
        m = w.here["uav-m"]
        assert (await w.ask("uav-b", "uav-m", ["car1-state"])).startswith("x-")
        await w.until_stats(
            "uav-b", lambda s: "import/uav-m/car1-state" in s["labels"], "the stream imported"
        )
        # uav-m says, signed, that it leaves; its export (20 batches a second) goes on
        assert m.agents.df is not None
        await m.agents.df.announce_leave()

        def gone(s: dict[str, Any]) -> int:
            return int(s["imports"]["totals"]["dropped_samples"].get("sender-gone", 0))

        def told(s: dict[str, Any]) -> int:
            recs = audited(s, stage="import-samples", code="sender-gone", **{"from": "uav-m"})
            return sum(r["count"] for r in recs)

        s = await w.until_stats(
            "uav-b",
            lambda s: gone(s) >= 20 and told(s) == gone(s),
            "the samples of a member that left dropped, counted and audited summed up",
        )
        recs = audited(s, stage="import-samples", code="sender-gone")
        assert len(recs) <= 2 * 30, len(recs)  # one per report interval at most
        assert recs[-1]["stream"] == "car1-state"
        assert "left" in recs[-1]["reason"]


def _plain_client(tmp: Path, name: str) -> zenoh.Session:
    """A plain zenoh client of ``name``'s listener (from its config): no key, no trust file."""
    listen = json.loads((tmp / f"{name}.json").read_text())["transport"]["listen"]
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps(listen))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


async def test_a_batch_put_again_by_a_plain_client_is_refused_as_replayed_newest_or_not(
    tmp_path: Path,
) -> None:
    """A member's sealed batch captured and put again by a plain zenoh client: while its
    counter is still the newest uav-b has seen, and after a later one (inside the window).
    Each copy is refused as replayed, counted and audited; only the originals open (their
    stream unagreed here, so each is dropped as that, authentic)."""
    async with asyncio.timeout(150), world(tmp_path, ["uav-b"]) as w:
        m = w.here["uav-m"]
        sessions = InterfaceSessions(m.interface)
        await sessions.ensure("uav-b")
        key = wire_key(w.federation, "stream", "uav-b") + "/uav-m/car1-state"
        body = pack_batch("car1-state", [({"r": 1}, 1, 0)], 0)
        # nothing else is sealed to uav-b in binary: no export of uav-m's runs to it
        first, later = sessions.seal_bytes("uav-b", body), sessions.seal_bytes("uav-b", body)

        def samples(s: dict[str, Any], reason: str) -> int:
            return int(s["imports"]["totals"]["dropped_samples"].get(reason, 0))

        def batches(s: dict[str, Any], reason: str) -> int:
            return int(s["imports"]["totals"]["dropped_batches"].get(reason, 0))

        def told(s: dict[str, Any]) -> int:
            recs = audited(s, stage="import", code="replayed", **{"from": "uav-m"})
            return sum(r["count"] for r in recs)

        raw = _plain_client(tmp_path, "uav-b")
        try:
            put = raw.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            put.put(first)
            await w.until_stats("uav-b", lambda s: samples(s, "unagreed") == 1, "the original")
            put.put(first)  # its counter the newest yet
            s = await w.until_stats(
                "uav-b", lambda s: batches(s, "replayed") + samples(s, "unagreed") >= 2, "a copy"
            )
            assert (batches(s, "replayed"), samples(s, "unagreed")) == (1, 1)
            for payload in (later, first):  # a later original, then the copy again: older
                put.put(payload)
            s = await w.until_stats(
                "uav-b",
                lambda s: batches(s, "replayed") + samples(s, "unagreed") >= 4 and told(s) >= 2,
                "the later one, the copy, and their audit",
            )
        finally:
            raw.close()
        assert (batches(s, "replayed"), samples(s, "unagreed")) == (2, 2)
        assert s["imports"]["totals"]["injected"] == 0
        recs = audited(s, verdict="dropped", stage="import", code="replayed")
        assert sum(r["count"] for r in recs) == 2 and {r["from"] for r in recs} == {"uav-m"}
        await until(lambda: in_file(tmp_path, "uav-b", recs[-1]), "the record in the audit file")
