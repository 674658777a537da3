"""Directory statements: what a platform says about itself in the global directory, signed.

A DF answer (``dyknow/<fed>/v1/df/<platform>``) and a directory event
(``…/df-events/<platform>``) travel as one JSON *statement* (``docs/wire.md``)::

    {"v":1,"fed":F,"from":P,"kind":"df"|"df-event","boot":B,"seq":N,"ts_ms":T,
     "nonce":"<base64>","body":"<JSON text>","sig":"<base64 Ed25519>"}

``sig`` is the platform's Ed25519 signature over a domain label and every other field
(length-prefixed), so a statement cannot be forged, moved to another platform, kind or
federation, and a DF answer (whose ``nonce`` is the asker's fresh one) cannot be
replayed. Events are ordered by ``(boot, seq)``: ``boot`` is when the platform's
process started (ms), ``seq`` counts its events; a receiver keeps the newest pair it
accepted per platform and drops anything not newer, so a recorded event replayed later
changes nothing. A platform without keys (`PlainChannel`) sends the same statement
without ``sig``; a platform with a trust file accepts only signed ones from trusted
platforms (`DirectoryAuth.open`).
"""

from __future__ import annotations

import base64
import binascii
import os
import struct
import time
from collections.abc import Callable
from typing import Any

import orjson
from nacl.exceptions import CryptoError

from ._security import Clock, KeyPair, TrustStore, _untrusted

__all__ = ["DirectoryAuth", "DirectoryStatementError", "Statement", "make_nonce"]

WIRE_VERSION = 1
NONCE_BYTES = 16
MAX_STATEMENT_BYTES = 1 << 20
_SIG = b"dyknow-dir-v1 sig\x00"
_U64X3 = struct.Struct(">QQQ")
_KINDS = frozenset({"df", "df-event"})
_FIELDS = frozenset({"v", "fed", "from", "kind", "boot", "seq", "ts_ms", "nonce", "body"})


class DirectoryStatementError(ValueError):
    """A directory statement that is malformed, unsigned, untrusted, forged or stale."""

    def __init__(self, reason: str, platform: str | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.platform = platform


class Statement:
    """One opened statement: who said it, its order, its body (parsed JSON), when (Unix ms)."""

    __slots__ = ("body", "boot", "platform", "seq", "ts_ms")

    def __init__(self, platform: str, boot: int, seq: int, body: Any, ts_ms: int = 0) -> None:
        self.platform = platform
        self.boot = boot
        self.seq = seq
        self.body = body
        self.ts_ms = ts_ms  # as stamped by its platform (checked within the skew if signed)


def make_nonce() -> bytes:
    """A fresh nonce for a DF query (the answer must sign it)."""
    return os.urandom(NONCE_BYTES)


def _lp(raw: bytes) -> bytes:
    return len(raw).to_bytes(4, "big") + raw


def _signed_bytes(
    fed: str, frm: str, kind: str, boot: int, seq: int, ts_ms: int, nonce: bytes, body: bytes
) -> bytes:
    return (
        _SIG
        + _lp(fed.encode())
        + _lp(frm.encode())
        + _lp(kind.encode())
        + _U64X3.pack(boot, seq, ts_ms)
        + _lp(nonce)
        + body
    )


def _b64(raw: bytes) -> str:
    return base64.b64encode(raw).decode("ascii")


def _unb64(value: object, what: str) -> bytes:
    if not isinstance(value, str):
        raise DirectoryStatementError(f"field {what!r} is not a base64 string")
    try:
        return base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise DirectoryStatementError(f"field {what!r} is not base64") from None


class DirectoryAuth:
    """Makes this platform's directory statements and opens other platforms' ones.

    ``keys`` None: statements go out unsigned (a platform without an identity).
    ``trust`` None: statements are read without checking a signature (no trust file:
    the platform cannot tell members from outsiders, ``docs/security.md``). With a trust
    file, only statements signed by a trusted platform, of this federation, stamped
    within ``skew`` seconds are accepted.
    """

    def __init__(
        self,
        federation: str,
        keys: KeyPair | None = None,
        trust: TrustStore | None = None,
        *,
        skew: float = 30.0,
        clock: Clock = time.time,
    ) -> None:
        self.federation = federation
        self.keys = keys
        self.trust = trust
        self.skew = skew
        self._clock = clock
        self.boot = int(clock() * 1000)
        self.seq = 0
        self._newest: dict[str, tuple[int, int]] = {}

    @property
    def authenticates(self) -> bool:
        """Whether statements are checked against a trust file."""
        return self.trust is not None

    def trusted(self, platform: str) -> bool:
        """Whether ``platform`` may appear in the directory at all."""
        if self.trust is None:
            return True
        if platform in self.trust:
            return True
        return self.keys is not None and platform == self.keys.platform

    def seal(self, platform: str, kind: str, body: Any, *, nonce: bytes = b"") -> bytes:
        """A statement of ``kind`` with ``body``; a ``df-event`` takes the next sequence number."""
        if kind == "df-event":
            self.seq += 1
        text = orjson.dumps(body)
        ts_ms = int(self._clock() * 1000)
        obj: dict[str, Any] = {
            "v": WIRE_VERSION,
            "fed": self.federation,
            "from": platform,
            "kind": kind,
            "boot": self.boot,
            "seq": self.seq,
            "ts_ms": ts_ms,
            "nonce": _b64(nonce),
            "body": text.decode(),
        }
        if self.keys is not None:
            signed = _signed_bytes(
                self.federation, platform, kind, self.boot, self.seq, ts_ms, nonce, text
            )
            obj["sig"] = _b64(self.keys.sign(signed))
        return orjson.dumps(obj)

    def open(
        self, payload: bytes, kind: str, *, platform: str | None = None, nonce: bytes | None = None
    ) -> Statement:
        """Check a statement of ``kind`` (from ``platform`` when the key names it).

        ``nonce``: the one our query carried (DF answers). Raises DirectoryStatementError
        saying what is wrong; a ``df-event`` not newer than the last accepted one of its
        platform is refused as stale (``reason`` starts with ``stale``).
        """
        if len(payload) > MAX_STATEMENT_BYTES:
            raise DirectoryStatementError(f"statement of {len(payload)} bytes is too large")
        try:
            obj = orjson.loads(payload)
        except orjson.JSONDecodeError:
            raise DirectoryStatementError("not a JSON statement", platform) from None
        if not isinstance(obj, dict):
            raise DirectoryStatementError("a statement is a JSON object", platform)
        frm = obj.get("from")
        claimed = frm if isinstance(frm, str) else platform
        missing = _FIELDS - obj.keys()
        if missing:
            raise DirectoryStatementError(f"field {sorted(missing)[0]!r} is missing", claimed)
        if obj["v"] != WIRE_VERSION:
            raise DirectoryStatementError(f"version {obj['v']!r} (this side reads 1)", claimed)
        if not isinstance(frm, str) or (platform is not None and frm != platform):
            raise DirectoryStatementError(
                f"statement from {frm!r} published under {platform!r}", claimed
            )
        if obj["fed"] != self.federation:
            raise DirectoryStatementError(f"federation {obj['fed']!r}", frm)
        if obj["kind"] != kind or kind not in _KINDS:
            raise DirectoryStatementError(f"a {obj['kind']!r} statement where {kind!r} is", frm)
        boot, seq, ts_ms, body = obj["boot"], obj["seq"], obj["ts_ms"], obj["body"]
        for name, value in (("boot", boot), ("seq", seq), ("ts_ms", ts_ms)):
            if type(value) is not int or not 0 <= value < 1 << 63:
                raise DirectoryStatementError(f"field {name!r} is not a non-negative integer", frm)
        if not isinstance(body, str):
            raise DirectoryStatementError("field 'body' is not a JSON text", frm)
        got_nonce = _unb64(obj["nonce"], "nonce")
        if self.trust is not None:
            self._verify(obj, frm, kind, boot, seq, ts_ms, got_nonce, body.encode())
            if nonce is not None and got_nonce != nonce:
                raise DirectoryStatementError("answer to another query (nonce differs)", frm)
        if kind == "df-event":
            newest = self._newest.get(frm)
            if newest is not None and (boot, seq) <= newest:
                raise DirectoryStatementError(
                    f"stale: event ({boot}, {seq}) is not newer than {newest}", frm
                )
            self._newest[frm] = (boot, seq)
        elif (newest := self._newest.get(frm)) is None or (boot, seq) > newest:
            # the events the answer already reflects are stale from now on
            self._newest[frm] = (boot, seq)
        try:
            parsed = orjson.loads(body)
        except orjson.JSONDecodeError:
            raise DirectoryStatementError("field 'body' is not JSON", frm) from None
        return Statement(frm, boot, seq, parsed, ts_ms)

    def _verify(
        self,
        obj: dict[str, Any],
        frm: str,
        kind: str,
        boot: int,
        seq: int,
        ts_ms: int,
        nonce: bytes,
        body: bytes,
    ) -> None:
        assert self.trust is not None
        if frm in self.trust:
            verify = self.trust.verify_key(frm)
        elif self.keys is not None and frm == self.keys.platform:
            verify = None
        else:
            raise DirectoryStatementError(_untrusted(frm).args[0], frm)
        if "sig" not in obj:
            raise DirectoryStatementError("unsigned statement", frm)
        sig = _unb64(obj["sig"], "sig")
        signed = _signed_bytes(self.federation, frm, kind, boot, seq, ts_ms, nonce, body)
        try:
            if verify is None:
                assert self.keys is not None
                if self.keys.sign(signed) != sig:  # Ed25519 is deterministic
                    raise CryptoError("bad signature")
            else:
                verify.verify(signed, sig)
        except (CryptoError, ValueError):
            raise DirectoryStatementError(
                f"signature does not verify with {frm!r}'s trusted key", frm
            ) from None
        delta = self._clock() - ts_ms / 1000
        if abs(delta) > self.skew:
            raise DirectoryStatementError(
                f"timestamp is {delta:+.1f} s from this clock (allowed ±{self.skew:g} s)", frm
            )

    def newest(self, platform: str) -> tuple[int, int] | None:
        """The ``(boot, seq)`` of ``platform``'s newest statement accepted (any thread)."""
        return self._newest.get(platform)

    def forget(self, platform: str) -> None:
        """Nothing to remember of ``platform`` any more (its process ended)."""
        self._newest.pop(platform, None)


Refusal = Callable[[str | None, str, str], None]
"""Told of each refused statement or presence: (claimed platform, reason, stage)."""
