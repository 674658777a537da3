"""Regenerate ``docs/test-vectors.json``: fixed inputs, every output computed by our code.

::

    python -m tools.gen_vectors            # write docs/test-vectors.json
    python -m tools.gen_vectors --check    # exit 1 when the file is not what the code makes

The inputs (Ed25519 seeds, X25519 ephemeral secrets, nonces, timestamps, bodies) are
constants below. The outputs come from ``agents._security`` itself: a real handshake
between ``uav-a`` and ``uav-b`` (with the ephemeral keys and nonces injected, the clocks
fixed) and real sealed envelopes. The intermediate byte strings an implementer checks
step by step (transcripts, MAC inputs, associated data, nonces) are built with the same
helpers the sessions use; the directory statements are sealed by
``agents._directory_auth`` and opened by another platform's. ``docs/test-vectors.md``
explains each entry; ``tests/test_vectors.py`` recomputes everything independently from
that description.
"""

from __future__ import annotations

import argparse
import base64
import functools
import hashlib
import hmac
import json
import sys
from pathlib import Path
from typing import Any

import msgpack
from nacl import bindings as sodium
from nacl.signing import SigningKey

from agents import ACLMessage, Performative
from agents._directory_auth import DirectoryAuth
from agents._security import (
    _ACL_BOX,
    _ACL_MAC,
    _BIN_BOX,
    _BIN_MAC,
    _ENV_BOX,
    _ENV_MAC,
    _OWNER_SIG,
    _U64X2,
    Handshake,
    KeyPair,
    OwnerBatches,
    SecurityPolicy,
    Session,
    SessionTable,
    TrustStore,
    WatchGate,
    _acl_nonce,
    _aead_nonce,
    _bin_nonce,
    _env_head,
    _hkdf,
    _init_transcript,
    _owner_transcript,
    _reply_part,
    _session_id,
    _watch_answer_transcript,
    _watch_transcript,
    sign_owner_batch,
    watch_answer,
    watch_time,
)
from federation._batch import pack_batch

PATH = Path(__file__).resolve().parent.parent / "docs" / "test-vectors.json"

FEDERATION = "demo"
INITIATOR, RESPONDER = "uav-a", "uav-b"
SEEDS = {INITIATOR: bytes(range(0x00, 0x20)), RESPONDER: bytes(range(0x20, 0x40))}
# (nonce, X25519 secret) of each side's handshake message
EPHEMERAL = {
    INITIATOR: (bytes(range(0x80, 0x90)), bytes(range(0x40, 0x60))),
    RESPONDER: (bytes(range(0x90, 0xA0)), bytes(range(0x60, 0x80))),
}
TS_INIT, TS_REPLY = 1795000000123, 1795000000125
TS_ENVELOPES = 1795000000200  # the first envelope; each next one 1 ms later
LABEL = "car5-state"
TS_OWNER = 1795000000300  # the first batch for the owner; the next one 1 ms later
# the X25519 ephemeral secret of each sealed box to the owner (random in a real one)
OWNER_EPHEMERAL = (bytes(range(0xA0, 0xC0)), bytes(range(0xC0, 0xE0)))
# directory statements: uav-b's process start, the first statement's time, the DF query's nonce
TS_WATCH, TS_WATCHING = 1795000000500, 1795000000510  # the watch request, its answer
WATCH_NONCE = bytes(range(0xF0, 0x100))
DIR_BOOT, TS_DIR = 1795000000000, 1795000000400
DIR_NONCE = bytes(range(0xE0, 0xF0))


class _Clock:
    """A clock that reads a set number of milliseconds (exactly, after ``int(t * 1000)``)."""

    def __init__(self, ms: int) -> None:
        self.ms = ms

    def __call__(self) -> float:
        return (self.ms + 0.5) / 1000


def _ephemeral(platform: str) -> tuple[bytes, bytes, bytes]:
    nonce, secret = EPHEMERAL[platform]
    return nonce, sodium.crypto_scalarmult_base(secret), secret


def _acl(sender: str, receiver: str, performative: Performative, content: Any) -> bytes:
    return ACLMessage(
        performative=performative,
        sender=f"federation@{sender}",
        receivers=[f"federation@{receiver}"],
        content=content,
        ontology="dyknow-federation",
        protocol="fipa-request",
        conversation_id="c-0123abcd-1",
        reply_with="r-0123abcd-2" if performative is Performative.REQUEST else None,
        in_reply_to="r-0123abcd-2" if performative is not Performative.REQUEST else None,
    ).to_json()


def _envelope(
    name: str,
    session: Session,
    fed: str,
    *,
    binary: bool,
    encrypt: bool,
    body: bytes,
    clock: _Clock,
    about: str,
    acl: bool = False,
) -> dict[str, Any]:
    """Seal ``body`` on ``session`` with our code; the entry with its intermediate bytes.

    ``acl``: an ACL message in the binary form (msgpack on acl/…, the JSON form's counter).
    """
    session._encrypt = encrypt  # one session makes both kinds; only here
    if acl:
        sealed = session.seal_binary(body)
    else:
        sealed = session.seal_bytes(body) if binary else session.seal(body)
    clock.ms += 1
    n = session.sent_binary if binary else session.sent
    ts = clock.ms - 1
    direction = "i2r" if session.initiator else "r2i"
    entry: dict[str, Any] = {
        "name": name,
        "about": about,
        "kind": "acl-binary" if acl else "binary" if binary else "json",
        "encrypted": encrypt,
        "from": session.me,
        "to": session.peer,
        "sid": session.sid,
        "direction": direction,
        "ts_ms": ts,
        "n": n,
    }
    entry["body" if not binary else "body_hex"] = body.decode() if not binary else body.hex()
    ctr = _U64X2.pack(ts, n)
    head = (fed, session.me, session.peer, session.sid)
    if encrypt:
        box_label = _ACL_BOX if acl else _BIN_BOX if binary else _ENV_BOX
        ad = _env_head(box_label, *head) + ctr
        nonce = (_acl_nonce if acl else _bin_nonce if binary else _aead_nonce)(n)
        entry["key"] = f"{direction} box"
        entry["ad_hex"] = ad.hex()
        entry["nonce_hex"] = nonce.hex()
        if binary or acl:
            box = msgpack.unpackb(sealed, raw=False)[6]
        else:
            box = base64.b64decode(json.loads(sealed)["box"])
        entry["ciphertext_hex"] = box.hex()
    else:
        mac_label = _ACL_MAC if acl else _BIN_MAC if binary else _ENV_MAC
        mac_input = _env_head(mac_label, *head) + ctr + body
        entry["key"] = f"{direction} mac"
        entry["mac_input_hex"] = mac_input.hex()
        if binary or acl:
            mac = msgpack.unpackb(sealed, raw=False)[7]
        else:
            mac = base64.b64decode(json.loads(sealed)["mac"])
        entry["mac_hex"] = mac.hex()
    if binary:
        entry["envelope_hex"] = sealed.hex()
        entry["body_decoded"] = msgpack.unpackb(body, raw=False)
    elif acl:
        entry["envelope_hex"] = sealed.hex()
    else:
        entry["envelope"] = sealed.decode()
    return entry


def _refusals(
    pairs: dict[str, KeyPair], init: bytes, envelopes: list[dict[str, Any]], keys: dict[str, bytes]
) -> list[dict[str, Any]]:
    """Messages made with the usual mistakes: a receiver must refuse every one (forged)."""
    init_obj = json.loads(init)
    na, ea = EPHEMERAL[INITIATOR][0], sodium.crypto_scalarmult_base(EPHEMERAL[INITIATOR][1])

    def lp(text: str) -> bytes:
        return len(text.encode()).to_bytes(2, "big") + text.encode()

    # the label length-prefixed like the names, instead of followed by one zero byte
    wrong_t1 = (
        lp("dyknow-kx-v1 init")
        + lp(FEDERATION)
        + lp(INITIATOR)
        + lp(RESPONDER)
        + TS_INIT.to_bytes(8, "big")
        + na
        + ea
    )
    bad_init = {**init_obj, "sig": base64.b64encode(pairs[INITIATOR].sign(wrong_t1)).decode()}
    plain = next(e for e in envelopes if e["name"] == "json-mac")
    mac_input = bytes.fromhex(plain["mac_input_hex"])
    label = _ENV_MAC
    # the MAC input without the zero byte after the label
    no_zero = label[:-1] + mac_input[len(label) :]
    env = json.loads(plain["envelope"])
    env["mac"] = base64.b64encode(hmac.digest(keys["i2r mac"], no_zero, "sha256")).decode()
    # a binary envelope MACed with the JSON envelopes' label
    binary = next(e for e in envelopes if e["name"] == "binary-mac")
    bin_input = bytes.fromhex(binary["mac_input_hex"])
    swapped = _ENV_MAC + bin_input[len(_BIN_MAC) :]
    arr = msgpack.unpackb(bytes.fromhex(binary["envelope_hex"]), raw=False)
    arr[7] = hmac.digest(keys["i2r mac"], swapped, "sha256")
    # a binary ACL envelope MACed with the JSON envelopes' label
    acl_bin = next(e for e in envelopes if e["name"] == "acl-binary-mac")
    acl_input = bytes.fromhex(acl_bin["mac_input_hex"])
    acl_swapped = _ENV_MAC + acl_input[len(_ACL_MAC) :]
    acl_arr = msgpack.unpackb(bytes.fromhex(acl_bin["envelope_hex"]), raw=False)
    acl_arr[7] = hmac.digest(keys["i2r mac"], acl_swapped, "sha256")
    return [
        {
            "name": "kx-init-label-length-prefixed",
            "about": "an init signed over a T1 whose label is length-prefixed: bad signature",
            "kind": "kx-init",
            "to": RESPONDER,
            "signed_hex": wrong_t1.hex(),
            "json": json.dumps(bad_init, separators=(",", ":")),
        },
        {
            "name": "json-mac-label-without-zero-byte",
            "about": "json-mac with its MAC computed without the zero byte after the label",
            "kind": "json",
            "to": RESPONDER,
            "mac_input_hex": no_zero.hex(),
            "envelope": json.dumps(env, separators=(",", ":"), ensure_ascii=False),
        },
        {
            "name": "binary-mac-with-json-label",
            "about": "binary-mac with its MAC computed under the JSON label dyknow-env-v1 mac",
            "kind": "binary",
            "to": RESPONDER,
            "mac_input_hex": swapped.hex(),
            "envelope_hex": msgpack.packb(arr).hex(),
        },
        {
            "name": "acl-binary-mac-with-json-label",
            "about": "acl-binary-mac with its MAC computed under the JSON label dyknow-env-v1 mac",
            "kind": "acl-binary",
            "to": RESPONDER,
            "mac_input_hex": acl_swapped.hex(),
            "envelope_hex": msgpack.packb(acl_arr).hex(),
        },
    ]


def _seal(message: bytes, public_x25519: bytes, secret: bytes) -> tuple[bytes, bytes, bytes]:
    """A libsodium sealed box with a given ephemeral secret: (its public key, nonce, box)."""
    epk = sodium.crypto_scalarmult_base(secret)
    nonce = hashlib.blake2b(epk + public_x25519, digest_size=24).digest()
    return epk, nonce, epk + sodium.crypto_box(message, nonce, public_x25519, secret)


def _owner_batches(owner: KeyPair) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Batches ``owner``'s platform publishes to its owner, and the usual mistakes in them."""
    public_x25519 = sodium.crypto_sign_ed25519_pk_to_curve25519(owner.public_key)
    audit_key = f"dyknow/{FEDERATION}/v1/audit/{owner.platform}"
    watch_key = f"dyknow/{FEDERATION}/v1/watch/{owner.platform}"
    record = {"v": 1, "ts": 1795000000.25, "platform": owner.platform, "from": RESPONDER}
    record |= {"sender": f"federation@{RESPONDER}", "receivers": [f"federation@{owner.platform}"]}
    record |= {"performative": "request", "conversation_id": "c-0123abcd-1"}
    record |= {"verdict": "accepted", "reason": None}
    audit = json.dumps(record, separators=(",", ":")).encode() + b"\n"
    acl = _acl(RESPONDER, owner.platform, Performative.REQUEST, {"action": "get-latest"})
    watch = msgpack.packb([["acl", RESPONDER, 1795000000.25, acl]], use_bin_type=True)
    entries = []
    for i, (name, key, batch, about) in enumerate(
        (
            ("audit", audit_key, audit, "an audit batch of one record (JSON lines)"),
            ("watch", watch_key, watch, "a watch batch: one ACL message uav-b sent uav-a"),
        )
    ):
        ts = TS_OWNER + i
        transcript = _owner_transcript(key, ts, batch)
        signed = sign_owner_batch(owner, key, batch, ts)
        epk, nonce, payload = _seal(signed, public_x25519, OWNER_EPHEMERAL[i])
        assert owner.open_sealed(payload) == signed
        opened = OwnerBatches(owner, owner.public_key, clock=_Clock(ts)).open(key, payload)
        assert opened == batch, name
        entries.append(
            {
                "name": name,
                "about": about,
                "platform": owner.platform,
                "key": key,
                "ts_ms": ts,
                "batch_hex": batch.hex(),
                "transcript_hex": transcript.hex(),
                "sig_hex": signed[:64].hex(),
                "signed_hex": signed.hex(),
                "owner_x25519_public_hex": public_x25519.hex(),
                "ephemeral_secret_hex": OWNER_EPHEMERAL[i].hex(),
                "ephemeral_public_hex": epk.hex(),
                "nonce_hex": nonce.hex(),
                "payload_hex": payload.hex(),
            }
        )
    watched = entries[1]
    # the length of the key in 4 bytes, as directory statements have it, instead of 2
    wide = _OWNER_SIG + len(audit_key).to_bytes(4, "big") + audit_key.encode()
    wide += TS_OWNER.to_bytes(8, "big") + audit
    refusals = [
        {
            "name": "owner-batch-on-another-key",
            "about": "the watch batch (signed over its key) published on the audit key",
            "kind": "owner-batch",
            "key": audit_key,
            "ts_ms": watched["ts_ms"],
            "signed_hex": watched["signed_hex"],
        },
        {
            "name": "owner-batch-key-4-byte-length",
            "about": "the audit batch signed with the key's length in 4 bytes, not 2",
            "kind": "owner-batch",
            "key": audit_key,
            "ts_ms": TS_OWNER,
            "transcript_hex": wide.hex(),
            "signed_hex": (owner.sign(wide) + TS_OWNER.to_bytes(8, "big") + audit).hex(),
        },
    ]
    return entries, refusals


def _watch(owner: KeyPair) -> dict[str, Any]:
    """The owner's watch request for ``owner``'s platform and the platform's signed answer."""
    request_transcript = _watch_transcript(FEDERATION, owner.platform, TS_WATCH, WATCH_NONCE)
    request_sig = owner.sign(request_transcript)
    request = {
        "v": 1,
        "watch": "lease",
        "fed": FEDERATION,
        "platform": owner.platform,
        "ts_ms": TS_WATCH,
        "nonce": base64.b64encode(WATCH_NONCE).decode(),
        "sig": base64.b64encode(request_sig).decode(),
    }
    request_json = json.dumps(request, separators=(",", ":"))
    gate = WatchGate(owner, FEDERATION, clock=_Clock(TS_WATCH))
    assert gate.check(request_json.encode()) == WATCH_NONCE
    answer = watch_answer(owner, FEDERATION, WATCH_NONCE, 10.0, clock=_Clock(TS_WATCHING))
    answer_transcript = _watch_answer_transcript(
        FEDERATION, owner.platform, TS_WATCHING, WATCH_NONCE
    )
    answered = watch_time(owner.public_key, FEDERATION, request_json.encode(), answer)
    assert answered == TS_WATCHING / 1000
    return {
        "platform": owner.platform,
        "request": request_json,
        "request_transcript_hex": request_transcript.hex(),
        "request_sig_hex": request_sig.hex(),
        "answer": answer.decode(),
        "answer_transcript_hex": answer_transcript.hex(),
        "answer_sig_hex": base64.b64decode(json.loads(answer)["sig"]).hex(),
    }


def _directory_statements(
    pairs: dict[str, KeyPair], trust: TrustStore
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """uav-b's signed DF answer to uav-a's query and its register event; the usual mistake."""
    me = RESPONDER
    clock = _Clock(TS_DIR)
    auth = DirectoryAuth(FEDERATION, keys=pairs[me], trust=trust, clock=clock)
    auth.boot = DIR_BOOT
    reader = DirectoryAuth(FEDERATION, keys=pairs[INITIATOR], trust=trust, clock=clock)
    # the public entry every member lists (docs/federation.md, "Membership")
    service = {
        "name": "dyknow-federation-discovery",
        "type": "dyknow-federation",
        "provider": f"federation@{me}",
        "properties": {"entry": "discovery"},
        "ontology": "dyknow-federation",
        "protocols": ["fipa-request", "fipa-query", "fipa-subscribe"],
        "visibility": "public",
    }
    entries = []
    for i, (name, kind, body, nonce, about) in enumerate(
        (
            ("df-answer", "df", [service], DIR_NONCE, "uav-b's answer to a query on df/uav-b"),
            (
                "df-event-register",
                "df-event",
                {"op": "register", "service": service},
                b"",
                "uav-b's event on df-events/uav-b as it registers the entry",
            ),
        )
    ):
        clock.ms = TS_DIR + i
        statement = auth.seal(me, kind, body, nonce=nonce)
        obj = json.loads(statement)
        text = obj["body"].encode()
        signed = (
            b"dyknow-dir-v1 sig\x00"
            + b"".join(len(x).to_bytes(4, "big") + x.encode() for x in (FEDERATION, me, kind))
            + obj["boot"].to_bytes(8, "big")
            + obj["seq"].to_bytes(8, "big")
            + obj["ts_ms"].to_bytes(8, "big")
            + len(nonce).to_bytes(4, "big")
            + nonce
            + text
        )
        assert base64.b64decode(obj["sig"]) == pairs[me].sign(signed), name
        key = f"dyknow/{FEDERATION}/v1/{'df' if kind == 'df' else 'df-events'}/{me}"
        opened = reader.open(statement, kind, platform=me, nonce=nonce if nonce else None)
        assert opened.body == body, name
        entries.append(
            {
                "name": name,
                "about": about,
                "key": key,
                "kind": kind,
                "from": me,
                "boot": obj["boot"],
                "seq": obj["seq"],
                "ts_ms": obj["ts_ms"],
                "query_nonce_hex": nonce.hex(),
                "body": obj["body"],
                "signed_hex": signed.hex(),
                "sig_hex": base64.b64decode(obj["sig"]).hex(),
                "statement": statement.decode(),
            }
        )
    answer = entries[0]
    # the nonce signed as its base64 text (what the statement carries) instead of its bytes
    text_nonce = base64.b64encode(DIR_NONCE)
    wrong = bytes.fromhex(answer["signed_hex"]).replace(
        len(DIR_NONCE).to_bytes(4, "big") + DIR_NONCE,
        len(text_nonce).to_bytes(4, "big") + text_nonce,
    )
    bad = {**json.loads(answer["statement"])}
    bad["sig"] = base64.b64encode(pairs[me].sign(wrong)).decode()
    refusals = [
        {
            "name": "df-answer-nonce-as-base64-text",
            "about": "df-answer signed over the nonce's base64 text instead of its 16 bytes",
            "kind": "directory",
            "key": answer["key"],
            "to": INITIATOR,
            "ts_ms": answer["ts_ms"],
            "query_nonce_hex": answer["query_nonce_hex"],
            "signed_hex": wrong.hex(),
            "statement": json.dumps(bad, separators=(",", ":")),
        }
    ]
    return entries, refusals


def generate() -> dict[str, Any]:
    """Every test vector, computed by the project's code from the fixed inputs above."""
    pairs = {p: KeyPair(p, SigningKey(seed)) for p, seed in SEEDS.items()}
    trust = TrustStore(FEDERATION, {p: k.public_key for p, k in pairs.items()})
    clocks = {INITIATOR: _Clock(TS_INIT), RESPONDER: _Clock(TS_REPLY)}
    # explicit, whatever the defaults: the vectors seal both kinds and read both
    policy = SecurityPolicy(encrypt=False, require_encryption=False)
    hs = {
        p: Handshake(pairs[p], trust, policy=policy, clock=clocks[p])
        for p in (INITIATOR, RESPONDER)
    }
    for p, h in hs.items():
        h._ephemeral = functools.partial(_ephemeral, p)
    init = hs[INITIATOR].initiate(RESPONDER)
    reply, s_resp = hs[RESPONDER].respond(init)
    clocks[INITIATOR].ms = TS_REPLY + 1
    s_init = hs[INITIATOR].finish(reply)

    (na, sa), (nb, sb) = EPHEMERAL[INITIATOR], EPHEMERAL[RESPONDER]
    ea, eb = sodium.crypto_scalarmult_base(sa), sodium.crypto_scalarmult_base(sb)
    t1 = _init_transcript(FEDERATION, INITIATOR, RESPONDER, TS_INIT, na, ea)
    reply_part = _reply_part(FEDERATION, RESPONDER, INITIATOR, TS_REPLY, nb, eb)
    t2 = t1 + reply_part
    shared = sodium.crypto_scalarmult(sa, eb)
    salt = hashlib.sha256(t2).digest()
    keys = _hkdf(t2, shared)
    sid = _session_id(keys["sid"])
    assert sid == s_init.sid == s_resp.sid

    platforms = {
        p: {
            "ed25519_seed_hex": SEEDS[p].hex(),
            "ed25519_public_hex": pairs[p].public_key.hex(),
            "role": "initiator" if p == INITIATOR else "responder",
        }
        for p in (INITIATOR, RESPONDER)
    }
    key_exchange = {
        "init": {
            "from": INITIATOR,
            "to": RESPONDER,
            "ts_ms": TS_INIT,
            "nonce_hex": na.hex(),
            "x25519_secret_hex": sa.hex(),
            "x25519_public_hex": ea.hex(),
            "t1_hex": t1.hex(),
            "sig_hex": base64.b64decode(json.loads(init)["sig"]).hex(),
            "json": init.decode(),
        },
        "reply": {
            "from": RESPONDER,
            "to": INITIATOR,
            "ts_ms": TS_REPLY,
            "nonce_hex": nb.hex(),
            "x25519_secret_hex": sb.hex(),
            "x25519_public_hex": eb.hex(),
            "reply_part_hex": reply_part.hex(),
            "t2_hex": t2.hex(),
            "sig_hex": base64.b64decode(json.loads(reply)["sig"]).hex(),
            "json": reply.decode(),
        },
        "shared_secret_hex": shared.hex(),
        "salt_hex": salt.hex(),
        "prk_hex": hmac.digest(salt, shared, "sha256").hex(),
        "keys_hex": {label: key.hex() for label, key in keys.items()},
        "sid": sid,
    }

    # both sides' tables must open what the other seals (a generator that drifted from
    # the receiving code would write vectors nobody accepts)
    tables = {p: SessionTable(p, trust, policy=policy, clock=clocks[p]) for p in pairs}
    tables[INITIATOR].add(s_init)
    tables[RESPONDER].add(s_resp)
    clock = _Clock(TS_ENVELOPES)
    for p in pairs:
        clocks[p].ms = TS_ENVELOPES
    s_init._clock = s_resp._clock = clock
    request = _acl(
        INITIATOR,
        RESPONDER,
        Performative.REQUEST,
        {"action": "get-latest", "label": "altitude", "where": "Linköping"},
    )
    answer = _acl(RESPONDER, INITIATOR, Performative.INFORM, {"value": 112.5})
    samples = [
        [12.5, 1795000000000000000, 1795000000100000000],
        [{"x": 3, "y": -4}, 1795000000050000000, 1795000000150000000],
    ]
    batch = pack_batch(LABEL, samples, 5120)  # type: ignore[arg-type]
    report = msgpack.packb({"v": 1, "lost": {LABEL: 3}, "resend": {LABEL: [5117, 5120]}})
    envelopes = [
        _envelope(
            "json-mac",
            s_init,
            FEDERATION,
            binary=False,
            encrypt=False,
            body=request,
            clock=clock,
            about="an ACL request, authenticated (HMAC-SHA256)",
        ),
        _envelope(
            "json-mac-reply",
            s_resp,
            FEDERATION,
            binary=False,
            encrypt=False,
            body=answer,
            clock=clock,
            about="the answer, on the responder-to-initiator key",
        ),
        _envelope(
            "json-box",
            s_init,
            FEDERATION,
            binary=False,
            encrypt=True,
            body=request,
            clock=clock,
            about="the same request encrypted (ChaCha20-Poly1305-IETF), counter 2",
        ),
        _envelope(
            "binary-mac",
            s_init,
            FEDERATION,
            binary=True,
            encrypt=False,
            body=batch,
            clock=clock,
            about="a sample batch, authenticated; binary counter 1",
        ),
        _envelope(
            "binary-box",
            s_init,
            FEDERATION,
            binary=True,
            encrypt=True,
            body=batch,
            clock=clock,
            about="the same batch encrypted; binary counter 2",
        ),
        _envelope(
            "stream-report-mac",
            s_resp,
            FEDERATION,
            binary=True,
            encrypt=False,
            body=report,
            clock=clock,
            about="the receiver's stream report (a binary envelope the other way)",
        ),
        _envelope(
            "json-box-batch",
            s_init,
            FEDERATION,
            binary=False,
            encrypt=True,
            body=b"[" + request + b"," + request + b"]",
            clock=clock,
            about="a batch of two ACL messages in one encrypted envelope (a JSON array), counter 3",
        ),
        _envelope(
            "acl-binary-mac",
            s_init,
            FEDERATION,
            binary=False,
            acl=True,
            encrypt=False,
            body=request,
            clock=clock,
            about="the request in the binary form of an ACL envelope, authenticated; "
            "the JSON envelopes' counter: 4",
        ),
        _envelope(
            "acl-binary-box",
            s_init,
            FEDERATION,
            binary=False,
            acl=True,
            encrypt=True,
            body=request,
            clock=clock,
            about="the same request in the binary form, encrypted, counter 5",
        ),
    ]
    for entry in envelopes:
        table = tables[entry["to"]]
        clocks[entry["to"]].ms = entry["ts_ms"]
        if entry["kind"] == "json":
            opened = table.open(entry["envelope"].encode())
            assert opened == (entry["from"], entry["body"].encode()), entry["name"]
        elif entry["kind"] == "acl-binary":
            opened = table.open(bytes.fromhex(entry["envelope_hex"]))
            assert opened == (entry["from"], entry["body"].encode()), entry["name"]
        else:
            opened = table.open_bytes(bytes.fromhex(entry["envelope_hex"]))
            assert opened == (entry["from"], bytes.fromhex(entry["body_hex"])), entry["name"]
    owner_batches, owner_refusals = _owner_batches(pairs[INITIATOR])
    statements, statement_refusals = _directory_statements(pairs, trust)
    return {
        "v": 1,
        "about": "DyKnow Federation wire test vectors; docs/test-vectors.md explains each entry",
        "federation": FEDERATION,
        "platforms": platforms,
        "key_exchange": key_exchange,
        "envelopes": envelopes,
        "owner_batches": owner_batches,
        "watch": _watch(pairs[INITIATOR]),
        "directory_statements": statements,
        "must_refuse": _refusals(pairs, init, envelopes, keys)
        + owner_refusals
        + statement_refusals,
    }


def render(vectors: dict[str, Any]) -> str:
    """The file's exact text (stable: the test compares it byte for byte)."""
    return json.dumps(vectors, indent=2, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write the vectors, or with ``--check`` say whether the file is up to date."""
    parser = argparse.ArgumentParser(prog="python -m tools.gen_vectors", description=__doc__)
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    parser.add_argument("--out", type=Path, default=PATH, help=f"default: {PATH}")
    args = parser.parse_args(argv)
    text = render(generate())
    if args.check:
        current = args.out.read_text(encoding="utf-8") if args.out.exists() else ""
        if current != text:
            print(f"{args.out} is out of date: run python -m tools.gen_vectors", file=sys.stderr)
            return 1
        print(f"{args.out} is up to date")
        return 0
    args.out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
