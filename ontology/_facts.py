"""Facts about objects (``(Car car5)``, ``(Color car5 blue)``), kept current from streams.

A `FactBase` is a set of ground atoms indexed by predicate and first argument, which
SL formulas are evaluated over. A `FactFeed` keeps one current from a platform's own
DyKnow instance by rules:

* `DomainRule`: membership in a domain as a unary fact — ``car5`` joins the domain
  ``cars`` → ``(Car car5)``; it leaves → the fact is retracted.
* `StreamRule`: the latest value of each object's stream as a binary fact —
  ``car/car5/color`` = ``"blue"`` → ``(Color car5 blue)``, replacing the previous
  ``Color`` fact about ``car5``. A value of None (or converted to None) retracts it.
  With ``unary=True`` the value's truth asserts or retracts ``(Speeding car5)``.

A stream rule with a ``domain`` follows the domain's members (a dyknow_core set
subscription): streams of members that join, or are published later, are picked up by
themselves. Without a domain, the rule covers the streams published when the feed
starts; `FactFeed.refresh` picks up later ones and drops removed ones.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Self

from dyknow_core import (
    DomainSubscription,
    DyKnowError,
    DyKnowInstance,
    MembershipChange,
    Order,
    Policy,
    SetSubscription,
    Subscription,
)

from ._exceptions import OntologyError
from ._labels import LOCAL_VALUE, OBJECT, LabelPattern
from ._sl import Atom, Constant, Value, _Frozen, format_value, is_word, parse

log = logging.getLogger(__name__)


def _constant(value: Any) -> Value:
    """``value`` as a fact argument; TypeError/ValueError if SL has no constant for it."""
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise TypeError(f"a fact argument is a str, int or float, not {type(value).__name__}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"a fact argument must be a finite number, got {value}")
    # StrEnum members and other subclasses become plain values, so they hash alike
    if isinstance(value, str):
        return str.__str__(value)
    return int(value) if isinstance(value, int) else float(value)


# the frozen dataclasses of this module have their methods written out (`ontology._sl`)


@dataclass(init=False, repr=False, eq=False)
class Fact(_Frozen):
    """A ground atom: a predicate applied to constants, ``(Color car5 blue)``."""

    __slots__ = ("args", "predicate")
    predicate: str
    args: tuple[Value, ...]

    def __init__(self, predicate: str, args: tuple[Value, ...] = ()) -> None:
        object.__setattr__(self, "predicate", predicate)
        object.__setattr__(self, "args", args)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return (self.predicate, self.args) == (other.predicate, other.args)

    def __hash__(self) -> int:
        return hash((self.predicate, self.args))

    @classmethod
    def of(cls, predicate: str, *args: Any) -> Fact:
        """A fact from a predicate and Python values; TypeError/ValueError if not constants."""
        if not is_word(predicate):
            raise ValueError(f"predicate {predicate!r} is not an SL word")
        return cls(predicate, tuple(_constant(a) for a in args))

    @classmethod
    def parse(cls, text: str) -> Fact:
        """A fact from SL text, ``(Color car5 blue)``; SLSyntaxError/ValueError if not one."""
        expr = parse(text)
        if not isinstance(expr, Atom) or not all(isinstance(a, Constant) for a in expr.args):
            raise ValueError(f"{text!r} is not a ground atom")
        return cls(expr.predicate, tuple(a.value for a in expr.args if isinstance(a, Constant)))

    def __str__(self) -> str:
        return "(" + " ".join([self.predicate, *map(format_value, self.args)]) + ")"


class FactBase:
    """A set of facts, indexed by predicate and first argument; what formulas are evaluated over.

    ``objects`` are the constants the facts mention: what variables range over.
    ``version`` grows with every change, so a reader can tell whether to look again.
    """

    def __init__(self, facts: Iterable[Fact] = ()) -> None:
        # predicate -> first argument -> facts; insertion-ordered for repeatable answers
        self._index: dict[str, dict[Value | None, dict[Fact, None]]] = {}
        self._counts: Counter[Value] = Counter()
        self._size = 0
        self.version = 0
        for f in facts:
            self.add(f)

    @staticmethod
    def _fact(predicate: str | Fact, args: tuple[Any, ...]) -> Fact:
        if isinstance(predicate, Fact):
            if args:
                raise TypeError("give a Fact, or a predicate and its arguments, not both")
            return predicate
        return Fact.of(predicate, *args)

    def add(self, predicate: str | Fact, *args: Any) -> bool:
        """Assert a fact (``add("Color", "car5", "blue")``); False if it was known already."""
        fact = self._fact(predicate, args)
        bucket = self._index.setdefault(fact.predicate, {}).setdefault(
            fact.args[0] if fact.args else None, {}
        )
        if fact in bucket:
            return False
        bucket[fact] = None
        self._counts.update(fact.args)
        self._size += 1
        self.version += 1
        return True

    def retract(self, predicate: str | Fact, *args: Any) -> bool:
        """Retract a fact; False if it was not known."""
        fact = self._fact(predicate, args)
        by_first = self._index.get(fact.predicate)
        key = fact.args[0] if fact.args else None
        bucket = None if by_first is None else by_first.get(key)
        if bucket is None or fact not in bucket:
            return False
        del bucket[fact]
        if not bucket:
            del by_first[key]  # type: ignore[union-attr]
            if not by_first:
                del self._index[fact.predicate]
        self._counts.subtract(fact.args)
        for a in fact.args:
            if self._counts[a] <= 0:
                del self._counts[a]
        self._size -= 1
        self.version += 1
        return True

    def about(self, predicate: str, subject: Value) -> list[Fact]:
        """The facts of ``predicate`` whose first argument is ``subject``."""
        return list(self._index.get(predicate, {}).get(subject, ()))

    def retract_about(self, predicate: str, subject: Value) -> int:
        """Retract every fact of ``predicate`` about ``subject``; how many there were."""
        facts = self.about(predicate, subject)
        for f in facts:
            self.retract(f)
        return len(facts)

    def replace(self, predicate: str, subject: Any, *rest: Any) -> bool:
        """Make ``(predicate subject rest…)`` the only fact of ``predicate`` about ``subject``.

        Returns whether anything changed.
        """
        fact = Fact.of(predicate, subject, *rest)
        old = [f for f in self.about(fact.predicate, fact.args[0]) if f != fact]
        for f in old:
            self.retract(f)
        return self.add(fact) or bool(old)

    def candidates(self, predicate: str, arity: int, first: Value | None = None) -> Iterator[Fact]:
        """The facts of ``predicate`` with ``arity`` arguments (and first argument ``first``)."""
        by_first = self._index.get(predicate)
        if not by_first:
            return
        if first is not None:
            buckets: Iterable[dict[Fact, None]] = [by_first.get(first, {})]
        else:
            buckets = list(by_first.values())
        for bucket in buckets:
            for f in list(bucket):
                if len(f.args) == arity:
                    yield f

    def facts(self, predicate: str | None = None) -> list[Fact]:
        """Every fact, or those of one predicate."""
        if predicate is not None:
            return [f for b in self._index.get(predicate, {}).values() for f in b]
        return [f for by_first in self._index.values() for b in by_first.values() for f in b]

    @property
    def predicates(self) -> list[str]:
        """The predicates with at least one fact."""
        return sorted(self._index)

    @property
    def objects(self) -> frozenset[Value]:
        """Every constant some fact mentions: what variables range over."""
        return frozenset(self._counts)

    def __contains__(self, fact: object) -> bool:
        if not isinstance(fact, Fact):
            return False
        key = fact.args[0] if fact.args else None
        return fact in self._index.get(fact.predicate, {}).get(key, {})

    def __iter__(self) -> Iterator[Fact]:
        return iter(self.facts())

    def __len__(self) -> int:
        return self._size

    def __repr__(self) -> str:
        return f"<FactBase ({self._size} facts)>"


# --- rules and the feed ------------------------------------------------------------------


@dataclass(init=False, repr=False, eq=False)
class DomainRule(_Frozen):
    """Membership in a dyknow_core domain as a unary fact: ``cars`` ∋ car5 → ``(Car car5)``."""

    __slots__ = ("domain", "predicate")
    domain: str
    predicate: str

    def __init__(self, domain: str, predicate: str) -> None:
        object.__setattr__(self, "domain", domain)
        object.__setattr__(self, "predicate", predicate)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return (self.domain, self.predicate) == (other.domain, other.predicate)

    def __hash__(self) -> int:
        return hash((self.domain, self.predicate))


@dataclass(init=False, repr=False, eq=False)
class StreamRule(_Frozen):
    """The latest value of each object's stream as a fact about it.

    ``pattern`` is a local label pattern with ``{object}`` (``car/{object}/color``);
    ``convert`` turns a value into the fact's argument (None retracts); ``unary`` makes
    the value's truth assert or retract ``(predicate object)`` instead; ``domain``
    follows that domain's members instead of the labels published at start.
    """

    __slots__ = ("convert", "domain", "pattern", "predicate", "unary")
    pattern: str
    predicate: str
    domain: str | None
    convert: Callable[[Any], Any] | None
    unary: bool

    def __init__(
        self,
        pattern: str,
        predicate: str,
        domain: str | None = None,
        convert: Callable[[Any], Any] | None = None,
        unary: bool = False,
    ) -> None:
        object.__setattr__(self, "pattern", pattern)
        object.__setattr__(self, "predicate", predicate)
        object.__setattr__(self, "domain", domain)
        object.__setattr__(self, "convert", convert)
        object.__setattr__(self, "unary", unary)

    def _key(self) -> tuple[object, ...]:
        return (self.pattern, self.predicate, self.domain, self.convert, self.unary)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())


Rule = DomainRule | StreamRule

# Replay a stream's cached history on subscribing, so the facts start from its latest
# value; monotone order keeps a late, older sample from overwriting a newer one.
_REPLAY = Policy(start=-(2**62), order=Order.MONOTONE)


class FactFeed:
    """Keeps a `FactBase` current from an instance's streams and domains by rules.

    An async context manager: entering subscribes and asserts the current facts,
    leaving unsubscribes (the facts stay). A stream published later is followed from
    the moment it is published, and a removed one's facts are retracted. Stream values
    arrive by subscription callbacks and apply at once; domain changes are applied by a
    task the feed owns (``await feed.sync()`` waits until those pending are applied). A
    value that cannot be a fact is skipped and counted in ``errors``; it never reaches
    the publisher.
    """

    def __init__(self, instance: DyKnowInstance, facts: FactBase, rules: Iterable[Rule]) -> None:
        self.instance = instance
        self.facts = facts
        self.rules = list(rules)
        self.errors = 0
        self.last_error: str | None = None
        self._patterns: dict[StreamRule, LabelPattern] = {}
        for rule in self.rules:
            if isinstance(rule, StreamRule):
                try:
                    pattern = LabelPattern(rule.pattern, value=LOCAL_VALUE)
                except ValueError as exc:
                    raise OntologyError(f"stream rule {rule.pattern!r}: {exc}") from None
                if pattern.params != (OBJECT,):
                    raise OntologyError(
                        f"stream rule {rule.pattern!r} needs exactly one placeholder, {{object}}"
                    )
                self._patterns[rule] = pattern
            if not is_word(rule.predicate):
                raise OntologyError(f"rule predicate {rule.predicate!r} is not an SL word")
        self._streams: dict[tuple[StreamRule, str], Subscription] = {}  # by (rule, label)
        self._sets: list[SetSubscription] = []
        self._domains: list[tuple[DomainSubscription, asyncio.Task[None]]] = []
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group
        self._stop_listening: Callable[[], None] | None = None
        self._state = "unopened"

    # -- lifecycle -------------------------------------------------------------------------
    async def __aenter__(self) -> Self:
        if self._state != "unopened":
            raise OntologyError(f"a fact feed is entered once; this one is {self._state}")
        self._state = "opened"
        stack = self._stack = contextlib.AsyncExitStack()
        tg = await stack.enter_async_context(asyncio.TaskGroup())
        try:
            for rule in self.rules:
                if isinstance(rule, DomainRule):
                    self._start_domain(rule, tg)
                elif rule.domain is not None:
                    self._start_set(rule)
            self.refresh()
            self._stop_listening = self.instance.on_label_change(self._label_changed)
        except BaseException:
            self.close()  # ends the tasks started so far, so the group exits at once
            self._stack = None
            await stack.aclose()
            raise
        return self

    async def __aexit__(self, *exc: Any) -> None:
        self.close()
        stack, self._stack = self._stack, None
        if stack is not None:
            # closing ended the tasks; the body's own error must not come back wrapped in a
            # group, so the group is told nothing of it (aclose passes no exception)
            await stack.aclose()

    def close(self) -> None:
        """Unsubscribe from everything; the domain tasks end. The facts stay."""
        self._state = "closed"
        if self._stop_listening is not None:
            self._stop_listening()
            self._stop_listening = None
        for sub in self._streams.values():
            sub.close()
        self._streams.clear()
        for ss in self._sets:
            ss.close()
        for ds, _ in self._domains:
            ds.close()

    async def sync(self) -> None:
        """Wait until the domain changes already made (a removal too) are applied to the facts."""
        # the follower tasks drain a buffer in one step once woken: yielding step by step
        # until every buffer is empty is exact, where an Event would need a second protocol
        while any(  # noqa: ASYNC110
            ds.buffered or (ds.closed and not task.done()) for ds, task in self._domains
        ):
            await asyncio.sleep(0)

    # -- domains ---------------------------------------------------------------------------
    def _domain(self, name: str, rule: Rule) -> Any:
        try:
            return self.instance.objects.domain(name)
        except DyKnowError as exc:
            raise OntologyError(f"{rule}: {exc}") from exc

    def _start_domain(self, rule: DomainRule, tg: asyncio.TaskGroup) -> None:
        domain = self._domain(rule.domain, rule)
        # no await between reading the members and subscribing: no change falls between
        for member in domain.members:
            self.facts.add(rule.predicate, member)
        sub = domain.subscribe()
        task = tg.create_task(
            self._follow(rule, sub), name=f"factfeed[{self.instance.name}].domain[{rule.domain}]"
        )
        self._domains.append((sub, task))

    async def _follow(self, rule: DomainRule, sub: DomainSubscription) -> None:
        async for change in sub:
            if change.kind is MembershipChange.ADDED:
                self.facts.add(rule.predicate, change.identifier)
            else:
                self.facts.retract(rule.predicate, change.identifier)
        if sub.domain.removed:  # the domain keeps its last members when removed
            for member in sub.domain.members:
                self.facts.retract(rule.predicate, member)

    # -- streams ---------------------------------------------------------------------------
    def _start_set(self, rule: StreamRule) -> None:
        assert rule.domain is not None
        self._domain(rule.domain, rule)
        pattern = rule.pattern.replace("{" + OBJECT + "}", "{id}")

        def on_batch(identifier: str, batch: Sequence[tuple[Any, int, int]]) -> None:
            self._apply(rule, identifier, batch)

        self._sets.append(
            self.instance.objects.subscribe_set(rule.domain, pattern, _REPLAY, callback=on_batch)
        )

    def refresh(self) -> int:
        """Follow every published stream a rule matches and forget removed ones; how many
        are new. The feed does this itself as streams come and go: this is a check."""
        if self._state != "opened":
            raise OntologyError(f"the fact feed is {self._state}")
        for (rule, label), sub in list(self._streams.items()):
            if sub.closed and not self.instance.has_label(label):
                self._forget(rule, label)
        return sum(self._follow_label(label) for label in self.instance.labels())

    def _label_changed(self, label: str, published: bool) -> None:
        if self._state != "opened":
            return
        if published:
            self._follow_label(label)
            return
        for rule, followed in list(self._streams):
            if followed == label:
                self._forget(rule, label)

    def _follow_label(self, label: str) -> int:
        """Subscribe the domain-less stream rules ``label`` matches; how many were new."""
        added = 0
        for rule, pattern in self._patterns.items():
            if rule.domain is not None or (rule, label) in self._streams:
                continue
            values = pattern.match(label)
            if values is None:
                continue
            self._streams[(rule, label)] = self.instance.subscribe(
                label, _REPLAY, callback=self._deliverer(rule, values[OBJECT])
            )
            added += 1
        return added

    def _forget(self, rule: StreamRule, label: str) -> None:
        self._streams.pop((rule, label)).close()
        identifier = self._patterns[rule].match(label)
        assert identifier is not None
        self._retract(rule, identifier[OBJECT])

    def _deliverer(
        self, rule: StreamRule, identifier: str
    ) -> Callable[[Sequence[tuple[Any, int, int]]], None]:
        def on_batch(batch: Sequence[tuple[Any, int, int]]) -> None:
            self._apply(rule, identifier, batch)

        return on_batch

    def _apply(
        self, rule: StreamRule, identifier: str, batch: Sequence[tuple[Any, int, int]]
    ) -> None:
        if not batch:
            return
        value = batch[-1][0]
        try:
            if rule.convert is not None:
                value = rule.convert(value)
            if rule.unary:
                if value:
                    self.facts.add(rule.predicate, identifier)
                else:
                    self.facts.retract(rule.predicate, identifier)
            elif value is None:
                self.facts.retract_about(rule.predicate, identifier)
            else:
                self.facts.replace(rule.predicate, identifier, value)
        except Exception as exc:  # runs inside the publisher's push: never raise into it
            self.errors += 1
            self.last_error = f"{rule.pattern} [{identifier}]: {type(exc).__name__}: {exc}"
            log.debug("fact feed skipped a value: %s", self.last_error)

    def _retract(self, rule: StreamRule, identifier: str) -> None:
        if rule.unary:
            self.facts.retract(rule.predicate, identifier)
        else:
            self.facts.retract_about(rule.predicate, identifier)

    def stats(self) -> dict[str, Any]:
        """A snapshot: streams followed, facts, errors."""
        return {
            "streams": len(self._streams) + sum(len(s.attached) for s in self._sets),
            "domains": len(self._domains),
            "facts": len(self.facts),
            "errors": self.errors,
            "last_error": self.last_error,
        }

    def __repr__(self) -> str:
        return f"<FactFeed {self.instance.name!r} ({len(self.rules)} rules, {self._state})>"
