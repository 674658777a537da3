"""Atheris harness: raw stream payloads into the import proxy (``fuzz/README.md``).

Run: ``.venv/bin/python fuzz/fuzz_import.py -runs=20000 [corpus_dir]``. The first byte
of each input picks what the rest becomes: the payload itself, the body of a correctly
sealed binary envelope, the samples (msgpack) of a sealed batch of the agreed label, or
a one-byte change to a real envelope. A `Crash` ends the run with the input saved.
"""

from __future__ import annotations

import sys
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

with atheris.instrument_imports(
    include=[
        "federation._batch",
        "federation._import",
        "federation._sequence",
        "agents._security",
    ]
):
    import msgpack

    from federation._batch import pack_batch
    from fuzz._harness import run
    from fuzz.targets import SEM, ImportTarget

# where a campaign starts when its corpus is empty: one input of each mode
SEEDS = [
    b"\x00\x93\x01\x02\x03",
    b"\x01\x80",
    b"\x02" + msgpack.packb([[1.5, 5, 5], ["x", 6, 6]]),
    b"\x03\x00\x10\x01",
]
# a batch map of the agreed label whose "b" (the samples) the fuzzer writes
BATCH_HEAD = b"\x83" + msgpack.packb("v") + b"\x01" + msgpack.packb("s") + msgpack.packb(SEM)


def payload_of(t: ImportTarget, data: bytes) -> bytes:
    """What one fuzzer input stands for (see the module docstring)."""
    if not data:
        return b""
    mode, rest = data[0] % 4, data[1:]
    if mode == 0:
        return rest
    if mode == 1:
        return t.seal(rest)
    if mode == 2:
        return t.seal(BATCH_HEAD + msgpack.packb("b") + rest)
    good = t.seal(pack_batch(SEM, [(1.5, 1, 1)]))
    if len(rest) < 3:
        return good[: len(rest) * 7]
    i = int.from_bytes(rest[:2], "big") % len(good)
    return good[:i] + bytes([good[i] ^ (rest[2] or 1)]) + good[i + 1 :]


def main() -> None:
    """Run libFuzzer over payloads fed to the import target."""
    run(atheris, "import", ImportTarget, payload_of, SEEDS)


if __name__ == "__main__":
    main()
