"""The sample batch wire format: what an export publishes and an import reads.

A batch is a msgpack map ``{"v": 1, "s": label, "q": seq, "b": [[v, tv, ta]…]}`` with
the optional ``"h"`` (history kept), ``"r"`` (resent) and ``"e"`` (why the sender ended
the export); ``docs/wire.md`` ("Sample batches") is the contract and
``docs/test-vectors.json`` pins the bytes.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import dataclasses
import re
import threading
from enum import Enum
from typing import Any, NamedTuple

import msgpack

from dyknow_core import RawSample

__all__ = [
    "BATCH_VERSION",
    "Batch",
    "check_semantic_label",
    "pack_batch",
    "read_batch",
    "unpack_batch",
]

BATCH_VERSION = 1

# A semantic label becomes key chunks: no wildcard or MQTT-special characters, no spaces.
_LABEL = re.compile(r"^[^\s/*$?#+\x00-\x1f\x7f]+(?:/[^\s/*$?#+\x00-\x1f\x7f]+)*$")
_MAX_LABEL = 256
_packb = msgpack.packb
_unpackb = msgpack.unpackb
# A packer per thread, made once: `msgpack.packb` makes one (and its buffer) per call, a
# good part of packing a batch of one sample; a packer shared between threads is not safe.
_packers = threading.local()
# A packer's buffer starts at 256 KiB and keeps the size of its largest body: a packer
# that packed more is dropped, so one large batch does not hold its memory for good.
_PACKER_KEPT_BYTES = 256 * 1024


def check_semantic_label(label: str) -> str:
    """Check that a semantic label can travel as key chunks, and return it."""
    if not isinstance(label, str) or len(label) > _MAX_LABEL or not _LABEL.fullmatch(label):
        long = isinstance(label, str) and len(label) > 64  # not echoed whole into a reply
        shown = repr(label[:64] + "…") if long else repr(label)
        raise ValueError(
            f"semantic label {shown} must be 1-{_MAX_LABEL} characters, '/'-separated "
            "non-empty chunks without spaces or any of * $ ? # +"
        )
    return label


def _encode_value(obj: Any) -> Any:
    """What msgpack cannot carry itself, as something it can (else TypeError)."""
    if isinstance(obj, Enum):
        return obj.value
    if isinstance(obj, set | frozenset):
        return list(obj)
    dump = getattr(obj, "model_dump", None)
    if callable(dump):  # a pydantic model
        return dump(mode="json")
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    raise TypeError(f"a {type(obj).__name__} value cannot travel in a sample batch")


def pack_batch(
    semantic_label: str,
    samples: list[RawSample],
    seq: int = 0,
    *,
    history: int = 0,
    recovered: bool = False,
    ended: str | None = None,
) -> bytes:
    """The msgpack body of one batch: ``{"v": 1, "s": label, "q": seq, "b": [[v, tv, ta]…]}``.

    ``history`` (the sender keeps that many samples to resend) adds ``"h"``; a batch
    resent from that history is marked ``"r": true``; the last batch of an export the
    sender ended by itself (its lease expired) carries the reason as ``"e"``.
    """
    obj: dict[str, Any] = {"v": BATCH_VERSION, "s": semantic_label, "q": seq, "b": samples}
    if history:
        obj["h"] = history
    if recovered:
        obj["r"] = True
    if ended is not None:
        obj["e"] = ended
    try:
        packer = _packers.batch
    except AttributeError:
        packer = _packers.batch = msgpack.Packer(default=_encode_value)
    # the same bytes as ``_packb(obj, default=_encode_value)``
    try:
        body: bytes = packer.pack(obj)
    except BaseException:
        # msgpack empties it, but its buffer stays as large as what it wrote before failing
        del _packers.batch
        raise
    if len(body) > _PACKER_KEPT_BYTES:
        del _packers.batch
    return body


class Batch(NamedTuple):
    """A batch as read: label, first sequence number, samples, history, resent, end reason."""

    label: str
    seq: int | None
    samples: list[Any]
    history: int = 0
    recovered: bool = False
    ended: str | None = None


def read_batch(body: bytes) -> Batch:
    """Read a batch body with all its fields; ValueError when it is not a batch of version 1.

    The samples themselves are checked by whoever uses them (each should be
    ``[value, valid_ns, available_ns]``).
    """
    try:
        obj = _unpackb(body, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several kinds on bad input
        raise ValueError(f"not msgpack: {type(exc).__name__}: {exc}") from None
    if type(obj) is not dict:
        raise ValueError("a batch is a msgpack map")
    v = obj.get("v")
    if type(v) is not int or v != BATCH_VERSION:
        raise ValueError(f"unsupported batch version {v!r} (this side reads {BATCH_VERSION})")
    label = obj.get("s")
    samples = obj.get("b")
    seq = obj.get("q")
    if type(label) is not str or type(samples) is not list:
        raise ValueError("a batch needs 's' (a string) and 'b' (an array)")
    if seq is not None and (type(seq) is not int or seq < 0):
        raise ValueError("'q' must be a non-negative integer")
    history = obj.get("h", 0)
    if type(history) is not int or history < 0:
        raise ValueError("'h' must be a non-negative integer")
    recovered = obj.get("r", False)
    if type(recovered) is not bool or (recovered and seq is None):
        raise ValueError("'r' must be a boolean, and a resent batch needs 'q'")
    ended = obj.get("e")
    if ended is not None and (type(ended) is not str or len(ended) > 1024):
        raise ValueError("'e' must be a string (why the sender ended the export)")
    return Batch(label, seq, samples, history, recovered, ended)


def unpack_batch(body: bytes) -> tuple[str, int | None, list[Any]]:
    """Read a batch body: ``(semantic label, first sequence number or None, samples)``.

    Raises ValueError when it is not a batch of version 1 (see `read_batch`).
    """
    batch = read_batch(body)
    return batch.label, batch.seq, batch.samples


def check_sample(sample: RawSample) -> None:
    """Raise TypeError, ValueError or OverflowError when ``sample`` cannot travel in a batch."""
    _packb(sample, default=_encode_value)
