"""Hot paths made faster decide as before: attacked where they stand in for slower checks.

An agent identifier checked in plain Python against pydantic's pattern; one
conversation's answers gathered by two waiters at once.
"""

from __future__ import annotations

import asyncio
from typing import Any

import orjson
import pytest
from pydantic import ValidationError

from agents import ACLMessage, Agent, AgentPlatform, MemoryHub, MessageError, wire_key
from agents import Performative as P

FED = "demo"
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


async def test_two_gathers_of_one_conversation_each_wake_when_their_senders_answered() -> None:
    async with (
        asyncio.timeout(5),
        MemoryHub().transport() as transport,
        AgentPlatform("p", transport, federation="t") as p,
    ):
        a = await p.add(Agent("a"))

        def answer(sender: str) -> ACLMessage:
            return ACLMessage(
                performative=P.INFORM, sender=sender, receivers=[a.aid], conversation_id="c1"
            )

        # no deadline: only the answers (or a close) can end either wait
        with a.conversation("c1", peers=["x@p", "y@p"]) as conv:
            first = asyncio.create_task(conv.gather(["x@p"]))
            second = asyncio.create_task(conv.gather(["y@p"]))
            await asyncio.sleep(0)
            a._deliver(answer("y@p"))
            await asyncio.wait_for(asyncio.shield(second), 1)
            assert not first.done()
            a._deliver(answer("x@p"))
            await asyncio.wait_for(asyncio.shield(first), 1)
            # a close ends every gather still waiting
            third = asyncio.create_task(conv.gather(["z@p"]))
            fourth = asyncio.create_task(conv.gather(["z@p"]))
            await asyncio.sleep(0)
            conv.close()
            await asyncio.wait_for(asyncio.gather(third, fourth), 1)


# -- InterfaceAgent: a lone message's quick parse decides as the full one ------------------


def _deep(levels: int) -> bytes:
    return b"[" * levels + b"1" + b"]" * levels


def _hostile_bodies() -> list[bytes]:
    """Bodies that open (sealed by uav-a) but are no message `_take_now` may take."""
    ok = (
        b'{"performative":"inform","sender":"l@uav-a","receivers":["echo@uav-b"],'
        b'"conversation_id":"c","content":%b}'
    )
    return [
        ok % b"1",  # a good one, for reference
        ok % _deep(198),
        ok % _deep(199),
        ok % _deep(200),
        ok % _deep(260),  # deeper than pydantic takes
        ok % _deep(1100),  # deeper than orjson reads
        b"[1,2,3]",
        b"42",
        b'"inform"',
        b"null",
        ok % b"1" + b" trailing",
        ok % b"1" * 2,
        ok % b"123456789012345678901234567890",  # bigger than 64 bits
        ok % b"1e400",
        ok.replace(b'"sender":"l@uav-a"', b'"sender":"l@uav-a","sender":"x@uav-c"') % b"2",
        ok.replace(b'"sender":"l@uav-a"', b'"sender":"x@uav-c","sender":"l@uav-a"') % b"3",
        ok.replace(b'"l@uav-a"', b"7") % b"4",
        ok.replace(b'["echo@uav-b"]', b'"echo@uav-b"') % b"5",
        ok.replace(b'"l@uav-a"', b'"l@uav-a\\n"') % b"6",
        ok.replace(b'["echo@uav-b"]', b'["echo@uav-b\\n"]') % b"7",
        ok.replace(b'"inform"', b'"INFORM"') % b"8",
        ok.replace(b'"conversation_id":"c"', b'"conversation_id":7') % b"9",
        ok.replace(b'"conversation_id":"c"', b'"v":2') % b"10",
        ok.replace(b'"conversation_id":"c"', b'"v":true') % b"11",
        ok.replace(b'"conversation_id":"c"', b'"extra":1') % b"12",
        ok.replace(b'"conversation_id":"c"', b'"reply_by":"soon"') % b"13",
        ok % b'"\\ud800"',
        ok.replace(b'"l@uav-a"', b'"l@uav-b"') % b"14",  # claims the receiver's platform
        ok.replace(b'"inform"', b'"request"') % b"15",
        ok.replace(b'"conversation_id":"c"', b'"reply_to":["x@uav-c"]') % b"16",
        ok.replace(b'"echo@uav-b"', b'"ghost@uav-b"') % b"17",
        ok % b"2",  # a good one at the end: everything before it was decided
    ]


async def _lone_decisions(
    quick: bool, batchable: bool = False, batched: bool = False
) -> dict[str, Any]:
    """What uav-b decides about the hostile bodies, each alone; ``quick`` False: in full.

    ``batchable``: only those a batch can hold (JSON within orjson's depth, no batch);
    ``batched``: those, in one batch.
    """
    from test_interface import _captured_session, federation, ia, until

    async with federation("uav-a", "uav-b") as fed:
        pair = await _captured_session(fed)
        pa, pb = pair.pa, pair.pb
        ib = ia(pb)
        ib._senders.clear()
        if not quick:
            # `_take_now` takes nothing while mirroring: every message goes through `_take`
            ib.mirroring = True
            ib._mirror_until = float("inf")
        key = wire_key(FED, "acl", "uav-b")
        raw = await fed.raw()
        seal = ia(pa).sessions.seal
        before = len(ib.audit.last(10_000))
        bodies = _hostile_bodies()
        if batchable or batched:
            bodies = [b for b in bodies if _batchable(b)]
        if batched:
            await raw.publish(key, seal("uav-b", b"[" + b",".join(bodies) + b"]"))
        else:
            for body in bodies:
                await raw.publish(key, seal("uav-b", body))
        # one record each, three for the batch of three numbers
        want = len(bodies) + (0 if batchable or batched else 2)
        await until(lambda: len(ib.audit.last(10_000)) - before >= want, "every one decided")
        await asyncio.sleep(0.2)  # the refusals and not-understoods go out
        records = [
            {k: v for k, v in r.items() if k != "ts"} for r in ib.audit.last(10_000)[before:]
        ]
        sender = pb.stats.senders["uav-a"]
        stats = pb.stats
        return {
            "records": records,
            "accepted": sender.accepted,
            "refused": sender.refused,
            "counts": dict(ib.audit.counts),
            "platform": (
                stats.received_remote,
                stats.local,
                stats.forged,
                stats.unknown_receiver,
            ),
        }


def _batchable(body: bytes) -> bool:
    """Whether ``body`` is one JSON value a batch can hold, and no batch itself."""
    try:
        orjson.loads(body)
    except orjson.JSONDecodeError:
        return False
    return not body.startswith(b"[")


async def test_a_lone_hostile_message_is_decided_by_the_quick_parse_as_in_full() -> None:
    quick = await _lone_decisions(quick=True)
    full = await _lone_decisions(quick=False)
    assert quick == full


async def test_hostile_messages_in_a_batch_are_decided_as_each_alone() -> None:
    alone = await _lone_decisions(quick=True, batchable=True)
    together = await _lone_decisions(quick=True, batched=True)
    assert together == alone


# -- global requests: a send that fails partway ---------------------------------------------


@pytest.mark.parametrize("in_turn", [True, False])
async def test_a_global_request_whose_send_fails_still_asks_the_others(in_turn: bool) -> None:
    """In turn (a session held) or in a task: the failure is reported, the rest answer."""
    from test_federation_service import WAIT, altitudes_and_operator_sessions, world

    from agents import TransportError

    async with world() as w:
        op = w["operator"].fed
        channel = await altitudes_and_operator_sessions(w, "uav-a", "uav-b")
        if not in_turn:
            channel.sends_now = lambda platform: False  # type: ignore[method-assign]
        # the link to uav-a fails, both ways a message goes out (awaited, or at once)
        transport = w["operator"].platform.transport
        publish, publish_now = transport.publish, transport.publish_nowait

        async def failing(key: str, payload: bytes, **kw: Any) -> None:
            if key.endswith("/acl/uav-a"):
                raise TransportError("link down")
            await publish(key, payload, **kw)

        def failing_now(key: str, payload: bytes) -> None:
            if key.endswith("/acl/uav-a"):
                raise TransportError("link down")
            publish_now(key, payload)

        transport.publish = failing  # type: ignore[method-assign]
        transport.publish_nowait = failing_now  # type: ignore[method-assign]
        content = {"action": "get-latest", "labels": ["heli-altitude"]}
        result = await op.global_request(content, deadline=WAIT, select="newest")
        assert result.refused == {"uav-a": "unreachable: TransportError: link down"}
        assert sorted(result.answers) == ["uav-b"] and result.no_answer == []


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


# -- get-latest of many labels: one clock reading, no Answer per label ----------------------


async def test_latest_of_many_labels_answers_as_one_latest_per_label() -> None:
    """`latest_contents` gives what `answer_content(latest(label))` gives, label by label."""
    from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, UnknownLabelError
    from federation._gateway_service import answer_content, latest_contents

    t0 = 1_000 * NS_PER_S
    clock = ManualClock(t0)
    async with DyKnowInstance("u", clock=clock) as dk:
        scalar, rich, _, bumped, future = (
            dk.add_source(label) for label in ("s", "r", "e", "b", "f")
        )
        scalar.push(1.5, valid_time=t0 - 5)
        scalar.push(2.5, valid_time=t0 - 9)  # older valid time: not the latest
        rich.push({"pos": (1, 2)}, valid_time=t0 - 1)  # a tuple inside: made JSON
        bumped.push("x")
        bumped.push("y")  # the same clock reading: stamped 1 ns later, seen now
        future.push(7, available_time=t0 + NS_PER_S)  # not known before the clock gets there
        labels = ["s", "r", "e", "b", "f", "s"]
        want = [answer_content(dk.latest(label)) for label in labels]
        assert latest_contents(dk, labels) == want
        # the cases above are what they say
        assert [c["samples"][0][0] if c["samples"] else None for c in want] == [
            1.5,
            {"pos": [1, 2]},
            None,
            "y",
            None,
            1.5,
        ]
        with pytest.raises(UnknownLabelError) as info:
            latest_contents(dk, ["s", "nope"])
        assert info.value.label == "nope"
