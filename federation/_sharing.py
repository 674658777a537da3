"""What a platform shares, and with whom: the ``[sharing]`` table of its config.

A platform's operator decides which other platforms may *query* which semantic labels
and have them *streamed* (rules: semantic-label patterns → platform patterns), whether
other platforms may use its Gateway Agent at all (``gateway``; private by default: local
labels never leave the platform), and which platforms may direct a stream *to* it when
they ask a third platform for one (``accept_for``, the receiver's consent). The Federation
Agent enforces it; every refusal names the rule (``docs/federation.md``, "Sharing")::

    [sharing]
    gateway = "private"        # or "protected": other members may use the Gateway Agent
    default = "members"        # labels no rule names: every member ("members") or nobody
    accept_for = ["operator"]  # whose create-stream may send streams to this platform

    [[sharing.rules]]
    name = "neighbours"
    labels = ["car*-state"]    # semantic-label patterns (shell-style: * ? [...])
    query = ["uav-b", "uav-c"] # platform patterns; "*" = every member, [] = nobody
    stream = ["uav-b"]

Rules are read in order; the first whose ``labels`` match a label decides for it. Agents
of the platform itself are never restricted by these rules.
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import fnmatch
from collections.abc import Iterable
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["Sharing", "SharingRule", "SharingSettings"]

# a pattern names labels or platforms: the characters they use, and shell wildcards
_PATTERN = r"^[A-Za-z0-9_.\-/*?\[\]!]+$"
Pattern = Annotated[str, Field(min_length=1, max_length=200, pattern=_PATTERN)]


def _no_items() -> list[Any]:
    """A new empty list: the default of a list field.

    Not ``list`` itself: pydantic reads a builtin's signature by tokenizing its text, and
    the first time compiles the tokenizer's expressions (~6 ms of a node's start).
    """
    return []


Action = Literal["query", "stream"]


class SharingRule(BaseModel):
    """One rule: the labels it covers, and the platforms that may query / stream them."""

    # defer_build: a config's rules are checked by PlatformConfig's own schema, so this
    # model's validator is built only if something validates one on its own (~0.3 MB of
    # a node's memory for the inputs, outputs and sharing rules together)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True)

    name: Annotated[str, Field(min_length=1, max_length=100)] | None = None
    labels: Annotated[list[Pattern], Field(min_length=1)]
    query: list[Pattern] = Field(default_factory=_no_items)
    stream: list[Pattern] = Field(default_factory=_no_items)


class SharingSettings(BaseModel):
    """The ``[sharing]`` table: gateway access, the rules, their default, consent to receive."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True)

    gateway: Literal["private", "protected"] = "private"
    default: Literal["members", "none"] = "members"
    accept_for: list[Pattern] = Field(default_factory=_no_items)
    rules: list[SharingRule] = Field(default_factory=_no_items)

    def sharing(self) -> "Sharing":
        """The rules as the Federation Agent applies them."""
        return Sharing(self)


def _matches(name: str, patterns: list[str]) -> bool:
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


class Sharing:
    """Decides who may query or stream a semantic label, and whose streams to accept."""

    def __init__(self, settings: SharingSettings | None = None) -> None:
        self.settings = settings if settings is not None else SharingSettings()

    def check(self, action: Action, label: str, platform: str) -> str | None:
        """None if ``platform`` may ``action`` ``label``; else the refusal, naming the rule."""
        return _check_in(self.settings, action, label, platform)

    def check_all(self, action: Action, labels: Iterable[str], platform: str) -> str | None:
        """`check` of each of ``labels`` in turn: the first refusal, or None if all are allowed."""
        settings = self.settings  # read once (a reload replaces it whole): any thread may ask
        if type(self).check is not _CHECK:
            check = self.check
            for label in labels:
                reason = check(action, label, platform)
                if reason is not None:
                    return reason
            return None
        if not settings.rules and settings.default == "members":
            return None  # what `check` says of any label (the default table), without a call each
        for label in labels:
            reason = _check_in(settings, action, label, platform)
            if reason is not None:
                return reason
        return None

    def accepts_for(self, requester: str) -> str | None:
        """None if streams ``requester`` asks for this platform are accepted; else why not."""
        patterns = self.settings.accept_for
        if _matches(requester, patterns):
            return None
        if not patterns:
            # the default: saying "or when no platform asks" read as if none asking sufficed
            return (
                "this platform receives streams only when it asks for them "
                f"(sharing.accept_for names no other platform); not for {requester}"
            )
        return (
            f"this platform receives streams only when it asks for them, or when "
            f"{', '.join(patterns)} asks for it (sharing.accept_for); not for {requester}"
        )


def _check_in(settings: SharingSettings, action: Action, label: str, platform: str) -> str | None:
    """`Sharing.check` by ``settings``."""
    verb = "queried by" if action == "query" else "streamed to"
    for i, rule in enumerate(settings.rules):
        if not _matches(label, rule.labels):
            continue
        allowed = rule.query if action == "query" else rule.stream
        if _matches(platform, allowed):
            return None
        name = f"{rule.name!r} (sharing.rules[{i}])" if rule.name else f"sharing.rules[{i}]"
        who = ", ".join(allowed) if allowed else "no platform"
        return (
            f"label {label!r} may not be {verb} {platform}: sharing rule {name} "
            f"({', '.join(rule.labels)}) lets {who} {action} it"
        )
    if settings.default == "members":
        return None
    return (
        f"label {label!r} may not be {verb} {platform}: no sharing rule names it "
        'and sharing.default is "none"'
    )


_CHECK = Sharing.check  # a subclass that decides otherwise is asked per label
