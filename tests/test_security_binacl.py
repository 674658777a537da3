"""Binary ACL envelopes (Session.seal_binary; SessionTable.open reads both forms).

The msgpack form of an ACL envelope (``docs/wire.md``, "Sealed envelopes"): its own
labels and nonce space, the JSON form's counter and replay window, and the same
refusals as either envelope kind. The test of the interface over zenoh is
tests/test_binary_acl.py.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os

import msgpack
import orjson
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nacl import bindings as sodium
from test_security_bytes import (
    ACL,
    BODY,
    T0,
    Clock,
    MacPolicy,
    Platform,
    connect,
    edit,
    fields,
    make_platform,
)

from agents._exceptions import (
    AuthenticationError,
    Expired,
    Forged,
    Malformed,
    Misdirected,
    Replayed,
    Unencrypted,
    UnknownPlatform,
    UnknownSession,
)
from agents._security import SecurityPolicy, Session, SessionTable

EncPolicy = SecurityPolicy  # encrypted, encryption required: the default


@pytest.fixture
def clock() -> Clock:
    return Clock()


def pair_of(clock: Clock, policy: SecurityPolicy) -> tuple[Platform, Platform]:
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    return a, b


def lp(text: str) -> bytes:
    raw = text.encode()
    return len(raw).to_bytes(2, "big") + raw


KEYS32 = {label: bytes([i + 1]) * 32 for i, label in enumerate(
    ("i2r mac", "r2i mac", "i2r box", "r2i box", "sid"))}  # fmt: skip


def fixed_session(clock: Clock, policy: SecurityPolicy) -> Session:
    """An initiator's session under known keys: its bytes are reproduced from the docs."""
    return Session(
        me="uav-a",
        peer="uav-b",
        federation="demo",
        sid="S1d",
        initiator=True,
        keys=KEYS32,
        order=(0, "S1d"),
        policy=policy,
        clock=clock,
    )


def header(label: bytes, ts: int, n: int) -> bytes:
    """Fields 1-7 of "Envelope bytes" for uav-a to uav-b on session S1d."""
    return (
        label + b"\x00" + lp("demo") + lp("uav-a") + lp("uav-b") + lp("S1d")
        + ts.to_bytes(8, "big") + n.to_bytes(8, "big")
    )  # fmt: skip


# --------------------------------------------------------------------------- the bytes


@pytest.mark.parametrize("encrypt", [False, True])
def test_round_trip_both_directions_in_the_documented_layout(clock: Clock, encrypt: bool) -> None:
    """Both forms open with `open`; the sender's bytes are those docs/wire.md spells out."""
    a, b = pair_of(clock, MacPolicy(encrypt=encrypt))
    for i in range(3):
        env = a.table.seal_binary("uav-b", ACL)
        assert env[0] == (0x97 if encrypt else 0x98)
        items = fields(env)
        ts, n, payload = items[4], items[5], items[6]
        layout = (
            bytes([env[0]]) + msgpack.packb(items[:4])[1:]  # the header's shortest
            + b"\xcf" + ts.to_bytes(8, "big") + b"\xcf" + n.to_bytes(8, "big")  # type: ignore[attr-defined]
            + b"\xc6" + len(payload).to_bytes(4, "big") + payload  # type: ignore[arg-type,operator]
            + (b"" if encrypt else b"\xc4\x20" + items[7])  # type: ignore[operator]
        )  # fmt: skip
        assert env == layout
        assert b.table.open(env) == ("uav-a", ACL)
        back = ACL + b" " * i
        assert a.table.open(b.table.seal_binary("uav-a", back)) == ("uav-b", back)
    got = fields(a.table.seal_binary("uav-b", ACL))
    assert got[:3] == [1, "uav-a", "uav-b"] and got[4] == int(T0 * 1000) and got[5] == 4
    if encrypt:
        assert len(got) == 7 and ACL not in got[6]  # type: ignore[operator]
    else:
        assert len(got) == 8 and got[6] == ACL and len(got[7]) == 32  # type: ignore[arg-type]


def test_mac_is_hmac_sha256_over_the_documented_input(clock: Clock) -> None:
    """The MAC-only form reproduced from the direction key and docs/wire.md alone."""
    v, frm, to, sid, ts, n, body, mac = fields(fixed_session(clock, MacPolicy()).seal_binary(ACL))
    assert (v, frm, to, sid, ts, n, body) == (1, "uav-a", "uav-b", "S1d", int(T0 * 1000), 1, ACL)
    msg = header(b"dyknow-acl-v1 mac", ts, n) + ACL  # type: ignore[arg-type]
    assert mac == hmac.new(KEYS32["i2r mac"], msg, hashlib.sha256).digest()


def test_box_is_chacha20_poly1305_with_the_documented_nonce_and_data(clock: Clock) -> None:
    """The encrypted form reproduced with libsodium: nonce 00 00 00 02 ‖ n, label acl box."""
    env = fixed_session(clock, EncPolicy()).seal_binary(ACL)
    ts, n, box = fields(env)[4:]
    nonce = b"\x00\x00\x00\x02" + n.to_bytes(8, "big")  # type: ignore[attr-defined]
    ad = header(b"dyknow-acl-v1 box", ts, n)  # type: ignore[arg-type]
    assert box == sodium.crypto_aead_chacha20poly1305_ietf_encrypt(
        ACL, ad, nonce, KEYS32["i2r box"]
    )


def test_the_forms_share_one_counter_and_window(clock: Clock) -> None:
    """JSON and binary ACL envelopes take turns on one counter: `missing` holds across both."""
    a, b = pair_of(clock, EncPolicy())
    sa = a.table.session_for("uav-b")
    assert sa is not None
    envs = [
        a.table.seal_binary("uav-b", ACL) if i % 2 else a.table.seal("uav-b", ACL) for i in range(6)
    ]
    ns = [fields(e)[5] if i % 2 else orjson.loads(e)["n"] for i, e in enumerate(envs)]
    assert ns == [1, 2, 3, 4, 5, 6] and sa.sent == 6 and sa.sent_binary == 0
    for env in envs[:2] + envs[3:]:  # the third never comes
        assert b.table.open(env) == ("uav-a", ACL)
    assert b.table.missing() == {"uav-a": 1}
    # the same counter in the other form is the same envelope: refused as a replay
    with pytest.raises(Replayed):
        b.table.open(envs[0])
    assert b.table.open(envs[2]) == ("uav-a", ACL)  # late, within the window
    assert b.table.missing() == {}
    # batches count apart: they neither move nor read this window
    b.table.open_bytes(a.table.seal_bytes("uav-b", BODY))
    assert fields(a.table.seal_binary("uav-b", ACL))[5] == 7


def test_a_binary_acl_envelope_never_stands_for_another_kind(clock: Clock) -> None:
    """Labels apart: never opened as a sample batch, nor a batch's as an ACL message."""
    for policy in (MacPolicy(require_encryption=False), EncPolicy()):
        a, b = pair_of(clock, policy)
        with pytest.raises(Forged):
            b.table.open_bytes(a.table.seal_binary("uav-b", ACL))
        with pytest.raises(Forged):
            b.table.open(a.table.seal_bytes("uav-b", ACL))
        # a JSON envelope's MAC or box moved into the binary form
        env = orjson.loads(a.table.seal("uav-b", ACL))
        tail = (
            [ACL, base64.b64decode(env["mac"])] if "mac" in env else [base64.b64decode(env["box"])]
        )
        moved = msgpack.packb([1, "uav-a", "uav-b", env["sid"], env["ts_ms"], env["n"], *tail])
        with pytest.raises(Forged):
            b.table.open(moved)
        # and the other way: a binary one's MAC or box in the JSON form
        items = fields(a.table.seal_binary("uav-b", ACL))
        keys = ("v", "from", "to", "sid", "ts_ms", "n")
        head = dict(zip(keys, items[:6], strict=True))
        if len(items) == 8:
            as_json = {**head, "body": ACL.decode(), "mac": base64.b64encode(items[7]).decode()}  # type: ignore[arg-type]
        else:
            as_json = {**head, "box": base64.b64encode(items[6]).decode()}  # type: ignore[arg-type]
        with pytest.raises(Forged):
            b.table.open(orjson.dumps(as_json))


# --------------------------------------------------------------------------- refusals


@pytest.mark.parametrize(
    ("payload", "match"),
    [
        (b"\x97\xc1", "not msgpack"),
        (b"\x90", "array of 8 items"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, 1]), "array of 8 items"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, 1, b"", b"", b""]), "array of 8 items"),
        (b"\xdd\x00\x00\x00\x01\x01", "array of 8 items"),
        (b"\xdd\xff\xff\xff\xff", "not msgpack"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, 1, b"x"]) + b"\x00", "not msgpack"),
        (msgpack.packb([2, "uav-a", "uav-b", "s", 1, 1, b"x"]), "version"),
        (msgpack.packb([True, "uav-a", "uav-b", "s", 1, 1, b"x"]), "version"),
        (msgpack.packb([1, b"uav-a", "uav-b", "s", 1, 1, b"x"]), "'from'"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, 1, "text"]), "binary"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1.0, 1, b"x"]), "ts_ms"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, 0, b"x"]), "'n'"),
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, -1, b"x"]), "'n'"),
        (b"\x97\xa1\xff", "not msgpack"),  # a str that is not UTF-8
        (msgpack.packb([1, "uav-a", "uav-b", "s", 1, 1, b"x" * (2 * 256 * 1024 + 1024)]), "limit"),
    ],
)
def test_malformed_binary_envelopes_are_refused_as_malformed(
    clock: Clock, payload: bytes, match: str | None
) -> None:
    """Whatever starts as a msgpack array and is not a binary envelope: Malformed, named."""
    _, b = pair_of(clock, EncPolicy())
    with pytest.raises(Malformed, match=match) as info:
        b.table.open(payload)
    assert info.value.code == "malformed"


@pytest.mark.parametrize(
    ("index", "value", "error"),
    [
        (4, int(T0 * 1000) + 1, Forged),
        (5, 7, Forged),
        (3, "AAAAAAAAAAAAAAAAAAAAAA", UnknownSession),
        (2, "uav-c", Misdirected),
        (1, "uav-c", UnknownPlatform),
        (6, b"\x00" * 40, Forged),
    ],
)
def test_tampered_header_field(
    clock: Clock, index: int, value: object, error: type[Exception]
) -> None:
    """A changed header or box: the refusal of the JSON form, the envelope still opens after."""
    a, b = pair_of(clock, EncPolicy())
    env = a.table.seal_binary("uav-b", ACL)
    with pytest.raises(error):
        b.table.open(edit(env, index, value))
    assert b.table.open(env) == ("uav-a", ACL)


def test_mac_only_where_encryption_is_required_is_refused_before_its_mac(clock: Clock) -> None:
    """`Unencrypted` (a kind of Malformed), even with a MAC that would not verify."""
    a = make_platform("uav-a", clock, MacPolicy())
    b = make_platform("uav-b", clock, EncPolicy())
    connect(a, b)
    env = a.table.seal_binary("uav-b", ACL)
    assert len(fields(env)) == 8
    for payload in (env, edit(env, 7, os.urandom(32))):
        with pytest.raises(Unencrypted) as info:
            b.table.open(payload)
        assert info.value.code == "unencrypted" and info.value.platform == "uav-a"
    a = make_platform("uav-a", clock, MacPolicy())
    b_lax = make_platform("uav-b", clock, EncPolicy(require_encryption=False))
    connect(a, b_lax)
    assert b_lax.table.open(a.table.seal_binary("uav-b", ACL)) == ("uav-a", ACL)
    with pytest.raises(Malformed, match="32 bytes"):
        b_lax.table.open(edit(a.table.seal_binary("uav-b", ACL), 7, b"short"))


def test_replayed_reordered_expired(clock: Clock) -> None:
    """The window and the clock checks of the JSON form."""
    a, b = pair_of(clock, EncPolicy(window=8, skew=5))
    envs = [a.table.seal_binary("uav-b", ACL) for _ in range(12)]
    b.table.open(envs[5])
    b.table.open(envs[3])
    with pytest.raises(Replayed, match="already seen"):
        b.table.open(envs[3])
    b.table.open(envs[11])
    with pytest.raises(Replayed, match="older than the replay window"):
        b.table.open(envs[0])
    late = a.table.seal_binary("uav-b", ACL)
    clock.t += 6
    with pytest.raises(Expired, match="timestamp"):
        b.table.open(late)


def test_an_untrusted_sender_and_a_reflected_envelope(clock: Clock) -> None:
    """Removing a platform from the trust store revokes it; an envelope sent back is refused."""
    a, b = pair_of(clock, EncPolicy())
    env = a.table.seal_binary("uav-b", ACL)
    with pytest.raises(Misdirected):
        a.table.open(env)
    b.table.trust.remove("uav-a")
    with pytest.raises(UnknownPlatform):
        b.table.open(env)


def test_any_msgpack_encoding_of_the_values_is_read(clock: Clock) -> None:
    """The shortest encodings, array 16 and 32 heads: the box covers values, not framing."""
    a, b = pair_of(clock, EncPolicy())
    for framing in (b"\x97", b"\xdc\x00\x07", b"\xdd\x00\x00\x00\x07"):
        items = fields(a.table.seal_binary("uav-b", ACL))
        assert b.table.open(framing + msgpack.packb(items)[1:]) == ("uav-a", ACL)
    with pytest.raises(Replayed):  # the same envelope, framed otherwise
        b.table.open(msgpack.packb(items))


def test_a_str_is_read_as_json(clock: Clock) -> None:
    """Only bytes can be the binary form: a str starting with what looks like one is JSON."""
    _, b = pair_of(clock, EncPolicy())
    with pytest.raises(Malformed, match="not JSON"):
        b.table.open("\x97abc")


# --------------------------------------------------------------------------- fuzz

ANY_MSGPACK = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
    | st.text(max_size=30) | st.binary(max_size=60),
    lambda inner: st.lists(inner, max_size=9)
    | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=20,
)  # fmt: skip


def _open_or_refuse(table: SessionTable, payload: bytes) -> bool:
    """Whether ``payload`` opened; a refusal is False, anything else raised is a bug."""
    try:
        assert table.open(payload) == ("uav-a", ACL)  # only what was sealed can open
    except AuthenticationError:
        return False
    return True


@settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_the_parser_never_raises_anything_but_a_refusal(data: st.DataObject) -> None:
    """Arbitrary arrays, bytes after an array head, a real envelope changed: refusals only."""
    clock = Clock()
    a, b = pair_of(clock, MacPolicy(require_encryption=False))
    good = a.table.seal_binary("uav-b", ACL)
    kind = data.draw(st.sampled_from(["array", "bytes", "field", "flip", "cut"]))
    if kind == "array":
        payload = msgpack.packb(data.draw(st.lists(ANY_MSGPACK, max_size=10)))
    elif kind == "bytes":
        head = data.draw(st.sampled_from([0x90, 0x97, 0x98, 0x9F, 0xDC, 0xDD]))
        payload = bytes([head]) + data.draw(st.binary(max_size=300))
    elif kind == "field":
        items = fields(good)
        items[data.draw(st.integers(0, len(items) - 1))] = data.draw(ANY_MSGPACK)
        payload = msgpack.packb(items)
    elif kind == "flip":
        i = data.draw(st.integers(0, len(good) - 1))
        payload = good[:i] + bytes([good[i] ^ data.draw(st.integers(1, 255))]) + good[i + 1 :]
    else:
        payload = good[: data.draw(st.integers(1, len(good) - 1))]
    if _open_or_refuse(b.table, payload):
        # the same values framed otherwise (or replaced by equal ones): the same envelope
        assert fields(payload) == fields(good)
        with pytest.raises(Replayed):
            b.table.open(good)
    else:
        assert b.table.open(good) == ("uav-a", ACL)  # nothing refused moved the window


def test_a_nil_mac_is_refused_as_a_mac_of_the_wrong_size(clock: Clock) -> None:
    """An 8-item array is MAC-only whatever its MAC holds: never read as a box."""
    a = make_platform("uav-a", clock, MacPolicy())
    b = make_platform("uav-b", clock, MacPolicy(require_encryption=False))
    connect(a, b)
    env = a.table.seal_binary("uav-b", ACL)
    with pytest.raises(Malformed, match="32 bytes"):
        b.table.open(edit(env, 7, None))
    with pytest.raises(Malformed, match="32 bytes"):
        b.table.open_bytes(edit(a.table.seal_bytes("uav-b", BODY), 7, None))
    a = make_platform("uav-a", clock, MacPolicy())
    strict = make_platform("uav-b", clock, EncPolicy())
    connect(a, strict)
    with pytest.raises(Unencrypted):
        strict.table.open(edit(a.table.seal_binary("uav-b", ACL), 7, None))
