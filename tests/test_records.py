"""The dataclasses whose methods are written out behave as the generated ones would.

Every node imports them, and a dataclass's generated methods are compiled at its start
(`agents._records`): each is checked here against a dataclass made the usual way from the
same fields, on what a user relies on: construction and defaults, repr, equality,
hashing, immutability, pickling, ``match`` and the `dataclasses` functions.
"""

from __future__ import annotations

import copy
import dataclasses
import pickle
from typing import Any

import pytest

from agents import (
    AgentStats,
    ContractNetResult,
    DfEventLimit,
    KxLimit,
    PlatformStats,
    Proposal,
    RateLimit,
    SecurityPolicy,
    SenderStats,
    Subscriber,
)
from agents._security import _Pending
from ontology import DomainRule, Fact, StreamRule
from ontology._sl import And, Atom, Constant, Not, Or, Query, QueryKind, Variable

_X = Variable("x")
_CAR = Atom("Car", (_X, Constant("car5")))

# class, the arguments of one instance, the fields equality leaves out
CASES: list[tuple[type, tuple[Any, ...], frozenset[str]]] = [
    (Variable, ("x",), frozenset()),
    (Constant, ("dark blue", True), frozenset({"quoted"})),
    (Atom, ("Color", (_X, Constant(7))), frozenset()),
    (And, ((_CAR, _CAR),), frozenset()),
    (Or, ((_CAR,),), frozenset()),
    (Not, (_CAR,), frozenset()),
    (Query, (QueryKind.ALL, (_X,), _CAR), frozenset()),
    (Fact, ("Color", ("car5", 7)), frozenset()),
    (DomainRule, ("cars", "Car"), frozenset()),
    (StreamRule, ("car/{object}/color", "Color", None, str, True), frozenset()),
    (Subscriber, ("a message", {"data": 1}), frozenset()),
    (Proposal, ("p1", "cheap", "a message"), frozenset()),
    (ContractNetResult, ([], {"p2": "no"}, [], {"p1": 1}, {}, ["p3"], [], []), frozenset()),
    (SecurityPolicy, (10.0, 64, 1000, 60.0, 5.0, False, True, 2, 4096), frozenset()),
    (_Pending, ("peer", b"transcript", b"secret", 1.5, 7), frozenset()),
    (SenderStats, (1, 2, 3), frozenset()),
    (PlatformStats, (*range(22), {"peer": SenderStats(1)}), frozenset()),
    (AgentStats, tuple(range(9)), frozenset()),
    (DfEventLimit, (1.0, 2.0, 3.0, 4.0, 5, 6.0), frozenset()),
    (KxLimit, (1.0, 2.0, 3.0, 4.0, 5, 6.0), frozenset()),
    (RateLimit, (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0), frozenset()),
]


def _frozen(cls: type) -> bool:
    return cls.__hash__ is not None and cls.__setattr__ is not object.__setattr__


def _reference(cls: type, uncompared: frozenset[str]) -> Any:
    """The dataclass the usual way: the fields of ``cls``, its frozenness, slots."""
    fields = [
        (f.name, Any, dataclasses.field(compare=f.name not in uncompared))
        for f in dataclasses.fields(cls)
    ]
    return dataclasses.make_dataclass(cls.__qualname__, fields, frozen=_frozen(cls), slots=True)


@pytest.mark.parametrize(("cls", "args", "uncompared"), CASES, ids=[c[0].__name__ for c in CASES])
def test_a_written_out_dataclass_behaves_as_a_generated_one(
    cls: type, args: tuple[Any, ...], uncompared: frozenset[str]
) -> None:
    ref_cls = _reference(cls, uncompared)
    ours, ref = cls(*args), ref_cls(*args)
    names = [f.name for f in dataclasses.fields(cls)]
    assert cls.__match_args__ == ref_cls.__match_args__ == tuple(names)
    assert dataclasses.is_dataclass(ours)
    assert not hasattr(ours, "__dict__")  # slotted (the two rules are since written out)
    assert repr(ours) == repr(ref)
    assert repr(dataclasses.asdict(ours)) == repr(dataclasses.asdict(ref))
    # keywords too, and every field read back
    by_name = cls(**dict(zip(names, args, strict=True)))
    assert [getattr(by_name, n) for n in names] == list(args)
    # equal to a copy, not to another class with the same fields, nor when a field differs
    assert ours == copy.deepcopy(ours) == dataclasses.replace(ours)
    assert ours != ref
    for n, value in zip(names, args, strict=True):
        other = dataclasses.replace(ours, **{n: _other(value)})
        assert (ours == other) is (n in uncompared), n
    assert pickle.loads(pickle.dumps(ours)) == ours
    if _frozen(cls):
        assert hash(ours) == hash(ref)
        for change in (lambda: setattr(ours, names[0], 1), lambda: delattr(ours, names[0])):
            with pytest.raises(dataclasses.FrozenInstanceError) as ours_error:
                change()
        with pytest.raises(dataclasses.FrozenInstanceError) as ref_error:
            setattr(ref, names[0], 1)
        assert str(ref_error.value) == f"cannot assign to field {names[0]!r}"
        assert ours_error.value.args == (f"cannot delete field {names[0]!r}",)
    else:
        with pytest.raises(TypeError, match="unhashable"):
            hash(ours)
        setattr(ours, names[0], _other(args[0]))
        assert getattr(ours, names[0]) == _other(args[0])


def _other(value: Any) -> Any:
    """A value unequal to ``value``."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int | float):
        return value + 1
    if isinstance(value, str | bytes):
        return value * 2 + value[:0]
    if isinstance(value, tuple | list):
        return type(value)([*value, value[0] if value else 0])
    if isinstance(value, dict):
        return {**value, "another": 0}
    return "something else"


def test_the_defaults_and_the_checks_at_construction_are_kept() -> None:
    # what the generated __init__ and __post_init__ did: defaults, fresh containers, checks
    assert SecurityPolicy().require_encryption is True
    assert SecurityPolicy(encrypt=False).require_encryption is False
    assert Atom("Car").args == () and Fact("Car").args == ()
    assert StreamRule("p", "Q") == StreamRule("p", "Q", None, None, False)
    assert Constant("blue") == Constant("blue", quoted=True)
    first, second = ContractNetResult(), ContractNetResult()
    first.proposals.append(Proposal("p", None, "m"))
    assert second.proposals == [] and PlatformStats().senders is not PlatformStats().senders
    assert AgentStats().received == 0 and RateLimit().rate == 5_000.0
    for bad in (
        lambda: SecurityPolicy(skew=0),
        lambda: KxLimit(detailed=-1),
        lambda: RateLimit(rate=-1.0),
        lambda: DfEventLimit(total=float("nan")),
        lambda: Constant(float("inf")),
    ):
        with pytest.raises(ValueError):
            bad()
    with pytest.raises(TypeError, match="not bool"):
        Constant(True)
    match Query(QueryKind.ANY, (_X,), Not(_CAR)):
        case Query(QueryKind.ANY, (Variable("x"),), Not(Atom("Car", _))):
            pass
        case _:
            pytest.fail("the nodes no longer match by position")
