"""Attacks on the binary form of ACL envelopes: each one a refusal a receiver relies on.

Sessions between two tables (as `tests/test_security.py`), envelopes sealed by hand from
the documents (`tests/test_binacl_from_docs.py`) where an attacker or a peer of another
implementation would, and real zenoh nodes where the path matters.
"""

from __future__ import annotations

import base64
import re
import struct
import threading
import time
from typing import Any

import msgpack
import nacl.bindings as sodium
import orjson
import pytest
from test_binacl_from_docs import header, seal_box
from test_binary_acl import _attack, _captured, _ia, pair
from test_security import Clock, MacPolicy, make_platform
from test_security import connect as _connect

from agents import request
from agents._exceptions import AuthenticationError, Forged, Malformed, Replayed
from agents._security import SecurityPolicy, Session

pytestmark = pytest.mark.timeout(120)

MAX = 256 * 1024


def _pair(policy: Any = None) -> tuple[Any, Any, Session, Session]:
    """uav-a and uav-b tables with one session, uav-a the initiator."""
    clock = Clock()
    a = make_platform("uav-a", clock, policy or SecurityPolicy())
    b = make_platform("uav-b", clock, policy or SecurityPolicy())
    sa, sb = _connect(a, b)
    return a, b, sa, sb


def _ts(sa: Session) -> int:
    return int(sa._clock() * 1000)


def _seal_json_box(sa: Session, n: int, body: bytes) -> bytes:
    """The JSON form's encrypted envelope, from `docs/wire.md`, at counter ``n``."""
    ts = _ts(sa)
    ad = header("dyknow-env-v1 box", "demo", sa.me, sa.peer, sa.sid, ts, n)
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


async def test_a_sample_batch_put_on_a_real_nodes_acl_key_is_audited_forged() -> None:
    async with pair() as p:
        await _captured(p)  # a session is there
        batch = _ia(p.pa).sessions.seal_bytes("uav-b", msgpack.packb({"v": 1}))
        reason = await _attack(p, batch, "forged")
        assert "uav-a" in reason


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


# --------------------------------------------------------------------------- real nodes


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


@pytest.mark.parametrize("size", [0, 1, 15, 16])
def test_a_box_shorter_than_its_tag_is_forged_not_a_crash(size: int) -> None:
    _, b, sa, sb = _pair()
    with pytest.raises(Forged):
        b.table.open(msgpack.packb([*_head(sa), b"\x00" * size], use_bin_type=True))
    assert sb.received == 0
