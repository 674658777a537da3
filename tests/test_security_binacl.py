"""Binary ACL envelopes (Session.seal_binary; SessionTable.open reads both forms).

The msgpack form of an ACL envelope (``docs/wire.md``, "Sealed envelopes"): its own
labels and nonce space, the JSON form's counter and replay window, and the same
refusals as either envelope kind. Envelopes sealed by hand from the documents
(`tests/test_binacl_from_docs.py`) attack it where an attacker or a peer of another
implementation would: one form passed off as the other, hostile msgpack, sizes, the
missing count across forms. The test of the interface over zenoh is
tests/test_binary_acl.py.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import struct
import threading
import time
from typing import Any

import msgpack
import orjson
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from nacl import bindings as sodium
from test_binacl_from_docs import header as docs_header
from test_binacl_from_docs import seal_box
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


MAX = 256 * 1024


def _pair(policy: Any = None) -> tuple[Any, Any, Session, Session]:
    """uav-a and uav-b tables with one session, uav-a the initiator."""
    clock = Clock()
    a = make_platform("uav-a", clock, policy or SecurityPolicy())
    b = make_platform("uav-b", clock, policy or SecurityPolicy())
    sa, sb = connect(a, b)
    return a, b, sa, sb


def _ts(sa: Session) -> int:
    return int(sa._clock() * 1000)


def _seal_json_box(sa: Session, n: int, body: bytes) -> bytes:
    """The JSON form's encrypted envelope, from `docs/wire.md`, at counter ``n``."""
    ts = _ts(sa)
    ad = docs_header("dyknow-env-v1 box", "demo", sa.me, sa.peer, sa.sid, ts, n)
    box = sodium.crypto_aead_chacha20poly1305_ietf_encrypt(
        body, ad, bytes(4) + struct.pack(">Q", n), sa._box_tx
    )
    return orjson.dumps(
        {
            "v": 1,
            "from": sa.me,
            "to": sa.peer,
            "sid": sa.sid,
            "ts_ms": ts,
            "n": n,
            "box": base64.b64encode(box).decode(),
        }
    )


def _seal_bin_box(sa: Session, n: int, body: bytes) -> bytes:
    """The binary ACL form's encrypted envelope, from `docs/wire.md`, at counter ``n``."""
    return seal_box(sa._box_tx, "demo", sa.me, sa.peer, sa.sid, _ts(sa), n, body)[3]


MSG = b'{"v":1,"performative":"inform","sender":"a@uav-a","receivers":["b@uav-b"],"content":1}'


# --------------------------------------------------------------------------- cross-form


def test_the_same_n_in_the_other_form_is_a_replay_both_ways() -> None:
    a, b, sa, _ = _pair()
    assert b.table.open(a.table.seal("uav-b", MSG)) == ("uav-a", MSG)  # JSON, n = 1
    with pytest.raises(Replayed):
        b.table.open(_seal_bin_box(sa, 1, MSG))
    assert b.table.open(a.table.seal_binary("uav-b", MSG)) == ("uav-a", MSG)  # binary, n = 2
    with pytest.raises(Replayed):
        b.table.open(_seal_json_box(sa, 2, MSG))
    # a reordered envelope in either form within the window is still accepted once
    assert b.table.open(_seal_json_box(sa, 10, MSG))[1] == MSG
    assert b.table.open(_seal_bin_box(sa, 9, MSG))[1] == MSG
    with pytest.raises(Replayed):
        b.table.open(_seal_json_box(sa, 9, MSG))


def test_a_json_mac_moved_into_the_binary_form_is_forged_and_moves_no_window() -> None:
    a, b, _sa, _ = _pair(MacPolicy())
    env = orjson.loads(a.table.seal("uav-b", MSG))
    mac = base64.b64decode(env["mac"])
    moved = msgpack.packb(
        [1, env["from"], env["to"], env["sid"], env["ts_ms"], env["n"], MSG, mac],
        use_bin_type=True,
    )
    with pytest.raises(Forged):
        b.table.open(moved)
    # the JSON original (same n) still opens: the forgery moved nothing
    assert b.table.open(orjson.dumps(env)) == ("uav-a", MSG)


def test_a_binary_acl_box_relabelled_as_json_is_forged() -> None:
    a, b, _sa, _ = _pair()
    items = msgpack.unpackb(a.table.seal_binary("uav-b", MSG), raw=False)
    keys = ("v", "from", "to", "sid", "ts_ms", "n")
    env = dict(zip(keys, items[:6], strict=True)) | {"box": base64.b64encode(items[6]).decode()}
    with pytest.raises(Forged):
        b.table.open(orjson.dumps(env))


# --------------------------------------------------------------------------- cross-kind


def test_a_sample_batch_or_stream_report_on_the_acl_key_is_forged_and_the_reverse() -> None:
    a, b, sa, sb = _pair()
    batch = a.table.seal_bytes("uav-b", msgpack.packb({"v": 1, "s": "x", "q": 1, "b": []}))
    with pytest.raises(Forged):
        b.table.open(batch)  # n = 1 of the binary counter, read as an ACL envelope
    report = sb.seal_bytes(msgpack.packb({"v": 1, "lost": {}}))  # the importer's report
    with pytest.raises(Forged):
        a.table.open(report)
    acl = a.table.seal_binary("uav-b", MSG)  # ACL counter n = 1
    with pytest.raises(Forged):
        b.table.open_bytes(acl)
    # nothing moved: each opens where it belongs, once
    assert b.table.open(acl) == ("uav-a", MSG)
    assert b.table.open_bytes(batch)[0] == "uav-a"
    assert a.table.open_bytes(report)[0] == "uav-b"
    assert sb.missing == 0 and sa.missing == 0


# --------------------------------------------------------------------------- bombs


def _head(sa: Session, ts: Any = None, n: Any = 7) -> list[Any]:
    return [1, sa.me, sa.peer, sa.sid, _ts(sa) if ts is None else ts, n]


def _items(sa: Session, **over: Any) -> bytes:
    items = [*_head(sa), b"\x00" * 40]
    for k, v in over.items():
        items[["v", "from", "to", "sid", "ts", "n", "box"].index(k)] = v
    return msgpack.packb(items, use_bin_type=True)


def _bombs(sa: Session) -> dict[str, bytes]:
    head = msgpack.packb(_head(sa), use_bin_type=True)[1:]
    return {
        "array32 of 2**32-1 items": b"\xdd\xff\xff\xff\xff",
        "array32 of 7, then bin32 of 4 GiB": b"\xdd\x00\x00\x00\x07"
        + head
        + b"\xc6\xff\xff\xff\xff",
        "str32 of 4 GiB as from": b"\x97\x01\xdb\xff\xff\xff\xff",
        "nested 100000 deep": b"\x91" * 100_000,
        "nested array as box": _items(sa, box=[[[[[[[]]]]]]]),
        "map32 of 2**32-1 pairs as box": b"\x97" + head + b"\xdf\xff\xff\xff\xff",
        "ext type as box": _items(sa, box=msgpack.ExtType(5, b"\x00" * 40)),
        "timestamp ext as ts_ms": _items(sa, ts=msgpack.Timestamp(1_795_000_000)),
        "str box": _items(sa, box="\x00" * 40),
        "bin from": _items(sa, **{"from": b"uav-a"}),
        "invalid utf-8 from": b"\x97\x01\xa2\xff\xfe" + head[7:],
        "n 2**64-1": _items(sa, n=2**64 - 1),
        "n 2**63": _items(sa, n=2**63),
        "n 0": _items(sa, n=0),
        "n -1": _items(sa, n=-1),
        "n float": _items(sa, n=7.0),
        "n true": _items(sa, n=True),
        "ts -1": _items(sa, ts=-1),
        "ts float": _items(sa, ts=float(_ts(sa))),
        "v true": _items(sa, v=True),
        "v 1.0": _items(sa, v=1.0),
        "v 2": _items(sa, v=2),
        "6 items": msgpack.packb(_head(sa)),
        "9 items": msgpack.packb([*_head(sa), b"x", b"\x00" * 32, b"y"], use_bin_type=True),
        "trailing bytes": _items(sa) + b"\xc0",
        "truncated": _items(sa)[:-3],
        "nil everywhere": msgpack.packb([None] * 7),
        "mac of 31 bytes": msgpack.packb([*_head(sa), MSG, b"\x00" * 31], use_bin_type=True),
        "str mac": msgpack.packb([*_head(sa), MSG, "x" * 32], use_bin_type=True),
        "body over the envelope's limit": msgpack.packb(
            [*_head(sa), b"{" * (2 * MAX + 1024), b"\x00" * 32]
        ),
        "box over the envelope's limit": msgpack.packb([*_head(sa), b"\x00" * (2 * MAX + 1024)]),
    }


@pytest.mark.parametrize("name", list(_bombs(_pair()[2]).keys()))
def test_hostile_msgpack_is_malformed_quickly_and_nothing_else(name: str) -> None:
    _, b, sa, sb = _pair(MacPolicy())
    payload = _bombs(sa)[name]
    t0 = time.process_time()
    with pytest.raises(AuthenticationError) as info:
        b.table.open(payload)
    assert time.process_time() - t0 < 0.5, name
    assert type(info.value) is Malformed, (name, info.value)
    assert sb.missing == 0 and sb.received == 0


def test_any_msgpack_encoding_of_the_values_opens() -> None:
    """array16 head, a fixint n, bin 8 box: not our sender's layout, the same values."""
    _, b, sa, _ = _pair()
    items = msgpack.unpackb(_seal_bin_box(sa, 3, MSG), raw=False)
    packed = msgpack.packb(items, use_bin_type=True)
    assert b.table.open(b"\xdc\x00\x07" + packed[1:]) == ("uav-a", MSG)


# --------------------------------------------------------------------------- sizes


def test_an_authentic_body_over_the_message_limit_opens_in_either_form() -> None:
    """Over 256 KiB: both forms open it (then answered as a message too large), alike."""
    _, b, sa, _ = _pair()
    big = b'{"x":"' + b"a" * MAX + b'"}'
    assert b.table.open(_seal_bin_box(sa, 1, big)) == ("uav-a", big)
    assert b.table.open(_seal_json_box(sa, 2, big)) == ("uav-a", big)


def test_a_binary_envelope_over_its_size_limit_is_malformed_before_unpacking() -> None:
    """The JSON form's envelope limit (2 x 256 KiB + 1 KiB) holds for the binary form too."""
    _, b, sa, _ = _pair()
    env = msgpack.packb([*_head(sa), b"\x00" * (2 * MAX)], use_bin_type=True) + b"\x00" * 1100
    with pytest.raises(Malformed, match="exceeds the limit"):
        b.table.open(env)


# --------------------------------------------------------------------------- counts


def test_the_missing_count_spans_both_forms_and_ignores_sample_batches() -> None:
    a, b, _sa, sb = _pair()
    sealed = [
        a.table.seal("uav-b", MSG),
        a.table.seal_binary("uav-b", MSG),
        a.table.seal("uav-b", MSG),
        a.table.seal_binary("uav-b", MSG),
    ]
    for _ in range(3):
        b.table.open_bytes(a.table.seal_bytes("uav-b", b"\x90"))
    for i in (0, 2, 3):
        b.table.open(sealed[i])
    assert sb.missing == 1
    b.table.open(sealed[1])
    assert sb.missing == 0
    assert [orjson.loads(sealed[0])["n"], msgpack.unpackb(sealed[3])[5]] == [1, 4]


def test_seals_from_two_threads_never_share_an_n() -> None:
    """The lane seals on zenoh's thread while the loop seals: one counter, no nonce twice."""
    a, _b, _sa, _sb = _pair()
    ns: list[int] = []
    lock = threading.Lock()

    def seal(binary: bool) -> None:
        for _ in range(2000):
            env = (a.table.seal_binary if binary else a.table.seal)("uav-b", MSG)
            n = msgpack.unpackb(env)[5] if binary else orjson.loads(env)["n"]
            with lock:
                ns.append(n)

    threads = [threading.Thread(target=seal, args=(i % 2 == 0,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert sorted(ns) == list(range(1, 8001))


# --------------------------------------------------------------------------- refusals alike


@pytest.mark.parametrize("what", ["misdirected", "untrusted", "unknown-session", "forged"])
def test_each_refusal_reads_the_same_in_both_forms(what: str) -> None:
    """The code, reason and claimed sender of a refusal do not tell the forms apart."""
    _, b, sa, _ = _pair()

    def variants(n: int) -> tuple[bytes, bytes]:
        j = orjson.loads(_seal_json_box(sa, n, MSG))
        bi = msgpack.unpackb(_seal_bin_box(sa, n, MSG), raw=False)
        if what == "misdirected":
            j["to"] = bi[2] = "uav-c"
        elif what == "untrusted":
            j["from"] = bi[1] = "uav-z"
        elif what == "unknown-session":
            j["sid"] = bi[3] = "A" * 22
        else:
            j["ts_ms"] += 1
            bi[4] += 1
        return orjson.dumps(j), msgpack.packb(bi, use_bin_type=True)

    j, bi = variants(5)
    errors = []
    for env in (j, bi):
        with pytest.raises(AuthenticationError) as info:
            b.table.open(env)
        errors.append((type(info.value), info.value.code, info.value.platform, str(info.value)))
    assert errors[0] == errors[1]
    assert errors[0][1] == what


def test_a_mac_one_byte_too_long_is_malformed() -> None:
    """The binary MAC is raw bytes: its exact value with a byte more is refused."""
    a, b, _, _ = _pair(MacPolicy())
    items = msgpack.unpackb(a.table.seal_binary("uav-b", MSG), raw=False)
    items[7] = items[7] + b"\x00"
    with pytest.raises(Malformed):
        b.table.open(msgpack.packb(items, use_bin_type=True))


@pytest.mark.parametrize("size", [0, 1, 15, 16])
def test_a_box_shorter_than_its_tag_is_forged_not_a_crash(size: int) -> None:
    _, b, sa, sb = _pair()
    with pytest.raises(Forged):
        b.table.open(msgpack.packb([*_head(sa), b"\x00" * size], use_bin_type=True))
    assert sb.received == 0
