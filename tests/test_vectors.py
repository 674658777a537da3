"""docs/test-vectors.json: what another implementation checks itself against.

Each vector is checked twice: recomputed from ``docs/test-vectors.md`` and
``docs/security.md`` alone, with plain PyNaCl, hmac, hashlib and msgpack (nothing of
``agents``), and reproduced by the project's own code (a handshake with the vectors'
ephemeral keys, sessions sealing and opening). The file itself must be what
``python -m tools.gen_vectors`` writes, so the document, the code and the file cannot
drift apart.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import hmac
import json
import re
from pathlib import Path
from typing import Any

import msgpack
import pytest
from nacl import bindings as sodium
from nacl.exceptions import BadSignatureError
from nacl.signing import SigningKey, VerifyKey

PATH = Path(__file__).resolve().parent.parent / "docs" / "test-vectors.json"
VECTORS: dict[str, Any] = json.loads(PATH.read_text(encoding="utf-8"))
KX = VECTORS["key_exchange"]
FED = VECTORS["federation"]


# -- an implementation written from the documents alone -------------------------------------


def lp(text: str) -> bytes:
    """A name in a transcript or MAC input: 2-byte big-endian length, then its UTF-8."""
    raw = text.encode("utf-8")
    return len(raw).to_bytes(2, "big") + raw


def u64(value: int) -> bytes:
    return value.to_bytes(8, "big")


def transcript_part(
    label: str, fed: str, frm: str, to: str, ts: int, nonce: bytes, epk: bytes
) -> bytes:
    """One half of a key-exchange transcript: the label, a zero byte, then the fields."""
    return label.encode() + b"\x00" + lp(fed) + lp(frm) + lp(to) + u64(ts) + nonce + epk


def session_keys(t2: bytes, shared: bytes) -> dict[str, bytes]:
    salt = hashlib.sha256(t2).digest()
    prk = hmac.digest(salt, shared, "sha256")
    labels = ("i2r mac", "r2i mac", "i2r box", "r2i box", "sid")
    return {
        label: hmac.digest(prk, b"dyknow-session-v1 " + label.encode() + b"\x01", "sha256")
        for label in labels
    }


def session_id(sid_key: bytes) -> str:
    return base64.urlsafe_b64encode(sid_key[:16]).decode().rstrip("=")


def header(label: str, fed: str, frm: str, to: str, sid: str, ts: int, n: int) -> bytes:
    """The MAC input's (or the associated data's) part before the body."""
    return label.encode() + b"\x00" + lp(fed) + lp(frm) + lp(to) + lp(sid) + u64(ts) + u64(n)


# the first 4 bytes of an AEAD nonce, per envelope kind: JSON, binary (batches), binary ACL
NONCE_SPACE = {
    "json": b"\x00\x00\x00\x00",
    "binary": b"\x00\x00\x00\x01",
    "acl-binary": b"\x00\x00\x00\x02",
}
# the label's word, per envelope kind: dyknow-<word>-v1 mac / box
LABEL_WORD = {"json": "env", "binary": "bin", "acl-binary": "acl"}


def aead_nonce(kind: str, n: int) -> bytes:
    return NONCE_SPACE[kind] + u64(n)


def b64(value: str) -> bytes:
    return base64.b64decode(value, validate=True)


def h(value: str) -> bytes:
    return bytes.fromhex(value)


def derived() -> dict[str, bytes]:
    """The session keys, derived from the vectors' inputs only (both sides' view)."""
    init, reply = KX["init"], KX["reply"]
    t2 = h(reply["t2_hex"])
    za = sodium.crypto_scalarmult(h(init["x25519_secret_hex"]), h(reply["x25519_public_hex"]))
    zb = sodium.crypto_scalarmult(h(reply["x25519_secret_hex"]), h(init["x25519_public_hex"]))
    assert za == zb == h(KX["shared_secret_hex"])
    return session_keys(t2, za)


# -- the file --------------------------------------------------------------------------------


def test_the_file_is_what_the_generator_writes() -> None:
    from tools.gen_vectors import generate, render

    assert PATH.read_text(encoding="utf-8") == render(generate()), (
        "docs/test-vectors.json is out of date: run python -m tools.gen_vectors"
    )


# -- from the description ----------------------------------------------------------------------


def test_keys_and_signatures_from_the_description() -> None:
    for platform, p in VECTORS["platforms"].items():
        public = bytes(SigningKey(h(p["ed25519_seed_hex"])).verify_key)
        assert public.hex() == p["ed25519_public_hex"], platform
    for side in ("init", "reply"):
        v = KX[side]
        assert (
            sodium.crypto_scalarmult_base(h(v["x25519_secret_hex"])).hex()
            == (v["x25519_public_hex"])
        )


def test_key_exchange_transcripts_from_the_description() -> None:
    init, reply = KX["init"], KX["reply"]
    msg_i, msg_r = json.loads(init["json"]), json.loads(reply["json"])
    assert set(msg_i) == {"v", "kx", "fed", "from", "to", "ts_ms", "nonce", "epk", "sig"}
    assert set(msg_r) == set(msg_i) | {"re"}
    assert (msg_i["v"], msg_i["kx"], msg_r["kx"], msg_i["fed"]) == (1, "init", "reply", FED)
    assert b64(msg_r["re"]) == b64(msg_i["nonce"])

    t1 = transcript_part(
        "dyknow-kx-v1 init",
        msg_i["fed"],
        msg_i["from"],
        msg_i["to"],
        msg_i["ts_ms"],
        b64(msg_i["nonce"]),
        b64(msg_i["epk"]),
    )
    assert t1.hex() == init["t1_hex"]
    part = transcript_part(
        "dyknow-kx-v1 reply",
        msg_r["fed"],
        msg_r["from"],
        msg_r["to"],
        msg_r["ts_ms"],
        b64(msg_r["nonce"]),
        b64(msg_r["epk"]),
    )
    assert part.hex() == reply["reply_part_hex"]
    assert (t1 + part).hex() == reply["t2_hex"]
    # the nonces and keys in the JSON are the vectors' raw bytes
    assert b64(msg_i["nonce"]).hex() == init["nonce_hex"]
    assert b64(msg_r["epk"]).hex() == reply["x25519_public_hex"]

    keys = VECTORS["platforms"]
    for msg, signed, v in ((msg_i, t1, init), (msg_r, t1 + part, reply)):
        seed = h(keys[msg["from"]]["ed25519_seed_hex"])
        # Ed25519 is deterministic: signing the transcript gives the very signature sent
        assert SigningKey(seed).sign(signed).signature == b64(msg["sig"])
        assert b64(msg["sig"]).hex() == v["sig_hex"]
        VerifyKey(h(keys[msg["from"]]["ed25519_public_hex"])).verify(signed, b64(msg["sig"]))


def test_the_documents_examples_are_the_vectors() -> None:
    text = (PATH.parent / "security.md").read_text(encoding="utf-8")
    example = text.split("at `tsA` = 1795000000123 (hex):", 1)[1].split("then `nA`", 1)[0]
    start = "".join(re.findall(r"`([0-9a-f ]+)`", example)).replace(" ", "")
    assert len(start) == 2 * (18 + 6 + 7 + 7 + 8)
    assert KX["init"]["t1_hex"].startswith(start)
    assert KX["init"]["ts_ms"] == 1795000000123


def test_session_keys_and_id_from_the_description() -> None:
    keys = derived()
    salt = hashlib.sha256(h(KX["reply"]["t2_hex"])).digest()
    assert salt.hex() == KX["salt_hex"]
    assert hmac.digest(salt, h(KX["shared_secret_hex"]), "sha256").hex() == KX["prk_hex"]
    assert {k: v.hex() for k, v in keys.items()} == KX["keys_hex"]
    sid = session_id(keys["sid"])
    assert sid == KX["sid"] and len(sid) == 22


@pytest.mark.parametrize("entry", VECTORS["envelopes"], ids=lambda e: e["name"])
def test_envelopes_from_the_description(entry: dict[str, Any]) -> None:
    keys = derived()
    binary = entry["kind"] != "json"  # a msgpack array: a batch's, or an ACL message's
    if binary:
        env = msgpack.unpackb(h(entry["envelope_hex"]), raw=False)
        assert type(env) is list and len(env) == (7 if entry["encrypted"] else 8)
        v, frm, to, sid, ts, n, payload = env[:7]
        if entry["kind"] == "binary":
            body = h(entry["body_hex"])
            assert msgpack.unpackb(body, raw=False) == entry["body_decoded"]
        else:  # the ACL message's JSON text, as in the JSON form
            body = entry["body"].encode("utf-8")
    else:
        env = json.loads(entry["envelope"])
        assert set(env) == {"v", "from", "to", "sid", "ts_ms", "n"} | (
            {"box"} if entry["encrypted"] else {"body", "mac"}
        )
        v, frm, to, sid, ts, n = (env[k] for k in ("v", "from", "to", "sid", "ts_ms", "n"))
        body = entry["body"].encode("utf-8")
    assert (v, frm, to, sid, ts, n) == (
        1,
        entry["from"],
        entry["to"],
        KX["sid"],
        entry["ts_ms"],
        entry["n"],
    )
    # the initiator (uav-a) sends on the i2r keys, the responder on the r2i keys
    direction = "i2r" if frm == KX["init"]["from"] else "r2i"
    assert entry["direction"] == direction
    kind = LABEL_WORD[entry["kind"]]
    if entry["encrypted"]:
        ad = header(f"dyknow-{kind}-v1 box", FED, frm, to, sid, ts, n)
        nonce = aead_nonce(entry["kind"], n)
        assert (ad.hex(), nonce.hex()) == (entry["ad_hex"], entry["nonce_hex"])
        box = payload if binary else b64(env["box"])
        assert box.hex() == entry["ciphertext_hex"]
        key = keys[f"{direction} box"]
        assert sodium.crypto_aead_chacha20poly1305_ietf_decrypt(box, ad, nonce, key) == body
        assert sodium.crypto_aead_chacha20poly1305_ietf_encrypt(body, ad, nonce, key) == box
    else:
        mac_input = header(f"dyknow-{kind}-v1 mac", FED, frm, to, sid, ts, n) + body
        assert mac_input.hex() == entry["mac_input_hex"]
        mac = hmac.digest(keys[f"{direction} mac"], mac_input, "sha256")
        sent = env[7] if binary else b64(env["mac"])
        assert mac == sent and mac.hex() == entry["mac_hex"]
        if binary:
            assert payload == body
        else:
            assert env["body"] == entry["body"]
    if entry["kind"] == "acl-binary":  # our sender's layout: docs/wire.md, "The binary form"
        tail = b"\xcf" + u64(ts) + b"\xcf" + u64(n) + b"\xc6" + len(payload).to_bytes(4, "big")
        mac = b"" if entry["encrypted"] else b"\xc4\x20" + env[7]
        head = bytes([0x90 + len(env)]) + msgpack.packb(env[:4])[1:]
        assert head + tail + payload + mac == h(entry["envelope_hex"])


@pytest.mark.parametrize("entry", VECTORS["must_refuse"], ids=lambda e: e["name"])
def test_refusals_fail_to_verify_from_the_description(entry: dict[str, Any]) -> None:
    keys = derived()
    if entry["kind"] == "kx-init":
        msg = json.loads(entry["json"])
        verify = VerifyKey(h(VECTORS["platforms"][msg["from"]]["ed25519_public_hex"]))
        verify.verify(h(entry["signed_hex"]), b64(msg["sig"]))  # it signs the wrong bytes
        with pytest.raises(BadSignatureError):
            verify.verify(h(KX["init"]["t1_hex"]), b64(msg["sig"]))
        return
    if entry["kind"] == "directory":
        st = json.loads(entry["statement"])
        verify = VerifyKey(h(VECTORS["platforms"][st["from"]]["ed25519_public_hex"]))
        verify.verify(h(entry["signed_hex"]), b64(st["sig"]))  # it signs the wrong bytes
        with pytest.raises(BadSignatureError):
            verify.verify(statement_bytes(st, h(entry["query_nonce_hex"])), b64(st["sig"]))
        return
    if entry["kind"] == "owner-batch":
        signed = h(entry["signed_hex"])
        sig, ts, batch = signed[:64], int.from_bytes(signed[64:72], "big"), signed[72:]
        public = VerifyKey(h(VECTORS["platforms"]["uav-a"]["ed25519_public_hex"]))
        if "transcript_hex" in entry:
            public.verify(h(entry["transcript_hex"]), sig)  # it signs the wrong bytes
        with pytest.raises(BadSignatureError):
            public.verify(owner_transcript(entry["key"], ts, batch), sig)
        return
    if entry["kind"] in ("binary", "acl-binary"):
        env = msgpack.unpackb(h(entry["envelope_hex"]), raw=False)
        frm, to, sid, ts, n, body, mac = env[1:]
        kind = LABEL_WORD[entry["kind"]]
    else:
        env = json.loads(entry["envelope"])
        frm, to, sid, ts, n = (env[k] for k in ("from", "to", "sid", "ts_ms", "n"))
        body, mac, kind = env["body"].encode(), b64(env["mac"]), "env"
    right = header(f"dyknow-{kind}-v1 mac", FED, frm, to, sid, ts, n) + body
    assert hmac.digest(keys["i2r mac"], h(entry["mac_input_hex"]), "sha256") == mac
    assert hmac.digest(keys["i2r mac"], right, "sha256") != mac


def owner_transcript(key: str, ts_ms: int, batch: bytes) -> bytes:
    """What a platform signs for its owner (docs/wire.md, "Batches for the owner")."""
    return b"dyknow-owner-v1 sig\x00" + lp(key) + u64(ts_ms) + batch


@pytest.mark.parametrize("entry", VECTORS["owner_batches"], ids=lambda e: e["name"])
def test_owner_batches_from_the_description(entry: dict[str, Any]) -> None:
    p = VECTORS["platforms"][entry["platform"]]
    public, seed = h(p["ed25519_public_hex"]), h(p["ed25519_seed_hex"])
    assert entry["key"] == f"dyknow/{FED}/v1/{entry['name']}/{entry['platform']}"
    # the owner opens the sealed box with the platform's key in its X25519 form
    x_public = sodium.crypto_sign_ed25519_pk_to_curve25519(public)
    x_secret = sodium.crypto_sign_ed25519_sk_to_curve25519(seed + public)
    assert x_public.hex() == entry["owner_x25519_public_hex"]
    payload = h(entry["payload_hex"])
    signed = sodium.crypto_box_seal_open(payload, x_public, x_secret)
    assert signed.hex() == entry["signed_hex"]
    # a libsodium sealed box: ephemeral public key, then crypto_box under the BLAKE2b nonce
    epk = sodium.crypto_scalarmult_base(h(entry["ephemeral_secret_hex"]))
    nonce = hashlib.blake2b(epk + x_public, digest_size=24).digest()
    assert (epk.hex(), nonce.hex()) == (entry["ephemeral_public_hex"], entry["nonce_hex"])
    assert payload == epk + sodium.crypto_box(
        signed, nonce, x_public, h(entry["ephemeral_secret_hex"])
    )
    # inside: the signature, the time, the batch; signed over label, key, time and batch
    sig, ts, batch = signed[:64], int.from_bytes(signed[64:72], "big"), signed[72:]
    assert (ts, batch.hex(), sig.hex()) == (entry["ts_ms"], entry["batch_hex"], entry["sig_hex"])
    transcript = owner_transcript(entry["key"], ts, batch)
    assert transcript.hex() == entry["transcript_hex"]
    VerifyKey(public).verify(transcript, sig)
    assert SigningKey(seed).sign(transcript).signature == sig  # deterministic (RFC 8032)
    if entry["name"] == "audit":
        assert all(json.loads(line)["v"] == 1 for line in batch.splitlines())
    else:
        [[kind, frm, _ts, body]] = msgpack.unpackb(batch, raw=False)
        assert (kind, frm, json.loads(body)["performative"]) == ("acl", "uav-b", "request")


def lp4(raw: bytes) -> bytes:
    """A field of a directory statement's signed bytes: 4-byte big-endian length, then it."""
    return len(raw).to_bytes(4, "big") + raw


def statement_bytes(st: dict[str, Any], nonce: bytes) -> bytes:
    """What a directory statement signs (docs/wire.md, "Directory statements")."""
    return (
        b"dyknow-dir-v1 sig\x00"
        + lp4(st["fed"].encode())
        + lp4(st["from"].encode())
        + lp4(st["kind"].encode())
        + u64(st["boot"])
        + u64(st["seq"])
        + u64(st["ts_ms"])
        + lp4(nonce)  # the nonce's bytes, not its base64 text
        + st["body"].encode()
    )


@pytest.mark.parametrize("entry", VECTORS["directory_statements"], ids=lambda e: e["name"])
def test_directory_statements_from_the_description(entry: dict[str, Any]) -> None:
    st = json.loads(entry["statement"])
    assert set(st) == {"v", "fed", "from", "kind", "boot", "seq", "ts_ms", "nonce", "body", "sig"}
    assert (st["v"], st["fed"], st["from"], st["kind"]) == (1, FED, entry["from"], entry["kind"])
    folder = {"df": "df", "df-event": "df-events"}[st["kind"]]
    assert entry["key"] == f"dyknow/{FED}/v1/{folder}/{st['from']}"
    nonce = h(entry["query_nonce_hex"])
    # an answer carries its query's nonce in base64; an event an empty one
    assert st["nonce"] == base64.b64encode(nonce).decode()
    assert (st["kind"] == "df") == (len(nonce) == 16)
    signed = statement_bytes(st, nonce)
    assert signed.hex() == entry["signed_hex"]
    p = VECTORS["platforms"][st["from"]]
    VerifyKey(h(p["ed25519_public_hex"])).verify(signed, b64(st["sig"]))
    assert SigningKey(h(p["ed25519_seed_hex"])).sign(signed).signature.hex() == entry["sig_hex"]
    body = json.loads(st["body"])
    services = body if st["kind"] == "df" else [body["service"]]
    for service in services:
        assert service["type"] == "dyknow-federation"
        assert service["provider"] == f"federation@{st['from']}"
        assert service["visibility"] == "public"


# -- the project's code ------------------------------------------------------------------------


class FixedClock:
    """A clock reading a set number of milliseconds."""

    def __init__(self, ms: int) -> None:
        self.ms = ms

    def __call__(self) -> float:
        return (self.ms + 0.5) / 1000


def _ephemeral_of(side: dict[str, str]) -> tuple[bytes, bytes, bytes]:
    """The nonce and X25519 key pair a handshake message of the vectors used."""
    return h(side["nonce_hex"]), h(side["x25519_public_hex"]), h(side["x25519_secret_hex"])


def _ours() -> tuple[Any, ...]:
    from agents._security import Handshake, KeyPair, SecurityPolicy, TrustStore

    pairs = {
        p: KeyPair(p, SigningKey(h(v["ed25519_seed_hex"]))) for p, v in VECTORS["platforms"].items()
    }
    trust = TrustStore(FED, {p: k.public_key for p, k in pairs.items()})
    # explicit, whatever the defaults: the vectors seal both kinds and read both
    policy = SecurityPolicy(encrypt=False, require_encryption=False)
    a, b = KX["init"]["from"], KX["reply"]["from"]
    clocks = {a: FixedClock(KX["init"]["ts_ms"]), b: FixedClock(KX["reply"]["ts_ms"])}
    hs = {p: Handshake(pairs[p], trust, policy=policy, clock=clocks[p]) for p in (a, b)}
    for p, side in ((a, KX["init"]), (b, KX["reply"])):
        hs[p]._ephemeral = functools.partial(_ephemeral_of, side)
    return a, b, trust, policy, clocks, hs


def test_our_code_makes_the_same_key_exchange_and_accepts_it() -> None:
    a, b, _trust, _policy, _clocks, hs = _ours()
    assert hs[a].initiate(b).decode() == KX["init"]["json"]
    reply, s_b = hs[b].respond(KX["init"]["json"].encode())
    assert reply.decode() == KX["reply"]["json"]
    s_a = hs[a].finish(KX["reply"]["json"].encode())
    assert s_a.sid == s_b.sid == KX["sid"]


def test_our_code_seals_the_same_envelopes_and_opens_them() -> None:
    from agents._security import SessionTable

    a, b, trust, policy, clocks, hs = _ours()
    hs[a].initiate(b)
    _, s_b = hs[b].respond(KX["init"]["json"].encode())
    s_a = hs[a].finish(KX["reply"]["json"].encode())
    sessions = {a: s_a, b: s_b}
    tables = {p: SessionTable(p, trust, policy=policy, clock=clocks[p]) for p in (a, b)}
    tables[a].add(s_a)
    tables[b].add(s_b)
    for entry in VECTORS["envelopes"]:
        session = sessions[entry["from"]]
        session._encrypt = entry["encrypted"]
        session._clock = FixedClock(entry["ts_ms"])
        clocks[entry["to"]].ms = entry["ts_ms"]
        if entry["kind"] == "binary":
            body = h(entry["body_hex"])
            assert session.seal_bytes(body).hex() == entry["envelope_hex"], entry["name"]
            opened = tables[entry["to"]].open_bytes(h(entry["envelope_hex"]))
            assert opened == (entry["from"], body)
        elif entry["kind"] == "acl-binary":
            sealed = session.seal_binary(entry["body"])
            assert sealed.hex() == entry["envelope_hex"], entry["name"]
            opened = tables[entry["to"]].open(h(entry["envelope_hex"]))
            assert opened == (entry["from"], entry["body"].encode())
        else:
            sealed = session.seal(entry["body"])
            assert sealed.decode() == entry["envelope"], entry["name"]
            opened = tables[entry["to"]].open(entry["envelope"].encode())
            assert opened == (entry["from"], entry["body"].encode())


def test_our_code_signs_and_opens_the_owner_batches() -> None:
    from agents._exceptions import Forged, Replayed
    from agents._security import KeyPair, OwnerBatches, sign_owner_batch

    for entry in VECTORS["owner_batches"]:
        seed = h(VECTORS["platforms"][entry["platform"]]["ed25519_seed_hex"])
        owner = KeyPair(entry["platform"], SigningKey(seed))
        batch, key, ts = h(entry["batch_hex"]), entry["key"], entry["ts_ms"]
        assert sign_owner_batch(owner, key, batch, ts).hex() == entry["signed_hex"]
        batches = OwnerBatches(owner, owner.public_key, clock=FixedClock(ts))
        assert batches.open(key, h(entry["payload_hex"])) == batch
        # the same batch again is a replay; on the other key it is not the platform's
        with pytest.raises(Replayed):
            batches.open(key, h(entry["payload_hex"]))
        other = (
            key.replace("/audit/", "/watch/")
            if "/audit/" in key
            else key.replace("/watch/", "/audit/")
        )
        with pytest.raises(Forged):
            OwnerBatches(owner, owner.public_key, clock=FixedClock(ts)).open(
                other, h(entry["payload_hex"])
            )


def test_our_code_signs_and_opens_the_directory_statements() -> None:
    from agents._directory_auth import DirectoryAuth

    a, b, trust, _policy, _clocks, _hs = _ours()
    pairs = {p: _pair(p) for p in (a, b)}
    for entry in VECTORS["directory_statements"]:
        clock = FixedClock(entry["ts_ms"])
        mine = DirectoryAuth(FED, keys=pairs[b], trust=trust, clock=clock)
        mine.boot, mine.seq = entry["boot"], entry["seq"] - (entry["kind"] == "df-event")
        st = json.loads(entry["statement"])
        nonce = h(entry["query_nonce_hex"])
        made = mine.seal(b, entry["kind"], json.loads(st["body"]), nonce=nonce)
        assert made.decode() == entry["statement"]
        reader = DirectoryAuth(FED, keys=pairs[a], trust=trust, clock=clock)
        opened = reader.open(made, entry["kind"], platform=b, nonce=nonce or None)
        assert opened.body == json.loads(st["body"])


def test_the_watch_request_and_answer_from_the_description() -> None:
    w = VECTORS["watch"]
    p = VECTORS["platforms"][w["platform"]]
    public = VerifyKey(h(p["ed25519_public_hex"]))
    request, answer = json.loads(w["request"]), json.loads(w["answer"])
    assert set(request) == {"v", "watch", "fed", "platform", "ts_ms", "nonce", "sig"}
    assert set(answer) == {"v", "watching", "lease_s", "ts_ms", "sig"}
    nonce = b64(request["nonce"])
    assert len(nonce) == 16
    signed = (
        b"dyknow-watch-v1\x00"
        + lp(request["fed"])
        + lp(request["platform"])
        + u64(request["ts_ms"])
        + nonce
    )
    assert signed.hex() == w["request_transcript_hex"]
    assert b64(request["sig"]).hex() == w["request_sig_hex"]
    public.verify(signed, b64(request["sig"]))
    # the answer is bound to the request's nonce, under another label
    said = (
        b"dyknow-watch-v1 answer\x00"
        + lp(request["fed"])
        + lp(request["platform"])
        + u64(answer["ts_ms"])
        + nonce
    )
    assert said.hex() == w["answer_transcript_hex"]
    assert b64(answer["sig"]).hex() == w["answer_sig_hex"]
    public.verify(said, b64(answer["sig"]))
    with pytest.raises(BadSignatureError):  # the request's signature does not answer it
        public.verify(said, b64(request["sig"]))


def test_our_code_accepts_the_watch_request_and_makes_the_same_answer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import agents._security as security
    from agents._exceptions import Forged

    w = VECTORS["watch"]
    request, answer = json.loads(w["request"]), json.loads(w["answer"])
    owner = _pair(w["platform"])
    nonce = b64(request["nonce"])
    monkeypatch.setattr(security.os, "urandom", lambda n: nonce[:n])
    made = security.watch_request(owner, FED, clock=FixedClock(request["ts_ms"]))
    assert made.decode() == w["request"]
    gate = security.WatchGate(owner, FED, clock=FixedClock(request["ts_ms"]))
    assert gate.check(made) == nonce
    said = security.watch_answer(owner, FED, nonce, 10.0, clock=FixedClock(answer["ts_ms"]))
    assert said.decode() == w["answer"]
    assert security.watch_time(owner.public_key, FED, made, said) == answer["ts_ms"] / 1000
    other = json.dumps(request | {"nonce": base64.b64encode(bytes(16)).decode()}).encode()
    with pytest.raises(Forged):  # an answer to another request
        security.watch_time(owner.public_key, FED, other, said)


def _pair(platform: str) -> Any:
    from agents._security import KeyPair

    return KeyPair(platform, SigningKey(h(VECTORS["platforms"][platform]["ed25519_seed_hex"])))


def test_our_code_refuses_the_usual_mistakes() -> None:
    from agents._directory_auth import DirectoryAuth, DirectoryStatementError
    from agents._exceptions import Forged
    from agents._security import KeyPair, OwnerBatches, SessionTable

    a, b, trust, policy, clocks, hs = _ours()
    owner = KeyPair(a, SigningKey(h(VECTORS["platforms"][a]["ed25519_seed_hex"])))
    for entry in VECTORS["must_refuse"]:
        if entry["kind"] == "directory":
            reader = DirectoryAuth(FED, keys=owner, trust=trust, clock=FixedClock(entry["ts_ms"]))
            with pytest.raises(DirectoryStatementError, match="signature does not verify"):
                reader.open(
                    entry["statement"].encode(),
                    "df",
                    platform=json.loads(entry["statement"])["from"],
                    nonce=h(entry["query_nonce_hex"]),
                )
        if entry["kind"] == "owner-batch":
            batches = OwnerBatches(owner, owner.public_key, clock=FixedClock(entry["ts_ms"]))
            with pytest.raises(Forged, match="not signed"):
                batches.open(entry["key"], h(entry["signed_hex"]), sealed=False)
        if entry["kind"] == "kx-init":
            with pytest.raises(Forged, match="signature"):
                hs[b].respond(entry["json"].encode())
    hs[a].initiate(b)
    _, s_b = hs[b].respond(KX["init"]["json"].encode())
    table = SessionTable(b, trust, policy=policy, clock=clocks[b])
    table.add(s_b)
    for entry in VECTORS["must_refuse"]:
        if entry["kind"] == "json":
            clocks[b].ms = json.loads(entry["envelope"])["ts_ms"]
            with pytest.raises(Forged, match="bad MAC"):
                table.open(entry["envelope"].encode())
        elif entry["kind"] == "binary":
            clocks[b].ms = msgpack.unpackb(h(entry["envelope_hex"]))[4]
            with pytest.raises(Forged, match="bad MAC"):
                table.open_bytes(h(entry["envelope_hex"]))
        elif entry["kind"] == "acl-binary":
            clocks[b].ms = msgpack.unpackb(h(entry["envelope_hex"]))[4]
            with pytest.raises(Forged, match="bad MAC"):
                table.open(h(entry["envelope_hex"]))
