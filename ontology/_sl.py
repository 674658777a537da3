"""The subset of FIPA SL used to find labels: a parser, a printer and an evaluator.

The grammar (whitespace separates tokens; newlines are whitespace)::

    query     := formula | "(" ("all" | "any" | "iota") vars formula ")"
    vars      := variable | "(" "sequence" variable+ ")"
    formula   := "(" "and" formula+ ")" | "(" "or" formula+ ")" | "(" "not" formula ")"
               | "(" predicate term* ")"
    term      := variable | constant
    variable  := "?" word
    constant  := word | string | number
    word      := a run of characters other than whitespace, parentheses and double quotes,
                 not starting with a digit, "+", "-", ".", "?" or "#"   (blue, road7, car5)
    string    := '"' characters, with \\" and \\\\ as escapes '"'       ("dark blue")
    number    := an integer or a decimal number, optionally signed       (7, -3, 2.5e3)

For example ``(all ?x (and (Car ?x) (Color ?x blue) (OnRoad ?x road7)))`` — every ?x that
is a car, is blue and is on road 7. A word and a string with the same characters are the
same constant (``blue`` and ``"blue"``).

The evaluator answers a query over a `FactBase` under the closed-world assumption, with
variables ranging over the objects the fact base knows (every constant in its facts):
``all`` gives every binding of the query's variables, ``any`` one binding (or none),
``iota`` exactly one (an `SLEvaluationError` with reason ``no-match`` or
``several-matches`` otherwise). A variable that is not the query's is existential,
over the smallest part of the formula holding all its occurrences:
``(all ?x (and (Car ?x) (OnRoad ?x ?r)))`` is every car on some road,
``(all ?x (and (Car ?x) (not (OnRoad ?x ?r))))`` every car on no road. A bare formula is
answered as ``all`` over its variables, in the order they first appear.
"""

from __future__ import annotations

import itertools
import math
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import FrozenInstanceError, dataclass
from enum import StrEnum
from typing import Protocol

from ._exceptions import SLEvaluationError, SLSyntaxError

Value = str | int | float
"""What a constant denotes: an object identifier, a word, a string or a number."""


class GroundAtom(Protocol):
    """A fact as the evaluator reads it: its arguments (`ontology.Fact` is one)."""

    @property
    def args(self) -> tuple[Value, ...]:
        """The constants the predicate is applied to."""
        ...


class Facts(Protocol):
    """What the evaluator asks of a fact base (`ontology.FactBase` is one).

    Declared here, not imported, as the fact base is built on this module's terms.
    """

    @property
    def objects(self) -> frozenset[Value]:
        """Every constant some fact mentions: what variables range over."""
        ...

    def candidates(
        self, predicate: str, arity: int, first: Value | None = None
    ) -> Iterator[GroundAtom]:
        """The facts of ``predicate`` with ``arity`` arguments (and first argument ``first``)."""
        ...


Binding = dict[str, Value]
"""One answer: variable name (without the ``?``) → value."""

_WORD = re.compile(r'[^\s()"?#0-9+\-.][^\s()"]*')
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_INTEGER = re.compile(r"[+-]?\d+")
_TOKEN = re.compile(r'\s+|[()]|"|[^\s()"]+')


def is_word(text: str) -> bool:
    """Whether ``text`` can be written as an SL word (unquoted constant, predicate name)."""
    return bool(_WORD.fullmatch(text))


# --- the AST ---------------------------------------------------------------------------
#
# The nodes are frozen dataclasses whose methods are written out: the generated ones cost
# ~0.4 ms of every process's start a class (Python compiles each method from source), and
# every node and command imports this module. `dataclasses.fields`, `replace` and `asdict`
# work as ever; `_Frozen` makes them immutable, pickled and printed like a frozen one.


class _Frozen:
    """What the frozen AST nodes share: no assignment, a dataclass's repr, pickling."""

    __slots__ = ()
    __match_args__: tuple[str, ...] = ()

    def __setattr__(self, name: str, value: object) -> None:
        raise FrozenInstanceError(f"cannot assign to field {name!r}")

    def __delattr__(self, name: str) -> None:
        raise FrozenInstanceError(f"cannot delete field {name!r}")

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}={getattr(self, n)!r}" for n in self.__match_args__)
        return f"{type(self).__qualname__}({fields})"

    def __reduce__(self) -> tuple[type, tuple[object, ...]]:
        return type(self), tuple(getattr(self, n) for n in self.__match_args__)


@dataclass(init=False, repr=False, eq=False)
class Variable(_Frozen):
    """A variable, ``?x``; ``name`` is without the question mark."""

    __slots__ = ("name",)
    name: str

    def __init__(self, name: str) -> None:
        object.__setattr__(self, "name", name)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self.name == other.name

    def __hash__(self) -> int:
        return hash((self.name,))

    def __str__(self) -> str:
        return f"?{self.name}"


@dataclass(init=False, repr=False, eq=False)
class Constant(_Frozen):
    """A constant: a word (``blue``), a string (``"dark blue"``) or a number (``7``).

    ``quoted`` only says how it was written; ``blue`` and ``"blue"`` are equal.
    """

    __slots__ = ("quoted", "value")
    value: Value
    quoted: bool

    def __init__(self, value: Value, quoted: bool = False) -> None:
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise TypeError(f"an SL constant is a str, int or float, not {type(value).__name__}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"an SL constant must be a finite number, got {value}")
        object.__setattr__(self, "value", value)
        object.__setattr__(self, "quoted", quoted)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self.value == other.value

    def __hash__(self) -> int:
        return hash((self.value,))

    def __str__(self) -> str:
        return format_value(self.value, quoted=self.quoted)


Term = Variable | Constant


@dataclass(init=False, repr=False, eq=False)
class Atom(_Frozen):
    """A predicate applied to terms: ``(Color ?x blue)``."""

    __slots__ = ("args", "predicate")
    predicate: str
    args: tuple[Term, ...]

    def __init__(self, predicate: str, args: tuple[Term, ...] = ()) -> None:
        object.__setattr__(self, "predicate", predicate)
        object.__setattr__(self, "args", args)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return (self.predicate, self.args) == (other.predicate, other.args)

    def __hash__(self) -> int:
        return hash((self.predicate, self.args))

    def __str__(self) -> str:
        return "(" + " ".join([self.predicate, *map(str, self.args)]) + ")"


@dataclass(init=False, repr=False, eq=False)
class And(_Frozen):
    """True when every operand is."""

    __slots__ = ("operands",)
    operands: tuple[Formula, ...]

    def __init__(self, operands: tuple[Formula, ...]) -> None:
        object.__setattr__(self, "operands", operands)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self.operands == other.operands

    def __hash__(self) -> int:
        return hash((self.operands,))

    def __str__(self) -> str:
        return "(and " + " ".join(map(str, self.operands)) + ")"


@dataclass(init=False, repr=False, eq=False)
class Or(_Frozen):
    """True when some operand is."""

    __slots__ = ("operands",)
    operands: tuple[Formula, ...]

    def __init__(self, operands: tuple[Formula, ...]) -> None:
        object.__setattr__(self, "operands", operands)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self.operands == other.operands

    def __hash__(self) -> int:
        return hash((self.operands,))

    def __str__(self) -> str:
        return "(or " + " ".join(map(str, self.operands)) + ")"


@dataclass(init=False, repr=False, eq=False)
class Not(_Frozen):
    """True when the operand is false (closed world: not known to hold)."""

    __slots__ = ("operand",)
    operand: Formula

    def __init__(self, operand: Formula) -> None:
        object.__setattr__(self, "operand", operand)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self.operand == other.operand

    def __hash__(self) -> int:
        return hash((self.operand,))

    def __str__(self) -> str:
        return f"(not {self.operand})"


Formula = Atom | And | Or | Not


class QueryKind(StrEnum):
    """How many answers a query asks for."""

    ALL = "all"
    ANY = "any"
    IOTA = "iota"


@dataclass(init=False, repr=False, eq=False)
class Query(_Frozen):
    """An identifying expression: the objects (``variables``) that make ``formula`` true."""

    __slots__ = ("formula", "kind", "variables")
    kind: QueryKind
    variables: tuple[Variable, ...]
    formula: Formula

    def __init__(self, kind: QueryKind, variables: tuple[Variable, ...], formula: Formula) -> None:
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "variables", variables)
        object.__setattr__(self, "formula", formula)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        mine, theirs = (
            (self.kind, self.variables, self.formula),
            (other.kind, other.variables, other.formula),
        )
        return mine == theirs

    def __hash__(self) -> int:
        return hash((self.kind, self.variables, self.formula))

    def __str__(self) -> str:
        if len(self.variables) == 1:
            head = str(self.variables[0])
        else:
            head = "(sequence " + " ".join(map(str, self.variables)) + ")"
        return f"({self.kind.value} {head} {self.formula})"


Expression = Query | Formula


def format_value(value: Value, *, quoted: bool = False) -> str:
    """``value`` as SL text: a bare word when it can be one, else a number or a string."""
    if isinstance(value, str):
        if not quoted and is_word(value):
            return value
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


# --- parsing -------------------------------------------------------------------------

_QUERIES = {k.value: k for k in QueryKind}
_UNSUPPORTED = frozenset(
    {"exists", "forall", "implies", "equiv", "=", "B", "U", "I", "PG"}
    | {"feasible", "done", "result", "set", "sequence", "action"}
)
_OPERATORS = "all, any, iota, and, or, not"
MAX_DEPTH = 64
"""Levels a formula may nest (``(not (and (not …))))``): the parser and every walk over a
formula recurse, and Python's stack is 1000 frames deep. A formula comes from anyone who
may ask (a search of another member, the console's page)."""


class _Token:
    __slots__ = ("kind", "pos", "text", "value")

    def __init__(self, kind: str, text: str, pos: int, value: Value | None = None) -> None:
        self.kind = kind  # "(", ")", "word", "var", "string", "number", "end"
        self.text = text
        self.pos = pos
        self.value = value

    def describe(self) -> str:
        return "the end of the formula" if self.kind == "end" else repr(self.text)


def _tokenize(text: str) -> list[_Token]:
    tokens: list[_Token] = []
    pos = 0
    n = len(text)
    while pos < n:
        c = text[pos]
        if c == '"':
            pos = _string(text, pos, tokens)
            continue
        m = _TOKEN.match(text, pos)
        assert m is not None  # the pattern's alternatives cover every character
        chunk = m.group()
        if not chunk[0].isspace():
            tokens.append(_classify(text, chunk, pos))
        pos = m.end()
    tokens.append(_Token("end", "", n))
    return tokens


def _string(text: str, start: int, tokens: list[_Token]) -> int:
    out: list[str] = []
    i = start + 1
    while i < len(text):
        c = text[i]
        if c == '"':
            tokens.append(_Token("string", text[start : i + 1], start, "".join(out)))
            return i + 1
        if c == "\\" and i + 1 < len(text) and text[i + 1] in '"\\':
            out.append(text[i + 1])
            i += 2
            continue
        out.append(c)
        i += 1
    raise SLSyntaxError("unterminated string: no closing '\"'", text, start)


def _classify(text: str, chunk: str, pos: int) -> _Token:
    if chunk in "()":
        return _Token(chunk, chunk, pos)
    if chunk[0] == "?":
        name = chunk[1:]
        if not name:
            raise SLSyntaxError("expected a variable name after '?'", text, pos)
        if not is_word(name):
            raise SLSyntaxError(f"malformed variable name {chunk!r}", text, pos)
        return _Token("var", chunk, pos, name)
    if _NUMBER.fullmatch(chunk):
        number: Value = int(chunk) if _INTEGER.fullmatch(chunk) else float(chunk)
        if isinstance(number, float) and not math.isfinite(number):
            raise SLSyntaxError(f"number {chunk!r} is out of range", text, pos)
        return _Token("number", chunk, pos, number)
    if chunk[0].isdigit() or chunk[0] in "+-.":
        raise SLSyntaxError(f"malformed number {chunk!r}", text, pos)
    if not is_word(chunk):
        raise SLSyntaxError(f"unexpected {chunk[0]!r}", text, pos)
    return _Token("word", chunk, pos, chunk)


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.tokens = _tokenize(text)
        self.i = 0
        self.depth = 0  # formulas open (`MAX_DEPTH`)

    def error(self, message: str, token: _Token | int) -> SLSyntaxError:
        pos = token if isinstance(token, int) else token.pos
        return SLSyntaxError(message, self.text, pos)

    def peek(self) -> _Token:
        return self.tokens[self.i]

    def take(self) -> _Token:
        tok = self.tokens[self.i]
        if tok.kind != "end":
            self.i += 1
        return tok

    def unclosed(self, opening: _Token) -> SLSyntaxError:
        return self.error("this '(' is never closed", opening)

    def open(self, what: str) -> _Token:
        tok = self.take()
        if tok.kind != "(":
            raise self.error(f"expected '(' to start {what}, found {tok.describe()}", tok)
        return tok

    def close(self, opening: _Token, message: str) -> None:
        tok = self.take()
        if tok.kind == "end":
            raise self.unclosed(opening)
        if tok.kind != ")":
            raise self.error(message, tok)

    def head(self, opening: _Token) -> _Token:
        tok = self.take()
        if tok.kind == "end":
            raise self.unclosed(opening)
        if tok.kind == ")":
            raise self.error(
                f"empty formula '()': expected one of {_OPERATORS} or a predicate", tok
            )
        if tok.kind != "word":
            raise self.error(
                f"expected one of {_OPERATORS} or a predicate name, found {tok.describe()}", tok
            )
        return tok

    def parse(self) -> Expression:
        if self.peek().kind == "end":
            raise self.error("empty formula", self.peek())
        opening = self.open("a formula")
        head = self.head(opening)
        expr: Expression
        if head.text in _QUERIES:
            expr = self.query(opening, head)
        else:
            expr = self.rest_of_formula(opening, head)
        tok = self.peek()
        if tok.kind == ")":
            raise self.error("unbalanced ')': nothing to close", tok)
        if tok.kind != "end":
            raise self.error(f"trailing input after the formula: {tok.describe()}", tok)
        return expr

    def query(self, opening: _Token, head: _Token) -> Query:
        kind = _QUERIES[head.text]
        variables = self.variables(opening, head)
        formula = self.formula()
        self.close(opening, f"'{kind.value}' takes variables and one formula; expected ')'")
        return Query(kind, variables, formula)

    def variables(self, opening: _Token, head: _Token) -> tuple[Variable, ...]:
        tok = self.take()
        if tok.kind == "var":
            assert isinstance(tok.value, str)
            return (Variable(tok.value),)
        if tok.kind == "(" and self.peek().text == "sequence":
            self.take()
            out: list[Variable] = []
            while (t := self.take()).kind == "var":
                assert isinstance(t.value, str)
                if Variable(t.value) in out:
                    raise self.error(f"variable {t.text} is listed twice", t)
                out.append(Variable(t.value))
            if t.kind == "end":
                raise self.unclosed(tok)
            if t.kind != ")":
                raise self.error(f"expected a variable, found {t.describe()}", t)
            if not out:
                raise self.error("'sequence' needs at least one variable", t)
            return tuple(out)
        if tok.kind == "end":
            raise self.unclosed(opening)
        raise self.error(
            f"expected a variable after '{head.text}' (?x, or (sequence ?x ?y)), "
            f"found {tok.describe()}",
            tok,
        )

    def formula(self) -> Formula:
        tok = self.peek()
        if tok.kind == ")":
            raise self.error("expected a formula, found ')'", tok)
        if self.depth >= MAX_DEPTH:
            raise self.error(f"formula nested deeper than {MAX_DEPTH} levels", tok)
        opening = self.open("a formula")
        self.depth += 1
        try:
            return self.rest_of_formula(opening, self.head(opening))
        finally:
            self.depth -= 1

    def rest_of_formula(self, opening: _Token, head: _Token) -> Formula:
        name = head.text
        if name in _QUERIES:
            raise self.error(f"'{name}' can only be the whole query, not part of a formula", head)
        if name in ("and", "or"):
            operands: list[Formula] = []
            while self.peek().kind not in (")", "end"):
                operands.append(self.formula())
            if not operands:
                raise self.error(f"'{name}' needs at least one formula", self.peek())
            self.close(opening, f"expected ')' to close '{name}'")
            return And(tuple(operands)) if name == "and" else Or(tuple(operands))
        if name == "not":
            operand = self.formula()
            self.close(opening, "'not' takes exactly one formula; expected ')'")
            return Not(operand)
        if name in _UNSUPPORTED:
            raise self.error(
                f"unsupported SL operator '{name}' (this subset has {_OPERATORS} and predicates)",
                head,
            )
        return self.atom(opening, head)

    def atom(self, opening: _Token, head: _Token) -> Atom:
        args: list[Term] = []
        while True:
            tok = self.take()
            if tok.kind == ")":
                return Atom(head.text, tuple(args))
            if tok.kind == "end":
                raise self.unclosed(opening)
            if tok.kind == "var":
                assert isinstance(tok.value, str)
                args.append(Variable(tok.value))
            elif tok.kind == "(":
                # a formula where a term belongs: most likely a misspelt operator
                raise self.error(
                    f"unknown operator '{head.text}' (known: {_OPERATORS}); "
                    "a predicate takes only constants and variables",
                    head,
                )
            else:
                assert tok.value is not None
                args.append(Constant(tok.value, quoted=tok.kind == "string"))


def parse(text: str) -> Expression:
    """Parse an SL query or formula; SLSyntaxError pointing at the position if malformed."""
    return _Parser(text).parse()


# --- evaluation ------------------------------------------------------------------------


def variables_of(expr: Expression) -> list[Variable]:
    """The variables of ``expr`` in the order they first appear."""
    seen: dict[Variable, None] = {}

    def walk(e: Expression) -> None:
        match e:
            case Query():
                seen.update(dict.fromkeys(e.variables))
                walk(e.formula)
            case Atom():
                seen.update((a, None) for a in e.args if isinstance(a, Variable))
            case And() | Or():
                for op in e.operands:
                    walk(op)
            case Not():
                walk(e.operand)

    walk(expr)
    return list(seen)


def atoms_of(expr: Expression) -> Iterator[Atom]:
    """Every atom in ``expr``."""
    match expr:
        case Query():
            yield from atoms_of(expr.formula)
        case Atom():
            yield expr
        case And() | Or():
            for op in expr.operands:
                yield from atoms_of(op)
        case Not():
            yield from atoms_of(expr.operand)


def _sort_key(values: tuple[Value, ...]) -> tuple[tuple[int, Value], ...]:
    # numbers and strings do not compare: numbers first, then strings
    return tuple((1, v) if isinstance(v, str) else (0, v) for v in values)


def evaluate(expr: Expression, facts: Facts) -> list[Binding]:
    """Answer ``expr`` over ``facts``: the bindings of its variables, sorted by value."""
    if isinstance(expr, Query):
        kind, wanted, formula = expr.kind, [v.name for v in expr.variables], expr.formula
    else:
        kind, wanted, formula = QueryKind.ALL, [v.name for v in variables_of(expr)], expr
    ctx = _Context(facts, formula, frozenset(wanted))
    answers: set[tuple[Value, ...]] = set()
    for env in ctx.solve(formula, {}):
        # a query variable the formula left free ranges over every object
        free = [n for n in wanted if n not in env]
        for values in itertools.product(ctx.domain, repeat=len(free)):
            full = env | dict(zip(free, values, strict=True))
            answers.add(tuple(full[n] for n in wanted))
    ordered = sorted(answers, key=_sort_key)
    if kind is QueryKind.ANY:
        ordered = ordered[:1]
    elif kind is QueryKind.IOTA and len(ordered) != 1:
        if not ordered:
            raise SLEvaluationError(
                SLEvaluationError.NO_MATCH, f"iota: nothing satisfies {formula}"
            )
        shown = ", ".join(" ".join(map(format_value, a)) for a in ordered[:5])
        raise SLEvaluationError(
            SLEvaluationError.SEVERAL_MATCHES,
            f"iota: {len(ordered)} answers satisfy {formula} ({shown}"
            f"{', …' if len(ordered) > 5 else ''}); iota needs exactly one",
        )
    return [dict(zip(wanted, a, strict=True)) for a in ordered]


def _occurrences(f: Formula) -> Counter[str]:
    counts: Counter[str] = Counter()
    for atom in atoms_of(f):
        counts.update(a.name for a in atom.args if isinstance(a, Variable))
    return counts


class _Context:
    """One evaluation: the facts, the objects variables range over, and variable scopes.

    A variable that is not the query's is existential over the smallest part of the
    formula holding all its occurrences, so ``(not (OnRoad ?x ?r))`` with ?r nowhere
    else means "on no road". A negation can only test bindings: the variables it must
    bind itself (the query's, and those also used outside it) range over the domain.
    """

    def __init__(self, facts: Facts, formula: Formula, wanted: frozenset[str]) -> None:
        self.facts = facts
        self.domain = sorted(facts.objects, key=lambda v: _sort_key((v,)))
        total = _occurrences(formula)
        self.outer: dict[int, list[str]] = {}  # id(Not node) -> variables it must bind
        for node in _negations(formula):
            inside = _occurrences(node.operand)
            self.outer[id(node)] = [v for v in inside if v in wanted or inside[v] < total[v]]

    def solve(self, f: Formula, env: Binding) -> Iterator[Binding]:
        """Every extension of ``env`` that makes ``f`` true (possibly with repeats)."""
        match f:
            case Atom():
                yield from _match(f, env, self.facts)
            case And():
                # a negation is a test: run it once the other conjuncts have bound what they can
                ops = sorted(f.operands, key=lambda op: isinstance(op, Not))
                yield from self.conjoin(ops, 0, env)
            case Or():
                for op in f.operands:
                    yield from self.solve(op, env)
            case Not():
                unbound = [v for v in self.outer[id(f)] if v not in env]
                for values in itertools.product(self.domain, repeat=len(unbound)):
                    trial = env | dict(zip(unbound, values, strict=True))
                    if next(self.solve(f.operand, trial), None) is None:
                        yield trial

    def conjoin(self, ops: list[Formula], i: int, env: Binding) -> Iterator[Binding]:
        """Every extension of ``env`` that makes ``ops[i:]`` all true."""
        if i == len(ops):
            yield env
            return
        for extended in self.solve(ops[i], env):
            yield from self.conjoin(ops, i + 1, extended)


def _negations(f: Formula) -> Iterator[Not]:
    match f:
        case Not():
            yield f
            yield from _negations(f.operand)
        case And() | Or():
            for op in f.operands:
                yield from _negations(op)


def _match(atom: Atom, env: Binding, facts: Facts) -> Iterator[Binding]:
    pattern: list[Value | Variable] = []
    for a in atom.args:
        if isinstance(a, Constant):
            pattern.append(a.value)
        else:
            pattern.append(env.get(a.name, a))
    first = pattern[0] if pattern and not isinstance(pattern[0], Variable) else None
    for fact in facts.candidates(atom.predicate, len(pattern), first):
        out = env
        for want, got in zip(pattern, fact.args, strict=True):
            if isinstance(want, Variable):
                bound = out.get(want.name)
                if bound is None:
                    out = out | {want.name: got}
                elif bound != got:
                    break
            elif want != got:
                break
        else:
            yield out
