"""Platform identity, the trust file, the authenticated key exchange and sealed envelopes.

Pure and transport-free: every operation takes and returns bytes, time comes from an
injectable clock, so the Interface Agent can run it over zenoh, MQTT or memory alike.
The scheme and its reasons are in ``docs/security.md``; the bytes on the wire in
``docs/wire.md``.

Nothing here is thread-safe: one platform's ``Handshake`` and ``SessionTable`` belong to
its Interface Agent's event loop.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import functools
import hashlib
import heapq
import hmac
import logging
import os
import re
import stat
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack
import orjson
from nacl import bindings as _sodium
from nacl.exceptions import CryptoError
from nacl.signing import SigningKey, VerifyKey

from ._acl import MAX_MESSAGE_BYTES
from ._exceptions import (
    Expired,
    Forged,
    KeyFileError,
    Malformed,
    MessageError,
    Misdirected,
    Replayed,
    Unencrypted,
    UnknownPlatform,
    UnknownSession,
)
from ._records import Frozen, Record

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

__all__ = [
    "Clock",
    "Handshake",
    "KeyPair",
    "OwnerBatches",
    "SecurityPolicy",
    "Session",
    "SessionTable",
    "TrustStore",
    "WatchGate",
    "check_name",
    "fingerprint",
    "key_paths",
    "open_for_owner",
    "read_public_key",
    "seal_for_owner",
    "seal_owner_batch",
    "sign_owner_batch",
    "watch_request",
]

log = logging.getLogger(__name__)

WIRE_VERSION = 1
MAX_HANDSHAKE_BYTES = 4096

Clock = Callable[[], float]
"""Unix time in seconds (``time.time``); tests inject their own."""

_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")
_PRIVATE_KIND = "dyknow-ed25519-private"
_PUBLIC_KIND = "dyknow-ed25519-public"
_U64 = struct.Struct(">Q")
_U64X2 = struct.Struct(">QQ")
# a binary ACL envelope after its header, as our sender packs it: uint 64 `ts_ms`, uint 64
# `n`, then the head of a bin 32 (the body or box follows)
_ACL_TAIL = struct.Struct(">BQBQBI")
_U64_HEAD, _BIN32_HEAD = 0xCF, 0xC6
_NONCE = struct.Struct(">IQ")  # an AEAD nonce: 4 bytes of space (`_aead_nonce`), the counter
_MAX_COUNTER = (1 << 63) - 1
_NONCE_BYTES = 16

# Domain-separation labels: a signature or MAC made for one purpose never verifies for another.
_KX_INIT = b"dyknow-kx-v1 init\x00"
_KX_REPLY = b"dyknow-kx-v1 reply\x00"
_ENV_MAC = b"dyknow-env-v1 mac\x00"
_ENV_BOX = b"dyknow-env-v1 box\x00"
# Binary envelopes (sample batches) have labels of their own: a binary envelope never
# verifies as a JSON one, so the two may keep separate counters and replay windows.
_BIN_MAC = b"dyknow-bin-v1 mac\x00"
_BIN_BOX = b"dyknow-bin-v1 box\x00"
# Binary ACL envelopes (msgpack, on acl/<platform>) count with the JSON ones but have
# labels of their own: one never verifies as a JSON ACL envelope nor as a sample batch's.
_ACL_MAC = b"dyknow-acl-v1 mac\x00"
_ACL_BOX = b"dyknow-acl-v1 box\x00"
# what a binary ACL envelope starts with: a msgpack array (fixarray, array 16, array 32);
# a JSON one starts with `{` (or white space), a str is JSON
_BINARY_HEADS = frozenset(bytes((b,)) for b in (*range(0x90, 0xA0), 0xDC, 0xDD))
# What a platform publishes to its owner (audit, watch) is signed under a label of its own.
_OWNER_SIG = b"dyknow-owner-v1 sig\x00"

_PLAIN_FIELDS = frozenset(("v", "from", "to", "sid", "ts_ms", "n", "body", "mac"))
_BOX_FIELDS = frozenset(("v", "from", "to", "sid", "ts_ms", "n", "box"))
_INIT_FIELDS = frozenset(("v", "kx", "fed", "from", "to", "ts_ms", "nonce", "epk", "sig"))
_REPLY_FIELDS = _INIT_FIELDS | {"re"}

_loads = orjson.loads
_dumps = orjson.dumps
_JSONDecodeError = orjson.JSONDecodeError
_b2a = binascii.b2a_base64
_a2b = binascii.a2b_base64


def _canonical_tail(raw: bytes, text: str) -> bool:
    """Whether ``text``, which strict base64 decoding made ``raw``, is its canonical spelling.

    Strict decoding accepts the alphabet only, padded, and nothing but padding after it;
    what it lets through besides the canonical form are padding to excess (the length
    tells) and unused bits set in the last quantum: re-encoding the bytes of that
    quantum, not the whole box, tells.
    """
    n = len(raw)
    if len(text) != (n + 2) // 3 * 4:
        return False
    rest = n % 3
    # the last letter before the padding carries unused bits, which must be zero: 4 of
    # them after one byte (letters 0, 16, 32, 48), 2 after two (multiples of 4)
    if rest == 1:
        return text[-3] in "AQgw" and text[-2:] == "=="
    return not rest or (text[-2] in "AEIMQUYcgkosw048" and text[-1] == "=")


def _box_text_std(raw: bytes) -> bytes:
    """``raw`` in standard base64, padded, without a newline (binascii)."""
    return _b2a(raw, newline=False)


def _box_bytes_std(text: str) -> bytes:
    """The bytes ``text`` spells in canonical standard base64; b"" when it is not such text."""
    try:
        raw = _a2b(text, strict_mode=True)
    except ValueError:  # binascii.Error is a ValueError
        return b""
    return raw if _canonical_tail(raw, text) else b""


# what `Session` encodes and decodes its boxes with: binascii, or SIMD base64 where installed
_box_text: Callable[[bytes], bytes] = _box_text_std
_box_bytes: Callable[[str], bytes] = _box_bytes_std

try:
    # an envelope's box decoded ~25x, encoded ~30x faster than binascii does it: ~0.6 µs
    # less per message of a batch at the receiver, ~0.25 µs at the sender
    from pybase64 import b64decode as _fast_decode
    from pybase64 import b64encode as _fast_encode
except ImportError:  # pragma: no cover - depends on what is installed
    pass
else:

    def _box_bytes_fast(text: str) -> bytes:
        """`_box_bytes_std` with pybase64: what it accepts, the text its bytes encode to."""
        try:
            raw: bytes = _fast_decode(text, validate=True)
        except ValueError:  # binascii.Error is a ValueError; so is a str not ASCII
            return b""
        # canonical only: the whole text compared with its bytes encoded again (padding
        # to excess and unused bits set are what a strict decoder lets through)
        return raw if _fast_encode(raw) == text.encode() else b""

    _box_text = _fast_encode
    _box_bytes = _box_bytes_fast


_compare = hmac.compare_digest
_packb = msgpack.packb  # a fresh packer per call: a shared one would not be thread-safe
_packers = threading.local()  # a packer per thread, for the binary envelopes (`_pack_own`)


def _pack_own(items: list[Any]) -> bytes:
    """``_packb(items)`` with this thread's packer: made once, not per envelope.

    For lists of ints, strs and bytes only (no ``default`` runs Python code mid-pack, so
    nothing else on this thread can use the packer before it is done).
    """
    try:
        packer = _packers.envelope
    except AttributeError:
        packer = _packers.envelope = msgpack.Packer()
    out: bytes = packer.pack(items)
    return out


_unpackb = msgpack.unpackb
_MAC_BYTES = 32
_TAG_BYTES = 16  # the ChaCha20-Poly1305 tag a box adds to its body


# ChaCha20-Poly1305-IETF through `cryptography` (OpenSSL): the same bytes as libsodium's,
# and about half the cost per call of nacl.bindings' wrapper, which checks and formats its
# arguments on every call (measured: 2.6 µs against 4.4 µs to seal 270 bytes). A key's
# cipher object is made once: sessions seal thousands of envelopes under one key.
# `cryptography` is imported with the first cipher, when the first session is made: its
# OpenSSL build is ~6 MB of a process's memory, which a node with no peer never needs.
_CIPHERS: dict[bytes, ChaCha20Poly1305] = {}
_MAX_CIPHERS = 4096  # sessions are per peer: a bound well above any federation's size


class _NoCipherYet(Exception):
    """Stands for cryptography's InvalidTag until the first cipher imports it."""


# what a cipher raises on a forged box; only a cipher can raise it, so the real class,
# bound by `_cipher` before any cipher exists, is there by the time one is caught
InvalidTag: type[Exception] = _NoCipherYet


def _cipher(key: bytes) -> ChaCha20Poly1305:
    cipher = _CIPHERS.get(key)
    if cipher is None:
        global InvalidTag
        import cryptography.exceptions
        from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

        InvalidTag = cryptography.exceptions.InvalidTag
        if len(_CIPHERS) >= _MAX_CIPHERS:
            _CIPHERS.clear()  # keys of ended sessions go; live ones come back on next use
        cipher = _CIPHERS[key] = ChaCha20Poly1305(key)
    return cipher


def _aead_encrypt(message: bytes, aad: bytes, nonce: bytes, key: bytes) -> bytes:
    """Encrypt ``message`` under ``key`` and ``nonce``, authenticating ``aad`` as well."""
    return _cipher(key).encrypt(nonce, message, aad)


def _aead_decrypt(ciphertext: bytes, aad: bytes, nonce: bytes, key: bytes) -> bytes:
    """Decrypt and verify; a forged or damaged box raises CryptoError, as libsodium's does."""
    try:
        return _cipher(key).decrypt(nonce, ciphertext, aad)
    except InvalidTag:
        raise CryptoError("Decryption failed. Ciphertext failed verification") from None


def check_name(value: str, what: str = "platform") -> str:
    """Check a platform or federation name (letters, digits, ``-``, ``_``, ``.``) and return it."""
    if not isinstance(value, str) or not _NAME.fullmatch(value) or value in {".", ".."}:
        raise ValueError(f"{what} name {value!r} must be 1-128 letters, digits, '-', '_' or '.'")
    return value


def fingerprint(public_key: bytes) -> str:
    """A short human-comparable fingerprint of an Ed25519 public key (SHA-256, 8 bytes)."""
    return hashlib.sha256(public_key).hexdigest()[:16]


def _b64(data: bytes) -> str:
    return _b2a(data, newline=False).decode("ascii")


def _unb64(value: Any, size: int | None = None) -> bytes:
    """Strict base64: raises ValueError on anything but canonical standard base64."""
    if not isinstance(value, str):
        raise ValueError("not a base64 string")
    try:
        raw = base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise ValueError(f"not base64 ({exc})") from None
    if size is not None and len(raw) != size:
        raise ValueError(f"{len(raw)} bytes where {size} are expected")
    if _b64(raw) != value:
        raise ValueError("not canonical base64")
    return raw


def _lp(text: str) -> bytes:
    """Length-prefixed UTF-8, so concatenated fields can never be re-split differently."""
    raw = text.encode()
    return len(raw).to_bytes(2, "big") + raw


def _env_head(label: bytes, fed: str, frm: str, to: str, sid: str) -> bytes:
    """The session-constant start of an envelope's MAC input or associated data."""
    return label + _lp(fed) + _lp(frm) + _lp(to) + _lp(sid)


# --------------------------------------------------------------------------- files


def key_paths(directory: str | os.PathLike[str], platform: str) -> tuple[Path, Path]:
    """The private and public key file of ``platform`` in ``directory`` (``.key``, ``.pub``)."""
    check_name(platform)
    base = Path(directory)
    return base / f"{platform}.key", base / f"{platform}.pub"


def _mode(path: Path, what: str) -> int:
    """``path``'s mode bits; KeyFileError when there is no such ``what``."""
    try:
        return path.stat().st_mode
    except FileNotFoundError:
        raise KeyFileError(path, f"no such {what}") from None


def _file_json(obj: dict[str, Any]) -> bytes:
    """A key or trust file's content: indented JSON ending in a newline."""
    return _dumps(obj, option=orjson.OPT_INDENT_2 | orjson.OPT_APPEND_NEWLINE)


_CLAIMED_WHOLE, _CLAIMED_START = 256, 64


def _untrusted(platform: str) -> UnknownPlatform:
    """The error for a platform the trust file does not name."""
    # a claimed name, anyone's: named by its start if longer than any name (audited)
    shown = platform if len(platform) <= _CLAIMED_WHOLE else platform[:_CLAIMED_START] + "…"
    return UnknownPlatform(f"platform {shown!r} is not in the trust file", platform)


MAX_KEY_FILE_BYTES = 4 << 20
"""The largest key or trust file read (a trust file of ten thousand platforms is ~1 MB)."""


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        # non-blocking, and the type checked on the file opened (not on its name, which
        # may be swapped in between): a FIFO put there would block the read for good
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise KeyFileError(path, f"no such {what}") from None
    except OSError as exc:
        raise KeyFileError(path, f"cannot read the {what}: {exc.strerror or exc}") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise KeyFileError(path, f"the {what} is not a regular file")
        try:
            raw = f.read(MAX_KEY_FILE_BYTES + 1)
        except OSError as exc:
            raise KeyFileError(path, f"cannot read the {what}: {exc.strerror or exc}") from None
    if len(raw) > MAX_KEY_FILE_BYTES:
        raise KeyFileError(path, f"the {what} is larger than {MAX_KEY_FILE_BYTES} bytes")
    try:
        obj = _loads(raw)
    except _JSONDecodeError as exc:
        raise KeyFileError(path, f"the {what} is not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise KeyFileError(path, f"the {what} must be a JSON object")
    if obj.get("v") != WIRE_VERSION:
        raise KeyFileError(path, f"key 'v': version {obj.get('v')!r} (this side reads 1)")
    return obj


def _field_name(path: Path, obj: Mapping[str, Any], key: str, what: str) -> str:
    value = obj.get(key)
    if not isinstance(value, str):
        raise KeyFileError(path, f"key {key!r}: missing, or not a string")
    try:
        return check_name(value, what)
    except ValueError as exc:
        raise KeyFileError(path, f"key {key!r}: {exc}") from None


def _write_atomic(path: Path, data: bytes, mode: int, *, overwrite: bool) -> None:
    """Write via a same-directory temporary file so a crash never leaves half a key behind."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        try:
            os.fchmod(fd, mode)  # the umask may only remove bits; make the mode exact
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)  # fails if path exists: no check-then-write race
            os.unlink(tmp)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


_KEY_THERE = "a private key is already there; not overwriting it (use --force)"


class KeyPair:
    """A platform's Ed25519 identity: its name and private signing key."""

    __slots__ = ("_signing_key", "platform")

    def __init__(self, platform: str, signing_key: SigningKey) -> None:
        self.platform = check_name(platform)
        self._signing_key = signing_key

    def __repr__(self) -> str:
        return f"KeyPair({self.platform!r}, fingerprint={self.fingerprint!r})"

    @classmethod
    def generate(cls, platform: str) -> KeyPair:
        """A fresh random key pair for ``platform``."""
        return cls(platform, SigningKey.generate())

    @property
    def public_key(self) -> bytes:
        """The raw 32-byte Ed25519 public key."""
        return bytes(self._signing_key.verify_key)

    @property
    def fingerprint(self) -> str:
        """The public key's fingerprint, for people to compare."""
        return fingerprint(self.public_key)

    def sign(self, data: bytes) -> bytes:
        """The 64-byte Ed25519 signature of ``data``."""
        return self._signing_key.sign(data).signature

    def open_sealed(self, data: bytes) -> bytes:
        """Open a sealed box addressed to this platform's owner (`seal_for_owner`).

        Raises Forged when ``data`` was not sealed to this key or was changed.
        """
        secret = bytes(self._signing_key.to_curve25519_private_key())
        public = _sodium.crypto_sign_ed25519_pk_to_curve25519(self.public_key)
        try:
            opened: bytes = _sodium.crypto_box_seal_open(data, public, secret)
        except (CryptoError, ValueError, TypeError):
            raise Forged(f"not sealed to {self.platform!r}'s key, or changed", None) from None
        return opened

    def public_json(self) -> bytes:
        """The public key file's content."""
        return _file_json(
            {
                "v": WIRE_VERSION,
                "kind": _PUBLIC_KIND,
                "platform": self.platform,
                "ed25519": _b64(self.public_key),
            }
        )

    def save(self, directory: str | os.PathLike[str], *, force: bool = False) -> tuple[Path, Path]:
        """Write ``<platform>.key`` (mode 0600) and ``<platform>.pub`` into ``directory``.

        An existing private key is never replaced unless ``force``: a replaced key locks the
        platform out of every federation that trusts the old one.
        """
        key_path, pub_path = key_paths(directory, self.platform)
        key_path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        if key_path.exists() and not force:
            raise KeyFileError(key_path, _KEY_THERE)
        private = _file_json(
            {
                "v": WIRE_VERSION,
                "kind": _PRIVATE_KIND,
                "platform": self.platform,
                "ed25519_seed": _b64(bytes(self._signing_key)),
            }
        )
        try:
            _write_atomic(key_path, private, 0o600, overwrite=force)
        except FileExistsError:
            raise KeyFileError(key_path, _KEY_THERE) from None
        _write_atomic(pub_path, self.public_json(), 0o644, overwrite=True)
        return key_path, pub_path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> KeyPair:
        """Read a private key file; refuse one that group or others can read."""
        path = Path(path)
        mode = _mode(path, "private key file")
        if os.name == "posix" and mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise KeyFileError(
                path,
                f"the private key is accessible to group or others (mode {mode & 0o777:04o}); "
                f"run: chmod 600 {path}",
            )
        obj = _read_json(path, "private key file")
        if obj.get("kind") != _PRIVATE_KIND:
            raise KeyFileError(path, f"key 'kind': expected {_PRIVATE_KIND!r}")
        platform = _field_name(path, obj, "platform", "platform")
        try:
            seed = _unb64(obj.get("ed25519_seed"), 32)
        except ValueError as exc:
            raise KeyFileError(path, f"key 'ed25519_seed': {exc}") from None
        return cls(platform, SigningKey(seed))


def read_public_key(path: str | os.PathLike[str]) -> tuple[str, bytes]:
    """Read a public key file: ``(platform, raw 32-byte Ed25519 public key)``."""
    path = Path(path)
    obj = _read_json(path, "public key file")
    if obj.get("kind") != _PUBLIC_KIND:
        raise KeyFileError(path, f"key 'kind': expected {_PUBLIC_KIND!r}")
    platform = _field_name(path, obj, "platform", "platform")
    try:
        public = _unb64(obj.get("ed25519"), 32)
        VerifyKey(public)
    except (ValueError, CryptoError) as exc:
        raise KeyFileError(path, f"key 'ed25519': {exc}") from None
    return platform, public


class TrustStore:
    """The federation's trust file: its name and the platforms (Ed25519 keys) it accepts."""

    __slots__ = ("_keys", "_on_remove", "_raw", "federation")

    def __init__(self, federation: str, platforms: Mapping[str, bytes] | None = None) -> None:
        self.federation = check_name(federation, "federation")
        self._raw: dict[str, bytes] = {}
        self._keys: dict[str, VerifyKey] = {}
        self._on_remove: list[Callable[[str], object]] = []
        for platform, public in (platforms or {}).items():
            self.add(platform, public)

    def __repr__(self) -> str:
        return f"TrustStore({self.federation!r}, platforms={sorted(self._raw)})"

    def __contains__(self, platform: object) -> bool:
        return platform in self._keys

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self._raw))

    def __len__(self) -> int:
        return len(self._raw)

    def public_key(self, platform: str) -> bytes:
        """The raw public key trusted for ``platform``; UnknownPlatform when there is none."""
        try:
            return self._raw[platform]
        except KeyError:
            raise _untrusted(platform) from None

    def verify_key(self, platform: str) -> VerifyKey:
        """The verifier for ``platform``'s signatures; UnknownPlatform when it is not trusted."""
        try:
            return self._keys[platform]
        except KeyError:
            raise _untrusted(platform) from None

    def add(self, platform: str, public_key: bytes, *, replace: bool = False) -> bool:
        """Trust ``public_key`` for ``platform``; True when something changed.

        A different key for an already trusted platform is refused unless ``replace``
        (key rotation), so a typo cannot silently swap a platform's identity.
        """
        check_name(platform)
        public_key = bytes(public_key)
        if len(public_key) != 32:
            raise ValueError(f"platform {platform!r}: an Ed25519 public key is 32 bytes")
        old = self._raw.get(platform)
        if old == public_key:
            return False
        if old is not None and not replace:
            raise ValueError(
                f"platform {platform!r} is already trusted with another key "
                f"(fingerprint {fingerprint(old)}); replace it explicitly to rotate"
            )
        self._keys[platform] = VerifyKey(public_key)
        self._raw[platform] = public_key
        return True

    def remove(self, platform: str) -> bool:
        """Stop trusting ``platform`` (its envelopes refused from now on, live sessions
        included), then tell each `on_remove` callback; True when it was trusted."""
        self._keys.pop(platform, None)
        if self._raw.pop(platform, None) is None:
            return False
        for callback in list(self._on_remove):
            try:
                callback(platform)
            except Exception:  # revoked all the same: the trust is gone already
                log.exception("trust store: a callback on removing %r failed", platform)
        return True

    def on_remove(self, callback: Callable[[str], object]) -> Callable[[], None]:
        """Call ``callback(platform)`` each time `remove` stops trusting a platform (what a
        running platform keeps for it ends there); returns the call that unhooks it."""
        self._on_remove.append(callback)

        def unhook() -> None:
            with contextlib.suppress(ValueError):
                self._on_remove.remove(callback)

        return unhook

    def to_json(self) -> bytes:
        """The trust file's content."""
        return _file_json(
            {
                "v": WIRE_VERSION,
                "federation": self.federation,
                "platforms": {p: _b64(k) for p, k in sorted(self._raw.items())},
            }
        )

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the trust file atomically (mode 0644: public keys are not secret)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_atomic(path, self.to_json(), 0o644, overwrite=True)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> TrustStore:
        """Read a trust file; KeyFileError names the file and the key that is wrong."""
        path = Path(path)
        mode = _mode(path, "trust file")
        if os.name == "posix" and mode & stat.S_IWOTH:
            # whoever can write the trust file decides whom this platform believes
            raise KeyFileError(
                path, f"the trust file is writable by others (mode {mode & 0o777:04o})"
            )
        obj = _read_json(path, "trust file")
        unknown = set(obj) - {"v", "federation", "platforms"}
        if unknown:
            raise KeyFileError(path, f"unexpected key {sorted(unknown)[0]!r}")
        federation = _field_name(path, obj, "federation", "federation")
        platforms = obj.get("platforms")
        if not isinstance(platforms, dict):
            raise KeyFileError(path, "key 'platforms': must be an object of platform: key")
        store = cls(federation)
        for platform, value in platforms.items():
            where = f"key 'platforms.{platform}'"
            try:
                check_name(platform)
            except ValueError as exc:
                raise KeyFileError(path, f"{where}: {exc}") from None
            try:
                public = _unb64(value, 32)
                store.add(platform, public)
            except (ValueError, CryptoError) as exc:
                raise KeyFileError(
                    path, f"{where}: not a base64 Ed25519 public key ({exc})"
                ) from None
        return store


# --------------------------------------------------------------------------- policy


@dataclass(init=False, repr=False, eq=False)
class SecurityPolicy(Frozen):
    """The tunables of a platform's handshakes and sessions (a federation should agree on them).

    ``skew``: how far (s) a timestamp may be from this platform's clock, either way.
    ``window``: how many counters back a reordered envelope is still accepted.
    ``renew_after_messages`` / ``renew_after_seconds``: when a session asks to be renewed;
    it is then accepted ``grace`` seconds beyond that, and an old session ``grace`` seconds
    after its peer started using a newer one. ``encrypt`` (default on): seal with
    ChaCha20-Poly1305, so bodies are confidential; off, only a MAC (bodies readable by
    anyone on the path: for debugging). ``require_encryption``: refuse envelopes that are
    not encrypted (`Unencrypted`); None (the default) means the same as ``encrypt``.
    """

    __slots__ = (
        "encrypt",
        "grace",
        "max_body_bytes",
        "max_sessions_per_peer",
        "renew_after_messages",
        "renew_after_seconds",
        "require_encryption",
        "skew",
        "window",
    )
    skew: float
    window: int
    renew_after_messages: int
    renew_after_seconds: float
    grace: float
    encrypt: bool
    require_encryption: bool | None
    max_sessions_per_peer: int
    max_body_bytes: int

    def __init__(
        self,
        skew: float = 30.0,
        window: int = 1024,
        renew_after_messages: int = 1_000_000,
        renew_after_seconds: float = 3600.0,
        grace: float = 30.0,
        encrypt: bool = True,
        require_encryption: bool | None = None,
        max_sessions_per_peer: int = 4,
        max_body_bytes: int = MAX_MESSAGE_BYTES,
    ) -> None:
        object.__setattr__(self, "skew", skew)
        object.__setattr__(self, "window", window)
        object.__setattr__(self, "renew_after_messages", renew_after_messages)
        object.__setattr__(self, "renew_after_seconds", renew_after_seconds)
        object.__setattr__(self, "grace", grace)
        object.__setattr__(self, "encrypt", encrypt)
        object.__setattr__(self, "require_encryption", require_encryption)
        object.__setattr__(self, "max_sessions_per_peer", max_sessions_per_peer)
        object.__setattr__(self, "max_body_bytes", max_body_bytes)
        self.__post_init__()

    def __post_init__(self) -> None:
        if self.require_encryption is None:
            # frozen: the resolved value is set once, here
            object.__setattr__(self, "require_encryption", self.encrypt)
        if self.skew <= 0 or self.grace < 0 or self.renew_after_seconds <= 0:
            raise ValueError("skew and renew_after_seconds must be > 0, grace >= 0")
        if self.window < 1 or self.renew_after_messages < 1 or self.max_sessions_per_peer < 1:
            raise ValueError("window, renew_after_messages, max_sessions_per_peer must be >= 1")

    @property
    def lifetime(self) -> float:
        """How long (s) a session is usable at all: renewal time plus grace."""
        return self.renew_after_seconds + self.grace

    @property
    def max_envelope_bytes(self) -> int:
        """Largest envelope read: a maximal body escaped as a JSON string, plus the header."""
        return 2 * self.max_body_bytes + 1024


_DEFAULT_POLICY = SecurityPolicy()


# --------------------------------------------------------------------------- sessions


class Session:
    """One authenticated session with a peer platform: direction keys, counter, replay window.

    Made by a ``Handshake``; the sending side calls ``seal``, the receiving side opens
    through its ``SessionTable``.
    """

    __slots__ = (
        "_acl_ad_rx",
        "_acl_ad_tx",
        "_acl_box_head",
        "_acl_prefix",
        "_acl_rx",
        "_acl_tx",
        "_bhi",
        "_bin_ad_rx",
        "_bin_ad_tx",
        "_bin_received",
        "_bin_rx",
        "_bin_tx",
        "_bmask",
        "_bn",
        "_box_ad_rx",
        "_box_ad_tx",
        "_box_rx",
        "_box_tx",
        "_clock",
        "_confirmed",
        "_encrypt",
        "_env_prefix",
        "_full",
        "_hi",
        "_lifetime",
        "_mac_rx",
        "_mac_tx",
        "_mask",
        "_max_body",
        "_n",
        "_open_rx",
        "_policy",
        "_received",
        "_retire_at",
        "_seal_tx",
        "_skew_ms",
        "_window",
        "established",
        "federation",
        "initiator",
        "me",
        "order",
        "peer",
        "peer_key",
        "peer_time",
        "sid",
    )

    def __init__(
        self,
        *,
        me: str,
        peer: str,
        federation: str,
        sid: str,
        initiator: bool,
        keys: Mapping[str, bytes],
        order: tuple[int, str],
        policy: SecurityPolicy,
        clock: Clock,
        peer_time: float | None = None,
        peer_key: object | None = None,
    ) -> None:
        self.me = me
        self.peer = peer
        # the trust store's key the exchange was verified with (None: not known): once the
        # store holds another (rotated, or removed and added again), the session is over
        self.peer_key = peer_key
        self.federation = federation
        self.sid = sid
        self.initiator = initiator
        self.order = order
        self.established = clock()
        # when the peer signed its half of the key exchange (POSIX s, its clock): compared
        # with the time it signs a leave at, never with ours (the clocks differ by the skew)
        self.peer_time = self.established if peer_time is None else peer_time
        self._policy = policy
        self._clock = clock
        self._lifetime = policy.lifetime
        self._encrypt = policy.encrypt
        self._max_body = policy.max_body_bytes
        self._skew_ms = policy.skew * 1000.0
        tx, rx = ("i2r", "r2i") if initiator else ("r2i", "i2r")
        tx_head = (federation, me, peer, sid)
        rx_head = (federation, peer, me, sid)
        # the per-session part of every MAC is hashed once; each message copies the state
        self._mac_tx = hmac.new(keys[f"{tx} mac"], _env_head(_ENV_MAC, *tx_head), hashlib.sha256)
        self._mac_rx = hmac.new(keys[f"{rx} mac"], _env_head(_ENV_MAC, *rx_head), hashlib.sha256)
        self._box_tx = keys[f"{tx} box"]
        self._box_rx = keys[f"{rx} box"]
        self._box_ad_tx = _env_head(_ENV_BOX, *tx_head)
        self._box_ad_rx = _env_head(_ENV_BOX, *rx_head)
        # per message, the cipher's own methods: no cache lookup, no wrapper call
        self._seal_tx = _cipher(self._box_tx).encrypt
        self._open_rx = _cipher(self._box_rx).decrypt
        # a boxed envelope's JSON up to the value of "ts_ms": the bytes orjson makes of
        # the envelope's dict start so, whatever the message
        self._env_prefix = _dumps({"v": 1, "from": me, "to": peer, "sid": sid, "ts_ms": 0})[:-2]
        self._bin_tx = hmac.new(keys[f"{tx} mac"], _env_head(_BIN_MAC, *tx_head), hashlib.sha256)
        self._bin_rx = hmac.new(keys[f"{rx} mac"], _env_head(_BIN_MAC, *rx_head), hashlib.sha256)
        self._bin_ad_tx = _env_head(_BIN_BOX, *tx_head)
        self._bin_ad_rx = _env_head(_BIN_BOX, *rx_head)
        self._acl_tx = hmac.new(keys[f"{tx} mac"], _env_head(_ACL_MAC, *tx_head), hashlib.sha256)
        self._acl_rx = hmac.new(keys[f"{rx} mac"], _env_head(_ACL_MAC, *rx_head), hashlib.sha256)
        self._acl_ad_tx = _env_head(_ACL_BOX, *tx_head)
        self._acl_ad_rx = _env_head(_ACL_BOX, *rx_head)
        # a binary ACL envelope's msgpack up to its `ts_ms`, without the array's head
        # (7 or 8 items): [v, from, to, sid] are the session's, packed once
        self._acl_prefix = _packb((WIRE_VERSION, me, peer, sid))[1:]
        self._acl_box_head = b"\x97" + self._acl_prefix
        self._n = 0
        self._hi = 0
        self._mask = 0
        # Binary envelopes count apart: batches and ACL messages travel on different keys
        # and are read by different tasks, so one must not push the other out of the window.
        self._bn = 0
        self._bhi = 0
        self._bmask = 0
        self._window = policy.window
        self._full = (1 << policy.window) - 1
        self._received = 0
        # binary envelopes accepted: `_received` less these is the JSON ones (`missing`),
        # so the JSON path counts nothing more than it did
        self._bin_received = 0
        # an initiator knows the responder holds the keys (it answered); a responder only
        # learns that the initiator finished when a message arrives on the session
        self._confirmed = initiator
        self._retire_at: float | None = None

    def __repr__(self) -> str:
        role = "initiator" if self.initiator else "responder"
        return (
            f"Session({self.me}->{self.peer}, sid={self.sid}, {role}, "
            f"sent={self._n}, received={self._received})"
        )

    @property
    def sent(self) -> int:
        """Envelopes sealed on this session so far (the last counter used)."""
        return self._n

    @property
    def sent_binary(self) -> int:
        """Binary envelopes (sample batches) sealed on this session so far."""
        return self._bn

    @property
    def received(self) -> int:
        """Envelopes accepted on this session so far (JSON and binary)."""
        return self._received

    @property
    def missing(self) -> int:
        """ACL envelopes, either form, the peer sealed up to the highest counter, not opened here.

        The highest counter less those accepted: lost on the way (or refused here), or still
        on their way (one that comes late within the window is counted again as it opens).
        """
        return self._hi - (self._received - self._bin_received)

    @property
    def confirmed(self) -> bool:
        """True once the peer is known to hold the session (initiator, or a message came).

        `SessionTable.doubt` makes it False again until the peer sends on it.
        """
        return self._confirmed

    def age(self) -> float:
        """Seconds since the session was established here."""
        return self._clock() - self.established

    def needs_renewal(self) -> bool:
        """True when a new handshake should start (N messages sent or T seconds old)."""
        if self._n + self._bn >= self._policy.renew_after_messages:
            return True
        limit = self._policy.renew_after_seconds
        if not self.initiator:
            # let the initiator renew first, so both sides rarely renew at once
            limit += self._policy.grace / 2
        return self._clock() - self.established >= limit

    def expired(self, now: float | None = None) -> bool:
        """True when the session may no longer be used (past its lifetime or retired past grace)."""
        if now is None:
            now = self._clock()
        if now - self.established > self._lifetime:
            return True
        return self._retire_at is not None and now > self._retire_at

    def _stamp(self, last: int) -> tuple[int, int]:
        """The timestamp (ms) and next counter for an envelope; Expired when renewal is due."""
        now = self._clock()
        if now - self.established > self._lifetime:
            raise Expired(f"session {self.sid} with {self.peer} is past its lifetime; renew")
        n = last + 1
        if n > _MAX_COUNTER:
            raise Expired(f"session {self.sid} with {self.peer} used up its counters; renew")
        return int(now * 1000), n

    def seal(self, body: bytes | str) -> bytes:
        """Seal one ACL message (JSON) into an envelope for the peer."""
        try:
            if isinstance(body, bytes):
                raw = body
                text = body.decode()
            else:
                text = body
                raw = body.encode()
        except UnicodeError as exc:  # the envelope carries the body as a JSON string
            raise MessageError(f"message body is not UTF-8 text: {exc}") from None
        if len(raw) > self._max_body:
            raise MessageError(f"message of {len(raw)} bytes exceeds the limit of {self._max_body}")
        # `_stamp`, inline (the path of every message)
        now = self._clock()
        if now - self.established > self._lifetime:
            raise Expired(f"session {self.sid} with {self.peer} is past its lifetime; renew")
        n = self._n + 1
        if n > _MAX_COUNTER:
            raise Expired(f"session {self.sid} with {self.peer} used up its counters; renew")
        ts = int(now * 1000)
        self._n = n
        if self._encrypt:
            box = self._seal_tx(_NONCE.pack(0, n), raw, self._box_ad_tx + _U64X2.pack(ts, n))
            # the bytes orjson makes of {"v": 1, …, "ts_ms": ts, "n": n, "box": base64}:
            # base64 needs no JSON escape
            return b'%b%d,"n":%d,"box":"%b"}' % (
                self._env_prefix,
                ts,
                n,
                _box_text(box),
            )
        h = self._mac_tx.copy()
        h.update(_U64X2.pack(ts, n))
        h.update(raw)
        return _dumps(
            {
                "v": 1,
                "from": self.me,
                "to": self.peer,
                "sid": self.sid,
                "ts_ms": ts,
                "n": n,
                "body": text,
                "mac": _b2a(h.digest(), newline=False).decode("ascii"),
            }
        )

    def seal_binary(self, body: bytes | str) -> bytes:
        """Seal one ACL message (JSON) into a binary (msgpack) envelope for the peer.

        ``[v, from, to, sid, ts_ms, n, box]``, or ``[v, from, to, sid, ts_ms, n, body, mac]``
        with encryption off; ``n`` is the JSON envelopes' counter (``docs/wire.md``).
        """
        return self._seal_binary(body, self._clock())

    def _seal_binary(self, body: bytes | str, now: float) -> bytes:
        """`seal_binary` at ``now``, this session's clock read by the caller."""
        raw = body.encode() if isinstance(body, str) else body
        if len(raw) > self._max_body:
            raise MessageError(f"message of {len(raw)} bytes exceeds the limit of {self._max_body}")
        # `_stamp`, inline (the path of every message)
        if now - self.established > self._lifetime:
            raise Expired(f"session {self.sid} with {self.peer} is past its lifetime; renew")
        n = self._n + 1
        if n > _MAX_COUNTER:
            raise Expired(f"session {self.sid} with {self.peer} used up its counters; renew")
        ts = int(now * 1000)
        self._n = n
        if self._encrypt:
            box = self._seal_tx(_NONCE.pack(2, n), raw, self._acl_ad_tx + _U64X2.pack(ts, n))
            # fixed widths (uint 64, uint 64, bin 32): one struct call, not a packer's
            return b"".join(
                (
                    self._acl_box_head,
                    _ACL_TAIL.pack(_U64_HEAD, ts, _U64_HEAD, n, _BIN32_HEAD, len(box)),
                    box,
                )
            )
        h = self._acl_tx.copy()
        h.update(_U64X2.pack(ts, n))
        h.update(raw)
        return b"".join(
            (
                b"\x98",
                self._acl_prefix,
                _ACL_TAIL.pack(_U64_HEAD, ts, _U64_HEAD, n, _BIN32_HEAD, len(raw)),
                raw,
                b"\xc4\x20",  # bin 8 of 32 bytes
                h.digest(),
            )
        )

    def _accept_binary(
        self, ts: int, n: int, payload: bytes, mac: bytes | None, now: float
    ) -> bytes:
        """Verify one parsed binary ACL envelope (``mac`` None: boxed); the body.

        Its own labels and nonce space, the JSON envelopes' counter and replay window.
        """
        peer = self.peer
        if mac is None:
            try:
                body: bytes = self._open_rx(
                    _NONCE.pack(2, n), payload, self._acl_ad_rx + _U64X2.pack(ts, n)
                )
            except InvalidTag:
                raise Forged(
                    f"bad authentication tag on session {self.sid} from {peer!r}: "
                    "forged or tampered",
                    peer,
                ) from None
        else:
            body = payload
            h = self._acl_rx.copy()
            h.update(_U64X2.pack(ts, n))
            h.update(body)
            if not _compare(h.digest(), mac):
                raise Forged(
                    f"bad MAC on session {self.sid} from {peer!r}: forged or tampered", peer
                )
        self._admit(ts, n, now)
        return body

    def _accept(self, ts: int, n: int, payload: str, mac: bytes | None, now: float) -> bytes:
        """Verify one parsed envelope of this session (``mac`` None: boxed); the body."""
        peer = self.peer
        if mac is None:
            # canonical base64 only: two spellings of one ciphertext would defeat byte checks
            raw = _box_bytes(payload)
            if not raw:
                raise Malformed("field 'box' is not canonical base64", peer)
            try:
                body: bytes = self._open_rx(
                    _NONCE.pack(0, n), raw, self._box_ad_rx + _U64X2.pack(ts, n)
                )
            except InvalidTag:
                raise Forged(
                    f"bad authentication tag on session {self.sid} from {peer!r}: "
                    "forged or tampered",
                    peer,
                ) from None
        else:
            body = payload.encode()
            h = self._mac_rx.copy()
            h.update(_U64X2.pack(ts, n))
            h.update(body)
            if not _compare(_b2a(h.digest(), newline=False), mac):
                raise Forged(
                    f"bad MAC on session {self.sid} from {peer!r}: forged or tampered", peer
                )
        self._admit(ts, n, now)
        return body

    def _admit(self, ts: int, n: int, now: float) -> None:
        """Take an authentic ACL envelope's ``n`` into the replay window (either form), or
        refuse it: the session over, the timestamp off, the counter seen or too old."""
        hi = self._hi
        delta = now * 1000.0 - ts
        skew_ms = self._skew_ms
        if (
            n > hi
            and self._retire_at is None
            and now - self.established <= self._lifetime
            and delta <= skew_ms
            and -delta <= skew_ms
        ):
            # the common case of `_check_live` and `_check_window`, inline: a live
            # session, a timestamp within the skew, a counter newer than any seen
            d = n - hi
            self._hi = n
            self._mask = ((self._mask << d) | 1) & self._full if d < self._window else 1
        else:
            self._check_live(ts, now)
            self._hi, self._mask = self._check_window(n, hi, self._mask)
        self._received += 1

    def _check_live(self, ts: int, now: float) -> None:
        """Refuse an authentic envelope of a session that is over, or stamped too far off."""
        peer = self.peer
        if self._retire_at is not None and now > self._retire_at:
            raise Expired(
                f"session {self.sid} with {peer!r} was renewed and its grace period is over",
                peer,
            )
        if now - self.established > self._lifetime:
            raise Expired(f"session {self.sid} with {peer!r} is past its lifetime", peer)
        skew_ms = self._skew_ms
        delta = now * 1000.0 - ts
        if delta > skew_ms or -delta > skew_ms:
            raise Expired(
                f"timestamp {ts / 1000:.3f} is {delta / 1000:+.3f} s from this clock "
                f"(allowed ±{self._policy.skew:g} s)",
                peer,
            )

    def _check_window(self, n: int, hi: int, mask: int) -> tuple[int, int]:
        """Refuse a counter already seen or too old; the window's new ``(highest, mask)``."""
        if n > hi:
            d = n - hi
            return n, ((mask << d) | 1) & self._full if d < self._window else 1
        d = hi - n
        if d >= self._window:
            raise Replayed(
                f"counter {n} on session {self.sid} is older than the replay window "
                f"(newest {hi}, window {self._window})",
                self.peer,
            )
        bit = 1 << d
        if mask & bit:
            raise Replayed(f"counter {n} on session {self.sid} was already seen", self.peer)
        return hi, mask | bit

    def seal_bytes(self, body: bytes) -> bytes:
        """Seal binary ``body`` (a sample batch) into a msgpack envelope for the peer.

        ``[v, from, to, sid, ts_ms, n, body, mac]``, or ``[v, from, to, sid, ts_ms, n, box]``
        when the policy encrypts; ``n`` counts binary envelopes only (``docs/wire.md``).
        """
        if len(body) > self._max_body:
            raise MessageError(
                f"binary body of {len(body)} bytes exceeds the limit of {self._max_body}"
            )
        ts, n = self._stamp(self._bn)
        self._bn = n
        if self._encrypt:
            # the cipher's own method and the nonce in one pack (`_bin_nonce`), as the ACL
            # envelopes: this runs once per stream batch
            box = self._seal_tx(_NONCE.pack(1, n), body, self._bin_ad_tx + _U64X2.pack(ts, n))
            return _pack_own([WIRE_VERSION, self.me, self.peer, self.sid, ts, n, box])
        h = self._bin_tx.copy()
        h.update(_U64X2.pack(ts, n))
        h.update(body)
        return _pack_own([WIRE_VERSION, self.me, self.peer, self.sid, ts, n, body, h.digest()])

    def _accept_bytes(
        self, ts: int, n: int, payload: bytes, mac: bytes | None, now: float
    ) -> bytes:
        """Verify one parsed binary envelope of this session (``mac`` None: boxed); the body."""
        peer = self.peer
        if mac is None:
            try:
                body: bytes = self._open_rx(
                    _NONCE.pack(1, n), payload, self._bin_ad_rx + _U64X2.pack(ts, n)
                )
            except InvalidTag:
                raise Forged(
                    f"bad authentication tag on session {self.sid} from {peer!r}: "
                    "forged or tampered",
                    peer,
                ) from None
        else:
            body = payload
            h = self._bin_rx.copy()
            h.update(_U64X2.pack(ts, n))
            h.update(body)
            if not _compare(h.digest(), mac):
                raise Forged(
                    f"bad MAC on session {self.sid} from {peer!r}: forged or tampered", peer
                )
        hi = self._bhi
        delta = now * 1000.0 - ts
        skew_ms = self._skew_ms
        if (
            n > hi
            and self._retire_at is None
            and now - self.established <= self._lifetime
            and delta <= skew_ms
            and -delta <= skew_ms
        ):
            # the common case of `_check_live` and `_check_window`, inline as in `_admit`:
            # this runs once per stream batch
            d = n - hi
            self._bhi = n
            self._bmask = ((self._bmask << d) | 1) & self._full if d < self._window else 1
        else:
            self._check_live(ts, now)
            self._bhi, self._bmask = self._check_window(n, hi, self._bmask)
        self._received += 1
        self._bin_received += 1
        return body


def _aead_nonce(n: int) -> bytes:
    """The 96-bit AEAD nonce: the session counter, unique per direction key by construction."""
    return b"\x00\x00\x00\x00" + _U64.pack(n)


def _acl_nonce(n: int) -> bytes:
    """The AEAD nonce of binary ACL envelopes: the JSON ones' counter, a nonce space apart."""
    return b"\x00\x00\x00\x02" + _U64.pack(n)


def _bin_nonce(n: int) -> bytes:
    """The AEAD nonce of binary envelopes: their own counter, in a nonce space of their own."""
    return b"\x00\x00\x00\x01" + _U64.pack(n)


class SessionTable:
    """All sessions of one platform: opens sealed envelopes and picks the session to seal with."""

    def __init__(
        self,
        me: str,
        trust: TrustStore,
        *,
        policy: SecurityPolicy = _DEFAULT_POLICY,
        clock: Clock = time.time,
    ) -> None:
        self.me = check_name(me)
        self.trust = trust
        self.policy = policy
        self._clock = clock
        self._by_sid: dict[str, Session] = {}
        self._by_peer: dict[str, list[Session]] = {}
        self._tx: dict[str, Session] = {}
        self._rx_latest: dict[str, Session] = {}
        # when each peer's last envelope opened: authenticated proof that it runs
        self._heard: dict[str, float] = {}
        # per peer, the `Session.missing` of its sessions dropped from the table
        self._missing_dropped: dict[str, int] = {}
        # per peer, how many times `forget` dropped sessions of it (`forgotten`): bounded,
        # as ``_missing_dropped``, by the platforms that held sessions here
        self._forgets: dict[str, int] = {}
        # per peer that left (signed), when: its sessions made before are never trusted again
        self._left: dict[str, float] = {}
        # per peer, what `needs_renewal` read when it said False: the newest session, its
        # renewal limit and message budget, the trusted key. False again while the clock is
        # before that limit, the key is the same and the budget holds; every change of the
        # peer's sessions (`add`, `_drop`, `doubt`, `retire`, `_on_rx_switch`) drops it.
        self._renew_due: dict[str, tuple[Session, float, int, VerifyKey | None]] = {}
        # Everything above, each session's counters and replay window included, under one
        # lock: envelopes are opened on the transport's thread (zenoh's, `InterfaceAgent`)
        # while the event loop seals, adds and drops. Reentrant: `seal` asks `session_for`.
        self._lock = threading.RLock()
        self._max_envelope = policy.max_envelope_bytes
        # a binary body is carried as is: the body plus a header of names, integers and a MAC
        self._max_bin_envelope = policy.max_body_bytes + 1024

    def __len__(self) -> int:
        return len(self._by_sid)

    def __repr__(self) -> str:
        return f"SessionTable({self.me!r}, sessions={len(self._by_sid)})"

    def peers(self) -> list[str]:
        """The platforms this table holds sessions with."""
        with self._lock:
            return sorted(self._by_peer)

    def heard_since(self, peer: str) -> float | None:
        """Seconds since an envelope from ``peer`` last opened here (None: never)."""
        with self._lock:
            at = self._heard.get(peer)
            return None if at is None else max(0.0, self._clock() - at)

    def sessions(self, peer: str | None = None) -> list[Session]:
        """The sessions with ``peer`` (all when None), oldest first."""
        with self._lock:
            if peer is None:
                return sorted(self._by_sid.values(), key=lambda s: s.order)
            return sorted(self._by_peer.get(peer, ()), key=lambda s: s.order)

    def add(self, session: Session) -> None:
        """Hold a session made by ``Handshake.respond`` or ``Handshake.finish``."""
        with self._lock:
            if session.me != self.me:
                raise ValueError(f"session of {session.me!r} added to the table of {self.me!r}")
            if session.sid in self._by_sid:
                raise ValueError(f"session {session.sid} is already in the table")
            mine = self._by_peer.setdefault(session.peer, [])
            mine.append(session)
            self._by_sid[session.sid] = session
            mine.sort(key=lambda s: s.order)
            while len(mine) > self.policy.max_sessions_per_peer:
                # Retired sessions go first. Then unconfirmed ones that are no newer than the
                # newest confirmed one: a replayed request makes those, and they cannot be a
                # renewal. A newer unconfirmed session stays: the peer may have just made it
                # and be about to send on it (both sides can renew at once). Then the oldest.
                # Never the one just added: it is a renewal.
                others = [s for s in mine if s is not session]
                newest = max((s.order[0] for s in others if s._confirmed), default=None)

                def rank(s: Session, newest: Any = newest) -> tuple[bool, bool, Any]:
                    # the order's timestamp, strictly: its second part is a random tie-break
                    plausible = s._confirmed or newest is None or s.order[0] > newest
                    return (s._retire_at is None, plausible, s.order)

                self._drop(min(others, key=rank))
            self._tx.pop(session.peer, None)
            self._renew_due.pop(session.peer, None)  # the new one may be the newest
            self.prune()

    def missing(self) -> dict[str, int]:
        """Per peer, its JSON envelopes that never opened here (`Session.missing`, summed).

        Sessions dropped from the table count still; a peer with none missing is left out.
        """
        with self._lock:
            counts = dict(self._missing_dropped)
            for s in self._by_sid.values():
                counts[s.peer] = counts.get(s.peer, 0) + s.missing
            return {peer: n for peer, n in counts.items() if n > 0}

    def _drop(self, session: Session) -> None:
        if self._by_sid.pop(session.sid, None) is not None and session.missing > 0:
            dropped = self._missing_dropped
            dropped[session.peer] = dropped.get(session.peer, 0) + session.missing
        mine = self._by_peer.get(session.peer)
        if mine is not None:
            if session in mine:
                mine.remove(session)
            if not mine:
                del self._by_peer[session.peer]
        self._renew_due.pop(session.peer, None)
        if self._tx.get(session.peer) is session:
            del self._tx[session.peer]
        if self._rx_latest.get(session.peer) is session:
            del self._rx_latest[session.peer]

    def forget(self, peer: str) -> int:
        """Drop every session with ``peer`` (it left the federation); how many were dropped."""
        with self._lock:
            dropped = list(self._by_peer.get(peer, ()))
            for session in dropped:
                self._drop(session)
            self._tx.pop(peer, None)
            self._rx_latest.pop(peer, None)
            if dropped:  # what opened on them before is refused when taken (`forgotten`)
                self._forgets[peer] = self._forgets.get(peer, 0) + 1
            return len(dropped)

    def forgotten(self, peer: str) -> int:
        """How many times `forget` dropped ``peer``'s sessions (0: never).

        An envelope opened on another thread and taken later (`open_noting`) opened on a
        session gone since when this changed in between: as if opened now, it is refused.
        """
        return self._forgets.get(peer, 0)

    def open_noting(self, envelope: bytes | str) -> tuple[str, bytes, int]:
        """`open`, and `forgotten` of its sender at that moment (read under the same lock)."""
        if type(envelope) is bytes and envelope[:1] in _BINARY_HEADS:
            # `_open_binary` in one lock section with the count: every envelope the lane opens
            # (its unpacking reads nothing of the table: outside it)
            frm, to, sid, ts, n, payload, mac = self._unpack(envelope, self._max_envelope, None)
            # the lock taken and released by its methods, not by `with`: ~0.8 k
            # instructions less on the path of every envelope the lane opens
            lock = self._lock
            lock.acquire()
            try:
                body = self._accept_binary(frm, to, sid, ts, n, payload, mac)
                return frm, body, self._forgets.get(frm, 0)
            finally:
                lock.release()
        with self._lock:
            frm, body = self.open(envelope)
            return frm, body, self._forgets.get(frm, 0)

    def doubt(self, peer: str) -> int:
        """Seal for ``peer`` on none of its sessions until it sends on one; how many were in use.

        For a platform whose liveliness token shows for the first time: the sessions held
        with it may be a previous process's (its token never seen here), which the new one
        cannot open; or the current one's (its token late), whose envelopes in flight must
        still open here. So none is dropped: the next message agrees a new session first
        (`session_for` is None), and one the peer sends on is trusted again.
        """
        with self._lock:
            doubted = 0
            for session in self._by_peer.get(peer, ()):
                if session._confirmed:
                    session._confirmed = False
                    doubted += 1
            self._tx.pop(peer, None)
            self._renew_due.pop(peer, None)
            # the next envelope from the peer, on whichever session, confirms that one again
            self._rx_latest.pop(peer, None)
            return doubted

    def retire(self, peer: str, before: float | None = None) -> int:
        """Seal for ``peer`` on none of its sessions agreed before ``before`` again.

        For a peer that said, signed, that it leaves (``before``: when it signed that,
        POSIX s in its clock, compared with each session's `Session.peer_time`; now when
        None): unlike `doubt`, an envelope of its that comes
        late still opens (within ``grace``, then the session is dropped) but trusts none
        of those sessions again, so the next message to it agrees a new session (and
        finds nobody, if it is gone). Sessions agreed since are its next process's and
        stay: a leave replayed, or come late, retires none of them. How many were retired.
        """
        with self._lock:
            now = self._clock()
            # in the peer's clock, as each session's `peer_time`: what it agreed after it signed
            # the leave is kept, however far (within the skew) its clock is from ours
            cutoff = now if before is None else before
            retire_at = now + self.policy.grace
            retired = 0
            for session in self._by_peer.get(peer, ()):
                if session.peer_time > cutoff:
                    continue
                retired += 1
                session._confirmed = False
                if session._retire_at is None or session._retire_at > retire_at:
                    session._retire_at = retire_at
            self._left[peer] = max(self._left.get(peer, cutoff), cutoff)
            self._tx.pop(peer, None)
            self._renew_due.pop(peer, None)
            latest = self._rx_latest.get(peer)
            if latest is not None and latest.peer_time <= cutoff:
                del self._rx_latest[peer]
            return retired

    def back_since_left(self, peer: str) -> bool:
        """Whether ``peer``, since the leave it signed, sent on a session it began after it.

        Only the holder of its key can agree a session, so this is as strong a proof as
        its signed directory snapshot that a process of it is back (a restarted one asks
        at once, before its directory answers). A session begun here is not counted: the
        refusal sent to a platform that left and goes on asking would agree one.
        """
        with self._lock:
            left = self._left.get(peer)
            latest = self._rx_latest.get(peer)
            return (
                left is not None
                and latest is not None
                and not latest.initiator
                and latest.peer_time > left
            )

    def peer_clock_offset(self, peer: str) -> float:
        """How far ``peer``'s clock is ahead of ours, by its newest session (s; 0 when none).

        The time it signed its half of the key exchange less when the session was made
        here: the message's transit counts too, so a little less than the true offset.
        """
        with self._lock:
            newest = max(self._by_peer.get(peer, ()), key=lambda s: s.order, default=None)
            return 0.0 if newest is None else newest.peer_time - newest.established

    def prune(self) -> int:
        """Drop sessions past their lifetime or their grace period; how many were dropped."""
        with self._lock:
            now = self._clock()
            dead = [s for s in self._by_sid.values() if s.expired(now)]
            for session in dead:
                self._drop(session)
            return len(dead)

    def session_for(self, peer: str) -> Session | None:
        """The session to seal with for ``peer``, or None when a handshake is needed first.

        The newest session the peer is known to hold: one this platform initiated, or one
        the peer has sent on. A responder never sends first on a fresh session, because a
        replayed request can make sessions the peer does not hold. A session agreed with
        a key the trust store no longer holds for ``peer`` is none, as opening says.
        """
        with self._lock:
            now = self._clock()
            cached = self._tx.get(peer)
            trusted = self.trust._keys.get(peer)
            # `Session.expired` and the key check of `_session_of`, inline: the path of
            # every message sealed (a re-key from another thread is seen before the
            # revocation reaches the loop)
            if (
                cached is not None
                and now - cached.established <= cached._lifetime
                and (cached._retire_at is None or now <= cached._retire_at)
                and (
                    (agreed := cached.peer_key) is trusted
                    or agreed is None
                    or (trusted is not None and agreed == trusted)
                )
            ):
                return cached
            best: Session | None = None
            for s in self._by_peer.get(peer, ()):
                if (
                    s._confirmed
                    and not s.expired(now)
                    and (best is None or s.order > best.order)
                    and (
                        (agreed := s.peer_key) is trusted
                        or agreed is None
                        or (trusted is not None and agreed == trusted)
                    )
                ):
                    best = s
            if best is None:
                self._tx.pop(peer, None)
            else:
                self._tx[peer] = best
            return best

    def seal(self, peer: str, body: bytes | str) -> bytes:
        """Seal ``body`` for ``peer`` on its current session; UnknownSession when there is none."""
        with self._lock:
            session = self.session_for(peer)
            if session is None:
                raise UnknownSession(f"no session with {peer!r}: run a handshake first", peer)
            return session.seal(body)

    def seal_binary(self, peer: str, body: bytes | str) -> bytes:
        """`seal` in the binary (msgpack) form of an ACL envelope; `open` reads both forms."""
        # in `with`, not taken by hand: the loop's thread seals too, and there an interrupt
        # (Ctrl-C's handler) can come right after a bare `acquire()`, before its `try`,
        # leaving the lock held for ever and zenoh's thread blocked at its next seal
        with self._lock:
            session = self._tx.get(peer)
            if session is not None:
                # `session_for`'s first answer, inline (the path of every ACL message
                # sealed, the lane's answers too): the session it chose before, while it
                # is within its lifetime, not retired past grace and of the trusted key
                now = self._clock()
                trusted = self.trust._keys.get(peer)
                if (
                    now - session.established > session._lifetime
                    or (session._retire_at is not None and now > session._retire_at)
                    or (
                        (agreed := session.peer_key) is not trusted
                        and agreed is not None
                        and (trusted is None or agreed != trusted)
                    )
                ):
                    session = self.session_for(peer)
                elif session._clock is self._clock:
                    # the session's clock is the table's: sealed at the reading just checked
                    return session._seal_binary(body, now)
            else:
                session = self.session_for(peer)
            if session is None:
                raise UnknownSession(f"no session with {peer!r}: run a handshake first", peer)
            return session.seal_binary(body)

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal binary ``body`` for ``peer`` on its current session; UnknownSession when none."""
        with self._lock:
            session = self.session_for(peer)
            if session is None:
                raise UnknownSession(f"no session with {peer!r}: run a handshake first", peer)
            return session.seal_bytes(body)

    def needs_renewal(self, peer: str) -> bool:
        """True when there is no session to seal with for ``peer``, or it asks for renewal.

        The caller then starts a handshake unless ``Handshake.pending(peer)`` says one is
        already under way; it may keep sealing on the old session until the new one is made.
        """
        with self._lock:  # not by hand: asked on the loop's thread (`seal_binary`)
            now = self._clock()
            trusted = self.trust._keys.get(peer)
            due = self._renew_due.get(peer)
            if due is not None:
                # asked after every message sent: what was read last, while it holds
                s, limit, budget, key = due
                if now - s.established < limit and key is trusted and s._n + s._bn < budget:
                    return False
            newest: Session | None = None
            for s in self._by_peer.get(peer, ()):
                # local time, not the agreed order: "did I make a session lately?" is local
                if (
                    s._confirmed
                    # `Session.expired`, inline: asked after every message sent
                    and now - s.established <= s._lifetime
                    and (s._retire_at is None or now <= s._retire_at)
                    and (newest is None or s.established > newest.established)
                    # one of a key no longer trusted seals nothing (`session_for`): not fresh
                    and (
                        (agreed := s.peer_key) is trusted
                        or agreed is None
                        or (trusted is not None and agreed == trusted)
                    )
                ):
                    newest = s
            if newest is None or newest.needs_renewal():
                return True
            if newest._retire_at is None and newest._clock is self._clock:
                # kept while the clock is before the renewal time (`Session.needs_renewal`'s
                # limit, below the session's lifetime): one retired, or read by another
                # clock than the table's, is asked in full every time
                policy = newest._policy
                limit = policy.renew_after_seconds
                if not newest.initiator:
                    limit += policy.grace / 2
                self._renew_due[peer] = (newest, limit, policy.renew_after_messages, trusted)
            return False

    def _session_of(self, frm: str, to: str, sid: str, ts: Any, n: Any) -> Session:
        """The header checks both envelope kinds share, in order; the session they name."""
        if type(ts) is not int or not 0 <= ts <= _MAX_COUNTER:
            raise Malformed("field 'ts_ms' must be a non-negative integer (Unix ms)", frm)
        if type(n) is not int or not 1 <= n <= _MAX_COUNTER:
            raise Malformed("field 'n' must be a positive integer", frm)
        if to != self.me:
            raise Misdirected(f"envelope for {to!r} reached {self.me!r}", frm)
        if frm not in self.trust._keys:  # checked per message: removing a platform revokes it
            raise _untrusted(frm)
        session = self._by_sid.get(sid)
        if session is None:
            raise UnknownSession(
                f"no session {sid!r} with {frm!r} (never made, renewed away or forgotten)", frm
            )
        if session.peer != frm:
            # the MAC binds the session's peer: a different 'from' is a tampered header
            raise Forged(f"session {sid} belongs to {session.peer!r}, not to {frm!r}", frm)
        agreed = session.peer_key
        if (
            agreed is not None
            and agreed is not (trusted := self.trust._keys.get(frm))
            and (trusted is None or agreed != trusted)
        ):
            # agreed with a key the trust store no longer holds: a platform removed and
            # trusted again, or its key rotated, before its old sessions were forgotten
            # (by value: a handshake may verify with another store holding the same keys)
            raise UnknownSession(
                f"session {sid!r} with {frm!r} was agreed with a key no longer trusted", frm
            )
        return session

    def open(self, envelope: bytes | str) -> tuple[str, bytes]:
        """Verify a sealed envelope: ``(sender platform, ACL message JSON bytes)`` or a refusal.

        Either form: a msgpack array (its first byte 0x90-0x9f, 0xdc or 0xdd) is a binary
        ACL envelope, anything else is read as JSON. Raises Malformed, Misdirected,
        UnknownPlatform, UnknownSession, Forged, Expired or Replayed (all
        AuthenticationError); nothing of a refused envelope can be trusted.
        """
        if type(envelope) is bytes and envelope[:1] in _BINARY_HEADS:
            return self._open_binary(envelope)
        if len(envelope) > self._max_envelope:
            raise Malformed(
                f"envelope of {len(envelope)} bytes exceeds the limit of {self._max_envelope}"
            )
        try:
            env = _loads(envelope)
        except _JSONDecodeError as exc:
            raise Malformed(f"not JSON: {exc}") from None
        if type(env) is not dict:
            raise Malformed(f"an envelope is a JSON object, not {type(env).__name__}")
        keys = env.keys()
        if keys == _PLAIN_FIELDS:
            boxed = False
            payload = env["body"]
        elif keys == _BOX_FIELDS:
            boxed = True
            payload = env["box"]
        else:
            raise Malformed(_field_problem(env), _str_or_none(env.get("from")))
        frm = env["from"]
        if type(frm) is not str:
            raise Malformed("field 'from' must be a string")
        v = env["v"]
        if type(v) is not int or v != WIRE_VERSION:
            raise Malformed(f"unsupported envelope version {v!r} (this side speaks 1)", frm)
        to = env["to"]
        sid = env["sid"]
        ts = env["ts_ms"]
        n = env["n"]
        if type(to) is not str or type(sid) is not str or type(payload) is not str:
            raise Malformed("fields 'to', 'sid', 'body'/'box' must be strings", frm)
        with self._lock:
            session = self._session_of(frm, to, sid, ts, n)
            tag: bytes | None = None
            if not boxed:
                if self.policy.require_encryption:
                    raise Unencrypted("this platform requires encrypted envelopes ('box')", frm)
                mac = env["mac"]
                if type(mac) is not str:
                    raise Malformed("field 'mac' must be a string", frm)
                tag = mac.encode()
            now = self._clock()
            body = session._accept(ts, n, payload, tag, now)
            self._heard[frm] = now
            if self._rx_latest.get(frm) is not session:
                self._on_rx_switch(session, now)
        return frm, body

    def _open_binary(self, envelope: bytes) -> tuple[str, bytes]:
        """`open` of a binary ACL envelope: the checks of `open_bytes`, the JSON form's counter.

        Its size limit is the JSON form's envelope's, and no body limit before it opens: an
        authentic body over the message limit opens in either form and is answered as a
        message too large (`not-understood`), never dropped unanswered in one form only.
        """
        frm, to, sid, ts, n, payload, mac = self._unpack(envelope, self._max_envelope, None)
        with self._lock:
            return frm, self._accept_binary(frm, to, sid, ts, n, payload, mac)

    def _accept_binary(
        self, frm: str, to: Any, sid: Any, ts: Any, n: Any, payload: bytes, mac: Any
    ) -> bytes:
        """An unpacked binary ACL envelope's session checks and opening, under the table's
        lock (the caller holds it): its body, or a refusal."""
        session = self._session_of(frm, to, sid, ts, n)
        if mac is not None:
            if self.policy.require_encryption:
                raise Unencrypted("this platform requires encrypted envelopes ('box')", frm)
            if type(mac) is not bytes or len(mac) != _MAC_BYTES:
                raise Malformed(f"field 'mac' must be {_MAC_BYTES} bytes", frm)
        now = self._clock()
        body: bytes = session._accept_binary(ts, n, payload, mac, now)
        self._heard[frm] = now
        if self._rx_latest.get(frm) is not session:
            self._on_rx_switch(session, now)
        return body

    def _unpack(
        self, envelope: bytes, max_envelope: int, max_body: int | None
    ) -> tuple[str, Any, Any, Any, Any, bytes, Any]:
        """A binary envelope's items ``(from, to, sid, ts_ms, n, body or box, mac or None)``.

        The checks that need no session: size (``max_body`` None: the envelope's only),
        msgpack, the array's length, ``v`` and the types of names and body; Malformed
        otherwise.
        """
        if len(envelope) > max_envelope:
            raise Malformed(
                f"envelope of {len(envelope)} bytes exceeds the limit of {max_envelope}"
            )
        try:
            env = _unpackb(envelope)  # raw=False, use_list=True: msgpack 1's defaults
        except Exception as exc:  # msgpack raises several kinds on bad input
            raise Malformed(f"not msgpack: {type(exc).__name__}: {exc}") from None
        if type(env) is not list or len(env) not in (7, 8):
            raise Malformed("a binary envelope is a msgpack array of 8 items (7 when encrypted)")
        if len(env) == 8:
            v, frm, to, sid, ts, n, payload, mac = env
            boxed = False
            if mac is None:  # a nil MAC is no MAC: None below means a box
                mac = b""  # refused as a MAC of the wrong size, where that is checked
        else:
            v, frm, to, sid, ts, n, payload = env
            mac = None
            boxed = True
        if type(frm) is not str:
            raise Malformed("field 'from' must be a string")
        if type(v) is not int or v != WIRE_VERSION:
            raise Malformed(f"unsupported envelope version {v!r} (this side speaks 1)", frm)
        if type(to) is not str or type(sid) is not str or type(payload) is not bytes:
            raise Malformed("fields 'to', 'sid' must be strings, 'body'/'box' binary", frm)
        # the envelope's limit leaves room for the header: the body has its own (a box adds
        # its tag), so a receiver never decodes a body larger than a sender may seal
        if max_body is not None and len(payload) > max_body + (_TAG_BYTES if boxed else 0):
            raise Malformed(
                f"binary body of {len(payload)} bytes exceeds the limit of {max_body}", frm
            )
        return frm, to, sid, ts, n, payload, mac

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Verify a binary envelope: ``(sender platform, body bytes)`` or a refusal.

        The msgpack counterpart of ``open``, with the same checks, in the same order, and
        the same errors (all AuthenticationError).
        """
        frm, to, sid, ts, n, payload, mac = self._unpack(
            envelope, self._max_bin_envelope, self.policy.max_body_bytes
        )
        with self._lock:
            session = self._session_of(frm, to, sid, ts, n)
            if mac is not None:
                if self.policy.require_encryption:
                    raise Unencrypted("this platform requires encrypted envelopes ('box')", frm)
                if type(mac) is not bytes or len(mac) != _MAC_BYTES:
                    raise Malformed(f"field 'mac' must be {_MAC_BYTES} bytes", frm)
            now = self._clock()
            body = session._accept_bytes(ts, n, payload, mac, now)
            self._heard[frm] = now
            if self._rx_latest.get(frm) is not session:
                self._on_rx_switch(session, now)
        return frm, body

    def _on_rx_switch(self, session: Session, now: float) -> None:
        """The peer sent on another session than last time: confirm it, retire older ones."""
        left = self._left.get(session.peer)
        if left is not None and session.peer_time <= left:
            return  # in flight when the peer left: opened, but its session is over
        session._confirmed = True
        self._tx.pop(session.peer, None)  # the choice of sending session may change
        self._renew_due.pop(session.peer, None)
        latest = self._rx_latest.get(session.peer)
        if latest is None or session.order > latest.order:
            self._rx_latest[session.peer] = session
            # the peer has moved on: its older sessions only carry messages still in flight
            retire_at = now + self.policy.grace
            for s in self._by_peer.get(session.peer, ()):
                if s.order < session.order and s._retire_at is None:
                    s._retire_at = retire_at


def _str_or_none(value: object) -> str | None:
    return value if isinstance(value, str) else None


def _field_problem(env: Mapping[str, Any]) -> str:
    """Name the first missing or unexpected envelope field (the slow path of a refusal)."""
    fields = _BOX_FIELDS if "box" in env else _PLAIN_FIELDS
    missing = sorted(fields - env.keys())
    extra = sorted(env.keys() - fields)
    if missing:
        return f"envelope field {missing[0]!r} is missing"
    return f"unexpected envelope field {extra[0]!r}"


# --------------------------------------------------------------------------- handshake


@dataclass(init=False, repr=False, eq=False)
class _Pending(Record):
    __slots__ = ("peer", "secret", "started", "transcript", "ts_ms")
    peer: str
    transcript: bytes  # the signed part of our request
    secret: bytes  # our ephemeral X25519 private key
    started: float
    ts_ms: int

    def __init__(
        self,
        peer: str,
        transcript: bytes,
        secret: bytes,
        started: float,
        ts_ms: int,
    ) -> None:
        self.peer = peer
        self.transcript = transcript
        self.secret = secret
        self.started = started
        self.ts_ms = ts_ms


_SESSION_KEYS = ("i2r mac", "r2i mac", "i2r box", "r2i box", "sid")


def _hkdf(transcript: bytes, shared: bytes) -> dict[str, bytes]:
    """HKDF-SHA256 (RFC 5869): the transcript hash salts the extract; one label per output."""
    prk = hmac.digest(hashlib.sha256(transcript).digest(), shared, "sha256")
    return {
        label: hmac.digest(prk, b"dyknow-session-v1 " + label.encode() + b"\x01", "sha256")
        for label in _SESSION_KEYS
    }


def _session_id(sid_key: bytes) -> str:
    """The session id: the first 16 bytes of the ``sid`` output, base64url without padding."""
    return base64.urlsafe_b64encode(sid_key[:16]).rstrip(b"=").decode("ascii")


def _fresh_ephemeral() -> tuple[bytes, bytes, bytes]:
    """A fresh nonce and X25519 key pair for one handshake message: ``(nonce, public, secret)``."""
    public, secret = _sodium.crypto_box_keypair()
    return os.urandom(_NONCE_BYTES), public, secret


class Handshake:
    """One platform's side of the authenticated key exchange, as a state machine over bytes.

    Initiator: ``request = hs.initiate(peer)``, send it on ``kx/<peer>``, then
    ``session = hs.finish(reply)``. Responder: ``reply, session = hs.respond(request)``.
    Both add the session to their ``SessionTable``.
    """

    def __init__(
        self,
        me: KeyPair,
        trust: TrustStore,
        federation: str | None = None,
        *,
        policy: SecurityPolicy = _DEFAULT_POLICY,
        clock: Clock = time.time,
    ) -> None:
        if federation is not None and federation != trust.federation:
            raise ValueError(
                f"federation {federation!r} differs from the trust file's {trust.federation!r}"
            )
        self.me = me
        self.trust = trust
        self.federation = trust.federation
        self.policy = policy
        self._clock = clock
        self._pending: dict[bytes, _Pending] = {}
        self._finished: dict[bytes, float] = {}
        # (initiator, nonce) of requests answered, kept until their timestamp goes stale
        self._seen: set[tuple[str, bytes]] = set()
        self._seen_heap: list[tuple[float, str, bytes]] = []
        # where nonces and ephemeral keys come from; only the test vectors replace it
        self._ephemeral: Callable[[], tuple[bytes, bytes, bytes]] = _fresh_ephemeral

    def _now_ms(self) -> tuple[float, int]:
        now = self._clock()
        return now, int(now * 1000)

    def _prune(self, now: float) -> None:
        horizon = 2 * self.policy.skew
        for key in [k for k, p in self._pending.items() if now - p.started > horizon]:
            del self._pending[key]
        for key in [k for k, t in self._finished.items() if now - t > horizon]:
            del self._finished[key]
        heap = self._seen_heap
        while heap and heap[0][0] < now:
            _, platform, nonce = heapq.heappop(heap)
            self._seen.discard((platform, nonce))

    def initiate(self, peer: str) -> bytes:
        """The request that opens a session with ``peer`` (kept pending until ``finish``)."""
        check_name(peer)
        if peer == self.me.platform:
            raise ValueError("a platform does not open a session with itself")
        self.trust.verify_key(peer)  # fail early: a reply from an untrusted peer is refused
        now, ts = self._now_ms()
        self._prune(now)
        nonce, epk, esk = self._ephemeral()
        transcript = _init_transcript(self.federation, self.me.platform, peer, ts, nonce, epk)
        self._pending[nonce] = _Pending(peer, transcript, esk, now, ts)
        return _dumps(
            {
                "v": WIRE_VERSION,
                "kx": "init",
                "fed": self.federation,
                "from": self.me.platform,
                "to": peer,
                "ts_ms": ts,
                "nonce": _b64(nonce),
                "epk": _b64(epk),
                "sig": _b64(self.me.sign(transcript)),
            }
        )

    def respond(self, request: bytes | str) -> tuple[bytes, Session]:
        """Check a request and answer it: ``(reply bytes, new Session)`` or a refusal."""
        msg = _parse_kx(request, "init", _INIT_FIELDS)
        frm, ts, nonce, epk, sig = self._check_kx(msg)
        transcript = _init_transcript(self.federation, frm, self.me.platform, ts, nonce, epk)
        key = self._verify(frm, transcript, sig)
        now, my_ts = self._now_ms()
        self._prune(now)
        if (frm, nonce) in self._seen:
            raise Replayed(f"handshake request from {frm!r} was already answered", frm)
        self._seen.add((frm, nonce))
        heapq.heappush(self._seen_heap, (ts / 1000 + self.policy.skew + 1, frm, nonce))
        my_nonce, my_epk, my_esk = self._ephemeral()
        full = transcript + _reply_part(
            self.federation, self.me.platform, frm, my_ts, my_nonce, my_epk
        )
        shared = _x25519(my_esk, epk, frm)
        reply = _dumps(
            {
                "v": WIRE_VERSION,
                "kx": "reply",
                "fed": self.federation,
                "from": self.me.platform,
                "to": frm,
                "ts_ms": my_ts,
                "nonce": _b64(my_nonce),
                "epk": _b64(my_epk),
                "re": _b64(nonce),
                "sig": _b64(self.me.sign(full)),
            }
        )
        return reply, self._session(
            frm, full, shared, initiator=False, order_ts=max(ts, my_ts), peer_ts=ts, key=key
        )

    def finish(self, reply: bytes | str) -> Session:
        """Check the reply to one of our requests and make the session, or refuse it."""
        msg = _parse_kx(reply, "reply", _REPLY_FIELDS)
        frm, ts, nonce, epk, sig = self._check_kx(msg)
        try:
            re_nonce = _unb64(msg["re"], _NONCE_BYTES)
        except ValueError as exc:
            raise Malformed(f"handshake field 're': {exc}", frm) from None
        now = self._clock()
        pending = self._pending.get(re_nonce)
        if pending is None:
            if re_nonce in self._finished:
                raise Replayed(f"handshake reply from {frm!r} was already used", frm)
            raise UnknownSession(
                f"handshake reply from {frm!r} answers no request of ours pending", frm
            )
        if pending.peer != frm:
            raise Forged(f"reply from {frm!r} to a handshake with {pending.peer!r}", frm)
        full = pending.transcript + _reply_part(
            self.federation, frm, self.me.platform, ts, nonce, epk
        )
        key = self._verify(frm, full, sig)
        if now - pending.started > self.policy.skew:
            del self._pending[re_nonce]
            raise Expired(f"handshake reply from {frm!r} came too late", frm)
        shared = _x25519(pending.secret, epk, frm)
        del self._pending[re_nonce]
        self._finished[re_nonce] = now
        return self._session(
            frm,
            full,
            shared,
            initiator=True,
            order_ts=max(pending.ts_ms, ts),
            peer_ts=ts,
            key=key,
        )

    def pending(self, peer: str) -> bool:
        """True while a request of ours to ``peer`` awaits its reply (do not start another)."""
        now = self._clock()
        return any(
            p.peer == peer and now - p.started <= self.policy.skew for p in self._pending.values()
        )

    def cancel(self, peer: str) -> int:
        """Drop our pending requests to ``peer`` (it left); how many were dropped."""
        keys = [k for k, p in self._pending.items() if p.peer == peer]
        for key in keys:
            del self._pending[key]
        return len(keys)

    def _check_kx(self, msg: dict[str, Any]) -> tuple[str, int, bytes, bytes, bytes]:
        """The checks common to request and reply, cheapest first; the decoded fields."""
        frm = msg["from"]
        if msg["fed"] != self.federation:
            raise Misdirected(
                f"handshake for federation {msg['fed']!r}, this is {self.federation!r}", frm
            )
        if msg["to"] != self.me.platform:
            raise Misdirected(f"handshake for {msg['to']!r} reached {self.me.platform!r}", frm)
        if frm == self.me.platform:
            raise Misdirected("handshake claims to come from this platform itself", frm)
        if frm not in self.trust:
            raise _untrusted(frm)
        ts = msg["ts_ms"]
        delta = self._clock() - ts / 1000
        if abs(delta) > self.policy.skew:
            raise Expired(
                f"handshake timestamp is {delta:+.3f} s from this clock "
                f"(allowed ±{self.policy.skew:g} s)",
                frm,
            )
        try:
            nonce = _unb64(msg["nonce"], _NONCE_BYTES)
            epk = _unb64(msg["epk"], 32)
            sig = _unb64(msg["sig"], 64)
        except ValueError as exc:
            raise Malformed(f"handshake field: {exc}", frm) from None
        return frm, ts, nonce, epk, sig

    def _verify(self, platform: str, transcript: bytes, sig: bytes) -> VerifyKey:
        """The trusted key of ``platform``, once ``sig`` verifies with it; else Forged."""
        key = self.trust.verify_key(platform)
        try:
            key.verify(transcript, sig)
        except CryptoError:
            raise Forged(
                f"handshake signature does not verify with {platform!r}'s trusted key", platform
            ) from None
        return key

    def _session(
        self,
        peer: str,
        transcript: bytes,
        shared: bytes,
        *,
        initiator: bool,
        order_ts: int,
        peer_ts: int,
        key: VerifyKey | None = None,
    ) -> Session:
        keys = _hkdf(transcript, shared)
        sid = _session_id(keys["sid"])
        return Session(
            me=self.me.platform,
            peer=peer,
            federation=self.federation,
            sid=sid,
            initiator=initiator,
            keys=keys,
            order=(order_ts, sid),
            policy=self.policy,
            clock=self._clock,
            peer_time=peer_ts / 1000,
            peer_key=key,
        )


def _init_transcript(fed: str, frm: str, to: str, ts: int, nonce: bytes, epk: bytes) -> bytes:
    return _KX_INIT + _lp(fed) + _lp(frm) + _lp(to) + _U64.pack(ts) + nonce + epk


def _reply_part(fed: str, frm: str, to: str, ts: int, nonce: bytes, epk: bytes) -> bytes:
    return _KX_REPLY + _lp(fed) + _lp(frm) + _lp(to) + _U64.pack(ts) + nonce + epk


def _x25519(secret: bytes, public: bytes, peer: str) -> bytes:
    try:
        shared: bytes = _sodium.crypto_scalarmult(secret, public)
    except CryptoError:
        # libsodium refuses low-order points (an all-zero shared secret)
        raise Forged(f"{peer!r} sent an invalid ephemeral key", peer) from None
    return shared


def _parse_kx(data: bytes | str, kind: str, fields: frozenset[str]) -> dict[str, Any]:
    if len(data) > MAX_HANDSHAKE_BYTES:
        raise Malformed(f"handshake message of {len(data)} bytes exceeds {MAX_HANDSHAKE_BYTES}")
    try:
        msg = _loads(data)
    except _JSONDecodeError as exc:
        raise Malformed(f"handshake message is not JSON: {exc}") from None
    if type(msg) is not dict:
        raise Malformed("a handshake message is a JSON object")
    frm = _str_or_none(msg.get("from"))
    if msg.keys() != fields:
        missing = sorted(fields - msg.keys())
        extra = sorted(msg.keys() - fields)
        what = f"field {missing[0]!r} is missing" if missing else f"unexpected field {extra[0]!r}"
        raise Malformed(f"handshake {what}", frm)
    v = msg["v"]
    if type(v) is not int or v != WIRE_VERSION:
        raise Malformed(f"unsupported handshake version {v!r} (this side speaks 1)", frm)
    if msg["kx"] != kind:
        raise Malformed(f"expected a handshake {kind!r}, got {msg['kx']!r}", frm)
    for key in ("fed", "from", "to"):
        value = msg[key]
        if type(value) is not str or not _NAME.fullmatch(value):
            raise Malformed(f"handshake field {key!r} is not a valid name", frm)
    ts = msg["ts_ms"]
    if type(ts) is not int or not 0 <= ts <= _MAX_COUNTER:
        raise Malformed("handshake field 'ts_ms' must be a non-negative integer", frm)
    return msg


# --------------------------------------------------------------------------- the owner


SEALED_OVERHEAD = 48
"""What a sealed box adds: the sender's ephemeral X25519 key (32 B) and the tag (16 B)."""


def seal_for_owner(public_key: bytes, data: bytes) -> bytes:
    """``data`` sealed to the owner of the Ed25519 ``public_key`` (libsodium sealed box).

    The Ed25519 key is converted to its X25519 form (``crypto_sign_ed25519_pk_to_curve25519``);
    only the private key's holder opens it (`KeyPair.open_sealed`). Anonymous: the box does
    not say who sealed it (anyone with the public key can), so what a platform publishes
    for its owner is signed inside the box (`seal_owner_batch`; ``docs/wire.md``, "Batches
    for the owner").
    """
    box: bytes = _sodium.crypto_box_seal(data, _owner_box_key(public_key))
    return box


@functools.lru_cache(maxsize=64)
def _owner_box_key(public_key: bytes) -> bytes:
    """The X25519 form of an Ed25519 public key: ~40 µs, half a seal, for the same few keys."""
    key: bytes = _sodium.crypto_sign_ed25519_pk_to_curve25519(public_key)
    return key


def open_for_owner(keys: KeyPair, data: bytes) -> bytes:
    """`KeyPair.open_sealed`, as a function (the counterpart of `seal_for_owner`)."""
    return keys.open_sealed(data)


OWNER_BATCH_OVERHEAD = 72
"""What signing adds to a batch for the owner: the signature (64 B) and ``ts_ms`` (8 B)."""


def _owner_transcript(key: str, ts_ms: int, data: bytes) -> bytes:
    """What a platform signs for its owner: label, the key published on, the time, the batch."""
    return _OWNER_SIG + _lp(key) + _U64.pack(ts_ms) + data


def sign_owner_batch(keys: KeyPair, key: str, data: bytes, ts_ms: int) -> bytes:
    """``data`` signed by the platform for publishing on ``key``: ``sig ‖ u64(ts_ms) ‖ data``.

    The signature binds the batch to the key expression it is published on (an audit
    batch never verifies as a watch batch, nor on another platform's key) and to its time
    (``docs/wire.md``, "Batches for the owner").
    """
    return keys.sign(_owner_transcript(key, ts_ms, data)) + _U64.pack(ts_ms) + data


def seal_owner_batch(keys: KeyPair, key: str, data: bytes, *, clock: Clock = time.time) -> bytes:
    """``data`` signed by the platform (`sign_owner_batch`), then sealed to its owner."""
    return seal_for_owner(keys.public_key, sign_owner_batch(keys, key, data, int(clock() * 1000)))


class OwnerBatches:
    """The owner's side: opens the batches a platform published to it and checks they are its.

    A batch is the platform's when it opens with the owner's key (sealed ones), its
    signature verifies with ``public_key`` (the platform's key in the trust file) over the
    key it came on, its ``ts_ms`` is within ``skew`` s of this clock and not before
    ``since`` (POSIX s on the platform's clock, when this side began listening; None: no
    bound), and its signature was not seen before. Every batch signed since reached this
    side as it went by, so a batch recorded and replayed within the skew is refused
    whether or not this side saw it. Anything else raises an AuthenticationError: an
    anonymous sealed box proves nothing about who sealed it.
    """

    def __init__(
        self,
        keys: KeyPair,
        public_key: bytes,
        *,
        skew: float = _DEFAULT_POLICY.skew,
        clock: Clock = time.time,
        since: float | None = None,
    ) -> None:
        self.keys = keys
        self._verify = VerifyKey(public_key)
        self._skew_ms = int(skew * 1000)
        self._clock = clock
        self.since = since
        self._seen: dict[bytes, int] = {}  # signature -> ts_ms, while within the skew

    def open(self, key: str, payload: bytes, *, sealed: bool = True) -> bytes:
        """The batch ``payload`` carries on ``key``, once opened (``sealed``) and verified."""
        signed = self.keys.open_sealed(payload) if sealed else payload
        if len(signed) < OWNER_BATCH_OVERHEAD:
            raise Malformed(f"a batch for the owner has at least {OWNER_BATCH_OVERHEAD} bytes")
        sig = signed[:64]
        (ts_ms,) = _U64.unpack_from(signed, 64)
        data = signed[OWNER_BATCH_OVERHEAD:]
        now_ms = int(self._clock() * 1000)
        if abs(now_ms - ts_ms) > self._skew_ms:
            raise Expired("batch for the owner outside the allowed clock skew")
        try:
            self._verify.verify(_owner_transcript(key, ts_ms, data), sig)
        except (CryptoError, ValueError):
            raise Forged(f"batch on {key!r} not signed by the platform's key", None) from None
        since_ms = None if self.since is None else int(self.since * 1000)
        if since_ms is not None and ts_ms < since_ms:
            raise Replayed(
                f"batch on {key!r} signed {(since_ms - ts_ms) / 1000:.3f} s before this "
                "side began reading (replayed, or the platform's clock stepped back)"
            )
        for old in [s for s, t in self._seen.items() if now_ms - t > self._skew_ms]:
            del self._seen[old]
        if sig in self._seen:
            raise Replayed(f"batch on {key!r} seen before")
        self._seen[sig] = ts_ms
        return data


_WATCH = b"dyknow-watch-v1\x00"
_WATCH_ANSWER = b"dyknow-watch-v1 answer\x00"
_WATCH_FIELDS = frozenset(("v", "watch", "fed", "platform", "ts_ms", "nonce", "sig"))
_WATCH_ANSWER_FIELDS = frozenset(("v", "watching", "lease_s", "ts_ms", "sig"))


def watch_request(keys: KeyPair, federation: str, *, clock: Clock = time.time) -> bytes:
    """A signed request from a platform's owner to see what is addressed to it (a lease).

    Signed with the platform's own key: only who holds the private key can ask.
    """
    ts = int(clock() * 1000)
    nonce = os.urandom(_NONCE_BYTES)
    sig = keys.sign(_watch_transcript(federation, keys.platform, ts, nonce))
    return _dumps(
        {
            "v": WIRE_VERSION,
            "watch": "lease",
            "fed": federation,
            "platform": keys.platform,
            "ts_ms": ts,
            "nonce": _b64(nonce),
            "sig": _b64(sig),
        }
    )


def watch_answer(
    keys: KeyPair, federation: str, nonce: bytes, lease_s: float, *, clock: Clock = time.time
) -> bytes:
    """The platform's answer to an accepted watch request of ``nonce``: its signed time.

    The owner reads, from the platform's own clock, when it began listening (`watch_time`).
    """
    ts = int(clock() * 1000)
    sig = keys.sign(_watch_answer_transcript(federation, keys.platform, ts, nonce))
    return _dumps(
        {"v": WIRE_VERSION, "watching": True, "lease_s": lease_s, "ts_ms": ts, "sig": _b64(sig)}
    )


def watch_time(public_key: bytes, federation: str, request: bytes, answer: bytes) -> float | None:
    """The platform's time (POSIX s) it signed into its answer to the watch ``request``.

    None for a bare ``{"v":1,"watching":true,...}`` (a platform of an older release, or
    anyone answering in its place); an AuthenticationError when the answer carries a time
    not signed with ``public_key`` over this request's nonce (forged, or replayed).
    """
    if len(answer) > MAX_HANDSHAKE_BYTES:
        raise Malformed(f"watch answer of {len(answer)} bytes exceeds {MAX_HANDSHAKE_BYTES}")
    try:
        msg = _loads(answer)
        asked = _loads(request)
        nonce = _unb64(asked["nonce"], _NONCE_BYTES)
        platform = asked["platform"]
    except (_JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise Malformed(f"watch answer: {exc}") from None
    if type(msg) is not dict or msg.get("watching") is not True:
        raise Malformed("a watch answer is a JSON object with 'watching': true")
    if "ts_ms" not in msg and "sig" not in msg:
        return None
    if msg.keys() != _WATCH_ANSWER_FIELDS:
        raise Malformed(
            "a signed watch answer has exactly the fields v, watching, lease_s, ts_ms, sig"
        )
    # every field checked before the transcript: its packing must not fail on an
    # answer's bytes (anyone may answer the watch query)
    if type(msg["v"]) is not int or msg["v"] != WIRE_VERSION:
        raise Malformed(f"unsupported watch answer version {msg['v']!r} (this side speaks 1)")
    lease = msg["lease_s"]
    if type(lease) not in (int, float) or not 0 < lease < float("inf"):
        raise Malformed("watch answer field 'lease_s' must be a positive number")
    ts = msg["ts_ms"]
    if type(ts) is not int or not 0 <= ts < 2**63:
        raise Malformed("watch answer field 'ts_ms' must be an integer in 0..2^63-1")
    try:
        sig = _unb64(msg["sig"], 64)
    except ValueError as exc:
        raise Malformed(f"watch answer field 'sig': {exc}") from None
    try:
        VerifyKey(public_key).verify(_watch_answer_transcript(federation, platform, ts, nonce), sig)
    except (CryptoError, ValueError):
        raise Forged("watch answer not signed by the platform over this request") from None
    return float(ts) / 1000


class WatchGate:
    """The platform's side of watch requests: checks them, cheapest first, then the signature.

    A request is accepted when it names this federation and platform, is fresh (``skew``),
    was not seen before, and is signed with this platform's own key. At most ``verify_rate``
    signatures are checked per second (a flood of forged requests costs a counter each).
    """

    def __init__(
        self,
        keys: KeyPair,
        federation: str,
        *,
        policy: SecurityPolicy = _DEFAULT_POLICY,
        clock: Clock = time.time,
        verify_rate: float = 10.0,
    ) -> None:
        self.keys = keys
        self.federation = federation
        self.policy = policy
        self._clock = clock
        self._verify = VerifyKey(keys.public_key)
        self._seen: dict[bytes, int] = {}
        self._rate = verify_rate
        self._tokens = verify_rate
        self._stamp = clock()

    def check(self, data: bytes | str) -> bytes:
        """Accept a watch request (its nonce, to answer), or raise an AuthenticationError."""
        if len(data) > MAX_HANDSHAKE_BYTES:
            raise Malformed(f"watch request of {len(data)} bytes exceeds {MAX_HANDSHAKE_BYTES}")
        try:
            msg = _loads(data)
        except _JSONDecodeError as exc:
            raise Malformed(f"watch request is not JSON: {exc}") from None
        if type(msg) is not dict or msg.keys() != _WATCH_FIELDS:
            raise Malformed("a watch request is a JSON object with exactly the fields of wire.md")
        if msg["v"] != WIRE_VERSION or msg["watch"] != "lease":
            raise Malformed("unsupported watch request (this side speaks v 1, 'lease')")
        if msg["fed"] != self.federation or msg["platform"] != self.keys.platform:
            raise Misdirected("watch request for another federation or platform")
        ts = msg["ts_ms"]
        if type(ts) is not int:
            raise Malformed("watch field 'ts_ms' must be an integer")
        now = self._clock()
        if abs(now * 1000 - ts) > self.policy.skew * 1000:
            raise Expired("watch request outside the allowed clock skew")
        try:
            nonce = _unb64(msg["nonce"], _NONCE_BYTES)
            sig = _unb64(msg["sig"], 64)
        except ValueError as exc:
            raise Malformed(f"watch request: {exc}") from None
        if nonce in self._seen:
            raise Replayed("watch request seen before")
        tokens = min(self._rate, self._tokens + (now - self._stamp) * self._rate)
        self._stamp = now
        if tokens < 1:
            self._tokens = tokens
            raise Expired("too many watch requests: not checked")
        self._tokens = tokens - 1
        transcript = _watch_transcript(self.federation, self.keys.platform, ts, nonce)
        try:
            self._verify.verify(transcript, sig)
        except CryptoError:
            raise Forged("watch request not signed with this platform's key") from None
        stale = int((now - 2 * self.policy.skew) * 1000)
        for old in [n for n, t in self._seen.items() if t < stale]:
            del self._seen[old]
        self._seen[nonce] = ts
        return nonce


def _watch_answer_transcript(fed: str, platform: str, ts: int, nonce: bytes) -> bytes:
    return _WATCH_ANSWER + _lp(fed) + _lp(platform) + _U64.pack(ts) + nonce


def _watch_transcript(fed: str, platform: str, ts: int, nonce: bytes) -> bytes:
    return _WATCH + _lp(fed) + _lp(platform) + _U64.pack(ts) + nonce
