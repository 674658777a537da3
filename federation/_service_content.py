"""The content of DyKnow Federation requests: JSON objects, validated into models.

Kept apart from the agent (``federation/_service.py``, whose docstring lists every action
with its content) so the wire format is in one place and testable without agents.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
from typing import Annotated, Any, Literal

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, JsonValue, ValidationError

from dyknow_core import PolicyError

from ._gateway_service import PolicySpec, RemotePeriod, Seconds

ONTOLOGY = "dyknow-federation"
"""The ontology of every message to and from a DyKnow Federation Agent."""

_MAX_LABEL = 200
# A request names a handful of labels; the bound keeps one request from asking for the
# whole instance.
_MAX_LABELS = 64
Label = Annotated[str, Field(min_length=1, max_length=_MAX_LABEL)]
Labels = Annotated[list[Label], Field(min_length=1, max_length=_MAX_LABELS)]
Platform = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.\-]+$", max_length=200)]
Units = Annotated[list[Platform], Field(min_length=1, max_length=64)]


def _labels() -> Any:
    # The paper writes ``semantic-labels: (seq car5-state)``; ``labels`` is the short form.
    return Field(validation_alias=AliasChoices("labels", "semantic-labels"))


class ContentError(Exception):
    """Request content that cannot be performed; ``reason`` goes into the refuse."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


MAX_HISTORY = 100_000
"""The most samples a create-stream may ask an exporter to keep for resending."""


class _Content(BaseModel):
    # defer_build: a kind of request is built when the first one arrives, not at start
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, defer_build=True)


class CreateStream(_Content):
    """``create-stream``: export the streams of ``labels`` to each of ``to-units``."""

    action: Literal["create-stream"]
    labels: Labels = _labels()
    start: Seconds | None = Field(default=None, alias="from")
    end: Seconds | None = Field(default=None, alias="to")
    relative: bool = False
    sample_period: RemotePeriod | None = Field(default=None, alias="sample-period")
    max_delay: Seconds | None = Field(default=None, alias="max-delay")
    to_units: Units | None = Field(default=None, alias="to-units")
    policy: dict[str, JsonValue] = Field(default_factory=dict)
    # samples kept by the exporter to resend what a partition lost (docs/federation.md)
    history: int = Field(default=0, ge=0, le=MAX_HISTORY)

    def policy_spec(self) -> PolicySpec:
        """The policy as the gateway reads it: the named fields over ``policy``'s extras."""
        named = {
            "from": self.start,
            "to": self.end,
            "sample_period": self.sample_period,
            "max_delay": self.max_delay,
        }
        clash = sorted(k for k, v in named.items() if v is not None and k in self.policy)
        if clash or "relative" in self.policy:
            raise ContentError(
                f"'policy' repeats {', '.join(clash) or 'relative'}: give it once, at the top"
            )
        data: dict[str, Any] = {**self.policy, "relative": self.relative}
        data.update({k: v for k, v in named.items() if v is not None})
        return _validated(PolicySpec, data, where="policy")


class CancelStream(_Content):
    """``cancel-stream``: stop the export ``id`` agreed earlier."""

    action: Literal["cancel-stream"]
    id: Annotated[str, Field(min_length=1, max_length=200)]


class AcceptStream(_Content):
    """``accept-stream``: a provider asks a receiver to agree to streams a third platform asked.

    Sent by the provider's Federation Agent to each receiver of a create-stream that is
    not the requester; the receiver agrees (inform ``{"accepted": [s…]}``, and then
    expects those streams) only if its own config allows ``requester`` to send it streams.
    """

    action: Literal["accept-stream"]
    requester: Platform
    labels: Labels = _labels()


class ConfirmStream(_Content):
    """``confirm-stream``: a receiver asks a requester whether it asked for the streams.

    The receiver's check of an ``accept-stream``: the provider only says who asked.
    """

    action: Literal["confirm-stream"]
    provider: Platform
    labels: Labels = _labels()


class _Query(_Content):
    labels: Labels = _labels()
    relative: bool = False
    to_units: Units | None = Field(default=None, alias="to-units")


class GetLatest(_Query):
    """``get-latest``: the newest sample of each label."""

    action: Literal["get-latest"]


class GetValueAt(_Query):
    """``get-value-at``: each label's value at valid time ``t`` (its fluent generator)."""

    action: Literal["get-value-at"]
    t: Seconds
    approximation: Literal["most_recent", "closest", "linear"] = "most_recent"


class GetTrajectory(_Query):
    """``get-trajectory``: every sample of each label with valid time in [from, to]."""

    action: Literal["get-trajectory"]
    start: Seconds | None = Field(default=None, alias="from")
    end: Seconds | None = Field(default=None, alias="to")


class SearchLabels(_Content):
    """``search-labels``: the semantic labels an FIPA-SL formula describes."""

    action: Literal["search-labels"]
    formula: Annotated[str, Field(min_length=1, max_length=10_000)]


class ListLabels(_Content):
    """``list-labels``: the semantic labels this platform provides."""

    action: Literal["list-labels"]


class GlobalRequest(_Content):
    """``global-request``: ask every federation member (local askers only)."""

    action: Literal["global-request"]
    request: dict[str, JsonValue]
    deadline: Annotated[float, Field(gt=0, le=60)]
    select: Literal["first", "newest"] = "first"
    include_self: bool = Field(default=False, alias="include-self")


Query = GetLatest | GetValueAt | GetTrajectory
Request = (
    CreateStream
    | AcceptStream
    | ConfirmStream
    | CancelStream
    | GetLatest
    | GetValueAt
    | GetTrajectory
    | SearchLabels
    | ListLabels
    | GlobalRequest
)

ACTIONS: dict[str, type[_Content]] = {
    "create-stream": CreateStream,
    "accept-stream": AcceptStream,
    "confirm-stream": ConfirmStream,
    "cancel-stream": CancelStream,
    "get-latest": GetLatest,
    "get-value-at": GetValueAt,
    "get-trajectory": GetTrajectory,
    "search-labels": SearchLabels,
    "list-labels": ListLabels,
    "global-request": GlobalRequest,
}
"""Every action of the DyKnow Federation service, by name."""

QUERY_ACTIONS = frozenset({"get-latest", "get-value-at", "get-trajectory", "search-labels"})
"""The actions that only read, also answered to FIPA-Query (query-ref)."""


def _validated(model: type[Any], data: Any, *, where: str | None = None) -> Any:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err.get("loc", ()))
        loc = ".".join(p for p in (where, loc) if p) or "content"
        raise ContentError(f"field {loc!r}: {err.get('msg', 'invalid')}") from exc
    except PolicyError as exc:
        raise ContentError(str(exc)) from exc


def parse_request(content: Any) -> Request:
    """Validate request content into its action's model; ContentError says what is wrong."""
    if not isinstance(content, dict) or not isinstance(content.get("action"), str):
        raise ContentError('the content must be a JSON object with an "action"')
    model = ACTIONS.get(content["action"])
    if model is None:
        raise ContentError(
            f"unknown action {content['action']!r} (known: {', '.join(sorted(ACTIONS))})"
        )
    parsed: Request = _validated(model, content)
    return parsed


_LATEST_KEYS = frozenset({"action", "labels"})


def latest_labels(content: Any) -> list[str] | None:
    """The labels of a plain get-latest, ``{"action": "get-latest", "labels": [s…]}``; else None.

    What `parse_request` makes of that exact shape (a `GetLatest` of those labels, no
    ``to-units``), checked in plain Python: pydantic's validation costs more than a
    provider's answer to a few labels. Anything else (another key or spelling, a label of
    another type or length, too few or too many) is None: `parse_request` decides it.
    """
    if type(content) is not dict or content.keys() != _LATEST_KEYS:
        return None
    action = content["action"]
    labels = content["labels"]
    if (
        type(action) is not str
        or action != "get-latest"
        or type(labels) is not list
        or not 0 < len(labels) <= _MAX_LABELS
    ):
        return None
    for label in labels:
        if type(label) is not str or not 0 < len(label) <= _MAX_LABEL:
            return None
    return labels


def newest_valid_time(content: Any) -> float | None:
    """The newest valid time (s) in a query answer ``{label: {"samples": [...]}}``, if any."""
    newest: float | None = None
    if not isinstance(content, dict):
        return None
    for answer in content.values():
        samples = answer.get("samples") if isinstance(answer, dict) else None
        if not isinstance(samples, list):
            continue
        for row in samples:
            if isinstance(row, list) and len(row) >= 2:
                tv = row[1]
                if isinstance(tv, int | float) and not isinstance(tv, bool):
                    newest = tv if newest is None else max(newest, tv)
    return newest
