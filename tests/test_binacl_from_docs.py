"""The binary ACL envelope, implemented from the documents alone, against our node.

An outside implementer's sealer and opener of the binary form of an ACL envelope, written
from `docs/wire.md` ("The binary form"), `docs/security.md` ("Envelope bytes") and
`docs/test-vectors.md` only, with plain ``hmac``, ``msgpack`` and PyNaCl's
ChaCha20-Poly1305-IETF: it reproduces the test vectors byte for byte, seals envelopes a
real node accepts over zenoh, and opens what a real node sends.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import struct
import time
from pathlib import Path
from typing import Any

import msgpack
import nacl.bindings as sodium
import pytest
from test_binary_acl import WAIT, _captured, _ia, pair

from agents import request

pytestmark = pytest.mark.timeout(120)

VECTORS = json.loads((Path(__file__).parent.parent / "docs" / "test-vectors.json").read_text())
FED = VECTORS["federation"]


def _lp(text: str) -> bytes:
    """A name as the documents lay it out: 2-byte big-endian length, then UTF-8."""
    raw = text.encode()
    return struct.pack(">H", len(raw)) + raw


def header(label: str, fed: str, frm: str, to: str, sid: str, ts_ms: int, n: int) -> bytes:
    """Fields 1-7 of "Envelope bytes": label and a zero byte, names, ts_ms and n."""
    return (
        label.encode("ascii")
        + b"\x00"
        + _lp(fed)
        + _lp(frm)
        + _lp(to)
        + _lp(sid)
        + struct.pack(">QQ", ts_ms, n)
    )


def nonce(n: int) -> bytes:
    """The binary ACL form's 96-bit nonce: 00 00 00 02, then n in 8 bytes big-endian."""
    return b"\x00\x00\x00\x02" + struct.pack(">Q", n)


def _fixed(frm: str, to: str, sid: str, ts_ms: int, n: int, payload: bytes) -> bytes:
    """Our sender's layout: shortest head, v, names; uint 64 ts_ms and n; bin 32 payload."""
    head = msgpack.packb([1, frm, to, sid])[1:]  # without the array's own head
    return (
        head
        + b"\xcf"
        + struct.pack(">Q", ts_ms)
        + b"\xcf"
        + struct.pack(">Q", n)
        + b"\xc6"
        + struct.pack(">I", len(payload))
        + payload
    )


def seal_mac(
    key: bytes, fed: str, frm: str, to: str, sid: str, ts_ms: int, n: int, body: bytes
) -> tuple[bytes, bytes, bytes]:
    """``(mac input, mac, envelope)`` of a MAC-only binary ACL envelope."""
    mac_input = header("dyknow-acl-v1 mac", fed, frm, to, sid, ts_ms, n) + body
    mac = hmac.new(key, mac_input, hashlib.sha256).digest()
    env = b"\x98" + _fixed(frm, to, sid, ts_ms, n, body) + b"\xc4\x20" + mac
    return mac_input, mac, env


def seal_box(
    key: bytes, fed: str, frm: str, to: str, sid: str, ts_ms: int, n: int, body: bytes
) -> tuple[bytes, bytes, bytes, bytes]:
    """``(associated data, nonce, box, envelope)`` of an encrypted binary ACL envelope."""
    ad = header("dyknow-acl-v1 box", fed, frm, to, sid, ts_ms, n)
    box = sodium.crypto_aead_chacha20poly1305_ietf_encrypt(body, ad, nonce(n), key)
    return ad, nonce(n), box, b"\x97" + _fixed(frm, to, sid, ts_ms, n, box)


def open_env(keys: dict[str, bytes], fed: str, payload: bytes) -> tuple[dict[str, Any], bytes]:
    """Open a binary ACL envelope with ``keys`` (``mac``, ``box``): its header and body."""
    assert payload[:1] in {bytes((b,)) for b in (*range(0x90, 0xA0), 0xDC, 0xDD)}
    items = msgpack.unpackb(payload, raw=False)
    assert len(items) in (7, 8)
    v, frm, to, sid, ts_ms, n = items[:6]
    assert v == 1
    head = {"from": frm, "to": to, "sid": sid, "ts_ms": ts_ms, "n": n}
    if len(items) == 8:
        body, mac = items[6], items[7]
        want = hmac.new(
            keys["mac"],
            header("dyknow-acl-v1 mac", fed, frm, to, sid, ts_ms, n) + body,
            hashlib.sha256,
        ).digest()
        assert hmac.compare_digest(want, mac)
        return head, body
    ad = header("dyknow-acl-v1 box", fed, frm, to, sid, ts_ms, n)
    return head, sodium.crypto_aead_chacha20poly1305_ietf_decrypt(
        items[6], ad, nonce(n), keys["box"]
    )


def _vector(name: str) -> dict[str, Any]:
    return next(e for e in VECTORS["envelopes"] if e["name"] == name)


def _key(entry: dict[str, Any]) -> bytes:
    return bytes.fromhex(VECTORS["key_exchange"]["keys_hex"][entry["key"]])


def _args(e: dict[str, Any]) -> tuple[str, str, str, str, int, int, bytes]:
    return (FED, e["from"], e["to"], e["sid"], e["ts_ms"], e["n"], e["body"].encode())


def test_the_mac_vector_is_reproduced_byte_for_byte() -> None:
    e = _vector("acl-binary-mac")
    mac_input, mac, env = seal_mac(_key(e), *_args(e))
    assert mac_input.hex() == e["mac_input_hex"]
    assert mac.hex() == e["mac_hex"]
    assert env.hex() == e["envelope_hex"]
    head, body = open_env({"mac": _key(e)}, FED, env)
    assert body == e["body"].encode() and head["n"] == e["n"] == 4


def test_the_box_vector_is_reproduced_byte_for_byte() -> None:
    e = _vector("acl-binary-box")
    ad, nce, box, env = seal_box(_key(e), *_args(e))
    assert ad.hex() == e["ad_hex"]
    assert nce.hex() == e["nonce_hex"]
    assert box.hex() == e["ciphertext_hex"]
    assert env.hex() == e["envelope_hex"]
    head, body = open_env({"box": _key(e)}, FED, env)
    assert body == e["body"].encode() and head["n"] == e["n"] == 5


def test_the_vectors_open_in_any_msgpack_encoding_of_the_same_values() -> None:
    """A receiver reads any valid encoding (the shortest one, here) of the same values."""
    for name in ("acl-binary-mac", "acl-binary-box"):
        e = _vector(name)
        items = msgpack.unpackb(bytes.fromhex(e["envelope_hex"]), raw=False)
        shortest = msgpack.packb(items, use_bin_type=True)
        assert shortest != bytes.fromhex(e["envelope_hex"])
        keys = {"mac": _key(e), "box": _key(e)}
        assert open_env(keys, FED, shortest)[1] == e["body"].encode()


def test_the_json_labelled_must_refuse_entry_does_not_open_here() -> None:
    bad = next(m for m in VECTORS["must_refuse"] if m["name"] == "acl-binary-mac-with-json-label")
    with pytest.raises(AssertionError):
        open_env({"mac": _key(_vector("acl-binary-mac"))}, FED, bytes.fromhex(bad["envelope_hex"]))


def _tx_keys(platform: Any, peer: str) -> tuple[Any, dict[str, bytes]]:
    """The session a real node seals with for ``peer`` and its sending box key.

    The key exchange itself is covered by the vectors; only the agreed box key is taken
    from the node (encryption is the default, so no MAC key is needed).
    """
    session = _ia(platform).sessions.session_for(peer)
    assert session is not None
    return session, {"box": session._box_tx}


async def test_a_real_node_accepts_what_the_documents_seal_and_sends_what_they_open() -> None:
    async with pair() as p:
        sent = await _captured(p)  # uav-a's real envelope to uav-b, on the wire
        session, keys = _tx_keys(p.pa, "uav-b")
        head, body = open_env(keys, p.fed, sent)
        assert (head["from"], head["to"], head["sid"]) == ("uav-a", "uav-b", session.sid)
        assert json.loads(body)["sender"] == "asker@uav-a"
        assert sent[0] == 0x97  # encrypted, 7 items: the default

        # seal, from the documents, a request of uav-a's asker to uav-b's echo
        msg = json.loads(body)
        msg["reply_with"] = "from-docs-1"
        msg["content"] = {"x": "from the docs"}
        n = session._n + 1000  # ahead of the node's own counter: never sealed by it
        env = seal_box(
            keys["box"],
            p.fed,
            "uav-a",
            "uav-b",
            session.sid,
            int(time.time() * 1000),
            n,
            json.dumps(msg).encode(),
        )[3]
        p.put(env)
        async with asyncio.timeout(WAIT):
            while not any(c.content == {"x": "from the docs"} for c in p.echo.calls):  # noqa: ASYNC110
                await asyncio.sleep(0.005)
        # the node goes on with uav-a's own envelopes (n below ours: within the window)
        assert await request(p.asker, "echo@uav-b", {"y": 2}, ontology="demo") == {
            "echo": {"y": 2},
            "by": "echo@uav-b",
        }
