"""Atheris harness: raw envelopes into the Interface Agent's receive loop (``fuzz/README.md``).

Run: ``.venv/bin/python fuzz/fuzz_interface.py -runs=20000 [corpus_dir]`` (libFuzzer
options apply). The first byte of each input picks what the rest becomes: the envelope
itself, the body of a correctly sealed envelope, the content of a sealed ACL message,
or a one-byte change to a real envelope; the last two again in the binary form of the
envelope (a msgpack array, its body raw bytes). A `Crash` (an escaped exception, a dead receive
task, a decision not recorded within 5 s) ends the run with the input saved.
"""

from __future__ import annotations

import sys
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

with atheris.instrument_imports(include=["agents"]):
    from fuzz._harness import run
    from fuzz.targets import InterfaceTarget

PERFORMATIVES = [b"request", b"inform", b"query-ref", b"failure", b"shout", b"", b"cfp"]
# where a campaign starts when its corpus is empty: one input of each mode
SEEDS = [
    b"\x00{}",
    b"\x01not json",
    b'\x02\x00{"x": [1, 2]}',
    b"\x03\x00\x10\x01",
    b"\x04\xff not text",
    b"\x05\x00\x10\x01",
]


def acl(performative: bytes, content: bytes) -> bytes:
    """A message from asker@uav-a to echo@uav-b with the raw JSON ``content``."""
    return (
        b'{"performative":"' + performative + b'","sender":"asker@uav-a",'
        b'"receivers":["echo@uav-b"],"ontology":"demo","reply_with":"r-1","content":'
        + content
        + b"}"
    )


def utf8(data: bytes) -> bytes:
    """``data`` as UTF-8 text: a JSON envelope carries its body as a string."""
    return data.decode("utf-8", "replace").encode()


def payload_of(t: InterfaceTarget, data: bytes) -> bytes:
    """What one fuzzer input stands for (see the module docstring)."""
    if not data:
        return b""
    mode, rest = data[0] % 6, data[1:]
    if mode == 0:
        return rest
    if mode == 1:
        return t.seal(utf8(rest))
    if mode == 2:
        choice = PERFORMATIVES[rest[0] % len(PERFORMATIVES)] if rest else b"request"
        return t.seal(acl(choice, utf8(rest[1:])))
    if mode == 4:  # the binary form's body is bytes: any, not only UTF-8 text
        return t.seal(rest, binary=True)
    good = t.seal(acl(b"inform", b'"x"'), binary=mode == 5)
    if len(rest) < 3:
        return good[: len(rest) * 7]
    i = int.from_bytes(rest[:2], "big") % len(good)
    return good[:i] + bytes([good[i] ^ (rest[2] or 1)]) + good[i + 1 :]


def main() -> None:
    """Run libFuzzer over payloads fed to the interface target."""
    run(atheris, "interface", InterfaceTarget, payload_of, SEEDS)


if __name__ == "__main__":
    main()
