"""ACL messages: parsing, validation, limits, versions, and the not-understood a bad one gets."""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from agents import (
    MAX_MESSAGE_BYTES,
    ACLMessage,
    Agent,
    AgentPlatform,
    HandedOver,
    MemoryHub,
    MessageError,
    MessageTemplate,
    Performative,
    _acl,
    agent_id,
    name_of,
    new_id,
    on,
    platform_of,
)
from agents._acl import compose, nesting_bound, reply_json

P = Performative
BASE: dict[str, Any] = {"performative": "inform", "sender": "a@uav-a", "receivers": ["b@uav-b"]}


def parse(obj: Any) -> ACLMessage:
    return ACLMessage.from_json(orjson.dumps(obj))


def reason(obj: Any) -> str:
    with pytest.raises(MessageError) as err:
        ACLMessage.from_json(obj if isinstance(obj, bytes | str) else orjson.dumps(obj))
    return err.value.reason


# -- the model ---------------------------------------------------------------------------


def test_round_trip_keeps_every_field_and_leaves_unset_ones_out() -> None:
    m = ACLMessage(
        performative=P.REQUEST,
        sender="federation@uav-b",
        receivers=["federation@uav-a"],
        reply_to=["other@uav-b"],
        content={"action": "create-stream", "n": [1, 2.5, None, True]},
        language="json",
        encoding="utf-8",
        ontology="dyknow-federation",
        protocol="fipa-request",
        conversation_id="c-1",
        reply_with="r-1",
        in_reply_to="r-0",
        reply_by=1795000000.5,
    )
    assert ACLMessage.from_json(m.to_json()) == m
    sparse = orjson.loads(ACLMessage(**BASE).to_json())
    assert sparse == {"v": 1, **BASE}


def test_reply_keeps_the_conversation_and_answers_reply_to() -> None:
    m = ACLMessage(
        performative=P.QUERY_REF,
        sender="a@p",
        receivers=["b@q"],
        reply_to=["c@p"],
        ontology="o",
        protocol="fipa-query",
        conversation_id="c-9",
        reply_with="r-9",
    )
    r = m.reply(P.INFORM, 42)
    assert (r.sender, r.receivers, r.in_reply_to) == ("b@q", ["c@p"], "r-9")
    assert (r.conversation_id, r.ontology, r.protocol, r.content) == ("c-9", "o", "fipa-query", 42)
    assert r.reply_with is None


def test_reply_is_the_message_build_makes() -> None:
    m = ACLMessage(
        performative=P.REQUEST,
        sender="a@p",
        receivers=["b@q", "d@q"],
        content={"x": [1]},
        language="json",
        ontology="o",
        protocol="fipa-request",
        conversation_id="c-9",
        reply_with="r-9",
        reply_by=5.0,
    )
    content: Any = {"samples": [[1.5, 2.0, None]], "label": "a/b"}
    for answering in (m, m.model_copy(update={"reply_to": ["c@p"]})):
        for performative, sender in ((P.INFORM, None), (P.REFUSE, "d@q"), ("inform", "b@q")):
            r = answering.reply(performative, content, sender=sender)  # type: ignore[arg-type]
            made = ACLMessage.build(
                performative=performative,
                sender=sender or answering.receivers[0],
                receivers=list(answering.reply_to or [answering.sender]),
                content=content,
                language=answering.language,
                ontology=answering.ontology,
                protocol=answering.protocol,
                conversation_id=answering.conversation_id,
                in_reply_to=answering.reply_with,
            )
            assert (r, r.model_fields_set, r.to_json()) == (
                made,
                made.model_fields_set,
                made.to_json(),
            )
            assert r.content is not content and r.receivers is not answering.receivers
    with pytest.raises(ValidationError):
        m.reply(P.INFORM, sender="not an id")


def test_a_handed_over_content_is_the_reply_s_own_else_it_is_copied_and_checked() -> None:
    """HandedOver: the reply takes the content as it is; a reply built by `build` copies it."""
    m = ACLMessage.build(
        performative=P.QUERY_REF,
        sender="a@p",
        receivers=["b@q"],
        conversation_id="c-9",
        reply_with="r-9",
    )
    content: Any = {"x": {"query_time": 1.5, "samples": [[1, 2.0, 3.0]]}}
    r = m.reply(P.INFORM, HandedOver(content))
    assert r.content is content  # no copy: its maker gave it up
    made = m.reply(P.INFORM, {"x": {"query_time": 1.5, "samples": [[1, 2.0, 3.0]]}})
    assert (r, r.model_fields_set, r.to_json()) == (made, made.model_fields_set, made.to_json())
    # a performative or sender the quick checks leave: `build` decides, as without it
    for performative, sender in (("inform", "b@q"), (P.INFORM, "not an id")):
        try:
            want: Any = m.reply(performative, content, sender=sender)  # type: ignore[arg-type]
        except ValidationError as exc:
            with pytest.raises(ValidationError) as err:
                m.reply(performative, HandedOver(content), sender=sender)  # type: ignore[arg-type]
            assert str(err.value) == str(exc)
            continue
        got = m.reply(performative, HandedOver(content), sender=sender)  # type: ignore[arg-type]
        assert (got, got.model_fields_set) == (want, want.model_fields_set)
        assert got.content is not content


def test_readdressed_is_the_copy_model_copy_makes_with_the_receiver_checked() -> None:
    m = ACLMessage(
        performative=Performative.QUERY_REF,
        sender="a@p",
        receivers=["b@q"],
        content={"action": "get-latest", "labels": ["x"]},
        conversation_id="c-1",
        reply_with="r-1",
        reply_by=1795000000.5,
    )
    got = m.readdressed("c@r", "r-2")
    want = m.model_copy(update={"receivers": ["c@r"], "reply_with": "r-2"})
    assert got == want and got.to_json() == want.to_json()
    assert got.model_fields_set == want.model_fields_set
    assert m.receivers == ["b@q"] and m.reply_with == "r-1"  # the original unchanged
    with pytest.raises(MessageError, match="name@platform"):
        m.readdressed("no-platform", "r-3")
    with pytest.raises(MessageError, match="reply_with"):
        m.readdressed("c@r", 3)  # type: ignore[arg-type]


def test_agent_identifiers() -> None:
    assert agent_id("federation", "uav-a") == "federation@uav-a"
    assert platform_of("federation@uav-a") == "uav-a"
    assert name_of("federation@uav-a") == "federation"
    for bad in ("no-at", "a@", "@p", "a b@p", "a@p/q", "a@p@q"):
        with pytest.raises(MessageError):
            ACLMessage.from_obj({**BASE, "sender": bad})


def test_new_ids_are_unique() -> None:
    ids = {new_id("c") for _ in range(1000)}
    assert len(ids) == 1000
    assert all(i.startswith("c-") for i in ids)


# -- what is refused, and why -----------------------------------------------------------


def test_unknown_performative_is_refused_naming_the_field() -> None:
    r = reason({**BASE, "performative": "shout"})
    assert "performative" in r


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"receivers": []}, "receivers"),
        ({"receivers": "b@uav-b"}, "receivers"),
        ({"sender": None}, "sender"),
        ({"reply_by": "soon"}, "reply_by"),
        # the contract says a number: what a lenient parser would coerce is refused too
        ({"reply_by": "1795000000.5"}, "reply_by"),
        ({"reply_by": True}, "reply_by"),
        ({"reply_by": "nan"}, "reply_by"),
        ({"reply_by": "inf"}, "reply_by"),
        ({"ontology": 5}, "ontology"),
        ({"in_reply_to": ["r-1"]}, "in_reply_to"),
        ({"reply_to": "a@uav-a"}, "reply_to"),
        ({"reply_to": ["nobody"]}, "reply_to"),
        ({"surprise": 1}, "surprise"),
    ],
)
def test_invalid_fields_are_named(change: dict[str, Any], field: str) -> None:
    assert field in reason({**BASE, **change})


def test_reply_by_is_any_finite_json_number() -> None:
    assert ACLMessage.from_obj({**BASE, "reply_by": 1795000000}).reply_by == 1795000000.0
    assert ACLMessage.from_obj({**BASE, "reply_by": 0.5}).reply_by == 0.5
    assert (
        ACLMessage.from_json(
            b'{"performative":"inform","sender":"a@p","receivers":["b@q"],"reply_by":1e3}'
        ).reply_by
        == 1000.0
    )


def test_missing_fields_are_named() -> None:
    obj = dict(BASE)
    del obj["sender"]
    assert "sender" in reason(obj)


@pytest.mark.parametrize("payload", [b"not json", b"\xff\xfe", b"[1, 2]", b"42", b'"inform"'])
def test_what_is_not_a_json_object_is_refused(payload: bytes) -> None:
    assert reason(payload)


@pytest.mark.parametrize("version", [2, 0, "1", True, 1.0, None, [1]])
def test_only_wire_version_1_is_spoken(version: Any) -> None:
    assert "version" in reason({**BASE, "v": version})


def test_a_message_without_version_is_version_1() -> None:
    assert parse(BASE).v == 1


def test_size_limit_counts_bytes_whether_given_bytes_or_str() -> None:
    filler = MAX_MESSAGE_BYTES // 2 + 10
    big = orjson.dumps({**BASE, "content": "é" * filler})  # 2 bytes per character
    assert len(big) > MAX_MESSAGE_BYTES
    assert "exceeds" in reason(big)
    assert "exceeds" in reason(big.decode())
    ok = orjson.dumps({**BASE, "content": "x" * (MAX_MESSAGE_BYTES - 200)})
    assert len(ACLMessage.from_json(ok).content) == MAX_MESSAGE_BYTES - 200  # type: ignore[arg-type]
    with pytest.raises(MessageError):
        ACLMessage.from_json(ok, max_bytes=1000)


def test_deep_nesting_is_refused_with_a_short_reason() -> None:
    deep_json = b'{"performative":"inform","sender":"a@b","receivers":["c@d"],"content":'
    deep_json += b"[" * 5000 + b"]" * 5000 + b"}"
    assert len(reason(deep_json)) < 300
    nested: list[Any] = []
    inner = nested
    for _ in range(3000):
        inner.append([])
        inner = inner[0]
    with pytest.raises(MessageError) as err:
        ACLMessage.from_obj({**BASE, "content": nested})
    assert len(err.value.reason) < 400  # a not-understood carrying it stays small


def test_content_that_is_not_json_cannot_be_built_or_sent() -> None:
    with pytest.raises(ValueError):
        ACLMessage(**BASE, content=b"bytes")
    with pytest.raises(ValueError):
        ACLMessage(**BASE, content={1: "int key"})
    huge = ACLMessage(**BASE, content=2**70)  # a Python int, valid here but not in JSON
    with pytest.raises(MessageError):
        huge.to_json()


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**53), max_value=2**53)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)


@settings(max_examples=60)
@given(content=json_values, perf=st.sampled_from(list(Performative)))
def test_any_json_content_round_trips(content: Any, perf: Performative) -> None:
    m = ACLMessage(performative=perf, sender="a@p", receivers=["b@q"], content=content)
    assert ACLMessage.from_json(m.to_json()) == m


# -- not-understood for what arrives malformed on a platform's inbox -----------------------


class Sink(Agent):
    """Keeps what it gets."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.got: asyncio.Queue[ACLMessage] = asyncio.Queue()

    @on(MessageTemplate())
    async def keep(self, message: ACLMessage) -> None:
        self.got.put_nowait(message)


@contextlib.asynccontextmanager
async def two_platforms() -> AsyncIterator[tuple[AgentPlatform, AgentPlatform, Sink]]:
    hub = MemoryHub()
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        AgentPlatform("uav-a", ta, federation="t") as pa,
        AgentPlatform("uav-b", tb, federation="t") as pb,
    ):
        sink = await pb.add(Sink("sink"))
        yield pa, pb, sink


@pytest.mark.parametrize(
    ("payload", "says"),
    [
        (
            {**BASE, "sender": "sink@uav-b", "receivers": ["x@uav-a"], "performative": "shout"},
            "performative",
        ),
        ({**BASE, "sender": "sink@uav-b", "receivers": ["x@uav-a"], "v": 7}, "version"),
        ({"sender": "sink@uav-b", "receivers": ["x@uav-a"], "reply_with": "r-7"}, "performative"),
    ],
)
async def test_malformed_message_gets_not_understood_saying_why(
    payload: dict[str, Any], says: str
) -> None:
    async with asyncio.timeout(5), two_platforms() as (pa, pb, sink):
        await pb.transport.publish(pa.key("acl"), orjson.dumps(payload))
        answer = await sink.got.get()
        assert answer.performative is P.NOT_UNDERSTOOD
        assert says in str(answer.content)
        assert answer.sender == "ams@uav-a"  # no agent x on uav-a: the platform answers
        assert answer.in_reply_to == payload.get("reply_with")
        assert pa.stats.malformed == 1
        assert pa.running


async def test_not_understood_comes_from_the_addressed_agent_when_it_exists() -> None:
    async with asyncio.timeout(5), two_platforms() as (pa, pb, sink):
        await pa.add(Agent("x"))
        bad = {**BASE, "performative": "shout", "sender": "sink@uav-b", "receivers": ["x@uav-a"]}
        await pb.transport.publish(pa.key("acl"), orjson.dumps(bad))
        answer = await sink.got.get()
        assert (answer.sender, answer.performative) == ("x@uav-a", P.NOT_UNDERSTOOD)


async def test_garbage_without_a_sender_is_counted_and_the_platform_keeps_running() -> None:
    async with asyncio.timeout(5), two_platforms() as (pa, pb, sink):
        probe = await pa.add(Sink("probe"))
        for junk in (b"\x00\x01", b"[]", b'{"sender": 5}', b'{"sender": "no-at-sign"}'):
            await pb.transport.publish(pa.key("acl"), junk)
        # A forged local sender is never answered: the answer would stay inside uav-a.
        forged = {**BASE, "performative": "shout", "sender": "x@uav-a", "receivers": ["y@uav-a"]}
        await pb.transport.publish(pa.key("acl"), orjson.dumps(forged))
        # The inbox is in order: once this arrives, all the junk before it was dealt with.
        good = ACLMessage(performative=P.INFORM, sender="sink@uav-b", receivers=["probe@uav-a"])
        await pb.transport.publish(pa.key("acl"), good.to_json())
        assert (await probe.got.get()) == good
        assert pa.stats.malformed == 5
        assert sink.got.empty() and probe.got.empty()
        assert pa.running


async def test_a_malformed_not_understood_is_not_answered() -> None:
    async with asyncio.timeout(5), two_platforms() as (pa, pb, sink):
        probe = await pa.add(Sink("probe"))
        bad = {**BASE, "performative": "not-understood", "sender": "sink@uav-b", "v": 9}
        await pb.transport.publish(pa.key("acl"), orjson.dumps({**bad, "receivers": ["x@uav-a"]}))
        # Once uav-a has seen the probe it has dealt with the bad message; then once sink
        # sees its own probe, whatever uav-a answered would have arrived before it.
        for target, inbox in ((probe, pa.key("acl")), (sink, pb.key("acl"))):
            mark = ACLMessage(
                performative=P.INFORM, sender="tester@elsewhere", receivers=[target.aid]
            )
            await pb.transport.publish(inbox, mark.to_json())
            assert (await target.got.get()) == mark
        assert sink.got.empty()
        assert pa.stats.malformed == 1


async def test_oversized_message_on_the_inbox_is_refused() -> None:
    async with asyncio.timeout(5), two_platforms() as (pa, pb, sink):
        huge = {
            **BASE,
            "sender": "sink@uav-b",
            "receivers": ["x@uav-a"],
            "content": "x" * MAX_MESSAGE_BYTES,
        }
        await pb.transport.publish(pa.key("acl"), orjson.dumps(huge))
        answer = await sink.got.get()
        assert answer.performative is P.NOT_UNDERSTOOD
        assert "exceeds" in str(answer.content)


# -- the contract (docs/wire.md) names exactly what the code reads -------------------------


def _wire_section(title: str) -> str:
    text = (Path(__file__).resolve().parent.parent / "docs" / "wire.md").read_text()
    return text.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def test_the_wire_document_lists_every_field_and_performative() -> None:
    section = _wire_section("ACL message schema")
    fields = re.findall(r"^\| `([a-z_]+)` \|", section, re.MULTILINE)
    assert fields == list(ACLMessage.model_fields)
    listed = section.split("Performatives (FIPA):", 1)[1].split("\n\n", 1)[0]
    assert re.findall(r"`([a-z-]+)`", listed) == sorted(p.value for p in Performative)


# -- the quick parse of decoded messages -------------------------------------------------------

_scalars = st.none() | st.booleans() | st.integers(-(2**63), 2**63 - 1) | st.floats()
_json = st.recursive(
    _scalars | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3)
    ),
    max_leaves=8,
)
_aid = st.sampled_from(["a@p", "bad", "x@y.z", "", "a@b@c"])
_field_values = {
    "v": st.sampled_from([1, 2, 1.0, True, "1"]) | _json,
    "performative": st.sampled_from(["inform", "request", "shout", "INFORM"]) | _json,
    "sender": _aid | _json,
    "receivers": st.lists(_aid, max_size=3) | _json,
    "reply_to": st.none() | st.lists(_aid, max_size=2) | _json,
    "content": _json,
    "language": st.none() | st.text(max_size=3) | _json,
    "encoding": st.none() | st.text(max_size=3) | _json,
    "ontology": st.none() | st.text(max_size=3) | _json,
    "protocol": st.none() | st.text(max_size=3) | _json,
    "in_reply_to": st.none() | st.text(max_size=3) | _json,
    "conversation_id": st.none() | st.text(max_size=3) | _json,
    "reply_with": st.none() | st.text(max_size=3) | _json,
    "reply_by": st.none() | st.floats() | st.integers() | _json,
    "surprise": _json,
}


@st.composite
def _decoded(draw: st.DrawFn) -> dict[str, Any]:
    names = draw(st.sets(st.sampled_from(sorted(_field_values))))
    obj = {name: draw(_field_values[name]) for name in names}
    # mostly valid messages with one field changed, so every check is reached
    base = {"performative": "inform", "sender": "a@p", "receivers": ["b@q"]}
    return {**base, **obj} if draw(st.booleans()) else obj


@settings(max_examples=400, deadline=None)
@given(_decoded())
def test_the_quick_parse_accepts_and_refuses_as_pydantic_does(obj: dict[str, Any]) -> None:
    """from_parsed: the same message, or the same error, as the full validation."""
    try:
        slow = ACLMessage.from_obj(obj)
    except MessageError as exc:
        with pytest.raises(MessageError) as quick:
            ACLMessage.from_parsed(obj)
        assert str(quick.value) == str(exc)
        return
    quick = ACLMessage.from_parsed(obj)
    assert quick == slow
    assert quick.__dict__ == slow.__dict__
    assert list(quick.__dict__) == list(slow.__dict__)
    assert quick.model_fields_set == slow.model_fields_set
    assert quick.to_json() == slow.to_json()


def _quick_fields_before(obj: dict[str, Any]) -> dict[str, Any] | None:
    """`_quick_fields` as it was before its common case was unrolled (the reference)."""
    fields = dict(_acl._DEFAULTS)
    fields.update(obj)
    if len(fields) != _acl._N_FIELDS:
        return None
    v, performative, sender = fields["v"], fields["performative"], fields["sender"]
    if (
        type(v) is not int
        or v != _acl.WIRE_VERSION
        or (type(performative) is not str and type(performative) is not Performative)
        or (performative := _acl._PERFORMATIVES.get(performative)) is None
        or not _acl._valid_aid(sender)
    ):
        return None
    receivers = _acl._aids(fields["receivers"])
    if not receivers:
        return None
    reply_to = fields["reply_to"]
    if reply_to is not None and (reply_to := _acl._aids(reply_to)) is None:
        return None
    for value in _acl._optional_strs(fields):
        if value is not None and type(value) is not str:
            return None
    reply_by = fields["reply_by"]
    if reply_by is not None and (type(reply_by) is not float or not math.isfinite(reply_by)):
        return None
    fields["performative"] = performative
    fields["receivers"] = receivers
    fields["reply_to"] = reply_to
    return fields


@settings(max_examples=400, deadline=None)
@given(_decoded())
def test_the_quick_fields_are_those_of_the_reference(obj: dict[str, Any]) -> None:
    """_quick_fields: the same fields, in the same order, or None, as the plain version."""
    before = _quick_fields_before(obj)
    now = _acl._quick_fields(obj)
    assert now == before
    if now is not None and before is not None:
        assert list(now) == list(before)
        assert now["receivers"] is not obj["receivers"]  # a copy, as before


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64) | _json.map(orjson.dumps))
def test_the_nesting_bound_counts_brackets_and_braces(data: bytes) -> None:
    """nesting_bound: the count of ``[`` and ``{``, for bytes and for str alike."""
    assert nesting_bound(data) == data.count(b"[") + data.count(b"{")
    text = data.decode("utf-8", "replace")
    assert nesting_bound(text) == text.count("[") + text.count("{")


def _depth(value: Any) -> int:
    """How many dicts and lists deep ``value`` nests (a scalar: 0)."""
    if type(value) is dict:
        return 1 + max(map(_depth, value.values()), default=0)
    if type(value) is list:
        return 1 + max(map(_depth, value), default=0)
    return 0


def test_json_shorter_than_the_shallow_length_nests_less_than_trusted() -> None:
    """A body under _SHALLOW_JSON_BYTES, its brackets left uncounted, cannot nest too deep."""
    half = _acl._SHALLOW_JSON_BYTES // 2
    deepest_short = b"[" * (half - 1) + b"]" * (half - 1)  # the deepest JSON below the length
    assert len(deepest_short) < _acl._SHALLOW_JSON_BYTES
    assert _depth(orjson.loads(deepest_short)) < _acl._TRUSTED_NESTING
    one_deeper = b"[" * half + b"]" * half  # the length itself: no longer surely shallow
    assert _depth(orjson.loads(one_deeper)) >= _acl._TRUSTED_NESTING


_python_content = st.recursive(
    _scalars | st.text(max_size=5) | st.sampled_from([Performative.INFORM, b"x", (1, 2)]),
    lambda inner: (
        st.lists(inner, max_size=3)
        | st.dictionaries(
            # a str subclass as a key too: equal to a str, not one
            st.text(max_size=3) | st.integers(0, 3) | st.just(Performative.INFORM),
            inner,
            max_size=3,
        )
        | st.tuples(inner)
    ),
    max_leaves=8,
)


def _containers(value: Any) -> list[Any]:
    """Every dict and list in ``value``, itself included."""
    if type(value) is dict:
        return [value, *(c for item in value.values() for c in _containers(item))]
    if type(value) is list:
        return [value, *(c for item in value for c in _containers(item))]
    return []


@st.composite
def _built(draw: st.DrawFn) -> dict[str, Any]:
    names = draw(st.sets(st.sampled_from(sorted(_field_values))))
    kw = {name: draw(_field_values[name]) for name in names}
    kw["content"] = draw(_python_content)
    base = {
        "performative": draw(st.sampled_from([Performative.REQUEST, "inform"])),
        "sender": "a@p",
        "receivers": draw(st.sampled_from([["b@q"], ("b@q",)])),
    }
    return {**base, **kw} if draw(st.booleans()) else kw


@settings(max_examples=400, deadline=None)
@given(_built())
def test_the_quick_build_makes_what_pydantic_makes(kw: dict[str, Any]) -> None:
    """ACLMessage.build: the same message, or the same error, as ACLMessage(**fields)."""
    try:
        slow = ACLMessage(**kw)
    except ValidationError as exc:
        with pytest.raises(ValidationError) as quick:
            ACLMessage.build(**kw)
        assert str(quick.value) == str(exc)
        return
    quick = ACLMessage.build(**kw)
    assert repr(quick) == repr(slow)  # repr: NaN in content is not equal to itself
    assert list(quick.__dict__) == list(slow.__dict__)
    assert quick.model_fields_set == slow.model_fields_set
    assert type(quick.performative) is Performative
    if isinstance(kw.get("content"), list | dict):
        assert quick.content is not kw["content"]  # copied, as pydantic copies


@pytest.mark.parametrize("depth", [10, 199, 200, 254, 255, 300])
def test_the_quick_parse_leaves_deep_content_to_pydantic(depth: int) -> None:
    """Content nested past pydantic's limit is refused by from_json and from_parsed alike."""
    content: Any = 1
    for _ in range(depth):
        content = [content]
    obj = {"performative": "inform", "sender": "a@p", "receivers": ["b@q"], "content": content}
    # by hand: orjson writes no more than 254 levels
    data = b'{"performative":"inform","sender":"a@p","receivers":["b@q"],"content":'
    data += b"[" * depth + b"1" + b"]" * depth + b"}"
    try:
        slow = ACLMessage.from_obj(obj)
    except MessageError as exc:
        for quick in (
            lambda: ACLMessage.from_json(data),
            lambda: ACLMessage.from_parsed(orjson.loads(data)),
            lambda: ACLMessage.from_parsed(orjson.loads(data), nesting=depth),
        ):
            with pytest.raises(MessageError) as err:
                quick()
            assert str(err.value) == str(exc)
        return
    assert ACLMessage.from_json(data) == slow
    assert ACLMessage.from_parsed(orjson.loads(data)) == slow


# -- what agents send: Agent.message without build's general checks, to_json without a loop ----


def _as_build_made_it(
    performative: Any, sender: Any, receivers: Any, content: Any, fields: dict[str, Any]
) -> ACLMessage:
    """Agent.message as it was: every field through `ACLMessage.build`."""
    return ACLMessage.build(
        performative=performative,
        sender=sender,
        receivers=[receivers] if isinstance(receivers, str) else list(receivers),
        content=content,
        **fields,
    )


def _outcome(make: Any) -> tuple[str, Any]:
    try:
        return "ok", make()
    except Exception as exc:  # the type and the words the caller sees
        return type(exc).__name__, str(exc)


_str_field = st.none() | st.text(max_size=3) | _json
_agent_fields = {
    **{name: _str_field for name in ("language", "encoding", "protocol", "in_reply_to")},
    **{
        name: _field_values[name]
        for name in ("ontology", "conversation_id", "reply_with", "reply_to", "reply_by", "v")
    },
    "surprise": _json,
    "sender": _aid,  # a keyword Agent.message already sets
}


@st.composite
def _composed(draw: st.DrawFn) -> tuple[Any, ...]:
    performative = draw(
        st.sampled_from([Performative.INFORM, Performative.REQUEST, "inform", "shout", "INFORM"])
        | _json
    )
    sender = draw(_aid)
    receivers = draw(
        _aid | st.lists(_aid, max_size=3) | st.tuples(_aid) | st.integers() | st.none()
    )
    names = draw(st.sets(st.sampled_from(sorted(_agent_fields)), max_size=3))
    fields = {name: draw(_agent_fields[name]) for name in names}
    content = draw(_python_content | st.dictionaries(st.text(max_size=3), _scalars, max_size=4))
    return performative, sender, receivers, content, fields


@settings(max_examples=500, deadline=None)
@given(_composed())
def test_an_agents_message_is_the_message_build_makes(args: tuple[Any, ...]) -> None:
    """compose (Agent.message): the same message as build, or the same error."""
    performative, sender, receivers, content, fields = args
    old = _outcome(lambda: _as_build_made_it(*args))
    new = _outcome(lambda: compose(performative, sender, receivers, content, dict(fields)))
    if old[0] != "ok":
        assert new == old
        return
    assert new[0] == "ok"
    quick, slow = new[1], old[1]
    assert repr(quick) == repr(slow)  # repr: NaN in content is not equal to itself
    assert list(quick.__dict__) == list(slow.__dict__)
    assert quick.model_fields_set == slow.model_fields_set
    assert type(quick.performative) is Performative
    # on the wire: the bytes the old path (build, then to_json's loop) wrote
    assert _outcome(quick.to_json) == _outcome(lambda: _old_to_json(slow))
    if isinstance(content, list | dict):
        assert quick.content is not content  # copied: changing it later changes no message
    # the same header again (a burst): taken as remembered, the same message as build's
    again = compose(performative, sender, receivers, content, dict(fields))
    assert repr(again) == repr(slow)
    assert list(again.__dict__) == list(slow.__dict__)
    assert again.model_fields_set == slow.model_fields_set
    assert _outcome(again.to_json) == _outcome(lambda: _old_to_json(slow))
    assert again.receivers is not quick.receivers  # each message its own list
    if isinstance(content, list | dict):
        assert again.content is not quick.content
    # a copy all through: no dict or list of the content is one of the message's
    given = {id(c) for c in _containers(content)}
    assert not any(
        id(c) in given for c in (*_containers(quick.content), *_containers(again.content))
    )


class _Text(str):
    """A str subclass: equal to the str it spells, not of its exact type."""


def test_a_burst_header_is_taken_again_only_as_it_was_checked() -> None:
    """A header equal to the last one's is not checked again; anything else is, as before."""
    aid, sink = "burst@p", "sink@q"
    fields = {"ontology": "o", "protocol": "x"}
    first = compose(Performative.INFORM, aid, sink, {"seq": 1}, fields)
    fields["ontology"] = "changed"  # the caller's dict, changed after the call
    second = compose(Performative.INFORM, aid, sink, {"seq": 2}, {"ontology": "o", "protocol": "x"})
    assert second.ontology == "o" and second.content == {"seq": 2}
    first.receivers.append("other@r")  # a message's list is its own
    third = compose(Performative.INFORM, aid, sink, {"seq": 3}, {"ontology": "o", "protocol": "x"})
    assert third.receivers == [sink]
    assert third.to_json() == _old_to_json(
        ACLMessage(
            performative="inform",
            sender=aid,
            receivers=[sink],
            content={"seq": 3},
            ontology="o",
            protocol="x",
        )
    )
    # the last message made, written with the header's remembered JSON: as it is now
    fourth = compose(Performative.INFORM, aid, sink, [1, "two"], {"ontology": "o", "protocol": "x"})
    assert fourth.to_json() == _old_to_json(fourth)
    fourth.receivers[0] = "elsewhere@r"
    assert orjson.loads(fourth.to_json())["receivers"] == ["elsewhere@r"]
    fourth.receivers.append("more@r")
    assert fourth.to_json() == _old_to_json(fourth)
    too_big = compose(Performative.INFORM, aid, sink, [2**70], {"ontology": "o", "protocol": "x"})
    with pytest.raises(MessageError, match="content cannot be sent as JSON"):
        too_big.to_json()
    # an equal value of another type goes to build, as it did before the header was met
    odd = {"ontology": _Text("o"), "protocol": "x"}
    built = _outcome(lambda: _as_build_made_it(Performative.INFORM, aid, sink, {"seq": 4}, odd))
    got = _outcome(lambda: compose(Performative.INFORM, aid, sink, {"seq": 4}, dict(odd)))
    assert got[0] == built[0] == "ok"
    assert repr(got[1]) == repr(built[1])
    # a changed field or receiver is a new header: checked, refused as build refuses it
    with pytest.raises(ValidationError):
        compose(Performative.INFORM, aid, sink, None, {"ontology": 5, "protocol": "x"})
    with pytest.raises(ValidationError):
        compose(Performative.INFORM, aid, "no-platform", None, {"ontology": "o"})


class _Key(dict):  # type: ignore[type-arg]
    """A dict subclass whose items and copy say other than it holds."""

    def items(self) -> Any:
        return [("said", 1)]

    def copy(self) -> Any:
        return {"said": 1}


@pytest.mark.parametrize(
    "content",
    [
        {1: "int key"},
        {Performative.INFORM: "str-subclass key"},
        {"k": _Text("str-subclass value")},
        {"k": Performative.INFORM},
        {"k": b"bytes"},
        {"k": (1, 2)},
        {"k": 2**70},
        {"k": math.nan},
        {"k": {"nested": [1, {"deeper": _Text("x")}]}},
        _Key(held=1),
    ],
    ids=repr,
)
def test_a_bursts_content_is_taken_as_build_takes_it(content: Any) -> None:
    """A content following a plain one of the same header (the burst's quick path): the
    message, fields and bytes build gives it, or its error."""
    aid, sink, fields = "content@p", "sink@q", {"ontology": "o"}
    compose(Performative.INFORM, aid, sink, {"plain": 1}, dict(fields))  # the header remembered
    got = _outcome(lambda: compose(Performative.INFORM, aid, sink, content, dict(fields)))
    built = _outcome(lambda: _as_build_made_it(Performative.INFORM, aid, sink, content, fields))
    assert got[0] == built[0]
    if got[0] != "ok":
        assert got == built
        return
    assert repr(got[1]) == repr(built[1])
    # of the same types too (an equal str subclass is no str to the one who reads it)
    assert [(type(k), type(v)) for k, v in got[1].content.items()] == [
        (type(k), type(v)) for k, v in built[1].content.items()
    ]
    assert _outcome(got[1].to_json) == _outcome(lambda: _old_to_json(built[1]))


@pytest.mark.parametrize("how", ["__dict__", "__init__", "__setstate__"])
def test_the_last_composed_message_given_other_fields_is_written_as_it_holds_them(
    how: str,
) -> None:
    """The last message compose made, its fields replaced in place (a frozen model lets
    __dict__ be assigned, __init__ run again, __setstate__ restore): to_json writes what it
    holds now, not the remembered header's JSON of the message it was."""
    aid, sink = "replaced@p", "sink@q"
    compose(Performative.INFORM, aid, sink, {"seq": 1}, {"ontology": "o"})
    last = compose(Performative.INFORM, aid, sink, {"seq": 2}, {"ontology": "o"})
    other = ACLMessage(
        performative="request", sender="x@r", receivers=["y@r"], content={"other": True}
    )
    if how == "__dict__":
        last.__dict__ = dict(other.__dict__)
    elif how == "__init__":
        last.__init__(  # type: ignore[misc]
            performative="request", sender="x@r", receivers=["y@r"], content={"other": True}
        )
    else:
        last.__setstate__(other.__getstate__())
    assert last.receivers == ["y@r"]
    assert last.to_json() == _old_to_json(other)


async def test_an_agent_not_on_a_platform_cannot_make_a_message() -> None:
    agent = Agent("loose")  # its identifier is no name@platform yet
    with pytest.raises(ValidationError):
        agent.message(P.INFORM, "b@q", {"x": 1})


def _old_to_json(message: ACLMessage) -> bytes:
    """to_json as it was: the fields not None, found by a loop over __dict__."""
    try:
        return orjson.dumps({k: v for k, v in message.__dict__.items() if v is not None})
    except orjson.JSONEncodeError as exc:
        raise MessageError(f"content cannot be sent as JSON: {exc}") from exc


@st.composite
def _any_message(draw: st.DrawFn) -> ACLMessage:
    names = draw(st.sets(st.sampled_from(sorted(_every_field))))
    kw = {name: draw(_every_field[name]) for name in names}
    kind = draw(st.sampled_from(["validated", "construct", "copy"]))
    if kind == "construct":  # unvalidated: fields may lack, or be None where required
        return ACLMessage.model_construct(**kw)
    base = {"performative": "inform", "sender": "a@p", "receivers": ["b@q"]}
    try:
        message = ACLMessage(**{**base, **kw})
    except ValidationError:
        message = ACLMessage(**base, content=kw.get("content"))
    if kind == "copy":
        message = message.model_copy(update=kw)
    return message


# every field (and one that is none)
_every_field = {**_agent_fields, **_field_values}


@settings(max_examples=500, deadline=None)
@given(_any_message())
def test_to_json_writes_the_bytes_it_wrote(message: ACLMessage) -> None:
    """The same bytes, or the same error, as before; pydantic's own dump agrees."""
    assert _outcome(message.to_json) == _outcome(lambda: _old_to_json(message))
    if list(message.__dict__) != list(ACLMessage.model_fields):
        return  # a copy updated with a name that is no field: pydantic's dump leaves it out
    try:
        ours = orjson.loads(message.to_json())
        theirs = orjson.loads(message.model_dump_json(warnings=False))
    except (MessageError, ValueError):
        return  # not JSON (a Python int past 64 bits, …), or not dumpable by pydantic
    # (a non-finite float, only in a model_construct, is written null by both)
    if isinstance(ours.get("reply_by"), int):
        # an int reply_by (strict float takes ints) is written exactly; pydantic writes it
        # as a float, which rounds past 2**53: the same JSON number to any reader below it
        ours["reply_by"] = float(ours["reply_by"])
    assert {k: v for k, v in ours.items() if v is not None} == {
        k: v for k, v in theirs.items() if v is not None
    }


def test_long_agent_identifiers_are_checked_each_time_not_remembered() -> None:
    """Identifiers another platform makes up, a message long, do not fill the memory."""
    from agents import _acl

    long = "x" * 100_000 + "@p"
    for i in range(20):
        aid = f"{i}{long}"
        message = ACLMessage.from_json(
            orjson.dumps({"performative": "inform", "sender": aid, "receivers": [aid]})
        )
        assert message.sender == aid
        assert compose(Performative.INFORM, aid, aid, None, {}).receivers == [aid]
    assert sum(len(a) for a in _acl._known_aids) < 4096 * 300
    assert not any(a.endswith(long) for a in _acl._known_aids)


def test_a_reply_written_at_once_is_the_reply_made_and_written() -> None:
    """`reply_json` writes the bytes `reply(...).to_json()` writes, or says None where
    `reply` leaves its checks to pydantic (an answer the lane puts is the loop's answer)."""
    asks = [
        ACLMessage.build(
            performative=P.REQUEST,
            sender="asker@uav-a",
            receivers=["gateway@uav-b"],
            content={"action": "query", "label": "x"},
            ontology="dyknow",
            protocol="fipa-request",
            conversation_id="c-1",
            reply_with="r-1",
        ),
        ACLMessage.build(
            performative=P.QUERY_REF,
            sender="asker@uav-a",
            receivers=["gateway@uav-b"],
            reply_to=["other@uav-c", "more@uav-d"],
            content=None,
            language="json",
        ),
        # every field set (odd but valid values): each written in its place, or left out
        ACLMessage.build(
            performative=P.REQUEST,
            sender="asker@uav-a",
            receivers=["gateway@uav-b"],
            reply_to=["other@uav-c"],
            content={"k": "\u00e9"},
            language="json",
            encoding="utf-8",
            ontology="dyknow-\u2028\u00e9",
            protocol="fipa-query",
            conversation_id="\U0001f600",
            reply_with="",
            in_reply_to="r-0",
            reply_by=1.5e9,
        ),
    ]
    contents: list[Any] = [
        {"label": "x", "samples": [[1.5, 2.0, 3.0]]},
        None,
        ["a", 1, None, {"deep": [True]}],
        "text",
        [math.nan, math.inf, -0.0, 2**63 - 1, "\u2028\U0001f600"],
    ]
    for ask in asks:
        for content in contents:
            made = ask.reply(P.INFORM, content, sender="gateway@uav-b").to_json()
            assert reply_json(ask, P.INFORM, content, "gateway@uav-b") == made
            assert reply_json(ask, P.INFORM, HandedOver(content), "gateway@uav-b") == made
        # what `reply` leaves to pydantic: not written here
        assert reply_json(ask, P.INFORM, (1, 2), "gateway@uav-b") is None
        assert reply_json(ask, P.INFORM, {1: "x"}, "gateway@uav-b") is None
        assert reply_json(ask, P.INFORM, 1, "not an agent id") is None
        assert reply_json(ask, P.INFORM, 1, "") is None
        assert reply_json(ask, "inform", 1, "gateway@uav-b") is None  # type: ignore[arg-type]
        assert reply_json(ask, P.INFORM, 2**70, "gateway@uav-b") is None  # no JSON number


# -- ACLMessage.reply: what build would make, or build's error ------------------------------


def _asked() -> ACLMessage:
    return ACLMessage.build(
        performative=P.REQUEST,
        sender="a@p1",
        receivers=["b@p2"],
        content={"x": 1},
        conversation_id="c-1",
        reply_with="r-1",
        protocol="fipa-request",
        ontology="o",
        language="json",
    )


class _Lying(str):
    """A str that says it equals (and hashes as) an identifier it does not spell."""

    def __eq__(self, other: object) -> bool:
        return True

    def __hash__(self) -> int:
        return hash("b@p2")


@pytest.mark.parametrize("sender", [["b@p2"], {"b": 1}, _Lying("not an aid")])
def test_a_reply_from_a_sender_that_is_no_identifier_is_refused_as_build_refuses(
    sender: object,
) -> None:
    asked = _asked()
    ACLMessage.build(performative=P.INFORM, sender="b@p2", receivers=["a@p1"])  # known now
    with pytest.raises((MessageError, ValueError)) as built:
        ACLMessage.build(
            performative=P.INFORM,
            sender=sender,
            receivers=["a@p1"],
        )
    with pytest.raises(type(built.value)):
        asked.reply(P.INFORM, {"ok": True}, sender=sender)  # type: ignore[arg-type]


def test_a_reply_is_the_message_build_makes() -> None:
    asked = _asked()
    for content in (None, 1, 1.5, "s", [1, [2, {"a": None}]], {"k": [True, {"z": "y"}]}):
        got = asked.reply(P.INFORM, content)
        want = ACLMessage.build(
            performative=P.INFORM,
            sender="b@p2",
            receivers=["a@p1"],
            content=content,
            language="json",
            ontology="o",
            protocol="fipa-request",
            conversation_id="c-1",
            in_reply_to="r-1",
        )
        assert got == want
        assert got.model_fields_set == want.model_fields_set
        assert got.to_json() == want.to_json()


_HOSTILE_AIDS = ["c@z\n", "c\n@z", "c@z\r", "c@z\n\n", "\nc@z", "c@z "]


def _message() -> ACLMessage:
    return ACLMessage(performative=P.INFORM, sender="a@x", receivers=["b@y"], content=1)


@pytest.mark.parametrize("aid", _HOSTILE_AIDS)
def test_a_receiver_pydantic_refuses_is_refused_by_readdressed(aid: str) -> None:
    message = _message()
    with pytest.raises(ValidationError):
        ACLMessage.model_validate({**message.model_dump(), "receivers": [aid]})
    with pytest.raises(MessageError):
        message.readdressed(aid, "r1")


@pytest.mark.parametrize("field", ["sender", "receivers"])
@pytest.mark.parametrize("aid", _HOSTILE_AIDS)
def test_an_identifier_pydantic_refuses_is_refused_by_the_quick_parse(field: str, aid: str) -> None:
    obj = _message().model_dump(mode="json")
    obj[field] = [aid] if field == "receivers" else aid
    with pytest.raises(ValidationError):
        ACLMessage.model_validate(obj)
    with pytest.raises(MessageError):
        ACLMessage.from_json(orjson.dumps(obj))
    with pytest.raises(MessageError):
        ACLMessage.from_parsed(obj, nesting=2)


@pytest.mark.parametrize("tail", ["\n", "\n\n"])
def test_a_name_label_or_endpoint_ending_in_a_newline_is_refused(tail: str) -> None:
    # `$` also matches before a final newline: each check must take the whole text
    from agents import check_name
    from agents.transports import ZenohConfig
    from federation._batch import check_semantic_label

    with pytest.raises(ValueError, match="name"):
        check_name("uav-a" + tail)
    with pytest.raises(ValueError, match="semantic label"):
        check_semantic_label("uav/pos" + tail)
    with pytest.raises(ValueError, match="name"):
        AgentPlatform("uav-a" + tail, MemoryHub().transport())
    with pytest.raises(ValueError, match="endpoint"):
        ZenohConfig(listen=["tcp/127.0.0.1:7447" + tail])
