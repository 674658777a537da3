"""FIPA ACL speech acts as JSON: the message model, agent identifiers, parsing with limits."""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import itertools
import math
import operator
import os
import re
from enum import StrEnum
from typing import Annotated, Any

import orjson
from pydantic import BaseModel, ConfigDict, Field, JsonValue, StringConstraints, ValidationError

from ._exceptions import MessageError

WIRE_VERSION = 1
MAX_MESSAGE_BYTES = 256 * 1024

_MAX_WHERE = 120

_AID = re.compile(r"^[A-Za-z0-9_.\-]+@[A-Za-z0-9_.\-]+$")


class Performative(StrEnum):
    """The FIPA communicative acts."""

    ACCEPT_PROPOSAL = "accept-proposal"
    AGREE = "agree"
    CANCEL = "cancel"
    CFP = "cfp"
    CONFIRM = "confirm"
    DISCONFIRM = "disconfirm"
    FAILURE = "failure"
    INFORM = "inform"
    INFORM_IF = "inform-if"
    INFORM_REF = "inform-ref"
    NOT_UNDERSTOOD = "not-understood"
    PROPAGATE = "propagate"
    PROPOSE = "propose"
    PROXY = "proxy"
    QUERY_IF = "query-if"
    QUERY_REF = "query-ref"
    REFUSE = "refuse"
    REJECT_PROPOSAL = "reject-proposal"
    REQUEST = "request"
    REQUEST_WHEN = "request-when"
    REQUEST_WHENEVER = "request-whenever"
    SUBSCRIBE = "subscribe"


def _check_aid(value: str) -> str:
    if not _AID.fullmatch(value):  # `$` alone lets a trailing newline through
        raise ValueError(f"agent identifier {value!r} is not of the form name@platform")
    return value


# A pattern constraint is checked in pydantic's Rust core: ~2 µs a message cheaper than a
# Python validator; from_obj rewrites its error into the friendly form below.
AgentIdStr = Annotated[str, StringConstraints(pattern=_AID.pattern)]
"""An agent identifier on the wire: ``name@platform`` (``federation@uav-a``)."""


def agent_id(name: str, platform: str) -> str:
    """Build and check the identifier of agent ``name`` on ``platform``."""
    return _check_aid(f"{name}@{platform}")


def platform_of(aid: str) -> str:
    """The platform part of an agent identifier."""
    return aid.rpartition("@")[2]


def name_of(aid: str) -> str:
    """The agent-name part of an agent identifier."""
    return aid.rpartition("@")[0]


_ids = itertools.count(1)
_prefix = os.urandom(4).hex()


def new_id(kind: str = "c") -> str:
    """A fresh conversation or reply-with identifier, unique in this process and beyond."""
    return f"{kind}-{_prefix}-{next(_ids)}"


class ACLMessage(BaseModel):
    """One speech act. ``content`` is any JSON value; ``reply_by`` is Unix time in seconds."""

    # defer_build: its validator is built by the first message, not by every import of
    # agents (a node that has started needs it from then on; a tool may never)
    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    v: int = WIRE_VERSION
    performative: Performative
    sender: AgentIdStr
    receivers: Annotated[list[AgentIdStr], Field(min_length=1)]
    reply_to: list[AgentIdStr] | None = None
    content: JsonValue = None
    language: str | None = None
    encoding: str | None = None
    ontology: str | None = None
    protocol: str | None = None
    conversation_id: str | None = None
    reply_with: str | None = None
    in_reply_to: str | None = None
    # a JSON number only: no numeric strings, booleans, NaN or infinities
    reply_by: Annotated[float, Field(strict=True, allow_inf_nan=False)] | None = None

    @classmethod
    def build(cls, **fields: Any) -> "ACLMessage":
        """A new message, as ``ACLMessage(**fields)`` makes it, with the same errors.

        Fields of the exact expected types (str, list of str, content of dicts with str
        keys, lists, str, int, float, bool and None) are checked in plain Python, and the
        content copied as pydantic would: a few µs less per message than pydantic's
        validation, and ~4x less for a large content. Anything else goes to pydantic.
        """
        # ``fields`` is this call's own keyword dict: the copied content may replace the
        # caller's (pydantic, if it still decides, gets an equal value); a keyword that
        # is no field makes _quick_fields say None, and pydantic say which
        if "content" in fields:
            try:
                fields["content"] = _json_copy(fields["content"], 0)
            except _NotPlain:
                return cls(**fields)
        checked = _quick_fields(fields)
        if checked is not None:
            return _constructed(cls, checked, set(fields))
        return cls(**fields)

    def reply(
        self, performative: Performative, content: Any = None, *, sender: str | None = None
    ) -> "ACLMessage":
        """The reply to this message: same conversation, addressed to its reply_to or sender.

        ``content`` is copied and checked, as `build` does, unless it is `HandedOver`.
        """
        sender = sender or self.receivers[0]
        handed_over = type(content) is HandedOver
        if handed_over:
            content = content.value
        # The fields taken from this message were checked when it was made: only the
        # new ones (performative, sender, content) are, here, as `build` checks them; a
        # value the quick checks leave goes to `build`, which decides as before.
        # `type(sender) is str` first: a set lookup would hash (or fail on) anything else
        if (
            type(performative) is Performative
            and type(sender) is str
            and (sender in _known_aids or _valid_aid(sender))
        ):
            try:
                if not handed_over:  # its maker vouches for it: no copy, no check
                    content = _json_copy(content, 0)
            except _NotPlain:
                pass
            else:
                fields = self.__dict__
                receivers = fields["reply_to"] or [fields["sender"]]
                return _constructed(
                    ACLMessage,
                    {
                        "v": WIRE_VERSION,
                        "performative": performative,
                        "sender": sender,
                        "receivers": list(receivers),
                        "reply_to": None,
                        "content": content,
                        "language": fields["language"],
                        "encoding": None,
                        "ontology": fields["ontology"],
                        "protocol": fields["protocol"],
                        "conversation_id": fields["conversation_id"],
                        "reply_with": None,
                        "in_reply_to": fields["reply_with"],
                        "reply_by": None,
                    },
                    set(_REPLY_FIELDS),
                )
        return ACLMessage.build(
            performative=performative,
            sender=sender,
            receivers=list(self.reply_to or [self.sender]),
            content=content,
            language=self.language,
            ontology=self.ontology,
            protocol=self.protocol,
            conversation_id=self.conversation_id,
            in_reply_to=self.reply_with,
        )

    def to_json(self) -> bytes:
        """The message as compact JSON bytes, leaving out unset fields."""
        header = _last_header
        fields = self.__dict__
        # the message `compose` made last of a remembered header, known by the dict of its
        # fields (not by the message alone: __init__, __setstate__ or an assignment to a
        # frozen model's __dict__ give it another, whose fields the header does not write)
        if fields is header.made:
            receivers = fields["receivers"]
            content = fields["content"]
            # its list is its own to change: only an unchanged one is written as remembered
            if content is not None and len(receivers) == 1 and receivers[0] is header.receivers:
                try:
                    return header.prefix + orjson.dumps(content) + header.suffix
                except orjson.JSONEncodeError as exc:
                    raise MessageError(f"content cannot be sent as JSON: {exc}") from exc
        try:
            # the fields are already valid JSON values (content is validated as JsonValue,
            # performative is a str enum): dumping __dict__ skips pydantic's serializer
            # __dict__ holds every field in the model's order (as pydantic, its
            # model_construct and `_constructed` make it): the dict of those not None is
            # put together below without a loop, which is cheaper. Only unvalidated
            # messages (model_construct) can lack a field or leave a required one None.
            v = fields.get("v")
            performative = fields.get("performative")
            sender = fields.get("sender")
            receivers = fields.get("receivers")
            if (
                len(fields) != _N_FIELDS
                or v is None
                or performative is None
                or sender is None
                or receivers is None
            ):
                return orjson.dumps({k: v for k, v in fields.items() if v is not None})
            wire = {"v": v, "performative": performative, "sender": sender, "receivers": receivers}
            if (value := fields["reply_to"]) is not None:
                wire["reply_to"] = value
            if (value := fields["content"]) is not None:
                wire["content"] = value
            if (value := fields["language"]) is not None:
                wire["language"] = value
            if (value := fields["encoding"]) is not None:
                wire["encoding"] = value
            if (value := fields["ontology"]) is not None:
                wire["ontology"] = value
            if (value := fields["protocol"]) is not None:
                wire["protocol"] = value
            if (value := fields["conversation_id"]) is not None:
                wire["conversation_id"] = value
            if (value := fields["reply_with"]) is not None:
                wire["reply_with"] = value
            if (value := fields["in_reply_to"]) is not None:
                wire["in_reply_to"] = value
            if (value := fields["reply_by"]) is not None:
                wire["reply_by"] = value
            return orjson.dumps(wire)
        except orjson.JSONEncodeError as exc:  # e.g. an int beyond 64 bits: valid here, not JSON
            raise MessageError(f"content cannot be sent as JSON: {exc}") from exc

    @classmethod
    def from_json(cls, data: bytes | str, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "ACLMessage":
        """Parse and validate a message; MessageError says what is wrong."""
        size = len(data) if isinstance(data, bytes) else len(data.encode("utf-8", "surrogatepass"))
        if size > max_bytes:
            raise MessageError(f"message of {size} bytes exceeds the limit of {max_bytes}")
        try:
            obj = orjson.loads(data)
        except orjson.JSONDecodeError as exc:
            raise MessageError(f"not JSON: {exc}") from exc
        return cls.from_parsed(obj, nesting=nesting_bound(data))

    @classmethod
    def from_parsed(cls, obj: Any, *, nesting: int | None = None) -> "ACLMessage":
        """Validate an object ``orjson.loads`` returned (only JSON types) as a message.

        The same checks and errors as `from_obj`, but a valid message is checked in plain
        Python and its content is taken as it is: JSON decoding made it a JSON value
        already, and pydantic's JsonValue walk costs ~20 µs per KiB of content. Only its
        depth is left to check (pydantic refuses 255 levels): ``nesting``, a bound the
        caller knows (`nesting_bound` of the decoded bytes), spares that walk. Anything
        the quick checks do not accept goes through `from_obj`, which says what is wrong.
        """
        if type(obj) is dict:
            fields = _quick_fields(obj)  # None for a key that is no field, among others
            if fields is not None and (
                (nesting is not None and nesting < _TRUSTED_NESTING)
                or _nests_less(fields["content"])
            ):
                return _constructed(cls, fields, set(obj))
        return cls.from_obj(obj)

    @classmethod
    def from_obj(cls, obj: Any) -> "ACLMessage":
        """Validate an already-decoded JSON object as a message."""
        if not isinstance(obj, dict):
            raise MessageError(f"a message is a JSON object, not {type(obj).__name__}")
        version = obj.get("v", WIRE_VERSION)
        # `type(...) is int`: True and 1.0 compare equal to 1 but are not version 1
        if type(version) is not int or version != WIRE_VERSION:
            raise MessageError(f"unsupported wire version {version!r} (this side speaks 1)")
        try:
            return cls.model_validate(obj)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err.get("loc", ())) or "message"
            if len(where) > _MAX_WHERE:  # deep content: the path alone could outgrow a reply
                where = where[:_MAX_WHERE] + "…"
            msg = err.get("msg", "invalid")
            if err.get("type") == "string_pattern_mismatch":
                msg = f"agent identifier {err.get('input')!r} is not of the form name@platform"
            raise MessageError(f"field {where!r}: {msg}") from exc
        except RecursionError as exc:
            raise MessageError("content nested too deeply") from exc

    def readdressed(self, receiver: str, reply_with: str | None) -> "ACLMessage":
        """This message for ``receiver`` alone, with its own ``reply_with``; else the same.

        One message sent to many platforms, each its own copy (sealed for its receiver):
        the fields were checked once, only ``receiver`` is (a few µs less than
        ``model_copy``). The content is shared, as ``model_copy`` shares it.
        """
        if type(receiver) is not str or not (receiver in _known_aids or _valid_aid(receiver)):
            raise MessageError(f"agent identifier {receiver!r} is not of the form name@platform")
        if reply_with is not None and type(reply_with) is not str:
            raise MessageError(f"reply_with must be a string, not {type(reply_with).__name__}")
        fields = self.__dict__.copy()
        fields["receivers"] = [receiver]
        fields["reply_with"] = reply_with
        return _constructed(
            type(self), fields, {*self.__pydantic_fields_set__, "receivers", "reply_with"}
        )


_FIELDS = frozenset(ACLMessage.model_fields)
_DEFAULTS: dict[str, Any] = {name: f.default for name, f in ACLMessage.model_fields.items()}
_OPTIONAL_STR = (
    "language",
    "encoding",
    "ontology",
    "protocol",
    "conversation_id",
    "reply_with",
    "in_reply_to",
)
_PERFORMATIVES = {p.value: p for p in Performative}
# fullmatch, as pydantic's pattern matches: `match` takes "a@b\n", whose `$` ends before it
_aid_match = _AID.fullmatch
_new_message = object.__new__
_setattr = object.__setattr__  # as pydantic's model_construct sets a frozen model's state


_TRUSTED_NESTING = 200  # below pydantic's limit of nesting (255): deeper goes to pydantic
# JSON nesting n levels deep opens and closes n brackets: a shorter text nests less than
# _TRUSTED_NESTING, whatever `nesting_bound` counts (brackets in strings count there too)
_SHALLOW_JSON_BYTES = 2 * _TRUSTED_NESTING


def nesting_bound(data: bytes | str) -> int:
    """A bound of how deep JSON ``data`` nests: its opening brackets and braces, counted."""
    if isinstance(data, bytes):
        # one pass in C, about half the time of two counts over a large batch
        return len(data) - len(data.translate(None, b"[{"))
    return data.count("[") + data.count("{")


def _nests_less(content: Any) -> bool:
    """Whether a decoded content nests less than `_TRUSTED_NESTING` levels deep.

    A scalar, or a dict or list of scalars (the common contents), is told in C without
    a walk; anything else is walked (`_shallower`).
    """
    kind = type(content)
    if kind is dict:
        if _all_scalars(map(type, content.values())):
            return True
    elif kind is list:
        if _all_scalars(map(type, content)):
            return True
    else:
        return True  # decoded JSON: a scalar
    return _shallower(content, _TRUSTED_NESTING)


def _shallower(value: Any, limit: int) -> bool:
    """Whether ``value``'s dicts and lists nest less than ``limit`` levels deep."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        kind = type(item)
        if kind is dict:
            children = item.values()
        elif kind is list:
            children = item
        else:
            continue
        if depth >= limit:
            return False
        stack.extend((child, depth + 1) for child in children if type(child) in (dict, list))
    return True


# the slots pydantic's model_construct fills, set through their descriptors (cheaper
# than object.__setattr__ looking each name up)
_set_dict, _set_fields_set, _set_extra, _set_private = (
    BaseModel.__dict__[name].__set__
    for name in (
        "__dict__",
        "__pydantic_fields_set__",
        "__pydantic_extra__",
        "__pydantic_private__",
    )
)


def _constructed(cls: type[ACLMessage], fields: dict[str, Any], names: set[str]) -> ACLMessage:
    """The message with these checked fields, made as pydantic's model_construct makes one."""
    message: ACLMessage = _new_message(cls)
    _set_dict(message, fields)
    _set_fields_set(message, names)
    _set_extra(message, None)
    _set_private(message, None)
    return message


def reply_json(
    message: ACLMessage, performative: Performative, content: Any, sender: str
) -> bytes | None:
    """``message.reply(performative, content, sender=sender).to_json()``, without the reply
    made: its bytes where `ACLMessage.reply`'s quick checks hold; None otherwise (ask it).

    For an answer sent at once and kept nowhere (the lane's): the same checks and copy of
    ``content`` (none when `HandedOver`), the same JSON, without the message in between.
    """
    handed_over = type(content) is HandedOver
    if handed_over:
        content = content.value
    if (
        type(performative) is not Performative
        or type(sender) is not str
        or not sender
        or (sender not in _known_aids and not _valid_aid(sender))
    ):
        return None
    if not handed_over:
        try:
            content = _json_copy(content, 0)
        except _NotPlain:
            return None
    fields = message.__dict__
    # `reply`'s fields in `to_json`'s order, those None left out as it leaves them (reply_to,
    # encoding, reply_with and reply_by are None in a reply)
    wire = {
        "v": WIRE_VERSION,
        "performative": performative,
        "sender": sender,
        "receivers": list(fields["reply_to"] or [fields["sender"]]),
    }
    if content is not None:
        wire["content"] = content
    if (value := fields["language"]) is not None:
        wire["language"] = value
    if (value := fields["ontology"]) is not None:
        wire["ontology"] = value
    if (value := fields["protocol"]) is not None:
        wire["protocol"] = value
    if (value := fields["conversation_id"]) is not None:
        wire["conversation_id"] = value
    if (value := fields["reply_with"]) is not None:
        wire["in_reply_to"] = value
    try:
        return orjson.dumps(wire)
    except orjson.JSONEncodeError:  # `to_json` says what is wrong
        return None


class HandedOver:
    """A reply's content its maker gives up: plain JSON that nothing else refers to.

    `ACLMessage.reply` takes ``value`` as the content as it is, without the copy and
    check it makes of any other content (~7 µs for a provider's answer of 10 labels).
    The maker vouches for both: ``value`` is made of dicts with str keys, lists, and str,
    int, float, bool and None of exactly those types (no subclass, no cycle, at most 64
    levels deep), and neither it nor anything else keeps a reference to ``value`` or to
    any dict or list in it. Anything else is to be handed to `reply` as it is, to be
    copied and checked.
    """

    __slots__ = ("value",)

    def __init__(self, value: Any) -> None:
        self.value = value


class _NotPlain(Exception):
    """A content the quick check leaves to pydantic."""


_JSON_SCALARS = frozenset({str, int, float, bool, type(None)})
_all_scalars = _JSON_SCALARS.issuperset
_MAX_QUICK_DEPTH = 64


def _json_copy(value: Any, depth: int) -> Any:
    """``value`` copied as pydantic's JsonValue copies it; _NotPlain for anything else."""
    kind = type(value)
    if kind in _JSON_SCALARS:
        return value
    if depth > _MAX_QUICK_DEPTH:
        raise _NotPlain
    # scalars inside are taken as they are, without a call each
    if kind is dict:
        out = value.copy()  # in C; a value not scalar is replaced by its copy below
        for key, item in out.items():
            if type(key) is not str:
                raise _NotPlain
            if type(item) not in _JSON_SCALARS:
                out[key] = _json_copy(item, depth + 1)  # the same key: the dict keeps its size
        return out
    if kind is list:
        return [
            item if type(item) in _JSON_SCALARS else _json_copy(item, depth + 1) for item in value
        ]
    raise _NotPlain


# identifiers that matched already: a platform talks with few agents, again and again
_known_aids: set[str] = set()
_MAX_KNOWN_AIDS = 4096
_MAX_KNOWN_AID = 256  # longer ones are checked each time: 4096 of a message's size would be 1 GiB


def _valid_aid(aid: Any) -> bool:
    """Whether ``aid`` is a str of the form name@platform (remembered when it is)."""
    if type(aid) is not str:
        return False
    if aid in _known_aids:
        return True
    if _aid_match(aid) is None:
        return False
    if len(aid) > _MAX_KNOWN_AID:
        return True  # valid, not remembered: another platform may make up such names
    if len(_known_aids) >= _MAX_KNOWN_AIDS:
        _known_aids.clear()
    _known_aids.add(aid)
    return True


def _aids(value: Any) -> list[str] | None:
    """A copy of a list of valid agent identifiers, else None."""
    if type(value) is not list:
        return None
    known = _known_aids
    for aid in value:
        if type(aid) is not str or (aid not in known and not _valid_aid(aid)):
            return None
    return value.copy()


def _quick_fields(obj: dict[str, Any]) -> dict[str, Any] | None:
    """The model's fields for a decoded message that passes every check, else None."""
    fields = {**_DEFAULTS, **obj}  # in the model's order, as pydantic keeps them
    if len(fields) != _N_FIELDS:
        return None  # a key that is no field: pydantic says which
    v = fields["v"]
    performative = fields["performative"]
    sender = fields["sender"]
    if (
        type(v) is not int
        or v != WIRE_VERSION
        or (type(performative) is not str and type(performative) is not Performative)
        or (performative := _PERFORMATIVES.get(performative)) is None
        or type(sender) is not str
        or (sender not in _known_aids and not _valid_aid(sender))
    ):
        return None
    receivers = fields["receivers"]
    if type(receivers) is list and len(receivers) == 1:  # the common case, without a call
        receiver = receivers[0]
        if type(receiver) is not str or (receiver not in _known_aids and not _valid_aid(receiver)):
            return None
        receivers = [receiver]
    elif not (receivers := _aids(receivers)):
        return None
    reply_to = fields["reply_to"]
    if reply_to is not None and (reply_to := _aids(reply_to)) is None:
        return None
    # unrolled: a loop over the seven costs as much again
    language, encoding, ontology, protocol, conversation_id, reply_with, in_reply_to = (
        _optional_strs(fields)
    )
    if (
        (language is not None and type(language) is not str)
        or (encoding is not None and type(encoding) is not str)
        or (ontology is not None and type(ontology) is not str)
        or (protocol is not None and type(protocol) is not str)
        or (conversation_id is not None and type(conversation_id) is not str)
        or (reply_with is not None and type(reply_with) is not str)
        or (in_reply_to is not None and type(in_reply_to) is not str)
    ):
        return None
    reply_by = fields["reply_by"]
    if reply_by is not None and (type(reply_by) is not float or not math.isfinite(reply_by)):
        return None  # an integer, or anything else: pydantic decides (and says why)
    fields["performative"] = performative
    fields["receivers"] = receivers
    fields["reply_to"] = reply_to
    return fields


_OPTIONAL_STR_SET = frozenset(_OPTIONAL_STR)


def compose(
    performative: Any, sender: str, receivers: Any, content: Any, fields: dict[str, Any]
) -> ACLMessage:
    """``ACLMessage.build`` of an agent's message: receivers one identifier or an iterable.

    What agents send is nearly always made of fields that are already of their exact
    type (a Performative, identifiers met before, a plain JSON content, optional str
    fields, a finite float reply_by): those are checked here, at the cost of a few
    lookups, and the message put together directly, in the model's order of fields and
    with the fields_set `build` gives it. Anything else goes to `build`, which decides
    as before (same errors). A burst repeats one header (the same performative, sender
    and receiver objects, equal str fields): the last one checked is remembered, and a
    message repeating it is put together without its checks again (~0.35 µs less), and
    `to_json` writes the last one made with the header's JSON remembered (~0.35 µs less).
    """
    last = _last_header
    if (
        receivers is last.receivers  # one identifier (only a str is remembered), unchanged
        and sender is last.sender
        and performative is last.performative
    ):
        # exact str or None, as `_plain_message` took them, before comparing: an equal
        # value of another type (a str subclass) is not taken for the remembered one (a
        # loop: the few fields cost less so than a set of their types made by issuperset)
        for value in fields.values():
            if type(value) is not str and value is not None:
                break
        else:
            if fields == last.fields:
                # a run of messages with the header of the last one (a burst): its checks
                # hold; its content copied, a flat dict (the usual) here, without a call
                copied: Any = _NOT_COPIED
                if type(content) is dict:
                    copied = content.copy()
                    for key, item in copied.items():
                        if type(key) is not str or type(item) not in _JSON_SCALARS:
                            copied = _NOT_COPIED  # nested, or no JSON: the general copy
                            break
                if copied is _NOT_COPIED:
                    try:
                        copied = _json_copy(content, 0)
                    except _NotPlain:
                        pass
                if copied is not _NOT_COPIED:
                    made_fields = last.template.copy()
                    made_fields["receivers"] = [receivers]
                    made_fields["content"] = copied
                    # `_constructed`, inline (the path of every message of a burst)
                    made: ACLMessage = _new_message(ACLMessage)
                    _set_dict(made, made_fields)
                    _set_fields_set(made, set(last.names))
                    _set_extra(made, None)
                    _set_private(made, None)
                    # for to_json: this message's header is written as remembered
                    last.made = made_fields
                    return made
    listed = [receivers] if isinstance(receivers, str) else list(receivers)
    act = _PERFORMATIVES.get(performative) if type(performative) is str else performative
    if _plain_message(act, sender, listed, fields):
        try:
            copied = _json_copy(content, 0)
        except _NotPlain:
            pass
        else:
            message = _DEFAULTS.copy()  # every field, in the model's order
            message["performative"] = act
            message["sender"] = sender
            message["receivers"] = listed
            message["content"] = copied
            names = {"performative", "sender", "receivers", "content"}
            if fields:
                message.update(fields)
                names.update(fields)
            made = _constructed(ACLMessage, message, names)
            # a reply_by (every request has its own) is never remembered: no call for it
            if type(receivers) is str and fields.get("reply_by") is None:
                _remember_header(performative, act, sender, receivers, fields, made)
            return made
    return ACLMessage.build(
        performative=performative,
        sender=sender,
        receivers=listed,
        content=content,
        **fields,
    )


_NO_HEADER = object()
_NOT_COPIED: Any = object()  # compose's content not copied (yet)


class _Header:
    """The header (all but content) of the last message `compose` checked and put together."""

    __slots__ = (
        "fields",
        "made",
        "names",
        "performative",
        "prefix",
        "receivers",
        "sender",
        "suffix",
        "template",
    )

    def __init__(self) -> None:
        self.performative: Any = None
        self.sender: Any = None
        # a str (a list could change between two calls); none at first: no call's
        self.receivers: Any = _NO_HEADER
        self.fields: dict[str, Any] = {}
        self.template: dict[str, Any] = {}
        self.names: frozenset[str] = frozenset()
        # the fields of the last message put together from it (a dict no one else makes:
        # `to_json` knows that message by it), and its JSON around the content: `to_json`
        # writes it with one dump
        self.made: dict[str, Any] | None = None
        self.prefix = b""
        self.suffix = b""


_last_header = _Header()
_all_str_or_none = frozenset({str, type(None)}).issuperset


def _remember_header(
    performative: Any,
    act: Any,
    sender: str,
    receivers: str,
    fields: dict[str, Any],
    made: ACLMessage,
) -> None:
    """Remember a checked header (of ``made``, just put together from these fields), for
    `compose` to take the next equal one without checks."""
    if not _all_str_or_none(map(type, fields.values())):
        # a reply_by: every request has its own, and an equal one of another type
        # (True, 1) is no float: `build` decides on it
        return
    message = made.__dict__
    names = made.__pydantic_fields_set__
    header = _Header()
    header.performative = performative
    header.sender = sender
    header.receivers = receivers
    header.fields = fields.copy()  # the caller's dict is its own to change
    header.template = {**message, "receivers": None, "content": None}
    header.names = frozenset(names)
    header.made = message
    # the JSON to_json writes, split around the content (between receivers and the
    # optional str fields, in the model's order; reply_to is a list: never remembered)
    head = {"v": message["v"], "performative": act, "sender": sender, "receivers": [receivers]}
    tail = {name: message[name] for name in _OPTIONAL_STR if message[name] is not None}
    header.prefix = orjson.dumps(head)[:-1] + b',"content":'
    header.suffix = b"," + orjson.dumps(tail)[1:] if tail else b"}"
    global _last_header
    _last_header = header


def _plain_message(act: Any, sender: Any, receivers: list[Any], fields: dict[str, Any]) -> bool:
    """Whether `compose` may put these fields together without `build`'s checks."""
    if type(act) is not Performative or type(sender) is not str or not receivers:
        return False
    known = _known_aids
    if sender not in known and not _valid_aid(sender):
        return False
    for aid in receivers:
        if type(aid) is not str or (aid not in known and not _valid_aid(aid)):
            return False
    for name, value in fields.items():
        if value is None:
            if name not in _OPTIONAL_STR_SET and name != "reply_by":
                return False
        elif type(value) is str:
            if name not in _OPTIONAL_STR_SET:
                return False
        # a finite float ``reply_by``, as `_quick_fields` takes it (every request has one)
        elif name != "reply_by" or type(value) is not float or not math.isfinite(value):
            return False
    return True


_N_FIELDS = len(_FIELDS)
# the fields `ACLMessage.reply` sets (its message's fields_set, as `build` records it)
_REPLY_FIELDS = frozenset(
    (
        "performative",
        "sender",
        "receivers",
        "content",
        "language",
        "ontology",
        "protocol",
        "conversation_id",
        "in_reply_to",
    )
)
_optional_strs = operator.itemgetter(*_OPTIONAL_STR)
