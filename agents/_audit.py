"""The Interface Agent's audit log: its records, kept, written to a file, rotated."""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import orjson

from ._acl import WIRE_VERSION, ACLMessage, Performative
from ._quote import quoted

# the Interface Agent's logger, whichever of its parts logs: the name operators configure
log = logging.getLogger("agents._interface")


class AuditLog:
    """What the Interface Agent decided about each remote message: kept, written, published.

    The last ``keep`` records stay in memory (`records`); with ``path`` they are appended
    to a JSON-lines file; with a platform they are published in batches on
    ``dyknow/<fed>/v1/audit/<platform>`` (one JSON record per line), so one publish
    carries many records and auditing does not double the transport's load.

    The file holds at most ``max_bytes`` (whole records; one longer record alone): the
    record that would pass it goes to a new file, the full one becomes ``<path>.1``, the
    older ones ``<path>.2`` ... ``<path>.<backups>``, and the oldest beyond is deleted.
    """

    DEFAULT_MAX_BYTES = 64 * 1024 * 1024
    DEFAULT_BACKUPS = 4

    def __init__(
        self,
        *,
        keep: int = 10_000,
        path: str | Path | None = None,
        platform: str | None = None,
        max_bytes: int = DEFAULT_MAX_BYTES,
        backups: int = DEFAULT_BACKUPS,
    ) -> None:
        if max_bytes < 1:
            raise ValueError(f"the audit file's max_bytes must be at least 1, not {max_bytes}")
        if backups < 0:
            raise ValueError(f"the audit file's backups must be 0 or more, not {backups}")
        self.max_bytes = max_bytes
        self.backups = backups
        # each entry a record (a dict), or an accepted message as a tuple (`accepted_entry`):
        # the common record of a flood, made a dict or a JSON line only when read
        self._log: deque[Any] = deque(maxlen=keep)
        self.counts: dict[str, int] = {"accepted": 0, "refused": 0, "dropped": 0}
        self.path = Path(path) if path is not None else None
        self.platform = platform
        # bounded too: records pile up here if nothing flushes them
        self._pending: deque[Any] = deque(maxlen=keep)
        # called when a record comes while none is pending: wakes a flush asleep while idle
        self.wake: Callable[[], None] | None = None
        # the JSON of an accepted record between "ts" and "conversation_id", per
        # (peer, sender, receiver, performative): a platform hears few such combinations
        self._lines: dict[tuple[Any, ...], bytes] = {}

    @property
    def records(self) -> deque[dict[str, Any]]:
        """The last records kept in memory, oldest first (a copy: the log goes on)."""
        log = self._log
        return deque((self._as_dict(e) for e in log), maxlen=log.maxlen)

    def last(self, n: int) -> list[dict[str, Any]]:
        """Copies of the last ``n`` records (none for n <= 0)."""
        entries = list(self._log)[-n:] if n > 0 else []
        return [dict(self._as_dict(e)) for e in entries]

    def record(self, **fields: Any) -> None:
        """Add one decision (``verdict`` is accepted, refused or dropped).

        Every record has the fields of ``docs/wire.md`` (None when unknown), so readers
        of the JSON lines need not guess which ones a kind of refusal leaves out. A
        ``reason`` holding characters that are not printable has them escaped (`quoted`).
        """
        reason = fields.get("reason")
        if type(reason) is str and not reason.isprintable():
            # a reason may echo another platform's words: whatever a site failed to
            # bound, a record's reason holds no raw newline or escape (each escaped, none cut)
            fields["reason"] = quoted(reason, 10 * len(reason))
        rec = self._new_record(**{"verdict": "accepted", **fields})
        self._log.append(rec)
        first = not self._pending  # the first since the flush took them: it may sleep
        self._pending.append(rec)
        if first and self.wake is not None:
            self.wake()  # after the append: a flush woken from another thread finds it
        verdict = rec["verdict"]
        self.counts[verdict] = self.counts.get(verdict, 0) + 1

    def _new_record(self, **fields: Any) -> dict[str, Any]:
        """A record with every field of ``docs/wire.md``, None where ``fields`` say nothing."""
        return {
            "v": WIRE_VERSION,
            "ts": time.time(),
            "platform": self.platform,
            "from": None,
            "sender": None,
            "receivers": None,
            "performative": None,
            "conversation_id": None,
            "verdict": None,
            "reason": None,
            **fields,
        }

    def accepted(self, peer: str, message: ACLMessage, ts: float | None = None) -> None:
        """Record that ``message`` from platform ``peer`` was admitted (at ``ts``, Unix s)."""
        self.add_accepted((accepted_entry(time.time() if ts is None else ts, peer, message),))

    def add_accepted(self, entries: Sequence[tuple[Any, ...]]) -> None:
        """Record admitted messages given as their `accepted_entry` tuples (a batch's at once)."""
        self._log.extend(entries)
        first = not self._pending  # a flush may sleep for want of records
        self._pending.extend(entries)
        if first and self.wake is not None:
            self.wake()  # after the append: a flush woken from another thread finds them
        self.counts["accepted"] += len(entries)

    def _as_dict(self, entry: Any) -> dict[str, Any]:
        """A log entry as its record."""
        if type(entry) is not tuple:
            return entry
        ts, peer, sender, receivers, performative, conversation_id = entry
        return {
            "v": WIRE_VERSION,
            "ts": ts,
            "platform": self.platform,
            "from": peer,
            "sender": sender,
            "receivers": [receivers] if type(receivers) is str else list(receivers),
            "performative": performative,
            "conversation_id": conversation_id,
            "verdict": "accepted",
            "reason": None,
        }

    def _middle(self, key: tuple[Any, ...]) -> bytes:
        """The JSON of an accepted record from "platform" to "performative" (no braces)."""
        lines = self._lines
        if len(lines) >= _MAX_AUDIT_LINES:
            lines.clear()
        peer, sender, receiver, performative = key
        middle = orjson.dumps(
            {
                "platform": self.platform,
                "from": peer,
                "sender": sender,
                "receivers": [receiver],
                "performative": performative,
            }
        )[1:-1]
        if len(middle) <= _MAX_AUDIT_LINE:  # a long one (names made up by a peer) is not kept
            lines[key] = middle
        return middle

    def take(self) -> bytes:
        """The records not yet flushed, as JSON lines (empty when none); appended to ``path``."""
        if not self._pending:
            return b""
        pending = list(self._pending)
        self._pending.clear()
        out: list[bytes] = []
        add = out.append
        dumps, lines = orjson.dumps, self._lines
        last_ts, ts_json = None, b""
        last: Any = None  # the last accepted entry pieced together, and its line
        line = b""
        for e in pending:
            if type(e) is tuple:
                if e == last:
                    # the same record again: a batch's messages of one conversation
                    # (equal times make the same JSON, as ``ts_json`` below assumes)
                    add(line)
                    continue
                ts, peer, sender, receivers, performative, conv = e
                if type(receivers) is str:
                    # an accepted message to one agent: its line pieced together, the
                    # same bytes orjson makes of the record (fields in the same order)
                    key = (peer, sender, receivers, performative)
                    middle = lines.get(key) or self._middle(key)
                    if ts != last_ts:  # a batch's records share theirs
                        last_ts, ts_json = ts, dumps(ts)
                    line = (
                        b'{"v":%d,"ts":%b,%b,"conversation_id":%b,"verdict":"accepted",'
                        b'"reason":null}\n'
                        % (WIRE_VERSION, ts_json, middle, b"null" if conv is None else dumps(conv))
                    )
                    add(line)
                    last = e
                    continue
                e = self._as_dict(e)
            add(dumps(e) + b"\n")
        data = b"".join(out)
        if self.path is not None:
            try:
                self._append(self.path, data)
            except OSError as exc:
                # a full disk must not stop the Interface Agent, nor the published audit
                log.warning("audit file %s not written: %s", self.path, exc)
        return data

    def _append(self, path: Path, data: bytes) -> None:
        """Append the JSON lines ``data`` to ``path``, rotating it at ``max_bytes``."""
        fresh = False  # the file was rotated just now: it takes a line whatever its length
        if not path.parent.is_dir():
            # a config's `audit = "audit/<platform>.jsonl"` names a folder nobody made yet
            path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            with path.open("ab") as f:
                size = f.tell()  # the file's end (append mode), whoever wrote or truncated it
                room = self.max_bytes - size
                if len(data) <= room:
                    f.write(data)
                    return
                # the whole lines that fit; the rest goes to the next file
                cut = data.rfind(b"\n", 0, max(room, 0)) + 1
                if not cut and (fresh or not size):
                    cut = data.find(b"\n") + 1 or len(data)  # longer than the bound: alone
                if cut:
                    f.write(data[:cut])
                    data = data[cut:]
                    if not data:
                        return
                # before its name changes: what is written stays written, even on power loss
                f.flush()
                os.fsync(f.fileno())
            self._rotate(path)
            fresh = True

    def _rotate(self, path: Path) -> None:
        """Move ``path`` to ``path.1`` (and each backup one up), and begin it anew.

        Each step is one atomic rename, the oldest last to go (overwritten): a crash
        between two leaves a gap in the numbers, never a record lost.
        """
        names = [path, *(path.with_name(f"{path.name}.{i}") for i in range(1, self.backups + 1))]
        # read before the names change; the highest of all, not the current file's: a
        # crash between the renames and the record leaves a current file without one
        number = max(_rotated_number(n) for n in names) + 1
        if self.backups == 0:
            path.unlink(missing_ok=True)
        for i in range(self.backups, 0, -1):
            with contextlib.suppress(FileNotFoundError):
                os.replace(names[i - 1], names[i])
        previous = names[1].name if self.backups else None
        note = f"audit file rotated at {self.max_bytes} bytes: the records before this one " + (
            f"are in {previous}" if previous else "were deleted (no backups kept)"
        )
        # `previous` names the file as it is now; the next rotation renames it, so the
        # chain is followed by `file`, which no rename changes: file n follows file n - 1
        record = self._new_record(
            reason=note, stage="audit-rotated", previous=previous, file=number
        )
        with path.open("ab") as f:
            f.write(orjson.dumps(record) + b"\n")
        _fsync_dir(path.parent)


def _rotated_number(path: Path) -> int:
    """The ``file`` number of the audit file ``path`` (its rotation record's); 0 without one.

    0 is a file no rotation began: the first one, or a file written by an earlier release.
    """
    try:
        with path.open("rb") as f:
            first = f.readline(_MAX_FIRST_LINE)
    except OSError:
        return 0
    try:
        record = orjson.loads(first)
    except orjson.JSONDecodeError:
        return 0
    if not isinstance(record, dict) or record.get("stage") != "audit-rotated":
        return 0
    number = record.get("file")
    return max(number, 0) if isinstance(number, int) and not isinstance(number, bool) else 0


_MAX_FIRST_LINE = 65536  # bytes read of an audit file's first line: a rotation record is < 1 KB


def _fsync_dir(directory: Path) -> None:
    """Make the renames in ``directory`` durable (where the system allows it)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # e.g. Windows opens no directory: its renames stand as they are
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def accepted_entry(ts: float, peer: str, message: ACLMessage) -> tuple[Any, ...]:
    """The audit log's entry for an accepted message: what its record says, and no more.

    Strings and a float only (one receiver as a str, several as a tuple): the garbage
    collector stops tracking such a tuple, and the message itself is not kept alive.
    """
    receivers = message.receivers
    return (
        ts,
        peer,
        message.sender,
        receivers[0] if len(receivers) == 1 else tuple(receivers),
        _NAMES[message.performative],
        message.conversation_id,
    )


_NAMES = {p: p.value for p in Performative}


_MAX_AUDIT_LINES = 4096
_MAX_AUDIT_LINE = 1024  # bytes of a kept line's middle: 4096 of a message's size would be 1 GiB
