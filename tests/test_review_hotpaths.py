"""Hot paths made faster decide as before: attacked where they stand in for slower checks.

An agent identifier checked in plain Python against pydantic's pattern; one
conversation's answers gathered by two waiters at once.
"""

from __future__ import annotations

import asyncio

import orjson
import pytest
from pydantic import ValidationError

from agents import ACLMessage, Agent, AgentPlatform, MemoryHub, MessageError
from agents import Performative as P

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
