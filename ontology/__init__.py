"""Ontology: semantic labels, their translation to local labels, and label search.

A federation agrees on a `Vocabulary` of semantic labels; each platform translates them
with its own `LabelMapping`. Facts about objects (`FactBase`, kept current by a
`FactFeed`) answer SL formulas (`parse`, `evaluate`), and `find_labels` turns the
answer into the semantic labels this platform provides.
"""

from ._exceptions import (
    OntologyError,
    Refusal,
    SLEvaluationError,
    SLSyntaxError,
    UnknownSemanticLabel,
    VocabularyError,
)
from ._facts import DomainRule, Fact, FactBase, FactFeed, Rule, StreamRule
from ._labels import OBJECT, LabelMapping, LabelPattern, Vocabulary, semantic_labels
from ._search import PlatformLabels, find_labels
from ._sl import (
    And,
    Atom,
    Binding,
    Constant,
    Expression,
    Formula,
    Not,
    Or,
    Query,
    QueryKind,
    Term,
    Value,
    Variable,
    evaluate,
    parse,
)

__all__ = [
    "OBJECT",
    "And",
    "Atom",
    "Binding",
    "Constant",
    "DomainRule",
    "Expression",
    "Fact",
    "FactBase",
    "FactFeed",
    "Formula",
    "LabelMapping",
    "LabelPattern",
    "Not",
    "OntologyError",
    "Or",
    "PlatformLabels",
    "Query",
    "QueryKind",
    "Refusal",
    "Rule",
    "SLEvaluationError",
    "SLSyntaxError",
    "StreamRule",
    "Term",
    "UnknownSemanticLabel",
    "Value",
    "Variable",
    "Vocabulary",
    "VocabularyError",
    "evaluate",
    "find_labels",
    "parse",
    "semantic_labels",
]
