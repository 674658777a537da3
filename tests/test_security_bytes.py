"""Binary sealed envelopes for sample batches (Session.seal_bytes / SessionTable.open_bytes)."""

from __future__ import annotations

import base64
import functools
import hashlib
import hmac
import os
from dataclasses import dataclass

import msgpack
import orjson
import pytest
from hypothesis import given
from hypothesis import strategies as st

from agents._exceptions import (
    AuthenticationError,
    Expired,
    Forged,
    Malformed,
    MessageError,
    Misdirected,
    Replayed,
    UnknownPlatform,
    UnknownSession,
)
from agents._security import Handshake, KeyPair, SecurityPolicy, Session, SessionTable, TrustStore

T0 = 1_795_000_000.0
BODY = msgpack.packb({"v": 1, "s": "car5-state", "b": [[1.5, 10, 11], ["x", 12, 13]]})
ACL = orjson.dumps(
    {"v": 1, "performative": "inform", "sender": "a@uav-a", "receivers": ["b@uav-b"]}
)
# These tests read the MAC-only envelope format; platforms encrypt by default, and the
# tests of the encrypted form say encrypt=True.
MacPolicy = functools.partial(SecurityPolicy, encrypt=False)

KEYS = {name: KeyPair.generate(name) for name in ("uav-a", "uav-b", "uav-c")}


class Clock:
    """A settable clock shared by both platforms of a test."""

    def __init__(self, t: float = T0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@dataclass
class Platform:
    hs: Handshake
    table: SessionTable


def make_platform(name: str, clock: Clock, policy: SecurityPolicy | None = None) -> Platform:
    policy = policy or MacPolicy()
    trust = TrustStore("demo", {p: KEYS[p].public_key for p in ("uav-a", "uav-b")})
    return Platform(
        Handshake(KEYS[name], trust, policy=policy, clock=clock),
        SessionTable(name, trust, policy=policy, clock=clock),
    )


def connect(a: Platform, b: Platform) -> tuple[Session, Session]:
    reply, sb = b.hs.respond(a.hs.initiate(b.table.me))
    sa = a.hs.finish(reply)
    a.table.add(sa)
    b.table.add(sb)
    return sa, sb


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def pair(clock: Clock) -> tuple[Platform, Platform]:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    return a, b


def fields(envelope: bytes) -> list[object]:
    out: list[object] = msgpack.unpackb(envelope, raw=False)
    return out


def edit(envelope: bytes, index: int, value: object) -> bytes:
    env = fields(envelope)
    env[index] = value
    return bytes(msgpack.packb(env))


# --------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("encrypt", [False, True])
def test_round_trip_both_directions(clock: Clock, encrypt: bool) -> None:
    policy = MacPolicy(encrypt=encrypt)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    sa, sb = connect(a, b)
    for i in range(3):
        assert b.table.open_bytes(a.table.seal_bytes("uav-b", BODY)) == ("uav-a", BODY)
        back = BODY + bytes([i])
        assert a.table.open_bytes(b.table.seal_bytes("uav-a", back)) == ("uav-b", back)
    env = fields(a.table.seal_bytes("uav-b", BODY))
    assert env[:3] == [1, "uav-a", "uav-b"] and env[3] == sa.sid and env[5] == 4
    assert env[4] == int(T0 * 1000)
    if encrypt:
        assert len(env) == 7 and BODY not in env[6]  # type: ignore[operator]
    else:
        assert len(env) == 8 and env[6] == BODY and len(env[7]) == 32  # type: ignore[arg-type]
    assert sa.sent_binary == 4 and sa.sent == 0 and sb.received == 3


def test_mac_is_hmac_sha256_over_the_documented_input(clock: Clock) -> None:
    """What docs/wire.md says, reproduced from the direction key alone (another language could)."""
    keys = {label: bytes([i]) * 32 for i, label in enumerate(
        ("i2r mac", "r2i mac", "i2r box", "r2i box", "sid"))}  # fmt: skip
    session = Session(
        me="uav-a",
        peer="uav-b",
        federation="demo",
        sid="S1d",
        initiator=True,
        keys=keys,
        order=(0, "S1d"),
        policy=MacPolicy(),
        clock=clock,
    )
    v, frm, to, sid, ts, n, body, mac = fields(session.seal_bytes(BODY))
    assert ts == int(T0 * 1000)

    def lp(text: str) -> bytes:
        raw = text.encode()
        return len(raw).to_bytes(2, "big") + raw

    assert (v, frm, to, sid, n) == (1, "uav-a", "uav-b", "S1d", 1) and body == BODY
    msg = (
        b"dyknow-bin-v1 mac\x00"
        + lp("demo")
        + lp("uav-a")
        + lp("uav-b")
        + lp("S1d")
        + int(T0 * 1000).to_bytes(8, "big")
        + (1).to_bytes(8, "big")
        + BODY
    )
    assert mac == hmac.new(keys["i2r mac"], msg, hashlib.sha256).digest()


def test_json_and_binary_counters_and_windows_are_independent(
    pair: tuple[Platform, Platform],
) -> None:
    a, b = pair
    # many batches first: an ACL message sealed before them still opens afterwards
    acl = a.table.seal("uav-b", ACL)
    for _ in range(2000):
        b.table.open_bytes(a.table.seal_bytes("uav-b", BODY))
    assert b.table.open(acl) == ("uav-a", ACL)
    assert fields(a.table.seal_bytes("uav-b", BODY))[5] == 2001
    assert orjson.loads(a.table.seal("uav-b", ACL))["n"] == 2


def test_binary_and_json_envelopes_never_stand_for_each_other(
    pair: tuple[Platform, Platform],
) -> None:
    a, b = pair
    body = b'{"v":1}'
    v, frm, to, sid, ts, n, _raw, mac = fields(a.table.seal_bytes("uav-b", body))
    as_json = orjson.dumps(
        {
            "v": v,
            "from": frm,
            "to": to,
            "sid": sid,
            "ts_ms": ts,
            "n": n,
            "body": body.decode(),
            "mac": base64.b64encode(mac).decode(),  # type: ignore[arg-type]
        }
    )
    with pytest.raises(Forged):
        b.table.open(as_json)
    env = orjson.loads(a.table.seal("uav-b", body))
    as_bin = msgpack.packb(
        [1, env["from"], env["to"], env["sid"], env["ts_ms"], env["n"], body,
         base64.b64decode(env["mac"])]
    )  # fmt: skip
    with pytest.raises(Forged):
        b.table.open_bytes(as_bin)


def test_encrypted_binary_uses_its_own_nonces(clock: Clock) -> None:
    policy = MacPolicy(encrypt=True)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    body = b"x" * 64
    box_json = base64.b64decode(orjson.loads(a.table.seal("uav-b", body.decode()))["box"])
    box_bin = fields(a.table.seal_bytes("uav-b", body))[6]
    assert fields(a.table.seal_bytes("uav-b", body))[5] == 2
    # both are counter 1 under the same key: equal keystreams would be a disaster
    assert box_json[:64] != box_bin[:64]  # type: ignore[index]


def test_responder_session_is_confirmed_by_a_binary_envelope(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    assert b.table.session_for("uav-a") is None  # a responder never sends first
    b.table.open_bytes(a.table.seal_bytes("uav-b", BODY))
    assert b.table.session_for("uav-a") is not None


def test_binary_envelopes_count_towards_renewal(clock: Clock) -> None:
    policy = MacPolicy(renew_after_messages=3)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    a.table.seal("uav-b", ACL)
    a.table.seal_bytes("uav-b", BODY)
    assert not a.table.needs_renewal("uav-b")
    a.table.seal_bytes("uav-b", BODY)
    assert a.table.needs_renewal("uav-b")


# --------------------------------------------------------------------------- refusals


def test_forged_and_tampered(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    env = a.table.seal_bytes("uav-b", BODY)
    with pytest.raises(Forged) as info:
        b.table.open_bytes(edit(env, 7, os.urandom(32)))
    assert info.value.code == "forged" and info.value.platform == "uav-a"
    with pytest.raises(Forged):
        b.table.open_bytes(edit(env, 6, BODY[:-1] + b"\x00"))
    with pytest.raises(Malformed, match="32 bytes"):
        b.table.open_bytes(edit(env, 7, b"short"))
    assert b.table.open_bytes(env) == ("uav-a", BODY)


@pytest.mark.parametrize(
    ("index", "value", "error"),
    [
        (4, int(T0 * 1000) + 1, Forged),
        (5, 7, Forged),
        (3, "AAAAAAAAAAAAAAAAAAAAAA", UnknownSession),
        (2, "uav-c", Misdirected),
        (1, "uav-c", UnknownPlatform),
        (0, 2, Malformed),
        (4, -1, Malformed),
        (5, 0, Malformed),
        (6, "a string, not bytes", Malformed),
        (1, 5, Malformed),
    ],
)
def test_tampered_header_field(
    pair: tuple[Platform, Platform], index: int, value: object, error: type[Exception]
) -> None:
    a, b = pair
    env = a.table.seal_bytes("uav-b", BODY)
    with pytest.raises(error):
        b.table.open_bytes(edit(env, index, value))
    assert b.table.open_bytes(env) == ("uav-a", BODY)


def test_reflected_envelope_is_refused(pair: tuple[Platform, Platform]) -> None:
    a, _ = pair
    env = a.table.seal_bytes("uav-b", BODY)
    with pytest.raises(Misdirected):
        a.table.open_bytes(env)
    with pytest.raises(Forged):
        a.table.open_bytes(edit(edit(env, 1, "uav-b"), 2, "uav-a"))


def test_replay_and_reordering(clock: Clock) -> None:
    policy = MacPolicy(window=8)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    envs = [a.table.seal_bytes("uav-b", BODY) for _ in range(12)]
    b.table.open_bytes(envs[5])
    b.table.open_bytes(envs[3])  # reordered, inside the window
    with pytest.raises(Replayed):
        b.table.open_bytes(envs[3])
    b.table.open_bytes(envs[11])
    with pytest.raises(Replayed, match="older than the replay window"):
        b.table.open_bytes(envs[0])
    assert b.table.open_bytes(envs[10]) == ("uav-a", BODY)


def test_expired_timestamp_and_session(clock: Clock) -> None:
    policy = MacPolicy(skew=5, renew_after_seconds=60, grace=10)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    env = a.table.seal_bytes("uav-b", BODY)
    clock.t += 6
    with pytest.raises(Expired):
        b.table.open_bytes(env)
    clock.t += 100
    session = a.table._by_peer["uav-b"][0]
    with pytest.raises(Expired):
        session.seal_bytes(BODY)
    assert a.table.session_for("uav-b") is None
    with pytest.raises(UnknownSession):
        a.table.seal_bytes("uav-b", BODY)


def test_a_new_counter_on_a_session_that_is_over_or_stamped_ahead_is_refused(
    clock: Clock,
) -> None:
    """A binary envelope's counter being the newest yet admits nothing by itself: one stamped
    beyond the skew ahead of this clock, one on a renewed session past its grace, and one on
    a session past its lifetime are refused (Expired), each leaving the window as it was."""
    policy = MacPolicy(skew=7, renew_after_seconds=100, grace=10)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    sa1, _ = connect(a, b)
    clock.t += 8
    ahead = a.table.seal_bytes("uav-b", BODY)
    clock.t -= 8
    with pytest.raises(Expired, match="from this clock"):
        b.table.open_bytes(ahead)
    assert b.table.open_bytes(a.table.seal_bytes("uav-b", BODY)) == ("uav-a", BODY)
    clock.t += 1  # a later session: sessions agreed in the same ms are ordered by sid
    sa2, _ = connect(a, b)
    late = sa1.seal_bytes(BODY)
    assert b.table.open_bytes(sa2.seal_bytes(BODY)) == ("uav-a", BODY)  # b retires sa1
    clock.t += 5
    assert b.table.open_bytes(late) == ("uav-a", BODY)  # in flight, within the grace
    clock.t += 5.5
    with pytest.raises(Expired, match="grace period is over"):
        b.table.open_bytes(sa1.seal_bytes(BODY))  # stamped now, its counter the newest
    clock.t += 94.5  # 105 s after sa2 was agreed: its renewal is due, it still seals
    old = sa2.seal_bytes(BODY)
    clock.t += 6
    with pytest.raises(Expired, match="past its lifetime"):
        b.table.open_bytes(old)
    clock.t -= 6
    assert b.table.open_bytes(sa2.seal_bytes(BODY)) == ("uav-a", BODY)


def test_require_encryption_refuses_plain_binary(clock: Clock) -> None:
    a = make_platform("uav-a", clock)
    b = make_platform("uav-b", clock, MacPolicy(require_encryption=True))
    connect(a, b)
    with pytest.raises(Malformed, match="encrypted"):
        b.table.open_bytes(a.table.seal_bytes("uav-b", BODY))


def test_forged_box(clock: Clock) -> None:
    policy = MacPolicy(encrypt=True)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    env = a.table.seal_bytes("uav-b", BODY)
    box = bytearray(fields(env)[6])  # type: ignore[arg-type]
    box[0] ^= 1
    with pytest.raises(Forged):
        b.table.open_bytes(edit(env, 6, bytes(box)))
    assert b.table.open_bytes(env) == ("uav-a", BODY)


def test_sizes(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    with pytest.raises(MessageError, match="exceeds"):
        a.table.seal_bytes("uav-b", b"x" * 300_000)
    with pytest.raises(Malformed, match="exceeds"):
        b.table.open_bytes(b"\x00" * 300_000)


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\xc1",
        b"not msgpack at all \xff",
        msgpack.packb({"v": 1}),
        msgpack.packb([1, "uav-a", "uav-b"]),
        msgpack.packb([1, "uav-a", "uav-b", "sid", 1, 1, b"b", b"m", b"extra"]),
        b'{"v": 1}',
    ],
)
def test_malformed(pair: tuple[Platform, Platform], payload: bytes) -> None:
    _, b = pair
    with pytest.raises(Malformed):
        b.table.open_bytes(payload)


@given(st.binary(max_size=300))
def test_random_bytes_only_ever_raise_authentication_errors(data: bytes) -> None:
    clock = Clock()
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    try:
        b.table.open_bytes(data)
    except AuthenticationError:
        pass


def test_json_envelope_is_unchanged(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    env = orjson.loads(a.table.seal("uav-b", ACL))
    assert set(env) == {"v", "from", "to", "sid", "ts_ms", "n", "body", "mac"}
    assert b.table.open(orjson.dumps(env)) == ("uav-a", ACL)


def test_missing_counts_json_envelopes_that_never_opened_not_binary_ones(clock: Clock) -> None:
    policy = MacPolicy(window=8)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    _, sb = connect(a, b)
    envs = [a.table.seal("uav-b", ACL) for _ in range(20)]
    for i in (0, 2, 5):  # 1, 3 and 4 late (or lost) so far
        b.table.open(envs[i])
    for _ in range(5):  # batches: counted apart, they neither add nor hide a gap
        b.table.open_bytes(a.table.seal_bytes("uav-b", BODY))
    assert sb.missing == 3 and b.table.missing() == {"uav-a": 3}
    b.table.open(envs[3])  # late, within the window: no longer missing
    with pytest.raises(Replayed):
        b.table.open(envs[3])  # a replay opens nothing and counts nothing
    assert b.table.missing() == {"uav-a": 2}
    b.table.open(envs[19])
    with pytest.raises(Replayed, match="older than the replay window"):
        b.table.open(envs[1])  # too late: refused, stays missing
    assert b.table.missing() == {"uav-a": 2 + 13}
    assert b.table.forget("uav-a") == 1
    assert b.table.missing() == {"uav-a": 15}  # a dropped session's count stays
