"""The ontology: vocabularies, label mappings, SL parsing and evaluation, facts, label search.

Streams run on a ManualClock; domain changes are awaited with ``feed.sync()``, so nothing
sleeps for time to pass.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, Source
from ontology import (
    And,
    Atom,
    Constant,
    DomainRule,
    Expression,
    Fact,
    FactBase,
    FactFeed,
    Formula,
    LabelMapping,
    LabelPattern,
    Not,
    OntologyError,
    Or,
    PlatformLabels,
    Query,
    QueryKind,
    Refusal,
    SLEvaluationError,
    SLSyntaxError,
    StreamRule,
    UnknownSemanticLabel,
    Variable,
    Vocabulary,
    VocabularyError,
    evaluate,
    find_labels,
    parse,
    semantic_labels,
)

S = NS_PER_S

VOCABULARY_TOML = """\
name = "traffic-monitoring"

[labels]
heli-position = "this platform's own position (x, y, z), metres"
heli-altitude = "this platform's own altitude, metres"
heli-max-speed = "this platform's top speed, m/s"
"{object}-state" = "the state of the tracked object, e.g. car5-state"
"{object}-speed" = "the speed of the tracked object, m/s"
"{object}-max-speed" = "the speed limit an object must keep"

[concepts]
Car = 1
Color = 2
OnRoad = 2
Speeding = 1
"""

MAPPING_TOML = """\
vocabulary = "traffic-monitoring"

[labels]
heli-position = "uav/self/position"
heli-max-speed = "uav/self/max_speed"
"{object}-state" = "car/{object}/state"
"{object}-speed" = "car/{object}/speed"
car0-state = "tracker/main/state"
"""


@pytest.fixture
def vocabulary(tmp_path: Path) -> Vocabulary:
    path = tmp_path / "vocabulary.toml"
    path.write_text(VOCABULARY_TOML)
    return Vocabulary.load(path)


@pytest.fixture
def mapping(tmp_path: Path, vocabulary: Vocabulary) -> LabelMapping:
    path = tmp_path / "uav-a.toml"
    path.write_text(MAPPING_TOML)
    return LabelMapping.load(path, vocabulary)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(1000 * S)


@pytest.fixture
async def dk(clock: ManualClock) -> AsyncIterator[DyKnowInstance]:
    async with DyKnowInstance("uav-a", clock=clock) as instance:
        yield instance


# --- vocabulary ----------------------------------------------------------------------------


def test_vocabulary_loads_labels_patterns_and_concepts(vocabulary: Vocabulary) -> None:
    assert vocabulary.name == "traffic-monitoring"
    assert vocabulary.labels[:3] == ["heli-position", "heli-altitude", "heli-max-speed"]
    assert [p.text for p in vocabulary.patterns] == [
        "{object}-state",
        "{object}-speed",
        "{object}-max-speed",
    ]
    assert vocabulary.concepts == {"Car": 1, "Color": 2, "OnRoad": 2, "Speeding": 1}
    assert "heli-position" in vocabulary
    assert "car5-state" in vocabulary
    assert "car5-max-speed" in vocabulary
    assert "car5-colour" not in vocabulary
    assert "car-5-state" not in vocabulary  # a value never holds a '-'
    assert vocabulary.entry("car5-max-speed") == (
        LabelPattern("{object}-max-speed"),
        {"object": "car5"},
    )
    assert vocabulary.description("car5-state").startswith("the state of the tracked object")
    assert vocabulary.object_labels("car5") == ["car5-state", "car5-speed", "car5-max-speed"]
    assert vocabulary.object_labels("car-5") == []


def test_vocabulary_from_a_list_and_a_dict() -> None:
    v = Vocabulary(["heli-position", "{object}-state"])
    assert v.labels == ["heli-position", "{object}-state"]
    assert v.concepts == {}
    d = Vocabulary.from_dict({"labels": {"a": "the a"}, "concepts": {"P": 0}})
    assert d.description("a") == "the a"
    assert d.name is None


def test_fixed_label_wins_over_a_pattern() -> None:
    v = Vocabulary(["{object}-state", "heli-state"])
    assert v.entry("heli-state") == (LabelPattern("heli-state"), {})


@pytest.mark.parametrize(
    ("text", "key", "fragment"),
    [
        ("name = 'x'\n[labels\n", None, "not valid TOML"),
        ("name = 'x'\n", "labels", "missing"),
        ("labels = 'heli'\n", "labels", "a table or a list"),
        ("colour = 1\n[labels]\na = ''\n", "colour", "unknown key"),
        ("[labels]\n", "labels", "at least one label"),
        ('[labels]\n"car 5" = ""\n', 'labels."car 5"', "letters, digits"),
        ('[labels]\n"-x" = ""\n', "labels.-x", "does not start with '-'"),
        ('[labels]\n"{a}{b}" = ""\n', 'labels."{a}{b}"', "touch"),
        ('[labels]\n"{a}-{a}" = ""\n', 'labels."{a}-{a}"', "appears twice"),
        ('[labels]\n"{a-state" = ""\n', 'labels."{a-state"', "brace"),
        ('[labels]\n"{object}-state" = ""\n"{car}-state" = ""\n', 'labels."{car}-state"', "same"),
        ("[labels]\na = 3\n", "labels.a", "description must be a string"),
        ("[labels]\na = ''\n[concepts]\nCar = -1\n", "concepts.Car", "arity"),
        ("[labels]\na = ''\n[concepts]\nCar = true\n", "concepts.Car", "arity"),
        ('[labels]\na = ""\n[concepts]\n"(x" = 1\n', 'concepts."(x"', "SL word"),
        ("name = 3\n[labels]\na = ''\n", "name", "string"),
    ],
)
def test_bad_vocabulary_names_file_and_key(
    tmp_path: Path, text: str, key: str | None, fragment: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(VocabularyError) as info:
        Vocabulary.load(path)
    err = info.value
    assert err.source == str(path)
    assert err.key == key
    assert fragment in str(err)
    assert str(err).startswith(f"{path}: ")
    assert isinstance(err, OntologyError) and isinstance(err, ValueError)


def test_toml_syntax_error_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[labels]\na = 'x'\nb = \n")
    with pytest.raises(VocabularyError, match=r"bad\.toml: not valid TOML: .*line 3"):
        Vocabulary.load(path)


def test_missing_vocabulary_file(tmp_path: Path) -> None:
    with pytest.raises(VocabularyError, match="cannot be read"):
        Vocabulary.load(tmp_path / "nowhere.toml")


# --- translation ---------------------------------------------------------------------------


def test_translation_both_ways(mapping: LabelMapping) -> None:
    assert mapping.to_local("heli-position") == "uav/self/position"
    assert mapping.to_semantic("uav/self/position") == "heli-position"
    assert mapping.to_local("car5-state") == "car/car5/state"
    assert mapping.to_semantic("car/car5/state") == "car5-state"
    assert mapping.to_local("car5-speed") == "car/car5/speed"
    assert mapping.to_semantic("car/car5/speed") == "car5-speed"
    # the concrete entry wins over the pattern, both ways
    assert mapping.to_local("car0-state") == "tracker/main/state"
    assert mapping.to_semantic("tracker/main/state") == "car0-state"
    assert mapping.mapped == [
        "heli-position",
        "heli-max-speed",
        "car0-state",
        "{object}-state",
        "{object}-speed",
    ]


@pytest.mark.parametrize(
    ("semantic", "reason"),
    [
        ("car5-colour", Refusal.NOT_IN_VOCABULARY),
        ("uav/self/position", Refusal.NOT_IN_VOCABULARY),
        ("", Refusal.NOT_IN_VOCABULARY),
        ("heli-altitude", Refusal.NOT_MAPPED),
        ("car5-max-speed", Refusal.NOT_MAPPED),
    ],
)
def test_unknown_semantic_labels_are_refused_with_the_reason(
    mapping: LabelMapping, semantic: str, reason: Refusal
) -> None:
    with pytest.raises(UnknownSemanticLabel) as info:
        mapping.to_local(semantic)
    assert info.value.reason is reason
    assert info.value.label == semantic
    assert reason.value in str(info.value)
    # what a refusal may carry to another platform names no local label
    assert "/" not in str(info.value).replace(semantic, "")
    assert not mapping.maps(semantic)


@pytest.mark.parametrize(
    "local",
    [
        "uav/self/altitude",  # not mapped at all
        "car/car5/colour",  # not the shape of any local pattern
        "car/car-5/state",  # an identifier a semantic label cannot carry
        "car/car0/state",  # car0-state is mapped to another local label
    ],
)
def test_local_labels_without_a_semantic_label(mapping: LabelMapping, local: str) -> None:
    with pytest.raises(UnknownSemanticLabel) as info:
        mapping.to_semantic(local)
    assert info.value.reason is Refusal.NOT_MAPPED
    assert info.value.local


@pytest.mark.parametrize(
    ("labels", "key", "fragment"),
    [
        ({"heli-colour": "x"}, "labels.heli-colour", "not in the vocabulary"),
        ({"{object}-colour": "car/{object}/c"}, 'labels."{object}-colour"', "not in the"),
        ({"{object}-state": "car/state"}, 'labels."{object}-state"', "exactly {object}"),
        ({"{object}-state": "car/{id}/state"}, 'labels."{object}-state"', "exactly {object}"),
        ({"heli-position": "uav/{object}/p"}, "labels.heli-position", "fixed local label"),
        ({"heli-position": ""}, "labels.heli-position", "non-empty"),
        ({"heli-position": "a", "heli-max-speed": "a"}, "labels.heli-max-speed", "also"),
    ],
)
def test_bad_mapping_names_the_key(
    vocabulary: Vocabulary, labels: dict[str, str], key: str, fragment: str
) -> None:
    with pytest.raises(VocabularyError) as info:
        LabelMapping.from_dict({"labels": labels}, vocabulary, source="uav-b.toml")
    assert info.value.key == key
    assert fragment in str(info.value)
    assert str(info.value).startswith("uav-b.toml: ")


def test_mapping_for_another_vocabulary_is_refused(tmp_path: Path, vocabulary: Vocabulary) -> None:
    path = tmp_path / "m.toml"
    path.write_text('vocabulary = "harbour"\n[labels]\nheli-position = "p"\n')
    with pytest.raises(VocabularyError, match=r"m\.toml: vocabulary: written for 'harbour'"):
        LabelMapping.load(path, vocabulary)
    with pytest.raises(VocabularyError, match="labels: missing"):
        LabelMapping.from_dict({}, vocabulary)


async def test_resolve_and_semantic_labels(dk: DyKnowInstance, mapping: LabelMapping) -> None:
    for label in [
        "uav/self/position",
        "car/car5/state",
        "car/car6/speed",
        "car/car-7/state",
        "tracker/main/state",
        "car/car0/state",
        "internal/debug",
    ]:
        dk.add_source(label)
    assert semantic_labels(dk, mapping) == [
        "car0-state",
        "car5-state",
        "car6-speed",
        "heli-position",
    ]
    assert mapping.resolve("car5-state", dk) == "car/car5/state"
    with pytest.raises(UnknownSemanticLabel) as info:
        mapping.resolve("heli-max-speed", dk)
    assert info.value.reason is Refusal.NOT_PROVIDED
    platform = PlatformLabels(mapping, dk)
    assert platform.provides() == semantic_labels(dk, mapping)
    assert platform.to_local("car5-state") == "car/car5/state"
    assert platform.to_semantic("car/car5/state") == "car5-state"


def test_label_patterns() -> None:
    p = LabelPattern("{object}-state")
    assert p.parameterized and p.params == ("object",)
    assert p.match("car5-state") == {"object": "car5"}
    assert p.match("car-5-state") is None
    assert p.format(object="car5") == "car5-state"
    with pytest.raises(ValueError, match="cannot stand for"):
        p.format(object="car 5")
    with pytest.raises(ValueError, match="needs values"):
        p.format()
    assert not LabelPattern("heli-position").parameterized
    two = LabelPattern("{object}-{feature}")
    assert two.match("car5-speed") == {"object": "car5", "feature": "speed"}


_ids = st.from_regex(r"[A-Za-z0-9_]{1,12}", fullmatch=True)


@given(identifier=_ids, pattern=st.sampled_from(["{object}-state", "{object}-speed"]))
def test_to_semantic_inverts_to_local(identifier: str, pattern: str) -> None:
    vocabulary = Vocabulary.from_dict({"labels": {"{object}-state": "", "{object}-speed": ""}})
    mapping = LabelMapping(
        vocabulary, {"{object}-state": "car/{object}/state", "{object}-speed": "speed_{object}"}
    )
    semantic = LabelPattern(pattern).format(object=identifier)
    local = mapping.to_local(semantic)
    assert local != semantic
    assert mapping.to_semantic(local) == semantic


# --- SL parsing ----------------------------------------------------------------------------

x, y, r = Variable("x"), Variable("y"), Variable("r")


def C(value: Any, quoted: bool = False) -> Constant:
    return Constant(value, quoted)


@pytest.mark.parametrize(
    ("text", "ast"),
    [
        ("(Car ?x)", Atom("Car", (x,))),
        ("(Color ?x blue)", Atom("Color", (x, C("blue")))),
        ("(OnRoad car5 road7)", Atom("OnRoad", (C("car5"), C("road7")))),
        ('(Color ?x "dark blue")', Atom("Color", (x, C("dark blue", True)))),
        (r'(Says ?x "a \"b\" \\ c")', Atom("Says", (x, C('a "b" \\ c', True)))),
        ("(Lanes road7 3)", Atom("Lanes", (C("road7"), C(3)))),
        ("(Speed ?x -2.5e1)", Atom("Speed", (x, C(-25.0)))),
        ("(Raining)", Atom("Raining", ())),
        ("(and (Car ?x) (Color ?x blue))", And((Atom("Car", (x,)), Atom("Color", (x, C("blue")))))),
        ("(or (Car ?x))", Or((Atom("Car", (x,)),))),
        ("(not (Car ?x))", Not(Atom("Car", (x,)))),
        ("(all ?x (Car ?x))", Query(QueryKind.ALL, (x,), Atom("Car", (x,)))),
        ("(any ?x (Car ?x))", Query(QueryKind.ANY, (x,), Atom("Car", (x,)))),
        ("(iota ?x (Car ?x))", Query(QueryKind.IOTA, (x,), Atom("Car", (x,)))),
        (
            "(all (sequence ?x ?r) (OnRoad ?x ?r))",
            Query(QueryKind.ALL, (x, r), Atom("OnRoad", (x, r))),
        ),
        (
            "(all ?x\n  (and (Car ?x)\n       (Color ?x blue)\n       (OnRoad ?x road7)))",
            Query(
                QueryKind.ALL,
                (x,),
                And(
                    (
                        Atom("Car", (x,)),
                        Atom("Color", (x, C("blue"))),
                        Atom("OnRoad", (x, C("road7"))),
                    )
                ),
            ),
        ),
    ],
)
def test_parse_every_construct(text: str, ast: Expression) -> None:
    assert parse(text) == ast
    assert parse(str(ast)) == ast


def test_a_word_and_a_string_are_the_same_constant() -> None:
    assert parse('(Color ?x "blue")') == parse("(Color ?x blue)")
    assert str(parse('(Color ?x "blue")')) == '(Color ?x "blue")'
    assert str(Constant("dark blue")) == '"dark blue"'  # not a word: quoted when printed
    assert str(Constant("7")) == '"7"'  # a string, not the number 7


@pytest.mark.parametrize(
    ("text", "line", "column", "fragment"),
    [
        ("(all ?x (and (Car ?x) (Color ?x blue))", 1, 1, "never closed"),
        ("(all ?x (Car ?x)", 1, 1, "never closed"),
        ("(Car ?x", 1, 1, "never closed"),
        ("(and (Car ?x) (Color ?x", 1, 15, "never closed"),
        ("(Car ?x))", 1, 9, "unbalanced ')'"),
        ("(Car ?x) (Car ?y)", 1, 10, "trailing input"),
        ("(Car ?x) blue", 1, 10, "trailing input"),
        ("(adn (Car ?x) (Color ?x blue))", 1, 2, "unknown operator 'adn'"),
        ("(exists ?x (Car ?x))", 1, 2, "unsupported SL operator 'exists'"),
        ("(all (Car ?x))", 1, 6, "expected a variable after 'all'"),
        ("(iota blue (Car ?x))", 1, 7, "expected a variable after 'iota'"),
        ("(all (sequence) (Car ?x))", 1, 15, "at least one variable"),
        ("(all (sequence ?x ?x) (Car ?x))", 1, 19, "listed twice"),
        ("(all ?x)", 1, 8, "expected a formula"),
        ("(all ?x (Car ?x) (Car ?x))", 1, 18, "expected ')'"),
        ("(not (Car ?x) (Car ?y))", 1, 15, "exactly one formula"),
        ("(and)", 1, 5, "at least one formula"),
        ("()", 1, 2, "empty formula"),
        ("", 1, 1, "empty formula"),
        ("   \n  ", 2, 3, "empty formula"),
        ("Car", 1, 1, "expected '('"),
        ("(?x Car)", 1, 2, "predicate name"),
        ("(Car ?)", 1, 6, "variable name"),
        ('(Color ?x "blue)', 1, 11, "unterminated string"),
        ("(Speed ?x 7kmh)", 1, 11, "malformed number"),
        ("(Car #x)", 1, 6, "unexpected '#'"),
        ("(and (Car ?x) (all ?y (Car ?y)))", 1, 16, "only be the whole query"),
        ("(all ?x\n  (and (Car ?x)\n       (Color ?x blue)\n  (OnRoad ?x road7))))", 4, 22, "')'"),
        ("(all ?x\n  (and (Car ?x)\n       (Colour ?x (blue))))", 3, 9, "unknown operator"),
    ],
)
def test_syntax_errors_point_at_the_position(
    text: str, line: int, column: int, fragment: str
) -> None:
    with pytest.raises(SLSyntaxError) as info:
        parse(text)
    err = info.value
    assert (err.line, err.column) == (line, column), str(err)
    assert fragment in err.message
    assert f"(line {line}, column {column})" in str(err)
    # the excerpt is the offending line, indented by two, with a caret under the column
    shown, caret = err.excerpt.split("\n")
    assert shown == "  " + text.split("\n")[line - 1]
    assert caret == " " * (column + 1) + "^"


def test_excerpt_of_a_long_line_is_cut_around_the_position() -> None:
    text = "(and " + " ".join(f"(Car c{i})" for i in range(40)) + " (Car ?x)"
    with pytest.raises(SLSyntaxError) as info:
        parse(text)
    shown, caret = info.value.excerpt.split("\n")
    assert len(shown) < 90 and shown.strip().startswith("(and")
    text = " ".join(f"(Car c{i})" for i in range(40))
    with pytest.raises(SLSyntaxError) as info:
        parse(text)
    assert info.value.column == 10
    text = "(and " + " ".join(f"(Car c{i})" for i in range(40)) + " (Car ?x) (Car"
    with pytest.raises(SLSyntaxError) as info:
        parse(text)
    shown, caret = info.value.excerpt.split("\n")
    assert shown.strip().startswith("…")
    assert shown[caret.index("^")] == "("  # the unclosed (Car


# generated formulas: printing then parsing gives the same AST

_reserved = {"all", "any", "iota", "and", "or", "not", "exists", "forall", "implies", "equiv"}
_reserved |= {"B", "U", "I", "PG", "feasible", "done", "result", "set", "sequence", "action"}
_words = st.from_regex(r"[A-Za-z_][A-Za-z0-9_\-.#:/]{0,8}", fullmatch=True)
_predicates = _words.filter(lambda w: w not in _reserved)
_variables = st.builds(Variable, _words)
_constants = st.one_of(
    st.builds(Constant, _words),
    st.builds(Constant, st.text(max_size=8), st.just(True)),
    st.builds(Constant, st.integers(-(10**20), 10**20)),
    st.builds(Constant, st.floats(allow_nan=False, allow_infinity=False)),
)
_atoms = st.builds(
    Atom, _predicates, st.lists(st.one_of(_variables, _constants), max_size=3).map(tuple)
)
_formulas: st.SearchStrategy[Formula] = st.recursive(
    _atoms,
    lambda inner: st.one_of(
        st.builds(And, st.lists(inner, min_size=1, max_size=3).map(tuple)),
        st.builds(Or, st.lists(inner, min_size=1, max_size=3).map(tuple)),
        st.builds(Not, inner),
    ),
    max_leaves=10,
)
_queries = st.builds(
    Query,
    st.sampled_from(QueryKind),
    st.lists(_variables, min_size=1, max_size=3, unique=True).map(tuple),
    _formulas,
)


@given(st.one_of(_formulas, _queries))
def test_parse_print_roundtrip(ast: Expression) -> None:
    assert parse(str(ast)) == ast


# --- SL evaluation -------------------------------------------------------------------------

TRAFFIC = [
    "(Car car5)",
    "(Car car6)",
    "(Car car7)",
    "(Car car8)",
    "(Color car5 blue)",
    "(Color car6 blue)",
    "(Color car7 red)",
    '(Color car8 "dark blue")',
    "(OnRoad car5 road7)",
    "(OnRoad car6 road8)",
    "(OnRoad car7 road7)",
    "(Lanes road7 2)",
    "(Lanes road8 3)",
]


@pytest.fixture
def traffic() -> FactBase:
    return FactBase(Fact.parse(f) for f in TRAFFIC)


def answers(text: str, facts: FactBase) -> list[Any]:
    out = evaluate(parse(text), facts)
    return [next(iter(b.values())) if len(b) == 1 else tuple(b.values()) for b in out]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("(all ?x (and (Car ?x) (Color ?x blue) (OnRoad ?x road7)))", ["car5"]),
        ("(all ?x (and (Car ?x) (Color ?x blue)))", ["car5", "car6"]),
        ('(all ?x (Color ?x "dark blue"))', ["car8"]),
        ("(all ?x (or (Color ?x red) (OnRoad ?x road8)))", ["car6", "car7"]),
        ("(all ?x (and (Car ?x) (not (Color ?x blue))))", ["car7", "car8"]),
        ("(all ?x (and (not (Color ?x blue)) (Car ?x)))", ["car7", "car8"]),
        ("(all ?x (and (Car ?x) (not (OnRoad ?x ?r))))", ["car8"]),  # on no road at all
        ("(all ?x (and (Car ?x) (OnRoad ?x ?r)))", ["car5", "car6", "car7"]),  # ?r existential
        ("(all ?r (OnRoad ?x ?r))", ["road7", "road8"]),
        (
            "(all (sequence ?x ?r) (OnRoad ?x ?r))",
            [("car5", "road7"), ("car6", "road8"), ("car7", "road7")],
        ),
        ("(all ?x (and (Car ?x) (OnRoad ?x ?r) (Lanes ?r 2)))", ["car5", "car7"]),
        ("(all ?n (Lanes ?r ?n))", [2, 3]),
        ("(all ?x (Lanes ?x 2.0))", ["road7"]),  # numbers compare by value
        ("(all ?x (Truck ?x))", []),
        ("(all ?x (Car ?x ?y))", []),  # no Car facts of arity 2
        ("(all ?x (not (or (Car ?x) (Color ?y ?x) (OnRoad ?y ?x))))", [2, 3]),
        ("(any ?x (and (Car ?x) (Color ?x blue)))", ["car5"]),
        ("(any ?x (Truck ?x))", []),
        ("(iota ?x (Color ?x red))", ["car7"]),
        ("(and (Car car5) (Color car5 blue))", [{}]),
        ("(Car car9)", []),
    ],
)
def test_evaluate(traffic: FactBase, text: str, expected: list[Any]) -> None:
    if expected == [{}]:
        assert evaluate(parse(text), traffic) == [{}]
    else:
        assert answers(text, traffic) == expected


def test_a_query_variable_the_formula_leaves_free_ranges_over_every_object(
    traffic: FactBase,
) -> None:
    every = answers("(all ?x (OnRoad car5 road7))", traffic)
    assert every[:2] == [2, 3]  # numbers first, then words and strings
    assert set(every) == traffic.objects
    assert answers("(all ?x (OnRoad car5 road8))", traffic) == []


def test_bare_formula_is_answered_over_its_variables(traffic: FactBase) -> None:
    assert evaluate(parse("(OnRoad ?x road7)"), traffic) == [{"x": "car5"}, {"x": "car7"}]
    assert evaluate(parse("(Lanes ?r ?n)"), traffic) == [
        {"r": "road7", "n": 2},
        {"r": "road8", "n": 3},
    ]


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("(iota ?x (Color ?x blue))", SLEvaluationError.SEVERAL_MATCHES),
        ("(iota ?x (Color ?x green))", SLEvaluationError.NO_MATCH),
    ],
)
def test_iota_needs_exactly_one_answer(traffic: FactBase, text: str, reason: str) -> None:
    with pytest.raises(SLEvaluationError) as info:
        evaluate(parse(text), traffic)
    assert info.value.reason == reason
    if reason == SLEvaluationError.SEVERAL_MATCHES:
        assert "2 answers" in str(info.value) and "car5, car6" in str(info.value)


def test_vocabulary_checks_concepts(vocabulary: Vocabulary) -> None:
    vocabulary.check(parse("(all ?x (and (Car ?x) (Color ?x blue)))"))
    with pytest.raises(SLEvaluationError) as info:
        vocabulary.check(parse("(all ?x (Colour ?x blue))"))
    assert info.value.reason == SLEvaluationError.UNKNOWN_CONCEPT
    assert "Colour" in str(info.value) and "Color" in str(info.value)
    with pytest.raises(SLEvaluationError) as info:
        vocabulary.check(parse("(all ?x (Car ?x blue))"))
    assert info.value.reason == SLEvaluationError.WRONG_ARITY
    Vocabulary(["a"]).check(parse("(Anything ?x)"))  # no concepts listed: nothing to check


# the evaluator agrees with brute force over every assignment of the variables

_objs = ["a", "b", "c"]
_small_facts = st.lists(
    st.one_of(
        st.builds(lambda o: Fact("P", (o,)), st.sampled_from(_objs)),
        st.builds(lambda o, p: Fact("Q", (o, p)), st.sampled_from(_objs), st.sampled_from(_objs)),
    ),
    max_size=8,
)
_small_terms = st.one_of(st.sampled_from([x, y]), st.sampled_from([Constant("a"), Constant("b")]))
_small_atoms = st.one_of(
    st.builds(lambda t: Atom("P", (t,)), _small_terms),
    st.builds(lambda t, u: Atom("Q", (t, u)), _small_terms, _small_terms),
)
_small_formulas: st.SearchStrategy[Formula] = st.recursive(
    _small_atoms,
    lambda inner: st.one_of(
        st.builds(And, st.lists(inner, min_size=1, max_size=3).map(tuple)),
        st.builds(Or, st.lists(inner, min_size=1, max_size=3).map(tuple)),
        st.builds(Not, inner),
    ),
    max_leaves=6,
)


def _children(f: Formula) -> tuple[Formula, ...]:
    if isinstance(f, And | Or):
        return f.operands
    return (f.operand,) if isinstance(f, Not) else ()


def _ys(f: Formula) -> int:
    if isinstance(f, Atom):
        return sum(a == y for a in f.args)
    return sum(map(_ys, _children(f)))


def _truth(f: Formula, env: dict[str, Any], facts: FactBase, domain: list[Any], ys: int) -> bool:
    """Truth by the definition: ∃?y at the smallest subformula holding every ?y."""
    if "y" not in env and ys and _ys(f) == ys and all(_ys(c) < ys for c in _children(f)):
        return any(_truth(f, env | {"y": d}, facts, domain, ys) for d in domain)
    match f:
        case Atom():
            args = tuple(env[a.name] if isinstance(a, Variable) else a.value for a in f.args)
            return Fact(f.predicate, args) in facts
        case And():
            return all(_truth(op, env, facts, domain, ys) for op in f.operands)
        case Or():
            return any(_truth(op, env, facts, domain, ys) for op in f.operands)
        case Not():
            return not _truth(f.operand, env, facts, domain, ys)
    raise AssertionError(f)


@given(facts=_small_facts, formula=_small_formulas)
def test_evaluate_agrees_with_brute_force(facts: list[Fact], formula: Formula) -> None:
    fb = FactBase(facts)
    domain = sorted(fb.objects, key=str)
    # ?x is the query's variable, ranging over every object; ?y is existential
    expected = [vx for vx in domain if _truth(formula, {"x": vx}, fb, domain, _ys(formula))]
    got = [b["x"] for b in evaluate(Query(QueryKind.ALL, (x,), formula), fb)]
    assert sorted(got, key=str) == expected


# --- facts --------------------------------------------------------------------------------


def test_fact_base() -> None:
    fb = FactBase()
    assert fb.add("Car", "car5")
    assert not fb.add("Car", "car5")
    assert fb.add(Fact.parse("(Color car5 blue)"))
    assert Fact("Car", ("car5",)) in fb
    assert fb.objects == {"car5", "blue"}
    v = fb.version
    assert fb.replace("Color", "car5", "red")
    assert fb.version > v
    assert fb.about("Color", "car5") == [Fact("Color", ("car5", "red"))]
    assert not fb.replace("Color", "car5", "red")
    assert fb.objects == {"car5", "red"}
    assert fb.add("Color", "car5", "green")
    assert fb.retract_about("Color", "car5") == 2
    assert fb.retract("Car", "car5")
    assert not fb.retract("Car", "car5")
    assert len(fb) == 0 and fb.objects == frozenset() and fb.predicates == []
    fb.add("Lanes", "road7", 2)
    assert str(fb.facts()[0]) == "(Lanes road7 2)"
    assert str(Fact.of("Color", "car5", "dark blue")) == '(Color car5 "dark blue")'


@pytest.mark.parametrize(
    "args", [("car5", None), ("car5", True), ("car5", float("nan")), ("car5", (1, 2))]
)
def test_facts_hold_only_constants(args: tuple[Any, ...]) -> None:
    with pytest.raises((TypeError, ValueError)):
        FactBase().add("Color", *args)


def test_fact_parse_refuses_non_ground_atoms() -> None:
    with pytest.raises(ValueError, match="not a ground atom"):
        Fact.parse("(Car ?x)")
    with pytest.raises(ValueError, match="not a ground atom"):
        Fact.parse("(not (Car car5))")


# --- the fact feed ------------------------------------------------------------------------


class Traffic:
    """A platform tracking cars: a ``cars`` domain and per-car color and road streams."""

    def __init__(self, dk: DyKnowInstance) -> None:
        self.dk = dk
        self.cars = dk.objects.add_domain("cars")
        self.sources: dict[str, Source] = {}

    def car(self, identifier: str, *, member: bool = True) -> None:
        self.dk.objects.reserve(identifier)
        if member:
            self.cars.add(identifier)

    def push(self, label: str, value: Any, valid_time: int | None = None) -> None:
        if label not in self.sources:
            self.sources[label] = self.dk.add_source(label)
        self.sources[label].push(value, valid_time=valid_time)


RULES = [
    DomainRule("cars", "Car"),
    StreamRule("car/{object}/color", "Color", domain="cars"),
    StreamRule("car/{object}/road", "OnRoad"),
]


async def test_feed_keeps_facts_current(dk: DyKnowInstance, clock: ManualClock) -> None:
    t = Traffic(dk)
    t.car("car5")
    t.push("car/car5/color", "green")
    t.push("car/car5/color", "blue")  # before the feed starts: its latest value counts
    t.push("car/car5/road", "road7")
    fb = FactBase()
    async with FactFeed(dk, fb, RULES) as feed:
        assert set(map(str, fb)) == {"(Car car5)", "(Color car5 blue)", "(OnRoad car5 road7)"}

        clock.advance(S)
        t.push("car/car5/color", "red")  # replaces the previous color
        assert fb.about("Color", "car5") == [Fact("Color", ("car5", "red"))]

        t.push("car/car5/color", "yellow", valid_time=clock.now() - S // 2)  # older: ignored
        assert fb.about("Color", "car5") == [Fact("Color", ("car5", "red"))]

        # a new car: membership, then a stream published after it joined
        t.car("car6")
        await feed.sync()
        assert Fact("Car", ("car6",)) in fb
        t.push("car/car6/color", "blue")
        assert Fact("Color", ("car6", "blue")) in fb

        # a road stream published after the start is followed from its first sample on
        # (no domain to follow: the feed hears of the new label)
        t.push("car/car6/road", "road8")
        assert fb.about("OnRoad", "car6") == [Fact("OnRoad", ("car6", "road8"))]
        assert feed.refresh() == 0  # nothing was left for a refresh to find

        # a car leaves the domain
        t.cars.remove("car6")
        await feed.sync()
        assert Fact("Car", ("car6",)) not in fb

        # None retracts
        t.push("car/car5/road", None)
        assert fb.about("OnRoad", "car5") == []

        # a removed stream's facts go with it
        t.push("car/car5/road", "road9")
        assert fb.about("OnRoad", "car5") == [Fact("OnRoad", ("car5", "road9"))]
        dk.remove_process("source:car/car5/road")
        assert fb.about("OnRoad", "car5") == []
        # published again under the same label: followed again
        del t.sources["car/car5/road"]
        t.push("car/car5/road", "road3")
        assert fb.about("OnRoad", "car5") == [Fact("OnRoad", ("car5", "road3"))]

        # a value that cannot be a fact is skipped and counted; the publisher never sees it
        t.push("car/car5/color", {"r": 1})
        assert feed.errors == 1 and "car5" in (feed.last_error or "")
        assert fb.about("Color", "car5") == [Fact("Color", ("car5", "red"))]
        assert feed.stats()["errors"] == 1

    # leaving unsubscribes; the facts stay
    t.push("car/car5/color", "black")
    assert fb.about("Color", "car5") == [Fact("Color", ("car5", "red"))]
    with pytest.raises(OntologyError, match="entered once"):
        async with feed:
            pass


async def test_feed_convert_and_unary_rules(dk: DyKnowInstance) -> None:
    t = Traffic(dk)
    t.car("car5")
    rules = [
        StreamRule("car/{object}/speeding", "Speeding", unary=True),
        StreamRule(
            "car/{object}/speed", "SpeedClass", convert=lambda v: None if v < 0 else int(v // 10)
        ),
    ]
    fb = FactBase()
    t.push("car/car5/speeding", False)
    t.push("car/car5/speed", 42.0)
    async with FactFeed(dk, fb, rules):
        assert set(map(str, fb)) == {"(SpeedClass car5 4)"}
        t.push("car/car5/speeding", True)
        assert Fact("Speeding", ("car5",)) in fb
        t.push("car/car5/speeding", False)
        assert Fact("Speeding", ("car5",)) not in fb
        t.push("car/car5/speed", -1.0)
        assert fb.about("SpeedClass", "car5") == []


async def test_feed_domain_removed(dk: DyKnowInstance) -> None:
    t = Traffic(dk)
    t.car("car5")
    fb = FactBase([Fact("Car", ("truck1",))])  # not the domain's: stays
    async with FactFeed(dk, fb, [DomainRule("cars", "Car")]) as feed:
        assert Fact("Car", ("car5",)) in fb
        dk.objects.remove_domain("cars")
        await feed.sync()
        assert set(fb) == {Fact("Car", ("truck1",))}


async def test_feed_refuses_bad_rules(dk: DyKnowInstance) -> None:
    with pytest.raises(OntologyError, match="unknown domain 'cars'"):
        async with FactFeed(dk, FactBase(), [DomainRule("cars", "Car")]):
            pass
    with pytest.raises(OntologyError, match="exactly one placeholder"):
        FactFeed(dk, FactBase(), [StreamRule("car/{id}/color", "Color")])
    with pytest.raises(OntologyError, match="SL word"):
        FactFeed(dk, FactBase(), [DomainRule("cars", "(Car")])


# --- label search end to end --------------------------------------------------------------

BLUE_ON_ROAD_7 = "(all ?x (and (Car ?x) (Color ?x blue) (OnRoad ?x road7)))"


async def test_find_labels(dk: DyKnowInstance, mapping: LabelMapping) -> None:
    t = Traffic(dk)
    for car, color, road in [
        ("car5", "blue", "road7"),
        ("car6", "blue", "road8"),
        ("car7", "red", "road7"),
        ("car8", "blue", "road7"),
        ("car9", "blue", "road7"),
    ]:
        t.car(car)
        t.push(f"car/{car}/color", color)
        t.push(f"car/{car}/road", road)
    for label in ["car/car5/state", "car/car5/speed", "car/car8/state", "car/car7/state"]:
        t.push(label, 0)
    # car9 matches but this platform publishes nothing about it
    fb = FactBase()
    async with FactFeed(dk, fb, RULES) as feed:
        found = find_labels(BLUE_ON_ROAD_7, fb, mapping, dk)
        assert found == ["car5-state", "car5-speed", "car8-state"]
        assert all("/" not in s for s in found)

        assert find_labels("(any ?x (and (Car ?x) (Color ?x red)))", fb, mapping, dk) == [
            "car7-state"
        ]
        assert find_labels("(all ?x (Color ?x green))", fb, mapping, dk) == []

        # the streams change: car8 turns off road 7, car9's state appears
        t.push("car/car8/road", "road8")
        t.push("car/car9/state", 1)
        assert find_labels(BLUE_ON_ROAD_7, fb, mapping, dk) == [
            "car5-state",
            "car5-speed",
            "car9-state",
        ]
        t.cars.remove("car5")
        await feed.sync()
        assert PlatformLabels(mapping, dk, fb).find(BLUE_ON_ROAD_7) == ["car9-state"]

        with pytest.raises(SLSyntaxError) as syntax:
            find_labels("(all ?x (and (Car ?x) (Colour ?x blue))", fb, mapping, dk)
        assert syntax.value.column == 1
        with pytest.raises(SLEvaluationError) as unknown:
            find_labels("(all ?x (Colour ?x blue))", fb, mapping, dk)
        assert unknown.value.reason == SLEvaluationError.UNKNOWN_CONCEPT
        with pytest.raises(SLEvaluationError) as several:
            find_labels("(iota ?x (Color ?x blue))", fb, mapping, dk)
        assert several.value.reason == SLEvaluationError.SEVERAL_MATCHES


def test_find_labels_takes_a_parsed_query(mapping: LabelMapping) -> None:
    dk = DyKnowInstance("uav-b", clock=ManualClock())
    dk.add_source("car/car5/state")
    fb = FactBase([Fact("Car", ("car5",)), Fact("Car", ("car-6",)), Fact("Car", (7,))])
    query = Query(QueryKind.ALL, (x,), Atom("Car", (x,)))
    # car-6 cannot be part of a semantic label, and a number is no object: both left out
    assert find_labels(query, fb, mapping, dk) == ["car5-state"]


async def test_an_error_in_the_feeds_body_comes_out_as_is(dk: DyKnowInstance) -> None:
    t = Traffic(dk)
    t.car("car5")
    with pytest.raises(KeyError, match="boom"):
        async with FactFeed(dk, FactBase(), RULES):
            raise KeyError("boom")


@pytest.mark.parametrize(
    ("pattern", "template", "overlaps"),
    [
        ("seg/{object}/flow", "seg/{segment}/flow", True),
        ("seg/{object}/flw", "seg/{segment}/flow", False),  # a typo: never matches
        ("seg/a{object}/flow", "seg/{segment}/flow", True),  # a segment 'a1' would do
        ("seg/{object}/flow", "seg/s1/flow", True),
        ("seg/{object}/flow", "seg//flow", False),  # a placeholder is never empty
        ("seg/{object}/flow", "seg/a/b/flow", False),  # nor holds a '/' (a local value)
        ("seg/{object}/flow", "{topic}", True),  # a hole is any text
        ("cars/{object}", "import/{sender}/{semantic}", False),
        ("import/uav-a/{object}-state", "import/{sender}/{semantic}", True),
    ],
)
def test_a_local_pattern_overlaps_the_labels_a_template_stands_for(
    pattern: str, template: str, overlaps: bool
) -> None:
    vocabulary = Vocabulary({"{object}-flow": ""})
    local = LabelMapping(vocabulary, {"{object}-flow": pattern}).local_entry("{object}-flow")
    assert local.overlaps(template) is overlaps
