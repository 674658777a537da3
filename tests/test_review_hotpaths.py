"""Hot paths made faster decide as before: attacked where they stand in for slower checks.

An agent identifier checked in plain Python against pydantic's pattern.
"""

from __future__ import annotations

import orjson
import pytest
from pydantic import ValidationError

from agents import ACLMessage, MessageError
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
