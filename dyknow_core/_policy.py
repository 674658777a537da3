"""Policies: the declarative contract of one subscription, validated once at the edge.

Durations are seconds (user-facing); time points (``start``, ``end``) are integer
nanoseconds on the instance's time line, like every other time point.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import math
import re
from enum import StrEnum
from typing import Any, Self

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator, model_validator

from ._exceptions import PolicyError


class Approximation(StrEnum):
    """How a grid point without an exact sample gets its value."""

    NONE = "none"
    MOST_RECENT = "most_recent"
    CLOSEST = "closest"
    LINEAR = "linear"


class Order(StrEnum):
    """Which valid-time order the output stream keeps."""

    ANY = "any"
    MONOTONE = "monotone"
    STRICT = "strict"


class LateAction(StrEnum):
    """What happens to data later than ``max_delay``: dropped, or (periodic) approximated."""

    DROP = "drop"
    APPROXIMATE = "approximate"


class ChangeKind(StrEnum):
    """Which updates count as a change worth emitting."""

    ANY_UPDATE = "any_update"
    ANY_CHANGE = "any_change"
    ABSOLUTE = "absolute"
    RELATIVE = "relative"


class Overflow(StrEnum):
    """What a full subscription buffer does with one more sample (publishing never waits)."""

    DROP_OLDEST = "drop_oldest"
    DROP_NEWEST = "drop_newest"


# Durations must land on the integer-nanosecond time line without overflowing a float:
# a billion seconds (~31 years) is far beyond any sample period or delay a platform needs.
MAX_DURATION_S = 1e9


def check_duration(name: str, value: float, *, minimum: float) -> float:
    """Refuse a duration (s) that cannot land on the nanosecond time line; names the field."""
    # NaN fails every comparison, so it is refused here too
    if not (minimum <= value <= MAX_DURATION_S):
        raise ValueError(
            f"{name} must be between {minimum:g} and {MAX_DURATION_S:g} s, got {value}"
        )
    return value


_CHANGE_TEXT = re.compile(r"^\s*(absolute|relative)\s*\(\s*([-+0-9.eE]+)\s*\)\s*$")


def _wrap_validation(exc: ValidationError) -> PolicyError:
    """Turn pydantic's error into a PolicyError that names the first bad field."""
    err = exc.errors()[0]
    loc = [str(p) for p in err.get("loc", ())]
    inner = (err.get("ctx") or {}).get("error")
    if isinstance(inner, PolicyError):
        # Raised by our own validators: keep its field, prefixed by where it was nested.
        return PolicyError(".".join([*loc, inner.field]), inner.reason)
    msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
    return PolicyError(".".join(loc) or "policy", msg)


class _EdgeModel(BaseModel):
    """A frozen model whose validation errors become PolicyError naming the field."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_enum_values=False, defer_build=True)

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise _wrap_validation(exc) from exc

    @classmethod
    def parse(cls, data: Any) -> Self:
        """Validate a mapping (a config, a message's content) into this model."""
        if isinstance(data, cls):
            return data
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise _wrap_validation(exc) from exc


class Change(_EdgeModel):
    """The change part of a policy: any update, any change, or a change larger than δ."""

    kind: ChangeKind = ChangeKind.ANY_UPDATE
    delta: float | None = None

    @model_validator(mode="before")
    @classmethod
    def _from_text(cls, data: Any) -> Any:
        # "any_change", "absolute(0.5)" are accepted so configs and KPL stay short.
        if isinstance(data, str):
            m = _CHANGE_TEXT.match(data)
            if m:
                return {"kind": m.group(1), "delta": float(m.group(2))}
            return {"kind": data.strip()}
        return data

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.kind in (ChangeKind.ABSOLUTE, ChangeKind.RELATIVE):
            if self.delta is None:
                raise PolicyError("delta", f"change {self.kind.value!r} needs a delta")
            if not self.delta >= 0 or math.isinf(self.delta):
                raise PolicyError(
                    "delta", f"change delta must be finite and >= 0, got {self.delta}"
                )
        elif self.delta is not None:
            raise PolicyError("delta", f"change {self.kind.value!r} takes no delta")
        return self

    @property
    def numeric(self) -> bool:
        """Whether this change test needs numeric values."""
        return self.kind in (ChangeKind.ABSOLUTE, ChangeKind.RELATIVE)


class Policy(_EdgeModel):
    """What one subscriber wants from a stream; each subscriber has its own.

    ``start``/``end`` bound valid time (ns; a past ``start`` replays history from the
    cache). ``sample_period`` (s) asks for one sample per period on a grid of valid
    times, filled per ``approximation``. ``max_delay`` (s) makes samples with
    available − valid time above it late: dropped, or for periodic streams approximated
    once the delay has passed (``late``). ``order``, ``change`` and the ``lower``/``upper``
    bounds filter what is emitted. ``buffer_size``/``overflow`` bound the subscription.
    """

    start: int | None = None
    end: int | None = None
    sample_period: float | None = None
    approximation: Approximation = Approximation.NONE
    max_delay: float | None = None
    late: LateAction = LateAction.DROP
    order: Order = Order.ANY
    change: Change = Change()
    lower: float | None = None
    upper: float | None = None
    buffer_size: int = 4096
    overflow: Overflow = Overflow.DROP_OLDEST

    @field_validator("change", mode="before")
    @classmethod
    def _change_text(cls, v: Any) -> Any:
        return Change.parse(v) if isinstance(v, str | dict) else v

    @field_validator("sample_period")
    @classmethod
    def _positive_period(cls, v: float | None) -> float | None:
        return None if v is None else check_duration("sample_period", v, minimum=1e-9)

    @field_validator("max_delay")
    @classmethod
    def _non_negative_delay(cls, v: float | None) -> float | None:
        return None if v is None else check_duration("max_delay", v, minimum=0.0)

    @field_validator("lower", "upper")
    @classmethod
    def _not_nan(cls, v: float | None) -> float | None:
        if v is not None and math.isnan(v):
            raise ValueError("a bound cannot be NaN (it would compare false with every value)")
        return v

    @field_validator("buffer_size")
    @classmethod
    def _positive_buffer(cls, v: int) -> int:
        if v < 1:
            raise ValueError(f"buffer_size must be >= 1, got {v}")
        return v

    @model_validator(mode="after")
    def _coherent(self) -> Self:
        if self.start is not None and self.end is not None and self.start > self.end:
            raise PolicyError("start", f"start {self.start} is after end {self.end}")
        if self.lower is not None and self.upper is not None and self.lower > self.upper:
            raise PolicyError("lower", f"lower bound {self.lower} is above upper {self.upper}")
        if self.sample_period is None and self.approximation is not Approximation.NONE:
            raise PolicyError(
                "approximation",
                f"approximation {self.approximation.value!r} needs a sample_period",
            )
        if self.late is LateAction.APPROXIMATE:
            if self.sample_period is None:
                raise PolicyError("late", "late='approximate' is for periodic streams only")
            if self.approximation is Approximation.NONE:
                raise PolicyError(
                    "late", "late='approximate' needs an approximation other than none"
                )
            if self.max_delay is None:
                raise PolicyError("late", "late='approximate' needs a max_delay")
        return self

    @property
    def numeric(self) -> bool:
        """Whether this policy can only be applied to numeric values."""
        return (
            self.lower is not None
            or self.upper is not None
            or self.change.numeric
            or self.approximation is Approximation.LINEAR
        )

    def numeric_field(self) -> str | None:
        """The first field that needs numeric values, for error messages."""
        if self.approximation is Approximation.LINEAR:
            return "approximation"
        if self.lower is not None:
            return "lower"
        if self.upper is not None:
            return "upper"
        if self.change.numeric:
            return "change"
        return None

    def replace(self, **changes: Any) -> "Policy":
        """Return a validated copy with some fields changed (for live refinement)."""
        data = self.model_dump()
        data.update(changes)
        return Policy(**data)


class CacheSpec(_EdgeModel):
    """How much history a location keeps per stream: the last N samples and/or last T seconds."""

    max_samples: int | None = 10_000
    max_age: float | None = None

    @model_validator(mode="after")
    def _bounded(self) -> Self:
        if self.max_samples is not None and self.max_samples < 1:
            raise PolicyError("max_samples", f"must be >= 1, got {self.max_samples}")
        if self.max_age is not None and not 0 < self.max_age <= MAX_DURATION_S:
            raise PolicyError(
                "max_age", f"must be > 0 and <= {MAX_DURATION_S:g} seconds, got {self.max_age}"
            )
        if self.max_samples is None and self.max_age is None:
            raise PolicyError(
                "max_samples", "a cache needs max_samples or max_age (it must be bounded)"
            )
        return self
