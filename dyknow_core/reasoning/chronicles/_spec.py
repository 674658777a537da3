"""Chronicle definitions as written (pydantic, seconds), checked at the edge."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..._exceptions import DyKnowError


class ChronicleError(DyKnowError, ValueError):
    """A chronicle definition that is invalid or inconsistent; ``field`` names where."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.reason = message
        super().__init__(f"chronicle field {field!r}: {message}")


# -- definitions at the edge ---------------------------------------------------------------

# Seconds of a window, finite and bounded (about 31 years): 1e300 s is no time line's
Seconds = Annotated[float, Field(allow_inf_nan=False, ge=-1e9, le=1e9)]


def _as_arg_map(v: Any) -> Any:
    # a list of names is shorthand for "the chronicle parameter is the event argument"
    if isinstance(v, (list, tuple)):
        return {str(x): str(x) for x in v}
    return v


class EventSpec(BaseModel):
    """One event of a chronicle: an input kind, parameters, optionally a from→to change."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    name: str = Field(min_length=1)
    event: str = Field(min_length=1)
    args: dict[str, str] = Field(default_factory=dict)
    from_: Any = Field(default=None, alias="from")
    to: Any = None

    _norm_args = field_validator("args", mode="before")(_as_arg_map)


class ConstraintSpec(BaseModel):
    """``lo <= t(end) - t(start) <= hi`` in seconds; a missing bound is unbounded."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    start: str
    end: str
    lo: Seconds | None = None
    hi: Seconds | None = None


class ForbiddenSpec(BaseModel):
    """An event that must not occur in ``(t(start), t(end))`` or ``(t(start)+lo, t(start)+hi)``."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    event: str = Field(min_length=1)
    args: dict[str, str] = Field(default_factory=dict)
    from_: Any = Field(default=None, alias="from")
    to: Any = None
    start: str
    end: str | None = None
    lo: Seconds | None = None
    hi: Seconds | None = None

    _norm_args = field_validator("args", mode="before")(_as_arg_map)


class ChronicleSpec(BaseModel):
    """A chronicle definition: events, metric constraints, forbidden events, memory cap."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1)
    events: list[EventSpec] = Field(min_length=1)
    constraints: list[ConstraintSpec] = Field(default_factory=list)
    forbidden: list[ForbiddenSpec] = Field(default_factory=list)
    max_partial: int = Field(default=10_000, gt=0)
