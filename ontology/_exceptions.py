"""Errors raised by the ontology: vocabularies, label translation, SL formulas.

The tree::

    OntologyError
    ├── VocabularyError         (also a ValueError: a malformed vocabulary or mapping;
    │                            .source names the file, .key the entry)
    ├── UnknownSemanticLabel    (also a KeyError: a label that cannot be translated;
    │                            .label, .reason is a Refusal)
    ├── SLSyntaxError           (also a ValueError: a malformed formula; .line, .column,
    │                            .excerpt with a caret under the position)
    └── SLEvaluationError       (a formula that parses but cannot be answered: iota
                                 without exactly one answer, an unknown concept; .reason)

The message of an `UnknownSemanticLabel` raised by `LabelMapping.to_local` names only
the semantic label, so it may be sent to another platform as the reason of a refusal.
One raised by `LabelMapping.to_semantic` names a local label and must stay on the platform.
"""

from __future__ import annotations

from enum import StrEnum


class OntologyError(Exception):
    """Base class of every error raised by `ontology`."""


class VocabularyError(OntologyError, ValueError):
    """A vocabulary or label mapping that cannot be used; names the file and the entry."""

    def __init__(self, source: str, key: str | None, message: str) -> None:
        self.source = source
        self.key = key
        self.reason = message
        where = f"{source}: {key}" if key else source
        super().__init__(f"{where}: {message}")


class Refusal(StrEnum):
    """Why a label was refused: what an agent says when it cannot serve a semantic label."""

    NOT_IN_VOCABULARY = "not-in-vocabulary"
    """The federation never agreed on this semantic label."""
    NOT_MAPPED = "not-mapped"
    """The label is in the vocabulary, but this platform has no mapping for it."""
    NOT_PROVIDED = "not-provided"
    """The label is mapped, but this platform publishes no stream for it now."""


_EXPLANATION = {
    Refusal.NOT_IN_VOCABULARY: "is not in the federation's vocabulary",
    Refusal.NOT_MAPPED: "has no mapping on this platform",
    Refusal.NOT_PROVIDED: "is not provided by this platform now",
}


class UnknownSemanticLabel(OntologyError, KeyError):
    """A label that cannot be translated; ``reason`` says why (a `Refusal`)."""

    def __init__(self, label: str, reason: Refusal, *, local: bool = False) -> None:
        self.label = label
        self.reason = reason
        self.local = local
        kind = "local label" if local else "semantic label"
        super().__init__(f"{kind} {label!r} {_EXPLANATION[reason]} ({reason.value})")

    def __str__(self) -> str:
        # KeyError would show the message in quotes
        return str(self.args[0])


class SLSyntaxError(OntologyError, ValueError):
    """A malformed SL formula; ``line`` and ``column`` (1-based) point at the position."""

    def __init__(self, message: str, text: str, offset: int) -> None:
        self.message = message
        self.offset = offset
        self.line = text.count("\n", 0, offset) + 1
        line_start = text.rfind("\n", 0, offset) + 1
        self.column = offset - line_start + 1
        line_end = text.find("\n", offset)
        self.excerpt = _excerpt(
            text[line_start : len(text) if line_end < 0 else line_end], offset - line_start
        )
        super().__init__(f"{message} (line {self.line}, column {self.column})\n{self.excerpt}")


def _excerpt(line: str, index: int, width: int = 72) -> str:
    """The line with a caret under ``index``, cut to ``width`` around it when long."""
    start = max(0, min(index - width // 2, len(line) - width))
    end = start + width
    shown = line[start:end]
    prefix = "…" if start > 0 else ""
    suffix = "…" if end < len(line) else ""
    # keep tabs in the caret line so the caret lines up under tab-indented text
    pad = "".join("\t" if c == "\t" else " " for c in shown[: index - start])
    return f"  {prefix}{shown}{suffix}\n  {' ' * len(prefix)}{pad}^"


class SLEvaluationError(OntologyError):
    """A formula that cannot be answered; ``reason`` is a short code, the message explains."""

    NO_MATCH = "no-match"
    SEVERAL_MATCHES = "several-matches"
    UNKNOWN_CONCEPT = "unknown-concept"
    WRONG_ARITY = "wrong-arity"

    def __init__(self, reason: str, message: str) -> None:
        self.reason = reason
        super().__init__(message)
