"""Hostile and bad input: the Interface Agent's and the import proxy's decoders, fuzzed.

Inputs go in where the network puts them: published on the platform's inbox
(``dyknow/demo/v1/acl/uav-b``) or stream keys (``…/stream/uav-b/<sender>/<label>``) of a
MemoryHub, so they reach the real receive loops (``fuzz/targets.py``). Besides random
bytes, JSON and msgpack, inputs are sealed with uav-a's real session keys so that the
garbage inside a *valid* envelope reaches the inner decoders (ACL message, sample batch).

What must hold for every input: no exception escapes a decoder (nothing logged as an
error, no non-authentication error from the envelope check), the receive task lives on,
a decision is recorded within 5 s (never blocks), and the input is counted: one audit
record per envelope, one counted batch per stream payload; a malformed message from an
authenticated sender is answered `not-understood`. After the garbage, a legitimate
request is still answered and a legitimate batch still lands. Each test prints one line
of figures. The atheris harnesses (``fuzz/``) drive the same targets for longer.
"""

from __future__ import annotations

import asyncio
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import orjson
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents import wire_key
from agents._acl import MAX_MESSAGE_BYTES, Performative
from agents._exceptions import Malformed, MessageError
from agents._security import Handshake, SecurityPolicy, SessionTable
from federation._batch import pack_batch
from fuzz.targets import BIG_POLICY, OTHER_SEM, SEM, ImportTarget, InterfaceTarget, keys, trust

ROOT = Path(__file__).resolve().parent.parent
KIB = 1024
# Bounded for the default suite (a few seconds each under the CI profile); FUZZ_EXAMPLES
# raises it for a longer local run.
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "250"))
FUZZ_SETTINGS = settings(
    max_examples=EXAMPLES,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.large_base_example,
    ],
)

# -- value strategies ---------------------------------------------------------------------------

INT64 = st.integers(min_value=-(2**63), max_value=2**64 - 1)
SCALARS = (
    st.none()
    | st.booleans()
    | INT64
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20)
)
JSON = st.recursive(
    SCALARS,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
MSGPACK = st.recursive(
    SCALARS | st.binary(max_size=20) | st.floats(),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.text(max_size=8) | INT64 | st.binary(max_size=4), inner, max_size=4)
    ),
    max_leaves=12,
)
# agents of the sender (uav-a), of the receiver, of a third platform, and no agents at all;
# no other valid platform appears where replies could go (see the report on reply_to)
AIDS = st.sampled_from(
    [
        "asker@uav-a",
        "listener@uav-a",
        "echo@uav-b",
        "df@uav-b",
        "interface@uav-b",
        "nobody@uav-b",
        "spy@uav-c",
        "no at sign",
        "@",
        "a@b@c",
        "",
    ]
)
# mostly agents of the authenticated sender, so most messages get past the impersonation check
SENDERS = st.sampled_from(["asker@uav-a", "listener@uav-a"]) | AIDS | st.text(max_size=12)


def mostly(valid: st.SearchStrategy[Any], other: st.SearchStrategy[Any] = JSON) -> Any:
    """``valid`` three times in four, ``other`` otherwise (one bad field spoils a message)."""
    return st.integers(0, 3).flatmap(lambda i: other if i == 0 else valid)


# any JSON value: a list or map once made the platform's not-understood raise, see
# test_regression_not_understood_for_an_unhashable_performative
PERFORMATIVES = mostly(st.sampled_from([p.value for p in Performative] + ["shout", "", "REQUEST"]))

ACL_SHAPED = st.fixed_dictionaries(
    {
        "performative": PERFORMATIVES,
        "sender": SENDERS,
        "receivers": mostly(st.lists(st.just("echo@uav-b") | AIDS, min_size=1, max_size=3)),
    },
    optional={
        "v": mostly(st.just(1)),
        "reply_to": st.lists(st.sampled_from(["asker@uav-a", "echo@uav-b", "x"]), max_size=2),
        "content": JSON,
        "ontology": mostly(st.sampled_from(["demo", "interface", "dyknow-federation"])),
        "protocol": mostly(st.sampled_from(["fipa-request", "fipa-query"])),
        "conversation_id": mostly(st.text(max_size=10)),
        "reply_with": mostly(st.text(max_size=10)),
        "in_reply_to": mostly(st.text(max_size=10)),
        "reply_by": mostly(st.floats(allow_nan=False, allow_infinity=False)),
        "language": mostly(st.just("json")),
    },
)


def dumps(value: Any) -> bytes:
    """JSON bytes of ``value`` (orjson refuses few values; those become their repr)."""
    try:
        return orjson.dumps(value)
    except (orjson.JSONEncodeError, TypeError):
        return repr(value).encode()


def packb(value: Any) -> bytes:
    """msgpack bytes of ``value`` (integers beyond 64 bits and the like: their repr)."""
    try:
        data: bytes = msgpack.packb(value)
    except (OverflowError, TypeError, ValueError):
        data = repr(value).encode()
    return data


def nested(depth: int, opener: bytes = b"[", closer: bytes = b"]", inner: bytes = b"") -> bytes:
    """``depth`` levels of nesting around ``inner``, closed (valid JSON when the levels are)."""
    return opener * depth + inner + closer * depth


# -- the Interface Agent ------------------------------------------------------------------------


def acl_body(content: bytes, performative: str = "request", sender: str = "asker@uav-a") -> bytes:
    """An ACL message for echo@uav-b whose content is the raw JSON ``content``."""
    head = {
        "performative": performative,
        "sender": sender,
        "receivers": ["echo@uav-b"],
        "ontology": "demo",
        "protocol": "fipa-request",
        "conversation_id": "c-fuzz",
        "reply_with": "r-fuzz",
    }
    return dumps(head)[:-1] + b',"content":' + content + b"}"


def envelope_inputs(t: InterfaceTarget) -> Iterator[tuple[str, bytes]]:
    """The named cases every run includes, whatever hypothesis draws."""
    good = t.seal(acl_body(b'"x"', performative="inform"))
    yield "empty", b""
    yield "deep JSON [ ×100k", b"[" * 100_000
    yield "deep JSON object ×100k", b'{"a":' * 100_000
    yield "envelope just above its limit", b'{"v":1,"body":"' + b"a" * (2 * 256 * KIB + KIB) + b'"}'
    yield (
        "envelope: wrong types",
        dumps(
            {
                "v": "1",
                "from": 1,
                "to": [],
                "sid": {},
                "ts_ms": "x",
                "n": -1,
                "body": 2,
                "mac": None,
            }
        ),
    )
    yield "envelope: floats for integers", dumps({**orjson.loads(good), "n": 1.0, "ts_ms": 1e12})
    yield "envelope: unknown field", dumps({**orjson.loads(good), "extra": 1})
    yield "envelope: huge sid", dumps({**orjson.loads(good), "sid": "s" * (200 * KIB)})
    for cut in (1, len(good) // 2, len(good) - 1):
        yield f"truncated envelope at {cut}", good[:cut]
    yield "sealed: deep JSON [ ×100k", t.seal(b"[" * 100_000)
    yield "sealed: content nested 1000 deep", t.seal(acl_body(nested(1000)))
    yield "sealed: content of dicts 1000 deep", t.seal(acl_body(nested(1000, b'{"a":', b"}", b"1")))
    yield "sealed: body just above 256 KiB", t.seal(acl_body(dumps("x" * MAX_MESSAGE_BYTES)))
    yield "sealed: unknown performative", t.seal(acl_body(b"1", performative="shout"))
    yield "sealed: not JSON", t.seal(b"\x00\x01 not json")
    yield "sealed: a JSON list", t.seal(b"[1,2,3]")
    yield (
        "sealed: wrong types",
        t.seal(dumps({"performative": 7, "sender": ["asker@uav-a"], "receivers": "echo@uav-b"})),
    )
    yield "sealed: integer beyond 64 bits", t.seal(acl_body(b"123456789012345678901234567890"))
    yield "sealed: version 2", t.seal(dumps({**orjson.loads(acl_body(b"1")), "v": 2}))
    yield "sealed: unknown field", t.seal(dumps({**orjson.loads(acl_body(b"1")), "shout": 1}))
    yield "sealed: lone surrogate", t.seal(acl_body(b'"\\ud800"'))
    # the binary form of the envelope: its body raw bytes, not necessarily UTF-8 text
    good_bin = t.seal(acl_body(b'"x"', performative="inform"), binary=True)
    yield "binary: empty array", b"\x90"
    yield "binary: array 32 of 4 G items", b"\xdd\xff\xff\xff\xff"
    yield "binary: deep arrays", b"\x91" * 100_000
    yield "binary: truncated", good_bin[: len(good_bin) // 2]
    yield "binary: a str box", msgpack.packb([*msgpack.unpackb(good_bin)[:6], "box"])
    yield "binary: sealed not UTF-8", t.seal(b"\xff\xfe" + acl_body(b"1"), binary=True)
    yield "binary: sealed request", t.seal(acl_body(b"1"), binary=True)
    big = acl_body(dumps("x" * MAX_MESSAGE_BYTES))
    yield "binary: sealed body just above 256 KiB", t.seal(big, binary=True)
    yield (
        "binary: sealed batch",
        t.seal(b"[" + acl_body(b"1") + b"," + acl_body(b"2") + b"]", binary=True),
    )


@st.composite
def interface_inputs(draw: st.DrawFn) -> tuple[str, Any]:
    """One hostile input, as a recipe: the target seals at feed time (counters move on)."""
    # half of them sealed with uav-a's real keys: garbage that reaches the ACL decoder
    kind = draw(
        st.sampled_from(
            ["raw", "text", "json", "envelope", "field", "truncated", "flip", "sealed"]
            + ["bin-raw", "bin-array", "bin-field", "bin-flip", "bin-sealed"]
            + ["acl"] * 7
            + ["bin-acl"] * 3
        )
    )
    if kind == "raw":
        return kind, draw(st.binary(max_size=400))
    if kind == "text":
        return kind, draw(st.text(max_size=200)).encode("utf-8", "surrogatepass")
    if kind == "json":
        return kind, dumps(draw(JSON))
    if kind == "envelope":
        fields = ["v", "from", "to", "sid", "ts_ms", "n", "body", "mac", "box", "x"]
        keys = draw(st.lists(st.sampled_from(fields), max_size=9, unique=True))
        return kind, dumps({k: draw(JSON) for k in keys})
    if kind == "field":  # a real envelope, one field replaced, removed or added
        name = draw(st.sampled_from(["v", "from", "to", "sid", "ts_ms", "n", "body", "mac", "x"]))
        return kind, (name, draw(st.none() | JSON.map(lambda v: [v])))
    if kind == "truncated":
        return kind, draw(st.floats(min_value=0, max_value=1, exclude_max=True))
    if kind == "flip":
        return kind, (draw(st.floats(0, 1, exclude_max=True)), draw(st.integers(1, 255)))
    if kind == "sealed":  # garbage inside a valid envelope
        return kind, draw(st.binary(max_size=200).map(lambda b: b.decode("latin-1").encode()))
    if kind == "bin-raw":  # bytes after a msgpack array's head: read as a binary envelope
        head = draw(st.sampled_from([b"\x90", b"\x97", b"\x98", b"\x9f", b"\xdc", b"\xdd"]))
        return kind, head + draw(st.binary(max_size=300))
    if kind == "bin-array":
        return kind, msgpack.packb(draw(st.lists(MSGPACK, max_size=9)))
    if kind == "bin-field":  # a real binary envelope, one item replaced
        return kind, (draw(st.integers(0, 6)), draw(MSGPACK))
    if kind == "bin-flip":
        return kind, (draw(st.floats(0, 1, exclude_max=True)), draw(st.integers(1, 255)))
    if kind == "bin-sealed":  # any bytes inside a valid binary envelope (not only text)
        return kind, draw(st.binary(max_size=200))
    if kind == "bin-acl":
        return kind, dumps(draw(ACL_SHAPED))
    return kind, dumps(draw(ACL_SHAPED))


def build_envelope(t: InterfaceTarget, kind: str, data: Any) -> bytes:
    """The bytes of one recipe of `interface_inputs`."""
    if kind in ("raw", "text", "json", "envelope"):
        return bytes(data)
    if kind in ("sealed", "acl"):
        return t.seal(data)
    if kind in ("bin-raw", "bin-array"):
        return bytes(data)
    if kind in ("bin-sealed", "bin-acl"):
        return t.seal(data, binary=True)
    if kind.startswith("bin-"):
        good_bin = t.seal(acl_body(b'"x"', performative="inform"), binary=True)
        if kind == "bin-field":
            items = msgpack.unpackb(good_bin)
            items[data[0]] = data[1]
            return bytes(msgpack.packb(items))
        at, xor = data
        i = int(at * len(good_bin))
        return good_bin[:i] + bytes([good_bin[i] ^ xor]) + good_bin[i + 1 :]
    good = t.seal(acl_body(b'"x"', performative="inform"))
    if kind == "field":
        name, value = data
        env = orjson.loads(good)
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value[0]
        return dumps(env)
    if kind == "truncated":
        return good[: int(data * len(good))]
    at, xor = data
    i = int(at * len(good))
    return good[:i] + bytes([good[i] ^ xor]) + good[i + 1 :]


def test_fuzz_interface_agent_decoding() -> None:
    """Hostile envelopes never crash, block or go uncounted; legitimate requests still work."""
    t = InterfaceTarget()
    try:
        named: dict[str, str] = {}
        for name, payload in envelope_inputs(t):
            named[name] = t.feed(payload)

        @FUZZ_SETTINGS
        @given(interface_inputs())
        def fuzz(recipe: tuple[str, Any]) -> None:
            t.feed(build_envelope(t, *recipe))

        fuzz()
        assert t.request({"after": "garbage"}) == ("inform", {"echo": {"after": "garbage"}})
        t.settle()  # every not-understood promised reached uav-a
        print(t.summary("interface"))
    finally:
        t.close()
    # what the named cases show: nothing a sender cannot be told is answered, and each
    # malformed message of an authenticated sender is
    for name in (
        "deep JSON [ ×100k",
        "envelope just above its limit",
        "truncated envelope at 1",
        "envelope: floats for integers",
        "envelope: huge sid",
    ):
        assert named[name] == "dropped+counted", name
    for name in (
        "sealed: content nested 1000 deep",
        "sealed: content of dicts 1000 deep",
        "sealed: body just above 256 KiB",
        "binary: sealed body just above 256 KiB",  # told alike in either form
        "sealed: unknown performative",
        "sealed: version 2",
        "sealed: unknown field",
    ):
        assert named[name] == "not-understood", name
    # orjson reads an integer beyond 64 bits as a float: a valid (if rounded) message
    assert named["sealed: integer beyond 64 bits"] == "accepted"
    assert named["sealed: not JSON"] == "dropped+counted"  # no sender to tell: counted only
    for name in (
        "binary: empty array",
        "binary: array 32 of 4 G items",
        "binary: deep arrays",
        "binary: truncated",
        "binary: a str box",
        "binary: sealed not UTF-8",  # authentic, but no message to read a sender from
    ):
        assert named[name] == "dropped+counted", name
    assert named["binary: sealed request"] == named["binary: sealed batch"] == "accepted"
    stats = t.platform.stats
    assert stats.unauthenticated == t.unauthentic  # each one counted by the platform
    assert stats.malformed >= t.outcomes["not-understood"]
    # agents answer not-understood too (an accepted message they cannot handle)
    assert t.answers["not-understood"] >= t.outcomes["not-understood"]


def test_regression_not_understood_for_an_unhashable_performative() -> None:
    """A malformed message whose performative is a list is still answered not-understood.

    Found by this fuzz: agents/_platform.py's ``_not_understood`` hashed the performative
    (``obj.get("performative") in NEVER_ANSWERED``: TypeError for a list or map), so the
    sender was never told and the platform logged an error per such message.
    """
    t = InterfaceTarget()
    try:
        for performative in (["request"], {"a": 1}):
            body = dumps(
                {
                    "performative": performative,
                    "sender": "listener@uav-a",
                    "receivers": ["echo@uav-b"],
                    "conversation_id": "c-unhashable",
                }
            )
            assert t.feed(t.seal(body)) == "not-understood"
        t.settle()
    finally:
        t.close()


def test_regression_a_failure_reply_to_a_frozen_platform_does_not_block_the_inbox() -> None:
    """An authenticated peer must not stall uav-b's inbox by where it asks replies to go.

    A message for an agent uav-b does not have, with ``reply_to`` naming an agent of a
    trusted platform that does not answer (frozen, partitioned; over MQTT, any absent
    one: its queries wait their timeout), makes the platform answer ``failure`` there.
    Found by this fuzz: that answer was sent from inside the Interface Agent's receive
    loop, which then waited the whole key exchange (``handshake_timeout``, 2 s) per such
    message, serving nobody else meanwhile (agents/_platform.py now answers in the
    background).
    """
    t = InterfaceTarget()
    # a key exchange far longer than any stall of a busy machine: an inbox that waited for
    # uav-c would answer after it, not merely a little late
    t.ia.handshake_timeout = 60.0
    try:
        frozen = asyncio.Event()

        async def never(key: str, payload: bytes) -> bytes | None:
            await frozen.wait()  # uav-c: trusted, its queryable declared, never answering
            return None

        t.loop.run_until_complete(t.raw.serve(wire_key("demo", "kx", "uav-c"), never))
        body = dumps(
            {
                "performative": "inform",
                "sender": "asker@uav-a",
                "receivers": ["nobody@uav-b"],
                "reply_to": ["x@uav-c"],
                "reply_with": "r-stall",
            }
        )
        assert t.feed(t.seal(body)) == "accepted"
        started = time.monotonic()
        assert t.request("still served?") == ("inform", {"echo": "still served?"})
        assert time.monotonic() - started < t.timeout / 2, "the inbox waited for uav-c"
        frozen.set()
    finally:
        t.close()


def test_regression_an_unhandled_message_does_not_crash_the_interface_agent() -> None:
    """interface@uav-b answers not-understood to what it has no handler for, and lives on.

    Found by the fuzz: the query handler was named ``_answer``, hiding ``Agent._answer``,
    which ``Agent._unhandled`` calls with three arguments, so any unhandled message (an
    ``inform`` in another ontology, from any authenticated peer: access control admits
    it, it starts no conversation) raised TypeError in the agent's receive loop and the
    agent crashed. The handler is ``_answer_query`` now.
    """
    t = InterfaceTarget()
    try:
        body = dumps(
            {
                "performative": "inform",
                "sender": "asker@uav-a",
                "receivers": ["interface@uav-b"],
                "ontology": "demo",
                "content": 1,
            }
        )
        assert t.feed(t.seal(body)) == "accepted"
        assert t.request("after") == ("inform", {"echo": "after"})  # the loop has run on
        t._check(body)  # the agent's crash, if any, is logged by now
        assert t.answers["not-understood"] == 1
    finally:
        t.close()


def test_a_binary_body_over_the_limit_is_refused_before_decoding() -> None:
    """A sealed batch body over 256 KiB is refused as malformed, encrypted or not."""
    for encrypt in (False, True):
        # the sender may seal more than the receiver accepts: its own policy is larger
        policy = SecurityPolicy(max_body_bytes=BIG_POLICY.max_body_bytes, encrypt=encrypt)
        hs_a = Handshake(keys("uav-a"), trust(), policy=policy)
        # the receiver takes both forms (the default refuses plain ones before their size)
        either = SecurityPolicy(require_encryption=False)
        hs_b = Handshake(keys("uav-b"), trust(), policy=either)
        a = SessionTable("uav-a", trust(), policy=policy)
        b = SessionTable("uav-b", trust(), policy=either)
        reply, session = hs_b.respond(hs_a.initiate("uav-b"))
        a.add(hs_a.finish(reply))
        b.add(session)
        largest = b"x" * MAX_MESSAGE_BYTES
        assert b.open_bytes(a.seal_bytes("uav-b", largest)) == ("uav-a", largest)
        too_big = r"binary body of 2621\d\d bytes exceeds the limit of 262144"
        with pytest.raises(Malformed, match=too_big):
            b.open_bytes(a.seal_bytes("uav-b", largest + b"x"))


def test_sealing_a_body_that_is_not_utf8_names_the_problem() -> None:
    """Bytes that are not UTF-8 (or a str with a lone surrogate) cannot be sealed: clear error.

    Found by the atheris harness: ``Session.seal`` raised a bare UnicodeDecodeError.
    """
    t = InterfaceTarget()
    try:
        for body in (b"\xa9 not utf-8", "\ud800"):
            with pytest.raises(MessageError, match="message body is not UTF-8 text"):
                t.table.seal("uav-b", body)
        assert t.feed(t.seal(b"ok, but not JSON")) == "dropped+counted"
    finally:
        t.close()


# -- the import proxy ----------------------------------------------------------------------------


def batch_inputs(t: ImportTarget) -> Iterator[tuple[str, bytes, str | None]]:
    """The named cases every run includes: ``(name, payload, key or None)``."""
    good = t.seal(pack_batch(SEM, [(1.5, 1, 1)]))
    yield "empty", b"", None
    yield "deep msgpack ×100k", b"\x91" * 100_000, None
    yield "sealed: deep msgpack ×100k", t.seal(b"\x91" * 100_000), None
    yield "sealed: deep map ×100k", t.seal(b"\x81\x00" * 100_000 + b"\xc0"), None
    too_big = packb([1, "uav-a", "uav-b", "s", 1, 1, b"x" * 257 * KIB, b"m"])
    yield "envelope just above its limit", too_big, None
    for cut in range(0, len(good), 7):
        yield f"truncated envelope at {cut}", good[:cut], None
    yield "envelope: wrong types", packb([1.0, b"uav-a", "uav-b", 1, "1", -1, "body", 3]), None
    yield "sealed: not msgpack", t.seal(b"\xc1\xc1\xc1"), None
    yield "sealed: truncated batch", t.seal(pack_batch(SEM, [(1, 2, 3)] * 10)[:-3]), None
    yield "sealed: batch version 2", t.seal(packb({"v": 2, "s": SEM, "b": []})), None
    yield "sealed: 's' not a string", t.seal(packb({"v": 1, "s": 5, "b": []})), None
    yield "sealed: negative 'q'", t.seal(packb({"v": 1, "s": SEM, "q": -1, "b": []})), None
    yield "sealed: other label", t.seal(pack_batch(OTHER_SEM, [(1, 1, 1)])), None
    yield (
        "sealed: label never agreed",
        t.seal(pack_batch("unknown", [(1, 1, 1)])),
        t.key(label="unknown"),
    )
    yield "sealed: body above 256 KiB", t.seal(pack_batch(SEM, [("x" * 256 * KIB, 1, 1)])), None
    edge_times = [0, -1, -(2**63), 2**63 - 1, 2**64 - 1]
    values: list[Any] = ["a", None, {}, [], b""]
    samples = [[v, tv, 0] for v, tv in zip(values, edge_times, strict=True)]
    yield "sealed: extreme valid times", t.seal(packb({"v": 1, "s": SEM, "b": samples})), None
    yield (
        "sealed: malformed samples",
        t.seal(packb({"v": 1, "s": SEM, "b": [1, [], [1, 2], [1, "t", 3], [1, 2.0, 3], None]})),
        None,
    )
    yield "sealed: 20k samples", t.seal(pack_batch(SEM, [(0, i, 0) for i in range(20_000)])), None
    yield "sealed, published as uav-c", good, t.key(sender="uav-c")
    yield "replayed", good, None
    forged_from = msgpack.unpackb(good)
    forged_from[1] = "mallory"
    yield "untrusted sender", packb(forged_from), t.key(sender="mallory")
    yield "key without a label", good, t.key(label="").rstrip("/")


@st.composite
def import_inputs(draw: st.DrawFn) -> tuple[str, Any, tuple[str, str] | None]:
    """One hostile stream payload as a recipe, and now and then an odd key."""
    key = draw(
        st.none()
        | st.tuples(
            st.sampled_from(["uav-a", "uav-c", "mallory", "-"]),
            st.sampled_from([SEM, OTHER_SEM, "unknown", "a/b/c", "x" * 300]),
        )
    )
    kind = draw(
        st.sampled_from(
            ["raw", "msgpack", "envelope", "truncated", "flip", "sealed", "body", "batch"]
        )
    )
    if kind == "raw":
        return kind, draw(st.binary(max_size=400)), key
    if kind == "msgpack":
        return kind, packb(draw(MSGPACK)), key
    if kind == "envelope":  # an envelope-shaped array of anything
        return kind, packb(draw(st.lists(MSGPACK, min_size=6, max_size=9))), key
    if kind == "truncated":
        return kind, draw(st.floats(min_value=0, max_value=1, exclude_max=True)), key
    if kind == "flip":
        return kind, (draw(st.floats(0, 1, exclude_max=True)), draw(st.integers(1, 255))), key
    if kind == "sealed":  # garbage inside a valid envelope
        return kind, draw(st.binary(max_size=300)), key
    if kind == "body":  # a batch-shaped map of anything, sealed
        obj = draw(
            st.fixed_dictionaries(
                {},
                optional={
                    "v": st.just(1) | MSGPACK,
                    "s": st.just(SEM) | MSGPACK,
                    "q": st.integers(0, 2**64 - 1) | MSGPACK,
                    "b": st.lists(MSGPACK, max_size=5) | MSGPACK,
                    "x": MSGPACK,
                },
            )
        )
        return kind, packb(obj), key
    sample = st.tuples(MSGPACK, INT64, INT64).map(list) | st.lists(MSGPACK, max_size=4)
    q = draw(st.none() | st.integers(0, 2**64 - 1))
    batch: dict[str, Any] = {"v": 1, "s": SEM, "b": draw(st.lists(sample, max_size=8))}
    if q is not None:
        batch["q"] = q
    return kind, packb(batch), key


def build_batch(t: ImportTarget, kind: str, data: Any) -> bytes:
    """The payload of one recipe of `import_inputs`."""
    if kind in ("raw", "msgpack", "envelope"):
        return bytes(data)
    if kind in ("sealed", "body", "batch"):
        return t.seal(data)
    good = t.seal(pack_batch(SEM, [(1.5, 1, 1)]))
    if kind == "truncated":
        return good[: int(data * len(good))]
    at, xor = data
    i = int(at * len(good))
    return good[:i] + bytes([good[i] ^ xor]) + good[i + 1 :]


def test_fuzz_import_proxy_sample_decoding() -> None:
    """Hostile stream payloads never crash, block or go uncounted; good batches still land."""
    t = ImportTarget()
    try:
        named: dict[str, str] = {}
        for name, payload, key in batch_inputs(t):
            named[name] = t.feed(payload, key=key)
        assert t.legit([1.0, 2.0, 3.0]) == [1.0, 2.0, 3.0]

        @FUZZ_SETTINGS
        @given(import_inputs())
        def fuzz(recipe: tuple[str, Any, tuple[str, str] | None]) -> None:
            kind, data, key = recipe
            t.feed(build_batch(t, kind, data), key=t.key(*key) if key else None)

        fuzz()
        assert t.legit([4.0, 5.0]) == [4.0, 5.0]
        print(t.summary("import"))
    finally:
        t.close()
    for name in (
        "empty",
        "deep msgpack ×100k",
        "sealed: deep msgpack ×100k",
        "sealed: deep map ×100k",
        "envelope just above its limit",
        "envelope: wrong types",
        "sealed: not msgpack",
        "sealed: truncated batch",
        "sealed: batch version 2",
        "sealed: 's' not a string",
        "sealed: negative 'q'",
        "key without a label",
    ):
        assert named[name] == "dropped:malformed", name
    assert all(v == "dropped:malformed" for k, v in named.items() if k.startswith("truncated"))
    assert named["sealed: other label"] == "dropped:wrong-label"
    assert named["sealed, published as uav-c"] == "dropped:wrong-sender"
    assert named["replayed"] == "dropped:replayed"
    assert named["untrusted sender"] == "dropped:untrusted"
    assert named["sealed: label never agreed"] == "unagreed"
    assert named["sealed: malformed samples"] == "samples-dropped"
    assert named["sealed: extreme valid times"] == "injected"
    assert named["sealed: 20k samples"] == "injected"
    # authentic, but larger than any sender may seal: never decoded
    assert named["sealed: body above 256 KiB"] == "dropped:malformed"


# -- atheris -------------------------------------------------------------------------------------


def _atheris_available() -> bool:
    try:
        import atheris  # noqa: F401
    except ImportError:
        return False
    return True


# CPU-bound: 8 s on a core of its own, 63 s beside other tests on a loaded 2-core machine,
# and once 4 000 of its 10 000 runs in 90 s: its wall time is the share of a CPU it gets.
# What it costs is bounded as CPU time (a campaign that spins for good ends there, with its
# output); the wall time only by the test's generous timeout, for one that hangs idle
CAMPAIGN_CPU_SECONDS = 90


@pytest.mark.timeout(480)
@pytest.mark.parametrize("harness", ["fuzz_interface.py", "fuzz_import.py"])
def test_atheris_harness_runs_clean(harness: str, tmp_path: Path) -> None:
    """Each atheris harness runs a bounded coverage-guided campaign without a crash."""
    if not _atheris_available():
        if os.environ.get("CI"):
            pytest.fail("atheris is not installed: pip install -e '.[dev]'", pytrace=False)
        pytest.skip("atheris is not installed (pip install atheris); CI fails instead")
    runs = 10_000
    with subprocess.Popen(
        [sys.executable, str(ROOT / "fuzz" / harness), f"-runs={runs}", "-seed=1", str(tmp_path)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as proc:
        limit = (CAMPAIGN_CPU_SECONDS, CAMPAIGN_CPU_SECONDS)
        resource.prlimit(proc.pid, resource.RLIMIT_CPU, limit)
        try:
            stdout, stderr = proc.communicate(timeout=450)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    out = stdout + stderr
    assert proc.returncode == 0, f"exit {proc.returncode} (-24: over its CPU time)\n{out[-4000:]}"
    assert f"Done {runs} runs" in out, out[-4000:]
    summary = [line for line in out.splitlines() if line.startswith("fuzz ")]
    assert summary, out[-2000:]
    print(summary[-1])
    shutil.rmtree(tmp_path, ignore_errors=True)
