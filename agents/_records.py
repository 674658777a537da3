"""What the package's dataclasses share when their methods are written out.

A dataclass's generated ``__init__``, ``__repr__``, ``__eq__`` (and a frozen one's
``__setattr__``, ``__delattr__``, ``__hash__``) are compiled from source when its class
is made: ~0.2-0.7 ms a class of every process's start, and every node imports these. The
classes stay dataclasses (``@dataclass(init=False, repr=False, eq=False)``: `fields`,
`asdict` and `replace` work as ever) with their ``__init__`` written out; the rest, which
no message's path calls, comes from here, keyed by the fields in ``__match_args__``.
"""

from __future__ import annotations

from dataclasses import FrozenInstanceError


class Record:
    """A mutable dataclass's repr and equality (by its fields; unhashable, as one is)."""

    __slots__ = ()
    __match_args__: tuple[str, ...] = ()

    def _values(self) -> tuple[object, ...]:
        return tuple(getattr(self, n) for n in self.__match_args__)

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}={getattr(self, n)!r}" for n in self.__match_args__)
        return f"{type(self).__qualname__}({fields})"

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self._values() == other._values()

    __hash__ = None  # type: ignore[assignment]


class Frozen(Record):
    """A frozen dataclass's: no assignment, hashable by its fields, pickled by them."""

    __slots__ = ()

    def __setattr__(self, name: str, value: object) -> None:
        raise FrozenInstanceError(f"cannot assign to field {name!r}")

    def __delattr__(self, name: str) -> None:
        raise FrozenInstanceError(f"cannot delete field {name!r}")

    def __hash__(self) -> int:  # type: ignore[override]
        return hash(self._values())

    def __reduce__(self) -> tuple[type, tuple[object, ...]]:
        return type(self), self._values()
