"""Semantic labels: a federation's vocabulary, and each platform's mapping to local labels.

A federation agrees on *semantic labels* (``heli-position``, ``car5-state``); each
platform translates them to the labels of its own DyKnow instance. Agents talk semantic
labels; local labels never leave the platform.

**Patterns.** A label may have placeholders, ``{name}``, standing for a value made of
letters, digits and underscores: ``{object}-state`` is ``car5-state`` for the object
``car5``. ``{object}`` is the placeholder for object identifiers (label search fills it
in). A placeholder appears at most once per label and two placeholders never touch (the
values could not be told apart). Semantic labels are made of letters, digits, ``_`` and
``-``; since ``-`` never occurs in a value, ``{object}-max-speed`` and ``{object}-speed``
cannot be confused.

**The vocabulary file** (TOML) lists the agreed labels, each with what it means, and
optionally the concepts formulas may use, with their arity::

    name = "traffic-monitoring"          # optional; a mapping file may name it

    [labels]
    heli-position = "this platform's own position (x, y, z), metres"
    heli-altitude = "this platform's own altitude, metres"
    heli-max-speed = "this platform's top speed, m/s"
    "{object}-state" = "the state of the tracked object, e.g. car5-state"
    "{object}-speed" = "the speed of the tracked object, m/s"

    [concepts]                           # optional; formulas are then checked against it
    Car = 1
    Color = 2
    OnRoad = 2

``labels`` may also be a plain list of labels (``labels = ["heli-position", …]``).

**The mapping file** (TOML) is one platform's table from semantic labels (or vocabulary
patterns) to local labels (or local patterns with the same placeholders)::

    vocabulary = "traffic-monitoring"    # optional; refused if it names another one

    [labels]
    heli-position = "uav/self/position"
    heli-max-speed = "uav/self/max_speed"
    "{object}-state" = "car/{object}/state"
    car0-state = "tracker/main/state"    # a concrete entry wins over the pattern

Every key must be in the vocabulary. Both files can also be given as dicts of the same
shape (`Vocabulary.from_dict`, `LabelMapping.from_dict`).
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._exceptions import Refusal, SLEvaluationError, UnknownSemanticLabel, VocabularyError
from ._sl import Expression, atoms_of, is_word

if TYPE_CHECKING:
    from dyknow_core import DyKnowInstance

OBJECT = "object"
"""The placeholder name for object identifiers: ``{object}-state``."""

SEMANTIC_VALUE = r"[A-Za-z0-9_]+"
"""What a placeholder of a semantic label stands for."""

# dyknow_core's object identifiers: no whitespace, '/', braces or glob characters
LOCAL_VALUE = r"[^\s/{}*?\[\]]+"

_PLACEHOLDER = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")
_HOLE = re.compile(r"\{[^{}]+\}")  # a template's hole: an input's {field}, import {sender}
_SEMANTIC = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]*")
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


class LabelPattern:
    """A label with placeholders (``{object}-state``, ``car/{object}/state``), or without."""

    __slots__ = ("_regex", "_value", "params", "text")

    def __init__(self, text: str, *, value: str = SEMANTIC_VALUE) -> None:
        if not isinstance(text, str) or not text:
            raise ValueError("a label must be a non-empty string")
        parts: list[str] = []
        params: list[str] = []
        pos = 0
        for m in _PLACEHOLDER.finditer(text):
            if params and m.start() == pos:
                raise ValueError(
                    f"placeholders {{{params[-1]}}} and {{{m.group(1)}}} touch: "
                    "put a separator between them"
                )
            if m.group(1) in params:
                raise ValueError(f"placeholder {{{m.group(1)}}} appears twice")
            parts.append(re.escape(text[pos : m.start()]))
            parts.append(f"(?P<{m.group(1)}>{value})")
            params.append(m.group(1))
            pos = m.end()
        parts.append(re.escape(text[pos:]))
        literal = _PLACEHOLDER.sub("", text)
        if "{" in literal or "}" in literal:
            raise ValueError("a brace that is not part of a {name} placeholder")
        self.text = text
        self.params = tuple(params)
        self._value = re.compile(value)
        self._regex = re.compile("".join(parts))

    @property
    def parameterized(self) -> bool:
        """Whether the label has placeholders."""
        return bool(self.params)

    def match(self, label: str) -> dict[str, str] | None:
        """The placeholder values that make ``label`` from this pattern, or None."""
        m = self._regex.fullmatch(label)
        return None if m is None else m.groupdict()

    def format(self, **values: str) -> str:
        """The label with each placeholder replaced by its value; ValueError if one is bad."""
        if set(values) != set(self.params):
            raise ValueError(f"{self.text!r} needs values for {list(self.params)}, got {values}")
        out = self.text
        for name, v in values.items():
            if not isinstance(v, str) or not self._value.fullmatch(v):
                raise ValueError(f"{v!r} cannot stand for {{{name}}} in {self.text!r}")
            out = out.replace(f"{{{name}}}", v)
        return out

    def overlaps(self, template: str) -> bool:
        """Whether some label ``template`` stands for matches this pattern.

        ``template`` is a label, or one with ``{holes}`` standing for any text (zero or
        more characters: a message's field, a topic). The two are walked side by side, a
        product of their automata: a placeholder here is one character of a value or more.
        """
        ours: list[str | None] = []  # a literal character, or None: one value character
        stars: set[int] = set()  # the items that repeat (zero or more): a value's rest
        pos = 0
        for m in _PLACEHOLDER.finditer(self.text):
            ours.extend(self.text[pos : m.start()])
            ours.extend((None, None))
            stars.add(len(ours) - 1)
            pos = m.end()
        ours.extend(self.text[pos:])
        theirs: list[str | None] = []  # a literal character, or None: a hole (any text)
        pos = 0
        for m in _HOLE.finditer(template):
            theirs.extend(template[pos : m.start()])
            theirs.append(None)
            pos = m.end()
        theirs.extend(template[pos:])
        seen: set[tuple[int, int]] = set()
        todo = [(0, 0)]
        while todo:
            i, j = todo.pop()
            if (i, j) in seen:
                continue
            seen.add((i, j))
            if i == len(ours) and j == len(theirs):
                return True
            if i in stars:
                todo.append((i + 1, j))
            if j < len(theirs) and theirs[j] is None:
                todo.append((i, j + 1))
            if i == len(ours) or j == len(theirs):
                continue
            x, y = ours[i], theirs[j]
            # one character both can be: a hole takes any; a value character one of its class
            if y is None or (x == y if x is not None else bool(self._value.fullmatch(y))):
                todo.append((i if i in stars else i + 1, j if y is None else j + 1))
        return False

    def shape(self) -> str:
        """The pattern with its placeholder names erased: equal shapes match the same labels."""
        return _PLACEHOLDER.sub("{}", self.text)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, LabelPattern) and other.text == self.text

    def __hash__(self) -> int:
        return hash(self.text)

    def __repr__(self) -> str:
        return f"LabelPattern({self.text!r})"


def _semantic_pattern(text: str) -> LabelPattern:
    pattern = LabelPattern(text)
    if not _SEMANTIC.fullmatch(_PLACEHOLDER.sub("x", text)):
        raise ValueError(
            "a semantic label is made of letters, digits, '_' and '-' (and {name} "
            "placeholders), and does not start with '-'"
        )
    return pattern


def _key(table: str, key: str) -> str:
    """A TOML-style path to an entry, for error messages: ``labels."{object}-state"``."""
    return f"{table}.{key}" if _BARE_KEY.fullmatch(key) else f'{table}."{key}"'


def _read_toml(path: str | Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except OSError as exc:
        raise VocabularyError(str(path), None, f"cannot be read: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise VocabularyError(str(path), None, f"not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:  # TOML is UTF-8
        reason = f"not UTF-8 text: {exc.reason} at byte {exc.start}"
        raise VocabularyError(str(path), None, reason) from None
    except RecursionError:  # tomllib recurses into nested arrays and tables
        raise VocabularyError(str(path), None, "not valid TOML: nested too deep") from None


def _check_keys(data: Any, allowed: tuple[str, ...], source: str) -> Mapping[str, Any]:
    if not isinstance(data, Mapping):
        raise VocabularyError(source, None, f"expected a table, got {type(data).__name__}")
    for k in data:
        if k not in allowed:
            raise VocabularyError(source, str(k), f"unknown key (expected: {', '.join(allowed)})")
    return data


class Vocabulary:
    """The semantic labels a federation agreed on, with what they mean, and its concepts."""

    def __init__(
        self,
        labels: Mapping[str, str] | Iterable[str],
        *,
        concepts: Mapping[str, int] | None = None,
        name: str | None = None,
        source: str = "<vocabulary>",
    ) -> None:
        self.name = name
        self.source = source
        items = labels.items() if isinstance(labels, Mapping) else ((x, "") for x in labels)
        self._descriptions: dict[str, str] = {}
        self._fixed: dict[str, LabelPattern] = {}
        self._patterns: dict[str, LabelPattern] = {}
        shapes: dict[str, str] = {}
        for text, description in items:
            where = _key("labels", str(text))
            if not isinstance(description, str):
                raise VocabularyError(source, where, "the description must be a string")
            try:
                pattern = _semantic_pattern(text)
            except ValueError as exc:
                raise VocabularyError(source, where, str(exc)) from None
            if text in self._descriptions:
                raise VocabularyError(source, where, "listed twice")
            if pattern.parameterized:
                if pattern.shape() in shapes:
                    raise VocabularyError(
                        source, where, f"matches the same labels as {shapes[pattern.shape()]!r}"
                    )
                shapes[pattern.shape()] = text
                self._patterns[text] = pattern
            else:
                self._fixed[text] = pattern
            self._descriptions[text] = description
        if not self._descriptions:
            raise VocabularyError(source, "labels", "a vocabulary needs at least one label")
        self.concepts: dict[str, int] = {}
        for concept, arity in (concepts or {}).items():
            where = _key("concepts", str(concept))
            if not isinstance(concept, str) or not is_word(concept):
                raise VocabularyError(source, where, "a concept name must be an SL word")
            if isinstance(arity, bool) or not isinstance(arity, int) or arity < 0:
                raise VocabularyError(
                    source, where, f"the arity must be an integer >= 0, got {arity!r}"
                )
            self.concepts[concept] = arity

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        """Read a vocabulary from a TOML file; VocabularyError naming the file and key."""
        return cls.from_dict(_read_toml(path), source=str(path))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "<dict>") -> Vocabulary:
        """A vocabulary from a dict shaped like the file (``name``, ``labels``, ``concepts``)."""
        data = _check_keys(data, ("name", "labels", "concepts"), source)
        if "labels" not in data:
            raise VocabularyError(source, "labels", "missing: a vocabulary lists its labels")
        labels = data["labels"]
        if not isinstance(labels, Mapping | list):
            raise VocabularyError(source, "labels", "expected a table or a list of labels")
        concepts = data.get("concepts", {})
        if not isinstance(concepts, Mapping):
            raise VocabularyError(source, "concepts", "expected a table of name = arity")
        name = data.get("name")
        if name is not None and not isinstance(name, str):
            raise VocabularyError(source, "name", "expected a string")
        return cls(labels, concepts=concepts, name=name, source=source)

    # -- labels ---------------------------------------------------------------------------
    @property
    def labels(self) -> list[str]:
        """Every entry as written, fixed labels and patterns, in the file's order."""
        return list(self._descriptions)

    @property
    def patterns(self) -> list[LabelPattern]:
        """The parameterized entries, in the file's order."""
        return list(self._patterns.values())

    def description(self, label: str) -> str:
        """What a semantic label means, as the vocabulary says (its pattern's description)."""
        return self._descriptions[self.entry(label)[0].text]

    def pattern(self, text: str) -> LabelPattern | None:
        """The entry written exactly ``text`` (a fixed label or a pattern), or None."""
        return self._fixed.get(text) or self._patterns.get(text)

    def entry(self, label: str) -> tuple[LabelPattern, dict[str, str]]:
        """The entry ``label`` is an instance of, and its placeholder values."""
        fixed = self._fixed.get(label)
        if fixed is not None:
            return fixed, {}
        for pattern in self._patterns.values():
            values = pattern.match(label)
            if values is not None:
                return pattern, values
        raise UnknownSemanticLabel(label, Refusal.NOT_IN_VOCABULARY)

    def __contains__(self, label: object) -> bool:
        if not isinstance(label, str):
            return False
        try:
            self.entry(label)
        except UnknownSemanticLabel:
            return False
        return True

    def object_labels(self, identifier: str) -> list[str]:
        """The semantic labels about one object: each ``{object}``-only pattern filled in."""
        out = []
        for pattern in self._patterns.values():
            if pattern.params == (OBJECT,):
                try:
                    out.append(pattern.format(object=identifier))
                except ValueError:  # an identifier a semantic label cannot carry
                    return []
        return out

    # -- concepts ---------------------------------------------------------------------------
    def check(self, expr: Expression) -> None:
        """Refuse a formula using concepts the vocabulary does not have (when it lists some)."""
        if not self.concepts:
            return
        for atom in atoms_of(expr):
            arity = self.concepts.get(atom.predicate)
            if arity is None:
                known = ", ".join(sorted(self.concepts))
                raise SLEvaluationError(
                    SLEvaluationError.UNKNOWN_CONCEPT,
                    f"unknown concept {atom.predicate!r} in {atom} (the vocabulary has: {known})",
                )
            if arity != len(atom.args):
                raise SLEvaluationError(
                    SLEvaluationError.WRONG_ARITY,
                    f"{atom}: concept {atom.predicate!r} takes {arity} argument(s), "
                    f"not {len(atom.args)}",
                )

    def __repr__(self) -> str:
        return f"<Vocabulary {self.name or self.source!r} ({len(self._descriptions)} labels)>"


class LabelMapping:
    """One platform's translation between semantic labels and its local labels.

    ``labels`` maps vocabulary entries to local labels: a fixed semantic label to a local
    label, a vocabulary pattern to a local pattern with the same placeholders, or a
    concrete instance of a pattern (``car0-state``) to a local label, which wins over
    the pattern. Translation works both ways and refuses, with an `UnknownSemanticLabel`
    whose ``reason`` says why, what is not in the vocabulary or not mapped here.
    """

    def __init__(
        self,
        vocabulary: Vocabulary,
        labels: Mapping[str, str],
        *,
        source: str = "<mapping>",
    ) -> None:
        self.vocabulary = vocabulary
        self.source = source
        self._exact: dict[str, str] = {}  # semantic -> local
        self._reverse: dict[str, str] = {}  # local -> semantic
        self._patterns: dict[str, LabelPattern] = {}  # vocabulary pattern text -> local
        for semantic, local in labels.items():
            where = _key("labels", str(semantic))
            if not isinstance(local, str) or not local:
                raise VocabularyError(source, where, "the local label must be a non-empty string")
            entry = vocabulary.pattern(semantic)
            if entry is not None and entry.parameterized:
                self._add_pattern(entry, local, where)
                continue
            if semantic not in vocabulary:
                import difflib  # only for an error: not at every node's start

                near = difflib.get_close_matches(str(semantic), vocabulary.labels, n=3)
                hint = f" (did you mean {', '.join(map(repr, near))}?)" if near else ""
                raise VocabularyError(
                    source,
                    where,
                    f"not in the vocabulary {vocabulary.name or vocabulary.source}{hint}",
                )
            try:
                if LabelPattern(local, value=LOCAL_VALUE).parameterized:
                    raise VocabularyError(
                        source, where, f"a fixed label maps to a fixed local label, not {local!r}"
                    )
            except ValueError as exc:
                raise VocabularyError(source, where, f"local label {local!r}: {exc}") from None
            if local in self._reverse:
                raise VocabularyError(
                    source, where, f"{local!r} is also the mapping of {self._reverse[local]!r}"
                )
            self._exact[semantic] = local
            self._reverse[local] = semantic

    def _add_pattern(self, semantic: LabelPattern, local: str, where: str) -> None:
        try:
            pattern = LabelPattern(local, value=LOCAL_VALUE)
        except ValueError as exc:
            raise VocabularyError(self.source, where, f"local pattern {local!r}: {exc}") from None
        if sorted(pattern.params) != sorted(semantic.params):
            want = ", ".join(f"{{{p}}}" for p in semantic.params)
            raise VocabularyError(
                self.source, where, f"local pattern {local!r} must have exactly {want}"
            )
        self._patterns[semantic.text] = pattern

    @classmethod
    def load(cls, path: str | Path, vocabulary: Vocabulary) -> LabelMapping:
        """Read a mapping from a TOML file; VocabularyError naming the file and key."""
        return cls.from_dict(_read_toml(path), vocabulary, source=str(path))

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], vocabulary: Vocabulary, *, source: str = "<dict>"
    ) -> LabelMapping:
        """A mapping from a dict shaped like the file (``vocabulary``, ``labels``)."""
        data = _check_keys(data, ("vocabulary", "labels"), source)
        named = data.get("vocabulary")
        if named is not None and named != vocabulary.name:
            raise VocabularyError(
                source, "vocabulary", f"written for {named!r}, not for {vocabulary.name!r}"
            )
        labels = data.get("labels")
        if not isinstance(labels, Mapping):
            raise VocabularyError(source, "labels", "missing or not a table of semantic = local")
        return cls(vocabulary, labels, source=source)

    @property
    def mapped(self) -> list[str]:
        """The vocabulary entries (labels and patterns) this platform maps; no local labels."""
        return [*self._exact, *self._patterns]

    def local_entry(self, entry: str) -> LabelPattern:
        """The local label or local pattern an entry of `mapped` (as written) maps to."""
        local = self._exact.get(entry)
        return (
            LabelPattern(local, value=LOCAL_VALUE) if local is not None else self._patterns[entry]
        )

    def to_local(self, semantic: str) -> str:
        """The local label of ``semantic``; UnknownSemanticLabel says why if there is none."""
        local = self._exact.get(semantic)
        if local is not None:
            return local
        entry, values = self.vocabulary.entry(semantic)
        pattern = self._patterns.get(entry.text)
        if pattern is None:
            raise UnknownSemanticLabel(semantic, Refusal.NOT_MAPPED)
        return pattern.format(**values)

    def to_semantic(self, local: str) -> str:
        """The semantic label of a local one; UnknownSemanticLabel (reason not-mapped) if none."""
        semantic = self._reverse.get(local)
        if semantic is not None:
            return semantic
        for text, pattern in self._patterns.items():
            values = pattern.match(local)
            if values is None:
                continue
            vocab_pattern = self.vocabulary.pattern(text)
            assert vocab_pattern is not None
            try:
                semantic = vocab_pattern.format(**values)
            except ValueError:  # a value a semantic label cannot carry (car-5)
                continue
            # a concrete entry may have claimed that semantic label for another local one
            if self.to_local(semantic) == local:
                return semantic
        raise UnknownSemanticLabel(local, Refusal.NOT_MAPPED, local=True)

    def maps(self, semantic: str) -> bool:
        """Whether ``semantic`` is in the vocabulary and mapped on this platform."""
        try:
            self.to_local(semantic)
        except UnknownSemanticLabel:
            return False
        return True

    def resolve(self, semantic: str, instance: DyKnowInstance) -> str:
        """The local label of ``semantic`` if ``instance`` publishes it; else refused with why."""
        local = self.to_local(semantic)
        if not instance.has_label(local):
            raise UnknownSemanticLabel(semantic, Refusal.NOT_PROVIDED)
        return local

    def __repr__(self) -> str:
        return f"<LabelMapping {self.source!r} ({len(self._exact) + len(self._patterns)} entries)>"


def semantic_labels(instance: DyKnowInstance, mapping: LabelMapping) -> list[str]:
    """The semantic labels ``instance`` can provide now: its published labels, translated."""
    out = set()
    for local in instance.labels():
        try:
            out.add(mapping.to_semantic(local))
        except UnknownSemanticLabel:
            continue
    return sorted(out)
