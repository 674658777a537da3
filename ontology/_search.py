"""Label search: the semantic labels of the objects that satisfy an SL formula.

A platform that does not know a semantic label asks for those matching a formula, e.g.
``(all ?x (and (Car ?x) (Color ?x blue) (OnRoad ?x road7)))``: every platform answers
over its own facts, with the labels it can provide.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ._exceptions import UnknownSemanticLabel
from ._facts import FactBase
from ._labels import LabelMapping, semantic_labels
from ._sl import Expression, evaluate, parse

if TYPE_CHECKING:
    from dyknow_core import DyKnowInstance


def find_labels(
    formula: str | Expression,
    facts: FactBase,
    mapping: LabelMapping,
    instance: DyKnowInstance,
) -> list[str]:
    """The semantic labels of the objects satisfying ``formula`` that ``instance`` provides now.

    For each object in an answer, each of the vocabulary's ``{object}`` patterns filled
    in with it, kept if this platform maps it and publishes the local stream. In answer
    order, then vocabulary order; no local label is ever returned. Raises SLSyntaxError
    for a malformed formula, SLEvaluationError for an iota without exactly one answer or
    a concept the vocabulary does not have.
    """
    expr = parse(formula) if isinstance(formula, str) else formula
    vocabulary = mapping.vocabulary
    vocabulary.check(expr)
    found: dict[str, None] = {}
    for binding in evaluate(expr, facts):
        for value in binding.values():
            if not isinstance(value, str):
                continue
            for semantic in vocabulary.object_labels(value):
                try:
                    local = mapping.to_local(semantic)
                except UnknownSemanticLabel:
                    continue
                if instance.has_label(local):
                    found[semantic] = None
    return list(found)


class PlatformLabels:
    """One platform's labels as its Federation Agent needs them: translate, list, search."""

    def __init__(
        self, mapping: LabelMapping, instance: DyKnowInstance, facts: FactBase | None = None
    ) -> None:
        self.mapping = mapping
        self.instance = instance
        self.facts = facts if facts is not None else FactBase()

    def to_local(self, semantic: str, /) -> str:
        """The local label of ``semantic``; UnknownSemanticLabel with the reason if none."""
        return self.mapping.to_local(semantic)

    def to_semantic(self, local: str, /) -> str:
        """The semantic label of local label ``local``; UnknownSemanticLabel if none."""
        return self.mapping.to_semantic(local)

    def provides(self) -> list[str]:
        """The semantic labels this platform can provide now."""
        return semantic_labels(self.instance, self.mapping)

    def find(self, formula: str, /) -> list[str]:
        """The semantic labels of the objects satisfying ``formula`` (see `find_labels`)."""
        return find_labels(formula, self.facts, self.mapping, self.instance)
