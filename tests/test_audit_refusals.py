"""Every kind of refusal between platforms is refused AND in the audit log, with its reason.

The audit log is three things (``docs/wire.md``, "Audit records"): the Interface Agent's
records in memory, the JSON-lines file (``audit_path``) and the batches published on
``dyknow/<fed>/v1/audit/<platform>``. tests/test_interface.py checks the in-memory records
of several refusals; here each kind gets its own test and must be in all three, with the
same record (verdict, claimed sender, reason starting with its code), and nothing of what
was refused may reach an agent. Hostile inputs are real envelopes and handshakes, captured
on the wire or made with real (or impostor) keys, as in tests/test_interface.py, whose
helpers are reused.
"""

from __future__ import annotations

import asyncio
import base64
import logging
import os
import re
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import orjson
import pytest
from test_interface import (
    FED,
    WAIT,
    Echo,
    Fed,
    acl,
    federation,
    ia,
    records,
    serve,
    until,
    untouched,
)

from agents import AgentPlatform, Performative, Refused, request, wire_key
from agents._security import Handshake, KeyPair, OwnerBatches, Session, TrustStore
from agents.transports import Message, Subscription


@dataclass
class Watched:
    """uav-b (audit file, published audit watched), uav-a with a session, a captured request."""

    fed: Fed
    pa: AgentPlatform
    pb: AgentPlatform
    asker: Echo
    echo: Echo
    envelope: bytes
    offset: list[float]  # uav-a's clock offset (s)
    path: Path
    feed: Subscription[Message]
    published: list[dict[str, Any]]

    @property
    def inbox(self) -> str:
        """uav-b's ACL inbox key."""
        return wire_key(FED, "acl", "uav-b")

    @property
    def kx(self) -> str:
        """uav-b's key-exchange key."""
        return wire_key(FED, "kx", "uav-b")


@asynccontextmanager
async def watched(tmp_path: Path, *names: str) -> AsyncIterator[Watched]:
    """uav-a and uav-b with a session (and ``names`` in the trust file, not started)."""
    async with federation("uav-a", "uav-b", *names) as fed:
        offset = [0.0]
        path = tmp_path / "audit-uav-b.jsonl"
        raw = await fed.raw()
        feed = await raw.subscribe(wire_key(FED, "audit", "uav-b"))
        # JSON envelopes, whose fields these tests edit (tests/test_binary_acl.py: binary ones)
        pa = await fed.start("uav-a", clock=lambda: time.time() + offset[0], binary_acl=False)
        pb = await fed.start("uav-b", audit_path=path)
        wire = await raw.subscribe(wire_key(FED, "acl", "uav-b"))
        asker = await serve(pa, "asker", None)
        echo = await serve(pb, "echo")  # a protected service
        assert await request(asker, "echo@uav-b", {"x": 1}, ontology="demo") is not None
        envelope = (await wire.get(WAIT)).payload
        wire.close()
        yield Watched(fed, pa, pb, asker, echo, envelope, offset, path, feed, [])


async def logged(w: Watched, code: str, **match: Any) -> dict[str, Any]:
    """The audit record whose reason starts with ``code`` and whose fields equal ``match``.

    Waits for it in memory, then for the very same record in the audit file and in the
    published audit; fails naming what is missing.
    """

    def matches(r: dict[str, Any]) -> bool:
        reason = str(r.get("reason"))
        return reason.startswith(code) and all(r.get(k) == v for k, v in match.items())

    def in_memory() -> dict[str, Any] | None:
        return next((r for r in records(w.pb) if matches(r)), None)

    rec = await until(in_memory, f"an audit record {code!r} {match} in memory")

    def in_file() -> bool:
        if not w.path.exists():
            return False
        return rec in [orjson.loads(line) for line in w.path.read_bytes().splitlines()]

    await until(in_file, f"the record {rec} in the audit file")
    async with asyncio.timeout(WAIT):
        while rec not in w.published:
            msg = await w.feed.get()
            keys = ia(w.pb).keys  # sealed to uav-b's owner, signed with its key
            opened = OwnerBatches(keys, keys.public_key).open(msg.key, msg.payload)
            w.published += [orjson.loads(line) for line in opened.splitlines()]
    return rec


def envelope_fields(w: Watched) -> dict[str, Any]:
    """The captured envelope's fields."""
    env: dict[str, Any] = orjson.loads(w.envelope)
    return env


async def test_forged_handshake_signature(tmp_path: Path) -> None:
    """A handshake under a trusted name but signed with another key: no session, audited."""
    # tests/test_interface.py::test_key_exchanges_from_untrusted_or_forged_keys_are_dropped
    # checks the in-memory record (and the initiator's side); here: the whole audit log
    async with watched(tmp_path, "uav-c") as w:
        raw = await w.fed.raw()
        impostor = KeyPair.generate("uav-c")  # uav-c is trusted, with another key
        trust = TrustStore(
            FED, {"uav-c": impostor.public_key, "uav-b": w.fed.keys["uav-b"].public_key}
        )
        replies = await raw.query(w.kx, Handshake(impostor, trust).initiate("uav-b"), timeout=1)
        assert [r for r in replies if r.ok] == []
        rec = await logged(w, "forged:", verdict="dropped", stage="kx")
        assert rec["from"] == "uav-c"
        assert "signature" in rec["reason"]
        assert ia(w.pb).sessions.sessions("uav-c") == []


async def test_tampered_mac(tmp_path: Path) -> None:
    """An envelope whose ciphertext was changed, or whose box is made up, is dropped and audited."""
    # in-memory records: test_interface.py::test_forged_tampered_replayed_expired_and_…
    async with watched(tmp_path) as w:
        raw = await w.fed.raw()
        env = envelope_fields(w)
        calls, received = len(w.echo.calls), w.echo.stats.received
        box = base64.b64decode(env["box"])  # encrypted: the default
        flipped = box[:-1] + bytes([box[-1] ^ 0x80])
        tampered = {**env, "n": env["n"] + 1, "box": base64.b64encode(flipped).decode()}
        await raw.publish(w.inbox, orjson.dumps(tampered))
        rec = await logged(w, "forged:", verdict="dropped")
        assert rec["from"] == "uav-a"
        assert "authentication tag" in rec["reason"]
        made_up = {**env, "n": env["n"] + 2, "box": base64.b64encode(os.urandom(len(box))).decode()}
        await raw.publish(w.inbox, orjson.dumps(made_up))
        await until(lambda: len(records(w.pb, verdict="dropped")) == 2, "the made-up MAC")
        assert str(records(w.pb, verdict="dropped")[1]["reason"]).startswith("forged:")
        untouched(w.echo, calls, received)


async def test_replayed_envelope_and_handshake(tmp_path: Path) -> None:
    """The same envelope twice, or the same handshake request twice: the second is refused."""
    async with watched(tmp_path, "uav-c") as w:
        raw = await w.fed.raw()
        calls, received = len(w.echo.calls), w.echo.stats.received
        await raw.publish(w.inbox, w.envelope)  # the very bytes that were accepted
        rec = await logged(w, "replayed:", verdict="dropped")
        assert rec["from"] == "uav-a"
        assert "already seen" in rec["reason"]
        untouched(w.echo, calls, received)

        # a handshake request recorded on the wire and played again makes no second session
        c = w.fed.keys["uav-c"]
        init = Handshake(c, w.fed.trust_copy()).initiate("uav-b")
        assert [r.ok for r in await raw.query(w.kx, init, timeout=1)] == [True]
        assert [r.ok for r in await raw.query(w.kx, init, timeout=1)] == []
        rec = await logged(w, "replayed:", verdict="dropped", stage="kx")
        assert rec["from"] == "uav-c"
        assert len(ia(w.pb).sessions.sessions("uav-c")) == 1


@pytest.mark.parametrize("skew", [-120.0, 120.0])
async def test_expired_or_future_timestamp(tmp_path: Path, skew: float) -> None:
    """An envelope stamped two minutes off this clock (either way) is refused and audited."""
    # the late case's in-memory record: test_interface.py::test_forged_tampered_replayed_…
    async with watched(tmp_path) as w:
        calls, received = len(w.echo.calls), w.echo.stats.received
        w.offset[0] = skew  # uav-a's clock; its session with uav-b was made before
        await w.asker.send(acl("asker@uav-a", "echo@uav-b", {"x": 2}))
        rec = await logged(w, "expired:", verdict="dropped")
        assert rec["from"] == "uav-a"
        # how far off: two minutes, give or take the milliseconds the send took
        off = re.search(r"is ([+-]?[0-9.]+) s from this clock", rec["reason"])
        assert off is not None and abs(abs(float(off.group(1))) - 120) < 1, rec["reason"]
        assert "allowed ±30 s" in rec["reason"]
        untouched(w.echo, calls, received)


async def test_expired_handshake(tmp_path: Path) -> None:
    """A handshake request stamped two minutes ago (held back, replayed later) is refused."""
    async with watched(tmp_path, "uav-c") as w:
        raw = await w.fed.raw()
        late = Handshake(w.fed.keys["uav-c"], w.fed.trust_copy(), clock=lambda: time.time() - 120)
        assert [r for r in await raw.query(w.kx, late.initiate("uav-b"), timeout=1) if r.ok] == []
        rec = await logged(w, "expired:", verdict="dropped", stage="kx")
        assert rec["from"] == "uav-c"
        assert ia(w.pb).sessions.sessions("uav-c") == []


async def test_unknown_platform(tmp_path: Path) -> None:
    """A platform missing from the trust file opens no session, and its envelopes are dropped."""
    # the handshake's in-memory record: test_interface.py::test_key_exchanges_from_untrusted_…
    async with watched(tmp_path) as w:
        raw = await w.fed.raw()
        evil = KeyPair.generate("evil")
        trust = TrustStore(FED, {"evil": evil.public_key, "uav-b": w.fed.keys["uav-b"].public_key})
        replies = await raw.query(w.kx, Handshake(evil, trust).initiate("uav-b"), timeout=1)
        assert [r for r in replies if r.ok] == []
        rec = await logged(w, "untrusted:", verdict="dropped", stage="kx")
        assert rec["from"] == "evil"
        assert "not in the trust file" in rec["reason"]

        calls, received = len(w.echo.calls), w.echo.stats.received
        env = {**envelope_fields(w), "from": "evil"}
        await raw.publish(w.inbox, orjson.dumps(env))
        rec = await logged(w, "untrusted:", verdict="dropped", stage=None)
        assert rec["from"] == "evil"
        untouched(w.echo, calls, received)


async def test_an_untrusted_sender_is_logged_once_a_while_and_garbage_summed_up(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The operator of a platform that refuses an untrusted asker sees it in its log, rarely."""
    caplog.set_level(logging.WARNING, logger="agents._interface")

    def lines(text: str) -> list[str]:
        return [r.getMessage() for r in caplog.records if text in r.getMessage()]

    async with watched(tmp_path) as w:
        raw = await w.fed.raw()
        evil = KeyPair.generate("evil")
        trust = TrustStore(FED, {"evil": evil.public_key, "uav-b": w.fed.keys["uav-b"].public_key})
        for _ in range(3):  # an asker trying again and again
            await raw.query(w.kx, Handshake(evil, trust).initiate("uav-b"), timeout=1)
        await until(lambda: len(records(w.pb, **{"from": "evil"})) >= 3, "three refusals")
        assert lines("'evil'") == [
            "interface[uav-b]: refused a platform calling itself 'evil' (a claimed name, not "
            "authenticated): not in this platform's trust file (untrusted: platform 'evil' is "
            "not in the trust file); if it is one of yours, trust its key, then SIGHUP its "
            "node (dyknow node) or restart this platform (logged once per 30 s)"
        ]

        # a flood of made-up names: a few logged, the rest summed up in the next interval
        agent = ia(w.pb)
        for n in range(100):
            name = f"x{n}"
            agent.audit_unauthenticated(name, f"untrusted: platform {name!r} is not in", "kx")
        assert len(lines("calling itself '")) == 8
        monkeypatch.setattr("agents._interface_admit.UNTRUSTED_LOG_INTERVAL", 0.0)
        agent.audit_unauthenticated("evil", "untrusted: platform 'evil' is not in", "kx")
        (summed,) = lines("more refusal")
        assert summed.startswith("interface[uav-b]: 93 more refusal(s) of senders not in the ")
        assert len(lines("'evil'")) == 2  # a new interval: logged again


async def test_impersonation(tmp_path: Path) -> None:
    """uav-a's authentic envelope carrying a message from another platform's agent is dropped."""
    # in-memory records: test_interface.py::test_an_authenticated_platform_cannot_speak_for_…
    async with watched(tmp_path) as w:
        raw = await w.fed.raw()
        calls, received = len(w.echo.calls), w.echo.stats.received
        for sender in ("spy@uav-c", "df@uav-b"):
            body = acl(sender, "echo@uav-b", 9).to_json()
            await raw.publish(w.inbox, ia(w.pa).sessions.seal("uav-b", body))
            rec = await logged(w, "sender is not an agent of 'uav-a'", sender=sender)
            assert rec["verdict"] == "dropped"
            assert rec["from"] == "uav-a"  # the platform the envelope proves
        untouched(w.echo, calls, received)


async def test_private_service_from_outside(tmp_path: Path) -> None:
    """A request from another platform to a private service is refused, told and audited."""
    # in-memory record: test_interface.py::test_access_follows_service_visibility
    async with watched(tmp_path) as w:
        private = await serve(w.pb, "private", "private")
        with pytest.raises(Refused, match="access denied"):
            await request(w.asker, "private@uav-b", 1, ontology="demo", timeout=2)
        rec = await logged(w, "access denied", verdict="refused", receivers=["private@uav-b"])
        assert rec["sender"] == "asker@uav-a"
        assert rec["from"] == "uav-a"
        assert rec["performative"] == "request"
        assert "private@uav-b offers no service that platform 'uav-a' may use" in rec["reason"]
        assert private.calls == []
        assert private.stats.received == 0


async def test_protected_service_from_a_non_member(tmp_path: Path) -> None:
    """A protected service is for federation members: a platform outside it never reaches it.

    Members (in the trust file) may use protected services through the Interface Agent;
    a non-member cannot open a session, so its request never arrives, and its attempts
    (handshake and envelopes on a made-up session) are audited.
    """
    async with watched(tmp_path) as w:
        # a member may (the positive control: the setup's request went to it as well)
        assert await request(w.asker, "echo@uav-b", 2, ontology="demo") == {
            "echo": 2,
            "by": "echo@uav-b",
        }
        calls, received = len(w.echo.calls), w.echo.stats.received
        # a non-member: its own keys and its own trust file, which trusts uav-b
        outsider = KeyPair.generate("outsider")
        trust = TrustStore(
            FED, {"outsider": outsider.public_key, "uav-b": w.fed.keys["uav-b"].public_key}
        )
        t = await w.fed.raw()
        channel = ia(w.pa).__class__(outsider, trust, handshake_timeout=0.5)
        async with AgentPlatform("outsider", t, federation=FED, channel=channel) as po:
            agent = await serve(po, "asker", None)
            with pytest.raises(Exception, match=r"not in the trust file|refused|did not answer"):
                await request(agent, "echo@uav-b", 3, ontology="demo", timeout=2)
        rec = await logged(w, "untrusted:", verdict="dropped", stage="kx")
        assert rec["from"] == "outsider"
        # nor can it use a session it does not have: an envelope in its name is dropped
        env = {**envelope_fields(w), "from": "outsider", "n": 99}
        await (await w.fed.raw()).publish(w.inbox, orjson.dumps(env))
        rec = await logged(w, "untrusted:", verdict="dropped", stage=None, **{"from": "outsider"})
        untouched(w.echo, calls, received)


async def test_misdirected_and_unknown_session(tmp_path: Path) -> None:
    """An envelope for another platform, or on a session uav-b does not hold, is dropped."""
    async with watched(tmp_path, "uav-c") as w:
        raw = await w.fed.raw()
        calls, received = len(w.echo.calls), w.echo.stats.received
        env = envelope_fields(w)
        await raw.publish(w.inbox, orjson.dumps({**env, "to": "uav-c"}))
        rec = await logged(w, "misdirected:", verdict="dropped")
        assert rec["from"] == "uav-a"
        await raw.publish(w.inbox, orjson.dumps({**env, "sid": "A" * 22}))
        rec = await logged(w, "unknown-session:", verdict="dropped")
        assert rec["from"] == "uav-a"
        untouched(w.echo, calls, received)


async def test_a_message_claiming_the_receivers_own_platform(tmp_path: Path) -> None:
    """A sender of uav-b's own platform from outside is dropped, never audited as accepted.

    Whoever holds uav-b's key cannot open a session with uav-b as uav-b (the handshake is
    misdirected); were a session with itself in its table all the same, a message from
    "its own" agent on it is dropped, counted as forged and audited with its reason, and
    the audit has no record of it as accepted (alone, in a batch, or to several receivers).
    """
    async with watched(tmp_path) as w:
        raw = await w.fed.raw()
        table = ia(w.pb).sessions
        init = orjson.loads(Handshake(w.fed.keys["uav-b"], table.trust).initiate("uav-a"))
        replies = await raw.query(w.kx, orjson.dumps({**init, "to": "uav-b"}), timeout=1)
        assert [r for r in replies if r.ok] == []
        rec = await logged(w, "misdirected:", verdict="dropped", stage="kx")
        assert "this platform itself" in rec["reason"]
        assert table.sessions("uav-b") == []

        keys = {k: os.urandom(32) for k in ("i2r mac", "r2i mac", "i2r box", "r2i box")}
        made: dict[str, Any] = {"me": "uav-b", "peer": "uav-b", "federation": FED}
        made.update(sid="S" * 22, keys=keys, order=(0, "S" * 22), policy=table.policy)
        mine = Session(initiator=True, clock=time.time, **made)
        table.add(Session(initiator=False, clock=time.time, **made))

        calls, received = len(w.echo.calls), w.echo.stats.received
        counts, forged = dict(ia(w.pb).audit.counts), w.pb.stats.forged
        inform = Performative.INFORM
        alone = acl("spy@uav-b", "echo@uav-b", 1, performative=inform)
        several = acl("spy@uav-b", "echo@uav-b", 2, performative=inform)
        several = several.model_copy(update={"receivers": ["echo@uav-b", "asker@uav-a"]})
        batched = acl("spy@uav-b", "echo@uav-b", 3, performative=inform)
        for body in (alone.to_json(), several.to_json(), b"[" + batched.to_json() + b"]"):
            await raw.publish(w.inbox, mine.seal(body))
        for m in (alone, several, batched):
            rec = await logged(
                w, "sender claims this platform 'uav-b'", conversation_id=m.conversation_id
            )
            assert (rec["verdict"], rec["from"], rec["sender"]) == ("dropped", "uav-b", "spy@uav-b")
            assert rec["receivers"] == m.receivers
        assert w.pb.stats.forged == forged + 3
        after = ia(w.pb).audit.counts
        assert after["dropped"] == counts["dropped"] + 3
        assert after["accepted"] == counts["accepted"]
        ours = {"from": "uav-b", "verdict": "accepted"}
        assert records(w.pb, **ours) == []
        lines = [orjson.loads(line) for line in w.path.read_bytes().splitlines()]
        for log in (lines, w.published):
            assert [r for r in log if all(r.get(k) == v for k, v in ours.items())] == []
        untouched(w.echo, calls, received)


def test_a_reason_no_site_bounded_is_kept_on_one_line_in_memory_and_in_the_file(
    tmp_path: Path,
) -> None:
    """Whatever a refusing site left unescaped, an audit record's reason holds no raw
    newline nor escape: each written as `agents.quoted` writes it, nothing cut; a
    printable reason is kept as it is."""
    from agents import AuditLog

    path = tmp_path / "audit.jsonl"
    audit = AuditLog(path=path, platform="uav-a")
    forged = 'x\n{"verdict": "accepted"}\x1b[2J\u202e'
    audit.record(verdict="refused", stage="gateway", reason=f"refuse: {forged}")
    audit.record(verdict="refused", stage="gateway", reason="refuse: 'label' (plain)")
    audit.take()
    want = 'refuse: x\\x0a{"verdict": "accepted"}\\x1b[2J\\u202e'
    assert [r["reason"] for r in audit.records] == [want, "refuse: 'label' (plain)"]
    lines = path.read_text().splitlines()
    assert [orjson.loads(line)["reason"] for line in lines] == [
        want,
        "refuse: 'label' (plain)",
    ]


async def test_a_claimed_name_of_any_size_is_audited_bounded_on_one_line(tmp_path: Path) -> None:
    """An envelope claiming a name no platform has, of 20 000 characters with a forged
    line and a terminal escape, is dropped; its record names the claim by its start, on
    one line, in `from` and in the reason: one envelope writes a record of bounded size."""
    async with watched(tmp_path) as w:
        raw = await w.fed.raw()
        claim = 'evil\n{"verdict": "accepted"}\x1b[2J' + "e" * 20_000
        calls, received = len(w.echo.calls), w.echo.stats.received
        env = {**envelope_fields(w), "from": claim}
        await raw.publish(w.inbox, orjson.dumps(env))
        rec = await logged(w, "untrusted:", verdict="dropped", stage=None)
        assert rec["from"].startswith('evil\\x0a{"verdict": "accepted"}\\x1b[2Je')
        assert rec["from"].endswith("… (20032 characters, 19974 left out)")
        assert rec["reason"] == (
            "untrusted: platform " + repr(claim[:64] + "…") + " is not in the trust file"
        )
        assert len(orjson.dumps(rec)) < 1000
        untouched(w.echo, calls, received)
