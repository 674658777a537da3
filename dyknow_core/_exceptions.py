"""Errors raised by a DyKnow instance.

The tree::

    DyKnowError
    ├── UnknownLabelError        (also a KeyError: no stream generator under that label)
    ├── DuplicateLabelError      (a label is published twice)
    ├── PolicyError              (also a ValueError: an impossible policy; names the field)
    ├── ProcessError             (a knowledge process could not be added or removed)
    ├── ObjectError              (an identifier assigned twice, an unknown domain …)
    └── ClosedError              (the instance or subscription is closed)
"""

from __future__ import annotations


class DyKnowError(Exception):
    """Base class of every error raised by `dyknow_core`."""


class UnknownLabelError(DyKnowError, KeyError):
    """No stream generator is published under the label."""

    def __init__(self, label: str, known: list[str] | None = None) -> None:
        self.label = label
        hint = ""
        if known:
            shown = ", ".join(sorted(known)[:8])
            hint = f" (known labels: {shown}{', …' if len(known) > 8 else ''})"
        super().__init__(f"unknown label {label!r}{hint}")

    def __str__(self) -> str:
        return str(self.args[0])


class DuplicateLabelError(DyKnowError):
    """A stream generator is already published under the label."""


class PolicyError(DyKnowError, ValueError):
    """A policy (or state policy, cache spec) that cannot be satisfied; names the field."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.reason = message
        super().__init__(f"policy field {field!r}: {message}")


class ProcessError(DyKnowError):
    """A knowledge process could not be added, removed or started."""


class ObjectError(DyKnowError):
    """An object identifier or domain operation is not allowed."""


class ClosedError(DyKnowError):
    """The instance, location or subscription is closed."""
