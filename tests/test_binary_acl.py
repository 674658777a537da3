"""The binary form of ACL envelopes between real platforms over zenoh (``docs/wire.md``).

Two platforms on loopback zenoh sessions in this process, ``uav-a`` sending and ``uav-b``
receiving on its lane (envelopes open on zenoh's thread), and an attacker's plain zenoh
session in the same mesh: it records what uav-a sends and puts hostile payloads on
uav-b's ACL key. Each refusal is asserted with its code, its count and its audit record,
and nothing of it reaches an agent. A pair where one side seals in the JSON form
(``binary_acl=False``) talks both ways.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import queue
import re
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import msgpack
import orjson
import pytest
import zenoh
from test_interface import Echo, serve, untouched

from agents import AgentPlatform, request, wire_key
from agents._interface import InterfaceAgent
from agents._security import KeyPair, SecurityPolicy, TrustStore
from agents.transports import ZenohConfig, ZenohTransport
from agents.transports import free_tcp_port as free_port

pytestmark = pytest.mark.timeout(120)

WAIT = 10.0  # the bound on any single wait (a busy machine); each test ends far below it


@dataclass
class Pair:
    """uav-a (asker) and uav-b (echo, on its lane), and an attacker's zenoh session."""

    pa: AgentPlatform
    pb: AgentPlatform
    asker: Echo
    echo: Echo
    fed: str
    raw: zenoh.Session
    seed: int
    wire: queue.Queue[bytes]  # what reaches uav-b's ACL key, as the attacker saw it

    @property
    def inbox(self) -> str:
        """uav-b's ACL key."""
        return wire_key(self.fed, "acl", "uav-b")

    def put(self, payload: bytes) -> None:
        """Publish on uav-b's ACL key as the attacker, the put never dropped on the way."""
        self.raw.put(self.inbox, payload, congestion_control=zenoh.CongestionControl.BLOCK)


def _attacker(port: int) -> zenoh.Session:
    """A plain zenoh client of the platforms' mesh: no key, no trust file."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


@contextlib.asynccontextmanager
async def pair(
    *,
    a: dict[str, Any] | None = None,
    b: dict[str, Any] | None = None,
) -> AsyncIterator[Pair]:
    """uav-a and uav-b over zenoh (``a``, ``b``: their InterfaceAgent's options)."""
    fed = f"binacl-{uuid.uuid4().hex[:12]}"
    keys = {n: KeyPair.generate(n) for n in ("uav-a", "uav-b")}
    trusted = {n: k.public_key for n, k in keys.items()}
    seed = free_port()
    ta = ZenohTransport(ZenohConfig.loopback(seed))
    tb = ZenohTransport(ZenohConfig.loopback(free_port(), connect=[seed]))
    # one lane a process: uav-b's, so what it receives opens on zenoh's thread
    ia_a = InterfaceAgent(
        keys["uav-a"], TrustStore(fed, trusted), audit_interval=0.02, lane=False, **(a or {})
    )
    ia_b = InterfaceAgent(keys["uav-b"], TrustStore(fed, trusted), audit_interval=0.02, **(b or {}))
    wire: queue.Queue[bytes] = queue.Queue()
    async with contextlib.AsyncExitStack() as stack:
        await stack.enter_async_context(ta)
        await stack.enter_async_context(tb)
        raw = _attacker(seed)
        stack.callback(raw.close)
        sub = raw.declare_subscriber(
            wire_key(fed, "acl", "uav-b"), lambda s: wire.put(s.payload.to_bytes())
        )
        stack.callback(sub.undeclare)
        pa = await stack.enter_async_context(
            AgentPlatform("uav-a", ta, federation=fed, channel=ia_a)
        )
        pb = await stack.enter_async_context(
            AgentPlatform("uav-b", tb, federation=fed, channel=ia_b)
        )
        asker = await serve(pa, "asker")
        echo = await serve(pb, "echo")
        async with asyncio.timeout(WAIT * 3):
            # the mesh is up once uav-a saw uav-b's liveliness token come (a token alive
            # before a platform starts is not reported to it: uav-a's, to uav-b)
            while "uav-b" not in ia_a._alive:  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            yield Pair(pa, pb, asker, echo, fed, raw, seed, wire)


def _ia(platform: AgentPlatform) -> InterfaceAgent:
    assert isinstance(platform.channel, InterfaceAgent)
    return platform.channel


async def _captured(p: Pair) -> bytes:
    """The envelope of a real request of uav-a to uav-b, as the attacker recorded it.

    Asked again while the attacker's subscription is still on its way through the mesh
    (its first requests then pass unseen), within the bound of one wait.
    """
    async with asyncio.timeout(WAIT):
        while True:
            while not p.wire.empty():
                p.wire.get_nowait()
            assert await request(p.asker, "echo@uav-b", {"x": 1}, ontology="demo") == {
                "echo": {"x": 1},
                "by": "echo@uav-b",
            }
            for _ in range(100):  # a zenoh callback's queue: polled, 0.5 s
                if not p.wire.empty():
                    return p.wire.get_nowait()
                await asyncio.sleep(0.005)


async def _attack(p: Pair, payload: bytes, code: str, *, claimed: str | None = "uav-a") -> str:
    """Put ``payload`` on uav-b's ACL key: one more envelope counted as not opened, and
    audited as dropped with ``code`` and the ``claimed`` sender; the record's reason."""
    ib = _ia(p.pb)
    counted, seen = p.pb.stats.unauthenticated, {id(r) for r in ib.audit.records}
    p.put(payload)

    def found() -> dict[str, Any] | None:
        for r in ib.audit.records:
            if (
                id(r) not in seen
                and r["verdict"] == "dropped"
                and str(r["reason"]).startswith(f"{code}:")
            ):
                return r
        return None

    try:
        async with asyncio.timeout(WAIT):
            while (rec := found()) is None:  # noqa: ASYNC110 - the audit has no event
                await asyncio.sleep(0.005)
    except TimeoutError:
        raise AssertionError(
            f"no {code!r} record; the latest: {list(ib.audit.records)[-3:]}"
        ) from None
    assert rec.get("from") == claimed, rec
    assert p.pb.stats.unauthenticated == counted + 1, rec
    return str(rec["reason"])


def _mac_only(p: Pair, body: bytes) -> bytes:
    """A binary envelope uav-a's session seals MAC-only (what a downgraded peer sends)."""
    session = _ia(p.pa).sessions.session_for("uav-b")
    assert session is not None
    session._encrypt = False  # this one envelope only: uav-a encrypts otherwise
    try:
        return session.seal_binary(body)
    finally:
        session._encrypt = True


async def test_the_default_form_is_binary_and_encrypted_and_opens_on_the_lane() -> None:
    """What uav-a sends is a 7-item msgpack array without a readable body; uav-b answers."""
    async with pair() as p:
        envelope = await _captured(p)
        assert envelope[0] == 0x97
        v, frm, to, _sid, _ts, _n, box = msgpack.unpackb(envelope)
        assert (v, frm, to, type(box)) == (1, "uav-a", "uav-b", bytes)
        assert b'"x"' not in envelope
        assert _ia(p.pb).sessions.missing() == {}
        accepted = [r for r in _ia(p.pb).audit.records if r["verdict"] == "accepted"]
        assert accepted and accepted[-1]["from"] == "uav-a"


async def test_each_refusal_of_the_binary_form_is_counted_and_audited() -> None:
    """Malformed, wrong length, unencrypted, another label's box, replayed, forged: dropped."""
    async with pair() as p:
        envelope = await _captured(p)
        items = msgpack.unpackb(envelope)
        calls, received = len(p.echo.calls), p.echo.stats.received
        body = b'{"performative":"inform","sender":"asker@uav-a","receivers":["echo@uav-b"]}'

        reason = await _attack(p, b"\x97\xc1" + envelope[2:], "malformed", claimed=None)
        assert "not msgpack" in reason
        reason = await _attack(p, msgpack.packb(items[:6]), "malformed", claimed=None)
        assert "array of 8 items" in reason
        reason = await _attack(p, _mac_only(p, body), "unencrypted")
        assert "requires encrypted" in reason

        # the box of a JSON envelope sealed for uav-b, moved into the binary form: its
        # label and nonce are the JSON form's, so it is no binary envelope's
        sent = orjson.loads(_ia(p.pa).sessions.seal("uav-b", body))
        moved = [1, "uav-a", "uav-b", sent["sid"], sent["ts_ms"], sent["n"]]
        reason = await _attack(p, msgpack.packb([*moved, base64.b64decode(sent["box"])]), "forged")
        assert "authentication tag" in reason

        await _attack(p, envelope, "replayed")  # the very bytes uav-b accepted
        flipped = items[6][:-1] + bytes([items[6][-1] ^ 0x80])
        reason = await _attack(p, msgpack.packb([*items[:5], items[5] + 50, flipped]), "forged")
        assert "authentication tag" in reason
        misdirected = msgpack.packb([*items[:2], "uav-c", *items[3:]])
        await _attack(p, misdirected, "misdirected")
        unknown = msgpack.packb([*items[:3], "A" * 22, *items[4:]])
        await _attack(p, unknown, "unknown-session")
        untouched(p.echo, calls, received)
        # and uav-a is still heard (the unknown session made uav-b agree a new one, so the
        # loss count depends on which session this goes on: tests/test_security_binacl.py)
        assert await request(p.asker, "echo@uav-b", 2, ontology="demo") == {
            "echo": 2,
            "by": "echo@uav-b",
        }


async def test_a_json_labelled_mac_on_the_binary_form_is_forged() -> None:
    """Where MAC-only is accepted: a JSON envelope's MAC never verifies a binary one."""
    lax = SecurityPolicy(encrypt=False, require_encryption=False)
    async with pair(a={"policy": lax}, b={"policy": lax}) as p:
        envelope = await _captured(p)
        assert envelope[0] == 0x98  # MAC-only: [v, from, to, sid, ts_ms, n, body, mac]
        calls, received = len(p.echo.calls), p.echo.stats.received
        body = b'{"performative":"inform","sender":"asker@uav-a","receivers":["echo@uav-b"]}'
        sent = orjson.loads(_ia(p.pa).sessions.seal("uav-b", body))
        head = [1, "uav-a", "uav-b", sent["sid"], sent["ts_ms"], sent["n"]]
        as_binary = msgpack.packb([*head, body, base64.b64decode(sent["mac"])])
        reason = await _attack(p, as_binary, "forged")
        assert "bad MAC" in reason
        untouched(p.echo, calls, received)


@pytest.mark.parametrize("json_side", ["uav-a", "uav-b"])
async def test_a_pair_with_one_side_sealing_json_talks_both_ways(json_side: str) -> None:
    """``binary_acl=False`` on one side: each sends its form, each reads the other's."""
    old = {"binary_acl": False}
    async with pair(**({"a": old} if json_side == "uav-a" else {"b": old})) as p:
        inbox_a: queue.Queue[bytes] = queue.Queue()
        sub = p.raw.declare_subscriber(
            wire_key(p.fed, "acl", "uav-a"), lambda s: inbox_a.put(s.payload.to_bytes())
        )
        try:
            envelope = await _captured(p)  # uav-a asks, uav-b answers
            assert await request(p.echo, "asker@uav-a", 3, ontology="demo") == {
                "echo": 3,
                "by": "asker@uav-a",
            }
            async with asyncio.timeout(WAIT):
                while inbox_a.qsize() < 2:  # noqa: ASYNC110 - a zenoh callback's queue
                    await asyncio.sleep(0.005)
        finally:
            sub.undeclare()
        to_a = inbox_a.get_nowait()
        # each side's envelopes in its own form
        assert (envelope[:1] == b"{") == (json_side == "uav-a")
        assert (to_a[:1] == b"{") == (json_side == "uav-b")
        assert envelope[:1] in (b"{", b"\x97") and to_a[:1] in (b"{", b"\x97")
        for platform in (p.pa, p.pb):
            assert _ia(platform).sessions.missing() == {}
            assert platform.stats.unauthenticated == 0


async def test_a_sample_batch_put_on_a_real_nodes_acl_key_is_audited_forged() -> None:
    async with pair() as p:
        await _captured(p)  # a session is there
        batch = _ia(p.pa).sessions.seal_bytes("uav-b", msgpack.packb({"v": 1}))
        reason = await _attack(p, batch, "forged")
        assert "uav-a" in reason


def _masked(record: dict[str, Any]) -> dict[str, Any]:
    """An audit record without what differs between two runs (times, ids, counters)."""
    keep = {k: v for k, v in record.items() if k not in ("ts", "seq", "id")}
    keep["reason"] = re.sub(r"[A-Za-z0-9_-]{22}|\d+", "#", str(keep.get("reason")))
    return keep


async def _replay_record(binary: bool) -> tuple[dict[str, Any], dict[str, int]]:
    """A captured envelope of uav-a put again on uav-b's ACL key: its audit record."""
    async with pair(a={"binary_acl": binary}) as p:
        sent = await _captured(p)
        assert (sent[:1] == b"{") is not binary
        await _attack(p, sent, "replayed")
        ib = _ia(p.pb)
        rec = next(r for r in reversed(ib.audit.records) if r["verdict"] == "dropped")
        return _masked(rec), ib.missing()


async def test_a_replay_is_audited_alike_in_both_forms_on_a_real_node() -> None:
    json_rec, json_missing = await _replay_record(False)
    bin_rec, bin_missing = await _replay_record(True)
    assert json_rec == bin_rec
    assert json_missing == bin_missing
    assert json_missing.get("uav-a", 0) == 0


async def test_the_missing_count_of_a_real_node_spans_both_forms() -> None:
    """uav-a switches form between envelopes; one of each form lost: two missing."""
    from test_security_binacl import MSG

    async with pair() as p:
        await _captured(p)
        ia, ib = _ia(p.pa), _ia(p.pb)
        # two envelopes sealed, one per form, and never published: lost on the way
        ia.sessions.seal("uav-b", MSG)
        ia.sessions.seal_binary("uav-b", MSG)
        ia._seal = ia.sessions.seal  # the JSON form from now on
        assert await request(p.asker, "echo@uav-b", {"z": 3}, ontology="demo") == {
            "echo": {"z": 3},
            "by": "echo@uav-b",
        }
        assert ib.missing() == {"uav-a": 2}
