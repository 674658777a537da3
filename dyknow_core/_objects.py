"""Objects: identifiers issued by the DOM, domains of identifiers, and set subscriptions.

An *object identifier* names an entity ("blob3", "car5"); the DOM (domain and object
manager) issues each identifier once. Several identifiers may denote the same entity
without the system knowing it: nothing here merges them. A *domain* is a dynamic set of
identifiers (the cars currently tracked); an identifier may be in several domains, and
a domain can be subscribed to. A *set subscription* is one stream of a feature
(``car/{id}/speed``) over all current members of a domain, following membership.
"""

from __future__ import annotations

import asyncio
import re
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Generic, NamedTuple, Protocol, Self, TypeVar

from ._exceptions import ClosedError, ObjectError, PolicyError
from ._policy import Overflow, Policy
from ._sample import Sample
from ._stream import StreamGenerator, Subscription
from ._time import Clock

if TYPE_CHECKING:
    from ._instance import DyKnowInstance

ID_PLACEHOLDER = "{id}"

# Identifiers are spliced into structured labels (car/{id}/speed) and label globs, so
# the characters that would change a label's structure or meaning are refused.
_IDENTIFIER = re.compile(r"[^\s/{}*?\[\]]+")

_T = TypeVar("_T")


def _check_identifier(identifier: str, what: str = "identifier") -> str:
    if not isinstance(identifier, str) or not _IDENTIFIER.fullmatch(identifier):
        raise ObjectError(
            f"{what} {identifier!r} is not valid: it must be a non-empty string without "
            "whitespace, '/', braces or glob characters"
        )
    return identifier


class MembershipChange(StrEnum):
    """Whether an identifier joined or left a domain."""

    ADDED = "added"
    REMOVED = "removed"


class DomainChange(NamedTuple):
    """One membership change of a domain: an identifier was added or removed at ``time``."""

    kind: MembershipChange
    identifier: str
    time: int
    domain: str


class DOM:
    """The domain and object manager's identifier registry: each identifier is assigned once."""

    __slots__ = ("_counters", "_issued")

    def __init__(self) -> None:
        self._issued: set[str] = set()
        self._counters: dict[str, int] = {}

    def new_id(self, prefix: str) -> str:
        """Issue a fresh identifier ``prefix`` + number (``car1``, ``car2``, …)."""
        _check_identifier(prefix, "identifier prefix")
        n = self._counters.get(prefix, 0)
        # Skip numbers taken by reserve() or by another prefix ("x1"+"1" == "x"+"11").
        while True:
            n += 1
            identifier = f"{prefix}{n}"
            if identifier not in self._issued:
                break
        self._counters[prefix] = n
        self._issued.add(identifier)
        return identifier

    def reserve(self, identifier: str) -> str:
        """Assign an explicit identifier (``car5``); ObjectError if it was assigned before."""
        _check_identifier(identifier)
        if identifier in self._issued:
            raise ObjectError(f"identifier {identifier!r} is already assigned")
        self._issued.add(identifier)
        return identifier

    def __contains__(self, identifier: object) -> bool:
        return identifier in self._issued

    def __len__(self) -> int:
        return len(self._issued)

    @property
    def issued(self) -> frozenset[str]:
        """Every identifier assigned so far."""
        return frozenset(self._issued)


class _Feed(Generic[_T]):
    """A bounded async-iterable buffer that never makes the producer wait.

    When full, ``overflow`` decides which item is lost and ``overflowed`` counts it.
    Iteration ends once the feed is closed and drained.
    """

    __slots__ = ("_buffer", "_overflow", "_size", "_waiter", "closed", "delivered", "overflowed")

    def __init__(self, buffer_size: int, overflow: Overflow) -> None:
        if buffer_size < 1:
            raise PolicyError("buffer_size", f"must be >= 1, got {buffer_size}")
        self._buffer: deque[_T] = deque()
        self._size = buffer_size
        self._overflow = Overflow(overflow)
        self._waiter: asyncio.Future[None] | None = None
        self.closed = False
        self.delivered = 0
        self.overflowed = 0

    def _put(self, items: list[_T]) -> None:
        if self.closed or not items:
            return
        self.delivered += len(items)
        buf = self._buffer
        size = self._size
        if self._overflow is Overflow.DROP_NEWEST:
            room = max(size - len(buf), 0)
            if len(items) > room:
                self.overflowed += len(items) - room
                items = items[:room]
            buf.extend(items)
        elif len(items) >= size:
            self.overflowed += len(buf) + len(items) - size
            buf.clear()
            buf.extend(items[len(items) - size :])
        else:
            buf.extend(items)
            for _ in range(len(buf) - size):
                buf.popleft()
                self.overflowed += 1
        self._wake()

    def _wake(self) -> None:
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def _end(self) -> None:
        self.closed = True
        self._wake()

    @property
    def buffered(self) -> int:
        """How many items wait to be consumed."""
        return len(self._buffer)

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> _T:
        while not self._buffer:
            if self.closed:
                raise StopAsyncIteration
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._buffer.popleft()

    async def get(self, timeout: float | None = None) -> _T:
        """The next item, or TimeoutError after ``timeout`` seconds, ClosedError at the end."""
        try:
            async with asyncio.timeout(timeout):
                return await self.__anext__()
        except StopAsyncIteration:
            raise ClosedError(f"{self!r} ended") from None

    def close(self) -> None:
        """Stop receiving; iteration ends once what was buffered is consumed."""
        self._end()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Listener(Protocol):
    """What a domain tells of its changes: domain and set subscriptions."""

    def _on_change(self, change: DomainChange) -> None: ...

    def close(self) -> None:
        """End the subscription."""


class DomainSubscription(_Feed[DomainChange]):
    """Membership changes of one domain as an async iterator of DomainChange events."""

    __slots__ = ("domain",)

    def __init__(self, domain: Domain, buffer_size: int, overflow: Overflow) -> None:
        super().__init__(buffer_size, overflow)
        self.domain = domain

    def close(self) -> None:
        """Stop receiving changes; iteration ends once what was buffered is consumed."""
        if not self.closed:
            self.domain._unlisten(self)
        self._end()

    def _on_change(self, change: DomainChange) -> None:
        self._put([change])

    def stats(self) -> dict[str, Any]:
        """A snapshot of this subscription's counters."""
        return {
            "domain": self.domain.name,
            "delivered": self.delivered,
            "overflowed": self.overflowed,
            "buffered": self.buffered,
        }

    def __repr__(self) -> str:
        return f"<DomainSubscription {self.domain.name!r}>"


class Domain:
    """A dynamic named set of object identifiers (the cars currently tracked).

    Members must be identifiers the DOM issued; an identifier may be in several
    domains. Every change is told to the domain's subscribers synchronously, and
    published on the domain's stream when it has one.
    """

    def __init__(
        self,
        name: str,
        dom: DOM,
        clock: Clock,
        generator: StreamGenerator | None = None,
    ) -> None:
        self.name = name
        self.generator = generator
        self.removed = False
        self._dom = dom
        self._clock = clock
        self._members: dict[str, int] = {}  # identifier -> time it joined, in join order
        self._listeners: list[_Listener] = []

    # -- membership -------------------------------------------------------------------
    def add(self, identifier: str, *, time: int | None = None) -> bool:
        """Make ``identifier`` a member (at ``time``, default now); False if it already was."""
        self._check_open()
        if identifier not in self._dom:
            raise ObjectError(f"identifier {identifier!r} was not issued by the DOM")
        if identifier in self._members:
            return False
        t = self._clock.now() if time is None else time
        self._members[identifier] = t
        self._changed(DomainChange(MembershipChange.ADDED, identifier, t, self.name))
        return True

    def remove(self, identifier: str, *, time: int | None = None) -> None:
        """Make ``identifier`` leave (at ``time``, default now); ObjectError if not a member."""
        if not self.discard(identifier, time=time):
            raise ObjectError(f"identifier {identifier!r} is not a member of domain {self.name!r}")

    def discard(self, identifier: str, *, time: int | None = None) -> bool:
        """Make ``identifier`` leave if it is a member; whether it was."""
        self._check_open()
        if self._members.pop(identifier, None) is None:
            return False
        t = self._clock.now() if time is None else time
        self._changed(DomainChange(MembershipChange.REMOVED, identifier, t, self.name))
        return True

    def _check_open(self) -> None:
        if self.removed:
            raise ObjectError(f"domain {self.name!r} was removed")

    def _changed(self, change: DomainChange) -> None:
        for listener in self._listeners:
            listener._on_change(change)
        # a closed stream (the instance is closing) stops recording; membership goes on
        if self.generator is not None and not self.generator.closed:
            self.generator.publish(change, change.time, self._clock.now())

    @property
    def members(self) -> frozenset[str]:
        """The identifiers in the domain now."""
        return frozenset(self._members)

    def joined(self, identifier: str) -> int:
        """When ``identifier`` joined the domain; ObjectError if it is not a member."""
        try:
            return self._members[identifier]
        except KeyError:
            raise ObjectError(
                f"identifier {identifier!r} is not a member of domain {self.name!r}"
            ) from None

    def __contains__(self, identifier: object) -> bool:
        return identifier in self._members

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._members))

    def __len__(self) -> int:
        return len(self._members)

    def __repr__(self) -> str:
        return f"<Domain {self.name!r} ({len(self._members)} members)>"

    # -- subscriptions ----------------------------------------------------------------
    def subscribe(
        self,
        *,
        initial: bool = False,
        buffer_size: int = 1024,
        overflow: Overflow = Overflow.DROP_OLDEST,
    ) -> DomainSubscription:
        """Subscribe to membership changes; ``initial`` first yields the current members."""
        self._check_open()
        sub = DomainSubscription(self, buffer_size, overflow)
        if initial:
            sub._put(
                [
                    DomainChange(MembershipChange.ADDED, i, t, self.name)
                    for i, t in self._members.items()
                ]
            )
        self._listen(sub)
        return sub

    def _listen(self, listener: _Listener) -> None:
        # copy-on-write: a listener may unsubscribe while changes are being told
        self._listeners = [*self._listeners, listener]

    def _unlisten(self, listener: _Listener) -> None:
        self._listeners = [x for x in self._listeners if x is not listener]

    def _end_subscriptions(self) -> None:
        for listener in self._listeners:
            listener.close()


# What a stream hands its callbacks: (value, valid_time, available_time) tuples, which
# may be plain tuples rather than Samples on the core's hot path.
_RawSample = tuple[Any, int, int]
_new_tuple: Any = tuple.__new__

SetCallback = Callable[[str, Sequence[_RawSample]], None]


def _as_sample(raw: _RawSample) -> Sample:
    return raw if type(raw) is Sample else _new_tuple(Sample, raw)


class SetSubscription(_Feed[tuple[str, Sample]]):
    """One stream of a feature over all current members of a domain, following membership.

    Each member's feature stream (``pattern`` with ``{id}`` replaced by the identifier)
    is subscribed with ``policy`` when the member joins, and unsubscribed when it
    leaves. A member whose stream does not exist yet is attached when the stream is
    created. Iterate for ``(identifier, Sample)`` pairs, or give a callback that
    receives ``(identifier, batch)`` synchronously, the batch's items being
    ``(value, valid_time, available_time)`` tuples as computational units get them.
    The buffer is bounded by the policy's ``buffer_size``/``overflow`` and never makes
    a publisher wait.
    """

    __slots__ = (
        "_callback",
        "_manager",
        "_members",
        "domain",
        "errors",
        "last_error",
        "pattern",
        "policy",
    )

    def __init__(
        self,
        manager: ObjectManager,
        domain: Domain,
        pattern: str,
        policy: Policy,
        callback: SetCallback | None,
    ) -> None:
        super().__init__(policy.buffer_size, policy.overflow)
        self._manager = manager
        self.domain = domain
        self.pattern = pattern
        self.policy = policy
        self._callback = callback
        # member label -> (identifier, its feature subscription, or None while waiting)
        self._members: dict[str, tuple[str, Subscription | None]] = {}
        self.errors = 0
        self.last_error: str | None = None

    def label_of(self, identifier: str) -> str:
        """The label of ``identifier``'s feature stream."""
        return self.pattern.replace(ID_PLACEHOLDER, identifier)

    # -- membership -------------------------------------------------------------------
    def _on_change(self, change: DomainChange) -> None:
        if change.kind is MembershipChange.ADDED:
            self._join(change.identifier)
        else:
            self._leave(change.identifier)

    def _join(self, identifier: str) -> None:
        label = self.label_of(identifier)
        self._members[label] = (identifier, None)
        self._attach(label)

    def _leave(self, identifier: str) -> None:
        entry = self._members.pop(self.label_of(identifier), None)
        if entry is not None and entry[1] is not None:
            entry[1].close()

    def _attach(self, label: str) -> None:
        """Subscribe to a member's feature stream if it exists and is not subscribed yet."""
        entry = self._members.get(label)
        if entry is None or self.closed:
            return
        identifier, sub = entry
        instance = self._manager.instance
        if not instance.has_label(label):
            return
        if sub is not None and (not sub.closed or sub.generator is instance.stream(label)):
            # live, or ended by its own policy on this very stream: do not replay it
            return
        try:
            sub = instance.subscribe(label, self.policy, callback=self._deliverer(identifier))
        except Exception as exc:  # one member's stream must not break the domain or the rest
            self.errors += 1
            self.last_error = f"{label}: {type(exc).__name__}: {exc}"
            instance._report_error(f"set-subscription[{self.domain.name}:{self.pattern}]", exc)
            return
        self._members[label] = (identifier, sub)

    def _deliverer(self, identifier: str) -> Callable[[Sequence[_RawSample]], None]:
        callback = self._callback
        if callback is not None:

            def call(batch: Sequence[_RawSample]) -> None:
                self.delivered += len(batch)
                callback(identifier, batch)

            return call

        def put(batch: Sequence[_RawSample]) -> None:
            self._put([(identifier, _as_sample(s)) for s in batch])

        return put

    def refresh(self) -> int:
        """Attach members whose feature stream now exists; how many are still waiting."""
        for label in list(self._members):
            self._attach(label)
        return len(self.waiting)

    # -- introspection ------------------------------------------------------------------
    @property
    def attached(self) -> list[str]:
        """Members whose feature stream is subscribed."""
        return [i for i, s in self._members.values() if s is not None and not s.closed]

    @property
    def waiting(self) -> list[str]:
        """Members whose feature stream does not exist (yet, or any more)."""
        return [i for i, s in self._members.values() if s is None or s.closed]

    def member_subscription(self, identifier: str) -> Subscription | None:
        """The live feature subscription of ``identifier``, if it has one."""
        entry = self._members.get(self.label_of(identifier))
        return entry[1] if entry is not None else None

    @property
    def dropped(self) -> int:
        """Samples this subscriber did not get: held back by the policy or lost to overflow."""
        return self.overflowed + sum(
            s.filter.stats.dropped for _, s in self._members.values() if s is not None
        )

    def stats(self) -> dict[str, Any]:
        """A snapshot of this set subscription's counters."""
        return {
            "domain": self.domain.name,
            "pattern": self.pattern,
            "members": len(self._members),
            "attached": len(self.attached),
            "waiting": len(self.waiting),
            "delivered": self.delivered,
            "overflowed": self.overflowed,
            "dropped": self.dropped,
            "buffered": self.buffered,
            "errors": self.errors,
        }

    # -- control --------------------------------------------------------------------------
    def replace_policy(self, policy: Policy) -> None:
        """Swap the policy of every member's feature subscription, and of members to come."""
        if self.closed:
            raise ClosedError(f"{self!r} is closed")
        for _, sub in self._members.values():
            if sub is not None and not sub.closed:
                sub.replace_policy(policy)
        self.policy = policy
        self._size = policy.buffer_size
        self._overflow = policy.overflow

    def close(self) -> None:
        """Unsubscribe from every member's stream; iteration ends once drained."""
        if not self.closed:
            self.domain._unlisten(self)
            self._manager._forget(self)
            for _, sub in self._members.values():
                if sub is not None:
                    sub.close()
            self._members.clear()
        self._end()

    def __repr__(self) -> str:
        return f"<SetSubscription {self.domain.name!r} {self.pattern!r}>"


class ObjectManager:
    """The DOM and the domains of one DyKnow instance (``instance.objects``).

    Issues identifiers, holds domains, and gives domain and set subscriptions. The
    instance tells it of every new label (``label_created``) so set subscriptions pick
    up member streams created after the member joined.
    """

    def __init__(self, instance: DyKnowInstance) -> None:
        self.instance = instance
        self.dom = DOM()
        self._domains: dict[str, Domain] = {}
        self._set_subs: list[SetSubscription] = []

    # -- identifiers ------------------------------------------------------------------------
    def new_id(self, prefix: str) -> str:
        """Issue a fresh identifier ``prefix`` + number (``car1``, ``car2``, …)."""
        return self.dom.new_id(prefix)

    def reserve(self, identifier: str) -> str:
        """Assign an explicit identifier; ObjectError if it was assigned before."""
        return self.dom.reserve(identifier)

    # -- domains ---------------------------------------------------------------------------------
    def add_domain(self, name: str, *, publish: bool | str = False) -> Domain:
        """Create a domain; ``publish`` also makes its changes a stream (label ``domain/<name>``).

        A string ``publish`` is the label to use. The stream's samples carry DomainChange
        values with the change's time as valid time, so membership history is cached and
        can be queried like any stream.
        """
        _check_identifier(name, "domain name")
        if name in self._domains:
            raise ObjectError(f"domain {name!r} exists already")
        generator = None
        if publish:
            label = publish if isinstance(publish, str) else f"domain/{name}"
            generator = self.instance.create_stream(label)
        domain = Domain(name, self.dom, self.instance.clock, generator)
        self._domains[name] = domain
        return domain

    def domain(self, name: str) -> Domain:
        """The domain called ``name``; ObjectError naming it when there is none."""
        try:
            return self._domains[name]
        except KeyError:
            known = ", ".join(sorted(self._domains)) or "none"
            raise ObjectError(f"unknown domain {name!r} (known domains: {known})") from None

    def domains(self) -> list[str]:
        """The names of all domains."""
        return sorted(self._domains)

    def domains_of(self, identifier: str) -> list[str]:
        """The names of the domains ``identifier`` is a member of."""
        return sorted(n for n, d in self._domains.items() if identifier in d)

    def remove_domain(self, name: str) -> None:
        """Remove a domain: its subscriptions end and its published stream is removed."""
        domain = self.domain(name)
        del self._domains[name]
        domain.removed = True
        domain._end_subscriptions()
        gen = domain.generator
        # only our own stream: the label may have been removed and published anew
        if gen is not None and not gen.closed and self.instance.has_label(gen.label):
            self.instance.remove_stream(gen.label)

    # -- subscriptions -------------------------------------------------------------------------
    def subscribe_domain(
        self,
        name: str,
        *,
        initial: bool = False,
        buffer_size: int = 1024,
        overflow: Overflow = Overflow.DROP_OLDEST,
    ) -> DomainSubscription:
        """Subscribe to the membership changes of domain ``name``."""
        return self.domain(name).subscribe(
            initial=initial, buffer_size=buffer_size, overflow=overflow
        )

    def subscribe_set(
        self,
        domain: str,
        pattern: str,
        policy: Policy | None = None,
        *,
        callback: SetCallback | None = None,
    ) -> SetSubscription:
        """One stream of feature ``pattern`` (``car/{id}/speed``) over all members of ``domain``."""
        if ID_PLACEHOLDER not in pattern:
            raise ObjectError(f"set subscription pattern {pattern!r} has no {ID_PLACEHOLDER}")
        dom = self.domain(domain)
        ss = SetSubscription(self, dom, pattern, policy or Policy(), callback)
        self._set_subs.append(ss)
        dom._listen(ss)
        for identifier in dom:
            ss._join(identifier)
        return ss

    @property
    def set_subscriptions(self) -> list[SetSubscription]:
        """The live set subscriptions."""
        return list(self._set_subs)

    def _forget(self, ss: SetSubscription) -> None:
        self._set_subs = [s for s in self._set_subs if s is not ss]

    # -- instance hooks ----------------------------------------------------------------------------
    def label_created(self, label: str) -> None:
        """Tell set subscriptions that a stream is now published under ``label``."""
        for ss in self._set_subs:
            if label in ss._members:
                ss._attach(label)

    def close(self) -> None:
        """End every domain and set subscription (the instance is closing)."""
        for domain in self._domains.values():
            domain._end_subscriptions()
