"""Classes and links (anchoring): object classes whose membership follows MTL constraints.

An ``ObjectClass`` names a domain of identifiers, the features its instances have (label
patterns with ``{id}``) and four constraints, each an MTL formula over the features of one
instance (``create``, ``add``, ``maintain``) or of a pair (``codesignate``). A ``LinkType``
says when an instance of one class is the same entity as an instance of another
(``establish`` makes a new linked-to instance, ``reestablish`` links two existing ones,
``maintain`` removes a link, never the objects) and how the linked-to instance's features
are computed from the linked-from one's.

An ``Anchoring`` process samples every object's features on a period (the value at each
grid point, most recent sample) and progresses the constraints over these per-object
states. Each constraint is evaluated *from every state* (a new evaluation starts at each
step, as :class:`StepMonitor` does), and the period closes windows at once: so a
future-time formula decided now is a statement about the recent past.
``always[0,10] on_road`` becomes true at ``t`` when every state in ``[t-10, t]`` was on a
road; ``eventually[0,5] on_road`` becomes false at ``t`` when none in ``[t-5, t]`` was.

Rules, per step at time ``t``:

* links first, in definition order: ``maintain`` false → unlink; ``reestablish`` true for a
  free from/to pair → link; ``establish`` true for a free from-instance → a new
  to-instance (identifier from the DOM, joins the to-class, feature streams created) and a
  link; then each link's ``compute`` publishes the to-instance's features at ``t``;
* then classes, in definition order: members whose ``maintain`` became false leave (and
  leave every subclass and every link of a type naming the class); members of ``base``
  whose ``add`` became true join; pairs of members whose ``codesignate`` became true are
  fused (``once``: the second identifier leaves the class for good and its features fill
  the survivor's; ``continuous``: both stay, fused while the constraint holds and separated
  when it becomes false).

``create`` is evaluated on the samples of the class's ``create_from`` stream, whose values
map a percept key (a blob tracker's ``blob7``) to that percept's feature values; a key whose
``create`` became true gets an identifier, joins the class, and from then on its feature
values are published on the instance's feature streams.

Every change is published on the event stream (default ``events/anchoring``) as a dict
``{"event": joined|left|created|linked|unlinked|codesignated|separated, ...}``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Mapping, Sequence
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Self

from pydantic import ConfigDict, field_validator, model_validator

from .._exceptions import ObjectError, PolicyError, ProcessError, UnknownLabelError
from .._objects import ID_PLACEHOLDER, _check_identifier
from .._policy import CacheSpec, _EdgeModel, check_duration
from .._process import Process
from .._sample import RawSample
from .._stream import StreamGenerator, Subscription
from .._time import NS_PER_S, seconds_to_ns
from .mtl import MTLSyntaxError, Residual, compile_formula, progress
from .mtl import parse as parse_formula

if TYPE_CHECKING:
    from .._instance import DyKnowInstance

Features = dict[str, Any]
Compute = Callable[[Features], Mapping[str, Any] | None]
Relation = Callable[[Features, Features], Any]

# A formula with an unbounded window never decides; its evaluations would pile up.
_MAX_PENDING = 4096


class Codesignation(StrEnum):
    """How codesignated instances are fused: for good, or while the constraint holds."""

    ONCE = "once"
    CONTINUOUS = "continuous"


def _check_formula(text: str | None) -> str | None:
    if text is None:
        return None
    try:
        parse_formula(text)
    except MTLSyntaxError as exc:
        raise ValueError(f"bad formula: {exc}") from None
    return text


class ObjectClass(_EdgeModel):
    """A class of objects: its domain name, features and create/add/codesignate/maintain."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    name: str
    features: dict[str, str] = {}
    prefix: str | None = None
    base: str | None = None
    create: str | None = None
    create_from: str | None = None
    add: str | None = None
    maintain: str | None = None
    codesignate: str | None = None
    codesignation: Codesignation = Codesignation.ONCE
    relations: dict[str, Relation] = {}

    @field_validator("name", "prefix", "base")
    @classmethod
    def _ident(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                _check_identifier(v, "name")
            except ObjectError as exc:
                raise ValueError(str(exc)) from None
        return v

    @field_validator("features")
    @classmethod
    def _patterns(cls, v: dict[str, str]) -> dict[str, str]:
        for feature, pattern in v.items():
            if not feature.isidentifier():
                raise PolicyError(feature, "a feature name must be an identifier")
            if ID_PLACEHOLDER not in pattern:
                raise PolicyError(feature, f"label pattern {pattern!r} has no {ID_PLACEHOLDER}")
        return v

    @field_validator("create", "add", "maintain", "codesignate")
    @classmethod
    def _formula(cls, v: str | None) -> str | None:
        return _check_formula(v)

    @model_validator(mode="after")
    def _coherent(self) -> Self:
        if self.add is not None and self.base is None:
            raise PolicyError("add", "an add constraint needs a base class to draw candidates from")
        if (self.create is None) != (self.create_from is None):
            raise PolicyError("create_from", "give both create and create_from, or neither")
        if self.base == self.name:
            raise PolicyError("base", "a class cannot be its own base")
        return self

    @property
    def id_prefix(self) -> str:
        """The prefix of the identifiers this class issues (default: the name, lower case)."""
        return self.prefix or self.name.lower()


class LinkType(_EdgeModel):
    """A link type between two classes: establish / reestablish / maintain, and compute."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    name: str
    from_class: str
    to_class: str
    establish: str | None = None
    reestablish: str | None = None
    maintain: str | None = None
    compute: Compute | None = None

    @field_validator("name", "from_class", "to_class")
    @classmethod
    def _ident(cls, v: str) -> str:
        try:
            _check_identifier(v, "name")
        except ObjectError as exc:
            raise ValueError(str(exc)) from None
        return v

    @field_validator("establish", "reestablish", "maintain")
    @classmethod
    def _formula(cls, v: str | None) -> str | None:
        return _check_formula(v)

    @model_validator(mode="after")
    def _coherent(self) -> Self:
        if self.from_class == self.to_class:
            raise PolicyError("to_class", "a link joins two different classes")
        return self


class _Every:
    """Evaluates one formula from every state; the verdicts each step makes certain."""

    __slots__ = ("_fresh", "pending")

    def __init__(self, text: str) -> None:
        self._fresh = compile_formula(text)
        self.pending: list[tuple[float, bool | Residual]] = []

    def step(self, t: float, state: Mapping[str, Any], dt: float) -> list[tuple[float, bool]]:
        """Start an evaluation at ``t``, progress the pending ones; (start, verdict) decided."""
        out: list[tuple[float, bool]] = []
        keep: list[tuple[float, bool | Residual]] = []
        for start, n in [*self.pending, (t, self._fresh)]:
            r = progress(n, state, t, dt)
            if isinstance(r, bool):
                out.append((start, r))
            else:
                keep.append((start, r))
        self.pending = keep[-_MAX_PENDING:]
        return out


def _became(verdicts: list[tuple[float, bool]], value: bool) -> bool:
    return any(v is value for _, v in verdicts)


def _latest(verdicts: list[tuple[float, bool]]) -> bool | None:
    """The verdict of the latest start decided now: the freshest view of the recent past."""
    return max(verdicts)[1] if verdicts else None


class Anchoring(Process):
    """Keeps class domains, the object linkage structure and linked features current."""

    kind = "anchoring"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        classes: Sequence[ObjectClass],
        links: Sequence[LinkType],
        period: float,
        output: StreamGenerator,
    ) -> None:
        super().__init__(name, instance)
        self.classes = {c.name: c for c in classes}
        self.link_types = {lt.name: lt for lt in links}
        self.period = period
        self._period_ns = seconds_to_ns(period)
        self.output = output
        self.label = output.label
        self.steps = 0
        self.last_step: int | None = None
        # link type -> from id -> to id (one to-instance per from-instance and type)
        self.links: dict[str, dict[str, str]] = {lt.name: {} for lt in links}
        self._fused: dict[str, dict[str, str]] = {c.name: {} for c in classes}
        self._absorbed: dict[str, dict[str, str]] = {c.name: {} for c in classes}
        self._members: dict[str, set[str]] = {c.name: set() for c in classes}
        self._monitors: dict[tuple[str, ...], _Every] = {}
        self._keys: dict[str, dict[str, str]] = {c.name: {} for c in classes}
        self._owned: dict[str, StreamGenerator] = {}
        self._subscriptions: list[Subscription] = []

    # -- queries -----------------------------------------------------------------------
    def members(self, cls: str) -> frozenset[str]:
        """The identifiers in class ``cls`` now."""
        return self.instance.objects.domain(cls).members

    def linked(self, identifier: str) -> list[tuple[str, str, str]]:
        """The links involving ``identifier``: (link type, from id, to id)."""
        return [
            (lt, f, to)
            for lt, pairs in self.links.items()
            for f, to in pairs.items()
            if identifier in (f, to)
        ]

    def fused_with(self, cls: str, identifier: str) -> frozenset[str]:
        """The identifiers of ``cls`` fused with ``identifier`` (itself included)."""
        group = {identifier}
        for a, b in [*self._fused[cls].items(), *self._absorbed[cls].items()]:
            if identifier in (a, b):
                group |= {a, b}
        return frozenset(group)

    def features(self, cls: str, identifier: str, t: int | None = None) -> Features:
        """The features of ``identifier`` as an instance of ``cls`` at ``t`` (default: now).

        Fused identifiers are one entity: each feature is the value with the newest valid
        time among them.
        """
        when = self.instance.clock.now() if t is None else t
        out: Features = {}
        newest: dict[str, int] = {}
        for ident in sorted(self.fused_with(cls, identifier), key=lambda i: i != identifier):
            for feature, pattern in self._patterns(cls).items():
                s = self._value(pattern.replace(ID_PLACEHOLDER, ident), when)
                if s is not None and s[1] > newest.get(feature, -(2**63)):
                    out[feature] = s[0]
                    newest[feature] = s[1]
        for feature in self._patterns(cls):
            out.setdefault(feature, None)
        return out

    def _patterns(self, cls: str) -> dict[str, str]:
        c = self.classes[cls]
        inherited = self._patterns(c.base) if c.base in self.classes else {}
        return {**inherited, **c.features}

    def _value(self, label: str, t: int) -> tuple[Any, int] | None:
        if not self.instance.has_label(label):
            return None
        s = self.instance.at(label, t).latest
        return None if s is None else (s.value, s.valid_time)

    # -- events ------------------------------------------------------------------------
    def _event(self, t: int, **what: Any) -> None:
        gen = self.output
        if gen.closed:
            return
        gen.publish(what, t, max(self.instance.clock.now(), t, gen.last_available_time + 1))

    def _publish(self, label: str, value: Any, t: int) -> None:
        gen = self._owned.get(label)
        if gen is None:
            if self.instance.has_label(label):
                return  # someone else's stream: never write on it
            gen = self.instance.create_stream(label)
            self._owned[label] = gen
        if not gen.closed:
            gen.publish(value, t, max(self.instance.clock.now(), t, gen.last_available_time + 1))

    def _monitor(self, key: tuple[str, ...], text: str) -> _Every:
        m = self._monitors.get(key)
        if m is None:
            m = self._monitors[key] = _Every(text)
        return m

    def _drop_monitors(self, *prefix: str) -> None:
        n = len(prefix)
        for key in [k for k in self._monitors if k[:n] == prefix]:
            del self._monitors[key]

    # -- membership --------------------------------------------------------------------
    def join(self, cls: str, identifier: str, t: int) -> None:
        """Make ``identifier`` a member of ``cls`` at ``t`` and report it."""
        if self.instance.objects.domain(cls).add(identifier, time=t):
            self._members[cls].add(identifier)
            self._drop_monitors("add", cls, identifier)
            self._event(t, event="joined", **{"class": cls, "id": identifier})

    def leave(self, cls: str, identifier: str, t: int) -> None:
        """Make ``identifier`` leave ``cls`` (its subclasses and links naming it) at ``t``."""
        self.instance.objects.domain(cls).discard(identifier, time=t)
        if identifier not in self._members[cls]:
            return
        self._members[cls].discard(identifier)
        self._drop_monitors("maintain", cls, identifier)
        self._event(t, event="left", **{"class": cls, "id": identifier})
        for lt in self.link_types.values():
            if cls not in (lt.from_class, lt.to_class):
                continue
            for f, to in list(self.links[lt.name].items()):
                if identifier in (f, to):
                    self._unlink(lt.name, f, t)
        fused = self._fused[cls]
        for a, b in list(fused.items()):
            if identifier in (a, b):
                del fused[a]
                self._event(t, event="separated", **{"class": cls, "ids": [a, b]})
        for sub in self.classes.values():
            if sub.base == cls and identifier in self._members[sub.name]:
                self.leave(sub.name, identifier, t)

    def _sync_members(self, cls: str) -> None:
        """Follow membership changed by others (an application adding to the domain)."""
        now = self.instance.objects.domain(cls).members
        known = self._members[cls]
        for gone in known - now:
            self._drop_monitors("maintain", cls, gone)
        self._members[cls] = set(now)

    # -- links -------------------------------------------------------------------------
    def _link(self, lt: str, f: str, to: str, t: int) -> None:
        self.links[lt][f] = to
        self._event(t, event="linked", link=lt, **{"from": f, "to": to})

    def _unlink(self, lt: str, f: str, t: int) -> None:
        to = self.links[lt].pop(f)
        self._drop_monitors("link", lt, f)
        self._event(t, event="unlinked", link=lt, **{"from": f, "to": to})

    @staticmethod
    def _pair(a: Features, b: Features, relations: Mapping[str, Relation]) -> Features:
        state = {f"a_{k}": v for k, v in a.items()}
        state.update({f"b_{k}": v for k, v in b.items()})
        for name, fn in relations.items():
            state[name] = fn(a, b)
        return state

    def _step_links(self, t: int, ts: float, dt: float) -> None:
        for lt in self.link_types.values():
            pairs = self.links[lt.name]
            if lt.maintain is not None:
                for f, to in list(pairs.items()):
                    state = self._pair(
                        self.features(lt.from_class, f, t), self.features(lt.to_class, to, t), {}
                    )
                    m = self._monitor(("link", lt.name, f, to), lt.maintain)
                    if _became(m.step(ts, state, dt), False):
                        self._unlink(lt.name, f, t)
            free_from = sorted(self._members[lt.from_class] - pairs.keys())
            if lt.reestablish is not None:
                taken = set(pairs.values())
                for f in free_from:
                    a = self.features(lt.from_class, f, t)
                    for to in sorted(self._members[lt.to_class] - taken):
                        state = self._pair(a, self.features(lt.to_class, to, t), {})
                        m = self._monitor(("relink", lt.name, f, to), lt.reestablish)
                        if _became(m.step(ts, state, dt), True):
                            self._drop_monitors("relink", lt.name, f)
                            self._link(lt.name, f, to, t)
                            taken.add(to)
                            break
            if lt.establish is not None:
                for f in sorted(self._members[lt.from_class] - pairs.keys()):
                    state = self.features(lt.from_class, f, t)
                    m = self._monitor(("establish", lt.name, f), lt.establish)
                    if _became(m.step(ts, state, dt), True):
                        self._drop_monitors("establish", lt.name, f)
                        to = self.instance.objects.new_id(self.classes[lt.to_class].id_prefix)
                        # created, then joined: the order a created percept reports
                        self._event(t, event="created", **{"class": lt.to_class, "id": to})
                        self.join(lt.to_class, to, t)
                        self._link(lt.name, f, to, t)
            if lt.compute is not None:
                patterns = self._patterns(lt.to_class)
                for f, to in list(pairs.items()):
                    try:
                        values = lt.compute(self.features(lt.from_class, f, t))
                    except Exception as exc:  # one object's bad data must not stop the rest
                        self._fail(exc)
                        continue
                    for feature, value in (values or {}).items():
                        if feature in patterns and value is not None:
                            self._publish(patterns[feature].replace(ID_PLACEHOLDER, to), value, t)

    # -- classes -----------------------------------------------------------------------
    def _step_class(self, c: ObjectClass, t: int, ts: float, dt: float) -> None:
        self._sync_members(c.name)
        if c.maintain is not None:
            for ident in sorted(self._members[c.name]):
                m = self._monitor(("maintain", c.name, ident), c.maintain)
                if _became(m.step(ts, self.features(c.name, ident, t), dt), False):
                    self.leave(c.name, ident, t)
        if c.add is not None and c.base is not None:
            base = self.instance.objects.domain(c.base).members
            for ident in sorted(base - self._members[c.name]):
                m = self._monitor(("add", c.name, ident), c.add)
                if _became(m.step(ts, self.features(c.base, ident, t), dt), True):
                    self.join(c.name, ident, t)
        if c.codesignate is not None:
            self._step_codesignation(c, t, ts, dt)

    def _step_codesignation(self, c: ObjectClass, t: int, ts: float, dt: float) -> None:
        members = sorted(self._members[c.name])
        fused = self._fused[c.name]
        assert c.codesignate is not None
        for i, a in enumerate(members):
            for b in members[i + 1 :]:
                if a not in self._members[c.name] or b not in self._members[c.name]:
                    continue
                state = self._pair(
                    self.features(c.name, a, t), self.features(c.name, b, t), c.relations
                )
                m = self._monitor(("codesignate", c.name, a, b), c.codesignate)
                verdict = _latest(m.step(ts, state, dt))
                ids = {"class": c.name, "ids": [a, b]}
                if verdict is True and fused.get(a) != b:
                    if c.codesignation is Codesignation.ONCE:
                        self._absorbed[c.name][b] = a
                        self._event(t, event="codesignated", mode="once", **ids)
                        self.leave(c.name, b, t)
                    else:
                        fused[a] = b
                        self._event(t, event="codesignated", mode="continuous", **ids)
                elif verdict is False and fused.get(a) == b:
                    del fused[a]
                    self._event(t, event="separated", **ids)

    # -- creation ----------------------------------------------------------------------
    def _on_percepts(self, cls: str, batch: list[RawSample]) -> None:
        """Create instances for percepts whose create constraint became true; feed the rest."""
        if not self.running:
            return
        c = self.classes[cls]
        assert c.create is not None
        keys = self._keys[cls]
        patterns = self._patterns(cls)
        for value, tv, _ta in batch:
            if not isinstance(value, Mapping):
                self._fail(TypeError(f"{c.create_from}: expected a mapping key -> features"))
                continue
            ts = tv / NS_PER_S
            for key, feats in value.items():
                if not isinstance(feats, Mapping):
                    continue
                ident = keys.get(key)
                if ident is None:
                    m = self._monitor(("create", cls, str(key)), c.create)
                    if not _became(m.step(ts, feats, self.period), True):
                        continue
                    self._drop_monitors("create", cls, str(key))
                    ident = keys[key] = self.instance.objects.new_id(c.id_prefix)
                    self._event(tv, event="created", **{"class": cls, "id": ident, "key": key})
                    self.join(cls, ident, tv)
                for feature, v in feats.items():
                    if feature in patterns:
                        self._publish(patterns[feature].replace(ID_PLACEHOLDER, ident), v, tv)

    def _percepts_of(self, cls: str) -> Callable[[list[RawSample]], None]:
        return lambda batch: self._on_percepts(cls, batch)

    def identifier_of(self, cls: str, key: str) -> str | None:
        """The identifier created for percept ``key`` of ``cls``'s create_from stream."""
        return self._keys[cls].get(key)

    # -- running -----------------------------------------------------------------------
    def step(self, t: int | None = None) -> None:
        """Evaluate every link and class constraint on the states at ``t`` (default: now)."""
        if not self.running:
            return
        t = self.instance.clock.now() if t is None else t
        ts, dt = t / NS_PER_S, self.period
        try:
            self._step_links(t, ts, dt)
            for c in self.classes.values():
                self._step_class(c, t, ts, dt)
        except Exception as exc:
            self._fail(exc)
        self.steps += 1
        self.last_step = t

    async def _run(self) -> None:
        """Step on every grid point ``k · period`` of the instance clock."""
        clock = self.instance.clock
        p = self._period_ns
        due = -(-clock.now() // p) * p
        while self.running:
            # one yield per step, whatever the clock: a late anchoring catches up one grid
            # point per loop turn, so the producers feeding it keep their pace meanwhile
            if due > clock.now():
                await clock.sleep_until(due)
            else:
                await asyncio.sleep(0)
            if not self.running:
                break
            if due <= clock.now():
                self.step(due)
                due += p

    def _stop(self) -> None:
        super()._stop()
        for sub in self._subscriptions:
            sub.close()
        for label in list(self._owned):
            if self.instance.has_label(label):
                with contextlib.suppress(UnknownLabelError):  # removed by its user meanwhile
                    self.instance.remove_stream(label)
        self._owned.clear()

    def describe(self) -> dict[str, Any]:
        """Adds the classes, link types, members, links and step count to the description."""
        d = super().describe()
        d["output"] = self.label
        d["classes"] = {n: sorted(m) for n, m in self._members.items()}
        d["links"] = {n: dict(p) for n, p in self.links.items()}
        d["steps"] = self.steps
        return d


def _check_model(
    classes: Sequence[ObjectClass | Mapping[str, Any]],
    links: Sequence[LinkType | Mapping[str, Any]],
) -> tuple[list[ObjectClass], list[LinkType]]:
    cs = [ObjectClass.parse(c) for c in classes]
    ls = [LinkType.parse(x) for x in links]
    names: set[str] = set()
    for i, c in enumerate(cs):
        if c.name in names:
            raise PolicyError(f"classes.{i}.name", f"class {c.name!r} is defined twice")
        if c.base is not None and c.base not in names:
            raise PolicyError(f"classes.{i}.base", f"base class {c.base!r} must be defined before")
        names.add(c.name)
    seen: set[str] = set()
    for i, lt in enumerate(ls):
        if lt.name in seen:
            raise PolicyError(f"links.{i}.name", f"link type {lt.name!r} is defined twice")
        seen.add(lt.name)
        for field in ("from_class", "to_class"):
            if getattr(lt, field) not in names:
                raise PolicyError(f"links.{i}.{field}", f"unknown class {getattr(lt, field)!r}")
    return cs, ls


def add_anchoring(
    instance: DyKnowInstance,
    classes: Sequence[ObjectClass | Mapping[str, Any]],
    links: Sequence[LinkType | Mapping[str, Any]] = (),
    *,
    period: float = 1.0,
    output: str = "events/anchoring",
    name: str = "anchoring",
    cache: CacheSpec | None = None,
) -> Anchoring:
    """Add an anchoring process for ``classes`` and ``links``, stepping every ``period`` s.

    Each class's domain (named after it) is created unless it exists, with its membership
    published on ``domain/<class>``. Changes are published on ``output``.
    """
    try:
        period = check_duration("period", period, minimum=1e-6)
    except ValueError as exc:
        raise PolicyError("period", str(exc)) from None
    cs, ls = _check_model(classes, links)
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    for c in cs:
        if c.name not in instance.objects.domains():
            instance.objects.add_domain(c.name, publish=True)
    out = instance.create_stream(output, cache=cache, value_type=dict)
    proc = Anchoring(name, instance, cs, ls, period, out)
    try:
        for c in cs:
            if c.create_from is not None:
                proc._subscriptions.append(
                    instance.subscribe(c.create_from, callback=proc._percepts_of(c.name))
                )
        instance.add_process(proc)
    except Exception:
        proc._stop()
        instance.remove_stream(output)
        raise
    instance.spawn(f"anchoring[{name}]", proc._run())
    return proc


__all__ = [
    "Anchoring",
    "Codesignation",
    "LinkType",
    "ObjectClass",
    "add_anchoring",
]
