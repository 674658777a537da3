"""A federation member written from docs/ alone: plain zenoh, msgpack and PyNaCl.

Nothing of this project is imported: this is what another implementation does to
join a federation (docs/wire.md, docs/security.md, docs/federation.md). It joins as
the platform of ``--key`` (presence, signed directory answers, key exchanges), asks
``--peer`` for its labels, streams ``--stream`` from it for ``--count`` batches, then
answers ``get-latest`` for ``--serve`` seconds (or until Ctrl-C) with fixed values
(``--value LABEL=NUMBER``), and leaves. Each step prints one JSON line. With examples/node::

    python examples/outsider.py --key keys/operator.key --trust keys/trust.json \\
        --connect tcp/127.0.0.1:7450 --peer station --stream temperature --serve 5 \\
        --value temperature=21.5
    dyknow ask temperature --platform operator --config station-python.toml  # meanwhile
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import hmac
import json
import os
import struct
import threading
import time
from typing import Any

import msgpack
import nacl.bindings as sodium
import zenoh
from nacl.signing import SigningKey, VerifyKey

# an AEAD nonce's first 4 bytes, per envelope kind: JSON ACL, sample batch, binary ACL
NONCE_SPACE = {"env": bytes(4), "bin": b"\x00\x00\x00\x01", "acl": b"\x00\x00\x00\x02"}


def b64(raw: bytes) -> str:
    """Standard base64 with padding, as every binary JSON field."""
    return base64.b64encode(raw).decode()


def unb64(text: str) -> bytes:
    """The bytes of a standard base64 field."""
    return base64.b64decode(text, validate=True)


def lp2(text: str) -> bytes:
    """A name in transcripts and envelope headers: 2-byte big-endian length, UTF-8."""
    raw = text.encode()
    return struct.pack(">H", len(raw)) + raw


def lp4(raw: bytes) -> bytes:
    """A field of a directory statement's signed bytes: 4-byte big-endian length."""
    return struct.pack(">I", len(raw)) + raw


def u64(value: int) -> bytes:
    """8 bytes big-endian."""
    return struct.pack(">Q", value)


def now_ms() -> int:
    """Unix time in integer milliseconds."""
    return int(time.time() * 1000)


def say(**fields: Any) -> None:
    """One step's JSON line on stdout."""
    print(json.dumps(fields), flush=True)


class Session:
    """The keys and counters of one session (docs/security.md, "Session keys")."""

    def __init__(self, t2: bytes, shared: bytes, peer: str, initiator: bool) -> None:
        prk = hmac.digest(hashlib.sha256(t2).digest(), shared, "sha256")

        def okm(label: str) -> bytes:
            return hmac.digest(prk, f"dyknow-session-v1 {label}".encode() + b"\x01", "sha256")

        self.peer = peer
        self.sid = base64.urlsafe_b64encode(okm("sid")[:16]).rstrip(b"=").decode()
        mine, theirs = ("i2r", "r2i") if initiator else ("r2i", "i2r")
        self.send_box, self.recv_box = okm(f"{mine} box"), okm(f"{theirs} box")
        self.counters = {"env": 0, "bin": 0}
        self.seen: set[tuple[str, int]] = set()


class Member:
    """One platform of the federation, with just enough to join, ask, stream and answer."""

    def __init__(self, key_file: str, trust_file: str, connect: list[str]) -> None:
        with open(key_file) as f:
            key = json.load(f)
        self.name: str = key["platform"]
        self.key = SigningKey(unb64(key["ed25519_seed"]))
        with open(trust_file) as f:
            trust = json.load(f)
        self.fed: str = trust["federation"]
        self.trust = {p: VerifyKey(unb64(k)) for p, k in trust["platforms"].items()}
        self.prefix = f"dyknow/{self.fed}/v1/"
        self.boot, self.seq = now_ms(), 0
        self.sessions: dict[str, Session] = {}
        self.sending: dict[str, Session] = {}  # the session each peer is sent on
        self.waiting: dict[str, list[Any]] = {}  # reply_with -> [event, answer]
        self.batches: list[dict[str, Any]] = []
        self.values: dict[str, float] = {}
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("scouting/multicast/enabled", "false")  # docs/wire.md, "Discovery"
        self.z = zenoh.open(conf)
        self.service = {
            "name": "dyknow-federation-discovery",
            "type": "dyknow-federation",
            "provider": f"federation@{self.name}",
            "properties": {"entry": "discovery"},
            "ontology": "dyknow-federation",
            "protocols": ["fipa-request", "fipa-query", "fipa-subscribe"],
            "visibility": "public",
        }

    # -- the directory (docs/wire.md, "Directory statements") ------------------------------

    def statement(self, kind: str, body: Any, nonce: bytes = b"") -> bytes:
        """A signed directory statement; the nonce is signed as its bytes."""
        text, ts = json.dumps(body), now_ms()
        signed = b"dyknow-dir-v1 sig\x00" + lp4(self.fed.encode()) + lp4(self.name.encode())
        signed += lp4(kind.encode()) + u64(self.boot) + u64(self.seq) + u64(ts)
        signed += lp4(nonce) + text.encode()
        return json.dumps(
            {
                "v": 1,
                "fed": self.fed,
                "from": self.name,
                "kind": kind,
                "boot": self.boot,
                "seq": self.seq,
                "ts_ms": ts,
                "nonce": b64(nonce),
                "body": text,
                "sig": b64(self.key.sign(signed).signature),
            }
        ).encode()

    def on_df(self, query: zenoh.Query) -> None:
        """Answer a directory query with our one public service, signing its nonce."""
        asked = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
        nonce = unb64(asked.get("nonce", ""))
        query.reply(f"{self.prefix}df/{self.name}", self.statement("df", [self.service], nonce))

    def services_of(self, peer: str) -> list[dict[str, Any]]:
        """``peer``'s public services, from its signed answer to a fresh nonce."""
        nonce = os.urandom(16)
        ask = json.dumps({"v": 1, "nonce": b64(nonce)}).encode()
        for reply in self.z.get(f"{self.prefix}df/{peer}", payload=ask, timeout=2.0):
            if reply.ok is None:
                continue
            st = json.loads(reply.ok.payload.to_bytes())
            signed = b"dyknow-dir-v1 sig\x00" + b"".join(
                lp4(st[k].encode()) for k in ("fed", "from", "kind")
            )
            signed += u64(st["boot"]) + u64(st["seq"]) + u64(st["ts_ms"])
            signed += lp4(unb64(st["nonce"])) + st["body"].encode()
            self.trust[peer].verify(signed, unb64(st["sig"]))
            if st["from"] == peer and unb64(st["nonce"]) == nonce:
                services: list[dict[str, Any]] = json.loads(st["body"])
                return services
        return []

    # -- key exchange (docs/security.md, "The key exchange") -------------------------------

    @staticmethod
    def part(label: str, fed: str, frm: str, to: str, ts: int, nonce: bytes, epk: bytes) -> bytes:
        """One half of a transcript: label, zero byte, names, time, nonce, key."""
        return label.encode() + b"\x00" + lp2(fed) + lp2(frm) + lp2(to) + u64(ts) + nonce + epk

    def key_exchange(self, peer: str) -> Session:
        """Open a session with ``peer`` as the initiator."""
        secret, nonce, ts = os.urandom(32), os.urandom(16), now_ms()
        epk = sodium.crypto_scalarmult_base(secret)
        t1 = self.part("dyknow-kx-v1 init", self.fed, self.name, peer, ts, nonce, epk)
        init = {
            "v": 1,
            "kx": "init",
            "fed": self.fed,
            "from": self.name,
            "to": peer,
            "ts_ms": ts,
            "nonce": b64(nonce),
            "epk": b64(epk),
            "sig": b64(self.key.sign(t1).signature),
        }
        for reply in self.z.get(f"{self.prefix}kx/{peer}", payload=json.dumps(init), timeout=2.0):
            if reply.ok is None:
                continue  # an error reply: a reason, not authenticated
            r = json.loads(reply.ok.payload.to_bytes())
            if (r["kx"], r["from"], r["to"], r["re"]) != ("reply", peer, self.name, b64(nonce)):
                continue
            t2 = t1 + self.part(
                "dyknow-kx-v1 reply",
                self.fed,
                peer,
                self.name,
                r["ts_ms"],
                unb64(r["nonce"]),
                unb64(r["epk"]),
            )
            self.trust[peer].verify(t2, unb64(r["sig"]))
            session = Session(t2, sodium.crypto_scalarmult(secret, unb64(r["epk"])), peer, True)
            self.sessions[session.sid] = self.sending[peer] = session
            return session
        raise RuntimeError(f"no key-exchange reply from {peer}")

    def on_kx(self, query: zenoh.Query) -> None:
        """Answer another platform's init as the responder."""
        init = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
        peer = init.get("from", "")
        if peer not in self.trust or init.get("to") != self.name or init.get("fed") != self.fed:
            return
        t1 = self.part(
            "dyknow-kx-v1 init",
            self.fed,
            peer,
            self.name,
            init["ts_ms"],
            unb64(init["nonce"]),
            unb64(init["epk"]),
        )
        self.trust[peer].verify(t1, unb64(init["sig"]))
        secret, nonce, ts = os.urandom(32), os.urandom(16), now_ms()
        epk = sodium.crypto_scalarmult_base(secret)
        t2 = t1 + self.part("dyknow-kx-v1 reply", self.fed, self.name, peer, ts, nonce, epk)
        session = Session(t2, sodium.crypto_scalarmult(secret, unb64(init["epk"])), peer, False)
        self.sessions[session.sid] = session
        reply = {
            "v": 1,
            "kx": "reply",
            "fed": self.fed,
            "from": self.name,
            "to": peer,
            "ts_ms": ts,
            "nonce": b64(nonce),
            "epk": b64(epk),
            "re": init["nonce"],
            "sig": b64(self.key.sign(t2).signature),
        }
        query.reply(f"{self.prefix}kx/{self.name}", json.dumps(reply))

    # -- sealed envelopes (docs/security.md, "Envelope bytes") -----------------------------

    def head(self, kind: str, s: Session, frm: str, to: str, ts: int, n: int) -> bytes:
        """Fields 1-7: the associated data of an encrypted envelope."""
        label = f"dyknow-{kind}-v1 box".encode() + b"\x00"
        return label + lp2(self.fed) + lp2(frm) + lp2(to) + lp2(s.sid) + u64(ts) + u64(n)

    def seal(self, kind: str, s: Session, body: bytes) -> tuple[int, int, bytes]:
        """Encrypt ``body`` (kind ``env``: JSON ACL envelopes, ``bin``: sample batches)."""
        s.counters[kind] += 1
        n, ts = s.counters[kind], now_ms()
        nonce = NONCE_SPACE[kind] + u64(n)
        ad = self.head(kind, s, self.name, s.peer, ts, n)
        box = sodium.crypto_aead_chacha20poly1305_ietf_encrypt(body, ad, nonce, s.send_box)
        return ts, n, box

    def open(self, kind: str, frm: str, to: str, sid: str, ts: int, n: int, box: bytes) -> bytes:
        """Decrypt an envelope to us on a session we hold (kind ``acl``: an ACL envelope's
        binary form); refuse replays."""
        s = self.sessions[sid]
        # the two forms of an ACL envelope count on one counter: an n is one envelope
        counter = "bin" if kind == "bin" else "env"
        if to != self.name or s.peer != frm or abs(ts - now_ms()) > 30_000:
            raise ValueError("misdirected, forged or expired")
        if (counter, n) in s.seen:
            raise ValueError("replayed")
        nonce = NONCE_SPACE[kind] + u64(n)
        ad = self.head(kind, s, frm, to, ts, n)
        body: bytes = sodium.crypto_aead_chacha20poly1305_ietf_decrypt(box, ad, nonce, s.recv_box)
        s.seen.add((counter, n))
        return body

    def send(self, peer: str, message: dict[str, Any]) -> None:
        """One ACL message to ``peer``, on the session we send it on (else the one it opened)."""
        s = self.sending.get(peer) or next(
            (x for x in reversed(self.sessions.values()) if x.peer == peer), None
        )
        s = s or self.key_exchange(peer)
        ts, n, box = self.seal("env", s, json.dumps(message).encode())
        env = {
            "v": 1,
            "from": self.name,
            "to": peer,
            "sid": s.sid,
            "ts_ms": ts,
            "n": n,
            "box": b64(box),
        }
        self.z.put(f"{self.prefix}acl/{peer}", json.dumps(env))

    def on_acl(self, sample: zenoh.Sample) -> None:
        """An envelope on acl/<us>, JSON or binary (a msgpack array): one ACL message, or a
        batch of them (a JSON array)."""
        payload = sample.payload.to_bytes()
        if payload[:1] == b"{":
            e = json.loads(payload)
            frm = e["from"]
            body = self.open("env", frm, e["to"], e["sid"], e["ts_ms"], e["n"], unb64(e["box"]))
        else:
            v, frm, to, sid, ts, n, box = msgpack.unpackb(payload)
            if v != 1:
                return
            body = self.open("acl", frm, to, sid, ts, n, box)
        messages = json.loads(body)
        for m in messages if isinstance(messages, list) else [messages]:
            waiter = self.waiting.get(m.get("in_reply_to", ""))
            if waiter is not None:
                waiter.append(m)
                waiter[0].set()
            elif m["performative"] in ("request", "query-ref"):
                self.answer(frm, m)

    def answer(self, peer: str, m: dict[str, Any]) -> None:
        """Answer get-latest with our fixed values; refuse anything else."""
        content = m.get("content") or {}
        labels = content.get("labels", []) if isinstance(content, dict) else []
        if content.get("action") == "get-latest" and all(x in self.values for x in labels):
            t = time.time()
            performative: str = "inform"
            result: Any = {
                x: {"query_time": t, "samples": [[self.values[x], t, t]]} for x in labels
            }
        else:
            performative, result = "refuse", f"not offered here: {content!r}"
        reply = {
            "v": 1,
            "performative": performative,
            "sender": f"federation@{self.name}",
            "receivers": m.get("reply_to") or [m["sender"]],
            "content": result,
        }
        for field in ("conversation_id", "ontology", "protocol", "language"):
            if m.get(field) is not None:
                reply[field] = m[field]
        if m.get("reply_with"):
            reply["in_reply_to"] = m["reply_with"]
        say(step="answered", to=peer, performative=performative, content=result)
        self.send(peer, reply)

    def ask(self, peer: str, performative: str, content: Any, timeout: float = 5.0) -> Any:
        """A FIPA request (or query-ref) to ``federation@peer``; its answer."""
        label = "r-" + os.urandom(6).hex()
        waiter: list[Any] = [threading.Event()]
        self.waiting[label] = waiter
        protocol = "fipa-query" if performative == "query-ref" else "fipa-request"
        self.send(
            peer,
            {
                "v": 1,
                "performative": performative,
                "sender": f"federation@{self.name}",
                "receivers": [f"federation@{peer}"],
                "content": content,
                "language": "json",
                "ontology": "dyknow-federation",
                "protocol": protocol,
                "conversation_id": "c-" + os.urandom(6).hex(),
                "reply_with": label,
                "reply_by": time.time() + timeout,
            },
        )
        if not waiter[0].wait(timeout):
            raise TimeoutError(f"{peer} did not answer {content}")
        return self.waiting.pop(label)[1]

    # -- streams (docs/wire.md, "Sample batches") ------------------------------------------

    def on_stream(self, sample: zenoh.Sample) -> None:
        """A binary envelope on stream/<us>/<sender>/<label>: one sample batch."""
        sender, label = str(sample.key_expr).split("/", 6)[5:]
        v, frm, to, sid, ts, n, box = msgpack.unpackb(sample.payload.to_bytes())
        if v != 1 or frm != sender:
            return
        batch = msgpack.unpackb(self.open("bin", frm, to, sid, ts, n, box))
        if batch["s"] == label:
            self.batches.append(batch)

    def report(self, peer: str, labels: list[str]) -> None:
        """The stream report that keeps ``peer``'s exports to us alive (their lease)."""
        s = self.sending[peer]
        ts, n, box = self.seal("bin", s, msgpack.packb({"v": 1, "lost": dict.fromkeys(labels, 0)}))
        payload = msgpack.packb([1, self.name, peer, s.sid, ts, n, box])
        self.z.put(f"{self.prefix}stream-report/{peer}/{self.name}", payload)

    # -- joining and leaving ---------------------------------------------------------------

    def join(self) -> None:
        """Serve kx and df, follow acl and streams, then show our presence."""
        z, p = self.z, self.prefix
        self.held = [
            z.declare_queryable(f"{p}kx/{self.name}", self.on_kx),
            z.declare_queryable(f"{p}df/{self.name}", self.on_df),
            z.declare_subscriber(f"{p}acl/{self.name}", self.on_acl),
            z.declare_subscriber(f"{p}stream/{self.name}/*/**", self.on_stream),
        ]
        self.token = z.liveliness().declare_token(f"{p}alive/{self.name}")

    def leave(self) -> None:
        """The signed leave, then the presence goes."""
        self.seq += 1
        self.z.put(
            f"{self.prefix}df-events/{self.name}", self.statement("df-event", {"op": "leave"})
        )
        time.sleep(0.2)
        self.token.undeclare()
        self.z.close()


def main() -> None:
    """Join, ask the peer, stream from it, answer for a while, leave."""
    args = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    args.add_argument("--key", required=True)
    args.add_argument("--trust", required=True)
    args.add_argument("--connect", action="append", required=True)
    args.add_argument("--peer", required=True)
    args.add_argument("--stream", required=True)
    args.add_argument("--count", type=int, default=3)
    args.add_argument("--serve", type=float, default=0.0)
    args.add_argument("--value", action="append", default=[])
    a = args.parse_args()
    me = Member(a.key, a.trust, a.connect)
    me.values = {k: float(v) for k, v in (x.split("=", 1) for x in a.value)}
    me.join()
    for _ in range(50):  # the peer's signed answer: it is there and a member
        services = me.services_of(a.peer)
        if any(s["type"] == "dyknow-federation" for s in services):
            break
        time.sleep(0.2)
    say(step="joined", platform=me.name, federation=me.fed, peer_services=services)
    labels = me.ask(a.peer, "query-ref", {"action": "list-labels"})
    say(step="labels", performative=labels["performative"], content=labels["content"])
    created = me.ask(
        a.peer, "request", {"action": "create-stream", "labels": [a.stream], "sample-period": 0.2}
    )
    say(step="create-stream", performative=created["performative"], content=created["content"])
    deadline = time.time() + 20
    while sum(1 for b in me.batches if b["b"]) < a.count and time.time() < deadline:
        me.report(a.peer, [a.stream])
        time.sleep(0.5)
    samples = [s for b in me.batches for s in b["b"]][: a.count]
    say(step="stream", label=a.stream, samples=samples)
    cancelled = me.ask(
        a.peer, "request", {"action": "cancel-stream", "id": created["content"]["id"]}
    )
    say(step="cancel-stream", performative=cancelled["performative"])
    say(step="serving", seconds=a.serve)
    try:
        time.sleep(a.serve)
    except KeyboardInterrupt:
        pass  # Ctrl-C (SIGINT) ends the serving: leave as ever
    me.leave()
    say(step="left")


if __name__ == "__main__":
    main()
